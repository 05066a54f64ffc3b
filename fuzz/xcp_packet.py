"""atheris target: the XCP slave's packet handler (rt_loop/measure/xcp/protocol.py
Slave.handle) with the protocol tests' memory and DAQ backends.

The input is a run of packets, each a length byte then its bytes; with its
first bit set the slave is connected first. Between packets the fake DAQ
ticks and its DTOs are taken, as the transport does. Any exception is a
finding; so is an answer longer than MAX_CTO or more than one answer to a
command.
"""

from __future__ import annotations

import _atheris

xp = None
fakes = None


def _import() -> None:
    global xp
    from rt_loop.measure.xcp import protocol
    xp = protocol


def _fakes() -> None:
    global fakes
    import test_xcp_protocol
    fakes = test_xcp_protocol


def TestOneInput(data: bytes) -> None:
    if fakes is None:
        _import()
        _fakes()
    memory = fakes.FakeMemory()
    daq = fakes.FakeDaq(memory)
    slave = xp.Slave(memory, daq)
    if data[:1] and data[0] & 1:
        slave.handle(bytes([xp.CONNECT, 0]))
    at = 1
    while at < len(data):
        n = data[at]
        packet = data[at + 1:at + 1 + n]
        at += 1 + n
        out = slave.handle(packet)
        if packet and packet[0] >= xp.FIRST_CMD_PID and len(out) > 1:
            raise _atheris.Finding(f"{len(out)} answers to command 0x{packet[0]:02X}")
        for answer in out:
            if len(answer) > slave.max_cto:
                raise _atheris.Finding(f"an answer of {len(answer)} bytes, MAX_CTO {slave.max_cto}")
        daq.tick()
        daq.pop(64)
    slave.counters()


if __name__ == "__main__":
    _atheris.run(TestOneInput, _import, _fakes)
