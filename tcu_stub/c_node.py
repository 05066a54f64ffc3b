"""The reference TCU as a CAN node in C: ``CTcuNode``, the C task of
``tcu_stub/csrc/tcu_node.c`` on a thread of its own (``dct-hil tcu --impl c``,
the default; the demo's and the test bench's TCU).

The C runs what ``tcu_stub.can_tcu.CanTcu`` runs in Python, period for
period: every frame waiting is taken in and checked with the table codec
(``can_dbc/csrc/can_table.c``: length, CRC, AliveCounter), each needed plant
message judged (missing, ``REJECTS_TO_STALE`` rejects in a row, or
``TIMEOUT_CYCLES`` cycle times without an accepted frame), the sensors read
from the last accepted values, the C port of ``logic.py`` steps (stale
handling, diagnostics and the message trouble codes included), the messages
due are encoded, protected and sent; at stop one frame of each TCU message
with its safe values. No Python runs per period: this class builds the C's
tables from the same sources the Python node reads (the contract, or a
mapping's ``TcuMatrix``: which signal feeds which sensor with the scaling
undone, which command goes into which signal, cycle times, which messages
are needed), starts and stops the thread, and reads its figures (a
sequence-counted copy the thread writes each period, never a lock).

The thread runs SCHED_FIFO at ``priority`` when the process may (root,
CAP_SYS_NICE or an rtprio limit), else on the normal scheduler; the report
says which (``sched``).

Frames in and out (``tcu_stub/csrc/tcu_port.c``):

- SocketCAN (``interface="socketcan"``): a CAN_RAW socket per bus, read and
  written by the C thread itself;
- any other python-can interface: the node's own frame rings, served by a
  bridge thread in Python (a Python step per frame, none per period);
- ``ports``: {bus name: (recv, recv_ctx, send, send_ctx)} addresses of
  frame functions and their contexts given by a connector (the plant loop's
  own rings, ``rt_loop.embedded``): no Python between them at all.

``report()``, ``status_line()``, ``write_report()``, ``counts()``,
``sent()``, ``events``, ``pause()`` and ``wait_for()`` are those of
``CanTcu``.
"""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time

from can_dbc import codec
from can_dbc.channels import open_bus
from tcu_stub.can_tcu import (
    CLOCKS,
    DERIVE_INTERFACES,
    PLANT_NEEDED,
    RCVBUF_BYTES,
    REJECTS_TO_STALE,
    TCU_MESSAGES,
    TIMEOUT_CYCLES,
    MappedSetup,
    check_time_scale,
    matrix_message_name,
    raise_rcvbuf,
)
from tcu_stub.diagnostics import (
    DTCS,
    ENGINE_SIGNALS,
    decode_active_faults,
    inhibited_gears,
)
from tcu_stub.logic import OIL_DEFAULT_DEGC, PERIOD_S, PHASES, SELECTOR_D
from tcu_stub.mapped_link import cycle_ticks, message_key, start_value

__all__ = ["CTcuNode", "DEFAULT_PRIORITY", "IMPLS", "NodeError", "frame_layout"]

#: the implementations of the reference TCU's CAN node (``--impl``)
IMPLS = ("c", "python")
#: SCHED_FIFO priority of the node's thread when none is given (the plant
#: loop's default is 80: the TCU runs below it)
DEFAULT_PRIORITY = 70
_CAUSES = {1: "missing", 2: "timeout", 3: "bad_crc", 4: "bad_counter", 5: "bad_length", 6: "rejected"}
_EPISODE_CAUSES = {1: "missing", 2: "timeout"}      # else "rejected"
_BRIDGE_POLL_S = 0.0005
_BRIDGE_BATCH = 64
#: at most this many frames discarded at the start (a bus busier than the drain would never end)
_DRAIN_MAX_FRAMES = 100_000


class NodeError(RuntimeError):
    """The C node cannot be set up (one line)."""


def _lib():
    from tcu_stub.fast import _lib as lib

    return lib()


def frame_layout():
    """(sizeof, offset of id, len, flags, channel, data) of the C node's frame."""
    ffi, lib = _lib()
    out = ffi.new("int64_t[]", lib.TCU_N_FRAME_LAYOUT)
    lib.tcu_frame_layout(out)
    return tuple(int(x) for x in out)


def _one_line(text):
    return " ".join(str(text).split())


def _negative_codes(reader):
    return sorted(float(c) for c in reader.negative_codes)


class _Bus:
    """One bus of the node: its codec table and the messages on it."""

    def __init__(self, name, table, messages):
        self.name, self.table, self.messages = name, table, messages


class CTcuNode:
    """The reference TCU's CAN node in C (see the module's text).

    bus         an open python-can Bus (the contract), or with ``mapping`` one
                per mapping bus ({name: Bus} or a list); None with ``ports``
                or ``sockets``
    sockets     {bus name: a bound CAN_RAW socket} (SocketCAN: the C thread
                reads and writes them); kept open until ``close()``
    ports       {bus name: (recv, recv_ctx, send, send_ctx)} as integers
                (addresses): frame functions of a connector
    time_scale, clock, mapping: as ``CanTcu``
    priority    SCHED_FIFO priority of the thread (0: the normal scheduler)
    calibration a ``tcu_stub.fast.TcuCalibration`` or dict (default: logic.py's)
    """

    def __init__(self, bus=None, time_scale=1.0, start=True, clock="wall", mapping=None,
                 sockets=None, ports=None, priority=DEFAULT_PRIORITY, calibration=None,
                 rcvbuf_bytes=RCVBUF_BYTES, keepalive=None):
        from tcu_stub.fast import CTcu

        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        self.clock = clock
        self.time_scale = check_time_scale(time_scale)
        self.period_wall_s = PERIOD_S / self.time_scale
        self.setup = None if mapping is None else (
            mapping if isinstance(mapping, MappedSetup) else MappedSetup(mapping))
        self.mapping = None if self.setup is None else self.setup.mapping
        self.matrix = None if self.setup is None else self.setup.matrix
        self.interface = None
        self.channel = None
        self.channels = None
        self._owns_bus = False
        self._keepalive = keepalive             # the connector's objects the ports point into
        self.rcvbuf_bytes = None
        self.rcvbuf_by_bus = {}
        self.error = None
        self.started_at = None
        self.stopped_at = None
        self._pauses = 0
        self._tcu = CTcu(calibration)
        ffi, lib = self._ffi, self._lib = _lib()
        self._n = ffi.new("tcu_node *")
        n = self._n
        n.cal = self._tcu.cal
        n.tcu = self._tcu.state
        self._buses = self._layout()
        self._fill_tables()
        n.period_s = PERIOD_S
        n.period_ns = int(round(self.period_wall_s * 1e9))
        n.priority = int(priority or 0)
        n.rejects_to_stale = REJECTS_TO_STALE
        self._bridges = []
        self._sockets = {}
        self._buses_py = None
        self._connect(bus, sockets, ports, rcvbuf_bytes)
        lib.tcu_node_reset(n)
        self._thread_started = False
        if start:
            self.start()

    # ------------------------------------------------------------ tables
    def _layout(self):
        """The buses, their tables and the messages received and sent (names)."""
        if self.setup is None:
            from can_dbc.table import contract_table

            table = contract_table()
            self._rx_names = tuple(m.name for m in codec.messages("PLANT"))
            self._tx_names = TCU_MESSAGES
            self._needed = PLANT_NEEDED
            self._cycle_ms = {m.name: m.cycle_time for m in codec.messages("PLANT") + codec.messages("TCU")}
            self._where = {name: ("can", table.index(name)) for name in self._rx_names + self._tx_names}
            return [_Bus("can", table, None)]
        buses = []
        self._where = {}
        for name in self.setup.bus_names:
            entry = self.setup.tables.get(name)
            if entry is None:
                buses.append(_Bus(name, None, ()))
                continue
            table, msgs = entry
            buses.append(_Bus(name, table, msgs))
            for i, m in enumerate(msgs):
                self._where[message_key(m)] = (name, i)
        self._rx_names = tuple(message_key(m) for m in self.matrix.sent)
        self._tx_names = tuple(message_key(m) for m in self.matrix.received)
        self._needed = tuple(message_key(m) for m in self.matrix.needed)
        self._cycle_ms = {message_key(m): m.cycle_ms for m in self.matrix.sent + self.matrix.received}
        self._rx_messages = {message_key(m): m for m in self.matrix.sent}
        self._tx_messages = {message_key(m): m for m in self.matrix.received}
        return buses

    def _engine_messages(self):
        engine = set(ENGINE_SIGNALS)
        carried = {name: set() for name in self._needed}
        if self.matrix is None:
            for name in self._needed:
                carried[name] = {s.name for s in codec.payload_signals(codec.message(name))}
        else:
            for quantity, reader in self.matrix.readers.items():
                if reader.key in carried:
                    carried[reader.key].add(quantity)
        return {name for name, q in carried.items() if q and q <= engine}

    def _fill_tables(self):
        from tcu_stub.fast import command_names, sensor_names

        lib, n = self._lib, self._n
        sensors = {name: i for i, name in enumerate(sensor_names()) if name}
        commands = {name: i for i, name in enumerate(command_names()) if name}
        bus_index = {b.name: i for i, b in enumerate(self._buses)}
        if len(self._buses) > lib.TCU_NODE_MAX_BUSES:
            raise NodeError(f"{len(self._buses)} buses: the C node takes at most {lib.TCU_NODE_MAX_BUSES}")
        n.n_buses = len(self._buses)
        for i, b in enumerate(self._buses):
            if b.table is not None:
                if len(b.table) > lib.TCU_NODE_MAX_TABLE:
                    raise NodeError(f"bus {b.name}: {len(b.table)} messages, the C node takes at most "
                                    f"{lib.TCU_NODE_MAX_TABLE}")
                n.tables[i] = b.table.table
            for k in range(lib.TCU_NODE_MAX_TABLE):
                n.rx_of[i][k] = -1
            n.ports[i].fd = -1
        if len(self._rx_names) > lib.TCU_NODE_MAX_RX or len(self._tx_names) > lib.TCU_NODE_MAX_TX:
            raise NodeError(f"{len(self._rx_names)} messages received, {len(self._tx_names)} sent: the C node "
                            f"takes at most {lib.TCU_NODE_MAX_RX} and {lib.TCU_NODE_MAX_TX}")
        engine = self._engine_messages()
        self._timeout_s = {}
        rx_index = {}
        for r, name in enumerate(self._rx_names):
            bus, i = self._where[name]
            rx = n.rx[r]
            rx.bus, rx.msg = bus_index[bus], i
            rx.needed = 1 if name in self._needed else 0
            rx.engine = 1 if name in engine else 0
            rx.timeout_s = TIMEOUT_CYCLES * self._cycle_ms[name] / 1000.0 / self.time_scale
            if name in self._needed:
                self._timeout_s[name] = rx.timeout_s
            n.rx_of[bus_index[bus]][i] = r
            rx_index[name] = r
            self._check_signals(bus, i)
        n.n_rx = len(self._rx_names)
        # the sensors: a value before its message is received, as logic._read's defaults
        for i in range(lib.TCU_N_SENSORS):
            n.defaults[i] = 0.0
        n.defaults[sensors["TransOilTemp"]] = OIL_DEFAULT_DEGC
        n.defaults[sensors["SelectorLever"]] = float(SELECTOR_D)
        reads = []
        if self.matrix is None:
            table = self._buses[0].table
            for name in self._needed:
                sig_names = table.signal_names(name)
                for s in codec.payload_signals(codec.message(name)):
                    if s.name in sensors:
                        reads.append((sensors[s.name], rx_index[name], sig_names.index(s.name), -1, 1.0, 0.0, ()))
            sig_names = table.signal_names("SIM_Status")
            reads.append((-1, rx_index["SIM_Status"], sig_names.index("SimTime"), -1, 1.0, 0.0, ()))
        else:
            readers = [(q, r) for q, r in self.matrix.readers.items() if q in sensors]
            if "sim_time_s" in self.matrix.status:
                readers.append((None, self.matrix.status["sim_time_s"]))
            for quantity, rd in readers:
                bus, i = self._where[rd.key]
                sig_names = self._table(bus).signal_names(i)
                direction = -1 if rd.direction_sig is None or not rd.absolute else \
                    sig_names.index(rd.direction_sig.name)
                codes = _negative_codes(rd) if direction >= 0 else ()
                reads.append((-1 if quantity is None else sensors[quantity], rx_index[rd.key],
                              sig_names.index(rd.sig.name), direction, float(rd.gain), float(rd.bias), codes))
        if len(reads) > lib.TCU_NODE_MAX_READS:
            raise NodeError(f"{len(reads)} quantities read: the C node takes at most {lib.TCU_NODE_MAX_READS}")
        n.line_slot_read = 0
        for j, (slot, r, sig, direction, gain, bias, codes) in enumerate(reads):
            rd = n.reads[j]
            rd.slot, rd.rx, rd.sig, rd.dir_sig, rd.gain, rd.bias = slot, r, sig, direction, gain, bias
            codes = list(codes)[:lib.TCU_NODE_MAX_CODES]
            rd.n_codes = len(codes)
            for k, c in enumerate(codes):
                rd.codes[k] = c
            if slot == sensors["LinePressure"]:
                n.line_slot_read = 1
        n.n_reads = len(reads)
        self._fill_tx(bus_index, commands)

    def _table(self, bus):
        return next(b.table for b in self._buses if b.name == bus)

    def _check_signals(self, bus, i):
        count = len(self._table(bus).signal_names(i))
        if count > self._lib.TCU_NODE_MAX_SIGNALS:
            raise NodeError(f"bus {bus}: a message of {count} signals: the C node takes at most "
                            f"{self._lib.TCU_NODE_MAX_SIGNALS}")

    def _fill_tx(self, bus_index, commands):
        from tcu_stub.mapped_link import target_signal_value

        n, lib = self._n, self._lib
        pairs = []
        self._every = {}
        for j, name in enumerate(self._tx_names):
            bus, i = self._where[name]
            self._check_signals(bus, i)
            table = self._table(bus)
            t = n.tx[j]
            t.bus, t.msg = bus_index[bus], i
            t.every = max(1, int(round(self._cycle_ms[name] / 1000.0 / PERIOD_S)))
            self._every[name] = t.every
            sig_names = table.signal_names(i)
            t.n_signals = len(sig_names)
            for k in range(t.n_signals):
                t.kind[k], t.slot[k], t.gain[k], t.bias[k] = lib.TCU_TX_CONST, 0, 1.0, 0.0
                t.start[k] = t.safe[k] = 0.0
                t.pair_first[k] = t.pair_count[k] = 0
            if self.matrix is None:
                msg = codec.message(name)
                payload = {s.name: s for s in codec.payload_signals(msg)}
                safe = codec.TCU_SAFE_VALUES[name]
                for k, sname in enumerate(sig_names):
                    s = payload.get(sname)
                    if s is None:                       # CRC, AliveCounter: the codec's
                        continue
                    t.start[k] = codec.start_value(s)
                    t.safe[k] = float(safe.get(sname, t.start[k]))
                    if sname in commands:
                        t.kind[k], t.slot[k] = lib.TCU_TX_LINEAR, commands[sname]
                continue
            m = self._tx_messages[name]
            by_name = {s.name: s for s in m.signals}
            written = self.matrix.written(m)
            safe = self.matrix.safe_values(m)
            for k, sname in enumerate(sig_names):
                s = by_name.get(sname)
                if s is None or s.protection_field is not None:
                    continue
                t.start[k] = start_value(s)
                t.safe[k] = float(safe.get(sname, t.start[k]))
                command = written.get(sname)
                if command is None or command not in commands:
                    continue
                tg = s.target
                if tg.table is not None or tg.ranges:
                    first = len(pairs)
                    for key, v in tg.table or ():
                        pairs.append((float(v), float(key)))
                    for lo, hi, v in tg.ranges:
                        pairs.append((float(v), float(lo if lo is not None else hi if hi is not None else 0)))
                    t.kind[k], t.slot[k] = lib.TCU_TX_TABLE, commands[command]
                    t.pair_first[k], t.pair_count[k] = first, len(pairs) - first
                elif tg.gain != 0:
                    t.kind[k], t.slot[k] = lib.TCU_TX_LINEAR, commands[command]
                    t.gain[k], t.bias[k] = float(tg.gain), float(tg.bias)
                    assert target_signal_value(tg, 1.0) == (1.0 - t.bias[k]) / t.gain[k]
        if len(pairs) > lib.TCU_NODE_MAX_PAIRS:
            raise NodeError(f"{len(pairs)} table entries of recorded commands: the C node takes at most "
                            f"{lib.TCU_NODE_MAX_PAIRS}")
        for p, (v, key) in enumerate(pairs):
            n.pairs[p][0], n.pairs[p][1] = v, key
        n.n_tx = len(self._tx_names)
        if self.clock == "bus":
            if self.matrix is None:
                clock_name, ticks = "DCT_ShaftSpeeds", 1
            else:
                fastest = min(self.matrix.needed, key=lambda m: m.cycle_ms)
                clock_name, ticks = message_key(fastest), cycle_ticks(fastest.cycle_ms)
            n.clock = lib.TCU_CLOCK_BUS
            n.clock_rx = self._rx_names.index(clock_name)
            n.clock_ticks = ticks
        else:
            n.clock = lib.TCU_CLOCK_WALL

    # ------------------------------------------------------------ ports
    def _bus_names(self):
        return [b.name for b in self._buses]

    def _connect(self, bus, sockets, ports, rcvbuf_bytes):
        ffi, n = self._ffi, self._n
        names = self._bus_names()
        given = [x is not None for x in (bus, sockets, ports)]
        if sum(given) != 1:
            raise ValueError("give the node one of: a python-can bus, sockets or ports")
        if ports is not None:
            self._check_keys(ports, names, "ports")
            for i, name in enumerate(names):
                recv, recv_ctx, send, send_ctx = ports[name]
                p = n.ports[i]
                p.fd = -1
                p.recv = ffi.cast("tcu_frame_fn", recv)
                p.recv_ctx = ffi.cast("void *", recv_ctx)
                p.send = ffi.cast("tcu_frame_fn", send)
                p.send_ctx = ffi.cast("void *", send_ctx)
            return
        if sockets is not None:
            self._check_keys(sockets, names, "sockets")
            for i, name in enumerate(names):
                sock = sockets[name]
                self._sockets[name] = sock
                if rcvbuf_bytes:
                    try:
                        self.rcvbuf_by_bus[name] = raise_rcvbuf(sock, rcvbuf_bytes)
                    except OSError:
                        self.rcvbuf_by_bus[name] = None
                n.ports[i].fd = sock.fileno()
                n.ports[i].fd_frames = 1 if self._bus_fd(name) else 0
            known = [g for g in self.rcvbuf_by_bus.values() if g]
            self.rcvbuf_bytes = min(known) if known else None
            return
        if self.mapping is None:
            buses = {names[0]: bus}
        else:
            from tcu_stub.can_tcu import _bus_dict

            buses = _bus_dict(bus, self.mapping)
        self._buses_py = buses
        lib = self._lib
        for i, name in enumerate(names):
            bridge = _Bridge(self, name, buses[name])
            self._bridges.append(bridge)
            p = n.ports[i]
            p.fd = -1
            p.recv, p.recv_ctx = lib.tcu_ring_pop_fn(), bridge.rx
            p.send, p.send_ctx = lib.tcu_ring_push_fn(), bridge.tx

    @staticmethod
    def _check_keys(given, names, what):
        if sorted(given) != sorted(names):
            raise ValueError(f"{what}: the buses are {', '.join(names)}, given {', '.join(map(str, given))}")

    def _bus_fd(self, name):
        if self.mapping is None:
            return False
        return bool(next(b.fd for b in self.mapping.buses if b.name == name))

    @classmethod
    def open(cls, interface="socketcan", channel="vcan0", bitrate=None, time_scale=1.0, start=True,
             clock="wall", mapping=None, bus_channels=None, priority=DEFAULT_PRIORITY,
             rcvbuf_bytes=RCVBUF_BYTES, **bus_kwargs):
        """A node on new buses (``CanTcu.open``'s arguments): SocketCAN sockets read by
        the C thread itself, any other interface through python-can and a bridge
        thread. A bus that cannot be opened raises ConnectionError (one line)."""
        time_scale = check_time_scale(time_scale)
        setup = None if mapping is None else (mapping if isinstance(mapping, MappedSetup)
                                              else MappedSetup(mapping))
        if setup is None:
            channels = {"can": channel}
            fds = {"can": False}
            extras = {"can": dict(bus_kwargs, **({"bitrate": bitrate} if bitrate else {}))}
        else:
            if bitrate:
                raise ValueError("bitrate: with a mapping each bus runs at the mapping's bit rate")
            channels = setup.mapping.channels(channel, bus_channels, derive=interface in DERIVE_INTERFACES)
            fds = {b.name: bool(b.fd) for b in setup.mapping.buses}
            extras = {}
            for b in setup.mapping.buses:
                extra = dict(bus_kwargs, bitrate=b.bitrate)
                if b.fd:
                    extra["fd"] = True
                    if b.data_bitrate:
                        extra["data_bitrate"] = b.data_bitrate
                extras[b.name] = extra
        opened = {}
        try:
            for name, ch in channels.items():
                where = f"{interface} bus on channel {ch}" + ("" if setup is None else f" (mapping bus {name})")
                try:
                    if interface == "socketcan":
                        opened[name] = _can_socket(ch, fds[name])
                    else:
                        opened[name] = open_bus(interface, ch, **extras[name])
                except Exception as e:  # python-can and the socket layer raise many kinds
                    raise ConnectionError(f"cannot open {where}: {_one_line(e) or type(e).__name__}") from None
            kwargs = {"sockets": opened} if interface == "socketcan" else {
                "bus": opened if setup is not None else opened["can"]}
            node = cls(time_scale=time_scale, start=False, clock=clock, mapping=setup, priority=priority,
                       rcvbuf_bytes=rcvbuf_bytes, **kwargs)
        except BaseException:
            for x in opened.values():
                (x.close if isinstance(x, socket.socket) else x.shutdown)()
            raise
        node._owns_bus = True
        node.interface, node.channel = interface, channel
        node.channels = dict(channels) if setup is not None else None
        if start:
            node.start()
        return node

    # ------------------------------------------------------------ life cycle
    def lock_phase(self, ref_ns, step_ns, offset_ns):
        """Before start: the periods begin on ref_ns + offset_ns + k step_ns
        (CLOCK_MONOTONIC ns), not at the start (the embedded connection puts
        them half a loop tick after a tick)."""
        if self._thread_started:
            raise NodeError("lock_phase: the node has started")
        if not (ref_ns > 0 and step_ns > 0 and 0 <= offset_ns < step_ns):
            raise NodeError(f"lock_phase: ref {ref_ns}, step {step_ns}, offset {offset_ns} ns: "
                            "ref and step > 0, 0 <= offset < step")
        self._n.phase_ref_ns, self._n.phase_step_ns, self._n.phase_offset_ns = ref_ns, step_ns, offset_ns

    def start(self):
        """Starts the bridges (if any) and the C thread (once)."""
        if self._thread_started:
            return
        for b in self._bridges:
            b.start()
        rc = self._lib.tcu_node_start(self._n)
        if rc != 0:
            for b in self._bridges:
                b.stop()
            raise NodeError(f"the TCU node's thread did not start: {os.strerror(rc)}")
        self._thread_started = True
        self.started_at = time.monotonic()

    @property
    def running(self):
        """The thread runs its periods (it ends on stop())."""
        return self._thread_started and self.stopped_at is None

    @property
    def sched_fifo(self):
        return bool(self._n.sched_fifo)

    def stop(self):
        """Ends the thread, which sends one final frame of each TCU message with
        safe values; the bridges forward them, then stop. Safe to call more than once."""
        if self._thread_started and self.stopped_at is None:
            self._lib.tcu_node_stop(self._n)
            self.stopped_at = time.monotonic()
        for b in self._bridges:
            b.stop()

    def close(self):
        """``stop()``, then closes the buses (sockets) if ``open`` made them."""
        self.stop()
        if self._owns_bus:
            self._owns_bus = False
            for s in self._sockets.values():
                s.close()
            for b in (self._buses_py or {}).values():
                b.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def pause(self, seconds):
        """Starves the node for ``seconds`` from its next period (``CanTcu.pause``)."""
        try:
            s = float(seconds)
        except (TypeError, ValueError):
            raise ValueError(f"pause {seconds!r} is not a number of seconds") from None
        if not (math.isfinite(s) and 0.0 < s <= 60.0):
            raise ValueError(f"pause must be above 0 and at most 60 s, got {seconds}")
        self._lib.tcu_node_pause(self._n, s)

    def wait_for(self, predicate, timeout=5.0, poll_s=0.01):
        deadline = time.monotonic() + timeout
        while True:
            ok = predicate(self)
            if ok or time.monotonic() >= deadline:
                return ok
            time.sleep(poll_s)

    # ------------------------------------------------------------ figures
    def figures(self):
        """One consistent copy of the thread's figures (a ``tcu_node_figures``)."""
        out = self._ffi.new("tcu_node_figures *")
        self._lib.tcu_node_figures_read(self._n, out)
        return out

    def stalls(self, since=0):
        """(stalls, count): the wake-ups of the thread later than
        ``TCU_NODE_STALL_PERIODS`` periods numbered ``since`` and after, still in
        the node's ring (the last ``TCU_NODE_MAX_STALLS``), oldest first, each
        ``{"index", "at_s" (node time), "late_ms"}``; ``count`` is every stall so far
        (pass it as ``since`` next time). Stalls overwritten before they were
        read are left out: ``count - since - len(stalls)`` says how many."""
        lib = self._lib
        count = int(self.figures().n_stalls)
        first = max(int(since), count - lib.TCU_NODE_MAX_STALLS)
        out = []
        for i in range(first, count):
            e = self._n.stall_log[i % lib.TCU_NODE_MAX_STALLS]
            at_s, late_s = float(e.at_s), float(e.late_s)
            if int(e.index) == i:       # not overwritten meanwhile by a newer one
                out.append({"index": i, "at_s": round(at_s, 4), "late_ms": round(late_s * 1e3, 3)})
        return out, count

    @property
    def t_s(self):
        return float(self.figures().t_s)

    @property
    def ticks(self):
        return int(self.figures().ticks)

    @property
    def stale(self):
        return bool(self.figures().stale)

    @property
    def phase(self):
        return PHASES[self.figures().phase]

    @property
    def events(self):
        """The shifts the logic started: [(TCU time s, from gear, to gear)]."""
        f = self.figures()
        return [(float(e.t_s), int(e.from_gear), int(e.to_gear))
                for e in (self._n.shift_log[i] for i in range(f.n_shifts))]

    def message_name(self, message):
        if self.matrix is None:
            return codec.message(message).name
        return matrix_message_name(message, tuple(self._rx_names + self._tx_names), self.mapping.path)

    def counts(self, message):
        """{received, accepted, bad_length, bad_crc, bad_counter} of a plant message."""
        r = self.figures().rx[self._rx_names.index(self.message_name(message))]
        return {"received": int(r.received), "accepted": int(r.accepted), "bad_length": int(r.bad_length),
                "bad_crc": int(r.bad_crc), "bad_counter": int(r.bad_counter)}

    def sent(self, message):
        return int(self.figures().sent[self._tx_names.index(self.message_name(message))])

    @property
    def commands(self):
        from tcu_stub.fast import command_names

        f = self.figures()
        return {name: _number(f.commands[i]) for i, name in enumerate(command_names()) if name}

    def status_line(self):
        """One line: TCU time, phase, gear -> target gear, stale or not, speeds, frames rx/tx."""
        from tcu_stub.fast import sensor_names

        f = self.figures()
        names = sensor_names()
        rx = sum(int(f.rx[i].accepted) for i in range(len(self._rx_names)))
        tx = sum(int(f.sent[i]) for i in range(len(self._tx_names)))
        if f.have_sensors:
            v, rpm = f.sensors[names.index("VehicleSpeed")], f.sensors[names.index("EngineSpeed")]
            speeds = f"v {v:5.1f} km/h  engine {rpm:5.0f} rpm"
        else:
            speeds = "v   -   km/h  engine   -   rpm"
        faults = decode_active_faults(f.active_bits)
        return (f"TCU {f.t_s:8.2f} s  {PHASES[f.phase]:<17} gear {f.gear} -> {f.target_gear}  "
                f"{'STALE' if f.stale else 'ok   '}  {speeds}  rx {rx}  tx {tx}  skipped {f.skipped_ticks}"
                + (f"  DTC {','.join(faults)}" if faults else "")
                + ("  LIMP HOME" if f.limp_home else ""))

    def _hist(self, h):
        n = int(h.n)
        if not n:
            return {"n": 0, "mean": None, "p50": None, "p99": None, "p99_9": None, "max": None}

        def pct(q):
            want, seen = q / 100.0 * n, 0
            for i in range(self._lib.TCU_NODE_HIST_BINS):
                seen += int(h.bins[i])
                if seen >= want:
                    return (i + 1) * 10.0
            return round(float(h.max), 1)

        return {"n": n, "mean": round(float(h.total) / n, 1), "p50": pct(50), "p99": pct(99),
                "p99_9": pct(99.9), "max": round(float(h.max), 1)}

    def _stall_report(self, f):
        lib = self._lib
        kept, count = self.stalls(0)
        return {"longest_ms": round(float(f.stall_max_s) * 1e3, 3),
                "over_ms": round(lib.TCU_NODE_STALL_PERIODS * self.period_wall_s * 1e3, 3),
                "count": count, "last": kept}

    def _episodes(self, f):
        out = []
        for i in range(min(int(f.n_episodes), self._lib.TCU_NODE_MAX_EPISODES)):
            e = self._n.episodes[i]
            causes = {name: _EPISODE_CAUSES.get(int(e.causes[r]), "rejected")
                      for r, name in enumerate(self._rx_names) if int(e.causes[r])}
            out.append({"start_s": float(e.start_s), "end_s": None if e.open else float(e.end_s),
                        "causes": causes})
        return out

    def _diagnostics(self, f):
        events = []
        for i in range(int(f.n_events)):
            e = self._n.event_log[i]
            events.append({"t_s": round(float(e.t_s), 4), "dtc": DTCS[int(e.bit)].name,
                           "what": "set" if e.set else "healed"})
        return {"active": decode_active_faults(int(f.active_bits)),
                "stored": decode_active_faults(int(f.stored_bits)),
                "fault_count": int(f.fault_count), "inhibited_gears": inhibited_gears(int(f.inhibited)),
                "limp_home": bool(f.limp_home), "safe_state": bool(f.safe_state), "events": events}

    def report(self):
        """Everything recorded, as JSON-ready data (``CanTcu.report``'s keys, and
        ``impl`` and ``sched``)."""
        from tcu_stub.fast import command_names

        f = self.figures()
        end = self.stopped_at if self.stopped_at is not None else time.monotonic()
        mapped = self.matrix is not None
        received = {}
        for r, name in enumerate(self._rx_names):
            c = f.rx[r]
            acc = int(c.accepted)
            mean = (float(c.last_t) - float(c.first_t)) / (acc - 1) * 1000.0 if acc >= 2 else None
            entry = {} if not mapped else {"bus": self._rx_messages[name].bus,
                                           "message": self._rx_messages[name].name}
            entry.update({"frame_id": self._frame_id(name), "cycle_ms": self._cycle_ms[name],
                          "received": int(c.received), "accepted": acc,
                          "rejected": {"bad_length": int(c.bad_length), "bad_crc": int(c.bad_crc),
                                       "bad_counter": int(c.bad_counter)},
                          "mean_interval_ms": mean,
                          "max_interval_ms": float(c.max_interval_s) * 1000.0 if acc >= 2 else None})
            received[name] = entry
        sent = {}
        for j, name in enumerate(self._tx_names):
            entry = {} if not mapped else {"bus": self._tx_messages[name].bus,
                                           "message": self._tx_messages[name].name}
            entry.update({"frame_id": self._frame_id(name), "cycle_ms": self._cycle_ms[name],
                          "frames": int(f.sent[j]), "errors": int(f.send_errors[j]),
                          "saturated": int(f.saturated[j])})
            sent[name] = entry
        last_error = None
        if f.last_send_error_tx >= 0:
            last_error = f"{self._tx_names[f.last_send_error_tx]}: {os.strerror(int(f.last_send_errno))}"
        for b in self._bridges:
            if b.last_error and b.last_error.startswith("send"):
                last_error = f"bus {b.name}: {b.last_error}"
        error = self.error
        if error is None and (f.shifts_lost or f.events_lost):
            error = (f"the C node's logs overflowed: {int(f.shifts_lost)} shifts, {int(f.events_lost)} "
                     "trouble code events not kept")
        rep = {
            "node": "TCU",
            "impl": "c",
            "sched": {"policy": "SCHED_FIFO" if self._n.sched_fifo else "SCHED_OTHER",
                      "priority": int(self._n.priority) if self._n.sched_fifo else 0},
            "interface": self.interface,
            "channel": self.channel,
            "time_scale": self.time_scale,
            "clock": self.clock,
            "period_s": PERIOD_S,
            "period_wall_s": self.period_wall_s,
            "wall_time_s": (end - self.started_at) if self.started_at is not None else 0.0,
            "tcu_time_s": float(f.t_s),
            "ticks": int(f.ticks),
            "skipped_ticks": int(f.skipped_ticks),
            "tick_exec_us": self._hist(self._n.exec_us),
            "tick_wake_late_us": self._hist(self._n.late_us),
            "stalls": self._stall_report(f),
            "socket_rcvbuf_bytes": self.rcvbuf_bytes,
            "phase": PHASES[f.phase],
            "gear": int(f.gear),
            "target_gear": int(f.target_gear),
            "shifts": [{"t_s": round(t, 6), "from_gear": a, "to_gear": b} for t, a, b in self.events],
            "diagnostics": self._diagnostics(f),
            "stale": {
                "now": bool(f.stale),
                "ticks": int(f.stale_ticks),
                "episode_count": int(f.episode_count),
                "episodes": self._episodes(f),
                "timeout_ms": {name: round(t * 1000.0, 3) for name, t in self._timeout_s.items()},
            },
            "sim_time_s": float(f.sim_time_s) if f.have_sim_time else None,
            "received": received,
            "unknown_frames": sum(int(f.unknown[i]) for i in range(len(self._buses))),
            "error_frames": sum(int(f.error_frames[i]) for i in range(len(self._buses))),
            "sent": sent,
            "send_errors": (sum(s["errors"] for s in sent.values())
                            + sum(b.counters()["tx_errors"] for b in self._bridges)),
            "last_send_error": last_error,
            "saturated": sum(s["saturated"] for s in sent.values()),
            "last_commands": self._last_commands(f, command_names()),
            "final_safe_frames": None if f.final_safe_frames < 0 else bool(f.final_safe_frames),
            "error": error,
            "pauses": {"count": int(f.pauses), "total_s": round(float(f.paused_s), 6)},
            "drained_at_start": int(f.drained_at_start)
            + sum(b.counters()["rx_drained_at_start"] for b in self._bridges),
            "bridge": [b.counters() for b in self._bridges] or None,
        }
        if mapped:
            rep["mapping"] = self.mapping.path
            rep["buses"] = {b.name: {"channel": (self.channels or {}).get(b.name), "bitrate": b.bitrate,
                                     "fd": b.fd, "socket_rcvbuf_bytes": self.rcvbuf_by_bus.get(b.name),
                                     "unknown_frames": int(f.unknown[i])}
                            for i, b in enumerate(self.mapping.buses)}
            rep["stale"]["needed"] = list(self._needed)
        return rep

    def _last_commands(self, f, names):
        """The commands of the last period; after the safe final frames their values (as CanTcu)."""
        if f.final_safe_frames >= 0:
            if self.matrix is None:
                return {k: v for vals in codec.TCU_SAFE_VALUES.values() for k, v in vals.items()}
            return self.matrix.safe_commands()
        return {name: _number(f.commands[i]) for i, name in enumerate(names) if name}

    def _frame_id(self, name):
        bus, i = self._where[name]
        return int(self._table(bus).messages[i].frame_id)

    def write_report(self, path):
        """Writes ``report()`` as JSON to ``path`` (its folder is created); returns the report."""
        rep = self.report()
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, "w", encoding="utf-8") as f:
            json.dump(rep, f, indent=2)
            f.write("\n")
        return rep


def _number(x):
    x = float(x)
    return int(x) if x.is_integer() and abs(x) < 2 ** 53 else x


def _can_socket(channel, fd):
    """A CAN_RAW socket bound to ``channel`` (CAN FD frames on when ``fd``)."""
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    try:
        if fd:
            sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, 1)
        sock.bind((channel,))
    except BaseException:
        sock.close()
        raise
    return sock


class _Bridge:
    """The node's own rings on one python-can bus: a Python thread moves each
    received frame into the rx ring and each frame the node sent from the tx
    ring onto the bus (echoes of its own frames on an echoing bus dropped)."""

    def __init__(self, node, name, bus):
        from can_dbc.own_frames import OwnFrames, is_echoing_bus

        self.node, self.name, self.bus = node, name, bus
        ffi = node._ffi
        self._ffi, self._lib = ffi, node._lib
        self.rx = ffi.new("tcu_ring *")
        self.tx = ffi.new("tcu_ring *")
        self.own = OwnFrames(f"{getattr(bus, 'channel_info', '') or name}") if is_echoing_bus(bus) else None
        self._stop = threading.Event()
        self._thread = None
        self._counts = {"rx_forwarded": 0, "tx_forwarded": 0, "rx_ring_full": 0, "rx_skipped": 0,
                        "tx_errors": 0, "rx_errors": 0, "rx_drained_at_start": 0}
        self.last_error = None

    def start(self):
        self._thread = threading.Thread(target=self._run, name=f"tcu-bridge-{self.name}", daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def counters(self):
        from can_dbc.channels import backlog_dropped

        return {"bus": self.name, **self._counts, "rx_backlog_dropped": backlog_dropped(self.bus),
                "last_error": self.last_error}

    def _run(self):
        ffi = self._ffi
        buf = ffi.new("tcu_frame[]", _BRIDGE_BATCH)
        out = ffi.new("tcu_frame[]", _BRIDGE_BATCH)
        self._drain()
        while True:
            stopping = self._stop.is_set()
            self._forward_tx(out)
            if stopping:
                return
            self._forward_rx(buf)

    def _drain(self):
        """Discards (and counts) the frames the bus queued before the node started,
        as the C thread does with its ports: they are of another time."""
        try:
            while self._counts["rx_drained_at_start"] < _DRAIN_MAX_FRAMES:
                if self.bus.recv(timeout=0.0) is None:
                    return
                self._counts["rx_drained_at_start"] += 1
        except Exception as e:  # a python-can backend may raise anything: counted, the bridge goes on
            self._counts["rx_errors"] += 1
            self.last_error = f"receive: {type(e).__name__}: {_one_line(e)}"

    def _forward_rx(self, buf):
        ffi, lib = self._ffi, self._lib
        n = 0
        timeout = _BRIDGE_POLL_S
        try:
            while n < _BRIDGE_BATCH:
                msg = self.bus.recv(timeout=timeout)
                if msg is None:
                    break
                timeout = 0.0
                if self.own is not None and self.own.is_echo(msg):
                    continue
                f = buf[n]
                if msg.is_error_frame:
                    f.id = lib.TCU_FRAME_ERR
                    f.len = 0
                else:
                    ident = msg.arbitration_id
                    f.id = ((ident & 0x1FFFFFFF) | lib.TCU_FRAME_EFF if msg.is_extended_id else ident & 0x7FF) \
                        | (lib.TCU_FRAME_RTR if msg.is_remote_frame else 0)
                    data = bytes(msg.data)[:64]
                    f.len = len(data)
                    f.flags = lib.TCU_FRAME_FD if msg.is_fd else 0
                    ffi.memmove(f.data, data, len(data))
                n += 1
        except Exception as e:  # a python-can backend may raise anything: counted, the bridge goes on
            self._counts["rx_errors"] += 1
            self.last_error = f"receive: {type(e).__name__}: {_one_line(e)}"
            time.sleep(_BRIDGE_POLL_S)
        if n:
            pushed = lib.tcu_ring_push_many(self.rx, buf, n)
            self._counts["rx_forwarded"] += pushed
            self._counts["rx_ring_full"] += n - pushed

    def _forward_tx(self, out):
        import can

        ffi, lib = self._ffi, self._lib
        fd_brs = False
        if self.node.mapping is not None:
            b = next(b for b in self.node.mapping.buses if b.name == self.name)
            fd_brs = bool(b.fd and b.data_bitrate)
        while True:
            n = lib.tcu_ring_pop_many(self.tx, out, _BRIDGE_BATCH)
            for i in range(n):
                f = out[i]
                ident = int(f.id)
                is_fd = bool(int(f.flags) & lib.TCU_FRAME_FD)
                kw = {"arbitration_id": ident & 0x1FFFFFFF, "is_extended_id": bool(ident & lib.TCU_FRAME_EFF),
                      "data": ffi.unpack(ffi.cast("char *", f.data), int(f.len)), "is_fd": is_fd,
                      "bitrate_switch": is_fd and fd_brs}
                seq = None
                if self.own is not None:
                    kw["channel"], seq = self.own.stamp()
                try:
                    self.bus.send(can.Message(**kw))
                except Exception as e:  # counted; the node's counts stand (the frame left the node)
                    if seq is not None:
                        self.own.unsent(seq)
                    self._counts["tx_errors"] += 1
                    self.last_error = f"send: {type(e).__name__}: {_one_line(e)}"
                else:
                    self._counts["tx_forwarded"] += 1
            if n < _BRIDGE_BATCH:
                return
