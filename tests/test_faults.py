"""Failure simulation inside the tick (rt_loop/csrc/rt_faults.c, rt_loop/faults/).

Each fault kind is shown by its effect on the bus or the plant while it is
active, and by its absence once it ended or was cleared; no fault makes the
plant state non-finite. The loop runs in a thread on the ring transport
(tests/test_rt_loop_c.py's Loop) and faults are injected through the same
FaultManager the server uses. Waits poll the statistics and never judge how
long something took.
"""

import math
import time

import numpy as np
import pytest
from test_rt_loop_c import CHANNELS, CMD, DB, MSG, TCU_MESSAGES, Loop, e2e_ok, tcu_frame

from rt_loop._rt_loop import ffi, lib
from rt_loop.faults import (
    FaultError,
    FaultManager,
    Names,
    invalid_value,
    load_faults,
    parse_fault,
)

CLUTCH_MSG = DB.get_message_by_name("DCT_Clutch")
SHAFT_MSG = DB.get_message_by_name("DCT_ShaftSpeeds")
SHIFT_MSG = DB.get_message_by_name("DCT_Shift")
PERIOD_S = 0.0005


def manager(loop):
    return FaultManager(ffi, lib, loop.c, CHANNELS, read_stats=loop.stats)


def run_with(fault, seconds=0.3, before=0.05, **loop_kw):
    """Frames of a run: the fault injected after `before` s of plant time for
    `seconds`, then `seconds` more without it. Returns (frames with the tick's
    plant time, start_s, end_s, status)."""
    with Loop(log_frames=1, **loop_kw) as loop:
        fm = manager(loop)
        s0 = loop.wait(lambda s: s.sim_time_s >= before, "the first ticks")
        fid = fm.inject({**fault, "start_s": s0.sim_time_s + 0.01, "duration_s": seconds})
        loop.wait(lambda s: s.sim_time_s >= s0.sim_time_s + 2 * seconds + 0.05, "the fault's end")
        status = fm.status(loop.stats())[0]
        events = fm.events()
    log = loop.pop_log()
    status["run_s"] = loop.stats().sim_time_s     # plant time of the whole run
    assert [e["event"] for e in events if e["id"] == fid] == ["start", "end"]
    start, end = status["started_s"], status["ended_s"]
    assert end - start == pytest.approx(seconds, abs=PERIOD_S + 1e-9)
    frames = [(e[0], e[2], e[3], e[4]) for e in log if e[1] == lib.RT_DIR_TX]
    return frames, start, end, status


def split(frames, msg, start, end):
    """A message's frames (len, data) before/while/after the fault, by plant
    time. The log stamps each frame with its tick's deadline, which runs ahead
    of plant time by the deadlines a loaded host made the loop skip; the send
    schedule counts executed ticks instead, so the k-th frame of a message
    sent every cycle went out at a plant time within (k, k + 1] cycles. The
    frames within 20 ms of the fault's edges are left out."""
    cycle = msg.cycle_time / 1000.0
    own = [(k * cycle, n, d) for k, (_, fid, n, d) in
           enumerate(f for f in frames if f[1] == msg.frame_id)]
    margin = 0.02
    during = [(n, d) for t, n, d in own if start + margin <= t <= end - margin - cycle]
    after = [(n, d) for t, n, d in own if t >= end + margin]
    before = [(n, d) for t, n, d in own if t + cycle <= start - margin]
    return before, during, after


# ------------------------------------------------------------------ CAN faults
def test_omit_keeps_the_message_off_the_bus_and_counts_each_frame():
    frames, start, end, status = run_with({"kind": "can.omit", "message": "DCT_Clutch"})
    sent = sum(1 for f in frames if f[1] == CLUTCH_MSG.frame_id)
    assert status["hits"] == pytest.approx((end - start) / 0.002, abs=1)
    # every frame of the run's cycles either sent or omitted (counted)
    assert sent + status["hits"] == pytest.approx(status["run_s"] / 0.002, abs=2)
    # the other messages go on, every cycle
    shaft = sum(1 for f in frames if f[1] == SHAFT_MSG.frame_id)
    assert shaft == pytest.approx(status["run_s"] / 0.002, abs=2)


def test_frozen_counter_repeats_with_a_valid_checksum_then_counts_on():
    frames, start, end, status = run_with({"kind": "can.freeze_counter", "message": "DCT_Clutch"})
    # by the frames' order, not the log's deadline stamps (a loaded host's skipped
    # deadlines move those away from plant time): one run of a repeated counter,
    # counting on by one before it
    own = [d for _, fid, _, d in frames if fid == CLUTCH_MSG.frame_id]
    seq = [d[1] & 0x0F for d in own]
    runs, k = [], 0
    while k < len(seq):
        j = k
        while j + 1 < len(seq) and seq[j + 1] == seq[k]:
            j += 1
        runs.append((k, j))
        k = j + 1
    long = [(a, b) for a, b in runs if b > a]
    assert len(long) == 1, long
    a, b = long[0]
    assert b - a + 1 == status["hits"] + 1   # the frame before the fault, then each frozen one
    assert status["hits"] > 50
    assert all(e2e_ok(CLUTCH_MSG.frame_id, d) for d in own)
    assert all((y - x) % 16 == 1 for x, y in zip(seq[:a + 1], seq[1:a + 1]))
    # the sender's count went on meanwhile: one jump back to it, then by one again
    assert seq[b + 1] == (seq[b] + status["hits"] + 1) % 16
    assert all((y - x) % 16 == 1 for x, y in zip(seq[b + 1:], seq[b + 2:]))


def test_bad_checksum_while_active_only():
    frames, start, end, status = run_with({"kind": "can.bad_crc", "message": "DCT_ShaftSpeeds"})
    ok = [e2e_ok(SHAFT_MSG.frame_id, d) for _, fid, _, d in frames if fid == SHAFT_MSG.frame_id]
    bad = [k for k, good in enumerate(ok) if not good]
    # one block of bad checksums, one per frame of the fault, valid before and after
    assert len(bad) == status["hits"] > 100 and bad == list(range(bad[0], bad[0] + len(bad)))
    assert 0 < bad[0] and bad[-1] < len(ok) - 100


def frame_times(frames, msg):
    return [t for t, fid, _, _ in frames if fid == msg.frame_id]


def expected_frames(status, cycle_s, faulted_cycle_s):
    """Frames of a message over the run: its cycle outside the fault, the
    faulted cycle inside (plant time: the loop's schedule counts executed
    ticks, so a loaded host's skipped deadlines change nothing)."""
    active = status["ended_s"] - status["started_s"]
    return (status["run_s"] - active) / cycle_s + active / faulted_cycle_s


def test_late_stretches_the_cycle_by_the_delay():
    frames, start, end, status = run_with({"kind": "can.late", "message": "DCT_Shift",
                                           "delay_ms": 15})
    # DCT_Shift: 10 ms cycle; late by 15 ms: 25 ms apart while active
    n = len(frame_times(frames, SHIFT_MSG))
    assert n == pytest.approx(expected_frames(status, 0.010, 0.025), abs=3)
    assert n < expected_frames(status, 0.010, 0.010) - 10


def test_too_often_divides_the_cycle():
    frames, start, end, status = run_with({"kind": "can.too_often", "message": "DCT_Shift",
                                           "factor": 5})
    n = len(frame_times(frames, SHIFT_MSG))
    assert n == pytest.approx(expected_frames(status, 0.010, 0.002), abs=3)


def test_wrong_length_pads_or_cuts():
    frames, start, end, _ = run_with({"kind": "can.length", "message": "DCT_Clutch", "length": 5})
    before, during, after = split(frames, CLUTCH_MSG, start, end)
    assert during and {n for n, _ in during} == {5}
    assert {n for n, _ in before + after} == {8}


def test_bus_off_stops_every_plant_frame():
    frames, start, end, status = run_with({"kind": "can.bus_off"})
    # by counts and one silence, not the log's deadline stamps against plant
    # time (a loaded host's skipped deadlines move those apart): each message
    # sent at its cycle outside the fault and never inside, frames after it
    # again, and the bus silent once for the fault's whole length (deadlines
    # advance at least as fast as plant time)
    for msg in (SHAFT_MSG, CLUTCH_MSG, SHIFT_MSG):
        cycle_s = msg.cycle_time / 1000.0
        assert len(frame_times(frames, msg)) == pytest.approx(
            expected_frames(status, cycle_s, math.inf), abs=3), msg.name
    times = np.array(sorted(t for t, _, _, _ in frames))
    gaps = np.diff(times)
    assert gaps.max() >= (end - start) - 0.002
    assert times[-1] > times[int(np.argmax(gaps >= (end - start) - 0.002))]
    assert status["hits"] > 0


# ------------------------------------------------------------------ signal faults (sent)
def line_pressures(rows):
    return np.array([CLUTCH_MSG.decode(d)["LinePressure"] for _, d in rows])


@pytest.mark.parametrize("kind, params, check", [
    ("signal.value", {"value": 3.25}, lambda base, got: np.allclose(got, 3.25, atol=1e-3)),
    ("signal.offset", {"offset": 2.0}, lambda base, got: abs(got.mean() - base.mean() - 2.0) < 0.05),
    ("signal.gain", {"gain": 0.5}, lambda base, got: abs(got.mean() - 0.5 * base.mean()) < 0.05),
    ("signal.hold", {}, lambda base, got: np.ptp(got) < 1e-9),
])
def test_sent_signal_faults_change_the_value_on_the_bus(kind, params, check):
    frames, start, end, status = run_with({"kind": kind, "signal": "DCT_Clutch.LinePressure",
                                           **params}, before=0.3)
    before, during, after = split(frames, CLUTCH_MSG, start, end)
    base = line_pressures(before[-20:])
    assert check(base, line_pressures(during)), (base[-3:], line_pressures(during)[:3])
    # the other signals of the frame are untouched and the frame stays valid
    assert all(e2e_ok(CLUTCH_MSG.frame_id, d) for _, d in during)
    assert status["hits"] >= len(during)
    # afterwards the true value again
    assert abs(line_pressures(after[-5:]).mean() - line_pressures(before[-5:]).mean()) < 0.5


@pytest.mark.slow
def test_noise_is_seeded_gaussian_and_reproducible():
    runs = []
    for _ in range(2):
        frames, start, end, _ = run_with({"kind": "signal.noise", "signal": "DCT_Clutch.LinePressure",
                                          "sigma": 0.5, "seed": 7}, before=0.3)
        _, during, _ = split(frames, CLUTCH_MSG, start, end)
        runs.append(line_pressures(during))
    truth = 20.0  # the supply holds 20 bar at 0 A once settled
    noise = runs[0] - np.median(runs[0])
    assert 0.4 < noise.std() < 0.6                      # sigma 0.5 over ~130 samples: +-20 %
    assert abs(np.median(runs[0]) - truth) < 1.0
    # the same seed, the same sequence (the plant is the same tick by tick)
    n = min(len(r) for r in runs)
    k = 20
    a, b = runs[0][:n], runs[1][:n]
    # the windows may hold a few frames more or less at their edges: the same
    # values, frame for frame, at one offset (chance cannot match 80 noisy values)
    def match(o):
        x, y = (a[k:n - k], b[k + o:n - k + o]) if o >= 0 else (a[k - o:n - k - o], b[k:n - k])
        m = min(len(x), len(y))
        return m >= 80 and np.allclose(x[:m], y[:m], atol=1e-3)
    assert any(match(o) for o in range(-k, k + 1))


def test_invalid_is_the_dbcs_invalid_value():
    frames, start, end, _ = run_with({"kind": "signal.invalid", "signal": "DCT_ShaftSpeeds.InputShaft2Speed"})
    _, during, _ = split(frames, SHAFT_MSG, start, end)
    sig = SHAFT_MSG.get_signal_by_name("InputShaft2Speed")
    expected = invalid_value(sig)
    got = {SHAFT_MSG.decode(d, decode_choices=False)["InputShaft2Speed"] for _, d in during}
    assert got == {expected}


# ------------------------------------------------------------------ signal faults (received)
def test_received_signal_fault_changes_the_command_value_then_lets_go():
    with Loop() as loop:
        fm = manager(loop)
        counter = 0

        def feed(until):
            nonlocal counter
            while not until():
                loop.push([tcu_frame(TCU_MESSAGES["TCU_ClutchCmd"], counter, SolenoidCurrent1=0.5)])
                counter = (counter + 1) % 16
                time.sleep(0.001)

        def cmd():
            return loop.stats().commands[CMD["solenoid_current1_a"]]

        feed(lambda: cmd() == pytest.approx(0.5, abs=1e-4))
        fid = fm.inject({"kind": "signal.value", "signal": "TCU_ClutchCmd.SolenoidCurrent1",
                         "value": 0.2})
        feed(lambda: cmd() == pytest.approx(0.2, abs=1e-4))
        feed(lambda: loop.stats().outputs.solenoid_current1_a == pytest.approx(0.2, abs=1e-4))
        fm.clear(fid)
        feed(lambda: cmd() == pytest.approx(0.5, abs=1e-4))
        assert [e["event"] for e in fm.events()] == ["start", "cleared"]


# ------------------------------------------------------------------ conditions and scheduling
def test_a_fault_waits_for_its_condition():
    with Loop() as loop:
        fm = manager(loop)
        fid = fm.inject({"kind": "can.omit", "message": "DCT_Clutch",
                         "when": "cmd.solenoid_current1_a > 0.3 and time_s > 0.1"})
        loop.wait(lambda s: s.sim_time_s > 0.3, "0.3 s")
        assert fm.status()[0]["state"] == "armed"
        counter = 0
        while fm.status()[0]["state"] != "active":
            loop.push([tcu_frame(TCU_MESSAGES["TCU_ClutchCmd"], counter, SolenoidCurrent1=0.5)])
            counter = (counter + 1) % 16
            time.sleep(0.001)
        st = fm.status()[0]
        assert st["started_s"] > 0.3 and st["activations"] == 1
        fm.clear(fid)


def test_a_watch_latches_the_plant_time_its_condition_first_held():
    with Loop() as loop:
        fm = manager(loop)
        wid = fm.watch("time_s >= 0.25")
        loop.wait(lambda s: s.sim_time_s > 0.4, "0.4 s")
        st = fm.status()[0]
    assert st["state"] == "active" and st["started_s"] == pytest.approx(0.25, abs=PERIOD_S + 1e-9)
    assert wid == 1


def test_a_bit_test_holds_when_any_bit_of_the_mask_is_set():
    """``&`` reads the signal as an integer: TCU_Status.ActiveFaults 0x0004 and
    0x0100 leave a watch on 0x1010 armed, 0x1000 latches it."""
    status = TCU_MESSAGES["TCU_Status"]
    with Loop() as loop:
        fm = manager(loop)
        fm.watch("TCU_Status.ActiveFaults & 0x1010")
        counter = 0
        for bits in (0x0004, 0x0100):
            for _ in range(20):
                loop.push([tcu_frame(status, counter, ActiveFaults=bits)])
                counter = (counter + 1) % 16
                time.sleep(0.001)
            assert fm.status()[0]["state"] == "armed", hex(bits)
        for _ in range(5000):
            if fm.status()[0]["state"] == "active":
                break
            loop.push([tcu_frame(status, counter, ActiveFaults=0x1000)])
            counter = (counter + 1) % 16
            time.sleep(0.001)
        assert fm.status()[0]["state"] == "active", "0x1000 has a bit of the mask"


def test_recorder_samples_carry_the_active_faults():
    with Loop(record_every=1) as loop:
        fm = manager(loop)
        fm.inject({"kind": "can.omit", "message": "DCT_Clutch", "start_s": 0.1, "duration_s": 0.1})
        loop.wait(lambda s: s.sim_time_s > 0.3, "0.3 s")
        buf = ffi.new("rt_sample[2048]")
        n = lib.rt_rec_pop_many(ffi.addressof(loop.c[0], "rec"), buf, 2048)
    rows = [(buf[i].time_s, int(buf[i].fault_mask)) for i in range(n)]
    on = [t for t, m in rows if m == 1]
    assert on and min(on) == pytest.approx(0.1 + PERIOD_S, abs=PERIOD_S + 1e-9)
    assert max(on) == pytest.approx(0.2, abs=PERIOD_S + 1e-9)
    assert all(m == 0 for t, m in rows if t < 0.1 or t > 0.2 + 2 * PERIOD_S)


# ------------------------------------------------------------------ physical faults
PHYSICAL = [
    ({"kind": "valve.spool_stuck", "clutch": 1}, "spool_stuck", 0, 1.0),
    ({"kind": "valve.solenoid_open", "clutch": 2}, "solenoid_open", 1, 1.0),
    ({"kind": "clutch.friction_fade", "clutch": 1, "loss": 0.4}, "friction_loss", 0, 0.4),
    ({"kind": "clutch.kiss_drift", "clutch": 2, "gap_mm": 0.3}, "pack_gap_offset_mm", 1, 0.3),
    ({"kind": "hydraulics.line_pressure_loss", "loss": 0.5}, "line_pressure_loss", None, 0.5),
    ({"kind": "fork.jammed", "sleeve": "5-R"}, "fork_jammed", 2, 1.0),
    ({"kind": "sync.blocker_failed", "sleeve": 4}, "blocker_failed", 3, 1.0),
    ({"kind": "engine.torque_limit", "max_nm": 80}, "engine_torque_max_nm", None, 80.0),
]


def plant_fault(loop, field, index):
    v = getattr(loop.c.plant.faults, field)
    return float(v if index is None else v[index])


@pytest.mark.parametrize("spec, field, index, value", PHYSICAL, ids=[p[0]["kind"] for p in PHYSICAL])
def test_physical_faults_reach_the_plant_and_leave_it_as_it_was(spec, field, index, value):
    with Loop() as loop:
        params_before = bytes(ffi.buffer(ffi.addressof(loop.c.plant, "effective")))
        fm = manager(loop)
        fid = fm.inject(spec)
        loop.wait(lambda s: fm.status(s)[0]["state"] == "active", "the fault to start")
        assert plant_fault(loop, field, index) == pytest.approx(value)
        fm.clear(fid)
        loop.wait(lambda s: int(s.fault_mask) == 0 and s.fault_changes == 2, "the fault to end")
        time.sleep(0.01)
        assert bytes(ffi.buffer(ffi.addressof(loop.c.plant, "faults"))) == bytes(ffi.sizeof("dct_faults"))
        assert bytes(ffi.buffer(ffi.addressof(loop.c.plant, "effective"))) == params_before


def test_engine_torque_limit_caps_the_engine_at_full_pedal():
    with Loop() as loop:
        fm = manager(loop)
        loop.c.plant.inputs.accel_pedal_pct = 100.0      # no TCU: clutches open, the engine revs
        fid = fm.inject({"kind": "engine.torque_limit", "max_nm": 40})
        loop.wait(lambda s: s.sim_time_s > 0.5, "0.5 s")
        peak = 0.0
        end = loop.stats().sim_time_s + 0.3
        while (s := loop.stats()).sim_time_s < end:
            peak = max(peak, s.outputs.engine_torque_nm)
            time.sleep(0.002)
        assert peak <= 40.0 + 1e-6
        fm.clear(fid)
        loop.wait(lambda s: s.outputs.engine_torque_nm > 60.0, "the torque back above the limit")
        loop.c.plant.inputs.accel_pedal_pct = 0.0


@pytest.mark.slow
def test_every_fault_at_once_keeps_the_plant_finite():
    specs = [p[0] for p in PHYSICAL] + [
        {"kind": "clutch.friction_fade", "clutch": 2, "loss": 1.0},
        {"kind": "hydraulics.line_pressure_loss", "loss": 1.0},
        {"kind": "engine.torque_limit", "max_nm": 0},
        {"kind": "signal.noise", "signal": "TCU_ClutchCmd.SolenoidCurrent1", "sigma": 1.0},
        {"kind": "can.bus_off"},
    ]
    with Loop() as loop:
        fm = manager(loop)
        loop.c.plant.inputs.accel_pedal_pct = 60.0
        for spec in specs:
            fm.inject(spec)
        counter = 0
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            loop.push([tcu_frame(TCU_MESSAGES["TCU_ClutchCmd"], counter, SolenoidCurrent1=0.7,
                                 SolenoidCurrent2=0.7)])
            counter = (counter + 1) % 16
            time.sleep(0.002)
        s = loop.stats()
        assert s.state == lib.RT_STATE_RUNNING
        assert int(s.fault_mask).bit_count() == len(specs)
        state = ffi.buffer(ffi.addressof(loop.c.plant, "state"))
        assert np.all(np.isfinite(np.frombuffer(bytes(state), dtype=np.float64)))
        fm.clear_all()
        loop.wait(lambda s: int(s.fault_mask) == 0, "every fault cleared")


# ------------------------------------------------------------------ bad input
NAMES = Names(ffi, lib, CHANNELS)


@pytest.mark.parametrize("spec, words", [
    ({"kind": "can.explode", "message": "DCT_Clutch"}, ["can.explode", "not known"]),
    ({"kind": "can.omit", "message": "DCT_Nope"}, ["DCT_Nope", "not in the served mapping"]),
    ({"kind": "can.omit", "message": "TCU_ClutchCmd"}, ["does not send", "TCU_ClutchCmd"]),
    ({"kind": "signal.hold", "signal": "DCT_Clutch.Nope"}, ["DCT_Clutch.Nope"]),
    ({"kind": "signal.value", "signal": "DCT_Clutch.LinePressure"}, ["needs value"]),
    ({"kind": "signal.hold", "signal": "DCT_Clutch.AliveCounter"},
     ["protection counter", "can.freeze_counter"]),
    ({"kind": "clutch.friction_fade", "clutch": 1, "loss": 1.5}, ["loss", "outside"]),
    ({"kind": "clutch.friction_fade", "clutch": 3, "loss": 0.5}, ["clutch = 1 or 2"]),
    ({"kind": "fork.jammed", "sleeve": "7-8"}, ["sleeve"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gear === 3"}, ["cannot read"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gearz == 3"}, ["gearz", "gear"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gear == 3 and a > 1 or b < 2"},
     ["mixes"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gear == three"}, ["number"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gear & 1.5"}, ["integer mask"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "when": "gear & 0"}, ["between 1"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "delay_ms": 3}, ["delay_ms", "not a parameter"]),
    ({"kind": "can.length", "message": "DCT_Clutch", "length": 12}, ["12 bytes"]),
    ({"kind": "can.omit", "message": "DCT_Clutch", "duration_s": -1}, ["duration_s"]),
    ({"kind": "signal.offset", "signal": "DCT_Clutch.LinePressure", "offset": "nan"}, ["NaN"]),
])
def test_bad_faults_are_refused_with_a_line_naming_the_cause(spec, words):
    with pytest.raises(FaultError) as e:
        parse_fault(spec, NAMES)
    text = str(e.value)
    assert "\n" not in text
    for w in words:
        assert w in text, text


def test_a_faults_file_is_checked_whole_before_anything_is_queued(tmp_path):
    path = tmp_path / "faults.toml"
    path.write_text('[[fault]]\nkind = "can.omit"\nmessage = "DCT_Clutch"\n\n'
                    '[[fault]]\nkind = "signal.hold"\nsignal = "DCT_Clutch.Nope"\n')
    with pytest.raises(FaultError, match=r"faults.toml: fault 2: .*DCT_Clutch.Nope"):
        load_faults(path, NAMES)
    path.write_text('[[fault]]\nkind = "can.omit"\nmessage = "DCT_Clutch"\nstart_s = 1.0\n')
    assert [f.kind.name for f in load_faults(path, NAMES)] == ["can.omit"]
    path.write_text("[[fault]\n")
    with pytest.raises(FaultError, match="not TOML"):
        load_faults(path, NAMES)


def test_the_loop_refuses_a_bad_definition_and_keeps_its_slots():
    with Loop() as loop:
        fm = manager(loop)
        good = fm.inject({"kind": "can.omit", "message": "DCT_Clutch"})
        cmd = ffi.new("rt_fault_cmd *")
        cmd.op = lib.RT_FCMD_SET
        cmd.slot = 5
        cmd.fault.id = 99
        cmd.fault.kind = lib.RT_FAULT_CAN_OMIT
        cmd.fault.message = 1000                    # no such message
        assert lib.rt_fault_push_many(ffi.addressof(loop.c[0], "fault_cmds"), cmd, 1) == 1
        cmd.fault.kind = 77                         # no such kind
        cmd.fault.id = 100
        assert lib.rt_fault_push_many(ffi.addressof(loop.c[0], "fault_cmds"), cmd, 1) == 1
        loop.wait(lambda s: int(loop.c.fault_cmds.last_id) == 100, "the commands taken")
        assert fm.counters()["commands_refused"] == 2
        s = loop.wait(lambda s: s.fault_mask == 1, "the good fault active")
        assert s.faults[5].state == lib.RT_FSTATE_FREE
        assert fm.status(s)[0]["id"] == good and fm.status(s)[0]["state"] == "active"


def test_no_fault_message_index_is_outside_the_loop():
    # every message and signal name resolves to the loop's own numbering
    for name, g in NAMES.messages.items():
        assert 0 <= g < len(CHANNELS.messages)
        assert CHANNELS.messages[g][1].name == name.split(":")[-1]
    for name, (_g, _k, _index, sig) in NAMES.signals.items():
        assert sig.name == name.split(".")[-1]
    assert MSG["DCT_Clutch"] == NAMES.messages["DCT_Clutch"]
    assert not math.isnan(invalid_value(CLUTCH_MSG.get_signal_by_name("LinePressure")))


# ------------------------------------------------------------------ the run's records
@pytest.mark.parametrize("suffix", ["csv", "mf4"])
def test_a_recording_holds_each_faults_start_and_end(tmp_path, suffix):
    from asammdf import MDF

    from rt_loop.measure.recorder import faults_path, read_recording
    from rt_loop.server import Server

    path = tmp_path / f"run.{suffix}"
    # no --duration (that counts deadlines: on a loaded host the plant time
    # reached when it ends can fall short of the fault's end): 0.6 s of plant time
    srv = Server(f"faults-rec-{suffix}-{tmp_path.name}", interface="virtual", priority=0,
                 record_path=path)
    fid = srv.faults.inject({"kind": "can.omit", "message": "DCT_Clutch", "start_s": 0.2,
                             "duration_s": 0.2})
    srv.start()
    try:
        deadline = time.monotonic() + 60
        while srv.snapshot()["sim_time_s"] < 0.6:
            assert time.monotonic() < deadline, "the loop did not reach 0.6 s of plant time in 60 s"
            time.sleep(0.01)
    finally:
        srv.stop()
    rec = read_recording(path)
    on = rec["time_s"][rec["fault_mask"] == 1]
    # a sample every 2 ms of plant time (after its tick's step): the fault is
    # active in the ticks from 0.2 s to the one before 0.4 s
    assert 0.2 < on.min() <= 0.2 + 0.002 and 0.4 - 0.002 <= on.max() <= 0.4
    assert set(np.unique(rec["fault_mask"])) == {0, 1}
    if suffix == "csv":
        lines = open(faults_path(path)).read().splitlines()
        assert lines[0] == "time_s,id,kind,target,event"
        assert [ln.split(",")[4] for ln in lines[1:]] == ["start", "end"]
        assert [float(ln.split(",")[0]) for ln in lines[1:]] == pytest.approx([0.2, 0.4], abs=1e-9)
    else:
        with MDF(str(path)) as mdf:
            ev = mdf.get("fault.event")
            assert list(ev.samples) == [1, 2]
            assert list(ev.timestamps) == pytest.approx([0.2, 0.4], abs=1e-9)
            assert list(mdf.get("fault.id").samples) == [fid, fid]
            assert list(mdf.get("fault.kind").samples) == [lib.RT_FAULT_CAN_OMIT] * 2
    # the run report lists the fault with its plant times
    rep = srv.report(histograms=False)["faults"]
    assert rep["set"][0]["started_s"] == pytest.approx(0.2, abs=1e-9)
    assert rep["set"][0]["ended_s"] == pytest.approx(0.4, abs=1e-9)
    assert [e["event"] for e in rep["events"]] == ["start", "end"]
