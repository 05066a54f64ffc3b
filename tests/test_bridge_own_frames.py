"""The bridge transport does not count its own frames as received traffic.

On python-can's ``udp_multicast`` interface the kernel loops every datagram
back to every member of the group on the host, the sender included, so the
plant server hears each frame it sends. The bridge recognises those echoes
and drops them before the loop's ring, counted as ``own_frames_dropped``;
frames of another program on the same host, in another process or on another
bus object of the same process, still reach the loop. Each test takes a
multicast group and a UDP port of its own; the server runs with priority 0
(no privileges). Nothing here depends on timing: every wait is for a
behaviour, with a generous limit.
"""

import json
import os
import random
import subprocess
import sys
import textwrap
import time

import can
import pytest
from waiting import wait_until

from can_dbc import codec
from can_dbc.peer import CanPeer
from rt_loop.server import Server
from rt_loop.transport import BridgeTransport, OwnFrames

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WAIT_S = 30.0
TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")
#: rounds of the three TCU messages the peer sends (well inside the 8192-frame ring)
ROUNDS = 200








def _server(udp_group):
    address, port = udp_group
    return Server(address, interface="udp_multicast", priority=0, bus_kwargs={"port": port})


#: the peer in a process of its own: waits until it has heard every plant message
#: of the server (the server's frames reach other programs on this host), then
#: sends ROUNDS rounds of the TCU messages and prints what it sent and heard
_PEER_PROCESS = textwrap.dedent("""
    import json, sys, time
    import can
    from can_dbc import codec
    from can_dbc.peer import CanPeer

    address, port, rounds, wait_s = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    bus = can.Bus(interface="udp_multicast", channel=address, port=port)
    peer = CanPeer(bus, side="tcu", start=True, send_thread=False,
                   values={"SolenoidCurrent1": 0.4, "TargetGear": 1})
    plant = [m.name for m in codec.messages("PLANT")]
    deadline = time.monotonic() + wait_s
    def heard():
        rep = peer.report()["received"]
        return all(rep[name]["accepted"] > 0 for name in plant)
    while not heard() and time.monotonic() < deadline:
        time.sleep(0.01)
    ok = heard()
    sent = 0
    if ok:
        for _ in range(rounds):
            for name in ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd"):
                sent += peer.send_now(name)
    rep = peer.report()
    peer.close()
    bus.shutdown()
    print(json.dumps({"heard_every_plant_message": ok, "sent": sent,
                      "plant_accepted": {n: rep["received"][n]["accepted"] for n in plant}}))
""")


def _check_counts(srv, peer_sent):
    """The server's counts after a run with a peer that sent ``peer_sent`` frames."""
    report = srv.report(histograms=False)
    rx, b = report["counts"]["rx"], report["counts"]["bridge"]
    own = srv.transport.own
    # the peer's frames reached the loop, every one accepted
    assert rx["accepted"] == peer_sent, rx
    # nothing else did: none of the server's own frames came back as an unknown id
    assert rx["unknown_id"] == 0 and rx["rejected"] == 0, rx
    assert rx["frames"] == peer_sent and b["rx_forwarded"] == peer_sent
    # the echoes were heard and counted apart: not lost, not rejected, not late
    assert b["rx_kernel_drops"] == 0 and rx["lost"] == 0, b
    assert b["own_frames_dropped"] > 0 and b["tx_forwarded"] > 0
    assert b["own_frames_dropped"] == own.echoes
    assert b["own_echoes_forgotten"] == 0
    # every frame sent was echoed, but for the last few whose echo had not been
    # queued yet when the bridge read its socket for the last time
    assert b["own_frames_dropped"] + own.awaited == b["tx_forwarded"]
    assert own.awaited <= 8, own.awaited
    assert b["rx_drained_at_stop"] == 0, b
    return report


def test_a_peer_in_another_process_is_heard_and_the_echoes_are_not_traffic(udp_group):
    address, port = udp_group
    srv = _server(udp_group)
    try:
        srv.start()
        env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
        child = subprocess.run(
            [sys.executable, "-c", _PEER_PROCESS, address, str(port), str(ROUNDS), str(WAIT_S)],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=3 * WAIT_S)
        assert child.returncode == 0, child.stderr
        peer = json.loads(child.stdout.strip().splitlines()[-1])
        # the other process hears the server: multicast loopback is still on
        assert peer["heard_every_plant_message"], peer
        assert peer["sent"] == ROUNDS * len(TCU_MESSAGES)
        assert wait_until(lambda: srv.snapshot()["counts"]["rx"]["accepted"] >= peer["sent"])
    finally:
        srv.stop()
    _check_counts(srv, peer["sent"])


def test_a_peer_on_another_bus_object_is_heard_and_the_echoes_are_not_traffic(udp_group):
    address, port = udp_group
    srv = _server(udp_group)
    bus = can.Bus(interface="udp_multicast", channel=address, port=port)
    peer = CanPeer(bus, side="tcu", start=True, send_thread=False,
                   values={"SolenoidCurrent1": 0.4})
    sent = 0
    try:
        srv.start()
        assert wait_until(lambda: all(peer.report()["received"][m.name]["accepted"] > 0
                                      for m in codec.messages("PLANT")))
        for _ in range(ROUNDS):
            for name in TCU_MESSAGES:
                sent += peer.send_now(name)
        assert sent == ROUNDS * len(TCU_MESSAGES)
        assert wait_until(lambda: srv.snapshot()["counts"]["rx"]["accepted"] >= sent)
    finally:
        peer.close()
        bus.shutdown()
        srv.stop()
    _check_counts(srv, sent)


def test_a_copy_of_a_server_frame_sent_again_by_another_program_reaches_the_loop(udp_group):
    """A replay keeps the channel field of the frames it recorded: the copy is the
    replaying program's frame, so the loop gets it (a plant message: unknown id)."""
    address, port = udp_group
    srv = _server(udp_group)
    listener = can.Bus(interface="udp_multicast", channel=address, port=port)
    try:
        srv.start()
        plant_ids = {m.frame_id for m in codec.messages("PLANT")}
        heard = None
        deadline = time.monotonic() + WAIT_S
        while heard is None and time.monotonic() < deadline:
            msg = listener.recv(timeout=0.1)
            if msg is not None and msg.arbitration_id in plant_ids:
                heard = msg
        assert heard is not None
        # the server stamps its frames: its channel, a token, a sequence number
        assert heard.channel.startswith(srv.transport.own.prefix)
        assert heard.channel.startswith(f"{address}@")
        listener.send(can.Message(arbitration_id=heard.arbitration_id, data=heard.data,
                                  is_extended_id=False, channel=heard.channel))
        assert wait_until(lambda: srv.snapshot()["counts"]["rx"]["unknown_id"] >= 1)
    finally:
        listener.shutdown()
        srv.stop()
    report = srv.report(histograms=False)
    assert report["counts"]["rx"]["unknown_id"] == 1
    assert report["counts"]["bridge"]["own_frames_dropped"] > 0


# ----------------------------------------------------------------- OwnFrames
class _Msg:
    def __init__(self, channel):
        self.channel = channel


def test_own_frames_each_echo_is_recognised_once():
    own = OwnFrames("239.1.2.3")
    stamps = [own.stamp() for _ in range(3)]
    assert [n for _, n in stamps] == [0, 1, 2]
    assert len({ch for ch, _ in stamps}) == 3
    assert all(ch.startswith("239.1.2.3@") for ch, _ in stamps)
    assert own.awaited == 3
    assert own.is_echo(_Msg(stamps[1][0]))            # out of order is fine
    assert not own.is_echo(_Msg(stamps[1][0]))        # a second copy is not an echo
    assert own.is_echo(_Msg(stamps[0][0])) and own.is_echo(_Msg(stamps[2][0]))
    assert own.echoes == 3 and own.awaited == 0 and own.forgotten == 0


@pytest.mark.parametrize("channel", [None, 0, "239.1.2.3", "vcan0", "239.1.2.3@00000000:0",
                                     "239.1.2.3@{token}:x", "239.1.2.3@{token}:7"])
def test_own_frames_other_programs_frames_are_not_echoes(channel):
    own = OwnFrames("239.1.2.3")
    own.stamp()
    if isinstance(channel, str):
        channel = channel.format(token=own.prefix.split("@")[1][:-1])
    assert not own.is_echo(_Msg(channel))
    assert own.awaited == 1


def test_own_frames_an_unsent_frame_is_not_awaited():
    own = OwnFrames("g")
    channel, n = own.stamp()
    own.unsent(n)
    assert own.awaited == 0 and not own.is_echo(_Msg(channel))


def test_own_frames_echoes_lost_below_the_bridge_are_given_up():
    own = OwnFrames("g", awaited_max=100, reorder=4)
    stamps = [own.stamp() for _ in range(20)]
    # echoes 0..9 were lost; echo 10 arrives: 0..5 are more than 4 behind it
    assert own.is_echo(_Msg(stamps[10][0]))
    assert own.forgotten == 6 and own.awaited == 13
    assert own.is_echo(_Msg(stamps[7][0]))          # still within the reorder window
    assert not own.is_echo(_Msg(stamps[3][0]))      # given up
    # never more than awaited_max awaited: the oldest is given up
    for _ in range(200):
        own.stamp()
    assert own.awaited == 100


def test_a_bus_that_does_not_echo_has_nothing_to_drop():
    t = BridgeTransport("virtual", f"own-{random.random()}")
    try:
        assert t.own is None
        c = t.counters
        assert c["own_frames_dropped"] == 0 and c["own_echoes_forgotten"] == 0
    finally:
        t.close()


# ----------------------------------------------------- the peer's own echoes
def test_the_peer_drops_its_own_echoes_and_hears_the_plant(udp_group):
    """The test TCU (CanPeer, which the TCU node uses) on udp_multicast hears
    its own frames looped back too: they are dropped and counted apart, never
    unknown identifiers, while the plant's frames are accepted."""
    address, port = udp_group
    srv = _server(udp_group)
    srv.start()
    bus = can.Bus(interface="udp_multicast", channel=address, port=port)
    peer = CanPeer(bus, side="tcu")
    try:
        assert wait_until(lambda: peer.own_echoes >= 300 and all(
            peer.counts(m)["accepted"] > 0 for m in ("DCT_ShaftSpeeds", "DCT_Clutch")))
        rep = peer.report()
    finally:
        peer.close()
        bus.shutdown()
        srv.stop()
    assert rep["unknown_frames"] == 0
    assert rep["own_echoes_dropped"] >= 300
    assert srv.report()["counts"]["rx"]["unknown_id"] == 0
