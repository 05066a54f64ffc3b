"""Captures: named values at a chosen downsampling of the tick, started and
stopped by conditions, with the history before the start trigger, several at
once (the XIL API's capture with its start and stop triggers).

    cap = captures.start(["vehicle_speed_kmh", "cmd.target_gear"], every_s=0.002,
                         start_when="gear == 2", pre_s=2.0, post_s=5.0)
    captures.status(cap)    # armed -> capturing -> done
    captures.fetch(cap)     # {"time_s", "tick", "values": {name: array}, ...}

In the tick (``csrc/rt_capture.c``): one configuration, the union of the
sources of every capture armed or running, at the greatest common divisor of
their downsamplings; each due tick copies those values into the capture
ring, nothing more. This module's thread drains the ring every
``POLL_S`` and cuts each capture out of it:

- armed: the last ``pre_s`` of its signals are kept (the history; at most
  ``MAX_PRE_S``, and only since it was armed); its start condition is a
  watch of the loop (``rt_loop.faults``, the language of ``wait_until``:
  exact to the tick), no condition: it starts at once;
- capturing: from the start trigger's plant time minus ``pre_s``;
- done: at the stop condition's time plus ``post_s``, or ``duration_s``
  after the start, or ``MAX_SAMPLES`` rows, or ``stop(id)``.

Values are those of the plant after each tick's step, as the recorder's
samples (a capture and a recording of the same run agree sample for
sample); ``cmd.<name>`` the received value as applied in that tick; the
timing figures (``exec_us``, ...) those of the tick before. Records the
reader could not take in time are counted (``dropped``) and the captures
running then say so (``gaps``).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

__all__ = ["CaptureError", "Captures", "MAX_CAPTURES", "MAX_PRE_S"]

#: captures armed or running at once
MAX_CAPTURES = 8
#: the longest history before a start trigger (plant seconds)
MAX_PRE_S = 30.0
#: rows one capture holds at most (then it is done)
MAX_SAMPLES = 2_000_000
#: values (rows x signals) one capture holds at most
MAX_VALUES = 40_000_000
#: how often the reader drains the ring (wall seconds)
POLL_S = 0.02
STATES = ("armed", "capturing", "done")


class CaptureError(ValueError):
    """A capture that cannot be made or found (one line)."""


def _number(value: Any, what: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise CaptureError(f"capture: {what} must be seconds, got {value!r}")
    if not lo <= value <= hi:
        raise CaptureError(f"capture: {what} {value:g} s is outside {lo:g} .. {hi:g} s")
    return float(value)


class _Capture:
    def __init__(self, cid: int, names: list[str], every: int, start_when: str | None,
                 pre_s: float, stop_when: str | None, post_s: float,
                 duration_s: float | None) -> None:
        self.id = cid
        self.names = names
        self.every = every
        self.start_when, self.stop_when = start_when, stop_when
        self.pre_s, self.post_s, self.duration_s = pre_s, post_s, duration_s
        self.state = "armed"
        self.armed_s: float | None = None       # plant time of its first record
        self.trigger_s: float | None = None
        self.stop_s: float | None = None        # the stop condition's time (or stop())
        self.end_s: float | None = None         # the last plant time it keeps
        self.start_watch: int | None = None
        self.stop_watch: int | None = None
        self.ticks: list[np.ndarray] = []
        self.times: list[np.ndarray] = []
        self.values: list[np.ndarray] = []      # rows x len(names)
        self.rows = 0
        self.gaps = 0                            # records lost while it was armed or running
        self.why_done: str | None = None

    def keep(self, ticks: np.ndarray, times: np.ndarray, values: np.ndarray) -> None:
        self.ticks.append(ticks)
        self.times.append(times)
        self.values.append(values)
        self.rows += len(ticks)

    def trim_before(self, t0: float) -> None:
        """Drops the rows before plant time ``t0`` (the history's window)."""
        while self.times and self.times[0][-1] < t0:
            self.rows -= len(self.times[0])
            del self.ticks[0], self.times[0], self.values[0]
        if self.times and self.times[0][0] < t0:
            k = int(np.searchsorted(self.times[0], t0, side="left"))
            self.rows -= k
            self.ticks[0], self.times[0], self.values[0] = (
                self.ticks[0][k:], self.times[0][k:], self.values[0][k:])

    def trim_after(self, t1: float) -> None:
        while self.times and self.times[-1][0] > t1:
            self.rows -= len(self.times[-1])
            del self.ticks[-1], self.times[-1], self.values[-1]
        if self.times and self.times[-1][-1] > t1:
            k = int(np.searchsorted(self.times[-1], t1, side="right"))
            self.rows -= len(self.times[-1]) - k
            self.ticks[-1], self.times[-1], self.values[-1] = (
                self.ticks[-1][:k], self.times[-1][:k], self.values[-1][:k])

    def last_s(self) -> float | None:
        return float(self.times[-1][-1]) if self.times else None


class Captures:
    """The captures of one served loop (``Server.captures``; see the module)."""

    def __init__(self, server: Any) -> None:
        from rt_loop.measure.scope import traceable_offsets

        self.server = server
        self._ffi, self._lib, self._loop = server._ffi, server._lib, server._l
        ffi, lib = self._ffi, self._lib
        self.step_s = float(server.step_s)
        self._sources = dict(traceable_offsets(ffi, lib, server.channels))
        for k, name in enumerate(server.channels.command_names):   # this tick's, not the stats'
            self._sources[f"cmd.{name}"] = int(lib.RT_CAPTURE_CMD) | k
        self._lock = threading.Lock()
        self._captures: dict[int, _Capture] = {}
        self._next_id = 1
        self._gen = int(lib.rt_capture_acked(self._loop))
        self._gen_sources: dict[int, list[int]] = {}
        self._dropped_seen = 0
        self._buf = ffi.new("rt_capture_record[]", 512)
        self._ring = ffi.addressof(self._loop, "capture")
        self._held = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.counts = {"started": 0, "done": 0, "cleared": 0, "records": 0}

    # ------------------------------------------------------------ requests
    def capturable(self) -> list[str]:
        return sorted(self._sources)

    def start(self, signals: Any = None, every_s: Any = None, start_when: Any = None,
              pre_s: Any = 0.0, stop_when: Any = None, post_s: Any = 0.0,
              duration_s: Any = None) -> int:
        """Arms a capture; returns its id. ``every_s``: the time between samples (a
        whole number of ticks; default every tick)."""
        from rt_loop.faults import FaultError
        from rt_loop.measure.scope import _suggest

        if isinstance(signals, str):
            signals = [signals]
        if not isinstance(signals, list) or not signals or \
                not all(isinstance(n, str) for n in signals):
            raise CaptureError("capture needs signals: a list of value names")
        if len(set(signals)) != len(signals):
            raise CaptureError("capture: a signal is named twice")
        for n in signals:
            if n not in self._sources:
                raise CaptureError(f"capture: {n!r} cannot be captured"
                                   + _suggest(n, self._sources))
        if len(signals) > int(self._lib.RT_CAPTURE_SIGNALS):
            raise CaptureError(f"capture: at most {int(self._lib.RT_CAPTURE_SIGNALS)} signals")
        every = 1
        if every_s is not None:
            e = _number(every_s, "every_s", self.step_s,
                        self.step_s * int(self._lib.RT_CAPTURE_MAX_EVERY))
            every = round(e / self.step_s)
            if abs(every * self.step_s - e) > 1e-9 * max(1.0, e):
                raise CaptureError(f"capture: every_s {e:g} s is not a whole number of ticks "
                                   f"({self.step_s * 1e3:g} ms each)")
        pre = _number(pre_s, "pre_s", 0.0, 1e9)
        if pre > MAX_PRE_S:
            raise CaptureError(f"capture: pre_s {pre:g} s is more history than is kept "
                               f"(at most {MAX_PRE_S:g} s before the start trigger)")
        post = _number(post_s, "post_s", 0.0, 1e9)
        dur = None if duration_s is None else _number(duration_s, "duration_s", 0.0, 1e9)
        for what, cond in (("start_when", start_when), ("stop_when", stop_when)):
            if cond is not None and (not isinstance(cond, str) or not cond.strip()):
                raise CaptureError(f"capture: {what} must be a condition such as \"gear == 2\"")
        rows = (pre + (dur or 0.0) + post) / (every * self.step_s)
        if rows * len(signals) > MAX_VALUES:
            raise CaptureError(f"capture: {rows:.0f} rows of {len(signals)} signals are more "
                               f"than a capture holds ({MAX_VALUES:.0e} values)")
        with self._lock:
            live = [c for c in self._captures.values() if c.state != "done"]
            if len(live) >= MAX_CAPTURES:
                raise CaptureError(f"capture: {MAX_CAPTURES} captures armed or running at once "
                                   "at most")
            sources = {self._sources[n] for c in live for n in c.names} | \
                {self._sources[n] for n in signals}
            if len(sources) > int(self._lib.RT_CAPTURE_SIGNALS):
                raise CaptureError(f"capture: the captures running would need {len(sources)} "
                                   f"signals at once (the loop copies at most "
                                   f"{int(self._lib.RT_CAPTURE_SIGNALS)})")
            cid = self._next_id
            self._next_id += 1
            cap = _Capture(cid, list(signals), every, start_when, pre, stop_when, post, dur)
        faults = self.server.faults
        try:
            if start_when is not None:
                cap.start_watch = faults.watch(start_when)
            if stop_when is not None:
                cap.stop_watch = faults.watch(stop_when)
        except FaultError as e:
            self._free_watches(cap)
            raise CaptureError(f"capture: {e}") from None
        self._hold_ring()
        with self._lock:
            self._captures[cid] = cap
            self._configure()
        self.counts["started"] += 1
        self._ensure_thread()
        return cid

    def stop(self, cid: Any) -> None:
        """Ends a capture now (what it holds stays for fetch)."""
        with self._lock:
            cap = self._get(cid)
            if cap.state == "capturing":
                cap.stop_s = cap.end_s = cap.last_s()
            elif cap.state == "armed":
                cap.rows, cap.ticks, cap.times, cap.values = 0, [], [], []
            self._finish(cap, "stopped")

    def clear(self, cid: Any) -> None:
        """Ends a capture and frees what it holds."""
        with self._lock:
            cap = self._get(cid)
            if cap.state != "done":
                self._finish(cap, "cleared")
            del self._captures[cap.id]
        self.counts["cleared"] += 1

    def status(self, cid: Any) -> dict:
        with self._lock:
            cap = self._get(cid)
            return self._status(cap)

    def fetch(self, cid: Any) -> dict:
        """What a capture holds: ``tick``, ``time_s`` and ``values`` ({name: array}),
        with its ``status``."""
        with self._lock:
            cap = self._get(cid)
            n = len(cap.names)
            ticks = np.concatenate(cap.ticks) if cap.ticks else np.zeros(0, np.uint64)
            times = np.concatenate(cap.times) if cap.times else np.zeros(0)
            vals = np.concatenate(cap.values) if cap.values else np.zeros((0, n))
            if cap.state == "armed":           # the history is not the capture yet
                ticks, times, vals = ticks[:0], times[:0], vals[:0]
            return {"status": self._status(cap), "tick": ticks, "time_s": times,
                    "values": {name: vals[:, k].copy() for k, name in enumerate(cap.names)}}

    def ids(self) -> list[int]:
        with self._lock:
            return sorted(self._captures)

    def counters(self) -> dict:
        return {**self.counts, "dropped": int(self._loop.capture.dropped),
                "refused": int(self._loop.capture_refused),
                "live": sum(1 for c in self._captures.values() if c.state != "done")}

    def close(self) -> None:
        """Ends the reader (at the server's stop); captures keep what they hold."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        with self._lock:
            for cap in self._captures.values():
                if cap.state != "done":
                    if cap.state == "capturing":
                        cap.end_s = cap.last_s()
                    self._finish(cap, "the server stopped")

    # ------------------------------------------------------------ internals
    def _get(self, cid: Any) -> _Capture:
        if isinstance(cid, bool) or not isinstance(cid, int) or cid not in self._captures:
            raise CaptureError(f"no capture {cid!r}")
        return self._captures[cid]

    def _status(self, cap: _Capture) -> dict:
        return {"id": cap.id, "state": cap.state, "signals": list(cap.names),
                "every_s": cap.every * self.step_s, "pre_s": cap.pre_s, "post_s": cap.post_s,
                "armed_s": cap.armed_s, "trigger_s": cap.trigger_s, "stop_s": cap.stop_s,
                "end_s": cap.end_s, "rows": 0 if cap.state == "armed" else cap.rows,
                "history_s": (None if cap.trigger_s is None or cap.armed_s is None
                              else max(0.0, min(cap.pre_s, cap.trigger_s - cap.armed_s))),
                "gaps": cap.gaps, "why_done": cap.why_done}

    def _hold_ring(self) -> None:
        if not self._held:
            rc = int(self._lib.rt_loop_hold_rings(self._loop, self._lib.RT_RELEASE_CAPTURE))
            if rc != 0:
                raise CaptureError(f"capture: the capture ring cannot be locked in memory "
                                   f"(errno {-rc})")
            self._held = True

    def _free_watches(self, cap: _Capture) -> None:
        for wid in (cap.start_watch, cap.stop_watch):
            if wid is not None:
                try:
                    self.server.faults.clear(wid)
                except Exception:  # cleared already (clear_all)
                    pass
        cap.start_watch = cap.stop_watch = None

    def _finish(self, cap: _Capture, why: str) -> None:
        """Done (holding the lock): its watches freed, the loop's configuration without it."""
        cap.state = "done"
        cap.why_done = cap.why_done or why
        self._free_watches(cap)
        self._configure()
        self.counts["done"] += 1

    def _configure(self) -> None:
        """Publishes the union of the live captures' sources (holding the lock)."""
        lib, loop = self._lib, self._loop
        live = [c for c in self._captures.values() if c.state != "done"]
        sources: list[int] = []
        every = 0
        for c in live:
            every = math.gcd(every, c.every)
            for n in c.names:
                s = self._sources[n]
                if s not in sources:
                    sources.append(s)
        if sources == self._gen_sources.get(self._gen, []) and every == getattr(
                self, "_every", 0):
            return
        deadline = time.monotonic() + 1.0
        while int(lib.rt_capture_acked(loop)) != self._gen:   # the other slot is free
            if not self.server.running or time.monotonic() > deadline:
                break
            time.sleep(0.0005)
        gen = (self._gen + 1) & 0xFFFFFFFF
        cfg = loop.capture_cfg[gen & 1]
        cfg.n = len(sources)
        cfg.every = max(1, every)
        for k, s in enumerate(sources):
            cfg.source[k] = s
        self._gen_sources[gen] = sources
        self._gen = gen
        self._every = every
        lib.rt_capture_publish(loop, gen)

    def _ensure_thread(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="captures", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                n = self.drain()
            except Exception:  # the reader goes on; the captures say what they lack
                n = 0
            if n < len(self._buf) // 2:
                self._stop.wait(POLL_S)

    def _watch_time(self, wid: int | None) -> float | None:
        if wid is None:
            return None
        for f in self.server.faults.status():
            if f["id"] == wid:
                t = f["started_s"]
                return None if t is None or (isinstance(t, float) and math.isnan(t)) else float(t)
        return None

    def drain(self) -> int:
        """Takes the records waiting in the ring into the captures; returns how many."""
        n = int(self._lib.rt_capture_pop_many(self._ring, self._buf, len(self._buf)))
        dropped = int(self._loop.capture.dropped)
        lost = dropped - self._dropped_seen
        self._dropped_seen = dropped
        with self._lock:
            live = [c for c in self._captures.values() if c.state != "done"]
            if lost:
                for c in live:
                    c.gaps += lost
            if n:
                raw = self._ffi.buffer(self._buf, n * self._ffi.sizeof("rt_capture_record"))
                rec = np.frombuffer(raw, dtype=_record_dtype()).copy()
                self.counts["records"] += n
                for gen in np.unique(rec["gen"]):
                    sources = self._gen_sources.get(int(gen))
                    if sources is None:
                        continue
                    part = rec[rec["gen"] == gen]
                    for c in live:
                        self._take(c, part, sources)
                for g in [g for g in self._gen_sources if g != self._gen
                          and g != int(rec[-1]["gen"])]:
                    del self._gen_sources[g]
            for c in live:
                self._advance(c)
        return n

    def _take(self, c: _Capture, part: np.ndarray, sources: list[int]) -> None:
        try:
            cols = [sources.index(self._sources[name]) for name in c.names]
        except ValueError:
            return                              # a configuration from before it was armed
        rows = part[part["tick"] % np.uint64(c.every) == 0]
        if not len(rows):
            return
        if c.armed_s is None:
            c.armed_s = float(rows["time_s"][0])
        c.keep(rows["tick"].copy(), rows["time_s"].copy(), rows["values"][:, cols].copy())

    def _advance(self, c: _Capture) -> None:
        """Moves one capture on by its triggers (holding the lock)."""
        last = c.last_s()
        if c.state == "armed":
            if c.start_when is None:
                t = c.armed_s
            else:
                t = self._watch_time(c.start_watch)
            if t is None:
                if last is not None:
                    c.trim_before(last - c.pre_s - self.step_s)
                return
            c.trigger_s = t
            c.trim_before(t - c.pre_s - 1e-9)
            c.state = "capturing"
            if c.duration_s is not None:
                c.end_s = t + c.duration_s
        if c.state == "capturing":
            if c.stop_when is not None and c.stop_s is None:
                s = self._watch_time(c.stop_watch)
                if s is not None:
                    c.stop_s = s
                    end = s + c.post_s
                    c.end_s = end if c.end_s is None else min(c.end_s, end)
            if c.end_s is not None and last is not None and last >= c.end_s - 1e-9:
                c.trim_after(c.end_s + 1e-9)
                self._finish(c, "its end")
            elif c.rows >= MAX_SAMPLES or c.rows * len(c.names) >= MAX_VALUES:
                c.end_s = last
                self._finish(c, f"full ({c.rows} rows)")


_DTYPE: np.dtype | None = None


def _record_dtype() -> np.dtype:
    """numpy's view of rt_capture_record (checked against cffi's layout)."""
    global _DTYPE
    if _DTYPE is None:
        from rt_loop._rt_loop import ffi, lib

        n = int(lib.RT_CAPTURE_SIGNALS)
        t = ffi.typeof("rt_capture_record")
        f = dict(t.fields)
        _DTYPE = np.dtype({"names": ["tick", "time_s", "gen", "n", "values"],
                           "formats": ["<u8", "<f8", "<u4", "<u4", (np.float64, n)],
                           "offsets": [f[k].offset for k in ("tick", "time_s", "gen", "n",
                                                              "values")],
                           "itemsize": ffi.sizeof(t)})
    return _DTYPE
