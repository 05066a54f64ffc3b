"""The echoes of a node's own frames on a bus that loops them back.

python-can's ``udp_multicast`` bus delivers every frame to every member of
its multicast group on the host, the sender included, although the bus was
opened with ``receive_own_messages=False``. A node that counted those as
received traffic would see its own transmissions as unknown identifiers.
``OwnFrames`` stamps each frame a node sends and recognises the echoes; the
plant server's bridge (``rt_loop.transport``) and the test peer
(``can_dbc.peer``, and through it the TCU node) drop them before they are
counted, and count them apart.
"""

from __future__ import annotations

import secrets
from typing import Any

__all__ = ["ECHOING_INTERFACES", "OWN_FRAMES_AWAITED_MAX", "OWN_FRAMES_REORDER", "OwnFrames",
           "is_echoing_bus"]

#: python-can interfaces that deliver a bus's own frames back to it although
#: it was opened with receive_own_messages=False, and carry each frame's
#: ``Message.channel`` from the sender to every receiver (``OwnFrames``)
ECHOING_INTERFACES = ("udp_multicast",)
#: an echo is awaited for at most this many of the bridge's latest frames
#: (far more than can be in flight between a send and its echo: the echo is
#: queued on the socket at once, behind what the socket already holds)
OWN_FRAMES_AWAITED_MAX = 1 << 16
#: echoes may arrive out of order by this many frames (loopback delivery
#: goes through the backlog queue of whichever CPU sent); an awaited echo
#: further behind the latest one seen was lost (the kernel's drop counts
#: have it) and is no longer awaited
OWN_FRAMES_REORDER = 256


def is_echoing_bus(bus: Any) -> bool:
    """Whether a python-can bus object is of an interface in ``ECHOING_INTERFACES``."""
    module = type(bus).__module__ or ""
    return any(module.startswith(f"can.interfaces.{name}") for name in ECHOING_INTERFACES)


class OwnFrames:
    """Tells the echoes of a bridge's own frames from other programs' frames.

    python-can's ``udp_multicast`` bus sends each frame as a UDP datagram to
    a multicast group, and the kernel delivers it to every member socket on
    the host, the sender's own included (multicast loopback). The bus does
    not say who sent a datagram: it drops the source address, and that
    address would not tell two programs on one host apart anyway (every
    member is bound to the group's port on the same host address). What it
    does carry, in the datagram, is the sending ``Message.channel``. So each
    frame the bridge sends gets a channel of ``<channel>@<token>:<n>``: the
    bus's channel, a random token of this bridge and the frame's sequence
    number; a received frame is an echo when it carries this bridge's token
    and a number still awaited. Each number is an echo once: a copy sent
    again by another program (a replay of a recording of the bus keeps the
    channel field) is that program's frame and goes to the loop.

    Not the socket option IP_MULTICAST_LOOP = 0 instead: it stops the
    kernel from looping this socket's datagrams back to *any* socket on the
    host, so a TCU or a logger in another process on the same machine (the
    demo's and the tests' set-up) would no longer hear the plant at all.

    Echoes come back in the order sent, give or take ``OWN_FRAMES_REORDER``
    frames; an awaited number further behind the latest echo seen was lost
    below the bridge (the kernel's drop count has it) and is forgotten, as
    is the oldest when more than ``OWN_FRAMES_AWAITED_MAX`` are awaited.
    Used by the bridge thread only (no lock).
    """

    def __init__(self, channel: str, awaited_max: int = OWN_FRAMES_AWAITED_MAX,
                 reorder: int = OWN_FRAMES_REORDER) -> None:
        self.prefix = f"{channel}@{secrets.token_hex(4)}:"
        self._next = 0
        self._awaited: dict[int, None] = {}   # sequence numbers in the order sent
        self._awaited_max = int(awaited_max)
        self._reorder = int(reorder)
        #: echoes recognised; awaited echoes given up (lost below the bridge,
        #: or more awaited than ``awaited_max``)
        self.echoes = 0
        self.forgotten = 0

    def stamp(self) -> tuple[str, int]:
        """The channel for the next frame sent, and its sequence number."""
        n = self._next
        self._next += 1
        awaited = self._awaited
        awaited[n] = None
        if len(awaited) > self._awaited_max:
            del awaited[next(iter(awaited))]
            self.forgotten += 1
        return self.prefix + str(n), n

    def unsent(self, n: int) -> None:
        """Frame ``n`` could not be sent: no echo will come."""
        self._awaited.pop(n, None)

    def is_echo(self, msg: Any) -> bool:
        """Whether ``msg`` is the echo of a frame sent through ``stamp``."""
        channel = msg.channel
        if type(channel) is not str or not channel.startswith(self.prefix):
            return False
        try:
            n = int(channel[len(self.prefix):])
        except ValueError:
            return False
        awaited = self._awaited
        if n not in awaited:
            return False     # seen already, or given up: another program's copy
        del awaited[n]
        self.echoes += 1
        oldest = n - self._reorder
        while awaited:
            first = next(iter(awaited))
            if first >= oldest:
                break
            del awaited[first]
            self.forgotten += 1
        return True

    @property
    def awaited(self) -> int:
        """Frames sent whose echo has not been seen yet."""
        return len(self._awaited)
