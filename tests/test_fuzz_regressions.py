"""What the coverage-guided fuzzers found (scripts/fuzz-coverage), each kept as
a regression: the saved input (fuzz/regressions/<target>/) fed again through
the same entry, and where the entry is reachable from Python, the case
written out through the project's own extension.

C targets: the input runs through the libFuzzer binary of its target, built
with clang into build/fuzz/ (AddressSanitizer, UBSan): exit status 0, no
report. Python targets: the target's TestOneInput, which raises on anything
but the loader's one-line error.
"""

import errno
import importlib
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import requires

from rt_loop.tools import fuzz_coverage as fc

REGRESSIONS = fc.FUZZ / "regressions"


def _inputs(kinds):
    out = []
    for target in kinds:
        d = REGRESSIONS / target
        if d.is_dir():
            out += [pytest.param(target, p, id=f"{target}/{p.name}") for p in sorted(d.iterdir())]
    return out


@pytest.mark.parametrize("target,path", _inputs(fc.C_TARGETS))
def test_c_finding_stays_fixed(target, path):
    if not any(shutil.which(c) for c in ("clang", "clang-14", "clang-15", "clang-16")):
        pytest.skip("clang missing (scripts/fuzz-coverage installs it)")
    binary = fc.build([target])[target]
    r = subprocess.run([str(binary), str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]


@pytest.mark.parametrize("target,path", _inputs(fc.PY_TARGETS))
def test_python_finding_stays_fixed(target, path):
    sys.path.insert(0, str(fc.FUZZ))
    try:
        mod = importlib.import_module(target)
    finally:
        sys.path.remove(str(fc.FUZZ))
    mod.TestOneInput(path.read_bytes())


def test_mapping_that_is_not_utf8_is_one_line_error(tmp_path):
    from can_dbc.mapping import MappingError, load
    p = tmp_path / "m.toml"
    p.write_bytes(b"\xc1[[bus]]\n")
    with pytest.raises(MappingError, match="not UTF-8 text") as e:
        load(p)
    assert "\n" not in str(e.value)


# ---- rt_loop_prepare refuses codec tables the builder would never lay out
from test_rt_loop_channels import Loop, Rig, rig_dir  # noqa: F401  (the rig and its fixture)


def _first_message(loop, pred=lambda m: m.n_signals >= 2):
    ch = loop.c.chan[0]
    for m in range(ch.table.n_messages):
        if pred(ch.table.messages[m]):
            return ch, ch.table.messages[m]
    raise AssertionError("no such message")


def _break_counter(loop):        # the finding: a counter index outside its message
    ch, m = _first_message(loop)
    m.counter_signal = m.n_signals


def _break_first_signal(loop):   # signals of a message elsewhere than after the previous one's
    ch = loop.c.chan[0]
    ch.table.messages[ch.table.n_messages - 1].first_signal += 1


def _break_raw_range(loop):      # an integer field whose raw range is not its bits'
    ch, m = _first_message(loop)
    ch.table.signals[m.first_signal].raw_min = math.nan


def _break_start(loop):          # a signal ending beyond its frame
    ch, m = _first_message(loop)
    ch.table.signals[m.first_signal].start = 8 * m.length


def _break_mux(loop):            # a multiplexer index outside the message
    ch, m = _first_message(loop)
    ch.table.signals[m.first_signal].mux_signal = m.n_signals


@pytest.mark.parametrize("brk", [_break_counter, _break_first_signal, _break_raw_range, _break_start,
                                 _break_mux], ids=lambda f: f.__name__[7:])
def test_prepare_refuses_codec_tables_outside_the_builders_layout(rig_dir, brk):  # noqa: F811
    loop = Loop(Rig(rig_dir / "rig.toml").channels)
    brk(loop)
    assert loop.prepare() == -errno.EINVAL
    assert loop.stats().n_channels == 0
    fresh = Loop(Rig(rig_dir / "rig.toml").channels)
    assert fresh.prepare() == 0


def test_regression_inputs_are_small():
    for p in REGRESSIONS.rglob("*"):
        if p.is_file():
            assert p.stat().st_size < 65536, p
    assert Path(os.path.relpath(REGRESSIONS, fc.ROOT)) == Path("fuzz/regressions")


def test_an_mdf_stimulus_that_crashes_the_reader_is_one_line_error(tmp_path):
    """asammdf 8.8 segfaults on this 1.2 kB MF4 (found by fuzz/stimulus_load.py): the
    stimulus is read in a child process, so serve refuses it in one line and lives."""
    requires.module("asammdf")
    from rt_loop._rt_loop import ffi
    from rt_loop.measure import stimulus

    data = (REGRESSIONS / "stimulus_load" / "mdf-reader-segfault").read_bytes()
    path = tmp_path / "stim.mf4"
    path.write_bytes(data[1:])                       # the target's first byte picks MF4
    with pytest.raises(stimulus.StimulusError) as e:
        stimulus.load_stimulus(str(path), stimulus.plant_inputs_writable(ffi))
    assert str(e.value).startswith(f"stimulus {path}: not a readable MDF file") and "\n" not in str(e.value)
