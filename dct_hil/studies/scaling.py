"""How the sweep scales with Dask workers: the same sweep with 1 worker, then with 2.

    .venv/bin/python -m dct_hil.studies.scaling                      # 12 runs of the WLTC
    .venv/bin/python -m dct_hil.studies.scaling --case paper-cycle --points 24

Each round starts a LocalCluster with that many worker processes (one thread each),
runs every point from scratch (``--fresh``: nothing is taken from a journal) and times
the computing part: from the first task submitted to the last result (the cluster's
start-up is timed apart). The speed-up is the 1-worker time over the 2-worker time.

Other processes on the machine take CPU from the workers, so each round also reports
the machine's load: the load averages, the CPU time the sweep (this process and its
workers) used, and the CPU time the rest of the machine used per second of the round,
in cores. A speed-up below 2x on a busy machine shows there as CPU the 2 workers did
not get. Prints the
figures and writes them to ``out/scaling.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from plant.machine import cpu_model

TARGET = 1.7


def _tree_cpu_s(proc) -> float:
    import psutil

    total = 0.0
    for p in [proc] + proc.children(recursive=True):
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def _busy_s() -> float:
    import psutil

    t = psutil.cpu_times()
    return sum(t) - t.idle - getattr(t, "iowait", 0.0)


def spec_text(case: str, duration: float | None, points: int) -> str:
    dur = f"\nduration_s = {duration:g}" if duration else ""
    return f"""\
[sweep]
sampling = "lhs"
samples = {points}
seed = 7

[[case]]
name = "{case}"{dur}

[[parameter]]
key = "vehicle.mass_kg"
range = [1300, 1600]

[[parameter]]
key = "tyre.rolling_resistance"
range = [0.008, 0.011]
"""


def one_round(spec, workers: int, folder: Path) -> dict:
    import psutil

    from dct_hil.studies.engine import Engine
    from dct_hil.studies.sweep import run_sweep

    me = psutil.Process()
    load_before = os.getloadavg()
    t0 = time.monotonic()
    with Engine(workers=workers) as engine:
        startup = time.monotonic() - t0
        ours0, busy0, w0 = _tree_cpu_s(me), _busy_s(), time.monotonic()
        res = run_sweep(spec, out=folder, engine=engine, fresh=True, plots=False,
                        progress=False, log=lambda s: None)
        w1 = time.monotonic()
        ours1, busy1 = _tree_cpu_s(me), _busy_s()
    wall = w1 - w0
    others = max(0.0, (busy1 - busy0) - (ours1 - ours0)) / wall if wall > 0 else 0.0
    runs = res.run_df
    return {"workers": workers, "runs": int(res.runs), "failed": int(res.failed),
            "compute_s": round(wall, 3), "startup_s": round(startup, 3),
            "run_wall_mean_s": round(float(runs["wall_s"].mean()), 4),
            "cpu_of_sweep_s": round(ours1 - ours0, 2),
            "cpu_of_sweep_cores": round((ours1 - ours0) / wall, 3) if wall > 0 else None,
            "cpu_of_others_cores": round(others, 3),
            "loadavg_before": [round(x, 2) for x in load_before],
            "loadavg_after": [round(x, 2) for x in os.getloadavg()]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m dct_hil.studies.scaling", description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="wltc", help="maneuver or scenario (default wltc)")
    ap.add_argument("--duration", type=float, help="cut the case to S simulated seconds")
    ap.add_argument("--points", type=int, default=12, help="runs in the sweep (default 12)")
    ap.add_argument("--out", default="out/scaling.json", help="JSON file (default out/scaling.json)")
    args = ap.parse_args(argv)
    if args.points < 2:
        ap.error("--points must be at least 2")

    from dct_hil.studies import StudyError
    from dct_hil.studies.sweep import load_spec

    with tempfile.TemporaryDirectory(prefix="dct-scaling-") as tmp:
        spec_path = Path(tmp) / "scaling.toml"
        spec_path.write_text(spec_text(args.case, args.duration, args.points))
        try:
            spec = load_spec(spec_path)
        except StudyError as e:
            print(f"dct_hil.studies.scaling: error: {e}", file=sys.stderr)
            return 2
        rounds = []
        for workers in (1, 2):
            print(f"{workers} worker{'s' if workers > 1 else ''}: {args.points} runs of "
                  f"{args.case} ...", flush=True)
            r = one_round(spec, workers, Path(tmp) / f"w{workers}")
            rounds.append(r)
            print(f"  {r['compute_s']:.2f} s computing ({r['startup_s']:.1f} s cluster start), "
                  f"{r['run_wall_mean_s']:.3f} s per run on its worker, failed {r['failed']}; "
                  f"the sweep used {r['cpu_of_sweep_s']:.1f} CPU s, "
                  f"{r['cpu_of_sweep_cores']:.2f} cores, other processes "
                  f"{r['cpu_of_others_cores']:.2f} cores; load average "
                  f"{r['loadavg_before'][0]:.2f} before, {r['loadavg_after'][0]:.2f} after",
                  flush=True)
    speedup = rounds[0]["compute_s"] / rounds[1]["compute_s"]
    cores = os.cpu_count()
    result = {"case": args.case, "duration_s": args.duration, "runs": args.points,
              "speedup_2_over_1": round(speedup, 3), "target": TARGET,
              "met": speedup >= TARGET, "rounds": rounds,
              "machine": {"cpus": cores, "cpu_model": cpu_model(),
                          "python": platform.python_version()},
              "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    busy = max(r["cpu_of_others_cores"] for r in rounds)
    cores_ratio = rounds[1]["cpu_of_sweep_cores"] / rounds[0]["cpu_of_sweep_cores"]
    result["cores_got_2_over_1"] = round(cores_ratio, 3)
    out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    print(f"speed-up 1 -> 2 workers: {speedup:.2f}x (target {TARGET}x: "
          f"{'met' if speedup >= TARGET else 'NOT met'}) on {cores} CPUs; other processes "
          f"used up to {busy:.2f} cores meanwhile; the 2 workers got {cores_ratio:.2f}x the "
          "CPU the 1 worker got")
    print(f"json: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
