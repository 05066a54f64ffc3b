"""The reference TCU's CAN node in C (tcu_stub.c_node) against the Python node
(tcu_stub.can_tcu.CanTcu).

The same traffic into both, period by period and without threads
(``tcu_node_receive`` / ``tcu_node_period`` against ``CanTcu._tick`` with a
snapshot of the same frames): a closed loop of the paper-cycle with frames
lost, corrupted and cut short, so that every stale cause, the engine
message's ride-out and the recovery are in it. The commands must be the same
to the bit in every period; the stale episodes, shifts and trouble codes
too. Then the node on its thread: on the in-process bus against a stand-in
plant (frames, E2E, rates, safe final frames, a silent plant), on the loop's
own rings (rt_loop.embedded), and the command line.
"""

import json
import subprocess
import sys
import uuid

import can
import pytest

from can_dbc import codec
from can_dbc.node import RxStats
from can_dbc.peer import CanPeer
from plant.driver import driver_inputs
from plant.maneuvers import get_maneuver
from plant.model import Plant
from tcu_stub.c_node import CTcuNode, frame_layout
from tcu_stub.can_tcu import REJECTS_TO_STALE, CanTcu
from tcu_stub.contract_link import PLANT_PLAN, apply_commands
from tcu_stub.logic import PERIOD_S

PLANT = [m.name for m in codec.messages("PLANT")]
TCU = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd", "TCU_Status")
WAIT_S = 20.0


def _plant_values(name, plant):
    out = {}
    for sig, src in codec.PLANT_SIGNAL_SOURCES.get(name, {}).items():
        kind, field = src.split(".", 1)
        if kind == "o":
            out[sig] = float(plant.outputs[field])
        elif field == "sim_time_s":
            out[sig] = float(plant.time_s)
    return out


def _fault(k, name):
    """The traffic's faults: what happens to ``name``'s frame in period ``k``."""
    if 1500 <= k < 1530 and name == "DCT_ShaftSpeeds":
        return "drop"                                    # timed out (10 cycles), then back
    if 2200 <= k < 2200 + 5 * REJECTS_TO_STALE and name == "DCT_Shift":
        return "crc"                                     # rejected 3 in a row: stale
    if 2600 <= k < 2650 and name == "VEH_Driver":
        return "drop"                                    # the engine message: ridden out
    if k == 2900 and name == "DCT_Clutch":
        return "len"                                     # one short frame: counted only
    if k == 3100 and name == "DCT_OutputSpeeds":
        return "crc"
    return None


class _Rings:
    """The C node's own rings as its ports: frames pushed in by the test, popped out."""

    def __init__(self):
        from tcu_stub.fast import _lib

        self.ffi, self.lib = ffi, lib = _lib()
        self.rx, self.tx = ffi.new("tcu_ring *"), ffi.new("tcu_ring *")

        def addr(x):
            return int(ffi.cast("uintptr_t", x))

        self.ports = {"can": (addr(lib.tcu_ring_pop_fn()), addr(self.rx),
                              addr(lib.tcu_ring_push_fn()), addr(self.tx))}
        self.buf = ffi.new("tcu_frame[]", 64)

    def push(self, frame_id, data):
        f = self.ffi.new("tcu_frame *")
        f.id, f.len = frame_id, len(data)
        self.ffi.memmove(f.data, data, len(data))
        assert self.lib.tcu_ring_push_many(self.rx, f, 1) == 1

    def pop(self):
        n = self.lib.tcu_ring_pop_many(self.tx, self.buf, 64)
        return [(int(self.buf[i].id), bytes(self.ffi.unpack(self.ffi.cast("char *", self.buf[i].data),
                                                            int(self.buf[i].len)))) for i in range(n)]


@pytest.fixture(scope="module")
def pair_run():
    """Both nodes through 3400 periods (6.8 s) of the paper-cycle with the faults above."""
    rings = _Rings()
    node = CTcuNode(ports=rings.ports, start=False)
    lib, n = node._lib, node._n
    channel = f"c-node-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    listener = can.Bus(interface="virtual", channel=channel)
    py = CanTcu(bus, start=False)
    stats = {name: RxStats() for name in PLANT}
    e2e = codec.E2eReceiver(sender="PLANT")
    m = get_maneuver("paper-cycle")
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
    m.start(plant)
    steps = int(round(PERIOD_S / plant.step_s))
    counters = dict.fromkeys(PLANT, 0)
    plan = dict(PLANT_PLAN, SIM_Status=(5, 4))
    diffs, c_frames, py_frames = [], [], []
    for k in range(3400):
        now = k * PERIOD_S
        if k % 5 == 0:
            for key, value in driver_inputs(m.driver, plant.time_s, plant.outputs).items():
                plant.inputs[key] = value
            plant.update_outputs() if hasattr(plant, "update_outputs") else None
        for name in PLANT:
            div, off = plan[name]
            if k % div != off and k > 0:
                continue
            fault = _fault(k, name)
            if fault == "drop":
                continue
            data = codec.encode(name, _plant_values(name, plant), counters[name] % 16)
            counters[name] += 1
            if fault == "crc":
                data = bytes([data[0] ^ 0x55]) + data[1:]
            elif fault == "len":
                data = data[:5]
            frame_id = codec.message(name).frame_id
            rings.push(frame_id, data)
            status = e2e.check(frame_id, data)
            stats[name].frame(now, status, codec.decode(frame_id, data)[1] if status == codec.OK else None)
        lib.tcu_node_receive(n, now)
        lib.tcu_node_period(n, k, now)
        py._tick(k, now, {name: st.snapshot() for name, st in stats.items()})
        c_cmd = node.commands
        if c_cmd != {key: py.commands[key] for key in c_cmd}:
            diffs.append((k, {key: (v, py.commands[key]) for key, v in c_cmd.items() if v != py.commands[key]}))
        c_frames += rings.pop()
        while (msg := listener.recv(timeout=0.0)) is not None:
            py_frames.append((msg.arbitration_id, bytes(msg.data)))
        apply_commands(plant, py.commands)
        plant.step(steps)
    lib.tcu_node_send_safe(n)
    c_frames += rings.pop()
    py._send_safe()
    while (msg := listener.recv(timeout=0.0)) is not None:
        py_frames.append((msg.arbitration_id, bytes(msg.data)))
    rep_c, rep_py = node.report(), py.report()
    rep_py["received"] = {name: {"received": st.received, "accepted": st.accepted,
                                 "rejected": dict(st.rejected)} for name, st in stats.items()}
    bus.shutdown()
    listener.shutdown()
    return diffs, rep_c, rep_py, c_frames, py_frames


def test_the_c_node_commands_what_the_python_node_commands_in_every_period(pair_run):
    diffs, rep_c, rep_py, _, _ = pair_run
    assert not diffs, diffs[:3]
    assert rep_c["ticks"] == rep_py["ticks"] == 3400
    assert rep_c["shifts"] == rep_py["shifts"] and len(rep_c["shifts"]) >= 2


def test_every_frame_sent_is_the_python_nodes_to_the_byte(pair_run):
    _, _, _, c_frames, py_frames = pair_run
    assert len(c_frames) == len(py_frames) > 3400
    assert c_frames == py_frames


def test_stale_episodes_causes_and_trouble_codes_are_the_python_nodes(pair_run):
    _, rep_c, rep_py, _, _ = pair_run
    assert rep_c["stale"]["episodes"] == rep_py["stale"]["episodes"]
    causes = [ep["causes"] for ep in rep_c["stale"]["episodes"]]
    assert {"DCT_ShaftSpeeds": "timeout"} in causes and {"DCT_Shift": "rejected"} in causes
    assert {"VEH_Driver": "timeout"} in causes                       # ridden out, still an episode
    assert rep_c["stale"]["ticks"] == rep_py["stale"]["ticks"]
    assert rep_c["diagnostics"] == rep_py["diagnostics"]
    assert {"can_timeout", "can_crc", "engine_message"} <= set(rep_c["diagnostics"]["stored"])
    for name in PLANT:
        for key in ("received", "accepted", "rejected"):
            assert rep_c["received"][name][key] == rep_py["received"][name][key], (name, key)
    assert rep_c["received"]["DCT_Clutch"]["rejected"]["bad_length"] == 1
    assert rep_c["final_safe_frames"] is True and rep_py["final_safe_frames"] is True
    assert rep_c["last_commands"] == {k: rep_py["last_commands"][k] for k in rep_c["last_commands"]}


def test_the_frames_have_the_layout_of_the_loops():
    from rt_loop._rt_loop import ffi

    assert frame_layout() == (ffi.sizeof("rt_frame"), ffi.offsetof("rt_frame", "id"),
                              ffi.offsetof("rt_frame", "len"), ffi.offsetof("rt_frame", "flags"),
                              ffi.offsetof("rt_frame", "channel"), ffi.offsetof("rt_frame", "data"))


# ------------------------------------------------------------------ on its thread
STANDSTILL = {"EngineSpeed": 750, "LinePressure": 20, "BrakePedal": 30, "EngineTorque": 20,
              "SimTime": 12.5, "SimState": 1}


@pytest.fixture
def channel():
    return f"c-node-{uuid.uuid4().hex[:10]}"


def _drain(bus):
    out = {n: [] for n in TCU}
    ids = {codec.message(n).frame_id: n for n in TCU}
    while (msg := bus.recv(timeout=0.0)) is not None:
        if msg.arbitration_id in ids:
            out[ids[msg.arbitration_id]].append(bytes(msg.data))
    return out


def test_on_the_in_process_bus_it_sends_protected_frames_goes_stale_and_ends_safe(channel):
    listener = can.Bus(interface="virtual", channel=channel)
    plant = CanPeer.open("plant", interface="virtual", channel=channel, values=STANDSTILL)
    try:
        with CTcuNode.open("virtual", channel) as tcu:
            assert tcu.wait_for(lambda t: t.sent("TCU_ShiftCmd") >= 40 and not t.stale, timeout=WAIT_S)
            assert tcu.wait_for(lambda t: t.phase == "standstill" and t.commands["ForkForce1"] > 0)
            for name in ("DCT_ShaftSpeeds", "DCT_OutputSpeeds", "DCT_Clutch", "DCT_Shift", "VEH_Motion",
                         "VEH_Driver"):
                plant.enable(name, False)
            assert tcu.wait_for(lambda t: t.stale and t.phase == "stale", timeout=WAIT_S)
            assert tcu.wait_for(lambda t: t.commands["ForkForce1"] == 0)
            for name in ("DCT_ShaftSpeeds", "DCT_OutputSpeeds", "DCT_Clutch", "DCT_Shift", "VEH_Motion",
                         "VEH_Driver"):
                plant.enable(name, True)
            assert tcu.wait_for(lambda t: not t.stale and t.commands["ForkForce1"] > 0, timeout=WAIT_S)
        rep = tcu.report()
        frames = _drain(listener)
    finally:
        plant.close()
        listener.shutdown()
    rx = codec.E2eReceiver(sender="TCU")
    for name, datas in frames.items():
        assert datas and all(rx.check(codec.message(name).frame_id, d) == codec.OK for d in datas), name
        assert rep["sent"][name]["frames"] == len(datas)
        last = codec.decode(codec.message(name).frame_id, datas[-1])[1]
        assert all(last[sig] == v for sig, v in codec.TCU_SAFE_VALUES[name].items()), name
    assert 3.5 <= len(frames["TCU_ClutchCmd"]) / len(frames["TCU_ShiftCmd"]) <= 6.5
    assert rep["impl"] == "c" and rep["final_safe_frames"] is True and rep["error"] is None
    assert rep["stale"]["episode_count"] >= 1 and rep["stale"]["episodes"][-1]["end_s"] is not None
    assert set(rep["stale"]["episodes"][-1]["causes"].values()) == {"timeout"}
    assert rep["sim_time_s"] == pytest.approx(12.5) and rep["tick_exec_us"]["n"] == rep["ticks"]
    json.dumps(rep)


def test_on_the_loops_own_rings_it_launches_the_car_with_a_matrix():
    from rt_loop.embedded import connect_tcu, embedded_server

    m = get_maneuver("paper-cycle")
    server = embedded_server(f"c-node-{uuid.uuid4().hex[:8]}", priority=0, driver=m.driver,
                             maneuver_inputs=m.inputs, maneuver_start="tcu", maneuver_end_s=3.0,
                             mapping="vehicle")
    server.start()
    try:
        tcu = connect_tcu(server, mapping=server.mapping, priority=0)
        # its periods begin half a loop tick after a tick (the loop's first deadline t0_ns)
        step = int(round(server.period_s * 1e9))
        assert (tcu._n.phase_ref_ns, tcu._n.phase_step_ns, tcu._n.phase_offset_ns) == \
            (int(server.stats.read().t0_ns), step, step // 2) and tcu._n.phase_ref_ns > 0
        assert tcu.wait_for(lambda t: not server.running, timeout=WAIT_S)
        tcu.stop()
    finally:
        server.stop()
    rep, srv = tcu.report(), server.report()
    assert srv["run"]["maneuver"] == "done" and srv["counts"]["rx"]["rejected"] == 0
    assert rep["interface"] == "embedded" and rep["error"] is None and rep["send_errors"] == 0
    assert sum(r["accepted"] for r in rep["received"].values()) > 1000
    assert rep["phase"] in ("launch", "drive") and rep["unknown_frames"] == 0


def test_the_command_line_takes_impl_and_refuses_a_bad_one_in_one_line():
    r = subprocess.run([sys.executable, "-m", "tcu_stub.command", "--impl", "rust"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--impl" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run([sys.executable, "-m", "tcu_stub.command", "--interface", "socketcan",
                        "--channel", "nosuchcan0", "--duration", "1"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 1 and "nosuchcan0" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_bad_phase_is_refused_in_one_line():
    from tcu_stub.c_node import NodeError

    node = CTcuNode(ports=_Rings().ports, start=False)
    for ref, step, offset in ((0, 500_000, 250_000), (1, 0, 0), (1, 500_000, 500_000)):
        with pytest.raises(NodeError, match="lock_phase") as e:
            node.lock_phase(ref, step, offset)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("impl", ["c", "python"])
def test_frames_queued_before_the_start_are_discarded_and_counted(channel, impl):
    """A bus that queued frames before the node started (a socket bound long before,
    which overflowed and cut their counters): either node discards them at its
    start, so its first period sees none of them rejected."""
    node = CTcuNode.open("virtual", channel, start=False, priority=0) if impl == "c" else \
        CanTcu.open("virtual", channel, start=False)
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        ident = codec.message("DCT_ShaftSpeeds").frame_id
        stale = codec.encode("DCT_ShaftSpeeds", {}, 3)
        for _ in range(300):                               # the same counter 300 times: repeats
            sender.send(can.Message(arbitration_id=ident, data=stale, is_extended_id=False))
        node.start()
        # drained, and the node past its start (its first period done)
        assert node.wait_for(lambda t: t.report()["drained_at_start"] >= 300 and t.report()["ticks"] >= 1,
                             timeout=WAIT_S)
        for k in range(10):                                # then fresh frames, counters running
            sender.send(can.Message(arbitration_id=ident, data=codec.encode("DCT_ShaftSpeeds", {}, k),
                                    is_extended_id=False))
        assert node.wait_for(lambda t: t.report()["received"]["DCT_ShaftSpeeds"]["accepted"] >= 10,
                             timeout=WAIT_S)
        rep = node.report()
    finally:
        node.close()
        sender.shutdown()
    speeds = rep["received"]["DCT_ShaftSpeeds"]
    assert rep["drained_at_start"] == 300
    assert speeds["received"] == speeds["accepted"] == 10
    assert speeds["rejected"] == {"bad_length": 0, "bad_crc": 0, "bad_counter": 0}


_HELD = """
import json, sys, time
impl, channel = sys.argv[1], sys.argv[2]
if impl == "c":
    from tcu_stub.c_node import CTcuNode
    node = CTcuNode.open("virtual", channel, priority=0)
else:
    from tcu_stub.can_tcu import CanTcu
    node = CanTcu.open("virtual", channel)
with node:
    node.wait_for(lambda t: t.report()["ticks"] >= 50, timeout=20)
    node.pause(0.3)                        # asked for: not a stall
    node.wait_for(lambda t: t.report()["pauses"]["count"] == 1, timeout=20)
    time.sleep(0.1)
    print(json.dumps(node.stalls(0)[0]), flush=True)
    sys.stdin.readline()                   # the test holds this process meanwhile
    time.sleep(0.1)
    after, count = node.stalls(0)
rep = node.report()
print(json.dumps({"after": after, "count": count, "report": rep["stalls"]}), flush=True)
"""


@pytest.mark.parametrize("impl", ["c", "python"])
def test_a_hold_of_the_machine_is_a_stall_in_the_log_and_a_pause_asked_for_is_not(channel, impl):
    """The process held 150 ms (SIGSTOP/SIGCONT: what a host does to a VM): the node's
    next wake-up is that late, logged with its lateness; the pause of 300 ms asked for
    before is not a stall. The soak excuses a timeout only with such a stall."""
    import os
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-c", _HELD, impl, channel], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        before = json.loads(proc.stdout.readline())
        os.kill(proc.pid, signal.SIGSTOP)
        time.sleep(0.15)
        os.kill(proc.pid, signal.SIGCONT)
        proc.stdin.write("\n")
        proc.stdin.flush()
        out = json.loads(proc.stdout.readline())
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=WAIT_S) == 0
    assert not [s for s in before if s["late_ms"] >= 100.0], before       # the pause is not one
    held = [s for s in out["after"] if s["late_ms"] >= 100.0]
    assert len(held) == 1 and held[0]["late_ms"] >= 140.0, out["after"]
    assert [s["index"] for s in out["after"]] == list(range(out["count"]))
    rep = out["report"]
    assert rep["count"] == out["count"] and rep["longest_ms"] >= held[0]["late_ms"]
    assert rep["over_ms"] == pytest.approx(10.0) and rep["last"] == out["after"]


def test_the_stall_constants_are_the_python_nodes():
    from tcu_stub import can_tcu
    from tcu_stub.c_node import CTcuNode

    lib = CTcuNode(ports=_Rings().ports, start=False)._lib
    assert lib.TCU_NODE_STALL_PERIODS == can_tcu.STALL_PERIODS
    assert lib.TCU_NODE_MAX_STALLS == can_tcu.MAX_STALLS
