"""The reference TCU on any vehicle CAN matrix: its signals found through a mapping file.

The TCU logic (``tcu_stub.logic``) reads and writes quantities under the
names of the project's own contract (``EngineSpeed``, ``ClutchPressure1``,
``SolenoidCurrent1`` ...): each is a plant output or input
(``can_dbc.codec.PLANT_SIGNAL_SOURCES``, ``TCU_SIGNAL_TARGETS``). A mapping
file (``can_dbc.mapping``) says which signal of which message carries each
plant output the plant sends, and which received signal drives each plant
input. The TCU uses the same file the other way round: it reads the signal
that carries the quantity it needs and undoes the mapping's scaling (unit,
factor, offset; a magnitude sent with ``abs = true`` gets its sign back from
the direction signal the mapping derives from the same output), and for each
command writes the signal that drives the input it means, scaled so the
plant ends up with the value the TCU asked for.

``TcuMatrix(mapping)`` is that search and scaling, once, for both users:
this offline link and the CAN node (``tcu_stub.can_tcu.CanTcu`` with a
mapping). It names messages ``bus:Message`` (``message_key``), since one
name may be on two buses.

``MappedLink(mapping)`` is a drop-in for ``tcu_stub.offline.ContractLink``:
every message goes through the table codec the real-time loop uses
(``can_dbc.table.CodecTable``, one per bus) at its mapping cycle time, so the
TCU sees the matrix's quantisation and refresh rates, and a value outside a
signal's range (a negative torque into an unsigned signal) is limited as the
loop limits it and counted (``saturated``). The end-to-end protection is left
to the codec and the loop (offline, nothing corrupts a frame). A matrix that does not carry what the TCU needs is refused
with one line naming the mapping file and the quantity
(``MissingSignalError``).
"""

from __future__ import annotations

import math

from can_dbc import codec
from can_dbc.mapping import STATUS_FIELDS, Mapping
from can_dbc.table import CodecTable
from tcu_stub.logic import PERIOD_S

__all__ = ["MappedLink", "MissingSignalError", "REQUIRED_READS", "TCU_READS", "TCU_RECORDS",
           "TCU_WRITES", "TcuMatrix", "cycle_ticks", "message_key", "start_value",
           "target_signal_value"]


def _tcu_reads():
    reads = {}
    for sources in codec.PLANT_SIGNAL_SOURCES.values():
        for name, src in sources.items():
            if src.startswith("o."):
                reads[name] = src[2:]
    return reads


#: what the reference TCU reads: its name for it -> the plant output that carries it
TCU_READS = _tcu_reads()
#: the quantities the TCU cannot run without (what TcuLogic._read and the fork loops use)
REQUIRED_READS = ("AccelPedal", "BrakePedal", "EngineSpeed", "InputShaft1Speed",
                  "InputShaft2Speed", "OutputShaft1Speed", "VehicleSpeed", "EngineTorque",
                  "ClutchPressure1", "ClutchPressure2", "ForkPosition1", "ForkPosition2",
                  "ForkPosition3", "ForkPosition4")
#: what the TCU commands: its name -> the plant input it means (None: information only)
TCU_WRITES = {sig: input_name for targets in codec.TCU_SIGNAL_TARGETS.values()
              for sig, (_, input_name) in targets.items()}
#: what the TCU commands that drives no plant input: its name -> the field a
#: mapping records it under (``TargetGear`` -> ``target_gear``)
TCU_RECORDS = {sig: field for targets in codec.TCU_SIGNAL_TARGETS.values()
               for sig, (field, input_name) in targets.items() if input_name is None}


class MissingSignalError(ValueError):
    """The matrix lacks a signal the reference TCU needs (one line)."""


def message_key(m):
    """``bus:Message``: how a mapped message is named wherever two buses may
    carry the same message name (decoded values, counts, reports)."""
    return f"{m.bus}:{m.name}"


def _divisor(cycle_ms):
    return max(1, int(round(cycle_ms / 1000.0 / PERIOD_S)))


def cycle_ticks(cycle_ms):
    """A cycle time in TCU periods (PERIOD_S), at least 1."""
    return _divisor(cycle_ms)


class _Reader:
    """One quantity the TCU reads: a sent signal and the way back to the output."""

    def __init__(self, msg, sig, direction_sig=None):
        self.msg, self.sig, self.direction_sig = msg, sig, direction_sig
        self.key = message_key(msg)
        src = sig.source
        self.gain, self.bias, self.absolute = src.gain, src.bias, src.absolute
        self.negative_codes = set() if direction_sig is None else _negative_codes(
            direction_sig.source)

    def value(self, decoded):
        """The quantity from ``decoded`` ({message_key: {signal: value}})."""
        values = decoded[self.key]
        raw = float(values[self.sig.name])
        x = (raw - self.bias) / self.gain
        if self.absolute and self.direction_sig is not None:
            code = values.get(self.direction_sig.name)
            if code is not None and float(code) in self.negative_codes:
                x = -x
        return x


class TcuMatrix:
    """What the reference TCU reads and writes on a mapping's matrix: the one
    search for the signal carrying each quantity, and the scaling both ways.

    The plant sends the mapping's ``direction == "send"`` messages (``sent``),
    which the TCU receives; the TCU sends the ``direction == "receive"`` ones
    (``received``), which the plant receives.

    ``readers``   TCU name (``EngineSpeed`` ...) -> how to read it from the
                  decoded frames (``view``)
    ``writers``   TCU command (``SolenoidCurrent1`` ...) -> (message, signal)
                  whose target is the plant input the command means
    ``records``   TCU command without a plant input (``TargetGear``) ->
                  (message, signal) recorded under the command's contract field
                  (``target_gear``), when the matrix has one
    ``status``    status field (``sim_time_s`` ...) -> reader, when sent
    ``needed``    the sent messages that carry a quantity the TCU reads, in
                  mapping order (the ones whose loss makes the TCU stale)

    A matrix without a quantity the TCU cannot run without, or without a
    received signal for every plant input it commands, raises
    ``MissingSignalError`` (one line naming the mapping file)."""

    def __init__(self, mapping: Mapping) -> None:
        self.mapping = mapping
        self.sent = tuple(m for m in mapping.messages if m.direction == "send")
        self.received = tuple(m for m in mapping.messages if m.direction == "receive")
        self.readers = self._find_readers()
        self.writers = self._find_writers()
        self.records = self._find_records()
        self.status = self._find_status()
        used = {r.key for r in self.readers.values()}
        self.needed = tuple(m for m in self.sent if message_key(m) in used)
        self._written = {}
        for name, (m, s) in list(self.writers.items()) + list(self.records.items()):
            self._written.setdefault(message_key(m), {})[s.name] = name

    # ------------------------------------------------------------ the search
    def _fail(self, what):
        raise MissingSignalError(f"{self.mapping.path}: the reference TCU needs {what}")

    @staticmethod
    def _carrier(messages, role, kind, name):
        """(message, signal) of the first signal whose ``role`` ("source" or
        "target") is of ``kind`` on plant field ``name`` with plain scaling."""
        for m in messages:
            for s in m.signals:
                x = getattr(s, role)
                if (x is not None and x.kind == kind and x.name == name and x.table is None
                        and not x.ranges and x.gain != 0):
                    return m, s
        return None

    def _reader(self, m, s):
        direction = None
        if s.source.absolute:
            # the signal of the same message that tells negative values apart
            direction = next((d for d in m.signals if d.source is not None
                              and d.source.kind == s.source.kind and d.source.name == s.source.name
                              and _negative_codes(d.source)), None)
        return _Reader(m, s, direction)

    def _find_readers(self):
        readers = {}
        for name, output in TCU_READS.items():
            found = self._carrier(self.sent, "source", "output", output)
            if found is None:
                if name in REQUIRED_READS:
                    self._fail(f"{output} ({name}), which no signal the plant sends carries")
                continue
            readers[name] = self._reader(*found)
        return readers

    def _find_status(self):
        status = {}
        for field in STATUS_FIELDS:
            found = self._carrier(self.sent, "source", "status", field)
            if found is not None:
                status[field] = self._reader(*found)
        return status

    def _find_writers(self):
        writers = {}
        for name, input_name in TCU_WRITES.items():
            if input_name is None:
                continue
            found = self._carrier(self.received, "target", "input", input_name)
            if found is None:
                self._fail(f"a received signal that drives {input_name} ({name})")
            writers[name] = found
        return writers

    def _find_records(self):
        records = {}
        for name, field in TCU_RECORDS.items():
            for m in self.received:
                s = next((s for s in m.signals if s.target is not None and s.target.kind == "record"
                          and s.target.name == field), None)
                if s is not None:
                    records[name] = (m, s)
                    break
        return records

    # ------------------------------------------------------------ reading
    def view(self, decoded):
        """The TCU's sensors ({TCU name: value}, without ``stale``) from
        ``decoded`` ({message_key: {signal: value}}); a quantity whose message
        has not been decoded yet is left out."""
        return {name: r.value(decoded) for name, r in self.readers.items() if r.key in decoded}

    def status_value(self, decoded, field):
        """A status field (``sim_time_s`` ...) from ``decoded``, None when no
        message carries it or it has not been decoded yet."""
        r = self.status.get(field)
        if r is None or r.key not in decoded:
            return None
        return r.value(decoded)

    # ------------------------------------------------------------ writing
    def written(self, m):
        """{signal: TCU command} of the signals of a received message the TCU drives."""
        return dict(self._written.get(message_key(m), {}))

    def command_values(self, m, commands):
        """{signal: value} of every signal of the TCU message ``m`` but its
        protection fields: each signal that drives a plant input the value that
        makes the plant's input ``commands[name]`` (the mapping's scaling
        undone), a recorded command (``TargetGear``) through its table, any
        other signal its start value (GenSigStartValue, else 0)."""
        written = self._written.get(message_key(m), {})
        values = {}
        for s in m.signals:
            if s.protection_field is not None:
                continue
            name = written.get(s.name)
            raw = None
            if name is not None and name in commands:
                raw = target_signal_value(s.target, commands[name])
            values[s.name] = start_value(s) if raw is None else raw
        return values

    def safe_values(self, m):
        """``command_values`` with each target's ``safe`` value: what the plant
        takes while the message is timed out, sent as the TCU's last word."""
        values = {}
        for s in m.signals:
            if s.protection_field is not None:
                continue
            raw = None if s.target is None else target_signal_value(s.target, s.target.safe)
            values[s.name] = start_value(s) if raw is None else raw
        return values

    def safe_commands(self):
        """{TCU command: the safe value its carrier takes} (the contract's
        safe values for commands the matrix does not carry)."""
        out = {k: v for vals in codec.TCU_SAFE_VALUES.values() for k, v in vals.items()}
        for name, (_, s) in list(self.writers.items()) + list(self.records.items()):
            out[name] = s.target.safe
        return out


def target_signal_value(t, x):
    """The signal value that makes target ``t`` take ``x`` (the inverse of its
    scaling, or the first table key that gives ``x``); None if none does."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(x):
        return None
    if t.table is not None or t.ranges:
        for k, v in t.table or ():
            if float(v) == x:
                return float(k)
        for lo, hi, v in t.ranges:
            if float(v) == x:
                return float(lo if lo is not None else hi if hi is not None else 0)
        return None
    if t.gain == 0:
        return None
    return (x - t.bias) / t.gain


def start_value(s):
    """A mapped signal's start value: the DBC's GenSigStartValue scaled, else 0."""
    sig = s.signal
    raw = getattr(sig, "raw_initial", None) if sig is not None else None
    if raw is None:
        return 0.0
    return float(raw) * sig.scale + sig.offset


class MappedLink:
    """The plant and the reference TCU through a vehicle matrix, in one process.

    ``sensors(outputs, k)`` gives the TCU's view at TCU period ``k``;
    ``apply(plant, commands, k)`` writes the TCU's messages due at ``k``
    into the plant inputs they drive. The signals are found, and scaled, by
    ``TcuMatrix`` (the same search the CAN node ``tcu_stub.can_tcu`` uses).

    ``saturated``: ``{"bus:Message.Signal": count}`` of the values the codec
    limited to the signal's range or bit field (``CodecTable.saturated``),
    both directions."""

    def __init__(self, mapping: Mapping) -> None:
        self.mapping = mapping
        self.matrix = TcuMatrix(mapping)
        self.sent = list(self.matrix.sent)
        self.received = list(self.matrix.received)
        self._decoded: dict[str, dict] = {}
        self._frames = {message_key(m): 0 for m in mapping.messages}
        self._plan = self._phases(self.sent)
        self._codec = {}                         # message key -> (CodecTable of its bus, index)
        for b in mapping.buses:
            msgs = mapping.codec_order(b.name)
            if msgs:
                table = CodecTable([(m.message, m.protection) for m in msgs])
                for i, m in enumerate(msgs):
                    self._codec[message_key(m)] = (table, i)
        self.saturated: dict[str, int] = {}

    def _through(self, m, values):
        """The values of message ``m`` as the receiver decodes them, packed by
        the table codec (out-of-range values limited and counted)."""
        key = message_key(m)
        table, i = self._codec[key]
        for name in table.saturated(i, values):
            k = f"{key}.{name}"
            self.saturated[k] = self.saturated.get(k, 0) + 1
        return table.decode(i, table.encode(i, values))

    @staticmethod
    def _phases(messages):
        """{key: (divisor, offset)} in TCU periods; one cycle time's messages
        take consecutive offsets, as the server staggers them."""
        plan, used = {}, {}
        for m in messages:
            div = _divisor(m.cycle_ms)
            off = used.get(div, 0)
            used[div] = off + 1
            plan[message_key(m)] = (div, off % div)
        return plan

    # ------------------------------------------------------------ the link
    def _values(self, m, outputs):
        values = {}
        n = self._frames[message_key(m)]
        for s in m.signals:
            src = s.source
            if src is None:                      # a protection field: the codec writes it
                values[s.name] = 0
            elif src.kind == "output":
                values[s.name] = _source_value(src, float(outputs[src.name]))
            elif src.kind == "status":
                values[s.name] = 0.0
            elif src.kind == "toggle":
                values[s.name] = n % 2
            elif src.kind == "counter":
                values[s.name] = n % (int(src.counter_max) + 1)
            else:                                # constant, start value
                values[s.name] = src.value if src.value is not None else 0.0
        return values

    def _send(self, m, outputs):
        key = message_key(m)
        self._decoded[key] = self._through(m, self._values(m, outputs))
        self._frames[key] += 1

    def sensors(self, outputs, k):
        first = not self._decoded
        for m in self.sent:
            div, off = self._plan[message_key(m)]
            if first or k % div == off:
                self._send(m, outputs)
        view = self.matrix.view(self._decoded)
        view["stale"] = False
        return view

    def refresh(self, outputs, due):
        """The plant messages named in ``due`` ((bus, message) pairs, as
        ``can_dbc.table.send_schedule`` gives them) sent now with ``outputs``:
        what the TCU reads of them until they are sent again (``view``)."""
        keys = {f"{bus}:{name}" for bus, name in due}
        for m in self.sent:
            if message_key(m) in keys:
                self._send(m, outputs)

    def view(self):
        """The TCU's view: each plant message as last sent (``refresh``)."""
        view = self.matrix.view(self._decoded)
        view["stale"] = False
        return view

    def apply(self, plant, commands, k):
        for m in self.received:
            if k % _divisor(m.cycle_ms) != 0:
                continue
            written = self.matrix.written(m)
            if not any(m.signal(name).target.kind == "input" for name in written):
                continue
            values = {s.name: 0 for s in m.signals if s.protection_field is not None}
            values.update(self.matrix.command_values(m, commands))
            decoded = self._through(m, values)
            for s in m.signals:
                t = s.target
                if t is None or t.kind != "input" or s.name not in written:
                    continue
                x = t.gain * float(decoded[s.name]) + t.bias
                if t.minimum is not None:
                    x = max(t.minimum, x)
                if t.maximum is not None:
                    x = min(t.maximum, x)
                plant.inputs[t.name] = x


def _negative_codes(src):
    """The values a table source sends for negative inputs only."""
    codes = {v for k, v in (src.table or ()) if k < 0}
    codes |= {v for lo, hi, v in src.ranges if hi is not None and hi < 0}
    positive = {v for k, v in (src.table or ()) if k >= 0}
    positive |= {v for lo, hi, v in src.ranges if hi is None or hi >= 0}
    return {float(c) for c in codes - positive}


def _source_value(src, x):
    if src.absolute:
        x = abs(x)
    if src.table is not None or src.ranges:
        key = int(round(x)) if math.isfinite(x) else None
        for k, v in src.table or ():
            if k == key:
                return v
        for lo, hi, v in src.ranges:
            if key is not None and (lo is None or key >= lo) and (hi is None or key <= hi):
                return v
        return src.default
    return src.gain * x + src.bias
