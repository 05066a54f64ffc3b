"""The machine a figure was measured on: one ``machine_info`` for every report.

Every benchmark, soak, fuzz run and validation report writes this dict beside
its figures (``"machine": machine_info()``), so that a number read later says
where and from which build it came. It lives in the lowest layer because
every layer above measures something.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess

__all__ = ["cpu_model", "machine_info", "preempt_rt", "write_figures"]


def cpu_model() -> str:
    """The CPU's model name (for benchmark reports)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "Hardware"):
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def preempt_rt() -> bool:
    """Whether the running kernel is a PREEMPT_RT one."""
    try:
        with open("/sys/kernel/realtime", encoding="ascii") as f:
            return f.read().strip() == "1"
    except OSError:
        return "PREEMPT_RT" in platform.uname().version


def _git(*args: str) -> str | None:
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        r = subprocess.run(["git", "-C", here, *args], capture_output=True, text=True, timeout=10,
                           check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def _build() -> tuple[str | None, str | None]:
    """Compiler and flags of the plant's extension (None, None when it is not built)."""
    try:
        from plant.model import build_info
        compiler, _, flags = build_info().partition("; ")
    except ImportError:
        return None, None
    return compiler, flags


def machine_info(build: bool = False) -> dict:
    """CPU, kernel, Python and the date of this run; with ``build``, also the plant
    extension's compiler and flags and the checkout's git commit (two git calls:
    for a benchmark of the code, not for a server's report)."""
    uname = platform.uname()
    info = {
        "cpu": cpu_model(),
        "nproc": os.cpu_count(),
        "kernel": uname.release,
        "kernel_version": uname.version,
        "preempt_rt": preempt_rt(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    if build:
        compiler, flags = _build()
        commit = _git("rev-parse", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no") if commit else None
        info.update(compiler=compiler, compiler_flags=flags, git_commit=commit,
                    git_dirty=bool(dirty) if commit else None)
    info["date"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    return info


def write_figures(path: str | os.PathLike, report: dict, indent: int = 2) -> None:
    """A benchmark's report as JSON at ``path`` (its folder made; written whole
    or not at all: a reader never sees half a file): what is not JSON (a NumPy
    number, a path) written as its text."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=indent, default=str)
        f.write("\n")
    os.replace(tmp, path)
