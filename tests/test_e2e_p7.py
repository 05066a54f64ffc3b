"""AUTOSAR E2E Profile 7 (protection kind ``p7``, CAN FD) against the reference on PyPI.

The table codec in C and ``can_dbc.codec.p7_protect`` write the header
``e2e.p07.e2e_p07_protect`` writes (CRC-64, length, 32-bit counter, 32-bit
Data ID, each big endian, at the header's offset) for random CAN FD payloads,
lengths, offsets, Data IDs and counters; a frame with any bit changed, or for
another Data ID, is rejected by both codecs and the reference; the 32-bit
counter wraps and a jump above max_delta_counter is refused.
"""

import random

import pytest
import requires

from can_dbc import codec
from can_dbc.protection import Protection, ProtectionError, parse_protection
from can_dbc.table import CodecTable, TableError

e2e_p07 = requires.module("e2e.p07")
e2e_crc = requires.module("e2e.crc")
cantools = requires.module("cantools")
from cantools.database.can import Message, Signal

FD_LENGTHS = (20, 24, 32, 48, 64)


def p7_table(length, offset_bits, data_id, with_signals=False, max_delta=2):
    h = offset_bits // 8
    signals = []
    if with_signals:
        signals = [Signal("CRC", start=8 * h + 7, length=64, byte_order="big_endian"),
                   Signal("Ctr", start=8 * (h + 12) + 7, length=32, byte_order="big_endian")]
    msg = Message(frame_id=0x19, name="P7_Msg", length=length, signals=signals, is_fd=True)
    prot = Protection(kind="p7", data_id=data_id, offset_bits=offset_bits, max_delta_counter=max_delta,
                      crc_signal="CRC" if with_signals else None, counter_signal="Ctr" if with_signals else None)
    return CodecTable([(msg, prot)])


def reference(data, data_id, counter, offset_bits):
    buf = bytearray(data)
    h = offset_bits // 8
    buf[h + 12:h + 16] = ((counter - 1) & 0xFFFFFFFF).to_bytes(4, "big")     # it increments first
    e2e_p07.e2e_p07_protect(buf, data_id, offset=h, increment_counter=True)
    return bytes(buf)


def test_the_crc_is_crc64_xz_in_c_and_python():
    from can_dbc._can_table import lib
    lib = requires.built_with(lib, "ct_crc64")
    ones = 0xFFFFFFFFFFFFFFFF
    assert lib.ct_crc64(b"123456789", 9) == codec.crc64(b"123456789") ^ ones == 0x995DC9BBDF1939FA
    rng = random.Random(7)
    for _ in range(300):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 70)))
        assert lib.ct_crc64(data, len(data)) == e2e_crc.calculate_crc64(data) == codec.crc64(data) ^ ones


def test_both_codecs_write_the_references_header_for_random_frames():
    rng = random.Random(77)
    for length in FD_LENGTHS:
        for _ in range(6):
            offset_bits = 8 * rng.randrange(0, length - 19)
            data_id = rng.choice((0, 0xFFFFFFFF, rng.randrange(1 << 32)))
            table = p7_table(length, offset_bits, data_id, with_signals=rng.random() < 0.5)
            for _ in range(30):
                counter = rng.randrange(1 << 32)
                payload = bytes(rng.randrange(256) for _ in range(length))
                ref = reference(payload, data_id, counter, offset_bits)
                assert table.protect(0, payload, counter) == ref, (length, offset_bits, counter)
                assert codec.p7_protect(payload, data_id, counter, offset_bits) == ref
                assert e2e_p07.e2e_p07_check(ref, data_id, offset=offset_bits // 8)
                assert table.check(0, ref) == "ok"
                assert codec.p7_check(ref, data_id, offset_bits) == (True, counter)


def test_a_changed_bit_or_data_id_is_rejected_by_both_codecs_and_the_reference():
    rng = random.Random(707)
    table = p7_table(48, 96, 0x01020304)
    for _ in range(60):
        good = reference(bytes(rng.randrange(256) for _ in range(48)), 0x01020304, rng.randrange(1 << 32), 96)
        bit = rng.randrange(8 * 48)
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        assert table.check(0, bytes(bad)) == "bad_crc"
        assert not e2e_p07.e2e_p07_check(bytes(bad), 0x01020304, offset=12)
        assert codec.p7_check(bytes(bad), 0x01020304, 96)[0] is False
    assert table.check(0, reference(bytes(48), 0x01020305, 1, 96)) == "bad_crc"


def test_the_32_bit_counter_wraps_and_jumps_are_refused():
    table = p7_table(20, 0, 9, max_delta=2)
    state = table.new_state()
    frame = {c: reference(bytes(20), 9, c, 0) for c in (0x7FFFFFFF, 0x80000000, 0xFFFFFFFD, 0xFFFFFFFE, 0, 3)}
    assert table.check(0, frame[0x7FFFFFFF], state) == "ok"
    assert table.check(0, frame[0x80000000], state) == "ok"    # above 2^31: no sign trouble
    assert table.check(0, frame[0x7FFFFFFF], state) == "bad_counter"
    state.last_counter = -1
    assert table.check(0, frame[0xFFFFFFFD], state) == "ok"
    assert table.check(0, frame[0xFFFFFFFE], state) == "ok"
    assert table.check(0, frame[0], state) == "ok"              # over the wrap: +2
    assert table.check(0, frame[3], state) == "bad_counter"     # +3
    assert table.check(0, frame[0], state) == "bad_counter"     # repeated
    assert state.last_counter == 0


def test_bad_p7_descriptions_are_one_line_errors():
    for spec, word in (({"kind": "p7"}, "needs data_id"), ({"kind": "p7", "data_id": 1 << 32}, "0..4294967295"),
                       ({"kind": "p7", "data_id": 1, "offset_bits": 360}, "0 to 352")):
        with pytest.raises(ProtectionError) as e:
            parse_protection(spec, "f.toml: message.M.protection")
        assert "\n" not in str(e.value) and word in str(e.value), str(e.value)
    msg = Message(frame_id=0x10, name="P7_Msg", length=16, signals=[], is_fd=True)
    with pytest.raises(TableError, match="E2E Profile 7 header .20 bytes at bit 0. does not fit the message's 16"):
        CodecTable([(msg, Protection(kind="p7", data_id=1))])
