"""Creep, reverse and hill start: the drivers' selector column and the maneuvers' fixed
inputs (the road grade), their figures on recorded data built here, the same driver
in C (tcu_stub/csrc/tcu_driver.c) and in Python to the bit, the closed-loop figures
within their bands, and the maneuvers through `dct-hil simulate`.

The closed-loop bands, with the reference TCU (tcu_stub/logic.py): creep 3-8 km/h on level
ground, 2-6 m backwards in R, at most 0.1 m of rollback on a 20 % grade.
"""

import math

import numpy as np
import pytest

from plant.driver import SELECTOR_CODES, ScriptedDriver, driver_inputs
from plant.maneuvers import (
    MANEUVERS,
    Maneuver,
    brake_applies,
    brake_releases,
    format_report,
    get_maneuver,
    mean_speed_kmh,
    report,
    reverse_figures,
    rollback_m,
    selector_times,
    speed_max_abs_kmh,
    time_to_speed_s,
)
from plant.model import Plant
from tcu_stub import fast
from tcu_stub.offline import run_offline

LOW_SPEED = ("creep", "reverse-park", "hill-start")


# ---------------------------------------------------------------------------
# the selector column
# ---------------------------------------------------------------------------

def test_a_selector_column_holds_each_position_from_its_row_on():
    d = ScriptedDriver([(0.0, 0.0, 30.0, "D"), (1.0, 0.0, 30.0, "r"), (2.0, 10.0, 0.0, 2),
                        (3.0, 0.0, 40.0, "P")])
    assert d.selector_table.tolist() == [3.0, 1.0, 2.0, 0.0]
    assert [d.selector(t) for t in (-1.0, 0.0, 0.99, 1.0, 2.5, 3.0, 9.0)] == [3, 3, 3, 1, 2, 0, 0]
    assert d(2.5) == (10.0, 0.0)                              # the pedals as before
    assert driver_inputs(d, 1.5, None) == {"accel_pedal_pct": 0.0, "brake_pedal_pct": 30.0,
                                           "selector_lever": 1.0}
    # linear pedals, the selector still held from its row on
    lin = ScriptedDriver([(0.0, 0.0, 30.0, "D"), (2.0, 20.0, 0.0, "R")], mode="linear")
    assert lin(1.0) == (10.0, 15.0) and lin.selector(1.99) == 3 and lin.selector(2.0) == 1


def test_a_three_column_table_is_unchanged_and_sets_no_selector():
    d = ScriptedDriver([(0.0, 0.0, 30.0), (1.0, 100.0, 0.0)])
    assert d.selector_table is None and d.selector(0.5) is None
    assert d.table.shape == (2, 3)
    assert driver_inputs(d, 1.5, None) == {"accel_pedal_pct": 100.0, "brake_pedal_pct": 0.0}
    assert driver_inputs(lambda t, o: (1.0, 2.0), 0.0, None) == {"accel_pedal_pct": 1.0,
                                                                 "brake_pedal_pct": 2.0}


@pytest.mark.parametrize("rows, message", [
    ([(0, 0, 30, "X")], "pedal profile row 1: unknown selector position 'X' (P, R, N or D)"),
    ([(0, 0, 30, "D"), (1, 0, 0, 4)], "pedal profile row 2: unknown selector position 4"),
    ([(0, 0, 30, "D"), (1, 0, 0, 1.5)], "pedal profile row 2: unknown selector position 1.5"),
    ([(0, 0, 30, "D"), (1, 0, 0)], "pedal profile row 2: 3 values, the first row has 4"),
    ([(0, 0, 130, "D")], "pedal profile: pedals must be within 0..100 %"),
])
def test_a_bad_selector_table_is_one_line_naming_it(rows, message):
    with pytest.raises(ValueError) as e:
        ScriptedDriver(rows)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_the_codes_are_the_dbc_signals_and_the_plants():
    from can_dbc import codec

    sig = codec.message("VEH_Driver").get_signal_by_name("SelectorLever")
    assert {str(v): int(k) for k, v in sig.choices.items()} == SELECTOR_CODES
    p = Plant()
    assert float(p.inputs["selector_lever"]) == SELECTOR_CODES["D"]       # the plant's default


# ---------------------------------------------------------------------------
# a maneuver's fixed inputs
# ---------------------------------------------------------------------------

def test_hill_start_sets_its_grade_from_the_start_and_others_leave_it():
    m = get_maneuver("hill-start")
    assert m.inputs == {"road_grade_pct": 20.0}
    p = Plant()
    m.start(p)
    assert float(p.inputs["road_grade_pct"]) == 20.0
    p.step(1)
    assert float(p.outputs["road_grade_pct"]) == 20.0
    assert get_maneuver("creep").inputs == {} and get_maneuver("0-100").inputs == {}


@pytest.mark.parametrize("inputs, message", [
    ({"road_grade_pct": 45.0}, "maneuver x: road_grade_pct = 45.0 is outside -40 .. 40"),
    ({"road_grade_pct": float("nan")}, "maneuver x: road_grade_pct = nan is outside -40 .. 40"),
    ({"road_grade_pct": "steep"}, "maneuver x: road_grade_pct must be a number, got 'steep'"),
    ({"accel_pedal_pct": 3.0}, "maneuver x: 'accel_pedal_pct' is not an input a maneuver fixes"),
])
def test_a_bad_fixed_input_is_one_line_naming_it(inputs, message):
    with pytest.raises(ValueError) as e:
        Maneuver("x", ScriptedDriver([(0, 0, 0)]), 1.0, (), inputs=inputs)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_the_low_speed_maneuvers_are_named_and_scripted():
    for name in LOW_SPEED:
        assert name in MANEUVERS
        m = get_maneuver(name)
        assert isinstance(m.driver, ScriptedDriver) and m.driver.selector_table is not None
        assert m.duration_s == m.driver.duration_s
    creep = get_maneuver("creep")
    assert brake_releases(creep) == [2.0, 32.0] and brake_applies(creep) == [20.0]
    rp = get_maneuver("reverse-park")
    assert selector_times(rp, "R") == [1.0] and selector_times(rp, "P") == [10.0]
    assert brake_releases(rp) == [3.0, 12.0]
    assert brake_releases(get_maneuver("hill-start")) == [3.0]


# ---------------------------------------------------------------------------
# the figures on recorded data built here
# ---------------------------------------------------------------------------

def _rec(t, v_kmh, gear=None):
    """A recording with the speed given and the distance its integral (trapezoids)."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(v_kmh, dtype=float)
    d = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / 3.6 * np.diff(t))])
    rec = {"time_s": t, "vehicle_speed_kmh": v, "distance_m": d}
    rec["gear"] = np.zeros_like(t) if gear is None else np.asarray(gear, dtype=float)
    for name in ("accel_pedal_pct", "fuel_l"):
        rec[name] = np.zeros_like(t)
    return rec


def test_speed_windows():
    t = np.arange(0.0, 10.0, 0.01)
    rec = _rec(t, np.where(t < 5.0, 2.0, 6.0))
    assert mean_speed_kmh(rec, 5.0, 10.0) == 6.0
    assert mean_speed_kmh(rec, 4.0, 6.0) == pytest.approx(4.0)
    assert speed_max_abs_kmh(_rec(t, -3.0 * np.sin(t)), 0.0, 10.0) == pytest.approx(3.0, abs=1e-4)


def test_rollback_is_the_most_negative_displacement_after_the_release():
    t = np.arange(0.0, 6.0, 0.01)
    # rolls back before the release (not counted), then 0.5 s at -1.8 km/h (0.25 m), then forward
    v = np.where(t < 1.0, -3.6, np.where(t < 2.0, 0.0, np.where(t < 2.5, -1.8, 7.2)))
    rec = _rec(t, v)
    assert rollback_m(rec, 2.0) == pytest.approx(0.25, abs=0.006)      # to a sample (5 mm)
    assert rollback_m(rec, 2.5) == 0.0
    assert rollback_m(_rec(t, np.full_like(t, 5.0)), 1.0) == 0.0


def test_time_to_speed_interpolates_the_crossing():
    t = np.arange(0.0, 10.0, 0.1)
    rec = _rec(t, np.maximum(0.0, 4.0 * (t - 3.0)))          # 10 km/h at 5.5 s
    assert time_to_speed_s(rec, 3.0, 10.0) == pytest.approx(2.5)
    assert time_to_speed_s(rec, 3.0, 50.0) is None


def test_reverse_figures():
    t = np.arange(0.0, 16.0, 0.01)
    v = np.where((t >= 3.0) & (t < 7.0), -4.5, 0.0)          # 4 s at 1.25 m/s backwards = 5 m
    gear = np.where(t >= 3.2, -1, 0)
    fig = reverse_figures(_rec(t, v, gear), 1.0, 10.0, 12.0)
    assert fig["reverse_engaged_s"] == pytest.approx(2.2)
    assert fig["reverse_distance_m"] == pytest.approx(5.0, abs=0.01)
    assert fig["reverse_speed_max_kmh"] == 4.5 and fig["park_creep_m"] == 0.0
    assert reverse_figures(_rec(t, v), 1.0, 10.0, 12.0)["reverse_engaged_s"] is None


def test_report_of_each_low_speed_maneuver_on_built_data():
    t = np.arange(0.0, 45.0, 0.01)
    v = np.where((t >= 2) & (t < 20), np.minimum(5.0, 5.0 * (t - 2)), 0.0)
    v = np.where(t >= 32, np.minimum(5.5, 5.5 * (t - 32)), v)
    fig = report("creep", _rec(t, v))
    assert fig == {"creep_speed_kmh": pytest.approx(5.0), "hold_speed_max_kmh": 0.0,
                   "creep_again_speed_kmh": pytest.approx(5.5)}
    assert "creep_speed_kmh = 5.00 km/h" in format_report("creep", fig)

    t = np.arange(0.0, 15.0, 0.01)
    v = np.where(t < 3.0, 0.0, np.where(t < 3.2, -0.9, 6.0 * (t - 3.2)))
    fig = report("hill-start", _rec(t, v))
    assert fig["rollback_m"] == pytest.approx(0.05, abs=0.006)
    assert fig["time_to_10kmh_s"] == pytest.approx(0.2 + 10.0 / 6.0, abs=0.01)

    t = np.arange(0.0, 16.0, 0.01)
    fig = report("reverse-park", _rec(t, np.where((t >= 3) & (t < 7), -3.6, 0.0),
                                      np.where(t >= 3.5, -1, 0)))
    assert fig["reverse_distance_m"] == pytest.approx(4.0, abs=0.01)
    assert fig["reverse_engaged_s"] == pytest.approx(2.5)


def test_a_run_cut_short_gives_no_figure_for_the_phases_it_did_not_reach():
    t = np.arange(0.0, 1.0, 0.01)
    fig = report("creep", _rec(t, np.zeros_like(t)))
    assert fig == {"creep_speed_kmh": None, "hold_speed_max_kmh": None, "creep_again_speed_kmh": None}
    assert report("hill-start", _rec(t, np.zeros_like(t))) == {"rollback_m": None,
                                                                "time_to_10kmh_s": None}


# ---------------------------------------------------------------------------
# the selector in the C driver, to the bit
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["step", "linear"])
def test_the_c_driver_gives_the_python_drivers_selector_and_pedals(mode):
    ffi, lib = fast._lib()
    shipped = get_maneuver("reverse-park").driver
    py = ScriptedDriver([(*r, s) for r, s in zip(shipped.table.tolist(), shipped.selector_table)],
                        mode=mode)
    d, keep = ffi.new("tcu_driver *"), []
    assert fast.fill_driver(d, py, keep)
    out = ffi.new("dct_outputs *")
    accel, brake = ffi.new("double *"), ffi.new("double *")
    for t in np.concatenate([np.arange(-1.0, 17.0, 0.01), [1.0, 3.0, 10.0, 12.0]]):
        t = float(t)
        lib.tcu_driver_pedals(d, t, out, accel, brake)
        assert (accel[0], brake[0]) == py(t)
        assert lib.tcu_driver_selector(d, t) == py.selector(t)
    d3 = ffi.new("tcu_driver *")
    assert fast.fill_driver(d3, ScriptedDriver([(0, 0, 30), (1, 10, 0)]), keep)
    assert lib.tcu_driver_selector(d3, 0.5) == -1.0               # no column: leaves the selector


class _PythonDriver:
    """The same table, called from Python (EXTERNAL in the C loop)."""

    def __init__(self, d):
        self.d = d

    def __call__(self, t_s, outputs):
        return self.d(t_s, outputs)

    def selector(self, t_s):
        return self.d.selector(t_s)


@pytest.mark.slow
@pytest.mark.parametrize("name", LOW_SPEED)
def test_the_c_loop_plays_the_selector_and_grade_as_the_python_driver(name):
    """The C driver against the Python driver between C calls, and the Python loop:
    every recorded plant output the same double (the selector, the parking lock, the grade)."""
    m = get_maneuver(name)
    recs = []
    for driver in (m.driver, _PythonDriver(m.driver)):
        p = Plant()
        m.start(p)
        loop = fast.FastLoop(p, driver, m.duration_s)
        assert loop.driver_in_c == (driver is m.driver)
        loop.step()
        recs.append(loop.recorded())
    for k in recs[0]:
        assert np.array_equal(recs[0][k], recs[1][k]), k
    rec = recs[0]
    sel = m.driver.selector_table
    for t_row, code in zip(m.driver.table[:, 0], sel):
        k = int(round(t_row / 0.01)) + 2       # the driver's call at or after the row, then a step
        if k < len(rec["time_s"]):
            assert rec["selector_lever"][k] == code, (name, t_row)
    assert np.all(rec["road_grade_pct"][1:] == m.inputs.get("road_grade_pct", 0.0))
    if name == "reverse-park":                       # P at the end: the parking lock
        assert rec["park_lock_engaged"][-1] == 1.0
    # run_offline's Python loop sets it too (driver_inputs), every 10 ms
    seen = {}
    p = Plant()
    m.start(p)
    run_offline(p, m.driver, m.duration_s, tcu_impl="python",
                on_period=lambda k, plant: seen.setdefault(k, (plant.time_s, float(plant.inputs["selector_lever"]),
                                                               float(plant.inputs["road_grade_pct"]))))
    for k in range(0, len(seen), 5):
        t, selector, grade = seen[k]
        assert (selector, grade) == (m.driver.selector(t), m.inputs.get("road_grade_pct", 0.0)), (name, k)


# ---------------------------------------------------------------------------
# closed loop: the figures within their bands
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs():
    out = {}
    for name in LOW_SPEED:
        m = get_maneuver(name)
        p = Plant()
        m.start(p)
        rec = run_offline(p, m.driver, m.duration_s)
        out[name] = (rec, report(m, rec))
    return out


def test_creep_rolls_at_a_few_kmh_and_holds_on_the_brake(runs):
    rec, fig = runs["creep"]
    assert 3.0 <= fig["creep_speed_kmh"] <= 8.0, fig
    assert 3.0 <= fig["creep_again_speed_kmh"] <= 8.0, fig
    assert fig["hold_speed_max_kmh"] < 0.1, fig
    assert rec["gear_clashes"][-1] == 0 and not rec["shifts"]


def test_reverse_park_reverses_a_few_metres_in_r_and_parks(runs):
    rec, fig = runs["reverse-park"]
    assert fig["reverse_engaged_s"] is not None, fig                  # gear R, seen by the plant
    assert 2.0 <= fig["reverse_distance_m"] <= 6.0, fig               # backwards
    assert fig["park_creep_m"] < 0.05, fig
    t = rec["time_s"]
    moving = (t > 3.0) & (t < 10.0) & (rec["vehicle_speed_kmh"] < -0.5)
    assert np.any(moving) and np.all(rec["gear"][moving] == -1)
    assert rec["gear_clashes"][-1] == 0


def test_hill_start_does_not_roll_back_and_drives_away(runs):
    rec, fig = runs["hill-start"]
    assert fig["rollback_m"] <= 0.1, fig
    assert fig["time_to_10kmh_s"] is not None and fig["time_to_10kmh_s"] < 8.0, fig
    assert rec["gear_clashes"][-1] == 0


# ---------------------------------------------------------------------------
# dct-hil simulate --scenario
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", LOW_SPEED)
def test_simulate_plays_them_with_the_grade_and_selector(name, tmp_path, capsys):
    from dct_hil.cli import main

    out = tmp_path / f"{name}.csv"
    assert main(["simulate", "--scenario", name, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"maneuver          {name}" in text and f"report            {name}: " in text
    header = out.read_text().splitlines()[0].split(",")
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    col = {n: data[:, k] for k, n in enumerate(header)}
    m = get_maneuver(name)
    assert np.all(col["road_grade_pct"][1:] == m.inputs.get("road_grade_pct", 0.0))
    assert set(np.unique(col["selector_lever"])) == set(np.unique(m.driver.selector_table))
    assert math.isclose(col["time_s"][-1], m.duration_s)


# ---------------------------------------------------------------------------
# over CAN: the demo on the embedded transport
# ---------------------------------------------------------------------------

@pytest.mark.slow
def test_the_demo_plays_reverse_park_over_can_with_the_selector(tmp_path):
    """The first 4 s of reverse-park: the loop's scripted driver moves the selector from D
    to R at 1 s, the plant sends it in VEH_Driver.SelectorLever and the TCU reads it."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from rt_loop.measure.recorder import read_recording

    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", "--maneuver", "reverse-park",
                           "--duration", "4", "--out", str(tmp_path), "--priority", "0", "--quiet"],
                          capture_output=True, text=True, timeout=120, cwd=repo)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["maneuver"] == "reverse-park" and summary["completed"]
    assert set(summary["figures"]) == set(get_maneuver("reverse-park").report)
    rec = read_recording(tmp_path / "plant.csv")
    started = rec["maneuver_time_s"] >= 0
    mt, sel = rec["maneuver_time_s"][started], rec["selector_lever"][started]
    assert (sel[mt < 0.99] == 3).all() and (sel[mt > 1.01] == 1).all()
    assert (rec["brake_pedal_pct"][started][(mt > 1.01) & (mt < 2.99)] == 40).all()
    # on the bus (can.log, candump format): D, then R; the transmission oil warm
    from can_dbc import codec

    seen = {"VEH_Driver": [], "DCT_Shift": []}
    for line in (tmp_path / "can.log").read_text().splitlines():
        ident, _, data = line.split()[2].partition("#")
        name = {0x121: "VEH_Driver", 0x110: "DCT_Shift"}.get(int(ident, 16))
        if name:
            seen[name].append(codec.decode(int(ident, 16), bytes.fromhex(data))[1])
    levers = [v["SelectorLever"] for v in seen["VEH_Driver"]]
    assert levers[0] == 3 and levers[-1] == 1 and set(levers) == {1, 3}
    assert all(20 < v["TransOilTemp"] < 130 for v in seen["DCT_Shift"])
    tcu = json.loads((tmp_path / "tcu-report.json").read_text())
    assert tcu["error"] is None and tcu["received"]["VEH_Driver"]["accepted"] > 300
