"""The server waits for its loop's own readiness, however long the loop's
set-up takes, says what it waits for, and can be cancelled while waiting.

A slow start is made by holding the loop thread back before it enters the
C loop (the phase a loaded machine shows first); nothing here is timed
beyond generous limits.
"""

import threading
import time
import uuid

import pytest

from rt_loop import console
from rt_loop.server import Server, ServerError, startup


def new_server(**kw):
    kw.setdefault("priority", 0)
    return Server(f"dct-test-{uuid.uuid4().hex[:10]}", interface="virtual", **kw)


@pytest.fixture
def slow_entry(monkeypatch):
    """The loop thread waits on this event before it calls rt_loop_run."""
    gate = threading.Event()
    original = Server._run

    def held_back(self):
        gate.wait(60)
        original(self)

    monkeypatch.setattr(Server, "_run", held_back)
    monkeypatch.setattr(startup, "START_NOTE_S", 0.05)     # read by StartupMixin._await_running
    yield gate
    gate.set()


def test_a_slow_start_is_waited_for_and_named(slow_entry):
    srv = new_server()
    notes = []
    # the old fixed 5 s bound would have failed this start; now the server
    # waits as long as the loop is setting up. The loop thread is let in once the
    # server has said what it waits for (a timer could fire before a starved
    # waiting thread ever looked); the timer only ends a start that never says it.
    threading.Timer(30.0, slow_entry.set).start()

    def note(line):
        notes.append(line)
        slow_entry.set()

    srv.start(progress=note)
    try:
        assert srv.running
        assert notes and "waiting for the loop thread to enter the C loop" in notes[0]
        assert all(n.startswith("starting the loop (") for n in notes)
    finally:
        srv.stop()


@pytest.mark.slow
def test_start_can_be_cancelled_while_waiting(slow_entry):
    srv = new_server()
    cancel = threading.Event()
    threading.Timer(0.3, cancel.set).start()
    threading.Timer(1.0, slow_entry.set).start()      # the thread enters, then sees the stop
    with pytest.raises(ServerError, match="start-up cancelled while waiting for the loop thread"):
        srv.start(cancel=cancel)
    assert not srv.running


def test_no_note_when_the_start_is_quick():
    srv = new_server()
    notes = []
    srv.start(progress=notes.append)
    try:
        assert srv.running
        assert notes == []
    finally:
        srv.stop()


def test_every_phase_has_a_description():
    srv = new_server(cpu=0)
    lib = srv._lib
    texts = {p: srv.startup_phase_text(p) for p in (
        lib.RT_START_NOT_STARTED, lib.RT_START_SCHEDULING, lib.RT_START_PINNING,
        lib.RT_START_LOCKING_MEMORY, lib.RT_START_PREFAULTING, lib.RT_START_READY)}
    assert len(set(texts.values())) == len(texts)
    assert "mlockall" in texts[lib.RT_START_LOCKING_MEMORY]
    assert "CPU 0" in texts[lib.RT_START_PINNING]


def test_the_loop_reports_it_is_ready_once_running():
    srv = new_server()
    srv.start()
    try:
        s = srv.stats.read()
        assert int(s.startup_phase) == srv._lib.RT_START_READY
    finally:
        srv.stop()


@pytest.mark.slow
def test_serve_cancelled_during_start_exits_130(slow_entry, tmp_path, capsys):
    """Ctrl-C while the loop is still setting up: the start is abandoned,
    nothing is left running, exit 130."""
    import signal

    srv = new_server()
    threading.Timer(0.3, lambda: signal.raise_signal(signal.SIGINT)).start()
    threading.Timer(1.0, slow_entry.set).start()
    t0 = time.monotonic()
    rc = console.run_console(srv, str(tmp_path / "s.json"), quiet=True)
    assert rc == 130
    assert time.monotonic() - t0 < 60
    err = capsys.readouterr().err
    assert "stopped by SIGINT before the loop ran" in err
    assert not srv.running
