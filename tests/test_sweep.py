"""dct-hil sweep: a sample of runs on a Dask LocalCluster and on a separately started
scheduler + worker, resume, failed runs recorded, bad input refused in one line.

The runs are the short open-loop scenarios (launch-1st 4.5 s, coastdown 60 s: tens of
milliseconds each), so the tests measure the machinery, not the plant."""

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pandas as pd
import pytest
from cli_errors import one_line_error

from dct_hil.studies import StudyError
from dct_hil.studies.engine import Engine
from dct_hil.studies.sweep import JOURNAL, load_spec, read_journal, run_sweep

SPEC_32 = """\
[sweep]
sampling = "grid"
cases = ["launch-1st", "coastdown"]

[[parameter]]
key = "vehicle.mass_kg"
range = [1200, 1760]
steps = 8

[[parameter]]
key = "clutch[0].mu_static"
values = [0.10, 0.12]
"""


@pytest.fixture(scope="module")
def engine():
    with Engine(workers=2) as e:
        yield e


def _write(tmp_path, text, name="spec.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


@pytest.mark.slow
def test_sweep_of_32_runs_on_the_local_cluster_then_resumed(tmp_path, engine):
    spec = load_spec(_write(tmp_path, SPEC_32))
    out = tmp_path / "out"
    res = run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res.runs, res.computed, res.skipped, res.failed) == (32, 32, 0, 0)
    runs = pd.read_parquet(out / "runs.parquet")
    assert len(runs) == 32 and set(runs["status"]) == {"ok"}
    assert list(runs.columns[:5]) == ["run_id", "point", "case", "vehicle.mass_kg",
                                      "clutch[0].mu_static"]
    assert runs["run_id"].is_unique
    # both workers took part
    assert runs["worker"].nunique() == 2
    csv = pd.read_csv(out / "runs.csv")
    assert len(csv) == 32 and np.allclose(csv["fuel_l"], runs["fuel_l"])
    # the figures follow the parameter: a heavier car coasts down more slowly
    coast = runs[(runs["case"] == "coastdown") & (runs["clutch[0].mu_static"] == 0.12)]
    coast = coast.sort_values("vehicle.mass_kg")
    assert np.all(np.diff(coast["final_speed_kmh"]) > 0)
    points = pd.read_parquet(out / "points.parquet")
    assert len(points) == 16 and "coastdown.final_speed_kmh" in points
    for case in ("launch-1st", "coastdown"):
        assert (out / f"figures_{case}.png").stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 32 and summary["failed"] == 0

    # resume: nothing left to compute
    res2 = run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res2.computed, res2.skipped) == (0, 32)

    # an interrupted sweep: the journal holds 11 finished runs and a torn last line
    lines = (out / JOURNAL).read_text().splitlines()
    (out / JOURNAL).write_text("\n".join(lines[:11]) + "\n" + lines[11][:40])
    kept = set(read_journal(out / JOURNAL))
    assert len(kept) == 11
    res3 = run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res3.computed, res3.skipped, res3.failed) == (21, 11, 0)
    assert len(read_journal(out / JOURNAL)) == 32        # the first record after the torn line kept
    again = pd.read_parquet(out / "runs.parquet").set_index("run_id")
    before = runs.set_index("run_id")
    assert np.allclose(again.loc[before.index, "fuel_l"], before["fuel_l"])

    # a grid extended by one value computes only the new points
    spec4 = load_spec(_write(tmp_path, SPEC_32.replace("range = [1200, 1760]\nsteps = 8",
                                                        "values = [1200, 1280, 1900]")))
    res4 = run_sweep(spec4, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res4.runs, res4.computed, res4.skipped) == (12, 4, 8)


@pytest.mark.slow
def test_a_failed_run_is_recorded_with_its_error(tmp_path, engine):
    spec = load_spec(_write(tmp_path, """\
        [sweep]
        cases = ["launch-1st"]
        [[parameter]]
        key = "solver.step_s"
        values = [0.0005, 0.005]
        [[parameter]]
        key = "vehicle.mass_kg"
        values = [1300, 1500]
        """))
    out = tmp_path / "out"
    res = run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res.runs, res.failed) == (4, 2)
    runs = pd.read_csv(out / "runs.csv")
    runs["error"] = runs["error"].astype(object).fillna("")
    bad = runs[runs["status"] == "failed"]
    assert set(bad["solver.step_s"]) == {0.005}
    for err in bad["error"]:
        assert "became" in err and "\n" not in err        # the plant's one-line PlantError
    assert (runs[runs["status"] == "ok"]["top_speed_kmh"] > 40).all()
    # a failed run is finished: kept on resume, computed again with --retry-failed
    assert run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None).computed == 0
    again = run_sweep(spec, out=out, engine=engine, progress=False, retry_failed=True,
                      log=lambda s: None)
    assert (again.computed, again.failed) == (2, 2)


@pytest.mark.slow
def test_tcu_calibration_and_maneuver_in_a_sweep(tmp_path, engine):
    """A TCU calibration value reaches the TCU: a lower full-pedal upshift speed makes
    the 0-100 slower; the shipped shift-map example runs (few points, cut short) and
    finds its Pareto front."""
    from dct_hil import studies
    from dct_hil.studies import sweep as sw

    example = os.path.join(os.path.dirname(studies.__file__), "examples", "shift_map.toml")
    spec = load_spec(example, duration_cap_s=40.0)
    assert [c.label for c in spec.cases] == ["wltc", "0-100"]
    assert spec.cases[0].duration_s == 40.0 and spec.cases[1].duration_s == 15.0
    assert len(sw.plan(spec)) == 14
    spec.parameters[0].range, spec.parameters[0].steps = (0.75, 1.0), 3
    out = tmp_path / "shift"
    res = run_sweep(spec, out=out, engine=engine, progress=False, log=lambda s: None)
    assert (res.runs, res.failed) == (6, 0)
    pts = res.point_df.sort_values("shift_line_factor")
    t100 = pts["0-100.zero_to_100_s"].to_numpy()
    assert t100[0] > t100[-1] + 0.3          # shifting up at 0.75 x 6300 rpm costs time
    assert np.isfinite(pts["wltc.fuel_l_per_100km"]).all()
    assert pts["pareto"].any()
    assert (out / "pareto.png").stat().st_size > 10_000


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask_cli():
    exe = os.path.join(os.path.dirname(sys.executable), "dask")
    return [exe] if os.path.exists(exe) else [sys.executable, "-m", "dask"]


def _stop(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


@pytest.mark.slow
def test_the_same_sweep_on_a_separate_scheduler_and_worker(tmp_path):
    """As a user with a cluster: `dask scheduler` and `dask worker` started on their own
    (loopback), `dct-hil sweep --scheduler` sends them the 32 runs."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ)
    log = open(tmp_path / "dask.log", "w")
    scheduler = subprocess.Popen(_dask_cli() + ["scheduler", "--host", "127.0.0.1", "--port",
                                                str(port), "--no-dashboard", "--dashboard-address",
                                                "127.0.0.1:0"],
                                 stdout=log, stderr=subprocess.STDOUT, env=env)
    worker = None
    try:
        worker = subprocess.Popen(_dask_cli() + ["worker", address, "--host", "127.0.0.1",
                                                 "--nworkers", "2", "--nthreads", "1",
                                                 "--no-dashboard"],
                                  stdout=log, stderr=subprocess.STDOUT, env=env,
                                  cwd=str(tmp_path))
        # both workers up before the sweep connects (the sweep itself waits for one;
        # on a loaded machine the second joined after it had counted them)
        from distributed import Client

        with Client(address, timeout=120) as client:
            client.wait_for_workers(2, timeout=120)
        spec = _write(tmp_path, SPEC_32)
        out = tmp_path / "out"
        cmd = [sys.executable, "-m", "dct_hil.cli", "sweep", str(spec), "--scheduler", address,
               "--out", str(out), "--connect-timeout", "60", "--no-plots"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr + open(tmp_path / "dask.log").read()[-3000:]
        assert f"Dask scheduler {address}: 2 workers" in done.stdout
        assert "runs: 32 (32 computed, 0 from the journal), 0 failed" in done.stdout
        runs = pd.read_parquet(out / "runs.parquet")
        assert len(runs) == 32 and set(runs["status"]) == {"ok"}
        assert runs["worker"].nunique() == 2
    finally:
        for p in (worker, scheduler):
            if p is not None:
                _stop(p)
        log.close()


# ------------------------------------------------------------------ bad input


@pytest.mark.slow
def test_bad_sweep_input_is_one_line(tmp_path, capsys):
    spec = _write(tmp_path, SPEC_32.replace('key = "vehicle.mass_kg"', 'key = "vehicle.mass_kgs"'))
    line = one_line_error(capsys, ["sweep", str(spec), "--out", str(tmp_path / "o")])
    assert "vehicle.mass_kgs" in line and "did you mean vehicle.mass_kg" in line

    spec = _write(tmp_path, SPEC_32.replace("range = [1200, 1760]", "range = [1200, 90000]"))
    line = one_line_error(capsys, ["sweep", str(spec), "--out", str(tmp_path / "o")])
    assert "vehicle.mass_kg = 90000" in line and "out of range [100.0, 40000.0]" in line
    assert "ranges.toml" in line

    spec = _write(tmp_path, SPEC_32.replace('key = "clutch[0].mu_static"',
                                            'key = "tcu.UPSHIFT_RPMS[4]"'))
    line = one_line_error(capsys, ["sweep", str(spec)])
    assert "tcu.UPSHIFT_RPMS[4]" in line and "did you mean tcu.UPSHIFT_RPM" in line

    spec = _write(tmp_path, SPEC_32.replace('"coastdown"', '"coast-down"'))
    line = one_line_error(capsys, ["sweep", str(spec)])
    assert "unknown scenario 'coast-down'" in line

    spec = _write(tmp_path, SPEC_32)
    t0 = time.monotonic()
    line = one_line_error(capsys, ["sweep", str(spec), "--out", str(tmp_path / "o"),
                           "--scheduler", f"tcp://127.0.0.1:{_free_port()}",
                           "--connect-timeout", "1"])
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:" in line
    assert time.monotonic() - t0 < 30

    line = one_line_error(capsys, ["sweep", str(tmp_path / "missing.toml")])
    assert "missing.toml" in line and "cannot read" in line


def test_keys_build_overrides_as_the_parameter_files_name_them():
    from dct_hil.studies.keys import Assignment, build, resolve

    over, cal = build([Assignment(resolve("clutch[1].mu_static"), 0.1),
                       Assignment(resolve("gearbox.ratio[2]"), 1.4),
                       Assignment(resolve("vehicle.mass_kg"), 1.1, relative=True),
                       Assignment(resolve("tcu.upshift_rpm[4]"), 5000.0),
                       Assignment(resolve("tcu.DOWNSHIFT_RPM"), 0.9, relative=True)])
    assert over["clutch"] == [{}, {"mu_static": 0.1}]
    assert over["gearbox"]["ratio"][2] == 1.4 and len(over["gearbox"]["ratio"]) == 7
    assert over["vehicle"]["mass_kg"] == pytest.approx(1540.0)
    assert cal["UPSHIFT_RPM"][4] == (100.0, 5000.0) and cal["UPSHIFT_RPM"][0] == (0.0, 1900.0)
    assert cal["DOWNSHIFT_RPM"][0] == (0.0, pytest.approx(945.0))
    with pytest.raises(StudyError, match="clutch has 2 elements"):
        resolve("clutch[2].mu_static")
    with pytest.raises(StudyError, match="point count"):
        resolve("engine.full_load.n")


def test_calibrated_tcu_leaves_the_shared_module_alone():
    from dct_hil.studies.tcu import calibrated_module, make_tcu
    from tcu_stub import logic

    tcu = make_tcu({"LAUNCH_RPM_MAX": 2500.0, "TYRE_RADIUS_M": 0.33})
    mod = calibrated_module({"LAUNCH_RPM_MAX": 2500.0, "TYRE_RADIUS_M": 0.33})
    assert type(tcu).__name__ == "TcuLogic"
    assert mod.LAUNCH_RPM_MAX == 2500.0 and logic.LAUNCH_RPM_MAX == 3400.0
    # values derived at import follow the calibration
    assert mod.RPM_PER_KMH == pytest.approx(logic.RPM_PER_KMH * 0.316 / 0.33)
