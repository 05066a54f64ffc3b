"""The ``dct-hil sweep`` and ``dct-hil fit`` commands: their options and what they run.

``dct_hil/cli.py`` adds the subcommands with ``sweep_arguments`` /
``fit_arguments`` and calls ``sweep(args)`` / ``fit(args)``; user errors are
``StudyError`` (one line), which it reports as ``dct-hil: error: ...`` (exit 2).
Nothing heavy is imported here at module level (the parser is built for every
dct-hil command).
"""

from __future__ import annotations

import argparse
import math
import sys

from studies import StudyError


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def _seconds(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a number of seconds > 0, got {text}")
    return x


def _port(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 0-65535, got {n}")
    return n


def _engine_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, metavar="N",
                       help="worker processes of the local Dask cluster (default: every core)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster (e.g. tcp://10.0.0.5:8786); its "
                            "workers need dct-hil installed")
    p.add_argument("--dashboard", type=_port, metavar="PORT",
                   help="the local cluster's Dask dashboard on 127.0.0.1:PORT (default: off)")
    p.add_argument("--connect-timeout", type=_seconds, default=10.0, metavar="S",
                   help="seconds to reach --scheduler and find a worker (default 10)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def sweep_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC.toml",
                   help="the sweep: parameters, sampling, cases (see studies/examples/"
                        "shift_map.toml)")
    p.add_argument("--out", metavar="DIR",
                   help="results folder (default: the spec's out, else out/sweeps/<spec name>)")
    p.add_argument("--duration", type=_seconds, metavar="S",
                   help="cut every case to at most S simulated seconds (a quick look)")
    p.add_argument("--fresh", action="store_true",
                   help="forget the finished runs in the folder and compute everything")
    p.add_argument("--retry-failed", action="store_true",
                   help="compute the runs that failed before again (finished ones are kept)")
    p.add_argument("--no-plots", action="store_true", help="no PNG plots")
    p.add_argument("--dry-run", action="store_true", help="list the runs and exit")
    _engine_arguments(p)


def sweep(args: argparse.Namespace) -> int:
    from studies.sweep import load_spec, plan, print_summary, read_journal, run_sweep

    spec = load_spec(args.spec, duration_cap_s=args.duration)
    if args.dry_run:
        runs = plan(spec)
        from pathlib import Path

        out = Path(args.out or spec.out or Path("out") / "sweeps" / spec.name)
        done = read_journal(out / "runs.jsonl")
        for r in runs:
            ins = ", ".join(f"{k} = {v:.6g}" for k, v in r.inputs.items())
            state = "done" if r.run_id in done else "to run"
            print(f"{r.run_id}  point {r.point:4d}  {r.case.label:12s} {ins}  [{state}]")
        print(f"{len(runs)} runs, {sum(r.run_id in done for r in runs)} already in {out}")
        return 0
    try:
        res = run_sweep(spec, out=args.out, workers=args.workers, scheduler=args.scheduler,
                        fresh=args.fresh, retry_failed=args.retry_failed,
                        plots=not args.no_plots, progress=not args.no_progress,
                        dashboard=args.dashboard, connect_timeout_s=args.connect_timeout)
    except KeyboardInterrupt:
        print("dct-hil sweep: interrupted; the finished runs are kept: run the same command "
              "again to resume", file=sys.stderr)
        return 130
    print_summary(spec, res)
    return 0
