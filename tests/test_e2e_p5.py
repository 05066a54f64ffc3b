"""AUTOSAR E2E Profile 5 (protection kind ``p5``) against the reference on PyPI.

``autosar-e2e`` (module ``e2e``) implements the AUTOSAR E2E Protocol
Specification in C. For many random payloads, frame lengths (classic and CAN
FD), header offsets, Data IDs and counters, the table codec in C
(can_dbc/csrc/can_table.c through ``CodecTable``) and the Python codec
(``can_dbc.codec.p5_protect``) write the same CRC and counter bytes as
``e2e.p05.e2e_p05_protect``; the reference accepts what both write, and a
frame with any one bit changed is rejected by both codecs and the reference.
The receiver's counter check (repeat, a jump above ``max_delta_counter``,
wrap 255 -> 0) and the one-line refusals of a bad description are here too.
"""

import random

import pytest
import requires

from can_dbc import codec
from can_dbc.protection import Protection, ProtectionError, parse_protection
from can_dbc.table import CodecTable, TableError

e2e_p05 = requires.module("e2e.p05")
e2e_crc = requires.module("e2e.crc")
cantools = requires.module("cantools")
from cantools.database.can import Message, Signal

LENGTHS = (3, 4, 8, 12, 16, 32, 64)


def p5_message(length, offset_bits, with_signals=True, frame_id=0x123):
    h = offset_bits // 8
    signals = []
    if with_signals:
        signals = [Signal("E2E_CRC", start=8 * h, length=16, byte_order="little_endian"),
                   Signal("E2E_Counter", start=8 * h + 16, length=8)]
    if length >= h + 4:          # a payload signal after the header
        signals.append(Signal("Value", start=8 * (h + 3), length=8))
    return Message(frame_id=frame_id, name="P5_Msg", length=length, signals=signals,
                   is_fd=length > 8)


def p5_table(length, offset_bits, data_id, with_signals=True, max_delta=2):
    prot = Protection(kind="p5", crc_signal="E2E_CRC" if with_signals else None,
                      counter_signal="E2E_Counter" if with_signals else None, data_id=data_id,
                      offset_bits=offset_bits, max_delta_counter=max_delta)
    return CodecTable([(p5_message(length, offset_bits, with_signals), prot)])


def reference(data, data_id, counter, offset_bits):
    """``data`` protected by the reference with counter ``counter``."""
    buf = bytearray(data)
    buf[offset_bits // 8 + 2] = (counter - 1) & 0xFF      # it increments before it protects
    e2e_p05.e2e_p05_protect(buf, data_id, offset=offset_bits // 8, increment_counter=True)
    return bytes(buf)


def test_the_crc_is_crc16_ccitt_false_in_c_and_python():
    from can_dbc._can_table import lib
    lib = requires.built_with(lib, "ct_crc16_ccitt_false")
    check = b"123456789"
    assert codec.crc16_ccitt_false(check) == lib.ct_crc16_ccitt_false(check, 9) == 0x29B1
    rng = random.Random(5)
    for _ in range(500):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 70)))
        ref = e2e_crc.calculate_crc16(data)
        assert codec.crc16_ccitt_false(data) == lib.ct_crc16_ccitt_false(data, len(data)) == ref


def test_both_codecs_write_the_references_crc_and_counter_for_random_frames():
    rng = random.Random(27)
    cases = 0
    for length in LENGTHS:
        for _ in range(6):
            offset_bits = 8 * rng.randrange(0, length - 2)
            data_id = rng.choice((0x0000, 0xFFFF, rng.randrange(0x10000)))
            with_signals = rng.random() < 0.5
            table = p5_table(length, offset_bits, data_id, with_signals)
            for _ in range(40):
                counter = rng.randrange(0, 1 << 32)
                payload = bytes(rng.randrange(256) for _ in range(length))
                ref = reference(payload, data_id, counter, offset_bits)
                assert table.protect(0, payload, counter) == ref, (length, offset_bits, data_id, counter)
                assert codec.p5_protect(payload, data_id, counter, offset_bits) == ref
                assert e2e_p05.e2e_p05_check(ref, data_id, offset=offset_bits // 8)
                cases += 1
    assert cases == len(LENGTHS) * 6 * 40


def test_a_frame_with_one_bit_changed_is_rejected_by_both_codecs_and_the_reference():
    rng = random.Random(2705)
    for length in (8, 16, 64):
        offset_bits = 8 * (length // 4)
        data_id = rng.randrange(0x10000)
        table = p5_table(length, offset_bits, data_id)
        for _ in range(30):
            counter = rng.randrange(256)
            good = reference(bytes(rng.randrange(256) for _ in range(length)), data_id, counter,
                             offset_bits)
            assert table.check(0, good) == "ok"
            assert codec.p5_check(good, data_id, offset_bits) == (True, counter)
            bit = rng.randrange(8 * length)
            bad = bytearray(good)
            bad[bit // 8] ^= 1 << (bit % 8)
            bad = bytes(bad)
            assert not e2e_p05.e2e_p05_check(bad, data_id, offset=offset_bits // 8)
            assert table.check(0, bad) == "bad_crc", (length, bit)
            assert codec.p5_check(bad, data_id, offset_bits)[0] is False
        # another Data ID: the same frame is rejected (masquerading)
        assert table.check(0, reference(bytes(length), data_id ^ 0x0100, 1, offset_bits)) == "bad_crc"


def test_the_receivers_counter_check_repeats_jumps_and_wraps():
    table = p5_table(8, 0, 0x0ABC, max_delta=3)
    state = table.new_state()

    def frame(counter):
        return reference(bytes(8), 0x0ABC, counter, 0)

    assert table.check(0, frame(250), state) == "ok"           # the first frame: any counter
    assert table.check(0, frame(250), state) == "bad_counter"  # repeated
    assert table.check(0, frame(253), state) == "ok"           # +3: max_delta_counter
    assert table.check(0, frame(1), state) == "bad_counter"    # 253 -> 1: +4
    assert state.last_counter == 253                           # a rejected frame moves nothing
    assert table.check(0, frame(255), state) == "ok"
    assert table.check(0, frame(1), state) == "ok"             # 255 -> 1 over the wrap: +2


def test_the_counter_jump_above_max_delta_counter_is_rejected_and_the_state_stays():
    table = p5_table(8, 0, 0x0ABC, max_delta=3)
    state = table.new_state()
    frames = {c: reference(bytes(8), 0x0ABC, c, 0) for c in range(256)}
    assert table.check(0, frames[254], state) == "ok"
    assert table.check(0, frames[2], state) == "bad_counter"   # 254 -> 2: +4
    assert state.last_counter == 254
    assert table.check(0, frames[255], state) == "ok"
    assert table.check(0, frames[0], state) == "ok"            # wraps 255 -> 0
    assert table.check(0, frames[3], state) == "ok"            # +3
    assert table.check(0, frames[3], state) == "bad_counter"
    assert table.check(0, frames[3][:7], state) == "bad_length"


def test_encode_with_a_counter_writes_the_header_over_the_named_signals():
    table = p5_table(8, 16, 0x4242)
    data = table.encode(0, {"Value": 77}, counter=258)
    assert data == reference(data, 0x4242, 2, 16)
    decoded = table.decode(0, data)
    assert decoded["E2E_Counter"] == 2 and decoded["Value"] == 77
    assert decoded["E2E_CRC"] == data[2] | data[3] << 8
    with pytest.raises(TableError, match="written by the protection"):
        table.encode(0, {"E2E_Counter": 1}, counter=0)


@pytest.mark.parametrize("spec, words", [
    ({"kind": "p5"}, ["needs data_id"]),
    ({"kind": "p5", "data_id": 0x10000}, ["data_id", "0..65535"]),
    ({"kind": "p5", "data_id": 1, "offset_bits": 4}, ["offset_bits", "multiple of 8"]),
    ({"kind": "p5", "data_id": 1, "offset_bits": 496}, ["offset_bits", "0 to 488"]),
    ({"kind": "p1", "data_id": 1, "crc": "C", "counter": "Z", "offset_bits": 8}, ["offset_bits", "only"]),
    ({"kind": "p5", "data_id": 1, "max_delta_counter": 256}, ["max_delta_counter", "1..255"]),
    ({"kind": "p1", "data_id": 1, "crc": "C", "counter": "Z", "max_delta_counter": 15},
     ["max_delta_counter", "1..14"]),
])
def test_bad_p5_descriptions_are_one_line_errors(spec, words):
    with pytest.raises(ProtectionError) as e:
        parse_protection(spec, "f.toml: message.M.protection")
    text = str(e.value)
    assert "\n" not in text and text.startswith("f.toml: message.M.protection")
    for w in words:
        assert w in text, text


def test_a_p5_description_parses_with_its_defaults():
    p = parse_protection({"kind": "p5", "data_id": 0x1234}, "w")
    assert (p.kind, p.data_id, p.offset_bits, p.max_delta_counter, p.signals()) == ("p5", 0x1234, 0, 2, ())
    p = parse_protection({"kind": "p5", "data_id": 7, "crc": "C", "counter": "Z", "offset_bits": 24,
                          "max_delta_counter": 200}, "w")
    assert (p.offset_bits, p.max_delta_counter, p.signals()) == (24, 200, ("C", "Z"))


@pytest.mark.parametrize("length, offset_bits, signals, words", [
    (8, 48, None, ["header", "bit 48", "8 bytes"]),
    (8, 0, [Signal("E2E_CRC", start=0, length=8), Signal("E2E_Counter", start=16, length=8)],
     ["E2E_CRC", "16 bits at byte 0"]),
    (8, 0, [Signal("E2E_CRC", start=7, length=16, byte_order="big_endian"),
            Signal("E2E_Counter", start=16, length=8)], ["E2E_CRC", "low byte first"]),
    (8, 0, [Signal("E2E_CRC", start=0, length=16), Signal("E2E_Counter", start=20, length=8)],
     ["E2E_Counter", "8 bits at byte 2"]),
    (8, 0, [Signal("Other", start=12, length=8)], ["Other", "header", "bytes 0..2"]),
])
def test_a_p5_layout_the_codec_cannot_take_is_a_one_line_error(length, offset_bits, signals, words):
    if signals is None:
        signals = []
    msg = Message(frame_id=0x10, name="P5_Msg", length=length, signals=signals)
    names = {s.name for s in signals}
    prot = Protection(kind="p5", data_id=1, offset_bits=offset_bits,
                      crc_signal="E2E_CRC" if "E2E_CRC" in names else None,
                      counter_signal="E2E_Counter" if "E2E_Counter" in names else None)
    with pytest.raises(TableError) as e:
        CodecTable([(msg, prot)])
    text = str(e.value)
    assert "\n" not in text and "P5_Msg" in text
    for w in words:
        assert w in text, text


def test_the_codec_benchmark_takes_a_p5_message_as_it_takes_the_others():
    """ct_bench_tick replays 16 prepared frames: with an 8-bit counter it
    starts the receive state again at each run, so every frame is accepted
    (it checked the 16th against the 1st and refused it)."""
    from can_dbc import table as table_mod

    t = p5_table(8, 0, 0x0101)
    call = table_mod._bench_calls(t, [0], [0])[0]
    table_mod._bench_call(t, call, 1000)          # raises when a frame is rejected
    assert call["accepted"][0] == 1000


@pytest.mark.slow
def test_the_loop_and_the_tcu_node_speak_p5_on_the_embedded_transport(tmp_path):
    """The example matrix with three messages on Profile 5 (their headers in
    bytes 5..7, which no signal takes): one the TCU sends (TCU_TorqueReq,
    instead of its P1) and two the plant sends (GW_Terminal, IC_Status). The
    demo runs the loop and the TCU stub on it: every frame of theirs is
    accepted on both sides, none rejected."""
    import json
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    from can_dbc import mapping

    src = mapping.find_mapping("vehicle")
    here = os.path.dirname(src)
    text = open(src, encoding="utf-8").read()
    text = re.sub(r'dbc = "([^"]+)"', lambda m: f'dbc = "{os.path.normpath(os.path.join(here, m.group(1)))}"',
                  text)
    text = re.sub(r'\[message\.TCU_TorqueReq\]\nprotection = [^\n]+\n',
                  '[message.TCU_TorqueReq]\nprotection = { kind = "p5", data_id = 0x2E70, offset_bits = 40 }\n', text)
    text += ('\n[message.GW_Terminal]\nprotection = { kind = "p5", data_id = 0x3B00, offset_bits = 40 }\n'
             '\n[message.IC_Status]\nprotection = { kind = "p5", data_id = 0x3C00, offset_bits = 40, '
             'max_delta_counter = 3 }\n')
    path = tmp_path / "vehicle_p5.toml"
    path.write_text(text, encoding="utf-8")
    m = mapping.load(str(path))
    assert [x.name for x in m.messages if x.protection.kind == "p5"] == ["GW_Terminal", "IC_Status", "TCU_TorqueReq"]
    proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", "--mapping", str(path), "--duration", "3",
                           "--out", str(tmp_path / "out"), "--priority", "0", "--quiet"],
                          capture_output=True, text=True, timeout=180, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr
    stats = json.loads((tmp_path / "out" / "serve-stats.json").read_text())
    counts = stats["counts"]
    c = counts["tcu_messages"]["pt:TCU_TorqueReq"]
    assert c["accepted"] > 0 and c["bad_crc"] == c["bad_counter"] == c["bad_length"] == 0, c
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    received = summary["tcu"]["received"]
    for name in ("pt:GW_Terminal", "pt:IC_Status"):
        assert counts["plant_messages"][name]["sent"] > 0
        r = received[name]
        assert r["accepted"] > 0 and not any(r["rejected"].values()), (name, r)
