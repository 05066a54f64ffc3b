"""``Server``: one plant served on CAN, put together from its parts.

This module holds what the parts share: the arguments, checked and kept
(``__init__``), the loop's memory (one ``rt_loop`` allocated zeroed, the
plant parameters written into it), the loop's thread as seen from outside
(``running``, ``wait``) and ``stop``, which undoes every part's set-up in
order. The parts: ``startup``, ``recording``, ``reports``, ``maneuvers`` and
``remote`` (see ``rt_loop.server``).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

from rt_loop.channels import ChannelError, LoopChannels
from rt_loop.drain import one_line as _one_line
from rt_loop.measure.recorder import Recorder
from rt_loop.pm_qos import PmQos
from rt_loop.server.checks import (
    MANEUVER_STARTS,
    OVERRUN_POLICIES,
    _check_channel,
    _check_choice,
    _check_control_tcp,
    _check_cpu,
    _check_driver,
    _check_duration,
    _check_maneuver_inputs,
    _check_period,
    _check_pm_qos,
    _check_priority,
    _check_rate,
    _check_record_every,
    _check_spin,
    _check_time_scale,
    _check_xcp,
)
from rt_loop.server.errors import ServerError
from rt_loop.server.maneuvers import ManeuverMixin
from rt_loop.server.recording import RecordingMixin, TrafficLogger
from rt_loop.server.remote import RemoteAccessMixin
from rt_loop.server.reports import ReportsMixin
from rt_loop.server.startup import _LIVE, START_LIMIT_S, StartupMixin
from rt_loop.stats import StatsReader
from rt_loop.transport import Transport, default_interface

__all__ = ["HYDRAULICS", "Server"]

#: the plant parameters the server always uses: the TCU drives solenoid currents
HYDRAULICS = {"hydraulics": {"pressure_commanded": 0}}
_STOP_TIMEOUT_S = 10.0


def _extension() -> tuple[Any, Any]:
    try:
        from rt_loop._rt_loop import ffi, lib  # compiled module
    except ImportError as e:
        raise ServerError(f"the real-time loop is not built ({e}); run scripts/setup") from None
    return ffi, lib


def _load_mapping(mapping: Any, rate_hz: float, channel: str, interface: str | None,
                  bus_channels: dict | None) -> tuple[Any, dict]:
    """(the ``Mapping`` at ``rate_hz``, bus name -> the CAN channel it is served on)."""
    from can_dbc import mapping as _mapping

    try:
        if isinstance(mapping, _mapping.Mapping):
            loaded = mapping
        else:
            path = _mapping.find_mapping(_mapping.DEFAULT_MAPPING if mapping is None
                                         else mapping)
            loaded = _mapping.load(path, rate_hz=rate_hz)
        if abs(loaded.rate_hz - rate_hz) > 1e-9 * rate_hz:
            loaded = _mapping.load(loaded.path, rate_hz=rate_hz,
                                   dbc={b.name: b.dbc for b in loaded.buses})
        iface = interface if interface is not None else default_interface(channel)[0]
        return loaded, loaded.channels(channel, bus_channels, derive=iface != "socketcan")
    except _mapping.MappingError as e:
        raise ServerError(str(e)) from None


class Server(StartupMixin, RecordingMixin, ReportsMixin, ManeuverMixin, RemoteAccessMixin):
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
    inject and clear faults, watch conditions, stop). ``control_tcp``:
    (host, port) the same channel also listens on (beyond loopback only with
    ``control_token``; ``control_tls``: an ``ssl.SSLContext`` for its TLS,
    ``rt_loop.access.server_tls_context``). ``cal_lock`` is held by
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
                 maneuver_inputs: dict | None = None,
                 control_tcp: tuple[str, int] | None = None, control_token: str | None = None,
                 control_tls: Any = None) -> None:
        from plant.params import fill_params, load_params

        self.channel = _check_channel(channel)
        self.interface = interface
        self.rate_hz = _check_rate(rate_hz)
        self.time_scale = _check_time_scale(time_scale)
        self.step_s = 1.0 / self.rate_hz                 # simulated time per tick
        self.period_s = _check_period(self.rate_hz, self.time_scale)  # wall clock between deadlines
        self.driver_rows, self.driver_linear, self.driver_selectors = _check_driver(driver)
        self.maneuver_inputs = _check_maneuver_inputs(maneuver_inputs)
        self.maneuver_start = _check_choice(maneuver_start, MANEUVER_STARTS, "maneuver start")
        self.maneuver_end_s = None if maneuver_end_s is None else _check_duration(maneuver_end_s)
        if self.maneuver_end_s is not None and not self.driver_rows:
            raise ServerError("a maneuver end needs a driver table")
        self.record_path = None if record_path is None else os.fspath(record_path)
        self.record_every = _check_record_every(record_every_s, self.step_s)
        self.priority = _check_priority(priority)
        self.cpu = _check_cpu(cpu)
        self.duration_s = _check_duration(duration_s)
        self.overrun_policy = _check_choice(overrun_policy, OVERRUN_POLICIES, "overrun policy")
        self.lock_memory = self.priority > 0 if lock_memory is None else bool(lock_memory)
        self.spin_us = _check_spin(spin_us, self.priority, self.period_s)
        pm_qos_us, off_because = _check_pm_qos(pm_qos_us, self.priority)
        #: why no PM QoS request is made (None: one is)
        self.pm_qos_off_because = off_because
        self.pm_qos = None if pm_qos_us is None else (
            PmQos(pm_qos_us) if pm_qos_path is None else PmQos(pm_qos_us, pm_qos_path))
        self.params_path = None if params_path is None else os.fspath(params_path)
        self.log_path = None if log_path is None else os.fspath(log_path)
        self.bus_kwargs = dict(bus_kwargs or {})

        self._ffi, self._lib = ffi, lib = _extension()
        #: the CAN matrix; bus name -> the CAN channel it is served on
        self.mapping, self.bus_channels = _load_mapping(mapping, self.rate_hz, self.channel,
                                                        interface, bus_channels)
        try:
            self.channels = LoopChannels(self.mapping, ffi, lib)
        except (ChannelError, ValueError) as e:
            raise ServerError(_one_line(e)) from None
        self.xcp_address, self.xcp_protocol, self.xcp_key = _check_xcp(xcp, xcp_protocol, xcp_key)
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
        self.control_tcp, self.control_token, self.control_tls = \
            control_tcp, control_token, control_tls
        if control_tcp is not None or control_token is not None or control_tls is not None:
            _check_control_tcp(control_tcp, control_token, control_tls)
        #: the live scope (``rt_loop.measure.scope``): min and max of chosen values per bucket of ticks
        self.scope = None
        #: the captures (``rt_loop.measure.capture``), made at the first (capture_manager)
        self.captures = None
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
        #: start-up times and memory at the first tick (``StartupMixin.start``), None before
        self.startup: dict | None = None
        self._t_start = self._t_end = None

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
                     self._stop_scope, self._stop_captures, self._stop_transport,
                     self._stop_logger,
                     self._stop_recorder, self._close_transport, self._release_cpu,
                     self._release_threads):
            try:
                step()
            except Exception as e:  # every step runs; the first error is raised
                errors.append(e)
        with self._read_lock:
            self.stats.read()
        errors = hook_errors + errors
        if errors:
            raise ServerError(f"stopping: {_one_line(errors[0])}")

    def add_stop_hook(self, hook: Callable[[], None]) -> None:
        """``hook()`` runs first in ``stop()``, while the loop still runs (the
        last added first): for what reads the running loop from outside, such
        as the live view (``dct_hil.ui``). An error it raises is reported by
        ``stop()`` after everything stopped."""
        self._stop_hooks.append(hook)

    def _stop_transport(self) -> None:
        for t in self.transports:
            t.stop()

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

