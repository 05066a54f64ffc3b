"""dct-hil demo on the embedded transport with two CPU-bound processes beside it.

The C TCU (tcu_stub.c_node) on the loop's own rings, both on SCHED_FIFO as
root: the hogs must change nothing the run is judged by: no TCU stale
episode, no TCU message timeout at the server, the offline run's shift
sequence (through the same matrix), each shift close to it. Once on the
project's contract and once on the vehicle matrix (--mapping vehicle).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: the largest difference of a shift's time from the offline run's held here in a run
#: the host did not disturb (no tick skipped by the loop or the TCU): issue 26's 10 ms. The offline run is the server's loop without a bus (the same send
#: schedule and matrix, the maneuver from the live run's tick): runs whose TCU frames
#: land on their ticks match it to the 2 ms sample. Measured 2026-12-04 (12 runs, 6 on
#: each matrix): 9 within 10 ms (6 at 0 ms), 3 at 14-20 ms where the TCU's frames
#: landed a tick late in a share of its periods (its 2 ms phase near the loop's tick)
#: or the loop skipped ticks. The embedded TCU's periods now begin half a tick after a
#: loop tick (rt_loop.embedded: lock_phase), so its frames land on their tick; what
#: remains is the loop's skipped ticks (the host not waking it: 25 skipped, +14 ms)
#: and the TCU's, which the verdict reports: such a run is held to the verdict's own
#: bound (rt_loop.verdict.SHIFT_TOLERANCE_S) plus the time the loop lost.
SHIFT_TOLERANCE_S_UNDISTURBED = 0.010
DURATION_S = 8.0


def _hogs(n=2):
    """``n`` CPU-bound processes on the normal scheduler (ended by the caller)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _demo_under_load(tmp_path, *args):
    hogs = _hogs()
    try:
        proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", "--duration", str(DURATION_S),
                               "--out", str(tmp_path), "--quiet", *args],
                              capture_output=True, text=True, timeout=240, cwd=REPO)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    stats = json.loads((tmp_path / "serve-stats.json").read_text())
    return summary, stats


def _assert_held(summary, stats):
    tcu = summary["tcu"]
    assert tcu["impl"] == "c" and summary["transport"]["tcu_impl"] == "c"
    # both threads above the hogs: what the hogs could change, they cannot reach
    assert tcu["sched"]["policy"] == "SCHED_FIFO" and stats["config"]["rt_policy_ok"], \
        (tcu["sched"], stats["config"]["rt_policy_ok"])
    from rt_loop.verdict import END_MARGIN_S, SHIFT_TOLERANCE_S, timeouts_held_by_stalls

    end = summary["maneuver_time_s"]
    counted = [ep for ep in tcu["stale"]["episodes"]       # not the start-up, not the plant stopping
               if not all(why == "missing" for why in ep["causes"].values())
               and not (ep["end_s"] is None and ep["start_s"] >= end - END_MARGIN_S)]
    assert not counted, counted
    # a timeout only where the TCU thread's own stall log shows the machine held it
    # that long (CI 2026-12-05, beside the guest: one of a 2 ms message, 20 ms of
    # silence), and then the verdict names the stall
    held = timeouts_held_by_stalls(stats, tcu)
    unexplained = {n: h for n, h in held.items() if h["explained"] < h["timeouts"]}
    assert not unexplained, (unexplained, tcu["stalls"])
    if held:
        assert any("stall log" in n for n in summary["verdict"]["notes"]), summary["verdict"]
    run = [(s["from"], s["to"]) for s in summary["shifts"]]
    offline = [(s["from"], s["to"]) for s in summary["offline_shifts"]]
    assert run == offline and len(run) == 2, (summary["shifts"], summary["offline_shifts"])
    deltas = [a["time_s"] - b["time_s"] for a, b in zip(summary["shifts"], summary["offline_shifts"])]
    # ticks the loop skipped (the machine did not wake it: the host's floor, not
    # the hogs, which run below SCHED_FIFO) put the plant behind the TCU's wall
    # clock by that long; the TCU's periods skipped (its thread woken late) send its
    # frames late; the verdict must then say so, and the shifts may be off by what the
    # verdict holds (a handover moved by up to a 10 ms message cycle or two: measured
    # +12 and +22 ms with 3 and 6 skipped ticks beside the guest, 2026-12-05) and the
    # time lost. Undisturbed: issue 26's 10 ms.
    skipped = int(stats["counts"]["skipped_ticks"])
    tcu_skipped = int(tcu["skipped_ticks"])
    lost_s = skipped / float(stats["config"]["rate_hz"]) if skipped else 0.0
    if skipped:
        assert not summary["verdict"]["valid"] and any("skipped tick" in f for f in summary["verdict"]["findings"]), \
            summary["verdict"]
    if tcu_skipped:
        assert any("TCU task skipped" in n for n in summary["verdict"]["notes"]), summary["verdict"]
    bound = (SHIFT_TOLERANCE_S if skipped or tcu_skipped or held else SHIFT_TOLERANCE_S_UNDISTURBED) + lost_s
    # (+1 us: the times are sums of 10 ms steps in floating point; a shift one record
    # late, 10 ms, came out as 0.010000000001)
    assert max(abs(d) for d in deltas) <= bound + 1e-6, (deltas, skipped, tcu_skipped)
    if not (skipped or held):   # with ticks lost the verdict also names what followed from them
        assert not any("stale" in f or "timeout" in f or "shift" in f for f in summary["verdict"]["findings"]), \
            summary["verdict"]


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_FIFO for the loop and the TCU needs root")
def test_the_demo_holds_with_two_cpu_hogs_beside_it(tmp_path):
    summary, stats = _demo_under_load(tmp_path)
    _assert_held(summary, stats)
    assert summary["mapping"].endswith("dct_hil.toml") or summary["mapping"]


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_FIFO for the loop and the TCU needs root")
def test_the_demo_on_the_vehicle_matrix_holds_with_two_cpu_hogs_beside_it(tmp_path):
    summary, stats = _demo_under_load(tmp_path, "--mapping", "vehicle")
    assert "vehicle" in summary["mapping"]
    _assert_held(summary, stats)
