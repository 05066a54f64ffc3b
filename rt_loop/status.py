"""What ``dct-hil serve`` prints: start-up banner, live status, exit summary.

The live status is one screen redrawn in place (ANSI cursor movement) about
5 times per second when the output is a terminal; otherwise (a pipe, a log
file, a service manager) one line per second, so unattended runs leave a
readable record.
"""

from __future__ import annotations

import shutil
from typing import Any, TextIO

__all__ = ["LiveStatus", "banner_lines", "screen_lines", "status_line", "summary_lines"]

SLEEVES = ("1/3", "2/4", "5/R", "6/N")
_CSI = "\x1b["


def _z(x: float, digits: int = 2) -> float:
    """``x`` rounded for display, without a minus sign on zero."""
    return round(x, digits) + 0.0


def _gear(gear: int) -> str:
    return {0: "-", -1: "R"}.get(gear, str(gear))


def _engaged(plant: dict) -> str:
    gears = [_gear(g) for s, g in zip(plant["sync_state"], plant["sync_gear"]) if s == 2 and g]
    return ",".join(gears) if gears else "none"


def _timed_out(counts: dict) -> list[str]:
    return [name for name, m in counts["tcu_messages"].items() if m["timed_out"]]


def banner_lines(server: Any, stats_path: str) -> list[str]:
    t = server.transport
    lines = [f"dct-hil serve     {t.describe()}"]
    if t.chosen_because:
        lines.append(f"interface         {t.interface} (default: {t.chosen_because})")
    if server.priority:
        sched = f"SCHED_FIFO {server.priority}" + (" + mlockall" if server.lock_memory else "")
    else:
        sched = "normal scheduling (priority 0)"
    cpu = "any CPU" if server.cpu is None else f"CPU {server.cpu}"
    policy = {"skip": "overruns counted and skipped", "stop": "stop at the first overrun"}
    until = (f"for {server.duration_s:g} s" if server.duration_s is not None
             else "until Ctrl-C or SIGTERM")
    lines.append(f"loop              {server.rate_hz:g} Hz (period {server.period_s * 1e6:g} us), "
                 f"{sched}, {cpu}, {policy[server.overrun_policy]}, {until}")
    if server.time_scale != 1.0:
        lines.append(f"time scale        {server.time_scale:g}: a {server.step_s * 1e6:g} us plant "
                     f"step every {server.period_s * 1e6:g} us, bus cycles "
                     f"{1 / server.time_scale:g}x longer (slow motion, not real time)")
    if server.driver_rows:
        start = {"tcu": "at the first TCU frame", "now": "at once"}[server.maneuver_start]
        end = (f", ends at {server.maneuver_end_s:g} s" if server.maneuver_end_s is not None
               else "")
        lines.append(f"driver            pedal table of {len(server.driver_rows)} rows, starts "
                     f"{start}{end}")
    q = getattr(server, "pm_qos", None)
    lines.append("PM QoS            " + (f"off ({getattr(server, 'pm_qos_off_because', None)})"
                                        if q is None else q.describe()))
    lines.append(f"plant             {server.params_path or 'default parameters'}; "
                 "solenoid currents drive the clutch hydraulics")
    m = getattr(server, "mapping", None)
    if m is not None and len(getattr(server, "transports", [])) > 1:
        lines.append("buses             " + ", ".join(
            f"{b.name} on {server.bus_channels[b.name]}" for b in m.buses))
    x = getattr(server, "xcp", None)
    if x is not None:
        host, port = x.address
        lines.append(f"XCP               on {x.protocol.upper()} {host}:{port} (A2L on GET_ID"
                     + (", seed & key" if server.xcp_key else "") + ")")
    c = getattr(server, "control", None)
    if c is not None:
        doors = [f"socket {c.path}"] if c.path else []
        if c.tcp_address is not None:
            host, port = c.tcp_address
            doors.append(f"{'tls' if c.tls else 'tcp'}://{host}:{port}"
                         + (" (token)" if c.token else ""))
        lines.append(f"control           {', '.join(doors)}")
    if server.logger is not None:
        lines.append(f"log               {server.logger.path} ({server.logger.format})")
    if server.recorder is not None:
        lines.append(f"recording         {server.recorder.path} (every "
                     f"{server.record_every * server.step_s * 1e3:g} ms of plant time)")
    lines.append(f"stats             {stats_path} (written on exit)")
    return lines


def _short(name: str) -> str:
    return name.removeprefix("TCU_")


def _torque_request(p: dict) -> str:
    nm, active = p.get("engine_torque_request_nm"), p.get("torque_request_active")
    if nm is None:
        return "not in the mapping"
    return f"{nm:.0f} Nm {'on' if active else 'off'}"


def screen_lines(snap: dict, server: Any = None) -> list[str]:
    """The live status as a screen of lines (each under 80 columns for usual figures)."""
    c, p = snap["counts"], snap["plant"]
    rx, tx = c["rx"], c["tx"]
    sleeves = "   ".join(
        f"{name} " + ({0: "-", 1: "sync"}.get(s, "in") + (f" {_gear(g)}" if s and g else ""))
        for name, s, g in zip(SLEEVES, p["sync_state"], p["sync_gear"]))
    maneuver = ""
    if snap.get("maneuver", "none") != "none":
        mt = snap.get("maneuver_time_s")
        maneuver = f"   maneuver {snap['maneuver']}" + (f" {mt:.2f} s" if mt is not None else "")
    lines = [
        f"t {snap['sim_time_s']:.2f} s   {snap['state']}   ticks {c['ticks']}{maneuver}",
        f"turnaround  {snap['turnaround_us']:.1f} us (max {snap['turnaround_max_us']:.1f})   "
        f"exec {snap['exec_us']:.1f} ({snap['exec_max_us']:.1f})   "
        f"wake-up {snap['latency_us']:.1f} ({snap['latency_max_us']:.1f})",
        f"overruns    {c['overruns']} (skipped ticks {c['skipped_ticks']})",
        f"rx          {rx['frames']} frames, {rx['accepted']} accepted, {rx['rejected']} rejected "
        f"(id {rx['unknown_id']} len {rx['bad_length']} crc {rx['bad_crc']} ctr "
        f"{rx['bad_counter']}), {rx.get('lost', rx['overflow'])} lost",
        f"tx          {tx['frames']} frames, {tx['dropped']} dropped",
        "timeouts    " + "   ".join(
            f"{_short(name)} {m['timeouts']}{' TIMED OUT' if m['timed_out'] else ''}"
            for name, m in c["tcu_messages"].items()),
        f"engine      {p['engine_speed_rpm']:.0f} rpm, torque request {_torque_request(p)}"
        f"   vehicle {_z(p['vehicle_speed_kmh'], 1):.1f} km/h",
        f"clutches    K1 {_z(p['clutch1_pressure_bar']):.2f} bar "
        f"{p['solenoid_current1_a']:.2f} A   "
        f"K2 {_z(p['clutch2_pressure_bar']):.2f} bar {p['solenoid_current2_a']:.2f} A   "
        f"line {_z(p['line_pressure_bar']):.2f} bar {p['line_solenoid_current_a']:.2f} A",
        f"sleeves     {sleeves}   driving gear {p.get('gear', 0)}",
    ]
    bridge = c.get("bridge")
    if bridge:
        lines.append(f"bridge      {bridge['rx_forwarded']} in, {bridge['tx_forwarded']} out, "
                     f"ring full {bridge['rx_ring_full']}, bus errors {bridge['rx_errors']}"
                     f"/{bridge['tx_errors']}, error frames {bridge['rx_error_frames']}")
    if server is not None and server.logger is not None:
        lines.append(f"log         {c['log']['written']} frames written, "
                     f"{c['log']['dropped']} lost")
    if server is not None and server.recorder is not None:
        lines.append(f"recording   {c['record']['written']} samples written, "
                     f"{c['record']['dropped']} lost")
    f = snap.get("faults")
    if f and (f["active"] or f["changes"]):
        lines.append(f"faults      {f['active']} active, {f['changes']} starts and ends")
    return lines


def status_line(snap: dict) -> str:
    """The live status as one line (output that is not a terminal)."""
    c, p = snap["counts"], snap["plant"]
    rx, tx = c["rx"], c["tx"]
    late = _timed_out(c)
    bridge = c.get("bridge")
    extra = ""
    if bridge:
        extra = (f" | bridge ring full {bridge['rx_ring_full']} bus errors "
                 f"{bridge['rx_errors'] + bridge['tx_errors']}")
    mt = snap.get("maneuver_time_s")
    maneuver = f" maneuver {mt:.1f}s" if mt is not None else ""
    return (f"t={snap['sim_time_s']:.1f}s{maneuver} {snap['state']} turnaround {snap['turnaround_us']:.1f}us "
            f"max {snap['turnaround_max_us']:.1f}us overruns {c['overruns']} | rx {rx['frames']} "
            f"rejected {rx['rejected']} lost {rx.get('lost', rx['overflow'])} tx {tx['frames']} dropped "
            f"{tx['dropped']} | timeouts {c['timeouts']}"
            + (f" (timed out: {','.join(late)})" if late else "")
            + f" | engine {p['engine_speed_rpm']:.0f}rpm {_z(p['vehicle_speed_kmh'], 1):.1f}km/h "
            f"K1 {_z(p['clutch1_pressure_bar']):.2f} K2 {_z(p['clutch2_pressure_bar']):.2f} "
            f"line {_z(p['line_pressure_bar']):.2f}bar gears {_engaged(p)} driving "
            f"{p.get('gear', 0)}" + extra
            + (f" | faults {snap['faults']['active']} active"
               if snap.get("faults", {}).get("active") else ""))


class LiveStatus:
    """Redraws the status in place on a terminal, else prints a line per update."""

    def __init__(self, out: TextIO, quiet: bool = False, tty: bool | None = None) -> None:
        self.out = out
        self.quiet = quiet
        if tty is None:
            try:
                tty = out.isatty()
            except (AttributeError, ValueError):
                tty = False
        self.tty = bool(tty)
        #: how often update() should be called
        self.interval_s = 0.2 if self.tty else 1.0
        self._drawn = 0

    def update(self, snap: dict, server: Any = None) -> None:
        if self.quiet:
            return
        try:
            self._draw(snap, server)
        except OSError:   # the reader went away (a closed pipe): the server goes on
            self.quiet = True

    def _draw(self, snap: dict, server: Any) -> None:
        if not self.tty:
            print(status_line(snap), file=self.out, flush=True)
            return
        # a line wider than the terminal wraps and the redraw would drift: cut it
        width = max(20, shutil.get_terminal_size((100, 24)).columns - 1)
        lines = [line[:width] for line in screen_lines(snap, server)]
        text = f"{_CSI}{self._drawn}F" if self._drawn else ""
        text += "".join(f"{line}{_CSI}K\n" for line in lines) + f"{_CSI}J"
        self.out.write(text)
        self.out.flush()
        self._drawn = len(lines)

    def close(self) -> None:
        """Leaves the last screen in place; the summary follows below it."""
        if self._drawn:
            self.out.write("\n")
            self.out.flush()


def _fig(x: Any) -> str:
    return "       -" if x is None else f"{x:8.1f}"


def _lost(rx: dict) -> str:
    """Frames lost, with their causes (the bridge's counts when there is one)."""
    lost, below = rx.get("lost", rx["overflow"]), rx.get("lost_below_bridge", 0)
    text = f"{lost} lost"
    if below:
        text += f" ({rx['overflow']} to a full ring, {below} dropped by the kernel below the bridge)"
    elif lost:
        text += " to overflow"
    events = rx.get("overflow_events", 0)
    if events:
        text += f", and {events} controller overflows (frames lost: unknown)"
    return text


def _below_bridge_lines(b: dict) -> list[str]:
    """What the bridge learnt about losses below it (summary lines)."""
    lines = []
    if b.get("udp_sockets"):
        size = ("the kernel's default" if b.get("rcvbuf_bytes") is None
                else f"{b['rcvbuf_bytes'] // 1024} KiB (about {b['rcvbuf_frames']} frames)")
        drops = (f"{b['rx_kernel_drops']} frames dropped by the kernel"
                 if b.get("kernel_drops_counted") else "the kernel's drops could NOT be read")
        lines.append(f"below the bridge  UDP receive buffer {size}: {drops}")
    kinds = b.get("error_frame_kinds") or {}
    if kinds:
        lines.append("error frames      " + ", ".join(f"{k} {n}" for k, n in kinds.items())
                     + f" (controller overflows: {b.get('rx_overflow_events', 0)} receive, "
                     f"{b.get('tx_overflow_events', 0)} send; frames lost each: unknown)")
    if b.get("bus_state") is not None:
        moves = b.get("bus_state_transitions") or {}
        lines.append(f"bus state         {b['bus_state']} at the end; {b.get('bus_state_changes', 0)} "
                     "changes" + (" (" + ", ".join(f"{k} {n}" for k, n in moves.items()) + ")"
                                  if moves else ""))
    if b.get("backend_overruns"):
        lines.append(f"interface         {b['backend_overruns']} overruns reported by the backend "
                     "(frames lost each: unknown)")
    late = b.get("rx_left_in_ring", 0) + b.get("rx_drained_at_stop", 0)
    if late:
        lines.append(f"after the loop    {late} frames arrived too late to be read "
                     f"({b.get('rx_left_in_ring', 0)} in the ring, "
                     f"{b.get('rx_drained_at_stop', 0)} read from the bus at stop)")
    return lines


def summary_lines(report: dict, stats_path: str) -> list[str]:
    from rt_loop.verdict import verdict_lines

    run, cfg, c = report["run"], report["config"], report["counts"]
    rx, tx = c["rx"], c["tx"]

    def timeouts(name: str, m: dict) -> str:
        # a message never received was timed out from the start: no timeout event
        if m.get("accepted") == 0:
            return f"{name} never received" + (" (optional)" if m.get("optional") else "")
        n = m["timeouts"]
        if not n:
            return f"{name} 0"
        return (f"{name} timed out {'once' if n == 1 else f'{n} times'}"
                + (", still timed out at the end" if m["timed_out"] else ", came back"))

    messages = c["tcu_messages"]
    needed = [m for m in messages.values() if not m.get("optional")]
    if needed and all(m.get("accepted") == 0 for m in needed):
        tcu = "none: no TCU frame received (every TCU message timed out from the start)"
    else:
        tcu = "; ".join(timeouts(name, m) for name, m in messages.items())
    lines = [
        f"run               {run['state']}: {run['wall_s']:.3f} s, {run['ticks']} ticks at "
        f"{cfg['rate_hz']:g} Hz, {run['sim_time_s']:.3f} s simulated; {cfg['real_time']} real "
        f"time over {cfg['transport']}"
        + ("" if cfg["rt_policy_ok"] and cfg["memory_locked"] else " (timing not real time)"),
    ]
    if run.get("start_to_first_tick_s") is not None:
        mem = report.get("memory") or {}
        since = run.get("process_to_first_tick_s")
        lines.append(
            f"start-up          first tick {run['start_to_first_tick_s']:.2f} s after start"
            + (f" ({since:.2f} s after the process started)" if since is not None else "")
            + (f"; {mem['vm_rss_mb']:.0f} MB resident, {mem['vm_lck_mb']:.0f} MB locked"
               if mem.get("vm_rss_mb") is not None and mem.get("vm_lck_mb") is not None else ""))
    lines.append("timing (us)            p50      p90      p99    p99.9      max")
    for key, label in (("turnaround", "turnaround"), ("execution", "execution"),
                       ("wakeup_latency", "wake-up latency")):
        f = report[key]
        figures = (_fig(f[k]) for k in ("p50_us", "p90_us", "p99_us", "p99_9_us", "max_us"))
        lines.append(f"  {label:<16}" + " ".join(figures))
    lines += [
        f"overruns          {c['overruns']} (skipped ticks {c['skipped_ticks']})",
        f"received          {rx['frames']} frames: {rx['accepted']} accepted, {rx['rejected']} "
        f"rejected (unknown id {rx['unknown_id']}, length {rx['bad_length']}, CRC "
        f"{rx['bad_crc']}, counter {rx['bad_counter']}), {_lost(rx)}",
        f"sent              {tx['frames']} frames, {tx['dropped']} dropped"
        + (f", {tx['saturated']} values saturated (limited to their signal's range: "
           + ", ".join(f"{n} {m['saturated']}" for n, m in c["plant_messages"].items() if m.get("saturated"))
           + ")" if tx.get("saturated") else ""),
        f"TCU timeouts      {tcu}",
    ]
    if c.get("bridge"):
        b = c["bridge"]
        lines.append(f"bridge            {b['rx_forwarded']} frames in, {b['tx_forwarded']} out; "
                     f"{b['rx_ring_full']} refused by a full ring; bus errors "
                     f"{b['rx_errors']} receive / {b['tx_errors']} send; not forwarded: "
                     f"{b['rx_error_frames']} error, {b['rx_remote_frames']} remote, "
                     f"{b['rx_fd_frames']} CAN FD frames"
                     + (f"; {b['own_frames_dropped']} of its own frames heard back and dropped"
                        if b.get("own_frames_dropped") else ""))
        lines += _below_bridge_lines(b)
        if report["transport"].get("last_error"):
            lines.append(f"bridge error      {report['transport']['last_error']}")
    log = report.get("log")
    if log:
        lines.append(f"log               {log['path']} ({log['format']}): {log['written']} frames, "
                     f"{log['dropped']} lost" + (f"; ERROR {log['error']}" if log["error"] else ""))
    faults = report.get("faults") or {}
    if faults.get("events") or faults.get("set"):
        lines.append(f"faults            {len(faults.get('set', []))} set, "
                     f"{len(faults.get('events', []))} starts and ends (in {stats_path}: faults)")
        for e in faults.get("events", [])[:20]:
            lines.append(f"  {e['time_s']:10.4f} s  {e['event']:<7} #{e['id']} {e['target']}")
        if len(faults.get("events", [])) > 20:
            lines.append(f"  ... {len(faults['events']) - 20} more")
    lines.append(f"stats             {stats_path}")
    if report.get("verdict"):
        lines += verdict_lines(report["verdict"])
    return lines
