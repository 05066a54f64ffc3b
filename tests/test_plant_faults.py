"""Physical faults of the plant (plant/csrc/faults.c, ``Plant.set_faults``):
each fault's effect on the car, the healthy car back once they are cleared,
no fault that makes the state NaN, and bad fault values refused in one line."""

import math

import numpy as np
import pytest

from plant import Plant
from plant._dct_plant import ffi, lib
from plant.driver import ScriptedDriver
from plant.maneuvers import PAPER_CYCLE
from plant.model import FAULT_FIELDS, FAULT_NAMES
from tcu_stub.logic import PERIOD_S
from tcu_stub.offline import run_offline

HYD = {"hydraulics": {"pressure_commanded": 0}}   # the TCU drives valve currents
CMD = {"hydraulics": {"pressure_commanded": 1}}   # clutch pressures are inputs


def run(p, seconds):
    """Step ``seconds`` one step at a time; the outputs after each step."""
    rows = []
    for _ in range(int(round(seconds / p.step_s))):
        p.step(1)
        rows.append(p.outputs.copy())
    return np.array(rows)


def part(p, name):
    """The bytes of one member of the C plant struct."""
    off = ffi.offsetof("dct_plant", name)
    return bytes(p._buf[off:off + ffi.sizeof(getattr(p._p, name))])


# --------------------------------------------------------------- the effects

def test_solenoid_open_drains_the_clutch_whatever_the_current():
    p = Plant(overrides=HYD)
    p.inputs["solenoid_current1_a"] = 0.8
    p.inputs["solenoid_current2_a"] = 0.8
    run(p, 0.5)
    assert p.outputs["clutch1_pressure_bar"] > 10.0
    k2_before = float(p.outputs["clutch2_pressure_bar"])

    p.set_faults(solenoid_open=[1, 0])
    r = run(p, 0.5)
    assert p.inputs["solenoid_current1_a"] == 0.8          # still commanded
    assert np.all(r["solenoid_current1_a"] == 0.0)         # measured: no current flows
    assert np.all(r["solenoid_current2_a"] == 0.8)
    # 0 A: the spring opens the tank edge and the clutch drains, to the level
    # of the valve's 0 A point (tests/test_hydraulics.py: below 0.1 bar)
    assert r["clutch1_pressure_bar"][-1] < 0.1
    assert r["clutch1_clamp_force_n"][-1] == 0.0
    # the healthy valve regulates on: within 0.01 bar (its settling wobble)
    assert r["clutch2_pressure_bar"][-1] == pytest.approx(k2_before, abs=0.01)


def test_spool_stuck_holds_the_spool_while_the_current_changes():
    p = Plant(overrides=HYD)
    p.inputs["solenoid_current1_a"] = 0.5
    p.inputs["solenoid_current2_a"] = 0.5
    run(p, 0.5)
    held_mm = float(p.outputs["spool1_position_mm"])
    held_bar = float(p.outputs["clutch1_pressure_bar"])

    p.set_faults(spool_stuck={0: 1})
    for current in (0.9, 0.1, 0.6):
        p.inputs["solenoid_current1_a"] = current
        p.inputs["solenoid_current2_a"] = current
        r = run(p, 0.3)
        assert np.all(r["spool1_position_mm"] == held_mm)   # not a bit of motion
        assert np.ptp(r["spool2_position_mm"]) > 0.01       # K2's valve still regulates
        # the held (nearly lapped) opening keeps the pressure where it was:
        # no longer proportional to the current (0.9 A asks for 18 bar, 0.1 A
        # for 0.5 bar); the land leakage moves it by less than 0.5 bar
        assert r["clutch1_pressure_bar"][-1] == pytest.approx(held_bar, abs=0.5)


def test_friction_loss_scales_the_capacity_at_the_same_clamp_force():
    # the friction coefficients and the pack gap held at their temperature:
    # the oil warms by about 1e-5 K a step, which moves them by 1e-8
    p = Plant(overrides={**CMD, "thermal": {"clutch_mu_change_per_k": 0.0,
                                            "clutch_gap_expansion_per_k": 0.0}})
    p.inputs["clutch1_pressure_bar"] = 10.0
    p.inputs["clutch2_pressure_bar"] = 10.0
    p.step(1)
    healthy = p.outputs.copy()
    p.set_faults(friction_loss=[0.5, 0.25])
    p.step(1)
    faded = p.outputs.copy()
    for k, keep in ((1, 0.5), (2, 0.75)):
        force = f"clutch{k}_clamp_force_n"
        cap = f"clutch{k}_capacity_nm"
        assert faded[force] == healthy[force] > 0.0      # the pistons are untouched
        # capacity = surfaces x mu x radius x clamp force: linear in mu, so
        # the ratio is exact but for the rounding of the product
        assert faded[cap] / healthy[cap] == pytest.approx(keep, rel=1e-12)


def _clamp_start_bar(p, k):
    """The pressure at which clutch k starts to clamp, pressure_commanded:
    the clamp force is linear in the pressure once the pack is closed
    (piston.c), so two points extrapolate to its zero exactly."""
    name = f"clutch{k + 1}_pressure_bar"
    force = []
    for bar in (10.0, 15.0):
        p.inputs[name] = bar
        p.step(1)
        force.append(float(p.outputs[f"clutch{k + 1}_clamp_force_n"]))
    return 10.0 - force[0] * 5.0 / (force[1] - force[0])


def test_pack_gap_offset_raises_the_clamp_pressure_by_the_spring():
    p = Plant(overrides=CMD)
    healthy = [_clamp_start_bar(p, k) for k in (0, 1)]
    offsets = (1.0, 2.0)
    p.set_faults(pack_gap_offset_mm=list(offsets))
    drifted = [_clamp_start_bar(p, k) for k in (0, 1)]
    for k in (0, 1):
        c = p.params["clutch"][k]
        rise_bar = c["return_spring_n_per_m"] * offsets[k] * 1e-3 / c["piston_area_m2"] / 1e5
        # p A = F0 + k_r gap at the kiss point: exact but for rounding
        assert drifted[k] - healthy[k] == pytest.approx(rise_bar, rel=1e-6)


def test_pack_gap_offset_lengthens_the_fill():
    def fill_s(offset_mm):
        p = Plant(overrides=HYD)
        p.set_faults(pack_gap_offset_mm=[offset_mm, 0.0])
        p.inputs["solenoid_current1_a"] = 0.6
        for i in range(4000):
            p.step(1)
            if p.outputs["clutch1_clamp_force_n"] > 0.0:
                return (i + 1) * p.step_s
        raise AssertionError("the clutch never clamped")

    gap = Plant().params["clutch"][0]["pack_gap_mm"]
    healthy, doubled = fill_s(0.0), fill_s(gap)
    # twice the gap: twice the stroke volume behind the same metering edge at
    # the same (return spring) pressure; the compression of oil and air
    # before the stroke is the same, so a bit less than twice the time
    assert 1.6 * healthy < doubled < 2.2 * healthy


def test_line_pressure_loss_lowers_the_supply_and_caps_the_clutch():
    # half the line pressure: a wide-open valve gives the clutch what the line
    # has, within 1 % (as tests/test_hydraulics.py at full current)
    p = Plant(overrides=HYD)
    p.set_faults(line_pressure_loss=0.5)
    p.inputs["solenoid_current1_a"] = 1.0
    run(p, 1.0)
    line0 = p.params["hydraulics"]["supply"]["line"]["pressure_bar"][0]
    assert p.outputs["line_pressure_bar"] == pytest.approx(0.5 * line0, rel=1e-6)
    assert p.outputs["clutch1_pressure_bar"] == pytest.approx(0.5 * line0, rel=0.01)


def test_line_pressure_loss_decays_with_the_supply_lag():
    p = Plant(overrides=HYD)
    p.inputs["solenoid_current1_a"] = 0.9
    run(p, 0.5)
    line0 = float(p.outputs["line_pressure_bar"])
    p.set_faults(line_pressure_loss=1.0)
    r = run(p, 0.5)
    tau = p.params["hydraulics"]["supply"]["tau_s"]
    t = np.arange(1, len(r) + 1) * p.step_s
    for when in (tau, 2 * tau):
        i = int(np.argmin(abs(t - when)))
        # first-order lag, Euler at the hydraulic sub-step: within 1 %
        assert r["line_pressure_bar"][i] == pytest.approx(line0 * math.exp(-t[i] / tau), rel=0.01)
    assert r["line_pressure_bar"][-1] < 1e-3
    # the chamber empties back through the open supply edge (a lag of some
    # 10 ms behind the line); once it has, the clutch cannot get more than
    # the line gives, whatever the current
    p.inputs["solenoid_current1_a"] = 1.0
    r = run(p, 0.5)
    assert np.all(r["clutch1_pressure_bar"] <= r["line_pressure_bar"] + 0.01)
    assert np.all(r["clutch1_clamp_force_n"] == 0.0)


def test_fork_jammed_holds_the_sleeve_under_the_fork_force():
    for jammed in (0, 1):
        p = Plant(overrides=CMD)
        p.set_faults(fork_jammed={0: jammed})
        p.inputs["fork_force1_n"] = 1000.0
        r = run(p, 0.3)
        if jammed:
            assert np.all(r["fork1_position_mm"] == 0.0) and np.all(r["sync1_state"] == 0)
        else:
            assert r["fork1_position_mm"][-1] == pytest.approx(8.5) and r["sync1_state"][-1] == 2

    # jammed in gear: a pull-out force does not take the gear out
    p = Plant(overrides=CMD)
    p.reset(vehicle_speed_kmh=30.0, sleeves=(1, 0, 0, 0))
    p.set_faults(fork_jammed=[1, 0, 0, 0])
    p.inputs["fork_force1_n"] = -1000.0
    r = run(p, 0.3)
    assert np.all(r["fork1_position_mm"] == r["fork1_position_mm"][0])
    assert np.all(r["sync1_state"] == 2) and np.all(r["sync1_gear"] == 1)


def _preselect_fifth(blocker_failed):
    """Driving in 2nd (K2 closed), the TCU pre-selects 5th on sleeve 5-R with
    800 N, below the blocker's 1300 N: the slip of the 5th gear is large."""
    p = Plant(overrides=CMD)
    p.reset(vehicle_speed_kmh=50.0, sleeves=(0, 1, 0, 0), clutch_locked=(0, 1))
    p.inputs["clutch2_pressure_bar"] = 20.0
    p.inputs["accel_pedal_pct"] = 20.0
    if blocker_failed:
        p.set_faults(blocker_failed={2: 1})
    p.step(200)
    p.inputs["fork_force3_n"] = 800.0
    return p, run(p, 0.5)


def test_blocker_failed_engages_without_synchronizing():
    gear5 = Plant().params["gearbox"]["ratio"][4]
    clash_rpm = Plant().params["gearbox"]["sync"][2]["clash_speed_rad_s"] * 30 / math.pi
    results = {}
    for failed in (0, 1):
        p, r = _preselect_fifth(failed)
        state = r["sync3_state"]
        on_cone = int(np.argmax(state == 1))
        engaged = int(np.argmax(state == 2))
        before = r[engaged - 1]            # the last step before the engagement
        slip_rpm = before["input_shaft1_speed_rpm"] / gear5 - before["output_shaft2_speed_rpm"]
        results[failed] = (on_cone, engaged, slip_rpm, r["gear_clashes"][-1])
        assert state[-1] == 2 and r["fork3_position_mm"][-1] == pytest.approx(8.5)
    on_cone, engaged, slip_rpm, clashes = results[0]
    assert engaged - on_cone > 100 and abs(slip_rpm) < clash_rpm and clashes == 0  # synchronized
    on_cone, engaged, slip_rpm, clashes = results[1]
    # through at the first step on the cone, thousands of rpm apart: a clash
    assert engaged - on_cone <= 1 and abs(slip_rpm) > 10 * clash_rpm and clashes == 1


@pytest.mark.slow
def test_engine_torque_limited_at_full_pedal_and_on_request():
    peak = {}
    for limited in (0, 1):
        p = Plant(overrides=CMD)
        p.reset(vehicle_speed_kmh=60.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
        p.inputs["clutch1_pressure_bar"] = 20.0
        p.set_faults(engine_torque_limited=limited, engine_torque_max_nm=120.0)
        p.inputs["accel_pedal_pct"] = 100.0
        pedal = run(p, 3.0)["engine_torque_nm"]
        p.inputs["accel_pedal_pct"] = 0.0
        p.inputs["torque_request_active"] = 1.0
        p.inputs["engine_torque_request_nm"] = 400.0           # a TCU asking for more
        request = run(p, 2.0)["engine_torque_nm"]
        peak[limited] = (pedal.max(), request.max())
    assert min(peak[0]) > 250.0
    for torque in peak[1]:
        # the lag approaches the capped demand from below; the drag term moves
        # with the speed by far less than 0.1 Nm per step
        assert 110.0 < torque <= 120.0 + 0.1


# ------------------------------------------------------- cleared, in effect

def test_no_fault_effective_params_are_the_params_byte_for_byte():
    p = Plant()
    assert part(p, "effective") == part(p, "params")
    assert all(np.all(np.asarray(v) == 0.0) for v in p.faults.values())


ALL = dict(spool_stuck=[1, 1], solenoid_open=[1, 1], friction_loss=[0.3, 0.6],
           pack_gap_offset_mm=[0.5, -0.5], line_pressure_loss=0.4, fork_jammed=[1, 0, 1, 0],
           blocker_failed=[0, 1, 0, 1], engine_torque_limited=1, engine_torque_max_nm=90.0)


def test_cleared_faults_give_the_healthy_car_back():
    fresh = Plant(overrides=HYD)
    p = Plant(overrides=HYD)
    p.set_faults(**ALL)
    assert part(p, "effective") != part(p, "params")
    p.step(100)
    p.clear_faults()
    assert part(p, "effective") == part(p, "params")
    assert part(p, "derived") == part(fresh, "derived")
    assert p.faults == fresh.faults

    # a run after faults set and cleared is the healthy run, bit for bit
    q = Plant(overrides=HYD)
    q.set_faults(**ALL)
    q.clear_faults()
    for plant in (fresh, q):
        plant.inputs["accel_pedal_pct"] = 40.0
        plant.inputs["solenoid_current1_a"] = 0.6
        plant.inputs["fork_force1_n"] = 900.0
        plant.step(2000)
    assert np.array_equal(fresh.state, q.state)
    assert np.array_equal(fresh.output_values, q.output_values)


def test_faults_take_effect_at_prepare():
    # the C contract: set dct_plant.faults, then dct_plant_prepare
    p = Plant(overrides=HYD)
    p.inputs["solenoid_current1_a"] = 0.6
    p._p.faults.solenoid_open[0] = 1.0
    p.step(1)
    assert p.outputs["solenoid_current1_a"] == 0.6
    assert lib.dct_plant_prepare(p._p) == lib.DCT_OK
    p.step(1)
    assert p.outputs["solenoid_current1_a"] == 0.0
    assert p.faults["solenoid_open"] == [1.0, 0.0]


def test_set_faults_keeps_the_others_and_reads_back():
    p = Plant()
    p.set_faults(friction_loss={1: 0.25})
    p.set_faults(fork_jammed=(0, 0, 1, 0), engine_torque_limited=True, engine_torque_max_nm=150)
    f = p.faults
    assert set(f) == set(FAULT_NAMES)
    assert f["friction_loss"] == [0.0, 0.25]
    assert f["fork_jammed"] == [0.0, 0.0, 1.0, 0.0]
    assert f["engine_torque_limited"] == 1.0 and f["engine_torque_max_nm"] == 150.0
    assert p._p.effective.clutch[1].mu_static == p.params["clutch"][1]["mu_static"] * 0.75


def test_snapshot_leaves_the_faults_as_set():
    p = Plant(overrides=HYD)
    p.inputs["solenoid_current1_a"] = 0.7
    p.step(100)
    snap = p.snapshot()
    assert len(snap) == ffi.offsetof("dct_plant", "faults") - ffi.offsetof("dct_plant", "state")
    p.set_faults(solenoid_open=[1, 0])
    p.step(200)
    after = p.state.copy()
    p.restore(snap)
    assert p.faults["solenoid_open"] == [1.0, 0.0]     # faults are not in a snapshot
    p.step(200)
    assert np.array_equal(p.state, after)               # continues identically


# ------------------------------------------------------------- robustness

FAULT_CASES = {
    "spool_stuck": dict(spool_stuck=[1, 1]),
    "solenoid_open": dict(solenoid_open=[1, 1]),
    "friction_loss": dict(friction_loss=[0.9, 0.9]),
    "pack_gap_offset_mm": dict(pack_gap_offset_mm=[3.0, -1.5]),
    "line_pressure_loss": dict(line_pressure_loss=1.0),
    "fork_jammed": dict(fork_jammed=[1, 1, 1, 1]),
    "blocker_failed": dict(blocker_failed=[1, 1, 1, 1]),
    "engine_torque_limited": dict(engine_torque_limited=1, engine_torque_max_nm=0.0),
    "all": ALL,
}


@pytest.mark.slow
@pytest.mark.parametrize("case", FAULT_CASES)
def test_no_fault_makes_the_state_nan(case):
    """The reference TCU launches at full throttle through the gears; the
    fault strikes 3 s in (mid-launch, the first shifts) and stays for 7 s."""
    assert set(FAULT_NAMES) <= {k for c in FAULT_CASES.values() for k in c}
    p = Plant(overrides=HYD)
    strike = int(round(3.0 / PERIOD_S))

    def on_period(k, plant):
        if k == strike:
            plant.set_faults(**FAULT_CASES[case])

    rec = run_offline(p, ScriptedDriver(PAPER_CYCLE), 10.0, on_period=on_period)
    assert p.faults != Plant().faults
    assert np.all(np.isfinite(p.state))
    for name, values in rec.items():
        if isinstance(values, np.ndarray) and values.dtype.kind == "f":
            assert np.all(np.isfinite(values)), name


# ------------------------------------------------------------- bad values

BAD = [
    (dict(friction_los=0.5), "friction_los"),
    (dict(friction_loss=[1.5, 0]), "friction_loss[0]"),
    (dict(friction_loss={1: -0.1}), "friction_loss[1]"),
    (dict(line_pressure_loss=math.nan), "line_pressure_loss"),
    (dict(line_pressure_loss=2.0), "line_pressure_loss"),
    (dict(pack_gap_offset_mm=[0.0, -1.6]), "pack_gap_offset_mm[1]"),
    (dict(pack_gap_offset_mm=[math.inf, 0.0]), "pack_gap_offset_mm[0]"),
    (dict(engine_torque_max_nm=-5.0), "engine_torque_max_nm"),
    (dict(engine_torque_limited=3), "engine_torque_limited"),
    (dict(spool_stuck=1), "spool_stuck"),
    (dict(fork_jammed=[1, 0]), "fork_jammed"),
    (dict(blocker_failed={4: 1}), "blocker_failed"),
    (dict(solenoid_open=["yes", 0]), "solenoid_open[0]"),
]


@pytest.mark.parametrize("faults, named", BAD, ids=[n for _, n in BAD])
def test_bad_fault_values_raise_one_line_and_change_nothing(faults, named):
    p = Plant()
    p.set_faults(friction_loss=[0.2, 0.0])
    before = (p.faults, part(p, "effective"), part(p, "derived"))
    with pytest.raises(ValueError) as err:
        p.set_faults(**faults)
    msg = str(err.value)
    assert "\n" not in msg and named in msg
    assert (p.faults, part(p, "effective"), part(p, "derived")) == before


def test_fault_fields_are_the_c_struct():
    assert FAULT_FIELDS == {"spool_stuck": 2, "solenoid_open": 2, "friction_loss": 2,
                            "pack_gap_offset_mm": 2, "line_pressure_loss": 1,
                            "fork_jammed": lib.DCT_N_SLEEVES, "blocker_failed": lib.DCT_N_SLEEVES,
                            "engine_torque_limited": 1, "engine_torque_max_nm": 1}
