"""Clutch kiss point and its thermal expansion (thermal.c, plant.c, piston.c).

The pack gap the piston closes grows with the transmission oil temperature:
  gap(T) = gap + (alpha_housing - alpha_plates) L (T - T_ref)
and the kiss pressure, the chamber pressure at which the pack closes,
  p_kiss = (F0 + k_r gap(T)) / A
with it. The outputs clutch1/2_kiss_pressure_bar give p_kiss as the plant
uses it now (temperature and the kiss-drift fault pack_gap_offset_mm), and
clutch1/2_friction_coeff the kinetic coefficient with its temperature factor.

Tolerances: the laws are evaluated in the same double arithmetic by the
plant and by the test, in a different order: 1e-9 relative.
"""

import pytest

from plant import Plant

REL = 1e-9
T_HOT, T_COLD = 110.0, -10.0


def plant_at(trans_oil_degc, pressure_commanded=1, **faults):
    p = Plant(overrides={"hydraulics": {"pressure_commanded": pressure_commanded}})
    if faults:
        p.set_faults(**faults)
    p.reset(coolant_temp_degc=90.0, engine_oil_temp_degc=90.0, trans_oil_temp_degc=trans_oil_degc)
    return p


def gap_law_mm(plant, k, temp_degc):
    th = plant.params["thermal"]
    return plant.params["clutch"][k]["pack_gap_mm"] + th["clutch_gap_expansion_per_k"] * \
        th["clutch_gap_length_mm"] * (temp_degc - th["trans_ref_temp_degc"])


def kiss_law_bar(plant, k, gap_mm):
    c = plant.params["clutch"][k]
    return (c["return_spring_n"] + c["return_spring_n_per_m"] * gap_mm * 1e-3) / c["piston_area_m2"] / 1e5


def test_parameters_give_a_gap_that_grows_with_temperature():
    th = Plant().params["thermal"]
    assert th["clutch_gap_expansion_per_k"] > 0.0      # aluminium around steel
    assert th["clutch_gap_length_mm"] > 0.0


@pytest.mark.parametrize("temp", [T_COLD, 80.0, T_HOT])
def test_gap_of_the_piston_law_follows_the_expansion_law(temp):
    """The gap the piston closes, read from the piston as the plant runs it
    (pressure-commanded, 10 bar: clamped; the pack is an elastic end stop
    beyond the gap: gap = x - F_clamp / k_pack), at three oil temperatures,
    against gap(T). The oil's temperature hardly moves in the 1 ms run."""
    p = plant_at(temp)
    p.inputs["clutch1_pressure_bar"] = 10.0
    p.inputs["clutch2_pressure_bar"] = 10.0
    p.step(2)
    t_now = float(p.outputs["trans_oil_temp_degc"])
    assert t_now == pytest.approx(temp, abs=1e-3)
    for k in range(2):
        x_mm = float(p.outputs[f"piston{k + 1}_position_mm"])
        f_n = float(p.outputs[f"clutch{k + 1}_clamp_force_n"])
        assert f_n > 0.0
        gap = x_mm - f_n / p.params["clutch"][k]["pack_stiffness_n_per_m"] * 1e3
        # the state is read after the step: the law at the temperature the step started from
        assert gap == pytest.approx(gap_law_mm(p, k, temp), rel=1e-6)


def test_gap_at_two_temperatures_against_the_formula():
    """Hot minus cold: the gap grows by (alpha_h - alpha_p) L (T_hot - T_cold)
    (0.040 mm over these 120 K with the default parameters)."""
    hot, cold = plant_at(T_HOT), plant_at(T_COLD)
    th = hot.params["thermal"]
    expected = th["clutch_gap_expansion_per_k"] * th["clutch_gap_length_mm"] * (T_HOT - T_COLD)
    for k in range(2):
        gaps = []
        for p in (hot, cold):
            bar = float(p.outputs[f"clutch{k + 1}_kiss_pressure_bar"])
            c = p.params["clutch"][k]
            gaps.append((bar * 1e5 * c["piston_area_m2"] - c["return_spring_n"]) /
                        c["return_spring_n_per_m"] * 1e3)
        assert gaps[0] - gaps[1] == pytest.approx(expected, rel=1e-6)
        assert gaps[0] > gaps[1]


@pytest.mark.parametrize("temp", [T_COLD, 80.0, T_HOT])
def test_kiss_pressure_output_is_the_law(temp):
    p = plant_at(temp)
    for k in range(2):
        assert float(p.outputs[f"clutch{k + 1}_kiss_pressure_bar"]) == pytest.approx(
            kiss_law_bar(p, k, gap_law_mm(p, k, temp)), rel=REL)


def test_kiss_pressure_moves_with_temperature_and_with_the_drift_fault():
    """Hot oil: a higher kiss pressure than cold (by k_r dgap / A); the
    kiss-drift fault adds its offset to the gap on top of the temperature's."""
    hot, cold = plant_at(T_HOT), plant_at(T_COLD)
    for k in range(2):
        c = hot.params["clutch"][k]
        d_gap_m = (gap_law_mm(hot, k, T_HOT) - gap_law_mm(hot, k, T_COLD)) * 1e-3
        rise = float(hot.outputs[f"clutch{k + 1}_kiss_pressure_bar"]) - \
            float(cold.outputs[f"clutch{k + 1}_kiss_pressure_bar"])
        assert rise == pytest.approx(c["return_spring_n_per_m"] * d_gap_m / c["piston_area_m2"] / 1e5,
                                     rel=1e-6)
        assert rise > 0.0
    drift = plant_at(T_HOT, pack_gap_offset_mm=[0.5, 0.0])
    assert float(drift.outputs["clutch1_kiss_pressure_bar"]) == pytest.approx(
        kiss_law_bar(drift, 0, gap_law_mm(drift, 0, T_HOT) + 0.5), rel=REL)
    assert float(drift.outputs["clutch2_kiss_pressure_bar"]) == pytest.approx(
        float(hot.outputs["clutch2_kiss_pressure_bar"]), rel=REL)


def test_hydraulics_fill_the_temperature_gap():
    """With the hydraulics, the chamber law follows the gap too: the same oil
    volume, just enough to close the pack at the reference temperature (plus
    0.01 cm3), clamps it when cold (smaller gap), not when hot (larger)."""
    ref = plant_at(80.0, pressure_commanded=0)
    closed = {}
    for label, temp in (("cold", T_COLD), ("ref", 80.0), ("hot", T_HOT)):
        p = plant_at(temp, pressure_commanded=0)
        names = p.state_names
        # the volume that closes the pack at the reference gap: the derived chamber law
        v = float(ref._p.derived.hydraulics.chamber[0].closed_m3) + 1e-8
        p.state[names.index("hydraulics.clutch_oil_m3[0]")] = v
        p.update_outputs()
        closed[label] = float(p.outputs["clutch1_clamp_force_n"])
    assert closed["hot"] == 0.0
    assert closed["ref"] > 0.0
    assert closed["cold"] > closed["ref"]


def test_friction_coefficient_output_follows_temperature_and_fade():
    for temp in (T_COLD, 80.0, T_HOT):
        p = plant_at(temp)
        th = p.params["thermal"]
        factor = 1.0 + th["clutch_mu_change_per_k"] * (temp - th["trans_ref_temp_degc"])
        for k in range(2):
            assert float(p.outputs[f"clutch{k + 1}_friction_coeff"]) == pytest.approx(
                p.params["clutch"][k]["mu_kinetic"] * factor, rel=REL)
    faded = plant_at(80.0, friction_loss=[0.0, 0.25])
    assert float(faded.outputs["clutch2_friction_coeff"]) == pytest.approx(
        0.75 * faded.params["clutch"][1]["mu_kinetic"], rel=REL)


def test_open_pack_drag_output():
    """The open K1 with the engine idling and input shaft 1 held in 1st at
    standstill: the drag output is the viscous law at this slip (warm oil)."""
    p = plant_at(80.0)
    p.reset(sleeves=(1, 0, 0, 0))
    p.step(2000)
    c = p.params["clutch"][0]
    slip = float(p.outputs["clutch1_slip_rpm"]) * 3.141592653589793 / 30.0
    fx = 1.0  # warm: no thermal factor (within the 1 s the oil warms by far less than 0.1 K)
    assert float(p.outputs["clutch1_drag_torque_nm"]) == pytest.approx(
        c["drag_nms_per_rad"] * fx * slip, rel=2e-3)
    assert float(p.outputs["clutch1_drag_torque_nm"]) > 0.5
