"""The server's reports: what the running loop and the finished run show.

``snapshot`` is the live status (a consistent copy of the loop's figures,
read as often as the status line or the live view asks); ``report`` is
everything for the JSON stats file (``write_report``): the configuration
(``config``), the run, the timing, the counts, the rings, the transports'
and the XCP slave's counters, the plant and the faults, the machine.
"""

from __future__ import annotations

import json
import os
import time

from plant.machine import machine_info

__all__ = ["MANEUVER_STATES", "ReportsMixin"]

#: RT_MANEUVER_* -> name
MANEUVER_STATES = {0: "none", 1: "waiting for the TCU", 2: "running", 3: "done"}


class ReportsMixin:
    """``Server``'s part that reads the loop and reports on it.

    Reads the server's loop (``_lib``, ``_l``), its statistics (``stats``,
    under ``_read_lock``), ``transports``, ``logger``, ``recorder``, ``xcp``,
    ``player``, ``faults``, the settings ``config`` lists, and the run's
    times and error (``_t_start``, ``_t_end``, ``_loop_error``); ``_rings``
    holds the ring figures ``snapshot`` samples.
    """

    @property
    def state(self) -> str:
        """idle, running, stopped, overrun_stop or error (of the last read)."""
        return self.stats.state

    def snapshot(self) -> dict:
        """A consistent copy of the loop's figures, as plain Python values.

        Keys: state, sim_time_s, the last and largest turnaround_us, exec_us
        and latency_us (``*_max_us``), counts (``StatsReader.counts`` plus
        ``log`` and, for the bridge, ``bridge``) and plant (key signals and
        the commands applied, ``StatsReader.plant``).
        """
        with self._read_lock:
            return self._snapshot()

    def _snapshot(self) -> dict:
        s = self.stats.read()
        self._sample_rings()
        return {
            "state": self.stats.state,
            "sim_time_s": float(s.sim_time_s),
            "maneuver": MANEUVER_STATES.get(int(s.maneuver_state), "?"),
            "maneuver_time_s": float(s.maneuver_time_s) if s.maneuver_time_s >= 0 else None,
            "turnaround_us": float(s.turnaround_us),
            "turnaround_max_us": float(s.turnaround_max_us),
            "exec_us": float(s.exec_us),
            "exec_max_us": float(s.exec_max_us),
            "latency_us": float(s.latency_us),
            "latency_max_us": float(s.latency_max_us),
            "counts": self._counts(),
            "plant": self.stats.plant(),
            "faults": {"active": int(s.fault_mask).bit_count(),
                       "changes": int(s.fault_changes)},
        }

    def _counts(self) -> dict:
        counts = self.stats.counts()
        counts["log"] = {"written": 0 if self.logger is None else self.logger.written,
                         "dropped": int(self._l.log.dropped)}
        bridges = [t for t in self.transports if not t.hard_real_time]
        bridge = _sum_counters([t.counters for t in bridges])
        counts["bridge"] = bridge
        for t, ch in zip(self.transports, counts["channels"].values()):
            ch["channel"] = t.channel
            if not t.hard_real_time and len(self.transports) > 1:
                ch["bridge"] = {k: v for k, v in t.counters.items() if k != "last_error"}
        # frames lost: those the loop counted (a full ring, or the kernel's drops of
        # the SocketCAN socket) and those lost below the bridge (the kernel's drops of
        # the bus's UDP socket); controller overflows are events of unknown size
        rx = counts["rx"]
        rx["lost_below_bridge"] = int(bridge.get("rx_kernel_drops") or 0)
        rx["lost"] = rx["overflow"] + rx["lost_below_bridge"]
        rx["overflow_events"] = int(bridge.get("rx_overflow_events") or 0)
        counts["record"] = {"written": 0 if self.recorder is None else self.recorder.written,
                            "dropped": int(self._l.rec.dropped)}
        return counts

    def _sample_rings(self) -> None:
        """Notes how many frames wait in the bridge's rings now (rx: for the loop, tx:
        for the bridge thread): a frame waits there while the other side is late."""
        if not self.running or all(t.hard_real_time for t in self.transports):
            return
        size = self._lib.RT_RING_SIZE
        for i, t in enumerate(self.transports):
            if t.hard_real_time:
                continue
            for name in ("rx", "tx"):
                ring = getattr(self._l, name)[i]
                waiting = (int(ring.head) - int(ring.tail)) & 0xFFFFFFFF
                if waiting <= size:              # head and tail are read one after the other
                    key = f"{name}_waiting_max"
                    self._rings[key] = max(self._rings[key], waiting)
        self._rings["samples"] += 1

    def memory_report(self) -> dict:
        """The process's memory (MB, /proc/self/status): VmRSS and VmLck at the first tick
        (the run's locked memory), VmHWM (peak resident) now; with mlockall (priority > 0)
        every page mapped is resident, docs/server.md "Memory"."""
        from rt_loop.server.startup import process_memory

        first = (self.startup or {}).get("memory_at_first_tick") or {}
        now = process_memory()
        return {"vm_rss_mb": first.get("vm_rss_mb"), "vm_lck_mb": first.get("vm_lck_mb"),
                "vm_hwm_mb": now.get("vm_hwm_mb"), "locked": bool(self.lock_memory)}

    def rings_report(self) -> dict | None:
        """The most frames seen waiting in the bridge's rx and tx rings at a status read
        (``snapshot``), and how many reads there were; None without a bridge. A sampled
        figure: frames that waited between two reads are not seen."""
        if not self.transports or all(t.hard_real_time for t in self.transports):
            return None
        return {**self._rings, "size": int(self._lib.RT_RING_SIZE)}

    def xcp_counters(self) -> dict | None:
        """The XCP slave's counters and the loop's side (DTOs lost in a full ring,
        DAQ configurations refused, calibration writes applied and refused); None
        without XCP."""
        if self.xcp is None:
            return None
        loop = self._l
        return {**self.xcp.counters(),
                "loop": {"dto_ring_dropped": int(loop.daq_ring.dropped),
                         "daq_configurations_refused": int(loop.daq_refused),
                         "cal_applied": int(loop.cal.applied),
                         "cal_refused": int(loop.cal.refused)}}

    def transport_counters(self) -> dict:
        """The transports' own counters: the first bus's, or with several buses
        their sums (``counts.channels`` has each bus's)."""
        if len(self.transports) == 1:
            return self.transports[0].counters
        return _sum_counters([t.counters for t in self.transports])

    def _control_config(self) -> dict | None:
        """The control channel's doors (the TCP port bound once it runs)."""
        if self.control_path is None and self.control_tcp is None:
            return None
        tcp = self.control_tcp
        if self.control is not None and self.control.tcp_address is not None:
            tcp = self.control.tcp_address
        return {"socket": self.control_path,
                "tcp": None if tcp is None else f"{tcp[0]}:{tcp[1]}",
                "token": self.control_token is not None, "tls": self.control_tls is not None}

    def config(self) -> dict:
        s = self.stats.copy
        t = self.transport
        return {
            "rate_hz": self.rate_hz,
            "step_us": self.step_s * 1e6,
            "time_scale": self.time_scale,
            "period_us": self.period_s * 1e6,
            "priority": self.priority,
            "cpu": self.cpu,
            "lock_memory": self.lock_memory,
            "overrun_policy": self.overrun_policy,
            "spin_us": self.spin_us,
            "pm_qos": None if self.pm_qos is None else self.pm_qos.report(),
            "duration_s": self.duration_s,
            "transport": None if t is None else t.kind,
            "real_time": None if t is None else ("hard" if t.hard_real_time else "soft"),
            "interface": None if t is None else t.interface,
            "interface_chosen_because": None if t is None else t.chosen_because,
            "channel": self.channel,
            "mapping": self.mapping.path,
            "buses": [{"name": b.name, "channel": self.bus_channels[b.name],
                       "dbc": b.dbc, "bitrate": b.bitrate, "fd": b.fd,
                       "transport": None if i >= len(self.transports) else self.transports[i].kind,
                       "sends": [m.name for m in self.mapping.messages
                                 if m.bus == b.name and m.direction == "send"],
                       "receives": [m.name for m in self.mapping.messages
                                    if m.bus == b.name and m.direction == "receive"]}
                      for i, b in enumerate(self.mapping.buses)],
            "commands": list(self.channels.command_names),
            "xcp": None if self.xcp_address is None else {
                "protocol": self.xcp_protocol,
                "address": list(self.xcp.address) if self.xcp is not None else list(self.xcp_address),
                "seed_and_key": self.xcp_key is not None},
            "control": self._control_config(),
            "params": self.params_path,
            "hydraulics": "solenoid currents (pressure_commanded = 0)",
            "log": self.log_path,
            "record": self.record_path,
            "record_every_s": self.record_every * self.step_s if self.record_path else None,
            "driver_rows": len(self.driver_rows),
            "maneuver_start": self.maneuver_start if self.driver_rows else None,
            "maneuver_end_s": self.maneuver_end_s,
            "rt_policy_ok": bool(s.rt_policy_ok),
            "memory_locked": bool(s.memory_locked),
            "affinity_ok": bool(s.affinity_ok) if self.cpu is not None else None,
        }

    def report(self, histograms: bool = True) -> dict:
        """Everything for the JSON stats file (reads the statistics once more)."""
        with self._read_lock:
            return self._report(histograms)

    def _report(self, histograms: bool) -> dict:
        s = self.stats.read()
        machine = machine_info()
        end = self._t_end if self._t_end is not None else time.monotonic()
        wall_s = (end - self._t_start) if self._t_start is not None else 0.0
        error = None
        if self._loop_error:
            error = self._loop_error
        elif int(s.state) == self._lib.RT_STATE_ERROR and int(s.error) < 0:
            error = (f"the plant core stopped the loop (dct_plant_step status {-int(s.error)}: "
                     "a value that is not finite)")
        elif int(s.state) == self._lib.RT_STATE_ERROR:
            error = f"transport error: {os.strerror(int(s.error))} (errno {int(s.error)})"
        timing = self.stats.timing(histograms=histograms)
        return {
            "date": machine.pop("date"),
            "config": self.config(),
            "run": {
                "state": self.stats.state,
                "error": error,
                "wall_s": wall_s,
                "sim_time_s": float(s.sim_time_s),
                "maneuver": MANEUVER_STATES.get(int(s.maneuver_state), "?"),
                "maneuver_time_s": float(s.maneuver_time_s) if s.maneuver_time_s >= 0 else None,
                "ticks": int(s.ticks),
                "start_to_first_tick_s": (self.startup or {}).get("start_to_first_tick_s"),
                "process_to_first_tick_s": (self.startup or {}).get("process_to_first_tick_s"),
                "warnings": list(self.warnings),
                "stats_read_failures": self.stats.read_failures,
            },
            "turnaround": timing["turnaround"],
            "execution": timing["execution"],
            "wakeup_latency": timing["wakeup_latency"],
            "histogram_bin_us": 1,
            "counts": self._counts(),
            "rings": self.rings_report(),
            "transport": {key: value for key, value in self.transport_counters().items()},
            "log": self.logger.counters() if self.logger is not None else None,
            "record": self.recorder.counters() if self.recorder is not None else None,
            "xcp": self.xcp_counters(),
            "stimulus": None if self.player is None else {
                "file": self.stimulus.path if hasattr(self.stimulus, "path") else None,
                "start": self.stimulus_start, **self.player.counters()},
            "plant": self.stats.plant(),
            "faults": self.faults.report(s),
            "memory": self.memory_report(),
            "machine": machine,
        }

    def write_report(self, path: str | os.PathLike, report: dict | None = None) -> dict:
        """Writes ``report`` (default: ``report()``) as the JSON stats file; returns it."""
        report = self.report() if report is None else report
        path = os.fspath(path)
        folder = os.path.dirname(os.path.abspath(path))
        os.makedirs(folder, exist_ok=True)
        tmp = f"{path}.tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
        return report


def _sum_counters(counters: list[dict]) -> dict:
    """Counters of several transports added up key by key (numbers and dicts of
    numbers; anything else is the first's). ``last_error`` is left out."""
    out: dict = {}
    for c in counters:
        for key, value in c.items():
            if key == "last_error":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, dict)):
                out.setdefault(key, value)
            elif isinstance(value, dict):
                d = out.setdefault(key, {})
                for k, v in value.items():
                    d[k] = d.get(k, 0) + v if isinstance(v, (int, float)) else v
            elif key in out and isinstance(out[key], (int, float)):
                out[key] += value
            else:
                out[key] = value
    return out
