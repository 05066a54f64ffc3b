"""The table-driven CAN codec (can_dbc/csrc/can_table.c, can_dbc/table.py).

- Random DBC layouts (hypothesis): byte orders, start bits, lengths 1-64,
  signed/unsigned, float32/float64, integer and fractional factors and
  offsets, limits or none, multiplexers with several branches (signals in
  more than one branch, a nested multiplexer), classic and FD lengths up to
  64 bytes. The C pack equals cantools' encode and the C unpack equals
  cantools' decode, bit for bit.
- Every protection against a reference written here from its definition
  (bitwise CRCs, no table), the published CRC check values and known frames
  of AUTOSAR E2E Profiles 1 and 2.
- The project's contract: the table codec on can_dbc/dct_hil.dbc (and the
  one the loop builds from the default mapping) gives the frames of
  can_dbc.codec and of cantools with a CRC written here, decodes as they do,
  and accepts and rejects the same frames as can_dbc.codec's receiver.
"""

import ctypes
import math
import random
import struct

import pytest
import requires
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from can_dbc import codec, table
from can_dbc.protection import KINDS, P1_DATA_ID_MODES, Protection

cantools = requires.module("cantools")
from cantools.database.can import Message, Signal
from cantools.database.conversion import BaseConversion

# Every property test: no example database on disk, no deadline (the first
# examples build the cffi tables), the same number of examples each run.
SETTINGS = settings(max_examples=300, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


@pytest.fixture(scope="module")
def c():
    from can_dbc._can_table import (  # built by scripts/setup: a missing build fails here
        ffi,
        lib,
    )
    assert hasattr(lib, "ct_encode"), "can_dbc._can_table does not hold the table codec"
    return ffi, lib


# ---------------------------------------------------------------------------
# References written from the definitions
# ---------------------------------------------------------------------------

def ref_crc8(data, poly, init, xorout):
    """Bitwise CRC-8, not reflected."""
    crc = init
    for byte in bytes(data):
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ xorout


def ref_j1850(data):
    return ref_crc8(data, 0x1D, 0xFF, 0xFF)


def ref_h2f(data):
    return ref_crc8(data, 0x2F, 0xFF, 0xFF)


def same_float(a, b):
    """Bit-identical doubles (any NaN equals any NaN)."""
    a, b = float(a), float(b)
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return struct.pack("<d", a) == struct.pack("<d", b)


def field_range(sig):
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def ref_limit(sig, v):
    """The sender's limits (can_table.h): NaN -> 0, then [minimum, maximum] when minimum < maximum."""
    v = float(v)
    if math.isnan(v):
        v = 0.0
    lo = -math.inf if sig.minimum is None else float(sig.minimum)
    hi = math.inf if sig.maximum is None else float(sig.maximum)
    if lo < hi:
        v = min(max(v, lo), hi)
    return v


def ref_raw(sig, v):
    """The raw value cantools scales v to, kept inside the bit field."""
    v = ref_limit(sig, v)
    if sig.is_float:
        return sig.conversion.numeric_scaled_to_raw(v)
    lo, hi = field_range(sig)
    try:
        r = sig.conversion.numeric_scaled_to_raw(v)
    except OverflowError:          # round(+-inf): beyond every field
        r = hi if (v - sig.offset) / sig.scale > 0 else lo
    return min(max(r, lo), hi)


def ref_encode(msg, values):
    """cantools' encode of the limited values (scaling done by cantools' conversion)."""
    raw = {s.name: ref_raw(s, values[s.name]) for s in msg.signals}
    return msg.encode(raw, scaling=False, padding=False, strict=False)


def single_signal_value(msg, sig, data):
    """cantools' decode of one signal of a frame, multiplexing aside."""
    alone = Signal(sig.name, sig.start, sig.length, sig.byte_order, sig.is_signed,
                   conversion=sig.conversion, minimum=sig.minimum, maximum=sig.maximum)
    one = Message(0x1, "One", msg.length, [alone], strict=False)
    return one.decode(bytes(data), decode_choices=False, scaling=True)[sig.name]


def ref_selected(msg, data):
    """Names of the signals a frame carries: every multiplexer up the chain
    selects the signal's branch (int() of its decoded value, as cantools)."""
    by_name = {s.name: s for s in msg.signals}
    values = {s.name: single_signal_value(msg, s, data) for s in msg.signals}
    out = set()
    for s in msg.signals:
        cur, ok = s, True
        while cur.multiplexer_signal is not None:
            if int(values[cur.multiplexer_signal]) not in cur.multiplexer_ids:
                ok = False
                break
            cur = by_name[cur.multiplexer_signal]
        if ok:
            out.add(s.name)
    return out, values


# ---------------------------------------------------------------------------
# Random layouts
# ---------------------------------------------------------------------------

SCALES = [1, 1, 2, 3, 10, 1000, -1, -4, 0.5, 0.25, 0.1, 0.01, 0.001, 1e-5, 0.03125, 7.3, -0.5,
          1.5, 2.0, 100.0]
OFFSETS = [0, 0, 0, 1, -40, 100, -1000, 2 ** 40, 0.5, -273.15, 0.1, -0.25, 1e3, 3.0]

CLASSIC_LENGTHS = list(range(1, 9))
FD_LENGTHS = [8, 12, 16, 20, 24, 32, 48, 64]


def bits_of(byte_order, start, length):
    if byte_order == "little_endian":
        return list(range(start, start + length))
    msb = 8 * (start // 8) + 7 - start % 8
    return [8 * (k // 8) + 7 - k % 8 for k in range(msb, msb + length)]


def end_of(byte_order, start, length):
    if byte_order == "little_endian":
        return start + length
    return 8 * (start // 8) + 7 - start % 8 + length


@st.composite
def scalings(draw):
    scale = draw(st.one_of(st.sampled_from(SCALES),
                           st.floats(1e-4, 1e4).map(lambda x: x if x != 0 else 1.0),
                           st.floats(-1e4, -1e-4)))
    offset = draw(st.one_of(st.sampled_from(OFFSETS), st.floats(-1e6, 1e6),
                            st.integers(-10 ** 6, 10 ** 6)))
    return scale, offset


@st.composite
def limits(draw, sig_len, signed, scale, offset, is_float):
    if is_float:
        lo_raw, hi_raw = -1e30, 1e30
    elif signed:
        lo_raw, hi_raw = -(1 << (sig_len - 1)), (1 << (sig_len - 1)) - 1
    else:
        lo_raw, hi_raw = 0, (1 << sig_len) - 1
    a, b = float(lo_raw * scale + offset), float(hi_raw * scale + offset)
    plo, phi = min(a, b), max(a, b)
    kind = draw(st.sampled_from(["none", "zero", "full", "sub", "wide", "reversed"]))
    if kind == "none":
        return None, None
    if kind == "zero":
        return 0, 0
    if kind == "full":
        return plo, phi
    if kind == "wide":
        span = (phi - plo) or 1.0
        return plo - span, phi + span
    x = draw(st.floats(plo, phi))
    y = draw(st.floats(plo, phi))
    if kind == "reversed":
        return max(x, y), min(x, y)
    return min(x, y), max(x, y)


class Layout:
    """A random message: its cantools Message and, per multiplexer, its branch values."""

    def __init__(self, msg, branches):
        self.msg = msg
        self.branches = branches


@st.composite
def layouts(draw, allow_mux=True):
    fd = draw(st.booleans())
    length = draw(st.sampled_from(FD_LENGTHS if fd else CLASSIC_LENGTHS))
    nbits = 8 * length
    signals = []
    counter = [0]

    def place(taken, *, mux=None, ids=None, selector=False):
        """One signal that fits and avoids ``taken`` (a set of bits), or None."""
        is_float = not selector and draw(st.integers(0, 7)) == 0
        if is_float:
            sig_len = draw(st.sampled_from([32, 64]))
        elif selector:
            sig_len = draw(st.integers(1, 6))
        else:
            sig_len = draw(st.one_of(st.integers(1, 16), st.integers(1, 64),
                                     st.sampled_from([8, 16, 32, 53, 54, 63, 64])))
        order = draw(st.sampled_from(["little_endian", "big_endian"]))
        if sig_len > nbits:
            return None
        first = draw(st.integers(0, nbits - sig_len))     # in the signal's own bit order
        start = first if order == "little_endian" else 8 * (first // 8) + 7 - first % 8
        assert end_of(order, start, sig_len) <= nbits
        bits = set(bits_of(order, start, sig_len))
        if bits & taken:
            return None
        signed = (not selector and not is_float and draw(st.booleans()))
        scale, offset = (1, 0) if selector else draw(scalings())
        lo, hi = (None, None) if selector else draw(limits(sig_len, signed, scale, offset, is_float))
        counter[0] += 1
        name = f"{'M' if selector else 'S'}{counter[0]}"
        # named values (not on a multiplexer: cantools makes each an empty branch)
        choices = {0: "zero", 1: "one"} if not selector and draw(st.integers(0, 5)) == 0 else None
        sig = Signal(name, start, sig_len, order, signed,
                     conversion=BaseConversion.factory(scale=scale, offset=offset, choices=choices,
                                                       is_float=is_float),
                     minimum=lo, maximum=hi, is_multiplexer=selector,
                     multiplexer_ids=ids, multiplexer_signal=mux)
        signals.append(sig)
        taken |= bits
        return sig

    root = set()
    branches = {}
    mux = None
    if allow_mux and length >= 2 and draw(st.integers(0, 2)) == 0:
        mux = place(root, selector=True)
    for _ in range(draw(st.integers(1, 8))):
        place(root)
    if mux is not None:
        n_ids = 1 << mux.length
        ids = draw(st.lists(st.integers(0, n_ids - 1), min_size=1, max_size=min(4, n_ids), unique=True))
        branches[mux.name] = ids
        taken = {i: set(root) for i in ids}
        for i in ids:
            for _ in range(draw(st.integers(0, 3))):
                place(taken[i], mux=mux.name, ids=[i])
        if len(ids) >= 2 and draw(st.booleans()):       # one signal in two branches
            a, b = ids[0], ids[1]
            both = taken[a] | taken[b]
            sig = place(both, mux=mux.name, ids=[a, b])
            if sig is not None:
                bits = set(bits_of(sig.byte_order, sig.start, sig.length))
                taken[a] |= bits
                taken[b] |= bits
        if draw(st.integers(0, 2)) == 0:                 # a multiplexer inside a branch
            a = ids[0]
            inner = place(taken[a], mux=mux.name, ids=[a], selector=True)
            if inner is not None:
                inner_ids = draw(st.lists(st.integers(0, (1 << inner.length) - 1), min_size=1,
                                          max_size=3, unique=True))
                branches[inner.name] = inner_ids
                for j in inner_ids:
                    sub = set(taken[a])
                    for _ in range(draw(st.integers(1, 2))):
                        place(sub, mux=inner.name, ids=[j])
    assume(signals)
    # cantools knows a multiplexer value only when a signal is in its branch
    for name in branches:
        branches[name] = sorted({i for s in signals if s.multiplexer_signal == name
                                 for i in s.multiplexer_ids})
    msg = Message(0x123, "Random", length, signals, is_fd=fd, strict=True)
    return Layout(msg, {k: v for k, v in branches.items() if v})


def value_for(draw, sig, branches):
    if sig.name in branches:                           # a multiplexer: one of its branches
        return float(draw(st.sampled_from(branches[sig.name])))
    if sig.is_float:
        return draw(st.floats(width=64))
    lo, hi = field_range(sig)
    raw = draw(st.integers(lo, hi))
    kind = draw(st.integers(0, 5))
    if kind == 0:
        return float(raw * sig.scale + sig.offset)          # on the raw grid
    if kind == 1:
        return float((raw + 0.5) * sig.scale + sig.offset)  # half a step off: rounding ties
    if kind == 2 and sig.minimum is not None and sig.maximum is not None:
        return float(draw(st.sampled_from([sig.minimum, sig.maximum])))
    if kind == 3:
        return draw(st.floats())                            # anything: NaN, inf, huge
    return draw(st.floats(float(min(lo * sig.scale + sig.offset, hi * sig.scale + sig.offset)) * 1.2 - 1,
                          float(max(lo * sig.scale + sig.offset, hi * sig.scale + sig.offset)) * 1.2 + 1))


# ---------------------------------------------------------------------------
# Constants and CRCs
# ---------------------------------------------------------------------------

def test_constants_match_the_python_side(c):
    _, lib = c
    assert [lib.CT_RX_OK, lib.CT_RX_UNKNOWN_ID, lib.CT_RX_BAD_LENGTH, lib.CT_RX_BAD_CRC,
            lib.CT_RX_BAD_COUNTER] == [0, 1, 2, 3, 4]
    assert [codec.STATUSES[getattr(lib, f"CT_RX_{x.upper()}")] for x in codec.STATUSES] == list(codec.STATUSES)
    assert [getattr(lib, f"CT_PROT_{k.upper()}") for k in KINDS] == list(range(len(KINDS)))
    assert [getattr(lib, f"CT_P1_{m.upper()}") for m in P1_DATA_ID_MODES] == list(range(4))
    assert codec.STATUSES[lib.CT_RX_BAD_CRC] == codec.BAD_CRC


def test_crc_check_values(c):
    _, lib = c
    check = b"123456789"
    # the published check values: CRC-8/SAE-J1850 0x4B, CRC-8H2F (AUTOSAR) 0xDF
    assert ref_j1850(check) == lib.ct_crc8_j1850(check, 9) == 0x4B
    assert ref_h2f(check) == lib.ct_crc8_h2f(check, 9) == 0xDF
    # the check tables of AUTOSAR's Specification of CRC Routines (CRC8 SAE-J1850, CRC8H2F)
    for data, j1850, h2f in AUTOSAR_CRC8_CHECKS:
        data = bytes.fromhex(data)
        assert (lib.ct_crc8_j1850(data, len(data)), lib.ct_crc8_h2f(data, len(data))) == (j1850, h2f)
        assert (ref_j1850(data), ref_h2f(data)) == (j1850, h2f)


AUTOSAR_CRC8_CHECKS = [
    ("00000000", 0x59, 0x12), ("F20183", 0x37, 0xC2), ("0FAA0055", 0x79, 0xC6),
    ("00FF5511", 0xB8, 0x77), ("332255AABBCCDDEEFF", 0xCB, 0x11), ("926B55", 0x8C, 0x33),
    ("FFFFFFFF", 0x74, 0x6C),
]


@SETTINGS
@given(st.binary(max_size=80))
def test_crcs_equal_the_bitwise_reference(c, data):
    _, lib = c
    assert lib.ct_crc8_j1850(data, len(data)) == ref_j1850(data)
    assert lib.ct_crc8_h2f(data, len(data)) == ref_h2f(data)


# ---------------------------------------------------------------------------
# Random layouts: C against cantools
# ---------------------------------------------------------------------------

@pytest.mark.slow
@SETTINGS
@given(st.data())
def test_encode_equals_cantools_on_random_layouts(c, data):
    layout = data.draw(layouts())
    msg = layout.msg
    t = table.CodecTable([msg])
    values = {s.name: value_for(data.draw, s, layout.branches) for s in msg.signals}
    got = t.encode(0, values)
    assert got == ref_encode(msg, values), (msg.signals, values)


@pytest.mark.slow
@SETTINGS
@given(st.data())
def test_decode_equals_cantools_on_random_layouts(c, data):
    layout = data.draw(layouts())
    msg = layout.msg
    t = table.CodecTable([msg])
    if data.draw(st.booleans()):
        frame = data.draw(st.binary(min_size=msg.length, max_size=msg.length))
    else:   # a frame of valid branches, with random values
        values = {s.name: value_for(data.draw, s, layout.branches) for s in msg.signals}
        frame = ref_encode(msg, values)
    got = t.decode(0, frame)
    selected, single = ref_selected(msg, frame)
    assert set(got) == selected
    for name in selected:
        assert same_float(got[name], single[name]), (name, got[name], single[name])
    try:
        whole = msg.decode(frame, decode_choices=False, scaling=True)
    except cantools.database.DecodeError:
        whole = None        # a multiplexer value without a branch: cantools gives up
    if whole is not None:
        assert set(whole) == set(got)
        for name, value in whole.items():
            assert same_float(got[name], value), (name, got[name], value)


@pytest.mark.slow
@SETTINGS
@given(st.data())
def test_decode_of_encode_is_the_limited_raw_value(c, data):
    layout = data.draw(layouts(allow_mux=False))
    msg = layout.msg
    t = table.CodecTable([msg])
    values = {s.name: value_for(data.draw, s, layout.branches) for s in msg.signals}
    got = t.decode(0, t.encode(0, values))
    for s in msg.signals:
        raw = ref_raw(s, values[s.name])
        expect = s.conversion.raw_to_scaled(raw, decode_choices=False)
        if s.is_float and s.length == 32:      # stored as float32 (a C cast, as bitstruct does)
            expect = s.conversion.raw_to_scaled(ctypes.c_float(raw).value, decode_choices=False)
        assert same_float(got[s.name], expect), (s, values[s.name], got[s.name], expect)


def test_limits_and_rounding_rules(c):
    sigs = [
        Signal("Half", 0, 8, "little_endian", False, minimum=0, maximum=255),
        Signal("Lim", 8, 8, "little_endian", True, conversion=BaseConversion.factory(0.5, 10),
               minimum=12, maximum=20),
        Signal("Free", 16, 8, "little_endian", True, minimum=0, maximum=0),   # [0|0]: no range
        Signal("Big", 24, 12, "big_endian", False, conversion=BaseConversion.factory(2, 0)),
    ]
    msg = Message(0x10, "Rules", 8, sigs, strict=True)
    t = table.CodecTable([msg])
    d = t.decode(0, t.encode(0, {"Half": 2.5, "Lim": 99, "Free": 300, "Big": 1e9}))
    assert d["Half"] == 2.0                      # round half to even, as Python's round()
    assert t.decode(0, t.encode(0, {"Half": 3.5}))["Half"] == 4.0
    assert d["Lim"] == 20.0                      # limited to [minimum, maximum]
    assert d["Free"] == 127.0                    # no range: only the bit field's limit
    assert d["Big"] == 2 * 4095.0
    d = t.decode(0, t.encode(0, {"Half": float("nan"), "Lim": -math.inf, "Free": -math.inf}))
    assert (d["Half"], d["Lim"], d["Free"]) == (0.0, 12.0, -128.0)   # NaN is sent as 0
    assert t.decode(0, t.encode(0, {"Lim": float("nan")}))["Lim"] == 12.0   # 0, limited to the range


def test_wide_integer_decoding_is_rounded_once_like_python_integers(c):
    """64-bit fields with an integer factor: cantools multiplies Python
    integers, exactly; the C result is that value rounded once, where the
    plain double product would round twice."""
    sigs = [Signal("I", 0, 64, "little_endian", True, conversion=BaseConversion.factory(3, -7)),
            Signal("F", 71, 64, "big_endian", False, conversion=BaseConversion.factory(3, 0.5))]
    msg = Message(0x40, "Wide", 16, sigs, is_fd=True, strict=True)
    t = table.CodecTable([msg])
    twice = 0
    for raw in (2 ** 53 + 1, 2 ** 62 + 12345, 2 ** 63 - 1, -(2 ** 63), -(2 ** 53) - 3, 123456789012345678):
        unsigned = raw % 2 ** 64
        frame = unsigned.to_bytes(8, "little") + unsigned.to_bytes(8, "big")
        got = t.decode(0, frame)
        expect = msg.decode(frame, decode_choices=False)
        assert same_float(got["I"], expect["I"]) and same_float(got["F"], expect["F"]), raw
        twice += float(raw) * 3.0 - 7.0 != float(raw * 3 - 7)
    assert twice > 0          # the cases above do tell the two apart


def test_multiplexed_signals_of_other_branches_are_left_untouched(c):
    ffi, lib = c
    sigs = [
        Signal("Mux", 0, 4, "little_endian", False, is_multiplexer=True),
        Signal("A", 8, 8, "little_endian", False, multiplexer_ids=[1], multiplexer_signal="Mux"),
        Signal("B", 8, 16, "little_endian", False, multiplexer_ids=[2, 3, 4, 9], multiplexer_signal="Mux"),
        Signal("Plain", 32, 8, "little_endian", False),
    ]
    msg = Message(0x20, "Muxed", 8, sigs, strict=True)
    t = table.CodecTable([msg])
    assert t.decode(0, t.encode(0, {"Mux": 1, "A": 7, "B": 999, "Plain": 5})) == \
        {"Mux": 1.0, "A": 7.0, "Plain": 5.0}
    assert t.decode(0, t.encode(0, {"Mux": 3, "A": 7, "B": 999, "Plain": 5})) == \
        {"Mux": 3.0, "B": 999.0, "Plain": 5.0}
    frame = t.encode(0, {"Mux": 7, "A": 7, "B": 999, "Plain": 5})   # no branch 7: root only
    assert frame == bytes([7, 0, 0, 0, 5, 0, 0, 0])
    values = ffi.new("double[]", [-1.0] * 4)
    written = ffi.new("uint8_t[]", 4)
    assert lib.ct_decode(t.table, 0, frame, 8, values, written) == 2
    assert list(values) == [7.0, -1.0, -1.0, 5.0] and list(written) == [1, 0, 0, 1]
    assert lib.ct_decode(t.table, 0, frame, 7, values, written) == -1   # wrong length


# ---------------------------------------------------------------------------
# Protection against the references
# ---------------------------------------------------------------------------

def protected_message(length, crc_byte, counter_bit, nibble_bit=None, extra=True):
    """A little-endian message: an 8-bit checksum in byte crc_byte, a 4-bit
    counter at counter_bit, optionally a 4-bit Data ID nibble, and payload
    bytes in the rest."""
    sigs = [Signal("CHK", 8 * crc_byte, 8, "little_endian", False),
            Signal("CNT", counter_bit, 4, "little_endian", False)]
    used = set(range(8 * crc_byte, 8 * crc_byte + 8)) | set(range(counter_bit, counter_bit + 4))
    if nibble_bit is not None:
        sigs.append(Signal("NIB", nibble_bit, 4, "little_endian", False))
        used |= set(range(nibble_bit, nibble_bit + 4))
    if extra:
        for b in range(length):
            if not used & set(range(8 * b, 8 * b + 8)):
                sigs.append(Signal(f"P{b}", 8 * b, 8, "little_endian", False))
    return Message(0x1A5, "Prot", length, sigs, strict=True)


def write_nibble(buf, bit, value):
    byte, shift = bit // 8, bit % 8
    buf[byte] = (buf[byte] & ~(0x0F << shift) & 0xFF) | ((value & 0x0F) << shift)


def read_nibble(buf, bit):
    return (buf[bit // 8] >> (bit % 8)) & 0x0F


class RefProtection:
    """Protect and check from the definitions in can_dbc/protection.py and
    AUTOSAR's E2E Protocol Specification (Profile 1: CRC-8/SAE-J1850's
    polynomial, start value and final XOR 0x00, over the Data ID by mode and
    the data without the CRC byte, counter 0..14; Profile 2: CRC-8H2F over
    the data after the CRC byte, then the Data ID of the counter's list
    entry, counter 0..15)."""

    def __init__(self, kind, frame_id, length, crc_byte, counter_bit, nibble_bit=None, data_id=0,
                 mode="both", id_list=None, max_delta=2):
        self.kind, self.frame_id, self.length = kind, frame_id, length
        self.crc_byte, self.counter_bit, self.nibble_bit = crc_byte, counter_bit, nibble_bit
        self.data_id, self.mode, self.id_list, self.max_delta = data_id, mode, id_list, max_delta
        self.modulus = 15 if kind == "p1" else 16
        self.last = -1

    def crc(self, buf, counter):
        rest = bytes(b for i, b in enumerate(buf) if i != self.crc_byte)
        if self.kind == "dct":
            return ref_crc8(bytes([self.frame_id & 0xFF, (self.frame_id >> 8) & 0xFF]) + rest,
                            0x1D, 0xFF, 0xFF)
        if self.kind == "p1":
            lo, hi = self.data_id & 0xFF, self.data_id >> 8
            ids = {"both": [lo, hi], "alt": [hi if counter % 2 else lo], "low": [lo],
                   "nibble": [lo, 0]}[self.mode]
            return ref_crc8(bytes(ids) + rest, 0x1D, 0x00, 0x00)
        if self.kind == "p2":
            return ref_crc8(rest + bytes([self.id_list[counter]]), 0x2F, 0xFF, 0xFF)
        x = 0
        for b in rest:
            x ^= b
        return x

    def protect(self, data, counter):
        buf = bytearray(data)
        value = counter % self.modulus
        write_nibble(buf, self.counter_bit, value)
        if self.kind == "p1" and self.mode == "nibble":
            write_nibble(buf, self.nibble_bit, self.data_id >> 8)
        buf[self.crc_byte] = self.crc(buf, value)
        return bytes(buf)

    def check(self, data):
        if len(data) != self.length:
            return codec.BAD_LENGTH
        counter = read_nibble(data, self.counter_bit)
        if data[self.crc_byte] != self.crc(data, counter):
            return codec.BAD_CRC
        if self.kind == "p1" and self.mode == "nibble" and \
                read_nibble(data, self.nibble_bit) != (self.data_id >> 8) & 0x0F:
            return codec.BAD_CRC
        if counter >= self.modulus:
            return codec.BAD_COUNTER
        if self.last >= 0:
            step = (counter - self.last) % self.modulus
            if step == 0 or step > self.max_delta:
                return codec.BAD_COUNTER
        self.last = counter
        return codec.OK


@st.composite
def protected_setups(draw):
    kind = draw(st.sampled_from(["dct", "p1", "p2"]))
    length = draw(st.sampled_from([2, 3, 4, 8, 8, 8, 16, 32, 64]))
    crc_byte = draw(st.integers(0, length - 1))
    nibbles = [b for b in range(0, 8 * length, 4) if b // 8 != crc_byte]
    counter_bit = draw(st.sampled_from(nibbles))
    mode = draw(st.sampled_from(P1_DATA_ID_MODES)) if kind == "p1" else "both"
    nibble_bit = None
    if kind == "p1" and mode == "nibble":
        rest = [b for b in nibbles if b != counter_bit]
        assume(rest)
        nibble_bit = draw(st.sampled_from(rest))
    data_id = draw(st.integers(0, 0xFFFF))
    id_list = tuple(draw(st.lists(st.integers(0, 255), min_size=16, max_size=16)))
    max_delta = draw(st.integers(1, 14))
    msg = protected_message(length, crc_byte, counter_bit, nibble_bit)
    prot = Protection(kind=kind, crc_signal="CHK", counter_signal="CNT", data_id=data_id,
                      data_id_mode=mode, data_id_nibble_signal="NIB" if nibble_bit is not None else None,
                      data_id_list=id_list, max_delta_counter=max_delta)
    ref = RefProtection(kind, msg.frame_id, length, crc_byte, counter_bit, nibble_bit, data_id, mode,
                        id_list, max_delta)
    return msg, prot, ref


@pytest.mark.slow
@SETTINGS
@given(protected_setups(), st.data())
def test_protect_equals_the_reference(c, setup, data):
    msg, prot, ref = setup
    t = table.CodecTable([(msg, prot)])
    frame = data.draw(st.binary(min_size=msg.length, max_size=msg.length))
    counter = data.draw(st.integers(0, 2 ** 32 - 1))
    assert t.protect(0, frame, counter) == ref.protect(frame, counter)


@pytest.mark.slow
@SETTINGS
@given(protected_setups(), st.data())
def test_check_equals_the_reference_over_a_sequence(c, setup, data):
    msg, prot, ref = setup
    t = table.CodecTable([(msg, prot)])
    state = t.new_state()
    counter = data.draw(st.integers(0, 30))
    for _ in range(data.draw(st.integers(1, 25))):
        counter += data.draw(st.sampled_from([1, 1, 1, 0, 2, 3, 7, 15]))
        frame = bytearray(ref.protect(data.draw(st.binary(min_size=msg.length, max_size=msg.length)),
                                      counter))
        what = data.draw(st.integers(0, 9))
        if what == 0:
            bit = data.draw(st.integers(0, 8 * msg.length - 1))
            frame[bit // 8] ^= 1 << (bit % 8)
        elif what == 1:
            frame = frame[:-1] if data.draw(st.booleans()) else frame + b"\0"
        elif what == 2 and prot.kind == "p1":
            write_nibble(frame, ref.counter_bit, 15)            # P1's invalid counter, CRC made right
            frame[ref.crc_byte] = ref.crc(frame, 15)
        assert t.check(0, bytes(frame), state) == ref.check(bytes(frame))
        assert state.last_counter == ref.last


# Known frames, published as the test vectors of the `e2e` package on PyPI
# (Artur Drogunow, tests/test_p01.py and tests/test_p02.py): 8 bytes, the
# CRC in byte 0, the counter in the low nibble of byte 1, for Profile 1's
# nibble mode the Data ID nibble in the high nibble of byte 1.
P1_KNOWN = [  # (mode, counter, frame) with Data ID 0x123, payload zeros
    ("both", 0, "cc00000000000000"), ("both", 1, "9101000000000000"),
    ("alt", 0, "ce00000000000000"), ("alt", 1, "0201000000000000"),
    ("low", 0, "ce00000000000000"), ("low", 1, "9301000000000000"),
    ("nibble", 0, "2a10000000000000"), ("nibble", 1, "7711000000000000"),
]
P2_KNOWN = [  # (Data ID list, payload, counter, frame)
    (bytes(16), bytes(8), 1, "4501000000000000"),
    (bytes(range(16)), bytes(range(8)), 2, "bc02020304050607"),
    (bytes(range(16)), bytes(range(8)), 1, "6101020304050607"),
]


@pytest.mark.parametrize("mode, counter, frame", P1_KNOWN)
def test_profile1_known_frames(c, mode, counter, frame):
    msg = protected_message(8, 0, 8, 12 if mode == "nibble" else None)
    prot = Protection(kind="p1", crc_signal="CHK", counter_signal="CNT", data_id=0x123, data_id_mode=mode,
                      data_id_nibble_signal="NIB" if mode == "nibble" else None)
    t = table.CodecTable([(msg, prot)])
    assert t.protect(0, bytes(8), counter).hex() == frame
    assert t.check(0, bytes.fromhex(frame), t.new_state()) == codec.OK
    assert RefProtection("p1", 0, 8, 0, 8, 12, 0x123, mode).protect(bytes(8), counter).hex() == frame


@pytest.mark.parametrize("ids, payload, counter, frame", P2_KNOWN)
def test_profile2_known_frames(c, ids, payload, counter, frame):
    msg = protected_message(8, 0, 8)
    prot = Protection(kind="p2", crc_signal="CHK", counter_signal="CNT", data_id_list=tuple(ids))
    t = table.CodecTable([(msg, prot)])
    assert t.protect(0, payload, counter).hex() == frame
    assert t.check(0, bytes.fromhex(frame), t.new_state()) == codec.OK
    assert RefProtection("p2", 0, 8, 0, 8, id_list=ids).protect(payload, counter).hex() == frame


def test_profile1_rejects_counter_15_and_a_wrong_nibble(c):
    msg = protected_message(8, 0, 8, 12)
    prot = Protection(kind="p1", crc_signal="CHK", counter_signal="CNT", data_id=0x123,
                      data_id_mode="nibble", data_id_nibble_signal="NIB")
    t = table.CodecTable([(msg, prot)])
    assert t.protect(0, bytes(8), 15)[1] & 0x0F == 0          # counter 15 is written as 0 (modulo 15)
    ref = RefProtection("p1", 0, 8, 0, 8, 12, 0x123, "nibble")
    bad = bytearray(ref.protect(bytes(8), 3))
    write_nibble(bad, 12, 0x2)
    bad[0] = ref.crc(bad, 3)                                  # the CRC matches, the nibble does not
    assert t.check(0, bytes(bad), t.new_state()) == codec.BAD_CRC


@SETTINGS
@given(st.binary(min_size=8, max_size=8), st.integers(0, 100), st.booleans())
def test_xor_and_counter_protections(c, payload, counter, with_counter):
    sigs = [Signal("CS", 63, 8, "big_endian", False), Signal("ALIVE", 4, 3, "little_endian", False)]
    sigs += [Signal(f"P{b}", 8 * b, 8, "little_endian", False) for b in range(1, 7)]
    msg = Message(0x300, "Old", 8, sigs, strict=True)
    xor = Protection(kind="xor", crc_signal="CS", counter_signal="ALIVE" if with_counter else None)
    only = Protection(kind="counter", counter_signal="ALIVE")
    t = table.CodecTable([(msg, xor), (msg.__class__(0x301, "Old2", 8, list(msg.signals)), only)])
    frame = t.protect(0, payload, counter)
    buf = bytearray(payload)
    if with_counter:
        buf[0] = (buf[0] & 0x8F) | ((counter % 8) << 4)
    cs = 0
    for b in buf[:7]:
        cs ^= b
    buf[7] = cs
    assert frame == bytes(buf)
    assert t.check(0, frame, t.new_state()) == codec.OK
    assert t.check(0, frame[:7] + bytes([frame[7] ^ 0x40]), t.new_state()) == codec.BAD_CRC
    framed = t.protect(1, payload, counter)
    assert framed[1:] == payload[1:] and (framed[0] >> 4) & 7 == counter % 8
    state = t.new_state()
    assert [t.check(1, t.protect(1, payload, k), state) for k in (5, 6, 6, 8, 9, 12, 13)] == \
        ["ok", "ok", "bad_counter", "ok", "ok", "bad_counter", "bad_counter"]


# ---------------------------------------------------------------------------
# The project's own contract
# ---------------------------------------------------------------------------

RX_NAMES = [m.name for m in codec.messages("TCU")]


@pytest.fixture(scope="module")
def contract(c):
    return table.contract_table()


@pytest.fixture(scope="module")
def loop_table():
    """The table the loop serves the default mapping with (rt_loop.channels, with
    the loop's extension: it takes the codec's types from can_dbc._can_table)."""
    from can_dbc import mapping
    from rt_loop._rt_loop import ffi, lib
    from rt_loop.channels import LoopChannels
    return LoopChannels(mapping.load(mapping.DEFAULT_MAPPING), ffi, lib).table(0)


def contract_values(draw, msg):
    vals = {}
    for s in codec.payload_signals(msg):
        span = s.maximum - s.minimum
        vals[s.name] = draw(st.one_of(st.floats(s.minimum - 0.2 * span, s.maximum + 0.2 * span),
                                      st.sampled_from([s.minimum, s.maximum]),
                                      st.integers(int(s.minimum), int(s.maximum)).map(float)))
    return vals


@SETTINGS
@given(st.data())
def test_contract_encode_equals_codec_and_cantools(c, contract, loop_table, data):
    name = data.draw(st.sampled_from([m.name for m in contract.messages]))
    msg = codec.message(name)
    vals = contract_values(data.draw, msg)
    counter = data.draw(st.integers(0, 15))
    got = contract.encode(name, vals, counter=counter)
    assert got == codec.encode(name, vals, counter)
    assert loop_table.encode(name, vals, counter=counter) == got
    # cantools packs the limited values with the counter; the CRC written here
    packed = bytearray(msg.encode({**{s.name: ref_limit(s, vals[s.name]) for s in codec.payload_signals(msg)},
                                   codec.CRC_SIGNAL: 0, codec.COUNTER_SIGNAL: counter},
                                  scaling=True, padding=False, strict=False))
    packed[0] = ref_j1850(bytes([msg.frame_id & 0xFF, msg.frame_id >> 8]) + bytes(packed[1:]))
    assert got == bytes(packed)


@SETTINGS
@given(st.data())
def test_contract_decode_equals_codec_and_cantools(c, contract, loop_table, data):
    name = data.draw(st.sampled_from([m.name for m in contract.messages]))
    frame = data.draw(st.binary(min_size=8, max_size=8))
    got = contract.decode(name, frame)
    _, expect = codec.decode(codec.message(name).frame_id, frame)
    direct = codec.message(name).decode(frame, decode_choices=False, scaling=True)
    assert set(got) == set(expect) == set(direct)
    for k, v in expect.items():
        assert same_float(got[k], v), (k, got[k], v)
        assert same_float(direct[k], v), (k, direct[k], v)
    served = loop_table.decode(name, frame)
    assert set(served) == set(got) and all(same_float(served[k], got[k]) for k in got)


@pytest.mark.slow
@SETTINGS
@given(st.data())
def test_contract_check_accepts_and_rejects_as_codec(c, contract, loop_table, data):
    name = data.draw(st.sampled_from(RX_NAMES))
    msg = codec.message(name)
    receiver = codec.E2eReceiver(names=[name])
    state = contract.new_state()
    served_state = loop_table.new_state()
    counter = data.draw(st.integers(0, 15))
    for _ in range(data.draw(st.integers(1, 20))):
        counter = (counter + data.draw(st.sampled_from([1, 1, 0, 2, 3, 9]))) % 16
        frame = bytearray(codec.encode(name, contract_values(data.draw, msg), counter))
        what = data.draw(st.integers(0, 6))
        if what == 0:
            bit = data.draw(st.integers(0, 63))
            frame[bit // 8] ^= 1 << (bit % 8)
        elif what == 1:
            frame = frame[:data.draw(st.integers(0, 7))]
        got = contract.check(name, bytes(frame), state)
        assert got == receiver.check(msg.frame_id, bytes(frame))
        assert loop_table.check(name, bytes(frame), served_state) == got
        assert state.last_counter == served_state.last_counter == receiver.last_counter[name]


def test_contract_find_and_lookup(c, contract):
    assert len(contract) == 11
    for i, m in enumerate(contract.messages):
        assert contract.find(m.frame_id) == i and contract.index(m.name) == i
    assert contract.find(0x7FF) == -1 and contract.find(0x100, extended=True) == -1
    with pytest.raises(table.TableError, match="unknown message 'Nope'"):
        contract.index("Nope")
    with pytest.raises(table.TableError, match="written by the protection"):
        contract.encode("DCT_Clutch", {"CRC": 1}, counter=0)
    with pytest.raises(table.TableError, match="has no signal 'Foo'"):
        contract.encode("DCT_Clutch", {"Foo": 1})
    with pytest.raises(table.TableError, match="DCT_Clutch: 7 data bytes, the message has 8"):
        contract.decode("DCT_Clutch", bytes(7))
    assert contract.encode("DCT_Shift", {"SyncState1": "engaged"})[6] & 0x03 == 2
    assert contract.check("DCT_Clutch", bytes(3)) == codec.BAD_LENGTH


# ---------------------------------------------------------------------------
# Layouts the codec refuses
# ---------------------------------------------------------------------------

def _sig(name, start, length, order="little_endian", **kw):
    return Signal(name, start, length, order, kw.pop("signed", False), **kw)


BAD_LAYOUTS = [
    ("beyond", lambda: Message(1, "Short", 2, [_sig("Wide", 8, 16)], strict=False),
     "Short.Wide: start bit 8, 16 bits (little endian) ends beyond the message's 2 bytes"),
    ("beyond big endian", lambda: Message(1, "ShortBE", 2, [_sig("Wide", 15, 24, "big_endian")],
                                          strict=False),
     "ShortBE.Wide: start bit 15, 24 bits (big endian) ends beyond the message's 2 bytes"),
    ("overlap", lambda: Message(1, "Ovl", 8, [_sig("A", 0, 12), _sig("B", 8, 8)], strict=False),
     "Ovl: signals A and B overlap"),
    ("overlap in a branch", lambda: Message(1, "MuxOvl", 8, [
        _sig("M", 0, 4, is_multiplexer=True),
        _sig("A", 8, 8, multiplexer_ids=[1, 2], multiplexer_signal="M"),
        _sig("B", 12, 8, multiplexer_ids=[2], multiplexer_signal="M")], strict=False),
     "MuxOvl: signals A and B overlap in one multiplexed branch"),
    ("overlap with the multiplexer", lambda: Message(1, "MuxSel", 8, [
        _sig("M", 0, 4, is_multiplexer=True),
        _sig("A", 2, 8, multiplexer_ids=[1], multiplexer_signal="M")], strict=False),
     "MuxSel: signals M and A overlap in one multiplexed branch"),
    ("float length", lambda: Message(1, "Flt", 8, [
        _sig("F", 0, 16, conversion=BaseConversion.factory(1, 0, is_float=True))], strict=False),
     "Flt.F: a float signal of 16 bits, must be 32 or 64"),
    ("factor 0", lambda: Message(1, "Zero", 8, [
        _sig("Z", 0, 8, conversion=BaseConversion.factory(0.0, 1.5))], strict=False),
     "Zero.Z: factor 0"),
    ("missing multiplexer", lambda: Message(1, "Orphan", 8, [
        _sig("A", 0, 8, multiplexer_ids=[1], multiplexer_signal="Gone")], strict=False),
     "Orphan.A: multiplexer Gone is not a signal of the message"),
    ("too long", lambda: Message(1, "Huge", 65, [_sig("A", 0, 8)], strict=False),
     "Huge: 65 bytes, at most 64"),
]


@pytest.mark.parametrize("what, build, message", BAD_LAYOUTS, ids=[b[0] for b in BAD_LAYOUTS])
def test_refused_layouts_give_one_line_errors(c, what, build, message):
    with pytest.raises(table.TableError) as e:
        table.CodecTable([build()])
    assert str(e.value) == message
    assert "\n" not in str(e.value)


BAD_PROTECTIONS = [
    (Protection(kind="dct", crc_signal="CRC", counter_signal="Cnt"),
     "P: checksum signal CRC is not a signal of the message"),
    (Protection(kind="dct", crc_signal="Chk", counter_signal="Cnt"),
     "P.Chk: the checksum must fill one whole byte (8 bits from bit 0 of a byte), not start bit 4, 8 bits"),
    (Protection(kind="p2", crc_signal="Ok", counter_signal="Wide", data_id_list=tuple(range(16))),
     "P.Wide: the p2 counter has 4 bits, not 6"),
    (Protection(kind="p1", crc_signal="Ok", counter_signal="Cnt", data_id=1, data_id_mode="nibble"),
     "P: protection 'p1' needs a Data ID nibble signal"),
]


@pytest.mark.parametrize("prot, message", BAD_PROTECTIONS)
def test_refused_protections_give_one_line_errors(c, prot, message):
    msg = Message(1, "P", 8, [_sig("Chk", 4, 8), _sig("Cnt", 12, 4), _sig("Ok", 16, 8),
                              _sig("Wide", 24, 6)], strict=True)
    with pytest.raises(table.TableError) as e:
        table.CodecTable([(msg, prot)])
    assert str(e.value) == message


def test_duplicate_identifiers_are_refused(c):
    a = Message(5, "A", 8, [_sig("X", 0, 8)])
    b = Message(5, "B", 8, [_sig("Y", 0, 8)])
    with pytest.raises(table.TableError, match="messages A and B have the same identifier 0x5"):
        table.CodecTable([a, b])


# ---------------------------------------------------------------------------
# Cost
# ---------------------------------------------------------------------------

def test_bench_runs_in_c_and_accepts_every_frame(c, capsys):
    r = table.bench(iterations=2000, repeat=2)
    assert len(r["tx_messages"]) == 7 and len(r["rx_messages"]) == 4
    assert r["ns_per_tick"] > 0 and len(r["runs_ns"]) == 2
    assert table.main(["--bench", "--iterations", "1000", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "7 plant messages encoded + protected, 4 TCU messages checked + decoded" in out
    assert "ns per tick" in out
    assert table.main([]) == 2


def test_random_contract_round_trip_with_a_seeded_rng(c, contract):
    """A quick deterministic pass over every message (no hypothesis)."""
    rng = random.Random(11)
    for i, m in enumerate(contract.messages):
        for k in range(50):
            vals = {s.name: rng.uniform(s.minimum, s.maximum) for s in codec.payload_signals(m)}
            frame = contract.encode(i, vals, counter=k)
            assert frame == codec.encode(m.name, vals, k % 16)
            assert contract.decode(i, frame) == pytest.approx(codec.decode(m.frame_id, frame)[1], abs=0)
