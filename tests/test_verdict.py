"""The verdict of a run on its own timing (rt_loop.verdict), rule by rule.

Every rule is checked on report dicts built here (the shapes ``Server.report()``
and ``CanTcu.report()`` write), so nothing depends on the machine's timing; a
demo recorded on this VM (tests/data/verdict/) is judged on its loop alone and
is VALID once its missed deadlines are taken out; the summary's wording of TCU
timeouts; and ``dct-hil serve --strict`` end to end with no TCU on the bus.
"""

import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest

from rt_loop import status as rt_status
from rt_loop import verdict as vd

REPO = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data" / "verdict"
TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")


def fig(max_us):
    return {"samples": 16000, "p50_us": 4.0, "p90_us": 8.0, "p99_us": 19.0, "p99_9_us": 40.0,
            "max_us": float(max_us)}


def clean_report(**run):
    """A serve report of a clean 8 s maneuver over the bridge."""
    report = {
        "config": {"rate_hz": 2000.0, "time_scale": 1.0, "period_us": 500.0, "priority": 80,
                   "transport": "bridge", "real_time": "soft", "rt_policy_ok": True,
                   "memory_locked": True},
        "run": {"state": "stopped", "error": None, "wall_s": 8.1, "sim_time_s": 8.1,
                "maneuver": "done", "maneuver_time_s": 8.0, "ticks": 16200, "warnings": []},
        "turnaround": fig(30), "execution": fig(20), "wakeup_latency": fig(60),
        "counts": {
            "ticks": 16200, "overruns": 0, "skipped_ticks": 0,
            "rx": {"frames": 5600, "accepted": 5600, "unknown_id": 0, "bad_length": 0,
                   "bad_crc": 0, "bad_counter": 0, "overflow": 0, "rejected": 0},
            "tx": {"frames": 14600, "dropped": 0},
            "tcu_messages": {name: {"accepted": 4000 if name == "TCU_ClutchCmd" else 800,
                                    "timeouts": 0, "timed_out": False}
                             for name in TCU_MESSAGES},
            "timeouts": 0,
            "log": {"written": 20200, "dropped": 0},
            "bridge": {"rx_forwarded": 5600, "tx_forwarded": 14600, "rx_ring_full": 0,
                       "rx_error_frames": 0, "rx_remote_frames": 0, "rx_fd_frames": 0,
                       "rx_errors": 0, "tx_errors": 0},
            "record": {"written": 4000, "dropped": 0},
        },
        "rings": {"rx_waiting_max": 1, "tx_waiting_max": 2, "samples": 80, "size": 8192},
        "transport": {"last_error": None},
    }
    report["run"].update(run)
    return report


def clean_tcu():
    return {
        "period_s": 0.002, "ticks": 4000, "skipped_ticks": 0, "error": None, "send_errors": 0,
        "last_send_error": None, "tick_wake_late_us": {"max": 900.0},
        "stale": {"now": True, "ticks": 3, "episode_count": 2, "episodes": [
            {"start_s": 0.0, "end_s": 0.004, "causes": {"DCT_ShaftSpeeds": "missing"}},
            {"start_s": 8.024, "end_s": None, "causes": {"DCT_ShaftSpeeds": "timeout"}},
        ]},
        "received": {"DCT_ShaftSpeeds": {"cycle_ms": 2, "max_interval_ms": 3.1}},
        "pauses": {"count": 0, "total_s": 0.0},
    }


OFFLINE = [(4.07, 1, 2), (6.85, 2, 3)]


def test_a_clean_run_is_valid_with_nothing_to_say():
    v = vd.serve_verdict(clean_report())
    assert v == {"valid": True, "findings": [], "notes": []}
    v = vd.demo_verdict(clean_report(), clean_tcu(), [(4.075, 1, 2), (6.86, 2, 3)], OFFLINE)
    assert v["valid"] and v["findings"] == []
    assert any("the 2 of the offline run" in n and "+5, +10" in n for n in v["notes"])
    assert vd.verdict_lines(v)[0] == "timing: VALID"
    assert vd.warning_line(v, strict=True) is None and vd.exit_code(v, strict=True) == 0


def test_a_recorded_demo_is_judged_by_its_loop_alone():
    """A real 8 s demo on this VM (tests/data/verdict/): the loop missed 4 deadlines, the
    rest was clean. Only the loop's findings may come out; the TCU's end-of-run stale
    episode (the plant stopping at 8.0 s, the TCU noticing at 8.028 s) and the shifts (each
    within 1 ms of the offline run) give none. With the missed deadlines taken out of the
    recorded figures, the same run is VALID (no overrun-free run could be recorded on this
    shared VM: every 5-8 s run had 2-44 overruns)."""
    rec = json.loads((DATA / "recorded-demo-8s.json").read_text())
    v = vd.demo_verdict(rec["serve"], rec["tcu"], rec["shifts"], rec["offline_shifts"])
    assert v == rec["verdict"]                        # as the demo judged it then
    assert [f.split(" ", 2)[:2] for f in v["findings"]] == [["4", "overruns"],
                                                           ["wake-up", "latency"]]
    assert vd.tcu_report_rules(rec["tcu"], rec["serve"]["run"]["maneuver_time_s"])[0] == []
    assert vd.shift_rules(rec["shifts"], rec["offline_shifts"], 8.0)[0] == []
    kept = copy.deepcopy(rec["serve"])
    kept["counts"].update(overruns=0, skipped_ticks=0)
    for key in ("turnaround", "wakeup_latency"):
        kept[key]["max_us"] = kept[key]["p99_9_us"]
    v = vd.demo_verdict(kept, rec["tcu"], rec["shifts"], rec["offline_shifts"])
    assert v["valid"] and v["findings"] == [], v
    assert vd.verdict_lines(v)[0] == "timing: VALID"


def test_a_missing_or_partial_report_is_judged_without_an_exception():
    assert vd.serve_verdict(None)["findings"] == [
        "no statistics of the loop: its timing cannot be judged"]
    for partial in ({}, {"run": {}}, {"counts": {"rx": {}}}, {"run": None, "counts": None},
                    {"counts": {"tcu_messages": {"TCU_ClutchCmd": {}}}}):
        v = vd.serve_verdict(partial)
        assert isinstance(v["valid"], bool)
    v = vd.demo_verdict(clean_report(), None, [], None, "the run was stopped")
    assert not v["valid"]
    assert any(f.startswith("no TCU report") for f in v["findings"])
    assert any("not compared" in n and "the run was stopped" in n for n in v["notes"])
    v = vd.demo_verdict(None, {}, None, None)
    assert not v["valid"] and all(isinstance(f, str) for f in v["findings"])
    bad_shifts = [("x", 1, 2), {"time_s": 1.0}, None, (4.07, 1, 2)]
    assert vd.shift_rules(bad_shifts, OFFLINE[:1])[0] == []


@pytest.mark.parametrize("overruns, skipped", [(1, 0), (0, 3), (149, 160)])
def test_any_overrun_or_skipped_tick_invalidates(overruns, skipped):
    r = clean_report()
    r["counts"].update(overruns=overruns, skipped_ticks=skipped)
    r["turnaround"]["max_us"] = 5123.0
    v = vd.serve_verdict(r)
    assert not v["valid"]
    (f,) = v["findings"]
    assert "in 16200 ticks" in f and "turnaround max 5123 us against the 500 us period" in f
    assert str(overruns) in f and str(skipped) in f
    assert vd.exit_code(v, strict=True) == vd.EXIT_INVALID == 3
    assert vd.exit_code(v, strict=False) == 0


def test_loop_error_overrun_stop_and_no_tick_invalidate():
    v = vd.serve_verdict(clean_report(error="transport error: No buffer space (errno 105)"))
    assert v["findings"][0] == ("the loop stopped on an error: transport error: No buffer "
                                "space (errno 105)")
    r = clean_report(state="overrun_stop")
    r["counts"]["overruns"] = 1
    assert any("stopped by the overrun policy" in f for f in vd.serve_verdict(r)["findings"])
    assert "the loop ran no tick" in vd.serve_verdict(clean_report(ticks=0))["findings"]


def test_wake_up_latency_against_the_period():
    r = clean_report()
    r["wakeup_latency"]["max_us"] = 17002.0
    v = vd.serve_verdict(r)
    assert v["findings"] == ["wake-up latency max 17002 us, 34.0x the 500 us period: the OS "
                             "woke the loop after its next deadline"]
    r["wakeup_latency"]["max_us"] = 310.0
    v = vd.serve_verdict(r)
    assert v["valid"] and v["notes"] == [
        "wake-up latency max 310 us, 62 % of the 500 us period: close to an overrun"]
    r["wakeup_latency"]["max_us"] = 240.0
    assert vd.serve_verdict(r)["notes"] == []
    # with the early wake-up only the latency beyond it reaches the tick
    r["config"]["spin_us"] = 300.0
    r["wakeup_latency"]["max_us"] = 622.0
    v = vd.serve_verdict(r)
    assert v["valid"] and v["notes"] == [
        "wake-up latency max 622 us (woken 300 us early, so up to 322 us late), 64 % of the "
        "500 us period: close to an overrun"]
    r["wakeup_latency"]["max_us"] = 900.0
    assert vd.serve_verdict(r)["findings"] == [
        "wake-up latency max 900 us (woken 300 us early, so up to 600 us late), 1.2x the "
        "500 us period: the OS woke the loop after its next deadline"]


def test_no_tcu_at_all_is_a_finding_and_the_summary_says_never_received():
    r = clean_report(maneuver="waiting for the TCU", maneuver_time_s=None, wall_s=1.0)
    r["counts"]["tcu_messages"] = {n: {"accepted": 0, "timeouts": 0, "timed_out": True}
                                   for n in TCU_MESSAGES}
    v = vd.serve_verdict(r)
    assert v["findings"] == ["no TCU frame received in 1.0 s: no TCU took part (every TCU "
                             "message timed out from the start; the plant ran on safe values)"]
    text = "\n".join(rt_status.summary_lines(r, "s.json"))
    assert "TCU timeouts      none: no TCU frame received" in text
    assert "timed out at the end" not in text


def test_a_tcu_message_never_received_while_others_were_is_a_finding():
    r = clean_report()
    r["counts"]["tcu_messages"]["TCU_ShiftCmd"] = {"accepted": 0, "timeouts": 0,
                                                   "timed_out": True}
    (f,) = vd.serve_verdict(r)["findings"]
    assert f.startswith("TCU_ShiftCmd never received: the plant ran on safe values")
    text = "\n".join(rt_status.summary_lines(r, "s.json"))
    assert "TCU_ShiftCmd never received" in text and "TCU_ClutchCmd 0" in text


def test_an_optional_tcu_message_never_received_is_no_finding():
    # a TCU written from the README need not send the TCU's status message
    r = clean_report()
    r["counts"]["tcu_messages"]["TCU_Status"] = {"accepted": 0, "timeouts": 0,
                                                 "timed_out": True, "optional": True}
    v = vd.serve_verdict(r)
    assert v["valid"] and v["findings"] == []
    text = "\n".join(rt_status.summary_lines(r, "s.json"))
    assert "TCU_Status never received (optional)" in text
    # the TCU's own messages missing: still a TCU that took no part
    for name in TCU_MESSAGES:
        r["counts"]["tcu_messages"][name] = {"accepted": 0, "timeouts": 0, "timed_out": True}
    assert vd.serve_verdict(r)["findings"][0].startswith("no TCU frame received")
    # once it came, it is judged as the others: its timeout is a finding
    r = clean_report()
    r["counts"]["tcu_messages"]["TCU_Status"] = {"accepted": 10, "timeouts": 1,
                                                 "timed_out": False, "optional": True}
    assert any("TCU_Status" in f for f in vd.serve_verdict(r)["findings"])


def test_every_timeout_during_a_maneuver_invalidates():
    r = clean_report()
    r["counts"]["tcu_messages"]["TCU_ClutchCmd"].update(timeouts=3, timed_out=False)
    r["counts"]["tcu_messages"]["TCU_EngineCmd"].update(timeouts=1, timed_out=True)
    (f,) = vd.serve_verdict(r)["findings"]
    assert f.startswith("TCU messages timed out during the maneuver (TCU_ClutchCmd 3 times; "
                        "TCU_EngineCmd once, still at its end): the plant ran on safe values")
    text = "\n".join(rt_status.summary_lines(r, "s.json"))
    assert "TCU_ClutchCmd timed out 3 times, came back" in text
    assert "TCU_EngineCmd timed out once, still timed out at the end" in text


def test_the_stall_that_times_a_message_out():
    # 10 cycles of 2 ms: silent 20 ms; the TCU sends every cycle and its period's phase
    # is up to 2 ms: a wake-up 16 ms late is enough, in slow motion (scale 0.5) 34 ms
    assert vd.stall_limit_ms(20.0, 2.0, 2.0) == pytest.approx(16.0)
    assert vd.stall_limit_ms(100.0, 10.0, 2.0) == pytest.approx(88.0)
    assert vd.stall_limit_ms(20.0, 2.0, 4.0, time_scale=0.5) == pytest.approx(32.0)


def _timed_out_with_stalls(*late_ms, count=None, timeouts=1):
    r = clean_report()
    for name, cycle in (("TCU_ClutchCmd", 2.0), ("TCU_ShiftCmd", 10.0), ("TCU_EngineCmd", 10.0)):
        r["counts"]["tcu_messages"][name].update(cycle_ms=cycle, timeout_ms=10 * cycle)
    r["counts"]["tcu_messages"]["TCU_ClutchCmd"].update(timeouts=timeouts)
    tcu = clean_tcu()
    tcu["period_wall_s"] = 0.002
    tcu["stalls"] = {"longest_ms": max(late_ms, default=3.0), "over_ms": 10.0,
                     "count": len(late_ms) if count is None else count,
                     "last": [{"index": i, "at_s": 3.0 + i, "late_ms": x} for i, x in enumerate(late_ms)]}
    return r, tcu


def test_a_timeout_the_tcu_threads_stall_log_explains_is_named_and_still_a_finding():
    r, tcu = _timed_out_with_stalls(12.0, 25.3)
    assert vd.timeouts_held_by_stalls(r, tcu) == {
        "TCU_ClutchCmd": {"timeouts": 1, "explained": 1, "limit_ms": 16.0}}
    v = vd.demo_verdict(r, tcu, OFFLINE, OFFLINE)
    assert not v["valid"] and any(f.startswith("TCU messages timed out during the maneuver")
                                  for f in v["findings"])
    (note,) = [n for n in v["notes"] if "stall log" in n]
    assert "25.3 ms at 4.00 s" in note and "12.0" not in note
    assert "TCU_ClutchCmd once (a stall of 16 ms or more times it out)" in note


def test_a_timeout_without_a_stall_long_enough_is_not_explained():
    for r, tcu in (_timed_out_with_stalls(12.0, 15.9),        # too short for 16 ms
                   _timed_out_with_stalls(25.0, timeouts=2),  # one stall, two timeouts
                   (_timed_out_with_stalls(25.0)[0], clean_tcu())):   # no stall log (a foreign TCU)
        held = vd.timeouts_held_by_stalls(r, tcu)["TCU_ClutchCmd"]
        assert held["explained"] < held["timeouts"]
        v = vd.demo_verdict(r, tcu, OFFLINE, OFFLINE)
        assert not [n for n in v["notes"] if "stall log" in n] or held["explained"]
    r, tcu = _timed_out_with_stalls(12.0, 15.9)
    assert not [n for n in vd.demo_verdict(r, tcu, OFFLINE, OFFLINE)["notes"] if "stall log" in n]
    # stalls overwritten in the node's ring count when the longest is long enough
    r, tcu = _timed_out_with_stalls(25.0, count=3, timeouts=3)
    assert vd.timeouts_held_by_stalls(r, tcu)["TCU_ClutchCmd"]["explained"] == 3
    r, tcu = _timed_out_with_stalls(11.0, count=3, timeouts=3)
    assert vd.timeouts_held_by_stalls(r, tcu)["TCU_ClutchCmd"]["explained"] == 0


def test_without_a_maneuver_the_last_timeout_is_the_tcu_leaving():
    r = clean_report(maneuver="none", maneuver_time_s=None)
    r["counts"]["tcu_messages"]["TCU_ClutchCmd"].update(timeouts=1, timed_out=True)
    v = vd.serve_verdict(r)
    assert v["valid"] and v["notes"] == [
        "TCU_ClutchCmd stopped arriving before the server stopped (timed out at the end): the "
        "TCU left first"]
    r["counts"]["tcu_messages"]["TCU_ClutchCmd"].update(timeouts=3, timed_out=True)
    v = vd.serve_verdict(r)
    assert v["findings"][0].startswith("TCU messages timed out and came back (TCU_ClutchCmd "
                                       "2 times)")


def test_frames_lost_below_or_in_the_bridge_invalidate():
    r = clean_report()
    r["counts"]["rx"].update(overflow=2, lost=10, lost_below_bridge=8, overflow_events=1)
    r["counts"]["tx"]["dropped"] = 4
    r["counts"]["bridge"].update(rx_errors=1, tx_errors=2, backend_overruns=5,
                                 tx_overflow_events=1)
    r["transport"]["last_error"] = "send: CanOperationError: Transmit buffer full"
    f = vd.serve_verdict(r)["findings"]
    assert f[0] == ("10 received frames lost (2 to a full ring or socket buffer, 8 dropped by "
                    "the kernel below the bridge)")
    assert any(x.startswith("1 controller receive overflow reported") for x in f)
    assert any(x.startswith("1 controller send overflow reported") for x in f)
    assert any(x.startswith("5 overruns reported by the bus interface") for x in f)
    assert any(x.startswith("4 plant frames not sent") for x in f)
    assert any(x.startswith("bridge errors, 1 receiving and 2 sending: frames not moved; the "
                            "last: send: CanOperationError") for x in f)
    # an older report: overflow only
    r = clean_report()
    r["counts"]["rx"]["overflow"] = 3
    assert vd.serve_verdict(r)["findings"] == [
        "3 received frames lost (a full ring or socket buffer)"]


def test_notes_do_not_invalidate():
    r = clean_report(warnings=["timing is not real time: priority 0 (normal scheduling)",
                               "PM QoS not held (no /dev/cpu_dma_latency): idle CPUs may wake "
                               "up late (tens to hundreds of us)"])
    r["config"]["time_scale"] = 0.1
    r["config"]["period_us"] = 5000.0
    r["counts"]["rx"].update(rejected=3, bad_crc=2, bad_counter=1)
    r["counts"]["log"]["dropped"] = 7
    r["counts"]["record"]["dropped"] = 9
    r["counts"]["bridge"].update(bus_state_changes=2, bus_state="passive")
    r["rings"].update(tx_waiting_max=107, rx_waiting_max=114)
    v = vd.serve_verdict(r)
    assert v["valid"] and v["findings"] == []
    notes = "\n".join(v["notes"])
    for words in ("server: timing is not real time", "server: PM QoS not held",
                  "slow motion (time scale 0.1): deadlines 5000 us apart",
                  "3 received frames rejected (unknown id 0, length 0, CRC 2, counter 1)",
                  "traffic log: 7 frames not logged", "recording: 9 samples lost",
                  "bus state changed 2 times (now passive)",
                  "up to 107 plant frames waiting in the tx ring (about 59 ms of the plant's "
                  "traffic) and 114 TCU frames in the rx ring, at 80 status reads"):
        assert words in notes, words
    assert "bridge: up to 107" in notes
    # the embedded TCU on the loop's own rings: no bridge to name
    r["config"]["transport"] = "rings"
    assert "rings: up to 107" in "\n".join(vd.serve_verdict(r)["notes"])


def test_tcu_stale_episodes_during_the_maneuver_invalidate_but_not_start_up_or_the_end():
    tcu = clean_tcu()
    assert vd.tcu_report_rules(tcu, 8.0) == ([], [])
    tcu["stale"]["episodes"].insert(1, {"start_s": 4.504, "end_s": 4.51, "causes": {
        "DCT_ShaftSpeeds": "timeout", "DCT_Clutch": "timeout", "VEH_Driver": "rejected"}})
    tcu["stale"]["episode_count"] = 3
    findings, _ = vd.tcu_report_rules(tcu, 8.0)
    assert findings == ["TCU stale once during the maneuver (TCU time): 4.504-4.510 s "
                        "(timeout: DCT_ShaftSpeeds, DCT_Clutch; rejected: VEH_Driver): it "
                        "opened both clutches meanwhile"]
    # stale from mid-maneuver to the end is no plant stopping
    tcu = clean_tcu()
    tcu["stale"]["episodes"][1]["start_s"] = 6.0
    (f,), _ = vd.tcu_report_rules(tcu, 8.0)
    assert "6.000-the end" in f
    # episodes beyond the report's list are counted
    tcu = clean_tcu()
    tcu["stale"]["episodes"] += [{"start_s": 1.0 + i, "end_s": 1.01 + i,
                                  "causes": {"DCT_ShaftSpeeds": "timeout"}} for i in range(5)]
    tcu["stale"]["episode_count"] = 1000 + 2
    (f,), _ = vd.tcu_report_rules(tcu, 8.0)
    assert f.startswith("TCU stale 1000 times during the maneuver") and "and 996 more" in f


def test_tcu_errors_and_notes():
    tcu = clean_tcu()
    tcu.update(error="TCU task stopped at 3.000 s: ValueError: boom", send_errors=2,
               last_send_error="TCU_ClutchCmd: bus closed", skipped_ticks=362)
    tcu["pauses"] = {"count": 1, "total_s": 0.5}
    tcu["received"]["DCT_ShaftSpeeds"]["max_interval_ms"] = 501.0
    findings, notes = vd.tcu_report_rules(tcu, 8.0)
    assert findings == ["the TCU task stopped: TCU task stopped at 3.000 s: ValueError: boom",
                        "the TCU failed to send 2 frames: the last error TCU_ClutchCmd: bus "
                        "closed"]
    assert notes == ["TCU task skipped 362 ticks of 2 ms (woke up to 0.9 ms late)",
                     "TCU paused on request once, 0.5 s in all (CanTcu.pause)",
                     "TCU saw plant frames far apart: DCT_ShaftSpeeds 501 ms (cycle 2 ms)"]
    tcu["stalls"] = {"longest_ms": 731.5, "over_ms": 10.0, "count": 3, "last": []}
    _, notes = vd.tcu_report_rules(tcu, 8.0)
    assert notes[0] == "TCU task skipped 362 ticks of 2 ms (its thread woke up to 731.5 ms late, 3 times later than 10 ms)"


def test_a_different_shift_sequence_invalidates_and_names_the_difference():
    offline = [(4.07, 1, 2), (6.85, 2, 3), (12.89, 3, 4), (19.56, 4, 3)]
    run = [(4.08, 1, 2), (6.86, 2, 3), (12.9, 3, 4), (15.2, 4, 6), (16.0, 6, 4), (19.6, 4, 3)]
    findings, notes = vd.shift_rules(run, offline, 30.0)
    assert findings == ["shift sequence differs from the offline run (6 shifts against 4): "
                        "extra 4-6 at 15.20 s, 6-4 at 16.00 s"]
    findings, _ = vd.shift_rules(run[:2], offline, 30.0)
    assert findings == ["shift sequence differs from the offline run (2 shifts against 4): "
                        "missing 3-4 at 12.89 s, 4-3 at 19.56 s (offline times)"]
    # the first run of issue 10's kind on this VM: a 3-6 in the first launch; the
    # difference is what the two sequences do not share, not a shifted block
    offline = [(4.07, 1, 2), (6.85, 2, 3), (12.89, 3, 4), (19.56, 4, 3), (20.28, 3, 2),
               (20.85, 2, 1), (29.21, 1, 2), (31.19, 2, 3), (35.80, 3, 4), (44.83, 4, 5),
               (48.55, 5, 4), (49.47, 4, 3), (50.39, 3, 2), (51.11, 2, 1)]
    demo = [(4.06, 1, 2), (6.85, 2, 3), (13.36, 3, 6), (16.83, 6, 5), (17.73, 5, 4),
            (19.08, 4, 3), (19.95, 3, 2), (27.07, 2, 1), (30.20, 1, 2), (33.00, 2, 3),
            (37.59, 3, 4), (49.04, 4, 3), (49.96, 3, 2), (50.67, 2, 1)]
    assert vd.shift_rules(demo, offline, 65.0)[0] == [
        "shift sequence differs from the offline run (14 shifts against 14): extra 3-6 at "
        "13.36 s, 6-5 at 16.83 s, 5-4 at 17.73 s; missing 3-4 at 12.89 s, 4-5 at 44.83 s, 5-4 "
        "at 48.55 s (offline times)"]
    # the summary's dicts work as well
    as_dicts = [{"time_s": t, "from": a, "to": b} for t, a, b in run]
    assert vd.shift_rules(as_dicts, offline, 30.0)[0] == vd.shift_rules(run, offline, 30.0)[0]


def test_shift_times_beyond_the_tolerance_invalidate_and_every_difference_is_noted():
    findings, notes = vd.shift_rules([(4.24, 1, 2), (6.87, 2, 3)], OFFLINE, 8.0)
    assert findings == ["shift times differ from the offline run by more than 25 ms: "
                        "1-2 at 4.24 s (+170 ms)"]
    assert notes == ["shifts: the 2 of the offline run, in order, each within 170 ms "
                     "(ms: +170, +20)"]


def test_shifts_at_the_very_end_are_not_compared():
    findings, notes = vd.shift_rules([(4.07, 1, 2), (7.9, 2, 3)], [(4.07, 1, 2)], 8.0)
    assert findings == [] and "1 shift in the last 0.2 s of the run not compared" in notes


def test_no_offline_run_is_a_note():
    assert vd.shift_rules([(4.0, 1, 2)], None, 8.0, "the run was stopped") == (
        [], ["shift sequence not compared with the offline run: the run was stopped"])


def test_the_printed_verdict_and_the_exit_status():
    r = clean_report()
    r["counts"]["overruns"] = 2
    r["counts"]["tcu_messages"]["TCU_ClutchCmd"]["timeouts"] = 1
    v = vd.serve_verdict(r)
    lines = vd.verdict_lines(v)
    assert lines[0] == ("timing: INVALID - 2 overruns and 0 skipped ticks in 16200 ticks "
                        "(0.012 %); TCU messages timed out during the maneuver (TCU_ClutchCmd "
                        "once)")
    assert [line.split(":")[0].strip() for line in lines[1:]] == ["finding", "finding"]
    assert vd.warning_line(v, strict=False).startswith("dct-hil: warning: timing INVALID - 2 "
                                                       "overruns")
    assert vd.warning_line(v, strict=True).endswith("(--strict: exit 3)")
    assert vd.exit_code(v, strict=True) == 3
    assert vd.exit_code(v, strict=True, code=1) == 1          # a failure stays a failure
    assert vd.exit_code(v, strict=True, code=130) == 130      # so does Ctrl-C
    assert vd.exit_code(v, strict=False) == 0
    # the summary of dct-hil serve ends with it
    r["verdict"] = v
    text = rt_status.summary_lines(r, "s.json")
    assert text[-3:] == lines


def test_a_verdict_survives_the_json_file():
    r = clean_report()
    r["counts"]["overruns"] = 1
    v = vd.serve_verdict(r)
    assert json.loads(json.dumps(v)) == v
    assert set(v) == {"valid", "findings", "notes"}


def run_serve(tmp_path, *extra):
    stats = tmp_path / "stats.json"
    r = subprocess.run([sys.executable, "-m", "dct_hil.cli", "serve", "--interface", "virtual",
                        "--channel", f"verdict-{tmp_path.name}", "--duration", "1", "--priority",
                        "0", "--quiet", "--stats", str(stats), *extra],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    return r, json.loads(stats.read_text())


@pytest.mark.slow
def test_serve_with_no_tcu_says_so_and_strict_exits_3(tmp_path):
    r, report = run_serve(tmp_path, "--strict")
    assert r.returncode == 3, r.stderr
    assert not report["verdict"]["valid"]
    assert any(f.startswith("no TCU frame received") for f in report["verdict"]["findings"])
    assert "TCU timeouts      none: no TCU frame received" in r.stdout
    assert "timing: INVALID - " in r.stdout and "no TCU frame received" in r.stdout
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("dct-hil: error: timing INVALID - ") and last.endswith(
        "(--strict: exit 3)")
    assert "Traceback" not in r.stderr


@pytest.mark.slow
def test_serve_without_strict_keeps_exit_0_and_warns(tmp_path):
    r, report = run_serve(tmp_path)
    assert r.returncode == 0, r.stderr
    assert not report["verdict"]["valid"]
    assert r.stderr.strip().splitlines()[-1].startswith("dct-hil: warning: timing INVALID - ")


@pytest.mark.slow
def test_help_names_strict_and_the_exit_codes():
    for command in ("serve", "demo"):
        r = subprocess.run([sys.executable, "-m", "dct_hil.cli", command, "--help"],
                           capture_output=True, text=True, timeout=60, cwd=REPO)
        text = " ".join(r.stdout.split())
        assert "--strict" in text and "3 timing INVALID with --strict" in text, command
        assert "130 Ctrl-C" in text and "2 bad options" in text


def test_a_report_copy_is_not_changed_by_the_verdict():
    r = clean_report()
    before = copy.deepcopy(r)
    vd.serve_verdict(r)
    vd.demo_verdict(r, clean_tcu(), OFFLINE, OFFLINE)
    assert r == before
