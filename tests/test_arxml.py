"""CAN matrices as AUTOSAR system descriptions (ARXML), KCD and SYM files.

- The shipped example: can_dbc/matrices/vehicle_pt.arxml (the example
  vehicle matrix's pt bus in AUTOSAR 4 form) and
  can_dbc/mappings/vehicle_arxml.toml are what ``python -m can_dbc.to_arxml``
  writes; ``dct-hil mapping check`` passes on the ARXML mapping with the DBC
  version's summary; every pt message, sent and received, encodes from the
  same plant values (and the same received values) into the same frames as
  through vehicle.toml, bit for bit: identifiers, lengths, payloads, CRCs
  and counters (the E2E Profile 1 protection coming from the ARXML).
- The E2E protection an ARXML declares (E2E transformer or protection set:
  profile, Data IDs, offsets) becomes the message's protection unless the
  mapping gives one; a Profile 5 message's header signals are found where
  the profile puts them; a profile the codec lacks is one line naming it.
- KCD and SYM files load through the same reader; a broken file is one line
  naming it.
- ``dct-hil demo`` serves the ARXML mapping on the embedded transport: every
  message goes both ways unrejected.
"""

import json
import math
import random
import subprocess
import sys
from pathlib import Path

import pytest
import requires

from can_dbc import mapping, matrix, to_arxml
from can_dbc.table import CodecTable

cantools = requires.module("cantools")

REPO = Path(__file__).resolve().parents[1]
ARXML = REPO / "can_dbc" / "matrices" / "vehicle_pt.arxml"
DBC = REPO / "can_dbc" / "matrices" / "vehicle_pt.dbc"


@pytest.fixture(scope="module")
def both():
    return (mapping.load(mapping.find_mapping("vehicle")),
            mapping.load(mapping.find_mapping("vehicle_arxml")))


def test_the_shipped_example_is_what_the_generator_writes(capsys):
    assert to_arxml.main(["--check"]) == 0, capsys.readouterr().err


def test_the_arxml_is_an_autosar_4_system_description_cantools_reads():
    db = matrix.read_matrix(str(ARXML))
    dbc = matrix.read_matrix(str(DBC))
    assert db.autosar is not None and db.autosar.arxml_version.startswith("4.")
    assert [b.name for b in db.buses] == ["PT_CAN"] and db.buses[0].baudrate == 500_000
    assert sorted(n.name for n in db.nodes) == sorted(n.name for n in dbc.nodes)
    assert sorted(m.name for m in db.messages) == sorted(m.name for m in dbc.messages)
    for m in dbc.messages:
        a = db.get_message_by_name(m.name)
        assert (a.frame_id, a.length, a.is_extended_frame, a.cycle_time, a.senders) == \
            (m.frame_id, m.length, m.is_extended_frame, m.cycle_time, m.senders), m.name
        names = {s.name for s in m.signals if not s.is_multiplexer}
        assert names <= {s.name for s in a.signals}, m.name
        for s in m.signals:
            if s.is_multiplexer:
                continue
            t = a.get_signal_by_name(s.name)
            assert (t.start, t.length, t.byte_order, t.is_signed, t.raw_initial, t.multiplexer_ids) == \
                (s.start, s.length, s.byte_order, s.is_signed, s.raw_initial, s.multiplexer_ids), s.name
            assert (t.scale, t.offset) == (s.scale, s.offset), s.name
            assert (t.unit or "") == (s.unit or ""), s.name
            assert {k: str(v) for k, v in (t.choices or {}).items()} == \
                {k: str(v) for k, v in (s.choices or {}).items()}, s.name
            for lim in ("minimum", "maximum"):
                assert math.isclose(getattr(t, lim), getattr(s, lim), rel_tol=1e-12, abs_tol=1e-12), s.name
    # the E2E transformers cantools sees
    e2e = {m.name: m.autosar.e2e for m in db.messages if m.autosar.e2e is not None}
    assert sorted(e2e) == ["ECM_Torque", "ESP_Motion", "TCU_Gear", "TCU_TorqueReq"]
    assert {e.category for e in e2e.values()} == {"PROFILE_01"}
    assert e2e["ECM_Torque"].data_ids == [0x01D3] and e2e["ESP_Motion"].data_ids == [0x074B]


def test_mapping_check_passes_on_the_arxml_mapping_as_on_the_dbc_one():
    def check(name):
        proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "mapping", "check", name],
                              capture_output=True, text=True, timeout=120, cwd=REPO)
        assert proc.returncode == 0, proc.stderr
        return proc.stdout

    dbc, arxml = check("vehicle"), check("vehicle_arxml")
    assert "bus pt: vehicle_pt.arxml, classic CAN at 500 kbit/s" in arxml
    # the same summary, bus load included, but for the file's name
    assert arxml.replace("vehicle_arxml.toml", "vehicle.toml").replace("vehicle_pt.arxml", "vehicle_pt.dbc") == dbc


def test_the_arxml_gives_the_e2e_protection_the_dbc_mapping_writes_out(both):
    dbc, arxml = both
    for m in dbc.codec_order("pt"):
        a = arxml.message(m.name, "pt")
        assert a.protection == m.protection, m.name
        assert a.protection_from_file == (m.protection.kind == "p1"), m.name
    shown = mapping.show(arxml)
    assert ("protection p1 (crc ESP_Motion_CRC, counter ESP_Motion_Ctr, data id 0x074B (nibble)) "
            "from vehicle_pt.arxml") in shown


def plant_values(seed):
    """Plant outputs: a few states of the model, then random values (negative,
    beyond the signals' ranges, fractional) for every output."""
    from plant.model import OUTPUT_NAMES, Plant

    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
    out = []
    for speed, pedal in ((0.0, 0.0), (-8.0, 0.0), (42.0, 35.0), (130.0, 100.0)):
        plant.reset(vehicle_speed_kmh=speed)
        plant.inputs["accel_pedal_pct"] = pedal
        plant.step(400)
        out.append({n: float(plant.outputs[n]) for n in OUTPUT_NAMES})
    rng = random.Random(seed)
    for _ in range(40):
        out.append({n: rng.choice((rng.uniform(-1e3, 1e4), rng.uniform(-5, 5), 0.0)) for n in OUTPUT_NAMES})
    return out


def sent_values(m, outputs, frame):
    """The signal values the loop sends for message ``m`` (mapping.Source)."""
    from tcu_stub.mapped_link import _source_value

    values = {}
    for s in m.signals:
        src = s.source
        if src is None:
            continue                      # a protection field: written by the protection
        if src.kind == "output":
            values[s.name] = _source_value(src, outputs[src.name])
        elif src.kind == "toggle":
            values[s.name] = frame % 2
        elif src.kind == "counter":
            values[s.name] = frame % (src.counter_max + 1)
        elif src.kind == "status":
            values[s.name] = 0.0
        else:
            values[s.name] = src.value
    return values


def tables(m, bus):
    msgs = m.codec_order(bus)
    return CodecTable([(x.message, x.protection) for x in msgs]), msgs


def test_every_pt_message_gives_the_same_frames_through_the_arxml_as_through_the_dbc(both):
    dbc, arxml = both
    (t_dbc, m_dbc), (t_arx, m_arx) = tables(dbc, "pt"), tables(arxml, "pt")
    assert [(x.name, x.frame_id, x.is_extended, x.length, x.direction, x.cycle_ms) for x in m_dbc] == \
        [(x.name, x.frame_id, x.is_extended, x.length, x.direction, x.cycle_ms) for x in m_arx]
    rng = random.Random(27)
    frames = 0
    for k, outputs in enumerate(plant_values(3)):
        for i, (a, b) in enumerate(zip(m_dbc, m_arx)):
            counter = rng.randrange(1 << 16)
            if a.direction == "send":
                va, vb = sent_values(a, outputs, k), sent_values(b, outputs, k)
                assert va == vb, a.name
            else:
                # what the TCU would send: random physical values over each signal's bits
                va = {}
                for s in a.signals:
                    if s.signal.is_multiplexer:       # one of its branches (cantools keeps no range
                        va[s.name] = rng.choice(sorted({i for x in a.signals  # for an ARXML's selector)
                                                        for i in x.signal.multiplexer_ids or ()}))
                    elif s.protection_field is None:
                        lo, hi = mapping._signal_range(s.signal)
                        va[s.name] = rng.choice((lo, hi, rng.uniform(lo - 10, hi + 10), round(rng.uniform(lo, hi))))
                # the multiplexer's name is cantools' in an ARXML (<message>_selector1): by position
                names = {(s.signal.start, s.signal.length): s.name for s in b.signals}
                vb = {names[(a.signal(n).signal.start, a.signal(n).signal.length)]: v for n, v in va.items()}
            fa = t_dbc.encode(i, va, counter=counter if a.protection.kind != "none" else None)
            fb = t_arx.encode(i, vb, counter=counter if b.protection.kind != "none" else None)
            assert fa == fb, (a.name, fa.hex(), fb.hex())
            assert t_arx.check(i, fb) == t_dbc.check(i, fa) == "ok"
            frames += 1
    assert frames == len(m_dbc) * 44


# ---------------------------------------------------------------------------
# E2E protection from a file, by hand-written ARXMLs
# ---------------------------------------------------------------------------

def _arxml(messages, e2e_style="set", profile="PROFILE_05", data_ids=(0x1234,), fields=""):
    """A small AUTOSAR 4 ARXML: a CAN cluster ``C`` with ECUs E (sender) and T,
    messages [(name, id, [(signal, start, length)], frame length (default 8;
    above 8 a CAN FD frame))], each of them protected by one E2E profile
    (END-TO-END-PROTECTION-SET or an E2E transformer)."""
    ns = "http://autosar.org/schema/r4.0"
    sig_els, pdu_els, frame_els, trig_els, refs, groups = [], [], [], [], [], []
    for name, ident, signals, *rest in messages:
        size = rest[0] if rest else 8
        fd = "<CAN-FRAME-TX-BEHAVIOR>CAN-FD</CAN-FRAME-TX-BEHAVIOR>" if size > 8 else ""
        maps = []
        for s, start, length in signals:
            sig_els.append(f"<I-SIGNAL><SHORT-NAME>{s}</SHORT-NAME><LENGTH>{length}</LENGTH>"
                           f"<SYSTEM-SIGNAL-REF DEST=\"SYSTEM-SIGNAL\">/P/S/{s}_S</SYSTEM-SIGNAL-REF></I-SIGNAL>"
                           f"<SYSTEM-SIGNAL><SHORT-NAME>{s}_S</SHORT-NAME></SYSTEM-SIGNAL>")
            maps.append(f"<I-SIGNAL-TO-I-PDU-MAPPING><SHORT-NAME>{name}_{s}</SHORT-NAME>"
                        f"<I-SIGNAL-REF DEST=\"I-SIGNAL\">/P/S/{s}</I-SIGNAL-REF>"
                        "<PACKING-BYTE-ORDER>MOST-SIGNIFICANT-BYTE-LAST</PACKING-BYTE-ORDER>"
                        f"<START-POSITION>{start}</START-POSITION></I-SIGNAL-TO-I-PDU-MAPPING>")
        if e2e_style == "transformer":
            groups.append(f"<I-SIGNAL-GROUP><SHORT-NAME>{name}_G</SHORT-NAME><TRANSFORMATION-I-SIGNAL-PROPSS>"
                          "<END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS>"
                          "<END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-VARIANTS>"
                          "<END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-CONDITIONAL>"
                          "<TRANSFORMER-REF DEST=\"TRANSFORMATION-TECHNOLOGY\">/P/S/X/E2E</TRANSFORMER-REF>"
                          "<DATA-IDS>" + "".join(f"<DATA-ID>{d}</DATA-ID>" for d in data_ids) + "</DATA-IDS>"
                          "</END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-CONDITIONAL>"
                          "</END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-VARIANTS>"
                          "</END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS></TRANSFORMATION-I-SIGNAL-PROPSS>"
                          "</I-SIGNAL-GROUP>")
            maps.append(f"<I-SIGNAL-TO-I-PDU-MAPPING><SHORT-NAME>{name}_G</SHORT-NAME>"
                        f"<I-SIGNAL-GROUP-REF DEST=\"I-SIGNAL-GROUP\">/P/S/{name}_G</I-SIGNAL-GROUP-REF>"
                        "</I-SIGNAL-TO-I-PDU-MAPPING>")
        pdu_els.append(f"<I-SIGNAL-I-PDU><SHORT-NAME>{name}_Pdu</SHORT-NAME><LENGTH>{size}</LENGTH>"
                       "<I-PDU-TIMING-SPECIFICATIONS><I-PDU-TIMING><TRANSMISSION-MODE-DECLARATION>"
                       "<TRANSMISSION-MODE-TRUE-TIMING><CYCLIC-TIMING><TIME-PERIOD><VALUE>0.01</VALUE>"
                       "</TIME-PERIOD></CYCLIC-TIMING></TRANSMISSION-MODE-TRUE-TIMING>"
                       "</TRANSMISSION-MODE-DECLARATION></I-PDU-TIMING></I-PDU-TIMING-SPECIFICATIONS>"
                       f"<I-SIGNAL-TO-PDU-MAPPINGS>{''.join(maps)}</I-SIGNAL-TO-PDU-MAPPINGS></I-SIGNAL-I-PDU>")
        frame_els.append(f"<CAN-FRAME><SHORT-NAME>{name}</SHORT-NAME><FRAME-LENGTH>{size}</FRAME-LENGTH>"
                         f"<PDU-TO-FRAME-MAPPINGS><PDU-TO-FRAME-MAPPING><SHORT-NAME>{name}</SHORT-NAME>"
                         f"<PDU-REF DEST=\"I-SIGNAL-I-PDU\">/P/S/{name}_Pdu</PDU-REF><START-POSITION>0</START-POSITION>"
                         "</PDU-TO-FRAME-MAPPING></PDU-TO-FRAME-MAPPINGS></CAN-FRAME>")
        trig_els.append(f"<CAN-FRAME-TRIGGERING><SHORT-NAME>FT_{name}</SHORT-NAME>"
                        f"<FRAME-REF DEST=\"CAN-FRAME\">/P/S/{name}</FRAME-REF>{fd}"
                        f"<IDENTIFIER>{ident}</IDENTIFIER></CAN-FRAME-TRIGGERING>")
        refs.append(f"<I-SIGNAL-I-PDU-REF-CONDITIONAL><I-SIGNAL-I-PDU-REF DEST=\"I-SIGNAL-I-PDU\">/P/S/{name}_Pdu"
                    "</I-SIGNAL-I-PDU-REF></I-SIGNAL-I-PDU-REF-CONDITIONAL>")
    ids = "".join(f"<DATA-ID>{d}</DATA-ID>" for d in data_ids)
    if e2e_style == "set":
        pdus = "".join(f"<END-TO-END-PROTECTION-I-SIGNAL-I-PDU><I-SIGNAL-I-PDU-REF DEST=\"I-SIGNAL-I-PDU\">"
                       f"/P/S/{m[0]}_Pdu</I-SIGNAL-I-PDU-REF></END-TO-END-PROTECTION-I-SIGNAL-I-PDU>" for m in messages)
        e2e = ("<END-TO-END-PROTECTION-SET><SHORT-NAME>E2E</SHORT-NAME><END-TO-END-PROTECTIONS>"
               "<END-TO-END-PROTECTION><SHORT-NAME>Prot</SHORT-NAME><END-TO-END-PROFILE>"
               f"<CATEGORY>{profile}</CATEGORY><DATA-IDS>{ids}</DATA-IDS>{fields}</END-TO-END-PROFILE>"
               f"<END-TO-END-PROTECTION-I-SIGNAL-I-PDUS>{pdus}</END-TO-END-PROTECTION-I-SIGNAL-I-PDUS>"
               "</END-TO-END-PROTECTION></END-TO-END-PROTECTIONS></END-TO-END-PROTECTION-SET>")
    else:
        e2e = ("<DATA-TRANSFORMATION-SET><SHORT-NAME>X</SHORT-NAME><TRANSFORMATION-TECHNOLOGYS>"
               "<TRANSFORMATION-TECHNOLOGY><SHORT-NAME>E2E</SHORT-NAME><PROTOCOL>E2E</PROTOCOL>"
               "<TRANSFORMATION-DESCRIPTIONS><END-TO-END-TRANSFORMATION-DESCRIPTION>"
               f"<PROFILE-NAME>{profile}</PROFILE-NAME>{fields}</END-TO-END-TRANSFORMATION-DESCRIPTION>"
               "</TRANSFORMATION-DESCRIPTIONS></TRANSFORMATION-TECHNOLOGY></TRANSFORMATION-TECHNOLOGYS>"
               "</DATA-TRANSFORMATION-SET>")
    ecus = ("<I-SIGNAL-I-PDU-GROUP><SHORT-NAME>E_Out</SHORT-NAME><COMMUNICATION-DIRECTION>OUT"
            f"</COMMUNICATION-DIRECTION><I-SIGNAL-I-PDUS>{''.join(refs)}</I-SIGNAL-I-PDUS></I-SIGNAL-I-PDU-GROUP>"
            "<ECU-INSTANCE><SHORT-NAME>E</SHORT-NAME><ASSOCIATED-COM-I-PDU-GROUP-REFS>"
            "<ASSOCIATED-COM-I-PDU-GROUP-REF DEST=\"I-SIGNAL-I-PDU-GROUP\">/P/S/E_Out"
            "</ASSOCIATED-COM-I-PDU-GROUP-REF></ASSOCIATED-COM-I-PDU-GROUP-REFS></ECU-INSTANCE>"
            "<ECU-INSTANCE><SHORT-NAME>T</SHORT-NAME></ECU-INSTANCE>")
    cluster = ("<CAN-CLUSTER><SHORT-NAME>C</SHORT-NAME><CAN-CLUSTER-VARIANTS><CAN-CLUSTER-CONDITIONAL>"
               "<BAUDRATE>500000</BAUDRATE><PHYSICAL-CHANNELS><CAN-PHYSICAL-CHANNEL><SHORT-NAME>Ch</SHORT-NAME>"
               f"<FRAME-TRIGGERINGS>{''.join(trig_els)}</FRAME-TRIGGERINGS></CAN-PHYSICAL-CHANNEL>"
               "</PHYSICAL-CHANNELS></CAN-CLUSTER-CONDITIONAL></CAN-CLUSTER-VARIANTS></CAN-CLUSTER>")
    body = "".join(sig_els + groups + pdu_els + frame_els) + e2e + ecus + cluster
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<AUTOSAR xmlns="{ns}"><AR-PACKAGES><AR-PACKAGE>'
            f"<SHORT-NAME>P</SHORT-NAME><AR-PACKAGES><AR-PACKAGE><SHORT-NAME>S</SHORT-NAME><ELEMENTS>{body}"
            "</ELEMENTS></AR-PACKAGE></AR-PACKAGES></AR-PACKAGE></AR-PACKAGES></AUTOSAR>\n")


P5_MESSAGES = [("Brake", 0x101, [("Brake_CRC", 16, 16), ("Brake_Counter", 32, 8), ("Brake_Value", 0, 16),
                                 ("Brake_Flag", 40, 1)])]


def _mapping(tmp_path, arxml_text, entries=""):
    (tmp_path / "m.arxml").write_text(arxml_text, encoding="utf-8")
    (tmp_path / "m.toml").write_text('[[bus]]\nname = "c"\ndbc = "m.arxml"\nplant_nodes = ["E"]\n'
                                     'tcu_nodes = ["T"]\n' + entries, encoding="utf-8")
    return str(tmp_path / "m.toml")


@pytest.mark.parametrize("style", ["set", "transformer"])
def test_a_profile_5_message_of_an_arxml_is_protected_as_the_file_says(tmp_path, style):
    path = _mapping(tmp_path, _arxml(P5_MESSAGES, style, "PROFILE_05", (0x1234,),
                                     "<MAX-DELTA-COUNTER>3</MAX-DELTA-COUNTER><OFFSET>16</OFFSET>"))
    m = mapping.load(path)
    msg = m.message("Brake")
    p = msg.protection
    assert (p.kind, p.data_id, p.offset_bits, p.max_delta_counter) == ("p5", 0x1234, 16, 3)
    assert (p.crc_signal, p.counter_signal) == ("Brake_CRC", "Brake_Counter")
    assert msg.protection_from_file and msg.signal("Brake_CRC").protection_field == "crc"
    assert m.bus("c").bitrate == 500_000
    assert "protection p5 (crc Brake_CRC, counter Brake_Counter, data id 0x1234, header at byte 2) " \
           "from m.arxml" in mapping.show(m)
    # the frame the codec writes is the reference's
    e2e_p05 = requires.module("e2e.p05")
    t = CodecTable([(msg.message, p)])
    frame = t.encode(0, {"Brake_Value": 700, "Brake_Flag": 1}, counter=9)
    assert e2e_p05.e2e_p05_check(frame, 0x1234, offset=2) and frame[4] == 9


def test_without_an_offset_the_profile_5_header_is_at_the_start(tmp_path):
    msgs = [("M", 0x10, [("M_Value", 24, 16)])]
    m = mapping.load(_mapping(tmp_path, _arxml(msgs, "set", "PROFILE_05", (7,))))
    p = m.message("M").protection
    assert (p.kind, p.offset_bits, p.crc_signal, p.counter_signal) == ("p5", 0, None, None)


def test_the_mapping_overrides_the_files_protection(tmp_path):
    text = _arxml(P5_MESSAGES, "set", "PROFILE_05", (0x1234,), "<OFFSET>16</OFFSET>")
    m = mapping.load(_mapping(tmp_path, text, '[message.Brake]\nprotection = "none"\n'))
    assert m.message("Brake").protection.kind == "none" and not m.message("Brake").protection_from_file
    m = mapping.load(_mapping(tmp_path, text, '[message.Brake]\nprotection = { kind = "p5", data_id = 0x99, '
                                              'offset_bits = 16, crc = "Brake_CRC" }\n'))
    assert m.message("Brake").protection.data_id == 0x99


@pytest.mark.parametrize("profile, fields, ids, words", [
    ("PROFILE_11", "", (1,), ["PROFILE_11", "not supported", "profiles 1, 2, 4, 5 and 7",
                              "give the message's protection"]),
    ("PROFILE_06", "", (1,), ["PROFILE_06", "not supported"]),
    ("PROFILE_07", "", (1,), ["profile 7 header (20 bytes) at bit 0", "8-byte frame"]),
    ("PROFILE_04", "", (1,), ["profile 4 header (12 bytes) at bit 0", "8-byte frame"]),
    ("PROFILE_05", "", (1, 2), ["profile 5 needs one Data ID", "gives 2"]),
    ("PROFILE_05", "<OFFSET>48</OFFSET>", (1,), ["header (3 bytes) at bit 48", "8-byte"]),
    ("PROFILE_01", "<CRC-OFFSET>56</CRC-OFFSET>", (1,), ["CRC at bits 56..63", "no 8-bit signal"]),
])
def test_a_protection_from_the_file_the_codec_cannot_take_is_one_line(tmp_path, profile, fields, ids, words):
    path = _mapping(tmp_path, _arxml(P5_MESSAGES, "set", profile, ids, fields))
    with pytest.raises(mapping.MappingError) as e:
        mapping.load(path)
    text = str(e.value)
    assert "\n" not in text and "m.arxml" in text and "message.Brake" in text
    for w in words:
        assert w in text, text
    # a protection in the mapping (or ignoring the message) is the way out
    assert mapping.load(_mapping(tmp_path, _arxml(P5_MESSAGES, "set", profile, ids, fields),
                                 '[message.Brake]\nprotection = "none"\n')).message("Brake")


@pytest.mark.parametrize("style", ["set", "transformer"])
@pytest.mark.parametrize("profile", ["PROFILE_04", "PROFILE_07"])
def test_a_profile_4_or_7_can_fd_message_of_an_arxml_is_protected_as_the_file_says(tmp_path, style, profile):
    if profile == "PROFILE_04":     # counter 16 bits at byte 2, CRC 32 bits at byte 8, Motorola
        msgs = [("Fd", 0x300, [("Fd_Ctr", 23, 16), ("Fd_Crc", 71, 32), ("Fd_Value", 96, 32)], 16)]
    else:                           # CRC 64 bits at byte 0, counter 32 bits at byte 12
        msgs = [("Fd", 0x300, [("Fd_Crc", 7, 64), ("Fd_Ctr", 103, 32), ("Fd_Value", 160, 32)], 24)]
    text = _arxml(msgs, style, profile, (0xDEADBEEF,), "<MAX-DELTA-COUNTER>5</MAX-DELTA-COUNTER>")
    for _, start, _ in msgs[0][2][:2]:
        text = text.replace(f"MOST-SIGNIFICANT-BYTE-LAST</PACKING-BYTE-ORDER><START-POSITION>{start}<",
                            f"MOST-SIGNIFICANT-BYTE-FIRST</PACKING-BYTE-ORDER><START-POSITION>{start}<")
    path = _mapping(tmp_path, text)
    toml = Path(path).read_text().replace('tcu_nodes = ["T"]', 'tcu_nodes = ["T"]\nfd = true')
    Path(path).write_text(toml)
    m = mapping.load(path)
    msg = m.message("Fd")
    p = msg.protection
    kind = "p4" if profile == "PROFILE_04" else "p7"
    assert (p.kind, p.data_id, p.offset_bits, p.max_delta_counter, p.crc_signal, p.counter_signal) == \
        (kind, 0xDEADBEEF, 0, 5, "Fd_Crc", "Fd_Ctr")
    assert f"protection {kind} (crc Fd_Crc, counter Fd_Ctr, data id 0xDEADBEEF, header at byte 0) from m.arxml" \
        in mapping.show(m)
    assert msg.is_fd and msg.length == (16 if kind == "p4" else 24)
    t = CodecTable([(msg.message, p)])
    frame = t.encode(0, {"Fd_Value": 123456}, counter=300)
    if kind == "p4":
        assert requires.module("e2e.p04").e2e_p04_check(frame, 0xDEADBEEF)
        assert int.from_bytes(frame[2:4], "big") == 300
    else:
        assert requires.module("e2e.p07").e2e_p07_check(frame, 0xDEADBEEF)
        assert int.from_bytes(frame[12:16], "big") == 300
    assert t.decode(0, frame)["Fd_Value"] == 123456


def test_a_profile_1_transformer_gives_its_mode_and_offsets(tmp_path):
    msgs = [("P1", 0x20, [("P1_CRC", 8, 8), ("P1_Ctr", 20, 4), ("P1_Nib", 16, 4), ("P1_Val", 32, 8)])]
    fields = ("<COUNTER-OFFSET>20</COUNTER-OFFSET><CRC-OFFSET>8</CRC-OFFSET><DATA-ID-MODE>LOWER_12_BIT"
              "</DATA-ID-MODE><DATA-ID-NIBBLE-OFFSET>16</DATA-ID-NIBBLE-OFFSET>")
    m = mapping.load(_mapping(tmp_path, _arxml(msgs, "transformer", "PROFILE_01", (0x0ABC,), fields)))
    p = m.message("P1").protection
    assert (p.kind, p.crc_signal, p.counter_signal, p.data_id, p.data_id_mode, p.data_id_nibble_signal) == \
        ("p1", "P1_CRC", "P1_Ctr", 0x0ABC, "nibble", "P1_Nib")


def test_a_broken_arxml_is_one_line_naming_it(tmp_path):
    for text in ("<AUTOSAR><not closed", _arxml(P5_MESSAGES).replace("r4.0", "r9.9")):
        path = _mapping(tmp_path, text)
        with pytest.raises(mapping.MappingError) as e:
            mapping.load(path)
        assert "\n" not in str(e.value) and "m.arxml" in str(e.value) and "bus[0].dbc" in str(e.value)


def test_an_arxml_with_two_clusters_needs_the_bus_to_name_one(tmp_path):
    text = _arxml(P5_MESSAGES, "set", "PROFILE_05", (1,), "<OFFSET>16</OFFSET>")
    two = text.replace("<CAN-CLUSTER><SHORT-NAME>C</SHORT-NAME>",
                       "<CAN-CLUSTER><SHORT-NAME>Other</SHORT-NAME><CAN-CLUSTER-VARIANTS><CAN-CLUSTER-CONDITIONAL>"
                       "<BAUDRATE>250000</BAUDRATE><PHYSICAL-CHANNELS><CAN-PHYSICAL-CHANNEL><SHORT-NAME>Ch"
                       "</SHORT-NAME><FRAME-TRIGGERINGS><CAN-FRAME-TRIGGERING><SHORT-NAME>FT2</SHORT-NAME>"
                       "<FRAME-REF DEST=\"CAN-FRAME\">/P/S/Brake</FRAME-REF><IDENTIFIER>5</IDENTIFIER>"
                       "</CAN-FRAME-TRIGGERING></FRAME-TRIGGERINGS></CAN-PHYSICAL-CHANNEL></PHYSICAL-CHANNELS>"
                       "</CAN-CLUSTER-CONDITIONAL></CAN-CLUSTER-VARIANTS></CAN-CLUSTER>"
                       "<CAN-CLUSTER><SHORT-NAME>C</SHORT-NAME>")
    with pytest.raises(mapping.MappingError, match="CAN clusters Other, C: give the bus's cluster"):
        mapping.load(_mapping(tmp_path, two))
    path = _mapping(tmp_path, two)
    text = Path(path).read_text().replace('dbc = "m.arxml"', 'dbc = "m.arxml"\ncluster = "C"')
    Path(path).write_text(text)
    m = mapping.load(path)
    assert m.message("Brake").frame_id == 0x101 and m.bus("c").bitrate == 500_000
    Path(path).write_text(text.replace('cluster = "C"', 'cluster = "Body"'))
    with pytest.raises(mapping.MappingError, match="no CAN cluster 'Body'"):
        mapping.load(path)


# ---------------------------------------------------------------------------
# KCD and SYM
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["kcd", "sym"])
def test_kcd_and_sym_files_load_with_the_dbcs_layouts(tmp_path, fmt):
    dbc = matrix.read_matrix(str(DBC))
    path = tmp_path / f"vehicle_pt.{fmt}"
    cantools.database.dump_file(dbc, str(path))
    db = matrix.read_matrix(str(path))
    ta = CodecTable(list(dbc.messages))
    tb = CodecTable([db.get_message_by_name(m.name) for m in dbc.messages])
    rng = random.Random(fmt)
    for i, m in enumerate(dbc.messages):
        for _ in range(20):
            values = {s.name: rng.uniform(*mapping._signal_range(s)) for s in m.signals}
            assert ta.encode(i, values) == tb.encode(i, values), m.name
    if fmt == "kcd":      # a KCD names senders: the example's mapping serves it
        m = mapping.load(mapping.find_mapping("vehicle"), dbc={"pt": str(path)})
        assert m.bus("pt").dbc == str(path) and len(m.codec_order("pt")) == 12


def test_a_matrix_cantools_cannot_parse_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "bad.kcd"
    bad.write_text("<NetworkDefinition><Bus", encoding="utf-8")
    with pytest.raises(ValueError) as e:
        matrix.read_matrix(str(bad))
    assert "\n" not in str(e.value) and "bad.kcd" in str(e.value) and "as KCD" in str(e.value)


# ---------------------------------------------------------------------------
# Serving it
# ---------------------------------------------------------------------------

@pytest.mark.slow
def test_the_demo_serves_the_arxml_mapping_and_its_frames_decode(tmp_path):
    """The plant and the TCU stub over vehicle_arxml.toml on the embedded
    transport: every message of both buses goes both ways, none rejected
    (the TCU node checks the plant's P1 frames the ARXML protects, the loop
    the TCU's)."""
    proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", "--mapping", "vehicle_arxml",
                           "--duration", "3", "--out", str(tmp_path), "--priority", "0", "--quiet"],
                          capture_output=True, text=True, timeout=180, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["mapping"].endswith("vehicle_arxml.toml")
    stats = json.loads((tmp_path / "serve-stats.json").read_text())
    counts = stats["counts"]
    assert set(counts["channels"]) == {"pt", "io"}
    assert "pt:TCU_TorqueReq" in counts["tcu_messages"] and "pt:ECM_Torque" in counts["plant_messages"]
    for name, c in counts["tcu_messages"].items():
        assert c["accepted"] > 0 and c["bad_crc"] == c["bad_counter"] == c["bad_length"] == 0, name
    for name, c in counts["plant_messages"].items():
        assert c["sent"] > 0, name
    for name, r in summary["tcu"]["received"].items():
        assert r["accepted"] > 0 and not any(r["rejected"].values()), (name, r)


def test_the_generator_writes_profiles_4_5_and_7_that_read_back_as_the_mapping_gave_them(tmp_path):
    """A CAN FD bus whose mapping protects a message with P5, one with P4, one with P7:
    written as ARXML by can_dbc.to_arxml and read back without the mapping's
    protection, the messages have the same protection and give the same frames."""
    from cantools.database.can import Database, Message, Node, Signal
    from cantools.database.conversion import BaseConversion

    msgs = [Message(frame_id=0x120, name="P5_Msg", length=8, senders=["E"], cycle_time=10, signals=[
                Signal("P5_Crc", start=16, length=16), Signal("P5_Ctr", start=32, length=8),
                Signal("P5_Value", start=0, length=16, unit="Nm", minimum=0, maximum=1000,
                       conversion=BaseConversion.factory(scale=0.5, offset=0))]),
            Message(frame_id=0x130, name="P4_Msg", length=24, senders=["E"], cycle_time=20, is_fd=True, signals=[
                Signal("P4_Ctr", start=23, length=16, byte_order="big_endian"),
                Signal("P4_Crc", start=71, length=32, byte_order="big_endian"),
                Signal("P4_Value", start=96, length=32, is_signed=True)]),
            Message(frame_id=0x140, name="P7_Msg", length=32, senders=["E"], cycle_time=20, is_fd=True, signals=[
                Signal("P7_Crc", start=71, length=64, byte_order="big_endian"),
                Signal("P7_Ctr", start=167, length=32, byte_order="big_endian"),
                Signal("P7_Value", start=0, length=64)])]
    db = Database(messages=msgs, nodes=[Node("E"), Node("T")], strict=False)
    (tmp_path / "fd.dbc").write_text(db.as_dbc_string(), encoding="utf-8")
    prots = ('[message.P5_Msg]\nprotection = { kind = "p5", data_id = 0x0456, offset_bits = 16, crc = "P5_Crc", '
             'counter = "P5_Ctr", max_delta_counter = 4 }\n'
             '[message.P4_Msg]\nprotection = { kind = "p4", data_id = 0x12345678, crc = "P4_Crc", counter = "P4_Ctr" }\n'
             '[message.P7_Msg]\nprotection = { kind = "p7", data_id = 0x9ABCDEF0, offset_bits = 64, crc = "P7_Crc", '
             'counter = "P7_Ctr", max_delta_counter = 9 }\n')
    head = '[[bus]]\nname = "fd"\ndbc = "{}"\nbitrate = 500000\ndata_bitrate = 2000000\nfd = true\n' \
           'plant_nodes = ["E"]\ntcu_nodes = ["T"]\n'
    (tmp_path / "dbc.toml").write_text(head.format("fd.dbc") + prots, encoding="utf-8")
    src = mapping.load(str(tmp_path / "dbc.toml"))
    (tmp_path / "fd.arxml").write_text(to_arxml.arxml_text(src, "fd"), encoding="utf-8")
    (tmp_path / "arxml.toml").write_text(head.format("fd.arxml"), encoding="utf-8")
    got = mapping.load(str(tmp_path / "arxml.toml"))
    assert got.bus("fd").fd and got.bus("fd").data_bitrate == 2_000_000
    for m in src.codec_order("fd"):
        a = got.message(m.name)
        assert a.protection == m.protection and a.protection_from_file, m.name
        assert (a.frame_id, a.length, a.is_fd, a.cycle_ms) == (m.frame_id, m.length, m.is_fd, m.cycle_ms)
    (ta, ma), (tb, mb) = tables(src, "fd"), tables(got, "fd")
    assert [m.name for m in ma] == [m.name for m in mb]
    rng = random.Random(45)
    for i, m in enumerate(ma):
        for counter in range(0, 70000, 997):
            values = {s.name: rng.uniform(*mapping._signal_range(s.signal)) for s in m.signals
                      if s.protection_field is None}
            assert ta.encode(i, values, counter=counter) == tb.encode(i, values, counter=counter), m.name


def test_the_template_of_an_arxml_names_its_e2e_protection_and_loads_with_it(tmp_path):
    out = tmp_path / "from_arxml.toml"
    text = mapping.template(str(ARXML), tcu_nodes=["TCU"], out_path=str(out))
    assert ("# protection p1 (crc ESP_Motion_CRC, counter ESP_Motion_Ctr, data id 0x074B (nibble)): from "
            "vehicle_pt.arxml") in text
    assert "#   (the protection's Data ID nibble: written or checked by the protection, no entry)" in text
    assert 'dbc = "' in text and "vehicle_pt.arxml" in text and "bitrate = 500000" in text
    out.write_text(text, encoding="utf-8")
    m = mapping.load(str(out))
    p = m.message("ESP_Motion").protection
    assert (p.kind, p.data_id, p.data_id_mode) == ("p1", 0x074B, "nibble")
    assert m.message("ECM_Speed").protection.kind == "none"      # XOR: not in the file
