"""The reference TCU as a CAN node: ``tcu_stub.logic.TcuLogic`` against
``dct-hil serve`` (or any plant) on a python-can bus.

    dct-hil tcu --channel vcan0                          # SocketCAN (vcan0, can0)
    dct-hil tcu --interface virtual --channel demo       # python-can's in-process bus
    python -m tcu_stub.can_tcu --channel vcan0 --duration 60 --report out/tcu.json

From Python::

    tcu = CanTcu.open("socketcan", "vcan0")     # or CanTcu(bus) on an open python-can bus
    print(tcu.status_line())
    tcu.close()                                 # safe final frames, threads stopped
    tcu.report()                                # JSON-ready dict

The node reads and writes only the DBC signals of the CAN contract
(``can_dbc/dct_hil.dbc``), or of a vehicle matrix through a mapping file
(below); there is no back door into the plant.

Vehicle matrices (mapping files)
--------------------------------
::

    dct-hil tcu --interface virtual --channel demo --mapping vehicle       # pt on demo, io on demo-io
    dct-hil tcu --channel can0 --mapping vehicle --bus io=can1             # SocketCAN: each bus named
    tcu = CanTcu.open("virtual", "demo", mapping=can_dbc.mapping.load(...), bus_channels={"io": "x"})

With a mapping (``can_dbc.mapping``) the node plays the other side of what
the plant server serves from the same file: it receives the mapping's
``direction == "send"`` messages and sends its ``"receive"`` ones, one
python-can bus per mapping bus, on the channels ``Mapping.channels`` gives
(the first bus on ``--channel``, the others on ``--bus NAME=CHANNEL`` or, on
the ``DERIVE_INTERFACES``, on ``<channel>-<bus>``), each at the mapping's
bit rate. Messages are named ``bus:Message`` in counts, stale causes,
reports and the summary.

The TCU's quantities are found through the mapping by
``tcu_stub.mapped_link.TcuMatrix`` (the search the offline
``MappedLink`` uses too): each sensor from the signal that carries the plant
output, with the mapping's scaling undone (a magnitude gets its sign back
from its direction signal); each command into the signal that drives the
plant input it means, scaled so the plant gets the value asked for; a
recorded command (``TargetGear``) through its table; every other signal of
a TCU message at its start value. A matrix without what the TCU needs is
refused with one line (``MissingSignalError``) before any bus is opened.

Every frame goes through the table codec (``can_dbc.table.CodecTable``,
one per bus, the codec of the server's loop): received frames are found by
bus and identifier and checked with the protection the mapping gives them
(``check``: bad_length, bad_crc, bad_counter, counted per message;
identifiers the plant does not send on that bus count as unknown, per bus);
sent frames are packed and protected with a counter that advances per frame.
Each TCU message is sent at its mapping cycle time from the task; the
messages the logic needs (``needed``: those that carry a quantity it reads)
make it stale as on the contract, with TIMEOUT_CYCLES of their mapping cycle
time; the final frames on stop carry every target's ``safe`` value, scaled
back to the signal. The bus clock (``clock="bus"``) follows the fastest
needed message (on ``vehicle.toml``: ``io:IO_ShaftSpeeds``).

Task
----
One task runs ``TcuLogic.step`` every ``PERIOD_S`` (2 ms) of TCU time, as the
2 ms task of a production TCU, on absolute deadlines ``t0 + k * PERIOD_S /
time_scale`` of ``time.monotonic``. ``time_scale`` (0 < s <= 1, default 1)
runs the whole HiL in slow motion on a slow machine: the server then runs its
0.5 ms plant step every 0.5 ms / s of wall time, so every cycle time on the
bus, and this task's period, stretches by 1 / s. Each tick:

1. builds the sensors dict from the last accepted plant frames (the DBC
   signal names, as ``tcu_stub.offline.sensors_from_plant`` gives them) and
   sets ``stale`` when any plant message the logic needs (all plant messages
   but ``SIM_Status``) was never received, had its last ``REJECTS_TO_STALE``
   (3) frames rejected in a row (length, CRC, AliveCounter), or has not been
   accepted for 10 of its DBC cycle times (``GenMsgCycleTime``, scaled by
   1 / time_scale). Until then the last accepted values stand in, as a
   production TCU debounces E2E errors: a single corrupted frame is counted,
   not answered by opening both clutches. ``sensors["stale_messages"]``
   names each stale message and why (missing, timeout, or the kind of the
   last rejected frame: bad_crc, bad_counter, bad_length) for the logic's
   diagnostics (``tcu_stub.diagnostics``): a trouble code per cause, and the
   engine message (``VEH_Driver``; on a matrix the needed messages that carry
   only the pedals and the engine torque) ridden out without torque requests
   instead of opening the clutches;
2. calls ``logic.step(t_s, sensors)`` with ``t_s = k * PERIOD_S``: TCU time
   from the tick index, never a wall-clock difference;
3. sends right away the messages due this tick, each with its own
   AliveCounter and CRC (``can_dbc.codec.encode``): ``TCU_ClutchCmd`` every
   tick (2 ms), ``TCU_ShiftCmd``, ``TCU_EngineCmd`` and ``TCU_Status`` (the
   diagnosis: trouble codes, limp home, phase) every 5th tick (10 ms), as the
   DBC's ``GenMsgCycleTime`` says; on a matrix its messages, each carrying the
   diagnosis's signals it has a recorded target for (``TcuMatrix.records``).
   The frames leave from the task right after the computation, as on a real
   TCU, not from a free-running sender.

Late ticks: a tick that starts more than one period after its deadline skips
the missed deadlines (counted in ``skipped_ticks``) and runs at the next one;
there is never a burst of catch-up ticks. The tick index, and so ``t_s``,
advances by the number of periods that really elapsed (executed plus
skipped), so TCU time stays equal to the bus clock: the plant (and its
SIM_Status SimTime) keeps running while this task is late, and the logic's
timers (torque phase length, shift timeout, fill pulse) must measure the time
the plant experienced. The logic's per-step integrators use their fixed
PERIOD_S, so a skipped tick costs those one step of integration, nothing more.
A 10 ms message whose tick was skipped is sent at the next executed tick.

Timing is soft real time: a Python thread on the normal scheduler (with the
GIL), so single ticks may start late and some may be skipped; the report
gives the wake-up lateness and the tick cost. A real TCU is the hard
real-time peer; this node is the reference for behaviour, not for jitter.

Reception
---------
A ``can_dbc.peer.CanPeer`` (side "tcu", its send thread off) receives in a
thread of its own and checks every plant frame with ``codec.E2eReceiver``;
rejected frames are counted per message and reason (bad_length, bad_crc,
bad_counter), frames with ids that are not plant messages as unknown. On
SocketCAN the bus socket's receive buffer is raised (``SO_RCVBUFFORCE`` when
the process may, else ``SO_RCVBUF``, capped by ``net.core.rmem_max``; asked:
``RCVBUF_BYTES``, granted: ``rcvbuf_bytes`` in the report) so a late Python
thread does not lose frames. Frames the kernel drops because that buffer was
full never reach python-can and are NOT counted here; they show up only as
AliveCounter jumps (a jump of 2 is accepted, more is rejected) and, when
long, as timeouts.

Safe state
----------
While stale, the logic opens both clutches (0 A), applies no fork force and
requests no torque (unless only the engine message is stale: then it drives
on without torque requests), and the node records a stale episode (TCU start
and end time and, per message, why: missing, rejected or timeout). ``stop()`` ends the
task, then sends one final frame of each TCU message with the contract's safe
values (``codec.TCU_SAFE_VALUES``: 0 A, no fork force, no torque request), so
the last commands on the bus are safe; the plant's own timeout does the same
if even those are lost.

Records: ``events`` (the shifts the logic started, TCU time), stale episodes,
counters (ticks, skipped ticks, frames sent and send errors per message,
frames received, accepted and rejected per message and reason, unknown ids),
the SimTime of the last SIM_Status, the diagnosis (``diagnostics``: trouble
codes active and set since the start, their events, inhibited gears, limp
home); ``report()`` returns them as JSON-ready
data, ``write_report(path)`` writes them; ``status_line()`` is the one-line
live status ``dct-hil tcu`` prints once a second.
"""

import argparse
import collections
import json
import math
import os
import socket
import sys
import threading
import time

from can_dbc import codec
from can_dbc.channels import ChannelError, default_channel, open_bus
from can_dbc.node import ReceivingNode, RxStats
from can_dbc.options import add_matrix_options
from can_dbc.own_frames import OwnFrames, is_echoing_bus
from can_dbc.peer import CanPeer
from plant import argtypes
from plant.stop_signals import StopSignals
from tcu_stub.diagnostics import ENGINE_SIGNALS, decode_active_faults
from tcu_stub.logic import PERIOD_S, TcuLogic
from tcu_stub.mapped_link import MissingSignalError, TcuMatrix, cycle_ticks, message_key

__all__ = ["CanTcu", "DERIVE_INTERFACES", "MappedPeer", "MappedSetup", "MissingSignalError",
           "RCVBUF_BYTES", "TIMEOUT_CYCLES", "add_arguments", "load_mapping", "main", "parse_bus_channels",
           "run"]

#: a plant message not accepted for this many of its cycle times is timed out
TIMEOUT_CYCLES = 10
#: receive buffer asked for on a SocketCAN socket (about 1400 queued frames,
#: 0.75 s of the plant's traffic at time scale 1)
RCVBUF_BYTES = 1 << 20
#: bytes a queued CAN frame costs in a socket receive buffer (a whole skb)
SKB_BYTES_PER_FRAME = 760
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_HIST_BIN_US = 10.0
_HIST_BINS = 5000                      # 10 us bins up to 50 ms; later goes in the last one
_MAX_EPISODES = 1000                   # stale episodes kept in the report (all are counted)
STALL_PERIODS = 5                      # a wake-up later than this many periods is a stall
MAX_STALLS = 256                       # the last stalls kept in the report (all are counted)
#: frames of one plant message rejected in a row that make the TCU stale
REJECTS_TO_STALE = 3
_EPISODE_CAUSES = ("missing", "timeout")      # else "rejected" (the kind goes to the logic)

PLANT_NEEDED = tuple(m.name for m in codec.messages("PLANT")
                     if any(src.startswith("o.") for src in codec.PLANT_SIGNAL_SOURCES.get(m.name, {}).values()))
TCU_MESSAGES = tuple(codec.TCU_SIGNAL_TARGETS)
#: python-can interfaces on which the buses of a mapping get derived channel
#: names (``<channel>-<bus>``) unless ``--bus`` names them (in-process and
#: host-local buses); on any other interface each bus after the first needs
#: ``--bus NAME=CHANNEL``
DERIVE_INTERFACES = ("virtual", "udp_multicast")


def matrix_message_name(message, known, mapping_path):
    """``message`` as a node on a matrix counts it: ``bus:Message`` from
    ``known`` (those names), a bare name when one bus has it; ValueError for
    one on several buses or on none."""
    if message in known:
        return message
    hits = [k for k in known if k.split(":", 1)[1] == message]
    if len(hits) == 1:
        return hits[0]
    if hits:
        raise ValueError(f"{message} is on more than one bus: name it as {' or '.join(hits)}")
    raise ValueError(f"{message} is not a message of {mapping_path} the TCU receives or sends")


def _one_line(text):
    return " ".join(str(text).split())


def check_time_scale(time_scale):
    """``time_scale`` as a float in (0, 1]; ValueError otherwise."""
    try:
        x = float(time_scale)
    except (TypeError, ValueError):
        raise ValueError(f"time scale {time_scale!r} is not a number") from None
    if not (math.isfinite(x) and 0.0 < x <= 1.0):
        raise ValueError(f"time scale must be above 0 and at most 1 (1 = real time), got {time_scale}")
    return x


def raise_rcvbuf(sock, want_bytes=RCVBUF_BYTES):
    """Asks for a ``want_bytes`` receive buffer on ``sock`` (SO_RCVBUFFORCE, needs
    CAP_NET_ADMIN; else SO_RCVBUF, capped at net.core.rmem_max); returns the
    size the kernel granted (getsockopt, which on Linux counts its bookkeeping:
    about twice what was set)."""
    for option in (_SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, int(want_bytes))
            break
        except OSError:
            continue
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


CLOCKS = ("wall", "bus")


def _raise_bus_rcvbuf(bus, rcvbuf_bytes):
    """The receive buffer granted on a bus's SocketCAN socket (None: not a socket, or refused)."""
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket) and rcvbuf_bytes:
        try:
            return raise_rcvbuf(sock, rcvbuf_bytes)
        except OSError:
            return None
    return None


def _bus_dict(bus, mapping):
    """{mapping bus name: python-can bus} from a dict, a list in the mapping's
    bus order, or one bus for a mapping of one bus; ValueError (one line) else."""
    names = [b.name for b in mapping.buses]
    if isinstance(bus, dict):
        buses = dict(bus)
    elif isinstance(bus, (list, tuple)):
        if len(bus) != len(names):
            raise ValueError(f"{mapping.path}: {len(names)} buses ({', '.join(names)}), "
                             f"{len(bus)} python-can buses given")
        buses = dict(zip(names, bus))
    elif len(names) == 1:
        buses = {names[0]: bus}
    else:
        raise ValueError(f"{mapping.path}: the mapping has {len(names)} buses ({', '.join(names)}): "
                         "give one python-can bus per mapping bus ({name: bus})")
    missing = [n for n in names if n not in buses]
    extra = [n for n in buses if n not in names]
    if missing or extra:
        raise ValueError(f"{mapping.path}: buses given {', '.join(map(str, buses)) or 'none'}; "
                         f"the mapping's buses are {', '.join(names)}")
    return {n: buses[n] for n in names}


class _Histogram:
    """Microsecond values in 10 us bins: count, mean, max, percentiles."""

    def __init__(self):
        self.bins = [0] * _HIST_BINS
        self.n = 0
        self.total = 0.0
        self.max = 0.0

    def add(self, us):
        self.n += 1
        self.total += us
        if us > self.max:
            self.max = us
        i = int(us / _HIST_BIN_US)
        self.bins[min(max(i, 0), _HIST_BINS - 1)] += 1

    def percentile(self, q):
        if not self.n:
            return None
        want = q / 100.0 * self.n
        seen = 0
        for i, c in enumerate(self.bins):
            seen += c
            if seen >= want:
                return (i + 1) * _HIST_BIN_US       # upper edge of the bin
        return self.max

    def summary(self):
        if not self.n:
            return {"n": 0, "mean": None, "p50": None, "p99": None, "p99_9": None, "max": None}
        return {"n": self.n, "mean": round(self.total / self.n, 1), "p50": self.percentile(50),
                "p99": self.percentile(99), "p99_9": self.percentile(99.9), "max": round(self.max, 1)}


class MappedSetup:
    """Everything a mapped TCU node needs before a bus is opened: the mapping,
    the TCU's signals in it (``TcuMatrix``: ``MissingSignalError`` when one is
    missing) and one ``can_dbc.table.CodecTable`` per bus (``TableError`` for
    a layout the codec cannot take)."""

    def __init__(self, mapping):
        from can_dbc.table import CodecTable

        self.matrix = mapping if isinstance(mapping, TcuMatrix) else TcuMatrix(mapping)
        self.mapping = self.matrix.mapping
        self.bus_names = tuple(b.name for b in self.mapping.buses)
        self.tables = {}
        for b in self.mapping.buses:
            msgs = tuple(self.mapping.codec_order(b.name))
            if msgs:
                self.tables[b.name] = (CodecTable([(m.message, m.protection) for m in msgs]), msgs)


class MappedPeer(ReceivingNode):
    """The reference TCU's side of a mapping file on one python-can bus per
    mapping bus: receives the messages the plant sends (``direction ==
    "send"``), checks each frame with the table codec (``CodecTable.check``,
    the protection the mapping gives it: CRC, counter) and keeps the last
    decoded values and per-message counts; sends the messages the plant
    receives (``send_now``), protected, with a counter advancing per frame.

    Messages are named ``bus:Message`` (``tcu_stub.mapped_link.message_key``).
    One receive thread per bus; the counts, the last values and the send
    counters are under one lock (``_lock``), as in ``can_dbc.peer.CanPeer``,
    whose interface ``CanTcu`` uses (``rx_snapshot``, ``send_now``,
    ``counts``, ``sent``, ``wait_for``, ``report``)."""

    def __init__(self, buses, setup, start=True):
        self.setup = setup
        self.matrix = setup.matrix
        self.buses = dict(buses)
        self._owns_buses = False
        self._where = {}                           # key -> (bus name, table index)
        for bus_name, (_, msgs) in setup.tables.items():
            for i, m in enumerate(msgs):
                self._where[message_key(m)] = (bus_name, i)
        self.rx_messages = {message_key(m): m for m in self.matrix.sent}
        self.tx_messages = {message_key(m): m for m in self.matrix.received}
        self._fd_brs = {b.name: bool(b.fd and b.data_bitrate) for b in setup.mapping.buses}
        self._rx_stats = {k: RxStats(setup.tables[m.bus][0].new_state()) for k, m in self.rx_messages.items()}
        self._counter = {k: 0 for k in self.tx_messages}
        self.sent = {k: 0 for k in self.tx_messages}
        self.send_errors = {k: 0 for k in self.tx_messages}
        #: values the table codec limited to their signal's range or bit field, frames sent
        self.saturated = {k: 0 for k in self.tx_messages}
        self.unknown = {name: 0 for name in self.buses}
        self.error_frames_by_bus = {name: 0 for name in self.buses}
        self.last_send_error = None
        self._own = {name: (OwnFrames(f"{getattr(bus, 'channel_info', '') or name}")
                            if is_echoing_bus(bus) else None) for name, bus in self.buses.items()}
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._threads = []
        self.started_at = None
        self.stopped_at = None
        if start:
            self.start()

    @property
    def names(self):
        """The keys of the messages received."""
        return tuple(self._rx_stats)

    # -- control ------------------------------------------------------------
    def start(self):
        if self._threads:
            return
        self._drain(*self.buses.values())
        self._start_threads((self._recv_loop, (name,), f"tcu-recv-{name}") for name in self.buses)

    def close(self):
        """Stops the receive threads; shuts the buses down if the peer owns them."""
        self._stop_threads()
        if self._owns_buses:
            self._owns_buses = False
            for bus in self.buses.values():
                bus.shutdown()

    # -- sending ------------------------------------------------------------
    def send_now(self, key, values):
        """Sends one frame of the TCU message ``key`` now with ``values``
        ({signal: physical value}, protection fields left out): packed and
        protected by the table codec with the message's next counter. True
        when the bus took it; a refused send is counted in ``send_errors``
        and the counter does not move."""
        import can

        m = self.tx_messages.get(key)
        if m is None:
            raise ValueError(f"{key} is not a message the TCU sends")
        bus_name, i = self._where[key]
        table = self.setup.tables[bus_name][0]
        bus = self.buses[bus_name]
        own = self._own[bus_name]
        with self._send_lock:
            with self._lock:
                counter = self._counter[key]
            data = table.encode(i, values, counter=counter)
            limited = len(table.saturated(i, values))
            kw = {"arbitration_id": m.frame_id, "data": data, "is_extended_id": m.is_extended,
                  "is_fd": m.is_fd, "bitrate_switch": m.is_fd and self._fd_brs[bus_name]}
            n = None
            if own is not None:
                with self._lock:
                    kw["channel"], n = own.stamp()
            try:
                bus.send(can.Message(**kw))
            except Exception as e:  # a full tx queue or a bus error: counted, the next cycle tries again
                with self._lock:
                    if own is not None and n is not None:
                        own.unsent(n)
                    self.send_errors[key] += 1
                    self.last_send_error = f"{key}: {_one_line(e) or type(e).__name__}"
                return False
            with self._lock:
                self._counter[key] = (counter + 1) & 0xFFFFFFFF
                self.sent[key] += 1
                self.saturated[key] += limited
        return True

    # -- what was received --------------------------------------------------
    @property
    def unknown_frames(self):
        with self._lock:
            return sum(self.unknown.values())

    @property
    def error_frames(self):
        with self._lock:
            return sum(self.error_frames_by_bus.values())

    @property
    def own_echoes(self):
        return sum(o.echoes for o in self._own.values() if o is not None)

    def report(self):
        """Everything counted so far, as JSON-ready data."""
        with self._lock:
            received = {}
            for k, st in self._rx_stats.items():
                m = self.rx_messages[k]
                received[k] = {"bus": m.bus, "message": m.name, "frame_id": m.frame_id,
                               "cycle_ms": m.cycle_ms, **st.figures()}
            sent = {k: {"bus": m.bus, "message": m.name, "frame_id": m.frame_id, "cycle_ms": m.cycle_ms,
                        "frames": self.sent[k], "errors": self.send_errors[k],
                        "saturated": self.saturated[k]}
                    for k, m in self.tx_messages.items()}
            return {
                "received": received,
                "unknown_frames": sum(self.unknown.values()),
                "unknown_frames_by_bus": dict(self.unknown),
                "own_echoes_dropped": self.own_echoes,
                "error_frames": sum(self.error_frames_by_bus.values()),
                "sent": sent,
                "drained_at_start": self.drained_at_start,
                "last_send_error": self.last_send_error,
            }

    # -- threads ------------------------------------------------------------
    def _recv_loop(self, bus_name):
        bus = self.buses[bus_name]
        own = self._own[bus_name]
        table, msgs = self.setup.tables.get(bus_name, (None, ()))
        keys = [message_key(m) if m.direction == "send" else None for m in msgs]
        for t, msg in self._frames(bus):
            with self._lock:
                if own is not None and own.is_echo(msg):
                    continue                          # our own frame, looped back
                if msg.is_error_frame:
                    self.error_frames_by_bus[bus_name] += 1
                    self._changed.notify_all()
                    continue
                i = table.find(msg.arbitration_id, msg.is_extended_id) if table is not None else -1
                key = keys[i] if i >= 0 else None
                if key is None:                       # not a message the plant sends on this bus
                    self.unknown[bus_name] += 1
                    self._changed.notify_all()
                    continue
                data = b"" if msg.is_remote_frame else bytes(msg.data)
                st = self._rx_stats[key]
                status = table.check(i, data, st.state)
                st.frame(t, status, table.decode(i, data) if status == codec.OK else None)
                self._changed.notify_all()


class CanTcu:
    """The reference TCU on an open python-can bus (``CanTcu.open`` makes one).

    bus         an open python-can Bus; shut down by ``close()`` only if
                ``open`` made it. With ``mapping``: one bus per mapping bus,
                as {bus name: Bus} or a list in the mapping's bus order (a
                single Bus for a mapping of one bus)
    time_scale  0 < s <= 1: the task period is PERIOD_S / s of wall time
                (slow-motion HiL; the plant server must run at the same scale)
    logic       a TcuLogic (default: a new one)
    start       start reception and the task now (else call ``start()``)
    rcvbuf_bytes  receive buffer asked for when the bus is a SocketCAN socket
    clock       "wall": a task tick every PERIOD_S / time_scale of wall time, as a
                production TCU; "bus": a task tick per accepted DCT_ShaftSpeeds
                frame (one per 2 ms of plant time), so the TCU follows the plant's
                time exactly, however slowly the plant runs (a slow-motion run on a
                machine that cannot keep even the slowed schedule). Without that
                frame for its timeout the bus clock ticks anyway, stale. With a
                mapping the clock message is the fastest of the needed messages
                (the first of them in mapping order), a tick per PERIOD_S of
                its cycle time.
    mapping     None: the project's own contract (``can_dbc/dct_hil.dbc``).
                A ``can_dbc.mapping.Mapping`` (or a ``MappedSetup``): the
                vehicle matrix it describes; the TCU receives its
                ``direction == "send"`` messages and sends its ``"receive"``
                ones (``MappedPeer``). A matrix without a signal the TCU needs
                raises ``MissingSignalError`` (one line) before anything starts.
    """

    def __init__(self, bus, time_scale=1.0, logic=None, start=True, rcvbuf_bytes=RCVBUF_BYTES,
                 clock="wall", mapping=None):
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        self.clock = clock
        self.time_scale = check_time_scale(time_scale)
        self.period_wall_s = PERIOD_S / self.time_scale
        setup = None
        if mapping is not None:
            setup = mapping if isinstance(mapping, MappedSetup) else MappedSetup(mapping)
            buses = _bus_dict(bus, setup.mapping)
        self.logic = logic if logic is not None else TcuLogic()
        self._owns_bus = False
        self.interface = None
        self.channel = None
        self.channels = None
        self.rcvbuf_bytes = None
        self.setup = setup
        self.mapping = None if setup is None else setup.mapping
        self.matrix = None if setup is None else setup.matrix
        if setup is None:
            self.bus = bus
            self.buses = None
            self.rcvbuf_bytes = _raise_bus_rcvbuf(bus, rcvbuf_bytes)
            self.peer = CanPeer(bus, side="tcu", start=False, send_thread=False, drain=True)
            self._needed = PLANT_NEEDED
            self._tx_names = TCU_MESSAGES
            self._cycle_ms = {name: codec.message(name).cycle_time for name in PLANT_NEEDED + TCU_MESSAGES}
            self._signals = {name: tuple(s.name for s in codec.payload_signals(codec.message(name)))
                             for name in PLANT_NEEDED}
            self._tx_signals = {name: tuple(targets) for name, targets in codec.TCU_SIGNAL_TARGETS.items()}
            self._clock_message, self._clock_ticks = "DCT_ShaftSpeeds", 1
        else:
            self.buses = buses
            self.bus = next(iter(buses.values()))
            granted = {name: _raise_bus_rcvbuf(b, rcvbuf_bytes) for name, b in buses.items()}
            self.rcvbuf_by_bus = granted
            known = [g for g in granted.values() if g]
            self.rcvbuf_bytes = min(known) if known else None
            self.peer = MappedPeer(buses, setup, start=False)
            self._needed = tuple(message_key(m) for m in self.matrix.needed)
            self._tx_names = tuple(message_key(m) for m in self.matrix.received)
            self._cycle_ms = {message_key(m): m.cycle_ms for m in self.matrix.sent + self.matrix.received}
            fastest = min(self.matrix.needed, key=lambda m: m.cycle_ms)
            self._clock_message, self._clock_ticks = message_key(fastest), cycle_ticks(fastest.cycle_ms)
        self._timeout_s = {name: TIMEOUT_CYCLES * self._cycle_ms[name] / 1000.0 / self.time_scale
                           for name in self._needed}
        # the needed messages that carry nothing but the engine's quantities (pedals, torque):
        # their loss the logic rides out (tcu_stub.diagnostics), the others make it stale
        diag = getattr(self.logic, "diag", None)
        if diag is not None:
            diag.engine_messages = frozenset(self._engine_messages())
        self._every_ticks = {name: max(1, int(round(self._cycle_ms[name] / 1000.0 / PERIOD_S)))
                             for name in self._tx_names}
        self._next_due = {name: 0 for name in self._tx_names}
        self._tx_absent = None            # the messages the logic's results do not carry (first tick)

        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ended = threading.Event()
        self._thread = None
        self.ticks = 0
        self.skipped_ticks = 0
        self.tick_index = 0
        self.t_s = 0.0
        self.stale = True                 # no plant frame yet
        self._episode = None              # the stale episode going on
        self.stale_ticks = 0
        self.stale_episodes = []          # {"start_s", "end_s" (None while stale), "causes": {msg: why}}
        self.stale_episode_count = 0
        self.sim_time_s = None
        self.commands = {sig: 0.0 for targets in codec.TCU_SIGNAL_TARGETS.values() for sig in targets}
        self.sensors = {}
        self.error = None                 # one line, when the task stopped on an exception
        self._pause_s = 0.0               # a pause asked for by pause(), taken at the next tick
        self.pauses = 0
        self.paused_s = 0.0
        self.final_safe_frames = None     # True/False once stop() sent (or tried) them
        self._exec_us = _Histogram()
        self._late_us = _Histogram()
        self.stall_max_s = 0.0            # the latest wake-up of the task (wall clock only)
        self.stall_count = 0              # ... later than STALL_PERIODS periods; the last kept:
        self.stall_log = collections.deque(maxlen=MAX_STALLS)
        self.started_at = None
        self.stopped_at = None
        if start:
            self.start()

    def _engine_messages(self):
        engine = set(ENGINE_SIGNALS)
        if self.matrix is None:
            carried = {name: set(self._signals[name]) for name in self._needed}
        else:
            carried = {name: set() for name in self._needed}
            for quantity, reader in self.matrix.readers.items():
                if reader.key in carried:
                    carried[reader.key].add(quantity)
        return [name for name, quantities in carried.items() if quantities and quantities <= engine]

    @classmethod
    def open(cls, interface="socketcan", channel="vcan0", bitrate=None, time_scale=1.0, logic=None,
             start=True, rcvbuf_bytes=RCVBUF_BYTES, clock="wall", mapping=None, bus_channels=None,
             **bus_kwargs):
        """A CanTcu on a new python-can Bus (shut down again by ``close()``).
        A bus that cannot be opened raises ConnectionError, one line naming the
        interface and the channel.

        With ``mapping`` (a ``Mapping``): one bus per mapping bus, on the
        channels ``mapping.channels(channel, bus_channels, derive)`` gives
        (``derive`` on the ``DERIVE_INTERFACES``), each at the mapping's bit
        rate (``bitrate`` must then be None). The matrix is checked (a missing
        signal: ``MissingSignalError``), the channels too (``MappingError``),
        before any bus is opened; a bus that cannot be opened closes the ones
        opened before it."""
        time_scale = check_time_scale(time_scale)
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
        kwargs = dict(bus_kwargs)
        if mapping is not None:
            if bitrate:
                raise ValueError("bitrate: with a mapping each bus runs at the mapping's bit rate")
            setup = mapping if isinstance(mapping, MappedSetup) else MappedSetup(mapping)
            channels = setup.mapping.channels(channel, bus_channels, derive=interface in DERIVE_INTERFACES)
            buses = {}
            try:
                for b in setup.mapping.buses:
                    extra = dict(kwargs, bitrate=b.bitrate)
                    if b.fd:
                        extra["fd"] = True
                        if b.data_bitrate:
                            extra["data_bitrate"] = b.data_bitrate
                    try:
                        buses[b.name] = open_bus(interface, channels[b.name], **extra)
                    except ConnectionError as e:
                        raise ConnectionError(f"{e} (mapping bus {b.name})") from None
                tcu = cls(buses, time_scale=time_scale, logic=logic, start=False, rcvbuf_bytes=rcvbuf_bytes,
                          clock=clock, mapping=setup)
            except BaseException:
                for opened in buses.values():
                    opened.shutdown()
                raise
            tcu._owns_bus = True
            tcu.interface, tcu.channel, tcu.channels = interface, channel, channels
            if start:
                tcu.start()
            return tcu
        if bitrate:
            kwargs["bitrate"] = bitrate
        bus = open_bus(interface, channel, **kwargs)
        try:
            tcu = cls(bus, time_scale=time_scale, logic=logic, start=False, rcvbuf_bytes=rcvbuf_bytes,
                      clock=clock)
        except Exception:
            bus.shutdown()
            raise
        tcu._owns_bus = True
        tcu.interface, tcu.channel = interface, channel
        if start:
            tcu.start()
        return tcu

    # ------------------------------------------------------------ life cycle
    def start(self):
        """Starts reception and the task (once)."""
        if self._thread is not None:
            return
        self.peer.start()
        self.started_at = time.monotonic()
        self._thread = threading.Thread(target=self._task, name="tcu-task", daemon=True)
        self._thread.start()

    @property
    def running(self):
        """The task thread runs (it ends on stop() or on an error in the task)."""
        return self._thread is not None and not self._ended.is_set()

    def stop(self):
        """Ends the task, then sends one final frame of each TCU message with safe
        values (0 A, no fork force, no torque request). Reception goes on until
        ``close()``. Safe to call more than once."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.stopped_at is None and self.started_at is not None:
            self.stopped_at = time.monotonic()
        if self.final_safe_frames is None and self._thread is not None:
            self._send_safe()

    def _send_safe(self):
        """One frame of each TCU message with safe values: the contract's
        (``codec.TCU_SAFE_VALUES``), or through a mapping each target's
        ``safe`` value (the signal value that gives it)."""
        ok = True
        for name in self._tx_names:
            if self._tx_absent and name in self._tx_absent:
                continue
            try:
                if self.matrix is None:
                    values = codec.TCU_SAFE_VALUES[name]
                else:
                    values = self.matrix.safe_values(self.peer.tx_messages[name])
                ok = self.peer.send_now(name, values) and ok
            except Exception as e:
                ok = False
                self.peer.last_send_error = f"{name}: {_one_line(e) or type(e).__name__}"
        with self._lock:
            self.final_safe_frames = ok
            if self.matrix is None:
                self.commands = {k: v for vals in codec.TCU_SAFE_VALUES.values() for k, v in vals.items()}
            else:
                self.commands = self.matrix.safe_commands()

    def close(self):
        """``stop()``, then ends reception; shuts the bus (the buses) down if ``open`` made it."""
        self.stop()
        self.peer.close()
        if self._owns_bus:
            self._owns_bus = False
            for bus in (self.buses.values() if self.buses is not None else (self.bus,)):
                bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def wait_for(self, predicate, timeout=5.0, poll_s=0.01):
        """Waits until ``predicate(self)`` is true or ``timeout`` seconds passed;
        returns the predicate's last value."""
        deadline = time.monotonic() + timeout
        while True:
            ok = predicate(self)
            if ok or time.monotonic() >= deadline:
                return ok
            time.sleep(poll_s)

    def pause(self, seconds):
        """Starves the node for ``seconds`` of wall time from its next tick, as a TCU
        whose threads get no CPU (to see what a starved TCU does to a run, in a test
        or while debugging). The task stops, holding the lock its reception needs:
        no tick runs, no frame is sent and none is taken in. Its first tick after the
        pause works with what the node had received before it (by then older than
        the pause), and the deadlines missed are skipped as after any late wake-up;
        then reception takes in the frames that queued up meanwhile. Returns at once;
        the report counts the pauses (``pauses``). ValueError unless 0 < seconds <= 60."""
        try:
            s = float(seconds)
        except (TypeError, ValueError):
            raise ValueError(f"pause {seconds!r} is not a number of seconds") from None
        if not (math.isfinite(s) and 0.0 < s <= 60.0):
            raise ValueError(f"pause must be above 0 and at most 60 s, got {seconds}")
        with self._lock:
            self._pause_s = s

    def _starve(self):
        """The pause asked for by ``pause()``, taken in the task thread; returns the
        plant frames as received before it (``peer.rx_snapshot()``)."""
        with self._lock:
            seconds, self._pause_s = self._pause_s, 0.0
        snap = self.peer.rx_snapshot()
        if seconds > 0:
            with self.peer._lock:       # reception waits with the task: the whole node starves
                self._stop.wait(seconds)
            with self._lock:
                self.pauses += 1
                self.paused_s += seconds
        return snap

    # ------------------------------------------------------------ the task
    def _task(self):
        if self.clock == "bus":
            return self._task_bus()
        period = self.period_wall_s
        t0 = time.monotonic()
        k = 0
        try:
            while not self._stop.is_set():
                deadline = t0 + k * period
                now = time.monotonic()
                while now < deadline:
                    if self._stop.wait(deadline - now):
                        return
                    now = time.monotonic()
                self._note_wake(now - deadline, now - t0)
                snap = None
                if self._pause_s:
                    snap = self._starve()
                    now = time.monotonic()
                late = now - deadline
                if late > period:                       # skip the missed deadlines, no burst
                    missed = int(late // period)
                    k += missed
                    deadline += missed * period
                    late = now - deadline
                    with self._lock:
                        self.skipped_ticks += missed
                self._tick(k, now, snap)
                self._late_us.add(late * 1e6)
                self._exec_us.add((time.monotonic() - now) * 1e6)
                k += 1
        except Exception as e:  # the task stops; stop() sends the safe frames
            self.error = f"TCU task stopped at {k * PERIOD_S:.3f} s: {type(e).__name__}: {_one_line(e)}"
            self._send_safe()                           # the last commands on the bus are safe
        finally:
            self._ended.set()

    def _note_wake(self, late_s, at_s):
        """A wake-up late_s after its deadline (before a pause asked for), as the C
        node's note_wake: the latest kept, one later than STALL_PERIODS periods logged."""
        if late_s > self.stall_max_s:
            self.stall_max_s = late_s
        if late_s > STALL_PERIODS * self.period_wall_s:
            with self._lock:
                self.stall_log.append({"index": self.stall_count, "at_s": round(at_s, 4),
                                       "late_ms": round(late_s * 1e3, 3)})
                self.stall_count += 1

    def stalls(self, since=0):
        """(stalls, count) as ``CTcuNode.stalls``: the task's wake-ups later than
        STALL_PERIODS periods numbered ``since`` and after, of the last MAX_STALLS
        kept (wall clock only; the bus clock's task waits for frames, not deadlines)."""
        with self._lock:
            return [dict(e) for e in self.stall_log if e["index"] >= since], self.stall_count

    def _task_bus(self):
        """One tick per accepted DCT_ShaftSpeeds frame (2 ms of plant time each);
        frames missed in between advance the TCU time and count as skipped.
        Through a mapping: the clock message's frames, each as many ticks in a
        row as its cycle time holds TCU periods."""
        name = self._clock_message
        per_frame = self._clock_ticks
        seen = self.peer.counts(name)["accepted"]
        wait_s = self._timeout_s[name]
        k = 0
        try:
            while not self._stop.is_set():
                self.peer.wait_for(lambda p, seen=seen: self._stop.is_set()
                                   or p.counts(name)["accepted"] > seen, timeout=wait_s)
                if self._stop.is_set():
                    return
                snap = self._starve() if self._pause_s else None
                now = time.monotonic()
                accepted = self.peer.counts(name)["accepted"]
                if accepted > seen + 1 and k > 0:       # frames this task did not get to
                    with self._lock:
                        self.skipped_ticks += (accepted - seen - 1) * per_frame
                    k += (accepted - seen - 1) * per_frame
                seen = max(seen, accepted)
                for _ in range(per_frame):
                    self._tick(k, now, snap)
                    self._exec_us.add((time.monotonic() - now) * 1e6)
                    k += 1
        except Exception as e:  # the task stops; stop() sends the safe frames
            self.error = f"TCU task stopped at {k * PERIOD_S:.3f} s: {type(e).__name__}: {_one_line(e)}"
            self._send_safe()
        finally:
            self._ended.set()

    def _read_sensors(self, now, snap=None):
        """(sensors, {message: why} of the stale ones) from the last accepted plant frames
        (``snap``: a ``peer.rx_snapshot()`` taken earlier, else one taken now)."""
        if snap is None:
            snap = self.peer.rx_snapshot()
        sensors = {}
        causes = {}
        for name in self._needed:
            values, t_ok, rejects_in_row, why = snap[name]
            if values is None:
                causes[name] = "missing"
                continue
            if rejects_in_row >= REJECTS_TO_STALE:
                causes[name] = why or "rejected"          # bad_crc, bad_counter, bad_length
            elif now - t_ok > self._timeout_s[name]:
                causes[name] = "timeout"
            if self.matrix is None:
                for sig in self._signals[name]:
                    sensors[sig] = values[sig]
        if self.matrix is None:
            status = snap.get("SIM_Status")
            sim_time = status[0]["SimTime"] if status is not None and status[0] is not None else None
        else:
            decoded = {key: v[0] for key, v in snap.items() if v[0] is not None}
            sensors = self.matrix.view(decoded)
            sim_time = self.matrix.status_value(decoded, "sim_time_s")
        sensors["stale"] = bool(causes)
        sensors["stale_messages"] = causes
        return sensors, causes, sim_time

    def _absent_messages(self, cmd):
        """The contract's TCU messages none of whose signals a logic's result carries (a logic
        without the diagnosis sends no TCU_Status); they are not sent."""
        if self.matrix is not None:
            return frozenset()
        return frozenset(name for name in self._tx_names
                         if not any(sig in cmd for sig in self._tx_signals[name]))

    def _tick(self, k, now, snap=None):
        t_s = k * PERIOD_S
        sensors, causes, sim_time = self._read_sensors(now, snap)
        cmd = self.logic.step(t_s, sensors)
        if self._tx_absent is None:
            self._tx_absent = self._absent_messages(cmd)
        for name in self._tx_names:
            if k >= self._next_due[name] and name not in self._tx_absent:
                every = self._every_ticks[name]
                if self.matrix is None:
                    self.peer.send_now(name, {sig: cmd[sig] for sig in self._tx_signals[name]})
                else:
                    self.peer.send_now(name, self.matrix.command_values(self.peer.tx_messages[name], cmd))
                self._next_due[name] = (k // every + 1) * every
        with self._lock:
            self.tick_index = k
            self.t_s = t_s
            self.ticks += 1
            self.sensors = sensors
            self.commands = cmd
            self.sim_time_s = sim_time
            stale = bool(causes)
            if stale:
                self.stale_ticks += 1
                if self._episode is None:
                    self.stale_episode_count += 1
                    self._episode = {"start_s": t_s, "end_s": None, "causes": {}}
                    if len(self.stale_episodes) < _MAX_EPISODES:
                        self.stale_episodes.append(self._episode)
                for name, why in causes.items():
                    self._episode["causes"].setdefault(name, why if why in _EPISODE_CAUSES else "rejected")
            elif self._episode is not None:
                self._episode["end_s"] = t_s
                self._episode = None
            self.stale = stale

    # ------------------------------------------------------------ records
    @property
    def events(self):
        """The shifts the logic started: [(TCU time s, from gear, to gear)]."""
        return list(self.logic.events)

    def message_name(self, message):
        """The name the node counts a message under: the DBC name on the
        contract; through a mapping ``bus:Message`` (a bare message name
        when only one bus has it). ValueError for a message it neither
        receives nor sends."""
        if self.matrix is None:
            return codec.message(message).name
        return matrix_message_name(message, tuple(self.peer.rx_messages) + tuple(self.peer.tx_messages),
                                   self.mapping.path)

    def counts(self, message):
        """{received, accepted, bad_length, bad_crc, bad_counter} of a plant message."""
        return self.peer.counts(self.message_name(message))

    def sent(self, message):
        """Frames of a TCU message put on the bus."""
        return self.peer.sent[self.message_name(message)]

    def status_line(self):
        """One line: TCU time, phase, gear -> target gear, stale or not, speeds, frames rx/tx."""
        with self._lock:
            t_s, stale, s, skipped = self.t_s, self.stale, self.sensors, self.skipped_ticks
        logic = self.logic
        names = self.peer.rx.names if self.matrix is None else self.peer.names
        rx = sum(self.peer.counts(m)["accepted"] for m in names)
        tx = sum(self.peer.sent.values())
        v = s.get("VehicleSpeed")
        n = s.get("EngineSpeed")
        speeds = (f"v {v:5.1f} km/h  engine {n:5.0f} rpm" if v is not None and n is not None
                  else "v   -   km/h  engine   -   rpm")
        diag = getattr(logic, "diag", None)
        faults = decode_active_faults(diag.active_bits) if diag is not None else ()
        return (f"TCU {t_s:8.2f} s  {logic.phase:<17} gear {logic.gear} -> {logic.target_gear}  "
                f"{'STALE' if stale else 'ok   '}  {speeds}  rx {rx}  tx {tx}  skipped {skipped}"
                + (f"  DTC {','.join(faults)}" if faults else "")
                + ("  LIMP HOME" if diag is not None and diag.limp_home else ""))

    def report(self):
        """Everything recorded, as JSON-ready data."""
        peer = self.peer.report()
        with self._lock:
            end = self.stopped_at if self.stopped_at is not None else time.monotonic()
            where = ("bus", "message") if self.matrix is not None else ()
            received = {name: {**{k: r[k] for k in where},
                               "frame_id": r["frame_id"], "cycle_ms": r["cycle_ms"], "received": r["received"],
                               "accepted": r["accepted"], "rejected": r["rejected"],
                               "mean_interval_ms": r["mean_interval_ms"], "max_interval_ms": r["max_interval_ms"]}
                        for name, r in peer["received"].items()}
            sent = {name: {**{k: s[k] for k in where},
                           "frame_id": s["frame_id"], "cycle_ms": self._cycle_ms[name],
                           "frames": s["frames"], "errors": s["errors"], "saturated": s["saturated"]}
                    for name, s in peer["sent"].items()}
            diag = getattr(self.logic, "diag", None)
            rep = {
                "node": "TCU",
                "interface": self.interface,
                "channel": self.channel,
                "time_scale": self.time_scale,
                "clock": self.clock,
                "period_s": PERIOD_S,
                "period_wall_s": self.period_wall_s,
                "wall_time_s": (end - self.started_at) if self.started_at is not None else 0.0,
                "tcu_time_s": self.t_s,
                "ticks": self.ticks,
                "skipped_ticks": self.skipped_ticks,
                "tick_exec_us": self._exec_us.summary(),
                "tick_wake_late_us": self._late_us.summary(),
                "stalls": None if self.clock == "bus" else {
                    "longest_ms": round(self.stall_max_s * 1e3, 3),
                    "over_ms": round(STALL_PERIODS * self.period_wall_s * 1e3, 3),
                    "count": self.stall_count, "last": list(self.stall_log)},
                "socket_rcvbuf_bytes": self.rcvbuf_bytes,
                "phase": self.logic.phase,
                "gear": self.logic.gear,
                "target_gear": self.logic.target_gear,
                "shifts": [{"t_s": round(t, 6), "from_gear": a, "to_gear": b} for t, a, b in self.logic.events],
                "diagnostics": diag.report() if diag is not None else None,
                "stale": {
                    "now": self.stale,
                    "ticks": self.stale_ticks,
                    "episode_count": self.stale_episode_count,
                    "episodes": [dict(ep, causes=dict(ep["causes"])) for ep in self.stale_episodes],
                    "timeout_ms": {n: round(t * 1000.0, 3) for n, t in self._timeout_s.items()},
                },
                "sim_time_s": self.sim_time_s,
                "received": received,
                "unknown_frames": peer["unknown_frames"],
                "error_frames": peer["error_frames"],
                "sent": sent,
                "send_errors": sum(s["errors"] for s in sent.values()),
                "last_send_error": peer["last_send_error"],
                "drained_at_start": peer["drained_at_start"],
                "saturated": sum(s["saturated"] for s in sent.values()),
                "last_commands": dict(self.commands),
                "final_safe_frames": self.final_safe_frames,
                "error": self.error,
                "pauses": {"count": self.pauses, "total_s": round(self.paused_s, 6)},
            }
            if self.matrix is not None:
                rep["mapping"] = self.mapping.path
                rep["buses"] = {b.name: {"channel": (self.channels or {}).get(b.name), "bitrate": b.bitrate,
                                         "fd": b.fd, "socket_rcvbuf_bytes": self.rcvbuf_by_bus.get(b.name),
                                         "unknown_frames": peer["unknown_frames_by_bus"].get(b.name, 0)}
                                for b in self.mapping.buses}
                rep["stale"]["needed"] = list(self._needed)
                rep["own_echoes_dropped"] = peer["own_echoes_dropped"]
            return rep

    def write_report(self, path):
        """Writes ``report()`` as JSON to ``path`` (its folder is created); returns the report."""
        rep = self.report()
        folder = os.path.dirname(os.path.abspath(path))
        os.makedirs(folder, exist_ok=True)
        with open(path, "w", encoding="utf-8") as f:
            json.dump(rep, f, indent=2)
            f.write("\n")
        return rep


# ---------------------------------------------------------------------------
# Command line: dct-hil tcu / python -m tcu_stub.can_tcu
# ---------------------------------------------------------------------------

def _time_scale_arg(text):
    try:
        return check_time_scale(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).replace("time scale ", "", 1)) from None




def add_arguments(parser, impl=True):
    """The options of ``dct-hil tcu`` on an argparse parser (or subparser);
    ``impl``: with ``--impl`` and ``--priority`` (the C node's, ``tcu_stub.command``)."""
    parser.add_argument("--channel", metavar="NAME",
                        help="CAN channel: a network interface for socketcan (vcan0, can0), the "
                             "python-can channel otherwise, for udp_multicast GROUP or GROUP:PORT "
                             "(default: vcan0 on socketcan and virtual, 239.74.163.2 on "
                             "udp_multicast, else the one python-can finds for the interface)")
    parser.add_argument("--interface", default="socketcan", metavar="NAME",
                        help="python-can interface: socketcan, virtual, udp_multicast, pcan, ... "
                             "(default socketcan)")
    parser.add_argument("--bitrate", type=argtypes.bitrate, metavar="BIT/S",
                        help="bit rate, for interfaces that set it")
    parser.add_argument("--duration", type=argtypes.seconds, metavar="S",
                        help="stop after S seconds of wall time (default: run until Ctrl-C or SIGTERM)")
    parser.add_argument("--time-scale", type=_time_scale_arg, default=1.0, metavar="S",
                        help="run slower than real time by this factor, 0 < S <= 1 (the server must "
                             "use the same); the task period is 2 ms / S (default 1)")
    parser.add_argument("--clock", choices=CLOCKS, default="wall",
                        help="wall: a task tick every 2 ms (/ time scale) of wall time, as a TCU "
                             "(default); bus: a tick per DCT_ShaftSpeeds frame, following the "
                             "plant's time exactly (slow-motion runs on slow machines)")
    add_matrix_options(
        parser, needs_mapping=True,
        mapping_help="speak a vehicle CAN matrix through this mapping file (or a shipped one: "
                     "dct_hil, vehicle) instead of the project's own contract: receive the "
                     "messages the plant sends, send the ones it receives, one CAN channel "
                     "per bus of the mapping",
        bus_help="the CAN channel of the mapping's bus NAME (repeatable); the first bus "
                 "defaults to --channel, the others on virtual and udp_multicast to "
                 "CHANNEL-NAME, elsewhere each needs --bus")
    if impl:
        _add_impl_arguments(parser)
    parser.add_argument("--report", metavar="FILE.json", help="write the JSON report here at the end")
    parser.add_argument("--quiet", action="store_true", help="no live status and no summary")
    return parser


def _add_impl_arguments(parser):
    parser.add_argument("--impl", choices=("c", "python"), default="c",
                        help="c: the C node (tcu_stub.c_node: the task, the codec and the logic in a "
                             "C thread of its own, SCHED_FIFO when allowed; the default); python: this "
                             "module's node, for editing tcu_stub/logic.py")
    parser.add_argument("--priority", type=argtypes.priority, default=None, metavar="0..99",
                        help="SCHED_FIFO priority of the C node's thread (default 70, below the "
                             "server's 80; refused without the right: the normal scheduler)")


def parse_bus_channels(items):
    """{bus name: channel} from ``--bus NAME=CHANNEL`` items; ValueError (one line) for
    an item without both parts or a bus named twice (``can_dbc.mapping.parse_pairs``)."""
    from can_dbc.mapping import parse_pairs

    return parse_pairs(items, "--bus", "NAME=CHANNEL")


def load_mapping(name_or_path, dbc=()):
    """``(MappedSetup, None)`` for a mapping file or shipped name (``dbc``:
    ``--dbc [BUS=]FILE`` values, DBCs read instead of the mapping's), or
    ``(None, one-line error)`` when it cannot be loaded, lacks what the TCU
    needs, or has a layout the table codec cannot take. Opens no bus."""
    from can_dbc.mapping import MappingError, load_options
    from can_dbc.table import TableError

    try:
        return MappedSetup(load_options(name_or_path, dbc)), None
    except (MappingError, MissingSignalError, TableError) as e:
        return None, _one_line(e)
    except OSError as e:
        return None, f"{name_or_path}: {e.strerror or e}"


def _check_report_path(path):
    full = os.path.abspath(path)
    if os.path.isdir(full):
        return f"--report {path}: is a directory"
    folder = os.path.dirname(full)
    probe = folder
    while not os.path.isdir(probe):          # the folder is created at the end; check its nearest parent
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.access(probe, os.W_OK | os.X_OK) or (os.path.exists(full) and not os.access(full, os.W_OK)):
        return f"--report {path}: not writable"
    return None


def summary_lines(rep):
    """The exit summary of a run, from ``report()``."""
    lines = [f"TCU on {_where(rep)}: {rep['tcu_time_s']:.2f} s of TCU time "
             f"(time scale {rep['time_scale']:g}), {rep['ticks']} ticks, {rep['skipped_ticks']} skipped; "
             f"tick cost p99 {rep['tick_exec_us']['p99']} us"]
    w = max([17] + [len(name) for name in list(rep["received"]) + list(rep["sent"])])
    for name, r in rep["received"].items():
        rej = ", ".join(f"{k} {v}" for k, v in r["rejected"].items() if v)
        lines.append(f"  rx {name:<{w}} {r['accepted']:>8} accepted of {r['received']:>8}"
                     + (f"  rejected: {rej}" if rej else ""))
    for name, s in rep["sent"].items():
        lines.append(f"  tx {name:<{w}} {s['frames']:>8} sent" + (f"  errors {s['errors']}" if s["errors"] else "")
                     + (f"  saturated {s['saturated']}" if s.get("saturated") else ""))
    shifts = " ".join(f"{s['from_gear']}>{s['to_gear']}@{s['t_s']:.2f}" for s in rep["shifts"][:20])
    more = f" (+{len(rep['shifts']) - 20})" if len(rep["shifts"]) > 20 else ""
    lines.append(f"  shifts: {len(rep['shifts'])} {shifts}{more}".rstrip())
    lines.append(f"  stale episodes: {rep['stale']['episode_count']}"
                 + (", stale now" if rep["stale"]["now"] else ""))
    diag = rep.get("diagnostics") or {}
    if diag.get("stored"):
        lines.append(f"  trouble codes set: {', '.join(diag['stored'])} ({diag['fault_count']} times)"
                     + (f"; active now: {', '.join(diag['active'])}" if diag.get("active") else "")
                     + ("; limp home" if diag.get("limp_home") else "")
                     + (f"; gears inhibited: {', '.join(map(str, diag['inhibited_gears']))}"
                        if diag.get("inhibited_gears") else ""))
    if rep["unknown_frames"]:
        by_bus = rep.get("buses")
        detail = (" (" + ", ".join(f"{n} {b['unknown_frames']}" for n, b in by_bus.items()) + ")"
                  if by_bus else "")
        lines.append(f"  unknown ids: {rep['unknown_frames']}{detail}")
    return lines


def _where(rep):
    """``interface:channel``, or through a mapping the interface, each bus's
    channel and the mapping file."""
    buses = rep.get("buses")
    if not buses:
        return f"{rep['interface']}:{rep['channel']}"
    chans = ", ".join(f"{name} {b['channel']}" for name, b in buses.items())
    return f"{rep['interface']} ({chans}) through {rep['mapping']}"


def run(args, out=None, err=None, prog="dct-hil tcu", open_node=None):
    """``dct-hil tcu``: runs the node until ``--duration``, Ctrl-C or SIGTERM;
    returns the exit status (0 stopped cleanly by --duration or SIGTERM, 130
    after Ctrl-C (also clean), 1 the bus cannot be opened or the task failed,
    2 bad options). ``open_node``: opens the node as ``CanTcu.open`` does
    (default ``CanTcu.open``; ``tcu_stub.command`` gives the C node's), and
    raises ConnectionError, or RuntimeError for a node that cannot start."""
    out = out or sys.stdout
    err = err or sys.stderr

    def fail(code, message):
        print(f"{prog}: error: {_one_line(message)}", file=err)
        return code

    try:
        time_scale = check_time_scale(getattr(args, "time_scale", 1.0))
    except ValueError as e:
        return fail(2, f"--time-scale: {e}")
    duration = getattr(args, "duration", None)
    if duration is not None and not (isinstance(duration, (int, float)) and math.isfinite(duration)
                                     and duration > 0):
        return fail(2, f"--duration: must be a number of seconds above 0, got {duration}")
    if args.channel is None:
        try:
            args.channel = default_channel(args.interface)
        except ChannelError as e:
            return fail(2, f"--channel: {e}")
    if args.report:
        problem = _check_report_path(args.report)
        if problem:
            return fail(2, problem)
    setup, bus_channels = None, None
    bus_items = getattr(args, "bus", None) or []
    if getattr(args, "mapping", None):
        if args.bitrate:
            return fail(2, "--bitrate: with --mapping each bus runs at the mapping's bit rate")
        try:
            bus_channels = parse_bus_channels(bus_items)
        except ValueError as e:
            return fail(2, e)
        setup, problem = load_mapping(args.mapping, getattr(args, "dbc", None) or ())
        if problem:
            return fail(2, f"--mapping: {problem}")
        from can_dbc.mapping import MappingError

        try:
            setup.mapping.channels(args.channel, bus_channels, derive=args.interface in DERIVE_INTERFACES)
        except MappingError as e:
            return fail(2, e)
    elif getattr(args, "dbc", None):
        return fail(2, "--dbc needs --mapping (the project's own contract has its own DBC)")
    elif bus_items:
        return fail(2, "--bus: only with --mapping (the contract has one bus: --channel)")
    try:
        tcu = (open_node or CanTcu.open)(args.interface, args.channel, bitrate=args.bitrate,
                                         time_scale=time_scale, clock=getattr(args, "clock", "wall"),
                                         mapping=setup, bus_channels=bus_channels)
    except (ConnectionError, RuntimeError) as e:
        return fail(1, e)

    signals = StopSignals().__enter__()      # SIGINT, SIGTERM: stop (restored below)
    done = signals.event
    tty = hasattr(out, "isatty") and out.isatty()
    try:
        if not args.quiet:
            rcv = (f", receive buffer {tcu.rcvbuf_bytes} bytes (about {tcu.rcvbuf_bytes // SKB_BYTES_PER_FRAME} "
                   "frames)" if tcu.rcvbuf_bytes else "")
            where = (f"{args.interface}:{args.channel}" if setup is None else
                     f"{args.interface} (" + ", ".join(f"{n} {c}" for n, c in tcu.channels.items())
                     + f") through {setup.mapping.path}")
            print(f"{prog} on {where}, period {PERIOD_S * 1000:g} ms of TCU time "
                  f"({tcu.period_wall_s * 1000:g} ms wall at time scale {time_scale:g}){rcv}; "
                  "Ctrl-C or SIGTERM stops", file=out, flush=True)
        end = None if duration is None else time.monotonic() + duration
        while not done.is_set() and tcu.running:
            left = 1.0 if end is None else min(1.0, end - time.monotonic())
            if left <= 0:
                break
            done.wait(left)
            if not args.quiet and not done.is_set():
                line = tcu.status_line()
                print(("\r\x1b[K" + line) if tty else line, end="" if tty else "\n", file=out, flush=True)
    finally:
        tcu.close()
        signals.__exit__()
    if tty and not args.quiet:
        print(file=out)
    rep = tcu.report()
    if args.report:
        try:
            tcu.write_report(args.report)
        except OSError as e:
            return fail(1, f"--report {args.report}: {e.strerror or e}")
    if not args.quiet:
        print("\n".join(summary_lines(rep)), file=out)
        if args.report:
            print(f"report: {args.report}", file=out)
    if rep["last_send_error"]:
        print(f"{prog}: send errors: {rep['send_errors']}, last: {_one_line(rep['last_send_error'])}", file=err)
    if tcu.error:
        return fail(1, tcu.error)
    if signals.interrupted:
        return 130                       # Ctrl-C, as everywhere in dct-hil
    return 0


class _Parser(argparse.ArgumentParser):
    """Bad options: one line naming the option, exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {_one_line(message)}\n")


def main(argv=None):
    parser = _Parser(prog="python -m tcu_stub.can_tcu",
                     description="The reference TCU (tcu_stub.logic) as a CAN node against the plant "
                                 "server: 2 ms task, E2E-protected frames, safe frames on exit.")
    add_arguments(parser, impl=False)
    args = parser.parse_args(argv)
    return run(args, prog=parser.prog)


if __name__ == "__main__":
    sys.exit(main())
