"""The table-driven CAN codec: any DBC's messages as flat C arrays.

``CodecTable([(message, protection), ...])`` turns cantools messages (a
DBC's parse) and their end-to-end protection (``can_dbc.protection``) into
the arrays of ``can_dbc/csrc/can_table.h``: one ``ct_message`` per message,
one ``ct_signal`` per signal (start bit, length, byte order, signedness,
float type, factor, offset, limits, multiplexer), one ``ct_mux_range`` per
run of multiplexer values. The C functions pack, unpack, protect and check
frames from these arrays alone, bit-exact with cantools' encode and decode
(the rules are in can_table.h): the real-time loop can speak any vehicle's
matrix without generated code and without Python in its tick.

Layouts the codec cannot take are refused with a one-line ``TableError``
naming the message and signal: a message longer than 64 bytes, a signal
outside its message, overlapping signals that can be sent together (in the
same multiplexed branch), float signals other than 32/64 bits, a zero or
non-finite factor, a multiplexer that is missing or a float, protection
signals of the wrong shape.

``python -m can_dbc.table --bench`` times, in C, one tick's CAN work for the
project's own contract (every plant message encoded and protected, every TCU
message checked and decoded).
"""

from __future__ import annotations

import argparse
import math
import sys

from . import codec
from .codec import signal_bits
from .protection import (
    HEADER_BYTES,
    HEADER_FIELDS,
    KINDS,
    P1_DATA_ID_MODES,
    Protection,
    header_field_bits,
)
from .python_can import python_can

__all__ = ["CodecTable", "TableError", "bench", "contract_protection", "contract_table"]

MAX_LENGTH = 64
_EXACT = 2 ** 53            # integers up to this are exact in double


class TableError(ValueError):
    """A message layout or protection the table codec cannot take (one line)."""


def _c():
    from can_dbc._can_table import ffi, lib  # built by scripts/setup
    return ffi, lib


def _arithmetic(signal):
    """The conversion whose arithmetic cantools' decode runs for a signal:
    its own, or for a signal with named values the numeric one it wraps."""
    python_can()  # cantools imports can: without asammdf (can_dbc.python_can)
    from cantools.database.conversion import BaseConversion, NamedSignalConversion
    conv = signal.conversion
    if isinstance(conv, NamedSignalConversion):
        return BaseConversion.factory(scale=conv.scale, offset=conv.offset, choices=None,
                                      is_float=conv.is_float)
    return conv


def _signal_end(signal) -> int:
    """One past the last bit in the order the signal runs (its own numbering)."""
    if signal.byte_order == "little_endian":
        return signal.start + signal.length
    return 8 * (signal.start // 8) + 7 - signal.start % 8 + signal.length


class CodecTable:
    """The C tables of a list of messages, with a small Python API over them.

    ``messages``: (cantools Message, Protection) pairs, or bare Messages (no
    protection). Message ``i`` of the list is index ``i`` of the C table;
    its values are in ``signal_names(i)`` order (cantools' order).
    """

    def __init__(self, messages):
        ffi, lib = _c()
        self.ffi, self.lib = ffi, lib
        pairs = []
        for item in messages:
            msg, prot = item if isinstance(item, tuple) else (item, Protection())
            pairs.append((msg, prot if prot is not None else Protection()))
        if not pairs:
            raise TableError("no messages: the table needs at least one")
        seen = {}
        for msg, _ in pairs:
            key = (msg.frame_id, bool(msg.is_extended_frame))
            if key in seen:
                raise TableError(f"messages {seen[key]} and {msg.name} have the same identifier "
                                 f"0x{msg.frame_id:X}")
            seen[key] = msg.name
        self.messages = [m for m, _ in pairs]
        self.protections = [p for _, p in pairs]
        self._names = {m.name: i for i, m in enumerate(self.messages)}
        self._signals = [list(m.signals) for m in self.messages]

        n_sig = sum(len(s) for s in self._signals)
        mux_runs = [[] for _ in pairs]            # per message: per signal its runs
        for mi, (msg, prot) in enumerate(pairs):
            mux_runs[mi] = _check_layout(msg)
            _check_protection(msg, prot)
        n_mux = sum(len(r) for runs in mux_runs for r in runs)

        self._c_messages = ffi.new("ct_message[]", len(pairs))
        self._c_signals = ffi.new("ct_signal[]", max(n_sig, 1))
        self._c_mux = ffi.new("ct_mux_range[]", max(n_mux, 1))
        first = 0
        mux_at = 0
        for mi, (msg, prot) in enumerate(pairs):
            sigs = self._signals[mi]
            index = {s.name: i for i, s in enumerate(sigs)}
            for i, s in enumerate(sigs):
                c = self._c_signals[first + i]
                _fill_signal(c, msg, s)
                if s.multiplexer_signal is not None:
                    c.mux_signal = index[s.multiplexer_signal]
                    c.mux_first = mux_at
                    c.mux_count = len(mux_runs[mi][i])
                    for lo, hi in mux_runs[mi][i]:
                        self._c_mux[mux_at].lo = lo
                        self._c_mux[mux_at].hi = hi
                        mux_at += 1
                else:
                    c.mux_signal = -1
            cm = self._c_messages[mi]
            cm.id = msg.frame_id
            cm.extended = 1 if msg.is_extended_frame else 0
            cm.fd = 1 if getattr(msg, "is_fd", False) else 0
            cm.length = msg.length
            cm.first_signal = first
            cm.n_signals = len(sigs)
            _fill_protection(cm, msg, prot, index)
            first += len(sigs)
        self.table = ffi.new("ct_table *", {"messages": self._c_messages, "signals": self._c_signals,
                                            "mux": self._c_mux, "n_messages": len(pairs)})
        self._first = [self._c_messages[i].first_signal for i in range(len(pairs))]

    # -- lookup -------------------------------------------------------------

    def __len__(self):
        return len(self.messages)

    def index(self, message) -> int:
        """The table index of a message given by index, name or cantools Message."""
        if isinstance(message, bool):
            raise TableError(f"not a message: {message!r}")
        if isinstance(message, int):
            if not 0 <= message < len(self.messages):
                raise TableError(f"message index {message} out of range 0..{len(self.messages) - 1}")
            return message
        name = message if isinstance(message, str) else getattr(message, "name", None)
        if name not in self._names:
            raise TableError(f"unknown message {name!r} (the table has {', '.join(self._names)})")
        return self._names[name]

    def find(self, frame_id, extended=False) -> int:
        """The index of the message with this identifier, -1 if none (ct_find)."""
        return self.lib.ct_find(self.table, int(frame_id), 1 if extended else 0)

    def signal_names(self, message) -> list[str]:
        return [s.name for s in self._signals[self.index(message)]]

    # -- codec --------------------------------------------------------------

    def encode(self, message, values=None, counter=None) -> bytes:
        """A frame's data: ``values`` (signal name -> physical value; missing
        signals 0) packed by ct_encode; with ``counter`` also protected
        (ct_protect), and then the protection's own signals may not be given."""
        i = self.index(message)
        msg = self.messages[i]
        given = dict(values or {})
        sigs = self._signals[i]
        names = {s.name: k for k, s in enumerate(sigs)}
        arr = self.ffi.new("double[]", max(len(sigs), 1))
        protected = set(self.protections[i].signals()) if counter is not None else set()
        for name, value in given.items():
            if name not in names:
                raise TableError(f"{msg.name} has no signal {name!r} (it has {', '.join(names)})")
            if name in protected:
                raise TableError(f"{msg.name}: {name} is written by the protection, not given as a value")
            arr[names[name]] = _number(sigs[names[name]], value)
        data = self.ffi.new("uint8_t[]", MAX_LENGTH)
        self.lib.ct_encode(self.table, i, arr, data)
        if counter is not None:
            self.lib.ct_protect(self.table, i, data, _counter(counter))
        return bytes(self.ffi.buffer(data, msg.length))

    def saturated(self, message, values) -> list[str]:
        """The signals of ``values`` (as ``encode`` takes them) whose value
        ``encode`` limits, in the message's signal order: outside the DBC's
        [minimum, maximum] (when minimum < maximum), or a raw value beyond the
        bit field (an unsigned field and a negative value, say), as
        ct_encode limits them (can_table.h), from the same signal tables. NaN
        (sent as 0) is not counted, nor a multiplexed signal of a branch the
        frame does not carry."""
        i = self.index(message)
        sigs = self._signals[i]
        names = {s.name: k for k, s in enumerate(sigs)}
        hits = []
        for name, value in (values or {}).items():
            k = names.get(name)
            if k is None:
                raise TableError(f"{self.messages[i].name} has no signal {name!r} "
                                 f"(it has {', '.join(names)})")
            v = _number(sigs[k], value)
            c = self._c_signals[self._first[i] + k]
            if math.isnan(v):
                continue
            limited = min(max(v, c.minimum), c.maximum) if c.limited else v
            out = limited != v
            if not out and not c.is_float:
                r = round((limited - c.offset) / c.factor) if math.isfinite(limited) else limited
                out = not c.raw_min <= r < c.raw_end
            if out:
                hits.append(k)
        if not hits:
            return []
        carried = self.decode(i, self.encode(i, values))
        return [sigs[k].name for k in sorted(hits) if sigs[k].name in carried]

    def decode(self, message, data) -> dict:
        """{signal name: physical value} of the signals the frame carries
        (multiplexed signals of other branches left out), by ct_decode."""
        i = self.index(message)
        msg = self.messages[i]
        data = bytes(data)
        if len(data) != msg.length:
            raise TableError(f"{msg.name}: {len(data)} data bytes, the message has {msg.length}")
        n = len(self._signals[i])
        values = self.ffi.new("double[]", max(n, 1))
        written = self.ffi.new("uint8_t[]", max(n, 1))
        self.lib.ct_decode(self.table, i, data, len(data), values, written)
        return {s.name: values[k] for k, s in enumerate(self._signals[i]) if written[k]}

    def protect(self, message, data, counter) -> bytes:
        """``data`` with counter, Data ID nibble and checksum written (ct_protect)."""
        i = self.index(message)
        msg = self.messages[i]
        data = bytes(data)
        if len(data) != msg.length:
            raise TableError(f"{msg.name}: {len(data)} data bytes, the message has {msg.length}")
        buf = self.ffi.new("uint8_t[]", data or b"\0")
        self.lib.ct_protect(self.table, i, buf, _counter(counter))
        return bytes(self.ffi.buffer(buf, len(data)))

    def new_state(self):
        """A receive state for ``check`` (no frame accepted yet)."""
        return self.ffi.new("ct_rx_state *", {"last_counter": -1})

    def check(self, message, data, state=None) -> str:
        """One of can_dbc.codec.STATUSES for a received frame (ct_check);
        ``state`` from ``new_state()`` moves on only when the frame is accepted."""
        i = self.index(message)
        data = bytes(data)
        code = self.lib.ct_check(self.table, i, data or b"\0", len(data),
                                 state if state is not None else self.ffi.NULL)
        return codec.STATUSES[code]


def _number(signal, value) -> float:
    if isinstance(value, str):
        for number, name in (signal.choices or {}).items():
            if str(name) == value:
                return float(number)
        raise TableError(f"signal {signal.name}: {value!r} is not one of its values "
                         f"({', '.join(str(n) for n in (signal.choices or {}).values()) or 'no named values'})")
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise TableError(f"signal {signal.name}: {value!r} is not a number") from None


def _counter(counter) -> int:
    if isinstance(counter, bool) or not isinstance(counter, int) or not 0 <= counter <= 0xFFFFFFFF:
        raise TableError(f"counter must be a whole number 0..4294967295, got {counter!r}")
    return counter


# ---------------------------------------------------------------------------
# Building the arrays
# ---------------------------------------------------------------------------

def _check_layout(msg):
    """Per signal its multiplexer value runs [(lo, hi), ...] (empty if not
    multiplexed), after checking everything the C codec relies on."""
    if getattr(msg, "is_container", False):
        raise TableError(f"{msg.name}: container messages are not supported")
    if not 0 <= msg.length <= MAX_LENGTH:
        raise TableError(f"{msg.name}: {msg.length} bytes, at most {MAX_LENGTH}")
    sigs = list(msg.signals)
    index = {}
    for i, s in enumerate(sigs):
        if s.name in index:
            raise TableError(f"{msg.name}: two signals named {s.name}")
        index[s.name] = i
    masks = []
    for s in sigs:
        where = f"{msg.name}.{s.name}"
        if not 1 <= s.length <= 64:
            raise TableError(f"{where}: {s.length} bits, must be 1..64")
        if s.is_float and s.length not in (32, 64):
            raise TableError(f"{where}: a float signal of {s.length} bits, must be 32 or 64")
        if s.start < 0 or _signal_end(s) > 8 * msg.length:
            raise TableError(f"{where}: start bit {s.start}, {s.length} bits "
                             f"({s.byte_order.replace('_', ' ')}) ends beyond the message's "
                             f"{msg.length} bytes")
        for what, v in (("factor", s.scale), ("offset", s.offset)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise TableError(f"{where}: {what} {v!r} is not a finite number")
        if s.scale == 0:
            raise TableError(f"{where}: factor 0")
        for what, v in (("minimum", s.minimum), ("maximum", s.maximum)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v)):
                raise TableError(f"{where}: {what} {v!r} is not a number")
        bits = 0
        for b in signal_bits(s):
            bits |= 1 << b
        masks.append(bits)

    # multiplexers: each chain ends at an unmultiplexed signal
    runs = []
    chains = []
    for s in sigs:
        where = f"{msg.name}.{s.name}"
        if s.multiplexer_signal is None:
            runs.append([])
            continue
        sel = s.multiplexer_signal
        if sel not in index:
            raise TableError(f"{where}: multiplexer {sel} is not a signal of the message")
        sel_sig = sigs[index[sel]]
        if not sel_sig.is_multiplexer:
            raise TableError(f"{where}: multiplexer {sel} is not marked as a multiplexer")
        if sel_sig.is_float:
            raise TableError(f"{where}: multiplexer {sel} is a float signal")
        ids = s.multiplexer_ids
        if not ids:
            raise TableError(f"{where}: multiplexed by {sel} but has no multiplexer values")
        if any(isinstance(v, bool) or not isinstance(v, int) or not -2 ** 63 <= v < 2 ** 63 for v in ids):
            raise TableError(f"{where}: multiplexer values must be 64-bit whole numbers")
        runs.append(_runs(ids))
    for i, s in enumerate(sigs):
        chain = {}
        j = i
        while sigs[j].multiplexer_signal is not None:
            sel = index[sigs[j].multiplexer_signal]
            if sel in chain or sel == i:
                raise TableError(f"{msg.name}.{s.name}: its multiplexers form a loop")
            chain[sel] = frozenset(sigs[j].multiplexer_ids)
            j = sel
        chains.append(chain)

    # overlapping bits are allowed only between signals of exclusive branches
    for a in range(len(sigs)):
        for b in range(a + 1, len(sigs)):
            if not masks[a] & masks[b]:
                continue
            ca, cb = chains[a], chains[b]
            if any(sel in cb and not (ca[sel] & cb[sel]) for sel in ca):
                continue
            branch = " in one multiplexed branch" if ca or cb else ""
            raise TableError(f"{msg.name}: signals {sigs[a].name} and {sigs[b].name} overlap{branch}")
    return runs


def _runs(ids):
    out = []
    for v in sorted(set(ids)):
        if out and v == out[-1][1] + 1:
            out[-1][1] = v
        else:
            out.append([v, v])
    return [tuple(r) for r in out]


def _fill_signal(c, msg, s):
    python_can()
    from cantools.database.conversion import IdentityConversion
    lib = _c()[1]
    c.start = s.start
    c.length = s.length
    c.big_endian = 1 if s.byte_order == "big_endian" else 0
    c.is_signed = 1 if s.is_signed else 0
    c.is_float = 1 if s.is_float else 0
    conv = _arithmetic(s)
    scale, offset = conv.scale, conv.offset
    c.factor = float(scale)
    c.offset = float(offset)
    c.factor_int = c.offset_int = 0
    c.exact_raw = 0
    if isinstance(conv, IdentityConversion):
        c.conversion = lib.CT_CONV_IDENTITY
    elif isinstance(scale, int) and not s.is_float:
        # cantools multiplies Python integers here (raw * scale, and with an
        # integer offset the sum too): reproduce it exactly
        exact_sum = isinstance(offset, int)
        o = offset if exact_sum else 0
        if abs(scale) > _EXACT or abs(o) > _EXACT:
            raise TableError(f"{msg.name}.{s.name}: integer factor {scale} or offset {offset} "
                             "beyond 2^53, cannot be decoded exactly")
        c.factor_int = scale
        c.offset_int = o
        c.exact_raw = (_EXACT - abs(o)) // abs(scale)
        c.conversion = lib.CT_CONV_INTEGER if exact_sum else lib.CT_CONV_INT_FACTOR
    else:
        c.conversion = lib.CT_CONV_LINEAR
    lo = -math.inf if s.minimum is None else float(s.minimum)
    hi = math.inf if s.maximum is None else float(s.maximum)
    c.limited = 1 if lo < hi else 0
    c.minimum = lo
    c.maximum = hi
    if s.is_signed:
        c.raw_min = -float(2 ** (s.length - 1))
        c.raw_end = float(2 ** (s.length - 1))
    else:
        c.raw_min = 0.0
        c.raw_end = float(2 ** s.length)
    c.mux_first = c.mux_count = 0


def _check_protection(msg, prot):
    if not isinstance(prot, Protection):
        raise TableError(f"{msg.name}: protection must be a can_dbc.protection.Protection, got {prot!r}")
    if prot.kind not in KINDS:
        raise TableError(f"{msg.name}: protection kind {prot.kind!r}: choose one of {', '.join(KINDS)}")
    if prot.kind == "none":
        return
    if prot.kind in HEADER_FIELDS:
        _check_header(msg, prot)
        return
    sigs = {s.name: s for s in msg.signals}
    kind = prot.kind
    needs_crc = kind in ("dct", "p1", "p2", "xor")
    needs_counter = kind in ("counter", "dct", "p1", "p2")
    for role, name, needed in (("checksum", prot.crc_signal, needs_crc),
                               ("counter", prot.counter_signal, needs_counter),
                               ("Data ID nibble", prot.data_id_nibble_signal,
                                kind == "p1" and prot.data_id_mode == "nibble")):
        if name is None:
            if needed:
                raise TableError(f"{msg.name}: protection {kind!r} needs a {role} signal")
            continue
        if name not in sigs:
            raise TableError(f"{msg.name}: {role} signal {name} is not a signal of the message")
        s = sigs[name]
        if s.multiplexer_signal is not None:
            raise TableError(f"{msg.name}.{name}: the {role} signal must not be multiplexed")
        if s.is_float:
            raise TableError(f"{msg.name}.{name}: the {role} signal must not be a float signal")
    if needs_crc:
        s = sigs[prot.crc_signal]
        whole_byte = s.length == 8 and s.start % 8 == (0 if s.byte_order == "little_endian" else 7)
        if not whole_byte:
            raise TableError(f"{msg.name}.{s.name}: the checksum must fill one whole byte "
                             f"(8 bits from bit 0 of a byte), not start bit {s.start}, {s.length} bits")
    if prot.counter_signal:
        s = sigs[prot.counter_signal]
        if kind in ("dct", "p1", "p2") and s.length != 4:
            raise TableError(f"{msg.name}.{s.name}: the {kind} counter has 4 bits, not {s.length}")
        if not 1 <= s.length <= 16:
            raise TableError(f"{msg.name}.{s.name}: a counter of {s.length} bits, must be 1..16")
    if kind == "p1" and prot.data_id_mode == "nibble":
        s = sigs[prot.data_id_nibble_signal]
        if s.length != 4:
            raise TableError(f"{msg.name}.{s.name}: the Data ID nibble has 4 bits, not {s.length}")
    if kind == "p1" and prot.data_id is None:
        raise TableError(f"{msg.name}: protection 'p1' needs data_id")
    if kind == "p2" and (prot.data_id_list is None or len(prot.data_id_list) != 16):
        raise TableError(f"{msg.name}: protection 'p2' needs data_id_list (16 Data IDs)")
    if not 1 <= prot.max_delta_counter <= 14:
        raise TableError(f"{msg.name}: max_delta_counter {prot.max_delta_counter}, must be 1..14")


def _check_header(msg, prot):
    """Profiles 5, 4 and 7: the Data ID, the header inside the frame, the named
    CRC and counter signals on the header's fields, no other signal on the
    header (the codec writes it)."""
    number, fields = HEADER_FIELDS[prot.kind]
    size = HEADER_BYTES[prot.kind]
    id_bits = 32 if prot.kind in ("p4", "p7") else 16
    what = f"E2E Profile {number}"
    if prot.data_id is None or not 0 <= prot.data_id < 2 ** id_bits:
        raise TableError(f"{msg.name}: protection {prot.kind!r} needs data_id ({id_bits} bits)")
    if prot.offset_bits % 8 or prot.offset_bits // 8 + size > msg.length:
        raise TableError(f"{msg.name}: the {what} header ({size} bytes at bit {prot.offset_bits}) "
                         f"does not fit the message's {msg.length} bytes")
    if not 1 <= prot.max_delta_counter <= 255:
        raise TableError(f"{msg.name}: max_delta_counter {prot.max_delta_counter}, must be 1..255")
    lo = prot.offset_bits // 8
    sigs = {s.name: s for s in msg.signals}
    for role, name in (("crc", prot.crc_signal), ("counter", prot.counter_signal)):
        if name is None:
            continue
        if name not in sigs:
            raise TableError(f"{msg.name}: {role} signal {name} is not a signal of the message")
        s = sigs[name]
        first, bits, order = fields[role]
        if (set(signal_bits(s)) != header_field_bits(prot, role) or s.is_float
                or (order is not None and s.byte_order != order)):
            how = {"little_endian": " (low byte first)", "big_endian": " (high byte first)", None: ""}[order]
            raise TableError(f"{msg.name}.{name}: the {what} {'CRC' if role == 'crc' else role} takes "
                             f"{bits} bits at byte {lo + first}{how}, not start bit {s.start}, {s.length} "
                             f"bits ({s.byte_order.replace('_', ' ')})")
    mine = {prot.crc_signal, prot.counter_signal}
    header_bits = set(range(8 * lo, 8 * (lo + size)))
    for s in msg.signals:
        if s.name not in mine and header_bits & set(signal_bits(s)):
            raise TableError(f"{msg.name}.{s.name}: lies on the {what} header (bytes {lo}..{lo + size - 1}), "
                             "which the protection writes")


def _fill_protection(cm, msg, prot, index):
    kind = prot.kind
    cm.protection = KINDS.index(kind)
    cm.crc_signal = cm.counter_signal = cm.nibble_signal = cm.crc_byte = -1
    cm.counter_modulus = 0
    cm.data_id = 0
    cm.data_id_mode = 0
    cm.max_delta_counter = prot.max_delta_counter
    if kind == "none":
        return
    if kind in HEADER_FIELDS:
        cm.crc_byte = prot.offset_bits // 8
        if kind == "p5":
            cm.counter_modulus = 256
            cm.data_id = prot.data_id
        else:                                    # p4, p7: the 32-bit Data ID in data_id_list[0..3]
            cm.counter_modulus = 65536 if kind == "p4" else 0xFFFFFFFF
            for k in range(4):
                cm.data_id_list[k] = (prot.data_id >> (8 * k)) & 0xFF
        if prot.crc_signal:
            cm.crc_signal = index[prot.crc_signal]
        if prot.counter_signal:
            cm.counter_signal = index[prot.counter_signal]
        return
    if kind != "counter" and prot.crc_signal:
        cm.crc_signal = index[prot.crc_signal]
        cm.crc_byte = msg.get_signal_by_name(prot.crc_signal).start // 8
    if prot.counter_signal and kind in ("counter", "dct", "p1", "p2", "xor"):
        cm.counter_signal = index[prot.counter_signal]
        length = msg.get_signal_by_name(prot.counter_signal).length
        cm.counter_modulus = {"p1": 15, "dct": 16, "p2": 16}.get(kind, 2 ** length)
    if kind == "p1":
        cm.data_id = prot.data_id
        cm.data_id_mode = P1_DATA_ID_MODES.index(prot.data_id_mode)
        if prot.data_id_mode == "nibble":
            cm.nibble_signal = index[prot.data_id_nibble_signal]
    if kind == "p2":
        for k, v in enumerate(prot.data_id_list):
            cm.data_id_list[k] = v


# ---------------------------------------------------------------------------
# The project's own contract and the benchmark
# ---------------------------------------------------------------------------

def contract_protection() -> Protection:
    """The protection of every message of can_dbc/dct_hil.dbc."""
    return Protection(kind="dct", crc_signal=codec.CRC_SIGNAL, counter_signal=codec.COUNTER_SIGNAL,
                      max_delta_counter=codec.COUNTER_MAX_JUMP)


def contract_table() -> CodecTable:
    """A CodecTable of can_dbc/dct_hil.dbc: the plant's messages, then the TCU's."""
    msgs = codec.messages("PLANT") + codec.messages("TCU")
    return CodecTable([(m, contract_protection()) for m in msgs])


def bench(iterations=200_000, repeat=5, mapping=None) -> dict:
    """The codec cost of one tick of the real-time loop for a mapping file,
    timed in C (ct_bench_tick). ``mapping``: a path, the name of a shipped
    mapping (``dct_hil``, ``vehicle``) or a loaded can_dbc.mapping.Mapping;
    default the project's own contract (can_dbc/mappings/dct_hil.toml).

    One tick's work, as the loop does it: the frames due in the costliest
    tick of the loop's send schedule (``send_schedule``, the staggering of
    rt_loop/csrc/rt_tx.c) encoded and protected, and one frame of every
    message the plant receives (a full burst) checked and decoded, timed together
    (``schedule``, see _schedule_figure). That figure, ``ns_per_tick``, is
    the one held against ``BOUND_NS`` (``pass``). For comparison
    ``all_messages_ns`` times every sent message at once with the burst: an
    upper bound for any schedule (and the figure used when the schedule's
    hyperperiod is too long to walk). Each bus is one table (as in the loop,
    one per channel); the buses' figures are summed.
    ct_bench_tick takes at most CT_BENCH_MAX_RX received messages per call:
    a bus with more is timed in several calls (each with its share of the
    messages) whose figures are added.

    The best of ``repeat`` runs of ``iterations`` ticks: a run times every
    call of every bus once; its figure is their sum (every run's kept in
    ``runs_ns``). Raises RuntimeError when a prepared frame is rejected."""
    import os

    if iterations < 1 or repeat < 1:
        raise ValueError("iterations and repeat must be at least 1")
    m = _load_mapping(mapping)
    buses = []
    for b in m.buses:
        msgs = m.codec_order(b.name)
        if not msgs:
            continue
        t = CodecTable([(x.message, x.protection) for x in msgs])
        tx = [i for i, x in enumerate(msgs) if x.direction == "send"]
        rx = [i for i, x in enumerate(msgs) if x.direction == "receive"]
        buses.append({"bus": b.name, "table": t, "calls": _bench_calls(t, tx, rx), "tx": tx, "rx": rx,
                      "runs_ns": []})
    if not buses:
        raise ValueError(f"{m.path}: no messages to time")
    totals = []
    for _ in range(repeat):
        total = 0.0
        for bus in buses:
            ns = sum(_bench_call(bus["table"], call, iterations) for call in bus["calls"])
            bus["runs_ns"].append(ns)
            total += ns
        totals.append(total)
    all_ns = min(totals)
    schedule = _schedule_figure(m, buses, iterations, repeat)
    best = all_ns if schedule is None else schedule["ns_per_tick"]

    def names(bus, key):
        return [bus["table"].messages[i].name for i in bus[key]]

    tx_names = [n for bus in buses for n in names(bus, "tx")]
    rx_names = [n for bus in buses for n in names(bus, "rx")]
    return {
        "mapping": _shown_path(m.path),
        "name": os.path.splitext(os.path.basename(m.path))[0],
        "rate_hz": m.rate_hz,
        "ns_per_tick": best,
        "figure": "all_messages" if schedule is None else "schedule_worst_tick",
        "all_messages_ns": all_ns,
        "runs_ns": totals,
        "iterations": iterations,
        "repeat": repeat,
        "tx_messages": tx_names,
        "rx_messages": rx_names,
        "frames_per_tick": {"encoded": len(tx_names), "decoded": len(rx_names),
                            "total": len(tx_names) + len(rx_names)},
        "schedule_worst_tick_tx": None if schedule is None else len(schedule["tx_messages"]),
        "schedule": schedule,
        "buses": [{"bus": bus["bus"], "tx_messages": names(bus, "tx"), "rx_messages": names(bus, "rx"),
                   "calls": len(bus["calls"]), "ns_per_tick": min(bus["runs_ns"]),
                   "runs_ns": bus["runs_ns"]} for bus in buses],
        "bound_ns": BOUND_NS,
        "pass": best <= BOUND_NS,
    }


#: the requirement: the codec cost per tick at most 1 us
BOUND_NS = 1000.0
#: the shipped mappings the benchmark reports by default
BENCH_MAPPINGS = ("dct_hil", "vehicle")
DEFAULT_JSON = "out/codec_bench.json"
DEFINITION = ("one tick's work: the frames due in the loop's costliest tick (its send schedule) "
              "encoded + protected and one frame of every received message checked + decoded "
              "(a full burst), timed together; for comparison every sent message at once "
              "(all_messages_ns, an upper bound for any schedule); one table per bus, the buses "
              "summed")


def _load_mapping(mapping):
    from . import mapping as mapping_mod
    if mapping is None:
        return mapping_mod.load(mapping_mod.DEFAULT_MAPPING)
    if isinstance(mapping, mapping_mod.Mapping):
        return mapping
    return mapping_mod.load(mapping_mod.find_mapping(mapping))


def _shown_path(path):
    import os

    rel = os.path.relpath(os.path.abspath(path))
    return rel if not rel.startswith(os.pardir) else os.path.abspath(path)


def _rx_per_call():
    return int(getattr(_c()[1], "CT_BENCH_MAX_RX", 8))


#: sent messages ct_bench_tick takes per call
_TX_PER_CALL = 64


def _bench_calls(t, tx, rx):
    """The ct_bench_tick calls that together make one tick's work on table
    ``t``: (tx indices, rx indices) per call, each within the call's limits,
    with the C arrays of their signal values (a fixed point of each signal's
    range, 37 % of the way up)."""
    ffi = t.ffi
    per_rx = _rx_per_call()
    tx_chunks = [tx[k:k + _TX_PER_CALL] for k in range(0, len(tx), _TX_PER_CALL)]
    rx_chunks = [rx[k:k + per_rx] for k in range(0, len(rx), per_rx)]
    n = max(len(tx_chunks), len(rx_chunks))
    tx_chunks += [[]] * (n - len(tx_chunks))
    rx_chunks += [[]] * (n - len(rx_chunks))

    def values(indices):
        out = []
        for i in indices:
            for s in t._signals[i]:
                lo = s.minimum if s.minimum is not None else 0.0
                hi = s.maximum if s.maximum is not None else 1.0
                out.append(lo + 0.37 * (hi - lo))
        return out

    calls = []
    for txs, rxs in zip(tx_chunks, rx_chunks):
        rx_vals = values(rxs)
        calls.append({
            "tx": ffi.new("int32_t[]", txs or [0]), "n_tx": len(txs),
            "tx_values": ffi.new("double[]", values(txs) or [0.0]),
            "rx": ffi.new("int32_t[]", rxs or [0]), "n_rx": len(rxs),
            "rx_values": ffi.new("double[]", rx_vals or [0.0]),
            "rx_out": ffi.new("double[]", max(len(rx_vals), 1)),
            "accepted": ffi.new("int64_t *"),
        })
    return calls


def _bench_call(t, call, iterations):
    ns = t.lib.ct_bench_tick(t.table, call["tx"], call["n_tx"], call["tx_values"], call["rx"],
                             call["n_rx"], call["rx_values"], call["rx_out"], iterations, call["accepted"])
    if ns < 0:
        raise RuntimeError("ct_bench_tick refused its arguments")
    if call["accepted"][0] != iterations * call["n_rx"]:
        raise RuntimeError(f"the benchmark's frames were rejected ({call['accepted'][0]} of "
                           f"{iterations * call['n_rx']} accepted)")
    return ns


def send_schedule(mapping):
    """The loop's send schedule for a loaded mapping, as rt_tx.c (rt_tx_plan)
    computes it: [(bus, message, div, offset)], a message of cycle c sent at
    the ticks k with k % div == offset, div = round(c / period) (at least 1);
    the offsets chosen message by message, in the order of their cycle times
    (then bus, then codec order), to meet the fewest messages already planned."""
    period_ms = 1000.0 / mapping.rate_hz
    sent = sorted((m for b in mapping.buses for m in mapping.codec_order(b.name) if m.direction == "send"),
                  key=lambda m: m.cycle_ms)
    plan = []
    for m in sent:
        ticks = m.cycle_ms / period_ms
        div = 1 if ticks < 1.5 else int(math.floor(ticks + 0.5))
        best, best_cost = 0, math.inf
        for off in range(div):
            cost = sum(1.0 / d for _, _, d, o in plan if off % math.gcd(div, d) == o % math.gcd(div, d))
            if cost < best_cost - 1e-12:
                best, best_cost = off, cost
        plan.append((m.bus, m.name, div, best))
    return plan


def _schedule_ticks(plan, max_ticks=1_000_000):
    """The sets of (bus, message) due in each tick of one hyperperiod of a
    send schedule, None if the hyperperiod exceeds ``max_ticks``."""
    hyper = 1
    for _, _, d, _ in plan:
        hyper = hyper * d // math.gcd(hyper, d)
        if hyper > max_ticks:
            return None
    return [[(b, n) for b, n, d, o in plan if k % d == o] for k in range(hyper)]


def schedule_worst_tick(mapping, max_ticks=1_000_000):
    """The most sent frames due in one tick of the loop's schedule
    (send_schedule), over one hyperperiod; None if that exceeds ``max_ticks``."""
    ticks = _schedule_ticks(send_schedule(mapping), max_ticks)
    return None if ticks is None else max((len(due) for due in ticks), default=0)


def _schedule_figure(m, buses, iterations, repeat):
    """The loop's own worst tick: the tick of the schedule (send_schedule) whose
    due frames cost the most (each sent message's encode + protect timed alone
    to rank the ticks), then that tick's frames encoded + protected together
    with one frame of every received message checked + decoded (a full burst),
    timed in C as one tick (best of ``repeat``): {"tx_messages": the frames due
    in that tick, "ns_per_tick": its measured cost, "rx_burst_ns": the burst's
    alone}. None if the schedule's hyperperiod is too long to walk."""
    ticks = _schedule_ticks(send_schedule(m))
    if ticks is None:
        return None
    tx_ns, rx_ns = {}, 0.0
    for bus in buses:
        t = bus["table"]
        for i in bus["tx"]:
            call = _bench_calls(t, [i], [])[0]
            tx_ns[(bus["bus"], t.messages[i].name)] = min(_bench_call(t, call, iterations)
                                                          for _ in range(repeat))
        if bus["rx"]:
            calls = _bench_calls(t, [], bus["rx"])
            rx_ns += min(sum(_bench_call(t, c, iterations) for c in calls) for _ in range(repeat))
    worst = max(ticks, key=lambda due: (sum(tx_ns[k] for k in due), len(due)))
    calls = []
    for bus in buses:
        t = bus["table"]
        due = [i for i in bus["tx"] if (bus["bus"], t.messages[i].name) in worst]
        if due or bus["rx"]:
            calls.extend((t, c) for c in _bench_calls(t, due, bus["rx"]))
    measured = min(sum(_bench_call(t, c, iterations) for t, c in calls) for _ in range(repeat))
    return {"tx_messages": [f"{b}.{n}" if len(buses) > 1 else n for b, n in worst],
            "ns_per_tick": measured, "rx_burst_ns": rx_ns}


def bench_report(mappings=BENCH_MAPPINGS, iterations=200_000, repeat=5) -> dict:
    """bench() of each mapping, with the machine and the definition: what
    ``--bench`` writes as JSON."""
    from plant.machine import machine_info
    results = [bench(iterations, repeat, m) for m in mappings]
    return {
        "what": "codec cost per tick (can_dbc/csrc/can_table.c, timed in C by ct_bench_tick)",
        "definition": DEFINITION,
        "bound_ns": BOUND_NS,
        "iterations": iterations,
        "repeat": repeat,
        "machine": machine_info(),
        "mappings": results,
        "pass": all(r["pass"] for r in results),
    }


def _print_report(report):
    print(f"codec cost per tick, table codec in C (best of {report['repeat']} runs of "
          f"{report['iterations']} ticks); {report['definition']}")
    for r in report["mappings"]:
        buses = ", ".join(f"{b['bus']} {len(b['tx_messages'])} + {len(b['rx_messages'])}"
                          + (f" in {b['calls']} calls" if b["calls"] > 1 else "") for b in r["buses"])
        print(f"{r['name']} ({r['mapping']}): {len(r['tx_messages'])} plant messages encoded + protected, "
              f"{len(r['rx_messages'])} TCU messages checked + decoded ({len(r['buses'])} "
              f"bus{'es' if len(r['buses']) > 1 else ''}: {buses})")
        fpt = r["frames_per_tick"]
        sched = r["schedule"]
        if sched is not None:
            print(f"  the loop's costliest tick: {len(sched['tx_messages'])} frames due "
                  f"({', '.join(sched['tx_messages'])}) + the burst of {fpt['decoded']}: "
                  f"{sched['ns_per_tick']:.0f} ns per tick, bound {r['bound_ns']:.0f} ns: "
                  f"{'pass' if r['pass'] else 'FAIL'}")
        print(f"  every message at once ({fpt['encoded']} encoded, {fpt['decoded']} decoded, an "
              f"upper bound for any schedule): {r['all_messages_ns']:.0f} ns per tick (runs: "
              f"{', '.join(f'{x:.0f}' for x in r['runs_ns'])} ns)"
              + ("" if sched is not None else
                 f", bound {r['bound_ns']:.0f} ns: {'pass' if r['pass'] else 'FAIL'}"))


def main(argv=None):
    import json
    import os

    parser = argparse.ArgumentParser(prog="python -m can_dbc.table",
                                     description="The table-driven CAN codec (can_dbc/csrc/can_table.c).")
    parser.add_argument("--bench", action="store_true",
                        help="time one tick's CAN work in C per mapping: every sent message encoded "
                             "and protected, one frame of every received message checked and decoded")
    parser.add_argument("--mapping", action="append", metavar="FILE",
                        help="a mapping file (or a shipped mapping's name) to time; may be given "
                             f"several times (default: {', '.join(BENCH_MAPPINGS)})")
    parser.add_argument("--iterations", type=int, default=200_000, help="ticks per run (default: %(default)s)")
    parser.add_argument("--repeat", type=int, default=5, help="runs; the best is reported (default: %(default)s)")
    parser.add_argument("--json", default=DEFAULT_JSON, metavar="PATH",
                        help="write the figures here (default %(default)s; the folder is created)")
    parser.add_argument("--check", action="store_true",
                        help=f"exit 1 when a mapping's figure exceeds {BOUND_NS:.0f} ns per tick")
    args = parser.parse_args(argv)
    if not args.bench:
        parser.print_usage(sys.stderr)
        print("python -m can_dbc.table: nothing to do (try --bench)", file=sys.stderr)
        return 2
    if args.iterations < 1 or args.repeat < 1:
        print("python -m can_dbc.table: --iterations and --repeat must be at least 1", file=sys.stderr)
        return 2
    from .mapping import MappingError
    try:
        report = bench_report(args.mapping or BENCH_MAPPINGS, args.iterations, args.repeat)
    except (MappingError, TableError, ValueError) as e:
        print(f"python -m can_dbc.table: {e}", file=sys.stderr)
        return 2
    _print_report(report)
    if args.json:
        folder = os.path.dirname(args.json)
        if folder:
            os.makedirs(folder, exist_ok=True)
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=2)
            f.write("\n")
        print(f"figures in {args.json}")
    if args.check and not report["pass"]:
        over = [r["name"] for r in report["mappings"] if not r["pass"]]
        print(f"python -m can_dbc.table: above {BOUND_NS:.0f} ns per tick: {', '.join(over)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
