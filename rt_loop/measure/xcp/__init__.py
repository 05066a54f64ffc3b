"""The plant server's XCP on Ethernet slave: measurement (DAQ) and
calibration of the real-time loop from any XCP master (CANape, INCA,
pyxcp, ...), in threads of its own beside the loop.

* ``rt_loop.measure.xcp.protocol``: the XCP 1.4 protocol layer (``Slave``) over a
  ``Memory`` and a ``Daq`` backend: measurement (DAQ), calibration (with
  master block mode, MODIFY_BITS, BUILD_CHECKSUM), STIM, the clock (time
  correlation); seed & key (``compute_key``);
* ``rt_loop.measure.xcp.transport``: XCP on Ethernet framing, the UDP and TCP
  servers (a receiver thread for commands, a sender thread for DTOs);
* ``rt_loop.measure.xcp.loop_backend``: ``LoopBackend``, the loop's memory and DAQ
  (``rt_loop.h``: the ``cal`` ring, ``daq[2]``/``daq_gen``/``daq_ack``,
  ``daq_ring``);
* ``XcpServer`` puts them together: ``start()``, ``stop()``, ``counters()``.

An address is a byte offset in the ``rt_loop`` struct (extension 0); the
A2L file that describes it comes from the caller (``a2l_text``), the master
can upload it (GET_ID 4).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from rt_loop.measure.xcp.protocol import (
    DEFAULT_EVENTS,
    Daq,
    Event,
    Limits,
    Memory,
    Slave,
    read_secret,
)
from rt_loop.measure.xcp.transport import make_server

__all__ = ["XcpServer", "parse_address", "DEFAULT_PORT", "DEFAULT_HOST", "STIM_EVENTS"]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 5555
#: the event channels that take STIM lists: the loop's tick (RT_EVENT_TICK; the
#: A2L declares it DAQ_STIM)
STIM_EVENTS = (0,)


def parse_address(text: str) -> tuple[str, int]:
    """``--xcp [HOST:]PORT`` as (host, port); host 127.0.0.1 by default,
    an IPv6 host in brackets (``[::1]:5555``)."""
    text = text.strip()
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, text
    elif host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(f"--xcp {text!r}: an IPv6 address goes in brackets, [::1]:5555")
    if not host:
        host = DEFAULT_HOST
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"--xcp {text!r}: not [HOST:]PORT") from None
    if not 0 <= number <= 65535:
        raise ValueError(f"--xcp {text!r}: port {number} is not 0..65535")
    return host, number


class XcpServer:
    """The XCP slave of a loop, over UDP or TCP.

    With the loop: ``XcpServer(ffi, lib, loop, host=..., port=...)`` after
    the loop's writable regions are set and ``rt_loop_prepare`` succeeded
    (it resets the rings this uses); ``start()`` before or after the loop
    thread; ``stop()`` ends the session and the threads. Without a loop
    (tests, other producers): ``memory=`` and ``daq=`` backends.

    ``a2l_text``: a callable giving the A2L file's text (asked at each
    upload), ``epk`` its ident (GET_ID 5); ``key_file``: a file holding the
    seed & key secret (CAL/PAG and DAQ locked until unlocked); ``events``:
    the event channels (default: the loop's tick, 10 ms and 100 ms, in
    wall-clock time); ``readable``: the (offset, size) ranges a master may
    read and measure (default: the whole rt_loop); ``ranges``: the writable
    values' limits (``rt_loop.measure.xcp.a2l.calibration_regions``);
    ``stim_events``: the event channels that take STIM lists (default the
    first, the loop's tick: STIM values are written at the next tick
    boundary; ``()``: no STIM)."""

    def __init__(
        self,
        ffi: Any = None,
        lib: Any = None,
        loop: Any = None,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        protocol: str = "udp",
        a2l_text: Callable[[], str | bytes] | None = None,
        a2l_name: str | None = None,
        key_file: str | os.PathLike | None = None,
        name: str = "dct-hil",
        events: Sequence[Event] | None = None,
        memory: Memory | None = None,
        daq: Daq | None = None,
        limits: Limits | None = None,
        readable: Sequence[tuple[int, int]] | None = None,
        ranges: Sequence[tuple] | None = None,
        epk: str | None = None,
        stim_events: Sequence[int] = STIM_EVENTS,
    ) -> None:
        self.backend = None
        if memory is None or daq is None:
            if loop is None:
                raise TypeError("XcpServer needs the loop (ffi, lib, loop) or memory= and daq=")
            from rt_loop.measure.xcp.loop_backend import LoopBackend

            self.backend = LoopBackend(ffi, lib, loop, readable=readable, ranges=ranges)
            memory = memory or self.backend
            daq = daq or self.backend
            limits = limits or self.backend.limits
            events = events or self.backend.events()
        secret = read_secret(key_file) if key_file is not None else None
        self.slave = Slave(
            memory, daq,
            name=name, a2l_name=a2l_name, a2l_text=a2l_text, epk=epk,
            events=events or DEFAULT_EVENTS, secret=secret, limits=limits or Limits(),
            stim_events=stim_events)
        self.server = make_server(protocol, self.slave, daq, host, port)
        self.protocol = self.server.protocol
        self._started = False

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port): the port chosen when 0 was asked for."""
        if self.server.address is None:
            return self.server.host, self.server.port
        return self.server.address[0], self.server.address[1]

    def start(self) -> None:
        """Binds the socket (OSError when taken) and starts the threads."""
        self.server.start()
        self._started = True

    def stop(self) -> None:
        if self._started:
            self.server.stop()
            self._started = False

    def __enter__(self) -> XcpServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def counters(self) -> dict:
        """Everything counted: the transport's (frames, drops, bad frames,
        masters), the protocol's (commands, errors by name, ignored packets
        by reason, DTOs) and the loop backend's (writes, DAQ configurations)."""
        out = {"address": list(self.address), "transport": self.server.counters(),
               "protocol": self.slave.counters()}
        if self.backend is not None:
            out["loop"] = self.backend.counters()
        return out
