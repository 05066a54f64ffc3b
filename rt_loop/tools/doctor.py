"""``dct-hil doctor``: how ready this PC is for the 2 kHz SCHED_FIFO loop.

    report = run_doctor(cpu=1, channel="can0", floor_s=10)
    print(report.text())          # findings by severity, then the fixes
    report.to_dict()              # the same for --json
    report.exit_code              # 1 when an item is "fail", else 0

Every item gets a verdict (``ok``, ``warn``, ``fail``, ``info``), a one-line
finding with the numbers it rests on, and, when it is not ok, a one-line fix
(the command or boot option). A file that cannot be read or makes no sense
turns its item into "unknown: <why>" (a warning), never an exception.

Everything is read below ``root`` ("/" normally), so the tests build a fake
/proc and /sys; ``ip_link`` (iproute2's JSON for an interface) and
``measure`` (``rt_loop.floor.measure_floor``) can be replaced the same way.
"""

from __future__ import annotations

import errno
import gzip
import json
import math
import os
import platform
import re
import shutil
import subprocess
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "DoctorError",
    "IDLE_EXIT_LATENCY_LIMIT_US",
    "Item",
    "Report",
    "VERDICTS",
    "format_cpulist",
    "parse_cpulist",
    "run_doctor",
]

#: verdicts, most severe first (the order of the report)
VERDICTS = ("fail", "warn", "info", "ok")

#: An enabled idle state that takes longer than this to leave is a warning.
#: The loop wakes every 500 us and its turnaround target is 35 us at p99.9;
#: a CPU that idles between two ticks pays the exit latency of the state it
#: chose on every wake-up. Halt-like states (POLL, C1, a VM's haltpoll) leave
#: in 0-2 us, C1E in about 10 us; from C3/C6 on (caches flushed, the core
#: powered down) it is 30 to several hundred us, which alone would use up the
#: loop's budget.
IDLE_EXIT_LATENCY_LIMIT_US = 10

#: the floor is good enough when its p99.9 with PM QoS stays under this
FLOOR_P99_9_LIMIT_US = 100.0

#: what one tick of the loop itself costs, on top of its early wake-up (the
#: measured median is about 4 us; generous so RT throttling is judged safely)
LOOP_TICK_WORK_US = 10.0

#: a real CAN adapter's transmit queue below this drops frames in bursts
CAN_TXQUEUELEN_MIN = 1000

ARPHRD_CAN = 280
CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
#: the kernel's "no PM QoS constraint" value
PM_QOS_NO_CONSTRAINT_US = 2_000_000_000

PREEMPT_MODES = ("none", "voluntary", "full", "lazy")
_MODE_LABEL = {"rt": "PREEMPT_RT", "full": "full", "lazy": "lazy", "voluntary": "voluntary",
               "none": "none"}
_CONFIG_MODE = (("CONFIG_PREEMPT_RT", "rt"), ("CONFIG_PREEMPT", "full"),
                ("CONFIG_PREEMPT_LAZY", "lazy"), ("CONFIG_PREEMPT_VOLUNTARY", "voluntary"),
                ("CONFIG_PREEMPT_NONE", "none"))


class DoctorError(ValueError):
    """Arguments the doctor cannot work with (one line)."""


class _Unreadable(Exception):
    """A file that could not be read; ``str()`` names it and why."""

    def __init__(self, why: str, err: int | None = None) -> None:
        super().__init__(why)
        self.errno = err


@dataclass
class Item:
    key: str
    title: str
    verdict: str
    finding: str
    fix: str | None = None
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"key": self.key, "title": self.title, "verdict": self.verdict,
                "finding": self.finding, "fix": self.fix, "details": self.details}


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


# --------------------------------------------------------------------------
# CPU lists (the kernel's "0-3,8,10-11" format)
# --------------------------------------------------------------------------

def _cpu_number(text: str, last_cpu: int | None) -> int:
    text = text.strip()
    if text == "N":
        if last_cpu is None:
            raise ValueError("'N' (the last CPU) with the CPU count unknown")
        return last_cpu
    if not text.isdigit():
        raise ValueError(f"{text!r} is not a CPU number")
    return int(text)


def parse_cpulist(text: str, last_cpu: int | None = None) -> set[int]:
    """The CPUs of a kernel CPU list ("0-3,8", "1-N", "0-7:2/4", "" or "(null)").
    ValueError for anything else."""
    text = text.strip()
    cpus: set[int] = set()
    if text in ("", "(null)"):
        return cpus
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise ValueError(f"empty entry in CPU list {text!r}")
        span, colon, group = part.partition(":")
        lo_text, dash, hi_text = span.partition("-")
        lo = _cpu_number(lo_text, last_cpu)
        hi = _cpu_number(hi_text, last_cpu) if dash else lo
        if hi < lo or hi - lo > 65536:
            raise ValueError(f"bad CPU range {span!r}")
        used, size = 1, 1
        if colon:
            used_text, _, size_text = group.partition("/")
            if not (used_text.isdigit() and size_text.isdigit()) or int(size_text) == 0:
                raise ValueError(f"bad CPU group {group!r}")
            used, size = int(used_text), int(size_text)
        cpus.update(c for c in range(lo, hi + 1) if (c - lo) % size < used)
    return cpus


def format_cpulist(cpus: Any) -> str:
    """"0-3,8" for {0, 1, 2, 3, 8}; "none" for an empty set."""
    cpus = sorted(set(cpus))
    if not cpus:
        return "none"
    parts = []
    start = prev = cpus[0]
    for c in cpus[1:] + [None]:
        if c is not None and c == prev + 1:
            prev = c
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if c is not None:
            start = prev = c
    return ",".join(parts)


def _cpu_word(cpus: Any) -> str:
    cpus = set(cpus)
    return ("CPU " if len(cpus) == 1 else "CPUs ") + format_cpulist(cpus)


# --------------------------------------------------------------------------
# the files, below a root
# --------------------------------------------------------------------------

class _Tree:
    """Reads files below ``root``; messages name the path as seen from it."""

    def __init__(self, root: str) -> None:
        self.root = os.path.realpath(root)

    def host(self, path: str) -> str:
        return os.path.join(self.root, path.lstrip("/"))

    def virtual(self, host_path: str) -> str:
        rel = os.path.relpath(host_path, self.root)
        return "/" + ("" if rel == "." else rel)

    def read_bytes(self, path: str, limit: int = 4 << 20) -> bytes:
        """Up to ``limit`` bytes, read in 64 KiB pieces (procfs refuses huge reads)."""
        chunks = []
        size = 0
        try:
            with open(self.host(path), "rb", buffering=0) as f:
                while size < limit:
                    chunk = f.read(min(65536, limit - size))
                    if not chunk:
                        break
                    chunks.append(chunk)
                    size += len(chunk)
        except OSError as e:
            raise _Unreadable(f"{path}: {e.strerror or e}", e.errno) from None
        return b"".join(chunks)

    def read(self, path: str) -> str:
        return self.read_bytes(path).decode("utf-8", "replace")

    def get(self, path: str) -> tuple[str | None, _Unreadable | None]:
        try:
            return self.read(path), None
        except _Unreadable as e:
            return None, e

    def exists(self, path: str) -> bool:
        return os.path.exists(self.host(path))

    def isdir(self, path: str) -> bool:
        return os.path.isdir(self.host(path))

    def listdir(self, path: str) -> list[str]:
        try:
            return sorted(os.listdir(self.host(path)))
        except OSError:
            return []


def _int_of(text: str, path: str) -> int:
    value = text.strip()
    try:
        return int(value, 0) if value.startswith("0x") else int(value)
    except ValueError:
        raise _Unreadable(f"{path}: {value[:40]!r} is not a number") from None


class _Context:
    """What several items share: options, the command line, CPUs, rights."""

    def __init__(self, tree: _Tree, cpu: int | None, channel: str | None, priority: int,
                 rate_hz: float, ip_link: Callable[[str], Any] | None) -> None:
        self.tree = tree
        self.cpu = cpu
        self.channel = channel
        self.priority = priority
        self.rate_hz = rate_hz
        self.period_us = 1e6 / rate_hz
        self.ip_link = ip_link
        self.cmdline, self.cmdline_error = self._cmdline()
        self.online, self.online_error = self._online()
        self.last_cpu = max(self.online) if self.online else None
        self.euid, self.cap_eff, self.status_error = self._status()
        self.limits, self.limits_error = self._limits()
        self._config: tuple[dict | None, str | None, str | None] | None = None
        self.isolated: set[int] = set()

    # -- /proc/cmdline: {key: value} (the last of each; flags map to "")
    def _cmdline(self) -> tuple[dict[str, str], str | None]:
        text, err = self.tree.get("/proc/cmdline")
        if text is None:
            return {}, str(err)
        out: dict[str, str] = {}
        for word in text.split():
            if word == "--":
                break           # the rest goes to init
            key, _, value = word.partition("=")
            out[key] = value
        return out, None

    def _online(self) -> tuple[set[int], str | None]:
        text, err = self.tree.get("/sys/devices/system/cpu/online")
        if text is not None:
            try:
                cpus = parse_cpulist(text)
                if cpus:
                    return cpus, None
            except ValueError as e:
                err = _Unreadable(f"/sys/devices/system/cpu/online: {e}")
        found = {int(name[3:]) for name in self.tree.listdir("/sys/devices/system/cpu")
                 if name.startswith("cpu") and name[3:].isdigit()}
        return found, (None if found else str(err))

    def _status(self) -> tuple[int | None, int | None, str | None]:
        text, err = self.tree.get("/proc/self/status")
        if text is None:
            return None, None, str(err)
        euid = cap = None
        for line in text.splitlines():
            key, _, value = line.partition(":")
            fields = value.split()
            try:
                if key == "Uid" and len(fields) >= 2:
                    euid = int(fields[1])
                elif key == "CapEff" and fields:
                    cap = int(fields[0], 16)
            except ValueError:
                return None, None, f"/proc/self/status: garbled {key} line"
        if euid is None and cap is None:
            return None, None, "/proc/self/status: no Uid or CapEff line"
        return euid, cap, None

    def _limits(self) -> tuple[dict[str, tuple[int | None, int | None]], str | None]:
        """{"Max locked memory": (soft, hard), ...}; None is unlimited."""
        text, err = self.tree.get("/proc/self/limits")
        if text is None:
            return {}, str(err)
        out = {}
        for line in text.splitlines():
            m = re.match(r"(Max [a-z ]+?)\s{2,}(\S+)\s+(\S+)", line)
            if not m:
                continue
            values = []
            for v in m.group(2, 3):
                if v == "unlimited":
                    values.append(None)
                elif v.isdigit():
                    values.append(int(v))
                else:
                    break
            if len(values) == 2:
                out[m.group(1)] = (values[0], values[1])
        return out, (None if out else "/proc/self/limits: no limits found")

    def has_cap(self, bit: int) -> bool | None:
        return None if self.cap_eff is None else bool(self.cap_eff >> bit & 1)

    def config(self) -> tuple[dict | None, str | None, str | None]:
        """(the kernel config {CONFIG_X: value}, where it came from, why not)."""
        if self._config is None:
            self._config = self._read_config()
        return self._config

    def _read_config(self) -> tuple[dict | None, str | None, str | None]:
        why = []
        try:
            raw = self.tree.read_bytes("/proc/config.gz", limit=16 << 20)
            try:
                return _parse_config(gzip.decompress(raw).decode("utf-8", "replace")), \
                    "/proc/config.gz", None
            except (OSError, EOFError, zlib.error) as e:
                why.append(f"/proc/config.gz: not gzip data ({_one_line(e)})")
        except _Unreadable as e:
            why.append(str(e))
        release, err = self.tree.get("/proc/sys/kernel/osrelease")
        if release is None or not release.strip() or "/" in release:
            why.append(f"no kernel release ({err or 'empty /proc/sys/kernel/osrelease'})")
            return None, None, "; ".join(why)
        path = f"/boot/config-{release.strip()}"
        text, err = self.tree.get(path)
        if text is None:
            why.append(str(err))
            return None, None, "; ".join(why)
        return _parse_config(text), path, None

    def loop_cpus(self) -> list[int]:
        """The CPUs the loop may run on: --cpu, else every online CPU."""
        if self.cpu is not None:
            return [self.cpu]
        return sorted(self.online)


def _parse_config(text: str) -> dict:
    out = {}
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("CONFIG_") and "=" in line:
            key, _, value = line.partition("=")
            out[key] = value
        elif line.startswith("# CONFIG_") and line.endswith(" is not set"):
            out[line[2:-len(" is not set")]] = "n"
    return out


def _unknown(key: str, title: str, why: Any, fix: str, **details: Any) -> Item:
    return Item(key, title, "warn", f"unknown: {_one_line(why)}", fix, details)


# --------------------------------------------------------------------------
# the items
# --------------------------------------------------------------------------

def _rt_kernel_fix(dynamic: bool | None, mode: str | None) -> str:
    arch = {"x86_64": "amd64", "aarch64": "arm64", "arm64": "arm64"}.get(platform.machine(),
                                                                       "amd64")
    fix = f"apt-get install linux-image-rt-{arch} and reboot into it (Debian's PREEMPT_RT kernel)"
    if dynamic and mode != "full":
        fix += "; with this kernel at least boot with preempt=full on the kernel command line"
    return fix


def check_preemption(ctx: _Context) -> Item:
    key, title = "preemption", "kernel preemption"
    tree = ctx.tree
    sources: dict[str, str] = {}
    mode = dynamic = decided = None
    notes = []

    text, err = tree.get("/sys/kernel/realtime")
    if text is None:
        sources["/sys/kernel/realtime"] = str(err)
    else:
        value = text.strip()
        sources["/sys/kernel/realtime"] = value[:40]
        if value == "1":
            mode, decided = "rt", "/sys/kernel/realtime = 1"
        elif value != "0":
            notes.append(f"/sys/kernel/realtime holds {value[:20]!r}")

    version, err = tree.get("/proc/sys/kernel/version")
    if version is None:
        sources["/proc/sys/kernel/version"] = str(err)
        notes.append(f"no version string ({err})")
    else:
        version = _one_line(version)
        sources["/proc/sys/kernel/version"] = version[:200]
        tokens = version.split()
        if mode is None and "PREEMPT_RT" in tokens:
            mode, decided = "rt", f"PREEMPT_RT in the version string {version[:60]!r}"
        if "PREEMPT_DYNAMIC" in tokens:
            dynamic = True
            notes.append("the version string says PREEMPT_DYNAMIC")
        elif mode is None and "PREEMPT" in tokens:
            mode, dynamic = "full", False
            decided = f"PREEMPT in the version string {version[:60]!r}"

    debug_path = "/sys/kernel/debug/sched/preempt"
    text, err = tree.get(debug_path)
    if text is None:
        sources[debug_path] = str(err)
        if mode is None and dynamic is not False:
            reason = err.args[0].split(": ", 1)[-1] if err else "unreadable"
            notes.append(f"{debug_path} unreadable ({reason})")
    else:
        sources[debug_path] = _one_line(text)[:80]
        m = re.search(r"\((\w+)\)", text)
        if m and m.group(1) in PREEMPT_MODES:
            dynamic = True
            if mode is None:
                mode, decided = m.group(1), f"{debug_path} marks ({m.group(1)})"
        else:
            notes.append(f"{debug_path} holds {_one_line(text)[:40]!r}")

    config, config_path, config_why = ctx.config()
    config_dynamic = None
    config_mode = None
    if config is not None:
        config_dynamic = config.get("CONFIG_PREEMPT_DYNAMIC") == "y"
        for name, m in _CONFIG_MODE:
            if config.get(name) == "y":
                config_mode = f"{name}=y", m
                break
        sources[config_path] = (f"{config_mode[0]}" if config_mode else "no preemption model") + (
            ", CONFIG_PREEMPT_DYNAMIC=y" if config_dynamic else "")
    else:
        sources["kernel config"] = config_why
    if dynamic is None and config_dynamic is not None:
        dynamic = config_dynamic

    boot = ctx.cmdline.get("preempt")
    if boot is not None:
        sources["/proc/cmdline"] = f"preempt={boot}"
        if mode is None:
            if boot not in PREEMPT_MODES:
                notes.append(f"preempt={boot} on the command line is not a mode the kernel knows")
            elif dynamic is False:
                notes.append(f"preempt={boot} on the command line is ignored (not a dynamic "
                             "kernel)")
            else:
                mode, decided = boot, f"preempt={boot} on the kernel command line"
                dynamic = True
    elif mode is None and dynamic:
        notes.append("no preempt= on the command line")

    if mode is None and config_mode is not None:
        mode, decided = config_mode[1], f"{config_mode[0]} in {config_path}"
    elif mode is None and config is None:
        notes.append(f"no kernel config ({config_why})")

    details = {"mode": mode, "dynamic": dynamic, "decided_by": decided, "sources": sources}
    if mode is None:
        return _unknown(key, title, "preemption model not found: " + "; ".join(notes),
                        _rt_kernel_fix(dynamic, None)
                        + " (check: uname -v; dmesg | grep -i preempt)",
                        **details)
    label = _MODE_LABEL[mode] + (" (dynamic)" if dynamic and mode != "rt" else "")
    finding = f"{label}, decided by {decided}"
    if notes:
        finding += " (" + "; ".join(notes) + ")"
    if mode == "rt":
        return Item(key, title, "ok", finding, None, details)
    if mode in ("full", "lazy"):
        finding += "; preemptible, but interrupts and long kernel sections still delay the loop"
    elif mode == "voluntary":
        finding += "; the kernel gives the CPU to the loop only at its explicit preemption points"
    else:
        finding += "; kernel code keeps the CPU until it gives it up, the loop's thread waits"
    return Item(key, title, "warn", finding, _rt_kernel_fix(dynamic, mode), details)


def check_rt_throttling(ctx: _Context) -> Item:
    key, title = "rt_throttling", "RT throttling"
    fix_default = "sysctl -w kernel.sched_rt_runtime_us=950000 (the default; -1: no limit)"
    try:
        runtime_us = _int_of(ctx.tree.read("/proc/sys/kernel/sched_rt_runtime_us"),
                             "/proc/sys/kernel/sched_rt_runtime_us")
        period_us = _int_of(ctx.tree.read("/proc/sys/kernel/sched_rt_period_us"),
                            "/proc/sys/kernel/sched_rt_period_us")
    except _Unreadable as e:
        return _unknown(key, title, e,
                        "sysctl kernel.sched_rt_runtime_us kernel.sched_rt_period_us")
    from rt_loop.server import DEFAULT_SPIN_US

    spin_us = min(DEFAULT_SPIN_US, 0.6 * ctx.period_us) if ctx.priority > 0 else 0.0
    need = (spin_us + LOOP_TICK_WORK_US) / ctx.period_us
    need_no_spin = LOOP_TICK_WORK_US / ctx.period_us
    details = {"runtime_us": runtime_us, "period_us": period_us, "loop_share": round(need, 3),
               "loop_spin_us": spin_us}
    if runtime_us == -1:
        return Item(key, title, "ok", "off (sched_rt_runtime_us = -1): SCHED_FIFO threads are "
                    "never throttled", None, details)
    if period_us <= 0 or runtime_us < -1:
        return _unknown(key, title, f"sched_rt_runtime_us {runtime_us}, sched_rt_period_us "
                        f"{period_us} make no sense", fix_default, **details)
    share = runtime_us / period_us
    details["rt_share"] = round(share, 3)
    head = f"SCHED_FIFO may use {runtime_us} of every {period_us} us ({share:.0%} of a CPU)"
    need_text = (f"the ~{need:.0%} the loop needs at {ctx.rate_hz:g} Hz ({spin_us:g} us early "
                 f"wake-up spin + ~{LOOP_TICK_WORK_US:g} us work per {ctx.period_us:g} us tick)")
    if share >= 1.0:
        return Item(key, title, "ok", f"{head}: no effective limit", None, details)
    if share >= need:
        return Item(key, title, "ok", f"{head}: a safety net above {need_text}; a runaway "
                    f"real-time thread still leaves {1 - share:.0%} to the rest", None, details)
    if runtime_us == 0:
        return Item(key, title, "fail", f"{head}: real-time threads get no CPU time at all",
                    fix_default, details)
    if share >= need_no_spin:
        return Item(key, title, "warn", f"{head}, below {need_text}: the loop would be "
                    "throttled every period; without the spin (--spin-us 0) it needs "
                    f"~{need_no_spin:.0%}", fix_default + ", or dct-hil serve --spin-us 0", details)
    return Item(key, title, "fail", f"{head}, below {need_text}: the loop would be "
                "throttled every period", fix_default, details)


def check_isolation(ctx: _Context) -> Item:
    key, title = "isolation", "CPU isolation"
    tree = ctx.tree
    if not ctx.online:
        return _unknown(key, title, f"online CPUs not known ({ctx.online_error})",
                        "cat /sys/devices/system/cpu/online /sys/devices/system/cpu/isolated")
    notes = []
    no_nohz_full = False
    sets: dict[str, set[int] | None] = {}
    for name, path in (("isolated", "/sys/devices/system/cpu/isolated"),
                       ("nohz_full_active", "/sys/devices/system/cpu/nohz_full"),
                       ("cpuset_isolated", "/sys/fs/cgroup/cpuset.cpus.isolated")):
        text, err = tree.get(path)
        if text is None:
            sets[name] = None
            if name == "nohz_full_active" and err.errno == errno.ENOENT:
                no_nohz_full = True
            if name == "isolated":
                notes.append(f"{path} unreadable ({str(err).split(': ', 1)[-1]})")
            continue
        try:
            sets[name] = parse_cpulist(text, ctx.last_cpu)
        except ValueError as e:
            sets[name] = None
            notes.append(f"{path}: {e}")
    boot: dict[str, set[int] | None] = {}
    for option in ("isolcpus", "nohz_full", "rcu_nocbs", "irqaffinity"):
        value = ctx.cmdline.get(option)
        if value is None:
            continue
        words = value.split(",")
        while option == "isolcpus" and words and re.fullmatch(r"[a-z_]+", words[0]):
            words.pop(0)    # flags: nohz, domain, managed_irq
        try:
            boot[option] = parse_cpulist(",".join(words), ctx.last_cpu)
        except ValueError as e:
            boot[option] = None
            notes.append(f"{option}={value} on the command line: {e}")
    isolated = set(sets["isolated"] or ()) | set(boot.get("isolcpus") or ()) | set(
        sets["cpuset_isolated"] or ())
    isolated &= ctx.online
    ctx.isolated = isolated
    nohz = set(sets["nohz_full_active"] or ()) | set(boot.get("nohz_full") or ())
    nocbs = set(boot.get("rcu_nocbs") or ())
    details = {"online": format_cpulist(ctx.online), "isolated": format_cpulist(isolated),
               "nohz_full": format_cpulist(nohz), "rcu_nocbs": format_cpulist(nocbs),
               "irqaffinity": format_cpulist(boot["irqaffinity"]) if boot.get("irqaffinity")
               else None, "cpu": ctx.cpu}
    extra = ""
    if boot.get("irqaffinity"):
        extra += f"; irqaffinity={format_cpulist(boot['irqaffinity'])}"
    if no_nohz_full and tree.exists("/sys/devices/system/cpu"):
        extra += ("; this kernel has no nohz_full (CONFIG_NO_HZ_FULL off: nohz_full= does "
                  "nothing, the tick stays)")
    if notes:
        extra += "; " + "; ".join(notes)
    if len(ctx.online) < 2:
        return Item(key, title, "warn", f"{_cpu_word(ctx.online)} online: nothing to isolate the "
                    f"loop on{extra}", "a PC with 2 or more cores: one for the loop, the rest for "
                    "everything else", details)
    if ctx.cpu is not None and ctx.cpu not in ctx.online:
        return Item(key, title, "fail", f"--cpu {ctx.cpu} is not online ("
                    f"{_cpu_word(ctx.online)} online){extra}",
                    f"dct-hil serve --cpu {ctx.last_cpu}", details)

    def boot_fix(n: int) -> str:
        return (f"boot with isolcpus={n} nohz_full={n} rcu_nocbs={n} on the kernel command line, "
                f"then run dct-hil serve --cpu {n}")

    if not isolated:
        target = ctx.cpu if ctx.cpu is not None else ctx.last_cpu
        sysfs = ("/sys/devices/system/cpu/isolated empty, " if sets["isolated"] is not None
                 else "")
        what = (f"no CPU isolated ({sysfs}no isolcpus= on the command line): the loop shares its "
                "CPU with everything else")
        if ctx.cpu is not None:
            what += f"; --cpu {ctx.cpu} is not isolated"
        if nohz:
            what += f"; nohz_full={format_cpulist(nohz)} without isolcpus"
        return Item(key, title, "warn", what + extra, boot_fix(target)
                    + ("" if ctx.cpu is not None else " (the last CPU)"), details)
    if ctx.cpu is None:
        pick = max(isolated)
        return Item(key, title, "warn", f"{_cpu_word(isolated)} isolated, but no --cpu: the loop "
                    f"would run on any CPU{extra}",
                    f"pin the loop there: dct-hil serve --cpu {pick} (and dct-hil doctor --cpu "
                    f"{pick})", details)
    if ctx.cpu not in isolated:
        pick = max(isolated)
        return Item(key, title, "warn", f"--cpu {ctx.cpu} is not isolated ({_cpu_word(isolated)} "
                    f"are){extra}", f"dct-hil serve --cpu {pick}", details)
    missing = [name for name, s in (("nohz_full", nohz), ("rcu_nocbs", nocbs)) if ctx.cpu not in s]
    finding = f"the loop's CPU {ctx.cpu} is isolated (isolated: {format_cpulist(isolated)})"
    if missing:
        finding += f"; not in {' or '.join(missing)} (its tick or RCU callbacks still run there)"
    return Item(key, title, "ok", finding + extra, None, details)


def check_governor(ctx: _Context) -> Item:
    key, title = "governor", "CPU governor"
    cpus = ctx.loop_cpus()
    if not cpus:
        return _unknown(key, title, f"online CPUs not known ({ctx.online_error})",
                        "cat /sys/devices/system/cpu/cpu*/cpufreq/scaling_governor")
    governors: dict[str, set[int]] = {}
    no_cpufreq: set[int] = set()
    for c in cpus:
        base = f"/sys/devices/system/cpu/cpu{c}/cpufreq"
        if not ctx.tree.isdir(base):
            no_cpufreq.add(c)
            continue
        text, err = ctx.tree.get(f"{base}/scaling_governor")
        name = text.strip() if text is not None else ""
        if not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
            return _unknown(key, title, err or f"{base}/scaling_governor holds {name[:30]!r}",
                            f"cat {base}/scaling_governor")
        governors.setdefault(name, set()).add(c)
    details = {"governors": {g: format_cpulist(s) for g, s in governors.items()},
               "no_cpufreq": format_cpulist(no_cpufreq)}
    if not governors:
        return Item(key, title, "info", f"no cpufreq on {_cpu_word(no_cpufreq)}: a fixed "
                    "frequency, or a VM (the host sets it)", None, details)
    found = ", ".join(f"{g} on {_cpu_word(s)}" for g, s in sorted(governors.items()))
    if no_cpufreq:
        found += f"; no cpufreq on {_cpu_word(no_cpufreq)}"
    slow = {g: s for g, s in governors.items() if g != "performance"}
    if not slow:
        return Item(key, title, "ok", found, None, details)
    return Item(key, title, "warn", found + ": the clock ramps up only after the loop has "
                "started working", "cpupower frequency-set -g performance (or: echo performance "
                "| tee /sys/devices/system/cpu/cpu*/cpufreq/scaling_governor)", details)


def check_idle_states(ctx: _Context) -> Item:
    from rt_loop.pm_qos import current_latency_us

    key, title = "idle_states", "CPU idle states"
    qos_us = current_latency_us(ctx.tree.host("/dev/cpu_dma_latency"))
    if qos_us is None:
        qos_text = "PM QoS now: unknown (/dev/cpu_dma_latency unreadable)"
    elif qos_us >= PM_QOS_NO_CONSTRAINT_US:
        qos_text = "PM QoS now: no request"
    else:
        qos_text = f"PM QoS now: {qos_us} us (a request is held)"
    cpus = ctx.loop_cpus()
    states: dict[tuple[int, str, int], set[int]] = {}     # (index, name, latency_us) -> CPUs
    deep: dict[tuple[int, str, int], set[int]] = {}
    enabled: dict[tuple[int, str, int], set[int]] = {}
    no_idle: set[int] = set()
    for c in cpus:
        base = f"/sys/devices/system/cpu/cpu{c}/cpuidle"
        names = [n for n in ctx.tree.listdir(base) if re.fullmatch(r"state\d+", n)]
        if not names:
            no_idle.add(c)
            continue
        for n in sorted(names, key=lambda s: int(s[5:])):
            try:
                name = ctx.tree.read(f"{base}/{n}/name").strip()[:32] or "?"
                latency_us = _int_of(ctx.tree.read(f"{base}/{n}/latency"), f"{base}/{n}/latency")
                disabled = _int_of(ctx.tree.read(f"{base}/{n}/disable"), f"{base}/{n}/disable")
            except _Unreadable as e:
                return _unknown(key, title, e, f"grep . {base}/state*/*", pm_qos_now_us=qos_us)
            k = (int(n[5:]), name, latency_us)
            states.setdefault(k, set()).add(c)
            if not disabled:
                enabled.setdefault(k, set()).add(c)
            if latency_us > IDLE_EXIT_LATENCY_LIMIT_US and not disabled:
                deep.setdefault(k, set()).add(c)
    details = {"limit_us": IDLE_EXIT_LATENCY_LIMIT_US, "pm_qos_now_us": qos_us,
               "states": [{"state": k[0], "name": k[1], "latency_us": k[2], "cpus":
                           format_cpulist(s), "deep_enabled_cpus": format_cpulist(deep.get(k, ()))}
                          for k, s in sorted(states.items())]}
    if not states:
        return Item(key, title, "info", f"no cpuidle states on {_cpu_word(no_idle)} (the "
                    f"architecture's default idle); {qos_text}", None, details)
    if not deep:
        off = sorted({k[1] for k in states if k not in enabled or states[k] - enabled[k]})
        if enabled:
            deepest = max(enabled, key=lambda k: k[2])
            head = (f"every enabled state leaves within {IDLE_EXIT_LATENCY_LIMIT_US} us (deepest: "
                    f"{deepest[1]}, {deepest[2]} us, on {_cpu_word(enabled[deepest])})")
        else:
            head = "every idle state disabled"
        if off:
            head += f"; disabled: {', '.join(off)}"
        return Item(key, title, "ok", f"{head}; {qos_text}", None, details)
    listed = ", ".join(f"{k[1]} ({k[2]} us) on {_cpu_word(s)}" for k, s in sorted(deep.items()))
    indexes = sorted({k[0] for k in deep})
    glob = f"state{indexes[0]}" if len(indexes) == 1 else "state{" + ",".join(
        str(i) for i in indexes) + "}"
    return Item(key, title, "warn", f"enabled states slower to leave than "
                f"{IDLE_EXIT_LATENCY_LIMIT_US} us: {listed}; {qos_text}",
                "dct-hil serve holds /dev/cpu_dma_latency at 0 while it runs (--pm-qos-us, on by "
                "default), which keeps the CPUs out of them; to keep them off for everything: "
                f"echo 1 | tee /sys/devices/system/cpu/cpu*/cpuidle/{glob}/disable "
                "(boot: intel_idle.max_cstate=1 processor.max_cstate=1)", details)


def check_smt(ctx: _Context) -> Item:
    key, title = "smt", "SMT siblings"
    control, _ = ctx.tree.get("/sys/devices/system/cpu/smt/control")
    control = control.strip()[:20] if control is not None else None
    ctrl_text = f"smt/control: {control}" if control else "no smt/control"
    cpus = ctx.loop_cpus()
    shared: dict[int, set[int]] = {}
    for c in cpus:
        path = f"/sys/devices/system/cpu/cpu{c}/topology/thread_siblings_list"
        text, err = ctx.tree.get(path)
        if text is None:
            if control in ("notsupported", "off", "forceoff", "notimplemented"):
                continue
            return _unknown(key, title, err, f"cat {path} /sys/devices/system/cpu/smt/control")
        try:
            others = parse_cpulist(text) - {c}
        except ValueError as e:
            return _unknown(key, title, f"{path}: {e}", f"cat {path}")
        if others:
            shared[c] = others
    details = {"control": control, "siblings": {str(c): format_cpulist(s)
                                                for c, s in shared.items()}}
    fix = ("turn SMT off: echo off > /sys/devices/system/cpu/smt/control (boot: nosmt), or "
           "isolate the sibling too and leave it idle")
    if not shared:
        return Item(key, title, "ok", f"no SMT sibling on {_cpu_word(cpus)} ({ctrl_text})",
                    None, details)
    if ctx.cpu is not None:
        sibs = shared[ctx.cpu]
        if sibs <= ctx.isolated:
            return Item(key, title, "ok", f"CPU {ctx.cpu} shares its core with "
                        f"{_cpu_word(sibs)}, isolated too: keep it idle ({ctrl_text})", None,
                        details)
        both = format_cpulist(sibs | {ctx.cpu})
        return Item(key, title, "warn", f"CPU {ctx.cpu} shares its core with {_cpu_word(sibs)} "
                    f"({ctrl_text}): whatever runs there slows the loop's tick", fix +
                    f" (isolcpus={both} nohz_full={both} rcu_nocbs={both})", details)
    pairs = sorted({format_cpulist(s | {c}) for c, s in shared.items()})
    return Item(key, title, "warn", f"SMT on ({ctrl_text}): cores shared by CPUs "
                f"{' '.join(pairs)}; the loop's CPU would share its core", fix + ", then --cpu "
                "on that core", details)


def _irq_of_device(ctx: _Context, name: str) -> tuple[set[int], str | None, str | None]:
    """IRQs of the interface's device (or the nearest parent with any), the
    device's driver, and the device they were found on when it is a parent."""
    tree = ctx.tree
    dev_link = tree.host(f"/sys/class/net/{name}/device")
    driver = None
    if os.path.exists(os.path.join(dev_link, "driver")):
        driver = os.path.basename(os.path.realpath(os.path.join(dev_link, "driver")))
    top = tree.host("/sys/devices")
    d = os.path.realpath(dev_link)
    first = d
    for _ in range(8):
        irqs = {int(n) for n in tree.listdir(tree.virtual(os.path.join(d, "msi_irqs")))
                if n.isdigit()}
        try:
            with open(os.path.join(d, "irq"), encoding="ascii") as f:
                n = int(f.read().strip() or 0)
            if n > 0:
                irqs.add(n)
        except (OSError, ValueError):
            pass
        if irqs:
            return irqs, driver, None if d == first else tree.virtual(d)
        parent = os.path.dirname(d)
        if not parent.startswith(top + os.sep) and parent != top:
            break
        d = parent
    return set(), driver, None


def check_can_irq(ctx: _Context, can: dict) -> Item:
    key, title = "can_irq", "CAN interrupts"
    name = can.get("name")
    if not can.get("exists"):
        return Item(key, title, "info", f"no CAN interface ({name} absent): no interrupts to "
                    "place", None, {"interface": name})
    if not can.get("is_can"):
        return Item(key, title, "info", f"{name} is not a CAN interface: nothing to check", None,
                    {"interface": name})
    if can.get("virtual"):
        return Item(key, title, "info", f"{name} is virtual ({can.get('kind') or 'no device'}): "
                    "it has no interrupts", None, {"interface": name})
    irqs, driver, via = _irq_of_device(ctx, name)
    text, err = ctx.tree.get("/proc/interrupts")
    words = [w for w in (name, driver) if w]
    if text is not None:
        for line in text.splitlines():
            head, _, rest = line.partition(":")
            if head.strip().isdigit() and any(re.search(rf"(?<![\w-]){re.escape(w)}(?![\w-])", rest)
                                              for w in words):
                irqs.add(int(head))
    details: dict[str, Any] = {"interface": name, "driver": driver, "found_on": via, "irqs": {}}
    if not irqs:
        return Item(key, title, "info", f"no IRQ found for {name} (driver {driver or 'unknown'}; "
                    f"not in /proc/interrupts{'' if text is not None else f': {err}'})", None,
                    details)
    affinity: dict[int, set[int]] = {}
    for n in sorted(irqs):
        path = f"/proc/irq/{n}/smp_affinity_list"
        t, e = ctx.tree.get(path)
        try:
            if t is None:
                raise ValueError(str(e).split(": ", 1)[-1])
            affinity[n] = parse_cpulist(t, ctx.last_cpu)
        except ValueError as e2:
            return _unknown(key, title, f"{path}: {e2}", f"cat {path}", **details)
        details["irqs"][str(n)] = format_cpulist(affinity[n])
    listed = ", ".join(f"IRQ {n} on {_cpu_word(s)}" for n, s in affinity.items())
    where = f" (via {via})" if via else ""
    if ctx.cpu is None:
        return Item(key, title, "info", f"{name}{where}: {listed}; give --cpu to check them "
                    "against the loop's CPU", None, details)
    hit = [n for n, s in affinity.items() if ctx.cpu in s]
    if not hit:
        return Item(key, title, "ok", f"{name}{where}: {listed}, away from the loop's CPU "
                    f"{ctx.cpu}", None, details)
    others = sorted((ctx.online - {ctx.cpu} - ctx.isolated) or (ctx.online - {ctx.cpu}))
    target = others[0] if others else 0
    cmds = "; ".join(f"echo {target} > /proc/irq/{n}/smp_affinity_list" for n in hit)
    return Item(key, title, "warn", f"{name}{where}: {listed}: may run on the loop's CPU "
                f"{ctx.cpu} and interrupt its tick", f"{cmds} (the loop polls its socket every "
                f"tick, the interrupt need not run on its CPU); keep irqbalance off it "
                f"(IRQBALANCE_BANNED_CPULIST={ctx.cpu} in /etc/default/irqbalance)", details)


def check_thp(ctx: _Context) -> Item:
    key, title = "thp", "transparent hugepages"
    path = "/sys/kernel/mm/transparent_hugepage/enabled"
    text, err = ctx.tree.get(path)
    if text is None:
        if err.errno == errno.ENOENT:
            return Item(key, title, "ok", "not built into this kernel", None, {"enabled": None})
        return _unknown(key, title, err, f"cat {path}")
    m = re.search(r"\[(\w+)\]", text)
    if not m:
        return _unknown(key, title, f"{path} holds {_one_line(text)[:40]!r}", f"cat {path}")
    mode = m.group(1)
    details = {"enabled": mode}
    if mode == "always":
        return Item(key, title, "warn", "[always]: any page fault may stop to assemble a huge "
                    "page, and khugepaged compacts memory behind the loop's back",
                    f"echo madvise > {path} (boot: transparent_hugepage=madvise)", details)
    if mode in ("madvise", "never"):
        return Item(key, title, "ok", f"[{mode}]: only where a program asks for them", None,
                    details)
    return _unknown(key, title, f"{path} selects {mode!r}", f"echo madvise > {path}", **details)


def _size_text(size_bytes: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if size_bytes >= scale:
            return f"{size_bytes / scale:.3g} {unit}"
    return f"{size_bytes} bytes"


def _memlock(ctx: _Context) -> tuple[bool | None, str]:
    """(can the process lock all its memory, why)."""
    cap = ctx.has_cap(CAP_IPC_LOCK)
    if cap:
        who = "root" if ctx.euid == 0 else f"uid {ctx.euid}"
        return True, f"CAP_IPC_LOCK ({who}): mlockall has no limit"
    limit = ctx.limits.get("Max locked memory")
    if limit is None:
        why = ctx.limits_error or "no 'Max locked memory' in /proc/self/limits"
        if cap is None:
            why += f"; capabilities unknown ({ctx.status_error})"
        return None, why
    soft, _hard = limit
    if soft is None:
        return True, "Max locked memory unlimited"
    return False, (f"Max locked memory {_size_text(soft)} and no CAP_IPC_LOCK: mlockall of "
                   "the whole server (Python, NumPy, the plant) fails")


def check_memlock(ctx: _Context) -> Item:
    key, title = "memlock", "memory locking"
    ok, why = _memlock(ctx)
    limit = ctx.limits.get("Max locked memory")
    details = {"can_lock": ok, "soft_bytes": limit[0] if limit else None,
               "hard_bytes": limit[1] if limit else None, "cap_ipc_lock": ctx.has_cap(CAP_IPC_LOCK)}
    if ok is None:
        return _unknown(key, title, why, "ulimit -l; grep CapEff /proc/self/status", **details)
    if ok:
        return Item(key, title, "ok", why, None, details)
    fix = ("run dct-hil serve as root, or give the user the limit: '<user> - memlock unlimited' "
           "in /etc/security/limits.d/dct-hil.conf and log in again")
    if limit and limit[1] is None:
        fix = "ulimit -l unlimited before dct-hil serve (the hard limit allows it), or " + fix
    return Item(key, title, "warn", why + "; the loop's pages can then be paged out or faulted in "
                "mid-tick", fix, details)


def check_swap(ctx: _Context) -> Item:
    key, title = "swap", "swap"
    text, err = ctx.tree.get("/proc/swaps")
    if text is None:
        if err.errno == errno.ENOENT:
            return Item(key, title, "ok", "no swap support in this kernel (no /proc/swaps)", None,
                        {"swap_kib": 0})
        return _unknown(key, title, err, "swapon --show")
    total_kib = 0
    names = []
    for line in text.splitlines()[1:]:
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 3 or not fields[2].isdigit():
            return _unknown(key, title, f"/proc/swaps: garbled line {line[:40]!r}", "swapon --show")
        total_kib += int(fields[2])
        names.append(fields[0])
    details = {"swap_kib": total_kib, "devices": names}
    if not names:
        return Item(key, title, "ok", "no swap in use", None, details)
    size = _size_text(total_kib * 1024)
    head = f"{size} on {', '.join(names[:3])}{' ...' if len(names) > 3 else ''}"
    can_lock, why = _memlock(ctx)
    details["can_lock"] = can_lock
    if can_lock:
        return Item(key, title, "info", f"{head}; the server locks its memory (mlockall), so the "
                    "loop's pages stay in RAM", None, details)
    if can_lock is None:
        return Item(key, title, "info", f"{head}; whether the server can lock its memory is "
                    f"unknown ({why})", None, details)
    return Item(key, title, "warn", f"{head}, and the server cannot lock its memory: the loop's "
                "pages may be swapped out", "let the server lock its memory (see memory locking), "
                "or swapoff -a", details)


def check_sched_fifo(ctx: _Context) -> Item:
    key, title = "sched_fifo", "SCHED_FIFO rights"
    prio = ctx.priority
    cap = ctx.has_cap(CAP_SYS_NICE)
    rtprio = ctx.limits.get("Max realtime priority")
    details = {"priority": prio, "cap_sys_nice": cap, "euid": ctx.euid,
               "rtprio_soft": rtprio[0] if rtprio else None,
               "rtprio_hard": rtprio[1] if rtprio else None}
    if prio == 0:
        return Item(key, title, "info", "--priority 0: normal scheduling, no rights needed (not "
                    "real time)", None, details)
    if cap:
        who = "root" if ctx.euid == 0 else f"uid {ctx.euid}"
        return Item(key, title, "ok", f"CAP_SYS_NICE ({who}): SCHED_FIFO {prio} allowed", None,
                    details)
    if rtprio is not None and (rtprio[0] is None or rtprio[0] >= prio):
        limit = "unlimited" if rtprio[0] is None else rtprio[0]
        return Item(key, title, "ok", f"Max realtime priority {limit} >= {prio}: SCHED_FIFO "
                    f"{prio} allowed", None, details)
    if cap is None and rtprio is None:
        return _unknown(key, title, f"neither capabilities ({ctx.status_error}) nor limits "
                        f"({ctx.limits_error}) readable",
                        "ulimit -r; grep CapEff /proc/self/status",
                        **details)
    have = "unknown" if rtprio is None else ("unlimited" if rtprio[0] is None else rtprio[0])
    fix = ("run dct-hil serve as root (sudo), or allow the user: '<user> - rtprio 99' and "
           "'<user> - memlock unlimited' in /etc/security/limits.d/dct-hil.conf, then log in again")
    if rtprio is not None and (rtprio[1] is None or rtprio[1] >= prio):
        fix = f"ulimit -r {prio} before dct-hil serve (the hard limit allows it), or " + fix
    return Item(key, title, "fail", f"no CAP_SYS_NICE and Max realtime priority {have} < {prio}: "
                "SCHED_FIFO is refused and the server runs with normal scheduling (not real time)",
                fix, details)


def contract_bitrate() -> int | None:
    """The bit rate of the CAN contract (the DBC's "Baudrate" attribute)."""
    import can_dbc

    path = os.path.join(os.path.dirname(os.path.abspath(can_dbc.__file__)), "dct_hil.dbc")
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            m = re.search(r'^BA_\s+"Baudrate"\s+(\d+)\s*;', f.read(), re.MULTILINE)
    except OSError:
        return None
    return int(m.group(1)) if m else None


def _ip_link_default(name: str) -> Any:
    exe = shutil.which("ip") or next((p for p in ("/usr/sbin/ip", "/sbin/ip", "/usr/bin/ip")
                                      if os.access(p, os.X_OK)), None)
    if exe is None:
        raise OSError("iproute2's ip is not installed")
    r = subprocess.run([exe, "-details", "-statistics", "-json", "link", "show", "dev", name],
                       capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise OSError(_one_line(r.stderr) or f"ip exited with {r.returncode}")
    return json.loads(r.stdout)


def _can_facts(ctx: _Context) -> dict:
    """The CAN interface: name, whether given, exists, is CAN, virtual, kind, ip JSON."""
    explicit = ctx.channel is not None
    name = ctx.channel if explicit else "vcan0"
    facts: dict[str, Any] = {"name": name, "explicit": explicit}
    if not name or "/" in name or name in (".", ".."):
        facts["exists"] = False
        return facts
    base = f"/sys/class/net/{name}"
    facts["exists"] = ctx.tree.isdir(base)
    others = []
    for other in ctx.tree.listdir("/sys/class/net"):
        t, _ = ctx.tree.get(f"/sys/class/net/{other}/type")
        if t is not None and t.strip() == str(ARPHRD_CAN) and other != name:
            others.append(other)
    facts["other_can"] = others
    if not facts["exists"]:
        return facts
    text, err = ctx.tree.get(f"{base}/type")
    try:
        if text is None:
            raise _Unreadable(str(err))
        facts["type"] = _int_of(text, f"{base}/type")
    except _Unreadable as e:
        facts["type_error"] = str(e)
        facts["type"] = None
    facts["is_can"] = facts["type"] == ARPHRD_CAN
    info = None
    if ctx.ip_link is not None:
        try:
            data = ctx.ip_link(name)
            if isinstance(data, list):
                data = data[0] if data else None
            if data is not None and not isinstance(data, dict):
                raise ValueError("not an ip -json link object")
            info = data
            if info is None:
                facts["ip_error"] = "ip gave nothing"
        except (OSError, ValueError, subprocess.SubprocessError) as e:
            facts["ip_error"] = _one_line(e)
    else:
        facts["ip_error"] = "ip not asked (files below another root)"
    facts["ip"] = info
    linkinfo = (info or {}).get("linkinfo") or {}
    facts["kind"] = linkinfo.get("info_kind") if isinstance(linkinfo, dict) else None
    has_device = ctx.tree.exists(f"{base}/device")
    facts["virtual"] = facts["kind"] in ("vcan", "vxcan") or (
        facts["kind"] is None and not has_device)
    return facts


def check_can_interface(ctx: _Context, can: dict) -> Item:
    key, title = "can_interface", "CAN interface"
    name, explicit = can["name"], can["explicit"]
    base = f"/sys/class/net/{name}"
    others = can.get("other_can") or []
    details: dict[str, Any] = {"interface": name, "explicit": explicit}
    if not can.get("exists"):
        there = f"; CAN interfaces here: {', '.join(others)}" if others else ""
        if explicit:
            if name.startswith("vcan"):
                fix = (f"modprobe vcan && ip link add dev {name} type vcan && ip link set {name} "
                       "up")
            else:
                fix = ("plug in the adapter and check dmesg and ip -details link show type can; "
                       "its driver names the interface")
            return Item(key, title, "fail", f"no network interface {name} ({base} missing){there}",
                        fix, details)
        hint = f" (--channel {others[0]} checks it)" if others else ""
        return Item(key, title, "info", f"no {name}: dct-hil serve uses its embedded transport "
                    f"(python-can's virtual bus, one process){there}{hint}", None, details)
    if not can.get("is_can"):
        why = can.get("type_error") or f"type {can.get('type')}, CAN is {ARPHRD_CAN}"
        return Item(key, title, "fail", f"{name} is not a CAN interface ({why})",
                    "give a CAN interface: --channel can0 (list: ip -details link show type can)",
                    details)
    virtual = can["virtual"]
    info = can.get("ip") or {}
    findings: list[tuple[str, str, str | None]] = []    # (verdict, text, fix)
    facts = [f"{name}: {'virtual ' + (can.get('kind') or 'CAN') if virtual else 'CAN'}"]

    flags_text, err = ctx.tree.get(f"{base}/flags")
    oper, _ = ctx.tree.get(f"{base}/operstate")
    oper = oper.strip()[:20] if oper is not None else None
    try:
        if flags_text is None:
            raise _Unreadable(str(err))
        up = bool(_int_of(flags_text, f"{base}/flags") & 1)
    except _Unreadable as e:
        up = None
        findings.append(("warn", f"up or down unknown ({e})", f"ip link show {name}"))
    details.update({"up": up, "operstate": oper, "kind": can.get("kind")})
    if up is not None:
        state_word = "up" if up else "down"
        facts.append(state_word + (f" (operstate {oper})" if oper and oper != state_word else ""))
    bitrate = contract_bitrate()
    if up is False:
        fix = (f"ip link set {name} up" if virtual else
               f"ip link set {name} up type can bitrate {bitrate or 1000000}")
        findings.append(("fail", "down: no frame gets through", fix))

    if not virtual:
        data = (info.get("linkinfo") or {}).get("info_data") or {}
        if not info:
            facts.append(f"bitrate and bus state unknown ({can.get('ip_error')})")
        else:
            rate = (data.get("bittiming") or {}).get("bitrate")
            state = data.get("state")
            berr = data.get("berr_counter") or {}
            details.update({"bitrate": rate, "state": state, "berr_counter": berr,
                            "contract_bitrate": bitrate})
            if rate:
                facts.append(f"{rate} bit/s")
                if bitrate and rate != bitrate:
                    findings.append(("warn", f"bitrate {rate}, the contract's (the DBC's "
                                     f"Baudrate) is {bitrate}", f"ip link set {name} down && "
                                     f"ip link set {name} up type can bitrate {bitrate}"))
            if state:
                counters = (f" (error counters tx {berr.get('tx', '?')}, rx {berr.get('rx', '?')})"
                            if berr else "")
                facts.append(f"{state}{counters}")
                wiring = ("check the wiring, the 120 ohm termination at both ends and that every "
                          f"node uses {bitrate or 'the same'} bit/s")
                if state == "BUS-OFF":
                    findings.append(("fail", "BUS-OFF: the controller has left the bus",
                                     f"ip link set {name} down && ip link set {name} up (or "
                                     f"ip link set {name} type can restart-ms 100); {wiring}"))
                elif state in ("ERROR-PASSIVE", "ERROR-WARNING"):
                    findings.append(("warn", f"{state}: many errors on the bus", wiring))
    txq = CAN_TXQUEUELEN_MIN
    txq_text, _ = ctx.tree.get(f"{base}/tx_queue_len")
    if txq_text is not None and txq_text.strip().isdigit():
        txq = int(txq_text)
        details["txqueuelen"] = txq
        facts.append(f"txqueuelen {txq}")
        if not virtual and txq < CAN_TXQUEUELEN_MIN:
            findings.append(("warn", f"txqueuelen {txq}: a burst of frames overflows it",
                             f"ip link set {name} txqueuelen {CAN_TXQUEUELEN_MIN}"))
    stats = {}
    for counter in ("rx_dropped", "tx_dropped", "rx_errors", "tx_errors"):
        t, _ = ctx.tree.get(f"{base}/statistics/{counter}")
        if t is not None and t.strip().isdigit():
            stats[counter] = int(t)
    details["statistics"] = stats
    dropped = {k: v for k, v in stats.items() if k.endswith("dropped") and v}
    if dropped:
        text = ", ".join(f"{k} {v}" for k, v in dropped.items())
        fix = f"watch ip -s link show {name} while dct-hil serve runs"
        if "tx_dropped" in dropped and not any("txqueuelen" in (f or "") for _, _, f in findings):
            fix = (f"a longer transmit queue: ip link set {name} txqueuelen "
                   f"{max(2 * txq, CAN_TXQUEUELEN_MIN)}; " + fix)
        findings.append(("warn", f"{text} since the interface came up", fix))
    elif stats:
        facts.append("no drops")
    verdict = "ok"
    for v, _, _ in findings:
        if VERDICTS.index(v) < VERDICTS.index(verdict):
            verdict = v
    finding = ", ".join(facts)
    if findings:
        finding += "; " + "; ".join(t for _, t, _ in findings)
    fixes = list(dict.fromkeys(f for v, _, f in findings if f))
    return Item(key, title, verdict, finding, "; ".join(fixes) if fixes else None, details)


_FLOOR_KEYS = ("samples", "p50_us", "p90_us", "p99_us", "p99_9_us", "max_us", "mean_us",
               "late_wakeups", "late_threshold_us", "skipped", "rt_policy_ok", "memory_locked",
               "affinity_ok", "pm_qos")


def check_floor(ctx: _Context, floor_s: float, measure: Callable[..., dict] | None,
                progress: Callable[[str], None] | None) -> Item:
    key, title = "floor", "wake-up floor"
    if measure is None:
        from rt_loop.floor import measure_floor as measure
    from rt_loop.floor import FloorError
    from rt_loop.pm_qos import current_latency_us

    held_before_us = current_latency_us(ctx.tree.host("/dev/cpu_dma_latency"))
    runs = {}
    for label, qos in (("without_pm_qos", None), ("with_pm_qos", 0)):
        if progress is not None:
            progress(f"measuring the wake-up floor for {floor_s:g} s "
                     f"{'without PM QoS' if qos is None else 'with PM QoS at 0 us'} ...")
        try:
            fig = measure(floor_s, ctx.rate_hz, ctx.priority, ctx.cpu, pm_qos_us=qos)
        except (FloorError, OSError, ValueError, RuntimeError) as e:
            return Item(key, title, "warn", f"unknown: the floor loop did not run ({_one_line(e)})",
                        "bash scripts/setup (builds the loop), then dct-hil doctor again",
                        {"duration_s": floor_s})
        runs[label] = {k: fig.get(k) for k in _FLOOR_KEYS}
    wo, wi = runs["without_pm_qos"], runs["with_pm_qos"]
    details = {"duration_s": floor_s, "rate_hz": ctx.rate_hz, "priority": ctx.priority,
               "cpu": ctx.cpu, "limit_p99_9_us": FLOOR_P99_9_LIMIT_US, **runs}
    if not wi.get("samples") or wi.get("p99_9_us") is None or wo.get("p99_9_us") is None:
        return Item(key, title, "warn", "unknown: the floor loop measured no wake-ups",
                    "dct-hil doctor --floor-s 10 again", details)
    p_wi, p_wo = float(wi["p99_9_us"]), float(wo["p99_9_us"])
    ratio = p_wo / p_wi if p_wi > 0 else math.inf
    late_wi, late_wo = int(wi["late_wakeups"] or 0), int(wo["late_wakeups"] or 0)
    ratio_text = f"{ratio:.1f}x" if ratio >= 0.1 else f"{ratio:.2f}x"
    finding = (f"with PM QoS p99.9 {p_wi:.0f} us, max {float(wi['max_us']):.0f} us, {late_wi} "
               f"late wake-ups (later than a {ctx.period_us:g} us period); without: p99.9 "
               f"{p_wo:.0f} us, max {float(wo['max_us']):.0f} us, {late_wo} late; p99.9 "
               f"without/with {ratio_text}")
    caveats = []
    if ctx.priority > 0 and not (wi.get("rt_policy_ok") and wo.get("rt_policy_ok")):
        caveats.append("measured without SCHED_FIFO (refused)")
    qos = wi.get("pm_qos") or {}
    if not qos.get("held"):
        caveats.append(f"the PM QoS request was not held ({qos.get('error') or 'refused'}), "
                       "both runs are without it")
    if caveats:
        finding += "; " + "; ".join(caveats)
    if held_before_us is not None and held_before_us < PM_QOS_NO_CONSTRAINT_US:
        finding += (f"; another process held PM QoS at {held_before_us} us, so the run without "
                    "it may not be")
    details["pm_qos_before_us"] = held_before_us
    good = p_wi < FLOOR_P99_9_LIMIT_US and late_wi == 0 and not caveats
    if good:
        return Item(key, title, "ok", finding, None, details)
    return Item(key, title, "warn", finding, None, details)   # the fix names the other items


#: the items that change the wake-up floor
_FLOOR_CAUSES = ("preemption", "rt_throttling", "isolation", "governor", "idle_states", "smt",
                 "can_irq", "thp", "memlock", "sched_fifo")


def _floor_fix(items: list[Item]) -> str:
    others = [i.title for i in items if i.key in _FLOOR_CAUSES and i.verdict in ("fail", "warn")]
    fix = ("apply the fixes for " + ", ".join(others) if others else
           "nothing above explains it: check for SMIs and firmware power management in the BIOS")
    return (fix + "; on a VM the hypervisor's scheduling adds what no setting in the guest "
            "removes; dct-hil serve's early wake-up (--spin-us, 300 us by default) keeps wake-up "
            "latency up to that size out of the tick")


# --------------------------------------------------------------------------
# the report
# --------------------------------------------------------------------------

class Report:
    def __init__(self, items: list[Item], options: dict, machine: dict) -> None:
        self.items = items
        self.options = options
        self.machine = machine

    @property
    def exit_code(self) -> int:
        return 1 if any(i.verdict == "fail" for i in self.items) else 0

    def counts(self) -> dict[str, int]:
        return {v: sum(1 for i in self.items if i.verdict == v) for v in VERDICTS}

    def item(self, key: str) -> Item:
        for i in self.items:
            if i.key == key:
                return i
        raise KeyError(key)

    def by_severity(self) -> list[Item]:
        return sorted(self.items, key=lambda i: VERDICTS.index(i.verdict))

    def to_dict(self) -> dict:
        return {"machine": self.machine, "options": self.options, "counts": self.counts(),
                "exit_code": self.exit_code, "items": [i.to_dict() for i in self.by_severity()]}

    def json_text(self) -> str:
        return json.dumps(self.to_dict(), indent=2) + "\n"

    def text(self) -> str:
        o = self.options
        cpu = "any CPU" if o["cpu"] is None else f"CPU {o['cpu']}"
        lines = [f"dct-hil doctor: {self.machine.get('kernel') or 'kernel ?'}, "
                 f"{self.machine.get('cpus') or '?'} CPUs; the loop at {o['rate_hz']:g} Hz, "
                 f"SCHED_FIFO {o['priority']}, {cpu}", ""]
        width = max(len(i.title) for i in self.items)
        for i in self.by_severity():
            lines.append(f"{i.verdict.upper():<4}  {i.title:<{width}}  {i.finding}")
        fixes = [i for i in self.by_severity() if i.fix]
        if fixes:
            lines += ["", "fixes"]
            for i in fixes:
                lines.append(f"  {i.title:<{width}}  {i.fix}")
        floor = next((i for i in self.items if i.key == "floor"), None)
        if floor is not None and "with_pm_qos" in floor.details:
            d = floor.details
            lines += ["", f"wake-up floor: {d['duration_s']:g} s each at {d['rate_hz']:g} Hz, "
                      f"SCHED_FIFO {d['priority']}, {cpu}"]
            lines.append(f"  {'us':<16}{'p50':>8}{'p99':>8}{'p99.9':>8}{'max':>8}  late wake-ups")
            for label, k in (("without PM QoS", "without_pm_qos"),
                             ("with PM QoS 0", "with_pm_qos")):
                f = d[k]
                figures = "".join(f"{_num(f[name]):>8}" for name in
                                  ("p50_us", "p99_us", "p99_9_us", "max_us"))
                lines.append(f"  {label:<16}{figures}  {f['late_wakeups']}")
        c = self.counts()
        lines += ["", ", ".join(f"{c[v]} {v}" for v in VERDICTS)]
        return "\n".join(lines) + "\n"


def _num(x: Any) -> str:
    return "-" if x is None else f"{float(x):.0f}"


def _machine(tree: _Tree, ctx: _Context) -> dict:
    release, _ = tree.get("/proc/sys/kernel/osrelease")
    version, _ = tree.get("/proc/sys/kernel/version")
    model = None
    text, _ = tree.get("/proc/cpuinfo")
    for line in (text or "").splitlines():
        k, _, v = line.partition(":")
        if k.strip() in ("model name", "Model", "Hardware"):
            model = v.strip()
            break
    return {"kernel": release.strip() if release else None,
            "kernel_version": _one_line(version) if version else None,
            "cpu_model": model, "cpus": len(ctx.online) or None,
            "online": format_cpulist(ctx.online) if ctx.online else None}


_CHECKS = (
    ("preemption", "kernel preemption", check_preemption),
    ("rt_throttling", "RT throttling", check_rt_throttling),
    ("isolation", "CPU isolation", check_isolation),
    ("governor", "CPU governor", check_governor),
    ("idle_states", "CPU idle states", check_idle_states),
    ("smt", "SMT siblings", check_smt),
    ("can_irq", "CAN interrupts", check_can_irq),
    ("thp", "transparent hugepages", check_thp),
    ("swap", "swap", check_swap),
    ("memlock", "memory locking", check_memlock),
    ("sched_fifo", "SCHED_FIFO rights", check_sched_fifo),
    ("can_interface", "CAN interface", check_can_interface),
)


def run_doctor(root: str = "/", cpu: int | None = None, channel: str | None = None,
               priority: int = 80, rate_hz: float = 2000.0, floor_s: float = 10.0,
               floor: bool = True, ip_link: Callable[[str], Any] | None = None,
               measure: Callable[..., dict] | None = None,
               progress: Callable[[str], None] | None = None) -> Report:
    """Checks this PC (the files below ``root``) and returns the report.

    ``cpu``: the CPU the loop will be pinned to; ``channel``: the CAN
    interface (None: vcan0 when it exists). ``ip_link(name)`` returns
    iproute2's ``ip -details -statistics -json link show dev NAME`` output
    (default: runs ip, only when ``root`` is "/"); ``measure(duration_s,
    rate_hz, priority, cpu, pm_qos_us=...)`` the floor figures (default
    ``rt_loop.floor.measure_floor``), run twice for ``floor_s`` each unless
    ``floor`` is False. ``progress`` gets a line before each measurement.
    """
    from rt_loop.server import MAX_RATE_HZ, MIN_RATE_HZ

    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise DoctorError(f"priority must be 0..99, got {priority!r}")
    if not (isinstance(rate_hz, (int, float)) and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ):
        raise DoctorError(f"rate must be {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz, got {rate_hz!r}")
    if floor and not (isinstance(floor_s, (int, float)) and math.isfinite(floor_s) and floor_s > 0):
        raise DoctorError(f"floor duration must be a number of seconds above 0, got {floor_s!r}")
    if cpu is not None and (isinstance(cpu, bool) or not isinstance(cpu, int) or cpu < 0):
        raise DoctorError(f"cpu must be a CPU number >= 0, got {cpu!r}")
    if not os.path.isdir(root):
        raise DoctorError(f"root {root}: not a directory")
    tree = _Tree(root)
    if ip_link is None and tree.root == "/":
        ip_link = _ip_link_default
    ctx = _Context(tree, cpu, channel, priority, float(rate_hz), ip_link)
    if cpu is not None and ctx.online and cpu not in ctx.online:
        raise DoctorError(f"cpu {cpu} is not online on this machine (online: "
                          f"{format_cpulist(ctx.online)})")
    can = None
    items = []
    for key, title, fn in _CHECKS:
        try:
            if key in ("can_irq", "can_interface"):
                if can is None:
                    can = _can_facts(ctx)
                item = fn(ctx, can)
            else:
                item = fn(ctx)
        except Exception as e:  # one odd file must not take the report down
            item = _unknown(key, title, f"the check failed ({type(e).__name__}: {e})",
                            "run dct-hil doctor --json - and report the output")
        items.append(item)
    if floor:
        item = check_floor(ctx, float(floor_s), measure, progress)
        if item.verdict != "ok" and item.fix is None:
            item.fix = _floor_fix(items)
    else:
        item = Item("floor", "wake-up floor", "info", "not measured (--no-floor)", None, {})
    items.append(item)
    options = {"root": tree.root, "cpu": cpu, "channel": channel, "priority": priority,
               "rate_hz": float(rate_hz), "floor_s": float(floor_s) if floor else None}
    return Report(items, options, _machine(tree, ctx))
