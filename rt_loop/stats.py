"""Timing figures and counts of the real-time loop, as ControlDesk reports them.

The loop writes ``rt_stats`` every tick and never waits for a reader;
``StatsReader.read`` takes a consistent copy with ``rt_stats_read`` (a
sequence counter) into memory allocated once, so reading at 5 Hz costs no
allocation in the loop and little in Python.

Three times per tick, each with a histogram of 1 us bins (``RT_HIST_BINS``;
the last bin holds everything above):

* turnaround: deadline of the tick to its end (what ControlDesk calls
  turnaround time: the tick's work as seen from the time it was due);
* execution: wake-up to end (the work itself);
* wake-up latency: deadline to wake-up (the scheduler's share).

Percentiles come from the histograms by the nearest-rank rule and are
reported as the upper edge of their 1 us bin (never below the true value),
limited to the exact maximum the loop measured; ``max_us`` is that exact
maximum.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "PERCENTILES",
    "STATE_NAMES",
    "StatsReader",
    "hist_percentiles",
]

#: (percent, key) of the figures reported for every time
PERCENTILES = ((50.0, "p50_us"), (90.0, "p90_us"), (99.0, "p99_us"), (99.9, "p99_9_us"))

#: RT_STATE_* -> name
STATE_NAMES = {0: "idle", 1: "running", 2: "stopped", 3: "overrun_stop", 4: "error"}

#: (key, rt_stats field of the histogram, field of the last value, of the maximum)
TIMES = (
    ("turnaround", "turnaround_hist", "turnaround_us", "turnaround_max_us"),
    ("execution", "exec_hist", "exec_us", "exec_max_us"),
    ("wakeup_latency", "latency_hist", "latency_us", "latency_max_us"),
)

# rt_stats counters -> key in counts()["rx"] / ["tx"]
_RX_COUNTS = (("frames", "rx_frames"), ("accepted", "rx_accepted"),
              ("unknown_id", "rx_unknown_id"), ("bad_length", "rx_bad_length"),
              ("bad_crc", "rx_bad_crc"), ("bad_counter", "rx_bad_counter"),
              ("overflow", "rx_overflow"))
_TX_COUNTS = (("frames", "tx_frames"), ("dropped", "tx_dropped"))


def hist_percentiles(hist: np.ndarray, max_us: float) -> dict:
    """p50/p90/p99/p99.9 and max (us) of a histogram of 1 us bins.

    Bin ``i`` holds [i, i+1) us, the last bin everything above its lower
    edge. A percentile is the upper edge of the bin holding the nearest-rank
    sample, limited to ``max_us``; in the last bin it is ``max_us``. With no
    samples every figure is None.
    """
    hist = np.asarray(hist, dtype=np.uint64)
    total = int(hist.sum())
    out: dict[str, Any] = {"samples": total}
    if total == 0:
        out.update({key: None for _, key in PERCENTILES})
        out["max_us"] = None
        return out
    cum = np.cumsum(hist)
    last = len(hist) - 1
    for pct, key in PERCENTILES:
        rank = max(1, math.ceil(pct * total / 100.0 - 1e-9))  # 99.9 % of 1000 is 999
        i = int(np.searchsorted(cum, rank, side="left"))
        value = float(max_us) if i >= last else min(float(i + 1), float(max_us))
        out[key] = value
    out["max_us"] = float(max_us)
    return out


def sparse_hist(hist: np.ndarray) -> list[list[int]]:
    """[[bin_us, count], ...] of the non-empty bins."""
    nz = np.flatnonzero(hist)
    return [[int(i), int(hist[i])] for i in nz]


class StatsReader:
    """Consistent copies of a running loop's ``rt_stats``.

    ``read()`` refreshes ``copy`` (an ``rt_stats *`` owned by the reader) and
    returns it; when the loop kept writing through every retry of
    ``rt_stats_read`` the previous copy is kept and ``read_failures`` counts
    it. ``timing()``, ``counts()`` and ``plant()`` describe the last copy.
    ``channels`` (``rt_loop.channels.LoopChannels``) names the buses,
    messages and command values of the loop's numbering.
    """

    def __init__(self, ffi: Any, lib: Any, loop: Any, channels: Any) -> None:
        self._ffi, self._lib, self._loop = ffi, lib, loop
        self._work = ffi.new("rt_stats *")
        self.copy = ffi.new("rt_stats *")
        self._size = ffi.sizeof("rt_stats")
        self._hists = {
            key: np.frombuffer(ffi.buffer(getattr(self.copy, field)), dtype=np.uint64)
            for key, field, _, _ in TIMES
        }
        names = channels.message_names()
        #: received messages the mapping marks optional (a TCU may leave them out)
        self.optional = {names[i] for i, (_, m) in enumerate(channels.messages)
                         if m.direction == "receive" and getattr(m, "optional", False)}
        self.buses = list(channels.buses)
        #: (index in rt_stats.msgs, name) of the received and of the sent messages
        self.rx_messages = [(i, names[i]) for i, (_, m) in enumerate(channels.messages)
                            if m.direction == "receive"]
        self.tx_messages = [(i, names[i]) for i, (_, m) in enumerate(channels.messages)
                            if m.direction == "send"]
        #: {received message: (its cycle, the loop's timeout of it), ms of model time}:
        #: timed out after timeout_cycles cycles of silence (RT_TIMEOUT_CYCLES when unset)
        self.rx_timing = {names[i]: (float(m.cycle_ms), float(m.cycle_ms) * float(
            m.timeout_cycles or lib.RT_TIMEOUT_CYCLES))
            for i, (_, m) in enumerate(channels.messages) if m.direction == "receive"}
        self.command_names = list(channels.command_names)
        self.read_failures = 0
        self.reads = 0

    def read(self) -> Any:
        if self._lib.rt_stats_read(self._loop, self._work) == 0:
            self._ffi.memmove(self.copy, self._work, self._size)
            self.reads += 1
        else:
            self.read_failures += 1
        return self.copy

    # -- views of the last copy
    @property
    def state(self) -> str:
        return STATE_NAMES.get(int(self.copy.state), f"state {int(self.copy.state)}")

    def timing(self, histograms: bool = False) -> dict:
        """{"turnaround": {...}, "execution": {...}, "wakeup_latency": {...}}."""
        s = self.copy
        out = {}
        for key, _, last, peak in TIMES:
            fig = hist_percentiles(self._hists[key], getattr(s, peak))
            fig["last_us"] = float(getattr(s, last))
            if histograms:
                fig["histogram"] = sparse_hist(self._hists[key])
            out[key] = fig
        return out

    def counts(self) -> dict:
        """Every counter of the loop, as plain ints."""
        s = self.copy
        rx = {key: int(getattr(s, field)) for key, field in _RX_COUNTS}
        rx["rejected"] = rx["unknown_id"] + rx["bad_length"] + rx["bad_crc"] + rx["bad_counter"]
        tcu = {}
        for i, name in self.rx_messages:
            m = s.msgs[i]
            tcu[name] = {"accepted": int(m.frames), "bad_length": int(m.bad_length),
                         "bad_crc": int(m.bad_crc), "bad_counter": int(m.bad_counter),
                         "timeouts": int(m.timeouts), "timed_out": bool(m.timed_out),
                         "optional": name in self.optional,
                         "cycle_ms": self.rx_timing[name][0], "timeout_ms": self.rx_timing[name][1]}
        plant = {name: {"sent": int(s.msgs[i].frames), "dropped": int(s.msgs[i].dropped),
                        "saturated": int(s.msgs[i].saturated)}
                 for i, name in self.tx_messages}
        channels = {}
        for k, bus in enumerate(self.buses):
            c = s.chan[k]
            crx = {key: int(getattr(c, field)) for key, field in _RX_COUNTS}
            crx["rejected"] = (crx["unknown_id"] + crx["bad_length"] + crx["bad_crc"]
                               + crx["bad_counter"])
            channels[bus] = {"rx": crx,
                             "tx": {key: int(getattr(c, field)) for key, field in _TX_COUNTS}}
        return {
            "ticks": int(s.ticks),
            "overruns": int(s.overruns),
            "skipped_ticks": int(s.skipped_ticks),
            "rx": rx,
            "tx": {**{key: int(getattr(s, field)) for key, field in _TX_COUNTS},
                   "saturated": sum(m["saturated"] for m in plant.values())},
            "tcu_messages": tcu,
            "plant_messages": plant,
            "channels": channels,
            "timeouts": sum(m["timeouts"] for m in tcu.values()),
        }

    def commands(self) -> dict:
        """{name: value} of the received values as applied in the last tick."""
        c = self.copy.commands
        return {name: float(c[i]) for i, name in enumerate(self.command_names)}

    def plant(self) -> dict:
        """Key plant signals and the commands applied in the last tick (the
        solenoid currents as the plant applied them; a torque request the
        mapping does not carry is None)."""
        o = self.copy.outputs
        cmd = self.commands()
        syncs = [(int(round(getattr(o, f"sync{i}_state"))), int(round(getattr(o, f"sync{i}_gear"))))
                 for i in range(1, 5)]
        return {
            "engine_speed_rpm": float(o.engine_speed_rpm),
            "vehicle_speed_kmh": float(o.vehicle_speed_kmh),
            "gear": int(round(o.gear)),
            "accel_pedal_pct": float(o.accel_pedal_pct),
            "brake_pedal_pct": float(o.brake_pedal_pct),
            "clutch1_pressure_bar": float(o.clutch1_pressure_bar),
            "clutch2_pressure_bar": float(o.clutch2_pressure_bar),
            "line_pressure_bar": float(o.line_pressure_bar),
            "sync_state": [state for state, _ in syncs],
            "sync_gear": [gear for _, gear in syncs],
            "solenoid_current1_a": float(o.solenoid_current1_a),
            "solenoid_current2_a": float(o.solenoid_current2_a),
            "line_solenoid_current_a": float(o.line_solenoid_current_a),
            "engine_torque_request_nm": cmd.get("engine_torque_request_nm"),
            "torque_request_active": cmd.get("torque_request_active"),
            "commands": cmd,
        }
