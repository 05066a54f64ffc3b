"""Offline runs: a scenario through the plant as fast as the CPU goes.

The plant is stepped in chunks that end at the next scenario row or the next
record time, so each chunk is one FFI call; between chunks Python only
writes inputs and copies one row of outputs.
"""

import math
import time
from dataclasses import dataclass

import numpy as np

from plant.model import PlantError


@dataclass
class SimResult:
    simulated_s: float        # simulated time covered
    wall_s: float             # wall time of the stepping loop (perf_counter)
    real_time_factor: float   # simulated_s / wall_s
    data: np.ndarray          # recorded outputs, shape (records, len(names))
    names: list               # dct_outputs fields, time_s first
    steps: int
    out_path: str = None
    complete: bool = True     # False when interrupted or stopped by a PlantError


def start(plant, scenario):
    """Reset the plant to the scenario's initial conditions and default inputs."""
    plant.inputs[()] = plant.default_inputs   # before reset: it sets engine_on
    plant.reset(**scenario.reset_kwargs())


def _apply(plant, scenario, row):
    for name, value in zip(scenario.columns, scenario.values[row]):
        plant.inputs[name] = value


def run(plant, scenario, duration_s=None, out_path=None, record_every_s=0.01):
    """Run ``scenario`` (default: its own length) and record the outputs.

    Writes the records as CSV to ``out_path`` if given, also the part done
    when a KeyboardInterrupt or a PlantError stops the run (then re-raised).
    """
    h = plant.step_s
    duration = scenario.duration_s if duration_s is None else float(duration_s)
    if not (math.isfinite(duration) and duration >= 0):
        raise ValueError(f"duration must be a finite number >= 0, got {duration_s}")
    if not (math.isfinite(record_every_s) and record_every_s > 0):
        raise ValueError(f"record interval must be > 0, got {record_every_s}")
    n_end = int(round(duration / h))
    every = max(1, int(round(record_every_s / h)))
    names = list(plant.output_names)
    data = np.empty((n_end // every + 1, len(names)))
    row_k = scenario.row_steps(h)
    n_rows = len(row_k)

    start(plant, scenario)
    k = 0          # steps done
    j = 0          # records done
    row = 0        # next scenario row
    wall0 = time.perf_counter()
    try:
        while True:
            while row < n_rows and row_k[row] <= k:
                _apply(plant, scenario, row)
                row += 1
            if k == j * every:
                data[j] = plant.output_values
                j += 1
            if k >= n_end:
                break
            target = min(n_end, j * every)
            if row < n_rows:
                target = min(target, int(row_k[row]))
            plant.step(target - k)
            k = target
    except (KeyboardInterrupt, PlantError):
        if out_path is not None:
            write_csv(out_path, names, data[:j])
        raise
    wall = time.perf_counter() - wall0

    if out_path is not None:
        write_csv(out_path, names, data[:j])
    return SimResult(
        simulated_s=k * h,
        wall_s=wall,
        real_time_factor=(k * h / wall) if wall > 0 else math.inf,
        data=data[:j],
        names=names,
        steps=k,
        out_path=out_path,
    )


def write_csv(path, names, data):
    """Outputs as CSV: header of names, time_s in full, other values %.6g."""
    fmt = ["%.10g" if n == "time_s" else "%.6g" for n in names]
    np.savetxt(path, data, fmt=fmt, delimiter=",", header=",".join(names), comments="")


def bench(plant, scenario, n_steps, out=None):
    """Cost of ``n_steps`` single steps (ns each) while the scenario plays.

    Rows are applied as in ``run``; at the scenario's end the plant is reset
    and the scenario starts over, so every phase of it is sampled.
    """
    ns = np.empty(n_steps) if out is None else out
    row_k = scenario.row_steps(plant.step_s)
    n_rows = len(row_k)
    n_end = int(row_k[-1])
    start(plant, scenario)
    k = row = i = 0
    while i < n_steps:
        while row < n_rows and row_k[row] <= k:
            _apply(plant, scenario, row)
            row += 1
        if n_end > 0 and k >= n_end:
            start(plant, scenario)
            k = row = 0
            continue
        if row < n_rows:
            chunk = int(row_k[row]) - k
        elif n_end > 0:
            chunk = n_end - k
        else:
            chunk = n_steps - i
        chunk = min(chunk, n_steps - i)
        plant.bench(chunk, out=ns[i:i + chunk])
        i += chunk
        k += chunk
    return ns


# ------------------------------------------------------------------- benchmark
TARGET_MEDIAN_US = 2.0   # step-cost target of the real-time loop (0.5 ms step)
MAX_BENCH_STEPS = 100_000_000


def bench_figures(step_ns, step_s):
    """Summary of per-step costs (ns) in microseconds."""
    import numpy as np

    us = np.asarray(step_ns) / 1e3
    mean = float(us.mean())
    return {
        "median_us": float(np.median(us)),
        "p90_us": float(np.percentile(us, 90)),
        "p99_us": float(np.percentile(us, 99)),
        "p99_9_us": float(np.percentile(us, 99.9)),
        "max_us": float(us.max()),
        "mean_us": mean,
        "real_time_factor": step_s * 1e6 / mean if mean > 0 else math.inf,
        "steps_per_s": 1e6 / mean if mean > 0 else math.inf,
    }


def bench_report(scenario, params_path, steps, repeat=1):
    """``bench`` ``repeat`` times on a fresh plant each, the figures of each run
    and, at the top, those of the run with the lowest median (the code's cost
    with the least interference from the machine), with this machine's facts:
    the report ``dct-hil bench`` writes (``target_median_us`` at the time)."""
    from plant.machine import machine_info
    from plant.model import Plant

    runs = []
    for _ in range(repeat):
        plant = Plant(params_path, scenario.param_overrides())
        runs.append(bench_figures(bench(plant, scenario, steps), plant.step_s))
    best = min(range(len(runs)), key=lambda k: runs[k]["median_us"])
    return {
        "steps": steps,
        "scenario": scenario.name,
        "step_s": plant.step_s,
        **runs[best],
        "repeat": repeat,
        "best_run": best + 1,
        "runs": runs,
        "target_median_us": TARGET_MEDIAN_US,
        "machine": machine_info(build=True),
    }
