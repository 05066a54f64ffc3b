"""The scope (rt_loop/csrc/rt_scope.c, rt_loop/measure/scope.py): min and max of
chosen values over buckets of ticks, drained in a thread of its own.

Shown on a running server (the embedded transport, no TCU): a one-tick spike
written by the stimulus ring is in its bucket's max, the buckets follow each
other tick for tick, names are checked, tracing is counted per reader, a
bad configuration is refused by the loop and counted, and a ring nobody
drains counts what it drops while the loop runs on."""

import struct

import numpy as np
import pytest

from dct_hil.bench import Bench
from rt_loop.measure.scope import MAX_TRACES, ScopeError


@pytest.fixture(scope="module")
def bench():
    b = Bench.start(tcu=False)
    yield b
    b.stop()


def stim_writes(server, writes):
    """Queues (plant time, name of a plant input, value) into the stim ring."""
    ffi, lib, loop = server._ffi, server._lib, server._l
    buf = ffi.new("rt_write[]", len(writes))
    for k, (t, name, value) in enumerate(writes):
        w = buf[k]
        w.time_s = t
        w.offset = ffi.offsetof("rt_loop", "plant", "inputs", name)
        w.len = 8
        w.id = 900_000 + k
        ffi.memmove(w.data, struct.pack("<d", value), 8)
    assert lib.rt_write_push_many(ffi.addressof(loop, "stim"), buf, len(writes)) == len(writes)


def wait_buckets(scope, names, tick, bench, timeout_s=3.0):
    end = bench.time_s + timeout_s
    while True:
        d = scope.read(names)
        if len(d["tick"]) and d["tick"][-1] > tick:
            return d
        assert bench.time_s < end, "no bucket past the tick"
        bench.sleep(0.02)


def test_a_one_tick_spike_is_in_its_buckets_max(bench):
    srv, scope = bench.server, bench.server.scope
    scope.add(["inputs.road_grade_pct", "time_s"])
    try:
        t0 = round(bench.time_s + 0.2, 4)
        step = srv.step_s
        stim_writes(srv, [(t0, "road_grade_pct", 30.0), (t0 + step, "road_grade_pct", 0.0)])
        tick_end = int((t0 + 0.1) / step)
        d = wait_buckets(scope, ["inputs.road_grade_pct", "time_s"], tick_end, bench)
        hi, lo = d["max"]["inputs.road_grade_pct"], d["min"]["inputs.road_grade_pct"]
        spikes = np.flatnonzero(hi == 30.0)
        assert len(spikes) == 1, "the spike is in exactly one bucket"
        k = spikes[0]
        assert lo[k] == 0.0, "the same bucket's min is the value around it"
        # plant time of the bucket: the spike's tick lies inside it
        assert d["min"]["time_s"][k] - step <= t0 + 1e-9 <= d["max"]["time_s"][k]
        # buckets of 10 ticks, one after the other, none missing
        ticks = d["tick"][np.isfinite(d["max"]["time_s"])]
        assert set(np.diff(ticks)) == {scope.bucket_ticks}
        assert d["max"]["time_s"][k] - d["min"]["time_s"][k] == pytest.approx(
            (scope.bucket_ticks - 1) * step, abs=1e-9)
    finally:
        scope.remove(["inputs.road_grade_pct", "time_s"])


def test_names_are_checked_with_a_line_naming_the_cause(bench):
    scope = bench.server.scope
    names = scope.traceable()
    for n in ("vehicle_speed_kmh", "inputs.road_grade_pct", "cmd.solenoid_current1_a",
              "TCU_ClutchCmd.SolenoidCurrent1", "turnaround_us", "maneuver_time_s"):
        assert n in names
    with pytest.raises(ScopeError) as e:
        scope.add(["vehicle_speed_kmhh"])
    assert "vehicle_speed_kmhh" in str(e.value) and "vehicle_speed_kmh" in str(e.value)
    assert "\n" not in str(e.value)
    outputs = [n for n in names if "." not in n][:MAX_TRACES + 1]
    with pytest.raises(ScopeError, match=f"at most {MAX_TRACES}"):
        scope.add(outputs)
    assert scope.traced() == [], "a refused add traces nothing"


def test_tracing_is_counted_per_reader(bench):
    scope = bench.server.scope
    scope.add(["engine_speed_rpm"])
    scope.add(["engine_speed_rpm", "gear"])
    scope.remove(["engine_speed_rpm"])
    assert sorted(scope.traced()) == ["engine_speed_rpm", "gear"]
    t = bench.time_s
    d = wait_buckets(scope, ["engine_speed_rpm"], int(t / bench.server.step_s), bench)
    assert np.isfinite(d["max"]["engine_speed_rpm"][-1])
    scope.remove(["engine_speed_rpm", "gear"])
    assert scope.traced() == []
    assert np.isnan(scope.read(["gear"])["max"]["gear"]).all(), "no history once untraced"


def test_a_bad_configuration_is_refused_and_counted(bench):
    srv = bench.server
    lib, loop = srv._lib, srv._l
    scope = srv.scope
    refused = int(loop.scope_refused)
    with scope._lock:                         # the scope's own publication path, a bad offset
        gen = scope._gen + 1
        cfg = loop.scope_cfg[gen & 1]
        cfg.n, cfg.bucket_ticks, cfg.offset[0] = 1, 10, 3          # not 8-aligned
        scope._gen = gen
        lib.rt_scope_publish(loop, gen)
    t = bench.time_s
    bench.wait_until(f"time_s > {t + 0.05:.4f}", timeout_s=1.0)
    assert int(loop.scope_refused) == refused + 1
    assert int(lib.rt_scope_acked(loop)) == gen and srv.running
    scope.add(["gear"])                       # the next good one is taken
    bench.wait_until(f"time_s > {bench.time_s + 0.05:.4f}", timeout_s=1.0)
    assert int(loop.scope_refused) == refused + 1
    scope.remove(["gear"])


@pytest.mark.slow
def test_a_ring_nobody_drains_counts_its_drops():
    b = Bench.start(tcu=False)
    try:
        srv = b.server
        srv.scope.stop()                      # the drain is gone
        loop, lib = srv._l, srv._lib
        cfg = loop.scope_cfg[1]
        cfg.n, cfg.bucket_ticks = 1, 1
        cfg.offset[0] = srv._ffi.offsetof("rt_loop", "plant", "outputs", "time_s")
        lib.rt_scope_publish(loop, int(loop.scope_gen) + 1)
        ring = int(lib.RT_SCOPE_RING_SIZE)
        t = b.time_s
        b.wait_until(f"time_s > {t + (ring + 200) * srv.step_s:.4f}", timeout_s=3.0)
        assert int(loop.scope.dropped) >= 100
        assert srv.running
    finally:
        b.stop()
