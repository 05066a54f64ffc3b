"""The Python plant (validation/pyplant.py) against the C core, side by side.

Both start from the same state and get the same inputs: the launch-1st
scenario (valve currents through the hydraulics), then a power-on shift to
2nd (fork force on the 2-4 sleeve, K1 handed over to K2) with a TCU torque
request below the driver's torque over the handover (the engine's spark
cut), a stop on the brakes, and the selector lever to P while the car still
rolls at 26 km/h (the parking pawl ratchets, then engages below its speed
and holds the front wheels): 9 s, 18000 steps. Every state and every output
is compared after every step.

Tolerance: 1e-9 of the largest magnitude the variable takes in the run
(per state or output; a variable that crosses zero has no useful relative
error of its own). The two implementations do the same IEEE double operations
in the same order and call the same libm, so on this machine they agree to
the last bit (but for magnitudes near 1e-307: the C step flushes subnormal
results to zero, Python keeps them); the tolerance leaves room for a compiler that reorders or
contracts (fused multiply-add) the C arithmetic, which moves results by a few
ulps per operation. It is not loosened anywhere: the run's discrete events
(stick/slip, synchronizer phase, valve end stops) are decided by comparisons
on states that agree to the bit, so they happen on the same step in both.
"""

import numpy as np
import pytest

from plant.model import INPUT_NAMES, OUTPUT_NAMES, STATE_NAMES, Plant
from plant.scenario import load_scenario
from validation import pyplant
from validation.pyplant import PyPlant, PyPlantError

REL_TOL = 1e-9
HYDRAULICS = {"hydraulics": {"pressure_commanded": 0}}

# after launch-1st (4.5 s): time_s -> inputs set from then on
SHIFT_AND_BRAKE = [
    (4.5, {"fork_force2_n": 900.0}),                       # pre-select 2nd on the 2-4 sleeve
    (5.3, {"solenoid_current2_a": 0.35, "solenoid_current1_a": 0.6,
           "torque_request_active": 1.0, "engine_torque_request_nm": 60.0}),  # torque cut: spark retard
    (5.4, {"solenoid_current2_a": 0.6, "solenoid_current1_a": 0.3}),
    (5.5, {"solenoid_current2_a": 1.0, "solenoid_current1_a": 0.0}),  # K1 -> K2 handed over
    (5.6, {"torque_request_active": 0.0}),                 # torque back
    (5.7, {"fork_force2_n": 0.0}),
    (6.0, {"accel_pedal_pct": 0.0, "brake_pedal_pct": 80.0,
           "solenoid_current2_a": 0.0}),                   # lift off, open K2, brake
    (7.2, {"selector_lever": 0.0, "brake_pedal_pct": 40.0}),  # P while rolling: the pawl ratchets
    (9.0, {}),                                             # end: parked on the lock
]


def _script():
    """(step index, {input: value}) changes of the whole run, and its steps."""
    scen = load_scenario("launch-1st")
    step_s = 0.0005
    changes = {}
    for row, k in zip(scen.values, scen.row_steps(step_s)):
        changes.setdefault(int(k), {}).update(dict(zip(scen.columns, map(float, row))))
    for t, values in SHIFT_AND_BRAKE:
        changes.setdefault(int(round(t / step_s)), {}).update(values)
    return scen, changes, int(round(SHIFT_AND_BRAKE[-1][0] / step_s))


@pytest.fixture(scope="module")
def runs():
    scen, changes, n_steps = _script()
    c = Plant(overrides=HYDRAULICS)
    c.reset(**scen.reset_kwargs())
    py = PyPlant(c.params)
    py.init_from(c)
    cs, ps = np.empty((n_steps, len(STATE_NAMES))), np.empty((n_steps, len(STATE_NAMES)))
    co, po = np.empty((n_steps, len(OUTPUT_NAMES))), np.empty((n_steps, len(OUTPUT_NAMES)))
    for k in range(n_steps):
        for name, value in changes.get(k, {}).items():
            c.inputs[name] = value
            py.inputs[name] = value
        c.step(1)
        py.step(1)
        cs[k], ps[k] = c.state, py.state
        co[k], po[k] = c.output_values, py.output_values
    return cs, ps, co, po


def _worst(c, p, names):
    scale = np.max(np.abs(c), axis=0)
    err = np.abs(c - p) / np.where(scale > 0.0, scale, 1.0)
    j = int(np.argmax(np.max(err, axis=0)))
    k = int(np.argmax(err[:, j]))
    return float(err[k, j]), f"{names[j]} at step {k}: C {c[k, j]!r}, Python {p[k, j]!r}"


def test_layout_matches_the_c_structs():
    assert pyplant.STATE_NAMES == STATE_NAMES
    assert list(pyplant.INPUT_NAMES) == INPUT_NAMES
    assert list(pyplant.OUTPUT_NAMES) == OUTPUT_NAMES


@pytest.mark.slow
def test_every_state_agrees_after_every_step(runs):
    cs, ps, _, _ = runs
    err, where = _worst(cs, ps, STATE_NAMES)
    assert err <= REL_TOL, where


@pytest.mark.slow
def test_every_output_agrees_after_every_step(runs):
    _, _, co, po = runs
    err, where = _worst(co, po, OUTPUT_NAMES)
    assert err <= REL_TOL, where


@pytest.mark.slow
def test_the_run_exercises_every_component(runs):
    cs, _, co, _ = runs
    col = {name: co[:, i] for i, name in enumerate(OUTPUT_NAMES)}
    state = {name: cs[:, i] for i, name in enumerate(STATE_NAMES)}
    assert col["vehicle_speed_kmh"].max() > 30.0                     # engine, driveline, vehicle
    assert col["clutch1_clamp_force_n"].max() > 1000.0               # K1 valve, chamber, piston
    assert col["clutch2_clamp_force_n"].max() > 1000.0               # K2
    assert abs(col["clutch1_slip_rpm"]).max() > 500.0                # K1 slipping, then locked
    assert np.any(col["sync2_state"] == 1.0)                         # 2nd synchronizing
    assert col["sync2_gear"][-1] == 2.0 and col["sync1_gear"][-1] == 1.0
    assert np.any(col["gear"] == 1.0) and np.any(col["gear"] == 2.0)  # drive handed over
    assert col["gear"][-1] == 2.0 and col["clutch2_capacity_nm"][-1] < 2.0  # K2 open: 2nd held
    assert col["brake_torque_nm"].max() > 1000.0                     # brakes
    assert col["front_tyre_slip"].max() > 0.02                      # tyres in transient slip
    assert np.ptp(col["pitch_deg"]) > 0.1                             # body pitch
    assert state["engine.spark_cut_nm"].max() > 20.0                 # the request's spark cut
    assert np.abs(state["driveline.roll_rad"]).max() > 0.01          # powertrain roll on its mounts
    assert col["trans_pump_torque_nm"].min() > 1.0                   # the oil pump on the crank
    assert np.ptp(col["clutch1_kiss_pressure_bar"]) > 0.0            # pack gap with the oil temperature
    p_sel = col["selector_lever"] == 0.0
    assert p_sel[-1] and np.any(p_sel & (col["park_lock_engaged"] == 0.0)
                                & (col["vehicle_speed_kmh"] > 10.0))  # P too fast: ratchets
    assert col["park_lock_engaged"][-1] == 1.0                       # then holds


def test_pressure_commanded_mode_agrees():
    c = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    c.reset(vehicle_speed_kmh=30.0, sleeves=(0, 1, 0, 0), clutch_locked=(0, 1))
    c.inputs["accel_pedal_pct"] = 40.0
    c.inputs["clutch2_pressure_bar"] = 8.0
    py = PyPlant(c.params)
    py.init_from(c)
    for _ in range(200):
        c.step(1)
        py.step(1)
    np.testing.assert_allclose(py.state, c.state, rtol=REL_TOL, atol=1e-12)
    np.testing.assert_allclose(py.output_values, c.output_values, rtol=REL_TOL, atol=1e-12)


def test_cold_start_agrees(monkeypatch):
    """23 degC: the cold open K1 drags input shaft 1 and the 1-3 cone creeps
    above the lock speed; the blocker releases by the cone holding a settled
    load below the chamfers' index torque (synchronizer.c cone_holds_load).
    The cold oil's pack gap, drag and the cold engine's idle rise on the way."""
    released = []
    holds = pyplant._cone_holds_load

    def spy(*args):
        r = holds(*args)
        released.append(r)
        return r

    monkeypatch.setattr(pyplant, "_cone_holds_load", spy)
    c = Plant(overrides=HYDRAULICS)
    c.reset(coolant_temp_degc=23.0, engine_oil_temp_degc=23.0, trans_oil_temp_degc=23.0)
    py = PyPlant(c.params)
    py.init_from(c)
    c.inputs["fork_force1_n"] = py.inputs["fork_force1_n"] = 900.0  # pre-select 1st at a standstill
    n = 1600
    cs, ps = np.empty((n, len(STATE_NAMES))), np.empty((n, len(STATE_NAMES)))
    co, po = np.empty((n, len(OUTPUT_NAMES))), np.empty((n, len(OUTPUT_NAMES)))
    for k in range(n):
        c.step(1)
        py.step(1)
        cs[k], ps[k] = c.state, py.state
        co[k], po[k] = c.output_values, py.output_values
    err, where = _worst(cs, ps, STATE_NAMES)
    assert err <= REL_TOL, where
    err, where = _worst(co, po, OUTPUT_NAMES)
    assert err <= REL_TOL, where
    assert any(released) and co[-1, OUTPUT_NAMES.index("sync1_gear")] == 1.0
    assert co[-1, OUTPUT_NAMES.index("sync1_state")] == 2.0


def test_a_tie_up_agrees():
    """Two gears on one input shaft (3rd and 5th on shaft 1, a tie-up a
    faulty TCU can command) with K1 stuck, driving: the step takes the tied
    shaft's and the carrier's dampers implicitly (gearbox.c); both
    implementations agree step by step and stay finite."""
    c = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    c.reset(vehicle_speed_kmh=60.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    py = PyPlant(c.params)
    py.init_from(c)
    for name, value in (("accel_pedal_pct", 60.0), ("clutch1_pressure_bar", 12.0), ("fork_force3_n", 2000.0)):
        c.inputs[name] = py.inputs[name] = value
    n = 1200
    cs, ps = np.empty((n, len(STATE_NAMES))), np.empty((n, len(STATE_NAMES)))
    for k in range(n):
        c.step(1)
        py.step(1)
        cs[k], ps[k] = c.state, py.state
    err, where = _worst(cs, ps, STATE_NAMES)
    assert err <= REL_TOL, where
    assert c.outputs["sync1_gear"] == 3.0 and c.outputs["sync3_gear"] == 5.0   # both in: tied up
    assert np.all(np.isfinite(cs))


def test_reset_matches_the_c_reset():
    c = Plant(overrides=HYDRAULICS)
    py = PyPlant(c.params)
    for kw in ({}, {"vehicle_speed_kmh": 80.0, "sleeves": (0, -1, 0, 0), "clutch_locked": (0, 1)},
               {"vehicle_speed_kmh": 10.0, "sleeves": (0, 0, -1, 0), "engine_on": 0}):
        c.reset(**kw)
        py.reset(**kw)
        np.testing.assert_array_equal(py.state, c.state)
        np.testing.assert_allclose(py.output_values, c.output_values, rtol=REL_TOL, atol=1e-12)


def test_bad_input_is_one_line_error():
    py = PyPlant(Plant().params)
    py.inputs["accel_pedal_pct"] = float("nan")
    with pytest.raises(PyPlantError, match="accel_pedal_pct") as e:
        py.step(1)
    assert "\n" not in str(e.value)


def test_state_setter_rejects_wrong_length():
    py = PyPlant(Plant().params)
    with pytest.raises(ValueError, match=str(len(STATE_NAMES))):
        py.state = [0.0] * 3


def test_bench_step_returns_a_positive_duration():
    s = pyplant.bench_step(5)
    assert isinstance(s, float) and s > 0.0
