"""dct-hil fit: plant parameters from recorded runs, least squares on Dask
(``studies``: its options and its run)."""

from . import options


def add_parser(sub):
    from dct_hil.studies import cli as studies_cli

    fit = sub.add_parser(
        "fit", help="identify plant parameters from a recorded run (least squares on Dask)",
        description="Fits the chosen plant parameters to recorded runs (CSV or MF4, a car's "
                    "signals through --mapping) by least squares, the candidate runs on Dask; "
                    "prints the values with 95 %% confidence intervals, writes the residual "
                    "plot (the manual: docs/studies.md).")
    studies_cli.fit_arguments(fit)
    fit.set_defaults(func=run)


def run(args):
    return options.run_study("fit", args)
