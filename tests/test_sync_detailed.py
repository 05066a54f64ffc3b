"""The detailed synchronizer reference model (validation/sync_detailed.py) and its
comparison with the plant's hybrid synchronizer.

The detailed model is checked against physics it must obey (momentum, the cone
friction law while sliding, blocking, turn-back, dog-tooth alignment, step
convergence); the comparison against what it must deliver (coupling times,
their error, series for the overlay plot). Every tolerance says why.
"""

import math
from dataclasses import replace

import numpy as np
import pytest

from validation import sync_detailed as sd

RPM = math.pi / 30.0


@pytest.fixture(scope="module")
def p():
    return sd.DetailedParams.from_plant()


@pytest.fixture(scope="module")
def run600(p):
    """600 N, 1000 rpm: the reference case, with its series."""
    case = sd.Case(600.0, 1000.0)
    return sd.simulate_detailed(case, p, t_end_s=sd._t_end(case))


def momentum(x, j_gear, j_shaft, j_ring):
    return j_gear * x["w_g"] + j_shaft * x["w_h"] + j_ring * x["w_r"]


def test_parameters_are_the_plants(p):
    from plant.params import load_params
    sync = load_params()["gearbox"]["sync"][sd.SLEEVE]
    for key in ("cone_mu", "cone_radius_m", "cone_half_angle_deg", "sleeve_mass_kg",
                "sleeve_damping_ns_per_m", "cone_travel_mm", "engaged_travel_mm",
                "detent_force_n", "lock_speed_rad_s", "dog_friction_mu"):
        assert getattr(p, key) == sync[key], key
    assert p.tooth_radius_m == sync["dog_radius_m"]
    assert p.chamfer_angle_deg == sync["ring_chamfer_angle_deg"]
    # the plant's ring-pass travel is the detailed geometry's (given to 0.1 um)
    assert sync["ring_pass_travel_mm"] == pytest.approx(p.ring_pass_travel_mm, abs=1e-4)
    # the geometry blocks at the plant's cone travel and clears before the dog teeth
    assert p.blocking_offset_m < p.tooth_width_pitch * p.pitch_m
    assert p.cone_travel_mm * 1e-3 < p.through_travel_m < p.dog_tip_mm * 1e-3


def test_momentum_conserved_without_friction_and_drag(p):
    # light shaft side so that the exchange is visible; no cone or tooth
    # friction and no drag: only contact forces between the bodies remain
    # (the ring, unindexed, lets the sleeve pass; the dog chamfers then ratchet
    # and align the gear). Semi-implicit Euler applies every pair of internal
    # forces as equal and opposite impulses, so the total angular momentum is
    # kept to rounding: 1e-12 of its value over some 4 10^4 steps (measured 1e-15)
    case = sd.Case(300.0, 40.0, shaft_inertia_kgm2=0.05, dog_phase_pitch=0.3)
    c = case.resolved()
    start = {"w_g": (c.shaft_speed_rpm + c.slip_rpm) * RPM, "w_h": c.shaft_speed_rpm * RPM,
             "w_r": c.shaft_speed_rpm * RPM}
    run = sd.simulate_detailed(case, p, t_end_s=0.15, stop_after_s=None, friction=False,
                               drag=False)
    x = run.extra
    j = (x["gear_inertia_kgm2"], x["shaft_inertia_kgm2"], x["ring_inertia_kgm2"])
    h0, h1 = momentum(start, *j), momentum(x, *j)
    assert abs(h1 - h0) <= 1e-12 * abs(h0)
    # and momentum was exchanged: the dog teeth reversed the slip (without
    # friction the engaged gear rattles in its backlash, +-30 rpm)
    assert run.series["slip_rpm"].min() < -0.5 * c.slip_rpm
    assert run.t_full_s == run.t_full_s  # the sleeve got in


def test_cone_torque_follows_the_cone_law_while_slipping(p, run600):
    # T = mu r_s F / sin(alpha): sliding at the capacity of the axial cone
    # contact (exact: that is the sliding state of the friction element), and
    # the axial force is the fork force once the blocking transient has died
    # out: the sleeve and ring stand still, the force path sleeve -> chamfer ->
    # ring -> cone is static. The transient decays with the sleeve damping on
    # the chamfer contact (about 1.5 ms); 10 ms after blocking it is below
    # 0.5 %
    s, run = run600.series, run600
    gain = p.cone_mu * p.cone_radius_m / math.sin(math.radians(p.cone_half_angle_deg))
    t = s["time_s"]
    m = (t > run.t_block_s + 0.010) & (t < run.t_sync_s - 0.010)
    assert m.sum() > 100
    tc = s["cone_torque_nm"][m]
    np.testing.assert_allclose(tc, gain * s["ring_axial_force_n"][m], rtol=1e-9)
    np.testing.assert_allclose(tc, gain * s["fork_force_n"][m], rtol=0.005)
    assert np.all(s["slip_rpm"][m] > 0) and np.all(tc > 0)  # braking the faster gear


def test_blocker_indexed_and_keeps_the_sleeve_out_while_slipping(p, run600):
    s, run = run600.series, run600
    t = s["time_s"]
    slipping = (t > run.t_block_s) & (np.abs(s["slip_rpm"]) * RPM > p.lock_speed_rad_s)
    slipping &= t < run.t_sync_s
    # indexing: the ring is dragged by the cone to the end of its slot (the
    # gear is faster: + side) and stays there, its chamfers against the sleeve's
    slot_mm = p.slot_play_pitch * p.pitch_m * 1e3
    offset = s["ring_offset_mm"][slipping]
    # the cone torque (21 Nm) presses the ring's lug 0.024 mm into its stop, a little more
    # in the impact at blocking: within 0.05 mm
    assert np.all(offset > slot_mm) and np.all(offset < slot_mm + 0.05)
    # the sleeve stays on the ring's chamfers: at the cone travel (penetration of the
    # chamfer and cone contacts: below 0.1 mm at 600 N), far from passing through
    sleeve = s["sleeve_mm"][slipping]
    assert np.all(sleeve < p.cone_travel_mm + 0.1)
    assert np.all(sleeve > p.cone_travel_mm - 0.1)
    assert run.t_through_s > run.t_sync_s


def test_speeds_match_before_the_sleeve_passes(p, run600):
    s, run = run600.series, run600
    t = s["time_s"]
    before = t < run.t_sync_s
    # the slip falls through the lock speed while the sleeve is still blocked ...
    i = np.searchsorted(t, run.t_sync_s)
    assert s["sleeve_mm"][i] * 1e-3 < p.through_travel_m
    assert np.all(s["sleeve_mm"][before] * 1e-3 < p.through_travel_m)
    # ... then the sleeve turns the ring (and the stuck cone with the gear) back
    # out of the way: the ring leaves its slot end only after synchronization
    moved = np.abs(s["ring_offset_mm"] - s["ring_offset_mm"][i]) > 0.05
    assert t[np.argmax(moved & (t > run.t_block_s + 0.01))] > run.t_sync_s
    # the sleeve gets through and to full engagement
    assert run.t_sync_s < run.t_through_s < run.t_full_s


def test_dog_chamfers_turn_the_gear_into_alignment(p):
    # sleeve past the ring, gear at the shaft speed but 0.3 of a pitch out of
    # line: the sleeve's apexes land on the dog teeth's chamfers
    pitch = p.pitch_m
    case = sd.Case(300.0, 0.0, dog_phase_pitch=0.3)
    start = {"x_s": 4.5e-3, "x_r": p.ring_axial_play_mm * 1e-3}
    run = sd.simulate_detailed(case, p, t_end_s=0.2, stop_after_s=None, drag=False,
                               initial=start)
    x = run.extra
    assert run.t_full_s == run.t_full_s
    assert x["x_s"] == pytest.approx(p.engaged_travel_mm * 1e-3, abs=0.05e-3)
    s = run.series
    late = s["time_s"] > s["time_s"][-1] - 0.05
    v = np.abs(s["dog_offset_mm"][late]) * 1e-3
    # aligned: the sleeve's teeth sit in the dog gaps, within the backlash
    # (gap - tooth width) / 2 either side. Without drag the gear keeps rattling
    # in it; its impacts press the flanks in by up to about 0.1 mm (the gear,
    # 34 kg at the tooth radius, at 1-2 rad/s on the 2e7 N/m contact)
    backlash = (0.5 - p.tooth_width_pitch) * pitch
    assert np.all(v <= backlash + 0.15e-3)
    # turned from 0.3 pitch (2.4 mm) towards the nearer gap: the chamfers did it
    assert s["dog_offset_mm"][0] == pytest.approx(0.3 * pitch * 1e3)
    assert run.t_full_s < 0.1   # 4 mm of travel at 300 N against 2000 Ns/m, and the turning


def test_step_converged(p):
    # coupling time at the quick step (8 us), the default (4 us) and 1 us:
    # agree within 0.05 %, i.e. the integration error is far below the 3 % compared
    case = sd.Case(900.0, 500.0)
    t = [sd.simulate_detailed(case, replace(p, step_s=h), t_end_s=sd._t_end(case),
                              record=False).coupling_time_s for h in (8e-6, 4e-6, 1e-6)]
    assert t[0] == pytest.approx(t[2], rel=5e-4)
    assert t[1] == pytest.approx(t[2], rel=5e-4)


def test_coupling_time_falls_as_fork_force_rises(p):
    detailed, hybrid = [], []
    for force in sd.FORCES_N:
        case = sd.Case(force, 1000.0)
        detailed.append(sd.simulate_detailed(case, p, t_end_s=sd._t_end(case),
                                             record=False).coupling_time_s)
        hybrid.append(sd.simulate_hybrid_c(case, t_end_s=sd._t_end(case),
                                           record=False).coupling_time_s)
    assert detailed[0] > detailed[1] > detailed[2]
    assert hybrid[0] > hybrid[1] > hybrid[2]
    # roughly as 1 / F (the slip phase dominates): 300 -> 900 N cuts it by 2.2-3x
    assert 2.2 < detailed[0] / detailed[2] < 3.0


def test_python_replica_matches_the_c_component():
    # the replica (used for the like-for-like timing and the proposal) runs the
    # same law at the same step: identical event times up to one sub-step
    h = sd.plant_substep_s()
    for force, slip in ((300.0, 1000.0), (900.0, -800.0)):
        case = sd.Case(force, slip)
        c = sd.simulate_hybrid_c(case, t_end_s=sd._t_end(case), record=False)
        py = sd.simulate_hybrid_py(case, t_end_s=sd._t_end(case))
        for key in ("t_block_s", "t_sync_s", "t_through_s", "t_full_s"):
            assert getattr(py, key) == pytest.approx(getattr(c, key), abs=1.01 * h), key


def test_compare_reports_the_coupling_time_error():
    r = sd.compare(fork_force_n=600.0, slip_rpm=1000.0, quick=True)
    td, th = r["coupling_time_detailed_s"], r["coupling_time_hybrid_s"]
    assert 0.2 < td < 0.6 and 0.2 < th < 0.6
    assert r["coupling_time_error_pct"] == pytest.approx(100.0 * (th - td) / td)
    # the slip phases agree within 3 %, and so does the passage through the
    # ring (20.6 ms against 19.3 ms): the ring turn-back term moves the gear
    # side's inertia with the sleeve, as the detailed model's chamfers do
    # (within 25 %: 5 ms; without the term the hybrid sleeve took 3-8 ms)
    slip_d = r["sync_time_detailed_s"] - r["block_time_detailed_s"]
    slip_h = r["sync_time_hybrid_s"] - r["block_time_hybrid_s"]
    assert slip_h == pytest.approx(slip_d, rel=0.03)
    assert r["ring_pass_hybrid_s"] == pytest.approx(r["ring_pass_detailed_s"], rel=0.25)
    assert r["hybrid_clashes"] == 0
    for model in ("detailed", "hybrid"):
        s = r["series"][model]
        n = len(s["time_s"])
        assert n > 100
        for key in ("sleeve_mm", "slip_rpm", "cone_torque_nm"):
            assert len(s[key]) == n and np.all(np.isfinite(s[key]))
        assert s["sleeve_mm"][-1] == pytest.approx(8.5, abs=0.1)


def test_turn_back_term_meets_the_bound_in_the_replica():
    # the ring turn-back term (the gear's inertia reflected onto the sleeve
    # until the ring is passed), in the Python replica: within 3 % of the
    # detailed model, and closer than without it
    for row in sd.propose(quick=True):
        assert abs(row["error_turn_back_pct"]) <= 3.0
        assert abs(row["error_turn_back_pct"]) < abs(row["error_pct"])


@pytest.mark.slow
def test_plant_hybrid_meets_the_3_percent_bound():
    # the paper's check: the plant's hybrid synchronizer (the C component, with
    # the ring turn-back term) within 3 % of the detailed model's coupling time
    # in every case of the comparison (measured +0.36 .. +1.28 %)
    for force, slip in sd.cases():
        r = sd.compare(force, slip)
        assert abs(r["coupling_time_error_pct"]) <= 3.0, (force, slip, r["coupling_time_error_pct"])
        assert r["hybrid_clashes"] == 0


def test_compute_times_are_reported():
    t = sd.compute_times(sim_s=0.05)
    for key in ("detailed_python_s", "hybrid_python_s", "hybrid_c_from_python_s"):
        assert t[key] > 0.0
    assert t["sim_s"] == 0.05


@pytest.mark.parametrize("kwargs", [dict(fork_force_n=-5.0), dict(fork_force_n=float("nan")),
                                    dict(slip_rpm=float("inf"))])
def test_bad_input_is_one_line_error(kwargs):
    with pytest.raises(ValueError) as e:
        sd.compare(**kwargs)
    assert "\n" not in str(e.value)
