"""atheris target: the stimulus loader (rt_loop.measure.stimulus.load_stimulus)
on arbitrary CSV text and, with the first byte odd, arbitrary MF4 bytes.

The writable values are the plant inputs, as dct-hil serve --stimulus has
them. The loader must return a Stimulus or raise StimulusError of one line;
any other exception is a finding.

MF4 bytes go through the checks the loader makes in its own process
(check_mdf_identification); a file that passes them is not read here: the
loader reads it with asammdf in a child process (about 0.4 s, whose code no
coverage of this process sees, and whose crash is one line:
tests/test_fuzz_regressions.py), which would make the target blind and 50
times slower. The CSV side is read whole.
"""

from __future__ import annotations

import os

import _atheris

stimulus = None
writable = None
DIR = _atheris.scratch("stimulus")


def _import() -> None:
    global stimulus, writable
    from rt_loop._rt_loop import ffi
    from rt_loop.measure import stimulus as s
    stimulus = s
    writable = s.plant_inputs_writable(ffi)


def TestOneInput(data: bytes) -> None:
    if stimulus is None:
        _import()
    mdf = bool(data[:1]) and data[0] & 1
    path = os.path.join(DIR, "stim.mf4" if mdf else "stim.csv")
    with open(path, "wb") as f:
        f.write(data[1:])
    try:
        if mdf:
            stimulus.check_mdf_identification(path)
        else:
            stimulus.load_stimulus(path, writable)
    except stimulus.StimulusError as e:
        _atheris.one_line(e)


if __name__ == "__main__":
    _atheris.run(TestOneInput, _import)
