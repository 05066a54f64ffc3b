"""End-to-end protection of one CAN message: which scheme, where its fields are.

A DBC says where a checksum and a counter signal sit, never how they are
computed; the mapping file says that, and this is its parsed form, shared by
the mapping loader (``can_dbc.mapping``) and the table-driven codec
(``can_dbc.table``, ``can_dbc/csrc/can_table.c``) that applies it.

Kinds:

``none``
    no protection.
``counter``
    ``counter_signal`` only: +1 per frame, wrapping at 2**length - 1 -> 0.
``dct``
    the project's own contract (can_dbc/dct_hil.dbc): CRC-8/SAE-J1850
    (poly 0x1D, init 0xFF, xorout 0xFF) over the identifier as two bytes
    (low byte first) followed by every payload byte except the checksum's,
    in ``crc_signal``; a 4-bit ``counter_signal``.
``p1``
    AUTOSAR E2E Profile 1: CRC-8/SAE-J1850 over the Data ID (``data_id``,
    16 bits, put in by ``data_id_mode``: ``both`` low then high byte, ``alt``
    the low byte for even counters and the high byte for odd ones, ``low``
    the low byte only, ``nibble`` the low byte, with the high byte's low
    nibble sent in the payload nibble ``data_id_nibble_signal``) followed by
    the payload without the CRC byte; a 4-bit counter (14 is the largest
    value, 15 is invalid).
``p2``
    AUTOSAR E2E Profile 2: CRC-8H2F (poly 0x2F, init 0xFF, xorout 0xFF) over
    the payload bytes after the CRC byte, then the Data ID
    ``data_id_list[counter]`` (16 entries); a 4-bit counter 0..15.
``xor``
    a checksum that is the XOR of every payload byte except its own
    (older VW/Audi powertrain messages); optionally a counter.
``p5``
    AUTOSAR E2E Profile 5: a 3-byte header at bit ``offset_bits`` (its
    Offset, a multiple of 8; default 0): the CRC in that byte and the next
    (low byte first), the 8-bit counter (0..255) in the byte after them. The CRC is CRC-16/CCITT-FALSE
    (poly 0x1021, init 0xFFFF, no reflection, no final XOR) over the payload
    bytes before the header, the bytes after the CRC (the counter first),
    then the Data ID's (``data_id``, 16 bits) low and high byte. ``crc`` (a
    16-bit signal on the CRC's bytes) and ``counter`` (an 8-bit signal on
    the counter's byte) name the message's signals there when it has them;
    the codec writes the header either way. ``max_delta_counter`` 1..255.
``p4``
    AUTOSAR E2E Profile 4 (CAN FD frames: its header takes 12 bytes): at bit
    ``offset_bits`` (a multiple of 8; default 0), each field big endian, the
    frame's length in bytes (16 bits), the counter (16 bits, 0..65535), the
    Data ID (``data_id``, 32 bits) and the CRC-32P4 (poly 0xF4ACFB13,
    reflected, init and final XOR 0xFFFFFFFF) over every byte but the CRC's.
    ``crc`` (a 32-bit Motorola signal on the CRC) and ``counter`` (a 16-bit
    Motorola signal on the counter) name the message's signals there when it
    has them. A receiver also rejects a frame whose length or Data ID field
    is not the message's (as a bad CRC). ``max_delta_counter`` 1..255.
``p7``
    AUTOSAR E2E Profile 7 (CAN FD frames: its header takes 20 bytes): at bit
    ``offset_bits``, each field big endian, the CRC-64 (ECMA-182 poly
    0x42F0E1EBA9EA3693, reflected, init and final XOR all ones; CRC-64/XZ)
    over every byte but the CRC's, the frame's length (32 bits), the counter
    (32 bits) and the Data ID (``data_id``, 32 bits); ``crc`` (a 64-bit
    Motorola signal) and ``counter`` (a 32-bit Motorola signal) name the
    message's signals there. As P4's, a frame with another length or Data ID
    is rejected as a bad CRC. The loop's counter runs 0 .. 2^32 - 2 (its
    counter modulus is 32 bits); a receiver that accepted 0xFFFFFFFF takes
    the next frame as its first. ``max_delta_counter`` 1..255.

A receiver rejects a frame whose checksum is wrong or whose counter repeats
or advances by more than ``max_delta_counter``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["HEADER_BYTES", "HEADER_FIELDS", "KINDS", "P1_DATA_ID_MODES", "Protection", "ProtectionError",
           "header_field_bits", "parse_protection"]

KINDS = ("none", "counter", "dct", "p1", "p2", "xor", "p5", "p4", "p7")
P1_DATA_ID_MODES = ("both", "alt", "low", "nibble")
#: which fields each kind needs
_NEEDS = {
    "none": (),
    "counter": ("counter_signal",),
    "dct": ("crc_signal", "counter_signal"),
    "p1": ("crc_signal", "counter_signal", "data_id"),
    "p2": ("crc_signal", "counter_signal", "data_id_list"),
    "xor": ("crc_signal",),
    "p5": ("data_id",),
    "p4": ("data_id",),
    "p7": ("data_id",),
}
#: the largest max_delta_counter per kind (the counter's range less one; 14 for the 4-bit ones)
_MAX_DELTA = {"p5": 255, "p4": 255, "p7": 255}
#: the Data ID's largest value per kind (16 bits unless named here)
_MAX_DATA_ID = {"p4": 0xFFFFFFFF, "p7": 0xFFFFFFFF}
#: the kinds with a header at offset_bits: its length in bytes
HEADER_BYTES = {"p5": 3, "p4": 12, "p7": 20}
#: the fields of the header kinds: role -> (byte within the header, bits, byte order of a
#: multi-byte field), and the profile's number
HEADER_FIELDS = {
    "p5": (5, {"crc": (0, 16, "little_endian"), "counter": (2, 8, None)}),
    "p4": (4, {"counter": (2, 16, "big_endian"), "crc": (8, 32, "big_endian")}),
    "p7": (7, {"crc": (0, 64, "big_endian"), "counter": (12, 32, "big_endian")}),
}


def header_field_bits(prot, role):
    """The frame bits (8 * byte + bit) of a header kind's field ``role`` (crc, counter)."""
    first, bits, _ = HEADER_FIELDS[prot.kind][1][role]
    b = prot.offset_bits // 8 + first
    return set(range(8 * b, 8 * b + bits))


_KEYS = ("kind", "crc", "counter", "data_id", "data_id_mode", "data_id_nibble", "data_id_list",
         "max_delta_counter", "offset_bits")


class ProtectionError(ValueError):
    """A protection description that cannot be used (one line: the key and the cause)."""


@dataclass(frozen=True)
class Protection:
    kind: str = "none"
    crc_signal: str | None = None           # the checksum signal (dct, p1, p2, xor)
    counter_signal: str | None = None       # the counter signal
    data_id: int | None = None              # p1, p5: 16-bit Data ID; p4, p7: 32 bits
    data_id_mode: str = "both"              # p1: P1_DATA_ID_MODES
    data_id_nibble_signal: str | None = None  # p1 "nibble": where the high nibble goes
    data_id_list: tuple[int, ...] | None = None  # p2: 16 Data IDs (8 bits), one per counter value
    max_delta_counter: int = 2              # a counter may advance by 1..this
    offset_bits: int = 0                    # p5, p4, p7: where the header starts, a multiple of 8
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    def signals(self) -> tuple[str, ...]:
        """The message's signals this protection writes (never a plant signal)."""
        return tuple(s for s in (self.crc_signal, self.counter_signal,
                                 self.data_id_nibble_signal) if s)


def parse_protection(spec: Any, where: str) -> Protection:
    """A Protection from a mapping file's ``protection`` value.

    ``spec`` is a kind name ("none") or a table: ``{kind = "p1", crc =
    "CHK", counter = "BZ", data_id = 0x123, data_id_mode = "both"}``;
    ``where`` names the place for the one-line error (``file: key``).
    """
    if isinstance(spec, str):
        spec = {"kind": spec}
    if not isinstance(spec, dict):
        raise ProtectionError(f"{where}: protection must be a kind name or a table, got {spec!r}")
    unknown = sorted(set(spec) - set(_KEYS))
    if unknown:
        raise ProtectionError(f"{where}: unknown protection key {unknown[0]!r} (known: "
                              f"{', '.join(_KEYS)})")
    kind = spec.get("kind", "none")
    if kind not in KINDS:
        raise ProtectionError(f"{where}: protection kind {kind!r}: choose one of {', '.join(KINDS)}")
    crc = _name(spec.get("crc"), f"{where}.crc")
    counter = _name(spec.get("counter"), f"{where}.counter")
    data_id = spec.get("data_id")
    most_id = _MAX_DATA_ID.get(kind, 0xFFFF)
    if data_id is not None and (isinstance(data_id, bool) or not isinstance(data_id, int)
                                or not 0 <= data_id <= most_id):
        raise ProtectionError(f"{where}.data_id: must be a whole number 0..{most_id}, got {data_id!r}")
    mode = spec.get("data_id_mode", "both")
    if mode not in P1_DATA_ID_MODES:
        raise ProtectionError(f"{where}.data_id_mode: {mode!r}: choose one of "
                              f"{', '.join(P1_DATA_ID_MODES)}")
    nibble = _name(spec.get("data_id_nibble"), f"{where}.data_id_nibble")
    if kind == "p1" and mode == "nibble" and nibble is None:
        raise ProtectionError(f"{where}: data_id_mode \"nibble\" needs data_id_nibble (the signal "
                              "that carries the Data ID's high nibble)")
    ids = spec.get("data_id_list")
    if ids is not None:
        if (not isinstance(ids, list) or len(ids) != 16
                or any(isinstance(x, bool) or not isinstance(x, int) or not 0 <= x <= 255
                       for x in ids)):
            raise ProtectionError(f"{where}.data_id_list: must be 16 whole numbers 0..255 (one "
                                  "per counter value)")
        ids = tuple(ids)
    delta = spec.get("max_delta_counter", 2)
    most = _MAX_DELTA.get(kind, 14)
    if isinstance(delta, bool) or not isinstance(delta, int) or not 1 <= delta <= most:
        raise ProtectionError(f"{where}.max_delta_counter: must be 1..{most}, got {delta!r}")
    offset = spec.get("offset_bits", 0)
    if "offset_bits" in spec and kind not in HEADER_BYTES:
        raise ProtectionError(f"{where}.offset_bits: only protections p4, p5 and p7 have an offset "
                              "(their header's first bit)")
    last = 8 * (64 - HEADER_BYTES.get(kind, 3))
    if isinstance(offset, bool) or not isinstance(offset, int) or not 0 <= offset <= last or offset % 8:
        raise ProtectionError(f"{where}.offset_bits: must be the header's first bit, a multiple of 8 "
                              f"from 0 to {last}, got {offset!r}")
    p = Protection(kind=kind, crc_signal=crc, counter_signal=counter, data_id=data_id,
                   data_id_mode=mode, data_id_nibble_signal=nibble, data_id_list=ids,
                   max_delta_counter=delta, offset_bits=offset)
    for need in _NEEDS[kind]:
        if getattr(p, need) is None:
            key = {"crc_signal": "crc", "counter_signal": "counter"}.get(need, need)
            raise ProtectionError(f"{where}: protection {kind!r} needs {key}")
    return p


def _name(value: Any, where: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise ProtectionError(f"{where}: must be a signal name, got {value!r}")
    return value
