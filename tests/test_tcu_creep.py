"""Creep of the reference TCU (tcu_stub/logic.py): at idle without the accelerator, the
brake released, the launch clutch carries the creep torque (CREEP_NM, ramped) and the car
rolls at idle speed in 1st; on the brake only CREEP_HOLD_NM (the clutch's slip power stays
small); released again, it creeps again; the pedal launches as before. Run in the compiled
loop (equal to the Python TCU to the bit: tests/test_offline_fast.py's lockstep)."""

import numpy as np
import pytest

from plant.model import Plant
from tcu_stub import fast, logic

OUT = ["vehicle_speed_kmh", "engine_speed_rpm", "clutch1_torque_nm", "clutch1_slip_rpm", "gear",
       "clutch1_pressure_bar"]


def creep_driver(t_s, outputs):
    """Brake 0-2 s, released 2-14 s (creep), brake 14-24 s (held at a stop), released 24-34 s,
    then a light pedal."""
    if t_s < 2.0 or 14.0 <= t_s < 24.0:
        return 0.0, 40.0
    return (20.0, 0.0) if t_s >= 34.0 else (0.0, 0.0)


def run(calibration=None, duration_s=40.0, reset=None):
    plant = Plant()
    plant.reset(**(reset or {}))
    tcu = fast.python_tcu(calibration)
    loop = fast.FastLoop(plant, creep_driver, duration_s, record_every_s=0.01, tcu=tcu, record_outputs=OUT)
    loop.step()
    return loop.recorded(), tcu


def window(rec, t0, t1):
    return (rec["time_s"] >= t0) & (rec["time_s"] < t1)


@pytest.fixture(scope="module")
def creep():
    return run()


def test_creep_rolls_the_car_at_a_few_kmh_in_first_without_the_pedal(creep):
    rec, _ = creep
    v = rec["vehicle_speed_kmh"][window(rec, 9.0, 14.0)]
    assert 5.0 < v.min() and v.max() < 7.0, (v.min(), v.max())      # 6.3 km/h: idle speed in 1st
    assert set(rec["gear"][window(rec, 3.0, 14.0)]) == {1}
    assert (rec["tcu_phase"][window(rec, 2.0, 14.0)] == logic.PHASE_CODES["standstill"]).all()
    # the creep torque ramps in: no step of the clutch torque as the brake lets go
    torque = rec["clutch1_torque_nm"][window(rec, 2.0, 3.0)]
    rate = (torque[10:] - torque[:-10]) / 0.1                       # Nm/s over 0.1 s
    assert rate.max() < 1.5 * logic.CREEP_RAMP_NM_PER_S, rate.max()


def test_on_the_brake_at_a_stop_the_clutch_slips_with_little_power_and_creeps_again_released(creep):
    rec, _ = creep
    held = window(rec, 18.0, 24.0)
    assert np.abs(rec["vehicle_speed_kmh"][held]).max() < 0.05
    power_w = rec["clutch1_torque_nm"][held] * rec["clutch1_slip_rpm"][held] * np.pi / 30.0
    # CREEP_HOLD_NM of friction (the adapted kiss point) and the open pack's drag (about 1.6 Nm at idle)
    # at 750 rpm of slip: about 380 W
    assert power_w.mean() < 450.0 and power_w.max() < 500.0, power_w.mean()
    assert power_w.mean() > 50.0                        # the pack is kept at its kiss point, not opened
    v = rec["vehicle_speed_kmh"][window(rec, 30.0, 34.0)]
    assert 5.0 < v.min() and v.max() < 7.0                # creeping again


def test_the_pedal_launches_from_creep_as_before(creep):
    rec, _ = creep
    assert rec["vehicle_speed_kmh"][-1] > 10.0
    assert logic.PHASE_CODES["drive"] in set(rec["tcu_phase"][window(rec, 34.0, 40.0)].astype(int))


def test_without_creep_torque_the_car_stands(creep):
    rec, _ = run({"CREEP_NM": 0.0, "CREEP_HOLD_NM": 0.0}, duration_s=14.0)
    assert np.abs(rec["vehicle_speed_kmh"]).max() < 0.5


def test_creep_speed_is_limited_by_the_fade_of_the_creep_torque():
    # a creep limit below idle speed in 1st: the torque fades out and the clutch slips
    rec, _ = run({"CREEP_MAX_KMH": 5.0}, duration_s=14.0)
    v = rec["vehicle_speed_kmh"][window(rec, 9.0, 14.0)]
    assert 3.0 < v.min() and v.max() < 5.0, (v.min(), v.max())
