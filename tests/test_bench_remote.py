"""A bench that stays up between tests, driven from another process: the
plant put back at rest while the loop runs (reset_plant), the reference TCU's
ignition cycled (a fresh TCU), Bench.reset() between tests, and the HiL
suite (tests/hil) through pytest --bench-url against `dct-hil serve --tcu
reference --control-tcp` in another process, with a token."""

import socket
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from dct_hil.bench import Bench, BenchError

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "remote-bench-token-1"


@pytest.fixture
def bench():
    b = Bench.start()
    yield b
    b.stop()


@pytest.mark.slow
def test_reset_plant_puts_the_car_at_rest_and_time_goes_on(bench):
    bench.set("accel_pedal_pct", 40)
    bench.wait_until("gear == 2", timeout_s=10)
    before = bench.read_many(["time_s", "vehicle_speed_kmh"])
    assert before["vehicle_speed_kmh"] > 10
    bench.set("accel_pedal_pct", 0)
    t = bench._request("reset_plant")["time_s"]
    assert t >= before["time_s"]                      # plant time never goes back
    after = bench.read_many(["time_s", "vehicle_speed_kmh", "engine_speed_rpm"])
    # at rest: the TCU (still the old one) may have moved off again by a few ms
    assert abs(after["vehicle_speed_kmh"]) < 1.0
    assert 500 < after["engine_speed_rpm"] < 1200                      # idling
    assert after["time_s"] >= t


@pytest.mark.slow
def test_a_stalled_engine_runs_again_after_reset_plant(bench):
    bench.set("engine_on", 0)
    bench.wait_until("engine_speed_rpm < 50", timeout_s=5)
    bench.set("engine_on", 1)
    bench.sleep(0.5)
    assert bench.read("engine_speed_rpm") < 50, "a stopped engine stays off until a reset"
    bench._request("reset_plant")
    bench.sleep(0.2)
    assert bench.read("engine_speed_rpm") > 500


@pytest.mark.slow
def test_bench_reset_clears_what_the_tcu_latched(bench):
    bench.set("accel_pedal_pct", 30)
    bench.wait_until("gear == 2", timeout_s=10)
    bench.inject("hydraulics.line_pressure_loss", loss=0.8)
    bench.wait_until("TCU_Status.LimpHome == 1", timeout_s=3)
    assert bench.tcu_status()["dtcs"]
    t = bench.reset()
    status = bench.tcu_status()
    assert status["LimpHome"] == 0 and status["InhibitedGears"] == 0 and status["dtcs"] == []
    assert bench.faults() == []
    v = bench.read_many(["vehicle_speed_kmh", "gear", "accel_pedal_pct"])
    assert abs(v["vehicle_speed_kmh"]) < 1.0 and v["gear"] <= 1 and v["accel_pedal_pct"] == 0
    assert bench._tcu.restarts == 1
    bench.set("accel_pedal_pct", 30)                      # and it drives again as a fresh one
    assert bench.wait_until("gear == 2", timeout_s=10) > t


def _param_of(values, name):
    """params.clutch[0].mu_static -> values["clutch"][0]["mu_static"]"""
    v = values
    for part in name.split(".")[1:]:
        key, _, index = part.partition("[")
        v = v[key]
        if index:
            v = v[int(index.rstrip("]"))]
    return v


def test_online_parameters_read_as_loaded(bench):
    from plant.params import load_params

    names = _writable_params()
    assert len(names) > 40
    values = bench.read_many(names)
    loaded = load_params()
    assert values == {n: float(_param_of(loaded, n)) for n in names}
    with pytest.raises(BenchError, match="'params.engine.no_such_field' is no online parameter"):
        bench.read("params.engine.no_such_field")


def _writable_params():
    from rt_loop import _rt_loop
    from rt_loop.measure.stimulus import writable_of_regions
    from rt_loop.measure.xcp import a2l

    regions = a2l.calibration_regions(_rt_loop.ffi, _rt_loop.lib)
    return sorted(n for n in writable_of_regions(regions) if n.startswith("params."))


@pytest.mark.slow
def test_reset_puts_back_the_online_parameters_any_client_set(tmp_path):
    sock = tmp_path / "control.sock"
    b = Bench.start(control=sock)
    try:
        idle, mu = "params.engine.idle_speed_rpm", "params.clutch[0].mu_static"
        start = b.read_many([idle, mu])
        b.wait_until(f"engine_speed_rpm > {start[idle] - 100}", timeout_s=5)
        other = Bench.attach(sock)                       # another client sets them
        try:
            other.set(idle, start[idle] + 400)
            other.set(mu, start[mu] * 0.9)
        finally:
            other.detach()
        assert b.read_many([idle, mu]) == {idle: start[idle] + 400, mu: start[mu] * 0.9}
        b.wait_until(f"engine_speed_rpm > {start[idle] + 250}", timeout_s=5)   # the engine obeys
        b.reset()
        assert b.read_many([idle, mu]) == start
        b.wait_until(f"engine_speed_rpm < {start[idle] + 100}", timeout_s=5)
        assert b._request("restore_params")["restored"] == {}             # nothing left to restore
        b.set("accel_pedal_pct", 30)
        b.wait_until("gear == 2", timeout_s=10)                           # and it drives as before
    finally:
        b.stop()


def test_ignition_is_refused_with_a_bad_off_time(bench):
    with pytest.raises(BenchError, match="off_s must be seconds"):
        bench._request("ignition", off_s=-1)
    with pytest.raises(BenchError, match="off_s must be seconds"):
        bench._request("ignition", off_s="long")


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_hil_suite_runs_through_bench_url_against_another_process(tmp_path):
    """Every test of tests/hil passes against `dct-hil serve --tcu reference
    --control-tcp` in another process (loopback TCP, a token), as it does on
    the local bench of this suite (tests/hil runs in it too)."""
    token = tmp_path / "bench.token"
    token.write_text(TOKEN + "\n")
    port = _free_port()
    stats = tmp_path / "serve-stats.json"
    server = subprocess.Popen(
        [sys.executable, "-m", "dct_hil.cli", "serve", "--priority", "0", "--tcu", "reference",
         "--tcu-clock", "bus",         # as the local suite's marker: the TCU on plant time
         "--control-tcp", f"127.0.0.1:{port}", "--control-token-file", str(token),
         "--stats", str(stats), "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                Bench.attach(f"tcp://127.0.0.1:{port}", token_file=token).detach()
                break
            except BenchError:
                assert server.poll() is None, server.stdout.read()
                assert time.monotonic() < deadline, "the server did not open its TCP port"
                time.sleep(0.2)
        junit = tmp_path / "remote.xml"
        run = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/hil",
             "--bench-url", f"tcp://127.0.0.1:{port}", "--bench-token-file", str(token),
             f"--junitxml={junit}"],
            cwd=ROOT, capture_output=True, text=True, timeout=540)
        cases = list(ET.parse(junit).iter("testcase"))
        failed = [c.get("name") for c in cases
                  if any(e.tag in ("failure", "error", "skipped") for e in c)]
        assert run.returncode == 0 and not failed, run.stdout[-3000:]
        collected = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "--collect-only", "-p", "no:cacheprovider",
             "tests/hil"], cwd=ROOT, capture_output=True, text=True, timeout=120).stdout
        ids = {ln.split("::")[-1] for ln in collected.splitlines() if "::" in ln}
        assert ids == {c.get("name") for c in cases}       # every test of the suite ran
        # a wrong token: the plugin fails the test in one line, the server goes on
        bad = tmp_path / "bad.token"
        bad.write_text("not-the-token\n")
        wrong = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
             "tests/hil/test_reference_tcu.py::test_launch_moves_off_and_shifts_1_2",
             "--bench-url", f"tcp://127.0.0.1:{port}", "--bench-token-file", str(bad)],
            cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert wrong.returncode != 0 and "wrong token" in wrong.stdout
        assert server.poll() is None
    finally:
        server.terminate()
        out, _ = server.communicate(timeout=60)
    assert server.returncode == 0, out
    assert "control           tcp://127.0.0.1:" in out and "(token)" in out
    assert stats.exists() and (tmp_path / "tcu-report.json").exists()
