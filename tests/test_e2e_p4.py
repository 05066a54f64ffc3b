"""AUTOSAR E2E Profile 4 (protection kind ``p4``, CAN FD) against the reference on PyPI.

The table codec in C and ``can_dbc.codec.p4_protect`` write the header
``e2e.p04.e2e_p04_protect`` writes (length, 16-bit counter, 32-bit Data ID,
CRC-32P4, each big endian, at the header's offset) for random CAN FD payloads,
lengths, offsets, Data IDs and counters; a frame with any bit changed, another
length or another Data ID is rejected by both codecs and the reference.
"""

import random

import pytest
import requires

from can_dbc import codec
from can_dbc.protection import Protection, ProtectionError, parse_protection
from can_dbc.table import CodecTable, TableError

e2e_p04 = requires.module("e2e.p04")
e2e_crc = requires.module("e2e.crc")
cantools = requires.module("cantools")
from cantools.database.can import Message, Signal

FD_LENGTHS = (12, 16, 20, 24, 32, 48, 64)


def p4_table(length, offset_bits, data_id, with_signals=False, max_delta=2):
    h = offset_bits // 8
    signals = []
    if with_signals:
        signals = [Signal("Ctr", start=8 * (h + 2) + 7, length=16, byte_order="big_endian"),
                   Signal("CRC", start=8 * (h + 8) + 7, length=32, byte_order="big_endian")]
    msg = Message(frame_id=0x18, name="P4_Msg", length=length, signals=signals, is_fd=True)
    prot = Protection(kind="p4", data_id=data_id, offset_bits=offset_bits, max_delta_counter=max_delta,
                      crc_signal="CRC" if with_signals else None, counter_signal="Ctr" if with_signals else None)
    return CodecTable([(msg, prot)])


def reference(data, data_id, counter, offset_bits):
    buf = bytearray(data)
    h = offset_bits // 8
    buf[h + 2:h + 4] = ((counter - 1) & 0xFFFF).to_bytes(2, "big")     # it increments first
    e2e_p04.e2e_p04_protect(buf, data_id, offset=h, increment_counter=True)
    return bytes(buf)


def test_the_crc_is_crc32_p4_in_c_and_python():
    from can_dbc._can_table import lib
    lib = requires.built_with(lib, "ct_crc32_p4")
    assert lib.ct_crc32_p4(b"123456789", 9) == codec.crc32_p4(b"123456789") ^ 0xFFFFFFFF == 0x1697D06A
    rng = random.Random(4)
    for _ in range(300):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 70)))
        assert lib.ct_crc32_p4(data, len(data)) == e2e_crc.calculate_crc32_p4(data) == \
            codec.crc32_p4(data) ^ 0xFFFFFFFF


def test_both_codecs_write_the_references_header_for_random_frames():
    rng = random.Random(44)
    for length in FD_LENGTHS:
        for _ in range(6):
            offset_bits = 8 * rng.randrange(0, length - 11)
            data_id = rng.choice((0, 0xFFFFFFFF, rng.randrange(1 << 32)))
            table = p4_table(length, offset_bits, data_id, with_signals=rng.random() < 0.5)
            for _ in range(30):
                counter = rng.randrange(1 << 32)
                payload = bytes(rng.randrange(256) for _ in range(length))
                ref = reference(payload, data_id, counter, offset_bits)
                assert table.protect(0, payload, counter) == ref, (length, offset_bits, counter)
                assert codec.p4_protect(payload, data_id, counter, offset_bits) == ref
                assert e2e_p04.e2e_p04_check(ref, data_id, offset=offset_bits // 8)
                assert table.check(0, ref) == "ok"
                assert codec.p4_check(ref, data_id, offset_bits) == (True, counter & 0xFFFF)


def test_a_changed_bit_length_or_data_id_is_rejected_by_both_codecs_and_the_reference():
    rng = random.Random(404)
    table = p4_table(32, 64, 0x0A0B0C0D)
    for _ in range(60):
        good = reference(bytes(rng.randrange(256) for _ in range(32)), 0x0A0B0C0D, rng.randrange(65536), 64)
        bit = rng.randrange(8 * 32)
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        assert table.check(0, bytes(bad)) == "bad_crc"
        assert not e2e_p04.e2e_p04_check(bytes(bad), 0x0A0B0C0D, offset=8)
        assert codec.p4_check(bytes(bad), 0x0A0B0C0D, 64)[0] is False
    # a frame protected for another Data ID: its Data ID field and CRC differ
    assert table.check(0, reference(bytes(32), 0x0A0B0C0E, 1, 64)) == "bad_crc"


def test_the_16_bit_counter_wraps_and_jumps_are_refused():
    table = p4_table(16, 0, 77, max_delta=2)
    state = table.new_state()
    frame = {c: reference(bytes(16), 77, c, 0) for c in (65534, 65535, 0, 1, 4)}
    assert table.check(0, frame[65534], state) == "ok"
    assert table.check(0, frame[65535], state) == "ok"
    assert table.check(0, frame[1], state) == "ok"              # 65535 -> 1 over the wrap: +2
    assert table.check(0, frame[4], state) == "bad_counter"     # +3
    assert table.check(0, frame[1], state) == "bad_counter"     # repeated
    assert state.last_counter == 1


@pytest.mark.parametrize("spec, words", [
    ({"kind": "p4"}, ["needs data_id"]),
    ({"kind": "p4", "data_id": 1 << 32}, ["data_id", "0..4294967295"]),
    ({"kind": "p4", "data_id": 1, "offset_bits": 424}, ["offset_bits", "0 to 416"]),
    ({"kind": "p5", "data_id": 0x10000}, ["data_id", "0..65535"]),
])
def test_bad_p4_descriptions_are_one_line_errors(spec, words):
    with pytest.raises(ProtectionError) as e:
        parse_protection(spec, "f.toml: message.M.protection")
    assert "\n" not in str(e.value)
    for w in words:
        assert w in str(e.value), str(e.value)


@pytest.mark.parametrize("length, offset_bits, signals, words", [
    (8, 0, [], ["header", "12 bytes", "8 bytes"]),
    (16, 0, [Signal("Ctr", start=16, length=16), Signal("CRC", start=71, length=32, byte_order="big_endian")],
     ["Ctr", "16 bits at byte 2", "high byte first"]),
    (16, 0, [Signal("X", start=40, length=8)], ["X", "lies on the E2E Profile 4 header", "bytes 0..11"]),
])
def test_a_p4_layout_the_codec_cannot_take_is_a_one_line_error(length, offset_bits, signals, words):
    msg = Message(frame_id=0x10, name="P4_Msg", length=length, signals=signals, is_fd=length > 8)
    names = {s.name for s in signals}
    prot = Protection(kind="p4", data_id=1, offset_bits=offset_bits,
                      crc_signal="CRC" if "CRC" in names else None, counter_signal="Ctr" if "Ctr" in names else None)
    with pytest.raises(TableError) as e:
        CodecTable([(msg, prot)])
    assert "\n" not in str(e.value)
    for w in words:
        assert w in str(e.value), str(e.value)
