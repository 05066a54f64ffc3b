"""``dct-hil fit MEASUREMENT[@CASE] ... --params KEY,...``: plant parameters identified
from recorded runs by least squares.

Each measurement is paired with the case that reproduces its inputs: ``@CASE`` names a
maneuver (closed loop with the reference TCU) or a scenario (shipped name or CSV file)
that was run to record it; without one, the measurement's own pedals (and road grade,
if recorded) are replayed with the reference TCU in the loop, starting at the first
sample's vehicle speed. Each candidate simulates every case for the measurement's length
and compares the chosen signals (default ``vehicle_speed_kmh``) sample by sample;
residuals are divided by the signal's sigma (``--signal NAME:SIGMA``, default 1 in the
signal's unit).

The parameters are searched as factors on their start values (``--start KEY=VALUE``,
default the car's values), within their ranges of ``plant/data/ranges.toml``, by
``scipy.optimize.least_squares`` (trust region reflective). Its Jacobian is computed here
by forward differences (``--diff-step``, default 1 % of the start value) with every
perturbed candidate of every measurement run at once on the Dask engine (as the sweeps
run).

Confidence intervals (95 %) come from the Jacobian at the solution: covariance
s^2 (J^T J)^-1 with s^2 the residual variance (sum of squares / (samples - parameters)),
scaled by Student's t. They assume independent residuals: with correlated measurement
errors (a real car's unmodelled dynamics) they are too narrow, and the residual plot is
the check.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dct_hil.studies import StudyError
from dct_hil.studies.keys import (
    Assignment,
    build,
    check_plant,
    default_of,
    merge,
    plant_range,
    resolve,
)
from dct_hil.studies.measurement import ChannelMap, Measurement, load
from dct_hil.studies.runs import Case, evaluate_signals, make_case

DEFAULT_SIGNALS = ("vehicle_speed_kmh",)
REPLAY_INPUTS = ("accel_pedal_pct", "brake_pedal_pct")
REPLAY_OPTIONAL = ("road_grade_pct",)
DIFF_STEP = 0.01


@dataclass
class Target:
    """One measurement with the case that reproduces it."""

    measurement: Measurement
    case: Case
    label: str


@dataclass
class FitResult:
    keys: list
    start: np.ndarray
    value: np.ndarray
    std: np.ndarray
    ci95: np.ndarray
    corr: np.ndarray
    cost: float
    n_samples: int
    runs: int
    iterations: int
    wall_s: float
    status: str
    rms: dict                 # (label, signal) -> residual RMS in the signal's unit
    success: bool
    engine: str = ""
    files: list = dataclasses.field(default_factory=list)


def parse_params(texts: list[str]) -> list:
    keys = []
    for text in texts:
        for part in text.split(","):
            if part.strip():
                k = resolve(part.strip(), "--params")
                if k.kind != "plant":
                    raise StudyError(f"--params {k.text}: the fit identifies plant parameters "
                                     "(a TCU calibration is not measured)")
                if not isinstance(default_of(k), float):
                    raise StudyError(f"--params {k.text}: a list or table; give an index, "
                                     "e.g. [0]")
                if any(k.text == q.text for q in keys):
                    raise StudyError(f"--params {k.text}: given twice")
                keys.append(k)
    if not keys:
        raise StudyError("--params: name at least one parameter (e.g. vehicle.mass_kg)")
    return keys


def parse_signals(texts: list[str] | None) -> dict:
    """{signal: sigma} from NAME[:SIGMA] items."""
    from plant.model import OUTPUT_NAMES

    out = {}
    for text in texts or list(DEFAULT_SIGNALS):
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            name, _, sigma = part.partition(":")
            if name not in OUTPUT_NAMES or name == "time_s":
                import difflib

                close = difflib.get_close_matches(name, OUTPUT_NAMES, n=1)
                hint = f" (did you mean {close[0]}?)" if close else ""
                raise StudyError(f"--signal {name!r}: not a plant output{hint}")
            try:
                s = float(sigma) if sigma else 1.0
            except ValueError:
                raise StudyError(f"--signal {part!r}: sigma {sigma!r} is not a number") from None
            if not (math.isfinite(s) and s > 0):
                raise StudyError(f"--signal {part!r}: sigma must be > 0")
            out[name] = s
    return out


def parse_start(texts: list[str] | None, keys: list) -> dict:
    out = {}
    for text in texts or []:
        name, sep, value = text.partition("=")
        if not sep:
            raise StudyError(f"--start {text!r}: expected KEY=VALUE")
        match = [k for k in keys if k.text == name.strip()]
        if not match:
            raise StudyError(f"--start {name.strip()!r}: not among --params "
                             f"({', '.join(k.text for k in keys)})")
        try:
            out[match[0].text] = float(value)
        except ValueError:
            raise StudyError(f"--start {text!r}: {value!r} is not a number") from None
    return out


def targets(items: list[str], signals: dict, mapping: ChannelMap) -> list[Target]:
    """Measurements (``FILE[@CASE]``) loaded with the channels they need."""
    out = []
    for item in items:
        path, _, case_name = item.partition("@")
        if case_name:
            m = load(path, list(signals), mapping=mapping)
            case = make_case(case_name, where=path)
            label = f"{Path(path).name}@{case.label}"
        else:
            m = load(path, list(signals) + [x for x in REPLAY_INPUTS if x not in signals],
                     optional=REPLAY_OPTIONAL + ("vehicle_speed_kmh",), mapping=mapping)
            case = replay_case(m)
            label = Path(path).name
        length = case.length_s()
        if m.duration_s > length + 0.011:
            m = _cut(m, length)
        case = dataclasses.replace(case, duration_s=float(m.duration_s + 0.011))
        out.append(Target(m, case, label))
    return out


def _cut(m: Measurement, t_end: float) -> Measurement:
    keep = m.time <= t_end + 1e-9
    return Measurement(m.path, m.time[keep], {k: v[keep] for k, v in m.channels.items()},
                       m.available)


def replay_case(m: Measurement) -> Case:
    """A scenario of the measurement's pedals (and grade) with the reference TCU."""
    from plant.scenario import Scenario

    cols = [c for c in REPLAY_INPUTS + REPLAY_OPTIONAL if c in m.channels]
    values = np.column_stack([m.channels[c] for c in cols])
    v0 = float(m.channels["vehicle_speed_kmh"][0]) if "vehicle_speed_kmh" in m.channels else 0.0
    sc = Scenario(name=Path(m.path).stem, times=m.time.copy(), columns=cols, values=values,
                  initial={"vehicle_speed_kmh": max(v0, 0.0)}, path=m.path)
    return Case(f"{Path(m.path).stem} (replayed)", "scenario", sc.name, None, sc, "stub")


class _Problem:
    """Residuals of candidate parameter vectors (factors on the start values)."""

    def __init__(self, keys, start, targets_, signals, base_raw, engine, log):
        self.keys = keys
        self.start = start
        self.targets = targets_
        self.signals = signals
        self.base_raw = base_raw
        self.engine = engine
        self.log = log
        self.cache: dict = {}
        self.runs = 0
        self.evals = 0

    def overrides(self, theta: np.ndarray) -> dict:
        values = theta * self.start
        assigns = [Assignment(k, float(v)) for k, v in zip(self.keys, values)]
        over, _ = build(assigns)
        return merge(self.base_raw, over) if self.base_raw else over

    def residuals_many(self, thetas: list) -> list:
        """Residual vectors of several candidates, their runs all at once on the engine."""
        todo, tasks = [], []
        for th in thetas:
            key = tuple(np.round(th, 12))
            if key in self.cache or key in todo:
                continue
            todo.append(key)
            over = self.overrides(np.array(key))
            for t in self.targets:
                tasks.append({"case": t.case, "overrides": over, "times": t.measurement.time,
                              "signals": list(self.signals)})
        if tasks:
            results = self.engine.map(evaluate_signals, tasks)
            self.runs += len(tasks)
            k = 0
            for key in todo:
                parts = []
                for t in self.targets:
                    r = results[k]
                    k += 1
                    if not r or r.get("error"):
                        shown = ", ".join(f"{q.text} = {v:.6g}"
                                          for q, v in zip(self.keys, np.array(key) * self.start))
                        raise StudyError(f"a candidate run failed ({t.label}, {shown}): "
                                         f"{(r or {}).get('error')}")
                    for s, sigma in self.signals.items():
                        parts.append((r["signals"][s] - t.measurement.channels[s]) / sigma)
                self.cache[key] = np.concatenate(parts)
        return [self.cache[tuple(np.round(th, 12))] for th in thetas]

    def fun(self, theta):
        self.evals += 1
        return self.residuals_many([theta])[0]

    def jac(self, theta, step):
        thetas = [theta]
        for i in range(len(theta)):
            th = theta.copy()
            h = step * max(abs(theta[i]), 1e-3)
            th[i] += h
            thetas.append(th)
        res = self.residuals_many(thetas)
        J = np.empty((len(res[0]), len(theta)))
        for i in range(len(theta)):
            J[:, i] = (res[i + 1] - res[0]) / (thetas[i + 1][i] - theta[i])
        return J


def fit(keys, targets_, signals, start_values: dict | None = None, base_raw: dict | None = None,
        engine=None, diff_step: float = DIFF_STEP, max_iterations: int = 30, log=None) -> FitResult:
    """Least-squares fit of ``keys`` to ``targets_``; ``engine`` an open studies Engine."""
    from scipy.optimize import least_squares
    from scipy.stats import t as student_t

    log = log or (lambda text: None)
    base_raw = base_raw or {}
    from dct_hil.studies.keys import base_params

    base = base_params(base_raw)
    start = np.array([float(start_values.get(k.text, default_of(k, base))) if start_values
                      else float(default_of(k, base)) for k in keys])
    for k, v in zip(keys, start):
        if v == 0.0:
            raise StudyError(f"--start {k.text}: the fit searches factors on the start value; "
                             "give a start other than 0")
    check_plant([Assignment(k, float(v)) for k, v in zip(keys, start)], base_raw, "--start")
    lo, hi = [], []
    for k, v in zip(keys, start):
        rng = plant_range(k.path)
        a, b = (rng[0], rng[1]) if rng else (-math.inf, math.inf)
        fa, fb = a / v, b / v
        lo.append(min(fa, fb))
        hi.append(max(fa, fb))
    prob = _Problem(keys, start, targets_, signals, base_raw, engine, log)
    t0 = time.monotonic()
    iteration = {"n": 0}

    def jac(theta):
        iteration["n"] += 1
        J = prob.jac(theta, diff_step)
        r = prob.residuals_many([theta])[0]
        shown = ", ".join(f"{k.text} = {v:.6g}" for k, v in zip(keys, theta * start))
        log(f"iteration {iteration['n']}: {shown}; RMS residual {np.sqrt(np.mean(r ** 2)):.4g} "
            f"({prob.runs} runs, {time.monotonic() - t0:.0f} s)")
        return J

    theta0 = np.ones(len(keys))
    sol = least_squares(prob.fun, theta0, jac=jac, bounds=(lo, hi), method="trf",
                        x_scale=1.0, max_nfev=max_iterations, xtol=1e-5, ftol=1e-6, gtol=1e-8)
    theta = sol.x
    r = prob.residuals_many([theta])[0]
    J = prob.jac(theta, diff_step)
    m, n = len(r), len(theta)
    dof = max(m - n, 1)
    s2 = float(r @ r) / dof
    try:
        cov_theta = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov_theta = np.full((n, n), np.nan)
    cov = cov_theta * np.outer(start, start)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    ci = std * float(student_t.ppf(0.975, dof))
    rms = {}
    k = 0
    for t in targets_:
        for s, sigma in signals.items():
            nn = len(t.measurement.time)
            rms[(t.label, s)] = float(np.sqrt(np.mean((r[k:k + nn] * sigma) ** 2)))
            k += nn
    return FitResult(keys, start, theta * start, std, ci, corr, float(sol.cost), m, prob.runs,
                     iteration["n"], time.monotonic() - t0, sol.message, rms,
                     bool(sol.success), getattr(engine, "description", ""))


def simulate_targets(keys, values, targets_, signals, base_raw, engine) -> list:
    """Simulated signals of each target with parameter ``values``."""
    assigns = [Assignment(k, float(v)) for k, v in zip(keys, values)]
    over, _ = build(assigns)
    over = merge(base_raw, over) if base_raw else over
    tasks = [{"case": t.case, "overrides": over, "times": t.measurement.time,
              "signals": list(signals)} for t in targets_]
    out = engine.map(evaluate_signals, tasks)
    for t, r in zip(targets_, out):
        if not r or r.get("error"):
            raise StudyError(f"{t.label}: the run failed: {(r or {}).get('error')}")
    return [r["signals"] for r in out]


def report_lines(res: FitResult) -> list[str]:
    lines = []
    width = max(len(k.text) for k in res.keys)
    lines.append(f"  {'parameter':{width}s}  {'start':>10s}  {'fitted':>12s}  {'95 % interval':>14s}")
    for i, k in enumerate(res.keys):
        v, ci = res.value[i], res.ci95[i]
        rel = abs(ci / v) * 100 if v else math.nan
        lines.append(f"  {k.text:{width}s}  {res.start[i]:10.5g}  {v:12.6g}  "
                     f"+- {ci:<10.3g} ({rel:.2g} %)")
    n = len(res.keys)
    if n > 1:
        pairs = [(res.keys[i].text, res.keys[j].text, res.corr[i, j])
                 for i in range(n) for j in range(i + 1, n)]
        lines.append("  correlation: " + ", ".join(f"{a} / {b} {c:+.2f}" for a, b, c in pairs))
    return lines


def fitted_toml(keys, values) -> str:
    """The fitted values as a parameter override file (for --params)."""
    over, _ = build([Assignment(k, float(v)) for k, v in zip(keys, values)])
    lines = ["# fitted by dct-hil fit; merge over the default car with --params", ""]
    _toml(over, [], lines)
    return "\n".join(lines) + "\n"


def _toml(tree: dict, path: list, lines: list) -> None:
    scalars = {k: v for k, v in tree.items() if not isinstance(v, (dict, list))
               or (isinstance(v, list) and not (v and isinstance(v[0], dict)))}
    if scalars:
        if path:
            lines.append(f"[{'.'.join(path)}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")
    for k, v in tree.items():
        if isinstance(v, dict):
            _toml(v, path + [k], lines)
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines.append(f"[[{'.'.join(path + [k])}]]")
                sub_lines: list = []
                _toml(item, [], sub_lines)
                lines.extend(sub_lines if sub_lines else [""])


def _toml_value(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(float(v)) if isinstance(v, float) else str(v)


def write_outputs(out: Path, res: FitResult, targets_, signals, fitted_sig, start_sig) -> list:
    from dct_hil.studies.plots import fit_plot
    from dct_hil.studies.runs import UNITS

    out.mkdir(parents=True, exist_ok=True)
    files = []
    data = {
        "parameters": [{"key": k.text, "start": float(res.start[i]), "value": float(res.value[i]),
                        "std": float(res.std[i]), "ci95": float(res.ci95[i])}
                       for i, k in enumerate(res.keys)],
        "correlation": [[float(x) for x in row] for row in res.corr],
        "samples": res.n_samples, "runs": res.runs, "iterations": res.iterations,
        "wall_s": round(res.wall_s, 3), "cost": res.cost, "status": res.status,
        "success": res.success, "engine": res.engine,
        "measurements": [{"file": t.measurement.path, "case": t.case.label,
                          "duration_s": t.measurement.duration_s} for t in targets_],
        "residual_rms": [{"measurement": a, "signal": b, "rms": v} for (a, b), v in res.rms.items()],
    }
    (out / "fit.json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    files.append(out / "fit.json")
    (out / "fitted.toml").write_text(fitted_toml(res.keys, res.value), encoding="utf-8")
    files.append(out / "fitted.toml")
    panels = []
    for t, fs, ss in zip(targets_, fitted_sig, start_sig):
        for s in signals:
            panels.append({"title": f"{t.label}: {s}", "t": t.measurement.time,
                           "measured": t.measurement.channels[s], "fitted": fs[s],
                           "start": ss[s], "unit": _unit(s, UNITS)})
    shown = ", ".join(f"{k.text} = {v:.5g}" for k, v in zip(res.keys, res.value))
    files.append(fit_plot(out / "fit_residuals.png", panels, f"fit: {shown}"))
    return files


def _unit(name: str, units: dict) -> str:
    for suffix, unit in (("_kmh", "km/h"), ("_rpm", "rpm"), ("_bar", "bar"), ("_nm", "Nm"),
                         ("_mps2", "m/s2"), ("_pct", "%"), ("_a", "A"), ("_m", "m"),
                         ("_l", "l"), ("_deg", "deg"), ("_mm", "mm"), ("_n", "N")):
        if name.endswith(suffix):
            return f"{name} [{unit}]"
    return name
