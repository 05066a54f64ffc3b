"""XCP DAQ delivery benchmark: N signals at 2 kHz to pyxcp while a CPU-bound
Python thread runs in the server's process, against the same without it.

    python -m rt_loop.tools.bench_xcp_daq [--signals 100] [--window-s 10] [--pairs 2]
                                          [--protocol udp|tcp|both] [--priority 80]
                                          [--json out/bench-xcp-daq.json]

The plant server (2 kHz on python-can's virtual bus, no TCU, SCHED_FIFO at
``--priority`` when granted) serves XCP on loopback; pyxcp, in a process of
its own (so that only the server's process carries the busy thread), measures
``--signals`` values on the tick event: the loop's tick counter and plant
doubles, one DAQ list with timestamps. In one DAQ session the windows
alternate, ``--pairs`` times: ``busy`` (a Python thread in the server's
process computing without pause: it takes the GIL whenever it can) and
``quiet``. Per window: the rows (ticks) the loop made and pyxcp received,
the DTOs the sender sent (rows x ODTs), lost (ticks missing between the first
and the last received, per window), and the DTO delay from the tick's
deadline to the send, measured by the C sender (``rt_xcp_send.h``: its
histogram of 1 us bins, read before and after the window): p50, p99,
p99.9 and max. Figures to stdout and the JSON file; exit 0 (1 with
``--check`` when a DTO was lost).
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import sys
import threading
import time
import uuid
from array import array

from plant import argtypes

RCVBUF_BYTES = 8 << 20               # the master's socket: bursts while its process waits
QS = (50, 99, 99.9)


# ---- the master, in a process of its own -----------------------------------------

def _master(conn, host: str, port: int, protocol: str, measurements: list, keep: tuple) -> None:
    """pyxcp measuring one DAQ list on the tick event until told to stop; sends
    back the timestamps (ns) and the ``keep`` columns of every row."""
    from pyxcp.config import (
        create_application_from_config,
        reset_application,
        set_application,
    )
    from pyxcp.daq_stim import DaqList, DaqOnlinePolicy
    from pyxcp.master import Master

    logging.getLogger("pyxcp").setLevel(logging.CRITICAL)
    app = create_application_from_config(
        {"Transport": {"Eth": {"host": host, "port": port, "protocol": protocol.upper(),
                               "tcp_nodelay": True}},
         "General": {"disable_error_handling": True}},
        log_level=logging.CRITICAL)
    set_application(app)
    rows: list = []

    class Rows(DaqOnlinePolicy):
        def initialize(self):
            pass

        def finalize(self):
            pass

        def on_daq_list(self, daq_list, ts0, ts1, payload):
            rows.append((ts1, payload))

    lists = [DaqList(name="tick", event_num=0, stim=False, enable_timestamps=True,
                     measurements=[tuple(m) for m in measurements], priority=0, prescaler=1)]
    policy = Rows(lists)
    try:
        with Master("eth", config=app, policy=policy) as x:
            sock = getattr(x.transport, "sock", None)
            if sock is not None:
                import socket

                for opt in ("SO_RCVBUFFORCE", "SO_RCVBUF"):
                    try:
                        sock.setsockopt(socket.SOL_SOCKET, getattr(socket, opt), RCVBUF_BYTES)
                        break
                    except (OSError, AttributeError):
                        continue
            x.connect()
            policy.setup()
            policy.start()
            conn.send(("started", lists[0].odt_count))
            conn.recv()                                   # the parent: stop
            policy.stop()
            last = -1
            while last != len(rows):                      # pyxcp decodes behind the socket
                last = len(rows)
                time.sleep(0.3)
            x.disconnect()
        names = [h[0] if isinstance(h, (tuple, list)) else h for h in lists[0].headers]
        cols = {name: array("d" if name != "ticks" else "Q",
                            (r[1][names.index(name)] for r in rows)) for name in keep}
        conn.send(("rows", array("q", (r[0] for r in rows)), cols))
    except Exception as e:  # one line to the parent, which reports it
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        reset_application()
        conn.close()


class Master:
    """The master process: start() returns once its DAQ runs; stop() returns
    (timestamps ns, {column: values}) of every row received."""

    def __init__(self, address: tuple, protocol: str, measurements: list, keep: tuple) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_master, args=(child, address[0], address[1], protocol,
                                                       measurements, keep), daemon=True)
        self.odts = 0

    def start(self, timeout_s: float = 60.0) -> None:
        self._proc.start()
        kind, *rest = self._receive(timeout_s)
        if kind != "started":
            raise RuntimeError(f"the pyxcp master: {rest[0] if rest else kind}")
        self.odts = rest[0]

    def stop(self, timeout_s: float = 120.0):
        self._conn.send("stop")
        kind, *rest = self._receive(timeout_s)
        self._proc.join(30)
        if kind != "rows":
            raise RuntimeError(f"the pyxcp master: {rest[0] if rest else kind}")
        return rest[0], rest[1]

    def _receive(self, timeout_s: float):
        try:
            if self._conn.poll(timeout_s):
                return self._conn.recv()
        except EOFError:
            raise RuntimeError(f"the pyxcp master ended (exit code {self._proc.exitcode})") from None
        self._proc.kill()
        raise RuntimeError(f"the pyxcp master said nothing for {timeout_s:g} s")

    def kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(10)


# ---- the busy thread ---------------------------------------------------------------

class Busy:
    """A CPU-bound Python thread: it computes without pause (and so holds the
    GIL whenever the interpreter lets it)."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self.rounds = 0
        self._thread: threading.Thread | None = None

    def _run(self) -> None:
        while not self._stop.is_set():
            sum(k * k for k in range(20000))
            self.rounds += 1

    def __enter__(self) -> Busy:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="busy", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


# ---- figures ---------------------------------------------------------------------

def histogram_figures(hist: list[int]) -> dict:
    """count, p50 / p99 / p99.9 and max (us, upper bin edges) of a 1 us histogram."""
    from rt_loop.measure.xcp.transport import delay_percentiles_us

    n = sum(hist)
    top = max((k for k, c in enumerate(hist) if c), default=None)
    pct = delay_percentiles_us(hist, QS)
    return {"dtos": n, "p50_us": pct["p50"], "p99_us": pct["p99"], "p99_9_us": pct["p99.9"],
            "max_us": None if top is None else top + 1,
            "above_range": hist[-1] if hist else 0}


def window_rows(ticks, first: int, last: int) -> dict:
    """Rows of the ticks first..last (inclusive) received, and the missing ones."""
    got = sorted({t for t in ticks if first <= t <= last})
    if not got:
        return {"expected": last - first + 1, "received": 0, "lost": last - first + 1}
    expected = got[-1] - got[0] + 1                      # the window's ends may be cut by a tick
    return {"expected": expected, "received": len(got), "lost": expected - len(got)}


def _print_window(w: dict) -> None:
    d = w["delay"]
    print(f"  {w['protocol']} {w['case']:5s} window {w['index']}: rows {w['rows']['received']:6d} of "
          f"{w['rows']['expected']:6d} ({w['rows']['lost']} lost), DTOs {w['dtos_expected']} expected "
          f"{w['dtos_received']} received; delay p50 {d['p50_us']} p99 {d['p99_us']} "
          f"p99.9 {d['p99_9_us']} max {d['max_us']} us; busy rounds {w['busy_rounds']}",
          flush=True)


# ---- one run ---------------------------------------------------------------------

def run(protocol: str, signals: int, window_s: float, pairs: int, priority: int) -> dict:
    from rt_loop._rt_loop import ffi
    from rt_loop.server import Server
    from rt_loop.tools.xcp_bench import measurable_doubles

    ticks_off = ffi.offsetof("rt_loop", "stats", "ticks")
    measurements = [("ticks", ticks_off, 0, "U64")]
    measurements += [(n, off, 0, "F64") for n, off in measurable_doubles(ffi, signals - 1)]
    srv = Server(f"bench-xcp-daq-{uuid.uuid4().hex[:8]}", interface="virtual", priority=priority,
                 xcp="127.0.0.1:0", xcp_protocol=protocol, pm_qos_us=None)
    srv.start()
    master = Master(tuple(srv.xcp.address), protocol, measurements, ("ticks",))
    windows = []
    try:
        master.start()
        sender = srv.xcp.server.sender
        time.sleep(0.5)                                   # the first rows in
        for pair in range(pairs):
            for case in ("busy", "quiet"):
                busy = Busy()
                hist0, t0 = sender.delays(), int(srv.stats.read().ticks)
                out0 = sender.stats()["dtos_out"]
                if case == "busy":
                    busy.__enter__()
                time.sleep(window_s)
                if case == "busy":
                    busy.__exit__()
                hist1, t1 = sender.delays(), int(srv.stats.read().ticks)
                out1 = sender.stats()["dtos_out"]
                hist = [b - a for a, b in zip(hist0, hist1)]
                windows.append({"protocol": protocol, "case": case, "index": pair, "ticks": (t0, t1),
                                "delay": histogram_figures(hist),
                                "delay_hist_us": {k: n for k, n in enumerate(hist) if n},
                                "dtos_sent": out1 - out0, "busy_rounds": busy.rounds})
        stamps, cols = master.stop()
    except BaseException:
        master.kill()
        raise
    finally:
        x = srv.xcp_counters()
        s = srv.stats.read()
        srv.stop()
    ticks = cols["ticks"]
    for w in windows:
        t0, t1 = w.pop("ticks")
        # the row of a tick carries the count the previous tick published: one less
        w["rows"] = window_rows(ticks, t0 + 1, t1 - 2)
        w["dtos_expected"] = w["rows"]["expected"] * master.odts
        w["dtos_received"] = w["rows"]["received"] * master.odts
        _print_window(w)
    steps = [b - a for a, b in zip(ticks, ticks[1:])]
    return {
        "protocol": protocol,
        "signals": signals,
        "odts_per_row": master.odts,
        "windows": windows,
        "rows_received": len(ticks),
        "rows_lost": sum(d - 1 for d in steps if d > 1),
        "rows_repeated": sum(1 for d in steps if d < 1),
        "loop": {"ticks": int(s.ticks), "overruns": int(s.overruns),
                 "skipped_ticks": int(s.skipped_ticks), "sched_fifo": bool(s.rt_policy_ok)},
        "transport": (x or {}).get("transport"),
        "dto_ring_dropped": ((x or {}).get("loop") or {}).get("dto_ring_dropped"),
    }


def summary(runs: list[dict]) -> dict:
    """Per protocol and case: the windows' rows and DTOs, expected and lost, and
    the delay figures of all their DTOs together (their histograms summed)."""
    out: dict = {}
    for r in runs:
        for case in ("busy", "quiet"):
            ws = [w for w in r["windows"] if w["case"] == case]
            hist = [0] * max((max(w["delay_hist_us"], default=0) + 1 for w in ws), default=0)
            for w in ws:
                for k, n in w["delay_hist_us"].items():
                    hist[k] += n
            d = histogram_figures(hist)
            out.setdefault(r["protocol"], {})[case] = {
                "windows": len(ws),
                "rows_expected": sum(w["rows"]["expected"] for w in ws),
                "rows_lost": sum(w["rows"]["lost"] for w in ws),
                "dtos_expected": sum(w["dtos_expected"] for w in ws),
                "dtos_received": sum(w["dtos_received"] for w in ws),
                "delay_p50_us": d["p50_us"], "delay_p99_us": d["p99_us"],
                "delay_p99_9_us": d["p99_9_us"], "delay_max_us": d["max_us"],
            }
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rt_loop.tools.bench_xcp_daq",
                                description=__doc__.split("\n")[0])
    p.add_argument("--signals", type=argtypes.whole_number(2, 1000), default=100)
    p.add_argument("--window-s", type=argtypes.seconds, default=10.0)
    p.add_argument("--pairs", type=argtypes.whole_number(1), default=2)
    p.add_argument("--protocol", choices=("udp", "tcp", "both"), default="both")
    p.add_argument("--priority", type=argtypes.priority, default=80)
    p.add_argument("--json", default="out/bench-xcp-daq.json")
    p.add_argument("--check", action="store_true", help="exit 1 when a DTO was lost")
    args = p.parse_args(argv)
    from plant.machine import machine_info

    protocols = ("udp", "tcp") if args.protocol == "both" else (args.protocol,)
    print(f"XCP DAQ: {args.signals} signals at 2 kHz to pyxcp (its own process), windows of "
          f"{args.window_s:g} s, busy / quiet x {args.pairs}, {', '.join(protocols)}", flush=True)
    runs = []
    for protocol in protocols:
        try:
            runs.append(run(protocol, args.signals, args.window_s, args.pairs, args.priority))
        except (OSError, RuntimeError) as e:
            print(f"bench-xcp-daq: {protocol}: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"bench-xcp-daq: interrupted during {protocol}; nothing written", file=sys.stderr)
            return 130
    figures = summary(runs)
    lost = 0
    for protocol, cases in figures.items():
        for case, f in cases.items():
            lost += f["rows_lost"]
            print(f"{protocol} {case:5s}: DTOs {f['dtos_received']} of {f['dtos_expected']} "
                  f"({f['dtos_expected'] - f['dtos_received']} lost); DTO delay (tick deadline "
                  f"to send) p50 {f['delay_p50_us']} p99 {f['delay_p99_us']} p99.9 "
                  f"{f['delay_p99_9_us']} max {f['delay_max_us']} us", flush=True)
    result = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": machine_info(),
              "args": vars(args), "summary": figures, "runs": runs}
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
        print(f"wrote {args.json}")
    return 1 if args.check and lost else 0


if __name__ == "__main__":
    sys.exit(main())
