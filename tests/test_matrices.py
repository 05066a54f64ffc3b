"""The example vehicle matrix (can_dbc/matrices/): a powertrain CAN and the bench's I/O bus.

vehicle_pt.dbc is a production-style powertrain CAN (engine, ABS/ESP, cluster,
gateway, TCU at 500 kbit/s); vehicle_io.dbc the bench's I/O bus (1 Mbit/s)
for what sits inside the transmission. Together they must carry everything
the reference TCU (tcu_stub) reads and writes through today's contract
(can_dbc/dct_hil.dbc): ``TCU_NEEDS`` names the carrier of each signal, and
the set of signals is taken from a closed-loop run of the TCU, not written
down by hand.
"""

import glob
import os
import re

import cantools
import pytest

from can_dbc import codec
from can_dbc.protection import parse_protection

MATRICES = os.path.join(os.path.dirname(codec.DBC_PATH), "matrices")
PT, IO = "vehicle_pt", "vehicle_io"

#: today's contract signal -> (matrix, message, signal) that carries it
TCU_NEEDS = {
    # what the reference TCU reads
    "EngineSpeed": (IO, "IO_ShaftSpeeds", "ClutchInputSpeed"),
    "InputShaft1Speed": (IO, "IO_ShaftSpeeds", "InputShaftSpeed1"),
    "InputShaft2Speed": (IO, "IO_ShaftSpeeds", "InputShaftSpeed2"),
    "OutputShaft1Speed": (IO, "IO_OutputSpeeds", "OutputShaftSpeed1"),
    "OutputShaft2Speed": (IO, "IO_OutputSpeeds", "OutputShaftSpeed2"),   # the diagnostics (gears 5, 6)
    "LinePressure": (IO, "IO_Pressures", "LinePressureSensor"),           # the diagnostics
    "ClutchPressure1": (IO, "IO_Pressures", "ClutchPressureK1"),
    "ClutchPressure2": (IO, "IO_Pressures", "ClutchPressureK2"),
    "ForkPosition1": (IO, "IO_Forks", "ForkTravel1"),
    "ForkPosition2": (IO, "IO_Forks", "ForkTravel2"),
    "ForkPosition3": (IO, "IO_Forks", "ForkTravel3"),
    "ForkPosition4": (IO, "IO_Forks", "ForkTravel4"),
    "SyncState1": (IO, "IO_Forks", "SynchroState1"),
    "SyncState2": (IO, "IO_Forks", "SynchroState2"),
    "SyncState3": (IO, "IO_Forks", "SynchroState3"),
    "SyncState4": (IO, "IO_Forks", "SynchroState4"),
    "VehicleSpeed": (PT, "ESP_Motion", "VehicleSpeed"),
    "AccelPedal": (PT, "ECM_Speed", "AccelPedalPos"),
    "BrakePedal": (PT, "ESP_Motion", "BrakePressure"),
    "EngineTorque": (PT, "ECM_Torque", "EngTorqueActual"),
    "RoadGrade": (PT, "ESP_Accel", "RoadInclination"),                   # read when carried
    "SelectorLever": (PT, "GW_Selector", "SelectorLever"),                # read when carried
    "TransOilTemp": (IO, "IO_Temperatures", "SumpOilTemp"),               # read when carried
    # what it sends
    "SolenoidCurrent1": (IO, "TCU_ValveCurrents", "ValveCurrentK1"),
    "SolenoidCurrent2": (IO, "TCU_ValveCurrents", "ValveCurrentK2"),
    "LineSolenoidCurrent": (IO, "TCU_ValveCurrents", "ValveCurrentLine"),
    "ForkForce1": (IO, "TCU_ForkForces", "ForkActuatorForce1"),
    "ForkForce2": (IO, "TCU_ForkForces", "ForkActuatorForce2"),
    "ForkForce3": (IO, "TCU_ForkForces", "ForkActuatorForce3"),
    "ForkForce4": (IO, "TCU_ForkForces", "ForkActuatorForce4"),
    "EngineTorqueRequest": (PT, "TCU_TorqueReq", "TrqReqValue"),
    "TorqueRequestActive": (PT, "TCU_TorqueReq", "TrqReqActive"),
    "TargetGear": (PT, "TCU_Gear", "GearTarget"),
    # of its diagnosis (TCU_Status, optional: sent where the matrix carries it)
    "ShiftActive": (PT, "TCU_Gear", "ShiftActive"),
    "TcuState": (PT, "TCU_Gear", "TcuState"),
}
#: what the reference TCU sends that a matrix may leave out: its diagnosis
OPTIONAL = {s.name for s in codec.message("TCU_Status").signals} - set(codec.E2E_SIGNALS)
#: what the reference TCU reads when a matrix carries it and otherwise takes as level
#: ground, D and warm oil: slow quantities, whose carrier may be slower (its cycle, ms,
#: here) and coarser than today's signal (a grade to 0.1 % within +-51 %)
OPTIONAL_READS = {"RoadGrade": 20, "SelectorLever": 20, "TransOilTemp": 100}
#: carriers in another unit or form than today's signal: what the mapping converts
CONVERTED = {
    "EngineTorque": "Nm -> % of EngineRefTorque (ECM_Info)",
    "EngineTorqueRequest": "% of EngineRefTorque -> Nm",
    "BrakePedal": "pedal % -> master cylinder pressure, bar (BrakePressed alongside)",
    "VehicleSpeed": "signed km/h -> km/h without sign, VehicleDirection alongside",
}
#: a raw "not available" code announced in a signal's comment ("0xFF: not available.")
CODE_RE = re.compile(r"\b0x([0-9A-Fa-f]+): ")
UNITLESS = (None, "", "-")


@pytest.fixture(scope="module", params=[True, False], ids=["strict", "lenient"])
def parsed(request):
    """Both matrices, parsed by cantools in strict mode (overlaps are errors) and not."""
    return {name: cantools.database.load_file(os.path.join(MATRICES, f"{name}.dbc"),
                                              database_format="dbc", strict=request.param)
            for name in (PT, IO)}


@pytest.fixture(scope="module")
def dbs():
    return {name: cantools.database.load_file(os.path.join(MATRICES, f"{name}.dbc"),
                                              database_format="dbc", strict=True)
            for name in (PT, IO)}


def _protection(msg):
    """The message's protection as its comment states it, parsed as a mapping file would."""
    found = re.search(r"Protection: ([^.]*)\.\s*$", msg.comment or "")
    assert found, f"{msg.name}: no 'Protection: ...' at the end of its comment"
    parts = [p.strip() for p in found.group(1).split(";")]
    spec = {"kind": parts[0]}
    for part in parts[1:]:
        key, _, value = part.partition(" ")
        value = value.strip()
        if key == "data_id":
            value = int(value, 16)
        elif key == "data_id_list":
            value = [int(x, 16) for x in value.split(",")]
        spec[key] = value
    return parse_protection(spec, msg.name)


def _bits(sig):
    """The message bits (byte * 8 + bit, bit 0 the least significant) a signal occupies."""
    if sig.byte_order == "little_endian":
        return {sig.start + i for i in range(sig.length)}
    bits, pos = set(), sig.start
    for _ in range(sig.length):
        bits.add(pos)
        pos = pos - 1 if pos % 8 else pos + 15   # Motorola: next lower bit, then the next byte's bit 7
    return bits


def _raw_limits(sig):
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def _bus_load(db):
    """Worst-case bus load (with bit stuffing) as a fraction of the matrix's bit rate."""
    bits_per_s = sum(codec.frame_bits_worst_case(m.length) * 1000.0 / m.cycle_time
                     for m in db.messages)
    return bits_per_s / db.dbc.attributes["Baudrate"].value


def _carrier(dbs, name):
    matrix, message, signal = TCU_NEEDS[name]
    msg = dbs[matrix].get_message_by_name(message)
    return msg, msg.get_signal_by_name(signal)


# --------------------------------------------------------------- parsing
def test_both_matrices_parse(parsed):
    assert {m.name for m in parsed[PT].messages} >= {"ECM_Torque", "ESP_WheelSpeeds", "TCU_Gear"}
    assert {m.name for m in parsed[IO].messages} >= {"TCU_ValveCurrents", "IO_ShaftSpeeds"}


def test_bit_rates_and_nodes(dbs):
    assert dbs[PT].dbc.attributes["Baudrate"].value == 500_000
    assert dbs[IO].dbc.attributes["Baudrate"].value == 1_000_000
    assert {n.name for n in dbs[PT].nodes} == {"ECM", "ESP", "IC", "GW", "TCU"}
    assert {n.name for n in dbs[IO].nodes} == {"PLANT", "TCU"}


@pytest.mark.parametrize("matrix", [PT, IO])
def test_classic_can_frames_with_a_cycle_time(dbs, matrix):
    db = dbs[matrix]
    ids = [m.frame_id for m in db.messages]
    assert len(ids) == len(set(ids))
    for m in db.messages:
        assert not m.is_extended_frame and m.frame_id <= 0x7FF and not m.is_fd, m.name
        assert m.length == 8, m.name
        assert m.cycle_time and m.cycle_time > 0, f"{m.name} has no GenMsgCycleTime"
        assert len(m.senders) == 1, m.name


def test_cycle_times(dbs):
    assert {m.cycle_time for m in dbs[PT].messages} == {10, 20, 100}
    io = {m.name: m.cycle_time for m in dbs[IO].messages}
    assert io["TCU_ValveCurrents"] == io["IO_ShaftSpeeds"] == io["IO_OutputSpeeds"] == 2
    assert io["IO_Pressures"] == 2
    assert io["IO_Forks"] == io["TCU_ForkForces"] == 10


@pytest.mark.parametrize("matrix", [PT, IO])
def test_no_signals_overlap_and_every_signal_fits(dbs, matrix):
    """Checked here independently of cantools' strict mode: bit by bit, per multiplexer branch."""
    for m in dbs[matrix].messages:
        branches = {None}
        for s in m.signals:
            branches |= set(s.multiplexer_ids or ())
        for branch in branches:
            used = {}
            for s in m.signals:
                if s.multiplexer_ids and branch not in s.multiplexer_ids:
                    continue
                bits = _bits(s)
                assert all(0 <= b < 8 * m.length for b in bits), f"{m.name}.{s.name} does not fit"
                for b in bits:
                    assert b not in used, f"{m.name}: {s.name} overlaps {used[b]} at bit {b}"
                    used[b] = s.name


def test_signal_names_are_unique_across_both_matrices(dbs):
    names = [s.name for db in dbs.values() for m in db.messages for s in m.signals]
    assert len(names) == len(set(names))


def test_byte_orders_signed_signals_and_a_multiplexed_message(dbs):
    signals = [s for m in dbs[PT].messages for s in m.signals]
    assert {s.byte_order for s in signals} == {"little_endian", "big_endian"}
    assert any(s.is_signed and s.byte_order == "big_endian" for s in signals)     # LongAccel
    assert any(s.is_signed and s.byte_order == "little_endian" for s in signals)  # torques
    wheel = dbs[PT].get_message_by_name("ESP_WheelSpeeds")
    assert {s.byte_order for s in wheel.signals} == {"big_endian"}
    muxed = [m for m in dbs[PT].messages if m.is_multiplexed()]
    assert [m.name for m in muxed] == ["TCU_Info"]
    info = muxed[0]
    mux = next(s for s in info.signals if s.is_multiplexer)
    branches = {i for s in info.signals for i in (s.multiplexer_ids or ())}
    assert branches == {0, 1, 2} and mux.name == "TCU_Info_Mux"
    # each branch encodes and decodes on its own
    for branch, values in {0: {"TransOilTemp": 90, "ClutchTempK1": 120, "ClutchTempK2": 110},
                           1: {"KissPointK1": 1.56, "KissPointK2": 1.27},
                           2: {"ShiftCount": 1234, "ActiveFaultCode": 0}}.items():
        data = info.encode({"TCU_Info_Mux": branch, **values})
        decoded = info.decode(data, decode_choices=False)
        assert decoded["TCU_Info_Mux"] == branch
        for name, value in values.items():
            assert decoded[name] == pytest.approx(value, abs=1e-3)


def test_motorola_wheel_speeds_round_trip(dbs):
    wheel = dbs[PT].get_message_by_name("ESP_WheelSpeeds")
    values = {"WheelSpeedFL": 101.5, "WheelSpeedFR": 0.02, "WheelSpeedRL": 327.64,
              "WheelSpeedRR": 55.0, "WheelDirFL": 0, "WheelDirFR": 1, "WheelDirRL": 0,
              "WheelDirRR": 1, "ESP_WheelSpeeds_Ctr": 9}
    decoded = wheel.decode(wheel.encode(values), decode_choices=False)
    assert decoded == pytest.approx(values, abs=1e-9)


# ----------------------------------------------------------- signals
@pytest.mark.parametrize("matrix", [PT, IO])
def test_ranges_fit_the_raw_values_and_units_are_known(dbs, matrix):
    units = {"", "%", "rpm", "km/h", "m/s2", "bar", "degC", "Nm", "km", "A", "N", "mm"}
    for m in dbs[matrix].messages:
        for s in m.signals:
            assert (s.unit or "") in units, f"{m.name}.{s.name}: unit {s.unit!r}"
            lo, hi = _raw_limits(s)
            phys = sorted((lo * s.scale + s.offset, hi * s.scale + s.offset))
            assert s.minimum is not None and s.maximum is not None, s.name
            assert phys[0] - 1e-9 <= s.minimum < s.maximum <= phys[1] + 1e-9, \
                f"{m.name}.{s.name}: range {s.minimum}..{s.maximum} outside {phys}"


@pytest.mark.parametrize("matrix", [PT, IO])
def test_not_available_codes_are_the_start_values(dbs, matrix):
    """A code named in a signal's comment ("0xFF: not available") is its GenSigStartValue
    and the top of its range (above every valid value, and sendable: a sender limits values
    to [minimum, maximum]); every start value other than 0 is such a code, a value
    description, or a constant of the protection (the Data ID nibble)."""
    coded = 0
    for m in dbs[matrix].messages:
        nibble = _protection(m).data_id_nibble_signal
        for s in m.signals:
            code = CODE_RE.search(s.comment or "")
            if code:
                coded += 1
                raw = int(code.group(1), 16)
                assert s.raw_initial == raw, f"{m.name}.{s.name}: start value {s.raw_initial}"
                assert raw * s.scale + s.offset == pytest.approx(s.maximum, abs=abs(s.scale) * 1e-6), \
                    f"{m.name}.{s.name}: code {raw} is not the top of the range {s.minimum}..{s.maximum}"
            elif s.raw_initial:
                assert s.name == nibble or (s.choices and s.raw_initial in s.choices), \
                    f"{m.name}.{s.name}: start value {s.raw_initial} unexplained"
    assert coded > 0


#: every shipped matrix, not only the two above: a new one is checked as it is added
SHIPPED = sorted(glob.glob(os.path.join(MATRICES, "*.dbc")))


def _start_raw(db, sig):
    """The raw value a sender starts with: GenSigStartValue, else the attribute's
    default (BA_DEF_DEF_), else None."""
    if sig.raw_initial is not None:
        return sig.raw_initial
    definition = db.dbc.attribute_definitions.get("GenSigStartValue") if db.dbc else None
    return None if definition is None else definition.default_value


def _code_problems(db):
    """One line per start value or value table entry of a signal that lies outside the
    signal's [minimum, maximum] or outside what its bits hold (raw units; the tolerance
    of cantools' own range check, 1e-6 of a step)."""
    problems = []
    for m in db.messages:
        for s in m.signals:
            codes = [("start value", _start_raw(db, s))]
            codes += [(f"value {int(k)} ({v})", k) for k, v in sorted((s.choices or {}).items())]
            lo, hi = (None, None) if s.is_float else _raw_limits(s)
            ends = [(x - s.offset) / s.scale for x in (s.minimum, s.maximum) if x is not None]
            rmin = min(ends) if s.minimum is not None and s.maximum is not None else None
            rmax = max(ends) if s.minimum is not None and s.maximum is not None else None
            if rmin is None and len(ends) == 1:         # one limit only
                end = ends[0]
                below = (s.minimum is not None) == (s.scale > 0)
                rmin, rmax = (end, None) if below else (None, end)
            for what, raw in codes:
                if raw is None:
                    continue
                where = f"{m.name}.{s.name}: {what}, raw {raw}"
                if not s.is_float and (raw != int(raw) or not lo <= raw <= hi):
                    problems.append(f"{where}, is not a value of its {s.length} bits "
                                    f"({'signed' if s.is_signed else 'unsigned'}: {lo}..{hi})")
                    continue
                if (rmin is not None and raw < rmin - 1e-6) or (rmax is not None and raw > rmax + 1e-6):
                    phys = raw * s.scale + s.offset
                    problems.append(f"{where} = {phys:.10g}{' ' + s.unit if s.unit else ''}, lies outside its range "
                                    f"{s.minimum}..{s.maximum}: a sender cannot send it")
    return problems


@pytest.mark.parametrize("path", SHIPPED, ids=os.path.basename)
def test_start_values_and_value_tables_lie_in_the_range_and_the_bits(path):
    """A sender (cantools, can_dbc.table's C codec) limits a value to the signal's
    [minimum, maximum] and to what its bits hold: a start value ("not available" code)
    or a value description outside them could never be sent."""
    db = cantools.database.load_file(path, database_format="dbc", strict=True)
    assert not _code_problems(db), "\n".join(_code_problems(db))


@pytest.mark.parametrize("change, problems", [
    (("[0|16383.75]", "[0|16383.5]"),
     ["ECM_Speed.EngineSpeed: start value, raw 65535 = 16383.75 rpm, lies outside its range 0..16383.5"]),
    (("12|4@1- (1,0) [-1|7]", "12|4@1- (1,0) [-1|6]"),
     ["TCU_Gear.GearEngaged: start value, raw 7 = 7, lies outside its range -1..6",
      "TCU_Gear.GearEngaged: value 7 (not available), raw 7 = 7, lies outside its range -1..6"]),
    (("(1,0) [0|3] \"\" TCU,GW", "(1,0) [0|2] \"\" TCU,GW"),
     ["ECM_Torque.TrqIntervState: value 3 (request refused), raw 3 = 3, lies outside its range 0..2"]),
    (("SelectorDisplay 15;", "SelectorDisplay 16;"),
     ["TCU_Gear.SelectorDisplay: start value, raw 16, is not a value of its 4 bits (unsigned: 0..15)"]),
    (("[-51.2|51.1]", "[1|51.1]"),       # no GenSigStartValue: the default, raw 0
     ["ESP_Accel.RoadInclination: start value, raw 0 = 0 %, lies outside its range 1..51.1"]),
])
def test_the_range_check_finds_a_code_outside(change, problems):
    """The check above on a copy of vehicle_pt.dbc with one range or start value broken."""
    with open(os.path.join(MATRICES, f"{PT}.dbc"), encoding="utf-8") as f:
        text = f.read()
    old, new = change
    assert text.count(old) == 1
    db = cantools.database.load_string(text.replace(old, new), database_format="dbc")
    found = _code_problems(db)
    assert len(found) == len(problems), found
    for line, problem in zip(found, problems):
        assert line.startswith(problem), found


@pytest.mark.parametrize("path", SHIPPED, ids=os.path.basename)
def test_start_values_are_sent_as_they_are(path):
    """Every message encoded with its signals' start values (each multiplexer branch in
    turn) by cantools (strict range check) and by the C table codec carries exactly the
    raw start values."""
    from can_dbc.table import CodecTable

    db = cantools.database.load_file(path, database_format="dbc", strict=True)
    table = CodecTable(list(db.messages))
    for i, m in enumerate(db.messages):
        mux = next((s for s in m.signals if s.is_multiplexer), None)
        branches = sorted({b for s in m.signals for b in (s.multiplexer_ids or ())}) or [None]
        for branch in branches:
            raw = {s.name: _start_raw(db, s) or 0 for s in m.signals
                   if not s.multiplexer_ids or branch in s.multiplexer_ids}
            if mux is not None:
                raw[mux.name] = branch
            values = {name: r * m.get_signal_by_name(name).scale + m.get_signal_by_name(name).offset
                      for name, r in raw.items()}
            for who, data in (("cantools", m.encode(values, strict=True)),
                              ("C table codec", table.encode(i, values))):
                sent = m.decode(data, decode_choices=False, scaling=False)
                assert sent == raw, f"{m.name} (branch {branch}), {who}: sent {sent}, start values {raw}"


def test_the_plants_values_fit_the_vehicle_signals(dbs):
    """What the model produces stays inside the signals that would carry it."""
    pt = dbs[PT]
    sig = {s.name: s for m in pt.messages for s in m.signals}
    assert sig["EngineSpeed"].maximum >= 7000                         # rev limit about 6800 rpm
    assert sig["VehicleSpeed"].maximum >= 250 and sig["WheelSpeedFL"].maximum >= 250
    assert sig["RoadInclination"].minimum <= -40 and sig["RoadInclination"].maximum >= 40
    assert sig["LongAccel"].minimum <= -12 and sig["LongAccel"].maximum >= 10
    # 280 Nm rated torque: full load 100 %, the drag torque a few % below 0
    assert sig["EngTorqueActual"].minimum <= -50 and sig["EngTorqueActual"].maximum >= 120
    assert sig["EngineRefTorque"].maximum >= 280


# ------------------------------------------------------------ protection
def test_every_message_states_its_protection(dbs):
    kinds = {matrix: {m.name: _protection(m).kind for m in db.messages}
             for matrix, db in dbs.items()}
    pt, io = kinds[PT], kinds[IO]
    # powertrain: E2E Profile 1 on some, XOR on others, one counter alone, nothing at 100 ms
    assert {k for k in pt.values()} == {"p1", "xor", "counter", "none"}
    assert sum(k == "counter" for k in pt.values()) == 1
    assert sum(k == "p1" for k in pt.values()) >= 2 and sum(k == "xor" for k in pt.values()) >= 2
    for m in dbs[PT].messages:
        assert (pt[m.name] == "none") == (m.cycle_time == 100), m.name
    # the bench's I/O: the project's protection, and E2E Profile 2 on the valve currents
    assert set(io.values()) == {"dct", "p2"}
    assert io["TCU_ValveCurrents"] == "p2"
    p1_modes = {_protection(m).data_id_mode for m in dbs[PT].messages if pt[m.name] == "p1"}
    assert p1_modes == {"both", "alt", "nibble"}


@pytest.mark.parametrize("matrix", [PT, IO])
def test_protection_signals_are_where_the_comments_say(dbs, matrix):
    data_ids = []
    for m in dbs[matrix].messages:
        p = _protection(m)
        names = {s.name for s in m.signals}
        for name in p.signals():
            assert name in names, f"{m.name}: protection signal {name} is not in the message"
        if p.crc_signal:
            crc = m.get_signal_by_name(p.crc_signal)
            bits = _bits(crc)
            assert crc.length == 8 and not crc.is_signed and len({b // 8 for b in bits}) == 1, \
                f"{m.name}: the checksum must fill one byte"
            if p.kind in ("p1", "p2", "dct"):
                assert bits == set(range(8)), f"{m.name}: CRC not in byte 0"
        if p.counter_signal:
            ctr = m.get_signal_by_name(p.counter_signal)
            assert ctr.length == 4 and not ctr.is_signed and min(_bits(ctr)) % 4 == 0, m.name
            assert ctr.maximum == (14 if p.kind == "p1" else 15), f"{m.name}: counter range"
            if p.kind in ("p1", "p2", "dct"):
                assert _bits(ctr) == set(range(8, 12)), f"{m.name}: counter not in byte 1 low nibble"
        if p.kind == "p1":
            data_ids.append(p.data_id)
            assert f"0x{p.data_id:04X}" in m.comment
            if p.data_id_mode == "nibble":
                nibble = m.get_signal_by_name(p.data_id_nibble_signal)
                assert p.data_id >> 12 == 0, "nibble mode: a 12-bit Data ID"
                assert nibble.length == 4 and nibble.raw_initial == (p.data_id >> 8) & 0xF
                assert _bits(nibble) == set(range(12, 16))
        if p.kind == "p2":
            assert len(p.data_id_list) == 16 and len(set(p.data_id_list)) == 16
        if p.kind == "none":
            assert not any("_CRC" in n or "_XOR" in n or "_Ctr" in n for n in names), m.name
    assert len(data_ids) == len(set(data_ids)), "Data IDs must differ between messages"


# -------------------------------------------------------------- bus load
@pytest.mark.parametrize("matrix, percent", [(PT, 20.0), (IO, 29.8)])
def test_worst_case_bus_load_is_under_half_the_bit_rate(dbs, matrix, percent):
    load = _bus_load(dbs[matrix])
    assert load < 0.5
    assert round(100 * load, 1) == percent     # the figures the README gives


# ------------------------------------------------------------- the TCU's needs
class _ReadSensors(dict):
    """The sensors dict of one TCU period, noting which signals the TCU reads."""

    read: set = set()

    def get(self, key, default=None):
        _ReadSensors.read.add(key)
        return super().get(key, default)

    def __getitem__(self, key):
        _ReadSensors.read.add(key)
        return super().__getitem__(key)


@pytest.fixture(scope="module")
def tcu_signals():
    """(read, written): today's contract signals the reference TCU reads and writes in
    a closed-loop run (launch at full pedal, an upshift, braking to a stop)."""
    from plant import Plant
    from tcu_stub.logic import TcuLogic
    from tcu_stub.offline import run_offline

    written = set()

    class Tcu(TcuLogic):
        def step(self, t_s, sensors):
            out = super().step(t_s, _ReadSensors(sensors))
            written.update(out)
            return out

    _ReadSensors.read = set()
    result = run_offline(Plant(), lambda t, o: (100.0, 0.0) if t < 5.0 else (0.0, 60.0), 7.0,
                         tcu=Tcu())
    assert result["shifts"], "the run must shift at least once"
    contract = {s.name for m in codec.messages() for s in m.signals}
    read = _ReadSensors.read - {"stale", "stale_messages"}
    assert read <= contract and written <= contract
    return read, written


def test_the_two_matrices_carry_everything_the_reference_tcu_uses(dbs, tcu_signals):
    read, written = tcu_signals
    optional = set(OPTIONAL_READS)
    assert set(TCU_NEEDS) - optional == (read | written) - (OPTIONAL - set(TCU_NEEDS)) - optional
    carriers = [TCU_NEEDS[n] for n in TCU_NEEDS]
    assert len(carriers) == len(set(carriers)), "one carrier per signal"
    for name in sorted(set(TCU_NEEDS)):
        today = codec.message(next(m.name for m in codec.messages()
                                   if name in [s.name for s in m.signals]))
        old = today.get_signal_by_name(name)
        msg, new = _carrier(dbs, name)
        where = f"{name} -> {msg.name}.{new.name}"
        if name in read or name in OPTIONAL_READS:
            assert msg.senders != ["TCU"] and "TCU" in new.receivers, where
        else:
            assert msg.senders == ["TCU"], where
        # as fresh as today (a slow quantity: as its carrier is listed)
        assert msg.cycle_time <= OPTIONAL_READS.get(name, today.cycle_time), where
        if name in CONVERTED:
            continue
        assert new.unit == old.unit or (new.unit in UNITLESS and old.unit in UNITLESS), where
        if name in OPTIONAL_READS and name != "SelectorLever":
            continue
        assert new.unit == old.unit or (new.unit in UNITLESS and old.unit in UNITLESS), where
        assert new.minimum <= old.minimum + 1e-9 and new.maximum >= old.maximum - 1e-9, where
        assert new.scale <= old.scale + 1e-12, f"{where}: coarser than today"
        if old.choices:         # today's values with today's codes (the vehicle's may have more)
            new_choices = {int(k): str(v) for k, v in new.choices.items()}
            assert {int(k): str(v) for k, v in old.choices.items()}.items() <= new_choices.items(), where


def test_converted_carriers_cover_what_the_plant_produces(dbs):
    pt = dbs[PT]
    torque = _carrier(dbs, "EngineTorque")[1]
    request = _carrier(dbs, "EngineTorqueRequest")[1]
    assert torque.unit == request.unit == "%" and torque.is_signed and request.is_signed
    assert pt.get_message_by_name("ECM_Info").get_signal_by_name("EngineRefTorque").unit == "Nm"
    brake = _carrier(dbs, "BrakePedal")[1]
    assert brake.unit == "bar" and brake.maximum >= 200
    speed_msg, speed = _carrier(dbs, "VehicleSpeed")
    assert speed.unit == "km/h" and not speed.is_signed
    direction = speed_msg.get_signal_by_name("VehicleDirection")
    assert {str(v) for v in direction.choices.values()} >= {"forward", "backward"}
    assert speed_msg.get_signal_by_name("BrakePressed").length == 1
