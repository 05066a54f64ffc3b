"""SIGINT and SIGTERM turned into a stop that every command of the project waits on.

A Python signal handler runs in the main thread between two bytecodes, wherever
that thread is, including inside ``threading.Event.wait``, which holds the
event's lock around its flag test; ``Event.set`` from the handler then waits for
that lock forever (the thread that holds it is the one running the handler),
and a server asked to stop keeps running. ``StopEvent`` is an event a handler
may set: ``set`` takes no lock (a flag and a byte written to its own pipe) and
``wait`` waits on the pipe. ``StopSignals`` installs the handlers around a block
and sets such an event. In the lowest layer so that every command line stops
on a signal the same way, written once.
"""

from __future__ import annotations

import os
import select
import signal
import threading
from typing import Any

__all__ = ["StopEvent", "StopSignals"]


class StopEvent:
    """``threading.Event``'s ``set``, ``is_set``, ``clear`` and ``wait``, safe to
    set from a signal handler (no lock; any number of threads may wait)."""

    def __init__(self) -> None:
        self._flag = False
        self._r, self._w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)

    def set(self) -> None:
        self._flag = True
        try:
            os.write(self._w, b"\0")
        except OSError:          # the pipe full (a byte is already there) or closed
            pass

    def is_set(self) -> bool:
        return self._flag

    def clear(self) -> None:
        self._flag = False
        try:
            while os.read(self._r, 4096):
                pass
        except OSError:          # drained (EAGAIN) or closed
            pass

    def wait(self, timeout: float | None = None) -> bool:
        """True once set; False when ``timeout`` seconds passed first."""
        if self._flag:
            return True
        if timeout is not None and timeout <= 0:
            return self._flag
        try:
            select.select([self._r], [], [], timeout)
        except (OSError, ValueError):   # closed meanwhile
            pass
        return self._flag

    def close(self) -> None:
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._r = self._w = -1

    def __del__(self) -> None:
        if getattr(self, "_r", -1) >= 0:
            self.close()


class StopSignals:
    """SIGINT and SIGTERM turned into ``event`` (a ``StopEvent``) while the block
    runs (main thread only; elsewhere the handlers stay as they are).
    ``received`` lists the signals in order; ``interrupted`` is True after a
    Ctrl-C. ``once``: the first signal restores the previous handlers, so the
    next one acts as it did before (aborts)."""

    def __init__(self, once: bool = False, signals: tuple = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.event = StopEvent()
        self.received: list[int] = []
        self._once = once
        self._signals = tuple(signals)
        self._previous: dict = {}

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.received.append(signum)
        self.event.set()
        if self._once:
            self._restore()

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in self._signals:
                self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc: Any) -> None:
        self._restore()

    @property
    def interrupted(self) -> bool:
        return bool(self.received) and self.received[0] == signal.SIGINT
