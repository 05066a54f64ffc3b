"""Floods and fuzzing on real SocketCAN (vcan0).

- A second node floods vcan0 for 12 s (``cangen -g 0``: frames back to back,
  as fast as the kernel takes them, more than a 1 Mbit/s bus carries; the
  server's socket buffer overflows within the first second), then
  sends a burst larger than every buffer (the server's socket buffer and
  the kernel's backlog); a TCU that was silent meanwhile sends one frame of
  each of its messages. The loop goes on through it (ticks advance during
  the flood, the plant's frames keep going out), every frame of the second
  node is received (counted as an unknown identifier) or counted as lost
  (the kernel's drops on the server's socket, SO_RXQ_OVFL, and in its
  receive backlog, /proc/net/softnet_stat), and the TCU's first frame after
  the flood is accepted and decoded (its value is the message's last).
- ``rt_loop.tools.fuzz`` over SocketCAN for 20 s with CAN FD frames (1e7 frames on
  the embedded transport are scripts/test-long's) (vcan0's MTU
  raised to 72 for the test): every frame accounted for, the table written
  to the run folder.

In the guest time means nothing: ticks per second and how many
ticks the TCU's first frame waited are written to ``flood.json``, not judged.
"""

import json
import os
import subprocess
import sys
import time

import pytest
from waiting import wait_for

from can_dbc import codec

pytestmark = pytest.mark.vcan

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FLOOD_S = 12                    # six samples of the loop during the flood, 2 s apart
FLOOD_ID = 0x7A1
WAIT_S = 300.0


def softnet_drops():
    total = 0
    with open("/proc/net/softnet_stat", encoding="ascii") as f:
        for line in f:
            total += int(line.split()[1], 16)
    return total


def if_tx(name):
    with open(f"/sys/class/net/{name}/statistics/tx_packets", encoding="ascii") as f:
        return int(f.read())


def _wait(pred, what, timeout=WAIT_S):
    return wait_for(pred, what, timeout, step=0.05)


def _taken(c):
    return int(c["rx"]["frames"]) + int(c["rx"]["overflow"])


def _quiet(srv, what):
    """Until the server's received counts stop moving (the socket drained)."""
    last, same = None, 0
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        now = _taken(srv.snapshot()["counts"])
        same = same + 1 if now == last else 0
        last = now
        if same >= 10:
            return now
        time.sleep(0.1)
    raise AssertionError(f"the server's counts did not settle after {what}")


@pytest.fixture(scope="module")
def flood(vcan0, tmp_path_factory):
    import can

    from rt_loop.server import Server

    d = tmp_path_factory.mktemp("flood")
    r = {"dir": d}
    tx0 = if_tx(vcan0)
    drops0 = softnet_drops()
    srv = Server(vcan0, interface="socketcan", priority=0, pm_qos_us=None)
    bus = can.Bus(interface="socketcan", channel=vcan0)
    sent_tcu = 0
    counters = {}

    def tcu_frames(values=None):
        nonlocal sent_tcu
        for name in ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd"):
            c = counters.get(name, -1) + 1
            counters[name] = c % 16
            data = codec.encode(name, (values or {}).get(name, {}), c % 16)
            bus.send(can.Message(arbitration_id=codec.message(name).frame_id,
                                 is_extended_id=False, data=data))
            sent_tcu += 1

    try:
        srv.start()
        r["rcvbuf_frames"] = srv.transport.rcvbuf_frames
        for _ in range(5):
            tcu_frames()
        _wait(lambda: srv.snapshot()["counts"]["rx"]["accepted"] >= 15, "the TCU's frames")
        before = srv.snapshot()
        t0 = time.monotonic()
        samples = []
        flood_p = subprocess.Popen(
            ["cangen", vcan0, "-g", "0", "-i", "-I", f"{FLOOD_ID:X}", "-L", "8", "-D", "i"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            while time.monotonic() - t0 < FLOOD_S:
                s = srv.snapshot()
                samples.append((time.monotonic() - t0, s["counts"]["ticks"],
                                s["counts"]["tx"]["frames"], _taken(s["counts"])))
                time.sleep(2.0)
        finally:
            flood_p.terminate()
            flood_p.wait(timeout=WAIT_S)
        r["flood_wall_s"] = time.monotonic() - t0
        r["samples"] = samples
        r["after_flood"] = srv.snapshot()
        # a burst larger than every buffer: the socket's and the kernel's backlog
        r["burst_frames"] = burst = 4 * r["rcvbuf_frames"] + 10_000
        subprocess.run(["cangen", vcan0, "-g", "0", "-i", "-n", str(burst), "-I",
                        f"{FLOOD_ID + 1:X}", "-L", "8", "-D", "i"],
                       check=True, timeout=WAIT_S, capture_output=True)
        _quiet(srv, "the burst")
        # the TCU again: one frame of each message, SolenoidCurrent1 = 0.5 A
        pre = srv.snapshot()
        tcu_frames({"TCU_ClutchCmd": {"SolenoidCurrent1": 0.5}})
        r["resume"] = _wait(
            lambda: (lambda s: s if s["counts"]["rx"]["accepted"] >= pre["counts"]["rx"]["accepted"] + 3
                     else None)(srv.snapshot()), "the TCU's frames after the flood")
        r["resume_ticks"] = r["resume"]["counts"]["ticks"] - pre["counts"]["ticks"]
        # the value the loop decoded from the first ClutchCmd after the flood (the
        # plant's input falls back to 0 A when the message times out again)
        index = srv.faults.names.signals["TCU_ClutchCmd.SolenoidCurrent1"][2]
        r["solenoid_current1_signal"] = float(srv._l.signal_values[index])
        r["pre_resume"] = pre
        _quiet(srv, "the TCU's frames")
        r["before"] = before
    finally:
        srv.stop()
        bus.shutdown()
    r["report"] = srv.report(histograms=False)
    r["state"] = r["report"]["run"]["state"]
    r["others"] = if_tx(vcan0) - tx0 - r["report"]["counts"]["tx"]["frames"]
    r["softnet_drops"] = softnet_drops() - drops0
    c = r["report"]["counts"]
    out = {k: v for k, v in r.items() if k not in ("dir", "report", "before", "after_flood",
                                                   "resume", "pre_resume")}
    out["ticks_during_flood_per_s"] = (
        (r["samples"][-1][1] - r["samples"][0][1]) / (r["samples"][-1][0] - r["samples"][0][0])
        if len(r["samples"]) >= 2 else None)
    out["counts"] = {"rx": c["rx"], "tx": c["tx"], "ticks": c["ticks"],
                     "overruns": c["overruns"], "timeouts": c["timeouts"]}
    out["sent_tcu"] = sent_tcu
    (d / "flood.json").write_text(json.dumps(out, indent=1, default=str) + "\n")
    r["sent_tcu"] = sent_tcu
    return r


def test_the_loop_goes_on_through_a_flood(flood):
    s = flood["samples"]
    assert len(s) >= 3
    ticks = [x[1] for x in s]
    sent = [x[2] for x in s]
    # every sample during the flood saw new ticks and new plant frames on the bus
    assert all(b > a for a, b in zip(ticks, ticks[1:])), ticks
    assert all(b > a for a, b in zip(sent, sent[1:])), sent
    assert flood["state"] == "stopped", flood["report"]["run"]
    assert flood["report"]["run"]["error"] is None


def test_every_frame_of_the_flood_is_received_or_counted_lost(flood):
    rx = flood["report"]["counts"]["rx"]
    counted = rx["frames"] + rx["overflow"] + flood["softnet_drops"]
    assert counted == flood["others"], (
        f"{flood['others']} frames of other nodes on vcan0, {rx['frames']} received, "
        f"{rx['overflow']} dropped on the socket, {flood['softnet_drops']} in the backlog")
    assert rx["unknown_id"] + rx["overflow"] + flood["softnet_drops"] \
        == flood["others"] - flood["sent_tcu"]
    # the burst is larger than the socket buffer, but a loop that drains it as fast as it
    # comes loses nothing: losses are not required, only counted when they happen


def test_the_tcu_is_taken_again_with_its_first_frame_after_the_flood(flood):
    rx = flood["report"]["counts"]["rx"]
    assert rx["bad_counter"] == 0 and rx["bad_crc"] == 0 and rx["bad_length"] == 0
    assert flood["solenoid_current1_signal"] == pytest.approx(0.5)


@pytest.fixture
def fd_mtu(vcan0):
    def mtu(n):
        subprocess.run(["ip", "link", "set", vcan0, "down"], check=True)
        subprocess.run(["ip", "link", "set", vcan0, "mtu", str(n)], check=True)
        subprocess.run(["ip", "link", "set", vcan0, "up"], check=True)
    mtu(72)
    try:
        yield vcan0
    finally:
        mtu(16)


def test_fuzz_on_vcan0_explains_every_frame(fd_mtu, tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    out = d / "fuzz.json"
    p = subprocess.run([sys.executable, "-m", "rt_loop.tools.fuzz", "--transport", "socketcan",
                        "--channel", fd_mtu, "--fd", "--seconds", "20", "--time-scale", "0.02",
                        "--bursts", "1", "--burst-frames", "5000", "--silent-restarts", "1",
                        "--xcp-packets", "100", "--seed", "18", "--json", str(out), "--quiet"],
                       cwd=REPO, capture_output=True, text=True, timeout=1800)
    (d / "fuzz.txt").write_text(p.stdout + p.stderr)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    r = json.loads(out.read_text())
    assert r["unexplained"] == 0
    assert r["sent_by_kind"]["fd"] > 0
