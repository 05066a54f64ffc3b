"""Coverage-guided fuzzing: libFuzzer targets for the C side, atheris targets
for the Python side (fuzz/).

    python -m rt_loop.tools.fuzz_coverage can_frame --seconds 60     # scripts/fuzz-coverage
    python -m rt_loop.tools.fuzz_coverage --all --seconds 20         # scripts/test's stage
    python -m rt_loop.tools.fuzz_coverage --all --runs 100000000 --fast --workers 2 --keep   # the long stage
    python -m rt_loop.tools.fuzz_coverage --list

The C targets are built with clang -fsanitize=fuzzer,address,undefined
straight from the C sources into build/fuzz/ (objects rebuilt when a source
or header changed). ``--fast`` runs them from a second build
(build/fuzz/fast/: -O2, UBSan without its checks of every memory access,
alignment and pointer-overflow, no ASan; 5-8 times the executions per
second), then replays every input of the grown corpus once through the
checked build, so each input that reached new code is also seen by ASan and
the full UBSan. ``--workers M`` runs M processes of a target on one corpus
(libFuzzer re-reads it for the others' finds), its runs shared among them;
``--parallel N`` N targets at once. The Python targets run under atheris in this
interpreter's environment. Each target starts from its seed corpus
(fuzz/corpus/<target>/, in the repository, written by fuzz/make_corpus.py)
and the corpus its earlier runs grew (build/fuzz/corpus/<target>/), with
its dictionary (fuzz/<target>.dict) when there is one. Printed per target:
executions, coverage (libFuzzer's cov: edges and ft: features; atheris
reports the same two counts for the Python bytecode it instruments),
corpus size and findings; out/fuzz-coverage.json holds the figures. A
crash, a sanitizer report, a leak or a timeout is a finding: its input is
kept under out/fuzz-crashes/<target>/ and the exit status is 1. Ctrl-C or
SIGTERM stops the fuzzers (their figures kept and written, exit status 130).
Every run's executions are added to build/fuzz/ledger.json: a campaign's
executions from the corpus it grows, over runs and sessions. ``--keep``
afterwards adds the grown corpus's inputs that reach coverage the
repository's folders do not (libFuzzer's -merge=1, through the checked build)
to fuzz/grown/<target>/, which every run reads beside the seeds: committed,
the next campaign on a fresh clone starts from the coverage this one reached.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import datetime
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from plant.machine import machine_info, write_figures
from plant.stop_signals import StopEvent

ROOT = Path(__file__).resolve().parents[2]
FUZZ = ROOT / "fuzz"
BUILD = ROOT / "build" / "fuzz"
OUT_JSON = ROOT / "out" / "fuzz-coverage.json"
#: set by SIGINT / SIGTERM: the running fuzzers are stopped, their figures kept, no new one starts
_STOP = StopEvent()   # set by the signal handlers: no lock (plant.stop_signals)
STOP_GRACE_S = 10.0
CRASHES = ROOT / "out" / "fuzz-crashes"

PLANT = ROOT / "plant" / "csrc"
CAN = ROOT / "can_dbc" / "csrc"
LOOP = ROOT / "rt_loop" / "csrc"
FMU = ROOT / "plant" / "fmu" / "csrc"
FMU_TABLE = BUILD / "fmu_variables.c"   # generated: the default car's parameters
#: the inputs earlier campaigns grew that reach code the seeds do not (``--keep``), in the
#: repository: a fresh clone's campaign starts from the coverage the last one reached
GROWN = FUZZ / "grown"

SAN = ["-g", "-O1", "-fno-omit-frame-pointer", "-fsanitize=address,undefined",
       "-fno-sanitize-recover=undefined"]
# the long runs' build: UBSan without the two checks of every memory access (alignment,
# pointer-overflow: 3-5x slower on the plant's arithmetic), no ASan; what it finds is
# what UBSan finds, and its corpus is replayed through SAN's build afterwards
FAST = ["-g", "-O2", "-fno-omit-frame-pointer", "-fsanitize=undefined",
        "-fno-sanitize=alignment,pointer-overflow", "-fno-sanitize-recover=undefined"]
PROFILES = {"checked": (SAN, BUILD), "fast": (FAST, BUILD / "fast")}


def _plant_sources() -> list[Path]:
    return [p for p in sorted(PLANT.glob("*.c")) if p.name != "dct_bench.c"]


# C targets: their sources besides fuzz/<name>.c, libraries
C_TARGETS = {
    "can_frame": (lambda: [CAN / "can_table.c"], []),
    "rt_prepare": (lambda: [FMU_TABLE, *_plant_sources(), CAN / "can_table.c", *sorted(LOOP.glob("*.c"))],
                   ["-lpthread"]),
    "fmu_state": (lambda: [FMU / "fmu_instance.c", FMU_TABLE, *_plant_sources()], []),
    "plant_prepare": (lambda: [FMU_TABLE, *_plant_sources()], []),
}
# Python targets: fuzz/<name>.py
PY_TARGETS = ["xcp_packet", "mapping_load", "stimulus_load", "control_request", "control_stream"]
TARGETS = [*C_TARGETS, *PY_TARGETS]
# longest input (libFuzzer's -max_len): the seeds of the table and mapping targets are long
MAX_LEN = {"rt_prepare": 65536, "mapping_load": 65536, "stimulus_load": 16384, "plant_prepare": 1024,
           "xcp_packet": 1024}

# the status lines of libFuzzer (and atheris, which is libFuzzer):
# "#1234\tpulse  cov: 56 ft: 78 corp: 9/1Kb ...", "#1234\tDONE   cov: ..."
_STATUS = re.compile(r"^#(\d+)\s+\S+\s+cov: (\d+) ft: (\d+) corp: (\d+)/")
_DONE = re.compile(r"^Done (\d+) runs in (\d+) second")
_ARTIFACT = re.compile(r"Test unit written to (\S+)")
_FINDING = re.compile(r"^(==\d+==ERROR: .*|SUMMARY: .*|.*runtime error: .*|=== Uncaught Python exception: ===|"
                      r"==\d+== ERROR: libFuzzer: .*)$")


class FuzzError(Exception):
    """A one-line reason the run cannot go on (no compiler, a build failed)."""


def _clang() -> str:
    for cc in ("clang", *(f"clang-{v}" for v in range(19, 13, -1))):
        if shutil.which(cc):
            return cc
    raise FuzzError("clang not found: scripts/fuzz-coverage installs it (apt-get install clang), "
                    "or install it yourself")


def _fmu_table() -> None:
    """fuzz targets link the FMU's generated parameter table (the default car)."""
    from plant.fmu import variables
    text = variables.generate_c()
    if not FMU_TABLE.exists() or FMU_TABLE.read_text(encoding="utf-8") != text:
        FMU_TABLE.parent.mkdir(parents=True, exist_ok=True)
        FMU_TABLE.write_text(text, encoding="utf-8")


def _newest_header(dirs) -> float:
    return max((h.stat().st_mtime for d in dirs for h in d.glob("*.h")), default=0.0)


def _compile(cc: str, flags, src: Path, obj: Path, incs, headers_mtime: float) -> None:
    if obj.exists() and obj.stat().st_mtime >= max(src.stat().st_mtime, headers_mtime):
        return
    obj.parent.mkdir(parents=True, exist_ok=True)
    cmd = [cc, *flags, "-fsanitize=fuzzer-no-link", "-D_GNU_SOURCE",
           *(f"-I{d}" for d in incs), "-c", str(src), "-o", str(obj)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise FuzzError(f"compiling {src.relative_to(ROOT)} failed: {r.stderr.strip().splitlines()[0]}")


def build(names, out=None, profile: str = "checked") -> dict[str, Path]:
    """Builds the C targets ``names`` with ``profile``'s flags (PROFILES: into
    build/fuzz/ or build/fuzz/fast/); returns their binaries."""
    names = [n for n in names if n in C_TARGETS]
    if not names:
        return {}
    flags, where = PROFILES[profile]
    cc = _clang()
    _fmu_table()
    t0 = time.monotonic()
    jobs, objs = {}, {}
    incs = [PLANT, CAN, LOOP, FMU, FUZZ]          # one set: every object serves every target
    headers = _newest_header(incs)
    for name in names:
        objs[name] = []
        for src in [FUZZ / f"{name}.c", *C_TARGETS[name][0]()]:
            obj = where / "obj" / (str(src.relative_to(ROOT)).replace("/", "__") + ".o")
            jobs[obj] = (src, incs, headers)
            objs[name].append(obj)
    with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as ex:
        for f in [ex.submit(_compile, cc, flags, src, obj, incs, h) for obj, (src, incs, h) in jobs.items()]:
            f.result()
    bins = {}
    for name in names:
        exe = where / name
        if not exe.exists() or exe.stat().st_mtime < max(o.stat().st_mtime for o in objs[name]):
            cmd = [cc, *flags, "-fsanitize=fuzzer", *map(str, objs[name]), "-lm", *C_TARGETS[name][1],
                   "-o", str(exe)]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                raise FuzzError(f"linking {name} failed: {r.stderr.strip().splitlines()[0]}")
        bins[name] = exe
    print(f"fuzz-coverage: C targets built in {where.relative_to(ROOT)}/ ({profile}, "
          f"{time.monotonic() - t0:.0f} s)", file=out or sys.stdout)
    return bins


def command(name: str, binary: Path | None, seconds: float | None, runs: int | None,
            replay: bool = False) -> list[str]:
    """The libFuzzer command line of one target (corpus folders last); ``replay``:
    every input of the corpus folders once, nothing mutated (-runs=0)."""
    work = BUILD / "corpus" / name
    work.mkdir(parents=True, exist_ok=True)
    crashes = CRASHES / name
    crashes.mkdir(parents=True, exist_ok=True)
    exe = [str(binary)] if binary else [sys.executable, str(FUZZ / f"{name}.py")]
    flags = [f"-artifact_prefix={crashes}/", "-print_final_stats=1", "-timeout=25",
             "-rss_limit_mb=4096", f"-max_len={MAX_LEN.get(name, 4096)}"]
    if replay:
        flags.append("-runs=0")
    else:
        if seconds is not None:
            flags.append(f"-max_total_time={max(1, int(round(seconds)))}")
        if runs is not None:
            flags.append(f"-runs={runs}")
    d = FUZZ / f"{name}.dict"
    if d.exists():
        flags.append(f"-dict={d}")
    return [*exe, *flags, str(work), *map(str, _kept_folders(name))]


def _kept_folders(name: str) -> list[Path]:
    """The repository's corpus folders of ``name``: its seeds, the inputs kept from
    earlier campaigns."""
    return [d for d in (FUZZ / "corpus" / name, GROWN / name) if d.is_dir()]


def keep_corpus(name: str, binary: Path | None, timeout_s: float = 3600.0) -> dict:
    """Adds to ``GROWN/name`` the inputs of the corpus this machine's runs grew
    (build/fuzz/corpus/<name>) that reach coverage the seeds and the inputs kept
    before do not: libFuzzer's ``-merge=1`` through ``binary`` (the checked build
    of a C target; None: the atheris target), which also runs every input once. A
    merge that fails is a FuzzError; the repository's folders are only added to.
    Returns {"kept": new inputs, "total": inputs in GROWN/name}."""
    work = BUILD / "corpus" / name
    grown = GROWN / name
    have = {p.name for d in _kept_folders(name) for p in d.iterdir()}
    BUILD.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=BUILD, prefix=f"merge-{name}-") as tmp:
        base = Path(tmp) / "corpus"
        base.mkdir()
        for d in _kept_folders(name):
            for f in d.iterdir():
                if f.is_file():
                    shutil.copyfile(f, base / f.name)
        exe = [str(binary)] if binary else [sys.executable, str(FUZZ / f"{name}.py")]
        cmd = [*exe, "-merge=1", f"-max_len={MAX_LEN.get(name, 4096)}", "-timeout=25",
               "-rss_limit_mb=4096", f"-artifact_prefix={tmp}/", str(base),
               *([str(work)] if work.is_dir() else [])]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise FuzzError(f"{name}: merging its corpus took more than {timeout_s:g} s") from None
        text = (p.stdout + p.stderr).strip()
        if p.returncode != 0:
            last = text.splitlines()[-1:] or ["no output"]
            raise FuzzError(f"{name}: merging its corpus failed (exit {p.returncode}): {last[0]}")
        if "MERGE-INNER" not in text:   # libFuzzer's outer process says 0 new files then
            why = next((ln for ln in text.splitlines() if "MERGE-OUTER" not in ln), "no output")
            raise FuzzError(f"{name}: merging its corpus failed: the inner process did not run ({why.strip()})")
        new = sorted(f for f in base.iterdir() if f.name not in have)
        if new:
            grown.mkdir(parents=True, exist_ok=True)
        for f in new:
            shutil.copyfile(f, grown / f.name)
    return {"kept": len(new), "total": len(list(grown.iterdir())) if grown.is_dir() else 0}


def parse(text: str) -> dict:
    """Executions, coverage and findings from a libFuzzer / atheris log."""
    res = {"executions": 0, "cov": 0, "ft": 0, "corpus": 0, "findings": [], "inputs": []}
    for line in text.splitlines():
        m = _STATUS.match(line)
        if m:
            res["executions"], res["cov"], res["ft"], res["corpus"] = map(int, m.groups())
        m = _DONE.match(line)
        if m:
            res["executions"] = int(m.group(1))
        m = re.match(r"^stat::number_of_executed_units: (\d+)", line)
        if m:
            res["executions"] = int(m.group(1))
        m = _ARTIFACT.search(line)
        if m:
            res["inputs"].append(m.group(1))
        if _FINDING.match(line) and line not in res["findings"]:
            res["findings"].append(line.strip())
    return res


def _run(name: str, cmds: list[list[str]], log: Path) -> dict:
    """Runs ``cmds`` at once (a target's workers: one corpus folder, which
    libFuzzer re-reads for what the others found), one log each; when one
    stops with a finding the others are stopped. Executions summed, coverage
    the highest, findings all of them."""
    log.parent.mkdir(parents=True, exist_ok=True)
    logs = [log] if len(cmds) == 1 else [log.with_name(f"{log.stem}.w{i}{log.suffix}")
                                          for i in range(len(cmds))]
    t0 = time.monotonic()
    env = dict(os.environ)
    env.setdefault("ASAN_OPTIONS", "detect_leaks=1")
    env.setdefault("UBSAN_OPTIONS", "print_stacktrace=1")
    files = [open(path, "w", encoding="utf-8") for path in logs]
    try:
        procs = [subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
                 for cmd, f in zip(cmds, files)]
        stopped = set()                 # the workers stopped here: not findings of their own
        grace_end = None
        try:
            while None in (running := [p.poll() for p in procs]):
                if _STOP.is_set() and grace_end is None:
                    for p in procs:     # libFuzzer prints its final figures on SIGINT
                        if p.poll() is None:
                            p.send_signal(signal.SIGINT)
                    grace_end = time.monotonic() + STOP_GRACE_S
                elif grace_end is None and any(c not in (None, 0) for c in running):
                    for i, p in enumerate(procs):
                        if p.poll() is None:
                            p.terminate()
                            stopped.add(i)
                if grace_end is not None and time.monotonic() > grace_end:
                    break
                time.sleep(0.2)
        finally:
            for i, p in enumerate(procs):
                if p.poll() is None:
                    p.kill()
                    stopped.add(i)
                p.wait()
    finally:
        for f in files:
            f.close()
    wall = time.monotonic() - t0
    interrupted = _STOP.is_set()
    if interrupted:                     # every worker was stopped by the signal, here or by the terminal
        stopped = set(range(len(procs)))
    res = {"executions": 0, "cov": 0, "ft": 0, "corpus": 0, "findings": [], "inputs": [],
           "interrupted": interrupted}
    codes = []
    for i, (path, p) in enumerate(zip(logs, procs)):
        one = parse(path.read_text(encoding="utf-8", errors="replace"))
        res["executions"] += one["executions"]
        for k in ("cov", "ft", "corpus"):
            res[k] = max(res[k], one[k])
        res["findings"] += [x for x in one["findings"] if x not in res["findings"]]
        res["inputs"] += one["inputs"]
        codes.append(0 if i in stopped and not (one["findings"] or one["inputs"]) else p.returncode)
    status = next((c for c in codes if c != 0), 0)
    res.update(seconds=round(wall, 1), exit=status, log=str(log.relative_to(ROOT)),
               exec_per_s=round(res["executions"] / wall) if wall > 0 else 0)
    if len(cmds) > 1:
        res.update(workers=len(cmds), logs=[str(x.relative_to(ROOT)) for x in logs])
        res["log"] = res["logs"][0]
    res["crashed"] = status != 0 or bool(res["inputs"])
    if res["crashed"] and not res["findings"]:
        res["findings"].append(f"exit status {status} (see {res['log']})")
    return res


def _report(res: dict) -> list[str]:
    lines = [f"      {line}" for line in res["findings"][:3]]
    return lines + [f"      input kept: {os.path.relpath(path, ROOT)}" for path in res["inputs"]]


def run_target(name: str, binary: Path | None, seconds, runs, out=None,
               checked: Path | None = None, workers: int = 1) -> dict:
    """One target's run; ``checked`` (with a fast ``binary``): afterwards every
    input of the grown corpus once through this (ASan + UBSan) build, its
    findings the run's ("replay" in the result). ``workers`` processes share
    the corpus and ``runs`` (each runs its part; ``seconds`` each)."""
    share = None if runs is None else -(-runs // workers)
    cmds = [command(name, binary, seconds, share) for _ in range(workers)]
    res = _run(name, cmds, BUILD / "logs" / f"{name}.log")
    res["kind"] = ("C (libFuzzer" + (", fast build)" if checked else ")")) if binary else "Python (atheris)"
    wall = res["seconds"]
    lines = [f"  {name:16s} {res['kind']:17s} {res['executions']:>12,d} runs {wall:7.1f} s "
             f"{res['exec_per_s']:>9,d}/s  cov {res['cov']:>5d}  ft {res['ft']:>6d}  "
             f"corpus {res['corpus']:>5d}  {'CRASH' if res['crashed'] else 'ok'}", *_report(res)]
    if res["interrupted"]:
        lines[0] = lines[0].rsplit("  ", 1)[0] + "  interrupted"
    if checked is not None and not res["crashed"] and not res["interrupted"]:
        rep = _run(name, [command(name, checked, None, None, replay=True)],
                   BUILD / "logs" / f"{name}-replay.log")
        res["replay"] = {k: rep[k] for k in ("executions", "cov", "ft", "seconds", "findings", "inputs",
                                             "exit", "log", "crashed")}
        if rep["crashed"]:
            res["crashed"] = True
            res["findings"] += rep["findings"]
            res["inputs"] += rep["inputs"]
        lines += [f"  {'':16s} {'replay (checked)':17s} {rep['executions']:>12,d} inputs "
                  f"{rep['seconds']:7.1f} s  ASan + UBSan  cov {rep['cov']:>5d}  ft {rep['ft']:>6d}  "
                  f"{'CRASH' if rep['crashed'] else 'ok'}", *_report(rep)]
    print("\n".join(lines), file=out or sys.stdout, flush=True)
    return res


def record_campaign(results: dict, build: str, workers: int, ledger: Path | None = None) -> dict:
    """Adds this run's executions per target to the campaign's ledger
    (build/fuzz/ledger.json: what the fuzzers did from the corpus they grew,
    run after run and session after session; removing the file starts a new
    campaign); returns {target: (executions in all, runs, first date)}."""
    ledger = ledger or BUILD / "ledger.json"
    try:
        book = json.loads(ledger.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        book = {}
    now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    totals = {}
    for name, r in results.items():
        kind = "atheris" if name in PY_TARGETS else build
        entry = book.setdefault(name, {"executions": 0, "runs": []})
        entry["executions"] += int(r["executions"])
        entry["runs"].append({"date": now, "executions": int(r["executions"]), "seconds": r["seconds"],
                              "build": kind, "workers": workers, "cov": r["cov"], "ft": r["ft"],
                              "findings": len(r["findings"]), "interrupted": bool(r.get("interrupted"))})
        totals[name] = (entry["executions"], len(entry["runs"]), entry["runs"][0]["date"])
    ledger.parent.mkdir(parents=True, exist_ok=True)
    tmp = ledger.with_suffix(".tmp")
    tmp.write_text(json.dumps(book, indent=1), encoding="utf-8")
    tmp.replace(ledger)
    return totals


def main(argv=None, out=None, err=None) -> int:
    out, err = out or sys.stdout, err or sys.stderr
    ap = argparse.ArgumentParser(prog="scripts/fuzz-coverage", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("targets", nargs="*", metavar="TARGET", help=f"one or more of: {', '.join(TARGETS)}")
    ap.add_argument("--all", action="store_true", help="every target")
    ap.add_argument("--seconds", type=float, help="seconds per target (default 20 without --runs)")
    ap.add_argument("--runs", type=int, help="executions per target (the long stage: 1e8 C, 1e6 Python)")
    ap.add_argument("--py-runs", type=int, help="with --runs: executions per Python target instead")
    ap.add_argument("--fast", action="store_true",
                    help="C targets from the fast build (UBSan, -O2), then their corpus replayed "
                         "through the checked one (ASan + UBSan): the long stage's runs")
    ap.add_argument("--parallel", type=int, default=1, metavar="N",
                    help="N targets at once (default 1)")
    ap.add_argument("--workers", type=int, default=1, metavar="M",
                    help="M processes per target sharing its corpus and its --runs (default 1)")
    ap.add_argument("--keep", action="store_true",
                    help=f"afterwards add the grown corpus's inputs that reach new coverage to "
                         f"{os.path.relpath(GROWN, ROOT)}/<target>/ (commit them: the next campaign starts there)")
    ap.add_argument("--build-only", action="store_true", help="build the C targets and stop")
    ap.add_argument("--list", action="store_true", help="name the targets and stop")
    ap.add_argument("--json", default=str(OUT_JSON), help="figures (default out/fuzz-coverage.json)")
    a = ap.parse_args(argv)
    if a.list:
        for n in TARGETS:
            print(f"{n:16s} {'C (libFuzzer)' if n in C_TARGETS else 'Python (atheris)'}", file=out)
        return 0
    names = TARGETS if a.all else a.targets
    unknown = [n for n in names if n not in TARGETS]
    if unknown:
        print(f"scripts/fuzz-coverage: unknown target {unknown[0]!r}: choose from {', '.join(TARGETS)}",
              file=err)
        return 2
    if not names:
        print("scripts/fuzz-coverage: name a TARGET or --all", file=err)
        return 2
    if a.seconds is not None and not a.seconds > 0:
        print(f"scripts/fuzz-coverage: --seconds {a.seconds:g}: must be a positive number", file=err)
        return 2
    if a.runs is not None and a.runs < 1:
        print(f"scripts/fuzz-coverage: --runs {a.runs}: must be at least 1", file=err)
        return 2
    for opt in ("parallel", "workers"):
        if getattr(a, opt) < 1:
            print(f"scripts/fuzz-coverage: --{opt} {getattr(a, opt)}: must be at least 1", file=err)
            return 2
    seconds = a.seconds if a.seconds is not None or a.runs is not None else 20.0
    try:
        bins = build(names, out=out)
        fast = build(names, out=out, profile="fast") if a.fast else {}
    except FuzzError as e:
        print(f"scripts/fuzz-coverage: {e}", file=err)
        return 2
    if a.build_only:
        return 0
    if any(n in PY_TARGETS for n in names):
        try:
            import atheris  # noqa: F401
        except ImportError:
            print("scripts/fuzz-coverage: atheris is not installed (the test extra: scripts/setup)",
                  file=err)
            return 2
    limit = f"{seconds:g} s" if a.runs is None else f"{a.runs:,d} runs" + (
        f" (Python {a.py_runs:,d})" if a.py_runs else "") + (f", at most {seconds:g} s" if seconds else "")
    print(f"fuzz-coverage: {len(names)} target(s), {limit} each", file=out)
    t0 = time.monotonic()

    def one(n: str) -> dict | None:
        if _STOP.is_set():
            return None
        runs = a.py_runs if (a.py_runs and n in PY_TARGETS) else a.runs
        if n in fast:
            return run_target(n, fast[n], seconds, runs, out=out, checked=bins[n], workers=a.workers)
        return run_target(n, bins.get(n), seconds, runs, out=out, workers=a.workers)

    _STOP.clear()
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            handlers[sig] = signal.signal(sig, lambda *_: _STOP.set())
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=a.parallel) as ex:
            futures = {n: ex.submit(one, n) for n in names}
            results = {n: r for n, r in ((n, f.result()) for n, f in futures.items()) if r is not None}
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)
    interrupted = _STOP.is_set()
    crashed = [n for n, r in results.items() if r["crashed"]]
    if a.keep and not interrupted:
        for n, r in results.items():
            if r["crashed"]:
                continue
            try:
                r["kept"] = keep_corpus(n, bins.get(n))
            except FuzzError as e:
                print(f"scripts/fuzz-coverage: {e}", file=err)
                r["keep_error"] = str(e)
                continue
            print(f"  {n:16s} kept: {r['kept']['kept']:,d} new input(s) in "
                  f"{os.path.relpath(GROWN / n, ROOT)} ({r['kept']['total']:,d} there)", file=out)
    campaign = record_campaign(results, "fast" if a.fast else "checked", a.workers)
    for n, r in results.items():
        r["campaign_executions"], r["campaign_runs"], r["campaign_since"] = campaign[n]
    report = {"machine": machine_info(), "seconds_per_target": seconds, "runs_per_target": a.runs,
              "py_runs_per_target": a.py_runs, "build": "fast, corpus replayed checked" if a.fast else "checked",
              "parallel": a.parallel, "workers": a.workers,
              "wall_s": round(time.monotonic() - t0, 1), "targets": results,
              "crashed": crashed, "interrupted": interrupted,
              "not_run": [n for n in names if n not in results]}
    write_figures(a.json, report)
    for n, (execs, k, since) in campaign.items():
        print(f"  {n:16s} campaign: {execs:>14,d} executions in {k} run(s) since {since[:10]} "
              "(build/fuzz/ledger.json)", file=out)
    total = sum(r["executions"] for r in results.values())
    print(f"fuzz-coverage: {total:,d} executions, {len(crashed)} target(s) with findings"
          f"{': ' + ', '.join(crashed) if crashed else ''}"
          f"{'; INTERRUPTED, not run: ' + (', '.join(report['not_run']) or 'none') if interrupted else ''}"
          f"; figures in {os.path.relpath(a.json, ROOT)}", file=out)
    keep_failed = any("keep_error" in r for r in results.values())
    return 1 if crashed else (130 if interrupted else (2 if keep_failed else 0))


if __name__ == "__main__":
    sys.exit(main())
