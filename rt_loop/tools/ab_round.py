"""One round of an A/B benchmark of the loop (faults_bench, xcp_bench): a
server on a virtual bus driven by a test TCU for the round's length, and the
figures compared between the rounds with and without what is measured."""

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
