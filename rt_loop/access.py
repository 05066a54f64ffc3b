"""Who may connect to a listener of the bench: addresses, tokens, TLS.

One set of rules for every network listener (the bench view's web server,
the control channel over TCP):

- it binds a loopback address (127.0.0.1) unless the user names another;
- beyond loopback it needs a token: at least ``MIN_TOKEN`` printable
  characters without spaces, given on the command line or, better, as the
  first line of a file (``read_token_file``: ``ps`` does not show it);
- a token is compared in constant time (``token_matches``);
- TLS, when wanted, from a certificate and key the user gives
  (``server_tls_context``); the client checks the server's certificate
  against a CA file, or the system's (``client_tls_context``).

Every function raises ``error`` (``AccessError`` unless a caller passes its
own class) with one line naming the cause; ``what`` / ``option`` name the
address or option in that line ("UI address", "--control-token").
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import socket
import ssl
from typing import Any

__all__ = ["AccessError", "MIN_TOKEN", "check_token", "client_tls_context", "is_loopback",
           "parse_address", "read_token_file", "resolve", "server_tls_context",
           "token_matches"]

#: shortest token accepted
MIN_TOKEN = 8
DEFAULT_HOST = "127.0.0.1"


class AccessError(RuntimeError):
    """An address, token or TLS setting that cannot be used (one line)."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


def parse_address(text: Any, what: str = "address", default_host: str = DEFAULT_HOST,
                  error: type = AccessError, ipv6_why: str | None = None) -> tuple[str, int]:
    """(host, port) of "[HOST:]PORT" ("8080", "0.0.0.0:8080", "bench-pc:8080").
    Port 0 means any free port. IPv6 literals are refused (``ipv6_why`` says why)."""
    if not isinstance(text, str) or not text.strip():
        raise error(f"{what} {text!r}: give [HOST:]PORT, e.g. 5006 or 127.0.0.1:5006")
    s = text.strip()
    if s.startswith("[") or s.count(":") > 1:
        raise error(f"{what} {text!r}: IPv6 addresses are not served"
                    + (f" ({ipv6_why})" if ipv6_why else "") + "; use an IPv4 address or a name")
    if ":" in s:
        host, port_text = s.split(":")
    else:
        host, port_text = default_host, s
    if not host:
        raise error(f"{what} {text!r}: the host before ':' is empty")
    if not port_text.isdigit():
        raise error(f"{what} {text!r}: port {port_text!r} is not a number 0..65535")
    port = int(port_text)
    if port > 65535:
        raise error(f"{what} {text!r}: port {port} is outside 0..65535")
    if any(c.isspace() or c in "/?#@" for c in host):
        raise error(f"{what} {text!r}: {host!r} is not a host name or address")
    return host, port


def resolve(host: str, port: int, what: str = "address", error: type = AccessError) -> list[str]:
    """The addresses ``host`` resolves to (``error`` when it does not)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, OSError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else _one_line(e)
        raise error(f"{what} {host}:{port}: host {host!r} does not resolve ({why})") from None
    return sorted({info[4][0] for info in infos})


def is_loopback(host: str, addresses: list[str] | None = None) -> bool:
    """True when every address ``host`` stands for is a loopback address."""
    addrs = addresses if addresses is not None else resolve(host, 0)
    try:
        return bool(addrs) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback
                                   for a in addrs)
    except ValueError:
        return False


def check_token(token: Any, option: str = "token", error: type = AccessError) -> str:
    """The token as given: at least ``MIN_TOKEN`` printable characters, no spaces."""
    if not isinstance(token, str) or not token:
        raise error(f"{option}: give a token (at least {MIN_TOKEN} characters)")
    if len(token) < MIN_TOKEN:
        raise error(f"{option}: at least {MIN_TOKEN} characters, got {len(token)}")
    if any(c.isspace() or not c.isprintable() for c in token):
        raise error(f"{option}: no spaces or control characters")
    return token


def read_token_file(path: str | os.PathLike, option: str = "token file",
                    error: type = AccessError) -> str:
    """The token in the first line of ``path`` (the rest is ignored)."""
    try:
        with open(path, encoding="utf-8") as f:
            line = f.readline().strip()
    except (OSError, UnicodeDecodeError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else _one_line(e)
        raise error(f"{option} {os.fspath(path)}: {why}") from None
    try:
        return check_token(line, "", error)
    except error as e:
        raise error(f"{option} {os.fspath(path)}: {str(e).removeprefix(': ')}") from None


def token_matches(given: Any, token: str | None) -> bool:
    """Constant-time comparison of a token a peer sent with the right one
    (None: no token needed)."""
    if token is None:
        return True
    if not isinstance(given, str):
        return False
    return hmac.compare_digest(given.encode("utf-8", "surrogateescape"), token.encode("utf-8"))


def server_tls_context(cert: str | os.PathLike, key: str | os.PathLike | None = None,
                       option: str = "TLS", error: type = AccessError) -> ssl.SSLContext:
    """A server's TLS context from a PEM certificate (chain) and its key (None:
    the key is in the certificate's file); TLS 1.2 at least."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(os.fspath(cert), None if key is None else os.fspath(key))
    except FileNotFoundError as e:
        raise error(f"{option}: {e.filename or cert}: no such file") from None
    except (ssl.SSLError, OSError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror and not isinstance(
            e, ssl.SSLError) else _one_line(getattr(e, "reason", None) or e)
        raise error(f"{option}: certificate {os.fspath(cert)}"
                    + (f" with key {os.fspath(key)}" if key is not None else "")
                    + f" cannot be used: {why}") from None
    return ctx


def client_tls_context(ca_file: str | os.PathLike | None = None, option: str = "TLS",
                       error: type = AccessError) -> ssl.SSLContext:
    """A client's TLS context that checks the server's certificate and host name
    against ``ca_file`` (a self-signed certificate is its own CA), else the
    system's CAs."""
    try:
        return ssl.create_default_context(cafile=None if ca_file is None else os.fspath(ca_file))
    except FileNotFoundError:
        raise error(f"{option}: CA file {os.fspath(ca_file)}: no such file") from None
    except (ssl.SSLError, OSError) as e:
        raise error(f"{option}: CA file {os.fspath(ca_file)} cannot be used: "
                    f"{_one_line(e)}") from None
