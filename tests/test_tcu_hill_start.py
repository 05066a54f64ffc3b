"""Hill start of the reference TCU (tcu_stub/logic.py) on a 20 % grade: the driver holds
the brake, lets it go, then presses the accelerator. The TCU reads RoadGrade and
BrakePedal and builds the holding torque on the launch clutch (grade force x tyre radius /
overall ratio x HILL_MARGIN, less the brake's estimated torque) as the brake is released,
with an engine torque request that carries it at idle; the car must not roll back more than
0.1 m. Run in the compiled loop (equal to the Python TCU: tests/test_offline_fast.py)."""

import numpy as np
import pytest

from plant.model import Plant
from tcu_stub import fast, logic

OUT = ["vehicle_speed_kmh", "engine_speed_rpm", "clutch1_torque_nm", "gear", "brake_pedal_pct"]
RELEASE_S = 3.0


def driver_for(release):
    def driver(t_s, outputs):
        if t_s < RELEASE_S:
            return 0.0, 60.0
        if release == "ramp" and t_s < RELEASE_S + 0.3:
            return 0.0, 60.0 * (RELEASE_S + 0.3 - t_s) / 0.3
        return (0.0, 0.0) if t_s < RELEASE_S + 1.0 else (40.0, 0.0)
    return driver


def run(release="ramp", grade_pct=20.0, calibration=None, duration_s=9.0):
    plant = Plant()
    plant.reset()
    plant.inputs["road_grade_pct"] = grade_pct
    tcu = fast.python_tcu(calibration)
    loop = fast.FastLoop(plant, driver_for(release), duration_s, record_every_s=0.002, tcu=tcu,
                         record_outputs=OUT)
    loop.step()
    rec = loop.recorded()
    v = rec["vehicle_speed_kmh"] / 3.6
    t = rec["time_s"]
    rec["x_m"] = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    return rec, tcu


def rollback_m(rec):
    """How far the car went back from where it stood when the brake began to let go."""
    after = rec["time_s"] >= RELEASE_S - 0.1
    x = rec["x_m"][after]
    return x[0] - x.min()


@pytest.mark.parametrize("release", ["ramp", "step"])
def test_hill_start_on_20_percent_rolls_back_less_than_0_1_m_and_pulls_away(release):
    rec, _ = run(release)
    assert rollback_m(rec) < 0.1, rollback_m(rec)
    held = (rec["time_s"] > 1.0) & (rec["time_s"] < RELEASE_S)          # settled on the brake
    assert np.abs(rec["vehicle_speed_kmh"][held]).max() < 0.05
    assert rec["engine_speed_rpm"].min() > 400.0                                       # no stall
    assert rec["vehicle_speed_kmh"][-1] > 12.0 and rec["gear"][-1] >= 1                # pulled away
    assert logic.PHASE_CODES["drive"] in set(rec["tcu_phase"].astype(int))


def test_on_the_brake_the_tcu_holds_no_grade_torque_and_builds_it_as_the_brake_lets_go():
    rec, tcu = run("ramp", duration_s=RELEASE_S + 0.9)
    on_brake = rec["time_s"] < RELEASE_S - 0.1
    assert rec["clutch1_torque_nm"][on_brake][-100:].max() < 10.0       # creep hold only (60 % holds the car)
    # after the release, before the pedal: the clutch carries the grade (about 62 Nm at the clutch)
    assert rec["clutch1_torque_nm"][-50:].mean() > 55.0
    assert tcu.hill_nm == pytest.approx(logic.HILL_MARGIN * logic.VEHICLE_WEIGHT_N * 20.0 / np.sqrt(10400.0)
                                        * logic.TYRE_RADIUS_M / logic.GEAR_OVERALL_RATIO[1])


def test_without_the_holding_torque_the_car_rolls_back():
    rec, _ = run("ramp", calibration={"HILL_MARGIN": 0.0}, duration_s=RELEASE_S + 1.0)
    assert rollback_m(rec) > 0.1


def test_downhill_needs_no_holding_torque_the_car_creeps_forward():
    rec, tcu = run("ramp", grade_pct=-20.0, duration_s=RELEASE_S + 0.9)
    assert tcu.hill_nm == 0.0
    assert rec["x_m"][-1] - rec["x_m"][rec["time_s"] < RELEASE_S][-1] > 0.0
