"""dct-hil command line: simulate, bench, and one-line user errors."""

import json
import os
import resource
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dct_hil import cli
from plant import simulate as plant_simulate
from plant._dct_plant import ffi

OUTPUTS = [name for name, _ in ffi.typeof("dct_outputs").fields]

TINY = """\
# initial: vehicle_speed_kmh=0, sleeve1_side=1
time_s,accel_pedal_pct,brake_pedal_pct
0,0,30
0.2,20,0
0.5,20,0
"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.csv"
    path.write_text(TINY)
    return str(path)


def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_user_error(code, err, *fragments):
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dct-hil: error: "), err
    for f in fragments:
        assert f in lines[0], err


# ----------------------------------------------------------------- simulate
def test_simulate_writes_all_outputs_every_10_ms(capsys, tiny, tmp_path):
    out_csv = tmp_path / "run.csv"
    code, out, err = run_cli(capsys, "simulate", "--scenario", tiny, "--out", out_csv)
    assert code == 0, err
    for word in ("simulated", "wall time", "real-time factor", str(out_csv), "km/h", "rpm", "clashes"):
        assert word in out
    header = out_csv.read_text().splitlines()[0].split(",")
    assert header == OUTPUTS and header[0] == "time_s"
    data = np.loadtxt(out_csv, delimiter=",", skiprows=1)
    assert data.shape == (51, len(OUTPUTS))
    np.testing.assert_allclose(data[:, 0], np.arange(51) * 0.01, atol=1e-9)
    assert np.isfinite(data).all()


def test_simulate_duration_holds_the_last_row(capsys, tiny, tmp_path):
    out_csv = tmp_path / "long.csv"
    code, _, err = run_cli(capsys, "simulate", "--scenario", tiny, "--duration", "0.8", "--out", out_csv)
    assert code == 0, err
    data = np.loadtxt(out_csv, delimiter=",", skiprows=1)
    assert data.shape[0] == 81
    assert data[-1, 0] == pytest.approx(0.8)


def test_simulate_without_out_writes_nothing(capsys, tiny, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, "simulate", "--scenario", tiny, "--duration", "0.05")
    assert code == 0, err
    assert "not written" in out
    assert list(tmp_path.iterdir()) == [tmp_path / "tiny.csv"]


def test_ctrl_c_exits_130_and_keeps_the_partial_csv(capsys, tiny, tmp_path, monkeypatch):
    from plant.model import Plant

    real_step = Plant.step
    calls = []

    def step(self, n=1):
        calls.append(n)
        if len(calls) == 10:
            raise KeyboardInterrupt
        real_step(self, n)

    monkeypatch.setattr(Plant, "step", step)
    out_csv = tmp_path / "partial.csv"
    # Plant.step is what the Python loop calls (the compiled loop's own test:
    # tests/test_offline_fast.py)
    code, _, err = run_cli(capsys, "simulate", "--scenario", tiny, "--out", out_csv,
                           "--tcu-impl", "python")
    assert code == 130
    assert len(err.splitlines()) == 1 and "interrupted" in err and str(out_csv) in err
    data = np.loadtxt(out_csv, delimiter=",", skiprows=1, ndmin=2)
    assert 1 <= data.shape[0] < 51
    assert out_csv.read_text().startswith("time_s,")


# -------------------------------------------------------------------- bench
def test_bench_writes_the_json_report(capsys, tiny, tmp_path):
    report_path = tmp_path / "bench.json"
    # 3000 steps > the 1000-step scenario: it restarts from a reset
    code, out, err = run_cli(capsys, "bench", "--steps", 3000, "--scenario", tiny, "--json", report_path)
    assert code == 0, err
    for word in ("median", "p99.9", "real-time factor", "steps/s"):
        assert word in out
    report = json.loads(report_path.read_text())
    for key in ("steps", "scenario", "median_us", "p90_us", "p99_us", "p99_9_us", "max_us",
                "mean_us", "real_time_factor", "steps_per_s", "machine"):
        assert key in report, key
    for key in ("cpu", "nproc", "python", "compiler", "compiler_flags", "git_commit", "date"):
        assert key in report["machine"], key
    assert report["steps"] == 3000 and report["scenario"] == "tiny"
    assert 0 < report["median_us"] <= report["p90_us"] <= report["p99_us"] <= report["max_us"]
    assert report["real_time_factor"] == pytest.approx(500.0 / report["mean_us"])
    from plant._build import COMPILE_ARGS

    assert report["machine"]["compiler_flags"] == " ".join(COMPILE_ARGS)   # the flags of this build


def test_bench_writes_out_bench_json_by_default(capsys, tiny, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, "bench", "--steps", 200, "--scenario", tiny)
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "bench.json").read_text())
    assert report["steps"] == 200
    assert not (tmp_path / "bench.json").exists()
    assert "out/bench.json" in out


def test_bench_check_fails_above_the_target(capsys, tiny, tmp_path, monkeypatch):
    monkeypatch.setattr(plant_simulate, "TARGET_MEDIAN_US", 0.0)
    code, _, err = run_cli(capsys, "bench", "--steps", 200, "--scenario", tiny,
                           "--json", tmp_path / "b.json", "--check")
    assert code == 1
    assert len(err.splitlines()) == 1 and "above" in err


def test_bench_check_passes_below_the_target(capsys, tiny, tmp_path, monkeypatch):
    monkeypatch.setattr(plant_simulate, "TARGET_MEDIAN_US", 1e9)
    code, out, err = run_cli(capsys, "bench", "--steps", 200, "--scenario", tiny,
                             "--json", tmp_path / "b.json", "--check")
    assert code == 0, err
    assert "passed" in out


def test_bench_repeat_keeps_every_run_and_reports_the_lowest_median(capsys, tiny, tmp_path):
    report_path = tmp_path / "b.json"
    code, out, err = run_cli(capsys, "bench", "--steps", 500, "--scenario", tiny,
                             "--json", report_path, "--repeat", 3)
    assert code == 0, err
    report = json.loads(report_path.read_text())
    medians = [r["median_us"] for r in report["runs"]]
    assert report["repeat"] == 3 and len(medians) == 3
    assert report["median_us"] == min(medians) == medians[report["best_run"] - 1]
    assert report["runs"][report["best_run"] - 1]["max_us"] == report["max_us"]
    assert "medians" in out


# -------------------------------------------------------------- user errors
def bad_scenario(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("time_s,accel_pedal_pct\n0,1\n1,oops\n")
    return str(path)


def bad_toml(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[engine\ninertia_kgm2 = \n")
    return str(path)


def out_of_range_toml(tmp_path):
    path = tmp_path / "range.toml"
    path.write_text("[engine]\ninertia_kgm2 = -3.0\n")
    return str(path)


USER_ERRORS = {
    "no command": (lambda t, s: [], ["choose a command"]),
    "unknown command": (lambda t, s: ["fly"], ["fly"]),
    "missing scenario option": (lambda t, s: ["simulate"], ["--scenario"]),
    "unknown scenario": (lambda t, s: ["simulate", "--scenario", "nope"], ["nope", "launch-1st"]),
    "bad scenario file": (lambda t, s: ["simulate", "--scenario", bad_scenario(t)], ["bad.csv:3:", "oops"]),
    "negative duration": (lambda t, s: ["simulate", "--scenario", s, "--duration", "-1"], ["--duration"]),
    "non-numeric duration": (lambda t, s: ["simulate", "--scenario", s, "--duration", "abc"], ["--duration"]),
    "out folder is a file": (lambda t, s: ["simulate", "--scenario", s, "--out", str(t / "tiny.csv" / "x.csv")], ["cannot create folder"]),
    "out is a dir": (lambda t, s: ["simulate", "--scenario", s, "--out", str(t)], ["directory"]),
    "missing params file": (lambda t, s: ["simulate", "--scenario", s, "--params", str(t / "no.toml")], ["no.toml"]),
    "bad params syntax": (lambda t, s: ["simulate", "--scenario", s, "--params", bad_toml(t)], ["bad.toml"]),
    "param out of range": (lambda t, s: ["simulate", "--scenario", s, "--params", out_of_range_toml(t)], ["inertia_kgm2"]),
    "zero steps": (lambda t, s: ["bench", "--steps", "0"], ["--steps"]),
    "negative steps": (lambda t, s: ["bench", "--steps", "-5"], ["--steps"]),
    "zero repeats": (lambda t, s: ["bench", "--repeat", "0"], ["--repeat"]),
    "too many repeats": (lambda t, s: ["bench", "--repeat", "50"], ["--repeat"]),
    "fractional steps": (lambda t, s: ["bench", "--steps", "1.5"], ["--steps"]),
    "json folder is a file": (lambda t, s: ["bench", "--steps", "10", "--json", str(t / "tiny.csv" / "b.json")], ["cannot create folder"]),
    "bench unknown scenario": (lambda t, s: ["bench", "--steps", "10", "--scenario", "nope",
                                             "--json", str(t / "b.json")], ["nope"]),
}


@pytest.mark.parametrize("case", sorted(USER_ERRORS))
def test_user_errors_are_one_line_and_exit_2(capsys, tiny, tmp_path, case):
    make_argv, fragments = USER_ERRORS[case]
    code, _, err = run_cli(capsys, *make_argv(tmp_path, tiny))
    assert_user_error(code, err, *fragments)


def test_plant_error_is_a_user_error(capsys, tiny, tmp_path, monkeypatch):
    from plant.model import Plant, PlantError

    def step(self, n=1):
        raise PlantError("state engine.speed_rad_s became nan at t=0.1000 s")

    monkeypatch.setattr(Plant, "step", step)
    out_csv = tmp_path / "x.csv"
    code, _, err = run_cli(capsys, "simulate", "--scenario", tiny, "--out", out_csv,
                           "--tcu-impl", "python")
    assert_user_error(code, err, "engine.speed_rad_s became nan", str(out_csv))


@pytest.mark.slow
def _cpu_s(pid):
    """CPU seconds a process has used so far (Linux: /proc/PID/stat)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_sigint_exits_130_with_a_partial_csv(tmp_path):
    # A real Ctrl-C on a real process, once its run has started: the signal comes
    # when the process has used a second of CPU more than its start-up (the imports,
    # measured first), a measure of its progress that a loaded machine does not move
    # the way it moves wall time (a wall-clock wait sent the signal during the
    # imports on one run and after the run's end on another).
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", "import dct_hil.cli, plant.model, plant.simulate"],
                   check=True, timeout=120)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    startup_cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    out_csv = tmp_path / "long.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "dct_hil.cli", "simulate", "--scenario", "coastdown",
         "--duration", "3600", "--out", str(out_csv)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # Ctrl-C as a terminal delivers it: a suite started in the background of a
        # shell without job control (nohup, a CI runner) passes SIGINT on ignored,
        # and Python then installs no KeyboardInterrupt for it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while proc.poll() is None and _cpu_s(proc.pid) < startup_cpu_s + 1.0:
            assert time.monotonic() < deadline, "the run did not get going in 120 s"
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.splitlines() == [err.strip()] and "interrupted" in err, err
    lines = out_csv.read_text().splitlines()
    assert lines[0].startswith("time_s,") and len(lines) > 2


def test_module_entry_point_reports_one_line(tmp_path):
    # the real process: no traceback, exit status 2
    r = subprocess.run(
        [sys.executable, "-m", "dct_hil.cli", "simulate", "--scenario", "nope"],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.splitlines() == [r.stderr.strip()] and r.stderr.startswith("dct-hil: error: ")


def test_help_exits_0():
    r = subprocess.run([sys.executable, "-m", "dct_hil.cli", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0
    assert "simulate" in r.stdout and "bench" in r.stdout


def test_simulate_creates_the_output_folder(capsys, tiny, tmp_path):
    out = tmp_path / "new" / "deeper" / "run.csv"
    code, _, err = run_cli(capsys, "simulate", "--scenario", tiny, "--out", out)
    assert code == 0, err
    assert out.read_text().startswith("time_s,")
