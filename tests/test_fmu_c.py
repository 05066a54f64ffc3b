"""The FMU's C side (plant/fmu/csrc: fmi2.c, fmi3.c, fmu_instance.c) without
an FMU file or an importer: the FMI 2 and FMI 3 libraries compiled with gcc
from the sources and the table plant/fmu/variables.py generates, driven
through ctypes.

Covered for both versions: the library exports the FMI functions and
nothing else; instantiation (a foreign token refused), initialization
(initial conditions and parameters set before it, inputs set before it
written after the reset), DoStep (a step that is no multiple of the plant's
refused with the message the logger gets), variables (NaN, range, unknown
value references, fixed and tunable parameters), the call sequence, the
saved and serialized FMU states, the error state after a failed step, two
instances side by side, and the run itself bit for bit against
plant.model.Plant and plant.simulate.
"""

import ctypes
import math
import re
import struct
import subprocess
from ctypes import (
    CFUNCTYPE,
    POINTER,
    Structure,
    byref,
    c_bool,
    c_char,
    c_char_p,
    c_double,
    c_int,
    c_int32,
    c_size_t,
    c_uint,
    c_uint32,
    c_void_p,
)
from pathlib import Path

import numpy as np
import pytest
import requires

from plant import simulate
from plant._dct_plant import ffi
from plant.fmu import scenario as fmu_scenario
from plant.fmu import variables
from plant.model import Plant
from plant.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PLANT_CSRC = ROOT / "plant" / "csrc"
FMU_CSRC = ROOT / "plant" / "fmu" / "csrc"
CFLAGS = ["-std=c11", "-O2", "-fPIC", "-shared", "-fvisibility=hidden", "-Wall", "-Wextra"]
VERSIONS = (2, 3)
OK, WARNING, DISCARD, ERROR, FATAL = range(5)

#: every function of the FMI 3.0 API (an importer binds them all by name)
FMI3_API = """
GetVersion SetDebugLogging InstantiateModelExchange InstantiateCoSimulation
InstantiateScheduledExecution FreeInstance EnterInitializationMode ExitInitializationMode
EnterEventMode Terminate Reset GetFloat32 GetFloat64 GetInt8 GetUInt8 GetInt16 GetUInt16
GetInt32 GetUInt32 GetInt64 GetUInt64 GetBoolean GetString GetBinary GetClock SetFloat32
SetFloat64 SetInt8 SetUInt8 SetInt16 SetUInt16 SetInt32 SetUInt32 SetInt64 SetUInt64 SetBoolean
SetString SetBinary SetClock GetNumberOfVariableDependencies GetVariableDependencies
GetFMUState SetFMUState FreeFMUState SerializedFMUStateSize SerializeFMUState
DeserializeFMUState GetDirectionalDerivative GetAdjointDerivative EnterConfigurationMode
ExitConfigurationMode GetIntervalDecimal GetIntervalFraction GetShiftDecimal GetShiftFraction
SetIntervalDecimal SetIntervalFraction SetShiftDecimal SetShiftFraction EvaluateDiscreteStates
UpdateDiscreteStates EnterContinuousTimeMode CompletedIntegratorStep SetTime
SetContinuousStates GetContinuousStateDerivatives GetEventIndicators GetContinuousStates
GetNominalsOfContinuousStates GetNumberOfEventIndicators GetNumberOfContinuousStates
EnterStepMode GetOutputDerivatives DoStep ActivateModelPartition
""".split()
#: the FMI 2.0 common and co-simulation functions
FMI2_API = """
GetTypesPlatform GetVersion SetDebugLogging Instantiate FreeInstance SetupExperiment
EnterInitializationMode ExitInitializationMode Terminate Reset GetReal GetInteger GetBoolean
GetString SetReal SetInteger SetBoolean SetString GetFMUstate SetFMUstate FreeFMUstate
SerializedFMUstateSize SerializeFMUstate DeSerializeFMUstate GetDirectionalDerivative
SetRealInputDerivatives GetRealOutputDerivatives DoStep CancelStep GetStatus GetRealStatus
GetIntegerStatus GetBooleanStatus GetStringStatus
""".split()

# -- the libraries --------------------------------------------------------------


@pytest.fixture(scope="module")
def model():
    return variables.load()


@pytest.fixture(scope="module")
def built(tmp_path_factory, model):
    """{version: path of the .so}, compiled as the brief of fmi2.c/fmi3.c says."""
    gcc = requires.c_compiler()
    d = tmp_path_factory.mktemp("fmu_c")
    table = d / "fmu_variables.c"
    table.write_text(variables.generate_c(model=model), encoding="utf-8")
    core = sorted(str(p) for p in PLANT_CSRC.glob("*.c") if p.name != "dct_bench.c")
    out = {}
    for v in VERSIONS:
        so = d / f"dct_plant_fmi{v}.so"
        cmd = [gcc, *CFLAGS, "-I", str(PLANT_CSRC), "-I", str(FMU_CSRC), "-o", str(so),
               str(FMU_CSRC / f"fmi{v}.c"), str(FMU_CSRC / "fmu_instance.c"), str(table),
               *core, "-lm"]
        run = subprocess.run(cmd, capture_output=True, text=True, check=False)
        assert run.returncode == 0, run.stderr
        assert run.stderr == "", f"FMI {v}: the build warns:\n{run.stderr}"
        out[v] = so
    return out


LOG2 = CFUNCTYPE(None, c_void_p, c_char_p, c_int, c_char_p, c_char_p)
LOG3 = CFUNCTYPE(None, c_void_p, c_int, c_char_p, c_char_p)


class CALLBACKS2(Structure):
    _fields_ = [("logger", LOG2), ("allocateMemory", c_void_p), ("freeMemory", c_void_p),
                ("stepFinished", c_void_p), ("componentEnvironment", c_void_p)]


def _bind(lib, version):
    V, I, D, S = c_void_p, c_int, c_double, c_size_t  # noqa: E741 (I: the C int, beside V, D, S)
    if version == 2:
        VR = POINTER(c_uint)
        sig = {
            "GetVersion": (c_char_p, []), "GetTypesPlatform": (c_char_p, []),
            "Instantiate": (V, [c_char_p, I, c_char_p, c_char_p, POINTER(CALLBACKS2), I, I]),
            "FreeInstance": (None, [V]),
            "SetDebugLogging": (I, [V, I, S, POINTER(c_char_p)]),
            "SetupExperiment": (I, [V, I, D, D, I, D]),
            "EnterInitializationMode": (I, [V]), "ExitInitializationMode": (I, [V]),
            "Terminate": (I, [V]), "Reset": (I, [V]),
            "GetReal": (I, [V, VR, S, POINTER(D)]), "SetReal": (I, [V, VR, S, POINTER(D)]),
            "GetInteger": (I, [V, VR, S, POINTER(I)]), "SetInteger": (I, [V, VR, S, POINTER(I)]),
            "GetBoolean": (I, [V, VR, S, POINTER(I)]),
            "DoStep": (I, [V, D, D, I]), "CancelStep": (I, [V]),
            "GetFMUstate": (I, [V, POINTER(V)]), "SetFMUstate": (I, [V, V]),
            "FreeFMUstate": (I, [V, POINTER(V)]),
            "SerializedFMUstateSize": (I, [V, V, POINTER(S)]),
            "SerializeFMUstate": (I, [V, V, V, S]),
            "DeSerializeFMUstate": (I, [V, c_char_p, S, POINTER(V)]),
            "GetRealStatus": (I, [V, I, POINTER(D)]), "GetBooleanStatus": (I, [V, I, POINTER(I)]),
            "GetDirectionalDerivative": (I, [V, VR, S, VR, S, POINTER(D), POINTER(D)]),
        }
    else:
        VR = POINTER(c_uint32)
        B = c_bool
        sig = {
            "GetVersion": (c_char_p, []),
            "InstantiateCoSimulation": (V, [c_char_p, c_char_p, c_char_p, B, B, B, B, VR, S, V,
                                            LOG3, V]),
            "InstantiateModelExchange": (V, [c_char_p, c_char_p, c_char_p, B, B, V, LOG3]),
            "FreeInstance": (None, [V]),
            "SetDebugLogging": (I, [V, B, S, POINTER(c_char_p)]),
            "EnterInitializationMode": (I, [V, B, D, D, B, D]),
            "ExitInitializationMode": (I, [V]), "Terminate": (I, [V]), "Reset": (I, [V]),
            "GetFloat64": (I, [V, VR, S, POINTER(D), S]), "SetFloat64": (I, [V, VR, S, POINTER(D), S]),
            "GetInt32": (I, [V, VR, S, POINTER(c_int32), S]),
            "SetBoolean": (I, [V, VR, S, POINTER(B), S]),
            "DoStep": (I, [V, D, D, B, POINTER(B), POINTER(B), POINTER(B), POINTER(D)]),
            "EnterEventMode": (I, [V]), "EnterStepMode": (I, [V]), "SetTime": (I, [V, D]),
            "GetFMUState": (I, [V, POINTER(V)]), "SetFMUState": (I, [V, V]),
            "FreeFMUState": (I, [V, POINTER(V)]),
            "SerializedFMUStateSize": (I, [V, V, POINTER(S)]),
            "SerializeFMUState": (I, [V, V, V, S]),
            "DeserializeFMUState": (I, [V, c_char_p, S, POINTER(V)]),
        }
    for name, (res, args) in sig.items():
        f = getattr(lib, f"fmi{version}{name}")
        f.restype, f.argtypes = res, args


@pytest.fixture(scope="module")
def libs(built):
    out = {}
    for v, so in built.items():
        lib = ctypes.CDLL(str(so))
        _bind(lib, v)
        out[v] = lib
    return out


# -- one instance through ctypes, the same calls for both versions ---------------

class Instance:
    def __init__(self, lib, version, model, name="dct", token=None, logging_on=False,
                 fmu_type=1, event_mode_used=False, logger=True):
        self.lib, self.version, self.model = lib, version, model
        self.vrs = {v.name: v.vr for v in model.variables}
        self.messages = []          # (status, category, message)
        self.token = model.token if token is None else token
        self.last_successful_time = None
        if version == 2:
            def log(env, inst, status, category, message):
                self.messages.append((status, category.decode(), message.decode()))
            self._log = LOG2(log)
            self._cb = CALLBACKS2(self._log, None, None, None, None)
            if not logger:
                self._cb = CALLBACKS2()
            self.c = lib.fmi2Instantiate(name.encode(), fmu_type, self.token.encode(), b"",
                                         byref(self._cb), 0, int(logging_on))
        else:
            def log(env, status, category, message):
                self.messages.append((status, category.decode(), message.decode()))
            self._log = LOG3(log) if logger else LOG3()
            self.c = lib.fmi3InstantiateCoSimulation(name.encode(), self.token.encode(), b"",
                                                     False, logging_on, event_mode_used, False,
                                                     None, 0, None, self._log, None)

    def f(self, name):
        return getattr(self.lib, f"fmi{self.version}{name}")

    @property
    def errors(self):
        return [m for s, _, m in self.messages if s >= ERROR]

    def last(self):
        return self.messages[-1][2] if self.messages else None

    # modes
    def enter_init(self, start=0.0, stop=None):
        if self.version == 2:
            st = self.f("SetupExperiment")(self.c, 0, 0.0, start, stop is not None,
                                           0.0 if stop is None else stop)
            if st != OK:
                return st
            return self.f("EnterInitializationMode")(self.c)
        return self.f("EnterInitializationMode")(self.c, False, 0.0, start, stop is not None,
                                                 0.0 if stop is None else stop)

    def exit_init(self):
        return self.f("ExitInitializationMode")(self.c)

    def initialize(self, values=None, start=0.0, stop=None):
        assert self.enter_init(start, stop) == OK, self.messages
        if values:
            assert self.set(values) == OK, self.messages
        assert self.exit_init() == OK, self.messages

    def terminate(self):
        return self.f("Terminate")(self.c)

    def reset(self):
        return self.f("Reset")(self.c)

    def free(self):
        if self.c:
            self.f("FreeInstance")(self.c)
            self.c = None

    # variables
    def _vr_array(self, vrs):
        return ((c_uint if self.version == 2 else c_uint32) * len(vrs))(*vrs)

    def get_vrs(self, vrs):
        values = (c_double * len(vrs))()
        if self.version == 2:
            st = self.f("GetReal")(self.c, self._vr_array(vrs), len(vrs), values)
        else:
            st = self.f("GetFloat64")(self.c, self._vr_array(vrs), len(vrs), values, len(vrs))
        return st, np.array(values[:])

    def get(self, *names):
        st, values = self.get_vrs([self.vrs[n] for n in names])
        assert st == OK, self.messages
        return values if len(names) > 1 else float(values[0])

    def set_vrs(self, vrs, values):
        arr = (c_double * len(values))(*values)
        if self.version == 2:
            return self.f("SetReal")(self.c, self._vr_array(vrs), len(vrs), arr)
        return self.f("SetFloat64")(self.c, self._vr_array(vrs), len(vrs), arr, len(values))

    def set(self, values):
        return self.set_vrs([self.vrs[n] for n in values], list(values.values()))

    @property
    def time(self):
        return self.get("time")

    def do_step(self, t, h):
        if self.version == 2:
            return self.f("DoStep")(self.c, t, h, 1)
        flags = [c_bool(True) for _ in range(3)]
        last = c_double(math.nan)
        st = self.f("DoStep")(self.c, t, h, True, *(byref(x) for x in flags), byref(last))
        assert not any(x.value for x in flags)
        self.last_successful_time = last.value
        return st

    def step(self, h):
        st = self.do_step(self.time, h)
        assert st == OK, self.messages
        return st

    # FMU states
    def get_state(self, state=None):
        s = c_void_p(state)
        st = self.f("GetFMUstate" if self.version == 2 else "GetFMUState")(self.c, byref(s))
        assert st == OK, self.messages
        return s.value

    def set_state(self, state):
        return self.f("SetFMUstate" if self.version == 2 else "SetFMUState")(self.c, state)

    def free_state(self, state):
        s = c_void_p(state)
        st = self.f("FreeFMUstate" if self.version == 2 else "FreeFMUState")(self.c, byref(s))
        assert s.value is None
        return st

    def serialize(self, state):
        n = c_size_t()
        size_fn = "SerializedFMUstateSize" if self.version == 2 else "SerializedFMUStateSize"
        assert self.f(size_fn)(self.c, state, byref(n)) == OK, self.messages
        buf = (c_char * n.value)()
        ser_fn = "SerializeFMUstate" if self.version == 2 else "SerializeFMUState"
        assert self.f(ser_fn)(self.c, state, buf, n.value) == OK, self.messages
        return bytes(buf)

    def deserialize(self, data):
        s = c_void_p()
        fn = "DeSerializeFMUstate" if self.version == 2 else "DeserializeFMUState"
        st = self.f(fn)(self.c, data, len(data), byref(s))
        return st, s.value


@pytest.fixture
def make(libs, model):
    """make(version, **kw) -> an Instance, freed at the end of the test."""
    made = []

    def _make(version, **kw):
        inst = Instance(libs[version], version, model, **kw)
        made.append(inst)
        return inst
    yield _make
    for inst in made:
        inst.free()


def _bits(a):
    """The bytes of a float array: equality of these is bit for bit (-0.0, NaN)."""
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def _output_names(model):
    inputs = {v.name for v in model.variables if v.kind == variables.INPUT}
    return [f"out.{n}" if n in inputs else n for n in Plant.output_names]


# -- the library ------------------------------------------------------------------

@pytest.mark.slow
def test_libraries_export_the_fmi_functions_and_nothing_else(built):
    nm = requires.tool("nm", "apt-get install binutils (it comes with gcc)")
    for v, so in built.items():
        out = subprocess.run([nm, "-D", "--defined-only", str(so)], capture_output=True,
                             text=True, check=True).stdout
        names = {line.split()[-1] for line in out.splitlines() if line.strip()}
        api = {f"fmi{v}{n}" for n in (FMI2_API if v == 2 else FMI3_API)}
        assert names == api, (sorted(names - api), sorted(api - names))


def test_versions_and_platform(libs):
    assert libs[2].fmi2GetVersion() == b"2.0"
    assert libs[2].fmi2GetTypesPlatform() == b"default"
    assert libs[3].fmi3GetVersion() == b"3.0"


# -- instantiation ----------------------------------------------------------------

@pytest.mark.parametrize("version", VERSIONS)
def test_defaults_readable_before_initialization(make, model, version):
    f = make(version)
    assert f.c
    plant = Plant()
    assert f.get("engine_on") == 1.0 and f.get("accel_pedal_pct") == 0.0
    assert f.get("engine_speed_rpm") == float(plant.outputs["engine_speed_rpm"])
    assert f.get("engine.idle_speed_rpm") == plant.params["engine"]["idle_speed_rpm"]
    assert f.get("initial.engine_on") == 1.0
    assert f.time == 0.0


@pytest.mark.parametrize("version", VERSIONS)
def test_foreign_token_refused(make, version):
    f = make(version, token="{00000000-0000-0000-0000-000000000000}")
    assert not f.c
    word = "GUID" if version == 2 else "instantiationToken"
    assert len(f.errors) == 1
    assert f.errors[0].startswith(f"fmi{version}Instantiate")
    assert f'{word} "{{00000000-0000-0000-0000-000000000000}}" is not this FMU' in f.errors[0]
    assert f.messages[0][1] == "logStatusError"


def test_fmi2_refuses_model_exchange_and_a_missing_logger(make):
    f = make(2, fmu_type=0)
    assert not f.c and "co-simulation only" in f.errors[0]
    assert not make(2, logger=False).c          # nobody to tell: NULL, silently


def test_fmi3_refuses_event_mode_and_other_interface_types(make, libs, model):
    f = make(3, event_mode_used=True)
    assert not f.c and "eventModeUsed refused" in f.errors[0]
    got = []
    log = LOG3(lambda env, st, cat, msg: got.append(msg.decode()))
    assert not libs[3].fmi3InstantiateModelExchange(b"me", model.token.encode(), b"", False,
                                                   False, None, log)
    assert "co-simulation only" in got[0]
    g = make(3, logger=False)                   # FMI 3 allows no logger: no messages
    assert g.c
    g.initialize()
    assert g.do_step(0.0, 0.0007) == ERROR      # refused, told to no one


@pytest.mark.parametrize("version", VERSIONS)
def test_percent_in_a_message_reaches_the_logger_as_text(make, version):
    f = make(version, token="x%sy%n")
    assert not f.c
    # FMI 2's logger takes a format: the '%' doubled, no conversion left
    assert ("x%%sy%%n" if version == 2 else "x%sy%n") in f.errors[0]


# -- initialization and stepping ----------------------------------------------------

@pytest.mark.parametrize("version", VERSIONS)
def test_initialize_step_get(make, version):
    f = make(version)
    f.initialize({"accel_pedal_pct": 20.0})
    assert f.time == 0.0
    rpm0 = f.get("engine_speed_rpm")
    for _ in range(50):
        f.step(0.01)
    assert f.time == 0.5
    assert f.get("accel_pedal_pct") == 20.0 and f.get("out.accel_pedal_pct") == 20.0
    assert f.get("time_s") == pytest.approx(0.5)
    out = f.get(*_output_names(f.model))
    assert np.all(np.isfinite(out))
    assert f.get("engine_speed_rpm") > rpm0 + 250   # the pedal revs the engine in neutral (against the alternator and the transmission's pump)
    if version == 3:
        assert f.last_successful_time == 0.5
    assert f.terminate() == OK


@pytest.mark.parametrize("version", VERSIONS)
def test_time_is_counted_from_the_start_time(make, version):
    f = make(version)
    f.initialize(start=10.0)
    assert f.time == 10.0
    assert f.do_step(0.0, 0.01) == ERROR
    assert "currentCommunicationPoint 0 s is not the FMU's time 10 s" in f.last()
    t = 10.0
    for _ in range(200):
        assert f.do_step(t, 0.01) == OK
        t += 0.01                               # the master's sum drifts ...
    assert t != 12.0 and abs(t - 12.0) < 1e-9
    assert f.time == 10.0 + 4000 * 0.0005       # ... the FMU's time is counted


@pytest.mark.parametrize("version", VERSIONS)
def test_step_not_a_multiple_of_the_plant_step_refused(make, version):
    f = make(version)
    f.initialize()
    assert f.do_step(0.0, 0.0007) == ERROR
    assert f.messages[-1] == (ERROR, "logStatusError",
                              f"fmi{version}DoStep: communication step 0.0007 s is not a "
                              "multiple of the plant's 0.0005 s step")
    for h in (0.0, -0.01, math.nan, math.inf, 0.0002):
        assert f.do_step(0.0, h) == ERROR
    assert f.do_step(0.3, 0.01) == ERROR and "is not the FMU's time" in f.last()
    assert f.time == 0.0
    # refusals leave the instance usable; a step off by a few ulps is a multiple
    assert f.do_step(1e-12, 0.3 - 0.2) == OK
    assert f.time == 0.1


@pytest.mark.parametrize("version", VERSIONS)
def test_stop_time_refuses_steps_beyond_it(make, version):
    f = make(version)
    f.initialize(stop=0.02)
    f.step(0.02)
    assert f.do_step(0.02, 0.01) == ERROR and "past the stop time 0.02 s" in f.last()


@pytest.mark.parametrize("version", VERSIONS)
def test_call_sequence_checked(make, version):
    f = make(version)
    assert f.do_step(0.0, 0.01) == ERROR
    assert f.last() == f"fmi{version}DoStep: not allowed before initialization (the instance is only instantiated)"
    assert f.exit_init() == ERROR and "ExitInitializationMode: not allowed" in f.last()
    assert f.terminate() == ERROR
    assert f.enter_init() == OK
    assert f.enter_init() == ERROR
    assert f.do_step(0.0, 0.01) == ERROR and "in initialization mode" in f.last()
    assert f.exit_init() == OK
    assert f.exit_init() == ERROR
    f.step(0.01)
    assert f.terminate() == OK
    assert f.do_step(0.01, 0.01) == ERROR and "after Terminate" in f.last()
    assert f.set({"accel_pedal_pct": 10.0}) == ERROR
    assert f.get("engine_speed_rpm") > 0          # getters still work
    # Reset: instantiated again, the same run again
    assert f.reset() == OK
    assert f.time == 0.0 and f.get("accel_pedal_pct") == 0.0
    f.initialize()
    f.step(0.01)
    g = make(version)
    g.initialize()
    g.step(0.01)
    names = _output_names(f.model)
    assert _bits(f.get(*names)) == _bits(g.get(*names))


@pytest.mark.parametrize("version", VERSIONS)
def test_logging_info_only_when_on(make, version):
    quiet = make(version)
    quiet.initialize()
    assert quiet.messages == []
    loud = make(version, logging_on=True)
    loud.initialize()
    assert (OK, "logEvents") in [(s, c) for s, c, _ in loud.messages]
    assert any("initialized at t=0 s" in m for _, _, m in loud.messages)
    # only logStatusError named: info off, errors still logged
    cats = (c_char_p * 1)(b"logStatusError")
    assert loud.f("SetDebugLogging")(loud.c, True, 1, cats) == OK
    n = len(loud.messages)
    assert loud.terminate() == OK and len(loud.messages) == n
    bad = (c_char_p * 1)(b"logEverything")
    assert loud.f("SetDebugLogging")(loud.c, True, 1, bad) == WARNING
    assert "unknown log category" in loud.last()


# -- variables -------------------------------------------------------------------

@pytest.mark.parametrize("version", VERSIONS)
def test_nan_and_infinite_inputs_refused(make, version):
    f = make(version)
    f.initialize({"accel_pedal_pct": 30.0})
    f.step(0.1)
    for bad in (math.nan, math.inf, -math.inf):
        assert f.set({"accel_pedal_pct": bad}) == ERROR
        assert f.last().startswith(f"fmi{version}Set")
        assert "input accel_pedal_pct" in f.last() and "not a finite number" in f.last()
        assert f.get("accel_pedal_pct") == 30.0
    # a call with a bad value writes none of its values
    assert f.set({"brake_pedal_pct": 50.0, "road_grade_pct": math.nan}) == ERROR
    assert f.get("brake_pedal_pct") == 0.0
    f.step(0.1)
    assert np.all(np.isfinite(f.get(*_output_names(f.model))))


@pytest.mark.parametrize("version", VERSIONS)
def test_outputs_and_time_cannot_be_set(make, version):
    f = make(version)
    assert f.set({"engine_speed_rpm": 1000.0}) == ERROR
    assert "engine_speed_rpm cannot be set: it is an output" in f.last()
    assert f.set({"time": 1.0}) == ERROR and "time cannot be set" in f.last()


@pytest.mark.parametrize("version", VERSIONS)
def test_unknown_value_references(make, model, version):
    f = make(version)
    n = len(model.variables)
    st, _ = f.get_vrs([1, n])
    assert st == ERROR and f.last() == (f"fmi{version}{'GetReal' if version == 2 else 'GetFloat64'}"
                                        f": value reference {n} does not exist (this FMU has "
                                        f"0..{n - 1})")
    assert f.set_vrs([n + 5], [1.0]) == ERROR and f"value reference {n + 5} does not exist" in f.last()
    # no Integer / Int32 variables: any value reference names none, none given is fine
    vr = f._vr_array([1])
    value = (c_int * 1)() if version == 2 else (c_int32 * 1)()
    if version == 2:
        assert f.f("GetInteger")(f.c, vr, 1, value) == ERROR
        assert f.f("GetInteger")(f.c, None, 0, None) == OK
    else:
        assert f.f("GetInt32")(f.c, vr, 1, value, 1) == ERROR
        assert f.f("GetInt32")(f.c, None, 0, None, 0) == OK
    assert "value reference 1 does not exist as an" in f.last()


@pytest.mark.parametrize("version", VERSIONS)
def test_values_outside_the_range_refused(make, version):
    f = make(version)
    assert f.set({"clutch[0].mu_static": 0.5}) == ERROR
    assert "clutch[0].mu_static = 0.5 refused: outside its range" in f.last()
    assert f.set({"initial.sleeve_side[0]": 2.0}) == ERROR
    assert f.get("clutch[0].mu_static") == 0.11 and f.get("initial.sleeve_side[0]") == 0.0


@pytest.mark.parametrize("version", VERSIONS)
def test_fixed_parameter_before_initialization_only(make, version):
    f = make(version)
    f.initialize({"hydraulics.pressure_commanded": 1.0, "clutch1_pressure_bar": 5.0})
    f.step(0.1)
    assert f.get("clutch1_pressure_bar") == 5.0    # the pressure commanded directly
    assert f.set({"hydraulics.pressure_commanded": 0.0}) == ERROR
    assert ("fixed parameter hydraulics.pressure_commanded cannot be set once initialized"
            in f.last())
    assert f.set({"initial.vehicle_speed_kmh": 50.0}) == ERROR
    assert f.get("hydraulics.pressure_commanded") == 1.0


@pytest.mark.parametrize("version", VERSIONS)
def test_tunable_parameter_while_stepping(make, version):
    f = make(version)
    ref = make(version)
    for x in (f, ref):
        x.initialize()
        x.step(0.1)
    assert f.set({"engine.idle_speed_rpm": 900.0}) == OK
    assert f.get("engine.idle_speed_rpm") == 900.0
    # refused by the plant's check (the pack gap would be negative): the old value kept
    assert f.set({"faults.pack_gap_offset_mm[0]": -1000.0}) == ERROR
    assert re.search(r"faults\.pack_gap_offset_mm\[0\] = -1000 refused by the plant's "
                     r"parameter check .*it keeps 0$", f.last())
    assert f.get("faults.pack_gap_offset_mm[0]") == 0.0
    assert ref.set({"faults.pack_gap_offset_mm[0]": -1000.0}) == ERROR
    for x in (f, ref):
        x.step(3.0)
    assert f.get("engine_speed_rpm") == pytest.approx(900.0, abs=5.0)
    assert ref.get("engine_speed_rpm") == pytest.approx(750.0, abs=5.0)
    # the refused fault changed nothing: ref runs as a fresh instance does
    fresh = make(version)
    fresh.initialize()
    fresh.step(0.1)
    fresh.step(3.0)
    names = _output_names(f.model)
    assert _bits(ref.get(*names)) == _bits(fresh.get(*names))


@pytest.mark.parametrize("version", VERSIONS)
def test_parameter_check_failure_at_initialization(make, version):
    f = make(version)
    assert f.enter_init() == OK
    assert f.set({"faults.pack_gap_offset_mm[1]": -1000.0}) == OK   # checked at the end
    assert f.exit_init() == ERROR
    assert f.last().startswith(f"fmi{version}ExitInitializationMode: parameter check failed:")
    assert "changed: faults.pack_gap_offset_mm[1] = -1000" in f.last()
    assert f.do_step(0.0, 0.01) == ERROR and "error state" in f.last()
    assert f.reset() == OK
    f.initialize()
    f.step(0.01)


@pytest.mark.parametrize("version", VERSIONS)
def test_inputs_set_before_initialization_written_after_the_reset(make, version):
    f = make(version)
    # initial.engine_on 1 (the reset sets input engine_on to 1), input engine_on set to 0:
    # the input set wins; the outputs at the start are the reset's (engine running)
    f.initialize({"engine_on": 0.0, "accel_pedal_pct": 40.0})
    assert f.get("engine_on") == 0.0 and f.get("accel_pedal_pct") == 40.0
    assert f.get("engine_running") == 1.0 and f.get("out.accel_pedal_pct") == 0.0
    # not set: the input is what the reset leaves (engine_on from the initial conditions)
    g = make(version)
    g.initialize({"initial.engine_on": 0.0})
    assert g.get("engine_on") == 0.0 and g.get("engine_running") == 0.0


@pytest.mark.parametrize("version", VERSIONS)
def test_initial_conditions(make, version):
    f = make(version)
    f.initialize({"initial.vehicle_speed_kmh": 50.0, "initial.sleeve_side[1]": 1.0,
                  "initial.clutch_locked[1]": 1.0})
    assert f.get("vehicle_speed_kmh") == pytest.approx(50.0)
    assert f.get("gear") == 2.0


# -- instances side by side --------------------------------------------------------------

@pytest.mark.parametrize("version", VERSIONS)
def test_two_instances_run_independently(make, version):
    names = _output_names(make(version).model)

    def setup(f, which):
        if which == "a":
            f.initialize({"accel_pedal_pct": 30.0})
        else:
            f.initialize({"initial.vehicle_speed_kmh": 40.0, "initial.sleeve_side[0]": -1.0,
                          "brake_pedal_pct": 20.0})

    alone = {}
    for which in "ab":
        f = make(version, name=which)
        setup(f, which)
        rows = []
        for _ in range(40):
            f.step(0.01)
            rows.append(f.get(*names))
        alone[which] = _bits(np.array(rows))
        f.free()
    a, b = make(version, name="a"), make(version, name="b")
    setup(a, "a")
    setup(b, "b")
    rows = {"a": [], "b": []}
    for _ in range(40):
        for which, f in (("b", b), ("a", a)):
            f.step(0.01)
            rows[which].append(f.get(*names))
    assert _bits(np.array(rows["a"])) == alone["a"]
    assert _bits(np.array(rows["b"])) == alone["b"]
    assert alone["a"] != alone["b"]


# -- FMU states ----------------------------------------------------------------------

def _run(f, n, h=0.01):
    names = _output_names(f.model)
    rows = []
    for _ in range(n):
        f.step(h)
        rows.append(f.get(*names))
    return _bits(np.array(rows))


@pytest.mark.parametrize("version", VERSIONS)
def test_get_and_set_fmu_state_reproduce_a_run(make, version):
    f = make(version)
    early = f.get_state()                       # taken while only instantiated
    f.initialize({"accel_pedal_pct": 25.0, "initial.vehicle_speed_kmh": 20.0,
                  "initial.sleeve_side[0]": 1.0, "initial.clutch_locked[0]": 1.0})
    f.step(0.2)
    saved = f.get_state()
    first = _run(f, 30)
    t = f.time
    assert f.set_state(saved) == OK
    assert f.time == pytest.approx(0.2)
    assert _run(f, 30) == first
    assert f.time == t
    # a state saved again overwrites the one given
    assert f.get_state(saved) == saved
    # the mode is part of the state: back to instantiated
    assert f.set_state(early) == OK
    assert f.do_step(f.time, 0.01) == ERROR and "before initialization" in f.last()
    assert f.free_state(saved) == OK and f.free_state(early) == OK
    assert f.free_state(None) == OK


@pytest.mark.parametrize("version", VERSIONS)
def test_serialized_state_round_trip_in_another_instance(make, version):
    f = make(version)
    f.initialize({"accel_pedal_pct": 25.0})
    f.step(0.2)
    state = f.get_state()
    data = f.serialize(state)
    first = _run(f, 30)
    g = make(version)                           # a fresh instance, only instantiated
    st, restored = g.deserialize(data)
    assert st == OK and restored
    assert g.set_state(restored) == OK
    assert g.time == pytest.approx(0.2)
    assert _run(g, 30) == first
    assert g.serialize(restored) == data
    g.free_state(restored)
    f.free_state(state)


def _fnv1a(data):
    h = 14695981039346656037
    for b in data:
        h = ((h ^ b) * 1099511628211) & 0xFFFFFFFFFFFFFFFF
    return h


def _with_checksum(body):
    return body + struct.pack("=Q", _fnv1a(body))


@pytest.mark.parametrize("version", VERSIONS)
def test_damaged_or_foreign_serialized_state_refused(make, model, version):
    f = make(version)
    f.initialize()
    state = f.get_state()
    data = f.serialize(state)
    fn = "fmi2DeSerializeFMUstate" if version == 2 else "fmi3DeserializeFMUState"
    body = bytearray(data[:-8])
    body[-100] ^= 0x01
    cases = {
        "checksum mismatch: the serialized state is damaged": bytes(body) + data[-8:],
        "wrong magic": b"X" + data[1:],
        "too few for a serialized FMU state": data[:20],
        "a serialized state of this FMU has": data[:-1],
        "serialization format 7": data[:8] + struct.pack("=I", 7) + data[12:],
        "the state's dct_plant has 12 bytes": data[:16] + struct.pack("=Q", 12) + data[24:],
    }
    token = model.token.encode()
    other = token.replace(token[1:9], b"01234567")
    cases[f'the state\'s token "{other.decode()}" is not this FMU\'s'] = _with_checksum(
        data[:-8].replace(token, other))
    for what, bad in cases.items():
        st, s = f.deserialize(bad)
        assert st == ERROR and s is None, what
        assert f.last().startswith(f"{fn}: ") and what in f.last(), (what, f.last())
    f.free_state(state)


@pytest.mark.parametrize("version", VERSIONS)
def test_failed_step_puts_the_instance_in_the_error_state(make, model, version):
    f = make(version)
    f.initialize()
    f.step(0.01)
    good = f.get_state()
    data = bytearray(f.serialize(good))
    # a state holding a NaN (checksum made right): the step finds it
    index = Plant.state_names.index("engine.speed_rad_s")
    at = 36 + len(model.token) + ffi.offsetof("dct_plant", "state") + 8 * index
    data[at:at + 8] = struct.pack("=d", math.nan)
    st, poisoned = f.deserialize(_with_checksum(bytes(data[:-8])))
    assert st == OK
    assert f.set_state(poisoned) == OK
    assert f.do_step(0.01, 0.01) == ERROR
    assert re.fullmatch(rf"fmi{version}DoStep: state engine\.speed_rad_s became -?nan at "
                        r"t=0\.010\d s", f.last()), f.last()
    if version == 3:
        assert f.last_successful_time == 0.01
    else:
        t = c_double()
        assert f.f("GetRealStatus")(f.c, 2, byref(t)) == OK and t.value == 0.01
    assert f.time == 0.01                          # the last time with a finite state
    assert f.do_step(0.01, 0.01) == ERROR and "error state" in f.last()
    assert f.set({"accel_pedal_pct": 1.0}) == ERROR
    s = c_void_p()
    get_fn = "GetFMUstate" if version == 2 else "GetFMUState"
    assert f.f(get_fn)(f.c, byref(s)) == ERROR and s.value is None
    f.get("engine_speed_rpm")                      # getters still answer
    # a good saved state brings it back
    assert f.set_state(good) == OK
    f.step(0.01)
    f.free_state(good)
    f.free_state(poisoned)


# -- bit for bit with the plant's own Python binding ------------------------------------

@pytest.mark.parametrize("version", VERSIONS)
def test_bit_for_bit_with_plant_model(make, version):
    f = make(version)
    names = _output_names(f.model)
    plant = Plant()
    plant.inputs[()] = plant.default_inputs
    plant.reset(vehicle_speed_kmh=30.0, sleeves=(0, 1, 0, 0), clutch_locked=(0, 1), engine_on=1)
    plant.inputs["accel_pedal_pct"] = 15.0
    plant.inputs["solenoid_current2_a"] = 0.9
    f.initialize({"initial.vehicle_speed_kmh": 30.0, "initial.sleeve_side[1]": 1.0,
                  "initial.clutch_locked[1]": 1.0, "accel_pedal_pct": 15.0,
                  "solenoid_current2_a": 0.9})

    def same():
        assert _bits(f.get(*names)) == _bits(plant.output_values)

    same()
    plant.step(200)
    f.step(0.1)
    same()
    plant.set_faults(friction_loss={1: 0.3})
    assert f.set({"faults.friction_loss[1]": 0.3}) == OK
    plant.inputs["brake_pedal_pct"] = 10.0
    assert f.set({"brake_pedal_pct": 10.0}) == OK
    for n in (1, 7, 300):
        plant.step(n)
        f.step(n * 0.0005)
        same()


@pytest.mark.parametrize("version", VERSIONS)
def test_bit_for_bit_with_simulate_run(make, version):
    """The FMU driven as plant/simulate.run drives the plant (rows written at
    their step, outputs read at every record, a DoStep per chunk) records
    the same numbers."""
    scenario = load_scenario("launch-1st")
    duration = min(3.0, scenario.duration_s)
    every_s = 0.01
    ref = simulate.run(Plant(overrides=scenario.param_overrides()), scenario,
                       duration_s=duration, record_every_s=every_s)
    f = make(version)
    vrs = [f.vrs[n] for n in _output_names(f.model)]
    h = f.model.step_s
    row_k = scenario.row_steps(h)
    every = int(round(every_s / h))
    n_end = int(round(duration / h))

    def apply(row):
        assert f.set(dict(zip(scenario.columns, map(float, scenario.values[row])))) == OK

    assert f.enter_init() == OK
    assert f.set(fmu_scenario.start_values(scenario)) == OK
    row = 0
    while row < len(row_k) and row_k[row] <= 0:
        apply(row)                               # before initialization ends: after the reset
        row += 1
    assert f.exit_init() == OK
    data = []
    k = 0
    while True:
        while row < len(row_k) and row_k[row] <= k:
            apply(row)
            row += 1
        if k == len(data) * every:
            st, values = f.get_vrs(vrs)
            assert st == OK
            data.append(values)
        if k >= n_end:
            break
        target = min(n_end, len(data) * every)
        if row < len(row_k):
            target = min(target, int(row_k[row]))
        assert f.do_step(k * h, (target - k) * h) == OK, f.messages
        k = target
    assert np.array(data).shape == ref.data.shape
    assert _bits(np.array(data)) == _bits(ref.data)
