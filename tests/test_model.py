"""The Python wrapper of the C plant: views, stepping, errors, snapshots."""

import math
import re

import numpy as np
import pytest

from plant import Plant, PlantError
from plant._dct_plant import ffi, lib


@pytest.fixture(scope="module")
def plant():
    return Plant()


def test_names_follow_the_c_structs(plant):
    assert plant.input_names == [n for n, _ in ffi.typeof("dct_inputs").fields]
    assert plant.output_names == [n for n, _ in ffi.typeof("dct_outputs").fields]
    assert len(plant.state_names) == lib.dct_plant_state_size() == plant.state.size
    assert plant.state_names[0] == "time_s"
    assert "gearbox.sync[2].twist_rad" in plant.state_names
    assert "wheel[0].speed_rad_s" in plant.state_names
    assert len(set(plant.state_names)) == len(plant.state_names)


def test_views_share_memory_with_the_c_struct():
    p = Plant()
    assert p.inputs.shape == () and p.outputs.shape == ()
    p.inputs["accel_pedal_pct"] = 42.0
    assert p._p.inputs.accel_pedal_pct == 42.0
    p._p.inputs.brake_pedal_pct = 7.0
    assert p.inputs["brake_pedal_pct"] == 7.0
    assert p.input_values[p.input_names.index("brake_pedal_pct")] == 7.0
    p.step(10)
    assert p.outputs["time_s"] == pytest.approx(10 * p.step_s)
    assert p.output_values[0] == p.outputs["time_s"]
    assert p.state[0] == p.time_s == pytest.approx(10 * p.step_s)


def test_views_outlive_the_plant_object():
    p = Plant()
    outputs = p.outputs
    del p
    assert math.isfinite(float(outputs["time_s"]))


def test_step_n_is_n_steps():
    a, b = Plant(), Plant()
    for q in (a, b):
        q.reset(vehicle_speed_kmh=30, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
        q.inputs["accel_pedal_pct"] = 20
        q.inputs["clutch1_pressure_bar"] = 10
    a.step(400)
    for _ in range(400):
        b.step()
    assert a.time_s == pytest.approx(0.2)
    np.testing.assert_array_equal(a.state, b.state)


def test_reset_sets_speed_and_time():
    p = Plant()
    p.step(20)
    p.reset(vehicle_speed_kmh=50, sleeves=(0, 0, 1, 0))
    assert p.time_s == 0.0
    assert p.outputs["vehicle_speed_kmh"] == pytest.approx(50, rel=1e-6)
    with pytest.raises(ValueError):
        p.reset(sleeves=(1, 0))


def test_snapshot_restore_continues_identically():
    p = Plant()
    p.reset(vehicle_speed_kmh=20, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    p.inputs["accel_pedal_pct"] = 40
    p.inputs["clutch1_pressure_bar"] = 12
    p.step(100)
    snap = p.snapshot()
    p.step(300)
    state, outputs = p.state.copy(), p.outputs.copy()
    p.inputs["accel_pedal_pct"] = 0
    p.step(50)
    p.restore(snap)
    assert p.inputs["accel_pedal_pct"] == 40
    p.step(300)
    np.testing.assert_array_equal(p.state, state)
    assert p.outputs.tobytes() == outputs.tobytes()
    with pytest.raises(ValueError):
        p.restore(b"short")


def test_non_finite_input_names_the_input():
    p = Plant()
    p.inputs["clutch2_pressure_bar"] = math.nan
    with pytest.raises(PlantError) as e:
        p.step()
    assert str(e.value) == "input clutch2_pressure_bar is not finite: nan"


def test_non_finite_state_names_the_component():
    p = Plant()
    i = p.state_names.index("wheel[2].speed_rad_s")
    p.state[i] = math.inf
    with pytest.raises(PlantError) as e:
        p.step()
    # the first bad state in memory order is named (inf spreads within a step)
    assert re.fullmatch(r"state [a-z_]+(\[\d\])?\.[\w.\[\]]+ became (nan|inf|-inf) at t=0\.0005 s",
                        str(e.value)), str(e.value)


def test_state_error_message_names_the_flat_index():
    p = Plant()
    p._p.error_index = p.state_names.index("gearbox.sync[2].twist_rad")
    p.state[p._p.error_index] = math.nan
    with pytest.raises(PlantError) as e:
        p._check(lib.DCT_ERR_STATE)
    assert str(e.value) == "state gearbox.sync[2].twist_rad became nan at t=0.0000 s"


def test_parameter_check_failure_is_a_plant_error():
    p = Plant()
    p._p.params.solver.step_s = 0.0
    with pytest.raises(PlantError, match="^parameter check failed: "):
        p._check(lib.dct_plant_init(p._p))


def test_step_rejects_bad_counts(plant):
    with pytest.raises(ValueError):
        plant.step(-1)
    with pytest.raises(TypeError):
        plant.step(1.5)


def test_bench_times_each_step():
    p = Plant()
    ns = p.bench(500)
    assert ns.shape == (500,) and (ns > 0).all()
    assert p.time_s == pytest.approx(500 * p.step_s)


def test_energy_and_params(plant):
    assert math.isfinite(plant.energy())
    assert plant.params["solver"]["step_s"] == plant.step_s


@pytest.mark.slow
def test_a_long_stalled_plant_has_no_subnormal_state_and_the_callers_mode_is_kept():
    """A stalled engine's speeds and torques decay towards zero; after some
    minutes they reached subnormal magnitudes, where every operation takes
    the processor's slow path (a step of about 1.2 us took 17.5 us). The
    step flushes them to zero, and gives the caller's floating-point mode
    back: Python's own arithmetic still has subnormals afterwards."""
    tiny = 2.2250738585072014e-308              # the smallest normal double
    p = Plant()
    p.reset(sleeves=(1, 0, 0, 0))
    p.inputs["solenoid_current1_a"] = 1.0       # K1 closed at standstill: the engine stalls
    p.step(2000 * 365)
    assert float(p.outputs["engine_running"]) == 0.0
    subnormal = [n for n, v in zip(p.state_names, p.state) if v != 0 and abs(v) < tiny]
    assert subnormal == []
    assert tiny * 1e-5 != 0.0                    # the interpreter's mode is untouched
