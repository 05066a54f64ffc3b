"""Parameter sets of the dct-hil plant: load, validate, and write them into C.

A parameter set is a TOML file whose layout mirrors the C struct ``dct_params``
of ``plant/csrc/dct_plant.h``:

* a nested struct is a TOML table (``[engine]``, ``[engine.full_load]``);
* an array of structs is an array of tables (``[[clutch]]``, ``[[gearbox.sync]]``);
* a ``double`` array is a list, a 2-D ``double`` array a list of lists;
* the point counts (``int`` fields named ``n`` or ``n_<list>``) are not written:
  the loader takes them from the length of the list(s) they count.

The layout is never written down in Python: it is read from the cffi type of
``dct_params`` (``ffi.typeof("dct_params").fields``, recursively), so the
header stays the single contract. The allowed range of every field is in
``data/ranges.toml``.

``load_params`` reads the default car (``DEFAULT_PARAMS``), merges an optional
user file over it and validates the result; ``fill_params`` writes the
validated dict into a ``dct_params`` cdata; ``params_to_dict`` reads one back.
Every problem is reported as a one-line ``ParamError`` naming the file, the
dotted key, the value and the allowed range or the reason.
"""

from __future__ import annotations

import copy
import datetime
import difflib
import os
import tomllib
from pathlib import Path
from typing import Any

__all__ = [
    "DEFAULT_PARAMS",
    "RANGES",
    "ParamError",
    "fill_params",
    "load_params",
    "params_to_dict",
]

_PARAM_DIR = Path(__file__).resolve().parent / "data"

#: The default car: VW Golf Mk5 GTI with the DSG 02E.
DEFAULT_PARAMS: Path = _PARAM_DIR / "golf_mk5_gti_dsg.toml"

#: Allowed range of every field of ``dct_params``.
RANGES: Path = _PARAM_DIR / "ranges.toml"

_STRUCT = "dct_params"

# 2-D tables: field -> (list giving the rows, list giving the columns), both
# in the same struct. The header documents bsfc_g_per_kwh as
# [torque row][speed column]; the index order cannot be read from cffi.
_TABLE_AXES = {"bsfc_g_per_kwh": ("torque_nm", "speed_rpm")}

_REAL_TYPES = frozenset({"double", "float"})
_INT_TYPES = frozenset({"int", "short", "long", "long long", "unsigned int",
                        "unsigned short", "unsigned long", "unsigned long long"})

_NOVALUE = object()
_SHOW_MAX = 72


class ParamError(ValueError):
    """A parameter file or value is invalid.

    ``str()`` is one line: ``<file>: <key> = <value>: <reason>`` (the key or
    the value is left out when there is none, e.g. for a TOML syntax error).
    The parts are also available as the attributes ``file``, ``key``,
    ``value`` (None when there is none) and ``reason``.
    """

    def __init__(self, file: str | os.PathLike, key: str | None, reason: str,
                 value: Any = _NOVALUE) -> None:
        self.file = str(file)
        self.key = key
        self.reason = reason
        self.value = None if value is _NOVALUE else value
        parts = [self.file]
        if key:
            parts.append(key if value is _NOVALUE else f"{key} = {_show(value)}")
        parts.append(reason)
        message = ": ".join(parts)
        super().__init__(" ".join(message.split()))
        self._args = (file, key, reason) if value is _NOVALUE else (file, key, reason, value)

    def __reduce__(self):
        # rebuild from the parts (pickling, e.g. across processes)
        return (type(self), self._args)


# ---------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------

def load_params(path: str | os.PathLike | None = None, ffi: Any = None,
                overrides: dict | None = None) -> dict:
    """Load, merge and validate a parameter set.

    The default car (``DEFAULT_PARAMS``) is always read first. If ``path`` is
    given, that file is deep-merged over it: tables key by key, arrays of
    tables element by element (by index), anything else replaced. A user file
    may therefore hold only the keys it changes, or be complete.

    The merged set is checked against the layout of ``dct_params`` taken from
    ``ffi`` (unknown key, missing key, wrong type, list length against the C
    array, equal lengths of the lists of one curve or map, strictly increasing
    axes) and against ``RANGES`` (every number, and the number of points of
    every curve or map), plus a few relations between fields without which the
    model is meaningless (e.g. the centre of gravity inside the wheelbase).

    ``overrides`` (a dict shaped like the file, e.g. ``{"solver": {"substeps":
    4}}``) is merged last, with the same rules, and checked the same way.

    ``ffi`` is the cffi FFI object that knows ``dct_params``; when None, the
    compiled module's is used (``from plant._dct_plant import ffi``).

    Returns a dict shaped like the struct (keys in C field order): numbers as
    float, point counts (``n``, ``n_<list>``) as int, filled in. Raises
    ``ParamError`` on the first problem found.
    """
    if ffi is None:
        from plant._dct_plant import ffi  # the compiled module

    default_file = Path(DEFAULT_PARAMS)
    default_raw = _read_toml(default_file)
    user_file = user_raw = None
    merged = default_raw
    if path is not None:
        user_file = Path(path)
        user_raw = _read_toml(user_file)
        merged = _merge(default_raw, user_raw)
    if overrides:
        user_raw = _merge(user_raw, overrides) if user_raw is not None else overrides
        if user_file is None:
            user_file = Path("<overrides>")
        merged = _merge(merged, overrides)

    ctx = _Context(_read_ranges(Path(RANGES)), default_file, default_raw,
                   user_file, user_raw)
    values = _check_struct(ffi.typeof(_STRUCT), merged, (), (), ctx)
    _check_relations(values, ctx)
    return values


def fill_params(ffi: Any, cparams: Any, values: dict) -> None:
    """Write a validated parameter dict into a ``dct_params`` cdata.

    ``cparams`` is a ``dct_params *`` (e.g. ``ffi.new("dct_params *")``) or a
    ``dct_params`` struct field of a larger struct (e.g. ``plant.params``).
    ``values`` is what ``load_params`` returns; point counts missing from it
    are taken from the list lengths. Arrays are written element by element;
    array elements beyond the used points are set to 0.
    """
    ctype = ffi.typeof(cparams)
    if ctype.kind == "pointer":
        ctype = ctype.item
    expected = ffi.typeof(_STRUCT)
    if ctype is not expected:
        raise TypeError(f"fill_params needs a {_STRUCT} cdata, got {ctype.cname}")
    _fill_struct(ctype, cparams, values)


def params_to_dict(ffi: Any, cparams: Any) -> dict:
    """Read a ``dct_params`` cdata back into a dict shaped like ``load_params``'s.

    Counted lists and maps are cut to their point counts; numbers come back
    as float, counts as int. ``params_to_dict(ffi, p)`` after
    ``fill_params(ffi, p, values)`` equals ``values``.
    """
    ctype = ffi.typeof(cparams)
    if ctype.kind == "pointer":
        ctype = ctype.item
    expected = ffi.typeof(_STRUCT)
    if ctype is not expected:
        raise TypeError(f"params_to_dict needs a {_STRUCT} cdata, got {ctype.cname}")
    return _read_struct(ctype, cparams)


# ---------------------------------------------------------------------------
# layout of the C struct
# ---------------------------------------------------------------------------

class _Layout:
    """What the loader needs to know about one C struct type.

    types:     field -> its cffi type
    kinds:     field -> "struct", "structs" (array of struct), "list"
               (double array), "table" (2-D double array), "real", "int"
    counts:    count field -> the list fields whose common length it holds
    count_of:  list field -> its count field
    axes:      list fields that must be strictly increasing
    tables:    table field -> (row list, column list) or None (fixed size)
    """

    def __init__(self, ctype: Any) -> None:
        self.ctype = ctype
        self.fields = list(ctype.fields)
        self.types = {name: field.type for name, field in self.fields}
        self.kinds = {name: _classify(field.type, name) for name, field in self.fields}
        lists = [name for name, kind in self.kinds.items() if kind == "list"]
        self.counts: dict[str, list[str]] = {}
        for name, kind in self.kinds.items():
            if kind == "int" and name.startswith("n_") and self.kinds.get(name[2:]) == "list":
                self.counts[name] = [name[2:]]
        claimed = {item for group in self.counts.values() for item in group}
        if self.kinds.get("n") == "int":
            rest = [name for name in lists if name not in claimed]
            if rest:
                self.counts["n"] = rest
        self.count_of = {item: count for count, group in self.counts.items() for item in group}
        # the first list a count governs is its axis (speed_rpm of a curve;
        # speed_rpm and torque_nm of a map, each with its own count)
        self.axes = [group[0] for group in self.counts.values()]
        self.tables: dict[str, tuple[str, str] | None] = {}
        for name, kind in self.kinds.items():
            if kind != "table":
                continue
            axes = _TABLE_AXES.get(name)
            if axes is not None and not all(axis in self.count_of for axis in axes):
                raise TypeError(f"{ctype.cname}.{name}: axis lists {axes} are not counted lists")
            self.tables[name] = axes


_LAYOUTS: dict[Any, _Layout] = {}


def _layout(ctype: Any) -> _Layout:
    layout = _LAYOUTS.get(ctype)
    if layout is None:
        layout = _LAYOUTS[ctype] = _Layout(ctype)
    return layout


def _classify(ctype: Any, name: str) -> str:
    """Kind of a C field type (see _Layout); TypeError for anything else."""
    if ctype.kind == "struct":
        return "struct"
    if ctype.kind == "array":
        item = ctype.item
        if item.kind == "struct":
            return "structs"
        if item.kind == "primitive" and item.cname in _REAL_TYPES:
            return "list"
        if (item.kind == "array" and item.item.kind == "primitive"
                and item.item.cname in _REAL_TYPES):
            return "table"
    if ctype.kind == "primitive":
        if ctype.cname in _REAL_TYPES:
            return "real"
        if ctype.cname in _INT_TYPES:
            return "int"
    raise TypeError(f"field {name}: C type {ctype.cname} is not supported in parameters")


# ---------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------

def _read_toml(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ParamError(path, None, f"TOML syntax error: {exc}") from None
    except OSError as exc:
        raise ParamError(path, None, f"cannot read the file: {exc.strerror or exc}") from None


def _read_ranges(path: Path) -> dict[str, tuple[float, float, bool]]:
    """ranges.toml -> {range key: (min, max, integer)}."""
    raw = _read_toml(path)
    ranges = {}
    for key, entry in raw.items():
        ok = (isinstance(entry, list) and len(entry) in (2, 3)
              and all(_is_number(x) for x in entry[:2])
              and (len(entry) == 2 or entry[2] == "integer"))
        if not ok or not entry[0] <= entry[1]:
            raise ParamError(path, key, 'malformed range: expected [min, max] with min <= max, '
                             'or [min, max, "integer"]', entry)
        ranges[key] = (entry[0], entry[1], len(entry) == 3)
    return ranges


def _merge(base: Any, over: Any) -> Any:
    """Deep-merge ``over`` onto ``base`` (neither is modified)."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for key, value in over.items():
            out[key] = _merge(base[key], value) if key in base else copy.deepcopy(value)
        return out
    if _is_tables(base) and _is_tables(over):
        out = []
        for i in range(max(len(base), len(over))):
            if i < len(base) and i < len(over):
                out.append(_merge(base[i], over[i]))
            else:
                out.append(copy.deepcopy(over[i] if i < len(over) else base[i]))
        return out
    return copy.deepcopy(over)


def _is_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(x, dict) for x in value)


# ---------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------

class _Context:
    """Ranges and the files a value can come from (for the error messages)."""

    def __init__(self, ranges, default_file, default_raw, user_file, user_raw):
        self.ranges = ranges
        self.default_file = default_file
        self.default_raw = default_raw
        self.user_file = user_file
        self.user_raw = user_raw

    def file_of(self, *paths: tuple) -> Path:
        """The file to blame for merged values: the user file if it set any of them."""
        if self.user_raw is not None and any(_has(self.user_raw, p) for p in paths):
            return self.user_file
        return self.default_file

    def error(self, path: tuple, reason: str, value: Any = _NOVALUE,
              file: Path | None = None, related: tuple = ()) -> ParamError:
        """ParamError for ``path``; ``related`` paths took part in the problem."""
        return ParamError(file or self.file_of(path, *related), _dotted(path), reason, value)

    def range_of(self, rpath: tuple) -> tuple[float, float, bool]:
        key = ".".join(rpath).replace(".[]", "[]")
        try:
            return self.ranges[key]
        except KeyError:
            raise ParamError(RANGES, key, "no range entry for this field of "
                             f"{_STRUCT}; add one") from None


def _check_struct(ctype: Any, value: Any, path: tuple, rpath: tuple, ctx: _Context) -> dict:
    """Validate one struct; returns the normalized dict (C field order)."""
    if not isinstance(value, dict):
        raise ctx.error(path, f"wrong type: expected a table, got {_toml_type(value)}", value)
    layout = _layout(ctype)

    for key in value:
        if key in layout.counts:
            raise ctx.error(path + (key,), "unknown key: the loader fills it from the length of "
                            f"{' and '.join(layout.counts[key])}; leave it out", value[key])
        if key not in layout.kinds:
            close = difflib.get_close_matches(key, list(layout.kinds), n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ctx.error(path + (key,), f"unknown key: {ctype.cname} has no such field{hint}",
                            value[key])

    out: dict[str, Any] = {}
    for name, field in layout.fields:
        if name in layout.counts:
            continue
        fpath, frpath = path + (name,), rpath + (name,)
        if name not in value:
            # a merged set has every key of the default file, so a missing
            # key is missing there, or in a table that only the user file has
            in_default = _has(ctx.default_raw, path)
            raise ctx.error(fpath, "missing key",
                            file=ctx.default_file if in_default or ctx.user_file is None
                            else ctx.user_file)
        item = value[name]
        kind = layout.kinds[name]
        if kind == "struct":
            out[name] = _check_struct(field.type, item, fpath, frpath, ctx)
        elif kind == "structs":
            out[name] = _check_structs(field.type, item, fpath, frpath, ctx)
        elif kind == "list":
            out[name] = _check_list(field.type, item, fpath, frpath, ctx,
                                    exact=name not in layout.count_of)
        elif kind == "table":
            out[name] = _check_table_cells(field.type, item, fpath, frpath, ctx)
        elif kind == "real":
            out[name] = _check_number(item, fpath, frpath, ctx)
        else:
            out[name] = _check_int(item, fpath, frpath, ctx)

    for count, group in layout.counts.items():
        first = group[0]
        for other in group[1:]:
            if len(out[other]) != len(out[first]):
                blame, ref = other, first
                user_set = ctx.file_of(path + (first,)) != ctx.default_file
                if user_set and ctx.file_of(path + (other,)) == ctx.default_file:
                    blame, ref = first, other
                raise ctx.error(path + (blame,), f"has {len(out[blame])} values but {ref} has "
                                f"{len(out[ref])}: the lists of one table must have equal "
                                "length", out[blame], related=(path + (ref,),))
        points = len(out[first])
        lo, hi, _ = ctx.range_of(rpath + (count,))
        if not lo <= points <= hi:
            raise ctx.error(path + (first,), f"{points} point{'' if points == 1 else 's'}, "
                            f"needs {lo} to {hi} (range of {_dotted(path + (count,))})",
                            out[first], related=tuple(path + (item,) for item in group))
        out[count] = points

    for axis in layout.axes:
        values = out[axis]
        for i in range(1, len(values)):
            if not values[i] > values[i - 1]:
                raise ctx.error(path + (axis,), "not strictly increasing "
                                f"(index {i - 1}: {values[i - 1]:g}, index {i}: {values[i]:g})",
                                values)

    for name, axes in layout.tables.items():
        _check_table_shape(layout.types[name], out[name], axes, out, path, name, ctx)

    return {name: out[name] for name, _ in layout.fields}


def _check_structs(ctype: Any, value: Any, path: tuple, rpath: tuple, ctx: _Context) -> list:
    if not (isinstance(value, list) and all(isinstance(x, dict) for x in value)):
        raise ctx.error(path, "wrong type: expected an array of tables "
                        f"([[{_dotted(path)}]]), got {_toml_type(value)}", value)
    if len(value) > ctype.length:
        raise ctx.error(path, f"{len(value)} tables: list too long for the C array "
                        f"(maximum {ctype.length})", value)
    if len(value) < ctype.length:
        raise ctx.error(path, f"{len(value)} tables: the C array needs exactly "
                        f"{ctype.length}", value)
    return [_check_struct(ctype.item, item, path + (i,), rpath + ("[]",), ctx)
            for i, item in enumerate(value)]


def _check_list(ctype: Any, value: Any, path: tuple, rpath: tuple, ctx: _Context,
                exact: bool) -> list:
    if not isinstance(value, list):
        raise ctx.error(path, f"wrong type: expected a list of numbers, got {_toml_type(value)}",
                        value)
    if len(value) > ctype.length:
        raise ctx.error(path, f"{len(value)} values: list too long for the C array "
                        f"(maximum {ctype.length})", value)
    if exact and len(value) != ctype.length:
        raise ctx.error(path, f"{len(value)} values: the C array needs exactly {ctype.length}",
                        value)
    return [_check_number(x, path + (i,), rpath, ctx) for i, x in enumerate(value)]


def _check_table_cells(ctype: Any, value: Any, path: tuple, rpath: tuple,
                       ctx: _Context) -> list:
    """Type, C size and range of a 2-D table (the shape is checked later)."""
    if not (isinstance(value, list) and all(isinstance(row, list) for row in value)):
        raise ctx.error(path, "wrong type: expected a list of lists of numbers, got "
                        f"{_toml_type(value)}", value)
    if len(value) > ctype.length:
        raise ctx.error(path, f"{len(value)} rows: list too long for the C array "
                        f"(maximum {ctype.length} rows)", value)
    out = []
    for i, row in enumerate(value):
        if len(row) > ctype.item.length:
            raise ctx.error(path + (i,), f"{len(row)} values: list too long for the C array "
                            f"(maximum {ctype.item.length} per row)", row)
        out.append([_check_number(x, path + (i, j), rpath, ctx) for j, x in enumerate(row)])
    return out


def _check_table_shape(ctype: Any, table: list, axes: tuple[str, str] | None,
                       struct: dict, path: tuple, name: str, ctx: _Context) -> None:
    if axes is None:
        rows, cols = ctype.length, ctype.item.length
        row_what = col_what = "the C array size"
        related: tuple = ()
    else:
        rows, cols = len(struct[axes[0]]), len(struct[axes[1]])
        row_what, col_what = f"one row per {axes[0]} value", f"one per {axes[1]} value"
        related = (path + (axes[0],), path + (axes[1],))
    if len(table) != rows:
        raise ctx.error(path + (name,), f"{len(table)} rows, expected {rows} ({row_what})",
                        table, related=related)
    for i, row in enumerate(table):
        if len(row) != cols:
            raise ctx.error(path + (name, i), f"{len(row)} values, expected {cols} "
                            f"({col_what})", row, related=related)


def _check_number(value: Any, path: tuple, rpath: tuple, ctx: _Context) -> float:
    if not _is_number(value):
        raise ctx.error(path, f"wrong type: expected a number, got {_toml_type(value)}", value)
    lo, hi, integer = ctx.range_of(rpath)
    if integer and not float(value).is_integer():
        raise ctx.error(path, f"must be a whole number in [{lo}, {hi}]", value)
    if not lo <= value <= hi:
        raise ctx.error(path, f"out of range [{lo}, {hi}]", value)
    return float(value)


def _check_int(value: Any, path: tuple, rpath: tuple, ctx: _Context) -> int:
    if not _is_number(value) or not float(value).is_integer():
        raise ctx.error(path, f"wrong type: expected an integer, got {_toml_type(value)}", value)
    lo, hi, _ = ctx.range_of(rpath)
    if not lo <= value <= hi:
        raise ctx.error(path, f"out of range [{lo}, {hi}]", value)
    return int(value)


def _check_relations(v: dict, ctx: _Context) -> None:
    """Relations between fields without which the model is meaningless."""

    def below(path: tuple, limit: float, what: str, related: tuple) -> None:
        """Require value < limit; ``what`` names the limit, "{}" stands for its value."""
        value = _get(v, path)
        if not value < limit:
            text = what.format(f"{limit:g}") if "{}" in what else f"{what} ({limit:g})"
            raise ctx.error(path, f"must be below {text}", value, related=related)

    engine = v["engine"]
    below(("engine", "stall_speed_rpm"), engine["idle_speed_rpm"], "engine.idle_speed_rpm",
          (("engine", "idle_speed_rpm"),))
    below(("engine", "idle_speed_rpm"), engine["rev_limit_rpm"], "engine.rev_limit_rpm",
          (("engine", "rev_limit_rpm"),))
    for i, clutch in enumerate(v["clutch"]):
        force = clutch["max_pressure_bar"] * 1e5 * clutch["piston_area_m2"]
        below(("clutch", i, "return_spring_n"), force,
              "max_pressure_bar x piston_area_m2 = {} N, else the clutch never closes",
              (("clutch", i, "max_pressure_bar"), ("clutch", i, "piston_area_m2")))
    for i, sync in enumerate(v["gearbox"]["sync"]):
        below(("gearbox", "sync", i, "cone_travel_mm"), sync["engaged_travel_mm"],
              f"gearbox.sync[{i}].engaged_travel_mm", (("gearbox", "sync", i, "engaged_travel_mm"),))
    vehicle = v["vehicle"]
    below(("vehicle", "cg_to_front_axle_m"), vehicle["wheelbase_m"], "vehicle.wheelbase_m",
          (("vehicle", "wheelbase_m"),))
    below(("vehicle", "front_unsprung_kg"), vehicle["mass_kg"] - vehicle["rear_unsprung_kg"],
          "mass_kg - rear_unsprung_kg = {} kg, else the sprung mass is not positive",
          (("vehicle", "mass_kg"), ("vehicle", "rear_unsprung_kg")))


# ---------------------------------------------------------------------------
# C <-> dict
# ---------------------------------------------------------------------------

def _fill_struct(ctype: Any, c: Any, values: dict) -> None:
    layout = _layout(ctype)
    for name, field in layout.fields:
        kind = layout.kinds[name]
        if name in layout.counts:
            points = values.get(name)
            setattr(c, name, len(values[layout.counts[name][0]]) if points is None else int(points))
            continue
        value = values[name]
        if kind == "struct":
            _fill_struct(field.type, getattr(c, name), value)
        elif kind == "structs":
            array = getattr(c, name)
            for i in range(field.type.length):
                _fill_struct(field.type.item, array[i], value[i])
        elif kind == "list":
            array = getattr(c, name)
            for i in range(field.type.length):
                array[i] = float(value[i]) if i < len(value) else 0.0
        elif kind == "table":
            array = getattr(c, name)
            for i in range(field.type.length):
                row = array[i]
                cells = value[i] if i < len(value) else []
                for j in range(field.type.item.length):
                    row[j] = float(cells[j]) if j < len(cells) else 0.0
        elif kind == "real":
            setattr(c, name, float(value))
        else:
            setattr(c, name, int(value))


def _read_struct(ctype: Any, c: Any) -> dict:
    layout = _layout(ctype)
    counts = {name: getattr(c, name) for name in layout.counts}

    def used(list_name: str, capacity: int) -> int:
        count = layout.count_of.get(list_name)
        return capacity if count is None else max(0, min(counts[count], capacity))

    out: dict[str, Any] = {}
    for name, field in layout.fields:
        kind = layout.kinds[name]
        if name in layout.counts:
            out[name] = int(counts[name])
        elif kind == "struct":
            out[name] = _read_struct(field.type, getattr(c, name))
        elif kind == "structs":
            array = getattr(c, name)
            out[name] = [_read_struct(field.type.item, array[i]) for i in range(field.type.length)]
        elif kind == "list":
            array = getattr(c, name)
            out[name] = [float(array[i]) for i in range(used(name, field.type.length))]
        elif kind == "table":
            array = getattr(c, name)
            axes = layout.tables[name]
            rows, cols = field.type.length, field.type.item.length
            if axes is not None:
                rows, cols = used(axes[0], rows), used(axes[1], cols)
            out[name] = [[float(array[i][j]) for j in range(cols)] for i in range(rows)]
        elif kind == "real":
            out[name] = float(getattr(c, name))
        else:
            out[name] = int(getattr(c, name))
    return out


# ---------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------

def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _get(tree: Any, path: tuple) -> Any:
    for step in path:
        tree = tree[step]
    return tree


def _has(raw: Any, path: tuple) -> bool:
    """Whether ``path`` (keys and list indices) exists in a parsed TOML tree."""
    node = raw
    for step in path:
        if isinstance(step, int):
            if not isinstance(node, list) or step >= len(node):
                return False
        elif not isinstance(node, dict) or step not in node:
            return False
        node = node[step]
    return True


def _dotted(path: tuple) -> str:
    """('clutch', 1, 'friction', 'x') -> 'clutch[1].friction.x'."""
    text = ""
    for step in path:
        text += f"[{step}]" if isinstance(step, int) else (f".{step}" if text else step)
    return text


def _toml_type(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, (datetime.date, datetime.time)):
        return "a date/time"
    return type(value).__name__


def _show(value: Any) -> str:
    """Short one-line rendering of a value for an error message."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, float):
        text = repr(value)
    elif isinstance(value, str):
        text = '"' + value.replace('"', '\\"') + '"'
    elif isinstance(value, list):
        text = "[" + ", ".join(_show(x) for x in value) + "]"
    elif isinstance(value, dict):
        text = "{" + ", ".join(f"{k} = {_show(x)}" for k, x in value.items()) + "}"
    else:
        text = str(value)
    text = " ".join(text.split())
    return text if len(text) <= _SHOW_MAX else text[:_SHOW_MAX - 3] + "..."
