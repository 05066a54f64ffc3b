"""XCP measurement benchmark: the loop with N signals measured at 2 kHz over XCP
beside the same loop without XCP, in one run.

    python -m rt_loop.tools.xcp_bench [--signals 100] [--pairs 3] [--round-s 20]
                                [--priority 80] [--json out/bench-xcp.json]

Rounds alternate, one loop at a time: the plant server (2 kHz, SCHED_FIFO,
bridge transport, a test TCU peer sending commands, as rt_loop.tools.bench's loop
round) without XCP, then with XCP on UDP loopback and pyxcp as the master
measuring ``--signals`` doubles (plant outputs, inputs and state, in address
order) on the tick event, ``--pairs`` times. Per round: turnaround and
execution p50 / p99.9 / max, the mean execution of the ticks under 20 us,
overruns, DTOs received by the master and lost in the loop's ring. Beside
them, the DAQ copy alone in C (``rt_daq_bench``: the same configuration,
cache warm): ns per tick. The target: the DAQ copy at most 1 us per tick.
Figures to stdout and the JSON file; exit 0 (1 with ``--check`` when the copy
exceeds 1 us or a DTO was lost).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import uuid

from plant import argtypes
from rt_loop.tools.ab_round import drive, idle_loop, loop_figures

TARGET_NS = 1000.0


def measurable_doubles(ffi, n):
    """(name, offset) of the first n doubles of plant outputs, inputs and state."""
    out = []
    for part in ("outputs", "inputs", "state"):
        base = ffi.offsetof("rt_loop", "plant", part)
        ctype = ffi.typeof("dct_plant").fields
        typ = dict(ctype)[part].type

        def walk(t, off, name):
            if t.kind == "primitive" and t.cname == "double":
                out.append((name, off))
            elif t.kind == "struct":
                for fname, f in t.fields:
                    walk(f.type, off + f.offset, f"{name}.{fname}")
            elif t.kind == "array" and t.item.kind in ("primitive", "struct"):
                for i in range(t.length):
                    walk(t.item, off + i * ffi.sizeof(t.item), f"{name}[{i}]")
        walk(typ, base, part)
        if len(out) >= n:
            break
    return out[:n]


def _round(args, with_xcp, signals):
    from can_dbc.peer import CanPeer
    from rt_loop.server import Server

    channel = f"bench-xcp-{uuid.uuid4().hex[:8]}"
    srv = Server(channel, interface="virtual", priority=args.priority, duration_s=args.round_s,
                 xcp="127.0.0.1:0" if with_xcp else None)
    srv.start()
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel,
                        values={"SolenoidCurrent1": 0.4, "SolenoidCurrent2": 0.0})
    received = [0]
    master = None
    try:
        if with_xcp:
            master = _Master(srv, signals, received)
            master.start()
        drive(srv, peer)
    finally:
        if master is not None:
            master.stop()
        peer.close()
        srv.stop()
    x = srv.xcp_counters() if with_xcp else None
    return {
        "xcp": with_xcp,
        "signals": len(signals) if with_xcp else 0,
        **loop_figures(srv.report(histograms=True)),
        "dtos_received": received[0] if with_xcp else None,
        "dtos_lost_in_loop": None if x is None else x["loop"]["dto_ring_dropped"],
    }


class _Master:
    """pyxcp measuring the signals on the tick event, counting the DTO rows."""

    def __init__(self, srv, signals, received):
        from pyxcp.config import create_application_from_config, set_application
        from pyxcp.daq_stim import DaqList, DaqOnlinePolicy

        host, port = srv.xcp.address
        self._app = create_application_from_config(
            {"Transport": {"Eth": {"host": host, "port": port, "protocol": "UDP"}},
             "General": {"disable_error_handling": True}}, log_level=logging.CRITICAL)
        set_application(self._app)

        class Count(DaqOnlinePolicy):
            def initialize(self):
                pass

            def finalize(self):
                pass

            def on_daq_list(self, daq_list, ts0, ts1, payload):
                received[0] += 1

        lists = [DaqList(name="tick", event_num=0, stim=False, enable_timestamps=True,
                         measurements=[(n, off, 0, "F64") for n, off in signals],
                         priority=0, prescaler=1)]
        self.policy = Count(lists)
        self._master = None

    def start(self):
        from pyxcp.master import Master

        self._master = Master("eth", config=self._app, policy=self.policy)
        self._master.__enter__()
        self._master.connect()
        self.policy.setup()
        self.policy.start()

    def stop(self):
        from pyxcp.config import reset_application

        try:
            self.policy.stop()
            self._master.disconnect()
        finally:
            self._master.__exit__(None, None, None)
            reset_application()


def daq_copy_ns(signals, iterations=200_000):
    """rt_daq_bench of one list of these signals on the tick event (a prepared, idle loop)."""
    ffi, lib, loop = idle_loop()
    cfg = loop.daq[1]
    per_odt = int(lib.RT_DAQ_ODT_BYTES) // 8
    odts = [signals[i:i + per_odt] for i in range(0, len(signals), per_odt)]
    cfg.n_lists = 1
    d = cfg.lists[0]
    d.first_odt, d.n_odts, d.event, d.prescaler, d.running = 0, len(odts), 0, 1, 1
    e = 0
    for k, odt in enumerate(odts):
        cfg.odts[k].first_entry, cfg.odts[k].n_entries = e, len(odt)
        for _, off in odt:
            cfg.entries[e].offset, cfg.entries[e].size = off, 8
            e += 1
    loop.daq_gen = 1
    return min(lib.rt_daq_bench(loop, iterations) for _ in range(5)), len(odts)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rt_loop.tools.xcp_bench", description=__doc__.split("\n")[0])
    p.add_argument("--signals", type=argtypes.whole_number(1, 1000), default=100)
    p.add_argument("--pairs", type=argtypes.whole_number(1), default=3)
    p.add_argument("--round-s", type=argtypes.seconds, default=20.0)
    p.add_argument("--priority", type=argtypes.priority, default=80)
    p.add_argument("--json", default="out/bench-xcp.json")
    p.add_argument("--check", action="store_true")
    args = p.parse_args(argv)
    from plant.machine import machine_info, write_figures
    from rt_loop._rt_loop import ffi

    signals = measurable_doubles(ffi, args.signals)
    copy_ns, n_odts = daq_copy_ns(signals)
    print(f"DAQ copy alone (rt_daq_bench, cache warm): {len(signals)} doubles in {n_odts} ODTs: "
          f"{copy_ns:.0f} ns per tick (target {TARGET_NS:.0f} ns)", flush=True)
    rounds = []
    for _ in range(args.pairs):
        for with_xcp in (False, True):
            r = _round(args, with_xcp, signals)
            rounds.append(r)
            ta, ex = r["turnaround"], r["execution"]
            print(f"round {len(rounds):2d} {'XCP ' + str(r['signals']) + ' signals' if with_xcp else 'no XCP':16s}"
                  f" turnaround p50 {ta['p50_us']} p99.9 {ta['p99_9_us']} max {ta['max_us']:.0f} us;"
                  f" execution p50 {ex['p50_us']} p99.9 {ex['p99_9_us']} mean<20us "
                  f"{r['execution_mean_under_20us']:.2f} us; overruns {r['overruns']}"
                  + (f"; DTOs {r['dtos_received']} received, {r['dtos_lost_in_loop']} lost"
                     if with_xcp else ""), flush=True)

    def median(with_xcp, key):
        xs = [r[key] if "." not in key else r[key.split(".")[0]][key.split(".")[1]]
              for r in rounds if r["xcp"] == with_xcp]
        xs = [x for x in xs if x is not None]
        return statistics.median(xs) if xs else None

    summary = {w: {k: median(w, k) for k in ("execution_mean_under_20us", "turnaround.p50_us",
                                              "turnaround.p99_9_us", "execution.p99_9_us",
                                              "overruns")} for w in (False, True)}
    lost = sum(r["dtos_lost_in_loop"] or 0 for r in rounds if r["xcp"])
    print(f"medians without XCP: {summary[False]}")
    print(f"medians with XCP:    {summary[True]}")
    report = {"benchmark": "xcp", "signals": len(signals), "odts": n_odts,
              "daq_copy_ns": copy_ns, "target_ns": TARGET_NS, "rounds": rounds,
              "median": {"without_xcp": summary[False], "with_xcp": summary[True]},
              "dtos_lost_in_loop": lost, "machine": machine_info(),
              "pass": copy_ns <= TARGET_NS and lost == 0}
    write_figures(args.json, report)
    print(f"figures in {args.json}")
    return 1 if args.check and not report["pass"] else 0


if __name__ == "__main__":
    sys.exit(main())
