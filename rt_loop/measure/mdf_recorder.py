"""The measurement recorder in ASAM MDF 4: plant samples and CAN traffic in one .mf4 file.

``MdfRecorder`` has the interface of ``rt_loop.measure.recorder.Recorder`` (a
``RingDrain`` over the loop's ``rec`` ring: ``start(ffi, lib, loop)``,
``stop()``, ``counters()``, ``written``, ``dropped``) and writes an MDF 4.10
file (asammdf reads it; so do the usual MDF tools) instead of a CSV:

- channel group ``plant``: master ``time`` = the plant time after the step
  (the CSV's ``time_s``), then the CSV's columns in its order: every plant
  output (unit from its name's suffix, ``can_dbc.mapping.unit_of_name``;
  comment from ``plant/csrc/dct_plant.h``), ``maneuver_time_s`` (NaN before
  the maneuver started), ``tick`` (uint64), and the ``cmd_<name>`` received
  values the loop applied that the outputs do not already hold. The values
  are the doubles the loop recorded (the CSV rounds them to 9 digits).
- CAN traffic as ASAM MDF bus logging: channel groups ``CAN_DataFrame``,
  ``CAN_RemoteFrame`` and ``CAN_ErrorFrame`` (the structures asammdf and
  python-can's MF4 reader read back, and that ``MDF.extract_bus_logging``
  decodes with a DBC), ``BusChannel`` = index of the loop's bus + 1 (0 means
  "any" to asammdf), ``Dir`` 0 received / 1 sent, ``DataBytes`` 64 bytes
  (zeros past ``DataLength``). Their master ``time`` is the loop time of the
  tick that received or sent the frame (its deadline since the loop
  started) times the time scale (step_s / period_s): the plant time at the
  start of that tick as long as no tick was skipped (a skipped tick, an
  overrun, makes the run INVALID anyway). The plant samples are taken after
  the step: a frame sent in the tick of a sample has a time one step less.

Where the frames come from: the loop's ``log`` ring has one reader. When
the server runs a traffic log (``TrafficLogger``) that one drains the ring
and hands each batch to ``add_frames(buf, n)`` as well; without one, the
recorder drains the ``log`` ring itself (``start(..., drain_log=True)``;
the loop's ``cfg.log_frames`` must be 1 in both cases).

Streaming. asammdf cannot append to an MDF file on disk (``MDF.append`` /
``extend`` fill a temporary file and ``save`` writes the whole file at the
end), so asammdf writes the file's metadata (every block up to the data
groups, from zero-sample signals) and this module appends the data itself,
with asammdf's block classes: every ``flush_s`` (1 s of wall time, or
``_MAX_PENDING_BYTES`` of records earlier) each group that got records gets
one DZ block (transposed deflate) and one DL block linking it; the first DL
of a group hangs under an HL block that the data group points to, each
later DL is chained to the one before. Only after the new blocks are in the
file does one 8-byte write raise the channel group's cycle count and a
second one link the blocks in. So after every flush the file on disk is a
complete, finalized MDF 4.10 file with every record flushed so far; a
process killed at any moment (SIGKILL, a crash) leaves a file asammdf opens
up to the last flushed block (killed between the two 8-byte writes: the
count is ahead of the blocks, and asammdf reads the records the blocks
hold; the other order, blocks beyond the count, asammdf refuses to read).
Nothing is kept in memory beyond the records of one flush, in a buffer per
group that is kept and reused (``_Pending``: no batch allocates). The writes are
not fsync'ed per block (only at ``stop()``): after a power cut the file
system may not have kept their order. A copy taken while the recorder runs
(``cp``) is read front to back over time: one that spans a flush can hold
the count from before it and a link from after it, which asammdf refuses;
copy between flushes (a flush takes a few milliseconds every ``flush_s``;
``blocks`` counts the finished ones) and check that ``blocks`` did not move. ``stop()`` writes what is left in the
rings and closes the file: there is no finalisation step to miss.

Size, measured on the demo's paper-cycle (65 s, 2 ms samples of 69
columns, 2435 CAN frames per second both ways) replayed through this
recorder in 1 s blocks: 168 bytes per sample (552 raw) and 6 bytes per
frame (84 raw), 356 MB per hour for both, against 864 MB per hour of the
CSV (480 bytes per sample) and 491 MB of the candump log. Compressing a
second's blocks takes about 3 ms.
"""

from __future__ import annotations

import ctypes
import datetime as _dt
import io
import os
import re
import struct
import threading
import time
from typing import Any

import numpy as np

import plant
from can_dbc.mapping import unit_of_name
from rt_loop.drain import RingDrain, one_line
from rt_loop.measure.recorder import sample_layout

__all__ = ["MdfRecorder", "MDF_VERSION", "fixed_mmap_threshold", "output_comments"]

MDF_VERSION = "4.10"
FLUSH_S = 1.0                           # wall-clock seconds between blocks
_BATCH = 1024                           # rt_sample per pop
_LOG_BATCH = 4096                       # rt_log_entry per pop
_MAX_PENDING_BYTES = 16 * 1024 * 1024   # flush earlier than flush_s beyond this
_DATA_BYTES = 64                        # CAN_DataFrame.DataBytes: CAN FD's 64 bytes
#: glibc's M_MMAP_THRESHOLD (malloc.h) and the value the recorder fixes it at: its
#: default, 128 kB, which glibc raises to the size of every mapped block freed (up
#: to 32 MB); see ``fixed_mmap_threshold``
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 128 * 1024

_CAN_EFF_FLAG = 0x80000000
_CAN_RTR_FLAG = 0x40000000
_CAN_ERR_FLAG = 0x20000000
_CAN_ID_MASK = 0x1FFFFFFF
_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)

# the bus logging structures (ASAM MDF bus logging, as python-can's MF4 writer and
# asammdf's extract_bus_logging know them)
_FRAME_FIELDS = [("BusChannel", "<u1"), ("ID", "<u4"), ("IDE", "<u1"), ("DLC", "<u1"),
                 ("DataLength", "<u1"), ("DataBytes", f"({_DATA_BYTES},)u1"), ("Dir", "<u1"),
                 ("EDL", "<u1"), ("BRS", "<u1"), ("ESI", "<u1")]
_REMOTE_FIELDS = [("BusChannel", "<u1"), ("ID", "<u4"), ("IDE", "<u1"), ("DLC", "<u1"),
                  ("DataLength", "<u1"), ("Dir", "<u1")]
_BUS_GROUPS = (("CAN_DataFrame", _FRAME_FIELDS), ("CAN_RemoteFrame", _REMOTE_FIELDS),
               ("CAN_ErrorFrame", _FRAME_FIELDS))

_HEADER = os.path.join(os.path.dirname(os.path.abspath(plant.__file__)), "csrc", "dct_plant.h")


def fixed_mmap_threshold() -> bool:
    """Keeps glibc's malloc from taking the recorder's blocks into its heap: every
    second the recorder allocates and frees buffers of 0.1-1 MB (a batch of samples,
    the records joined, the transposed and compressed block). glibc maps blocks above
    its threshold on their own, and raises the threshold to the size of each mapped
    block freed, so from the first block on these come from the heap, between
    smaller blocks that outlive them: the heap's free space grows in steps and, under
    mlockall, stays resident (in a soak, RSS rose by 4.6 MB in 6.5 minutes while
    malloc's bytes in use stayed at 30 MB and its free bytes rose from 0.6 to 4.3). Set explicitly, the threshold stays put: these blocks are
    mapped and unmapped again. Process-wide, as every malloc setting; False when not
    glibc."""
    try:
        return bool(ctypes.CDLL(None).mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    except (OSError, AttributeError):
        return False


def _asammdf() -> Any:
    try:
        import asammdf  # optional: only MF4 recordings need it
    except ImportError as e:
        raise ImportError(f"MF4 recordings need the asammdf package ({one_line(e)}); "
                          "pip install asammdf") from None
    return asammdf


def output_comments(header: str = _HEADER) -> dict[str, str]:
    """{output: comment} from the ``dct_outputs`` struct of ``dct_plant.h`` (the
    comment after each field, continued on the lines below it), {} when the
    header is not there."""
    try:
        with open(header, encoding="utf-8") as f:
            text = f.read()
    except OSError:
        return {}
    m = re.search(r"typedef struct \{(?P<body>(?:(?!typedef).)*?)\}\s*dct_outputs;", text, re.S)
    if not m:
        return {}
    out = {}
    for f_m in re.finditer(r"double\s+(\w+);[ \t]*(/\*.*?\*/)?", m.group("body"), re.S):
        if f_m.group(2):
            out[f_m.group(1)] = " ".join(f_m.group(2)[2:-2].split())
    return out


# --------------------------------------------------------------------------
# the file: asammdf writes the metadata, the data blocks are appended here
# --------------------------------------------------------------------------

class _Group:
    """One channel group being appended to."""

    def __init__(self, name: str, dtype: np.dtype, dg_addr: int, cg_addr: int,
                 cycles_at: int) -> None:
        self.name = name
        self.dtype = dtype            # one record: master time first
        self.dg_addr = dg_addr
        self.cg_addr = cg_addr
        self.cycles_at = cycles_at    # file offset of the CG's cycle count
        self.cycles = 0
        self.stream_bytes = 0         # bytes of records so far (the DL offsets)
        self.last_dl = 0              # address of the last DL of the chain (0: none yet)
        self.stored = 0               # bytes of its data blocks in the file (DZ, DL, HL)
        self.pending = _Pending()


#: the smallest buffer a group's records wait in: above the mmap threshold the recorder
#: fixes (``fixed_mmap_threshold``), so glibc maps it on its own, never in its heap
_PENDING_MIN_BYTES = 2 * MMAP_THRESHOLD_BYTES


class _Pending:
    """A group's records waiting for the next flush, in one buffer kept from flush
    to flush. It grows to the largest flush seen and never shrinks, from
    ``_PENDING_MIN_BYTES`` on: a batch of records is copied in, not allocated
    (a list of the batches' bytes, freed at each flush, left holes in malloc's heap
    around whatever other threads allocated meanwhile, and under mlockall the holes
    stay resident)."""

    def __init__(self) -> None:
        self.nbytes = 0
        self._buf = np.empty(_PENDING_MIN_BYTES, np.uint8)

    def reserve(self, nbytes: int) -> np.ndarray:
        """The next ``nbytes`` of the buffer (uint8), counted as filled: the
        caller writes its records there."""
        end = self.nbytes + nbytes
        if end > self._buf.size:
            grown = np.empty(max(end, 2 * self._buf.size), np.uint8)
            grown[:self.nbytes] = self._buf[:self.nbytes]
            self._buf = grown
        view = self._buf[self.nbytes:end]
        self.nbytes = end
        return view

    def add(self, records: Any) -> None:
        """Copies ``records`` (bytes, or a contiguous numpy array of whole records) in."""
        src = np.frombuffer(records, np.uint8)
        self.reserve(src.size)[:] = src

    def view(self) -> memoryview:
        """The pending records' bytes (valid until the next ``reserve`` or ``clear``)."""
        return memoryview(self._buf[:self.nbytes])

    def clear(self) -> None:
        self.nbytes = 0


class _Mf4File:
    """An MDF 4.10 file whose channel groups grow block by block; complete after
    every ``flush()`` (see the module's docstring)."""

    def __init__(self, f: Any, mdf: Any, layouts: list[tuple[str, np.dtype]],
                 compression_level: int) -> None:
        asammdf = _asammdf()
        from asammdf.blocks import v4_blocks
        from asammdf.blocks import v4_constants as v4c

        self._v4b, self._v4c, self._level = v4_blocks, v4c, compression_level
        buf = io.BytesIO()
        mdf.save(buf, overwrite=True)
        meta = buf.getvalue()
        written = asammdf.MDF(io.BytesIO(meta))
        self.groups: list[_Group] = []
        try:
            for (name, dtype), gp in zip(layouts, written.groups, strict=True):
                cg = gp.channel_group
                if cg.samples_byte_nr != dtype.itemsize or cg.invalidation_bytes_nr:
                    raise RuntimeError(f"asammdf laid out group {name} in {cg.samples_byte_nr} "
                                       f"bytes, expected {dtype.itemsize}")
                _check_layout(name, gp, dtype)
                # CG block: 24-byte header, the links, then record id (u64), cycle count (u64)
                self.groups.append(_Group(name, dtype, gp.data_group.address, cg.address,
                                          cg.address + 24 + 8 * cg.links_nr + 8))
        finally:
            written.close()
        self._f = f
        f.seek(0)
        f.truncate()
        f.write(meta)
        self._pad()
        f.flush()
        for g in self.groups:
            if g.dg_addr == 0 or self._read_u64(g.cycles_at) != 0:
                raise RuntimeError(f"unexpected metadata of group {g.name}")
        self.bytes = f.tell()
        self.flushes = 0              # flushes that appended blocks, each counted when done

    def _read_u64(self, at: int) -> int:
        self._f.flush()
        return struct.unpack("<Q", os.pread(self._f.fileno(), 8, at))[0]

    def _write_u64(self, at: int, value: int) -> None:
        self._f.flush()
        os.pwrite(self._f.fileno(), struct.pack("<Q", value), at)

    def _pad(self) -> None:
        end = self._f.seek(0, os.SEEK_END)
        if end % 8:
            self._f.write(b"\0" * (8 - end % 8))

    def _append_block(self, block: Any) -> int:
        address = self._f.seek(0, os.SEEK_END)
        self._f.write(bytes(block))
        self._pad()
        return address

    def add(self, index: int, records: Any) -> None:
        """Records for group ``index`` (bytes or a numpy array of whole records)."""
        self.groups[index].pending.add(records)

    def reserve(self, index: int, n: int) -> np.ndarray:
        """Room for ``n`` records of group ``index`` (uint8, n x the record size),
        counted as added: the caller fills it."""
        g = self.groups[index]
        return g.pending.reserve(n * g.dtype.itemsize)

    @property
    def pending_bytes(self) -> int:
        return sum(g.pending.nbytes for g in self.groups)

    def flush(self) -> None:
        """Appends the pending records of every group and links them in."""
        v4b, v4c = self._v4b, self._v4c
        appends = any(g.pending.nbytes for g in self.groups)
        for g in self.groups:
            if not g.pending.nbytes:
                continue
            size = g.pending.nbytes
            n = size // g.dtype.itemsize
            # asammdf transposes a copy (one above the mmap threshold for a second of
            # samples or frames: mapped, not in the heap) and compresses that
            dz = v4b.DataZippedBlock(data=g.pending.view(),
                                     zip_type=v4c.FLAG_DZ_TRANSPOSED_DEFLATE,
                                     param=g.dtype.itemsize, original_type=b"DT",
                                     compression_level=self._level)
            g.pending.clear()
            dz_addr = self._append_block(dz)     # the file's end before: where its blocks start
            dl = v4b.DataList(links_nr=2, data_block_addr0=dz_addr, flags=0, data_block_nr=1,
                              offset_0=g.stream_bytes)
            dl_addr = self._append_block(dl)
            hl_addr = 0
            if g.last_dl == 0:
                hl = v4b.HeaderList(first_dl_addr=dl_addr, flags=0,
                                    zip_type=v4c.FLAG_DZ_TRANSPOSED_DEFLATE)
                hl_addr = self._append_block(hl)
            g.stored += self._f.tell() - dz_addr
            # the count first: asammdf reads a group with fewer records than its
            # count (what the blocks hold), not one with more
            g.cycles += n
            self._write_u64(g.cycles_at, g.cycles)                  # cg_cycle_count
            if hl_addr:
                self._write_u64(g.dg_addr + 40, hl_addr)           # dg_data
            else:
                self._write_u64(g.last_dl + 24, dl_addr)            # dl_dl_next
            g.last_dl = dl_addr
            g.stream_bytes += size
        self._f.flush()
        self.bytes = self._f.seek(0, os.SEEK_END)
        if appends:
            self.flushes += 1         # counted once its blocks are linked in

    def close(self, sync: bool = True) -> None:
        try:
            self.flush()
            if sync:
                os.fsync(self._f.fileno())
        finally:
            self._f.close()


def _check_layout(name: str, gp: Any, dtype: np.dtype) -> None:
    """The channels' byte offsets asammdf chose are those of ``dtype``."""
    offsets = {field: dtype.fields[field][1] for field in dtype.names}
    for ch in gp.channels:
        key = "time" if ch.channel_type == 2 else ch.name.split(".", 1)[-1]
        if key in offsets and ch.byte_offset != offsets[key]:
            raise RuntimeError(f"asammdf put {name}.{ch.name} at byte {ch.byte_offset}, "
                               f"expected {offsets[key]}")


# --------------------------------------------------------------------------
# the recorder
# --------------------------------------------------------------------------

class MdfRecorder(RingDrain):
    """Drains the loop's ``rec`` ring (and, with ``drain_log``, its ``log`` ring)
    into ``path`` (MDF 4.10) in a thread of its own.

    ``command_names``: the received values the loop records (as for the CSV
    ``Recorder``). ``channels``: the names of the loop's buses, in its order
    (``rt_frame.channel`` indexes them; written into the CAN groups'
    comments), None for one unnamed bus. ``flush_s``: wall-clock seconds
    between appended blocks (what a crash can lose at most).
    """

    ring, pop, entry, batch, poll_s, thread_name = (
        "rec", "rt_rec_pop_many", "rt_sample", _BATCH, 0.05, "mdf-recorder")

    def __init__(self, path: str | os.PathLike, command_names: list[str] | tuple = (),
                 channels: list[str] | tuple | None = None, flush_s: float = FLUSH_S,
                 compression_level: int = 6) -> None:
        super().__init__(path)
        self.command_names = list(command_names)
        self.bus_names = [str(c) for c in channels] if channels else []
        self.flush_s = float(flush_s)
        self.compression_level = int(compression_level)
        self.frames_written = 0
        self.frames_handed = 0
        self.fault_events: Any = None     # callable: the fault events not taken yet
        self.fault_events_written = 0
        self._lock = threading.Lock()
        self._frames: list[np.ndarray] = []      # handed by add_frames, not yet added
        self._file: _Mf4File | None = None
        self._closed = False
        self._drain_log = False
        try:
            _asammdf()
        except ImportError as e:
            raise OSError(f"recording {self.path}: {e}") from None
        folder = os.path.dirname(os.path.abspath(self.path))
        try:
            os.makedirs(folder, exist_ok=True)
            self._f = open(self.path, "w+b")  # closed by stop()
        except OSError as e:
            raise OSError(f"recording {self.path}: {e.strerror}") from None

    # ------------------------------------------------------------ set-up
    def start(self, ffi: Any, lib: Any, loop: Any, drain_log: bool = False,
              wall0: float | None = None) -> None:
        """Writes the file's metadata and starts draining. ``drain_log``: also
        drain the loop's ``log`` ring (only when no ``TrafficLogger`` does; it
        would then hand its batches to ``add_frames``). ``wall0``: the wall
        clock (time.time()) of the loop's start, the file's start time (now
        when None)."""
        asammdf = _asammdf()
        from asammdf import Signal
        from asammdf.blocks import v4_constants as v4c
        from asammdf.blocks.v4_blocks import SourceInformation

        fixed_mmap_threshold()

        lay = sample_layout(ffi, self.command_names)
        outputs, base_o, base_c, cmd_extra = lay.outputs, lay.base_o, lay.base_c, lay.cmd_extra
        fields = lay.fields
        self._n_doubles = lay.n_doubles
        self.columns = lay.columns
        self._mt_col = 1 + len(outputs)          # in the record: time first
        # the record's doubles, picked from the sample: time (the output time_s), the
        # outputs, maneuver time, tick (its bits), the commands
        self._cols = np.array([base_o + outputs.index("time_s")]
                              + list(range(base_o, base_o + len(outputs)))
                              + [fields["maneuver_time_s"].offset // 8, 0, lay.fault_mask]
                              + [base_c + k for k, _ in cmd_extra], dtype=np.intp)
        plant_dtype = np.dtype([("time", "<f8")]
                               + [(c, "<u8" if c in _BITS else "<f8") for c in self.columns])

        comments = output_comments()
        wall0 = time.time() if wall0 is None else float(wall0)
        period = float(loop.cfg.period_s) if float(loop.cfg.period_s) > 0 else 0.0005
        step = float(loop.cfg.step_s) if float(loop.cfg.step_s) > 0 else period
        self._time_scale = step / period

        mdf = asammdf.MDF(version=MDF_VERSION)
        mdf.header.start_time = _dt.datetime.fromtimestamp(wall0, tz=_dt.UTC)
        mdf.header.comment = ("dct-hil plant server recording: plant outputs each "
                              "record period of plant time, and the CAN traffic")
        empty_t = np.zeros(0, dtype="<f8")
        signals = []
        for c in self.columns:
            dtype = "<u8" if c in _BITS else "<f8"
            signals.append(Signal(np.zeros(0, dtype=dtype), empty_t, name=c,
                                  unit=_unit(c), comment=self._comment(c, outputs, comments)))
        mdf.append(signals, acq_name="plant",
                   comment="plant samples: master time = plant time after the step (s)")
        buses = ", ".join(f"{i + 1} = {n}" for i, n in enumerate(self.bus_names)) or "1"
        layouts: list[tuple[str, np.dtype]] = [("plant", plant_dtype)]
        for name, fields_ in _BUS_GROUPS:
            dtype = np.dtype([(f"{name}.{f}", t) for f, t in fields_])
            src = SourceInformation(source_type=v4c.SOURCE_BUS, bus_type=v4c.BUS_TYPE_CAN)
            src.name = "dct-hil loop"
            mdf.append(Signal(np.zeros(0, dtype=dtype), empty_t, name=name, source=src,
                              comment=f"CAN traffic of the loop, BusChannel {buses}; Dir 0 "
                                      "received, 1 sent; master time = the tick's loop time "
                                      "x step_s/period_s (s)"),
                       acq_name="CAN", comment=f"{name}: BusChannel {buses}")
            layouts.append((name, np.dtype([("time", "<f8")]
                                           + [(f, t) for f, t in fields_])))
        # the fault starts and ends (rt_loop.faults): one record each
        fault_fields = [("id", "<u4"), ("event", "u1"), ("kind", "<u2")]
        mdf.append([Signal(np.zeros(0, dtype=t), empty_t, name=f"fault.{f}", comment=c)
                    for (f, t), c in zip(fault_fields, (
                        "the fault's id (the run report's faults.set and faults.events)",
                        "1 started, 2 ended (its duration over), 3 cleared",
                        "its kind: the RT_FAULT_* code of rt_loop.h"))],
                   acq_name="faults",
                   comment="fault starts and ends: master time = plant time (s)")
        layouts.append(("faults", np.dtype([("time", "<f8")]
                                           + [(f"fault.{f}", t) for f, t in fault_fields])))
        self._fault_dtype = layouts[-1][1]
        self._fault_codes = {name: int(getattr(lib, k.code)) for name, k in _fault_kinds().items()}
        self._bus_dtypes = {name: lay for name, lay in layouts[1:-1]}
        try:
            self._file = _Mf4File(self._f, mdf, layouts, self.compression_level)
        except OSError as e:
            raise OSError(f"recording {self.path}: {e.strerror}") from None
        finally:
            mdf.close()
        self._log_entry_dtype = _log_entry_dtype(ffi)
        self._drain_log = bool(drain_log)
        if self._drain_log:
            self._log_ring = ffi.addressof(loop[0], "log")
            self._log_pop = lib.rt_log_pop_many
            self._log_buf = ffi.new("rt_log_entry[]", _LOG_BATCH)
        self._rx_dir = int(lib.RT_DIR_RX)
        self._fd_flag, self._brs_flag = int(lib.RT_FRAME_FD), int(lib.RT_FRAME_BRS)
        self._last_flush = time.monotonic()
        self._start(ffi, lib, loop)

    def _comment(self, column: str, outputs: list[str], comments: dict) -> str:
        if column == "time_s":
            return "plant output: plant time after the step"
        if column in outputs:
            text = comments.get(column)
            return f"plant output: {text}" if text else "plant output"
        if column == "maneuver_time_s":
            return "plant time since the scripted maneuver started (NaN before)"
        if column == "tick":
            return "the loop's executed tick of the sample"
        if column == "fault_mask":
            return ("fault slots active in the tick (bit k: slot k); the faults group holds "
                    "their starts and ends")
        return (f"received value {column[4:]} as the loop applied it in the tick "
                "(the mapping's input or recorded value)")

    # ------------------------------------------------------------ data
    def _write(self, buf: Any, n: int) -> None:
        raw = np.frombuffer(self._ffi.buffer(buf, n * self._n_doubles * 8), dtype=np.float64)
        # the recorded columns straight into the group's pending buffer (mode "clip":
        # numpy takes into ``out`` unbuffered; every column index is in range)
        rec = self._file.reserve(0, n).view(np.float64).reshape(n, len(self._cols))
        np.take(raw.reshape(n, self._n_doubles), self._cols, axis=1, out=rec, mode="clip")
        mt = rec[:, self._mt_col]
        mt[mt < 0] = np.nan                                     # before the maneuver started

    def add_frames(self, buf: Any, n: int) -> None:
        """The traffic log's batch of ``n`` ``rt_log_entry`` (copied at once: the
        caller may reuse ``buf``). Thread-safe; ignored after ``stop()``."""
        if n <= 0 or self._closed or self._file is None:
            return
        entries = np.frombuffer(self._ffi.buffer(buf, n * self._log_entry_dtype.itemsize),
                                dtype=self._log_entry_dtype).copy()
        with self._lock:
            self._frames.append(entries)
            self.frames_handed += n

    def _take_frames(self) -> None:
        with self._lock:
            batches, self._frames = self._frames, []
        for e in batches:
            self._add_entries(e)

    def _add_entries(self, e: np.ndarray) -> None:
        ident = e["id"].astype(np.uint32)
        length = np.minimum(e["len"], _DATA_BYTES).astype(np.uint8)
        flags = e["flags"]
        fd = (flags & self._fd_flag) != 0
        kind = np.where(ident & _CAN_ERR_FLAG, 2, np.where(ident & _CAN_RTR_FLAG, 1, 0))
        for index, (name, _fields) in enumerate(_BUS_GROUPS):
            sel = kind == index
            if not sel.any():
                continue
            lay = self._bus_dtypes[name]
            r = np.zeros(int(sel.sum()), dtype=lay)
            r["time"] = e["time_s"][sel] * self._time_scale
            r["BusChannel"] = e["channel"][sel] + 1
            r["ID"] = ident[sel] & _CAN_ID_MASK
            r["IDE"] = (ident[sel] & _CAN_EFF_FLAG) != 0
            ln = length[sel]
            r["DataLength"] = ln
            r["DLC"] = _dlc(ln, fd[sel])
            r["Dir"] = e["dir"][sel] != self._rx_dir
            if "DataBytes" in lay.names:
                data = e["data"][sel]
                data[np.arange(_DATA_BYTES)[None, :] >= ln[:, None]] = 0
                r["DataBytes"] = data
                r["EDL"] = fd[sel]
                r["BRS"] = (flags[sel] & self._brs_flag) != 0
            self._file.add(1 + index, r)
            self.frames_written += len(r)

    def _drain(self) -> int:
        n = super()._drain()
        if self.error is None:
            try:
                if self._drain_log:
                    while True:
                        k = self._log_pop(self._log_ring, self._log_buf, _LOG_BATCH)
                        if k:
                            self._add_entries(np.frombuffer(
                                self._ffi.buffer(self._log_buf,
                                                 k * self._log_entry_dtype.itemsize),
                                dtype=self._log_entry_dtype).copy())
                        if k < _LOG_BATCH:
                            break
                self._take_frames()
                self._take_fault_events()
                now = time.monotonic()
                if (now - self._last_flush >= self.flush_s
                        or self._file.pending_bytes >= _MAX_PENDING_BYTES):
                    self._flush()
                    self._last_flush = now
            except Exception as e:  # reported, not fatal to the loop
                self.error = f"{self.path}: {_cause(e)}"
        return n

    def _take_fault_events(self) -> None:
        if self.fault_events is None or self._file is None:
            return
        events = self.fault_events()
        if not events:
            return
        r = np.zeros(len(events), dtype=self._fault_dtype)
        what = {"start": 1, "end": 2, "cleared": 3}
        for i, e in enumerate(events):
            r[i] = (e["time_s"], e["id"], what.get(e["event"], 0),
                    self._fault_codes.get(e["kind"], 0))
        self._file.add(len(self._file.groups) - 1, r)
        self.fault_events_written += len(events)

    def _flush(self) -> None:
        if self._file.pending_bytes:
            self._file.flush()

    def _close(self) -> None:
        self._closed = True
        if self._file is None:
            self._f.close()
            return
        if self.error is None:
            self._take_frames()
            self._take_fault_events()
            self._file.close()
        else:
            self._file._f.close()

    @property
    def log_dropped(self) -> int:
        """Log entries the loop could not put in its ring (counted by the loop)."""
        return int(self._loop.log.dropped) if self._loop is not None else 0

    @property
    def blocks(self) -> int:
        """Flushes that appended data blocks to the file and linked them in so far
        (a flush is counted when it is done: a reader that sees the count grow
        finds the file complete up to that flush)."""
        return self._file.flushes if self._file is not None else 0

    @property
    def bytes(self) -> int:
        """The file's size after the last flush."""
        return self._file.bytes if self._file is not None else 0

    def counters(self) -> dict:
        return {**super().counters(), "format": f"MDF {MDF_VERSION}",
                "frames_written": self.frames_written,
                "frames_dropped": self.log_dropped if self._drain_log else None,
                "blocks": self.blocks, "bytes": self.bytes,
                "group_bytes": ({g.name: g.stored for g in self._file.groups}
                                if self._file is not None else {})}


_BITS = ("tick", "fault_mask")      # plant columns stored as the uint64 they are


def _fault_kinds() -> dict:
    from rt_loop.faults import KINDS

    return KINDS


def _unit(column: str) -> str:
    name = column[4:] if column.startswith("cmd_") else column
    return unit_of_name(name) or ""


def _dlc(length: np.ndarray, fd: np.ndarray) -> np.ndarray:
    """The DLC of each data length (CAN FD lengths above 8 coded 9..15)."""
    code = np.searchsorted(np.array(_FD_LENGTHS), length, side="left").astype(np.uint8)
    return np.where(fd, code, np.minimum(length, 8)).astype(np.uint8)


def _log_entry_dtype(ffi: Any) -> np.dtype:
    """numpy's view of one ``rt_log_entry`` (offsets from the compiled struct)."""
    entry, frame = dict(ffi.typeof("rt_log_entry").fields), dict(ffi.typeof("rt_frame").fields)
    base = entry["frame"].offset
    names = ["time_s", "dir", "id", "len", "flags", "channel", "data"]
    formats = ["<f8", "<u4", "<u4", "u1", "u1", "u1", (np.uint8, ffi.sizeof(frame["data"].type))]
    offsets = [entry["time_s"].offset, entry["dir"].offset] + [
        base + frame[n].offset for n in ("id", "len", "flags", "channel", "data")]
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": ffi.sizeof("rt_log_entry")})
    if dtype["data"].shape[0] < _DATA_BYTES:     # classic-only build: pad to 64
        raise TypeError("rt_frame.data holds fewer than 64 bytes")
    return dtype


def _cause(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror:
        return e.strerror
    return f"{type(e).__name__}: {one_line(e)}"
