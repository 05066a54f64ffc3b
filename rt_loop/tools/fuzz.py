"""Fuzz: hostile traffic into a running plant server, every frame accounted for.

    python -m rt_loop.tools.fuzz --frames 1000000 --seed 7            # scripts/fuzz
    python -m rt_loop.tools.fuzz --transport socketcan --channel vcan0 --seconds 60
    python -m rt_loop.tools.fuzz --transport udp_multicast --frames 200000 --xcp-packets 0

The server (``rt_loop.server.Server``) runs in this process on the chosen
transport (``embedded``: python-can's in-process virtual bus through the
bridge; ``udp_multicast``: the bridge on a multicast group; ``socketcan``:
the loop's own CAN_RAW socket on a CAN interface, e.g. vcan0 in the guest of
``scripts/vcan-vm``). A second node on the same bus sends a seeded stream of
frames of these kinds (``KINDS``):

    valid           the TCU's messages, right CRC, the next counter
    extreme         the same with raw payloads at the ends (all 0x00, all
                    0xFF, random): physical values far outside the ranges
    unknown_11 / unknown_29   identifiers no one receives (29-bit: also the
                    TCU messages' numbers as extended identifiers)
    bad_length      a TCU message with any length but its own (0..7, and
                    classic frames with more than 8 bytes where the bus
                    allows it: never on SocketCAN)
    bad_crc         a TCU message with a wrong CRC byte
    counter_repeat / counter_jump   right after a valid frame: its counter
                    again, or a jump of 3..15
    restart         a TCU that restarts at once: counters 0, 1, 2, ... while
                    the receiver still expects the old sequence (rejected
                    until the counter is 1 or 2 ahead of the last accepted)
    restart_silent  a TCU that restarts after going silent for longer than
                    the message's timeout: the loop has timed it out and
                    takes any counter again (resynchronisation)
    remote / error / fd   remote frames, error frames, CAN FD frames
    burst           unknown identifiers back to back, more than every
                    buffer holds (the bridge's ring: 8192 frames): what does
                    not fit is counted as lost

and, with ``--xcp-packets`` (the server's XCP slave on UDP loopback),
malformed XCP on Ethernet datagrams (cut headers, lengths beyond MAX_CTO,
empty frames, random commands before and after CONNECT, DOWNLOADs of
non-finite and out-of-range values into the writable inputs and
parameters).

Every frame must end in one of the server's counts: accepted, rejected by
a reason (unknown_id, bad_length, bad_crc, bad_counter), lost (the loop's
rx_overflow: a full ring or the kernel's drops on the socket; the kernel's
drops below the bridge), not forwarded by the bridge by kind (remote, error,
FD frames), or, on SocketCAN, not delivered by the kernel by design (error
frames go only to sockets that subscribe them). The run fails when
``unexplained`` (frames sent minus all of these) is not 0, when a reason's
count differs from what the kinds sent predict, when the loop is not
running at the end, or when the commands do not resume after the traffic.
Each datagram of XCP must likewise end as a bad frame, a packet dropped by
reason, a positive answer, an error answer by name or an ignored packet by
reason; a packet that made the slave's backend raise (``internal_error``)
fails the run.

The counter kinds depend on the receiver's counter state, which a timeout
resets (the loop times a TCU message out after 10 of its cycles without an
accepted frame). The generator keeps its own copy of that state; the loop
runs at ``--time-scale`` (0.1: a tenth of real time, so the timeouts are
200 ms and more of wall time, longer than this sender stalls on a loaded
machine). When the loop saw more timeouts than the generator caused, the
split between accepted and bad_counter is reported and not judged (their sum
still is).

Prints the table (frames sent per kind; counts per reason, expected against
counted; unexplained) and writes it as JSON (``--json``).
"""

from __future__ import annotations

import argparse
import math
import random
import socket
import struct
import sys
import time
from typing import Any

from can_dbc.channels import open_bus
from can_dbc.python_can import python_can
from plant import argtypes
from plant.machine import write_figures
from plant.stop_signals import StopSignals

__all__ = ["KINDS", "FuzzError", "main", "run_fuzz"]

TRANSPORTS = ("embedded", "udp_multicast", "socketcan")
KINDS = ("valid", "extreme", "unknown_11", "unknown_29", "bad_length", "bad_crc",
         "counter_repeat", "counter_jump", "restart", "restart_silent", "remote", "error",
         "fd", "burst")
#: relative weights of the kinds in the stream (per event; some events send several frames)
WEIGHTS = {"valid": 30, "extreme": 6, "unknown_11": 8, "unknown_29": 6, "bad_length": 8,
           "bad_crc": 8, "counter_repeat": 5, "counter_jump": 5, "restart": 1, "remote": 4,
           "error": 3, "fd": 4}
REASONS = ("accepted", "unknown_id", "bad_length", "bad_crc", "bad_counter", "lost",
           "bridge_remote", "bridge_error", "bridge_fd", "kernel_filtered")
EMBEDDED_CHANNEL = "dct-hil-fuzz"
UDP_CHANNEL = "239.74.163.5"
BURST_FRAMES = 20_000
IN_FLIGHT_MAX = 4_000
_COUNTER_MOD = 16


class FuzzError(RuntimeError):
    """The fuzz run cannot be set up (one line)."""


# --------------------------------------------------------------------------
# the generator
# --------------------------------------------------------------------------

class _Msg:
    def __init__(self, name: str, frame_id: int, length: int, cycle_s: float) -> None:
        self.name, self.id, self.length, self.cycle_s = name, frame_id, length, cycle_s
        self.last: int | None = None          # the receiver's last accepted counter (model)


class Frame:
    """One frame to send: id, data, flags; ``expect`` the reason it must end in."""

    __slots__ = ("kind", "id", "data", "ext", "remote", "error", "fd", "expect")

    def __init__(self, kind: str, frame_id: int, data: bytes, expect: str, ext: bool = False,
                 remote: bool = False, error: bool = False, fd: bool = False) -> None:
        self.kind, self.id, self.data, self.expect = kind, frame_id, data, expect
        self.ext, self.remote, self.error, self.fd = ext, remote, error, fd


class Generator:
    """The seeded stream of events; each event is a list of Frames (or a pause)."""

    def __init__(self, seed: int, transport: str, fd_allowed: bool) -> None:
        from can_dbc import codec

        self.rng = random.Random(seed)
        self.codec = codec
        self.transport = transport
        self.fd_allowed = fd_allowed
        db = codec.database()
        self.msgs = []
        known = set()
        for m in db.messages:
            known.add(m.frame_id)
            if m.senders and "TCU" in m.senders:
                self.msgs.append(_Msg(m.name, m.frame_id, m.length, (m.cycle_time or 10) / 1000))
        self.known = known
        self.kinds = [k for k in WEIGHTS if k != "fd" or fd_allowed]
        self.weights = [WEIGHTS[k] for k in self.kinds]
        self.bridge = transport != "socketcan"

    # -- helpers
    def _payload(self, m: _Msg, counter: int, raw: bytes | None = None) -> bytes:
        if raw is None:
            raw = self.rng.randbytes(m.length)
        return self.codec.protect(m.id, raw, counter)

    def valid(self, m: _Msg, kind: str = "valid", raw: bytes | None = None) -> Frame:
        c = (m.last + 1) % _COUNTER_MOD if m.last is not None else self.rng.randrange(16)
        m.last = c
        return Frame(kind, m.id, self._payload(m, c, raw), "accepted")

    def _unknown_11(self) -> int:
        while True:
            i = self.rng.randrange(0x800)
            if i not in self.known:
                return i

    def _counter_frame(self, m: _Msg, kind: str, c: int) -> Frame:
        """A frame with counter c judged by the model (accepted moves it on)."""
        step = None if m.last is None else (c - m.last) % _COUNTER_MOD
        if step is None or step in (1, 2):
            m.last = c
            expect = "accepted"
        else:
            expect = "bad_counter"
        return Frame(kind, m.id, self._payload(m, c), expect)

    def on_timeout(self, m: _Msg) -> None:
        m.last = None

    # -- one event
    def event(self) -> list[Frame]:
        rng = self.rng
        kind = rng.choices(self.kinds, self.weights)[0]
        m = rng.choice(self.msgs)
        if kind == "valid":
            return [self.valid(m)]
        if kind == "extreme":
            raw = rng.choice((bytes(m.length), b"\xff" * m.length,
                              rng.randbytes(m.length)))
            return [self.valid(m, "extreme", raw)]
        if kind == "unknown_11":
            return [Frame(kind, self._unknown_11(), rng.randbytes(rng.randrange(9)),
                          "unknown_id")]
        if kind == "unknown_29":
            ident = m.id if rng.random() < 0.3 else rng.randrange(0x800, 1 << 29)
            return [Frame(kind, ident, rng.randbytes(rng.randrange(9)),
                          "unknown_id", ext=True)]
        if kind == "bad_length":
            n = rng.choice([k for k in range(9) if k != m.length])
            data = rng.randbytes(n)
            if n >= 2:
                data = self.codec.protect(m.id, data, rng.randrange(16))
            return [Frame(kind, m.id, data, "bad_length")]
        if kind == "bad_crc":
            data = bytearray(self._payload(m, rng.randrange(16)))
            data[0] ^= rng.randrange(1, 256)
            return [Frame(kind, m.id, bytes(data), "bad_crc")]
        if kind in ("counter_repeat", "counter_jump"):
            first = self.valid(m)
            c = m.last if kind == "counter_repeat" else (m.last + rng.randrange(3, 16)) % 16
            return [first, self._counter_frame(m, kind, c)]
        if kind == "restart":
            out = [self.valid(m)]
            for c in range(rng.randrange(4, 20)):
                out.append(self._counter_frame(m, kind, c % 16))
            return out
        if kind == "remote":
            if rng.random() < 0.5:
                ident, known = m.id, True
            else:
                ident, known = self._unknown_11(), False
            expect = "bridge_remote" if self.bridge else ("bad_length" if known else "unknown_id")
            return [Frame(kind, ident, b"", expect, remote=True)]
        if kind == "error":
            expect = "bridge_error" if self.bridge else "kernel_filtered"
            data = rng.randbytes(8)
            return [Frame(kind, rng.randrange(1, 0x200), data, expect, error=True)]
        if kind == "fd":
            n = rng.choice((12, 16, 20, 24, 32, 48, 64, 8, 5))
            if rng.random() < 0.5:
                ident, known = m.id, True
            else:
                ident, known = self._unknown_11(), False
            data = rng.randbytes(n)
            expect = "bridge_fd" if self.bridge else ("bad_length" if known else "unknown_id")
            return [Frame(kind, ident, data, expect, fd=True)]
        raise AssertionError(kind)

    def burst(self, n: int) -> list[Frame]:
        return [Frame("burst", self._unknown_11(), bytes(8), "unknown_id") for _ in range(n)]


# --------------------------------------------------------------------------
# the sender (a second node)
# --------------------------------------------------------------------------

class Sender:
    def __init__(self, transport: str, channel: str, fd: bool) -> None:
        self.can = python_can()
        kwargs: dict[str, Any] = {}
        if transport == "embedded":
            iface = "virtual"
        elif transport == "udp_multicast":
            iface = "udp_multicast"
            kwargs["fd"] = fd
        else:
            iface = "socketcan"
            kwargs["fd"] = fd
        try:
            self.bus = open_bus(iface, channel, receive_own_messages=False, **kwargs)
        except ConnectionError as e:
            raise FuzzError(f"the fuzzer's sender: {e}") from None
        self.send_errors = 0
        self.last_error: str | None = None
        #: the in-process bus: straight into the other nodes' queues (python-can's
        #: VirtualBus.send deep-copies each message, 15 us; the bridge reads the same queue)
        self._queues = None
        if transport == "embedded" and hasattr(self.bus, "channel") and hasattr(self.bus, "queue"):
            self._queues = self.bus.channel

    def send(self, f: Frame) -> bool:
        if self._queues is not None:
            msg = self.can.Message(arbitration_id=f.id, is_extended_id=f.ext, data=f.data,
                                   dlc=len(f.data) if not f.remote else 0,
                                   is_remote_frame=f.remote, is_error_frame=f.error,
                                   is_fd=f.fd, check=False, is_rx=True,
                                   timestamp=time.time())
            own = self.bus.queue
            for q in self._queues:
                if q is not own:
                    q.put_nowait(msg)
            return True
        msg = self.can.Message(arbitration_id=f.id, is_extended_id=f.ext, data=f.data,
                               dlc=len(f.data) if not f.remote else 0,
                               is_remote_frame=f.remote, is_error_frame=f.error, is_fd=f.fd,
                               check=False)
        for _attempt in range(200):
            try:
                self.bus.send(msg, timeout=0.05)
                return True
            except Exception as e:  # a full queue: ENOBUFS on SocketCAN
                self.last_error = " ".join(str(e).split())
                if "No buffer space" in self.last_error or "ENOBUFS" in self.last_error \
                        or "Resource temporarily" in self.last_error:
                    time.sleep(0.001)
                    continue
                break
        self.send_errors += 1
        return False

    def drain(self) -> None:
        """Reads what the plant sent (the virtual bus queues it for every other node)."""
        try:
            while self.bus.recv(timeout=0.0) is not None:
                pass
        except Exception:  # nothing of ours
            pass

    def close(self) -> None:
        self.bus.shutdown()


# --------------------------------------------------------------------------
# XCP
# --------------------------------------------------------------------------

def fuzz_xcp(address: tuple, n: int, rng: random.Random, regions: list) -> dict:
    """Sends n malformed or random XCP datagrams (one frame each, or a cut
    header) from one socket; returns what was sent by kind."""
    from rt_loop.measure.xcp import protocol as P

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.05)
    sock.connect(address)
    sent: dict[str, int] = {}
    answers = 0
    ctr = 0

    def put(kind: str, datagram: bytes) -> None:
        nonlocal ctr, answers
        sock.send(datagram)
        sent[kind] = sent.get(kind, 0) + 1
        ctr += 1
        try:
            while True:
                sock.recv(65536)
                answers += 1
                sock.settimeout(0.0)
        except (TimeoutError, BlockingIOError, ConnectionRefusedError):
            pass
        finally:
            sock.settimeout(0.02)

    def frame(packet: bytes) -> bytes:
        return struct.pack("<HH", len(packet), ctr & 0xFFFF) + packet

    doubles = [r for r in regions if r[6] == "double" and r[1] >= 8]
    for i in range(n):
        k = rng.random()
        if i % 50 == 0:
            put("connect", frame(bytes([P.CONNECT, 0])))
        elif k < 0.05:
            put("cut_header", bytes(rng.getrandbits(8) for _ in range(rng.randrange(4))))
        elif k < 0.10:
            put("empty_frame", struct.pack("<HH", 0, ctr))
        elif k < 0.15:
            body = bytes(rng.getrandbits(8) for _ in range(rng.randrange(1, 40)))
            put("length_beyond_data", struct.pack("<HH", len(body) + rng.randrange(1, 50), ctr)
                + body)
        elif k < 0.20:
            put("too_long", frame(bytes(rng.getrandbits(8) for _ in range(rng.randrange(253, 600)))))
        elif k < 0.25:
            put("disconnect", frame(bytes([P.DISCONNECT])))
        elif k < 0.45 and doubles:
            off, size, _kind, _name, lo, hi, _ct = rng.choice(doubles)
            value = rng.choice((math.nan, math.inf, -math.inf, 1e308, -1e308,
                                (hi if math.isfinite(hi) else 1e9) * 10 + 1))
            put("connect", frame(bytes([P.CONNECT, 0])))
            put("set_mta", frame(bytes([P.SET_MTA, 0, 0, 0]) + struct.pack("<I", off)))
            put("download_non_finite" if not math.isfinite(value) else "download_out_of_range",
                frame(bytes([P.DOWNLOAD, 8]) + struct.pack("<d", value)))
        elif k < 0.50:
            put("zero_datagram", b"")
        else:
            body = bytes([rng.randrange(256)]) + bytes(rng.getrandbits(8)
                                                       for _ in range(rng.randrange(0, 20)))
            put("random_command", frame(body))
    sock.close()
    return {"sent": sent, "datagrams": sum(sent.values()), "answers": answers}


def xcp_balance(sent: dict, counters: dict) -> dict:
    """Datagrams sent against the slave's counts (``Server.xcp_counters()``:
    the transport's and the protocol's)."""
    tr, pr = counters.get("transport", {}), counters.get("protocol", {})
    bad = sum(tr.get("bad_frames", {}).values())
    frames_in = int(tr.get("frames_in", 0))
    dropped_in = sum(v for k, v in tr.get("dropped", {}).items()
                     if k in ("not_connected", "other_master"))
    handled = frames_in - dropped_in
    errors = sum(pr.get("errors", {}).values())
    ignored = sum(pr.get("ignored", {}).values())
    positive = int(pr.get("positive", 0))
    return {
        "datagrams": sent["datagrams"],
        "bad_frames": dict(tr.get("bad_frames", {})),
        "packets": frames_in,
        "dropped_by_transport": dropped_in,
        "positive": positive,
        "errors": dict(pr.get("errors", {})),
        "ignored": dict(pr.get("ignored", {})),
        "unexplained_datagrams": sent["datagrams"] - frames_in - bad,
        "unexplained_packets": handled - positive - errors - ignored,
        "internal_errors": int(pr.get("ignored", {}).get("internal_error", 0)),
        "cal_refused": (counters.get("loop") or {}).get("cal_refused"),
    }


# --------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------

def _bridge_counts(c: dict) -> dict:
    b = c.get("bridge") or {}
    return {k: int(b.get(k) or 0) for k in ("rx_remote_frames", "rx_error_frames", "rx_fd_frames",
                                           "rx_kernel_drops", "rx_left_in_ring",
                                           "rx_drained_at_stop", "rx_ring_full")}


def _seen(c: dict) -> int:
    """Frames the server has taken in so far (any outcome)."""
    b = _bridge_counts(c)
    rx = c["rx"]
    return (int(rx["frames"]) + int(rx["overflow"]) + b["rx_remote_frames"]
            + b["rx_error_frames"] + b["rx_fd_frames"] + b["rx_kernel_drops"])


def run_fuzz(args: argparse.Namespace, out=sys.stdout, err=sys.stderr) -> dict:
    from rt_loop.server import Server, ServerError
    from rt_loop.transport import TransportError

    transport = args.transport
    channel = args.channel or {"embedded": EMBEDDED_CHANNEL, "udp_multicast": UDP_CHANNEL,
                               "socketcan": "vcan0"}[transport]
    iface = {"embedded": "virtual", "udp_multicast": "udp_multicast",
             "socketcan": "socketcan"}[transport]
    fd = args.fd if args.fd is not None else transport != "socketcan"
    xcp = ("127.0.0.1", 0) if args.xcp_packets > 0 else None
    try:
        server = Server(channel, interface=iface, priority=args.priority,
                        time_scale=args.time_scale, xcp=xcp, pm_qos_us=None)
    except (ServerError, TransportError) as e:
        raise FuzzError(str(e)) from None
    except Exception as e:  # the plant's parameters, the build: one line
        raise FuzzError(f"the server cannot be set up: {type(e).__name__}: "
                        f"{' '.join(str(e).split())}") from None
    signals = StopSignals().__enter__()    # SIGINT, SIGTERM: stop (restored at the end)
    stop, received = signals.event, signals.received
    gen = Generator(args.seed, transport, fd_allowed=fd)
    sent_kind = dict.fromkeys(KINDS, 0)
    expect = dict.fromkeys(REASONS, 0)
    burst_sent = 0
    deliberate_timeouts = 0
    sender = None
    xcp_result = None
    resumed = None
    timeouts_in_run = 0
    t0 = time.monotonic()
    try:
        try:
            server.start(cancel=stop)
        except (ServerError, TransportError) as e:
            raise FuzzError(str(e)) from None
        sender = Sender(transport, channel, fd)
        timeouts_at_start = server.snapshot()["counts"]["timeouts"]
        timeout_wall = {m.name: 10 * m.cycle_s / args.time_scale for m in gen.msgs}
        total = 0
        next_check = 0
        next_progress = time.monotonic() + 5.0
        deadline = (time.monotonic() + args.seconds) if args.seconds else None
        started = time.monotonic()

        def progress() -> float:
            """How far the run is, 0..1: by frames or by time, whichever is further."""
            by_frames = total / args.frames if args.frames else 0.0
            by_time = (time.monotonic() - started) / args.seconds if args.seconds else 0.0
            return max(by_frames, by_time)

        # bursts and silent restarts spread over the run
        bursts_at = [(i + 0.5) / args.bursts for i in range(args.bursts)]
        silent_at = [(i + 1.0 / 3.0) / args.silent_restarts for i in range(args.silent_restarts)]

        def taken_in() -> int:
            """Frames sent that the server has taken in, with those the kernel filters out
            before its socket (error frames on SocketCAN: they never arrive, so waiting for
            them waited out every limit)."""
            return _seen(server.snapshot()["counts"]) + expect["kernel_filtered"]

        def wait_idle(limit_s: float = 30.0) -> None:
            """Until the server has taken in every frame sent."""
            end = time.monotonic() + limit_s
            while time.monotonic() < end:
                sender.drain()
                if taken_in() >= total:
                    return
                time.sleep(0.002)

        def send(frames: list[Frame]) -> None:
            nonlocal total
            for f in frames:
                if sender.send(f):
                    sent_kind[f.kind] += 1
                    expect[f.expect] += 1
                    total += 1

        while not stop.is_set():
            done = ((args.frames and total >= args.frames)
                    or (deadline is not None and time.monotonic() >= deadline))
            if (done and not bursts_at and not silent_at) or not server.running:
                break
            if total >= next_check:
                sender.drain()
                seen = taken_in()
                while total - seen > IN_FLIGHT_MAX and server.running and not stop.is_set():
                    time.sleep(0.0005)
                    sender.drain()
                    seen = taken_in()
                next_check = total + 1000
            if bursts_at and progress() >= bursts_at[0]:
                bursts_at.pop(0)
                wait_idle()
                before = server.snapshot()["counts"]["timeouts"]
                frames = gen.burst(args.burst_frames)
                send(frames)
                burst_sent += len(frames)
                wait_idle()
                # no TCU frame while the burst drains: the loop may time messages out
                deliberate_timeouts += server.snapshot()["counts"]["timeouts"] - before
            if silent_at and progress() >= silent_at[0]:
                silent_at.pop(0)
                # a TCU restarting after a pause: one message silent past its timeout
                m = gen.rng.choice(gen.msgs)
                wait_idle()
                all_before = server.snapshot()["counts"]["timeouts"]
                before = server.snapshot()["counts"]["tcu_messages"][m.name]["timeouts"]
                end = time.monotonic() + 3 * timeout_wall[m.name] + 0.2
                while time.monotonic() < end and not stop.is_set():
                    # the others go on meanwhile
                    others = [x for x in gen.msgs if x is not m]
                    send([gen.valid(gen.rng.choice(others))])
                    sender.drain()
                    time.sleep(0.001)
                wait_idle()
                after = server.snapshot()["counts"]["tcu_messages"][m.name]["timeouts"]
                deliberate_timeouts += server.snapshot()["counts"]["timeouts"] - all_before
                if after > before:
                    gen.on_timeout(m)
                    m.last = None
                    send([gen._counter_frame(m, "restart_silent", 0)])
            if not done:
                send(gen.event())
            if time.monotonic() >= next_progress and not args.quiet:
                el = time.monotonic() - t0
                print(f"fuzz: {total:,} frames in {el:.0f} s ({total / el:,.0f}/s)", file=out,
                      flush=True)
                next_progress += 10.0
        wait_idle()
        # the commands resume: valid frames of every message, accepted
        before = server.snapshot()["counts"]["rx"]["accepted"]
        for m in gen.msgs:
            send([gen.valid(m)])
        wait_idle()
        snap = server.snapshot()["counts"]
        resumed = snap["rx"]["accepted"] - before == len(gen.msgs)
        timeouts_in_run = snap["timeouts"] - timeouts_at_start
        if args.xcp_packets > 0 and server.xcp is not None and not stop.is_set():
            from rt_loop.measure.xcp import a2l as _a2l

            regions = _a2l.calibration_regions(server._ffi, server._lib)
            xcp_result = fuzz_xcp(tuple(server.xcp.address[:2]), args.xcp_packets,
                                  random.Random(args.seed + 1), regions)
            time.sleep(0.3)
    finally:
        wall = time.monotonic() - t0
        running_at_end = server.running
        state_at_end = server.state
        server.stop()
        if sender is not None:
            sender.close()
        signals.__exit__(None, None, None)
    report = server.report(histograms=False)
    c = report["counts"]
    result = _table(args, transport, channel, sent_kind, expect, c, burst_sent,
                    deliberate_timeouts, timeouts_in_run, sender, wall, running_at_end, state_at_end, resumed,
                    report)
    if xcp_result is not None:
        xb = xcp_balance(xcp_result, report["xcp"] or {})
        result["xcp"] = {"sent": xcp_result["sent"], **xb}
        if xb["unexplained_datagrams"] or xb["unexplained_packets"] or xb["internal_errors"]:
            result["failures"].append(
                f"XCP: {xb['unexplained_datagrams']} datagrams and {xb['unexplained_packets']} "
                f"packets unexplained, {xb['internal_errors']} internal errors")
    result["interrupted"] = bool(received)
    result["passed"] = not result["failures"] and not received
    return result


def _table(args, transport, channel, sent_kind, expect, c, burst_sent, deliberate_timeouts,
           timeouts, sender, wall, running_at_end, state_at_end, resumed, report) -> dict:
    rx, b = c["rx"], _bridge_counts(c)
    counted = {
        "accepted": int(rx["accepted"]),
        "unknown_id": int(rx["unknown_id"]),
        "bad_length": int(rx["bad_length"]),
        "bad_crc": int(rx["bad_crc"]),
        "bad_counter": int(rx["bad_counter"]),
        "lost": int(rx["overflow"]) + b["rx_kernel_drops"] + b["rx_left_in_ring"]
        + b["rx_drained_at_stop"],
        "bridge_remote": b["rx_remote_frames"],
        "bridge_error": b["rx_error_frames"],
        "bridge_fd": b["rx_fd_frames"],
        "kernel_filtered": expect["kernel_filtered"],   # never reaches the socket: by design
    }
    sent_total = sum(sent_kind.values())
    unexplained = sent_total - sum(counted.values())
    failures: list[str] = []
    if unexplained:
        failures.append(f"{unexplained} frames neither accepted, rejected by a reason nor "
                        "counted as lost")
    # timeouts while frames flowed that the generator did not cause (bursts and
    # silent restarts cause them): a stall of this sender longer than a timeout
    unexpected_timeouts = max(0, timeouts - deliberate_timeouts)
    counter_judged = unexpected_timeouts == 0
    lost = counted["lost"]
    for reason in REASONS:
        e, k = expect[reason], counted[reason]
        if reason == "unknown_id":
            ok = (k <= e and e - k == lost) if burst_sent else e == k
        elif reason == "lost":
            ok = k <= burst_sent
        elif reason in ("accepted", "bad_counter") and not counter_judged:
            ok = True
        else:
            ok = e == k
        if not ok:
            failures.append(f"{reason}: {k} counted, {e} expected")
    if not counter_judged:
        s_e, s_k = expect["accepted"] + expect["bad_counter"], counted["accepted"] + \
            counted["bad_counter"]
        if s_e != s_k:
            failures.append(f"accepted + bad_counter: {s_k} counted, {s_e} expected")
    if not running_at_end:
        failures.append(f"the loop was not running at the end (state {state_at_end}; "
                        f"{report['run']['error']})")
    if resumed is False:
        failures.append("the commands did not resume after the traffic")
    return {
        "transport": transport, "channel": channel, "seed": args.seed,
        "time_scale": args.time_scale, "wall_s": wall,
        "frames_per_s": sent_total / wall if wall > 0 else None,
        "sent_by_kind": dict(sent_kind), "sent_total": sent_total,
        "expected_by_reason": dict(expect), "counted_by_reason": counted,
        "unexplained": unexplained,
        "bursts": {"frames": burst_sent, "lost": lost},
        "timeouts": {"in_run": timeouts, "deliberate": deliberate_timeouts,
                     "unexpected": unexpected_timeouts,
                     "counter_split_judged": counter_judged},
        "sender": {"send_errors": sender.send_errors if sender else None,
                   "last_error": sender.last_error if sender else None},
        "loop": {"state_at_end": state_at_end, "running_at_end": running_at_end,
                 "error": report["run"]["error"], "ticks": report["run"]["ticks"],
                 "overruns": c["overruns"], "input_clamps": report["plant"].get("input_clamps")},
        "commands_resumed": resumed,
        "bridge": {k: v for k, v in (c.get("bridge") or {}).items()
                   if not isinstance(v, dict)},
        "failures": failures,
    }


def format_table(r: dict) -> str:
    lines = [f"fuzz over {r['transport']} ({r['channel']}), seed {r['seed']}: "
             f"{r['sent_total']:,} frames in {r['wall_s']:.0f} s "
             f"({r['frames_per_s'] or 0:,.0f}/s), loop at {r['time_scale']:g}x real time", "",
             "| kind | frames sent |", "|---|---:|"]
    for k, n in r["sent_by_kind"].items():
        if n:
            lines.append(f"| {k} | {n:,} |")
    lines.append(f"| **total** | **{r['sent_total']:,}** |")
    lines += ["", "| reason | expected | counted |", "|---|---:|---:|"]
    for reason in REASONS:
        e, k = r["expected_by_reason"][reason], r["counted_by_reason"][reason]
        if e or k:
            lines.append(f"| {reason} | {e:,} | {k:,} |")
    lines.append(f"| **unexplained** | | **{r['unexplained']:,}** |")
    t = r["timeouts"]
    lines += ["", f"bursts: {r['bursts']['frames']:,} frames, {r['bursts']['lost']:,} lost "
                  "(counted); timeouts: "
                  f"{t['in_run']} while sending ({t['deliberate']} in bursts and silent restarts, {t['unexpected']} "
                  "unexpected" + ("" if t["counter_split_judged"] else
                                  ": accepted/bad_counter judged as a sum") + ")",
              f"loop: {r['loop']['state_at_end']} at the end, {r['loop']['ticks']:,} ticks, "
              f"{r['loop']['overruns']} overruns; commands resumed after the traffic: "
              f"{r['commands_resumed']}"]
    if r.get("xcp"):
        x = r["xcp"]
        lines += ["", f"XCP: {x['datagrams']:,} datagrams "
                      + ", ".join(f"{k} {v}" for k, v in sorted(x["sent"].items())),
                  f"  bad frames {x['bad_frames']}; packets {x['packets']} (dropped before the "
                  f"slave {x['dropped_by_transport']}); positive {x['positive']}; errors "
                  f"{x['errors']}; ignored {x['ignored']}",
                  f"  unexplained datagrams {x['unexplained_datagrams']}, packets "
                  f"{x['unexplained_packets']}; internal errors {x['internal_errors']}"]
    lines.append("")
    lines.append("fuzz: " + ("PASS" if r["passed"] else "FAIL"))
    for f in r["failures"]:
        lines.append(f"fuzz: FAIL {f}")
    return "\n".join(lines)




def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scripts/fuzz", description=__doc__.split("\n\n")[0])
    p.add_argument("--transport", choices=TRANSPORTS, default="embedded")
    p.add_argument("--channel", metavar="NAME", help="the bus (default per transport; vcan0)")
    p.add_argument("--frames", type=argtypes.count, default=None, metavar="N",
                   help="frames to send (default 100000 unless --seconds)")
    p.add_argument("--seconds", type=argtypes.positive, default=None, metavar="S",
                   help="send for S seconds (with --frames: whichever comes first)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--time-scale", type=argtypes.positive, default=0.1, metavar="X",
                   help="the loop's pace (0.1: timeouts of 200 ms and more in wall time)")
    p.add_argument("--priority", type=int, default=0, metavar="0..99",
                   help="SCHED_FIFO priority of the loop (0: none)")
    p.add_argument("--bursts", type=argtypes.count, default=3, metavar="N",
                   help="bursts of --burst-frames unknown frames back to back (3)")
    p.add_argument("--burst-frames", type=argtypes.count, default=BURST_FRAMES, metavar="N")
    p.add_argument("--silent-restarts", type=argtypes.count, default=2, metavar="N",
                   help="TCU restarts after a silence past the timeout (2)")
    p.add_argument("--fd", action=argparse.BooleanOptionalAction, default=None,
                   help="send CAN FD frames (default: yes, on SocketCAN only with --fd: "
                        "the interface needs an MTU of 72)")
    p.add_argument("--xcp-packets", type=argtypes.count, default=2000, metavar="N",
                   help="malformed XCP datagrams to the server's slave (0: no XCP)")
    p.add_argument("--json", default="out/fuzz.json", metavar="FILE")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 0 <= args.priority <= 99:
        print("fuzz: error: --priority must be 0..99", file=sys.stderr)
        return 2
    if args.frames is None and args.seconds is None:
        args.frames = 100_000
    if args.frames is None:
        args.frames = 0
    try:
        r = run_fuzz(args)
    except FuzzError as e:
        print(f"fuzz: error: {e}", file=sys.stderr)
        return 1
    print(format_table(r), flush=True)
    if args.json:
        write_figures(args.json, r, indent=1)
    if r["interrupted"]:
        return 130
    return 0 if r["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
