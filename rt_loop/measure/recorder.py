"""The measurement recorder: the loop's plant samples written to a CSV file.

Every ``record_every`` executed ticks the C loop copies the plant outputs
and the commands it applied into a ring of ``rt_sample`` (no allocation, no
lock); this thread drains the ring about 20 times per second and appends the
rows to a CSV file. The columns are those of ``dct-hil simulate`` (every
plant output, ``time_s`` first, in plant time), then ``maneuver_time_s``
(plant time since the scripted maneuver started, ``nan`` before), ``tick``
(the executed tick), ``fault_mask`` (the fault slots active in the tick, bit
k = slot k: ``rt_loop.faults``), and the received values the loop applied (the
mapping's inputs and recorded names, ``command_names``) that the outputs do
not already hold, as ``cmd_<name>`` (with the project's own contract among
them ``cmd_target_gear``, the TCU's TargetGear, which drives no input). Samples the loop could not put in the
ring because this thread fell behind are counted (``dropped``), never lost
silently. With ``fault_events`` set (a callable returning the fault starts
and ends not taken yet, ``FaultManager.take_events``), every start and end
goes into ``<recording>.faults.csv`` beside it: plant time, id, kind, target,
event.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from rt_loop.drain import RingDrain

__all__ = ["Recorder", "SampleLayout", "read_recording", "sample_layout"]

_BATCH = 1024


class SampleLayout(NamedTuple):
    """Where a recording's columns are in an ``rt_sample`` seen as doubles."""
    n_doubles: int                       # doubles in one rt_sample (tick first, as uint64)
    fields: dict                         # rt_sample's cffi fields by name
    outputs: list                        # dct_outputs names, time_s first
    base_o: int                          # index of the first output double
    base_c: int                          # index of the first command value
    fault_mask: int                      # index of the fault mask (uint64 bits)
    cmd_extra: list                      # (index in commands, name) of those no output holds
    columns: list                        # outputs, maneuver_time_s, tick, cmd_<name>...


def sample_layout(ffi: Any, command_names: list | tuple) -> SampleLayout:
    """The recording's columns and where they sit in a sample (every recorder's)."""
    outputs = [name for name, _ in ffi.typeof("dct_outputs").fields]
    sample = ffi.typeof("rt_sample")
    fields = dict(sample.fields)
    if ffi.sizeof(sample) % 8 or fields["tick"].offset != 0:
        raise TypeError("rt_sample must be a uint64 tick followed by doubles")
    cmd_extra = [(k, n) for k, n in enumerate(command_names) if n not in outputs]
    # column order: outputs (time_s first), maneuver_time_s, tick, fault_mask, cmd_*
    columns = (outputs + ["maneuver_time_s", "tick", "fault_mask"]
               + [f"cmd_{n}" for _, n in cmd_extra])
    return SampleLayout(ffi.sizeof(sample) // 8, fields, outputs, fields["outputs"].offset // 8,
                        fields["commands"].offset // 8, fields["fault_mask"].offset // 8,
                        cmd_extra, columns)


def faults_path(path: str | os.PathLike) -> str:
    """The fault events file beside a CSV recording."""
    base = os.fspath(path)
    stem = base[:-4] if base.lower().endswith(".csv") else base
    return f"{stem}.faults.csv"


class Recorder(RingDrain):
    """Drains the loop's ``rec`` ring into ``path`` (CSV) in a thread of its own."""

    ring, pop, entry, batch, poll_s, thread_name = (
        "rec", "rt_rec_pop_many", "rt_sample", _BATCH, 0.05, "recorder")

    def __init__(self, path: str | os.PathLike, command_names: list[str] | tuple = ()) -> None:
        super().__init__(path)
        self.command_names = list(command_names)
        self.fault_events: Any = None
        self._events_file: Any = None
        self.fault_events_written = 0
        folder = os.path.dirname(os.path.abspath(self.path))
        try:
            os.makedirs(folder, exist_ok=True)
            self._file = open(self.path, "w", encoding="ascii", newline="\n")
        except OSError as e:
            raise OSError(f"recording {self.path}: {e.strerror}") from None

    def start(self, ffi: Any, lib: Any, loop: Any) -> None:
        lay = sample_layout(ffi, self.command_names)
        outputs, base_o, base_c, cmd_extra = lay.outputs, lay.base_o, lay.base_c, lay.cmd_extra
        fields = lay.fields
        self._n_doubles = lay.n_doubles
        self.columns = lay.columns
        self._out_idx = np.arange(base_o, base_o + len(outputs))
        self._mt_idx = fields["maneuver_time_s"].offset // 8
        self._fm_idx = lay.fault_mask
        self._cmd_idx = np.array([base_c + k for k, _ in cmd_extra], dtype=int)
        # one printf-style format per row: the columns in file order
        self._cols = np.concatenate([self._out_idx, [self._mt_idx], self._cmd_idx]).astype(int)
        n_out = len(self._out_idx)
        self._fmt = ",".join(["%.9g"] * n_out + ["%.9g", "%d", "%d"]
                             + ["%.9g"] * len(self._cmd_idx))
        self._file.write(",".join(self.columns) + "\n")
        self._start(ffi, lib, loop)

    def _write(self, buf: Any, n: int) -> None:
        raw = np.frombuffer(self._ffi.buffer(buf, n * self._n_doubles * 8), dtype=np.float64)
        raw = raw.reshape(n, self._n_doubles)
        ticks = raw[:, 0].view(np.uint64).tolist()
        masks = np.ascontiguousarray(raw[:, self._fm_idx]).view(np.uint64).tolist()
        values = raw[:, self._cols]
        mt_col = len(self._out_idx)
        values[values[:, mt_col] < 0, mt_col] = np.nan     # before the maneuver started
        fmt = self._fmt
        n_head = mt_col + 1
        lines = [fmt % (*row[:n_head], tick, mask, *row[n_head:])
                 for row, tick, mask in zip(values.tolist(), ticks, masks)]
        self._file.write("\n".join(lines) + "\n")
        self._write_events()

    def _write_events(self) -> None:
        if self.fault_events is None:
            return
        events = self.fault_events()
        if not events:
            return
        if self._events_file is None:
            self._events_file = open(faults_path(self.path), "w", encoding="utf-8",
                                     newline="\n")
            self._events_file.write("time_s,id,kind,target,event\n")
        for e in events:
            target = str(e.get("target", "")).replace(",", ";")
            self._events_file.write(f"{e['time_s']:.9g},{e['id']},{e['kind']},{target},"
                                    f"{e['event']}\n")
        self.fault_events_written += len(events)

    def _close(self) -> None:
        try:
            self._write_events()
        finally:
            self._file.close()
            if self._events_file is not None:
                self._events_file.close()

def read_recording(path: str | os.PathLike) -> dict:
    """A recording (CSV, or the plant group of an MF4 recording) as {column:
    float array}; maneuver times before the start are NaN."""
    path = os.fspath(path)
    if path.lower().endswith((".mf4", ".mdf")):
        return _read_mf4(path)
    with open(path, encoding="ascii") as f:
        header = f.readline().strip().split(",")
    if not header or header[0] != "time_s":
        raise ValueError(f"{path}: not a dct-hil recording (no time_s column first)")
    data = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float,
                         missing_values="", filling_values=np.nan)
    data = np.atleast_2d(data)
    if data.size == 0:
        return {name: np.zeros(0) for name in header}
    return {name: data[:, k] for k, name in enumerate(header)}


def _read_mf4(path: str) -> dict:
    from asammdf import MDF

    with MDF(path) as mdf:
        for index, group in enumerate(mdf.groups):
            names = [ch.name for ch in group.channels]
            if "time_s" in names and "maneuver_time_s" in names:
                return {name: np.asarray(mdf.get(name, group=index).samples, dtype=float)
                        for name in names if name != "time"}
    raise ValueError(f"{path}: not a dct-hil recording (no plant group with time_s)")
