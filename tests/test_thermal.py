"""Thermal states (plant/csrc/thermal.c): each law on its own, then the plant.

Component tests call the C functions through cffi with the default car's
thermal parameters, changed where a law is to be seen alone (another node
held by a heat capacity of 1e15 J/K: it moves by less than 1e-9 K).
Tolerances:
- steady states and time constants: the Euler step (0.1 s here, 1/500 of the
  shortest time constant) puts the discrete exponential within 0.02 % of the
  continuous one; 0.1 % is asked;
- energy balance over a plant run: the outputs are sampled once per 0.5 ms
  step, the plant's Euler step; 1 % is asked (the
  issue's bound), measured far below;
- the viscosity law passes through its data points by construction: to
  rounding (1e-9);
- the dependencies: the laws' own values (1e-9), and the plant's cold idle
  within 5 rpm of the target (the PI governor's integral removes the error).
"""

import math

import numpy as np
import pytest

from plant._dct_plant import ffi, lib
from plant.model import Plant

BIG = 1e15  # J/K: a node held at its temperature


@pytest.fixture(scope="module")
def plant():
    return Plant()


@pytest.fixture
def th(plant):
    p = ffi.new("dct_thermal_params *")
    p[0] = plant._p.params.thermal
    return p


@pytest.fixture
def oil(plant):
    o = ffi.new("dct_oil_params *")
    o[0] = plant._p.params.hydraulics.oil
    return o


def _run(th, oil, temps, inputs, seconds, h=0.1):
    """Integrate the thermal component alone with constant heat inputs."""
    s = ffi.new("dct_thermal_state *")
    lib.dct_thermal_init(th, s, *temps)
    fx = ffi.new("dct_thermal_effects *")
    inp = ffi.new("dct_thermal_input *", inputs)
    out = ffi.new("dct_thermal_output *")
    for _ in range(int(round(seconds / h))):
        lib.dct_thermal_effects_eval(th, _derived(th), oil, s, fx)
        lib.dct_thermal_output_eval(th, s, fx, inp, out)
        lib.dct_thermal_advance(th, s, out, h)
    return s, out


def _derived(th):
    d = ffi.new("dct_thermal_derived *")
    lib.dct_thermal_prepare(th, d)
    return d


def _walther(p, which, t):
    return lib.dct_walther_viscosity(getattr(p, f"{which}_oil_viscosity_40c_mm2_s"),
                                     getattr(p, f"{which}_oil_viscosity_100c_mm2_s"), t)


# ---------------------------------------------------------------- heat laws

def test_transmission_oil_time_constant_and_steady_state(th, oil):
    """C_t dT/dt = Q - UA_c (T - T_c) - UA_a (T - T_a): first order."""
    th.coolant_heat_capacity_j_per_k = BIG
    q, tc, ta = 800.0, 90.0, th.ambient_temp_degc
    ua = th.trans_cooler_ua_w_per_k + th.trans_ambient_ua_w_per_k
    t_inf = (q + th.trans_cooler_ua_w_per_k * tc + th.trans_ambient_ua_w_per_k * ta) / ua
    tau = th.trans_heat_capacity_j_per_k / ua
    t0 = 20.0
    s, _ = _run(th, oil, (tc, tc, t0), {"trans_heat_w": q}, tau)
    expected = t_inf + (t0 - t_inf) * math.exp(-1.0)
    assert s.trans_oil_temp_degc == pytest.approx(expected, rel=1e-3)
    s, _ = _run(th, oil, (tc, tc, t0), {"trans_heat_w": q}, 20 * tau)
    assert s.trans_oil_temp_degc == pytest.approx(t_inf, abs=1e-3)


def test_engine_oil_follows_the_coolant_with_its_time_constant(th, oil):
    """C_o dT_o/dt = s_o P_fric - UA_oc (T_o - T_c), coolant held."""
    th.coolant_heat_capacity_j_per_k = BIG
    th.trans_heat_capacity_j_per_k = BIG
    fric, tc = 3000.0, 90.0
    t_inf = tc + th.friction_heat_oil_share * fric / th.oil_coolant_ua_w_per_k
    tau = th.engine_oil_heat_capacity_j_per_k / th.oil_coolant_ua_w_per_k
    s, _ = _run(th, oil, (tc, 40.0, tc), {"friction_power_w": fric}, tau)
    assert s.engine_oil_temp_degc == pytest.approx(t_inf + (40.0 - t_inf) * math.exp(-1.0), rel=1e-3)
    s, _ = _run(th, oil, (tc, 40.0, tc), {"friction_power_w": fric}, 20 * tau)
    assert s.engine_oil_temp_degc == pytest.approx(t_inf, abs=1e-3)


def test_coolant_steady_state_on_the_thermostat(th, oil):
    """All heat in leaves through radiator (thermostat), block and housing:
    the steady coolant temperature solves that balance (bisection here)."""
    p = th
    v = 20.0                                 # m/s
    fuel, comb, fric, qt = 60000.0, 15000.0, 4000.0, 600.0
    q_in = p.wall_heat_fraction * (fuel - comb) + fric + qt
    ta = p.ambient_temp_degc
    ua_ta = p.trans_ambient_ua_w_per_k + p.trans_ambient_ua_per_speed_ws_per_km * v
    ua_tc = p.trans_cooler_ua_w_per_k

    def rejected(tc):
        opening = min(max((tc - p.thermostat_open_degc)
                          / (p.thermostat_full_degc - p.thermostat_open_degc),
                          p.thermostat_min_opening), 1.0)
        tt = (qt + ua_tc * tc + ua_ta * ta) / (ua_tc + ua_ta)
        return ((p.radiator_ua_w_per_k + p.radiator_ua_per_speed_ws_per_km * v) * opening
                * (tc - ta) + p.engine_ambient_ua_w_per_k * (tc - ta) + ua_ta * (tt - ta))

    lo, hi = ta, 130.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if rejected(mid) < q_in else (lo, mid)
    tc_expected = 0.5 * (lo + hi)
    assert p.thermostat_open_degc < tc_expected < p.thermostat_full_degc  # regulating
    inputs = {"fuel_heat_w": fuel, "combustion_power_w": comb, "friction_power_w": fric,
              "trans_heat_w": qt, "vehicle_speed_m_s": v}
    s, out = _run(th, oil, (90.0, 90.0, 80.0), inputs, 3000.0)
    assert s.coolant_temp_degc == pytest.approx(tc_expected, abs=0.01)
    total_out = out.radiator_w + out.engine_ambient_w + out.trans_ambient_w
    assert total_out == pytest.approx(q_in, rel=1e-3)


def test_no_heat_from_a_fuel_cut(th, oil):
    """The combustion torque's lag after a fuel cut is no heat source or sink."""
    s = ffi.new("dct_thermal_state *")
    lib.dct_thermal_init(th, s, 90.0, 90.0, 80.0)
    fx = ffi.new("dct_thermal_effects *")
    lib.dct_thermal_effects_eval(th, _derived(th), oil, s, fx)
    out = ffi.new("dct_thermal_output *")
    inp = ffi.new("dct_thermal_input *", {"fuel_heat_w": 0.0, "combustion_power_w": 5000.0})
    lib.dct_thermal_output_eval(th, s, fx, inp, out)
    assert out.coolant_heat_in_w == 0.0 and out.engine_oil_heat_in_w == 0.0


def test_energy_balance_over_a_run():
    """Heat in = stored + rejected within 1 %, from the plant's outputs: a
    cold start, idle, launch through the clutch in 1st, drive, brake."""
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.reset(sleeves=(1, 0, 0, 0), coolant_temp_degc=20, engine_oil_temp_degc=20,
            trans_oil_temp_degc=20)
    th = p.params["thermal"]
    caps = np.array([th["coolant_heat_capacity_j_per_k"], th["engine_oil_heat_capacity_j_per_k"],
                     th["trans_heat_capacity_j_per_k"]])
    names = ("coolant_temp_degc", "engine_oil_temp_degc", "trans_oil_temp_degc")
    t0 = np.array([float(p.outputs[n]) for n in names])
    dt = p.step_s
    heat_in = rejected = slip_heat = shaft_heat = trans_in_launch = 0.0
    eta = p.params["gearbox"]["mesh_efficiency"][0]
    schedule = [(5.0, 0.0, 0.0, 0.0), (8.0, 70.0, 3.0, 0.0), (30.0, 40.0, 14.0, 0.0),
                (40.0, 0.0, 0.0, 30.0)]
    t = 0.0
    for end, pedal, pressure, brake in schedule:
        p.inputs["accel_pedal_pct"] = pedal
        p.inputs["clutch1_pressure_bar"] = pressure
        p.inputs["brake_pedal_pct"] = brake
        while t < end - 1e-9:
            p.step(1)
            t += dt
            o = p.outputs
            heat_in += dt * (float(o["engine_heat_in_w"]) + float(o["trans_heat_in_w"]))
            rejected += dt * float(o["heat_rejected_w"])
            if 5.0 < t <= 8.0:
                rad = math.pi / 30.0
                t1, t2 = float(o["clutch1_torque_nm"]), float(o["clutch2_torque_nm"])
                slip_heat += dt * rad * (t1 * float(o["clutch1_slip_rpm"])
                                         + t2 * float(o["clutch2_slip_rpm"]))
                # what the clutches deliver that the gearbox turns into heat:
                # the free input shaft 2's drag takes all of K2's torque; 1st
                # gear's mesh loses (1 / eta - 1) of K1's
                shaft_heat += dt * rad * (t2 * float(o["input_shaft2_speed_rpm"])
                                          + (1.0 / eta - 1.0) * t1 * float(o["input_shaft1_speed_rpm"]))
                trans_in_launch += dt * float(o["trans_heat_in_w"])
    stored = float(np.dot(caps, np.array([float(p.outputs[n]) for n in names]) - t0))
    assert heat_in > 1e6                                   # a run that heats
    assert abs(heat_in - stored - rejected) <= 0.01 * heat_in
    # the launch's transmission heat, computed here from the clutches'
    # torques and speeds: their slip power and what the gearbox dissipates
    # of their torque; within 5 % (the bearings and the loose gears' drag
    # are left out here)
    assert slip_heat > 50e3
    assert trans_in_launch == pytest.approx(slip_heat + shaft_heat, rel=0.05)


# ------------------------------------------------------------ viscosity law

def test_viscosity_law_through_its_data_points(th):
    for which in ("engine", "trans"):
        nu40 = getattr(th, f"{which}_oil_viscosity_40c_mm2_s")
        nu100 = getattr(th, f"{which}_oil_viscosity_100c_mm2_s")
        assert _walther(th, which, 40.0) == pytest.approx(nu40, rel=1e-9)
        assert _walther(th, which, 100.0) == pytest.approx(nu100, rel=1e-9)
        temps = np.linspace(-30.0, 140.0, 35)
        nus = [_walther(th, which, t) for t in temps]
        assert all(a > b for a, b in zip(nus, nus[1:]))    # thinner when hotter
    # ASTM D341 check by hand at 0 degC: log log (nu + 0.7) linear in log T
    a = [math.log10(math.log10(v + 0.7)) for v in (th.trans_oil_viscosity_40c_mm2_s,
                                                    th.trans_oil_viscosity_100c_mm2_s)]
    x = [math.log10(t + 273.15) for t in (40.0, 100.0)]
    w0 = a[0] + (a[1] - a[0]) * (math.log10(273.15) - x[0]) / (x[1] - x[0])
    assert _walther(th, "trans", 0.0) == pytest.approx(10 ** 10 ** w0 - 0.7, rel=1e-9)


def test_valve_viscosity_follows_the_oil_temperature(plant):
    """At the reference temperature the valves see hydraulics.oil.viscosity_m2_s;
    elsewhere that value times nu(T) / nu(T_ref)."""
    th = plant._p.params.thermal
    ref = plant.params["hydraulics"]["oil"]["viscosity_m2_s"] * 1e6
    for temp in (th.trans_ref_temp_degc, 20.0, 40.0, 100.0):
        q = Plant()
        q.reset(trans_oil_temp_degc=temp)
        expected = ref * _walther(th, "trans", temp) / _walther(th, "trans", th.trans_ref_temp_degc)
        assert float(q.outputs["trans_oil_viscosity_mm2_s"]) == pytest.approx(expected, rel=1e-9)


# ------------------------------------------------------------- dependencies

def _effects(th, oil, coolant, engine_oil, trans_oil):
    s = ffi.new("dct_thermal_state *")
    lib.dct_thermal_init(th, s, coolant, engine_oil, trans_oil)
    fx = ffi.new("dct_thermal_effects *")
    lib.dct_thermal_effects_eval(th, _derived(th), oil, s, fx)
    return fx


def test_warm_car_has_no_thermal_effect(th, oil):
    fx = _effects(th, oil, th.initial_coolant_temp_degc, th.engine_ref_temp_degc,
                  th.trans_ref_temp_degc)
    assert fx.engine_drag_factor == pytest.approx(1.0, abs=1e-12)
    assert fx.idle_rise_rpm == 0.0 and fx.fuel_enrichment == 0.0
    assert fx.clutch_drag_factor == pytest.approx(1.0, abs=1e-12)
    assert fx.churning_factor == pytest.approx(1.0, abs=1e-12)
    assert fx.clutch_mu_factor == 1.0


def test_cold_engine_drag_idle_and_enrichment(th, oil):
    fx = _effects(th, oil, 20.0, 20.0, 80.0)
    ratio = _walther(th, "engine", 20.0) / _walther(th, "engine", th.engine_ref_temp_degc)
    drag = 1.0 + th.engine_rubbing_share * (ratio ** th.engine_friction_viscosity_exponent - 1.0)
    assert fx.engine_drag_factor == pytest.approx(drag, rel=1e-9)
    assert 1.4 < fx.engine_drag_factor < 2.0          # cold engines: about 1.5-2 x at 20 degC
    cold = (th.idle_warm_degc - 20.0) / (th.idle_warm_degc - th.idle_cold_degc)
    assert fx.idle_rise_rpm == pytest.approx(th.idle_cold_rise_rpm * cold, rel=1e-12)
    assert fx.fuel_enrichment == pytest.approx(th.cold_enrichment * cold, rel=1e-12)
    full = _effects(th, oil, -20.0, -20.0, 80.0)
    assert full.idle_rise_rpm == th.idle_cold_rise_rpm
    assert full.engine_drag_factor > fx.engine_drag_factor


def test_cold_car_idles_higher_and_burns_more():
    warm, cold = Plant(), Plant()
    cold.reset(coolant_temp_degc=20, engine_oil_temp_degc=20, trans_oil_temp_degc=20)
    warm.step(10000)
    cold.step(10000)
    th = cold.params["thermal"]
    target = cold.params["engine"]["idle_speed_rpm"] + th["idle_cold_rise_rpm"] * (
        th["idle_warm_degc"] - float(cold.outputs["coolant_temp_degc"])) / (
        th["idle_warm_degc"] - th["idle_cold_degc"])
    assert float(cold.outputs["engine_speed_rpm"]) == pytest.approx(target, abs=5.0)
    assert float(warm.outputs["engine_speed_rpm"]) == pytest.approx(
        warm.params["engine"]["idle_speed_rpm"], abs=5.0)
    assert float(cold.outputs["fuel_rate_lph"]) > 1.3 * float(warm.outputs["fuel_rate_lph"])
    # the engine warms and the transmission follows through its cooler
    assert float(cold.outputs["coolant_temp_degc"]) > 20.2
    assert float(cold.outputs["trans_oil_temp_degc"]) > 20.0


def test_cold_transmission_oil(th, oil):
    """Cold oil: the open pack drags and the gearbox churns by powers of the
    viscosity ratio, the friction coefficients rise by
    the relative change per K x (T_ref - T)."""
    fx = _effects(th, oil, 90.0, 90.0, 0.0)
    r = _walther(th, "trans", 0.0) / _walther(th, "trans", th.trans_ref_temp_degc)
    assert fx.trans_viscosity_ratio == pytest.approx(r, rel=1e-9)
    assert r > 15.0
    assert fx.clutch_drag_factor == pytest.approx(r ** th.clutch_drag_viscosity_exponent, rel=1e-9)
    assert fx.churning_factor == pytest.approx(r ** th.churning_viscosity_exponent, rel=1e-9)
    assert fx.clutch_mu_factor == pytest.approx(
        1.0 + th.clutch_mu_change_per_k * (0.0 - th.trans_ref_temp_degc), rel=1e-12)
    assert fx.clutch_mu_factor > 1.05


def test_cold_oil_drags_the_open_clutch_harder():
    """The plant: the drag of the open K1 (input shaft 1 standing in 1st,
    the engine at idle) per rpm of slip, cold against warm."""
    def open_drag(temp):
        p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
        p.reset(sleeves=(1, 0, 0, 0), trans_oil_temp_degc=temp)
        p.step(1)
        return float(p.outputs["clutch1_torque_nm"]) / float(p.outputs["clutch1_slip_rpm"])

    th = Plant().params["thermal"]
    ratio = (lib.dct_walther_viscosity(th["trans_oil_viscosity_40c_mm2_s"],
                                       th["trans_oil_viscosity_100c_mm2_s"], 0.0)
             / lib.dct_walther_viscosity(th["trans_oil_viscosity_40c_mm2_s"],
                                         th["trans_oil_viscosity_100c_mm2_s"], 80.0))
    warm, cold = open_drag(80.0), open_drag(0.0)
    assert warm > 0.0
    # per rpm of slip (the idle speeds differ: cold idle rise); within 0.5 %:
    # the stick damping of the friction element adds its share to the drag
    assert cold / warm == pytest.approx(ratio ** th["clutch_drag_viscosity_exponent"], rel=5e-3)
    assert cold / warm > 3.0


def test_accessories_load_the_crank():
    warm = Plant()
    ac = Plant(overrides={"thermal": {"ac_on": 1}})
    warm.step(10000)
    ac.step(10000)
    th = warm.params["thermal"]
    w = float(warm.outputs["engine_speed_rpm"]) * math.pi / 30.0
    alternator = th["alternator_load_w"] / th["alternator_efficiency"] / max(w, 500 * math.pi / 30)
    assert float(warm.outputs["accessory_torque_nm"]) == pytest.approx(alternator, rel=1e-3)
    assert float(ac.outputs["accessory_torque_nm"]) == pytest.approx(
        float(warm.outputs["accessory_torque_nm"]) + th["ac_torque_nm"], rel=1e-3)
    # the idle governor holds the speed; the compressor costs fuel
    assert float(ac.outputs["engine_speed_rpm"]) == pytest.approx(
        float(warm.outputs["engine_speed_rpm"]), abs=5.0)
    assert float(ac.outputs["fuel_rate_lph"]) > float(warm.outputs["fuel_rate_lph"])


def test_bad_initial_temperature_is_one_line():
    with pytest.raises(ValueError, match="coolant_temp_degc"):
        Plant().reset(coolant_temp_degc=float("nan"))


# ------------------------------------------------------- the effects' resolution

def test_effects_are_taken_at_the_rounded_temperatures(th, oil):
    """thermal.effects_resolution_k (0.01 K): temperatures within half a step
    of the same multiple give the same effects to the bit, across a multiple
    they differ; at resolution 0 every temperature counts."""
    q = th.effects_resolution_k
    assert q == 0.01
    base = _effects(th, oil, 60.0, 60.0, 60.0)
    near = _effects(th, oil, 60.004, 60.004, 60.004)
    across = _effects(th, oil, 60.006, 60.006, 60.006)
    for name in ("engine_drag_factor", "trans_oil_viscosity_m2_s", "clutch_drag_factor",
                 "clutch_gap_change_mm", "idle_rise_rpm"):
        assert getattr(near, name) == getattr(base, name), name
        assert getattr(across, name) != getattr(base, name), name
    th.effects_resolution_k = 0.0
    assert _effects(th, oil, 60.004, 60.0, 60.0).idle_rise_rpm != base.idle_rise_rpm


def _cold_start(seconds):
    p = Plant()
    p.reset(coolant_temp_degc=20.0, engine_oil_temp_degc=20.0, trans_oil_temp_degc=20.0)
    p.inputs["accel_pedal_pct"] = 30.0
    p.step(int(round(seconds / p.step_s)))
    return p


def test_a_restored_state_steps_as_the_one_it_was_taken_from():
    """The step keeps the effects while the rounded temperatures stay (a cache
    keyed by them): a plant restored from a snapshot, whatever it held before,
    steps on to the same outputs, bit for bit, as the original; the
    temperatures rise through many multiples of the resolution meanwhile."""
    a = _cold_start(2.0)
    snap = a.snapshot()
    t0 = float(a.outputs["trans_oil_temp_degc"])
    a.step(4000)
    assert float(a.outputs["trans_oil_temp_degc"]) - t0 > 0.02
    b = _cold_start(0.5)              # a cache of other temperatures
    b.restore(snap)
    b.step(4000)
    assert np.array_equal(np.asarray(a.outputs.tolist()), np.asarray(b.outputs.tolist()))


def test_a_parameter_change_acts_at_the_next_step():
    """dct_plant_prepare (a fault, an XCP calibration write) computes the
    effects again at once, though the temperatures did not move."""
    p = Plant()
    p.reset()
    p.step(10)
    gap = float(p.outputs["clutch1_kiss_pressure_bar"])
    p.set_faults(pack_gap_offset_mm=[0.5, 0.0])
    p.step(1)
    assert float(p.outputs["clutch1_kiss_pressure_bar"]) > gap
