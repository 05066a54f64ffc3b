"""Helpers shared by the tests that wait for a behaviour of a running server."""

import signal
import socket
import subprocess
import time

import pytest

#: the longest any such wait lasts: nothing is timed, a wait only bounds a failure
WAIT_S = 30.0


def wait_until(predicate, timeout=WAIT_S, step=0.01):
    """Calls ``predicate`` until it returns something true or ``timeout`` s
    passed; returns its last value."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() > deadline:
            return value
        time.sleep(step)


def wait_for(predicate, what, timeout=WAIT_S, step=0.01):
    """``wait_until``, and an AssertionError naming ``what`` when it did not come."""
    value = wait_until(predicate, timeout, step)
    if not value:
        raise AssertionError(f"waited {timeout:g} s for {what}")
    return value


def free_udp_port():
    """A UDP port no socket of this host is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def stop_server(p, err_path, timeout=120.0):
    """SIGTERM to a ``dct-hil`` process and its exit status; one that has not ended
    within ``timeout`` prints every thread's stack (SIGUSR1: the CLI's faulthandler)
    into its stderr file, is killed, and fails the test with that file's end, so that
    no server outlives its test (one left running sends into vcan0 under the next)."""
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
    try:
        return p.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGUSR1)
        time.sleep(3.0)
        p.kill()
        p.wait()
        text = err_path.read_text(errors="replace") if err_path.exists() else ""
        pytest.fail(f"the process did not stop within {timeout:g} s of SIGTERM; its stacks "
                    f"and stderr:\n{text[-6000:]}")
