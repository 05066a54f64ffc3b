"""dct-hil tcu: the reference TCU as a CAN node against dct-hil serve
(``tcu_stub.can_tcu``: its options; ``tcu_stub.command``: its run, the C node
or the Python one)."""

from tcu_stub import can_tcu


def add_parser(sub):
    tcu = sub.add_parser(
        "tcu", help="the reference TCU stub on a CAN bus, against dct-hil serve",
        description="The reference TCU (tcu_stub.logic) as a CAN node: reads only the plant's "
                    "DBC messages, sends TCU_ClutchCmd, TCU_ShiftCmd and TCU_EngineCmd with "
                    "AliveCounter and CRC; or, with --mapping, the messages a vehicle matrix's "
                    "mapping file gives the TCU, one CAN channel per bus (--bus NAME=CHANNEL), "
                    "each frame protected and checked as the mapping says. Ctrl-C or SIGTERM "
                    "send safe values and stop.")
    can_tcu.add_arguments(tcu)
    tcu.set_defaults(func=run)


def run(args):
    from tcu_stub import command

    return command.run(args)
