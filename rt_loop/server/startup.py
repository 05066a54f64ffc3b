"""The server's start-up and its CPU.

``start`` opens the buses and the outputs, has the loop check its set-up
(``rt_loop_prepare``) and starts the loop's thread, then waits while that
thread sets itself up (SCHED_FIFO, CPU affinity, mlockall; what it is doing:
``startup_phase_text``) and says in ``warnings`` what keeps the timing from
real time. While the loop runs on its own CPU, the process's other threads
are kept on the others (``_confine_others``, undone by ``_release_cpu``);
a PM QoS request keeps idle CPUs from sleeping deeply.
"""

from __future__ import annotations

import atexit
import ctypes
import errno
import os
import threading
import time
import weakref
from collections.abc import Callable

from rt_loop.drain import one_line as _one_line
from rt_loop.server.errors import ServerError
from rt_loop.transport import open_transport

__all__ = ["SOCKET_FRAMES_WANTED", "START_LIMIT_S", "START_NOTE_S", "StartupMixin",
           "THREAD_STACK_BYTES", "process_memory"]

#: below this many frames of receive buffer a SocketCAN run warns
SOCKET_FRAMES_WANTED = 10_000

#: the loop thread sets itself up (SCHED_FIFO, CPU, mlockall) before its first
#: tick; the server waits for it as long as that takes, up to this bound
#: (locking a Python process's memory takes seconds on a slow or emulated
#: machine), and names what it waits for after START_NOTE_S
START_LIMIT_S = 600.0
START_NOTE_S = 2.0

#: the stack of every thread the process starts while a server that locks its memory
#: runs (the loop's, the bridge's, the drains', XCP's, the control's, the bench view's):
#: under mlockall a thread's whole stack is resident, and the default is 8 MB. Measured
#: high-water marks (docs/server.md, "Memory"): the loop thread 216 kB (128 kB of it
#: touched on purpose before the first tick), the bench view's thread 44 kB after
#: rendering its page, every other thread at most 16 kB; 1 MiB is 4.7x the largest
THREAD_STACK_BYTES = 1 << 20
#: glibc's M_ARENA_MAX (malloc.h): threads that start later share the malloc arenas
#: there are, with no new ones: each new arena reserves 64 MB of address space that
#: mlockall counts as locked (VmLck, against RLIMIT_MEMLOCK) though it is never touched
#: (190 MB of a plain serve's VmLck). glibc fixes the limit at the first arena it would
#: add after this, for the rest of the process: it is not undone by stop()
_M_ARENA_MAX = -8


def _lean_threads() -> int:
    """Small stacks for the threads started from now on, and no new malloc arenas: what
    a server that locks its memory sets before it starts its threads; returns the stack
    size of before (``_restore_stack``)."""
    before = threading.stack_size(THREAD_STACK_BYTES)
    try:
        ctypes.CDLL(None).mallopt(_M_ARENA_MAX, 1)
    except (OSError, AttributeError):       # not glibc: the stacks alone
        pass
    return before


def _restore_stack(before: int | None) -> None:
    if before is not None and threading.stack_size() == THREAD_STACK_BYTES:
        threading.stack_size(before)


# servers whose loop thread may run: stopped at interpreter exit, so that no
# C thread is left working on memory Python is about to free
_LIVE: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def _stop_live_servers() -> None:
    for server in list(_LIVE):
        try:
            server.stop()
        except Exception:  # exiting anyway
            pass


class StartupMixin:
    """``Server``'s part that starts the loop and keeps its CPU.

    Reads the server's loop (``_ffi``, ``_lib``, ``_l``), its statistics
    (``stats``, under ``_read_lock``), the settings checked at construction
    (``mapping``, ``bus_channels``, ``bus_kwargs``, ``interface``, the
    timing, ``priority``, ``cpu``, ``lock_memory``, ``pm_qos`` ...) and the
    other parts' set-up steps; keeps the loop's thread (``_thread``,
    ``_done``), the run's start time and ``warnings``.
    """

    def start(self, progress: Callable[[str], None] | None = None,
              cancel: threading.Event | None = None) -> None:
        """Opens the transport and the log, prepares and starts the loop.

        Returns once the loop runs its first deadline (or has already
        ended); ``warnings`` then says whether the timing is real time. The
        loop's thread sets itself up first (SCHED_FIFO, CPU affinity,
        mlockall); the wait follows its start-up phase, with no fixed bound
        below ``START_LIMIT_S``: when it takes longer than ``START_NOTE_S``
        ``progress`` (if given) is called with one line naming the phase.
        ``cancel`` set while waiting stops the server and raises
        ``ServerError``.
        """
        if self._started:
            raise ServerError("the server was already started (one run per Server)")
        self._started = True
        t_called = time.monotonic()
        ffi, lib, loop = self._ffi, self._lib, self._l
        if self.lock_memory:
            self._lean = _lean_threads()
        try:
            self._open_transports()
            self._open_outputs()                  # log and recording files (recording.py)
            self._prepare_loop()
            self._start_scope()                   # recording.py
            if self.xcp_address is not None:
                self._start_xcp()                 # remote.py
            if self.control_path is not None or self.control_tcp is not None:
                self._start_control()             # remote.py
            self._acquire_pm_qos()
            for i, t in enumerate(self.transports):
                t.start(ffi, lib, loop, i)
            self._t_start = time.monotonic()
            self._start_outputs(wall0=time.time())  # their drains (recording.py)
            self._start_player()                  # the stimulus (maneuvers.py)
            self._thread = threading.Thread(target=self._run, name="rt-loop", daemon=True)
            _LIVE.add(self)
            self._thread.start()
        except BaseException:
            self.stop()
            raise
        self._await_running(progress, cancel)
        t_first = time.monotonic()
        #: seconds to the loop's first tick (within the 2 ms of the wait's polling) from
        #: start() and from the process's start; the process's memory at that moment
        #: (its locking done: what the run holds), read from /proc/self/status
        self.startup = {"start_to_first_tick_s": round(t_first - t_called, 3),
                        "process_to_first_tick_s": _process_age_s(),
                        "memory_at_first_tick": process_memory()}
        self._confine_others()
        self._check_real_time()

    def _open_transports(self) -> None:
        """One transport per bus of the mapping, on its channel; ``transport``: the first."""
        for bus in self.mapping.buses:
            kwargs = dict(self.bus_kwargs)
            if bus.fd:
                kwargs["fd"] = True
            self.transports.append(open_transport(self.interface,
                                                  self.bus_channels[bus.name], **kwargs))
        self.transport = self.transports[0]

    def _prepare_loop(self) -> None:
        """Fills the loop's configuration and driver, installs the channels and the
        calibration regions, and has the loop check its set-up (``rt_loop_prepare``)."""
        ffi, lib, loop = self._ffi, self._lib, self._l
        cfg = loop.cfg
        cfg.period_s = self.period_s
        cfg.step_s = self.step_s
        cfg.record_every = self.record_every if self.recorder is not None else 0
        self._configure_driver(loop.driver)       # maneuvers.py
        cfg.priority = self.priority
        cfg.cpu = -1 if self.cpu is None else self.cpu
        cfg.lock_memory = int(self.lock_memory)
        cfg.overrun_stop = int(self.overrun_policy == "stop")
        cfg.spin_us = self.spin_us
        cfg.duration_s = 0.0 if self.duration_s is None else self.duration_s
        cfg.log_frames = int(self._logs_frames())  # recording.py
        # the rings this run does not use as it starts stay out of the locked memory
        # (a recording started later holds its rings first: start_recording)
        cfg.release_rings = ((0 if cfg.log_frames else lib.RT_RELEASE_LOG)
                             | (0 if self.recorder is not None else lib.RT_RELEASE_REC)
                             | (0 if self.xcp_address is not None else lib.RT_RELEASE_DAQ)
                             | lib.RT_RELEASE_CAPTURE)          # held at the first capture
        self.channels.install(loop, self.transports)
        from rt_loop.measure.xcp import a2l as _a2l
        from rt_loop.measure.xcp.loop_backend import set_regions

        self._regions = _a2l.calibration_regions(ffi, lib)
        set_regions(ffi, lib, loop, self._regions)
        rc = lib.rt_loop_prepare(loop)
        if rc == -errno.EDOM:
            raise ServerError("the plant core rejected the parameter set (dct_plant_init "
                              f"status {-int(loop.stats.error)}; see check_params in "
                              "plant/csrc/plant.c)")
        if rc != 0:
            raise ServerError(f"the loop refused its set-up: {os.strerror(abs(rc))} "
                              f"(rt_loop_prepare returned {rc}; rate {self.rate_hz:g} Hz, "
                              f"priority {self.priority}, cpu {cfg.cpu})")

    def _acquire_pm_qos(self) -> None:
        if self.pm_qos is not None and not self.pm_qos.acquire():
            self.warnings.append(f"PM QoS not held ({self.pm_qos.error}): idle CPUs may "
                                 "wake up late (tens to hundreds of us)")

    def _release_pm_qos(self) -> None:
        if self.pm_qos is not None:
            self.pm_qos.release()

    def _run(self) -> None:
        try:
            self._final_state = self._lib.rt_loop_run(self._l)
        except BaseException as e:  # reported by stop()/report()
            self._loop_error = f"{type(e).__name__}: {_one_line(e)}"
        finally:
            self._t_end = time.monotonic()
            self._done.set()

    def _await_running(self, progress: Callable[[str], None] | None,
                       cancel: threading.Event | None) -> None:
        lib = self._lib
        t0 = time.monotonic()
        noted: dict[int, float] = {}
        while True:
            with self._read_lock:
                s = self.stats.read()
                state, phase = int(s.state), int(s.startup_phase)
            if state != lib.RT_STATE_IDLE or self._done.is_set():
                return
            waited = time.monotonic() - t0
            if cancel is not None and cancel.is_set():
                self._abort_start(f"start-up cancelled while {self.startup_phase_text(phase)}")
            if waited > START_LIMIT_S:
                self._abort_start(f"the loop did not start within {START_LIMIT_S:g} s (still "
                                  f"{self.startup_phase_text(phase)})")
            if progress is not None and waited >= START_NOTE_S:
                last = noted.get(phase)
                if last is None or waited - last >= 10.0:
                    noted[phase] = waited
                    progress(f"starting the loop ({waited:.0f} s): "
                             f"{self.startup_phase_text(phase)}")
            time.sleep(0.002)

    def _abort_start(self, why: str) -> None:
        try:
            self.stop()
        except ServerError as e:
            why = f"{why}; {e}"
        raise ServerError(why)

    def startup_phase_text(self, phase: int) -> str:
        """What the loop thread is doing in start-up phase ``phase`` (RT_START_*)."""
        lib = self._lib
        if phase == lib.RT_START_SCHEDULING:
            return f"asking for SCHED_FIFO priority {self.priority}"
        if phase == lib.RT_START_PINNING:
            return f"pinning the loop to CPU {self.cpu}"
        if phase == lib.RT_START_LOCKING_MEMORY:
            return (f"locking the process's memory (mlockall, {_resident_mb():.0f} MB resident; "
                    "slow on an emulated or loaded machine)")
        if phase == lib.RT_START_PREFAULTING:
            return "touching the loop's stack"
        if phase == lib.RT_START_READY:
            return "setting the first deadline"
        return "waiting for the loop thread to enter the C loop"

    def _check_real_time(self) -> None:
        with self._read_lock:
            s = self.stats.read()
            policy_ok, locked, pinned = s.rt_policy_ok, s.memory_locked, s.affinity_ok
        why = []
        if self.priority == 0:
            why.append("priority 0 (normal scheduling)")
        elif not policy_ok:
            why.append(f"SCHED_FIFO {self.priority} refused (needs root, CAP_SYS_NICE or an "
                       "rtprio limit)")
        if self.lock_memory and not locked:
            why.append("mlockall refused (needs root, CAP_IPC_LOCK or a memlock limit)")
        if why:
            self.warnings.append("timing is not real time: " + "; ".join(why))
        t = self.transport
        if t is not None and t.hard_real_time and t.rcvbuf_frames < SOCKET_FRAMES_WANTED:
            self.warnings.append(
                f"the socket receive buffer holds only about {t.rcvbuf_frames} frames "
                "(net.core.rmem_max caps it without CAP_NET_ADMIN; raise it with sysctl -w "
                "net.core.rmem_max=16777216): bursts may overflow it; lost frames are counted")
        if self.cpu is not None and not pinned:
            self.warnings.append(f"the loop could not be pinned to CPU {self.cpu}")

    def _confine_others(self) -> None:
        """With ``cpu`` set, the loop has that CPU to itself: every other thread
        of this process (and, by inheritance, every thread and process they
        start later: the live view, browsers a test starts) is moved to the
        remaining CPUs. Without it, a Python thread woken on the loop's CPU
        costs the tick rescheduling and function-call interrupts (measured:
        about 60 + 70 a second with two browsers on the live view, none with
        the threads kept off). Undone by ``stop()``; a CPU the loop would not
        leave (a single-CPU process) leaves everything as it is."""
        self._confined = None
        if self.cpu is None or self._thread is None or not self.running:
            return
        try:
            allowed = os.sched_getaffinity(0)
        except OSError:
            return
        others = set(allowed) - {self.cpu}
        if not others:
            self.warnings.append(f"cpu {self.cpu}: no other CPU to keep the process's other "
                                 "threads on; they share the loop's CPU")
            return
        loop_tid = self._thread.native_id
        moved = []
        for tid in _thread_ids():
            if tid == loop_tid:
                continue
            try:
                before = os.sched_getaffinity(tid)
                os.sched_setaffinity(tid, others)
                moved.append((tid, before))
            except OSError:           # a thread that ended meanwhile
                continue
        self._confined = (others, moved)

    def _release_threads(self) -> None:
        """Threads started from now on get the stack size of before ``start``
        (``_lean_threads``)."""
        before, self._lean = getattr(self, "_lean", None), None
        _restore_stack(before)

    def _release_cpu(self) -> None:
        """Gives the threads ``_confine_others`` moved their CPUs back (those still
        on the ones it set), and so the threads started since by them."""
        confined, self._confined = getattr(self, "_confined", None), None
        if confined is None:
            return
        others, moved = confined
        before = dict(moved)
        fallback = next(iter(before.values()), None)
        for tid in _thread_ids():
            try:
                if os.sched_getaffinity(tid) == others:
                    os.sched_setaffinity(tid, before.get(tid, fallback))
            except OSError:
                continue


def _thread_ids() -> list[int]:
    """The kernel thread ids of this process's threads."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [threading.get_native_id()]


#: /proc/PID/status fields of ``process_memory`` and their keys
_MEMORY_FIELDS = {"VmRSS": "vm_rss_mb", "VmLck": "vm_lck_mb", "VmHWM": "vm_hwm_mb"}


def process_memory(pid: int | str = "self") -> dict:
    """Resident (VmRSS), locked (VmLck) and peak resident (VmHWM) memory of a process in
    MB, from /proc/PID/status; {} where it cannot be read."""
    out: dict = {}
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in _MEMORY_FIELDS:
                    out[_MEMORY_FIELDS[key]] = round(int(value.split()[0]) / 1024, 1)
    except (OSError, ValueError, IndexError):
        return {}
    return out


def _process_age_s() -> float | None:
    """Seconds since this process started (its start time in /proc/self/stat, clock ticks
    since boot, against CLOCK_BOOTTIME), or None."""
    try:
        with open("/proc/self/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")
        return round(time.clock_gettime(time.CLOCK_BOOTTIME) - started, 2)
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def _resident_mb() -> float:
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return float("nan")
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
