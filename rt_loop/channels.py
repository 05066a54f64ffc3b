"""The CAN buses the loop serves, as the flat tables its tick reads.

A mapping file (``can_dbc.mapping``: a DBC per bus, what the plant sends and
receives, where each sent signal's value comes from and what each received
signal drives) becomes, per bus, one ``rt_channel`` of ``rt_loop.h``:

* the bus's messages as a table-driven codec (``can_dbc.table.CodecTable``:
  layouts and end-to-end protection, bit-exact with cantools);
* per message an ``rt_msg`` (sent or received, cycle time, timeout cycles,
  CAN FD flags, whether it carries the simulator's state);
* per signal an ``rt_source`` (sent: plant output, status, fixed value,
  toggle, counter, with gain/bias or a value table) and an ``rt_target``
  (received: which command value it sets, gain/bias or value table,
  limits, safe value);
* the value tables' ranges.

The received signals' targets share one vector of command values
(``command_names``): one per plant input the mapping drives (the loop
writes it into ``dct_inputs`` every tick) and one per recorded name (kept
for the statistics and the recording only). Nothing here runs in the tick:
``LoopChannels(mapping, ffi, lib)`` builds everything once, ``install(loop)``
writes the pointers into an ``rt_loop`` before ``rt_loop_prepare``, and the
object keeps the arrays alive as long as it lives (keep it as long as the
loop).
"""

from __future__ import annotations

import math
from typing import Any

from can_dbc.mapping import STATUS_FIELDS, Mapping
from can_dbc.table import CodecTable

__all__ = ["ChannelError", "LoopChannels"]


class ChannelError(ValueError):
    """A mapping the loop cannot serve (one line)."""


def _field_names(ffi: Any, cname: str) -> list[str]:
    return [name for name, _ in ffi.typeof(cname).fields]


class LoopChannels:
    """The C tables of every bus of ``mapping`` (see the module's text).

    ``messages``: (bus name, MappedMessage) in the loop's numbering (the
    index into ``rt_stats.msgs``); ``command_names``: the command values'
    names in their order; ``command_inputs``: for each, the plant input it
    drives or None (recorded only)."""

    def __init__(self, mapping: Mapping, ffi: Any, lib: Any) -> None:
        self.mapping = mapping
        self.ffi, self.lib = ffi, lib
        outputs = _field_names(ffi, "dct_outputs")
        inputs = _field_names(ffi, "dct_inputs")
        self._output_index = {n: i for i, n in enumerate(outputs)}
        self._input_index = {n: i for i, n in enumerate(inputs)}
        if len(mapping.buses) > lib.RT_MAX_CHANNELS:
            raise ChannelError(f"{mapping.path}: {len(mapping.buses)} buses; the loop serves at "
                               f"most {lib.RT_MAX_CHANNELS}")
        self.command_names: list[str] = []
        self.command_inputs: list[str | None] = []
        self._commands: dict[tuple[str, str], int] = {}
        self.messages: list[tuple[str, Any]] = []
        self.buses = [b.name for b in mapping.buses]
        self._keep: list[Any] = []
        self._channels = [self._build(b) for b in mapping.buses]
        if len(self.messages) > lib.RT_MAX_MESSAGES:
            raise ChannelError(f"{mapping.path}: {len(self.messages)} messages used; the loop "
                               f"serves at most {lib.RT_MAX_MESSAGES}")
        if len(self.command_names) > lib.RT_MAX_COMMANDS:
            raise ChannelError(f"{mapping.path}: {len(self.command_names)} received values "
                               f"(inputs and records); the loop holds at most "
                               f"{lib.RT_MAX_COMMANDS}")

    # ------------------------------------------------------------------ build
    def _command(self, kind: str, name: str) -> int:
        key = (kind, name)
        if key not in self._commands:
            self._commands[key] = len(self.command_names)
            self.command_names.append(name)
            self.command_inputs.append(name if kind == "input" else None)
        return self._commands[key]

    def _lookup(self, c_lookup: Any, item: Any, ranges: list) -> None:
        """Fills an rt_lookup from a Source/Target with a table (else count 0)."""
        if item.table is None and not item.ranges:
            c_lookup.count = 0
            return
        c_lookup.first = len(ranges)
        for key, value in item.table or ():
            ranges.append((float(key), float(key), float(value)))
        for lo, hi, value in item.ranges:
            ranges.append((-math.inf if lo is None else float(lo),
                           math.inf if hi is None else float(hi), float(value)))
        c_lookup.count = len(ranges) - c_lookup.first
        c_lookup.fallback = 0.0 if item.default is None else float(item.default)

    def _source(self, c: Any, src: Any, ranges: list) -> None:
        lib = self.lib
        c.gain, c.bias, c.value = 1.0, 0.0, 0.0
        c.table.count = 0
        if src is None or src.kind in ("constant", "start"):
            c.kind = lib.RT_SRC_VALUE        # a protection field (ct_protect writes it) or fixed
            c.value = 0.0 if src is None or src.value is None else float(src.value)
            return
        if src.kind == "toggle":
            c.kind = lib.RT_SRC_TOGGLE
            return
        if src.kind == "counter":
            c.kind = lib.RT_SRC_COUNTER
            c.modulus = int(src.counter_max) + 1
            return
        if src.kind == "output":
            c.kind, c.field = lib.RT_SRC_OUTPUT, self._output_index[src.name]
        elif src.kind == "status":
            c.kind, c.field = lib.RT_SRC_STATUS, STATUS_FIELDS.index(src.name)
        else:
            raise ChannelError(f"{self.mapping.path}: source kind {src.kind!r} is not known "
                               "to the loop")
        c.absolute = 1 if src.absolute else 0
        c.gain, c.bias = float(src.gain), float(src.bias)
        self._lookup(c.table, src, ranges)

    def _target(self, c: Any, tgt: Any, ranges: list) -> None:
        c.minimum, c.maximum = -math.inf, math.inf
        c.gain, c.bias, c.safe = 1.0, 0.0, 0.0
        c.table.count = 0
        if tgt is None:
            c.kind = self.lib.RT_TGT_NONE
            return
        c.kind = self.lib.RT_TGT_COMMAND
        c.command = self._command(tgt.kind, tgt.name)
        c.gain, c.bias, c.safe = float(tgt.gain), float(tgt.bias), float(tgt.safe)
        if tgt.minimum is not None:
            c.minimum = float(tgt.minimum)
        if tgt.maximum is not None:
            c.maximum = float(tgt.maximum)
        self._lookup(c.table, tgt, ranges)

    def _build(self, bus: Any) -> dict:
        ffi, lib = self.ffi, self.lib
        msgs = self.mapping.codec_order(bus.name)
        if not msgs:
            raise ChannelError(f"{self.mapping.path}: bus {bus.name!r} sends and receives "
                               "nothing")
        table = CodecTable([(m.message, m.protection) for m in msgs])
        n_sig = sum(len(m.signals) for m in msgs)
        c_msgs = ffi.new("rt_msg[]", len(msgs))
        c_src = ffi.new("rt_source[]", max(n_sig, 1))
        c_tgt = ffi.new("rt_target[]", max(n_sig, 1))
        ranges: list[tuple[float, float, float]] = []
        k = 0
        for i, m in enumerate(msgs):
            names = table.signal_names(i)
            by_name = {s.name: s for s in m.signals}
            cm = c_msgs[i]
            send = m.direction == "send"
            cm.direction = lib.RT_DIR_TX if send else lib.RT_DIR_RX
            cm.cycle_s = float(m.cycle_ms) / 1000.0
            cm.timeout_cycles = 0 if m.timeout_cycles is None else int(m.timeout_cycles)
            cm.flags = ((lib.RT_FRAME_FD if m.is_fd else 0)
                        | (lib.RT_FRAME_BRS if m.is_fd and bus.data_bitrate else 0))
            final = False
            for name in names:
                ms = by_name[name]
                if send:
                    self._source(c_src[k], ms.source, ranges)
                    final |= (ms.source is not None and ms.source.kind == "status"
                              and ms.source.name == "sim_state")
                    self._target(c_tgt[k], None, ranges)
                else:
                    self._source(c_src[k], None, ranges)
                    self._target(c_tgt[k], ms.target, ranges)
                k += 1
            cm.final_frame = 1 if final else 0
            self.messages.append((bus.name, m))
        c_ranges = ffi.new("rt_range[]", max(len(ranges), 1))
        for i, (lo, hi, value) in enumerate(ranges):
            c_ranges[i].lo, c_ranges[i].hi, c_ranges[i].value = lo, hi, value
        self._keep.extend((table, c_msgs, c_src, c_tgt, c_ranges))
        return {"bus": bus, "table": table, "msgs": c_msgs, "sources": c_src,
                "targets": c_tgt, "ranges": c_ranges, "n_ranges": len(ranges)}

    # ---------------------------------------------------------------- install
    def install(self, loop: Any, transports: list | None = None) -> None:
        """Writes every channel's tables (and, given, its transport) into ``loop``
        (an ``rt_loop *``); call before ``rt_loop_prepare``."""
        loop.n_channels = len(self._channels)
        for i, ch in enumerate(self._channels):
            c = loop.chan[i]
            c.table = ch["table"].table[0]
            c.msgs = ch["msgs"]
            c.sources = ch["sources"]
            c.targets = ch["targets"]
            c.ranges = ch["ranges"]
            c.n_ranges = ch["n_ranges"]
            if transports is not None:
                transports[i].configure(c, self.lib)
        loop.n_commands = len(self.command_names)
        for i, name in enumerate(self.command_inputs):
            loop.command_input[i] = -1 if name is None else self._input_index[name]

    def table(self, bus: str | int) -> CodecTable:
        """The codec table of a bus (by name or index)."""
        i = bus if isinstance(bus, int) else self.buses.index(bus)
        return self._channels[i]["table"]

    def message_names(self) -> list[str]:
        """``bus:Message`` of every message in the loop's numbering (a single bus: the name)."""
        if len(self.buses) == 1:
            return [m.name for _, m in self.messages]
        return [f"{b}:{m.name}" for b, m in self.messages]
