"""The subcommands of ``dct-hil``, one module each (``dct_hil.cli`` assembles
them): ``add_parser(sub)`` declares the command's options on the subparsers and
sets ``run(args)`` as its function. A command parses and dispatches; the work
is done by the package it belongs to (plant, tcu_stub, rt_loop, studies,
dct_hil.demo). Options several commands share, and the one-line user error,
are in ``options``."""

# the order of dct-hil --help
COMMANDS = ("simulate", "bench", "valve", "serve", "tcu", "demo", "doctor", "a2l", "fmu",
            "mapping", "sweep", "fit")
