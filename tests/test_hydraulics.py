"""Clutch hydraulics: valve characteristic (the reference paper's Fig. 8),
current step responses, step-size independence, the orifice and chamber
laws, the line pressure supply, and out-of-range currents."""

import math

import numpy as np
import pytest

from plant import Plant, PlantError
from plant._dct_plant import ffi, lib
from plant.valve_report import steady_state_curve, step_response

FINE = {"solver": {"step_s": 0.5e-3 / 20}}  # the same model with a 20x smaller step


@pytest.fixture(scope="module")
def curve():
    return steady_state_curve(Plant())


def test_steady_state_pressure_is_monotonic_in_current(curve):
    currents, up, down, line = curve
    # rounding-level tolerance: the settled pressure may wobble by the
    # leakage balance, never by more than 1 mbar
    assert np.all(np.diff(up) >= -1e-3)
    assert np.all(np.diff(down) >= -1e-3)


def test_steady_state_pressure_spans_zero_to_line_pressure(curve):
    currents, up, down, line = curve
    assert up[0] < 0.1                       # 0 A: the clutch drains to the tank
    assert up[-1] == pytest.approx(line, rel=0.01)  # max current: the supply edge wide open
    # in between the valve is a proportional pressure regulator:
    # p = (k_f i - F_0) / A_fb, within 0.3 bar where the spool regulates
    v = Plant().params["hydraulics"]["valve"]
    a_fb = math.pi / 4 * (v["spool_diameter_mm"] ** 2 - v["rod_diameter_mm"] ** 2) * 1e-6
    mid = (currents > 0.25) & (currents < 0.85)
    expected = (v["solenoid_gain_n_per_a"] * currents[mid] - v["spring_preload_n"]) / a_fb / 1e5
    assert np.abs(up[mid] - expected).max() < 0.3


def test_step_fills_the_gap_before_the_pressure_rises():
    r = step_response(0.0, 0.6)
    clutch = Plant().params["clutch"][0]
    gap = clutch["pack_gap_mm"]
    kiss_bar = clutch["return_spring_n"] / clutch["piston_area_m2"] / 1e5
    closed_bar = kiss_bar + clutch["return_spring_n_per_m"] * gap * 1e-3 / clutch["piston_area_m2"] / 1e5
    stroking = (r.piston_mm > 0.05) & (r.piston_mm < 0.95 * gap)
    assert stroking.sum() * 0.5e-3 > 0.01          # the fill lasts (more than 10 ms)
    # while the piston strokes the pressure is the return spring's
    assert r.pressure_bar[stroking].max() < closed_bar + 0.1
    assert r.pressure_bar[stroking].min() > kiss_bar - 0.1
    # it rises only once the pack is closed
    t_rise = r.time_s[np.argmax(r.pressure_bar > closed_bar + 1.0)]
    t_closed = r.time_s[np.argmax(r.piston_mm >= gap)]
    assert t_rise >= t_closed


def test_step_response_reaches_90_percent_without_oscillating():
    r = step_response(0.0, 0.6)
    t90 = r.time_to(0.9)
    assert 0.02 < t90 < 0.15                       # tens of ms, fill included
    assert r.overshoot < 0.01
    # after 90 % the pressure only creeps towards its final value
    after = r.pressure_bar[r.time_s >= t90]
    assert np.all(np.diff(after) > -0.002 * r.final_bar)


STEPS = [(0.0, 0.2), (0.0, 0.6), (0.0, 1.0), (1.0, 0.0), (0.6, 0.0), (0.3, 0.7), (0.7, 0.3),
         (0.5, 0.55)]


@pytest.mark.parametrize("i_from,i_to", STEPS)
def test_step_at_half_a_millisecond_matches_a_20x_smaller_step(i_from, i_to):
    coarse = step_response(i_from, i_to)
    fine = step_response(i_from, i_to, overrides=FINE)
    scale = max(abs(coarse.final_bar), abs(coarse.start_bar))
    assert np.abs(coarse.pressure_bar - fine.pressure_bar).max() < 0.03 * scale


GRID = [0.0, 0.25, 0.5, 0.75, 1.0]


@pytest.mark.parametrize("i_from,i_to", [(a, b) for a in GRID for b in GRID if a != b])
def test_any_current_step_is_stable(i_from, i_to):
    """Every step between 0 and the maximum current settles without
    overshooting by more than 1 % of the line pressure (0.2 bar)."""
    r = step_response(i_from, i_to, duration_s=0.5)
    hi, lo = max(r.start_bar, r.final_bar), min(r.start_bar, r.final_bar)
    assert r.pressure_bar.max() < hi + 0.2 and r.pressure_bar.min() > lo - 0.2
    assert np.all(np.isfinite(r.pressure_bar))


# ------------------------------------------------------------------ laws


def test_orifice_is_laminar_near_zero_and_turbulent_at_high_reynolds():
    oil = ffi.new("dct_oil_params *", {"density_kg_m3": 850.0, "viscosity_m2_s": 1e-5,
                                      "bulk_modulus_pa": 1.5e9, "air_fraction": 0.0})

    def q(dp, opening=2e-4):
        return lib.dct_orifice_flow(oil, 0.61, 260.0, 8e-3, opening, dp, 0.0)

    # eq. 11: C_d -> 0 with Re, so Q ~ dp (laminar) near dp = 0: doubling a
    # small dp doubles the flow (within 1 %)
    assert q(20.0) / q(10.0) == pytest.approx(2.0, rel=0.01)
    # at high Re, C_d -> 0.61 and Q = 0.61 A sqrt(2 dp / rho) (density
    # ratio of eq. 13 at 10 bar mean: 1 + 10e5/1.5e9)
    dp = 20e5
    expect = 0.61 * 8e-3 * 2e-4 * math.sqrt(2 * dp / 850.0) * (1 + 10e5 / 1.5e9)
    assert q(dp) == pytest.approx(expect, rel=1e-6)
    reverse = lib.dct_orifice_flow(oil, 0.61, 260.0, 8e-3, 2e-4, 0.0, dp)
    assert reverse == pytest.approx(-q(dp), rel=1e-12)
    assert q(dp, opening=0.0) == 0.0 and q(dp, opening=-1e-4) == 0.0


def test_chamber_pressure_inverts_the_chamber_volume():
    p = Plant()
    clutch = ffi.new("dct_clutch_params *")
    oil = ffi.new("dct_oil_params *")
    from plant.params import fill_params
    cp = ffi.new("dct_params *")
    fill_params(ffi, cp, p.params)
    clutch[0] = cp.clutch[0]
    oil[0] = cp.hydraulics.oil
    vol = cp.hydraulics.chamber_volume_cm3[0] * 1e-6
    d = ffi.new("dct_chamber_derived *")
    lib.dct_chamber_prepare(oil, clutch, vol, d)
    for bar in (-0.5, 0.0, 0.5, 1.0, 1.58, 1.6, 1.62, 2.0, 5.0, 12.0, 20.0, 30.0):
        v = lib.dct_chamber_volume(oil, clutch, vol, bar * 1e5)
        assert lib.dct_chamber_pressure(d, v) == pytest.approx(bar * 1e5, abs=1.0)  # 10 ubar
    # the fill volume is the piston area times the gap
    kiss = clutch.return_spring_n / clutch.piston_area_m2
    closed = kiss + clutch.return_spring_n_per_m * clutch.pack_gap_mm * 1e-3 / clutch.piston_area_m2
    swept = lib.dct_chamber_volume(oil, clutch, vol, closed) - lib.dct_chamber_volume(oil, clutch, vol, kiss)
    assert swept == pytest.approx(clutch.piston_area_m2 * clutch.pack_gap_mm * 1e-3, rel=0.01)


def test_line_pressure_follows_its_map_through_a_lag():
    plant = Plant()
    supply = plant.params["hydraulics"]["supply"]
    plant.reset()
    assert float(plant.outputs["line_pressure_bar"]) == pytest.approx(supply["line"]["pressure_bar"][0])
    plant.inputs["line_solenoid_current_a"] = 1.0
    plant.step(int(round(supply["tau_s"] / plant.step_s)))
    start, end = supply["line"]["pressure_bar"][0], supply["line"]["pressure_bar"][-1]
    # one time constant: 63 % of the way (Euler at 0.25 ms: within 1 %)
    covered = (start - float(plant.outputs["line_pressure_bar"])) / (start - end)
    assert covered == pytest.approx(1 - math.exp(-1), abs=0.01)
    plant.inputs["solenoid_current1_a"] = 1.0
    plant.step(4000)
    # a clutch valve held wide open follows the line pressure
    assert float(plant.outputs["clutch1_pressure_bar"]) == pytest.approx(end, rel=0.01)


# ---------------------------------------------------------------- inputs


def test_out_of_range_currents_are_limited_and_counted():
    plant = Plant()
    plant.reset()
    imax = plant.params["hydraulics"]["valve"]["max_current_a"]
    plant.inputs["solenoid_current1_a"] = -0.5
    plant.inputs["solenoid_current2_a"] = 3.0 * imax
    plant.step(1)
    o = plant.outputs
    assert float(o["solenoid_current1_a"]) == 0.0
    assert float(o["solenoid_current2_a"]) == imax
    assert float(o["input_clamps"]) == 2.0
    plant.step(1)
    assert float(plant.outputs["input_clamps"]) == 4.0  # counted at every step they stay out
    assert np.all(np.isfinite(plant.state))


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_current_is_rejected_before_the_state(value):
    plant = Plant()
    plant.reset()
    before = plant.state.copy()
    plant.inputs["line_solenoid_current_a"] = value
    with pytest.raises(PlantError, match="line_solenoid_current_a"):
        plant.step(1)
    assert np.array_equal(plant.state, before)


def test_pressure_commanded_mode_bypasses_the_hydraulics():
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    plant.reset()
    plant.inputs["clutch1_pressure_bar"] = 12.0
    plant.inputs["solenoid_current1_a"] = 0.0
    plant.step(1)
    assert float(plant.outputs["clutch1_pressure_bar"]) == 12.0
    assert float(plant.outputs["clutch1_clamp_force_n"]) > 0.0
