"""The control channel's requests: one JSON object in, one answer out.

``RequestHandler(server)`` answers the requests of the table in
``rt_loop.control`` against a running ``rt_loop.server.Server``. It never
touches the tick: it reads a sequence-counted copy of the loop's statistics
(a ``StatsReader`` of its own), the CAN signals' last values, and acts only
through the server's own paths: plant inputs through the loop's ``cal`` ring
(holding ``Server.cal_lock``, the ring's shared producer side), faults and
watches through ``Server.faults`` (``rt_loop.faults.FaultManager``), and a
stop as ``rt_loop_request_stop`` (whoever runs the server finalises its
files). ``handle(request, client)`` never raises: a request that cannot be
served is answered ``{"ok": false, "error": "<one line>"}`` and changes
nothing. ``client``: the connection's own state (``Client``): the watches it
set are its own and end with it.
"""

from __future__ import annotations

import json
import math
import os
import stat
import struct
import time
from typing import Any

__all__ = ["Client", "ControlError", "RequestHandler", "check_socket_path"]

#: how long a set waits for the loop to take the write (wall seconds)
WRITE_WAIT_S = 0.5
#: how long a stop waits for the loop to end before answering
STOP_WAIT_S = 10.0


class ControlError(RuntimeError):
    """A refused request or a channel that cannot be used (one line)."""


class _Refused(Exception):
    """A request answered ok: false."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


def check_socket_path(path: str, error: type = ControlError) -> None:
    """Raises ``error`` (one line) when ``path`` cannot be a control socket:
    too long for a Unix socket address, in a folder that does not exist, or an
    existing file that is not a socket."""
    if len(os.fsencode(path)) > 107:
        raise error(f"control socket {path}: the path is too long for a Unix socket "
                    "(at most 107 bytes)")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise error(f"control socket {path}: folder {folder} does not exist")
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as e:
        raise error(f"control socket {path}: {e.strerror}") from None
    if not stat.S_ISSOCK(st.st_mode):
        raise error(f"control socket {path}: exists and is not a socket")


def _clean(value: Any) -> Any:
    """JSON-ready: NaN and infinities become None, tuples lists."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


class Client:
    """What one connection owns: the watches it set and its captures (both end
    with it)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.watches: set[int] = set()
        self.captures: set[int] = set()


class RequestHandler:
    """Answers control requests for a running ``rt_loop.server.Server``."""

    def __init__(self, server: Any) -> None:
        from rt_loop.faults import FaultError
        from rt_loop.measure.stimulus import writable_of_regions
        from rt_loop.measure.xcp import a2l as _a2l
        from rt_loop.stats import StatsReader

        self.server = server
        self._ffi, self._lib, self._loop = server._ffi, server._lib, server._l
        self._FaultError = FaultError
        self._stats = StatsReader(self._ffi, self._lib, self._loop, server.channels)
        self._names = server.faults.names
        #: what ``set`` may write: {name: (offset, size, lo, hi)}
        self.writable = writable_of_regions(_a2l.calibration_regions(self._ffi, self._lib))
        #: the online parameters as the server started with them, and those ``set`` wrote since
        self._params_at_start = self._start_params()
        self._params_written: set[str] = set()
        self.counts = {"requests": 0, "refused": 0, "writes": 0}
        self._ops = {
            "ping": self._ping, "snapshot": self._snapshot, "read": self._read,
            "set": self._set, "inject": self._inject, "watch": self._watch,
            "clear": self._clear, "clear_all": self._clear_all, "faults": self._faults,
            "events": self._events, "config": self._config, "stop": self._stop_loop,
            "reset_plant": self._reset_plant, "restore_params": self._restore_params,
            "capture": self._capture, "capture_status": self._capture_status,
            "capture_fetch": self._capture_fetch, "capture_stop": self._capture_stop,
            "capture_clear": self._capture_clear,
        }

    def add_op(self, name: str, op: Any) -> None:
        """Serves ``op(request) -> dict`` as the request ``name`` (a request the
        process running the server offers, e.g. the reference TCU's ``ignition``);
        a ValueError it raises is the refusal's line."""
        if name in self._ops:
            raise ValueError(f"control op {name!r} exists already")

        def served(request: dict) -> dict:
            try:
                return op(request)
            except ValueError as e:
                raise _Refused(str(e)) from None

        self._ops[name] = served

    def client_ended(self, client: Client) -> None:
        """Frees what ``client`` owned (its watches, its captures: counted as
        ``captures_abandoned`` when one was not done)."""
        for wid in sorted(client.watches):
            try:
                self.server.faults.clear(wid)
            except self._FaultError:
                pass                          # cleared already (clear_all, or by id)
        client.watches.clear()
        captures = self.server.captures
        for cid in sorted(client.captures):
            if captures is None:
                break
            try:
                if captures.status(cid)["state"] != "done":
                    self.counts["captures_abandoned"] = self.counts.get("captures_abandoned",
                                                                        0) + 1
                captures.clear(cid)
            except ValueError:
                pass                          # cleared already
        client.captures.clear()

    # ------------------------------------------------------------ requests
    def handle_line(self, line: bytes | str, client: Client | None = None) -> dict:
        """The answer to one request line (never raises)."""
        try:
            request = json.loads(line)
        except (ValueError, UnicodeDecodeError) as e:
            self.counts["requests"] += 1
            self.counts["refused"] += 1
            return {"ok": False, "error": f"not JSON: {_one_line(e)}"}
        return self.handle(request, client)

    def handle(self, request: Any, client: Client | None = None) -> dict:
        """The answer to one request (a decoded JSON object; never raises).
        In-process users (``dct_hil.bench``) call it directly: the same
        checks and answers as over the socket."""
        self.counts["requests"] += 1
        try:
            if not isinstance(request, dict):
                raise _Refused("a request is a JSON object with an op, e.g. {\"op\": \"ping\"}")
            op = request.get("op")
            if op not in self._ops:
                raise _Refused(f"unknown op {op!r}; ops: " + ", ".join(self._ops))
            answer = self._ops[op](request)
            if op == "watch" and client is not None:
                client.watches.add(answer["id"])
            elif op == "capture" and client is not None:
                client.captures.add(answer["id"])
            return _clean({"ok": True, **answer})
        except _Refused as e:
            self.counts["refused"] += 1
            return {"ok": False, "error": _one_line(e)}
        except self._FaultError as e:
            self.counts["refused"] += 1
            return {"ok": False, "error": _one_line(e)}
        except Exception as e:  # the channel keeps serving
            self.counts["refused"] += 1
            return {"ok": False, "error": f"{type(e).__name__}: {_one_line(e)}"}

    # ------------------------------------------------------------ values
    def _copy(self) -> Any:
        return self._stats.read()

    def read_values(self, names: Any) -> dict:
        """{name: value} of plant outputs, maneuver_time_s, cmd.<name>,
        Message.Signal and online parameters (params.<name>); raises _Refused
        naming the first unknown name."""
        if isinstance(names, str):
            names = [names]
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise _Refused("read needs names: a list of value names")
        s = self._copy()
        values = {}
        nm = self._names
        commands = None
        for name in names:
            if name in nm.outputs:
                values[name] = float(getattr(s.outputs, name))
            elif name == "maneuver_time_s":
                t = float(s.maneuver_time_s)
                values[name] = t if t >= 0 else None
            elif name == "sim_time_s":
                values[name] = float(s.sim_time_s)
            elif name.startswith("cmd.") and name[4:] in nm.commands:
                if commands is None:
                    commands = s.commands
                values[name] = float(commands[nm.commands[name[4:]]])
            elif name in nm.signals:
                values[name] = float(self._loop.signal_values[nm.signals[name][2]])
            elif name.startswith("params."):
                if name not in self.writable:
                    raise _Refused(f"read: {name!r} is no online parameter (the single values marked "
                                   "# online in plant/data/ranges.toml, e.g. params.engine.idle_speed_rpm)")
                values[name] = self._param(name)
            else:
                try:
                    nm.operand(name, "read")
                except self._FaultError as e:
                    raise _Refused(str(e)) from None
                raise _Refused(f"read: {name!r} cannot be read")
        return values

    def _ping(self, _r: dict) -> dict:
        s = self._copy()
        return {"time_s": float(s.sim_time_s), "state": self._stats.state}

    def _snapshot(self, _r: dict) -> dict:
        return {"snapshot": self.server.snapshot()}

    def _read(self, r: dict) -> dict:
        return {"values": self.read_values(r.get("names"))}

    def _param(self, name: str) -> float:
        """An online parameter's value in the loop (as an XCP master uploads it: the
        loop writes it only when it applies a queued write, a whole aligned double)."""
        offset = self.writable[name][0]
        return struct.unpack("<d", self._ffi.buffer(self._ffi.cast("char *", self._loop) + offset, 8)[:])[0]

    def _start_params(self) -> dict[str, float]:
        """{params.<name>: value} of the parameter set the server loaded (its file and
        overrides), laid out as in the loop, whatever was written since."""
        from plant.params import fill_params

        ffi = self._ffi
        fresh = ffi.new("dct_params *")
        fill_params(ffi, fresh, self.server.params)
        base = ffi.offsetof("rt_loop", "plant", "params")
        blob = ffi.buffer(fresh)
        return {name: struct.unpack_from("<d", blob, offset - base)[0]
                for name, (offset, _size, _lo, _hi) in self.writable.items()
                if name.startswith("params.") and 0 <= offset - base <= len(blob) - 8}

    # ------------------------------------------------------------ writes
    def target(self, name: Any) -> tuple[str, tuple]:
        """(region name, (offset, size, lo, hi)) of a name ``set`` may write."""
        if not isinstance(name, str) or not name:
            raise _Refused("set needs name: a plant input such as road_grade_pct")
        key = name if name in self.writable else f"override.{name}"
        if key not in self.writable:
            inputs = sorted(n.split(".", 1)[1] for n in self.writable
                            if n.startswith("override."))
            raise _Refused(f"set: {name!r} is not a plant input a test may set (inputs: "
                           + ", ".join(inputs) + "; or an online params.<name>)")
        if key in ("override.accel_pedal_pct", "override.brake_pedal_pct") and \
                self.server.maneuver_playing:
            raise _Refused(f"set: {name} is played by the maneuver's driver table now")
        return key, self.writable[key]

    def write_value(self, name: Any, value: Any) -> bool:
        """Queues one value into the cal ring (holding the server's cal_lock);
        True once the loop applied it, False when it is still queued."""
        from rt_loop.measure.xcp.loop_backend import push_writes

        key, (offset, size, lo, hi) = self.target(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Refused(f"set: {name} value must be a number, got {value!r}")
        x = float(value)
        if not math.isfinite(x) or not (lo <= x <= hi):
            raise _Refused(f"set: {name} = {value!r} is outside {lo:g} .. {hi:g}")
        if size != 8:
            raise _Refused(f"set: {name} is not a single value")
        ids = push_writes(self._ffi, self._lib, self._loop, [(offset, struct.pack("<d", x))],
                          self.server.cal_lock)
        if ids is None:
            raise _Refused("set: the loop's write ring is full (is the loop ticking?)")
        self.counts["writes"] += 1
        if key.startswith("params."):
            self._params_written.add(key)
        first, last = ids
        cal = self._loop.cal
        deadline = time.monotonic() + WRITE_WAIT_S
        while self.server.running and time.monotonic() < deadline:
            if max(int(cal.last_applied_id), int(cal.last_refused_id)) >= last:
                if first <= int(cal.last_refused_id) <= last:
                    raise _Refused(f"set: the loop refused {name} = {value!r}")
                return True
            time.sleep(0.0005)
        return False

    def _set(self, r: dict) -> dict:
        if "value" not in r:
            raise _Refused("set needs value")
        return {"applied": self.write_value(r.get("name"), r["value"])}

    # ------------------------------------------------------------ faults
    def _inject(self, r: dict) -> dict:
        spec = r.get("spec")
        if not isinstance(spec, dict):
            raise _Refused("inject needs spec: a fault table such as {\"kind\": \"can.omit\", "
                           "\"message\": \"VEH_Driver\"}")
        return {"id": self.server.faults.inject(spec)}

    def _watch(self, r: dict) -> dict:
        when = r.get("when")
        start = r.get("start_s")
        return {"id": self.server.faults.watch(when, start_s=start)}

    def _fault_id(self, r: dict) -> int:
        fid = r.get("id")
        if isinstance(fid, bool) or not isinstance(fid, int):
            raise _Refused(f"clear needs id: the number inject or watch returned, got {fid!r}")
        return fid

    def _clear(self, r: dict) -> dict:
        self.server.faults.clear(self._fault_id(r))
        return {}

    def _clear_all(self, _r: dict) -> dict:
        self.server.faults.clear_all()
        return {}

    def _faults(self, _r: dict) -> dict:
        s = self._copy()
        return {"faults": self.server.faults.status(s), "time_s": float(s.sim_time_s)}

    def _events(self, _r: dict) -> dict:
        return {"events": self.server.faults.events()}

    def _config(self, _r: dict) -> dict:
        return {"config": self.server.config(), "ops": list(self._ops)}

    def _reset_plant(self, _r: dict) -> dict:
        try:
            self.server.reset_plant()
        except RuntimeError as e:           # ServerError: the loop is not running, ...
            raise _Refused(f"reset_plant: {e}") from None
        return {"time_s": float(self._copy().sim_time_s)}

    def _restore_params(self, _r: dict) -> dict:
        """Every online parameter ``set`` wrote back to the value the server started
        with (a calibration tool's own writes over XCP are not the channel's)."""
        restored = {}
        for name in sorted(self._params_written):
            value = self._params_at_start[name]
            self.write_value(name, value)
            restored[name] = value
        self._params_written.clear()
        return {"restored": restored}

    # ------------------------------------------------------------ captures
    def _captures(self) -> Any:
        try:
            return self.server.capture_manager()
        except RuntimeError as e:           # ServerError: the loop is not running
            raise _Refused(f"capture: {e}") from None

    def _capture(self, r: dict) -> dict:
        from rt_loop.measure.capture import CaptureError

        keys = ("signals", "every_s", "start_when", "pre_s", "stop_when", "post_s", "duration_s")
        extra = sorted(set(r) - {"op", *keys})
        if extra:
            raise _Refused(f"capture: unknown fields {', '.join(extra)} (fields: "
                           + ", ".join(keys) + ")")
        try:
            cid = self._captures().start(**{k: r[k] for k in keys if k in r})
        except CaptureError as e:
            raise _Refused(str(e)) from None
        return {"id": cid}

    def _capture_call(self, r: dict, what: str) -> Any:
        from rt_loop.measure.capture import CaptureError

        captures = self._captures()
        try:
            return getattr(captures, what)(r.get("id"))
        except CaptureError as e:
            raise _Refused(str(e)) from None

    def _capture_status(self, r: dict) -> dict:
        return {"capture": self._capture_call(r, "status")}

    def _capture_fetch(self, r: dict) -> dict:
        got = self._capture_call(r, "fetch")
        return {"capture": got["status"], "tick": got["tick"].tolist(),
                "time_s": got["time_s"].tolist(),
                "values": {n: v.tolist() for n, v in got["values"].items()}}

    def _capture_stop(self, r: dict) -> dict:
        self._capture_call(r, "stop")
        return {}

    def _capture_clear(self, r: dict) -> dict:
        self._capture_call(r, "clear")
        return {}

    # ------------------------------------------------------------ stop
    def _stop_loop(self, _r: dict) -> dict:
        self._lib.rt_loop_request_stop(self._loop)
        self.server.wait(STOP_WAIT_S)
        return {"report": self.server.report(histograms=False)}
