"""The A2L (ASAM MCD-2 MC, ASAP2 1.71) of the loop's memory, generated from the C structs.

An XCP address is a byte offset from the start of the ``rt_loop`` struct
(address extension 0: ``rt_loop/csrc/rt_loop.h``, "measurement, calibration
and stimulus"). Every address here is ``ffi.offsetof("rt_loop", ...)`` of its
field, taken at run time from the cffi ``ffi`` it is given (the compiled
module's), so the A2L always describes the structs as they are compiled;
nothing is hard-coded.

What it describes:

* MEASUREMENTs, one per field, nested structs and arrays flattened with
  readable names: ``inputs.*``, ``applied.*`` (the inputs as the last step
  limited and used them), ``outputs.*``, ``state.*`` (``state.clutch[0].twist_rad``),
  ``derived.*``, ``plant.*`` (the plant's own scalars), ``stats.*`` (timing,
  counters, plant and maneuver time; per channel ``stats.chan.<bus>.*`` and
  per message ``stats.msgs.<bus>.<Message>.*`` when the channels are known,
  ``stats.chan[k].*`` otherwise), ``commands.<name>`` (``stats.commands[k]``
  named by ``LoopChannels.command_names``), ``<bus>.<Message>.<Signal>`` (each
  CAN signal's last physical value, ``signal_values``) and ``loop.*`` (the
  configuration, the DAQ and write rings' counters).
* CHARACTERISTICs: every parameter of ``dct_params`` (``params.*``; a double
  array is one VAL_BLK), READ_ONLY unless ``plant/data/ranges.toml`` marks it
  ``online``, and ``override.<input>`` for the plant inputs a test may set
  while running (``OVERRIDABLE_INPUTS``; the inputs the TCU drives are
  overwritten by the loop every tick and stay measurements). The writable
  CHARACTERISTICs are exactly ``calibration_regions()``: the regions the loop
  accepts writes into (``rt_loop.regions``) and the XCP slave range-checks.
* the A2ML of its IF_DATA XCP (``rt_loop.measure.xcp.a2ml``), so a tool
  reads the XCP blocks by their description;
* MOD_PAR (EPK: ``epk()``; ADDR_EPK: ``protocol.EPK_ADDRESS``, where the
  slave answers the EPK as memory; the calibration MEMORY_SEGMENT with its
  XCP SEGMENT, its BUILD_CHECKSUM type and largest block, and its pages, as
  GET_SEGMENT_INFO and GET_PAGE_INFO answer),
  MOD_COMMON (BYTE_ORDER MSB_LAST, natural
  alignment), IF_DATA XCP: PROTOCOL_LAYER (the optional commands, master
  block mode with the slave's MAX_BS and MIN_ST), PAG (one segment, as
  GET_PAG_PROCESSOR_INFO), DAQ (DYNAMIC, MAX_DAQ from
  ``RT_DAQ_MAX_LISTS``, STIM, the events ``tick`` (DAQ and STIM: the slave's
  STIM event), ``10ms`` and ``100ms`` with their cycle times at the loop's
  rate) and the Ethernet transport layer (XCP_ON_UDP_IP and/or
  XCP_ON_TCP_IP, ``xcp``'s address and port).

Units come from the field names' suffixes (``plant.describe.SUFFIX_UNITS``,
plus compound SI suffixes such as ``_nm_per_rad`` or ``_rad_s``) and, for
signals, from the DBC; comments from the C headers' field comments and the
parameter file's trailing comments; the parameters' limits from
``plant/data/ranges.toml``, the signals' from the DBC.

``dct-hil a2l OUT.a2l [--mapping ...]``: ``add_arguments`` and ``run``.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import os
import re
import sys
from dataclasses import dataclass, field
from typing import Any

from can_dbc.options import add_matrix_options
from plant import __version__, argtypes
from plant.describe import RANGES as _RANGES
from plant.describe import header_comments as _header_comments
from plant.describe import online_keys, unit_of
from plant.describe import range_key as _range_key
from plant.describe import ranges as _ranges
from plant.describe import toml_comments as _toml_comments
from rt_loop.measure.xcp import a2ml
from rt_loop.measure.xcp.protocol import EPK_ADDRESS

__all__ = [
    "OVERRIDABLE_INPUTS",
    "XCP_DEFAULTS",
    "A2lObject",
    "add_arguments",
    "calibration_regions",
    "epk",
    "generate",
    "objects",
    "online_keys",
    "run",
]


#: plant inputs a test may set while running (writable CHARACTERISTICs
#: ``override.<name>``, regions of kind RT_REGION_DATA); the TCU-driven
#: inputs are written by the loop every tick
OVERRIDABLE_INPUTS = ("accel_pedal_pct", "brake_pedal_pct", "road_grade_pct", "engine_on")

#: what dct_plant_step limits each input to (apply_inputs in plant/csrc/plant.c);
#: the limits that are parameters are given at their ranges' widest
INPUT_LIMITS = {
    "accel_pedal_pct": (0.0, 100.0),
    "brake_pedal_pct": (0.0, 100.0),
    "solenoid_current1_a": (0.0, 10.0),
    "solenoid_current2_a": (0.0, 10.0),
    "line_solenoid_current_a": (0.0, 10.0),
    "clutch1_pressure_bar": (0.0, 100.0),
    "clutch2_pressure_bar": (0.0, 100.0),
    "fork_force1_n": (-20000.0, 20000.0),
    "fork_force2_n": (-20000.0, 20000.0),
    "fork_force3_n": (-20000.0, 20000.0),
    "fork_force4_n": (-20000.0, 20000.0),
    "road_grade_pct": (-40.0, 40.0),
    "engine_torque_request_nm": (-200.0, 1000.0),
    "torque_request_active": (0.0, 1.0),
    "engine_on": (0.0, 1.0),
}

#: the IF_DATA XCP settings; ``generate(xcp={...})`` overrides any of them. The
#: defaults are what the slave (rt_loop/measure/xcp/protocol.py) declares at CONNECT and
#: in its GET_*_INFO answers
XCP_DEFAULTS: dict[str, Any] = {
    "transport": "udp",            # "udp", "tcp" or "both"
    "address": "127.0.0.1",        # IPv4 address, IPv6 address or host name
    "port": 5555,
    "rate_hz": None,               # the loop's rate (None: the mapping's, else 2000)
    "time_scale": 1.0,             # wall-clock stretch of a slowed-down run (serve --time-scale)
    "protocol_version": 0x0104,
    "transport_version": 0x0104,
    "max_cto": 252,
    "max_dto": None,               # None: 4 (identification field) + RT_DAQ_ODT_BYTES
    "identification": "IDENTIFICATION_FIELD_TYPE_RELATIVE_WORD_ALIGNED",
    "overload": "OVERLOAD_INDICATION_EVENT",
    "timestamp_size": "SIZE_DWORD",
    "timestamp_unit": "UNIT_1US",
    "optional_cmds": (
        "GET_COMM_MODE_INFO", "GET_ID", "GET_SEED", "UNLOCK", "SET_MTA", "UPLOAD",
        "SHORT_UPLOAD", "BUILD_CHECKSUM", "DOWNLOAD", "DOWNLOAD_NEXT", "SHORT_DOWNLOAD",
        "MODIFY_BITS", "SET_CAL_PAGE", "GET_CAL_PAGE",
        "GET_PAG_PROCESSOR_INFO", "GET_SEGMENT_INFO", "COPY_CAL_PAGE", "CLEAR_DAQ_LIST",
        "SET_DAQ_PTR", "WRITE_DAQ", "WRITE_DAQ_MULTIPLE", "SET_DAQ_LIST_MODE",
        "GET_DAQ_LIST_MODE", "START_STOP_DAQ_LIST", "START_STOP_SYNCH", "GET_DAQ_CLOCK",
        "READ_DAQ", "GET_DAQ_PROCESSOR_INFO", "GET_DAQ_RESOLUTION_INFO", "GET_DAQ_LIST_INFO",
        "GET_DAQ_EVENT_INFO", "FREE_DAQ", "ALLOC_DAQ", "ALLOC_ODT", "ALLOC_ODT_ENTRY",
        "TIME_CORRELATION_PROPERTIES",
    ),
    "optional_level1_cmds": ("GET_VERSION",),
}

# rt_loop.h's values, for a compiled module whose cdef lags behind the header
# (tests/test_a2l.py checks them against the header)
_FALLBACK = {
    "RT_REGION_DATA": 0,
    "RT_REGION_PARAM": 1,
    "RT_DAQ_MAX_LISTS": 32,
    "RT_DAQ_ODT_BYTES": 248,
    "RT_EVENT_TICK": 0,
    "RT_EVENT_10MS": 1,
    "RT_EVENT_100MS": 2,
    "RT_MAX_SIGNAL_VALUES": 4096,
    "RT_MAX_COMMANDS": 32,
    "RT_MAX_CHANNELS": 4,
}

#: the DAQ events: (name, RT_EVENT_* constant, plant time between two, 0: every tick)
_EVENTS = (("tick", "RT_EVENT_TICK", 0.0), ("10ms", "RT_EVENT_10MS", 0.010),
           ("100ms", "RT_EVENT_100MS", 0.100))

# rt_msg_stats fields that do not apply to a sent / a received message
_SENT_SKIP = frozenset({"bad_length", "bad_crc", "bad_counter", "timeouts", "timed_out", "reserved"})
_RECEIVED_SKIP = frozenset({"dropped", "saturated", "reserved"})

_WIDE = 1e12                       # limits of a double without a better bound
_UNIT_LIMITS = {"rpm": 30000.0, "km/h": 600.0, "%": 1000.0, "bar": 1000.0, "A": 100.0}
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\[\]]*$")
_MAX_LONG_ID = 255


def _const(lib: Any, name: str) -> int:
    return int(getattr(lib, name, _FALLBACK[name]))


# ---------------------------------------------------------------------------
# the objects
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class A2lObject:
    """One MEASUREMENT or CHARACTERISTIC.

    ``path``: the ``ffi.offsetof("rt_loop", *path)`` arguments of its field
    (``address`` is that offset); ``c_type``: the cffi name of its (element)
    type; ``size``: bytes (a whole block for a VAL_BLK); ``dims``: () for a
    single value, (n,) or (rows, columns) for a VAL_BLK; ``writable``: a
    CHARACTERISTIC the loop accepts writes into, with ``region_kind``
    (RT_REGION_DATA or RT_REGION_PARAM) and the range ``lower``..``upper``
    each value written must lie in."""
    name: str
    kind: str                            # "MEASUREMENT" or "CHARACTERISTIC"
    path: tuple
    address: int
    c_type: str
    datatype: str                        # A2L data type: FLOAT64_IEEE, ULONG, ...
    size: int
    dims: tuple = ()
    unit: str = ""
    lower: float = -_WIDE
    upper: float = _WIDE
    comment: str = ""
    writable: bool = False
    region_kind: int | None = None
    vtab: tuple = ()                     # ((value, text), ...): a verbal conversion
    group: str = ""
    extra: dict = field(default_factory=dict, compare=False, repr=False)


def _datatype(ffi: Any, ctype: Any) -> str | None:
    """The A2L data type of a cffi primitive type (None: not a number)."""
    if ctype.kind != "primitive":
        return None
    if ctype.cname == "double":
        return "FLOAT64_IEEE"
    if ctype.cname == "float":
        return "FLOAT32_IEEE"
    if ctype.cname in ("char", "_Bool", "bool") or "char16" in ctype.cname or "wchar" in ctype.cname:
        return None
    try:
        signed = int(ffi.cast(ctype, -1)) < 0
    except (TypeError, ValueError):
        return None
    size = ffi.sizeof(ctype)
    names = {1: ("SBYTE", "UBYTE"), 2: ("SWORD", "UWORD"), 4: ("SLONG", "ULONG"),
             8: ("A_INT64", "A_UINT64")}
    if size not in names:
        return None
    return names[size][0 if signed else 1]


def _type_limits(datatype: str) -> tuple[float, float]:
    bits = {"SBYTE": 8, "UBYTE": 8, "SWORD": 16, "UWORD": 16, "SLONG": 32, "ULONG": 32,
            "A_INT64": 64, "A_UINT64": 64}.get(datatype)
    if bits is None:
        return -_WIDE, _WIDE
    if datatype.startswith(("S", "A_INT")):
        return -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    return 0, 2 ** bits - 1


# -- units ------------------------------------------------------------------

def _unit_limits(unit: str, datatype: str) -> tuple[float, float]:
    if datatype not in ("FLOAT64_IEEE", "FLOAT32_IEEE"):
        return _type_limits(datatype)
    if unit in _UNIT_LIMITS:
        return -_UNIT_LIMITS[unit], _UNIT_LIMITS[unit]
    return -_WIDE, _WIDE


# -- comments ---------------------------------------------------------------

def _text(*parts: str) -> str:
    """A long identifier: the parts joined, one line, no double quotes, at most 255 characters."""
    text = "; ".join(p.strip() for p in parts if p and p.strip())
    text = " ".join(text.replace('"', "'").replace("\\", "/").split())
    text = text.encode("ascii", "replace").decode("ascii")
    return text if len(text) <= _MAX_LONG_ID else text[:_MAX_LONG_ID - 3] + "..."


# -- the ranges file and its online marker ----------------------------------

# -- walking the cffi types --------------------------------------------------

def _leaves(ffi: Any, ctype: Any, path: tuple, name: str, blocks: bool = False):
    """(path, name, primitive ctype, dims, parent struct cname, field name) of
    every number below ``ctype``; with ``blocks`` a double array (1-D or 2-D)
    is one leaf with its dims, else every element is one."""
    if ctype.kind == "struct":
        for fname, f in ctype.fields:
            yield from _walk_field(ffi, f.type, path + (fname,), f"{name}.{fname}" if name else fname,
                                   blocks, ctype.cname, fname)
        return
    yield from _walk_field(ffi, ctype, path, name, blocks, "", "")


def _walk_field(ffi, ctype, path, name, blocks, parent, fname):
    if ctype.kind == "struct":
        yield from _leaves(ffi, ctype, path, name, blocks)
    elif ctype.kind == "array":
        item = ctype.item
        if blocks and item.kind == "primitive" and _datatype(ffi, item):
            yield path, name, item, (ctype.length,), parent, fname
        elif (blocks and item.kind == "array" and item.item.kind == "primitive"
              and _datatype(ffi, item.item)):
            yield path, name, item.item, (ctype.length, item.length), parent, fname
        else:
            for i in range(ctype.length):
                yield from _walk_field(ffi, item, path + (i,), f"{name}[{i}]", blocks, parent, fname)
    elif ctype.kind == "primitive" and _datatype(ffi, ctype):
        yield path, name, ctype, (), parent, fname


def _has(ffi: Any, cname: str, *path) -> bool:
    try:
        ffi.offsetof(cname, *path)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError):
        return False
    return True


def _vtab(lib: Any, prefix: str) -> tuple:
    """((value, name without the prefix), ...) of the integer constants named ``prefix*``."""
    return tuple(sorted((int(getattr(lib, n)), n[len(prefix):])
                        for n in dir(lib)
                        if n.startswith(prefix) and isinstance(getattr(lib, n), int)))


class _Builder:
    def __init__(self, ffi, lib, channels, params_doc):
        self.ffi, self.lib, self.channels = ffi, lib, channels
        self.out: list[A2lObject] = []
        self.names: set[str] = set()
        self.c_comments = _header_comments()
        if params_doc is None:
            from plant.params import DEFAULT_PARAMS

            params_doc = DEFAULT_PARAMS
        self.p_comments = (dict(params_doc) if isinstance(params_doc, dict)
                           else _toml_comments(params_doc))
        self.ranges = _ranges()
        self.online = online_keys()
        self.vtabs = {
            ("rt_stats", "state"): _vtab(lib, "RT_STATE_"),
            ("rt_stats", "startup_phase"): _vtab(lib, "RT_START_"),
            ("rt_stats", "maneuver_state"): _vtab(lib, "RT_MANEUVER_"),
            ("dct_sync_state", "phase"): _vtab(lib, "DCT_SYNC_"),
        }
        sync = self.vtabs[("dct_sync_state", "phase")]
        for k in range(1, 5):
            self.vtabs[("dct_outputs", f"sync{k}_state")] = sync

    def offset(self, *path) -> int:
        return int(self.ffi.offsetof("rt_loop", *path))

    def add(self, **kw) -> None:
        name = kw["name"]
        if not _IDENT.match(name):
            raise ValueError(f"A2L name {name!r}: not an ASAP2 identifier")
        if name in self.names:
            raise ValueError(f"A2L name {name!r} is given twice (a bus, message or command "
                             "named like a field of the loop?)")
        self.names.add(name)
        kw["comment"] = _text(kw.get("comment", ""))
        self.out.append(A2lObject(**kw))

    def measurements(self, path: tuple, prefix: str, group: str, *, skip=(), limits=None,
                     comment_of=None, comment_base: str = "") -> None:
        """One MEASUREMENT per number below the field at ``path``."""
        ffi = self.ffi
        ctype = ffi.typeof("rt_loop")
        for item in path:
            ctype = ctype.item if isinstance(item, int) else dict(ctype.fields)[item].type
        for leaf_path, name, ptype, _dims, parent, fname in _leaves(ffi, ctype, (), ""):
            if leaf_path and leaf_path[0] in skip:
                continue
            full = f"{prefix}.{name}" if name else prefix
            datatype = _datatype(ffi, ptype)
            unit = unit_of(fname or name or prefix.rsplit(".", 1)[-1])
            lo, hi = (limits or {}).get(fname) or _unit_limits(unit, datatype)
            vtab = self.vtabs.get((parent, fname), ())
            if vtab:
                unit, lo, hi = "", min(v for v, _ in vtab), max(v for v, _ in vtab)
            if comment_of:
                comment = comment_of(leaf_path, name)
            else:
                comment = _text(comment_base, self.c_comments.get((parent, fname), ""))
            self.add(name=full, kind="MEASUREMENT", path=path + leaf_path,
                     address=self.offset(*(path + leaf_path)), c_type=ptype.cname,
                     datatype=datatype, size=ffi.sizeof(ptype), unit=unit, lower=lo, upper=hi,
                     comment=comment, vtab=vtab, group=group)

    # -- the parts ----------------------------------------------------------

    def plant(self) -> None:
        ffi, lib = self.ffi, self.lib
        data = _const(lib, "RT_REGION_DATA")
        for fname, _f in ffi.typeof("dct_inputs").fields:
            if fname not in OVERRIDABLE_INPUTS:
                continue
            path = ("plant", "inputs", fname)
            lo, hi = INPUT_LIMITS[fname]
            self.add(name=f"override.{fname}", kind="CHARACTERISTIC", path=path,
                     address=self.offset(*path), c_type="double", datatype="FLOAT64_IEEE",
                     size=8, unit=unit_of(fname), lower=lo, upper=hi, writable=True,
                     region_kind=data, group="override",
                     comment=f"plant input {fname} set by the test: written at a tick "
                             f"boundary, used by the next step (measured as inputs.{fname})")
        for part in ("inputs", "applied"):
            what = "as given" if part == "inputs" else "as limited and used by the last step"
            self.measurements(("plant", part), part, part, limits=INPUT_LIMITS,
                              comment_of=lambda p, n, w=what: _text(
                                  f"plant input {n} {w}",
                                  self.c_comments.get(("dct_inputs", n), "")))
        for part, what in (("outputs", "plant output, after the last step"),
                           ("state", "plant state"),
                           ("derived", "derived from the parameters (dct_plant_prepare)")):
            self.measurements(("plant", part), part, part, comment_base=what)
        for fname, f in ffi.typeof("dct_plant").fields:
            if f.type.kind == "primitive":
                self.measurements(("plant", fname), f"plant.{fname}", "plant",
                                  comment_of=lambda p, n, fn=fname: self.c_comments.get(
                                      ("dct_plant", fn), ""))

    def params(self) -> None:
        ffi, lib = self.ffi, self.lib
        param = _const(lib, "RT_REGION_PARAM")
        for leaf_path, name, ptype, dims, parent, fname in _leaves(
                ffi, ffi.typeof("dct_params"), (), "", blocks=True):
            path = ("plant", "params") + leaf_path
            key = _range_key(leaf_path)
            if key not in self.ranges:
                raise ValueError(f"{_RANGES}: no range for {key} (a field of dct_params)")
            lo, hi = self.ranges[key]
            datatype = _datatype(ffi, ptype)
            count = fname == "n" or (fname.startswith("n_") and datatype not in
                                     ("FLOAT64_IEEE", "FLOAT32_IEEE"))
            unit = "" if count else unit_of(fname)
            online = key in self.online and not count
            n = 1
            for d in dims:
                n *= d
            doc = self.p_comments.get(name, "")
            layout = ""
            if len(dims) == 2:
                layout = f"C [{dims[0]}][{dims[1]}], row by row: MATRIX_DIM columns rows"
            self.add(name=f"params.{name}", kind="CHARACTERISTIC", path=path,
                     address=self.offset(*path), c_type=ptype.cname, datatype=datatype,
                     size=n * ffi.sizeof(ptype), dims=dims, unit=unit, lower=lo, upper=hi,
                     writable=online, region_kind=param if online else None, group="params",
                     comment=_text("changeable while running" if online else
                                   "read only while running (ranges.toml: not online)",
                                   layout, self.c_comments.get((parent, fname), ""), doc))

    def stats(self) -> None:
        ffi, lib, ch = self.ffi, self.lib, self.channels
        skip = {"seq", "chan", "msgs", "commands", "outputs"}
        skip |= {n for n, f in ffi.typeof("rt_stats").fields if f.type.kind == "array"}
        self.measurements(("stats",), "stats", "stats", skip=skip)
        n_chan = _const(lib, "RT_MAX_CHANNELS")
        buses = list(ch.buses) if ch is not None else [None] * n_chan
        for k, bus in enumerate(buses):
            name = f"stats.chan.{bus}" if bus else f"stats.chan[{k}]"
            self.measurements(("stats", "chan", k), name, "stats",
                              comment_of=lambda p, n, b=bus or f"channel {k}": _text(
                                  f"{b}: {n}", self.c_comments.get(("rt_chan_stats", n), "")))
        if ch is not None:
            for k, (bus, msg) in enumerate(ch.messages):
                sent = msg.direction == "send"
                direction = "sent" if sent else "received"
                self.measurements(
                    ("stats", "msgs", k), f"stats.msgs.{bus}.{msg.name}", "stats",
                    skip=_SENT_SKIP if sent else _RECEIVED_SKIP,
                    comment_of=lambda p, n, b=bus, m=msg, d=direction: _text(
                        f"{b} {m.name} (0x{m.frame_id:X}, {d}): {n}",
                        self.c_comments.get(("rt_msg_stats", n), "")))
        n_cmd = _const(lib, "RT_MAX_COMMANDS")
        if ch is not None:
            names = list(ch.command_names)
            inputs = list(getattr(ch, "command_inputs", [None] * len(names)))
        else:
            names, inputs = [None] * n_cmd, [None] * n_cmd
        seen: set[str] = set()
        for k, cname in enumerate(names):
            path = ("stats", "commands", k)
            if cname is None:
                name, unit = f"stats.commands[{k}]", ""
                comment = f"command value {k} as applied this tick (named by the mapping)"
            else:
                name = f"commands.{cname}" if cname not in seen else f"commands.{cname}[{k}]"
                seen.add(cname)
                drives = (f"drives plant input {inputs[k]}" if inputs[k] is not None
                          else "recorded only")
                comment = f"received value {cname} as applied this tick ({drives})"
                unit = unit_of(cname)
            if cname is None:
                lo, hi = -_WIDE, _WIDE
            elif inputs[k] is not None:
                lo, hi = INPUT_LIMITS.get(inputs[k]) or _unit_limits(unit, "FLOAT64_IEEE")
            else:
                lo, hi = _unit_limits(unit, "FLOAT64_IEEE")
            self.add(name=name, kind="MEASUREMENT", path=path, address=self.offset(*path),
                     c_type="double", datatype="FLOAT64_IEEE", size=8, unit=unit,
                     lower=lo, upper=hi, comment=comment, group="commands")

    def loop(self) -> None:
        ffi = self.ffi
        self.measurements(("cfg",), "loop.cfg", "loop")
        fields = dict(ffi.typeof("rt_loop").fields)
        if "driver" in fields:
            self.measurements(("driver",), "loop.driver", "loop",
                              skip={n for n, f in ffi.typeof("rt_driver").fields
                                    if f.type.kind == "array"})
        for fname in ("stop_request", "n_channels", "n_commands", "n_regions", "daq_gen",
                      "daq_ack", "daq_refused", "n_signal_values"):
            if fname in fields and fields[fname].type.kind == "primitive":
                self.measurements((fname,), f"loop.{fname}", "loop",
                                  comment_of=lambda p, n, fn=fname: self.c_comments.get(
                                      ("rt_loop", fn), ""))
        for ring in ("rec", "log", "daq_ring"):
            if ring in fields and _has(ffi, "rt_loop", ring, "dropped"):
                self.measurements((ring, "dropped"), f"loop.{ring}.dropped", "loop",
                                  comment_of=lambda p, n, r=ring: f"{r}: entries lost (full)")
        for ring in ("cal", "stim"):
            if ring not in fields:
                continue
            for fname in ("dropped", "applied", "refused", "last_applied_id", "last_refused_id"):
                if _has(ffi, "rt_loop", ring, fname):
                    self.measurements((ring, fname), f"loop.{ring}.{fname}", "loop",
                                      comment_of=lambda p, n, r=ring, fn=fname: _text(
                                          f"{r} writes", self.c_comments.get(("rt_write_ring", fn), "")))

    def signals(self) -> None:
        ffi, lib, ch = self.ffi, self.lib, self.channels
        if ch is None or not _has(ffi, "rt_loop", "signal_values", 0):
            return
        limit = _const(lib, "RT_MAX_SIGNAL_VALUES")
        mapped = {}
        for bus, msg in ch.messages:
            mapped[(bus, msg.name)] = msg
        base = 0
        for i, bus in enumerate(ch.buses):
            table = ch.table(i)
            for m in range(len(table)):
                cmsg = table.messages[m]
                msg = mapped.get((bus, cmsg.name))
                by_name = {s.name: s for s in cmsg.signals}
                for k, sname in enumerate(table.signal_names(m)):
                    index = base + k
                    if index >= limit:
                        raise ValueError(f"{index + 1} CAN signals: the loop keeps at most "
                                         f"{limit} (RT_MAX_SIGNAL_VALUES)")
                    sig = by_name[sname]
                    self.add(**_signal_object(self, bus, cmsg, msg, sig, index))
                base += len(table.signal_names(m))

    def build(self) -> list[A2lObject]:
        self.plant()
        self.params()
        self.stats()
        self.loop()
        self.signals()
        return self.out


def _signal_object(b: _Builder, bus: str, cmsg: Any, msg: Any, sig: Any, index: int) -> dict:
    path = ("signal_values", index)
    scale = float(getattr(sig, "scale", 1.0) or 1.0)
    offset = float(getattr(sig, "offset", 0.0) or 0.0)
    lo, hi = getattr(sig, "minimum", None), getattr(sig, "maximum", None)
    if lo is None or hi is None:
        length = int(getattr(sig, "length", 64))
        if getattr(sig, "is_float", False):
            raw_lo, raw_hi = -_WIDE, _WIDE
        elif getattr(sig, "is_signed", False):
            raw_lo, raw_hi = -(2 ** (length - 1)), 2 ** (length - 1) - 1
        else:
            raw_lo, raw_hi = 0, 2 ** length - 1
        a, c = raw_lo * scale + offset, raw_hi * scale + offset
        lo = min(a, c) if lo is None else lo
        hi = max(a, c) if hi is None else hi
    lo, hi = max(float(lo), -_WIDE), min(float(hi), _WIDE)
    if not lo <= hi:
        lo, hi = hi, lo
    vtab = ()
    choices = getattr(sig, "choices", None) or {}
    if choices:
        vtab = tuple(sorted((int(v) * scale + offset, _text(str(t)) or str(v))
                            for v, t in choices.items()))
    role = ""
    if msg is not None:
        ms = next((s for s in msg.signals if s.name == sig.name), None)
        if ms is not None and ms.source is not None and ms.source.name:
            role = f"from {ms.source.kind} {ms.source.name}"
        elif ms is not None and ms.target is not None:
            role = f"drives {ms.target.kind} {ms.target.name}"
        elif ms is not None and ms.protection_field:
            role = f"protection: {ms.protection_field}"
        direction = "sent by the plant" if msg.direction == "send" else "received"
    else:
        direction = ""
    unit = (getattr(sig, "unit", None) or "").strip()
    return dict(name=f"{bus}.{cmsg.name}.{sig.name}", kind="MEASUREMENT", path=path,
                address=b.offset(*path), c_type="double", datatype="FLOAT64_IEEE", size=8,
                unit=unit, lower=lo, upper=hi, vtab=vtab, group=bus,
                comment=_text(f"{bus} {cmsg.name} (0x{cmsg.frame_id:X}) {direction}".strip(),
                              role, getattr(sig, "comment", None) or ""),
                extra={"bus": bus, "message": cmsg.name, "signal": sig.name, "index": index})


def objects(ffi: Any, lib: Any, *, channels: Any = None, params_doc: Any = None) -> list[A2lObject]:
    """Every MEASUREMENT and CHARACTERISTIC of the A2L (see the module's text).

    ``channels``: a ``rt_loop.channels.LoopChannels`` (names the commands, the
    channels, the messages and the signal values); ``params_doc``: the
    parameter TOML whose trailing comments describe the parameters (default:
    ``plant.params.DEFAULT_PARAMS``), or a dict of dotted key -> text."""
    return _Builder(ffi, lib, channels, params_doc).build()


def calibration_regions(ffi: Any, lib: Any) -> list[tuple]:
    """The writable CHARACTERISTICs as the loop's and the XCP slave's regions:
    ``(offset, size, kind, name, lo, hi, c_type)``, offset and size in bytes
    within the rt_loop, kind RT_REGION_DATA (plant inputs) or RT_REGION_PARAM
    (parameters: the loop calls dct_plant_prepare after a write), every value
    written must lie in lo..hi (c_type: the cffi name of each value's type; a
    block holds size / sizeof(c_type) of them)."""
    return [(o.address, o.size, o.region_kind, o.name, o.lower, o.upper, o.c_type)
            for o in objects(ffi, lib) if o.writable]


def epk(ffi: Any, lib: Any, *, channels: Any = None, objs: list | None = None) -> str:
    """The A2L's ident (MOD_PAR EPK): the project's version and a hash of the
    layout it describes (size of the rt_loop, every object's name, address,
    type and size), so a stale A2L can be told from a matching one."""
    objs = objs if objs is not None else objects(ffi, lib, channels=channels)
    h = hashlib.sha256(f"rt_loop {ffi.sizeof('rt_loop')}\n".encode())
    for o in objs:
        h.update(f"{o.kind} {o.name} {o.address} {o.datatype} {o.size} {o.writable}\n".encode())
    return f"dct-hil {__version__} {h.hexdigest()[:16]}"


# ---------------------------------------------------------------------------
# the text
# ---------------------------------------------------------------------------

def _num(x: float) -> str:
    if isinstance(x, int) or (float(x).is_integer() and abs(x) < 1e16):
        return str(int(x))
    return repr(float(x))


def _slug(unit: str) -> str:
    s = unit.replace("%", "pct").replace("/", "_per_")
    s = re.sub(r"[^A-Za-z0-9]+", "_", s).strip("_")
    return s or "none"


def _time_code(seconds: float) -> tuple[int, int]:
    """XCP EVENT TIME_CYCLE and TIME_UNIT of a cycle time, as the slave's
    GET_DAQ_EVENT_INFO codes it (one rule: rt_loop.measure.xcp.protocol.event_cycle)."""
    from rt_loop.measure.xcp.protocol import event_cycle

    return event_cycle(seconds)


def _xcp_settings(xcp: dict | None, channels: Any, lib: Any) -> dict:
    cfg = dict(XCP_DEFAULTS)
    for key, value in (xcp or {}).items():
        if key not in XCP_DEFAULTS:
            raise ValueError(f"xcp: unknown setting {key!r} (known: {', '.join(XCP_DEFAULTS)})")
        if value is not None:
            cfg[key] = value
    if cfg["transport"] not in ("udp", "tcp", "both"):
        raise ValueError(f"xcp: transport must be udp, tcp or both, got {cfg['transport']!r}")
    port = cfg["port"]
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f"xcp: port must be 1..65535, got {port!r}")
    address = str(cfg["address"])
    if not address or '"' in address or any(c.isspace() for c in address):
        raise ValueError(f"xcp: bad address {address!r}")
    rate = cfg["rate_hz"]
    if rate is None:
        rate = float(getattr(getattr(channels, "mapping", None), "rate_hz", 0.0) or 2000.0)
    if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise ValueError(f"xcp: rate_hz must be a positive number, got {rate!r}")
    cfg["rate_hz"] = float(rate)
    scale = cfg["time_scale"]
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and 0 < scale <= 1):
        raise ValueError(f"xcp: time_scale must be above 0 and at most 1, got {scale!r}")
    if cfg["max_dto"] is None:
        cfg["max_dto"] = _const(lib, "RT_DAQ_ODT_BYTES") + 4
    return cfg


def _if_data(cfg: dict, lib: Any, calibration: bool) -> list[str]:
    from rt_loop.measure.xcp import STIM_EVENTS, protocol

    step = 1.0 / cfg["rate_hz"]                  # plant time per tick
    period = step / cfg["time_scale"]            # wall-clock time per tick
    max_daq = _const(lib, "RT_DAQ_MAX_LISTS")
    odt_entry = min(255, _const(lib, "RT_DAQ_ODT_BYTES"))
    lines = ["/begin IF_DATA XCP",
             "  /begin PROTOCOL_LAYER",
             f"    0x{cfg['protocol_version']:04X} 1000 2000 0 0 0 0 0 {cfg['max_cto']} "
             f"{cfg['max_dto']} BYTE_ORDER_MSB_LAST ADDRESS_GRANULARITY_BYTE"]
    lines += [f"    OPTIONAL_CMD {c}" for c in cfg["optional_cmds"]]
    lines += [f"    OPTIONAL_LEVEL1_CMD {c}" for c in cfg["optional_level1_cmds"]]
    lines += [f"    COMMUNICATION_MODE_SUPPORTED BLOCK MASTER {protocol.MAX_BS} {protocol.MIN_ST}",
              "  /end PROTOCOL_LAYER",
              f"  /begin PAG {1 if calibration else 0} /end PAG",
              "  /begin DAQ",
              f"    DYNAMIC {max_daq} {len(_EVENTS)} 0 OPTIMISATION_TYPE_DEFAULT "
              f"ADDRESS_EXTENSION_FREE {cfg['identification']} "
              f"GRANULARITY_ODT_ENTRY_SIZE_DAQ_BYTE {odt_entry} {cfg['overload']} "
              "PRESCALER_SUPPORTED",
              f"    /begin STIM GRANULARITY_ODT_ENTRY_SIZE_STIM_BYTE {odt_entry} /end STIM",
              f"    /begin TIMESTAMP_SUPPORTED 0x1 {cfg['timestamp_size']} "
              f"{cfg['timestamp_unit']} /end TIMESTAMP_SUPPORTED"]
    for name, const, every_s in _EVENTS:
        channel = _const(lib, const)
        if every_s <= 0.0:
            cycle_s = period
        else:
            ticks = every_s / step               # as rt_loop.c: whole ticks, at least 1
            cycle_s = (1 if ticks < 1.5 else round(ticks)) * period
        tc, tu = _time_code(cycle_s)
        direction = "DAQ_STIM" if channel in STIM_EVENTS else "DAQ"
        # any number of lists per event (0xFF), priority 0, consistency per event
        lines.append(f'    /begin EVENT "{name}" "{name[:8]}" {channel} {direction} 0xFF {tc} {tu} 0 '
                     "CONSISTENCY EVENT /end EVENT")
    lines.append("  /end DAQ")
    address = cfg["address"]
    if ":" in address:
        where = f'IPV6 "{address}"'
    elif re.fullmatch(r"\d{1,3}(\.\d{1,3}){3}", address):
        where = f'ADDRESS "{address}"'
    else:
        where = f'HOST_NAME "{address}"'
    for tl in (("UDP", "TCP") if cfg["transport"] == "both" else (cfg["transport"].upper(),)):
        lines.append(f"  /begin XCP_ON_{tl}_IP 0x{cfg['transport_version']:04X} {cfg['port']} "
                     f"{where} /end XCP_ON_{tl}_IP")
    lines.append("/end IF_DATA")
    return lines


def _memory_segment(objs: list[A2lObject]) -> list[str]:
    """The calibration segment as the slave declares it (GET_SEGMENT_INFO,
    GET_PAGE_INFO): segment 0 from the first writable region to the end of
    the last, two pages: 0 the working page (the loop's memory), 1 the
    reference page (read only)."""
    from rt_loop.measure.xcp import protocol

    spans = [(o.address, o.address + o.size) for o in objs if o.writable]
    if not spans:
        return []
    checksum_type = {0x09: "XCP_CRC_32"}[protocol.CHECKSUM_TYPE]
    max_block = protocol.MAX_CHECKSUM_BLOCK
    start, end = min(a for a, _ in spans), max(b for _, b in spans)
    return [f'/begin MEMORY_SEGMENT calibration "the writable regions\' span (XCP segment 0)" '
            f"DATA RAM INTERN 0x{start:X} 0x{end - start:X} -1 -1 -1 -1 -1",
            "  /begin IF_DATA XCP",
            "    /begin SEGMENT 0 2 0 0 0",
            f"      /begin CHECKSUM {checksum_type} MAX_BLOCK_SIZE 0x{max_block:X} /end CHECKSUM",
            "      /begin PAGE 0 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE "
            "XCP_WRITE_ACCESS_DONT_CARE INIT_SEGMENT 0 /end PAGE",
            "      /begin PAGE 1 ECU_ACCESS_DONT_CARE XCP_READ_ACCESS_DONT_CARE "
            "XCP_WRITE_ACCESS_NOT_ALLOWED INIT_SEGMENT 0 /end PAGE",
            "    /end SEGMENT",
            "  /end IF_DATA",
            "/end MEMORY_SEGMENT"]


def generate(ffi: Any, lib: Any, *, channels: Any = None, params_doc: Any = None,
             xcp: dict | None = None) -> str:
    """The A2L text (ASAP2 1.71) of the loop's memory (see the module's text).

    ``ffi``/``lib``: the compiled module's (``rt_loop._rt_loop``); ``channels``:
    a ``LoopChannels`` (commands, channels, messages and signal values by
    name; without it the commands and channels go by index and there are no
    signals); ``params_doc``: see ``objects``; ``xcp``: IF_DATA settings over
    ``XCP_DEFAULTS`` (transport, address, port, rate_hz, ...).
    ValueError for a bad setting or names the A2L cannot carry."""
    cfg = _xcp_settings(xcp, channels, lib)
    objs = objects(ffi, lib, channels=channels, params_doc=params_doc)
    ident = epk(ffi, lib, objs=objs)

    out: list[str] = ["ASAP2_VERSION 1 71",
                      '/begin PROJECT dct_hil "dct-hil: hardware-in-the-loop plant of the VW DSG 02E"',
                      f'  /begin HEADER "generated by rt_loop/measure/xcp/a2l.py from the C structs" '
                      f'VERSION "{__version__}" PROJECT_NO dct_hil /end HEADER',
                      '  /begin MODULE rt_loop "the real-time loop\'s memory: an address is a byte '
                      'offset from the start of the rt_loop struct, address extension 0"',
                      *a2ml.block(),
                      f'    /begin MOD_PAR "sizeof(rt_loop) = {ffi.sizeof("rt_loop")} bytes"',
                      f'      VERSION "{__version__}" ADDR_EPK 0x{EPK_ADDRESS:X} EPK "{ident}" '
                      'ECU "dct-hil"']
    out += ["      " + line for line in _memory_segment(objs)]
    out += ["    /end MOD_PAR",
                      '    /begin MOD_COMMON "little endian, natural alignment (x86-64, aarch64)"',
                      "      BYTE_ORDER MSB_LAST",
                      "      ALIGNMENT_BYTE 1 ALIGNMENT_WORD 2 ALIGNMENT_LONG 4 ALIGNMENT_INT64 8 "
                      "ALIGNMENT_FLOAT32_IEEE 4 ALIGNMENT_FLOAT64_IEEE 8",
                      "    /end MOD_COMMON"]
    out += ["    " + line for line in _if_data(cfg, lib, any(o.writable for o in objs))]

    # record layouts (one per data type of a CHARACTERISTIC)
    layouts = sorted({o.datatype for o in objs if o.kind == "CHARACTERISTIC"})
    for dt in layouts:
        out.append(f"    /begin RECORD_LAYOUT RL_{dt} FNC_VALUES 1 {dt} ROW_DIR DIRECT "
                   "/end RECORD_LAYOUT")

    # conversions: one IDENTICAL per unit and kind of number, one verbal per table
    cms: dict[tuple, str] = {}
    conv: dict[str, str] = {}
    vtabs: dict[tuple, str] = {}
    cm_lines: list[str] = []
    for o in objs:
        if o.vtab:
            if o.vtab not in vtabs:
                vt = f"VT_{len(vtabs)}"
                vtabs[o.vtab] = vt
                pairs = " ".join(f'{_num(v)} "{_text(t) or _num(v)}"' for v, t in o.vtab)
                cm_lines.append(f'    /begin COMPU_VTAB {vt} "" TAB_VERB {len(o.vtab)} {pairs} '
                                'DEFAULT_VALUE "?" /end COMPU_VTAB')
                cm_lines.append(f'    /begin COMPU_METHOD CM_{vt} "verbal" TAB_VERB "%12.0" "" '
                                f"COMPU_TAB_REF {vt} /end COMPU_METHOD")
            conv[o.name] = f"CM_{vtabs[o.vtab]}"
            continue
        is_int = o.datatype not in ("FLOAT64_IEEE", "FLOAT32_IEEE")
        key = (o.unit, is_int)
        if key not in cms:
            name = f"CM_{_slug(o.unit)}" + ("_int" if is_int else "")
            while name in cms.values():
                name += "_"
            cms[key] = name
            fmt = "%20.0" if is_int else "%16.6"
            cm_lines.append(f'    /begin COMPU_METHOD {name} "{_text(o.unit) or "no unit"}" '
                            f'IDENTICAL "{fmt}" "{_text(o.unit)}" /end COMPU_METHOD')
        conv[o.name] = cms[key]
    out += cm_lines

    for o in objs:
        if o.kind != "CHARACTERISTIC":
            continue
        kind = "VAL_BLK" if o.dims else "VALUE"
        line = (f'    /begin CHARACTERISTIC {o.name} "{o.comment}" {kind} 0x{o.address:X} '
                f"RL_{o.datatype} 0 {conv[o.name]} {_num(o.lower)} {_num(o.upper)}")
        if o.dims:
            cols = o.dims[-1]
            rows = o.dims[0] if len(o.dims) == 2 else 1
            line += f" MATRIX_DIM {cols} {rows} 1"
        if not o.writable:
            line += " READ_ONLY"
        out.append(line + " /end CHARACTERISTIC")
    for o in objs:
        if o.kind != "MEASUREMENT":
            continue
        out.append(f'    /begin MEASUREMENT {o.name} "{o.comment}" {o.datatype} {conv[o.name]} 0 0 '
                   f"{_num(o.lower)} {_num(o.upper)} ECU_ADDRESS 0x{o.address:X} /end MEASUREMENT")

    groups: dict[str, tuple[list[str], list[str]]] = {}
    for o in objs:
        meas, char = groups.setdefault(o.group or "other", ([], []))
        (char if o.kind == "CHARACTERISTIC" else meas).append(o.name)
    for g, (meas, char) in groups.items():
        out.append(f'    /begin GROUP G_{_slug(g)} "{_text(g)}" ROOT')
        if char:
            out.append("      /begin REF_CHARACTERISTIC " + " ".join(char) + " /end REF_CHARACTERISTIC")
        if meas:
            out.append("      /begin REF_MEASUREMENT " + " ".join(meas) + " /end REF_MEASUREMENT")
        out.append("    /end GROUP")
    out += ["  /end MODULE", "/end PROJECT", ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------
# dct-hil a2l
# ---------------------------------------------------------------------------



def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``dct-hil a2l`` on an argparse parser (or subparser)."""
    parser.add_argument("out", metavar="OUT.a2l",
                        help="the A2L file to write (its folder is made if missing)")
    add_matrix_options(
        parser, mapping_help="the CAN matrix the server plays (a mapping file or a shipped one: "
                             "dct_hil, the default, or vehicle): names the commands, the "
                             "channels, the messages' counters and every signal's last value "
                             "(<bus>.<Message>.<Signal>)")
    parser.add_argument("--rate", type=argtypes.rate_hz, default=2000.0, metavar="HZ",
                        help="the loop's rate, as dct-hil serve --rate: the DAQ events' cycle "
                             "times (default 2000)")
    parser.add_argument("--xcp-address", default=XCP_DEFAULTS["address"], metavar="ADDR",
                        help="the XCP slave's IP address or host name (default "
                             f"{XCP_DEFAULTS['address']})")
    parser.add_argument("--xcp-port", type=argtypes.port(), default=XCP_DEFAULTS["port"], metavar="PORT",
                        help=f"the XCP slave's port (default {XCP_DEFAULTS['port']})")
    parser.add_argument("--xcp-transport", choices=("udp", "tcp", "both"),
                        default=XCP_DEFAULTS["transport"],
                        help="XCP on UDP/IP, TCP/IP or both (default udp)")


def _check_out(path: str) -> str | None:
    """None when ``path`` can be written (its folder made), else why not."""
    full = os.path.abspath(path)
    folder = os.path.dirname(full)
    if os.path.isdir(full):
        return f"{path}: is a directory"
    parent = folder
    while parent and not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if parent and not os.path.isdir(parent):
        return f"{path}: {parent} is not a folder"
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        return f"{path}: cannot create folder {folder}: {e.strerror or e}"
    if not os.access(folder, os.W_OK | os.X_OK) or (
            os.path.exists(full) and not os.access(full, os.W_OK)):
        return f"{path}: not writable"
    return None


def run(args: argparse.Namespace, out=None, err=None, prog: str = "dct-hil a2l") -> int:
    """``dct-hil a2l``: writes the A2L; 0 written, 1 the compiled module is
    missing, 2 bad options (path, mapping, DBC, XCP settings)."""
    out = out or sys.stdout
    err = err or sys.stderr

    def fail(code: int, message: Any) -> int:
        print(f"{prog}: error: {' '.join(str(message).split())}", file=err)
        return code

    problem = _check_out(args.out)
    if problem:
        return fail(2, problem)
    try:
        from rt_loop._rt_loop import ffi, lib
    except ImportError as e:
        return fail(1, f"the loop's C extension is not built ({e}); run scripts/setup")
    from can_dbc.mapping import MappingError, load_options
    from rt_loop.channels import ChannelError, LoopChannels

    try:
        mapping = load_options(getattr(args, "mapping", None), getattr(args, "dbc", None) or (),
                               rate_hz=args.rate)
        channels = LoopChannels(mapping, ffi, lib)
        text = generate(ffi, lib, channels=channels,
                        xcp={"address": args.xcp_address, "port": args.xcp_port,
                             "transport": args.xcp_transport, "rate_hz": args.rate})
    except (MappingError, ChannelError, ValueError) as e:
        return fail(2, e)
    tmp = f"{args.out}.tmp{os.getpid()}"
    try:
        with open(tmp, "w", encoding="ascii", newline="\n") as f:
            f.write(text)
        os.replace(tmp, args.out)
    except OSError as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        return fail(2, f"{args.out}: {e.strerror or e}")
    n_meas = text.count("/begin MEASUREMENT ")
    regions = calibration_regions(ffi, lib)
    n_char = text.count("/begin CHARACTERISTIC ")
    ident = re.search(r'EPK "([^"]*)"', text)
    print(f"a2l: {args.out}: {n_meas} measurements, {n_char} characteristics ({len(regions)} "
          f"writable), mapping {os.path.basename(mapping.path)}, XCP on {args.xcp_transport} "
          f"{args.xcp_address}:{args.xcp_port}, EPK {ident.group(1) if ident else '?'}", file=out)
    return 0
