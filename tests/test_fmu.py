"""The plant as an FMU (plant/fmu, ``dct-hil fmu``), seen from FMPy: valid
for FMI 2.0 and 3.0, compiles from its own sources, reproduces ``dct-hil
simulate`` bit for bit, keeps and restores its state, runs as two
independent instances, and refuses bad input with the FMI status and a
message naming the cause."""

import io
import math
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import requires

fmpy = requires.module("fmpy")
from fmpy import extract, read_model_description, simulate_fmu
from fmpy.fmi2 import FMU2Slave
from fmpy.fmi3 import FMU3Slave
from fmpy.model_description import read_build_description
from fmpy.validation import validate_fmu

from plant import simulate
from plant.fmu import build
from plant.fmu import scenario as fmu_scenario
from plant.model import Plant
from plant.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
VERSIONS = (2, 3)


@pytest.fixture(scope="module")
def fmus(tmp_path_factory):
    d = tmp_path_factory.mktemp("fmu")
    out = {}
    for v in VERSIONS:
        path = d / f"dct_plant_fmi{v}.fmu"
        build.build(path, v)
        out[v] = str(path)
    return out


@pytest.fixture(scope="module")
def unzipped(fmus, tmp_path_factory):
    return {v: extract(p, str(tmp_path_factory.mktemp(f"unzip{v}"))) for v, p in fmus.items()}


# ------------------------------------------------------------------ validity

@pytest.mark.slow
@pytest.mark.parametrize("version", VERSIONS)
def test_fmpy_finds_no_problem(fmus, version):
    assert validate_fmu(fmus[version]) == []
    md = read_model_description(fmus[version], validate=True, validate_variable_names=True,
                                validate_model_structure=True)
    assert md.fmiVersion == f"{version}.0"
    assert md.coSimulation.modelIdentifier == "dct_plant"


@pytest.mark.parametrize("version", VERSIONS)
def test_variables_follow_the_c_structs_and_the_parameter_files(fmus, version):
    from plant._dct_plant import ffi
    from plant.describe import online_keys
    md = read_model_description(fmus[version])
    by = {v.name: v for v in md.modelVariables}
    inputs = [v for v in md.modelVariables if v.causality == "input"]
    outputs = [v for v in md.modelVariables if v.causality == "output"]
    assert [v.name for v in inputs] == [f for f, _ in ffi.typeof("dct_inputs").fields]
    assert len(outputs) == len(ffi.typeof("dct_outputs").fields)
    assert by["engine_speed_rpm"].unit == "rpm" and by["out.accel_pedal_pct"].causality == "output"
    assert by["engine.inertia_kgm2"].variability == "fixed"
    assert float(by["engine.inertia_kgm2"].start) == Plant().params["engine"]["inertia_kgm2"]
    assert float(by["engine.inertia_kgm2"].min) > 0
    assert by["engine.idle_speed_rpm"].variability == "tunable"             # marked online
    tunable = {v.name for v in md.modelVariables
               if v.causality == "parameter" and v.variability == "tunable"}
    assert "clutch[0].mu_static" in tunable and "faults.spool_stuck[0]" in tunable
    assert "engine.full_load.torque_nm[3]" in tunable                       # marked online
    online = online_keys()
    assert "engine.inertia_kgm2" not in online and "engine.inertia_kgm2" not in tunable
    assert "solver.step_s" not in by                                        # the FMU's own step
    assert all(v.start is not None for v in md.modelVariables if v.causality in ("input",
                                                                                  "parameter"))
    units = {u.name for u in md.unitDefinitions}
    assert all(v.unit in units for v in md.modelVariables if v.unit)


@pytest.mark.parametrize("version", VERSIONS)
def test_fmu_carries_its_sources_and_build_description(fmus, version):
    names = zipfile.ZipFile(fmus[version]).namelist()
    plat = build.platform_dir(version)
    assert f"binaries/{plat}/dct_plant.so" in names
    assert "modelDescription.xml" in names and "sources/fmu_variables.c" in names
    assert "sources/plant.c" in names and "sources/dct_bench.c" not in names
    c_files = sorted(n[len("sources/"):] for n in names if n.startswith("sources/")
                     and n.endswith(".c"))
    if version == 3:
        (config,) = read_build_description(fmus[version])
    else:
        (config,) = read_model_description(fmus[version]).buildConfigurations
    assert sorted(config.sourceFileSets[0].sourceFiles) == c_files


def _compile_from_sources(unzipdir, version, out_so):
    """What another tool does: the build description's (FMI 3) or the
    modelDescription's (FMI 2) file list, compiled with the system compiler."""
    src = Path(unzipdir) / "sources"
    if version == 3:
        (config,) = read_build_description(unzipdir)
    else:
        (config,) = read_model_description(unzipdir).buildConfigurations
    files = config.sourceFileSets[0].sourceFiles
    includes = config.sourceFileSets[0].includeDirectories or ["."]
    cmd = ["cc", "-std=c11", "-O2", "-fno-math-errno", "-fPIC", "-shared", "-o", str(out_so)]
    cmd += [f"-I{src / d}" for d in includes] + [str(src / f) for f in files] + ["-lm"]
    subprocess.run(cmd, check=True, capture_output=True)


@pytest.mark.slow
@pytest.mark.parametrize("version", VERSIONS)
def test_compiles_from_its_sources_and_computes_the_same(fmus, version, tmp_path):
    unz = extract(fmus[version], str(tmp_path / "u"))
    plat = build.platform_dir(version)
    so = Path(unz) / "binaries" / plat / "dct_plant.so"
    table, start, _ = fmu_scenario.for_fmpy("launch-1st")
    shipped = simulate_fmu(unz, stop_time=1.0, step_size=0.01, output_interval=0.01, input=table, start_values=start)
    so.unlink()
    _compile_from_sources(unz, version, so)
    again = simulate_fmu(unz, stop_time=1.0, step_size=0.01, output_interval=0.01, input=table, start_values=start)
    assert len(shipped) > 100 and np.array_equal(_values(shipped), _values(again))


# ------------------------------------------------------------------ the same numbers

def _values(result):
    return np.column_stack([result[n] for n in result.dtype.names])


def _at(result, times):
    """The rows of an FMPy result at ``times`` (FMPy also records at the
    input rows' times: the last row recorded at each time)."""
    idx = []
    for t in times:
        hits = np.flatnonzero(np.abs(result["time"] - t) < 1e-9)
        assert hits.size, f"no result row at t={t}"
        idx.append(hits[-1])
    return result[np.array(idx)]


def _offline(name, every_s):
    scenario = load_scenario(name)
    plant = Plant(None, scenario.param_overrides())
    return simulate.run(plant, scenario, record_every_s=every_s)


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("step_s", [0.0005, 0.001, 0.01])
def test_launch_equals_dct_hil_simulate_bit_for_bit(unzipped, version, step_s):
    table, start, duration = fmu_scenario.for_fmpy("launch-1st")
    res = simulate_fmu(unzipped[version], stop_time=duration, step_size=step_s, output_interval=step_s, input=table,
                       start_values=start)
    offline = _offline("launch-1st", 0.01)
    rows = _at(res, offline.data[:, 0])
    md = read_model_description(unzipped[version])
    name_of = {v.name.removeprefix("out."): v.name for v in md.modelVariables
               if v.causality == "output"}
    for k, name in enumerate(offline.names):
        fmu_values = rows[name_of[name]]
        same = (fmu_values == offline.data[:, k]) | (np.isnan(fmu_values)
                                                     & np.isnan(offline.data[:, k]))
        assert same.all(), (name, np.flatnonzero(~same)[:3])
    assert offline.data[-1, offline.names.index("vehicle_speed_kmh")] > 30   # it drove off


def test_a_pressure_commanded_scenario_sets_the_parameter_it_needs(unzipped):
    table, start, duration = fmu_scenario.for_fmpy("launch-1st-pressure")
    assert start["hydraulics.pressure_commanded"] == 1.0
    res = simulate_fmu(unzipped[2], stop_time=1.0, step_size=0.01, output_interval=0.01, input=table,
                       start_values=start)
    offline = _offline("launch-1st-pressure", 0.01)
    k = offline.names.index("clutch1_pressure_bar")
    rows = _at(res, offline.data[:101, 0])
    assert np.array_equal(rows["out.clutch1_pressure_bar"], offline.data[:101, k])


# ------------------------------------------------------------------ instances and state

def _slave(unzipdir, version, name="a", messages=None):
    md = read_model_description(unzipdir)
    vr = {v.name: v.valueReference for v in md.modelVariables}
    if version == 2:
        fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipdir,
                        modelIdentifier="dct_plant", instanceName=name)
        if messages is None:
            fmu.instantiate()
        else:
            fmu.instantiate(callbacks=_fmi2_callbacks(messages))
        fmu.setupExperiment(startTime=0.0)
    else:
        fmu = FMU3Slave(guid=md.guid, unzipDirectory=unzipdir,
                        modelIdentifier="dct_plant", instanceName=name)
        if messages is None:
            fmu.instantiate()
        else:
            fmu.instantiate(logMessage=_fmi3_logger(messages))
    return fmu, vr


_KEEP = []    # ctypes callbacks must outlive the instances


def _fmi2_callbacks(messages):
    from fmpy.fmi2 import (
        defaultCallbacks,
        fmi2CallbackFunctions,
        fmi2CallbackLoggerTYPE,
    )

    def logger(env, instance, status, category, message):
        messages.append((status, category.decode(), message.decode()))

    cb = fmi2CallbackFunctions()
    cb.logger = fmi2CallbackLoggerTYPE(logger)
    cb.allocateMemory = defaultCallbacks.allocateMemory
    cb.freeMemory = defaultCallbacks.freeMemory
    _KEEP.append(cb)
    return cb


def _fmi3_logger(messages):
    def logger(env, status, category, message):
        messages.append((status, category.decode(), message.decode()))
    return logger


def _set(fmu, version, vrs, values):
    if version == 2:
        fmu.setReal(vrs, values)
    else:
        fmu.setFloat64(vrs, values)


def _get(fmu, version, vrs):
    return list(fmu.getReal(vrs) if version == 2 else fmu.getFloat64(vrs))


def _init(fmu, version, vr, start=None):
    if version == 2:
        fmu.enterInitializationMode()
    else:
        fmu.enterInitializationMode(startTime=0.0)
    for name, value in (start or {}).items():
        _set(fmu, version, [vr[name]], [value])
    fmu.exitInitializationMode()


def _launch(fmu, version, vr, t0, seconds, step=0.01):
    """Full throttle in 1st from t0 on; returns the outputs after each step."""
    outs = [vr[n] for n in ("engine_speed_rpm", "vehicle_speed_kmh", "clutch1_pressure_bar")]
    rows = []
    t = t0
    for k in range(int(round(seconds / step))):
        _set(fmu, version, [vr["accel_pedal_pct"], vr["solenoid_current1_a"]],
             [100.0, min(1.0, 0.15 + 0.5 * t)])
        fmu.doStep(currentCommunicationPoint=t, communicationStepSize=step)
        t = t0 + (k + 1) * step
        rows.append(_get(fmu, version, outs))
    return np.array(rows), t


LAUNCH = {"initial.sleeve_side[0]": 1.0}


@pytest.mark.parametrize("version", VERSIONS)
def test_get_and_set_fmu_state_reproduce_a_run_exactly(unzipped, version):
    fmu, vr = _slave(unzipped[version], version)
    try:
        _init(fmu, version, vr, LAUNCH)
        _, t = _launch(fmu, version, vr, 0.0, 0.5)
        state = fmu.getFMUState() if version == 3 else fmu.getFMUstate()
        first, t_end = _launch(fmu, version, vr, t, 0.5)
        if version == 3:
            fmu.setFMUState(state)
        else:
            fmu.setFMUstate(state)
        again, _ = _launch(fmu, version, vr, t, 0.5)
        assert np.array_equal(first, again)
        assert first[-1, 1] > first[0, 1] > 0               # it is moving: a real run
        # the serialized state too, in a fresh instance
        if version == 3:
            fmu.setFMUState(state)
            blob = fmu.serializeFMUState(state)
            fmu.freeFMUState(state)
        else:
            fmu.setFMUstate(state)
            blob = fmu.serializeFMUstate(state)
            fmu.freeFMUstate(state)
        other, vr2 = _slave(unzipped[version], version, "b")
        try:
            _init(other, version, vr2)
            if version == 3:
                s2 = other.deserializeFMUState(blob)
                other.setFMUState(s2)
                other.freeFMUState(s2)
            else:
                s2 = other.deSerializeFMUstate(blob)
                other.setFMUstate(s2)
                other.freeFMUstate(s2)
            third, _ = _launch(other, version, vr2, t, 0.5)
            assert np.array_equal(first, third)
        finally:
            other.terminate()
            other.freeInstance()
    finally:
        fmu.terminate()
        fmu.freeInstance()


@pytest.mark.parametrize("version", VERSIONS)
def test_two_instances_in_one_process_run_independently(unzipped, version):
    alone, vra = _slave(unzipped[version], version, "alone")
    _init(alone, version, vra, LAUNCH)
    expected, _ = _launch(alone, version, vra, 0.0, 0.5)
    alone.terminate()
    alone.freeInstance()

    a, vr = _slave(unzipped[version], version, "a")
    b, _ = _slave(unzipped[version], version, "b")
    try:
        _init(a, version, vr, LAUNCH)
        _init(b, version, vr, {"initial.vehicle_speed_kmh": 80.0})
        rows = []
        t = 0.0
        for k in range(50):                       # interleaved, b coasting at 80 km/h
            _set(a, version, [vr["accel_pedal_pct"], vr["solenoid_current1_a"]],
                 [100.0, min(1.0, 0.15 + 0.5 * t)])
            _set(b, version, [vr["brake_pedal_pct"]], [30.0])
            a.doStep(currentCommunicationPoint=t, communicationStepSize=0.01)
            b.doStep(currentCommunicationPoint=t, communicationStepSize=0.01)
            t = (k + 1) * 0.01
            rows.append(_get(a, version, [vr[n] for n in ("engine_speed_rpm", "vehicle_speed_kmh",
                                                          "clutch1_pressure_bar")]))
        assert np.array_equal(np.array(rows), expected)
        assert 60 < _get(b, version, [vr["vehicle_speed_kmh"]])[0] < 80     # b braked
    finally:
        for f in (a, b):
            f.terminate()
            f.freeInstance()


# ------------------------------------------------------------------ bad input

@pytest.mark.parametrize("version", VERSIONS)
def test_bad_requests_get_an_error_status_and_a_message(unzipped, version):
    from fmpy.fmi1 import FMICallException
    messages = []
    fmu, vr = _slave(unzipped[version], version, "bad", messages)
    try:
        _init(fmu, version, vr)
        with pytest.raises(FMICallException):
            fmu.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.0007)
        assert "0.0007" in messages[-1][2] and "multiple" in messages[-1][2]
        with pytest.raises(FMICallException):
            _get(fmu, version, [99999])
        assert "99999" in messages[-1][2] and "exist" in messages[-1][2]
        with pytest.raises(FMICallException):
            _set(fmu, version, [vr["accel_pedal_pct"]], [math.nan])
        assert "accel_pedal_pct" in messages[-1][2]
        with pytest.raises(FMICallException):
            _set(fmu, version, [vr["engine.inertia_kgm2"]], [0.3])      # fixed, after init
        assert "engine.inertia_kgm2" in messages[-1][2]
        with pytest.raises(FMICallException):
            _set(fmu, version, [vr["clutch[0].mu_static"]], [-1.0])     # below its range
        assert _get(fmu, version, [vr["clutch[0].mu_static"]])[0] > 0
        _set(fmu, version, [vr["clutch[0].mu_static"]], [0.12])         # tunable: taken
        assert _get(fmu, version, [vr["clutch[0].mu_static"]]) == [0.12]
        fmu.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.01)   # still running
        values = _get(fmu, version, [vr[n] for n in ("engine_speed_rpm", "vehicle_speed_kmh")])
        assert all(math.isfinite(x) for x in values) and 600 < values[0] < 900
        assert all(s != 0 for s, _, _ in messages[-5:-1])
    finally:
        fmu.terminate()
        fmu.freeInstance()


def test_a_wrong_guid_is_refused(unzipped):
    fmu = FMU2Slave(guid="{00000000-0000-0000-0000-000000000000}", unzipDirectory=unzipped[2],
                    modelIdentifier="dct_plant", instanceName="x")
    with pytest.raises(Exception, match="instantiate"):
        fmu.instantiate()
    fmu.freeLibrary()


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "dct_hil.cli", "fmu", *args],
                          capture_output=True, text=True, cwd=ROOT)


@pytest.mark.slow
def test_command_line_bad_input_is_one_line(tmp_path):
    r = _cli(str(tmp_path / "x.fmu"), "--fmi", "4")
    assert r.returncode == 2 and "unknown FMI version '4'" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[engine]\nidle_speed_rpm = -5\n")
    r = _cli(str(tmp_path / "x.fmu"), "--params", str(bad))
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "idle_speed_rpm" in r.stderr
    assert not list(tmp_path.glob("x.fmu*"))
    r = _cli(str(tmp_path / "no" / "x.fmu"))
    assert r.returncode == 1 and "does not exist" in r.stderr


@pytest.mark.slow
def test_params_bake_another_car_in(tmp_path):
    car = tmp_path / "heavy.toml"
    car.write_text("[vehicle]\nmass_kg = 1900.0\n")
    out = tmp_path / "heavy.fmu"
    r = _cli(str(out), "--params", str(car), "--fmi", "3")
    assert r.returncode == 0, r.stderr
    md = read_model_description(str(out))
    assert float({v.name: v for v in md.modelVariables}["vehicle.mass_kg"].start) == 1900.0
    table, start, _ = fmu_scenario.for_fmpy("launch-1st")
    res = simulate_fmu(str(out), stop_time=2.0, step_size=0.01, output_interval=0.01, input=table, start_values=start)
    scenario = load_scenario("launch-1st")
    offline = simulate.run(Plant(str(car), scenario.param_overrides()), scenario, duration_s=2.0)
    k = offline.names.index("vehicle_speed_kmh")
    assert np.array_equal(_at(res, offline.data[:, 0])["vehicle_speed_kmh"], offline.data[:, k])


@pytest.mark.slow
def test_speed_benchmark_runs_the_same_inputs_three_ways(tmp_path):
    from plant.fmu import bench
    out = io.StringIO()
    report = bench.run(2, 0.01, 20.0, 1, str(tmp_path / "b.json"), out=out)
    assert report["same_vehicle_speed"] is True
    assert report["simulated_s"] == 20.0 and report["outputs_recorded"] > 50
    assert {"offline_best_s", "fmu_best_s", "lean_master_best_s", "ratio"} <= set(report)
    assert "lean master" in out.getvalue() and (tmp_path / "b.json").exists()
