"""The reference TCU in C wired to the plant loop's own rings: the embedded
transport of ``dct-hil demo`` and of the test bench, with no bus and no
Python between the two.

The loop (``rt_loop``) moves a channel's frames through its rx and tx rings
when the channel's transport is a ring (``RT_TRANSPORT_RING``); the C TCU
node (``tcu_stub.c_node``) takes frames in and puts them out through a pair
of frame functions with a context each. Neither knows the other: this
module (the loop's layer, which may use the TCU's below it) hands the node the loop's
``rt_ring_pop_many`` on the channel's tx ring as its source and
``rt_ring_push_many`` on the rx ring as its sink, after checking that the
two sides' frame structs have the same layout. The server runs with
``RingTransport`` (no python-can bus, no bridge thread consuming the rings:
each ring has exactly one producer and one consumer).

    server = embedded_server(channel, driver=..., mapping=...)
    server.start()
    tcu = connect_tcu(server, mapping=server.mapping, time_scale=...)
"""

from __future__ import annotations

import time
from typing import Any

from rt_loop.transport import Transport

__all__ = ["EmbeddedError", "RingTransport", "connect_tcu", "embedded_server", "tcu_priority"]


class EmbeddedError(RuntimeError):
    """The TCU cannot be wired to the loop (one line)."""


class RingTransport(Transport):
    """A loop channel whose frames stay in the loop's rx/tx rings for a node in
    this process to take and fill (``connect_tcu``); no bus, no thread."""

    hard_real_time = False
    interface = "embedded"
    kind = "rings"

    def __init__(self, channel: str, fd: bool = False) -> None:
        self.channel = channel
        self.fd = bool(fd)
        self.rings: tuple[Any, Any, Any, Any] | None = None

    def configure(self, chan: Any, lib: Any) -> None:
        chan.transport = lib.RT_TRANSPORT_RING
        chan.fd = -1
        chan.fd_frames = 1 if self.fd else 0

    def start(self, ffi: Any, lib: Any, loop: Any, index: int = 0) -> None:
        # (ffi, lib, rx ring: node -> loop, tx ring: loop -> node); loop keeps them alive
        self.rings = (ffi, lib, ffi.addressof(loop[0].rx, index), ffi.addressof(loop[0].tx, index))
        self._loop = loop

    def close(self) -> None:
        self.rings = None

    def describe(self) -> str:
        return (f"{self.channel}: the loop's own rings, the reference TCU in C at their other end "
                "(no bus, no Python between them)")


def embedded_server(channel: str, **kwargs: Any) -> Any:
    """A ``rt_loop.server.Server`` on ``channel`` whose buses are the loop's rings
    (``RingTransport``), for ``connect_tcu``; ``kwargs`` as Server's."""
    from rt_loop.server import Server

    class EmbeddedServer(Server):
        def _open_transports(self) -> None:
            for bus in self.mapping.buses:
                self.transports.append(RingTransport(self.bus_channels[bus.name], fd=bool(bus.fd)))
            self.transport = self.transports[0]

    kwargs.setdefault("interface", "virtual")
    return EmbeddedServer(channel, **kwargs)


def tcu_priority(loop_priority: int) -> int:
    """The TCU thread's SCHED_FIFO priority below the loop's (0: the loop itself
    runs on the normal scheduler, so does the TCU)."""
    from tcu_stub.c_node import DEFAULT_PRIORITY

    if loop_priority is None or loop_priority <= 1:
        return 0
    return min(DEFAULT_PRIORITY, int(loop_priority) - 1)


def _check_layout(ffi: Any) -> None:
    from tcu_stub.c_node import frame_layout

    loop = (ffi.sizeof("rt_frame"), ffi.offsetof("rt_frame", "id"), ffi.offsetof("rt_frame", "len"),
            ffi.offsetof("rt_frame", "flags"), ffi.offsetof("rt_frame", "channel"),
            ffi.offsetof("rt_frame", "data"))
    node = frame_layout()
    if loop != node:
        raise EmbeddedError(f"the loop's frames (size and offsets {loop}) and the TCU node's ({node}) "
                            "differ: rebuild both extensions (scripts/setup)")


def _loop_t0_ns(server: Any, timeout_s: float = 10.0) -> int:
    """The loop's first deadline (CLOCK_MONOTONIC ns), once it is ticking."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        t0 = int(server.stats.read().t0_ns)
        if t0 > 0:
            return t0
        time.sleep(0.002)
    raise EmbeddedError(f"the loop did not start ticking within {timeout_s:g} s")


def connect_tcu(server: Any, start: bool = True, **node_kwargs: Any) -> Any:
    """A ``tcu_stub.c_node.CTcuNode`` whose frames are the running server's rings:
    per bus the loop's tx ring as its source and its rx ring as its sink.
    ``node_kwargs``: CTcuNode's (mapping, time_scale, clock, priority, ...)."""
    from tcu_stub.c_node import CTcuNode

    transports = list(getattr(server, "transports", ()))
    if not transports or not all(isinstance(t, RingTransport) and t.rings is not None for t in transports):
        raise EmbeddedError("the server does not run on the loop's rings (embedded_server, started)")
    ffi, lib = transports[0].rings[0], transports[0].rings[1]
    _check_layout(ffi)

    def address(x: Any) -> int:
        return int(ffi.cast("uintptr_t", x))

    pop = address(ffi.addressof(lib, "rt_ring_pop_many"))
    push = address(ffi.addressof(lib, "rt_ring_push_many"))
    names = [b.name for b in server.mapping.buses] if node_kwargs.get("mapping") is not None else ["can"]
    if len(names) != len(transports):
        raise EmbeddedError(f"the TCU has {len(names)} buses, the server {len(transports)}")
    ports = {name: (pop, address(t.rings[3]), push, address(t.rings[2]))
             for name, t in zip(names, transports)}
    node = CTcuNode(ports=ports, start=False, keepalive=server, **node_kwargs)
    if node_kwargs.get("clock", "wall") == "wall":
        # the TCU's periods half a loop tick after a tick: its commands are in
        # the rings well before the next tick reads them, every period the
        # same tick (a period ending just after a tick's read would land a
        # tick late, now and then: a shift a 10 ms message cycle later)
        step_ns = int(round(server.period_s * 1e9))
        node.lock_phase(_loop_t0_ns(server), step_ns, step_ns // 2)
    node.interface, node.channel = "embedded", transports[0].channel
    node.channels = {name: t.channel for name, t in zip(names, transports)} \
        if node_kwargs.get("mapping") is not None else None
    if start:
        node.start()
    return node
