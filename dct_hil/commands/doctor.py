"""dct-hil doctor: how ready this PC is for the real-time loop
(``rt_loop.tools.doctor.run_doctor``): findings and fixes, as a table or JSON."""

import sys

from plant import argtypes

from . import options
from .options import UserError, check_writable


def add_parser(sub):
    doctor = sub.add_parser(
        "doctor", help="how ready this PC is for the real-time loop: findings and fixes",
        description="Checks the kernel's preemption model, RT throttling, CPU isolation, "
                    "frequency governor, idle states, SMT, the CAN interface and its interrupts, "
                    "transparent huge pages, swap, memory locking and SCHED_FIFO rights, then "
                    "measures the machine's wake-up floor with and without PM QoS. Exit 1 when "
                    "an item fails.")
    doctor.add_argument("--cpu", type=argtypes.cpu, metavar="N",
                        help="the CPU the loop will be pinned to (dct-hil serve --cpu)")
    doctor.add_argument("--channel", metavar="NAME",
                        help="the CAN network interface (default: vcan0 if it exists)")
    doctor.add_argument("--priority", type=argtypes.priority, default=80, metavar="1..99",
                        help="the loop's SCHED_FIFO priority (default 80)")
    doctor.add_argument("--rate", type=options.loop_rate(), default=2000.0, metavar="HZ",
                        help="the loop's rate (default 2000)")
    doctor.add_argument("--floor-s", type=argtypes.seconds, default=10.0, metavar="S",
                        help="length of each wake-up floor measurement (default 10)")
    doctor.add_argument("--no-floor", action="store_true", help="skip the floor measurement")
    doctor.add_argument("--json", nargs="?", const="-", metavar="FILE|-",
                        help="write the report as JSON to FILE, or to stdout (-, or no FILE) "
                             "instead of the table")
    doctor.set_defaults(func=run)


def run(args):
    from rt_loop.tools.doctor import DoctorError, run_doctor

    to_file = args.json not in (None, "-")
    if to_file:
        check_writable(args.json, "--json")
    try:
        report = run_doctor(cpu=args.cpu, channel=args.channel, priority=args.priority,
                            rate_hz=args.rate, floor_s=args.floor_s, floor=not args.no_floor,
                            progress=lambda line: print(f"dct-hil doctor: {line}",
                                                        file=sys.stderr, flush=True))
    except DoctorError as e:
        raise UserError(str(e)) from None
    if args.json == "-":
        sys.stdout.write(report.json_text())
        return report.exit_code
    sys.stdout.write(report.text())
    if to_file:
        with open(args.json, "w", encoding="utf-8") as f:
            f.write(report.json_text())
        print(f"json: {args.json}")
    return report.exit_code
