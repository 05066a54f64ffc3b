"""The CAN interface taken down and up again under ``dct-hil serve`` (vcan0).

``ip link set vcan0 down`` under a running server: the kernel reports
ENETDOWN on the loop's socket; the server ends with one error line
(``dct-hil: error: the loop stopped: transport error: Network is down
(errno 100)``, then the usual ``timing INVALID`` warning), exit status 1, and
leaves whole files: the stats JSON (``run.error``) and the MF4 recording,
readable to its last second. After ``ip link set vcan0 up`` a server started
again runs on it.
"""

import json
import os
import subprocess
import sys
import time

import pytest
from waiting import stop_server, wait_for

pytestmark = pytest.mark.vcan

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WAIT_S = 600.0


def _wait(pred, what, timeout=WAIT_S):
    return wait_for(pred, what, timeout, step=0.1)


def _serve(vcan0, d, name):
    out = open(d / f"{name}.out", "w")
    err = open(d / f"{name}.err", "w")
    p = subprocess.Popen(
        [sys.executable, "-m", "dct_hil.cli", "serve", "--channel", vcan0, "--interface",
         "socketcan", "--priority", "0", "--no-pm-qos", "--quiet",
         "--stats", str(d / f"{name}.json"), "--record", str(d / f"{name}.mf4")],
        cwd=REPO, stdout=out, stderr=err)
    return p, out, err


def _plant_frame(bus, timeout, proc):
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        m = bus.recv(timeout=1.0)
        if m is not None and m.arbitration_id == 0x1F0:       # SIM_Status
            return True
    return False


def _link(vcan0, state):
    subprocess.run(["ip", "link", "set", vcan0, state], check=True)


def test_the_interface_going_down_ends_the_server_with_one_line_and_whole_files(vcan0,
                                                                              tmp_path):
    import can
    from asammdf import MDF

    p, out, err = _serve(vcan0, tmp_path, "down")
    bus = can.Bus(interface="socketcan", channel=vcan0)
    try:
        assert _plant_frame(bus, WAIT_S, p), (tmp_path / "down.err").read_text()
        time.sleep(3.0)                       # a second or more of recording
        _link(vcan0, "down")
        try:
            rc = p.wait(timeout=WAIT_S)
        finally:
            _link(vcan0, "up")
    finally:
        bus.shutdown()
        if p.poll() is None:
            stop_server(p, tmp_path / "down.err")
        out.close()
        err.close()
    text = (tmp_path / "down.err").read_text()
    lines = [line for line in text.splitlines() if line.startswith("dct-hil: error:")]
    assert rc == 1, text
    assert lines == ["dct-hil: error: the loop stopped: transport error: Network is down "
                     "(errno 100)"], text
    stats = json.loads((tmp_path / "down.json").read_text())
    assert "Network is down" in stats["run"]["error"]
    with MDF(str(tmp_path / "down.mf4")) as mdf:
        t = mdf.get("vehicle_speed_kmh").timestamps
    assert len(t) > 10

    # the interface up again: a new server runs on it
    p, out, err = _serve(vcan0, tmp_path, "up")
    bus = can.Bus(interface="socketcan", channel=vcan0)
    try:
        assert _plant_frame(bus, WAIT_S, p), (tmp_path / "up.err").read_text()
    finally:
        bus.shutdown()
        rc = stop_server(p, tmp_path / "up.err")
        out.close()
        err.close()
    assert rc == 0, (tmp_path / "up.err").read_text()
