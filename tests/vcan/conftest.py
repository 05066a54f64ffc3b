"""Real SocketCAN tests (marker ``vcan``): they need a Linux kernel with vcan0 up
and can-utils. The host kernel of the development machines has no CAN, so
``scripts/vcan-vm`` boots a real kernel under QEMU and runs them there;
``scripts/test`` runs the host tests with ``-m "not vcan"`` and then it.

Run by hand where vcan0 is missing, they fail (never skip) and say so.
"""

import os
import shutil

import pytest

TOOLS = ("candump", "cansend", "cangen")


@pytest.fixture(scope="session")
def vcan0():
    """The name of the vcan interface, after checking it and the tools exist."""
    if not os.path.exists("/sys/class/net/vcan0"):
        pytest.fail("no vcan0 on this kernel: run scripts/vcan-vm (it boots a kernel with vcan "
                    "under QEMU), or create it: modprobe vcan && ip link add dev vcan0 type vcan "
                    "&& ip link set up vcan0", pytrace=False)
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        pytest.fail(f"can-utils missing ({', '.join(missing)}): apt-get install can-utils",
                    pytrace=False)
    with open("/sys/class/net/vcan0/operstate", encoding="ascii") as f:
        if f.read().strip() == "down":
            pytest.fail("vcan0 is down: ip link set up vcan0", pytrace=False)
    return "vcan0"
