"""The real-time loop in C (rt_loop/csrc/), driven from Python on the host.

No CAN needed: the loop runs in a Python thread (cffi releases the GIL for
rt_loop_run) and exchanges frames through its rings (the bridge transport),
or through an AF_UNIX datagram socket pair standing in for a CAN_RAW socket
(the same recvmmsg/sendmmsg path; the host kernel has no CAN). The loop
serves the default mapping (can_dbc/mappings/dct_hil.toml: the project's own
contract, one bus), its tables built once by rt_loop.channels.LoopChannels.
TCU frames are packed and protected by that mapping's CodecTable; the
plant's frames are checked against the DBC (cantools) and a CRC written here.

Every assertion is about behaviour: counts, values, ordering. Waits poll the
statistics with a generous limit and never judge how long something took.
"""

import errno
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

import cantools
import numpy as np
import pytest

from can_dbc import mapping as can_mapping
from plant.params import fill_params, load_params
from rt_loop._rt_loop import ffi, lib
from rt_loop.channels import LoopChannels

DBC_PATH = Path(__file__).resolve().parents[1] / "can_dbc" / "dct_hil.dbc"
DB = cantools.database.load_file(str(DBC_PATH))
PLANT_MESSAGES = [m for m in DB.messages if "PLANT" in m.senders]
TCU_MESSAGES = {m.name: m for m in DB.messages if "TCU" in m.senders}
CLUTCH_CMD = TCU_MESSAGES["TCU_ClutchCmd"]
ENGINE_CMD = TCU_MESSAGES["TCU_EngineCmd"]

# the default mapping's tables, built once and installed into every loop
MAPPING = can_mapping.load(can_mapping.DEFAULT_MAPPING)
CHANNELS = LoopChannels(MAPPING, ffi, lib)
TABLE = CHANNELS.table(0)
MSG = {m.name: g for g, (_, m) in enumerate(CHANNELS.messages)}      # stats.msgs index
RX_MSGS = [g for g, (_, m) in enumerate(CHANNELS.messages) if m.direction == "receive"]
TX_MSGS = [g for g, (_, m) in enumerate(CHANNELS.messages) if m.direction == "send"]
CMD = {name: k for k, name in enumerate(CHANNELS.command_names)}   # stats.commands index
CLUTCH, SHIFT, ENGINE = MSG["TCU_ClutchCmd"], MSG["TCU_ShiftCmd"], MSG["TCU_EngineCmd"]

WAIT_S = 30.0                   # limit of a wait for behaviour (never a timing check)
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_FRAME = struct.Struct("<IBxxx8s")   # struct can_frame (CAN_MTU, 16 bytes): id, len, pad, res0, len8_dlc, data

_PARAMS = load_params(None, ffi, None)


def crc8_j1850(data):
    """CRC-8/SAE-J1850, written independently of the C (poly 0x1D, init and xorout 0xFF)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def e2e_ok(frame_id, data):
    return data[0] == crc8_j1850(bytes([frame_id & 0xFF, (frame_id >> 8) & 0xFF]) + bytes(data[1:]))


def tcu_frame(message, counter, **signals):
    """(id, len, data) of a TCU frame: the signals packed, AliveCounter and CRC
    written by the default mapping's table codec."""
    data = TABLE.encode(message.name, signals, counter=counter)
    return (message.frame_id, len(data), data)


def ring_addr(loop, name, channel=0):
    return ffi.addressof(loop.c[0], name, channel)


def frames_of(buf, n):
    """(id, len, data) of rt_frames, data as long as the frame."""
    return [(buf[i].id, buf[i].len, bytes(ffi.buffer(buf[i].data, buf[i].len))) for i in range(n)]


class Loop:
    """One rt_loop serving the default mapping: prepared on creation, run in a thread of its own."""

    def __init__(self, period_s=0.0005, duration_s=0.0, transport=lib.RT_TRANSPORT_RING, fd=-1,
                 log_frames=0, overrun_stop=0, tweak=None, step_s=0.0, record_every=0,
                 driver=None):
        self.c = ffi.new("rt_loop *")
        fill_params(ffi, ffi.addressof(self.c[0].plant, "params"), _PARAMS)
        if tweak:
            tweak(self.c.plant.params)
        cfg = self.c.cfg
        cfg.period_s = period_s
        cfg.priority = 0
        cfg.cpu = -1
        cfg.lock_memory = 0
        cfg.overrun_stop = overrun_stop
        cfg.duration_s = duration_s
        cfg.log_frames = log_frames
        cfg.step_s = step_s
        cfg.record_every = record_every
        CHANNELS.install(self.c)
        self.c.chan[0].transport = transport
        self.c.chan[0].fd = fd
        if driver is not None:      # dict: rows [(t_s, accel, brake)], linear, start_on_tcu, end_s
            d = self.c.driver
            d.rows = len(driver["rows"])
            for i, (t, a, b) in enumerate(driver["rows"]):
                d.t_s[i], d.accel_pedal_pct[i], d.brake_pedal_pct[i] = t, a, b
            d.linear = driver.get("linear", 0)
            d.start_on_tcu = driver.get("start_on_tcu", 0)
            d.end_s = driver.get("end_s", 0.0)
            if "selector" in driver:    # a code per row (0 P, 1 R, 2 N, 3 D)
                d.has_selector = 1
                for i, code in enumerate(driver["selector"]):
                    d.selector_lever[i] = code
            if "grade" in driver:       # the maneuver's road grade, %
                d.has_grade, d.road_grade_pct = 1, driver["grade"]
        self.prepare_rc = lib.rt_loop_prepare(self.c)
        self.thread = None
        self.result = None

    def start(self):
        assert self.prepare_rc == 0, os.strerror(-self.prepare_rc)

        def run():
            self.result = lib.rt_loop_run(self.c)

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        return self

    def join(self):
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "the loop did not end"
        return self.result

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
        end = time.monotonic() + WAIT_S
        while True:
            s = self.stats()
            if predicate(s):
                return s
            assert self.thread.is_alive(), f"the loop ended before {what} (state {s.state})"
            assert time.monotonic() < end, f"no {what} after {WAIT_S} s"
            time.sleep(0.0005)

    def push(self, frames):
        arr = ffi.new("rt_frame[]", len(frames))
        for i, (fid, length, data) in enumerate(frames):
            arr[i].id = fid
            arr[i].len = length
            data = bytes(data)[:lib.CT_MAX_LENGTH]
            ffi.memmove(arr[i].data, data, len(data))
        return lib.rt_ring_push_many(ring_addr(self, "rx"), arr, len(frames))

    def pop_tx(self):
        out = []
        buf = ffi.new("rt_frame[1024]")
        while True:
            n = lib.rt_ring_pop_many(ring_addr(self, "tx"), buf, 1024)
            out.extend(frames_of(buf, n))
            if n < 1024:
                return out

    def pop_log(self):
        out = []
        buf = ffi.new("rt_log_entry[4096]")
        while True:
            n = lib.rt_log_pop_many(ffi.addressof(self.c[0], "log"), buf, 4096)
            out.extend((buf[i].time_s, buf[i].dir, buf[i].frame.id, buf[i].frame.len,
                        bytes(ffi.buffer(buf[i].frame.data, buf[i].frame.len))) for i in range(n))
            if n < 4096:
                return out

    def pop_rec(self):
        out = []
        buf = ffi.new("rt_sample[512]")
        while True:
            n = lib.rt_rec_pop_many(ffi.addressof(self.c[0], "rec"), buf, 512)
            out.extend((buf[i].tick, buf[i].time_s, buf[i].maneuver_time_s,
                        buf[i].outputs.accel_pedal_pct, buf[i].outputs.brake_pedal_pct,
                        buf[i].commands[CMD["solenoid_current1_a"]]) for i in range(n))
            if n < 512:
                return out


def hist(s, name):
    return np.frombuffer(ffi.buffer(getattr(s, name)), dtype=np.uint64)


def rejected(s):
    return s.rx_unknown_id + s.rx_bad_length + s.rx_bad_crc + s.rx_bad_counter


def command(s, name):
    return s.commands[CMD[name]]


def divisor(cycle_ms, period_s):
    return max(1, round(cycle_ms * 1e-3 / period_s))


# --------------------------------------------------------------------- set-up
def test_prepare_rejects_bad_configurations():
    assert Loop(period_s=40e-6).prepare_rc == -errno.EINVAL
    assert Loop(period_s=0.02).prepare_rc == -errno.EINVAL     # the step (the period) above 10 ms
    assert Loop(period_s=float("nan")).prepare_rc == -errno.EINVAL
    assert Loop(transport=7).prepare_rc == -errno.EINVAL
    assert Loop(duration_s=float("nan")).prepare_rc == -errno.EINVAL
    assert Loop(transport=lib.RT_TRANSPORT_SOCKETCAN, fd=-1).prepare_rc == -errno.EBADF
    with open(__file__, "rb") as f:
        assert Loop(transport=lib.RT_TRANSPORT_SOCKETCAN, fd=f.fileno()).prepare_rc == -errno.ENOTSOCK
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with a, b:
        assert Loop(transport=lib.RT_TRANSPORT_SOCKETCAN, fd=a.fileno()).prepare_rc == -errno.EPROTOTYPE
    # the plant rejects its parameters: -EDOM, the plant's status in stats.error
    bad = Loop(tweak=lambda p: setattr(p.solver, "substeps", 0))
    assert bad.prepare_rc == -errno.EDOM and bad.c.stats.error == -lib.DCT_ERR_PARAM


def test_prepare_starts_timed_out_on_safe_values():
    loop = Loop(period_s=0.001)
    assert loop.prepare_rc == 0
    s = loop.stats()
    assert s.state == lib.RT_STATE_IDLE and s.seq % 2 == 0 and s.ticks == 0
    assert s.n_channels == 1 and s.n_messages == len(CHANNELS.messages) == len(TABLE)
    assert loop.c.chan[0].first_message == 0
    assert [s.msgs[g].timed_out for g in RX_MSGS] == [1] * len(RX_MSGS) == [1] * 4
    assert [s.msgs[g].timed_out for g in TX_MSGS] == [0] * len(TX_MSGS)
    assert [s.msgs[g].timeouts for g in RX_MSGS] == [0] * len(RX_MSGS)
    assert command(s, "solenoid_current1_a") == 0 and command(s, "torque_request_active") == 0
    assert [command(s, f"fork_force{i}_n") for i in range(1, 5)] == [0.0] * 4
    assert command(s, "target_gear") == 0
    assert [loop.c.rx_state[g].last_counter for g in range(len(TABLE))] == [-1] * len(TABLE)
    assert loop.c.plant.params.solver.step_s == 0.001
    assert loop.c.plant.inputs.engine_on == 1.0


def test_run_needs_prepare():
    loop = Loop(duration_s=0.01)
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    assert lib.rt_loop_run(loop.c) == -errno.EINVAL        # ran already
    assert lib.rt_loop_prepare(loop.c) == 0
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    fresh = ffi.new("rt_loop *")
    assert lib.rt_loop_run(fresh) == -errno.EINVAL          # never prepared
    assert lib.rt_loop_prepare(fresh) == -errno.EINVAL      # no configuration, no channel tables
    # configured and given its tables, but never prepared: refused all the same
    fresh.cfg.period_s, fresh.cfg.cpu, fresh.cfg.duration_s = 0.0005, -1, 0.01
    CHANNELS.install(fresh)
    fresh.chan[0].transport = lib.RT_TRANSPORT_RING
    assert lib.rt_loop_run(fresh) == -errno.EINVAL and fresh.stats.ticks == 0
    # a prepare that failed leaves the loop unprepared, even after an earlier good one
    again = Loop(duration_s=0.01)
    assert again.prepare_rc == 0
    again.c.n_channels = lib.RT_MAX_CHANNELS + 1
    assert lib.rt_loop_prepare(again.c) == -errno.EINVAL
    assert lib.rt_loop_run(again.c) == -errno.EINVAL and again.c.stats.ticks == 0
    again.c.n_channels = 1
    assert lib.rt_loop_prepare(again.c) == 0
    again.start()
    assert again.join() == lib.RT_STATE_STOPPED


# ---------------------------------------------------------------------- rings
def test_ring_refuses_when_full_and_keeps_order_across_the_index_wrap():
    r = ffi.new("rt_ring *")
    frames = ffi.new("rt_frame[]", lib.RT_RING_SIZE + 5)
    for i in range(lib.RT_RING_SIZE + 5):
        frames[i].id = i
        frames[i].len = 64
        frames[i].data[63] = i & 0xFF
    assert lib.rt_ring_push_many(r, frames, lib.RT_RING_SIZE + 5) == lib.RT_RING_SIZE
    assert r.dropped == 5
    assert lib.rt_ring_push(r, frames) == -1 and r.dropped == 6
    out = ffi.new("rt_frame[]", lib.RT_RING_SIZE)
    assert lib.rt_ring_pop_many(r, out, lib.RT_RING_SIZE) == lib.RT_RING_SIZE
    assert [out[i].id for i in range(lib.RT_RING_SIZE)] == list(range(lib.RT_RING_SIZE))
    assert [out[i].data[63] for i in range(lib.RT_RING_SIZE)] == [i & 0xFF for i in range(lib.RT_RING_SIZE)]
    one = ffi.new("rt_frame *")
    assert lib.rt_ring_pop(r, one) == -1

    r.head = r.tail = 0xFFFFFFF0                  # the free-running indices wrap
    assert lib.rt_ring_push_many(r, frames, 40) == 40
    assert r.head == (0xFFFFFFF0 + 40) & 0xFFFFFFFF
    assert lib.rt_ring_pop_many(r, out, 100) == 40
    assert [out[i].id for i in range(40)] == list(range(40))


# ------------------------------------------------------------- plant frames
def test_plant_frames_ids_lengths_counters_crc_and_rates():
    period = 0.0005
    loop = Loop(period_s=period, duration_s=0.5, log_frames=1)
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    s = loop.stats()
    frames = loop.pop_tx()
    ticks = s.ticks
    assert ticks > 0 and ticks + s.skipped_ticks == round(0.5 / period)
    assert s.tx_frames == len(frames) and s.tx_dropped == 0
    assert s.chan[0].tx_frames == s.tx_frames and s.chan[0].tx_dropped == 0
    assert s.sim_time_s == pytest.approx(ticks * period, abs=1e-9)

    by_id = defaultdict(list)
    for fid, length, data in frames:
        by_id[fid].append((length, data))
    assert set(by_id) == {m.frame_id for m in PLANT_MESSAGES}
    for m in PLANT_MESSAGES:
        got = by_id[m.frame_id]
        assert all(length == m.length for length, _ in got), m.name
        assert all(e2e_ok(m.frame_id, data) for _, data in got), m.name
        counters = [data[1] & 0x0F for _, data in got]
        assert counters[0] == 0
        assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:])), m.name
        for _, data in got:
            m.decode(data)              # every frame decodes against the DBC
        # counted per message
        assert s.msgs[MSG[m.name]].frames == len(got) and s.msgs[MSG[m.name]].dropped == 0
        # rates: one frame per cycle time of executed ticks (+ the final SIM_Status)
        extra = 1 if m.name == "SIM_Status" else 0
        expected = ticks / divisor(m.cycle_time, period)
        assert abs(len(got) - extra - expected) <= 1, (m.name, len(got), expected)

    status = [DB.get_message_by_name("SIM_Status").decode(d, decode_choices=False)
              for _, d in by_id[DB.get_message_by_name("SIM_Status").frame_id]]
    assert [st["SimState"] for st in status[:-1]] == [0] * (len(status) - 1)   # no TCU heard
    assert status[-1]["SimState"] == 2                                          # stopping
    times = [st["SimTime"] for st in status]
    assert times == sorted(times) and times[-1] == pytest.approx(ticks * period, abs=0.01)

    clutch = [DB.get_message_by_name("DCT_Clutch").decode(d)
              for _, d in by_id[DB.get_message_by_name("DCT_Clutch").frame_id]]
    assert clutch[-1]["LinePressure"] == pytest.approx(s.outputs.line_pressure_bar, abs=0.01)
    shaft = [DB.get_message_by_name("DCT_ShaftSpeeds").decode(d)
             for _, d in by_id[DB.get_message_by_name("DCT_ShaftSpeeds").frame_id]]
    assert shaft[-1]["EngineSpeed"] == pytest.approx(s.outputs.engine_speed_rpm, abs=0.5)

    # the traffic log holds every frame sent, stamped with its tick's deadline;
    # the offsets spread the messages: at 2 kHz no tick sends two frames
    log = loop.pop_log()
    assert [(e[2], e[3], e[4]) for e in log] == frames
    assert all(e[1] == lib.RT_DIR_TX for e in log) and loop.c.log.dropped == 0
    per_tick = Counter(e[0] for e in log[:-1])          # the last one is the final SIM_Status
    assert max(per_tick.values()) == 1


# ---------------------------------------------------------- TCU commands in
def feed_clutch(loop, current_a, until):
    counter = 0
    while not until():
        loop.push([tcu_frame(CLUTCH_CMD, counter, SolenoidCurrent1=current_a)])
        counter = (counter + 1) % 16
        time.sleep(0.001)
    return counter


def test_commanded_solenoid_current_raises_clutch_pressure():
    with Loop(log_frames=0) as loop:
        base = loop.wait(lambda s: s.ticks >= 100, "100 ticks")
        assert base.outputs.clutch1_pressure_bar < 1.0
        seen = {"pressure": 0.0, "current": 0.0}

        def enough():
            s = loop.stats()
            seen["pressure"] = max(seen["pressure"], s.outputs.clutch1_pressure_bar)
            seen["current"] = max(seen["current"], s.outputs.solenoid_current1_a)
            return s.sim_time_s > base.sim_time_s + 0.3 and seen["pressure"] > 5.0

        feed_clutch(loop, 0.8, enough)
        s = loop.stats()
    assert seen["current"] == pytest.approx(0.8, abs=1e-3)
    assert seen["pressure"] > 5.0 > base.outputs.clutch1_pressure_bar
    assert s.msgs[CLUTCH].frames == s.rx_accepted == s.chan[0].rx_accepted > 0
    assert rejected(s) == 0
    # the pressure reaches the TCU in DCT_Clutch; SIM_Status says when the TCU was heard
    frames = loop.pop_tx()
    clutch = DB.get_message_by_name("DCT_Clutch")
    pressures = [clutch.decode(d)["ClutchPressure1"] for fid, _, d in frames if fid == clutch.frame_id]
    assert max(pressures) > 5.0
    status = DB.get_message_by_name("SIM_Status")
    states = [status.decode(d, decode_choices=False)["SimState"] for fid, _, d in frames
              if fid == status.frame_id]
    assert 1 in states and states[-1] == 2
    assert states == sorted(states)


def test_bad_frames_are_counted_and_change_nothing():
    good = tcu_frame(CLUTCH_CMD, 0, SolenoidCurrent1=0.5)
    bad_crc = tcu_frame(CLUTCH_CMD, 1, SolenoidCurrent1=1.5)
    bad_crc = (bad_crc[0], bad_crc[1], bytes([bad_crc[2][0] ^ 0x5A]) + bad_crc[2][1:])
    short = tcu_frame(CLUTCH_CMD, 1, SolenoidCurrent1=1.5)
    short = (short[0], 7, short[2][:7])
    remote = (CLUTCH_CMD.frame_id | CAN_RTR_FLAG, 8, tcu_frame(CLUTCH_CMD, 1, SolenoidCurrent1=1.5)[2])
    repeated = tcu_frame(CLUTCH_CMD, 0, SolenoidCurrent1=1.5)
    jumped = tcu_frame(CLUTCH_CMD, 3, SolenoidCurrent1=1.5)
    unknown = (0x555, 8, bytes(8))
    extended = (CLUTCH_CMD.frame_id | CAN_EFF_FLAG, 8, tcu_frame(CLUTCH_CMD, 1, SolenoidCurrent1=1.5)[2])
    batch = [good, bad_crc, short, remote, repeated, jumped, unknown, extended]
    with Loop(log_frames=1) as loop:
        loop.wait(lambda s: s.ticks >= 10, "10 ticks")
        assert loop.push(batch) == len(batch)     # one push: drained in one tick
        s = loop.wait(lambda s: s.rx_frames == len(batch), "the batch")
        assert s.rx_accepted == 1 and s.rx_bad_crc == 1 and s.rx_bad_length == 2
        assert s.rx_bad_counter == 2 and s.rx_unknown_id == 2
        # per message and per channel: the rejections of TCU_ClutchCmd by reason,
        # the unknown ids on the channel only
        m = s.msgs[CLUTCH]
        assert (m.frames, m.bad_crc, m.bad_length, m.bad_counter) == (1, 1, 2, 2)
        c = s.chan[0]
        assert (c.rx_frames, c.rx_accepted, c.rx_unknown_id, c.rx_bad_crc, c.rx_bad_length,
                c.rx_bad_counter) == (8, 1, 2, 1, 2, 2)
        assert all(s.msgs[g].frames == s.msgs[g].bad_crc == s.msgs[g].bad_length
                   == s.msgs[g].bad_counter == 0 for g in (SHIFT, ENGINE))
        # only the good frame was decoded: 0.5 A (or the safe 0 A if the
        # message timed out since), never the rejected frames' 1.5 A
        if s.msgs[CLUTCH].timed_out:
            assert command(s, "solenoid_current1_a") == 0.0
        else:
            assert command(s, "solenoid_current1_a") == pytest.approx(0.5, abs=1e-4)
        assert loop.c.rx_state[CLUTCH].last_counter in (0, -1)
        ticks = s.ticks
        loop.wait(lambda s: s.ticks > ticks + 10, "ticks after the bad frames")
    rx_log = [e for e in loop.pop_log() if e[1] == lib.RT_DIR_RX]
    assert [(e[2], e[3]) for e in rx_log] == [(f[0], f[1]) for f in batch]


def test_burst_of_frames_is_counted_while_the_loop_goes_on():
    junk = (0x7FF, 8, bytes(8))
    n_total = 70000
    loop = Loop(log_frames=1)
    # before the start: the ring takes RT_RING_SIZE frames, refuses (and counts) the rest
    assert loop.push([junk] * (lib.RT_RING_SIZE + 100)) == lib.RT_RING_SIZE
    pushed = lib.RT_RING_SIZE
    with loop:
        chunk = ffi.new("rt_frame[]", 4096)
        for i in range(4096):
            chunk[i].id, chunk[i].len = junk[0], junk[1]
        end = time.monotonic() + WAIT_S
        while pushed < n_total:
            pushed += lib.rt_ring_push_many(ring_addr(loop, "rx"), chunk, min(4096, n_total - pushed))
            assert time.monotonic() < end, "the loop stopped draining"
            time.sleep(0.001)
        s = loop.wait(lambda s: s.rx_frames >= n_total, "all frames")
        ticks = s.ticks
        loop.wait(lambda s: s.ticks > ticks + 10, "ticks after the burst")
    s = loop.stats()
    dropped_by_ring = loop.c.rx[0].dropped
    assert s.state == lib.RT_STATE_STOPPED
    assert s.rx_frames == s.rx_unknown_id == n_total
    assert s.chan[0].rx_frames == s.chan[0].rx_unknown_id == n_total
    assert dropped_by_ring >= 100 and s.rx_overflow == s.chan[0].rx_overflow == dropped_by_ring
    # the log (never read here) kept its first RT_LOG_SIZE entries and counted the rest
    assert loop.c.log.head - loop.c.log.tail == lib.RT_LOG_SIZE
    assert loop.c.log.dropped == s.rx_frames + s.tx_frames - lib.RT_LOG_SIZE


def test_timeout_falls_back_to_safe_values_and_recovers():
    with Loop() as loop:
        loop.wait(lambda s: s.ticks >= 10, "10 ticks")
        loop.push([tcu_frame(CLUTCH_CMD, 5, SolenoidCurrent1=0.8),
                   tcu_frame(ENGINE_CMD, 0, EngineTorqueRequest=40.0, TorqueRequestActive=1)])
        s = loop.wait(lambda s: s.rx_accepted == 2, "the first frames")
        assert s.msgs[CLUTCH].timeouts == 1 or (
            command(s, "solenoid_current1_a") == pytest.approx(0.8, abs=1e-4)
            and s.msgs[CLUTCH].timed_out == 0)
        # the TCU falls silent: 10 cycles later each message is timed out
        s = loop.wait(lambda s: s.msgs[CLUTCH].timed_out
                      and s.msgs[ENGINE].timed_out, "the timeouts")
        assert s.msgs[CLUTCH].timeouts == 1
        assert s.msgs[ENGINE].timeouts == 1
        assert s.msgs[SHIFT].timeouts == 0     # never heard: timed out from the start
        assert s.msgs[SHIFT].timed_out == 1
        assert command(s, "solenoid_current1_a") == 0.0 and s.outputs.solenoid_current1_a == 0.0
        assert command(s, "torque_request_active") == 0.0 and command(s, "engine_torque_request_nm") == 0.0
        assert loop.c.plant.inputs.solenoid_current1_a == 0.0
        # it comes back: the first frame after a timeout is accepted whatever its counter
        loop.push([tcu_frame(CLUTCH_CMD, 12, SolenoidCurrent1=0.6)])
        s = loop.wait(lambda s: s.rx_accepted == 3, "the recovery frame")
        assert s.rx_bad_counter == 0
        assert (s.msgs[CLUTCH].timed_out == 0
                and command(s, "solenoid_current1_a") == pytest.approx(0.6, abs=1e-4)
                ) or s.msgs[CLUTCH].timeouts == 2
        loop.wait(lambda s: s.msgs[CLUTCH].timeouts == 2, "the second timeout")


_HOG = """
import os, sys, time
os.sched_setaffinity(0, {int(sys.argv[1])})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    pass
"""


@pytest.mark.skipif(os.geteuid() != 0 or len(os.sched_getaffinity(0)) < 2,
                    reason="holds the loop's CPU with a SCHED_FIFO process: root and 2 CPUs")
def test_a_loop_held_from_its_cpu_does_not_time_out_a_tcu_that_kept_sending():
    """The loop's thread held 80 ms, three times (a real-time process on its CPU, as a
    host holds a vCPU) while the TCU goes on sending every cycle: the late tick drains what
    came meanwhile, and its receive clock is the time of the drain, so the ticks it
    skips do not make those frames look 80 ms old: no timeout."""
    cpus = sorted(os.sched_getaffinity(0))
    loop_cpu, own_cpu = cpus[0], cpus[1]
    plan = {CLUTCH_CMD: (1, {"SolenoidCurrent1": 0.5}),             # every 2 ms tick
            ENGINE_CMD: (5, {"EngineTorqueRequest": 20.0, "TorqueRequestActive": 1}),
            TCU_MESSAGES["TCU_ShiftCmd"]: (5, {})}
    counters = dict.fromkeys(plan, 0)
    saved = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {own_cpu})          # this thread sends, beside the loop's CPU
    loop = Loop()
    loop.c.cfg.cpu = loop_cpu
    try:
        with loop:
            k, t_next = 0, time.monotonic()

            def send_until(t_end):
                nonlocal k, t_next
                while time.monotonic() < t_end:
                    frames = []
                    for msg, (every, sig) in plan.items():
                        if k % every == 0:
                            frames.append(tcu_frame(msg, counters[msg] % 16, **sig))
                            counters[msg] += 1
                    assert loop.push(frames) == len(frames)
                    k += 1
                    t_next += 0.002
                    time.sleep(max(0.0, t_next - time.monotonic()))

            send_until(time.monotonic() + 0.3)
            before = loop.stats()
            assert [before.msgs[g].timed_out for g in (CLUTCH, ENGINE, SHIFT)] == [0, 0, 0]
            for _ in range(3):
                hog = subprocess.Popen([sys.executable, "-c", _HOG, str(loop_cpu), "0.08"])
                send_until(time.monotonic() + 0.4)          # the hold is in here
                assert hog.wait(WAIT_S) == 0
            after = loop.stats()
    finally:
        os.sched_setaffinity(0, saved)
    assert after.skipped_ticks - before.skipped_ticks >= 300, "the loop was not held"
    assert after.rx_bad_counter == 0 and after.rx_accepted > before.rx_accepted
    assert [after.msgs[g].timeouts - before.msgs[g].timeouts for g in (CLUTCH, ENGINE, SHIFT)] == [0, 0, 0]


# ----------------------------------------------------------------- overruns
def heavy_plant(params):
    # about 1.5 ms of arithmetic per step: every 0.1 ms tick overruns
    params.solver.substeps = 1000
    params.hydraulics.substeps = 8


def test_overrun_count_and_skip_ahead():
    period = 0.0001
    loop = Loop(period_s=period, duration_s=0.2, tweak=heavy_plant)
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.ticks > 0
    assert s.overruns == s.ticks                     # every tick ended after the next deadline
    # each overrun skips at least one deadline, except the last one if the run ends there
    assert s.skipped_ticks >= s.ticks - 1
    assert s.ticks + s.skipped_ticks == round(0.2 / period)    # every deadline of the run
    # skipped deadlines are not simulated: one plant step per executed tick
    assert s.sim_time_s == pytest.approx(s.ticks * period, abs=1e-9)
    assert s.turnaround_max_us > period * 1e6
    assert hist(s, "turnaround_hist").sum() == s.ticks


def test_overrun_stop_policy():
    loop = Loop(period_s=0.0001, duration_s=1.0, overrun_stop=1, tweak=heavy_plant)
    loop.start()
    assert loop.join() == lib.RT_STATE_OVERRUN_STOP
    s = loop.stats()
    assert s.state == lib.RT_STATE_OVERRUN_STOP
    assert s.ticks == 1 and s.overruns == 1 and s.skipped_ticks == 0
    status = DB.get_message_by_name("SIM_Status")
    last = [d for fid, _, d in loop.pop_tx() if fid == status.frame_id][-1]
    assert status.decode(last, decode_choices=False)["SimState"] == 3      # fault


@pytest.mark.parametrize("overrun_stop", [0, 1])
def test_overrun_policy_at_50_us(overrun_stop):
    # whether this machine meets 50 us or not, the figures stay consistent
    period = 50e-6
    loop = Loop(period_s=period, duration_s=0.2, overrun_stop=overrun_stop)
    loop.start()
    state = loop.join()
    s = loop.stats()
    turnaround = hist(s, "turnaround_hist")
    assert turnaround.sum() == s.ticks == hist(s, "exec_hist").sum() == hist(s, "latency_hist").sum()
    # an overrun is a tick whose turnaround exceeded the period (1 us bins)
    assert turnaround[51:].sum() <= s.overruns <= turnaround[50:].sum()
    assert s.sim_time_s == pytest.approx(s.ticks * period, abs=1e-9)
    if overrun_stop:
        assert (state, s.overruns) in ((lib.RT_STATE_OVERRUN_STOP, 1), (lib.RT_STATE_STOPPED, 0))
        assert s.skipped_ticks == 0
        assert state == lib.RT_STATE_OVERRUN_STOP or s.ticks == round(0.2 / period)
    else:
        assert state == lib.RT_STATE_STOPPED
        assert s.skipped_ticks >= s.overruns - 1
        assert s.ticks + s.skipped_ticks == round(0.2 / period)


# ------------------------------------------------------------ stop, stats
def test_request_stop_ends_the_loop():
    loop = Loop()                                   # no duration: runs until asked
    loop.start()
    loop.wait(lambda s: s.ticks >= 20, "20 ticks")
    assert loop.stop() == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.state == lib.RT_STATE_STOPPED and s.error == 0
    status = DB.get_message_by_name("SIM_Status")
    frames = loop.pop_tx()
    assert frames[-1][0] == status.frame_id
    assert status.decode(frames[-1][2], decode_choices=False)["SimState"] == 2

    early = Loop()
    lib.rt_loop_request_stop(early.c)               # before the start: no tick at all
    early.start()
    assert early.join() == lib.RT_STATE_STOPPED and early.stats().ticks == 0


def test_stats_read_gives_consistent_copies_while_running():
    with Loop() as loop:
        loop.wait(lambda s: s.ticks > 0, "the first tick")
        stop = threading.Event()

        def tcu():
            counter = 0
            while not stop.is_set():
                loop.push([tcu_frame(CLUTCH_CMD, counter, SolenoidCurrent1=0.3), (0x7FF, 8, bytes(8))])
                counter = (counter + 1) % 16
                time.sleep(0.0005)

        feeder = threading.Thread(target=tcu, daemon=True)
        feeder.start()
        try:
            last_seq = last_ticks = -1
            reads = 0
            s = loop.stats()
            end = time.monotonic() + WAIT_S
            while reads < 300 or s.rx_accepted < 10 or s.rx_unknown_id < 10:
                assert time.monotonic() < end, "the loop took no frames"
                reads += 1
                s = loop.stats()
                assert s.seq % 2 == 0 and s.seq >= last_seq and s.ticks >= last_ticks
                assert s.state == lib.RT_STATE_RUNNING
                assert hist(s, "turnaround_hist").sum() == s.ticks == hist(s, "latency_hist").sum()
                assert s.rx_frames == s.rx_accepted + rejected(s)
                assert s.rx_accepted == sum(s.msgs[g].frames for g in RX_MSGS)
                assert s.rx_unknown_id == s.chan[0].rx_unknown_id
                assert s.tx_frames == sum(s.msgs[g].frames for g in TX_MSGS)
                last_seq, last_ticks = s.seq, s.ticks
        finally:
            stop.set()
            feeder.join()


# ------------------------------------------ the socket path (recvmmsg, sendmmsg)
def can_bytes(fid, length, data):
    """A struct can_frame datagram (CAN_MTU bytes) as a CAN_RAW socket carries it."""
    return CAN_FRAME.pack(fid, length, data[:8].ljust(8, b"\0"))


@pytest.mark.slow
def test_socket_transport_exchanges_frames_and_never_blocks():
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    with ours, peer:
        loop = Loop(transport=lib.RT_TRANSPORT_SOCKETCAN, fd=ours.fileno())
        assert loop.prepare_rc == 0
        with loop:
            peer.settimeout(WAIT_S)
            received = []
            while len(received) < 200:                    # the plant's frames arrive
                raw = peer.recv(256)
                assert len(raw) == CAN_FRAME.size            # classic frames: CAN_MTU, 16 bytes
                received.append(CAN_FRAME.unpack(raw))
            peer.send(can_bytes(*tcu_frame(CLUTCH_CMD, 0, SolenoidCurrent1=0.7)))
            peer.send(can_bytes(*tcu_frame(ENGINE_CMD, 0, EngineTorqueRequest=10.0)))
            long = tcu_frame(CLUTCH_CMD, 1, SolenoidCurrent1=1.5)
            peer.send(can_bytes(*long) + bytes(56))              # a 72-byte (CAN FD sized) frame
            peer.send(can_bytes(long[0], 9, long[2]))            # length code above 8
            peer.send(can_bytes(long[0] | CAN_EFF_FLAG, 8, long[2]))
            s = loop.wait(lambda s: s.rx_frames == 5, "the TCU frames")
            assert s.rx_accepted == 2 and s.rx_bad_length == 2 and s.rx_unknown_id == 1
            assert s.msgs[CLUTCH].frames == 1 and s.msgs[ENGINE].frames == 1
            assert s.msgs[CLUTCH].bad_length == 2 and s.chan[0].rx_unknown_id == 1
            # the peer stops reading: its queue fills, sends are refused and
            # counted, the loop does not block
            ticks = s.ticks
            s = loop.wait(lambda s: s.tx_dropped > 0 and s.ticks > ticks + 100, "refused sends")
            assert s.state == lib.RT_STATE_RUNNING
        s = loop.stats()
        assert s.state == lib.RT_STATE_STOPPED and s.error == 0
        peer.setblocking(False)
        try:
            while True:
                raw = peer.recv(256)
                assert len(raw) == CAN_FRAME.size
                received.append(CAN_FRAME.unpack(raw))
        except BlockingIOError:
            pass
    assert len(received) == s.tx_frames == s.chan[0].tx_frames
    assert s.tx_dropped == s.chan[0].tx_dropped == sum(s.msgs[g].dropped for g in TX_MSGS) > 0
    for m in PLANT_MESSAGES:
        assert s.msgs[MSG[m.name]].frames == sum(1 for f in received if f[0] == m.frame_id), m.name
    ids = {m.frame_id: m for m in PLANT_MESSAGES}
    last = {}
    for fid, length, data in received:
        assert fid in ids and length == ids[fid].length and e2e_ok(fid, data)
        counter = data[1] & 0x0F
        if fid in last:
            assert counter != last[fid]                   # each frame a new counter
        last[fid] = counter


def test_transport_error_stops_the_loop_with_its_errno():
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    with ours:
        loop = Loop(transport=lib.RT_TRANSPORT_SOCKETCAN, fd=ours.fileno())
        loop.start()
        loop.wait(lambda s: s.ticks >= 10, "10 ticks")
        peer.close()                                  # the interface goes away
        assert loop.join() == lib.RT_STATE_ERROR
    s = loop.stats()
    # the errno of the failed call (ECONNREFUSED for this socket pair)
    assert s.state == lib.RT_STATE_ERROR and s.error in errno.errorcode


# ------------------------------------------------------------ plant, thread
def test_plant_error_stops_the_loop():
    loop = Loop()
    loop.start()
    loop.wait(lambda s: s.ticks >= 10, "10 ticks")
    loop.c.plant.inputs.accel_pedal_pct = float("nan")   # Python writes a driver input
    assert loop.join() == lib.RT_STATE_ERROR
    s = loop.stats()
    assert s.state == lib.RT_STATE_ERROR and s.error == -lib.DCT_ERR_INPUT
    status = DB.get_message_by_name("SIM_Status")
    frames = loop.pop_tx()
    assert frames[-1][0] == status.frame_id
    assert status.decode(frames[-1][2], decode_choices=False)["SimState"] == 3


def test_scheduling_is_recorded_and_restored():
    cpu = sorted(os.sched_getaffinity(0))[-1]
    loop = Loop(duration_s=0.05)
    loop.c.cfg.priority = 10
    loop.c.cfg.cpu = cpu
    seen = {}

    def run():
        seen["before"] = (os.sched_getscheduler(0), os.sched_getaffinity(0))
        seen["state"] = lib.rt_loop_run(loop.c)
        seen["after"] = (os.sched_getscheduler(0), os.sched_getaffinity(0))

    t = threading.Thread(target=run)
    t.start()
    t.join(WAIT_S)
    assert seen["state"] == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.affinity_ok == 1                       # narrowing one's own affinity is always allowed
    assert s.rt_policy_ok in (0, 1)                 # SCHED_FIFO needs CAP_SYS_NICE: recorded, not fatal
    assert s.memory_locked == 0                     # not asked
    assert seen["after"] == seen["before"]


# ------------------------------------------------- time scale, driver, recorder
def test_a_slowed_down_run_steps_the_plant_by_step_s_and_stretches_the_bus_cycles():
    period, step = 0.005, 0.0005                  # one tenth of real time
    loop = Loop(period_s=period, step_s=step, duration_s=0.4, record_every=1)
    assert loop.prepare_rc == 0
    assert loop.c.plant.params.solver.step_s == step
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.ticks + s.skipped_ticks == round(0.4 / period)            # deadlines: wall clock
    assert s.sim_time_s == pytest.approx(s.ticks * step, abs=1e-9)     # plant: step_s per tick
    frames = loop.pop_tx()
    shaft = [f for f in frames if f[0] == DB.get_message_by_name("DCT_ShaftSpeeds").frame_id]
    # 2 ms of simulated time = every 4th tick, whatever the wall-clock period
    assert abs(len(shaft) - s.ticks / 4) <= 1
    rec = loop.pop_rec()
    assert [r[0] for r in rec] == list(range(s.ticks))
    assert rec[-1][1] == pytest.approx(s.ticks * step, abs=1e-9)


def test_step_longer_than_the_period_or_out_of_range_is_refused():
    assert Loop(period_s=0.0005, step_s=0.001).prepare_rc == -errno.EINVAL   # faster than real time
    assert Loop(period_s=0.05, step_s=0.02).prepare_rc == -errno.EINVAL      # step above 10 ms
    assert Loop(period_s=0.2, step_s=0.0005).prepare_rc == -errno.EINVAL     # period above 100 ms
    assert Loop(record_every=-1).prepare_rc == -errno.EINVAL


@pytest.mark.parametrize("rows", [
    [(0.0, 0.0, 10.0), (0.0, 10.0, 0.0)],          # times not increasing
    [(0.0, 101.0, 0.0)],                            # pedal above 100 %
    [(0.0, 0.0, -1.0)],                             # below 0
    [(float("nan"), 0.0, 0.0)],
])
def test_a_bad_driver_table_is_refused(rows):
    assert Loop(driver={"rows": rows}).prepare_rc == -errno.EINVAL


@pytest.mark.parametrize("extra", [{"selector": [4.0]}, {"selector": [1.5]}, {"selector": [-1.0]},
                                   {"grade": 40.5}, {"grade": float("nan")}])
def test_a_bad_selector_code_or_grade_is_refused(extra):
    assert Loop(driver={"rows": [(0.0, 0.0, 10.0)], **extra}).prepare_rc == -errno.EINVAL


@pytest.mark.parametrize("end_s, selector", [(0.04, 3.0), (0.08, 1.0), (0.15, 0.0)])
def test_the_driver_plays_the_selector_column_and_sets_the_grade(end_s, selector):
    rows = [(0.0, 0.0, 30.0), (0.05, 0.0, 30.0), (0.1, 0.0, 30.0)]
    loop = Loop(driver={"rows": rows, "selector": [3.0, 1.0, 0.0], "grade": 12.5, "end_s": end_s,
                        "start_on_tcu": 1}, duration_s=5.0)
    # before the maneuver starts: the first row's selector and the grade already
    assert loop.c.plant.inputs.selector_lever == 3.0 and loop.c.plant.inputs.road_grade_pct == 12.5
    loop.c.driver.start_on_tcu = 0
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.maneuver_state == lib.RT_MANEUVER_DONE
    assert s.outputs.selector_lever == selector and s.outputs.road_grade_pct == 12.5


def test_a_table_without_selector_or_grade_leaves_them():
    loop = Loop(driver={"rows": [(0.0, 0.0, 30.0)], "end_s": 0.01})
    assert loop.c.plant.inputs.selector_lever == 3.0 and loop.c.plant.inputs.road_grade_pct == 0.0


def test_too_many_driver_rows_are_refused():
    loop = Loop()
    loop.c.driver.rows = lib.RT_DRIVER_ROWS + 1
    assert lib.rt_loop_prepare(loop.c) == -errno.EINVAL


def test_the_driver_plays_its_table_over_maneuver_time_and_ends_the_run():
    rows = [(0.0, 0.0, 30.0), (0.05, 40.0, 0.0), (0.1, 80.0, 0.0)]
    loop = Loop(driver={"rows": rows, "end_s": 0.15}, record_every=1, duration_s=5.0)
    assert loop.c.stats.maneuver_state == lib.RT_MANEUVER_WAITING
    loop.start()
    assert loop.join() == lib.RT_STATE_STOPPED           # stopped by end_s, long before 5 s
    s = loop.stats()
    assert s.maneuver_state == lib.RT_MANEUVER_DONE
    assert s.maneuver_time_s == pytest.approx(0.15, abs=1e-9)
    assert s.sim_time_s == pytest.approx(0.15, abs=1e-9)   # started at the first tick
    rec = loop.pop_rec()
    assert len(rec) == s.ticks == 300
    for _tick, t, mt, accel, brake, _i in rec:
        assert mt == pytest.approx(t, abs=1e-12)
        before = mt - 0.0005                              # the pedals of the tick's start
        want = [r for r in rows if r[0] <= before + 1e-12][-1]
        assert (accel, brake) == (want[1], want[2]), (mt, accel, brake)


def test_linear_driver_interpolates_between_rows():
    rows = [(0.0, 0.0, 0.0), (0.1, 100.0, 0.0)]
    loop = Loop(driver={"rows": rows, "linear": 1, "end_s": 0.1}, record_every=1)
    loop.start()
    loop.join()
    for _tick, _t, mt, accel, _b, _i in loop.pop_rec():
        assert accel == pytest.approx(1000.0 * (mt - 0.0005), abs=1e-9)


def test_the_maneuver_waits_for_the_tcu_then_starts():
    clutch = DB.get_message_by_name("TCU_ClutchCmd")
    rows = [(0.0, 0.0, 30.0), (0.02, 60.0, 0.0)]
    with Loop(driver={"rows": rows, "start_on_tcu": 1, "end_s": 0.05}, record_every=1,
              duration_s=10.0) as loop:
        time.sleep(0.1)
        s = loop.stats()
        assert s.maneuver_state == lib.RT_MANEUVER_WAITING and s.maneuver_time_s < 0
        assert s.outputs.brake_pedal_pct == 30.0 and s.outputs.accel_pedal_pct == 0.0
        t_heard = s.sim_time_s
        assert loop.push([tcu_frame(clutch, 0, SolenoidCurrent1=0.2)]) == 1
        assert loop.join() == lib.RT_STATE_STOPPED
    s = loop.stats()
    assert s.maneuver_state == lib.RT_MANEUVER_DONE
    assert s.sim_time_s > t_heard + 0.05 - 1e-9
    rec = loop.pop_rec()
    waiting = [r for r in rec if r[2] < 0]
    running = [r for r in rec if r[2] >= 0]
    assert waiting and all(r[3] == 0.0 and r[4] == 30.0 for r in waiting)
    assert running[0][5] == pytest.approx(0.2, abs=0.01)   # started with the TCU's first frame
    assert running[-1][2] == pytest.approx(0.05, abs=1e-9)
    assert running[-1][3] == 60.0


def test_a_full_recorder_ring_counts_the_samples_it_drops():
    loop = Loop(record_every=1, duration_s=(lib.RT_REC_SIZE + 500) * 0.0001, period_s=0.0001)
    loop.start()
    loop.join()
    s = loop.stats()
    got = len(loop.pop_rec())
    assert got == min(s.ticks, lib.RT_REC_SIZE)
    assert loop.c.rec.dropped == s.ticks - got
