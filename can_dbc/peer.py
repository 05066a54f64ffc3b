"""An end-to-end-aware CAN node for either side of the contract, on any
python-can bus: a test TCU against the plant server, or a stand-in plant
against a TCU.

``CanPeer(bus, side="tcu")`` sends the TCU messages at their DBC cycle times
(its own thread on absolute deadlines, AliveCounter and CRC per frame),
receives the plant's messages in a second thread, checks them with
``E2eReceiver`` and keeps the last decoded values and per-message counts.
``side="plant"`` is the reverse. With ``send_thread=False`` there is no send
thread: the caller sends each frame when it is due with ``send_now`` (an ECU
task that computes, then sends; ``tcu_stub.can_tcu`` does so).

Command line (a test TCU for a while, then a JSON report)::

    python -m can_dbc.peer tcu --channel vcan0 --interface socketcan --duration 3 \\
        --set SolenoidCurrent1=0.6 --set ForkForce1=800 --report out.json

Timing is soft: Python threads on a normal scheduler. The send thread keeps
absolute deadlines, so the mean cycle time is right even when single frames
are late; when it falls more than a whole cycle behind it skips the missed
frames (counted as ``skipped``) instead of sending a burst.
"""

import argparse
import json
import math
import os
import signal
import sys
import threading
import time

from plant.stop_signals import StopSignals

from . import codec
from .channels import open_bus
from .node import ReceivingNode, RxStats
from .own_frames import OwnFrames, is_echoing_bus
from .python_can import python_can

SIDES = {"tcu": ("TCU", "PLANT"), "plant": ("PLANT", "TCU")}


class CanPeer(ReceivingNode):
    """One node on a python-can bus, sending and receiving with E2E protection.

    bus     an open python-can Bus (``CanPeer.open`` makes one); the peer
            shuts it down in ``close()`` only if it opened it
    side    "tcu": sends TCU_*, receives the plant's messages;
            "plant": sends the plant's messages, receives TCU_*
    values  initial signal values ({signal: value}); unset signals send their
            start value (codec.start_value: GenSigStartValue, else 0)
    start   start the send and receive threads now (else call ``start()``)
    send_thread
            False: no send thread; the caller sends each frame with
            ``send_now`` when it is due (a task that computes and then
            sends, as an ECU does). Reception is the same either way.
    drain   True: at ``start()`` the frames the bus queued before are
            discarded and counted (``drained_at_start``), as a TCU starting
            late does; False (a test node that accounts for every frame): kept
    """

    def __init__(self, bus, side="tcu", values=None, start=True, send_thread=True, drain=False):
        if side not in SIDES:
            raise ValueError(f"side must be one of {', '.join(SIDES)}, got {side!r}")
        self.side = side
        self.send_thread = bool(send_thread)
        self.drain = bool(drain)
        self.node, self.peer_node = SIDES[side]
        self.bus = bus
        self._owns_bus = False
        self.tx_messages = codec.messages(self.node)
        self.rx = codec.E2eReceiver(sender=self.peer_node)
        self._signal_msg = {s.name: m for m in self.tx_messages for s in codec.payload_signals(m)}
        self._values = {m.name: {s.name: codec.start_value(s) for s in codec.payload_signals(m)}
                        for m in self.tx_messages}
        self._enabled = {m.name: True for m in self.tx_messages}
        self._counter = {m.name: 0 for m in self.tx_messages}
        self.sent = {m.name: 0 for m in self.tx_messages}
        self.send_errors = {m.name: 0 for m in self.tx_messages}
        #: values the encoder limited to their signal's DBC range, frames sent
        self.saturated = {m.name: 0 for m in self.tx_messages}
        self.skipped = {m.name: 0 for m in self.tx_messages}
        self.last_send_error = None
        self.injected = 0
        self.error_frames = 0
        # a bus that loops our own frames back (udp_multicast): stamp what we
        # send and drop the echoes before they count as received traffic
        self._own = OwnFrames(str(getattr(bus, "channel_info", "") or side)) \
            if is_echoing_bus(bus) else None
        self._rx_stats = {name: RxStats() for name in self.rx.names}
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()   # one frame at a time: send thread and send_now share counters
        self._changed = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._threads = []
        self.started_at = None
        self.stopped_at = None
        if values:
            self.set(**values)
        if start:
            self.start()

    @classmethod
    def open(cls, side="tcu", interface="socketcan", channel="vcan0", bitrate=None, values=None, start=True,
             send_thread=True, **bus_kwargs):
        """A peer on a new python-can Bus (closed again by ``close()``)."""
        kwargs = dict(bus_kwargs)
        if bitrate:
            kwargs["bitrate"] = bitrate
        bus = open_bus(interface, channel, **kwargs)
        try:
            peer = cls(bus, side=side, values=values, start=start, send_thread=send_thread)
        except Exception:
            bus.shutdown()
            raise
        peer._owns_bus = True
        return peer

    # -- control ------------------------------------------------------------

    def start(self):
        if self._threads:
            return
        loops = ((self._send_loop, "send"), (self._recv_loop, "recv")) if self.send_thread else \
            ((self._recv_loop, "recv"),)
        if self.drain:
            self._drain(self.bus)
        self._start_threads((target, (), f"can-peer-{self.side}-{name}") for target, name in loops)

    def close(self):
        """Stops both threads; shuts the bus down if the peer opened it."""
        self._stop_threads()
        if self._owns_bus:
            self._owns_bus = False
            self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def set(self, **signals):
        """Changes the values sent from the next frame on: ``set(SolenoidCurrent1=0.6, ForkForce1=800)``.
        Values are limited to the signal's DBC range when sent."""
        staged = []
        for name, value in signals.items():
            msg = self._signal_msg.get(name)
            if msg is None:
                raise ValueError(f"{name} is not a signal the {self.node} sends "
                                 f"(it sends {', '.join(sorted(self._signal_msg))})")
            sig = msg.get_signal_by_name(name)
            codec.limit(sig, value)          # raises on NaN, non-numbers, unknown choice names
            staged.append((msg.name, name, value))
        with self._lock:
            for msg_name, name, value in staged:
                self._values[msg_name][name] = value

    def values_sent(self, message=None):
        """The values being sent (of one message, or {message: values})."""
        with self._lock:
            if message is not None:
                return dict(self._values[codec.message(message).name])
            return {k: dict(v) for k, v in self._values.items()}

    def enable(self, message, on=True):
        """Starts or stops sending one message (e.g. to make the other side time it out)."""
        name = codec.message(message).name
        if name not in self._enabled:
            raise ValueError(f"{name} is not a message the {self.node} sends")
        with self._lock:
            self._enabled[name] = bool(on)

    def inject(self, frame_id, data, is_extended_id=False):
        """Puts one raw frame on the bus as given (any id, any length 0..8, any CRC)."""
        can = python_can()

        data = bytes(data)
        if len(data) > 8:
            raise ValueError(f"classic CAN carries at most 8 data bytes, got {len(data)}")
        limit = 0x1FFFFFFF if is_extended_id else 0x7FF
        if not 0 <= int(frame_id) <= limit:
            raise ValueError(f"frame id 0x{int(frame_id):X} out of range for a "
                             f"{'29' if is_extended_id else '11'}-bit identifier")
        self.bus.send(self._message(can, arbitration_id=int(frame_id), data=data, dlc=len(data),
                                    is_extended_id=is_extended_id))
        with self._lock:
            self.injected += 1

    def send_now(self, message, values=None):
        """Sends one frame of ``message`` now, from the calling thread (the
        next AliveCounter, the CRC), after taking ``values`` ({signal: value},
        the others keep their last values) as the values sent from now on.
        Returns True when the bus took the frame; a refused send is counted
        in ``send_errors`` and the counter does not move. Values are limited
        to the DBC ranges by the encoder; NaN raises ValueError."""
        msg = codec.message(message)
        if msg.name not in self._values:
            raise ValueError(f"{msg.name} is not a message the {self.node} sends")
        if values:
            current = self._values[msg.name]
            unknown = [name for name in values if name not in current]
            if unknown:
                raise ValueError(f"{msg.name} has no signal {unknown[0]} (it has {', '.join(current)})")
            with self._lock:
                current.update(values)
        return self._send_one(msg)

    # -- what was received --------------------------------------------------

    def _rx_key(self, message):
        return codec.message(message).name

    @property
    def unknown_frames(self):
        with self._lock:
            return self.rx.unknown

    def report(self):
        """Everything counted so far, as JSON-ready data."""
        with self._lock:
            end = self.stopped_at if self.stopped_at is not None else time.monotonic()
            received = {}
            for name, st in self._rx_stats.items():
                m = codec.message(name)
                received[name] = {"frame_id": m.frame_id, "cycle_ms": m.cycle_time, **st.figures()}
            sent = {name: {"frame_id": codec.message(name).frame_id, "frames": self.sent[name],
                           "errors": self.send_errors[name], "skipped": self.skipped[name],
                           "saturated": self.saturated[name], "values": dict(self._values[name])}
                    for name in self._values}
            return {
                "side": self.side,
                "node": self.node,
                "duration_s": (end - self.started_at) if self.started_at is not None else 0.0,
                "received": received,
                "unknown_frames": self.rx.unknown,
                "own_echoes_dropped": self.own_echoes,
                "error_frames": self.error_frames,
                "sent": sent,
                "injected": self.injected,
                "drained_at_start": self.drained_at_start,
                "last_send_error": self.last_send_error,
            }

    # -- threads ------------------------------------------------------------

    def _send_one(self, msg):
        with self._send_lock:
            return self._send_one_locked(msg)

    def _send_one_locked(self, msg):
        can = python_can()

        with self._lock:
            if not self._enabled[msg.name]:
                return False
            values = dict(self._values[msg.name])
            counter = self._counter[msg.name]
        data = codec.encode(msg.name, values, counter)
        limited = _limited(msg, values)
        try:
            self.bus.send(self._message(can, arbitration_id=msg.frame_id, data=data,
                                        is_extended_id=False))
        except Exception as e:  # a full tx queue or a bus error: counted, the next cycle tries again
            with self._lock:
                self.send_errors[msg.name] += 1
                self.last_send_error = f"{msg.name}: {str(e).strip() or type(e).__name__}"
            return False
        with self._lock:
            self._counter[msg.name] = (counter + 1) & 0x0F
            self.sent[msg.name] += 1
            self.saturated[msg.name] += limited
        return True

    def _message(self, can, **kw):
        """A can.Message to send, stamped when the bus echoes our own frames."""
        if self._own is not None:
            with self._lock:
                kw["channel"], _ = self._own.stamp()
        return can.Message(**kw)

    @property
    def own_echoes(self):
        """Our own frames the bus looped back and the peer dropped (0 on other buses)."""
        return 0 if self._own is None else self._own.echoes

    def _send_loop(self):
        t0 = time.monotonic()
        period = {m.name: m.cycle_time / 1000.0 for m in self.tx_messages}
        due = {m.name: t0 for m in self.tx_messages}
        while not self._stop.is_set():
            now = time.monotonic()
            for m in self.tx_messages:
                if due[m.name] <= now:
                    self._send_one(m)
                    due[m.name] += period[m.name]
                    if due[m.name] <= now:                 # more than a cycle late: skip, no burst
                        missed = math.floor((now - due[m.name]) / period[m.name]) + 1
                        due[m.name] += missed * period[m.name]
                        with self._lock:
                            self.skipped[m.name] += missed
            wait = min(due.values()) - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)

    def _recv_loop(self):
        for t, msg in self._frames(self.bus):
            with self._lock:
                if self._own is not None and self._own.is_echo(msg):
                    continue                          # our own frame, looped back
                if msg.is_error_frame:
                    self.error_frames += 1
                    self._changed.notify_all()
                    continue
                data = b"" if msg.is_remote_frame else bytes(msg.data)
                status, name, values = self.rx.receive(msg.arbitration_id, data, msg.is_extended_id)
                if name is not None:
                    self._rx_stats[name].frame(t, status, values)
                self._changed.notify_all()


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def _parse_set(items):
    values = {}
    for item in items or []:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {item!r}: expected SIGNAL=VALUE")
        try:
            values[name.strip()] = float(text)
        except ValueError:
            values[name.strip()] = text.strip()     # a choice name, checked by set()
    return values


def _summary_lines(rep):
    lines = []
    for name, r in rep["received"].items():
        rej = ", ".join(f"{k} {v}" for k, v in r["rejected"].items() if v)
        mean = f"{r['mean_interval_ms']:.2f} ms" if r["mean_interval_ms"] is not None else "-"
        lines.append(f"  rx {name:<17} {r['accepted']:>7} accepted of {r['received']:>7}"
                     f"  mean interval {mean:>9} (cycle {r['cycle_ms']} ms)" + (f"  rejected: {rej}" if rej else ""))
    for name, s in rep["sent"].items():
        extra = f"  errors {s['errors']}" if s["errors"] else ""
        lines.append(f"  tx {name:<17} {s['frames']:>7} sent{extra}")
    if rep["unknown_frames"]:
        lines.append(f"  unknown ids: {rep['unknown_frames']}")
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="python -m can_dbc.peer",
        description="Run an E2E-protected CAN node of the dct-hil contract for a while and report what it received.")
    parser.add_argument("side", choices=sorted(SIDES), help="tcu: a test TCU; plant: a stand-in plant")
    parser.add_argument("--channel", default="vcan0", help="bus channel (default: %(default)s)")
    parser.add_argument("--interface", default="socketcan",
                        help="python-can interface: socketcan, virtual, udp_multicast, pcan, ... (default: %(default)s)")
    parser.add_argument("--bitrate", type=int, default=None, help="bit rate for interfaces that set it")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds to run (default: %(default)s)")
    parser.add_argument("--set", action="append", default=[], metavar="SIGNAL=VALUE",
                        help="value of a signal this side sends (repeatable)")
    parser.add_argument("--report", default=None, metavar="FILE.json", help="write the JSON report here")
    parser.add_argument("--quiet", action="store_true", help="no summary on stdout")
    args = parser.parse_args(argv)

    def fail(msg):
        print(f"can_dbc.peer: {msg}", file=sys.stderr)
        return 2

    if not (args.duration > 0 and math.isfinite(args.duration)):
        return fail(f"--duration must be a positive number of seconds, got {args.duration}")
    if args.bitrate is not None and args.bitrate <= 0:
        return fail(f"--bitrate must be positive, got {args.bitrate}")
    try:
        values = _parse_set(args.set)
        # check the values before opening the bus
        CanPeer(_NoBus(), side=args.side, values=values, start=False)
    except ValueError as e:
        return fail(str(e))
    if args.report:
        folder = os.path.dirname(os.path.abspath(args.report))
        if not os.path.isdir(folder):
            return fail(f"cannot write report {args.report}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK) or (os.path.exists(args.report) and not os.access(args.report, os.W_OK)):
            return fail(f"cannot write report {args.report}: permission denied")

    try:
        peer = CanPeer.open(args.side, interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                            values=values)
    except (ConnectionError, ValueError) as e:
        return fail(str(e))

    stop = StopSignals(signals=(signal.SIGTERM,)).__enter__()   # SIGTERM: stop (restored below)
    try:
        stop.event.wait(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        stop.__exit__()
        peer.close()
    rep = peer.report()
    rep["interface"] = args.interface
    rep["channel"] = args.channel
    if args.report:
        with open(args.report, "w", encoding="utf-8") as f:
            json.dump(rep, f, indent=2)
            f.write("\n")
    if not args.quiet:
        print(f"{args.side} on {args.interface}:{args.channel} for {rep['duration_s']:.2f} s")
        print("\n".join(_summary_lines(rep)))
        if args.report:
            print(f"report: {args.report}")
    if rep["last_send_error"]:
        print(f"can_dbc.peer: send errors, last: {rep['last_send_error']}", file=sys.stderr)
    return 0


class _NoBus:
    """Stands in for a bus when only the options are checked."""

    def send(self, msg, timeout=None):
        raise ConnectionError("no bus")

    def recv(self, timeout=None):
        return None

    def shutdown(self):
        pass


def _limited(msg, values):
    """How many of ``values`` ``codec.encode`` limits to their signal's DBC range
    (``codec.limit``; a choice name is never out of range)."""
    n = 0
    for sig in codec.payload_signals(msg):
        v = values.get(sig.name)
        if v is not None and not isinstance(v, str) and codec.limit(sig, v) != float(v):
            n += 1
    return n


if __name__ == "__main__":
    sys.exit(main())
