"""The server's argument checks and the limits they hold.

Each check takes what a caller gave and returns the value the server keeps,
or raises ``ServerError`` with one line naming what is wrong. The loop's own
limits are those of ``rt_loop_prepare`` (``csrc/rt_prepare.c``).
"""

from __future__ import annotations

import math
import os
from typing import Any

from rt_loop.drain import one_line as _one_line
from rt_loop.pm_qos import DEFAULT_LATENCY_US as DEFAULT_PM_QOS_US
from rt_loop.server.errors import ServerError

#: the loop's limits: periods from 10 ms down to 50 us (rt_loop_prepare)
MIN_RATE_HZ = 100.0
MAX_RATE_HZ = 20_000.0
DEFAULT_SPIN_US = 300.0  # early wake-up at SCHED_FIFO: covers these VMs' wake-up latency beyond p99.9
OVERRUN_POLICIES = ("skip", "stop")
#: the loop's longest wall-clock period (a slowed-down run, rt_loop_prepare)
MAX_PERIOD_S = 0.1
#: rows of the in-loop driver table (RT_DRIVER_ROWS)
MAX_DRIVER_ROWS = 64
MANEUVER_STARTS = ("tcu", "now")
#: a stimulus's time 0: the plant's or the maneuver's
STIMULUS_STARTS = ("plant", "maneuver")
XCP_PROTOCOLS = ("udp", "tcp")


def _number(value: Any, what: str) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ServerError(f"{what} {value!r} is not a number") from None


def _check_choice(value: Any, choices: tuple[str, ...], what: str) -> str:
    if value not in choices:
        raise ServerError(f"{what} {value!r}: choose " + " or ".join(choices))
    return value


def _check_channel(channel: Any) -> str:
    if not isinstance(channel, str) or not channel.strip():
        raise ServerError(f"channel must be a non-empty name, got {channel!r}")
    return channel


def _check_rate(rate_hz: Any) -> float:
    rate = _number(rate_hz, "rate")
    if not (math.isfinite(rate) and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
        raise ServerError(f"rate must be {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz (a period of "
                          f"10 ms to 50 us), got {rate_hz}")
    return rate


def _check_time_scale(time_scale: Any) -> float:
    scale = _number(time_scale, "time scale")
    if not (math.isfinite(scale) and 0 < scale <= 1):
        raise ServerError(f"time scale must be above 0 and at most 1 (1: real time, 0.1: ten "
                          f"times slower), got {time_scale}")
    return scale


def _check_period(rate_hz: float, time_scale: float) -> float:
    """The wall clock between two deadlines: a tick's plant time slowed by ``time_scale``."""
    period_s = 1.0 / rate_hz / time_scale
    if period_s > MAX_PERIOD_S:
        raise ServerError(f"time scale {time_scale} at {rate_hz:g} Hz gives a period of "
                          f"{period_s * 1e3:g} ms; the loop allows up to "
                          f"{MAX_PERIOD_S * 1e3:g} ms")
    return period_s


def _check_duration(duration_s: Any) -> float | None:
    if duration_s is None:
        return None
    d = _number(duration_s, "duration")
    if not (math.isfinite(d) and d > 0):
        raise ServerError(f"duration must be a number of seconds above 0, got {duration_s}")
    return d


def _check_record_every(every_s: Any, step_s: float) -> int:
    """Ticks between two recorded samples for one each ``every_s`` of plant time."""
    every = _number(every_s, "record interval")
    if not (math.isfinite(every) and every > 0):
        raise ServerError(f"record interval must be a number of seconds above 0, "
                          f"got {every_s}")
    return max(1, int(round(every / step_s)))


def _check_priority(priority: Any) -> int:
    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise ServerError(f"priority must be a whole number 1..99 (SCHED_FIFO), or 0 for "
                          f"normal scheduling, got {priority!r}")
    return priority


def _check_cpu(cpu: Any) -> int | None:
    if cpu is None:
        return None
    if isinstance(cpu, bool) or not isinstance(cpu, int) or cpu < 0:
        raise ServerError(f"cpu must be a CPU number >= 0, got {cpu!r}")
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        allowed = list(range(os.cpu_count() or 1))
    if cpu not in allowed:
        raise ServerError(f"cpu {cpu}: not one of the CPUs this process may use "
                          f"({', '.join(map(str, allowed))})")
    return cpu


def _check_spin(spin_us: Any, priority: int, period_s: float) -> float:
    """The early wake-up before each deadline, busy-waited: hides the OS's
    wake-up latency from the tick. None: a default at real-time priority only
    (a normal thread would just burn the CPU others need)."""
    if spin_us is None:
        spin_us = min(DEFAULT_SPIN_US, 0.6 * period_s * 1e6) if priority > 0 else 0.0
    if not (0.0 <= float(spin_us) < 0.8 * period_s * 1e6):
        raise ServerError(f"spin {spin_us} us: must be at least 0 and under 80 % of the "
                          f"period ({0.8 * period_s * 1e6:.0f} us)")
    return float(spin_us)


def _check_pm_qos(pm_qos_us: Any, priority: int) -> tuple[int | None, str | None]:
    """(the PM QoS latency to request, None: none; why none is requested, None: one is).
    "auto" requests ``DEFAULT_PM_QOS_US`` at real-time priority, nothing else."""
    off_because = None if pm_qos_us is not None else "no request asked for"
    if pm_qos_us == "auto":
        pm_qos_us = DEFAULT_PM_QOS_US if priority > 0 else None
        if pm_qos_us is None:
            off_because = "normal scheduling (priority 0): no request"
    if pm_qos_us is not None and (isinstance(pm_qos_us, bool) or not isinstance(pm_qos_us, int)
                                  or not 0 <= pm_qos_us <= 1_000_000):
        raise ServerError(f"PM QoS latency must be a whole number of microseconds 0..1000000, "
                          f"got {pm_qos_us!r}")
    return pm_qos_us, off_because


def _check_xcp(xcp: Any, protocol: str, key: Any) -> tuple:
    """(address or None, protocol, key file or None) of the XCP slave asked for."""
    if xcp is None:
        if key is not None:
            raise ServerError("--xcp-key needs --xcp")
        return None, protocol, None
    from rt_loop.measure.xcp import parse_address
    from rt_loop.measure.xcp.protocol import read_secret

    try:
        address = parse_address(xcp) if isinstance(xcp, str) else (str(xcp[0]), int(xcp[1]))
    except (ValueError, TypeError, IndexError) as e:
        raise ServerError(_one_line(e)) from None
    _check_choice(protocol, XCP_PROTOCOLS, "XCP transport")
    if key is not None:
        try:
            read_secret(key)
        except (OSError, ValueError) as e:
            raise ServerError(f"--xcp-key {key}: {_one_line(e)}") from None
    return address, protocol, None if key is None else os.fspath(key)


def _check_driver(driver: Any) -> tuple[list, bool, list | None]:
    """(rows, linear, selector codes per row or None) of a driver table: a
    ScriptedDriver or rows (t_s, accel %, brake %[, selector P/R/N/D])."""
    if driver is None:
        return [], False, None
    from plant.driver import selector_code

    table = getattr(driver, "table", driver)
    linear = getattr(driver, "mode", "step") == "linear"
    selectors = getattr(driver, "selector_table", None)
    try:
        raw = [tuple(r) for r in table]
        if selectors is None and raw and all(len(r) == 4 for r in raw):
            selectors = [selector_code(r[3], f"driver table row {k + 1}") for k, r in enumerate(raw)]
            raw = [r[:3] for r in raw]
        rows = [(float(t), float(a), float(b)) for t, a, b in raw]
    except ValueError as e:
        if "selector" in str(e):
            raise ServerError(str(e)) from None
        raise ServerError("driver table: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                          "[, selector])") from None
    except TypeError:
        raise ServerError("driver table: rows must be (t_s, accel_pedal_pct, brake_pedal_pct"
                          "[, selector])") from None
    if selectors is not None:
        selectors = [float(x) for x in selectors]
    if not rows:
        raise ServerError("driver table: no rows")
    if len(rows) > MAX_DRIVER_ROWS:
        raise ServerError(f"driver table: {len(rows)} rows; the loop holds {MAX_DRIVER_ROWS}")
    for k, (t, a, b) in enumerate(rows):
        if not math.isfinite(t) or (k and not t > rows[k - 1][0]):
            raise ServerError(f"driver table row {k + 1}: times must be finite and increasing")
        if not (0 <= a <= 100 and 0 <= b <= 100):
            raise ServerError(f"driver table row {k + 1}: pedals must be within 0..100 %")
    return rows, linear, selectors


def _check_maneuver_inputs(inputs: Any) -> dict:
    """A maneuver's fixed plant inputs (``plant.maneuvers.FIXED_INPUTS``: the road grade)."""
    from plant.maneuvers import check_inputs

    try:
        return check_inputs(inputs, "maneuver inputs")
    except ValueError as e:
        raise ServerError(str(e)) from None


def _check_control_tcp(address: Any, token: Any, tls: Any) -> None:
    """The control channel's TCP settings: an address (host, port); a token
    needs it, as does TLS; beyond loopback only with a token."""
    import ssl

    from rt_loop import access

    if address is None:
        raise ServerError("a control token or TLS needs a TCP address (control_tcp)")
    if not (isinstance(address, tuple) and len(address) == 2 and isinstance(address[0], str)
            and isinstance(address[1], int) and 0 <= address[1] <= 65535):
        raise ServerError(f"control_tcp {address!r}: give (host, port)")
    if token is not None:
        access.check_token(token, "control token", ServerError)
    if tls is not None and not isinstance(tls, ssl.SSLContext):
        raise ServerError("control_tls: give an ssl.SSLContext (rt_loop.access."
                          "server_tls_context)")
    host, port = address
    if token is None and not access.is_loopback(host, access.resolve(host, port,
                                                                     "control address",
                                                                     ServerError)):
        raise ServerError(f"control on {host}:{port}: beyond loopback only with a token "
                          "(--control-token-file); without one bind 127.0.0.1")
