"""Stimulus files played into the running loop: plant inputs (and calibratable
values) over plant time, through the loop's ``stim`` ring of ``rt_write``.

``load_stimulus(path, writable)`` reads a CSV file (a ``time_s`` column,
then one column per channel) or an MDF file (``.mf4``/``.mdf``/``.dat``,
asammdf: the recorded channels, each on its own time base, e.g. a
recording of ``dct-hil serve --record run.mf4`` whose ``accel_pedal_pct``,
``brake_pedal_pct`` and ``road_grade_pct`` are played again) into a
``Stimulus``. ``writable`` is ``{name: (offset, size, lo, hi)}``: what may
be stimulated, the byte offset of its double in the ``rt_loop`` and its
range (``plant_inputs_writable(ffi)`` gives the plant inputs a stimulus
drives; ``writable_of_regions(calibration_regions(ffi, lib))`` the A2L's
writable CHARACTERISTICs, ``override.<input>`` and the online
``params.<name>``). The loop applies a write only inside a region declared
before ``rt_loop_prepare`` (``rt_loop.regions``): whoever sets up the loop
declares them. Every problem is a
``StimulusError`` of one line naming the file, the channel and the cause: an
unknown or unwritable channel, a value that is NaN, infinite or out of
range, a time that is negative, not a number or not increasing, a cell that
is not a number, a file that is empty or has no samples.

Each value holds from its sample's time until the next sample (zero-order
hold); a channel is written only when its value changes (and at its first
sample), so a step costs one write, whatever the sample rate of the file
(a recording that changes every sample costs one write per sample).

``StimulusPlayer(stimulus, ffi, lib, loop)`` queues the writes in a thread
of its own. Time base (``start``): ``"plant"`` (default): stimulus time 0 is
the plant time when the player starts (``t0_s`` to give it: 0 for a player
started before the loop, the run's start); ``"maneuver"``: stimulus time 0
is the start of the scripted maneuver (the player waits for it; with
``start_on_tcu`` the TCU's first frame). Each write carries its plant time
``t0 + t`` and the loop applies it at the first tick whose plant time before
the step has reached it (before the plant step of that tick). The player
keeps the writes of about ``lead_s`` (1 s) of plant time ahead queued,
reading the plant time from ``loop.stats.sim_time_s``, never more than the
ring has room for: the ring does not overflow (``dropped`` counts what the
ring refused all the same). A write queued when its time had already passed
(a player started late, a slow thread) is applied at the next tick and
counted in ``late``.

Inputs the loop itself sets each tick win over a stimulus of them: the
pedals while a driver table plays, and the inputs the mapping's received
CAN signals drive.
"""

from __future__ import annotations

import csv
import math
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Stimulus", "StimulusError", "StimulusPlayer", "load_stimulus",
           "plant_inputs_writable", "writable_of_regions", "PLANT_INPUT_RANGES"]

#: the plant inputs a stimulus may drive, with their ranges (the plant limits
#: pedals to 0..100 %, the grade to +-40 %; engine_on is 0 or 1)
PLANT_INPUT_RANGES = {
    "accel_pedal_pct": (0.0, 100.0),
    "brake_pedal_pct": (0.0, 100.0),
    "road_grade_pct": (-40.0, 40.0),
    "engine_on": (0.0, 1.0),
}
MDF_SUFFIXES = (".mf4", ".mdf", ".dat")
LEAD_S = 1.0                   # plant seconds of writes kept queued ahead
POLL_S = 0.05                  # wall seconds between the player's looks at the plant time
_VALUE_BYTES = 8               # a double, little endian


class StimulusError(ValueError):
    """A stimulus file that cannot be played: one line, naming the file."""


def plant_inputs_writable(ffi: Any) -> dict[str, tuple[int, int, float, float]]:
    """``{name: (offset, size, lo, hi)}`` of the plant inputs in ``PLANT_INPUT_RANGES``:
    byte offsets of ``rt_loop.plant.inputs.<name>``. The loop applies a write only
    inside a region Python declared before ``rt_loop_prepare`` (``rt_loop.regions``)."""
    base = ffi.offsetof("rt_loop", "plant") + ffi.offsetof("dct_plant", "inputs")
    return {name: (base + ffi.offsetof("dct_inputs", name), _VALUE_BYTES, lo, hi)
            for name, (lo, hi) in PLANT_INPUT_RANGES.items()}


def writable_of_regions(regions: list[tuple] | tuple) -> dict[str, tuple[int, int, float, float]]:
    """``{name: (offset, size, lo, hi)}`` of the single doubles among writable regions
    given as ``(offset, size, kind, name, lo, hi, c_type)`` (what
    ``rt_loop.measure.xcp.a2l.calibration_regions(ffi, lib)`` returns: ``override.<input>``,
    ``params.<name>``); blocks of several values are left out."""
    return {name: (int(offset), int(size), lo, hi)
            for offset, size, _kind, name, lo, hi, c_type in regions
            if int(size) == _VALUE_BYTES and c_type == "double"}


@dataclass(frozen=True)
class Stimulus:
    """A loaded stimulus: per channel its sample times (s, increasing, from 0 on)
    and values, and where each channel is written."""

    path: str
    channels: dict[str, tuple[np.ndarray, np.ndarray]]
    targets: dict[str, tuple[int, int, float, float]] = field(repr=False)

    @property
    def duration_s(self) -> float:
        """Time of the last sample of any channel."""
        return max(float(t[-1]) for t, _ in self.channels.values())

    def events(self) -> np.ndarray:
        """The writes, in time order: a structured array of (time_s, channel,
        offset, value), one per sample whose value differs from the sample
        before (and each channel's first); equal times in channel order."""
        parts = []
        for k, (name, (t, v)) in enumerate(self.channels.items()):
            keep = np.ones(len(v), dtype=bool)
            keep[1:] = v[1:] != v[:-1]
            e = np.zeros(int(keep.sum()), dtype=_EVENT)
            e["time_s"], e["value"] = t[keep], v[keep]
            e["channel"], e["offset"] = k, self.targets[name][0]
            parts.append(e)
        events = np.concatenate(parts) if parts else np.zeros(0, dtype=_EVENT)
        return events[np.lexsort((events["channel"], events["time_s"]))]


_EVENT = np.dtype([("time_s", "<f8"), ("channel", "<u4"), ("offset", "<u4"), ("value", "<f8")])


# --------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------

def load_stimulus(path: str | os.PathLike, writable: dict,
                  channels: list[str] | tuple | None = None) -> Stimulus:
    """Reads a CSV or MDF stimulus file; ``channels``: play only these (None: a
    CSV's every column, an MDF file's every channel that is ``writable``)."""
    path = os.fspath(path)
    suffix = os.path.splitext(path)[1].lower()
    if channels is not None:
        channels = list(channels)
        for name in channels:
            _check_writable(path, name, writable)
    if suffix in MDF_SUFFIXES:
        data = _load_mdf(path, writable, channels)
    elif suffix == ".csv" or suffix == ".txt":
        data = _load_csv(path, writable, channels)
    else:
        raise StimulusError(f"stimulus {path}: unknown format {suffix or '(no suffix)'!r}: "
                            f"a CSV file (.csv) or an MDF file ({', '.join(MDF_SUFFIXES)})")
    for name, (t, v) in data.items():
        _check_samples(path, name, t, v, writable[name])
    return Stimulus(path, data, {name: _target(writable[name]) for name in data})


def _target(entry: tuple) -> tuple[int, int, float, float]:
    offset, size, lo, hi = entry
    return (int(offset), int(size), -math.inf if lo is None else float(lo),
            math.inf if hi is None else float(hi))


def _check_writable(path: str, name: str, writable: dict) -> None:
    if name not in writable:
        known = ", ".join(sorted(writable)) or "nothing"
        raise StimulusError(f"stimulus {path}: channel {name!r} cannot be stimulated "
                            f"(writable: {known})")
    size = int(writable[name][1])
    if size != _VALUE_BYTES:
        raise StimulusError(f"stimulus {path}: channel {name!r} is {size} bytes: only doubles "
                            f"({_VALUE_BYTES} bytes) can be written")


def _check_samples(path: str, name: str, t: np.ndarray, v: np.ndarray, entry: tuple) -> None:
    where = f"stimulus {path}: channel {name!r}"
    if len(t) == 0:
        raise StimulusError(f"{where}: no samples")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise StimulusError(f"{where}: time {t[bad[0]]} at sample {bad[0] + 1} is not a number")
    if t[0] < 0:
        raise StimulusError(f"{where}: time {t[0]:g} s is negative (times start at 0 or later)")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise StimulusError(f"{where}: time not increasing at sample {i + 1}: "
                            f"{t[i]:.9g} s after {t[i - 1]:.9g} s")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        i = int(bad[0])
        raise StimulusError(f"{where}: value {v[i]} at {t[i]:.9g} s is not a finite number")
    _, _, lo, hi = _target(entry)
    out = np.flatnonzero((v < lo) | (v > hi))
    if out.size:
        i = int(out[0])
        raise StimulusError(f"{where}: value {v[i]:.9g} at {t[i]:.9g} s is out of its range "
                            f"{lo:g} .. {hi:g}")


def _load_csv(path: str, writable: dict, channels: list[str] | None) -> dict:
    try:
        with open(path, encoding="utf-8", newline="") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise StimulusError(f"stimulus {path}: cannot read it: {e.strerror}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise StimulusError(f"stimulus {path}: not a CSV text file ({_one_line(e)})") from None
    lines = [(n, row) for n, row in enumerate(rows, 1) if row and any(c.strip() for c in row)]
    if not lines:
        raise StimulusError(f"stimulus {path}: the file is empty")
    head_line, header = lines[0]
    header = [h.strip() for h in header]
    if "time_s" not in header:
        raise StimulusError(f"stimulus {path}: no time_s column in the header (line {head_line})")
    seen = set()
    for h in header:
        if not h:
            raise StimulusError(f"stimulus {path}: a column without a name (line {head_line})")
        if h in seen:
            raise StimulusError(f"stimulus {path}: channel {h!r}: the column appears twice")
        seen.add(h)
    names = [h for h in header if h != "time_s"]
    if channels is None:
        for h in names:
            _check_writable(path, h, writable)
        wanted = names
    else:
        for name in channels:
            if name not in names:
                raise StimulusError(f"stimulus {path}: channel {name!r}: no such column")
        wanted = channels
    if not wanted:
        raise StimulusError(f"stimulus {path}: no channel column besides time_s")
    if len(lines) < 2:
        raise StimulusError(f"stimulus {path}: no samples (only the header)")
    cols = {h: k for k, h in enumerate(header)}
    pick = [cols["time_s"]] + [cols[n] for n in wanted]
    out = np.empty((len(lines) - 1, len(pick)))
    for r, (line, row) in enumerate(lines[1:]):
        if len(row) != len(header):
            raise StimulusError(f"stimulus {path}: line {line} has {len(row)} cells, "
                                f"the header {len(header)}")
        for j, k in enumerate(pick):
            cell = row[k].strip()
            try:
                out[r, j] = float(cell)
            except ValueError:
                name = header[k]
                what = "time" if name == "time_s" else f"channel {name!r}"
                shown = repr(cell) if cell else "an empty cell"
                raise StimulusError(f"stimulus {path}: {what}: {shown} on line {line} "
                                    "is not a number") from None
    t = out[:, 0].copy()
    return {name: (t, out[:, 1 + j].copy()) for j, name in enumerate(wanted)}


def _load_mdf(path: str, writable: dict, channels: list[str] | None) -> dict:
    """The channels of an MDF stimulus, read in a child process: asammdf's C
    parts can crash the process on a malformed file (a 1.2 kB MF4 found by
    fuzz/stimulus_load.py segfaults asammdf 8.8), and the server must refuse
    such a file in one line, not die with it."""
    import importlib.util

    if importlib.util.find_spec("asammdf") is None:
        raise StimulusError(f"stimulus {path}: MDF files need the asammdf package "
                            "(pip install asammdf)")
    check_mdf_identification(path)
    import json
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory(prefix="dct-hil-stimulus-") as tmp:
        out = os.path.join(tmp, "channels.npz")
        args = json.dumps({"path": path, "writable": list(writable), "channels": channels, "out": out})
        code = "from rt_loop.measure.stimulus import _read_mdf_child; _read_mdf_child()"
        try:
            r = subprocess.run([sys.executable, "-c", code, args], capture_output=True, text=True,
                               timeout=600, check=False)
        except subprocess.TimeoutExpired:
            raise StimulusError(f"stimulus {path}: the MDF reader took over 600 s") from None
        if r.returncode == _CHILD_REFUSED:
            raise StimulusError(r.stderr.strip().splitlines()[-1])
        if r.returncode != 0:
            why = (f"signal {-r.returncode}" if r.returncode < 0
                   else _one_line(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode))
            raise StimulusError(f"stimulus {path}: not a readable MDF file (the MDF reader "
                                f"crashed on it: {why})")
        with np.load(out) as z:
            names = [str(n) for n in z["names"]]
            return {n: (z[f"t{k}"].copy(), z[f"v{k}"].copy()) for k, n in enumerate(names)}


def check_mdf_identification(path: str | os.PathLike) -> None:
    """Refuses in one line (StimulusError) a path that is no file, an empty one, or
    one that does not begin with an MDF identification block: read in the process,
    before any reader is started for it."""
    if not os.path.isfile(path):
        why = "no such file" if not os.path.exists(path) else "not a file"
        raise StimulusError(f"stimulus {path}: cannot read it: {why}")
    size = os.path.getsize(path)
    if size == 0:
        raise StimulusError(f"stimulus {path}: the file is empty")
    with open(path, "rb") as f:
        head = f.read(_MDF_ID_BYTES)
    if head[:8] not in _MDF_IDS:
        raise StimulusError(f"stimulus {path}: not an MDF file (it begins with {head[:8]!r}; "
                            "an MDF file with b'MDF     ')")
    if size < _MDF_ID_BYTES:
        raise StimulusError(f"stimulus {path}: not a readable MDF file ({size} bytes; its "
                            f"identification block alone is {_MDF_ID_BYTES})")


_CHILD_REFUSED = 3
_MDF_ID_BYTES = 64                               # the identification block of MDF 3 and 4
_MDF_IDS = (b"MDF     ", b"UnFinMF ")           # its file identifier (finalized or not)


def _read_mdf_child() -> None:
    """The child of ``_load_mdf``: reads the channels into an .npz; a refusal is its
    one line on stderr and exit status 3."""
    import json
    import sys

    a = json.loads(sys.argv[1])
    try:
        data = _read_mdf_channels(a["path"], a["writable"], a["channels"])
    except StimulusError as e:
        print(str(e), file=sys.stderr)
        sys.exit(_CHILD_REFUSED)
    arrays = {"names": np.array(list(data), dtype=str)}
    for k, (t, v) in enumerate(data.values()):
        arrays[f"t{k}"], arrays[f"v{k}"] = t, v
    np.savez(a["out"], **arrays)


def _read_mdf_channels(path: str, writable: list[str], channels: list[str] | None) -> dict:
    from asammdf import MDF

    try:
        mdf = MDF(path)
    except Exception as e:  # asammdf raises many kinds for a bad file
        raise StimulusError(f"stimulus {path}: not a readable MDF file "
                            f"({type(e).__name__}: {_one_line(e)})") from None
    try:
        present = [n for n in mdf.channels_db if n in writable]
        if channels is None:
            wanted = sorted(present, key=list(writable).index)
            if not wanted:
                known = ", ".join(sorted(writable)) or "nothing"
                raise StimulusError(f"stimulus {path}: no channel that can be stimulated "
                                    f"(writable: {known})")
        else:
            for name in channels:
                if name not in mdf.channels_db:
                    raise StimulusError(f"stimulus {path}: channel {name!r}: not in the file")
            wanted = channels
        out = {}
        for name in wanted:
            try:
                sig = mdf.get(name, raw=False)
            except Exception as e:
                raise StimulusError(f"stimulus {path}: channel {name!r}: cannot read it "
                                    f"({type(e).__name__}: {_one_line(e)})") from None
            samples = np.asarray(sig.samples)
            if samples.ndim != 1 or samples.dtype.kind not in "biuf":
                raise StimulusError(f"stimulus {path}: channel {name!r}: not numeric "
                                    f"({samples.dtype})")
            out[name] = (np.asarray(sig.timestamps, dtype=float).copy(),
                         samples.astype(float))
        return out
    finally:
        mdf.close()


def _one_line(e: Any) -> str:
    return " ".join(str(e).split())


# --------------------------------------------------------------------------
# playing
# --------------------------------------------------------------------------

class StimulusPlayer:
    """Queues a ``Stimulus``'s writes into ``loop.stim`` in a thread of its own
    (see the module's docstring). ``start()``, ``stop()``, ``wait()``,
    ``counters()``."""

    def __init__(self, stimulus: Stimulus, ffi: Any, lib: Any, loop: Any,
                 start: str = "plant", t0_s: float | None = None,
                 lead_s: float = LEAD_S, poll_s: float = POLL_S) -> None:
        if start not in ("plant", "maneuver"):
            raise ValueError(f"start must be 'plant' or 'maneuver', got {start!r}")
        if not hasattr(lib, "rt_write_push_many"):
            raise RuntimeError("the loop has no stimulus ring (rt_write_push_many): "
                               "rebuild it (scripts/setup)")
        self.stimulus = stimulus
        self.start_mode = start
        self.lead_s = float(lead_s)
        self.poll_s = float(poll_s)
        self._ffi, self._lib = ffi, lib
        self._owner = loop                    # keeps the loop's memory alive
        self._loop = loop[0] if ffi.typeof(loop).kind == "pointer" else loop
        self._ring = ffi.addressof(self._loop, "stim")
        self._size = int(lib.RT_WRITE_RING_SIZE)
        self._events = stimulus.events()
        self._next = 0
        self.t0_s = None if t0_s is None else float(t0_s)
        self.queued = 0
        self.late = 0
        self.error: str | None = None
        self._base = (int(self._ring.applied), int(self._ring.refused))
        self._id0 = int(self._ring.last_applied_id)     # ids continue after earlier players
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        w = ffi.typeof("rt_write")
        fields = dict(w.fields)
        if ffi.sizeof(fields["data"].type) < _VALUE_BYTES:
            raise TypeError("rt_write.data holds fewer than 8 bytes")
        self._batch = min(1024, self._size)
        self._buf = ffi.new("rt_write[]", self._batch)
        self._view = np.frombuffer(ffi.buffer(self._buf), dtype=np.dtype({
            "names": ["time_s", "offset", "len", "id", "value"],
            "formats": ["<f8", "<u4", "<u4", "<u8", "<f8"],
            "offsets": [fields["time_s"].offset, fields["offset"].offset, fields["len"].offset,
                        fields["id"].offset, fields["data"].offset],
            "itemsize": ffi.sizeof(w)}))

    # ------------------------------------------------------------ life cycle
    def start(self) -> StimulusPlayer:
        if self._thread is not None:
            raise RuntimeError("the player was already started")
        if self.start_mode == "plant" and self.t0_s is None:
            self.t0_s = float(self._loop.stats.sim_time_s)
        self._thread = threading.Thread(target=self._run, name="stimulus", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stops queuing; writes already queued stay and are applied in time."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    @property
    def done(self) -> bool:
        """Every write was queued and the loop applied or refused it."""
        return self._next == len(self._events) and self.applied + self.refused >= self.queued

    def wait(self, timeout: float | None = None) -> bool:
        """Waits until ``done`` (or the player stopped); False on the timeout."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self.done:
            if self._thread is None or (not self._thread.is_alive() and
                                        self._next < len(self._events)):
                return False
            if end is not None and time.monotonic() >= end:
                return False
            self._stop.wait(min(self.poll_s, 0.01))
        return True

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        lib, loop = self._lib, self._loop
        try:
            while not self._stop.is_set() and self._next < len(self._events):
                state = int(loop.stats.state)
                if state not in (lib.RT_STATE_IDLE, lib.RT_STATE_RUNNING):
                    break                             # the loop ended
                if self.t0_s is None:
                    self._find_maneuver_start()
                if self.t0_s is not None:
                    self._queue(float(loop.stats.sim_time_s))
                self._stop.wait(self.poll_s)
        except Exception as e:  # reported by counters()
            self.error = f"stimulus {self.stimulus.path}: {type(e).__name__}: {_one_line(e)}"

    def _find_maneuver_start(self) -> None:
        s = self._ffi.new("rt_stats *")
        if self._lib.rt_stats_read(self._ffi.addressof(self._loop), s) != 0:
            return
        if s.maneuver_state >= self._lib.RT_MANEUVER_RUNNING and s.maneuver_time_s >= 0:
            self.t0_s = float(s.sim_time_s) - float(s.maneuver_time_s)

    def _queue(self, now_s: float) -> None:
        """Queues the writes due up to ``now_s + lead_s``, as many as the ring holds."""
        ev, t0 = self._events, self.t0_s
        horizon = now_s + self.lead_s - t0
        end = int(np.searchsorted(ev["time_s"], horizon, side="right"))
        ring = self._ring
        while self._next < end:
            free = self._size - ((int(ring.head) - int(ring.tail)) & 0xFFFFFFFF)
            n = min(end - self._next, free, self._batch)
            if n <= 0:
                return
            part = ev[self._next:self._next + n]
            v = self._view[:n]
            v["time_s"] = t0 + part["time_s"]
            v["offset"] = part["offset"]
            v["len"] = _VALUE_BYTES
            v["id"] = self._id0 + np.arange(self._next + 1, self._next + n + 1, dtype=np.uint64)
            v["value"] = part["value"]
            k = int(self._lib.rt_write_push_many(ring, self._buf, n))
            self.late += int(np.count_nonzero(v["time_s"][:k] < now_s))
            self._next += k
            self.queued += k
            if k < n:
                return

    # ------------------------------------------------------------ counts
    @property
    def applied(self) -> int:
        return int(self._ring.applied) - self._base[0]

    @property
    def refused(self) -> int:
        return int(self._ring.refused) - self._base[1]

    @property
    def dropped(self) -> int:
        """Writes the ring refused because it was full (counted by the ring)."""
        return int(self._ring.dropped)

    def counters(self) -> dict:
        return {"path": self.stimulus.path, "start": self.start_mode, "t0_s": self.t0_s,
                "writes": len(self._events), "queued": self.queued, "late": self.late,
                "applied": self.applied, "refused": self.refused, "dropped": self.dropped,
                "error": self.error}
