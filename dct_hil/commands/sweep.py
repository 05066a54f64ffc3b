"""dct-hil sweep: a parameter sweep on Dask (``studies``: its options and its run)."""

from .options import UserError


def add_parser(sub):
    from studies import cli as studies_cli

    sweep = sub.add_parser(
        "sweep", help="run a parameter sweep (grid, random, Latin hypercube) on Dask",
        description="Runs every point of SPEC.toml (plant parameters, TCU calibration values, "
                    "maneuvers or scenarios) on a local Dask cluster or --scheduler; results "
                    "as Parquet and CSV, resumable, plots (README: Sweeps and fits).")
    studies_cli.sweep_arguments(sweep)
    sweep.set_defaults(func=run)


def run(args):
    from studies import StudyError
    from studies import cli as studies_cli

    try:
        return studies_cli.sweep(args)
    except StudyError as e:
        raise UserError(str(e)) from None
