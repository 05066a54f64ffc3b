"""Real SocketCAN tests (marker ``vcan``): they need a Linux kernel with vcan0 up
and can-utils. The host kernel of the development machines has no CAN, so
``scripts/vcan-vm`` starts a Linux kernel with vcan beside it (User-mode Linux,
or QEMU with VCAN_VM=qemu) and runs them there;
``scripts/test`` runs the host tests with ``-m "not vcan"`` and then it.

Run by hand where vcan0 is missing, they fail (never skip) and say so.

In the guest these tests take about 9 minutes under User-mode Linux (a quarter
of an hour emulated under QEMU), most of it in the module fixtures (one server
run, one demo in slow motion). ``scripts/vcan-vm``
runs pytest verbose and unbuffered so each test's name shows when it starts;
the result word here carries the test's wall time, its setup (where a module
fixture runs) included, e.g. ``PASSED (812 s)``.
"""

import os
import shutil

import pytest

TOOLS = ("candump", "cansend", "cangen")

_setup_s = {}
_live = [True]


@pytest.hookimpl(wrapper=True)
def pytest_report_teststatus(report, config):
    """Append the test's wall time (setup + call) to its live verbose result word."""
    status = yield
    if report.when == "setup":
        _setup_s[report.nodeid] = report.duration
    if not status or report.when != "call" or not _live[0]:
        return status
    category, letter, word = status
    total_s = _setup_s.pop(report.nodeid, 0.0) + report.duration
    if isinstance(word, tuple):
        return category, letter, (f"{word[0]} ({total_s:.0f} s)", word[1])
    if word:
        return category, letter, f"{word} ({total_s:.0f} s)"
    return status


def pytest_sessionfinish(session):
    _live[0] = False      # the end summary asks again: plain words there


@pytest.fixture(scope="session")
def vcan0():
    """The name of the vcan interface, after checking it and the tools exist."""
    if not os.path.exists("/sys/class/net/vcan0"):
        pytest.fail("no vcan0 on this kernel: run scripts/vcan-vm (it starts a kernel with vcan "
                    "as User-mode Linux), or create it: modprobe vcan && ip link add dev vcan0 type vcan "
                    "&& ip link set up vcan0", pytrace=False)
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        pytest.fail(f"can-utils missing ({', '.join(missing)}): apt-get install can-utils",
                    pytrace=False)
    with open("/sys/class/net/vcan0/operstate", encoding="ascii") as f:
        if f.read().strip() == "down":
            pytest.fail("vcan0 is down: ip link set up vcan0", pytrace=False)
    return "vcan0"
