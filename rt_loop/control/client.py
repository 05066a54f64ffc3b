"""The control channel's client: a Unix socket path or a URL.

    with ControlClient("/tmp/bench.sock") as c: ...
    with ControlClient("tcp://bench-pc:7000", token_file="bench.token") as c: ...
    with ControlClient("tls://bench-pc:7000", token_file="bench.token",
                       ca_file="bench-cert.pem") as c: ...

``request(op, **fields)`` sends one request and returns the answer's fields
(without ``ok``); a refused request raises ``ControlError`` with the
server's line, as does a channel that cannot be reached or ends. With a
token the client says hello first. ``tls://``: the server's certificate is
checked against ``ca_file`` (a self-signed certificate is its own CA) or the
system's CAs, with its host name.
"""

from __future__ import annotations

import json
import os
import socket
import threading
from typing import Any
from urllib.parse import urlsplit

from rt_loop import access
from rt_loop.control.requests import ControlError, _one_line

__all__ = ["ControlClient", "parse_url"]

SCHEMES = ("unix", "tcp", "tls")


def parse_url(target: str | os.PathLike) -> tuple[str, Any]:
    """("unix", path) or ("tcp" | "tls", (host, port)) of a path, ``unix:PATH``,
    ``tcp://HOST:PORT`` or ``tls://HOST:PORT``; ControlError (one line) otherwise."""
    text = os.fspath(target)
    if "://" not in text:
        return "unix", text.removeprefix("unix:")
    parts = urlsplit(text)
    if parts.scheme not in SCHEMES:
        raise ControlError(f"control URL {text!r}: the scheme must be one of "
                           + ", ".join(f"{s}://" for s in SCHEMES))
    if parts.scheme == "unix":
        return "unix", parts.path
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None or parts.path not in ("", "/"):
        raise ControlError(f"control URL {text!r}: give {parts.scheme}://HOST:PORT")
    return parts.scheme, (parts.hostname, port)


class ControlClient:
    """One connection to a control channel (see the module)."""

    def __init__(self, target: str | os.PathLike, timeout_s: float = 30.0,
                 token: str | None = None, token_file: str | os.PathLike | None = None,
                 ca_file: str | os.PathLike | None = None) -> None:
        self.url = os.fspath(target)
        self.scheme, where = parse_url(target)
        self.path = where if self.scheme == "unix" else None
        self._what = f"control socket {where}" if self.path else f"control channel {self.url}"
        if token_file is not None:
            token = access.read_token_file(token_file, "token file", ControlError)
        if self.scheme == "unix":
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            hint = "is dct-hil serve --control running?"
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            hint = "is dct-hil serve --control-tcp running there?"
        sock.settimeout(timeout_s)
        try:
            sock.connect(where)
            if self.scheme == "tls":
                ctx = access.client_tls_context(ca_file, "control TLS", ControlError)
                sock = ctx.wrap_socket(sock, server_hostname=where[0])
        except ControlError:
            sock.close()
            raise
        except OSError as e:
            sock.close()
            raise ControlError(f"{self._what}: {e.strerror or _one_line(e)} "
                               f"({hint})") from None
        self._sock = sock
        self._file = sock.makefile("rb")
        self._lock = threading.Lock()
        if token is not None:
            try:
                self.request("hello", token=token)
            except ControlError:
                self.close()
                raise

    def request(self, op: str, **fields: Any) -> dict:
        line = json.dumps({"op": op, **fields}).encode() + b"\n"
        with self._lock:
            try:
                self._sock.sendall(line)
                answer = self._file.readline()
            except OSError as e:
                raise ControlError(f"{self._what}: {e.strerror or _one_line(e)}"
                                   ) from None
        if not answer:
            raise ControlError(f"{self._what}: the server closed the connection")
        try:
            reply = json.loads(answer)
        except ValueError:
            raise ControlError(f"{self._what}: the answer is not JSON") from None
        if not reply.pop("ok", False):
            raise ControlError(reply.get("error", "refused"))
        return reply

    def close(self) -> None:
        try:
            self._file.close()
        finally:
            self._sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
