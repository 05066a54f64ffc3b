"""What the bench view shows, as plain data: pure functions of the loop's
figures (no Bokeh, no loop), so that each one is tested on its own.

- ``MinMaxMerger``: the scope's min/max buckets merged into display buckets
  (the min of the mins, the max of the maxes: a spike of one tick stays);
- ``histogram_view``: a 1 us histogram cut to where it has samples and
  coarsened to a number of bars a browser draws quickly;
- ``timing_table`` / ``timing_lines``: p50/p99/p99.9/max of turnaround,
  execution and wake-up latency, overruns, the latency against the period;
- ``message_info`` / ``bus_rows``: one row per CAN message: measured rate
  (frame count deltas) against its cycle time, accepted, rejected by reason,
  timeouts, timed out now;
- ``fault_spec`` / ``fault_rows``: the fault form's text as a spec, the set
  faults as table columns;
- ``instrument_items``: the instrument row.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any, NamedTuple

import numpy as np

__all__ = ["MessageInfo", "MinMaxMerger", "bus_rows", "fault_rows", "fault_spec",
           "histogram_view", "instrument_items", "message_info",
           "parse_value", "timing_lines", "timing_table"]

#: a measured rate this far off its cycle's is flagged
RATE_TOLERANCE = 0.25


# --------------------------------------------------------------------------
# traces
# --------------------------------------------------------------------------

class MinMaxMerger:
    """Merges the scope's buckets into display buckets of ``group_ticks`` ticks.

    ``feed(tick, time_s, mins, maxs)`` takes buckets in tick order (``tick``:
    the last tick of each bucket; ``mins``/``maxs``: {name: array}) and
    returns the display buckets now complete: {"t": plant time of each
    group's last bucket, "tick": its last tick, "min": {name: the min of the
    mins}, "max": {name: the max of the maxes}} (NaN where a name has no
    value in the whole group). A group is complete once a bucket of a later
    group arrived; the open group waits for the next feed. ``group_ticks`` 0
    or 1 passes the buckets through unmerged."""

    def __init__(self, group_ticks: int) -> None:
        self.group_ticks = max(1, int(group_ticks))
        self._held: tuple | None = None

    def reset(self) -> None:
        self._held = None

    @staticmethod
    def _empty(names: Any) -> dict:
        return {"t": np.empty(0), "tick": np.empty(0, dtype=np.int64),
                "min": {n: np.empty(0) for n in names}, "max": {n: np.empty(0) for n in names}}

    def feed(self, tick: Any, time_s: Any, mins: dict, maxs: dict) -> dict:
        names = list(mins)
        tick = np.asarray(tick, dtype=np.int64)
        time_s = np.asarray(time_s, dtype=float)
        lo = {n: np.asarray(mins[n], dtype=float) for n in names}
        hi = {n: np.asarray(maxs[n], dtype=float) for n in names}
        if self._held is not None:
            htick, htime, hlo, hhi = self._held
            if set(hlo) == set(names):
                tick = np.concatenate([htick, tick])
                time_s = np.concatenate([htime, time_s])
                lo = {n: np.concatenate([hlo[n], lo[n]]) for n in names}
                hi = {n: np.concatenate([hhi[n], hi[n]]) for n in names}
            self._held = None
        if len(tick) == 0:
            return self._empty(names)
        if self.group_ticks == 1:
            return {"t": time_s, "tick": tick, "min": lo, "max": hi}
        keys = (tick - 1) // self.group_ticks      # tick k closes its group when k % g == 0
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        last = starts[-1]                          # the open group: held for the next feed
        self._held = (tick[last:], time_s[last:], {n: lo[n][last:] for n in names},
                      {n: hi[n][last:] for n in names})
        starts = starts[:-1]
        if len(starts) == 0:
            return self._empty(names)
        ends = np.r_[starts[1:], last] - 1
        out_lo, out_hi = {}, {}
        with np.errstate(invalid="ignore"):
            for n in names:
                a, b = lo[n][:last], hi[n][:last]
                out_lo[n] = np.fmin.reduceat(a, starts)
                out_hi[n] = np.fmax.reduceat(b, starts)
        return {"t": time_s[ends], "tick": tick[ends], "min": out_lo, "max": out_hi}


# --------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------

def histogram_view(hist: Any, max_bars: int = 200, min_us: int = 20) -> dict:
    """Bars of a histogram of 1 us bins (bin i: [i, i+1) us; the last bin
    holds everything above): the bins up to the last one with samples (at
    least ``min_us``), grouped so that at most ``max_bars`` remain; only bars
    with samples are returned (for a log axis). {"left", "right", "count"}
    (us, us, samples), and "overflow": samples in the last bin."""
    h = np.asarray(hist, dtype=np.float64)
    n = len(h)
    nz = np.flatnonzero(h)
    if n == 0 or len(nz) == 0:
        return {"left": [], "right": [], "count": [], "overflow": 0}
    hi = max(int(nz[-1]) + 1, min(min_us, n))
    group = max(1, math.ceil(hi / max(1, max_bars)))
    hi = math.ceil(hi / group) * group
    padded = np.zeros(hi)
    padded[:min(hi, n)] = h[:min(hi, n)]
    counts = padded.reshape(-1, group).sum(axis=1)
    left = np.arange(len(counts)) * group
    keep = counts > 0
    return {"left": left[keep].astype(float).tolist(),
            "right": (left[keep] + group).astype(float).tolist(),
            "count": counts[keep].tolist(), "overflow": int(h[-1])}


_TIMES = (("turnaround", "turnaround"), ("execution", "execution"),
          ("wakeup_latency", "wake-up latency"))


def _us(x: Any) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.0f}"


def timing_table(timing: dict) -> dict:
    """Columns of the timing table: one row per time (turnaround, execution,
    wake-up latency), p50/p99/p99.9/max in us as ``StatsReader.timing`` gives
    them (None before the first tick shows as "-")."""
    cols: dict[str, list] = {"time": [], "p50": [], "p99": [], "p99_9": [], "max": [],
                             "samples": []}
    for key, label in _TIMES:
        t = timing.get(key) or {}
        cols["time"].append(label)
        cols["p50"].append(_us(t.get("p50_us")))
        cols["p99"].append(_us(t.get("p99_us")))
        cols["p99_9"].append(_us(t.get("p99_9_us")))
        mx = t.get("max_us")
        cols["max"].append("-" if mx is None else f"{mx:.1f}")
        cols["samples"].append(int(t.get("samples") or 0))
    return cols


def timing_lines(timing: dict, counts: dict, period_us: float, spin_us: float = 0.0) -> list[str]:
    """The lines beside the histograms: the period, overruns and skipped ticks,
    the wake-up latency maximum (less the early wake-up) against the period."""
    lines = [f"period {period_us:g} us"
             + (f", early wake-up {spin_us:g} us" if spin_us else "")]
    lines.append(f"overruns {int(counts.get('overruns', 0))}, skipped ticks "
                 f"{int(counts.get('skipped_ticks', 0))}, ticks {int(counts.get('ticks', 0))}")
    lat = (timing.get("wakeup_latency") or {}).get("max_us")
    if lat is None:
        lines.append("wake-up latency: no tick yet")
    else:
        late = max(0.0, float(lat) - float(spin_us))
        share = 100.0 * late / period_us if period_us > 0 else math.inf
        verdict = ("after the next deadline" if share >= 100 else
                   "over half the period" if share >= 50 else "within half the period")
        lines.append(f"wake-up latency max {float(lat):.1f} us"
                     + (f" ({late:.1f} us past the early wake-up)" if spin_us else "")
                     + f" = {share:.0f} % of the period: {verdict}")
    ta = (timing.get("turnaround") or {}).get("max_us")
    if ta is not None and period_us > 0:
        lines.append(f"turnaround max {float(ta):.1f} us = {100 * float(ta) / period_us:.0f} % "
                     "of the period")
    return lines


# --------------------------------------------------------------------------
# the bus
# --------------------------------------------------------------------------

class MessageInfo(NamedTuple):
    key: str            # the name in the counts (Message, or bus:Message on several buses)
    bus: str
    name: str
    direction: str      # "receive" (from the TCU) or "send" (the plant's)
    cycle_ms: float
    optional: bool


def message_info(channels: Any) -> list[MessageInfo]:
    """Every message the loop serves (``rt_loop.channels.LoopChannels``), in its numbering."""
    keys = channels.message_names()
    return [MessageInfo(keys[i], bus, m.name, m.direction, float(m.cycle_ms),
                        bool(getattr(m, "optional", False)))
            for i, (bus, m) in enumerate(channels.messages)]


_BUS_COLUMNS = ("message", "bus", "dir", "cycle_ms", "expected_hz", "rate_hz", "frames",
                "bad_length", "bad_crc", "bad_counter", "timeouts", "timed_out", "dropped",
                "state")


def bus_rows(info: list[MessageInfo], counts: dict, previous: dict | None, dt_s: float,
             time_scale: float = 1.0) -> tuple[dict, dict]:
    """(columns, frames) of the bus table: a row per message (received first).

    ``counts``: ``StatsReader.counts()``; ``previous``: the ``frames`` this
    function returned ``dt_s`` wall seconds earlier (None: no rate yet). The
    rate is the frame count's increase over ``dt_s``; the expected rate is
    1000 / cycle_ms, times ``time_scale`` (a slowed loop stretches the
    cycles). ``state``: TIMED OUT, none yet, rate low/high (beyond
    ``RATE_TOLERANCE``) or ok."""
    cols: dict[str, list] = {c: [] for c in _BUS_COLUMNS}
    frames: dict[str, int] = {}
    rx, tx = counts.get("tcu_messages", {}), counts.get("plant_messages", {})
    order = [m for m in info if m.direction == "receive"] + \
            [m for m in info if m.direction != "receive"]
    for m in order:
        receive = m.direction == "receive"
        c = (rx if receive else tx).get(m.key, {})
        n = int(c.get("accepted" if receive else "sent", 0))
        frames[m.key] = n
        expected = 1000.0 / m.cycle_ms * time_scale if m.cycle_ms > 0 else math.nan
        rate = math.nan
        if previous is not None and m.key in previous and dt_s > 0:
            rate = (n - previous[m.key]) / dt_s
        timed_out = bool(c.get("timed_out", False))
        if receive and timed_out:
            state = "TIMED OUT"
        elif n == 0:
            state = "optional, none yet" if m.optional else "none yet"
        elif math.isfinite(rate) and math.isfinite(expected) and expected > 0 and \
                abs(rate - expected) > RATE_TOLERANCE * expected:
            state = "rate low" if rate < expected else "rate high"
        else:
            state = "ok"
        cols["message"].append(m.name)
        cols["bus"].append(m.bus)
        cols["dir"].append("from TCU" if receive else "to TCU")
        cols["cycle_ms"].append(f"{m.cycle_ms:g}")
        cols["expected_hz"].append(f"{expected:.1f}" if math.isfinite(expected) else "")
        cols["rate_hz"].append(f"{rate:.1f}" if math.isfinite(rate) else "")
        cols["frames"].append(n)
        for key in ("bad_length", "bad_crc", "bad_counter", "timeouts"):
            cols[key].append(str(int(c.get(key, 0))) if receive else "")
        cols["timed_out"].append(("yes" if timed_out else "no") if receive else "")
        cols["dropped"].append("" if receive else str(int(c.get("dropped", 0))))
        cols["state"].append(state)
    return cols, frames


# --------------------------------------------------------------------------
# faults and inputs
# --------------------------------------------------------------------------

_PAIR = re.compile(r"\s*([A-Za-z_]\w*)\s*=(?!=)\s*(.*?)\s*(?=[;,]|\s+[A-Za-z_]\w*\s*=(?!=)|$)[;,]?")


def parse_value(text: str) -> Any:
    """A number when ``text`` reads as one (int when whole and written so), else the text."""
    t = text.strip()
    if re.fullmatch(r"[+-]?\d+", t):
        return int(t)
    try:
        x = float(t)
    except ValueError:
        return t
    return x if math.isfinite(x) else t


def fault_spec(kind: str, text: str) -> dict:
    """The fault form as a spec for ``rt_loop.faults``: ``text`` is either a
    JSON object (its ``kind``, if any, wins) or NAME=VALUE pairs separated by
    spaces, commas or semicolons (``message=VEH_Driver duration_s=2``,
    ``signal=DCT_Clutch.ClutchPressure2 when=gear == 3``: a value runs to the
    next NAME=). Numbers become numbers. Raises ValueError (one line) for
    text that is neither."""
    t = (text or "").strip()
    spec: dict[str, Any] = {"kind": kind}
    if not t:
        return spec
    if t.startswith("{"):
        try:
            given = json.loads(t)
        except ValueError as e:
            raise ValueError(f"fault spec: not a JSON object ({' '.join(str(e).split())})"
                             ) from None
        if not isinstance(given, dict):
            raise ValueError("fault spec: not a JSON object")
        spec.update(given)
        return spec
    pos = 0
    while pos < len(t):
        m = _PAIR.match(t, pos)
        if m is None or m.end() == pos:
            rest = t[pos:].strip().split()[0] if t[pos:].strip() else t[pos:]
            raise ValueError(f"fault parameters: {rest!r} is not NAME=VALUE (e.g. "
                             "message=VEH_Driver duration_s=2)")
        name, value = m.group(1), m.group(2)
        if not value:
            raise ValueError(f"fault parameters: {name}= has no value")
        spec[name] = value if name == "when" else parse_value(value)
        pos = m.end()
        while pos < len(t) and t[pos] in " \t;,":
            pos += 1
    return spec


def _time(x: Any) -> str:
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def fault_rows(status: list[dict]) -> dict:
    """Columns of the fault table from ``FaultManager.status()``."""
    cols: dict[str, list] = {"id": [], "kind": [], "target": [], "state": [], "started_s": [],
                             "ended_s": [], "activations": [], "hits": []}
    for f in status:
        cols["id"].append(int(f["id"]))
        cols["kind"].append(str(f["kind"]))
        cols["target"].append(str(f.get("target", "")))
        cols["state"].append(str(f.get("state", "")))
        cols["started_s"].append(_time(f.get("started_s")))
        cols["ended_s"].append(_time(f.get("ended_s")))
        cols["activations"].append(int(f.get("activations", 0)))
        cols["hits"].append(int(f.get("hits", 0)))
    return cols


# --------------------------------------------------------------------------
# the instrument row
# --------------------------------------------------------------------------

def _gear(g: Any) -> str:
    try:
        g = int(round(float(g)))
    except (TypeError, ValueError):
        return "-"
    return {0: "N", -1: "R"}.get(g, str(g))


def _choice(value: Any, choices: dict | None) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    k = int(round(float(value)))
    if choices and k in choices:
        return f"{choices[k]} ({k})"
    return str(k)


def instrument_items(v: dict) -> list[tuple[str, str, str]]:
    """(key, label, text) of each instrument from the values ``v``:
    vehicle_speed_kmh, gear, engine_speed_rpm, clutch1/2_pressure_bar,
    tcu_phase (a number, or None when the mapping has no TCU_Status.TcuPhase)
    with tcu_phase_choices, maneuver, maneuver_time_s, state, sim_time_s."""
    def num(key: str, fmt: str) -> str:
        x = v.get(key)
        return "-" if x is None or not math.isfinite(float(x)) else format(float(x) + 0.0, fmt)

    items = [
        ("speed", "vehicle speed", f"{num('vehicle_speed_kmh', '.1f')} km/h"),
        ("gear", "gear", _gear(v.get("gear"))),
        ("engine", "engine speed", f"{num('engine_speed_rpm', '.0f')} rpm"),
        ("k1", "clutch K1", f"{num('clutch1_pressure_bar', '.2f')} bar"),
        ("k2", "clutch K2", f"{num('clutch2_pressure_bar', '.2f')} bar"),
    ]
    if v.get("tcu_phase_known", True):
        items.append(("phase", "TCU phase", _choice(v.get("tcu_phase"),
                                                     v.get("tcu_phase_choices"))))
    else:
        items.append(("phase", "TCU phase", "not in the mapping"))
    mt = v.get("maneuver_time_s")
    maneuver = str(v.get("maneuver") or "none")
    if mt is not None and maneuver != "none":
        maneuver += f" {mt:.2f} s"
    if v.get("maneuver_name"):
        maneuver = f"{v['maneuver_name']}: {maneuver}"
    items.append(("maneuver", "maneuver", maneuver))
    loop = str(v.get("state", "?"))
    if v.get("sim_time_s") is not None:
        loop += f", t {float(v['sim_time_s']):.2f} s"
    items.append(("loop", "loop", loop))
    return items
