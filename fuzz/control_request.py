"""atheris target: the control channel's request handler
(rt_loop.control.ControlServer.handle_line) of a running plant server.

A Server on python-can's virtual bus runs its loop (priority 0) for the
whole run; each input is one request line (JSON text, the dictionary
control_request.dict helps). handle_line must answer every line; its
refusals are answers. An exception that only its catch-all turned into an
answer (an op that failed on a value it did not check) is a finding, as is
an exception out of handle_line. The "stop" op is left out (it ends the
loop); every 200 inputs the faults are cleared.
"""

from __future__ import annotations

import _atheris

ctl = None
count = 0


def _import() -> None:
    import rt_loop.control
    import rt_loop.faults  # noqa: F401


def _wrap(op):
    def checked(request):
        try:
            return op(request)
        except (ctl._Refused, ctl._FaultError):
            raise
        except Exception as e:
            raise _atheris.Finding(f"{type(e).__name__}: {e}") from e
    return checked


def _start():
    global ctl
    import os

    from rt_loop.control import ControlServer, _Refused
    from rt_loop.server import Server
    server = Server(f"fuzz-ctl-{os.getpid()}", interface="virtual", priority=0)
    server.start()
    ctl = ControlServer(server, None)
    ctl._Refused = _Refused
    ctl._ops = {name: _wrap(op) for name, op in ctl._ops.items() if name != "stop"}


def TestOneInput(data: bytes) -> None:
    global count
    if ctl is None:
        _start()
    answer = ctl.handle_line(data)
    if not isinstance(answer, dict) or "ok" not in answer:
        raise _atheris.Finding(f"not an answer: {answer!r}")
    if not answer["ok"]:
        _atheris.one_line(Exception(answer.get("error", "")))
    count += 1
    if count % 200 == 0:
        ctl.handle({"op": "clear_all"})


if __name__ == "__main__":
    _atheris.run(TestOneInput, _import, _start)
