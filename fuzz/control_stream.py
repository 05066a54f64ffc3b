"""atheris target: the control channel's TCP side (rt_loop.control.serving) of
a running plant server with a token: a client's bytes as they come (with or
without the right hello first, cut at arbitrary points, then the end of its
sending). Every answer must be one JSON object with "ok"; the serving thread
must stay alive and the loop running; the connection must end.

    scripts/fuzz-coverage control_stream --seconds 60
"""

from __future__ import annotations

import json
import socket

import _atheris

TOKEN = "fuzz-stream-token"
srv = None
port = 0
count = 0


def _import() -> None:
    import rt_loop.access
    import rt_loop.control.serving  # noqa: F401


def _start() -> None:
    global srv, port
    import os

    from rt_loop.server import Server

    srv = Server(f"fuzz-stream-{os.getpid()}", interface="virtual", priority=0,
                 control_tcp=("127.0.0.1", 0), control_token=TOKEN)
    srv.start()
    srv.control._log = lambda _line: None
    srv.control._ops.pop("stop")                  # the one request that ends the run
    port = srv.control.tcp_address[1]


def TestOneInput(data: bytes) -> None:
    global count
    import atheris

    if srv is None:
        _start()
    fdp = atheris.FuzzedDataProvider(data)
    hello = fdp.ConsumeIntInRange(0, 2)           # none, the right one, a wrong one
    cuts = sorted(fdp.ConsumeIntListInRange(fdp.ConsumeIntInRange(0, 4), 0, 4096))
    body = fdp.ConsumeBytes(fdp.remaining_bytes())
    head = b"" if hello == 0 else json.dumps(
        {"op": "hello", "token": TOKEN if hello == 1 else "not-the-token"}).encode() + b"\n"
    stream = head + body
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        last = 0
        for c in [*cuts, len(stream)]:
            c = min(max(c, last), len(stream))
            if c > last:
                try:
                    s.sendall(stream[last:c])
                except OSError:
                    break                         # the server closed it (a refusal): fine
                last = c
        try:
            s.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        f = s.makefile("rb")
        try:
            for line in f:
                try:
                    answer = json.loads(line)
                except ValueError:
                    raise _atheris.Finding(f"an answer that is not JSON: {line[:200]!r}") from None
                if not isinstance(answer, dict) or "ok" not in answer:
                    raise _atheris.Finding(f"not an answer: {answer!r}")
                if not answer["ok"]:
                    _atheris.one_line(Exception(answer.get("error", "")))
        except TimeoutError:
            raise _atheris.Finding("the connection did not end within 5 s of the client's "
                                   "end of sending") from None
        except OSError:
            pass                                  # reset after a refusal
        finally:
            f.close()
    finally:
        s.close()
    ctl = srv.control
    if ctl._thread is None or not ctl._thread.is_alive():
        raise _atheris.Finding("the serving thread died")
    if not srv.running:
        raise _atheris.Finding("the loop stopped")
    count += 1
    if count % 200 == 0:
        ctl.handle({"op": "clear_all"})
        caps = srv.captures
        if caps is not None:
            for cid in caps.ids():
                caps.clear(cid)


if __name__ == "__main__":
    _atheris.run(TestOneInput, _import, _start)
