"""Powertrain roll on its mounts (plant/csrc/driveline.c).

  J_pt d2phi/dt2 = -k_m phi - k_s (|phi| - phi_s)+ sgn(phi) - c_m dphi/dt - 2 T
The half-shafts' torque 2 T rolls the engine and gearbox against the mounts;
the carrier turns with them in the half-shafts' twist; the mounts' torque
reaches the body.
"""

import numpy as np
import pytest

from plant import Plant


def stall_plant():
    """Standing on the full brake in 1st, the clutch slipping at a fixed
    pressure, the engine at full throttle: the half-shafts carry a steady
    torque (the clutch's sliding capacity through 1st)."""
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.reset(sleeves=(1, 0, 0, 0))
    return p


@pytest.mark.parametrize("pressure_bar", [2.5, 3.0, 3.5])
def test_steady_roll_carries_the_half_shafts_torque(pressure_bar):
    """In steady state the mounts carry the half-shafts' reaction: k_m d
    (+ the stop beyond phi_s) = -2 T, d = roll + body pitch (the mounts'
    deflection), within 0.1 % (what is left of the decaying roll after 4 s
    and the idle governor's ripple through the slipping clutch)."""
    p = stall_plant()
    p.inputs["brake_pedal_pct"] = 100.0
    p.inputs["accel_pedal_pct"] = 60.0
    p.inputs["clutch1_pressure_bar"] = pressure_bar
    p.step(8000)
    dl = p.params["driveline"]
    phi = float(p.state[p.state_names.index("driveline.roll_rad")]) + float(
        p.state[p.state_names.index("vehicle.pitch_rad")])
    t2 = 2.0 * float(p.outputs["halfshaft_torque_nm"])
    over = max(abs(phi) - dl["mount_roll_stop_rad"], 0.0)
    mount = dl["mount_roll_stiffness_nm_per_rad"] * phi + np.sign(phi) * dl[
        "mount_roll_stop_stiffness_nm_per_rad"] * over
    assert abs(t2) > 100.0
    assert mount == pytest.approx(-t2, rel=1e-3)


def test_energy_of_a_rolled_powertrain_rings_down():
    """Engine off, no pedal, level road, neutral: a powertrain rolled beyond
    its stop and let go swings out on its mounts; the stored energy (now with
    the roll's kinetic and the mounts' spring energy) never grows at the 10 ms
    output rate (tolerance: rounding, 1e-9 of it) and within a step by at
    most 1 %: explicit Euler adds (w h)^2 of a spring's energy at a
    turning point (tests/test_plant_system.py), and the roll on the stops is
    the stiffest spring in play: w = sqrt(445000 / 18) = 157 rad/s,
    (w h)^2 = 0.62 % per 0.5 ms step (measured 0.58 %)."""
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.reset(engine_on=0)
    for name in ("accel_pedal_pct", "brake_pedal_pct", "road_grade_pct"):
        p.inputs[name] = 0.0
    p.inputs["engine_on"] = 0.0
    p.state[p.state_names.index("driveline.roll_rad")] = 0.03
    energy = [p.energy()]
    for _ in range(4000):
        p.step(1)
        energy.append(p.energy())
    energy = np.array(energy)
    assert energy[-1] < 0.01 * energy[0]
    assert np.diff(energy[::20]).max() <= 1e-9 * energy[0]
    assert np.diff(energy).max() <= 1e-2 * energy[0]
