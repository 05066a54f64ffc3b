"""PM QoS: the server holds its CPU latency request while the loop runs, and
only then.

Most tests point the request at a file of their own (``pm_qos_path``), so
they see exactly what was written and whether it is still open. One test
uses the kernel's /dev/cpu_dma_latency (root only), whose read gives the
limit in force: the lowest request of every process holding the file.
"""

import os
import struct
import subprocess
import sys
import time
import uuid

import pytest

from rt_loop import pm_qos
from rt_loop.floor import measure_floor
from rt_loop.pm_qos import PmQos, current_latency_us
from rt_loop.server import Server, ServerError


def open_paths():
    """Paths this process holds open (its file descriptors)."""
    paths = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            paths.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:
            pass
    return paths


@pytest.fixture
def fake_device(tmp_path):
    path = tmp_path / "cpu_dma_latency"
    path.write_bytes(b"")
    return str(path)


def test_request_is_written_and_held_until_release(fake_device):
    q = PmQos(25, fake_device)
    assert fake_device not in open_paths()
    assert q.acquire()
    assert q.held and q.error is None
    with open(fake_device, "rb") as f:
        assert struct.unpack("=i", f.read()) == (25,)
    assert fake_device in open_paths()
    q.release()
    assert not q.held
    assert fake_device not in open_paths()
    assert q.report()["held"] is True      # it was held for the run


def test_a_request_that_cannot_be_made_says_why(tmp_path):
    q = PmQos(0, str(tmp_path / "missing" / "cpu_dma_latency"))
    assert not q.acquire()
    assert not q.held
    assert "cannot open" in q.error and "\n" not in q.error
    assert q.describe().startswith("not held")


@pytest.mark.parametrize("bad", [-1, 1.5, "0", True, None])
def test_bad_latency_is_refused(bad):
    with pytest.raises(ValueError):
        PmQos(bad)


def test_server_holds_the_request_while_the_loop_runs(fake_device):
    srv = Server(f"dct-test-{uuid.uuid4().hex[:10]}", interface="virtual", priority=0,
                 pm_qos_us=3, pm_qos_path=fake_device)
    assert fake_device not in open_paths()
    srv.start()
    try:
        assert srv.running
        assert fake_device in open_paths()
        with open(fake_device, "rb") as f:
            assert struct.unpack("=i", f.read()) == (3,)
        assert srv.config()["pm_qos"] == {"requested_us": 3, "path": fake_device,
                                          "held": True, "error": None}
    finally:
        srv.stop()
    assert fake_device not in open_paths()
    assert srv.report()["config"]["pm_qos"]["held"] is True


def test_server_without_pm_qos_makes_no_request(fake_device):
    srv = Server(f"dct-test-{uuid.uuid4().hex[:10]}", interface="virtual", priority=0,
                 pm_qos_us=None, pm_qos_path=fake_device)
    srv.start()
    try:
        assert fake_device not in open_paths()
    finally:
        srv.stop()
    assert srv.report()["config"]["pm_qos"] is None
    assert os.path.getsize(fake_device) == 0


def test_by_default_only_a_real_time_loop_makes_the_request(fake_device):
    """Normal scheduling is not real time: no request (it would only keep idle
    CPUs polling); SCHED_FIFO asks for 0 us. Asking explicitly always counts."""
    idle = Server("x", interface="virtual", priority=0, pm_qos_path=fake_device)
    assert idle.pm_qos is None and "priority 0" in idle.pm_qos_off_because
    rt = Server("x", interface="virtual", priority=80, pm_qos_path=fake_device)
    assert rt.pm_qos is not None and rt.pm_qos.latency_us == 0
    asked = Server("x", interface="virtual", priority=0, pm_qos_us=0, pm_qos_path=fake_device)
    assert asked.pm_qos is not None


def test_server_runs_on_with_a_warning_when_the_request_fails(tmp_path):
    srv = Server(f"dct-test-{uuid.uuid4().hex[:10]}", interface="virtual", priority=0,
                 pm_qos_us=0, pm_qos_path=str(tmp_path / "no" / "such"))
    srv.start()
    try:
        assert srv.running
        assert any(w.startswith("PM QoS not held") for w in srv.warnings)
    finally:
        srv.stop()
    assert srv.report()["config"]["pm_qos"]["held"] is False


@pytest.mark.parametrize("bad", [-1, 2_000_000, 0.5, True])
def test_server_refuses_a_bad_latency(bad):
    with pytest.raises(ServerError, match="PM QoS"):
        Server("x", interface="virtual", priority=0, pm_qos_us=bad)


def test_the_floor_loop_holds_the_request_for_its_run_only(fake_device):
    fig = measure_floor(duration_s=0.05, rate_hz=2000, priority=0, pm_qos_us=4,
                        pm_qos_path=fake_device)
    assert fig["pm_qos"]["held"] is True
    assert fake_device not in open_paths()
    with open(fake_device, "rb") as f:
        assert struct.unpack("=i", f.read()) == (4,)
    assert fig["samples"] > 0


@pytest.mark.skipif(not (os.geteuid() == 0 and os.path.exists(pm_qos.DEVICE)),
                    reason="needs root and /dev/cpu_dma_latency")
def test_kernel_limit_is_in_force_while_serving_and_released_after():
    # a value no other process is likely to hold, above the 0 that
    # cyclictest or another server might hold at the same time
    want = 7
    before = current_latency_us()
    srv = Server(f"dct-test-{uuid.uuid4().hex[:10]}", interface="virtual", priority=0,
                 pm_qos_us=want)
    srv.start()
    try:
        during = current_latency_us()
        assert during is not None and during <= want
    finally:
        srv.stop()
    assert pm_qos.DEVICE not in open_paths()
    after = current_latency_us()
    if before is not None and before > want:
        # nobody else asked for less meanwhile: the kernel is back where it was
        deadline = time.monotonic() + 5
        while after != before and after is not None and after <= want \
                and time.monotonic() < deadline:
            time.sleep(0.05)
            after = current_latency_us()
        assert after is None or after > want


@pytest.mark.slow
def test_cli_options(tmp_path):
    base = [sys.executable, "-m", "dct_hil.cli", "serve", "--channel", "x", "--priority", "0",
            "--duration", "0.2", "--quiet", "--stats", str(tmp_path / "s.json")]
    r = subprocess.run(base + ["--pm-qos-us", "-3"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--pm-qos-us" in lines[0]
    r = subprocess.run(base + ["--no-pm-qos"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "PM QoS            off (no request asked for)" in r.stdout
    r = subprocess.run(base, capture_output=True, text=True, timeout=120)
    assert r.returncode == 3 or r.returncode == 0, r.stderr     # no TCU: INVALID, exit 0 or 3
    assert "PM QoS            off (normal scheduling (priority 0): no request)" in r.stdout
    r = subprocess.run(base + ["--no-pm-qos", "--pm-qos-us", "5"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
