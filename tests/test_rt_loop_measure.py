"""The loop's measurement and calibration path in C (rt_loop.h: DAQ, writes, stimulus).

The C loop runs from Python in a thread of its own on the ring transport,
with the project's own contract; nothing here speaks XCP (tests/test_xcp_*.py
do): these tests drive the rings and the DAQ configuration slots directly and
assert what the tick does with them. Waits poll with a generous limit; nothing
is timed.
"""

import math
import struct
import threading

import pytest
from waiting import WAIT_S
from waiting import wait_until as _wait_until

from can_dbc import mapping as can_mapping
from plant.params import fill_params, load_params
from rt_loop._rt_loop import ffi, lib
from rt_loop.channels import LoopChannels

_PARAMS = load_params(None, ffi, {"hydraulics": {"pressure_commanded": 0}})
_CHANNELS = LoopChannels(can_mapping.load(can_mapping.DEFAULT_MAPPING), ffi, lib)


def wait_until(predicate, what):
    assert _wait_until(predicate, WAIT_S), f"waited {WAIT_S:g} s for: {what}"


def offset(*path):
    return ffi.offsetof("rt_loop", *path)


class Loop:
    def __init__(self, duration_s=0.0, regions=(), period_s=0.0005):
        self.c = ffi.new("rt_loop *")
        fill_params(ffi, ffi.addressof(self.c[0].plant, "params"), _PARAMS)
        cfg = self.c.cfg
        cfg.period_s, cfg.priority, cfg.cpu, cfg.duration_s = period_s, 0, -1, duration_s
        _CHANNELS.install(self.c)
        self.c.chan[0].transport, self.c.chan[0].fd = lib.RT_TRANSPORT_RING, -1
        self.c.n_regions = len(regions)
        for i, (off, size, kind) in enumerate(regions):
            g = self.c.regions[i]
            g.offset, g.size, g.kind = off, size, kind
        self.rc = lib.rt_loop_prepare(self.c)
        self.thread = None

    def start(self):
        assert self.rc == 0, self.rc
        self.thread = threading.Thread(target=lib.rt_loop_run, args=(self.c,), daemon=True)
        self.thread.start()
        wait_until(lambda: self.c.stats.ticks > 5, "the loop ticks")
        return self

    def stop(self):
        lib.rt_loop_request_stop(self.c)
        self.thread.join(30)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def ticks(self):
        return int(self.c.stats.ticks)

    # -- DAQ
    def publish_daq(self, lists):
        """lists: [(event, prescaler, [[(offset, size), ...] per ODT])]; returns the generation."""
        gen = int(self.c.daq_gen) + 1
        cfg = self.c.daq[gen & 1]
        cfg.n_lists = len(lists)
        odt_at = entry_at = 0
        for i, (event, prescaler, odts) in enumerate(lists):
            d = cfg.lists[i]
            d.first_odt, d.n_odts, d.event, d.prescaler, d.running = odt_at, len(odts), event, prescaler, 1
            for entries in odts:
                t = cfg.odts[odt_at]
                t.first_entry, t.n_entries = entry_at, len(entries)
                for off, size in entries:
                    cfg.entries[entry_at].offset, cfg.entries[entry_at].size = off, size
                    entry_at += 1
                odt_at += 1
        self.c.daq_gen = gen
        wait_until(lambda: int(self.c.daq_ack) == gen, "the loop takes the DAQ configuration")
        return gen

    def pop_dtos(self, n=4096):
        buf = ffi.new("rt_dto[]", n)
        k = lib.rt_daq_pop_many(ffi.addressof(self.c, "daq_ring"), buf, n)
        return [buf[i] for i in range(k)], buf

    # -- writes
    def write(self, ring, off, data, time_s=0.0, wid=1):
        w = ffi.new("rt_write *")
        w.time_s, w.offset, w.len, w.id = time_s, off, len(data), wid
        ffi.memmove(w.data, data, len(data))
        return lib.rt_write_push_many(ffi.addressof(self.c, ring), w, 1)


def dbl(x):
    return struct.pack("<d", x)


# ------------------------------------------------------------------ DAQ

def test_daq_copies_the_configured_bytes_every_tick_with_the_ticks_deadline():
    speed = offset("plant", "outputs", "engine_speed_rpm")
    t_off = offset("plant", "state", "time_s")
    with Loop() as loop:
        assert int(loop.c.daq_ring.head) == 0           # no configuration: nothing copied
        loop.publish_daq([(lib.RT_EVENT_TICK, 1, [[(t_off, 8), (speed, 8)]])])
        wait_until(lambda: int(loop.c.daq_ring.head) >= 200, "DTOs")
        dtos, _keep = loop.pop_dtos()
    assert len(dtos) >= 200
    ticks = [int(d.tick) for d in dtos]
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks)))     # every tick, none lost
    times = [int(d.time_ns) for d in dtos]
    steps = {b - a for a, b in zip(times, times[1:])}
    assert all(s % 500_000 == 0 and s > 0 for s in steps)            # deadlines, 0.5 ms apart
    for d in dtos:
        assert d.len == 16 and d.list == 0 and d.odt == 0
        plant_t, rpm = struct.unpack("<dd", bytes(ffi.buffer(d.data, 16)))
        assert plant_t == pytest.approx((int(d.tick) + 1) * 0.0005, abs=1e-9)   # after its step
        assert 500 < rpm < 1000                                         # idling
    assert int(loop.c.daq_ring.dropped) == 0


def test_daq_events_and_prescalers_thin_the_lists_out():
    speed = offset("plant", "outputs", "engine_speed_rpm")
    with Loop() as loop:
        loop.publish_daq([(lib.RT_EVENT_10MS, 1, [[(speed, 8)]]),
                          (lib.RT_EVENT_TICK, 4, [[(speed, 8)], [(speed, 4)]])])
        t0 = loop.ticks()
        wait_until(lambda: loop.ticks() > t0 + 400, "400 ticks")
        loop.publish_daq([])                             # stop copying
        dtos, _keep = loop.pop_dtos()
    by_list = {0: [], 1: []}
    for d in dtos:
        by_list[int(d.list)].append((int(d.tick), int(d.odt), int(d.len)))
    ten = [t for t, _, _ in by_list[0]]
    assert len(ten) >= 18 and {b - a for a, b in zip(ten, ten[1:])} == {20}
    quarter = by_list[1]
    odt0 = [t for t, o, _ in quarter if o == 0]
    assert {b - a for a, b in zip(odt0, odt0[1:])} == {4}
    assert [o for _, o, _ in quarter[:4]] == [0, 1, 0, 1] and quarter[1][2] == 4


def test_a_bad_daq_configuration_is_refused_counted_and_copies_nothing():
    with Loop() as loop:
        loop.publish_daq([(lib.RT_EVENT_TICK, 1, [[(ffi.sizeof("rt_loop") - 4, 8)]])])
        assert int(loop.c.daq_refused) == 1
        loop.publish_daq([(lib.RT_EVENT_TICK, 1, [[(0, 200), (0, 100)]])])   # ODT > 248 bytes
        assert int(loop.c.daq_refused) == 2
        ticks = loop.ticks()
        wait_until(lambda: loop.ticks() > ticks + 20, "ticks")
        assert int(loop.c.daq_ring.head) == 0


def test_a_full_daq_ring_drops_and_counts_and_the_loop_goes_on():
    speed = offset("plant", "outputs", "engine_speed_rpm")
    with Loop() as loop:
        loop.publish_daq([(lib.RT_EVENT_TICK, 1, [[(speed, 8)]] * 20)])     # 20 DTOs per tick
        wait_until(lambda: int(loop.c.daq_ring.dropped) > 100, "the ring overflows")
        ticks = loop.ticks()
        wait_until(lambda: loop.ticks() > ticks + 20, "the loop still ticks")
        assert int(loop.c.stats.state) == lib.RT_STATE_RUNNING
    assert int(loop.c.daq_ring.head) - int(loop.c.daq_ring.tail) == lib.RT_DAQ_RING_SIZE


# ------------------------------------------------------------------ writes

def test_a_calibration_write_into_a_region_is_applied_whole_at_a_tick_boundary():
    grade = offset("plant", "inputs", "road_grade_pct")
    mass = offset("plant", "params", "vehicle", "mass_kg")
    regions = [(grade, 8, lib.RT_REGION_DATA), (mass, 8, lib.RT_REGION_PARAM)]
    with Loop(regions=regions) as loop:
        assert loop.write("cal", grade, dbl(12.5), wid=7) == 1
        wait_until(lambda: int(loop.c.cal.applied) == 1, "the write applied")
        assert loop.c.plant.inputs.road_grade_pct == 12.5 and int(loop.c.cal.last_applied_id) == 7
        wait_until(lambda: loop.c.plant.outputs.road_grade_pct == 12.5, "the plant uses it")
        # a parameter: re-derived by the plant, kept
        loop.write("cal", mass, dbl(1800.0), wid=8)
        wait_until(lambda: int(loop.c.cal.applied) == 2, "the parameter applied")
        assert loop.c.plant.params.vehicle.mass_kg == 1800.0
        # refused: outside every region, across a region's end, a parameter the plant refuses
        loop.write("cal", offset("plant", "inputs", "fork_force1_n"), dbl(5.0), wid=9)
        loop.write("cal", grade + 4, dbl(1.0), wid=10)
        loop.write("cal", mass, dbl(-5.0), wid=11)
        wait_until(lambda: int(loop.c.cal.refused) == 3, "three writes refused")
        assert int(loop.c.cal.last_refused_id) == 11
        assert loop.c.plant.params.vehicle.mass_kg == 1800.0          # as before the refusal
        assert loop.c.plant.inputs.road_grade_pct == 12.5
        assert int(loop.c.stats.state) == lib.RT_STATE_RUNNING


def test_stimulus_writes_wait_for_their_plant_time():
    accel = offset("plant", "inputs", "accel_pedal_pct")
    with Loop(regions=[(accel, 8, lib.RT_REGION_DATA)]) as loop:
        t_now = float(loop.c.stats.sim_time_s)
        at = t_now + 0.2
        loop.write("stim", accel, dbl(30.0), time_s=at, wid=1)
        loop.write("stim", accel, dbl(60.0), time_s=at + 0.1, wid=2)
        loop.write("stim", accel, dbl(0.0), time_s=math.nan, wid=3)    # never due: waits forever
        wait_until(lambda: int(loop.c.stim.applied) >= 1, "the first stimulus")
        first = float(loop.c.stats.sim_time_s)
        assert first >= at - 1e-9
        wait_until(lambda: int(loop.c.stim.applied) == 2, "the second")
        assert loop.c.plant.inputs.accel_pedal_pct == 60.0
        ticks = loop.ticks()
        wait_until(lambda: loop.ticks() > ticks + 40, "more ticks")
        assert int(loop.c.stim.applied) == 2 and loop.c.plant.inputs.accel_pedal_pct == 60.0


def test_bad_regions_are_refused_by_prepare():
    size = ffi.sizeof("rt_loop")
    for regions in ([(size - 4, 8, lib.RT_REGION_DATA)], [(0, 0, lib.RT_REGION_DATA)],
                    [(0, 8, 7)]):
        assert Loop(regions=regions).rc == -22, regions


# ------------------------------------------------------------------ signal values

def test_the_can_signals_last_values_are_in_the_loop_memory():
    names = []
    for bus, msg in _CHANNELS.messages:
        i = _CHANNELS.messages.index((bus, msg))
        names += [(msg.name, s) for s in _CHANNELS.table(0).signal_names(i)]
    at = {n: k for k, n in enumerate(names)}
    with Loop() as loop:
        wait_until(lambda: loop.ticks() > 400, "ticks")
        v = loop.c.signal_values
        assert int(loop.c.n_signal_values) == len(names)
        assert v[at[("DCT_ShaftSpeeds", "EngineSpeed")]] == pytest.approx(
            loop.c.plant.outputs.engine_speed_rpm, abs=30)
        assert 0 < v[at[("SIM_Status", "SimTime")]] <= float(loop.c.stats.sim_time_s)


def test_a_signal_has_no_value_until_its_first_frame():
    """NaN (null on the control channel) before a signal was ever on the bus,
    not a 0 that reads as a value: before the first tick every signal; while
    no TCU sends, the TCU's signals stay without value as the plant's get theirs."""
    names = []
    for bus, msg in _CHANNELS.messages:
        i = _CHANNELS.messages.index((bus, msg))
        names += [(msg.name, s) for s in _CHANNELS.table(0).signal_names(i)]
    at = {n: k for k, n in enumerate(names)}
    loop = Loop()
    assert loop.rc == 0
    assert all(math.isnan(loop.c.signal_values[k]) for k in range(len(names)))
    with loop:
        wait_until(lambda: loop.ticks() > 400, "ticks")
        assert math.isfinite(loop.c.signal_values[at[("DCT_ShaftSpeeds", "EngineSpeed")]])
        assert math.isnan(loop.c.signal_values[at[("TCU_EngineCmd", "TargetGear")]])
