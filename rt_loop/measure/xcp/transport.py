"""XCP on Ethernet: the framing and the UDP and TCP servers of the slave.

Every XCP packet travels with a 4-byte header: LEN (the packet's bytes,
u16 little endian) and CTR (u16 little endian: the master counts its
commands, the slave every packet it sends: responses, events and DTOs, so
the master sees what was lost). A UDP datagram may hold several packets;
over TCP they follow each other in the stream.

Two threads per server: the receiver (commands in, responses out) and the
sender (DTOs out: ``Daq.pop`` -> ``Slave.dto_packet`` -> the socket; also
the overload event). Neither ever blocks on the master: the sockets are
non-blocking; a DTO or response the socket cannot take now is dropped and
counted (UDP), or queued up to ``TCP_QUEUE_BYTES`` and then dropped and
counted (TCP: a frame is never cut). A frame that is empty, longer than
MAX_CTO, or cut short is dropped and counted; a TCP stream announcing a
frame larger than ``TCP_GARBAGE_LEN`` cannot be trusted any more and is
closed.

One master at a time: over UDP the address that sent the last CONNECT (a
CONNECT from another address takes the slave over: the previous master's
session ends, its DAQ lists stop); over TCP the last connection accepted
(the previous one is closed and its session ends). A master that vanishes
therefore never keeps the next one out. Packets from any other address
are dropped and counted.
"""

from __future__ import annotations

import errno
import selectors
import socket
import struct
import threading
from collections.abc import Iterator

from rt_loop.measure.xcp.protocol import CONNECT, Daq, Slave

__all__ = ["HEADER", "frame", "deframe_datagram", "StreamDeframer", "UdpServer", "TcpServer",
           "make_server", "TCP_QUEUE_BYTES", "TCP_GARBAGE_LEN"]

HEADER = struct.Struct("<HH")
TCP_QUEUE_BYTES = 1 << 20            # bytes waiting for a slow TCP master at most
TCP_GARBAGE_LEN = 4096               # a LEN above this: the stream is out of step
_DTO_BATCH = 512
#: the most bytes of XCP frames in one UDP datagram: an Ethernet frame's payload
#: (1500) less the IPv4 and UDP headers, so a datagram is never fragmented
UDP_PAYLOAD = 1472
_POLL_RUNNING_S = 0.001              # the sender's pause when the producer ran dry
_POLL_IDLE_S = 0.02                  # ... and when no DAQ list runs
_SELECT_S = 0.1


def frame(ctr: int, packet: bytes) -> bytes:
    """One packet with its XCP on Ethernet header."""
    return HEADER.pack(len(packet), ctr & 0xFFFF) + packet


def deframe_datagram(data: bytes, max_len: int, bad: dict[str, int]) -> Iterator[bytes]:
    """The packets of one UDP datagram. A frame that is empty, longer than
    ``max_len`` or cut short ends the datagram (counted in ``bad``)."""
    at, n = 0, len(data)
    while at < n:
        if n - at < HEADER.size:
            _bump(bad, "truncated")
            return
        length, _ctr = HEADER.unpack_from(data, at)
        if length == 0:
            _bump(bad, "empty")
            return
        if length > max_len:
            _bump(bad, "oversized")
            return
        if at + HEADER.size + length > n:
            _bump(bad, "truncated")
            return
        yield bytes(data[at + HEADER.size:at + HEADER.size + length])
        at += HEADER.size + length


class StreamDeframer:
    """The packets of a TCP stream, fed as it comes. An empty frame is
    skipped, one longer than ``max_len`` skipped whole (both counted); a
    LEN beyond ``TCP_GARBAGE_LEN`` sets ``broken`` (the caller closes)."""

    def __init__(self, max_len: int, bad: dict[str, int]) -> None:
        self.max_len = max_len
        self.bad = bad
        self._buf = bytearray()
        self._skip = 0
        self.broken = False

    def feed(self, data: bytes) -> list[bytes]:
        buf = self._buf
        buf += data
        out = []
        while not self.broken:
            if self._skip:
                k = min(self._skip, len(buf))
                del buf[:k]
                self._skip -= k
                if self._skip:
                    break
            if len(buf) < HEADER.size:
                break
            length, _ctr = HEADER.unpack_from(buf, 0)
            if length == 0:
                _bump(self.bad, "empty")
                del buf[:HEADER.size]
                continue
            if length > TCP_GARBAGE_LEN:
                _bump(self.bad, "garbage")
                self.broken = True
                break
            if length > self.max_len:
                _bump(self.bad, "oversized")
                del buf[:HEADER.size]
                self._skip = length
                continue
            if len(buf) < HEADER.size + length:
                break
            out.append(bytes(buf[HEADER.size:HEADER.size + length]))
            del buf[:HEADER.size + length]
        return out


def _bump(d: dict[str, int], key: str, by: int = 1) -> None:
    d[key] = d.get(key, 0) + by


def _family(host: str, kind: int) -> tuple[int, tuple]:
    infos = socket.getaddrinfo(host, None, 0, kind, 0, socket.AI_PASSIVE)
    if not infos:
        raise OSError(f"cannot resolve {host!r}")
    family, _, _, _, sockaddr = infos[0]
    return family, sockaddr


class _Server:
    """What both transports share: the threads, the sending, the counts."""

    protocol = ""

    def __init__(self, slave: Slave, daq: Daq, host: str = "127.0.0.1", port: int = 5555) -> None:
        self.slave = slave
        self.daq = daq
        self.host = host
        self.port = port
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._ctr = 0
        self.address: tuple | None = None            # bound (host, port, ...)
        self._counts = {"frames_in": 0, "packets_out": 0, "dtos_out": 0, "masters": 0,
                        "takeovers": 0}
        self._bad_frames: dict[str, int] = {}
        self._dropped: dict[str, int] = {}
        self.error: str | None = None

    # ---- life -------------------------------------------------------------------
    def start(self) -> None:
        self._open()
        for target, name in ((self._receiver, "xcp-rx"), (self._sender, "xcp-tx")):
            t = threading.Thread(target=self._guard(target), name=name, daemon=True)
            self._threads.append(t)
            t.start()

    def _guard(self, target):
        def run() -> None:
            try:
                target()
            except Exception as e:  # reported in counters, never fatal to the loop
                self.error = f"{type(e).__name__}: {e}"
        return run

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join()
        self._threads = []
        self.slave.reset("server stop")
        self._close()

    def counters(self) -> dict:
        with self._send_lock:
            return {"protocol": self.protocol, **self._counts,
                    "bad_frames": dict(self._bad_frames), "dropped": dict(self._dropped),
                    "error": self.error}

    # ---- the sender thread ----------------------------------------------------
    def _sender(self) -> None:
        slave, daq = self.slave, self.daq
        while not self._stop.is_set():
            dtos = daq.pop(_DTO_BATCH)
            packets = [pk for pk in map(slave.dto_packet, dtos) if pk is not None]
            packets += slave.overload_events(daq.dropped())
            if packets:
                self._send(packets, dtos=True)
            self._flush()
            if len(dtos) < _DTO_BATCH:
                self._stop.wait(_POLL_RUNNING_S if slave.daq_running else _POLL_IDLE_S)

    def _send(self, packets: list[bytes], dtos: bool = False) -> None:
        with self._send_lock:
            if not self._connected_locked():
                _bump(self._dropped, "no_master", len(packets))
                return
            frames = []
            for pk in packets:
                frames.append(frame(self._ctr, pk))
                self._ctr = (self._ctr + 1) & 0xFFFF
            sent = self._transmit_locked(frames)
            self._counts["packets_out"] += sent
            if dtos:
                self._counts["dtos_out"] += sent

    def _flush(self) -> None:
        pass

    # ---- per transport --------------------------------------------------------------
    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _receiver(self) -> None:
        raise NotImplementedError

    def _connected_locked(self) -> bool:
        raise NotImplementedError

    def _transmit_locked(self, frames: list[bytes]) -> int:
        raise NotImplementedError


class UdpServer(_Server):
    """XCP on UDP: one socket; the master is the address of the last CONNECT."""

    protocol = "udp"

    def __init__(self, *args, **kws) -> None:
        super().__init__(*args, **kws)
        self._sock: socket.socket | None = None
        self._peer: tuple | None = None

    def _open(self) -> None:
        family, sockaddr = _family(self.host, socket.SOCK_DGRAM)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            sock.bind((sockaddr[0], self.port) + tuple(sockaddr[2:]))
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self.address = sock.getsockname()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _connected_locked(self) -> bool:
        return self._peer is not None and self._sock is not None

    def _transmit_locked(self, frames: list[bytes]) -> int:
        """Frames packed into datagrams of at most UDP_PAYLOAD bytes (XCP on UDP
        lets a datagram carry several packets): a few system calls and interrupts
        per tick instead of one per DTO. Returns the frames sent."""
        sent = 0
        i = 0
        while i < len(frames):
            j, size = i, 0
            while j < len(frames) and (j == i or size + len(frames[j]) <= UDP_PAYLOAD):
                size += len(frames[j])
                j += 1
            try:
                self._sock.sendto(b"".join(frames[i:j]), self._peer)
                sent += j - i
            except BlockingIOError:
                _bump(self._dropped, "would_block", j - i)
            except OSError as e:
                _bump(self._dropped, errno.errorcode.get(e.errno, "send_error"), j - i)
            i = j
        return sent

    def _receiver(self) -> None:
        sock = self._sock
        sel = selectors.DefaultSelector()
        sel.register(sock, selectors.EVENT_READ)
        max_len = self.slave.max_cto
        try:
            while not self._stop.is_set():
                if not sel.select(_SELECT_S):
                    continue
                try:
                    data, addr = sock.recvfrom(65536)
                except BlockingIOError:
                    continue
                except OSError as e:           # e.g. ECONNREFUSED from an earlier send
                    with self._send_lock:
                        _bump(self._bad_frames, errno.errorcode.get(e.errno, "recv_error"))
                    continue
                with self._send_lock:
                    if not data:               # a datagram of no bytes: no frame in it
                        _bump(self._bad_frames, "empty_datagram")
                    packets = list(deframe_datagram(data, max_len, self._bad_frames))
                    self._counts["frames_in"] += len(packets)
                for packet in packets:
                    self._command(packet, addr)
        finally:
            sel.close()

    def _command(self, packet: bytes, addr: tuple) -> None:
        if addr != self._peer:
            if packet[0] != CONNECT:
                with self._send_lock:
                    _bump(self._dropped, "other_master" if self._peer else "not_connected")
                return
            takeover = self._peer is not None and self.slave.connected
            if takeover:
                self.slave.reset("takeover")
            with self._send_lock:
                self._counts["takeovers"] += takeover
                self._peer = addr
                self._ctr = 0
                self._counts["masters"] += 1
        self._send(self.slave.handle(packet))


class TcpServer(_Server):
    """XCP on TCP: one connection at a time; a new one replaces the old."""

    protocol = "tcp"

    def __init__(self, *args, **kws) -> None:
        super().__init__(*args, **kws)
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._out = bytearray()

    def _open(self) -> None:
        family, sockaddr = _family(self.host, socket.SOCK_STREAM)
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((sockaddr[0], self.port) + tuple(sockaddr[2:]))
            sock.listen(4)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._listener = sock
        self.address = sock.getsockname()

    def _close(self) -> None:
        with self._send_lock:
            self._drop_client_locked()
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _connected_locked(self) -> bool:
        return self._client is not None

    def _drop_client_locked(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except OSError:
                pass
        self._client = None
        self._out = bytearray()

    def _transmit_locked(self, frames: list[bytes]) -> int:
        queued = 0
        for f in frames:
            if len(self._out) + len(f) > TCP_QUEUE_BYTES:
                _bump(self._dropped, "queue_full")
                continue
            self._out += f
            queued += 1
        self._flush_locked()
        return queued

    def _flush(self) -> None:
        if self._out:
            with self._send_lock:
                self._flush_locked()

    def _flush_locked(self) -> None:
        client = self._client
        while self._out and client is not None:
            try:
                n = client.send(self._out)
            except BlockingIOError:
                return
            except OSError as e:
                # the master is gone: the receiver sees the end of its stream
                _bump(self._dropped, errno.errorcode.get(e.errno, "send_error"))
                self._out = bytearray()
                try:
                    client.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                return
            del self._out[:n]

    def _receiver(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._listener, selectors.EVENT_READ)
        deframer: StreamDeframer | None = None
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(_SELECT_S):
                    if key.fileobj is self._listener:
                        conn = self._accept(sel)
                        if conn is not None:
                            deframer = StreamDeframer(self.slave.max_cto, self._bad_frames)
                        continue
                    conn = key.fileobj
                    if conn is not self._client or deframer is None:
                        continue
                    try:
                        data = conn.recv(65536)
                    except BlockingIOError:
                        continue
                    except OSError:
                        data = b""
                    with self._send_lock:
                        packets = deframer.feed(data) if data else []
                        self._counts["frames_in"] += len(packets)
                    for packet in packets:
                        self._send(self.slave.handle(packet))
                    if not data or deframer.broken:
                        self._end_client(sel, conn, "master gone" if not data else "garbage")
                        deframer = None
        finally:
            sel.close()

    def _accept(self, sel: selectors.BaseSelector) -> socket.socket | None:
        try:
            conn, _addr = self._listener.accept()
        except (BlockingIOError, OSError):
            return None
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for opt, value in (("TCP_KEEPIDLE", 5), ("TCP_KEEPINTVL", 2), ("TCP_KEEPCNT", 3)):
            if hasattr(socket, opt):
                conn.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), value)
        old = self._client
        takeover = False
        if old is not None:
            sel.unregister(old)
            if _closed(old):                   # it left before: not taken over
                self.slave.reset("master gone")
            else:
                takeover = self.slave.connected
                self.slave.reset("takeover")
        with self._send_lock:
            self._counts["takeovers"] += takeover
            self._drop_client_locked()
            self._client = conn
            self._ctr = 0
            self._counts["masters"] += 1
        sel.register(conn, selectors.EVENT_READ)
        return conn

    def _end_client(self, sel: selectors.BaseSelector, conn: socket.socket, why: str) -> None:
        sel.unregister(conn)
        self.slave.reset(why)
        with self._send_lock:
            if self._client is conn:
                self._drop_client_locked()
            else:
                conn.close()


def _closed(sock: socket.socket) -> bool:
    """The peer closed its side (nothing left to read but the end)."""
    try:
        return sock.recv(1, socket.MSG_PEEK) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def make_server(protocol: str, slave: Slave, daq: Daq, host: str = "127.0.0.1",
                port: int = 5555) -> _Server:
    """A UdpServer or TcpServer ('udp' or 'tcp')."""
    kinds = {"udp": UdpServer, "tcp": TcpServer}
    try:
        cls = kinds[protocol.lower()]
    except KeyError:
        raise ValueError(f"XCP transport {protocol!r}: 'udp' or 'tcp'") from None
    return cls(slave, daq, host, port)
