"""The stub TCU closing the loop with the default plant, in-process through the CAN codec."""

import numpy as np
import pytest

from plant.model import Plant
from tcu_stub import logic
from tcu_stub.logic import TcuLogic
from tcu_stub.offline import run_offline, sensors_from_plant

PEDAL_START_S = 1.0


def _full_throttle(t_s, outputs):
    return (100.0 if t_s >= PEDAL_START_S else 0.0), 0.0


@pytest.fixture(scope="module")
def full_load_run():
    return run_offline(Plant(), _full_throttle, 12.0)


def test_full_throttle_launch_reaches_100_kmh_shifting_up(full_load_run):
    r = full_load_run
    v = r["vehicle_speed_kmh"]
    assert v.max() > 100.0
    assert r["engine_speed_rpm"][r["time_s"] > PEDAL_START_S].min() > 600.0  # no stall
    ups = [(a, b) for _, a, b in r["shifts"]]
    assert ups[:2] == [(1, 2), (2, 3)]
    assert r["gear_clashes"][-1] == 0
    t100 = r["time_s"][np.argmax(v >= 100.0)] - PEDAL_START_S
    assert 6.9 * 0.9 < t100 < 6.9 * 1.1   # the published 0-100 km/h time of the car


def test_full_load_upshifts_keep_pulling(full_load_run):
    r = full_load_run
    shifting = np.array([p.startswith("upshift") for p in r["tcu_phase"]])
    assert shifting.any()
    assert r["vehicle_accel_mps2"][shifting].min() > -1.0


def test_brake_to_standstill_downshifts_to_first_and_holds_k1_at_its_kiss_point():
    def driver(t_s, outputs):
        if t_s < 6.0:
            return _full_throttle(t_s, outputs)
        return 0.0, 40.0

    tcu = TcuLogic()
    r = run_offline(Plant(), driver, 16.0, tcu=tcu)
    downs = [(a, b) for t, a, b in r["shifts"] if t > 6.0]
    assert downs and all(b == a - 1 for a, b in downs)
    assert downs[-1][1] == 1
    end = r["time_s"] > 15.0
    assert r["vehicle_speed_kmh"][end].max() < 0.5
    assert tcu.gear == 1 and tcu.phase == "standstill"
    # on the brake only the creep hold torque: K1 just past its kiss point, K2 open
    hold_bar = logic.CLUTCH_KISS_BAR[0] + logic.CREEP_HOLD_NM / logic.CLUTCH_NM_PER_BAR[0]
    assert np.abs(r["clutch1_pressure_bar"][end] - hold_bar).max() < 0.1
    assert r["clutch2_pressure_bar"][end].max() < 0.5
    assert 650.0 < r["engine_speed_rpm"][end].min() and r["engine_speed_rpm"][end].max() < 900.0
    assert r["gear_clashes"][-1] == 0


def test_braking_downshifts_blip_the_engine_without_a_deceleration_jerk():
    # a coast downshift opens both clutches and raises the engine to the lower
    # gear's shaft with a torque request; pulling it up with the on-coming
    # clutch instead costs the car its momentum (a jerk of 2.5 m/s2 into 1st)
    def driver(t_s, outputs):
        if t_s < 6.0:
            return _full_throttle(t_s, outputs)
        return 0.0, 40.0

    r = run_offline(Plant(), driver, 12.0, record_every_s=0.002)
    t, v, a = r["time_s"], r["vehicle_speed_kmh"], r["vehicle_accel_mps2"]
    phase = np.array(r["tcu_phase"])
    braking = (t > 7.0) & (v > 8.0)
    shifting = braking & np.char.startswith(phase.astype(str), "downshift")
    assert shifting.any()
    baseline = float(np.median(a[braking]))
    assert baseline < -3.0
    assert a[shifting].min() > baseline - 1.0, (a[shifting].min(), baseline)
    blip = braking & (phase == "downshift_inertia")
    assert r["engine_torque_nm"][blip].max() > 30.0          # the engine pushed itself up
    assert r["gear_clashes"][-1] == 0


def test_stale_plant_messages_open_both_clutches_then_drive_on():
    tcu = TcuLogic()
    r = run_offline(Plant(), _full_throttle, 8.0, tcu=tcu, stale_fn=lambda t: 5.0 < t < 5.5)
    t = r["time_s"]
    stale = (t > 5.1) & (t < 5.5)
    assert all(p == "stale" for p, s in zip(r["tcu_phase"], stale) if s)
    assert not r["solenoid_current1_a"][stale].any() and not r["solenoid_current2_a"][stale].any()
    assert r["clutch1_pressure_bar"][stale & (t > 5.3)].max() < 2.0
    assert r["clutch2_pressure_bar"][stale & (t > 5.3)].max() < 2.0
    # messages back: the TCU re-engages and the car pulls again
    assert tcu.phase == "drive"
    assert r["vehicle_accel_mps2"][t > 6.5].min() > 1.0
    assert r["gear_clashes"][-1] == 0


def test_kick_down_shifts_down_and_pulls_harder():
    def driver(t_s, outputs):
        return (30.0 if t_s < 15.0 else 100.0), 0.0

    r = run_offline(Plant(), driver, 17.0)
    later = [(a, b) for t, a, b in r["shifts"] if t >= 15.0]
    assert later and later[0][1] == later[0][0] - 1
    t = r["time_s"]
    before = r["vehicle_accel_mps2"][(t > 14.0) & (t < 15.0)].mean()
    after = r["vehicle_accel_mps2"][(t > 16.0) & (t < 17.0)].mean()
    assert after > before + 1.0
    assert r["gear_clashes"][-1] == 0


def test_half_load_launch_shifts_up_early_and_stops_on_brake():
    def driver(t_s, outputs):
        return (50.0, 0.0) if t_s < 12.0 else (0.0, 40.0)

    tcu = TcuLogic()
    r = run_offline(Plant(), driver, 25.0, tcu=tcu)
    ups = [a for t, a, b in r["shifts"] if b == a + 1]
    assert len(ups) >= 3
    assert r["engine_speed_rpm"].max() < 4000.0
    assert r["vehicle_speed_kmh"][-1] < 0.5 and tcu.gear == 1 and tcu.phase == "standstill"
    assert r["engine_speed_rpm"][r["time_s"] > 0.5].min() > 600.0
    assert r["gear_clashes"][-1] == 0


def test_stale_flag_gives_zero_currents_at_once():
    plant = Plant()
    tcu = TcuLogic()
    sensors = sensors_from_plant(plant.outputs)
    sensors["stale"] = True
    cmd = tcu.step(0.0, sensors)
    assert cmd["SolenoidCurrent1"] == 0.0 and cmd["SolenoidCurrent2"] == 0.0
    assert tcu.phase == "stale"


def test_bad_duration_is_rejected():
    with pytest.raises(ValueError, match="duration_s"):
        run_offline(Plant(), _full_throttle, 0.0)
