"""The control channel's listeners: a Unix socket and TCP (with a token, with
TLS), many clients served from one thread that never waits for any of them.

``ControlServer(server, path, tcp=None, token=None, tls=None)`` is the
request handler (``rt_loop.control.requests``) behind one or two listeners:

- ``path``: a Unix domain socket, file mode 0600 (the owner only), removed
  on ``stop()``; a stale file (nobody listening) is replaced;
- ``tcp``: (host, port) as ``rt_loop.access.parse_address`` gives it (port
  0: any free one; ``tcp_address`` tells which). Beyond loopback only with
  ``token``. With a token every TCP connection first sends
  ``{"op": "hello", "token": "..."}``; a wrong token is answered in one line,
  counted, logged and the connection closed; any other request first is
  refused the same way. ``tls``: an ``ssl.SSLContext`` for the server side
  (``rt_loop.access.server_tls_context``): the TCP connections speak TLS.

One thread serves every connection with a selector; the sockets never block
it. A connection gets its next answer only after the last one left (one
answer in flight: a client that stops reading holds its own answer and
nothing else), and is closed, counted as ``slow_clients_dropped``, when that
answer has not moved for ``SLOW_CLIENT_S``. A request line longer than
``MAX_LINE`` is refused and the connection closed; a TCP connection that has
not said hello (with a token) or finished its TLS handshake within
``HELLO_TIMEOUT_S`` is closed (``unauthenticated``); TCP keepalive closes
half-open connections; beyond ``MAX_CLIENTS`` a new connection is told so
and closed. The watches a connection set end with it.
"""

from __future__ import annotations

import errno
import json
import os
import selectors
import socket
import ssl
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from rt_loop import access
from rt_loop.control.requests import (
    Client,
    ControlError,
    RequestHandler,
    _clean,
    _one_line,
)

__all__ = ["ControlServer", "HELLO_TIMEOUT_S", "MAX_CLIENTS", "MAX_LINE", "SLOW_CLIENT_S"]

#: longest request line accepted (bytes)
MAX_LINE = 1 << 20
#: connections served at once (both listeners together)
MAX_CLIENTS = 64
#: a TCP connection must finish TLS and say hello (with a token) within this (s)
HELLO_TIMEOUT_S = 10.0
#: an answer that has not moved for this long closes its connection (s)
SLOW_CLIENT_S = 10.0
#: keepalive of TCP connections: idle seconds, interval, probes (a half-open one
#: ends after about 60 s)
KEEPALIVE = (30, 10, 3)
_POLL_S = 0.1


class _Conn:
    """One connection: its socket, what came in, what goes out, its client state."""

    def __init__(self, sock: Any, name: str, tcp: bool, needs_hello: bool) -> None:
        self.sock = sock
        self.client = Client(name)
        self.tcp = tcp
        self.inbuf = bytearray()
        self.out = b""
        self.out_moved = 0.0                  # monotonic time the answer last moved
        self.opened = time.monotonic()
        self.handshaking = isinstance(sock, ssl.SSLSocket)
        self.authenticated = not needs_hello
        self.close_after_send = False


class ControlServer(RequestHandler):
    """Serves a running ``rt_loop.server.Server`` on a Unix socket and/or TCP (one thread)."""

    def __init__(self, server: Any, path: str | os.PathLike | None,
                 tcp: tuple[str, int] | None = None, token: str | None = None,
                 tls: ssl.SSLContext | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        from rt_loop.control.requests import check_socket_path

        super().__init__(server)
        self.path = None if path is None else os.fspath(path)   # None: no Unix socket
        if self.path is not None:
            check_socket_path(self.path)
        self.token = None if token is None else access.check_token(token, "control token",
                                                                  ControlError)
        self.tls = tls
        self.tcp = tcp
        if tcp is not None:
            host, port = tcp
            addresses = access.resolve(host, port, "control address", ControlError)
            if self.token is None and not access.is_loopback(host, addresses):
                raise ControlError(f"control on {host}:{port}: beyond loopback only with a "
                                   "token (--control-token-file); without one bind 127.0.0.1")
        if tls is not None and tcp is None:
            raise ControlError("control TLS needs a TCP address (--control-tcp)")
        self.tcp_address: tuple[str, int] | None = None
        self._log = log if log is not None else (
            lambda line: print(f"dct-hil: {line}", file=sys.stderr, flush=True))
        self._unix: socket.socket | None = None
        self._ino = -1
        self._tcp: socket.socket | None = None
        self._conns: dict[Any, _Conn] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r, self._wake_w = -1, -1
        self._serial = iter(range(1, 1 << 62))
        self.counts.update({"clients": 0, "clients_open": 0, "refused_clients": 0,
                            "refused_tokens": 0, "unauthenticated": 0, "tls_failures": 0,
                            "slow_clients_dropped": 0, "long_lines": 0, "errors": 0})

    # ------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Binds the listeners and starts the serving thread. A live Unix socket
        or a TCP port in use raises OSError (nothing left bound)."""
        if self.path is None and self.tcp is None:
            raise ControlError("an in-process control channel has no socket to serve")
        try:
            if self.path is not None:
                self._unix = self._bind_unix(self.path)
                self._ino = os.stat(self.path).st_ino
            if self.tcp is not None:
                self._tcp = self._bind_tcp(*self.tcp)
                self.tcp_address = self._tcp.getsockname()[:2]
        except OSError:
            self._close_listeners()
            raise
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._serve, name="control", daemon=True)
        self._thread.start()

    @staticmethod
    def _bind_unix(path: str) -> socket.socket:
        if os.path.exists(path):
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(path)
            except OSError:
                os.unlink(path)               # stale: left by a run that was killed
            else:
                raise OSError(errno.EADDRINUSE, "a server is already listening there")
            finally:
                probe.close()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)                 # created 0600, never wider, not even briefly
        try:
            sock.bind(path)
        except OSError:
            sock.close()
            raise
        finally:
            os.umask(old)
        os.chmod(path, 0o600)
        sock.listen(16)
        sock.setblocking(False)
        return sock

    @staticmethod
    def _bind_tcp(host: str, port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(16)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        return sock

    def stop(self) -> None:
        """Stops the thread, closes every connection (their watches end), removes
        the socket file."""
        if self._thread is None:
            return
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._thread = None
        self._close_listeners()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def _close_listeners(self) -> None:
        if self._unix is not None:
            ino = self._ino
            self._unix.close()
            self._unix = None
            try:                               # only the file this server made
                if os.stat(self.path).st_ino == ino:
                    os.unlink(self.path)
            except OSError:
                pass
        if self._tcp is not None:
            self._tcp.close()
            self._tcp = None

    def counters(self) -> dict:
        out = {"path": self.path, **self.counts}
        if self.tcp_address is not None:
            out["tcp"] = f"{self.tcp_address[0]}:{self.tcp_address[1]}"
            out["tls"] = self.tls is not None
            out["token"] = self.token is not None
        return out

    # ------------------------------------------------------------ serving
    def _serve(self) -> None:
        sel = selectors.DefaultSelector()
        self._sel = sel
        for listener in (self._unix, self._tcp):
            if listener is not None:
                sel.register(listener, selectors.EVENT_READ, "listen")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            while not self._stop.is_set():
                for key, events in sel.select(_POLL_S):
                    if key.data == "wake":
                        continue
                    if key.data == "listen":
                        self._accept(key.fileobj)
                        continue
                    c = key.data
                    if c.sock not in self._conns:
                        continue
                    try:
                        # a reset or hang-up reports both events (epoll): the read finds it
                        if c.handshaking or (events & selectors.EVENT_WRITE and c.out):
                            self._progress(c)
                        if (events & selectors.EVENT_READ and c.sock in self._conns
                                and not c.handshaking):
                            self._receive(c)
                    except Exception as e:  # that connection ends; the others are served
                        self.counts["errors"] += 1
                        self._log(f"control: {c.client.name}: {type(e).__name__}: "
                                  f"{_one_line(e)} (connection closed)")
                        self._close(c)
                self._check_times()
        finally:
            for c in list(self._conns.values()):
                self._close(c)
            sel.close()

    def _accept(self, listener: socket.socket) -> None:
        try:
            sock, peer = listener.accept()
        except OSError:
            return
        tcp = listener is self._tcp
        name = (f"{peer[0]}:{peer[1]}" if tcp else "unix") + f"#{next(self._serial)}"
        self.counts["clients"] += 1
        if len(self._conns) >= MAX_CLIENTS:
            self.counts["refused_clients"] += 1
            try:
                sock.setblocking(False)
                sock.send(json.dumps({"ok": False, "error": f"the control channel serves "
                                      f"{MAX_CLIENTS} clients at once; try later"}).encode()
                          + b"\n")
            except OSError:
                pass
            sock.close()
            return
        sock.setblocking(False)
        if tcp:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            idle, interval, count = KEEPALIVE
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, idle)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, interval)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, count)
            if self.tls is not None:
                try:
                    sock = self.tls.wrap_socket(sock, server_side=True,
                                                do_handshake_on_connect=False)
                except (OSError, ssl.SSLError):
                    self.counts["tls_failures"] += 1
                    sock.close()
                    return
        c = _Conn(sock, name, tcp, needs_hello=tcp and self.token is not None)
        self._conns[sock] = c
        self.counts["clients_open"] = len(self._conns)
        self._sel.register(sock, selectors.EVENT_READ, c)
        if c.handshaking:
            self._progress(c)

    def _check_times(self) -> None:
        now = time.monotonic()
        for c in list(self._conns.values()):
            if c.out and now - c.out_moved > SLOW_CLIENT_S:
                self.counts["slow_clients_dropped"] += 1
                self._close(c)
            elif (c.handshaking or not c.authenticated) and now - c.opened > HELLO_TIMEOUT_S:
                self.counts["unauthenticated"] += 1
                self._close(c)

    def _close(self, c: _Conn) -> None:
        if self._conns.pop(c.sock, None) is None:
            return
        try:
            self._sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        try:
            c.sock.close()
        except OSError:
            pass
        self.counts["clients_open"] = len(self._conns)
        self.client_ended(c.client)

    def _want(self, c: _Conn, events: int) -> None:
        try:
            self._sel.modify(c.sock, events, c)
        except (KeyError, ValueError):
            pass

    # -- bytes in
    def _receive(self, c: _Conn) -> None:
        """Reads what arrived (everything TLS holds decrypted too) and answers the
        first complete line; the next waits until that answer has left."""
        try:
            while True:
                data = c.sock.recv(65536)
                if not data:
                    self._close(c)
                    return
                c.inbuf += data
                if not (isinstance(c.sock, ssl.SSLSocket) and c.sock.pending()):
                    break
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError, BlockingIOError):
            pass
        except OSError:
            self._close(c)
            return
        self._next_request(c)

    def _next_request(self, c: _Conn) -> None:
        while not c.out and c.sock in self._conns:
            end = c.inbuf.find(b"\n")
            if end < 0:
                if len(c.inbuf) > MAX_LINE:
                    self.counts["long_lines"] += 1
                    self.counts["refused"] += 1
                    c.inbuf.clear()
                    self._answer(c, {"ok": False, "error": f"request longer than {MAX_LINE} "
                                     "bytes without a newline"}, close=True)
                return
            line = bytes(c.inbuf[:end])
            del c.inbuf[:end + 1]
            if line.strip():
                self._answer(c, self._request(c, line))

    def _request(self, c: _Conn, line: bytes) -> dict:
        try:
            request = json.loads(line)
        except (ValueError, UnicodeDecodeError):
            request = None
        if isinstance(request, dict) and request.get("op") == "hello":
            if not access.token_matches(request.get("token"), self.token if c.tcp else None):
                self.counts["refused_tokens"] += 1
                self._log(f"control: wrong token from {c.client.name.rsplit('#', 1)[0]} "
                          f"(refused: {self.counts['refused_tokens']})")
                c.close_after_send = True
                return {"ok": False, "error": "wrong token"}
            c.authenticated = True
            return {"ok": True, "server": "dct-hil", "protocol": 1}
        if not c.authenticated:
            self.counts["unauthenticated"] += 1
            c.close_after_send = True
            return {"ok": False, "error": "this control channel needs a token: send "
                    "{\"op\": \"hello\", \"token\": \"...\"} first"}
        return self.handle_line(line, c.client)

    # -- bytes out
    def _answer(self, c: _Conn, answer: dict, close: bool = False) -> None:
        try:
            c.out = json.dumps(_clean(answer)).encode() + b"\n"
        except (ValueError, TypeError) as e:
            c.out = json.dumps({"ok": False, "error": f"the answer is not JSON: "
                                f"{_one_line(e)}"}).encode() + b"\n"
        c.close_after_send = c.close_after_send or close
        c.out_moved = time.monotonic()
        self._progress(c, resume=False)           # the caller goes on with the next request

    def _progress(self, c: _Conn, resume: bool = True) -> None:
        """Moves the TLS handshake or the answer on as far as the socket takes it;
        with ``resume``, once it has left, the requests waiting behind it."""
        shook = False
        try:
            if c.handshaking:
                c.sock.do_handshake()
                c.handshaking, shook = False, True
            while c.out:
                n = c.sock.send(c.out)
                if n <= 0:
                    break
                c.out = c.out[n:]
                c.out_moved = time.monotonic()
        except ssl.SSLWantReadError:
            self._want(c, selectors.EVENT_READ)
            return
        except (ssl.SSLWantWriteError, BlockingIOError):
            self._want(c, selectors.EVENT_WRITE)
            return
        except ssl.SSLError:
            if c.handshaking:
                self.counts["tls_failures"] += 1
            self._close(c)
            return
        except OSError:
            self._close(c)
            return
        if c.out:
            self._want(c, selectors.EVENT_WRITE)
            return
        if c.close_after_send:
            self._close(c)
            return
        self._want(c, selectors.EVENT_READ)
        if shook:
            self._receive(c)          # what came with the handshake may be decrypted already
        elif resume and c.inbuf:
            self._next_request(c)
