"""dct-hil sweep: a parameter sweep on Dask (``studies``: its options and its run)."""

from . import options


def add_parser(sub):
    from dct_hil.studies import cli as studies_cli

    sweep = sub.add_parser(
        "sweep", help="run a parameter sweep (grid, random, Latin hypercube) on Dask",
        description="Runs every point of SPEC.toml (plant parameters, TCU calibration values, "
                    "maneuvers or scenarios) on a local Dask cluster or --scheduler; results "
                    "as Parquet and CSV, resumable, plots (the manual: docs/studies.md).")
    studies_cli.sweep_arguments(sweep)
    sweep.set_defaults(func=run)


def run(args):
    return options.run_study("sweep", args)
