"""The Dask engine of the studies: where runs execute.

``Engine(workers=N)`` starts a ``LocalCluster`` of N worker processes with one
thread each (default: every core; a run is one Python thread stepping the C
plant, so processes are what run in parallel), scheduler and workers on
127.0.0.1, the dashboard off unless ``dashboard`` names a port (then on
127.0.0.1; the scheduler's own HTTP endpoints take a free loopback port). ``Engine(scheduler="tcp://host:8786")`` uses an existing cluster
instead; its workers need this package installed (``pip install dct-hil`` in
the workers' environment), which the engine checks first.

``run(fn, tasks, keys, on_result)`` submits every task and calls
``on_result(i, result)`` as they finish, in completion order; a task whose
worker died or that raised gives ``{"error": "<one line>"}`` instead of
stopping the others. ``map(fn, tasks)`` returns the results in order (the fit
uses it for its candidates). ``Progress`` is the text progress bar.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable
from typing import Any

from dct_hil.studies import StudyError

CONNECT_TIMEOUT_S = 10.0


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _probe() -> str:
    """Runs on each worker: the package imports there, and a 50 ms closed-loop run
    loads what every run needs (the plant, the codec, the TCU), so the first real
    run of each worker costs what the others do."""
    from dct_hil.studies import runs

    runs.simulate(runs.make_case("0-100", 0.05))
    return runs.worker_name()


class Engine:
    """A Dask client on a LocalCluster or an existing scheduler (a context manager)."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None,
                 dashboard: int | None = None, connect_timeout_s: float = CONNECT_TIMEOUT_S):
        if workers is not None and scheduler is not None:
            raise StudyError("give either a number of local workers or a scheduler address, "
                             "not both")
        if workers is not None and workers < 1:
            raise StudyError(f"workers must be at least 1, got {workers}")
        self.workers = workers
        self.scheduler = scheduler
        self.dashboard = dashboard
        self.connect_timeout_s = connect_timeout_s
        self.cluster = None
        self.client = None
        self.description = ""

    # ------------------------------------------------------------ lifecycle
    def __enter__(self) -> Engine:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        from distributed import Client, LocalCluster

        for name in ("distributed", "distributed.worker", "distributed.scheduler",
                     "distributed.nanny", "distributed.core", "distributed.comm"):
            logging.getLogger(name).setLevel(logging.ERROR)
        if self.scheduler is None:
            n = self.workers or default_workers()
            dash = None if self.dashboard is None else f"127.0.0.1:{self.dashboard}"
            # without a dashboard the scheduler still serves /health and /metrics over
            # HTTP: on a free loopback port, not on the dashboard's 8787
            sched = None if dash else {"dashboard": False, "dashboard_address": "127.0.0.1:0"}
            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                        host="127.0.0.1", scheduler_port=0,
                                        dashboard_address=dash, scheduler_kwargs=sched,
                                        silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
            self.description = (f"LocalCluster: {n} worker process{'es' if n != 1 else ''} "
                                f"x 1 thread on 127.0.0.1")
            if dash:
                self.description += f", dashboard http://{dash}/status"
        else:
            address = self.scheduler
            try:
                self.client = Client(address, timeout=self.connect_timeout_s)
            except (OSError, TimeoutError) as e:
                reason = " ".join(str(e).split()) or type(e).__name__
                raise StudyError(f"cannot reach the Dask scheduler at {address}: {reason}") from None
            except ValueError as e:
                raise StudyError(f"bad Dask scheduler address {address!r}: {e}") from None
            try:
                self.client.wait_for_workers(1, timeout=self.connect_timeout_s)
            except (TimeoutError, OSError):
                self.close()
                raise StudyError(f"the Dask scheduler at {address} has no workers "
                                 f"(waited {self.connect_timeout_s:g} s)") from None
            n = len(self.client.scheduler_info(n_workers=-1)["workers"])
            self.description = f"Dask scheduler {address}: {n} worker{'s' if n != 1 else ''}"
        self._check_workers()

    def _check_workers(self) -> None:
        try:
            self.client.run(_probe)
        except Exception as e:
            where = self.scheduler or "the LocalCluster"
            reason = " ".join(str(e).split()) or type(e).__name__
            self.close()
            raise StudyError(f"the workers of {where} cannot run the studies ({type(e).__name__}: "
                             f"{reason}); install dct-hil in the workers' environment") from None

    def close(self) -> None:
        with contextlib.suppress(Exception):
            if self.client is not None:
                self.client.close(timeout=10)
        with contextlib.suppress(Exception):
            if self.cluster is not None:
                self.cluster.close(timeout=10)
        self.client = self.cluster = None

    @property
    def n_workers(self) -> int:
        if self.client is None:
            return 0
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    # ------------------------------------------------------------- running
    def run(self, fn: Callable, tasks: list, keys: list[str] | None,
            on_result: Callable[[int, dict], None]) -> None:
        """Submit ``fn(task)`` for every task; ``on_result(i, result)`` as each finishes."""
        from distributed import as_completed

        if not tasks:
            return
        futures = []
        index = {}
        for i, task in enumerate(tasks):
            kw = {"key": keys[i]} if keys else {"pure": False}
            fut = self.client.submit(fn, task, retries=0, **kw)
            futures.append(fut)
            index[fut.key] = i
        try:
            for fut in as_completed(futures):
                i = index[fut.key]
                try:
                    result = fut.result()
                except Exception as e:  # a worker lost, a task that raised
                    reason = " ".join(str(e).split()) or type(e).__name__
                    result = {"error": f"{type(e).__name__}: {reason}"}
                fut.release()
                on_result(i, result)
        except BaseException:
            with contextlib.suppress(Exception):
                self.client.cancel(futures)
            raise

    def map(self, fn: Callable, tasks: list) -> list[dict]:
        results: list = [None] * len(tasks)

        def keep(i, r):
            results[i] = r

        self.run(fn, tasks, None, keep)
        return results


class Progress:
    """A one-line progress bar on stderr (redrawn in place on a terminal, every
    10 % as lines otherwise)."""

    def __init__(self, total: int, what: str = "runs", stream: Any = None,
                 enabled: bool = True, width: int = 30):
        self.total = total
        self.what = what
        self.stream = stream or sys.stderr
        self.enabled = enabled and total > 0
        self.width = width
        self.done = 0
        self.failed = 0
        self.t0 = time.monotonic()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_decile = -1

    def update(self, failed: bool = False) -> None:
        self.done += 1
        self.failed += int(failed)
        if not self.enabled:
            return
        decile = self.done * 10 // self.total
        if self._tty or decile != self._last_decile or self.done == self.total:
            self._last_decile = decile
            self._draw()

    def _draw(self) -> None:
        frac = self.done / self.total
        filled = int(round(frac * self.width))
        elapsed = time.monotonic() - self.t0
        eta = elapsed / self.done * (self.total - self.done) if self.done else 0.0
        line = (f"[{'#' * filled}{'.' * (self.width - filled)}] {self.done}/{self.total} "
                f"{self.what}, {self.failed} failed, {_clock(elapsed)} elapsed, "
                f"ETA {_clock(eta)}")
        if self._tty:
            end = "\n" if self.done == self.total else ""
            self.stream.write("\r" + line + end)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self._tty and self.done < self.total:
            self.stream.write("\n")
            self.stream.flush()


def _clock(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"
