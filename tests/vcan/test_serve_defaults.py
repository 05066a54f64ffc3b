"""``dct-hil serve`` with its default real-time options starts on a slow machine.

The guest (User-mode Linux or emulated) is such a machine: locking a Python process's memory
(mlockall) takes seconds there, which a fixed start-up bound once refused
(`the loop did not start within 5 s`). Here the server runs with the
defaults a user gets (SCHED_FIFO 80, mlockall, PM QoS 0, the early wake-up
spin), only slowed down (--time-scale 0.1) as every guest run is; the test
waits for its frames on vcan0, stops it with SIGTERM and reads what the
loop was granted. Nothing is timed.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from can_dbc import codec

pytestmark = pytest.mark.vcan

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WAIT_S = 300.0


def test_serve_starts_with_the_default_real_time_options(vcan0, tmp_path):
    import can

    stats_path = tmp_path / "stats.json"
    out = open(tmp_path / "serve.out", "w", encoding="utf-8")
    err_path = tmp_path / "serve.err"
    err = open(err_path, "w", encoding="utf-8")
    sim_status = codec.message("SIM_Status").frame_id
    bus = can.Bus(interface="socketcan", channel=vcan0,
                  can_filters=[{"can_id": sim_status, "can_mask": 0x7FF, "extended": False}])
    cmd = [sys.executable, "-m", "dct_hil.cli", "serve", "--interface", "socketcan",
           "--channel", vcan0, "--time-scale", "0.1", "--duration", "3600", "--quiet",
           "--stats", str(stats_path)]
    server = subprocess.Popen(cmd, stdout=out, stderr=err, cwd=REPO)
    seen = 0
    try:
        deadline = time.monotonic() + WAIT_S
        while seen < 3 and time.monotonic() < deadline and server.poll() is None:
            msg = bus.recv(timeout=1.0)
            if msg is not None and msg.arbitration_id == sim_status:
                seen += 1
        assert seen >= 3, (f"no SIM_Status from the server within {WAIT_S:g} s (exit "
                           f"{server.poll()}): {err_path.read_text()[-2000:]}")
        server.send_signal(signal.SIGTERM)
        rc = server.wait(timeout=WAIT_S)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
        bus.shutdown()
        out.close()
        err.close()
    stderr = err_path.read_text()
    assert rc == 0, stderr[-2000:]
    assert "did not start" not in stderr
    cfg = json.loads(stats_path.read_text())["config"]
    assert cfg["priority"] == 80
    assert cfg["rt_policy_ok"] is True
    assert cfg["lock_memory"] is True and cfg["memory_locked"] is True
    assert cfg["spin_us"] > 0
    if os.path.exists("/dev/cpu_dma_latency"):
        assert cfg["pm_qos"]["held"] is True, cfg["pm_qos"]
