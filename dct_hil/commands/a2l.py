"""dct-hil a2l: the A2L file of the loop's memory for an XCP master
(``rt_loop.measure.xcp.a2l``: its options and its run)."""

from rt_loop.measure.xcp import a2l as a2l_module


def add_parser(sub):
    a2l_cmd = sub.add_parser(
        "a2l", help="write the A2L (ASAP2) file of the loop's memory for an XCP master",
        description="Writes the A2L file (ASAM MCD-2 MC 1.71) of the real-time loop's memory: plant "
                    "inputs, outputs, state and parameters, the statistics, the received values and "
                    "every CAN signal's last value; writable: the inputs a test may override and the "
                    "parameters marked online in plant/data/ranges.toml. dct-hil serve --xcp serves "
                    "the same file on GET_ID. Exit status: 0 written, 1 the C extension is not "
                    "built, 2 bad options.")
    a2l_module.add_arguments(a2l_cmd)
    a2l_cmd.set_defaults(func=run)


def run(args):
    from rt_loop.measure.xcp import a2l

    return a2l.run(args)
