"""STIM: DAQ lists in the other direction. The master configures a list as
STIM (SET_DAQ_LIST_MODE's DIRECTION bit) on an event that takes STIM, starts
it, and sends STIM DTOs; the slave writes their values through the
calibration path (only into the calibration regions, within the values'
ranges) and counts every DTO it drops.

The protocol layer alone over the fake memory of tests/test_xcp_protocol.py,
then pyxcp configuring a STIM list on the running loop (tests/test_xcp_loop.py's
Loop): a parameter written by STIM DTOs changes in the loop at a tick boundary.
"""

import struct

import pytest
import requires

requires.module("pyxcp")

from test_xcp_protocol import (
    CAL,
    DATA,
    POSITIVE,
    REFUSE_AT,
    SECRET,
    FakeDaq,
    FakeMemory,
    cmd,
    connected_slave,
    err,
)

from rt_loop.measure.xcp import protocol as xp
from rt_loop.measure.xcp.protocol import compute_key


@pytest.fixture
def fakes():
    memory = FakeMemory()
    return memory, FakeDaq(memory)


def u16(x):
    return struct.pack("<H", x)


def u32(x):
    return struct.pack("<I", x)


def stim_dto(odt, daq, data):
    """A STIM DTO: relative ODT, fill, absolute DAQ list (word), the values."""
    return bytes([odt, 0]) + u16(daq) + bytes(data)


def configure(slave, entries, *, event=0, mode=0x02):
    """Lists 0 (STIM: one ODT of ``entries``) and 1 (DAQ), list 0 started."""
    assert cmd(slave, xp.FREE_DAQ) == POSITIVE
    assert cmd(slave, xp.ALLOC_DAQ, 0, *u16(2)) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT, 0, *u16(0), 1) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT, 0, *u16(1), 1) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, *u16(0), 0, len(entries)) == POSITIVE
    assert cmd(slave, xp.ALLOC_ODT_ENTRY, 0, *u16(1), 0, 1) == POSITIVE
    assert cmd(slave, xp.SET_DAQ_PTR, 0, *u16(0), 0, 0) == POSITIVE
    for address, size in entries:
        assert cmd(slave, xp.WRITE_DAQ, 0xFF, size, 0, *u32(address)) == POSITIVE
    assert cmd(slave, xp.SET_DAQ_PTR, 0, *u16(1), 0, 0) == POSITIVE
    assert cmd(slave, xp.WRITE_DAQ, 0xFF, 4, 0, *u32(0)) == POSITIVE
    answer = cmd(slave, xp.SET_DAQ_LIST_MODE, mode, *u16(0), *u16(event), 1, 0)
    if answer != POSITIVE:
        return answer
    assert cmd(slave, xp.SET_DAQ_LIST_MODE, 0, *u16(1), *u16(1), 1, 0) == POSITIVE
    return cmd(slave, xp.START_STOP_DAQ_LIST, 1, *u16(0))


def test_a_slave_with_stim_events_declares_stim(fakes):
    slave = connected_slave(fakes, stim_events=(0,))
    assert cmd(slave, xp.CONNECT, 0)[1] == xp.RES_CALPAG | xp.RES_DAQ | xp.RES_STIM
    assert cmd(slave, xp.GET_DAQ_EVENT_INFO, 0, *u16(0))[1] == 0x8C        # DAQ and STIM
    assert cmd(slave, xp.GET_DAQ_EVENT_INFO, 0, *u16(1))[1] == 0x84        # DAQ only
    assert cmd(slave, xp.GET_DAQ_RESOLUTION_INFO)[1:5] == bytes([1, 248, 1, 248])
    assert cmd(slave, xp.ALLOC_DAQ, 0, *u16(1)) == POSITIVE
    assert cmd(slave, xp.GET_DAQ_LIST_INFO, 0, *u16(0))[1] == 0x0C        # DAQ or STIM
    # without: no STIM anywhere
    plain = connected_slave(fakes)
    assert cmd(plain, xp.CONNECT, 0)[1] == xp.RES_CALPAG | xp.RES_DAQ
    assert cmd(plain, xp.GET_DAQ_EVENT_INFO, 0, *u16(0))[1] == 0x84
    with pytest.raises(ValueError, match="event channels"):
        xp.Slave(*fakes, stim_events=(3,))


def test_stim_dtos_write_the_lists_entries_and_bad_ones_are_counted(fakes):
    memory, daq = fakes
    slave = connected_slave(fakes, stim_events=(0,))
    # two adjacent entries (one write) and one apart
    entries = [(CAL[0] + 16, 4), (CAL[0] + 20, 2), (DATA[0], 1)]
    assert configure(slave, entries) == err(xp.ERR_WRITE_PROTECTED)        # DATA: not calibration
    entries[2] = (CAL[0] + 40, 1)
    assert configure(slave, entries) == POSITIVE + bytes([0])              # FIRST_PID 0
    assert cmd(slave, xp.GET_DAQ_LIST_MODE, 0, *u16(0))[1] == 0x40 | 0x02  # running, STIM
    assert daq.config[0].running is False                                 # not measured
    writes = []
    write = memory.write
    memory.write = lambda a, d: writes.append((a, bytes(d))) or write(a, d)
    assert slave.handle(stim_dto(0, 0, b"\x01\x02\x03\x04\x05\x06\x07")) == []   # no answer
    assert bytes(memory.b[CAL[0] + 16:CAL[0] + 22]) == b"\x01\x02\x03\x04\x05\x06"
    assert memory.b[CAL[0] + 40] == 7
    assert writes == [(CAL[0] + 16, b"\x01\x02\x03\x04\x05\x06"), (CAL[0] + 40, b"\x07")]
    before = bytes(memory.b)
    bad = [stim_dto(0, 0, bytes(6)),               # a byte short
           stim_dto(0, 0, bytes(8)),               # a byte long
           stim_dto(1, 0, bytes(7)),               # no ODT 1
           stim_dto(0, 5, bytes(7)),               # no list 5
           stim_dto(0, 1, bytes(4)),               # list 1 is DAQ
           b"\x00\x00"]                            # shorter than the identification field
    for packet in bad:
        assert slave.handle(packet) == []
    assert bytes(memory.b) == before
    # a value the memory refuses: dropped and counted by the error
    assert cmd(slave, xp.START_STOP_DAQ_LIST, 0, *u16(0)) == POSITIVE + bytes([0])
    assert slave.handle(stim_dto(0, 0, bytes(7))) == []                    # stopped
    assert configure(slave, [(REFUSE_AT, 1)]) == POSITIVE + bytes([0])
    assert slave.handle(stim_dto(0, 0, b"\xff")) == []
    assert memory.b[REFUSE_AT] != 0xFF
    stim = slave.counters()["stim"]
    assert stim["dtos"] == 9 and stim["written"] == 1
    assert stim["dropped"] == {"bad_length": 3, "unknown_odt": 1, "unknown_list": 1,
                               "not_running": 2, "ERR_OUT_OF_RANGE": 1}
    assert slave.counters()["errors"] == {"ERR_WRITE_PROTECTED": 1}       # STIM gets no answer
    assert slave.counters()["ignored"]["stim_bad_length"] == 3            # packets ignored
    # a STIM DTO before CONNECT
    slave.reset()
    assert slave.handle(stim_dto(0, 0, b"\x01")) == []
    assert slave.counters()["stim"]["dropped"]["not_connected"] == 1


def test_stim_list_mode_rules(fakes):
    slave = connected_slave(fakes, stim_events=(0,))
    entries = [(CAL[0], 4)]
    assert configure(slave, entries, event=1) == err(xp.ERR_OUT_OF_RANGE)   # a DAQ-only event
    assert configure(slave, entries, mode=0x12) == err(xp.ERR_OUT_OF_RANGE)  # with a timestamp
    plain = connected_slave(fakes)
    assert configure(plain, entries) == err(xp.ERR_OUT_OF_RANGE)             # no STIM event
    # seed & key: a STIM list needs DAQ (its configuration) and CAL/PAG (it
    # calibrates) unlocked; STIM is not locked apart
    locked = connected_slave(fakes, stim_events=(0,), secret=SECRET)
    assert cmd(locked, xp.GET_STATUS)[2] == xp.RES_CALPAG | xp.RES_DAQ
    assert cmd(locked, xp.GET_SEED, 0, xp.RES_STIM) == POSITIVE + bytes([0])   # not protected
    seed = cmd(locked, xp.GET_SEED, 0, xp.RES_DAQ)
    key = compute_key(SECRET, seed[2:2 + seed[1]])
    assert cmd(locked, xp.UNLOCK, len(key), *key)[0] == xp.PID_RES
    assert configure(locked, entries) == err(xp.ERR_ACCESS_LOCKED)
    seed = cmd(locked, xp.GET_SEED, 0, xp.RES_CALPAG)
    key = compute_key(SECRET, seed[2:2 + seed[1]])
    assert cmd(locked, xp.UNLOCK, len(key), *key)[0] == xp.PID_RES
    assert configure(locked, entries) == POSITIVE + bytes([0])


# ---- pyxcp and the running loop -------------------------------------------------------

class _StimPid(int):
    """A STIM DTO's first byte (its ODT number) as pyxcp's transport sends a packet."""

    name = "STIM"


def send_stim(x, odt, daq, data):
    """A STIM DTO through pyxcp's transport (sent, no answer awaited)."""
    x.transport.block_request(_StimPid(odt), 0, *u16(daq), *data)


def test_pyxcp_stim_writes_a_parameter_of_the_running_loop_at_a_tick_boundary():
    from test_xcp_loop import TAU_RISE, TICKS, Loop
    from test_xcp_protocol import error_of, pyxcp_master
    from waiting import wait_until

    from rt_loop._rt_loop import ffi, lib
    from rt_loop.measure.xcp import XcpServer

    loop = Loop()
    srv = XcpServer(ffi, lib, loop.c, port=0, protocol="udp")
    loop.start()
    try:
        tau = loop.double(TAU_RISE)
        with srv, pyxcp_master(srv) as x:
            x.connect()
            assert x.slaveProperties.supportsStim
            assert x.getDaqEventInfo(0).daqEventProperties.stim               # the tick
            assert not x.getDaqEventInfo(1).daqEventProperties.stim
            x.freeDaq()
            x.allocDaq(2)
            for n in (0, 1):
                x.allocOdt(n, 1)
            for n in (0, 1):
                x.allocOdtEntry(n, 0, 1)
            x.setDaqPtr(0, 0, 0)
            x.writeDaq(0xFF, 8, 0, TAU_RISE)
            x.setDaqPtr(1, 0, 0)
            x.writeDaq(0xFF, 8, 0, TICKS)                                     # not writable
            x.setDaqListMode(mode=0x02, daq_list_number=0, event_channel_number=0,
                             prescaler=1, priority=0)
            x.setDaqListMode(mode=0x02, daq_list_number=1, event_channel_number=0,
                             prescaler=1, priority=0)
            assert x.getDaqListMode(0).currentMode.direction
            with pytest.raises(Exception) as e:
                x.startStopDaqList(1, 1)
            assert "ERR_WRITE_PROTECTED" in error_of(e)
            x.startStopDaqList(1, 0)
            applied = int(loop.c.cal.applied)
            send_stim(x, 0, 0, struct.pack("<d", tau * 1.5))
            assert wait_until(lambda: loop.double(TAU_RISE) == tau * 1.5)
            assert int(loop.c.cal.applied) > applied          # through the cal ring, at a tick
            # a value the plant refuses: queued (nobody waits for a STIM write), refused
            # and undone by the loop at the tick, counted there
            refused = int(loop.c.cal.refused)
            send_stim(x, 0, 0, struct.pack("<d", -1.0))
            assert wait_until(lambda: int(loop.c.cal.refused) == refused + 1)
            # dropped and counted: a wrong length, no such list
            send_stim(x, 0, 0, struct.pack("<d", 0.1)[:7])
            send_stim(x, 0, 9, struct.pack("<d", 0.1))
            assert wait_until(lambda: srv.slave.counters()["stim"]["dtos"] == 4)
            stim = srv.slave.counters()["stim"]
            assert stim["written"] == 2
            assert stim["dropped"] == {"bad_length": 1, "unknown_list": 1}
            assert loop.double(TAU_RISE) == tau * 1.5
            x.startStopDaqList(0, 0)
            x.disconnect()
    finally:
        loop.stop()


def test_pyxcp_modify_bits_checksum_and_a_block_on_the_running_loop():
    import zlib

    from pyxcp.types import XcpResponseError
    from test_xcp_loop import DRIVER_T, ENGINE, ENGINE_SIZE, TAU_RISE, Loop
    from test_xcp_protocol import error_of, pyxcp_master

    from rt_loop._rt_loop import ffi, lib
    from rt_loop.measure.xcp import XcpServer

    loop = Loop()
    srv = XcpServer(ffi, lib, loop.c, port=0, protocol="udp")
    loop.start()
    try:
        tau = loop.double(TAU_RISE)
        with srv, pyxcp_master(srv) as x:
            x.connect()
            # MODIFY_BITS on the upper half of a double: its lowest mantissa bit there
            x.setMta(TAU_RISE + 4)
            x.modifyBits(0, 0xFFFF, 0x0001)
            raw = bytearray(struct.pack("<d", tau))
            raw[4] ^= 0x01
            assert loop.double(TAU_RISE) == struct.unpack("<d", raw)[0] != tau
            with pytest.raises(XcpResponseError) as e:
                x.modifyBits(16, 0xFFFF, 0x8000)                  # the sign: the plant refuses
            assert "ERR_OUT_OF_RANGE" in error_of(e)
            assert loop.double(TAU_RISE) == struct.unpack("<d", raw)[0]
            # BUILD_CHECKSUM over the engine's parameters
            x.setMta(ENGINE)
            cs = x.buildChecksum(ENGINE_SIZE)
            assert cs.checksum == zlib.crc32(srv.backend.read(ENGINE, ENGINE_SIZE))
            # a master block into the driver table: one write of four pieces, applied whole
            pieces = srv.backend.counters()["write_pieces"]
            block = struct.pack("<31d", *(0.5 * k for k in range(31))) + b"\x00" * 7
            x.setMta(DRIVER_T)
            x.download(block[:250], block_mode_length=255)
            x.downloadNext(block[250:], remaining_block_length=5, last=True)
            assert srv.backend.read(DRIVER_T, 255) == block
            c = srv.backend.counters()
            assert c["write_pieces"] - pieces == -(-255 // lib.RT_WRITE_BYTES)
            x.disconnect()
    finally:
        loop.stop()
