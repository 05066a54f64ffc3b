"""dct-hil fit: plant parameters recovered from synthetic measurements made by the plant
with known parameters plus noise (CSV, MF4, a car's signal names through a mapping)."""

import json

import numpy as np
import pytest
from cli_errors import one_line_error

from dct_hil.cli import main
from dct_hil.studies.engine import Engine
from dct_hil.studies.fit import fit, parse_params, parse_signals, targets
from dct_hil.studies.measurement import load_mapping
from dct_hil.studies.runs import make_case, simulate
from plant.params import load_params
from plant.simulate import write_csv


@pytest.fixture(scope="module")
def engine():
    with Engine(workers=2) as e:
        yield e


def _record(case, duration, overrides, noise, seed):
    """A run of the plant with ``overrides`` and Gaussian noise on some outputs."""
    rec, _ = simulate(make_case(case, duration), overrides)
    rng = np.random.default_rng(seed)
    for name, sigma in noise.items():
        rec[name] = rec[name] + rng.normal(0.0, sigma, len(rec[name]))
    return rec


def _csv(path, rec, names=None):
    names = names or list(rec)
    write_csv(path, names, np.column_stack([rec[n] for n in names]))
    return path


@pytest.mark.slow
def test_coastdown_and_launch_recover_mass_drag_and_rolling_resistance(tmp_path, capsys):
    """The brief's case: a coastdown (plant/scenarios/coastdown.csv) and a full-throttle
    launch (0-100, 10 s) together, speed with 0.1 km/h noise: mass, Cd and rolling
    resistance from the car's values (1400 kg, 0.32, 0.009) to within 3 % of the truth."""
    truth = {"vehicle": {"mass_kg": 1520.0, "drag_coefficient": 0.30},
             "tyre": {"rolling_resistance": 0.0105}}
    noise = {"vehicle_speed_kmh": 0.1}
    coast = _csv(tmp_path / "coast.csv", _record("coastdown", None, truth, noise, 1))
    launch = _csv(tmp_path / "launch.csv", _record("0-100", 10.0, truth, noise, 2))
    out = tmp_path / "fit"
    code = main(["fit", f"{coast}@coastdown", f"{launch}@0-100", "--params",
                 "vehicle.mass_kg,vehicle.drag_coefficient,tyre.rolling_resistance",
                 "--workers", "2", "--out", str(out), "--no-progress"])
    text = capsys.readouterr().out
    assert code == 0, text
    result = json.loads((out / "fit.json").read_text())
    got = {p["key"]: p for p in result["parameters"]}
    for key, true in (("vehicle.mass_kg", 1520.0), ("vehicle.drag_coefficient", 0.30),
                      ("tyre.rolling_resistance", 0.0105)):
        assert got[key]["value"] == pytest.approx(true, rel=0.03), key
        assert 0 < got[key]["ci95"] < 0.03 * true, key     # an interval, and a tight one
        assert key in text
    assert "95 % interval" in text and "+-" in text
    for r in result["residual_rms"]:                      # down to the noise
        assert r["rms"] == pytest.approx(0.1, rel=0.2)
    assert (out / "fit_residuals.png").stat().st_size > 20_000
    # the fitted values as a parameter file the plant takes
    params = load_params(out / "fitted.toml")
    assert params["vehicle"]["mass_kg"] == pytest.approx(got["vehicle.mass_kg"]["value"])


@pytest.mark.slow
def test_clutch_friction_and_turbo_lag_from_an_mf4(tmp_path, engine):
    """launch-1st recorded as MF4 (engine speed with 5 rpm noise): K1's kinetic friction
    and the turbo lag from 0.12 / 0.35 s back to 0.105 / 0.5 s within 2 %."""
    from asammdf import MDF, Signal

    truth = {"clutch": [{"mu_kinetic": 0.105}, {}], "engine": {"tau_boost_s": 0.5}}
    rec = _record("launch-1st", None, truth, {"engine_speed_rpm": 5.0}, 3)
    mdf = MDF(version="4.10")
    mdf.append([Signal(rec[n], rec["time_s"], name=n) for n in
                ("engine_speed_rpm", "vehicle_speed_kmh", "clutch1_pressure_bar")])
    path = tmp_path / "launch.mf4"
    mdf.save(path, overwrite=True)
    keys = parse_params(["clutch[0].mu_kinetic", "engine.tau_boost_s"])
    signals = parse_signals(["engine_speed_rpm:5"])
    res = fit(keys, targets([f"{path}@launch-1st"], signals, load_mapping(None)), signals,
              engine=engine)
    assert res.success
    assert res.value[0] == pytest.approx(0.105, rel=0.02)
    assert res.value[1] == pytest.approx(0.5, rel=0.02)
    assert list(res.rms.values())[0] == pytest.approx(5.0, rel=0.2)


@pytest.mark.slow
def test_a_cars_signals_named_in_a_mapping(tmp_path, engine):
    """A car's log: its own names and units (speed in m/s), no case given: its pedals
    are replayed with the reference TCU in the loop; the mass comes back within 2 %."""
    rec = _record("0-100", 10.0, {"vehicle": {"mass_kg": 1580.0}},
                  {"vehicle_speed_kmh": 0.2}, 4)
    car = {"Zeit": rec["time_s"], "VehSpd": rec["vehicle_speed_kmh"] / 3.6,
           "AccPed": rec["accel_pedal_pct"], "BrkPed": rec["brake_pedal_pct"]}
    log = _csv(tmp_path / "car.csv", car)
    mapping = tmp_path / "car.toml"
    mapping.write_text('[measurement]\ntime = "Zeit"\n\n[channels]\n'
                       'vehicle_speed_kmh = { name = "VehSpd", scale = 3.6 }\n'
                       'accel_pedal_pct = "AccPed"\nbrake_pedal_pct = "BrkPed"\n')
    keys = parse_params(["vehicle.mass_kg"])
    signals = parse_signals(None)
    tg = targets([str(log)], signals, load_mapping(mapping))
    assert tg[0].case.tcu == "stub" and tg[0].case.kind == "scenario"
    res = fit(keys, tg, signals, engine=engine)
    assert res.value[0] == pytest.approx(1580.0, rel=0.02)




def test_bad_fit_input_is_one_line(tmp_path, capsys):
    meas = tmp_path / "m.csv"
    meas.write_text("time_s,engine_speed_rpm\n0,800\n0.01,810\n")
    line = one_line_error(capsys, ["fit", f"{meas}@coastdown", "--params", "vehicle.mass_kg"])
    assert "m.csv: no channel vehicle_speed_kmh (needed)" in line
    assert "time_s, engine_speed_rpm" in line
    line = one_line_error(capsys, ["fit", str(meas), "--params", "vehicle.mass_kg"])
    assert "vehicle_speed_kmh, accel_pedal_pct, brake_pedal_pct" in line
    mapping = tmp_path / "car.toml"
    mapping.write_text('[channels]\nvehicle_speed_kmh = "VehSpd"\n')
    line = one_line_error(capsys, ["fit", f"{meas}@coastdown", "--params", "vehicle.mass_kg",
                           "--mapping", str(mapping)])
    assert "no channel vehicle_speed_kmh (channel 'VehSpd')" in line
    line = one_line_error(capsys, ["fit", f"{meas}@coastdown", "--params", "vehicle.drag_coef"])
    assert "unknown parameter key 'vehicle.drag_coef'" in line
    assert "did you mean vehicle.drag_coefficient" in line
    line = one_line_error(capsys, ["fit", f"{meas}@coastdown", "--params", "tcu.LAUNCH_RPM_MAX"])
    assert "plant parameters" in line
    line = one_line_error(capsys, ["fit", str(tmp_path / "none.mf4"), "--params", "vehicle.mass_kg"])
    assert "none.mf4: no such measurement file" in line
