"""The MDF 4 recorder (rt_loop/measure/mdf_recorder.py): plant samples and CAN traffic in one .mf4.

The samples and frames come from the real loop (rt_loop.c run from Python,
the default mapping, the ring transport, a TCU stand-in pushing
TCU_ClutchCmd) or from an rt_loop that does not run and whose rings the
test fills (the recorder pops them with the real rt_rec_pop_many /
rt_log_pop_many). The file is read back with asammdf: channels, units,
comments, values against the CSV recorder's for the same samples, the CAN
frames as bus logging decoded with the project's DBC, a file whose
recorder was killed, and the one-line error of an unwritable path.
"""

import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import requires

asammdf = requires.module("asammdf")

from waiting import WAIT_S, wait_until

from can_dbc import mapping as can_mapping
from plant.params import fill_params, load_params
from rt_loop._rt_loop import ffi, lib
from rt_loop.channels import LoopChannels
from rt_loop.measure.mdf_recorder import MdfRecorder, output_comments
from rt_loop.measure.recorder import Recorder, read_recording

ROOT = Path(__file__).resolve().parents[1]
DBC_PATH = ROOT / "can_dbc" / "dct_hil.dbc"
MAPPING = can_mapping.load(can_mapping.DEFAULT_MAPPING)
CHANNELS = LoopChannels(MAPPING, ffi, lib)
TABLE = CHANNELS.table(0)
COMMANDS = list(CHANNELS.command_names)
OUTPUTS = [n for n, _ in ffi.typeof("dct_outputs").fields]
_PARAMS = load_params(None, ffi, None)

CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
PERIOD_S, STEP_S = 0.001, 0.0005          # a half-speed run: time scale 0.5


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------

def new_loop(period_s=PERIOD_S, step_s=STEP_S):
    """An rt_loop that is not run: the test fills its rings."""
    c = ffi.new("rt_loop *")
    c.cfg.period_s = period_s
    c.cfg.step_s = step_s
    return c


def fill_rec(loop, samples, n):
    """Puts n rt_sample into the (empty) rec ring of a loop that does not run."""
    assert n < lib.RT_REC_SIZE
    ffi.memmove(loop.rec.samples, samples, n * ffi.sizeof("rt_sample"))
    loop.rec.head = n


def fill_log(loop, entries, n):
    assert n < lib.RT_LOG_SIZE
    ffi.memmove(loop.log.entries, entries, n * ffi.sizeof("rt_log_entry"))
    loop.log.head = n


def push_sample(loop, k, **outputs):
    """One sample k (tick k, plant time (k+1) ms) into a loop's rec ring, waiting for room."""
    ring = loop.rec
    assert wait_until(lambda: ring.head - ring.tail < lib.RT_REC_SIZE - 1, step=0.001)
    s = ring.samples[ring.head & (lib.RT_REC_SIZE - 1)]
    ffi.memmove(ffi.addressof(s), b"\0" * ffi.sizeof("rt_sample"), ffi.sizeof("rt_sample"))
    s.tick = k
    s.time_s = s.outputs.time_s = (k + 1) * 0.001
    s.maneuver_time_s = -1.0
    s.outputs.gear = k % 7
    for name, value in outputs.items():
        setattr(s.outputs, name, value)
    ring.head += 1


def log_entries(frames):
    """rt_log_entry[] of (time_s, dir, id, data, flags, channel)."""
    buf = ffi.new("rt_log_entry[]", len(frames))
    for i, (t, direction, ident, data, flags, channel) in enumerate(frames):
        e = buf[i]
        e.time_s, e.dir = t, direction
        e.frame.id, e.frame.len, e.frame.flags, e.frame.channel = ident, len(data), flags, channel
        ffi.memmove(e.frame.data, bytes(data), len(data))
    return buf


def drain_tx(c, thread):
    """Empties the loop's tx ring (the bus) while the loop's thread runs."""
    tx = ffi.new("rt_frame[1024]")
    while thread.is_alive():
        lib.rt_ring_pop_many(ffi.addressof(c[0], "tx", 0), tx, 1024)
        time.sleep(0.005)


def csv_columns(command_names):
    return (OUTPUTS + ["maneuver_time_s", "tick", "fault_mask"]
            + [f"cmd_{n}" for n in command_names if n not in OUTPUTS])


def record(loop, path, drain_log=True, channels=("vcan0",), **kw):
    """MdfRecorder over a filled loop, stopped once it has drained it."""
    rec = MdfRecorder(path, COMMANDS, channels=list(channels), **kw)
    rec.start(ffi, lib, loop, drain_log=drain_log)
    rec.stop()
    assert rec.error is None, rec.error
    return rec


class RealRun:
    """One run of the real loop: the default mapping on the ring transport, a
    driver table started by the TCU's first frame, TCU_ClutchCmd frames pushed
    from plant time 0.3 s on, every frame logged, every tick recorded. Nothing
    drains the rec and log rings while it runs: they hold the whole run."""

    def __init__(self, duration_s=3.0):
        c = ffi.new("rt_loop *")
        fill_params(ffi, ffi.addressof(c[0].plant, "params"), _PARAMS)
        cfg = c.cfg
        cfg.period_s, cfg.step_s = PERIOD_S, STEP_S
        cfg.priority, cfg.cpu, cfg.lock_memory = 0, -1, 0
        cfg.duration_s = duration_s
        cfg.log_frames = 1
        cfg.record_every = 1
        CHANNELS.install(c)
        c.chan[0].transport = lib.RT_TRANSPORT_RING
        d = c.driver
        rows = [(0.0, 0.0, 10.0), (0.3, 40.0, 0.0), (1.0, 0.0, 30.0)]
        d.rows = len(rows)
        for i, (t, a, b) in enumerate(rows):
            d.t_s[i], d.accel_pedal_pct[i], d.brake_pedal_pct[i] = t, a, b
        d.linear, d.start_on_tcu = 1, 1
        assert lib.rt_loop_prepare(c) == 0
        self.c = c
        self.currents = []
        thread = threading.Thread(target=lambda: lib.rt_loop_run(c), daemon=True)
        thread.start()
        self._feed_tcu(thread)
        thread.join(WAIT_S)
        assert not thread.is_alive(), "the loop did not end"
        self.stats = ffi.new("rt_stats *")
        assert lib.rt_stats_read(c, self.stats) == 0
        assert c.rec.dropped == 0 and c.log.dropped == 0
        self.samples = ffi.new("rt_sample[]", lib.RT_REC_SIZE)
        self.n = lib.rt_rec_pop_many(ffi.addressof(c[0], "rec"), self.samples, lib.RT_REC_SIZE)
        self.entries = ffi.new("rt_log_entry[]", lib.RT_LOG_SIZE)
        self.n_log = lib.rt_log_pop_many(ffi.addressof(c[0], "log"), self.entries,
                                         lib.RT_LOG_SIZE)
        assert 0 < self.n < lib.RT_REC_SIZE and 0 < self.n_log < lib.RT_LOG_SIZE

    def _feed_tcu(self, thread):
        c, counter = self.c, 0
        frame = ffi.new("rt_frame[1]")
        tx = ffi.new("rt_frame[1024]")
        while thread.is_alive():
            while lib.rt_ring_pop_many(ffi.addressof(c[0], "tx", 0), tx, 1024) == 1024:
                pass
            if c.stats.sim_time_s >= 0.3:
                current = round(0.2 + 0.0001 * (counter % 5000), 4)
                data = TABLE.encode("TCU_ClutchCmd", {"SolenoidCurrent1": current},
                                    counter=counter % 16)
                frame[0].id = MAPPING_IDS["TCU_ClutchCmd"]
                frame[0].len = len(data)
                ffi.memmove(frame[0].data, bytes(data), len(data))
                if lib.rt_ring_push_many(ffi.addressof(c[0], "rx", 0), frame, 1) == 1:
                    self.currents.append(current)
                    counter += 1
            time.sleep(0.001)

    def mdf_loop(self):
        """A loop that does not run, holding this run's samples and frames."""
        loop = new_loop()
        fill_rec(loop, self.samples, self.n)
        fill_log(loop, self.entries, self.n_log)
        return loop


MAPPING_IDS = {m.name: m.frame_id for _, m in CHANNELS.messages}


@pytest.fixture(scope="module")
def run():
    return RealRun()


@pytest.fixture(scope="module")
def recorded(run, tmp_path_factory):
    """The run written by both recorders: (MDF, CSV columns)."""
    folder = tmp_path_factory.mktemp("rec")
    csv_loop, mdf_loop = new_loop(), run.mdf_loop()
    fill_rec(csv_loop, run.samples, run.n)
    csv = Recorder(folder / "run.csv", COMMANDS)
    csv.start(ffi, lib, csv_loop)
    csv.stop()
    rec = record(mdf_loop, folder / "run.mf4")
    assert rec.written == csv.written == run.n
    assert rec.frames_written == run.n_log
    mdf = asammdf.MDF(folder / "run.mf4")
    yield mdf, read_recording(folder / "run.csv"), rec
    mdf.close()


# --------------------------------------------------------------------------
# channels
# --------------------------------------------------------------------------

@pytest.mark.slow
def test_every_csv_column_is_a_channel_with_its_unit_and_a_comment(recorded):
    mdf, csv, _ = recorded
    assert mdf.version == "4.10"
    plant = mdf.groups[0]
    names = [ch.name for ch in plant.channels]
    assert names[0] == "time" and plant.channels[0].unit == "s"
    assert names[1:] == list(csv) == csv_columns(COMMANDS)
    assert "cmd_target_gear" in names                # the TCU's target gear, as in the CSV
    for name in names[1:]:
        sig = mdf.get(name, group=0)
        base = name[4:] if name.startswith("cmd_") else name
        assert sig.unit == (can_mapping.unit_of_name(base) or ""), name
        assert sig.comment.strip(), name
    assert mdf.get("engine_speed_rpm").unit == "rpm"
    assert mdf.get("clutch1_pressure_bar").unit == "bar"
    assert mdf.get("accel_pedal_pct").unit == "%"
    assert "active input shaft" in mdf.get("gear").comment     # from dct_plant.h
    assert output_comments()["solenoid_current1_a"].startswith("as applied")
    assert mdf.get("tick").samples.dtype == np.uint64


@pytest.mark.slow
def test_values_equal_the_csv_recorders_for_the_same_run(run, recorded):
    mdf, csv, _ = recorded
    time_s = mdf.get("time_s")
    # the master is the plant time: the CSV's time_s, each tick's step later
    np.testing.assert_array_equal(time_s.timestamps, time_s.samples)
    np.testing.assert_allclose(time_s.timestamps, csv["time_s"], rtol=1e-9, atol=0)
    assert np.all(np.diff(mdf.get("tick").samples) == 1)
    for name in csv:
        sig = mdf.get(name, group=0)
        assert len(sig) == run.n, name
        # the MF4 holds the loop's doubles, the CSV them to 9 digits (%.9g)
        to_9 = np.array([float(f"{v:.9g}") for v in sig.samples.tolist()])
        np.testing.assert_array_equal(to_9, csv[name], err_msg=name)
    # and exactly what the loop recorded
    s = run.samples
    assert mdf.get("engine_speed_rpm").samples.tolist() == [
        s[i].outputs.engine_speed_rpm for i in range(run.n)]
    assert mdf.get("tick").samples.tolist() == [int(s[i].tick) for i in range(run.n)]
    k = COMMANDS.index("target_gear")
    assert mdf.get("cmd_target_gear").samples.tolist() == [s[i].commands[k]
                                                           for i in range(run.n)]
    # the maneuver started at the TCU's first frame: NaN before, as the CSV
    mt = mdf.get("maneuver_time_s").samples
    assert np.isnan(mt[0]) and np.isfinite(mt[-1])
    assert np.isnan(mt).sum() == np.isnan(csv["maneuver_time_s"]).sum() > 0
    # the pedals of the driver table moved and the TCU's current arrived
    assert mdf.get("accel_pedal_pct").samples.max() > 10
    assert mdf.get("solenoid_current1_a").samples.max() >= 0.2


# --------------------------------------------------------------------------
# CAN traffic
# --------------------------------------------------------------------------

@pytest.mark.slow
def test_can_frames_are_the_logged_ones_and_decode_with_the_dbc(run, recorded):
    mdf, _, rec = recorded
    e = run.entries
    logged = [(e[i].time_s, int(e[i].dir), int(e[i].frame.id),
               bytes(ffi.buffer(e[i].frame.data, e[i].frame.len))) for i in range(run.n_log)]
    ids = mdf.get("CAN_DataFrame.ID")
    t = ids.timestamps
    direction = mdf.get("CAN_DataFrame.Dir").samples
    length = mdf.get("CAN_DataFrame.DataLength").samples
    data = mdf.get("CAN_DataFrame.DataBytes").samples
    assert len(ids) == len(logged) == rec.frames_written
    assert set(mdf.get("CAN_DataFrame.BusChannel").samples.tolist()) == {1}
    assert not mdf.get("CAN_DataFrame.IDE").samples.any()
    for i, (time_s, d, ident, payload) in enumerate(logged):
        # loop time x time scale: the plant time at the start of the tick
        assert t[i] == pytest.approx(time_s * STEP_S / PERIOD_S, abs=1e-12)
        assert (int(ids.samples[i]), int(direction[i])) == (ident, 0 if d == lib.RT_DIR_RX else 1)
        assert bytes(data[i][:length[i]]) == payload and not data[i][length[i]:].any()
    assert {"TCU_ClutchCmd", "DCT_ShaftSpeeds", "SIM_Status"} <= {
        name for name, fid in MAPPING_IDS.items() if fid in set(ids.samples.tolist())}

    decoded = mdf.extract_bus_logging({"CAN": [(str(DBC_PATH), 0)]})
    try:
        # what the TCU stand-in sent, in order
        current = decoded.get("SolenoidCurrent1")
        assert len(run.currents) - 5 <= len(current) <= len(run.currents)   # the last may
        assert current.samples.tolist() == pytest.approx(                  # not be read
            run.currents[:len(current)], abs=1e-9)
        # the plant's engine speed, sent in the tick of a sample: 0.5 rpm resolution
        speed = decoded.get("EngineSpeed")
        rpm = mdf.get("engine_speed_rpm")
        assert len(speed) > 100
        if run.stats.skipped_ticks == 0:
            # frame time + one step = the time of the sample of the same tick
            at = np.searchsorted(rpm.timestamps, speed.timestamps + STEP_S - 1e-9)
            np.testing.assert_allclose(speed.samples, rpm.samples[at], atol=0.25 + 1e-9)
        else:   # a skipped deadline moves the loop time off the plant time: values only
            j = 0
            for v in speed.samples:
                while abs(rpm.samples[j] - v) > 0.25 + 1e-9:
                    j += 1                                   # IndexError: not in order
    finally:
        decoded.close()


def test_frames_handed_by_the_traffic_log_keep_ids_lengths_directions_and_buses(tmp_path):
    loop = new_loop(period_s=0.0005, step_s=0.0005)
    frames = [
        (0.001, lib.RT_DIR_TX, 0x100, b"\x01\x02\x03", 0, 0),
        (0.002, lib.RT_DIR_RX, 0x18FF0102 | CAN_EFF_FLAG, bytes(range(8)), 0, 1),
        (0.003, lib.RT_DIR_TX, 0x123, bytes(range(64)),
         lib.RT_FRAME_FD | lib.RT_FRAME_BRS, 1),
        (0.004, lib.RT_DIR_RX, 0x7FF, bytes(range(12)), lib.RT_FRAME_FD, 0),
        (0.005, lib.RT_DIR_RX, 0x222 | CAN_RTR_FLAG, b"", 0, 0),
        (0.006, lib.RT_DIR_RX, 0x004 | CAN_ERR_FLAG, bytes(8), 0, 0),
    ]
    rec = MdfRecorder(tmp_path / "f.mf4", COMMANDS, channels=["can0", "can1"])
    rec.start(ffi, lib, loop)                        # the log ring is the traffic log's
    buf = log_entries(frames)
    rec.add_frames(buf, len(frames))
    buf[0].frame.id = 0x555                          # the caller reuses its buffer
    rec.stop()
    assert rec.error is None and rec.frames_handed == rec.frames_written == 6
    with asammdf.MDF(tmp_path / "f.mf4") as mdf:
        g = {n: mdf.get(f"CAN_DataFrame.{n}").samples.tolist() for n in
             ("ID", "IDE", "DLC", "DataLength", "Dir", "BusChannel", "EDL", "BRS")}
        assert g["ID"] == [0x100, 0x18FF0102, 0x123, 0x7FF]
        assert g["IDE"] == [0, 1, 0, 0]
        assert g["DataLength"] == [3, 8, 64, 12]
        assert g["DLC"] == [3, 8, 15, 9]
        assert g["Dir"] == [1, 0, 1, 0]
        assert g["BusChannel"] == [1, 2, 2, 1]
        assert g["EDL"] == [0, 0, 1, 1] and g["BRS"] == [0, 0, 1, 0]
        assert mdf.get("CAN_DataFrame.DataBytes").samples[2].tolist() == list(range(64))
        assert mdf.get("CAN_DataFrame.ID").timestamps.tolist() == pytest.approx(
            [0.001, 0.002, 0.003, 0.004])
        assert mdf.get("CAN_RemoteFrame.ID").samples.tolist() == [0x222]
        assert mdf.get("CAN_ErrorFrame.ID").samples.tolist() == [0x004]
        assert "1 = can0, 2 = can1" in mdf.groups[1].channel_group.comment
    # python-can reads the bus logging back (its MF4 reader)
    import can

    msgs = list(can.io.MF4Reader(tmp_path / "f.mf4"))
    assert [(m.arbitration_id, m.is_extended_id, m.is_rx, m.is_fd, m.bitrate_switch, m.dlc,
             m.channel) for m in msgs if not (m.is_remote_frame or m.is_error_frame)] == [
        (0x100, False, False, False, False, 3, 1), (0x18FF0102, True, True, False, False, 8, 2),
        (0x123, False, False, True, True, 64, 2), (0x7FF, False, True, True, False, 12, 1)]
    assert bytes(msgs[2].data) == bytes(range(64))
    assert [m.arbitration_id for m in msgs if m.is_remote_frame] == [0x222]


# --------------------------------------------------------------------------
# streaming
# --------------------------------------------------------------------------

def test_a_running_loop_is_recorded_block_by_block(tmp_path):
    """The recorder drains the real loop while it runs; copies of the file taken
    meanwhile open with what was flushed; at the end nothing is missing."""
    c = ffi.new("rt_loop *")
    fill_params(ffi, ffi.addressof(c[0].plant, "params"), _PARAMS)
    c.cfg.period_s, c.cfg.priority, c.cfg.cpu = 0.0005, 0, -1
    c.cfg.log_frames, c.cfg.record_every = 1, 4
    CHANNELS.install(c)
    c.chan[0].transport = lib.RT_TRANSPORT_RING
    assert lib.rt_loop_prepare(c) == 0
    path = tmp_path / "live.mf4"
    rec = MdfRecorder(path, COMMANDS, flush_s=0.1)
    rec.start(ffi, lib, c, drain_log=True)
    thread = threading.Thread(target=lambda: lib.rt_loop_run(c), daemon=True)
    thread.start()
    drainer = threading.Thread(target=drain_tx, args=(c, thread), daemon=True)
    drainer.start()
    copies = []
    try:
        for k in range(3):
            target = rec.blocks + 2
            assert wait_until(lambda t=target: rec.blocks >= t)
            copy = tmp_path / f"copy{k}.mf4"
            for _attempt in range(10):      # a copy that spans a flush is torn: again
                done = rec.blocks
                shutil.copy(path, copy)
                if rec.blocks == done:
                    break
            copies.append(copy)
    finally:
        lib.rt_loop_request_stop(c)
        thread.join(WAIT_S)
        drainer.join(WAIT_S)
        rec.stop()
    assert rec.error is None and rec.dropped == 0 and c.log.dropped == 0
    ticks = int(c.stats.ticks)
    assert rec.written == (ticks + 3) // 4                  # ticks 0, 4, 8, ...
    with asammdf.MDF(path) as mdf:
        tick = mdf.get("tick").samples
        assert tick.tolist() == list(range(0, ticks, 4))
        assert len(mdf.get("CAN_DataFrame.ID")) == rec.frames_written > 0
    seen = []
    for copy in copies:
        with asammdf.MDF(copy) as mdf:
            tick = mdf.get("tick").samples
            assert len(tick) > 0 and tick.tolist() == list(range(0, 4 * len(tick), 4))
            assert len(mdf.get("CAN_DataFrame.ID")) > 0
            seen.append(len(tick))
    assert seen == sorted(seen) and seen[-1] <= rec.written


def test_a_killed_recorder_leaves_a_file_readable_up_to_its_last_block(tmp_path):
    """SIGKILL while recording: no stop(), no close; the file opens with every
    sample of the blocks flushed before."""
    path = tmp_path / "killed.mf4"
    child = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_mdf_recorder import new_loop, push_sample, COMMANDS
        from rt_loop._rt_loop import ffi, lib
        from rt_loop.measure.mdf_recorder import MdfRecorder
        loop = new_loop()
        rec = MdfRecorder({str(path)!r}, COMMANDS, flush_s=0.05)
        rec.start(ffi, lib, loop, drain_log=True)
        k, blocks = 0, 0
        while True:
            push_sample(loop, k, engine_speed_rpm=800.0 + k)
            k += 1
            if k % 50 == 0:
                time.sleep(0.01)
            if rec.blocks != blocks:
                blocks = rec.blocks
                print(blocks, flush=True)
    """)
    proc = subprocess.Popen([sys.executable, "-c", child], cwd=str(Path(__file__).parents[1]),
                            stdout=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:
            if int(line) >= 4:
                break
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(WAIT_S)
    assert proc.returncode == -signal.SIGKILL
    with asammdf.MDF(path) as mdf:
        tick = mdf.get("tick").samples
        assert len(tick) >= 4 and tick.tolist() == list(range(len(tick)))
        rpm = mdf.get("engine_speed_rpm")
        assert rpm.samples.tolist() == [800.0 + k for k in range(len(tick))]
        assert rpm.timestamps.tolist() == pytest.approx([(k + 1) * 0.001
                                                         for k in range(len(tick))])


def test_killed_between_the_count_and_the_link_the_blocks_before_still_read(tmp_path,
                                                                             monkeypatch):
    path = tmp_path / "window.mf4"
    loop = new_loop()
    rec = MdfRecorder(path, COMMANDS, flush_s=3600)
    rec.start(ffi, lib, loop)
    for k in range(100):
        push_sample(loop, k)
    assert wait_until(lambda: rec.written == 100)
    rec._file.flush()
    for k in range(100, 250):
        push_sample(loop, k)
    assert wait_until(lambda: rec.written == 250)
    writes = []
    real = rec._file._write_u64

    def dies_after_the_count(at, value):
        if writes:
            raise KeyboardInterrupt("killed")
        writes.append((at, value))
        real(at, value)

    monkeypatch.setattr(rec._file, "_write_u64", dies_after_the_count)
    with pytest.raises(KeyboardInterrupt):
        rec._file.flush()
    rec._file._f.flush()
    shutil.copy(path, tmp_path / "copy.mf4")
    monkeypatch.undo()
    rec.stop()
    with asammdf.MDF(tmp_path / "copy.mf4") as mdf:
        assert mdf.groups[0].channel_group.cycles_nr == 250      # the count went first
        assert mdf.get("tick").samples.tolist() == list(range(100))


def test_memory_is_one_block_and_the_file_grows_by_blocks(tmp_path):
    loop = new_loop()
    rec = MdfRecorder(tmp_path / "grow.mf4", COMMANDS, flush_s=3600)
    rec.start(ffi, lib, loop)
    sizes, buffers = [], []
    for block in range(5):
        for k in range(block * 500, (block + 1) * 500):
            push_sample(loop, k, vehicle_speed_kmh=k * 0.01)
        assert wait_until(lambda b=block: rec.written == (b + 1) * 500)
        assert rec._file.pending_bytes == 500 * rec._file.groups[0].dtype.itemsize
        rec._file.flush()
        assert rec._file.pending_bytes == 0
        sizes.append(rec.bytes)
        buffers.append(rec._file.groups[0].pending._buf.ctypes.data)
        with asammdf.MDF(tmp_path / "grow.mf4") as mdf:
            assert len(mdf.get("vehicle_speed_kmh")) == (block + 1) * 500
    rec.stop()
    assert sizes == sorted(sizes)
    steps = np.diff(sizes)
    assert steps.max() < 500 * rec._file.groups[0].dtype.itemsize      # compressed blocks
    assert rec.counters()["group_bytes"]["plant"] > 0
    # the records waited in one buffer, kept from block to block once it held the first
    assert len(set(buffers[1:])) == 1 and buffers[1] == buffers[0]


def test_pending_records_keep_their_bytes_in_one_kept_buffer():
    from rt_loop.measure.mdf_recorder import _PENDING_MIN_BYTES, _Pending
    rng = np.random.default_rng(3)
    p = _Pending()
    first = p._buf
    batches = [rng.integers(0, 256, 24 * k, dtype=np.uint8) for k in (1, 7, 5000, 30000, 2)]
    for b in batches[:2]:
        p.add(b.tobytes())                     # bytes
    assert p._buf is first and first.size == _PENDING_MIN_BYTES
    for b in batches[2:]:
        p.add(b.view([("a", "<f8"), ("b", "<u8"), ("c", "<i8")]))   # structured records
    whole = np.concatenate(batches)
    assert p.nbytes == whole.size and bytes(p._buf[:p.nbytes]) == whole.tobytes()   # grown, kept
    assert bytes(p.view()) == whole.tobytes()
    grown = p._buf
    p.clear()
    p.add(batches[0])
    assert p._buf is grown and p.nbytes == 24


# --------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------

@pytest.mark.parametrize("where", ["a directory", "under a file"])
def test_an_unwritable_path_is_one_line(tmp_path, where):
    if where == "a directory":
        path = tmp_path
    else:
        (tmp_path / "plain").write_text("x")
        path = tmp_path / "plain" / "run.mf4"
    with pytest.raises(OSError) as e:
        MdfRecorder(path, COMMANDS)
    text = str(e.value)
    assert text.startswith(f"recording {path}: ") and "\n" not in text
    assert len(text) < 200
