"""The table-driven channels of the real-time loop (rt_loop/channels.py ->
rt_loop/csrc), on the host, through the loop's rings.

A small rig written here (two DBCs, a mapping with two buses; a CAN FD bus
of its own) exercises what the table path adds to the loop: where each sent
signal's value comes from (plant output with factor/offset and magnitude,
value tables with keys, ranges and default, constant, toggle, counter, the
DBC start value, the simulator's status), what each received signal drives
(a plant input with factor/offset and limits, a value table, a recorded
value), safe values at start and while timed out, counts per message and per
channel, two buses with the same identifiers, 29-bit identifiers, CAN FD
frames of 64 bytes, the tables rt_loop_prepare refuses; then the shipped
vehicle mapping (two buses) served for a short while.

The loop runs with priority 0 (normal scheduling). Every assertion is about
frames and counts: rates are counted over the loop's own ticks, never
against the wall clock; waits (tests/waiting.py) only bound a failure.
"""

import errno
import os
import socket
import struct
import threading

import cantools
import pytest
from waiting import WAIT_S, wait_until

from can_dbc import mapping as can_mapping
from plant.params import fill_params, load_params
from rt_loop._rt_loop import ffi, lib
from rt_loop.channels import LoopChannels

CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CANFD_BRS = 0x01
CAN_FRAME = struct.Struct("<IBxxx8s")       # struct can_frame, CAN_MTU (16 bytes)
CANFD_FRAME = struct.Struct("<IBBxx64s")    # struct canfd_frame, CANFD_MTU (72 bytes)

_PARAMS = load_params(None, ffi, None)
_OUTPUTS = [n for n, _ in ffi.typeof("dct_outputs").fields]
_INPUTS = [n for n, _ in ffi.typeof("dct_inputs").fields]

# The rig: bus "a" (P_Values: every kind of source; P_Status: the simulator's
# status; E_Cmd: an input with factor/offset and limits, a value table, a
# recorded value; E_Beat: a short timeout) and bus "b" (the same identifiers
# 0x200 and 0x100 with other layouts, 29-bit identifiers). The plant plays
# PLANT, the device under test is ECU.
RIG_A_DBC = """\
VERSION ""

NS_ :
	BA_DEF_
	BA_
	VAL_
	BA_DEF_DEF_

BS_:

BU_: PLANT ECU

BO_ 512 P_Values: 8 PLANT
 SG_ P_Values_CRC : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ P_Values_Ctr : 8|4@1+ (1,0) [0|15] "" ECU
 SG_ Mode : 12|4@1+ (1,0) [0|15] "" ECU
 SG_ Brake : 16|8@1+ (0.5,0) [0|127.5] "%" ECU
 SG_ Grade : 24|16@1- (0.01,0) [-100|100] "%" ECU
 SG_ BrakeClass : 40|4@1+ (1,0) [0|15] "" ECU
 SG_ AccelClass : 44|4@1+ (1,0) [0|15] "" ECU
 SG_ GradeClass : 48|4@1+ (1,0) [0|15] "" ECU
 SG_ Tgl : 52|1@1+ (1,0) [0|1] "" ECU
 SG_ Cnt : 53|3@1+ (1,0) [0|7] "" ECU
 SG_ Spare : 56|8@1+ (1,0) [0|255] "" ECU

BO_ 513 P_Status: 8 PLANT
 SG_ SimTime : 0|24@1+ (0.001,0) [0|16777.215] "s" ECU
 SG_ SimState : 24|2@1+ (1,0) [0|3] "" ECU

BO_ 256 E_Cmd: 8 ECU
 SG_ E_Cmd_CRC : 0|8@1+ (1,0) [0|255] "" PLANT
 SG_ E_Cmd_Ctr : 8|4@1+ (1,0) [0|15] "" PLANT
 SG_ GearReq : 12|4@1- (1,0) [-8|7] "" PLANT
 SG_ Current : 16|16@1+ (0.001,0) [0|65.535] "A" PLANT
 SG_ Aux : 32|8@1+ (1,0) [0|255] "" PLANT

BO_ 257 E_Beat: 2 ECU
 SG_ Beat : 0|8@1+ (1,0) [0|255] "" PLANT

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_ SG_ "GenSigStartValue" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_DEF_DEF_ "GenSigStartValue" 0;
BA_ "GenMsgCycleTime" BO_ 512 2;
BA_ "GenMsgCycleTime" BO_ 513 10;
BA_ "GenMsgCycleTime" BO_ 256 100;
BA_ "GenMsgCycleTime" BO_ 257 10;
BA_ "GenSigStartValue" SG_ 512 Spare 17;
VAL_ 512 Mode 0 "normal" 3 "sport" ;
"""

RIG_B_DBC = """\
VERSION ""

NS_ :
	BA_DEF_
	BA_
	BA_DEF_DEF_

BS_:

BU_: PLANT ECU

BO_ 512 Q_Out: 4 PLANT
 SG_ Q_Out_Ctr : 0|4@1+ (1,0) [0|15] "" ECU
 SG_ Pedal : 8|8@1+ (0.5,0) [0|127.5] "%" ECU

BO_ 2566844672 Q_Ext: 8 PLANT
 SG_ ExtSpeed : 0|16@1+ (0.01,0) [0|655.35] "km/h" ECU

BO_ 256 F_Cmd: 6 ECU
 SG_ Force : 0|16@1- (1,0) [-32768|32767] "N" PLANT
 SG_ F_Cmd_Ctr : 16|4@1+ (1,0) [0|15] "" PLANT

BO_ 2566848528 F_Ext: 8 ECU
 SG_ ExtValue : 0|16@1+ (0.1,0) [0|6553.5] "" PLANT

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 512 4;
BA_ "GenMsgCycleTime" BO_ 2566844672 10;
BA_ "GenMsgCycleTime" BO_ 256 100;
BA_ "GenMsgCycleTime" BO_ 2566848528 100;
"""

RIG_TOML = """\
[[bus]]
name = "a"
dbc = "rig_a.dbc"
bitrate = 500000
plant_nodes = ["PLANT"]
tcu_nodes = ["ECU"]

[[bus]]
name = "b"
dbc = "rig_b.dbc"
bitrate = 500000
plant_nodes = ["PLANT"]
tcu_nodes = ["ECU"]

[message.P_Values]
protection = {{ kind = "dct", crc = "P_Values_CRC", counter = "P_Values_Ctr" }}

[message.P_Values.signals]
Mode = {{ constant = "sport" }}
Brake = {{ output = "brake_pedal_pct", factor = 0.5, offset = 3.0 }}
Grade = {{ output = "road_grade_pct", abs = true }}
BrakeClass = {{ output = "brake_pedal_pct", table = {{ "..9" = 1, "10..50" = 2, "60" = 5, default = 7 }} }}
AccelClass = {{ output = "accel_pedal_pct", table = {{ "..59" = 1, "61.." = 2, default = 7 }} }}
GradeClass = {{ output = "road_grade_pct", table = {{ "-7" = 6, "-6" = 4, default = 3 }} }}
Tgl = {{ toggle = true }}
Cnt = {{ counter = 5 }}

[message.P_Status.signals]
SimTime = {{ status = "sim_time_s" }}
SimState = {{ status = "sim_state" }}

[message.E_Cmd]
timeout_cycles = {cmd_timeout}
protection = {{ kind = "dct", crc = "E_Cmd_CRC", counter = "E_Cmd_Ctr" }}

[message.E_Cmd.signals]
Current = {{ input = "solenoid_current1_a", factor = 0.5, offset = -0.2, min = 0.0, max = 1.0, safe = 0.05 }}
GearReq = {{ record = "gear_req", table = {{ "-1" = -1, "1..6" = 10, "7" = 0, default = 99 }}, safe = 3 }}
Aux = {{ record = "aux", factor = 2.0, offset = 1.0, safe = 7 }}

[message.E_Beat]
timeout_cycles = 3

[message.E_Beat.signals]
Beat = {{ record = "beat", safe = 42 }}

[message.Q_Out]
protection = {{ kind = "counter", counter = "Q_Out_Ctr" }}

[message.Q_Out.signals]
Pedal = {{ output = "accel_pedal_pct" }}

[message.Q_Ext.signals]
ExtSpeed = {{ constant = 12.5 }}

[message.F_Cmd]
timeout_cycles = 1000
protection = {{ kind = "counter", counter = "F_Cmd_Ctr" }}

[message.F_Cmd.signals]
Force = {{ input = "fork_force1_n", safe = 0.0 }}

[message.F_Ext]
timeout_cycles = 1000

[message.F_Ext.signals]
ExtValue = {{ record = "ext_value", safe = 0 }}
"""

# A CAN FD bus (BusType "CAN FD", VFrameFormat StandardCAN_FD: cantools marks
# the messages FD) with a bit rate switch: 64-byte frames both ways.
FD_DBC = """\
VERSION ""

NS_ :
	BA_DEF_
	BA_
	BA_DEF_DEF_

BS_:

BU_: PLANT ECU

BO_ 768 FD_Out: 64 PLANT
 SG_ FD_Out_CRC : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ FD_Out_Ctr : 8|4@1+ (1,0) [0|15] "" ECU
 SG_ Pedal : 16|8@1+ (0.5,0) [0|127.5] "%" ECU
 SG_ Far : 496|16@1+ (1,0) [0|65535] "" ECU

BO_ 769 FD_In: 64 ECU
 SG_ FD_In_CRC : 0|8@1+ (1,0) [0|255] "" PLANT
 SG_ FD_In_Ctr : 8|4@1+ (1,0) [0|15] "" PLANT
 SG_ Level : 496|16@1+ (0.1,0) [0|6553.5] "" PLANT

BA_DEF_ "BusType" STRING ;
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_ BO_ "VFrameFormat" ENUM "StandardCAN","ExtendedCAN","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","StandardCAN_FD","ExtendedCAN_FD";
BA_DEF_DEF_ "BusType" "CAN";
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_DEF_DEF_ "VFrameFormat" "StandardCAN";
BA_ "BusType" "CAN FD";
BA_ "GenMsgCycleTime" BO_ 768 2;
BA_ "GenMsgCycleTime" BO_ 769 100;
BA_ "VFrameFormat" BO_ 768 14;
BA_ "VFrameFormat" BO_ 769 14;
"""

FD_TOML = """\
[[bus]]
name = "fd"
dbc = "rig_fd.dbc"
bitrate = 500000
data_bitrate = 2000000
plant_nodes = ["PLANT"]
tcu_nodes = ["ECU"]

[message.FD_Out]
protection = { kind = "dct", crc = "FD_Out_CRC", counter = "FD_Out_Ctr" }

[message.FD_Out.signals]
Pedal = { output = "accel_pedal_pct" }
Far = { constant = 4660 }

[message.FD_In]
timeout_cycles = 1000
protection = { kind = "dct", crc = "FD_In_CRC", counter = "FD_In_Ctr" }

[message.FD_In.signals]
Level = { record = "level", safe = 0 }
"""


def crc8_j1850(data):
    """CRC-8/SAE-J1850 written here (poly 0x1D, init and xorout 0xFF)."""
    crc = 0xFF
    for byte in bytes(data):
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def dct_crc_ok(frame_id, data):
    """The contract's checksum (byte 0) over the identifier (2 bytes) and data[1:]."""
    return data[0] == crc8_j1850(bytes([frame_id & 0xFF, (frame_id >> 8) & 0xFF]) + bytes(data[1:]))


class Rig:
    """A loaded mapping with its loop tables, DBCs and indices."""

    def __init__(self, path):
        self.mapping = can_mapping.load(str(path))
        self.channels = LoopChannels(self.mapping, ffi, lib)
        self.buses = self.channels.buses
        self.db = {b.name: cantools.database.load_file(b.dbc, strict=False) for b in self.mapping.buses}
        #: (bus, message name) -> index in stats.msgs
        self.msg = {(b, m.name): g for g, (b, m) in enumerate(self.channels.messages)}
        #: command name -> index in stats.commands
        self.cmd = {name: k for k, name in enumerate(self.channels.command_names)}

    def chan(self, bus):
        return self.buses.index(bus)

    def frame(self, bus, name, values=None, counter=None, flags=0):
        """(id with flags, len, data, frame flags) of a frame of ``name``, packed
        (and protected with ``counter``) by the bus's table codec."""
        t = self.channels.table(bus)
        m = t.messages[t.index(name)]
        data = t.encode(name, values or {}, counter=counter)
        return (m.frame_id | (CAN_EFF_FLAG if m.is_extended_frame else 0), len(data), data, flags)

    def decode(self, bus, name, data):
        return self.db[bus].get_message_by_name(name).decode(bytes(data), decode_choices=False)


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("rig")
    (d / "rig_a.dbc").write_text(RIG_A_DBC)
    (d / "rig_b.dbc").write_text(RIG_B_DBC)
    (d / "rig.toml").write_text(RIG_TOML.format(cmd_timeout=1000))
    (d / "rig_short.toml").write_text(RIG_TOML.format(cmd_timeout=2))
    (d / "rig_fd.dbc").write_text(FD_DBC)
    (d / "fd.toml").write_text(FD_TOML)
    return d


@pytest.fixture(scope="module")
def rig(rig_dir):
    return Rig(rig_dir / "rig.toml")


@pytest.fixture(scope="module")
def fd_rig(rig_dir):
    return Rig(rig_dir / "fd.toml")


class Loop:
    """One rt_loop serving a LoopChannels over ring transports, run in a thread of its own.

    ``inputs``: driver inputs (dct_inputs fields) written after rt_loop_prepare."""

    def __init__(self, channels, period_s=0.0005, duration_s=0.0, inputs=None, log_frames=0):
        self.channels = channels            # the tables live as long as the loop
        self.c = ffi.new("rt_loop *")
        fill_params(ffi, ffi.addressof(self.c[0].plant, "params"), _PARAMS)
        cfg = self.c.cfg
        cfg.period_s = period_s
        cfg.priority = 0
        cfg.cpu = -1
        cfg.duration_s = duration_s
        cfg.log_frames = log_frames
        channels.install(self.c)
        for i in range(len(channels.buses)):
            self.c.chan[i].transport = lib.RT_TRANSPORT_RING
        self.inputs = dict(inputs or {})
        self.prepared = False
        self.thread = None

    def prepare(self):
        rc = lib.rt_loop_prepare(self.c)
        if rc == 0:
            self.prepared = True
            for name, value in self.inputs.items():
                setattr(self.c.plant.inputs, name, value)
        return rc

    def start(self):
        if not self.prepared:
            rc = self.prepare()
            assert rc == 0, os.strerror(-rc)
        self.thread = threading.Thread(target=lib.rt_loop_run, args=(self.c,), daemon=True)
        self.thread.start()
        return self

    def join(self):
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "the loop did not end"
        return self.stats()

    def stop(self):
        lib.rt_loop_request_stop(self.c)
        return self.join()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        if self.thread is not None and self.thread.is_alive():
            self.stop()

    def stats(self):
        s = ffi.new("rt_stats *")
        assert lib.rt_stats_read(self.c, s) == 0
        return s

    def wait(self, predicate, what):
        seen = {}

        def check():
            seen["s"] = s = self.stats()
            return predicate(s) or not self.thread.is_alive()

        wait_until(check, step=0.001)
        s = seen["s"]
        assert predicate(s), f"no {what} (loop state {s.state}, {s.ticks} ticks)"
        return s

    def push(self, channel, frames):
        """Frames (id, len, data[, flags]) into the channel's rx ring; returns how many it took."""
        arr = ffi.new("rt_frame[]", len(frames))
        for i, f in enumerate(frames):
            fid, length, data = f[:3]
            arr[i].id, arr[i].len = fid, length
            arr[i].flags = f[3] if len(f) > 3 else 0
            data = bytes(data)[:lib.CT_MAX_LENGTH]
            ffi.memmove(arr[i].data, data, len(data))
        return lib.rt_ring_push_many(ffi.addressof(self.c[0], "rx", channel), arr, len(frames))

    def pop_tx(self, channel):
        """Everything the loop sent on a channel: (id, len, data, flags, channel) in order."""
        out = []
        buf = ffi.new("rt_frame[1024]")
        while True:
            n = lib.rt_ring_pop_many(ffi.addressof(self.c[0], "tx", channel), buf, 1024)
            out.extend((buf[i].id, buf[i].len, bytes(ffi.buffer(buf[i].data, buf[i].len)), buf[i].flags,
                        buf[i].channel) for i in range(n))
            if n < 1024:
                return out

    def pop_log(self):
        out = []
        buf = ffi.new("rt_log_entry[1024]")
        while True:
            n = lib.rt_log_pop_many(ffi.addressof(self.c[0], "log"), buf, 1024)
            out.extend((buf[i].dir, buf[i].frame.id, buf[i].frame.len, buf[i].frame.flags,
                        buf[i].frame.channel) for i in range(n))
            if n < 1024:
                return out


def of(frames, frame_id):
    return [f for f in frames if f[0] == frame_id]


def sent_ticks(ticks, cycle_ms, period_s=0.0005):
    """Frames of a message of cycle_ms over ``ticks`` executed ticks (the loop's schedule)."""
    return ticks / max(1, round(cycle_ms * 1e-3 / period_s))


# ------------------------------------------------------------------ sent signals
def test_sent_signals_take_their_values_from_their_sources(rig):
    loop = Loop(rig.channels, duration_s=0.3,
                inputs={"brake_pedal_pct": 40.0, "accel_pedal_pct": 60.0, "road_grade_pct": -6.5})
    loop.start()
    s = loop.join()
    assert s.state == lib.RT_STATE_STOPPED and s.ticks > 0 and s.tx_dropped == 0
    a = loop.pop_tx(rig.chan("a"))
    assert {f[4] for f in a} == {rig.chan("a")} and {f[0] for f in a} == {0x200, 0x201}

    values = [f for f in a if f[0] == 0x200]
    assert len(values) == s.msgs[rig.msg["a", "P_Values"]].frames
    assert abs(len(values) - sent_ticks(s.ticks, 2)) <= 1
    for j, (fid, length, data, flags, _) in enumerate(values):
        assert (length, flags) == (8, 0)
        v = rig.decode("a", "P_Values", data)
        assert v["Mode"] == 3                                     # constant, by its value name "sport"
        assert v["Brake"] == pytest.approx(0.5 * 40.0 + 3.0)      # output * factor + offset
        assert v["Grade"] == pytest.approx(6.5)                   # abs: the magnitude of -6.5 %
        assert v["BrakeClass"] == 2                               # 40 in the range 10..50
        assert v["AccelClass"] == 7                               # 60 between ..59 and 61..: the default
        assert v["GradeClass"] == 4                               # -6.5 rounds half to even: key -6
        assert v["Spare"] == 17                                   # unmapped: the DBC's start value
        assert v["Tgl"] == j % 2                                  # 0, 1, 0, ... per frame
        assert v["Cnt"] == j % 6                                  # counter = 5: 0 .. 5 per frame
        assert v["P_Values_Ctr"] == j % 16                        # the protection's counter
        assert dct_crc_ok(fid, data), j

    status = [rig.decode("a", "P_Status", f[2]) for f in a if f[0] == 0x201]
    assert len(status) == s.msgs[rig.msg["a", "P_Status"]].frames
    assert abs(len(status) - 1 - sent_ticks(s.ticks, 10)) <= 1   # and the final frame
    # nothing received: starting (0) until the final frame says stopping (2)
    assert [x["SimState"] for x in status] == [0] * (len(status) - 1) + [2]
    times = [x["SimTime"] for x in status]
    # simulated time: one 10 ms cycle (20 ticks of 0.5 ms) from frame to frame
    assert all(abs(b - a_ - 0.010) <= 0.0011 for a_, b in zip(times[:-2], times[1:-1])), times
    assert times[0] <= 0.0105
    assert times[-1] == pytest.approx(s.sim_time_s, abs=0.001) and s.sim_time_s == pytest.approx(s.ticks * 0.0005)

    # the other bus: its own messages only, on its own ring
    b = loop.pop_tx(rig.chan("b"))
    assert {f[4] for f in b} == {rig.chan("b")}
    assert {f[0] for f in b} == {0x200, 0x18FEF100 | CAN_EFF_FLAG}
    out = [rig.decode("b", "Q_Out", f[2]) for f in b if f[0] == 0x200]
    assert all(len(f[2]) == 4 for f in b if f[0] == 0x200)
    assert [x["Pedal"] for x in out] == [60.0] * len(out)
    assert [x["Q_Out_Ctr"] for x in out] == [j % 16 for j in range(len(out))]
    assert abs(len(out) - sent_ticks(s.ticks, 4)) <= 1
    assert s.chan[rig.chan("a")].tx_frames == len(a) and s.chan[rig.chan("b")].tx_frames == len(b)
    assert s.tx_frames == len(a) + len(b)


def test_sim_state_says_running_once_a_received_frame_is_accepted(rig):
    with Loop(rig.channels) as loop:
        loop.wait(lambda s: s.msgs[rig.msg["a", "P_Status"]].frames >= 3, "3 status frames")
        assert loop.push(rig.chan("b"), [rig.frame("b", "F_Ext", {"ExtValue": 1.0})]) == 1
        loop.wait(lambda s: s.msgs[rig.msg["a", "P_Status"]].frames >= 8 and s.rx_accepted == 1,
                      "status frames after the first accepted frame")
    states = [rig.decode("a", "P_Status", f[2])["SimState"] for f in loop.pop_tx(rig.chan("a"))
              if f[0] == 0x201]
    # a frame accepted on any bus: 0 (starting) -> 1 (running), then 2 at the end
    assert states[0] == 0 and 1 in states and states[-1] == 2 and states == sorted(states)


# -------------------------------------------------------------- received signals
def test_received_signals_drive_their_targets_and_start_on_safe_values(rig):
    e_cmd = rig.msg["a", "E_Cmd"]
    loop = Loop(rig.channels)
    assert loop.prepare() == 0
    s = loop.stats()
    # at start every received message is timed out, every command at its safe value
    assert [s.msgs[g].timed_out for g in range(s.n_messages)] == [
        int(m.direction == "receive") for _, m in rig.channels.messages]
    assert {n: s.commands[k] for n, k in rig.cmd.items()} == {
        "gear_req": 3.0, "solenoid_current1_a": 0.05, "aux": 7.0, "beat": 42.0, "fork_force1_n": 0.0,
        "ext_value": 0.0}
    assert loop.c.plant.inputs.solenoid_current1_a == 0.05        # the safe value drives the input
    assert list(loop.c.command_input)[:len(rig.cmd)] == [
        -1 if i is None else _INPUTS.index(i) for i in rig.channels.command_inputs]

    # (Current, GearReq, Aux) -> (solenoid_current1_a, gear_req, aux):
    # current = 0.5 * signal - 0.2 limited to 0..1; gear_req by the value table
    # (-1 -> -1, 1..6 -> 10, 7 -> 0, else 99); aux = 2 * signal + 1
    cases = [((1.0, -1, 5), (0.3, -1.0, 11.0)),
             ((4.0, 3, 0), (1.0, 10.0, 1.0)),            # above max: 1.0
             ((0.2, 7, 100), (0.0, 0.0, 201.0)),         # below min: 0.0
             ((0.6, -8, 1), (0.1, 99.0, 3.0))]           # not in the table: its default
    with loop:
        for k, ((current, gear, aux), want) in enumerate(cases):
            frame = rig.frame("a", "E_Cmd", {"Current": current, "GearReq": gear, "Aux": aux}, counter=k)
            assert loop.push(rig.chan("a"), [frame]) == 1
            s = loop.wait(lambda s, k=k: s.msgs[e_cmd].frames == k + 1, f"E_Cmd frame {k}")
            got = (s.commands[rig.cmd["solenoid_current1_a"]], s.commands[rig.cmd["gear_req"]],
                   s.commands[rig.cmd["aux"]])
            assert got == pytest.approx(want, abs=1e-9), (k, got)
            assert loop.c.plant.inputs.solenoid_current1_a == pytest.approx(want[0], abs=1e-9)
            assert s.msgs[e_cmd].timed_out == 0
        assert s.rx_accepted == len(cases) and s.rx_frames == len(cases)
        # the other commands kept their safe values
        assert s.commands[rig.cmd["beat"]] == 42.0 and s.commands[rig.cmd["fork_force1_n"]] == 0.0


def test_a_silent_message_times_out_to_its_safe_values_and_recovers(rig_dir):
    rig = Rig(rig_dir / "rig_short.toml")             # E_Cmd timed out after 2 cycles (200 ms)
    e_cmd, e_beat, f_cmd = rig.msg["a", "E_Cmd"], rig.msg["a", "E_Beat"], rig.msg["b", "F_Cmd"]
    cmd = rig.cmd
    with Loop(rig.channels) as loop:
        loop.wait(lambda s: s.ticks >= 10, "10 ticks")
        loop.push(rig.chan("a"), [rig.frame("a", "E_Cmd", {"Current": 1.0, "GearReq": 2, "Aux": 5}, counter=5),
                                  rig.frame("a", "E_Beat", {"Beat": 9})])
        s = loop.wait(lambda s: s.rx_accepted == 2, "the first frames")
        # applied, unless the short-lived E_Beat (30 ms) timed out already
        assert (s.commands[cmd["beat"]] == 9.0 and s.msgs[e_beat].timed_out == 0) or s.msgs[e_beat].timeouts == 1
        assert (s.commands[cmd["solenoid_current1_a"]] == pytest.approx(0.3) and s.commands[cmd["gear_req"]] == 10
                ) or s.msgs[e_cmd].timeouts == 1
        # silence: each message times out after its own timeout
        s = loop.wait(lambda s: s.msgs[e_cmd].timed_out and s.msgs[e_beat].timed_out, "the timeouts")
        assert s.msgs[e_cmd].timeouts == 1 and s.msgs[e_beat].timeouts == 1
        assert s.msgs[f_cmd].timeouts == 0 and s.msgs[f_cmd].timed_out == 1      # never heard
        assert (s.commands[cmd["solenoid_current1_a"]], s.commands[cmd["gear_req"]], s.commands[cmd["aux"]],
                s.commands[cmd["beat"]]) == (0.05, 3.0, 7.0, 42.0)
        assert loop.c.plant.inputs.solenoid_current1_a == 0.05
        # back: the first frame after a timeout is accepted whatever its counter
        loop.push(rig.chan("a"), [rig.frame("a", "E_Cmd", {"Current": 0.6, "GearReq": 7, "Aux": 1}, counter=12)])
        s = loop.wait(lambda s: s.msgs[e_cmd].frames == 2, "the recovery frame")
        assert s.rx_bad_counter == 0
        assert (s.msgs[e_cmd].timed_out == 0 and s.commands[cmd["solenoid_current1_a"]] == pytest.approx(0.1)
                and s.commands[cmd["gear_req"]] == 0.0) or s.msgs[e_cmd].timeouts == 2
        loop.wait(lambda s: s.msgs[e_cmd].timeouts == 2, "the second timeout")


def test_rejected_frames_are_counted_per_message_and_per_channel(rig):
    a, b = rig.chan("a"), rig.chan("b")
    e_cmd, f_cmd = rig.msg["a", "E_Cmd"], rig.msg["b", "F_Cmd"]

    def e(counter, current=4.0):
        return rig.frame("a", "E_Cmd", {"Current": current}, counter=counter)

    good = e(0, current=0.6)
    bad_crc = e(1)
    bad_crc = (bad_crc[0], 8, bytes([bad_crc[2][0] ^ 0x21]) + bad_crc[2][1:])
    on_a = [good, bad_crc,
            e(0), e(4),                                             # repeated, jumped by 4: bad counter
            (good[0], 7, e(1)[2][:7]), (good[0], 9, e(1)[2] + b"\0"),  # short, long: bad length
            (good[0], 8, e(1)[2], lib.RT_FRAME_FD),                 # a CAN FD frame of a classic message
            (good[0] | CAN_RTR_FLAG, 8, e(1)[2]),                   # a remote frame
            (0x7FF, 8, bytes(8)),                                   # unknown ids: not in the table,
            (0x200, 8, bytes(8)),                                   # a message the plant sends,
            (good[0] | CAN_ERR_FLAG, 8, e(1)[2])]                   # an error frame
    f_good = rig.frame("b", "F_Cmd", {"Force": 120}, counter=3)
    on_b = [(0x555, 8, bytes(8)), f_good, (f_good[0], 8, e(1)[2])]  # F_Cmd has 6 bytes
    with Loop(rig.channels, log_frames=1) as loop:
        assert loop.push(a, on_a) == len(on_a) and loop.push(b, on_b) == len(on_b)
        s = loop.wait(lambda s: s.rx_frames == len(on_a) + len(on_b), "every frame")
        m = s.msgs[e_cmd]
        assert (m.frames, m.bad_crc, m.bad_counter, m.bad_length) == (1, 1, 2, 4)
        m = s.msgs[f_cmd]
        assert (m.frames, m.bad_crc, m.bad_counter, m.bad_length) == (1, 0, 0, 1)
        ca, cb = s.chan[a], s.chan[b]
        assert (ca.rx_frames, ca.rx_accepted, ca.rx_bad_crc, ca.rx_bad_counter, ca.rx_bad_length,
                ca.rx_unknown_id) == (11, 1, 1, 2, 4, 3)
        assert (cb.rx_frames, cb.rx_accepted, cb.rx_bad_crc, cb.rx_bad_counter, cb.rx_bad_length,
                cb.rx_unknown_id) == (3, 1, 0, 0, 1, 1)
        for total in ("rx_frames", "rx_accepted", "rx_bad_crc", "rx_bad_counter", "rx_bad_length",
                      "rx_unknown_id"):
            assert getattr(s, total) == getattr(ca, total) + getattr(cb, total), total
        others = [g for g in range(s.n_messages) if g not in (e_cmd, f_cmd)]
        assert all(s.msgs[g].bad_crc + s.msgs[g].bad_counter + s.msgs[g].bad_length == 0 for g in others)
        # only the accepted frames were decoded (the rejected ones carried 4 A)
        assert s.commands[rig.cmd["solenoid_current1_a"]] == pytest.approx(0.1)
        assert s.commands[rig.cmd["fork_force1_n"]] == 120.0
        assert loop.c.rx_state[e_cmd].last_counter == 0
    rx = [e for e in loop.pop_log() if e[0] == lib.RT_DIR_RX]
    assert [(e[1], e[2], e[3], e[4]) for e in rx if e[4] == a] == [
        (f[0], f[1], f[3] if len(f) > 3 else 0, a) for f in on_a]


# ------------------------------------------------------------------ two buses
def test_two_channels_keep_their_frames_and_identifiers_apart(rig):
    a, b = rig.chan("a"), rig.chan("b")
    e_cmd, f_cmd = rig.msg["a", "E_Cmd"], rig.msg["b", "F_Cmd"]
    e = rig.frame("a", "E_Cmd", {"Current": 1.0}, counter=0)        # 0x100 on bus a: 8 bytes
    f = rig.frame("b", "F_Cmd", {"Force": -250}, counter=0)         # 0x100 on bus b: 6 bytes
    assert e[0] == f[0] == 0x100
    with Loop(rig.channels, inputs={"accel_pedal_pct": 60.0}) as loop:
        loop.push(a, [e])
        loop.push(b, [f])
        s = loop.wait(lambda s: s.rx_accepted == 2, "a frame on each bus")
        assert s.msgs[e_cmd].frames == 1 and s.msgs[f_cmd].frames == 1
        assert s.chan[a].rx_accepted == 1 and s.chan[b].rx_accepted == 1
        assert s.commands[rig.cmd["solenoid_current1_a"]] == pytest.approx(0.3)
        assert s.commands[rig.cmd["fork_force1_n"]] == -250.0
        assert loop.c.plant.inputs.fork_force1_n == -250.0
        # each bus's frame on the other bus: the other layout, rejected there
        loop.push(a, [(f[0], f[1], f[2])])
        loop.push(b, [(e[0], e[1], e[2])])
        s = loop.wait(lambda s: s.rx_frames == 4, "the crossed frames")
        assert s.msgs[e_cmd].bad_length == 1 and s.msgs[f_cmd].bad_length == 1 and s.rx_accepted == 2
        assert s.commands[rig.cmd["solenoid_current1_a"]] == pytest.approx(0.3)
        assert s.commands[rig.cmd["fork_force1_n"]] == -250.0
        loop.wait(lambda s: s.msgs[rig.msg["b", "Q_Out"]].frames >= 5, "frames on bus b")
    s = loop.stats()
    fa, fb = loop.pop_tx(a), loop.pop_tx(b)
    # 0x200 is P_Values (8 bytes) on bus a and Q_Out (4 bytes) on bus b
    assert {(fid, n, ch) for fid, n, _, _, ch in fa} == {(0x200, 8, a), (0x201, 8, a)}
    assert {(fid, n, ch) for fid, n, _, _, ch in fb} == {(0x200, 4, b), (0x18FEF100 | CAN_EFF_FLAG, 8, b)}
    for bus, frames in (("a", fa), ("b", fb)):
        ch = rig.chan(bus)
        assert s.chan[ch].tx_frames == len(frames) and s.chan[ch].tx_dropped == 0
        for (mbus, m), g in rig.msg.items():
            if mbus == bus and m in ("P_Values", "P_Status", "Q_Out", "Q_Ext"):
                fid = rig.db[bus].get_message_by_name(m).frame_id
                assert s.msgs[g].frames == len([x for x in frames if x[0] & 0x1FFFFFFF == fid]), m


def test_extended_identifiers_are_sent_and_received_as_29_bit(rig):
    b = rig.chan("b")
    f_ext = rig.msg["b", "F_Ext"]
    ext = rig.frame("b", "F_Ext", {"ExtValue": 321.5})
    assert ext[0] == 0x18FF0010 | CAN_EFF_FLAG
    with Loop(rig.channels) as loop:
        loop.push(b, [ext,
                      (0x18FF0010, 8, ext[2]),                      # the same number without the flag
                      (0x100 | CAN_EFF_FLAG, 6, bytes(6))])         # a standard message's id as 29-bit
        s = loop.wait(lambda s: s.rx_frames == 3, "the frames")
        assert s.msgs[f_ext].frames == 1 and s.chan[b].rx_unknown_id == 2
        assert s.commands[rig.cmd["ext_value"]] == pytest.approx(321.5)
        loop.wait(lambda s: s.msgs[rig.msg["b", "Q_Ext"]].frames >= 3, "3 extended frames")
    sent = of(loop.pop_tx(b), 0x18FEF100 | CAN_EFF_FLAG)
    assert len(sent) >= 3
    assert all(rig.decode("b", "Q_Ext", f[2])["ExtSpeed"] == 12.5 for f in sent)


# ------------------------------------------------------------------ CAN FD
def test_can_fd_frames_of_64_bytes_round_trip_through_the_ring(fd_rig):
    fd_out, fd_in = fd_rig.msg["fd", "FD_Out"], fd_rig.msg["fd", "FD_In"]
    db_out = fd_rig.db["fd"].get_message_by_name("FD_Out")
    assert db_out.is_fd and db_out.length == 64
    fd_flags = lib.RT_FRAME_FD | lib.RT_FRAME_BRS                    # data_bitrate: bit rate switch
    first = fd_rig.frame("fd", "FD_In", {"Level": 123.4}, counter=0, flags=fd_flags)
    second = fd_rig.frame("fd", "FD_In", {"Level": 5.5}, counter=1, flags=lib.RT_FRAME_FD)
    assert first[1] == 64
    with Loop(fd_rig.channels, inputs={"accel_pedal_pct": 60.0}, log_frames=1) as loop:
        loop.push(0, [first])
        s = loop.wait(lambda s: s.rx_accepted == 1, "the FD frame")
        assert s.commands[fd_rig.cmd["level"]] == pytest.approx(123.4)
        loop.push(0, [(first[0], 64, first[2]),                     # 64 bytes, not flagged CAN FD
                      (first[0], 8, first[2][:8], lib.RT_FRAME_FD),  # CAN FD, 8 bytes
                      second])
        s = loop.wait(lambda s: s.rx_frames == 4, "the frames")
        m = s.msgs[fd_in]
        assert (m.frames, m.bad_length, m.bad_crc, m.bad_counter) == (2, 2, 0, 0)
        assert s.commands[fd_rig.cmd["level"]] == pytest.approx(5.5)
        loop.wait(lambda s: s.msgs[fd_out].frames >= 20, "20 FD frames")
    s = loop.stats()
    frames = loop.pop_tx(0)
    assert len(frames) == s.msgs[fd_out].frames == s.tx_frames
    for j, (fid, length, data, flags, ch) in enumerate(frames):
        assert (fid, length, flags, ch) == (0x300, 64, fd_flags, 0)
        v = db_out.decode(data, decode_choices=False)
        assert (v["Pedal"], v["Far"], v["FD_Out_Ctr"]) == (60.0, 4660, j % 16)
        assert data[62:64] == bytes([0x34, 0x12])
        assert dct_crc_ok(fid, data), j                           # over the identifier and 63 bytes
    # the traffic log keeps whole CAN FD frames, received and sent
    log = loop.pop_log()
    assert [(e[2], e[3]) for e in log if e[0] == lib.RT_DIR_RX] == [
        (64, fd_flags), (64, 0), (8, lib.RT_FRAME_FD), (64, lib.RT_FRAME_FD)]
    assert {(e[2], e[3]) for e in log if e[0] == lib.RT_DIR_TX} == {(64, fd_flags)}


def test_can_fd_on_a_socket_needs_fd_frames_and_carries_canfd_frames(fd_rig):
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    with ours, peer:
        loop = Loop(fd_rig.channels)
        loop.c.chan[0].transport = lib.RT_TRANSPORT_SOCKETCAN
        loop.c.chan[0].fd = ours.fileno()
        loop.c.chan[0].fd_frames = 0
        assert loop.prepare() == -errno.EINVAL          # a CAN FD message on a classic socket
        loop.c.chan[0].fd_frames = 1
        assert loop.prepare() == 0
        with loop:
            peer.settimeout(WAIT_S)
            got = []
            while len(got) < 10:
                raw = peer.recv(256)
                assert len(raw) == CANFD_FRAME.size         # CANFD_MTU, 72 bytes
                got.append(CANFD_FRAME.unpack(raw))
            level = fd_rig.frame("fd", "FD_In", {"Level": 77.7}, counter=0)
            peer.send(CANFD_FRAME.pack(level[0], 64, CANFD_BRS, level[2]))
            peer.send(CAN_FRAME.pack(level[0], 8, level[2][:8]))    # a classic frame of it
            s = loop.wait(lambda s: s.rx_frames == 2, "the frames")
            assert s.rx_accepted == 1 and s.msgs[fd_rig.msg["fd", "FD_In"]].bad_length == 1
            assert s.commands[fd_rig.cmd["level"]] == pytest.approx(77.7)
    for j, (fid, length, flags, data) in enumerate(got):
        assert (fid, length, flags) == (0x300, 64, CANFD_BRS)
        assert data[62:64] == bytes([0x34, 0x12]) and (data[1] & 0x0F) == j % 16 and dct_crc_ok(fid, data)


# ------------------------------------------------------------ refused tables
def _signal(loop, array, pred):
    """(channel, signal index) of the first source or target (``array``) of a
    sent or received message for which ``pred`` holds, read from the loop's tables."""
    lc = loop.c
    for c in range(lc.n_channels):
        ch = lc.chan[c]
        for m in range(ch.table.n_messages):
            if ch.msgs[m].direction != (lib.RT_DIR_TX if array == "sources" else lib.RT_DIR_RX):
                continue
            cm = ch.table.messages[m]
            for k in range(cm.first_signal, cm.first_signal + cm.n_signals):
                if pred(getattr(ch, array)[k]):
                    return c, k
    raise AssertionError(f"no such {array}")


def _break(loop, what):
    lc = loop.c
    if what == "output index":
        c, k = _signal(loop, "sources", lambda x: x.kind == lib.RT_SRC_OUTPUT)
        lc.chan[c].sources[k].field = len(_OUTPUTS)
    elif what == "status index":
        c, k = _signal(loop, "sources", lambda x: x.kind == lib.RT_SRC_STATUS)
        lc.chan[c].sources[k].field = lib.RT_N_STATUS
    elif what == "value table beyond the ranges":
        c, k = _signal(loop, "sources", lambda x: x.kind == lib.RT_SRC_OUTPUT and x.table.count > 0)
        lc.chan[c].sources[k].table.first = lc.chan[c].n_ranges
    elif what == "command index":
        c, k = _signal(loop, "targets", lambda x: x.kind == lib.RT_TGT_COMMAND)
        lc.chan[c].targets[k].command = lc.n_commands
    elif what == "min above max":
        c, k = _signal(loop, "targets", lambda x: x.kind == lib.RT_TGT_COMMAND)
        lc.chan[c].targets[k].minimum, lc.chan[c].targets[k].maximum = 2.0, 1.0
    elif what == "input index":
        lc.command_input[0] = len(_INPUTS)
    elif what == "no channel":
        lc.n_channels = 0
    elif what == "five channels":
        lc.n_channels = 5
    elif what == "no table":
        lc.chan[1].table.messages = ffi.NULL
    elif what == "cycle time 0":
        lc.chan[0].msgs[0].cycle_s = 0.0
    elif what == "unknown transport":
        lc.chan[1].transport = 7
    else:
        raise AssertionError(what)


BROKEN = ["output index", "status index", "value table beyond the ranges", "command index",
          "min above max", "input index", "no channel", "five channels", "no table", "cycle time 0",
          "unknown transport"]


@pytest.mark.parametrize("what", BROKEN)
def test_prepare_refuses_bad_tables(rig_dir, what):
    rig = Rig(rig_dir / "rig.toml")                      # tables of its own: this test breaks them
    loop = Loop(rig.channels)
    _break(loop, what)
    assert loop.prepare() == -errno.EINVAL
    s = loop.stats()
    assert s.n_channels == 0 and s.n_messages == 0 and s.ticks == 0
    assert lib.rt_loop_run(loop.c) == -errno.EINVAL             # a refused set-up never runs
    assert loop.stats().ticks == 0
    fresh = Loop(Rig(rig_dir / "rig.toml").channels)            # the same tables, unbroken
    assert fresh.prepare() == 0 and fresh.stats().n_channels == 2


# ------------------------------------------------------------ the vehicle matrix
def test_the_vehicle_mapping_is_served_on_both_buses():
    rig = Rig(can_mapping.find_mapping("vehicle"))
    assert rig.buses == ["pt", "io"]
    duration, period = 0.5, 0.0005
    loop = Loop(rig.channels, duration_s=duration, inputs={"accel_pedal_pct": 20.0})
    assert loop.prepare() == 0
    # one protected frame of every message the TCU sends, on its own bus
    received = [(b, m) for b, m in rig.channels.messages if m.direction == "receive"]
    for bus, m in received:
        counter = 0 if m.protection.kind != "none" else None
        assert loop.push(rig.chan(bus), [rig.frame(bus, m.name, {}, counter=counter)]) == 1
    loop.start()
    s = loop.join()
    assert s.state == lib.RT_STATE_STOPPED and s.ticks + s.skipped_ticks == round(duration / period)
    assert s.rx_accepted == len(received) and s.rx_frames == len(received) and s.tx_dropped == 0
    for bus, m in received:
        assert s.msgs[rig.msg[bus, m.name]].frames == 1, m.name

    checked = set()
    for bus in rig.buses:
        ch = rig.chan(bus)
        frames = loop.pop_tx(ch)
        assert {f[4] for f in frames} == {ch}
        table = rig.channels.table(bus)
        sent = [m for b, m in rig.channels.messages if b == bus and m.direction == "send"]
        assert {f[0] for f in frames} == {m.frame_id for m in sent}
        assert s.chan[ch].tx_frames == len(frames)
        for m in sent:
            mine = [f[2] for f in frames if f[0] == m.frame_id]
            # about one frame per cycle of the ticks the loop executed
            assert abs(len(mine) - sent_ticks(s.ticks, m.cycle_ms, period)) <= 2, (m.name, len(mine))
            assert len(mine) == s.msgs[rig.msg[bus, m.name]].frames
            for data in mine:
                rig.db[bus].decode_message(m.frame_id, data)
            if m.protection.kind != "none":
                state = table.new_state()
                assert [table.check(m.name, d, state) for d in mine] == ["ok"] * len(mine), m.name
                checked.add((m.protection.kind, m.protection.data_id_mode if m.protection.kind == "p1" else None,
                             m.protection.counter_signal is not None))
    # Profile 1 (both Data ID bytes, the nibble), XOR with and without a counter, the contract's
    assert {("p1", "both", True), ("p1", "nibble", True), ("xor", None, True), ("xor", None, False),
            ("dct", None, True), ("counter", None, True)} <= checked
