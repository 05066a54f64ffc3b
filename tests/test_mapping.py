"""Mapping files (can_dbc.mapping): the project's contract as a mapping, the
rules a mapping file is checked against (one line each, through the CLI with
exit 2), units and value tables, the template, a messy DBC read leniently,
the bus load."""

import dataclasses
import math
import os
import re

import pytest

from can_dbc import codec
from can_dbc import mapping as M
from dct_hil import cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ---------------------------------------------------------------------------
# a small vehicle matrix, written here
# ---------------------------------------------------------------------------

VEHICLE_DBC = """\
VERSION ""

NS_ :
	CM_
	BA_DEF_
	BA_
	VAL_
	BA_DEF_DEF_

BS_:

BU_: Motor ABS Kombi Getriebe Airbag

BO_ 640 Motor_1: 8 Motor
 SG_ Motor_1_CRC : 0|8@1+ (1,0) [0|255] "" Getriebe
 SG_ Motor_1_BZ : 8|4@1+ (1,0) [0|15] "" Getriebe
 SG_ Motordrehzahl : 16|16@1+ (0.25,0) [0|16383.75] "U/min" Getriebe
 SG_ Fahrpedal : 32|8@1+ (0.4,0) [0|101.6] "%" Getriebe
 SG_ Motormoment : 40|8@1+ (0.5,0) [0|127.5] "%" Getriebe
 SG_ Temperatur : 48|8@1+ (1,-48) [-48|207] "degC" Getriebe

BO_ 416 ABS_1: 8 ABS
 SG_ Geschwindigkeit : 0|16@1+ (0.01,0) [0|655.35] "m/s" Getriebe
 SG_ Raddrehzahl : 16|16@1+ (0.01,0) [0|655.35] "rad/s" Getriebe
 SG_ Bremsdruck : 32|16@1+ (0.1,0) [0|6553.5] "kPa" Getriebe

BO_ 800 Kombi_1: 8 Kombi
 SG_ Kodierung : 0|4@1+ (1,0) [0|15] "" Vector__XXX
 SG_ Toggle : 4|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ Zaehler : 8|4@1+ (1,0) [0|15] "" Vector__XXX
 SG_ Gang : 12|4@1+ (1,0) [0|15] "" Vector__XXX
 SG_ Licht : 16|2@1+ (1,0) [0|3] "" Vector__XXX

BO_ 1088 Getriebe_1: 8 Getriebe
 SG_ Getriebe_1_CRC : 0|8@1+ (1,0) [0|255] "" Motor
 SG_ Getriebe_1_BZ : 8|4@1+ (1,0) [0|15] "" Motor
 SG_ Strom_K1 : 16|16@1+ (1,0) [0|2000] "mA" Motor
 SG_ Zielgang : 32|4@1+ (1,0) [0|15] "" Motor
 SG_ Momentenanforderung : 40|8@1+ (1,0) [0|255] "%" Motor
 SG_ Reserve : 48|16@1+ (1,0) [0|65535] "" Motor

BO_ 1280 Airbag_1: 8 Airbag
 SG_ Crash : 0|16@1+ (1,0) [0|65535] "" Vector__XXX
 SG_ Crash2 : 8|16@1+ (1,0) [0|65535] "" Vector__XXX

BA_DEF_ "Baudrate" INT 0 1000000;
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_ SG_ "GenSigStartValue" INT 0 65535;
BA_DEF_DEF_ "Baudrate" 500000;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_DEF_DEF_ "GenSigStartValue" 0;
BA_ "Baudrate" 500000;
BA_ "GenMsgCycleTime" BO_ 640 10;
BA_ "GenMsgCycleTime" BO_ 416 20;
BA_ "GenMsgCycleTime" BO_ 800 100;
BA_ "GenMsgCycleTime" BO_ 1088 10;
BA_ "GenSigStartValue" SG_ 800 Licht 2;
VAL_ 800 Gang 7 "R" 0 "N" 1 "1" 2 "2" 15 "invalid" ;
"""

VEHICLE_TOML = """\
[[bus]]
name = "pt"
dbc = "vehicle.dbc"
bitrate = 500000
plant_nodes = ["Motor", "ABS", "Kombi"]
tcu_nodes = ["Getriebe"]

[message.Motor_1]
protection = { kind = "p1", crc = "Motor_1_CRC", counter = "Motor_1_BZ", data_id = 0x123 }

[message.Motor_1.signals]
Motordrehzahl = { output = "engine_speed_rpm" }
Fahrpedal = { output = "accel_pedal_pct", factor = 1.0, offset = 0.0 }
Motormoment = { output = "engine_torque_nm", unit = "%", reference = 350.0 }
Temperatur = { constant = 90 }

[message.ABS_1.signals]
Geschwindigkeit = { output = "vehicle_speed_kmh", unit = "m/s" }
Raddrehzahl = { output = "wheel_speed_fl_rpm", unit = "rad/s" }
Bremsdruck = { output = "clutch1_pressure_bar", unit = "kPa" }

[message.Kombi_1.signals]
Kodierung = { constant = 3 }
Toggle = { toggle = true }
Zaehler = { counter = 15 }
Gang = { output = "gear", table = { "-1" = "R", "0" = 0, "1" = 1, "2" = 2, default = "invalid" } }

[message.Getriebe_1]
timeout_cycles = 5
protection = { kind = "p1", crc = "Getriebe_1_CRC", counter = "Getriebe_1_BZ", data_id = 0x440 }

[message.Getriebe_1.signals]
Strom_K1 = { input = "solenoid_current1_a", unit = "mA", min = 0.0, max = 1.2, safe = 0.0 }
Zielgang = { record = "target_gear", table = { "7" = -1, "0" = 0, "1" = 1, "2" = 2, default = 0 } }
Momentenanforderung = { input = "engine_torque_request_nm", unit = "%", reference = 350.0 }
"""


@pytest.fixture
def vehicle(tmp_path):
    """(folder, write(toml=..., dbc=...) -> mapping path) with the vehicle matrix."""
    def write(toml=VEHICLE_TOML, dbc=VEHICLE_DBC, name="vehicle.toml"):
        (tmp_path / "vehicle.dbc").write_text(dbc)
        path = tmp_path / name
        path.write_text(toml)
        return str(path)
    return write


def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line(code, err, *fragments):
    assert code == 2, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dct-hil: error: "), err
    for f in fragments:
        assert f in lines[0], (f, err)


# ---------------------------------------------------------------------------
# the project's contract as a mapping
# ---------------------------------------------------------------------------

def _rt_timeout_cycles():
    text = open(os.path.join(ROOT, "rt_loop", "csrc", "rt_loop.h")).read()
    return int(re.search(r"#define RT_TIMEOUT_CYCLES (\d+)", text).group(1))


def _sim_status_fields():
    """The loop's status sources (RT_STATUS_* of rt_loop.h) in their index order, as names."""
    text = open(os.path.join(ROOT, "rt_loop", "csrc", "rt_loop.h")).read()
    fields = {int(v): name.lower() for name, v in re.findall(r"#define RT_STATUS_(\w+) (\d+)", text)}
    count = int(re.search(r"#define RT_N_STATUS (\d+)", text).group(1))
    assert sorted(fields) == list(range(count))
    return tuple(fields[i] for i in range(count))


def test_the_shipped_mapping_says_exactly_what_the_hard_wired_contract_says():
    m = M.load(M.DEFAULT_MAPPING)
    assert M.find_mapping("dct_hil") == M.DEFAULT_MAPPING
    (bus,) = m.buses
    assert (bus.dbc, bus.bitrate, bus.fd, bus.plant_nodes, bus.tcu_nodes) == (
        codec.DBC_PATH, 1_000_000, False, ("PLANT",), ("TCU",))
    sent = [x for x in m.messages if x.direction == "send"]
    received = [x for x in m.messages if x.direction == "receive"]
    assert {x.name for x in sent} == {x.name for x in codec.messages("PLANT")} == set(codec.PLANT_SIGNAL_SOURCES)
    assert {x.name for x in received} == {x.name for x in codec.messages("TCU")} == set(codec.TCU_SIGNAL_TARGETS)
    assert M.STATUS_FIELDS == _sim_status_fields()

    for x in m.messages:
        dbc = codec.message(x.name)
        assert (x.frame_id, x.length, x.is_extended, x.is_fd, x.cycle_ms) == (
            dbc.frame_id, dbc.length, False, False, dbc.cycle_time)
        p = x.protection
        assert (p.kind, p.crc_signal, p.counter_signal, p.max_delta_counter) == (
            "dct", codec.CRC_SIGNAL, codec.COUNTER_SIGNAL, codec.COUNTER_MAX_JUMP)
        assert [s.name for s in x.signals] == [s.name for s in dbc.signals]
        assert {s.name: s.protection_field for s in x.signals if s.protection_field} == {
            codec.CRC_SIGNAL: "crc", codec.COUNTER_SIGNAL: "counter"}

    for x in sent:
        assert x.timeout_cycles is None
        sources = {}
        for s in x.signals:
            if s.protection_field:
                continue
            src = s.source
            assert (src.gain, src.bias, src.table) == (1.0, 0.0, None), s.name
            sources[s.name] = {"output": "o.", "status": "st."}[src.kind] + src.name
        assert sources == codec.PLANT_SIGNAL_SOURCES[x.name]

    for x in received:
        assert x.timeout_cycles == _rt_timeout_cycles()
        targets, safe = {}, {}
        for s in x.signals:
            if s.protection_field:
                continue
            t = s.target
            assert (t.gain, t.bias, t.table, t.minimum, t.maximum) == (1.0, 0.0, None, None, None)
            if t.kind == "input":
                targets[s.name] = t.name
            else:
                targets[s.name] = None
                assert t.name == codec.TCU_SIGNAL_TARGETS[x.name][s.name][0]
            safe[s.name] = t.safe
        assert targets == {k: v[1] for k, v in codec.TCU_SIGNAL_TARGETS[x.name].items()}
        assert safe == codec.TCU_SAFE_VALUES[x.name]
        # a TCU may leave out its status (recorded only), nothing else
        assert x.optional == (x.name == "TCU_Status"), x.name
    assert not any(x.optional for x in sent)

    # the C codec's order: sent then received, each by identifier
    order = m.codec_order("dct")
    assert [x.direction for x in order] == ["send"] * 7 + ["receive"] * 4
    assert [x.frame_id for x in order[:7]] == sorted(x.frame_id for x in sent)
    assert [x.frame_id for x in order[7:]] == sorted(x.frame_id for x in received)
    # the bus load the contract's summary gives
    assert M.bus_load(m, "dct").load == pytest.approx(codec.bus_load(1_000_000))


def test_the_description_is_immutable():
    m = M.load()
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.messages[0].cycle_ms = 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.messages[0].signals[2].source.gain = 2.0
    assert isinstance(m.messages, tuple) and isinstance(m.messages[0].signals, tuple)


def test_check_and_show_of_the_shipped_mapping(capsys):
    code, out, err = run_cli(capsys, "mapping", "check", "dct_hil")
    assert code == 0, err
    assert "valid at 2000 Hz" in out
    assert "sends 7 messages" in out and "receives 4" in out
    assert "worst-case bus load at 1 Mbit/s: 35.2 %" in out
    assert "warning" not in out
    code, out, err = run_cli(capsys, "mapping", "show", M.DEFAULT_MAPPING)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("bus dct: dct_hil.dbc, classic CAN at 1 Mbit/s")
    assert any(re.match(r"\s+send\s+0x100 DCT_ShaftSpeeds \(8 B\) every 2 ms; protection dct", x)
               for x in lines)
    assert any(re.match(r"\s+receive 0x080 TCU_ClutchCmd .* timed out after 10 cycles \(20 ms\)", x)
               for x in lines)
    assert any(re.match(r"\s+EngineSpeed\s+rpm\s+<- engine_speed_rpm$", x) for x in lines)
    assert any(re.match(r"\s+SimTime\s+s\s+<- status sim_time_s$", x) for x in lines)
    assert any(re.match(r"\s+TargetGear\s+-\s+-> record target_gear, safe 0$", x) for x in lines)
    assert any(re.match(r"\s+receive 0x150 TCU_Status .* timed out after 10 cycles \(100 ms\), optional;", x)
               for x in lines)
    assert any(re.match(r"\s+CRC\s+-\s+protection crc$", x) for x in lines)


# ---------------------------------------------------------------------------
# a vehicle matrix: units, value tables, restbus
# ---------------------------------------------------------------------------

def test_a_vehicle_mapping_units_tables_and_restbus(vehicle, capsys):
    m = M.load(vehicle())
    motor, abs1, kombi, getr = (m.message(n) for n in ("Motor_1", "ABS_1", "Kombi_1", "Getriebe_1"))
    assert [x.name for x in m.codec_order("pt")] == ["ABS_1", "Motor_1", "Kombi_1", "Getriebe_1"]
    assert "Airbag_1" not in [x.name for x in m.messages]       # neither plant's nor TCU's
    # units
    src = motor.signal("Motordrehzahl").source                    # rpm == U/min
    assert (src.kind, src.name, src.gain, src.bias) == ("output", "engine_speed_rpm", 1.0, 0.0)
    assert motor.signal("Motormoment").source.gain == pytest.approx(100 / 350)
    assert abs1.signal("Geschwindigkeit").source.gain == pytest.approx(1 / 3.6)
    assert abs1.signal("Raddrehzahl").source.gain == pytest.approx(2 * math.pi / 60)
    assert abs1.signal("Bremsdruck").source.gain == pytest.approx(100.0)
    strom = getr.signal("Strom_K1").target
    assert (strom.kind, strom.name, strom.gain, strom.minimum, strom.maximum, strom.safe) == (
        "input", "solenoid_current1_a", pytest.approx(1e-3), 0.0, 1.2, 0.0)
    assert getr.signal("Momentenanforderung").target.gain == pytest.approx(3.5)   # % of 350 Nm
    # constants, toggle, counter, start values (restbus)
    assert motor.signal("Temperatur").source == M.Source("constant", value=90.0)
    assert kombi.signal("Toggle").source.kind == "toggle"
    assert kombi.signal("Zaehler").source.counter_max == 15
    assert kombi.signal("Licht").source == M.Source("start", value=2.0)      # GenSigStartValue
    assert getr.signal("Reserve").target is None
    # value tables, DBC value names for values
    gang = kombi.signal("Gang").source
    assert (gang.table, gang.default) == (((-1, 7.0), (0, 0.0), (1, 1.0), (2, 2.0)), 15.0)
    ziel = getr.signal("Zielgang").target
    assert (ziel.kind, ziel.name, ziel.table, ziel.default) == (
        "record", "target_gear", ((0, 0.0), (1, 1.0), (2, 2.0), (7, -1.0)), 0.0)
    # protection fields
    assert motor.protection.kind == "p1" and motor.protection.data_id == 0x123
    assert motor.signal("Motor_1_CRC").protection_field == "crc"
    assert (getr.timeout_cycles, motor.timeout_cycles) == (5, None)

    code, out, err = run_cli(capsys, "mapping", "show", vehicle())
    assert code == 0, err
    assert re.search(r"Motormoment\s+%\s+<- engine_torque_nm \[Nm -> % of 350 Nm\] x 0\.28571", out)
    assert re.search(r"Geschwindigkeit\s+m/s\s+<- vehicle_speed_kmh \[km/h -> m/s\] x 0\.27777", out)
    assert re.search(r"Gang\s+<- gear via table \{-1: 7, 0: 0, 1: 1, 2: 2, default: 15\}", out)
    assert re.search(r"Strom_K1\s+mA\s+-> solenoid_current1_a \[mA -> A\] x 0\.001, limited to 0 \.\. 1\.2, "
                     r"safe 0", out)
    assert re.search(r"Licht\s+= 2 \(start value\)", out)
    assert re.search(r"Zaehler\s+counter 0\.\.15 per frame", out)
    assert re.search(r"send\s+0x320 Kombi_1 \(8 B\) every 100 ms; no protection", out)


def test_value_table_ranges_and_magnitudes(vehicle):
    toml = VEHICLE_TOML.replace(
        'Gang = { output = "gear", table = { "-1" = "R", "0" = 0, "1" = 1, "2" = 2, default = "invalid" } }',
        'Gang = { output = "vehicle_speed_kmh", table = { "..-1" = 2, "0" = 0, "1..9" = 1, "10.." = 3, default = 15 } }')
    toml = toml.replace('Geschwindigkeit = { output = "vehicle_speed_kmh", unit = "m/s" }',
                        'Geschwindigkeit = { output = "vehicle_speed_kmh", unit = "m/s", abs = true }')
    m = M.load(vehicle(toml=toml))
    gang = m.message("Kombi_1").signal("Gang").source
    assert (gang.table, gang.ranges, gang.default) == (((0, 0.0),), ((None, -1, 2.0), (1, 9, 1.0), (10, None, 3.0)),
                                                       15.0)
    speed = m.message("ABS_1").signal("Geschwindigkeit").source
    assert speed.absolute and speed.gain == pytest.approx(1 / 3.6)
    assert not m.message("ABS_1").signal("Raddrehzahl").source.absolute
    with pytest.raises(M.MappingError, match=r"Kodierung\.abs: abs applies to output and status, not constant"):
        M.load(vehicle(toml=toml.replace("Kodierung = { constant = 3 }", "Kodierung = { constant = 3, abs = true }")))


def test_unit_conversions():
    assert M.conversion("degC", "K") == (1.0, 273.15)
    g, b = M.conversion("degC", "degF")
    assert (g * 100 + b) == pytest.approx(212.0)
    assert M.conversion("bar", "kPa") == (pytest.approx(100.0), 0.0)
    assert M.conversion("bar", "psi")[0] == pytest.approx(14.5037738)
    assert M.conversion("km/h", "mph")[0] == pytest.approx(0.621371192)
    assert M.conversion("rpm", "rad/s")[0] == pytest.approx(2 * math.pi / 60)
    assert M.conversion("A", "mA")[0] == pytest.approx(1000.0)
    assert M.conversion("mm", "m")[0] == pytest.approx(1e-3)
    assert M.conversion("KM/H", "m/s")[0] == pytest.approx(1 / 3.6)        # case from sloppy DBCs
    with pytest.raises(ValueError, match="cannot convert rpm"):
        M.conversion("rpm", "bar")
    with pytest.raises(ValueError, match="unknown unit 'furlong'"):
        M.conversion("furlong", "m")
    assert [M.unit_of_name(n) for n in ("engine_speed_rpm", "vehicle_speed_kmh", "vehicle_accel_mps2",
                                        "fork_force1_n", "solenoid_current1_a", "gear", "sim_time_s",
                                        "turnaround_max_us", "front_tyre_slip")] == [
        "rpm", "km/h", "m/s2", "N", "A", None, "s", "us", None]


# ---------------------------------------------------------------------------
# every rule: one line naming the file, the key and the cause; exit 2
# ---------------------------------------------------------------------------

def _sub(old, new):
    def edit(text):
        assert old in text, old
        return text.replace(old, new, 1)
    return edit


def _add(extra):
    return lambda text: text + extra


BAD_MAPPINGS = {
    "unknown message": (_add("\n[message.Motor_9]\ncycle_ms = 10\n"), None,
                        ["message.Motor_9:", "unknown message 'Motor_9' on bus pt", "did you mean Motor_1"]),
    "unknown signal": (_sub("Motordrehzahl = {", "Drehzahl = {"), None,
                       ["message.Motor_1.signals.Drehzahl:", "no signal 'Drehzahl'"]),
    "unknown output": (_sub('"engine_speed_rpm"', '"engine_sped_rpm"'), None,
                       ["message.Motor_1.signals.Motordrehzahl.output:", "unknown plant output 'engine_sped_rpm'",
                        "did you mean engine_speed_rpm"]),
    "unknown input": (_sub('"solenoid_current1_a"', '"solenoid_current9_a"'), None,
                      ["message.Getriebe_1.signals.Strom_K1.input:", "unknown plant input 'solenoid_current9_a'"]),
    "unknown status": (_sub("Kodierung = { constant = 3 }", 'Kodierung = { status = "uptime_s" }'), None,
                       ["signals.Kodierung.status:", "unknown status 'uptime_s'", "sim_time_s"]),
    "output on a received message": (_sub('Zielgang = { record = "target_gear",',
                                          'Zielgang = { output = "gear",'), None,
                                     ["message.Getriebe_1.signals.Zielgang.output:", "is received",
                                      "input or record"]),
    "overlapping signals in a used message": (
        None, _sub(" SG_ Fahrpedal : 32|8@1+", " SG_ Fahrpedal : 28|8@1+"),
        ["vehicle.dbc: message Motor_1:", "signals Motordrehzahl (bits 16-31) and Fahrpedal (bits 28-35) overlap",
         "sent on bus pt"]),
    "signal outside the frame": (None, _sub(" SG_ Reserve : 48|16@1+", " SG_ Reserve : 56|16@1+"),
                                 ["vehicle.dbc: message Getriebe_1:", "Reserve (bits 56-71) lies outside the 8-byte frame"]),
    "used message without a cycle time": (
        None, _sub('BA_ "GenMsgCycleTime" BO_ 800 100;\n', ""),
        ["message.Kombi_1.cycle_ms:", "has no cycle time", "give cycle_ms"]),
    "cycle time the loop cannot hit": (_add("\n[message.ABS_1]\ncycle_ms = 2.2\n"), None,
                                       ["message.ABS_1.cycle_ms:", "cycle time 2.2 ms",
                                        "whole number of the loop's 0.5 ms ticks at 2000 Hz"]),
    "identifier both sent and received": (
        None, _add("\nBO_ 640 Getriebe_2: 8 Getriebe\n SG_ X : 0|8@1+ (1,0) [0|255] \"\" Motor\n"
                   "BA_ \"GenMsgCycleTime\" BO_ 640 10;\n"),
        ["identifier 0x280 on bus pt is both sent (Motor_1) and received (Getriebe_2)"]),
    "value table without a default": (_sub(', default = "invalid" }', " }"), None,
                                      ["message.Kombi_1.signals.Gang.table:", "needs a default"]),
    "value table value outside the signal's range": (_sub('"2" = 2, default', '"2" = 16, default'), None,
                                                     ["signals.Gang.table.2:", "value 16 is outside signal Gang's range 0 .. 15"]),
    "overlapping value table keys": (_sub('"1" = 1, "2" = 2, default = "invalid"', '"1..3" = 1, "2" = 2, default = "invalid"'),
                                     None, ["signals.Gang.table:", "keys '1..3' and '2' overlap"]),
    "value table key neither number nor range": (_sub('"1" = 1, "2" = 2, default = "invalid"',
                                                      '"one" = 1, default = "invalid"'), None,
                                                 ["signals.Gang.table:", "key 'one' is not a whole number or a range A..B"]),
    "value name the signal lacks": (_sub('"-1" = "R"', '"-1" = "Reverse"'), None,
                                    ["signals.Gang.table.-1:", "'Reverse' is not a value name of signal Gang"]),
    "source and protection field": (_sub("Temperatur = { constant = 90 }", "Motor_1_CRC = { constant = 1 }"),
                                    None, ["message.Motor_1.signals.Motor_1_CRC:",
                                           "is the protection's crc field"]),
    "protection field not in the message": (_sub('crc = "Motor_1_CRC"', 'crc = "Motor_1_CHK"'), None,
                                            ["message.Motor_1.protection.crc:", "no signal 'Motor_1_CHK'"]),
    "bad protection": (_sub('kind = "p1", crc = "Motor_1_CRC"', 'kind = "p3", crc = "Motor_1_CRC"'), None,
                       ["message.Motor_1.protection:", "protection kind 'p3'"]),
    "unknown key at the top": (_add("\n[vehicle]\nname = 'x'\n"), None,
                               ["vehicle.toml: vehicle:", "unknown key 'vehicle' (known: bus, message)"]),
    "unknown key in a bus": (_sub("bitrate = 500000", "baudrate = 500000"), None,
                             ["bus[0].baudrate:", "unknown key 'baudrate'", "known: name, dbc, bitrate"]),
    "unknown key in a message": (_sub("timeout_cycles = 5", "timeout = 5"), None,
                                 ["message.Getriebe_1.timeout:", "unknown key 'timeout'", "timeout_cycles"]),
    "unknown key in a signal entry": (_sub('output = "engine_speed_rpm" }', 'output = "engine_speed_rpm", scale = 2 }'),
                                      None, ["signals.Motordrehzahl.scale:", "unknown key 'scale'", "known: output"]),
    "unknown key in a protection": (_sub("data_id = 0x123", "dataid = 0x123"), None,
                                    ["message.Motor_1.protection:", "unknown protection key 'dataid'", "known:"]),
    "DBC cantools cannot parse": (None, lambda text: "BO_ this is not ( a DBC\n",
                                  ["vehicle.toml: bus[0].dbc:", "cantools cannot parse", "vehicle.dbc"]),
    "DBC missing": (_sub('dbc = "vehicle.dbc"', 'dbc = "nowhere.dbc"'), None,
                    ["bus[0].dbc:", "cannot read", "nowhere.dbc"]),
    "unit the table lacks": (_sub('unit = "m/s"', 'unit = "furlong/fortnight"'), None,
                             ["signals.Geschwindigkeit.unit:", "unknown unit 'furlong/fortnight'", "known:"]),
    "DBC unit differs from the output's": (_sub('Geschwindigkeit = { output = "vehicle_speed_kmh", unit = "m/s" }',
                                                'Geschwindigkeit = { output = "vehicle_speed_kmh" }'), None,
                                           ["message.ABS_1.signals.Geschwindigkeit:", "the DBC's unit of the signal is 'm/s'",
                                            "'km/h'", "give unit = \"m/s\""]),
    "unit contradicts the DBC": (_sub('unit = "kPa"', 'unit = "bar"'), None,
                                 ["signals.Bremsdruck.unit:", "unit 'bar' but the DBC's unit of the signal is 'kPa'"]),
    "unit of another quantity": (None, _sub('[0|6553.5] "kPa"', '[0|6553.5] ""'),
                                 []),   # filled below: kPa given for a bar output works; see next
    "percent without reference": (_sub(', unit = "%", reference = 350.0 }\nTemperatur', ', unit = "%" }\nTemperatur'),
                                  None, ["signals.Motormoment.reference:", "needs reference"]),
    "input driven twice": (_sub('Momentenanforderung = { input = "engine_torque_request_nm"',
                                'Momentenanforderung = { input = "solenoid_current1_a"'), None,
                           ["signals.Momentenanforderung.input:", "solenoid_current1_a is already driven by "
                            "message.Getriebe_1.signals.Strom_K1"]),
    "timeout on a sent message": (_sub("[message.Motor_1]\n", "[message.Motor_1]\ntimeout_cycles = 3\n"), None,
                                  ["message.Motor_1.timeout_cycles:", "only received messages time out"]),
    "optional on a sent message": (_sub("[message.Motor_1]\n", "[message.Motor_1]\noptional = true\n"), None,
                                   ["message.Motor_1.optional:", "only received messages are optional"]),
    "optional not a flag": (_sub("timeout_cycles = 5", "timeout_cycles = 5\noptional = 1"), None,
                            ["message.Getriebe_1.optional:", "must be true or false, got 1"]),
    "bad direction": (_sub("timeout_cycles = 5", 'timeout_cycles = 5\ndirection = "both"'), None,
                      ["message.Getriebe_1.direction:", "'both': choose one of send, receive, ignore"]),
    "unknown node": (_sub('"Kombi"]', '"Kombi", "Radio"]'), None,
                     ["bus[0].plant_nodes:", "unknown node 'Radio'", "Motor, ABS, Kombi, Getriebe, Airbag"]),
    "placeholder node": (_sub('"Kombi"]', '"Kombi", "Vector__XXX"]'), None,
                         ["bus[0].plant_nodes:", "Vector__XXX is the DBC's placeholder for no node"]),
    "message of neither side": (_add("\n[message.Airbag_1]\ncycle_ms = 10\n"), None,
                                ["message.Airbag_1.direction:", "sent by Airbag, not a plant or TCU node",
                                 "give direction"]),
    "an ignored message with entries": (_sub("timeout_cycles = 5", 'timeout_cycles = 5\ndirection = "ignore"'), None,
                                        ["message.Getriebe_1.timeout_cycles:", "is ignored", "has no use"]),
    "two sources in one entry": (_sub("Kodierung = { constant = 3 }", "Kodierung = { constant = 3, toggle = true }"),
                                 None, ["signals.Kodierung:", "give exactly one of output, status, constant, toggle, counter"]),
    "not TOML": (lambda text: text + "\n[message.Motor_1\n", None, ["vehicle.toml: not valid TOML"]),
}
del BAD_MAPPINGS["unit of another quantity"]


@pytest.mark.parametrize("case", list(BAD_MAPPINGS))
def test_each_bad_mapping_gives_one_line_with_file_key_and_cause_and_exit_2(case, vehicle, capsys):
    edit_toml, edit_dbc, fragments = BAD_MAPPINGS[case]
    path = vehicle(toml=(edit_toml or (lambda t: t))(VEHICLE_TOML), dbc=(edit_dbc or (lambda t: t))(VEHICLE_DBC))
    with pytest.raises(M.MappingError) as e:
        M.load(path)
    assert "\n" not in str(e.value)
    for action in ("check", "show"):
        code, out, err = run_cli(capsys, "mapping", action, path)
        assert out == ""
        assert_one_line(code, err, *fragments)
        dbc_level = fragments[0].startswith("vehicle.dbc: message")
        file = os.path.join(os.path.dirname(path), "vehicle.dbc") if dbc_level else path
        assert err.startswith(f"dct-hil: error: {file}: "), err


def test_the_vehicle_mapping_is_valid_as_written(vehicle, capsys):
    code, out, err = run_cli(capsys, "mapping", "check", vehicle())
    assert code == 0, err
    assert "bus pt: vehicle.dbc, classic CAN at 500 kbit/s; plant nodes Motor, ABS, Kombi; TCU nodes Getriebe" in out
    assert "sends 3 messages (0 restbus" in out and "receives 1" in out
    assert "received signals: 2 drive plant inputs, 1 recorded, 1 unused" in out
    assert "warning" not in out and "note" not in out


def test_the_rate_decides_which_cycle_times_are_whole_ticks(vehicle, capsys):
    path = vehicle(toml=VEHICLE_TOML + "\n[message.ABS_1]\ncycle_ms = 5\n")
    assert run_cli(capsys, "mapping", "check", path, "--rate", "2000")[0] == 0
    assert run_cli(capsys, "mapping", "check", path, "--rate", "400")[0] == 0        # 2 ticks
    code, out, err = run_cli(capsys, "mapping", "check", path, "--rate", "300")       # 1.5 ticks
    assert_one_line(code, err, "message.ABS_1.cycle_ms:", "cycle time 5 ms",
                    "the loop's 3.33333 ms ticks at 300 Hz")
    # the DBC's cycle time is checked as well, and says so
    code, out, err = run_cli(capsys, "mapping", "check", vehicle(), "--rate", "125")
    assert_one_line(code, err, "message.Motor_1.cycle_ms:", "cycle time 10 ms (the DBC's GenMsgCycleTime) "
                    "is not a whole number of the loop's 8 ms ticks at 125 Hz")


def test_ignore_and_direction_overrides(vehicle):
    toml = VEHICLE_TOML + '\n[message.Airbag_1]\ndirection = "ignore"\n\n[message.Kombi_1]\ndirection = "ignore"\n'
    toml = toml.replace("[message.Kombi_1.signals]\nKodierung = { constant = 3 }\nToggle = { toggle = true }\n"
                        "Zaehler = { counter = 15 }\n", "")
    toml = re.sub(r"Gang = \{ output = \"gear\".*\n", "", toml)
    m = M.load(vehicle(toml=toml))
    assert [x.name for x in m.messages] == ["ABS_1", "Motor_1", "Getriebe_1"]
    assert m.ignored == (("pt", "Kombi_1"), ("pt", "Airbag_1"))          # in the DBC's order


# ---------------------------------------------------------------------------
# a messy DBC, read leniently; the mapping supplies what it lacks
# ---------------------------------------------------------------------------

MESSY_DBC = """\
VERSION ""

NS_ :
	CM_

BS_:

BU_:

BO_ 100 Engine_1: 8 Vector__XXX
 SG_ Speed : 0|16@1+ (0.25,0) [0|16383.75] "U/min" Vector__XXX
 SG_ Pedal : 16|8@1+ (0.4,0) [0|100] "%" Vector__XXX

BO_ 200 Odd: 8 Vector__XXX
 SG_ A : 0|16@1+ (1,0) [0|65535] "" Vector__XXX
 SG_ B : 8|16@1+ (1,0) [0|65535] "" Vector__XXX

BO_ 300 Tcu_1: 8 Vector__XXX
 SG_ Current : 0|16@1+ (1,0) [0|2000] "mA" Vector__XXX
 SG_ Mode M : 16|4@1+ (1,0) [0|15] "" Vector__XXX
 SG_ X m0 : 24|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ Y m1 : 24|8@1+ (1,0) [0|255] "" Vector__XXX
"""

MESSY_TOML = """\
[[bus]]
name = "can1"
dbc = "messy.dbc"
bitrate = 250000

[message.Engine_1]
direction = "send"
cycle_ms = 20

[message.Engine_1.signals]
Speed = { output = "engine_speed_rpm" }
Pedal = { output = "accel_pedal_pct" }

[message.Tcu_1]
direction = "receive"
cycle_ms = 10
timeout_cycles = 20

[message.Tcu_1.signals]
Current = { input = "solenoid_current1_a", unit = "mA", max = 1.0 }
"""


def test_a_messy_dbc_loads_leniently_with_the_mapping_supplying_what_it_lacks(tmp_path, capsys):
    (tmp_path / "messy.dbc").write_text(MESSY_DBC)
    path = tmp_path / "messy.toml"
    path.write_text(MESSY_TOML)
    with pytest.raises(ValueError, match="overlapping"):       # what a strict reader says
        codec.load_database(str(tmp_path / "messy.dbc"))
    m = M.load(str(path))
    assert [(x.name, x.direction, x.cycle_ms) for x in m.messages] == [
        ("Engine_1", "send", 20.0), ("Tcu_1", "receive", 10.0)]
    assert m.message("Tcu_1").timeout_cycles == 20
    assert m.message("Tcu_1").signal("Current").target.gain == pytest.approx(1e-3)
    # multiplexed signals X and Y share bits in different branches: no overlap
    assert [s.name for s in m.message("Tcu_1").signals] == ["Current", "Mode", "X", "Y"]
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert code == 0, err
    assert "plant nodes none; TCU nodes none" in out
    # the unused message with overlapping signals is used: now it is an error
    path.write_text(MESSY_TOML + '\n[message.Odd]\ndirection = "send"\ncycle_ms = 100\n')
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert_one_line(code, err, "messy.dbc: message Odd:", "signals A (bits 0-15) and B (bits 8-23) overlap")
    # without the cycle time the mapping gives, the message lacks one
    path.write_text(MESSY_TOML.replace("cycle_ms = 20\n", ""))
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert_one_line(code, err, "messy.toml: message.Engine_1.cycle_ms:", "the DBC gives no GenMsgCycleTime")
    # a message named without a direction: the DBC has no nodes to tell
    path.write_text(MESSY_TOML.replace('direction = "send"\n', ""))
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert_one_line(code, err, "message.Engine_1.direction:", "has no sending node in the DBC", "give direction")


# ---------------------------------------------------------------------------
# template
# ---------------------------------------------------------------------------

def test_a_template_of_the_contract_dbc_loads_after_filling_and_equals_the_shipped_mapping(tmp_path, capsys):
    out = tmp_path / "sub" / "mine.toml"
    out.parent.mkdir()
    code, text, err = run_cli(capsys, "mapping", "template", codec.DBC_PATH, "--tcu-node", "TCU", "--out", out)
    assert code == 0, err
    assert text == f"template: {out}\n"
    body = out.read_text()
    rel = os.path.relpath(codec.DBC_PATH, out.parent)
    assert f'dbc = "{codec.DBC_PATH if rel.startswith(3 * (os.pardir + os.sep)) else rel}"' in body
    assert 'plant_nodes = ["PLANT"]' in body and 'tcu_nodes = ["TCU"]' in body
    assert re.search(r"^\[message\.DCT_ShaftSpeeds\]\s+# 0x100, 8 bytes, sent by PLANT, every 2 ms$", body, re.M)
    assert re.search(r"^# EngineSpeed: 16 bit signed at bit 16 \(Intel\), -16383.5 \.\. 16383.5 rpm, step 0.5$",
                     body, re.M)
    assert '\nEngineSpeed = { output = "engine_speed_rpm" }\n' in body     # the contract's own name
    assert '\nSimTime = { status = "sim_time_s" }\n' in body
    assert '\nTargetGear = { record = "target_gear", safe = 0 }\n' in body
    assert body.count('# protection = { kind = "?", crc = "CRC", counter = "AliveCounter" }') == 11
    # as written it is valid, and check says what it lacks
    code, report, err = run_cli(capsys, "mapping", "check", out)
    assert code == 0, err
    assert "0 protected" in report
    assert "note: message TCU_ClutchCmd (bus dct_hil): CRC, AliveCounter look like a checksum and a counter" in report
    # filled in: the project's contract
    out.write_text(body.replace('# protection = { kind = "?"', 'protection = { kind = "dct"'))
    filled, shipped = M.load(str(out)), M.load(M.DEFAULT_MAPPING)
    assert filled.buses[0].dbc == shipped.buses[0].dbc
    # the same but for optional, the mapping author's word (the DBC cannot say it)
    assert [dataclasses.replace(x, bus="dct", mapped=True, optional=x.name == "TCU_Status")
            for x in filled.messages] == list(shipped.messages)
    assert M.bus_load(filled, "dct_hil") == dataclasses.replace(M.bus_load(shipped, "dct"), bus="dct_hil")


def test_a_template_lists_what_the_dbc_lacks_and_guesses_nothing_else(vehicle, tmp_path, capsys):
    dbc = VEHICLE_DBC.replace('BA_ "GenMsgCycleTime" BO_ 800 100;\n', "")
    vehicle(dbc=dbc)
    code, text, err = run_cli(capsys, "mapping", "template", tmp_path / "vehicle.dbc", "--tcu-node", "Getriebe")
    assert code == 0, err
    assert 'bitrate = 500000' in text
    assert 'plant_nodes = ["Motor", "ABS"]' in text                 # the senders of what the TCU receives
    assert re.search(r"^\[message\.Motor_1\]\s+# 0x280, 8 bytes, sent by Motor, every 10 ms$", text, re.M)
    assert '# protection = { kind = "?", crc = "Motor_1_CRC", counter = "Motor_1_BZ" }' in text
    assert re.search(r'^# Motordrehzahl = \{ output = "" \}\s+# outputs in its quantity: engine_speed_rpm, '
                     r'input_shaft1_speed_rpm', text, re.M)
    assert re.search(r'^# Strom_K1 = \{ input = "", safe = 0.0 \}\s+# inputs in its quantity: '
                     r'solenoid_current1_a, solenoid_current2_a, line_solenoid_current_a$', text, re.M)
    assert not re.search(r"^[A-Z][A-Za-z_0-9]* = \{", text, re.M)        # no name of the contract: no guess
    # Kombi is not a plant node of this template (the TCU receives nothing of it)
    assert "# 0x320 Kombi_1 (Kombi), 8 bytes, no cycle time" in text
    # with Kombi as a plant node, its message is restbus and lacks a cycle time
    code, text, err = run_cli(capsys, "mapping", "template", tmp_path / "vehicle.dbc", "--tcu-node", "Getriebe",
                              "--plant-node", "Motor", "--plant-node", "ABS", "--plant-node", "Kombi",
                              "--out", tmp_path / "t.toml")
    assert code == 0, err
    text = (tmp_path / "t.toml").read_text()
    assert re.search(r"^\[message\.Kombi_1\]\s+# 0x320, 8 bytes, sent by Kombi, cycle time missing: give "
                     r"cycle_ms; or direction = \"ignore\"$", text, re.M)
    assert "# cycle_ms =                    # cycle time missing: give cycle_ms" in text
    code, out, err = run_cli(capsys, "mapping", "check", tmp_path / "t.toml")
    assert_one_line(code, err, "t.toml: message.Kombi_1.cycle_ms:", "has no cycle time")
    (tmp_path / "t.toml").write_text(text.replace("# cycle_ms =    ", "cycle_ms = 100"))
    assert run_cli(capsys, "mapping", "check", tmp_path / "t.toml")[0] == 0


def test_a_template_for_a_dbc_without_nodes_takes_the_tcu_messages(tmp_path, capsys):
    (tmp_path / "messy.dbc").write_text(MESSY_DBC)
    code, text, err = run_cli(capsys, "mapping", "template", tmp_path / "messy.dbc", "--tcu-messages", "Tcu_1")
    assert code == 0, err
    assert re.search(r"^\[message\.Tcu_1\]\s+# 0x12C, 8 bytes, sent by no node, cycle time missing", text, re.M)
    assert '\ndirection = "receive"\n' in text
    assert "# 0x064 Engine_1 (no node), 8 bytes, no cycle time" in text
    for argv, fragments in (
            ([], ["messy.dbc: the TCU is missing: give --tcu-node"]),
            (["--tcu-node", "TCU"], ["--tcu-node TCU: no such node (its nodes: none)"]),
            (["--tcu-messages", "Tcu_2"], ["--tcu-messages Tcu_2: no such message", "did you mean Tcu_1"])):
        code, out, err = run_cli(capsys, "mapping", "template", tmp_path / "messy.dbc", *argv)
        assert_one_line(code, err, *fragments)
    (tmp_path / "bad.dbc").write_text("BO_ this is not ( a DBC\n")
    code, out, err = run_cli(capsys, "mapping", "template", tmp_path / "bad.dbc", "--tcu-node", "X")
    assert_one_line(code, err, "bad.dbc", "cantools cannot parse")


def test_mapping_without_an_action_is_a_one_line_error(capsys):
    code, out, err = run_cli(capsys, "mapping")
    assert_one_line(code, err, "choose an action: dct-hil mapping template, check or show")


# ---------------------------------------------------------------------------
# bus load
# ---------------------------------------------------------------------------

def test_frame_bits_classic_and_fd():
    assert M.classic_frame_bits(8) == codec.frame_bits_worst_case(8) == 135
    assert M.classic_frame_bits(8, extended=True) == 67 + 64 + (54 + 64 - 1) // 4 == 160
    # CAN FD, 11-bit id: 17 arbitration bits + 4 stuff + 13 (CRC delimiter .. IFS)
    assert M.fd_frame_bits(8) == (34, 5 + 64 + (17 + 5 + 64 - 1) // 4 - 4 + 4 + 17 + 6)
    assert M.fd_frame_bits(64) == (34, 5 + 512 + (17 + 5 + 512 - 1) // 4 - 4 + 4 + 21 + 7)
    assert M.fd_frame_bits(10) == M.fd_frame_bits(12)                      # the next DLC length
    arb, data = M.fd_frame_bits(64)
    assert M.frame_time_s(64, fd=True, bitrate=500_000, data_bitrate=2_000_000) == pytest.approx(
        arb / 500e3 + data / 2e6)
    assert M.frame_time_s(64, fd=True, bitrate=500_000) == pytest.approx((arb + data) / 500e3)
    with pytest.raises(ValueError):
        M.fd_frame_bits(65)


def test_bus_load_of_an_fd_bus_and_the_warning_above_half(tmp_path, capsys):
    dbc = MESSY_DBC.replace("BO_ 200 Odd: 8", "BO_ 200 Odd: 64").replace(
        "BU_:", 'BU_:').replace("BS_:", "BS_:") + (
        'BA_DEF_ BO_ "VFrameFormat" ENUM "StandardCAN","ExtendedCAN","reserved","reserved","reserved",'
        '"reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved",'
        '"StandardCAN_FD","ExtendedCAN_FD";\n'
        'BA_ "VFrameFormat" BO_ 200 14;\n')
    (tmp_path / "messy.dbc").write_text(dbc)
    toml = MESSY_TOML.replace("bitrate = 250000", "bitrate = 500000\ndata_bitrate = 2000000") + (
        '\n[message.Odd]\ndirection = "send"\ncycle_ms = 1\n')
    path = tmp_path / "fd.toml"
    path.write_text(toml.replace('SG_ B : 8|16', 'SG_ B : 16|16'))
    (tmp_path / "messy.dbc").write_text(dbc.replace("SG_ B : 8|16", "SG_ B : 16|16"))
    m = M.load(str(path))
    assert m.buses[0].fd and m.message("Odd").is_fd and not m.message("Engine_1").is_fd
    load = M.bus_load(m, "can1")
    arb, data = M.fd_frame_bits(64)
    expected = (1000 * (arb / 500e3 + data / 2e6) + 50 * 135 / 500e3 + 100 * 135 / 500e3)
    assert load.load == pytest.approx(expected)
    assert load.sent == pytest.approx(1000 * (arb / 500e3 + data / 2e6) + 50 * 135 / 500e3)
    assert load.warning is None
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert code == 0, err
    assert "CAN FD at 500 kbit/s, data phase 2 Mbit/s" in out
    assert f"worst-case bus load at 500 kbit/s: {100 * expected:.1f} %" in out
    # without the bit rate switch the 64-byte frame every 1 ms fills more than half the bus
    path.write_text(path.read_text().replace("data_bitrate = 2000000\n", ""))
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert code == 0, err
    assert re.search(r"^warning: bus can1: worst-case bus load \d+\.\d % is above 50 %$", out, re.M)
    # a classic bus cannot carry it
    path.write_text(path.read_text().replace("bitrate = 500000\n", "bitrate = 500000\nfd = false\n"))
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert_one_line(code, err, "message.Odd:", "is a CAN FD frame (64 bytes) but bus can1 is classic CAN")


# ---------------------------------------------------------------------------
# the example vehicle matrix (can_dbc/matrices/): two buses
# ---------------------------------------------------------------------------

VEHICLE_MAPPING = os.path.join(ROOT, "can_dbc", "mappings", "vehicle.toml")


def _comment_protection(msg):
    """The protection a message's DBC comment names ('Protection: p1; crc X; ...')."""
    found = re.search(r"Protection: ([^.]*)\.", msg.comment or "")
    assert found, msg.name
    kind, *items = [x.strip() for x in found.group(1).split(";")]
    spec = {"kind": kind}
    for item in items:
        key, value = item.split(" ", 1)
        if key == "data_id":
            value = int(value, 16)
        elif key == "data_id_list":
            value = tuple(int(x, 16) for x in value.split(","))
        spec[key] = value
    return spec


def test_the_vehicle_mapping_loads_and_passes_check(capsys):
    m = M.load(M.find_mapping("vehicle"))
    assert [(b.name, os.path.basename(b.dbc), b.bitrate, b.plant_nodes, b.tcu_nodes) for b in m.buses] == [
        ("pt", "vehicle_pt.dbc", 500_000, ("ECM", "ESP", "IC", "GW"), ("TCU",)),
        ("io", "vehicle_io.dbc", 1_000_000, ("PLANT",), ("TCU",))]
    for b in m.buses:
        senders = {n: [x.name for x in b.database.messages if n in x.senders] for n in b.plant_nodes + b.tcu_nodes}
        assert {x.name for x in m.codec_order(b.name)} == {n for names in senders.values() for n in names}
    # every message's protection is the one its DBC comment names
    for x in m.messages:
        p, spec = x.protection, _comment_protection(x.message)
        assert p.kind == spec["kind"], x.name
        assert (p.crc_signal, p.counter_signal) == (spec.get("crc"), spec.get("counter")), x.name
        assert p.data_id == spec.get("data_id"), x.name
        assert p.data_id_list == spec.get("data_id_list"), x.name
        if "data_id_mode" in spec:
            assert p.data_id_mode == spec["data_id_mode"], x.name
        assert p.data_id_nibble_signal == spec.get("data_id_nibble"), x.name
    # the TCU drives every input it drives through the project's contract, and the target gear is recorded
    def driven(mapping, kind):
        return {s.target.name for x in mapping.messages for s in x.signals if s.target and s.target.kind == kind}
    assert driven(m, "input") == driven(M.load(), "input")
    assert "target_gear" in driven(m, "record")
    torque = m.message("TCU_TorqueReq").signal("TrqReqValue").target
    assert torque.gain == pytest.approx(2.8)                    # % of EngineRefTorque (280 Nm) -> Nm
    assert m.message("ECM_Info").signal("EngineRefTorque").source.value == 280.0
    assert m.message("ESP_WheelSpeeds").signal("WheelSpeedFL").source.gain == pytest.approx(
        2 * math.pi * 0.316 * 60 / 1000, rel=1e-5)             # wheel rpm -> km/h at the tyre's radius

    code, out, err = run_cli(capsys, "mapping", "check", "vehicle")
    assert code == 0, err
    assert "bus pt: vehicle_pt.dbc, classic CAN at 500 kbit/s" in out
    assert "bus io: vehicle_io.dbc, classic CAN at 1 Mbit/s" in out
    assert len(re.findall(r"worst-case bus load at", out)) == 2
    assert "warning" not in out and "note" not in out
    code, out, err = run_cli(capsys, "mapping", "show", "vehicle")
    assert code == 0, err
    assert re.search(r"SelectorLever\s+<- selector_lever", out)


def test_a_factor_converts_between_quantities_that_no_unit_converts(vehicle, capsys):
    toml = VEHICLE_TOML.replace('Raddrehzahl = { output = "wheel_speed_fl_rpm", unit = "rad/s" }',
                                'Raddrehzahl = { output = "vehicle_speed_kmh" }')
    code, out, err = run_cli(capsys, "mapping", "check", vehicle(toml=toml))
    assert_one_line(code, err, "message.ABS_1.signals.Raddrehzahl:", "the DBC's unit of the signal is 'rad/s'",
                    "'km/h', another quantity", "give factor (rad/s per km/h)")
    toml = toml.replace('Raddrehzahl = { output = "vehicle_speed_kmh" }',
                        'Raddrehzahl = { output = "vehicle_speed_kmh", unit = "rad/s" }')
    code, out, err = run_cli(capsys, "mapping", "check", vehicle(toml=toml))
    assert_one_line(code, err, "signals.Raddrehzahl.unit:", "cannot convert km/h (speed) to rad/s",
                    "without unit, factor does")
    toml = toml.replace('"vehicle_speed_kmh", unit = "rad/s" }', '"vehicle_speed_kmh", factor = 0.879 }')
    m = M.load(vehicle(toml=toml))
    src = m.message("ABS_1").signal("Raddrehzahl").source
    assert (src.gain, src.unit, src.signal_unit) == (0.879, "km/h", "rad/s")


def test_the_vehicle_mapping_carries_what_the_reference_tcu_needs_where_the_matrices_put_it():
    """tests/test_matrices.py names, for each contract signal the reference TCU reads
    or writes, the vehicle matrix signal that carries it: the vehicle mapping fills
    that signal from (or into) the same plant field as the contract's mapping."""
    from test_matrices import TCU_NEEDS as needs
    contract, vehicle_map = M.load(), M.load(M.find_mapping("vehicle"))

    def field(mapped):
        what = mapped.source or mapped.target
        return (what.kind, what.name)

    contract_fields = {s.name: field(s) for x in contract.messages for s in x.signals if not s.protection_field}
    buses = {"vehicle_pt": "pt", "vehicle_io": "io"}
    for name, (matrix, message, signal) in needs.items():
        carrier = vehicle_map.message(message, bus=buses[matrix]).signal(signal)
        assert field(carrier) == contract_fields[name], (name, message, signal)


# ------------------------------------------------------------ the buses' channels

def test_each_bus_gets_a_channel_of_its_own():
    m = M.load(M.find_mapping("vehicle"))
    # the first bus on the channel given, the others derived on virtual buses ...
    assert m.channels("demo") == {"pt": "demo", "io": "demo-io"}
    # ... the next address and port for a udp_multicast group (IPv4 and IPv6) ...
    assert m.channels("239.74.163.2") == {"pt": "239.74.163.2", "io": "239.74.163.3:43114"}
    assert m.channels("ff15::7") == {"pt": "ff15::7", "io": "[ff15::8]:43114"}
    assert m.channels("239.1.1.1:5000") == {"pt": "239.1.1.1:5000", "io": "239.1.1.2:5001"}
    # ... and named ones as given, the first bus too
    assert m.channels("can0", {"io": "can1"}, derive=False) == {"pt": "can0", "io": "can1"}
    assert m.channels("x", {"pt": "can3", "io": "can1"}) == {"pt": "can3", "io": "can1"}


@pytest.mark.parametrize("first, named, derive, words", [
    ("can0", {}, False, ["bus 'io' has no CAN channel", "--bus io=CHANNEL"]),
    ("can0", {"xx": "can1"}, True, ["bus 'xx'", "pt, io"]),
    ("can0", {"io": "can0"}, True, ["'pt' and 'io'", "channel of its own"]),
])
def test_a_bus_without_a_channel_or_a_shared_one_is_one_line(first, named, derive, words):
    m = M.load(M.find_mapping("vehicle"))
    with pytest.raises(M.MappingError) as e:
        m.channels(first, named, derive=derive)
    text = str(e.value)
    assert "\n" not in text and text.startswith(m.path)
    for w in words:
        assert w in text, text


def test_dbc_options_replace_a_buss_dbc_or_name_the_cause(tmp_path):
    pt = os.path.join(M.MAPPINGS_DIR, "..", "matrices", "vehicle_pt.dbc")
    m = M.load_options("vehicle", [f"pt={pt}"])
    assert m.bus("pt").dbc == os.path.abspath(pt)
    m = M.load_options("dct_hil", [os.path.join(M.MAPPINGS_DIR, "..", "dct_hil.dbc")])
    assert m.bus("dct").dbc.endswith("dct_hil.dbc")
    bad = tmp_path / "bad.dbc"
    bad.write_text("this is no DBC\n")
    for values, words in (([f"zz={pt}"], "bus 'zz'"), ([str(bad)], "bad.dbc"),
                          (["pt="], "BUS=FILE"), ([pt, pt], "given twice")):
        with pytest.raises(M.MappingError) as e:
            M.load_options("vehicle" if values != [str(bad)] else "dct_hil", values)
        assert words in str(e.value) and "\n" not in str(e.value), (values, str(e.value))
    assert M.parse_pairs(["io=vcan1", " pt = vcan0 "], "--bus") == {"io": "vcan1", "pt": "vcan0"}
    for values in (["io"], ["=x"], ["io=a", "io=b"]):
        with pytest.raises(M.MappingError):
            M.parse_pairs(values, "--bus")
