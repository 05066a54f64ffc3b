"""Scripted tests of a running bench: the plant server (and the reference TCU,
or the TCU under test on the bus), driven from Python.

    from dct_hil.bench import Bench

    with Bench.start() as bench:                  # embedded transport, reference TCU
        bench.set("accel_pedal_pct", 40)
        t = bench.wait_until("gear == 2", timeout_s=8)      # plant time it first held
        fid = bench.inject("can.omit", message="VEH_Driver")
        bench.wait_until("TCU_EngineCmd.TorqueRequestActive == 0", timeout_s=0.5)
        bench.clear(fid)

    bench = Bench.attach("/tmp/bench.sock")       # dct-hil serve --control /tmp/bench.sock
    bench = Bench.attach("tcp://bench-pc:7000", token_file="bench.token")  # --control-tcp

``Bench.start`` runs a ``rt_loop.server.Server`` in this process: on the
embedded transport (python-can's in-process virtual bus, a channel of its
own, the reference TCU in a thread) or on SocketCAN (``channel``, default
vcan0; the reference TCU as a second process, as ``dct-hil demo`` runs it);
``tcu=False`` when the TCU under test is on the bus. It returns once the
TCU is heard (every TCU message accepted by the loop). ``Bench.attach``
drives an already running ``dct-hil serve --control PATH`` through its
control socket, or one on another machine through ``--control-tcp``
(``tcp://`` or ``tls://``, with a token), with the same methods: both go through the same request
handler (``rt_loop.control``), so a test behaves alike in both.

Values (``read``): plant outputs (``vehicle_speed_kmh``, ``gear``,
``time_s``, ...), ``maneuver_time_s``, the received values ``cmd.<name>``
as the loop applied them, and every CAN signal ``Message.Signal`` (its
last value on the bus, either direction). ``set`` writes the plant inputs a
test may set (``road_grade_pct``, ``accel_pedal_pct`` and
``brake_pedal_pct`` when no maneuver plays, ``engine_on``).

Time is plant time: ``wait_until(condition, timeout_s)`` sets a watch in the
loop (exact to the tick: it returns the plant time the condition first
held) and raises ``BenchTimeout`` naming the condition and the plant time
reached when ``timeout_s`` of plant time pass first; ``sleep(plant_s)``
waits for plant time to advance. Faults: ``inject(kind, **params)`` with
the kinds and schedule keys (``start_s``, ``when``, ``duration_s``) of
``rt_loop.faults``.

Every error is a ``BenchError`` of one line.
"""

from __future__ import annotations

import itertools
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["Bench", "BenchCapture", "BenchError", "BenchTimeout", "TRANSPORTS"]

TRANSPORTS = ("embedded", "socketcan")
#: how long start() waits for the TCU to be heard (wall seconds, at time scale 1)
TCU_HEARD_TIMEOUT_S = 30.0
#: reset(): how long the car may take to stop and the TCU to calm (plant seconds)
RESET_TIMEOUT_S = 60.0
#: reset(): the brake pedal while the car slows down (the TCU's coast down-shifts)
RESET_BRAKE_PCT = 30.0
#: reset(): the car stands
RESET_STANDSTILL = "vehicle_speed_kmh < 0.05 and vehicle_speed_kmh > -0.05"
#: reset() of a bench with a TCU under test: plant time after the brake is released
RESET_SETTLE_S = 0.5
#: wall seconds without any advance of plant time after which a wait gives up
STALL_S = 10.0
_POLL_S = 0.005
_ids = itertools.count(1)


class BenchError(RuntimeError):
    """A bench that cannot be started or a request it refused (one line)."""


class BenchTimeout(BenchError, AssertionError):
    """``wait_until``: the condition did not hold within its plant time."""


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


class Bench:
    """A running bench (``Bench.start``) or one attached to (``Bench.attach``)."""

    def __init__(self, request: Any, *, server: Any = None, tcu: Any = None,
                 client: Any = None, record: str | None = None, time_scale: float = 1.0,
                 transport: str = "embedded", channel: str | None = None,
                 work_dir: Any = None) -> None:
        self._request_fn = request
        self.server = server            # the in-process Server (None when attached)
        self._tcu = tcu
        self._client = client
        self.record_path = record
        self.time_scale = time_scale
        self.transport = transport
        self.channel = channel
        self._work_dir = work_dir
        self._report: dict | None = None
        self._stopped = False
        self.tcu_report: dict | None = None
        self._status_signals: list[str] | None = None
        self._final_events: list | None = None

    # ------------------------------------------------------------------ set-up
    @classmethod
    def start(cls, transport: str = "embedded", channel: str | None = None, tcu: bool = True,
              record: str | os.PathLike | None = None, maneuver: str | None = None,
              params: str | os.PathLike | None = None, mapping: Any = None,
              time_scale: float = 1.0, priority: int = 0, faults: str | os.PathLike | None = None,
              control: str | os.PathLike | None = None, log: str | os.PathLike | None = None,
              tcu_clock: str | None = None, record_every_s: float = 0.002,
              tcu_timeout_s: float = TCU_HEARD_TIMEOUT_S, tcu_impl: str = "c") -> Bench:
        """Starts a server (and the reference TCU unless ``tcu`` is False) and
        returns once the TCU is heard.

        ``transport`` "embedded" (python-can's in-process bus, a channel of
        its own per bench, the TCU in a thread) or "socketcan" (``channel``,
        default vcan0, must be a CAN interface that is up; the TCU as a
        second process). ``record``: a recording of every plant output (.mf4
        with the CAN traffic, or .csv); ``maneuver``: a scripted maneuver of
        ``plant.maneuvers`` the loop's driver plays from the TCU's first
        frame (the pedals are then the maneuver's; the run goes on after it
        with its last row held); ``params``, ``mapping``, ``time_scale``,
        ``priority`` (0: normal scheduling), ``faults`` (a [[fault]] TOML
        file), ``control`` (also serve a control socket), ``log`` (the CAN
        traffic) as ``rt_loop.server.Server`` takes them. ``tcu_impl``: the
        reference TCU, "c" (``tcu_stub.c_node``; on the embedded transport its
        frames go through the loop's own rings, no bus between them) or
        "python" (``tcu_stub.can_tcu``)."""
        from dct_hil.demo import can_netdev_up, make_server
        from rt_loop.server import ServerError
        from rt_loop.transport import TransportError

        if transport not in TRANSPORTS:
            raise BenchError(f"transport {transport!r}: choose " + " or ".join(TRANSPORTS))
        if tcu_impl not in ("c", "python"):
            raise BenchError(f"tcu_impl {tcu_impl!r}: choose c or python")
        if transport == "embedded":
            interface = "virtual"
            chan = channel or f"dct-hil-bench-{os.getpid()}-{next(_ids)}"
        else:
            interface = "socketcan"
            chan = channel or "vcan0"
            if not can_netdev_up(chan):
                raise BenchError(f"{chan} is not a CAN network interface that is up (ip link add "
                                 f"dev {chan} type vcan && ip link set up {chan})")
        driver, maneuver_inputs = None, None
        if maneuver is not None:
            from plant.maneuvers import MANEUVERS, get_maneuver

            try:
                m = get_maneuver(maneuver)
            except (KeyError, ValueError) as e:
                raise BenchError(f"maneuver {maneuver!r}: {_one_line(e)}") from None
            driver = getattr(m, "driver", None)
            if driver is None or not hasattr(driver, "table"):
                raise BenchError(f"maneuver {maneuver!r} is not a scripted pedal table the loop "
                                 f"can play (known: {', '.join(MANEUVERS)})")
            maneuver_inputs = dict(m.inputs) or None        # the hill-start's grade
        if record is not None:
            record = os.fspath(record)
            folder = os.path.dirname(os.path.abspath(record))
            try:
                os.makedirs(folder, exist_ok=True)
            except OSError as e:
                raise BenchError(f"record {record}: cannot create {folder}: {e.strerror}") from None
        if tcu_clock is None:
            tcu_clock = "wall" if float(time_scale) >= 1.0 else "bus"
        try:
            server = make_server(tcu_impl if tcu else "python", transport != "embedded", chan,
                                 interface=interface, priority=priority, driver=driver,
                                 maneuver_start="tcu", maneuver_inputs=maneuver_inputs,
                                 record_path=record, record_every_s=record_every_s,
                                 params_path=params, mapping=mapping, time_scale=time_scale,
                                 faults_path=faults, control_path=control, log_path=log)
        except (ServerError, TransportError, OSError, ValueError) as e:
            raise BenchError(_one_line(e)) from None
        from rt_loop.control import ControlServer

        handler = server.control if server.control is not None else None
        bench = None
        try:
            try:
                server.start()
            except (ServerError, TransportError) as e:
                raise BenchError(_one_line(e)) from None
            handler = server.control or ControlServer(server, None)
            work = tempfile.TemporaryDirectory(prefix="dct-hil-bench-")
            bench = cls(_local(handler), server=server, record=record,
                        time_scale=server.time_scale, transport=transport, channel=chan,
                        work_dir=work)
            if tcu:
                from dct_hil.demo import RestartableTcu

                bench._tcu = RestartableTcu(lambda: _start_tcu(
                    interface, chan, server, mapping, tcu_clock, work.name, tcu_impl))
                handler.add_op("ignition", bench._tcu.ignition_op)
                bench._await_tcu(tcu_timeout_s / min(1.0, server.time_scale))
        except BaseException:
            if bench is not None:
                bench._teardown()
            else:
                server.stop()
            raise
        return bench

    @classmethod
    def attach(cls, target: str | os.PathLike, timeout_s: float = 30.0, *,
               token: str | None = None, token_file: str | os.PathLike | None = None,
               ca_file: str | os.PathLike | None = None) -> Bench:
        """Drives a running ``dct-hil serve`` through its control channel: a
        socket path (``--control PATH``) or ``tcp://HOST:PORT`` /
        ``tls://HOST:PORT`` (``--control-tcp``; the token from ``token_file``,
        the server's certificate checked against ``ca_file``)."""
        from rt_loop.control import ControlClient, ControlError

        try:
            client = ControlClient(target, timeout_s=timeout_s, token=token,
                                   token_file=token_file, ca_file=ca_file)
        except ControlError as e:
            raise BenchError(_one_line(e)) from None
        try:
            answer = client.request("config")
        except ControlError as e:
            client.close()
            raise BenchError(_one_line(e)) from None
        config = answer["config"]

        def request(op: str, **fields: Any) -> dict:
            try:
                return client.request(op, **fields)
            except ControlError as e:
                raise BenchError(_one_line(e)) from None

        return cls(request, client=client, record=config.get("record"),
                   time_scale=float(config.get("time_scale") or 1.0),
                   transport="socketcan" if config.get("transport") == "socketcan" else "attached",
                   channel=config.get("channel"))

    def detach(self) -> None:
        """Ends an attached bench's connection and leaves the server running (its
        watches end with the connection; faults set stay)."""
        if self.server is not None:
            raise BenchError("detach: this bench runs in this process (stop() ends it)")
        if not self._stopped:
            self._stopped = True
            self._client.close()

    def _await_tcu(self, timeout_s: float) -> None:
        """Until every TCU message the mapping needs (not ``optional``, such as a
        status a foreign TCU may not have) has been accepted and none is timed out."""
        optional = {m.name for m in self.server.mapping.messages if getattr(m, "optional", False)}
        end = time.monotonic() + timeout_s
        while True:
            snap = self._request("snapshot")["snapshot"]
            msgs = {n: m for n, m in snap["counts"]["tcu_messages"].items()
                    if n.rsplit(":", 1)[-1] not in optional}
            if msgs and all(m["accepted"] > 0 and not m["timed_out"] for m in msgs.values()):
                return
            if snap["state"] != "running":
                raise BenchError(f"the loop stopped ({snap['state']}) before the TCU was heard")
            alive = getattr(self._tcu, "alive", lambda: True)
            if not alive():
                raise BenchError(f"the TCU stopped before it was heard: "
                                 f"{self._tcu.status_line()}")
            if time.monotonic() > end:
                missing = [n for n, m in msgs.items() if not m["accepted"]] or list(msgs)
                line = getattr(self._tcu, "status_line", lambda: "")()
                raise BenchError(f"the TCU was not heard within {timeout_s:g} s (no accepted "
                                 f"frame of {', '.join(missing)})" + (f"; TCU: {line}" if line
                                                                     else ""))
            time.sleep(0.02)

    # ------------------------------------------------------------------ requests
    def _request(self, op: str, **fields: Any) -> dict:
        if self._stopped:
            raise BenchError(f"{op}: the bench is stopped")
        return self._request_fn(op, **fields)

    def read(self, name: str) -> float | None:
        """One value: a plant output, maneuver_time_s, cmd.<name>, Message.Signal or
        an online parameter (params.<name>)."""
        return self._request("read", names=[name])["values"][name]

    def read_many(self, names: list[str] | tuple[str, ...]) -> dict:
        """{name: value} of several values from the same moment."""
        return self._request("read", names=list(names))["values"]

    def __getitem__(self, name: str) -> float | None:
        return self.read(name)

    def set(self, name: str, value: float) -> None:
        """Sets a plant input (road_grade_pct, accel_pedal_pct, ...; override.<input>)
        or an online parameter (params.<name>; ``reset`` puts it back) at the next
        tick boundary."""
        self._request("set", name=name, value=value)

    @property
    def time_s(self) -> float:
        """Plant time (s)."""
        return float(self._request("ping")["time_s"])

    def snapshot(self) -> dict:
        return self._request("snapshot")["snapshot"]

    # ------------------------------------------------------------------ faults
    def inject(self, kind: str, **params: Any) -> int:
        """Injects a fault (``rt_loop.faults`` kinds); returns its id."""
        return int(self._request("inject", spec={"kind": kind, **params})["id"])

    def clear(self, fault_id: int) -> None:
        self._request("clear", id=fault_id)

    def clear_all(self) -> None:
        self._request("clear_all")

    def faults(self) -> list[dict]:
        """The set faults and watches: id, kind, target, state, started_s, ended_s, ..."""
        return self._request("faults")["faults"]

    def events(self, watches: bool = False) -> list[dict]:
        """Every fault start and end so far (plant time; the watches of
        ``wait_until`` only with ``watches``)."""
        if self._stopped and self._final_events is not None:
            events = self._final_events
        else:
            events = self._request("events")["events"]
        return events if watches else [e for e in events if e["kind"] != "watch"]

    # ------------------------------------------------------------------ time
    def wait_until(self, condition: str, timeout_s: float) -> float:
        """Waits until ``condition`` holds (``rt_loop.faults`` condition syntax,
        e.g. ``"gear == 2 and vehicle_speed_kmh > 20"``), checked by the loop
        every tick; returns the plant time it first held. Raises BenchTimeout
        when ``timeout_s`` of plant time pass first."""
        try:
            timeout = float(timeout_s)
        except (TypeError, ValueError):
            raise BenchError(f"wait_until: timeout_s must be seconds, got {timeout_s!r}") from None
        if not (math.isfinite(timeout) and timeout > 0):
            raise BenchError(f"wait_until: timeout_s must be seconds above 0, got {timeout_s!r}")
        t0 = self.time_s
        wid = int(self._request("watch", when=condition)["id"])
        try:
            last_t, last_wall = t0, time.monotonic()
            while True:
                answer = self._request("faults")
                now = float(answer["time_s"])
                mine = next((f for f in answer["faults"] if f["id"] == wid), None)
                if mine is not None and mine["started_s"] is not None:
                    return float(mine["started_s"])
                if now >= t0 + timeout:
                    raise BenchTimeout(f"{condition!r} did not hold within {timeout:g} s of plant "
                                       f"time (from {t0:.3f} s to {now:.3f} s)")
                self._check_progress(now, last_t, last_wall, f"waiting for {condition!r}")
                if now > last_t:
                    last_t, last_wall = now, time.monotonic()
                time.sleep(_POLL_S)
        finally:
            if not self._stopped:
                try:
                    self._request("clear", id=wid)
                except BenchError:
                    pass

    def _check_progress(self, now: float, last_t: float, last_wall: float, what: str) -> None:
        if now > last_t:
            return
        if time.monotonic() - last_wall > STALL_S / min(1.0, self.time_scale):
            snap = self._request("snapshot")["snapshot"]
            raise BenchError(f"{what}: plant time stopped at {now:.3f} s (loop {snap['state']})")

    def sleep(self, plant_s: float) -> float:
        """Waits until ``plant_s`` seconds of plant time have passed; returns the plant time."""
        try:
            dt = float(plant_s)
        except (TypeError, ValueError):
            raise BenchError(f"sleep: plant_s must be seconds, got {plant_s!r}") from None
        if not (math.isfinite(dt) and dt >= 0):
            raise BenchError(f"sleep: plant_s must be seconds >= 0, got {plant_s!r}")
        t0 = self.time_s
        end = t0 + dt
        last_t, last_wall = t0, time.monotonic()
        while True:
            now = self.time_s
            if now >= end:
                return now
            self._check_progress(now, last_t, last_wall, f"sleeping {dt:g} s")
            if now > last_t:
                last_t, last_wall = now, time.monotonic()
            time.sleep(min(0.02, max(0.001, (end - now) / self.time_scale)))

    # ------------------------------------------------------------------ captures
    def capture(self, signals: list[str] | tuple[str, ...], every_s: float | None = None,
                start_when: str | None = None, pre_s: float = 0.0,
                stop_when: str | None = None, post_s: float = 0.0,
                duration_s: float | None = None) -> BenchCapture:
        """Arms a capture in the loop (``rt_loop.measure.capture``): ``signals``
        (plant outputs, ``inputs.<name>``, ``cmd.<name>``, ``Message.Signal``,
        ``exec_us``, ...) every ``every_s`` (default every tick), from the
        plant time ``start_when`` first holds (None: now) minus ``pre_s`` (at
        most 30 s of history, kept since it was armed) to the time
        ``stop_when`` holds plus ``post_s``, or ``duration_s`` after the start.
        Several at once; returns a ``BenchCapture`` (``wait``, ``result``,
        ``to_mf4``)."""
        fields = {"signals": list(signals), "pre_s": pre_s, "post_s": post_s}
        for k, v in (("every_s", every_s), ("start_when", start_when),
                     ("stop_when", stop_when), ("duration_s", duration_s)):
            if v is not None:
                fields[k] = v
        cid = int(self._request("capture", **fields)["id"])
        return BenchCapture(self, cid)

    # ------------------------------------------------------------------ between tests
    def reset(self, timeout_s: float = RESET_TIMEOUT_S) -> float:
        """Brings a running bench back to where a fresh one starts, for a bench
        that stays up between tests (pytest ``--bench-url``): every fault and
        watch cleared, the pedals released, the grade 0, then

        - where the reference TCU runs beside the server (the ``ignition``
          request: ``Bench.start``, ``dct-hil serve --tcu reference``): the
          plant put back at rest (``reset_plant``: standing, idling, every
          sleeve in neutral, the initial temperatures) and the TCU's ignition
          cycled (a fresh TCU: no trouble code, limp home or inhibited gear
          kept), as a fresh bench;
        - else (a TCU under test on the bus: its ignition is the bench's
          wiring): the car braked to a stop as a driver does
          (``RESET_BRAKE_PCT``, then the brake fully applied);

        then until the car is in first gear or neutral with the TCU reporting
        no active fault (``TCU_Status``, when the TCU sends one) (after the
        braking: the brake released and ``RESET_SETTLE_S`` of plant time).
        Online parameters set through the bench (``set("params.<name>", ...)``,
        by any client) go back first to the values the server started with; a
        calibration tool's own writes over XCP stay. Returns the plant time;
        raises BenchTimeout when that does not happen within ``timeout_s`` of
        plant time."""
        self.clear_all()
        if self.snapshot().get("maneuver") in ("waiting for the TCU", "running"):
            raise BenchError("reset: a maneuver plays the pedals (start the bench without one)")
        self.set("accel_pedal_pct", 0.0)
        self.set("road_grade_pct", 0.0)
        t0 = self.time_s
        ops = self._request("config").get("ops", ())
        if "restore_params" in ops:                      # a server of an earlier version has not
            self._request("restore_params")
        fresh = "ignition" in ops
        if fresh:
            self.set("brake_pedal_pct", 0.0)
            self._request("reset_plant")
            self.ignition()                                  # a fresh TCU: nothing it latched
        else:
            self.set("brake_pedal_pct", RESET_BRAKE_PCT)  # as a driver stops: the TCU downshifts
            self.wait_until(RESET_STANDSTILL, timeout_s=timeout_s)
            self.set("brake_pedal_pct", 100.0)
        calm = "gear <= 1"
        msgs = self.snapshot()["counts"]["tcu_messages"]
        status = next((n for n in msgs if n.rsplit(":", 1)[-1] == "TCU_Status"), None)
        if status is not None and msgs[status]["accepted"] > 0:
            prefix = status if ":" in status else "TCU_Status"
            calm += f" and {prefix}.ActiveFaults == 0"
        self.wait_until(calm, timeout_s=max(0.5, t0 + timeout_s - self.time_s))
        if fresh:                               # as Bench.start: the test starts at once
            return self.time_s
        self.set("brake_pedal_pct", 0.0)
        return self.sleep(RESET_SETTLE_S)

    # ------------------------------------------------------------------ the TCU
    def ignition(self, off_s: float = 0.5, timeout_s: float = TCU_HEARD_TIMEOUT_S) -> None:
        """Switches the reference TCU off and on again (``off_s`` wall seconds off:
        the plant sees its messages time out) and returns once every message it
        sent before is accepted again. Only where the reference TCU runs beside
        the server (``Bench.start``, ``dct-hil serve --tcu reference``); a TCU
        under test has its ignition on the bench's own wiring."""
        before = self.snapshot()["counts"]["tcu_messages"]
        self._request("ignition", off_s=off_s)
        heard = {n: m["accepted"] for n, m in before.items() if m["accepted"] > 0}
        end = time.monotonic() + timeout_s
        while True:
            msgs = self.snapshot()["counts"]["tcu_messages"]
            if all(msgs[n]["accepted"] > heard[n] and not msgs[n]["timed_out"] for n in heard):
                return
            if time.monotonic() > end:
                raise BenchError(f"ignition: the TCU was not heard again within {timeout_s:g} s")
            time.sleep(0.02)

    def tcu_status(self) -> dict:
        """The TCU's status message (``TCU_Status``) as {signal: value}; with
        ``tcu_stub.diagnostics`` the active faults also as DTC names
        (``dtcs``). Raises BenchError when the mapping has no such message or
        the TCU has sent none (a TCU need not have it)."""
        msgs = self.snapshot()["counts"]["tcu_messages"]
        key = next((n for n in msgs if n.rsplit(":", 1)[-1] == "TCU_Status"), None)
        if key is None:
            raise BenchError("tcu_status: the served mapping has no TCU_Status message")
        if msgs[key]["accepted"] == 0:
            raise BenchError("tcu_status: no TCU_Status frame received (the TCU on the bus "
                             "sends no status)")
        if self._status_signals is None:
            from can_dbc import codec

            msg = next((m for m in codec.messages("TCU") if m.name == "TCU_Status"), None)
            sigs = ([s.name for s in msg.signals if s.name not in ("CRC", "AliveCounter")]
                    if msg is not None else ["ActiveFaults"])
            prefix = key if ":" in key else "TCU_Status"
            self._status_signals = [f"{prefix}.{s}" for s in sigs]
        values = self._request("read", names=self._status_signals)["values"]
        out = {name.rsplit(".", 1)[1]: v for name, v in values.items()}
        decode = _dtc_decoder()
        if decode is not None and out.get("ActiveFaults") is not None:
            out["dtcs"] = decode(int(out["ActiveFaults"]))
        return out

    # ------------------------------------------------------------------ files
    def recording(self) -> dict:
        """The run's recording read back ({column: array}); complete after stop(),
        up to the last flush while running."""
        from rt_loop.measure.recorder import read_recording

        if not self.record_path:
            raise BenchError("recording: this bench records nothing (start it with record=PATH)")
        try:
            return read_recording(self.record_path)
        except (OSError, ValueError) as e:
            raise BenchError(f"recording {self.record_path}: {_one_line(e)}") from None

    # ------------------------------------------------------------------ stop
    def stop(self) -> dict:
        """Stops the TCU (safe final frames) and the server, finalises the files;
        returns the server's report (again on a second call)."""
        if self._stopped:
            return self._report or {}
        try:
            self._final_events = self._request("events")["events"]
        except BenchError:
            pass
        if self.server is None:                  # attached: the serving process finalises
            try:
                self._report = self._request("stop")["report"]
            finally:
                self._stopped = True
                path = self._client.path           # None over TCP
                self._client.close()
                end = time.monotonic() + 60.0
                while path is not None and os.path.exists(path) and time.monotonic() < end:
                    time.sleep(0.02)
            return self._report
        self._teardown()
        return self._report or {}

    def _teardown(self) -> None:
        from rt_loop.server import ServerError

        self._stopped = True
        errors = []
        if self._tcu is not None:
            try:
                self._tcu.stop()
                self.tcu_report = self._tcu.report()
            except Exception as e:  # the server still stops
                errors.append(e)
            self._tcu = None
        try:
            self.server.stop()
        except ServerError as e:
            errors.append(e)
        self._report = self.server.report(histograms=False)
        if self._work_dir is not None:
            self._work_dir.cleanup()
            self._work_dir = None
        if errors:
            raise BenchError(f"stopping: {_one_line(errors[0])}")

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


class BenchCapture:
    """A capture armed by ``Bench.capture``: ``status()``, ``wait(timeout_s)``
    until it is done, ``result()`` (``time_s``, ``tick`` and every signal as
    numpy arrays, with ``trigger_s``), ``to_mf4(path)``, ``stop()``, ``clear()``."""

    def __init__(self, bench: Bench, cid: int) -> None:
        self.bench, self.id = bench, cid

    def status(self) -> dict:
        return self.bench._request("capture_status", id=self.id)["capture"]

    def wait(self, timeout_s: float = 60.0) -> dict:
        """Waits (wall seconds) until the capture is done; returns its status."""
        end = time.monotonic() + float(timeout_s)
        while True:
            st = self.status()
            if st["state"] == "done":
                return st
            if time.monotonic() > end:
                raise BenchTimeout(f"capture {self.id} not done within {timeout_s:g} s "
                                   f"({st['state']}, {st['rows']} rows)")
            time.sleep(0.02)

    def result(self) -> dict:
        """{"time_s", "tick", <signal>: array, "status": {...}} of what it holds."""
        import numpy as np

        got = self.bench._request("capture_fetch", id=self.id)
        out: dict[str, Any] = {"time_s": np.asarray(got["time_s"], dtype=float),
                               "tick": np.asarray(got["tick"], dtype=np.uint64),
                               "status": got["capture"]}
        for name, values in got["values"].items():
            out[name] = np.asarray([np.nan if v is None else v for v in values], dtype=float)
        return out

    def to_mf4(self, path: str | os.PathLike) -> str:
        """Writes what it holds as an ASAM MDF4 file (one channel group, plant time
        as the master); returns the path."""
        from plant.extras import require

        require("asammdf")
        from asammdf import MDF, Signal

        data = self.result()
        t = data["time_s"]
        mdf = MDF(version="4.10")
        sigs = [Signal(samples=data[name], timestamps=t, name=name)
                for name in data["status"]["signals"]]
        mdf.append(sigs, comment=f"dct-hil capture {self.id}: trigger at "
                                 f"{data['status']['trigger_s']} s")
        out = os.fspath(path)
        mdf.save(out, overwrite=True)
        mdf.close()
        return out

    def stop(self) -> None:
        self.bench._request("capture_stop", id=self.id)

    def clear(self) -> None:
        self.bench._request("capture_clear", id=self.id)


def _local(handler: Any) -> Any:
    def request(op: str, **fields: Any) -> dict:
        reply = handler.handle({"op": op, **fields})
        if not reply.pop("ok", False):
            raise BenchError(reply.get("error", "refused"))
        return reply
    return request


def _start_tcu(interface: str, channel: str, server: Any, mapping: Any, clock: str,
               folder: str, impl: str = "c") -> Any:
    """The reference TCU: in this process (the C node on the loop's rings, or the
    Python node on the in-process bus), else a second process."""
    from dct_hil.demo import start_tcu

    tcu_mapping = None if mapping is None else server.mapping
    return start_tcu(impl, interface != "virtual", interface, channel, server, server.time_scale,
                     Path(folder) / "tcu-report.json", Path(folder) / "tcu.out", clock, tcu_mapping)


def _dtc_decoder() -> Any:
    """ActiveFaults bits -> DTC names, from ``tcu_stub.diagnostics`` when it is there."""
    try:
        from tcu_stub import diagnostics
    except ImportError:
        return None
    for name in ("decode_active_faults", "decode", "dtc_names", "active_dtcs"):
        fn = getattr(diagnostics, name, None)
        if callable(fn):
            return lambda bits, fn=fn: list(fn(bits))
    table = getattr(diagnostics, "DTCS", None)
    if isinstance(table, dict):
        def decode(bits: int) -> list:
            return [str(getattr(d, "name", d)) for bit, d in sorted(table.items())
                    if isinstance(bit, int) and bits >> bit & 1]
        return decode
    return None
