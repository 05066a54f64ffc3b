"""SIGINT/SIGTERM into a stop (plant.stop_signals): a handler may set the event
wherever the main thread is, inside the event's own wait included.

Why it exists: a Python handler runs in the main thread between two bytecodes;
``threading.Event.set`` from it waits for the lock ``Event.wait`` holds in that
same thread, forever. In CI a ``dct-hil serve`` under the test guest's load got
SIGTERM at that moment and kept running (and recording) for 15 minutes.
"""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from plant import stop_signals
from plant.stop_signals import StopEvent, StopSignals

REPO = Path(__file__).resolve().parents[1]


def test_a_threading_event_set_by_a_handler_hangs_when_the_signal_lands_in_its_wait():
    # the hazard itself, made certain: the signal raised while this thread holds the
    # event's lock (as Event.wait does around its flag test); the handler's set() waits
    code = ("import signal, threading\n"
            "ev = threading.Event()\n"
            "signal.signal(signal.SIGTERM, lambda *_: ev.set())\n"
            "with ev._cond:\n"
            "    signal.raise_signal(signal.SIGTERM)\n"
            "    x = [0]\n"
            "print('done')\n")
    with pytest.raises(subprocess.TimeoutExpired):
        subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=3)


def test_the_handler_sets_the_stop_while_the_main_thread_waits_on_it(monkeypatch):
    real_select = stop_signals.select.select
    raised = []

    def select_after_the_signal(r, w, x, timeout):
        if not raised:                    # the signal lands inside wait()
            raised.append(True)
            signal.raise_signal(signal.SIGTERM)
        return real_select(r, w, x, timeout)

    monkeypatch.setattr(stop_signals.select, "select", select_after_the_signal)
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals() as s:
        t0 = time.monotonic()
        assert s.event.wait(10.0) is True
        assert time.monotonic() - t0 < 5.0
    assert raised and s.received == [signal.SIGTERM] and not s.interrupted
    assert signal.getsignal(signal.SIGTERM) is before          # restored


def test_a_serve_like_watcher_stops_on_every_sigterm_at_any_moment(tmp_path):
    # the console's pattern (a status read, then a short wait on the stop), in a child
    # with a busy thread beside; SIGTERM at random moments, 60 times: every child ends
    code = ("import sys, threading\n"
            f"sys.path.insert(0, {str(REPO)!r})\n"
            "from plant.stop_signals import StopSignals\n"
            "def busy():\n"
            "    while True:\n"
            "        sum(range(100))\n"
            "threading.Thread(target=busy, daemon=True).start()\n"
            "with StopSignals() as s:\n"
            "    print('ready', flush=True)\n"
            "    while not s.event.is_set():\n"
            "        s.event.wait(0.0002)\n"
            "print('stopped', s.received, flush=True)\n")
    import random

    rng = random.Random(7)
    for _ in range(60):
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        assert p.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.0, 0.02))
        p.send_signal(signal.SIGTERM)
        out, _ = p.communicate(timeout=10)
        assert p.returncode == 0 and out.startswith(f"stopped [{int(signal.SIGTERM)}]"), out


def test_the_event_waits_times_out_wakes_every_waiter_and_clears():
    ev = StopEvent()
    assert ev.wait(0.05) is False and not ev.is_set()
    assert ev.wait(0) is False
    woke = []
    threads = [threading.Thread(target=lambda: woke.append(ev.wait(10.0))) for _ in range(3)]
    for t in threads:
        t.start()
    time.sleep(0.05)
    ev.set()
    ev.set()                                   # twice: no error, one byte is enough
    for t in threads:
        t.join(5.0)
    assert woke == [True, True, True]
    ev.clear()
    assert not ev.is_set() and ev.wait(0.05) is False
    ev.set()
    assert ev.wait(0.0) is True
    ev.close()
    assert ev.wait(0.01) is True               # closed: still answers its flag


def test_once_gives_the_next_signal_back_to_the_previous_handler():
    seen = []
    old = signal.signal(signal.SIGUSR1, lambda *_: seen.append("previous"))
    try:
        with StopSignals(once=True, signals=(signal.SIGUSR1,)) as s:
            os.kill(os.getpid(), signal.SIGUSR1)
            assert s.event.wait(5.0)
            os.kill(os.getpid(), signal.SIGUSR1)
            time.sleep(0.05)
        assert s.received == [signal.SIGUSR1] and seen == ["previous"]
    finally:
        signal.signal(signal.SIGUSR1, old)


def test_a_serve_prints_its_stacks_on_sigusr1_and_stops_on_sigterm(tmp_path):
    err_path = tmp_path / "serve.err"
    with open(err_path, "w") as err:
        p = subprocess.Popen([sys.executable, "-m", "dct_hil.cli", "serve", "--priority", "0",
                              "--no-pm-qos", "--quiet", "--duration", "60",
                              "--stats", str(tmp_path / "s.json")],
                             cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True)
        try:
            assert p.stdout.readline().startswith("dct-hil serve"), err_path.read_text()
            p.send_signal(signal.SIGUSR1)              # stacks: the process goes on
            deadline = time.monotonic() + 30
            while "most recent call first" not in err_path.read_text() and time.monotonic() < deadline:
                time.sleep(0.1)
            assert p.poll() is None
            p.send_signal(signal.SIGTERM)
            p.stdout.read()
            assert p.wait(timeout=60) == 0
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
    text = err_path.read_text()
    # every thread: the main one in the console's watch, the loop's in the C loop
    assert "in run_console" in text and "in _run" in text, text
    assert (tmp_path / "s.json").exists()
