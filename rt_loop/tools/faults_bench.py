"""Failure simulation benchmark: the loop with 20 faults active beside the same
loop without any, in one run.

    python -m rt_loop.tools.faults_bench [--pairs 3] [--round-s 20] [--priority 80]
                                   [--json out/bench-faults.json] [--check]

Rounds alternate, one loop at a time: the plant server (2 kHz, SCHED_FIFO,
bridge transport, a test TCU peer sending commands, as rt_loop.tools.bench's loop
round) without faults, then with ``FAULTS`` active from the first tick
(20: four CAN faults on sent messages, twelve signal faults on sent and
received signals, four physical faults with values that leave the run as it
was, so both rounds do the same work apart from the faults), ``--pairs``
times. Per round: turnaround and execution p50 / p99.9 / max, the mean
execution of the ticks under 20 us (1 us bins, their middles), overruns and
the faults' hits. The target: at most 0.5 us more mean execution with the
faults (the median of the pairs' differences). Figures to stdout and the JSON
file; exit 0 (1 with ``--check`` when the target is missed).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import uuid

from plant import argtypes
from rt_loop.tools.ab_round import drive, loop_figures

TARGET_US = 0.5

#: 20 faults that change what they touch but not the run's course
FAULTS = [
    {"kind": "can.freeze_counter", "message": "DCT_Clutch"},
    {"kind": "can.bad_crc", "message": "DCT_OutputSpeeds"},
    {"kind": "can.length", "message": "VEH_Driver", "length": 8},
    {"kind": "can.late", "message": "SIM_Status", "delay_ms": 0},
    {"kind": "signal.offset", "signal": "DCT_ShaftSpeeds.EngineSpeed", "offset": 1.0},
    {"kind": "signal.gain", "signal": "DCT_ShaftSpeeds.InputShaft1Speed", "gain": 1.01},
    {"kind": "signal.noise", "signal": "DCT_ShaftSpeeds.InputShaft2Speed", "sigma": 2.0},
    {"kind": "signal.hold", "signal": "DCT_OutputSpeeds.OutputShaft1Speed"},
    {"kind": "signal.value", "signal": "DCT_OutputSpeeds.OutputShaft2Speed", "value": 0.0},
    {"kind": "signal.noise", "signal": "DCT_Clutch.ClutchPressure1", "sigma": 0.01},
    {"kind": "signal.offset", "signal": "DCT_Clutch.ClutchPressure2", "offset": 0.01},
    {"kind": "signal.invalid", "signal": "VEH_Motion.RoadGrade"},
    {"kind": "signal.gain", "signal": "TCU_ClutchCmd.SolenoidCurrent1", "gain": 1.0},
    {"kind": "signal.offset", "signal": "TCU_ClutchCmd.SolenoidCurrent2", "offset": 0.0},
    {"kind": "signal.noise", "signal": "TCU_ShiftCmd.ForkForce1", "sigma": 0.001},
    {"kind": "signal.gain", "signal": "TCU_EngineCmd.EngineTorqueRequest", "gain": 1.0},
    {"kind": "clutch.friction_fade", "clutch": 1, "loss": 0.001},
    {"kind": "clutch.kiss_drift", "clutch": 2, "gap_mm": 0.001},
    {"kind": "hydraulics.line_pressure_loss", "loss": 0.001},
    {"kind": "engine.torque_limit", "max_nm": 1000.0},
]


def _round(args, with_faults):
    from can_dbc.peer import CanPeer
    from rt_loop.server import Server

    channel = f"bench-faults-{uuid.uuid4().hex[:8]}"
    srv = Server(channel, interface="virtual", priority=args.priority, duration_s=args.round_s)
    if with_faults:
        for spec in FAULTS:
            srv.faults.inject(spec)
    srv.start()
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel,
                        values={"SolenoidCurrent1": 0.4, "SolenoidCurrent2": 0.0})
    try:
        drive(srv, peer)
    finally:
        peer.close()
        srv.stop()
    rep = srv.report(histograms=True)
    faults = rep["faults"]["set"]
    return {
        "faults": with_faults,
        "active": sum(1 for f in faults if f["state"] == "active"),
        "hits": sum(f["hits"] for f in faults),
        **loop_figures(rep),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rt_loop.tools.faults_bench",
                                description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=argtypes.whole_number(1), default=3)
    p.add_argument("--round-s", type=argtypes.seconds, default=20.0)
    p.add_argument("--priority", type=argtypes.priority, default=80)
    p.add_argument("--json", default="out/bench-faults.json")
    p.add_argument("--check", action="store_true")
    args = p.parse_args(argv)
    from plant.machine import machine_info, write_figures

    rounds = []
    for _ in range(args.pairs):
        for with_faults in (False, True):
            r = _round(args, with_faults)
            rounds.append(r)
            ta, ex = r["turnaround"], r["execution"]
            print(f"round {len(rounds):2d} {str(r['active']) + ' faults' if with_faults else 'no faults':10s}"
                  f" turnaround p50 {ta['p50_us']} p99.9 {ta['p99_9_us']} max {ta['max_us']:.0f} us;"
                  f" execution p50 {ex['p50_us']} p99.9 {ex['p99_9_us']} mean<20us "
                  f"{r['execution_mean_under_20us']:.2f} us; overruns {r['overruns']}"
                  + (f"; {r['hits']} frames/values changed" if with_faults else ""), flush=True)
    diffs = [b["execution_mean_under_20us"] - a["execution_mean_under_20us"]
             for a, b in zip(rounds[0::2], rounds[1::2])]
    extra = statistics.median(diffs)

    def median(with_faults, key):
        xs = [r[key] if "." not in key else r[key.split(".")[0]][key.split(".")[1]]
              for r in rounds if r["faults"] == with_faults]
        return statistics.median(xs)

    summary = {w: {k: median(w, k) for k in ("execution_mean_under_20us", "turnaround.p50_us",
                                              "turnaround.p99_9_us", "execution.p99_9_us",
                                              "overruns")} for w in (False, True)}
    print(f"medians without faults: {summary[False]}")
    print(f"medians with {len(FAULTS)} faults: {summary[True]}")
    print(f"mean execution with the faults: {extra:+.2f} us (median of the pairs; "
          f"target at most +{TARGET_US} us)")
    active = min(r["active"] for r in rounds if r["faults"])
    report = {"benchmark": "faults", "faults": FAULTS, "rounds": rounds,
              "median": {"without_faults": summary[False], "with_faults": summary[True]},
              "extra_execution_us": extra, "pair_differences_us": diffs, "target_us": TARGET_US,
              "machine": machine_info(),
              "pass": extra <= TARGET_US and active == len(FAULTS)}
    write_figures(args.json, report)
    print(f"figures in {args.json}")
    return 1 if args.check and not report["pass"] else 0


if __name__ == "__main__":
    sys.exit(main())
