"""What a running server changes without a restart (rt_loop/server/): a
maneuver started and stopped by the loop's command hand-over, and a
recording started and stopped while the loop ticks. Shown on the embedded
transport without a TCU (the pedals act on the plant directly)."""

import numpy as np
import pytest

from dct_hil.bench import Bench, BenchError
from rt_loop.control import ControlServer
from rt_loop.measure.recorder import read_recording
from rt_loop.server import ServerError


@pytest.fixture
def bench():
    b = Bench.start(tcu=False)
    yield b
    b.stop()


def pedal(srv):
    return float(srv._l.plant.inputs.accel_pedal_pct)


@pytest.mark.slow
def test_a_maneuver_starts_and_stops_while_running(bench):
    srv = bench.server
    assert set(srv.loop_maneuvers()) == {"paper-cycle", "0-100", "creep", "reverse-park", "hill-start"}
    assert not srv.maneuver_playing and srv.snapshot()["maneuver"] == "none"
    control = ControlServer(srv, None)
    srv.start_maneuver("0-100")
    assert srv.maneuver_playing and srv.maneuver_name == "0-100"
    bench.wait_until("maneuver_time_s > 0.2", timeout_s=1.0)
    assert float(srv._l.plant.inputs.brake_pedal_pct) == 30.0, "the table's first row: on the brake"
    bench.wait_until("maneuver_time_s > 1.05", timeout_s=2.0)
    assert pedal(srv) == 100.0 and srv.snapshot()["maneuver"] == "running"
    answer = control.handle({"op": "set", "name": "accel_pedal_pct", "value": 10})
    assert not answer["ok"] and "maneuver" in answer["error"]
    srv.stop_maneuver()
    assert not srv.maneuver_playing
    snap = srv.snapshot()
    assert snap["maneuver"] == "done" and pedal(srv) == 0.0
    assert control.handle({"op": "set", "name": "accel_pedal_pct", "value": 10})["ok"]
    bench.sleep(0.05)
    assert pedal(srv) == 10.0, "a set after the stop drives the pedal"
    assert srv.running


def test_a_maneuver_is_named_before_the_loop_can_play_it(bench, monkeypatch):
    """A reader that sees the maneuver playing (another thread: the page, the
    control channel) sees its name: it is set before the command is published,
    and put back when the loop refuses it."""
    srv = bench.server
    command = srv._maneuver_command
    named_at_publish = []

    def spy(op, fill=None):
        named_at_publish.append(srv.maneuver_name)
        command(op, fill)

    monkeypatch.setattr(srv, "_maneuver_command", spy)
    srv.start_maneuver("creep")
    assert named_at_publish == ["creep"] and srv.maneuver_playing

    def refused(op, fill=None):
        raise ServerError("the loop refused the maneuver command")

    monkeypatch.setattr(srv, "_maneuver_command", refused)
    with pytest.raises(ServerError):
        srv.start_maneuver("0-100")
    assert srv.maneuver_name == "creep"


def test_a_maneuver_table_ends_and_the_loop_goes_on(bench):
    srv = bench.server
    srv.start_maneuver([(0.0, 40.0, 0.0), (0.1, 20.0, 5.0)], end_s=0.2)
    bench.wait_until("maneuver_time_s > 0.199", timeout_s=1.0)
    bench.sleep(0.1)
    assert srv.snapshot()["maneuver"] == "done" and srv.running
    assert pedal(srv) == 20.0 and float(srv._l.plant.inputs.brake_pedal_pct) == 5.0, \
        "the last row's pedals stay"
    srv.start_maneuver("paper-cycle")           # another one replaces it
    assert srv.maneuver_playing and srv.maneuver_name == "paper-cycle"


def test_a_maneuver_plays_its_selector_and_sets_its_grade_as_it_starts(bench):
    srv = bench.server
    srv.start_maneuver("hill-start")
    bench.wait_until("maneuver_time_s > 0.05", timeout_s=1.0)
    assert float(srv._l.plant.inputs.road_grade_pct) == 20.0
    srv.start_maneuver([(0.0, 0.0, 30.0, "D"), (0.05, 0.0, 30.0, "R")], end_s=0.1,
                       inputs={"road_grade_pct": -3.0})
    bench.wait_until("maneuver_time_s > 0.099", timeout_s=1.0)
    bench.sleep(0.05)
    assert float(srv._l.plant.inputs.selector_lever) == 1.0, "R from its row on"
    assert float(srv._l.plant.inputs.road_grade_pct) == -3.0
    with pytest.raises(ServerError, match="unknown selector position 'Q'"):
        srv.start_maneuver([(0.0, 0.0, 30.0, "Q")])


@pytest.mark.parametrize("maneuver, words", [
    ("wltc", ["wltc", "paper-cycle"]),
    ("nope", ["nope"]),
    ([(0.0, 120.0, 0.0)], ["0..100"]),
    ([(0.0, 10.0, 0.0), (0.0, 10.0, 0.0)], ["increasing"]),
])
def test_bad_maneuvers_are_refused_with_nothing_changed(bench, maneuver, words):
    srv = bench.server
    with pytest.raises(ServerError) as e:
        srv.start_maneuver(maneuver)
    for w in words:
        assert w in str(e.value)
    assert not srv.maneuver_playing and int(srv._l.maneuver_refused) == 0


@pytest.mark.parametrize("suffix", ["csv", "mf4"])
def test_a_recording_starts_and_stops_while_running(bench, tmp_path, suffix):
    srv = bench.server
    assert srv.recording is None
    t_start = bench.time_s
    path = srv.start_recording(tmp_path / f"live.{suffix}", every_s=0.01)
    assert srv.recording["path"] == path
    with pytest.raises(ServerError, match="runs already"):
        srv.start_recording(tmp_path / "second.csv")
    bench.sleep(0.5)
    assert srv.stop_recording() == path and srv.recording is None
    t_stop = bench.time_s
    rec = read_recording(path)
    t = rec["time_s"]
    assert t[0] >= t_start and t[-1] <= t_stop
    assert len(t) >= 40
    assert np.allclose(np.diff(t), 0.01, atol=1e-9), "every sample, none lost"
    with pytest.raises(ServerError, match="no recording"):
        srv.stop_recording()
    again = srv.start_recording(tmp_path / f"again.{suffix}")    # another one after it
    bench.sleep(0.1)
    srv.stop_recording()
    assert len(read_recording(again)["time_s"]) > 0
    if suffix == "mf4":
        assert int(srv._l.cfg.log_frames) == 0, "the traffic copy is off again"


def test_a_recording_into_a_folder_that_cannot_be_written_is_one_line(bench, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(ServerError) as e:
        bench.server.start_recording(blocker / "sub" / "r.csv")
    assert "\n" not in str(e.value) and "r.csv" in str(e.value)
    assert bench.server.recording is None and int(bench.server._l.cfg.record_every) == 0


def test_stop_hooks_run_first_while_the_loop_still_runs():
    b = Bench.start(tcu=False)
    srv = b.server
    seen = []
    srv.add_stop_hook(lambda: seen.append(("first added", srv.running)))
    srv.add_stop_hook(lambda: seen.append(("last added", srv.running)))

    def broken():
        raise OSError("the page's port is gone")

    srv.add_stop_hook(broken)
    with pytest.raises(BenchError, match="the page's port is gone"):
        b.stop()
    assert seen == [("last added", True), ("first added", True)]
    assert not srv.running


def test_a_loop_with_a_cpu_of_its_own_keeps_the_other_threads_off_it():
    import os
    import threading

    from rt_loop.server import Server

    allowed = sorted(os.sched_getaffinity(0))
    cpu = allowed[-1]
    srv = Server("cpu-own-test", interface="virtual", priority=0, cpu=cpu)
    srv.start()
    try:
        loop_tid = srv._thread.native_id
        masks = {int(t): os.sched_getaffinity(int(t)) for t in os.listdir("/proc/self/task")}
        assert os.sched_getaffinity(loop_tid) == {cpu}
        if len(allowed) == 1:
            assert any("no other CPU" in w for w in srv.warnings)
        else:
            others = {t: m for t, m in masks.items() if t != loop_tid}
            assert others and all(cpu not in m for m in others.values()), others
            seen = []
            t = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0)))
            t.start()
            t.join()
            assert cpu not in seen[0], "a thread started later inherits it"
    finally:
        srv.stop()
    assert os.sched_getaffinity(0) == set(allowed), "stop() gives the CPUs back"
