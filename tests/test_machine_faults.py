"""Faults of the machine under a running plant server, as the user sees them.

``dct-hil serve`` and the reference TCU (``dct-hil tcu``) as two processes on
python-can's ``udp_multicast`` bus (the host kernel has no CAN; the SocketCAN
faults are in tests/vcan/test_can_faults.py), recording to MF4:

- the TCU process killed with SIGKILL mid-run: the server goes on, its
  messages time out (the plant gets the safe values), a TCU started again is
  taken (the timeout reset the counter check: resynchronisation), and the
  summary says ``timed out N times, came back``;
- the server stopped with SIGSTOP for 2 s and continued with SIGCONT: the
  loop goes on, the late tick is counted as an overrun with the skipped
  ticks, the run is reported ``timing: INVALID`` on one warning line, and a
  SIGTERM afterwards ends it with exit 0 and whole files.

The disk filling up during a recording is in tests/test_mdf_recorder.py.
Nothing here asserts a time: the waits only bound a failure. python-can's
udp_multicast binds its port (43113) for every group, so frames of other
groups on this host reach these servers too; nothing here counts on a quiet
port.
"""

import json
import os
import random
import signal
import subprocess
import sys
import time

import pytest
import requires
from waiting import wait_until

requires.module("msgpack")

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DCT_HIL = [sys.executable, "-m", "dct_hil.cli"]
WAIT_S = 60.0


def _group():
    return f"239.{random.randrange(1, 255)}.{random.randrange(1, 255)}.{random.randrange(1, 255)}"


class Bench:
    def __init__(self, tmp_path):
        self.dir = tmp_path
        self.group = _group()
        self.stats = tmp_path / "stats.json"
        self.mf4 = tmp_path / "run.mf4"
        self.sock = tmp_path / "control.sock"
        self.out = open(tmp_path / "serve.out", "w")
        self.err_path = tmp_path / "serve.err"
        self.err = open(self.err_path, "w")
        self.server = subprocess.Popen(
            DCT_HIL + ["serve", "--interface", "udp_multicast", "--channel", self.group,
                       "--priority", "0", "--no-pm-qos", "--quiet", "--stats", str(self.stats),
                       "--record", str(self.mf4), "--control", str(self.sock)],
            cwd=REPO, stdout=self.out, stderr=self.err)
        self.tcus = []
        self.client = None

    def tcu(self):
        p = subprocess.Popen(DCT_HIL + ["tcu", "--interface", "udp_multicast", "--channel",
                                        self.group, "--quiet"],
                             cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self.tcus.append(p)
        return p

    def snapshot(self):
        from rt_loop.control import ControlClient

        if self.client is None:
            assert wait_until(self.sock.exists, WAIT_S), self.err_path.read_text()
            self.client = ControlClient(str(self.sock))
        return self.client.request("snapshot")["snapshot"]

    def counts(self):
        return self.snapshot()["counts"]

    def finish(self):
        if self.client is not None:
            self.client.close()
        for p in self.tcus:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                p.wait(timeout=WAIT_S)
        if self.server.poll() is None:
            self.server.send_signal(signal.SIGTERM)
        rc = self.server.wait(timeout=WAIT_S)
        self.out.close()
        self.err.close()
        return rc


@pytest.fixture
def bench(tmp_path):
    b = Bench(tmp_path)
    try:
        yield b
    finally:
        for p in b.tcus + [b.server]:
            if p.poll() is None:
                p.kill()
                p.wait()


def _accepted(bench):
    return bench.counts()["rx"]["accepted"]


def _mf4_samples(path):
    from asammdf import MDF

    with MDF(str(path)) as mdf:
        t = mdf.get("vehicle_speed_kmh").timestamps
    return len(t), float(t[-1]) if len(t) else None


@pytest.mark.slow
def test_a_tcu_killed_mid_run_times_out_and_a_new_one_is_taken_again(bench):
    tcu = bench.tcu()
    assert wait_until(lambda: _accepted(bench) > 500, WAIT_S), (
        "the TCU's frames were not accepted: " + bench.err_path.read_text()[-1000:])
    tcu.send_signal(signal.SIGKILL)
    tcu.wait(timeout=WAIT_S)
    msgs = lambda: bench.counts()["tcu_messages"]  # noqa: E731 (a short probe, named for the lines below)
    assert wait_until(lambda: all(m["timed_out"] for n, m in msgs().items()
                                  if not m["optional"]), WAIT_S), msgs()
    before = _accepted(bench)
    assert bench.server.poll() is None, "the server stopped with its TCU"
    bench.tcu()
    assert wait_until(lambda: _accepted(bench) > before + 500, WAIT_S)
    m = msgs()
    assert all(not v["timed_out"] for v in m.values() if not v["optional"]), m
    rc = bench.finish()
    assert rc == 0, bench.err_path.read_text()
    stats = json.loads(bench.stats.read_text())
    assert stats["counts"]["tcu_messages"]["TCU_ClutchCmd"]["timeouts"] >= 1
    out = (bench.dir / "serve.out").read_text()
    assert "came back" in out, out[-2000:]
    n, last = _mf4_samples(bench.mf4)
    assert n > 100 and last > 0


@pytest.mark.slow
def test_a_server_stopped_for_2_s_goes_on_counts_the_late_tick_and_says_so(bench):
    bench.tcu()
    assert wait_until(lambda: _accepted(bench) > 500, WAIT_S), bench.err_path.read_text()
    before = bench.counts()
    bench.server.send_signal(signal.SIGSTOP)
    time.sleep(2.0)
    bench.server.send_signal(signal.SIGCONT)
    after_ticks = before["ticks"]
    assert wait_until(lambda: bench.counts()["ticks"] > after_ticks + 2000, WAIT_S)
    c = bench.counts()
    assert c["overruns"] > before["overruns"]
    # 2 s at 2 kHz: about 4000 deadlines missed, skipped and counted
    assert c["skipped_ticks"] - before["skipped_ticks"] >= 2000, c
    acc = c["rx"]["accepted"]
    assert wait_until(lambda: _accepted(bench) > acc + 500, WAIT_S), "no TCU frame after SIGCONT"
    rc = bench.finish()
    err = bench.err_path.read_text()
    assert rc == 0, err
    stats = json.loads(bench.stats.read_text())
    assert stats["verdict"]["valid"] is False
    warnings = [line for line in err.splitlines() if "INVALID" in line]
    assert len(warnings) == 1, err
    assert "overrun" in warnings[0], warnings
    n, last = _mf4_samples(bench.mf4)
    assert n > 100
