"""Plant: one instance of the C powertrain model, seen through NumPy.

The C core owns nothing: Python allocates one ``dct_plant`` (params, state,
inputs and outputs in one struct), fills the parameters, and the C functions
work on it in place. ``inputs``, ``outputs`` and ``state`` are NumPy views of
that memory, so reading an output or writing an input costs no copy and no
FFI call; only ``step``/``reset``/``bench`` cross into C.
"""

import math
import operator

import numpy as np

from plant import params as _params
from plant._dct_plant import ffi, lib

_INT_MAX = 2**31 - 1
_DOUBLE = ffi.typeof("double")


class PlantError(RuntimeError):
    """The C core refused a step, a reset or the parameters (one-line message)."""


def _struct_dtype(cname):
    """NumPy dtype laid out exactly like the C struct ``cname`` (doubles only)."""
    ctype = ffi.typeof(cname)
    names, offsets = [], []
    for name, field in ctype.fields:
        if field.type is not _DOUBLE:
            raise TypeError(f"{cname}.{name} is not a double; the NumPy view needs doubles only")
        names.append(name)
        offsets.append(field.offset)
    return np.dtype(
        {
            "names": names,
            "formats": [np.float64] * len(names),
            "offsets": offsets,
            "itemsize": ffi.sizeof(ctype),
        }
    )


def _flat_names(ctype, prefix, offset, found):
    """Walk a struct of doubles (nested structs, arrays) into {byte offset: dotted name}."""
    if ctype.kind == "struct":
        for name, field in ctype.fields:
            path = f"{prefix}.{name}" if prefix else name
            _flat_names(field.type, path, offset + field.offset, found)
    elif ctype.kind == "array":
        size = ffi.sizeof(ctype.item)
        for i in range(ctype.length):
            _flat_names(ctype.item, f"{prefix}[{i}]", offset + i * size, found)
    elif ctype is _DOUBLE:
        found[offset] = prefix
    else:
        raise TypeError(f"{prefix} is {ctype.cname}; the state must hold doubles only")


def _state_names():
    found = {}
    _flat_names(ffi.typeof("dct_state"), "", 0, found)
    n = ffi.sizeof("dct_state") // 8
    if sorted(found) != [8 * i for i in range(n)]:
        raise TypeError("dct_state is not one contiguous array of doubles")
    return [found[8 * i] for i in range(n)]


INPUT_DTYPE = _struct_dtype("dct_inputs")
OUTPUT_DTYPE = _struct_dtype("dct_outputs")
INPUT_NAMES = list(INPUT_DTYPE.names)
# the flat views (input_values, output_values) need doubles packed without gaps
assert INPUT_DTYPE.itemsize == 8 * len(INPUT_DTYPE.names)
assert OUTPUT_DTYPE.itemsize == 8 * len(OUTPUT_DTYPE.names)
OUTPUT_NAMES = list(OUTPUT_DTYPE.names)
STATE_NAMES = _state_names()

_OFF_STATE = ffi.offsetof("dct_plant", "state")
_OFF_INPUTS = ffi.offsetof("dct_plant", "inputs")
_OFF_OUTPUTS = ffi.offsetof("dct_plant", "outputs")
# snapshot: state, inputs, outputs and the step's bookkeeping; not the
# parameters, their derived constants, the faults or the parameters they make
_SNAP_BEGIN = _OFF_STATE
_SNAP_END = ffi.offsetof("dct_plant", "faults")
assert _SNAP_END > ffi.offsetof("dct_plant", "applied")


def _fault_fields():
    """{name: number of values} of dct_faults (1: a scalar), in struct order."""
    fields = {}
    for name, field in ffi.typeof("dct_faults").fields:
        if field.type is _DOUBLE:
            fields[name] = 1
        elif field.type.kind == "array" and field.type.item is _DOUBLE:
            fields[name] = field.type.length
        else:
            raise TypeError(f"dct_faults.{name} is {field.type.cname}; faults are doubles")
    return fields


#: physical faults (``Plant.set_faults``): name -> number of values (1: scalar;
#: 2: K1, K2; 4: sleeves 1-3, 2-4, 5-R, 6-N)
FAULT_FIELDS = _fault_fields()
FAULT_NAMES = list(FAULT_FIELDS)
# the ranges dct_faults_check (plant/csrc/faults.c) holds, for the messages
_FAULT_RANGE = {
    "friction_loss": "a share from 0 to 1",
    "line_pressure_loss": "a share from 0 to 1",
    "engine_torque_max_nm": "a torque >= 0",
}
_FLAG_RANGE = "0 (healthy) to 1 (failed), in effect above 0.5"


class Plant:
    """One powertrain plant (engine, DSG 02E, driveline, vehicle).

    >>> p = Plant()                       # default parameter set
    >>> p.inputs["accel_pedal_pct"] = 30  # writes the C struct
    >>> p.step(2000)                      # 1 s at 0.5 ms, one FFI call
    >>> float(p.outputs["vehicle_speed_kmh"])
    """

    input_names = INPUT_NAMES
    output_names = OUTPUT_NAMES
    state_names = STATE_NAMES

    def __init__(self, params_path=None, overrides=None):
        """``params_path``: a TOML file merged over the default car;
        ``overrides``: a dict shaped like that file, merged last."""
        self.params = _params.load_params(params_path, ffi, overrides)
        self._p = ffi.new("dct_plant *")  # zeroed; freed with this object
        _params.fill_params(ffi, ffi.addressof(self._p[0], "params"), self.params)
        self._check(lib.dct_plant_init(self._p))

        # One buffer over the whole struct; it keeps self._p alive, so the
        # views stay valid even if they outlive this object.
        self._buf = ffi.buffer(self._p)
        self.inputs = np.frombuffer(self._buf, INPUT_DTYPE, 1, _OFF_INPUTS).reshape(())
        self.outputs = np.frombuffer(self._buf, OUTPUT_DTYPE, 1, _OFF_OUTPUTS).reshape(())
        self.state = np.frombuffer(self._buf, np.float64, len(STATE_NAMES), _OFF_STATE)
        # the same memory as flat float64 arrays, in input_names/output_names order
        self.input_values = np.frombuffer(self._buf, np.float64, len(INPUT_NAMES), _OFF_INPUTS)
        self.output_values = np.frombuffer(self._buf, np.float64, len(OUTPUT_NAMES), _OFF_OUTPUTS)
        self.default_inputs = self.inputs.copy()  # the inputs as dct_plant_init left them

    # ------------------------------------------------------------------ errors
    def _check(self, status):
        """Turn a C status into PlantError (the only place that does)."""
        if status == lib.DCT_OK:
            return
        index = self._p.error_index
        if status == lib.DCT_ERR_INPUT:
            name = INPUT_NAMES[index] if 0 <= index < len(INPUT_NAMES) else f"#{index}"
            value = getattr(self._p.inputs, name) if 0 <= index < len(INPUT_NAMES) else math.nan
            raise PlantError(f"input {name} is not finite: {value!r}")
        if status == lib.DCT_ERR_STATE:
            if 0 <= index < len(STATE_NAMES):
                name = STATE_NAMES[index]
                value = float(ffi.cast("double *", ffi.addressof(self._p[0], "state"))[index])
            else:
                name, value = f"#{index}", math.nan
            raise PlantError(
                f"state {name} became {value!r} at t={self._p.state.time_s:.4f} s"
            )
        if status == lib.DCT_ERR_PARAM:
            raise PlantError(
                "parameter check failed: the C core rejected the parameter set "
                "(a value outside its physical range, see check_params in plant/csrc/plant.c)"
            )
        raise PlantError(f"the C core returned unknown status {status}")

    # --------------------------------------------------------------- stepping
    @property
    def time_s(self):
        """Simulated time of the state, s."""
        return float(self._p.state.time_s)

    @property
    def step_s(self):
        """Fixed step of one ``step()``, s (0.5 ms by default)."""
        return float(self._p.params.solver.step_s)

    def step(self, n=1):
        """Advance ``n`` steps in one FFI call; raises PlantError on a bad value."""
        n = _count(n, "n")
        if n:
            self._check(lib.dct_plant_step(self._p, n))

    def reset(self, vehicle_speed_kmh=0.0, sleeves=(0, 0, 0, 0), clutch_locked=(0, 0), engine_on=1,
              coolant_temp_degc=None, engine_oil_temp_degc=None, trans_oil_temp_degc=None):
        """Restart from steady motion: speed, engaged sleeve sides (+1/-1/0), locked clutches.

        The temperatures (degC) start at the parameters' ``thermal.initial_*``;
        each one given replaces its parameter (a cold start:
        ``coolant_temp_degc=20, engine_oil_temp_degc=20, trans_oil_temp_degc=20``)."""
        sleeves = [float(s) for s in sleeves]
        clutch_locked = [float(c) for c in clutch_locked]
        if len(sleeves) != lib.DCT_N_SLEEVES:
            raise ValueError(f"sleeves needs {lib.DCT_N_SLEEVES} values, got {len(sleeves)}")
        if len(clutch_locked) != 2:
            raise ValueError(f"clutch_locked needs 2 values, got {len(clutch_locked)}")
        init = ffi.new(
            "dct_initial *",
            {
                "vehicle_speed_kmh": float(vehicle_speed_kmh),
                "sleeve_side": sleeves,
                "clutch_locked": clutch_locked,
                "engine_on": float(engine_on),
                **self._initial_temperatures(coolant_temp_degc, engine_oil_temp_degc,
                                             trans_oil_temp_degc),
            },
        )
        self._check(lib.dct_plant_reset(self._p, init))

    def _initial_temperatures(self, coolant, engine_oil, trans_oil):
        given = {"coolant_temp_degc": coolant, "engine_oil_temp_degc": engine_oil,
                 "trans_oil_temp_degc": trans_oil}
        if all(v is None for v in given.values()):
            return {"temperatures_given": 0.0}
        out = {"temperatures_given": 1.0}
        for name, value in given.items():
            x = float(self.params["thermal"][f"initial_{name}"] if value is None else value)
            if not (math.isfinite(x) and -60.0 <= x <= 200.0):
                raise ValueError(f"{name} must be a temperature in degC (-60..200), got {value!r}")
            out[name] = x
        return out

    # ----------------------------------------------------------------- faults
    @property
    def faults(self):
        """The physical faults in effect: {name: value, or a list for K1/K2 or
        the four sleeves}; all zero is the healthy car."""
        f = self._p.derived.faults
        return {name: float(getattr(f, name)) if n == 1 else [float(x) for x in getattr(f, name)]
                for name, n in FAULT_FIELDS.items()}

    def set_faults(self, **faults):
        """Put physical faults in effect from the next step; the others stay.

        Names as ``FAULT_NAMES`` (dct_faults in plant/csrc/dct_plant.h). A
        per-clutch or per-sleeve fault takes a list of all its values or
        ``{index: value}`` for some (``fork_jammed={1: 1}``: sleeve 2-4).
        Flags (``spool_stuck``, ``solenoid_open``, ``fork_jammed``,
        ``blocker_failed``, ``engine_torque_limited``) are 0 or 1; losses a
        share 0..1; ``pack_gap_offset_mm`` in mm, the gap staying >= 0;
        ``engine_torque_max_nm`` >= 0. A bad name or value raises ValueError
        and changes nothing.
        """
        wanted = self.faults
        for name, value in faults.items():
            if name not in FAULT_FIELDS:
                raise ValueError(f"unknown fault {name!r}; the faults are {', '.join(FAULT_NAMES)}")
            n = FAULT_FIELDS[name]
            if n == 1:
                wanted[name] = _fault_number(name, value)
            elif isinstance(value, dict):
                for i, v in value.items():
                    if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < n:
                        raise ValueError(f"fault {name}: index {i!r} is not 0..{n - 1}")
                    wanted[name][i] = _fault_number(f"{name}[{i}]", v)
            elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == n:
                wanted[name] = [_fault_number(f"{name}[{i}]", v) for i, v in enumerate(value)]
            else:
                raise ValueError(f"fault {name} needs {n} values (a list) or {{index: value}}, "
                                 f"got {value!r}")
        self._put_faults(wanted)

    def clear_faults(self):
        """The healthy car again: every fault zero (effective params = params, byte for byte)."""
        self._put_faults({name: 0.0 if n == 1 else [0.0] * n for name, n in FAULT_FIELDS.items()})

    def _put_faults(self, values):
        f = self._p.faults
        before = {name: getattr(f, name) if n == 1 else list(getattr(f, name))
                  for name, n in FAULT_FIELDS.items()}
        for name, value in values.items():
            setattr(f, name, value)
        self._p.error_index = -1
        if lib.dct_plant_prepare(self._p) == lib.DCT_OK:
            return
        bad = int(self._p.error_index)
        for name, value in before.items():
            setattr(f, name, value)
        self._check(lib.dct_plant_prepare(self._p))  # the faults as they were
        raise ValueError(self._fault_refused(bad, values))

    def _fault_refused(self, index, values):
        """One line naming the fault value at ``index`` (doubles into dct_faults)."""
        i = 0
        for name, n in FAULT_FIELDS.items():
            if index < i + n:
                k = index - i
                label = name if n == 1 else f"{name}[{k}]"
                value = values[name] if n == 1 else values[name][k]
                if name == "pack_gap_offset_mm":
                    gap = float(self._p.params.clutch[k].pack_gap_mm)
                    rule = f"the pack gap ({gap:g} mm) plus the offset must stay >= 0"
                else:
                    rule = f"it must be {_FAULT_RANGE.get(name, _FLAG_RANGE)}"
                return f"fault {label} = {value!r} refused: {rule}"
            i += n
        return "faults refused by the plant core (dct_faults_check, plant/csrc/faults.c)"

    # ------------------------------------------------------------ save/restore
    def snapshot(self):
        """Copy of state, inputs and outputs: ``restore()`` continues identically
        (the parameters and the faults are not in it: they stay as set)."""
        return self._buf[_SNAP_BEGIN:_SNAP_END]

    def restore(self, snap):
        """Go back to a ``snapshot()`` of a plant with the same parameters."""
        snap = bytes(snap)
        if len(snap) != _SNAP_END - _SNAP_BEGIN:
            raise ValueError(
                f"snapshot has {len(snap)} bytes, expected {_SNAP_END - _SNAP_BEGIN}"
            )
        self._buf[_SNAP_BEGIN:_SNAP_END] = snap

    # ----------------------------------------------------------------- others
    def energy(self):
        """Stored energy (kinetic + springs + gravity), J."""
        return float(lib.dct_plant_energy(self._p))

    def update_outputs(self):
        """Recompute the outputs from the present state and inputs."""
        lib.dct_plant_update_outputs(self._p)

    def bench(self, n, out=None):
        """Run ``n`` single steps timed in C; returns each step's cost in ns."""
        n = _count(n, "n")
        if out is None:
            out = np.empty(n)
        elif out.dtype != np.float64 or not out.flags.c_contiguous or len(out) < n:
            raise ValueError("out must be a contiguous float64 array of at least n items")
        if n:
            self._check(lib.dct_bench_steps(self._p, n, ffi.from_buffer("double[]", out)))
        return out[:n]

    def bench_components(self, n=20000):
        """Each component's share of one step, ns per 0.5 ms step (C clock).

        ``{name: ns}`` in ``COMPONENT_NAMES`` order: the component's output and
        advance functions timed in C on the present state and applied inputs
        (about ``n`` calls each, median over batches, on copies: the plant is
        not changed), times the sub-steps per step. The assembly's own work
        (input limits, state check, outputs) is in no component.
        """
        n = _count(n, "n")
        if n < 1:
            raise ValueError("n must be at least 1")
        out = ffi.new("double[]", lib.DCT_BENCH_N_COMPONENTS)
        self._check(lib.dct_bench_components(self._p, n, out))
        substeps = int(self._p.params.solver.substeps)
        return {name: float(out[i]) * substeps for i, name in enumerate(COMPONENT_NAMES)}

    def state_counts(self, kind=None):
        """State variables per component; see ``state_counts``."""
        return state_counts(kind)

    def __repr__(self):
        return f"<Plant t={self.time_s:.4f} s, step {self.step_s * 1e3:g} ms>"


#: the components of ``Plant.bench_components``, in the assembly's order
COMPONENT_NAMES = [ffi.string(lib.dct_bench_component_name(i)).decode()
                   for i in range(lib.DCT_BENCH_N_COMPONENTS)]

# state struct (first part of a state name) -> component
_STATE_COMPONENT = {
    "time_s": "time", "engine": "engine", "clutch": "clutches", "hydraulics": "hydraulics",
    "gearbox": "gearbox", "driveline": "driveline", "wheel": "wheels", "tyre": "tyres",
    "vehicle": "vehicle", "thermal": "thermal",
}
# states that are not continuous states of the dynamics
_DISCRETE = ("engine.running", ".phase", ".side")            # switch the equations
_BOOKKEEPING = ("time_s", "engine.fuel_g", ".clashes", "vehicle.position_m")  # read, never fed back


def state_kind(name):
    """'continuous', 'discrete' (phase, side, running) or 'bookkeeping'
    (time, fuel burnt, clash count, distance: integrated for the outputs,
    never fed back into the dynamics) for a name of ``STATE_NAMES``."""
    if name not in STATE_NAMES:
        raise ValueError(f"no state named {name!r}")
    if any(name == k or (k.startswith(".") and name.endswith(k)) for k in _BOOKKEEPING):
        return "bookkeeping"
    if any(name == k or (k.startswith(".") and name.endswith(k)) for k in _DISCRETE):
        return "discrete"
    return "continuous"


def state_component(name):
    """The component (a ``COMPONENT_NAMES`` entry, or 'time') a state belongs to."""
    if name not in STATE_NAMES:
        raise ValueError(f"no state named {name!r}")
    return _STATE_COMPONENT[name.split(".")[0].split("[")[0]]


def state_counts(kind=None):
    """Number of state doubles per component, from the layout of ``dct_state``.

    ``{component: count}``: 'time', then ``COMPONENT_NAMES`` order (the
    gearbox includes its four synchronizers). ``kind`` ('continuous',
    'discrete', 'bookkeeping') counts only that kind; None counts all, and
    the counts then sum to ``len(STATE_NAMES)``.
    """
    kinds = ("continuous", "discrete", "bookkeeping")
    if kind is not None and kind not in kinds:
        raise ValueError(f"kind must be one of {', '.join(kinds)} or None, got {kind!r}")
    counts = {name: 0 for name in ["time", *COMPONENT_NAMES]}
    for name in STATE_NAMES:
        if kind is None or state_kind(name) == kind:
            counts[state_component(name)] += 1
    return counts


def build_info():
    """Compiler and flags the C extension was built with."""
    return ffi.string(lib.dct_bench_build_info()).decode()


def _fault_number(label, value):
    if isinstance(value, (str, bytes)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"fault {label} must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"fault {label} must be finite, got {value!r}")
    return x


def _count(n, what):
    try:
        n = operator.index(n)
    except TypeError:
        raise TypeError(f"{what} must be an integer, got {n!r}") from None
    if not 0 <= n <= _INT_MAX:
        raise ValueError(f"{what} must be between 0 and {_INT_MAX}, got {n}")
    return n
