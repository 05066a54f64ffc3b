"""What a fault is: its kinds and parameters, the names it may act on or watch,
and the checks that turn a spec (a dict, a ``[[fault]]`` table) into the loop's
``rt_fault_def`` (``parse_fault``, ``load_faults``). The kinds and the schedule
are described in ``rt_loop.faults``."""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from typing import Any

__all__ = ["KINDS", "Fault", "FaultError", "Names", "invalid_value", "load_faults",
           "parse_condition", "parse_fault"]


class FaultError(ValueError):
    """A fault that cannot be injected (one line naming the cause)."""


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    lo: float
    hi: float
    default: float | None = None      # None: required
    integer: bool = False


@dataclass(frozen=True)
class Kind:
    name: str
    code: str                         # the rt_loop.h constant
    needs: str                        # "message", "signal", "bus", "clutch", "sleeve", ""
    params: tuple[Param, ...]
    text: str


_INF = math.inf
KINDS: dict[str, Kind] = {k.name: k for k in (
    Kind("can.omit", "RT_FAULT_CAN_OMIT", "message", (), "the message is not sent"),
    Kind("can.freeze_counter", "RT_FAULT_CAN_FREEZE_COUNTER", "message", (),
         "its alive counter stays at the value it had"),
    Kind("can.bad_crc", "RT_FAULT_CAN_BAD_CRC", "message", (), "its checksum byte inverted"),
    Kind("can.late", "RT_FAULT_CAN_CYCLE", "message",
         (Param("delay_ms", "ms", 0.0, 60_000.0),),
         "sent delay_ms later than its cycle, every cycle (its cycle + delay_ms apart)"),
    Kind("can.too_often", "RT_FAULT_CAN_CYCLE", "message",
         (Param("factor", "-", 1.0, 1000.0),),
         "sent factor times as often as its cycle (at most once per tick)"),
    Kind("can.length", "RT_FAULT_CAN_LENGTH", "message",
         (Param("length", "bytes", 0, 64, integer=True),),
         "sent with length data bytes (zeros added, or bytes cut)"),
    Kind("can.bus_off", "RT_FAULT_CAN_BUS_OFF", "bus", (),
         "no frame of the plant node on the bus (every bus without one named)"),
    Kind("signal.hold", "RT_FAULT_SIG_HOLD", "signal", (), "stuck at its last value"),
    Kind("signal.value", "RT_FAULT_SIG_VALUE", "signal", (Param("value", "signal", -_INF, _INF),),
         "stuck at value (physical, the signal's unit)"),
    Kind("signal.offset", "RT_FAULT_SIG_OFFSET", "signal",
         (Param("offset", "signal", -_INF, _INF),), "offset added (the signal's unit)"),
    Kind("signal.gain", "RT_FAULT_SIG_GAIN", "signal", (Param("gain", "-", -_INF, _INF),),
         "multiplied by gain"),
    Kind("signal.noise", "RT_FAULT_SIG_NOISE", "signal",
         (Param("sigma", "signal", 0.0, _INF), Param("seed", "-", 0, 2 ** 63, 1, True)),
         "Gaussian noise of standard deviation sigma added (seeded: reproducible)"),
    Kind("signal.invalid", "RT_FAULT_SIG_INVALID", "signal", (),
         "its invalid value: the DBC's value named invalid/SNA/error, else the raw value "
         "all ones (unsigned) or the lowest raw value (signed)"),
    Kind("valve.spool_stuck", "RT_FAULT_SPOOL_STUCK", "clutch", (),
         "the clutch valve's spool does not move"),
    Kind("valve.solenoid_open", "RT_FAULT_SOLENOID_OPEN", "clutch", (),
         "open circuit: no current in the clutch valve's solenoid"),
    Kind("clutch.friction_fade", "RT_FAULT_FRICTION_FADE", "clutch",
         (Param("loss", "-", 0.0, 1.0),), "the clutch's friction coefficients x (1 - loss)"),
    Kind("clutch.kiss_drift", "RT_FAULT_KISS_DRIFT", "clutch",
         (Param("gap_mm", "mm", -5.0, 5.0),), "the clutch's pack gap + gap_mm"),
    Kind("hydraulics.line_pressure_loss", "RT_FAULT_LINE_PRESSURE_LOSS", "",
         (Param("loss", "-", 0.0, 1.0, 1.0),), "the line pressure x (1 - loss)"),
    Kind("fork.jammed", "RT_FAULT_FORK_JAMMED", "sleeve", (), "the sleeve's fork does not move"),
    Kind("sync.blocker_failed", "RT_FAULT_BLOCKER_FAILED", "sleeve", (),
         "the sleeve's blocker ring does not block: it engages without synchronizing"),
    Kind("engine.torque_limit", "RT_FAULT_ENGINE_TORQUE_LIMIT", "",
         (Param("max_nm", "Nm", 0.0, 10_000.0),), "the engine's combustion torque <= max_nm"),
)}

#: the kind a watch has (no effect: it latches when its condition holds)
WATCH_KIND = Kind("watch", "RT_FAULT_WATCH", "", (), "no effect: latches when its condition holds")

#: sleeves by number or by the gears they carry
SLEEVES = {"1": 0, "2": 1, "3": 2, "4": 3, "1-3": 0, "2-4": 1, "5-R": 2, "6-N": 3}
_SCHEDULE = ("start_s", "when", "duration_s")
_OPS = {"<": "RT_OP_LT", "<=": "RT_OP_LE", ">": "RT_OP_GT", ">=": "RT_OP_GE",
        "==": "RT_OP_EQ", "!=": "RT_OP_NE", "&": "RT_OP_BITS"}
_TERM = re.compile(r"^\s*([A-Za-z_][\w.:\-]*)\s*(<=|>=|==|!=|<|>|&)\s*(\S+)\s*$")
_INVALID_NAMES = re.compile(r"invalid|^sna$|not.?available|error|fault|n/a", re.I)
STATE_NAMES = {0: "free", 1: "armed", 2: "active", 3: "ended"}
EVENT_NAMES = {1: "start", 2: "end", 3: "cleared"}


def _suggest(name: str, known: Any) -> str:
    import difflib

    close = difflib.get_close_matches(str(name), list(known), n=3)
    return f" (did you mean {', '.join(close)}?)" if close else ""


class Names:
    """What a fault may name in one served loop: the plant outputs, the
    command values, and every message and signal of its mapping with their
    indices in the loop (``rt_loop.channels.LoopChannels``)."""

    def __init__(self, ffi: Any, lib: Any, channels: Any) -> None:
        self.ffi, self.lib = ffi, lib
        self.outputs = {n: i for i, (n, _) in enumerate(ffi.typeof("dct_outputs").fields)}
        self.commands = {n: i for i, n in enumerate(channels.command_names)}
        self.buses = list(channels.buses)
        self.messages: dict[str, int] = {}           # "Msg" and "bus:Msg" -> loop-wide index
        self.message_info: list[Any] = []            # loop-wide index -> MappedMessage
        self.signals: dict[str, tuple[int, int, int, Any]] = {}  # name -> (g, k, value index, sig)
        self.protection: dict[str, str] = {}         # the protection fields: name -> crc/counter
        first_value = 0
        g = 0
        counts: dict[str, int] = {}
        for b in channels.buses:
            for m in channels.mapping.codec_order(b):
                counts[m.name] = counts.get(m.name, 0) + 1
        for bi, b in enumerate(channels.buses):
            table = channels.table(bi)
            for mi, m in enumerate(channels.mapping.codec_order(b)):
                keys = [f"{b}:{m.name}"] + ([m.name] if counts[m.name] == 1 else [])
                for key in keys:
                    self.messages[key] = g
                self.message_info.append(m)
                by_name = {s.name: s for s in m.signals}
                for k, sname in enumerate(table.signal_names(mi)):
                    entry = (g, k, first_value + k, by_name[sname].signal)
                    for key in keys:
                        self.signals[f"{key}.{sname}"] = entry
                        if by_name[sname].protection_field is not None:
                            self.protection[f"{key}.{sname}"] = by_name[sname].protection_field
                first_value += len(table.signal_names(mi))
                g += 1

    def message(self, name: Any, what: str) -> int:
        if not isinstance(name, str) or name not in self.messages:
            raise FaultError(f"{what}: message {name!r} is not in the served mapping"
                             + _suggest(name, self.messages))
        return self.messages[name]

    def signal(self, name: Any, what: str) -> tuple[int, int, int, Any]:
        if not isinstance(name, str) or name not in self.signals:
            raise FaultError(f"{what}: signal {name!r} is not in the served mapping (name it "
                             "Message.Signal)" + _suggest(name, self.signals))
        return self.signals[name]

    def operand(self, name: str, what: str) -> tuple[str, int]:
        """(RT_OPD_* name, index) of a condition's name."""
        if name == "maneuver_time_s":
            return "RT_OPD_MANEUVER_TIME", 0
        if name in self.outputs:
            return "RT_OPD_OUTPUT", self.outputs[name]
        if name.startswith("cmd.") and name[4:] in self.commands:
            return "RT_OPD_COMMAND", self.commands[name[4:]]
        if name in self.signals:
            return "RT_OPD_SIGNAL", self.signals[name][2]
        known = (list(self.outputs) + ["maneuver_time_s"] + [f"cmd.{c}" for c in self.commands]
                 + list(self.signals))
        raise FaultError(f"{what}: {name!r} is no plant output, cmd.<received value> or "
                         "Message.Signal" + _suggest(name, known))


def check_number(value: Any, what: str) -> float:
    if isinstance(value, bool):
        raise FaultError(f"{what} must be a number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise FaultError(f"{what} must be a number, got {value!r}") from None
    if math.isnan(x):
        raise FaultError(f"{what} must be a number, got NaN")
    return x


def _mask(value: str, what: str) -> float:
    """A bit mask: a positive integer below 2**53 (decimal, 0x.. or 0b..)."""
    try:
        x = int(value, 0)
    except ValueError:
        raise FaultError(f"{what} must be an integer mask such as 4096 or 0x1000, got {value!r}") from None
    if not 0 < x < 2 ** 53:
        raise FaultError(f"{what} must be a mask between 1 and 2**53 - 1, got {value!r}")
    return float(x)


def parse_condition(text: Any, names: Names, what: str = "when") -> list[tuple[str, int, str, float]]:
    """The terms (operand kind, index, op, value) and the join of a condition
    text; raises FaultError naming what cannot be read."""
    if not isinstance(text, str) or not text.strip():
        raise FaultError(f"{what}: a condition is a text such as 'gear == 3', got {text!r}")
    words = re.split(r"\s+(and|or)\s+", text.strip())
    terms = words[0::2]
    joins = set(words[1::2])
    if len(joins) > 1:
        raise FaultError(f"{what}: {text!r} mixes 'and' and 'or' (use one of them)")
    limit = int(names.lib.RT_COND_TERMS)
    if len(terms) > limit:
        raise FaultError(f"{what}: {text!r} has {len(terms)} comparisons; at most {limit}")
    out = []
    for t in terms:
        m = _TERM.match(t)
        if not m:
            raise FaultError(f"{what}: cannot read {t.strip()!r} (write NAME OP NUMBER, OP one of "
                             "< <= > >= == != &)")
        name, op, value = m.groups()
        source, index = names.operand(name, what)
        if op == "&":
            x = _mask(value, f"{what}: the mask in {t.strip()!r}")
        else:
            x = check_number(value, f"{what}: the value in {t.strip()!r}")
        out.append((source, index, _OPS[op], x))
    return out, ("or" in joins)


def invalid_raw(sig: Any) -> int | None:
    """The raw value a DBC signal uses for invalid: a value named
    invalid/SNA/error/not available in its value table, else the raw value all
    ones (unsigned) or the lowest raw value (signed); None for a float signal
    without a named one."""
    choices = getattr(sig, "choices", None) or {}
    for raw, label in choices.items():
        if _INVALID_NAMES.search(str(label)):
            return int(raw)
    if getattr(sig, "is_float", False):
        return None
    n = int(sig.length)
    return -(2 ** (n - 1)) if sig.is_signed else 2 ** n - 1


def invalid_value(sig: Any) -> float:
    """The physical value of ``invalid_raw`` (NaN: none)."""
    raw = invalid_raw(sig)
    if raw is None:
        return math.nan
    return raw * float(sig.scale or 1.0) + float(sig.offset or 0.0)


@dataclass
class Fault:
    """One parsed fault: its spec as given and the C definition's fields."""
    spec: dict
    kind: Kind
    fields: dict = field(default_factory=dict)
    terms: list = field(default_factory=list)
    any: bool = False

    def describe(self) -> str:
        s = self.spec
        what = next((str(s[k]) for k in ("signal", "message", "bus", "clutch", "sleeve")
                     if k in s), "")
        return f"{self.kind.name} {what}".strip()


def parse_fault(spec: Any, names: Names) -> Fault:
    """A fault spec (dict) checked against the served loop (``names``)."""
    if not isinstance(spec, dict):
        raise FaultError(f"a fault is a table of kind, target and parameters, got {spec!r}")
    kind_name = spec.get("kind")
    if not isinstance(kind_name, str) or kind_name not in KINDS:   # a table or list: not a name
        raise FaultError(f"fault kind {kind_name!r} is not known; kinds: "
                         + ", ".join(KINDS) + _suggest(kind_name, KINDS))
    kind = KINDS[kind_name]
    what = kind_name
    allowed = {"kind", *_SCHEDULE, *(p.name for p in kind.params)}
    target_key = {"message": "message", "signal": "signal", "bus": "bus", "clutch": "clutch",
                  "sleeve": "sleeve"}.get(kind.needs)
    if target_key:
        allowed.add(target_key)
    if kind_name == "signal.invalid":
        allowed.add("invalid_value")
    extra = sorted(set(spec) - allowed)
    if extra:
        raise FaultError(f"{what}: {extra[0]!r} is not a parameter of it (it takes "
                         + ", ".join(sorted(allowed - {"kind"})) + ")")
    f = Fault(dict(spec), kind)
    lib = names.lib
    d = f.fields
    d.update(kind=int(getattr(lib, kind.code)), channel=-1, message=-1, signal=-1,
             local_signal=-1, target=-1, value=0.0, raw=0, seed=0)
    # what it acts on
    if kind.needs == "message":
        if "message" not in spec:
            raise FaultError(f"{what} needs message = the name of a message the plant sends")
        g = names.message(spec["message"], what)
        m = names.message_info[g]
        if m.direction != "send":
            raise FaultError(f"{what}: the mapping does not send {spec['message']!r} (the plant "
                             "receives it); CAN faults act on the plant's own messages")
        if kind_name == "can.bad_crc" and getattr(m.protection, "crc_signal", None) is None:
            raise FaultError(f"{what}: {spec['message']!r} carries no checksum")
        d["message"] = g
    elif kind.needs == "signal":
        if "signal" not in spec:
            raise FaultError(f"{what} needs signal = Message.Signal")
        g, k, index, sig = names.signal(spec["signal"], what)
        field_ = names.protection.get(spec["signal"])
        if field_ is not None:
            raise FaultError(f"{what}: {spec['signal']!r} is the message's protection {field_} "
                             "(written after and checked before the signals): use "
                             "can.freeze_counter or can.bad_crc on a message the plant sends")
        d.update(message=g, local_signal=k, signal=index)
    elif kind.needs == "bus":
        bus = spec.get("bus")
        if bus is not None and bus not in names.buses:
            raise FaultError(f"{what}: bus {bus!r} is not served (buses: "
                             + ", ".join(names.buses) + ")")
        d["channel"] = -1 if bus is None else names.buses.index(bus)
    elif kind.needs == "clutch":
        c = spec.get("clutch")
        if c not in (1, 2, "1", "2", "K1", "K2"):
            raise FaultError(f"{what} needs clutch = 1 or 2 (K1: gears 1 3 5 R, K2: 2 4 6), "
                             f"got {c!r}")
        d["target"] = int(str(c)[-1]) - 1
    elif kind.needs == "sleeve":
        s = spec.get("sleeve")
        if str(s) not in SLEEVES:
            raise FaultError(f"{what} needs sleeve = 1..4 or 1-3, 2-4, 5-R, 6-N, got {s!r}")
        d["target"] = SLEEVES[str(s)]
    # parameters
    values = {}
    for p in kind.params:
        if p.name not in spec:
            if p.default is None:
                raise FaultError(f"{what} needs {p.name} ({p.unit})")
            values[p.name] = p.default
            continue
        x = check_number(spec[p.name], f"{what}: {p.name}")
        if p.integer and x != int(x):
            raise FaultError(f"{what}: {p.name} must be a whole number, got {spec[p.name]!r}")
        if not p.lo <= x <= p.hi:
            raise FaultError(f"{what}: {p.name} = {spec[p.name]!r} is outside {p.lo:g}..{p.hi:g}"
                             f" {p.unit}")
        values[p.name] = x
    if kind_name == "can.late":
        d["value"] = names.message_info[d["message"]].cycle_ms / 1000.0 + values["delay_ms"] / 1e3
    elif kind_name == "can.too_often":
        d["value"] = names.message_info[d["message"]].cycle_ms / 1000.0 / values["factor"]
    elif kind_name == "can.length":
        m = names.message_info[d["message"]]
        n = int(values["length"])
        fd_lengths = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
        if (m.is_fd and n not in fd_lengths) or (not m.is_fd and n > 8):
            raise FaultError(f"{what}: {n} bytes is no {'CAN FD' if m.is_fd else 'classic CAN'} "
                             "frame length")
        d["value"] = float(n)
    elif kind_name == "signal.noise":
        d["value"] = values["sigma"]
        d["seed"] = int(values["seed"])
    elif kind_name == "signal.invalid":
        sig = names.signal(spec["signal"], what)[3]
        scale, offset = float(sig.scale or 1.0), float(sig.offset or 0.0)
        if "invalid_value" in spec:
            d["value"] = check_number(spec["invalid_value"], f"{what}: invalid_value")
            raw = None if sig.is_float else round((d["value"] - offset) / scale)
        else:
            raw = invalid_raw(sig)
            if raw is None:
                raise FaultError(f"{what}: {spec['signal']!r} is a float signal without a named "
                                 "invalid value; give invalid_value")
            d["value"] = raw * scale + offset
        if raw is None:               # a float signal: its value as it is (no raw field to write)
            d["kind"] = int(lib.RT_FAULT_SIG_VALUE)
        else:
            d["raw"] = int(raw)
    elif kind.params:
        d["value"] = float(values[kind.params[0].name])
    # schedule
    start = spec.get("start_s")
    d["start_s"] = -_INF if start is None else check_number(start, f"{what}: start_s")
    dur = spec.get("duration_s")
    d["duration_s"] = 0.0 if dur is None else check_number(dur, f"{what}: duration_s")
    if d["duration_s"] < 0:
        raise FaultError(f"{what}: duration_s must be above 0 (leave it out: until cleared)")
    if "when" in spec:
        f.terms, f.any = parse_condition(spec["when"], names, f"{what}: when")
    return f


def load_faults(path: str | os.PathLike, names: Names) -> list[Fault]:
    """The ``[[fault]]`` tables of a TOML file, each checked (the first bad
    one raises FaultError naming the file and its place)."""
    import tomllib

    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except OSError as e:
        raise FaultError(f"{path}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise FaultError(f"{path}: not TOML ({e})") from None
    extra = sorted(set(raw) - {"fault"})
    if extra:
        raise FaultError(f"{path}: {extra[0]!r} is not known (a faults file holds [[fault]] tables)")
    specs = raw.get("fault", [])
    if not isinstance(specs, list):
        raise FaultError(f"{path}: fault must be an array of tables ([[fault]])")
    out = []
    for i, spec in enumerate(specs):
        try:
            out.append(parse_fault(spec, names))
        except FaultError as e:
            raise FaultError(f"{path}: fault {i + 1}: {e}") from None
    return out
