"""Soak: the plant server and the reference TCU for hours, memory watched.

    python -m rt_loop.tools.soak --hours 1            # scripts/soak --hours 1
    python -m rt_loop.tools.soak --minutes 3 --out out/soak-short

One process: ``rt_loop.server.Server`` and the reference TCU, as ``dct-hil
demo`` runs them without a CAN interface: the C node (``tcu_stub.c_node``,
its task on a C thread) on the loop's own rings (``rt_loop.embedded``: no
bus, no Python between them; ``--tcu-impl c``, the default). ``--bridged``:
the C node on python-can's in-process virtual bus instead, a bridge thread
on each side; ``--tcu-impl python``: the Python node
(``tcu_stub.can_tcu.CanTcu``) on that bus. The TCU report names which
(``impl``).
The loop plays ``paper-cycle`` again each time it ends (65 s of pedals from
standstill) and records every plant output and both directions of CAN to
one MF4 file (``rt_loop.measure.mdf_recorder``) for the whole run.

Every ``--sample-s`` (10 s) one row: the process's resident memory (VmRSS),
the Python heap (``tracemalloc``, started once server, recording and TCU
are set up: what was allocated since and is alive, current and peak; its
own tables), glibc
malloc's bytes in use, free inside its arenas and mapped on their own
(``mallinfo2``), its open file descriptors and threads, how many frames wait in the loop's
rings (rx and tx of the bridge, the log and recorder rings) and what they
dropped, overruns and skipped ticks, ticks, frames received and rejected and
lost, frames sent, samples recorded, the MF4 file's size, cycles played.
Rows go to ``soak.csv`` as they are taken and to ``soak.json`` (with the
verdict) at the end and every minute; ``soak.png`` plots them. The slope
of each of those memory figures, of the descriptors and the threads over
the second half (``SLOPES``: per hour) is in the JSON and the summary, and
so is what the Python heap's allocation sites (``--tracemalloc`` frames,
1 by default; 0: not traced) grew by between the middle of the run and its
end (the middle's snapshot taken ``mid_snapshot_s`` ahead of the judged half:
its sites stay for the run's end, and Python places them among the snapshot's
objects, so they keep one of Python's 1 MiB arenas, resident under mlockall:
a step of the instrument's own that must not fall in the half it judges): a
growth is told apart at once (Python objects, memory malloc holds
free, or memory allocated outside Python's view); glibc's own account of its
arenas (``malloc_info``: free chunks by size) at the middle and the end goes to
``malloc-mid.xml`` and ``malloc-end.xml``, which tell holes left in the heap from
a high-water mark at its top. ``--no-record`` runs
without the MF4 recording (to compare). The samples are kept in columns of
machine numbers (``Samples``): the soak's own bookkeeping grows by a few
hundred bytes per row, not by a dict of Python objects.

Verdict (exit 1 when failed, one line per finding):

- **memory**: the slope of a least-squares line through RSS over the second
  half of the run (the first half holds the warm-up: allocator arenas,
  Python's caches, asammdf's first blocks) at most ``--rss-slope-mb-h``
  (4 MB per hour). Why 4: one byte leaked per tick is 2000 B/s = 7.2 MB/h
  and one byte per received frame about 1.2 MB/h more, so a leak of one
  byte per tick is caught (the MF4 recorder keeps no list of the blocks it
  appends: counts and the last block's address); and at 4 MB/h a bench that
  soaks for a week grows by 0.7 GB, which a bench PC holds. A slope needs data: growth of less than
  ``--rss-noise-mb`` (3 MB) between the second half's first and last
  samples is never a failure (the slope of a few minutes is noise; the
  byte-per-tick leak grows 3.6 MB in the second half of an hour).
- **descriptors and threads**: after the first minute their number may not
  rise above its value then by more than 2 (a transient file or socket);
  a leak of one per cycle is seen within a few cycles.
- **the loop**: it ran to the end (no error state, the recording finalized,
  the TCU stopped cleanly). Frames lost, samples or log entries dropped,
  TCU timeouts and paper-cycles cut short are notes, not failures: on a
  loaded machine they follow the load (a bridge or the Python TCU is a
  Python thread). Not so for the default set-up with SCHED_FIFO: there the
  C TCU and the loop are both real-time threads with only the rings between
  them, and a TCU message timeout is a finding, unless the TCU thread's
  stall log shows the machine held it long enough to cause it (a wake-up
  later than the message's timeout less a cycle, in the row of samples of
  the timeout or the next: ``timeout_rows``). Overruns
  are reported per hour beside the machine's wake-up floor
  (``rt_loop.floor``) measured before and after, not judged: they are the
  machine's.
"""

from __future__ import annotations

import argparse
import array
import csv
import ctypes
import dis
import json
import math
import os
import signal
import sys
import time
import tracemalloc
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from plant import argtypes
from plant.stop_signals import StopSignals

__all__ = ["SLOPES", "Samples", "SoakError", "heap_figures", "heap_sites", "main",
           "proc_figures", "run_soak", "rx_stall_s", "second_half_slopes", "slope_per_hour",
           "timeout_limits_ms", "timeout_rows"]

CHANNEL = "dct-hil-soak"
MANEUVER = "paper-cycle"
RSS_SLOPE_MB_H = 4.0
RSS_NOISE_MB = 3.0
FD_TOLERANCE = 2
#: the middle's heap snapshot this long before the second half (at most a tenth of the run)
MID_SNAPSHOT_AHEAD_S = 60.0
THREAD_TOLERANCE = 2
_TCU_START_S = 30.0
#: the figures whose slope over the second half the soak reports: (row key, unit)
SLOPES = (("rss_mb", "MB/h"), ("rss_anon_mb", "MB/h"), ("rss_file_mb", "MB/h"),
          ("py_heap_mb", "MB/h"), ("malloc_used_mb", "MB/h"), ("malloc_free_mb", "MB/h"),
          ("malloc_mmap_mb", "MB/h"), ("fds", "/h"), ("threads", "/h"))
#: allocation sites reported with their growth between the middle and the end
HEAP_SITES = 12


class SoakError(RuntimeError):
    """The soak cannot run (one line)."""


def proc_figures(pid: int | str = "self") -> dict:
    """VmRSS and VmHWM in kB, of it RssAnon (heaps, stacks, anonymous maps: what
    malloc and Python's own small-object arenas hold) and RssFile (mapped files:
    the extensions and libraries), threads and open file descriptors of a process."""
    out: dict[str, Any] = {}
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM", "RssAnon", "RssFile"):
                out[key.lower() + "_kb"] = int(value.split()[0])
            elif key == "Threads":
                out["threads"] = int(value)
    out["fds"] = len(os.listdir(f"/proc/{pid}/fd"))
    return out


def steal_ms(stat: str = "/proc/stat") -> float:
    """The time the host ran something else while this machine's CPUs wanted to run
    (``steal`` of the ``cpu`` line: all CPUs, since boot), in ms; 0.0 where the
    kernel does not count it. Its growth in a row tells a thread held by the
    machine's host from one held inside the machine."""
    try:
        with open(stat, encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return 0.0
    if len(fields) < 9 or fields[0] != "cpu":
        return 0.0
    return int(fields[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                               "usmblks", "fsmblks", "uordblks", "fordblks",
                                               "keepcost")]


def _mallinfo2() -> Any:
    try:
        f = ctypes.CDLL(None).mallinfo2
    except (OSError, AttributeError):       # not glibc >= 2.33
        return None
    f.restype = _Mallinfo2
    f.argtypes = []
    return f


_MALLINFO2 = _mallinfo2()


def heap_figures() -> dict:
    """The Python heap (tracemalloc, when tracing: current, peak and its own tables)
    and glibc malloc's (mallinfo2: in use, free inside the arenas, mapped on their
    own), in MB; keys absent where not known."""
    out: dict[str, float] = {}
    if tracemalloc.is_tracing():
        cur, peak = tracemalloc.get_traced_memory()
        out["py_heap_mb"] = round(cur / 1e6, 3)
        out["py_heap_peak_mb"] = round(peak / 1e6, 3)
        out["tracemalloc_mb"] = round(tracemalloc.get_tracemalloc_memory() / 1e6, 3)
    if _MALLINFO2 is not None:
        m = _MALLINFO2()
        out["malloc_used_mb"] = round(m.uordblks / 1e6, 3)
        out["malloc_free_mb"] = round(m.fordblks / 1e6, 3)
        out["malloc_mmap_mb"] = round(m.hblkhd / 1e6, 3)
    return out


def malloc_info(path: Any) -> bool:
    """glibc's own account of its arenas (``malloc_info``: XML, the free chunks by
    size class, per arena) into ``path``: where free bytes grow, it tells holes in
    the heap (many small free chunks) from a high-water mark (one large one at the
    top). False, with no file, where not glibc."""
    try:
        libc = ctypes.CDLL(None)
        fopen, fclose, info = libc.fopen, libc.fclose, libc.malloc_info
    except (OSError, AttributeError):
        return False
    fopen.restype, fopen.argtypes = ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_char_p]
    fclose.argtypes = [ctypes.c_void_p]
    info.argtypes = [ctypes.c_int, ctypes.c_void_p]
    fp = fopen(os.fsencode(path), b"w")
    if not fp:
        return False
    try:
        return info(0, fp) == 0
    finally:
        fclose(fp)


def heap_sites(snapshot: Any) -> dict[str, tuple[int, int]]:
    """{allocation site: (bytes, blocks)} of a tracemalloc snapshot; tracemalloc's
    own frames and this function's left out (by the grouped sites, not by
    ``Snapshot.filter_traces``: that matches every trace in Python and held the
    GIL for minutes over a few 100 000 traces)."""
    own = {line for _, line in dis.findlinestarts(heap_sites.__code__) if line}
    skip = (tracemalloc.__file__, "<frozen importlib._bootstrap>", "<unknown>")
    cwd = os.getcwd() + os.sep
    out = {}
    for st in snapshot.statistics("traceback"):
        fr = st.traceback[-1]                  # the most recent frame
        if fr.filename in skip or (fr.filename == __file__ and fr.lineno in own):
            continue
        site = " <- ".join(f"{f.filename.removeprefix(cwd)}:{f.lineno}" for f in st.traceback)
        out[site] = (st.size, st.count)
    return out


def heap_growth(before: dict, after: dict, top: int = HEAP_SITES) -> list[dict]:
    """The ``top`` sites whose bytes grew most from ``before`` to ``after``
    (``heap_sites``), largest growth first."""
    rows = []
    for site, (size, count) in after.items():
        b_size, b_count = before.get(site, (0, 0))
        rows.append({"site": site, "grew_kb": round((size - b_size) / 1e3, 1),
                     "blocks_grew": count - b_count, "kb": round(size / 1e3, 1)})
    rows.sort(key=lambda r: -r["grew_kb"])
    return rows[:top]


class Samples:
    """The soak's rows in columns of machine numbers (8 bytes a figure, not a dict of
    Python objects per row: the soak's bookkeeping must not be what grows). Reads as
    a list of dicts (``rows[i]``, ``rows[-1]``, iteration, ``len``)."""

    def __init__(self, capacity: int = 1024) -> None:
        # every column allocated once for ``capacity`` rows (the run's, when known):
        # columns grown row by row were reallocated past each other, and their old
        # blocks left holes in malloc's heap that grew with the run (3-8 kB free
        # chunks by the hundred at the end of two hours)
        self._capacity = max(1, int(capacity))
        self._n = 0
        self._cols: dict[str, array.array] = {}

    def append(self, row: dict) -> None:
        if not self._cols:
            self._cols = {k: array.array("q" if isinstance(v, int) else "d", bytes(8 * self._capacity))
                          for k, v in row.items()}
        elif row.keys() != self._cols.keys():
            raise ValueError("a row with other keys than the first")
        if self._n == self._capacity:           # beyond the run's length: doubled, once in a while
            for c in self._cols.values():
                c.extend(array.array(c.typecode, bytes(8 * self._capacity)))
            self._capacity *= 2
        for k, v in row.items():
            self._cols[k][self._n] = v
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i: int) -> dict:
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError("row index out of range")
        return {k: c[i] for k, c in self._cols.items()}

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def column(self, key: str) -> array.array:
        """One figure of every row, as machine numbers (a copy: 8 bytes a row, not a
        Python number each; the verdict reads these every minute, and a list of them
        grew a burst of Python objects with the run that Python's allocator met with
        new 1 MiB arenas, one of which stayed)."""
        return self._cols[key][:self._n]


def mid_snapshot_s(duration_s: float) -> float:
    """When (seconds into the run) the middle's heap snapshot is taken: ahead of the
    second half, whose slopes are judged (see the module's docstring)."""
    return max(0.0, duration_s / 2.0 - min(MID_SNAPSHOT_AHEAD_S, duration_s / 10.0))


def slope_per_hour(t_s: Sequence[float], y: Sequence[float]) -> float | None:
    """Least-squares slope of y over t in units of y per hour (None: < 3 points)."""
    n = len(t_s)
    if n < 3:
        return None
    mt, my = sum(t_s) / n, sum(y) / n
    sxx = sum((t - mt) ** 2 for t in t_s)
    if sxx <= 0:
        return None
    sxy = sum((t - mt) * (v - my) for t, v in zip(t_s, y))
    return sxy / sxx * 3600.0


def _fill(ring: Any) -> int:
    return (int(ring.head) - int(ring.tail)) & 0xFFFFFFFF


def _sample(server: Any, t0: float, cycles: int, mf4: Path) -> dict:
    loop = server._l  # read-only look at the rings' indices
    snap = server.snapshot()
    c = snap["counts"]
    row: dict[str, Any] = {"t_s": round(time.monotonic() - t0, 3), **proc_figures()}
    row["rss_mb"] = round(row["vmrss_kb"] / 1024.0, 3)
    row["rss_anon_mb"] = round(row.get("rssanon_kb", 0) / 1024.0, 3)
    row["rss_file_mb"] = round(row.get("rssfile_kb", 0) / 1024.0, 3)
    row.update(heap_figures())
    n = len(server.transports)
    row["ring_rx_fill"] = max((_fill(loop.rx[i]) for i in range(n)), default=0)
    row["ring_tx_fill"] = max((_fill(loop.tx[i]) for i in range(n)), default=0)
    row["ring_rx_dropped"] = sum(int(loop.rx[i].dropped) for i in range(n))
    row["ring_tx_dropped"] = sum(int(loop.tx[i].dropped) for i in range(n))
    row["ring_log_fill"] = _fill(loop.log)
    row["ring_log_dropped"] = int(loop.log.dropped)
    row["ring_rec_fill"] = _fill(loop.rec)
    row["ring_rec_dropped"] = int(loop.rec.dropped)
    row["overruns"] = int(c["overruns"])
    row["skipped_ticks"] = int(c["skipped_ticks"])
    row["ticks"] = int(c.get("ticks", 0) or int(loop.stats.ticks))
    rx, tx = c["rx"], c["tx"]
    row["rx_frames"] = int(rx["frames"])
    row["rx_accepted"] = int(rx["accepted"])
    row["rx_rejected"] = int(rx["rejected"])
    row["rx_lost"] = int(rx["lost"])
    row["tx_frames"] = int(tx["frames"])
    row["tx_dropped"] = int(tx["dropped"])
    row["tcu_timeouts"] = sum(int(m.get("timeouts", 0)) for m in c["tcu_messages"].values())
    for name, m in c["tcu_messages"].items():
        row[f"timeouts:{name}"] = int(m.get("timeouts", 0))
    row["record_written"] = int(c["record"]["written"])
    row["mf4_mb"] = round(mf4.stat().st_size / 1e6, 3) if mf4.exists() else 0.0
    row["turnaround_max_us"] = round(snap["turnaround_max_us"], 1)
    row["sim_time_s"] = round(snap["sim_time_s"], 3)
    row["cycles_started"] = cycles
    row["vehicle_speed_kmh"] = round(float(snap["plant"].get("vehicle_speed_kmh", float("nan"))), 2)
    row["steal_ms"] = steal_ms()
    return row


def rx_stall_s(rows: Any) -> float:
    """The longest time between samples in which no TCU frame was accepted (0: a
    frame in every interval)."""
    longest, since = 0.0, None
    prev = None
    for r in rows:
        if prev is not None and r["rx_accepted"] == prev["rx_accepted"]:
            since = prev["t_s"] if since is None else since
            longest = max(longest, r["t_s"] - since)
        else:
            since = None
        prev = r
    return longest


def timeout_limits_ms(server: Any) -> dict[str, float]:
    """{received message: the shortest stall of the TCU's thread that times it out}
    (``rt_loop.verdict.stall_limit_ms`` of the loop's timeout and cycle of each
    received message, the TCU's period; the soak runs in real time)."""
    from rt_loop.verdict import stall_limit_ms
    from tcu_stub.logic import PERIOD_S

    return {name: stall_limit_ms(timeout_ms, cycle_ms, PERIOD_S * 1e3)
            for name, (cycle_ms, timeout_ms) in server.stats.rx_timing.items()}


def timeout_rows(rows: Any, limits: dict[str, float]) -> dict:
    """The TCU message timeouts of the run, row by row: excused when the TCU's
    thread woke late enough to cause them (``limits``) in that row or the next
    (a stall is logged when the thread wakes, the timeout counted before), else
    unexplained. {"excused", "unexplained": timeouts; "episodes": [{t_s, timeouts:
    {message: n}, stall_ms, steal_ms, excused}]}: ``steal_ms`` is what the host took
    of the machine's CPUs over the same rows (None: the rows do not count it)."""
    episodes, excused, unexplained = [], 0, 0
    prev: dict = {}
    for i, r in enumerate(rows):
        new = {k.split(":", 1)[1]: r[k] - prev.get(k, 0) for k in r if k.startswith("timeouts:")}
        new = {k: n for k, n in new.items() if n > 0}
        prev = r
        if not new:
            continue
        stall = max(rows[j].get("tcu_stall_max_ms", 0.0) for j in (i, i + 1) if j < len(rows))
        ok = all(stall >= limits.get(name, math.inf) for name in new)
        n = sum(new.values())
        excused, unexplained = excused + (n if ok else 0), unexplained + (0 if ok else n)
        last = rows[min(i + 1, len(rows) - 1)]
        steal = (last["steal_ms"] - rows[i - 1]["steal_ms"]
                 if i > 0 and "steal_ms" in r else None)
        episodes.append({"t_s": r["t_s"], "timeouts": new, "stall_ms": stall, "steal_ms": steal,
                         "excused": ok})
    return {"excused": excused, "unexplained": unexplained, "episodes": episodes}


def _column(rows: Any, key: str) -> Sequence:
    """One figure of every row (``Samples`` reads it from its column: no row's dict)."""
    return rows.column(key) if hasattr(rows, "column") else [r[key] for r in rows]


def _first_at(t: Sequence[float], t_from: float) -> int:
    """The index of the first row at or after ``t_from`` (len(t): none)."""
    return next((i for i, x in enumerate(t) if x >= t_from), len(t))


def _second_half(t: Sequence[float]) -> int:
    """The index of the first row of the second half, which the verdict judges."""
    return _first_at(t, t[-1] / 2.0) if len(t) else 0


def _max_of(rows: Any, key: str, missing: Any = None) -> Any:
    """The largest of a figure over the rows (None: no rows; ``missing``: not a figure of theirs)."""
    if not len(rows):
        return None
    return max(_column(rows, key)) if key in rows[0] else missing


def second_half_slopes(rows: Any) -> dict:
    """{key: slope per hour over the second half} of each of ``SLOPES`` the rows hold."""
    if not len(rows):
        return {}
    t = _column(rows, "t_s")
    i0 = _second_half(t)
    keys = rows[0].keys()
    return {key: slope_per_hour(t[i0:], _column(rows, key)[i0:]) for key, _unit in SLOPES if key in keys}


def _verdict(rows: Any, args: argparse.Namespace, run: dict) -> dict:
    findings: list[str] = []
    # figures from the columns, not a list of the rows' dicts: the verdict is written every
    # minute, and lists of them grew Python's heap with the run
    t = _column(rows, "t_s")
    rss = _column(rows, "rss_mb") if len(rows) else []
    i_half = _second_half(t)
    slopes = second_half_slopes(rows) if len(rows) else {}
    rss_slope = slopes.get("rss_mb")
    growth = (rss[-1] - rss[i_half]) if len(rss) - i_half >= 2 else 0.0
    if rss_slope is not None and rss_slope > args.rss_slope_mb_h and growth > args.rss_noise_mb:
        findings.append(f"memory grows: RSS slope {rss_slope:.2f} MB/h over the second half "
                        f"(limit {args.rss_slope_mb_h:g} MB/h), {growth:.1f} MB in it")
    i_after = _first_at(t, min(60.0, t[-1] / 2.0)) if t else 0
    for key, tol, what in (("fds", FD_TOLERANCE, "open file descriptors"),
                           ("threads", THREAD_TOLERANCE, "threads")):
        if len(t) - i_after >= 2:
            after = _column(rows, key)[i_after:]
            base, top = after[0], max(after)
            if top > base + tol:
                findings.append(f"{what} grow: {base} after the first minute, up to {top} "
                                f"(tolerance {tol})")
    last = rows[-1] if rows else {}
    notes: list[str] = []
    for key, what in (("rx_lost", "received frames lost"),
                      ("ring_log_dropped", "log ring entries dropped"),
                      ("ring_rec_dropped", "recorder samples dropped"),
                      ("tx_dropped", "frames not sent"),
                      ("tcu_timeouts", "TCU message timeouts")):
        if not last.get(key):
            continue
        if key == "tcu_timeouts" and run.get("tcu_on_rings_fifo"):
            # the C TCU on the loop's rings, both SCHED_FIFO: no Python and no bus between
            # them, so a timeout is a fault of the wiring unless the machine held the TCU's
            # thread long enough to cause it (its stall log, row by row)
            tm = timeout_rows(rows, run.get("timeout_limits_ms") or {})
            unexplained = last[key] - tm["excused"]    # rows without a message's column too
            if unexplained:
                findings.append(f"TCU message timeouts: {unexplained} with the C TCU on the "
                                "loop's rings and its thread not held long enough to explain them "
                                "(both SCHED_FIFO, nothing between them: there should be none)")
            if tm["excused"]:
                held = [e["stall_ms"] for e in tm["episodes"] if e["excused"]]
                steal = [e["steal_ms"] for e in tm["episodes"]
                         if e["excused"] and e["steal_ms"] is not None]
                notes.append(f"TCU message timeouts: {tm['excused']} in {len(held)} "
                             f"{'row' if len(held) == 1 else 'rows'} of samples, each with the "
                             f"TCU's thread held {min(held):.0f}-{max(held):.0f} ms by the machine"
                             + (f" (the host's steal time over those rows: "
                                f"{min(steal):.0f}-{max(steal):.0f} ms)" if steal else ""))
        else:
            notes.append(f"{what}: {last[key]}")
    if run.get("error"):
        findings.append(f"the loop stopped: {run['error']}")
    if run.get("record_error"):
        findings.append(f"recording: {run['record_error']}")
    if run.get("tcu_error"):
        findings.append(f"TCU: {run['tcu_error']}")
    if run.get("cycles_completed", 0) < 1 and run.get("wall_s", 0) > 80:
        findings.append("no paper-cycle completed")
    if run.get("cycles_incomplete"):
        notes.append(f"{run['cycles_incomplete']} paper-cycles did not complete")
    stall = rx_stall_s(rows)
    if stall > 10.0:
        notes.append(f"no TCU frame accepted for {stall:.0f} s at a time (the TCU or a bridge "
                     "fell behind; a virtual bus keeps at most "
                     "can_dbc.channels.VIRTUAL_BACKLOG_FRAMES frames for it)")
    hours = (t[-1] / 3600.0) if rows else 0.0
    return {
        "passed": not findings and not run.get("interrupted"),
        "findings": findings,
        "notes": notes,
        "rss_start_mb": rows[0]["rss_mb"] if rows else None,
        "rss_end_mb": last.get("rss_mb"),
        "rss_max_mb": _max_of(rows, "rss_mb"),
        "rss_slope_mb_h_second_half": rss_slope,
        "rss_slope_mb_h_all": slope_per_hour(t, rss),
        "rss_growth_second_half_mb": growth,
        "rx_stall_max_s": stall,
        "slopes_second_half": slopes,
        "slope_units": dict(SLOPES),
        "py_heap_peak_mb": _max_of(rows, "py_heap_peak_mb", 0.0),
        "fds_start": rows[0]["fds"] if rows else None, "fds_end": last.get("fds"),
        "fds_max": _max_of(rows, "fds"),
        "threads_start": rows[0]["threads"] if rows else None,
        "threads_end": last.get("threads"),
        "overruns": last.get("overruns"),
        "overruns_per_hour": (last.get("overruns", 0) / hours) if hours > 0 else None,
        "limits": {"rss_slope_mb_h": args.rss_slope_mb_h, "rss_noise_mb": args.rss_noise_mb,
                   "fd_tolerance": FD_TOLERANCE, "thread_tolerance": THREAD_TOLERANCE},
    }


def _floor(seconds: float, priority: int) -> dict | None:
    if seconds <= 0:
        return None
    from rt_loop.floor import FloorError, measure_floor

    try:
        fig = measure_floor(duration_s=seconds, priority=priority,
                            pm_qos_us=0 if priority > 0 else None)
    except FloorError as e:
        return {"error": str(e)}
    fig.pop("hist", None)
    fig["late_per_hour"] = fig["late_wakeups"] / seconds * 3600.0
    return fig


def plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["t_s"] / 60.0 for r in rows]
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    ax = axes[0]
    rss0 = rows[0]["rss_mb"]
    ax.plot(t, [r["rss_mb"] - rss0 for r in rows], label=f"RSS - {rss0:.0f} MB")
    for key, what in (("py_heap_mb", "Python heap (tracemalloc)"),
                      ("malloc_used_mb", "malloc in use"), ("malloc_free_mb", "malloc free")):
        if key in rows[0]:
            v0 = rows[0][key]
            ax.plot(t, [r[key] - v0 for r in rows], label=f"{what} - {v0:.0f} MB")
    ax.set_ylabel("growth (MB)")
    ax.set_title(title)
    ax.legend(loc="best", fontsize="small")
    ax = axes[1]
    ax.plot(t, [r["fds"] for r in rows], label="open file descriptors")
    ax.plot(t, [r["threads"] for r in rows], label="threads")
    ax.set_ylabel("count")
    ax.legend(loc="best")
    ax = axes[2]
    for key in ("ring_rx_fill", "ring_tx_fill", "ring_log_fill", "ring_rec_fill"):
        ax.plot(t, [r[key] for r in rows], label=key.replace("ring_", "").replace("_fill", ""))
    ax.set_ylabel("entries waiting\n(at the sample)")
    ax.legend(loc="best")
    ax = axes[3]
    ax.plot(t, [r["overruns"] for r in rows], label="overruns")
    ax.plot(t, [r["rx_lost"] for r in rows], label="rx lost")
    ax.plot(t, [r["ring_rec_dropped"] + r["ring_log_dropped"] for r in rows],
            label="rec + log dropped")
    ax.set_ylabel("count (cumulative)")
    ax.set_xlabel("time (min)")
    ax.legend(loc="best")
    for a in axes:
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_soak(args: argparse.Namespace, out=sys.stdout, err=sys.stderr) -> int:
    from plant.maneuvers import get_maneuver
    from rt_loop.server import Server, ServerError
    from rt_loop.transport import TransportError

    duration = args.seconds
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {k: folder / n for k, n in (("csv", "soak.csv"), ("json", "soak.json"),
                                          ("png", "soak.png"), ("mf4", "soak.mf4"),
                                          ("stats", "serve-stats.json"),
                                          ("tcu_report", "tcu-report.json"),
                                          ("malloc_mid", "malloc-mid.xml"),
                                          ("malloc_end", "malloc-end.xml"))}
    for p in paths.values():
        if p.exists():
            p.unlink()
    priority = args.priority if args.priority is not None else (80 if os.geteuid() == 0 else 0)
    cycle_s = get_maneuver(MANEUVER).duration_s
    signals = StopSignals().__enter__()    # SIGINT, SIGTERM: stop (restored at the end)
    stop, received = signals.event, signals.received
    run: dict[str, Any] = {"cycles_completed": 0, "cycles_incomplete": 0,
                           "recording": args.record, "tracemalloc_frames": args.tracemalloc}
    floor_before = floor_after = None
    rows = Samples(int(duration / args.sample_s) + 16)
    heap_mid: dict | None = None
    server = tcu = None
    t0 = time.monotonic()
    try:
        floor_s = args.floor_s
        if floor_s > 0:
            print(f"soak: the machine's wake-up floor for {floor_s:g} s ...", file=out, flush=True)
            floor_before = _floor(floor_s, priority)
        try:
            kwargs = {"priority": priority, "record_every_s": args.record_every,
                      "pm_qos_us": "auto"}
            if args.tcu_impl == "c" and not args.bridged:     # as dct-hil demo: the loop's rings
                from rt_loop.embedded import embedded_server

                server = embedded_server(CHANNEL, **kwargs)
            else:
                server = Server(CHANNEL, interface="virtual", **kwargs)
            server.start(cancel=stop)
        except (ServerError, TransportError) as e:
            raise SoakError(str(e)) from None
        except Exception as e:  # the plant's parameters, the build: one line
            raise SoakError(f"the server cannot be set up: {type(e).__name__}: "
                            f"{' '.join(str(e).split())}") from None
        tcu = _open_tcu(args.tcu_impl, priority, None if args.bridged else server)
        run["tcu_on_rings_fifo"] = args.tcu_impl == "c" and not args.bridged and priority > 0
        run["timeout_limits_ms"] = timeout_limits_ms(server)
        if args.record:
            server.start_recording(paths["mf4"], args.record_every)
        if args.tracemalloc and not tracemalloc.is_tracing():
            # in this process (the server's, the recorder's and the TCU's threads), from
            # here on: what was allocated after the set-up and is still alive, so that
            # a snapshot holds few traces and is taken in a moment
            tracemalloc.start(args.tracemalloc)
        print(f"soak: {duration / 3600.0:.3g} h of {MANEUVER} ({cycle_s:g} s each) over the "
              f"embedded transport, SCHED_FIFO {priority}, the {args.tcu_impl.upper()} TCU"
              if priority else
              f"soak: {duration / 3600.0:.3g} h of {MANEUVER} over the embedded transport "
              f"(no SCHED_FIFO: not real time), the {args.tcu_impl.upper()} TCU", file=out, flush=True)
        t0 = time.monotonic()
        deadline = time.monotonic() + _TCU_START_S
        while not stop.is_set():
            if server.snapshot()["counts"]["rx"]["accepted"] > 0:
                break
            if time.monotonic() > deadline:
                raise SoakError(f"the TCU sent no valid frame within {_TCU_START_S:g} s")
            stop.wait(0.05)
        cycles = 0
        cycle_started = None
        f = open(paths["csv"], "w", newline="", encoding="utf-8")
        writer = None

        stalls_seen = 0

        def sample():
            """One row: taken, kept, written to the CSV (its header first)."""
            nonlocal writer, stalls_seen
            row = _sample(server, t0, cycles, paths["mf4"])
            new, stalls_seen = tcu.stalls(stalls_seen)
            row["tcu_stalls"] = stalls_seen      # the TCU thread's wake-ups a few periods late
            row["tcu_stall_max_ms"] = max((e["late_ms"] for e in new), default=0.0)
            rows.append(row)
            if writer is None:
                writer = csv.DictWriter(f, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            f.flush()
            return row

        next_sample = time.monotonic()
        next_json = time.monotonic() + 60.0
        end = t0 + duration
        try:
            while not stop.is_set():
                now = time.monotonic()
                if not server.running:
                    break
                if not server.maneuver_playing:
                    if cycle_started is not None:
                        snap = server.snapshot()
                        mt = snap["maneuver_time_s"] or 0.0
                        if mt >= cycle_s - 0.01:
                            run["cycles_completed"] += 1
                        else:
                            run["cycles_incomplete"] += 1
                    if now >= end:
                        break
                    server.start_maneuver(MANEUVER)
                    cycles += 1
                    cycle_started = now
                if heap_mid is None and tracemalloc.is_tracing() and now >= t0 + mid_snapshot_s(duration):
                    heap_mid = heap_sites(tracemalloc.take_snapshot())   # the middle
                    malloc_info(paths["malloc_mid"])
                if now >= next_sample:
                    row = sample()
                    if not args.quiet:
                        print(f"soak: {row['t_s'] / 60.0:6.1f} min  RSS {row['rss_mb']:.1f} MB  "
                              f"fds {row['fds']}  threads {row['threads']}  cycle {cycles}  "
                              f"overruns {row['overruns']}  rx lost {row['rx_lost']}  "
                              f"MF4 {row['mf4_mb']:.0f} MB", file=out, flush=True)
                    next_sample += args.sample_s
                if now >= next_json and rows:
                    _write_json(paths["json"], args, rows, run, floor_before, None, partial=True)
                    next_json += 60.0
                stop.wait(0.05)
        finally:
            if rows and (time.monotonic() - t0) - rows[-1]["t_s"] > 1.0 and server.running:
                sample()
            f.close()
            malloc_info(paths["malloc_end"])
            if heap_mid is not None and tracemalloc.is_tracing():
                run["heap_sites_growth_second_half"] = heap_growth(
                    heap_mid, heap_sites(tracemalloc.take_snapshot()))
    except SoakError as e:
        print(f"soak: error: {e}", file=err)
        run["error"] = str(e)
    finally:
        run["wall_s"] = time.monotonic() - t0
        if tcu is not None:
            try:
                tcu.stop()
                tcu.write_report(paths["tcu_report"])
                tcu.close()
            except Exception as e:  # the run's files stand; said in the JSON
                run["tcu_error"] = " ".join(str(e).split())
        if server is not None:
            try:
                if server.recording is not None:
                    server.stop_recording()
            except ServerError as e:
                run["record_error"] = str(e)
            server.stop()
            report = server.report()
            server.write_report(paths["stats"], report)
            run.setdefault("error", report["run"]["error"])
            run["ticks"] = report["run"]["ticks"]
        signals.__exit__(None, None, None)
        if args.tracemalloc:
            tracemalloc.stop()
    run["interrupted"] = bool(received)
    if rows and not received and args.floor_s > 0:
        print(f"soak: the machine's wake-up floor again for {args.floor_s:g} s ...", file=out,
              flush=True)
        floor_after = _floor(args.floor_s, priority)
    doc = _write_json(paths["json"], args, rows, run, floor_before, floor_after, partial=False)
    if rows:
        try:
            plot(rows, paths["png"], f"soak: {rows[-1]['t_s'] / 60.0:.0f} min of {MANEUVER}, "
                 "embedded transport, MF4 recording")
        except Exception as e:  # a plot is not worth the verdict
            print(f"soak: warning: no plot: {' '.join(str(e).split())}", file=err)
    _print_summary(doc, paths, out)
    v = doc["verdict"]
    if received:
        print(f"soak: stopped by {signal.Signals(received[0]).name} after "
              f"{run['wall_s'] / 60.0:.1f} min; files written", file=err)
        return 130
    if run.get("error") and not rows:
        return 1
    for line in v.get("notes", []):
        print(f"soak: note: {line} (the machine's load: not judged)", file=err)
    for line in v["findings"]:
        print(f"soak: FAIL {line}", file=err)
    return 0 if v["passed"] else 1


def _write_json(path: Path, args, rows, run, floor_before, floor_after, partial) -> dict:
    v = _verdict(rows, args, run) if rows else {"passed": False, "findings": ["no sample"]}
    floors = [f for f in (floor_before, floor_after) if f and "late_per_hour" in f]
    doc = {
        "partial": partial,
        "config": {"seconds": args.seconds, "sample_s": args.sample_s,
                   "record_every_s": args.record_every, "record": args.record,
                   "tracemalloc_frames": args.tracemalloc, "maneuver": MANEUVER,
                   "transport": ("embedded (python-can virtual, bridged)"
                                 if args.bridged or args.tcu_impl == "python"
                                 else "embedded (the loop's rings)"),
                   "priority": args.priority},
        "run": run,
        "verdict": v,
        "floor_before": floor_before,
        "floor_after": floor_after,
        "floor_late_per_hour": (sum(f["late_per_hour"] for f in floors) / len(floors)
                                if floors else None),
        "load_average": os.getloadavg(),
    }
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        # the samples one row at a time, as they are encoded: every minute, a list of
        # every row's dict (or the text of them all) grew Python's heap with the run
        head = json.dumps(doc, indent=1, default=float)
        f.write(head[:-2] + ',\n "samples": [')
        for i, row in enumerate(rows):
            f.write(("\n  " if i == 0 else ",\n  ") + json.dumps(row, default=float))
        f.write("\n ]\n}\n")
    os.replace(tmp, path)
    doc["samples"] = rows
    return doc


def _print_summary(doc: dict, paths: dict, out) -> None:
    v, r = doc["verdict"], doc["run"]
    fl = doc["floor_late_per_hour"]

    def num(x, fmt="{:.2f}"):
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt.format(x)

    print("", file=out)
    print(f"soak              {num(r.get('wall_s', 0) / 60.0, '{:.1f}')} min, "
          f"{r['cycles_completed']} paper-cycles completed", file=out)
    print(f"RSS               start {num(v.get('rss_start_mb'), '{:.1f}')} MB, end "
          f"{num(v.get('rss_end_mb'), '{:.1f}')} MB, max {num(v.get('rss_max_mb'), '{:.1f}')} MB; "
          f"slope over the second half {num(v.get('rss_slope_mb_h_second_half'))} MB/h "
          f"(limit {v.get('limits', {}).get('rss_slope_mb_h')})", file=out)
    last = doc["samples"][-1] if doc["samples"] else {}
    if "py_heap_mb" in last:
        print(f"Python heap       {num(doc['samples'][0]['py_heap_mb'], '{:.1f}')} -> "
              f"{num(last['py_heap_mb'], '{:.1f}')} MB (peak {num(v.get('py_heap_peak_mb'), '{:.1f}')} "
              f"MB; tracemalloc's own tables {num(last.get('tracemalloc_mb'), '{:.1f}')} MB)",
              file=out)
    if "malloc_used_mb" in last:
        print(f"malloc            in use {num(last['malloc_used_mb'], '{:.1f}')} MB, free in its "
              f"arenas {num(last['malloc_free_mb'], '{:.1f}')} MB, mapped on their own "
              f"{num(last['malloc_mmap_mb'], '{:.1f}')} MB", file=out)
    units = v.get("slope_units", {})
    slopes = v.get("slopes_second_half") or {}
    print("second half       " + ", ".join(
        f"{k.removesuffix('_mb')} {num(x, '{:+.2f}')} {units.get(k, '')}" for k, x in slopes.items()),
        file=out)
    for g in (r.get("heap_sites_growth_second_half") or [])[:5]:
        print(f"  heap site       {g['grew_kb']:+9.1f} kB ({g['blocks_grew']:+d} blocks, now "
              f"{g['kb']:.0f} kB)  {g['site']}", file=out)
    print(f"descriptors       {v.get('fds_start')} -> {v.get('fds_end')} (max {v.get('fds_max')}); "
          f"threads {v.get('threads_start')} -> {v.get('threads_end')}", file=out)
    print(f"overruns          {v.get('overruns')} ({num(v.get('overruns_per_hour'), '{:.0f}')}/h); "
          f"the machine's floor: {num(fl, '{:.0f}')} wake-ups later than a period per hour",
          file=out)
    print(f"counters          rx {last.get('rx_frames')} (accepted {last.get('rx_accepted')}, "
          f"rejected {last.get('rx_rejected')}, lost {last.get('rx_lost')}); tx "
          f"{last.get('tx_frames')} (dropped {last.get('tx_dropped')}); recorded "
          f"{last.get('record_written')} samples, MF4 {last.get('mf4_mb')} MB", file=out)
    print("written           " + ", ".join(str(p) for k, p in paths.items() if p.exists()),
          file=out)
    print("soak: " + ("PASS" if v["passed"] else "FAIL"), file=out, flush=True)




def _open_tcu(impl: str, loop_priority: int, server: Any = None) -> Any:
    """The reference TCU: the C node (SCHED_FIFO below the loop when the loop has
    it) on the loop's own rings (``server``: an ``embedded_server``), else on the
    soak's virtual bus through a bridge thread; or the Python node on that bus."""
    if impl == "python":
        from tcu_stub.can_tcu import CanTcu

        return CanTcu.open("virtual", CHANNEL)
    from rt_loop.embedded import connect_tcu, tcu_priority
    from tcu_stub.c_node import CTcuNode

    if server is not None:
        return connect_tcu(server, priority=tcu_priority(loop_priority))
    return CTcuNode.open("virtual", CHANNEL, priority=tcu_priority(loop_priority))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scripts/soak", description=__doc__.split("\n\n")[0])
    length = p.add_mutually_exclusive_group()
    length.add_argument("--hours", type=argtypes.positive, metavar="H", help="run length (default 1 h)")
    length.add_argument("--minutes", type=argtypes.positive, metavar="M", help="run length in minutes")
    p.add_argument("--out", default="out/soak", metavar="DIR")
    p.add_argument("--sample-s", type=argtypes.positive, default=10.0, metavar="S",
                   help="one row every S seconds (10)")
    p.add_argument("--record-every", type=argtypes.positive, default=0.002, metavar="S",
                   help="MF4 sample interval in plant time (0.002)")
    p.add_argument("--priority", type=int, default=None, metavar="0..99",
                   help="SCHED_FIFO priority of the loop (80 as root, else 0)")
    p.add_argument("--floor-s", type=argtypes.non_negative, default=None, metavar="S",
                   help="the machine's wake-up floor measured this long before and after "
                        "(30 s for an hour or more, else 10; 0: not measured)")
    p.add_argument("--rss-slope-mb-h", type=argtypes.positive, default=RSS_SLOPE_MB_H, metavar="MB",
                   help=f"memory slope limit ({RSS_SLOPE_MB_H:g} MB/h)")
    p.add_argument("--rss-noise-mb", type=argtypes.non_negative, default=RSS_NOISE_MB, metavar="MB",
                   help=f"growth never judged a leak ({RSS_NOISE_MB:g} MB)")
    p.add_argument("--bridged", action="store_true",
                   help="the C TCU on python-can's virtual bus through bridge threads, not on "
                        "the loop's own rings")
    p.add_argument("--tcu-impl", choices=("c", "python"), default="c",
                   help="the reference TCU: the C node (default, as the demo's) or the Python "
                        "node (tcu_stub/can_tcu.py)")
    p.add_argument("--no-record", dest="record", action="store_false",
                   help="no MF4 recording (to compare the memory figures with and without)")
    p.add_argument("--tracemalloc", type=int, default=1, metavar="FRAMES",
                   help="trace the Python heap with this many frames per allocation site "
                        "(1; 0: not traced)")
    p.add_argument("--quiet", action="store_true", help="no line per sample")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.priority is not None and not 0 <= args.priority <= 99:
        print("soak: error: --priority must be 0..99", file=sys.stderr)
        return 2
    if args.tracemalloc < 0:
        print("soak: error: --tracemalloc must be 0 or more frames", file=sys.stderr)
        return 2
    args.seconds = (args.minutes * 60.0 if args.minutes else (args.hours or 1.0) * 3600.0)
    if args.floor_s is None:
        args.floor_s = 30.0 if args.seconds >= 3600 else 10.0
    try:
        return run_soak(args)
    except SoakError as e:
        print(f"soak: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
