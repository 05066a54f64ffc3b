"""Stimulus files (rt_loop/measure/stimulus.py): loading CSV and MF4, every bad input in
one line, and playing them into the loop's stim ring.

The player is first driven against a stand-in: an rt_loop-shaped struct of
a cffi of its own (the rt_write ring as rt_loop.h declares it) and a
Python consumer that applies the writes the way the loop does (in ring
order, at the first tick whose plant time before the step has reached
their time). Once the C side has the ring (``rt_write_push_many`` in the
built module), a grade step is played into a real loop run from Python and
the plant's road grade follows it at the right plant time.
"""

import math
import struct
import threading
import time

import cffi
import numpy as np
import pytest
import requires
from waiting import WAIT_S, wait_until

from rt_loop._rt_loop import ffi, lib
from rt_loop.measure.stimulus import (
    PLANT_INPUT_RANGES,
    Stimulus,
    StimulusError,
    StimulusPlayer,
    load_stimulus,
    plant_inputs_writable,
)

WRITABLE = plant_inputs_writable(ffi)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


# --------------------------------------------------------------------------
# loading
# --------------------------------------------------------------------------

def test_plant_inputs_are_writable_at_their_offsets():
    base = ffi.offsetof("rt_loop", "plant") + ffi.offsetof("dct_plant", "inputs")
    assert set(WRITABLE) == {"accel_pedal_pct", "brake_pedal_pct", "road_grade_pct", "engine_on"}
    for name, (offset, size, lo, hi) in WRITABLE.items():
        assert offset == base + ffi.offsetof("dct_inputs", name)
        assert size == 8 and (lo, hi) == PLANT_INPUT_RANGES[name]


def test_a_csv_stimulus_holds_each_channel_and_writes_only_changes(tmp_path):
    path = write(tmp_path, "grade.csv",
                 "time_s,road_grade_pct,accel_pedal_pct\n"
                 "0,0,10\n0.5,0,10\n0.5005,8,10\n1.25,8,20.5\n2,-3.5,20.5\n")
    stim = load_stimulus(path, WRITABLE)
    assert isinstance(stim, Stimulus) and stim.path == str(path)
    assert list(stim.channels) == ["road_grade_pct", "accel_pedal_pct"]
    t, v = stim.channels["road_grade_pct"]
    assert t.tolist() == [0, 0.5, 0.5005, 1.25, 2] and v.tolist() == [0, 0, 8, 8, -3.5]
    assert stim.duration_s == 2
    ev = stim.events()
    grade, accel = WRITABLE["road_grade_pct"][0], WRITABLE["accel_pedal_pct"][0]
    assert [(e["time_s"], int(e["offset"]), e["value"]) for e in ev] == [
        (0.0, grade, 0.0), (0.0, accel, 10.0), (0.5005, grade, 8.0), (1.25, accel, 20.5),
        (2.0, grade, -3.5)]


def test_a_csv_stimulus_may_play_some_of_its_columns(tmp_path):
    path = write(tmp_path, "rec.csv", "time_s,engine_speed_rpm,brake_pedal_pct\n0,800,0\n1,900,30\n")
    stim = load_stimulus(path, WRITABLE, channels=["brake_pedal_pct"])
    assert list(stim.channels) == ["brake_pedal_pct"]


def _mf4(path, signals):
    from asammdf import MDF, Signal
    mdf = MDF(version="4.10")
    for group in signals:
        mdf.append([Signal(np.asarray(v, dtype=float), np.asarray(t, dtype=float), name=n)
                    for n, t, v in group])
    mdf.save(path, overwrite=True)
    mdf.close()
    return path


def test_an_mf4_stimulus_takes_its_writable_channels_each_on_its_time_base(tmp_path):
    requires.module("asammdf")
    path = _mf4(tmp_path / "s.mf4", [
        [("road_grade_pct", [0, 1, 2], [0, 5, 5]), ("engine_speed_rpm", [0, 1, 2], [8, 9, 9])],
        [("accel_pedal_pct", [0.25, 0.75], [10, 0])]])
    stim = load_stimulus(path, WRITABLE)
    assert list(stim.channels) == ["accel_pedal_pct", "road_grade_pct"]   # writable's order
    assert stim.channels["accel_pedal_pct"][0].tolist() == [0.25, 0.75]
    assert stim.channels["road_grade_pct"][1].tolist() == [0, 5, 5]
    assert [e["time_s"] for e in stim.events()] == [0, 0.25, 0.75, 1]
    only = load_stimulus(path, WRITABLE, channels=["road_grade_pct"])
    assert list(only.channels) == ["road_grade_pct"]


def test_a_recording_of_the_mdf_recorder_plays_its_pedals_and_grade(tmp_path):
    requires.module("asammdf")
    from rt_loop.measure.mdf_recorder import MdfRecorder

    loop = ffi.new("rt_loop *")
    loop.cfg.period_s = 0.0005
    ring = loop.rec
    for k in range(200):
        s = ring.samples[k]
        s.tick = k
        s.time_s = s.outputs.time_s = (k + 1) * 0.002
        s.maneuver_time_s = -1
        s.outputs.road_grade_pct = 0.0 if k < 100 else 6.0
        s.outputs.accel_pedal_pct = k * 0.25
    ring.head = 200
    rec = MdfRecorder(tmp_path / "run.mf4", [])
    rec.start(ffi, lib, loop)
    rec.stop()
    stim = load_stimulus(tmp_path / "run.mf4", WRITABLE)
    assert set(stim.channels) == {"accel_pedal_pct", "brake_pedal_pct", "road_grade_pct"}
    t, v = stim.channels["road_grade_pct"]
    assert len(t) == 200 and v[99] == 0.0 and v[100] == 6.0
    grade = [e for e in stim.events() if e["offset"] == WRITABLE["road_grade_pct"][0]]
    assert [(round(e["time_s"], 9), e["value"]) for e in grade] == [(0.002, 0.0), (0.202, 6.0)]


# every bad input: (file name, content or None for a missing file, channels, words the
# one line must hold besides the file's name)
_BAD = [
    ("unknown.csv", "time_s,road_grade_pct,pedal_pct\n0,0,0\n", None,
     ["'pedal_pct'", "cannot be stimulated", "road_grade_pct"]),
    ("nan.csv", "time_s,road_grade_pct\n0,0\n0.5,nan\n", None,
     ["'road_grade_pct'", "nan", "0.5 s", "not a finite number"]),
    ("inf.csv", "time_s,accel_pedal_pct\n0,inf\n", None, ["'accel_pedal_pct'", "inf"]),
    ("range.csv", "time_s,road_grade_pct\n0,0\n1,45\n", None,
     ["'road_grade_pct'", "45", "out of its range -40 .. 40"]),
    ("range_low.csv", "time_s,brake_pedal_pct\n0,-1\n", None,
     ["'brake_pedal_pct'", "-1", "0 .. 100"]),
    ("engine.csv", "time_s,engine_on\n0,1\n1,2\n", None, ["'engine_on'", "0 .. 1"]),
    ("back.csv", "time_s,road_grade_pct\n0,0\n1,1\n1,2\n", None,
     ["'road_grade_pct'", "not increasing at sample 3", "1 s after 1 s"]),
    ("back2.csv", "time_s,road_grade_pct\n0,0\n2,1\n1.5,2\n", None,
     ["not increasing", "1.5 s after 2 s"]),
    ("negative.csv", "time_s,road_grade_pct\n-0.5,0\n1,1\n", None, ["negative"]),
    ("nantime.csv", "time_s,road_grade_pct\n0,0\nnan,1\n", None, ["time nan", "not a number"]),
    ("empty.csv", "", None, ["empty"]),
    ("blank.csv", "\n\n  \n", None, ["empty"]),
    ("header.csv", "time_s,road_grade_pct\n", None, ["no samples"]),
    ("notime.csv", "t,road_grade_pct\n0,0\n", None, ["no time_s column"]),
    ("onlytime.csv", "time_s\n0\n1\n", None, ["no channel column"]),
    ("cell.csv", "time_s,road_grade_pct\n0,0\n1,abc\n", None,
     ["'road_grade_pct'", "'abc' on line 3", "not a number"]),
    ("emptycell.csv", "time_s,road_grade_pct\n0,0\n1,\n", None,
     ["'road_grade_pct'", "an empty cell on line 3"]),
    ("timecell.csv", "time_s,road_grade_pct\nzero,0\n", None, ["time", "'zero' on line 2"]),
    ("ragged.csv", "time_s,road_grade_pct\n0,0\n1\n", None, ["line 3 has 1 cells"]),
    ("twice.csv", "time_s,road_grade_pct,road_grade_pct\n0,0,0\n", None,
     ["'road_grade_pct'", "appears twice"]),
    ("subset.csv", "time_s,road_grade_pct\n0,0\n", ["accel_pedal_pct"],
     ["'accel_pedal_pct'", "no such column"]),
    ("subset2.csv", "time_s,road_grade_pct\n0,0\n", ["gear"], ["'gear'", "cannot be stimulated"]),
    ("missing.csv", None, None, ["cannot read it", "No such file"]),
    ("stimulus.json", "{}", None, ["unknown format", "'.json'"]),
    ("garbage.mf4", "this is not an MDF file at all" * 10, None, ["not an MDF file", "b'this is '"]),
    ("table.mf4", "time_s,road_grade_pct\n0,0\n", None, ["not an MDF file", "b'time_s,r'"]),
    ("short.mf4", "MDF     4.10    ", None, ["not a readable MDF file", "16 bytes"]),
    ("empty.mf4", "", None, ["empty"]),
    ("missing.mf4", None, None, ["cannot read it", "no such file"]),
]


@pytest.mark.parametrize("name,content,channels,words", _BAD, ids=[b[0] for b in _BAD])
def test_every_bad_input_is_one_line_naming_the_file_channel_and_cause(tmp_path, name, content,
                                                                       channels, words):
    if name.endswith(".mf4"):
        requires.module("asammdf")
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    _refused_in_one_line(path, channels, words)


def _refused_in_one_line(path, channels, words):
    """Loading ``path`` fails with one line that names the file and says ``words``."""
    with pytest.raises(StimulusError) as e:
        load_stimulus(path, WRITABLE, channels=channels)
    text = str(e.value)
    assert "\n" not in text and text.startswith(f"stimulus {path}: ")
    for word in words:
        assert word in text, (word, text)


def test_a_file_that_is_no_mdf_file_is_refused_before_a_reader_is_started(tmp_path, monkeypatch):
    """The identification block is read in the process: a table renamed .mf4 or a cut
    file is refused at once, no reader process started for it."""
    requires.module("asammdf")
    import subprocess

    started = []
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: started.append(a) or 1 / 0)
    (tmp_path / "t.mf4").write_bytes(b"\x00" * 4096)
    _refused_in_one_line(tmp_path / "t.mf4", None, ["not an MDF file"])
    (tmp_path / "u.mf4").write_bytes(b"UnFinMF 4.10")
    _refused_in_one_line(tmp_path / "u.mf4", None, ["12 bytes", "identification block alone is 64"])
    assert not started
    # an unfinalized file's identifier is taken: its reader is started
    (tmp_path / "v.mf4").write_bytes(b"UnFinMF 4.10    " + b"\x00" * 100)
    with pytest.raises(ZeroDivisionError):
        load_stimulus(tmp_path / "v.mf4", WRITABLE)
    assert len(started) == 1


def test_bad_mf4_channels_are_one_line_too(tmp_path):
    requires.module("asammdf")
    none = _mf4(tmp_path / "none.mf4", [[("engine_speed_rpm", [0, 1], [800, 900])]])
    nan = _mf4(tmp_path / "nan.mf4", [[("road_grade_pct", [0, 1], [0, math.nan])]])
    high = _mf4(tmp_path / "high.mf4", [[("accel_pedal_pct", [0, 1], [0, 100.5])]])
    cases = [
        (none, None, ["no channel that can be stimulated", "road_grade_pct"]),
        (none, ["road_grade_pct"], ["'road_grade_pct'", "not in the file"]),
        (none, ["engine_speed_rpm"], ["'engine_speed_rpm'", "cannot be stimulated"]),
        (nan, None, ["'road_grade_pct'", "nan at 1 s"]),
        (high, None, ["'accel_pedal_pct'", "100.5", "0 .. 100"]),
    ]
    for path, channels, words in cases:
        _refused_in_one_line(path, channels, words)


def test_only_doubles_can_be_written(tmp_path):
    path = write(tmp_path, "cal.csv", "time_s,gear_count\n0,6\n")
    writable = {**WRITABLE, "gear_count": (4096, 4, 0, 10)}
    with pytest.raises(StimulusError, match=r"'gear_count' is 4 bytes: only doubles"):
        load_stimulus(path, writable)
    # a calibratable double with an open range
    writable = {**WRITABLE, "shift_delay_s": (4096, 8, None, None)}
    path = write(tmp_path, "cal2.csv", "time_s,shift_delay_s\n0,0.25\n1,1e6\n")
    assert load_stimulus(path, writable).channels["shift_delay_s"][1].tolist() == [0.25, 1e6]


# --------------------------------------------------------------------------
# playing, against a stand-in of the loop
# --------------------------------------------------------------------------

FAKE_FFI = cffi.FFI()
FAKE_FFI.cdef("""
#define RT_WRITE_RING_SIZE 64
typedef struct {
    double time_s;
    uint32_t offset;
    uint32_t len;
    uint64_t id;
    uint8_t data[64];
} rt_write;
typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;
    uint64_t applied;
    uint64_t refused;
    uint64_t last_applied_id;
    uint64_t last_refused_id;
    rt_write writes[RT_WRITE_RING_SIZE];
} rt_write_ring;
typedef struct {
    int state;
    int maneuver_state;
    double sim_time_s;
    double maneuver_time_s;
} rt_stats;
typedef struct {
    rt_stats stats;
    rt_write_ring stim;
} rt_loop;
""")


class FakeLib:
    """The loop's side of the stim ring, in Python (a ring of 64 writes)."""

    RT_WRITE_RING_SIZE = 64
    RT_STATE_IDLE, RT_STATE_RUNNING, RT_STATE_STOPPED = 0, 1, 2
    RT_MANEUVER_NONE, RT_MANEUVER_WAITING, RT_MANEUVER_RUNNING = 0, 1, 2

    def __init__(self):
        self.max_queued = 0

    def rt_write_push_many(self, ring, w, n):
        space = self.RT_WRITE_RING_SIZE - (ring.head - ring.tail)
        k = min(n, space)
        for i in range(k):
            ring.writes[(ring.head + i) % self.RT_WRITE_RING_SIZE] = w[i]
        ring.head += k
        ring.dropped += n - k
        self.max_queued = max(self.max_queued, ring.head - ring.tail)
        return k

    def rt_stats_read(self, loop, copy):
        copy.state, copy.maneuver_state = loop.stats.state, loop.stats.maneuver_state
        copy.sim_time_s, copy.maneuver_time_s = loop.stats.sim_time_s, loop.stats.maneuver_time_s
        return 0


class FakePlant:
    """Ticks of 0.5 ms: before each step, the writes due (in ring order) are applied."""

    def __init__(self, step_s=0.0005):
        self.lib = FakeLib()
        self.loop = FAKE_FFI.new("rt_loop *")
        self.loop.stats.state = FakeLib.RT_STATE_RUNNING
        self.step_s = step_s
        self.ticks = 0
        self.applied = []        # (plant time before the step, offset, value, id)
        self.values = {}

    def tick(self, n=1):
        ring = self.loop.stim
        for _ in range(n):
            now = self.ticks * self.step_s
            while ring.tail != ring.head:
                w = ring.writes[ring.tail % FakeLib.RT_WRITE_RING_SIZE]
                if not w.time_s <= now + 1e-9:
                    break
                value = struct.unpack("<d", bytes(FAKE_FFI.buffer(w.data, 8)))[0]
                assert w.len == 8
                self.applied.append((now, w.offset, value, w.id))
                self.values[w.offset] = value
                ring.applied += 1
                ring.last_applied_id = w.id
                ring.tail += 1
            self.ticks += 1
            self.loop.stats.sim_time_s = self.ticks * self.step_s

    def run_until(self, player, end_s):
        """Ticks to end_s; before each tick, waits until the player has queued every
        write due by then (a loop that never waits, with a player that keeps up)."""
        due = np.sort(player._events["time_s"])
        while self.ticks * self.step_s < end_s:
            now = self.ticks * self.step_s
            if player.t0_s is not None:
                needed = int(np.searchsorted(due + player.t0_s, now + 1e-9, side="right"))
                assert wait_until(lambda n=needed: player.queued >= n, step=0.0002), \
                    (now, needed, player.counters())
            self.tick()
            assert player.error is None, player.error


def grade_stim(tmp_path, rows, name="grade.csv"):
    body = "time_s,road_grade_pct\n" + "".join(f"{t},{v}\n" for t, v in rows)
    return load_stimulus(write(tmp_path, name, body), WRITABLE)


def test_writes_are_applied_at_their_plant_time_relative_to_the_start(tmp_path):
    stim = grade_stim(tmp_path, [(0, 0), (0.1, 0), (0.25, 5), (0.4, 5), (0.6, -2.5)])
    plant = FakePlant()
    plant.tick(200)                                       # the run is 0.1 s old
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, poll_s=0.001).start()
    assert player.t0_s == pytest.approx(0.1)
    plant.run_until(player, 1.0)
    assert player.wait(WAIT_S)
    player.stop()
    grade = WRITABLE["road_grade_pct"][0]
    assert [(round(t, 6), off, v) for t, off, v, _ in plant.applied] == [
        (0.1, grade, 0.0), (0.35, grade, 5.0), (0.7, grade, -2.5)]     # changes only
    assert [i for *_, i in plant.applied] == [1, 2, 3]
    c = player.counters()
    assert (c["writes"], c["queued"], c["applied"], c["refused"], c["dropped"]) == (3, 3, 3, 0, 0)
    assert c["late"] == 0 and c["error"] is None


def test_the_ring_never_overflows_when_a_second_holds_more_writes_than_it(tmp_path):
    # a write every 2 ms for 2 s: 1000 writes, 500 within the lead, through a ring of 64
    rows = [(k * 0.002, (k % 2) * 10.0) for k in range(1000)]
    stim = grade_stim(tmp_path, rows)
    plant = FakePlant()
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, t0_s=0.0,
                            poll_s=0.0005).start()
    plant.run_until(player, 2.1)
    assert player.wait(WAIT_S)
    player.stop()
    assert plant.lib.max_queued == FakeLib.RT_WRITE_RING_SIZE     # full, never over
    assert player.dropped == 0 and player.late == 0 and player.queued == 1000
    assert len(plant.applied) == 1000
    assert all(abs(t - k * 0.002) < 1e-9 for k, (t, *_) in enumerate(plant.applied))


def test_the_player_queues_no_further_ahead_than_its_lead(tmp_path):
    rows = [(k * 0.1, k % 2) for k in range(30)]
    stim = grade_stim(tmp_path, rows)
    plant = FakePlant()
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, t0_s=0.0, lead_s=0.25,
                            poll_s=0.0005).start()
    for end in (0.0, 0.5, 1.23, 2.0):
        plant.run_until(player, end)
        now = plant.loop.stats.sim_time_s
        expect = sum(1 for t, _ in rows if t <= now + 0.25 + 1e-9)
        assert wait_until(lambda e=expect: player.queued == e, step=0.0005), (end, player.queued)
        time.sleep(0.01)                             # and no more
        assert player.queued == expect
    plant.run_until(player, 3.0)
    assert player.wait(WAIT_S) and len(plant.applied) == 30


def test_a_player_started_before_the_loop_runs_on_the_runs_plant_time(tmp_path):
    stim = grade_stim(tmp_path, [(0, 1), (0.01, 2)])
    plant = FakePlant()
    plant.loop.stats.state = FakeLib.RT_STATE_IDLE
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, poll_s=0.001).start()
    assert wait_until(lambda: player.queued == 2)      # queued while the loop is idle
    plant.loop.stats.state = FakeLib.RT_STATE_RUNNING
    plant.run_until(player, 0.05)
    assert player.wait(WAIT_S)
    assert [(round(t, 9), v) for t, _, v, _ in plant.applied] == [(0.0, 1.0), (0.01, 2.0)]


def test_maneuver_time_waits_for_the_maneuver_start(tmp_path):
    stim = grade_stim(tmp_path, [(0, 3), (0.02, 4)])
    plant = FakePlant()
    plant.loop.stats.maneuver_state = FakeLib.RT_MANEUVER_WAITING
    plant.loop.stats.maneuver_time_s = -1
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, start="maneuver",
                            poll_s=0.001).start()
    plant.tick(100)
    time.sleep(0.02)
    assert player.queued == 0 and player.t0_s is None
    plant.tick(60)                                       # the maneuver starts at 0.08 s
    plant.loop.stats.maneuver_state = FakeLib.RT_MANEUVER_RUNNING
    plant.loop.stats.maneuver_time_s = plant.loop.stats.sim_time_s - 0.08
    assert wait_until(lambda: player.queued == 2)
    assert player.t0_s == pytest.approx(0.08)
    plant.run_until(player, 0.2)
    assert player.wait(WAIT_S)
    assert [(round(t, 9), v) for t, _, v, _ in plant.applied] == [(0.08, 3.0), (0.1, 4.0)]


def test_writes_whose_time_passed_are_applied_at_once_and_counted_late(tmp_path):
    stim = grade_stim(tmp_path, [(0, 1), (0.05, 2), (1.0, 3)])
    plant = FakePlant()
    plant.tick(400)                                      # 0.2 s of plant time already
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, t0_s=0.0,
                            poll_s=0.001).start()
    assert wait_until(lambda: player.queued == 3)
    plant.run_until(player, 1.1)
    assert player.wait(WAIT_S)
    assert player.late == 2
    assert [(round(t, 9), v) for t, _, v, _ in plant.applied] == [(0.2, 1.0), (0.2, 2.0),
                                                                  (1.0, 3.0)]


def test_stop_ends_the_thread_with_writes_left(tmp_path):
    stim = grade_stim(tmp_path, [(k * 1.0, k % 3) for k in range(100)])
    plant = FakePlant()
    player = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, t0_s=0.0,
                            poll_s=0.001).start()
    assert wait_until(lambda: player.queued == 2)        # 0 and 1 s within the lead
    player.stop()
    assert not player._thread.is_alive()
    assert not player.done and not player.wait(0.1)
    # the loop ending ends a player too
    player2 = StimulusPlayer(stim, FAKE_FFI, plant.lib, plant.loop, t0_s=0.0,
                             poll_s=0.001).start()
    plant.loop.stats.state = FakeLib.RT_STATE_STOPPED
    player2._thread.join(WAIT_S)
    assert not player2._thread.is_alive()


# --------------------------------------------------------------------------
# playing into the real loop
# --------------------------------------------------------------------------

@pytest.mark.slow
def test_a_grade_step_reaches_the_plant_at_its_plant_time(tmp_path):
    requires.built_with(lib, "rt_write_push_many")
    from can_dbc import mapping as can_mapping
    from plant.params import fill_params, load_params
    from rt_loop.channels import LoopChannels

    stim = load_stimulus(write(tmp_path, "step.csv",
                               "time_s,road_grade_pct\n0,0\n0.5,8\n1.0,-3.5\n"), WRITABLE)
    channels = LoopChannels(can_mapping.load(can_mapping.DEFAULT_MAPPING), ffi, lib)
    c = ffi.new("rt_loop *")
    fill_params(ffi, ffi.addressof(c[0].plant, "params"), load_params(None, ffi, None))
    cfg = c.cfg
    cfg.period_s, cfg.step_s = 0.0005, 0.0005
    cfg.priority, cfg.cpu, cfg.lock_memory = 0, -1, 0
    cfg.duration_s = 1.5                                  # 3000 ticks: the rec ring holds them
    cfg.record_every = 1
    channels.install(c)
    c.chan[0].transport = lib.RT_TRANSPORT_RING
    base = ffi.offsetof("rt_loop", "plant") + ffi.offsetof("dct_plant", "inputs")
    c.n_regions = 1
    c.regions[0].offset, c.regions[0].size = base, ffi.sizeof("dct_inputs")
    c.regions[0].kind = lib.RT_REGION_DATA
    assert lib.rt_loop_prepare(c) == 0
    player = StimulusPlayer(stim, ffi, lib, c, t0_s=0.0, poll_s=0.01).start()
    assert wait_until(lambda: player.queued == 3)         # queued before the first tick
    thread = threading.Thread(target=lambda: lib.rt_loop_run(c), daemon=True)
    thread.start()
    thread.join(WAIT_S)
    assert not thread.is_alive()
    player.stop()
    assert player.done and player.counters()["applied"] == 3 and player.refused == 0
    assert c.stim.last_applied_id == 3
    assert c.plant.inputs.road_grade_pct == -3.5
    samples = ffi.new("rt_sample[]", lib.RT_REC_SIZE)
    n = lib.rt_rec_pop_many(ffi.addressof(c[0], "rec"), samples, lib.RT_REC_SIZE)
    assert c.rec.dropped == 0 and n > 2100
    time_s = np.array([samples[i].time_s for i in range(n)])
    grade = np.array([samples[i].outputs.road_grade_pct for i in range(n)])
    before = time_s - 0.0005                              # plant time before each step
    for start, value in ((0.5, 8.0), (1.0, -3.5)):
        first = int(np.argmax(grade == value))
        # the first tick whose plant time before the step reached the write's time
        assert before[first] == pytest.approx(start, abs=1e-9), (start, before[first])
        assert grade[first - 1] != value
    assert np.all(grade[before < 0.5 - 1e-9] == 0.0)
    assert np.all(grade[(before >= 0.5 - 1e-9) & (before < 1.0 - 1e-9)] == 8.0)
    assert np.all(grade[before >= 1.0 - 1e-9] == -3.5)


def test_the_a2ls_writable_doubles_can_be_stimulated(tmp_path):
    from rt_loop.measure.stimulus import writable_of_regions

    regions = [(100, 8, 0, "override.road_grade_pct", -40.0, 40.0, "double"),
               (200, 8, 1, "params.engine.drag_nm", 0.0, 50.0, "double"),
               (300, 80, 1, "params.engine.full_load_nm", 0.0, 900.0, "double"),
               (400, 4, 1, "params.solver.substeps", 1, 16, "int32_t")]
    writable = writable_of_regions(regions)
    assert writable == {"override.road_grade_pct": (100, 8, -40.0, 40.0),
                        "params.engine.drag_nm": (200, 8, 0.0, 50.0)}
    path = write(tmp_path, "cal.csv", "time_s,params.engine.drag_nm\n0,10\n2,20\n")
    stim = load_stimulus(path, writable)
    assert [(e["time_s"], int(e["offset"]), e["value"]) for e in stim.events()] == [
        (0.0, 200, 10.0), (2.0, 200, 20.0)]
    with pytest.raises(StimulusError, match="out of its range 0 .. 50"):
        load_stimulus(write(tmp_path, "cal2.csv", "time_s,params.engine.drag_nm\n0,60\n"),
                      writable)
