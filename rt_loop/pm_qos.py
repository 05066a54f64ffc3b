"""PM QoS: keep the CPUs out of deep idle states while the loop runs.

Linux lets a process cap the exit latency of the CPU idle states it tolerates
by writing a number of microseconds to ``/dev/cpu_dma_latency`` and keeping
the file open; the request holds until the file is closed (the kernel keeps
the lowest of all open requests). Without it a CPU that idles between two
ticks may pick a state whose wake-up costs tens to hundreds of
microseconds, and every wake-up of the loop pays it. cyclictest holds the
file at 0 for its run; so does the plant server (``--pm-qos-us``, default
0), the floor measurement and the loop benchmark.

    with PmQos(0) as q:          # q.held, q.error
        ...                      # the CPUs stay in shallow idle states

Writing needs root (the device is 0600). A request that cannot be made is
not an error: ``held`` is False and ``error`` says why in one line, so the
caller can warn and run on.
"""

from __future__ import annotations

import os
import struct
from typing import Any

__all__ = ["DEFAULT_LATENCY_US", "DEVICE", "PmQos", "current_latency_us"]

DEVICE = "/dev/cpu_dma_latency"
DEFAULT_LATENCY_US = 0
#: the kernel's "no constraint" value (PM_QOS_CPU_LATENCY_DEFAULT_VALUE, 2000 s)
NO_CONSTRAINT_US = 2_000_000_000


def current_latency_us(path: str = DEVICE) -> int | None:
    """The latency limit in force (the lowest request of every process), or
    None when the file cannot be read."""
    try:
        with open(path, "rb") as f:
            data = f.read(4)
    except OSError:
        return None
    if len(data) != 4:
        return None
    return struct.unpack("=i", data)[0]


class PmQos:
    """One PM QoS CPU latency request, held from ``acquire()`` to ``release()``."""

    def __init__(self, latency_us: int = DEFAULT_LATENCY_US, path: str = DEVICE) -> None:
        if isinstance(latency_us, bool) or not isinstance(latency_us, int) or latency_us < 0:
            raise ValueError(f"PM QoS latency must be a whole number of microseconds >= 0, "
                             f"got {latency_us!r}")
        self.latency_us = latency_us
        self.path = path
        self.held = False            # the request is in force now
        self.acquired = False        # it was in force at some time (for the run's report)
        self.error: str | None = None
        self._fd: int | None = None

    def acquire(self) -> bool:
        """Opens the file and writes the request; True when it is held."""
        if self._fd is not None:
            return True
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as e:
            self.error = f"cannot open {self.path}: {e.strerror}" + (
                " (needs root)" if e.errno in (1, 13) else "")
            return False
        try:
            written = os.write(fd, struct.pack("=i", self.latency_us))
            if written != 4:
                raise OSError(0, f"short write ({written} of 4 bytes)")
        except OSError as e:
            os.close(fd)
            self.error = f"cannot write {self.path}: {e.strerror}"
            return False
        self._fd = fd
        self.held = self.acquired = True
        self.error = None
        return True

    def release(self) -> None:
        """Closes the file: the kernel drops the request."""
        fd, self._fd = self._fd, None
        self.held = False
        if fd is not None:
            os.close(fd)

    def describe(self) -> str:
        if self.held or self.acquired:
            return f"{self.path} held at {self.latency_us} us (CPUs kept out of deeper idle states)"
        if self.error:
            return f"not held: {self.error}"
        return "off"

    def report(self) -> dict[str, Any]:
        return {"requested_us": self.latency_us, "path": self.path, "held": self.acquired,
                "error": self.error}

    def __enter__(self) -> PmQos:
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # interpreter shutdown
            pass
