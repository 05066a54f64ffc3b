"""scripts/bench-plant-compare's measurements: REF's tree and this one, alternating.

    python scripts/plant_compare.py REF REF_TREE PAIRS OUT.json

Each measurement runs in a fresh process with its tree first on the path: the
plant step's median (plant.simulate.bench, the launch-1st scenario, 200,000
steps, as dct-hil bench) and the WLTC closed loop's real-time factor
(tcu_stub.offline.run_offline in C, a fresh plant)."""

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
STEPS = 200_000

MEASURE = f"""
import json, time
import numpy as np
from plant.maneuvers import get_maneuver
from plant.model import Plant
from plant.scenario import load_scenario
from plant.simulate import bench
from tcu_stub.offline import run_offline

sc = load_scenario("launch-1st")
plant = Plant(None, sc.param_overrides())
step_us = float(np.median(bench(plant, sc, {STEPS}))) / 1e3
m = get_maneuver("wltc")
plant = Plant()
plant.reset(**m.reset_kwargs)
m.start(plant)
t0 = time.perf_counter()
run_offline(plant, m.driver, m.duration_s)
wall = time.perf_counter() - t0
print(json.dumps({{"step_median_us": step_us, "wltc_rtf": m.duration_s / wall}}))
"""


def measure(tree):
    env = dict(os.environ, PYTHONPATH=str(tree))
    r = subprocess.run([sys.executable, "-c", MEASURE], cwd=tree, env=env, capture_output=True,
                       text=True, check=False)
    if r.returncode != 0:
        sys.exit(f"bench-plant-compare: the measurement in {tree} failed: "
                 f"{' '.join(r.stderr.split()[-30:])}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv):
    ref, ref_tree, pairs, out = argv[0], Path(argv[1]).resolve(), int(argv[2]), Path(argv[3])
    sys.path.insert(0, str(ROOT))
    from plant.machine import machine_info, write_figures

    rows = []
    print(f"{'pair':>4}  {'side':<5} {'step median us':>15} {'WLTC x real time':>17}", flush=True)
    for k in range(pairs):
        order = (("ref", ref_tree), ("this", ROOT)) if k % 2 == 0 else (("this", ROOT), ("ref", ref_tree))
        for side, tree in order:
            fig = measure(tree)
            rows.append({"pair": k + 1, "side": side, **fig})
            print(f"{k + 1:>4}  {side:<5} {fig['step_median_us']:>15.3f} {fig['wltc_rtf']:>17.0f}",
                  flush=True)
    med = {side: {key: statistics.median(r[key] for r in rows if r["side"] == side)
                  for key in ("step_median_us", "wltc_rtf")} for side in ("ref", "this")}
    step_ratio = med["this"]["step_median_us"] / med["ref"]["step_median_us"]
    rtf_ratio = med["this"]["wltc_rtf"] / med["ref"]["wltc_rtf"]
    print(f"medians   ref {ref}: step {med['ref']['step_median_us']:.3f} us, WLTC "
          f"{med['ref']['wltc_rtf']:.0f}x; this tree: step {med['this']['step_median_us']:.3f} us, "
          f"WLTC {med['this']['wltc_rtf']:.0f}x")
    print(f"this/ref  step {step_ratio:.3f}x (cost), WLTC {rtf_ratio:.2f}x (speed)")
    write_figures(out, {"benchmark": "plant-compare", "ref": ref, "pairs": pairs, "steps": STEPS,
                        "rows": rows, "median": med, "step_ratio": step_ratio,
                        "wltc_rtf_ratio": rtf_ratio, "machine": machine_info(build=True)})
    print(f"figures in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
