"""The control channel over TCP (rt_loop.control.serving): the same requests
as on the Unix socket, a token said in hello (a wrong one refused, counted,
logged), TLS from the user's certificate, several clients at once each with
its own watches, and clients that misbehave (stop reading, send half a line,
send a huge line, vanish) never holding the server or the others."""

import json
import os
import socket
import ssl
import subprocess
import threading
import time

import pytest
from cli_errors import one_line_error
from requires import tool

from rt_loop import access
from rt_loop.control import ControlClient, ControlError, ControlServer
from rt_loop.control import serving as serving_mod
from rt_loop.server import Server, ServerError

TOKEN = "s3cret-bench-token"


def _server(**control):
    return Server(f"tcp-{os.getpid()}-{threading.get_ident()}-{time.monotonic_ns()}",
                  interface="virtual", priority=0, **control)


@pytest.fixture
def logged():
    return []


@pytest.fixture
def served(logged):
    """A running server and its control channel on loopback TCP with a token."""
    server = _server(control_tcp=("127.0.0.1", 0), control_token=TOKEN)
    server.start()
    ctl = server.control
    ctl._log = logged.append
    host, port = ctl.tcp_address
    yield server, ctl, f"tcp://{host}:{port}"
    server.stop()


def _raw(url):
    host, port = url.removeprefix("tcp://").split(":")
    s = socket.create_connection((host, int(port)), timeout=5)
    return s, s.makefile("rb")


def _ask(sock, f, request):
    sock.sendall(json.dumps(request).encode() + b"\n")
    return json.loads(f.readline())


def test_the_requests_work_over_tcp_after_hello(served):
    server, ctl, url = served
    with ControlClient(url, token=TOKEN) as c:
        assert c.request("ping")["time_s"] >= 0
        values = c.request("read", names=["vehicle_speed_kmh", "gear"])["values"]
        assert set(values) == {"vehicle_speed_kmh", "gear"}
        assert c.request("set", name="road_grade_pct", value=4.0)["applied"]
        config = c.request("config")["config"]
        assert config["control"]["tcp"] == url.removeprefix("tcp://")
        assert config["control"]["token"] is True and config["control"]["tls"] is False
    assert ctl.counts["refused_tokens"] == 0 and ctl.counts["clients"] == 1


def test_a_wrong_or_missing_token_is_refused_counted_and_logged(served, logged):
    server, ctl, url = served
    with pytest.raises(ControlError, match="wrong token"):
        ControlClient(url, token="not-the-token")
    assert ctl.counts["refused_tokens"] == 1
    assert logged and "wrong token from 127.0.0.1" in logged[0]
    s, f = _raw(url)                       # no hello: the first request is refused, the door shut
    answer = _ask(s, f, {"op": "set", "name": "road_grade_pct", "value": 9})
    assert not answer["ok"] and "needs a token" in answer["error"]
    assert f.readline() == b""
    s.close()
    assert ctl.counts["unauthenticated"] == 1
    with ControlClient(url, token=TOKEN) as c:
        assert c.request("read", names=["road_grade_pct"])["values"]["road_grade_pct"] == 0.0


def test_beyond_loopback_only_with_a_token(tmp_path, capsys):
    server = _server()
    with pytest.raises(ControlError, match="beyond loopback only with a token"):
        ControlServer(server, None, tcp=("0.0.0.0", 0))
    with pytest.raises(ServerError, match="beyond loopback only with a token"):
        _server(control_tcp=("0.0.0.0", 0))
    with pytest.raises(ServerError, match="at least 8"):
        _server(control_tcp=("127.0.0.1", 0), control_token="short")
    short = tmp_path / "short.token"
    short.write_text("abc\n")
    for argv, says in ((["--control-tcp", "0.0.0.0:7000"], "beyond loopback only with"),
                       (["--control-token-file", short], "need --control-tcp"),
                       (["--control-tcp", "7000", "--control-token-file", short],
                        "at least 8 characters"),
                       (["--control-tcp", "70000"], "outside 0..65535"),
                       (["--control-tcp", "7000", "--control-tls-cert", tmp_path / "no.pem"],
                        "no such file"),
                       (["--tcu-clock", "bus"], "needs --tcu reference")):
        line = one_line_error(capsys, ["serve", "--duration", "0.1", *argv])
        assert says in line, (argv, line)


def test_two_clients_each_with_its_own_watches(served):
    server, ctl, url = served
    a = ControlClient(url, token=TOKEN)
    b = ControlClient(url, token=TOKEN)
    try:
        wa = a.request("watch", when="vehicle_speed_kmh > 500")["id"]
        wb = b.request("watch", when="vehicle_speed_kmh > 600")["id"]
        ids = {f["id"] for f in b.request("faults")["faults"]}
        assert {wa, wb} <= ids
        a.close()                                           # a's watch ends with it
        deadline = time.monotonic() + 5
        while wa in {f["id"] for f in b.request("faults")["faults"]}:
            assert time.monotonic() < deadline, "the closed client's watch was not freed"
            time.sleep(0.01)
        assert wb in {f["id"] for f in b.request("faults")["faults"]}
        assert b.request("ping")["time_s"] >= 0
    finally:
        b.close()


def test_a_client_that_stops_reading_is_dropped_and_holds_nobody(served, monkeypatch):
    server, ctl, url = served
    monkeypatch.setattr(serving_mod, "SLOW_CLIENT_S", 1.0)
    slow, slow_file = _raw(url)
    slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    slow.sendall(json.dumps({"op": "hello", "token": TOKEN}).encode() + b"\n")
    request = json.dumps({"op": "snapshot"}).encode() + b"\n"
    slow.settimeout(0.5)
    try:
        for _ in range(2000):                  # answers pile up: it never reads one
            slow.sendall(request)
    except (TimeoutError, OSError):
        pass                                   # its own send buffer full: the server stopped reading it
    with ControlClient(url, token=TOKEN, timeout_s=5) as other:
        t0 = time.monotonic()
        for _ in range(20):
            assert other.request("ping")["time_s"] >= 0
        assert time.monotonic() - t0 < 5.0
        deadline = time.monotonic() + 10
        while ctl.counts["slow_clients_dropped"] < 1:
            assert time.monotonic() < deadline, "the client that stopped reading was kept"
            time.sleep(0.05)
        assert other.request("ping")["time_s"] >= 0
    slow_file.close()
    slow.close()
    assert server.running


def test_half_a_line_a_huge_line_and_a_vanished_client(served, monkeypatch):
    server, ctl, url = served
    monkeypatch.setattr(serving_mod, "HELLO_TIMEOUT_S", 1.0)
    half, half_file = _raw(url)
    half.sendall(b'{"op": "hel')                       # and never more
    with ControlClient(url, token=TOKEN) as c:
        assert c.request("ping")["time_s"] >= 0
        huge, hf = _raw(url)
        huge.sendall(json.dumps({"op": "hello", "token": TOKEN}).encode() + b"\n")
        assert json.loads(hf.readline())["ok"]
        try:
            huge.sendall(b"x" * (serving_mod.MAX_LINE + 10))
        except OSError:
            pass
        answer = json.loads(hf.readline())
        assert not answer["ok"] and "longer than" in answer["error"]
        hf.close()
        huge.close()
        assert ctl.counts["long_lines"] == 1
        gone, gf = _raw(url)
        gone.sendall(json.dumps({"op": "hello", "token": TOKEN}).encode() + b"\n"
                     + json.dumps({"op": "events"}).encode() + b"\n")
        gone.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        gf.close()
        gone.close()                                   # reset: vanished mid-request
        deadline = time.monotonic() + 5
        while ctl.counts["unauthenticated"] < 1:       # the half line timed out
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert c.request("ping")["time_s"] >= 0
    half_file.close()
    half.close()
    deadline = time.monotonic() + 5
    while ctl.counts["clients_open"]:                  # every connection freed as it ended
        assert time.monotonic() < deadline, (ctl.counts, [
            (c.client.name, c.authenticated, len(c.out), len(c.inbuf)) for c in ctl._conns.values()])
        time.sleep(0.02)
    assert server.running and ctl.counts["errors"] == 0


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    """A self-signed certificate for localhost (its own CA) and its key."""
    openssl = tool("openssl", "apt-get install openssl")
    d = tmp_path_factory.mktemp("tls")
    cert, key = d / "cert.pem", d / "key.pem"
    subprocess.run([openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                    "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
                    "-keyout", str(key), "-out", str(cert)], check=True, capture_output=True)
    return cert, key


def test_tls_with_the_users_certificate(certificate):
    cert, key = certificate
    ctx = access.server_tls_context(cert, key)
    server = _server(control_tcp=("127.0.0.1", 0), control_token=TOKEN, control_tls=ctx)
    server.start()
    try:
        host, port = server.control.tcp_address
        with ControlClient(f"tls://localhost:{port}", token=TOKEN, ca_file=cert) as c:
            assert c.request("ping")["time_s"] >= 0
            assert c.request("config")["config"]["control"]["tls"] is True
        with pytest.raises(ControlError, match="CERTIFICATE_VERIFY_FAILED|certificate verify"):
            ControlClient(f"tls://localhost:{port}", token=TOKEN)     # not the system's CAs
        with pytest.raises(ControlError):                              # plain TCP to TLS
            ControlClient(f"tcp://127.0.0.1:{port}", token=TOKEN, timeout_s=5)
        deadline = time.monotonic() + 5
        while server.control.counts["tls_failures"] < 2:
            assert time.monotonic() < deadline, server.control.counts
            time.sleep(0.05)
        with ControlClient(f"tls://localhost:{port}", token=TOKEN, ca_file=cert) as c:
            assert c.request("ping")["time_s"] >= 0
    finally:
        server.stop()
    with pytest.raises(access.AccessError, match="cannot be used"):
        access.server_tls_context(key, cert)                           # swapped
    assert isinstance(ctx, ssl.SSLContext)


def test_bench_attach_over_tcp_with_a_token_file(tmp_path):
    from dct_hil.bench import Bench, BenchError

    token_file = tmp_path / "bench.token"
    token_file.write_text(TOKEN + "\n")
    server = _server(control_tcp=("127.0.0.1", 0), control_token=TOKEN)
    server.start()
    try:
        host, port = server.control.tcp_address
        bench = Bench.attach(f"tcp://{host}:{port}", token_file=token_file)
        bench.set("accel_pedal_pct", 20)
        assert bench.read("accel_pedal_pct") == 20.0
        t0 = bench.time_s
        t = bench.wait_until(f"time_s > {t0 + 0.05}", timeout_s=2.0)
        assert t > t0 + 0.05
        bench.detach()
        assert server.running
        with pytest.raises(BenchError, match="wrong token"):
            Bench.attach(f"tcp://{host}:{port}", token="wrong-token-123")
        with pytest.raises(BenchError, match="scheme"):
            Bench.attach(f"http://{host}:{port}")
    finally:
        server.stop()


def test_a_client_that_half_closes_gets_every_answer(served):
    """printf '...\\n...\\n' | nc: the requests, then the end of its sending; every
    line is answered before the server closes."""
    server, ctl, url = served
    s, f = _raw(url)
    lines = [{"op": "hello", "token": TOKEN}] + [{"op": "ping"}] * 20 + [{"op": "snapshot"}]
    s.sendall(b"".join(json.dumps(x).encode() + b"\n" for x in lines))
    s.shutdown(socket.SHUT_WR)
    answers = [json.loads(line) for line in f]
    assert len(answers) == len(lines) and all(a["ok"] for a in answers)
    assert "snapshot" in answers[-1]
    f.close()
    s.close()
