"""The XCP slave's memory and DAQ producer: the real-time loop itself.

An XCP address is a byte offset from the start of the ``rt_loop`` struct
(address extension 0), as ``rt_loop.h`` defines it.

* Reading (UPLOAD, SHORT_UPLOAD) copies the bytes out of the loop's
  memory while it runs: a value the tick is writing at that moment may come
  out torn (DAQ, copied by the tick itself, never is). Only the
  ``readable`` ranges may be read and measured (default: the whole struct).
* Writing (DOWNLOAD, SHORT_DOWNLOAD, the calibration pages) goes through the
  loop's ``cal`` ring: each write must lie inside the loop's writable
  regions (``rt_loop.regions``, set with ``set_regions`` before
  ``rt_loop_prepare``; else ERR_WRITE_PROTECTED), every value it changes
  within its range (``ranges``: ``(offset, size, ..., lo, hi, c_type)`` as
  ``rt_loop.measure.xcp.a2l.calibration_regions`` gives them, the A2L's limits;
  else ERR_OUT_OF_RANGE), is cut at region borders and into pieces of
  RT_WRITE_BYTES, and all its pieces are queued at once (the loop applies
  them at its next tick boundary; one piece is never torn, a write of more
  than RT_WRITE_BYTES is several). The answer waits for the loop (at most
  ``write_wait_s``): ERR_OUT_OF_RANGE when the plant refused the new
  parameters (the loop undid that piece), OK when applied, or when the loop
  is not ticking (queued: applied at its first tick). ``write_queued`` (STIM,
  which nobody answers) does not wait: OK once queued (a value the plant
  refuses then shows in ``cal_refused`` only). The ``cal`` ring has
  one producer side: every producer (this backend, the control channel,
  ``rt_loop.control``) pushes through ``push_writes`` holding the same lock
  (``Server.cal_lock``, given as ``cal_lock``; the loop never takes it), and
  the write ids continue from the ring's last entry, so they increase in
  ring order whoever queued them.
* DAQ: a configuration goes into ``daq[(daq_gen + 1) & 1]``, then
  ``daq_gen`` is incremented; while the loop ticks, the other slot is
  written again only once ``daq_ack == daq_gen`` (waited for at most
  ``ack_wait_s``, else ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE: the master
  repeats). A configuration the loop refused (``daq_refused``) answers
  ERR_DAQ_CONFIG. Lists that do not run are published without ODTs. The
  measured ODTs come out of ``daq_ring``: read by the transport's C sender
  (``dto_ring``, ``rt_loop/csrc/rt_xcp_send.h``: packed and sent with no
  Python on the way), or by ``pop`` (``rt_daq_pop_many``) where no sender
  runs; the ring's ``dropped`` is the overload indication.

``daq_gen`` is published and ``daq_ack`` read through ``rt_daq_publish`` /
``rt_daq_acked`` (release / acquire in C); the write ring is filled by
``rt_write_push_many`` and the DTO ring drained by ``rt_daq_pop_many``, both
with the ring's own atomics.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Sequence
from typing import Any

from rt_loop.measure.xcp.protocol import (
    ERR_ACCESS_DENIED,
    ERR_CMD_BUSY,
    ERR_DAQ_CONFIG,
    ERR_MEMORY_OVERFLOW,
    ERR_OUT_OF_RANGE,
    ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE,
    ERR_WRITE_PROTECTED,
    OK,
    Daq,
    DaqListConfig,
    Dto,
    Event,
    Limits,
    Memory,
    merge_ranges,
)

__all__ = ["LoopBackend", "loop_events", "push_writes", "set_regions"]

_DTO_BATCH = 512
_POLL_S = 0.0002
#: struct formats of the C types a range may name
_FORMATS = {"double": "d", "float": "f", "int": "i", "int32_t": "i", "unsigned int": "I",
            "uint32_t": "I", "int64_t": "q", "uint64_t": "Q", "int16_t": "h", "uint16_t": "H",
            "int8_t": "b", "uint8_t": "B", "char": "b", "signed char": "b", "unsigned char": "B"}


def set_regions(ffi: Any, lib: Any, loop: Any, regions: Sequence[tuple]) -> None:
    """Writes the loop's writable regions: (offset, size, kind RT_REGION_*,
    ...) each, as ``rt_loop.measure.xcp.a2l.calibration_regions`` gives them (what
    follows the kind is not the loop's); before ``rt_loop_prepare`` (which
    checks them)."""
    size = ffi.sizeof("rt_loop")
    if len(regions) > lib.RT_MAX_REGIONS:
        raise ValueError(f"{len(regions)} writable regions: at most {lib.RT_MAX_REGIONS}")
    for offset, n, kind, *_ in regions:
        if n <= 0 or offset < 0 or offset + n > size:
            raise ValueError(f"writable region {offset:#x} + {n}: outside the loop ({size} bytes)")
        if kind not in (lib.RT_REGION_DATA, lib.RT_REGION_PARAM):
            raise ValueError(f"writable region {offset:#x}: unknown kind {kind}")
    for k, (offset, n, kind, *_) in enumerate(regions):
        loop.regions[k].offset = offset
        loop.regions[k].size = n
        loop.regions[k].kind = kind
    loop.n_regions = len(regions)


def push_writes(ffi: Any, lib: Any, loop: Any, pieces: Sequence[tuple[int, bytes]],
                lock: Any) -> tuple[int, int] | None:
    """Queues ``pieces`` ((offset, bytes of at most RT_WRITE_BYTES) each) into the
    loop's ``cal`` ring, all or none, holding ``lock`` (the ring's one producer
    side, shared by every producer). Their ids continue from the last entry
    queued, by whichever producer. Returns (first id, last id), or None when
    the ring has no room for all of them (nothing queued)."""
    cal = loop.cal
    size = int(lib.RT_WRITE_RING_SIZE)
    with lock:
        head = int(cal.head)
        used = (head - int(cal.tail)) & 0xFFFFFFFF
        if size - used < len(pieces):
            return None
        last_queued = int(cal.writes[(head - 1) & (size - 1)].id) if head else 0
        first = max(last_queued, int(cal.last_applied_id), int(cal.last_refused_id)) + 1
        writes = ffi.new("rt_write[]", len(pieces))
        for k, (offset, blob) in enumerate(pieces):
            w = writes[k]
            w.time_s = 0.0
            w.offset = offset
            w.len = len(blob)
            w.id = first + k
            ffi.memmove(w.data, blob, len(blob))
        queued = lib.rt_write_push_many(ffi.addressof(loop, "cal"), writes, len(pieces))
        if queued != len(pieces):          # cannot happen: room was checked under the lock
            return None
        return first, first + len(pieces) - 1


def loop_events(loop: Any) -> tuple[Event, ...]:
    """The loop's event channels in wall-clock time: every tick, every
    10 ms and every 100 ms of plant time (stretched by the time scale)."""
    period = float(loop.cfg.period_s)
    step = float(loop.cfg.step_s) or period

    def every(plant_s: float) -> float:
        ticks = plant_s / step
        return period * (1 if ticks < 1.5 else round(ticks))

    return (Event("tick", period), Event("10ms", every(0.010)), Event("100ms", every(0.100)))


class LoopBackend(Memory, Daq):
    """``Memory`` and ``Daq`` of the XCP slave over a prepared ``rt_loop``
    (``loop`` is the ``rt_loop *`` of ``Server``)."""

    def __init__(
        self,
        ffi: Any,
        lib: Any,
        loop: Any,
        *,
        readable: Sequence[tuple[int, int]] | None = None,
        ranges: Sequence[tuple] | None = None,
        write_wait_s: float = 0.2,
        ack_wait_s: float = 0.2,
        cal_lock: Any = None,
    ) -> None:
        self.ffi, self.lib, self.loop = ffi, lib, loop
        self.size = ffi.sizeof("rt_loop")
        self._mem = ffi.buffer(loop, self.size)
        self.readable = merge_ranges(readable) if readable is not None else [(0, self.size)]
        for start, n in self.readable:
            if start < 0 or start + n > self.size:
                raise ValueError(f"readable range {start:#x} + {n}: outside the loop")
        self._ranges = sorted(self._range(ffi, r) for r in ranges or ())
        self.limits = Limits(max_lists=lib.RT_DAQ_MAX_LISTS, max_odts=lib.RT_DAQ_MAX_ODTS,
                             max_entries=lib.RT_DAQ_MAX_ENTRIES, odt_bytes=lib.RT_DAQ_ODT_BYTES)
        self.write_wait_s = write_wait_s
        self.ack_wait_s = ack_wait_s
        # the rt_loop * for the hand-over functions (loop may be the pointer or the struct)
        self._loop_ptr = loop if ffi.typeof(loop).kind == "pointer" else ffi.addressof(loop)
        self._cal = ffi.addressof(loop, "cal")
        self._ring = ffi.addressof(loop, "daq_ring")
        #: held while pushing into the cal ring (shared with its other producers)
        self.cal_lock = cal_lock if cal_lock is not None else threading.Lock()
        self._dto_buf = ffi.new("rt_dto[]", _DTO_BATCH)
        self._dto_size = ffi.sizeof("rt_dto")
        self._off_time = ffi.offsetof("rt_dto", "time_ns")
        self._off_ids = ffi.offsetof("rt_dto", "list")
        self._off_data = ffi.offsetof("rt_dto", "data")
        if (ffi.offsetof("rt_dto", "odt") != self._off_ids + 2
                or ffi.offsetof("rt_dto", "len") != self._off_ids + 4):
            raise TypeError("rt_dto: list, odt and len must follow each other (uint16)")
        self._counts = {"writes": 0, "write_pieces": 0, "writes_refused": 0, "writes_queued": 0,
                        "writes_out_of_range": 0, "daq_configs": 0}

    @staticmethod
    def _range(ffi: Any, r: tuple) -> tuple:
        offset, size, lo, hi, c_type = r[0], r[1], r[-3], r[-2], r[-1]
        fmt = _FORMATS.get(c_type)
        if fmt is None or struct.calcsize(fmt) != ffi.sizeof(c_type):
            raise ValueError(f"range at {offset:#x}: no check for C type {c_type!r}")
        esize = struct.calcsize(fmt)
        if size <= 0 or size % esize:
            raise ValueError(f"range at {offset:#x}: {size} bytes of {c_type}")
        return offset, size, float(lo), float(hi), "<" + fmt, esize

    def _in_range(self, address: int, data: bytes) -> bool:
        """Every value the write changes (whole, with the bytes around it it
        does not write) within its range's lo..hi (NaN never is)."""
        end = address + len(data)
        for offset, size, lo, hi, fmt, esize in self._ranges:
            if offset >= end or offset + size <= address:
                continue
            first = offset + (max(address, offset) - offset) // esize * esize
            last = offset + -(-(min(end, offset + size) - offset) // esize) * esize
            values = bytearray(self._mem[first:last])
            a, b = max(address, first), min(end, last)
            values[a - first:b - first] = data[a - address:b - address]
            if not all(lo <= v <= hi for (v,) in struct.iter_unpack(fmt, values)):
                return False
        return True

    # ---- the loop's state -------------------------------------------------------
    def ticking(self) -> bool:
        """True while the loop thread may be ticking (or about to)."""
        s = self.loop.stats
        state = int(s.state)
        if state == self.lib.RT_STATE_RUNNING:
            return True
        return state == self.lib.RT_STATE_IDLE and int(s.startup_phase) != self.lib.RT_START_NOT_STARTED

    def events(self) -> tuple[Event, ...]:
        return loop_events(self.loop)

    # ---- Memory -----------------------------------------------------------------
    def _readable(self, address: int, n: int) -> bool:
        return n > 0 and any(start <= address and address + n <= start + size
                             for start, size in self.readable)

    def read(self, address: int, n: int) -> bytes | int:
        if not self._readable(address, n):
            return ERR_ACCESS_DENIED
        return self._mem[address:address + n]

    def regions(self) -> list[tuple[int, int, int]]:
        """The loop's writable regions: (offset, size, kind)."""
        loop = self.loop
        return [(int(loop.regions[k].offset), int(loop.regions[k].size), int(loop.regions[k].kind))
                for k in range(int(loop.n_regions))]

    def cal_regions(self) -> list[tuple[int, int]]:
        return [(offset, size) for offset, size, _ in self.regions()]

    def _pieces(self, address: int, data: bytes) -> list[tuple[int, bytes]] | int:
        regions = self.regions()
        chunk = int(self.lib.RT_WRITE_BYTES)
        pieces = []
        at, end = address, address + len(data)
        while at < end:
            region = next(((o, n) for o, n, _ in regions if o <= at < o + n), None)
            if region is None:
                return ERR_WRITE_PROTECTED
            stop = min(end, region[0] + region[1], at + chunk)
            pieces.append((at, data[at - address:stop - address]))
            at = stop
        return pieces

    def write(self, address: int, data: bytes, wait: bool = True) -> int | None:
        if not data or address < 0 or address + len(data) > self.size:
            return ERR_ACCESS_DENIED
        pieces = self._pieces(address, data)
        if isinstance(pieces, int):
            return pieces
        if not self._in_range(address, data):
            self._counts["writes_out_of_range"] += 1
            return ERR_OUT_OF_RANGE
        cal = self.loop.cal
        ids = push_writes(self.ffi, self.lib, self.loop, pieces, self.cal_lock)
        if ids is None:
            return ERR_CMD_BUSY
        first, last = ids
        self._counts["writes"] += 1
        self._counts["write_pieces"] += len(pieces)
        if not wait:
            return OK                              # queued: applied at the next tick boundary
        deadline = time.monotonic() + self.write_wait_s
        while self.ticking():
            if max(int(cal.last_applied_id), int(cal.last_refused_id)) >= last:
                if first <= int(cal.last_refused_id) <= last:
                    self._counts["writes_refused"] += 1
                    return ERR_OUT_OF_RANGE       # the plant refused the values
                return OK
            if time.monotonic() > deadline:
                break
            time.sleep(_POLL_S)
        self._counts["writes_queued"] += 1
        return OK                                  # queued: the loop applies it when it ticks

    def write_queued(self, address: int, data: bytes) -> int | None:
        return self.write(address, data, wait=False)

    # ---- Daq ------------------------------------------------------------------------
    def _wait_ack(self) -> bool:
        loop = self.loop
        deadline = time.monotonic() + self.ack_wait_s
        while int(self.lib.rt_daq_acked(self._loop_ptr)) != int(loop.daq_gen):
            if not self.ticking():
                return True                        # nobody reads the slots now
            if time.monotonic() > deadline:
                return False
            time.sleep(_POLL_S)
        return True

    def apply(self, lists: Sequence[DaqListConfig]) -> int | None:
        lim = self.limits
        running = [d.running for d in lists]
        odts = [d.odts if d.running else () for d in lists]
        if (len(lists) > lim.max_lists or sum(map(len, odts)) > lim.max_odts
                or sum(len(o) for od in odts for o in od) > lim.max_entries):
            return ERR_MEMORY_OVERFLOW
        if not self._wait_ack():
            return ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE
        loop = self.loop
        gen = int(loop.daq_gen)
        slot = loop.daq[(gen + 1) & 1]
        n_odt = n_entry = 0
        for i, d in enumerate(lists):
            entry = slot.lists[i]
            entry.first_odt = n_odt
            entry.n_odts = len(odts[i])
            entry.event = d.event if running[i] else 0
            entry.prescaler = max(1, d.prescaler)
            entry.running = 1 if running[i] else 0
            for odt in odts[i]:
                o = slot.odts[n_odt]
                o.first_entry = n_entry
                o.n_entries = len(odt)
                for e in odt:
                    x = slot.entries[n_entry]
                    x.offset = e.address
                    x.size = e.size
                    n_entry += 1
                n_odt += 1
        slot.n_lists = len(lists)
        refused = int(loop.daq_refused)
        new_gen = (gen + 1) & 0xFFFFFFFF
        self.lib.rt_daq_publish(self._loop_ptr, new_gen)   # release: the slot before the generation
        self._counts["daq_configs"] += 1
        deadline = time.monotonic() + self.ack_wait_s
        while (self.ticking() and int(self.lib.rt_daq_acked(self._loop_ptr)) != new_gen
               and time.monotonic() < deadline):
            time.sleep(_POLL_S)
        if int(loop.daq_ack) == new_gen and int(loop.daq_refused) != refused:
            return ERR_DAQ_CONFIG
        return OK

    def pop(self, n: int) -> list[Dto]:
        n = min(n, _DTO_BATCH)
        k = self.lib.rt_daq_pop_many(self._ring, self._dto_buf, n)
        if k <= 0:
            return []
        size = self._dto_size
        raw = self.ffi.buffer(self._dto_buf, k * size)[:]
        out = []
        unpack_time = struct.Struct("<q").unpack_from
        unpack_ids = struct.Struct("<HHH").unpack_from
        ot, oi, od = self._off_time, self._off_ids, self._off_data
        for j in range(k):
            base = j * size
            lst, odt, length = unpack_ids(raw, base + oi)
            out.append(Dto(lst, odt, unpack_time(raw, base + ot)[0],
                           raw[base + od:base + od + length]))
        return out

    def dropped(self) -> int:
        return int(self.loop.daq_ring.dropped)

    def dto_ring(self) -> Any:
        """The loop's DAQ ring (``rt_daq_ring *``): the C sender of the
        transport (``rt_xcp_send.h``) reads it itself, so ``pop`` is for
        readers without a sender only (one consumer at a time)."""
        return self._ring

    def counters(self) -> dict:
        loop = self.loop
        return {
            **self._counts,
            "daq_gen": int(loop.daq_gen),
            "daq_ack": int(loop.daq_ack),
            "daq_refused": int(loop.daq_refused),
            "daq_ring_dropped": int(loop.daq_ring.dropped),
            "cal_applied": int(loop.cal.applied),
            "cal_refused": int(loop.cal.refused),
            "cal_dropped": int(loop.cal.dropped),
        }
