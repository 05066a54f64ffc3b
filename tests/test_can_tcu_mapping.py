"""The reference TCU as a CAN node on a vehicle matrix (tcu_stub.can_tcu with a mapping).

Every test uses python-can's ``virtual`` interface on channels of its own
(the first bus on a fresh name, the others on ``<name>-<bus>``, as
``Mapping.channels`` derives them). The plant side is written here from the
mapping with the table codec (``FakePlant``): it sends the mapping's
``direction == "send"`` messages with the values of a dict of plant outputs,
scaled as the mapping says, protected with a counter per frame, and keeps
every frame the TCU sends. Nothing here asserts timing: every wait is for a
behaviour, with a generous time limit.
"""

import json
import math
import os
import re
import threading
import time
import uuid

import can
import pytest
from waiting import wait_until

from can_dbc import mapping as mapping_mod
from can_dbc.table import CodecTable
from tcu_stub import can_tcu
from tcu_stub.can_tcu import REJECTS_TO_STALE, CanTcu, MissingSignalError

#: a car at standstill, brake on, engine idling (the plant's output names)
STANDSTILL = {
    "engine_speed_rpm": 750.0, "engine_torque_nm": 20.0, "accel_pedal_pct": 0.0, "brake_pedal_pct": 30.0,
    "engine_running": 1.0, "vehicle_speed_kmh": 0.0, "vehicle_accel_mps2": 0.0, "road_grade_pct": 0.0,
    "wheel_speed_fl_rpm": 0.0, "wheel_speed_fr_rpm": 0.0, "wheel_speed_rear_rpm": 0.0,
    "distance_m": 1234.0, "input_shaft1_speed_rpm": 0.0, "input_shaft2_speed_rpm": 0.0,
    "output_shaft1_speed_rpm": 0.0, "output_shaft2_speed_rpm": 0.0, "clutch1_pressure_bar": 0.0,
    "clutch2_pressure_bar": 0.0, "line_pressure_bar": 20.0, "fork1_position_mm": 0.0,
    "fork2_position_mm": 0.0, "fork3_position_mm": 0.0, "fork4_position_mm": 0.0,
    "sync1_state": 0.0, "sync2_state": 0.0, "sync3_state": 0.0, "sync4_state": 0.0,
    "selector_lever": 3.0, "trans_oil_temp_degc": 80.0,        # in D (the plant's default), warm oil
}
TCU_SENDS = ("pt:TCU_TorqueReq", "pt:TCU_Gear", "pt:TCU_Info", "io:TCU_ValveCurrents", "io:TCU_ForkForces")
NEEDED = ("pt:ECM_Torque", "pt:ECM_Speed", "pt:ESP_Motion", "pt:ESP_Accel", "pt:GW_Selector",
          "io:IO_ShaftSpeeds", "io:IO_OutputSpeeds", "io:IO_Pressures", "io:IO_Forks",
          "io:IO_Temperatures")
WAIT_S = 20.0


def key(m):
    return f"{m.bus}:{m.name}"


def plant_value(src, outputs, n):
    """A sent signal's value from the plant outputs, as the mapping file's rules say."""
    if src.kind in ("output", "status"):
        x = float(outputs.get(src.name, 0.0))
        if src.absolute:
            x = abs(x)
        if src.table is not None or src.ranges:
            k = int(round(x))
            for t, v in src.table or ():
                if t == k:
                    return v
            for lo, hi, v in src.ranges:
                if (lo is None or k >= lo) and (hi is None or k <= hi):
                    return v
            return src.default
        return src.gain * x + src.bias
    if src.kind == "toggle":
        return n % 2
    if src.kind == "counter":
        return n % (src.counter_max + 1)
    return src.value or 0.0


class FakePlant:
    """The plant's side of a mapping on virtual buses: sends the mapping's sent
    messages every cycle (a thread on a 2 ms tick), keeps the TCU's frames."""

    def __init__(self, mapping, channels, outputs=None):
        self.mapping = mapping
        self.outputs = dict(STANDSTILL if outputs is None else outputs)
        self.buses = {name: can.Bus(interface="virtual", channel=ch) for name, ch in channels.items()}
        self.tables = {}
        self.where = {}
        for b in mapping.buses:
            msgs = mapping.codec_order(b.name)
            self.tables[b.name] = CodecTable([(m.message, m.protection) for m in msgs])
            for i, m in enumerate(msgs):
                self.where[key(m)] = (b.name, i, m)
        self.sent_messages = [m for m in mapping.messages if m.direction == "send"]
        self.frames = {key(m): [] for m in mapping.messages if m.direction == "receive"}
        self.counter = {key(m): 0 for m in self.sent_messages}
        self.enabled = {key(m): True for m in self.sent_messages}
        self.lock = threading.Lock()
        self.send_lock = threading.Lock()        # enable() returns between two frames, never in one
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._send_loop, daemon=True)]
        self.threads += [threading.Thread(target=self._recv_loop, args=(name,), daemon=True) for name in self.buses]
        for t in self.threads:
            t.start()

    def encode(self, k, counter, **overrides):
        bus, i, m = self.where[k]
        with self.lock:
            values = {s.name: plant_value(s.source, self.outputs, counter) for s in m.signals
                      if s.protection_field is None}
        values.update(overrides)
        return self.tables[bus].encode(i, values, counter=counter)

    def inject(self, k, data):
        bus, _, m = self.where[k]
        self.buses[bus].send(can.Message(arbitration_id=m.frame_id, data=data, is_extended_id=m.is_extended))

    def send_one(self, k):
        with self.lock:
            n = self.counter[k]
            self.counter[k] = n + 1
        self.inject(k, self.encode(k, n))

    def set(self, **outputs):
        with self.lock:
            self.outputs.update(outputs)

    def enable(self, names, on=True):
        """Starts or stops sending these messages; once it returns, none is sent (or half sent)."""
        with self.send_lock:
            for k in names:
                self.enabled[k] = on

    def _send_loop(self):
        t0 = time.monotonic()
        tick = 0
        while not self.stop.is_set():
            with self.send_lock:
                for m in self.sent_messages:
                    every = max(1, int(round(m.cycle_ms / 2.0)))
                    if tick % every == 0 and self.enabled[key(m)]:
                        self.send_one(key(m))
            tick += 1
            self.stop.wait(max(0.0, t0 + tick * 0.002 - time.monotonic()))

    def _recv_loop(self, bus_name):
        bus = self.buses[bus_name]
        table = self.tables[bus_name]
        msgs = self.mapping.codec_order(bus_name)
        while not self.stop.is_set():
            msg = bus.recv(timeout=0.05)
            if msg is None:
                continue
            i = table.find(msg.arbitration_id, msg.is_extended_id)
            if i >= 0 and key(msgs[i]) in self.frames:
                with self.lock:
                    self.frames[key(msgs[i])].append(bytes(msg.data))

    def tcu_frames(self, k):
        with self.lock:
            return list(self.frames[k])

    def decoded(self, k, frames=None):
        bus, i, _ = self.where[k]
        return [self.tables[bus].decode(i, d) for d in (self.tcu_frames(k) if frames is None else frames)]

    def close(self):
        self.stop.set()
        for t in self.threads:
            t.join(timeout=5.0)
        for bus in self.buses.values():
            bus.shutdown()


@pytest.fixture(scope="module")
def vehicle():
    return mapping_mod.load(mapping_mod.find_mapping("vehicle"))


@pytest.fixture
def channel():
    return f"tcu-map-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def plant(vehicle, channel):
    p = FakePlant(vehicle, vehicle.channels(channel))
    yield p
    p.close()


def fresh(tcu):
    return not tcu.stale and tcu.t_s > 0


def vehicle_copy(tmp_path, edit):
    """vehicle.toml in tmp_path with absolute DBC paths and ``edit(text)`` applied."""
    src = mapping_mod.find_mapping("vehicle")
    here = os.path.dirname(src)
    with open(src, encoding="utf-8") as f:
        text = f.read()
    text = re.sub(r'dbc = "([^"]+)"',
                  lambda m: f'dbc = "{os.path.normpath(os.path.join(here, m.group(1)))}"', text)
    path = tmp_path / "vehicle-edited.toml"
    path.write_text(edit(text), encoding="utf-8")
    return str(path)


def without_pressures(text):
    """The plant sends IO_Pressures with no signal mapped: nothing carries the clutch pressures."""
    head = "[message.IO_Pressures.signals]\n"
    start = text.index(head)
    end = text.index("\n\n", start)
    return text[:start] + text[end + 2:]


# ------------------------------------------------------------------ reading
def test_reads_sensors_through_the_vehicle_mapping_on_both_buses(vehicle, channel, plant):
    plant.set(engine_speed_rpm=2000.0, vehicle_speed_kmh=36.0, engine_torque_nm=140.0,
              input_shaft1_speed_rpm=1500.0, clutch1_pressure_bar=4.5, fork2_position_mm=-3.2,
              brake_pedal_pct=0.0, accel_pedal_pct=20.0, sync2_state=2.0, selector_lever=1.0,
              trans_oil_temp_degc=47.0)
    with CanTcu.open("virtual", channel, mapping=vehicle) as tcu:
        assert tcu.channels == {"pt": channel, "io": f"{channel}-io"}
        assert tcu.wait_for(lambda t: fresh(t) and t.sensors.get("EngineSpeed", 0) > 1000, timeout=WAIT_S)
        s = dict(tcu.sensors)
        assert s["EngineSpeed"] == pytest.approx(2000.0, abs=0.25)            # pt: ECM_Speed
        assert s["VehicleSpeed"] == pytest.approx(36.0, abs=0.01)             # pt: ESP_Motion, magnitude
        assert s["EngineTorque"] == pytest.approx(140.0, abs=0.3)             # % of 280 Nm, back in Nm
        assert s["AccelPedal"] == pytest.approx(20.0, abs=0.4)
        assert s["BrakePedal"] == 0.0
        assert s["InputShaft1Speed"] == pytest.approx(1500.0, abs=0.5)        # io: IO_ShaftSpeeds
        assert s["ClutchPressure1"] == pytest.approx(4.5, abs=0.05)           # io: IO_Pressures
        assert s["ForkPosition2"] == pytest.approx(-3.2, abs=0.05)            # io: IO_Forks
        assert s["SyncState2"] == 2
        assert s["SelectorLever"] == 1                                         # pt: GW_Selector, R
        assert s["TransOilTemp"] == 47.0                                       # io: IO_Temperatures
        # backwards: the speed's sign comes back from VehicleDirection
        plant.set(vehicle_speed_kmh=-5.0, engine_speed_rpm=900.0)
        assert tcu.wait_for(lambda t: t.sensors.get("EngineSpeed", 0) < 1000, timeout=WAIT_S)
        assert tcu.wait_for(lambda t: t.sensors.get("VehicleSpeed", 0) < 0, timeout=WAIT_S)
        assert tcu.sensors["VehicleSpeed"] == pytest.approx(-5.0, abs=0.01)
        rep = tcu.report()
    assert rep["mapping"] == vehicle.path
    assert set(rep["received"]) == {key(m) for m in vehicle.messages if m.direction == "send"}
    assert set(rep["sent"]) == set(TCU_SENDS)
    assert rep["stale"]["needed"] == list(NEEDED)
    for k in NEEDED:
        assert rep["received"][k]["accepted"] >= 1
        assert rep["received"][k]["rejected"] == {"bad_length": 0, "bad_crc": 0, "bad_counter": 0}
    assert rep["received"]["io:IO_ShaftSpeeds"]["bus"] == "io"
    assert rep["unknown_frames"] == 0
    assert rep["sim_time_s"] is None                    # the vehicle matrix has no simulator status
    assert rep["buses"]["io"]["channel"] == f"{channel}-io" and rep["buses"]["pt"]["bitrate"] == 500000


def test_at_standstill_it_preselects_and_sends_what_it_decided_through_the_matrix(vehicle, channel, plant):
    with CanTcu.open("virtual", channel, mapping=vehicle) as tcu:
        assert tcu.wait_for(lambda t: fresh(t) and t.commands["ForkForce1"] > 0, timeout=WAIT_S)
        n = len(plant.tcu_frames("io:TCU_ForkForces"))
        assert wait_until(lambda: len(plant.tcu_frames("io:TCU_ForkForces")) > n + 2, timeout=WAIT_S)
        assert tcu.logic.phase == "standstill"
        forks = plant.decoded("io:TCU_ForkForces")[-1]
        valves = plant.decoded("io:TCU_ValveCurrents")[-1]
        gear = plant.decoded("pt:TCU_Gear")[-1]
        torque = plant.decoded("pt:TCU_TorqueReq")[-1]
    assert forks["ForkActuatorForce1"] > 0                 # 1st being pre-selected, brake on
    assert valves["ValveCurrentK1"] == 0 and valves["ValveCurrentK2"] == 0
    assert gear["GearTarget"] == 1                         # TargetGear, recorded as target_gear
    assert torque["TrqReqActive"] == 0


# ------------------------------------------------------------------ sending
def test_sends_its_messages_at_their_cycle_times_with_valid_protection(vehicle, channel, plant):
    with CanTcu.open("virtual", channel, mapping=vehicle) as tcu:
        assert tcu.wait_for(lambda t: t.sent("pt:TCU_Info") >= 3 and fresh(t), timeout=WAIT_S)
    rep = tcu.report()
    counts = {}
    for k in TCU_SENDS:
        bus, i, m = plant.where[k]
        frames = plant.tcu_frames(k)
        counts[k] = len(frames)
        assert frames, k
        assert rep["sent"][k]["frames"] == len(frames) and rep["sent"][k]["errors"] == 0
        table, state = plant.tables[bus], plant.tables[bus].new_state()
        assert [table.check(i, d, state) for d in frames] == ["ok"] * len(frames), k
        counter = m.protection.counter_signal
        if counter:                                        # lossless bus: +1 per frame, wrapping
            values = [int(v[counter]) for v in plant.decoded(k, frames)]
            modulus = 15 if m.protection.kind == "p1" else 16
            assert all((b - a) % modulus == 1 for a, b in zip(values, values[1:])), (k, values)
    # the 2 ms message at every executed task tick, the 10 ms ones every 5th period and
    # TCU_Info (100 ms) every 50th, counted in periods (executed + skipped ticks: a slower
    # message whose tick was skipped goes out at the next one), plus the final safe frame
    ticks, periods = rep["ticks"], rep["ticks"] + rep["skipped_ticks"]
    assert abs(counts["io:TCU_ValveCurrents"] - ticks) <= 2, (counts, ticks)
    for k in ("io:TCU_ForkForces", "pt:TCU_TorqueReq", "pt:TCU_Gear"):
        assert abs(counts[k] - periods / 5) <= 2, (k, counts, periods)
    assert abs(counts["pt:TCU_Info"] - periods / 50) <= 2, (counts, periods)
    assert rep["final_safe_frames"] is True


# ------------------------------------------------------------------ checking what it receives
def test_a_bad_crc_a_counter_jump_and_unknown_ids_are_counted_per_message(vehicle, channel, plant):
    # slow motion (time scale 0.1): 1 s timeouts, so the rejected frames are the cause seen first
    with CanTcu.open("virtual", channel, mapping=vehicle, time_scale=0.1) as tcu:
        assert tcu.wait_for(fresh, timeout=WAIT_S)
        episodes = tcu.report()["stale"]["episode_count"]
        for k in ("pt:ECM_Speed", "io:IO_ShaftSpeeds"):           # xor + counter; the contract's CRC
            plant.enable([k], False)
            n = plant.counter[k]
            good = plant.encode(k, n)
            bad_crc = bytearray(good)
            m = plant.where[k][2]
            bad_crc[m.message.get_signal_by_name(m.protection.crc_signal).start // 8] ^= 0x5A
            plant.inject(k, bytes(bad_crc))
            plant.inject(k, plant.encode(k, n + 4))               # the counter jumps by 5
            assert tcu.wait_for(lambda t, k=k: t.counts(k)["bad_crc"] == 1 and t.counts(k)["bad_counter"] == 1,
                                timeout=WAIT_S), tcu.counts(k)
            plant.inject(k, good)                                 # the next counter: accepted again
            assert tcu.wait_for(lambda t, k=k: t.counts(k)["accepted"] > 0 and t.peer.rx_snapshot()[k][2] == 0,
                                timeout=WAIT_S)
            plant.counter[k] = n + 1
            plant.enable([k], True)
        assert tcu.report()["stale"]["episode_count"] == episodes and not tcu.stale
        # a frame the plant does not send on that bus: unknown, counted per bus
        plant.buses["io"].send(can.Message(arbitration_id=0x7AB, data=bytes(8), is_extended_id=False))
        plant.buses["pt"].send(can.Message(arbitration_id=0x80, data=bytes(8), is_extended_id=False))  # io id
        assert tcu.wait_for(lambda t: t.report()["unknown_frames"] >= 2, timeout=WAIT_S)
        # REJECTS_TO_STALE bad frames in a row: stale, the rejections named as the cause
        k = "io:IO_Forks"
        plant.enable([k], False)
        for j in range(REJECTS_TO_STALE):
            data = bytearray(plant.encode(k, plant.counter[k] + j))
            data[0] ^= 0x01
            plant.inject(k, bytes(data))
        assert tcu.wait_for(lambda t: t.stale, timeout=WAIT_S)
        rep = tcu.report()
    assert rep["received"]["pt:ECM_Speed"]["rejected"] == {"bad_length": 0, "bad_crc": 1, "bad_counter": 1}
    assert rep["received"]["io:IO_ShaftSpeeds"]["rejected"] == {"bad_length": 0, "bad_crc": 1, "bad_counter": 1}
    assert rep["received"][k]["rejected"]["bad_crc"] == REJECTS_TO_STALE
    assert rep["stale"]["episodes"][-1]["causes"][k] == "rejected"
    assert rep["buses"]["io"]["unknown_frames"] == 1 and rep["buses"]["pt"]["unknown_frames"] == 1
    assert rep["stale"]["timeout_ms"]["pt:ESP_Accel"] == pytest.approx(2000.0)    # 10 cycles of 20 ms / 0.1
    summary = "\n".join(can_tcu.summary_lines(rep))
    assert "pt:ECM_Speed" in summary and "unknown ids: 2 (pt 1, io 1)" in summary


# ------------------------------------------------------------------ stale and safe
@pytest.mark.slow
def test_a_silent_plant_makes_it_stale_and_it_ends_on_the_mappings_safe_values(tmp_path, channel):
    # ValveCurrentLine drives the line valve at twice its value, safe 0.8 A: the signal's safe
    # value is 0.4 A; ForkActuatorForce1 drives fork 1 at twice its value
    def edit(text):
        text = text.replace('ValveCurrentLine = { input = "line_solenoid_current_a", safe = 0.0 }',
                            'ValveCurrentLine = { input = "line_solenoid_current_a", factor = 2.0, safe = 0.8 }')
        return text.replace('ForkActuatorForce1 = { input = "fork_force1_n", safe = 0.0 }',
                            'ForkActuatorForce1 = { input = "fork_force1_n", factor = 2.0, safe = 0.0 }')

    path = vehicle_copy(tmp_path, edit)
    m = mapping_mod.load(path)
    plant = FakePlant(m, m.channels(channel))
    try:
        tcu = CanTcu.open("virtual", channel, mapping=m)
        try:
            assert tcu.wait_for(lambda t: fresh(t) and t.commands["ForkForce1"] > 0, timeout=WAIT_S)
            force = tcu.commands["ForkForce1"]                          # pushing sleeve 1 (constant)
            n = len(plant.tcu_frames("io:TCU_ForkForces"))
            assert wait_until(lambda: len(plant.tcu_frames("io:TCU_ForkForces")) > n + 2, timeout=WAIT_S)
            sent = plant.decoded("io:TCU_ForkForces")[-1]["ForkActuatorForce1"]
            assert 2.0 * sent == force and force > 0                    # the mapping's scaling undone
            plant.enable(NEEDED, False)
            assert tcu.wait_for(lambda t: t.stale and t.logic.phase == "stale", timeout=WAIT_S)
            assert tcu.wait_for(lambda t: len(t.report()["stale"]["episodes"][-1]["causes"]) == len(NEEDED),
                                timeout=WAIT_S)
            n = len(plant.tcu_frames("io:TCU_ForkForces"))
            assert wait_until(lambda: len(plant.tcu_frames("io:TCU_ForkForces")) > n + 2, timeout=WAIT_S)
            forks = plant.decoded("io:TCU_ForkForces")[-1]
            assert all(forks[f"ForkActuatorForce{i}"] == 0 for i in range(1, 5))
            valves = plant.decoded("io:TCU_ValveCurrents")[-1]
            assert valves["ValveCurrentK1"] == 0 and valves["ValveCurrentK2"] == 0
            episode = tcu.report()["stale"]["episodes"][-1]
            assert set(episode["causes"]) == set(NEEDED) and set(episode["causes"].values()) == {"timeout"}
            plant.enable(NEEDED, True)
            assert tcu.wait_for(lambda t: not t.stale and t.commands["ForkForce1"] > 0, timeout=WAIT_S)
        finally:
            tcu.close()
        # the last frame of each TCU message: every target at its safe value
        assert wait_until(lambda: all(len(plant.tcu_frames(k)) == tcu.sent(k) for k in TCU_SENDS),
                          timeout=WAIT_S)
        last = {k: plant.decoded(k)[-1] for k in TCU_SENDS}
    finally:
        plant.close()
    valves = last["io:TCU_ValveCurrents"]
    assert valves["ValveCurrentK1"] == 0 and valves["ValveCurrentK2"] == 0
    assert valves["ValveCurrentLine"] == pytest.approx(0.4, abs=0.0001)
    assert all(last["io:TCU_ForkForces"][f"ForkActuatorForce{i}"] == 0 for i in range(1, 5))
    assert last["pt:TCU_TorqueReq"]["TrqReqValue"] == 0 and last["pt:TCU_TorqueReq"]["TrqReqActive"] == 0
    assert last["pt:TCU_Gear"]["GearTarget"] == 0
    rep = tcu.report()
    assert rep["final_safe_frames"] is True
    assert rep["last_commands"]["LineSolenoidCurrent"] == 0.8
    assert rep["stale"]["episodes"][-1]["end_s"] is not None


def test_the_bus_clock_follows_the_fastest_needed_message(vehicle, channel, plant):
    with CanTcu.open("virtual", channel, mapping=vehicle, clock="bus") as tcu:
        assert tcu._clock_message == "io:IO_ShaftSpeeds"
        assert tcu.wait_for(lambda t: fresh(t) and t.ticks >= 20, timeout=WAIT_S)
        plant.enable(["io:IO_ShaftSpeeds"], False)
        assert tcu.wait_for(lambda t: t.stale, timeout=WAIT_S)
        assert "io:IO_ShaftSpeeds" in tcu.report()["stale"]["episodes"][-1]["causes"]


# ------------------------------------------------------------------ refusals
def test_a_matrix_without_a_signal_the_tcu_needs_is_one_line_before_any_bus_opens(tmp_path, channel):
    from can.interfaces import virtual

    m = mapping_mod.load(vehicle_copy(tmp_path, without_pressures))
    with pytest.raises(MissingSignalError) as e:
        CanTcu.open("virtual", channel, mapping=m)
    text = str(e.value)
    assert "\n" not in text and "vehicle-edited.toml" in text and "clutch1_pressure_bar" in text
    assert channel not in virtual.channels and f"{channel}-io" not in virtual.channels


def test_buses_given_must_be_the_mappings(vehicle, channel):
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        with pytest.raises(ValueError, match="pt, io"):
            CanTcu(bus, mapping=vehicle, start=False)
        with pytest.raises(ValueError, match="pt, io"):
            CanTcu({"pt": bus, "body": bus}, mapping=vehicle, start=False)
    finally:
        bus.shutdown()


def run_main(capsys, *argv):
    code = can_tcu.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("args, says", [
    (["--mapping", "no-such-mapping.toml"], "no-such-mapping.toml"),
    (["--mapping", "vehicle", "--bus", "body=x"], "body"),
    (["--mapping", "vehicle", "--bus", "io"], "NAME=CHANNEL"),
    (["--mapping", "vehicle", "--bus", "io=a", "--bus", "io=b"], "twice"),
    (["--mapping", "vehicle", "--bitrate", "500000"], "--bitrate"),
    (["--bus", "io=x"], "--mapping"),
])
def test_cli_bad_mapping_options_are_one_line_exit_2(capsys, channel, args, says):
    code, _, err = run_main(capsys, "--interface", "virtual", "--channel", channel, "--duration", "1", *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and says in lines[0], err


def test_cli_on_socketcan_each_bus_after_the_first_needs_its_channel(capsys):
    code, _, err = run_main(capsys, "--interface", "socketcan", "--channel", "nowhere0", "--mapping", "vehicle")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "--bus io=CHANNEL" in lines[0], err


def test_cli_missing_signal_is_one_line_exit_2_and_opens_nothing(capsys, tmp_path, channel):
    from can.interfaces import virtual

    path = vehicle_copy(tmp_path, without_pressures)
    code, _, err = run_main(capsys, "--interface", "virtual", "--channel", channel, "--mapping", path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "clutch1_pressure_bar" in lines[0], err
    assert channel not in virtual.channels


def test_cli_runs_on_the_mappings_buses_and_writes_the_report(capsys, tmp_path, channel):
    path = tmp_path / "tcu.json"
    code, out, err = run_main(capsys, "--interface", "virtual", "--channel", channel, "--mapping", "vehicle",
                              "--bus", f"io={channel}-bench", "--duration", "0.3", "--report", path)
    assert code == 0, err
    data = json.loads(path.read_text())
    assert data["buses"]["pt"]["channel"] == channel and data["buses"]["io"]["channel"] == f"{channel}-bench"
    assert data["final_safe_frames"] is True and data["stale"]["now"] is True      # no plant there
    assert data["sent"]["io:TCU_ValveCurrents"]["frames"] > 0
    assert math.isclose(data["period_s"], 0.002)
    assert f"through {data['mapping']}" in out and "tx io:TCU_ValveCurrents" in out


def test_on_udp_multicast_its_own_frames_looped_back_are_not_traffic(vehicle, udp_group):
    """udp_multicast delivers the TCU's frames back to its own buses: they are
    dropped as echoes on each bus, never counted as unknown identifiers."""
    from waiting import free_udp_port

    address, port = udp_group
    io_address = address.rsplit(".", 1)[0] + f".{(int(address.rsplit('.', 1)[1]) % 254) + 1}"
    buses = {"pt": can.Bus(interface="udp_multicast", channel=address, port=port),
             "io": can.Bus(interface="udp_multicast", channel=io_address, port=free_udp_port())}
    try:
        with CanTcu(buses, mapping=vehicle) as tcu:
            assert tcu.wait_for(lambda t: t.peer.own_echoes >= 100 and t.sent("pt:TCU_Gear") >= 5,
                                timeout=WAIT_S)
            rep = tcu.report()
    finally:
        for bus in buses.values():
            bus.shutdown()
    assert rep["unknown_frames"] == 0 and rep["own_echoes_dropped"] >= 100
    assert rep["sent"]["io:TCU_ValveCurrents"]["frames"] > 0


def test_the_default_mapping_speaks_the_contract_with_the_contracts_test_plant(channel):
    """Through dct_hil.toml (the contract as a mapping) the mapped node and the
    contract's own stand-in plant (can_dbc.peer, side "plant") accept each
    other's frames."""
    from can_dbc.peer import CanPeer

    m = mapping_mod.load(mapping_mod.DEFAULT_MAPPING)
    plant = CanPeer.open("plant", interface="virtual", channel=channel,
                         values={"EngineSpeed": 750, "BrakePedal": 30, "SimTime": 12.5})
    try:
        with CanTcu.open("virtual", channel, mapping=m) as tcu:
            assert tcu.wait_for(lambda t: fresh(t) and t.sim_time_s is not None, timeout=WAIT_S)
            assert plant.wait_for(lambda p: all(p.counts(n)["accepted"] >= 3 for n in
                                                ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")),
                                  timeout=WAIT_S)
            sensors = dict(tcu.sensors)
            rep = tcu.report()
        counts = {n: plant.counts(n) for n in ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")}
    finally:
        plant.close()
    assert sensors["EngineSpeed"] == 750 and sensors["BrakePedal"] == 30
    assert rep["sim_time_s"] == pytest.approx(12.5, abs=0.01)
    assert all(r["rejected"] == {"bad_length": 0, "bad_crc": 0, "bad_counter": 0} for r in rep["received"].values())
    for n, c in counts.items():
        assert c["bad_crc"] == 0 and c["bad_counter"] == 0 and c["bad_length"] == 0, (n, c)
