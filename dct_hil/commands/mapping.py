"""dct-hil mapping template|check|show: vehicle CAN matrices' mapping files
(``can_dbc.mapping``)."""

import sys

from plant import argtypes

from . import options
from .options import UserError, check_writable


def add_parser(sub):
    mapping = sub.add_parser(
        "mapping", help="vehicle CAN matrices: write, check and show mapping files",
        description="A mapping file (TOML) says what the plant sends and receives on a vehicle's "
                    "DBC (the manual: docs/can-matrices.md).")
    msub = mapping.add_subparsers(dest="mapping_command", metavar="ACTION")
    tpl = msub.add_parser("template", help="a commented mapping skeleton for a DBC")
    tpl.add_argument("dbc", metavar="VEHICLE.dbc")
    tpl.add_argument("--tcu-node", action="append", default=[], metavar="NAME",
                     help="a DBC node of the TCU (its messages are received); repeatable")
    tpl.add_argument("--tcu-messages", default="", metavar="A,B,...",
                     help="messages the TCU sends (for a DBC without node names)")
    tpl.add_argument("--plant-node", action="append", default=[], metavar="NAME",
                     help="a DBC node the plant plays (default: the senders of what the TCU receives)")
    tpl.add_argument("--bitrate", type=argtypes.bitrate, metavar="BIT/S",
                     help="the bus's bit rate (default: the DBC's Baudrate)")
    tpl.add_argument("--out", metavar="FILE", help="write it to FILE (default: stdout)")
    for action, text in (("check", "validate a mapping file; a summary with the bus load per bus"),
                         ("show", "what goes where: per bus and message, each signal's source or target")):
        p = msub.add_parser(action, help=text)
        p.add_argument("mapping", metavar="MAPPING.toml",
                       help="a mapping file, or a shipped one by name (dct_hil, vehicle)")
        p.add_argument("--rate", type=options.loop_rate(), default=2000.0, metavar="HZ",
                       help="the loop's rate: cycle times must be whole ticks (default 2000)")
    mapping.set_defaults(func=run)


def run(args):
    from can_dbc import mapping

    if args.mapping_command is None:
        raise UserError("choose an action: dct-hil mapping template, check or show")
    try:
        if args.mapping_command == "template":
            if args.out:
                check_writable(args.out, "--out")
            text = mapping.template(
                args.dbc, tcu_nodes=args.tcu_node, plant_nodes=args.plant_node,
                tcu_messages=[n.strip() for n in args.tcu_messages.split(",") if n.strip()],
                bitrate=args.bitrate, out_path=args.out)
            if not args.out:
                sys.stdout.write(text)
                return 0
            with open(args.out, "w", encoding="utf-8") as f:
                f.write(text)
            print(f"template: {args.out}")
            return 0
        m = mapping.load(mapping.find_mapping(args.mapping), rate_hz=args.rate)
    except mapping.MappingError as e:
        raise UserError(str(e)) from None
    sys.stdout.write(mapping.check_report(m) if args.mapping_command == "check" else mapping.show(m))
    return 0
