"""Frames lost below the bridge transport are counted, on the host.

The plant server runs over python-can's ``udp_multicast`` interface (UDP on
loopback; it needs msgpack, python-can's "multicast" extra) with priority 0:
no privileges needed. Each test takes a multicast group and a UDP port of its
own, so tests running in parallel do not hear each other. Nothing here depends
on timing: the flood goes on until the kernel has dropped frames, and every
wait is for a behaviour, with a generous time limit.
"""

import random

import can
import pytest
from waiting import wait_until

from can_dbc import codec
from can_dbc.peer import CanPeer
from rt_loop import status as rt_status
from rt_loop.server import Server
from rt_loop.transport import (
    BridgeTransport,
    BusWatch,
    TransportError,
    classify_error_frame,
)

TCU_MESSAGES = ("TCU_ClutchCmd", "TCU_ShiftCmd", "TCU_EngineCmd")
#: flood at most this many frames waiting for the kernel to drop some
MAX_FLOOD_FRAMES = 200_000








def _udp_bus(udp_group):
    address, port = udp_group
    return can.Bus(interface="udp_multicast", channel=address, port=port)


# ----------------------------------------------------------------- the server
def test_every_frame_sent_is_accepted_rejected_or_counted_lost(udp_group):
    address, port = udp_group
    # a receive buffer of 8 KiB (the kernel doubles it: about 20 datagrams), so
    # the kernel drops frames as soon as the bridge thread falls behind the flood
    srv = Server(address, interface="udp_multicast", priority=0,
                 bus_kwargs={"port": port, "rcvbuf_bytes": 8192})
    sender = _udp_bus(udp_group)
    tcu = CanPeer(sender, side="tcu", start=False, send_thread=False)
    sent = {"tcu": 0, "unknown_id": 0, "bad_crc": 0, "error": 0, "remote": 0}
    overflow = can.Message(arbitration_id=0x004, is_error_frame=True,
                           data=bytes([0, 0x01, 0, 0, 0, 0, 0, 0]))   # controller: rx overflow
    bus_off = can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8))
    bad_crc = bytearray(codec.encode("TCU_ClutchCmd", {"SolenoidCurrent1": 0.4}, counter=0))
    bad_crc[0] ^= 0x5A
    try:
        srv.start()
        t = srv.transport
        assert t.watch.kernel_drops_counted and t.watch.rcvbuf_bytes <= 4 * 8192
        # error frames first, before the flood could drop them: two controller
        # overflows and a bus-off, counted by the bridge and never given to the loop
        for msg in (overflow, bus_off, overflow):
            sender.send(msg)
            sent["error"] += 1
        assert wait_until(lambda: t.counters["rx_error_frames"] == 3), t.counters
        i = 0
        while i < MAX_FLOOD_FRAMES:
            # mixed traffic, 16 frames a round: the three TCU messages with valid E2E
            # protection, unknown identifiers, a frame with a bad CRC and a remote frame
            for name in TCU_MESSAGES:
                sent["tcu"] += tcu.send_now(name)
            for k in range(11):
                sender.send(can.Message(arbitration_id=0x700 + k, is_extended_id=False,
                                        data=i.to_bytes(4, "little") * 2))
                sent["unknown_id"] += 1
            sender.send(can.Message(arbitration_id=codec.message("TCU_ClutchCmd").frame_id,
                                    data=bytes(bad_crc), is_extended_id=False))
            sent["bad_crc"] += 1
            sender.send(can.Message(arbitration_id=0x7FE, is_remote_frame=True, dlc=8,
                                    is_extended_id=False))
            sent["remote"] += 1
            i += 16
            if i % 1024 == 0 and t.counters["rx_kernel_drops"] > 0:
                break
        # the server catches up: as many frames read or counted as were sent (the
        # bridge reads the kernel's drop count every 100 ms; the kernel's drops of
        # the echoes of the server's own frames come on top)
        assert wait_until(lambda: _accounted(srv) >= sum(sent.values())), \
            srv.snapshot()["counts"]
    finally:
        tcu.close()
        sender.shutdown()
        srv.stop()

    report = srv.report(histograms=False)
    c, b = report["counts"], report["counts"]["bridge"]
    rx = c["rx"]
    sent_total = sum(sent.values())
    assert b["rx_kernel_drops"] > 0, b
    assert rx["lost_below_bridge"] == b["rx_kernel_drops"]
    assert rx["lost"] == rx["overflow"] + rx["lost_below_bridge"]
    assert rx["overflow"] == b["rx_ring_full"]
    assert rx["frames"] == rx["accepted"] + rx["rejected"]
    assert b["rx_errors"] == 0 and b["watch_errors"] == 0, b
    assert b["own_frames_dropped"] > 0
    # the sender's frames and the echoes of the server's own (multicast loops every
    # frame back to every member on the host, the server too) are each accepted or
    # rejected by the loop, not forwarded (error, remote frames; the server's own
    # echoes, recognised and dropped by the bridge), counted lost (kernel, full
    # ring) or counted as too late (after the loop's last tick). The own echoes
    # once went to the loop as unknown identifiers: they are counted apart now,
    # in own_frames_dropped; one the kernel dropped is among its drops.
    # At stop the bridge reads the socket until it is empty, so no frame should be
    # in flight: the tolerance covers datagrams the kernel had not yet queued on the
    # socket then (loopback delivery is deferred to softirq context), never more
    # counted than sent
    on_the_bus = sent_total + b["tx_forwarded"]
    counted = (rx["accepted"] + rx["rejected"] + rx["lost"]
               + b["rx_error_frames"] + b["rx_remote_frames"] + b["rx_fd_frames"]
               + b["rx_left_in_ring"] + b["rx_drained_at_stop"] + b["own_frames_dropped"])
    assert 0 <= on_the_bus - counted <= 8, (on_the_bus, counted, sent, b, rx)

    # error frames never reach the loop; counted by kind, overflows as events
    assert b["rx_error_frames"] == sent["error"] == 3
    assert b["error_frame_kinds"] == {"controller": 2, "rx_overflow": 2, "bus_off": 1}
    assert b["rx_overflow_events"] == rx["overflow_events"] == 2
    assert b["tx_overflow_events"] == 0
    assert b["rx_remote_frames"] <= sent["remote"]
    # what the loop saw: valid TCU frames are accepted or (after a gap the kernel
    # made) rejected for their counter; everything else is rejected by reason
    assert rx["accepted"] > 0 and rx["unknown_id"] > 0 and rx["bad_crc"] > 0
    assert rx["accepted"] + rx["bad_counter"] <= sent["tcu"]

    # nothing silent: the stats JSON and the summary say so
    assert report["transport"]["rx_kernel_drops"] == b["rx_kernel_drops"]
    text = "\n".join(rt_status.summary_lines(report, "stats.json"))
    assert f"{rx['lost']} lost" in text
    assert f"{b['rx_kernel_drops']} dropped by the kernel below the bridge" in text
    assert "below the bridge  UDP receive buffer" in text
    assert "2 controller overflows (frames lost: unknown)" in text
    assert "error frames      controller 2, rx_overflow 2, bus_off 1" in text


def _accounted(srv):
    """Frames the server has read or counted so far (while it runs)."""
    c = srv.snapshot()["counts"]
    b = c["bridge"]
    return (c["rx"]["frames"] + c["rx"]["lost"] + b["rx_error_frames"] + b["rx_remote_frames"]
            + b["rx_fd_frames"])


def test_the_receive_buffer_is_raised_and_reported(udp_group):
    address, port = udp_group
    t = BridgeTransport("udp_multicast", address, port=port)
    try:
        c = t.counters
        assert c["udp_sockets"] == 1 and c["kernel_drops_counted"]
        # SO_RCVBUFFORCE as root, else capped at net.core.rmem_max: never below the default
        with open("/proc/sys/net/core/rmem_default", encoding="ascii") as f:
            assert c["rcvbuf_bytes"] >= int(f.read())
        assert c["rcvbuf_frames"] > 0
        assert "UDP receive buffer" in t.describe() and "kernel drops counted" in t.describe()
    finally:
        t.close()
    with pytest.raises(TransportError, match="receive buffer"):
        BridgeTransport("udp_multicast", address, port=port, rcvbuf_bytes=-1)
    with pytest.raises(TransportError, match="receive buffer"):
        BridgeTransport("udp_multicast", address, port=port, rcvbuf_bytes="big")


def test_kernel_drops_read_two_ways_agree(udp_group):
    """SO_MEMINFO and /proc/net/udp give the same drop count of the bus's socket."""
    sender, receiver = _udp_bus(udp_group), _udp_bus(udp_group)
    meminfo = BusWatch(receiver, can, rcvbuf_bytes=4096, drops_from="meminfo")
    proc = BusWatch(receiver, can, drops_from="proc")
    try:
        frames = 2000
        for i in range(frames):
            sender.send(can.Message(arbitration_id=0x123, data=i.to_bytes(8, "little"),
                                    is_extended_id=False))
        read = 0
        while receiver.recv(timeout=0) is not None:
            read += 1
        meminfo.poll()
        proc.poll()
        drops = meminfo.counters()["rx_kernel_drops"]
        assert drops > 0
        assert proc.counters()["rx_kernel_drops"] == drops
        assert read + drops == frames    # loopback: nothing else is lost
    finally:
        meminfo.close()
        proc.close()
        receiver.shutdown()
        sender.shutdown()


# ----------------------------------------------------------- error frames
@pytest.mark.parametrize("ident, data1, kinds", [
    (0x004, 0x01, ("controller", "rx_overflow")),
    (0x004, 0x02, ("controller", "tx_overflow")),
    (0x004, 0x03, ("controller", "rx_overflow", "tx_overflow")),
    (0x004, 0x14, ("controller", "rx_warning", "rx_passive")),
    (0x004, 0x40, ("controller", "back_to_error_active")),
    (0x004, 0x00, ("controller",)),                            # CAN_ERR_CRTL_UNSPEC
    (0x040, 0x00, ("bus_off",)),
    (0x100, 0x00, ("restarted",)),
    (0x0A8, 0x00, ("protocol_violation", "no_ack", "bus_error")),
    (0x001, 0x01, ("tx_timeout",)),                            # data[1] is only for CRTL
    (0x002, 0x00, ("lost_arbitration",)),
    (0x210, 0x00, ("transceiver", "error_counters")),
    (0x800, 0x00, ("unknown_class",)),
])
def test_error_frames_are_classified_by_the_socketcan_layout(ident, data1, kinds):
    assert classify_error_frame(ident, bytes([0, data1, 0, 0, 0, 0, 0, 0])) == kinds


def test_error_frames_outside_the_socketcan_layout_are_unclassified():
    assert classify_error_frame(0x004, bytes([0, 1])) == ("unclassified",)   # not 8 bytes
    assert classify_error_frame(0x000, bytes(8)) == ("unclassified",)        # no class
    assert classify_error_frame(0x20000004, bytes([0, 1, 0, 0, 0, 0, 0, 0])) \
        == ("controller", "rx_overflow")                                     # flag bits ignored


# ---------------------------------------------------------------- bus state
class _StateBus:
    """A stand-in bus whose interface reports its state (as pcan, ixxat do)."""

    def __init__(self, states):
        self.states = list(states)

    @property
    def state(self):
        return self.states.pop(0) if len(self.states) > 1 else self.states[0]


def test_bus_state_changes_are_counted():
    bus = _StateBus([can.BusState.ACTIVE, can.BusState.ACTIVE, can.BusState.PASSIVE,
                     can.BusState.PASSIVE, can.BusState.ERROR, can.BusState.ACTIVE,
                     can.BusState.PASSIVE])
    watch = BusWatch(bus, can)
    assert watch.counters()["bus_state"] == "active"
    assert watch.counters()["bus_state_changes"] == 0
    for _ in range(8):
        watch.poll()
    c = watch.counters()
    assert c["bus_state"] == "passive"
    assert c["bus_state_changes"] == 4
    assert c["bus_state_transitions"] == {"active->passive": 2, "passive->error": 1,
                                          "error->active": 1}
    assert c["udp_sockets"] == 0 and not c["kernel_drops_counted"]


def test_an_interface_without_a_state_reports_none():
    bus = can.Bus(interface="virtual", channel=f"state-{random.random()}")
    try:
        watch = BusWatch(bus, can)          # python-can's default says "active" always
        watch.poll()
        assert watch.counters()["bus_state"] is None
        assert watch.counters()["bus_state_changes"] == 0
    finally:
        bus.shutdown()


def test_a_failing_state_or_statistics_read_is_reported_not_raised():
    errors = []

    class Flaky:
        calls = 0

        @property
        def state(self):
            Flaky.calls += 1
            if Flaky.calls == 2:
                raise can.CanOperationError("device unplugged")
            return can.BusState.ACTIVE

        def get_stats(self):
            return type("Stats", (), {"overruns": 5 + Flaky.calls})()

    watch = BusWatch(Flaky(), can, on_error=errors.append)
    watch.poll()    # the state read fails: the last state stands
    watch.poll()
    c = watch.counters()
    assert c["bus_state"] == "active" and c["bus_state_changes"] == 0
    assert errors == ["bus state: CanOperationError: device unplugged"]
    assert c["backend_overruns"] == 2      # growth of the backend's counter since the start


def test_the_summary_names_what_was_lost_below_the_bridge():
    rx = {"frames": 90, "accepted": 60, "rejected": 30, "unknown_id": 30, "bad_length": 0,
          "bad_crc": 0, "bad_counter": 0, "overflow": 2, "lost_below_bridge": 8, "lost": 10,
          "overflow_events": 1}
    bridge = {"rx_forwarded": 92, "tx_forwarded": 5, "rx_ring_full": 2, "rx_errors": 0,
              "tx_errors": 0, "rx_error_frames": 2, "rx_remote_frames": 0, "rx_fd_frames": 0,
              "error_frame_kinds": {"controller": 1, "rx_overflow": 1, "bus_off": 1},
              "rx_overflow_events": 1, "tx_overflow_events": 0, "rx_kernel_drops": 8,
              "kernel_drops_counted": True, "udp_sockets": 1, "rcvbuf_bytes": 16384,
              "rcvbuf_frames": 19, "bus_state": "passive", "bus_state_changes": 1,
              "bus_state_transitions": {"active->passive": 1}, "backend_overruns": None,
              "rx_left_in_ring": 0, "rx_drained_at_stop": 3}
    fig = {k: 1.0 for k in ("p50_us", "p90_us", "p99_us", "p99_9_us", "max_us")}
    report = {
        "run": {"state": "stopped", "wall_s": 1.0, "ticks": 2000, "sim_time_s": 1.0},
        "config": {"rate_hz": 2000, "real_time": "soft", "transport": "bridge",
                   "rt_policy_ok": False, "memory_locked": False},
        "turnaround": fig, "execution": fig, "wakeup_latency": fig,
        "counts": {"overruns": 0, "skipped_ticks": 0, "rx": rx,
                   "tx": {"frames": 5, "dropped": 0}, "tcu_messages": {}, "bridge": bridge},
        "transport": {**bridge, "last_error": None},
    }
    text = "\n".join(rt_status.summary_lines(report, "s.json"))
    assert ("10 lost (2 to a full ring, 8 dropped by the kernel below the bridge), and 1 "
            "controller overflows (frames lost: unknown)") in text
    assert "UDP receive buffer 16 KiB (about 19 frames): 8 frames dropped by the kernel" in text
    assert "controller 1, rx_overflow 1, bus_off 1" in text
    assert "bus state         passive at the end; 1 changes (active->passive 1)" in text
    assert "3 frames arrived too late" in text


def test_a_virtual_bus_keeps_a_bounded_backlog_and_counts_what_it_drops(monkeypatch):
    """A reader that does not read (a starved bridge) holds at most the bound;
    its oldest frames go for the newest, counted; the sender never waits and
    another reader gets every frame."""
    import uuid

    import can

    from can_dbc import channels

    monkeypatch.setattr(channels, "VIRTUAL_BACKLOG_FRAMES", 100)
    name = f"backlog-{uuid.uuid4().hex[:8]}"
    starved = channels.open_bus("virtual", name)
    reader = channels.open_bus("virtual", name)
    sender = can.Bus(interface="virtual", channel=name)
    try:
        read = []
        for i in range(250):
            sender.send(can.Message(arbitration_id=0x100, data=i.to_bytes(2, "little")),
                        timeout=0.0)
            read.append(reader.recv(0.0))                 # a reader that keeps up
        assert [int.from_bytes(m.data, "little") for m in read] == list(range(250))
        assert channels.backlog_dropped(reader) == 0
        got = [starved.recv(0.0) for _ in range(101)]
        assert got[-1] is None and all(m is not None for m in got[:100])
        assert [int.from_bytes(m.data, "little") for m in got[:100]] == list(range(150, 250))
        assert channels.backlog_dropped(starved) == 150
    finally:
        for b in (starved, reader, sender):
            b.shutdown()
