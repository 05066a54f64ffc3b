"""Recorded runs to fit the plant to: CSV, MF4, and a mapping for other names.

- CSV: a header of channel names, one row per sample, ``time_s`` first (what
  ``dct-hil simulate --out`` and ``dct-hil serve --record FILE.csv`` write); ``#``
  lines are comments.
- MF4 (asammdf): every channel by name, each on its own master time, resampled
  (linear) onto the time of the first channel used; ``dct-hil serve --record
  FILE.mf4`` writes the plant outputs under their own names.
- A mapping TOML names a car's signals as the plant's (``--mapping car.toml``)::

      [measurement]
      time = "Time"               # the time column of a CSV (default time_s); an MF4
                                  # channel's own master time is used

      [channels]                  # plant name = the file's channel, or a table with
      vehicle_speed_kmh = { name = "VehSpd", scale = 3.6 }   # value = scale x raw + offset
      accel_pedal_pct = "AccPedal"
      brake_pedal_pct = { name = "BrakePressure", scale = 2.0, offset = 0.0 }

Time starts at the first sample (0 s), or where the recording's ``maneuver_time_s``
(a plant server recording of a maneuver) is 0. ``load(path, mapping)`` returns a
``Measurement``; a missing file, channel or column is a one-line ``StudyError``
naming the file and the channels.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dct_hil.studies import StudyError

SUFFIXES = (".csv", ".mf4", ".mdf")


@dataclass
class ChannelMap:
    """plant name -> (file channel, scale, offset); ``time`` the CSV time column."""

    path: str | None = None
    time: str = "time_s"
    channels: dict = field(default_factory=dict)

    def source(self, name: str) -> tuple[str, float, float]:
        return self.channels.get(name, (name, 1.0, 0.0))


@dataclass
class Measurement:
    path: str
    time: np.ndarray                     # s, from 0
    channels: dict                       # plant name -> values (only the ones asked for)
    available: list                      # the file's channel names

    @property
    def duration_s(self) -> float:
        return float(self.time[-1])


def load_mapping(path: str | os.PathLike | None) -> ChannelMap:
    if path is None:
        return ChannelMap()
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise StudyError(f"--mapping {p}: cannot read: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise StudyError(f"--mapping {p}: not valid TOML: {e}") from None
    for k in raw:
        if k not in ("measurement", "channels"):
            raise StudyError(f"{p}: unknown table [{k}]; a mapping has [measurement] and "
                             "[channels]")
    meas = raw.get("measurement", {})
    if not isinstance(meas, dict) or set(meas) - {"time"}:
        raise StudyError(f"{p}: [measurement] takes time = \"<the time column>\"")
    cmap = ChannelMap(str(p), str(meas.get("time", "time_s")))
    chans = raw.get("channels", {})
    if not isinstance(chans, dict):
        raise StudyError(f"{p}: [channels] must be a table")
    for name, entry in chans.items():
        if isinstance(entry, str):
            cmap.channels[name] = (entry, 1.0, 0.0)
            continue
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) \
                or set(entry) - {"name", "scale", "offset"}:
            raise StudyError(f"{p}: [channels] {name}: give the file's channel name, or "
                             "{ name = \"...\", scale = 1.0, offset = 0.0 }")
        scale, offset = entry.get("scale", 1.0), entry.get("offset", 0.0)
        for what, x in (("scale", scale), ("offset", offset)):
            if not (isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)):
                raise StudyError(f"{p}: [channels] {name}: {what} must be a number")
        cmap.channels[name] = (entry["name"], float(scale), float(offset))
    return cmap


def load(path: str | os.PathLike, needed: list[str], optional: tuple = (),
         mapping: ChannelMap | None = None) -> Measurement:
    """Read ``needed`` (plant names; StudyError naming any missing) and whatever of
    ``optional`` the file has."""
    mapping = mapping or ChannelMap()
    p = Path(path)
    if not p.is_file():
        raise StudyError(f"{p}: no such measurement file")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        t, get, available = _csv(p, mapping)
    elif suffix in (".mf4", ".mdf"):
        t, get, available = _mdf(p, needed, mapping)
    else:
        raise StudyError(f"{p}: unknown measurement format {p.suffix!r}; give a .csv or .mf4 file")
    missing = [n for n in needed if mapping.source(n)[0] not in available]
    if missing:
        shown = ", ".join(f"{n} (channel {mapping.source(n)[0]!r})" if n in mapping.channels
                          else n for n in missing)
        have = ", ".join(available[:12]) + (", ..." if len(available) > 12 else "")
        hint = "" if mapping.path else "; name a car's signals with --mapping MAP.toml"
        raise StudyError(f"{p}: no channel {shown} (needed); the file has {len(available)} "
                         f"channels: {have}{hint}")
    channels = {}
    for n in list(needed) + [o for o in optional if o not in needed]:
        src, scale, offset = mapping.source(n)
        if src in available:
            channels[n] = get(src) * scale + offset
    keep = np.isfinite(t)
    if "maneuver_time_s" in available:
        mt = get("maneuver_time_s")
        started = np.isfinite(mt) & (mt >= 0)
        if started.any():
            keep &= started
            t = np.where(started, mt, t)
    for v in channels.values():
        keep &= np.isfinite(v)
    t = t[keep]
    if len(t) < 2:
        raise StudyError(f"{p}: fewer than 2 samples with finite values of "
                         f"{', '.join(channels) or 'the channels'}")
    order = np.argsort(t, kind="stable")
    t = t[order]
    if np.any(np.diff(t) <= 0):
        uniq = np.concatenate([[True], np.diff(t) > 0])
        order, t = order[uniq], t[uniq]
    channels = {n: v[keep][order] for n, v in channels.items()}
    return Measurement(str(p), t - t[0], channels, available)


def _csv(p: Path, mapping: ChannelMap):
    import pandas as pd

    try:
        df = pd.read_csv(p, comment="#", skipinitialspace=True)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise StudyError(f"{p}: cannot read as CSV: {' '.join(str(e).split())}") from None
    available = [str(c) for c in df.columns]
    if mapping.time not in df.columns:
        raise StudyError(f"{p}: no time column {mapping.time!r}; the file has "
                         f"{', '.join(available[:12])}{', ...' if len(available) > 12 else ''}"
                         + ("" if mapping.path else "; name it in a --mapping file's "
                                                    "[measurement] time"))

    def get(name):
        v = pd.to_numeric(df[name], errors="coerce").to_numpy(dtype=float)
        return v

    return get(mapping.time), get, available


def _mdf(p: Path, needed: list[str], mapping: ChannelMap):
    try:
        from asammdf import MDF
    except ImportError:
        raise StudyError(f"{p}: reading MF4 needs asammdf (pip install asammdf)") from None
    try:
        mdf = MDF(str(p))
    except Exception as e:  # asammdf raises many kinds
        raise StudyError(f"{p}: cannot read as MDF: {' '.join(str(e).split())}") from None
    available = sorted({name for name in mdf.channels_db if name and name != "time"})
    cache: dict = {}
    master: list = []

    def signal(name):
        if name not in cache:
            sig = mdf.get(name)
            cache[name] = (np.asarray(sig.timestamps, dtype=float),
                           np.asarray(sig.samples, dtype=float))
        return cache[name]

    first = next((mapping.source(n)[0] for n in needed if mapping.source(n)[0] in available),
                 None)
    if first is None:
        first = available[0] if available else None
    if first is None:
        raise StudyError(f"{p}: the MDF file has no channels")
    t0, _ = signal(first)
    master.append(t0)

    def get(name):
        t, v = signal(name)
        if len(t) == len(master[0]) and np.array_equal(t, master[0]):
            return v
        return np.interp(master[0], t, v, left=np.nan, right=np.nan)

    return master[0].copy(), get, available
