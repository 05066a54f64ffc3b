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
frames it could not forward, bus errors, and what python-can's interface can
tell about losses below it (``BusWatch``): the kernel's receive drops of its
UDP socket (``udp_multicast``), controller overflows reported in error frames
(``classify_error_frame``), bus state changes and a backend's overrun counter.
On a bus that loops every frame back to its sender (``udp_multicast``), the
bridge recognises the echoes of its own frames (``OwnFrames``) and drops them
before the ring, counted as ``own_frames_dropped``: they are neither traffic
received nor lost.

Every failure to open a transport is a ``TransportError`` with a one-line
message naming the cause.
"""

from __future__ import annotations

import os
import socket
import stat
import struct
import threading
import time
from typing import Any

from can_dbc.channels import backlog_dropped, open_bus
from can_dbc.own_frames import ECHOING_INTERFACES, OwnFrames
from can_dbc.python_can import python_can

__all__ = [
    "BRIDGE_POLL_S",
    "BRIDGE_WATCH_S",
    "RCVBUF_BYTES",
    "BridgeTransport",
    "BusWatch",
    "OwnFrames",
    "SocketCanTransport",
    "Transport",
    "TransportError",
    "check_interface",
    "classify_error_frame",
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
#: the largest receive buffer one may ask for (the kernel doubles it into an int)
MAX_RCVBUF_BYTES = 1 << 30

#: How long the bridge thread waits for a bus frame before it looks at the
#: loop's tx ring again, s. It must be well below the shortest cycle time of
#: the contract (2 ms) so plant frames leave in the period they were made.
BRIDGE_POLL_S = 0.0005
#: frames moved per ring call
BRIDGE_BATCH = 256
#: How often the bridge thread asks the bus what it lost (the kernel's drop
#: count of its socket, the bus state, a backend's overrun counter), s: a
#: low rate, never per frame
BRIDGE_WATCH_S = 0.1
#: At stop, the longest the bridge keeps reading frames that arrived after
#: the loop's last tick (counted, not forwarded), s
BRIDGE_DRAIN_S = 1.0
#: bytes a queued python-can udp_multicast datagram (one frame, msgpack)
#: costs in a UDP receive buffer (measured on loopback: the default
#: 212992-byte buffer held 256 of them)
UDP_BYTES_PER_FRAME = 832

# Linux socket options (asm-generic values, used by x86, arm, arm64, riscv)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)
_SK_MEMINFO_DROPS = 8         # index of sk_drops in SO_MEMINFO's u32 array (Linux >= 4.13)
_ARPHRD_CAN = 280
_PROC_NET_UDP = ("/proc/net/udp", "/proc/net/udp6")

# SocketCAN identifier flags (linux/can.h), used to pass non-standard frames
# through the 32-bit id of rt_frame exactly as a CAN_RAW socket would
CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF

# SocketCAN error frames (linux/can/error.h): the error classes are bits of
# the identifier, the details are in the 8 data bytes (CAN_ERR_DLC)
CAN_ERR_DLC = 8
CAN_ERR_CRTL = 0x004
#: (bit of the identifier, name) of every error class
CAN_ERR_CLASSES = (
    (0x001, "tx_timeout"), (0x002, "lost_arbitration"), (CAN_ERR_CRTL, "controller"),
    (0x008, "protocol_violation"), (0x010, "transceiver"), (0x020, "no_ack"),
    (0x040, "bus_off"), (0x080, "bus_error"), (0x100, "restarted"), (0x200, "error_counters"),
)
#: (bit of data[1], name) of the controller problems (CAN_ERR_CRTL_*)
CAN_ERR_CRTL_PROBLEMS = (
    (0x01, "rx_overflow"), (0x02, "tx_overflow"), (0x04, "rx_warning"), (0x08, "tx_warning"),
    (0x10, "rx_passive"), (0x20, "tx_passive"), (0x40, "back_to_error_active"),
)
_CAN_ERR_KNOWN = sum(bit for bit, _ in CAN_ERR_CLASSES)

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
    can = python_can()  # only when asked

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
    ``bus_kwargs`` passed to ``can.Bus`` (e.g. ``bitrate``, ``fd``), except the
    bridge's own ``poll_s`` and ``rcvbuf_bytes`` (the receive buffer asked
    for on the bus's UDP sockets, None: the kernel's default). ``None`` picks
    ``default_interface(channel)``; the choice and its reason are in the
    transport's ``chosen_because`` (None when the caller chose). ``fd=True``
    makes a SocketCAN socket carry CAN FD frames (CAN_RAW_FD_FRAMES).
    """
    because = None
    if interface is None:
        interface, because = default_interface(channel)
    check_interface(interface)
    if interface == "socketcan":
        fd = bool(bus_kwargs.pop("fd", False))
        if bus_kwargs:
            names = ", ".join(sorted(bus_kwargs))
            raise TransportError(f"socketcan takes no bus options ({names}); set the bit rate "
                                 f"with 'ip link set {channel} type can bitrate ...'")
        transport: Transport = SocketCanTransport(channel, fd=fd)
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
    ``TransportError``) -> ``configure(chan, lib)`` (fills the transport
    fields of the loop's ``rt_channel``) -> ``rt_loop_prepare`` ->
    ``start(ffi, lib, loop, index)`` (``index``: the channel's index in
    ``rt_loop.chan``) -> the loop runs -> ``stop()`` after the loop has
    returned -> ``close()``. ``fd``: the bus carries CAN FD frames.
    """

    #: "socketcan" or the python-can interface name
    interface: str
    channel: str
    #: True when the loop exchanges frames with the CAN controller itself
    hard_real_time: bool = False
    #: why open_transport picked this interface (None: the caller chose it)
    chosen_because: str | None = None

    #: the bus carries CAN FD frames
    fd: bool = False

    @property
    def kind(self) -> str:
        """How the loop's frames travel, for reports: "socketcan" (the loop's
        own socket), "bridge" (a python-can bus through a thread), or what a
        transport of another kind names itself."""
        return "socketcan" if self.hard_real_time else "bridge"

    def configure(self, chan: Any, lib: Any) -> None:
        raise NotImplementedError

    def start(self, ffi: Any, lib: Any, loop: Any, index: int = 0) -> None:
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
    identifier (unknown ones are counted by the loop) and CAN FD frames also
    on a classic bus (counted as bad length or unknown id), not its own frames,
    has its receive buffer raised to ``RCVBUF_BYTES`` (SO_RCVBUFFORCE when
    the process may, else SO_RCVBUF up to net.core.rmem_max) and SO_RXQ_OVFL
    enabled, so each received frame carries the kernel's count of frames
    dropped on this socket and the loop reports them in ``rx_overflow``.
    """

    hard_real_time = True

    def __init__(self, channel: str, rcvbuf_bytes: int = RCVBUF_BYTES, fd: bool = False) -> None:
        self.interface = "socketcan"
        self.channel = channel
        self.fd = bool(fd)
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
            try:
                # CAN FD frames are received on a classic bus too, so that the loop
                # counts them (bad length, unknown id): without this option the
                # kernel drops them before the socket, uncounted
                sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, 1)
            except (OSError, AttributeError) as e:
                if self.fd:
                    raise TransportError(f"SocketCAN {channel}: CAN FD frames refused: "
                                         f"{getattr(e, 'strerror', None) or e}") from None
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
        return _raise_rcvbuf(sock, want)

    @property
    def rcvbuf_frames(self) -> int:
        """About how many frames the receive buffer holds."""
        return self.rcvbuf_bytes // SKB_BYTES_PER_FRAME

    def fileno(self) -> int:
        if self._sock is None:
            raise TransportError(f"SocketCAN {self.channel}: the socket is closed")
        return self._sock.fileno()

    def configure(self, chan: Any, lib: Any) -> None:
        chan.transport = lib.RT_TRANSPORT_SOCKETCAN
        chan.fd = self.fileno()
        chan.fd_frames = 1 if self.fd else 0

    def start(self, ffi: Any, lib: Any, loop: Any, index: int = 0) -> None:
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
# what a python-can bus can tell about frames lost below the bridge
# --------------------------------------------------------------------------

def classify_error_frame(arbitration_id: int, data: Any) -> tuple[str, ...]:
    """The kinds of a SocketCAN error frame (linux/can/error.h), by name.

    Each error class bit of ``arbitration_id`` gives its name
    (``CAN_ERR_CLASSES``: ``controller``, ``bus_off``, ``restarted``, ...),
    bits beyond the known classes ``unknown_class``; a controller problem
    (``CAN_ERR_CRTL``) adds the problems of ``data[1]``
    (``CAN_ERR_CRTL_PROBLEMS``: ``rx_overflow``, ``tx_overflow``,
    ``rx_passive``, ...). A frame that is not in that layout (not 8 data
    bytes, or no class bit: other interfaces' error frames) is
    ``("unclassified",)``.
    """
    ident = int(arbitration_id) & CAN_EFF_MASK
    data = bytes(data)
    if len(data) != CAN_ERR_DLC or not ident:
        return ("unclassified",)
    kinds = [name for bit, name in CAN_ERR_CLASSES if ident & bit]
    if ident & ~_CAN_ERR_KNOWN:
        kinds.append("unknown_class")
    if ident & CAN_ERR_CRTL:
        kinds += [name for bit, name in CAN_ERR_CRTL_PROBLEMS if data[1] & bit]
    return tuple(kinds)


def proc_udp_drops() -> dict[int, int]:
    """{socket inode: the kernel's drop count} of every UDP socket of this
    network namespace (the last column of /proc/net/udp and /proc/net/udp6)."""
    drops = {}
    for path in _PROC_NET_UDP:
        try:
            with open(path, encoding="ascii") as f:
                next(f, None)  # the header
                for line in f:
                    fields = line.split()
                    if len(fields) >= 13:
                        try:
                            drops[int(fields[9])] = int(fields[-1]) & 0xFFFFFFFF
                        except ValueError:
                            continue
        except OSError:
            continue
    return drops


def _attributes(obj: Any) -> list:
    """The values of ``obj``'s instance attributes (and of lists/tuples among them)."""
    try:
        values = list(vars(obj).values())
    except TypeError:
        return []
    out = []
    for value in values:
        if isinstance(value, (list, tuple)):
            out.extend(value)
        else:
            out.append(value)
    return out


def _bus_udp_sockets(bus: Any) -> list[socket.socket]:
    """Duplicates of the UDP sockets a python-can bus receives on.

    Looked for among the bus's attributes and theirs (python-can 4's
    udp_multicast keeps its socket in ``bus._multicast._socket``), then
    ``bus.fileno()``. Each is ``dup()``ed, so it stays the same socket
    whatever the bus does with its descriptor; the caller closes them.
    """
    fds = []
    for value in _attributes(bus):
        for item in [value, *(() if isinstance(value, socket.socket) else _attributes(value))]:
            if isinstance(item, socket.socket):
                try:
                    fds.append(item.fileno())
                except OSError:
                    continue
    try:
        fds.append(int(bus.fileno()))
    except Exception:  # BusABC.fileno raises NotImplementedError; others anything
        pass
    sockets: list[socket.socket] = []
    seen = set()
    for fd in fds:
        if fd < 0:
            continue  # python-can's "no descriptor"
        try:
            st = os.fstat(fd)
        except OSError:
            continue
        if not stat.S_ISSOCK(st.st_mode) or (st.st_dev, st.st_ino) in seen:
            continue
        seen.add((st.st_dev, st.st_ino))
        try:
            sock = socket.socket(fileno=os.dup(fd))
        except OSError:
            continue
        if sock.family in (socket.AF_INET, socket.AF_INET6) and sock.type == socket.SOCK_DGRAM:
            sockets.append(sock)
        else:
            sock.close()
    return sockets


def _raise_rcvbuf(sock: socket.socket, want: int) -> int:
    """Raises a socket's receive buffer; returns what the kernel granted (bytes)."""
    for option in (_SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, want)
            break
        except OSError:
            continue  # SO_RCVBUFFORCE needs CAP_NET_ADMIN
    return sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)


def _implements_state(bus: Any, can: Any) -> bool:
    """Whether the interface reports a bus state (python-can's default always says active)."""
    prop = getattr(type(bus), "state", None)
    if prop is None:
        return "state" in getattr(bus, "__dict__", {})
    return prop is not getattr(getattr(can, "BusABC", None), "state", None)


def _state_name(state: Any) -> str:
    name = getattr(state, "name", None)
    if isinstance(name, str):
        return name.lower()
    return "unknown" if state is None else _one_line(state).lower()


class BusWatch:
    """What a python-can bus can tell about frames lost below it, read at a low rate.

    Made on the open bus; ``poll()`` (the bridge thread calls it every
    ``BRIDGE_WATCH_S``, never per frame) reads, ``counters()`` reports:

    * ``rx_kernel_drops``: datagrams the kernel dropped on the bus's UDP
      socket(s) because the receive buffer was full (python-can's
      ``udp_multicast``), since the watch was made: frames that never
      reached python-can. Read per socket with SO_MEMINFO, else from the
      drops column of /proc/net/udp and /proc/net/udp6 by the socket's inode
      (``drops_from`` "auto", "meminfo" or "proc");
      ``kernel_drops_counted`` says whether they can be read. The sockets'
      receive buffers are raised to ``rcvbuf_bytes`` (SO_RCVBUFFORCE when
      the process may, else SO_RCVBUF up to net.core.rmem_max; None leaves
      the kernel's default) and ``rcvbuf_bytes`` / ``rcvbuf_frames`` report
      what the kernel granted (the smallest, with more than one socket).
    * ``bus_state``: ``bus.state`` as "active", "passive" or "error" where
      the interface implements it (None where it does not),
      ``bus_state_changes`` and ``bus_state_transitions``
      ({"active->passive": n, ...}). What the state means is the
      interface's: some (pcan) report the mode they were opened in.
    * ``backend_overruns``: a backend's own overrun counter (Kvaser's
      ``get_stats().overruns``), growth since the watch was made; events,
      not frames (None where the backend has none).

    Failures while reading go to ``on_error`` (one line) and leave the
    figures as they were.
    """

    def __init__(self, bus: Any, can: Any = None, rcvbuf_bytes: int | None = None,
                 drops_from: str = "auto", on_error: Any = None) -> None:
        if drops_from not in ("auto", "meminfo", "proc"):
            raise ValueError(f"drops_from {drops_from!r}: choose auto, meminfo or proc")
        self.bus = bus
        self._on_error = on_error
        self._lock = threading.Lock()
        self.sockets = _bus_udp_sockets(bus)
        self.rcvbuf_bytes: int | None = None
        if self.sockets:
            granted = []
            for sock in self.sockets:
                try:
                    granted.append(_raise_rcvbuf(sock, rcvbuf_bytes) if rcvbuf_bytes
                                   else sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
                except OSError as e:
                    self._error("receive buffer", e)
            self.rcvbuf_bytes = min(granted) if granted else None
        self._inodes = [os.fstat(sock.fileno()).st_ino for sock in self.sockets]
        self.drops_from = drops_from
        if drops_from == "auto":
            self.drops_from = "meminfo" if self.sockets and all(
                self._meminfo_drops(sock) is not None for sock in self.sockets) else "proc"
        self._drops_last = self._read_drops()
        self.kernel_drops_counted = bool(self.sockets) and None not in self._drops_last
        self.rx_kernel_drops = 0

        self._state_reported = _implements_state(bus, can)
        self.bus_state: str | None = None
        self.bus_state_changes = 0
        self.bus_state_transitions: dict[str, int] = {}
        if self._state_reported:
            self.bus_state = self._read_state()

        self._overruns_base = self._read_overruns()
        self.backend_overruns = None if self._overruns_base is None else 0

    # -- reading
    def _error(self, what: str, e: BaseException) -> None:
        if self._on_error is not None:
            self._on_error(f"{what}: {type(e).__name__}: {_one_line(e)}")

    @staticmethod
    def _meminfo_drops(sock: socket.socket) -> int | None:
        size = 4 * (_SK_MEMINFO_DROPS + 1)
        try:
            raw = sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, size)
        except OSError:
            return None
        if len(raw) < size:
            return None  # a kernel before 4.13 has no drop count there
        return struct.unpack_from("=I", raw, 4 * _SK_MEMINFO_DROPS)[0]

    def _read_drops(self) -> list[int | None]:
        if not self.sockets:
            return []
        if self.drops_from == "meminfo":
            return [self._meminfo_drops(sock) for sock in self.sockets]
        table = proc_udp_drops()
        return [table.get(inode) for inode in self._inodes]

    def _read_state(self) -> str | None:
        try:
            return _state_name(self.bus.state)
        except NotImplementedError:
            self._state_reported = False
            return None
        except Exception as e:  # a backend may raise anything
            self._error("bus state", e)
            return self.bus_state

    def _read_overruns(self) -> int | None:
        get_stats = getattr(self.bus, "get_stats", None)
        if not callable(get_stats):
            return None
        try:
            value = getattr(get_stats(), "overruns", None)
            return None if value is None else int(value)
        except Exception:  # no statistics: not counted
            return None

    def poll(self) -> None:
        """Reads the drop counts, the bus state and the overrun counter once."""
        drops = self._read_drops()
        grew = 0
        for i, value in enumerate(drops):
            last = self._drops_last[i]
            if value is not None and last is not None:
                grew += (value - last) & 0xFFFFFFFF  # a 32-bit counter
            if value is not None:
                self._drops_last[i] = value
        state = self._read_state() if self._state_reported else None
        overruns = None
        if self._overruns_base is not None:
            overruns = self._read_overruns()
        with self._lock:
            self.rx_kernel_drops += grew
            if state is not None and state != self.bus_state:
                if self.bus_state is not None:
                    key = f"{self.bus_state}->{state}"
                    self.bus_state_transitions[key] = self.bus_state_transitions.get(key, 0) + 1
                    self.bus_state_changes += 1
                self.bus_state = state
            if overruns is not None:
                self.backend_overruns = max(0, overruns - self._overruns_base)

    def counters(self) -> dict:
        with self._lock:
            return {
                "rx_kernel_drops": self.rx_kernel_drops,
                "kernel_drops_counted": self.kernel_drops_counted,
                "udp_sockets": len(self.sockets),
                "rcvbuf_bytes": self.rcvbuf_bytes,
                "rcvbuf_frames": (None if self.rcvbuf_bytes is None
                                  else self.rcvbuf_bytes // UDP_BYTES_PER_FRAME),
                "bus_state": self.bus_state,
                "bus_state_changes": self.bus_state_changes,
                "bus_state_transitions": dict(self.bus_state_transitions),
                "backend_overruns": self.backend_overruns,
            }

    def close(self) -> None:
        for sock in self.sockets:
            sock.close()


def _check_rcvbuf(rcvbuf_bytes: Any) -> int | None:
    if rcvbuf_bytes is None:
        return None
    if isinstance(rcvbuf_bytes, bool) or not isinstance(rcvbuf_bytes, int) \
            or not 1 <= rcvbuf_bytes <= MAX_RCVBUF_BYTES:
        raise TransportError(f"receive buffer {rcvbuf_bytes!r}: a whole number of bytes from 1 "
                             f"to {MAX_RCVBUF_BYTES} (None: the kernel's default)")
    return rcvbuf_bytes


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
    (``rt_ring_pop_many``); every ``BRIDGE_WATCH_S`` it asks the bus what
    was lost below it (``BusWatch``). Frames that cannot be forwarded are
    counted in ``counters``, never dropped silently:

    * ``rx_ring_full``: received but refused by the full rx ring (the loop
      counts them too, in ``rx_overflow``);
    * ``rx_kernel_drops``: lost below python-can, in the kernel (the UDP
      socket of ``udp_multicast``; ``BusWatch``, with the receive buffer's
      size, the bus state and a backend's overruns);
    * ``rx_error_frames``: error frames, never forwarded (they are no
      commands); ``error_frame_kinds`` counts them by kind
      (``classify_error_frame``), and the controller overflows among them in
      ``rx_overflow_events`` / ``tx_overflow_events``: frames were lost, how
      many the frame does not say;
    * ``rx_remote_frames``, ``rx_fd_frames``: frames that are not data frames
      of classic CAN (not forwarded);
    * ``rx_errors`` / ``tx_errors``: exceptions from ``bus.recv`` /
      ``bus.send`` (``last_error`` holds the latest, one line);
      ``watch_errors``: failures reading what was lost;
    * ``rx_forwarded`` / ``tx_forwarded``: frames moved;
    * ``own_frames_dropped``: on a bus that loops frames back to their sender
      (``ECHOING_INTERFACES``: ``udp_multicast``), the echoes of the frames
      this bridge sent, recognised by ``OwnFrames`` and dropped before the
      ring: not traffic received (the loop would count each as an unknown
      identifier), not lost, not rejected; ``own_echoes_forgotten``: echoes
      awaited and given up (lost below the bridge: the kernel's drops
      include them). Frames of other programs, on this host or not, are
      forwarded as before. Other interfaces do not return a bus's own frames
      (it is opened with receive_own_messages=False): nothing to drop;
    * ``rx_backlog_dropped``: on the in-process ``virtual`` bus, frames its
      bounded backlog dropped for newer ones while this thread was starved
      (``can_dbc.channels.VIRTUAL_BACKLOG_FRAMES``);
    * at stop (the loop has returned): ``rx_left_in_ring``, frames forwarded
      that the loop never read, and ``rx_drained_at_stop``, data frames read
      from the bus after the loop's last tick (for at most
      ``BRIDGE_DRAIN_S``; not forwarded).

    Extended-identifier frames are forwarded with the SocketCAN EFF flag in
    the id, so the loop sees an unknown identifier and counts it.
    ``rcvbuf_bytes``: the receive buffer asked for on the bus's UDP sockets
    (None: the kernel's default).
    """

    hard_real_time = False

    def __init__(self, interface: str, channel: str, poll_s: float = BRIDGE_POLL_S,
                 rcvbuf_bytes: int | None = RCVBUF_BYTES, **bus_kwargs: Any) -> None:
        self.interface = interface
        self.channel = channel
        self.poll_s = float(poll_s)
        self.fd = bool(bus_kwargs.get("fd", False))
        if interface in _NOT_BRIDGED:
            raise TransportError(f"interface {interface}: {_NOT_BRIDGED[interface]}")
        check_interface(interface)
        rcvbuf_bytes = _check_rcvbuf(rcvbuf_bytes)
        can = python_can()  # python-can only for the bridge

        self._can = can
        try:
            self.bus = open_bus(interface, channel, receive_own_messages=False, **bus_kwargs)
        except ConnectionError as e:
            raise TransportError(str(e)) from None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(
            ("rx_forwarded", "tx_forwarded", "rx_ring_full", "rx_error_frames",
             "rx_overflow_events", "tx_overflow_events", "rx_remote_frames", "rx_fd_frames",
             "rx_errors", "tx_errors", "watch_errors", "rx_left_in_ring",
             "rx_drained_at_stop", "own_frames_dropped"), 0)
        self._error_kinds: dict[str, int] = {}
        self.last_error: str | None = None
        #: the echoes of this bridge's frames, on a bus that returns them
        self.own = OwnFrames(channel) if interface in ECHOING_INTERFACES else None
        try:
            self.watch = BusWatch(self.bus, can, rcvbuf_bytes, on_error=self._watch_error)
        except Exception as e:  # the bridge goes on
            self.bus.shutdown()
            raise TransportError(f"python-can {interface} channel {channel}: cannot watch "
                                 f"the bus: {_one_line(e)}") from None

    # -- set-up
    def configure(self, chan: Any, lib: Any) -> None:
        chan.transport = lib.RT_TRANSPORT_RING
        chan.fd = -1
        chan.fd_frames = 1 if self.fd else 0

    def start(self, ffi: Any, lib: Any, loop: Any, index: int = 0) -> None:
        if self._thread is not None:
            raise TransportError("the bridge is already running")
        self._ffi, self._lib = ffi, lib
        self._flag_fd, self._flag_brs = lib.RT_FRAME_FD, lib.RT_FRAME_BRS
        self._rx_ring = ffi.addressof(loop[0].rx, index)
        self._tx_ring = ffi.addressof(loop[0].tx, index)
        self._loop = loop  # keeps the rings alive while the thread runs
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="can-bridge", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Forwards what the loop still queued, counts what came too late, ends the thread.

        Called once the loop has returned: frames left in the rx ring and
        frames still arriving are counted (``rx_left_in_ring``,
        ``rx_drained_at_stop``), the kernel's drops read a last time.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def close(self) -> None:
        self.stop()
        bus, self.bus = getattr(self, "bus", None), None
        try:
            if bus is not None:
                bus.shutdown()
        finally:
            watch = getattr(self, "watch", None)
            if watch is not None:
                watch.close()

    def describe(self) -> str:
        below = ""
        w = self.watch
        if w.sockets:
            size = ("the kernel's default" if w.rcvbuf_bytes is None
                    else f"{w.rcvbuf_bytes // 1024} KiB, about "
                         f"{w.rcvbuf_bytes // UDP_BYTES_PER_FRAME} frames")
            drops = ("kernel drops counted" if w.kernel_drops_counted
                     else "kernel drops NOT counted")
            below += f"; UDP receive buffer {size}; {drops}"
        if w.bus_state is not None:
            below += f"; bus state {w.bus_state}, watched every {BRIDGE_WATCH_S * 1e3:g} ms"
        return (f"{self.channel} via python-can {self.interface} through a bridge thread "
                "(soft real time: frames wait for a Python thread between the bus and the "
                f"loop; for hard real time use SocketCAN{below})")

    @property
    def counters(self) -> dict:
        with self._lock:
            out = dict(self._counts)
            out["error_frame_kinds"] = dict(self._error_kinds)
        own = self.own
        out["own_echoes_forgotten"] = 0 if own is None else own.forgotten
        bus = self.bus
        out["rx_backlog_dropped"] = 0 if bus is None else backlog_dropped(bus)
        out.update(self.watch.counters())
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

    def _watch_error(self, line: str) -> None:
        self.last_error = f"watching the bus: {line}"
        self._count("watch_errors")

    def _on_error_frame(self, msg: Any) -> None:
        kinds = classify_error_frame(msg.arbitration_id, msg.data)
        with self._lock:
            self._counts["rx_error_frames"] += 1
            for kind in kinds:
                self._error_kinds[kind] = self._error_kinds.get(kind, 0) + 1
            if "rx_overflow" in kinds:
                self._counts["rx_overflow_events"] += 1
            if "tx_overflow" in kinds:
                self._counts["tx_overflow_events"] += 1

    def _own_echo(self, msg: Any) -> bool:
        """Counts the echo of a frame this bridge sent; False for any other frame."""
        if self.own is not None and self.own.is_echo(msg):
            self._count("own_frames_dropped")
            return True
        return False

    def _not_forwarded(self, msg: Any) -> bool:
        """Counts a frame that is not a classic CAN data frame; False for one that is."""
        if msg.is_error_frame:
            self._on_error_frame(msg)
        elif msg.is_remote_frame:
            self._count("rx_remote_frames")
        elif not self.fd and (msg.is_fd or msg.dlc > 8 or len(msg.data) > 8):
            self._count("rx_fd_frames")
        elif len(msg.data) > 64:
            self._count("rx_fd_frames")
        else:
            return False
        return True

    def _run(self) -> None:
        ffi = self._ffi
        rxbuf = ffi.new("rt_frame[]", BRIDGE_BATCH)
        txbuf = ffi.new("rt_frame[]", BRIDGE_BATCH)
        stopping = False
        next_watch = time.monotonic() + BRIDGE_WATCH_S
        while True:
            if self._stop.is_set():
                stopping = True  # one last pass, then out
            self._forward_tx(txbuf)
            if stopping:
                break
            if not self._forward_rx(rxbuf):
                time.sleep(self.poll_s)  # the bus failed: do not spin
            now = time.monotonic()
            if now >= next_watch:
                self._poll_watch()
                next_watch = now + BRIDGE_WATCH_S
        self._count_unread()
        self._poll_watch()

    def _poll_watch(self) -> None:
        try:
            self.watch.poll()
        except Exception as e:  # counted; the bus is closed next
            self._watch_error(f"{type(e).__name__}: {_one_line(e)}")

    def _count_unread(self) -> None:
        """At stop: frames the loop never read, and those arriving after its last tick."""
        ring = self._rx_ring
        self._count("rx_left_in_ring", (int(ring.head) - int(ring.tail)) & 0xFFFFFFFF)
        deadline = time.monotonic() + BRIDGE_DRAIN_S
        drained = 0
        try:
            while time.monotonic() < deadline:
                msg = self.bus.recv(timeout=0.0)
                if msg is None:
                    break
                if self._own_echo(msg):
                    continue
                if not self._not_forwarded(msg):
                    drained += 1
        except Exception as e:
            self._error("rx_errors", e)
        self._count("rx_drained_at_stop", drained)

    def _forward_rx(self, buf: Any) -> bool:
        """Moves up to one batch from the bus into the rx ring; False on a bus error."""
        bus, ffi = self.bus, self._ffi
        n = 0
        timeout = self.poll_s
        try:
            while n < BRIDGE_BATCH:
                msg = bus.recv(timeout=timeout)
                if msg is None:
                    break
                timeout = 0.0
                if self._own_echo(msg) or self._not_forwarded(msg):
                    continue
                f = buf[n]
                f.id = (msg.arbitration_id & CAN_EFF_MASK) | CAN_EFF_FLAG \
                    if msg.is_extended_id else msg.arbitration_id & 0x7FF
                data = bytes(msg.data)
                f.len = len(data)
                f.flags = ((self._flag_fd if msg.is_fd else 0)
                           | (self._flag_brs if msg.is_fd and msg.bitrate_switch else 0))
                ffi.memmove(f.data, data, len(data))
                n += 1
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
        lib, ffi, can, own = self._lib, self._ffi, self._can, self.own
        while True:
            n = lib.rt_ring_pop_many(self._tx_ring, buf, BRIDGE_BATCH)
            for i in range(n):
                f = buf[i]
                is_fd = bool(int(f.flags) & self._flag_fd)
                length = min(int(f.len), 64 if is_fd else 8)
                ident = int(f.id)
                channel, seq = self.channel, None
                if own is not None:
                    channel, seq = own.stamp()
                msg = can.Message(arbitration_id=ident & CAN_EFF_MASK,
                                  is_extended_id=bool(ident & CAN_EFF_FLAG),
                                  data=ffi.unpack(ffi.cast("char *", f.data), length),
                                  dlc=length, is_rx=False, channel=channel, is_fd=is_fd,
                                  bitrate_switch=bool(int(f.flags) & self._flag_brs))
                try:
                    self.bus.send(msg, timeout=0.005)
                except Exception as e:  # counted, the next frame is tried
                    if seq is not None:
                        own.unsent(seq)
                    self._error("tx_errors", e)
                else:
                    self._count("tx_forwarded")
            if n < BRIDGE_BATCH:
                return


def _one_line(text: Any) -> str:
    return " ".join(str(text).split()) or type(text).__name__
