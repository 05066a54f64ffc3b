"""``dct-hil demo``: the plant server and the reference TCU closing the loop over CAN.

What a new user runs first. The server plays a scripted maneuver
(``paper-cycle`` by default: the reference paper's TCU test) with the driver
inside the real-time loop; the TCU stub (``tcu_stub.can_tcu``) drives the
clutches, forks and engine interventions through the CAN contract only.

Transport:
- vcan0 (or the ``--channel`` given) is a CAN network interface that is up:
  SocketCAN, the server in this process, the TCU stub as a second process
  (``python -m tcu_stub.command``), exactly as a TCU on the bench would be;
- otherwise the embedded default: the TCU stub in a thread of this process
  exchanging frames with the loop. With the C TCU (``tcu_impl="c"``, the
  default: ``tcu_stub.c_node``) the thread is C and the frames go through
  the loop's own rings (``rt_loop.embedded``): no bus and no Python between
  them; with the Python TCU (``tcu_impl="python"``) over python-can's
  in-process ``virtual`` bus, the server bridged onto it.
  The demo says which, and why.

The maneuver starts when the TCU's first frame is accepted and the run ends
with it. Then the demo writes, into ``--out`` (default out/demo):
``plant.csv`` (every plant output each 2 ms of plant time),
``can.log`` (the traffic, candump format), ``serve-stats.json`` (turnaround,
overruns, counts), ``tcu-report.json`` (the TCU's own counts and shifts),
``summary.json`` (figures and shifts), and the plots (PNG, like the paper's
Figs. 10 and 11), and prints where they are.

It ends with a verdict on the run's timing (``rt_loop.verdict.demo_verdict``:
the server's overruns, TCU timeouts and lost frames, the TCU's stale episodes,
and the plant's shifts against the offline run of the same maneuver and
duration, ``offline_shifts``), in ``summary.json`` as ``verdict`` and printed
last: "timing: VALID" or "timing: INVALID - <first finding>". An INVALID run
warns on stderr; with ``strict`` a run that would exit 0 exits 3.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from can_dbc.channels import ChannelError, default_channel
from plant.maneuvers import LOOP_MANEUVERS

DEFAULT_CHANNEL = "vcan0"
EMBEDDED_CHANNEL = "dct-hil-demo"
SCRIPTED_MANEUVERS = LOOP_MANEUVERS              # the pedal tables the loop plays itself
RECORD_EVERY_S = 0.002
_TCU_START_TIMEOUT_S = 60.0
#: offline shifts by (maneuver, duration), for this process only (never on disk)
_OFFLINE_SHIFTS: dict = {}


class DemoError(RuntimeError):
    """A demo that cannot run (one-line message)."""


def can_netdev_up(name: str) -> bool:
    """True when ``name`` is a CAN network interface of this kernel and it is up."""
    base = Path("/sys/class/net") / name
    try:
        if (base / "type").read_text().strip() != "280":          # ARPHRD_CAN
            return False
        flags = int((base / "flags").read_text().strip(), 16)
    except (OSError, ValueError):
        return False
    return bool(flags & 0x1)                                        # IFF_UP


def choose_transport(channel: str | None, interface: str | None) -> tuple[str, str, str, bool]:
    """(interface, channel, why, two_processes)."""
    if interface is not None:
        if interface == "virtual":
            return ("virtual", channel or EMBEDDED_CHANNEL,
                    "--interface virtual: the in-process bus, the TCU stub in a thread", False)
        try:
            channel = channel or default_channel(interface)
        except ChannelError as e:
            raise DemoError(str(e)) from None
        return (interface, channel,
                f"--interface {interface}: the TCU stub as a second process", True)
    name = channel or DEFAULT_CHANNEL
    if can_netdev_up(name):
        return ("socketcan", name,
                f"{name} is a CAN network interface and up: SocketCAN, the TCU stub as a "
                "second process", True)
    if channel is not None:
        raise DemoError(f"{channel} is not a CAN network interface that is up (create it: "
                        f"ip link add dev {channel} type vcan && ip link set up {channel}), "
                        "or leave --channel out for the embedded transport")
    return ("virtual", EMBEDDED_CHANNEL,
            f"no {DEFAULT_CHANNEL} on this machine: the embedded transport (python-can's "
            "in-process virtual bus), the TCU stub in a thread of this process", False)


def _driver_for(name: str):
    from plant.maneuvers import get_maneuver

    if name not in SCRIPTED_MANEUVERS:
        raise DemoError(f"maneuver {name!r}: the demo plays the scripted maneuvers "
                        f"({', '.join(SCRIPTED_MANEUVERS)}); wltc runs offline: "
                        "dct-hil simulate --scenario wltc")
    return get_maneuver(name)


def offline_shifts(maneuver: str, duration_s: float, mapping=None, start_tick: int = 0,
                   schedule=None) -> list[tuple[float, int, int]]:
    """The plant's shifts (t_s, from, to) in the offline run of ``maneuver`` over
    its first ``duration_s``: the live run's loop without a bus
    (``tcu_stub.offline.run_scheduled``): the same plant, the same pedal table
    played every tick, the same TCU logic in-process every 2 ms, every message
    through the CAN matrix of the live run (the project's contract, or with
    ``mapping`` (a ``can_dbc.mapping.Mapping``) its matrix through
    ``tcu_stub.mapped_link.MappedLink``, so that the matrix's own scaling is in
    both runs) and sent at the ticks the server sends it (``schedule``:
    ``can_dbc.table.send_schedule`` of the live run's mapping; default the
    contract's), the maneuver started at the live run's tick ``start_tick``
    (the plant idling until then as the live one did, so that both start it
    from the same plant state and the same phase of the send schedule), the
    gear recorded at the ticks the demo's recorder records it and read by
    ``plant.maneuvers.gear_shifts``. About a second of CPU for 10 s of maneuver;
    kept in memory for the rest of the process."""
    from can_dbc.table import send_schedule
    from plant.maneuvers import gear_shifts, get_maneuver
    from plant.model import Plant
    from tcu_stub.offline import run_scheduled

    if schedule is None:
        if mapping is None:
            from can_dbc.mapping import load

            schedule = send_schedule(load())
        else:
            schedule = send_schedule(mapping)
    schedule = tuple(tuple(x) for x in schedule)
    key = (maneuver, round(float(duration_s), 6), None if mapping is None else mapping.path,
           int(start_tick), schedule)
    if key not in _OFFLINE_SHIFTS:
        m = get_maneuver(maneuver)
        plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
        m.start(plant)                      # its reset and fixed inputs (the road grade)
        link = None
        if mapping is not None:
            from tcu_stub.mapped_link import MappedLink

            link = MappedLink(mapping)
        every = max(1, int(round(RECORD_EVERY_S / plant.step_s)))
        rec = run_scheduled(plant, m.driver, float(duration_s), schedule, start_tick=int(start_tick),
                            link=link, record_every_ticks=every)
        _OFFLINE_SHIFTS[key] = gear_shifts(rec["time_s"], rec["gear"])
    return list(_OFFLINE_SHIFTS[key])


def maneuver_start_tick(rec: dict, step_s: float) -> int | None:
    """The loop's tick at which a recorded run's maneuver started (the plant's
    idle before it, in ticks), from its first recorded sample of maneuver time
    (plant time and maneuver time after the same step; plant time advances
    only with executed ticks); None when it never started."""
    mt = np.asarray(rec["maneuver_time_s"], dtype=float)
    idx = np.flatnonzero(~np.isnan(mt))
    if not len(idx):
        return None
    i = idx[0]
    return max(0, int(round((float(rec["time_s"][i]) - float(mt[i])) / step_s)))


class _TcuProcess:
    """The TCU stub as a second process on the same CAN channel."""

    def __init__(self, interface: str, channel: str, time_scale: float, report: Path,
                 log: Path, clock: str, mapping=None, bus_channels=None, impl: str = "c",
                 priority: int = 0) -> None:
        self.report_path = report
        self.log_path = log
        cmd = [sys.executable, "-m", "tcu_stub.command", "--channel", channel,
               "--interface", interface, "--time-scale", repr(time_scale), "--clock", clock,
               "--report", str(report), "--quiet", "--impl", impl, "--priority", str(priority)]
        if mapping is not None:                   # the same matrix, DBCs and channels
            cmd += ["--mapping", mapping.path]
            for b in mapping.buses:
                cmd += ["--dbc", f"{b.name}={b.dbc}"]
            for name, ch in (bus_channels or {}).items():
                if ch != channel:
                    cmd += ["--bus", f"{name}={ch}"]
        self._log = open(log, "w", encoding="utf-8")
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def status_line(self) -> str:
        return "" if self.alive() else f"TCU process ended ({self.proc.returncode})"

    def stop(self) -> int | None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def report(self) -> dict | None:
        try:
            return json.loads(self.report_path.read_text())
        except (OSError, ValueError):
            return None


class _TcuThread:
    """The TCU stub in a thread of this process, on the in-process bus."""

    def __init__(self, channel: str, time_scale: float, report: Path, clock: str,
                 mapping=None, bus_channels=None) -> None:
        from tcu_stub.can_tcu import CanTcu

        self.report_path = report
        self.tcu = CanTcu.open("virtual", channel, time_scale=time_scale, clock=clock,
                               **({} if mapping is None else
                                  {"mapping": mapping, "bus_channels": bus_channels}))
        self.tcu.start()

    def alive(self) -> bool:
        return True

    def status_line(self) -> str:
        return self.tcu.status_line()

    def stop(self) -> int:
        self.tcu.stop()
        self.tcu.write_report(self.report_path)
        return 0

    def report(self) -> dict | None:
        try:
            return json.loads(self.report_path.read_text())
        except (OSError, ValueError):
            return None


class _TcuEmbedded(_TcuThread):
    """The C TCU on a thread of its own, its frames the loop's rings (``rt_loop.embedded``)."""

    def __init__(self, server, time_scale: float, report: Path, clock: str, mapping=None,
                 priority: int = 0) -> None:
        from rt_loop.embedded import connect_tcu

        self.report_path = report
        self.tcu = connect_tcu(server, time_scale=time_scale, clock=clock, mapping=mapping,
                               priority=priority)


def start_tcu(impl: str, two: bool, interface: str, channel: str, server, time_scale: float,
              report: Path, log: Path, clock: str, mapping=None):
    """The reference TCU of a demo or test bench: a second process on a real bus
    (``two``), else the C node on the loop's rings (``impl`` "c": the server must be
    ``rt_loop.embedded.embedded_server``'s) or the Python node on the in-process bus."""
    from rt_loop.embedded import tcu_priority

    priority = tcu_priority(server.priority)
    if two:
        return _TcuProcess(interface, channel, time_scale, report, log, clock, mapping,
                           server.bus_channels, impl=impl, priority=priority)
    if impl == "c":
        return _TcuEmbedded(server, time_scale, report, clock, mapping, priority)
    return _TcuThread(channel, time_scale, report, clock, mapping, server.bus_channels)


class RestartableTcu:
    """A reference TCU (``start_tcu``'s) that can be switched off and on again, as
    the ignition does on a bench (``restart``): a fresh TCU, no state kept (its
    trouble codes, limp home, learned values). ``ignition_op`` is the control
    channel's ``ignition {off_s}`` request for it."""

    #: longest ignition-off time a request may ask for (s)
    MAX_OFF_S = 10.0

    def __init__(self, start) -> None:
        self._start = start
        self._lock = threading.Lock()
        self.tcu = start()
        self.restarts = 0

    def restart(self, off_s: float = 0.5) -> None:
        with self._lock:
            self.tcu.stop()                # its safe frames, its report
            time.sleep(off_s)
            self.tcu = self._start()
            self.restarts += 1

    def ignition_op(self, request: dict) -> dict:
        off = request.get("off_s", 0.5)
        if isinstance(off, bool) or not isinstance(off, (int, float)) or \
                not 0.0 <= off <= self.MAX_OFF_S:
            raise ValueError(f"ignition: off_s must be seconds 0..{self.MAX_OFF_S:g}, got {off!r}")
        self.restart(float(off))
        return {"off_s": float(off), "restarts": self.restarts}

    def stop(self):
        with self._lock:
            return self.tcu.stop()

    def alive(self) -> bool:
        return self.tcu.alive()

    def status_line(self) -> str:
        return self.tcu.status_line()

    def report(self) -> dict | None:
        return self.tcu.report()


def make_server(impl: str, two: bool, channel: str, **kwargs):
    """The plant server for ``start_tcu``: on the loop's rings for the embedded C TCU."""
    if not two and impl == "c":
        from rt_loop.embedded import embedded_server

        return embedded_server(channel, **kwargs)
    from rt_loop.server import Server

    return Server(channel, **kwargs)


def _status_line(snap: dict, tcu_line: str) -> str:
    p, c = snap["plant"], snap["counts"]
    mt = snap.get("maneuver_time_s")
    head = f"t {mt:6.2f} s" if mt is not None else "waiting for the TCU"
    line = (f"{head} | {p['vehicle_speed_kmh']:6.1f} km/h  gear {p['gear']}  engine "
            f"{p['engine_speed_rpm']:5.0f} rpm  K1 {max(p['clutch1_pressure_bar'], 0):4.1f} "
            f"K2 {max(p['clutch2_pressure_bar'], 0):4.1f} bar | turnaround max "
            f"{snap['turnaround_max_us']:.0f} us, overruns {c['overruns']}, rx rejected "
            f"{c['rx']['rejected']}")
    return line + (f" | {tcu_line}" if tcu_line else "")


def run_demo(maneuver: str = "paper-cycle", out_dir: str | os.PathLike = "out/demo",
             channel: str | None = None, interface: str | None = None,
             time_scale: float = 1.0, priority: int | None = None, quiet: bool = False,
             duration_s: float | None = None, tcu_clock: str | None = None,
             pm_qos_us: int | str | None = "auto", strict: bool = False, out=None, err=None,
             mapping=None, bus_channels: dict | None = None, mf4: bool = False,
             control_path: str | os.PathLike | None = None,
             ui: tuple | None = None, tcu_impl: str = "c") -> int:
    """Runs the demo; returns the exit code (0 done, 1 failed, 130 Ctrl-C; with
    ``strict``, 3 for a run that would exit 0 but whose timing verdict is INVALID).

    ``duration_s`` plays only the first seconds of the maneuver. ``tcu_clock``
    (``tcu_stub.can_tcu.CLOCKS``): the TCU's task clock; default "wall" in real
    time and "bus" in slow motion (a TCU tick per 2 ms of plant time, so plant
    and TCU stay in step even when the machine cannot keep the slowed pace).
    ``mapping`` (a ``can_dbc.mapping.Mapping``, default the project's own
    contract) is the CAN matrix both the server and the TCU stub use, its
    buses on the channels ``bus_channels`` names (``Server``); the shifts are
    compared with the offline run over the same matrix. ``tcu_impl``: "c" (the
    C TCU node, ``tcu_stub.c_node``; on the embedded transport on the loop's own
    rings) or "python" (``tcu_stub.can_tcu.CanTcu``). ``mf4``:
    the recording is ``plant.mf4`` (ASAM MDF4 with the CAN traffic as bus
    logging) instead of ``plant.csv``. ``control_path``: the server's control
    channel on that Unix socket (``rt_loop.control``). ``ui``: (host, port,
    token or None): the live bench view (``dct_hil.ui``) served while the demo
    runs; when the maneuver is over the page keeps the run's last figures
    (writes refused) until Ctrl-C or SIGTERM, then the demo exits with its
    own status."""
    from plant import maneuvers as mv
    from plant.extras import install_hint, missing_extra
    try:
        from plant.plots import write_plots
    except ImportError as e:                # a bench PC without the plots extra: no PNGs
        if missing_extra(e) != "plots":
            raise
        write_plots = None
    from plant.stop_signals import StopSignals
    from rt_loop import verdict as vd
    from rt_loop.measure.recorder import read_recording
    from tcu_stub.c_node import IMPLS

    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    if tcu_impl not in IMPLS:
        raise DemoError(f"TCU implementation {tcu_impl!r}: one of {', '.join(IMPLS)}")
    m = _driver_for(maneuver)
    if tcu_clock is None:
        tcu_clock = "wall" if time_scale >= 1.0 else "bus"
    end_s = m.duration_s if duration_s is None else min(float(duration_s), m.duration_s)
    iface, chan, why, two = choose_transport(channel, interface)
    if not two and tcu_impl == "c":
        why = why.split(":", 1)[0] + (": the embedded transport, the TCU in C on a thread of its "
                                      "own, its frames through the loop's own rings (no bus, no "
                                      "Python between them)")
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"recording": folder / ("plant.mf4" if mf4 else "plant.csv"), "can_log": folder / "can.log",
             "stats": folder / "serve-stats.json", "tcu_report": folder / "tcu-report.json",
             "summary": folder / "summary.json"}
    for p in paths.values():
        if p.exists():
            p.unlink()
    if priority is None:
        priority = 80 if os.geteuid() == 0 else 0
    server = make_server(tcu_impl, two, chan, interface=iface, priority=priority, driver=m.driver,
                    maneuver_inputs=m.inputs, maneuver_start="tcu", maneuver_end_s=end_s,
                    record_path=paths["recording"], record_every_s=RECORD_EVERY_S,
                    log_path=paths["can_log"], time_scale=time_scale, pm_qos_us=pm_qos_us,
                    mapping=mapping, bus_channels=bus_channels, control_path=control_path)
    tcu_mapping = None if mapping is None else server.mapping
    view = None
    if ui is not None:
        from dct_hil.ui.server import UiError, UiServer

        host, port, token = ui
        try:
            view = UiServer(server, (host, port), token=token,
                            recordings_dir=folder / "recordings", title=f"dct-hil demo {maneuver}")
            view.start()
        except UiError as e:
            raise DemoError(str(e)) from None
    print(f"dct-hil demo      {maneuver}: {m.description} ({end_s:g} s"
          + (f", at {time_scale:g}x real time" if time_scale != 1 else ", in real time") + ")",
          file=out)
    print(f"transport         {iface} on {chan}: {why}", file=out)
    if mapping is not None:
        buses = ", ".join(f"{b.name} ({os.path.basename(b.dbc)}, {b.bitrate // 1000} kbit/s) on "
                          f"{server.bus_channels[b.name]}" for b in server.mapping.buses)
        print(f"CAN matrix        {server.mapping.path}: {buses}", file=out)
    print("PM QoS            " + (f"off ({server.pm_qos_off_because})" if server.pm_qos is None
                                else f"{server.pm_qos.path} at {server.pm_qos.latency_us} us "
                                     "for the run"), file=out)
    if view is not None:
        print(f"live view         {view.url}" + (" (asks for the token)" if view.token else ""),
              file=out)
    if tcu_clock == "bus":
        print("TCU clock         bus: a TCU tick per frame of its fastest plant message (follows "
              "plant time)",
              file=out)

    signals = StopSignals()
    stop, received = signals.event, signals.received
    tcu = None
    tcu_rc = None
    try:
        signals.__enter__()
        server.start(progress=lambda line: print(f"dct-hil: {line}", file=err, flush=True),
                     cancel=stop)
        for w in server.warnings:
            print(f"dct-hil: warning: {w}", file=err)
        tcu = start_tcu(tcu_impl, two, iface, chan, server, time_scale, paths["tcu_report"],
                        folder / "tcu.out", tcu_clock, tcu_mapping)
        started = time.monotonic()
        # a machine slow enough for slow motion starts the TCU's process as slowly
        tcu_start_timeout_s = _TCU_START_TIMEOUT_S / min(1.0, time_scale)
        last = 0.0
        while not stop.is_set() and server.running:
            snap = server.snapshot()
            if snap["maneuver_time_s"] is None and time.monotonic() - started > tcu_start_timeout_s:
                raise DemoError(f"the TCU stub sent no valid frame within "
                                f"{tcu_start_timeout_s:g} s ({tcu.status_line() or 'no reason known'})")
            if not tcu.alive():
                raise DemoError(f"the TCU stub stopped: {tcu.status_line()}; see "
                                f"{folder / 'tcu.out'}")
            now = time.monotonic()
            if not quiet and now - last >= 1.0:
                print(_status_line(snap, tcu.status_line()), file=out, flush=True)
                last = now
            stop.wait(0.1)
    except DemoError as e:
        print(f"dct-hil: error: {e}", file=err)
        return_code = 1
    else:
        return_code = 0
    finally:
        try:
            if view is not None:
                view.freeze()            # its recording finalised, the sessions stop reading
            if tcu is not None:
                tcu_rc = tcu.stop()
            server.stop()
        finally:
            signals.__exit__()
            if view is not None and sys.exc_info()[0] is not None:
                view.stop()              # the demo fails: no page left behind

    report = server.report()
    report["verdict"] = vd.serve_verdict(report)
    server.write_report(paths["stats"], report)
    run = report["run"]
    if run["error"]:
        print(f"dct-hil: error: the loop stopped: {run['error']}", file=err)
        return_code = 1
    rec = read_recording(paths["recording"])
    started = ~np.isnan(rec["maneuver_time_s"])
    figures: dict = {}
    shifts: list = []
    plots: list = []
    if started.sum() >= 2:
        ran = {k: v[started] for k, v in rec.items()}
        ran["time_s"] = ran["maneuver_time_s"]
        figures = mv.report(m, ran)
        shifts = mv.gear_shifts(ran["time_s"], ran["gear"])
        if write_plots is not None:
            plots = write_plots(ran, folder, title=f"demo {maneuver}")
    tcu_report = tcu.report() if tcu is not None else None
    offline, not_compared, interrupted = None, None, signals.interrupted
    start_tick = maneuver_start_tick(rec, server.step_s) if len(rec["time_s"]) else None
    if received:
        not_compared = "the run was stopped"
    elif run["maneuver"] != "done":
        not_compared = f"the maneuver did not complete (state {run['maneuver']})"
    else:
        print(f"offline run       {maneuver} over {end_s:g} s with the TCU in-process, for the "
              "shift comparison ...", file=out, flush=True)
        try:
            from can_dbc.table import send_schedule

            offline = offline_shifts(maneuver, end_s, tcu_mapping, start_tick or 0,
                                     send_schedule(server.mapping))
        except KeyboardInterrupt:
            not_compared, interrupted = "interrupted while computing the offline run", True
        except Exception as e:  # the verdict says why; the run's files stand
            not_compared = f"the offline run failed: {type(e).__name__}: {' '.join(str(e).split())}"
    verdict = vd.demo_verdict(report, tcu_report, shifts, offline, not_compared)
    summary = {
        "maneuver": maneuver,
        "completed": run["maneuver"] == "done",
        "maneuver_time_s": run["maneuver_time_s"],
        "transport": {"interface": iface, "channel": chan, "why": why,
                      "tcu": "second process" if two else "thread",
                      "tcu_impl": tcu_impl},
        "mapping": server.mapping.path,
        "buses": dict(server.bus_channels),
        "time_scale": time_scale,
        "tcu_clock": tcu_clock,
        "figures": figures,
        "shifts": [{"time_s": t, "from": a, "to": b} for t, a, b in shifts],
        "maneuver_start_tick": start_tick,
        "offline_shifts": None if offline is None else [
            {"time_s": t, "from": a, "to": b} for t, a, b in offline],
        "verdict": verdict,
        "gear_clashes": float(rec["gear_clashes"][-1]) if len(rec["time_s"]) else None,
        "turnaround": report["turnaround"],
        "overruns": report["counts"]["overruns"],
        "skipped_ticks": report["counts"]["skipped_ticks"],
        "rx": report["counts"]["rx"],
        "tcu_exit": tcu_rc,
        "tcu": tcu_report,
        "files": {k: str(v) for k, v in paths.items()} | {"plots": plots},
    }
    paths["summary"].write_text(json.dumps(summary, indent=2, default=float) + "\n")

    print(file=out)
    if figures:
        print(mv.format_report(maneuver, figures), file=out)
    print(f"shifts            {len(shifts)}: "
          + ", ".join(f"{a}-{b} at {t:.2f} s" for t, a, b in shifts), file=out)
    ta = report["turnaround"]
    print(f"loop              turnaround p99.9 {_us(ta.get('p99_9_us'))}, max {_us(ta.get('max_us'))}; "
          f"overruns {summary['overruns']}; rx rejected {summary['rx']['rejected']}, lost "
          f"{summary['rx'].get('lost', summary['rx']['overflow'])}", file=out)
    if received:
        mt = run["maneuver_time_s"]
        print(f"dct-hil demo: stopped by {signal.Signals(received[0]).name} at maneuver time "
              + ("(not started)" if mt is None else f"{mt:.2f} s"), file=err)
    elif not summary["completed"]:
        print(f"dct-hil demo: the maneuver did not complete (state {run['maneuver']})", file=err)
        return_code = return_code or 1
    print("written:", file=out)
    no_plots = "none" if write_plots is not None else f"none (no matplotlib: {install_hint('plots')})"
    for name, p in [("plots", ", ".join(plots) or no_plots)] + [
            (k, str(v)) for k, v in paths.items()]:
        print(f"  {name:<15} {p}", file=out)
    for line in vd.verdict_lines(verdict):
        print(line, file=out)
    out.flush()
    if interrupted:
        return_code = 130
    warning = vd.warning_line(verdict, strict and return_code == 0)
    if warning:
        print(warning, file=err)
    if view is not None:
        _keep_serving(view, interrupted or bool(received), out)
    return vd.exit_code(verdict, strict, return_code)


def _keep_serving(view, stopped: bool, out) -> None:
    """After the run: the page keeps its last figures until Ctrl-C or SIGTERM
    (at once when the run itself was stopped that way)."""
    from plant.stop_signals import StopSignals

    try:
        if not stopped:
            print(f"live view         {view.url} stays up with the run's last figures; Ctrl-C "
                  "to end", file=out, flush=True)
            with StopSignals() as signals:
                while not signals.event.wait(0.5):
                    pass
    finally:
        view.stop()


def _us(v) -> str:
    return "n/a" if v is None else f"{v:.1f} us"
