"""The test API (dct_hil.bench) and its pytest plugin (dct_hil.pytest_plugin):
a bench started in-process, one attached through the control socket, the
wait on plant time and its timeout, errors, recordings kept on failure and
deleted on success, and the JUnit properties."""

import importlib.util
import os
import tempfile
import threading
import xml.etree.ElementTree as ET

import pytest

from dct_hil.bench import Bench, BenchError, BenchTimeout
from rt_loop.server import Server

pytest_plugins = ["pytester"]


@pytest.fixture
def quiet_bench(tmp_path):
    """A bench without a TCU (nothing on the bus): the plant idles."""
    b = Bench.start(tcu=False, record=tmp_path / "run.csv")
    yield b
    b.stop()


def test_wait_until_exact_to_the_tick_and_timeout_message(quiet_bench):
    b = quiet_bench
    t0 = b.time_s
    t = b.wait_until(f"time_s >= {t0 + 0.2:.4f}", timeout_s=1.0)
    assert t0 + 0.2 - 0.0005 <= t <= t0 + 0.2 + 0.0005        # the tick it first held
    with pytest.raises(BenchTimeout) as e:
        b.wait_until("vehicle_speed_kmh > 50", timeout_s=0.3)
    msg = str(e.value)
    assert "'vehicle_speed_kmh > 50' did not hold within 0.3 s of plant time" in msg
    assert "\n" not in msg and " to " in msg
    assert isinstance(e.value, AssertionError)                # a test failure, not an error
    assert [f for f in b.faults() if f["kind"] == "watch"] == []   # the watches are cleared


def test_sleep_set_read_inject(quiet_bench):
    b = quiet_bench
    t0 = b.time_s
    assert b.sleep(0.1) >= t0 + 0.1
    b.set("road_grade_pct", -3)
    assert b.read("road_grade_pct") == -3
    assert set(b.read_many(["gear", "VEH_Motion.RoadGrade"])) == {"gear", "VEH_Motion.RoadGrade"}
    fid = b.inject("can.omit", message="SIM_Status", duration_s=0.05)
    b.wait_until("time_s > 0", timeout_s=0.1)
    b.sleep(0.1)
    assert [e["event"] for e in b.events() if e["id"] == fid] == ["start", "end"]
    assert all(e["kind"] != "watch" for e in b.events())
    b.clear(fid)
    b.clear_all()


@pytest.mark.parametrize("call, cause", [
    (lambda b: b.set("nope", 1), "'nope' is not a plant input"),
    (lambda b: b.set("road_grade_pct", 1e9), "outside"),
    (lambda b: b.read("nope"), "'nope'"),
    (lambda b: b.inject("can.omit", message="Nope"), "'Nope'"),
    (lambda b: b.inject("fork.jammed", sleeve=9), "sleeve"),
    (lambda b: b.wait_until("gear === 3", timeout_s=1), "cannot read"),
    (lambda b: b.wait_until("gear == 3", timeout_s=0), "timeout_s"),
    (lambda b: b.clear(1234), "no fault 1234"),
    (lambda b: b.tcu_status(), "TCU_Status"),        # no TCU: no status received
])
def test_bench_errors_are_one_line(quiet_bench, call, cause):
    with pytest.raises(BenchError) as e:
        call(quiet_bench)
    assert cause in str(e.value) and "\n" not in str(e.value)
    assert quiet_bench.faults() == []


def test_start_errors():
    with pytest.raises(BenchError, match="transport 'can'"):
        Bench.start(transport="can")
    with pytest.raises(BenchError, match="not a CAN network interface"):
        Bench.start(transport="socketcan", channel="nocan0")
    with pytest.raises(BenchError, match="maneuver 'moon'"):
        Bench.start(maneuver="moon")


def test_reference_tcu_heard_recording_and_report(tmp_path):
    rec = tmp_path / "drive.mf4"
    with Bench.start(record=rec) as b:
        snap = b.snapshot()
        assert all(m["accepted"] > 0 for m in snap["counts"]["tcu_messages"].values())
        b.set("accel_pedal_pct", 30)
        b.wait_until("vehicle_speed_kmh > 1", timeout_s=2.0)
        if importlib.util.find_spec("tcu_stub.diagnostics") is not None:   # a diagnosing TCU
            status = b.tcu_status()
            # a healthy plant: no fault of the plant diagnosed. The CAN codes may set on
            # a loaded host, where the TCU's Python thread takes the plant's frames late
            # and times them out itself: its own view, not the plant's
            own = {"engine_message", "can_timeout", "can_crc", "can_counter", "can_length"}
            assert set(status["dtcs"]) <= own, status
    report = b.stop()                                          # again: the same report
    assert report["run"]["state"] == "stopped"
    assert b.tcu_report is not None
    data = b.recording()
    assert data["vehicle_speed_kmh"].max() > 1
    with pytest.raises(BenchError, match="stopped"):
        b.read("gear")


def test_attach_to_a_running_server(tmp_path):
    folder = tempfile.mkdtemp(prefix="att-", dir="/tmp")
    path = os.path.join(folder, "c.sock")
    server = Server(f"attach-{os.getpid()}", interface="virtual", priority=0, control_path=path,
                    record_path=tmp_path / "run.csv")
    server.start()

    def console():                      # what dct-hil serve does when the loop ends
        server.wait()
        server.stop()

    finisher = threading.Thread(target=console)
    finisher.start()
    try:
        b = Bench.attach(path)
        assert b.record_path == str(tmp_path / "run.csv")
        b.set("road_grade_pct", 2)
        assert b.read("road_grade_pct") == 2
        fid = b.inject("engine.torque_limit", max_nm=50)
        t = b.wait_until("time_s > 0.2", timeout_s=1.0)
        assert t > 0.2
        assert b.faults()[0]["id"] == fid
        with pytest.raises(BenchTimeout, match="gear == 5"):
            b.wait_until("gear == 5", timeout_s=0.1)
        report = b.stop()
        assert report["run"]["state"] == "stopped"
        assert not os.path.exists(path)                       # finalised by the server's side
        assert len(b.recording()["time_s"]) > 0
    finally:
        server.stop()
        finisher.join(10)
        os.rmdir(folder)
    with pytest.raises(BenchError, match="control socket"):
        Bench.attach(path)


PLUGIN_TESTS = """
import pytest

def test_passes(bench):
    bench.set("road_grade_pct", 1)
    bench.inject("can.omit", message="SIM_Status", duration_s=0.02)
    bench.sleep(0.1)

def test_fails(bench):
    bench.sleep(0.05)
    assert bench.read("gear") == 6

@pytest.mark.tcu_under_test
@pytest.mark.bench(record=None)
def test_marked(bench):
    assert bench._tcu is None
"""


@pytest.mark.slow
def test_plugin_recordings_and_junit(pytester):
    pytester.makepyfile(test_plugin_run=PLUGIN_TESTS)
    recordings = pytester.path / "rec"
    junit = pytester.path / "junit.xml"
    result = pytester.runpytest_subprocess("--strict-markers", "--bench-recordings",
                                           str(recordings), f"--junitxml={junit}", "-p",
                                           "no:cacheprovider")
    result.assert_outcomes(passed=2, failed=1)
    kept = sorted(p.name for p in recordings.iterdir())
    assert kept == ["test_fails.mf4"]                          # kept on failure only
    cases = {c.get("name"): c for c in ET.parse(junit).getroot().iter("testcase")}
    props = {name: {p.get("name"): p.get("value") for p in c.iter("property")}
             for name, c in cases.items()}
    assert props["test_fails"]["bench_recording"] == str(recordings / "test_fails.mf4")
    assert "bench_recording" not in props["test_passes"]
    assert '"can.omit"' in props["test_passes"]["bench_fault_events"]


@pytest.mark.slow
def test_plugin_keeps_recordings_when_asked(pytester):
    pytester.makepyfile(test_keep="def test_ok(bench):\n    bench.sleep(0.02)\n")
    recordings = pytester.path / "rec"
    result = pytester.runpytest_subprocess("--bench-recordings", str(recordings),
                                           "--bench-keep-recordings", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)
    assert [p.name for p in recordings.iterdir()] == ["test_ok.mf4"]


@pytest.mark.slow
def test_a_maneuver_with_a_grade_plays_on_it(tmp_path):
    """hill-start fixes the road grade: the bench's loop plays the maneuver on its 20 %
    from the TCU's first frame, held by the reference TCU (no rollback)."""
    from plant.maneuvers import get_maneuver

    grade = get_maneuver("hill-start").inputs["road_grade_pct"]
    b = Bench.start(maneuver="hill-start")
    try:
        assert b.read("road_grade_pct") == grade
        b.wait_until("maneuver_time_s > 4.0", timeout_s=30.0)        # the brake let go at 3 s
        assert b.read("road_grade_pct") == grade
        assert b.read("distance_m") > -0.1
    finally:
        b.stop()
