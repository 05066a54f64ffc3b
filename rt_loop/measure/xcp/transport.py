"""XCP on Ethernet: the framing and the UDP and TCP servers of the slave.

Every XCP packet travels with a 4-byte header: LEN (the packet's bytes,
u16 little endian) and CTR (u16 little endian: the master counts its
commands, the slave every packet it sends: responses, events and DTOs, in
one sequence, so the master sees what was lost). A UDP datagram may hold
several packets; over TCP they follow each other in the stream.

Python keeps the command channel: a receiver thread per server (commands
in, the ``Slave``, responses out). Everything the slave sends goes through
the C sender (``rt_loop/csrc/rt_xcp_send.h``), an ordinary thread of its
own that reads the DAQ ring, packs each DTO, frames it with the slave's CTR
and sends it on the socket opened here, with no Python between the tick
and the socket; the responses and events Python makes are framed and sent
by the same code (``rt_xcp_send_packets``), so the CTR is one sequence,
owned by the C side. The sender's DTO layout (the lists that run, their
timestamps, numbers and ODT sizes) is the Slave's: handed over whenever a
command or a session's end changed it. With the loop's ``LoopBackend`` the
sender reads the loop's ``daq_ring`` itself; any other ``Daq`` (a producer
in Python, the protocol tests' fake) is fed into a ring of the sender's
own by a feeder thread.

Nothing ever blocks on the master: the sockets are non-blocking; a packet
the UDP socket cannot take now is dropped and counted; over TCP frames
wait in the sender's queue (``TCP_QUEUE_BYTES``), beyond it they are
dropped and counted (a frame is never cut). A frame that is empty, longer
than MAX_CTO, or cut short is dropped and counted; a TCP stream announcing
a frame larger than ``TCP_GARBAGE_LEN`` cannot be trusted any more and is
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
import os
import selectors
import socket
import struct
import threading
from collections.abc import Iterator, Sequence

from rt_loop._rt_loop import ffi, lib
from rt_loop.measure.xcp.protocol import CONNECT, Daq, Slave

__all__ = ["HEADER", "frame", "deframe_datagram", "StreamDeframer", "UdpServer", "TcpServer",
           "make_server", "TCP_QUEUE_BYTES", "TCP_GARBAGE_LEN", "UDP_PAYLOAD", "CSender",
           "sender_layout", "delay_percentiles_us"]

HEADER = struct.Struct("<HH")
TCP_QUEUE_BYTES = int(lib.RT_XCP_TCP_QUEUE_BYTES)   # bytes waiting for a slow TCP master at most
TCP_GARBAGE_LEN = 4096               # a LEN above this: the stream is out of step
#: the most bytes of XCP frames in one UDP datagram: an Ethernet frame's payload
#: (1500) less the IPv4 and UDP headers, so a datagram is never fragmented
UDP_PAYLOAD = int(lib.RT_XCP_UDP_PAYLOAD)
_FEED_BATCH = 512
_POLL_RUNNING_S = 0.001              # the feeder's pause when the producer ran dry
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


def sender_layout(views: Sequence) -> tuple[object, bool]:
    """The C sender's DTO layout (``rt_xcp_layout``) of the Slave's DTO views
    (one per DAQ list: running, timestamp, the ODTs' sizes and their 4-byte
    identification fields), and whether it fits the sender's bounds (else
    the layout is empty: no list runs)."""
    layout = ffi.new("rt_xcp_layout *")
    n_sizes = sum(len(v.sizes) for v in views)
    if len(views) > lib.RT_DAQ_MAX_LISTS or n_sizes > lib.RT_DAQ_MAX_ODTS:
        return layout, False
    k = 0
    for i, v in enumerate(views):
        x = layout.lists[i]
        x.running = bool(v.running)
        x.timestamp = bool(v.timestamp)
        head = v.headers[0] if v.headers else bytes([0, 0]) + struct.pack("<H", i)
        x.first_pid = head[0]
        x.daq = struct.unpack_from("<H", head, 2)[0]
        x.n_odts = len(v.sizes)
        x.first_size = k
        for size in v.sizes:
            if not 0 <= size <= lib.RT_DAQ_ODT_BYTES:
                return ffi.new("rt_xcp_layout *"), False
            layout.sizes[k] = size
            k += 1
    layout.n_lists = len(views)
    return layout, True


def delay_percentiles_us(hist: Sequence[int], qs: Sequence[float] = (50, 99, 99.9)) -> dict:
    """Percentiles (upper bin edges, us) of a 1 us delay histogram."""
    total = sum(hist)
    out: dict = {}
    for q in qs:
        if not total:
            out[f"p{q:g}"] = None
            continue
        want = total * q / 100.0
        seen = 0
        for k, n in enumerate(hist):
            seen += n
            if seen >= want:
                out[f"p{q:g}"] = k + 1
                break
    return out


class CSender:
    """The C sender of one server (``rt_xcp_send.h``): its thread, the master,
    the layout, Python's packets, the counts. ``ring``: the loop's
    ``rt_daq_ring *``, or ``ffi.NULL`` for a ring of its own (``feed``)."""

    def __init__(self, ring, protocol: str, fd: int = -1) -> None:
        self.kind = lib.RT_XCP_UDP if protocol == "udp" else lib.RT_XCP_TCP
        self._s = lib.rt_xcp_sender_new(ring, self.kind, fd)
        if self._s == ffi.NULL:
            raise OSError(errno.ENOMEM, "XCP sender: no memory for its queue or ring")
        self._final: dict | None = None
        self._final_hist: list[int] | None = None

    def start(self, poll_us: int = 0) -> None:
        rc = lib.rt_xcp_sender_start(self._s, poll_us)
        if rc:
            raise OSError(-rc, f"XCP sender thread: {os.strerror(-rc)}")

    def close(self) -> None:
        """Stops the thread and frees the sender; its counts stay readable."""
        if self._s is None:
            return
        lib.rt_xcp_sender_stop(self._s)
        self._final = self.stats()
        self._final_hist = self.delays()
        lib.rt_xcp_sender_free(self._s)
        self._s = None

    def set_peer(self, addr: tuple | None) -> None:
        if self._s is None:
            return
        if addr is None:
            lib.rt_xcp_sender_clear_peer(self._s)
            return
        host = str(addr[0]).partition("%")[0]
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        scope = int(addr[3]) if len(addr) > 3 else 0
        lib.rt_xcp_sender_set_peer(self._s, family, host.encode("ascii"), int(addr[1]), scope)

    def set_tcp(self, fd: int) -> None:
        if self._s is not None:
            lib.rt_xcp_sender_set_tcp(self._s, fd)

    def set_layout(self, views: Sequence) -> bool:
        layout, ok = sender_layout(views)
        if self._s is None:
            return ok
        return lib.rt_xcp_sender_set_layout(self._s, layout) == 0 and ok

    def send(self, packets: Sequence[bytes]) -> int:
        if not packets or self._s is None:
            return 0
        data = b"".join(packets)
        lens = ffi.new("uint16_t[]", [min(len(p), 0xFFFF) for p in packets])
        return lib.rt_xcp_send_packets(self._s, ffi.from_buffer("uint8_t[]", data), lens,
                                       len(packets))

    def feed(self, dtos, n: int, dropped: int) -> int:
        if self._s is None:
            return 0
        return lib.rt_xcp_sender_feed(self._s, dtos, n, dropped)

    def stats(self) -> dict:
        """The sender's counts (``rt_xcp_send_stats``) as a dict; send errors by
        errno name."""
        if self._s is None:
            return dict(self._final or {})
        st = ffi.new("rt_xcp_send_stats *")
        lib.rt_xcp_sender_read(self._s, st)
        out = {name: int(getattr(st, name)) for name, _ in ffi.typeof("rt_xcp_send_stats").fields
               if name not in ("send_errors", "reserved")}
        errors: dict[str, int] = {}
        for e in range(lib.RT_XCP_ERRNO_SLOTS):
            n = int(st.send_errors[e])
            if n:
                name = errno.errorcode.get(e, "send_error") if e else "send_error"
                errors[name] = errors.get(name, 0) + n
        out["send_errors"] = errors
        return out

    def delays(self) -> list[int]:
        """The DTO delay histogram: DTOs per 1 us bin from the tick's deadline
        to the send (the last bin: everything above)."""
        if self._s is None:
            return list(self._final_hist or [])
        n = int(lib.RT_XCP_DELAY_BINS)
        hist = ffi.new("uint64_t[]", n)
        k = lib.rt_xcp_sender_delays(self._s, hist, n)
        return list(hist)[:k]


class _Server:
    """What both transports share: the threads, the C sender, the counts."""

    protocol = ""

    def __init__(self, slave: Slave, daq: Daq, host: str = "127.0.0.1", port: int = 5555,
                 poll_us: int = 0) -> None:
        self.slave = slave
        self.daq = daq
        self.host = host
        self.port = port
        self.poll_us = poll_us
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self.sender: CSender | None = None
        self._views: object = None
        self.address: tuple | None = None            # bound (host, port, ...)
        self._counts = {"frames_in": 0, "masters": 0, "takeovers": 0}
        self._bad_frames: dict[str, int] = {}
        self._dropped: dict[str, int] = {}
        self._fed_refused = 0
        self.error: str | None = None

    # ---- life -------------------------------------------------------------------
    def start(self) -> None:
        self._open()
        try:
            ring = self.daq.dto_ring() if hasattr(self.daq, "dto_ring") else ffi.NULL
            self.sender = CSender(ring, self.protocol, self._sender_fd())
            self._sync_layout()
            self.sender.start(self.poll_us)
        except OSError:
            if self.sender is not None:
                self.sender.close()
            self._close()
            raise
        targets = [(self._receiver, "xcp-rx")]
        if ring == ffi.NULL:
            targets.append((self._feeder, "xcp-feed"))
        for target, name in targets:
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
        if self.sender is not None:
            self.sender.close()
        self._close()

    def counters(self) -> dict:
        """frames_in, packets_out, dtos_out, masters, takeovers, bad frames
        and dropped packets by reason, the error that ended a thread. Also
        hands the sender's DTO counts to the Slave's (``dtos``,
        ``dto_dropped``, ``overload_events``: the sender packs for it)."""
        st = self.sender.stats() if self.sender is not None else {}
        self._count_into_slave(st)
        with self._send_lock:
            dropped = dict(self._dropped)
            for key in ("no_master", "would_block", "queue_full"):
                if st.get(key):
                    dropped[key] = dropped.get(key, 0) + st[key]
            for key, n in st.get("send_errors", {}).items():
                dropped[key] = dropped.get(key, 0) + n
            return {"protocol": self.protocol, "frames_in": self._counts["frames_in"],
                    "packets_out": st.get("packets_out", 0), "dtos_out": st.get("dtos_out", 0),
                    "masters": self._counts["masters"], "takeovers": self._counts["takeovers"],
                    "bad_frames": dict(self._bad_frames), "dropped": dropped,
                    "error": self.error}

    def _count_into_slave(self, st: dict) -> None:
        if not st:
            return
        self.slave.count_dtos_sent_elsewhere(st["dtos_packed"], st["not_running"],
                                             st["stale"] + self._fed_refused, st["overload_events"])

    def sender_stats(self) -> dict:
        """The C sender's own counts (``rt_xcp_send_stats``) and its DTO delay
        percentiles (us from the tick's deadline to the send)."""
        if self.sender is None:
            return {}
        return {**self.sender.stats(), "delay_us": delay_percentiles_us(self.sender.delays())}

    # ---- the Slave's answers and the sender's layout ----------------------------------
    def _sync_layout(self) -> None:
        """Hands the Slave's DTO layout to the sender when it changed."""
        views = self.slave.dto_layout
        if views is self._views or self.sender is None:
            return
        self._views = views
        if not self.sender.set_layout(views):
            with self._send_lock:
                _bump(self._dropped, "layout_refused")

    def _handle(self, packet: bytes) -> None:
        answer = self.slave.handle(packet)
        self._sync_layout()                  # before the answer: the DTOs may follow it
        self._send(answer)

    def _reset(self, why: str) -> None:
        self.slave.reset(why)
        self._sync_layout()

    def _send(self, packets: list[bytes]) -> None:
        if packets and self.sender is not None:
            self.sender.send(packets)

    # ---- a DAQ producer in Python: into the sender's own ring -----------------------
    def _feeder(self) -> None:
        daq, slave = self.daq, self.slave
        buf = ffi.new("rt_dto[]", _FEED_BATCH)
        odt_bytes = int(lib.RT_DAQ_ODT_BYTES)
        pending: list = []                   # popped, not in the ring yet (it was full)
        while not self._stop.is_set():
            full = False
            if not pending:
                popped = daq.pop(_FEED_BATCH)
                full = len(popped) >= _FEED_BATCH
                for d in popped:
                    if len(d.data) <= odt_bytes and 0 <= d.list <= 0xFFFF and 0 <= d.odt <= 0xFFFF:
                        pending.append(d)
                    else:
                        self._fed_refused += 1       # no loop DTO is like it: stale
            for k, d in enumerate(pending):
                x = buf[k]
                x.time_ns, x.tick, x.list, x.odt, x.len = d.time_ns, 0, d.list, d.odt, len(d.data)
                ffi.memmove(x.data, d.data, len(d.data))
            took = self.sender.feed(buf, len(pending), daq.dropped())
            pending = pending[took:]
            if pending:
                self._stop.wait(_POLL_RUNNING_S)
            elif not full:
                self._stop.wait(_POLL_RUNNING_S if slave.daq_running else _POLL_IDLE_S)

    # ---- per transport --------------------------------------------------------------
    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _sender_fd(self) -> int:
        raise NotImplementedError

    def _receiver(self) -> None:
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

    def _sender_fd(self) -> int:
        return self._sock.fileno()

    def _close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

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
                self._reset("takeover")
            with self._send_lock:
                self._counts["takeovers"] += takeover
                self._peer = addr
                self.sender.set_peer(addr)     # the CTR starts again at 0
                self._counts["masters"] += 1
        self._handle(packet)


class TcpServer(_Server):
    """XCP on TCP: one connection at a time; a new one replaces the old."""

    protocol = "tcp"

    def __init__(self, *args, **kws) -> None:
        super().__init__(*args, **kws)
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None

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

    def _sender_fd(self) -> int:
        return -1                               # the connection, once accepted

    def _close(self) -> None:
        with self._send_lock:
            self._drop_client_locked()
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _drop_client_locked(self) -> None:
        if self._client is not None:
            if self.sender is not None:
                self.sender.set_tcp(-1)         # the sender lets go of it before it closes
            try:
                self._client.close()
            except OSError:
                pass
        self._client = None

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
                        self._handle(packet)
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
                self._reset("master gone")
            else:
                takeover = self.slave.connected
                self._reset("takeover")
        with self._send_lock:
            self._counts["takeovers"] += takeover
            self._drop_client_locked()
            self._client = conn
            self.sender.set_tcp(conn.fileno())   # the CTR starts again at 0
            self._counts["masters"] += 1
        sel.register(conn, selectors.EVENT_READ)
        return conn

    def _end_client(self, sel: selectors.BaseSelector, conn: socket.socket, why: str) -> None:
        sel.unregister(conn)
        self._reset(why)
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
