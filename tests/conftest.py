"""Fixtures shared by the host tests."""

import random

import pytest
import requires
from waiting import free_udp_port


@pytest.fixture
def udp_group():
    """(multicast group, port) for one test on python-can's udp_multicast bus."""
    requires.module("msgpack")
    rnd = random.Random()
    return f"239.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}", \
        free_udp_port()
