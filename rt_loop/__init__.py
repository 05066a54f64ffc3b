"""The real-time plant server: every period (0.5 ms at 2 kHz) receive the TCU's
CAN frames, step the plant, send the frames due.

The tick runs in C (``csrc/rt_loop.c``, contract ``csrc/rt_loop.h``, compiled
into ``rt_loop._rt_loop``) in a thread of its own; Python sets it up and
watches it:

* ``rt_loop.server``: ``Server`` (set-up, loop thread, traffic log, stop), one
  module per concern: start-up and CPU, recording, reports, maneuvers, XCP and
  the control socket, the argument checks;
  ``rt_loop.console``: ``run_console`` (``dct-hil serve``);
* ``rt_loop.transport``: SocketCAN (hard real time) or a bridge to any
  python-can interface (soft real time);
* ``rt_loop.stats``: turnaround, execution time and wake-up latency
  percentiles, counters, the JSON report;
* ``rt_loop.status``: the live status and the summary.

Beside the loop and its server, two rooms: ``rt_loop.measure`` (XCP and the A2L,
MDF and CSV recording, stimulus, the scope: beside the tick, never in it) and
``rt_loop.tools`` (the benchmark, doctor, fuzz and soak: they drive a loop from
outside).

``Server``, ``ServerError``, ``TransportError`` and ``open_transport`` are
importable from here; nothing is loaded until first used.
"""

_LAZY = {
    "Server": "rt_loop.server",
    "ServerError": "rt_loop.server",
    "TransportError": "rt_loop.transport",
    "open_transport": "rt_loop.transport",
}

__all__ = ["Server", "ServerError", "TransportError", "open_transport"]   # _LAZY's keys


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'rt_loop' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
