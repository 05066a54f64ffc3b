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

``MappedLink(mapping)`` is a drop-in for ``tcu_stub.offline.ContractLink``:
every message goes through cantools' encode and decode at its mapping cycle
time, so the TCU sees the matrix's quantisation and refresh rates. The
end-to-end protection is left to the codec and the loop (offline, nothing
corrupts a frame). A matrix that does not carry what the TCU needs is refused
with one line naming the mapping file and the quantity
(``MissingSignalError``).
"""

from __future__ import annotations

import math

from can_dbc import codec
from can_dbc.mapping import Mapping
from tcu_stub.logic import PERIOD_S

__all__ = ["MappedLink", "MissingSignalError", "TCU_READS", "TCU_WRITES"]


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


class MissingSignalError(ValueError):
    """The matrix lacks a signal the reference TCU needs (one line)."""


def _divisor(cycle_ms):
    return max(1, int(round(cycle_ms / 1000.0 / PERIOD_S)))


class _Reader:
    """One quantity the TCU reads: a sent signal and the way back to the output."""

    def __init__(self, msg, sig, direction_sig=None):
        self.msg, self.sig, self.direction_sig = msg, sig, direction_sig
        src = sig.source
        self.gain, self.bias, self.absolute = src.gain, src.bias, src.absolute
        self.negative_codes = set() if direction_sig is None else _negative_codes(
            direction_sig.source)

    def value(self, decoded):
        raw = float(decoded[self.msg.name][self.sig.name])
        x = (raw - self.bias) / self.gain
        if self.absolute and self.direction_sig is not None:
            code = decoded[self.msg.name].get(self.direction_sig.name)
            if code is not None and float(code) in self.negative_codes:
                x = -x
        return x


class MappedLink:
    """The plant and the reference TCU through a vehicle matrix, in one process.

    ``sensors(outputs, k)`` gives the TCU's view at TCU period ``k``;
    ``apply(plant, commands, k)`` writes the TCU's messages due at ``k``
    into the plant inputs they drive."""

    def __init__(self, mapping: Mapping) -> None:
        self.mapping = mapping
        self.sent = [m for m in mapping.messages if m.direction == "send"]
        self.received = [m for m in mapping.messages if m.direction == "receive"]
        self._readers = self._find_readers()
        self._writers = self._find_writers()
        self._decoded: dict[str, dict] = {}
        self._frames = {m.name: 0 for m in mapping.messages}
        self._plan = self._phases(self.sent)

    # ------------------------------------------------------------ set-up
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

    def _find_readers(self):
        readers = {}
        for name, output in TCU_READS.items():
            found = self._carrier(self.sent, "source", "output", output)
            if found is None:
                if name in REQUIRED_READS:
                    self._fail(f"{output} ({name}), which no signal the plant sends carries")
                continue
            m, s = found
            direction = None
            if s.source.absolute:
                # the signal of the same message that tells negative values apart
                direction = next((d for d in m.signals if d.source is not None
                                  and d.source.kind == "output" and d.source.name == output
                                  and _negative_codes(d.source)), None)
            readers[name] = _Reader(m, s, direction)
        return readers

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

    @staticmethod
    def _phases(messages):
        """{name: (divisor, offset)} in TCU periods; one cycle time's messages
        take consecutive offsets, as the server staggers them."""
        plan, used = {}, {}
        for m in messages:
            div = _divisor(m.cycle_ms)
            off = used.get(div, 0)
            used[div] = off + 1
            plan[m.name] = (div, off % div)
        return plan

    # ------------------------------------------------------------ the link
    def _values(self, m, outputs):
        values = {}
        n = self._frames[m.name]
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
        values = self._values(m, outputs)
        msg = m.message
        data = msg.encode(values, scaling=True, strict=False)
        self._decoded[m.name] = msg.decode(data, decode_choices=False, scaling=True)
        self._frames[m.name] += 1

    def sensors(self, outputs, k):
        first = not self._decoded
        for m in self.sent:
            div, off = self._plan[m.name]
            if first or k % div == off:
                self._send(m, outputs)
        view = {name: r.value(self._decoded) for name, r in self._readers.items()}
        view["stale"] = False
        return view

    def apply(self, plant, commands, k):
        due = {m.name for m in self.received if k % _divisor(m.cycle_ms) == 0}
        by_message: dict[str, dict] = {}
        for name, (m, s) in self._writers.items():
            if m.name in due:
                t = s.target
                by_message.setdefault(m.name, {})[s.name] = (float(commands[name]) - t.bias) / t.gain
        for m in self.received:
            if m.name not in by_message:
                continue
            values = {s.name: by_message[m.name].get(s.name, 0) for s in m.signals}
            decoded = m.message.decode(m.message.encode(values, scaling=True, strict=False),
                                       decode_choices=False, scaling=True)
            for s in m.signals:
                t = s.target
                if t is None or t.kind != "input" or s.name not in by_message[m.name]:
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
