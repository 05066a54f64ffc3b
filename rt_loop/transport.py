"""CAN transports of the plant server: where the loop's frames come from and go to.

One interface, two backends (chosen by ``open_transport``; python-can is
imported only when a bridge is opened):

``SocketCanTransport``  hard real time. A CAN_RAW socket (Python's socket
    module) bound to a Linux CAN network interface (``can0``, ``vcan0``);
    the C loop reads and writes its file descriptor itself, inside the tick,
    without Python (``RT_TRANSPORT_SOCKETCAN``).

``BridgeTransport``  soft real time. Any other python-can interface
    (``virtual``, ``udp_multicast``, ``pcan``, ``kvaser``, ...): a Python
    thread moves frames between a ``can.Bus`` and the loop's rx/tx rings
    (``RT_TRANSPORT_RING``). The loop itself keeps its timing, but a frame
    waits in a ring until the bridge thread wakes (every ``poll_s``, 0.5 ms by
    default, or as soon as the bus has a frame) and the thread competes for
    the GIL with the rest of the process, so the delay from the bus to the
    tick (and back) is not bounded.

Nothing is lost silently: frames the kernel dropped (SO_RXQ_OVFL) and frames
refused by a full ring are counted by the loop (``rx_overflow``,
``tx_dropped``); the bridge adds its own counters (``BridgeTransport.counters``):
frames it could not forward, bus errors, error frames.

Every failure to open a transport is a ``TransportError`` with a one-line
message naming the cause.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from typing import Any

__all__ = [
    "BRIDGE_POLL_S",
    "RCVBUF_BYTES",
    "BridgeTransport",
    "SocketCanTransport",
    "Transport",
    "TransportError",
    "check_interface",
    "default_interface",
    "is_can_netdev",
    "open_transport",
]

#: Receive buffer asked for on the CAN_RAW socket. The kernel's default
#: (net.core.rmem_default, 212992 bytes) holds only about 280 frames, because
#: every queued frame costs a whole socket buffer (about 760 bytes), not its
#: 16 bytes: one late tick on a busy bus, or a burst, and frames are lost.
#: The kernel doubles the value asked for: 8 MiB gives 16 MiB, about 22 000
#: frames, enough for a 10 000-frame burst or half a minute of the TCU's
#: normal traffic (about 700 frames/s) while the loop catches up.
#: rt_loop_prepare asks for the same size again (it owns the socket from
#: then on); without CAP_NET_ADMIN both are capped at net.core.rmem_max.
RCVBUF_BYTES = 8 * 1024 * 1024
#: bytes a queued CAN frame costs in a socket receive buffer (measured: the
#: default 212992-byte buffer held 280 frames)
SKB_BYTES_PER_FRAME = 760

#: How long the bridge thread waits for a bus frame before it looks at the
#: loop's tx ring again, s. It must be well below the shortest cycle time of
#: the contract (2 ms) so plant frames leave in the period they were made.
BRIDGE_POLL_S = 0.0005
#: frames moved per ring call
BRIDGE_BATCH = 256

# Linux socket options (asm-generic values, used by x86, arm, arm64, riscv)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_ARPHRD_CAN = 280

# SocketCAN identifier flags (linux/can.h), used to pass non-standard frames
# through the 32-bit id of dct_can_frame exactly as a CAN_RAW socket would
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF

# python-can interfaces that cannot be bridged (the real-time path owns them)
_NOT_BRIDGED = {"socketcan": "use --interface socketcan (the loop reads the socket itself)"}


class TransportError(RuntimeError):
    """A transport cannot be opened or used; ``str()`` is one line naming the cause."""


# --------------------------------------------------------------------------
# choosing
# --------------------------------------------------------------------------

def is_can_netdev(channel: str) -> bool:
    """Whether ``channel`` is a Linux CAN network interface (can0, vcan0, ...)."""
    if not channel or "/" in channel or channel in (".", ".."):
        return False
    try:
        with open(f"/sys/class/net/{channel}/type", encoding="ascii") as f:
            return int(f.read().strip()) == _ARPHRD_CAN
    except (OSError, ValueError):
        return False


def default_interface(channel: str) -> tuple[str, str]:
    """The interface used when none is given, and why (one line for the user).

    SocketCAN if ``channel`` exists as a CAN network interface, else
    python-can's ``virtual`` bus (in this process only).
    """
    if is_can_netdev(channel):
        return "socketcan", f"{channel} is a CAN network interface"
    return "virtual", (f"no CAN network interface {channel} on this host; python-can's "
                       "virtual bus reaches peers in this process only")


def valid_interfaces() -> list[str]:
    """Every interface name ``open_transport`` accepts."""
    import can  # noqa: PLC0415 (only when asked)

    return sorted(set(can.interfaces.VALID_INTERFACES) | {"socketcan"})


def check_interface(interface: str) -> str:
    """``interface`` if known, else a one-line ``TransportError`` listing the known ones."""
    if interface == "socketcan":
        return interface
    try:
        names = valid_interfaces()
    except ImportError as e:
        raise TransportError(f"interface {interface}: python-can is not installed ({e})") from None
    if interface not in names:
        raise TransportError(f"unknown interface {interface!r}; python-can knows: "
                             + ", ".join(names))
    return interface


def open_transport(interface: str | None, channel: str, **bus_kwargs: Any) -> Transport:
    """The transport for ``interface`` on ``channel``.

    ``"socketcan"`` gives a ``SocketCanTransport`` (hard real time); any
    other python-can interface a ``BridgeTransport`` (soft real time), with
    ``bus_kwargs`` passed to ``can.Bus`` (e.g. ``bitrate``). ``None`` picks
    ``default_interface(channel)``; the choice and its reason are in the
    transport's ``chosen_because`` (None when the caller chose).
    """
    because = None
    if interface is None:
        interface, because = default_interface(channel)
    check_interface(interface)
    if interface == "socketcan":
        if bus_kwargs:
            names = ", ".join(sorted(bus_kwargs))
            raise TransportError(f"socketcan takes no bus options ({names}); set the bit rate "
                                 f"with 'ip link set {channel} type can bitrate ...'")
        transport: Transport = SocketCanTransport(channel)
    else:
        transport = BridgeTransport(interface, channel, **bus_kwargs)
    transport.chosen_because = because
    return transport


# --------------------------------------------------------------------------
# the interface
# --------------------------------------------------------------------------

class Transport:
    """What the server needs from a transport.

    Life cycle: construct (opens the socket or bus, may raise
    ``TransportError``) -> ``configure(cfg)`` (fills ``rt_config``) ->
    ``rt_loop_prepare`` -> ``start(ffi, lib, loop)`` -> the loop runs ->
    ``stop()`` after the loop has returned -> ``close()``.
    """

    #: "socketcan" or the python-can interface name
    interface: str
    channel: str
    #: True when the loop exchanges frames with the CAN controller itself
    hard_real_time: bool = False
    #: why open_transport picked this interface (None: the caller chose it)
    chosen_because: str | None = None

    def configure(self, cfg: Any, lib: Any) -> None:
        raise NotImplementedError

    def start(self, ffi: Any, lib: Any, loop: Any) -> None:
        """Called after rt_loop_prepare, before the loop thread starts."""

    def stop(self) -> None:
        """Called after the loop thread has returned."""

    def close(self) -> None:
        raise NotImplementedError

    def describe(self) -> str:
        """One line for the start-up banner."""
        raise NotImplementedError

    @property
    def counters(self) -> dict:
        """Counts kept by the transport itself (the loop's are in rt_stats)."""
        return {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
        self.close()


# --------------------------------------------------------------------------
# SocketCAN: the loop owns the socket
# --------------------------------------------------------------------------

class SocketCanTransport(Transport):
    """A CAN_RAW socket on a Linux CAN interface, read and written by the C loop.

    Hard real time: no Python between the controller and the tick. The
    socket is non-blocking (the loop drains it every tick), receives every
    identifier (unknown ones are counted by the loop), not its own frames,
    has its receive buffer raised to ``RCVBUF_BYTES`` (SO_RCVBUFFORCE when
    the process may, else SO_RCVBUF up to net.core.rmem_max) and SO_RXQ_OVFL
    enabled, so each received frame carries the kernel's count of frames
    dropped on this socket and the loop reports them in ``rx_overflow``.
    """

    hard_real_time = True

    def __init__(self, channel: str, rcvbuf_bytes: int = RCVBUF_BYTES) -> None:
        self.interface = "socketcan"
        self.channel = channel
        self._sock: socket.socket | None = None
        af_can = getattr(socket, "AF_CAN", None)
        if af_can is None or not hasattr(socket, "CAN_RAW"):
            raise TransportError("SocketCAN is not available: this Python has no AF_CAN "
                                 "(Linux only); use a python-can interface, e.g. "
                                 "--interface virtual")
        try:
            sock = socket.socket(af_can, socket.SOCK_RAW, socket.CAN_RAW)
        except OSError as e:
            raise TransportError(f"SocketCAN is not available: the kernel refused an AF_CAN "
                                 f"socket ({e.strerror}); this kernel has no CAN support: use "
                                 "a kernel with CAN (see the VM note) or --interface virtual"
                                 ) from None
        try:
            try:
                sock.bind((channel,))
            except OSError as e:
                if not os.path.exists(f"/sys/class/net/{channel}"):
                    hint = (f"no network interface {channel} (create it: ip link add dev "
                            f"{channel} type vcan && ip link set up {channel})")
                elif not is_can_netdev(channel):
                    hint = f"{channel} is not a CAN interface"
                else:
                    hint = e.strerror or str(e)
                raise TransportError(f"SocketCAN {channel}: cannot bind: {hint}") from None
            sock.setblocking(False)
            self.rcvbuf_bytes = self._raise_rcvbuf(sock, rcvbuf_bytes)
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
                self.drops_counted = True
            except OSError:
                self.drops_counted = False
        except BaseException:
            sock.close()
            raise
        self._sock = sock

    @staticmethod
    def _raise_rcvbuf(sock: socket.socket, want: int) -> int:
        """Raise the receive buffer; returns what the kernel granted (bytes)."""
        for option in (_SO_RCVBUFFORCE, socket.SO_RCVBUF):
            try:
                sock.setsockopt(socket.SOL_SOCKET, option, want)
                break
            except OSError:
                continue  # SO_RCVBUFFORCE needs CAP_NET_ADMIN
        return sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    @property
    def rcvbuf_frames(self) -> int:
        """About how many frames the receive buffer holds."""
        return self.rcvbuf_bytes // SKB_BYTES_PER_FRAME

    def fileno(self) -> int:
        if self._sock is None:
            raise TransportError(f"SocketCAN {self.channel}: the socket is closed")
        return self._sock.fileno()

    def configure(self, cfg: Any, lib: Any) -> None:
        cfg.transport = lib.RT_TRANSPORT_SOCKETCAN
        cfg.fd = self.fileno()

    def start(self, ffi: Any, lib: Any, loop: Any) -> None:
        # rt_loop_prepare has set the buffer sizes again: report what holds now
        if self._sock is not None:
            self.rcvbuf_bytes = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def describe(self) -> str:
        drops = "kernel drops counted" if self.drops_counted else "kernel drops NOT counted"
        return (f"{self.channel} via SocketCAN CAN_RAW (hard real time: the loop reads the "
                f"socket itself; receive buffer {self.rcvbuf_bytes // 1024} KiB, about "
                f"{self.rcvbuf_frames} frames; {drops})")

    @property
    def counters(self) -> dict:
        return {"rcvbuf_bytes": self.rcvbuf_bytes, "rcvbuf_frames": self.rcvbuf_frames}


# --------------------------------------------------------------------------
# bridge: a Python thread between a python-can Bus and the loop's rings
# --------------------------------------------------------------------------

class BridgeTransport(Transport):
    """Any python-can interface, bridged to the loop through its rx/tx rings.

    Soft real time: the loop keeps its own timing, but frames pass through a
    Python thread (``poll_s`` wake-ups, the GIL, python-can's own buffering),
    so their delay between the bus and the tick is not bounded. Use
    ``SocketCanTransport`` for hard real time.

    The thread receives in batches (the first ``bus.recv`` waits at most
    ``poll_s``, the rest do not wait), pushes them with
    ``rt_ring_push_many``, then sends everything the loop queued
    (``rt_ring_pop_many``). Frames that cannot be forwarded are counted in
    ``counters``, never dropped silently:

    * ``rx_ring_full``: received but refused by the full rx ring;
    * ``rx_error_frames``, ``rx_remote_frames``, ``rx_fd_frames``: bus
      frames that are not data frames of classic CAN (not forwarded);
    * ``rx_errors`` / ``tx_errors``: exceptions from ``bus.recv`` /
      ``bus.send`` (``last_error`` holds the latest, one line);
    * ``rx_forwarded`` / ``tx_forwarded``: frames moved.

    Extended-identifier frames are forwarded with the SocketCAN EFF flag in
    the id, so the loop sees an unknown identifier and counts it.
    """

    hard_real_time = False

    def __init__(self, interface: str, channel: str, poll_s: float = BRIDGE_POLL_S,
                 **bus_kwargs: Any) -> None:
        self.interface = interface
        self.channel = channel
        self.poll_s = float(poll_s)
        if interface in _NOT_BRIDGED:
            raise TransportError(f"interface {interface}: {_NOT_BRIDGED[interface]}")
        check_interface(interface)
        import can  # noqa: PLC0415 (python-can only for the bridge)

        self._can = can
        try:
            self.bus = can.Bus(interface=interface, channel=channel,
                               receive_own_messages=False, **bus_kwargs)
        except (can.CanError, ImportError, OSError, ValueError, TypeError) as e:
            raise TransportError(f"python-can {interface} channel {channel}: cannot open "
                                 f"the bus: {_one_line(e)}") from None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(
            ("rx_forwarded", "tx_forwarded", "rx_ring_full", "rx_error_frames",
             "rx_remote_frames", "rx_fd_frames", "rx_errors", "tx_errors"), 0)
        self.last_error: str | None = None

    # -- set-up
    def configure(self, cfg: Any, lib: Any) -> None:
        cfg.transport = lib.RT_TRANSPORT_RING
        cfg.fd = -1

    def start(self, ffi: Any, lib: Any, loop: Any) -> None:
        if self._thread is not None:
            raise TransportError("the bridge is already running")
        self._ffi, self._lib = ffi, lib
        self._rx_ring = ffi.addressof(loop[0], "rx")
        self._tx_ring = ffi.addressof(loop[0], "tx")
        self._loop = loop  # keeps the rings alive while the thread runs
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="can-bridge", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Forwards what the loop still queued, then ends the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def close(self) -> None:
        self.stop()
        bus, self.bus = getattr(self, "bus", None), None
        if bus is not None:
            bus.shutdown()

    def describe(self) -> str:
        return (f"{self.channel} via python-can {self.interface} through a bridge thread "
                "(soft real time: frames wait for a Python thread between the bus and the "
                "loop; for hard real time use SocketCAN)")

    @property
    def counters(self) -> dict:
        with self._lock:
            out = dict(self._counts)
        out["last_error"] = self.last_error
        return out

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- the thread
    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._counts[key] += n

    def _error(self, key: str, e: BaseException) -> None:
        what = "receive" if key.startswith("rx") else "send"
        self.last_error = f"{what}: {type(e).__name__}: {_one_line(e)}"
        self._count(key)

    def _run(self) -> None:
        ffi = self._ffi
        rxbuf = ffi.new("dct_can_frame[]", BRIDGE_BATCH)
        txbuf = ffi.new("dct_can_frame[]", BRIDGE_BATCH)
        stopping = False
        while True:
            if self._stop.is_set():
                stopping = True  # one last pass, then out
            self._forward_tx(txbuf)
            if stopping:
                break
            if not self._forward_rx(rxbuf):
                time.sleep(self.poll_s)  # the bus failed: do not spin

    def _forward_rx(self, buf: Any) -> bool:
        """Moves up to one batch from the bus into the rx ring; False on a bus error."""
        bus, ffi = self.bus, self._ffi
        n, skipped = 0, None
        timeout = self.poll_s
        try:
            while n < BRIDGE_BATCH:
                msg = bus.recv(timeout=timeout)
                if msg is None:
                    break
                timeout = 0.0
                if msg.is_error_frame:
                    skipped = "rx_error_frames"
                elif msg.is_remote_frame:
                    skipped = "rx_remote_frames"
                elif msg.is_fd or msg.dlc > 8 or len(msg.data) > 8:
                    skipped = "rx_fd_frames"
                else:
                    f = buf[n]
                    f.id = (msg.arbitration_id & CAN_EFF_MASK) | CAN_EFF_FLAG \
                        if msg.is_extended_id else msg.arbitration_id & 0x7FF
                    data = bytes(msg.data)
                    f.len = len(data)
                    ffi.memmove(f.data, data, len(data))
                    n += 1
                    continue
                self._count(skipped)
        except Exception as e:  # a python-can backend may raise anything
            self._error("rx_errors", e)
            self._push(buf, n)
            return False
        self._push(buf, n)
        return True

    def _push(self, buf: Any, n: int) -> None:
        if n:
            pushed = self._lib.rt_ring_push_many(self._rx_ring, buf, n)
            self._count("rx_forwarded", pushed)
            if pushed < n:
                self._count("rx_ring_full", n - pushed)

    def _forward_tx(self, buf: Any) -> None:
        lib, ffi, can = self._lib, self._ffi, self._can
        while True:
            n = lib.rt_ring_pop_many(self._tx_ring, buf, BRIDGE_BATCH)
            for i in range(n):
                f = buf[i]
                length = min(int(f.len), 8)
                ident = int(f.id)
                msg = can.Message(arbitration_id=ident & CAN_EFF_MASK,
                                  is_extended_id=bool(ident & CAN_EFF_FLAG),
                                  data=ffi.unpack(ffi.cast("char *", f.data), length),
                                  dlc=length, is_rx=False, channel=self.channel)
                try:
                    self.bus.send(msg, timeout=0.005)
                except Exception as e:  # counted, the next frame is tried
                    self._error("tx_errors", e)
                else:
                    self._count("tx_forwarded")
            if n < BRIDGE_BATCH:
                return


def _one_line(text: Any) -> str:
    return " ".join(str(text).split()) or type(text).__name__
