"""Plant server over the bridge transport (python-can's virtual bus), on the host.

A server and a test TCU (can_dbc.peer.CanPeer) share a virtual channel in
this process. The loop runs with priority 0 (normal scheduling): no
privileges needed, and nothing here depends on timing; every wait is for a
behaviour, with a generous time limit.
"""

import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid

import can
import numpy as np
import pytest
from waiting import wait_until

from can_dbc import codec
from can_dbc.peer import CanPeer
from dct_hil import cli
from rt_loop import stats as rt_stats
from rt_loop import status as rt_status
from rt_loop.server import Server, ServerError
from rt_loop.transport import (
    BridgeTransport,
    SocketCanTransport,
    TransportError,
    default_interface,
    open_transport,
)

PLANT_2MS = ("DCT_ShaftSpeeds", "DCT_OutputSpeeds", "DCT_Clutch")
PLANT_10MS = ("DCT_Shift", "VEH_Motion", "VEH_Driver")
PLANT_MESSAGES = PLANT_2MS + PLANT_10MS + ("SIM_Status",)
TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd", "TCU_Status")
WAIT_S = 20.0




def counts(srv):
    return srv.snapshot()["counts"]


@pytest.fixture
def channel():
    return f"dct-test-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def tcu(channel):
    """A test TCU. Its bus is open before the server starts, so it receives every
    plant frame; it starts sending once the server runs, so the server receives
    every TCU frame."""
    peer = CanPeer.open("tcu", interface="virtual", channel=channel, start=False)
    yield peer
    peer.close()


@pytest.fixture
def server(channel, tcu):
    srv = Server(channel, interface="virtual", priority=0)
    srv.start()
    tcu.start()
    yield srv
    srv.stop()


def silence(peer):
    for name in TCU_MESSAGES:
        peer.enable(name, False)


def all_delivered(srv, peer):
    """Every frame the peer put on the bus was read by the loop or counted as lost."""
    c = counts(srv)
    return c["rx"]["frames"] + c["rx"]["overflow"] == sum(peer.sent.values()) + peer.injected


# ------------------------------------------------------------------ plant -> TCU
@pytest.mark.slow
def test_plant_messages_arrive_with_valid_e2e_at_their_relative_rates(server, tcu):
    assert tcu.wait_for(lambda p: p.counts("SIM_Status")["accepted"] >= 12, timeout=WAIT_S)
    server.stop()
    sent = counts(server)["tx"]["frames"]
    assert counts(server)["tx"]["dropped"] == 0
    assert tcu.wait_for(lambda p: sum(p.counts(m)["received"] for m in PLANT_MESSAGES) == sent)

    got = {m: tcu.counts(m) for m in PLANT_MESSAGES}
    for name, c in got.items():
        assert c["accepted"] == c["received"] > 0, (name, c)      # every frame passes E2E
        assert c["bad_crc"] == c["bad_counter"] == c["bad_length"] == 0, (name, c)
    assert tcu.unknown_frames == 0
    fast = [got[m]["accepted"] for m in PLANT_2MS]
    slow = [got[m]["accepted"] for m in PLANT_10MS]
    status_frames = got["SIM_Status"]["accepted"]
    # at 2 kHz: a 2 ms message every 4th tick, a 10 ms one every 20th, SIM_Status
    # every 200th plus one last frame when the loop stops
    ticks = counts(server)["ticks"]
    assert all(abs(n - ticks / 4) <= 1 for n in fast), (ticks, fast)
    assert all(abs(n - ticks / 20) <= 1 for n in slow), (ticks, slow)
    assert abs(status_frames - 1 - ticks / 200) <= 1, (ticks, status_frames)

    engine = tcu.last("DCT_ShaftSpeeds")["EngineSpeed"]
    assert 500 < engine < 1000                          # idling
    assert tcu.last("SIM_Status")["SimState"] == 2      # the last frame says: stopped


def test_sim_status_reports_running_once_the_tcu_is_heard(server, tcu):
    assert tcu.wait_for(lambda p: (p.last("SIM_Status") or {}).get("SimState") == 1)
    c = counts(server)
    assert all(not m["timed_out"] for m in c["tcu_messages"].values())
    assert c["rx"]["accepted"] == c["rx"]["frames"] > 0


# ------------------------------------------------------------------ TCU -> plant
def clutch1_bar(peer):
    """K1 pressure in the last DCT_Clutch the TCU received (NaN before the first)."""
    last = peer.last("DCT_Clutch")
    return math.nan if last is None else last["ClutchPressure1"]


def test_solenoid_current_raises_the_clutch_pressure_the_tcu_sees(server, tcu):
    assert tcu.wait_for(lambda p: not math.isnan(clutch1_bar(p)))
    assert clutch1_bar(tcu) < 1.0
    tcu.set(SolenoidCurrent1=0.8)
    assert tcu.wait_for(lambda p: clutch1_bar(p) > 5.0)
    plant = server.snapshot()["plant"]
    assert plant["solenoid_current1_a"] == pytest.approx(0.8, abs=1e-3)
    assert plant["clutch1_pressure_bar"] > 5.0
    assert tcu.last("DCT_Clutch")["ClutchPressure2"] < 1.0


def test_a_silent_tcu_times_out_and_the_plant_falls_back_to_safe_values(server, tcu):
    tcu.set(SolenoidCurrent1=0.8, ForkForce1=300.0)
    assert tcu.wait_for(lambda p: clutch1_bar(p) > 5.0)
    assert wait_until(lambda: all(not m["timed_out"]
                                  for m in counts(server)["tcu_messages"].values()))
    silence(tcu)

    def all_timed_out():
        msgs = counts(server)["tcu_messages"]
        return all(m["timed_out"] and m["timeouts"] >= 1 for m in msgs.values())

    assert wait_until(all_timed_out)
    assert tcu.wait_for(lambda p: clutch1_bar(p) < 1.0)
    plant = server.snapshot()["plant"]
    assert plant["solenoid_current1_a"] == 0.0
    assert plant["torque_request_active"] == 0.0
    assert counts(server)["timeouts"] >= 3

    # the TCU comes back: accepted again, the pressure rises again
    tcu.enable("TCU_ClutchCmd", True)
    assert wait_until(lambda: not counts(server)["tcu_messages"]["TCU_ClutchCmd"]["timed_out"])
    assert tcu.wait_for(lambda p: clutch1_bar(p) > 5.0)
    assert counts(server)["rx"]["bad_counter"] == 0


def test_bad_frames_are_rejected_and_counted_and_the_loop_goes_on(server, tcu, channel):
    tcu.enable("TCU_EngineCmd", False)      # injected by hand below, once timed out (its
    assert wait_until(lambda: counts(server)["tcu_messages"]["TCU_EngineCmd"]["timeouts"] == 1)
    assert wait_until(lambda: counts(server)["rx"]["accepted"] > 0)   # counter state is reset)
    clutch_id = codec.message("TCU_ClutchCmd").frame_id
    engine_id = codec.message("TCU_EngineCmd").frame_id

    engine_accepted = counts(server)["tcu_messages"]["TCU_EngineCmd"]["accepted"]
    engine = codec.encode("TCU_EngineCmd", {"EngineTorqueRequest": 20.0}, counter=5)
    tcu.inject(engine_id, engine)                   # accepted
    tcu.inject(engine_id, engine)                   # the same counter again: bad counter
    bad_crc = bytearray(codec.encode("TCU_ClutchCmd", {"SolenoidCurrent1": 0.5}, counter=3))
    bad_crc[0] ^= 0x5A
    tcu.inject(clutch_id, bytes(bad_crc))           # bad CRC
    tcu.inject(clutch_id, codec.encode("TCU_ClutchCmd", {}, counter=3)[:7])  # wrong length
    tcu.inject(0x7FF, bytes(8))                     # unknown identifier
    tcu.inject(clutch_id, bytes(8), is_extended_id=True)  # an extended id: unknown too
    raw = can.Bus(interface="virtual", channel=channel)
    try:
        raw.send(can.Message(arbitration_id=clutch_id, is_remote_frame=True, dlc=8))
    finally:
        raw.shutdown()

    ticks_before_burst = counts(server)["ticks"]
    for i in range(10_000):
        tcu.inject(0x123, i.to_bytes(2, "little") * 4)
    received_before = sum(tcu.counts(m)["accepted"] for m in PLANT_MESSAGES)

    silence(tcu)
    assert wait_until(lambda: all_delivered(server, tcu)), counts(server)
    c = counts(server)
    rx = c["rx"]
    assert rx["bad_counter"] == 1, c
    assert rx["bad_crc"] == 1
    assert rx["bad_length"] == 1
    assert rx["unknown_id"] + rx["overflow"] == 10_000 + 2
    assert rx["overflow"] == c["bridge"]["rx_ring_full"]      # drops counted, not silent
    assert rx["rejected"] == rx["unknown_id"] + 3
    assert rx["frames"] == rx["accepted"] + rx["rejected"]
    assert c["tcu_messages"]["TCU_EngineCmd"]["accepted"] == engine_accepted + 1
    assert c["bridge"]["rx_remote_frames"] == 1              # not forwarded, counted

    # the loop went on: ticks increase and plant frames keep coming
    assert c["ticks"] > ticks_before_burst
    assert wait_until(lambda: counts(server)["ticks"] > c["ticks"] + 100)
    assert tcu.wait_for(lambda p: sum(p.counts(m)["accepted"] for m in PLANT_MESSAGES)
                        > received_before + 50)
    assert server.running and server.state == "running"


# ------------------------------------------------------------------ traffic log
@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_traffic_log_holds_both_directions_and_opens_in_python_can(tmp_path, channel, suffix):
    path = tmp_path / f"traffic{suffix}"
    channel += "-70000"     # a number no log format can hold as a channel number
    srv = Server(channel, interface="virtual", priority=0, log_path=path)
    srv.start()
    try:
        peer = CanPeer.open("tcu", interface="virtual", channel=channel)
        try:
            assert peer.wait_for(lambda p: p.counts("SIM_Status")["accepted"] >= 3)
        finally:
            peer.close()
    finally:
        srv.stop()
    c = counts(srv)
    assert srv.logger.error is None
    assert c["log"]["dropped"] == 0 and c["log"]["written"] > 0

    frames = list(can.LogReader(str(path)))
    rx = [m for m in frames if m.is_rx]
    tx = [m for m in frames if not m.is_rx]
    assert len(frames) == c["log"]["written"] == c["rx"]["frames"] + c["tx"]["frames"]
    assert len(rx) == c["rx"]["frames"] > 0 and len(tx) == c["tx"]["frames"] > 0
    tcu_ids = {codec.message(m).frame_id for m in TCU_MESSAGES}
    plant_ids = {codec.message(m).frame_id for m in PLANT_MESSAGES}
    assert {m.arbitration_id for m in rx} <= tcu_ids
    assert {m.arbitration_id for m in tx} == plant_ids
    check = codec.E2eReceiver(sender="PLANT")
    assert all(check.receive(m.arbitration_id, bytes(m.data))[0] == codec.OK for m in tx)
    stamps = [m.timestamp for m in frames]
    assert stamps == sorted(stamps)


def test_unknown_log_format_is_a_one_line_error(tmp_path, channel):
    srv = Server(channel, interface="virtual", priority=0, log_path=tmp_path / "x.xyz")
    with pytest.raises(ServerError) as e:
        srv.start()
    assert "\n" not in str(e.value) and ".xyz" in str(e.value) and ".log" in str(e.value)
    assert not srv.running


# ------------------------------------------------------------------ transports
def test_default_interface_is_virtual_without_a_can_netdev():
    name, why = default_interface("no-such-can9")
    assert name == "virtual" and "no-such-can9" in why
    t = open_transport(None, f"dct-test-{uuid.uuid4().hex[:8]}")
    try:
        assert isinstance(t, BridgeTransport) and t.chosen_because and not t.hard_real_time
    finally:
        t.close()


def test_socketcan_without_kernel_support_is_a_one_line_error():
    try:
        t = SocketCanTransport("no-such-can9")
    except TransportError as e:
        assert "\n" not in str(e) and ("SocketCAN" in str(e))
    else:  # a kernel with CAN: the missing interface must be the error then
        t.close()
        pytest.fail("bound to a CAN interface that does not exist")


def test_unknown_interface_is_a_one_line_error():
    with pytest.raises(TransportError) as e:
        open_transport("no-such-interface", "x")
    assert "\n" not in str(e.value) and "virtual" in str(e.value)


# ------------------------------------------------------------------ statistics
def test_percentiles_from_a_histogram():
    hist = np.zeros(5000, dtype=np.uint64)
    hist[10] = 900                    # 900 ticks in [10, 11) us
    hist[20] = 99                     # 99 in [20, 21) us
    hist[4999] = 1                    # one above the histogram
    fig = rt_stats.hist_percentiles(hist, max_us=7000.0)
    assert fig["samples"] == 1000
    assert fig["p50_us"] == 11.0 and fig["p90_us"] == 11.0
    assert fig["p99_us"] == 21.0
    assert fig["p99_9_us"] == 21.0
    assert fig["max_us"] == 7000.0
    # never above the maximum the loop measured
    assert rt_stats.hist_percentiles(hist[:21], max_us=20.5)["p99_us"] == 20.5
    empty = rt_stats.hist_percentiles(np.zeros(5000, dtype=np.uint64), 0.0)
    assert empty["samples"] == 0 and empty["p50_us"] is None


def test_live_status_redraws_in_place_on_a_terminal_and_prints_lines_otherwise(server, tcu):
    assert tcu.wait_for(lambda p: p.counts("DCT_Clutch")["accepted"] > 0)
    snap = server.snapshot()
    term = io.StringIO()
    view = rt_status.LiveStatus(term, tty=True)
    view.update(snap, server)
    first = term.getvalue()
    view.update(snap, server)
    second = term.getvalue()[len(first):]
    n = len(rt_status.screen_lines(snap, server))
    assert view.interval_s < 0.5
    assert first.count("\n") == n and second.startswith(f"\x1b[{n}F")
    for word in ("turnaround", "overruns", "rx ", "tx ", "timeouts", "rpm", "km/h", "bar",
                 "ClutchCmd"):
        assert word in first

    pipe = io.StringIO()
    lines = rt_status.LiveStatus(pipe, tty=False)
    assert lines.interval_s == 1.0
    lines.update(snap, server)
    lines.update(snap, server)
    out = pipe.getvalue().splitlines()
    assert len(out) == 2 and "\x1b" not in pipe.getvalue() and "turnaround" in out[0]


# ------------------------------------------------------------------ dct-hil serve
def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow
def test_serve_writes_the_json_stats(capsys, tmp_path, channel):
    stats = tmp_path / "serve.json"
    log = tmp_path / "serve.log"
    code, out, err = run_cli(capsys, "serve", "--interface", "virtual", "--channel", channel,
                             "--duration", "0.5", "--priority", "0", "--stats", stats,
                             "--log", log, "--quiet")
    assert code == 0, err
    assert "soft real time" in out and str(stats) in out and "p99.9" in out
    assert "timing is not real time" in err
    report = json.loads(stats.read_text())
    for key in ("turnaround", "execution", "wakeup_latency"):
        fig = report[key]
        for p in ("p50_us", "p90_us", "p99_us", "p99_9_us", "max_us"):
            assert isinstance(fig[p], float) and fig[p] >= 0, (key, p)
        assert fig["p50_us"] <= fig["p99_us"] <= fig["p99_9_us"] <= fig["max_us"]
        assert fig["samples"] == report["counts"]["ticks"]
    c = report["counts"]
    assert c["ticks"] > 0 and c["tx"]["frames"] > 0
    for key in ("frames", "accepted", "unknown_id", "bad_length", "bad_crc", "bad_counter",
                "overflow"):
        assert c["rx"][key] == 0
    assert set(c["tcu_messages"]) == set(TCU_MESSAGES)
    assert all(m["timed_out"] for m in c["tcu_messages"].values())   # no TCU on the bus
    assert c["log"] == {"written": c["tx"]["frames"], "dropped": 0}
    cfg = report["config"]
    assert cfg["rate_hz"] == 2000 and cfg["priority"] == 0 and cfg["interface"] == "virtual"
    assert cfg["transport"] == "bridge" and cfg["real_time"] == "soft"
    assert cfg["channel"] == channel and cfg["duration_s"] == 0.5
    assert cfg["rt_policy_ok"] is False and cfg["memory_locked"] is False
    assert report["run"]["state"] == "stopped"
    for key in ("cpu", "kernel", "python"):
        assert report["machine"][key]
    assert report["date"]


def serve_process(tmp_path, *extra, prefix=()):
    stats = tmp_path / "stats.json"
    argv = [*prefix, sys.executable, "-m", "dct_hil.cli", "serve", "--interface", "virtual",
            "--channel", "proc", "--stats", str(stats), *extra]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    return proc, stats


def stop_with(proc, sig):
    line = proc.stdout.readline()       # the banner: the server is up
    assert line.startswith("dct-hil serve"), line + proc.stderr.read()
    while not (line.startswith("t=") and not line.startswith("t=0.0s")):
        line = proc.stdout.readline()   # a status line after the start: the loop runs
        assert line, proc.stderr.read()
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    return proc.returncode, out, err


@pytest.mark.slow
def test_sigterm_stops_serve_cleanly_with_the_stats_written(tmp_path):
    proc, stats = serve_process(tmp_path, "--priority", "0", "--log", "t.log")
    code, out, err = stop_with(proc, signal.SIGTERM)
    assert code == 0, err
    assert "stats" in out and "Traceback" not in err
    report = json.loads(stats.read_text())
    assert report["run"]["state"] == "stopped" and report["counts"]["ticks"] > 0
    written = report["counts"]["log"]["written"]
    assert written > 0 and len((tmp_path / "t.log").read_text().splitlines()) == written


@pytest.mark.slow
def test_sigint_stops_serve_with_exit_130_and_the_stats_written(tmp_path):
    proc, stats = serve_process(tmp_path, "--priority", "0")
    code, out, err = stop_with(proc, signal.SIGINT)
    assert code == 130, err
    assert json.loads(stats.read_text())["run"]["state"] == "stopped"


@pytest.mark.slow
def test_serve_without_real_time_rights_runs_and_warns(tmp_path):
    prefix = ()
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("running as root and setpriv is missing: cannot drop CAP_SYS_NICE")
        prefix = ("setpriv", "--bounding-set", "-sys_nice,-ipc_lock", "--inh-caps",
                  "-sys_nice,-ipc_lock")
    proc, stats = serve_process(tmp_path, "--duration", "0.5", prefix=prefix)  # priority 80
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    report = json.loads(stats.read_text())
    if report["config"]["rt_policy_ok"] and report["config"]["memory_locked"]:
        pytest.skip("this account may use SCHED_FIFO and mlockall")
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) >= 1 and "timing is not real time" in warnings[0]
    assert report["counts"]["ticks"] > 0


BAD_OPTIONS = {
    "rate zero": (["--rate", "0"], ["--rate"]),
    "rate below the loop's longest period": (["--rate", "50"], ["--rate", "100"]),
    "rate too high": (["--rate", "20001"], ["--rate", "20000"]),
    "rate not a number": (["--rate", "fast"], ["--rate"]),
    "priority too high": (["--priority", "100"], ["--priority"]),
    "priority negative": (["--priority", "-1"], ["--priority"]),
    "negative duration": (["--duration", "-1"], ["--duration"]),
    "zero duration": (["--duration", "0"], ["--duration"]),
    "unknown interface": (["--interface", "nosuch"], ["nosuch"]),
    "unknown overrun policy": (["--overrun", "maybe"], ["--overrun"]),
    "cpu that does not exist": (["--cpu", "4096"], ["cpu 4096"]),
    "unknown log format": (["--log", "{tmp}/x.xyz"], ["x.xyz", ".log"]),
    "missing parameter file": (["--params", "{tmp}/none.toml"], ["none.toml"]),
    "bit rate on socketcan": (["--interface", "socketcan", "--bitrate", "500000"], ["socketcan"]),
    "missing mapping file": (["--mapping", "{tmp}/none.toml"], ["none.toml"]),
    "bus the mapping lacks": (["--mapping", "vehicle", "--bus", "xx=ch"], ["bus 'xx'", "pt, io"]),
    "bus without a channel": (["--mapping", "vehicle", "--bus", "io"], ["--bus", "NAME=CHANNEL"]),
    "one channel for two buses": (["--mapping", "vehicle", "--bus", "io=same", "--bus", "pt=same"],
                                  ["same", "channel of its own"]),
    "dbc for a bus the mapping lacks": (["--mapping", "vehicle", "--dbc", "zz=x.dbc"], ["zz"]),
    "dbc cantools cannot parse": (["--dbc", "README.md"], ["README.md"]),
    "socketcan bus without --bus": (["--mapping", "vehicle", "--interface", "socketcan"],
                                    ["io", "--bus io=CHANNEL"]),
    "cycle times the rate cannot hit": (["--mapping", "vehicle", "--rate", "300"], ["cycle"]),
}


@pytest.mark.parametrize("case", sorted(BAD_OPTIONS))
def test_serve_bad_options_are_one_line_exit_2(capsys, tmp_path, case):
    argv, fragments = BAD_OPTIONS[case]
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    for option, value in (("--interface", "virtual"), ("--priority", "0"), ("--duration", "0.2")):
        if option not in argv:
            argv += [option, value]
    code, out, err = run_cli(capsys, "serve", "--channel", f"bad-{uuid.uuid4().hex[:6]}",
                             "--stats", tmp_path / "s.json", *argv)
    assert code == 2, (out, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: "), err
    for f in fragments:
        assert f in lines[0], err
    assert not (tmp_path / "s.json").exists()


def test_serve_on_socketcan_without_can_in_the_kernel_is_one_line(capsys, tmp_path):
    try:
        SocketCanTransport("vcan0").close()
    except TransportError:
        pass
    else:
        pytest.skip("vcan0 exists here")
    code, out, err = run_cli(capsys, "serve", "--interface", "socketcan", "--channel", "vcan0",
                             "--priority", "0", "--duration", "0.2", "--stats",
                             tmp_path / "s.json")
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1 and "SocketCAN" in lines[0], err


# ------------------------------------------------------------ early wake-up

def test_early_wake_up_keeps_the_loop_running_and_is_reported(channel, tcu):
    """A spin of 200 us (the early wake-up busy-waited to each deadline)
    changes when a tick starts, not what it does: frames flow, ticks
    count, and the configuration reports the spin."""
    srv = Server(channel, interface="virtual", priority=0, spin_us=200.0)
    srv.start()
    tcu.start()
    try:
        assert tcu.wait_for(lambda p: p.counts("DCT_Clutch")["accepted"] > 20, timeout=10.0)
    finally:
        srv.stop()
    assert srv.config()["spin_us"] == 200.0
    assert counts(srv)["ticks"] > 80


@pytest.mark.parametrize("spin_us", [-1.0, 400.0, math.nan])
def test_early_wake_up_outside_the_period_is_a_one_line_error(channel, spin_us):
    with pytest.raises(ServerError) as e:
        Server(channel, interface="virtual", priority=0, spin_us=spin_us)
    assert "spin" in str(e.value) and "\n" not in str(e.value)


# ---------------------------------------------------- time scale, driver, recording
def test_a_slowed_down_server_steps_the_plant_and_stretches_the_bus_cycles(channel, tmp_path):
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel)
    try:
        with Server(channel, interface="virtual", priority=0, time_scale=0.25,
                    record_path=tmp_path / "rec.csv") as srv:
            assert srv.step_s == 0.0005 and srv.period_s == pytest.approx(0.002)
            assert srv.config()["time_scale"] == 0.25
            assert peer.wait_for(lambda p: p.counts("DCT_ShaftSpeeds")["accepted"] >= 50, WAIT_S)
            time.sleep(0.3)
        report = peer.report()
        rec = srv.report()
    finally:
        peer.close()
    # 2 ms of plant time between frames = 8 ms of wall time at a quarter of real time
    mean_ms = report["received"]["DCT_ShaftSpeeds"]["mean_interval_ms"]
    assert 4.0 < mean_ms < 16.0, mean_ms
    assert rec["config"]["period_us"] == pytest.approx(2000.0)
    assert rec["run"]["sim_time_s"] == pytest.approx(rec["run"]["ticks"] * 0.0005, abs=1e-9)


@pytest.mark.parametrize("kwargs, words", [
    ({"time_scale": 0}, "time scale must be above 0"),
    ({"time_scale": 2}, "at most 1"),
    ({"time_scale": "x"}, "is not a number"),
    ({"time_scale": 0.001}, "allows up to 100 ms"),
    ({"driver": [(0, 0, 0), (0, 1, 0)]}, "times must be finite and increasing"),
    ({"driver": [(0, 120, 0)]}, "pedals must be within"),
    ({"driver": [(k, 0, 0) for k in range(65)]}, "the loop holds 64"),
    ({"driver": [(0, 0)]}, "rows must be (t_s"),
    ({"driver": [(0, 0, 0, "D"), (1, 0, 0, "X")]}, "driver table row 2: unknown selector position 'X'"),
    ({"driver": [(0, 0, 0)], "maneuver_inputs": {"road_grade_pct": 50}},
     "maneuver inputs: road_grade_pct = 50 is outside -40 .. 40"),
    ({"maneuver_end_s": 3.0}, "needs a driver table"),
    ({"driver": [(0, 0, 0)], "maneuver_start": "later"}, "maneuver start"),
    ({"record_every_s": 0}, "record interval"),
])
def test_bad_time_scale_driver_or_recording_is_a_one_line_error(channel, kwargs, words):
    with pytest.raises(ServerError) as e:
        Server(channel, interface="virtual", priority=0, **kwargs)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_a_maneuvers_grade_and_first_selector_hold_while_it_waits_for_the_tcu(channel):
    from plant.maneuvers import get_maneuver

    m = get_maneuver("hill-start")
    rows = [(0.0, 0.0, 60.0, "N"), (1.0, 0.0, 0.0, "D")]
    srv = Server(channel, interface="virtual", priority=0, driver=rows, maneuver_inputs=m.inputs)
    srv.start()
    try:
        time.sleep(0.2)
        snap = srv.snapshot()
        assert snap["maneuver"] == "waiting for the TCU"
        assert snap["plant"]["brake_pedal_pct"] == 60.0
        inputs = srv._l.plant.inputs
        assert (float(inputs.road_grade_pct), float(inputs.selector_lever)) == (20.0, 2.0)
    finally:
        srv.stop()


def test_the_driver_table_waits_for_the_tcu_and_the_recording_holds_the_run(channel, tmp_path):
    from rt_loop.measure.recorder import read_recording

    rows = [(0.0, 0.0, 30.0), (0.2, 20.0, 0.0)]
    path = tmp_path / "rec.csv"
    srv = Server(channel, interface="virtual", priority=0, driver=rows, maneuver_end_s=0.5,
                 record_path=path, record_every_s=0.002)
    srv.start()
    try:
        time.sleep(0.2)
        snap = srv.snapshot()
        assert snap["maneuver"] == "waiting for the TCU" and snap["maneuver_time_s"] is None
        assert snap["plant"]["brake_pedal_pct"] == 30.0
        peer = CanPeer.open(side="tcu", interface="virtual", channel=channel,
                            values={"SolenoidCurrent1": 0.1})
        try:
            assert srv.wait(WAIT_S), "the maneuver end did not stop the loop"
        finally:
            peer.close()
    finally:
        srv.stop()
    report = srv.report()
    assert report["run"]["state"] == "stopped" and report["run"]["maneuver"] == "done"
    assert report["run"]["maneuver_time_s"] == pytest.approx(0.5, abs=1e-9)
    assert report["record"]["dropped"] == 0 and report["record"]["error"] is None
    rec = read_recording(path)
    assert report["record"]["written"] == len(rec["time_s"]) > 0
    assert np.all(np.diff(rec["tick"]) == 4)                       # every 2 ms of plant time
    assert np.allclose(np.diff(rec["time_s"]), 0.002)
    waiting = np.isnan(rec["maneuver_time_s"])
    assert waiting.any() and not waiting[-1]
    assert np.all(rec["brake_pedal_pct"][waiting] == 30.0)
    mt = rec["maneuver_time_s"][~waiting]
    pedal = rec["accel_pedal_pct"][~waiting]
    assert np.all(pedal[mt < 0.2 - 1e-9] == 0.0) and np.all(pedal[mt > 0.2 + 0.001] == 20.0)
    assert 0.5 - 0.002 < mt[-1] <= 0.5 + 1e-9                       # the last 2 ms sample
    assert "cmd_fork_force1_n" in rec and "cmd_torque_request_active" in rec


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_failing_recording_or_traffic_log_is_reported_and_the_loop_goes_on(
        channel, tmp_path, monkeypatch):
    # the recording goes to /dev/full (every write fails with ENOSPC); the
    # traffic log's writer fails on its first frame. Each reports once, keeps
    # its ring moving (nothing counted as dropped) and the loop runs on.
    def full(self, msg):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(can.CanutilsLogWriter, "on_message_received", full)
    srv = Server(channel, interface="virtual", priority=0, duration_s=0.6,
                 record_path="/dev/full", record_every_s=0.0005,
                 log_path=tmp_path / "traffic.log")
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel)
    try:
        srv.start()
        assert srv.wait(WAIT_S)
    finally:
        srv.stop()
        peer.close()
    report = srv.report()
    assert report["run"]["state"] == "stopped" and report["counts"]["ticks"] >= 500
    for key in ("record", "log"):
        assert "No space left on device" in report[key]["error"], key
        assert report[key]["dropped"] == 0, key
