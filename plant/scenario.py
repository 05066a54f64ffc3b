"""Scenarios: plant inputs over time, read from small CSV files.

Format (plant/scenarios/*.csv)::

    # comment lines start with '#'
    # initial: vehicle_speed_kmh=0, sleeve1_side=1, clutch1_locked=0
    time_s,accel_pedal_pct,clutch1_pressure_bar
    0,0,0
    1.0,30,4.5
    6.0,30,4.5

The first non-comment line is the header: ``time_s`` first, then names of
``dct_inputs`` fields. Each row holds until the next one: it is applied
before the first step whose start time is at or after the row time. Times
start at 0 and strictly increase; the last row time is the scenario length.
Inputs without a column keep the plant's defaults. ``# initial:`` lines set
the state the run starts from (``Plant.reset``).
"""

import math
import os
from dataclasses import dataclass, field

import numpy as np

SCENARIO_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenarios")

# initial key -> default; all floats, the file gives them as numbers
INITIAL_KEYS = {
    "vehicle_speed_kmh": 0.0,
    "sleeve1_side": 0.0,
    "sleeve2_side": 0.0,
    "sleeve3_side": 0.0,
    "sleeve4_side": 0.0,
    "clutch1_locked": 0.0,
    "clutch2_locked": 0.0,
    "engine_on": 1.0,
}
_ALLOWED = {
    **{f"sleeve{i}_side": (-1.0, 0.0, 1.0) for i in range(1, 5)},
    "clutch1_locked": (0.0, 1.0),
    "clutch2_locked": (0.0, 1.0),
    "engine_on": (0.0, 1.0),
}
# initial temperatures (degC): the parameters' thermal.initial_* when not given
TEMPERATURE_KEYS = {
    "coolant_temp_degc": (-40.0, 130.0),
    "engine_oil_temp_degc": (-40.0, 150.0),
    "trans_oil_temp_degc": (-40.0, 150.0),
}
_TIME_EPS = 1e-9  # s: row times closer than this to a step start count as on it


class ScenarioError(ValueError):
    """A scenario file could not be used: one line naming file, line and cause."""


PRESSURE_COLUMNS = ("clutch1_pressure_bar", "clutch2_pressure_bar")
CURRENT_COLUMNS = ("solenoid_current1_a", "solenoid_current2_a")


@dataclass
class Scenario:
    name: str
    times: np.ndarray            # row times, s, shape (rows,)
    columns: list                # dct_inputs field names, in file order
    values: np.ndarray           # shape (rows, len(columns))
    initial: dict = field(default_factory=dict)  # only the keys the file sets
    path: str = ""

    @property
    def duration_s(self):
        return float(self.times[-1])

    def reset_kwargs(self):
        """Keyword arguments of ``Plant.reset`` for the initial conditions."""
        init = {**INITIAL_KEYS, **self.initial}
        return {
            "vehicle_speed_kmh": init["vehicle_speed_kmh"],
            "sleeves": tuple(init[f"sleeve{i}_side"] for i in range(1, 5)),
            "clutch_locked": (init["clutch1_locked"], init["clutch2_locked"]),
            "engine_on": init["engine_on"],
            **{key: self.initial[key] for key in TEMPERATURE_KEYS if key in self.initial},
        }

    @property
    def pressure_commanded(self):
        """True when the file scripts clutch pressures rather than valve
        currents: it is then played with the hydraulics bypassed."""
        return any(c in PRESSURE_COLUMNS for c in self.columns)

    def param_overrides(self):
        """Parameter overrides the scenario needs: the clutch command mode
        its columns script (none when it scripts neither)."""
        if self.pressure_commanded:
            return {"hydraulics": {"pressure_commanded": 1}}
        if any(c in CURRENT_COLUMNS for c in self.columns):
            return {"hydraulics": {"pressure_commanded": 0}}
        return {}

    def row_steps(self, step_s):
        """Index of the step before which each row is applied."""
        return np.ceil(self.times / step_s - _TIME_EPS).astype(np.int64)

    def values_at(self, time_s):
        """The row values in force at ``time_s`` (the last row at or before it)."""
        i = int(np.searchsorted(self.times, time_s + _TIME_EPS, side="right")) - 1
        return self.values[max(i, 0)]


def shipped_names():
    """Names of the scenarios in plant/scenarios."""
    try:
        files = os.listdir(SCENARIO_DIR)
    except OSError:
        return []
    return sorted(f[:-4] for f in files if f.endswith(".csv"))


def resolve(name_or_path):
    """Path of a scenario given by name (plant/scenarios/<name>.csv) or by path."""
    text = os.fspath(name_or_path)
    shipped = os.path.join(SCENARIO_DIR, text if text.endswith(".csv") else text + ".csv")
    if os.sep in text or os.path.exists(text) or (text.endswith(".csv") and not os.path.isfile(shipped)):
        if not os.path.isfile(text):
            raise ScenarioError(f"{text}: no such scenario file")
        return text
    path = shipped
    if not os.path.isfile(path):
        raise ScenarioError(
            f"unknown scenario {text!r}; shipped: {', '.join(shipped_names()) or 'none'}"
        )
    return path


def _input_names():
    from plant._dct_plant import ffi

    return [name for name, _ in ffi.typeof("dct_inputs").fields]


def load_scenario(name_or_path, input_names=None):
    """Read a scenario by name or path; raises ScenarioError (one line)."""
    path = resolve(name_or_path)
    if input_names is None:
        input_names = _input_names()
    known = set(input_names)
    name = os.path.splitext(os.path.basename(path))[0]

    def fail(lineno, cause):
        raise ScenarioError(f"{path}:{lineno}: {cause}")

    try:
        with open(path, encoding="utf-8") as f:
            lines = f.read().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(f"{path}: cannot read: {getattr(e, 'strerror', None) or e}") from None

    initial = {}
    columns = None
    times, rows = [], []
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line[1:].strip()
            if body.lower().startswith("initial:"):
                _parse_initial(body[len("initial:"):], initial, lambda c, n=lineno: fail(n, c))
            continue
        cells = [c.strip() for c in line.split(",")]
        if columns is None:
            if cells[0] != "time_s":
                fail(lineno, f"the first column must be time_s, not {cells[0]!r}")
            columns = cells[1:]
            seen = set()
            for c in columns:
                if c not in known:
                    fail(lineno, f"unknown column {c!r}; inputs are: {', '.join(input_names)}")
                if c in seen:
                    fail(lineno, f"column {c!r} appears twice")
                seen.add(c)
            if seen & set(PRESSURE_COLUMNS) and seen & set(CURRENT_COLUMNS):
                fail(lineno, "script either clutch pressures (hydraulics bypassed) or "
                             "valve currents, not both")
            continue
        if len(cells) != len(columns) + 1:
            fail(lineno, f"{len(cells)} cells, the header has {len(columns) + 1}")
        numbers = []
        for col, cell in zip(["time_s"] + columns, cells):
            try:
                x = float(cell)
            except ValueError:
                fail(lineno, f"{col}: {cell!r} is not a number")
            if not math.isfinite(x):
                fail(lineno, f"{col}: {cell!r} is not a finite number")
            numbers.append(x)
        t = numbers[0]
        if not times and t != 0.0:
            fail(lineno, f"the first row must be at time 0, not {_num(t)}")
        if times and t <= times[-1]:
            fail(lineno, f"time {_num(t)} does not increase (previous row {_num(times[-1])})")
        times.append(t)
        rows.append(numbers[1:])

    if columns is None:
        fail(max(len(lines), 1), "empty file: no header line (time_s,<input>,...)")
    if not rows:
        fail(max(len(lines), 1), "no data rows after the header")
    return Scenario(
        name=name,
        times=np.array(times),
        columns=columns,
        values=np.array(rows, dtype=np.float64).reshape(len(rows), len(columns)),
        initial=initial,
        path=path,
    )


def _num(x):
    return f"{x:g}"


def _parse_initial(text, initial, fail):
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep:
            fail(f"initial: {item!r} is not key=value")
        if key not in INITIAL_KEYS and key not in TEMPERATURE_KEYS:
            fail(f"unknown initial key {key!r}; keys are: {', '.join([*INITIAL_KEYS, *TEMPERATURE_KEYS])}")
        try:
            x = float(value)
        except ValueError:
            fail(f"initial {key}: {value!r} is not a number")
        if not math.isfinite(x):
            fail(f"initial {key}: {value!r} is not a finite number")
        bounds = TEMPERATURE_KEYS.get(key)
        if bounds is not None and not bounds[0] <= x <= bounds[1]:
            fail(f"initial {key} = {value} is out of range [{bounds[0]:g}, {bounds[1]:g}] degC")
        allowed = _ALLOWED.get(key)
        if allowed is not None and x not in allowed:
            fail(f"initial {key} must be one of {', '.join(f'{a:g}' for a in allowed)}, not {value}")
        initial[key] = x
