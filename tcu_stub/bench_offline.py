"""Benchmark of the offline closed loop: ``python -m tcu_stub.bench_offline``.

In one run, on one core (one process, one thread), each figure the best of
``--repeat`` runs with the spread (other processes may share the machine):

- ``c_loop``: plant + reference TCU + driver + CAN contract in C
  (``tcu_stub.fast``, what run_offline and dct-hil simulate use), a whole
  maneuver (default the WLTC, 1800 s): wall time and real-time factor;
- ``split``: C runs with the time in the plant's steps and in the rest (TCU,
  link, driver, recording) measured apart (two clock reads a period; the
  fastest run's); the plant's part is the plant alone on the same trajectory;
- ``plant_alone``: the plant stepped with fixed inputs (a cruise in 3rd at
  50 km/h) in one C call, as long as the maneuver;
- ``python_loop``: run_offline's Python loop (tcu_stub/logic.py stepped from
  Python, the codec of can_dbc/codec.py), the first ``--python-duration`` s
  of the maneuver (the whole maneuver with ``--python-duration 0``).

Prints the figures and writes them as JSON (``--json``, default
out/offline_bench.json) with the machine, the load averages before and after,
and every repeat. The C loop runs one car per call; there is no batch (the
plant is most of the loop's time, see ``split``, so several cars per call
would save little of it on one core).
"""

import argparse
import json
import os
import statistics
import sys
import time

TARGET_RTF = 200.0


def _maneuver_run(name, duration_s, impl, split=False):
    """(wall s, plant s, other s, figures, shifts) of one run."""
    from plant.maneuvers import get_maneuver, report
    from plant.model import Plant
    from tcu_stub import fast, offline

    m = get_maneuver(name)
    plant = Plant()
    plant.reset(**m.reset_kwargs)
    duration = duration_s or m.duration_s
    if impl == "python":
        t0 = time.perf_counter()
        rec = offline.run_offline(plant, m.driver, duration, tcu_impl="python")
        wall = time.perf_counter() - t0
        return wall, None, None, report(m, rec), len(rec["shifts"])
    loop = fast.FastLoop(plant, m.driver, duration, record_outputs=offline.RECORDED)
    loop.run.time_split = 1 if split else 0
    t0 = time.perf_counter()
    loop.step()
    wall = time.perf_counter() - t0
    rec = loop.recorded()
    return (wall, float(loop.run.plant_s) if split else None, float(loop.run.other_s) if split else None,
            report(m, rec), len(loop.shifts))


def _plant_alone(duration_s):
    """Wall time of ``duration_s`` of plant steps with fixed inputs in one C call."""
    from plant.model import Plant

    plant = Plant()
    plant.reset(vehicle_speed_kmh=50.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    plant.inputs["accel_pedal_pct"] = 20.0
    plant.inputs["solenoid_current1_a"] = 0.75
    plant.inputs["fork_force1_n"] = -80.0
    n = int(round(duration_s / plant.step_s))
    t0 = time.perf_counter()
    plant.step(n)
    return time.perf_counter() - t0


def _summary(walls, simulated_s):
    best = min(walls)
    return {
        "simulated_s": simulated_s,
        "wall_s": walls,
        "wall_best_s": best,
        "wall_median_s": statistics.median(walls),
        "real_time_factor_best": simulated_s / best,
        "real_time_factor_median": simulated_s / statistics.median(walls),
        "real_time_factor_worst": simulated_s / max(walls),
    }


def bench(maneuver="wltc", repeat=3, python_duration_s=120.0, progress=print):
    """The figures (a JSON-ready dict)."""
    from plant.machine import machine_info
    from plant.maneuvers import get_maneuver

    duration = get_maneuver(maneuver).duration_s
    py_duration = python_duration_s or duration
    load_before = os.getloadavg()
    out = {"maneuver": maneuver, "repeat": repeat, "target_real_time_factor": TARGET_RTF}

    walls, figures = [], None
    for i in range(repeat):
        wall, _, _, figures, shifts = _maneuver_run(maneuver, None, "c")
        walls.append(wall)
        progress(f"  c loop        run {i + 1}/{repeat}: {wall:.2f} s ({duration / wall:.0f}x)")
    out["c_loop"] = _summary(walls, duration)
    out["c_loop"]["figures"] = figures
    out["c_loop"]["shifts"] = shifts

    splits = []
    for i in range(repeat):
        wall, plant_s, other_s, _, _ = _maneuver_run(maneuver, None, "c", split=True)
        splits.append((wall, plant_s, other_s))
        progress(f"  split         run {i + 1}/{repeat}: plant {plant_s:.2f} s, the rest {other_s:.2f} s")
    wall, plant_s, other_s = min(splits)
    periods = int(round(duration / 0.002))
    out["split"] = {"wall_s": wall, "plant_s": plant_s, "other_s": other_s,
                    "plant_share": plant_s / (plant_s + other_s),
                    "plant_us_per_period": plant_s / periods * 1e6,
                    "other_us_per_period": other_s / periods * 1e6,
                    "plant_real_time_factor": duration / plant_s,
                    "runs": [{"wall_s": w, "plant_s": p, "other_s": o} for w, p, o in splits]}

    walls = []
    for i in range(repeat):
        walls.append(_plant_alone(duration))
        progress(f"  plant alone   run {i + 1}/{repeat}: {walls[-1]:.2f} s ({duration / walls[-1]:.0f}x)")
    out["plant_alone"] = _summary(walls, duration)

    walls = []
    for i in range(repeat):
        wall, _, _, figures, shifts = _maneuver_run(maneuver, py_duration, "python")
        walls.append(wall)
        progress(f"  python loop   run {i + 1}/{repeat}: {wall:.2f} s for {py_duration:g} s "
                 f"({py_duration / wall:.1f}x)")
    out["python_loop"] = _summary(walls, py_duration)
    out["python_loop"]["figures"] = figures
    out["speedup_best"] = out["c_loop"]["real_time_factor_best"] / out["python_loop"]["real_time_factor_best"]
    out["batch"] = None
    out["load_average_before"] = list(load_before)
    out["load_average_after"] = list(os.getloadavg())
    out["machine"] = machine_info(build=True)
    return out


def print_report(r):
    c, s, p, py = r["c_loop"], r["split"], r["plant_alone"], r["python_loop"]
    print(f"offline closed loop, {r['maneuver']} ({c['simulated_s']:g} s), one core, best of "
          f"{r['repeat']} (worst in brackets):")
    print(f"  c loop (plant + reference TCU + driver + CAN contract in C): "
          f"{c['wall_best_s']:.2f} s [{max(c['wall_s']):.2f}] -> {c['real_time_factor_best']:.0f}x real time "
          f"[{c['real_time_factor_worst']:.0f}x]  (target {r['target_real_time_factor']:.0f}x: "
          f"{'met' if c['real_time_factor_best'] >= r['target_real_time_factor'] else 'NOT met'})")
    print(f"  where it goes (fastest timed run): plant {s['plant_us_per_period']:.2f} us + the rest "
          f"{s['other_us_per_period']:.2f} us per 2 ms TCU period; plant {100 * s['plant_share']:.0f} %, "
          f"plant alone on this trajectory {s['plant_real_time_factor']:.0f}x")
    print(f"  plant alone (cruise, fixed inputs, one C call): {p['wall_best_s']:.2f} s "
          f"[{max(p['wall_s']):.2f}] -> {p['real_time_factor_best']:.0f}x [{p['real_time_factor_worst']:.0f}x]")
    print(f"  python loop (run_offline's, first {py['simulated_s']:g} s): {py['wall_best_s']:.2f} s "
          f"[{max(py['wall_s']):.2f}] -> {py['real_time_factor_best']:.1f}x "
          f"[{py['real_time_factor_worst']:.1f}x]; the c loop is {r['speedup_best']:.0f}x faster")
    print("  batch: none (one car per C call; the plant is most of the loop)")
    print(f"  figures (c loop): {c['figures']}, shifts {c['shifts']}")
    print(f"  load average before {r['load_average_before'][0]:.2f}, after {r['load_average_after'][0]:.2f} "
          f"({r['machine']['nproc']} CPUs)")


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m tcu_stub.bench_offline",
                                 description="real-time factor of the offline closed loop, C and Python")
    ap.add_argument("--maneuver", default="wltc", help="paper-cycle, wltc, nedc or 0-100 (default wltc)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each measurement (default 3)")
    ap.add_argument("--python-duration", type=float, default=120.0, metavar="S",
                    help="simulated seconds of the Python loop (default 120; 0: the whole maneuver)")
    ap.add_argument("--json", default="out/offline_bench.json", metavar="FILE", help="write the figures here")
    args = ap.parse_args(argv)
    if args.repeat < 1 or args.python_duration < 0:
        ap.error("--repeat must be >= 1 and --python-duration >= 0")
    from plant.maneuvers import MANEUVERS
    if args.maneuver not in MANEUVERS:
        ap.error(f"unknown maneuver {args.maneuver!r}; choose from {', '.join(MANEUVERS)}")
    r = bench(args.maneuver, args.repeat, args.python_duration)
    print_report(r)
    folder = os.path.dirname(os.path.abspath(args.json))
    os.makedirs(folder, exist_ok=True)
    with open(args.json, "w", encoding="utf-8") as f:
        json.dump(r, f, indent=2)
    print(f"  json: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
