"""The server's recording: the traffic log, the recording of the plant's
outputs, and the live scope.

``TrafficLogger`` drains the loop's log ring (every CAN frame, both
directions) into a python-can writer. A recording (CSV, or MF4 with the CAN
traffic as bus logging in the same file) is asked for at construction
(``record_path``) or started and stopped while the loop runs
(``start_recording``, ``stop_recording``); one at a time. The scope
(``rt_loop.measure.scope``) keeps min and max of chosen values per bucket of
ticks for the live view.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Any

from can_dbc.python_can import python_can
from rt_loop.drain import RingDrain
from rt_loop.drain import one_line as _one_line
from rt_loop.measure.recorder import Recorder
from rt_loop.server.checks import _number
from rt_loop.server.errors import ServerError

__all__ = ["LOG_FORMATS", "RecordingMixin", "TrafficLogger"]

#: traffic log suffixes and what writes them (python-can picks the writer by suffix)
LOG_FORMATS = {".log": "candump", ".blf": "Vector BLF", ".asc": "Vector ASC",
               ".mf4": "ASAM MDF 4 (needs asammdf)", ".csv": "CSV", ".trc": "PEAK TRC",
               ".db": "SQLite", ".txt": "text"}
_LOG_BATCH = 4096


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
        super().__init__(path)
        channels = [channel] if isinstance(channel, str) else list(channel)
        self.channel = channels[0]
        self.channels = channels
        suffix = os.path.splitext(self.path)[1].lower()
        can = python_can(mf4=suffix == ".mf4")
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
    number = python_can().util.channel2int(channel)
    return number if number is not None and 0 <= number <= 63 else None



class RecordingMixin:
    """``Server``'s part that writes what the loop produces: the traffic log
    (``logger``), the recording (``recorder``, ``recording``) and the scope.

    Reads the server's loop (``_ffi``, ``_lib``, ``_l``), its ``channels``,
    ``bus_channels``, ``faults``, ``log_path``, ``record_path``,
    ``record_every`` and ``step_s``; ``_rec_lock`` guards the recording.
    """

    def _open_outputs(self) -> None:
        """Opens the traffic log and the recording asked for at construction
        (their files; nothing is drained before ``_start_outputs``)."""
        if self.log_path is not None:
            self.logger = TrafficLogger(self.log_path, list(self.bus_channels.values()))
        if self.record_path is not None:
            try:
                self.recorder = self._new_recorder(self.record_path)
            except OSError as e:
                raise ServerError(str(e)) from None

    def _new_recorder(self, path: str) -> Any:
        """A recorder of every plant output into ``path``: MF4 with the CAN traffic
        (``MdfRecorder``) by the suffix .mf4 or .mdf, else CSV (``Recorder``)."""
        if path.lower().endswith((".mf4", ".mdf")):
            from rt_loop.measure.mdf_recorder import MdfRecorder

            return MdfRecorder(path, self.channels.command_names,
                               channels=list(self.bus_channels.values()))
        return Recorder(path, self.channels.command_names)

    def _logs_frames(self) -> bool:
        """The loop must log the CAN frames: for the traffic log, or for an MF4
        recording's bus logging."""
        mf4 = self.recorder is not None and not isinstance(self.recorder, Recorder)
        return self.logger is not None or mf4

    def _start_outputs(self, wall0: float) -> None:
        """Starts draining the traffic log and the recording; ``wall0``: the
        wall-clock time of loop time 0 (the frames' timestamps)."""
        ffi, lib, loop = self._ffi, self._lib, self._l
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

    def _start_scope(self) -> None:
        from rt_loop.measure.scope import Scope

        self.scope = Scope(self._ffi, self._lib, self._l, self.channels, self.step_s)
        self.scope.start()

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
            x = _number(every_s, "record interval")
            if not (math.isfinite(x) and x > 0):
                raise ServerError(f"record interval must be above 0 s, got {every_s!r}")
            every = max(1, int(round(x / self.step_s)))
        with self._rec_lock:
            if not self.running:
                raise ServerError("the loop is not running")
            if self._recording is not None:
                raise ServerError(f"a recording runs already: {self._recording['path']}")
            # the rings the run left out of its locked memory, locked before the loop
            # writes them (rt_loop_hold_rings; nothing when memory is not locked)
            rc = lib.rt_loop_hold_rings(loop, lib.RT_RELEASE_REC | lib.RT_RELEASE_LOG)
            if rc != 0 and not getattr(self, "_hold_warned", False):
                self._hold_warned = True
                self.warnings.append(f"the recording's rings could not be locked "
                                     f"({os.strerror(-rc)}): the tick may fault on them")
            try:
                rec = self._new_recorder(path)
            except OSError as e:
                raise ServerError(_one_line(e)) from None
            mf4 = not isinstance(rec, Recorder)
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

    def _stop_logger(self) -> None:
        if self.logger is not None:
            self.logger.stop()

    def _stop_recorder(self) -> None:
        with self._rec_lock:
            if self.recorder is not None and self._recording is not None:
                self._recording = None
                self.recorder.stop()

    def capture_manager(self) -> Any:
        """The captures of this loop (``rt_loop.measure.capture.Captures``), made at
        the first use while the loop runs."""
        with self._rec_lock:
            if self.captures is None:
                if not self.running:
                    raise ServerError("captures need a running loop")
                from rt_loop.measure.capture import Captures

                self.captures = Captures(self)
            return self.captures

    def _stop_captures(self) -> None:
        if self.captures is not None:
            self.captures.close()

    def _stop_scope(self) -> None:
        if self.scope is not None:
            self.scope.stop()
