"""dct-hil simulate with the TCU stub: the maneuvers, pedal-only scenarios, --plot, --tcu."""

import re

import numpy as np
import pytest

from dct_hil import cli
from plant._dct_plant import ffi

OUTPUTS = [name for name, _ in ffi.typeof("dct_outputs").fields]

PEDALS_ONLY = """\
# pedals and grade only: the stub drives the clutches and forks
time_s,accel_pedal_pct,brake_pedal_pct,road_grade_pct
0,0,30,0
0.5,60,0,0
3.0,60,0,2
4.0,60,0,2
"""


def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def load_csv(path):
    header = path.read_text().splitlines()[0].split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return header, {name: data[:, k] for k, name in enumerate(header)}


def figure(out, name):
    m = re.search(rf"{name} = ([0-9.]+)", out)
    assert m, out
    return float(m.group(1))


def stops_after_moving(speed_kmh, moving_kmh=5.0, stopped_kmh=0.5):
    """How many times the car comes to a stop (below stopped_kmh) after moving."""
    stops, moving = 0, False
    for v in speed_kmh:
        if not moving and v > moving_kmh:
            moving = True
        elif moving and v < stopped_kmh:
            moving = False
            stops += 1
    return stops


@pytest.fixture
def pedals_only(tmp_path):
    path = tmp_path / "pedals.csv"
    path.write_text(PEDALS_ONLY)
    return str(path)


def test_0_100_reports_the_time_and_writes_the_tcu_columns(capsys, tmp_path):
    out_csv = tmp_path / "0-100.csv"
    # 9 s covers the launch at 1 s and the pass through 100 km/h
    code, out, err = run_cli(capsys, "simulate", "--scenario", "0-100", "--duration", "9",
                             "--out", out_csv)
    assert code == 0, err
    assert figure(out, "zero_to_100_s") == pytest.approx(6.9, rel=0.10)
    assert "top_speed_kmh" in out and figure(out, "gear_clashes") == 0
    header, rec = load_csv(out_csv)
    assert header[:len(OUTPUTS)] == OUTPUTS
    for name in ("gear", "tcu_target_gear", "accel_pedal_pct"):
        assert name in header
    np.testing.assert_allclose(np.diff(rec["time_s"]), 0.01, atol=1e-9)
    assert rec["time_s"][-1] == pytest.approx(9.0)
    assert rec["accel_pedal_pct"].max() == pytest.approx(100.0)
    assert rec["gear"].max() >= 2 and rec["tcu_target_gear"].max() >= 2


@pytest.mark.slow
def test_paper_cycle_plots_no_clashes_and_two_stops(capsys, tmp_path):
    out_csv = tmp_path / "paper" / "paper-cycle.csv"
    code, out, err = run_cli(capsys, "simulate", "--scenario", "paper-cycle", "--plot",
                             "--out", out_csv)
    assert code == 0, err
    assert figure(out, "gear_clashes") == 0
    assert figure(out, "shifts") > 0
    pngs = re.findall(r"^plot\s+(\S+\.png)$", out, flags=re.M)
    assert pngs
    for p in pngs:
        path = tmp_path / "paper" / p.rsplit("/", 1)[-1]
        assert str(path) == p and path.stat().st_size > 0
    _, rec = load_csv(out_csv)
    assert stops_after_moving(rec["vehicle_speed_kmh"]) == 2
    assert rec["gear_clashes"][-1] == 0
    assert rec["engine_speed_rpm"].min() > 400   # no stall


def test_pedal_only_scenario_runs_with_the_stub_by_default(capsys, pedals_only, tmp_path):
    out_csv = tmp_path / "run.csv"
    code, out, err = run_cli(capsys, "simulate", "--scenario", pedals_only, "--out", out_csv)
    assert code == 0, err
    assert re.search(r"^tcu\s+stub", out, flags=re.M), out
    header, rec = load_csv(out_csv)
    assert header == OUTPUTS
    assert rec["time_s"][-1] == pytest.approx(4.0)
    assert rec["vehicle_speed_kmh"][-1] > 10.0       # the stub launched the car
    assert rec["gear"].max() >= 1
    assert rec["gear_clashes"][-1] == 0


def test_pedal_only_scenario_with_tcu_none_plays_as_scripted(capsys, pedals_only, tmp_path):
    out_csv = tmp_path / "run.csv"
    code, out, err = run_cli(capsys, "simulate", "--scenario", pedals_only, "--tcu", "none",
                             "--out", out_csv)
    assert code == 0, err
    assert re.search(r"^tcu\s+none", out, flags=re.M), out
    _, rec = load_csv(out_csv)
    assert abs(rec["vehicle_speed_kmh"]).max() < 1.0   # no clutch closed, no gear: no drive


def test_plot_without_out_goes_to_out_name(capsys, pedals_only, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, "simulate", "--scenario", pedals_only, "--duration", "1",
                             "--plot")
    assert code == 0, err
    pngs = re.findall(r"^plot\s+(\S+\.png)$", out, flags=re.M)
    assert pngs
    for p in pngs:
        assert p.startswith("out/pedals/") and (tmp_path / p).stat().st_size > 0


BAD = {
    "stub with scripted clutches": (["--scenario", "launch-1st", "--tcu", "stub"],
                                    ["--tcu stub", "solenoid_current1_a", "fork_force1_n"]),
    "maneuver without tcu": (["--scenario", "0-100", "--tcu", "none"], ["--tcu none", "0-100"]),
    "maneuver of no length": (["--scenario", "paper-cycle", "--duration", "0"], ["--duration"]),
    "unknown tcu": (["--scenario", "0-100", "--tcu", "real"], ["--tcu", "real"]),
    "unknown name lists maneuvers": (["--scenario", "nope"], ["nope", "paper-cycle", "launch-1st"]),
    "plot of one sample": (["--scenario", "coastdown", "--duration", "0", "--plot"], ["--plot"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_combinations_are_one_line_errors(capsys, case, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv, fragments = BAD[case]
    code, out, err = run_cli(capsys, "simulate", *argv)
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: "), err
    for f in fragments:
        assert f in lines[0], err
