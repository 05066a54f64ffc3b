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


@pytest.fixture(scope="module")
def parser():
    """pya2l's A2L parser (tests/test_a2l.py, tests/test_a2l_tools.py)."""
    try:
        from pya2l.parser import A2lParser
    except ImportError as e:  # pragma: no cover
        pytest.fail(f"pya2l is not installed ({e}): scripts/setup installs the test extra")
    with A2lParser() as p:
        yield p
