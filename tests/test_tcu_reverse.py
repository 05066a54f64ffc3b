"""Reverse and the selector lever in the reference TCU (tcu_stub/logic.py). SelectorLever
(VEH_Driver: 0 P, 1 R, 2 N, 3 D; absent: D): R at a standstill takes 1st out and engages R
on the 5-R sleeve's other side (K1), then creeps and launches backwards on K1 (TargetGear
-1); R while rolling forward faster than REVERSE_MAX_KMH is refused (neutral, clutches open)
until slow; N and P open both clutches without a torque request; D again from R: 1st. Run
in the compiled loop (equal to the Python TCU to the bit: tests/test_offline_fast.py)."""

import numpy as np
import pytest

from plant.driver import ScriptedDriver
from plant.maneuvers import get_maneuver, report
from plant.model import Plant
from tcu_stub import fast, logic
from tcu_stub.offline import sensors_from_plant

OUT = ["vehicle_speed_kmh", "sync3_gear", "sync1_gear", "clutch1_pressure_bar", "clutch2_pressure_bar", "gear",
       "distance_m", "selector_lever"]


def run(driver, duration_s, plant=None):
    plant = plant or Plant()
    tcu = logic.TcuLogic()
    loop = fast.FastLoop(plant, driver, duration_s, record_every_s=0.01, tcu=tcu, record_outputs=OUT)
    loop.step()
    rec = loop.recorded()
    v = rec["vehicle_speed_kmh"] / 3.6
    rec["x_m"] = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.01)])
    return rec, tcu


def open_packs(rec, window):
    """Both clutches below their kiss points (no clamp force; a pack drains slowly there)."""
    return all(rec[f"clutch{k + 1}_pressure_bar"][window].max() < logic.CLUTCH_KISS_BAR[k] + 0.05 for k in (0, 1))


def at(rec, t_s):
    return int(round(t_s / 0.01))


@pytest.fixture(scope="module")
def reverse_park():
    m = get_maneuver("reverse-park")
    plant = Plant()
    m.start(plant)
    rec, tcu = run(m.driver, m.duration_s, plant)
    return m, rec, tcu


def test_r_engages_on_the_5_r_sleeve_and_the_car_reverses_a_few_metres(reverse_park):
    m, rec, _ = reverse_park
    k = at(rec, 2.9)
    assert rec["sync3_gear"][k] == -1 and rec["gear"][k] == -1         # R on sleeve 5-R (its - side)
    assert rec["sync1_gear"][k] == 0                                   # 1st taken out
    assert rec["tcu_target_gear"][k] == -1
    back = rec["x_m"][at(rec, 9.9)] - rec["x_m"][at(rec, 1.0)]
    assert -5.0 < back < -1.5, back                                     # 2.9 m backwards on the creep torque
    assert rec["vehicle_speed_kmh"][at(rec, 3.0):at(rec, 7.0)].min() < -3.0
    fig = report(m, rec | {"shifts": []})
    assert fig["reverse_distance_m"] > 1.5


def test_p_opens_both_clutches_and_the_lock_holds(reverse_park):
    _, rec, tcu = reverse_park
    p = slice(at(rec, 10.5), at(rec, 15.9))
    assert rec["clutch1_pressure_bar"][p].max() < 0.5 and rec["clutch2_pressure_bar"][p].max() < 0.5
    assert (rec["tcu_target_gear"][p] == 0).all()
    assert np.abs(rec["vehicle_speed_kmh"][p]).max() < 0.1
    assert tcu.torque_request_nm is None


def test_r_while_rolling_forward_is_refused_until_slow_then_d_again_is_first():
    driver = ScriptedDriver([
        (0.0, 40.0, 0.0, "D"),      # away in D
        (5.0, 0.0, 0.0, "R"),       # R at speed: refused, neutral
        (7.0, 0.0, 30.0, "R"),      # brake: R once slow
        (12.0, 0.0, 0.0, "R"),      # creep backwards
        (15.0, 0.0, 30.0, "D"),     # D again: 1st
        (18.0, 0.0, 0.0, "D"),      # creep forwards
    ])
    rec, tcu = run(driver, 22.0)
    refused = slice(at(rec, 5.1), at(rec, 6.9))
    drained = slice(at(rec, 5.5), at(rec, 6.9))                      # the locked K2 drained
    assert rec["vehicle_speed_kmh"][refused].min() > logic.REVERSE_MAX_KMH
    assert (rec["tcu_target_gear"][refused] == 0).all()
    assert open_packs(rec, drained)
    assert (rec["sync3_gear"][refused] != -1).all()                    # R not engaged at speed
    engaged = np.flatnonzero(rec["sync3_gear"] == -1)
    assert len(engaged) and rec["vehicle_speed_kmh"][engaged[0]] < logic.REVERSE_MAX_KMH
    assert rec["vehicle_speed_kmh"][at(rec, 12.0):at(rec, 15.0)].min() < -2.0       # backwards
    end = slice(at(rec, 20.0), at(rec, 22.0) - 1)
    assert (rec["gear"][end] == 1).all() and (rec["tcu_target_gear"][end] == 1).all()
    assert rec["vehicle_speed_kmh"][end].min() > 3.0                                  # creeping forward
    assert not rec["tcu_active_faults"].any()


def test_n_opens_both_clutches_without_a_torque_request():
    driver = ScriptedDriver([(0.0, 30.0, 0.0, "D"), (4.0, 30.0, 0.0, "N"), (6.0, 0.0, 0.0, "N")])
    rec, tcu = run(driver, 8.0)
    n = slice(at(rec, 4.5), at(rec, 7.9))
    assert open_packs(rec, n)
    assert tcu.torque_request_nm is None and tcu.target_gear == 0


def test_without_a_selector_signal_the_tcu_drives_in_d():
    s = sensors_from_plant(Plant().outputs)
    s.pop("SelectorLever", None)
    tcu = logic.TcuLogic()
    tcu.step(0.0, s)
    assert tcu.selector == logic.SELECTOR_D and tcu.target_gear == 1
