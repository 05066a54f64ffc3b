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

``Server`` (``core``) is put together from one part per concern, each a
module that reads on its own:

* ``startup``: ``start``, the wait for the loop thread's set-up and its
  phases, the real-time checks, the loop's CPU kept to itself, PM QoS;
* ``recording``: the traffic log (``TrafficLogger``), the recording of the
  plant's outputs (``start_recording``, ``stop_recording``), the scope;
* ``reports``: ``snapshot``, ``report``, ``write_report`` and the counters;
* ``maneuvers``: maneuvers the loop plays, started and stopped while it
  runs, and the stimulus;
* ``remote``: the XCP slave and the control socket;
* ``checks``: the argument checks and the limits; ``errors``: ``ServerError``.

``rt_loop.console.run_console`` is ``dct-hil serve`` around it: live status,
SIGINT/SIGTERM, summary, JSON file.
"""

from rt_loop.server.checks import (
    DEFAULT_SPIN_US,
    MANEUVER_STARTS,
    MAX_DRIVER_ROWS,
    MAX_PERIOD_S,
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    OVERRUN_POLICIES,
)
from rt_loop.server.core import HYDRAULICS, Server
from rt_loop.server.errors import ServerError
from rt_loop.server.recording import LOG_FORMATS, TrafficLogger
from rt_loop.server.reports import MANEUVER_STATES
from rt_loop.server.startup import SOCKET_FRAMES_WANTED
from rt_loop.transport import TransportError

__all__ = [
    "DEFAULT_SPIN_US",
    "HYDRAULICS",
    "LOG_FORMATS",
    "MANEUVER_STARTS",
    "MANEUVER_STATES",
    "MAX_DRIVER_ROWS",
    "MAX_PERIOD_S",
    "MAX_RATE_HZ",
    "MIN_RATE_HZ",
    "OVERRUN_POLICIES",
    "SOCKET_FRAMES_WANTED",
    "Server",
    "ServerError",
    "TrafficLogger",
    "TransportError",
]
