"""The CAN channel of a python-can interface: its default when none is given,
the ``udp_multicast`` channel's group and port, and opening a python-can bus.

Every place that opens a python-can bus (the server's bridge, the TCU stub,
the C TCU node on python-can, the peer, the fuzzer) goes through ``open_bus``,
so a channel means the same everywhere.

``udp_multicast`` channels: ``GROUP`` or ``GROUP:PORT`` (IPv4,
``239.74.163.2:43113``) or ``[GROUP]:PORT`` (IPv6). python-can binds its socket
to the port on every address, and Linux hands each socket the datagrams of
every group any socket of the host joined on that port: two buses on two groups
and one port receive each other's frames. So each bus of a mapping gets its
own port: the first bus's channel without a port is on python-can's port (or
the ``port`` bus option given), a later bus's on ``UDP_DEFAULT_PORT`` + its
index in the mapping (``with_port``), a derived bus on the first bus's group + i and
port + i (``derive``), and two buses on one port are refused (``check_ports``).

A ``virtual`` bus (python-can's in-process bus) keeps at most
``VIRTUAL_BACKLOG_FRAMES`` frames a reader has not taken: python-can's own
queue grows without bound while its reader is starved (hours of a busy
machine), so ``open_bus`` gives it a queue that drops its oldest frame for a
new one and counts it (``backlog_dropped(bus)``); a sender never waits and
every other reader still gets the frame.

A missing channel (``default_channel``): socketcan and virtual ``vcan0``,
udp_multicast python-can's IPv4 group, any other interface the one channel
python-can detects for it; else a one-line error saying what to give.
"""

from __future__ import annotations

import ipaddress
from typing import Any

__all__ = ["ChannelError", "UDP_DEFAULT_GROUP", "UDP_DEFAULT_PORT", "VIRTUAL_BACKLOG_FRAMES",
           "backlog_dropped", "check_ports", "default_channel", "derive", "is_udp_group",
           "open_bus", "split_udp", "udp_channel", "with_port"]

UDP_MULTICAST = "udp_multicast"
#: python-can's IPv4 group and port of udp_multicast (UdpMulticastBus.DEFAULT_GROUP_IPv4, port)
UDP_DEFAULT_GROUP = "239.74.163.2"
UDP_DEFAULT_PORT = 43113
#: channels used when none is given, per interface
DEFAULT_CHANNELS = {"socketcan": "vcan0", "virtual": "vcan0", UDP_MULTICAST: UDP_DEFAULT_GROUP}
#: frames a virtual bus keeps for its reader (about 25 s of a served bus; then the oldest goes)
VIRTUAL_BACKLOG_FRAMES = 65536


class ChannelError(ValueError):
    """A channel that cannot be used, or none to be found (one line)."""


def _group(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(text)
    except ValueError:
        return None


def split_udp(channel: str) -> tuple[str, int | None]:
    """(group, port or None) of a udp_multicast channel; ChannelError (one line)
    for a port that is not 1..65535 or an address that is not a multicast group."""
    text = str(channel).strip()
    port_text = None
    if text.startswith("["):
        host, sep, rest = text[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise ChannelError(f"udp_multicast channel {channel!r}: write [IPv6 GROUP]:PORT")
        text, port_text = host, (rest[1:] if rest else None)
    elif text.count(":") == 1:
        text, port_text = text.split(":")
    address = _group(text)
    if address is None or not address.is_multicast:
        raise ChannelError(f"udp_multicast channel {channel!r}: {text!r} is not a multicast group "
                           f"(IPv4 224.0.0.0/4, e.g. {UDP_DEFAULT_GROUP}, or IPv6 ff00::/8)")
    port = None
    if port_text is not None:
        try:
            port = int(port_text)
        except ValueError:
            port = -1
        if not 1 <= port <= 65535:
            raise ChannelError(f"udp_multicast channel {channel!r}: port {port_text!r} is not 1..65535")
    return str(address), port


def udp_channel(group: str, port: int) -> str:
    """The channel text of ``group`` on ``port`` (IPv6 in brackets)."""
    return f"[{group}]:{port}" if ":" in group else f"{group}:{port}"


def is_udp_group(channel: str) -> bool:
    """Whether ``channel`` is written as a multicast group (with or without port)."""
    try:
        split_udp(channel)
    except ChannelError:
        return False
    return True


def with_port(channel: str, index: int) -> str:
    """A udp_multicast channel with its port: as given, else ``UDP_DEFAULT_PORT``
    + ``index`` (the bus's index in the mapping: the first bus keeps
    python-can's port)."""
    group, port = split_udp(channel)
    return udp_channel(group, UDP_DEFAULT_PORT + index if port is None else port)


def derive(first: str, index: int) -> str:
    """The udp_multicast channel of the ``index``-th bus when only the first's is
    given: group + index on port + index."""
    group, port = split_udp(first)
    return udp_channel(str(ipaddress.ip_address(group) + index),
                       (UDP_DEFAULT_PORT if port is None else port) + index)


def check_ports(channels: dict[str, str], where: str) -> None:
    """ChannelError (one line) when two buses' udp_multicast channels share a port."""
    seen: dict[int, str] = {}
    for name, channel in channels.items():
        if not is_udp_group(channel):
            continue
        group, port = split_udp(channel)
        port = UDP_DEFAULT_PORT if port is None else port
        if port in seen:
            raise ChannelError(f"{where}: buses {seen[port]!r} and {name!r} are both on udp_multicast "
                               f"port {port}, so each would get the other's frames: give each bus its "
                               f"own port (--bus {name}={udp_channel(group, port + 1)})")
        seen[port] = name


def default_channel(interface: str | None) -> str:
    """The channel used when the command line gives none, for ``interface``
    (None: the server's choice, vcan0 if it is a CAN network interface)."""
    if interface is None or interface in DEFAULT_CHANNELS:
        return DEFAULT_CHANNELS.get(interface or "socketcan")
    from can_dbc.python_can import python_can

    can = python_can()
    try:
        found = [c.get("channel") for c in can.detect_available_configs(interfaces=[interface])]
    except Exception:  # python-can's detection raises many kinds per backend
        found = []
    found = [str(c) for c in found if c is not None]
    if len(found) == 1:
        return found[0]
    if found:
        raise ChannelError(f"interface {interface}: give --channel, one of {', '.join(found)} "
                           f"(python-can found {len(found)})")
    raise ChannelError(f"interface {interface}: give --channel with the python-can channel of the "
                       f"device (python-can found none on this host)")


def bus_arguments(interface: str, channel: str, **kwargs: Any) -> tuple[str, dict[str, Any]]:
    """(channel, keyword arguments) for ``can.Bus``: a udp_multicast channel's
    port goes to python-can's ``port``."""
    if interface == UDP_MULTICAST:
        group, port = split_udp(channel)
        if port is not None:
            kwargs["port"] = port
        return group, kwargs
    return channel, kwargs


def open_bus(interface: str, channel: str, **kwargs: Any) -> Any:
    """``can.Bus`` of ``interface`` on ``channel``; ConnectionError (one line,
    naming interface and channel) when python-can cannot open it."""
    from can_dbc.python_can import python_can

    can = python_can()
    try:
        ch, kw = bus_arguments(interface, channel, **kwargs)
        bus = can.Bus(interface=interface, channel=ch, **kw)
    except Exception as e:  # python-can raises many kinds (CanError, OSError, ImportError, ...)
        text = " ".join(str(e).split()) or type(e).__name__
        raise ConnectionError(f"cannot open {interface} bus on channel {channel}: {text}") from None
    if interface == "virtual" and not kwargs.get("rx_queue_size"):
        _bound_backlog(bus, VIRTUAL_BACKLOG_FRAMES)
    return bus


def _dropping_queue(maxsize: int) -> Any:
    import queue

    class DroppingQueue(queue.Queue):
        def __init__(self, maxsize: int) -> None:
            super().__init__(maxsize)
            self.dropped = 0

        def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
            with self.not_full:
                if self._qsize() >= self.maxsize:
                    self._get()                   # the oldest frame: of another time
                    self.dropped += 1
                self._put(item)
                self.unfinished_tasks += 1
                self.not_empty.notify()

    return DroppingQueue(maxsize)


def _bound_backlog(bus: Any, frames: int) -> None:
    """Gives a python-can virtual bus a queue that keeps at most ``frames``
    (python-can 4.x's VirtualBus: its ``queue`` in its channel's list); a bus
    made otherwise is left as it is."""
    try:
        from can.interfaces import virtual
    except ImportError:
        return
    lock = getattr(virtual, "channels_lock", None)
    members = getattr(bus, "channel", None)
    old = getattr(bus, "queue", None)
    if lock is None or not isinstance(members, list) or old is None:
        return
    q = _dropping_queue(frames)
    with lock:
        for i, member in enumerate(members):
            if member is old:
                while True:                       # what was queued meanwhile
                    try:
                        q.put(old.get_nowait())
                    except Exception:  # queue.Empty
                        break
                members[i] = q
                bus.queue = q
                return


def backlog_dropped(bus: Any) -> int:
    """Frames a bus's bounded backlog dropped for newer ones (0: none, or not bounded)."""
    return int(getattr(getattr(bus, "queue", None), "dropped", 0))
