"""The live bench view's web server: an embedded Bokeh server beside the plant server.

    ui = UiServer(server, parse_address("127.0.0.1:5006"), token=None,
                  recordings_dir="out/recordings")
    ui.start()            # binds the port (a one-line UiError if it cannot), serves the page
    ...
    ui.stop()             # before server.stop(): sessions closed, the UI's recording finalised

``UiServer`` runs ``bokeh.server.server.Server`` on a tornado IOLoop of its
own, in a daemon thread of its own: the plant's tick (C, in its thread)
never waits for it, and every session's Python work (``dct_hil.ui.app``)
runs in that one thread. Bokeh serves its own JavaScript and CSS from
``/static`` (resources mode "server": the bench needs no internet).

Access:

- loopback (127.0.0.1, ::1, localhost) by default; any other address
  needs a token (``--ui-token``) or the server refuses to start;
- with a token, every page, the websocket and the downloads need a signed
  cookie (tornado's secure cookie, a ``cookie_secret`` drawn at random per
  run) that ``/login`` sets after the right token was typed into its form;
  a wrong token gets 403 and one line, is counted and logged;
- the websocket accepts only the origin of the bound host and port (Bokeh's
  ``allow_websocket_origin``);
- ``/recordings/<name>`` serves only the files this UI recorded, from its
  recordings folder.

Errors (a bad address, a port in use, a host that does not resolve, a
token missing beyond loopback) are ``UiError`` with one line.
"""

from __future__ import annotations

import asyncio
import html
import logging
import os
import secrets
import socket
import sys
import threading
from collections.abc import Callable
from typing import Any
from urllib.parse import quote

from rt_loop import access

__all__ = ["DEFAULT_ADDRESS", "UiError", "UiServer", "check_token", "is_loopback",
           "origins_for", "parse_address", "read_token_file", "resolve"]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 5006
DEFAULT_ADDRESS = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
#: the signed cookie a right token earns (tornado secure cookie)
COOKIE = "dct_hil_ui"
COOKIE_DAYS = 1
MIN_TOKEN = access.MIN_TOKEN
#: a wrong token is answered after this pause (slows guessing; the IOLoop is not held)
REFUSED_PAUSE_S = 0.3
_START_TIMEOUT_S = 30.0
_STOP_TIMEOUT_S = 10.0


class UiError(access.AccessError):
    """A UI that cannot be served (one line naming the cause)."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


# --------------------------------------------------------------------------
# addresses and tokens (pure, tested in tests/test_ui.py)
# --------------------------------------------------------------------------

def parse_address(text: Any, default_host: str = DEFAULT_HOST) -> tuple[str, int]:
    """(host, port) of "[HOST:]PORT" (``rt_loop.access.parse_address``). Raises UiError."""
    return access.parse_address(text, "UI address", default_host, UiError,
                                ipv6_why="the page's websocket origin check takes host:port")


def resolve(host: str, port: int) -> list[str]:
    """The addresses ``host`` resolves to (raises UiError when it does not)."""
    return access.resolve(host, port, "UI address", UiError)


is_loopback = access.is_loopback


def check_token(token: Any) -> str:
    """The token as given, or UiError (``rt_loop.access.check_token``)."""
    return access.check_token(token, "--ui-token", UiError)


def read_token_file(path: str | os.PathLike) -> str:
    """The token in the first line of ``path`` (the rest is ignored)."""
    return access.read_token_file(path, "--ui-token-file", UiError)


def origins_for(host: str, port: int) -> list[str]:
    """The websocket origins (host:port) allowed for a server bound to ``host``:
    the bound host itself; for loopback also its other names; for a wildcard
    bind (0.0.0.0, ::) the machine's own names and addresses."""
    names = {host}
    wildcard = host in ("0.0.0.0", "")
    if wildcard or is_loopback(host, _quiet_resolve(host)):
        names |= {"localhost", "127.0.0.1"}
    if wildcard:
        for name in (socket.gethostname(), socket.getfqdn()):
            names.add(name)
            names.update(a for a in _quiet_resolve(name) if ":" not in a)
    return [f"{n.lower()}:{port}" for n in sorted(names)
            if n and ":" not in n and n != "0.0.0.0"]


def _quiet_resolve(host: str) -> list[str]:
    try:
        return resolve(host, 0)
    except UiError:
        return []


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------
# the server
# --------------------------------------------------------------------------

class UiServer:
    """The live bench view of one running ``rt_loop.server.Server`` (see the module).

    ``address``: (host, port) as ``parse_address`` gives it (port 0: any
    free port; ``port`` tells which after ``start``). ``token``: None, or the
    token the login page asks for (required beyond loopback).
    ``recordings_dir``: where the page's recordings go (created when the
    first one starts). ``log``: called with one line for each refused login
    (default: stderr)."""

    def __init__(self, server: Any, address: tuple[str, int] = (DEFAULT_HOST, DEFAULT_PORT),
                 token: str | None = None, recordings_dir: str | os.PathLike = "out/recordings",
                 title: str = "dct-hil bench", log: Callable[[str], None] | None = None) -> None:
        host, port = address
        self.server = server
        self.host = host
        self.port = int(port)
        self.token = None if token is None else check_token(token)
        addresses = resolve(host, self.port)
        self.loopback = is_loopback(host, addresses)
        if not self.loopback and self.token is None:
            raise UiError(f"UI on {host}:{port}: binding beyond loopback needs --ui-token "
                          "(or --ui-token-file); without one bind 127.0.0.1")
        self.recordings_dir = os.path.abspath(os.fspath(recordings_dir))
        self.title = title
        self._log = log if log is not None else (
            lambda line: print(f"dct-hil: {line}", file=sys.stderr, flush=True))
        #: file names this UI recorded (the only ones /recordings serves)
        self.recorded: dict[str, str] = {}
        #: the recording this UI started and has not stopped (its path), else None
        self.recording_path: str | None = None
        self.counts = {"sessions": 0, "sessions_open": 0, "logins": 0, "refused_logins": 0,
                       "downloads": 0}
        self.frozen = False
        self._bokeh: Any = None
        self._loop: Any = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stopped = False
        self._lock = threading.Lock()
        self.hub: Any = None
        #: the sessions' views (dct_hil.ui.app.BenchView), touched only in the UI's thread
        self.views: set = set()

    # ------------------------------------------------------------ life cycle
    @property
    def url(self) -> str:
        host = self.host
        if host == "0.0.0.0":
            host = socket.gethostname()
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        """Binds the port and serves the page; returns once it listens. A port
        in use, an address this machine does not have: UiError (nothing left
        running)."""
        if self._thread is not None:
            raise UiError("the UI was already started")
        from dct_hil.ui.app import Hub

        if self.port == 0:
            try:
                self.port = _free_port(self.host)
            except OSError as e:
                raise UiError(f"UI on {self.host}:0: {e.strerror or _one_line(e)}") from None
        self.hub = Hub(self)
        self._thread = threading.Thread(target=self._run, name="ui-bokeh", daemon=True)
        self._thread.start()
        if not self._ready.wait(_START_TIMEOUT_S):
            raise UiError(f"UI on {self.host}:{self.port}: the web server did not start within "
                          f"{_START_TIMEOUT_S:g} s")
        if self._error is not None:
            self._thread.join(_STOP_TIMEOUT_S)
            self._thread = None
            e = self._error
            why = e.strerror if isinstance(e, OSError) and e.strerror else _one_line(e)
            raise UiError(f"UI on {self.host}:{self.port}: {why}")

    def _run(self) -> None:
        from bokeh.application import Application
        from bokeh.application.handlers.function import FunctionHandler
        from bokeh.server.server import Server as BokehServer
        from bokeh.settings import settings
        from tornado.ioloop import IOLoop

        from dct_hil.ui.app import make_document

        # a closed tab's last pushes and the login's 403s are the page's business, not
        # the console's (the live status stays readable; refused logins are logged here)
        for name in ("bokeh.server.views.ws", "tornado.access"):
            logging.getLogger(name).setLevel(logging.ERROR)
        asyncio.set_event_loop(asyncio.new_event_loop())
        loop = IOLoop.current()
        self._loop = loop
        try:
            settings.resources.set_value("server")      # JS and CSS from this server, no CDN
            kwargs: dict[str, Any] = {}
            if self.token is not None:
                kwargs["auth_provider"] = _token_auth(self)
                kwargs["cookie_secret"] = secrets.token_bytes(32)
            self._bokeh = BokehServer(
                {"/": Application(FunctionHandler(lambda doc: make_document(doc, self)))},
                io_loop=loop, address=self.host, port=self.port,
                allow_websocket_origin=origins_for(self.host, self.port),
                extra_patterns=[(r"/recordings/([^/]+)", _download_handler(), {"ui": self})],
                check_unused_sessions_milliseconds=2000,
                unused_session_lifetime_milliseconds=5000,
                keep_alive_milliseconds=10000,
                **kwargs)
            self._bokeh.start()
        except BaseException as e:  # reported by start()
            self._error = e
            self._ready.set()
            loop.close(all_fds=True)
            return
        self._ready.set()
        try:
            loop.start()
        finally:
            try:
                loop.close(all_fds=True)
            except Exception:  # closing anyway
                pass

    def freeze(self) -> None:
        """The loop is about to stop: the UI's recording is finalised, the
        sessions stop reading the loop (the page keeps the last figures) and
        writes are refused. Safe to call more than once."""
        with self._lock:
            if self.frozen:
                return
            self.frozen = True
        self.finish_recording()

    def finish_recording(self) -> str | None:
        """Stops the recording this UI started, if one runs; returns its path."""
        path = self.recording_path
        if path is None:
            return None
        self.recording_path = None
        try:
            final = self.server.stop_recording()
        except Exception as e:  # told, the UI still stops
            self._log(f"UI: stopping the recording {path}: {_one_line(e)}")
            return None
        final = os.fspath(final) if final else path
        self.recorded[os.path.basename(final)] = final
        return final

    def stop(self) -> None:
        """Freezes, closes every session and the listening socket, ends the
        thread. Safe to call more than once and after a failed start."""
        self.freeze()
        if self._stopped:
            return
        self._stopped = True
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return
        done = threading.Event()

        async def shutdown() -> None:
            try:
                for view in list(self.views):     # their traces released in the scope
                    view._destroyed(None)
                if self._bokeh is not None:
                    self._bokeh.stop(wait=False)
                    http = self._bokeh._http
                    await asyncio.wait_for(http.close_all_connections(), 2.0)
            except Exception:  # stopping anyway
                pass
            finally:
                done.set()
                loop.stop()

        loop.add_callback(shutdown)
        thread.join(_STOP_TIMEOUT_S)

    def stop_before(self, server: Any) -> None:
        """Makes ``server.stop()`` stop this UI first (for ``run_console``, which
        stops the server in its own ``finally``)."""
        server.add_stop_hook(self.stop)

    # ------------------------------------------------------------ auth
    def token_ok(self, given: Any) -> bool:
        """Constant-time comparison of a typed token with this UI's."""
        return access.token_matches(given, self.token)

    def refused(self, remote: str) -> None:
        self.counts["refused_logins"] += 1
        self._log(f"UI: wrong token from {remote} (refused logins: "
                  f"{self.counts['refused_logins']})")


# --------------------------------------------------------------------------
# tornado handlers (made lazily: importing this module needs no tornado)
# --------------------------------------------------------------------------

_LOGIN_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{title}: token</title>
<style>body{{font-family:sans-serif;margin:4em auto;max-width:26em;color:#222}}
input{{font-size:1.1em;padding:.3em}} .err{{color:#b00020}}</style></head>
<body><h2>{title}</h2>
<p class="err" id="message">{message}</p>
<form method="post" action="/login">
<input type="hidden" name="next" value="{next}">
<label>Token <input type="password" name="token" id="token" autofocus></label>
<input type="submit" value="Open" id="submit">
</form></body></html>
"""


def _safe_next(value: str) -> str:
    """A local path to go back to after the login (never another site)."""
    if not value.startswith("/") or value.startswith("//") or "\\" in value:
        return "/"
    return value


def _token_auth(ui: UiServer) -> Any:
    from bokeh.server.auth_provider import AuthProvider
    from tornado.web import RequestHandler

    class LoginHandler(RequestHandler):
        def _page(self, message: str, next_: str) -> str:
            return _LOGIN_PAGE.format(title=html.escape(ui.title), message=html.escape(message),
                                      next=html.escape(_safe_next(next_), quote=True))

        def get(self) -> None:
            self.set_header("Cache-Control", "no-store")
            self.write(self._page("This bench view asks for its token.",
                                  self.get_argument("next", "/")))

        async def post(self) -> None:
            self.set_header("Cache-Control", "no-store")
            next_ = _safe_next(self.get_argument("next", "/"))
            if ui.token_ok(self.get_argument("token", "")):
                ui.counts["logins"] += 1
                self.set_secure_cookie(COOKIE, "bench", expires_days=COOKIE_DAYS,
                                       httponly=True, samesite="Strict")
                self.redirect(next_)
                return
            ui.refused(self.request.remote_ip or "?")
            await asyncio.sleep(REFUSED_PAUSE_S)
            self.set_status(403)
            self.write(self._page("Wrong token: refused.", next_))

    class TokenAuth(AuthProvider):
        @property
        def get_user(self) -> Callable:
            def user(handler: Any) -> str | None:
                value = handler.get_secure_cookie(COOKIE, max_age_days=COOKIE_DAYS)
                return "bench" if value == b"bench" else None
            return user

        @property
        def login_url(self) -> str:
            return "/login"

        @property
        def login_handler(self) -> type:
            return LoginHandler

    return TokenAuth()


def _download_handler() -> type:
    from bokeh.server.views.auth_request_handler import AuthRequestHandler
    from tornado.web import HTTPError, authenticated

    class RecordingHandler(AuthRequestHandler):
        """GET /recordings/<name>: a file this UI recorded, as an attachment."""

        def initialize(self, ui: UiServer) -> None:
            self.ui = ui

        @authenticated
        async def get(self, name: str) -> None:
            path = self.ui.recorded.get(name)
            if path is None or os.path.dirname(os.path.abspath(path)) != self.ui.recordings_dir \
                    or not os.path.isfile(path):
                raise HTTPError(404, "no such recording of this page")
            self.ui.counts["downloads"] += 1
            self.set_header("Content-Type", "application/octet-stream")
            self.set_header("Content-Disposition",
                            f"attachment; filename*=UTF-8''{quote(name)}")
            self.set_header("Content-Length", str(os.path.getsize(path)))
            with open(path, "rb") as f:
                while True:
                    chunk = f.read(1 << 16)
                    if not chunk:
                        break
                    self.write(chunk)
                    await self.flush()

    return RecordingHandler

