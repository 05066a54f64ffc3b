"""Named maneuvers: a driver, a duration, the start state and the figures to report.

- ``paper-cycle``: the reference paper's TCU test (section 5): launch from standstill at
  wide-open throttle, brake to zero, launch at half load, brake to zero (65 s).
- ``wltc``: WLTC class 3b followed by the PI speed-tracking driver (1800 s); fuel in l/100 km.
- ``nedc``: the NEDC, the cycle of the car's published fuel figures (1180 s); fuel in l/100 km.
- ``0-100``: full throttle from standstill through 100 km/h and on to top speed (100 s).

``report(maneuver, recorded)`` computes the figures from a recorded run: a mapping of
output name -> array (``time_s``, ``vehicle_speed_kmh``, ``accel_pedal_pct``, ``fuel_l``,
``distance_m``), or an object with ``names`` and ``data`` (``plant.simulate.SimResult``).
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plant.driver import ScriptedDriver, SpeedTrackingDriver

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


@dataclass
class Maneuver:
    name: str
    driver: object            # driver_fn(t_s, outputs) -> (accel_pedal_pct, brake_pedal_pct)
    duration_s: float
    report: tuple             # names of the figures report() gives
    reset_kwargs: dict = field(default_factory=dict)   # for Plant.reset()
    description: str = ""


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


MANEUVERS = {"paper-cycle": _paper_cycle, "wltc": _wltc, "nedc": _nedc, "0-100": _zero_to_100}


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


def gear_shifts(time_s, gear, min_hold_s=SHIFT_MIN_HOLD_S):
    """The shifts of a recorded run, seen from the plant: (t_s, from_gear, to_gear).

    ``gear`` is the plant's engaged gear: the gear engaged on the input shaft
    whose clutch carries the drive torque or, while neither does, carried it
    last (``dct_outputs.gear``); 0 before the first launch or while that
    shaft has no gear engaged. Samples with gear 0 are gaps, not a gear. A
    gear held for less than ``min_hold_s`` is not a shift and is dropped (the
    plant's gear does not flicker; a recording of the gear carrying the
    torque, without the hold, does at each torque handover and zero
    crossing). A shift is the first sample of the next gear held that long;
    the first gear of the run is no shift."""
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
        if seg[2] - seg[1] < min_hold_s:
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


def report(maneuver, recorded):
    """Figures of a recorded run: dict name -> value (None when not defined)."""
    m = get_maneuver(maneuver) if isinstance(maneuver, str) else maneuver
    rec = as_arrays(recorded)
    _need(rec, "time_s", "vehicle_speed_kmh")
    out = {}
    for name in m.report:
        if name == "zero_to_100_s":
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
             "fuel_l_per_100km": "l/100 km", "distance_km": "km"}
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
            accel, brake = driver_fn(plant.time_s - t0, plant.outputs)
            plant.inputs["accel_pedal_pct"] = accel
            plant.inputs["brake_pedal_pct"] = brake
            if controller is not None:
                controller(plant)
        n = min(n_drv - k % n_drv, every - k % every, n_end - k)
        plant.step(n)
        k += n
    data = np.array(rows)
    rec = {n: data[:, j] for j, n in enumerate(names)}
    rec["time_s"] = rec["time_s"] - t0
    return rec
