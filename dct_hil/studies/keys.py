"""Keys of what a study varies: plant parameters and TCU calibration values.

Plant parameters are named as the parameter files name them, dotted, with an
index for an array of tables or a list: ``vehicle.mass_kg``,
``clutch[0].mu_static``, ``gearbox.ratio[2]``; ``clutch[].mu_static`` sets
every element alike. Their allowed range is ``plant/data/ranges.toml``.

TCU calibration values are ``tcu.<NAME>``: a calibration constant of the
reference TCU (``tcu_stub/logic.py``; case does not matter), e.g.
``tcu.LAUNCH_RPM_MAX``. A shift line (a table of (pedal %, rpm) points) takes
the point's index: ``tcu.UPSHIFT_RPM[4]`` is the upshift engine speed at
100 % pedal. A relative value (a factor on the default) may address a whole
table or list: ``tcu.UPSHIFT_RPM`` with ``relative = true`` scales the whole
up line.

``resolve(text)`` gives a ``Key``; ``Assignment`` sets one key to a value;
``build(assignments, base)`` turns a run's assignments into the parameter
overrides (a dict shaped like a parameter file) and the TCU calibration
(``{NAME: full value}``) the run applies. ``check_plant(...)`` validates
values against ranges.toml and the relations ``plant.params`` checks.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from dct_hil.studies import StudyError

TCU_PREFIX = "tcu."
# constants of tcu_stub/logic.py that are structure, not calibration
_TCU_NOT_CALIBRATION = frozenset({"PERIOD_S", "TOP_GEAR", "SYNC_ENGAGED", "FAULT_COUNT_MAX"})
_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d*\])*)$")


@dataclass(frozen=True)
class Key:
    """One addressable value: ``kind`` "plant" or "tcu", ``path`` its steps
    (names, list indices, None for every element)."""

    text: str
    kind: str
    path: tuple

    @property
    def name(self) -> str:
        return self.text


@dataclass(frozen=True)
class Assignment:
    key: Key
    value: float
    relative: bool = False     # value is a factor on the default


# ----------------------------------------------------------------- parsing
def _parse_path(text: str) -> tuple:
    path: list = []
    for part in text.split("."):
        m = _STEP.match(part)
        if not m:
            raise ValueError(part)
        path.append(m.group(1))
        for idx in re.findall(r"\[(\d*)\]", m.group(2)):
            path.append(int(idx) if idx else None)
    return tuple(path)


def _dotted(path: tuple) -> str:
    text = ""
    for step in path:
        if step is None:
            text += "[]"
        elif isinstance(step, int):
            text += f"[{step}]"
        else:
            text += f".{step}" if text else step
    return text


@lru_cache(maxsize=1)
def default_params() -> dict:
    """The default car's validated parameters."""
    from plant.params import load_params

    return load_params()


@lru_cache(maxsize=1)
def plant_ranges() -> dict:
    from plant import params as _p

    return _p._read_ranges(_p.RANGES)


def plant_range(path: tuple) -> tuple[float, float, bool] | None:
    """(min, max, integer) of a plant number (the range of its list, for a list element)."""
    key = []
    node: Any = default_params()
    for step in path:
        if isinstance(step, str):
            key.append(step)
            node = node[step]
        else:
            if isinstance(node, list) and node and isinstance(node[0], dict):
                key[-1] += "[]"
            node = node[0 if step is None else step]
    return plant_ranges().get(".".join(key))


@lru_cache(maxsize=1)
def tcu_constants() -> dict[str, Any]:
    """{NAME: default value} of the reference TCU's calibration constants: the numbers,
    tuples of numbers and (x, y) tables that tcu_stub/logic.py assigns at module level
    (not its layout and timing; where tcu_stub names its calibration values, those)."""
    import ast

    from tcu_stub import logic

    with open(logic.__file__, encoding="utf-8") as f:
        tree = ast.parse(f.read())
    assigned = set()
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, ast.AnnAssign) else []
        assigned.update(t.id for t in targets if isinstance(t, ast.Name))
    try:
        from tcu_stub.fast import CALIBRATION_NAMES as named
    except Exception:  # no such module, or not built: the heuristics alone
        named = None
    out = {}
    for name, value in vars(logic).items():
        if not name.isupper() or name.startswith("_") or name in _TCU_NOT_CALIBRATION:
            continue
        if name not in assigned or (named is not None and name not in named):
            continue
        if _is_number(value) or _is_numbers(value) or _is_table(value):
            out[name] = value
    return out


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is_numbers(x: Any) -> bool:
    return isinstance(x, tuple) and bool(x) and all(_is_number(v) for v in x)


def _is_table(x: Any) -> bool:
    return (isinstance(x, tuple) and bool(x)
            and all(isinstance(p, tuple) and len(p) == 2 and all(_is_number(v) for v in p) for p in x))


def resolve(text: str, where: str = "") -> Key:
    """The Key of ``text``; StudyError naming it (and ``where``) when unknown."""
    prefix = f"{where}: " if where else ""
    if not isinstance(text, str) or not text.strip():
        raise StudyError(f"{prefix}a parameter key must be a non-empty string, got {text!r}")
    text = text.strip()
    if text.lower().startswith(TCU_PREFIX):
        return _resolve_tcu(text, prefix)
    try:
        path = _parse_path(text)
    except ValueError:
        raise StudyError(f"{prefix}parameter key {text!r} is not dotted names with optional "
                         "[index] (e.g. vehicle.mass_kg, clutch[0].mu_static)") from None
    node: Any = default_params()
    done: list = []
    for step in path:
        if isinstance(step, str):
            if not isinstance(node, dict) or step not in node:
                options = list(node) if isinstance(node, dict) else []
                close = difflib.get_close_matches(step, options, n=1)
                hint = f" (did you mean {_dotted(tuple(done) + (close[0],))}?)" if close else ""
                where_in = _dotted(tuple(done)) or "the parameter file"
                raise StudyError(f"{prefix}unknown parameter key {text!r}: {where_in} has no "
                                 f"{step!r}{hint}")
            node = node[step]
        else:
            if not isinstance(node, list):
                raise StudyError(f"{prefix}unknown parameter key {text!r}: "
                                 f"{_dotted(tuple(done))} is not a list")
            if step is not None and not 0 <= step < len(node):
                raise StudyError(f"{prefix}unknown parameter key {text!r}: "
                                 f"{_dotted(tuple(done))} has {len(node)} elements "
                                 f"(index 0 to {len(node) - 1})")
            node = node[0 if step is None else step]
        done.append(step)
    if isinstance(node, dict):
        raise StudyError(f"{prefix}parameter key {text!r} is a table, not a value; name one of "
                         f"its fields: {', '.join(list(node)[:8])}")
    if _is_count(path):
        raise StudyError(f"{prefix}parameter key {text!r} is a point count the loader fills "
                         "from the list lengths")
    return Key(text, "plant", path)


def _is_count(path: tuple) -> bool:
    last = path[-1]
    return isinstance(last, str) and (last == "n" or last.startswith("n_"))


def _resolve_tcu(text: str, prefix: str) -> Key:
    body = text[len(TCU_PREFIX):]
    m = _STEP.match(body)
    consts = tcu_constants()
    if not m or "." in body:
        raise StudyError(f"{prefix}TCU key {text!r} must be tcu.NAME or tcu.NAME[index]")
    name = m.group(1).upper()
    idx = re.findall(r"\[(\d*)\]", m.group(2))
    if name not in consts:
        close = difflib.get_close_matches(name, list(consts), n=1)
        hint = f" (did you mean tcu.{close[0]}?)" if close else ""
        raise StudyError(f"{prefix}unknown TCU calibration key {text!r}{hint}; the calibration "
                         "values are the constants of tcu_stub/logic.py")
    value = consts[name]
    if len(idx) > 1 or (idx and idx[0] == ""):
        raise StudyError(f"{prefix}TCU key {text!r}: at most one [index]")
    if idx:
        if _is_number(value):
            raise StudyError(f"{prefix}TCU key {text!r}: {name} is a single value, no index")
        i = int(idx[0])
        if not 0 <= i < len(value):
            raise StudyError(f"{prefix}TCU key {text!r}: {name} has {len(value)} points "
                             f"(index 0 to {len(value) - 1})")
        return Key(text, "tcu", (name, i))
    return Key(text, "tcu", (name,))


def default_of(key: Key, base: dict | None = None) -> Any:
    """The default value: a number, or a list for a list / table key without an index."""
    if key.kind == "tcu":
        value = tcu_constants()[key.path[0]]
        if len(key.path) == 2:
            item = value[key.path[1]]
            return float(item[1]) if isinstance(item, tuple) else float(item)
        if _is_table(value):
            return [float(p[1]) for p in value]
        return [float(v) for v in value] if isinstance(value, tuple) else float(value)
    node: Any = default_params() if base is None else base
    for step in key.path:
        node = node[0 if step is None else step]
    return copy.deepcopy(node)


def is_scalar(key: Key) -> bool:
    return _is_number(default_of(key))


# ----------------------------------------------------------------- building
def build(assignments: list[Assignment], base: dict | None = None) -> tuple[dict, dict]:
    """(plant overrides shaped like a parameter file, {TCU NAME: full value}).

    ``base``: the validated parameters the run starts from (default car)."""
    base = default_params() if base is None else base
    plant: dict = {}
    tcu: dict = {}
    for a in assignments:
        if a.key.kind == "tcu":
            _set_tcu(tcu, a)
        else:
            _set_plant(plant, base, a)
    return plant, tcu


def _scaled(default: Any, a: Assignment) -> Any:
    if isinstance(default, list):
        if not a.relative:
            raise StudyError(f"{a.key.text} is a list; give an index, or relative = true to "
                             "scale every element")
        return [_scaled(v, a) for v in default]
    return float(default) * a.value if a.relative else float(a.value)


def _set_plant(over: dict, base: dict, a: Assignment) -> None:
    path = a.key.path
    # expand [] (every element) into one path per element
    paths = [()]
    node_paths = [(base, ())]
    for step in path:
        new = []
        for node, p in node_paths:
            if step is None:
                new.extend((node[i], p + (i,)) for i in range(len(node)))
            else:
                new.append((node[step], p + (step,)))
        node_paths = new
    paths = [p for _, p in node_paths]
    for p in paths:
        value = _scaled(_get(base, p), a)
        rng = plant_range(p)
        if rng and rng[2]:
            value = [round(v) for v in value] if isinstance(value, list) else round(value)
        _put(over, base, p, value)


def _get(tree: Any, path: tuple) -> Any:
    for step in path:
        tree = tree[step]
    return tree


def _put(over: dict, base: Any, path: tuple, value: Any) -> None:
    """Write ``value`` at ``path`` into the override tree ``over`` (lists of tables
    as lists of (possibly empty) tables, a list element as the whole list)."""
    node, b = over, base
    for i, step in enumerate(path[:-1]):
        nxt = path[i + 1]
        b_child = b[step]
        if isinstance(step, int):
            child = node[step]
        else:
            if step not in node:
                if isinstance(b_child, list) and b_child and isinstance(b_child[0], dict):
                    node[step] = [{} for _ in b_child]
                elif isinstance(b_child, list):
                    node[step] = list(b_child)
                else:
                    node[step] = {}
            child = node[step]
        if isinstance(nxt, int) and isinstance(child, list) and not isinstance(b_child[0], dict):
            child[nxt] = value
            return
        node, b = child, b_child
    last = path[-1]
    node[last] = value


def _set_tcu(tcu: dict, a: Assignment) -> None:
    name = a.key.path[0]
    default = tcu_constants()[name]
    current = tcu.get(name, default)
    if len(a.key.path) == 2:
        i = a.key.path[1]
        items = list(current)
        old = items[i]
        if isinstance(old, tuple):
            base_y = default[i][1]
            items[i] = (old[0], float(base_y) * a.value if a.relative else float(a.value))
        else:
            items[i] = float(default[i]) * a.value if a.relative else float(a.value)
        tcu[name] = tuple(items)
    elif _is_table(default):
        if not a.relative:
            raise StudyError(f"{a.key.text} is a table of (x, y) points; give a point "
                             f"({a.key.text}[0] to [{len(default) - 1}]) or relative = true to "
                             "scale every y")
        tcu[name] = tuple((float(x), float(y) * a.value) for x, y in default)
    elif isinstance(default, tuple):
        if not a.relative:
            raise StudyError(f"{a.key.text} has {len(default)} values; give an index "
                             "or relative = true")
        tcu[name] = tuple(float(v) * a.value for v in default)
    else:
        tcu[name] = float(default) * a.value if a.relative else float(a.value)


# ----------------------------------------------------------------- checking
def check_plant(assignments: list[Assignment], base_raw: dict | None, where: str) -> None:
    """Validate the plant values of ``assignments`` as ``plant.params`` does (ranges,
    relations); StudyError naming ``where``, the key, the value and the range."""
    from plant.params import ParamError, load_params

    plant_as = [a for a in assignments if a.key.kind == "plant"]
    if not plant_as:
        return
    for a in plant_as:
        if not math.isfinite(a.value):
            raise StudyError(f"{where}: {a.key.text} = {a.value!r}: not a finite number")
    base = base_params(base_raw)
    over, _ = build(plant_as, base)
    try:
        load_params(None, overrides=merge(base_raw or {}, over))
    except ParamError as e:
        mine = [a for a in plant_as if _covers(a.key.path, e.key)]
        if mine:
            a = mine[0]
            shown = f"{a.key.text} = {_fmt(a)}"
            if a.relative or e.key != a.key.text:
                shown += f" ({e.key} = {e.value!r})"
            raise StudyError(f"{where}: {shown}: {e.reason} (plant/data/ranges.toml)") from None
        shown = ", ".join(f"{a.key.text} = {_fmt(a)}" for a in plant_as)
        raise StudyError(f"{where}: {shown}: {e.key} = {e.value!r}: {e.reason}") from None


def _covers(path: tuple, dotted: str | None) -> bool:
    """Whether the key ``path`` (None: every element) names the dotted ParamError key."""
    if not dotted:
        return False
    try:
        other = _parse_path(dotted)
    except ValueError:
        return False
    if len(other) < len(path):
        return False
    for mine, theirs in zip(path, other):
        if mine is None and isinstance(theirs, int):
            continue
        if mine != theirs:
            return False
    return True


def _fmt(a: Assignment) -> str:
    return f"{a.value:g} x default" if a.relative else f"{a.value:g}"


def check_tcu(assignments: list[Assignment], where: str) -> None:
    for a in assignments:
        if a.key.kind != "tcu":
            continue
        if not math.isfinite(a.value):
            raise StudyError(f"{where}: {a.key.text} = {a.value!r}: not a finite number")
        if a.relative and a.value <= 0:
            raise StudyError(f"{where}: {a.key.text}: a relative value must be a factor > 0, "
                             f"got {a.value:g}")
        default = default_of(a.key)
        if not a.relative and _is_number(default) and default > 0 and a.value < 0:
            raise StudyError(f"{where}: {a.key.text} = {a.value:g}: must be >= 0 (default "
                             f"{default:g})")


def base_params(base_raw: dict | None) -> dict:
    """Validated parameters of the default car with ``base_raw`` (a file's dict) over it."""
    if not base_raw:
        return default_params()
    from plant.params import load_params

    return load_params(None, overrides=base_raw)


def merge(base: Any, over: Any) -> Any:
    """Deep merge of parameter trees (tables key by key, lists of tables by index)."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = merge(base[k], v) if k in base else copy.deepcopy(v)
        return out
    if (isinstance(base, list) and isinstance(over, list) and base and over
            and all(isinstance(x, dict) for x in base) and all(isinstance(x, dict) for x in over)):
        return [merge(base[i], over[i]) if i < len(base) and i < len(over)
                else copy.deepcopy(over[i] if i < len(over) else base[i])
                for i in range(max(len(base), len(over)))]
    return copy.deepcopy(over)
