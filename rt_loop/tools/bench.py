"""Loop benchmark: the plant loop alone against the machine's wake-up floor alone.

    python -m rt_loop.tools.bench [--rounds 5] [--round-s 20] [--floor c|cyclictest]
                            [--no-pm-qos] [--rate 2000] [--priority 80] [--cpu N]
                            [--json out/bench-loop.json] [--check]
    python -m rt_loop.tools.bench --same-run [--duration 60] ...

Rounds (the default). Rounds of ``--round-s`` seconds alternate, one thing
running at a time: the machine's floor, the loop, the floor, the loop, ...,
the floor, so that every loop round has a floor round just before and just
after it (``--rounds`` loop rounds, 2 x rounds + 1 in all).

* floor round: the C floor loop (``rt_loop.floor.measure_floor``: the loop's
  thread set-up, absolute deadlines at the same period, no work), or with
  ``--floor cyclictest`` rt-tests' cyclictest with its own ``-m`` and its
  own PM QoS request;
* loop round: the plant server (``rt_loop.server.Server``) over the bridge
  transport (python-can's ``virtual`` bus) with a test TCU (``CanPeer``,
  side "tcu") in this process sending its commands (the clutch currents
  swap every second, as in a shift). Nothing else of ours runs beside it.

Both hold ``/dev/cpu_dma_latency`` at 0 us (PM QoS) for their own round
only; ``--no-pm-qos`` makes no request in either (cyclictest gets
``--laptop``), for the A/B of what PM QoS does. What is in force at the
start and end of each round is recorded (another process may hold it).

Neighbouring floor of a loop round: the floor rounds just before and just
after it (only the one before if the run was stopped early). Its p99.9 is
the mean of their p99.9s; its late wake-ups (later than one period) are
their rate per second times the loop round's length.

Targets (benchmark, not tests; ``--check`` exits 1 when one is missed):

* wake-up latency: the loop's wake-up latency p99.9 over the neighbouring
  floor's p99.9 (the round's ratio) at most 1.25, judged on the median
  ratio over the loop rounds (each round's PASS/FAIL is shown);
* turnaround p99.9 at most 35 us, judged in the loop rounds whose
  neighbouring floor rounds all have a p99.9 under 100 us; rounds beside a
  noisier floor are shown but not judged (and the table says so). No such
  round: the target is not judged (neither PASS nor FAIL);
* overruns: the loop rounds' overruns at most the neighbouring floors' late
  wake-ups, summed over the loop rounds.

Same run (``--same-run``, the old method, an extra): the loop and cyclictest
at the same period and priority for ``--duration`` seconds at the same time.
Each affects the other (cyclictest's PM QoS request helps the loop; the
loop's spin and bridge thread delay cyclictest), which the output and the
JSON say. Targets there: turnaround p99.9 <= 35 us, the loop's wake-up
latency p99.9 <= 1.25 x cyclictest's, overruns <= cyclictest's wake-ups
later than one period minus the loop's median turnaround.

Percentiles come from 1 us histograms (``rt_loop.stats.hist_percentiles``:
the upper edge of the bin of the nearest-rank sample). One progress line per
round goes to stderr; the table to stdout; the JSON file (every round with
its histograms, the config, the machine, the targets) is rewritten after
every round. Each loop round's report has the bench process's memory (VmRSS,
VmLck at the first tick, VmHWM: ``memory``) and its start-to-first-tick
(``run``); after the rounds, ``serve_process``: the same figures of a plain
``dct-hil serve`` run for 2 s in a process of its own (written, not judged). Ctrl-C (or SIGTERM) stops the round in progress, keeps what it
measured and writes everything (exit 130, after SIGTERM 143; a second one
aborts at once).
Exit 0, or 1 with ``--check`` and a missed target; bad options or a missing
cyclictest: one line, exit 2.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time

from plant import argtypes
from plant.machine import write_figures
from plant.stop_signals import StopSignals

TURNAROUND_P99_9_TARGET_US = 35.0
LATENCY_RATIO_TARGET = 1.25
#: a loop round's turnaround is judged only when its neighbouring floors' p99.9 are below this
QUIET_FLOOR_P99_9_US = 100.0
DEFAULT_ROUNDS = 5
DEFAULT_ROUND_S = 20
DEFAULT_SAME_RUN_S = 60
DEFAULT_JSON = os.path.join("out", "bench-loop.json")
FLOOR_TOOLS = ("c", "cyclictest")
#: the TCU's commands during a loop round; the clutch currents swap every SHIFT_S
SHIFT_S = 1.0
CLUTCH_CURRENT_A = 0.6
LINE_CURRENT_A = 0.3

SAME_RUN_NOTE = "loop and cyclictest in the same run: each affects the other"
NEIGHBOUR_RULE = ("neighbouring floor of a loop round: the floor rounds just before and just "
                  "after it (the one before only if the run stopped early); p99.9: the mean of "
                  "theirs; late wake-ups: their rate per second x the loop round's length")
CYCLICTEST_MISSING = ("cyclictest not found: install rt-tests (apt-get install rt-tests), "
                      "or run scripts/bench-loop, which does")


class BenchError(Exception):
    """Bad option or environment: one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise BenchError(message)




def build_parser():
    p = _Parser(prog="python -m rt_loop.tools.bench",
                description="Benchmark the real-time loop (bridge transport, TCU peer, SCHED_FIFO) "
                            "in rounds alternating with the machine's wake-up floor, one at a "
                            "time.")
    p.add_argument("--rounds", type=argtypes.whole_number(1, 1000), default=None, metavar="N",
                   help=f"loop rounds, each between two floor rounds (default {DEFAULT_ROUNDS})")
    p.add_argument("--round-s", type=argtypes.whole_number(1, 86_400), default=None, metavar="S",
                   help=f"seconds per round, floor and loop alike (default {DEFAULT_ROUND_S})")
    p.add_argument("--floor", choices=FLOOR_TOOLS, default=None,
                   help="what measures the floor: c (the C floor loop, rt_loop.floor; default) "
                        "or cyclictest (alone, with its own -m and PM QoS request)")
    p.add_argument("--same-run", action="store_true",
                   help=f"the old method instead of rounds: {SAME_RUN_NOTE}")
    p.add_argument("--duration", type=argtypes.whole_number(1, 86_400), default=None, metavar="S",
                   help=f"--same-run only: seconds to run (default {DEFAULT_SAME_RUN_S})")
    p.add_argument("--no-pm-qos", action="store_true",
                   help="make no PM QoS request (/dev/cpu_dma_latency) in the floor, the loop "
                        "or cyclictest (--laptop): the B of an A/B")
    p.add_argument("--rate", type=argtypes.whole_number(100, 20_000), default=2000, metavar="HZ",
                   help="loop and floor rate (default 2000: 500 us period)")
    p.add_argument("--priority", type=argtypes.whole_number(0, 99), default=80, metavar="0..99",
                   help="SCHED_FIFO priority of the loop, the floor and cyclictest (default 80; "
                        "0: normal scheduling, not real time)")
    p.add_argument("--cpu", type=argtypes.whole_number(0, 4095), metavar="N",
                   help="pin the loop and the floor to CPU N (in --same-run cyclictest is left "
                        "unpinned)")
    p.add_argument("--channel", default="dct-hil-bench", metavar="NAME",
                   help="python-can virtual channel shared by the server and the peer")
    p.add_argument("--hist-max-us", type=argtypes.whole_number(100, 100_000), default=10_000, metavar="US",
                   help="cyclictest histogram range (default 10000 us; above it: overflows)")
    p.add_argument("--json", default=DEFAULT_JSON, metavar="FILE",
                   help=f"where to write the figures (default {DEFAULT_JSON})")
    p.add_argument("--spin-us", type=argtypes.microseconds, default=None, metavar="US",
                   help="early wake-up busy-waited before each deadline (default: the server's)")
    p.add_argument("--check", action="store_true", help="exit 1 if a target is missed")
    return p


def parse_args(argv=None):
    """Options with the defaults of the chosen mode; BenchError on a bad combination."""
    args = build_parser().parse_args(argv)
    if args.same_run:
        given = [name for name, value in (("--rounds", args.rounds), ("--round-s", args.round_s),
                                          ("--floor", args.floor)) if value is not None]
        if given:
            raise BenchError(f"{', '.join(given)}: not with --same-run (it takes --duration)")
        args.duration = DEFAULT_SAME_RUN_S if args.duration is None else args.duration
    else:
        if args.duration is not None:
            raise BenchError("--duration goes with --same-run; the rounds take --rounds and "
                             "--round-s")
        args.rounds = DEFAULT_ROUNDS if args.rounds is None else args.rounds
        args.round_s = DEFAULT_ROUND_S if args.round_s is None else args.round_s
        args.floor = "c" if args.floor is None else args.floor
    uses_cyclictest = args.same_run or args.floor == "cyclictest"
    if uses_cyclictest and 1_000_000 % args.rate:
        raise BenchError(f"--rate {args.rate}: cyclictest needs a period of whole microseconds "
                         "(e.g. 1000, 2000, 4000, 5000 Hz)")
    return args


# --------------------------------------------------------------------------
# rounds: schedule and judgement (pure functions of the figures)
# --------------------------------------------------------------------------

def schedule(rounds):
    """The kinds of the rounds in order: floor, loop, floor, ..., loop, floor."""
    if rounds < 1:
        raise ValueError(f"at least one loop round, got {rounds}")
    return ["floor"] + ["loop", "floor"] * rounds


def _floor_p999(rec):
    fig = rec.get("floor")
    return None if not fig else fig.get("p99_9_us")


def _loop_fig(rec, *keys):
    d = rec.get("loop")
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def neighbour_floors(rounds, i):
    """The floor rounds (records with figures) just before and just after rounds[i]."""
    out = []
    for j in (i - 1, i + 1):
        if (0 <= j < len(rounds) and rounds[j]["kind"] == "floor"
                and _floor_p999(rounds[j]) is not None):
            out.append(rounds[j])
    return out


def judge_loop_round(rounds, i):
    """The judgement of loop round rounds[i] against its neighbouring floors."""
    rec = rounds[i]
    floors = neighbour_floors(rounds, i)
    wake = _loop_fig(rec, "wakeup_latency", "p99_9_us")
    turn = _loop_fig(rec, "turnaround", "p99_9_us")
    overruns = _loop_fig(rec, "counts", "overruns")
    j = {"round": rec["index"], "neighbour_rounds": [f["index"] for f in floors],
         "neighbour_floor_p99_9_us": None, "neighbour_floor_p99_9_max_us": None,
         "wakeup_p99_9_us": wake, "ratio": None, "ratio_pass": None,
         "turnaround_p99_9_us": turn, "turnaround_judged": False, "turnaround_pass": None,
         "turnaround_not_judged_because": None,
         "overruns": overruns, "allowed_overruns": None, "overruns_pass": None}
    if not floors:
        j["turnaround_not_judged_because"] = "no floor round beside it"
        return j
    p999 = [_floor_p999(f) for f in floors]
    j["neighbour_floor_p99_9_us"] = sum(p999) / len(p999)
    j["neighbour_floor_p99_9_max_us"] = max(p999)
    if wake is not None and j["neighbour_floor_p99_9_us"] > 0:
        j["ratio"] = wake / j["neighbour_floor_p99_9_us"]
        j["ratio_pass"] = j["ratio"] <= LATENCY_RATIO_TARGET
    if turn is None:
        j["turnaround_not_judged_because"] = "no ticks"
    elif max(p999) >= QUIET_FLOOR_P99_9_US:
        j["turnaround_not_judged_because"] = (f"a neighbouring floor's p99.9 is {max(p999):g} us "
                                              f"(not under {QUIET_FLOOR_P99_9_US:g} us)")
    else:
        j["turnaround_judged"] = True
        j["turnaround_pass"] = turn <= TURNAROUND_P99_9_TARGET_US
    floor_s = sum(float(f.get("duration_s") or 0.0) for f in floors)
    late = sum(int(f["floor"].get("late_wakeups") or 0) for f in floors)
    if floor_s > 0 and overruns is not None:
        j["allowed_overruns"] = late / floor_s * float(rec.get("duration_s") or 0.0)
        j["overruns_pass"] = overruns <= j["allowed_overruns"] + 1e-9
    return j


def _target(name, status, value, limit, unit, **extra):
    return {"target": name, "status": status, "pass": {"PASS": True, "FAIL": False}.get(status),
            "value": value, "limit": limit, "unit": unit, **extra}


def evaluate(rounds):
    """Judgements of the loop rounds, the median ratio and the three targets.

    ``rounds``: records {"index", "kind": "floor"|"loop", "duration_s",
    "floor": {"p99_9_us", "late_wakeups", ...} or "loop": {"wakeup_latency":
    {"p99_9_us"}, "turnaround": {"p99_9_us"}, "counts": {"overruns"}}}, the
    figures None for a round that measured nothing. A target is "PASS",
    "FAIL" or "NOT JUDGED" (nothing to judge it on); ``pass`` is False when
    one is "FAIL".
    """
    judgements = [judge_loop_round(rounds, i) for i, r in enumerate(rounds)
                  if r["kind"] == "loop" and r.get("loop")]
    ratios = [j["ratio"] for j in judgements if j["ratio"] is not None]
    median_ratio = statistics.median(ratios) if ratios else None

    if median_ratio is None:
        t_ratio = _target(f"wake-up latency p99.9 <= {LATENCY_RATIO_TARGET:g} x the neighbouring "
                          "floor's (median ratio over the loop rounds)", "NOT JUDGED", None,
                          LATENCY_RATIO_TARGET, "x", rounds=[])
    else:
        t_ratio = _target(f"wake-up latency p99.9 <= {LATENCY_RATIO_TARGET:g} x the neighbouring "
                          "floor's (median ratio over the loop rounds)",
                          "PASS" if median_ratio <= LATENCY_RATIO_TARGET else "FAIL",
                          median_ratio, LATENCY_RATIO_TARGET, "x",
                          rounds=[j["round"] for j in judgements if j["ratio"] is not None])

    judged = [j for j in judgements if j["turnaround_judged"]]
    not_judged = [j["round"] for j in judgements if not j["turnaround_judged"]]
    name = (f"turnaround p99.9 <= {TURNAROUND_P99_9_TARGET_US:g} us in rounds whose neighbouring "
            f"floors' p99.9 < {QUIET_FLOOR_P99_9_US:g} us")
    if judged:
        worst = max(j["turnaround_p99_9_us"] for j in judged)
        t_turn = _target(name, "PASS" if all(j["turnaround_pass"] for j in judged) else "FAIL",
                         worst, TURNAROUND_P99_9_TARGET_US, "us",
                         rounds=[j["round"] for j in judged], rounds_not_judged=not_judged)
    else:
        t_turn = _target(name, "NOT JUDGED", None, TURNAROUND_P99_9_TARGET_US, "us", rounds=[],
                         rounds_not_judged=not_judged)

    counted = [j for j in judgements if j["overruns_pass"] is not None]
    name = "overruns <= the neighbouring floors' wake-ups later than a period (summed)"
    if counted:
        total = sum(j["overruns"] for j in counted)
        allowed = sum(j["allowed_overruns"] for j in counted)
        t_over = _target(name, "PASS" if total <= allowed + 1e-9 else "FAIL", total, allowed, "",
                         rounds=[j["round"] for j in counted])
    else:
        t_over = _target(name, "NOT JUDGED", None, None, "", rounds=[])

    targets = [t_ratio, t_turn, t_over]
    return {"judgements": judgements, "median_ratio": median_ratio, "ratios": ratios,
            "targets": targets, "pass": all(t["status"] != "FAIL" for t in targets)}


# --------------------------------------------------------------------------
# cyclictest
# --------------------------------------------------------------------------

def cyclictest_command(exe, priority, period_us, duration_s, hist_max_us, pm_qos=True, cpu=None):
    """cyclictest, one thread; ``pm_qos`` False adds --laptop (no /dev/cpu_dma_latency request)."""
    cmd = [exe, "-m", "-p", str(priority), "-i", str(period_us), "-t", "1",
           "-D", f"{duration_s}s", "-q", "-h", str(hist_max_us)]
    if cpu is not None:
        cmd += ["-a", str(cpu)]
    if not pm_qos:
        cmd.append("--laptop")
    return cmd


def parse_cyclictest(text, hist_max_us):
    """Histogram and summary of ``cyclictest -q -h N`` output (one thread).

    Returns {"hist": list of N+1 counts (1 us bins; the last holds the
    overflows, i.e. everything from N us up), "samples", "min_us", "avg_us",
    "max_us", "overflows", "pm_qos_set_us"}. Raises BenchError if there is
    no histogram.
    """
    hist = [0] * (hist_max_us + 1)
    summary = {}
    pm_qos_set = None
    seen = False
    for raw in text.splitlines():
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            if "cpu_dma_latency set to" in line:
                digits = "".join(ch for ch in line.rsplit(" ", 1)[-1] if ch.isdigit())
                pm_qos_set = int(digits) if digits else None
            key, sep, value = line[1:].partition(":")
            if sep:
                summary[key.strip()] = value.strip()
            continue
        parts = line.split()
        try:
            values = [int(x) for x in parts]
        except ValueError:
            continue
        if len(values) < 2:
            continue
        b = values[0]
        if 0 <= b < hist_max_us:
            hist[b] += sum(values[1:])
            seen = True
    if not seen:
        raise BenchError("cyclictest printed no histogram (its output: "
                         + " ".join(text.split())[:200] + ")")

    def number(key):
        text_value = summary.get(key, "")
        first = text_value.split()[0] if text_value.split() else ""
        try:
            return int(first)
        except ValueError:
            return None

    overflows = number("Histogram Overflows") or 0
    hist[hist_max_us] = overflows
    max_us = number("Max Latencies")
    samples = sum(hist)
    if max_us is None:  # fall back on the histogram
        nz = [i for i, c in enumerate(hist) if c]
        max_us = nz[-1] if nz else None
    return {"hist": hist, "samples": samples, "min_us": number("Min Latencies"),
            "avg_us": number("Avg Latencies"), "max_us": max_us, "overflows": overflows,
            "total_reported": number("Total"), "pm_qos_set_us": pm_qos_set}


def late_count(hist, threshold_us):
    """Samples of a 1 us histogram (values truncated to whole us) later than threshold_us."""
    first = max(0, int(math.floor(threshold_us)) + 1)
    return int(sum(hist[first:]))


class Cyclictest:
    """cyclictest in its own session; ``interrupt()`` ends it early, ``result()`` waits
    and parses."""

    def __init__(self, priority, period_us, duration_s, hist_max_us, pm_qos=True, cpu=None):
        exe = shutil.which("cyclictest")
        if exe is None:
            raise BenchError(CYCLICTEST_MISSING)
        self.hist_max_us = hist_max_us
        self.duration_s = duration_s
        self.command = cyclictest_command(exe, priority, period_us, duration_s, hist_max_us,
                                          pm_qos=pm_qos, cpu=cpu)
        self.interrupted = False
        self.proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True)

    def interrupt(self):
        """SIGINT: cyclictest stops and prints what it measured."""
        if self.proc.poll() is None:
            self.interrupted = True
            try:
                os.killpg(self.proc.pid, signal.SIGINT)
            except OSError:
                pass

    def result(self, stop=None):
        """Waits for cyclictest, reading its output as it comes (its histogram is
        larger than a pipe holds), and parses it; ``stop`` set: interrupt it first."""
        limit = time.monotonic() + self.duration_s + 60
        while True:
            try:
                out, err = self.proc.communicate(timeout=0.1)
                break
            except subprocess.TimeoutExpired:
                if stop is not None and stop.is_set() and not self.interrupted:
                    self.interrupt()
                if time.monotonic() > limit:
                    self.kill()
                    raise BenchError(f"cyclictest did not finish within "
                                     f"{self.duration_s + 60} s") from None
        if self.proc.returncode != 0 and not self.interrupted:
            first = next((ln.strip() for ln in (err + out).splitlines() if ln.strip()), "")
            raise BenchError(f"cyclictest failed (exit {self.proc.returncode}): "
                             f"{first or 'no output'}"
                             + ("; SCHED_FIFO needs root or CAP_SYS_NICE" if "priority" in err
                                or "scheduling" in err else ""))
        return parse_cyclictest(out, self.hist_max_us)

    def kill(self):
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except OSError:
                pass
            self.proc.wait()


# --------------------------------------------------------------------------
# measuring: one floor round, one loop round
# --------------------------------------------------------------------------

def _commands(t_s):
    """The TCU's commands at t_s: a shift from K1 to K2 and back every SHIFT_S."""
    on_k1 = int(t_s / SHIFT_S) % 2 == 0
    return {"SolenoidCurrent1": CLUTCH_CURRENT_A if on_k1 else 0.0,
            "SolenoidCurrent2": 0.0 if on_k1 else CLUTCH_CURRENT_A,
            "LineSolenoidCurrent": LINE_CURRENT_A}


def _pm_qos_us(args):
    return None if args.no_pm_qos else 0


def measure_floor_round(args, stop):
    """One floor round alone: figures with the keys of ``rt_loop.floor.measure_floor``."""
    if args.floor == "cyclictest":
        return _cyclictest_floor(args, stop)
    from rt_loop.floor import FloorError, measure_floor

    try:
        fig = measure_floor(duration_s=args.round_s, rate_hz=args.rate, priority=args.priority,
                            cpu=args.cpu, pm_qos_us=_pm_qos_us(args), stop=stop)
    except FloorError as e:
        raise BenchError(str(e)) from None
    fig["tool"] = "C floor loop (rt_loop.floor)"
    return fig


def _cyclictest_floor(args, stop):
    import numpy as np

    from rt_loop.stats import hist_percentiles, sparse_hist

    period_us = 1_000_000 // args.rate
    ct = Cyclictest(args.priority, period_us, args.round_s, args.hist_max_us,
                    pm_qos=not args.no_pm_qos, cpu=args.cpu)
    try:
        fig = ct.result(stop)
    finally:
        ct.kill()
    hist = np.asarray(fig["hist"], dtype=np.uint64)
    if fig["samples"] == 0:
        pct = hist_percentiles(hist, 0.0)
    else:
        # cyclictest truncates to whole us: bin i holds [i, i+1), as the floor loop's
        pct = hist_percentiles(hist, float(fig["max_us"]) + 1.0)
        pct["max_us"] = float(fig["max_us"])
    return {
        **pct,
        "mean_us": None if fig["avg_us"] is None else float(fig["avg_us"]),
        # bins from the period up: wake-ups at least one period late (whole us)
        "late_wakeups": int(sum(fig["hist"][period_us:])),
        "late_threshold_us": float(period_us),
        "skipped": None,
        "overflows": fig["overflows"],
        "hist_max_us": args.hist_max_us,
        "pm_qos": {"requested_us": _pm_qos_us(args), "held": fig["pm_qos_set_us"] is not None,
                   "error": None, "path": "/dev/cpu_dma_latency (cyclictest's own)"},
        "tool": "cyclictest",
        "command": " ".join(ct.command),
        "config": {"duration_s": float(args.round_s), "rate_hz": float(args.rate),
                   "period_us": float(period_us), "priority": args.priority, "cpu": args.cpu},
        "hist": sparse_hist(hist),
    }


def _new_server(args, duration_s):
    from rt_loop.server import Server, ServerError
    from rt_loop.transport import TransportError

    try:
        return Server(args.channel, interface="virtual", rate_hz=args.rate,
                      priority=args.priority, cpu=args.cpu, duration_s=duration_s,
                      spin_us=args.spin_us, pm_qos_us=_pm_qos_us(args))
    except (ServerError, TransportError, ValueError) as e:
        raise BenchError(str(e)) from None


def measure_loop_round(args, stop, progress, duration_s=None, beside=None):
    """One loop round: the server's report (histograms included) and the peer's, or
    (None, None) when stopped before the loop ran. ``beside()``, if given, is called
    once the loop runs and the peer sends (the same-run mode starts cyclictest there)."""
    from can_dbc.peer import CanPeer
    from rt_loop.server import ServerError

    server = _new_server(args, args.round_s if duration_s is None else duration_s)
    peer = None
    try:
        try:
            server.start(progress=lambda line: _note(progress, line), cancel=stop)
        except ServerError as e:
            if stop.is_set():
                return None, None
            raise BenchError(str(e)) from None
        peer = CanPeer.open(side="tcu", interface="virtual", channel=args.channel,
                            values=_commands(0.0))
        if beside is not None:
            beside()
        t0 = time.monotonic()
        while server.running and not stop.is_set():
            peer.set(**_commands(time.monotonic() - t0))
            server.wait(0.05)
    finally:
        if peer is not None:
            peer.close()
        try:
            server.stop()
        except ServerError as e:
            _note(progress, str(e))
    rep = server.report(histograms=True)
    rep.pop("machine", None)
    return rep, (peer.report() if peer is not None else None)


def measure_serve_process(seconds=2.0):
    """A plain ``dct-hil serve`` (the contract, no options but a short duration, quiet, its
    stats in a temporary file) in a process of its own: its memory (VmRSS and VmLck at
    the first tick, VmHWM) and its start-to-first-tick times from its stats; written,
    not judged (issue 26: at most 150 MB resident is a test, tests/test_lean_server.py).
    None for each figure it could not get, with the reason."""
    import json
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        stats = os.path.join(tmp, "stats.json")
        argv = [sys.executable, "-m", "dct_hil.cli", "serve", "--duration", f"{seconds:g}",
                "--quiet", "--stats", stats]
        try:
            r = subprocess.run(argv, capture_output=True, text=True, timeout=600, cwd=tmp)
            rep = json.loads(open(stats, encoding="utf-8").read())
        except (OSError, ValueError, subprocess.TimeoutExpired) as e:
            return {"command": "dct-hil serve", "error": str(e).splitlines()[0] if str(e)
                    else type(e).__name__}
    run = rep.get("run", {})
    return {"command": f"dct-hil serve --duration {seconds:g} --quiet --stats FILE",
            "exit_status": r.returncode, "memory": rep.get("memory"),
            "memory_locked": rep.get("config", {}).get("memory_locked"),
            "start_to_first_tick_s": run.get("start_to_first_tick_s"),
            "process_to_first_tick_s": run.get("process_to_first_tick_s")}


def _note(progress, line):
    print(f"rt_loop.tools.bench: {line}", file=progress, flush=True)


# --------------------------------------------------------------------------
# the rounds
# --------------------------------------------------------------------------

def _in_force_us():
    from rt_loop.pm_qos import current_latency_us

    return current_latency_us()


def run_rounds(args, progress=sys.stderr, stop=None, write=None):
    """Floor, loop, floor, ...: returns the report; ``write(report)`` after every round."""
    stop = stop or threading.Event()
    if args.floor == "cyclictest" and shutil.which("cyclictest") is None:
        raise BenchError(CYCLICTEST_MISSING)
    probe = _new_server(args, args.round_s)   # every option the server checks, before round 1
    spin_us = probe.spin_us
    del probe
    kinds = schedule(args.rounds)
    report = {
        "benchmark": "loop",
        "mode": "rounds",
        "method": (f"rounds of {args.round_s} s, one thing at a time: floor, loop, floor, ..., "
                   "floor; each loop round judged against its neighbouring floor rounds"),
        "config": {
            "rounds": args.rounds,
            "round_s": args.round_s,
            "schedule": kinds,
            "rate_hz": args.rate,
            "period_us": 1e6 / args.rate,
            "priority": args.priority,
            "spin_us": spin_us,
            "cpu": args.cpu,
            "floor": ("cyclictest (alone, -m, its own PM QoS request)" if args.floor == "cyclictest"
                      else "C floor loop (rt_loop.floor.measure_floor)"),
            "pm_qos_us": _pm_qos_us(args),
            "pm_qos": ("/dev/cpu_dma_latency held at 0 us by the floor and by the loop, each "
                       "in its own round" if not args.no_pm_qos else
                       "no request (--no-pm-qos; cyclictest --laptop)"),
            "transport": "bridge (python-can virtual)",
            "channel": args.channel,
            "peer": "CanPeer side tcu in the same process",
            "tcu_commands": f"SolenoidCurrent1/2 swap between 0 and {CLUTCH_CURRENT_A} A every "
                            f"{SHIFT_S:g} s, LineSolenoidCurrent {LINE_CURRENT_A} A",
            "neighbouring_floor": NEIGHBOUR_RULE,
        },
        "target_limits": {
            "wakeup_ratio_max": LATENCY_RATIO_TARGET,
            "turnaround_p99_9_max_us": TURNAROUND_P99_9_TARGET_US,
            "quiet_floor_p99_9_below_us": QUIET_FLOOR_P99_9_US,
            "overruns": "<= the neighbouring floors' wake-ups later than a period",
        },
        "targets": [],
        "pass": None,
        "summary": {},
        "complete": False,
        "interrupted": False,
        "machine": _machine(),
        "rounds": [],
    }
    _note(progress, f"{len(kinds)} rounds of {args.round_s} s ({args.rounds} loop rounds, each "
                    f"between two floor rounds) at {args.rate} Hz; floor: "
                    + ("cyclictest" if args.floor == "cyclictest" else "the C floor loop")
                    + "; PM QoS: " + ("none" if args.no_pm_qos else "0 us") + "; about "
                    f"{len(kinds) * args.round_s} s")
    t_start = time.monotonic()
    for i, kind in enumerate(kinds, start=1):
        if stop.is_set():
            break
        rec = {"index": i, "kind": kind, "started_s": time.monotonic() - t_start,
               "pm_qos_in_force_us": {"start": _in_force_us()}}
        t0 = time.monotonic()
        if kind == "floor":
            rec["floor"] = measure_floor_round(args, stop)
        else:
            rec["loop"], rec["peer"] = measure_loop_round(args, stop, progress)
        rec["duration_s"] = _round_seconds(rec, time.monotonic() - t0)
        rec["pm_qos_in_force_us"]["end"] = _in_force_us()
        rec["partial"] = stop.is_set()
        report["rounds"].append(rec)
        _refresh(report)
        print(progress_line(report, rec, len(kinds)), file=progress, flush=True)
        if write is not None:
            write(report)
    if not stop.is_set():
        # a plain serve's memory and start-up, after the rounds (nothing beside them)
        report["serve_process"] = measure_serve_process()
        if write is not None:
            write(report)
    report["interrupted"] = stop.is_set()
    report["complete"] = not report["interrupted"]
    report["machine"]["load_average_end"] = _load_average()
    return report


def _round_seconds(rec, wall_s):
    """The round's measured length: the loop's own wall time, else the floor's samples x period."""
    if rec.get("loop"):
        return float(rec["loop"]["run"]["wall_s"])
    fig = rec.get("floor")
    if fig and fig.get("samples"):
        skipped = fig.get("skipped") or 0
        return (fig["samples"] + skipped) * fig["config"]["period_us"] * 1e-6
    return wall_s if fig else 0.0


def _refresh(report):
    ev = evaluate(report["rounds"])
    by_round = {j["round"]: j for j in ev["judgements"]}
    for rec in report["rounds"]:
        if rec["kind"] == "loop":
            rec["judgement"] = by_round.get(rec["index"])
    report["summary"] = {
        "median_ratio": ev["median_ratio"],
        "ratios": ev["ratios"],
        "loop_rounds": sum(1 for r in report["rounds"] if r["kind"] == "loop" and r.get("loop")),
        "floor_rounds": sum(1 for r in report["rounds"] if r["kind"] == "floor" and r.get("floor")),
        "warnings": round_warnings(report),
    }
    report["targets"] = ev["targets"]
    report["pass"] = ev["pass"]


def round_warnings(report):
    """What makes the figures less than they claim: refused rights, PM QoS not as asked."""
    out = []
    want_qos = report["config"]["pm_qos_us"] is not None
    for rec in report["rounds"]:
        fig = rec.get("floor") or rec.get("loop")
        if not fig:
            continue
        name = f"round {rec['index']} ({rec['kind']})"
        if rec["kind"] == "floor":
            if report["config"]["priority"] and fig.get("rt_policy_ok") is False:
                out.append(f"{name}: SCHED_FIFO refused")
            held = (fig.get("pm_qos") or {}).get("held")
        else:
            for w in fig["run"].get("warnings") or []:
                out.append(f"{name}: {w}")
            held = ((fig["config"].get("pm_qos")) or {}).get("held")
        if want_qos and not held:
            out.append(f"{name}: PM QoS request not held")
        in_force = [v for v in (rec.get("pm_qos_in_force_us") or {}).values() if v is not None]
        from rt_loop.pm_qos import NO_CONSTRAINT_US

        if not want_qos and any(v < NO_CONSTRAINT_US for v in in_force):
            out.append(f"{name}: another process held PM QoS at {min(in_force)} us (this run "
                       "is not one without PM QoS)")
    return out


# --------------------------------------------------------------------------
# same run (the old method)
# --------------------------------------------------------------------------

def run_same_run(args, progress=sys.stderr, stop=None):
    """The loop and cyclictest at the same time; returns the report."""
    import numpy as np

    from rt_loop.stats import hist_percentiles

    stop = stop or threading.Event()
    period_us = 1_000_000 // args.rate
    if shutil.which("cyclictest") is None:
        raise BenchError(CYCLICTEST_MISSING)
    machine = _machine()
    _note(progress, f"{SAME_RUN_NOTE}: {args.duration} s at {args.rate} Hz (figures at the end)")
    ct = None

    def start_cyclictest():
        nonlocal ct
        ct = Cyclictest(args.priority, period_us, args.duration, args.hist_max_us,
                        pm_qos=not args.no_pm_qos)

    try:
        loop, peer_rep = measure_loop_round(args, stop, progress, duration_s=args.duration,
                                            beside=start_cyclictest)
    except BaseException:
        if ct is not None:
            ct.kill()
        raise
    if ct is None:
        raise BenchError("stopped before the loop ran: nothing measured")
    try:
        ct_fig = ct.result(stop)
    finally:
        ct.kill()

    counts = loop["counts"]
    turn, lat = loop["turnaround"], loop["wakeup_latency"]
    ct_hist = np.asarray(ct_fig["hist"], dtype=np.uint64)
    ct_pct = hist_percentiles(ct_hist, float(ct_fig["max_us"]) + 1.0 if ct_fig["max_us"] is not None
                              else 0.0)
    ct_pct["max_us"] = ct_fig["max_us"]
    threshold_us = period_us - (turn["p50_us"] or 0.0)
    ct_late = late_count(ct_fig["hist"], threshold_us)

    def target(name, value, limit, unit):
        ok = value is not None and limit is not None and value <= limit
        return _target(name, "PASS" if ok else "FAIL", value, limit, unit)

    ct_p999 = ct_pct["p99_9_us"]
    targets = [
        target(f"turnaround p99.9 <= {TURNAROUND_P99_9_TARGET_US:g} us", turn["p99_9_us"],
               TURNAROUND_P99_9_TARGET_US, "us"),
        target(f"wake-up latency p99.9 <= {LATENCY_RATIO_TARGET:g} x cyclictest's (same run)",
               lat["p99_9_us"], None if ct_p999 is None else LATENCY_RATIO_TARGET * ct_p999, "us"),
        target(f"overruns <= cyclictest's wake-ups > {threshold_us:.0f} us (same run)",
               counts["overruns"], ct_late, ""),
    ]
    machine["load_average_end"] = _load_average()
    return {
        "benchmark": "loop",
        "mode": "same-run",
        "note": SAME_RUN_NOTE,
        "config": {
            "duration_s": args.duration,
            "rate_hz": args.rate,
            "period_us": period_us,
            "priority": args.priority,
            "spin_us": loop["config"]["spin_us"],
            "cpu": args.cpu,
            "pm_qos_us": _pm_qos_us(args),
            "transport": "bridge (python-can virtual)",
            "channel": args.channel,
            "peer": "CanPeer side tcu in the same process",
            "tcu_commands": f"SolenoidCurrent1/2 swap between 0 and {CLUTCH_CURRENT_A} A every "
                            f"{SHIFT_S:g} s, LineSolenoidCurrent {LINE_CURRENT_A} A",
        },
        "targets": targets,
        "pass": all(t["pass"] for t in targets),
        "complete": not stop.is_set(),
        "interrupted": stop.is_set(),
        "loop": loop,
        "cyclictest": {
            "command": " ".join(ct.command),
            "samples": ct_fig["samples"],
            "min_us": ct_fig["min_us"],
            "avg_us": ct_fig["avg_us"],
            **{k: v for k, v in ct_pct.items() if k != "samples"},
            "overflows": ct_fig["overflows"],
            "hist_max_us": args.hist_max_us,
            "pm_qos_set_us": ct_fig["pm_qos_set_us"],
            "late_threshold_us": threshold_us,
            "late_count": ct_late,
            "histogram": [[i, int(c)] for i, c in enumerate(ct_fig["hist"]) if c],
        },
        "peer": peer_rep,
        "machine": machine,
    }


# --------------------------------------------------------------------------
# the machine
# --------------------------------------------------------------------------

def _read(path):
    try:
        with open(path, encoding="ascii") as f:
            return f.read().strip()
    except OSError:
        return None


def _load_average():
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _machine():
    from plant.machine import machine_info

    info = machine_info(build=True)      # with the git commit (and the compiler)
    info["load_average_start"] = _load_average()
    info["rt_runtime_us"] = _read("/proc/sys/kernel/sched_rt_runtime_us")
    info["rt_period_us"] = _read("/proc/sys/kernel/sched_rt_period_us")
    info["cpufreq_governor"] = _read("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor")
    info["cpuidle_driver"] = _read("/sys/devices/system/cpu/cpuidle/current_driver")
    info["pm_qos_in_force_us_start"] = _in_force_us()
    info["euid"] = os.geteuid()
    return info


# --------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------

def _us(x, width=0):
    return f"{'-' if x is None else f'{x:.1f}':>{width}}"


def _verdict(ok):
    return "-" if ok is None else ("PASS" if ok else "FAIL")


def progress_line(report, rec, total):
    """One line for a finished round."""
    head = f"  round {rec['index']:>2}/{total} {rec['kind']:<5} {rec['duration_s']:5.1f} s"
    tail = " (stopped early)" if rec.get("partial") else ""
    if rec["kind"] == "floor":
        f = rec.get("floor")
        if not f or not f.get("samples"):
            return head + "  nothing measured" + tail
        line = (f"{head}  wake-up p50 {_us(f['p50_us'])} p99.9 {_us(f['p99_9_us'])} max "
                f"{_us(f['max_us'])} us, late {f['late_wakeups']}")
        prev = report["rounds"][-2] if len(report["rounds"]) >= 2 else None
        j = (prev or {}).get("judgement")
        if j and j["ratio"] is not None:
            line += f"  | round {j['round']} ratio {j['ratio']:.2f} {_verdict(j['ratio_pass'])}"
        return line + tail
    loop = rec.get("loop")
    if not loop:
        return head + "  nothing measured" + tail
    lat, turn, c = loop["wakeup_latency"], loop["turnaround"], loop["counts"]
    return (f"{head}  wake-up p50 {_us(lat['p50_us'])} p99.9 {_us(lat['p99_9_us'])} max "
            f"{_us(lat['max_us'])} us, turnaround p99.9 {_us(turn['p99_9_us'])} us, overruns "
            f"{c['overruns']}" + tail)


def table_lines(rep):
    lines = same_run_table_lines(rep) if rep.get("mode") == "same-run" else rounds_table_lines(rep)
    return [line.rstrip() for line in lines]


def _sched_text(priority, rt_ok, locked):
    if not priority:
        return "normal scheduling (priority 0: not real time)"
    text = f"SCHED_FIFO {priority}" + (", mlockall" if locked else "")
    refused = [w for ok, w in ((rt_ok, "SCHED_FIFO REFUSED"), (locked, "mlockall REFUSED"))
               if ok is False]
    return text + (f" ({', '.join(refused)})" if refused else "")


def rounds_table_lines(rep):
    cfg = rep["config"]
    rounds = rep["rounds"]
    loops = [r["loop"] for r in rounds if r["kind"] == "loop" and r.get("loop")]
    rt_ok = all(lp["config"].get("rt_policy_ok") for lp in loops) if loops else None
    locked = all(lp["config"].get("memory_locked") for lp in loops) if loops else None
    lines = [
        f"loop benchmark    {cfg['rounds']} loop rounds of {cfg['round_s']} s, each between two "
        f"floor rounds ({len(cfg['schedule'])} rounds, one thing at a time)",
        f"                  {cfg['rate_hz']} Hz (period {cfg['period_us']:g} us), "
        f"{_sched_text(cfg['priority'], rt_ok, locked)}, spin {cfg['spin_us']:g} us",
        f"floor             {cfg['floor']}",
        f"loop              the server over the {cfg['transport']}, TCU peer in the same process",
        f"PM QoS            {cfg['pm_qos']}",
        "",
        f"{'':11}{'wake-up latency (us)':^32}{'late/':>7}  {'turnaround (us)':^22}"
        f"{'skip':>6}{'floor':>8}{'ratio':>7}  {'verdict':^11}",
        f"{'round':<6}{'kind':<5}{'p50':>8}{'p99':>8}{'p99.9':>8}{'max':>8}{'ovr':>7}  "
        f"{'p50':>6}{'p99.9':>8}{'max':>8}{'':>6}{'p99.9':>8}{'':>7}  {'wake':>5} {'turn':>5}",
    ]
    for r in rounds:
        idx = f"{r['index']:<6}{r['kind']:<5}"
        if r["kind"] == "floor":
            f = r.get("floor")
            if not f or not f.get("samples"):
                lines.append(idx + "  nothing measured")
                continue
            lines.append(f"{idx}{_us(f['p50_us'], 8)}{_us(f['p99_us'], 8)}{_us(f['p99_9_us'], 8)}"
                         f"{_us(f['max_us'], 8)}{f['late_wakeups']:>7}  {'':>22}"
                         f"{'-' if f.get('skipped') is None else f['skipped']:>6}"
                         + (" (stopped early)" if r.get("partial") else ""))
            continue
        lp = r.get("loop")
        if not lp:
            lines.append(idx + "  nothing measured")
            continue
        lat, turn, c = lp["wakeup_latency"], lp["turnaround"], lp["counts"]
        j = r.get("judgement") or {}
        ratio = j.get("ratio")
        turn_v = _verdict(j.get("turnaround_pass")) if j.get("turnaround_judged") else "n/j"
        lines.append(f"{idx}{_us(lat['p50_us'], 8)}{_us(lat['p99_us'], 8)}{_us(lat['p99_9_us'], 8)}"
                     f"{_us(lat['max_us'], 8)}{c['overruns']:>7}  {_us(turn['p50_us'], 6)}"
                     f"{_us(turn['p99_9_us'], 8)}{_us(turn['max_us'], 8)}{c['skipped_ticks']:>6}"
                     f"{_us(j.get('neighbour_floor_p99_9_us'), 8)}"
                     f"{'-' if ratio is None else f'{ratio:.2f}':>7}  "
                     f"{_verdict(j.get('ratio_pass')):>5} {turn_v:>5}"
                     + (" (stopped early)" if r.get("partial") else ""))
    lines += [
        "",
        "late/ovr: the floor's wake-ups later than a period / the loop's overruns; floor p99.9: "
        "the mean of",
        "the floor rounds just before and after the loop round; ratio: loop wake-up p99.9 / that "
        f"(wake: <= {LATENCY_RATIO_TARGET:g});",
        f"turn: turnaround p99.9 <= {TURNAROUND_P99_9_TARGET_US:g} us; "
        f"n/j = not judged (a neighbouring floor's p99.9 is {QUIET_FLOOR_P99_9_US:g} us or more).",
    ]
    s = rep.get("summary") or {}
    if s.get("median_ratio") is not None:
        lines.append(f"median ratio      {s['median_ratio']:.2f} over {len(s['ratios'])} loop "
                     "round(s)")
    frames = _frames_line(loops)
    if frames:
        lines.append(frames)
    for w in s.get("warnings") or []:
        lines.append(f"warning           {w}")
    if rep.get("interrupted"):
        lines.append(f"stopped early     after {len(rounds)} of {len(cfg['schedule'])} rounds "
                     "(the last one cut short)")
    lines.append("")
    lines += _target_lines(rep["targets"])
    for t in rep["targets"]:
        if t["status"] == "NOT JUDGED" and "turnaround" in t["target"]:
            lines.append("  (turnaround not judged: no loop round had quiet floors on both sides)")
        elif t.get("rounds_not_judged") and "turnaround" in t["target"]:
            lines.append(f"  (turnaround judged in rounds {_list(t['rounds'])}; not judged in "
                         f"rounds {_list(t['rounds_not_judged'])}: a noisier floor beside them)")
    return lines


def _list(xs):
    return ", ".join(str(x) for x in xs) or "none"


def _frames_line(loops, what="loop rounds: "):
    if not loops:
        return None
    tot = {"rx": 0, "lost": 0, "rejected": 0, "tx": 0, "dropped": 0, "timeouts": 0}
    for lp in loops:
        c = lp["counts"]
        tot["rx"] += c["rx"]["frames"]
        tot["lost"] += c["rx"].get("lost", c["rx"].get("overflow", 0))
        tot["rejected"] += c["rx"]["rejected"]
        tot["tx"] += c["tx"]["frames"]
        tot["dropped"] += c["tx"]["dropped"]
        tot["timeouts"] += c["timeouts"]
    return (f"frames            {what}rx {tot['rx']} (rejected {tot['rejected']}, lost "
            f"{tot['lost']}), tx {tot['tx']} (dropped {tot['dropped']}), TCU timeouts "
            f"{tot['timeouts']}")


def _target_lines(targets):
    width = max(len(t["target"]) for t in targets)
    lines = [f"{'targets':<{width + 2}}{'value':>10}{'limit':>10}"]
    for t in targets:
        def fmt(x, unit=t["unit"]):
            if x is None:
                return "-"
            if unit == "us":
                return f"{x:.1f} us"
            if unit == "x":
                return f"{x:.2f}"
            return f"{x:.1f}" if isinstance(x, float) and x != int(x) else f"{x:g}"
        lines.append(f"  {t['target']:<{width}}{fmt(t['value']):>10}{fmt(t['limit']):>10}  "
                     f"{t['status']}")
    return lines


def same_run_table_lines(rep):
    cfg, loop, ct = rep["config"], rep["loop"], rep["cyclictest"]
    c = loop["counts"]
    lc = loop["config"]
    lines = [
        f"loop benchmark    SAME RUN: {rep['note']}",
        f"                  {cfg['duration_s']} s at {cfg['rate_hz']} Hz "
        f"(period {cfg['period_us']} us), "
        + _sched_text(cfg["priority"], lc.get("rt_policy_ok"), lc.get("memory_locked")),
        f"transport         {cfg['transport']}, TCU peer in the same process; cyclictest beside",
        "PM QoS            " + ("none (--no-pm-qos; cyclictest --laptop)"
                                if cfg["pm_qos_us"] is None
                                else "0 us, held by the loop and by cyclictest"),
        "",
        f"{'(us)':<26}{'p50':>8}{'p90':>8}{'p99':>8}{'p99.9':>8}{'max':>9}{'samples':>10}",
    ]

    def row(name, f):
        return (f"{name:<26}{_us(f.get('p50_us'), 8)}{_us(f.get('p90_us'), 8)}"
                f"{_us(f.get('p99_us'), 8)}{_us(f.get('p99_9_us'), 8)}{_us(f.get('max_us'), 9)}"
                f"{f.get('samples', 0):>10}")

    lines.append(row("loop turnaround", loop["turnaround"]))
    lines.append(row("loop execution", loop["execution"]))
    lines.append(row("loop wake-up latency", loop["wakeup_latency"]))
    lines.append(row("cyclictest, same run", {**ct, "max_us": None if ct["max_us"] is None
                                              else float(ct["max_us"])}))
    lines.append("")
    lines.append(f"ticks {c['ticks']}, overruns {c['overruns']}, skipped ticks "
                 f"{c['skipped_ticks']}; cyclictest: {ct['late_count']} of {ct['samples']} "
                 f"wake-ups later than {ct['late_threshold_us']:.0f} us, {ct['overflows']} above "
                 f"{ct['hist_max_us']} us")
    frames = _frames_line([loop], what="")
    if frames:
        lines.append(frames)
    for w in loop["run"].get("warnings") or []:
        lines.append(f"warning           {w}")
    if rep.get("interrupted"):
        lines.append("stopped early     (Ctrl-C): the figures cover the time run")
    lines.append("")
    lines += _target_lines(rep["targets"])
    lines.append(f"  ({ct['late_threshold_us']:.0f} us = period - loop p50 turnaround: a tick "
                 "waking later cannot end before the next deadline)")
    return lines


# --------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------

def _check_writable(path):
    full = os.path.abspath(path)
    if os.path.isdir(full):
        raise BenchError(f"--json {path}: is a directory")
    folder = os.path.dirname(full)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        raise BenchError(f"--json {path}: cannot create folder {folder}: {e.strerror}") from None
    if not os.access(folder, os.W_OK) or (os.path.exists(full) and not os.access(full, os.W_OK)):
        raise BenchError(f"--json {path}: not writable")


class StopOnSignal(StopSignals):
    """The first SIGINT/SIGTERM sets ``event`` (the run stops and writes what it has)
    and says so; the next one acts as usual (``StopSignals(once=True)``)."""

    def __init__(self, progress):
        super().__init__(once=True)
        self._progress = progress

    def _on_signal(self, signum, frame):
        super()._on_signal(signum, frame)
        _note(self._progress, "stopping: the figures measured so far will be written "
                              "(again to abort)")

    @property
    def signum(self):
        return self.received[0] if self.received else None


def main(argv=None, progress=None):
    progress = sys.stderr if progress is None else progress
    try:
        args = parse_args(argv)
        _check_writable(args.json)
        with StopOnSignal(progress) as stopper:
            if args.same_run:
                rep = run_same_run(args, progress, stopper.event)
            else:
                rep = run_rounds(args, progress, stopper.event,
                                 write=lambda r: write_figures(args.json, r))
    except BenchError as e:
        print(f"rt_loop.tools.bench: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rt_loop.tools.bench: aborted", file=sys.stderr)
        return 130
    except OSError as e:
        print(f"rt_loop.tools.bench: error: cannot write {args.json}: {e.strerror or e}", file=sys.stderr)
        return 2
    for line in table_lines(rep):
        print(line)
    try:
        write_figures(args.json, rep)
    except OSError as e:
        print(f"rt_loop.tools.bench: error: cannot write {args.json}: {e.strerror or e}", file=sys.stderr)
        return 2
    print(f"json              {args.json}")
    if stopper.signum is not None:
        return 128 + stopper.signum
    if args.check and not rep["pass"]:
        missed = [t["target"] for t in rep["targets"] if t["status"] == "FAIL"]
        print(f"rt_loop.tools.bench: check failed: {'; '.join(missed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
