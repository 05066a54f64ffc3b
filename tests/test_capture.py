"""Captures with triggers (rt_loop.measure.capture, csrc/rt_capture.c): the
history before a start trigger, checked sample for sample against the
server's own recording; several captures at once; bad requests refused in
one line with nothing changed; a client killed mid-capture and one that
stops reading leave the server and the other client unaffected."""

import json
import math
import socket
import time

import numpy as np
import pytest

from dct_hil.bench import Bench, BenchError
from rt_loop.control import ControlClient
from rt_loop.measure import capture as capture_mod
from rt_loop.measure.recorder import read_recording

TOKEN = "capture-token-123"


@pytest.mark.slow
def test_two_seconds_before_an_injected_fault_as_the_recording_has_them(tmp_path):
    """A capture armed 3 s before, started by the fault's effect (the TCU's
    DTC), with 2 s of history: its first sample is the trigger minus 2 s, and
    every sample equals the recording's at the same tick."""
    rec = tmp_path / "run.mf4"
    names = ["vehicle_speed_kmh", "engine_speed_rpm", "clutch1_pressure_bar",
             "clutch2_pressure_bar", "cmd.target_gear", "cmd.solenoid_current1_a"]
    with Bench.start(record=rec, record_every_s=0.002) as bench:
        names = [n for n in names if not n.startswith("cmd.") or
                 n[4:] in bench.server.channels.command_names]
        bench.set("accel_pedal_pct", 30)
        bench.wait_until("gear == 2", timeout_s=10)
        cap = bench.capture(names, every_s=0.002, start_when="TCU_Status.ActiveFaults != 0",
                            pre_s=2.0, duration_s=1.0)
        assert cap.status()["state"] == "armed"
        bench.sleep(3.0)
        bench.inject("hydraulics.line_pressure_loss", loss=0.8)
        st = cap.wait(30)
        data = cap.result()
        mf4 = cap.to_mf4(tmp_path / "cap.mf4")
        bench.sleep(0.2)
    t, trig = data["time_s"], st["trigger_s"]
    assert st["state"] == "done" and st["history_s"] == 2.0 and st["gaps"] == 0
    assert abs(t[0] - (trig - 2.0)) <= 0.002 + 1e-9, (t[0], trig)
    assert abs(t[-1] - (trig + 1.0)) <= 0.002 + 1e-9
    assert np.allclose(np.diff(t), 0.002)
    recording = read_recording(rec)
    rt = recording["time_s"]
    idx = np.searchsorted(rt, t - 1e-9)
    assert np.array_equal(rt[idx], t), "every captured tick is a recorded one"
    for name in names:
        col = name if name in recording else f"cmd_{name[4:]}" if f"cmd_{name[4:]}" in \
            recording else name[4:]
        assert col in recording, (name, list(recording)[:40])
        assert np.array_equal(recording[col][idx], data[name]), name
    before = t < trig
    assert before.sum() == 1000, "2 s of 2 ms samples before the trigger"
    from asammdf import MDF

    with MDF(mf4) as m:
        assert np.array_equal(m.get("vehicle_speed_kmh").samples, data["vehicle_speed_kmh"])


@pytest.mark.slow
def test_several_captures_at_once_each_its_signals_and_rate():
    with Bench.start(tcu=False) as bench:
        a = bench.capture(["vehicle_speed_kmh", "engine_speed_rpm"], duration_s=0.5)
        b = bench.capture(["engine_speed_rpm", "exec_us", "cmd.target_gear"]
                          if "target_gear" in bench.server.channels.command_names
                          else ["engine_speed_rpm", "exec_us"],
                          every_s=0.01, duration_s=0.5)
        ra, rb = a.wait(10) and a.result(), b.wait(10) and b.result()
    assert np.allclose(np.diff(ra["time_s"]), 0.0005) and len(ra["time_s"]) == 1001
    assert np.allclose(np.diff(rb["time_s"]), 0.01) and len(rb["time_s"]) == 51
    common = np.intersect1d(ra["tick"], rb["tick"])
    assert len(common) >= 40                 # b was armed a few ticks after a
    ia, ib = np.searchsorted(ra["tick"], common), np.searchsorted(rb["tick"], common)
    assert np.array_equal(ra["engine_speed_rpm"][ia], rb["engine_speed_rpm"][ib])
    assert set(rb) >= {"exec_us"} and np.all(rb["exec_us"] > 0)


@pytest.mark.parametrize("fields, says", [
    ({"signals": ["no_such_value"]}, "cannot be captured"),
    ({"signals": []}, "needs signals"),
    ({"signals": ["gear"], "pre_s": 100}, "more history than is kept (at most 30 s"),
    ({"signals": ["gear"], "every_s": 0.0007}, "not a whole number of ticks"),
    ({"signals": ["gear"], "start_when": "gear =="}, "capture:"),
    ({"signals": ["gear"], "duration_s": -1}, "outside"),
    ({"signals": ["gear"], "trigger": "x"}, "unknown fields trigger"),
    ({"signals": ["gear", "gear"]}, "named twice"),
])
def test_bad_captures_are_refused_in_one_line_with_nothing_changed(fields, says):
    with Bench.start(tcu=False) as bench:
        with pytest.raises(BenchError) as e:
            bench._request("capture", **fields)
        assert says in str(e.value) and "\n" not in str(e.value)
        caps = bench.server.captures
        assert caps is None or caps.counters()["live"] == 0
        assert bench.faults() == []                         # no watch left behind
        with pytest.raises(BenchError, match="no capture 99"):
            bench._request("capture_status", id=99)


def _raw(port, rcvbuf=None):
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(5)
    s.connect(("127.0.0.1", port))
    f = s.makefile("rb")
    s.sendall(json.dumps({"op": "hello", "token": TOKEN}).encode() + b"\n")
    assert json.loads(f.readline())["ok"]
    return s, f


@pytest.mark.slow
def test_a_client_killed_mid_capture_and_one_not_reading_leave_the_other_unaffected(
        monkeypatch):
    from rt_loop.control import serving

    monkeypatch.setattr(serving, "SLOW_CLIENT_S", 1.0)
    with Bench.start(tcu=False) as bench:
        srv = bench.server
        from rt_loop.control import ControlServer

        ctl = ControlServer(srv, None, tcp=("127.0.0.1", 0), token=TOKEN, log=lambda _l: None)
        ctl.start()
        try:
            port = ctl.tcp_address[1]
            other = ControlClient(f"tcp://127.0.0.1:{port}", token=TOKEN)
            mine = other.request("capture", signals=["engine_speed_rpm"], duration_s=2.0)["id"]
            killed, kf = _raw(port)
            killed.sendall(json.dumps({"op": "capture", "signals": ["vehicle_speed_kmh"],
                                       "pre_s": 1.0, "start_when": "gear == 9"}).encode()
                           + b"\n")
            theirs = json.loads(kf.readline())["id"]
            slow, sf = _raw(port, rcvbuf=4096)
            slow.sendall(json.dumps({"op": "capture", "signals": ["gear", "engine_speed_rpm",
                                                                  "vehicle_speed_kmh"]}).encode()
                         + b"\n")
            slow.settimeout(0.5)
            for _ in range(3000):                   # growing answers it never reads
                try:
                    slow.sendall(json.dumps({"op": "capture_fetch", "id": 3}).encode() + b"\n")
                except OSError:
                    break                           # its send buffer full: the server stopped
                time.sleep(0.002)
            killed.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\0\0\0\0\0\0\0")
            kf.close()
            killed.close()                          # killed: reset mid-capture
            deadline = time.monotonic() + 10
            while theirs in srv.captures.ids() or ctl.counts["slow_clients_dropped"] < 1:
                assert time.monotonic() < deadline, (srv.captures.ids(), ctl.counts)
                time.sleep(0.05)
            assert ctl.counts.get("captures_abandoned", 0) >= 1
            end = time.monotonic() + 10
            while other.request("capture_status", id=mine)["capture"]["state"] != "done":
                assert time.monotonic() < end
                time.sleep(0.05)
            got = other.request("capture_fetch", id=mine)
            assert len(got["time_s"]) == 4001 and got["capture"]["gaps"] == 0
            assert all(v is not None and math.isfinite(v) for v in got["values"]["engine_speed_rpm"])
            other.close()
            sf.close()
            slow.close()
            assert srv.running
        finally:
            ctl.stop()


def test_the_history_kept_is_limited_and_said():
    assert capture_mod.MAX_PRE_S == 30.0
    with Bench.start(tcu=False) as bench:
        with pytest.raises(BenchError, match=r"pre_s 31 s is more history than is kept"):
            bench.capture(["gear"], pre_s=31)


@pytest.mark.slow
def test_a_start_condition_true_when_armed_starts_at_once_with_no_history():
    with Bench.start(tcu=False) as bench:
        bench.sleep(0.2)
        cap = bench.capture(["engine_speed_rpm"], start_when="time_s > 0.1", pre_s=1.0,
                            duration_s=0.2)
        st = cap.wait(10)
        data = cap.result()
    assert st["history_s"] == 0.0 and st["trigger_s"] <= data["time_s"][0] + 1e-9
    assert data["time_s"][-1] <= st["trigger_s"] + 0.2 + 1e-9
