"""Drivers: the pedals a person would press, as functions of time and the plant outputs.

Both drivers are callables ``driver(t_s, outputs) -> (accel_pedal_pct, brake_pedal_pct)``;
``outputs`` is anything indexable by output name (``Plant.outputs``, a dict). They are
called every 10 ms by the offline runner and the server.

- ``ScriptedDriver``: a pedal profile as a time table, step-wise or linear, with an
  optional selector lever column (P, R, N, D); ``driver_inputs`` gives every plant
  input a driver sets.
- ``SpeedTrackingDriver``: follows a speed trace (a drive cycle) with a PI controller
  on the speed error, feed-forward of the force the trace needs, anti-windup and the
  brake when the needed force is negative.
"""

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFAULT_PARAMS = Path(__file__).parent / "data" / "golf_mk5_gti_dsg.toml"
AIR_DENSITY_KG_M3 = 1.2
G_MPS2 = 9.81


def _table(rows, name):
    """rows of numbers -> float array (n, k), time strictly increasing from column 0."""
    a = np.asarray(rows, dtype=float)
    if a.ndim != 2 or a.shape[0] < 1:
        raise ValueError(f"{name}: needs at least one row of numbers")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: values must be finite numbers")
    if a.shape[0] > 1 and not np.all(np.diff(a[:, 0]) > 0):
        raise ValueError(f"{name}: times must be strictly increasing")
    return a


#: selector lever positions: name -> the code of the plant input ``selector_lever``
#: (and of the CAN signal VEH_Driver.SelectorLever)
SELECTOR_CODES = {"P": 0, "R": 1, "N": 2, "D": 3}
SELECTOR_NAMES = {code: name for name, code in SELECTOR_CODES.items()}


def selector_code(value, where="selector"):
    """The code (0..3) of a selector position: "P", "R", "N", "D" (any case) or its code."""
    if isinstance(value, str):
        code = SELECTOR_CODES.get(value.strip().upper())
        if code is None:
            raise ValueError(f"{where}: unknown selector position {value!r} (P, R, N or D)")
        return code
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: unknown selector position {value!r} (P, R, N or D)") from None
    if x not in SELECTOR_NAMES:
        raise ValueError(f"{where}: unknown selector position {value!r} (P, R, N or D)")
    return int(x)


class ScriptedDriver:
    """Pedals, and optionally the selector lever, from a time table.

    ``profile``: rows ``(t_s, accel_pedal_pct, brake_pedal_pct)`` or, with the
    selector lever, ``(t_s, accel_pedal_pct, brake_pedal_pct, selector)`` (selector
    "P", "R", "N", "D" or its code 0..3; every row has one), times increasing.
    ``mode``: "step" holds each row's pedals until the next row (before the first row:
    the first row); "linear" interpolates the pedals between rows and holds the ends.
    The selector is held from its row on in either mode (``selector``).
    """

    def __init__(self, profile, mode="step"):
        try:
            rows = [list(r) for r in profile]
        except TypeError:
            raise ValueError("pedal profile: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                             "[, selector])") from None
        for k, r in enumerate(rows):
            if len(r) != len(rows[0]):
                raise ValueError(f"pedal profile row {k + 1}: {len(r)} values, the first row has "
                                 f"{len(rows[0])}")
        selector = None
        if rows and len(rows[0]) == 4:
            selector = np.array([float(selector_code(r[3], f"pedal profile row {k + 1}"))
                                 for k, r in enumerate(rows)])
            rows = [r[:3] for r in rows]
        a = _table(rows, "pedal profile")
        if a.shape[1] != 3:
            raise ValueError("pedal profile: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                             "[, selector])")
        if np.any(a[:, 1:] < 0) or np.any(a[:, 1:] > 100):
            raise ValueError("pedal profile: pedals must be within 0..100 %")
        if mode not in ("step", "linear"):
            raise ValueError(f"pedal profile mode must be 'step' or 'linear', got {mode!r}")
        self.table = a
        self.mode = mode
        #: selector code per row (float array), None: the table leaves the selector alone
        self.selector_table = selector

    @property
    def duration_s(self):
        return float(self.table[-1, 0])

    def _row(self, t):
        return max(0, int(np.searchsorted(self.table[:, 0], t, side="right")) - 1)

    def __call__(self, t_s, outputs=None):
        t, a = float(t_s), self.table
        if self.mode == "linear":
            return (float(np.interp(t, a[:, 0], a[:, 1])), float(np.interp(t, a[:, 0], a[:, 2])))
        k = self._row(t)
        return float(a[k, 1]), float(a[k, 2])

    def selector(self, t_s):
        """The selector lever's code at ``t_s`` (the last row at or before it, the
        first row before it), None when the table has no selector column."""
        if self.selector_table is None:
            return None
        return float(self.selector_table[self._row(float(t_s))])


def driver_inputs(driver_fn, t_s, outputs):
    """The plant inputs a driver sets at ``t_s``: the pedals and, for a driver with a
    selector column, ``selector_lever`` ({input name: value})."""
    accel, brake = driver_fn(t_s, outputs)
    out = {"accel_pedal_pct": accel, "brake_pedal_pct": brake}
    selector = getattr(driver_fn, "selector", None)
    if selector is not None:
        code = selector(t_s)
        if code is not None:
            out["selector_lever"] = code
    return out


@dataclass
class CarData:
    """What the speed-tracking driver knows of the car (for its feed-forward)."""
    mass_kg: float = 1400.0
    wheel_radius_m: float = 0.316
    rolling_resistance: float = 0.009
    drag_area_m2: float = 0.32 * 2.22          # cd * A
    full_load_rpm: tuple = (0, 600, 1000, 1500, 1800, 5000, 5500, 6000, 6500, 7000)
    full_load_nm: tuple = (0, 120, 170, 240, 280, 280, 255, 234, 200, 0)
    drag_rpm: tuple = (0, 1000, 2000, 3000, 4000, 5000, 6000, 7000)
    drag_nm: tuple = (-8, -12, -16, -21, -27, -34, -42, -51)
    brake_torque_max_nm: float = 2 * 1700.0 + 1400.0   # all wheels at 100 % pedal
    launch_ratio: float = 3.462 * 4.118                # 1st gear * final drive
    driveline_efficiency: float = 0.95
    rotating_mass_factor: float = 1.05                 # wheels, shafts, engine referred to the car

    @classmethod
    def from_toml(cls, path=None):
        """The car of a plant parameter file (default: the shipped Golf Mk5 GTI DSG)."""
        p = Path(path) if path is not None else DEFAULT_PARAMS
        with open(p, "rb") as f:
            d = tomllib.load(f)
        try:
            e, g, v, t = d["engine"], d["gearbox"], d["vehicle"], d["tyre"]
            return cls(
                mass_kg=float(v["mass_kg"]),
                wheel_radius_m=float(t["radius_m"]),
                rolling_resistance=float(t["rolling_resistance"]),
                drag_area_m2=float(v["drag_coefficient"]) * float(v["frontal_area_m2"]),
                full_load_rpm=tuple(e["full_load"]["speed_rpm"]),
                full_load_nm=tuple(e["full_load"]["torque_nm"]),
                drag_rpm=tuple(e["drag"]["speed_rpm"]),
                drag_nm=tuple(e["drag"]["torque_nm"]),
                brake_torque_max_nm=2 * float(d["front_wheel"]["brake_torque_max_nm"])
                + float(d["rear_wheels"]["brake_torque_max_nm"]),
                launch_ratio=float(g["ratio"][0]) * float(g["final_drive"][0]),
            )
        except KeyError as exc:
            raise ValueError(f"{p}: missing parameter {exc} for the driver's car data") from None

    def resistance_n(self, speed_mps):
        """Rolling and air resistance on a level road."""
        roll = self.rolling_resistance * self.mass_kg * G_MPS2 if speed_mps > 0.05 else 0.0
        return roll + 0.5 * AIR_DENSITY_KG_M3 * self.drag_area_m2 * speed_mps * speed_mps


class SpeedTrackingDriver:
    """A PI driver following a speed trace.

    The needed tractive force is feed-forward (the trace's acceleration at
    ``lookahead_s`` ahead, which covers the engine's torque build-up, times the
    car's mass, plus road resistance) plus ``kp`` [N per km/h] times the present
    speed error and ``ki`` [N per km/h s] times its integral. A positive force becomes accelerator pedal through the engine's
    torque range at the present overall ratio (engine speed / wheel speed);
    a negative force below the engine's drag becomes brake pedal. The integral
    stops growing while a pedal is saturated (anti-windup) and is limited to
    ``integral_limit_n``. At a trace speed of 0 with the car nearly stopped, the
    brake is held at ``hold_brake_pct``.
    """

    def __init__(self, trace_t_s, trace_kmh, kp=400.0, ki=150.0, lookahead_s=0.3,
                 car=None, integral_limit_n=3000.0, hold_brake_pct=30.0,
                 pedal_rate_pct_s=None):
        t = np.asarray(trace_t_s, dtype=float)
        v = np.asarray(trace_kmh, dtype=float)
        if t.ndim != 1 or t.shape != v.shape or len(t) < 2:
            raise ValueError("speed trace: times and speeds must be 1-D arrays of the same length >= 2")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
            raise ValueError("speed trace: values must be finite numbers")
        if not np.all(np.diff(t) > 0):
            raise ValueError("speed trace: times must be strictly increasing")
        if np.any(v < 0):
            raise ValueError("speed trace: speeds must be >= 0 km/h")
        for name, x in (("kp", kp), ("ki", ki), ("lookahead_s", lookahead_s),
                        ("integral_limit_n", integral_limit_n), ("hold_brake_pct", hold_brake_pct)):
            if not (math.isfinite(x) and x >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {x}")
        self.trace_t_s, self.trace_kmh = t, v
        # trace acceleration, central differences, m/s2
        self.trace_accel_mps2 = np.gradient(v / 3.6, t)
        self.kp, self.ki = float(kp), float(ki)
        self.lookahead_s = float(lookahead_s)
        self.car = car if car is not None else CarData.from_toml()
        self.integral_limit_n = float(integral_limit_n)
        self.hold_brake_pct = float(hold_brake_pct)
        self.reset()

    @property
    def duration_s(self):
        return float(self.trace_t_s[-1])

    def reset(self):
        self._integral = 0.0      # integral of the speed error, km/h s
        self._t_last = None

    def target_kmh(self, t_s):
        return float(np.interp(t_s, self.trace_t_s, self.trace_kmh))

    def _engine_torque(self, rpm):
        c = self.car
        return (float(np.interp(rpm, c.full_load_rpm, c.full_load_nm)),
                float(np.interp(rpm, c.drag_rpm, c.drag_nm)))

    def __call__(self, t_s, outputs):
        c = self.car
        t = float(t_s)
        dt = 0.0 if self._t_last is None else max(0.0, t - self._t_last)
        self._t_last = t
        v_kmh = float(outputs["vehicle_speed_kmh"])
        v_mps = v_kmh / 3.6
        ref_now = self.target_kmh(t)
        t_ahead = t + self.lookahead_s
        ref_ahead = self.target_kmh(t_ahead)
        a_ref = float(np.interp(t_ahead, self.trace_t_s, self.trace_accel_mps2))
        err = ref_now - v_kmh

        # standing still on a stopped trace: hold the brake, forget the integral
        if ref_now < 0.1 and ref_ahead < 0.1 and v_kmh < 2.0:
            self._integral = 0.0
            return 0.0, self.hold_brake_pct

        force_ff = c.rotating_mass_factor * c.mass_kg * a_ref + c.resistance_n(max(ref_ahead, 0.0) / 3.6)
        force = force_ff + self.kp * err + self.ki * self._integral

        # present overall ratio and engine torque range
        wheel_rad_s = v_mps / c.wheel_radius_m
        engine_rpm = float(outputs["engine_speed_rpm"]) if "engine_speed_rpm" in _keys(outputs) else 0.0
        ratio = engine_rpm * math.pi / 30.0 / wheel_rad_s if wheel_rad_s > 0.5 else c.launch_ratio
        if not (2.0 <= ratio <= 1.5 * c.launch_ratio):
            ratio = c.launch_ratio
        full_nm, drag_nm = self._engine_torque(max(engine_rpm, 1500.0))
        k = ratio * c.driveline_efficiency / c.wheel_radius_m     # wheel force per engine N m
        force_drag = drag_nm * k                                  # < 0: force at pedal 0
        force_full = full_nm * k
        brake_force_max = c.brake_torque_max_nm / c.wheel_radius_m

        accel = brake = 0.0
        if force >= 0.0:
            accel = 100.0 * (force - force_drag) / max(force_full - force_drag, 1.0)
        elif force > force_drag:
            accel = 100.0 * (force - force_drag) / max(force_full - force_drag, 1.0)
        else:
            brake = 100.0 * (force_drag - force) / brake_force_max
        saturated_up = accel >= 100.0 and err > 0
        saturated_down = brake >= 100.0 and err < 0
        accel = min(max(accel, 0.0), 100.0)
        brake = min(max(brake, 0.0), 100.0)

        if self.ki > 0 and not (saturated_up or saturated_down):
            lim = self.integral_limit_n / self.ki
            self._integral = min(max(self._integral + err * dt, -lim), lim)
        return accel, brake


def _keys(outputs):
    try:
        return outputs.keys()
    except AttributeError:
        names = getattr(getattr(outputs, "dtype", None), "names", None)
        return names or ()
