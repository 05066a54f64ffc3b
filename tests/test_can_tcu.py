"""The reference TCU as a CAN node (tcu_stub.can_tcu), on the host.

Every test uses python-can's ``virtual`` interface on a channel of its own.
A stand-in plant (can_dbc.peer.CanPeer, side "plant") or the real plant
server shares the channel with the TCU; a third bus listens to check the
TCU's frames. Nothing here asserts timing: every wait is for a behaviour,
with a generous time limit.
"""

import json
import os
import subprocess
import sys
import uuid

import can
import pytest

from can_dbc import codec
from can_dbc.peer import CanPeer
from tcu_stub import can_tcu
from tcu_stub.can_tcu import REJECTS_TO_STALE, CanTcu

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")
PLANT_NEEDED = ("DCT_ShaftSpeeds", "DCT_OutputSpeeds", "DCT_Clutch", "DCT_Shift", "VEH_Motion", "VEH_Driver")
STANDSTILL = {"EngineSpeed": 750, "InputShaft1Speed": 0, "InputShaft2Speed": 0, "OutputShaft1Speed": 0,
              "OutputShaft2Speed": 0, "ClutchPressure1": 0, "ClutchPressure2": 0, "LinePressure": 20,
              "ForkPosition1": 0, "ForkPosition2": 0, "ForkPosition3": 0, "ForkPosition4": 0,
              "SyncState1": 0, "SyncState2": 0, "SyncState3": 0, "SyncState4": 0,
              "VehicleSpeed": 0, "LongAccel": 0, "RoadGrade": 0, "AccelPedal": 0, "BrakePedal": 30,
              "EngineTorque": 20, "SimTime": 12.5, "SimState": 1}
WAIT_S = 20.0


@pytest.fixture
def channel():
    return f"tcu-test-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def listener(channel):
    """A third bus on the channel: sees every frame the TCU and the plant send."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


@pytest.fixture
def plant(channel):
    peer = CanPeer.open("plant", interface="virtual", channel=channel, values=STANDSTILL)
    yield peer
    peer.close()


def drain(bus):
    frames = []
    while True:
        msg = bus.recv(timeout=0.0)
        if msg is None:
            return frames
        frames.append(msg)


def tcu_frames(frames):
    """{message name: [data bytes, ...]} of the TCU's frames, in bus order."""
    ids = {codec.message(n).frame_id: n for n in TCU_MESSAGES}
    out = {n: [] for n in TCU_MESSAGES}
    for f in frames:
        if f.arbitration_id in ids:
            out[ids[f.arbitration_id]].append(bytes(f.data))
    return out


def decoded(data_list, name):
    return [codec.decode(codec.message(name).frame_id, d)[1] for d in data_list]


def fresh(tcu):
    return not tcu.stale and tcu.t_s > 0


# ------------------------------------------------------------------ frames on the bus
def test_sends_all_three_messages_with_valid_e2e_at_their_relative_rates(channel, plant, listener):
    with CanTcu.open("virtual", channel) as tcu:
        assert tcu.wait_for(lambda t: t.sent("TCU_ShiftCmd") >= 60 and fresh(t), timeout=WAIT_S)
        assert tcu.wait_for(lambda t: t.logic.phase == "standstill" and not t.stale)
        # a plant that leaves the selector and the oil temperature out sends their start values
        assert (tcu.sensors["SelectorLever"], tcu.sensors["TransOilTemp"]) == (3, 90)
    frames = tcu_frames(drain(listener))
    rx = codec.E2eReceiver(sender="TCU")
    for name, datas in frames.items():
        assert datas, name
        assert all(rx.check(codec.message(name).frame_id, d) == codec.OK for d in datas), name
        counters = [d[1] & 0x0F for d in datas]
        # lossless bus: each frame's AliveCounter is the previous one + 1
        assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:])), name
    n_fast = len(frames["TCU_ClutchCmd"])
    for name in ("TCU_ShiftCmd", "TCU_EngineCmd"):
        assert 3.5 <= n_fast / len(frames[name]) <= 6.5, (name, n_fast, len(frames[name]))
    # standstill with the brake on: clutches open, 1st and 2nd being pre-selected, no torque request
    shift = decoded(frames["TCU_ShiftCmd"], "TCU_ShiftCmd")[-2]      # the last one is the safe frame
    assert shift["ForkForce1"] > 0 and shift["ForkForce2"] > 0
    clutch = decoded(frames["TCU_ClutchCmd"], "TCU_ClutchCmd")[-2]
    assert clutch["SolenoidCurrent1"] == 0 and clutch["SolenoidCurrent2"] == 0
    rep = tcu.report()
    for name in TCU_MESSAGES:
        assert rep["sent"][name]["frames"] == len(frames[name])
        assert rep["sent"][name]["errors"] == 0
    assert rep["ticks"] > 0 and rep["tick_exec_us"]["n"] == rep["ticks"]


def test_a_silent_plant_makes_it_stale_and_safe_and_its_return_ends_the_episode(channel, plant, listener):
    with CanTcu.open("virtual", channel) as tcu:
        assert tcu.wait_for(fresh, timeout=WAIT_S)
        assert tcu.wait_for(lambda t: t.commands["ForkForce1"] > 0)      # pre-selecting 1st
        for name in PLANT_NEEDED:
            plant.enable(name, False)
        assert tcu.wait_for(lambda t: t.stale, timeout=WAIT_S)
        assert tcu.wait_for(lambda t: t.logic.phase == "stale")
        # the 2 ms messages time out first, the 10 ms ones after 100 ms
        assert tcu.wait_for(lambda t: len(t.report()["stale"]["episodes"][-1]["causes"]) == len(PLANT_NEEDED),
                            timeout=WAIT_S)
        drain(listener)
        n = tcu.ticks
        assert tcu.wait_for(lambda t: t.ticks >= n + 20 and t.sent("TCU_ShiftCmd") > 0, timeout=WAIT_S)
        frames = tcu_frames(drain(listener))
        for c in decoded(frames["TCU_ClutchCmd"], "TCU_ClutchCmd"):
            assert c["SolenoidCurrent1"] == 0 and c["SolenoidCurrent2"] == 0
        for s in decoded(frames["TCU_ShiftCmd"], "TCU_ShiftCmd"):
            assert all(s[f"ForkForce{i}"] == 0 for i in range(1, 5))
        for e in decoded(frames["TCU_EngineCmd"], "TCU_EngineCmd"):
            assert e["TorqueRequestActive"] == 0 and e["EngineTorqueRequest"] == 0
        rep = tcu.report()
        assert rep["stale"]["now"] is True
        episode = rep["stale"]["episodes"][-1]
        assert episode["end_s"] is None
        assert set(episode["causes"]) == set(PLANT_NEEDED)
        assert set(episode["causes"].values()) == {"timeout"}

        for name in PLANT_NEEDED:
            plant.enable(name, True)
        assert tcu.wait_for(lambda t: not t.stale, timeout=WAIT_S)
        assert tcu.wait_for(lambda t: t.commands["ForkForce1"] > 0)      # back to pre-selecting
        rep = tcu.report()
    episode = rep["stale"]["episodes"][-1]
    assert episode["end_s"] is not None and episode["end_s"] > episode["start_s"]
    assert rep["stale"]["episode_count"] == len(rep["stale"]["episodes"]) >= 1
    first = rep["stale"]["episodes"][0]
    if first["start_s"] == 0:          # a plant message had not arrived yet at the first tick
        assert set(first["causes"].values()) == {"missing"}


def test_bad_plant_frames_are_rejected_counted_and_make_it_stale(channel, plant):
    # slow motion (time scale 0.1): 1 s timeouts, so the rejected frames are the cause seen first
    with CanTcu.open("virtual", channel, time_scale=0.1) as tcu:
        assert tcu.wait_for(fresh, timeout=WAIT_S)
        episodes = tcu.report()["stale"]["episode_count"]
        # two bad frames as the newest DCT_ShaftSpeeds for three TCU ticks (its
        # timeout is ten): counted, the last good values stand in, not stale
        shaft = codec.message("DCT_ShaftSpeeds").frame_id
        plant.enable("DCT_ShaftSpeeds", False)
        good = codec.encode("DCT_ShaftSpeeds", {"EngineSpeed": 750}, 3)
        plant.inject(shaft, bytes([good[0] ^ 0x5A]) + good[1:])           # wrong CRC
        plant.inject(shaft, good[:6])                                      # wrong length
        plant.inject(0x7AB, bytes(8))                                      # not a plant message
        assert tcu.wait_for(lambda t: t.counts("DCT_ShaftSpeeds")["bad_crc"] >= 1
                            and t.counts("DCT_ShaftSpeeds")["bad_length"] >= 1, timeout=WAIT_S)
        t_bad = tcu.t_s
        assert tcu.wait_for(lambda t: t.t_s >= t_bad + 3 * tcu.logic.PERIOD_S, timeout=WAIT_S)
        quiet = tcu.report()["stale"]["episode_count"] == episodes and not tcu.stale
        plant.enable("DCT_ShaftSpeeds", True)
        assert quiet
        assert tcu.wait_for(lambda t: t.report()["unknown_frames"] >= 1)
        # REJECTS_TO_STALE bad frames in a row: stale, with the rejections named as the cause
        shift = codec.message("DCT_Shift").frame_id
        plant.enable("DCT_Shift", False)
        for k in range(REJECTS_TO_STALE):
            good = codec.encode("DCT_Shift", {}, k)
            plant.inject(shift, bytes([good[0] ^ 0x01]) + good[1:])
        assert tcu.wait_for(lambda t: t.stale, timeout=WAIT_S)
        rep = tcu.report()
    assert rep["received"]["DCT_ShaftSpeeds"]["rejected"]["bad_crc"] >= 1
    assert rep["received"]["DCT_ShaftSpeeds"]["rejected"]["bad_length"] >= 1
    assert rep["received"]["DCT_Shift"]["rejected"]["bad_crc"] == REJECTS_TO_STALE
    assert rep["stale"]["episodes"][-1]["causes"]["DCT_Shift"] == "rejected"
    assert rep["time_scale"] == 0.1
    assert rep["stale"]["timeout_ms"]["DCT_Shift"] == pytest.approx(1000.0)      # 10 cycles of 10 ms / 0.1
    assert rep["stale"]["timeout_ms"]["DCT_ShaftSpeeds"] == pytest.approx(200.0)


def test_stop_sends_safe_final_frames_and_the_report_is_json(channel, plant, listener, tmp_path):
    tcu = CanTcu.open("virtual", channel)
    assert tcu.wait_for(lambda t: fresh(t) and t.commands["ForkForce1"] > 0 and t.sim_time_s is not None,
                        timeout=WAIT_S)
    tcu.close()
    tcu.close()                                  # twice is fine
    frames = tcu_frames(drain(listener))
    for name in TCU_MESSAGES:
        last = decoded(frames[name][-1:], name)[0]
        for sig, value in codec.TCU_SAFE_VALUES[name].items():
            assert last[sig] == value, (name, sig)
    assert decoded(frames["TCU_ShiftCmd"][-2:-1], "TCU_ShiftCmd")[0]["ForkForce1"] > 0   # it was driving forks
    path = tmp_path / "sub" / "tcu.json"
    rep = tcu.write_report(path)
    with open(path, encoding="utf-8") as f:
        data = json.load(f)
    assert data == json.loads(json.dumps(rep))
    assert data["final_safe_frames"] is True
    assert data["ticks"] >= 1 and data["skipped_ticks"] >= 0
    for name in TCU_MESSAGES:
        assert data["sent"][name]["frames"] == len(frames[name])
    for name in PLANT_NEEDED:
        assert data["received"][name]["accepted"] >= 1
        assert set(data["received"][name]["rejected"]) == {"bad_length", "bad_crc", "bad_counter"}
    assert data["sim_time_s"] == pytest.approx(12.5, abs=0.01)
    assert data["phase"] == "standstill" and data["shifts"] == []
    line = tcu.status_line()
    assert "standstill" in line and "gear 1" in line


def test_time_scale_must_be_in_0_1(channel):
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        for bad in (0, -1, 1.5, float("nan"), "x"):
            with pytest.raises(ValueError, match="time scale"):
                CanTcu(bus, time_scale=bad, start=False)
    finally:
        bus.shutdown()


def test_a_bus_that_cannot_open_is_a_one_line_connection_error():
    with pytest.raises(ConnectionError) as e:
        CanTcu.open("no-such-interface", "nowhere0")
    assert "no-such-interface" in str(e.value) and "nowhere0" in str(e.value)
    assert "\n" not in str(e.value)


def test_receive_buffer_is_raised_on_a_socket():
    import socket

    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        before = a.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        granted = can_tcu.raise_rcvbuf(a, 1 << 20)
        assert granted == a.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert granted >= before
    finally:
        a.close()
        b.close()


def test_peer_without_send_thread_sends_only_when_told(channel, listener):
    peer = CanPeer.open("tcu", interface="virtual", channel=channel, send_thread=False)
    try:
        assert peer.send_now("TCU_ClutchCmd", {"SolenoidCurrent1": 0.6}) is True
        assert peer.send_now("TCU_ClutchCmd") is True
        with pytest.raises(ValueError):
            peer.send_now("DCT_Clutch")
        with pytest.raises(ValueError):
            peer.send_now("TCU_ClutchCmd", {"NoSuchSignal": 1})
    finally:
        peer.close()
    frames = tcu_frames(drain(listener))
    assert [len(frames[n]) for n in TCU_MESSAGES] == [2, 0, 0]
    values = decoded(frames["TCU_ClutchCmd"], "TCU_ClutchCmd")
    assert [v["SolenoidCurrent1"] for v in values] == [pytest.approx(0.6, abs=0.001)] * 2
    assert [v["AliveCounter"] for v in values] == [0, 1]
    assert peer.sent["TCU_ClutchCmd"] == 2


class _FailingLogic:
    phase, gear, target_gear, events = "standstill", 1, 1, []

    def step(self, t_s, sensors):
        if t_s >= 0.02:
            raise ZeroDivisionError("float division by zero")
        return {"SolenoidCurrent1": 0.5, "SolenoidCurrent2": 0.0, "LineSolenoidCurrent": 0.0,
                "ForkForce1": 900.0, "ForkForce2": 0.0, "ForkForce3": 0.0, "ForkForce4": 0.0,
                "EngineTorqueRequest": 50.0, "TorqueRequestActive": 1, "TargetGear": 1}


def test_an_error_in_the_task_stops_it_with_safe_frames_and_a_one_line_error(channel, listener):
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        tcu = CanTcu(bus, logic=_FailingLogic())
        assert tcu.wait_for(lambda t: not t.running, timeout=WAIT_S)
        tcu.close()
    finally:
        bus.shutdown()
    assert "ZeroDivisionError" in tcu.error and "\n" not in tcu.error
    frames = tcu_frames(drain(listener))
    for name in TCU_MESSAGES:
        assert len(frames[name]) >= 2
        last = decoded(frames[name][-1:], name)[0]
        assert all(last[sig] == v for sig, v in codec.TCU_SAFE_VALUES[name].items()), name
    assert tcu.report()["final_safe_frames"] is True


# ------------------------------------------------------------------ closed loop with the server
@pytest.mark.slow
def test_closed_loop_with_the_plant_server_launches_the_car(channel):
    from rt_loop.server import Server

    srv = Server(channel, interface="virtual", priority=0)
    srv.start()
    try:
        with CanTcu.open("virtual", channel) as tcu:
            assert tcu.wait_for(lambda t: fresh(t) and t.logic.phase == "standstill", timeout=WAIT_S)
            # the driver: the plant server owns the pedals (driver inputs of the running loop)
            srv._l.plant.inputs.brake_pedal_pct = 0.0
            srv._l.plant.inputs.accel_pedal_pct = 40.0
            launched = tcu.wait_for(lambda t: t.sensors.get("VehicleSpeed", 0) > 5.0, timeout=12.0)
            plant = srv.snapshot()["plant"]
            rep = tcu.report()
        assert launched, tcu.status_line()
        assert plant["vehicle_speed_kmh"] > 5.0
        assert plant["engine_speed_rpm"] > 600.0                  # not stalled
        assert rep["phase"] in ("launch", "drive", "upshift_torque", "upshift_inertia")
        assert rep["received"]["DCT_ShaftSpeeds"]["accepted"] > 0
        assert rep["stale"]["now"] is False
        counts = srv.snapshot()["counts"]
        assert counts["rx"]["bad_crc"] == 0 and counts["rx"]["bad_counter"] == 0
    finally:
        srv.stop()


# ------------------------------------------------------------------ command line
def cli(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "tcu_stub.can_tcu", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.parametrize("args, option", [
    (("--time-scale", "0"), "--time-scale"),
    (("--time-scale", "2"), "--time-scale"),
    (("--time-scale", "fast"), "--time-scale"),
    (("--duration", "-1"), "--duration"),
    (("--duration", "inf"), "--duration"),
    (("--bitrate", "x"), "--bitrate"),
])
def test_cli_bad_options_are_one_line_exit_2(args, option):
    r = cli("--interface", "virtual", *args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and option in lines[0], r.stderr


def test_cli_bus_that_cannot_open_is_one_line_exit_1():
    r = cli("--interface", "no-such-interface", "--channel", "nowhere0", "--duration", "1")
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "no-such-interface" in lines[0] and "nowhere0" in lines[0], r.stderr


@pytest.mark.slow
def test_cli_runs_writes_the_report_and_stops_on_sigterm(tmp_path, channel):
    import signal

    path = tmp_path / "tcu.json"
    proc = subprocess.Popen([sys.executable, "-m", "tcu_stub.can_tcu", "--interface", "virtual",
                             "--channel", channel, "--report", str(path)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()          # the banner: the node runs
        assert "tcu" in first
        proc.stdout.readline()                  # one status line (after about a second)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    data = json.loads(path.read_text())
    assert data["final_safe_frames"] is True
    assert data["stale"]["now"] is True                       # no plant on this channel
    assert data["sent"]["TCU_ClutchCmd"]["frames"] > 0
    assert f"report: {path}" in out
