"""How faults reach the tick: ``FaultManager`` (one per ``rt_loop.server.Server``,
``server.faults``) queues checked faults into the loop's fault command ring,
reads the loop's start and end events and its per-fault figures, and clears
faults. The loop applies commands at the next tick boundary and never waits for
Python (``rt_loop/csrc/rt_faults.c``)."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from rt_loop.faults.spec import (
    EVENT_NAMES,
    STATE_NAMES,
    WATCH_KIND,
    Fault,
    FaultError,
    Names,
    check_number,
    parse_condition,
    parse_fault,
)

__all__ = ["FaultManager"]


class FaultManager:
    """The faults of one loop: inject, clear, figures and events.

    ``inject`` queues a parsed fault into a free slot (at most
    RT_MAX_FAULTS at once) and returns its id; ``clear(id)`` / ``clear_all()``
    end and free them. Before the loop runs, commands wait in the ring and the
    first tick takes them. ``status()`` reads the loop's published figures
    (state, start and end in plant time, activations, hits: frames or values
    changed); ``events()`` every start and end so far, in order. Thread-safe:
    one lock serialises the ring's producer side and the event reader (the
    loop never takes it)."""

    def __init__(self, ffi: Any, lib: Any, loop: Any, channels: Any,
                 read_stats: Any = None) -> None:
        self.ffi, self.lib, self.loop = ffi, lib, loop
        self.names = Names(ffi, lib, channels)
        self._read_stats = read_stats
        self._lock = threading.Lock()
        self._next_id = 1
        self._slots: dict[int, int] = {}          # id -> slot
        self._faults: dict[int, Fault] = {}       # id -> fault (as injected)
        self._events: list[dict] = []
        self._taken = 0
        self._cmd = ffi.new("rt_fault_cmd *")
        self._ev = ffi.new("rt_fault_event[]", 256)

    # --------------------------------------------------------------- control
    def parse(self, spec: Any) -> Fault:
        return parse_fault(spec, self.names)

    def inject(self, spec: Any, watch: bool = False) -> int:
        """Queues a fault (a spec dict or a parsed Fault); returns its id."""
        f = spec if isinstance(spec, Fault) else self.parse(spec)
        with self._lock:
            used = set(self._slots.values())
            free = [s for s in range(int(self.lib.RT_MAX_FAULTS)) if s not in used]
            if not free:
                raise FaultError(f"{len(used)} faults and watches are set: the loop holds at most "
                                 f"{int(self.lib.RT_MAX_FAULTS)}; clear some first")
            fid = self._next_id
            c = self._cmd
            self.ffi.memmove(c, b"\0" * self.ffi.sizeof("rt_fault_cmd"),
                             self.ffi.sizeof("rt_fault_cmd"))
            c.op = self.lib.RT_FCMD_SET
            c.slot = free[0]
            d = c.fault
            for key, value in f.fields.items():
                setattr(d, key, value)
            d.id = fid
            d.when.n_terms = len(f.terms)
            d.when.any = 1 if f.any else 0
            for i, (source, index, op, value) in enumerate(f.terms):
                t = d.when.terms[i]
                t.source = int(getattr(self.lib, source))
                t.index = index
                t.op = int(getattr(self.lib, op))
                t.value = value
            self._push(c)
            self._next_id += 1
            self._slots[fid] = free[0]
            self._faults[fid] = f
            return fid

    def watch(self, when: str, start_s: float | None = None) -> int:
        """Sets a watch: no effect on the plant; the loop latches the plant
        time its condition first holds (``status`` started_s). Returns its id."""
        f = Fault({"kind": "watch", "when": when}, WATCH_KIND)
        f.fields.update(kind=int(self.lib.RT_FAULT_WATCH), channel=-1, message=-1, signal=-1,
                        local_signal=-1, target=-1, value=0.0, seed=0, duration_s=0.0,
                        start_s=-math.inf if start_s is None else check_number(start_s, "watch: start_s"))
        f.terms, f.any = parse_condition(when, self.names, "watch")
        return self.inject(f)

    def _push(self, c: Any) -> None:
        if self.lib.rt_fault_push_many(self.ffi.addressof(self.loop, "fault_cmds"), c, 1) != 1:
            raise FaultError("the loop's fault command ring is full (the loop is not taking "
                             "commands: is it running?)")

    def clear(self, fault_id: int) -> None:
        """Ends (if active) and frees one fault or watch."""
        with self._lock:
            if fault_id not in self._slots:
                raise FaultError(f"no fault {fault_id!r} is set")
            c = self._cmd
            c.op = self.lib.RT_FCMD_CLEAR
            c.slot = self._slots.pop(fault_id)
            c.fault.id = fault_id
            self._push(c)

    def clear_all(self) -> None:
        with self._lock:
            c = self._cmd
            c.op = self.lib.RT_FCMD_CLEAR_ALL
            c.slot = 0
            c.fault.id = 0
            self._push(c)
            self._slots.clear()

    def wait_taken(self, fault_id: int, timeout_s: float = 2.0) -> bool:
        """True once the loop has taken the command of ``fault_id`` (False:
        not within timeout_s, e.g. the loop is not running)."""
        end = time.monotonic() + timeout_s
        while int(self.loop.fault_cmds.last_id) < fault_id:
            if time.monotonic() > end:
                return False
            time.sleep(0.001)
        return True

    # --------------------------------------------------------------- figures
    def events(self) -> list[dict]:
        """Every start, end and clearing so far: time_s (plant), id, kind, event."""
        with self._lock:
            while True:
                n = self.lib.rt_fault_events_pop_many(
                    self.ffi.addressof(self.loop, "fault_events"), self._ev, 256)
                for i in range(n):
                    e = self._ev[i]
                    f = self._faults.get(int(e.id))
                    self._events.append({
                        "time_s": float(e.time_s), "id": int(e.id),
                        "kind": f.kind.name if f else int(e.kind),
                        "target": f.describe() if f else "",
                        "event": EVENT_NAMES.get(int(e.what), str(int(e.what)))})
                if n < 256:
                    break
            return list(self._events)

    def take_events(self) -> list[dict]:
        """The events not taken by an earlier call (for one reader: the recorder)."""
        events = self.events()
        with self._lock:
            new = events[self._taken:]
            self._taken = len(events)
        return new

    def status(self, stats: Any = None) -> list[dict]:
        """The set faults as the loop last published them (``stats``: an
        ``rt_stats`` copy, else the live one, read field by field)."""
        s = stats if stats is not None else (self._read_stats() if self._read_stats
                                             else self.loop.stats)
        out = []
        with self._lock:
            items = sorted(self._slots.items())
            faults = dict(self._faults)
        for fid, slot in items:
            x = s.faults[slot]
            f = faults[fid]
            mine = int(x.id) == fid
            out.append({
                "id": fid, "kind": f.kind.name, "target": f.describe(),
                "state": STATE_NAMES.get(int(x.state), "?") if mine else "queued",
                "started_s": float(x.started_s) if mine else math.nan,
                "ended_s": float(x.ended_s) if mine else math.nan,
                "activations": int(x.activations) if mine else 0,
                "hits": int(x.hits) if mine else 0})
        return out

    def report(self, stats: Any = None) -> dict:
        """For the run's JSON report: the faults set, every event, the ring's
        counters (plant times not reached are None)."""
        def clean(d: dict) -> dict:
            return {k: (None if isinstance(v, float) and math.isnan(v) else v)
                    for k, v in d.items()}
        return {"set": [clean(x) for x in self.status(stats)], "events": self.events(),
                **self.counters()}

    def counters(self) -> dict:
        r = self.loop.fault_cmds
        return {"commands_applied": int(r.applied), "commands_refused": int(r.refused),
                "commands_dropped": int(r.dropped),
                "events_dropped": int(self.loop.fault_events.dropped)}

    def slot_of(self, fault_id: int) -> int | None:
        with self._lock:
            return self._slots.get(fault_id)

    def fault(self, fault_id: int) -> Fault | None:
        return self._faults.get(fault_id)
