"""The CAN contract: the DBC, the Python codec and E2E protection, the table
codec of the default mapping (what the real-time loop serves) against the
Python codec, and the peer."""

import json
import math
import random
import re
import uuid

import pytest
import requires

from can_dbc import codec

# name -> (id, cycle ms, sender, {payload signal: (start bit, length, signed, scale, unit[, offset])})
EXPECTED = {
    "DCT_ShaftSpeeds": (0x100, 2, "PLANT", {
        "EngineSpeed": (16, 16, True, 0.5, "rpm"),
        "InputShaft1Speed": (32, 16, True, 0.5, "rpm"),
        "InputShaft2Speed": (48, 16, True, 0.5, "rpm")}),
    "DCT_OutputSpeeds": (0x101, 2, "PLANT", {
        "OutputShaft1Speed": (16, 16, True, 0.5, "rpm"),
        "OutputShaft2Speed": (32, 16, True, 0.5, "rpm")}),
    "DCT_Clutch": (0x102, 2, "PLANT", {
        "ClutchPressure1": (16, 16, False, 0.001, "bar"),
        "ClutchPressure2": (32, 16, False, 0.001, "bar"),
        "LinePressure": (48, 16, False, 0.001, "bar")}),
    "DCT_Shift": (0x110, 10, "PLANT", {
        **{f"ForkPosition{i}": (8 + 8 * i, 8, True, 0.1, "mm") for i in range(1, 5)},
        **{f"SyncState{i}": (46 + 2 * i, 2, False, 1, "-") for i in range(1, 5)},
        "TransOilTemp": (56, 8, False, 1, "degC", -40)}),
    "VEH_Motion": (0x120, 10, "PLANT", {
        "VehicleSpeed": (16, 16, True, 0.01, "km/h"),
        "LongAccel": (32, 16, True, 0.001, "m/s2"),
        "RoadGrade": (48, 16, True, 0.01, "%")}),
    "VEH_Driver": (0x121, 10, "PLANT", {
        "AccelPedal": (16, 8, False, 0.5, "%"),
        "BrakePedal": (24, 8, False, 0.5, "%"),
        "EngineTorque": (32, 16, True, 0.1, "Nm"),
        "SelectorLever": (48, 4, False, 1, "-")}),
    "SIM_Status": (0x1F0, 100, "PLANT", {
        "SimTime": (16, 24, False, 0.01, "s"),
        "OverrunCount": (40, 12, False, 1, "-"),
        "TurnaroundMax": (52, 10, False, 2, "us"),
        "SimState": (62, 2, False, 1, "-")}),
    "TCU_ClutchCmd": (0x080, 2, "TCU", {
        "SolenoidCurrent1": (16, 16, False, 0.0001, "A"),
        "SolenoidCurrent2": (32, 16, False, 0.0001, "A"),
        "LineSolenoidCurrent": (48, 16, False, 0.0001, "A")}),
    "TCU_ShiftCmd": (0x090, 10, "TCU", {
        f"ForkForce{i}": (4 + 12 * i, 12, True, 1, "N") for i in range(1, 5)}),
    "TCU_EngineCmd": (0x091, 10, "TCU", {
        "EngineTorqueRequest": (16, 16, True, 0.1, "Nm"),
        "TorqueRequestActive": (32, 1, False, 1, "-"),
        "TargetGear": (40, 4, True, 1, "-")}),
    "TCU_Status": (0x150, 10, "TCU", {
        "ActiveFaults": (16, 16, False, 1, "-"),
        "InhibitedGears": (32, 6, False, 1, "-"),
        "LimpHome": (38, 1, False, 1, "-"),
        "ShiftActive": (39, 1, False, 1, "-"),
        "TcuPhase": (40, 4, False, 1, "-"),
        "TcuState": (44, 3, False, 1, "-"),
        "FaultCount": (48, 8, False, 1, "-"),
        "LastFault": (56, 5, False, 1, "-")}),
}

PLANT_NAMES = sorted(codec.PLANT_SIGNAL_SOURCES)      # the messages the plant sends
TCU_NAMES = sorted(codec.TCU_SIGNAL_TARGETS)          # and those it receives

CHOICES = {
    "SyncState": {0: "disengaged", 1: "synchronizing", 2: "engaged"},
    "SimState": {0: "starting", 1: "running", 2: "stopping", 3: "fault"},
    "SelectorLever": {0: "P", 1: "R", 2: "N", 3: "D"},
}


def _values_at(msg, how, rng=None):
    vals = {}
    for s in codec.payload_signals(msg):
        if how == "min":
            vals[s.name] = s.minimum
        elif how == "max":
            vals[s.name] = s.maximum
        elif s.scale == 1 and isinstance(s.minimum, int):
            vals[s.name] = rng.randint(int(s.minimum), int(s.maximum))
        else:
            vals[s.name] = rng.uniform(s.minimum, s.maximum)
    return vals


# ---------------------------------------------------------------------------
# The DBC
# ---------------------------------------------------------------------------

def test_dbc_has_exactly_the_contract_messages_and_signals():
    db = codec.database()
    assert sorted(n.name for n in db.nodes) == ["PLANT", "TCU"]
    assert sorted(m.name for m in db.messages) == sorted(EXPECTED)
    for m in db.messages:
        frame_id, cycle_ms, sender, signals = EXPECTED[m.name]
        assert m.frame_id == frame_id, m.name
        assert not m.is_extended_frame and not m.is_fd, m.name
        assert m.cycle_time == cycle_ms, m.name
        assert m.senders == [sender], m.name
        assert sorted(s.name for s in m.signals) == sorted(["CRC", "AliveCounter", *signals]), m.name
        for s in codec.payload_signals(m):
            start, length, signed, scale, unit, *offset = signals[s.name]
            assert (s.start, s.length, s.is_signed, s.scale, s.offset) == \
                (start, length, signed, scale, offset[0] if offset else 0), s.name
            assert s.unit == unit, s.name
            other = "TCU" if sender == "PLANT" else "PLANT"
            assert s.receivers == [other], s.name


def test_every_message_is_classic_intel_with_crc_and_counter_in_the_exact_form():
    db = codec.database()
    definition = db.dbc.attribute_definitions["GenMsgCycleTime"]
    assert definition.kind == "BO_" and definition.type_name == "INT"
    for m in db.messages:
        assert m.length == 8 and m.length <= 8, m.name
        assert "GenMsgCycleTime" in m.dbc.attributes, m.name
        crc = m.get_signal_by_name("CRC")
        cnt = m.get_signal_by_name("AliveCounter")
        assert (crc.start, crc.length, crc.is_signed, crc.scale, crc.offset) == (0, 8, False, 1, 0)
        assert (cnt.start, cnt.length, cnt.is_signed, cnt.scale, cnt.offset) == (8, 4, False, 1, 0)
        for s in m.signals:
            assert s.byte_order == "little_endian", (m.name, s.name)
            assert s.unit, (m.name, s.name)
            assert s.minimum is not None and s.maximum is not None and s.minimum < s.maximum, (m.name, s.name)
            assert s.comment, (m.name, s.name)
            assert s.start + s.length <= 8 * m.length
            if s.name not in codec.E2E_SIGNALS:
                assert s.start >= 16, (m.name, s.name)     # payload from byte 2 on
                # the range is representable in the raw field
                raw_lo = -(1 << (s.length - 1)) if s.is_signed else 0
                raw_hi = (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1
                assert raw_lo * s.scale + s.offset <= s.minimum + 1e-9, s.name
                assert s.maximum <= raw_hi * s.scale + s.offset + 1e-9, s.name
        for prefix, choices in CHOICES.items():
            for s in m.signals:
                if s.name.startswith(prefix):
                    assert {k: str(v) for k, v in s.choices.items()} == choices, s.name


def test_bus_load_at_1_mbit_is_at_most_half():
    assert codec.frame_bits_worst_case(8) == 47 + 64 + (34 + 64 - 1) // 4 == 135
    load = codec.bus_load(1_000_000)
    expected = sum(135 * 1000.0 / m.cycle_time for m in codec.database().messages) / 1e6
    assert load == pytest.approx(expected)
    assert round(100 * load, 1) == 35.2              # the figure in the README
    assert load <= 0.5
    with pytest.raises(ValueError, match="bitrate"):
        codec.bus_load(0)


# ---------------------------------------------------------------------------
# Python codec and E2E
# ---------------------------------------------------------------------------

def test_crc8_sae_j1850_check_value():
    assert codec.crc8_j1850(b"123456789") == 0x4B
    assert codec.crc8_j1850(b"") == 0x00


def test_frame_crc_covers_id_low_id_high_and_bytes_1_to_end():
    data = bytes([0x00, 0x13, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77])
    for frame_id in (0x080, 0x1F0):
        ref = codec.crc8_j1850(bytes([frame_id & 0xFF, frame_id >> 8]) + data[1:])
        assert codec.e2e_crc(frame_id, data) == ref
        assert codec.e2e_crc(frame_id, b"\xff" + data[1:]) == ref            # byte 0 is not covered
        for i in range(1, 8):
            changed = bytearray(data)
            changed[i] ^= 0x01
            assert codec.e2e_crc(frame_id, changed) != ref, i
    assert codec.e2e_crc(0x0F0, data) != codec.e2e_crc(0x1F0, data)            # high byte of the id counts
    frame = codec.encode("TCU_ClutchCmd", {"SolenoidCurrent1": 0.5}, 9)
    assert frame[0] == codec.e2e_crc(0x080, frame) and frame[1] & 0x0F == 9


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_python_round_trip_min_max_random(name):
    msg = codec.message(name)
    rng = random.Random(name)
    cases = [_values_at(msg, "min"), _values_at(msg, "max")] + [_values_at(msg, "random", rng) for _ in range(50)]
    for k, vals in enumerate(cases):
        counter = k % 16
        data = codec.encode(name, vals, counter)
        assert len(data) == msg.length
        decoded_name, out = codec.decode(msg.frame_id, data)
        assert decoded_name == name
        assert out["AliveCounter"] == counter and out["CRC"] == codec.e2e_crc(msg.frame_id, data)
        for s in codec.payload_signals(msg):
            assert abs(out[s.name] - vals[s.name]) <= s.scale / 2 + 1e-9, (s.name, vals[s.name], out[s.name])
            assert s.minimum - 1e-9 <= out[s.name] <= s.maximum + 1e-9


def test_signals_not_given_are_sent_at_their_start_value():
    # SelectorLever starts in D (a plant that does not say otherwise drives forward), the
    # transmission oil warm (90 degC); every other signal starts at 0
    assert codec.start_value(codec.message("VEH_Driver").get_signal_by_name("SelectorLever")) == 3.0
    assert codec.start_value(codec.message("DCT_Shift").get_signal_by_name("TransOilTemp")) == 90.0
    out = codec.decode(0x121, codec.encode("VEH_Driver", {"AccelPedal": 10.0}, 0))[1]
    assert (out["SelectorLever"], out["BrakePedal"], out["AccelPedal"]) == (3, 0, 10.0)
    assert codec.decode(0x110, codec.encode("DCT_Shift", {}, 0))[1]["TransOilTemp"] == 90.0
    out = codec.decode(0x121, codec.encode("VEH_Driver", {"SelectorLever": "R"}, 0))[1]
    assert out["SelectorLever"] == 1
    with pytest.raises(ValueError, match="SelectorLever.*'X' is not one of its values"):
        codec.encode("VEH_Driver", {"SelectorLever": "X"}, 0)


def test_encode_limits_to_the_dbc_range_and_rejects_bad_input():
    out = codec.decode(0x080, codec.encode("TCU_ClutchCmd", {"SolenoidCurrent1": 7.0, "SolenoidCurrent2": -1.0,
                                                             "LineSolenoidCurrent": math.inf}, 0))[1]
    assert out["SolenoidCurrent1"] == pytest.approx(2.0) and out["SolenoidCurrent2"] == 0.0
    assert out["LineSolenoidCurrent"] == pytest.approx(2.0)
    out = codec.decode(0x1F0, codec.encode("SIM_Status", {"OverrunCount": 10**9, "TurnaroundMax": 5000}, 0))[1]
    assert out["OverrunCount"] == 4095 and out["TurnaroundMax"] == 2046          # saturating
    out = codec.decode(0x110, codec.encode("DCT_Shift", {"SyncState3": "synchronizing"}, 0))[1]
    assert out["SyncState3"] == 1 and out["ForkPosition1"] == 0.0                 # missing signals are 0
    assert codec.encode(0x091, {"TorqueRequestActive": 1}, 1) == codec.encode("TCU_EngineCmd",
                                                                              {"TorqueRequestActive": 1}, 1)
    for bad, match in (({"Nope": 1}, "has no signal Nope"), ({"SolenoidCurrent1": math.nan}, "NaN"),
                       ({"SolenoidCurrent1": "x"}, "not one of its values"), ({"CRC": 1}, "written by encode")):
        with pytest.raises(ValueError, match=match):
            codec.encode("TCU_ClutchCmd", bad, 0)
    with pytest.raises(ValueError, match="AliveCounter"):
        codec.encode("TCU_ClutchCmd", {}, 16)
    with pytest.raises(ValueError, match="unknown message"):
        codec.encode("NoSuchMessage", {}, 0)
    with pytest.raises(ValueError, match="unknown message frame id 0x7FF"):
        codec.decode(0x7FF, bytes(8))
    with pytest.raises(ValueError, match="7 data bytes"):
        codec.decode(0x080, bytes(7))


def test_e2e_receiver_rules_and_counts():
    rx = codec.E2eReceiver(sender="TCU")
    f = lambda c: codec.encode("TCU_EngineCmd", {"EngineTorqueRequest": 12.5}, c)  # noqa: E731 (a short probe, named for the lines below)
    assert rx.check(0x091, f(14)) == codec.OK                     # first frame: any counter
    assert rx.check(0x091, f(14)) == codec.BAD_COUNTER            # repeated
    assert rx.check(0x091, f(1)) == codec.BAD_COUNTER             # jump by 3 (14 -> 1)
    assert rx.check(0x091, f(15)) == codec.OK                     # +1
    assert rx.check(0x091, f(0)) == codec.OK                      # wrap 15 -> 0
    assert rx.check(0x091, f(2)) == codec.OK                      # +2 (one frame lost)
    assert rx.check(0x091, f(3)[:7]) == codec.BAD_LENGTH
    assert rx.check(0x091, f(3) + b"\x00") == codec.BAD_LENGTH
    bad = bytearray(f(3))
    bad[0] ^= 0xFF
    assert rx.check(0x091, bad) == codec.BAD_CRC
    bad = bytearray(f(3))
    bad[4] ^= 0x01
    assert rx.check(0x091, bad) == codec.BAD_CRC
    assert rx.check(0x091, f(3)) == codec.OK                      # rejects did not move the state
    assert rx.check(0x100, bytes(8)) == codec.UNKNOWN_ID           # a plant message
    assert rx.check(0x091, f(4), is_extended_id=True) == codec.UNKNOWN_ID
    assert rx.counts["TCU_EngineCmd"] == {"received": 11, "ok": 5, "bad_length": 2, "bad_crc": 2, "bad_counter": 2}
    assert rx.unknown == 2
    status, name, values = rx.receive(0x091, f(4))
    assert (status, name) == (codec.OK, "TCU_EngineCmd") and values["EngineTorqueRequest"] == 12.5
    rx.reset("TCU_EngineCmd")
    assert rx.check(0x091, f(4)) == codec.OK                      # after reset: any counter
    # counters of different messages are independent
    assert rx.check(0x080, codec.encode("TCU_ClutchCmd", {}, 4)) == codec.OK


# ---------------------------------------------------------------------------
# The loop's table codec (the default mapping) against the Python codec
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def served():
    """(mapping, CodecTable) of the default mapping: the tables the real-time
    loop serves the contract with (rt_loop/channels.py builds the same)."""
    requires.module("can_dbc._can_table")
    from can_dbc import mapping
    from can_dbc.table import CodecTable

    m = mapping.load(mapping.DEFAULT_MAPPING)
    (bus,) = m.buses
    return m, CodecTable([(x.message, x.protection) for x in m.codec_order(bus.name)])


def _sent(m):
    return [x.name for x in m.messages if x.direction == "send"]


def _received(m):
    return [x.name for x in m.messages if x.direction == "receive"]


def test_the_mapping_table_matches_the_dbc(served):
    m, t = served
    from can_dbc._can_table import lib

    assert sorted(_sent(m)) == sorted(codec.PLANT_SIGNAL_SOURCES) == sorted(x.name for x in codec.messages("PLANT"))
    assert sorted(_received(m)) == sorted(codec.TCU_SIGNAL_TARGETS) == sorted(x.name for x in codec.messages("TCU"))
    assert len(t) == len(codec.messages())
    for i, x in enumerate(m.codec_order("dct")):
        msg = codec.message(x.name)
        cm = t.table.messages[i]
        assert (cm.id, cm.extended, cm.fd, cm.length, cm.n_signals) == (
            msg.frame_id, 0, 0, msg.length, len(msg.signals)), x.name
        assert (t.index(x.name), t.find(msg.frame_id), x.cycle_ms) == (i, i, msg.cycle_time), x.name
        assert t.signal_names(i) == [s.name for s in msg.signals]
        assert cm.protection == lib.CT_PROT_DCT and cm.counter_modulus == 16
        assert cm.max_delta_counter == codec.COUNTER_MAX_JUMP
    assert t.find(0x7FF) == -1 and t.find(0x080, extended=True) == -1
    for status in codec.STATUSES:
        assert codec.STATUSES[getattr(lib, f"CT_RX_{status.upper()}")] == status


def test_table_crc_and_protection_equal_python(served):
    m, t = served
    from can_dbc._can_table import lib

    check = b"123456789"
    assert lib.ct_crc8_j1850(check, len(check)) == codec.crc8_j1850(check) == 0x4B
    rng = random.Random(7)
    for _ in range(200):
        frame_id = rng.randrange(0x800)
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 9)))
        covered = bytes([frame_id & 0xFF, frame_id >> 8]) + data[1:]
        assert lib.ct_crc8_j1850(covered, len(covered)) == codec.e2e_crc(frame_id, data)
    for i, msg in enumerate(t.messages):
        for _ in range(20):
            data = bytes(rng.randrange(256) for _ in range(msg.length))
            counter = rng.randrange(16)
            assert t.protect(i, data, counter) == codec.protect(msg.frame_id, data, counter), msg.name


@pytest.mark.parametrize("name", PLANT_NAMES)
def test_table_encoded_plant_frames_decode_in_python(served, name):
    _, t = served
    msg = codec.message(name)
    assert sorted(codec.PLANT_SIGNAL_SOURCES[name]) == sorted(s.name for s in codec.payload_signals(msg))
    rng = random.Random(name)
    cases = [_values_at(msg, "min"), _values_at(msg, "max")] + [_values_at(msg, "random", rng) for _ in range(40)]
    for k, vals in enumerate(cases):
        data = t.encode(name, vals, counter=k)          # the loop counts frames; 4 bits go out
        assert len(data) == msg.length
        assert data[0] == codec.e2e_crc(msg.frame_id, data) and data[1] & 0x0F == k % 16
        _, out = codec.decode(msg.frame_id, data)
        for s in codec.payload_signals(msg):
            assert abs(out[s.name] - vals[s.name]) <= s.scale + 1e-9, (s.name, vals[s.name], out[s.name])
        # the same values through the Python codec give the same bytes (and CRC)
        assert codec.encode(name, vals, k % 16) == data


@pytest.mark.parametrize("name", PLANT_NAMES)
def test_table_limits_plant_values_to_the_dbc_range(served, name):
    _, t = served
    msg = codec.message(name)
    for value, pick in ((1e12, "maximum"), (-1e12, "minimum"), (math.inf, "maximum"), (-math.inf, "minimum"),
                        (math.nan, None)):
        data = t.encode(name, {s.name: value for s in codec.payload_signals(msg)}, counter=0)
        _, out = codec.decode(msg.frame_id, data)
        for s in codec.payload_signals(msg):
            want = getattr(s, pick) if pick else min(max(0.0, s.minimum), s.maximum)
            assert out[s.name] == pytest.approx(want, abs=1e-9), (s.name, value)


@pytest.mark.parametrize("name", TCU_NAMES)
def test_python_encoded_tcu_frames_decode_in_the_table(served, name):
    m, t = served
    msg = codec.message(name)
    targets = codec.TCU_SIGNAL_TARGETS[name]
    assert sorted(targets) == sorted(s.name for s in codec.payload_signals(msg))
    # what each signal drives, and its safe value, as the mapping gives them to the loop
    mapped = m.message(name)
    for sig, (recorded, input_field) in targets.items():
        tgt = mapped.signal(sig).target
        assert (tgt.kind, tgt.name) == (("input", input_field) if input_field else ("record", recorded))
        assert (tgt.gain, tgt.bias, tgt.safe) == (1.0, 0.0, codec.TCU_SAFE_VALUES[name][sig])
    rng = random.Random(name)
    state = t.new_state()
    cases = [_values_at(msg, "min"), _values_at(msg, "max")] + [_values_at(msg, "random", rng) for _ in range(40)]
    for k, vals in enumerate(cases):
        data = codec.encode(name, vals, k % 16)
        assert t.check(name, data, state) == codec.OK
        got = t.decode(name, data)
        _, py = codec.decode(msg.frame_id, data)
        assert set(got) == set(py)
        for sig in targets:
            s = msg.get_signal_by_name(sig)
            assert abs(got[sig] - vals[sig]) <= s.scale + 1e-9 and got[sig] == py[sig], sig


def test_table_check_agrees_with_python_receiver(served):
    m, t = served
    received = {t.index(n) for n in _received(m)}
    rng = random.Random(3)
    rx = codec.E2eReceiver(sender="TCU")
    names = TCU_NAMES
    states = {name: t.new_state() for name in names}
    counters = {name: 0 for name in names}
    seen = set()
    for _ in range(600):
        name = rng.choice(names)
        msg = codec.message(name)
        step = rng.choice([1, 1, 1, 2, 0, 3, 7])
        counters[name] = (counters[name] + step) % 16
        data = bytearray(codec.encode(name, _values_at(msg, "random", rng), counters[name]))
        fault = rng.random()
        if fault < 0.1:
            data = data[:rng.randrange(0, 8)]
        elif fault < 0.2:
            data[rng.randrange(8)] ^= 1 << rng.randrange(8)
        frame_id = msg.frame_id if rng.random() > 0.05 else rng.choice([0x100, 0x7FF, 0x092])
        want = rx.check(frame_id, bytes(data))
        i = t.find(frame_id)                  # as the loop classifies a frame: by its identifier
        if i < 0 or i not in received:
            got = codec.UNKNOWN_ID
        else:
            got = t.check(i, bytes(data), states[t.messages[i].name])
        assert got == want
        seen.add(want)
        if want == codec.OK:
            assert states[name].last_counter == rx.last_counter[name]
    assert seen == set(codec.STATUSES)


# ---------------------------------------------------------------------------
# The peer on python-can's virtual bus
# ---------------------------------------------------------------------------

def _virtual_bus(channel):
    import can

    return can.Bus(interface="virtual", channel=channel)


def test_peers_exchange_protected_frames_and_count_rejects():
    from can_dbc.peer import CanPeer

    channel = "dct-" + uuid.uuid4().hex
    bus_tcu, bus_plant = _virtual_bus(channel), _virtual_bus(channel)
    plant = CanPeer(bus_plant, side="plant", values={"EngineSpeed": 2500.25, "SyncState2": "engaged"})
    tcu = CanPeer(bus_tcu, side="tcu", values={"SolenoidCurrent1": 0.6})
    try:
        tcu.set(ForkForce1=-800, EngineTorqueRequest=-42.0, TorqueRequestActive=1)
        with pytest.raises(ValueError, match="not a signal the TCU sends"):
            tcu.set(EngineSpeed=1.0)
        with pytest.raises(ValueError, match="NaN"):
            tcu.set(SolenoidCurrent2=math.nan)

        def all_seen(p, names, n=5):
            return all(p.counts(m)["accepted"] >= n for m in names)

        assert plant.wait_for(lambda p: all_seen(p, TCU_NAMES) and (p.last("TCU_ShiftCmd") or {}).get(
            "ForkForce1") == -800, timeout=10.0)
        assert tcu.wait_for(lambda p: all_seen(p, PLANT_NAMES, 1), timeout=10.0)
        assert plant.last("TCU_ClutchCmd")["SolenoidCurrent1"] == pytest.approx(0.6, abs=1e-4)
        assert plant.last("TCU_EngineCmd")["TorqueRequestActive"] == 1
        assert tcu.last("DCT_ShaftSpeeds")["EngineSpeed"] == 2500.0 or \
            tcu.last("DCT_ShaftSpeeds")["EngineSpeed"] == 2500.5
        assert tcu.last("DCT_Shift")["SyncState2"] == 2
        for name in TCU_NAMES:
            assert plant.counts(name)["received"] == plant.counts(name)["accepted"], name

        # bad frames from the TCU side are rejected and counted by the plant side
        good = codec.encode("TCU_ShiftCmd", {"ForkForce1": 1}, 0)
        tcu.inject(0x090, good[:6])                                   # wrong length
        tcu.inject(0x090, bytes([good[0] ^ 0x5A]) + good[1:])         # bad CRC
        tcu.inject(0x7FF, bytes(8))                                   # unknown id
        tcu.inject(0x090, good, is_extended_id=True)                  # 29-bit id: not ours
        last = plant.last("TCU_ShiftCmd")["AliveCounter"]
        tcu.inject(0x090, codec.encode("TCU_ShiftCmd", {}, (last + 8) % 16))   # counter jump
        assert plant.wait_for(lambda p: p.counts("TCU_ShiftCmd")["bad_length"] >= 1
                              and p.counts("TCU_ShiftCmd")["bad_crc"] >= 1
                              and p.counts("TCU_ShiftCmd")["bad_counter"] >= 1
                              and p.unknown_frames >= 2, timeout=10.0)
        with pytest.raises(ValueError, match="at most 8"):
            tcu.inject(0x090, bytes(9))
        with pytest.raises(ValueError, match="out of range"):
            tcu.inject(0x800, bytes(8))
        # the normal stream goes on being accepted
        before = plant.counts("TCU_ShiftCmd")["accepted"]
        assert plant.wait_for(lambda p: p.counts("TCU_ShiftCmd")["accepted"] >= before + 3, timeout=10.0)
    finally:
        tcu.close()
        plant.close()
        bus_tcu.shutdown()
        bus_plant.shutdown()
    rep = plant.report()
    json.dumps(rep)
    assert rep["injected"] == 0 and tcu.report()["injected"] == 5
    assert rep["received"]["TCU_ShiftCmd"]["rejected"]["bad_crc"] >= 1
    assert rep["received"]["TCU_ClutchCmd"]["mean_interval_ms"] > 0
    assert rep["sent"]["DCT_Clutch"]["frames"] >= 1


def test_peer_cli_runs_a_test_tcu_and_writes_the_report(tmp_path, capsys):
    from can_dbc.peer import CanPeer, main

    channel = "dct-" + uuid.uuid4().hex
    bus_plant = _virtual_bus(channel)
    plant = CanPeer(bus_plant, side="plant", values={"VehicleSpeed": 50.0, "SimState": "running"})
    report = tmp_path / "out.json"
    try:
        rc = main(["tcu", "--interface", "virtual", "--channel", channel, "--duration", "0.5",
                   "--set", "SolenoidCurrent1=0.6", "--set", "ForkForce2=-300", "--report", str(report)])
        assert rc == 0, capsys.readouterr().err
        seen_by_plant = plant.last("TCU_ClutchCmd")
    finally:
        plant.close()
        bus_plant.shutdown()
    rep = json.loads(report.read_text())
    assert rep["side"] == "tcu" and sorted(rep["received"]) == sorted(PLANT_NAMES)
    motion = rep["received"]["VEH_Motion"]
    assert motion["received"] >= 1 and motion["accepted"] == motion["received"]
    assert motion["last"]["VehicleSpeed"] == pytest.approx(50.0)
    assert set(motion["rejected"]) == {"bad_length", "bad_crc", "bad_counter"}
    assert rep["sent"]["TCU_ClutchCmd"]["values"]["SolenoidCurrent1"] == 0.6
    assert seen_by_plant is not None and seen_by_plant["SolenoidCurrent1"] == pytest.approx(0.6, abs=1e-4)
    assert "VEH_Motion" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["tcu", "--set", "Bogus=1"], "Bogus is not a signal the TCU sends"),
    (["tcu", "--set", "SolenoidCurrent1"], "expected SIGNAL=VALUE"),
    (["tcu", "--set", "SyncState1=engaged"], "not a signal the TCU sends"),
    (["plant", "--set", "SimState=flying"], "not one of its values"),
    (["tcu", "--duration", "-1"], "--duration must be a positive"),
    (["tcu", "--interface", "no_such_interface"], "cannot open no_such_interface bus"),
])
def test_peer_cli_bad_options_give_one_line_errors(args, message, capsys):
    from can_dbc.peer import main

    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


def test_peer_cli_refuses_an_unwritable_report(tmp_path, capsys):
    from can_dbc.peer import main

    missing = tmp_path / "nope" / "r.json"
    assert main(["tcu", "--interface", "virtual", "--channel", "x", "--report", str(missing)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_package_summary_runs(capsys):
    from can_dbc.__main__ import main

    assert main([]) == 0
    out = capsys.readouterr().out
    assert "TCU_ClutchCmd" in out and "bus load" in out
    assert "worst-case bus load at 1 Mbit/s: 35.23 %" in out


@pytest.mark.slow
def test_these_tests_print_nothing_into_pytests_progress():
    """Run this module's other tests in a pytest of their own: its output is
    pytest's progress and summary only (the CLI's own lines stay in capsys)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", __file__,
                        "-k", "not these_tests_print_nothing"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    lines = [line for line in r.stdout.splitlines() if line.strip()]
    progress = re.compile(r"^[.sxX]+\s*(\[\s*\d+%\])?$")
    stray = [line for line in lines[:-1] if not progress.match(line)]
    assert stray == [], stray
    assert re.match(r"^\d+ passed", lines[-1]), lines[-1]
