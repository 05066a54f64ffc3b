"""Named maneuvers: a driver, a duration, the start state and the figures to report.

- ``paper-cycle``: the reference paper's TCU test (section 5): launch from standstill at
  wide-open throttle, brake to zero, launch at half load, brake to zero (65 s).
- ``wltc``: WLTC class 3b followed by the PI speed-tracking driver (1800 s); fuel in l/100 km.
- ``nedc``: the NEDC, the cycle of the car's published fuel figures (1180 s); fuel in l/100 km.
- ``0-100``: full throttle from standstill through 100 km/h and on to top speed (100 s).
- ``creep``: idle in D on level ground, the brake released: the car creeps; then held on
  the brake for 10 s, then released again (45 s); creep speed.
- ``reverse-park``: at a stop select R, release the brake and creep backwards a few
  metres, brake to a stop, select P and release the brake (16 s); distance backwards.
- ``hill-start``: on a 20 % grade held on the brake, release it, then 30 % accelerator:
  drive away (15 s); rollback and time to 10 km/h.

A maneuver may set fixed plant inputs (``inputs``: the road grade) and scripts the
selector lever in its driver's table (``plant.driver.ScriptedDriver``);
``Maneuver.start(plant)`` resets the plant and sets them.

``report(maneuver, recorded)`` computes the figures from a recorded run: a mapping of
output name -> array (``time_s``, ``vehicle_speed_kmh``, ``accel_pedal_pct``, ``fuel_l``,
``distance_m``), or an object with ``names`` and ``data`` (``plant.simulate.SimResult``).
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plant.driver import ScriptedDriver, SpeedTrackingDriver, driver_inputs

WLTC_PATH = Path(__file__).parent / "data" / "wltc_class3b.csv"
NEDC_PATH = Path(__file__).parent / "data" / "nedc.csv"
DRIVER_PERIOD_S = 0.01

# paper-cycle: (t_s, accel_pedal_pct, brake_pedal_pct), held until the next row
PAPER_CYCLE = [
    (0.0, 0.0, 30.0),     # standing on the brake
    (1.0, 100.0, 0.0),    # launch at wide-open throttle, up through the gears
    (13.0, 0.0, 40.0),    # brake to zero (about 4 m/s2), downshifts to 1st
    (27.0, 50.0, 0.0),    # launch at half load
    (45.0, 0.0, 30.0),    # brake to zero
    (65.0, 0.0, 30.0),
]
FULL_THROTTLE = [(0.0, 0.0, 30.0), (1.0, 100.0, 0.0), (100.0, 100.0, 0.0)]
# creep: (t_s, accel_pedal_pct, brake_pedal_pct, selector)
CREEP = [
    (0.0, 0.0, 30.0, "D"),    # standing on the brake in D, engine at idle
    (2.0, 0.0, 0.0, "D"),     # brake released: the car creeps
    (20.0, 0.0, 30.0, "D"),   # brake: stop and hold for 10 s
    (32.0, 0.0, 0.0, "D"),    # released again
    (45.0, 0.0, 0.0, "D"),
]
CREEP_RELEASE_S = (2.0, 32.0)     # the brake releases
CREEP_HOLD_S = (20.0, 32.0)       # the brake hold
# reverse-park
REVERSE_PARK = [
    (0.0, 0.0, 40.0, "D"),    # stopped on the brake in D
    (1.0, 0.0, 40.0, "R"),    # select R, wait for R to engage
    (3.0, 0.0, 0.0, "R"),     # brake released: creeping backwards
    (7.0, 0.0, 40.0, "R"),    # brake to a stop
    (10.0, 0.0, 40.0, "P"),   # select P
    (12.0, 0.0, 0.0, "P"),    # brake released: the parking lock holds
    (16.0, 0.0, 0.0, "P"),
]
# hill-start on HILL_GRADE_PCT
HILL_GRADE_PCT = 20.0
HILL_START = [
    (0.0, 0.0, 60.0, "D"),    # held on the brake on the grade
    (3.0, 0.0, 0.0, "D"),     # brake released
    (3.5, 30.0, 0.0, "D"),    # accelerator 30 %: drive away
    (15.0, 30.0, 0.0, "D"),
]


#: the plant inputs a maneuver may fix for its whole run: name -> (min, max)
FIXED_INPUTS = {"road_grade_pct": (-40.0, 40.0)}


@dataclass
class Maneuver:
    name: str
    driver: object            # driver_fn(t_s, outputs) -> (accel_pedal_pct, brake_pedal_pct)
    duration_s: float
    report: tuple             # names of the figures report() gives
    reset_kwargs: dict = field(default_factory=dict)   # for Plant.reset()
    description: str = ""
    inputs: dict = field(default_factory=dict)         # fixed plant inputs (FIXED_INPUTS), from the start

    def __post_init__(self):
        self.inputs = check_inputs(self.inputs, f"maneuver {self.name}")

    def start(self, plant):
        """Resets the plant as the maneuver starts (``reset_kwargs``) and sets its fixed
        inputs (the road grade); the driver's table sets the pedals and the selector."""
        plant.reset(**self.reset_kwargs)
        for name, value in self.inputs.items():
            plant.inputs[name] = value
        plant.update_outputs()


def check_inputs(inputs, where):
    """``inputs`` ({input: value}) checked against FIXED_INPUTS: floats, or a
    ValueError of one line naming the input."""
    out = {}
    for name, value in dict(inputs or {}).items():
        if name not in FIXED_INPUTS:
            raise ValueError(f"{where}: {name!r} is not an input a maneuver fixes "
                             f"({', '.join(FIXED_INPUTS)})")
        lo, hi = FIXED_INPUTS[name]
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {name} must be a number, got {value!r}") from None
        if not (math.isfinite(x) and lo <= x <= hi):
            raise ValueError(f"{where}: {name} = {value!r} is outside {lo:g} .. {hi:g}")
        out[name] = x
    return out


def load_wltc(path=None):
    """WLTC class 3b trace: (time_s, speed_kmh) arrays, 1 Hz, 1801 samples."""
    return load_trace(WLTC_PATH if path is None else path)


def load_nedc(path=None):
    """NEDC trace: (time_s, speed_kmh) arrays, 1 Hz, 1180 samples."""
    return load_trace(NEDC_PATH if path is None else path)


def load_trace(path):
    """A drive-cycle speed trace file (``time_s,speed_kmh``, '#' comments)."""
    p = Path(path)
    try:
        lines = p.read_text().splitlines()
    except OSError as exc:
        raise ValueError(f"cannot read the speed trace {p}: {exc.strerror}") from None
    rows = [ln.split(",") for ln in lines if ln.strip() and not ln.startswith("#")]
    if not rows or rows[0][:2] != ["time_s", "speed_kmh"]:
        raise ValueError(f"{p}: expected a 'time_s,speed_kmh' header")
    try:
        a = np.array([[float(r[0]), float(r[1])] for r in rows[1:]])
    except (ValueError, IndexError):
        raise ValueError(f"{p}: rows must be two numbers: time_s,speed_kmh") from None
    t, v = a[:, 0], a[:, 1]
    return t, v


def _paper_cycle():
    return Maneuver("paper-cycle", ScriptedDriver(PAPER_CYCLE), 65.0,
                    ("zero_to_100_s", "top_speed_kmh", "fuel_l_per_100km"),
                    description="launch at WOT, brake to zero, launch at half load, brake to zero")


def _wltc():
    t, v = load_wltc()
    return Maneuver("wltc", SpeedTrackingDriver(t, v), float(t[-1]),
                    ("rms_speed_error_kmh", "fuel_l_per_100km", "distance_km", "top_speed_kmh"),
                    description="WLTC class 3b, PI speed-tracking driver")


def _nedc():
    t, v = load_nedc()
    return Maneuver("nedc", SpeedTrackingDriver(t, v), float(t[-1]),
                    ("rms_speed_error_kmh", "fuel_l_per_100km", "distance_km", "top_speed_kmh"),
                    description="NEDC (the cycle of the car's published fuel figures), PI "
                                "speed-tracking driver")


def _zero_to_100():
    return Maneuver("0-100", ScriptedDriver(FULL_THROTTLE), 100.0,
                    ("zero_to_100_s", "top_speed_kmh"),
                    description="full throttle from standstill to top speed")


def _creep():
    return Maneuver("creep", ScriptedDriver(CREEP), CREEP[-1][0],
                    ("creep_speed_kmh", "hold_speed_max_kmh", "creep_again_speed_kmh"),
                    description="idle in D, brake released: creep; held on the brake 10 s; "
                                "released again")


def _reverse_park():
    return Maneuver("reverse-park", ScriptedDriver(REVERSE_PARK), REVERSE_PARK[-1][0],
                    ("reverse_engaged_s", "reverse_distance_m", "reverse_speed_max_kmh",
                     "park_creep_m"),
                    description="select R at a stop, creep backwards a few metres, brake, "
                                "select P, release the brake")


def _hill_start():
    return Maneuver("hill-start", ScriptedDriver(HILL_START), HILL_START[-1][0],
                    ("rollback_m", "time_to_10kmh_s"),
                    description=f"{HILL_GRADE_PCT:g} % grade: brake released, 30 % accelerator",
                    inputs={"road_grade_pct": HILL_GRADE_PCT})


# the maneuvers given as pedal tables: the real-time loop plays them itself
# (dct-hil serve --maneuver, demo); wltc and nedc are speed traces a driver follows
LOOP_MANEUVERS = ("paper-cycle", "0-100", "creep", "reverse-park", "hill-start")
MANEUVERS = {"paper-cycle": _paper_cycle, "wltc": _wltc, "nedc": _nedc, "0-100": _zero_to_100,
             "creep": _creep, "reverse-park": _reverse_park, "hill-start": _hill_start}


def get_maneuver(name):
    """A fresh Maneuver (its driver has no history) by name."""
    try:
        return MANEUVERS[name]()
    except KeyError:
        raise ValueError(f"unknown maneuver {name!r}; choose from {', '.join(MANEUVERS)}") from None


def as_arrays(recorded):
    """mapping name -> 1-D float array from a dict of arrays or a SimResult-like object."""
    if hasattr(recorded, "names") and hasattr(recorded, "data"):
        data = np.asarray(recorded.data, dtype=float)
        return {n: data[:, k] for k, n in enumerate(recorded.names)}
    if hasattr(recorded, "dtype") and getattr(recorded.dtype, "names", None):
        return {n: np.asarray(recorded[n], dtype=float) for n in recorded.dtype.names}
    out = {}
    for n, v in dict(recorded).items():   # numeric 1-D series only (skips event lists, phases)
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            continue
        if a.ndim == 1:
            out[n] = a
    return out


def _need(rec, *names):
    for n in names:
        if n not in rec:
            raise ValueError(f"recorded run has no '{n}'")
        if len(rec[n]) != len(rec["time_s"]):
            raise ValueError(f"recorded '{n}' has {len(rec[n])} samples, time_s has {len(rec['time_s'])}")


def zero_to_100_s(rec):
    """Time from the full-throttle launch at standstill to 100 km/h (None if not reached)."""
    t, v, p = rec["time_s"], rec["vehicle_speed_kmh"], rec["accel_pedal_pct"]
    start = np.flatnonzero((p >= 99.0) & (v < 1.0))
    if len(start) == 0:
        return None
    k0 = start[0]
    above = np.flatnonzero(v[k0:] >= 100.0)
    if len(above) == 0:
        return None
    k1 = k0 + above[0]
    t1 = t[k1]
    if k1 > k0 and v[k1] > v[k1 - 1]:   # interpolate the crossing
        t1 = t[k1 - 1] + (100.0 - v[k1 - 1]) / (v[k1] - v[k1 - 1]) * (t[k1] - t[k1 - 1])
    return float(t1 - t[k0])


def rms_speed_error_kmh(rec, driver):
    """RMS of (trace speed - vehicle speed) over the samples within the trace."""
    t, v = rec["time_s"], rec["vehicle_speed_kmh"]
    inside = t <= driver.trace_t_s[-1]
    ref = np.interp(t[inside], driver.trace_t_s, driver.trace_kmh)
    return float(np.sqrt(np.mean((ref - v[inside]) ** 2)))


def fuel_l_per_100km(rec):
    d_km = (rec["distance_m"][-1] - rec["distance_m"][0]) / 1000.0
    if d_km <= 0.01:
        return None
    return float((rec["fuel_l"][-1] - rec["fuel_l"][0]) / d_km * 100.0)


SHIFT_MIN_HOLD_S = 0.1
#: slack on the hold: a recording's times carry rounding (a CSV's printed times differ
#: from the run's by up to 0.2 us), so a gear held exactly ``min_hold_s`` counts the
#: same in the run and in its CSV
SHIFT_HOLD_SLACK_S = 1e-6


def gear_shifts(time_s, gear, min_hold_s=SHIFT_MIN_HOLD_S):
    """The shifts of a recorded run, seen from the plant: (t_s, from_gear, to_gear).

    ``gear`` is the plant's engaged gear: the gear engaged on the input shaft
    whose clutch carries the drive torque or, while neither does, carried it
    last (``dct_outputs.gear``); 0 before the first launch or while that
    shaft has no gear engaged. Samples with gear 0 are gaps, not a gear. A
    gear held for less than ``min_hold_s`` is not a shift and is dropped (the
    plant's gear does not flicker; a recording of the gear carrying the
    torque, without the hold, does at each torque handover and zero
    crossing; within ``SHIFT_HOLD_SLACK_S``, the times' rounding). A shift is
    the first sample of the next gear held that long; the first gear of the
    run is no shift."""
    t = np.asarray(time_s, dtype=float)
    g = np.rint(np.asarray(gear, dtype=float)).astype(int)
    if t.shape != g.shape:
        raise ValueError("time_s and gear must have the same length")
    segments = []                               # [gear, first t, last t]
    for tk, gk in zip(t, g):
        if gk == 0:
            continue
        if segments and segments[-1][0] == gk:
            segments[-1][2] = tk
        else:
            segments.append([gk, tk, tk])
    kept = []
    for seg in segments:
        if seg[2] - seg[1] < min_hold_s - SHIFT_HOLD_SLACK_S:
            continue
        if kept and kept[-1][0] == seg[0]:
            kept[-1][2] = seg[2]
        else:
            kept.append(seg)
    return [(float(b[1]), int(a[0]), int(b[0])) for a, b in zip(kept, kept[1:])]


def compare_shifts(reference, other):
    """Shift sequences side by side: (same_sequence, [time differences other - reference, s])."""
    same = [(a, b) for _, a, b in reference] == [(a, b) for _, a, b in other]
    diffs = [o[0] - r[0] for r, o in zip(reference, other)] if same else []
    return same, diffs


# ---------------------------------------------------------------- low-speed figures
STEADY_S = 5.0          # the steady creep speed: the mean over the last seconds of a phase
HOLD_SETTLE_S = 2.0     # a brake hold's figure starts this long after the brake is applied


class NoSamples(ValueError):
    """The recording has no samples where a figure looks (a run cut short)."""


def _window(rec, t0, t1):
    t = rec["time_s"]
    inside = (t >= t0 - 1e-9) & (t < t1 - 1e-9)
    if not np.any(inside):
        raise NoSamples(f"recorded run has no samples between {t0:g} and {t1:g} s")
    return inside


def _at(rec, name, t_s):
    """``rec[name]`` at the last sample at or before ``t_s`` (the first sample before it)."""
    k = max(0, int(np.searchsorted(rec["time_s"], t_s + 1e-9, side="right")) - 1)
    return float(rec[name][k])


def mean_speed_kmh(rec, t0, t1):
    """Mean vehicle speed over the samples in [t0, t1)."""
    return float(np.mean(rec["vehicle_speed_kmh"][_window(rec, t0, t1)]))


def speed_max_abs_kmh(rec, t0, t1):
    """Largest |vehicle speed| over the samples in [t0, t1)."""
    return float(np.max(np.abs(rec["vehicle_speed_kmh"][_window(rec, t0, t1)])))


def rollback_m(rec, t_release_s):
    """How far the car rolled back after the brake released at ``t_release_s``: the most
    negative displacement (``distance_m``) from its position then, as metres >= 0."""
    inside = rec["time_s"] >= t_release_s - 1e-9
    if not np.any(inside):
        raise NoSamples(f"recorded run ends before the brake release at {t_release_s:g} s")
    d0 = _at(rec, "distance_m", t_release_s)
    return float(max(0.0, d0 - float(np.min(rec["distance_m"][inside]))))


def time_to_speed_s(rec, t0_s, kmh=10.0):
    """Time from ``t0_s`` until the vehicle speed first reaches ``kmh`` (the crossing
    interpolated between samples), None if it does not."""
    t, v = rec["time_s"], rec["vehicle_speed_kmh"]
    after = np.flatnonzero((t >= t0_s - 1e-9) & (v >= kmh))
    if len(after) == 0:
        return None
    k = after[0]
    t1 = t[k]
    if k > 0 and t[k - 1] >= t0_s - 1e-9 and v[k] > v[k - 1]:
        t1 = t[k - 1] + (kmh - v[k - 1]) / (v[k] - v[k - 1]) * (t[k] - t[k - 1])
    return float(t1 - t0_s)


def reverse_figures(rec, t_select_r_s, t_select_p_s, t_park_release_s):
    """The reverse-park figures: ``reverse_engaged_s`` (from selecting R to the first
    sample in gear R, None if never), ``reverse_distance_m`` (metres backwards between
    selecting R and selecting P), ``reverse_speed_max_kmh`` (largest backward speed in
    R, km/h >= 0) and ``park_creep_m`` (|movement| from the brake release in P to the
    end: the parking lock holds)."""
    t, gear = rec["time_s"], rec["gear"]
    in_r = np.flatnonzero((t >= t_select_r_s - 1e-9) & (t < t_select_p_s - 1e-9)
                          & (np.rint(gear) == -1))
    engaged = float(t[in_r[0]] - t_select_r_s) if len(in_r) else None
    back = -rec["vehicle_speed_kmh"][_window(rec, t_select_r_s, t_select_p_s)]
    return {
        "reverse_engaged_s": engaged,
        "reverse_distance_m": _at(rec, "distance_m", t_select_r_s) - _at(rec, "distance_m", t_select_p_s),
        "reverse_speed_max_kmh": float(max(0.0, np.max(back))),
        "park_creep_m": abs(float(rec["distance_m"][-1]) - _at(rec, "distance_m", t_park_release_s)),
    }


def _script(m):
    """The rows of a maneuver's scripted driver: [(t_s, accel, brake, selector code or None)]."""
    d = m.driver
    if not isinstance(d, ScriptedDriver):
        raise ValueError(f"maneuver {m.name}: its figures need a scripted driver")
    sel = d.selector_table
    return [(float(r[0]), float(r[1]), float(r[2]), None if sel is None else int(sel[k]))
            for k, r in enumerate(d.table)]


def brake_releases(m):
    """Times at which the maneuver's script releases the brake (brake > 0 -> 0)."""
    rows = _script(m)
    return [b[0] for a, b in zip(rows, rows[1:]) if a[2] > 0 and b[2] == 0]


def brake_applies(m):
    """Times at which the maneuver's script applies the brake (brake 0 -> > 0)."""
    rows = _script(m)
    return [b[0] for a, b in zip(rows, rows[1:]) if a[2] == 0 and b[2] > 0]


def selector_times(m, position):
    """Times at which the script moves the selector to ``position`` ("P", "R", "N", "D")."""
    from plant.driver import selector_code

    code = selector_code(position)
    rows = _script(m)
    return [b[0] for a, b in zip(rows, rows[1:]) if a[3] != code and b[3] == code]


def _low_speed(m, rec, name, cache):
    if name in ("creep_speed_kmh", "creep_again_speed_kmh"):
        releases, applies = brake_releases(m), brake_applies(m)
        k = 0 if name == "creep_speed_kmh" else 1
        if len(releases) <= k:
            raise ValueError(f"maneuver {m.name}: its script releases the brake {len(releases)} times")
        t0 = releases[k]
        ends = [t for t in applies if t > t0] + [m.duration_s]
        return mean_speed_kmh(rec, max(t0, ends[0] - STEADY_S), ends[0])
    if name == "hold_speed_max_kmh":
        t0 = brake_applies(m)[0]
        t1 = next(t for t in brake_releases(m) + [m.duration_s] if t > t0)
        return speed_max_abs_kmh(rec, t0 + HOLD_SETTLE_S, t1)
    if name in ("reverse_engaged_s", "reverse_distance_m", "reverse_speed_max_kmh", "park_creep_m"):
        if "reverse" not in cache:
            t_r = selector_times(m, "R")[0]
            t_p = selector_times(m, "P")[0]
            t_rel = next(t for t in brake_releases(m) if t > t_p)
            _need(rec, "gear", "distance_m")
            cache["reverse"] = reverse_figures(rec, t_r, t_p, t_rel)
        return cache["reverse"][name]
    if name == "rollback_m":
        _need(rec, "distance_m")
        return rollback_m(rec, brake_releases(m)[0])
    if name == "time_to_10kmh_s":
        return time_to_speed_s(rec, brake_releases(m)[0], 10.0)
    raise ValueError(f"unknown report figure {name!r}")


LOW_SPEED_FIGURES = ("creep_speed_kmh", "creep_again_speed_kmh", "hold_speed_max_kmh",
                     "reverse_engaged_s", "reverse_distance_m", "reverse_speed_max_kmh",
                     "park_creep_m", "rollback_m", "time_to_10kmh_s")


def report(maneuver, recorded):
    """Figures of a recorded run: dict name -> value (None when not defined)."""
    m = get_maneuver(maneuver) if isinstance(maneuver, str) else maneuver
    rec = as_arrays(recorded)
    _need(rec, "time_s", "vehicle_speed_kmh")
    out = {}
    cache = {}
    for name in m.report:
        if name in LOW_SPEED_FIGURES:
            try:
                out[name] = _low_speed(m, rec, name, cache)
            except NoSamples:               # the run ended before the figure's phase
                out[name] = None
        elif name == "zero_to_100_s":
            _need(rec, "accel_pedal_pct")
            out[name] = zero_to_100_s(rec)
        elif name == "top_speed_kmh":
            out[name] = float(np.max(rec["vehicle_speed_kmh"]))
        elif name == "rms_speed_error_kmh":
            out[name] = rms_speed_error_kmh(rec, m.driver)
        elif name == "fuel_l_per_100km":
            _need(rec, "fuel_l", "distance_m")
            out[name] = fuel_l_per_100km(rec)
        elif name == "distance_km":
            _need(rec, "distance_m")
            out[name] = float((rec["distance_m"][-1] - rec["distance_m"][0]) / 1000.0)
        else:
            raise ValueError(f"unknown report figure {name!r}")
    return out


def format_report(maneuver_name, figures):
    units = {"zero_to_100_s": "s", "top_speed_kmh": "km/h", "rms_speed_error_kmh": "km/h",
             "fuel_l_per_100km": "l/100 km", "distance_km": "km", "creep_speed_kmh": "km/h",
             "creep_again_speed_kmh": "km/h", "hold_speed_max_kmh": "km/h",
             "reverse_engaged_s": "s", "reverse_distance_m": "m", "reverse_speed_max_kmh": "km/h",
             "park_creep_m": "m", "rollback_m": "m", "time_to_10kmh_s": "s"}
    parts = []
    for k, v in figures.items():
        parts.append(f"{k} = {'n/a' if v is None else f'{v:.2f}'} {units.get(k, '')}".rstrip())
    return f"{maneuver_name}: " + ", ".join(parts)


def run_driver(plant, driver_fn, duration_s, controller=None, record_every_s=DRIVER_PERIOD_S):
    """Drive the plant without a TCU: pedals from ``driver_fn`` every 10 ms.

    ``controller(plant)``, if given, is called before each 10 ms chunk (a fixed
    gear strategy for tests). The plant must already be reset. Returns dict of
    recorded output arrays (every ``record_every_s``), ``time_s`` from the start.
    """
    if not (math.isfinite(duration_s) and duration_s >= 0):
        raise ValueError(f"duration must be a finite number >= 0, got {duration_s}")
    h = plant.step_s
    n_drv = max(1, int(round(DRIVER_PERIOD_S / h)))
    every = max(1, int(round(record_every_s / h)))
    n_end = int(round(duration_s / h))
    names = list(plant.output_names)
    rows = []
    t0 = plant.time_s
    k = 0
    while True:
        if k % every == 0:
            rows.append(np.array(plant.output_values))
        if k >= n_end:
            break
        if k % n_drv == 0:
            for name, value in driver_inputs(driver_fn, plant.time_s - t0, plant.outputs).items():
                plant.inputs[name] = value
            if controller is not None:
                controller(plant)
        n = min(n_drv - k % n_drv, every - k % every, n_end - k)
        plant.step(n)
        k += n
    data = np.array(rows)
    rec = {n: data[:, j] for j, n in enumerate(names)}
    rec["time_s"] = rec["time_s"] - t0
    return rec
