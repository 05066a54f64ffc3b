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

from dct_hil.studies import StudyError
from plant import argtypes


def _engine_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=argtypes.whole_number(1), metavar="N",
                       help="worker processes of the local Dask cluster (default: every core)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster (e.g. tcp://10.0.0.5:8786); its "
                            "workers need dct-hil installed")
    p.add_argument("--dashboard", type=argtypes.port(0), metavar="PORT",
                   help="the local cluster's Dask dashboard on 127.0.0.1:PORT (default: off)")
    p.add_argument("--connect-timeout", type=argtypes.seconds, default=10.0, metavar="S",
                   help="seconds to reach --scheduler and find a worker (default 10)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def sweep_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC.toml",
                   help="the sweep: parameters, sampling, cases (see dct_hil/studies/examples/"
                        "shift_map.toml)")
    p.add_argument("--out", metavar="DIR",
                   help="results folder (default: the spec's out, else out/sweeps/<spec name>)")
    p.add_argument("--duration", type=argtypes.seconds, metavar="S",
                   help="cut every case to at most S simulated seconds (a quick look)")
    p.add_argument("--fresh", action="store_true",
                   help="forget the finished runs in the folder and compute everything")
    p.add_argument("--retry-failed", action="store_true",
                   help="compute the runs that failed before again (finished ones are kept)")
    p.add_argument("--no-plots", action="store_true", help="no PNG plots")
    p.add_argument("--dry-run", action="store_true", help="list the runs and exit")
    _engine_arguments(p)


def sweep(args: argparse.Namespace) -> int:
    from dct_hil.studies.sweep import (
        load_spec,
        plan,
        print_summary,
        read_journal,
        run_sweep,
    )

    spec = load_spec(args.spec, duration_cap_s=args.duration)
    for note in spec.notes:
        print(f"note: {note}", file=sys.stderr)
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


def fit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("measurements", nargs="+", metavar="MEASUREMENT[@CASE]",
                   help="a recorded run (CSV as dct-hil simulate --out writes, or MF4), with "
                        "@CASE the maneuver or scenario it was recorded under (without: its "
                        "pedals are replayed with the reference TCU)")
    p.add_argument("--params", action="append", required=True, metavar="KEY[,KEY...]",
                   help="plant parameters to identify, as the parameter files name them "
                        "(vehicle.mass_kg, vehicle.drag_coefficient, tyre.rolling_resistance, "
                        "clutch[0].mu_kinetic, engine.tau_rise_s, ...); repeatable")
    p.add_argument("--signal", action="append", metavar="NAME[:SIGMA]",
                   help="plant output compared with the measurement, with its sigma (the "
                        "residual's unit; default 1); repeatable (default vehicle_speed_kmh)")
    p.add_argument("--start", action="append", metavar="KEY=VALUE",
                   help="start value of a fitted parameter (default: the car's)")
    p.add_argument("--base-params", metavar="FILE.toml",
                   help="parameter file the candidates start from (merged over the default car)")
    p.add_argument("--mapping", metavar="MAP.toml",
                   help="the measurement's channel names as the plant's (a car's signals)")
    p.add_argument("--out", default="out/fit", metavar="DIR",
                   help="fit.json, fitted.toml and fit_residuals.png go here (default out/fit)")
    p.add_argument("--diff-step", type=float, default=0.01, metavar="H",
                   help="Jacobian step as a share of each parameter (default 0.01)")
    p.add_argument("--max-evaluations", type=argtypes.whole_number(1), default=30, metavar="N",
                   help="at most N evaluations of the residuals (default 30)")
    _engine_arguments(p)


def fit(args: argparse.Namespace) -> int:
    import tomllib
    from pathlib import Path

    from dct_hil.studies import fit as fitting
    from dct_hil.studies.engine import Engine
    from dct_hil.studies.measurement import load_mapping

    if not (math.isfinite(args.diff_step) and 0 < args.diff_step <= 0.5):
        raise StudyError(f"--diff-step must be in (0, 0.5], got {args.diff_step}")
    keys = fitting.parse_params(args.params)
    signals = fitting.parse_signals(args.signal)
    start = fitting.parse_start(args.start, keys)
    base_raw = {}
    if args.base_params:
        from plant.params import ParamError, load_params

        try:
            load_params(args.base_params)
            base_raw = tomllib.loads(Path(args.base_params).read_text(encoding="utf-8"))
        except ParamError as e:
            raise StudyError(str(e)) from None
        except OSError as e:
            raise StudyError(f"--base-params {args.base_params}: cannot read: {e.strerror}") \
                from None
    mapping = load_mapping(args.mapping)
    targets = fitting.targets(args.measurements, signals, mapping)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise StudyError(f"--out {out}: cannot create the folder: {e.strerror}") from None
    n = sum(len(t.measurement.time) for t in targets) * len(signals)
    print(f"fit: {', '.join(k.text for k in keys)} from {len(targets)} measurement"
          f"{'s' if len(targets) != 1 else ''} ({n} residuals: "
          + "; ".join(f"{t.label} {t.measurement.duration_s:.1f} s as {t.case.label}"
                      for t in targets) + ")", flush=True)
    log = (lambda text: None) if args.no_progress else \
        (lambda text: print(f"  {text}", file=sys.stderr, flush=True))
    try:
        with Engine(workers=args.workers, scheduler=args.scheduler, dashboard=args.dashboard,
                    connect_timeout_s=args.connect_timeout) as engine:
            print(f"engine: {engine.description}", flush=True)
            res = fitting.fit(keys, targets, signals, start, base_raw, engine,
                              diff_step=args.diff_step, max_iterations=args.max_evaluations,
                              log=log)
            fitted = fitting.simulate_targets(keys, res.value, targets, signals, base_raw, engine)
            started = fitting.simulate_targets(keys, res.start, targets, signals, base_raw, engine)
    except KeyboardInterrupt:
        print("dct-hil fit: interrupted", file=sys.stderr)
        return 130
    files = fitting.write_outputs(out, res, targets, signals, fitted, started)
    print(f"result: {res.status} ({res.iterations} Jacobians, {res.runs} runs, "
          f"{res.wall_s:.1f} s)")
    for line in fitting.report_lines(res):
        print(line)
    for (label, sig), rms in res.rms.items():
        print(f"  residual RMS {label} {sig}: {rms:.4g}")
    for f in files:
        print(f"wrote: {f}")
    return 0 if res.success else 1
