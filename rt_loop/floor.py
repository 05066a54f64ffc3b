"""The machine's wake-up floor: a C loop that only sleeps (``rt_floor.c``).

    fig = measure_floor(duration_s=10, rate_hz=2000, priority=80, pm_qos_us=0)
    fig["p99_9_us"], fig["late_wakeups"], fig["pm_qos"]["held"]

What cyclictest measures, built in: the same thread set-up as the plant
loop (SCHED_FIFO, optional CPU, mlockall), the same absolute deadlines and
the same skip-ahead after a wake-up later than the next deadline, and no
work between wake-ups. The difference between this and the loop's own
wake-up latency is what the loop adds; the floor itself is the machine
(scheduler, timer, power management, hypervisor). `dct-hil doctor` and the
loop benchmark run it alone (nothing else of ours running), with and
without PM QoS.

Percentiles come from the 1 us histogram as the loop's do
(``rt_loop.stats.hist_percentiles``).
"""

from __future__ import annotations

import threading
from typing import Any

from rt_loop.pm_qos import PmQos

__all__ = ["FloorError", "measure_floor"]


class FloorError(RuntimeError):
    """Bad arguments or a missing extension (one line)."""


def measure_floor(duration_s: float = 10.0, rate_hz: float = 2000.0, priority: int = 80,
                  cpu: int | None = None, lock_memory: bool | None = None,
                  pm_qos_us: int | None = 0, pm_qos_path: str | None = None,
                  stop: threading.Event | None = None) -> dict[str, Any]:
    """Runs the floor loop for ``duration_s`` and returns its figures.

    ``pm_qos_us`` None makes no PM QoS request; a number holds
    ``/dev/cpu_dma_latency`` at it for the run (``pm_qos`` in the result
    says whether that worked). ``stop`` ends the run early when set.
    Keys: samples, p50_us .. p99_9_us, max_us, mean_us, late_wakeups (woke
    after the next deadline), skipped, late_threshold_us, rt_policy_ok,
    memory_locked, affinity_ok, pm_qos, config, hist (sparse [[bin_us,
    count], ...]).
    """
    import numpy as np

    from rt_loop.stats import hist_percentiles, sparse_hist

    try:
        from rt_loop._rt_loop import ffi, lib
    except ImportError as e:
        raise FloorError(f"the real-time loop is not built ({e}); run scripts/setup") from None
    if not (1.0 / 0.1 <= float(rate_hz) <= 1.0 / 50e-6):
        raise FloorError(f"rate must be 10 to 20000 Hz, got {rate_hz}")
    if not float(duration_s) > 0:
        raise FloorError(f"duration must be above 0 s, got {duration_s}")
    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise FloorError(f"priority must be 0..99, got {priority!r}")
    cfg = ffi.new("rt_floor_config *")
    cfg.period_s = 1.0 / float(rate_hz)
    cfg.duration_s = float(duration_s)
    cfg.priority = priority
    cfg.cpu = -1 if cpu is None else int(cpu)
    cfg.lock_memory = int(priority > 0 if lock_memory is None else lock_memory)
    res = ffi.new("rt_floor_result *")
    flag = ffi.new("int *")
    qos = None
    if pm_qos_us is not None:
        qos = PmQos(pm_qos_us) if pm_qos_path is None else PmQos(pm_qos_us, pm_qos_path)
        qos.acquire()
    rc = [None]

    def body() -> None:
        rc[0] = lib.rt_floor_run(cfg, res, flag)

    thread = threading.Thread(target=body, name="rt-floor", daemon=True)
    try:
        thread.start()
        while thread.is_alive():
            thread.join(0.1)
            if stop is not None and stop.is_set():
                flag[0] = 1
    except KeyboardInterrupt:
        flag[0] = 1
        thread.join()
        raise
    finally:
        qos_report = qos.report() if qos is not None else {"requested_us": None, "held": False,
                                                            "error": None, "path": None}
        if qos is not None:
            qos.release()
    if rc[0] != 0:
        raise FloorError(f"the floor loop refused its set-up (rt_floor_run returned {rc[0]})")
    hist = np.frombuffer(ffi.buffer(res.hist), dtype=np.uint64).copy()
    fig = hist_percentiles(hist, float(res.max_us))
    samples = int(res.samples)
    period_us = 1e6 / float(rate_hz)
    return {
        **fig,
        "mean_us": float(res.sum_us) / samples if samples else None,
        "late_wakeups": int(res.late_wakeups),
        "late_threshold_us": period_us,
        "skipped": int(res.skipped),
        "rt_policy_ok": bool(res.rt_policy_ok),
        "memory_locked": bool(res.memory_locked),
        "affinity_ok": bool(res.affinity_ok) if cpu is not None else None,
        "pm_qos": qos_report,
        "config": {"duration_s": float(duration_s), "rate_hz": float(rate_hz),
                   "period_us": period_us, "priority": priority, "cpu": cpu,
                   "lock_memory": bool(cfg.lock_memory)},
        "hist": sparse_hist(hist),
    }
