"""Capture benchmark: what a capture of N signals at every tick costs the tick,
A/B in one run.

    python -m rt_loop.tools.capture_bench [--signals 20] [--pairs 7] [--round-s 10]
                                          [--priority 80] [--json out/bench-capture.json]

Two measurements, each alternating without and with the capture:

- the capture's work alone in C (``rt_capture_bench``: the tick's capture
  code with no configuration, then with N plant outputs at every tick, the
  ring emptied after each; cache warm), ``--pairs`` times 200 000 ticks:
  ns per tick, the difference of the medians is the capture's cost;
- the loop (``--round-s`` rounds, 2 kHz, SCHED_FIFO at ``--priority``, a test
  TCU peer sending commands, as xcp_bench's rounds) without a capture, then
  with one of the same N signals at every tick (``rt_loop.measure.capture``,
  its reader draining): the mean execution of the ticks under 20 us and the
  percentiles, ``--pairs`` times.

The target: the capture costs at most ``TARGET_NS`` (300 ns) per tick, by the
C difference; the loop rounds' difference is reported beside it (a 1 us
histogram: its mean moves by the machine more than by 0.3 us, read it as a
check that nothing else got dearer). Figures to stdout and the JSON file;
exit 0 (1 with ``--check`` above the target or a record lost).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import uuid

from plant import argtypes
from rt_loop.tools.ab_round import drive, idle_loop, loop_figures

TARGET_NS = 300.0


def _outputs(ffi, n):
    """The first n plant outputs (names)."""
    names = [name for name, _ in ffi.typeof("dct_outputs").fields]
    if n > len(names):
        raise SystemExit(f"capture_bench: at most {len(names)} signals (plant outputs)")
    return names[:n]


def copy_ab(names, pairs, iterations=200_000):
    """[(ns without, ns with)] of rt_capture_bench, alternating."""
    ffi, lib, loop = idle_loop()
    offsets = [ffi.offsetof("rt_loop", "plant", "outputs", n) for n in names]
    gen = 0
    out = []

    def publish(sources):
        nonlocal gen
        gen += 1
        cfg = loop.capture_cfg[gen & 1]
        cfg.n, cfg.every = len(sources), 1
        for k, s in enumerate(sources):
            cfg.source[k] = s
        lib.rt_capture_publish(loop, gen)

    for _ in range(pairs):
        pair = []
        for sources in ([], offsets):
            publish(sources)
            ns = lib.rt_capture_bench(loop, iterations)
            if ns < 0:
                raise RuntimeError("rt_capture_bench refused the configuration")
            pair.append(ns)
        out.append(tuple(pair))
    return out


def _round(args, names, with_capture):
    from can_dbc.peer import CanPeer
    from rt_loop.server import Server

    channel = f"bench-capture-{uuid.uuid4().hex[:8]}"
    srv = Server(channel, interface="virtual", priority=args.priority, duration_s=args.round_s)
    srv.start()
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel,
                        values={"SolenoidCurrent1": 0.4, "SolenoidCurrent2": 0.0})
    rows = dropped = None
    try:
        if with_capture:
            caps = srv.capture_manager()
            cid = caps.start(names)                 # every tick, from now, until the round ends
        drive(srv, peer)
        if with_capture:
            caps.drain()
            rows = caps.status(cid)["rows"]
            dropped = caps.counters()["dropped"]
    finally:
        peer.close()
        srv.stop()
    return {"capture": with_capture, "signals": len(names) if with_capture else 0,
            **loop_figures(srv.report(histograms=True)), "rows": rows,
            "records_dropped": dropped}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rt_loop.tools.capture_bench",
                                description=__doc__.split("\n")[0])
    p.add_argument("--signals", type=argtypes.whole_number(1, 64), default=20)
    p.add_argument("--pairs", type=argtypes.whole_number(1), default=7)
    p.add_argument("--round-s", type=argtypes.seconds, default=10.0)
    p.add_argument("--no-loop", action="store_true", help="the C measurement only")
    p.add_argument("--priority", type=argtypes.priority, default=80)
    p.add_argument("--json", default="out/bench-capture.json")
    p.add_argument("--check", action="store_true")
    args = p.parse_args(argv)
    from plant.machine import machine_info, write_figures
    from rt_loop._rt_loop import ffi

    names = _outputs(ffi, args.signals)
    pairs = copy_ab(names, args.pairs)
    for k, (a, b) in enumerate(pairs, 1):
        print(f"C pair {k}: without {a:6.1f} ns, with {len(names)} signals {b:6.1f} ns per tick",
              flush=True)
    without = statistics.median(a for a, _ in pairs)
    with_ = statistics.median(b for _, b in pairs)
    cost = with_ - without
    print(f"capture of {len(names)} signals at every tick (rt_capture_bench, medians): "
          f"{without:.1f} -> {with_:.1f} ns: {cost:.1f} ns per tick (target {TARGET_NS:.0f} ns)",
          flush=True)
    rounds = []
    if not args.no_loop:
        for _ in range(args.pairs):
            for with_capture in (False, True):
                r = _round(args, names, with_capture)
                rounds.append(r)
                ex = r["execution"]
                print(f"round {len(rounds):2d} {'capture' if with_capture else 'none':8s} "
                      f"execution p50 {ex['p50_us']} p99.9 {ex['p99_9_us']} mean<20us "
                      f"{r['execution_mean_under_20us']:.3f} us; overruns {r['overruns']}"
                      + (f"; {r['rows']} rows, {r['records_dropped']} dropped"
                         if with_capture else ""), flush=True)
    loop_cost = None
    if rounds:
        def med(flag):
            xs = [r["execution_mean_under_20us"] for r in rounds if r["capture"] == flag
                  and r["execution_mean_under_20us"] is not None]
            return statistics.median(xs) if xs else None

        a, b = med(False), med(True)
        loop_cost = None if a is None or b is None else (b - a) * 1e3
        print(f"loop rounds, mean execution under 20 us (medians): {a:.3f} -> {b:.3f} us "
              f"({loop_cost:+.0f} ns)")
    lost = sum(r["records_dropped"] or 0 for r in rounds if r["capture"])
    report = {"benchmark": "capture", "signals": len(names), "names": names,
              "copy_pairs_ns": pairs, "copy_without_ns": without, "copy_with_ns": with_,
              "capture_cost_ns": cost, "target_ns": TARGET_NS, "rounds": rounds,
              "loop_cost_ns": loop_cost, "records_dropped": lost, "machine": machine_info(),
              "pass": cost <= TARGET_NS and lost == 0}
    write_figures(args.json, report)
    print(f"figures in {args.json}")
    return 1 if args.check and not report["pass"] else 0


if __name__ == "__main__":
    sys.exit(main())
