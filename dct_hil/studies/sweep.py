"""``dct-hil sweep SPEC.toml``: a sample over plant parameters, TCU calibration values and
cases (maneuvers or scenarios), evaluated on Dask, kept as tables and plots.

The spec (``dct_hil/studies/examples/shift_map.toml`` is a worked one)::

    [sweep]
    sampling = "grid"          # grid | random | lhs (Latin hypercube)
    samples = 16               # random / lhs: number of points
    seed = 1                   # random / lhs
    cases = ["0-100", "coastdown"]   # maneuvers, shipped scenarios or CSV files
    params = "heavier.toml"    # optional: a parameter file the runs start from
    out = "out/sweeps/NAME"    # optional (default out/sweeps/<spec file stem>)

    [[case]]                   # a case with options (instead of or beside `cases`)
    name = "wltc"
    duration_s = 600           # cut short (default: its own length)

    [[parameter]]
    key = "vehicle.mass_kg"    # a plant parameter, as the parameter files name it
    values = [1300, 1400, 1500]

    [[parameter]]
    key = "tcu.UPSHIFT_RPM"    # a TCU calibration value (tcu_stub/logic.py)
    relative = true            # a factor on the default (a table: every point)
    range = [0.8, 1.1]
    steps = 4                  # grid: points over the range (random/lhs: uniform in it)

    [pareto]                   # optional: the trade-off of two figures (both minimised)
    x = "wltc.fuel_l_per_100km"
    y = "0-100.zero_to_100_s"

Every point runs every case; a run is keyed by a hash of its inputs (case, its
scenario rows, duration, the parameter overrides including the base file, the
calibration). Finished runs are appended to ``runs.jsonl`` in the output folder
as they finish; running the same spec again computes only the runs not in it
(``--fresh`` starts over, ``--retry-failed`` runs the failed ones again). A run
that fails (the plant leaves its valid range, a bad combination) is recorded
with its error. Then ``runs.parquet``/``runs.csv`` (a row per run: inputs,
status, error, figures), ``points.parquet``/``points.csv`` (a row per point:
inputs and ``<case>.<figure>``) and the plots (``dct_hil.studies.plots``).
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import itertools
import json
import math
import os
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dct_hil.studies import StudyError
from dct_hil.studies.keys import (
    Assignment,
    Key,
    build,
    check_plant,
    check_tcu,
    merge,
    resolve,
)
from dct_hil.studies.runs import FIGURES, Case, evaluate, make_case

RUN_FORMAT = 1          # part of every run's hash: bump when a run's meaning changes
SAMPLINGS = ("grid", "random", "lhs")
JOURNAL = "runs.jsonl"
MAX_RUNS = 100_000


@dataclass
class Parameter:
    keys: list[Key]                 # one, or several set to the same value (linked)
    relative: bool = False
    values: list | None = None      # explicit values
    range: tuple | None = None      # (lo, hi)
    steps: int | None = None        # grid over the range
    integer: bool = False
    name: str | None = None         # the column's name (default: the key, ":factor" if relative)

    @property
    def key(self) -> Key:
        return self.keys[0]

    @property
    def column(self) -> str:
        if self.name:
            return self.name
        text = " + ".join(k.text for k in self.keys)
        return f"{text}:factor" if self.relative else text

    def assignments(self, value: float) -> list[Assignment]:
        return [Assignment(k, value, self.relative) for k in self.keys]

    def grid(self) -> list:
        if self.values is not None:
            return list(self.values)
        lo, hi = self.range
        vals = list(np.linspace(lo, hi, self.steps)) if self.steps > 1 else [lo]
        return [self._round(v) for v in vals]

    def from_unit(self, u: float) -> float:
        """A value for u in [0, 1): uniform over the range or one of the values."""
        if self.values is not None:
            return self.values[min(int(u * len(self.values)), len(self.values) - 1)]
        lo, hi = self.range
        return self._round(lo + (hi - lo) * u)

    def _round(self, v: float) -> float:
        return float(round(v)) if self.integer else float(v)

    def bounds(self) -> tuple[float, float]:
        vals = self.values if self.values is not None else self.range
        return min(vals), max(vals)


@dataclass
class Spec:
    path: Path
    name: str
    sampling: str
    cases: list[Case]
    parameters: list[Parameter]
    samples: int | None = None
    seed: int | None = None
    base_file: Path | None = None
    base_raw: dict = field(default_factory=dict)
    out: Path | None = None
    pareto: tuple | None = None     # (x column, y column)
    text: str = ""
    notes: list = field(default_factory=list)

    def points(self) -> list[list[float]]:
        """The parameter values of every point (one list per point, parameter order)."""
        params = self.parameters
        if not params:
            return [[]]
        if self.sampling == "grid":
            return [list(p) for p in itertools.product(*(q.grid() for q in params))]
        n = self.samples
        if self.sampling == "random":
            rng = np.random.default_rng(self.seed)
            units = rng.random((n, len(params)))
        else:
            from scipy.stats import qmc

            units = qmc.LatinHypercube(d=len(params), seed=self.seed).random(n)
        return [[q.from_unit(float(u)) for q, u in zip(params, row)] for row in units]


# ---------------------------------------------------------------------- spec
def load_spec(path: str | os.PathLike, duration_cap_s: float | None = None) -> Spec:
    """Read and check a sweep spec; StudyError (one line naming the file and key)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise StudyError(f"{p}: cannot read: {e.strerror}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"{p}: not valid TOML: {e}") from None
    where = str(p)
    known = {"sweep", "case", "parameter", "pareto"}
    for k in raw:
        if k not in known:
            raise StudyError(f"{where}: unknown table [{k}]; a spec has [sweep], [[case]], "
                             "[[parameter]] and [pareto]")
    sweep = _table(raw.get("sweep", {}), f"{where}: [sweep]")
    _only(sweep, {"name", "sampling", "samples", "seed", "cases", "params", "out"},
          f"{where}: [sweep]")
    name = sweep.get("name", p.stem)
    sampling = sweep.get("sampling", "grid")
    if sampling not in SAMPLINGS:
        raise StudyError(f"{where}: [sweep] sampling = {sampling!r}: choose {', '.join(SAMPLINGS)}")
    samples = sweep.get("samples")
    seed = sweep.get("seed", 0)
    if sampling != "grid":
        if not (isinstance(samples, int) and not isinstance(samples, bool) and samples >= 1):
            raise StudyError(f"{where}: [sweep] sampling = {sampling!r} needs samples = N "
                             f"(a whole number >= 1), got {samples!r}")
        if not (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0):
            raise StudyError(f"{where}: [sweep] seed must be a whole number >= 0, got {seed!r}")
    elif samples is not None:
        raise StudyError(f"{where}: [sweep] samples goes with sampling = \"random\" or \"lhs\" "
                         "(a grid has one point per combination)")

    base_file, base_raw = None, {}
    if "params" in sweep:
        base_file = (p.parent / sweep["params"]) if not os.path.isabs(sweep["params"]) \
            else Path(sweep["params"])
        base_raw = _base_params(base_file, where)

    cases = _cases(sweep, raw.get("case", []), where, duration_cap_s)
    parameters = _parameters(raw.get("parameter", []), where, base_raw)
    pareto = None
    if "pareto" in raw:
        par = _table(raw["pareto"], f"{where}: [pareto]")
        _only(par, {"x", "y"}, f"{where}: [pareto]")
        labels = {c.label for c in cases}
        for axis in ("x", "y"):
            col = par.get(axis)
            if not isinstance(col, str) or "." not in col:
                raise StudyError(f"{where}: [pareto] {axis} must be \"<case>.<figure>\", "
                                 f"got {col!r}")
            case, fig = col.rsplit(".", 1)
            if case not in labels:
                raise StudyError(f"{where}: [pareto] {axis} = {col!r}: no case {case!r} "
                                 f"(cases: {', '.join(sorted(labels))})")
            if fig not in FIGURES:
                raise StudyError(f"{where}: [pareto] {axis} = {col!r}: no figure {fig!r} "
                                 f"(figures: {', '.join(FIGURES)})")
        pareto = (par["x"], par["y"])
    out = None
    if "out" in sweep:
        if not isinstance(sweep["out"], str):
            raise StudyError(f"{where}: [sweep] out must be a folder name")
        out = Path(sweep["out"])
    spec = Spec(p, str(name), sampling, cases, parameters, samples, seed, base_file, base_raw,
                out, pareto, text)
    _check_grid(spec)
    if any(k.kind == "tcu" for q in parameters for k in q.keys):
        for c in cases:
            if c.tcu == "none":
                spec.notes.append(f"case {c.label} is played open-loop (no TCU): the tcu.* "
                                  "values do not act on it")
    n_runs = len(spec.points()) * len(cases) if sampling == "grid" else samples * len(cases)
    if n_runs > MAX_RUNS:
        raise StudyError(f"{where}: {n_runs} runs; at most {MAX_RUNS} in one sweep")
    return spec


def _table(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise StudyError(f"{where} must be a table")
    return value


def _only(table: dict, allowed: set, where: str) -> None:
    for k in table:
        if k not in allowed:
            raise StudyError(f"{where}: unknown key {k!r}; allowed: {', '.join(sorted(allowed))}")


def _base_params(path: Path, where: str) -> dict:
    from plant.params import ParamError, load_params

    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise StudyError(f"{where}: [sweep] params = {str(path)!r}: cannot read: {e.strerror}") \
            from None
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"{path}: not valid TOML: {e}") from None
    try:
        load_params(path)
    except ParamError as e:
        raise StudyError(str(e)) from None
    return raw


def _cases(sweep: dict, tables: Any, where: str, cap: float | None) -> list[Case]:
    entries = []
    names = sweep.get("cases", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise StudyError(f"{where}: [sweep] cases must be a list of names")
    entries += [{"name": n} for n in names]
    if not isinstance(tables, list):
        raise StudyError(f"{where}: case must be an array of tables ([[case]])")
    for i, t in enumerate(tables):
        _table(t, f"{where}: [[case]] {i + 1}")
        _only(t, {"name", "duration_s", "label", "tcu"}, f"{where}: [[case]] {i + 1}")
        if not isinstance(t.get("name"), str):
            raise StudyError(f"{where}: [[case]] {i + 1} needs name = \"<maneuver or scenario>\"")
        entries.append(t)
    if not entries:
        raise StudyError(f"{where}: no cases: give [sweep] cases = [...] or [[case]] tables "
                         "(maneuvers: paper-cycle, wltc, nedc, 0-100; or scenarios)")
    cases = []
    for t in entries:
        name = t["name"]
        rel = Path(where).parent / name
        if name.endswith(".csv") and not os.path.isabs(name) and rel.is_file():
            name = str(rel)
        c = make_case(name, t.get("duration_s"), t.get("label"), t.get("tcu"), where)
        if cap is not None and c.length_s() > cap:
            c = Case(c.label, c.kind, c.name, float(cap), c.scenario, c.tcu)
        cases.append(c)
    labels = [c.label for c in cases]
    dup = {x for x in labels if labels.count(x) > 1}
    if dup:
        raise StudyError(f"{where}: case {sorted(dup)[0]!r} appears twice; give one a label")
    return cases


def _parameters(tables: Any, where: str, base_raw: dict) -> list[Parameter]:
    if not isinstance(tables, list):
        raise StudyError(f"{where}: parameter must be an array of tables ([[parameter]])")
    out: list[Parameter] = []
    seen = set()
    from dct_hil.studies.keys import is_scalar, plant_range

    for i, t in enumerate(tables):
        w = f"{where}: [[parameter]] {i + 1}"
        _table(t, w)
        _only(t, {"key", "values", "range", "steps", "relative", "name"}, w)
        texts = t.get("key", "")
        texts = texts if isinstance(texts, list) and texts else [texts]
        keys = [resolve(x, w) for x in texts]
        key = keys[0]
        w = f"{where}: [[parameter]] {key.text}"
        for k in keys:
            if k.text in seen:
                raise StudyError(f"{where}: [[parameter]] {k.text}: appears twice")
            seen.add(k.text)
        name = t.get("name")
        if name is not None and not (isinstance(name, str) and name.strip()):
            raise StudyError(f"{w}: name must be a non-empty string")
        relative = t.get("relative", False)
        if not isinstance(relative, bool):
            raise StudyError(f"{w}: relative must be true or false")
        for k in keys:
            if not relative and not is_scalar(k):
                raise StudyError(f"{where}: [[parameter]] {k.text}: a list or table; give an "
                                 "index (e.g. [0]) or relative = true to scale all of it")
        values, rng, steps = t.get("values"), t.get("range"), t.get("steps")
        if (values is None) == (rng is None):
            raise StudyError(f"{w}: give either values = [...] or range = [min, max]")
        if values is not None:
            if not (isinstance(values, list) and values and all(_num(v) for v in values)):
                raise StudyError(f"{w}: values must be a non-empty list of numbers")
            values = [float(v) for v in values]
            if steps is not None:
                raise StudyError(f"{w}: steps goes with range, not with values")
        else:
            if not (isinstance(rng, list) and len(rng) == 2 and all(_num(v) for v in rng)
                    and rng[0] <= rng[1]):
                raise StudyError(f"{w}: range must be [min, max] with min <= max, got {rng!r}")
            rng = (float(rng[0]), float(rng[1]))
        integer = False
        if key.kind == "plant" and not relative:
            r = plant_range(key.path)
            integer = bool(r and r[2])
        par = Parameter(keys, relative, values, rng, None, integer, name)
        if rng is not None:
            if steps is None:
                par.steps = None
            elif not (isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1):
                raise StudyError(f"{w}: steps must be a whole number >= 1, got {steps!r}")
            else:
                par.steps = steps
        for bound in par.bounds():
            check_plant(par.assignments(bound), base_raw, f"{where}: [[parameter]] sweep bound")
            check_tcu(par.assignments(bound), f"{where}: [[parameter]] sweep bound")
        out.append(par)
    columns = [q.column for q in out]
    for c in columns:
        if columns.count(c) > 1:
            raise StudyError(f"{where}: two parameters have the column name {c!r}; give one "
                             "a name")
    return out


def _check_grid(spec: Spec) -> None:
    for q in spec.parameters:
        if spec.sampling == "grid" and q.range is not None and q.steps is None:
            raise StudyError(f"{spec.path}: [[parameter]] {q.column}: a grid over a range "
                             "needs steps = N")


def _num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# --------------------------------------------------------------------- runs
@dataclass
class Run:
    run_id: str
    point: int
    case: Case
    inputs: dict                 # column -> value
    task: dict


def plan(spec: Spec) -> list[Run]:
    """Every run of the spec: point-major, then case."""
    _check_grid(spec)
    runs = []
    from dct_hil.studies.keys import base_params

    base = base_params(spec.base_raw)
    for i, values in enumerate(spec.points()):
        assigns = [a for q, v in zip(spec.parameters, values) for a in q.assignments(v)]
        over, cal = build(assigns, base)
        over = merge(spec.base_raw, over) if spec.base_raw else over
        inputs = {q.column: float(v) for q, v in zip(spec.parameters, values)}
        for case in spec.cases:
            ident = {"format": RUN_FORMAT, "case": case.identity(), "overrides": over,
                     "calibration": {k: _jsonable(v) for k, v in sorted(cal.items())}}
            rid = hashlib.sha256(json.dumps(ident, sort_keys=True, default=float)
                                 .encode()).hexdigest()[:16]
            runs.append(Run(rid, i, case, inputs,
                            {"case": case, "overrides": over, "calibration": cal}))
    return runs


def _jsonable(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_jsonable(x) for x in v]
    return v


def read_journal(path: Path) -> dict[str, dict]:
    """{run_id: record} of a journal (a torn last line, from a kill, is skipped)."""
    out: dict[str, dict] = {}
    if not path.exists():
        return out
    with open(path, encoding="utf-8") as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict) and "run_id" in rec:
                out[rec["run_id"]] = rec
    return out


class Journal:
    """Append-only record of finished runs (one JSON line each, flushed as they finish)."""

    def __init__(self, path: Path):
        self.path = path
        torn = False
        if path.exists() and path.stat().st_size > 0:
            with open(path, "rb") as f:
                f.seek(-1, os.SEEK_END)
                torn = f.read(1) != b"\n"
        self._f = open(path, "a", encoding="utf-8")
        if torn:       # a killed sweep's torn last line: the next record starts a line of its own
            self._f.write("\n")

    def append(self, rec: dict) -> None:
        self._f.write(json.dumps(rec, default=_json_default) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        self._f.close()


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x).__name__)


# ------------------------------------------------------------------- tables
def tables(spec: Spec, runs: list[Run], done: dict[str, dict]):
    """(runs DataFrame, points DataFrame) of the spec's runs with what the journal holds."""
    import pandas as pd

    cols = [q.column for q in spec.parameters]
    rows = []
    for r in runs:
        rec = done.get(r.run_id)
        row: dict[str, Any] = {"run_id": r.run_id, "point": r.point, "case": r.case.label}
        row.update(r.inputs)
        if rec is None:
            row["status"], row["error"] = "pending", ""
        elif rec.get("error"):
            row["status"], row["error"] = "failed", rec["error"]
        else:
            row["status"], row["error"] = "ok", ""
        figs = (rec or {}).get("figures") or {}
        for f in FIGURES:
            v = figs.get(f)
            row[f] = math.nan if v is None else float(v)
        row["wall_s"] = float((rec or {}).get("wall_s", math.nan))
        row["worker"] = (rec or {}).get("worker", "")
        rows.append(row)
    run_df = pd.DataFrame(rows, columns=["run_id", "point", "case"] + cols
                          + ["status", "error"] + list(FIGURES) + ["wall_s", "worker"])
    pts = []
    for i, group in itertools.groupby(rows, key=lambda x: x["point"]):
        group = list(group)
        prow: dict[str, Any] = {"point": i}
        prow.update({c: group[0][c] for c in cols})
        prow["failed"] = sum(g["status"] == "failed" for g in group)
        prow["pending"] = sum(g["status"] == "pending" for g in group)
        for g in group:
            for f in FIGURES:
                prow[f"{g['case']}.{f}"] = g[f]
        pts.append(prow)
    point_df = pd.DataFrame(pts)
    if spec.pareto and not point_df.empty:
        point_df["pareto"] = pareto_mask(point_df, *spec.pareto)
    return run_df, point_df


def pareto_mask(df, x: str, y: str) -> np.ndarray:
    """True for the points no other point beats in both x and y (both minimised)."""
    xs = df[x].to_numpy(dtype=float) if x in df else np.full(len(df), np.nan)
    ys = df[y].to_numpy(dtype=float) if y in df else np.full(len(df), np.nan)
    ok = np.isfinite(xs) & np.isfinite(ys)
    mask = np.zeros(len(df), dtype=bool)
    for i in np.flatnonzero(ok):
        beaten = ok & (xs <= xs[i]) & (ys <= ys[i]) & ((xs < xs[i]) | (ys < ys[i]))
        mask[i] = not beaten.any()
    return mask


def write_tables(out: Path, run_df, point_df) -> list[Path]:
    paths = []
    for stem, df in (("runs", run_df), ("points", point_df)):
        pq, csv = out / f"{stem}.parquet", out / f"{stem}.csv"
        tmp = out / f".{stem}.parquet.tmp"
        df.to_parquet(tmp, index=False)
        os.replace(tmp, pq)
        df.to_csv(csv, index=False)
        paths += [pq, csv]
    return paths


# ---------------------------------------------------------------------- main
@dataclass
class SweepResult:
    out: Path
    runs: int
    computed: int
    skipped: int
    failed: int
    wall_s: float
    run_df: Any
    point_df: Any
    files: list
    engine: str = ""


def run_sweep(spec: Spec, out: Path | None = None, workers: int | None = None,
              scheduler: str | None = None, fresh: bool = False, retry_failed: bool = False,
              plots: bool = True, progress: bool = True, dashboard: int | None = None,
              connect_timeout_s: float | None = None, log=None, engine=None) -> SweepResult:
    """Run (or resume) the sweep; returns what was done and where the files are.

    ``engine``: an open ``dct_hil.studies.engine.Engine`` to run on (default: one started
    for this sweep from ``workers`` / ``scheduler`` and closed after it)."""
    from dct_hil.studies.engine import CONNECT_TIMEOUT_S, Engine, Progress

    log = log or (lambda text: print(text, flush=True))
    out = Path(out or spec.out or Path("out") / "sweeps" / spec.name)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise StudyError(f"--out {out}: cannot create the folder: {e.strerror}") from None
    runs = plan(spec)
    lock = _lock(out)
    try:
        journal_path = out / JOURNAL
        if fresh and journal_path.exists():
            journal_path.unlink()
        done = read_journal(journal_path)
        keep = {k: v for k, v in done.items() if not (retry_failed and v.get("error"))}
        (out / "spec.toml").write_text(spec.text, encoding="utf-8")
        todo = [r for r in runs if r.run_id not in keep]
        seen: set = set()
        todo = [r for r in todo if not (r.run_id in seen or seen.add(r.run_id))]
        skipped = len({r.run_id for r in runs}) - len(todo)
        log(f"sweep {spec.name}: {len(spec.points())} points x {len(spec.cases)} case"
            f"{'s' if len(spec.cases) != 1 else ''} = {len(runs)} runs; {skipped} already in "
            f"{journal_path}, {len(todo)} to compute")
        t0 = time.monotonic()
        failed_now = 0
        engine_text = ""
        if todo:
            journal = Journal(journal_path)
            bar = Progress(len(todo), enabled=progress)
            try:
                own = engine is None
                if own:
                    engine = Engine(workers=workers, scheduler=scheduler, dashboard=dashboard,
                                    connect_timeout_s=connect_timeout_s or CONNECT_TIMEOUT_S)
                with engine if own else contextlib.nullcontext(engine):
                    engine_text = engine.description
                    log(f"engine: {engine_text}")

                    def finished(i: int, result: dict) -> None:
                        nonlocal failed_now
                        r = todo[i]
                        rec = {"run_id": r.run_id, "point": r.point, "case": r.case.label,
                               "inputs": r.inputs, "figures": result.get("figures"),
                               "error": result.get("error"), "wall_s": result.get("wall_s"),
                               "worker": result.get("worker", ""),
                               "finished_at": datetime.datetime.now(datetime.UTC)
                               .isoformat(timespec="seconds")}
                        journal.append(rec)
                        keep[r.run_id] = rec
                        failed_now += bool(rec["error"])
                        bar.update(failed=bool(rec["error"]))

                    engine.run(evaluate, [r.task for r in todo],
                               [f"dct-run-{r.run_id}" for r in todo], finished)
            finally:
                bar.close()
                journal.close()
                run_df, point_df = tables(spec, runs, keep)
                write_tables(out, run_df, point_df)
        run_df, point_df = tables(spec, runs, keep)
        files = write_tables(out, run_df, point_df)
        wall = time.monotonic() - t0
        if plots:
            from dct_hil.studies.plots import sweep_plots

            files += sweep_plots(spec, run_df, point_df, out)
        summary = {"spec": str(spec.path), "name": spec.name, "runs": len(runs),
                   "computed": len(todo), "skipped": skipped,
                   "failed": int((run_df["status"] == "failed").sum()),
                   "wall_s": round(wall, 3), "engine": engine_text,
                   "files": [str(f) for f in files]}
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        return SweepResult(out, len(runs), len(todo), skipped, summary["failed"], wall, run_df,
                           point_df, files, engine_text)
    finally:
        _unlock(lock)


def _lock(out: Path):
    f = open(out / ".lock", "w")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise StudyError(f"another sweep is writing to {out} (its .lock is held)") from None
    return f


def _unlock(f) -> None:
    with contextlib.suppress(OSError):
        fcntl.flock(f, fcntl.LOCK_UN)
    f.close()


def print_summary(spec: Spec, res: SweepResult, stream=None) -> None:
    """The sweep's outcome: counts, each case's figures over the points, the files."""
    stream = stream or sys.stdout
    w = stream.write
    w(f"runs: {res.runs} ({res.computed} computed, {res.skipped} from the journal), "
      f"{res.failed} failed; {res.wall_s:.1f} s\n")
    df = res.run_df
    for case in spec.cases:
        sub = df[(df["case"] == case.label) & (df["status"] == "ok")]
        if sub.empty:
            continue
        parts = []
        for f in FIGURES:
            if f == "simulated_s":
                continue
            vals = sub[f].to_numpy(dtype=float)
            vals = vals[np.isfinite(vals)]
            if len(vals):
                parts.append(f"{f} {vals.min():.4g}..{vals.max():.4g}")
        w(f"  {case.label}: {', '.join(parts)}\n")
    bad = df[df["status"] == "failed"]
    for _, row in bad.head(5).iterrows():
        w(f"  failed: point {row['point']} {row['case']}: {row['error']}\n")
    if len(bad) > 5:
        w(f"  ... {len(bad) - 5} more failed runs in runs.csv\n")
    if spec.pareto and "pareto" in res.point_df:
        x, y = spec.pareto
        front = res.point_df[res.point_df["pareto"]].sort_values(x)
        cols = [q.column for q in spec.parameters]
        w(f"pareto front ({x} against {y}, both minimised): {len(front)} of "
          f"{len(res.point_df)} points\n")
        for _, row in front.iterrows():
            ins = ", ".join(f"{c} = {row[c]:.4g}" for c in cols)
            w(f"  {ins}: {x} = {row[x]:.4g}, {y} = {row[y]:.4g}\n")
    w(f"results: {res.out}/runs.parquet, runs.csv, points.parquet, points.csv\n")
    pngs = [f for f in res.files if str(f).endswith(".png")]
    for f in pngs:
        w(f"plot: {f}\n")

