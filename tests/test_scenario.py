"""Scenario CSV files: parsing, hold semantics, initial conditions, errors."""

import numpy as np
import pytest

from plant._dct_plant import ffi
from plant.scenario import ScenarioError, load_scenario, shipped_names

INPUTS = [name for name, _ in ffi.typeof("dct_inputs").fields]


def write(tmp_path, text, name="s.csv"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


GOOD = """\
# a comment
# initial: vehicle_speed_kmh=50, sleeve2_side=-1, clutch2_locked=1

time_s, accel_pedal_pct ,road_grade_pct
0,10,0
0.1,20,5
# comments may sit between rows
0.10025,30,5
0.3,0,0
"""


def test_parses_columns_rows_initial_and_duration(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    assert sc.name == "s"
    assert sc.columns == ["accel_pedal_pct", "road_grade_pct"]
    np.testing.assert_array_equal(sc.times, [0, 0.1, 0.10025, 0.3])
    np.testing.assert_array_equal(sc.values, [[10, 0], [20, 5], [30, 5], [0, 0]])
    assert sc.duration_s == 0.3
    assert sc.initial == {"vehicle_speed_kmh": 50.0, "sleeve2_side": -1.0, "clutch2_locked": 1.0}


def test_initial_conditions_become_reset_arguments(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    assert sc.reset_kwargs() == {
        "vehicle_speed_kmh": 50.0,
        "sleeves": (0.0, -1.0, 0.0, 0.0),
        "clutch_locked": (0.0, 1.0),
        "engine_on": 1.0,  # not given: default
    }


def test_rows_hold_until_the_next_row(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    # applied before the first step whose start time is >= the row time
    np.testing.assert_array_equal(sc.row_steps(0.0005), [0, 200, 201, 600])
    np.testing.assert_array_equal(sc.values_at(0.0), [10, 0])
    np.testing.assert_array_equal(sc.values_at(0.0999), [10, 0])
    np.testing.assert_array_equal(sc.values_at(0.1), [20, 5])
    np.testing.assert_array_equal(sc.values_at(0.2), [30, 5])
    np.testing.assert_array_equal(sc.values_at(5.0), [0, 0])  # the last row holds


def test_rows_drive_the_plant_stepwise(tmp_path):
    from plant.model import Plant
    from plant.simulate import run

    sc = load_scenario(write(tmp_path, "time_s,road_grade_pct\n0,0\n0.1,5\n0.25,-3\n0.5,-3\n"))
    plant = Plant()
    res = run(plant, sc)
    t = res.data[:, res.names.index("time_s")]
    grade = res.data[:, res.names.index("road_grade_pct")]
    np.testing.assert_allclose(grade[(t > 0) & (t < 0.1 - 1e-9)], 0)
    np.testing.assert_allclose(grade[(t > 0.1 + 1e-9) & (t < 0.25 - 1e-9)], 5)
    np.testing.assert_allclose(grade[t > 0.25 + 1e-9], -3)
    # inputs without a column keep the plant's defaults
    for name in INPUTS:
        if name != "road_grade_pct":
            assert plant.inputs[name] == plant.default_inputs[name], name


def test_shipped_scenarios_load_by_name():
    names = shipped_names()
    assert {"launch-1st", "coastdown"} <= set(names)
    for name in names:
        sc = load_scenario(name)
        assert sc.name == name
        assert sc.times[0] == 0 and sc.duration_s > 0
        assert set(sc.columns) <= set(INPUTS)


def test_unknown_name_lists_the_shipped_ones():
    with pytest.raises(ScenarioError) as e:
        load_scenario("no-such-scenario")
    msg = str(e.value)
    assert "no-such-scenario" in msg and "launch-1st" in msg and "\n" not in msg


def test_missing_file_is_named(tmp_path):
    path = str(tmp_path / "absent.csv")
    with pytest.raises(ScenarioError, match="absent.csv"):
        load_scenario(path)


# (file text, line number in the message, part of the cause)
BAD = {
    "unknown column": ("time_s,accel_pedal_pct,warp_drive\n0,1,2\n", 1, "unknown column 'warp_drive'"),
    "first column": ("accel_pedal_pct,time_s\n0,0\n", 1, "first column must be time_s"),
    "duplicate column": ("time_s,accel_pedal_pct,accel_pedal_pct\n0,1,2\n", 1, "appears twice"),
    "nan cell": ("time_s,accel_pedal_pct\n0,1\n1,nan\n", 3, "accel_pedal_pct: 'nan' is not a finite number"),
    "non-numeric cell": ("# c\ntime_s,accel_pedal_pct\n0,full\n", 3, "'full' is not a number"),
    "empty cell": ("time_s,accel_pedal_pct\n0,\n", 2, "'' is not a number"),
    "too few cells": ("time_s,accel_pedal_pct,brake_pedal_pct\n0,1,2\n1,1\n", 3, "2 cells, the header has 3"),
    "too many cells": ("time_s,accel_pedal_pct\n0,1,2\n", 2, "3 cells, the header has 2"),
    "time goes back": ("time_s,accel_pedal_pct\n0,1\n2,1\n1,1\n", 4, "time 1 does not increase"),
    "time repeats": ("time_s,accel_pedal_pct\n0,1\n1,1\n1,2\n", 4, "does not increase"),
    "start not at 0": ("time_s,accel_pedal_pct\n0.5,1\n", 2, "first row must be at time 0"),
    "unknown initial key": ("# initial: warp=1\ntime_s\n0\n", 1, "unknown initial key 'warp'"),
    "bad initial value": ("time_s\n# initial: sleeve1_side=2\n0\n", 2, "sleeve1_side must be one of"),
    "initial not key=value": ("# initial: engine_on\ntime_s\n0\n", 1, "not key=value"),
    "initial not a number": ("# initial: vehicle_speed_kmh=fast\ntime_s\n0\n", 1, "not a number"),
    "empty file": ("", 1, "empty file"),
    "only comments": ("# nothing\n# here\n", 2, "empty file"),
    "no rows": ("time_s,accel_pedal_pct\n", 1, "no data rows"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_errors_are_one_line_naming_file_and_line(tmp_path, case):
    text, line, cause = BAD[case]
    path = write(tmp_path, text, "bad.csv")
    with pytest.raises(ScenarioError) as e:
        load_scenario(path)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}:{line}: "), msg
    assert cause in msg, msg
