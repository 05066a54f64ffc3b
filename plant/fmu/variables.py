"""The FMU's variables: which of the plant's doubles it shows, and how.

Derived from the C structs (cffi's view of ``dct_inputs``, ``dct_outputs``,
``dct_params``, ``dct_faults``, ``dct_initial``) and the parameter files,
never listed by hand, so a field added to the core appears in the FMU:

- ``time`` (value reference 0): the independent variable;
- every input (``dct_inputs``): causality input, variability discrete (held
  over a communication step, as the offline scenarios hold their rows);
  start: the default the C core gives;
- every output (``dct_outputs``): causality output; one named like an
  input is ``out.<name>`` (``out.accel_pedal_pct``: the pedal as applied);
- every parameter of the car (``dct_params``, the used points of curves and
  maps), ``<path>`` as in the parameter TOML with 0-based indices
  (``clutch[1].mu_static``, ``engine.full_load.torque_nm[3]``): tunable when
  ``plant/data/ranges.toml`` marks it online (changed between steps, checked
  by ``dct_plant_prepare``), fixed otherwise; start: the car the FMU is built
  with; min/max: its range. Not parameters: the solver's step (the FMU's
  fixed internal step) and the point counts (the shape of the tables);
- the physical faults (``faults.<name>``, ``dct_faults``): tunable, 0 = healthy;
- the initial conditions (``initial.<name>``, ``dct_initial``): fixed.

Units come from the names' suffixes, descriptions from the C header's
comments and the parameter file's, as in the A2L (``plant.describe``).
``generate_c`` writes the table the C code reads (``csrc/fmu_model.h``).
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from typing import Any

from plant import describe
from plant import params as _params

TIME, INPUT, OUTPUT, PARAM_FIXED, PARAM_TUNABLE, INITIAL = range(6)
_C_KIND = {TIME: "FMU_VAR_TIME", INPUT: "FMU_VAR_INPUT", OUTPUT: "FMU_VAR_OUTPUT",
           PARAM_FIXED: "FMU_VAR_PARAM_FIXED", PARAM_TUNABLE: "FMU_VAR_PARAM_TUNABLE",
           INITIAL: "FMU_VAR_INITIAL"}

#: parameters that are not FMU variables: the FMU's fixed step
EXCLUDED_PARAMS = {"solver.step_s"}

#: ranges of the faults (the C core checks the rest, e.g. pack gap + offset >= 0)
_FAULT_RANGES = {"pack_gap_offset_mm": (-math.inf, math.inf),
                 "engine_torque_max_nm": (0.0, math.inf)}
_INITIAL_RANGES = {"vehicle_speed_kmh": (-100.0, 300.0), "sleeve_side": (-1.0, 1.0),
                   "clutch_locked": (0.0, 1.0), "engine_on": (0.0, 1.0),
                   "temperatures_given": (0.0, 1.0), "coolant_temp_degc": (-40.0, 130.0),
                   "engine_oil_temp_degc": (-40.0, 150.0), "trans_oil_temp_degc": (-40.0, 150.0)}
_INITIAL_TEXT = {
    "vehicle_speed_kmh": "vehicle speed the run starts at (steady motion)",
    "sleeve_side": "sleeve engaged at the start: +1 / -1 the side's gear (sleeve 0: 1/3, "
                   "1: 2/4, 2: 5/R, 3: 6/-), 0 neutral",
    "clutch_locked": "1: the clutch (K1, K2) is locked at the start: the engine turns with "
                     "its input shaft (needs a gear engaged on that shaft)",
    "engine_on": "1: the engine runs at the start (at idle speed unless a clutch is locked)",
    "temperatures_given": "1: the run starts at the three temperatures below; 0: at the "
                          "parameters' thermal.initial_* (the warm car)",
    "coolant_temp_degc": "engine coolant temperature at the start (with temperatures_given = 1)",
    "engine_oil_temp_degc": "engine oil temperature at the start (with temperatures_given = 1)",
    "trans_oil_temp_degc": "transmission oil temperature at the start (with temperatures_given = 1)",
}


class FmuError(ValueError):
    """An FMU could not be built: one line naming the cause."""


@dataclass(frozen=True)
class Variable:
    vr: int
    name: str
    kind: int
    c_member: str          # member designator in dct_plant (dct_initial for INITIAL); "" for time
    start: float
    min: float
    max: float
    unit: str
    description: str

    @property
    def causality(self) -> str:
        return {TIME: "independent", INPUT: "input", OUTPUT: "output"}.get(self.kind, "parameter")

    @property
    def variability(self) -> str:
        return {TIME: "continuous", INPUT: "discrete", OUTPUT: "continuous",
                PARAM_FIXED: "fixed", PARAM_TUNABLE: "tunable", INITIAL: "fixed"}[self.kind]


@dataclass
class Model:
    """The variables of one FMU build and what the C table needs besides."""
    variables: list
    params: dict           # load_params' dict of the car built in
    params_path: str | None
    token: str             # FMI 2 guid / FMI 3 instantiationToken
    step_s: float
    state_names: list
    input_names: list

    def by_name(self, name: str) -> Variable:
        for v in self.variables:
            if v.name == name:
                return v
        raise KeyError(name)


def _ffi():
    from plant._dct_plant import ffi  # the compiled module
    return ffi


def _designator(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else ("." if out else "") + p
    return out


def _name(path: tuple) -> str:
    """The FMI name of a path: as the C designator, but the indices of a
    table in one bracket (``engine.bsfc.bsfc_g_per_kwh[2,3]``: FMI's
    structured naming)."""
    out = ""
    for k, p in enumerate(path):
        if isinstance(p, int):
            out = out[:-1] + f",{p}]" if k and isinstance(path[k - 1], int) else out + f"[{p}]"
        else:
            out += ("." if out else "") + p
    return out


def _walk_values(ctype: Any, values: Any, path: tuple, parent: str, field: str):
    """(path, value, parent struct cname, field name) of every double the
    parameter dict holds (only the used points of lists)."""
    if ctype.kind == "struct":
        for fname, f in ctype.fields:
            yield from _walk_values(f.type, values[fname], path + (fname,), ctype.cname, fname)
    elif ctype.kind == "array":
        for i, item in enumerate(values):
            yield from _walk_values(ctype.item, item, path + (i,), parent, field)
    elif ctype.cname == "double":
        yield path, float(values), parent, field


def _walk_type(ctype: Any, path: tuple, parent: str, field: str):
    """(path, parent struct cname, field name) of every double of a struct type."""
    if ctype.kind == "struct":
        for fname, f in ctype.fields:
            yield from _walk_type(f.type, path + (fname,), ctype.cname, fname)
    elif ctype.kind == "array":
        for i in range(ctype.length):
            yield from _walk_type(ctype.item, path + (i,), parent, field)
    elif ctype.cname == "double":
        yield path, parent, field


def _field_key(path: tuple) -> str:
    """The path without the indices into a list of numbers: ranges.toml's
    keys (``clutch[].mu_static``, ``engine.full_load.torque_nm``)."""
    k = len(path)
    while k and isinstance(path[k - 1], int):
        k -= 1
    return describe.range_key(path[:k])


def _toml_key(path: tuple) -> str:
    k = len(path)
    while k and isinstance(path[k - 1], int):
        k -= 1
    return _designator(path[:k])


def _text(*parts: str) -> str:
    text = "; ".join(p.strip() for p in parts if p and p.strip())
    return " ".join(text.split())


def load(params_path: str | os.PathLike | None = None) -> Model:
    """The FMU's variables for the default car, or for the car of a
    parameter file merged over it (``ParamError``: one line)."""
    ffi = _ffi()
    values = _params.load_params(params_path, ffi)
    comments = describe.header_comments()
    toml_text = describe.toml_comments(_params.DEFAULT_PARAMS)
    if params_path is not None:
        toml_text.update(describe.toml_comments(params_path))
    ranges = describe.ranges()
    online = describe.online_keys()

    plant = ffi.new("dct_plant *")
    _params.fill_params(ffi, ffi.addressof(plant[0], "params"), values)
    from plant._dct_plant import lib
    if lib.dct_plant_init(plant) != lib.DCT_OK:
        raise FmuError("the plant's C core refused the parameter set (dct_plant_init)")

    variables: list[Variable] = []

    def add(name, kind, member, start, lo, hi, unit, text):
        variables.append(Variable(len(variables), name, kind, member, float(start), float(lo),
                                  float(hi), unit, text))

    add("time", TIME, "", 0.0, -math.inf, math.inf, "s", "simulation time")
    for fname, _ in ffi.typeof("dct_inputs").fields:
        add(fname, INPUT, f"inputs.{fname}", getattr(plant.inputs, fname), -math.inf, math.inf,
            describe.unit_of(fname), _text(comments.get(("dct_inputs", fname), ""),
                                          "limited to its range by the plant"))
    inputs = {f for f, _ in ffi.typeof("dct_inputs").fields}
    for fname, _ in ffi.typeof("dct_outputs").fields:
        add(f"out.{fname}" if fname in inputs else fname, OUTPUT, f"outputs.{fname}",
            getattr(plant.outputs, fname), -math.inf, math.inf, describe.unit_of(fname),
            _text(comments.get(("dct_outputs", fname), "")))
    for path, value, parent, fname in _walk_values(ffi.typeof("dct_params"), values, (), "", ""):
        name = _name(path)
        if name in EXCLUDED_PARAMS:
            continue
        key = _field_key(path)
        lo, hi = ranges.get(key, (-math.inf, math.inf))
        kind = PARAM_TUNABLE if key in online else PARAM_FIXED
        add(name, kind, f"params.{_designator(path)}", value, lo, hi, describe.unit_of(fname),
            _text(toml_text.get(_toml_key(path), ""), comments.get((parent, fname), "")))
    for path, parent, fname in _walk_type(ffi.typeof("dct_faults"), (), "", ""):
        name = _name(path)
        lo, hi = _FAULT_RANGES.get(fname, (0.0, 1.0))
        add(f"faults.{name}", PARAM_TUNABLE, f"faults.{_designator(path)}", 0.0, lo, hi,
            describe.unit_of(fname), _text("physical fault, 0 = healthy",
                                           comments.get((parent, fname), "")))
    initial = _initial_defaults(values)
    for path, _parent, fname in _walk_type(ffi.typeof("dct_initial"), (), "", ""):
        lo, hi = _INITIAL_RANGES[fname]
        add(f"initial.{_name(path)}", INITIAL, _designator(path), _get(initial, path), lo, hi,
            describe.unit_of(fname), _INITIAL_TEXT.get(fname, ""))

    state_names = [_designator(p) for p, _, _ in _walk_type(ffi.typeof("dct_state"), (), "", "")]
    input_names = [f for f, _ in ffi.typeof("dct_inputs").fields]
    digest = hashlib.sha256()
    for v in variables:
        digest.update(f"{v.vr} {v.name} {v.kind} {v.c_member} {v.start!r} {v.min!r} {v.max!r}\n"
                      .encode())
    for path, value, _, _ in _walk_values(ffi.typeof("dct_params"), values, (), "", ""):
        digest.update(f"{_designator(path)}={value!r}\n".encode())
    h = digest.hexdigest()
    token = "{" + f"{h[0:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:32]}" + "}"
    return Model(variables, values, None if params_path is None else str(params_path), token,
                 float(values["solver"]["step_s"]), state_names, input_names)


def _initial_defaults(values: dict | None = None) -> dict:
    """dct_initial's defaults: standing, neutral, clutches open, engine on,
    the parameters' initial temperatures (what ``Plant.reset()`` and the
    scenarios start from); ``values``: the car's parameters (default car)."""
    from plant.scenario import INITIAL_KEYS
    if values is None:
        from plant.params import load_params
        values = load_params(None, _ffi())
    k = INITIAL_KEYS
    th = values["thermal"]
    return {"vehicle_speed_kmh": k["vehicle_speed_kmh"],
            "sleeve_side": [k[f"sleeve{i}_side"] for i in range(1, 5)],
            "clutch_locked": [k["clutch1_locked"], k["clutch2_locked"]],
            "engine_on": k["engine_on"], "temperatures_given": 0.0,
            "coolant_temp_degc": th["initial_coolant_temp_degc"],
            "engine_oil_temp_degc": th["initial_engine_oil_temp_degc"],
            "trans_oil_temp_degc": th["initial_trans_oil_temp_degc"]}


def _get(tree: Any, path: tuple) -> float:
    for p in path:
        tree = tree[p]
    return float(tree)


# -- the C table --------------------------------------------------------------

def _c_double(x: float) -> str:
    if math.isinf(x):
        return "INFINITY" if x > 0 else "-INFINITY"
    if math.isnan(x):
        return "NAN"
    return float(x).hex()


def _c_string(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _c_initializer(ctype: Any, value: Any, indent: str) -> str:
    if ctype.kind == "struct":
        inner = indent + "    "
        parts = [f"{inner}.{fname} = {_c_initializer(f.type, value[fname], inner)}"
                 for fname, f in ctype.fields]
        return "{\n" + ",\n".join(parts) + "\n" + indent + "}"
    if ctype.kind == "array":
        if not value:
            return "{0}"
        return "{" + ", ".join(_c_initializer(ctype.item, v, indent) for v in value) + "}"
    if ctype.cname == "double":
        return _c_double(float(value))
    return str(int(value))


def generate_c(params_path: str | os.PathLike | None = None, model: Model | None = None) -> str:
    """fmu_variables.c: the table of ``csrc/fmu_model.h`` for a car."""
    m = model if model is not None else load(params_path)
    ffi = _ffi()
    lines = ["/* fmu_variables.c - generated by plant/fmu/variables.py: the FMU's variables",
             " * and the car it was built with (see fmu_model.h). Do not edit. */",
             "#include <math.h>", "#include <stddef.h>", "", '#include "fmu_model.h"', "",
             "const fmu_var fmu_vars[] = {"]
    for v in m.variables:
        if v.kind == TIME:
            off = "0"
        elif v.kind == INITIAL:
            off = f"offsetof(dct_initial, {v.c_member})"
        else:
            off = f"offsetof(dct_plant, {v.c_member})"
        lines.append(f"    {{{_C_KIND[v.kind]}, {off}, {_c_double(v.start)}, {_c_double(v.min)}, "
                     f"{_c_double(v.max)}, {_c_string(v.name)}}},  /* vr {v.vr} */")
    lines += ["};", f"const unsigned int fmu_n_vars = {len(m.variables)};", ""]
    lines.append("const dct_params fmu_params = "
                 + _c_initializer(ffi.typeof("dct_params"), m.params, "") + ";")
    lines.append("")
    lines.append("const dct_initial fmu_initial = "
                 + _c_initializer(ffi.typeof("dct_initial"), _initial_defaults(m.params), "") + ";")
    lines.append("")
    lines.append("const char *const fmu_state_names[] = {")
    lines += [f"    {_c_string(n)}," for n in m.state_names]
    lines += ["};", f"const unsigned int fmu_n_state_names = {len(m.state_names)};", ""]
    lines.append("const char *const fmu_input_names[] = {")
    lines += [f"    {_c_string(n)}," for n in m.input_names]
    lines += ["};", f"const unsigned int fmu_n_input_names = {len(m.input_names)};", ""]
    lines.append(f"const char fmu_token[] = {_c_string(m.token)};")
    return "\n".join(lines) + "\n"

