"""``dct-hil serve`` at the console: a started server watched until its end.

``run_console(server, stats_path)`` starts the server (Ctrl-C or SIGTERM
during start-up abandon it), prints the banner and a live status line, stops
on a signal, the duration or the loop's own end, and writes the report with
its timing verdict (the signals through ``plant.stop_signals.StopSignals``,
whose event a signal handler may set).
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Any, TextIO

from plant.stop_signals import StopSignals
from rt_loop import status as _status
from rt_loop import verdict as _verdict
from rt_loop.server import Server, ServerError

__all__ = ["run_console"]


def run_console(server: Server, stats_path: str | os.PathLike, quiet: bool = False,
                out: TextIO | None = None, err: TextIO | None = None,
                strict: bool = False, started: Any = None) -> int:
    """Runs ``server`` with a live status until it ends or SIGINT/SIGTERM arrives.

    The live status is redrawn in place about 5 times per second when
    ``out`` is a terminal, else printed as one line per second (``quiet``:
    none). On the way out the loop is stopped, the log and the bus are
    flushed and closed, a summary is printed and the JSON stats file
    written. Returns the exit code: 0 after a clean stop (duration reached,
    SIGTERM), 130 after SIGINT (Ctrl-C, as everywhere in dct-hil), 1 if the
    loop was stopped by the overrun policy or a transport error, or the
    traffic log could not be written completely.

    The summary ends with the run's verdict on its own timing
    (``rt_loop.verdict.serve_verdict``, also in the JSON file as ``verdict``);
    an INVALID run prints a warning to ``err``, and with ``strict`` a run that
    would exit 0 exits ``verdict.EXIT_INVALID`` (3) instead. ``started``:
    called with the server once it runs (an error it raises stops the server
    and propagates).
    """
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    signals = StopSignals()
    stop = signals.event
    view = None
    try:
        signals.__enter__()
        try:
            server.start(progress=lambda line: print(f"dct-hil: {line}", file=err, flush=True),
                         cancel=stop)
        except ServerError as e:
            if not signals.received:
                raise
            print(f"dct-hil: stopped by {signal.Signals(signals.received[0]).name} before the "
                  f"loop ran ({e})", file=err, flush=True)
            return 130 if signals.interrupted else 0
        if started is not None:
            started(server)        # what runs beside the loop (the reference TCU); may raise
        for line in _status.banner_lines(server, stats_path):
            print(line, file=out, flush=True)
        for warning in server.warnings:
            print(f"dct-hil: warning: {warning}", file=err, flush=True)
        view = _status.LiveStatus(out, quiet=quiet)
        while not stop.is_set() and server.running:
            view.update(server.snapshot(), server)
            stop.wait(view.interval_s)
    finally:
        try:
            server.stop()
        finally:
            signals.__exit__()
    if view is not None:
        view.close()
    report = server.report()
    report["verdict"] = _verdict.serve_verdict(report)
    server.write_report(stats_path, report)
    for line in _status.summary_lines(report, stats_path):
        print(line, file=out)
    out.flush()

    state = report["run"]["state"]
    log = report.get("log")
    code = 130 if signals.interrupted else 0
    if report["run"]["error"]:
        print(f"dct-hil: error: the loop stopped: {report['run']['error']}", file=err)
        code = 1
    elif state == "overrun_stop":
        print(f"dct-hil: stopped by the overrun policy after {report['run']['ticks']} ticks "
              f"(turnaround max {report['turnaround']['max_us']:.1f} us, period "
              f"{server.period_s * 1e6:g} us)", file=err)
        code = 1
    elif log and log["error"]:
        print(f"dct-hil: error: the traffic log is incomplete: {log['error']}", file=err)
        code = 1
    warning = _verdict.warning_line(report["verdict"], strict and code == 0)
    if warning:
        print(warning, file=err)
    return _verdict.exit_code(report["verdict"], strict, code)

