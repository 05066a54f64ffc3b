"""dct-hil serve: the plant to a TCU over CAN in real time (``rt_loop.server.Server``
run by ``rt_loop.console.run_console``), with the bench view when asked."""

import os

from plant import argtypes
from plant.extras import mf4_paths, require
from plant.maneuvers import LOOP_MANEUVERS

from . import options
from .options import UserError, check_writable


def add_parser(sub):
    from rt_loop.server import MAX_RATE_HZ, MIN_RATE_HZ

    serve = sub.add_parser(
        "serve", help="serve the plant to a TCU over CAN in real time (live status, JSON stats)",
        description="Serve the plant to a TCU over CAN: one tick per period in a SCHED_FIFO "
                    "thread (receive, check, step, send). SocketCAN is hard real time; any "
                    "other python-can interface goes through a bridge thread (soft real time). "
                    "Ctrl-C (exit 130) or SIGTERM (exit 0) stop it with everything written. It "
                    "ends with a verdict on its own timing (timing: VALID, or INVALID with the "
                    "findings: overruns, TCU timeouts, lost frames, no TCU). Exit status: 0 done, "
                    "1 the loop, transport or traffic log failed, 2 bad options, 3 timing "
                    "INVALID with --strict, 130 Ctrl-C.")
    serve.add_argument("--channel", metavar="NAME",
                       help="CAN channel: a network interface for socketcan (can0, vcan0), "
                            "the python-can channel otherwise, for udp_multicast GROUP or "
                            "GROUP:PORT (default: vcan0 on socketcan and virtual, 239.74.163.2 "
                            "on udp_multicast, else the one python-can finds for the interface)")
    serve.add_argument("--interface", metavar="NAME",
                       help="socketcan (hard real time) or any python-can interface, e.g. "
                            "virtual, udp_multicast, pcan, kvaser (bridged, soft real time); "
                            "default: socketcan if the channel is a CAN network interface, "
                            "else virtual")
    serve.add_argument("--rate", type=options.loop_rate(), default=2000.0, metavar="HZ",
                       help=f"ticks per second, {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} "
                            "(default 2000: 0.5 ms)")
    serve.add_argument("--priority", type=argtypes.priority, default=80, metavar="1..99",
                       help="SCHED_FIFO priority of the loop, with mlockall (default 80); "
                            "0: normal scheduling, no privileges needed, not real time")
    serve.add_argument("--cpu", type=argtypes.cpu, metavar="N", help="pin the loop to CPU N")
    serve.add_argument("--duration", type=argtypes.seconds, metavar="S",
                       help="stop after S seconds (default: run until Ctrl-C or SIGTERM)")
    serve.add_argument("--stats", default="out/serve-stats.json", metavar="FILE.json",
                       help="statistics written on exit (default out/serve-stats.json)")
    serve.add_argument("--log", metavar="FILE",
                       help="record the CAN traffic, both directions; the suffix picks the "
                            "format: .log (candump), .blf, .asc, .mf4 (needs asammdf), .csv, .trc")
    serve.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    serve.add_argument("--overrun", choices=("skip", "stop"), default="skip",
                       help="on an overrun: count it and skip the missed ticks (default), "
                            "or stop (exit 1)")
    serve.add_argument("--spin-us", type=float, default=None, metavar="US",
                       help="wake this long before each deadline and busy-wait to it, so the "
                            "OS's wake-up latency stays out of the tick; costs that share of a CPU "
                            "(default 300 us, at most 60 %% of the period, with SCHED_FIFO; 0 without)")
    serve.add_argument("--bitrate", type=argtypes.bitrate, metavar="BPS",
                       help="bit rate passed to the python-can bus (bridged interfaces only)")
    serve.add_argument("--time-scale", type=argtypes.time_scale, default=1.0, metavar="X",
                       help="run slower than real time: the same 1/rate plant step every "
                            "1/(rate x X) s of wall time; bus cycles and timeouts stretch by 1/X "
                            "(0 < X <= 1, default 1: real time). For machines too slow for real "
                            "time; the TCU must run at the same scale")
    serve.add_argument("--maneuver", choices=LOOP_MANEUVERS, metavar="NAME",
                       help="the driver inside the loop plays a scripted maneuver ("
                            + ", ".join(LOOP_MANEUVERS) + ") from the first accepted TCU "
                            "frame; the run ends with it")
    serve.add_argument("--record", metavar="FILE.csv|FILE.mf4",
                       help="record every plant output (the columns of dct-hil simulate) in plant "
                            "time: a CSV, or ASAM MDF4 (.mf4) with units, comments and the CAN "
                            "traffic of every bus as bus logging in the same file")
    serve.add_argument("--record-every", type=argtypes.record_interval, default=0.002, metavar="S",
                       help="recording interval in plant time (default 0.002)")
    serve.add_argument("--quiet", action="store_true",
                       help="no live status (the banner, warnings and summary stay)")
    options.add_strict_option(serve)
    options.add_pm_qos_options(serve)
    options.add_mapping_options(serve, "the plant")
    serve.add_argument("--xcp", metavar="[HOST:]PORT",
                       help="serve the loop's memory to an XCP master (XCP on Ethernet: measurement "
                            "with DAQ, calibration, the A2L on GET_ID); binds to 127.0.0.1 unless "
                            "HOST is given")
    serve.add_argument("--xcp-tcp", action="store_true", help="XCP on TCP instead of UDP")
    serve.add_argument("--stimulus", metavar="FILE.csv|FILE.mf4",
                       help="play recorded channels (a CSV with time_s, or an MF4 recording) into "
                            "the running loop: plant inputs and the parameters marked online, each "
                            "value at its plant time")
    serve.add_argument("--stimulus-start", choices=("plant", "maneuver"), default="plant",
                       help="stimulus time 0: plant time 0 (default) or the maneuver's start")
    serve.add_argument("--xcp-key", metavar="FILE",
                       help="seed & key: the secret in FILE (at least 16 bytes) locks calibration "
                            "and DAQ until the master unlocks them (HMAC-SHA256 of the seed)")
    options.add_control_option(serve, tcp=True)
    serve.add_argument("--tcu", choices=("none", "reference"), default="none",
                       help="none: the TCU under test is on the bus (default); reference: the "
                            "reference TCU runs beside the server (on the embedded transport the "
                            "C node on the loop's own rings, on a CAN interface a second "
                            "process), e.g. for tests driving the bench through --control-tcp; "
                            "its report goes beside --stats as tcu-report.json")
    serve.add_argument("--tcu-clock", choices=("wall", "bus"), default=None,
                       help="with --tcu reference: its task clock (default wall in real time, "
                            "bus in slow motion)")
    serve.add_argument("--faults", metavar="FILE.toml",
                       help="inject the faults of a [[fault]] file (rt_loop.faults: kind, target, "
                            "parameters, start_s / when / duration_s), checked whole before the run")
    options.add_ui_options(serve, demo=False)
    serve.set_defaults(func=run)


def run(args):
    from can_dbc.channels import ChannelError, default_channel
    from rt_loop.console import run_console
    from rt_loop.server import Server, ServerError
    from rt_loop.transport import TransportError, check_interface

    if mf4_paths(args.record, args.log, args.stimulus):
        require("asammdf")
    mapping, bus_channels = options.mapping_from_args(args, args.rate)
    ui = options.ui_settings(args)
    control = options.control_settings(args)
    try:
        if args.interface is not None:
            check_interface(args.interface)
        channel = args.channel if args.channel is not None else default_channel(args.interface)
        check_writable(args.stats, "--stats")
        if args.log:
            check_writable(args.log, "--log")
        if args.record:
            check_writable(args.record, "--record")
        driver = end = fixed = None
        if args.maneuver:
            from plant.maneuvers import get_maneuver

            m = get_maneuver(args.maneuver)
            driver, end, fixed = m.driver, m.duration_s, m.inputs
        kwargs = dict(
            interface=args.interface, rate_hz=args.rate, priority=args.priority,
            cpu=args.cpu, duration_s=args.duration, params_path=args.params, log_path=args.log,
            overrun_policy=args.overrun,
            bus_kwargs={"bitrate": args.bitrate} if args.bitrate else None,
            spin_us=args.spin_us, time_scale=args.time_scale, driver=driver,
            maneuver_end_s=end, record_path=args.record, record_every_s=args.record_every,
            pm_qos_us=args.pm_qos_us, mapping=mapping, bus_channels=bus_channels,
            xcp=args.xcp, xcp_protocol="tcp" if args.xcp_tcp else "udp", xcp_key=args.xcp_key,
            stimulus_path=args.stimulus, stimulus_start=args.stimulus_start,
            faults_path=args.faults, maneuver_inputs=fixed, **control,
        )
        started = None
        if args.tcu == "reference":
            server, started = _with_reference_tcu(channel, kwargs, args)
        else:
            if args.tcu_clock is not None:
                raise UserError("--tcu-clock needs --tcu reference")
            server = Server(channel, **kwargs)
        if ui is not None:
            recordings = os.path.join(os.path.dirname(os.path.abspath(args.stats)), "recordings")
            view = options.start_ui(server, ui, recordings, "dct-hil bench")
            view.stop_before(server)        # Ctrl-C, SIGTERM, the end: the page goes first
            print(f"live view         {view.url}"
                  + (" (asks for the token)" if view.token else "")
                  + f"; recordings from the page in {recordings}", flush=True)
        return run_console(server, args.stats, quiet=args.quiet, strict=args.strict,
                           started=started)
    except (ServerError, TransportError, ChannelError) as e:
        raise UserError(str(e)) from None


def _with_reference_tcu(channel, kwargs, args):
    """(server, started): the server made for the reference TCU (on the loop's rings
    on the embedded transport) and the function that starts the TCU once the loop
    runs (stopped, its report written, before the server stops; the control
    channel's ``ignition`` request restarts it)."""
    from pathlib import Path

    from dct_hil.demo import RestartableTcu, make_server, start_tcu
    from rt_loop.transport import default_interface

    interface = args.interface or default_interface(channel)[0]
    two = interface != "virtual"
    server = make_server("c", two, channel, **kwargs)
    folder = Path(os.path.dirname(os.path.abspath(args.stats)))
    clock = args.tcu_clock or ("wall" if args.time_scale >= 1.0 else "bus")
    mapping = None if kwargs.get("mapping") is None else server.mapping

    def started(srv):
        tcu = RestartableTcu(lambda: start_tcu("c", two, interface, channel, srv, srv.time_scale,
                                               folder / "tcu-report.json", folder / "tcu.out",
                                               clock, mapping))
        srv.add_stop_hook(tcu.stop)
        if srv.control is not None:
            srv.control.add_op("ignition", tcu.ignition_op)
        print(f"reference TCU     the C node ({'a second process' if two else 'on the loop rings'}"
              f", clock {clock}); its report: {folder / 'tcu-report.json'}", flush=True)

    return server, started
