"""Selector lever and parking lock (plant/csrc/wheel.c, input selector_lever).

The lever (0 P, 1 R, 2 N, 3 D) is a plant input whose default is D; it is
limited to P..D and passed through to the output selector_lever. In P the
parking lock holds the driven (front) wheels as a brake would, with its own
capacity, but only below park_lock_max_speed_kmh (above it the pawl
ratchets). R, N and D change nothing in the plant's physics.
"""

import math

import numpy as np
import pytest

from plant import Plant
from plant._dct_plant import lib

P, R, N, D = lib.DCT_SELECTOR_P, lib.DCT_SELECTOR_R, lib.DCT_SELECTOR_N, lib.DCT_SELECTOR_D


def pressure_plant():
    return Plant(overrides={"hydraulics": {"pressure_commanded": 1}})


def test_selector_codes_and_default_is_drive():
    assert (P, R, N, D) == (0, 1, 2, 3)
    plant = Plant()
    assert plant.inputs["selector_lever"] == D
    assert plant.default_inputs["selector_lever"] == D
    plant.step(1)
    assert plant.outputs["selector_lever"] == D
    assert plant.outputs["park_lock_engaged"] == 0.0


@pytest.mark.parametrize("given, applied, clamps", [(-1.0, P, 1), (7.0, D, 1), (1.4, R, 0),
                                                    (1.6, N, 0), (0.0, P, 0)])
def test_selector_is_limited_to_its_positions_and_passed_through(given, applied, clamps):
    plant = pressure_plant()
    plant.inputs["selector_lever"] = given
    plant.step(1)
    assert plant.outputs["selector_lever"] == applied
    assert plant.outputs["input_clamps"] == clamps


def test_park_holds_the_car_on_a_10_percent_grade_without_brake():
    """10 % grade, lever in P, no brake, engine idling in neutral: the pawl
    holds the front wheels; the car settles on the compliance of the lock
    element (brake stick stiffness), the tyres and the suspension, a few mm
    (holding torque per front wheel about 220 N m over 30 kN m/rad: 7 mrad,
    2.3 mm at the tyre radius, plus about 2 mm of tyre deflection), and then
    moves less than 1 mm in 10 s."""
    plant = pressure_plant()
    plant.reset()
    plant.inputs["selector_lever"] = P
    plant.inputs["road_grade_pct"] = 10.0
    plant.step(2000)
    assert plant.outputs["park_lock_engaged"] == 1.0
    x0 = float(plant.outputs["distance_m"])
    assert abs(x0) < 8e-3
    xs = []
    for _ in range(1000):
        plant.step(20)
        xs.append(float(plant.outputs["distance_m"]))
    assert np.abs(np.array(xs) - x0).max() < 1e-3
    assert abs(float(plant.outputs["vehicle_speed_kmh"])) < 0.01


def test_without_park_the_car_rolls_back_on_the_grade():
    """The same in N: nothing holds the car; after 3 s it rolls back at
    more than 5 km/h (the grade alone gives about 0.98 m/s2)."""
    plant = pressure_plant()
    plant.reset()
    plant.inputs["selector_lever"] = N
    plant.inputs["road_grade_pct"] = 10.0
    plant.step(6000)
    assert float(plant.outputs["vehicle_speed_kmh"]) < -5.0


def test_park_does_not_lock_at_20_kmh():
    """Coasting at 20 km/h in neutral, lever moved to P: the pawl ratchets
    (above park_lock_max_speed_kmh = 4 km/h) and the car coasts exactly as
    in N."""
    runs = {}
    for lever in (N, P):
        plant = pressure_plant()
        plant.reset(vehicle_speed_kmh=20.0)
        plant.inputs["selector_lever"] = lever
        engaged = 0.0
        for _ in range(100):
            plant.step(20)
            engaged = max(engaged, float(plant.outputs["park_lock_engaged"]))
        runs[lever] = (float(plant.outputs["vehicle_speed_kmh"]), engaged)
    assert runs[P][1] == 0.0
    assert runs[P][0] > 18.0
    assert runs[P][0] == runs[N][0]


def test_park_engages_once_slow_and_stops_the_car():
    """Lever in P while rolling at 3 km/h (below the pawl's 4 km/h): the lock
    engages at once and stops the wheels within 0.15 s (below 3 rpm, 25 rpm at 3 km/h: what is left is the lock element's and tyres' compliance) (3400 N m at the
    front axle: about 7 m/s2, the front tyres sliding); the body then rocks on
    the tyres' longitudinal compliance and suspension (about 3 Hz) and is at
    rest (below 0.05 km/h) within 6 s, a few cm from where the lock caught."""
    plant = pressure_plant()
    plant.reset(vehicle_speed_kmh=3.0)
    plant.inputs["selector_lever"] = P
    plant.step(1)
    assert plant.outputs["park_lock_engaged"] == 1.0
    plant.step(299)
    assert abs(float(plant.outputs["wheel_speed_fl_rpm"])) < 3.0  # 25 rpm at 3 km/h
    plant.step(11700)
    assert plant.outputs["park_lock_engaged"] == 1.0
    assert abs(float(plant.outputs["vehicle_speed_kmh"])) < 0.05
    assert abs(float(plant.outputs["distance_m"])) < 0.1


def test_park_capacity_is_the_parameter():
    """Pushed by the engine in 1st with the clutch closed, the lever in P:
    the lock slips once the wheel torque exceeds its capacity. With the
    capacity cut to 100 N m per wheel, full throttle drives the car through
    the lock; with the default it holds (the drive torque, about 280 N m x
    3.462 x 4.118 = 4000 N m at the axle, exceeds 2 x 1700 N m, but the
    engine cannot keep full torque at the stalling speed: the test looks at
    the small capacity only)."""
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 1},
                             "front_wheel": {"park_lock_torque_nm": 100.0}})
    plant.reset(sleeves=(1, 0, 0, 0))
    plant.inputs["selector_lever"] = P
    plant.inputs["clutch1_pressure_bar"] = 3.0
    plant.inputs["accel_pedal_pct"] = 30.0
    plant.step(4000)
    assert float(plant.outputs["vehicle_speed_kmh"]) > 1.0


@pytest.mark.parametrize("lever", [R, N])
def test_r_n_d_make_no_difference_to_the_physics(lever):
    """A launch in 1st with the lever in R or N gives exactly the outputs of
    the same run in D (the plant has no use for the lever but the lock)."""
    def launch(lv):
        plant = pressure_plant()
        plant.reset(sleeves=(1, 0, 0, 0))
        plant.inputs["selector_lever"] = lv
        plant.inputs["accel_pedal_pct"] = 40.0
        plant.inputs["clutch1_pressure_bar"] = 6.0
        plant.step(4000)
        out = plant.output_values.copy()
        return out
    a, b = launch(D), launch(lever)
    names = Plant.output_names
    differ = [n for i, n in enumerate(names) if not (a[i] == b[i] or (math.isnan(a[i]) and math.isnan(b[i])))]
    assert differ == ["selector_lever"]
