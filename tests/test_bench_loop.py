"""The loop benchmark (rt_loop.tools.bench): round schedule, judgement, output, options.

Most tests feed made-up figures to the pure functions (the schedule, the
neighbouring floors, the ratios and the targets, the table); two short
real runs check the JSON file and Ctrl-C. They use priority 0 (normal
scheduling, no privileges needed) and assert what was measured and
written, never how fast anything was.
"""

import json
import os
import signal
import subprocess
import sys
import time
import uuid

import pytest

from rt_loop.tools import bench

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# --------------------------------------------------------------------------
# made-up rounds
# --------------------------------------------------------------------------

def floor(index, p999, late=0, duration_s=20.0):
    return {"index": index, "kind": "floor", "duration_s": duration_s,
            "floor": {"p50_us": 20.0, "p99_us": p999 / 2, "p99_9_us": p999, "max_us": p999 * 3,
                      "samples": int(duration_s * 2000), "late_wakeups": late, "skipped": 0,
                      "rt_policy_ok": True, "pm_qos": {"held": True}}}


def loop(index, wake_p999, turn_p999=10.0, overruns=0, duration_s=20.0):
    counts = {"ticks": int(duration_s * 2000), "overruns": overruns, "skipped_ticks": overruns,
              "rx": {"frames": 100, "overflow": 0, "rejected": 0},
              "tx": {"frames": 200, "dropped": 0}, "timeouts": 0}
    return {"index": index, "kind": "loop", "duration_s": duration_s,
            "loop": {"wakeup_latency": {"p50_us": 20.0, "p99_us": 30.0, "p99_9_us": wake_p999,
                                        "max_us": wake_p999 * 2},
                     "turnaround": {"p50_us": 4.0, "p99_9_us": turn_p999, "max_us": turn_p999 * 2},
                     "counts": counts,
                     "config": {"rt_policy_ok": True, "memory_locked": True,
                                "pm_qos": {"held": True}},
                     "run": {"warnings": [], "wall_s": duration_s}}}


def alternate(floors, loops):
    """floor, loop, floor, ... from the p99.9 figures (len(floors) == len(loops) + 1)."""
    rounds, i = [], 1
    for k, f in enumerate(floors):
        rounds.append(floor(i, *f) if isinstance(f, tuple) else floor(i, f))
        i += 1
        if k < len(loops):
            lp = loops[k]
            rounds.append(loop(i, *lp) if isinstance(lp, tuple) else loop(i, lp))
            i += 1
    return rounds


def by_status(ev):
    return [t["status"] for t in ev["targets"]]


# --------------------------------------------------------------------------
# schedule and judgement
# --------------------------------------------------------------------------

def test_every_loop_round_has_a_floor_round_before_and_after():
    assert bench.schedule(1) == ["floor", "loop", "floor"]
    kinds = bench.schedule(5)
    assert len(kinds) == 11 and kinds[0] == kinds[-1] == "floor"
    for i, k in enumerate(kinds):
        if k == "loop":
            assert kinds[i - 1] == kinds[i + 1] == "floor"
    with pytest.raises(ValueError):
        bench.schedule(0)


def test_the_ratio_is_over_the_mean_of_the_floors_before_and_after():
    ev = bench.evaluate(alternate([40.0, 60.0], [60.0]))
    (j,) = ev["judgements"]
    assert j["neighbour_rounds"] == [1, 3]
    assert j["neighbour_floor_p99_9_us"] == pytest.approx(50.0)
    assert j["ratio"] == pytest.approx(1.2) and j["ratio_pass"] is True
    assert ev["median_ratio"] == pytest.approx(1.2)
    assert by_status(ev) == ["PASS", "PASS", "PASS"] and ev["pass"] is True


def test_the_wake_up_target_is_judged_on_the_median_ratio_not_the_worst_round():
    # ratios 0.9, 2.0, 1.1: one round fails, the median passes
    ev = bench.evaluate(alternate([50.0, 50.0, 50.0, 50.0], [45.0, 100.0, 55.0]))
    assert [j["ratio_pass"] for j in ev["judgements"]] == [True, False, True]
    assert ev["median_ratio"] == pytest.approx(1.1)
    assert ev["targets"][0]["status"] == "PASS"
    # and two of three rounds above the limit: the median fails
    ev = bench.evaluate(alternate([50.0, 50.0, 50.0, 50.0], [45.0, 100.0, 70.0]))
    assert ev["median_ratio"] == pytest.approx(1.4)
    assert ev["targets"][0]["status"] == "FAIL" and ev["pass"] is False


def test_turnaround_is_judged_only_beside_quiet_floors():
    # round 2: floors 40 and 60 (quiet); round 4: floors 60 and 150 (one noisy)
    ev = bench.evaluate(alternate([40.0, 60.0, 150.0], [(50.0, 20.0), (80.0, 90.0)]))
    j2, j4 = ev["judgements"]
    assert j2["turnaround_judged"] and j2["turnaround_pass"] is True
    assert not j4["turnaround_judged"] and j4["turnaround_pass"] is None
    assert "150" in j4["turnaround_not_judged_because"]
    t = ev["targets"][1]
    assert t["status"] == "PASS" and t["rounds"] == [2] and t["rounds_not_judged"] == [4]
    assert t["value"] == 20.0            # the 90 us of the noisy round is shown, not judged
    # a judged round above 35 us fails the target
    ev = bench.evaluate(alternate([40.0, 60.0], [(50.0, 36.0)]))
    assert ev["targets"][1]["status"] == "FAIL" and ev["pass"] is False


def test_no_quiet_round_leaves_the_turnaround_target_not_judged_and_check_passing():
    ev = bench.evaluate(alternate([300.0, 400.0], [(350.0, 500.0)]))
    t = ev["targets"][1]
    assert t["status"] == "NOT JUDGED" and t["pass"] is None and t["value"] is None
    assert ev["pass"] is True


def test_overruns_are_held_against_the_neighbouring_floors_late_wake_ups():
    # floors with 2 and 0 late wake-ups in 20 s each: 1 allowed in a 20 s loop round
    ev = bench.evaluate(alternate([(40.0, 2), (40.0, 0)], [(40.0, 10.0, 1)]))
    assert ev["judgements"][0]["allowed_overruns"] == pytest.approx(1.0)
    assert ev["targets"][2]["status"] == "PASS"
    ev = bench.evaluate(alternate([(40.0, 2), (40.0, 0)], [(40.0, 10.0, 2)]))
    assert ev["targets"][2]["status"] == "FAIL"
    # as a rate: floors of 10 s with 1 late wake-up each allow 2 in a 20 s loop round
    rounds = [floor(1, 40.0, 1, 10.0), loop(2, 40.0, 10.0, 2, 20.0), floor(3, 40.0, 1, 10.0)]
    ev = bench.evaluate(rounds)
    assert ev["judgements"][0]["allowed_overruns"] == pytest.approx(2.0)
    assert ev["targets"][2]["status"] == "PASS"


def test_a_run_stopped_early_judges_the_last_loop_round_on_the_floor_before_it():
    rounds = alternate([40.0, 60.0], [50.0])
    rounds.append(loop(4, 90.0))            # stopped before the floor after it
    ev = bench.evaluate(rounds)
    assert ev["judgements"][1]["neighbour_rounds"] == [3]
    assert ev["judgements"][1]["ratio"] == pytest.approx(1.5)
    # a floor round that measured nothing is no neighbour; a loop round that did not run is skipped
    rounds = alternate([40.0, 60.0], [50.0])
    rounds[2]["floor"] = None
    rounds.append({"index": 4, "kind": "loop", "duration_s": 0.0, "loop": None})
    ev = bench.evaluate(rounds)
    assert [j["round"] for j in ev["judgements"]] == [2]
    assert ev["judgements"][0]["neighbour_rounds"] == [1]


def test_nothing_to_judge_is_not_judged_rather_than_failed():
    ev = bench.evaluate([floor(1, 40.0)])
    assert by_status(ev) == ["NOT JUDGED"] * 3 and ev["pass"] is True
    assert ev["median_ratio"] is None


# --------------------------------------------------------------------------
# output
# --------------------------------------------------------------------------

def fake_report(rounds, **cfg):
    args = bench.parse_args(["--rounds", str(sum(r["kind"] == "loop" for r in rounds))])
    rep = {
        "benchmark": "loop", "mode": "rounds",
        "config": {"rounds": args.rounds, "round_s": 20, "schedule": bench.schedule(args.rounds),
                   "rate_hz": 2000, "period_us": 500.0, "priority": 80, "spin_us": 300.0,
                   "cpu": None, "floor": "C floor loop (rt_loop.floor.measure_floor)",
                   "pm_qos_us": 0, "pm_qos": "held at 0 us", "transport": "bridge", **cfg},
        "rounds": rounds, "interrupted": False, "complete": True, "machine": {},
    }
    bench._refresh(rep)
    return rep


def test_the_table_has_a_row_per_round_with_verdicts_and_the_median_ratio():
    rep = fake_report(alternate([40.0, 60.0, 150.0], [(50.0, 20.0), (140.0, 90.0)]))
    lines = bench.table_lines(rep)
    text = "\n".join(lines)
    rows = [ln for ln in lines if ln[:1].isdigit()]
    assert [r.split()[1] for r in rows] == ["floor", "loop", "floor", "loop", "floor"]
    assert "PASS" in rows[1] and "n/j" in rows[3] and "FAIL" in rows[3]
    assert "median ratio" in text and "not judged in rounds 4" in text
    assert [ln.split()[-1] for ln in lines if ln.startswith("  ") and ln.split()[-1]
            in ("PASS", "FAIL", "JUDGED")] == [t["status"].split()[-1] for t in rep["targets"]]


def test_the_report_is_json_with_every_round_judged_and_the_targets():
    rep = fake_report(alternate([40.0, 60.0], [50.0]))
    back = json.loads(json.dumps(rep))
    assert [r["kind"] for r in back["rounds"]] == ["floor", "loop", "floor"]
    assert back["rounds"][1]["judgement"]["neighbour_rounds"] == [1, 3]
    assert {t["status"] for t in back["targets"]} <= {"PASS", "FAIL", "NOT JUDGED"}
    assert back["summary"]["median_ratio"] == pytest.approx(1.0)


def test_refused_rights_and_a_foreign_pm_qos_request_are_warned():
    rounds = alternate([40.0, 60.0], [50.0])
    rounds[0]["floor"]["rt_policy_ok"] = False
    rounds[2]["pm_qos_in_force_us"] = {"start": 0, "end": 2_000_000_000}
    rep = fake_report(rounds, pm_qos_us=None)
    warnings = rep["summary"]["warnings"]
    assert any("round 1" in w and "SCHED_FIFO refused" in w for w in warnings)
    assert any("round 3" in w and "another process held PM QoS" in w for w in warnings)


def test_cyclictest_without_pm_qos_gets_laptop_and_its_request_is_parsed():
    cmd = bench.cyclictest_command("cyclictest", 80, 500, 20, 1000, pm_qos=False, cpu=1)
    assert "--laptop" in cmd and cmd[cmd.index("-a") + 1] == "1"
    assert "--laptop" not in bench.cyclictest_command("cyclictest", 80, 500, 20, 1000)
    out = "\n".join(["# /dev/cpu_dma_latency set to 0us"]
                    + [f"{i:06d} {n:06d}" for i, n in enumerate([0, 0, 5, 3, 2] + [0] * 5)]
                    + ["# Total: 000000010", "# Min Latencies: 00002", "# Avg Latencies: 00003",
                       "# Max Latencies: 00004", "# Histogram Overflows: 00000"])
    fig = bench.parse_cyclictest(out, 10)
    assert fig["samples"] == 10 and fig["max_us"] == 4 and fig["pm_qos_set_us"] == 0
    assert bench.parse_cyclictest(out.replace("# /dev/cpu_dma_latency set to 0us", ""),
                                  10)["pm_qos_set_us"] is None


# --------------------------------------------------------------------------
# options
# --------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["--rounds", "0"], "--rounds"),
    (["--round-s", "x"], "--round-s"),
    (["--floor", "ping"], "--floor"),
    (["--duration", "5"], "--same-run"),
    (["--same-run", "--rounds", "3"], "not with --same-run"),
    (["--floor", "cyclictest", "--rate", "3000"], "whole microseconds"),
    (["--priority", "120"], "--priority"),
    (["--spin-us", "-1"], "--spin-us"),
    (["--bogus"], "unrecognized"),
])
def test_bad_options_are_one_line_exit_2(capsys, tmp_path, argv, words):
    assert bench.main(argv + ["--json", str(tmp_path / "b.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("rt_loop.tools.bench: error:")
    assert words in err
    assert not (tmp_path / "b.json").exists()


def test_a_spin_the_server_refuses_is_one_line_before_any_round(capsys, tmp_path):
    assert bench.main(["--spin-us", "450", "--priority", "0", "--rounds", "1", "--round-s", "1",
                       "--json", str(tmp_path / "b.json")]) == 2
    err = capsys.readouterr().err
    assert "spin" in err and "round  1" not in err


def test_defaults_of_each_mode():
    a = bench.parse_args([])
    assert (a.rounds, a.round_s, a.floor, a.same_run, a.no_pm_qos) == (5, 20, "c", False, False)
    a = bench.parse_args(["--same-run"])
    assert a.duration == 60 and a.rounds is None


# --------------------------------------------------------------------------
# real runs (priority 0: no privileges; nothing here depends on timing)
# --------------------------------------------------------------------------

def bench_cmd(tmp_path, *extra):
    return [sys.executable, "-m", "rt_loop.tools.bench", "--priority", "0",
            "--channel", f"bench-{uuid.uuid4().hex[:8]}", "--json", str(tmp_path / "b.json"),
            *extra]


@pytest.mark.slow
def test_a_short_run_writes_floor_and_loop_rounds(tmp_path):
    r = subprocess.run(bench_cmd(tmp_path, "--rounds", "1", "--round-s", "1"), cwd=REPO,
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "b.json").read_text())
    assert rep["mode"] == "rounds" and rep["complete"] and not rep["interrupted"]
    assert [x["kind"] for x in rep["rounds"]] == ["floor", "loop", "floor"]
    floors = [x["floor"] for x in rep["rounds"] if x["kind"] == "floor"]
    (lp,) = [x for x in rep["rounds"] if x["kind"] == "loop"]
    assert all(f["samples"] > 0 and f["p99_9_us"] is not None for f in floors)
    assert lp["loop"]["counts"]["ticks"] > 0 and lp["loop"]["wakeup_latency"]["p99_9_us"]
    assert lp["loop"]["counts"]["rx"]["accepted"] > 0          # the TCU peer was heard
    assert lp["judgement"]["neighbour_rounds"] == [1, 3]
    assert len(rep["targets"]) == 3 and rep["config"]["pm_qos_us"] == 0
    assert {"git_commit", "kernel", "cpu"} <= set(rep["machine"])
    assert r.stderr.count("  round ") == 3                       # one progress line per round
    assert "median ratio" in r.stdout


@pytest.mark.slow
def test_ctrl_c_stops_the_round_in_progress_and_writes_what_was_measured(tmp_path):
    p = subprocess.Popen(bench_cmd(tmp_path, "--rounds", "3", "--round-s", "30", "--no-pm-qos"),
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # the first progress line comes as the run starts; stop during round 1
        first = p.stderr.readline()
        assert "rounds of 30 s" in first
        time.sleep(1.0)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, err
    rep = json.loads((tmp_path / "b.json").read_text())
    assert rep["interrupted"] and not rep["complete"]
    assert len(rep["rounds"]) == 1 and rep["rounds"][0]["partial"]
    assert rep["rounds"][0]["floor"]["pm_qos"]["requested_us"] is None
    assert "stopped early" in out
