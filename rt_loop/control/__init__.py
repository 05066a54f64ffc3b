"""The control channel: scripted tests drive a running plant server, one JSON
object per line each way, on a Unix socket of this machine or over TCP from
another (with a token; TLS when asked).

    dct-hil serve --control /tmp/bench.sock --control-tcp 7000 --control-token-file t ...
    printf '{"op": "read", "names": ["vehicle_speed_kmh", "gear"]}\\n' | nc -U /tmp/bench.sock

Where things are: ``requests.py`` answers the requests (``RequestHandler``),
``serving.py`` listens and serves the connections (``ControlServer``,
started and stopped by ``Server`` when it is given ``control_path`` or
``control_tcp``), ``client.py`` is the other end (``ControlClient``).

Requests (``{"op": ..., ...}``) and answers (``{"ok": true, ...}``):

========================  =====================================================
``hello {token}``         first on a TCP channel with a token; ``server``,
                          ``protocol``
``ping``                  ``time_s``: plant time
``snapshot``              ``snapshot``: ``Server.snapshot()``
``read {names}``          ``values``: {name: value}; a name is a plant output
                          (``vehicle_speed_kmh``, ``time_s``, ``gear``, ...),
                          ``maneuver_time_s``, a received value ``cmd.<name>``,
                          a CAN signal ``Message.Signal`` (its last value),
                          or an online parameter ``params.<name>``
``set {name, value}``     a writable plant input (``road_grade_pct``,
                          ``accel_pedal_pct``, ... or ``override.<input>``, and
                          the parameters marked online, ``params.<name>``);
                          ``applied``: the loop took it (False: queued)
``inject {spec}``         ``id``: a fault (``rt_loop.faults`` spec)
``watch {when}``          ``id``: a watch (latches the plant time ``when``
                          holds); it ends with the connection that set it
``clear {id}``            the fault or watch ends and is freed
``clear_all``
``faults``                ``faults``: the set faults and watches (state, times)
``events``                ``events``: every start and end so far
``config``                ``config``: ``Server.config()`` (transport, files,
                          ...); ``ops``: the requests served
``reset_plant``           the plant at rest as it starts (standing, idling,
                          neutral, clutches open), plant time going on
``restore_params``        every ``params.<name>`` that ``set`` wrote back to
                          the server's start value; ``restored``: {name: value}
``ignition {off_s}``      where the reference TCU runs beside the server: it
                          is switched off and on again (a fresh TCU)
``stop``                  the loop stops; ``report``: the server's report
========================  =====================================================

A request that cannot be served (not JSON, unknown op, unknown name, value
out of range, bad fault spec) is answered ``{"ok": false, "error": "<one
line>"}`` and changes nothing; the channel keeps serving. NaN in answers is
written as null. Faults stay set when the connection that injected them
ends (they are the plant's state, seen by every client).
"""

from rt_loop.control.client import ControlClient, parse_url
from rt_loop.control.requests import (
    Client,
    ControlError,
    RequestHandler,
    _Refused,
    check_socket_path,
)
from rt_loop.control.serving import MAX_LINE, ControlServer

__all__ = ["MAX_LINE", "Client", "ControlClient", "ControlError", "ControlServer",
           "RequestHandler", "_Refused", "check_socket_path", "parse_url"]
