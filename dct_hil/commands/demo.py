"""dct-hil demo: the plant server and the TCU stub over CAN, a maneuver in real
time, then plots and logs (``dct_hil.demo.run_demo``)."""

import os

from plant import argtypes
from plant.extras import require
from plant.maneuvers import LOOP_MANEUVERS

from . import options
from .options import UserError, check_writable


def add_parser(sub):
    demo = sub.add_parser(
        "demo", help="the plant server and the TCU stub over CAN, a maneuver in real time, "
                     "then plots and logs",
        description="Runs the plant server and the TCU stub as two processes on vcan0 when "
                    "vcan0 is up, otherwise on the embedded transport (python-can's in-process "
                    "virtual bus, the TCU in a thread); plays the maneuver with a live status, "
                    "then writes the plots, the recording, the CAN log and the statistics. It "
                    "ends with a verdict on the run's timing (timing: VALID, or INVALID with the "
                    "findings: overruns, TCU timeouts and stale episodes, lost frames, shifts "
                    "unlike the offline run of the same maneuver). Exit status: 0 done, 1 the "
                    "run failed or the maneuver did not complete, 2 bad options, 3 timing "
                    "INVALID with --strict, 130 Ctrl-C.")
    demo.add_argument("--maneuver", choices=LOOP_MANEUVERS, default="paper-cycle",
                      metavar="NAME", help="paper-cycle (default), " + ", ".join(LOOP_MANEUVERS[1:]))
    demo.add_argument("--out", default="out/demo", metavar="DIR",
                      help="where to write everything (default out/demo)")
    demo.add_argument("--channel", metavar="NAME",
                      help="a CAN network interface that is up (default: vcan0 if it is, else "
                           "the embedded transport)")
    demo.add_argument("--interface", metavar="NAME",
                      help="python-can interface (default: socketcan on a CAN network "
                           "interface, else virtual)")
    demo.add_argument("--time-scale", type=argtypes.time_scale, default=1.0, metavar="X",
                      help="slow motion for machines too slow for real time (0 < X <= 1)")
    demo.add_argument("--priority", type=argtypes.priority, default=None, metavar="0..99",
                      help="SCHED_FIFO priority of the loop (default 80 as root, else 0)")
    demo.add_argument("--tcu-clock", choices=("wall", "bus"), default=None,
                      help="the TCU stub's task clock: wall (2 ms of wall time, the default in "
                           "real time) or bus (a tick per 2 ms plant frame, the default with "
                           "--time-scale below 1)")
    demo.add_argument("--tcu-impl", choices=("c", "python"), default="c",
                      help="the TCU stub: c (the C node on a thread of its own; on the embedded "
                           "transport its frames go through the loop's own rings; the default) or "
                           "python (tcu_stub.can_tcu, for editing tcu_stub/logic.py)")
    demo.add_argument("--duration", type=argtypes.seconds, metavar="S",
                      help="play only the first S seconds of the maneuver")
    demo.add_argument("--quiet", action="store_true", help="no live status")
    options.add_strict_option(demo)
    options.add_pm_qos_options(demo)
    options.add_mapping_options(demo, "the plant and the TCU stub")
    demo.add_argument("--mf4", action="store_true",
                      help="record plant.mf4 (ASAM MDF4: every plant output with its unit and the "
                           "CAN traffic as bus logging) instead of plant.csv")
    options.add_control_option(demo)
    options.add_ui_options(demo, demo=True)
    demo.set_defaults(func=run)


def run(args):
    from dct_hil.demo import DemoError, run_demo
    from rt_loop.server import ServerError
    from rt_loop.transport import TransportError

    if args.mf4:
        require("asammdf")
    check_writable(os.path.join(args.out, "summary.json"), "--out")
    mapping, bus_channels = options.mapping_from_args(args, 2000.0)
    ui = options.ui_settings(args)
    try:
        return run_demo(args.maneuver, args.out, channel=args.channel, interface=args.interface,
                        time_scale=args.time_scale, priority=args.priority, quiet=args.quiet,
                        duration_s=args.duration, tcu_clock=args.tcu_clock,
                        pm_qos_us=args.pm_qos_us, strict=args.strict, mapping=mapping,
                        bus_channels=bus_channels, mf4=args.mf4, control_path=args.control,
                        ui=ui, tcu_impl=args.tcu_impl)
    except (DemoError, ServerError, TransportError) as e:
        raise UserError(str(e)) from None
