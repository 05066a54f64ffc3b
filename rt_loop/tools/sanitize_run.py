"""Sanitizer runs: the loop built with ThreadSanitizer or AddressSanitizer +
UndefinedBehaviorSanitizer, with everything that reads it attached at once.

    python -m rt_loop.tools.sanitize_run thread --seconds 300     # scripts/sanitize
    python -m rt_loop.tools.sanitize_run address --frames 1000000
    python -m rt_loop.tools.sanitize_run --short                  # both, about a minute

For each kind (``thread``, ``address``) this builds the four extensions
(``plant._dct_plant``, ``can_dbc._can_table``, ``rt_loop._rt_loop``,
``tcu_stub._tcu_fast``) with ``DCT_HIL_SANITIZE=<kind>`` (``plant/_build.py``)
into ``build/sanitize-<kind>/lib``, never over the working tree's, beside links
to the packages' Python files, so that a Python started with that directory
first on its path imports the instrumented extensions. Python itself is not
instrumented: the sanitizer's runtime is preloaded (``LD_PRELOAD``, the
compiler's ``libtsan.so`` or ``libasan.so``), and a child Python runs the
load:

- the plant server at 2 kHz on the embedded transport (python-can's virtual
  bus through the bridge), priority 0, real time (``--time-scale`` 1);
- the fuzz traffic of ``rt_loop.tools.fuzz`` (its ``Generator`` and
  ``Sender``: valid and extreme TCU frames, unknown identifiers, wrong
  lengths, bad CRCs and counters, restarts, remote, error and FD frames, and
  a burst beyond the rings now and then);
- the reference TCU as a C node on the same bus (``tcu_stub.c_node``: its C
  thread and bridge);
- an XCP master on UDP loopback (written here, raw packets): a DAQ list of
  16 plant doubles on the tick event, reconfigured every few seconds, and
  calibration writes (SHORT_UPLOAD then DOWNLOAD into the writable regions);
- the readers of the bench view: the scope (names added, read, removed, as
  the browser's sessions do), ``Server.snapshot`` and the statistics copy;
- an MF4 recording of every output and the CAN traffic (``record_path``);
- the control channel (``rt_loop.control``): faults injected and cleared,
  plant inputs set, values read;
- a stimulus file (CSV of the road grade and the throttle override) played
  into the loop.

Each sanitizer writes its reports to ``out/sanitize-<kind>/log.<pid>``
(``halt_on_error=0``: the run goes on after a report). The run prints the
number of reports and, per distinct report, its kind and first frame, and
writes ``out/sanitize-<kind>.json``. Exit 1 when a sanitizer reported
anything or the load did not run to its end (the loop stopped, a reader
failed), 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from plant import argtypes

__all__ = ["KINDS", "SanitizeError", "main", "parse_reports"]

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("thread", "address")
PACKAGES = ("plant", "can_dbc", "rt_loop", "tcu_stub")
RUNTIME = {"thread": "libtsan.so", "address": "libasan.so"}
#: the short runs (scripts/test): each kind 20 s of load
SHORT_SECONDS = 20.0
DAQ_SIGNALS = 16
#: the longest an XCP command may wait for its answer (a sanitizer slows the slave's
#: Python thread: every lock of the GIL goes through the runtime's interceptors)
XCP_ANSWER_S = 10.0


#: ThreadSanitizer's suppressions: Python's own code only, each with its reason.
TSAN_SUPPRESSIONS = """\
# An XCP master's UPLOAD and SHORT_UPLOAD (and the range check of a DOWNLOAD) read the
# live loop's memory as the protocol has it: polling, asynchronous to the tick (DAQ is
# the consistent path, the loop's rings). The slave's backend does it in Python
# (rt_loop/measure/xcp/loop_backend.py, bytes of an ffi.buffer), which TSan sees only
# through the memcpy in this Python function. No C of the project is in such a report.
race:PyBytes_FromStringAndSize
"""


class SanitizeError(RuntimeError):
    """The run cannot be set up (one line)."""


class _NoAnswer(Exception):
    """An XCP command without an answer in XCP_ANSWER_S."""


# --------------------------------------------------------------------------
# the build
# --------------------------------------------------------------------------

_SETUP = """
import sys
from setuptools import setup
lib, tmp = sys.argv[1], sys.argv[2]
setup(name="dct-hil-sanitize", packages=[], py_modules=[],
      cffi_modules=[m + "/_build.py:ffibuilder" for m in sys.argv[3].split(",")],
      script_args=["build_ext", "--build-lib", lib, "--build-temp", tmp])
"""


def build(kind: str, out: Any = sys.stdout) -> Path:
    """Builds the four extensions with the sanitizer of ``kind`` into
    build/sanitize-<kind>/lib (setuptools rebuilds what changed) and links the
    packages' other files beside them; returns that directory."""
    base = ROOT / "build" / f"sanitize-{kind}"
    lib, tmp = base / "lib", base / "tmp"
    lib.mkdir(parents=True, exist_ok=True)
    log = base / "build.log"
    t0 = time.monotonic()
    env = dict(os.environ, DCT_HIL_SANITIZE=kind)
    with open(log, "w", encoding="utf-8") as f:
        rc = subprocess.call([sys.executable, "-c", _SETUP, str(lib), str(tmp),
                              ",".join(PACKAGES)], cwd=ROOT, env=env, stdout=f,
                             stderr=subprocess.STDOUT)
    if rc != 0:
        raise SanitizeError(f"the {kind} build failed (exit {rc}): see {log.relative_to(ROOT)}")
    for pkg in PACKAGES:
        src, dst = ROOT / pkg, lib / pkg
        dst.mkdir(exist_ok=True)
        for entry in dst.iterdir():         # links of files since removed or renamed
            if entry.is_symlink() and not entry.exists():
                entry.unlink()
        for entry in src.iterdir():
            if entry.name == "__pycache__" or entry.name.endswith(".so"):
                continue
            link = dst / entry.name
            if not link.is_symlink() and not link.exists():
                link.symlink_to(entry)
    print(f"sanitize: {kind}: built into {lib.relative_to(ROOT)} in "
          f"{time.monotonic() - t0:.0f} s", file=out, flush=True)
    return lib


def runtime_library(kind: str) -> str:
    """The sanitizer's runtime the compiler links (preloaded into Python)."""
    cc = os.environ.get("CC", "gcc")
    try:
        path = subprocess.run([cc, f"-print-file-name={RUNTIME[kind]}"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as e:
        raise SanitizeError(f"{cc} cannot name its {RUNTIME[kind]}: {e}") from None
    if not os.path.isabs(path) or not os.path.exists(path):
        raise SanitizeError(f"{RUNTIME[kind]} is not installed ({cc} names {path!r}; Debian: "
                            f"apt-get install {'libtsan2' if kind == 'thread' else 'libasan8 libubsan1'})")
    return os.path.realpath(path)


def sanitizer_env(kind: str, lib: Path, logdir: Path) -> dict:
    """The child's environment: the build first on the path, the runtime preloaded,
    the sanitizer's options."""
    log = str(logdir / "log")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(lib)] + ([env["PYTHONPATH"]]
                                                      if env.get("PYTHONPATH") else []))
    env["LD_PRELOAD"] = runtime_library(kind)
    if kind == "thread":
        # halt_on_error=0: every report of the run, not only the first; the history of
        # each thread deep enough for the second stack of a race in a 2 kHz loop
        # exitcode=0: the reports are counted from the logs, not by the exit status
        supp = logdir / "tsan.supp"
        supp.write_text(TSAN_SUPPRESSIONS, encoding="ascii")
        env["TSAN_OPTIONS"] = f"halt_on_error=0 exitcode=0 log_path={log} history_size=4 " \
                              f"second_deadlock_stack=1 suppressions={supp}"
    else:
        # detect_leaks=0: Python keeps its objects until exit by design (interned
        # strings, modules), which LeakSanitizer would report by the thousand;
        # halt_on_error=0 goes on after an error (the build has -fsanitize-recover=address)
        env["ASAN_OPTIONS"] = f"halt_on_error=0 detect_leaks=0 log_path={log}"
        env["UBSAN_OPTIONS"] = f"halt_on_error=0 print_stacktrace=1 log_path={log}"
    return env


# --------------------------------------------------------------------------
# the reports
# --------------------------------------------------------------------------

_TSAN_HEAD = re.compile(r"WARNING: ThreadSanitizer: (.+?)(?: \(pid=\d+\))?$")
_ASAN_HEAD = re.compile(r"ERROR: AddressSanitizer: (\S+)")
_UBSAN_HEAD = re.compile(r"^(\S+:\d+:\d+): runtime error: (.+)$")
_FRAME = re.compile(r"^\s*#(\d+) (?:0x[0-9a-f]+ )?(?:in )?(.+)$")


def parse_reports(text: str) -> list[dict]:
    """The sanitizer reports in a log's text: {kind, what, first_frame}."""
    reports: list[dict] = []
    current: dict | None = None
    for line in text.splitlines():
        m = _TSAN_HEAD.search(line) or _ASAN_HEAD.search(line)
        if m:
            current = {"sanitizer": "TSan" if "Thread" in line else "ASan",
                       "what": m.group(1).strip(), "first_frame": None}
            reports.append(current)
            continue
        m = _UBSAN_HEAD.match(line.strip())
        if m:
            current = {"sanitizer": "UBSan", "what": m.group(2).strip(),
                       "first_frame": m.group(1)}
            reports.append(current)
            continue
        if current is not None and current["first_frame"] is None:
            f = _FRAME.match(line)
            if f:
                current["first_frame"] = f.group(2).strip()
    return reports


def summarize(reports: list[dict]) -> list[dict]:
    """Distinct reports (sanitizer, what, first frame) with how often each came."""
    seen: dict[tuple, dict] = {}
    for r in reports:
        key = (r["sanitizer"], r["what"], r["first_frame"])
        if key not in seen:
            seen[key] = {**r, "count": 0}
        seen[key]["count"] += 1
    return sorted(seen.values(), key=lambda r: -r["count"])


# --------------------------------------------------------------------------
# one run of one kind
# --------------------------------------------------------------------------

def run_kind(kind: str, args: argparse.Namespace, out: Any = sys.stdout) -> dict:
    lib = build(kind, out)
    outdir = ROOT / "out" / f"sanitize-{kind}"
    if outdir.exists():
        shutil.rmtree(outdir)
    outdir.mkdir(parents=True)
    env = sanitizer_env(kind, lib, outdir)
    load_json = outdir / "load.json"
    cmd = [sys.executable, "-P", "-m", "rt_loop.tools.sanitize_run", "--load", kind,
           "--load-json", str(load_json), "--seed", str(args.seed)]
    if args.seconds:
        cmd += ["--seconds", repr(args.seconds)]
    if args.frames:
        cmd += ["--frames", str(args.frames)]
    length = " or ".join(([f"{args.seconds:g} s"] if args.seconds else [])
                         + ([f"{args.frames} frames"] if args.frames else []))
    print(f"sanitize: {kind}: the load under {os.path.basename(env['LD_PRELOAD'])} ({length})",
          file=out, flush=True)
    t0 = time.monotonic()
    rc = subprocess.call(cmd, cwd=outdir, env=env)
    wall = time.monotonic() - t0
    text = ""
    logs = sorted(outdir.glob("log.*"))
    for p in logs:
        text += p.read_text(encoding="utf-8", errors="replace")
    reports = parse_reports(text)
    distinct = summarize(reports)
    try:
        load = json.loads(load_json.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        load = {"failures": [f"the load wrote no figures (exit {rc})"]}
    failures = list(load.get("failures", []))
    if rc != 0 and not failures:
        failures.append(f"the load exited {rc}")
    result = {
        "kind": kind, "sanitizers": "ThreadSanitizer" if kind == "thread"
        else "AddressSanitizer + UndefinedBehaviorSanitizer",
        "reports": len(reports), "distinct": distinct,
        "logs": [str(p.relative_to(ROOT)) for p in logs],
        "wall_s": round(wall, 1), "exit": rc, "load": load, "failures": failures,
        "passed": not reports and not failures,
    }
    return result


def format_result(r: dict) -> str:
    ld = r["load"]
    lines = [f"sanitize {r['kind']} ({r['sanitizers']}): {r['reports']} reports, "
             f"{len(r['distinct'])} distinct; {r['wall_s']:.0f} s"]
    if "frames_sent" in ld:
        lines.append(
            f"  load {ld['duration_s']:.0f} s: {ld['ticks']:,} ticks, {ld['overruns']} overruns; "
            f"{ld['frames_sent']:,} fuzz frames ({ld['frames_taken']:,} taken in); "
            f"DAQ {ld['xcp']['dtos']:,} DTOs, {ld['xcp']['daq_setups']} set-ups, "
            f"{ld['xcp']['lost_answers']} answers lost; "
            f"{ld['xcp']['cal_writes']:,} calibration writes; "
            f"scope {ld['readers']['scope_reads']:,} reads, captures "
            f"{ld['readers']['captures']:,} ({ld['readers']['capture_rows']:,} rows), snapshots "
            f"{ld['readers']['snapshots']:,}; control {ld['control']['requests']:,} requests, "
            f"{ld['control']['faults_injected']:,} faults; recorded "
            f"{ld['recording']['samples']:,} samples ({ld['recording']['mf4_mb']:.1f} MB); "
            f"stimulus {ld['stimulus']['written']} writes; TCU node "
            f"{ld['tcu']['ticks']:,} periods")
    for d in r["distinct"]:
        lines.append(f"  {d['count']:5d} x {d['sanitizer']} {d['what']}: {d['first_frame']}")
    for f in r["failures"]:
        lines.append(f"  FAIL {f}")
    lines.append(f"sanitize {r['kind']}: {'PASS' if r['passed'] else 'FAIL'}")
    return "\n".join(lines)


# --------------------------------------------------------------------------
# the load (the child: the instrumented extensions, the runtime preloaded)
# --------------------------------------------------------------------------

class _Readers:
    """The threads attached to the loop beside the fuzz traffic; each counts what
    it did and keeps its first error (a failure of the run)."""

    def __init__(self, server: Any, control_path: str, stop: Any, seed: int) -> None:
        import random

        self.server, self.control_path, self.stop = server, control_path, stop
        self.rng = random.Random(seed)
        self.errors: list[str] = []
        self.xcp = {"dtos": 0, "daq_setups": 0, "cal_writes": 0, "cal_refused": 0,
                    "commands": 0, "answer_max_s": 0.0, "lost_answers": 0}
        self.readers = {"scope_reads": 0, "scope_changes": 0, "snapshots": 0, "stats_reads": 0,
                        "tcu_figures": 0, "captures": 0, "capture_rows": 0}
        self.control = {"requests": 0, "faults_injected": 0, "faults_refused": 0, "sets": 0}
        self.threads: list[Any] = []
        self.tcu: Any = None                   # the C TCU node, once it runs

    def start(self) -> None:
        import threading

        for name, fn in (("xcp", self._xcp), ("scope", self._scope), ("control", self._control),
                         ("capture", self._capture)):
            t = threading.Thread(target=self._guard, args=(name, fn), name=f"sanitize-{name}",
                                 daemon=True)
            t.start()
            self.threads.append(t)

    def join(self) -> None:
        for t in self.threads:
            t.join(timeout=30)
            if t.is_alive():
                self.errors.append(f"{t.name} did not end")

    def _guard(self, name: str, fn: Any) -> None:
        try:
            fn()
        except Exception as e:  # one line into the figures: the run fails
            self.errors.append(f"{name}: {type(e).__name__}: {' '.join(str(e).split())}")

    # -- the XCP master: raw packets on UDP loopback
    def _xcp(self) -> None:
        import socket
        import struct

        from rt_loop.measure.xcp import a2l
        from rt_loop.measure.xcp import protocol as P
        from rt_loop.tools.xcp_bench import measurable_doubles

        srv = self.server
        ffi, lib = srv._ffi, srv._lib
        signals = measurable_doubles(ffi, DAQ_SIGNALS)
        regions = [r for r in a2l.calibration_regions(ffi, lib)
                   if r[6] == "double" and r[1] == 8 and str(r[3]).startswith("params.")]
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.connect(tuple(srv.xcp.address[:2]))
        ctr = 0

        def packets(timeout: float) -> list[bytes]:
            sock.settimeout(timeout)
            try:
                data = sock.recv(65536)
            except TimeoutError:
                return []
            out, i = [], 0
            while i + 4 <= len(data):
                n, _ = struct.unpack_from("<HH", data, i)
                out.append(data[i + 4:i + 4 + n])
                i += 4 + n
            return out

        def command(*packet: int | bytes) -> bytes:
            nonlocal ctr
            body = b"".join(bytes([p]) if isinstance(p, int) else p for p in packet)
            sock.send(struct.pack("<HH", len(body), ctr & 0xFFFF) + body)
            ctr += 1
            self.xcp["commands"] += 1
            t = time.monotonic()
            while time.monotonic() < t + XCP_ANSWER_S:
                for r in packets(0.5):
                    if r and r[0] in (P.PID_RES, P.PID_ERR):
                        wait = time.monotonic() - t
                        self.xcp["answer_max_s"] = max(self.xcp["answer_max_s"], round(wait, 3))
                        return r
                    self.xcp["dtos"] += 1
            raise _NoAnswer(f"no answer to XCP command 0x{packet[0]:02X} in {XCP_ANSWER_S:g} s")

        def positive(*packet: int | bytes) -> bytes:
            r = command(*packet)
            if r[0] != P.PID_RES:
                raise RuntimeError(f"XCP command 0x{packet[0]:02X} refused: {r.hex()}")
            return r

        def setup_daq() -> None:
            chosen = self.rng.sample(signals, k=self.rng.randrange(1, len(signals) + 1))
            positive(P.FREE_DAQ)
            positive(P.ALLOC_DAQ, 0, 1, 0)
            positive(P.ALLOC_ODT, 0, 0, 0, 1)
            positive(P.ALLOC_ODT_ENTRY, 0, 0, 0, 0, len(chosen))
            positive(P.SET_DAQ_PTR, 0, 0, 0, 0, 0)
            for _name, off in chosen:
                positive(P.WRITE_DAQ, 0xFF, 8, 0, struct.pack("<I", off))
            # every second tick: what a master on a loaded machine keeps up with
            positive(P.SET_DAQ_LIST_MODE, 0, 0, 0, 0, 0, 2, 0)
            positive(P.START_STOP_DAQ_LIST, 1, 0, 0)
            self.xcp["daq_setups"] += 1

        def session() -> None:
            positive(P.CONNECT, 0)
            setup_daq()
            next_setup = time.monotonic() + 3.0
            while not self.stop.is_set():
                for _ in range(20):                  # the DTOs of about 10 ms
                    self.xcp["dtos"] += len(packets(0.001))
                if regions:
                    off, _size, _kind, _name, lo, hi, _ct = self.rng.choice(regions)
                    old = positive(P.SHORT_UPLOAD, 8, 0, 0, struct.pack("<I", off))[1:9]
                    positive(P.SET_MTA, 0, 0, 0, struct.pack("<I", off))
                    r = command(P.DOWNLOAD, 8, old)  # the value it had: the plant unchanged
                    self.xcp["cal_writes" if r[0] == P.PID_RES else "cal_refused"] += 1
                if time.monotonic() >= next_setup:   # a new DAQ configuration for the loop
                    positive(P.START_STOP_DAQ_LIST, 0, 0, 0)
                    setup_daq()
                    next_setup = time.monotonic() + 3.0

        # an answer lost on UDP (a datagram the kernel dropped while this thread waited
        # for the GIL): a master connects again and sets its DAQ up anew, as a bench's
        # does; three in a row fail the run
        lost_in_a_row = 0
        while not self.stop.is_set():
            try:
                session()
                lost_in_a_row = 0
            except _NoAnswer as e:
                self.xcp["lost_answers"] += 1
                lost_in_a_row += 1
                if lost_in_a_row >= 3:
                    raise RuntimeError(f"{e}, three sessions in a row") from None
        positive(P.START_STOP_DAQ_LIST, 0, 0, 0)
        positive(P.DISCONNECT)
        sock.close()

    # -- the bench view's readers: the scope, the snapshot, the statistics
    def _scope(self) -> None:
        srv = self.server
        scope = srv.scope
        names = [n for n in ("vehicle_speed_kmh", "engine_speed_rpm", "turnaround_us",
                             "exec_us", "inputs.road_grade_pct", "maneuver_time_s")
                 if n in scope.traceable()]
        extra = [n for n in scope.traceable() if n.startswith("cmd.")][:4]
        scope.add(names)
        traced, since = list(names), None
        next_change = time.monotonic() + 1.0
        while not self.stop.wait(0.02):
            d = scope.read(traced, since_tick=since)
            if len(d["tick"]):
                since = int(d["tick"][-1])
            self.readers["scope_reads"] += 1
            srv.snapshot()
            self.readers["snapshots"] += 1
            with srv._read_lock:
                srv.stats.read()
            self.readers["stats_reads"] += 1
            if self.tcu is not None:             # the TCU node's figures, as the demo reads them
                self.tcu.figures()
                self.readers["tcu_figures"] += 1
            if time.monotonic() >= next_change and extra:  # a session opens or closes
                if len(traced) > len(names):
                    scope.remove(extra)
                    traced = list(names)
                else:
                    scope.add(extra)
                    traced = names + extra
                self.readers["scope_changes"] += 1
                next_change = time.monotonic() + 1.0
        scope.remove(traced)

    # -- captures: armed, triggered, fetched and cleared one after the other, two at once
    def _capture(self) -> None:
        caps = self.server.capture_manager()
        names = ["vehicle_speed_kmh", "engine_speed_rpm", "exec_us", "inputs.road_grade_pct"]
        while not self.stop.is_set():
            a = caps.start(names, duration_s=0.3)
            b = caps.start(names[:2], every_s=self.server.step_s * 4, start_when="time_s > 0",
                           pre_s=0.1, duration_s=0.2)
            for cid in (a, b):
                while caps.status(cid)["state"] != "done" and not self.stop.wait(0.02):
                    pass
                self.readers["capture_rows"] += len(caps.fetch(cid)["tick"])
                caps.clear(cid)
                self.readers["captures"] += 1

    # -- the control channel: faults injected and cleared, inputs set, values read
    def _control(self) -> None:
        from rt_loop.control import ControlClient, ControlError

        specs = [
            {"kind": "can.omit", "message": "DCT_ShaftSpeeds", "duration_s": 0.2},
            {"kind": "can.bad_crc", "message": "DCT_ShaftSpeeds"},
            {"kind": "can.freeze_counter", "message": "DCT_ShaftSpeeds"},
            {"kind": "can.late", "message": "DCT_ShaftSpeeds", "delay_ms": 15},
            {"kind": "can.too_often", "message": "DCT_ShaftSpeeds", "factor": 5},
            {"kind": "can.length", "message": "DCT_ShaftSpeeds", "length": 3},
            {"kind": "can.bus_off", "duration_s": 0.05},
            {"kind": "signal.value", "signal": "DCT_ShaftSpeeds.EngineSpeed", "value": 7000},
            {"kind": "signal.noise", "signal": "DCT_ShaftSpeeds.EngineSpeed", "sigma": 50},
            {"kind": "signal.invalid", "signal": "DCT_ShaftSpeeds.EngineSpeed"},
            {"kind": "valve.spool_stuck", "clutch": 1},
            {"kind": "clutch.friction_fade", "clutch": 2, "loss": 0.3},
            {"kind": "hydraulics.line_pressure_loss", "loss": 0.5},
            {"kind": "fork.jammed", "sleeve": "1-3"},
            {"kind": "sync.blocker_failed", "sleeve": "2-4"},
            {"kind": "engine.torque_limit", "max_nm": 50},
        ]
        with ControlClient(self.control_path) as c:
            while not self.stop.wait(0.05):
                spec = self.rng.choice(specs)
                try:
                    fid = c.request("inject", spec=spec)["id"]
                    self.control["faults_injected"] += 1
                except ControlError as e:
                    self.control["faults_refused"] += 1
                    if self.control["faults_refused"] == 1:
                        self.errors.append(f"control: a fault refused: {e}")
                    fid = None
                c.request("set", name="road_grade_pct", value=self.rng.uniform(-5, 5))
                self.control["sets"] += 1
                c.request("read", names=["vehicle_speed_kmh", "gear", "time_s"])
                c.request("faults")
                if fid is not None and self.rng.random() < 0.5:
                    c.request("clear", id=fid)
                else:
                    c.request("clear_all")
                self.control["requests"] += 5
            c.request("clear_all")


def _stimulus_csv(path: Path, seconds: float) -> None:
    """The road grade and the throttle override in steps every half second."""
    with open(path, "w", encoding="ascii") as f:
        f.write("time_s,road_grade_pct,override.accel_pedal_pct\n")
        for i in range(int(seconds * 2) + 2):
            f.write(f"{i * 0.5:.1f},{(i % 7) - 3},{(i * 13) % 60}\n")


def run_load(args: argparse.Namespace) -> dict:
    """The load of one run (in the child): the figures, with ``failures``."""
    import threading
    import uuid

    from rt_loop.server import Server
    from rt_loop.tools.fuzz import IN_FLIGHT_MAX, Generator, Sender, _seen
    from tcu_stub.c_node import CTcuNode

    here = Path.cwd()
    channel = f"dct-hil-sanitize-{uuid.uuid4().hex[:8]}"
    seconds = args.seconds or 0.0
    stim = here / "stimulus.csv"
    _stimulus_csv(stim, (seconds or 3600.0) + 60.0)
    control = f"/tmp/dct-hil-sanitize-{os.getpid()}.sock"
    mf4 = here / "run.mf4"
    failures: list[str] = []
    server = Server(channel, interface="virtual", priority=0, pm_qos_us=None,
                    xcp=("127.0.0.1", 0), record_path=mf4, control_path=control,
                    stimulus_path=stim)
    stop = threading.Event()
    t_setup = time.monotonic()
    server.start()
    tcu = CTcuNode.open("virtual", channel, priority=0)
    readers = _Readers(server, control, stop, args.seed)
    readers.tcu = tcu
    readers.start()
    gen = Generator(args.seed, "embedded", fd_allowed=True)
    sender = Sender("embedded", channel, True)
    sent = 0
    next_check, next_burst = 0, 200_000
    t0 = time.monotonic()
    print(f"sanitize: load set up in {t0 - t_setup:.0f} s", flush=True)
    next_progress = t0 + 30.0
    deadline = t0 + seconds if seconds else None
    try:
        while server.running:
            if args.frames and sent >= args.frames:
                break
            if deadline is not None and time.monotonic() >= deadline:
                break
            if sent >= next_check:
                sender.drain()
                while (sent - _seen(server.snapshot()["counts"]) > IN_FLIGHT_MAX
                       and server.running):
                    time.sleep(0.0005)
                    sender.drain()
                next_check = sent + 1000
            frames = gen.burst(20_000) if sent >= next_burst else gen.event()
            if sent >= next_burst:
                next_burst += 200_000
            for f in frames:
                sent += bool(sender.send(f))
            if readers.errors:
                break
            if time.monotonic() >= next_progress:
                print(f"sanitize: {time.monotonic() - t0:.0f} s: {sent:,} frames, "
                      f"{server.snapshot()['counts'].get('ticks', 0):,} ticks, "
                      f"{readers.xcp['dtos']:,} DTOs", flush=True)
                next_progress += 30.0
    finally:
        stop.set()
        readers.join()
        running_at_end = server.running
        tcu_ticks = int(tcu.figures().ticks)
        tcu.close()
        sender.close()
        player = server.player.counters() if server.player is not None else {}
        server.stop()
    wall = time.monotonic() - t0
    report = server.report(histograms=False)
    c = report["counts"]
    if not running_at_end:
        failures.append(f"the loop was not running at the end: {report['run']['error']}")
    failures += readers.errors
    rec = c.get("record") or {}
    return {
        "duration_s": round(wall, 1), "ticks": int(report["run"]["ticks"]),
        "overruns": int(c["overruns"]), "frames_sent": sent,
        "frames_taken": _seen(c), "rx": {k: int(v) for k, v in c["rx"].items()
                                         if isinstance(v, int | float)},
        "xcp": readers.xcp, "readers": readers.readers, "control": readers.control,
        "recording": {"samples": int(rec.get("written", 0)),
                      "mf4_mb": mf4.stat().st_size / 1e6 if mf4.exists() else 0.0},
        "stimulus": {"written": int(player.get("applied", 0) or 0), **player},
        "tcu": {"ticks": tcu_ticks},
        "failures": failures,
    }


def _load(args: argparse.Namespace) -> int:
    try:
        figures = run_load(args)
    except Exception as e:  # one line into the figures
        figures = {"failures": [f"the load failed: {type(e).__name__}: {' '.join(str(e).split())}"]}
    with open(args.load_json, "w", encoding="utf-8") as f:
        json.dump(figures, f, indent=1, default=str)
    return 0 if not figures["failures"] else 1


# --------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scripts/sanitize", description=__doc__.split("\n\n")[0])
    p.add_argument("kind", nargs="?", choices=KINDS,
                   help="thread (TSan) or address (ASan + UBSan); default both")
    p.add_argument("--seconds", type=argtypes.positive, default=None, metavar="S",
                   help="load for S seconds (with --frames: whichever comes first)")
    p.add_argument("--frames", type=argtypes.count, default=None, metavar="N",
                   help="fuzz frames to send (default 60 s of load unless --seconds)")
    p.add_argument("--short", action="store_true",
                   help=f"both kinds, {SHORT_SECONDS:g} s of load each (scripts/test)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", default=None, metavar="FILE",
                   help="figures (default out/sanitize-<kind>.json)")
    p.add_argument("--load", choices=KINDS, help=argparse.SUPPRESS)
    p.add_argument("--load-json", help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.load:
        return _load(args)
    if args.short:
        if args.seconds or args.frames:
            print("sanitize: error: --short sets the length itself (no --seconds or --frames)",
                  file=sys.stderr)
            return 2
        args.seconds = SHORT_SECONDS
    if not args.seconds and not args.frames:
        args.seconds = 60.0
    if args.json and not args.kind:
        print("sanitize: error: --json names one file: give one kind", file=sys.stderr)
        return 2
    from plant.machine import write_figures

    passed = True
    for kind in [args.kind] if args.kind else list(KINDS):
        try:
            r = run_kind(kind, args)
        except SanitizeError as e:
            print(f"sanitize: error: {e}", file=sys.stderr)
            return 1
        print(format_result(r), flush=True)
        path = args.json or f"out/sanitize-{kind}.json"
        write_figures(str(ROOT / path) if not os.path.isabs(path) else path, r, indent=1)
        passed = passed and r["passed"]
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
