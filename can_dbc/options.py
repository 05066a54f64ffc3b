"""The command-line options of a CAN matrix, for every command line that takes
one (dct-hil serve, demo, simulate, a2l, tcu): --mapping (a mapping file or a
shipped one), --dbc (a DBC read instead of the one the mapping names) and, where
the command opens buses, --bus (a bus's CAN channel). Their values are read by
``can_dbc.mapping.load_options`` and ``parse_pairs``."""

DBC_HELP = ("read this DBC instead of the one the mapping names for BUS (without BUS=: the "
            "first bus); repeatable")


def add_matrix_options(parser, mapping_help, bus_help=None, needs_mapping=False):
    """--mapping (``mapping_help``), --dbc and, with ``bus_help``, --bus on ``parser``;
    ``needs_mapping``: --dbc and --bus say that they go with --mapping."""
    prefix = "with --mapping: " if needs_mapping else ""
    parser.add_argument("--mapping", metavar="FILE_OR_NAME", help=mapping_help)
    parser.add_argument("--dbc", action="append", default=[], metavar="[BUS=]FILE",
                        help=prefix + DBC_HELP)
    if bus_help is not None:
        parser.add_argument("--bus", action="append", default=[], metavar="NAME=CHANNEL",
                            help=prefix + bus_help)
