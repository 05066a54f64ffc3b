"""The XCP on Ethernet slave (rt_loop/measure/xcp/) against fake backends.

The protocol layer alone (rt_loop.measure.xcp.protocol.Slave fed with command
packets), the framing (rt_loop.measure.xcp.transport), and the whole server over
UDP and TCP on loopback with pyxcp as the master: CONNECT, GET_ID and the
A2L upload, UPLOAD/DOWNLOAD and refused writes, the calibration pages,
dynamic DAQ of 20 entries decoded by pyxcp's own DAQ machinery, seed &
key, malformed packets, masters that vanish.

The memory is a bytearray (``FakeMemory``); the DAQ producer (``FakeDaq``)
measures it whenever the test (or a producer thread) calls ``tick()``,
stamping each DTO with CLOCK_MONOTONIC. Every assertion is about behaviour;
waits only bound a failure (tests/waiting.py).
"""

import contextlib
import logging
import socket
import struct
import threading
import time
from collections import deque

import pytest
import requires

requires.module("pyxcp")

from pyxcp.config import (
    create_application_from_config,
    reset_application,
    set_application,
)
from pyxcp.daq_stim import DaqList, DaqOnlinePolicy
from pyxcp.master import Master
from pyxcp.types import XcpResponseError
from waiting import wait_until

from rt_loop.measure.xcp import XcpServer, parse_address
from rt_loop.measure.xcp import protocol as xp
from rt_loop.measure.xcp.protocol import (
    OK,
    Daq,
    DaqEntry,
    Dto,
    Event,
    Limits,
    Memory,
    Slave,
    compute_key,
    read_secret,
    seed_n_key_function,
)
from rt_loop.measure.xcp.transport import (
    TCP_QUEUE_BYTES,
    StreamDeframer,
    deframe_datagram,
    frame,
)

MEM_SIZE = 8192
COUNTERS = 0              # 20 U32 counters: n * 100 + k at tick n
PATTERN = 512             # 280 bytes of a fixed pattern (a second DAQ list)
CAL = (1024, 256)         # the calibration region (paged)
DATA = (2048, 64)         # writable, not paged
REFUSE_AT = 1100          # 0xFF written here: refused like parameters the plant refuses
A2L = "".join(f"/* line {k:05d} of the A2L file */\n" for k in range(400))   # > 15 kB
SECRET = b"0123456789abcdef-the-shared-secret"

logging.getLogger("pyxcp").setLevel(logging.CRITICAL)


class FakeMemory(Memory):
    def __init__(self):
        self.b = bytearray(MEM_SIZE)
        self.b[CAL[0]:CAL[0] + CAL[1]] = bytes(range(CAL[1]))
        self.b[PATTERN:PATTERN + 280] = bytes((7 * k + 3) & 0xFF for k in range(280))
        self.lock = threading.Lock()

    def read(self, address, n):
        if address < 0 or address + n > MEM_SIZE:
            return xp.ERR_ACCESS_DENIED
        with self.lock:
            return bytes(self.b[address:address + n])

    def write(self, address, data):
        if address < 0 or address + len(data) > MEM_SIZE:
            return xp.ERR_ACCESS_DENIED
        if not any(a <= address and address + len(data) <= a + n for a, n in (CAL, DATA)):
            return xp.ERR_WRITE_PROTECTED
        if address <= REFUSE_AT < address + len(data) and data[REFUSE_AT - address] == 0xFF:
            return xp.ERR_OUT_OF_RANGE
        with self.lock:
            self.b[address:address + len(data)] = data
        return OK

    def cal_regions(self):
        return [CAL]


class FakeDaq(Daq):
    """Measures FakeMemory at each tick(), as the loop does at its events."""

    def __init__(self, memory):
        self.memory = memory
        self.config = ()
        self.applied = []
        self.queue = deque()
        self.ticks = 0
        self.lost = 0

    def apply(self, lists):
        self.config = tuple(lists)
        self.applied.append(self.config)
        return OK

    def tick(self):
        self.ticks += 1
        with self.memory.lock:
            for k in range(20):
                struct.pack_into("<I", self.memory.b, COUNTERS + 4 * k, self.ticks * 100 + k)
        now = time.monotonic_ns()
        for i, d in enumerate(self.config):
            if not d.running or self.ticks % d.prescaler:
                continue
            for o, odt in enumerate(d.odts):
                data = b"".join(self.memory.read(e.address, e.size) for e in odt)
                self.queue.append(Dto(i, o, now, data))

    def pop(self, n):
        out = []
        while self.queue and len(out) < n:
            out.append(self.queue.popleft())
        return out

    def dropped(self):
        return self.lost

    def running(self):
        return [d.running for d in self.config]


@pytest.fixture
def fakes():
    memory = FakeMemory()
    return memory, FakeDaq(memory)


def make_server(fakes, protocol, **kws):
    memory, daq = fakes
    kws.setdefault("a2l_text", lambda: A2L)
    return XcpServer(memory=memory, daq=daq, port=0, protocol=protocol, a2l_name="dct_hil", **kws)


@pytest.fixture(params=["udp", "tcp"])
def server(request, fakes):
    srv = make_server(fakes, request.param)
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture
def producer(fakes):
    """A thread ticking FakeDaq until the test ends."""
    _, daq = fakes
    stop = threading.Event()

    def run():
        while not stop.is_set():
            daq.tick()
            stop.wait(0.001)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    yield daq
    stop.set()
    t.join()


@contextlib.contextmanager
def pyxcp_master(srv, secret=None, policy=None):
    host, port = srv.address
    general = {"disable_error_handling": True}
    if secret is not None:
        general["seed_n_key_function"] = seed_n_key_function(secret)
    app = create_application_from_config(
        {"Transport": {"Eth": {"host": host, "port": port, "protocol": srv.protocol.upper(),
                               "tcp_nodelay": True}},
         "General": general},
        log_level=logging.CRITICAL)
    set_application(app)        # pyxcp's DAQ processor asks for the application
    try:
        with Master("eth", config=app, policy=policy) as x:
            yield x
    finally:
        reset_application()


def error_of(excinfo):
    return str(excinfo.value.args[0]) if excinfo.value.args else str(excinfo.value)


class Raw:
    """A master written here: frames as given, responses as they come."""

    def __init__(self, srv, rcvbuf=None):
        self.protocol = srv.protocol
        kind = socket.SOCK_DGRAM if self.protocol == "udp" else socket.SOCK_STREAM
        self.sock = socket.socket(socket.AF_INET, kind)
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(10)
        self.sock.connect(srv.address)
        self.ctr = 0
        self.buf = b""

    def send_raw(self, data):
        self.sock.send(data)

    def send(self, packet):
        self.send_raw(frame(self.ctr, bytes(packet)))
        self.ctr += 1

    def recv(self):
        """The next packet from the slave."""
        if self.protocol == "udp":
            data = self.sock.recv(65536)
            length, _ = struct.unpack_from("<HH", data)
            return data[4:4 + length]
        while True:
            if len(self.buf) >= 4:
                length, _ = struct.unpack_from("<HH", self.buf)
                if len(self.buf) >= 4 + length:
                    packet, self.buf = self.buf[4:4 + length], self.buf[4 + length:]
                    return packet
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed by the slave")
            self.buf += data

    def command(self, *packet):
        """The response (or error) to one command, DTOs and events skipped."""
        self.send(bytes(packet))
        while True:
            response = self.recv()
            if response[0] in (xp.PID_RES, xp.PID_ERR):
                return response

    def close(self):
        self.sock.close()


def cmd(slave, *packet):
    """The slave's only answer to one command packet (None: no answer)."""
    out = slave.handle(bytes(packet))
    assert len(out) <= 1
    return out[0] if out else None


def connected_slave(fakes, **kws):
    memory, daq = fakes
    slave = Slave(memory, daq, **kws)
    assert cmd(slave, xp.CONNECT, 0)[0] == xp.PID_RES
    return slave


def err(code):
    return bytes([xp.PID_ERR, code])


POSITIVE = bytes([xp.PID_RES])


# ---- the protocol layer alone ------------------------------------------------

def test_connect_declares_resources_byte_order_and_packet_sizes(fakes):
    slave = Slave(*fakes)
    # CAL/PAG + DAQ; optional comm mode info, Intel, byte granularity; MAX_CTO 252;
    # MAX_DTO 252 (4-byte identification field + 248 data bytes); versions 1, 1
    assert cmd(slave, xp.CONNECT, 0) == bytes([0xFF, 0x05, 0x80, 252, 252, 0, 1, 1])
    assert slave.max_dto == xp.DTO_HEADER_BYTES + Limits().odt_bytes
    assert cmd(slave, xp.GET_STATUS) == bytes([0xFF, 0, 0, 0, 0, 0])


def test_before_connect_only_connect_is_answered_and_the_rest_is_counted(fakes):
    slave = Slave(*fakes)
    assert cmd(slave, xp.GET_STATUS) is None
    assert cmd(slave, xp.SET_MTA, 0, 0, 0, 0, 0, 0, 0) is None
    assert cmd(slave) is None
    assert slave.counters()["ignored"] == {"not_connected": 2, "empty": 1}
    assert cmd(slave, xp.CONNECT, 7) == err(xp.ERR_OUT_OF_RANGE)      # unknown mode
    assert cmd(slave, xp.CONNECT, 0)[0] == xp.PID_RES
    assert cmd(slave, xp.GET_STATUS)[0] == xp.PID_RES


def test_unknown_commands_wrong_lengths_and_synch_answer_errors_counted_by_name(fakes):
    slave = connected_slave(fakes)
    assert cmd(slave, 0xD1, 0, 0, 0, 0, 0) == err(xp.ERR_CMD_UNKNOWN)      # PROGRAM_CLEAR
    assert cmd(slave, 0xD0, 1, 2) == err(xp.ERR_CMD_UNKNOWN)               # PROGRAM
    assert cmd(slave, xp.LEVEL_1, 0x7F) == err(xp.ERR_CMD_UNKNOWN)
    assert cmd(slave, xp.LEVEL_1) == err(xp.ERR_CMD_SYNTAX)
    assert cmd(slave, xp.SET_MTA, 0, 0, 0) == err(xp.ERR_CMD_SYNTAX)       # no address
    assert cmd(slave, xp.GET_ID) == err(xp.ERR_CMD_SYNTAX)
    assert cmd(slave, xp.DOWNLOAD, 10, 1, 2, 3) == err(xp.ERR_CMD_SYNTAX)  # 3 of 10 bytes
    assert cmd(slave, xp.UPLOAD, 0) == err(xp.ERR_OUT_OF_RANGE)
    assert cmd(slave, xp.UPLOAD, 252) == err(xp.ERR_OUT_OF_RANGE)          # > MAX_CTO - 1
    assert cmd(slave, xp.SET_MTA, 0, 0, 1, 0, 0, 0, 0) == err(xp.ERR_OUT_OF_RANGE)  # extension 1
    assert cmd(slave, xp.SYNCH) == err(xp.ERR_CMD_SYNCH)
    c = slave.counters()
    assert c["errors"] == {"ERR_CMD_UNKNOWN": 3, "ERR_CMD_SYNTAX": 4, "ERR_OUT_OF_RANGE": 3,
                           "ERR_CMD_SYNCH": 1}
    assert c["commands"] == 12 and c["positive"] == 1                      # the CONNECT


def test_trailing_bytes_are_allowed(fakes):
    slave = connected_slave(fakes)
    assert cmd(slave, xp.GET_STATUS, 0, 0, 0, 0, 0, 0, 0)[0] == xp.PID_RES
    assert cmd(slave, xp.SHORT_UPLOAD, 2, 0, 0, *struct.pack("<I", CAL[0]), 0xAA) == \
        POSITIVE + bytes([0, 1])


def test_memory_errors_pass_through_and_the_mta_advances(fakes):
    slave = connected_slave(fakes)
    assert cmd(slave, xp.SET_MTA, 0, 0, 0, *struct.pack("<I", CAL[0] + 4)) == POSITIVE
    assert cmd(slave, xp.UPLOAD, 2) == POSITIVE + bytes([4, 5])
    assert cmd(slave, xp.UPLOAD, 2) == POSITIVE + bytes([6, 7])
    assert cmd(slave, xp.DOWNLOAD, 2, 0xA1, 0xA2) == POSITIVE               # at CAL + 8
    assert fakes[0].b[CAL[0] + 8:CAL[0] + 10] == b"\xa1\xa2"
    assert cmd(slave, xp.SET_MTA, 0, 0, 0, *struct.pack("<I", MEM_SIZE - 1)) == POSITIVE
    assert cmd(slave, xp.UPLOAD, 2) == err(xp.ERR_ACCESS_DENIED)
    assert cmd(slave, xp.SHORT_DOWNLOAD, 1, 0, 0, *struct.pack("<I", 0), 1) == \
        err(xp.ERR_WRITE_PROTECTED)
    assert cmd(slave, xp.SHORT_DOWNLOAD, 1, 0, 0, *struct.pack("<I", REFUSE_AT), 0xFF) == \
        err(xp.ERR_OUT_OF_RANGE)


def test_get_id_name_a2l_name_epk_and_a2l_by_upload(fakes):
    slave = connected_slave(fakes, name="dct-hil plant", a2l_name="dct_hil",
                            a2l_text=lambda: "A2L!", epk="dct-hil 0.1.0 0123")
    assert cmd(slave, xp.GET_ID, 5) == POSITIVE + bytes([1, 0, 0, 18, 0, 0, 0]) + \
        b"dct-hil 0.1.0 0123"
    assert cmd(slave, xp.GET_ID, 0) == POSITIVE + bytes([1, 0, 0]) + struct.pack("<I", 13) + \
        b"dct-hil plant"
    assert cmd(slave, xp.GET_ID, 1) == POSITIVE + bytes([1, 0, 0, 7, 0, 0, 0]) + b"dct_hil"
    assert cmd(slave, xp.GET_ID, 4) == POSITIVE + bytes([0, 0, 0, 4, 0, 0, 0])  # by UPLOAD
    assert cmd(slave, xp.UPLOAD, 4) == POSITIVE + b"A2L!"
    assert cmd(slave, xp.UPLOAD, 1) == err(xp.ERR_OUT_OF_RANGE)            # past its end
    assert cmd(slave, xp.DOWNLOAD, 1, 0) == err(xp.ERR_WRITE_PROTECTED)     # not memory
    assert cmd(slave, xp.GET_ID, 3) == POSITIVE + bytes(7)                  # no URL: length 0


def test_page_info_segment_info_and_page_errors(fakes):
    slave = connected_slave(fakes)
    assert cmd(slave, xp.GET_PAG_PROCESSOR_INFO) == POSITIVE + bytes([1, 0])
    assert cmd(slave, xp.GET_PAGE_INFO, 0, 0, 0) == POSITIVE + bytes([0x3F, 0])
    assert cmd(slave, xp.GET_PAGE_INFO, 0, 0, 1) == POSITIVE + bytes([0x0F, 0])  # no XCP writes
    assert cmd(slave, xp.GET_PAGE_INFO, 0, 0, 2) == err(xp.ERR_PAGE_NOT_VALID)
    assert cmd(slave, xp.GET_PAGE_INFO, 0, 1, 0) == err(xp.ERR_SEGMENT_NOT_VALID)
    assert cmd(slave, xp.GET_SEGMENT_INFO, 0, 0, 0, 0) == POSITIVE + bytes(3) + \
        struct.pack("<I", CAL[0])
    assert cmd(slave, xp.GET_SEGMENT_INFO, 2, 0, 0, 0) == err(xp.ERR_OUT_OF_RANGE)  # no mapping
    assert cmd(slave, xp.GET_SEGMENT_INFO, 3, 0, 0, 0) == err(xp.ERR_MODE_NOT_VALID)
    assert cmd(slave, xp.SET_CAL_PAGE, 0x00, 0, 1) == err(xp.ERR_MODE_NOT_VALID)
    assert cmd(slave, xp.GET_CAL_PAGE, 0x03, 0) == err(xp.ERR_MODE_NOT_VALID)


def test_daq_allocation_beyond_the_loop_limits_is_a_memory_overflow(fakes):
    limits = Limits()
    slave = connected_slave(fakes)
    assert cmd(slave, xp.FREE_DAQ) == POSITIVE
    assert cmd(slave, xp.ALLOC_DAQ, 0, *struct.pack("<H", limits.max_lists + 1)) == \
        err(xp.ERR_MEMORY_OVERFLOW)
    assert cmd(slave, xp.ALLOC_DAQ, 0, *struct.pack("<H", limits.max_lists)) == POSITIVE
    assert cmd(slave, xp.ALLOC_DAQ, 0, 1, 0) == err(xp.ERR_SEQUENCE)       # only after FREE_DAQ
    for n in range(2):                                                      # 2 x 252 ODTs
        assert cmd(slave, xp.ALLOC_ODT, 0, n, 0, 252) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT, 0, 2, 0, 9) == err(xp.ERR_MEMORY_OVERFLOW)  # 513 > 512
    assert cmd(slave, xp.ALLOC_ODT, 0, 2, 0, 8) == POSITIVE                 # 512
    assert cmd(slave, xp.ALLOC_ODT, 0, 2, 0, 1) == err(xp.ERR_SEQUENCE)     # allocated already
    assert cmd(slave, xp.ALLOC_ODT, 0, 99, 0, 1) == err(xp.ERR_OUT_OF_RANGE)  # no list 99
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 249) == err(xp.ERR_MEMORY_OVERFLOW)
    for odt in range(16):                                                   # 16 x 248 = 3968
        assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, 0, 0, odt, 248) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, 0, 0, 16, 129) == err(xp.ERR_MEMORY_OVERFLOW)
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, 0, 0, 16, 128) == POSITIVE     # 4096
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, 0, 0, 17, 1) == err(xp.ERR_MEMORY_OVERFLOW)
    assert cmd(slave, xp.ALLOC_ODT, 0, 3, 0, 1) == err(xp.ERR_SEQUENCE)     # entries came
    assert slave.counters()["errors"]["ERR_MEMORY_OVERFLOW"] == 5


def test_odt_bytes_beyond_one_dto_are_a_memory_overflow_and_bad_entries_out_of_range(fakes):
    slave = connected_slave(fakes)
    for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 1, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                   (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 3), (xp.SET_DAQ_PTR, 0, 0, 0, 0, 0)):
        assert cmd(slave, *packet) == POSITIVE

    def write_daq(size, address=0, bit=0xFF, ext=0):
        return cmd(slave, xp.WRITE_DAQ, bit, size, ext, *struct.pack("<I", address))

    assert write_daq(249) == err(xp.ERR_OUT_OF_RANGE)                      # one entry > 248
    assert write_daq(4, bit=3) == err(xp.ERR_OUT_OF_RANGE)                 # no bit entries
    assert write_daq(4, ext=1) == err(xp.ERR_OUT_OF_RANGE)
    assert write_daq(4, address=MEM_SIZE) == err(xp.ERR_ACCESS_DENIED)    # not measurable
    assert write_daq(200) == POSITIVE
    assert write_daq(48) == POSITIVE                                       # 248 bytes
    assert write_daq(1) == err(xp.ERR_MEMORY_OVERFLOW)                     # 249 > RT_DAQ_ODT_BYTES
    assert cmd(slave, xp.SET_DAQ_PTR, 0, 0, 0, 0, 1) == POSITIVE
    assert write_daq(47) == POSITIVE                                       # entry 1 replaced
    assert write_daq(1) == POSITIVE                                        # 248 again
    assert write_daq(1) == err(xp.ERR_OUT_OF_RANGE)                        # past the last entry
    assert cmd(slave, xp.SET_DAQ_PTR, 0, 0, 0, 1, 0) == err(xp.ERR_OUT_OF_RANGE)   # no ODT 1
    assert cmd(slave, xp.SET_DAQ_PTR, 0, 0, 0, 0, 0) == POSITIVE
    assert cmd(slave, xp.READ_DAQ) == POSITIVE + bytes([0xFF, 200, 0, 0, 0, 0, 0])
    # a timestamp does not fit beside 248 bytes (MAX_DTO 252 - 4 - 4 = 244)
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x10, 0, 0, 0, 0, 1, 0) == POSITIVE
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 0, 0) == err(xp.ERR_DAQ_CONFIG)
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x00, 0, 0, 0, 0, 1, 0) == POSITIVE
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 0, 0) == POSITIVE + bytes([0])
    assert fakes[1].config[0].running and fakes[1].config[0].odts == (
        (DaqEntry(0, 200), DaqEntry(0, 47), DaqEntry(0, 1)),)
    assert cmd(slave, xp.SET_DAQ_PTR, 0, 0, 0, 0, 0) == err(xp.ERR_DAQ_ACTIVE)
    assert cmd(slave, xp.GET_STATUS)[1] & 0x40                              # DAQ running


def test_daq_list_mode_checks_and_start_stop_synch(fakes):
    memory, daq = fakes
    slave = connected_slave(fakes, events=(Event("a", 0.001), Event("b", 0.01)))
    for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 2, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                   (xp.ALLOC_ODT, 0, 1, 0, 1), (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1),
                   (xp.ALLOC_ODT_ENTRY, 0, 1, 0, 0, 1)):
        assert cmd(slave, *packet) == POSITIVE
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 2, 0, 0) == err(xp.ERR_DAQ_CONFIG)  # not written
    for n in range(2):
        assert cmd(slave, xp.SET_DAQ_PTR, 0, n, 0, 0, 0) == POSITIVE
        assert cmd(slave, xp.WRITE_DAQ, 0xFF, 4, 0, *struct.pack("<I", 4 * n)) == POSITIVE
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x02, 0, 0, 0, 0, 1, 0) == err(xp.ERR_OUT_OF_RANGE)  # STIM
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x20, 0, 0, 0, 0, 1, 0) == err(xp.ERR_OUT_OF_RANGE)  # PID_OFF
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x10, 0, 0, 2, 0, 1, 0) == err(xp.ERR_OUT_OF_RANGE)  # event 2
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x10, 0, 0, 1, 0, 0, 0) == err(xp.ERR_OUT_OF_RANGE)  # prescaler 0
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0x10, 0, 0, 1, 0, 5, 3) == POSITIVE
    assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, 0, 0) == POSITIVE + bytes([0x10, 0, 0, 1, 0, 5, 3])
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 2, 0, 0) == POSITIVE + bytes([0])  # select
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 2, 1, 0) == POSITIVE + bytes([0])
    assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, 0, 0)[1] == 0x11            # selected
    assert cmd(slave, xp.START_STOP_SYNCH, 1) == POSITIVE                  # start selected
    assert daq.running() == [True, True]
    assert daq.config[0].event == 1 and daq.config[0].prescaler == 5
    assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, 0, 0)[1] == 0x50            # running, timestamp
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 0, 1, 0) == POSITIVE + bytes([0])
    assert daq.running() == [True, False]
    assert cmd(slave, xp.START_STOP_SYNCH, 0) == POSITIVE                  # stop all
    assert daq.running() == [False, False]
    assert cmd(slave, xp.START_STOP_SYNCH, 7) == err(xp.ERR_MODE_NOT_VALID)
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 0, 0) == POSITIVE + bytes([0])
    assert cmd(slave, xp.DISCONNECT) == POSITIVE                            # stops DAQ too
    assert daq.running() == [] and not slave.connected


def test_a_producer_that_refuses_leaves_the_lists_as_they_were(fakes):
    memory, _ = fakes

    class Busy(FakeDaq):
        busy = True

        def apply(self, lists):
            return xp.ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE if self.busy else super().apply(lists)

    daq = Busy(memory)
    slave = Slave(memory, daq)
    cmd(slave, xp.CONNECT, 0)
    for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 1, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                   (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1), (xp.SET_DAQ_PTR, 0, 0, 0, 0, 0),
                   (xp.WRITE_DAQ, 0xFF, 4, 0, 0, 0, 0, 0)):
        assert cmd(slave, *packet) == POSITIVE
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 0, 0) == \
        err(xp.ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE)
    assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, 0, 0)[1] & 0x40 == 0        # not running
    daq.busy = False
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 0, 0) == POSITIVE + bytes([0])
    daq.busy = True
    for packet in ((xp.FREE_DAQ,), (xp.CLEAR_DAQ_LIST, 0, 0, 0), (xp.START_STOP_SYNCH, 0)):
        assert cmd(slave, *packet) == err(xp.ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE)
        assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, 0, 0)[1] & 0x40             # still running
        assert daq.running() == [True]
    slave.reset("master gone")                                             # cannot stop it
    assert slave.counters()["daq_stop_failed"] == 1 and not slave.daq_running


def test_dto_packets_carry_the_list_the_odt_and_the_timestamp_of_the_first(fakes):
    slave = connected_slave(fakes)
    for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 2, 0), (xp.ALLOC_ODT, 0, 1, 0, 2),
                   (xp.ALLOC_ODT_ENTRY, 0, 1, 0, 0, 1), (xp.ALLOC_ODT_ENTRY, 0, 1, 0, 1, 1),
                   (xp.SET_DAQ_PTR, 0, 1, 0, 0, 0), (xp.WRITE_DAQ, 0xFF, 2, 0, 0, 0, 0, 0),
                   (xp.SET_DAQ_PTR, 0, 1, 0, 1, 0), (xp.WRITE_DAQ, 0xFF, 3, 0, 0, 0, 0, 0),
                   (xp.SET_DAQ_LIST_MODE, 0x10, 1, 0, 0, 0, 1, 0)):
        assert cmd(slave, *packet) == POSITIVE
    t = 0x1_2345_6789_ABCD_E000
    assert slave.dto_packet(Dto(1, 0, t, b"ab")) is None                  # not running yet
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 1, 1, 0) == POSITIVE + bytes([0])
    us = (t // 1000) & 0xFFFFFFFF
    assert slave.dto_packet(Dto(1, 0, t, b"ab")) == bytes([0, 0, 1, 0]) + struct.pack("<I", us) + b"ab"
    assert slave.dto_packet(Dto(1, 1, t, b"cde")) == bytes([1, 0, 1, 0]) + b"cde"
    assert slave.dto_packet(Dto(1, 1, t, b"cd")) is None                  # another configuration's
    assert slave.dto_packet(Dto(1, 2, t, b"cde")) is None
    assert slave.dto_packet(Dto(0, 0, t, b"")) is None
    c = slave.counters()
    assert c["dto_dropped"] == {"not_running": 2, "stale": 2} and c["dtos"] == 2
    assert slave.overload_events(0) == []
    assert slave.overload_events(3) == [bytes([xp.PID_EV, xp.EV_DAQ_OVERLOAD])]
    assert slave.overload_events(3) == []                                  # nothing new lost
    assert slave.counters()["overload_events"] == 1


def test_daq_clock_resolution_processor_and_event_info(fakes):
    memory, daq = fakes
    events = (Event("tick", 0.0005), Event("10ms", 0.01), Event("100ms", 0.1), Event("sync", 0))
    slave = Slave(memory, daq, events=events, clock_ns=lambda: 0x7_0000_0000 * 1000 + 123_456)
    cmd(slave, xp.CONNECT, 0)
    # the slave clock in us, low 32 bits
    assert cmd(slave, xp.GET_DAQ_CLOCK) == POSITIVE + bytes([0, 0, 1]) + struct.pack("<I", 123)
    # granularity 1, max entry 248, no STIM; timestamps 4 bytes, 1 us, selectable; 1 tick
    assert cmd(slave, xp.GET_DAQ_RESOLUTION_INFO) == POSITIVE + bytes([1, 248, 1, 0, 0x34, 1, 0])
    # overload event, timestamps, prescaler, dynamic; 32 lists; 4 events; key byte: word aligned
    assert cmd(slave, xp.GET_DAQ_PROCESSOR_INFO) == POSITIVE + bytes([0x93, 32, 0, 4, 0, 0, 0xF0])
    cycles = {}
    for n, event in enumerate(events):
        info = cmd(slave, xp.GET_DAQ_EVENT_INFO, 0, n, 0)
        assert info[1] == 0x84                                              # DAQ, consistent per event
        cycles[event.name] = (info[4], info[5])
        assert cmd(slave, xp.UPLOAD, info[3]) == POSITIVE + event.name.encode()
    assert cycles == {"tick": (5, 5), "10ms": (1, 7), "100ms": (1, 8), "sync": (0, 0)}
    assert cmd(slave, xp.GET_DAQ_EVENT_INFO, 0, 4, 0) == err(xp.ERR_OUT_OF_RANGE)


def test_seed_and_key_unlocks_and_a_wrong_key_ends_the_session(fakes):
    slave = connected_slave(fakes, secret=SECRET)
    assert cmd(slave, xp.GET_STATUS)[2] == xp.RES_CALPAG | xp.RES_DAQ        # locked
    assert cmd(slave, xp.SHORT_DOWNLOAD, 1, 0, 0, *struct.pack("<I", CAL[0]), 9) == \
        err(xp.ERR_ACCESS_LOCKED)
    assert cmd(slave, xp.FREE_DAQ) == err(xp.ERR_ACCESS_LOCKED)
    assert cmd(slave, xp.SHORT_UPLOAD, 1, 0, 0, *struct.pack("<I", CAL[0]))[0] == xp.PID_RES
    assert cmd(slave, xp.UNLOCK, 1, 0) == err(xp.ERR_SEQUENCE)               # no seed asked
    assert cmd(slave, xp.GET_SEED, 0, 0x03) == err(xp.ERR_OUT_OF_RANGE)      # two resources
    assert cmd(slave, xp.GET_SEED, 0, xp.RES_PGM) == POSITIVE + bytes([0])   # not protected
    seed_response = cmd(slave, xp.GET_SEED, 0, xp.RES_CALPAG)
    seed = seed_response[2:2 + seed_response[1]]
    assert len(seed) == xp.SEED_BYTES
    key = compute_key(SECRET, seed)
    assert cmd(slave, xp.UNLOCK, len(key), *key[:5]) == POSITIVE + bytes([0x05])   # in two parts
    assert cmd(slave, xp.UNLOCK, len(key) - 5, *key[5:]) == POSITIVE + bytes([xp.RES_DAQ])
    assert cmd(slave, xp.SHORT_DOWNLOAD, 1, 0, 0, *struct.pack("<I", CAL[0]), 9) == POSITIVE
    seed_response = cmd(slave, xp.GET_SEED, 0, xp.RES_DAQ)
    wrong = compute_key(b"another secret, not the slave's", seed_response[2:])
    assert cmd(slave, xp.UNLOCK, len(wrong), *wrong) == err(xp.ERR_ACCESS_LOCKED)
    assert not slave.connected                                              # the session ended
    assert cmd(slave, xp.GET_STATUS) is None
    assert cmd(slave, xp.CONNECT, 0)[0] == xp.PID_RES
    assert cmd(slave, xp.GET_STATUS)[2] == xp.RES_CALPAG | xp.RES_DAQ        # locked again
    c = slave.counters()
    assert c["unlocked"] == 1 and c["ignored"]["unlock_wrong_key"] == 1
    assert c["session_ends"] == {"wrong_key": 1}


def test_the_key_file_needs_a_real_secret(tmp_path):
    short = tmp_path / "short.key"
    short.write_bytes(b"12345\n")
    with pytest.raises(ValueError, match="16 bytes"):
        read_secret(short)
    good = tmp_path / "good.key"
    good.write_bytes(b"  " + SECRET + b"\n")
    assert read_secret(good) == SECRET
    assert compute_key(SECRET, b"seed") == compute_key(SECRET, b"seed")
    assert compute_key(SECRET, b"seed") != compute_key(SECRET, b"seee")
    assert len(compute_key(SECRET, b"seed")) == xp.KEY_BYTES


def test_parse_address():
    assert parse_address("5555") == ("127.0.0.1", 5555)
    assert parse_address("0.0.0.0:5556") == ("0.0.0.0", 5556)
    assert parse_address(":17") == ("127.0.0.1", 17)
    assert parse_address("[::1]:5555") == ("::1", 5555)
    for bad in ("x", "host:", "1:2:3", "70000"):
        with pytest.raises(ValueError):
            parse_address(bad)


# ---- framing ----------------------------------------------------------------

def test_datagram_framing_takes_several_packets_and_drops_bad_frames():
    bad = {}
    good = frame(0, b"\xff\x00") + frame(1, b"\xfd")
    assert list(deframe_datagram(good, 252, bad)) == [b"\xff\x00", b"\xfd"]
    assert list(deframe_datagram(good + b"\x01", 252, bad)) == [b"\xff\x00", b"\xfd"]
    assert list(deframe_datagram(struct.pack("<HH", 0, 0) + good, 252, bad)) == []
    assert list(deframe_datagram(frame(0, bytes(253)), 252, bad)) == []
    assert list(deframe_datagram(struct.pack("<HH", 9, 0) + b"abc", 252, bad)) == []
    assert bad == {"truncated": 2, "empty": 1, "oversized": 1}


def test_stream_framing_skips_empty_and_oversized_frames_and_gives_up_on_garbage():
    bad = {}
    d = StreamDeframer(252, bad)
    stream = frame(0, b"\xff\x00") + struct.pack("<HH", 0, 1) + frame(2, bytes(300)) + \
        frame(3, b"\xfd")
    out = []
    for k in range(0, len(stream), 7):                                      # in pieces
        out += d.feed(stream[k:k + 7])
    assert out == [b"\xff\x00", b"\xfd"] and not d.broken
    assert bad == {"empty": 1, "oversized": 1}
    assert d.feed(struct.pack("<HH", 0xFFFF, 0) + frame(4, b"\xfd")) == [] and d.broken
    assert bad["garbage"] == 1


# ---- the server with pyxcp as the master ----------------------------------------

def test_connect_get_id_and_the_a2l_upload(server):
    with pyxcp_master(server) as x:
        r = x.connect()
        assert r.resource.calpag and r.resource.daq and not r.resource.pgm
        assert (r.maxCto, r.maxDto) == (252, 252)
        assert x.slaveProperties.byteOrder == "INTEL"
        assert x.getCommModeInfo().xcpDriverVersionNumber == 0x14
        assert x.identifier(0) == "dct-hil"
        assert x.identifier(1) == "dct_hil"
        assert x.identifier(4) == A2L                                       # 60+ UPLOADs
        x.disconnect()
    c = server.counters()
    assert c["protocol"]["errors"] == {} and c["protocol"]["session_ends"] == {"disconnect": 1}
    assert c["transport"]["bad_frames"] == {} and c["transport"]["dropped"] == {}


def test_upload_download_and_refused_downloads(server, fakes):
    memory, _ = fakes
    with pyxcp_master(server) as x:
        x.connect()
        x.setMta(CAL[0])
        assert x.upload(16) == bytes(range(16))
        assert x.shortUpload(4, CAL[0] + 100) == bytes([100, 101, 102, 103])
        x.setMta(CAL[0] + 4)
        x.download(b"\x10\x20\x30")
        x.download(b"\x40")                                                 # the MTA moved on
        assert memory.b[CAL[0] + 4:CAL[0] + 8] == b"\x10\x20\x30\x40"
        x.shortDownload(DATA[0], 0, b"\xaa\xbb")
        assert x.shortUpload(2, DATA[0]) == b"\xaa\xbb"
        x.setMta(CAL[0])
        assert x.fetch(CAL[1]) == bytes(memory.b[CAL[0]:CAL[0] + CAL[1]])    # more than MAX_CTO
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(16, 0, b"\x01")                                # read-only memory
        assert "ERR_WRITE_PROTECTED" in error_of(e)
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(REFUSE_AT, 0, b"\xff")                         # a refused value
        assert "ERR_OUT_OF_RANGE" in error_of(e)
        with pytest.raises(XcpResponseError) as e:
            x.shortUpload(8, MEM_SIZE - 4)
        assert "ERR_ACCESS_DENIED" in error_of(e)
        assert x.shortUpload(1, REFUSE_AT) == bytes([REFUSE_AT - CAL[0]])  # unchanged
        x.disconnect()
    errors = server.counters()["protocol"]["errors"]
    assert errors == {"ERR_WRITE_PROTECTED": 1, "ERR_OUT_OF_RANGE": 1, "ERR_ACCESS_DENIED": 1}


def test_calibration_pages_working_and_reference(fakes):
    memory, _ = fakes
    srv = make_server(fakes, "udp")
    with srv, pyxcp_master(srv) as x:
        x.connect()
        assert x.getPagProcessorInfo().maxSegments == 1
        assert x.getSegmentInfo(0, 0, 0, 0).basicInfo == CAL[0]
        assert x.getSegmentInfo(0, 0, 1, 0).basicInfo == CAL[1]
        assert x.getSegmentInfo(1, 0, 0, 0).maxPages == 2
        assert x.getCalPage(0x01, 0) == 0 and x.getCalPage(0x02, 0) == 0
        x.shortDownload(CAL[0], 0, b"\xee\xee")                              # the working page
        x.setCalPage(0x02, 0, 1)                                            # XCP reads page 1
        assert x.shortUpload(2, CAL[0]) == b"\x00\x01"                      # the reference
        assert x.shortUpload(2, 0) == bytes(memory.b[0:2])                  # outside: the same
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(CAL[0], 0, b"\x00")
        assert "ERR_WRITE_PROTECTED" in error_of(e)
        x.setCalPage(0x01, 0, 1)                                            # the ECU runs page 1
        assert memory.b[CAL[0]:CAL[0] + 2] == b"\x00\x01"
        x.setCalPage(0x02, 0, 0)
        assert x.shortUpload(2, CAL[0]) == b"\xee\xee"                      # working, kept aside
        x.shortDownload(CAL[0] + 2, 0, b"\xdd")                             # into the kept page
        assert memory.b[CAL[0] + 2] == 2
        x.setCalPage(0x83, 0, 0)                                            # all, ECU and XCP
        assert memory.b[CAL[0]:CAL[0] + 3] == b"\xee\xee\xdd"
        assert x.getCalPage(0x01, 0) == 0
        x.copyCalPage(0, 1, 0, 0)                                           # reference -> working
        assert memory.b[CAL[0]:CAL[0] + CAL[1]] == bytes(range(CAL[1]))
        with pytest.raises(XcpResponseError) as e:
            x.copyCalPage(0, 0, 0, 1)
        assert "ERR_WRITE_PROTECTED" in error_of(e)
        with pytest.raises(XcpResponseError) as e:
            x.setCalPage(0x01, 0, 2)
        assert "ERR_PAGE_NOT_VALID" in error_of(e)
        with pytest.raises(XcpResponseError) as e:
            x.getCalPage(0x01, 1)
        assert "ERR_SEGMENT_NOT_VALID" in error_of(e)
        x.disconnect()


class Measured(DaqOnlinePolicy):
    """pyxcp's own DAQ decoding: the rows it gives."""

    def __init__(self, lists):
        # pyxcp's policies ask for the application when made; without one set it
        # would parse the test runner's command line: set a neutral one first
        # (pyxcp_master sets its own for the session)
        set_application(create_application_from_config(
            {"General": {"disable_error_handling": True}}, log_level=logging.CRITICAL))
        super().__init__(lists)
        self.rows = []

    def initialize(self):
        pass

    def finalize(self):
        pass

    def on_daq_list(self, daq_list, timestamp0, timestamp1, payload):
        self.rows.append((daq_list, timestamp1, list(payload)))


def daq_lists():
    counters = DaqList(name="counters", event_num=0, stim=False, enable_timestamps=True,
                       measurements=[(f"c{k}", COUNTERS + 4 * k, 0, "U32") for k in range(20)],
                       priority=0, prescaler=1)
    # 280 bytes: two ODTs, the first one with the timestamp
    pattern = DaqList(name="pattern", event_num=1, stim=False, enable_timestamps=False,
                      measurements=[(f"p{k}", PATTERN + 4 * k, 0, "U32") for k in range(70)],
                      priority=0, prescaler=2)
    return [counters, pattern]


def test_daq_of_20_entries_and_a_two_odt_list_start_and_stop(server, producer):
    policy = Measured(daq_lists())
    want_pattern = list(struct.unpack("<70I", bytes((7 * k + 3) & 0xFF for k in range(280))))
    with pyxcp_master(server, policy=policy) as x:
        x.connect()
        policy.setup()
        policy.start()
        config = producer.config
        assert [len(d.odts) for d in config] == [1, 2]
        assert sum(e.size for o in config[0].odts for e in o) == 80
        assert sum(e.size for o in config[1].odts for e in o) == 280
        assert config[1].prescaler == 2 and config[1].event == 1
        assert producer.running() == [True, True] and x.getStatus().sessionStatus.daqRunning
        assert wait_until(lambda: sum(r[0] == 0 for r in policy.rows) >= 40 and
                          any(r[0] == 1 for r in policy.rows))
        policy.stop()
        assert producer.running() == [False, False]
        assert not x.getStatus().sessionStatus.daqRunning
        x.disconnect()
    counters = [r for r in policy.rows if r[0] == 0]
    ticks = []
    for _, _, values in counters:
        n = values[0] // 100
        assert values == [n * 100 + k for k in range(20)]                  # one tick's values
        ticks.append(n)
    assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
    stamps = [t for _, t, _ in counters]
    assert stamps == sorted(stamps) and stamps[-1] > stamps[0]            # the slave's clock
    assert all(values == want_pattern for k, _, values in policy.rows if k == 1)
    c = server.counters()
    assert c["transport"]["dtos_out"] >= len(policy.rows)
    assert c["protocol"]["errors"] == {}


def test_overload_is_an_event_to_the_master(fakes):
    memory, daq = fakes
    srv = make_server(fakes, "udp")
    with srv:
        raw = Raw(srv)
        assert raw.command(xp.CONNECT, 0)[0] == xp.PID_RES
        for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 1, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                       (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1), (xp.SET_DAQ_PTR, 0, 0, 0, 0, 0),
                       (xp.WRITE_DAQ, 0xFF, 4, 0, 0, 0, 0, 0), (xp.START_STOP_DAQ_LIST, 1, 0, 0)):
            assert raw.command(*packet)[0] == xp.PID_RES
        daq.lost = 5
        while True:                                                         # DTOs may come first
            packet = raw.recv()
            if packet[0] == xp.PID_EV:
                break
        assert packet == bytes([xp.PID_EV, xp.EV_DAQ_OVERLOAD])
        raw.close()
    assert srv.counters()["protocol"]["overload_events"] == 1


def test_seed_and_key_with_pyxcp(fakes, tmp_path):
    key_file = tmp_path / "xcp.key"
    key_file.write_bytes(SECRET + b"\n")
    srv = make_server(fakes, "tcp", key_file=key_file)
    with srv:
        with pyxcp_master(srv, secret=SECRET) as x:
            x.connect()
            assert x.getCurrentProtectionStatus() == {
                "dbg": False, "pgm": False, "stim": False, "daq": True, "calpag": True}
            with pytest.raises(XcpResponseError) as e:
                x.shortDownload(CAL[0], 0, b"\x05")
            assert "ERR_ACCESS_LOCKED" in error_of(e)
            x.cond_unlock()                                                 # GET_SEED + UNLOCK
            status = x.getStatus().resourceProtectionStatus
            assert not status.calpag and not status.daq
            x.shortDownload(CAL[0], 0, b"\x05")
            x.disconnect()
        with pyxcp_master(srv, secret=b"the wrong secret, 1234567890") as x:
            x.connect()
            with pytest.raises(XcpResponseError) as e:
                x.cond_unlock("calpag")
            assert "ERR_ACCESS_LOCKED" in error_of(e)
    c = srv.counters()["protocol"]
    assert c["unlocked"] == 2 and c["ignored"]["unlock_wrong_key"] == 1
    assert c["session_ends"]["wrong_key"] == 1


def test_malformed_udp_datagrams_are_dropped_and_counted(fakes):
    srv = make_server(fakes, "udp")
    with srv:
        raw = Raw(srv)
        raw.send_raw(b"\x01")                                               # shorter than a header
        raw.send_raw(struct.pack("<HH", 0, 0))                              # LEN 0
        raw.send_raw(frame(0, bytes([xp.CONNECT]) + bytes(299)))           # LEN > MAX_CTO
        raw.send_raw(struct.pack("<HH", 20, 0) + b"\xff\x00")              # cut short
        raw.send(bytes([xp.GET_STATUS]))                                    # before CONNECT
        assert raw.command(xp.CONNECT, 0)[0] == xp.PID_RES                  # the first answer
        assert raw.command(0xD1, 1, 2, 3, 4, 5) == err(xp.ERR_CMD_UNKNOWN)   # PROGRAM_CLEAR
        assert raw.command(xp.SET_MTA, 0) == err(xp.ERR_CMD_SYNTAX)
        raw.send_raw(frame(9, bytes([xp.GET_STATUS])) + frame(10, bytes([xp.SYNCH])))
        assert raw.recv()[0] == xp.PID_RES and raw.recv() == err(xp.ERR_CMD_SYNCH)
        other = Raw(srv)                                                    # not its session
        other.send(bytes([xp.GET_STATUS]))
        assert raw.command(xp.GET_STATUS)[0] == xp.PID_RES
        raw.close()
        other.close()
    c = srv.counters()
    assert c["transport"]["bad_frames"] == {"truncated": 2, "empty": 1, "oversized": 1}
    assert c["transport"]["dropped"] == {"not_connected": 1, "other_master": 1}
    assert c["protocol"]["errors"] == {"ERR_CMD_UNKNOWN": 1, "ERR_CMD_SYNTAX": 1,
                                       "ERR_CMD_SYNCH": 1}


def test_malformed_tcp_frames_are_skipped_and_garbage_closes_the_connection(fakes):
    srv = make_server(fakes, "tcp")
    with srv:
        raw = Raw(srv)
        raw.send_raw(struct.pack("<HH", 0, 0))                              # LEN 0: skipped
        raw.send_raw(frame(1, bytes(300)))                                  # LEN > MAX_CTO: skipped
        assert raw.command(xp.CONNECT, 0)[0] == xp.PID_RES
        assert raw.command(xp.GET_ID) == err(xp.ERR_CMD_SYNTAX)
        raw.send_raw(struct.pack("<HH", 0xF000, 0) + bytes(8))              # out of step
        with pytest.raises((ConnectionError, OSError)):
            raw.recv()
        raw.close()
        with pyxcp_master(srv) as x:                                        # the next one is served
            x.connect()
            assert x.identifier(1) == "dct_hil"
            x.disconnect()
    c = srv.counters()
    assert c["transport"]["bad_frames"] == {"empty": 1, "oversized": 1, "garbage": 1}
    assert c["protocol"]["session_ends"]["garbage"] == 1


def test_a_master_that_vanishes_leaves_the_server_to_the_next(server, fakes, producer):
    policy = Measured(daq_lists()[:1])
    with pyxcp_master(server, policy=policy) as x:
        x.connect()
        policy.setup()
        policy.start()
        assert wait_until(lambda: len(policy.rows) >= 5)
        # gone without DISCONNECT or stopping its DAQ
    with pyxcp_master(server) as x:
        x.connect()
        status = x.getStatus()
        assert not status.sessionStatus.daqRunning
        assert producer.running() == [] or not any(producer.running())
        x.setMta(CAL[0])
        assert x.upload(4) == bytes(range(4))
        x.disconnect()
    c = server.counters()
    ends = c["protocol"]["session_ends"]
    if server.protocol == "udp":        # nothing tells UDP: the next CONNECT takes over
        assert ends == {"takeover": 1, "disconnect": 1} and c["transport"]["takeovers"] == 1
    else:                               # TCP: the connection's end
        assert ends == {"master_gone": 1, "disconnect": 1}
    assert c["transport"]["masters"] == 2


def test_a_second_tcp_master_takes_over_a_live_connection(fakes):
    srv = make_server(fakes, "tcp")
    with srv:
        first = Raw(srv)
        assert first.command(xp.CONNECT, 0)[0] == xp.PID_RES
        with pyxcp_master(srv) as x:
            x.connect()
            assert x.identifier(0) == "dct-hil"
            x.disconnect()
        with pytest.raises((ConnectionError, OSError)):
            first.command(xp.GET_STATUS)                                    # it was closed
        first.close()
    c = srv.counters()
    assert c["transport"]["takeovers"] == 1
    assert c["protocol"]["session_ends"] == {"takeover": 1, "disconnect": 1}


def test_a_tcp_master_that_stops_reading_never_blocks_the_server(fakes):
    memory, daq = fakes
    srv = make_server(fakes, "tcp")
    with srv:
        stuck = Raw(srv, rcvbuf=4096)
        assert stuck.command(xp.CONNECT, 0)[0] == xp.PID_RES
        for packet in ((xp.FREE_DAQ,), (xp.ALLOC_DAQ, 0, 1, 0), (xp.ALLOC_ODT, 0, 0, 0, 1),
                       (xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1), (xp.SET_DAQ_PTR, 0, 0, 0, 0, 0),
                       (xp.WRITE_DAQ, 0xFF, 248, 0, 0, 0, 0, 0), (xp.START_STOP_DAQ_LIST, 1, 0, 0)):
            assert stuck.command(*packet)[0] == xp.PID_RES

        def overflowing():
            # it reads nothing more: DTOs until neither the sockets nor the queue hold more
            for _ in range(TCP_QUEUE_BYTES // 252):
                daq.tick()
            return srv.counters()["transport"]["dropped"].get("queue_full", 0) > 0

        assert wait_until(overflowing, step=0)
        with pyxcp_master(srv) as x:                                        # still served
            x.connect()
            assert x.shortUpload(2, CAL[0]) == b"\x00\x01"
            x.disconnect()
        stuck.close()
    c = srv.counters()
    assert c["transport"]["takeovers"] == 1 and c["transport"]["error"] is None
