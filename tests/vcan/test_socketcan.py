"""The plant server on real SocketCAN: ``dct-hil serve --interface socketcan``
on vcan0 against a test TCU, with can-utils recording and disturbing the bus.

One server run (module fixture ``run``) goes through these phases, each
waiting for what it needs to see on the bus rather than for a time:

0. the server is up (its SIM_Status is on the bus); four TCU_EngineCmd
   frames with AliveCounter 14, 14, 3, 15: two accepted, a repeat and a
   jump rejected;
1. the project's test TCU (``python -m can_dbc.peer tcu``) for 3 s with
   SolenoidCurrent2 = 0.6 A;
2. a second TCU from the kernel's broadcast manager (python-can
   ``send_periodic``: exact cycle times at no CPU cost, AliveCounter and CRC
   precomputed for 16 frames, each counter continuing the bus's last one)
   with SolenoidCurrent1 = 0.6 A until ClutchPressure1 has risen; then it
   stops and the TCU messages time out;
3. bad frames with ``cansend`` (wrong lengths, bad CRCs, unknown and
   extended identifiers), a burst of 10 000 frames with ``cangen``, then two
   valid frames;
4. SIGTERM; the stats JSON and the traffic log are read.

``candump -L`` records the whole bus. The tests then compare the bus, the
server's statistics and its log: every frame accounted for, and the rejects
counted by reason. Timing inside the guest means nothing (Python
runs about 20x slower than on the host), so nothing here asserts a time;
the loop runs with priority 0.
"""

import json
import os
import signal
import statistics
import subprocess
import sys
import time

import pytest

from can_dbc import codec

pytestmark = pytest.mark.vcan

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PLANT_2MS = ("DCT_ShaftSpeeds", "DCT_OutputSpeeds", "DCT_Clutch")
PLANT_10MS = ("DCT_Shift", "VEH_Motion", "VEH_Driver")
SIM_STATUS = "SIM_Status"
PLANT_MESSAGES = PLANT_2MS + PLANT_10MS + (SIM_STATUS,)
TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")
BURST_FRAMES = 10_000
BURST_ID = 0x7A0
END_ID = 0x7EE           # sent once the server is gone, to see candump caught up
WAIT_S = 300.0          # limit on every wait: the guest is slow, nothing is timed
CURRENT_A = 0.6         # a solenoid current that gives about 12 bar
HIGH_BAR = 5.0
LOW_BAR = 1.0


def fid(name):
    return codec.message(name).frame_id


PLANT_IDS = {fid(m): m for m in PLANT_MESSAGES}
TCU_IDS = {fid(m): m for m in TCU_MESSAGES}


def signal_value(name, signal_name, data):
    return codec.message(name).decode(bytes(data), decode_choices=False)[signal_name]


def can_hex(frame_id, data, extended=False):
    """cansend's frame syntax: 123#0011.. (00000123#.. for an extended id)."""
    return f"{frame_id:08X}#{bytes(data).hex().upper()}" if extended else \
        f"{frame_id:03X}#{bytes(data).hex().upper()}"


# ---------------------------------------------------------------------------
# the bus as candump recorded it
# ---------------------------------------------------------------------------

class BusRecord:
    """Frames of a growing ``candump -L -d`` output: (time_s, id, extended, data).

    candump writes through a buffer, so a frame sent at time t is certainly
    in the file once a frame stamped later than t is (``wait_past``)."""

    def __init__(self, path):
        self.path = path
        self.frames = []
        self.by_id = {}                # (id, extended) -> frames
        self.drops = 0                 # frames candump itself reported lost
        self._pos = 0
        self._partial = ""

    def refresh(self):
        with open(self.path, encoding="ascii", errors="replace") as f:
            f.seek(self._pos)
            chunk = f.read()
            self._pos = f.tell()
        lines = (self._partial + chunk).split("\n")
        self._partial = lines.pop()
        for line in lines:
            self._parse(line)
        return self

    def _parse(self, line):
        line = line.strip()
        if not line:
            return
        if line.startswith("DROPCOUNT"):
            # DROPCOUNT: dropped N CAN frame(s) on 'vcan0' socket (total drops M)
            words = line.split()
            self.drops += int(words[2])
            return
        if not line.startswith("("):
            return
        stamp, _, rest = line[1:].partition(")")
        parts = rest.split()
        ident, _, payload = parts[1].partition("#")
        if payload.startswith("R"):
            data = None                # remote frame
        else:
            data = bytes.fromhex(payload)
        frame = (float(stamp), int(ident, 16), len(ident) == 8, data)
        self.frames.append(frame)
        self.by_id.setdefault(frame[1:3], []).append(frame)

    def of(self, name, since=None, until=None):
        frames = self.by_id.get((fid(name), False), [])
        return [f for f in frames
                if (since is None or f[0] >= since) and (until is None or f[0] <= until)]

    def latest(self, name):
        frames = self.by_id.get((fid(name), False))
        return frames[-1] if frames else None

    def wait_for(self, predicate, what, server=None):
        deadline = time.monotonic() + WAIT_S
        while True:
            self.refresh()
            if predicate(self):
                return
            if server is not None and server.poll() is not None:
                pytest.fail(f"the server exited ({server.returncode}) while waiting for {what}")
            if time.monotonic() > deadline:
                pytest.fail(f"not seen on vcan0 within {WAIT_S:g} s: {what}")
            time.sleep(0.3)

    def wait_past(self, t, server=None):
        """Until every frame sent before wall time ``t`` is in the file."""
        self.wait_for(lambda r: r.frames and r.frames[-1][0] > t + 0.05,
                      f"frames stamped after {t:.3f}", server)

    def last_counter(self, name):
        """AliveCounter of the last frame of ``name`` with the right length and CRC."""
        msg = codec.message(name)
        for f in reversed(self.by_id.get((msg.frame_id, False), [])):
            data = f[3]
            if data is not None and len(data) == msg.length and \
                    data[0] == codec.e2e_crc(msg.frame_id, data):
                return data[1] & 0x0F
        return None


def latest_clutch_bar(record, which, since):
    """ClutchPressure<which> of the last DCT_Clutch frame if stamped after ``since``, else None."""
    f = record.latest("DCT_Clutch")
    if f is None or f[0] < since:
        return None
    return signal_value("DCT_Clutch", f"ClutchPressure{which}", f[3])


def clutch_bar(record, which, since, until=None):
    """ClutchPressure<which> of the DCT_Clutch frames in [since, until]."""
    return [signal_value("DCT_Clutch", f"ClutchPressure{which}", f[3])
            for f in record.of("DCT_Clutch", since, until)]


# ---------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------

class Run:
    """What one server run on vcan0 left: the bus, the stats, the log, the marks."""


def softnet_drops():
    """Frames the kernel dropped in its per-CPU receive backlogs so far (the
    second column of /proc/net/softnet_stat, summed over the CPUs)."""
    with open("/proc/net/softnet_stat", encoding="ascii") as f:
        return sum(int(line.split()[1], 16) for line in f if line.strip())


def _cansend(channel, frame):
    subprocess.run(["cansend", channel, frame], check=True, timeout=WAIT_S,
                   capture_output=True, text=True)


@pytest.fixture(scope="module")
def run(vcan0, tmp_path_factory):
    import can

    d = tmp_path_factory.mktemp("vcan")
    r = Run()
    r.dir = d
    r.marks = {}
    r.stats_path = d / "stats.json"
    r.log_path = d / "server.log"
    r.peer_report_path = d / "peer.json"
    procs = []
    drops_before = softnet_drops()

    dump_out = open(d / "candump.log", "w", encoding="ascii")
    candump = subprocess.Popen(["candump", "-L", "-d", "-r", str(8 * 1024 * 1024), vcan0],
                               stdout=dump_out, stderr=subprocess.PIPE, text=True)
    procs.append(candump)
    record = BusRecord(d / "candump.log")
    r.record = record
    server_out = open(d / "server.out", "w", encoding="utf-8")
    server_err = open(d / "server.err", "w", encoding="utf-8")
    r.server_cmd = [sys.executable, "-m", "dct_hil.cli", "serve", "--interface", "socketcan",
                    "--channel", vcan0, "--priority", "0", "--duration", "3600",
                    "--stats", str(r.stats_path), "--log", str(r.log_path)]
    server = subprocess.Popen(r.server_cmd, stdout=server_out, stderr=server_err, cwd=REPO)
    procs.append(server)
    # receives nothing (a filter no frame matches): it only sends
    bus = can.Bus(interface="socketcan", channel=vcan0, receive_own_messages=False,
                  can_filters=[{"can_id": 0x1FFFFFFF, "can_mask": 0x1FFFFFFF, "extended": True}])
    tasks = []
    try:
        # -- 0: the server is up; the counter check
        record.wait_for(lambda b: b.latest(SIM_STATUS), "the server's SIM_Status", server)
        r.marks["up"] = time.time()
        engine = fid("TCU_EngineCmd")
        for counter in (14, 14, 3, 15):      # ok, repeat, jump by 5, ok
            bus.send(can.Message(arbitration_id=engine, is_extended_id=False,
                                 data=codec.encode("TCU_EngineCmd", {}, counter)))

        # -- 1: the project's test TCU
        r.marks["peer_start"] = time.time()
        peer = subprocess.run(
            [sys.executable, "-m", "can_dbc.peer", "tcu", "--channel", vcan0,
             "--interface", "socketcan", "--duration", "3",
             "--set", f"SolenoidCurrent2={CURRENT_A}", "--report", str(r.peer_report_path)],
            capture_output=True, text=True, timeout=WAIT_S, cwd=REPO)
        r.marks["peer_end"] = time.time()
        r.peer_rc, r.peer_out, r.peer_err = peer.returncode, peer.stdout, peer.stderr
        r.peer_report = None
        if peer.returncode == 0 and r.peer_report_path.exists():
            r.peer_report = json.loads(r.peer_report_path.read_text())

        # -- 2: a broadcast-manager TCU commanding K1, continuing the counters
        record.wait_past(r.marks["peer_end"], server)
        commands = {"TCU_ClutchCmd": {"SolenoidCurrent1": CURRENT_A},
                    "TCU_ShiftCmd": {}, "TCU_EngineCmd": {}}
        r.marks["bcm_start"] = time.time()
        for name, values in commands.items():
            last = record.last_counter(name)
            start = 0 if last is None else (last + 1) % 16
            frames = [can.Message(arbitration_id=fid(name), is_extended_id=False,
                                  data=codec.encode(name, values, (start + k) % 16))
                      for k in range(16)]
            tasks.append(bus.send_periodic(frames, codec.message(name).cycle_time / 1000.0))
        start = r.marks["bcm_start"]
        record.wait_for(lambda b: (latest_clutch_bar(b, 1, start) or 0.0) > HIGH_BAR,
                        f"ClutchPressure1 above {HIGH_BAR} bar after SolenoidCurrent1 = "
                        f"{CURRENT_A} A", server)
        time.sleep(0.5)
        for task in tasks:
            task.stop()
        tasks = []
        r.marks["bcm_stop"] = time.time()
        record.wait_past(r.marks["bcm_stop"], server)
        stop = r.marks["bcm_stop"]
        record.wait_for(lambda b: (latest_clutch_bar(b, 1, stop + 0.05) or 99.0) < LOW_BAR,
                        f"ClutchPressure1 below {LOW_BAR} bar once the TCU went silent", server)
        r.marks["timed_out"] = time.time()

        # -- 3: bad frames, a burst, valid frames again
        clutch = codec.encode("TCU_ClutchCmd", {"SolenoidCurrent1": 0.3}, 1)
        shift = codec.encode("TCU_ShiftCmd", {"ForkForce1": 100.0}, 1)
        r.bad_length = [can_hex(fid("TCU_ClutchCmd"), clutch[:5]),
                        can_hex(fid("TCU_ClutchCmd"), b""),
                        can_hex(fid("TCU_EngineCmd"), clutch[:3])]
        r.bad_crc = [can_hex(fid("TCU_ClutchCmd"), bytes([clutch[0] ^ 0x01]) + clutch[1:]),
                     can_hex(fid("TCU_ShiftCmd"), bytes([shift[0] ^ 0xFF]) + shift[1:])]
        r.unknown = [can_hex(0x7FF, bytes(range(8))),
                     can_hex(0x123, b""),
                     can_hex(fid("TCU_ClutchCmd") + 1, clutch),       # next to a TCU id
                     can_hex(fid("TCU_ClutchCmd"), clutch, extended=True)]
        r.marks["bad_start"] = time.time()
        for frame in r.bad_length + r.bad_crc + r.unknown:
            _cansend(vcan0, frame)
        r.marks["burst_start"] = time.time()
        subprocess.run(["cangen", vcan0, "-g", "0", "-n", str(BURST_FRAMES), "-I", f"{BURST_ID:X}",
                        "-L", "8", "-D", "i", "-p", "10"],
                       check=True, timeout=WAIT_S, capture_output=True)
        r.marks["burst_end"] = time.time()
        end = r.marks["burst_end"]
        record.wait_for(lambda b: len(b.of(SIM_STATUS, since=end)) >= 3,
                        "SIM_Status frames after the burst", server)
        last = record.last_counter("TCU_EngineCmd")
        r.after_burst = [(last + k) % 16 for k in (1, 2)]
        for counter in r.after_burst:
            bus.send(can.Message(arbitration_id=engine, is_extended_id=False,
                                 data=codec.encode("TCU_EngineCmd", {}, counter)))
        r.marks["valid_again"] = time.time()
        record.wait_past(r.marks["valid_again"] + 1.0, server)   # the loop drains its socket

        # -- 4: SIGTERM
        r.marks["sigterm"] = time.time()
        server.send_signal(signal.SIGTERM)
        r.server_rc = server.wait(timeout=WAIT_S)
        r.marks["server_exit"] = time.time()
        # candump may lag behind the bus: stop it only once it printed a last
        # frame sent now (stamped after the server's exit, so not counted)
        bus.send(can.Message(arbitration_id=END_ID, is_extended_id=False, data=b"end"))
        record.wait_for(lambda b: b.by_id.get((END_ID, False)), "candump catching up")
    finally:
        for task in tasks:
            task.stop()
        bus.shutdown()
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT if p is candump else signal.SIGTERM)
                try:
                    p.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        dump_out.close()
        server_out.close()
        server_err.close()
    record.refresh()
    r.kernel_drops = softnet_drops() - drops_before
    (d / "losses.json").write_text(json.dumps(
        {"candump_drops": record.drops, "kernel_backlog_drops": r.kernel_drops}) + "\n")
    r.server_out = (d / "server.out").read_text()
    r.server_err = (d / "server.err").read_text()
    r.stats = json.loads(r.stats_path.read_text()) if r.stats_path.exists() else None
    return r


@pytest.fixture(scope="module")
def stats(run):
    assert run.stats is not None, f"no stats file; server stderr: {run.server_err[-2000:]}"
    return run.stats


def rx(stats):
    return stats["counts"]["rx"]


def lossless(run):
    """Every frame sent on vcan0 reached candump: candump reported no drop,
    and the kernel dropped none in its receive backlog (a frame dropped there
    after a successful send reaches no socket and no one else counts it)."""
    return run.record.drops == 0 and run.kernel_drops == 0


def clean(run, stats):
    """No frame was lost anywhere, so every count can be compared exactly."""
    return rx(stats)["overflow"] == 0 and lossless(run)


def replay_tcu_side(run):
    """The server's receive checks, replayed on every non-plant frame candump saw."""
    check = codec.E2eReceiver(sender="TCU")
    statuses = {s: 0 for s in codec.STATUSES}
    for t, ident, ext, data in run.record.frames:
        if (not ext and ident in PLANT_IDS) or t > run.marks["server_exit"]:
            continue
        statuses[check.check(ident, data if data is not None else b"", ext)] += 1
    return statuses, check


# ---------------------------------------------------------------------------
# the server
# ---------------------------------------------------------------------------

def test_serve_runs_on_socketcan_and_stops_cleanly_on_sigterm(run, stats):
    assert run.server_rc == 0, run.server_err[-2000:]
    assert stats["config"]["transport"] == "socketcan"
    assert stats["config"]["real_time"] == "hard"
    assert stats["run"]["state"] == "stopped"
    assert stats["run"]["error"] is None
    assert stats["run"]["ticks"] > 0
    assert "not real time" in run.server_err             # priority 0 says so
    # the last SIM_Status says: stopping, sent after SIGTERM
    last = run.record.of(SIM_STATUS)[-1]
    assert last[0] > run.marks["sigterm"]
    assert signal_value(SIM_STATUS, "SimState", last[3]) == 2


def test_every_plant_frame_on_the_bus_is_sent_and_protected(run, stats):
    plant = [f for f in run.record.frames if not f[2] and f[1] in PLANT_IDS]
    for name in PLANT_MESSAGES:
        assert run.record.of(name), f"{name} never on vcan0"
    check = codec.E2eReceiver(sender="PLANT")
    rejected = []                   # (time, message, counter, previous counter of that message)
    previous = {}
    for t, ident, _ext, data in plant:
        if check.check(ident, data) != codec.OK:
            rejected.append((t, PLANT_IDS[ident], data[1] & 0x0F, previous.get(ident)))
        previous[ident] = data[1] & 0x0F
    tx = stats["counts"]["tx"]
    for name, c in check.counts.items():
        assert c["bad_length"] == c["bad_crc"] == 0, (name, c)
        if tx["dropped"] == 0 and lossless(run):
            assert c["ok"] == c["received"], (name, c, rejected[:5])   # counters +1 every frame
    if lossless(run):
        assert len(plant) == tx["frames"]                     # sent = seen on the bus


def test_plant_messages_keep_their_cycle_proportions_and_order(run, stats):
    up, end = run.marks["up"], run.marks["sigterm"]
    n = {name: len(run.record.of(name, up, end)) for name in PLANT_MESSAGES}
    assert n[SIM_STATUS] >= 10, n
    fast = [n[m] for m in PLANT_2MS]
    for m in PLANT_10MS:
        assert all(4.5 <= f / n[m] <= 5.5 for f in fast), n       # 2 ms vs 10 ms: 5x
    assert all(40 <= f / n[SIM_STATUS] <= 60 for f in fast), n    # 2 ms vs 100 ms: 50x

    def mean_interval(name):
        t = [f[0] for f in run.record.of(name, up, end)]
        return (t[-1] - t[0]) / (len(t) - 1)

    base = mean_interval("DCT_ShaftSpeeds")
    for m in PLANT_2MS:
        assert 0.8 <= mean_interval(m) / base <= 1.25, m
    for m in PLANT_10MS:
        assert 3.5 <= mean_interval(m) / base <= 6.5, m
    assert 35 <= mean_interval(SIM_STATUS) / base <= 65

    # order: the 2 ms messages take turns, and between two SIM_Status frames
    # come about 50 of each 2 ms and 10 of each 10 ms message
    seq = [PLANT_IDS[f[1]] for f in run.record.frames
           if not f[2] and up <= f[0] <= end and f[1] in PLANT_IDS]
    fast_seq = [m for m in seq if m in PLANT_2MS]
    cycle = fast_seq[:3]
    assert sorted(cycle) == sorted(PLANT_2MS), cycle
    in_turn = sum(1 for i, m in enumerate(fast_seq) if m == cycle[i % 3])
    assert in_turn >= 0.95 * len(fast_seq)
    windows, current = [], None
    for m in seq:
        if m == SIM_STATUS:
            if current is not None:
                windows.append(current)
            current = dict.fromkeys(PLANT_MESSAGES[:-1], 0)
        elif current is not None:
            current[m] += 1
    assert len(windows) >= 8
    for m in PLANT_2MS:
        assert 45 <= statistics.median(w[m] for w in windows) <= 55, m
    for m in PLANT_10MS:
        assert 9 <= statistics.median(w[m] for w in windows) <= 11, m


def test_sim_status_time_runs_on(run):
    times = [signal_value(SIM_STATUS, "SimTime", f[3]) for f in run.record.of(SIM_STATUS)]
    assert all(b >= a for a, b in zip(times, times[1:]))
    assert times[-1] > times[0]


# ---------------------------------------------------------------------------
# the TCU side
# ---------------------------------------------------------------------------

def test_the_project_test_tcu_sees_every_plant_message(run):
    assert run.peer_rc == 0, run.peer_err[-2000:]
    rep = run.peer_report
    assert rep is not None
    for name in PLANT_MESSAGES:
        got = rep["received"][name]
        assert got["accepted"] > 0, (name, got)
        # its receive thread may fall behind in the guest (bad_counter then);
        # CRC and length never fail
        assert got["rejected"]["bad_crc"] == got["rejected"]["bad_length"] == 0, (name, got)
    assert all(rep["sent"][m]["frames"] > 0 for m in TCU_MESSAGES)


def test_commands_change_the_plant(run):
    m = run.marks
    # the test TCU commanded K2 only: K2 pressure rose, K1 stayed low
    k2 = clutch_bar(run.record, 2, m["peer_start"], m["peer_end"])
    k1 = clutch_bar(run.record, 1, m["peer_start"], m["peer_end"])
    assert max(k2) > HIGH_BAR
    assert max(k1) < LOW_BAR
    # the broadcast-manager TCU commanded K1 only
    k1 = clutch_bar(run.record, 1, m["bcm_start"], m["bcm_stop"])
    k2 = clutch_bar(run.record, 2, m["bcm_start"], m["bcm_stop"])
    assert k1[0] < LOW_BAR < HIGH_BAR < k1[-1]
    assert k2[-1] < LOW_BAR


def test_timeouts_when_the_tcu_stops(run, stats):
    msgs = stats["counts"]["tcu_messages"]
    for name in TCU_MESSAGES:
        # silent between the phases and at the end: timed out each time
        assert msgs[name]["timeouts"] >= 2, (name, msgs[name])
        assert msgs[name]["accepted"] > 0, (name, msgs[name])
    for name in ("TCU_ClutchCmd", "TCU_ShiftCmd"):
        assert msgs[name]["timed_out"], (name, msgs[name])
    assert stats["counts"]["timeouts"] == sum(m["timeouts"] for m in msgs.values())
    # safe values once timed out: 0 A, the pressure falls (seen on the bus)
    plant = stats["plant"]
    assert plant["solenoid_current1_a"] == plant["solenoid_current2_a"] == 0.0
    assert plant["torque_request_active"] == 0.0
    after = clutch_bar(run.record, 1, run.marks["bcm_stop"], run.marks["bad_start"])
    assert after[-1] < LOW_BAR


# ---------------------------------------------------------------------------
# bad frames
# ---------------------------------------------------------------------------

def test_the_test_itself_sent_what_it_meant(run):
    """The replayed checks see exactly the bad frames the fixture sent."""
    expected, check = replay_tcu_side(run)
    assert expected["bad_length"] == len(run.bad_length)
    assert expected["bad_crc"] == len(run.bad_crc)
    assert expected["bad_counter"] == 2            # the repeat and the jump of phase 0
    if lossless(run):
        assert check.unknown == len(run.unknown) + BURST_FRAMES
    assert len([f for f in run.record.frames if f[1] == BURST_ID and not f[2]]) \
        + run.record.drops + run.kernel_drops >= BURST_FRAMES


def test_bad_frames_are_rejected_and_counted_by_reason(run, stats):
    c = rx(stats)
    expected, check = replay_tcu_side(run)
    assert c["rejected"] == c["unknown_id"] + c["bad_length"] + c["bad_crc"] + c["bad_counter"]
    assert c["frames"] == c["accepted"] + c["rejected"]
    if clean(run, stats):
        assert c["bad_length"] == len(run.bad_length)
        assert c["bad_crc"] == len(run.bad_crc)
        assert c["bad_counter"] == 2
        assert c["unknown_id"] == len(run.unknown) + BURST_FRAMES
        assert c["accepted"] == expected["ok"]
    else:  # frames were lost (and counted): every kind still shows up
        assert 0 < c["bad_length"] <= len(run.bad_length)
        assert 0 < c["bad_crc"] <= len(run.bad_crc)
        assert c["bad_counter"] >= 1
        assert c["unknown_id"] + c["overflow"] >= len(run.unknown) + BURST_FRAMES


def test_a_burst_is_received_or_counted_as_lost_and_the_loop_goes_on(run, stats):
    c = rx(stats)
    # every frame others put on vcan0 was read by the loop or counted as lost
    others = sum(1 for f in run.record.frames if (f[2] or f[1] not in PLANT_IDS)
                 and f[0] < run.marks["server_exit"])
    if lossless(run):
        assert c["frames"] + c["overflow"] == others
    else:
        assert c["frames"] + c["overflow"] >= others
    assert c["unknown_id"] + c["overflow"] >= BURST_FRAMES
    # the loop kept ticking and sending through the burst ...
    start, end = run.marks["burst_start"], run.marks["burst_end"]
    before = run.record.of(SIM_STATUS, until=start)[-1]
    after = run.record.of(SIM_STATUS, since=end)
    assert len(after) >= 3
    assert signal_value(SIM_STATUS, "SimTime", after[0][3]) > \
        signal_value(SIM_STATUS, "SimTime", before[3])
    assert len(run.record.of("DCT_ShaftSpeeds", since=end)) > 50
    # ... and accepts valid frames after it
    msgs = stats["counts"]["tcu_messages"]
    engine_frames = run.record.of("TCU_EngineCmd")
    assert [f[3][1] & 0x0F for f in engine_frames[-2:]] == run.after_burst
    if clean(run, stats):      # per message as the replayed checks say
        _expected, check = replay_tcu_side(run)
        for name in TCU_MESSAGES:
            assert msgs[name]["accepted"] == check.counts[name]["ok"], name


# ---------------------------------------------------------------------------
# the traffic log
# ---------------------------------------------------------------------------

def test_traffic_log_holds_both_directions_in_candump_format(run, stats):
    import can

    log = stats["log"]
    assert log["error"] is None
    assert log["format"] == "candump"
    tx_frames, rx_frames = stats["counts"]["tx"]["frames"], rx(stats)["frames"]
    assert log["written"] + log["dropped"] == tx_frames + rx_frames
    sent = received = 0
    for msg in can.LogReader(str(run.log_path)):
        if msg.is_rx:
            received += 1
        else:
            sent += 1
            assert msg.arbitration_id in PLANT_IDS
    assert sent + received == log["written"]
    if log["dropped"] == 0:
        assert sent == tx_frames
        assert received == rx_frames
