"""dct-hil fmu: the plant as a co-simulation FMU (``plant.fmu.build``: its
options and its run)."""

from plant.fmu import build as fmu_module


def add_parser(sub):
    fmu_cmd = sub.add_parser(
        "fmu", help="write the plant as a co-simulation FMU (FMI 2.0 or 3.0)",
        description="Builds a co-simulation FMU of the plant from its own C core (compiled with "
                    "the system's C compiler, $CC or cc): modelDescription.xml with every input, "
                    "output, parameter (fixed, or tunable where plant/data/ranges.toml marks it "
                    "online), fault and initial condition; the binary for this platform; sources/ "
                    "to build it elsewhere. Internal step 0.5 ms; communication steps must be "
                    "multiples of it. Exit status: 0 written, 1 not built (the cause on one line), "
                    "2 bad options.")
    fmu_module.add_arguments(fmu_cmd)
    fmu_cmd.set_defaults(func=run)


def run(args):
    from plant.fmu import build

    return build.run(args)
