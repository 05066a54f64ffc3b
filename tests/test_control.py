"""The control channel (rt_loop.control) of a running server: requests over
the Unix socket, bad requests answered with one line and nothing changed,
the socket's life cycle, and the command-line wiring."""

import json
import os
import socket
import stat
import subprocess
import sys
import tempfile
import threading

import pytest

from rt_loop.control import ControlClient, ControlError
from rt_loop.server import Server, ServerError


@pytest.fixture
def short_dir():
    """A folder with a short path (a Unix socket address holds at most 107 bytes)."""
    d = tempfile.mkdtemp(prefix="ctl-", dir="/tmp")
    yield d
    for name in os.listdir(d):
        os.unlink(os.path.join(d, name))
    os.rmdir(d)


@pytest.fixture
def served(short_dir):
    path = os.path.join(short_dir, "c.sock")
    server = Server(f"ctl-{os.getpid()}-{threading.get_ident()}", interface="virtual",
                    priority=0, control_path=path)
    server.start()
    client = ControlClient(path)
    yield server, client, path
    client.close()
    server.stop()


def test_socket_is_private_and_removed_on_stop(served):
    server, client, path = served
    st = os.stat(path)
    assert stat.S_ISSOCK(st.st_mode)
    assert stat.S_IMODE(st.st_mode) == 0o600
    server.stop()
    assert not os.path.exists(path)


def test_read_set_and_faults(served):
    server, c, _ = served
    assert c.request("ping")["time_s"] >= 0
    values = c.request("read", names=["time_s", "vehicle_speed_kmh", "cmd.target_gear",
                                      "DCT_ShaftSpeeds.EngineSpeed", "maneuver_time_s"])["values"]
    assert set(values) == {"time_s", "vehicle_speed_kmh", "cmd.target_gear",
                           "DCT_ShaftSpeeds.EngineSpeed", "maneuver_time_s"}
    assert values["maneuver_time_s"] is None                 # no maneuver: null, not NaN
    engine = values["DCT_ShaftSpeeds.EngineSpeed"]
    while engine is None:                                    # not sent yet: null, not 0
        engine = c.request("read", names=["DCT_ShaftSpeeds.EngineSpeed"])["values"][
            "DCT_ShaftSpeeds.EngineSpeed"]
    assert 500 < engine < 1000                               # idling
    assert c.request("set", name="road_grade_pct", value=4.5)["applied"] is True
    assert c.request("read", names=["road_grade_pct"])["values"]["road_grade_pct"] == 4.5
    assert c.request("set", name="override.accel_pedal_pct", value=10)["applied"] is True
    fid = c.request("inject", spec={"kind": "can.omit", "message": "VEH_Driver",
                                    "duration_s": 0.05})["id"]
    wid = c.request("watch", when="time_s > 0.3")["id"]
    server.faults.wait_taken(wid)
    while c.request("faults")["faults"][1]["started_s"] is None:
        pass
    faults = {f["id"]: f for f in c.request("faults")["faults"]}
    assert faults[fid]["kind"] == "can.omit" and faults[wid]["kind"] == "watch"
    c.request("clear", id=wid)
    assert [f["id"] for f in c.request("faults")["faults"]] == [fid]
    c.request("clear_all")
    assert c.request("faults")["faults"] == []
    assert any(e["id"] == wid and e["event"] == "start" for e in c.request("events")["events"])
    snap = c.request("snapshot")["snapshot"]
    assert snap["state"] == "running"
    assert c.request("config")["config"]["channel"] == server.channel


@pytest.mark.parametrize("request_line, cause", [
    (b"not json\n", "not JSON"),
    (b"[1, 2]\n", "JSON object"),
    (b'{"op": "fly"}\n', "unknown op 'fly'"),
    (b'{"op": "read", "names": ["nope"]}\n', "'nope'"),
    (b'{"op": "read", "names": ["DCT_Nope.Speed"]}\n', "'DCT_Nope.Speed'"),
    (b'{"op": "read"}\n', "names"),
    (b'{"op": "set", "name": "road_grade_pct", "value": 41}\n', "outside -40 .. 40"),
    (b'{"op": "set", "name": "road_grade_pct", "value": "steep"}\n', "must be a number"),
    (b'{"op": "set", "name": "gear", "value": 1}\n', "not a plant input"),
    (b'{"op": "set", "name": "road_grade_pct"}\n', "needs value"),
    (b'{"op": "inject", "spec": {"kind": "can.omit", "message": "Nope"}}\n', "'Nope'"),
    (b'{"op": "inject", "spec": {"kind": "boom"}}\n', "'boom' is not known"),
    (b'{"op": "inject", "spec": {"kind": {"op": "x"}}}\n', "fault kind {'op': 'x'} is not known"),
    (b'{"op": "inject", "spec": {"kind": ["can.omit"]}}\n', "is not known"),
    (b'{"op": "inject"}\n', "needs spec"),
    (b'{"op": "watch", "when": "gear = 3"}\n', "cannot read"),
    (b'{"op": "clear", "id": 99}\n', "no fault 99"),
    (b'{"op": "clear", "id": "x"}\n', "needs id"),
])
def test_bad_requests_one_line_nothing_changed(served, request_line, cause):
    server, c, _ = served
    grade = c.request("read", names=["road_grade_pct"])["values"]["road_grade_pct"]
    c._sock.sendall(request_line)
    answer = json.loads(c._file.readline())
    assert answer["ok"] is False
    assert cause in answer["error"] and "\n" not in answer["error"]
    assert c.request("faults")["faults"] == []               # nothing queued
    assert c.request("read", names=["road_grade_pct"])["values"]["road_grade_pct"] == grade
    assert c.request("ping")["state"] == "running"           # still serving


def test_client_error_raises_one_line(served):
    _, c, _ = served
    with pytest.raises(ControlError, match="outside"):
        c.request("set", name="road_grade_pct", value=100)


def test_several_clients_and_a_client_that_leaves(served):
    _, c, path = served
    other = socket.socket(socket.AF_UNIX)
    other.connect(path)
    other.sendall(b'{"op": "ping"')                         # half a line, then gone
    other.close()
    with ControlClient(path) as second:
        assert second.request("ping")["state"] == "running"
    assert c.request("ping")["state"] == "running"


def test_stop_request_ends_the_loop(served):
    server, c, _ = served
    report = c.request("stop")["report"]
    assert report["run"]["state"] == "stopped"
    assert server.wait(5)


def test_stale_socket_replaced_live_one_refused(short_dir):
    path = os.path.join(short_dir, "s.sock")
    stale = socket.socket(socket.AF_UNIX)
    stale.bind(path)
    stale.close()                                            # left behind, nobody listening
    a = Server(f"ctl-a-{os.getpid()}", interface="virtual", priority=0, control_path=path)
    a.start()
    try:
        b = Server(f"ctl-b-{os.getpid()}", interface="virtual", priority=0, control_path=path)
        with pytest.raises(ServerError, match="already listening"):
            b.start()
        assert os.path.exists(path)                          # a's socket untouched
        with ControlClient(path) as c:
            assert c.request("ping")["state"] == "running"
    finally:
        a.stop()
    assert not os.path.exists(path)


def test_bad_socket_paths(short_dir):
    plain = os.path.join(short_dir, "file")
    open(plain, "w").close()
    with pytest.raises(ServerError, match="not a socket"):
        Server("x", interface="virtual", priority=0, control_path=plain)
    with pytest.raises(ServerError, match="does not exist"):
        Server("x", interface="virtual", priority=0, control_path="/nonexistent-dir/c.sock")
    with pytest.raises(ServerError, match="too long"):
        Server("x", interface="virtual", priority=0, control_path="/tmp/" + "x" * 200)


def test_xcp_calibration_shares_the_cal_lock():
    server = Server(f"ctl-x-{os.getpid()}", interface="virtual", priority=0, xcp="127.0.0.1:0")
    server.start()
    try:
        assert server.xcp.backend.cal_lock is server.cal_lock
    finally:
        server.stop()


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "dct_hil.cli", *args], capture_output=True,
                          text=True, timeout=60)


@pytest.mark.slow
def test_cli_serve_bad_faults_file_and_control_path(tmp_path):
    faults = tmp_path / "f.toml"
    faults.write_text('[[fault]]\nkind = "can.omit"\nmessage = "NOPE"\n')
    common = ["serve", "--interface", "virtual", "--channel", "cli-x", "--priority", "0",
              "--stats", str(tmp_path / "s.json"), "--duration", "1", "--quiet"]
    r = _cli(*common, "--faults", str(faults))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"dct-hil: error: {faults}: fault 1: can.omit: message 'NOPE' is not in the served mapping"]
    r = _cli(*common, "--control", str(tmp_path / "missing" / "c.sock"))
    assert r.returncode == 2
    assert "folder" in r.stderr and len(r.stderr.strip().splitlines()) == 1
