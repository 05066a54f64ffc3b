"""The plant server: the C loop in a thread, a transport, a traffic log, statistics.

    srv = Server("vcan0", interface="virtual", priority=0)
    srv.start()          # loop thread running, frames flowing
    srv.snapshot()       # counts, timing, plant signals (a consistent copy)
    srv.stop()           # loop stopped, log flushed, bus closed
    srv.report()         # the dict written as the JSON stats file

Python does only set-up and supervision: one ``rt_loop`` is allocated
zeroed with ``ffi.new``, the plant parameters are written into it (solenoid
currents drive the clutch hydraulics), ``rt_config`` is filled, and
``rt_loop_run`` runs in a thread of its own (cffi releases the GIL for the
call). Every tick then happens in C. Around it, Python threads only move
frames for the bridge transport, drain the traffic log into a python-can
writer, and read the statistics.

``rt_loop.console.run_console`` is ``dct-hil serve`` around it: live status,
SIGINT/SIGTERM, summary, JSON file.
"""

from __future__ import annotations

import atexit
import errno
import json
import math
import os
import threading
import time
import weakref
from collections.abc import Callable
from typing import Any

from plant.machine import machine_info
from rt_loop.channels import ChannelError, LoopChannels
from rt_loop.drain import RingDrain
from rt_loop.drain import one_line as _one_line
from rt_loop.measure.recorder import Recorder
from rt_loop.pm_qos import DEFAULT_LATENCY_US as DEFAULT_PM_QOS_US
from rt_loop.pm_qos import PmQos
from rt_loop.stats import StatsReader
from rt_loop.transport import (
    Transport,
    TransportError,
    default_interface,
    open_transport,
)

__all__ = [
    "LOG_FORMATS",
    "MAX_RATE_HZ",
    "MIN_RATE_HZ",
    "OVERRUN_POLICIES",
    "Server",
    "ServerError",
    "TrafficLogger",
    "TransportError",
]

#: the loop's limits: periods from 10 ms down to 50 us (rt_loop_prepare)
MIN_RATE_HZ = 100.0
MAX_RATE_HZ = 20_000.0
DEFAULT_SPIN_US = 300.0  # early wake-up at SCHED_FIFO: covers these VMs' wake-up latency beyond p99.9
OVERRUN_POLICIES = ("skip", "stop")
#: traffic log suffixes and what writes them (python-can picks the writer by suffix)
LOG_FORMATS = {".log": "candump", ".blf": "Vector BLF", ".asc": "Vector ASC",
               ".mf4": "ASAM MDF 4 (needs asammdf)", ".csv": "CSV", ".trc": "PEAK TRC",
               ".db": "SQLite", ".txt": "text"}
#: the plant parameters the server always uses: the TCU drives solenoid currents
HYDRAULICS = {"hydraulics": {"pressure_commanded": 0}}

#: the loop's longest wall-clock period (a slowed-down run, rt_loop_prepare)
MAX_PERIOD_S = 0.1
#: rows of the in-loop driver table (RT_DRIVER_ROWS)
MAX_DRIVER_ROWS = 64
MANEUVER_STARTS = ("tcu", "now")
#: RT_MANEUVER_* -> name
MANEUVER_STATES = {0: "none", 1: "waiting for the TCU", 2: "running", 3: "done"}

#: below this many frames of receive buffer a SocketCAN run warns
SOCKET_FRAMES_WANTED = 10_000

#: the loop thread sets itself up (SCHED_FIFO, CPU, mlockall) before its first
#: tick; the server waits for it as long as that takes, up to this bound
#: (locking a Python process's memory takes seconds on a slow or emulated
#: machine), and names what it waits for after START_NOTE_S
START_LIMIT_S = 600.0
START_NOTE_S = 2.0
_STOP_TIMEOUT_S = 10.0
_LOG_BATCH = 4096


class ServerError(RuntimeError):
    """The server cannot be set up or stopped; ``str()`` is one line naming the cause."""


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


def _extension() -> tuple[Any, Any]:
    try:
        from rt_loop._rt_loop import ffi, lib  # compiled module
    except ImportError as e:
        raise ServerError(f"the real-time loop is not built ({e}); run scripts/setup") from None
    return ffi, lib


# --------------------------------------------------------------------------
# traffic log
# --------------------------------------------------------------------------

class TrafficLogger(RingDrain):
    """Drains the loop's log ring into a python-can writer, in a thread of its own.

    ``can.Logger(path)`` picks the format from the suffix (``LOG_FORMATS``).
    Both directions are written, received frames with ``is_rx`` True.
    Timestamps are the wall-clock time at which the loop started plus the
    loop time of the tick that received or sent the frame (its deadline).
    Entries the loop could not log because this thread fell behind are
    counted by the loop (``dropped``), never lost silently.
    """

    ring, pop, entry, batch, poll_s, thread_name = (
        "log", "rt_log_pop_many", "rt_log_entry", _LOG_BATCH, 0.02, "can-log")

    def __init__(self, path: str | os.PathLike, channel: str | list[str]) -> None:
        import can

        super().__init__(path)
        channels = [channel] if isinstance(channel, str) else list(channel)
        self.channel = channels[0]
        self.channels = channels
        suffix = os.path.splitext(self.path)[1].lower()
        self.format = LOG_FORMATS.get(suffix, suffix)
        try:
            self.writer = can.Logger(self.path)
        except (ValueError, ImportError, NotImplementedError) as e:
            known = ", ".join(f"{s} ({n})" for s, n in LOG_FORMATS.items())
            cause = _one_line(e).rstrip(".")
            raise ServerError(f"traffic log {self.path}: {cause}; known formats: {known}"
                              ) from None
        self._can = can
        self._msg_channels = _log_channels(channels, suffix)

    def start(self, ffi: Any, lib: Any, loop: Any, wall0: float) -> None:
        self._wall0 = wall0
        self._rx = lib.RT_DIR_RX
        self._start(ffi, lib, loop)

    #: also handed every batch of log entries (an MF4 recording's bus logging), or None
    forward: Callable[[Any, int], None] | None = None

    def _write(self, buf: Any, n: int) -> None:
        if self.forward is not None:
            self.forward(buf, n)
        ffi, can, rx = self._ffi, self._can, self._rx
        fd_flag, brs_flag = self._lib.RT_FRAME_FD, self._lib.RT_FRAME_BRS
        for i in range(n):
            e = buf[i]
            f = e.frame
            ident = int(f.id)
            length = min(int(f.len), 64)
            index = int(f.channel)
            self.writer.on_message_received(can.Message(
                timestamp=self._wall0 + e.time_s,
                arbitration_id=ident & 0x1FFFFFFF,
                is_extended_id=bool(ident & 0x80000000),
                is_remote_frame=bool(ident & 0x40000000),
                dlc=length,
                data=ffi.unpack(ffi.cast("char *", f.data), length),
                is_rx=e.dir == rx,
                is_fd=bool(int(f.flags) & fd_flag),
                bitrate_switch=bool(int(f.flags) & brs_flag),
                channel=self._msg_channels[index] if index < len(self._msg_channels) else None,
            ))

    def _close(self) -> None:
        self.writer.stop()

    def counters(self) -> dict:
        return {**super().counters(), "format": self.format}


def _log_channels(channels: list[str], suffix: str) -> list:
    """The channel written with the frames of each bus: ``_log_channel`` of its
    name; for several buses whose names give no distinct numbers, 1, 2, ... in
    the mapping's order."""
    out = [_log_channel(c, suffix) for c in channels]
    if len(channels) > 1 and suffix != ".log" and (None in out or len(set(out)) < len(out)):
        out = list(range(1, len(channels) + 1))
    return out


def _log_channel(channel: str, suffix: str) -> str | int | None:
    """The channel written with each frame: candump logs keep the interface
    name; the other formats number their channels, so a name ending in a small
    number (can0, vcan1) gives that number, anything else the writer's default
    (None; a name like "bench-12345" would give a number the format cannot hold)."""
    if suffix == ".log":
        return channel
    from can.util import channel2int

    number = channel2int(channel)
    return number if number is not None and 0 <= number <= 63 else None


# --------------------------------------------------------------------------
# the server
# --------------------------------------------------------------------------

class Server:
    """One plant served on one CAN channel.

    ``interface`` None picks SocketCAN when ``channel`` is a CAN network
    interface, else python-can's virtual bus (``transport.chosen_because``
    says which and why). ``priority`` 1..99 asks for SCHED_FIFO and
    ``mlockall``; 0 leaves the scheduling alone (no privileges needed, timing
    not real time). ``cpu``: the loop's CPU; while it runs, the process's
    other threads are kept on the others (``_confine_others``).
    ``duration_s`` None runs until ``stop()``.
    ``overrun_policy`` "skip" counts overruns and skips the missed deadlines;
    "stop" ends the run at the first overrun. ``log_path`` records the
    traffic (format by suffix, ``LOG_FORMATS``). ``bus_kwargs`` go to
    ``can.Bus`` for the bridge (e.g. ``bitrate``).

    ``time_scale`` (0 < s <= 1) runs the same ticks slower than real time:
    the plant still steps 1 / rate_hz per tick and the bus cycles count
    ticks, but the deadlines are 1 / (rate_hz x time_scale) apart (for a
    machine or an emulated kernel too slow for real time; the TCU must be
    slowed by the same factor). ``driver``: a scripted maneuver the loop
    plays itself (``plant.driver.ScriptedDriver`` or rows of (t_s,
    accel_pedal_pct, brake_pedal_pct[, selector])), started at the first accepted TCU
    frame (``maneuver_start`` "tcu") or at once ("now"); the run ends when
    its maneuver time reaches ``maneuver_end_s`` (None: never).
    ``maneuver_inputs``: its fixed plant inputs (``Maneuver.inputs``: the road
    grade), set before it plays.
    ``record_path``: a recording (CSV, or with the suffix .mf4 ASAM MDF4
    with the CAN traffic as bus logging in the same file,
    ``rt_loop.measure.mdf_recorder``) of every plant output each
    ``record_every_s`` of plant time (``rt_loop.measure.recorder``).
    ``pm_qos_us``: the CPU wake-up latency (us) requested through PM QoS
    (``/dev/cpu_dma_latency``, or ``pm_qos_path``) from before the loop
    starts until it has stopped, so that idle CPUs do not sink into states
    whose exit costs the tick its deadline; None makes no request; "auto"
    (the default) requests ``DEFAULT_PM_QOS_US`` when the loop runs under
    SCHED_FIFO (``priority`` > 0) and nothing under normal scheduling, whose
    timing is not real time anyway (a request there only keeps idle CPUs
    polling: in an emulated machine that takes CPU time from the busy ones).
    A request the kernel refuses is a warning, not an error (``pm_qos.error``).

    ``mapping``: the CAN matrix the plant plays, a mapping file (path or the
    name of a shipped one, ``can_dbc.mapping``; default the project's own
    contract, ``dct_hil``) or a loaded ``Mapping``. Its first bus is served on
    ``channel``, the others on the channels ``bus_channels`` names (bus name
    -> channel), else, on interfaces other than SocketCAN, on
    ``f"{channel}-{bus}"`` (``Mapping.channels``); each bus has a transport
    of its own (``transports``; ``transport`` is the first).

    ``xcp``: serve the loop's memory to an XCP master (``rt_loop.measure.xcp``): a
    "[HOST:]PORT" text or (host, port); the host is 127.0.0.1 unless one is
    given; ``xcp_protocol`` "udp" or "tcp"; ``xcp_key``: a file holding the
    seed & key secret that locks calibration and DAQ (a warning when the port
    is opened beyond loopback without one). The A2L it serves on GET_ID is
    ``rt_loop.measure.xcp.a2l.generate`` of this loop and mapping. The loop's
    writable regions (the inputs a test may override and the parameters
    marked online) are set for every run: XCP calibration and stimulus
    write only there.

    ``faults_path``: a TOML file of ``[[fault]]`` tables (``rt_loop.faults``),
    checked whole and queued for the run. ``control_path``: a Unix domain
    socket (mode 0600, removed on stop) on which ``rt_loop.control`` serves
    JSON-line requests for the running loop (read values, set plant inputs,
    inject and clear faults, watch conditions, stop). ``cal_lock`` is held by
    every producer of the loop's ``cal`` ring (XCP calibration, the control
    channel); the loop never takes it.

    Errors in the arguments, the mapping (``MappingError``), the parameters (``ParamError``) or the
    transport (``TransportError``) are raised with one-line messages.
    """

    def __init__(self, channel: str, interface: str | None = None, rate_hz: float = 2000,
                 priority: int = 80, cpu: int | None = None, duration_s: float | None = None,
                 params_path: str | os.PathLike | None = None,
                 log_path: str | os.PathLike | None = None, overrun_policy: str = "skip",
                 lock_memory: bool | None = None, bus_kwargs: dict | None = None,
                 spin_us: float | None = None, time_scale: float = 1.0, driver: Any = None,
                 maneuver_start: str = "tcu", maneuver_end_s: float | None = None,
                 record_path: str | os.PathLike | None = None,
                 record_every_s: float = 0.002,
                 pm_qos_us: int | str | None = "auto",
                 pm_qos_path: str | None = None, mapping: Any = None,
                 bus_channels: dict | None = None, xcp: Any = None, xcp_protocol: str = "udp",
                 xcp_key: str | os.PathLike | None = None,
                 stimulus_path: str | os.PathLike | None = None,
                 stimulus_start: str = "plant",
                 faults_path: str | os.PathLike | None = None,
                 control_path: str | os.PathLike | None = None,
                 maneuver_inputs: dict | None = None) -> None:
        from can_dbc import mapping as _mapping
        from plant.params import fill_params, load_params

        self.channel = _check_channel(channel)
        self.interface = interface
        self.rate_hz = _check_rate(rate_hz)
        self.time_scale = _check_time_scale(time_scale)
        self.step_s = 1.0 / self.rate_hz                 # simulated time per tick
        self.period_s = self.step_s / self.time_scale    # wall clock between deadlines
        if self.period_s > MAX_PERIOD_S:
            raise ServerError(f"time scale {time_scale} at {self.rate_hz:g} Hz gives a period of "
                              f"{self.period_s * 1e3:g} ms; the loop allows up to "
                              f"{MAX_PERIOD_S * 1e3:g} ms")
        self.driver_rows, self.driver_linear, self.driver_selectors = _check_driver(driver)
        self.maneuver_inputs = _check_maneuver_inputs(maneuver_inputs)
        if maneuver_start not in MANEUVER_STARTS:
            raise ServerError(f"maneuver start {maneuver_start!r}: choose "
                              + " or ".join(MANEUVER_STARTS))
        self.maneuver_start = maneuver_start
        self.maneuver_end_s = None if maneuver_end_s is None else _check_duration(maneuver_end_s)
        if self.maneuver_end_s is not None and not self.driver_rows:
            raise ServerError("a maneuver end needs a driver table")
        self.record_path = None if record_path is None else os.fspath(record_path)
        try:
            every = float(record_every_s)
        except (TypeError, ValueError):
            raise ServerError(f"record interval {record_every_s!r} is not a number") from None
        if not (math.isfinite(every) and every > 0):
            raise ServerError(f"record interval must be a number of seconds above 0, "
                              f"got {record_every_s}")
        self.record_every = max(1, int(round(every / self.step_s)))
        self.priority = _check_priority(priority)
        self.cpu = _check_cpu(cpu)
        self.duration_s = _check_duration(duration_s)
        if overrun_policy not in OVERRUN_POLICIES:
            raise ServerError(f"overrun policy {overrun_policy!r}: choose "
                              + " or ".join(OVERRUN_POLICIES))
        self.overrun_policy = overrun_policy
        self.lock_memory = self.priority > 0 if lock_memory is None else bool(lock_memory)
        # early wake-up before each deadline, busy-waited: hides the OS's
        # wake-up latency from the tick (real-time priority only: a normal
        # thread would just burn the CPU others need)
        if spin_us is None:
            spin_us = min(DEFAULT_SPIN_US, 0.6 * self.period_s * 1e6) if self.priority > 0 else 0.0
        if not (0.0 <= float(spin_us) < 0.8 * self.period_s * 1e6):
            raise ServerError(f"spin {spin_us} us: must be at least 0 and under 80 % of the "
                              f"period ({0.8 * self.period_s * 1e6:.0f} us)")
        self.spin_us = float(spin_us)
        #: why no PM QoS request is made (None: one is)
        self.pm_qos_off_because = None if pm_qos_us is not None else "no request asked for"
        if pm_qos_us == "auto":
            pm_qos_us = DEFAULT_PM_QOS_US if self.priority > 0 else None
            if pm_qos_us is None:
                self.pm_qos_off_because = "normal scheduling (priority 0): no request"
        if pm_qos_us is not None and (isinstance(pm_qos_us, bool) or not isinstance(pm_qos_us, int)
                                      or not 0 <= pm_qos_us <= 1_000_000):
            raise ServerError(f"PM QoS latency must be a whole number of microseconds 0..1000000, "
                              f"got {pm_qos_us!r}")
        self.pm_qos = None if pm_qos_us is None else (
            PmQos(pm_qos_us) if pm_qos_path is None else PmQos(pm_qos_us, pm_qos_path))
        self.params_path = None if params_path is None else os.fspath(params_path)
        self.log_path = None if log_path is None else os.fspath(log_path)
        self.bus_kwargs = dict(bus_kwargs or {})

        self._ffi, self._lib = ffi, lib = _extension()
        try:
            if isinstance(mapping, _mapping.Mapping):
                self.mapping = mapping
            else:
                path = _mapping.find_mapping(_mapping.DEFAULT_MAPPING if mapping is None
                                             else mapping)
                self.mapping = _mapping.load(path, rate_hz=self.rate_hz)
            if abs(self.mapping.rate_hz - self.rate_hz) > 1e-9 * self.rate_hz:
                self.mapping = _mapping.load(self.mapping.path, rate_hz=self.rate_hz,
                                             dbc=self._dbc_of(self.mapping))
            iface = interface if interface is not None else default_interface(self.channel)[0]
            #: bus name -> the CAN channel it is served on
            self.bus_channels = self.mapping.channels(self.channel, bus_channels,
                                                      derive=iface != "socketcan")
        except _mapping.MappingError as e:
            raise ServerError(str(e)) from None
        try:
            self.channels = LoopChannels(self.mapping, ffi, lib)
        except (ChannelError, ValueError) as e:
            raise ServerError(_one_line(e)) from None
        self.xcp_address, self.xcp_protocol, self.xcp_key = self._check_xcp(xcp, xcp_protocol,
                                                                            xcp_key)
        self.xcp = None
        self.stimulus = self._load_stimulus(stimulus_path, stimulus_start)
        self.stimulus_start = stimulus_start
        self.player = None
        overrides = {**HYDRAULICS, "solver": {"step_s": self.step_s}}
        self.params = load_params(self.params_path, ffi, overrides)
        self._l = ffi.new("rt_loop *")  # zeroed; lives as long as this object
        fill_params(ffi, self._l.plant.params, self.params)
        self.stats = StatsReader(ffi, lib, self._l, self.channels)
        self._read_lock = threading.Lock()   # one copy of the statistics, many readers
        from rt_loop.faults import FaultError, FaultManager, load_faults

        #: failure simulation: inject and clear faults, their figures and events
        self.faults = FaultManager(ffi, lib, self._l, self.channels)
        self.faults_path = None if faults_path is None else os.fspath(faults_path)
        if self.faults_path is not None:
            try:                          # checked whole before any of it is queued
                for f in load_faults(self.faults_path, self.faults.names):
                    self.faults.inject(f)
            except FaultError as e:
                raise ServerError(str(e)) from None

        #: held while pushing into the loop's cal ring (its producers: XCP, the control channel)
        self.cal_lock = threading.Lock()
        self.control_path = None if control_path is None else os.fspath(control_path)
        self.control = None
        if self.control_path is not None:
            from rt_loop.control import check_socket_path

            check_socket_path(self.control_path, ServerError)
        #: the live scope (``rt_loop.measure.scope``): min and max of chosen values per bucket of ticks
        self.scope = None
        self._maneuver: str | None = None            # the name of the maneuver started last
        self._recording: dict | None = None          # the recording running, if any
        self._rec_lock = threading.Lock()
        self._stop_hooks: list[Callable[[], None]] = []
        self._rec_log_on = False                     # log_frames switched on for a recording
        self.transport: Transport | None = None
        self.transports: list[Transport] = []
        self.logger: TrafficLogger | None = None
        self.recorder: Recorder | None = None
        self.warnings: list[str] = []
        # frames seen waiting in the bridge's rings at the status reads (the verdict's figure)
        self._rings = {"rx_waiting_max": 0, "tx_waiting_max": 0, "samples": 0}
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self._final_state: int | None = None
        self._loop_error: str | None = None
        self._started = self._stopped = False
        self._t_start = self._t_end = None

    def _load_stimulus(self, path: Any, start: str) -> Any:
        if path is None:
            return None
        if start not in ("plant", "maneuver"):
            raise ServerError(f"stimulus start {start!r}: choose plant or maneuver")
        if start == "maneuver" and not self.driver_rows:
            raise ServerError("a stimulus started with the maneuver needs a maneuver")
        from rt_loop.measure.stimulus import (
            StimulusError,
            load_stimulus,
            plant_inputs_writable,
            writable_of_regions,
        )
        from rt_loop.measure.xcp import a2l as _a2l

        ffi, lib = self._ffi, self._lib
        writable = {**writable_of_regions(_a2l.calibration_regions(ffi, lib)),
                    **plant_inputs_writable(ffi)}
        try:
            return load_stimulus(path, writable)
        except StimulusError as e:
            raise ServerError(str(e)) from None

    def _check_xcp(self, xcp: Any, protocol: str, key: Any) -> tuple:
        if xcp is None:
            if key is not None:
                raise ServerError("--xcp-key needs --xcp")
            return None, protocol, None
        from rt_loop.measure.xcp import parse_address
        from rt_loop.measure.xcp.protocol import read_secret

        try:
            address = parse_address(xcp) if isinstance(xcp, str) else (str(xcp[0]), int(xcp[1]))
        except (ValueError, TypeError, IndexError) as e:
            raise ServerError(_one_line(e)) from None
        if protocol not in ("udp", "tcp"):
            raise ServerError(f"XCP transport {protocol!r}: choose udp or tcp")
        if key is not None:
            try:
                read_secret(key)
            except (OSError, ValueError) as e:
                raise ServerError(f"--xcp-key {key}: {_one_line(e)}") from None
        return address, protocol, None if key is None else os.fspath(key)

    @staticmethod
    def _dbc_of(mapping: Any) -> dict:
        return {b.name: b.dbc for b in mapping.buses}

    # ------------------------------------------------------------ life cycle
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
        ffi, lib, loop = self._ffi, self._lib, self._l
        try:
            for bus in self.mapping.buses:
                kwargs = dict(self.bus_kwargs)
                if bus.fd:
                    kwargs["fd"] = True
                self.transports.append(open_transport(self.interface,
                                                      self.bus_channels[bus.name], **kwargs))
            self.transport = self.transports[0]
            if self.log_path is not None:
                self.logger = TrafficLogger(self.log_path, list(self.bus_channels.values()))
            if self.record_path is not None:
                try:
                    if self.record_path.lower().endswith((".mf4", ".mdf")):
                        from rt_loop.measure.mdf_recorder import MdfRecorder

                        self.recorder = MdfRecorder(self.record_path, self.channels.command_names,
                                                    channels=list(self.bus_channels.values()))
                    else:
                        self.recorder = Recorder(self.record_path, self.channels.command_names)
                except OSError as e:
                    raise ServerError(str(e)) from None

            cfg = loop.cfg
            cfg.period_s = self.period_s
            cfg.step_s = self.step_s
            cfg.record_every = self.record_every if self.recorder is not None else 0
            d = loop.driver
            _fill_driver(d, self.driver_rows, self.driver_linear, self.driver_selectors,
                         self.maneuver_inputs)
            d.start_on_tcu = int(self.maneuver_start == "tcu")
            d.end_s = 0.0 if self.maneuver_end_s is None else self.maneuver_end_s
            cfg.priority = self.priority
            cfg.cpu = -1 if self.cpu is None else self.cpu
            cfg.lock_memory = int(self.lock_memory)
            cfg.overrun_stop = int(self.overrun_policy == "stop")
            cfg.spin_us = self.spin_us
            cfg.duration_s = 0.0 if self.duration_s is None else self.duration_s
            mf4 = self.recorder is not None and not isinstance(self.recorder, Recorder)
            cfg.log_frames = int(self.logger is not None or mf4)
            self.channels.install(loop, self.transports)
            if self.driver_rows:
                self._maneuver = "scripted"
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
            from rt_loop.measure.scope import Scope

            self.scope = Scope(ffi, lib, loop, self.channels, self.step_s)
            self.scope.start()
            if self.xcp_address is not None:
                self._start_xcp(_a2l)
            if self.control_path is not None:
                self._start_control()
            if self.pm_qos is not None and not self.pm_qos.acquire():
                self.warnings.append(f"PM QoS not held ({self.pm_qos.error}): idle CPUs may "
                                     "wake up late (tens to hundreds of us)")
            for i, t in enumerate(self.transports):
                t.start(ffi, lib, loop, i)
            self._t_start = time.monotonic()
            wall0 = time.time()
            if self.logger is not None:
                self.logger.start(ffi, lib, loop, wall0)
            if self.recorder is not None:
                self._recording = {"path": self.record_path, "started_s": 0.0,
                                   "log_on": False}
                self.recorder.fault_events = self.faults.take_events
                if isinstance(self.recorder, Recorder):
                    self.recorder.start(ffi, lib, loop)
                else:                     # MF4: the CAN traffic too, from the log ring or the log
                    self.recorder.start(ffi, lib, loop, drain_log=self.logger is None,
                                        wall0=wall0)
                    if self.logger is not None:
                        self.logger.forward = self.recorder.add_frames
            if self.stimulus is not None:
                from rt_loop.measure.stimulus import StimulusPlayer

                self.player = StimulusPlayer(self.stimulus, ffi, lib, loop,
                                             start=self.stimulus_start,
                                             t0_s=0.0 if self.stimulus_start == "plant" else None)
                self.player.start()
            self._thread = threading.Thread(target=self._run, name="rt-loop", daemon=True)
            _LIVE.add(self)
            self._thread.start()
        except BaseException:
            self.stop()
            raise
        self._await_running(progress, cancel)
        self._confine_others()
        self._check_real_time()

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

    @property
    def running(self) -> bool:
        """The loop thread is running (it ends on stop(), duration, overrun policy, error)."""
        return self._thread is not None and not self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Waits until the loop ends by itself or is stopped; True if it has ended."""
        if self._thread is None:
            return True
        return self._done.wait(timeout)

    def stop(self) -> None:
        """Stops the loop, forwards the last frames, flushes and closes the log and the bus.

        Safe to call more than once and after a failed start().
        """
        if self._stopped:
            return
        hooks, self._stop_hooks = self._stop_hooks, []
        hook_errors: list[Exception] = []
        for hook in reversed(hooks):          # what reads the loop stops while it still runs
            try:
                hook()
            except Exception as e:  # the server stops anyway; raised below
                hook_errors.append(e)
        if self._thread is not None:
            self._lib.rt_loop_request_stop(self._l)
            # a loop still setting itself up (mlockall) stops after that
            starting = int(self._l.stats.state) == self._lib.RT_STATE_IDLE
            self._thread.join(START_LIMIT_S if starting else _STOP_TIMEOUT_S)
            if self._thread.is_alive():
                # the loop still owns self._l: keep everything alive, do not close
                raise ServerError(f"the loop did not stop within {_STOP_TIMEOUT_S:g} s")
        self._stopped = True
        _LIVE.discard(self)
        errors: list[Exception] = []
        for step in (self._stop_control, self._stop_player, self._stop_xcp, self._release_pm_qos,
                     self._stop_scope, self._stop_transport, self._stop_logger,
                     self._stop_recorder, self._close_transport, self._release_cpu):
            try:
                step()
            except Exception as e:  # every step runs; the first error is raised
                errors.append(e)
        with self._read_lock:
            self.stats.read()
        errors = hook_errors + errors
        if errors:
            raise ServerError(f"stopping: {_one_line(errors[0])}")

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

    def add_stop_hook(self, hook: Callable[[], None]) -> None:
        """``hook()`` runs first in ``stop()``, while the loop still runs (the
        last added first): for what reads the running loop from outside, such
        as the live view (``dct_hil.ui``). An error it raises is reported by
        ``stop()`` after everything stopped."""
        self._stop_hooks.append(hook)

    def _start_xcp(self, a2l: Any) -> None:
        from rt_loop.measure.xcp import XcpServer

        host, port = self.xcp_address
        ffi, lib = self._ffi, self._lib

        def a2l_text() -> str:        # the address bound (a port 0 asked for is chosen then)
            bound_host, bound_port = self.xcp.address
            settings = {"transport": self.xcp_protocol, "address": bound_host, "port": bound_port,
                        "rate_hz": self.rate_hz, "time_scale": self.time_scale}
            return a2l.generate(ffi, lib, channels=self.channels, xcp=settings)

        try:
            self.xcp = XcpServer(
                ffi, lib, self._l, host=host, port=port, protocol=self.xcp_protocol,
                a2l_text=a2l_text,
                a2l_name="dct_hil", epk=a2l.epk(ffi, lib, channels=self.channels),
                key_file=self.xcp_key, ranges=self._regions)
            if self.xcp.backend is not None:
                self.xcp.backend.cal_lock = self.cal_lock
            self.xcp.start()
        except OSError as e:
            self.xcp = None
            raise ServerError(f"XCP on {self.xcp_protocol.upper()} {host}:{port}: "
                              f"{e.strerror or _one_line(e)}") from None
        if self.xcp_key is None and host not in ("127.0.0.1", "::1", "localhost"):
            self.warnings.append(f"XCP on {host}:{port} is open beyond loopback without "
                                 "--xcp-key: anyone who reaches it can calibrate the plant")

    def _start_control(self) -> None:
        from rt_loop.control import ControlServer

        try:
            self.control = ControlServer(self, self.control_path)
            self.control.start()
        except OSError as e:
            self.control = None
            raise ServerError(f"control socket {self.control_path}: "
                              f"{e.strerror or _one_line(e)}") from None

    def _stop_control(self) -> None:
        if self.control is not None:
            self.control.stop()

    def _stop_player(self) -> None:
        if self.player is not None:
            self.player.stop()

    def _stop_xcp(self) -> None:
        if self.xcp is not None:
            self.xcp.stop()

    def _release_pm_qos(self) -> None:
        if self.pm_qos is not None:
            self.pm_qos.release()

    def _stop_transport(self) -> None:
        for t in self.transports:
            t.stop()

    def _stop_logger(self) -> None:
        if self.logger is not None:
            self.logger.stop()

    def _stop_recorder(self) -> None:
        with self._rec_lock:
            if self.recorder is not None and self._recording is not None:
                self._recording = None
                self.recorder.stop()

    def _stop_scope(self) -> None:
        if self.scope is not None:
            self.scope.stop()

    # ----------------------------------------------------------- while running
    @staticmethod
    def loop_maneuvers() -> list[str]:
        """The shipped maneuvers the loop can play itself (pedal tables)."""
        from plant.driver import ScriptedDriver
        from plant.maneuvers import MANEUVERS, get_maneuver

        return [n for n in MANEUVERS if isinstance(get_maneuver(n).driver, ScriptedDriver)
                and len(get_maneuver(n).driver.table) <= MAX_DRIVER_ROWS]

    @property
    def maneuver_playing(self) -> bool:
        """A maneuver is waiting for the TCU or playing (the loop drives the pedals)."""
        state = int(self._l.stats.maneuver_state)
        return state in (int(self._lib.RT_MANEUVER_WAITING), int(self._lib.RT_MANEUVER_RUNNING))

    @property
    def maneuver_name(self) -> str | None:
        """The maneuver started last (``--maneuver`` or ``start_maneuver``), None: none."""
        return self._maneuver

    def _maneuver_command(self, op: int, fill: Callable[[Any], None] | None = None) -> None:
        lib, loop = self._lib, self._l
        if not self.running:
            raise ServerError("the loop is not running")
        seq = int(loop.maneuver_seq)
        deadline = time.monotonic() + 1.0
        while int(lib.rt_maneuver_acked(loop)) != seq:      # the last command not taken yet
            if time.monotonic() > deadline:
                raise ServerError("the loop did not take the last maneuver command (is it "
                                  "ticking?)")
            time.sleep(0.001)
        refused = int(loop.maneuver_refused)
        if fill is not None:
            fill(loop.maneuver_next)
        loop.maneuver_op = op
        seq = (seq + 1) & 0xFFFFFFFF
        lib.rt_maneuver_publish(loop, seq)
        deadline = time.monotonic() + 1.0
        while int(lib.rt_maneuver_acked(loop)) != seq and self.running:
            if time.monotonic() > deadline:
                return                    # queued: the loop takes it at its next tick
            time.sleep(0.0005)
        if int(loop.maneuver_refused) != refused:
            raise ServerError("the loop refused the maneuver command")

    def start_maneuver(self, maneuver: Any, end_s: float | None = None,
                       inputs: dict | None = None) -> None:
        """Plays a maneuver from the next tick while the loop runs: a shipped
        one by name (``loop_maneuvers``), a ``ScriptedDriver`` or rows
        (t_s, accel %, brake %[, selector]). It replaces one playing; at its end (``end_s``,
        by name its duration) the last row's pedals stay and the loop goes
        on. Pedal sets are refused while it plays. ``inputs``: its fixed plant
        inputs, set as it starts (``{"road_grade_pct": 20}``; by name the
        maneuver's own)."""
        name = None
        if isinstance(maneuver, str):
            from plant.maneuvers import get_maneuver

            if maneuver not in self.loop_maneuvers():
                raise ServerError(f"maneuver {maneuver!r}: the loop plays "
                                  + ", ".join(self.loop_maneuvers()))
            m = get_maneuver(maneuver)
            name, driver, end_s = maneuver, m.driver, (m.duration_s if end_s is None else end_s)
            inputs = m.inputs if inputs is None else inputs
        else:
            driver = maneuver
        rows, linear, selectors = _check_driver(driver)
        fixed = _check_maneuver_inputs(inputs)
        end = 0.0 if end_s is None else _check_duration(end_s)

        def fill(d: Any) -> None:
            _fill_driver(d, rows, linear, selectors, fixed)
            d.start_on_tcu = 0
            d.end_s = end
            d.keep_running = 1

        self._maneuver_command(int(self._lib.RT_MCMD_START), fill)
        self._maneuver = name or "table"

    def stop_maneuver(self) -> None:
        """Ends the maneuver playing (the accelerator released, the brake as
        it was); nothing when none plays."""
        self._maneuver_command(int(self._lib.RT_MCMD_STOP))

    @property
    def recording(self) -> dict | None:
        """The recording running: {path, started_s (plant time)}, None: none."""
        r = self._recording
        return None if r is None else {"path": r["path"], "started_s": r["started_s"]}

    def start_recording(self, path: str | os.PathLike, every_s: float | None = None) -> str:
        """Starts recording every plant output each ``every_s`` of plant time
        (default the server's ``record_every_s``) into ``path`` (CSV, or MF4
        with the CAN traffic by the suffix) while the loop runs; returns the
        path. One recording at a time."""
        ffi, lib, loop = self._ffi, self._lib, self._l
        path = os.fspath(path)
        if every_s is None:
            every = self.record_every
        else:
            try:
                x = float(every_s)
            except (TypeError, ValueError):
                raise ServerError(f"record interval {every_s!r} is not a number") from None
            if not (math.isfinite(x) and x > 0):
                raise ServerError(f"record interval must be above 0 s, got {every_s!r}")
            every = max(1, int(round(x / self.step_s)))
        with self._rec_lock:
            if not self.running:
                raise ServerError("the loop is not running")
            if self._recording is not None:
                raise ServerError(f"a recording runs already: {self._recording['path']}")
            mf4 = path.lower().endswith((".mf4", ".mdf"))
            try:
                if mf4:
                    from rt_loop.measure.mdf_recorder import MdfRecorder

                    rec = MdfRecorder(path, self.channels.command_names,
                                      channels=list(self.bus_channels.values()))
                else:
                    rec = Recorder(path, self.channels.command_names)
            except OSError as e:
                raise ServerError(_one_line(e)) from None
            self.faults.take_events()              # the recording's events start now
            rec.fault_events = self.faults.take_events
            log_on = False
            if mf4:
                if self.logger is None:
                    log_on = not int(loop.cfg.log_frames)
                    loop.cfg.log_frames = 1
                    rec.start(ffi, lib, loop, drain_log=True)
                else:
                    rec.start(ffi, lib, loop, drain_log=False)
                    self.logger.forward = rec.add_frames
            else:
                rec.start(ffi, lib, loop)
            self.recorder = rec
            self.record_path = path
            self._recording = {"path": path, "started_s": float(loop.stats.sim_time_s),
                               "log_on": log_on}
            loop.cfg.record_every = every          # the loop pushes samples from its next tick
        return path

    def stop_recording(self) -> str:
        """Stops the recording running and finalizes its file; returns its path."""
        loop = self._l
        with self._rec_lock:
            r = self._recording
            if r is None or self.recorder is None:
                raise ServerError("no recording runs")
            loop.cfg.record_every = 0
            if r.get("log_on"):
                loop.cfg.log_frames = 0
            if self.logger is not None:
                self.logger.forward = None
            self._recording = None
            self.recorder.stop()
            if self.recorder.error:
                raise ServerError(f"recording {r['path']}: {self.recorder.error}")
            return r["path"]

    def _close_transport(self) -> None:
        errors = []
        for t in self.transports:
            try:
                t.close()
            except Exception as e:  # every bus is closed; the first error raised
                errors.append(e)
        if errors:
            raise errors[0]

    def __enter__(self) -> Server:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # ----------------------------------------------------------- observation
    @property
    def state(self) -> str:
        """idle, running, stopped, overrun_stop or error (of the last read)."""
        return self.stats.state

    def snapshot(self) -> dict:
        """A consistent copy of the loop's figures, as plain Python values.

        Keys: state, sim_time_s, the last and largest turnaround_us, exec_us
        and latency_us (``*_max_us``), counts (``StatsReader.counts`` plus
        ``log`` and, for the bridge, ``bridge``) and plant (key signals and
        the commands applied, ``StatsReader.plant``).
        """
        with self._read_lock:
            return self._snapshot()

    def _snapshot(self) -> dict:
        s = self.stats.read()
        self._sample_rings()
        return {
            "state": self.stats.state,
            "sim_time_s": float(s.sim_time_s),
            "maneuver": MANEUVER_STATES.get(int(s.maneuver_state), "?"),
            "maneuver_time_s": float(s.maneuver_time_s) if s.maneuver_time_s >= 0 else None,
            "turnaround_us": float(s.turnaround_us),
            "turnaround_max_us": float(s.turnaround_max_us),
            "exec_us": float(s.exec_us),
            "exec_max_us": float(s.exec_max_us),
            "latency_us": float(s.latency_us),
            "latency_max_us": float(s.latency_max_us),
            "counts": self._counts(),
            "plant": self.stats.plant(),
            "faults": {"active": int(s.fault_mask).bit_count(),
                       "changes": int(s.fault_changes)},
        }

    def _counts(self) -> dict:
        counts = self.stats.counts()
        counts["log"] = {"written": 0 if self.logger is None else self.logger.written,
                         "dropped": int(self._l.log.dropped)}
        bridges = [t for t in self.transports if not t.hard_real_time]
        bridge = _sum_counters([t.counters for t in bridges])
        counts["bridge"] = bridge
        for t, ch in zip(self.transports, counts["channels"].values()):
            ch["channel"] = t.channel
            if not t.hard_real_time and len(self.transports) > 1:
                ch["bridge"] = {k: v for k, v in t.counters.items() if k != "last_error"}
        # frames lost: those the loop counted (a full ring, or the kernel's drops of
        # the SocketCAN socket) and those lost below the bridge (the kernel's drops of
        # the bus's UDP socket); controller overflows are events of unknown size
        rx = counts["rx"]
        rx["lost_below_bridge"] = int(bridge.get("rx_kernel_drops") or 0)
        rx["lost"] = rx["overflow"] + rx["lost_below_bridge"]
        rx["overflow_events"] = int(bridge.get("rx_overflow_events") or 0)
        counts["record"] = {"written": 0 if self.recorder is None else self.recorder.written,
                            "dropped": int(self._l.rec.dropped)}
        return counts

    def _sample_rings(self) -> None:
        """Notes how many frames wait in the bridge's rings now (rx: for the loop, tx:
        for the bridge thread): a frame waits there while the other side is late."""
        if not self.running or all(t.hard_real_time for t in self.transports):
            return
        size = self._lib.RT_RING_SIZE
        for i, t in enumerate(self.transports):
            if t.hard_real_time:
                continue
            for name in ("rx", "tx"):
                ring = getattr(self._l, name)[i]
                waiting = (int(ring.head) - int(ring.tail)) & 0xFFFFFFFF
                if waiting <= size:              # head and tail are read one after the other
                    key = f"{name}_waiting_max"
                    self._rings[key] = max(self._rings[key], waiting)
        self._rings["samples"] += 1

    def rings_report(self) -> dict | None:
        """The most frames seen waiting in the bridge's rx and tx rings at a status read
        (``snapshot``), and how many reads there were; None without a bridge. A sampled
        figure: frames that waited between two reads are not seen."""
        if not self.transports or all(t.hard_real_time for t in self.transports):
            return None
        return {**self._rings, "size": int(self._lib.RT_RING_SIZE)}

    def xcp_counters(self) -> dict | None:
        """The XCP slave's counters and the loop's side (DTOs lost in a full ring,
        DAQ configurations refused, calibration writes applied and refused); None
        without XCP."""
        if self.xcp is None:
            return None
        loop = self._l
        return {**self.xcp.counters(),
                "loop": {"dto_ring_dropped": int(loop.daq_ring.dropped),
                         "daq_configurations_refused": int(loop.daq_refused),
                         "cal_applied": int(loop.cal.applied),
                         "cal_refused": int(loop.cal.refused)}}

    def transport_counters(self) -> dict:
        """The transports' own counters: the first bus's, or with several buses
        their sums (``counts.channels`` has each bus's)."""
        if len(self.transports) == 1:
            return self.transports[0].counters
        return _sum_counters([t.counters for t in self.transports])

    def config(self) -> dict:
        s = self.stats.copy
        t = self.transport
        return {
            "rate_hz": self.rate_hz,
            "step_us": self.step_s * 1e6,
            "time_scale": self.time_scale,
            "period_us": self.period_s * 1e6,
            "priority": self.priority,
            "cpu": self.cpu,
            "lock_memory": self.lock_memory,
            "overrun_policy": self.overrun_policy,
            "spin_us": self.spin_us,
            "pm_qos": None if self.pm_qos is None else self.pm_qos.report(),
            "duration_s": self.duration_s,
            "transport": None if t is None else ("socketcan" if t.hard_real_time else "bridge"),
            "real_time": None if t is None else ("hard" if t.hard_real_time else "soft"),
            "interface": None if t is None else t.interface,
            "interface_chosen_because": None if t is None else t.chosen_because,
            "channel": self.channel,
            "mapping": self.mapping.path,
            "buses": [{"name": b.name, "channel": self.bus_channels[b.name],
                       "dbc": b.dbc, "bitrate": b.bitrate, "fd": b.fd,
                       "transport": (None if i >= len(self.transports) else
                                     "socketcan" if self.transports[i].hard_real_time
                                     else "bridge"),
                       "sends": [m.name for m in self.mapping.messages
                                 if m.bus == b.name and m.direction == "send"],
                       "receives": [m.name for m in self.mapping.messages
                                    if m.bus == b.name and m.direction == "receive"]}
                      for i, b in enumerate(self.mapping.buses)],
            "commands": list(self.channels.command_names),
            "xcp": None if self.xcp_address is None else {
                "protocol": self.xcp_protocol,
                "address": list(self.xcp.address) if self.xcp is not None else list(self.xcp_address),
                "seed_and_key": self.xcp_key is not None},
            "params": self.params_path,
            "hydraulics": "solenoid currents (pressure_commanded = 0)",
            "log": self.log_path,
            "record": self.record_path,
            "record_every_s": self.record_every * self.step_s if self.record_path else None,
            "driver_rows": len(self.driver_rows),
            "maneuver_start": self.maneuver_start if self.driver_rows else None,
            "maneuver_end_s": self.maneuver_end_s,
            "rt_policy_ok": bool(s.rt_policy_ok),
            "memory_locked": bool(s.memory_locked),
            "affinity_ok": bool(s.affinity_ok) if self.cpu is not None else None,
        }

    def report(self, histograms: bool = True) -> dict:
        """Everything for the JSON stats file (reads the statistics once more)."""
        with self._read_lock:
            return self._report(histograms)

    def _report(self, histograms: bool) -> dict:
        s = self.stats.read()
        machine = machine_info()
        end = self._t_end if self._t_end is not None else time.monotonic()
        wall_s = (end - self._t_start) if self._t_start is not None else 0.0
        error = None
        if self._loop_error:
            error = self._loop_error
        elif int(s.state) == self._lib.RT_STATE_ERROR and int(s.error) < 0:
            error = (f"the plant core stopped the loop (dct_plant_step status {-int(s.error)}: "
                     "a value that is not finite)")
        elif int(s.state) == self._lib.RT_STATE_ERROR:
            error = f"transport error: {os.strerror(int(s.error))} (errno {int(s.error)})"
        timing = self.stats.timing(histograms=histograms)
        return {
            "date": machine.pop("date"),
            "config": self.config(),
            "run": {
                "state": self.stats.state,
                "error": error,
                "wall_s": wall_s,
                "sim_time_s": float(s.sim_time_s),
                "maneuver": MANEUVER_STATES.get(int(s.maneuver_state), "?"),
                "maneuver_time_s": float(s.maneuver_time_s) if s.maneuver_time_s >= 0 else None,
                "ticks": int(s.ticks),
                "warnings": list(self.warnings),
                "stats_read_failures": self.stats.read_failures,
            },
            "turnaround": timing["turnaround"],
            "execution": timing["execution"],
            "wakeup_latency": timing["wakeup_latency"],
            "histogram_bin_us": 1,
            "counts": self._counts(),
            "rings": self.rings_report(),
            "transport": {key: value for key, value in self.transport_counters().items()},
            "log": self.logger.counters() if self.logger is not None else None,
            "record": self.recorder.counters() if self.recorder is not None else None,
            "xcp": self.xcp_counters(),
            "stimulus": None if self.player is None else {
                "file": self.stimulus.path if hasattr(self.stimulus, "path") else None,
                "start": self.stimulus_start, **self.player.counters()},
            "plant": self.stats.plant(),
            "faults": self.faults.report(s),
            "machine": machine,
        }

    def write_report(self, path: str | os.PathLike, report: dict | None = None) -> dict:
        """Writes ``report`` (default: ``report()``) as the JSON stats file; returns it."""
        report = self.report() if report is None else report
        path = os.fspath(path)
        folder = os.path.dirname(os.path.abspath(path))
        os.makedirs(folder, exist_ok=True)
        tmp = f"{path}.tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
        return report


def _sum_counters(counters: list[dict]) -> dict:
    """Counters of several transports added up key by key (numbers and dicts of
    numbers; anything else is the first's). ``last_error`` is left out."""
    out: dict = {}
    for c in counters:
        for key, value in c.items():
            if key == "last_error":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, dict)):
                out.setdefault(key, value)
            elif isinstance(value, dict):
                d = out.setdefault(key, {})
                for k, v in value.items():
                    d[k] = d.get(k, 0) + v if isinstance(v, (int, float)) else v
            elif key in out and isinstance(out[key], (int, float)):
                out[key] += value
            else:
                out[key] = value
    return out


def _resident_mb() -> float:
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return float("nan")
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


# --------------------------------------------------------------------------
# argument checks (one line each)
# --------------------------------------------------------------------------

def _check_channel(channel: Any) -> str:
    if not isinstance(channel, str) or not channel.strip():
        raise ServerError(f"channel must be a non-empty name, got {channel!r}")
    return channel


def _check_rate(rate_hz: Any) -> float:
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise ServerError(f"rate {rate_hz!r} is not a number") from None
    if not (math.isfinite(rate) and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
        raise ServerError(f"rate must be {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz (a period of "
                          f"10 ms to 50 us), got {rate_hz}")
    return rate


def _check_priority(priority: Any) -> int:
    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise ServerError(f"priority must be a whole number 1..99 (SCHED_FIFO), or 0 for "
                          f"normal scheduling, got {priority!r}")
    return priority


def _thread_ids() -> list[int]:
    """The kernel thread ids of this process's threads."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [threading.get_native_id()]


def _check_cpu(cpu: Any) -> int | None:
    if cpu is None:
        return None
    if isinstance(cpu, bool) or not isinstance(cpu, int) or cpu < 0:
        raise ServerError(f"cpu must be a CPU number >= 0, got {cpu!r}")
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        allowed = list(range(os.cpu_count() or 1))
    if cpu not in allowed:
        raise ServerError(f"cpu {cpu}: not one of the CPUs this process may use "
                          f"({', '.join(map(str, allowed))})")
    return cpu


def _check_time_scale(time_scale: Any) -> float:
    try:
        scale = float(time_scale)
    except (TypeError, ValueError):
        raise ServerError(f"time scale {time_scale!r} is not a number") from None
    if not (math.isfinite(scale) and 0 < scale <= 1):
        raise ServerError(f"time scale must be above 0 and at most 1 (1: real time, 0.1: ten "
                          f"times slower), got {time_scale}")
    return scale


def _check_driver(driver: Any) -> tuple[list, bool, list | None]:
    """(rows, linear, selector codes per row or None) of a driver table: a
    ScriptedDriver or rows (t_s, accel %, brake %[, selector P/R/N/D])."""
    if driver is None:
        return [], False, None
    from plant.driver import selector_code

    table = getattr(driver, "table", driver)
    linear = getattr(driver, "mode", "step") == "linear"
    selectors = getattr(driver, "selector_table", None)
    try:
        raw = [tuple(r) for r in table]
        if selectors is None and raw and all(len(r) == 4 for r in raw):
            selectors = [selector_code(r[3], f"driver table row {k + 1}") for k, r in enumerate(raw)]
            raw = [r[:3] for r in raw]
        rows = [(float(t), float(a), float(b)) for t, a, b in raw]
    except ValueError as e:
        if "selector" in str(e):
            raise ServerError(str(e)) from None
        raise ServerError("driver table: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                          "[, selector])") from None
    except TypeError:
        raise ServerError("driver table: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                          "[, selector])") from None
    if selectors is not None:
        selectors = [float(x) for x in selectors]
    if not rows:
        raise ServerError("driver table: no rows")
    if len(rows) > MAX_DRIVER_ROWS:
        raise ServerError(f"driver table: {len(rows)} rows; the loop holds {MAX_DRIVER_ROWS}")
    for k, (t, a, b) in enumerate(rows):
        if not math.isfinite(t) or (k and not t > rows[k - 1][0]):
            raise ServerError(f"driver table row {k + 1}: times must be finite and increasing")
        if not (0 <= a <= 100 and 0 <= b <= 100):
            raise ServerError(f"driver table row {k + 1}: pedals must be within 0..100 %")
    return rows, linear, selectors


def _check_maneuver_inputs(inputs: Any) -> dict:
    """A maneuver's fixed plant inputs (``plant.maneuvers.FIXED_INPUTS``: the road grade)."""
    from plant.maneuvers import check_inputs

    try:
        return check_inputs(inputs, "maneuver inputs")
    except ValueError as e:
        raise ServerError(str(e)) from None


def _fill_driver(d: Any, rows: list, linear: bool, selectors: list | None, inputs: dict) -> None:
    """An rt_driver's table, selector column and fixed grade (its timing fields stay)."""
    d.rows = len(rows)
    for i, (t, accel, brake) in enumerate(rows):
        d.t_s[i], d.accel_pedal_pct[i], d.brake_pedal_pct[i] = t, accel, brake
    d.linear = int(linear)
    d.has_selector = int(selectors is not None)
    for i, code in enumerate(selectors or ()):
        d.selector_lever[i] = code
    grade = inputs.get("road_grade_pct")
    d.has_grade = int(grade is not None)
    d.road_grade_pct = 0.0 if grade is None else grade


def _check_duration(duration_s: Any) -> float | None:
    if duration_s is None:
        return None
    try:
        d = float(duration_s)
    except (TypeError, ValueError):
        raise ServerError(f"duration {duration_s!r} is not a number") from None
    if not (math.isfinite(d) and d > 0):
        raise ServerError(f"duration must be a number of seconds above 0, got {duration_s}")
    return d
