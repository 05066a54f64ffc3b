"""scripts/fuzz for a few seconds over the embedded transport (the CI's short
run), the accounting it relies on, and the XCP regression it found."""

import json
import os
import socket
import subprocess
import sys

import pytest
from waiting import wait_until

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.slow
def test_a_short_fuzz_run_explains_every_frame_and_writes_its_table(tmp_path):
    out = tmp_path / "fuzz.json"
    p = subprocess.run([os.path.join(REPO, "scripts", "fuzz"), "--seconds", "8",
                        "--burst-frames", "12000", "--bursts", "1", "--silent-restarts", "1",
                        "--xcp-packets", "300", "--seed", "3", "--json", str(out), "--quiet"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "| **unexplained** | | **0** |" in p.stdout
    assert "fuzz: PASS" in p.stdout
    r = json.loads(out.read_text())
    assert r["unexplained"] == 0 and r["passed"] and r["commands_resumed"]
    sent = r["sent_by_kind"]
    for kind in ("valid", "extreme", "unknown_11", "unknown_29", "bad_length", "bad_crc",
                 "counter_repeat", "counter_jump", "restart", "remote", "error", "fd", "burst"):
        assert sent[kind] > 0, kind
    counted = r["counted_by_reason"]
    for reason in ("accepted", "unknown_id", "bad_length", "bad_crc", "bad_counter",
                   "bridge_remote", "bridge_error", "bridge_fd"):
        assert counted[reason] == r["expected_by_reason"][reason] or reason in (
            "unknown_id",), (reason, counted, r["expected_by_reason"])
    assert r["loop"]["running_at_end"]
    x = r["xcp"]
    assert x["unexplained_datagrams"] == 0 and x["unexplained_packets"] == 0
    assert x["internal_errors"] == 0
    # NaN, inf and values beyond the ranges written over XCP: all refused
    assert x["errors"].get("ERR_OUT_OF_RANGE", 0) >= (
        x["sent"].get("download_non_finite", 0) + x["sent"].get("download_out_of_range", 0))


def test_the_counter_model_follows_the_loops_check():
    from can_dbc import codec
    from rt_loop.tools.fuzz import Generator

    g = Generator(5, "embedded", True)
    rx = codec.E2eReceiver(sender="TCU")
    for _ in range(20_000):
        for f in g.event():
            if f.remote or f.error or f.fd or f.ext:
                continue
            status = rx.check(f.id, f.data)
            want = {"accepted": "ok"}.get(f.expect, f.expect)
            assert status == want, (f.kind, f.id, f.data.hex(), f.expect, status)


def test_bad_options_are_refused(tmp_path):
    p = subprocess.run([sys.executable, "-m", "rt_loop.tools.fuzz", "--frames", "-3"], cwd=REPO,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1].startswith("scripts/fuzz: error: argument --frames")
    p = subprocess.run([sys.executable, "-m", "rt_loop.tools.fuzz", "--transport", "socketcan",
                        "--channel", "nosuchcan9", "--frames", "10"], cwd=REPO,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert p.stderr.startswith("fuzz: error: ")


def test_an_xcp_datagram_of_no_bytes_is_counted_as_a_bad_frame():
    """Found by the fuzzer: a UDP datagram of no bytes went through the XCP
    slave's receiver uncounted (no frame, no bad frame)."""
    from rt_loop.server import Server

    srv = Server("xcp-empty", interface="virtual", priority=0, pm_qos_us=None,
                 xcp=("127.0.0.1", 0))
    srv.start()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(3):
                s.sendto(b"", tuple(srv.xcp.address[:2]))
        bad = lambda: srv.xcp_counters()["transport"]["bad_frames"].get(  # noqa: E731 (a short probe, named for the lines below)
            "empty_datagram", 0)
        assert wait_until(lambda: bad() == 3), srv.xcp_counters()["transport"]
    finally:
        srv.stop()


@pytest.mark.parametrize("kind", ["remote", "error", "fd"])
def test_frames_the_bridge_does_not_forward_are_expected_there(kind):
    from rt_loop.tools.fuzz import Generator

    g = Generator(1, "embedded", True)
    seen = set()
    for _ in range(5000):
        for f in g.event():
            if f.kind == kind:
                seen.add(f.expect)
    assert seen == {f"bridge_{kind}"}
