"""Speed of the FMU under FMPy against the plant's own offline run.

    python -m plant.fmu.bench [--fmi 2|3] [--step-s 0.01] [--duration-s 1800]
                              [--repeat 3] [--json out/fmu_bench.json]

All run the same inputs of the WLTC's length (1800 s, ``wltc_inputs``: a
launch in 1st, then the pedal following the class 3b speed trace of
plant/data/wltc_class3b.csv), every output recorded every communication step. Offline: ``plant.simulate.run`` (the
plant stepped in C between rows, every output recorded). FMU: FMPy's
``simulate_fmu`` at the communication step (inputs set, a ``doStep`` and
every output read per step, in Python), and a lean master on FMPy's
``FMU2Slave``/``FMU3Slave`` (``lean_master``: what the FMU itself costs).
Each is timed ``--repeat`` times,
alternately, on this machine in one run; the best of each is reported with
the ratio (target: the FMU within 2x of the offline run).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

from plant import simulate
from plant.fmu import build
from plant.model import Plant
from plant.scenario import Scenario

_WLTC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data",
                     "wltc_class3b.csv")


def wltc_inputs(duration_s: float = 1800.0) -> Scenario:
    """Open-loop inputs of the WLTC's length (a Scenario, rows at 1 s after
    the launch): the launch-1st scenario's launch (its first 4.5 s), then, K1
    kept closed in 1st, the pedal following the class 3b speed trace
    (10 % + 0.4 %/(km/h)), so the powertrain is driven the whole time."""
    from plant.scenario import load_scenario
    launch = load_scenario("launch-1st")
    data = np.loadtxt(_WLTC, delimiter=",", comments="#", skiprows=4)
    v = data[:, 1]
    t_end = float(launch.times[-1])
    later = np.arange(np.floor(t_end) + 1.0, duration_s + 0.5, 1.0)
    speed = np.tile(v, int(np.ceil(len(later) / len(v))) + 1)[:len(later)]
    rows = np.zeros((len(later), len(launch.columns)))
    rows[:] = launch.values[-1]
    rows[:, launch.columns.index("accel_pedal_pct")] = 10.0 + 0.4 * speed
    times = np.concatenate([launch.times, later])
    values = np.vstack([launch.values, rows])
    return Scenario("wltc-length", times, list(launch.columns), values, dict(launch.initial))


def _table(s: Scenario) -> np.ndarray:
    from plant.fmu.scenario import input_table
    return input_table(s)


def lean_master(unzipdir: str, md, scenario: Scenario, step_s: float, start: dict) -> np.ndarray:
    """A master without per-step Python beyond the FMI calls, on FMPy's
    FMU2Slave / FMU3Slave: the inputs set when a row changes, ``doStep``,
    every output read into a preallocated array (what a compiled master
    does; FMPy's ``simulate_fmu`` adds its input-event scan, interpolation
    and recorder in Python at every step). Returns the outputs, one row
    per communication point."""
    import ctypes

    from fmpy.fmi2 import FMU2Slave
    from fmpy.fmi3 import FMU3Slave
    v3 = md.fmiVersion.startswith("3")
    vr = {v.name: v.valueReference for v in md.modelVariables}
    outs = [v.valueReference for v in md.modelVariables if v.causality == "output"]
    cls = FMU3Slave if v3 else FMU2Slave
    fmu = cls(guid=md.guid, unzipDirectory=unzipdir, modelIdentifier=md.coSimulation.modelIdentifier,
              instanceName="lean")
    fmu.instantiate()
    if not v3:
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
    else:
        fmu.enterInitializationMode(startTime=0.0)
    set_real = fmu.setFloat64 if v3 else fmu.setReal
    for name, value in start.items():
        set_real([vr[name]], [value])
    in_vr = [vr[c] for c in scenario.columns]
    set_real(in_vr, list(scenario.values[0]))
    fmu.exitInitializationMode()
    n_steps = int(round(scenario.duration_s / step_s))
    out = np.empty((n_steps + 1, len(outs)))
    c = fmu.component
    out_vr = (ctypes.c_uint32 * len(outs))(*outs)
    in_vrs = (ctypes.c_uint32 * len(in_vr))(*in_vr)
    values = (ctypes.c_double * len(in_vr))()
    buf = (ctypes.c_double * len(outs))()
    view = np.frombuffer(buf, dtype=np.float64)
    if v3:
        get = lambda: fmu.fmi3GetFloat64(c, out_vr, len(outs), buf, len(outs))  # noqa: E731 (bound before the timed loop)
        put = lambda: fmu.fmi3SetFloat64(c, in_vrs, len(in_vr), values, len(in_vr))  # noqa: E731 (bound before the timed loop)
        ev, term, early, last = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(),
                                 ctypes.c_double())
        step = lambda t: fmu.fmi3DoStep(c, t, step_s, True, ctypes.byref(ev), ctypes.byref(term),  # noqa: E731 (bound before the timed loop)
                                        ctypes.byref(early), ctypes.byref(last))
    else:
        get = lambda: fmu.fmi2GetReal(c, out_vr, len(outs), buf)  # noqa: E731 (bound before the timed loop)
        put = lambda: fmu.fmi2SetReal(c, in_vrs, len(in_vr), values)  # noqa: E731 (bound before the timed loop)
        step = lambda t: fmu.fmi2DoStep(c, t, step_s, 1)  # noqa: E731 (bound before the timed loop)
    get()
    out[0] = view
    row_k = scenario.row_steps(step_s)
    row = 1
    for k in range(n_steps):
        if row < len(row_k) and row_k[row] <= k:
            while row < len(row_k) and row_k[row] <= k:
                row += 1
            values[:] = list(scenario.values[row - 1])
            put()
        step(k * step_s)
        get()
        out[k + 1] = view
    fmu.terminate()
    fmu.freeInstance()
    return out


def run(fmi: int = 2, step_s: float = 0.01, duration_s: float = 1800.0, repeat: int = 3,
        json_path: str | None = None, out=sys.stdout) -> dict:
    import fmpy

    from plant.fmu.scenario import start_values
    scenario = wltc_inputs(duration_s)
    table = _table(scenario)
    start = start_values(scenario)
    offline_s, fmu_s, lean_s = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "dct_plant.fmu")
        build.build(path, fmi)
        unzipdir = fmpy.extract(path, os.path.join(tmp, "u"))
        md = fmpy.read_model_description(unzipdir)
        for _ in range(repeat):
            plant = Plant(None, scenario.param_overrides())
            t0 = time.perf_counter()
            res = simulate.run(plant, scenario, record_every_s=step_s)
            offline_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            fres = fmpy.simulate_fmu(unzipdir, stop_time=scenario.duration_s, step_size=step_s, output_interval=step_s,
                                     input=table, start_values=start, model_description=md)
            fmu_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            lean = lean_master(unzipdir, md, scenario, step_s, start)
            lean_s.append(time.perf_counter() - t0)
        speed_vr = [v.name for v in md.modelVariables if v.causality == "output"].index(
            "vehicle_speed_kmh")
    k = res.names.index("vehicle_speed_kmh")
    same = bool(np.array_equal(fres["vehicle_speed_kmh"], res.data[:, k])
                and np.array_equal(lean[:, speed_vr], res.data[:, k]))
    best_off, best_fmu, best_lean = min(offline_s), min(fmu_s), min(lean_s)
    report = {
        "fmi": fmi, "communication_step_s": step_s, "simulated_s": scenario.duration_s,
        "outputs_recorded": len(res.names),
        "offline_s": offline_s, "fmu_s": fmu_s, "lean_master_s": lean_s,
        "offline_best_s": best_off, "fmu_best_s": best_fmu, "lean_master_best_s": best_lean,
        "offline_real_time_factor": scenario.duration_s / best_off,
        "fmu_real_time_factor": scenario.duration_s / best_fmu,
        "lean_master_real_time_factor": scenario.duration_s / best_lean,
        "ratio": best_fmu / best_off, "lean_master_ratio": best_lean / best_off,
        "target_ratio": 2.0,
        "target_met": best_fmu <= 2.0 * best_off,
        "lean_master_target_met": best_lean <= 2.0 * best_off,
        "same_vehicle_speed": same,
    }
    print(f"{scenario.duration_s:.0f} s of WLTC-length inputs, communication step "
          f"{step_s * 1e3:g} ms, best of {repeat}:", file=out)
    print(f"  plant offline (plant.simulate.run)   {best_off:7.2f} s   "
          f"{report['offline_real_time_factor']:7.0f}x real time", file=out)
    print(f"  FMU {fmi}.0 through FMPy (simulate_fmu) {best_fmu:7.2f} s   "
          f"{report['fmu_real_time_factor']:7.0f}x real time", file=out)
    print(f"  FMU {fmi}.0, lean master on FMPy's FMU{fmi}Slave {best_lean:5.2f} s   "
          f"{report['lean_master_real_time_factor']:7.0f}x real time", file=out)
    print(f"  ratio simulate_fmu {report['ratio']:.2f}, lean master "
          f"{report['lean_master_ratio']:.2f} (target <= 2.0: simulate_fmu "
          f"{'met' if report['target_met'] else 'NOT met'}, lean master "
          f"{'met' if report['lean_master_target_met'] else 'NOT met'}); "
          f"same vehicle speed trace: {same}", file=out)
    if json_path:
        os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
        with open(json_path, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=2)
        print(f"  written: {json_path}", file=out)
    return report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m plant.fmu.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--fmi", type=int, choices=(2, 3), default=2)
    ap.add_argument("--step-s", type=float, default=0.01)
    ap.add_argument("--duration-s", type=float, default=1800.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default="out/fmu_bench.json")
    a = ap.parse_args(argv)
    report = run(a.fmi, a.step_s, a.duration_s, a.repeat, a.json)
    return 0 if report["same_vehicle_speed"] else 1


if __name__ == "__main__":
    sys.exit(main())
