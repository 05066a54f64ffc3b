"""The XCP slave's memory and clock commands beyond UPLOAD/DOWNLOAD: BUILD_CHECKSUM,
MODIFY_BITS, master block mode (DOWNLOAD + DOWNLOAD_NEXT), SHORT_DOWNLOAD,
TIME_CORRELATION_PROPERTIES and GET_DAQ_CLOCK in both formats.

The protocol layer alone (rt_loop.measure.xcp.protocol.Slave over the fake
memory of tests/test_xcp_protocol.py), then the whole server over UDP and TCP
with pyxcp as the master: what it sends and how it parses the answers.
"""

import struct
import zlib

import pytest
import requires

requires.module("pyxcp")

from pyxcp import checksum as pyxcp_checksum
from pyxcp.time_correlation import ClockInformation
from pyxcp.types import XcpResponseError
from test_xcp_protocol import (
    CAL,
    DATA,
    POSITIVE,
    REFUSE_AT,
    FakeDaq,
    FakeMemory,
    cmd,
    connected_slave,
    err,
    error_of,
    make_server,
    pyxcp_master,
)

from rt_loop.measure.xcp import protocol as xp


@pytest.fixture
def fakes():
    memory = FakeMemory()
    return memory, FakeDaq(memory)


@pytest.fixture(params=["udp", "tcp"])
def server(request, fakes):
    srv = make_server(fakes, request.param)
    srv.start()
    yield srv
    srv.stop()


def u32(x):
    return struct.pack("<I", x)


def set_mta(slave, address):
    assert cmd(slave, xp.SET_MTA, 0, 0, 0, *u32(address)) == POSITIVE


def crc32_bitwise(data):
    """CRC-32 (IEEE 802.3, reflected, polynomial 0xEDB88320) bit by bit: a
    computation of its own, beside zlib's and pyxcp's."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def modify(value, shift, and_mask, xor_mask):
    """MODIFY_BITS as the standard writes it."""
    return ((value & ~(((~and_mask) & 0xFFFF) << shift)) ^ (xor_mask << shift)) & 0xFFFFFFFF


class CountingWrites:
    """Counts the memory's writes (a block must be one)."""

    def __init__(self, memory):
        self.calls = []
        write = memory.write

        def counted(address, data):
            self.calls.append((address, bytes(data)))
            return write(address, data)

        memory.write = counted


# ---- BUILD_CHECKSUM -----------------------------------------------------------

def test_build_checksum_is_crc32_over_the_mta_and_advances_it(fakes):
    memory, _ = fakes
    slave = connected_slave(fakes)
    set_mta(slave, CAL[0] + 3)
    answer = cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(100))
    block = bytes(memory.b[CAL[0] + 3:CAL[0] + 103])
    value = crc32_bitwise(block)
    assert answer == POSITIVE + bytes([0x09, 0, 0]) + u32(value)        # XCP_CRC_32
    assert value == pyxcp_checksum.check(block, "XCP_CRC_32") == zlib.crc32(block)
    assert cmd(slave, xp.UPLOAD, 2) == POSITIVE + bytes(memory.b[CAL[0] + 103:CAL[0] + 105])
    # too large, or nothing: ERR_OUT_OF_RANGE with the largest block the slave takes
    limit = err(xp.ERR_OUT_OF_RANGE) + bytes(2) + u32(xp.MAX_CHECKSUM_BLOCK)
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(xp.MAX_CHECKSUM_BLOCK + 1)) == limit
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(0)) == limit
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0) == err(xp.ERR_CMD_SYNTAX)
    set_mta(slave, 8192 - 10)                                              # past the memory
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(20)) == err(xp.ERR_ACCESS_DENIED)


def test_build_checksum_over_the_a2l_the_mta_points_to(fakes):
    slave = connected_slave(fakes, a2l_text=lambda: "A2L text " * 40)
    assert cmd(slave, xp.GET_ID, 4)[0] == xp.PID_RES                       # MTA: the A2L
    answer = cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(360))
    assert answer[4:] == u32(zlib.crc32(("A2L text " * 40).encode()))
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(1)) == err(xp.ERR_OUT_OF_RANGE)


# ---- MODIFY_BITS ----------------------------------------------------------------

def test_modify_bits_changes_the_value_at_the_mta_through_the_write_path(fakes):
    memory, _ = fakes
    slave = connected_slave(fakes)
    at = DATA[0] + 8
    memory.b[at:at + 4] = u32(0x12345678)
    set_mta(slave, at)
    assert cmd(slave, xp.MODIFY_BITS, 4, *struct.pack("<HH", 0xF00F, 0x0A50)) == POSITIVE
    assert struct.unpack_from("<I", memory.b, at)[0] == modify(0x12345678, 4, 0xF00F, 0x0A50)
    assert cmd(slave, xp.UPLOAD, 4) == POSITIVE + bytes(memory.b[at:at + 4])   # the MTA stays
    # masks that change nothing write nothing
    writes = CountingWrites(memory)
    set_mta(slave, at)
    assert cmd(slave, xp.MODIFY_BITS, 0, *struct.pack("<HH", 0xFFFF, 0)) == POSITIVE
    assert writes.calls == []
    # only the bytes the masks touch: the last byte of a writable region
    set_mta(slave, CAL[0] + CAL[1] - 1)
    assert cmd(slave, xp.MODIFY_BITS, 0, *struct.pack("<HH", 0xFF00, 0x0081)) == POSITIVE
    assert writes.calls == [(CAL[0] + CAL[1] - 1, b"\x81")]
    # refused: a value the memory refuses, a read-only address, a shift beyond 31 bits
    before = bytes(memory.b)
    set_mta(slave, REFUSE_AT)
    assert cmd(slave, xp.MODIFY_BITS, 0, *struct.pack("<HH", 0xFF00, 0x00FF)) == \
        err(xp.ERR_OUT_OF_RANGE)
    set_mta(slave, 16)
    assert cmd(slave, xp.MODIFY_BITS, 0, *struct.pack("<HH", 0, 0)) == err(xp.ERR_WRITE_PROTECTED)
    assert cmd(slave, xp.MODIFY_BITS, 32, *struct.pack("<HH", 0, 1)) == err(xp.ERR_OUT_OF_RANGE)
    assert bytes(memory.b) == before


# ---- master block mode --------------------------------------------------------------

def test_comm_mode_info_declares_master_block_mode():
    # reserved, COMM_MODE_OPTIONAL (master block mode), reserved, MAX_BS 2, MIN_ST 0,
    # queue 0, driver 1.4
    slave = connected_slave((xp.Memory(), xp.Daq()))
    assert cmd(slave, xp.GET_COMM_MODE_INFO) == POSITIVE + bytes([0, 1, 0, 2, 0, 0, 0x14])
    assert xp.MAX_BS * (xp.MAX_CTO - 2) >= 255


def test_a_master_block_is_answered_once_and_written_whole(fakes):
    memory, _ = fakes
    slave = connected_slave(fakes)
    writes = CountingWrites(memory)
    block = bytes((3 * k + 1) & 0xFF for k in range(255))
    set_mta(slave, CAL[0])
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []    # no answer yet
    assert writes.calls == []
    assert cmd(slave, xp.DOWNLOAD_NEXT, 5, *block[250:]) == POSITIVE
    assert writes.calls == [(CAL[0], block)]                              # one write
    assert bytes(memory.b[CAL[0]:CAL[0] + 255]) == block
    assert cmd(slave, xp.UPLOAD, 1) == POSITIVE + bytes([255])            # MTA past the block
    # a block's first packet carries MAX_CTO - 2 bytes
    assert cmd(slave, xp.DOWNLOAD, 255, *block[:100]) == err(xp.ERR_CMD_SYNTAX)


def test_a_wrong_download_next_is_a_sequence_error_with_the_count_expected(fakes):
    memory, _ = fakes
    slave = connected_slave(fakes)
    before = bytes(memory.b)
    block = bytes(range(255))
    set_mta(slave, CAL[0])
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []
    assert cmd(slave, xp.DOWNLOAD_NEXT, 4, *block[250:254]) == err(xp.ERR_SEQUENCE) + bytes([5])
    # the block was dropped: its rest is out of sequence too, nothing was written
    assert cmd(slave, xp.DOWNLOAD_NEXT, 5, *block[250:]) == err(xp.ERR_SEQUENCE) + bytes([0])
    assert bytes(memory.b) == before
    # another command inside a block drops it; a DOWNLOAD there is out of sequence...
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []
    assert cmd(slave, xp.GET_STATUS)[0] == xp.PID_RES
    assert cmd(slave, xp.DOWNLOAD_NEXT, 5, *block[250:]) == err(xp.ERR_SEQUENCE) + bytes([0])
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []
    assert cmd(slave, xp.DOWNLOAD, 4, *block[250:254]) == err(xp.ERR_SEQUENCE)
    assert bytes(memory.b) == before
    # ... unless it carries exactly the count still to come: the block's end
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []
    assert cmd(slave, xp.DOWNLOAD, 5, *block[250:]) == POSITIVE
    assert bytes(memory.b[CAL[0]:CAL[0] + 255]) == block
    memory.b[:] = before
    # a block into read-only memory is refused when it is complete, as one write
    set_mta(slave, 0)
    assert slave.handle(bytes([xp.DOWNLOAD, 255]) + block[:250]) == []
    assert cmd(slave, xp.DOWNLOAD_NEXT, 5, *block[250:]) == err(xp.ERR_WRITE_PROTECTED)
    c = slave.counters()
    assert c["ignored"]["download_block_dropped"] == 2
    assert c["errors"]["ERR_SEQUENCE"] == 4


# ---- the clock -------------------------------------------------------------------------

def test_time_correlation_properties_and_the_extended_daq_clock(fakes):
    memory, daq = fakes
    now_ns = 0x1_2345_6789 * 1000 + 999
    uuid = bytes([0x02, 1, 2, 3, 4, 5, 6, 7])
    slave = xp.Slave(memory, daq, clock_ns=lambda: now_ns, clock_uuid=uuid)
    cmd(slave, xp.CONNECT, 0)
    legacy = POSITIVE + bytes([0, 0, 1]) + u32(0x2345_6789)                # low 32 bits of us
    assert cmd(slave, xp.GET_DAQ_CLOCK) == legacy
    # ask nothing: legacy format, the slave clock free running, no sync, info available
    assert cmd(slave, xp.TIME_CORRELATION_PROPERTIES, 0, 0, 0, 0, 0) == \
        POSITIVE + bytes([0, 0, 0x07, 0x01, 0]) + struct.pack("<H", 0)
    # extended format for all triggers, a cluster id, the clock's information
    assert cmd(slave, xp.TIME_CORRELATION_PROPERTIES, 0x12, 0x01, 0, 0x34, 0x12) == \
        POSITIVE + bytes([2, 0, 0x07, 0x01, 0]) + struct.pack("<H", 0x1234)
    info = cmd(slave, xp.UPLOAD, 24)[1:]
    assert info == uuid + struct.pack("<HBBB", 1, 3, 255, 8) + bytes(3) + \
        struct.pack("<Q", 2 ** 64 - 1)
    assert cmd(slave, xp.GET_DAQ_CLOCK) == POSITIVE + bytes([0, 0, 2]) + \
        struct.pack("<Q", 0x1_2345_6789) + bytes([0x07])
    # reserved format, a time sync bridge the slave has not: refused
    assert cmd(slave, xp.TIME_CORRELATION_PROPERTIES, 0x03, 0, 0, 0, 0) == err(xp.ERR_OUT_OF_RANGE)
    assert cmd(slave, xp.TIME_CORRELATION_PROPERTIES, 0x04, 0, 0, 0, 0) == err(xp.ERR_OUT_OF_RANGE)
    assert cmd(slave, xp.TIME_CORRELATION_PROPERTIES, 0, 0) == err(xp.ERR_CMD_SYNTAX)
    # a new session starts in the legacy format
    cmd(slave, xp.DISCONNECT)
    cmd(slave, xp.CONNECT, 0)
    assert cmd(slave, xp.GET_DAQ_CLOCK) == legacy


def test_the_clock_uuid_is_the_boots():
    a, b = xp.default_clock_uuid(), xp.default_clock_uuid()
    assert len(a) == 8 and a[0] & 0x03 == 0x02                    # local, unicast EUI-64
    try:
        with open("/proc/sys/kernel/random/boot_id"):
            assert a == b                                          # one clock per boot
    except OSError:
        pass
    with pytest.raises(ValueError, match="EUI-64"):
        xp.Slave(xp.Memory(), xp.Daq(), clock_uuid=b"1234")


# ---- with pyxcp as the master ---------------------------------------------------------------

def test_pyxcp_checksum_modify_bits_and_downloads(server, fakes):
    memory, _ = fakes
    with pyxcp_master(server) as x:
        x.connect()
        info = x.getCommModeInfo()
        assert info.commModeOptional.masterBlockMode and info.maxBs == xp.MAX_BS
        # BUILD_CHECKSUM: pyxcp computes the same over the same bytes
        x.setMta(CAL[0])
        cs = x.buildChecksum(200)
        assert cs.checksumType == "XCP_CRC_32"
        assert pyxcp_checksum.validate_checksum(bytes(memory.b[CAL[0]:CAL[0] + 200]), cs)
        with pytest.raises(XcpResponseError) as e:
            x.buildChecksum(xp.MAX_CHECKSUM_BLOCK + 1)
        assert "ERR_OUT_OF_RANGE" in error_of(e)
        # SHORT_DOWNLOAD
        x.shortDownload(DATA[0], 0, b"\x11\x22\x33")
        assert bytes(memory.b[DATA[0]:DATA[0] + 3]) == b"\x11\x22\x33"
        # MODIFY_BITS
        at = DATA[0] + 4
        memory.b[at:at + 4] = u32(0xCAFEF00D)
        x.setMta(at)
        x.modifyBits(8, 0x00FF, 0x1200)
        assert struct.unpack_from("<I", memory.b, at)[0] == modify(0xCAFEF00D, 8, 0x00FF, 0x1200)
        x.setMta(REFUSE_AT - 1)
        with pytest.raises(XcpResponseError) as e:
            x.modifyBits(8, 0xFF00, 0x00FF)                          # 0xFF at REFUSE_AT
        assert "ERR_OUT_OF_RANGE" in error_of(e)
        # a master block: DOWNLOAD of all 255 bytes' count, then DOWNLOAD_NEXT
        block = bytes((5 * k) & 0xFF for k in range(255))
        x.setMta(CAL[0])
        assert x.download(block[:250], block_mode_length=255) is None    # not answered
        x.downloadNext(block[250:], remaining_block_length=5, last=True)
        assert bytes(memory.b[CAL[0]:CAL[0] + 255]) == block
        # out of sequence
        x.setMta(CAL[0])
        x.download(block[:250], block_mode_length=255)
        with pytest.raises(XcpResponseError) as e:
            x.downloadNext(block[250:254], remaining_block_length=4, last=True)
        assert "ERR_SEQUENCE" in error_of(e)
        assert bytes(memory.b[CAL[0]:CAL[0] + 255]) == block
        # pyxcp's push in master block mode (a block's last packet comes as DOWNLOAD)
        table = bytes((7 * k + 2) & 0xFF for k in range(CAL[1]))
        x.push(CAL[0], 0, table)
        assert bytes(memory.b[CAL[0]:CAL[0] + CAL[1]]) == table
        x.disconnect()


def test_pyxcp_parses_time_correlation_and_both_clock_formats(server):
    with pyxcp_master(server) as x:
        x.connect()
        legacy = x.getDaqClock()
        assert legacy.format == "LEGACY"
        props = x.timeCorrelationProperties(response_fmt=2, get_clk_info=1, cluster_id=7,
                                            set_cluster_id=True)
        assert props.slave_config.response_fmt.name == "ALL_TRIGGERS"
        assert props.observable_clocks.xcp_slv_clk.name == "XCP_FREE_RUNNING"
        assert props.sync_state.slv_clk_sync_state.name == "NOT_SUPPORTED"
        assert props.clock_info.slv_clk_info and not props.clock_info.grandm_clk_info
        assert props.cluster_id == 7
        info = ClockInformation.parse(bytes(x.upload(24)), "INTEL")
        assert info.uuid == xp.default_clock_uuid()
        assert (info.timestamp_ticks, info.timestamp_unit.name) == (1, "UNIT_1US")
        assert info.native_timestamp_size.name == "DLONG" and info.stratum_level == 255
        before_us = time_us()
        clock = x.getDaqClock()
        after_us = time_us()
        assert clock.format == "EXTENDED" and clock.payload_fmt.xcp_slave_fmt.name == "DLONG"
        assert before_us <= clock.timestamp <= after_us                  # CLOCK_MONOTONIC in us
        assert clock.sync_state.slv_clk_sync_state.name == "NOT_SUPPORTED"
        x.disconnect()


def time_us():
    import time

    return time.monotonic_ns() // 1000


# ---- the A2L declares what the slave does ---------------------------------------------------

def test_the_a2l_declares_the_commands_block_mode_checksum_and_stim_as_the_slave_answers():
    import re

    from rt_loop._rt_loop import ffi, lib
    from rt_loop.measure.xcp import STIM_EVENTS, a2l, a2ml

    text = a2l.generate(ffi, lib)
    declared = re.findall(r"^\s*OPTIONAL_CMD (\w+)$", text, re.M)
    assert {"BUILD_CHECKSUM", "DOWNLOAD_NEXT", "SHORT_DOWNLOAD", "MODIFY_BITS",
            "TIME_CORRELATION_PROPERTIES"} <= set(declared)
    # every command declared is one the slave knows (no ERR_CMD_UNKNOWN)
    slave = connected_slave((xp.Memory(), xp.Daq()), stim_events=STIM_EVENTS)
    for name in declared:
        answer = cmd(slave, a2ml.OPTIONAL_CMD_CODES[name], *bytes(7))
        assert answer is None or answer[:2] != err(xp.ERR_CMD_UNKNOWN), name
        cmd(slave, xp.SYNCH)                        # ends a block a DOWNLOAD may have begun
    # master block mode as GET_COMM_MODE_INFO says
    max_bs, min_st = map(int, re.search(r"COMMUNICATION_MODE_SUPPORTED BLOCK MASTER (\d+) (\d+)",
                                        text).groups())
    answer = cmd(slave, xp.GET_COMM_MODE_INFO)
    assert answer[2] & 0x01 and (answer[4], answer[5]) == (max_bs, min_st)
    # the checksum as BUILD_CHECKSUM answers
    kind, block = re.search(r"/begin CHECKSUM (\w+) MAX_BLOCK_SIZE (0x[0-9A-F]+) /end CHECKSUM",
                            text).groups()
    assert (kind, int(block, 16)) == ("XCP_CRC_32", xp.MAX_CHECKSUM_BLOCK)
    assert cmd(slave, xp.BUILD_CHECKSUM, 0, 0, 0, *u32(int(block, 16) + 1))[4:] == u32(int(block, 16))
    # STIM: the STIM block, and the events that take it as GET_DAQ_EVENT_INFO says
    assert re.search(r"/begin STIM GRANULARITY_ODT_ENTRY_SIZE_STIM_BYTE 248 /end STIM", text)
    for channel, direction in re.findall(r'/begin EVENT "\w+" "\w+" (\d+) (DAQ_STIM|DAQ|STIM) ',
                                         text):
        stim = bool(cmd(slave, xp.GET_DAQ_EVENT_INFO, 0, *struct.pack("<H", int(channel)))[1] & 0x08)
        assert stim == (direction == "DAQ_STIM"), channel
    assert STIM_EVENTS == (lib.RT_EVENT_TICK,)
