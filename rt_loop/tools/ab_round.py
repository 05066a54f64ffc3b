"""One round of an A/B benchmark of the loop (faults_bench, xcp_bench, capture_bench): a
server on a virtual bus driven by a test TCU for the round's length, and the
figures compared between the rounds with and without what is measured; and the
idle, prepared loop their C measurements time the tick's parts on."""

import time


def drive(srv, peer):
    """Keeps the TCU's command changing (a clutch current every second) until
    the server's round ends, so every tick has work."""
    t0 = time.monotonic()
    while srv.running:
        peer.set(SolenoidCurrent1=0.4 if int(time.monotonic() - t0) % 2 == 0 else 0.0)
        srv.wait(0.05)


def loop_figures(rep):
    """The loop's figures of a finished round from ``Server.report(histograms=True)``:
    ticks, turnaround and execution percentiles, the mean execution of the ticks
    under 20 us (the tick's own cost, without the machine's long interruptions)
    and the overruns."""
    ex = rep["execution"]
    return {
        "ticks": rep["counts"]["ticks"],
        "turnaround": {k: rep["turnaround"][k] for k in ("p50_us", "p99_9_us", "max_us")},
        "execution": {k: ex[k] for k in ("p50_us", "p99_9_us", "max_us")},
        "execution_mean_under_20us": execution_mean_under(ex.get("histogram", []), 20),
        "overruns": rep["counts"]["overruns"],
    }


def execution_mean_under(histogram, limit_us):
    """Mean execution of the ticks under ``limit_us`` from a 1 us histogram
    ((bin, count) pairs, bin centres): the tick's own cost without the
    machine's long interruptions; None without such ticks."""
    hist = [(b, c) for b, c in histogram if b < limit_us]
    n = sum(c for _, c in hist)
    return sum((b + 0.5) * c for b, c in hist) / n if n else None


def idle_loop():
    """(ffi, lib, loop): a loop prepared with the default parameters and mapping at
    2 kHz and never run, for the benchmarks that time the tick's parts in C
    (``rt_daq_bench``, ``rt_capture_bench``)."""
    from can_dbc import mapping
    from plant.params import fill_params, load_params
    from rt_loop._rt_loop import ffi, lib
    from rt_loop.channels import LoopChannels

    loop = ffi.new("rt_loop *")
    fill_params(ffi, ffi.addressof(loop[0].plant, "params"), load_params(None, ffi, None))
    LoopChannels(mapping.load(mapping.DEFAULT_MAPPING), ffi, lib).install(loop)
    loop.chan[0].transport = lib.RT_TRANSPORT_RING
    loop.cfg.period_s, loop.cfg.cpu = 0.0005, -1
    if lib.rt_loop_prepare(loop) != 0:
        raise RuntimeError("rt_loop_prepare failed")
    return ffi, lib, loop
