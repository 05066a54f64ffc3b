"""Helpers shared by the tests that wait for a behaviour of a running server."""

import socket
import time

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
