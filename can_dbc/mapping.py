"""Mapping files: what the plant sends and receives on a vehicle's CAN matrix.

A mapping file (TOML) names one CAN matrix per bus the plant serves (a DBC,
an AUTOSAR system description (ARXML), KCD or SYM file) and says
which DBC nodes the plant plays (all their messages are sent: restbus) and
which belong to the device under test (their messages are received), then,
per message, what drives each signal: a plant output (a ``dct_outputs``
field), the simulator's status, a constant, a toggle, a counter; or, for a
received message, which plant input (a ``dct_inputs`` field) a signal drives
or under which name it is recorded. ``load`` checks everything and returns a
plain, immutable description (:class:`Mapping`); any problem is one line
naming the file, the key and the cause (:class:`MappingError`).

The format, with every key::

    [[bus]]                          # one per CAN channel the plant serves
    name = "pt"                      # its name in statistics and on the command line
    dbc = "vehicle_pt.dbc"           # relative to the mapping file; .arxml, .kcd, .sym too
    cluster = "PT_CAN"               # an ARXML's CAN cluster; needed when it has several
    bitrate = 500000                 # bit/s; default: the DBC's Baudrate
    data_bitrate = 2000000           # CAN FD data phase (bit rate switch); default: none
    fd = false                       # CAN FD; default: what the DBC says
    plant_nodes = ["Motor", "ABS"]   # nodes the plant plays: all their messages are sent
    tcu_nodes = ["Getriebe"]         # nodes of the device under test: their messages are received

    [message.Motor_1]                # a message by name; "pt:Motor_1" or bus = "pt" picks the bus
    bus = "pt"                       # needed only when the name is on more than one bus
    direction = "send"               # send, receive or ignore; default: what the nodes imply
    cycle_ms = 10                    # default: the DBC's GenMsgCycleTime
    timeout_cycles = 10              # received messages only (default 10)
    optional = false                 # received messages only: true when the device under test may
                                     # leave it out (a status it may not have): never receiving it is
                                     # no failure of the run; its values stay safe (default false)
    protection = { kind = "p1", crc = "Motor_1_CRC", counter = "Motor_1_BZ", data_id = 0x123 }
                                     # default: the E2E protection an ARXML gives the message, else none

    [message.Motor_1.signals]        # sent: where each signal's value comes from
    Motordrehzahl = { output = "engine_speed_rpm" }
    Motormoment = { output = "engine_torque_nm", unit = "%", reference = 350.0 }
    Geschwindigkeit = { output = "vehicle_speed_kmh", unit = "m/s", factor = 1.0, offset = 0.0 }
    Gang = { output = "gear", table = { "-1" = 7, "0" = 0, "1" = 1, default = 15 } }
    Richtung = { output = "vehicle_speed_kmh", table = { "..-1" = 2, "0" = 0, "1.." = 1, default = 3 } }
    Tempo = { output = "vehicle_speed_kmh", abs = true }   # the magnitude (a direction signal beside it)
    Rad_VL = { output = "wheel_speed_fl_rpm", factor = 0.119129 }   # rpm -> km/h: no unit converts it
    Zeit = { status = "sim_time_s" }
    Kodierung = { constant = 3 }     # a number or one of the signal's DBC value names
    Toggle = { toggle = true }       # 0, 1, 0, 1 per frame
    Zaehler = { counter = 15 }       # 0 .. 15 per frame

    [message.Getriebe_1.signals]     # received: what each signal drives
    Strom_K1 = { input = "solenoid_current1_a", unit = "mA", min = 0.0, max = 1.2, safe = 0.0 }
    Zielgang = { record = "target_gear", safe = 0 }

Rules:

- Values: the unit conversion first, then ``factor`` and ``offset`` in the
  destination's unit: sent, signal = convert(output) * factor + offset;
  received, input = convert(signal) * factor + offset, then limited to
  ``min``/``max``; ``safe`` is the input's (or recorded) value while the
  message is timed out (default 0). ``abs = true`` (sent signals) takes the
  output's magnitude first. A ``table`` replaces the scaling: the source
  rounded to a whole number picks the entry, keys are whole numbers or ranges
  ("1..5", "..-1", "10.."; no two overlap), ``default`` any other value.
- Units: an output's or input's unit is its name's suffix (``_rpm``,
  ``_kmh``, ``_bar``, ``_nm``, ``_pct``, ``_a``, ``_n``, ``_mm``,
  ``_mps2``, ``_s``, ``_us``, ...; see ``SUFFIX_UNITS``); ``unit`` is the
  unit the signal is in on the bus and converts between the two (``UNITS``:
  an unknown unit is an error); ``unit = "%"`` needs ``reference`` (in the
  output's unit) unless the output is a percentage. When the DBC's unit is a
  known one, ``unit`` must agree with it, and without ``unit`` it must be the
  output's: otherwise an error names both. Between quantities no unit
  converts (wheel rpm to km/h, pedal % to bar) an explicit ``factor`` does,
  in the signal's unit per the output's. Outputs and inputs without a unit
  suffix (states, counts, the gear) and signals without a unit ("", "-") are
  not checked; a DBC unit the table does not know ("Stufe", "MDI") on a
  signal mapped without ``unit`` or ``factor`` to a field with a unit is a
  warning naming both units (``Mapping.warnings``, printed by ``mapping
  check``): the value goes as it is.
- Status sources (``STATUS_FIELDS``): the simulator's own state, as the
  project's ``SIM_Status`` carries it: ``sim_time_s``, ``overrun_count``,
  ``turnaround_max_us``, ``sim_state`` (0 starting, 1 running, 2 stopping,
  3 fault).
- Signals of a sent message without an entry send their GenSigStartValue
  (0 without one); the protection's fields are written by the protection.
  Signals of a received message without an entry drive nothing.
- DBCs are read leniently; only what the mapping uses is checked strictly
  (overlapping signals, lengths, cycle times, identifiers): see ``load``.
- A bus's matrix may be an ARXML, KCD or SYM file (by its suffix;
  ``can_dbc.matrix``). A message an ARXML protects end to end (an E2E
  transformer or protection set: profile 1, 2, 4, 5 or 7, its Data IDs,
  where its CRC and counter are) has that protection unless its entry gives
  ``protection`` (``"none"`` too); a profile the codec lacks (6, 11, 22,
  ...) is an error naming it for a used message without one.
"""

from __future__ import annotations

import difflib
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from typing import Any

from plant.describe import SUFFIX_UNITS

from . import channels as _channels
from . import codec
from .codec import dbc_encoding
from .matrix import file_protections, read_matrix, select_cluster
from .protection import Protection, ProtectionError, parse_protection

__all__ = [
    "DEFAULT_MAPPING", "DEFAULT_RATE_HZ", "DEFAULT_TIMEOUT_CYCLES", "LOAD_WARNING", "MAPPINGS_DIR",
    "STATUS_FIELDS", "SUFFIX_UNITS", "UNITS", "Bus", "BusLoad", "MappedMessage", "MappedSignal",
    "Mapping", "MappingError", "Source", "Target", "bus_load", "check_report", "classic_frame_bits",
    "conversion", "dbc_encoding", "fd_frame_bits", "find_mapping", "frame_time_s", "load", "load_options",
    "parse_pairs", "show", "template", "unit_of_name",
]

MAPPINGS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "mappings")
DEFAULT_MAPPING = os.path.join(MAPPINGS_DIR, "dct_hil.toml")
DEFAULT_RATE_HZ = 2000.0          # the loop's rate: a tick every 0.5 ms
DEFAULT_TIMEOUT_CYCLES = 10       # a received message missing this many cycles is timed out
LOAD_WARNING = 0.5                # warn above 50 % worst-case bus load
PLACEHOLDER_NODE = "Vector__XXX"  # a DBC's "no node"

#: the simulator's status a sent signal can carry ({ status = "..." }), as the C loop fills
#: them (RT_STATUS_* in rt_loop/csrc/rt_loop.h)
STATUS_FIELDS = ("sim_time_s", "overrun_count", "turnaround_max_us", "sim_state")

DIRECTIONS = ("send", "receive", "ignore")
_BUS_KEYS = ("name", "dbc", "bitrate", "data_bitrate", "fd", "plant_nodes", "tcu_nodes", "cluster")
_MESSAGE_KEYS = ("bus", "direction", "cycle_ms", "timeout_cycles", "optional", "protection", "signals")
_SEND_KINDS = ("output", "status", "constant", "toggle", "counter")
_SEND_KEYS = _SEND_KINDS + ("factor", "offset", "unit", "reference", "table", "abs")
_RECEIVE_KINDS = ("input", "record")
_RECEIVE_KEYS = _RECEIVE_KINDS + ("factor", "offset", "unit", "reference", "table", "min", "max",
                                  "safe")
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_RANGE_KEY = re.compile(r"^\s*(-?\d+)?\s*\.\.\s*(-?\d+)?\s*$")
_BUS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")
_FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


class MappingError(ValueError):
    """A mapping file (or its DBC) that cannot be used: one line, file: key: cause."""


# ---------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------

def _u(scale, offset=0.0):
    return (float(scale), float(offset))


#: known units per quantity: unit -> (scale, offset) to the quantity's first unit
#: (value in the first unit = value * scale + offset)
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "rotational speed": {"rpm": _u(1), "1/min": _u(1), "U/min": _u(1), "min-1": _u(1),
                         "min^-1": _u(1), "rev/min": _u(1), "rev/s": _u(60),
                         "rad/s": _u(60 / (2 * math.pi)), "deg/s": _u(1 / 6)},
    "speed": {"m/s": _u(1), "km/h": _u(1 / 3.6), "kmh": _u(1 / 3.6), "kph": _u(1 / 3.6),
              "mph": _u(0.44704), "kn": _u(1852 / 3600)},
    "pressure": {"Pa": _u(1), "hPa": _u(100), "kPa": _u(1e3), "MPa": _u(1e6), "bar": _u(1e5),
                 "mbar": _u(100), "psi": _u(6894.757293168361)},
    "torque": {"Nm": _u(1), "N.m": _u(1), "N*m": _u(1), "kNm": _u(1e3)},
    "force": {"N": _u(1), "kN": _u(1e3)},
    "current": {"A": _u(1), "mA": _u(1e-3)},
    "voltage": {"V": _u(1), "mV": _u(1e-3)},
    "length": {"m": _u(1), "mm": _u(1e-3), "cm": _u(1e-2), "km": _u(1e3), "um": _u(1e-6)},
    "acceleration": {"m/s2": _u(1), "m/s^2": _u(1), "m/s\u00b2": _u(1), "g": _u(9.80665)},
    "time": {"s": _u(1), "ms": _u(1e-3), "us": _u(1e-6), "\u00b5s": _u(1e-6), "min": _u(60),
             "h": _u(3600)},
    "temperature": {"K": _u(1), "degC": _u(1, 273.15), "\u00b0C": _u(1, 273.15),
                    "degF": _u(5 / 9, 273.15 - 32 * 5 / 9), "\u00b0F": _u(5 / 9, 273.15 - 32 * 5 / 9)},
    "angle": {"deg": _u(1), "\u00b0": _u(1), "rad": _u(180 / math.pi)},
    "percentage": {"%": _u(1)},
    "volume": {"l": _u(1), "L": _u(1), "ml": _u(1e-3)},
    "volume flow": {"l/h": _u(1), "L/h": _u(1), "l/min": _u(60), "ml/s": _u(3.6)},
    "power": {"W": _u(1), "kW": _u(1e3)},
}
#: DBC unit strings that say "no unit"
_NO_UNIT = ("", "-", "\u2013", "\u2014", "1", "none", "n/a", "n.a.")

_UNIT_INDEX = {u: (q, s) for q, units in UNITS.items() for u, s in units.items()}
_UNIT_FOLDED: dict[str, tuple[str, str] | None] = {}
for _unit, (_q, _s) in _UNIT_INDEX.items():
    _key = _unit.casefold()
    if _key in _UNIT_FOLDED and _UNIT_FOLDED[_key] is not None:
        if _UNIT_INDEX[_UNIT_FOLDED[_key][1]] != (_q, _s):
            _UNIT_FOLDED[_key] = None          # ambiguous without its case
    else:
        _UNIT_FOLDED.setdefault(_key, (_q, _unit))


def _known_unit(text):
    """The table's spelling of a unit string (exact, else ignoring case), or None."""
    if text is None:
        return None
    t = str(text).strip()
    if t in _UNIT_INDEX:
        return t
    hit = _UNIT_FOLDED.get(t.casefold())
    return hit[1] if hit else None


def _no_unit(text):
    return text is None or str(text).strip().casefold() in _NO_UNIT


def unit_of_name(name):
    """The unit a field name's suffix says (``engine_speed_rpm`` -> ``rpm``), or None."""
    suffix = name.rsplit("_", 1)[-1].casefold() if "_" in name else ""
    return SUFFIX_UNITS.get(suffix)


def conversion(from_unit, to_unit):
    """(gain, bias) with value_in_to = gain * value_in_from + bias; ValueError when the
    units are unknown or measure different quantities."""
    a, b = _known_unit(from_unit), _known_unit(to_unit)
    for given, known in ((from_unit, a), (to_unit, b)):
        if known is None:
            raise ValueError(f"unknown unit {given!r}")
    (qa, (sa, oa)), (qb, (sb, ob)) = _UNIT_INDEX[a], _UNIT_INDEX[b]
    if qa != qb:
        raise ValueError(f"cannot convert {a} ({qa}) to {b} ({qb})")
    return sa / sb, (oa - ob) / sb


def _same_unit(a, b):
    ka, kb = _known_unit(a), _known_unit(b)
    return ka is not None and kb is not None and _UNIT_INDEX[ka] == _UNIT_INDEX[kb]


# ---------------------------------------------------------------------------
# The description
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Bus:
    """One CAN channel the plant serves."""
    name: str
    dbc: str                                  # absolute path of the DBC
    bitrate: int                              # bit/s (arbitration phase for CAN FD)
    data_bitrate: int | None                  # CAN FD data phase, None: no bit rate switch
    fd: bool
    plant_nodes: tuple[str, ...]
    tcu_nodes: tuple[str, ...]
    database: Any = field(compare=False, repr=False)   # the cantools database (read leniently)
    #: an ARXML's E2E protection per message name: a Protection, or why it cannot be used (str)
    file_protections: Any = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Source:
    """Where a sent signal's value comes from.

    kind ``output`` (a dct_outputs field) or ``status`` (STATUS_FIELDS):
    signal = gain * field + bias (``absolute``: of the field's magnitude), or
    with ``table`` the entry of the field rounded to a whole number, else the
    first of ``ranges`` (lo, hi, value; lo/hi None: open) that holds it, else
    ``default``; ``constant`` and
    ``start`` (no entry: the GenSigStartValue or 0): ``value``; ``toggle``:
    0, 1, 0, ... per frame; ``counter``: 0 .. ``counter_max`` per frame."""
    kind: str
    name: str | None = None
    gain: float = 1.0
    bias: float = 0.0
    table: tuple[tuple[int, float], ...] | None = None
    ranges: tuple[tuple[int | None, int | None, float], ...] = ()
    default: float | None = None
    absolute: bool = False
    value: float | None = None
    counter_max: int | None = None
    unit: str | None = None                   # the field's unit (from its name)
    signal_unit: str | None = None            # the unit converted to (the mapping's ``unit``)
    reference: float | None = None


@dataclass(frozen=True)
class Target:
    """What a received signal drives: kind ``input`` (a dct_inputs field) or
    ``record`` (recorded with the commands under ``name``, drives no input).
    value = gain * signal + bias (or the ``table`` entry of the signal rounded to
    a whole number, else the first of ``ranges`` that holds it, else
    ``default``), limited to [minimum, maximum];
    ``safe`` while the message is timed out."""
    kind: str
    name: str
    gain: float = 1.0
    bias: float = 0.0
    table: tuple[tuple[int, float], ...] | None = None
    ranges: tuple[tuple[int | None, int | None, float], ...] = ()
    default: float | None = None
    minimum: float | None = None
    maximum: float | None = None
    safe: float = 0.0
    unit: str | None = None                   # the input's unit (from its name)
    signal_unit: str | None = None            # the unit converted from (the mapping's ``unit``)
    reference: float | None = None


@dataclass(frozen=True)
class MappedSignal:
    name: str
    source: Source | None = None              # sent messages (None: a protection field)
    target: Target | None = None              # received messages (None: drives nothing)
    protection_field: str | None = None       # "crc", "counter" or "data_id_nibble"
    signal: Any = field(default=None, compare=False, repr=False)   # the cantools Signal


@dataclass(frozen=True)
class MappedMessage:
    bus: str
    name: str
    frame_id: int
    is_extended: bool
    is_fd: bool
    length: int
    direction: str                            # "send" or "receive"
    cycle_ms: float
    timeout_cycles: int | None                # received messages
    protection: Protection
    signals: tuple[MappedSignal, ...]         # every signal of the message, in DBC order
    mapped: bool                              # named in the mapping file (else restbus / nodes only)
    message: Any = field(default=None, compare=False, repr=False)  # the cantools Message
    optional: bool = False                    # received: the device under test may not send it
    protection_from_file: bool = False        # the protection is the matrix file's (ARXML E2E)

    def signal(self, name):
        for s in self.signals:
            if s.name == name:
                return s
        raise KeyError(name)


@dataclass(frozen=True)
class Mapping:
    path: str
    rate_hz: float
    buses: tuple[Bus, ...]
    messages: tuple[MappedMessage, ...]       # bus by bus, in codec order
    ignored: tuple[tuple[str, str], ...] = ()  # (bus, message) given direction = "ignore"
    #: what the loader let through but a user should look at (one line each: key and cause)
    warnings: tuple[str, ...] = ()

    def bus(self, name):
        for b in self.buses:
            if b.name == name:
                return b
        raise KeyError(name)

    def message(self, name, bus=None):
        hits = [m for m in self.messages if m.name == name and bus in (None, m.bus)]
        if len(hits) != 1:
            raise KeyError(name)
        return hits[0]

    def channels(self, first, named=None, derive=True):
        """{bus name: CAN channel} for serving (or testing) this mapping.

        The first bus is on ``first`` unless ``named`` (bus name -> channel,
        from ``--bus NAME=CHANNEL``) names it; every other bus on the channel
        ``named`` gives it, else (``derive``: in-process and virtual buses)
        ``f"{first}-{bus}"`` or, when ``first`` is a udp_multicast group, the
        group + i on the port + i for the i-th bus (239.74.163.2:43113,
        239.74.163.3:43114, ...; ``can_dbc.channels``), else it is an error.
        A udp_multicast channel without a port, on a bus after the first,
        gets one (43113 + the bus's index). A name in ``named`` that is not a bus of the mapping, one
        channel for two buses, or one udp_multicast port for two, is a
        MappingError (one line)."""
        named = dict(named or {})
        known = [b.name for b in self.buses]
        for name in named:
            if name not in known:
                raise MappingError(f"{self.path}: bus {name!r} (from --bus): the mapping's buses "
                                   f"are {', '.join(known)}")
        out = {}
        for i, b in enumerate(self.buses):
            if b.name in named:
                out[b.name] = str(named[b.name])
            elif i == 0:
                out[b.name] = str(first)
            elif derive:
                out[b.name] = _derived_channel(str(first), b.name, i)
            else:
                raise MappingError(f"{self.path}: bus {b.name!r} has no CAN channel: give "
                                   f"--bus {b.name}=CHANNEL")
        try:
            out = {name: _channels.with_port(ch, i) if i and _channels.is_udp_group(ch) else ch
                   for i, (name, ch) in enumerate(out.items())}
            _channels.check_ports(out, self.path)
        except _channels.ChannelError as e:
            raise MappingError(str(e)) from None
        seen = {}
        for name, ch in out.items():
            if ch in seen:
                raise MappingError(f"{self.path}: buses {seen[ch]!r} and {name!r} are both on "
                                   f"channel {ch!r}; each bus needs a channel of its own")
            seen[ch] = name
        return out

    def codec_order(self, bus):
        """The messages of ``bus`` in the order the C codec gets them: first the
        sent ones, then the received ones, each by identifier (standard before
        extended, ascending)."""
        return tuple(m for m in self.messages if m.bus == bus)


def _derived_channel(first, bus, index):
    """The channel of the index-th bus when only the first's is given."""
    if _channels.is_udp_group(first):
        return _channels.derive(first, index)
    return f"{first}-{bus}"


def _codec_key(m):
    return (0 if m.direction == "send" else 1, m.is_extended, m.frame_id, m.name)


# ---------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------

def find_mapping(name_or_path):
    """A path as given, or the name of a shipped mapping (``dct_hil``, ``vehicle``)."""
    p = str(name_or_path)
    if os.path.isfile(p) or os.sep in p or p.endswith(".toml"):
        return p
    shipped = os.path.join(MAPPINGS_DIR, p + ".toml")
    return shipped if os.path.exists(shipped) else p


def load(path=DEFAULT_MAPPING, rate_hz=DEFAULT_RATE_HZ, *, outputs=None, inputs=None, dbc=None):
    """The checked :class:`Mapping` of a mapping file, or MappingError (one line:
    file: key: cause); nothing is returned half-loaded.

    ``rate_hz``: the loop's rate; every cycle time must be a whole number of its
    ticks. ``outputs``/``inputs``: the plant's field names (default: those of
    dct_outputs/dct_inputs as plant.model sees them). ``dbc``: DBC files used
    instead of those the mapping names (``--dbc``), bus name -> path (a path
    relative to the working directory); an unknown bus name is an error.

    Used messages are those the plant sends (every message of a plant node, or
    direction = "send") and receives (every message of a TCU node, or
    direction = "receive"); direction = "ignore" drops one. Errors: a file that
    is not TOML, a DBC cantools cannot parse even leniently; unknown keys
    anywhere (the known ones are named); an unknown bus, node (or the
    placeholder Vector__XXX), message (or one on several buses without bus),
    signal, plant output, plant input or status field; a message named but
    neither sent nor received by its nodes, or sent by a plant and a TCU node,
    without direction; in a used message, a signal outside the frame or two
    overlapping (except in different branches of one multiplexer), a CAN FD
    frame on a classic bus; a used message without a cycle time (DBC or
    cycle_ms) or one that is not a whole number of ticks; timeout_cycles on a
    sent message; an identifier used twice on one bus (both sent and received,
    or twice in one direction); a signal that is a protection field and has an
    entry, a protection field the message lacks, a bad protection; an entry
    with no or two sources, a key of the other direction; a value table without
    a default, with overlapping keys, or a value outside the signal's range or
    not among its value names (constants, counters, sent tables); unknown
    units, a unit that contradicts the DBC's, a DBC unit the output's differs
    from without unit (or factor, between quantities), % without reference;
    one plant input driven twice, a record name used twice; min above max, a
    safe value outside them."""
    if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate must be a positive number of Hz, got {rate_hz!r}")
    if outputs is None or inputs is None:
        from plant.model import INPUT_NAMES, OUTPUT_NAMES
        outputs = OUTPUT_NAMES if outputs is None else outputs
        inputs = INPUT_NAMES if inputs is None else inputs
    return _Loader(str(path), float(rate_hz), tuple(outputs), tuple(inputs), dict(dbc or {})).load()


def parse_pairs(values, option, form="NAME=VALUE"):
    """``["io=vcan1", ...]`` (a repeated command-line option) as {name: value};
    a value without ``=``, an empty side or a name given twice is a MappingError
    naming ``option`` (and the ``form`` expected)."""
    out = {}
    for text in values or ():
        name, sep, value = str(text).partition("=")
        name, value = name.strip(), value.strip()
        if not sep or not name or not value:
            raise MappingError(f"{option} {text!r}: give {form}")
        if name in out:
            raise MappingError(f"{option}: {name!r} given twice")
        out[name] = value
    return out


def load_options(mapping=None, dbc=(), rate_hz=DEFAULT_RATE_HZ):
    """The Mapping the command line's ``--mapping`` and ``--dbc`` options name:
    ``mapping`` a file or a shipped mapping's name (default: the project's own
    contract), each ``dbc`` value ``FILE`` (the mapping's first bus) or
    ``BUS=FILE``, read instead of the DBC the mapping names. MappingError (one
    line) for anything wrong."""
    overrides = {}
    for text in dbc or ():
        name, sep, value = str(text).partition("=")
        key = name.strip() if sep else None
        path = value.strip() if sep else str(text).strip()
        if not path or (sep and not key):
            raise MappingError(f"--dbc {text!r}: give FILE or BUS=FILE")
        if key in overrides:
            raise MappingError(f"--dbc: {'the first bus' if key is None else repr(key)} given twice")
        overrides[key] = path
    path = find_mapping(DEFAULT_MAPPING if mapping is None else mapping)
    return load(path, rate_hz=rate_hz, dbc=overrides)


def read_dbc(path):
    """The cantools database of a bus's CAN matrix (DBC, ARXML, KCD or SYM by its
    suffix) read leniently, its text decoded as UTF-8 when it is valid UTF-8,
    else as cp1252 (:func:`dbc_encoding`); ValueError with one line
    (``can_dbc.matrix.read_matrix``)."""
    return read_matrix(path)


def _number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _fmt(x):
    return f"{x:.10g}" if isinstance(x, float) else str(x)


def _suggest(name, known):
    close = difflib.get_close_matches(str(name), list(known), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _signal_bits(sig):
    """The frame bit positions (byte * 8 + bit in byte) a signal occupies."""
    bits = []
    if sig.byte_order == "little_endian":
        return list(range(sig.start, sig.start + sig.length))
    pos = sig.start                    # Motorola: the DBC start bit is the MSB
    for _ in range(sig.length):
        bits.append(pos)
        pos = pos + 15 if pos % 8 == 0 else pos - 1
    return bits


def _bit_range(sig):
    b = _signal_bits(sig)
    return f"bits {min(b)}-{max(b)}"


def _cycle_of(msg):
    ct = msg.cycle_time
    return float(ct) if ct else None


def _dbc_attr(db, name):
    try:
        attr = db.dbc.attributes.get(name) if db.dbc is not None else None
    except AttributeError:
        return None
    if attr is None and name == "Baudrate" and len(db.buses) == 1:
        return db.buses[0].baudrate               # an ARXML's cluster, a KCD's bus
    return None if attr is None else attr.value


def _dbc_nodes(db):
    names = [n.name for n in db.nodes]
    for m in db.messages:
        for s in m.senders:
            if s not in names:
                names.append(s)
    return [n for n in names if n != PLACEHOLDER_NODE]


def _dbc_is_fd(db):
    bus_type = _dbc_attr(db, "BusType")
    return ((isinstance(bus_type, str) and "FD" in bus_type.upper()) or any(m.is_fd for m in db.messages)
            or any(b.fd_baudrate for b in db.buses))


class _Loader:
    def __init__(self, path, rate_hz, outputs, inputs, dbc_overrides=None):
        self.path = path
        self.dbc_overrides = dict(dbc_overrides or {})
        self.rate_hz = rate_hz
        self.outputs = outputs
        self.inputs = inputs
        self.driven = {}          # input -> key that drives it
        self.recorded = {}        # record name -> key
        self.warnings = []        # Mapping.warnings

    def fail(self, key, cause, file=None):
        raise MappingError(f"{file or self.path}: {key}: {cause}")

    def keys(self, table, known, key):
        unknown = [k for k in table if k not in known]
        if unknown:
            self.fail(f"{key}.{unknown[0]}" if key else unknown[0],
                      f"unknown key {unknown[0]!r} (known: {', '.join(known)})")

    # -------------------------------------------------------------- file
    def load(self):
        try:
            with open(self.path, "rb") as f:
                doc = tomllib.load(f)
        except OSError as e:
            raise MappingError(f"{self.path}: cannot read: {e.strerror}") from None
        except tomllib.TOMLDecodeError as e:
            raise MappingError(f"{self.path}: not valid TOML: {e}") from None
        except UnicodeDecodeError as e:
            raise MappingError(f"{self.path}: not UTF-8 text (byte {e.start}): a mapping is "
                               "a TOML file") from None
        self.keys(doc, ("bus", "message"), "")
        buses = self.buses(doc.get("bus"))
        entries = self.entries(doc.get("message", {}), buses)
        messages, ignored = [], []
        for bus in buses:
            msgs, ign = self.bus_messages(bus, entries)
            messages.extend(msgs)
            ignored.extend(ign)
        return Mapping(path=os.path.abspath(self.path), rate_hz=self.rate_hz, buses=tuple(buses),
                       messages=tuple(messages), ignored=tuple(ignored), warnings=tuple(self.warnings))

    # -------------------------------------------------------------- buses
    def buses(self, raw):
        if raw is None:
            self.fail("bus", "no [[bus]]: name at least one bus with its DBC")
        if not isinstance(raw, list) or not all(isinstance(b, dict) for b in raw):
            self.fail("bus", "must be an array of tables ([[bus]])")
        names = [b.get("name") for b in raw]
        if None in self.dbc_overrides:                 # --dbc FILE: the first bus
            self.dbc_overrides[names[0]] = self.dbc_overrides.pop(None)
        for name in self.dbc_overrides:
            if name not in names:
                raise MappingError(f"{self.path}: --dbc {name}=...: the mapping has no bus {name!r} "
                                   f"(its buses: {', '.join(str(n) for n in names)})")
        buses = []
        for i, b in enumerate(raw):
            key = f"bus[{i}]"
            self.keys(b, _BUS_KEYS, key)
            name = b.get("name")
            if not isinstance(name, str) or not _BUS_NAME.match(name):
                self.fail(f"{key}.name", f"a bus needs a name (letters, digits, _ and -), got {name!r}")
            if any(x.name == name for x in buses):
                self.fail(f"{key}.name", f"bus {name!r} named twice")
            dbc = b.get("dbc")
            if not isinstance(dbc, str) or not dbc:
                self.fail(f"{key}.dbc", "the bus's DBC file (relative to this file) is missing")
            dbc_path = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(self.path)), dbc))
            if name in self.dbc_overrides:
                dbc = str(self.dbc_overrides[name])
                dbc_path = os.path.abspath(dbc)
            cluster = b.get("cluster")
            if cluster is not None and (not isinstance(cluster, str) or not cluster):
                self.fail(f"{key}.cluster", f"must be the name of a CAN cluster of the ARXML, got {cluster!r}")
            try:
                db = select_cluster(read_dbc(dbc_path), dbc_path, cluster)
                protections = file_protections(db, dbc_path)
            except ValueError as e:
                self.fail(f"{key}.dbc", str(e))
            bitrate = b.get("bitrate", _dbc_attr(db, "Baudrate"))
            if bitrate is None:
                self.fail(f"{key}.bitrate", f"missing: the DBC {dbc} gives no Baudrate")
            if not _number(bitrate) or int(bitrate) != bitrate or not 1_000 <= bitrate <= 8_000_000:
                self.fail(f"{key}.bitrate", f"must be a whole number of bit/s, 1000..8000000, got {bitrate!r}")
            fd = b.get("fd", _dbc_is_fd(db))
            if not isinstance(fd, bool):
                self.fail(f"{key}.fd", f"must be true or false, got {fd!r}")
            data_bitrate = b.get("data_bitrate")
            if data_bitrate is not None:
                if not fd:
                    self.fail(f"{key}.data_bitrate", "only a CAN FD bus (fd = true) has a data bit rate")
                if (not _number(data_bitrate) or int(data_bitrate) != data_bitrate
                        or not bitrate <= data_bitrate <= 16_000_000):
                    self.fail(f"{key}.data_bitrate", f"must be a whole number of bit/s from the "
                                                     f"bitrate ({int(bitrate)}) to 16000000, got {data_bitrate!r}")
                data_bitrate = int(data_bitrate)
            nodes = _dbc_nodes(db)
            plant = self.node_list(b.get("plant_nodes", []), f"{key}.plant_nodes", nodes, dbc)
            tcu = self.node_list(b.get("tcu_nodes", []), f"{key}.tcu_nodes", nodes, dbc)
            both = [n for n in plant if n in tcu]
            if both:
                self.fail(f"{key}.tcu_nodes", f"node {both[0]} is also a plant node")
            buses.append(Bus(name=name, dbc=dbc_path, bitrate=int(bitrate), data_bitrate=data_bitrate,
                             fd=fd, plant_nodes=plant, tcu_nodes=tcu, database=db,
                             file_protections=protections))
        if not buses:
            self.fail("bus", "no [[bus]]: name at least one bus with its DBC")
        return buses

    def node_list(self, raw, key, nodes, dbc):
        if not isinstance(raw, list) or not all(isinstance(n, str) for n in raw):
            self.fail(key, f"must be a list of DBC node names, got {raw!r}")
        for n in raw:
            if n == PLACEHOLDER_NODE:
                self.fail(key, f"{PLACEHOLDER_NODE} is the DBC's placeholder for no node: give the "
                               "messages' direction instead")
            if n not in nodes:
                known = ", ".join(nodes) if nodes else "none"
                self.fail(key, f"unknown node {n!r} in {dbc} (its nodes: {known})")
        if len(set(raw)) != len(raw):
            self.fail(key, "a node is named twice")
        return tuple(raw)

    # -------------------------------------------------------------- message entries
    def entries(self, raw, buses):
        """{(bus name, message name): (key, entry table)}"""
        if not isinstance(raw, dict):
            self.fail("message", "must be a table of messages ([message.NAME])")
        found = {}
        for name, entry in raw.items():
            key = f"message.{name}"
            if not isinstance(entry, dict):
                self.fail(key, "must be a table")
            self.keys(entry, _MESSAGE_KEYS, key)
            bus_name = entry.get("bus")
            msg_name = name
            if ":" in name:
                prefix, msg_name = name.split(":", 1)
                if bus_name is not None and bus_name != prefix:
                    self.fail(f"{key}.bus", f"{bus_name!r} contradicts the bus {prefix!r} in the key")
                bus_name = prefix
            if bus_name is not None:
                if not any(b.name == bus_name for b in buses):
                    self.fail(f"{key}.bus", f"unknown bus {bus_name!r} (buses: "
                                            f"{', '.join(b.name for b in buses)})")
                candidates = [b for b in buses if b.name == bus_name]
            else:
                candidates = buses
            hits = [b for b in candidates if _message_by_name(b.database, msg_name) is not None]
            if not hits:
                where = (f"bus {candidates[0].name} ({os.path.basename(candidates[0].dbc)})"
                         if len(candidates) == 1 else "any bus's DBC")
                known = [m.name for b in candidates for m in b.database.messages]
                self.fail(key, f"unknown message {msg_name!r} on {where}{_suggest(msg_name, known)}")
            if len(hits) > 1:
                self.fail(key, f"message {msg_name!r} is on buses {', '.join(b.name for b in hits)}: "
                               "give bus = \"...\"")
            k = (hits[0].name, msg_name)
            if k in found:
                self.fail(key, f"message {msg_name} on bus {hits[0].name} is mapped twice "
                               f"(also {found[k][0]})")
            found[k] = (key, entry)
        return found

    # -------------------------------------------------------------- per bus
    def bus_messages(self, bus, entries):
        used, ignored = [], []
        dbc = bus.dbc
        for msg in bus.database.messages:
            key, entry = entries.get((bus.name, msg.name), (f"message.{msg.name}", None))
            direction = self.direction(bus, msg, key, entry)
            if direction == "ignore":
                extra = [k for k in (entry or {}) if k not in ("bus", "direction")]
                if extra:
                    self.fail(f"{key}.{extra[0]}", f"message {msg.name} is ignored (direction = \"ignore\"): "
                                                   f"{extra[0]} has no use")
                ignored.append((bus.name, msg.name))
                continue
            if direction is None:
                continue
            used.append(self.message(bus, msg, direction, key, entry or {}, entry is not None, dbc))
        # identifiers: each at most once among the used messages of a bus
        seen = {}
        for m in used:
            k = (m.is_extended, m.frame_id)
            if k in seen:
                other = seen[k]
                ident = f"0x{m.frame_id:0{8 if m.is_extended else 3}X}"
                if other.direction != m.direction:
                    sent, recv = (other, m) if other.direction == "send" else (m, other)
                    self.fail(f"message.{m.name}", f"identifier {ident} on bus {bus.name} is both sent "
                                                   f"({sent.name}) and received ({recv.name})")
                self.fail(f"message.{m.name}", f"identifier {ident} on bus {bus.name} is "
                                               f"{m.direction == 'send' and 'sent' or 'received'} twice "
                                               f"({other.name} and {m.name})")
            seen[k] = m
        return sorted(used, key=_codec_key), ignored

    def direction(self, bus, msg, key, entry):
        given = entry.get("direction") if entry is not None else None
        if given is not None:
            if given not in DIRECTIONS:
                self.fail(f"{key}.direction", f"{given!r}: choose one of {', '.join(DIRECTIONS)}")
            return given
        plant = [s for s in msg.senders if s in bus.plant_nodes]
        tcu = [s for s in msg.senders if s in bus.tcu_nodes]
        if plant and tcu:
            if entry is None:
                self.fail(key, f"message {msg.name} is sent by plant node {plant[0]} and TCU node "
                               f"{tcu[0]}: give direction")
            self.fail(f"{key}.direction", f"message {msg.name} is sent by plant node {plant[0]} and "
                                          f"TCU node {tcu[0]}: give direction")
        if plant:
            return "send"
        if tcu:
            return "receive"
        if entry is not None:
            senders = ", ".join(s for s in msg.senders if s != PLACEHOLDER_NODE)
            who = f"sent by {senders}, not a plant or TCU node" if senders else "has no sending node in the DBC"
            self.fail(f"{key}.direction", f"message {msg.name} {who}: give direction "
                                          "(send, receive or ignore)")
        return None

    def message(self, bus, msg, direction, key, entry, mapped, dbc):
        kind = "sent" if direction == "send" else "received"
        is_fd = bool(msg.is_fd) or msg.length > 8
        if is_fd and not bus.fd:
            self.fail(key, f"message {msg.name} is a CAN FD frame ({msg.length} bytes) but bus "
                           f"{bus.name} is classic CAN (fd = false)")
        if msg.length > 64:
            self.fail(key, f"message {msg.name} has {msg.length} bytes, more than a CAN FD frame carries")
        self.check_layout(bus, msg, kind, dbc)
        # cycle time
        cycle = entry.get("cycle_ms")
        if cycle is not None:
            if not _number(cycle) or cycle <= 0:
                self.fail(f"{key}.cycle_ms", f"must be a number of ms above 0, got {cycle!r}")
            cycle = float(cycle)
            where = f"{key}.cycle_ms"
        else:
            cycle = _cycle_of(msg)
            where = f"{key}.cycle_ms"
            if cycle is None:
                self.fail(where, f"message {msg.name} ({kind} on bus {bus.name}) has no cycle time: the DBC "
                                 "gives no GenMsgCycleTime; give cycle_ms (or direction = \"ignore\")")
        ticks = cycle * self.rate_hz / 1000.0
        if abs(ticks - round(ticks)) > 1e-6 or round(ticks) < 1:
            source = "" if entry.get("cycle_ms") is not None else " (the DBC's GenMsgCycleTime)"
            self.fail(where, f"cycle time {_fmt(cycle)} ms{source} is not a whole number of the loop's "
                             f"{1000.0 / self.rate_hz:g} ms ticks at {self.rate_hz:g} Hz")
        # timeout
        timeout = entry.get("timeout_cycles")
        if timeout is not None and direction != "receive":
            self.fail(f"{key}.timeout_cycles", f"only received messages time out; {msg.name} is {kind}")
        if direction == "receive":
            timeout = DEFAULT_TIMEOUT_CYCLES if timeout is None else timeout
            if isinstance(timeout, bool) or not isinstance(timeout, int) or not 1 <= timeout <= 1000:
                self.fail(f"{key}.timeout_cycles", f"must be a whole number 1..1000, got {timeout!r}")
        optional = entry.get("optional", False)
        if not isinstance(optional, bool):
            self.fail(f"{key}.optional", f"must be true or false, got {optional!r}")
        if optional and direction != "receive":
            self.fail(f"{key}.optional", f"only received messages are optional; {msg.name} is {kind}")
        # protection: the mapping's, else the matrix file's (an ARXML's E2E), else none
        from_file = (bus.file_protections or {}).get(msg.name) if "protection" not in entry else None
        if isinstance(from_file, str):
            self.fail(key, f"message {msg.name} ({kind} on bus {bus.name}): {from_file} (or "
                           f"direction = \"ignore\")", file=dbc)
        try:
            prot = from_file or parse_protection(entry.get("protection", "none"),
                                                 f"{self.path}: {key}.protection")
        except ProtectionError as e:
            raise MappingError(str(e)) from None
        fields = {}
        for role, sig_name in (("crc", prot.crc_signal), ("counter", prot.counter_signal),
                               ("data_id_nibble", prot.data_id_nibble_signal)):
            if sig_name is None:
                continue
            if not _has_signal(msg, sig_name):
                self.fail(f"{key}.protection.{role}", f"message {msg.name} has no signal {sig_name!r}"
                                                      f"{_suggest(sig_name, [s.name for s in msg.signals])}")
            if sig_name in fields:
                self.fail(f"{key}.protection.{role}", f"signal {sig_name} is already the protection's "
                                                      f"{fields[sig_name]}")
            fields[sig_name] = role
        # signals
        raw = entry.get("signals", {})
        if not isinstance(raw, dict):
            self.fail(f"{key}.signals", "must be a table of signals")
        known = [s.name for s in msg.signals]
        for sig_name in raw:
            if sig_name not in known:
                self.fail(f"{key}.signals.{sig_name}", f"message {msg.name} has no signal {sig_name!r}"
                                                       f"{_suggest(sig_name, known)}")
            if sig_name in fields:
                self.fail(f"{key}.signals.{sig_name}", f"signal {sig_name} is the protection's "
                                                       f"{fields[sig_name]} field: it cannot also have an entry")
        signals = []
        for sig in msg.signals:
            skey = f"{key}.signals.{sig.name}"
            if sig.name in fields:
                signals.append(MappedSignal(sig.name, protection_field=fields[sig.name], signal=sig))
            elif direction == "send":
                src = self.source(raw[sig.name], sig, msg, skey) if sig.name in raw else _start(sig)
                signals.append(MappedSignal(sig.name, source=src, signal=sig))
            else:
                tgt = self.target(raw[sig.name], sig, msg, skey) if sig.name in raw else None
                signals.append(MappedSignal(sig.name, target=tgt, signal=sig))
        return MappedMessage(bus=bus.name, name=msg.name, frame_id=msg.frame_id,
                             is_extended=bool(msg.is_extended_frame), is_fd=is_fd, length=msg.length,
                             direction=direction, cycle_ms=cycle, timeout_cycles=timeout, protection=prot,
                             signals=tuple(signals), mapped=mapped, message=msg, optional=optional,
                             protection_from_file=from_file is not None)

    def check_layout(self, bus, msg, kind, dbc):
        """A used message: every signal inside the frame, no two overlapping
        (signals of different branches of one multiplexer may)."""
        where = f"message {msg.name}"
        by_name = {s.name: s for s in msg.signals}
        switched = {}
        for sig in msg.signals:
            if sig.multiplexer_signal is not None:
                switched.setdefault(sig.multiplexer_signal, []).append(sig.name)
        for name, branch in switched.items():
            switch = by_name.get(name)
            if switch is not None and not switch.is_multiplexer:
                # a real-world defect: "m" for "M" in the switch's SG_ line, while SG_MUL_VAL_
                # (or m<ID> markers) name it the multiplexer; the codec cannot send it
                self.fail(where, f"signal {name} switches {', '.join(branch)} but is not marked as a "
                                 f"multiplexer (its SG_ line has no 'M'; a lower-case 'm' is no multiplexer) "
                                 f"({kind} on bus {bus.name}): write '{name} M :' in the DBC, or give "
                                 f"[message.{msg.name}] direction = \"ignore\"", file=dbc)
            if switch is None:
                self.fail(where, f"signals {', '.join(branch)} are multiplexed by {name}, which the message "
                                 f"lacks ({kind} on bus {bus.name}): fix the DBC's SG_MUL_VAL_, or give "
                                 f"[message.{msg.name}] direction = \"ignore\"", file=dbc)
        size = 8 * msg.length
        occupied = []
        for sig in msg.signals:
            bits = _signal_bits(sig)
            if min(bits) < 0 or max(bits) >= size:
                self.fail(where, f"signal {sig.name} ({_bit_range(sig)}) lies outside the "
                                 f"{msg.length}-byte frame ({kind} on bus {bus.name})", file=dbc)
            mine = set(bits)
            for other, obits in occupied:
                if mine & obits and not _other_branch(sig, other):
                    self.fail(where, f"signals {other.name} ({_bit_range(other)}) and {sig.name} "
                                     f"({_bit_range(sig)}) overlap ({kind} on bus {bus.name})", file=dbc)
            occupied.append((sig, mine))

    # -------------------------------------------------------------- signal entries
    def entry_table(self, raw, key, kinds, allowed, other_kinds, msg, direction):
        if not isinstance(raw, dict):
            self.fail(key, f"must be a table such as {{ {kinds[0]} = \"...\" }}")
        wrong = [k for k in raw if k in other_kinds]
        if wrong:
            self.fail(f"{key}.{wrong[0]}", f"message {msg.name} is {direction}: its signals take "
                                           f"{' or '.join(kinds)}, not {wrong[0]}")
        self.keys(raw, allowed, key)
        given = [k for k in kinds if k in raw]
        if len(given) != 1:
            what = "none" if not given else " and ".join(given)
            self.fail(key, f"give exactly one of {', '.join(kinds)} (got {what})")
        return given[0]

    def source(self, raw, sig, msg, key):
        kind = self.entry_table(raw, key, _SEND_KINDS, _SEND_KEYS, ("input", "record", "min", "max", "safe"),
                                msg, "sent")
        if kind in ("constant", "toggle", "counter"):
            extra = [k for k in raw if k != kind]
            if extra:
                self.fail(f"{key}.{extra[0]}", f"{extra[0]} applies to output and status, not {kind}")
        if kind == "constant":
            value = self.signal_value(raw["constant"], sig, f"{key}.constant")
            return Source("constant", value=value)
        if kind == "toggle":
            if raw["toggle"] is not True:
                self.fail(f"{key}.toggle", "must be true (0, 1, 0, ... per frame)")
            self.signal_value(1, sig, f"{key}.toggle")
            return Source("toggle")
        if kind == "counter":
            n = raw["counter"]
            if isinstance(n, bool) or not isinstance(n, int) or n < 1:
                self.fail(f"{key}.counter", f"must be the counter's largest value, a whole number >= 1, got {n!r}")
            self.signal_value(n, sig, f"{key}.counter")
            return Source("counter", counter_max=n)
        name = raw[kind]
        if kind == "output":
            if name not in self.outputs:
                self.fail(f"{key}.output", f"unknown plant output {name!r}{_suggest(name, self.outputs)} "
                                           "(the fields of dct_outputs)")
        elif name not in STATUS_FIELDS:
            self.fail(f"{key}.status", f"unknown status {name!r} (known: {', '.join(STATUS_FIELDS)})")
        unit = unit_of_name(name)
        absolute = raw.get("abs", False)
        if not isinstance(absolute, bool):
            self.fail(f"{key}.abs", f"must be true (send the magnitude) or false, got {absolute!r}")
        if "table" in raw:
            table, ranges, default = self.table(raw, key, sig, to_signal=True)
            return Source(kind, name=name, table=table, ranges=ranges, default=default, absolute=absolute,
                          unit=unit)
        gain, bias, to_unit, ref = self.scaling(raw, key, unit, sig.unit, name, "output" if kind == "output"
                                               else "status", to_signal=True)
        return Source(kind, name=name, gain=gain, bias=bias, absolute=absolute, unit=unit, signal_unit=to_unit,
                      reference=ref)

    def target(self, raw, sig, msg, key):
        kind = self.entry_table(raw, key, _RECEIVE_KINDS, _RECEIVE_KEYS, ("output", "status", "constant",
                                                                          "toggle", "counter"),
                                msg, "received")
        name = raw[kind]
        if kind == "input":
            if name not in self.inputs:
                self.fail(f"{key}.input", f"unknown plant input {name!r}{_suggest(name, self.inputs)} "
                                          "(the fields of dct_inputs)")
            if name in self.driven:
                self.fail(f"{key}.input", f"plant input {name} is already driven by {self.driven[name]}")
            self.driven[name] = key
        else:
            if not isinstance(name, str) or not _NAME.match(name):
                self.fail(f"{key}.record", f"must be a name (letters, digits, _), got {name!r}")
            if name in self.recorded:
                self.fail(f"{key}.record", f"{name!r} is already recorded from {self.recorded[name]}")
            self.recorded[name] = key
        unit = unit_of_name(name)
        lo, hi = raw.get("min"), raw.get("max")
        for k, v in (("min", lo), ("max", hi)):
            if v is not None and not _number(v):
                self.fail(f"{key}.{k}", f"must be a number, got {v!r}")
        if lo is not None and hi is not None and lo > hi:
            self.fail(f"{key}.min", f"min {_fmt(lo)} is above max {_fmt(hi)}")
        safe = raw.get("safe", 0.0)
        if not _number(safe):
            self.fail(f"{key}.safe", f"must be a number, got {safe!r}")
        if (lo is not None and safe < lo) or (hi is not None and safe > hi):
            self.fail(f"{key}.safe", f"safe value {_fmt(safe)} is outside min..max "
                                     f"({_fmt(lo) if lo is not None else '-inf'} .. "
                                     f"{_fmt(hi) if hi is not None else 'inf'})")
        common = dict(minimum=None if lo is None else float(lo), maximum=None if hi is None else float(hi),
                      safe=float(safe), unit=unit)
        if "table" in raw:
            table, ranges, default = self.table(raw, key, sig, to_signal=False)
            return Target(kind, name, table=table, ranges=ranges, default=default, **common)
        gain, bias, from_unit, ref = self.scaling(raw, key, unit, sig.unit, name, kind, to_signal=False)
        return Target(kind, name, gain=gain, bias=bias, signal_unit=from_unit, reference=ref, **common)

    def scaling(self, raw, key, field_unit, dbc_unit, name, what, to_signal):
        """(gain, bias, the signal's unit, reference): field -> signal when
        ``to_signal``, else signal -> field."""
        factor, offset = raw.get("factor", 1.0), raw.get("offset", 0.0)
        for k, v in (("factor", factor), ("offset", offset)):
            if not _number(v):
                self.fail(f"{key}.{k}", f"must be a number, got {v!r}")
        if factor == 0:
            self.fail(f"{key}.factor", "must not be 0")
        unit, ref = raw.get("unit"), raw.get("reference")
        gain, bias = 1.0, 0.0
        if ref is not None and (not _number(ref) or ref == 0):
            self.fail(f"{key}.reference", f"must be a number other than 0, got {ref!r}")
        if unit is not None:
            if not isinstance(unit, str) or _known_unit(unit) is None:
                self.fail(f"{key}.unit", f"unknown unit {unit!r} (known: {', '.join(_UNIT_INDEX)})")
            if not _no_unit(dbc_unit) and _known_unit(dbc_unit) is not None and not _same_unit(unit, dbc_unit):
                self.fail(f"{key}.unit", f"unit {unit!r} but the DBC's unit of the signal is {dbc_unit!r}")
            if _known_unit(unit) == "%" and not _same_unit(field_unit, "%"):
                if ref is None:
                    self.fail(f"{key}.reference", f"unit \"%\" of {what} {name} "
                                                  f"({field_unit or 'no unit'}) needs reference (100 % in "
                                                  f"{field_unit or 'its unit'})")
                # field -> % of reference
                gain = 100.0 / ref if to_signal else ref / 100.0
            else:
                if ref is not None:
                    self.fail(f"{key}.reference", "reference applies to unit = \"%\" only")
                if field_unit is None:
                    self.fail(f"{key}.unit", f"{what} {name} has no unit (its name has no unit suffix) to "
                                             "convert: use factor and offset")
                try:
                    gain, bias = conversion(field_unit, unit) if to_signal else conversion(unit, field_unit)
                except ValueError as e:
                    self.fail(f"{key}.unit", f"{e}: no unit converts one into the other (without unit, "
                                             "factor does)")
        else:
            if ref is not None:
                self.fail(f"{key}.reference", "reference needs unit = \"%\"")
            known = _known_unit(dbc_unit) if not _no_unit(dbc_unit) else None
            if field_unit is not None and not _no_unit(dbc_unit) and known is None and "factor" not in raw:
                # a unit the table does not know: nothing to convert by, nothing to refuse by
                self.warnings.append(
                    f"{key}: the DBC's unit of the signal is {dbc_unit!r}, which the unit table does not "
                    f"know; {what} {name} is in {field_unit!r} and goes as it is: give unit (and "
                    f"reference for a share) or factor if {dbc_unit!r} is not {field_unit!r}")
            if field_unit is not None and known is not None and not _same_unit(field_unit, known):
                q_dbc, q_field = _UNIT_INDEX[known][0], _UNIT_INDEX[_known_unit(field_unit)][0]
                cause = (f"the DBC's unit of the signal is {dbc_unit!r}, {what} {name} is in "
                         f"{field_unit!r}")
                if known == "%":
                    self.fail(key, f"{cause}: give unit = \"%\" and reference (100 % in {field_unit})")
                if q_dbc == q_field:
                    self.fail(key, f"{cause}: give unit = \"{dbc_unit}\" to convert")
                if "factor" not in raw:
                    per = f"{dbc_unit} per {field_unit}" if to_signal else f"{field_unit} per {dbc_unit}"
                    self.fail(key, f"{cause}, another quantity ({q_dbc}, {q_field}): no unit converts one "
                                   f"into the other; give factor ({per}) if the signal derives from it")
                unit = known          # the factor converts: say so in the description
        return gain * factor, bias * factor + offset, unit, None if ref is None else float(ref)

    def table(self, raw, key, sig, to_signal):
        for k in ("factor", "offset", "unit", "reference"):
            if k in raw:
                self.fail(f"{key}.{k}", f"{k} does not combine with table (the table gives the values)")
        t = raw["table"]
        if not isinstance(t, dict):
            self.fail(f"{key}.table", "must be a table such as { \"0\" = 0, \"1\" = 1, default = 15 }")
        if "default" not in t:
            self.fail(f"{key}.table", "a value table needs a default (the value for anything not listed)")
        entries, ranges, spans = [], [], []
        for k, v in t.items():
            if k == "default":
                continue
            span = _table_key(k)
            if span is None:
                self.fail(f"{key}.table", f"key {k!r} is not a whole number or a range A..B (keys are the "
                                          f"{'source' if to_signal else 'signal'} value, rounded)")
            for other_key, other in spans:
                if max(span[0], other[0]) <= min(span[1], other[1]):
                    self.fail(f"{key}.table", f"keys {other_key!r} and {k!r} overlap")
            spans.append((k, span))
            value = (self.signal_value(v, sig, f"{key}.table.{k}") if to_signal
                     else self.plain_value(v, f"{key}.table.{k}"))
            if span[0] == span[1]:
                entries.append((int(span[0]), value))
            else:
                ranges.append((None if span[0] == -math.inf else int(span[0]),
                               None if span[1] == math.inf else int(span[1]), value))
        default = (self.signal_value(t["default"], sig, f"{key}.table.default") if to_signal
                   else self.plain_value(t["default"], f"{key}.table.default"))
        ranges.sort(key=lambda r: -math.inf if r[0] is None else r[0])
        return tuple(sorted(entries)), tuple(ranges), default

    def plain_value(self, v, key):
        if not _number(v):
            self.fail(key, f"must be a number, got {v!r}")
        return float(v)

    def signal_value(self, v, sig, key):
        """A value the signal can carry: a number in its range, or one of its value names."""
        if isinstance(v, str):
            for number, text in (sig.choices or {}).items():
                if str(text) == v:
                    return float(number) * sig.scale + sig.offset
            names = ", ".join(str(t) for t in (sig.choices or {}).values()) or "the signal has no value names"
            self.fail(key, f"{v!r} is not a value name of signal {sig.name} ({names})")
        if not _number(v):
            self.fail(key, f"must be a number, got {v!r}")
        lo, hi = _signal_range(sig)
        if not lo - 1e-9 * max(1.0, abs(lo)) <= v <= hi + 1e-9 * max(1.0, abs(hi)):
            self.fail(key, f"value {_fmt(v)} is outside signal {sig.name}'s range {_fmt(lo)} .. {_fmt(hi)}")
        return float(v)


def _table_key(text):
    """(lo, hi) of a value table key: "3" -> (3, 3), "1..5", "..-1" -> (-inf, -1),
    "1.." -> (1, inf); None when it is neither."""
    try:
        n = int(text.strip())
        return (n, n)
    except ValueError:
        pass
    m = _RANGE_KEY.match(text)
    if not m or (m.group(1) is None and m.group(2) is None):
        return None
    lo = -math.inf if m.group(1) is None else int(m.group(1))
    hi = math.inf if m.group(2) is None else int(m.group(2))
    return (lo, hi) if lo <= hi else None


def _has_signal(msg, name):
    return any(s.name == name for s in msg.signals)


def _message_by_name(db, name):
    for m in db.messages:
        if m.name == name:
            return m
    return None


def _other_branch(a, b):
    """Signals in different branches of the same multiplexer."""
    return (a.multiplexer_signal is not None and a.multiplexer_signal == b.multiplexer_signal
            and a.multiplexer_ids and b.multiplexer_ids
            and not set(a.multiplexer_ids) & set(b.multiplexer_ids))


def _raw_range(sig):
    if sig.is_float:
        return -math.inf, math.inf
    if sig.is_signed:
        return -(2 ** (sig.length - 1)), 2 ** (sig.length - 1) - 1
    return 0, 2 ** sig.length - 1


def _signal_range(sig):
    """The physical values a signal can carry: its DBC range within what its bits hold."""
    rlo, rhi = _raw_range(sig)
    a, b = rlo * sig.scale + sig.offset, rhi * sig.scale + sig.offset
    lo, hi = min(a, b), max(a, b)
    if sig.minimum is not None and sig.maximum is not None and sig.minimum < sig.maximum:
        lo, hi = max(lo, sig.minimum), min(hi, sig.maximum)
    return lo, hi


def _start(sig):
    raw = sig.raw_initial
    value = 0.0 if raw is None else float(raw) * sig.scale + sig.offset
    return Source("start", value=value)


# ---------------------------------------------------------------------------
# Bus load
# ---------------------------------------------------------------------------

def classic_frame_bits(data_bytes, extended=False):
    """Bits of a classic CAN data frame with worst-case bit stuffing (3-bit
    interframe space included): 11-bit id as codec.frame_bits_worst_case,
    29-bit id 67 + 8 n + floor((54 + 8 n - 1) / 4)."""
    if not extended:
        return codec.frame_bits_worst_case(data_bytes)
    n = int(data_bytes)
    if not 0 <= n <= 8:
        raise ValueError(f"classic CAN carries 0..8 data bytes, not {data_bytes}")
    return 67 + 8 * n + (54 + 8 * n - 1) // 4


def fd_frame_bits(data_bytes, extended=False):
    """(arbitration-phase bits, data-phase bits) of a CAN FD data frame, worst case.

    ISO 11898-1:2015 frame: the data length rounded up to the next DLC length;
    dynamic stuffing at worst (a stuff bit after every 4 bits) from SOF to the
    end of the data field, its stuff bits counted in the phase they fall in; the
    stuff count (4 bits), CRC-17 (up to 16 bytes) or CRC-21 and their fixed
    stuff bits (one before the stuff count, then one after every 4 bits) in the
    data phase; the bit rate switches at BRS and back at the CRC delimiter,
    which, ACK, EOF and a 3-bit interframe space count in the arbitration phase."""
    n = next((x for x in _FD_LENGTHS if x >= int(data_bytes)), None)
    if n is None or data_bytes < 0:
        raise ValueError(f"CAN FD carries 0..64 data bytes, not {data_bytes}")
    arb = 36 if extended else 17        # SOF, id, (SRR, IDE, id ext), RRS, IDE/FDF, res, BRS
    data = 5 + 8 * n                    # ESI, DLC, data
    stuff = (arb + data - 1) // 4
    stuff_arb = (arb - 1) // 4
    crc = 17 if n <= 16 else 21
    fixed = 1 + (4 + crc - 1) // 4
    return arb + stuff_arb + 13, data + (stuff - stuff_arb) + 4 + crc + fixed


def frame_time_s(data_bytes, *, extended=False, fd=False, bitrate, data_bitrate=None):
    """Worst-case time on the bus of one data frame (seconds)."""
    if not fd:
        return classic_frame_bits(data_bytes, extended) / bitrate
    arb, data = fd_frame_bits(data_bytes, extended)
    return arb / bitrate + data / (data_bitrate or bitrate)


@dataclass(frozen=True)
class BusLoad:
    bus: str
    bitrate: int
    data_bitrate: int | None
    load: float               # fraction of the bus's time, sent and received frames
    sent: float
    received: float
    frames_per_s: float

    @property
    def warning(self):
        if self.load > LOAD_WARNING:
            return (f"bus {self.bus}: worst-case bus load {100 * self.load:.1f} % is above "
                    f"{100 * LOAD_WARNING:.0f} %")
        return None


def bus_load(mapping, bus):
    """Worst-case load of ``bus``: every message the plant sends and receives at
    its cycle time, each frame with worst-case bit stuffing (see
    classic_frame_bits and fd_frame_bits); CAN FD frames' data phase at the
    bus's data_bitrate when it has one (bit rate switch), else at bitrate."""
    b = mapping.bus(bus)
    sent = received = frames = 0.0
    for m in mapping.codec_order(bus):
        per_s = 1000.0 / m.cycle_ms
        t = frame_time_s(m.length, extended=m.is_extended, fd=m.is_fd, bitrate=b.bitrate,
                         data_bitrate=b.data_bitrate) * per_s
        frames += per_s
        if m.direction == "send":
            sent += t
        else:
            received += t
    return BusLoad(bus=bus, bitrate=b.bitrate, data_bitrate=b.data_bitrate, load=sent + received,
                   sent=sent, received=received, frames_per_s=frames)


# ---------------------------------------------------------------------------
# Reports: check and show
# ---------------------------------------------------------------------------

def _rate(bits):
    return f"{bits / 1e6:g} Mbit/s" if bits >= 1e6 else f"{bits / 1e3:g} kbit/s"


def _ident(m):
    return f"0x{m.frame_id:08X}" if m.is_extended else f"0x{m.frame_id:03X}"


def _bus_line(b):
    kind = "CAN FD" if b.fd else "classic CAN"
    rate = _rate(b.bitrate) + (f", data phase {_rate(b.data_bitrate)}" if b.data_bitrate else "")
    return (f"bus {b.name}: {os.path.basename(b.dbc)}, {kind} at {rate}; plant nodes "
            f"{', '.join(b.plant_nodes) or 'none'}; TCU nodes {', '.join(b.tcu_nodes) or 'none'}")


def check_report(mapping):
    """``dct-hil mapping check``: a summary per bus with its bus load, and the warnings."""
    lines = [f"mapping {mapping.path}: valid at {mapping.rate_hz:g} Hz "
             f"(every cycle time a whole number of {1000.0 / mapping.rate_hz:g} ms ticks)"]
    warnings = []
    for b in mapping.buses:
        msgs = mapping.codec_order(b.name)
        sent = [m for m in msgs if m.direction == "send"]
        recv = [m for m in msgs if m.direction == "receive"]
        kinds = {}
        start = driven = recorded = unused = 0
        for m in sent:
            for s in m.signals:
                if s.source is not None:
                    kinds[s.source.kind] = kinds.get(s.source.kind, 0) + 1
        for m in recv:
            for s in m.signals:
                if s.protection_field:
                    continue
                if s.target is None:
                    unused += 1
                elif s.target.kind == "input":
                    driven += 1
                else:
                    recorded += 1
        start = kinds.pop("start", 0)
        restbus = sum(1 for m in sent if not m.mapped)
        protected = sum(1 for m in msgs if m.protection.kind != "none")
        load = bus_load(mapping, b.name)
        lines.append(_bus_line(b))
        lines.append(f"  sends {len(sent)} messages ({restbus} restbus: nodes only, no entry), "
                     f"receives {len(recv)}; {protected} protected")
        srcs = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "none"
        lines.append(f"  sent signals: {srcs}; {start} start values")
        lines.append(f"  received signals: {driven} drive plant inputs, {recorded} recorded, {unused} unused")
        ign = [n for bn, n in mapping.ignored if bn == b.name]
        if ign:
            lines.append(f"  ignored (direction = \"ignore\"): {', '.join(ign)}")
        lines.append(f"  worst-case bus load at {_rate(b.bitrate)}: {100 * load.load:.1f} % "
                     f"(sent {100 * load.sent:.1f} %, received {100 * load.received:.1f} %; "
                     f"{load.frames_per_s:.0f} frames/s)")
        if load.warning:
            warnings.append(f"warning: {load.warning}")
        for m in msgs:
            if m.protection.kind != "none" or m.message is None:
                continue
            crc, cnt = _protection_names(m.message)
            names = [n for n in crc[:1] + cnt[:1] if _without_entry(m.signal(n))]
            if names:
                what = " and ".join(x for x, n in (("a checksum", crc[:1]), ("a counter", cnt[:1]))
                                    if n and n[0] in names)
                verb = "looks" if len(names) == 1 else "look"
                warnings.append(f"note: message {m.name} (bus {b.name}): {', '.join(names)} {verb} like "
                                f"{what}, but the message has no protection")
    warnings.extend(f"warning: {w}" for w in mapping.warnings)
    return "\n".join(lines + warnings) + "\n"


def _without_entry(s):
    return s.target is None and (s.source is None or s.source.kind == "start")


def _values(table, default, ranges=()):
    items = [f"{k}: {_fmt(v)}" for k, v in table]
    items += [f"{'' if lo is None else lo}..{'' if hi is None else hi}: {_fmt(v)}" for lo, hi, v in ranges]
    body = ", ".join(items)
    return "{" + body + (", " if body else "") + f"default: {_fmt(default)}" + "}"


def _linear(gain, bias):
    parts = []
    if gain != 1.0:
        parts.append(f"x {gain:.6g}")
    if bias != 0.0:
        parts.append(f"{'+' if bias > 0 else '-'} {abs(bias):.6g}")
    return " ".join(parts)


def _value_name(value, sig):
    """' "D"' when the signal's DBC names the value."""
    if sig is None or not sig.choices or not sig.scale:
        return ""
    raw = (value - sig.offset) / sig.scale
    name = sig.choices.get(int(round(raw))) if abs(raw - round(raw)) < 1e-9 else None
    return "" if name is None else f" \"{name}\""


def _describe_source(s, sig=None):
    if s.kind in ("output", "status"):
        what = s.name if s.kind == "output" else f"status {s.name}"
        if s.absolute:
            what = f"|{what}|"
        if s.table is not None:
            return f"<- {what} via table {_values(s.table, s.default, s.ranges)}"
        unit = ""
        if s.signal_unit is not None:
            ref = f" of {_fmt(s.reference)} {s.unit or ''}".rstrip() if s.reference is not None else ""
            unit = f" [{s.unit or '-'} -> {s.signal_unit}{ref}]"
        lin = _linear(s.gain, s.bias)
        return f"<- {what}{unit}" + (f" {lin}" if lin else "")
    if s.kind == "constant":
        return f"= {_fmt(s.value)}{_value_name(s.value, sig)} (constant)"
    if s.kind == "toggle":
        return "toggle 0, 1 per frame"
    if s.kind == "counter":
        return f"counter 0..{s.counter_max} per frame"
    return f"= {_fmt(s.value)}{_value_name(s.value, sig)} (start value)"


def _describe_target(t):
    what = t.name if t.kind == "input" else f"record {t.name}"
    if t.table is not None:
        text = f"-> {what} via table {_values(t.table, t.default, t.ranges)}"
    else:
        unit = ""
        if t.signal_unit is not None:
            ref = f" of {_fmt(t.reference)} {t.unit or ''}".rstrip() if t.reference is not None else ""
            unit = f" [{t.signal_unit}{ref} -> {t.unit or '-'}]"
        lin = _linear(t.gain, t.bias)
        text = f"-> {what}{unit}" + (f" {lin}" if lin else "")
    if t.minimum is not None or t.maximum is not None:
        lo = _fmt(t.minimum) if t.minimum is not None else "-inf"
        hi = _fmt(t.maximum) if t.maximum is not None else "inf"
        text += f", limited to {lo} .. {hi}"
    return text + f", safe {_fmt(t.safe)}"


def _describe_protection(p):
    if p.kind == "none":
        return "no protection"
    parts = [f"crc {p.crc_signal}" if p.crc_signal else None,
             f"counter {p.counter_signal}" if p.counter_signal else None,
             (f"data id 0x{p.data_id:04X} ({p.data_id_mode})" if p.kind == "p1" else
              f"data id 0x{p.data_id:04X}") if p.data_id is not None else None,
             "data id list" if p.data_id_list else None,
             f"header at byte {p.offset_bits // 8}" if p.kind in ("p4", "p5", "p7") else None]
    return f"protection {p.kind} (" + ", ".join(x for x in parts if x) + ")"


def show(mapping):
    """``dct-hil mapping show``: per bus, per message (codec order) its identifier,
    cycle, protection and each signal's source or target."""
    out = []
    for b in mapping.buses:
        out.append(_bus_line(b))
        for m in mapping.codec_order(b.name):
            timing = f"every {_fmt(m.cycle_ms)} ms"
            if m.direction == "receive":
                timing += f", timed out after {m.timeout_cycles} cycles ({_fmt(m.timeout_cycles * m.cycle_ms)} ms)"
                if m.optional:
                    timing += ", optional"
            fd = ", FD" if m.is_fd else ""
            tag = "" if m.mapped else ", restbus" if m.direction == "send" else ", by its node"
            source = f" from {os.path.basename(b.dbc)}" if m.protection_from_file else ""
            out.append(f"  {m.direction:<7} {_ident(m)} {m.name} ({m.length} B{fd}{tag}) {timing}; "
                       f"{_describe_protection(m.protection)}{source}")
            width = max((len(s.name) for s in m.signals), default=0)
            for s in m.signals:
                unit = (s.signal.unit or "").strip() if s.signal is not None else ""
                label = f"{s.name:<{width}}  {unit:<6}"
                if s.protection_field:
                    text = f"protection {s.protection_field}"
                elif s.source is not None:
                    text = _describe_source(s.source, s.signal)
                elif s.target is not None:
                    text = _describe_target(s.target)
                else:
                    text = "(drives nothing)"
                out.append(f"      {label}  {text}")
        ign = [n for bn, n in mapping.ignored if bn == b.name]
        if ign:
            out.append(f"  ignored: {', '.join(ign)}")
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------
# Template
# ---------------------------------------------------------------------------

_CRC_NAME = re.compile(r"(crc|chk|checksum|check_sum|xor|pruef|prüf)", re.IGNORECASE)
_COUNTER_NAME = re.compile(r"(counter|alive|zaehler|zähler|(^|_)(ctr|cnt|bz|sqc|seq)(_|$))", re.IGNORECASE)


def _describe_signal(sig):
    order = "Intel" if sig.byte_order == "little_endian" else "Motorola"
    kind = "float" if sig.is_float else "signed" if sig.is_signed else "unsigned"
    lo, hi = sig.minimum, sig.maximum
    rng = f"{_fmt(lo)} .. {_fmt(hi)}" if lo is not None and hi is not None else "no range"
    unit = "" if _no_unit(sig.unit) else sig.unit.strip()
    text = f"{sig.length} bit {kind} at bit {sig.start} ({order}), {rng}{' ' + unit if unit else ''}, step {sig.scale:g}"
    if sig.offset:
        text += f", offset {sig.offset:g}"
    if sig.multiplexer_ids:
        text += f", when {sig.multiplexer_signal} is {'/'.join(str(i) for i in sig.multiplexer_ids)}"
    if sig.is_multiplexer:
        text += ", multiplexer"
    if sig.choices:
        text += ", values " + ", ".join(f"{k} {str(v)!r}" for k, v in list(sig.choices.items())[:8])
        if len(sig.choices) > 8:
            text += ", ..."
    if sig.raw_initial is not None:
        text += f", start value {_fmt(float(sig.raw_initial) * sig.scale + sig.offset)}"
    return text


def _toml_key(name):
    return name if re.match(r"^[A-Za-z0-9_-]+$", name) else f'"{name}"'


def _fields_by_unit(names):
    groups = {}
    for n in names:
        u = unit_of_name(n)
        q = _UNIT_INDEX[u][0] if u and _known_unit(u) else None
        groups.setdefault(q, []).append(n)
    return groups


def _candidates(groups, dbc_unit):
    """Fields that measure what the DBC unit measures (None: the unit says nothing)."""
    k = _known_unit(dbc_unit) if not _no_unit(dbc_unit) else None
    if k is None:
        return None
    q = _UNIT_INDEX[k][0]
    if q == "percentage":
        return groups.get("percentage", [])
    return groups.get(q, [])


def _default_guesses():
    """{(direction, signal name): entry text} from the project's own mapping: the
    only names the template fills in (the same name as the project's contract)."""
    try:
        m = load(DEFAULT_MAPPING)
    except Exception:        # the template works without it
        return {}
    guesses = {}
    for msg in m.messages:
        for s in msg.signals:
            if s.source is not None and s.source.kind in ("output", "status"):
                guesses[("send", s.name)] = (s.source.kind, s.source.name, None)
            elif s.target is not None:
                guesses[("receive", s.name)] = (s.target.kind, s.target.name, s.target.safe)
    return guesses


def _guess_entry(guess, sig, direction):
    kind, name, safe = guess
    unit = unit_of_name(name)
    dbc_unit = (sig.unit or "").strip()
    extra = ""
    if unit is not None and not _no_unit(dbc_unit) and _known_unit(dbc_unit) is not None \
            and not _same_unit(unit, dbc_unit):
        try:
            conversion(unit, dbc_unit)
        except ValueError:
            return None                      # a different quantity: not the same thing
        extra = f", unit = \"{dbc_unit}\""
    if direction == "receive":
        extra += f", safe = {_fmt(safe)}"
    return f"{{ {kind} = \"{name}\"{extra} }}"


def template(dbc_path, *, tcu_nodes=(), tcu_messages=(), plant_nodes=(), bitrate=None, out_path=None,
             bus_name=None, outputs=None, inputs=None):
    """The text of a commented mapping skeleton for the DBC at ``dbc_path``.

    The TCU is ``tcu_nodes`` (its messages are received) and/or ``tcu_messages``
    (messages the plant receives, for DBCs without node names). The plant plays
    ``plant_nodes``, by default every node that sends a message a TCU node
    receives. Entries are filled in only where a signal has the name it has in
    the project's own contract (can_dbc/mappings/dct_hil.toml); every other
    signal is listed with its layout and an entry commented out."""
    if outputs is None or inputs is None:
        from plant.model import INPUT_NAMES, OUTPUT_NAMES
        outputs = OUTPUT_NAMES if outputs is None else outputs
        inputs = INPUT_NAMES if inputs is None else inputs
    try:
        db = read_dbc(dbc_path)
        file_prot = file_protections(db, dbc_path)       # an ARXML's E2E protection
    except ValueError as e:
        raise MappingError(f"{dbc_path}: {e}") from None
    nodes = _dbc_nodes(db)
    for opt, given in (("--tcu-node", tcu_nodes), ("--plant-node", plant_nodes)):
        for n in given:
            if n not in nodes:
                raise MappingError(f"{dbc_path}: {opt} {n}: no such node (its nodes: "
                                   f"{', '.join(nodes) or 'none'})")
    names = [m.name for m in db.messages]
    for n in tcu_messages:
        if n not in names:
            raise MappingError(f"{dbc_path}: --tcu-messages {n}: no such message{_suggest(n, names)}")
    if not tcu_nodes and not tcu_messages:
        raise MappingError(f"{dbc_path}: the TCU is missing: give --tcu-node (its DBC node) or "
                           "--tcu-messages (the messages it sends)")
    tcu_nodes, plant_nodes = list(tcu_nodes), list(plant_nodes)
    both = [n for n in plant_nodes if n in tcu_nodes]
    if both:
        raise MappingError(f"{dbc_path}: --plant-node {both[0]}: also given as --tcu-node")

    def tcu_sends(m):
        return m.name in tcu_messages or any(s in tcu_nodes for s in m.senders)

    def tcu_receives(m):
        return any(r in tcu_nodes for s in m.signals for r in s.receivers) and not tcu_sends(m)

    if not plant_nodes:
        for m in db.messages:
            if tcu_receives(m):
                for s in m.senders:
                    if s != PLACEHOLDER_NODE and s not in plant_nodes and s not in tcu_nodes:
                        plant_nodes.append(s)

    def plant_sends(m):
        return any(s in plant_nodes for s in m.senders) and not tcu_sends(m)

    received = [m for m in db.messages if tcu_sends(m)]
    to_tcu = [m for m in db.messages if plant_sends(m) and tcu_receives(m)]
    restbus = [m for m in db.messages if plant_sends(m) and not tcu_receives(m)]
    unplaced = [m for m in db.messages if m not in received and m not in to_tcu and m not in restbus]
    rate = bitrate or _dbc_attr(db, "Baudrate")
    fd = _dbc_is_fd(db)
    guesses = _default_guesses()
    out_groups = _fields_by_unit(outputs)
    in_groups = _fields_by_unit(inputs)

    base = os.path.dirname(os.path.abspath(out_path)) if out_path else os.getcwd()
    rel = os.path.relpath(os.path.abspath(dbc_path), base)
    if rel.split(os.sep)[:3] == [os.pardir] * 3:       # far away: say where
        rel = os.path.abspath(dbc_path)
    stem = os.path.splitext(os.path.basename(dbc_path))[0]
    name = bus_name or re.sub(r"[^A-Za-z0-9_-]", "_", stem) or "can"
    if not name[0].isalpha():
        name = "bus_" + name

    L = []
    w = L.append
    w(f"# dct-hil mapping file for {os.path.basename(dbc_path)}: what the plant sends and receives.")
    w("# Written by `dct-hil mapping template`; fill it in, then `dct-hil mapping check FILE`.")
    w("# The format: docs/reference/mapping-format.md (from can_dbc/mapping.py); how to serve a")
    w("# vehicle matrix: docs/can-matrices.md.")
    w("#")
    w("# Sent signal:     Name = { output = \"<dct_outputs field>\" }   (unit = \"...\", reference, factor,")
    w("#                  offset, table = { \"0\" = 0, default = 15 }), or { status = \"sim_time_s\" },")
    w("#                  { constant = 3 }, { toggle = true }, { counter = 15 }. Without an entry: the")
    w("#                  signal's start value (GenSigStartValue) or 0.")
    w("# Received signal: Name = { input = \"<dct_inputs field>\", min = ..., max = ..., safe = 0.0 }")
    w("#                  or { record = \"name\" }. Without an entry it drives nothing.")
    w("# Entries filled in below are signals with the name they have in the project's own contract")
    w("# (can_dbc/mappings/dct_hil.toml); check them. Everything else is yours to fill in.")
    w("#")
    w("# Plant outputs by quantity:")
    for q, fields_ in sorted(out_groups.items(), key=lambda kv: (kv[0] is None, kv[0] or "")):
        w(f"#   {q or 'no unit'}: {', '.join(fields_)}")
    w(f"# Simulator status: {', '.join(STATUS_FIELDS)}")
    w("# Plant inputs by quantity:")
    for q, fields_ in sorted(in_groups.items(), key=lambda kv: (kv[0] is None, kv[0] or "")):
        w(f"#   {q or 'no unit'}: {', '.join(fields_)}")
    w("")
    w("[[bus]]")
    w(f"name = \"{name}\"")
    w(f"dbc = \"{rel}\"")
    if rate:
        w(f"bitrate = {int(rate)}" + ("" if bitrate else "                # the DBC's Baudrate"))
    else:
        w("# bitrate = 500000            # bit rate missing: the DBC gives no Baudrate")
    if fd:
        w("fd = true                     # the DBC has CAN FD frames")
        w("# data_bitrate = 2000000      # the data phase's bit rate (bit rate switch), for the bus load")
    w(f"plant_nodes = [{', '.join(chr(34) + n + chr(34) for n in plant_nodes)}]")
    w(f"tcu_nodes = [{', '.join(chr(34) + n + chr(34) for n in tcu_nodes)}]")

    def header(m, direction, note):
        cycle = (f"every {m.cycle_time} ms" if m.cycle_time else "cycle time missing: give cycle_ms")
        senders = ", ".join(s for s in m.senders if s != PLACEHOLDER_NODE) or "no node"
        w("")
        w(f"[message.{_toml_key(m.name)}]".ljust(40) + f"# {_ident_of(m)}, {m.length} bytes, sent by "
          f"{senders}, {cycle}{note}")
        node_dir = ("send" if any(s in plant_nodes for s in m.senders) else
                    "receive" if any(s in tcu_nodes for s in m.senders) else None)
        if node_dir != direction:
            w(f"direction = \"{direction}\"")
        if not m.cycle_time:
            w("# cycle_ms =                    # cycle time missing: give cycle_ms")
        crc, cnt = _template_protection_names(m, file_prot)
        given = file_prot.get(m.name)
        if isinstance(given, Protection):
            w(f"# {_describe_protection(given)}: from {os.path.basename(dbc_path)} (give protection to "
              "override it)")
        elif given is not None:
            w(f"# protection: {given}")
        elif crc or cnt:
            parts = ", ".join(x for x in (f"crc = \"{crc[0]}\"" if crc else "",
                                          f"counter = \"{cnt[0]}\"" if cnt else "") if x)
            w(f"# protection = {{ kind = \"?\", {parts} }}")
            w("#   (a checksum or counter by its name; the DBC does not say how it is computed: kind is")
            w("#    none, counter, dct, p1 (data_id), p2 (data_id_list), xor, p5, p4 or p7 (data_id);")
            w("#    see can_dbc/protection.py)")

    def signals(m, direction):
        w("")
        w(f"[message.{_toml_key(m.name)}.signals]")
        groups = out_groups if direction == "send" else in_groups
        crc, cnt = _template_protection_names(m, file_prot)
        for sig in m.signals:
            w(f"# {sig.name}: {_describe_signal(sig)}")
            given = file_prot.get(m.name)
            nibble = given.data_id_nibble_signal if isinstance(given, Protection) else None
            if sig.name in crc[:1] + cnt[:1] or sig.name == nibble:
                role = ("checksum" if sig.name in crc[:1] else "counter" if sig.name in cnt[:1]
                        else "Data ID nibble")
                w(f"#   (the protection's {role}: written or checked by the protection, no entry)")
                continue
            guess = guesses.get((direction, sig.name))
            entry = _guess_entry(guess, sig, direction) if guess else None
            if entry is not None:
                w(f"{_toml_key(sig.name)} = {entry}")
                continue
            cands = _candidates(groups, sig.unit)
            hint = ""
            if cands is not None and _known_unit(sig.unit) == "%":
                hint = (f"   # in %: {', '.join(cands)}; or any {'output' if direction == 'send' else 'input'} "
                        "with unit = \"%\", reference = (its 100 %)")
            elif cands is not None:
                hint = (f"   # {'outputs' if direction == 'send' else 'inputs'} in its quantity: "
                        f"{', '.join(cands[:6])}{', ...' if len(cands) > 6 else ''}" if cands
                        else f"   # no {'output' if direction == 'send' else 'input'} in its quantity")
            if direction == "send":
                w(f"# {_toml_key(sig.name)} = {{ output = \"\" }}{hint}")
            else:
                w(f"# {_toml_key(sig.name)} = {{ input = \"\", safe = 0.0 }}{hint}")

    if to_tcu:
        w("")
        w("# " + "-" * 70)
        w("# The plant sends these; the TCU receives them")
        w("# " + "-" * 70)
        for m in to_tcu:
            header(m, "send", "")
            signals(m, "send")
    if received:
        w("")
        w("# " + "-" * 70)
        w(f"# The TCU sends these; the plant receives them (timed out after timeout_cycles = "
          f"{DEFAULT_TIMEOUT_CYCLES} missing cycles)")
        w("# " + "-" * 70)
        for m in received:
            header(m, "receive", "")
            signals(m, "receive")
    if restbus:
        w("")
        w("# " + "-" * 70)
        w("# Restbus: the plant nodes' other messages, sent with their signals' start values.")
        w("# Give [message.NAME.signals] entries to send values, direction = \"ignore\" to not send one.")
        w("# " + "-" * 70)
        for m in restbus:
            if m.cycle_time:
                senders = ", ".join(s for s in m.senders if s != PLACEHOLDER_NODE)
                w(f"# {_ident_of(m)} {m.name} ({senders}), {m.length} bytes, every {m.cycle_time} ms: "
                  f"{', '.join(s.name for s in m.signals)}")
            else:
                header(m, "send", "; or direction = \"ignore\"")
    if unplaced:
        w("")
        w("# " + "-" * 70)
        w("# Neither sent nor received by the plant (other nodes, or no node in the DBC); to use one,")
        w("# give [message.NAME] direction = \"send\" or \"receive\" (and cycle_ms where it has none).")
        w("# " + "-" * 70)
        for m in unplaced:
            senders = ", ".join(s for s in m.senders if s != PLACEHOLDER_NODE) or "no node"
            cycle = f"every {m.cycle_time} ms" if m.cycle_time else "no cycle time"
            w(f"# {_ident_of(m)} {m.name} ({senders}), {m.length} bytes, {cycle}")
    return "\n".join(L) + "\n"


def _template_protection_names(msg, file_prot):
    """The checksum and counter signals of a message for the template: the
    file's protection's (an ARXML's E2E), else by their names."""
    given = file_prot.get(msg.name)
    if isinstance(given, Protection):
        return ([given.crc_signal] if given.crc_signal else []), \
            ([given.counter_signal] if given.counter_signal else [])
    return _protection_names(msg)


def _protection_names(msg):
    """Signals that look like a checksum and a counter by their names."""
    crc = [s.name for s in msg.signals if _CRC_NAME.search(s.name)]
    cnt = [s.name for s in msg.signals if _COUNTER_NAME.search(s.name) and s.name not in crc]
    return crc, cnt


def _ident_of(msg):
    return f"0x{msg.frame_id:08X}" if msg.is_extended_frame else f"0x{msg.frame_id:03X}"
