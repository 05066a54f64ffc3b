"""Driver, maneuvers, report figures, plots and the plant's `gear` output."""

import numpy as np
import pytest

from plant.driver import CarData, ScriptedDriver, SpeedTrackingDriver
from plant.maneuvers import Maneuver, get_maneuver, load_wltc, report, run_driver
from plant.model import Plant
from plant.plots import write_plots

RAMPS_T_S = [0.0, 5.0, 15.0, 25.0, 35.0, 40.0]
RAMPS_KMH = [40.0, 40.0, 60.0, 60.0, 40.0, 40.0]


def third_gear_plant(speed_kmh=40.0):
    """The simplest gear strategy: 3rd engaged, K1 held closed at 20 bar."""
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.inputs[()] = p.default_inputs
    p.reset(vehicle_speed_kmh=speed_kmh, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    p.inputs["clutch1_pressure_bar"] = 20.0
    return p


def test_speed_tracking_driver_follows_ramps_in_third():
    p = third_gear_plant()
    d = SpeedTrackingDriver(RAMPS_T_S, RAMPS_KMH)
    rec = run_driver(p, d, 40.0)
    t = rec["time_s"] - rec["time_s"][0]
    err = np.interp(t, RAMPS_T_S, RAMPS_KMH) - rec["vehicle_speed_kmh"]
    assert np.sqrt(np.mean(err ** 2)) <= 1.5
    # it used both pedals: throttle up the ramp, brake down it
    assert rec["accel_pedal_pct"].max() > 5.0
    assert rec["brake_pedal_pct"][(t > 26) & (t < 34)].max() > 0.5


def test_gear_output_follows_the_torque_carrying_clutch():
    p = third_gear_plant()
    rec = run_driver(p, SpeedTrackingDriver(RAMPS_T_S, RAMPS_KMH), 20.0)
    driving = np.abs(rec["clutch1_torque_nm"]) > 5.0
    assert driving.sum() > 100
    assert np.all(rec["gear"][driving] == 3.0)
    # neutral: no gear engaged, both clutches open
    q = Plant()
    q.inputs[()] = q.default_inputs
    q.reset(vehicle_speed_kmh=0.0)
    q.step(500)
    assert float(q.outputs["gear"]) == 0.0


def test_gear_output_holds_the_shaft_that_carried_the_torque_last():
    """Both clutches open (a coast downshift, standstill): the gear of the input
    shaft whose clutch carried the torque last; an open pack's drag does not count."""
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.inputs[()] = p.default_inputs
    p.reset(vehicle_speed_kmh=40.0, sleeves=(-1, -1, 0, 0), clutch_locked=(1, 0))  # 3rd on K1, 4th on K2
    assert float(p.outputs["gear"]) == 3.0

    def phase(n):
        gears, open_drag_nm = set(), 0.0
        for _ in range(n):
            p.step(1)
            gears.add(float(p.outputs["gear"]))
            open_drag_nm = max(open_drag_nm, abs(float(p.outputs["clutch1_torque_nm"])))
        return gears, open_drag_nm

    p.inputs["clutch1_pressure_bar"] = 20.0
    assert phase(400)[0] == {3.0}
    p.inputs["clutch1_pressure_bar"] = 0.0                  # both open: 3rd held
    assert phase(2000)[0] == {3.0}
    p.inputs["clutch2_pressure_bar"] = 20.0                 # K2 takes the drive: 4th
    assert phase(2000)[0] == {4.0}
    p.inputs["clutch2_pressure_bar"] = 0.0                  # both open again: 4th held,
    gears, k1_drag_nm = phase(2000)                          # though K1's drag exceeds 2 Nm
    assert gears == {4.0} and k1_drag_nm > 2.0
    # after a reset that locked no clutch: no gear until a clutch carries torque
    q = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    q.inputs[()] = q.default_inputs
    q.reset(vehicle_speed_kmh=0.0, sleeves=(1, 0, 0, 0))
    q.step(200)
    assert float(q.outputs["gear"]) == 0.0
    q.inputs["clutch1_pressure_bar"] = 3.0
    q.step(400)
    assert float(q.outputs["gear"]) == 1.0


def test_speed_tracking_driver_holds_brake_at_standstill():
    d = SpeedTrackingDriver([0.0, 10.0], [0.0, 0.0], hold_brake_pct=25.0)
    assert d(1.0, {"vehicle_speed_kmh": 0.0, "engine_speed_rpm": 750.0}) == (0.0, 25.0)


def test_speed_tracking_driver_rejects_bad_trace():
    with pytest.raises(ValueError, match="strictly increasing"):
        SpeedTrackingDriver([0.0, 0.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="same length"):
        SpeedTrackingDriver([0.0, 1.0], [1.0])


def test_scripted_driver_reproduces_its_table():
    table = [(0.0, 0.0, 30.0), (1.0, 100.0, 0.0), (5.0, 0.0, 40.0)]
    step = ScriptedDriver(table)
    assert step(0.0, {}) == (0.0, 30.0)
    assert step(0.99, {}) == (0.0, 30.0)
    assert step(1.0, {}) == (100.0, 0.0)
    assert step(4.0, {}) == (100.0, 0.0)
    assert step(9.0, {}) == (0.0, 40.0)
    lin = ScriptedDriver(table, mode="linear")
    assert lin(0.5, {}) == pytest.approx((50.0, 15.0))
    assert lin(3.0, {}) == pytest.approx((50.0, 20.0))
    assert lin(9.0, {}) == (0.0, 40.0)
    with pytest.raises(ValueError, match="within 0..100"):
        ScriptedDriver([(0.0, 120.0, 0.0)])
    with pytest.raises(ValueError, match="mode"):
        ScriptedDriver(table, mode="cubic")


def test_wltc_class3b_trace():
    t, v = load_wltc()
    assert len(t) == 1801
    assert np.all(np.diff(t) == 1.0)
    assert v.max() == pytest.approx(131.3)
    assert np.sum(v) / 3.6 / 1000.0 == pytest.approx(23.27, abs=0.01)   # km at 1 Hz
    assert v[0] == 0.0 and v[-1] == 0.0


def test_named_maneuvers():
    for name, lo, hi in (("paper-cycle", 60, 80), ("wltc", 1800, 1800), ("0-100", 30, 200)):
        m = get_maneuver(name)
        assert lo <= m.duration_s <= hi
        assert callable(m.driver)
    with pytest.raises(ValueError, match="unknown maneuver"):
        get_maneuver("nurburgring")


def test_report_on_synthetic_data():
    t = np.arange(0.0, 20.01, 0.01)
    pedal = np.where(t >= 1.0, 100.0, 0.0)
    speed = np.clip((t - 1.0) * 12.5, 0.0, 150.0)       # 100 km/h at 9 s after launch
    dist = np.cumsum(speed / 3.6) * 0.01
    fuel = dist / 1000.0 * 0.08                          # 8 l/100 km
    rec = {"time_s": t, "vehicle_speed_kmh": speed, "accel_pedal_pct": pedal,
           "distance_m": dist, "fuel_l": fuel, "tcu_phase": ["x"] * len(t), "shifts": []}
    fig = report("0-100", rec)
    assert fig["zero_to_100_s"] == pytest.approx(8.0, abs=0.02)
    assert fig["top_speed_kmh"] == pytest.approx(150.0)
    m = Maneuver("track", SpeedTrackingDriver([0.0, 20.0], [0.0, 0.0]), 20.0,
                 ("rms_speed_error_kmh", "fuel_l_per_100km", "distance_km"))
    rec2 = dict(rec, vehicle_speed_kmh=np.full_like(t, 2.0))
    fig2 = report(m, rec2)
    assert fig2["rms_speed_error_kmh"] == pytest.approx(2.0)
    assert fig2["fuel_l_per_100km"] == pytest.approx(8.0)
    with pytest.raises(ValueError, match="no 'fuel_l'"):
        report(m, {"time_s": t, "vehicle_speed_kmh": speed})


def test_car_data_from_the_shipped_parameters():
    c = CarData.from_toml()
    assert c.mass_kg == 1400.0
    assert c.brake_torque_max_nm == pytest.approx(4800.0)


def test_plots_are_written(tmp_path):
    p = third_gear_plant()
    rec = run_driver(p, SpeedTrackingDriver(RAMPS_T_S, RAMPS_KMH), 5.0)
    rec["tcu_target_gear"] = np.full_like(rec["time_s"], 3.0)
    paths = write_plots(rec, tmp_path / "plots", "ramps in 3rd")
    assert paths
    for path in paths:
        data = open(path, "rb").read()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    with pytest.raises(ValueError, match="vehicle_speed_kmh"):
        write_plots({"time_s": [0.0, 1.0]}, tmp_path, "x")
