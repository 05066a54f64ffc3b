"""scripts/soak: the verdict on memory and descriptors, and a run of one paper
cycle (the suite's share of the soak: server + reference TCU, paper-cycle,
MF4 recording, a row every 5 s). The hour's soak is in scripts/test-long."""

import argparse
import csv
import json
import os
import subprocess

import pytest

from rt_loop.tools import soak

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _rows(minutes, rss_mb_per_h=0.0, fds_per_h=0.0, start_mb=400.0):
    rows = []
    for i in range(int(minutes * 6) + 1):
        t = i * 10.0
        rows.append({"t_s": t, "rss_mb": start_mb + rss_mb_per_h * t / 3600.0 + (i % 3) * 0.2,
                     "fds": 9 + int(fds_per_h * t / 3600.0), "threads": 11, "overruns": 0,
                     "rx_accepted": i * 8000})
    return rows


def _args():
    return argparse.Namespace(rss_slope_mb_h=soak.RSS_SLOPE_MB_H, rss_noise_mb=soak.RSS_NOISE_MB)


def test_flat_memory_passes_and_a_leak_of_a_byte_per_tick_fails():
    ok = soak._verdict(_rows(60), _args(), {"cycles_completed": 55})
    assert ok["passed"], ok["findings"]
    # one byte per 2 kHz tick: 7.2 MB/h
    leak = soak._verdict(_rows(60, rss_mb_per_h=7.2), _args(), {"cycles_completed": 55})
    assert not leak["passed"]
    assert leak["findings"][0].startswith("memory grows: RSS slope 7.")
    # the same slope over 3 minutes is 0.36 MB: below the noise, not judged
    short = soak._verdict(_rows(3, rss_mb_per_h=7.2), _args(), {"cycles_completed": 2})
    assert short["passed"], short["findings"]


def test_growing_descriptors_fail():
    v = soak._verdict(_rows(30, fds_per_h=20), _args(), {"cycles_completed": 27})
    assert not v["passed"]
    assert any(f.startswith("open file descriptors grow") for f in v["findings"])


def test_slope_per_hour():
    assert soak.slope_per_hour([0, 1800, 3600], [1.0, 2.0, 3.0]) == 2.0
    assert soak.slope_per_hour([0, 1], [1.0, 2.0]) is None


@pytest.mark.slow
def test_a_soak_of_one_paper_cycle_passes_and_writes_csv_json_plot_and_mf4(tmp_path):
    from asammdf import MDF

    out = tmp_path / "soak"
    # half a minute asked for: the cycle started within it is played to its end (65 s)
    p = subprocess.run([os.path.join(REPO, "scripts", "soak"), "--minutes", "0.5", "--sample-s",
                        "5", "--floor-s", "2", "--priority", "0", "--quiet", "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "soak: PASS" in p.stdout
    doc = json.loads((out / "soak.json").read_text())
    assert not doc["partial"]
    v = doc["verdict"]
    assert v["passed"] and v["findings"] == []
    assert doc["run"]["cycles_completed"] == 1 and doc["run"]["cycles_incomplete"] == 0
    assert doc["run"]["error"] is None
    rows = list(csv.DictReader((out / "soak.csv").open()))
    assert len(rows) >= 12
    for key in ("rss_mb", "fds", "threads", "ring_rx_fill", "ring_tx_fill", "ring_log_fill",
                "ring_rec_fill", "overruns", "rx_accepted", "record_written", "mf4_mb",
                "tcu_stalls", "tcu_stall_max_ms", "timeouts:TCU_ClutchCmd"):
        assert key in rows[0], key
    # resident memory told apart: anonymous (malloc, Python's arenas) + mapped files
    r = rows[-1]
    assert float(r["rss_anon_mb"]) > 10 and float(r["rss_file_mb"]) > 1
    assert float(r["rss_anon_mb"]) + float(r["rss_file_mb"]) <= float(r["rss_mb"]) + 0.01
    assert (out / "soak.png").stat().st_size > 10_000
    with MDF(str(out / "soak.mf4")) as mdf:
        t = mdf.get("vehicle_speed_kmh").timestamps
    assert t[-1] - t[0] > 60.0
    assert json.loads((out / "serve-stats.json").read_text())["run"]["error"] is None
    tcu = json.loads((out / "tcu-report.json").read_text())
    assert tcu["impl"] == "c" and tcu["error"] is None, tcu["error"]      # the C node by default
    if soak._MALLINFO2 is not None:      # glibc's account of its arenas, mid-run and at the end
        for name in ("malloc-mid.xml", "malloc-end.xml"):
            assert (out / name).read_text().startswith("<malloc"), name


def test_bad_options_are_refused():
    p = subprocess.run([os.path.join(REPO, "scripts", "soak"), "--minutes", "0"], cwd=REPO,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert "argument --minutes: must be above 0" in p.stderr


def test_the_soaks_rows_are_kept_in_columns_of_machine_numbers():
    import tracemalloc

    rows = soak.Samples(10_001)          # the run's rows: every column allocated once
    row = {"t_s": 0.0, "rss_mb": 400.5, "fds": 9, "threads": 11, "rx_frames": 10**9}
    rows.append(row)
    where = {k: c.buffer_info()[0] for k, c in rows._cols.items()}
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(1, 10_001):
            rows.append({**row, "t_s": i * 10.0, "rx_frames": 10**9 + i})
        grew = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    # less than one figure's 8 bytes a row kept (the columns grown row by row took 5
    # figures' and more; a dict per row would hold some 500 bytes), and no column
    # moved: no reallocation leaves a hole in malloc's heap
    assert grew < 10_000 * 8
    assert {k: c.buffer_info()[0] for k, c in rows._cols.items()} == where
    assert len(rows) == 10_001 and bool(rows)
    with pytest.raises(IndexError):
        rows[10_001]
    more = soak.Samples(4)               # past its capacity: doubled, every value kept
    for i in range(10):
        more.append({**row, "t_s": float(i)})
    assert len(more) == 10 and more.column("t_s").tolist() == [float(i) for i in range(10)]
    assert more[-1]["t_s"] == 9.0 and more[0]["fds"] == 9
    assert rows[-1] == {"t_s": 100_000.0, "rss_mb": 400.5, "fds": 9, "threads": 11,
                        "rx_frames": 10**9 + 10_000}
    assert type(rows[0]["fds"]) is int and type(rows[0]["rss_mb"]) is float
    assert [r["t_s"] for r in rows][:3] == [0.0, 10.0, 20.0]
    with pytest.raises(ValueError):
        rows.append({"t_s": 1.0})
    assert not soak.Samples()


def test_slopes_of_every_figure_over_the_second_half():
    rows = _rows(60, rss_mb_per_h=1.0)
    for r in rows:          # the Python heap grows in the second half only; threads flat
        r["py_heap_mb"] = 50.0 + max(0.0, r["t_s"] - 1800.0) / 3600.0 * 2.0
    slopes = soak.second_half_slopes(rows)
    assert abs(slopes["py_heap_mb"] - 2.0) < 1e-9
    assert abs(slopes["rss_mb"] - 1.0) < 0.1
    assert slopes["threads"] == 0.0 and slopes["fds"] == 0.0
    assert "malloc_free_mb" not in slopes             # not in the rows: not reported
    v = soak._verdict(rows, _args(), {"cycles_completed": 55})
    assert v["slopes_second_half"] == slopes
    assert v["rss_slope_mb_h_second_half"] == slopes["rss_mb"]


def test_heap_figures_and_the_growth_of_allocation_sites():
    import tracemalloc

    assert "py_heap_mb" not in soak.heap_figures() or tracemalloc.is_tracing()
    tracemalloc.start()
    try:
        kept = []
        before = soak.heap_sites(tracemalloc.take_snapshot())
        kept.append([bytearray(1000) for _ in range(200)])       # about 200 kB on this line
        after = soak.heap_sites(tracemalloc.take_snapshot())
        fig = soak.heap_figures()
    finally:
        tracemalloc.stop()
    assert fig["py_heap_mb"] > 0.2 and fig["py_heap_peak_mb"] >= fig["py_heap_mb"]
    top = soak.heap_growth(before, after)[0]
    assert top["site"].startswith("tests/test_soak.py:") or "test_soak.py:" in top["site"]
    assert 200 <= top["grew_kb"] < 260 and top["blocks_grew"] >= 200
    assert not any("rt_loop/tools/soak.py" in s for s in after)     # its own tables left out
    if soak._MALLINFO2 is not None:                                  # glibc
        assert fig["malloc_used_mb"] > 0 and fig["malloc_free_mb"] >= 0


def test_a_stalled_bridge_is_a_note_with_its_length():
    rows = _rows(10)
    for r in rows:      # accepted frames stop from 120 s to 300 s
        r["rx_accepted"] = int(min(r["t_s"], 120.0) * 800 + max(0.0, r["t_s"] - 300.0) * 800)
    assert soak.rx_stall_s(rows) == 180.0
    v = soak._verdict(rows, _args(), {"cycles_completed": 9})
    assert v["passed"] and v["rx_stall_max_s"] == 180.0
    assert any(n.startswith("no TCU frame accepted for 180 s") for n in v["notes"])


def test_tcu_timeouts_fail_only_with_the_c_tcu_on_the_loops_rings():
    rows = _rows(10)
    rows[-1]["tcu_timeouts"] = 3
    rings = soak._verdict(rows, _args(), {"cycles_completed": 9, "tcu_on_rings_fifo": True})
    assert not rings["passed"]
    assert any(f.startswith("TCU message timeouts: 3 with the C TCU on the loop's rings")
               for f in rings["findings"])
    bridged = soak._verdict(rows, _args(), {"cycles_completed": 9, "tcu_on_rings_fifo": False})
    assert bridged["passed"] and "TCU message timeouts: 3" in bridged["notes"]
    rows[-1]["tcu_timeouts"] = 0
    assert soak._verdict(rows, _args(), {"cycles_completed": 9, "tcu_on_rings_fifo": True})["passed"]


def _timeouts(rows, at, name, n, stall_ms=0.0, stall_at=None):
    """n timeouts of message name counted in the row at index at (and every later row),
    the TCU thread's longest stall stall_ms logged in the row stall_at (default: at)."""
    for i, r in enumerate(rows):
        r.setdefault("tcu_timeouts", 0)
        r.setdefault("tcu_stall_max_ms", 0.0)
        for m in ("TCU_ClutchCmd", "TCU_ShiftCmd"):
            r.setdefault(f"timeouts:{m}", 0)
        if i >= at:
            r[f"timeouts:{name}"] += n
            r["tcu_timeouts"] += n
    rows[at if stall_at is None else stall_at]["tcu_stall_max_ms"] = max(
        stall_ms, rows[at if stall_at is None else stall_at]["tcu_stall_max_ms"])
    return rows


LIMITS = {"TCU_ClutchCmd": 16.0, "TCU_ShiftCmd": 88.0}     # (10 - 1) cycles of 2 and 10 ms, less 2 ms


def test_a_timeout_is_excused_only_by_a_stall_of_the_tcu_long_enough_to_cause_it():
    run = {"cycles_completed": 9, "tcu_on_rings_fifo": True, "timeout_limits_ms": LIMITS}
    # held 120 ms, logged when it woke: in the row of the timeouts or the next
    for stall_at in (20, 21):
        rows = _timeouts(_timeouts(_rows(10), 20, "TCU_ClutchCmd", 1), 20, "TCU_ShiftCmd", 1,
                         stall_ms=120.0, stall_at=stall_at)
        v = soak._verdict(rows, _args(), run)
        assert v["passed"], v["findings"]
        assert any(n.startswith("TCU message timeouts: 2 in 1 row of samples, each with the TCU's "
                                "thread held 120-120 ms") for n in v["notes"])
    # held 40 ms: long enough for the 2 ms message, not for the 10 ms one
    rows = _timeouts(_timeouts(_rows(10), 20, "TCU_ClutchCmd", 1), 20, "TCU_ShiftCmd", 1, stall_ms=40.0)
    v = soak._verdict(rows, _args(), run)
    assert not v["passed"]
    assert any(f.startswith("TCU message timeouts: 2 with the C TCU on the loop's rings and its "
                            "thread not held") for f in v["findings"])
    only_fast = _timeouts(_rows(10), 20, "TCU_ClutchCmd", 1, stall_ms=40.0)
    assert soak._verdict(only_fast, _args(), run)["passed"]
    # the stall two rows later, or before: not this timeout's
    for stall_at in (19, 22):
        rows = _timeouts(_rows(10), 20, "TCU_ClutchCmd", 1, stall_ms=120.0, stall_at=stall_at)
        assert not soak._verdict(rows, _args(), run)["passed"]
    # one excused episode and one without a stall: the second fails, counted alone
    rows = _timeouts(_timeouts(_rows(10), 20, "TCU_ClutchCmd", 1, stall_ms=30.0), 40, "TCU_ClutchCmd", 2)
    tm = soak.timeout_rows(rows, LIMITS)
    assert (tm["excused"], tm["unexplained"]) == (1, 2)
    assert [e["excused"] for e in tm["episodes"]] == [True, False]
    assert any(f.startswith("TCU message timeouts: 2 with") for f in soak._verdict(rows, _args(), run)["findings"])


def test_an_excused_timeout_names_the_hosts_steal_time_over_its_rows():
    run = {"cycles_completed": 9, "tcu_on_rings_fifo": True, "timeout_limits_ms": LIMITS}
    rows = _timeouts(_rows(10), 20, "TCU_ClutchCmd", 1, stall_ms=100.0)
    for i, r in enumerate(rows):            # 10 ms a row; 90 more in the timeout's row and the next
        r["steal_ms"] = 10.0 * i + (50.0 if i >= 20 else 0.0) + (40.0 if i >= 21 else 0.0)
    tm = soak.timeout_rows(rows, LIMITS)
    assert [e["steal_ms"] for e in tm["episodes"]] == [pytest.approx(110.0)]
    v = soak._verdict(rows, _args(), run)
    assert v["passed"]
    assert any(n.endswith("held 100-100 ms by the machine (the host's steal time over those rows: "
                          "110-110 ms)") for n in v["notes"]), v["notes"]
    # rows without the figure: none named
    rows = _timeouts(_rows(10), 20, "TCU_ClutchCmd", 1, stall_ms=100.0)
    assert soak.timeout_rows(rows, LIMITS)["episodes"][0]["steal_ms"] is None


def _samples(n):
    s = soak.Samples(n)
    for i in range(n):
        s.append({"t_s": i * 10.0, "rss_mb": 400.0, "rss_anon_mb": 200.0, "rss_file_mb": 150.0,
                  "py_heap_mb": 1.0, "py_heap_peak_mb": 1.5, "malloc_used_mb": 27.0,
                  "malloc_free_mb": 1.5, "malloc_mmap_mb": 29.0, "fds": 9, "threads": 9,
                  "overruns": 0, "rx_accepted": i * 8000, "tcu_timeouts": 0,
                  "timeouts:TCU_ClutchCmd": 0, "tcu_stall_max_ms": 0.0, "steal_ms": 0.0})
    return s


def test_the_verdict_makes_no_python_number_per_row():
    """The partial verdict runs every minute over every row: a Python float per row and
    column (a list of them: 40 bytes and more a figure) is a burst that grows with the
    run, and Python's allocator met it with new 1 MiB arenas, resident under mlockall,
    that stayed. Machine numbers cost 8 bytes a figure, a few columns at a time."""
    import tracemalloc

    def peak(n):
        rows = _samples(n)
        soak._verdict(rows, _args(), {"cycles_completed": 9})
        tracemalloc.start()
        try:
            v = soak._verdict(rows, _args(), {"cycles_completed": 9})
            return tracemalloc.get_traced_memory()[1], v
        finally:
            tracemalloc.stop()

    small, _ = peak(720)                       # two hours of 10 s rows
    large, v = peak(7200)                      # twenty
    assert v["passed"] and v["fds_max"] == 9 and v["py_heap_peak_mb"] == 1.5
    assert v["rss_max_mb"] == 400.0 and v["rss_slope_mb_h_all"] == pytest.approx(0.0)
    per_row = (large - small) / (7200 - 720)
    assert per_row < 64, f"{per_row:.0f} bytes of Python heap per row"   # lists of floats: 140


def test_the_middles_heap_snapshot_is_taken_before_the_judged_half():
    # two hours: a minute before the half; a minute: 6 s before; a run that short the
    # verdict never judges, but the snapshot still comes first
    assert soak.mid_snapshot_s(7200.0) == pytest.approx(3540.0)
    assert soak.mid_snapshot_s(60.0) == pytest.approx(24.0)
    for d in (1.0, 65.0, 600.0, 3600.0, 86400.0):
        assert 0.0 < soak.mid_snapshot_s(d) < d / 2.0


def test_steal_is_read_from_the_cpu_line_in_milliseconds(tmp_path):
    stat = tmp_path / "stat"
    hz = os.sysconf("SC_CLK_TCK")
    stat.write_text("cpu  1920511 929075 205745 2398192 13176 0 10420 5217 0 0\n"
                    "cpu0 837228 469774 83700 1274921 4867 0 571 2618 0 0\n")
    assert soak.steal_ms(str(stat)) == pytest.approx(5217 * 1000.0 / hz)
    stat.write_text("cpu  1 2 3 4\n")                  # a kernel that does not count it
    assert soak.steal_ms(str(stat)) == 0.0
    assert soak.steal_ms(str(tmp_path / "missing")) == 0.0
    assert soak.steal_ms() >= 0.0                          # this machine's


def test_the_limits_follow_the_loops_timeouts_of_the_received_messages():
    from rt_loop.embedded import embedded_server

    server = embedded_server("soak-limits", priority=0)
    limits = soak.timeout_limits_ms(server)
    # the contract: TCU_ClutchCmd every 2 ms, the others every 10 ms, 10 cycles each
    assert limits == {"TCU_ClutchCmd": pytest.approx(16.0), "TCU_ShiftCmd": pytest.approx(88.0),
                      "TCU_EngineCmd": pytest.approx(88.0), "TCU_Status": pytest.approx(88.0)}


_MAPPED = """
import sys
import numpy as np
from rt_loop.measure.mdf_recorder import fixed_mmap_threshold
from rt_loop.tools.soak import heap_figures
if sys.argv[1] == "fixed":
    assert fixed_mmap_threshold()
a = np.ones(1_000_000)       # 8 MB: mapped on its own (above the 128 kB threshold)
del a                        # freed: glibc raises its threshold to 8 MB unless fixed
before = heap_figures()["malloc_mmap_mb"]
b = np.ones(500_000)         # 4 MB, more than the heap has free: mapped, or the heap grows
print(round(heap_figures()["malloc_mmap_mb"] - before, 3))
"""


@pytest.mark.skipif(soak._MALLINFO2 is None, reason="glibc's mallinfo2")
def test_the_recorders_blocks_stay_out_of_mallocs_heap_once_the_threshold_is_fixed():
    def mapped(mode):
        p = subprocess.run([os.path.join(REPO, ".venv", "bin", "python"), "-c", _MAPPED, mode],
                           cwd=REPO, capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        return float(p.stdout.split()[-1])

    # with the threshold fixed the block is mapped (and unmapped when freed) whatever
    # glibc's dynamic threshold did before; without it the heap grew for it on the
    # development machine (0.0 MB mapped) but not in a CI run (4.0: the dynamic
    # threshold had not risen there, cause not found), so only the fix is asserted
    assert mapped("fixed") >= 4.0


@pytest.mark.skipif(soak._MALLINFO2 is None, reason="glibc's malloc_info")
def test_malloc_info_writes_glibcs_account_of_its_free_chunks(tmp_path):
    path = tmp_path / "malloc.xml"
    assert soak.malloc_info(path)
    text = path.read_text()
    assert text.startswith("<malloc") and "<heap nr=\"0\">" in text and "<total type=" in text
    assert not soak.malloc_info(tmp_path / "missing" / "malloc.xml")   # no folder: False, no raise
