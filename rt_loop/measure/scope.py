"""The scope: every tick of chosen values, as min and max per bucket, for a live view.

A view that samples the loop's statistics 20 times a second sees one tick in
a hundred; a 0.5 ms spike of a clutch pressure or of the turnaround falls
between the samples. The scope lets the tick itself keep, for up to
``MAX_TRACES`` values, their min and max over a bucket of ``bucket_ticks``
executed ticks (10 = 5 ms at 2 kHz; ``rt_loop/csrc/rt_scope.c``) and hand
each full bucket to this module through a lock-free ring. A thread of its
own drains the ring every ``poll_s`` and keeps ``history_s`` of buckets per
traced name, which any number of readers (browser sessions) read with
``read(names, since_tick)``. A reader that is slow or gone costs the loop
nothing: the ring is drained here whatever the readers do; a ring the
drain could not empty in time is counted by the loop (``dropped``).

Names (``traceable()``): plant outputs (``vehicle_speed_kmh``), plant
inputs as given (``inputs.road_grade_pct``), received values as applied
(``cmd.<name>``), any CAN signal of the served mapping (``Message.Signal``,
its last value), ``maneuver_time_s`` and the loop's own times
(``turnaround_us``, ``exec_us``, ``latency_us``: of the tick before).

Tracing is reference-counted: ``add(names)`` by each reader, ``remove`` when
it no longer shows them; the loop is reconfigured (a new generation of
``rt_scope_config``, taken whole at the next tick) only when the set of
traced names changes. A name's history starts when it is first traced.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = ["Scope", "ScopeError", "traceable_offsets"]

#: values traced at once (RT_SCOPE_TRACES)
MAX_TRACES = 32
_LOOP_TIMES = ("turnaround_us", "exec_us", "latency_us")


class ScopeError(ValueError):
    """A name that cannot be traced, too many traces, or a loop that did not
    take the configuration (one line)."""


def _suggest(name: str, known: Iterable[str]) -> str:
    import difflib

    close = difflib.get_close_matches(str(name), list(known), n=3)
    return f" (did you mean {', '.join(close)}?)" if close else ""


def traceable_offsets(ffi: Any, lib: Any, channels: Any) -> dict[str, int]:
    """name -> byte offset in the rt_loop of the double it traces."""
    out: dict[str, int] = {}
    for name, _ in ffi.typeof("dct_outputs").fields:
        out[name] = ffi.offsetof("rt_loop", "plant", "outputs", name)
    for name, _ in ffi.typeof("dct_inputs").fields:
        out[f"inputs.{name}"] = ffi.offsetof("rt_loop", "plant", "inputs", name)
    for k, name in enumerate(channels.command_names):
        out[f"cmd.{name}"] = ffi.offsetof("rt_loop", "stats", "commands", k)
    out["maneuver_time_s"] = ffi.offsetof("rt_loop", "stats", "maneuver_time_s")
    for name in _LOOP_TIMES:
        out[name] = ffi.offsetof("rt_loop", "stats", name)
    # every CAN signal by Message.Signal (and bus:Message.Signal), named as the faults name them
    from rt_loop.faults import Names

    for name, (_g, _k, value_index, _sig) in Names(ffi, lib, channels).signals.items():
        out[name] = ffi.offsetof("rt_loop", "signal_values", value_index)
    return out


class Scope:
    """The scope of one served loop (``Server.scope``); see the module text.

    ``bucket_ticks``: executed ticks per bucket; ``history_s``: plant seconds
    of buckets kept per name (at the loop's step ``step_s``).
    """

    max_traces = MAX_TRACES

    def __init__(self, ffi: Any, lib: Any, loop: Any, channels: Any, step_s: float,
                 bucket_ticks: int = 10, history_s: float = 120.0, poll_s: float = 0.01) -> None:
        if not 1 <= int(bucket_ticks) <= int(lib.RT_SCOPE_MAX_BUCKET):
            raise ScopeError(f"bucket of {bucket_ticks} ticks: 1 .. {int(lib.RT_SCOPE_MAX_BUCKET)}")
        self._ffi, self._lib, self._loop = ffi, lib, loop
        self.bucket_ticks = int(bucket_ticks)
        self.bucket_s = self.bucket_ticks * float(step_s)
        self.poll_s = float(poll_s)
        self._offsets = traceable_offsets(ffi, lib, channels)
        self._size = max(16, int(round(history_s / self.bucket_s)))
        self._lock = threading.Lock()           # readers and the drain; never the loop
        self._refs: dict[str, int] = {}
        self._slots: list[str] = []             # trace k of the configuration in use
        self._gen = int(loop.scope_gen)
        self._gen_names: dict[int, list[str]] = {}
        # history: a ring of buckets (tick, time) and per name its min and max
        self._tick = np.zeros(self._size, dtype=np.int64)
        self._time = np.zeros(self._size, dtype=np.float64)
        self._min: dict[str, np.ndarray] = {}
        self._max: dict[str, np.ndarray] = {}
        self._count = 0                         # buckets ever stored
        self._buf = ffi.new("rt_scope_bucket[]", int(lib.RT_SCOPE_RING_SIZE))
        self._ring = ffi.addressof(loop[0], "scope")      # loop: an "rt_loop *"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.buckets = 0                        # buckets drained

    # ------------------------------------------------------------ names
    def traceable(self) -> list[str]:
        """Every name that may be traced, sorted (plant outputs first)."""
        outs = [n for n, _ in self._ffi.typeof("dct_outputs").fields]
        rest = sorted(n for n in self._offsets if n not in set(outs))
        return outs + rest

    def traced(self) -> list[str]:
        with self._lock:
            return list(self._slots)

    def _check(self, names: Any) -> list[str]:
        if isinstance(names, str):
            names = [names]
        names = list(names)
        for n in names:
            if not isinstance(n, str) or n not in self._offsets:
                raise ScopeError(f"scope: {n!r} cannot be traced (a plant output, inputs.<name>, "
                                 "cmd.<name>, Message.Signal or turnaround_us)"
                                 + _suggest(n, self._offsets))
        return names

    def add(self, names: Any) -> None:
        """Traces ``names`` (counted: each add wants a remove)."""
        names = self._check(names)
        with self._lock:
            new = [n for n in dict.fromkeys(names) if n not in self._refs]
            if len(self._refs) + len(new) > MAX_TRACES:
                raise ScopeError(f"scope: {len(self._refs) + len(new)} values traced at once; at "
                                 f"most {MAX_TRACES} (remove some first)")
            for n in names:
                self._refs[n] = self._refs.get(n, 0) + 1
            if new:
                for n in new:
                    self._min[n] = np.full(self._size, np.nan)
                    self._max[n] = np.full(self._size, np.nan)
                self._configure()

    def remove(self, names: Any) -> None:
        """Stops tracing ``names`` once every reader that added them removed them."""
        names = self._check(names)
        with self._lock:
            gone = []
            for n in names:
                if n in self._refs:
                    self._refs[n] -= 1
                    if self._refs[n] <= 0:
                        del self._refs[n]
                        gone.append(n)
            if gone:
                for n in gone:
                    self._min.pop(n, None)
                    self._max.pop(n, None)
                self._configure()

    def _configure(self) -> None:
        """Publishes the traced names as a new configuration (holding the lock)."""
        lib, loop = self._lib, self._loop
        deadline = time.monotonic() + 1.0
        while int(lib.rt_scope_acked(loop)) != self._gen:   # the other slot is free
            if not self._running() or time.monotonic() > deadline:
                break
            time.sleep(0.0005)
        names = sorted(self._refs, key=lambda n: (n not in self._slots, n))
        gen = (self._gen + 1) & 0xFFFFFFFF
        cfg = loop.scope_cfg[gen & 1]
        cfg.n = len(names)
        cfg.bucket_ticks = self.bucket_ticks
        for k, n in enumerate(names):
            cfg.offset[k] = self._offsets[n]
        self._gen_names[gen] = names
        self._slots = names
        self._gen = gen
        lib.rt_scope_publish(loop, gen)

    def _running(self) -> bool:
        return int(self._loop.stats.state) == int(self._lib.RT_STATE_RUNNING)

    # ------------------------------------------------------------ the drain
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="scope", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        with self._lock:
            if self._refs:
                self._refs.clear()
                self._configure()

    def drain(self) -> int:
        """Moves the buckets waiting in the ring into the history; returns how many."""
        n = int(self._lib.rt_scope_pop_many(self._ring, self._buf, len(self._buf)))
        if n == 0:
            return 0
        raw = self._ffi.buffer(self._buf, n * self._ffi.sizeof("rt_scope_bucket"))
        rec = np.frombuffer(raw, dtype=_bucket_dtype()).copy()
        with self._lock:
            for b in rec:
                names = self._gen_names.get(int(b["gen"]))
                if names is None:
                    continue
                i = self._count % self._size
                self._tick[i] = b["tick"]
                self._time[i] = b["time_s"]
                for name in self._min:
                    self._min[name][i] = np.nan
                    self._max[name][i] = np.nan
                for k, name in enumerate(names):
                    if name in self._min:
                        lo, hi = b["min"][k], b["max"][k]
                        if lo <= hi:                 # +inf / -inf: no finite value
                            self._min[name][i] = lo
                            self._max[name][i] = hi
                self._count += 1
            # configurations no bucket can carry any more
            for g in [g for g in self._gen_names if g != self._gen
                      and g != int(rec[-1]["gen"])]:
                del self._gen_names[g]
        self.buckets += n
        return n

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.drain() < len(self._buf) // 2:
                self._stop.wait(self.poll_s)
        self.drain()

    @property
    def dropped(self) -> int:
        return int(self._loop.scope.dropped)

    # ------------------------------------------------------------ readers
    def read(self, names: Any, since_tick: int | None = None) -> dict:
        """The kept buckets after ``since_tick`` (all when None): ``tick``
        (the last tick of each), ``time_s`` (plant time) and ``min`` and
        ``max`` ({name: array}, NaN where the name was not traced)."""
        names = self._check(names)
        with self._lock:
            n = min(self._count, self._size)
            idx = (np.arange(self._count - n, self._count) % self._size)
            ticks = self._tick[idx]
            if since_tick is not None:
                keep = ticks > since_tick
                idx, ticks = idx[keep], ticks[keep]
            out = {"tick": ticks.copy(), "time_s": self._time[idx].copy(), "min": {}, "max": {}}
            nan = np.full(len(idx), np.nan)
            for name in names:
                out["min"][name] = self._min[name][idx].copy() if name in self._min else nan.copy()
                out["max"][name] = self._max[name][idx].copy() if name in self._max else nan.copy()
        return out


_DTYPE: np.dtype | None = None


def _bucket_dtype() -> np.dtype:
    """numpy's view of rt_scope_bucket (checked against cffi's layout)."""
    global _DTYPE
    if _DTYPE is None:
        from rt_loop._rt_loop import ffi, lib

        n = int(lib.RT_SCOPE_TRACES)
        t = ffi.typeof("rt_scope_bucket")
        f = dict(t.fields)
        dt = np.dtype({"names": ["tick", "time_s", "gen", "ticks", "min", "max"],
                       "formats": ["<u8", "<f8", "<u4", "<u4", (np.float64, n), (np.float64, n)],
                       "offsets": [f[k].offset for k in ("tick", "time_s", "gen", "ticks", "min",
                                                          "max")],
                       "itemsize": ffi.sizeof(t)})
        _DTYPE = dt
    return _DTYPE
