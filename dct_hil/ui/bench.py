"""Live view benchmark: the loop with browsers attached to the bench page beside
the same loop without them, in one run.

    python -m dct_hil.ui.bench [--pairs 3] [--round-s 15] [--browsers 2]
                               [--priority 80] [--json out/bench-ui.json] [--check]

Per pair, one thing at a time: a floor round (the C floor loop,
``rt_loop.floor``: the machine's wake-up latency at the loop's period with no
work), then a loop round without the page and one with the page served
(``dct_hil.ui.UiServer``) and ``--browsers`` headless Chromium sessions on
it (Debian's /usr/bin/chromium driven by Selenium), each streaming its
traces 20 times a second; the two loop rounds take turns in going first
(pair 1 without the page first, pair 2 with it first, ...). The loop runs on
one CPU (``--cpu``, default the last) and everything else of the benchmark
(browsers, the page's server, the TCU peer) on the others, as on a bench PC
whose loop has a CPU of its own. Loop rounds are the plant server at 2 kHz
under SCHED_FIFO on the bridge transport with a test TCU peer sending
commands (as ``rt_loop.tools.bench``). Each loop round settles first (the
browsers start and load the page there); its figures are those of the
``--round-s`` window after that (the difference of two copies of the loop's
1 us histograms and counters).

What the page can change in the loop, and what is judged: the tick's own
execution time (the mean of the ticks under 20 us, as the XCP and fault
benchmarks judge it, and the median) and the scope ring's drops (buckets the
page's reader did not take in time). The target: the mean execution with
the browsers at most 10 % above without (the median of the pairs' ratios),
and no scope bucket dropped. The turnaround's p99.9 and the floor's are
reported beside them, not judged: on a shared machine a round's p99.9
follows the host's wake-up latency, which the page does not set. Figures to
stdout, the JSON file; exit 0, 1 with ``--check`` when the target is missed,
2 for a missing browser or a bad option.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
import uuid
from typing import Any

import numpy as np

from rt_loop.tools.ab_round import execution_mean_under

TARGET_RATIO = 1.10
SETTLE_S = 3.0
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"



def open_browser(url: str, user_dir: str) -> Any:
    """A headless Chromium on ``url`` (Selenium with the system's driver)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--no-first-run", "--disable-background-networking", "--disable-component-update",
              "--disable-sync", "--window-size=1400,1000", f"--user-data-dir={user_dir}"):
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    driver.set_page_load_timeout(60)
    driver.set_script_timeout(60)
    driver.get(url)
    return driver


def _page_streams(driver: Any, timeout_s: float = 60.0) -> None:
    """Waits until the page's Bokeh document exists and its data moves."""
    end = time.monotonic() + timeout_s
    script = ("const d = window.Bokeh && Bokeh.documents && Bokeh.documents[0];"
              "const s = d && d.get_model_by_name('traces');"
              "if (!s || !s.data.t || !s.data.t.length) return null;"
              "return s.data.t[s.data.t.length - 1];")
    first = None
    while time.monotonic() < end:
        try:
            t = driver.execute_script(script)
        except Exception:  # the page is still loading
            t = None
        if t is not None:
            if first is None:
                first = t
            elif t > first:
                return
        time.sleep(0.25)
    raise RuntimeError("the bench page did not stream data within "
                       f"{timeout_s:g} s")


def updates_per_s(driver: Any, seconds: float = 3.0) -> float | None:
    """Updates of the page's traces per second as the browser shows them: how
    often the newest plotted time changed, looked at every 2 ms in the page
    (None: the page does not answer)."""
    try:
        driver.execute_script(
            "const s = Bokeh.documents[0].get_model_by_name('traces');"
            "window.__dct_updates = 0; window.__dct_last = null;"
            "window.__dct_timer = setInterval(() => { const t = s.data.t;"
            "  const v = t.length ? t[t.length - 1] : null;"
            "  if (v !== window.__dct_last) { window.__dct_updates += 1; window.__dct_last = v; }"
            "}, 2);")
        time.sleep(seconds)
        n = driver.execute_script("clearInterval(window.__dct_timer); return window.__dct_updates;")
    except Exception:  # a browser too busy to answer: not measured
        return None
    return max(0.0, float(n) - 1.0) / seconds


def _window(server: Any, seconds: float, stop: threading.Event) -> dict:
    """The loop's histograms and counts over the next ``seconds``."""
    from rt_loop.stats import hist_percentiles

    ffi = server._ffi

    def hist(field: Any) -> np.ndarray:
        return np.frombuffer(ffi.buffer(field), dtype=np.uint64).astype(np.int64)

    def copy() -> dict:
        s = server.stats.read()
        return {"turnaround": hist(s.turnaround_hist), "execution": hist(s.exec_hist),
                "latency": hist(s.latency_hist),
                "ticks": int(s.ticks), "overruns": int(s.overruns),
                "skipped": int(s.skipped_ticks),
                "scope_dropped": server.scope.dropped if server.scope is not None else 0}

    with server._read_lock:
        a = copy()
    stop.wait(seconds)
    with server._read_lock:
        b = copy()
    out: dict = {k: b[k] - a[k] for k in ("ticks", "overruns", "skipped", "scope_dropped")}
    for key in ("turnaround", "execution", "latency"):
        h = b[key] - a[key]
        top = np.flatnonzero(h)
        hi = float(top[-1] + 1) if len(top) else 0.0      # the upper edge of the last bin used
        out[key] = hist_percentiles(h.astype(np.uint64), hi)
    out["execution_mean_under_20us"] = execution_mean_under(enumerate(b["execution"] - a["execution"]), 20)
    return out


def _loop_round(args: Any, browsers: int, stop: threading.Event) -> dict:
    from can_dbc.peer import CanPeer
    from rt_loop.server import Server

    channel = f"bench-ui-{uuid.uuid4().hex[:8]}"
    srv = Server(channel, interface="virtual", priority=args.priority, cpu=args.cpu)
    srv.start()
    peer = CanPeer.open(side="tcu", interface="virtual", channel=channel,
                        values={"SolenoidCurrent1": 0.4, "SolenoidCurrent2": 0.0})
    ui = None
    drivers: list = []
    dirs: list = []
    rates: list = []
    feeding = threading.Event()

    def feed() -> None:                     # the clutch currents swap every second
        t0 = time.monotonic()
        while not feeding.is_set():
            on = int(time.monotonic() - t0) % 2 == 0
            peer.set(SolenoidCurrent1=0.4 if on else 0.0, SolenoidCurrent2=0.0 if on else 0.4)
            feeding.wait(0.05)

    feeder = threading.Thread(target=feed, name="bench-ui-peer", daemon=True)
    feeder.start()
    try:
        t_settle = time.monotonic()
        if browsers:
            from dct_hil.ui.server import UiServer

            mine = os.sched_getaffinity(0)
            os.sched_setaffinity(0, args.others)   # inherited by the page's thread, the browsers
            try:
                ui = UiServer(srv, ("127.0.0.1", 0), recordings_dir=tempfile.mkdtemp())
                ui.start()
                for _ in range(browsers):
                    d = tempfile.mkdtemp(prefix="bench-ui-chromium-")
                    dirs.append(d)
                    drivers.append(open_browser(ui.url, d))
            finally:
                os.sched_setaffinity(0, mine)
            for drv in drivers:
                _page_streams(drv)
            rates = [updates_per_s(drv, 2.0) for drv in drivers]
        rest = SETTLE_S - (time.monotonic() - t_settle)
        if rest > 0:
            stop.wait(rest)
        settle_s = time.monotonic() - t_settle
        fig = _window(srv, args.round_s, stop)
        sessions = ui.counts.get("sessions_open") if ui is not None else 0
    finally:
        feeding.set()
        feeder.join(2.0)
        for drv in drivers:
            try:
                drv.quit()
            except Exception:  # the round's figures are taken
                pass
        if ui is not None:
            ui.stop()
        peer.close()
        srv.stop()
        for d in dirs:
            shutil.rmtree(d, ignore_errors=True)
    return {"browsers": browsers, "sessions": sessions, "page_updates_per_s": rates,
            "settle_s": round(settle_s, 1), **fig}


def _floor_round(args: Any, stop: threading.Event) -> dict:
    from rt_loop.floor import measure_floor

    fig = measure_floor(duration_s=args.round_s, rate_hz=2000.0, priority=args.priority,
                        cpu=args.cpu, pm_qos_us=0, stop=stop)
    return {k: fig.get(k) for k in ("p50_us", "p99_us", "p99_9_us", "max_us", "late_wakeups")}


def _line(r: dict) -> str:
    ta, ex = r["turnaround"], r["execution"]
    what = f"{r['browsers']} browsers" if r["browsers"] else "no browser"
    return (f"{what:11s} execution mean<20us {r['execution_mean_under_20us']:.2f} p50 "
            f"{ex['p50_us']:.0f} p99.9 {ex['p99_9_us']:.0f} us; scope drops {r['scope_dropped']}; "
            f"turnaround p50 {ta['p50_us']:.0f} p99.9 {ta['p99_9_us']:.0f} max {ta['max_us']:.0f} us; "
            f"overruns {r['overruns']} in {r['ticks']} ticks"
            + (f"; page updates/s {', '.join(f'{x:.1f}' for x in r['page_updates_per_s'] if x)}"
               if r["page_updates_per_s"] else ""))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m dct_hil.ui.bench",
                                description=__doc__.split("\n")[0])
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--round-s", type=float, default=15.0)
    p.add_argument("--browsers", type=int, default=2)
    p.add_argument("--priority", type=int, default=80)
    p.add_argument("--cpu", type=int, default=None,
                   help="the loop's CPU (default the last); the browsers, the page's server and "
                        "the TCU peer run on the others")
    p.add_argument("--json", default="out/bench-ui.json")
    p.add_argument("--check", action="store_true")
    args = p.parse_args(argv)
    if not (args.pairs >= 1 and args.round_s > 0 and 1 <= args.browsers <= 8
            and 0 <= args.priority <= 99):
        p.error("--pairs >= 1, --round-s > 0, --browsers 1..8, --priority 0..99")
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not os.access(exe, os.X_OK):
            print(f"dct_hil.ui.bench: {exe} not found (apt-get install chromium chromium-driver)",
                  file=sys.stderr)
            return 2
    from plant.machine import machine_info

    cpus = sorted(os.sched_getaffinity(0))
    if args.cpu is None:
        args.cpu = cpus[-1]
    if args.cpu not in cpus:
        p.error(f"--cpu {args.cpu}: this process may use CPUs {cpus}")
    others = [c for c in cpus if c != args.cpu] or cpus
    args.others = others
    print(f"loop on CPU {args.cpu}; browsers, page server and TCU peer on CPUs {others}",
          flush=True)
    stop = threading.Event()
    pairs = []
    for k in range(args.pairs):
        floor = _floor_round(args, stop)
        print(f"pair {k + 1} floor       wake-up p50 {floor['p50_us']:.0f} p99.9 "
              f"{floor['p99_9_us']:.0f} max {floor['max_us']:.0f} us; late "
              f"{floor['late_wakeups']}", flush=True)
        rounds = {}
        for browsers in ((0, args.browsers) if k % 2 == 0 else (args.browsers, 0)):
            rounds[browsers] = _loop_round(args, browsers, stop)
            print(f"pair {k + 1} {_line(rounds[browsers])}", flush=True)
        without, with_ = rounds[0], rounds[args.browsers]
        pairs.append({"floor": floor, "without": without, "with": with_,
                      "first": "without" if k % 2 == 0 else "with",
                      "execution_ratio": with_["execution_mean_under_20us"]
                      / without["execution_mean_under_20us"],
                      "p99_9_ratio": with_["turnaround"]["p99_9_us"]
                      / max(without["turnaround"]["p99_9_us"], 1.0)})
    ratios = [x["execution_ratio"] for x in pairs]
    median = statistics.median(ratios)
    drops = sum(x["with"]["scope_dropped"] for x in pairs)

    def med(side: str, key: str) -> float:
        return statistics.median(x[side][key] for x in pairs)

    print(f"execution mean of the ticks under 20 us, median of {len(pairs)} pairs: without "
          f"{med('without', 'execution_mean_under_20us'):.2f} us, with {args.browsers} browsers "
          f"{med('with', 'execution_mean_under_20us'):.2f} us; ratio per pair "
          + ", ".join(f"{r:.3f}" for r in ratios)
          + f"; median {median:.3f} (target at most {TARGET_RATIO:.2f}); scope buckets dropped "
          f"with the page: {drops}")
    p999 = [x["p99_9_ratio"] for x in pairs]
    print("turnaround p99.9 (reported, not judged: it follows the host's wake-ups), ratio per "
          "pair " + ", ".join(f"{r:.2f}" for r in p999) + "; floor p99.9 per pair "
          + ", ".join(f"{x['floor']['p99_9_us']:.0f}" for x in pairs) + " us")
    report = {"benchmark": "ui", "browsers": args.browsers, "round_s": args.round_s,
              "loop_cpu": args.cpu, "other_cpus": others, "pairs": pairs,
              "judged": "execution_mean_under_20us ratio and scope drops",
              "median_execution_ratio": median, "scope_dropped_with_page": drops,
              "median_p99_9_ratio": statistics.median(p999), "target_ratio": TARGET_RATIO,
              "machine": machine_info(), "pass": median <= TARGET_RATIO and drops == 0}
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2, default=float)
    print(f"figures in {args.json}")
    return 1 if args.check and not report["pass"] else 0


if __name__ == "__main__":
    sys.exit(main())
