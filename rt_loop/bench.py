"""Loop benchmark: the plant server at 2 kHz under SCHED_FIFO beside cyclictest.

    python -m rt_loop.bench [--duration 60] [--rate 2000] [--priority 80]
                            [--json out/bench-loop.json] [--check]

For ``--duration`` seconds the server runs in this process over the bridge
transport (python-can's ``virtual`` bus) with a test TCU (``CanPeer``,
side "tcu") on the same bus sending its commands (the clutch currents swap
every second, as in a shift), while rt-tests' cyclictest measures the
machine's own wake-up latency at the same period and priority in the same
run::

    cyclictest -m -p PRIO -i PERIOD_US -t 1 -D DURATIONs -q -h HIST_MAX_US

Reported: turnaround, execution time and wake-up latency percentiles of the
loop beside cyclictest's latency percentiles, overruns, and how many of
cyclictest's wake-ups came later than one period minus the loop's median
turnaround (a tick waking that late could not have finished in time).

Targets (issue 4):

* turnaround p99.9 <= 35 us;
* the loop's wake-up latency p99.9 <= 1.25 x cyclictest's p99.9;
* overruns <= cyclictest's count of wake-ups later than one period minus
  the loop's p50 turnaround.

Percentiles of both come from 1 us histograms the same way
(``rt_loop.stats.hist_percentiles``: the upper edge of the bin of the
nearest-rank sample). The table and the JSON file always show every figure,
overruns included; the exit code is 0 unless ``--check`` is given and a
target is missed (1). Bad options or a missing cyclictest exit 2 with one
line. This is a benchmark, not a test: the figures depend on the machine
and on what else it runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time

TURNAROUND_P99_9_TARGET_US = 35.0
LATENCY_RATIO_TARGET = 1.25
DEFAULT_JSON = os.path.join("out", "bench-loop.json")
#: the TCU's commands during the run; the clutch currents swap every SHIFT_S
SHIFT_S = 1.0
CLUTCH_CURRENT_A = 0.6
LINE_CURRENT_A = 0.3


CYCLICTEST_MISSING = ("cyclictest not found: install rt-tests (apt-get install rt-tests), "
                      "or run scripts/bench-loop, which does")


class BenchError(Exception):
    """Bad option or environment: one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise BenchError(message)


def _positive_int(text, what, lo, hi):
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not lo <= n <= hi:
        raise argparse.ArgumentTypeError(f"{what} must be {lo}..{hi}, got {text}")
    return n


def build_parser():
    p = _Parser(prog="python -m rt_loop.bench",
                description="Benchmark the real-time loop (bridge transport, TCU peer, SCHED_FIFO) "
                            "beside cyclictest in the same run.")
    p.add_argument("--duration", type=lambda t: _positive_int(t, "--duration", 1, 86_400),
                   default=60, metavar="S", help="seconds to run (whole seconds, default 60)")
    p.add_argument("--rate", type=lambda t: _positive_int(t, "--rate", 100, 20_000),
                   default=2000, metavar="HZ", help="loop rate (default 2000: 500 us period)")
    p.add_argument("--priority", type=lambda t: _positive_int(t, "--priority", 0, 99),
                   default=80, metavar="1..99",
                   help="SCHED_FIFO priority of the loop and of cyclictest (default 80; "
                        "0: normal scheduling, not real time)")
    p.add_argument("--cpu", type=lambda t: _positive_int(t, "--cpu", 0, 4095), metavar="N",
                   help="pin the loop to CPU N (cyclictest is left unpinned)")
    p.add_argument("--channel", default="dct-hil-bench", metavar="NAME",
                   help="python-can virtual channel shared by the server and the peer")
    p.add_argument("--hist-max-us", type=lambda t: _positive_int(t, "--hist-max-us", 100, 100_000),
                   default=10_000, metavar="US",
                   help="cyclictest histogram range (default 10000 us; above it: overflows)")
    p.add_argument("--json", default=DEFAULT_JSON, metavar="FILE",
                   help=f"where to write the figures (default {DEFAULT_JSON})")
    p.add_argument("--spin-us", type=float, default=None, metavar="US",
                   help="early wake-up busy-waited before each deadline (default: the server's)")
    p.add_argument("--check", action="store_true", help="exit 1 if a target is missed")
    return p


# --------------------------------------------------------------------------
# cyclictest
# --------------------------------------------------------------------------

def cyclictest_command(exe, priority, period_us, duration_s, hist_max_us):
    return [exe, "-m", "-p", str(priority), "-i", str(period_us), "-t", "1",
            "-D", f"{duration_s}s", "-q", "-h", str(hist_max_us)]


def parse_cyclictest(text, hist_max_us):
    """Histogram and summary of ``cyclictest -q -h N`` output (one thread).

    Returns {"hist": list of N+1 counts (1 us bins; the last holds the
    overflows, i.e. everything from N us up), "samples", "min_us", "avg_us",
    "max_us", "overflows"}. Raises BenchError if there is no histogram.
    """
    hist = [0] * (hist_max_us + 1)
    summary = {}
    seen = False
    for raw in text.splitlines():
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
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
            "total_reported": number("Total")}


def late_count(hist, threshold_us):
    """Samples of a 1 us histogram (values truncated to whole us) later than threshold_us."""
    first = max(0, int(math.floor(threshold_us)) + 1)
    return int(sum(hist[first:]))


class Cyclictest:
    """cyclictest running beside the loop; ``result()`` waits and parses."""

    def __init__(self, priority, period_us, duration_s, hist_max_us):
        exe = shutil.which("cyclictest")
        if exe is None:
            raise BenchError(CYCLICTEST_MISSING)
        self.hist_max_us = hist_max_us
        self.duration_s = duration_s
        self.command = cyclictest_command(exe, priority, period_us, duration_s, hist_max_us)
        self.proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, start_new_session=True)

    def result(self):
        try:
            out, err = self.proc.communicate(timeout=self.duration_s + 60)
        except subprocess.TimeoutExpired:
            self.kill()
            raise BenchError(f"cyclictest did not finish within {self.duration_s + 60} s") from None
        if self.proc.returncode != 0:
            first = next((ln.strip() for ln in (err + out).splitlines() if ln.strip()), "")
            raise BenchError(f"cyclictest failed (exit {self.proc.returncode}): {first or 'no output'}"
                             + ("; SCHED_FIFO needs root or CAP_SYS_NICE" if "priority" in err
                                or "scheduling" in err else ""))
        return parse_cyclictest(out, self.hist_max_us)

    def kill(self):
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGINT)
                self.proc.wait(5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


# --------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------

def _commands(t_s):
    """The TCU's commands at t_s: a shift from K1 to K2 and back every SHIFT_S."""
    on_k1 = int(t_s / SHIFT_S) % 2 == 0
    return {"SolenoidCurrent1": CLUTCH_CURRENT_A if on_k1 else 0.0,
            "SolenoidCurrent2": 0.0 if on_k1 else CLUTCH_CURRENT_A,
            "LineSolenoidCurrent": LINE_CURRENT_A}


def run(args, progress=sys.stderr):
    """Runs the loop, the peer and cyclictest; returns the report dict."""
    from can_dbc.peer import CanPeer
    from rt_loop.server import Server, ServerError
    from rt_loop.stats import hist_percentiles
    from rt_loop.transport import TransportError

    import numpy as np

    period_us = int(round(1e6 / args.rate))
    if abs(period_us - 1e6 / args.rate) > 1e-6:
        raise BenchError(f"--rate {args.rate}: the period must be a whole number of "
                         "microseconds for cyclictest (e.g. 1000, 2000, 4000, 5000 Hz)")
    if shutil.which("cyclictest") is None:
        raise BenchError(CYCLICTEST_MISSING)
    _check_writable(args.json)

    try:
        server = Server(args.channel, interface="virtual", rate_hz=args.rate,
                        priority=args.priority, cpu=args.cpu, duration_s=args.duration,
                        spin_us=args.spin_us)
    except (ServerError, TransportError, ValueError) as e:
        raise BenchError(str(e)) from None
    peer = ct = None
    interrupted = False
    try:
        server.start()
        for w in server.warnings:
            print(f"rt_loop.bench: warning: {w}", file=progress, flush=True)
        peer = CanPeer.open(side="tcu", interface="virtual", channel=args.channel,
                            values=_commands(0.0))
        ct = Cyclictest(args.priority, period_us, args.duration, args.hist_max_us)
        t0 = time.monotonic()
        next_note = 10.0
        print(f"rt_loop.bench: {args.duration} s at {args.rate} Hz with cyclictest beside "
              "(figures at the end)", file=progress, flush=True)
        while server.running:
            t = time.monotonic() - t0
            peer.set(**_commands(t))
            if t >= next_note:
                snap = server.snapshot()
                c = snap["counts"]
                print(f"  {t:5.0f} s  ticks {c['ticks']}, overruns {c['overruns']}, "
                      f"turnaround max {snap['turnaround_max_us']:.1f} us", file=progress,
                      flush=True)
                next_note += 10.0
            server.wait(0.05)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if peer is not None:
            peer.close()
        try:
            server.stop()
        except ServerError as e:
            print(f"rt_loop.bench: {e}", file=progress)
        if interrupted and ct is not None:
            ct.kill()
    if interrupted:
        raise KeyboardInterrupt
    ct_fig = ct.result()
    loop = server.report(histograms=True)

    counts = loop["counts"]
    turn, lat = loop["turnaround"], loop["wakeup_latency"]
    ct_hist = np.asarray(ct_fig["hist"], dtype=np.uint64)
    # cyclictest truncates to whole us: bin i holds [i, i+1), as the loop's
    ct_pct = hist_percentiles(ct_hist, float(ct_fig["max_us"]) + 1.0 if ct_fig["max_us"] is not None
                              else 0.0)
    ct_pct["max_us"] = ct_fig["max_us"]
    threshold_us = period_us - (turn["p50_us"] or 0.0)
    ct_late = late_count(ct_fig["hist"], threshold_us)

    ct_p999 = ct_pct["p99_9_us"]
    targets = [
        _target(f"turnaround p99.9 <= {TURNAROUND_P99_9_TARGET_US:g} us", turn["p99_9_us"],
                TURNAROUND_P99_9_TARGET_US, "us"),
        _target(f"wake-up latency p99.9 <= {LATENCY_RATIO_TARGET:g} x cyclictest's",
                lat["p99_9_us"], None if ct_p999 is None else LATENCY_RATIO_TARGET * ct_p999, "us"),
        _target(f"overruns <= cyclictest's wake-ups > {threshold_us:.0f} us", counts["overruns"],
                ct_late, ""),
    ]
    peer_rep = peer.report() if peer is not None else None
    report = {
        "benchmark": "loop",
        "config": {
            "duration_s": args.duration,
            "rate_hz": args.rate,
            "period_us": period_us,
            "priority": args.priority,
            "spin_us": server.spin_us if server is not None else args.spin_us,
            "cpu": args.cpu,
            "transport": "bridge (python-can virtual)",
            "channel": args.channel,
            "peer": "CanPeer side tcu in the same process",
            "tcu_commands": f"SolenoidCurrent1/2 swap between 0 and {CLUTCH_CURRENT_A} A every "
                            f"{SHIFT_S:g} s, LineSolenoidCurrent {LINE_CURRENT_A} A",
        },
        "targets": targets,
        "pass": all(t["pass"] for t in targets),
        "loop": loop,
        "cyclictest": {
            "command": " ".join(ct.command),
            "samples": ct_fig["samples"],
            "min_us": ct_fig["min_us"],
            "avg_us": ct_fig["avg_us"],
            **{k: v for k, v in ct_pct.items() if k != "samples"},
            "overflows": ct_fig["overflows"],
            "hist_max_us": args.hist_max_us,
            "late_threshold_us": threshold_us,
            "late_count": ct_late,
            "histogram": [[i, int(c)] for i, c in enumerate(ct_fig["hist"]) if c],
        },
        "peer": peer_rep,
        "machine": _machine(),
    }
    return report


def _target(name, value, limit, unit):
    ok = value is not None and limit is not None and value <= limit
    return {"target": name, "value": value, "limit": limit, "unit": unit, "pass": bool(ok)}


def _us(x):
    return "-" if x is None else f"{x:.1f}"


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


def _read(path):
    try:
        with open(path, encoding="ascii") as f:
            return f.read().strip()
    except OSError:
        return None


def _machine():
    from rt_loop.stats import machine_info

    info = machine_info()
    info["rt_runtime_us"] = _read("/proc/sys/kernel/sched_rt_runtime_us")
    info["rt_period_us"] = _read("/proc/sys/kernel/sched_rt_period_us")
    info["cpufreq_governor"] = _read("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor")
    info["euid"] = os.geteuid()
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        r = subprocess.run(["git", "-C", here, "rev-parse", "HEAD"], capture_output=True,
                           text=True, timeout=10)
        info["git_commit"] = r.stdout.strip() if r.returncode == 0 else None
        if info["git_commit"]:
            r = subprocess.run(["git", "-C", here, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
            info["git_dirty"] = bool(r.stdout.strip()) if r.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        info["git_commit"] = None
    return info


# --------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------

def table_lines(rep):
    cfg, loop, ct = rep["config"], rep["loop"], rep["cyclictest"]
    c = loop["counts"]
    lc = loop["config"]
    sched = (f"SCHED_FIFO {cfg['priority']}" if cfg["priority"] else "normal scheduling")
    granted = []
    if cfg["priority"] and not lc.get("rt_policy_ok"):
        granted.append("SCHED_FIFO REFUSED")
    if lc.get("lock_memory") and not lc.get("memory_locked"):
        granted.append("mlockall REFUSED")
    lines = [
        f"loop benchmark    {cfg['duration_s']} s at {cfg['rate_hz']} Hz (period {cfg['period_us']} us), "
        f"{sched}{', mlockall' if lc.get('memory_locked') else ''}"
        + (f" ({', '.join(granted)})" if granted else ""),
        f"transport         {cfg['transport']}, TCU peer in the same process; cyclictest beside",
        "",
        f"{'(us)':<26}{'p50':>8}{'p90':>8}{'p99':>8}{'p99.9':>8}{'max':>9}{'samples':>10}",
    ]

    def row(name, f):
        return (f"{name:<26}{_us(f.get('p50_us')):>8}{_us(f.get('p90_us')):>8}"
                f"{_us(f.get('p99_us')):>8}{_us(f.get('p99_9_us')):>8}{_us(f.get('max_us')):>9}"
                f"{f.get('samples', 0):>10}")

    lines.append(row("loop turnaround", loop["turnaround"]))
    lines.append(row("loop execution", loop["execution"]))
    lines.append(row("loop wake-up latency", loop["wakeup_latency"]))
    lines.append(row("cyclictest latency", {**ct, "max_us": None if ct["max_us"] is None
                                            else float(ct["max_us"])}))
    lines.append("")
    lines.append(f"ticks {c['ticks']}, overruns {c['overruns']}, skipped ticks {c['skipped_ticks']}; "
                 f"cyclictest: {ct['late_count']} of {ct['samples']} wake-ups later than "
                 f"{ct['late_threshold_us']:.0f} us, {ct['overflows']} above {ct['hist_max_us']} us")
    rx, tx = c["rx"], c["tx"]
    lines.append(f"frames            rx {rx['frames']} (accepted {rx['accepted']}, rejected "
                 f"{rx['rejected']}, lost {rx['overflow']}), tx {tx['frames']} (dropped "
                 f"{tx['dropped']}), TCU timeouts {c['timeouts']}")
    bridge = c.get("bridge") or {}
    lost = {k: v for k, v in bridge.items() if k not in ("rx_forwarded", "tx_forwarded") and v}
    if lost:
        lines.append("bridge            " + ", ".join(f"{k} {v}" for k, v in lost.items()))
    for w in loop["run"].get("warnings") or []:
        lines.append(f"warning           {w}")
    lines.append("")
    width = max(len(t["target"]) for t in rep["targets"])
    lines.append(f"{'targets':<{width + 2}}{'value':>10}{'limit':>10}")
    for t in rep["targets"]:
        def fmt(x, unit=t["unit"]):
            if x is None:
                return "-"
            return f"{x:.1f} {unit}" if unit else f"{x:g}"
        lines.append(f"  {t['target']:<{width}}{fmt(t['value']):>10}{fmt(t['limit']):>10}  "
                     f"{'PASS' if t['pass'] else 'FAIL'}")
    lines.append(f"  ({ct['late_threshold_us']:.0f} us = period - loop p50 turnaround: a tick waking "
                 "later cannot end before the next deadline)")
    return lines


def main(argv=None):
    try:
        args = build_parser().parse_args(argv)
        rep = run(args)
    except BenchError as e:
        print(f"rt_loop.bench: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rt_loop.bench: interrupted", file=sys.stderr)
        return 130
    for line in table_lines(rep):
        print(line)
    try:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(rep, f, indent=2)
            f.write("\n")
    except OSError as e:
        print(f"rt_loop.bench: error: cannot write {args.json}: {e.strerror or e}", file=sys.stderr)
        return 2
    print(f"json              {args.json}")
    if args.check and not rep["pass"]:
        missed = [t["target"] for t in rep["targets"] if not t["pass"]]
        print(f"rt_loop.bench: check failed: {'; '.join(missed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
