"""The XCP slave on the real loop: rt_loop.measure.xcp.loop_backend.LoopBackend over
a running rt_loop (the C side of rt_loop.h's measurement and calibration
block: the cal ring, daq[2] / daq_gen / daq_ack, the daq ring).

The loop serves the default mapping over its rings (no CAN); its writable
regions are the engine's parameters (RT_REGION_PARAM: the plant checks them)
and the driver's time column (RT_REGION_DATA: unused without a driver
table). pyxcp is the master where the whole chain is meant. Every assertion
is about behaviour (values, order, counts); waits only bound a failure.
"""

import struct
import threading
import time

import pytest
from requires import built_with, module

from rt_loop._rt_loop import ffi, lib

built_with(lib, "rt_daq_pop_many")
module("pyxcp")

from test_xcp_protocol import Measured, error_of, pyxcp_master
from waiting import wait_until

from can_dbc import mapping as can_mapping
from plant.params import fill_params, load_params
from rt_loop.channels import LoopChannels
from rt_loop.measure.xcp import XcpServer
from rt_loop.measure.xcp import protocol as xp
from rt_loop.measure.xcp.loop_backend import LoopBackend, loop_events, set_regions
from rt_loop.measure.xcp.protocol import DaqEntry, DaqListConfig

MAPPING = can_mapping.load(can_mapping.DEFAULT_MAPPING)
CHANNELS = LoopChannels(MAPPING, ffi, lib)
PARAMS = load_params(None, ffi, None)

ENGINE = ffi.offsetof("rt_loop", "plant", "params", "engine")
ENGINE_SIZE = ffi.sizeof("dct_engine_params")
TAU_RISE = ENGINE + ffi.offsetof("dct_engine_params", "tau_rise_s")
DRIVER_T = ffi.offsetof("rt_loop", "driver", "t_s")
DRIVER_T_SIZE = 8 * lib.RT_DRIVER_ROWS
TICKS = ffi.offsetof("rt_loop", "stats", "ticks")
SIM_TIME = ffi.offsetof("rt_loop", "stats", "sim_time_s")
LOOP_SIZE = ffi.sizeof("rt_loop")


class Loop:
    """A prepared rt_loop with writable regions, run in a thread of its own."""

    def __init__(self):
        self.c = ffi.new("rt_loop *")
        fill_params(ffi, ffi.addressof(self.c[0].plant, "params"), PARAMS)
        cfg = self.c.cfg
        cfg.period_s = 0.0005
        cfg.cpu = -1
        CHANNELS.install(self.c)
        self.c.chan[0].transport = lib.RT_TRANSPORT_RING
        self.c.chan[0].fd = -1
        set_regions(ffi, lib, self.c, [(ENGINE, ENGINE_SIZE, lib.RT_REGION_PARAM),
                                       (DRIVER_T, DRIVER_T_SIZE, lib.RT_REGION_DATA)])
        rc = lib.rt_loop_prepare(self.c)
        assert rc == 0, rc
        self.thread = None

    def start(self):
        self.thread = threading.Thread(target=lib.rt_loop_run, args=(self.c,), daemon=True)
        self.thread.start()
        assert wait_until(lambda: self.c.stats.state == lib.RT_STATE_RUNNING
                          and self.c.stats.ticks > 0)
        return self

    def stop(self):
        if self.thread is not None:
            lib.rt_loop_request_stop(self.c)
            self.thread.join(30)
            assert not self.thread.is_alive()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def double(self, offset):
        return struct.unpack("<d", ffi.buffer(self.c, LOOP_SIZE)[offset:offset + 8])[0]


@pytest.fixture
def loop():
    lp = Loop()
    yield lp
    lp.stop()


def test_set_regions_refuses_what_the_loop_would():
    c = ffi.new("rt_loop *")
    with pytest.raises(ValueError, match="outside"):
        set_regions(ffi, lib, c, [(LOOP_SIZE - 4, 8, lib.RT_REGION_DATA)])
    with pytest.raises(ValueError, match="kind"):
        set_regions(ffi, lib, c, [(0, 8, 7)])
    set_regions(ffi, lib, c, [(16, 8, lib.RT_REGION_DATA)])
    assert c.n_regions == 1 and (c.regions[0].offset, c.regions[0].size) == (16, 8)


def test_the_loops_events_in_wall_clock_time():
    c = ffi.new("rt_loop *")
    c.cfg.period_s = 0.0005
    assert [(e.name, e.cycle_s) for e in loop_events(c)] == [
        ("tick", 0.0005), ("10ms", 0.01), ("100ms", 0.1)]
    c.cfg.step_s = 0.00005                             # ten times slower
    assert [round(e.cycle_s, 9) for e in loop_events(c)] == [0.0005, 0.1, 1.0]


def test_memory_reads_the_loop_and_writes_through_its_cal_ring(loop):
    backend = LoopBackend(ffi, lib, loop.c)
    tau = loop.double(TAU_RISE)
    assert backend.read(TAU_RISE, 8) == struct.pack("<d", tau)
    assert backend.read(LOOP_SIZE - 4, 8) == xp.ERR_ACCESS_DENIED
    assert backend.cal_regions() == [(ENGINE, ENGINE_SIZE), (DRIVER_T, DRIVER_T_SIZE)]
    # not ticking yet: queued, applied at the first tick
    assert backend.write(DRIVER_T, struct.pack("<d", 1.5)) is xp.OK
    assert backend.write(TICKS, bytes(8)) == xp.ERR_WRITE_PROTECTED
    assert backend.write(LOOP_SIZE - 4, bytes(8)) == xp.ERR_ACCESS_DENIED
    assert backend.write(DRIVER_T + DRIVER_T_SIZE - 8, bytes(16)) == xp.ERR_WRITE_PROTECTED
    loop.start()
    assert wait_until(lambda: loop.double(DRIVER_T) == 1.5)
    # ticking: the answer comes once the loop applied it
    assert backend.write(TAU_RISE, struct.pack("<d", tau * 2)) is xp.OK
    assert loop.double(TAU_RISE) == tau * 2
    assert backend.write(TAU_RISE, struct.pack("<d", -1.0)) == xp.ERR_OUT_OF_RANGE
    assert loop.double(TAU_RISE) == tau * 2                      # the plant refused it: undone
    # more than RT_WRITE_BYTES: several writes, each whole
    table = b"".join(struct.pack("<d", 0.25 * k) for k in range(lib.RT_DRIVER_ROWS))
    assert backend.write(DRIVER_T, table) is xp.OK
    assert backend.read(DRIVER_T, DRIVER_T_SIZE) == table
    c = backend.counters()
    assert c["cal_refused"] == 1 and c["cal_applied"] >= 3
    assert c["write_pieces"] == 3 + -(-DRIVER_T_SIZE // lib.RT_WRITE_BYTES)


def test_values_outside_their_ranges_are_refused_before_the_loop(loop):
    # the A2L generator's form: (offset, size, kind, name, lo, hi, c_type)
    ranges = [(TAU_RISE, 8, lib.RT_REGION_PARAM, "params.engine.tau_rise_s", 0.001, 1.0, "double"),
              (DRIVER_T, DRIVER_T_SIZE, lib.RT_REGION_DATA, "driver.t_s", 0.0, 100.0, "double")]
    backend = LoopBackend(ffi, lib, loop.c, ranges=ranges)
    tau = loop.double(TAU_RISE)
    assert backend.write(TAU_RISE, struct.pack("<d", 5.0)) == xp.ERR_OUT_OF_RANGE
    assert backend.write(TAU_RISE, struct.pack("<d", float("nan"))) == xp.ERR_OUT_OF_RANGE
    # the last two bytes of the double alone: checked with the six it keeps
    assert backend.write(TAU_RISE + 6, b"\xf0\x7f") == xp.ERR_OUT_OF_RANGE   # -> inf or NaN
    block = struct.pack("<3d", 1.0, 2.0, 200.0)
    assert backend.write(DRIVER_T, block) == xp.ERR_OUT_OF_RANGE              # the third
    assert backend.counters()["writes_out_of_range"] == 4
    assert backend.counters()["write_pieces"] == 0                            # none queued
    loop.start()
    assert backend.write(TAU_RISE, struct.pack("<d", 0.5)) is xp.OK
    assert backend.write(DRIVER_T + 8, struct.pack("<2d", 3.0, 4.0)) is xp.OK
    assert loop.double(TAU_RISE) == 0.5 != tau
    with pytest.raises(ValueError, match="C type"):
        LoopBackend(ffi, lib, loop.c, ranges=[(TAU_RISE, 8, 1, "x", 0, 1, "long double")])


def test_daq_configurations_go_to_the_loop_and_its_dtos_come_back(loop):
    backend = LoopBackend(ffi, lib, loop.c)
    loop.start()
    lists = (DaqListConfig(odts=((DaqEntry(TICKS, 8),), (DaqEntry(SIM_TIME, 8),)),
                           event=lib.RT_EVENT_TICK, prescaler=1, running=True),
             DaqListConfig(odts=((DaqEntry(TICKS, 8), DaqEntry(SIM_TIME, 8)),),
                           event=lib.RT_EVENT_10MS, prescaler=2, running=True))
    assert backend.apply(lists) is xp.OK
    got = []
    assert wait_until(lambda: got.extend(backend.pop(512)) or
                      sum(d.list == 1 for d in got) >= 4)
    now = time.monotonic_ns()
    tick_dtos = [d for d in got if d.list == 0]
    assert {(d.odt, len(d.data)) for d in tick_dtos} == {(0, 8), (1, 8)}
    ticks = [struct.unpack("<Q", d.data)[0] for d in tick_dtos if d.odt == 0]
    assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
    stamps = [d.time_ns for d in tick_dtos if d.odt == 0]
    assert stamps == sorted(stamps) and stamps[-1] <= now           # CLOCK_MONOTONIC
    slow = [struct.unpack("<Qd", d.data) for d in got if d.list == 1]
    steps = [b[0] - a[0] for a, b in zip(slow, slow[1:])]
    assert steps and all(s > 0 and s % 40 == 0 for s in steps)      # 10 ms x prescaler 2
    # stopped: nothing more once the loop took the new configuration
    assert backend.apply(tuple(DaqListConfig(d.odts, d.event, d.prescaler, False)
                               for d in lists)) is xp.OK
    backend.pop(512)
    while backend.pop(512):
        pass
    seen = int(loop.c.stats.ticks)
    assert wait_until(lambda: loop.c.stats.ticks > seen + 40)
    assert backend.pop(512) == []
    # a configuration the loop refuses (an entry outside it)
    bad = (DaqListConfig(odts=((DaqEntry(LOOP_SIZE - 4, 8),),), event=0, prescaler=1,
                         running=True),)
    assert backend.apply(bad) == xp.ERR_DAQ_CONFIG
    assert backend.counters()["daq_refused"] == 1


def test_pyxcp_measures_and_calibrates_the_running_loop(loop):
    from pyxcp.daq_stim import DaqList
    from pyxcp.types import XcpResponseError

    srv = XcpServer(ffi, lib, loop.c, port=0, protocol="udp", a2l_text=lambda: "/* A2L */")
    loop.start()
    tau = loop.double(TAU_RISE)
    policy = Measured([
        DaqList(name="tick", event_num=0, stim=False, enable_timestamps=True,
                measurements=[("ticks", TICKS, 0, "U64"), ("t", SIM_TIME, 0, "F64")],
                priority=0, prescaler=1),
        DaqList(name="slow", event_num=2, stim=False, enable_timestamps=True,
                measurements=[("ticks", TICKS, 0, "U64")], priority=0, prescaler=1)])
    with srv, pyxcp_master(srv, policy=policy) as x:
        x.connect()
        assert x.identifier(4) == "/* A2L */"
        assert x.getDaqInfo()["channels"][1]["name"] == "10ms"
        assert x.shortUpload(8, TAU_RISE) == struct.pack("<d", tau)
        x.shortDownload(TAU_RISE, 0, struct.pack("<d", tau + 0.01))
        assert loop.double(TAU_RISE) == tau + 0.01
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(TAU_RISE, 0, struct.pack("<d", 0.0))    # the plant refuses it
        assert "ERR_OUT_OF_RANGE" in error_of(e)
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(TICKS, 0, bytes(8))                      # not a writable region
        assert "ERR_WRITE_PROTECTED" in error_of(e)
        x.copyCalPage(0, 1, 0, 0)                                    # back to the reference
        assert loop.double(TAU_RISE) == tau
        policy.setup()
        policy.start()
        assert wait_until(lambda: sum(r[0] == 0 for r in policy.rows) >= 50
                          and sum(r[0] == 1 for r in policy.rows) >= 3)
        policy.stop()
        x.disconnect()
    fast = [r for r in policy.rows if r[0] == 0]
    ticks = [r[2][0] for r in fast]
    assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
    assert [r[1] for r in fast] == sorted(r[1] for r in fast)        # the tick deadlines
    slow = [r[2][0] for r in policy.rows if r[0] == 1]
    assert all(b - a > 0 and (b - a) % 200 == 0 for a, b in zip(slow, slow[1:]))
    c = srv.counters()
    assert c["protocol"]["errors"] == {"ERR_OUT_OF_RANGE": 1, "ERR_WRITE_PROTECTED": 1}
    assert c["loop"]["daq_refused"] == 0 and c["transport"]["dtos_out"] >= len(policy.rows)
