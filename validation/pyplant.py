"""The plant's step in plain Python: the speed reference for the C core.

Every function here mirrors one function of plant/csrc, in the same order of
operations, so that a reader can compare them side by side and so that the
two agree to rounding (tests/test_pyplant.py runs both from the same start):

    C file           Python
    dct_util.h       clamp, sign, smooth_sign, gauss, interp1, fade
    friction.c       friction_eval, friction_advance
    engine.c         curve_eval, bsfc_eval, engine_init/_output/_advance
    clutch.c         clutch_output, clutch_advance
    piston.c         piston_eval
    valve.c          orifice_flow, pressure_map_eval, valve_init/_output/_advance
    hydraulics.c     chamber_volume, chamber_prepare, chamber_pressure,
                     hydraulics_init/_output/_advance
    synchronizer.c   sync_cone_torque, sync_init/_output/_advance
    gearbox.c        gearbox_prepare, gearbox_output, gearbox_advance
    driveline.c      driveline_output, driveline_advance (and the powertrain roll)
    wheel.c          _park_locked, _wheel_capacity, wheel_output, wheel_advance
    tyre.c           magic_formula, magic_formula_peak_slip, tyre_output, tyre_advance
    vehicle.c        vehicle_tyre_loads, vehicle_output, vehicle_advance
    thermal.c        walther_viscosity, thermal_effects, thermal_output, thermal_advance
    plant.c          accessory_torque, pump_torque, pack_closed_pressure_pa,
                     PyPlant: evaluate, advance, write_outputs, apply_inputs, step

Parameters are the dict of ``plant.params.load_params`` (the layout of
``dct_params``), read as attributes; the state is kept in small objects shaped
like the C state structs, and ``PyPlant.state`` flattens them into the order
of ``dct_state`` (``plant.model.STATE_NAMES``). Scalars are Python floats and
``math``: the straightforward way to write this model in Python, which is
what the C core is compared against (``bench_step``).

Not mirrored: the physical faults (faults.c; the Python plant is the healthy
car) and the C step's flush of subnormal results to zero (dct_util.h), which
moves only magnitudes below about 1e-307.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np

PI = math.pi
RPM_PER_RAD_S = 30.0 / PI
RAD_S_PER_RPM = PI / 30.0
PA_PER_BAR = 1.0e5

SYNC_DISENGAGED = 0.0
SYNC_SYNCHRONIZING = 1.0
SYNC_ENGAGED = 2.0
N_GEARS = 7
N_SLEEVES = 4
GEAR_R = 6


class PyPlantError(RuntimeError):
    """A non-finite input or state (one-line message, like plant.model.PlantError)."""


# --------------------------------------------------------------------------
# dct_util.h
# --------------------------------------------------------------------------

def clamp(x, lo, hi):
    return lo if x < lo else (hi if x > hi else x)


def sign(x):
    return float((x > 0.0) - (x < 0.0))


def smooth_sign(x, width):
    a = x / width
    if a > 20.0:
        return 1.0
    if a < -20.0:
        return -1.0
    e = math.exp(-2.0 * abs(a))              # tanh from one exp, as dct_util.h computes it
    t = (1.0 - e) / (1.0 + e)
    return -t if a < 0.0 else t


def gauss(x):
    q = x * x
    return 0.0 if q > 40.0 else math.exp(-q)


def interp1(x, y, n, xq):
    if n <= 0:
        return 0.0
    if xq <= x[0]:
        return y[0]
    if xq >= x[n - 1]:
        return y[n - 1]
    i = 1
    while i < n - 1 and xq > x[i]:
        i += 1
    return y[i - 1] + (xq - x[i - 1]) / (x[i] - x[i - 1]) * (y[i] - y[i - 1])


def fade(x, width):
    a = abs(x) / width
    if a >= 1.0:
        return 0.0
    return 0.5 * (1.0 + math.cos(PI * a))


class _Struct:
    """A C struct of doubles: fields in C order, flattened by ``values()``."""

    __slots__ = ()

    def __init__(self, **values):
        for name in self.__slots__:
            setattr(self, name, values.get(name, 0.0))

    def values(self):
        return [getattr(self, name) for name in self.__slots__]

    def load(self, values):
        for name, v in zip(self.__slots__, values):
            setattr(self, name, float(v))

    def copy(self):
        other = type(self)()
        other.load(self.values())
        return other


# --------------------------------------------------------------------------
# friction.c: reset integrator with stick-slip
# --------------------------------------------------------------------------

class FrictionOutput(_Struct):
    __slots__ = ("torque_nm", "twist_rate_rad_s", "sliding")


def friction_eval(p, twist_rad, slip_rad_s, cap_nm):
    out = FrictionOutput()
    cap = cap_nm if cap_nm > 0.0 else 0.0
    limit = cap / p.stiffness_nm_per_rad
    sliding = (twist_rad >= limit and slip_rad_s > 0.0) or (twist_rad <= -limit and slip_rad_s < 0.0)
    if sliding:
        out.torque_nm = cap if slip_rad_s > 0.0 else -cap
        out.twist_rate_rad_s = 0.0
        out.sliding = 1.0
    else:
        t = p.stiffness_nm_per_rad * twist_rad + p.damping_nms_per_rad * slip_rad_s
        out.torque_nm = clamp(t, -cap, cap)
        out.twist_rate_rad_s = slip_rad_s
        out.sliding = 0.0
    return out


def friction_advance(p, twist_rad, out, cap_nm, h):
    limit = (cap_nm if cap_nm > 0.0 else 0.0) / p.stiffness_nm_per_rad
    return clamp(twist_rad + h * out.twist_rate_rad_s, -limit, limit)


# --------------------------------------------------------------------------
# engine.c
# --------------------------------------------------------------------------

class EngineState(_Struct):
    __slots__ = ("speed_rad_s", "combustion_torque_nm", "idle_integral_nm", "fuel_g", "running",
                 "spark_cut_nm")


class EngineInput(_Struct):
    __slots__ = ("accel_pedal_pct", "torque_request_nm", "torque_request_active", "engine_on",
                 "load_torque_nm", "drag_excess", "idle_rise_rpm", "fuel_enrichment",
                 "accessory_torque_nm")


class EngineOutput(_Struct):
    __slots__ = ("torque_nm", "demand_nm", "air_demand_nm", "combustion_torque_nm", "drag_nm",
                 "fuel_rate_g_s", "burnt_fuel_rate_g_s", "accessory_torque_nm", "speed_deriv_rad_s2")


def curve_eval(c, speed_rpm):
    return interp1(c.speed_rpm, c.torque_nm, c.n, speed_rpm)


def _axis_locate(axis, n, x):
    if n < 2 or x <= axis[0]:
        return 0, 0.0
    if x >= axis[n - 1]:
        return n - 2, 1.0
    k = 0
    while k < n - 2 and x > axis[k + 1]:
        k += 1
    return k, (x - axis[k]) / (axis[k + 1] - axis[k])


def bsfc_eval(m, speed_rpm, torque_nm):
    if m.n_speed_rpm < 1 or m.n_torque_nm < 1:
        return 0.0
    table = m.bsfc_g_per_kwh
    if m.n_speed_rpm < 2 or m.n_torque_nm < 2:
        return table[0][0]
    i, fx = _axis_locate(m.speed_rpm, m.n_speed_rpm, speed_rpm)
    j, fy = _axis_locate(m.torque_nm, m.n_torque_nm, torque_nm)
    a = table[j][i] + fx * (table[j][i + 1] - table[j][i])
    b = table[j + 1][i] + fx * (table[j + 1][i + 1] - table[j + 1][i])
    return a + fy * (b - a)


def _engine_drag(p, speed_rad_s, factor=1.0):
    n = speed_rad_s * RPM_PER_RAD_S
    return factor * curve_eval(p.drag, abs(n)) * smooth_sign(speed_rad_s, p.drag_smoothing_rad_s)


def engine_init(p, s, speed_rad_s, running):
    s.speed_rad_s = speed_rad_s
    s.fuel_g = 0.0
    s.running = 1.0 if running else 0.0
    s.spark_cut_nm = 0.0
    hold = -_engine_drag(p, speed_rad_s) if running else 0.0
    s.combustion_torque_nm = hold
    idle_hold = -_engine_drag(p, p.idle_speed_rpm * RAD_S_PER_RPM)
    s.idle_integral_nm = clamp(idle_hold, 0.0, p.idle_torque_max_nm) if running else 0.0


def engine_output(p, s, inp):
    out = EngineOutput()
    w = s.speed_rad_s
    n = w * RPM_PER_RAD_S
    factor = 1.0 + inp.drag_excess
    drag = _engine_drag(p, w, factor)
    acc = inp.accessory_torque_nm * smooth_sign(w, p.drag_smoothing_rad_s)
    full = curve_eval(p.full_load, n)
    # full load is the rated brake torque (its drag in it); the accessories come off it
    drag_need = -factor * curve_eval(p.drag, abs(n))
    rng = full + drag_need
    if rng < 0.0:
        rng = 0.0
    demand = 0.0
    air = 0.0
    fired = s.running > 0.5 and inp.engine_on > 0.5
    if fired:
        err = p.idle_speed_rpm + inp.idle_rise_rpm - n
        gov = clamp(p.idle_kp_nm_per_rpm * err + s.idle_integral_nm, 0.0, p.idle_torque_max_nm)
        driver = clamp(0.01 * inp.accel_pedal_pct * rng + gov, 0.0, rng)
        demand = air = driver
        if inp.torque_request_active > 0.5:
            # a request is a brake torque at the clutch: accessories covered
            req = inp.torque_request_nm + drag_need + inp.accessory_torque_nm
            demand = clamp(req if req > gov else gov, 0.0, rng)
            # the air path keeps the driver's torque while spark retard can cut the rest
            keep = demand / (1.0 - p.spark_cut_max_share)
            air = driver if driver < keep else keep
            if demand > air:
                air = demand
        if n > p.rev_limit_rpm:
            demand = air = 0.0  # fuel cut
    out.demand_nm = demand
    out.air_demand_nm = air
    out.drag_nm = drag
    comb = s.combustion_torque_nm - s.spark_cut_nm
    out.combustion_torque_nm = comb
    out.torque_nm = comb + drag - acc
    out.accessory_torque_nm = acc
    fuel = 0.0
    if fired and demand > 0.0 and w > 0.0:
        t = out.torque_nm + acc + s.spark_cut_nm  # the retarded spark burns the air path's fuel
        if t < p.bsfc.torque_nm[0]:
            t = p.bsfc.torque_nm[0]
        fuel = bsfc_eval(p.bsfc, n, t) * t * w / 3.6e6
    out.burnt_fuel_rate_g_s = fuel
    out.fuel_rate_g_s = fuel * (1.0 + inp.fuel_enrichment)
    out.speed_deriv_rad_s2 = (out.torque_nm - inp.load_torque_nm) / p.inertia_kgm2
    return out


def engine_advance(p, s, inp, out, h):
    w = s.speed_rad_s
    n = w * RPM_PER_RAD_S
    comb = s.combustion_torque_nm
    target = out.air_demand_nm
    if target > comb:
        tau = p.tau_rise_s
        if p.turbocharged > 0.5 and comb > p.na_torque_fraction * curve_eval(p.full_load, n):
            tau = p.tau_boost_s
    else:
        tau = p.tau_fall_s
    s.combustion_torque_nm = comb + (h / tau) * (target - comb)
    # spark retard: cuts the request's difference (up to its share), in and out within tau_fall
    cut = 0.0
    if inp.torque_request_active > 0.5:
        cut = clamp(s.combustion_torque_nm - out.demand_nm, 0.0,
                    p.spark_cut_max_share * s.combustion_torque_nm)
    s.spark_cut_nm += (h / p.tau_fall_s) * (cut - s.spark_cut_nm)
    s.speed_rad_s = w + h * out.speed_deriv_rad_s2
    s.fuel_g += h * out.fuel_rate_g_s
    if s.running > 0.5 and inp.engine_on > 0.5:
        err = p.idle_speed_rpm + inp.idle_rise_rpm - n
        i_new = s.idle_integral_nm + h * p.idle_ki_nm_per_rpm_s * err
        s.idle_integral_nm = clamp(i_new, 0.0, p.idle_torque_max_nm)
    if s.running > 0.5 and n < p.stall_speed_rpm:
        s.running = 0.0
        s.idle_integral_nm = 0.0


# --------------------------------------------------------------------------
# piston.c and clutch.c
# --------------------------------------------------------------------------

class PistonOutput(_Struct):
    __slots__ = ("position_m", "clamp_force_n", "compliance_m3_per_pa")


def piston_eval(p, pressure_pa):
    out = PistonOutput()
    a = p.piston_area_m2
    f = pressure_pa * a - p.return_spring_n
    gap = p.pack_gap_mm * 1e-3
    kr, kp = p.return_spring_n_per_m, p.pack_stiffness_n_per_m
    if f <= 0.0:
        out.position_m = 0.0
        out.clamp_force_n = 0.0
        out.compliance_m3_per_pa = 0.0
    elif f <= kr * gap:
        out.position_m = f / kr
        out.clamp_force_n = 0.0
        out.compliance_m3_per_pa = a * a / kr
    else:
        x = (f + kp * gap) / (kr + kp)
        out.position_m = x
        out.clamp_force_n = kp * (x - gap)
        out.compliance_m3_per_pa = a * a / (kr + kp)
    return out


class ClutchState(_Struct):
    __slots__ = ("twist_rad",)


class ClutchInput(_Struct):
    __slots__ = ("clamp_force_n", "drive_speed_rad_s", "driven_speed_rad_s", "drag_excess", "mu_excess")


class ClutchOutput(_Struct):
    __slots__ = ("torque_nm", "clamp_force_n", "capacity_nm", "slide_capacity_nm", "slip_rad_s",
                 "heat_w", "drag_torque_nm", "mu_kinetic", "friction")


def _clutch_mu(p, slip_rad_s):
    return p.mu_kinetic + (p.mu_static - p.mu_kinetic) * gauss(slip_rad_s / p.stribeck_speed_rad_s)


def clutch_output(p, s, inp):
    out = ClutchOutput()
    slip = inp.drive_speed_rad_s - inp.driven_speed_rad_s
    force = inp.clamp_force_n if inp.clamp_force_n > 0.0 else 0.0
    lever = p.surfaces * p.radius_m * force
    mu_factor = 1.0 + inp.mu_excess
    cap = lever * (_clutch_mu(p, slip) * mu_factor)
    out.friction = friction_eval(p.friction, s.twist_rad, slip, cap)
    out.clamp_force_n = force
    out.capacity_nm = lever * (p.mu_static * mu_factor)
    out.slide_capacity_nm = cap
    out.slip_rad_s = slip
    drag = p.drag_nms_per_rad * (1.0 + inp.drag_excess) * slip
    out.drag_torque_nm = drag
    out.mu_kinetic = p.mu_kinetic * mu_factor
    out.torque_nm = out.friction.torque_nm + drag
    # sticking: what the element takes less what its spring stores
    fr = (out.friction.torque_nm * slip if out.friction.sliding > 0.5
          else (out.friction.torque_nm - p.friction.stiffness_nm_per_rad * s.twist_rad) * slip)
    out.heat_w = fr + drag * slip
    return out


def clutch_advance(p, s, out, h):
    s.twist_rad = friction_advance(p.friction, s.twist_rad, out.friction, out.slide_capacity_nm, h)


# --------------------------------------------------------------------------
# valve.c
# --------------------------------------------------------------------------

P_ATM = 1.0e5
P_MIN = -0.9e5


class ValveState(_Struct):
    __slots__ = ("solenoid_force_n", "spool_position_m", "spool_velocity_m_s", "friction_velocity_m_s")


class ValveOutput(_Struct):
    __slots__ = ("flow_m3_s", "supply_flow_m3_s", "tank_flow_m3_s", "spool_accel_m_s2",
                 "solenoid_force_rate_n_s", "friction_accel_m_s2")


def orifice_flow(oil, cd_max, transition_reynolds, width_m, opening_m, p1_pa, p2_pa):
    if opening_m <= 0.0:
        return 0.0
    dp = p1_pa - p2_pa
    area = width_m * opening_m
    v_ideal = math.sqrt(2.0 * abs(dp) / oil.density_kg_m3)
    re = 2.0 * opening_m * v_ideal / oil.viscosity_m2_s
    cd = cd_max * smooth_sign(2.0 * re, transition_reynolds)
    pm = 0.5 * (p1_pa + p2_pa)
    q = cd * area * v_ideal * (1.0 + pm / oil.bulk_modulus_pa)
    return q if dp >= 0.0 else -q


def pressure_map_eval(m, current_a):
    return interp1(m.current_a, m.pressure_bar, m.n, current_a)


def valve_init(p, s):
    s.solenoid_force_n = 0.0
    s.spool_position_m = -p.spool_travel_mm * 1e-3
    s.spool_velocity_m_s = 0.0
    s.friction_velocity_m_s = 0.0


def valve_output(p, oil, s, current_a, supply_pa, control_pa):
    out = ValveOutput()
    ds, dr = p.spool_diameter_mm * 1e-3, p.rod_diameter_mm * 1e-3
    a_fb = 0.25 * PI * (ds * ds - dr * dr)
    x, v, vf = s.spool_position_m, s.spool_velocity_m_s, s.friction_velocity_m_s
    travel, lap = p.spool_travel_mm * 1e-3, p.overlap_mm * 1e-3
    pc = control_pa
    f = s.solenoid_force_n - pc * a_fb - (p.spring_preload_n + p.spring_n_per_m * x)
    f -= p.viscous_friction_ns_per_m * vf + p.coulomb_friction_n * smooth_sign(vf, p.friction_speed_m_s)
    if x > travel:
        f -= p.stop_stiffness_n_per_m * (x - travel) + p.stop_damping_ns_per_m * v
    elif x < -travel:
        f += p.stop_stiffness_n_per_m * (-travel - x) - p.stop_damping_ns_per_m * v
    out.spool_accel_m_s2 = f / p.spool_mass_kg
    out.friction_accel_m_s2 = (v - vf) / p.friction_tau_s
    out.solenoid_force_rate_n_s = ((p.solenoid_gain_n_per_a * abs(current_a) - s.solenoid_force_n)
                                   / p.solenoid_tau_s)
    w = p.edge_width_mm * 1e-3
    q_in = orifice_flow(oil, p.cd_max, p.transition_reynolds, w, x - lap, supply_pa, pc)
    q_out = orifice_flow(oil, p.cd_max, p.transition_reynolds, w, -x - lap, pc, 0.0)
    q_in += p.leakage_m3_per_s_per_pa * (supply_pa - pc)
    q_out += p.leakage_m3_per_s_per_pa * pc
    out.supply_flow_m3_s = q_in
    out.tank_flow_m3_s = q_out
    out.flow_m3_s = q_in - q_out + v * a_fb * (1.0 + pc / oil.bulk_modulus_pa)
    return out


def valve_advance(p, s, out, h):
    s.spool_position_m += h * s.spool_velocity_m_s
    s.spool_velocity_m_s += h * out.spool_accel_m_s2
    s.friction_velocity_m_s += h * out.friction_accel_m_s2
    s.solenoid_force_n += h * out.solenoid_force_rate_n_s


# --------------------------------------------------------------------------
# hydraulics.c: supply, chambers, the two valves
# --------------------------------------------------------------------------

class HydraulicsState:
    """line_pressure_pa, clutch_oil_m3[2], valve[2] (C order)."""

    __slots__ = ("line_pressure_pa", "clutch_oil_m3", "valve")

    def __init__(self):
        self.line_pressure_pa = 0.0
        self.clutch_oil_m3 = [0.0, 0.0]
        self.valve = [ValveState(), ValveState()]

    def values(self):
        return [self.line_pressure_pa, *self.clutch_oil_m3, *self.valve[0].values(), *self.valve[1].values()]

    def load(self, v):
        self.line_pressure_pa = float(v[0])
        self.clutch_oil_m3 = [float(v[1]), float(v[2])]
        self.valve[0].load(v[3:7])
        self.valve[1].load(v[7:11])


class HydraulicsOutput(_Struct):
    __slots__ = ("clamp_force_n", "piston_position_m", "clutch_pressure_pa")


def chamber_volume(oil, clutch, chamber_m3, pressure_pa):
    a = oil.air_fraction
    p = pressure_pa if pressure_pa > P_MIN else P_MIN
    po = piston_eval(clutch, p)
    return (chamber_m3 * ((1.0 - a) * p / oil.bulk_modulus_pa + a * (1.0 - P_ATM / (p + P_ATM)))
            + clutch.piston_area_m2 * po.position_m)


def _piece_pressure(k, av, c0, v):
    b = k * P_ATM + av + c0 - v
    c = (c0 - v) * P_ATM
    disc = b * b - 4.0 * k * c
    root = math.sqrt(disc if disc > 0.0 else 0.0)
    return (2.0 * -c) / (b + root) if b > 0.0 else (-b + root) / (2.0 * k)


def chamber_prepare(oil, clutch, chamber_m3):
    d = SimpleNamespace()
    a, area = oil.air_fraction, clutch.piston_area_m2
    gap = clutch.pack_gap_mm * 1e-3
    kr = clutch.return_spring_n_per_m
    kt = kr + clutch.pack_stiffness_n_per_m
    p_kiss = clutch.return_spring_n / area
    p_closed = (clutch.return_spring_n + kr * gap) / area
    d.min_m3 = chamber_volume(oil, clutch, chamber_m3, P_MIN)
    d.kiss_m3 = chamber_volume(oil, clutch, chamber_m3, p_kiss)
    d.closed_m3 = chamber_volume(oil, clutch, chamber_m3, p_closed)
    d.oil_m3_per_pa = chamber_m3 * (1.0 - a) / oil.bulk_modulus_pa
    d.air_m3 = a * chamber_m3
    d.stroke_m3_per_pa = area * area / kr
    d.stroke_m3 = -d.stroke_m3_per_pa * p_kiss
    d.clamped_m3_per_pa = area * area / kt
    d.clamped_m3 = area * (clutch.pack_stiffness_n_per_m * gap - clutch.return_spring_n) / kt
    return d


def chamber_pressure(d, volume_m3):
    if volume_m3 <= d.min_m3:
        return P_MIN
    if volume_m3 <= d.kiss_m3:
        return _piece_pressure(d.oil_m3_per_pa, d.air_m3, 0.0, volume_m3)
    if volume_m3 <= d.closed_m3:
        return _piece_pressure(d.oil_m3_per_pa + d.stroke_m3_per_pa, d.air_m3, d.stroke_m3, volume_m3)
    return _piece_pressure(d.oil_m3_per_pa + d.clamped_m3_per_pa, d.air_m3, d.clamped_m3, volume_m3)


def hydraulics_prepare(p, clutch):
    return [chamber_prepare(p.oil, clutch[k], p.chamber_volume_cm3[k] * 1e-6) for k in range(2)]


def hydraulics_init(p, s):
    s.line_pressure_pa = pressure_map_eval(p.supply.line, 0.0) * PA_PER_BAR
    for k in range(2):
        s.clutch_oil_m3[k] = 0.0
        valve_init(p.valve, s.valve[k])


def hydraulics_output(chambers, clutch, s):
    out = HydraulicsOutput(clamp_force_n=[0.0, 0.0], piston_position_m=[0.0, 0.0],
                           clutch_pressure_pa=[0.0, 0.0])
    for k in range(2):
        pk = chamber_pressure(chambers[k], s.clutch_oil_m3[k])
        po = piston_eval(clutch[k], pk)
        out.clamp_force_n[k] = po.clamp_force_n
        out.piston_position_m[k] = po.position_m
        out.clutch_pressure_pa[k] = pk
    return out


def hydraulics_advance(p, chambers, s, current_a, line_current_a, h, oil_viscosity_m2_s=0.0):
    n = int(p.substeps)
    hh = h / n
    line_target = pressure_map_eval(p.supply.line, line_current_a) * PA_PER_BAR
    oil = p.oil
    if oil_viscosity_m2_s > 0.0:
        oil = SimpleNamespace(**vars(p.oil))
        oil.viscosity_m2_s = oil_viscosity_m2_s
    for _ in range(n):
        vo = [None, None]
        for k in range(2):
            pk = chamber_pressure(chambers[k], s.clutch_oil_m3[k])
            vo[k] = valve_output(p.valve, oil, s.valve[k], current_a[k], s.line_pressure_pa, pk)
        for k in range(2):
            valve_advance(p.valve, s.valve[k], vo[k], hh)
            s.clutch_oil_m3[k] += hh * vo[k].flow_m3_s
        s.line_pressure_pa += hh * (line_target - s.line_pressure_pa) / p.supply.tau_s


# --------------------------------------------------------------------------
# synchronizer.c: the hybrid three-phase synchronizer
# --------------------------------------------------------------------------

DETENT_TRAVEL_M = 0.0002


class SyncState(_Struct):
    __slots__ = ("position_m", "velocity_m_s", "phase", "side", "twist_rad", "clashes")


class SyncInput(_Struct):
    __slots__ = ("fork_force_n", "slip_pos_rad_s", "slip_neg_rad_s", "has_neg", "gear_inertia_pos_kgm2",
                 "gear_inertia_neg_kgm2")


class SyncOutput(_Struct):
    __slots__ = ("torque_nm", "side", "slip_rad_s", "cone_torque_nm")


def sync_cone_torque(p, force_n):
    return p.cone_mu * p.cone_radius_m / math.sin(p.cone_half_angle_deg * (PI / 180.0)) * force_n


def sync_init(p, s, side_engaged):
    s.velocity_m_s = 0.0
    s.twist_rad = 0.0
    s.clashes = 0.0
    if side_engaged != 0:
        side = 1.0 if side_engaged > 0 else -1.0
        s.phase = SYNC_ENGAGED
        s.side = side
        s.position_m = side * p.engaged_travel_mm * 1e-3
    else:
        s.phase = SYNC_DISENGAGED
        s.side = 0.0
        s.position_m = 0.0


def sync_output(p, s, inp):
    out = SyncOutput()
    side = s.side
    slip = inp.slip_pos_rad_s if side > 0.0 else (inp.slip_neg_rad_s if side < 0.0 else 0.0)
    out.side = side
    out.slip_rad_s = slip
    out.cone_torque_nm = 0.0
    if s.phase == SYNC_SYNCHRONIZING:
        f = inp.fork_force_n * side
        ts = sync_cone_torque(p, f if f > 0.0 else 0.0)
        out.cone_torque_nm = ts
        out.torque_nm = ts * math.tanh(2.0 * slip / p.tanh_speed_rad_s)
    elif s.phase == SYNC_ENGAGED:
        out.torque_nm = p.stiffness_nm_per_rad * s.twist_rad + p.damping_nms_per_rad * slip
    else:
        out.torque_nm = 0.0
    return out


def _sleeve_velocity(p, m, v, f, fc, h):
    v1 = v + h * (f - p.sleeve_damping_ns_per_m * v) / m
    dv = h * fc / m
    if abs(v1) <= dv:
        return 0.0
    return v1 - sign(v1) * dv


SYNC_SETTLED_SHARE = 0.1


def _cone_holds_load(p, s, inp, out, h):
    """synchronizer.c cone_holds_load: a settled slip whose torque the chamfers can index against."""
    ts = out.cone_torque_nm
    t = out.torque_nm
    t_prev = s.twist_rad * p.stiffness_nm_per_rad
    if not (ts > 0.0) or t_prev == 0.0 or not (abs(t_prev) < ts):
        return False
    index = abs(inp.fork_force_n) * p.dog_radius_m / math.tan(p.ring_chamfer_angle_deg * (PI / 180.0))
    if not (abs(t) < index):
        return False
    slip_prev = 0.5 * p.tanh_speed_rad_s * math.atanh(t_prev / ts)
    j = inp.gear_inertia_pos_kgm2 if s.side > 0.0 else inp.gear_inertia_neg_kgm2
    return abs(j * (out.slip_rad_s - slip_prev) / h) <= SYNC_SETTLED_SHARE * abs(t)


def _engage(p, s, out):
    if abs(out.slip_rad_s) > p.clash_speed_rad_s:
        s.clashes += 1.0
    s.phase = SYNC_ENGAGED
    s.twist_rad = out.torque_nm / p.stiffness_nm_per_rad


def sync_advance(p, s, inp, out, h):
    f = inp.fork_force_n
    cone = p.cone_travel_mm * 1e-3
    full = p.engaged_travel_mm * 1e-3
    x, v = s.position_m, s.velocity_m_s

    if s.phase == SYNC_SYNCHRONIZING:
        side = s.side
        if f * side <= 0.0:
            s.phase = SYNC_DISENGAGED
            s.side = 0.0
            s.twist_rad = 0.0
        elif (abs(out.slip_rad_s) <= p.lock_speed_rad_s or abs(f) > p.blocker_force_max_n
              or _cone_holds_load(p, s, inp, out, h)):
            _engage(p, s, out)
        else:
            s.twist_rad = out.torque_nm / p.stiffness_nm_per_rad
        return

    if s.phase == SYNC_ENGAGED:
        side = s.side
        s.twist_rad += h * out.slip_rad_s
        fdog = p.dog_friction_mu * abs(out.torque_nm) / p.dog_radius_m
        m = p.sleeve_mass_kg
        # ring turn-back: pushing in and not yet past the blocker ring
        pushing_in = v * side > 0.0 or (v == 0.0 and f * side > 0.0)
        if x * side < cone + p.ring_pass_travel_mm * 1e-3 and pushing_in:
            j = inp.gear_inertia_pos_kgm2 if side > 0.0 else inp.gear_inertia_neg_kgm2
            tb = math.tan(p.ring_chamfer_angle_deg * (PI / 180.0)) / p.dog_radius_m
            m += j * tb * tb
        v1 = _sleeve_velocity(p, m, v, f, fdog, h)
        x1 = x + h * v
        if x1 * side >= full:
            x1 = side * full
            if v1 * side > 0.0:
                v1 = 0.0
        s.position_m = x1
        s.velocity_m_s = v1
        if x1 * side < cone:
            s.phase = SYNC_DISENGAGED
            s.side = 0.0
            s.twist_rad = 0.0
        return

    detent = -clamp(x / DETENT_TRAVEL_M, -1.0, 1.0) * p.detent_force_n
    v1 = _sleeve_velocity(p, p.sleeve_mass_kg, v, f + detent, 0.0, h)
    x1 = x + h * v
    if not (inp.has_neg > 0.5) and x1 < 0.0:
        x1 = 0.0
        if v1 < 0.0:
            v1 = 0.0
    s.position_m = x1
    s.velocity_m_s = v1
    if abs(x1) >= cone:
        side = 1.0 if x1 > 0.0 else -1.0
        s.position_m = side * cone
        if v1 * side > 0.0:
            s.velocity_m_s = 0.0
        if f * side > 0.0:
            s.phase = SYNC_SYNCHRONIZING
            s.side = side
            s.twist_rad = 0.0


# --------------------------------------------------------------------------
# gearbox.c
# --------------------------------------------------------------------------

GEAR_INPUT = (0, 1, 0, 1, 0, 1, 0)
GEAR_OUTPUT = (0, 0, 0, 0, 1, 1, 1)
SLEEVE_POS = (0, 1, 4, 5)
SLEEVE_NEG = (2, 3, 6, -1)
SLEEVE_OUTPUT = (0, 0, 1, 1)


def gear_input_shaft(gear):
    return GEAR_INPUT[gear] if 0 <= gear < N_GEARS else -1


def gear_output_shaft(gear):
    return GEAR_OUTPUT[gear] if 0 <= gear < N_GEARS else -1


def sleeve_gear(sleeve, side):
    if sleeve < 0 or sleeve >= N_SLEEVES or side == 0:
        return -1
    return SLEEVE_POS[sleeve] if side > 0 else SLEEVE_NEG[sleeve]


class GearboxState:
    """input_speed_rad_s[2], carrier_speed_rad_s, sync[4] (C order)."""

    __slots__ = ("input_speed_rad_s", "carrier_speed_rad_s", "sync")

    def __init__(self):
        self.input_speed_rad_s = [0.0, 0.0]
        self.carrier_speed_rad_s = 0.0
        self.sync = [SyncState() for _ in range(N_SLEEVES)]

    def values(self):
        out = [*self.input_speed_rad_s, self.carrier_speed_rad_s]
        for y in self.sync:
            out += y.values()
        return out

    def load(self, v):
        self.input_speed_rad_s = [float(v[0]), float(v[1])]
        self.carrier_speed_rad_s = float(v[2])
        n = len(SyncState.__slots__)
        for k, y in enumerate(self.sync):
            y.load(v[3 + n * k: 3 + n * (k + 1)])


class GearboxOutput(_Struct):
    __slots__ = ("gear_torque_nm", "input_torque_nm", "carrier_torque_nm", "output_speed_rad_s",
                 "power_loss_w", "input_damping_nms_per_rad", "carrier_damping_nms_per_rad", "sync", "sync_in")


def gearbox_prepare(p):
    d = SimpleNamespace()
    d.input_inertia_kgm2 = [p.input_shaft_inertia_kgm2[0], p.input_shaft_inertia_kgm2[1]]
    d.signed_ratio = [0.0] * N_GEARS
    for g in range(N_GEARS):
        d.signed_ratio[g] = -p.ratio[g] if g == GEAR_R else p.ratio[g]
        d.input_inertia_kgm2[GEAR_INPUT[g]] += p.idle_gear_inertia_kgm2[g] / (p.ratio[g] * p.ratio[g])
    d.carrier_inertia_kgm2 = p.differential_inertia_kgm2
    for o in range(2):
        d.carrier_inertia_kgm2 += p.output_shaft_inertia_kgm2[o] * (p.final_drive[o] * p.final_drive[o])
    return d


def _gear_side_inertia(p, d, g):
    return d.input_inertia_kgm2[GEAR_INPUT[g]] * (p.ratio[g] * p.ratio[g])


def _efficiency_factor(eta, power_w, scale_w):
    t = smooth_sign(power_w, scale_w)
    if t > 0.0:
        return 1.0 + (1.0 / eta - 1.0) * t
    return 1.0 + (1.0 - eta) * t


def _gear_drag(c0, c1, w, smooth):
    return c0 * smooth_sign(w, smooth) + c1 * w


def gearbox_output(p, d, s, clutch_torque_nm, fork_force_n, load_torque_nm, viscous_drag_excess=0.0,
                   clutch_damping_nms_per_rad=(0.0, 0.0)):
    out = GearboxOutput()
    visc = 1.0 + viscous_drag_excess
    w_out = [s.carrier_speed_rad_s * p.final_drive[0], s.carrier_speed_rad_s * p.final_drive[1]]
    w_gear = [s.input_speed_rad_s[GEAR_INPUT[g]] / d.signed_ratio[g] for g in range(N_GEARS)]
    gear_torque = [0.0] * N_GEARS
    out.sync_in = []
    out.sync = []
    for k in range(N_SLEEVES):
        wo = w_out[SLEEVE_OUTPUT[k]]
        si = SyncInput()
        si.fork_force_n = fork_force_n[k]
        si.slip_pos_rad_s = w_gear[SLEEVE_POS[k]] - wo
        si.has_neg = 1.0 if SLEEVE_NEG[k] >= 0 else 0.0
        si.slip_neg_rad_s = w_gear[SLEEVE_NEG[k]] - wo if SLEEVE_NEG[k] >= 0 else 0.0
        si.gear_inertia_pos_kgm2 = _gear_side_inertia(p, d, SLEEVE_POS[k])
        si.gear_inertia_neg_kgm2 = _gear_side_inertia(p, d, SLEEVE_NEG[k]) if SLEEVE_NEG[k] >= 0 else 0.0
        so = sync_output(p.sync[k], s.sync[k], si)
        out.sync_in.append(si)
        out.sync.append(so)
        g = sleeve_gear(k, int(so.side))
        if g >= 0:
            gear_torque[g] += so.torque_nm
    # a tie-up (two gears engaged on one input shaft): the tied shafts and the
    # carrier take their dampers implicitly (gearbox.c); none otherwise
    engaged = [0, 0]
    for k in range(N_SLEEVES):
        g = sleeve_gear(k, int(out.sync[k].side))
        if g >= 0 and s.sync[k].phase == SYNC_ENGAGED:
            engaged[GEAR_INPUT[g]] += 1
    c_in = [0.0, 0.0]
    c_car = 0.0
    if engaged[0] > 1 or engaged[1] > 1:
        for k in range(N_SLEEVES):
            g = sleeve_gear(k, int(out.sync[k].side))
            if g < 0 or s.sync[k].phase != SYNC_ENGAGED:
                continue
            b = p.sync[k].damping_nms_per_rad
            c_in[GEAR_INPUT[g]] += b / (p.ratio[g] * p.ratio[g])
            c_car += b * (p.final_drive[GEAR_OUTPUT[g]] * p.final_drive[GEAR_OUTPUT[g]])
        c_in = [c_in[k] + clutch_damping_nms_per_rad[k] if engaged[k] > 1 else 0.0 for k in range(2)]
    out.input_damping_nms_per_rad = c_in
    out.carrier_damping_nms_per_rad = c_car
    loss = 0.0
    t_in = [0.0, 0.0]
    for k in range(2):
        w = s.input_speed_rad_s[k]
        t = _gear_drag(p.input_drag_nm[k], p.input_drag_nms_per_rad[k] * visc, w, p.drag_smoothing_rad_s)
        loss += t * w
        t_in[k] = clutch_torque_nm[k] - t
    w = s.carrier_speed_rad_s
    t = _gear_drag(p.output_drag_nm, p.output_drag_nms_per_rad * visc, w, p.drag_smoothing_rad_s)
    loss += t * w
    t_car = -t - load_torque_nm
    for g in range(N_GEARS):
        o = GEAR_OUTPUT[g]
        tg = gear_torque[g]
        rel = w_gear[g] - w_out[o]
        tig = p.idle_gear_drag_nms_per_rad * visc * rel
        f = (_efficiency_factor(p.mesh_efficiency[g], tg * w_gear[g], p.efficiency_smoothing_w)
             if tg != 0.0 else 1.0)
        loss += tg * w_gear[g] * (f - 1.0) + tig * rel
        t_in[GEAR_INPUT[g]] -= (tg * f + tig) / d.signed_ratio[g]
        t_car += (tg + tig) * p.final_drive[o]
        gear_torque[g] = tg + tig
    out.gear_torque_nm = gear_torque
    out.input_torque_nm = t_in
    out.carrier_torque_nm = t_car
    out.output_speed_rad_s = w_out
    out.power_loss_w = loss
    return out


def gearbox_advance(p, d, s, out, h):
    # linearly implicit in a shaft's own dampers in a tie-up (gearbox.c); explicit otherwise
    for k in range(2):
        s.input_speed_rad_s[k] += h * out.input_torque_nm[k] / (d.input_inertia_kgm2[k]
                                                               + h * out.input_damping_nms_per_rad[k])
    s.carrier_speed_rad_s += h * out.carrier_torque_nm / (d.carrier_inertia_kgm2
                                                          + h * out.carrier_damping_nms_per_rad)
    for k in range(N_SLEEVES):
        sync_advance(p.sync[k], s.sync[k], out.sync_in[k], out.sync[k], h)


# --------------------------------------------------------------------------
# driveline.c: open differential and half-shafts
# --------------------------------------------------------------------------

class DrivelineState(_Struct):
    __slots__ = ("left_twist_rad", "right_twist_rad", "roll_rad", "roll_rate_rad_s")


class DrivelineOutput(_Struct):
    __slots__ = ("shaft_torque_nm", "carrier_load_nm", "left_side_speed_rad_s", "right_side_speed_rad_s",
                 "mount_torque_nm", "roll_accel_rad_s2")


def driveline_output(p, s, carrier_speed_rad_s, left_wheel_speed_rad_s, right_wheel_speed_rad_s,
                     body_pitch_rad, body_pitch_rate_rad_s):
    out = DrivelineOutput()
    kl, cl = p.left_stiffness_nm_per_rad, p.left_damping_nms_per_rad
    kr, cr = p.right_stiffness_nm_per_rad, p.right_damping_nms_per_rad
    wc = carrier_speed_rad_s + s.roll_rate_rad_s  # the carrier turns with the rolled powertrain
    d = (kr * s.right_twist_rad - kl * s.left_twist_rad + cr * (wc - right_wheel_speed_rad_s)
         - cl * (wc - left_wheel_speed_rad_s)) / (cl + cr)
    out.left_side_speed_rad_s = wc + d
    out.right_side_speed_rad_s = wc - d
    out.shaft_torque_nm = kl * s.left_twist_rad + cl * (wc + d - left_wheel_speed_rad_s)
    out.carrier_load_nm = 2.0 * out.shaft_torque_nm
    # powertrain roll on its mounts: their deflection is the roll against the body's pitch
    phi = s.roll_rad + body_pitch_rad
    over = abs(phi) - p.mount_roll_stop_rad
    stop = p.mount_roll_stop_stiffness_nm_per_rad * over if over > 0.0 else 0.0
    out.mount_torque_nm = (-p.mount_roll_stiffness_nm_per_rad * phi - (stop if phi > 0.0 else -stop)
                           - p.mount_roll_damping_nms_per_rad * (s.roll_rate_rad_s + body_pitch_rate_rad_s))
    out.roll_accel_rad_s2 = (out.mount_torque_nm - out.carrier_load_nm) / p.powertrain_roll_inertia_kgm2
    return out


def driveline_advance(s, out, left_wheel_speed_rad_s, right_wheel_speed_rad_s, h):
    s.left_twist_rad += h * (out.left_side_speed_rad_s - left_wheel_speed_rad_s)
    s.right_twist_rad += h * (out.right_side_speed_rad_s - right_wheel_speed_rad_s)
    s.roll_rad += h * s.roll_rate_rad_s
    s.roll_rate_rad_s += h * out.roll_accel_rad_s2


# --------------------------------------------------------------------------
# wheel.c: wheel with friction brake
# --------------------------------------------------------------------------

class WheelState(_Struct):
    __slots__ = ("speed_rad_s", "brake_twist_rad")


class WheelInput(_Struct):
    __slots__ = ("drive_torque_nm", "tyre_force_n", "tyre_radius_m", "rolling_moment_nm", "brake_pedal_pct",
                 "park_lock")


class WheelOutput(_Struct):
    __slots__ = ("brake_torque_nm", "body_torque_nm", "speed_deriv_rad_s2", "capacity_nm", "park_locked",
                 "brake")


def _park_locked(p, s, inp):
    """Lever in P, a lock on this position, and the wheel slow enough for the pawl."""
    return (inp.park_lock > 0.5 and p.park_lock_torque_nm > 0.0
            and abs(s.speed_rad_s) * inp.tyre_radius_m < p.park_lock_max_speed_kmh / 3.6)


def _wheel_capacity(p, s, inp):
    cap = 0.01 * inp.brake_pedal_pct * p.brake_torque_max_nm
    if _park_locked(p, s, inp):
        cap += p.park_lock_torque_nm
    return cap


def wheel_output(p, s, inp):
    out = WheelOutput()
    cap = _wheel_capacity(p, s, inp)
    out.capacity_nm = cap
    out.park_locked = 1.0 if _park_locked(p, s, inp) else 0.0
    out.brake = friction_eval(p.brake, s.brake_twist_rad, s.speed_rad_s, cap)
    out.brake_torque_nm = out.brake.torque_nm
    out.body_torque_nm = inp.drive_torque_nm - out.brake.torque_nm
    out.speed_deriv_rad_s2 = (out.body_torque_nm - inp.tyre_force_n * inp.tyre_radius_m
                              - inp.rolling_moment_nm) / p.inertia_kgm2
    return out


def wheel_advance(p, s, inp, out, h):
    s.brake_twist_rad = friction_advance(p.brake, s.brake_twist_rad, out.brake, out.capacity_nm, h)
    s.speed_rad_s += h * out.speed_deriv_rad_s2


# --------------------------------------------------------------------------
# tyre.c: magic formula with transient slip
# --------------------------------------------------------------------------

class TyreState(_Struct):
    __slots__ = ("deflection_m",)


class TyreOutput(_Struct):
    __slots__ = ("force_n", "rolling_moment_nm", "slip", "slip_speed_m_s", "deflection_rate_m_s",
                 "contact_weight", "tyre_load_n")


def magic_formula(p, slip, fz):
    if fz <= 0.0:
        return 0.0
    dfz = (fz - p.nominal_load_n) / p.nominal_load_n
    c = p.pcx1
    mu = p.pdx1 + p.pdx2 * dfz
    d = mu * fz
    e = p.pex1 + p.pex2 * dfz
    if e > 1.0:
        e = 1.0
    k = fz * (p.pkx1 + p.pkx2 * dfz) * math.exp(p.pkx3 * dfz)
    b = k / (c * d)
    bx = b * slip
    return d * math.sin(c * math.atan(bx - e * (bx - math.atan(bx))))


def magic_formula_peak_slip(p, fz):
    c = p.pcx1
    if c <= 1.0 or fz <= 0.0:
        return 1e9
    dfz = (fz - p.nominal_load_n) / p.nominal_load_n
    d = (p.pdx1 + p.pdx2 * dfz) * fz
    e = p.pex1 + p.pex2 * dfz
    if e > 1.0:
        e = 1.0
    k = fz * (p.pkx1 + p.pkx2 * dfz) * math.exp(p.pkx3 * dfz)
    b = k / (c * d)
    rhs = math.tan(PI / (2.0 * c))
    x = rhs
    for _ in range(6):
        g = x * (1.0 - e) + e * math.atan(x) - rhs
        dg = (1.0 - e) + e / (1.0 + x * x)
        x -= g / dg
    return x / b


def tyre_output(p, s, wheel_speed_rad_s, ground_speed_m_s, normal_force_n, count):
    out = TyreOutput()
    n = count
    v = ground_speed_m_s
    wr = wheel_speed_rad_s * p.radius_m
    slip_speed = wr - v
    vref = abs(v) if abs(v) > abs(wr) else abs(wr)
    kappa = s.deflection_m / p.relaxation_length_m
    fz = normal_force_n if normal_force_n > 0.0 else 0.0
    f = n * magic_formula(p, kappa, fz / n)
    w = fade(v, p.low_speed_limit_m_s)
    f += n * p.low_speed_damping_ns_per_m * w * slip_speed
    out.force_n = f
    out.slip = kappa
    out.slip_speed_m_s = slip_speed
    out.deflection_rate_m_s = slip_speed - (1.0 - w) * vref * s.deflection_m / p.relaxation_length_m
    f += n * p.carcass_damping_ns_per_m * out.deflection_rate_m_s
    out.force_n = f
    out.contact_weight = w
    out.tyre_load_n = fz / n
    # rolling resistance rises with speed: f0 + fs (V / V_ref)^2.5
    x = abs(v) / p.rolling_resistance_ref_speed_m_s
    f_rr = p.rolling_resistance + p.rolling_resistance_speed * x * x * math.sqrt(x)
    out.rolling_moment_nm = f_rr * fz * p.radius_m * smooth_sign(wheel_speed_rad_s, p.rolling_smoothing_rad_s)
    return out


def tyre_advance(p, s, out, h):
    u = s.deflection_m + h * out.deflection_rate_m_s
    w = out.contact_weight
    if w > 0.0 and abs(u) * w > 0.02 * p.relaxation_length_m:
        lim = p.relaxation_length_m * magic_formula_peak_slip(p, out.tyre_load_n) / w
        u = clamp(u, -lim, lim)
    s.deflection_m = u


# --------------------------------------------------------------------------
# vehicle.c: body in the vertical plane
# --------------------------------------------------------------------------

class VehicleState(_Struct):
    __slots__ = ("position_m", "speed_m_s", "heave_m", "heave_rate_m_s", "pitch_rad", "pitch_rate_rad_s",
                 "front_spindle_m", "front_spindle_rate_m_s", "rear_spindle_m", "rear_spindle_rate_m_s")


class VehicleOutput(_Struct):
    __slots__ = ("front_normal_force_n", "rear_normal_force_n", "accel_m_s2", "aero_force_n",
                 "front_suspension_force_n", "rear_suspension_force_n", "heave_accel_m_s2",
                 "pitch_accel_rad_s2", "front_spindle_accel_m_s2", "rear_spindle_accel_m_s2")


def vehicle_static_front_n(p):
    ms = p.mass_kg - p.front_unsprung_kg - p.rear_unsprung_kg
    b = p.wheelbase_m - p.cg_to_front_axle_m
    return ms * p.gravity_m_s2 * b / p.wheelbase_m + p.front_unsprung_kg * p.gravity_m_s2


def vehicle_static_rear_n(p):
    ms = p.mass_kg - p.front_unsprung_kg - p.rear_unsprung_kg
    return ms * p.gravity_m_s2 * p.cg_to_front_axle_m / p.wheelbase_m + p.rear_unsprung_kg * p.gravity_m_s2


def _sprung_mass(p):
    return p.mass_kg - p.front_unsprung_kg - p.rear_unsprung_kg


def _spring_preloads(p):
    ms, wb, a = _sprung_mass(p), p.wheelbase_m, p.cg_to_front_axle_m
    return ms * p.gravity_m_s2 * (wb - a) / wb, ms * p.gravity_m_s2 * a / wb


def _suspension_forces(p, s):
    a = p.cg_to_front_axle_m
    b = p.wheelbase_m - a
    pf, pr = _spring_preloads(p)
    zf, vf = s.heave_m + a * s.pitch_rad, s.heave_rate_m_s + a * s.pitch_rate_rad_s
    zr, vr = s.heave_m - b * s.pitch_rad, s.heave_rate_m_s - b * s.pitch_rate_rad_s
    front = (pf + p.front_spring_n_per_m * (s.front_spindle_m - zf)
             + p.front_damper_ns_per_m * (s.front_spindle_rate_m_s - vf))
    rear = (pr + p.rear_spring_n_per_m * (s.rear_spindle_m - zr)
            + p.rear_damper_ns_per_m * (s.rear_spindle_rate_m_s - vr))
    return front, rear


def vehicle_tyre_loads(p, s):
    f = (vehicle_static_front_n(p) - p.front_tyre_vertical_n_per_m * s.front_spindle_m
         - p.tyre_vertical_damping_ns_per_m * s.front_spindle_rate_m_s)
    r = (vehicle_static_rear_n(p) - p.rear_tyre_vertical_n_per_m * s.rear_spindle_m
         - p.tyre_vertical_damping_ns_per_m * s.rear_spindle_rate_m_s)
    return (f if f > 0.0 else 0.0), (r if r > 0.0 else 0.0)


def vehicle_init(s, speed_m_s):
    s.load([0.0] * len(VehicleState.__slots__))
    s.speed_m_s = speed_m_s


def vehicle_output(p, s, front_tyre_force_n, rear_tyre_force_n, front_wheel_torque_nm,
                   rear_wheel_torque_nm, road_grade_pct):
    out = VehicleOutput()
    a = p.cg_to_front_axle_m
    b = p.wheelbase_m - a
    slope = 0.01 * road_grade_pct
    cos_a = 1.0 / math.sqrt(1.0 + slope * slope)
    gn = p.gravity_m_s2 * cos_a
    ms = _sprung_mass(p)
    fsf, fsr = _suspension_forces(p, s)
    ftf, ftr = vehicle_tyre_loads(p, s)
    fx = front_tyre_force_n + rear_tyre_force_n
    out.heave_accel_m_s2 = (fsf + fsr - ms * gn) / ms
    out.pitch_accel_rad_s2 = (a * fsf - b * fsr + fx * (p.cg_height_m - p.wheel_centre_height_m)
                              + front_wheel_torque_nm + rear_wheel_torque_nm) / p.pitch_inertia_kgm2
    out.front_spindle_accel_m_s2 = (ftf - fsf - p.front_unsprung_kg * gn) / p.front_unsprung_kg
    out.rear_spindle_accel_m_s2 = (ftr - fsr - p.rear_unsprung_kg * gn) / p.rear_unsprung_kg
    out.front_normal_force_n = ftf
    out.rear_normal_force_n = ftr
    out.front_suspension_force_n = fsf
    out.rear_suspension_force_n = fsr
    v = s.speed_m_s
    out.aero_force_n = 0.5 * p.air_density_kg_m3 * p.drag_coefficient * p.frontal_area_m2 * v * abs(v)
    out.accel_m_s2 = (front_tyre_force_n + rear_tyre_force_n - out.aero_force_n
                      - p.mass_kg * p.gravity_m_s2 * slope * cos_a) / p.mass_kg
    return out


def vehicle_advance(s, out, h):
    s.position_m += h * s.speed_m_s
    s.speed_m_s += h * out.accel_m_s2
    s.heave_m += h * s.heave_rate_m_s
    s.heave_rate_m_s += h * out.heave_accel_m_s2
    s.pitch_rad += h * s.pitch_rate_rad_s
    s.pitch_rate_rad_s += h * out.pitch_accel_rad_s2
    s.front_spindle_m += h * s.front_spindle_rate_m_s
    s.front_spindle_rate_m_s += h * out.front_spindle_accel_m_s2
    s.rear_spindle_m += h * s.rear_spindle_rate_m_s
    s.rear_spindle_rate_m_s += h * out.rear_spindle_accel_m_s2


# --------------------------------------------------------------------------
# plant.c: the assembly
# --------------------------------------------------------------------------

INPUT_NAMES = (
    "accel_pedal_pct", "brake_pedal_pct", "solenoid_current1_a", "solenoid_current2_a",
    "line_solenoid_current_a", "clutch1_pressure_bar", "clutch2_pressure_bar", "fork_force1_n",
    "fork_force2_n", "fork_force3_n", "fork_force4_n", "road_grade_pct", "engine_torque_request_nm",
    "torque_request_active", "engine_on", "selector_lever",
)

OUTPUT_NAMES = (
    "time_s", "engine_speed_rpm", "engine_torque_nm", "engine_running", "input_shaft1_speed_rpm",
    "input_shaft2_speed_rpm", "output_shaft1_speed_rpm", "output_shaft2_speed_rpm",
    "solenoid_current1_a", "solenoid_current2_a", "line_solenoid_current_a", "line_pressure_bar",
    "clutch1_pressure_bar", "clutch2_pressure_bar", "piston1_position_mm", "piston2_position_mm",
    "spool1_position_mm", "spool2_position_mm", "clutch1_clamp_force_n", "clutch2_clamp_force_n",
    "clutch1_torque_nm", "clutch2_torque_nm", "clutch1_slip_rpm", "clutch2_slip_rpm",
    "clutch1_capacity_nm", "clutch2_capacity_nm", "vehicle_speed_kmh", "vehicle_accel_mps2",
    "distance_m", "pitch_deg", "heave_mm", "sync1_state", "sync2_state", "sync3_state", "sync4_state",
    "sync1_gear", "sync2_gear", "sync3_gear", "sync4_gear", "fork1_position_mm", "fork2_position_mm",
    "fork3_position_mm", "fork4_position_mm", "gear_clashes", "fuel_l", "fuel_rate_lph",
    "wheel_speed_fl_rpm", "wheel_speed_fr_rpm", "wheel_speed_rear_rpm", "halfshaft_torque_nm",
    "front_tyre_slip", "front_axle_load_n", "rear_axle_load_n", "brake_torque_nm", "road_grade_pct",
    "accel_pedal_pct", "brake_pedal_pct", "input_clamps", "coolant_temp_degc",
    "engine_oil_temp_degc", "trans_oil_temp_degc", "thermostat_opening", "engine_heat_in_w",
    "trans_heat_in_w", "heat_rejected_w", "trans_oil_viscosity_mm2_s", "accessory_torque_nm", "gear",
    "selector_lever", "park_lock_engaged", "clutch1_kiss_pressure_bar", "clutch2_kiss_pressure_bar",
    "clutch1_friction_coeff", "clutch2_friction_coeff", "clutch1_drag_torque_nm", "clutch2_drag_torque_nm",
    "trans_pump_torque_nm",
)

SELECTOR_P = 0.0
SELECTOR_D = 3.0

GEAR_TORQUE_MIN_NM = 2.0


# --------------------------------------------------------------------------
# thermal.c: lumped temperatures and their effects
# --------------------------------------------------------------------------

KELVIN = 273.15


class ThermalState(_Struct):
    __slots__ = ("coolant_temp_degc", "engine_oil_temp_degc", "trans_oil_temp_degc")


class ThermalEffects(_Struct):
    __slots__ = ("engine_drag_factor", "idle_rise_rpm", "fuel_enrichment", "trans_viscosity_ratio",
                 "trans_oil_viscosity_m2_s", "engine_oil_viscosity_ratio", "clutch_drag_factor",
                 "churning_factor", "clutch_mu_factor", "clutch_gap_change_mm", "thermostat_opening")


class ThermalOutput(_Struct):
    __slots__ = ("coolant_heat_in_w", "engine_oil_heat_in_w", "trans_heat_in_w", "radiator_w",
                 "engine_ambient_w", "trans_ambient_w", "oil_to_coolant_w", "trans_to_coolant_w",
                 "coolant_rate_k_s", "engine_oil_rate_k_s", "trans_oil_rate_k_s")


def walther_viscosity(nu40_mm2_s, nu100_mm2_s, temp_degc):
    w40 = math.log10(math.log10(nu40_mm2_s + 0.7))
    w100 = math.log10(math.log10(nu100_mm2_s + 0.7))
    l40 = math.log10(40.0 + KELVIN)
    l100 = math.log10(100.0 + KELVIN)
    t = temp_degc + KELVIN
    if t < 150.0:
        t = 150.0
    w = w40 + (w100 - w40) * (math.log10(t) - l40) / (l100 - l40)
    return math.pow(10.0, math.pow(10.0, w)) - 0.7


def thermal_init(s, coolant_degc, engine_oil_degc, trans_oil_degc):
    s.coolant_temp_degc = coolant_degc
    s.engine_oil_temp_degc = engine_oil_degc
    s.trans_oil_temp_degc = trans_oil_degc


def thermal_prepare(p):
    return (walther_viscosity(p.engine_oil_viscosity_40c_mm2_s, p.engine_oil_viscosity_100c_mm2_s,
                              p.engine_ref_temp_degc),
            walther_viscosity(p.trans_oil_viscosity_40c_mm2_s, p.trans_oil_viscosity_100c_mm2_s,
                              p.trans_ref_temp_degc))


def thermal_effects_key(p, s):
    """The temperatures the effects are taken at: rounded to p.effects_resolution_k."""
    q = p.effects_resolution_k

    def rounded(t):
        return math.floor(t / q + 0.5) * q if q > 0.0 else t
    return (rounded(s.coolant_temp_degc), rounded(s.engine_oil_temp_degc), rounded(s.trans_oil_temp_degc))


def thermal_effects(p, d, trans_oil, state):
    key = thermal_effects_key(p, state)
    s = SimpleNamespace(coolant_temp_degc=key[0], engine_oil_temp_degc=key[1], trans_oil_temp_degc=key[2])
    fx = ThermalEffects()
    ro = (walther_viscosity(p.engine_oil_viscosity_40c_mm2_s, p.engine_oil_viscosity_100c_mm2_s,
                            s.engine_oil_temp_degc) / d[0])
    rt = (walther_viscosity(p.trans_oil_viscosity_40c_mm2_s, p.trans_oil_viscosity_100c_mm2_s,
                            s.trans_oil_temp_degc) / d[1])
    lo = math.log(ro)
    lt = math.log(rt)
    fx.engine_oil_viscosity_ratio = ro
    fx.engine_drag_factor = 1.0 + p.engine_rubbing_share * (math.exp(p.engine_friction_viscosity_exponent * lo) - 1.0)
    span = p.idle_warm_degc - p.idle_cold_degc
    cold = clamp((p.idle_warm_degc - s.coolant_temp_degc) / span, 0.0, 1.0)
    fx.idle_rise_rpm = p.idle_cold_rise_rpm * cold
    fx.fuel_enrichment = p.cold_enrichment * cold
    fx.trans_viscosity_ratio = rt
    fx.trans_oil_viscosity_m2_s = trans_oil.viscosity_m2_s * rt
    fx.clutch_drag_factor = math.exp(p.clutch_drag_viscosity_exponent * lt)
    fx.churning_factor = math.exp(p.churning_viscosity_exponent * lt)
    dt = s.trans_oil_temp_degc - p.trans_ref_temp_degc
    fx.clutch_mu_factor = 1.0 + p.clutch_mu_change_per_k * dt
    fx.clutch_gap_change_mm = p.clutch_gap_expansion_per_k * p.clutch_gap_length_mm * dt
    fx.thermostat_opening = clamp((s.coolant_temp_degc - p.thermostat_open_degc)
                                  / (p.thermostat_full_degc - p.thermostat_open_degc),
                                  p.thermostat_min_opening, 1.0)
    return fx


def thermal_output(p, s, fx, fuel_heat_w, combustion_power_w, friction_power_w, trans_heat_w,
                   vehicle_speed_m_s):
    out = ThermalOutput()
    ta = p.ambient_temp_degc
    tc, to, tt = s.coolant_temp_degc, s.engine_oil_temp_degc, s.trans_oil_temp_degc
    v = abs(vehicle_speed_m_s)
    unused = fuel_heat_w - combustion_power_w
    if unused < 0.0:
        unused = 0.0
    fric = friction_power_w if friction_power_w > 0.0 else 0.0
    out.coolant_heat_in_w = p.wall_heat_fraction * unused + (1.0 - p.friction_heat_oil_share) * fric
    out.engine_oil_heat_in_w = p.friction_heat_oil_share * fric
    out.trans_heat_in_w = trans_heat_w
    out.radiator_w = ((p.radiator_ua_w_per_k + p.radiator_ua_per_speed_ws_per_km * v)
                      * fx.thermostat_opening * (tc - ta))
    out.engine_ambient_w = p.engine_ambient_ua_w_per_k * (tc - ta)
    out.trans_ambient_w = (p.trans_ambient_ua_w_per_k + p.trans_ambient_ua_per_speed_ws_per_km * v) * (tt - ta)
    out.oil_to_coolant_w = p.oil_coolant_ua_w_per_k * (to - tc)
    out.trans_to_coolant_w = p.trans_cooler_ua_w_per_k * (tt - tc)
    out.coolant_rate_k_s = ((out.coolant_heat_in_w + out.oil_to_coolant_w + out.trans_to_coolant_w
                             - out.radiator_w - out.engine_ambient_w) / p.coolant_heat_capacity_j_per_k)
    out.engine_oil_rate_k_s = (out.engine_oil_heat_in_w - out.oil_to_coolant_w) / p.engine_oil_heat_capacity_j_per_k
    out.trans_oil_rate_k_s = ((out.trans_heat_in_w - out.trans_to_coolant_w - out.trans_ambient_w)
                              / p.trans_heat_capacity_j_per_k)
    return out


def thermal_advance(s, out, h):
    s.coolant_temp_degc += h * out.coolant_rate_k_s
    s.engine_oil_temp_degc += h * out.engine_oil_rate_k_s
    s.trans_oil_temp_degc += h * out.trans_oil_rate_k_s


def accessory_torque(p, speed_rad_s):
    w = abs(speed_rad_s)
    w_min = 500.0 * RAD_S_PER_RPM
    alt = p.alternator_load_w / p.alternator_efficiency / (w if w > w_min else w_min)
    t = alt + p.power_steering_nm + (p.ac_torque_nm if p.ac_on > 0.5 else 0.0)
    return t * smooth_sign(w, p.accessory_smoothing_rad_s)


def pump_torque(p, line_pressure_pa, speed_rad_s, smoothing_rad_s):
    """The transmission's engine-driven oil pump on the crank (p: hydraulics.supply)."""
    pa = line_pressure_pa if line_pressure_pa > 0.0 else 0.0
    return (pa * p.pump_displacement_cm3 * 1e-6 / (2.0 * PI * p.pump_efficiency)
            * smooth_sign(speed_rad_s, smoothing_rad_s))


def pack_closed_pressure_pa(cp):
    """The chamber pressure at which the piston has closed the pack gap (the kiss point)."""
    return (cp.return_spring_n + cp.return_spring_n_per_m * cp.pack_gap_mm * 1e-3) / cp.piston_area_m2


def _namespace(value):
    """The load_params dict read as attributes (lists of tables as lists)."""
    if isinstance(value, dict):
        return SimpleNamespace(**{k: _namespace(v) for k, v in value.items()})
    if isinstance(value, list) and value and isinstance(value[0], dict):
        return [_namespace(v) for v in value]
    return value


class Coupling:
    """Every coupling variable of one evaluation (plant.c: struct coupling)."""

    __slots__ = ("clutch_params", "chamber", "current_a", "line_current_a", "hydraulics", "clutch_in",
                 "clutch", "engine_in", "engine", "wheel_speeds", "body_pitch", "driveline", "gearbox",
                 "tyre", "wheel_in", "wheel", "vehicle", "thermal_fx", "thermal", "pump_torque_nm")


class PyPlant:
    """The plant of plant/csrc in Python: same parameters, state layout and step.

    ``params``: the dict of ``plant.params.load_params`` (or ``Plant.params``).
    ``inputs``: dict over ``INPUT_NAMES``; ``state``: flat array in the order
    of ``dct_state``; ``outputs``: dict over ``OUTPUT_NAMES`` (the order of
    ``dct_outputs``), ``output_values`` the same as an array.
    """

    input_names = INPUT_NAMES
    output_names = OUTPUT_NAMES

    def __init__(self, params):
        self.params = params
        p = self.p = _namespace(params)
        self.substeps = int(p.solver.substeps)
        self.chambers = hydraulics_prepare(p.hydraulics, p.clutch)
        self.gearbox_derived = gearbox_prepare(p.gearbox)
        self.thermal_derived = thermal_prepare(p.thermal)
        self.time_s = 0.0
        self.engine = EngineState()
        self.clutch = [ClutchState(), ClutchState()]
        self.hydraulics = HydraulicsState()
        self.gearbox = GearboxState()
        self.driveline = DrivelineState()
        self.wheel = [WheelState() for _ in range(3)]
        self.tyre = [TyreState() for _ in range(3)]
        self.vehicle = VehicleState()
        self.thermal = ThermalState()
        self.inputs = {name: 0.0 for name in INPUT_NAMES}
        self.inputs["engine_on"] = 1.0
        self.inputs["selector_lever"] = SELECTOR_D
        self.applied = dict(self.inputs)
        self.outputs = {name: 0.0 for name in OUTPUT_NAMES}
        self.step_count = 0.0
        self.input_clamps = 0.0
        self.active_shaft = -1.0
        self.reset()

    # ------------------------------------------------------------- the state
    def _parts(self):
        return [self.engine, *self.clutch, self.hydraulics, self.gearbox, self.driveline,
                *self.wheel, *self.tyre, self.vehicle, self.thermal]

    def _state_list(self):
        values = [self.time_s]
        for part in self._parts():
            values += part.values()
        return values

    @property
    def state(self):
        """The state as one flat float64 array, in the order of ``dct_state``."""
        return np.array(self._state_list(), dtype=np.float64)

    @state.setter
    def state(self, values):
        values = [float(v) for v in values]
        if len(values) != len(STATE_NAMES):
            raise ValueError(f"state needs {len(STATE_NAMES)} values, got {len(values)}")
        self.time_s = values[0]
        i = 1
        for part in self._parts():
            n = len(part.values())
            part.load(values[i:i + n])
            i += n

    @property
    def output_values(self):
        return np.array([self.outputs[name] for name in OUTPUT_NAMES], dtype=np.float64)

    def init_from(self, plant):
        """Copy a C ``plant.model.Plant``'s state, inputs, counters and outputs."""
        self.state = plant.state
        self.inputs = {name: float(plant.inputs[name]) for name in INPUT_NAMES}
        self.step_count = float(plant._p.step_count)
        self.input_clamps = float(plant._p.input_clamps)
        self.active_shaft = float(plant._p.active_shaft)
        self.applied = {name: float(getattr(plant._p.applied, name)) for name in INPUT_NAMES}
        self.outputs = {name: float(plant.outputs[name]) for name in OUTPUT_NAMES}

    # -------------------------------------------------------------- reset
    def reset(self, vehicle_speed_kmh=0.0, sleeves=(0, 0, 0, 0), clutch_locked=(0, 0), engine_on=1,
              temperatures=None):
        """dct_plant_reset: steady motion at a speed with sleeves engaged;
        ``temperatures``: (coolant, engine oil, transmission oil) in degC, or
        None for the parameters' initial ones."""
        p = self.p
        d = self.gearbox_derived
        self.time_s = 0.0
        for part in self._parts():
            part.load([0.0] * len(part.values()))
        v = vehicle_speed_kmh / 3.6
        w_wheel = v / p.tyre.radius_m
        w_car = w_wheel
        th = p.thermal
        if temperatures is not None:
            thermal_init(self.thermal, *[float(t) for t in temperatures])
        else:
            thermal_init(self.thermal, th.initial_coolant_temp_degc, th.initial_engine_oil_temp_degc,
                         th.initial_trans_oil_temp_degc)
        fx = thermal_effects(th, self.thermal_derived, p.hydraulics.oil, self.thermal)
        on = engine_on > 0.5
        w_idle = (p.engine.idle_speed_rpm + fx.idle_rise_rpm) * RAD_S_PER_RPM if on else 0.0
        w_in = [-1.0, -1.0]
        engaged = [False, False]
        for k in range(N_SLEEVES):
            side = 1 if sleeves[k] > 0.5 else (-1 if sleeves[k] < -0.5 else 0)
            g = sleeve_gear(k, side)
            if g < 0:
                side = 0
            sync_init(p.gearbox.sync[k], self.gearbox.sync[k], side)
            if g >= 0:
                shaft = gear_input_shaft(g)
                w_in[shaft] = w_car * p.gearbox.final_drive[gear_output_shaft(g)] * d.signed_ratio[g]
                engaged[shaft] = True
        w_eng = w_idle
        self.active_shaft = -1.0
        for k in range(2):
            if clutch_locked[k] > 0.5 and engaged[k]:
                w_eng = w_in[k]
                self.active_shaft = float(k)
                break
        for k in range(2):
            self.gearbox.input_speed_rad_s[k] = w_in[k] if engaged[k] else w_eng
        self.gearbox.carrier_speed_rad_s = w_car
        engine_init(p.engine, self.engine, w_eng, on)
        if on:
            k = fx.engine_drag_factor - 1.0
            w_i = (p.engine.idle_speed_rpm + fx.idle_rise_rpm) * RAD_S_PER_RPM
            n_e = abs(w_eng) * RPM_PER_RAD_S
            n_i = w_i * RPM_PER_RAD_S
            line_pa = pressure_map_eval(p.hydraulics.supply.line, 0.0) * PA_PER_BAR
            sm = th.accessory_smoothing_rad_s
            self.engine.combustion_torque_nm += (-k * curve_eval(p.engine.drag, n_e)
                                                 * smooth_sign(w_eng, p.engine.drag_smoothing_rad_s)
                                                 + accessory_torque(th, w_eng)
                                                 + pump_torque(p.hydraulics.supply, line_pa, w_eng, sm))
            self.engine.idle_integral_nm = clamp(-(1.0 + k) * curve_eval(p.engine.drag, n_i)
                                                 + accessory_torque(th, w_i)
                                                 + pump_torque(p.hydraulics.supply, line_pa, w_i, sm),
                                                 0.0, p.engine.idle_torque_max_nm)
        hydraulics_init(p.hydraulics, self.hydraulics)
        for i in range(3):
            self.wheel[i].speed_rad_s = w_wheel
        vehicle_init(self.vehicle, v)
        self.step_count = 0.0
        self.input_clamps = 0.0
        self.inputs["engine_on"] = 1.0 if on else 0.0
        self._apply_inputs()
        self.input_clamps = 0.0
        self._write_outputs(self._evaluate())

    # ------------------------------------------------------------ inputs
    def _limit(self, x, lo, hi):
        if x < lo:
            self.input_clamps += 1.0
            return lo
        if x > hi:
            self.input_clamps += 1.0
            return hi
        return x

    def _apply_inputs(self):
        u = self.inputs
        for name in INPUT_NAMES:
            if not math.isfinite(u[name]):
                raise PyPlantError(f"input {name} is not finite: {u[name]!r}")
        p = self.p
        a = self.applied
        lim = self._limit
        fmax = p.gearbox.max_fork_force_n
        imax = p.hydraulics.valve.max_current_a
        a["accel_pedal_pct"] = lim(u["accel_pedal_pct"], 0.0, 100.0)
        a["brake_pedal_pct"] = lim(u["brake_pedal_pct"], 0.0, 100.0)
        a["solenoid_current1_a"] = lim(u["solenoid_current1_a"], 0.0, imax)
        a["solenoid_current2_a"] = lim(u["solenoid_current2_a"], 0.0, imax)
        a["line_solenoid_current_a"] = lim(u["line_solenoid_current_a"], 0.0,
                                           p.hydraulics.supply.max_current_a)
        a["clutch1_pressure_bar"] = lim(u["clutch1_pressure_bar"], 0.0, p.clutch[0].max_pressure_bar)
        a["clutch2_pressure_bar"] = lim(u["clutch2_pressure_bar"], 0.0, p.clutch[1].max_pressure_bar)
        for k in range(1, 5):
            a[f"fork_force{k}_n"] = lim(u[f"fork_force{k}_n"], -fmax, fmax)
        a["road_grade_pct"] = lim(u["road_grade_pct"], -40.0, 40.0)
        a["engine_torque_request_nm"] = lim(u["engine_torque_request_nm"], -200.0, 1000.0)
        a["torque_request_active"] = 1.0 if u["torque_request_active"] > 0.5 else 0.0
        a["engine_on"] = 1.0 if u["engine_on"] > 0.5 else 0.0
        # the lever is in one of its positions: the nearest, within P..D
        a["selector_lever"] = float(math.floor(lim(u["selector_lever"], SELECTOR_P, SELECTOR_D) + 0.5))

    # ---------------------------------------------------- one evaluation
    def _evaluate_thermal(self):
        """What the temperatures change (thermal effects, pack gaps, chamber law):
        once a step, at its start, for all its sub-steps (plant.c, evaluate_thermal)."""
        p = self.p
        fx = thermal_effects(p.thermal, self.thermal_derived, p.hydraulics.oil, self.thermal)
        # the pack gaps at this oil temperature (thermal expansion) and their chamber law
        clutch_params = []
        for k in range(2):
            cp = SimpleNamespace(**vars(p.clutch[k]))
            gap = p.clutch[k].pack_gap_mm + fx.clutch_gap_change_mm
            cp.pack_gap_mm = gap if gap > 0.0 else 0.0
            clutch_params.append(cp)
        if fx.clutch_gap_change_mm != 0.0:
            chamber = hydraulics_prepare(p.hydraulics, clutch_params)
        else:
            chamber = self.chambers
        return fx, clutch_params, chamber

    def _evaluate(self, thermal=None):
        p = self.p
        u = self.applied
        c = Coupling()
        fx, c.clutch_params, c.chamber = self._evaluate_thermal() if thermal is None else thermal
        c.thermal_fx = fx
        c.current_a = (u["solenoid_current1_a"], u["solenoid_current2_a"])
        c.line_current_a = u["line_solenoid_current_a"]
        # hydraulics: clamp forces from the chambers, or from commanded pressures
        if p.hydraulics.pressure_commanded > 0.5:
            hy = HydraulicsOutput(clamp_force_n=[0.0, 0.0], piston_position_m=[0.0, 0.0],
                                  clutch_pressure_pa=[0.0, 0.0])
            pressure = (u["clutch1_pressure_bar"], u["clutch2_pressure_bar"])
            for k in range(2):
                po = piston_eval(c.clutch_params[k], pressure[k] * PA_PER_BAR)
                hy.clamp_force_n[k] = po.clamp_force_n
                hy.piston_position_m[k] = po.position_m
                hy.clutch_pressure_pa[k] = pressure[k] * PA_PER_BAR
        else:
            hy = hydraulics_output(c.chamber, c.clutch_params, self.hydraulics)
        c.hydraulics = hy

        # clutches: engine drum to the input shafts
        c.clutch_in = []
        c.clutch = []
        for k in range(2):
            ci = ClutchInput(clamp_force_n=hy.clamp_force_n[k], drive_speed_rad_s=self.engine.speed_rad_s,
                             driven_speed_rad_s=self.gearbox.input_speed_rad_s[k],
                             drag_excess=fx.clutch_drag_factor - 1.0, mu_excess=fx.clutch_mu_factor - 1.0)
            c.clutch_in.append(ci)
            c.clutch.append(clutch_output(p.clutch[k], self.clutch[k], ci))

        # engine, loaded by both clutches
        c.engine_in = EngineInput(accel_pedal_pct=u["accel_pedal_pct"],
                                  torque_request_nm=u["engine_torque_request_nm"],
                                  torque_request_active=u["torque_request_active"],
                                  engine_on=u["engine_on"],
                                  load_torque_nm=c.clutch[0].torque_nm + c.clutch[1].torque_nm,
                                  drag_excess=fx.engine_drag_factor - 1.0,
                                  idle_rise_rpm=fx.idle_rise_rpm, fuel_enrichment=fx.fuel_enrichment,
                                  accessory_torque_nm=0.0)
        c.pump_torque_nm = pump_torque(p.hydraulics.supply, self.hydraulics.line_pressure_pa,
                                       self.engine.speed_rad_s, p.thermal.accessory_smoothing_rad_s)
        c.engine_in.accessory_torque_nm = (accessory_torque(p.thermal, self.engine.speed_rad_s)
                                           + c.pump_torque_nm)
        c.engine = engine_output(p.engine, self.engine, c.engine_in)

        # differential and half-shafts
        c.wheel_speeds = (self.wheel[0].speed_rad_s, self.wheel[1].speed_rad_s)
        c.body_pitch = (self.vehicle.pitch_rad, self.vehicle.pitch_rate_rad_s)
        c.driveline = driveline_output(p.driveline, self.driveline, self.gearbox.carrier_speed_rad_s,
                                       c.wheel_speeds[0], c.wheel_speeds[1], *c.body_pitch)

        # gearbox
        forks = (u["fork_force1_n"], u["fork_force2_n"], u["fork_force3_n"], u["fork_force4_n"])
        c.gearbox = gearbox_output(p.gearbox, self.gearbox_derived, self.gearbox,
                                   (c.clutch[0].torque_nm, c.clutch[1].torque_nm), forks,
                                   c.driveline.carrier_load_nm, fx.churning_factor - 1.0,
                                   tuple(0.0 if c.clutch[k].friction.sliding > 0.5
                                         else p.clutch[k].friction.damping_nms_per_rad for k in range(2)))

        # tyres and wheels
        fz_front, fz_rear = vehicle_tyre_loads(p.vehicle, self.vehicle)
        fz = (0.5 * fz_front, 0.5 * fz_front, fz_rear)
        count = (1.0, 1.0, 2.0)
        shaft = (c.driveline.shaft_torque_nm, c.driveline.shaft_torque_nm, 0.0)
        c.tyre = []
        c.wheel_in = []
        c.wheel = []
        for i in range(3):
            to = tyre_output(p.tyre, self.tyre[i], self.wheel[i].speed_rad_s, self.vehicle.speed_m_s,
                             fz[i], count[i])
            wi = WheelInput(drive_torque_nm=shaft[i], tyre_force_n=to.force_n, tyre_radius_m=p.tyre.radius_m,
                            rolling_moment_nm=to.rolling_moment_nm, brake_pedal_pct=u["brake_pedal_pct"],
                            park_lock=1.0 if u["selector_lever"] == SELECTOR_P else 0.0)
            wp = p.front_wheel if i < 2 else p.rear_wheels
            c.tyre.append(to)
            c.wheel_in.append(wi)
            c.wheel.append(wheel_output(wp, self.wheel[i], wi))

        # body
        # the front wheels take the brakes' torques from the body; the half-shafts'
        # reaction reaches it through the powertrain mounts
        front_torque = (c.wheel[0].body_torque_nm + c.wheel[1].body_torque_nm - c.driveline.carrier_load_nm
                        + c.driveline.mount_torque_nm)
        c.vehicle = vehicle_output(p.vehicle, self.vehicle, c.tyre[0].force_n + c.tyre[1].force_n,
                                   c.tyre[2].force_n, front_torque, c.wheel[2].body_torque_nm,
                                   u["road_grade_pct"])

        # heat
        w = self.engine.speed_rad_s
        c.thermal = thermal_output(p.thermal, self.thermal, fx,
                                   c.engine.burnt_fuel_rate_g_s * p.thermal.fuel_lhv_j_per_g,
                                   c.engine.combustion_torque_nm * w, -c.engine.drag_nm * w,
                                   c.clutch[0].heat_w + c.clutch[1].heat_w + c.gearbox.power_loss_w
                                   + c.pump_torque_nm * w,
                                   self.vehicle.speed_m_s)
        return c

    def _advance(self, c, h):
        p = self.p
        if not (p.hydraulics.pressure_commanded > 0.5):
            hydraulics_advance(p.hydraulics, c.chamber, self.hydraulics, c.current_a, c.line_current_a, h,
                               c.thermal_fx.trans_oil_viscosity_m2_s)
        engine_advance(p.engine, self.engine, c.engine_in, c.engine, h)
        for k in range(2):
            clutch_advance(p.clutch[k], self.clutch[k], c.clutch[k], h)
        gearbox_advance(p.gearbox, self.gearbox_derived, self.gearbox, c.gearbox, h)
        driveline_advance(self.driveline, c.driveline, c.wheel_speeds[0], c.wheel_speeds[1], h)
        for i in range(3):
            wp = p.front_wheel if i < 2 else p.rear_wheels
            wheel_advance(wp, self.wheel[i], c.wheel_in[i], c.wheel[i], h)
            tyre_advance(p.tyre, self.tyre[i], c.tyre[i], h)
        vehicle_advance(self.vehicle, c.vehicle, h)
        thermal_advance(self.thermal, c.thermal, h)
        self.time_s += h

    # ------------------------------------------------------------ outputs
    def _sync_gear_number(self, y, sleeve):
        g = sleeve_gear(sleeve, int(y.side))
        if g < 0 or y.phase == SYNC_DISENGAGED:
            return 0.0
        return -1.0 if g == GEAR_R else float(g + 1)

    def _drive_shaft(self, c):
        shaft = -1
        best = 0.0
        for k in range(2):
            t = abs(c.clutch[k].torque_nm)
            if c.clutch[k].capacity_nm < GEAR_TORQUE_MIN_NM or t < GEAR_TORQUE_MIN_NM:
                continue
            if shaft < 0 or t > best:
                shaft = k
                best = t
        return shaft

    def _shaft_gear(self, shaft):
        for k in range(N_SLEEVES):
            y = self.gearbox.sync[k]
            g = sleeve_gear(k, int(y.side))
            if g < 0 or y.phase != SYNC_ENGAGED or gear_input_shaft(g) != shaft:
                continue
            return -1.0 if g == GEAR_R else float(g + 1)
        return 0.0

    def _engaged_gear(self, c):
        shaft = self._drive_shaft(c)
        if shaft < 0:
            shaft = int(self.active_shaft)
        return 0.0 if shaft < 0 else self._shaft_gear(shaft)

    def _write_outputs(self, c):
        p = self.p
        g = self.gearbox
        e = self.engine
        # the chambers' pressures (and the pistons on them) at the state now,
        # as the spools' and the line's (plant.c write_outputs)
        hy = c.hydraulics
        if not p.hydraulics.pressure_commanded > 0.5:
            hy = hydraulics_output(c.chamber, c.clutch_params, self.hydraulics)
        a = self.applied
        o = self.outputs
        o["time_s"] = self.time_s
        o["engine_speed_rpm"] = e.speed_rad_s * RPM_PER_RAD_S
        o["engine_torque_nm"] = c.engine.torque_nm
        o["engine_running"] = e.running
        o["input_shaft1_speed_rpm"] = g.input_speed_rad_s[0] * RPM_PER_RAD_S
        o["input_shaft2_speed_rpm"] = g.input_speed_rad_s[1] * RPM_PER_RAD_S
        o["output_shaft1_speed_rpm"] = g.carrier_speed_rad_s * p.gearbox.final_drive[0] * RPM_PER_RAD_S
        o["output_shaft2_speed_rpm"] = g.carrier_speed_rad_s * p.gearbox.final_drive[1] * RPM_PER_RAD_S
        o["solenoid_current1_a"] = a["solenoid_current1_a"]
        o["solenoid_current2_a"] = a["solenoid_current2_a"]
        o["line_solenoid_current_a"] = a["line_solenoid_current_a"]
        o["line_pressure_bar"] = self.hydraulics.line_pressure_pa / PA_PER_BAR
        o["clutch1_pressure_bar"] = hy.clutch_pressure_pa[0] / PA_PER_BAR
        o["clutch2_pressure_bar"] = hy.clutch_pressure_pa[1] / PA_PER_BAR
        o["piston1_position_mm"] = hy.piston_position_m[0] * 1e3
        o["piston2_position_mm"] = hy.piston_position_m[1] * 1e3
        o["spool1_position_mm"] = self.hydraulics.valve[0].spool_position_m * 1e3
        o["spool2_position_mm"] = self.hydraulics.valve[1].spool_position_m * 1e3
        o["clutch1_clamp_force_n"] = hy.clamp_force_n[0]
        o["clutch2_clamp_force_n"] = hy.clamp_force_n[1]
        o["clutch1_torque_nm"] = c.clutch[0].torque_nm
        o["clutch2_torque_nm"] = c.clutch[1].torque_nm
        o["clutch1_slip_rpm"] = (e.speed_rad_s - g.input_speed_rad_s[0]) * RPM_PER_RAD_S
        o["clutch2_slip_rpm"] = (e.speed_rad_s - g.input_speed_rad_s[1]) * RPM_PER_RAD_S
        o["clutch1_capacity_nm"] = c.clutch[0].capacity_nm
        o["clutch2_capacity_nm"] = c.clutch[1].capacity_nm
        o["vehicle_speed_kmh"] = self.vehicle.speed_m_s * 3.6
        o["vehicle_accel_mps2"] = c.vehicle.accel_m_s2
        o["distance_m"] = self.vehicle.position_m
        o["pitch_deg"] = self.vehicle.pitch_rad * (180.0 / PI)
        o["heave_mm"] = self.vehicle.heave_m * 1e3
        clashes = 0.0
        for k in range(N_SLEEVES):
            y = g.sync[k]
            o[f"sync{k + 1}_state"] = y.phase
            o[f"sync{k + 1}_gear"] = self._sync_gear_number(y, k)
            o[f"fork{k + 1}_position_mm"] = y.position_m * 1e3
            clashes += y.clashes
        o["gear_clashes"] = clashes
        o["fuel_l"] = e.fuel_g * 1e-3 / p.engine.fuel_density_kg_per_l
        o["fuel_rate_lph"] = c.engine.fuel_rate_g_s * 3.6 / p.engine.fuel_density_kg_per_l
        o["wheel_speed_fl_rpm"] = self.wheel[0].speed_rad_s * RPM_PER_RAD_S
        o["wheel_speed_fr_rpm"] = self.wheel[1].speed_rad_s * RPM_PER_RAD_S
        o["wheel_speed_rear_rpm"] = self.wheel[2].speed_rad_s * RPM_PER_RAD_S
        o["halfshaft_torque_nm"] = c.driveline.shaft_torque_nm
        o["front_tyre_slip"] = c.tyre[0].slip
        o["front_axle_load_n"] = c.vehicle.front_normal_force_n
        o["rear_axle_load_n"] = c.vehicle.rear_normal_force_n
        o["brake_torque_nm"] = (c.wheel[0].brake_torque_nm + c.wheel[1].brake_torque_nm
                                + c.wheel[2].brake_torque_nm)
        o["road_grade_pct"] = a["road_grade_pct"]
        o["accel_pedal_pct"] = a["accel_pedal_pct"]
        o["brake_pedal_pct"] = a["brake_pedal_pct"]
        o["input_clamps"] = self.input_clamps
        th = self.thermal
        o["coolant_temp_degc"] = th.coolant_temp_degc
        o["engine_oil_temp_degc"] = th.engine_oil_temp_degc
        o["trans_oil_temp_degc"] = th.trans_oil_temp_degc
        o["thermostat_opening"] = c.thermal_fx.thermostat_opening
        o["engine_heat_in_w"] = c.thermal.coolant_heat_in_w + c.thermal.engine_oil_heat_in_w
        o["trans_heat_in_w"] = c.thermal.trans_heat_in_w
        o["heat_rejected_w"] = c.thermal.radiator_w + c.thermal.engine_ambient_w + c.thermal.trans_ambient_w
        o["trans_oil_viscosity_mm2_s"] = c.thermal_fx.trans_oil_viscosity_m2_s * 1e6
        o["accessory_torque_nm"] = c.engine.accessory_torque_nm - c.pump_torque_nm
        o["trans_pump_torque_nm"] = c.pump_torque_nm
        o["gear"] = self._engaged_gear(c)
        o["selector_lever"] = a["selector_lever"]
        o["park_lock_engaged"] = 1.0 if c.wheel[0].park_locked > 0.5 or c.wheel[1].park_locked > 0.5 else 0.0
        for k in range(2):
            o[f"clutch{k + 1}_kiss_pressure_bar"] = pack_closed_pressure_pa(c.clutch_params[k]) / PA_PER_BAR
            o[f"clutch{k + 1}_friction_coeff"] = c.clutch[k].mu_kinetic
            o[f"clutch{k + 1}_drag_torque_nm"] = c.clutch[k].drag_torque_nm

    # --------------------------------------------------------------- step
    def _check_state(self):
        for name, value in zip(STATE_NAMES, self._state_list()):
            if not math.isfinite(value):
                raise PyPlantError(f"state {name} became {value!r} at t={self.time_s:.4f} s")

    def step(self, n=1):
        """``n`` steps of ``solver.step_s``, each of ``solver.substeps`` Euler sub-steps."""
        sub = self.substeps
        h = self.p.solver.step_s / sub
        self._apply_inputs()
        c = None
        for _ in range(n):
            thermal = self._evaluate_thermal()
            for _ in range(sub):
                c = self._evaluate(thermal)
                self._advance(c, h)
            self.step_count += 1.0
            shaft = self._drive_shaft(c)
            if shaft >= 0:
                self.active_shaft = float(shaft)
            if not all(map(math.isfinite, self._state_list())):
                self._check_state()
        if n > 0:
            self._write_outputs(c)


def _state_names():
    names = ["time_s"]
    names += [f"engine.{f}" for f in EngineState.__slots__]
    names += [f"clutch[{k}].twist_rad" for k in range(2)]
    names += ["hydraulics.line_pressure_pa", "hydraulics.clutch_oil_m3[0]", "hydraulics.clutch_oil_m3[1]"]
    names += [f"hydraulics.valve[{k}].{f}" for k in range(2) for f in ValveState.__slots__]
    names += ["gearbox.input_speed_rad_s[0]", "gearbox.input_speed_rad_s[1]", "gearbox.carrier_speed_rad_s"]
    names += [f"gearbox.sync[{k}].{f}" for k in range(N_SLEEVES) for f in SyncState.__slots__]
    names += [f"driveline.{f}" for f in DrivelineState.__slots__]
    names += [f"wheel[{i}].{f}" for i in range(3) for f in WheelState.__slots__]
    names += [f"tyre[{i}].deflection_m" for i in range(3)]
    names += [f"vehicle.{f}" for f in VehicleState.__slots__]
    names += [f"thermal.{f}" for f in ThermalState.__slots__]
    return names


#: names of the flat state, in the order of dct_state (as plant.model.STATE_NAMES)
STATE_NAMES = _state_names()


def bench_step(n_steps, params=None):
    """Median wall-clock seconds of one 0.5 ms step of the Python plant.

    Realistic state: the default car with the clutch hydraulics, in 3rd gear
    at 50 km/h with K1 clamped through its valve, 20 % pedal. ``n_steps``
    single steps are timed with ``time.perf_counter``.
    """
    if params is None:
        from plant.params import load_params

        params = load_params(None, None, {"hydraulics": {"pressure_commanded": 0}})
    py = PyPlant(params)
    py.reset(vehicle_speed_kmh=50.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    py.inputs["accel_pedal_pct"] = 20.0
    py.inputs["solenoid_current1_a"] = 1.0
    py.step(20)
    times = np.empty(max(int(n_steps), 1))
    clock = time.perf_counter
    for i in range(len(times)):
        t0 = clock()
        py.step(1)
        times[i] = clock() - t0
    return float(np.median(times))
