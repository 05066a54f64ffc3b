"""Model size: state count per component and step cost per component."""

import math

import numpy as np
import pytest

from plant.model import (
    COMPONENT_NAMES,
    STATE_NAMES,
    Plant,
    state_component,
    state_counts,
    state_kind,
)

HYDRAULICS = {"hydraulics": {"pressure_commanded": 0}}


@pytest.fixture(scope="module")
def driving():
    p = Plant(overrides=HYDRAULICS)
    p.reset(vehicle_speed_kmh=50.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    p.inputs["accel_pedal_pct"] = 20.0
    p.inputs["solenoid_current1_a"] = 1.0
    p.step(200)
    return p


def test_component_names_cover_the_assembly():
    assert COMPONENT_NAMES == ["hydraulics", "clutches", "engine", "driveline", "gearbox",
                               "tyres", "wheels", "vehicle", "thermal"]


def test_every_state_belongs_to_one_component():
    assert {state_component(n) for n in STATE_NAMES} == {"time", *COMPONENT_NAMES}


def test_counts_sum_to_the_state_size():
    counts = state_counts()
    assert list(counts) == ["time", *COMPONENT_NAMES]
    assert sum(counts.values()) == len(STATE_NAMES) == 73
    assert counts["engine"] == 6                  # speed, air-path torque, governor, fuel, running, spark cut
    assert counts["driveline"] == 2 + 2          # half-shaft twists, powertrain roll and its rate
    assert counts["gearbox"] == 3 + 4 * 6        # shafts, carrier, four synchronizers
    assert counts["hydraulics"] == 1 + 2 + 2 * 4  # line, two chambers, two valves
    assert counts["thermal"] == 3                 # coolant, engine oil, transmission oil


def test_kinds_partition_the_state():
    per_kind = {k: state_counts(k) for k in ("continuous", "discrete", "bookkeeping")}
    for comp in ["time", *COMPONENT_NAMES]:
        assert sum(per_kind[k][comp] for k in per_kind) == state_counts()[comp]
    assert state_kind("gearbox.sync[2].phase") == "discrete"
    assert state_kind("engine.running") == "discrete"
    assert state_kind("gearbox.sync[0].clashes") == "bookkeeping"
    assert state_kind("engine.fuel_g") == "bookkeeping"
    assert state_kind("vehicle.speed_m_s") == "continuous"
    assert sum(per_kind["bookkeeping"].values()) == 7
    assert sum(per_kind["discrete"].values()) == 9


def test_plant_state_counts_matches_the_function(driving):
    assert driving.state_counts() == state_counts()
    assert driving.state_counts("continuous") == state_counts("continuous")


def test_unknown_names_and_kinds_are_rejected():
    with pytest.raises(ValueError, match="no state named"):
        state_kind("engine.boost")
    with pytest.raises(ValueError, match="kind must be"):
        state_counts("algebraic")


def test_component_costs_are_positive_and_leave_the_plant_unchanged(driving):
    before = driving.snapshot()
    costs = driving.bench_components(300)
    assert list(costs) == COMPONENT_NAMES
    assert all(isinstance(v, float) and math.isfinite(v) and v > 0.0 for v in costs.values())
    assert driving.snapshot() == before


def test_component_costs_in_pressure_commanded_mode():
    p = Plant(overrides={"hydraulics": {"pressure_commanded": 1}})
    p.reset(vehicle_speed_kmh=20.0, sleeves=(1, 0, 0, 0), clutch_locked=(1, 0))
    p.inputs["clutch1_pressure_bar"] = 6.0
    p.step(10)
    state = p.state.copy()
    costs = p.bench_components(100)
    assert all(v > 0.0 for v in costs.values())
    np.testing.assert_array_equal(p.state, state)


def test_bench_components_rejects_a_bad_count(driving):
    with pytest.raises(ValueError, match="at least 1"):
        driving.bench_components(0)
    with pytest.raises(TypeError, match="integer"):
        driving.bench_components(2.5)
