"""What the plant's C structs and data files say of each number: its unit
(from the field name's suffix), its comment (in the C header, in the
parameter TOML), its allowed range and whether it may change while running
(``plant/data/ranges.toml``). Read by the generated descriptions of the
plant (the A2L of rt_loop/measure/xcp/a2l.py, the FMU's modelDescription.xml of
plant/fmu/) so that they describe it alike.
"""

from __future__ import annotations

import functools
import re
import tomllib
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
#: the C headers whose struct fields' comments describe the numbers
HEADERS = (
    _ROOT / "plant" / "csrc" / "dct_plant.h",
    _ROOT / "can_dbc" / "csrc" / "can_table.h",
    _ROOT / "rt_loop" / "csrc" / "rt_loop.h",
)
RANGES = _ROOT / "plant" / "data" / "ranges.toml"

#: the unit a name's last part says (``engine_speed_rpm``: rpm); the project's
#: naming of signals, inputs, outputs and parameters
SUFFIX_UNITS = {"rpm": "rpm", "kmh": "km/h", "mps": "m/s", "mps2": "m/s2", "bar": "bar",
                "kpa": "kPa", "nm": "Nm", "n": "N", "pct": "%", "a": "A", "ma": "mA", "v": "V",
                "mm": "mm", "m": "m", "s": "s", "ms": "ms", "us": "us", "deg": "deg",
                "rad": "rad", "l": "l", "lph": "l/h", "kw": "kW", "degc": "degC"}


# -- units ------------------------------------------------------------------

@functools.lru_cache(maxsize=1)
def _unit_tokens() -> dict[str, str]:
    tokens = dict(SUFFIX_UNITS)
    # compound SI names of the plant's parameters and states
    tokens.update({"kg": "kg", "g": "g", "kgm2": "kg m2", "nms": "N m s", "ns": "N s",
                   "pa": "Pa", "m2": "m2", "m3": "m3", "cm3": "cm3", "s2": "s2", "w": "W",
                   "kwh": "kWh", "hz": "Hz"})
    return tokens



def unit_of(name: str) -> str:
    """The unit a field name's suffix says: ``engine_speed_rpm`` -> ``rpm``,
    ``speed_rad_s`` -> ``rad/s``, ``stiffness_nm_per_rad`` -> ``Nm/rad``,
    ``idle_ki_nm_per_rpm_s`` -> ``Nm/(rpm s)``; "" when it says none. Within the
    first group a second unit divides (``m_s2``: m/s2), after ``per`` units
    multiply (the project's naming)."""
    tokens = _unit_tokens()
    parts = name.split("_")
    k = len(parts)
    while k > 1 and (parts[k - 1] in tokens or parts[k - 1] == "per"):
        k -= 1
    tail = parts[k:]
    while tail and tail[0] == "per":           # "..._per_x" needs a unit before per
        tail = tail[1:]
    if not tail:
        return ""
    groups: list[list[str]] = [[]]
    for t in tail:
        if t == "per":
            groups.append([])
        else:
            groups[-1].append(tokens[t])
    if any(not g for g in groups):
        return ""
    first = groups[0][0] if len(groups[0]) == 1 else "/".join(groups[0])
    rest = []
    for g in groups[1:]:
        rest.append(g[0] if len(g) == 1 else "(" + " ".join(g) + ")")
    return "/".join([first] + rest)


# -- comments ---------------------------------------------------------------

_FIELD = re.compile(r"^\s*(?:const\s+)?[A-Za-z_]\w*(?:\s+[A-Za-z_]\w*)*[\s*]+([A-Za-z_]\w*)\s*"
                    r"(?:\[[^\]]*\]\s*)*;(.*)$")
_STRUCT_END = re.compile(r"^\s*}\s*([A-Za-z_]\w*)\s*;")


def header_comments(paths=HEADERS) -> dict[tuple[str, str], str]:
    """(struct typedef name, field) -> the field's trailing comment in the headers."""
    out: dict[tuple[str, str], str] = {}
    for path in paths:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError:
            continue
        inside = False
        fields: list[tuple[str, list[str]]] = []
        pending: list[str] | None = None
        for line in text.splitlines():
            if pending is not None:
                end = line.find("*/")
                pending.append((line[:end] if end >= 0 else line).strip().lstrip("*").strip())
                if end >= 0:
                    pending = None
                continue
            stripped = line.strip()
            if stripped.startswith("typedef struct") and "{" in stripped:
                inside, fields = True, []
                continue
            if not inside:
                continue
            end_match = _STRUCT_END.match(line)
            if end_match:
                for name, parts in fields:
                    out[(end_match.group(1), name)] = " ".join(p for p in parts if p)
                inside = False
                continue
            if stripped.startswith(("/*", "*")):
                continue
            m = _FIELD.match(line)
            if not m:
                continue
            parts: list[str] = []
            rest = m.group(2)
            at = rest.find("/*")
            if at >= 0:
                body = rest[at + 2:]
                end = body.find("*/")
                parts.append((body[:end] if end >= 0 else body).strip())
                if end < 0:
                    pending = parts
            fields.append((m.group(1), parts))
    return out


_TABLE = re.compile(r"^\[\[?\s*([A-Za-z_][\w.]*)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^([A-Za-z_]\w*)\s*=\s*(.*)$")


def toml_comments(path) -> dict[str, str]:
    """Dotted key with element indices (``clutch[1].mu_kinetic``) -> the trailing
    comment of its value in a parameter TOML file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError:
        return {}
    out: dict[str, str] = {}
    counts: dict[str, int] = {}
    table: list[str] = []
    depth = 0
    for line in text.splitlines():
        stripped = line.strip()
        if depth > 0:                        # inside a multi-line array
            depth += _brackets(stripped)
            continue
        m = _TABLE.match(stripped)
        if m and stripped.startswith("["):
            key = m.group(1)
            if stripped.startswith("[["):
                counts[key] = counts.get(key, -1) + 1
            parts = key.split(".")
            table = []
            for i, part in enumerate(parts):
                prefix = ".".join(parts[:i + 1])
                table.append(f"{part}[{counts[prefix]}]" if prefix in counts else part)
            continue
        m = _KEY.match(stripped)
        if not m:
            continue
        value = m.group(2)
        at = value.find("#")
        if at >= 0:
            out[".".join(table + [m.group(1)])] = value[at + 1:].strip()
            value = value[:at]
        depth = max(0, _brackets(value))
    return out


def _brackets(text: str) -> int:
    text = text.split("#", 1)[0]
    return text.count("[") - text.count("]")


# -- the ranges file and its online marker ----------------------------------

_ONLINE = re.compile(r'^\s*"([^"]+)"\s*=\s*\[[^\]]*\]\s*#\s*online\b')


def online_keys(path=None) -> set[str]:
    """The range keys of ``plant/data/ranges.toml`` (``clutch[].mu_static``,
    ``engine.full_load.torque_nm``) whose comment begins with ``online``: the
    parameters that may be changed while the loop runs."""
    text = Path(path or RANGES).read_text(encoding="utf-8")
    return {m.group(1) for line in text.splitlines() if (m := _ONLINE.match(line))}


def ranges(path=None) -> dict[str, tuple[float, float]]:
    with open(path or RANGES, "rb") as f:
        raw = tomllib.load(f)
    return {k: (float(v[0]), float(v[1])) for k, v in raw.items()}


def range_key(param_path: tuple) -> str:
    """ranges.toml's key of a parameter path below plant.params."""
    out = ""
    for item in param_path:
        if isinstance(item, int):
            out += "[]"
        else:
            out += ("." if out else "") + item
    return out
