"""The XCP slave's C sender (rt_loop/csrc/rt_xcp_send.h, driven by
rt_loop.measure.xcp.transport): DTOs packed, framed and sent by a C thread.

* its packing byte for byte as the protocol layer's ``Slave.dto_packet``
  (the same layout: lists running or not, timestamps, ODT sizes);
* its framing on a raw master socket: one CTR sequence for Python's
  responses and the DTOs, the overload event, drops counted when no master
  is there, a TCP master that vanishes;
* the whole chain on the running loop with pyxcp as the master, over UDP and
  TCP, while a CPU-bound Python thread runs in the process: 100 signals on
  the tick event, every tick's row received with its values and the tick's
  deadline as timestamp;
* start, stop, a master that vanishes: no sender thread left, the next
  master served.
Every assertion is about behaviour; waits only bound a failure.
"""

import os
import random
import socket
import struct
import time

import pytest
from requires import built_with, module

from rt_loop._rt_loop import ffi, lib

built_with(lib, "rt_xcp_sender_new")
module("pyxcp")

from test_xcp_loop import SIM_TIME, TAU_RISE, TICKS, Loop
from test_xcp_protocol import FakeDaq, FakeMemory, Measured, Raw, pyxcp_master
from waiting import wait_for

from rt_loop.measure.xcp import XcpServer
from rt_loop.measure.xcp import protocol as xp
from rt_loop.measure.xcp.protocol import Dto, Slave
from rt_loop.measure.xcp.transport import (
    CSender,
    StreamDeframer,
    deframe_datagram,
    delay_percentiles_us,
    sender_layout,
)
from rt_loop.tools.bench_xcp_daq import Busy, Master, summary, window_rows
from rt_loop.tools.xcp_bench import measurable_doubles

SIGNALS = 100
PERIOD_US = 500


def configured_slave(timestamps=(True, False, True), running=(True, False, True)):
    """A Slave over the fakes with three DAQ lists: list 0 two ODTs (8 + 12
    bytes), list 1 one ODT (4 bytes), list 2 three ODTs (248, 100, 1 bytes;
    its first ODT 240 bytes when it has a timestamp)."""
    memory = FakeMemory()
    slave = Slave(memory, FakeDaq(memory))
    odts = {0: [[8], [4, 8]], 1: [[4]], 2: [[240 if timestamps[2] else 248], [100], [1]]}

    def cmd(*packet):
        answer = slave.handle(bytes(packet))
        assert answer and answer[0][0] == xp.PID_RES, (packet, answer)

    cmd(xp.CONNECT, 0)
    cmd(xp.FREE_DAQ)
    cmd(xp.ALLOC_DAQ, 0, len(odts), 0)
    for d, lst in odts.items():
        cmd(xp.ALLOC_ODT, 0, d, 0, len(lst))
    for d, lst in odts.items():
        for o, entries in enumerate(lst):
            cmd(xp.ALLOC_ODT_ENTRY, 0, d, 0, o, len(entries))
    for d, lst in odts.items():
        for o, entries in enumerate(lst):
            cmd(xp.SET_DAQ_PTR, 0, d, 0, o, 0)
            for size in entries:
                cmd(xp.WRITE_DAQ, 0xFF, size, 0, *struct.pack("<I", 16))
        mode = 0x10 if timestamps[d] else 0
        cmd(xp.SET_DAQ_LIST_MODE, mode, d, 0, 0, 0, 1, 0)
    for d in odts:
        if running[d]:
            cmd(xp.START_STOP_DAQ_LIST, 1, d, 0)
    return slave


def c_dtos(dtos):
    buf = ffi.new("rt_dto[]", max(1, len(dtos)))
    for k, d in enumerate(dtos):
        x = buf[k]
        x.time_ns, x.list, x.odt, x.len = d.time_ns, d.list, d.odt, len(d.data)
        ffi.memmove(x.data, d.data, len(d.data))
    return buf


def c_pack(layout, dto):
    out = ffi.new("uint8_t[]", lib.RT_XCP_MAX_PACKET)
    n = lib.rt_xcp_pack_dto(layout, c_dtos([dto]), out)
    return bytes(ffi.buffer(out, n)) if n >= 0 else n


def sender_threads():
    """The process's threads named as the C sender names its own."""
    names = []
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/comm") as f:
                names.append(f.read().strip())
        except OSError:
            pass
    return names.count("xcp-tx")


# ---- the packing -----------------------------------------------------------------

@pytest.mark.parametrize("timestamps", [(True, False, True), (False, True, False)])
def test_the_c_packing_is_the_protocol_layers_byte_for_byte(timestamps):
    slave = configured_slave(timestamps)
    layout, ok = sender_layout(slave._dto_views)
    assert ok
    sizes = {(k, o): s for k, v in enumerate(slave._dto_views) for o, s in enumerate(v.sizes)}
    rng = random.Random(27)
    checked = {"packet": 0, -1: 0, -2: 0}
    for _ in range(3000):
        lst, odt = rng.randrange(4), rng.randrange(4)
        size = sizes.get((lst, odt), rng.randrange(1, 249))
        if rng.random() < 0.1:
            size = rng.randrange(1, 249)                     # an older configuration's
        t = rng.choice((rng.randrange(0, 1 << 62), rng.randrange(-(1 << 40), 0),
                        (1 << 32) * 1000 + rng.randrange(10**6)))
        dto = Dto(lst, odt, t, bytes(rng.getrandbits(8) for _ in range(size)))
        want, got = slave.dto_packet(dto), c_pack(layout, dto)
        if want is None:
            assert got in (-1, -2)
            checked[got] += 1
        else:
            assert got == want
            checked["packet"] += 1
    assert all(checked.values()), checked          # packets, not running and stale all seen
    c = slave.counters()["dto_dropped"]
    assert c == {"not_running": checked[-1], "stale": checked[-2]}


def test_a_layout_beyond_the_senders_bounds_runs_no_list():
    slave = configured_slave()
    views = slave._dto_views * 11                                # 33 lists > RT_DAQ_MAX_LISTS
    layout, ok = sender_layout(views)
    assert not ok and layout.n_lists == 0
    s = CSender(ffi.NULL, "tcp")
    try:
        assert not s.set_layout(views)
        assert s.set_layout(slave._dto_views)
    finally:
        s.close()


# ---- the framing on a raw master socket -------------------------------------------

def recv_frames(sock, n):
    """(CTR, packet) of the next n frames on a UDP socket."""
    out = []
    sock.settimeout(10)
    while len(out) < n:
        data = sock.recv(65536)
        bad = {}
        packets = list(deframe_datagram(data, lib.RT_XCP_MAX_PACKET, bad))
        assert not bad
        at = 0
        for p in packets:
            out.append((struct.unpack_from("<H", data, at + 2)[0], p))
            at += 4 + len(p)
    return out


def test_responses_and_dtos_share_one_ctr_sequence_and_overload_is_an_event():
    slave = configured_slave()
    ours = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ours.bind(("127.0.0.1", 0))
    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    s = CSender(ffi.NULL, "udp", ours.fileno())
    try:
        assert s.set_layout(slave._dto_views)
        s.start()
        t = 1_234_567_891_000
        dtos = [Dto(0, 0, t, bytes(range(8))), Dto(0, 1, t, bytes(12)), Dto(2, 2, t, b"\x07"),
                Dto(1, 0, t, bytes(4)),                        # list 1 does not run
                Dto(0, 1, t, bytes(3))]                        # stale
        assert s.feed(c_dtos(dtos[:1]), 1, 0) == 1             # no master yet
        wait_for(lambda: s.stats()["no_master"] == 1, "the DTO counted without a master")
        s.set_peer(master.getsockname())
        assert s.send([bytes([xp.PID_RES, 1, 2]), bytes([xp.PID_ERR, xp.ERR_CMD_BUSY])]) == 2
        assert s.feed(c_dtos(dtos), len(dtos), 0) == len(dtos)
        frames = recv_frames(master, 5)
        assert [c for c, _ in frames] == [0, 1, 2, 3, 4]
        assert [p for _, p in frames] == [bytes([xp.PID_RES, 1, 2]),
                                          bytes([xp.PID_ERR, xp.ERR_CMD_BUSY]),
                                          *(slave.dto_packet(d) for d in dtos[:3])]
        s.feed(c_dtos([]), 0, 7)                               # the producer lost 7
        assert recv_frames(master, 1) == [(5, bytes([xp.PID_EV, xp.EV_DAQ_OVERLOAD]))]
        assert s.send([bytes([xp.PID_RES])]) == 1              # nothing new lost: no event
        assert recv_frames(master, 1) == [(6, bytes([xp.PID_RES]))]
        s.set_peer(master.getsockname())                      # a new master: CTR from 0
        s.send([bytes([xp.PID_RES, 9])])
        assert recv_frames(master, 1) == [(0, bytes([xp.PID_RES, 9]))]
        st = s.stats()
        assert (st["packets_out"], st["dtos_out"], st["dtos_packed"]) == (8, 3, 4)
        assert (st["not_running"], st["stale"], st["overload_events"]) == (1, 1, 1)
        assert st["delays"] == 3 and sum(s.delays()) == 3
    finally:
        s.close()
        ours.close()
        master.close()
    assert sender_threads() == 0
    assert s.stats()["packets_out"] == 8                       # still readable once closed


def test_a_tcp_master_that_vanishes_is_let_go_counted_and_never_blocks():
    slave = configured_slave()
    listener = socket.create_server(("127.0.0.1", 0))
    master = socket.create_connection(listener.getsockname())
    conn, _ = listener.accept()
    conn.setblocking(False)
    s = CSender(ffi.NULL, "tcp")
    try:
        s.set_layout(slave._dto_views)
        s.start()
        s.set_tcp(conn.fileno())
        t = 5_000_000_000
        dtos = [Dto(0, k % 2, t + 500_000 * k, bytes(8 if k % 2 == 0 else 12)) for k in range(40)]
        s.send([bytes([xp.PID_RES])])
        s.feed(c_dtos(dtos), len(dtos), 0)
        deframer, got = StreamDeframer(lib.RT_XCP_MAX_PACKET, {}), []
        master.settimeout(10)
        while len(got) < 41:
            got += deframer.feed(master.recv(65536))
        assert got == [bytes([xp.PID_RES]), *(slave.dto_packet(d) for d in dtos)]
        master.close()                                         # gone without a word
        for _ in range(50):                                    # DTOs go on coming
            s.feed(c_dtos(dtos), len(dtos), 0)
            time.sleep(0.002)
        wait_for(lambda: s.stats()["send_errors"], "the send error of a vanished master")
        assert set(s.stats()["send_errors"]) <= {"EPIPE", "ECONNRESET"}
        s.set_tcp(-1)                                          # let go of it
        s.feed(c_dtos(dtos[:2]), 2, 0)
        wait_for(lambda: s.stats()["no_master"] >= 2, "DTOs without a master counted")
    finally:
        s.close()
        conn.close()
        listener.close()
    assert sender_threads() == 0


@pytest.mark.parametrize("protocol", ["udp", "tcp"])
def test_a_server_stopped_under_a_connected_master_ends_clean(protocol):
    memory = FakeMemory()
    srv = XcpServer(memory=memory, daq=FakeDaq(memory), port=0, protocol=protocol)
    srv.start()
    raw = Raw(srv)
    try:
        assert raw.command(xp.CONNECT, 0)[0] == xp.PID_RES
        assert sender_threads() == 1
        srv.stop()                                             # the master still there
        assert sender_threads() == 0
        c = srv.counters()
        assert c["transport"]["packets_out"] == 1 and c["transport"]["error"] is None
    finally:
        raw.close()


# ---- the chain on the running loop, pyxcp as the master ------------------------------

def signal_measurements(n=SIGNALS):
    """(name, address, extension, type) of n signals: the tick counter, the plant
    time, a parameter, and plant doubles."""
    measurements = [("ticks", TICKS, 0, "U64"), ("sim_time", SIM_TIME, 0, "F64"),
                    ("tau_rise", TAU_RISE, 0, "F64")]
    return measurements + [(name, off, 0, "F64") for name, off in measurable_doubles(ffi, n - 3)]


def signal_lists(n=SIGNALS):
    from pyxcp.daq_stim import DaqList

    return [DaqList(name="tick", event_num=0, stim=False, enable_timestamps=True,
                    measurements=signal_measurements(n), priority=0, prescaler=1)]


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["udp", "tcp"])
def test_pyxcp_gets_every_ticks_row_of_100_signals_while_python_is_busy(protocol):
    # pyxcp in a process of its own: only the server's process carries the busy thread
    loop = Loop()
    srv = XcpServer(ffi, lib, loop.c, port=0, protocol=protocol, a2l_text=lambda: "/* A2L */")
    measurements = signal_measurements()
    loop.start()
    tau = loop.double(TAU_RISE)
    try:
        with srv:
            assert sender_threads() == 1
            master = Master(tuple(srv.address), protocol, measurements,
                            ("ticks", "sim_time", "tau_rise"))
            try:
                master.start()
                with Busy() as busy:
                    seen = int(loop.c.stats.ticks)
                    wait_for(lambda: loop.c.stats.ticks >= seen + 4000, "2 s of ticks")
                stamps, cols = master.stop()
            finally:
                master.kill()
            skipped = int(loop.c.stats.skipped_ticks)
            c = srv.counters()
            st = srv.server.sender_stats()
        assert busy.rounds > 10                                # it did run beside
    finally:
        loop.stop()
    assert master.odts == 4                                    # 100 x 8 bytes: 4 DTOs a row
    ticks, sim = cols["ticks"], cols["sim_time"]
    assert len(ticks) >= 4000
    assert all(b - a == 1 for a, b in zip(ticks, ticks[1:]))   # no row lost, none repeated
    steps = [b - a for a, b in zip(sim, sim[1:])]
    assert all(abs(s - PERIOD_US * 1e-6) < 1e-9 for s in steps)   # each row one tick's values
    assert set(cols["tau_rise"]) == {tau}                      # a parameter as the loop has it
    us = [t // 1000 for t in stamps]                           # pyxcp gives them in ns
    deltas = [b - a for a, b in zip(us, us[1:])]
    assert all(d > 0 and d % PERIOD_US == 0 for d in deltas)   # tick deadlines, 500 us apart
    assert sum(d // PERIOD_US - 1 for d in deltas) <= skipped  # beyond: deadlines the loop skipped
    assert c["transport"]["dtos_out"] >= 4 * len(ticks)
    assert c["transport"]["error"] is None and c["loop"]["daq_ring_dropped"] == 0
    assert st["delays"] >= 4 * len(ticks) and st["delay_us"]["p50"] is not None
    assert sender_threads() == 0


def test_the_loops_ring_overflowing_is_an_overload_event_to_the_master():
    loop = Loop()
    srv = XcpServer(ffi, lib, loop.c, port=0, protocol="udp")
    loop.start()
    try:
        with srv:
            raw = Raw(srv)
            assert raw.command(xp.CONNECT, 0)[0] == xp.PID_RES
            for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 1, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                           (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1), (xp.SET_DAQ_PTR, 0, 0, 0, 0, 0),
                           (xp.WRITE_DAQ, 0xFF, 8, 0, *struct.pack("<I", TICKS)),
                           (xp.START_STOP_DAQ_LIST, 1, 0, 0)):
                assert raw.command(*packet)[0] == xp.PID_RES
            assert raw.recv()[:4] == bytes([0, 0, 0, 0])          # DTOs of list 0 come
            # what the tick does when the ring is full: it counts the DTOs it could not copy
            loop.c.daq_ring.dropped += 3
            events = []
            for _ in range(4000):                                  # DTOs come before and after
                events += [p for _, p in recv_frames(raw.sock, 1) if p[0] == xp.PID_EV]
                if events:
                    break
            assert events == [bytes([xp.PID_EV, xp.EV_DAQ_OVERLOAD])]
            raw.close()
        assert srv.counters()["protocol"]["overload_events"] == 1
    finally:
        loop.stop()


@pytest.mark.slow
def test_start_stop_and_a_vanished_master_leave_no_sender_and_serve_the_next():
    loop = Loop()
    loop.start()
    try:
        for protocol in ("udp", "tcp", "udp"):
            srv = XcpServer(ffi, lib, loop.c, port=0, protocol=protocol)
            policy = Measured(signal_lists(8))
            with srv:
                assert sender_threads() == 1
                with pyxcp_master(srv, policy=policy) as x:
                    x.connect()
                    policy.setup()
                    policy.start()
                    wait_for(lambda p=policy: len(p.rows) >= 20, "rows")
                    # gone without stopping its DAQ or disconnecting
                again = Measured(signal_lists(8))
                with pyxcp_master(srv, policy=again) as x:
                    x.connect()
                    again.setup()
                    again.start()
                    wait_for(lambda p=again: len(p.rows) >= 20, "rows for the next master")
                    again.stop()
                    x.disconnect()
                c = srv.counters()
                assert c["transport"]["masters"] == 2 and c["transport"]["error"] is None
            assert sender_threads() == 0
            assert srv.counters()["transport"]["dtos_out"] >= 40
    finally:
        loop.stop()


def test_delay_percentiles_of_a_histogram():
    hist = [0] * 10
    hist[2], hist[5], hist[9] = 50, 49, 1
    assert delay_percentiles_us(hist) == {"p50": 3, "p99": 6, "p99.9": 10}
    assert delay_percentiles_us([0, 0]) == {"p50": None, "p99": None, "p99.9": None}


def test_the_benchmarks_windows_count_the_ticks_missing_and_pool_the_delays():
    assert window_rows([5, 6, 8, 9, 30], 6, 10) == {"expected": 4, "received": 3, "lost": 1}
    assert window_rows([1, 2], 6, 10) == {"expected": 5, "received": 0, "lost": 5}

    def window(case, hist, lost):
        return {"case": case, "delay_hist_us": hist, "dtos_expected": 40, "dtos_received": 40 - lost,
                "rows": {"expected": 10, "received": 10 - lost, "lost": lost}}

    runs = [{"protocol": "udp", "windows": [window("busy", {3: 98, 40: 2}, 1),
                                            window("quiet", {2: 100}, 0),
                                            window("busy", {3: 100}, 0)]}]
    busy = summary(runs)["udp"]["busy"]
    assert (busy["rows_lost"], busy["dtos_expected"], busy["dtos_received"]) == (1, 80, 79)
    assert (busy["delay_p50_us"], busy["delay_p99_us"], busy["delay_max_us"]) == (4, 4, 41)
    assert summary(runs)["udp"]["quiet"]["delay_p99_9_us"] == 3
