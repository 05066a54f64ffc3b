"""One run of a study: a case (maneuver or scenario) with parameter overrides and a
TCU calibration, and the figures of the result. This is what the workers execute.

A case is

- a maneuver (``paper-cycle``, ``wltc``, ``nedc``, ``0-100``): the closed loop of the
  plant and the reference TCU through ``tcu_stub.offline.run_offline``, the figures of
  ``plant.maneuvers.report``;
- a scenario (a shipped name or a CSV file): played open-loop by ``plant.simulate.run``
  when it scripts the clutches or forks (``tcu = "none"``), else with the reference TCU
  in the loop (the scenario gives the pedals and the road grade, applied every 10 ms as
  the driver's inputs are).

A case may be cut short with ``duration_s``. The scenario itself travels with the task
(its rows, not its path), so a worker on another machine needs only the package.

Figures (``FIGURES``; NaN where not defined): ``zero_to_100_s`` (from the first full
pedal at standstill), ``top_speed_kmh``, ``fuel_l_per_100km``, ``rms_speed_error_kmh``
(speed-tracking maneuvers), ``shifts`` (the TCU's shifts in a closed loop, the plant's
gear changes held 0.1 s open-loop), ``gear_clashes``, ``max_jerk_mps3`` (the largest
|d a / d t| of the vehicle acceleration sampled every 10 ms after a 50 ms moving
average), ``distance_km``, ``fuel_l``, ``final_speed_kmh``, ``simulated_s``.
"""

from __future__ import annotations

import math
import os
import socket
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dct_hil.studies import StudyError

FIGURES = ("zero_to_100_s", "top_speed_kmh", "fuel_l_per_100km", "rms_speed_error_kmh",
           "shifts", "gear_clashes", "max_jerk_mps3", "distance_km", "fuel_l",
           "final_speed_kmh", "simulated_s")
UNITS = {"zero_to_100_s": "s", "top_speed_kmh": "km/h", "fuel_l_per_100km": "l/100 km",
         "rms_speed_error_kmh": "km/h", "shifts": "", "gear_clashes": "",
         "max_jerk_mps3": "m/s3", "distance_km": "km", "fuel_l": "l", "final_speed_kmh": "km/h",
         "simulated_s": "s"}
RECORD_EVERY_S = 0.01
JERK_WINDOW = 5            # samples of the moving average before the derivative (50 ms)


@dataclass(frozen=True)
class Case:
    """What a run plays: ``kind`` "maneuver" or "scenario"; ``label`` names it in the
    results (default: the name)."""

    label: str
    kind: str
    name: str
    duration_s: float | None = None
    scenario: Any = field(default=None, compare=False, repr=False)
    tcu: str = "stub"          # "stub" (closed loop) or "none" (open loop)

    def identity(self) -> dict:
        """What decides the run's result (for its hash)."""
        out: dict = {"kind": self.kind, "name": self.name, "duration_s": self.duration_s,
                     "tcu": self.tcu}
        if self.scenario is not None:
            sc = self.scenario
            out["scenario"] = {"columns": list(sc.columns), "times": [float(x) for x in sc.times],
                               "values": [[float(x) for x in row] for row in sc.values],
                               "initial": dict(sorted(sc.initial.items()))}
        return out

    def length_s(self) -> float:
        if self.duration_s is not None:
            return self.duration_s
        if self.kind == "scenario":
            return self.scenario.duration_s
        from plant.maneuvers import get_maneuver

        return get_maneuver(self.name).duration_s


def make_case(name: str, duration_s: float | None = None, label: str | None = None,
              tcu: str | None = None, where: str = "") -> Case:
    """A Case from a maneuver name, a shipped scenario name or a scenario CSV path."""
    from plant.maneuvers import MANEUVERS
    from plant.scenario import ScenarioError, load_scenario

    prefix = f"{where}: " if where else ""
    if duration_s is not None and not (isinstance(duration_s, (int, float))
                                       and math.isfinite(duration_s) and duration_s > 0):
        raise StudyError(f"{prefix}case {name!r}: duration_s must be a number > 0, "
                         f"got {duration_s!r}")
    duration = None if duration_s is None else float(duration_s)
    if name in MANEUVERS:
        if tcu == "none":
            raise StudyError(f"{prefix}case {name!r}: a maneuver needs the TCU stub (tcu = \"stub\")")
        return Case(label or name, "maneuver", name, duration)
    try:
        sc = load_scenario(name)
    except ScenarioError as e:
        msg = str(e)
        if msg.startswith("unknown scenario"):
            msg += f"; maneuvers: {', '.join(MANEUVERS)}"
        raise StudyError(f"{prefix}{msg}") from None
    scripted = sorted(set(sc.columns) & tcu_columns())
    mode = tcu or ("none" if scripted else "stub")
    if mode == "stub" and scripted:
        raise StudyError(f"{prefix}case {name!r}: the scenario scripts {', '.join(scripted)}, "
                         "which the TCU stub drives; use tcu = \"none\"")
    if mode not in ("stub", "none"):
        raise StudyError(f"{prefix}case {name!r}: tcu must be \"stub\" or \"none\", got {tcu!r}")
    return Case(label or sc.name, "scenario", sc.name, duration, sc, mode)


def tcu_columns() -> set:
    """Scenario columns the TCU stub drives itself (clutches, forks, engine requests)."""
    from can_dbc import codec
    from plant.scenario import PRESSURE_COLUMNS

    cols = set(PRESSURE_COLUMNS)
    for targets in codec.TCU_SIGNAL_TARGETS.values():
        cols.update(input_name for _, input_name in targets.values())
    return cols


# ----------------------------------------------------------------- simulating
def simulate(case: Case, overrides: dict | None = None, calibration: dict | None = None,
             record_every_s: float = RECORD_EVERY_S) -> tuple[dict, list | None]:
    """Run ``case``; returns (recorded arrays by name, the TCU's shifts or None open-loop)."""
    from dct_hil.studies.keys import merge
    from plant.model import Plant
    from plant.simulate import run, start

    overrides = dict(overrides or {})
    if case.kind == "maneuver":
        from plant.maneuvers import get_maneuver

        m = get_maneuver(case.name)
        duration = m.duration_s if case.duration_s is None else case.duration_s

        def setup():
            plant = Plant(None, overrides or None)
            m.start(plant)                      # its reset and fixed inputs (a hill's grade)
            return plant, m.driver

        return _closed_loop(setup, duration, record_every_s, calibration)
    sc = case.scenario
    duration = sc.duration_s if case.duration_s is None else case.duration_s
    if case.tcu == "none":
        plant = Plant(None, merge(overrides, sc.param_overrides()) or None)
        res = run(plant, sc, duration_s=duration, record_every_s=record_every_s)
        return {n: res.data[:, k] for k, n in enumerate(res.names)}, None

    def setup():
        plant = Plant(None, merge(overrides, sc.param_overrides()) or None)
        start(plant, sc)
        return plant, _scenario_driver(plant, sc)

    return _closed_loop(setup, duration, record_every_s, calibration)


def _closed_loop(setup, duration, record_every_s, calibration):
    """run_offline on a fresh plant and driver from ``setup()``, with the calibration
    given through run_offline's own ``calibration`` argument where it has one
    (tcu_stub's documented way), else (or when tcu_stub cannot make its calibrated
    TCU: an ImportError before the run starts) as a TcuLogic of a calibrated copy
    of tcu_stub.logic (``dct_hil.studies.tcu``), passed as ``tcu``."""
    import inspect

    from dct_hil.studies.tcu import make_tcu
    from tcu_stub.offline import run_offline

    plant, driver = setup()
    if calibration and "calibration" in inspect.signature(run_offline).parameters:
        try:
            rec = run_offline(plant, driver, duration, record_every_s=record_every_s,
                              calibration=dict(calibration))
            return _arrays(rec), list(rec["shifts"])
        except ImportError:
            plant, driver = setup()
    kw = {"tcu": make_tcu(calibration)} if calibration else {}
    rec = run_offline(plant, driver, duration, record_every_s=record_every_s, **kw)
    return _arrays(rec), list(rec["shifts"])


def _arrays(rec: dict) -> dict:
    out = {}
    for k, v in rec.items():
        if k == "shifts":
            continue
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            continue
        if a.ndim == 1:
            out[k] = a
    return out


def _scenario_driver(plant, sc):
    """driver_fn for run_offline that plays a scenario's rows: every 10 ms (the driver's
    period) the row in force sets its columns (pedals returned, the others, e.g. the road
    grade, written into the plant's inputs)."""
    cols = list(sc.columns)
    ia = cols.index("accel_pedal_pct") if "accel_pedal_pct" in cols else None
    ib = cols.index("brake_pedal_pct") if "brake_pedal_pct" in cols else None
    others = [(k, c) for k, c in enumerate(cols) if k not in (ia, ib)]

    def driver(t, outputs):
        vals = sc.values_at(t)
        for k, name in others:
            plant.inputs[name] = vals[k]
        accel = float(vals[ia]) if ia is not None else float(plant.inputs["accel_pedal_pct"])
        brake = float(vals[ib]) if ib is not None else float(plant.inputs["brake_pedal_pct"])
        return accel, brake

    return driver


# ------------------------------------------------------------------- figures
def figures(case: Case, rec: dict, shifts: list | None) -> dict:
    """The run's figures (``FIGURES``), NaN where not defined."""
    from plant import maneuvers

    out = {name: math.nan for name in FIGURES}
    t = rec["time_s"]
    v = rec["vehicle_speed_kmh"]
    if case.kind == "maneuver":
        for k, x in maneuvers.report(case.name, rec).items():
            if k in out:
                out[k] = math.nan if x is None else float(x)
    if math.isnan(out["zero_to_100_s"]) and "accel_pedal_pct" in rec:
        x = maneuvers.zero_to_100_s(rec)
        out["zero_to_100_s"] = math.nan if x is None else x
    out["top_speed_kmh"] = float(np.max(v))
    out["final_speed_kmh"] = float(v[-1])
    out["simulated_s"] = float(t[-1] - t[0])
    if "distance_m" in rec:
        out["distance_km"] = float(rec["distance_m"][-1] - rec["distance_m"][0]) / 1000.0
    if "fuel_l" in rec:
        out["fuel_l"] = float(rec["fuel_l"][-1] - rec["fuel_l"][0])
        if "distance_m" in rec:
            x = maneuvers.fuel_l_per_100km(rec)
            out["fuel_l_per_100km"] = math.nan if x is None else x
    if "gear_clashes" in rec:
        out["gear_clashes"] = float(rec["gear_clashes"][-1] - rec["gear_clashes"][0])
    if shifts is not None:
        out["shifts"] = float(len(shifts))
    elif "gear" in rec:
        out["shifts"] = float(len(maneuvers.gear_shifts(t, rec["gear"])))
    if "vehicle_accel_mps2" in rec and len(t) > JERK_WINDOW + 1:
        out["max_jerk_mps3"] = max_jerk(t, rec["vehicle_accel_mps2"])
    return out


def max_jerk(t: np.ndarray, accel: np.ndarray, window: int = JERK_WINDOW) -> float:
    """Largest |d a / d t| after a ``window``-sample moving average."""
    smooth = np.convolve(accel, np.ones(window) / window, mode="valid")
    tt = np.convolve(t, np.ones(window) / window, mode="valid")
    dt = np.diff(tt)
    ok = dt > 0
    if not ok.any():
        return math.nan
    return float(np.max(np.abs(np.diff(smooth)[ok] / dt[ok])))


# ------------------------------------------------------------------- tasks
def one_line(exc: BaseException) -> str:
    """An exception as one line: its message, with its type unless it is a user error."""
    from plant.model import PlantError
    from plant.params import ParamError

    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, (StudyError, PlantError, ParamError)):
        return text
    return f"{type(exc).__name__}: {text}"


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def evaluate(task: dict) -> dict:
    """A sweep run: ``task`` has ``case`` (Case), ``overrides``, ``calibration``.

    Returns ``{"figures": {...} or None, "error": None or one line, "wall_s",
    "worker"}``; never raises for a failing run."""
    t0 = time.perf_counter()
    try:
        rec, shifts = simulate(task["case"], task.get("overrides"), task.get("calibration"))
        figs = figures(task["case"], rec, shifts)
        error = None
    except Exception as e:  # a failed run is a result
        figs, error = None, one_line(e)
    return {"figures": figs, "error": error, "wall_s": time.perf_counter() - t0,
            "worker": worker_name()}


def evaluate_signals(task: dict) -> dict:
    """A fit candidate: simulate ``case`` and return ``signals`` at ``times`` (linear
    interpolation of the 10 ms record). Returns ``{"signals": {name: array} or None,
    "error": ...}``."""
    t0 = time.perf_counter()
    try:
        case = task["case"]
        rec, _ = simulate(case, task.get("overrides"), task.get("calibration"),
                          record_every_s=task.get("record_every_s", RECORD_EVERY_S))
        times = np.asarray(task["times"], dtype=float)
        out = {}
        for name in task["signals"]:
            if name not in rec:
                raise StudyError(f"the simulation records no {name!r}")
            out[name] = np.interp(times, rec["time_s"], rec[name])
        error = None
    except Exception as e:
        out, error = None, one_line(e)
    return {"signals": out, "error": error, "wall_s": time.perf_counter() - t0,
            "worker": worker_name()}
