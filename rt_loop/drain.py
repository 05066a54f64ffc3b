"""A thread that empties one of the loop's output rings into a file.

The C loop puts entries (CAN frames for the traffic log, plant samples for
the recording) into single-producer single-consumer rings and never waits:
an entry the ring cannot take is counted by the loop (``dropped``). One
``RingDrain`` per ring pops batches in a thread of its own and hands them to
the subclass's writer. A writer that fails (disk full, a format limit)
keeps the ring moving and reports the error; it never stops the loop.
"""

from __future__ import annotations

import os
import threading
from typing import Any

__all__ = ["RingDrain", "one_line"]


def one_line(text: Any) -> str:
    """An exception or text folded into one line."""
    return " ".join(str(text).split())


class RingDrain:
    """Base of the ring writers. Subclasses set the class attributes and
    implement ``_write(buf, n)`` (write ``n`` entries of ``buf``) and
    ``_close()``."""

    ring = ""            # the rt_loop field holding the ring ("log", "rec")
    pop = ""             # the C function popping a batch ("rt_log_pop_many")
    entry = ""           # the ring's entry type
    batch = 1024         # entries per pop
    poll_s = 0.05        # wait between pops when the ring ran dry
    thread_name = "ring-drain"

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = os.fspath(path)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: Any = None
        self.written = 0
        self.error: str | None = None

    def _start(self, ffi: Any, lib: Any, loop: Any) -> None:
        self._ffi, self._lib, self._loop = ffi, lib, loop
        self._ring = ffi.addressof(loop[0], self.ring)
        self._pop = getattr(lib, self.pop)
        self._buf = ffi.new(f"{self.entry}[]", self.batch)
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> int:
        """Entries the loop could not put in the ring."""
        return int(getattr(self._loop, self.ring).dropped) if self._loop is not None else 0

    def _run(self) -> None:
        while True:
            stopping = self._stop.is_set()
            n = self._drain()
            if stopping and n == 0:
                break
            if n < self.batch:
                self._stop.wait(self.poll_s)

    def _drain(self) -> int:
        n = self._pop(self._ring, self._buf, self.batch)
        if n and self.error is None:          # after an error: keep the ring moving
            try:
                self._write(self._buf, n)
                self.written += n
            except Exception as e:  # reported, not fatal to the loop
                self.error = f"{self.path}: {_cause(e)}"
        return n

    def _write(self, buf: Any, n: int) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        """Writes what is left in the ring, then closes the file."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        try:
            self._close()
        except Exception as e:  # reported
            self.error = self.error or f"{self.path}: closing: {_cause(e)}"

    def counters(self) -> dict:
        return {"path": self.path, "written": self.written, "dropped": self.dropped,
                "error": self.error}


def _cause(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror:
        return e.strerror
    return f"{type(e).__name__}: {one_line(e)}"
