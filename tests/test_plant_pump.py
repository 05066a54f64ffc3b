"""The transmission's oil pump on the crank (plant/csrc/plant.c).

The 02E's gear pump turns with the engine and delivers its displacement
every revolution against the line pressure (the regulator spills what the
clutches do not take): it takes T = p_line V / (2 pi eta) from the crank, and
all of that power ends as heat in the transmission oil.
"""

import math

import pytest

from plant import Plant


def pump_law_nm(plant):
    s = plant.params["hydraulics"]["supply"]
    return float(plant.outputs["line_pressure_bar"]) * 1e5 * s["pump_displacement_cm3"] * 1e-6 / (
        2.0 * math.pi * s["pump_efficiency"])


@pytest.mark.parametrize("line_current_a", [0.0, 0.5, 1.0])
def test_pump_torque_follows_the_line_pressure(line_current_a):
    """At idle, line pressure 20 / 12.5 / 5 bar: the pump's torque is the law
    (1e-6: the smoothed sign at 750 rpm, 78 rad/s over 5 rad/s, is 1 to that)."""
    p = Plant()
    p.inputs["line_solenoid_current_a"] = line_current_a
    p.step(4000)
    assert float(p.outputs["trans_pump_torque_nm"]) == pytest.approx(pump_law_nm(p), rel=1e-6)
    assert float(p.outputs["trans_pump_torque_nm"]) > 1.0


def test_pump_heats_the_transmission_oil():
    """Standing at idle, clutches open: the transmission takes the pump's
    power and the open packs' drag (and the loose gears'); with the pump
    removed its heat input drops by the pump's power, T w (to 1 %: the drag
    terms are the same in both runs)."""
    runs = {}
    for v in (11.0, 0.0):
        p = Plant(overrides={"hydraulics": {"supply": {"pump_displacement_cm3": v}}})
        p.step(4000)
        runs[v] = (float(p.outputs["trans_heat_in_w"]), float(p.outputs["trans_pump_torque_nm"]),
                   float(p.outputs["engine_speed_rpm"]) * math.pi / 30.0)
    heat_with, torque, w = runs[11.0]
    assert runs[0.0][1] == 0.0
    assert heat_with - runs[0.0][0] == pytest.approx(torque * w, rel=0.01)
