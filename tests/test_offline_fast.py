"""The compiled closed loop (tcu_stub/fast.py, tcu_stub/csrc) against the reference.

tcu_stub/logic.py (with diagnostics.py), offline.ContractLink and plant/driver.py
are the truth. The C port keeps their order of operations in IEEE 754 double
(the C is compiled with -std=c11: no contraction into fused multiply-adds) and
Python's min/max on ties, so the tolerance is zero throughout: every command of
every period is the same double as the Python TCU's for the same sensors, the
link gives the same quantised values as the DBC codec, and the closed-loop runs
(shift times, figures, recordings) are identical. A difference of any size is a
divergence of the port, not rounding.

- lockstep: the C loop runs a whole cycle (WLTC 1800 s, paper-cycle, 0-100) and
  the Python TcuLogic steps on the very sensors the C TCU saw, period by period;
  their commands (all 18 signals) must be equal in every period, and their states
  at the end;
- the link: random values through the C link and through codec.encode/decode,
  with the cycle plan of ContractLink;
- closed loops, C against Python: paper-cycle, 0-100, a WLTC section, runs with
  plant faults that set trouble codes, a calibration, a TcuLogic taken over;
  the whole WLTC with the Python driver against the C driver;
- dct-hil simulate: the same CSV from both loops; Ctrl-C and a plant error in the
  C loop.

No timing is asserted (the benchmark is ``python -m tcu_stub.bench_offline``).
"""

import dataclasses
import math

import numpy as np
import pytest

from can_dbc import codec
from plant.maneuvers import get_maneuver, report
from plant.model import INPUT_NAMES, OUTPUT_NAMES, Plant, PlantError
from tcu_stub import contract_link, fast, logic, offline
from tcu_stub.logic import TcuLogic
from tcu_stub.offline import run_offline

TRACE_CHUNK = 50_000            # periods between two lockstep comparisons (100 s)


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------

def state_of(obj):
    """Everything a TcuLogic holds, recursively, with the Python types (for ==)."""
    if isinstance(obj, (list, tuple)):
        return (type(obj).__name__, [state_of(x) for x in obj])
    if isinstance(obj, dict):
        return ("dict", {k: state_of(v) for k, v in obj.items()})
    if hasattr(obj, "__dict__") or hasattr(type(obj), "__slots__"):
        names = list(getattr(obj, "__dict__", {})) + list(getattr(type(obj), "__slots__", ()))
        return (type(obj).__name__, {n: state_of(getattr(obj, n)) for n in names if n != "_handlers"})
    if isinstance(obj, (frozenset, set)):
        return (type(obj).__name__, sorted(obj))
    return (type(obj).__name__, obj)


def assert_same_state(a, b):
    sa, sb = state_of(a), state_of(b)
    if sa != sb:
        diffs = []

        def walk(x, y, path):
            if x == y:
                return
            if isinstance(x, tuple) and isinstance(y, tuple) and len(x) == len(y) == 2 and x[0] == y[0] \
                    and isinstance(x[1], (dict, list)):
                if isinstance(x[1], dict):
                    for k in set(x[1]) | set(y[1]):
                        walk(x[1].get(k), y[1].get(k), f"{path}.{k}")
                else:
                    for i, (u, v) in enumerate(zip(x[1], y[1])):
                        walk(u, v, f"{path}[{i}]")
                    if len(x[1]) != len(y[1]):
                        diffs.append(f"{path}: {len(x[1])} vs {len(y[1])} items")
                return
            diffs.append(f"{path}: {x} vs {y}")

        walk(sa, sb, "tcu")
        raise AssertionError("states differ: " + "; ".join(diffs[:5]))


def assert_same_run(a, b):
    """Two run_offline results: the same keys, types and values (exactly)."""
    assert list(a) == list(b)
    assert a["shifts"] == b["shifts"]
    assert a["tcu_phase"] == b["tcu_phase"]
    for k in a:
        if k in ("shifts", "tcu_phase"):
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert np.array_equal(x, y), (k, float(np.max(np.abs(x - y))))


def maneuver_run(name, duration_s=None, tcu_impl="auto", **kw):
    m = get_maneuver(name)
    plant = Plant()
    plant.reset(**m.reset_kwargs)
    return run_offline(plant, m.driver, duration_s or m.duration_s, tcu_impl=tcu_impl, **kw)


def lockstep(name, duration_s=None, python_driver=False, faults=None, driver=None, inputs=None, reset=None,
             calibration=None):
    """The C loop over a maneuver with the Python TCU stepping on the same sensors:
    (C's recording, periods compared). Asserts equal commands every period and
    equal states at the end. ``python_driver``: the driver runs in Python (the
    SpeedTrackingDriver as a plain callable); ``faults``: (t_s, {fault: value}) plant
    faults in effect from that period's plant step on. ``driver``: a pedal function
    (t_s, outputs) -> (accel %, brake %) instead of the maneuver's (``name`` then only
    names the run), with plant ``inputs`` set at the start (e.g. the road grade). ``reset``:
    the plant's reset arguments (a cold start); ``calibration``: both TCUs' calibration."""
    plant = Plant()
    if driver is None:
        m = get_maneuver(name)
        plant.reset(**dict(m.reset_kwargs, **(reset or {})))
        driver = (lambda t, o: m.driver(t, o)) if python_driver else m.driver
        duration = duration_s or m.duration_s
    else:
        plant.reset(**(reset or {}))
        from plant.driver import ScriptedDriver
        python_driver, duration = not isinstance(driver, ScriptedDriver), duration_s
    for key, value in (inputs or {}).items():
        plant.inputs[key] = value
    k_fault = int(round(faults[0] / logic.PERIOD_S)) if faults else -1
    c_tcu = fast.python_tcu(calibration)
    loop = fast.FastLoop(plant, driver, duration, tcu=c_tcu, record_outputs=offline.RECORDED,
                         trace=TRACE_CHUNK)
    assert loop.driver_in_c != python_driver
    py = fast.python_tcu(calibration)
    names = fast.sensor_names()
    commands = fast.command_names()
    compared = 0
    while loop.k < loop.n_periods:
        if loop.k == k_fault:
            plant.set_faults(**faults[1])
        loop.step(TRACE_CHUNK if loop.k >= k_fault else min(TRACE_CHUNK, k_fault - loop.k))
        times, sensors, c_cmds = loop.traced()
        for t, row, c_row in zip(times.tolist(), sensors.tolist(), c_cmds.tolist()):
            s = dict(zip(names, row))
            s["stale"] = False
            cmd = py.step(t, s)
            want = [float(cmd[n]) for n in commands]
            if want != c_row:
                bad = [(n, w, c) for n, w, c in zip(commands, want, c_row) if w != c]
                raise AssertionError(f"{name}: period {compared} (t = {t:.3f} s): commands differ "
                                     f"(signal, Python, C): {bad[:4]}")
            compared += 1
    assert compared == loop.n_periods
    py.s = dict(py.s)                                  # the C's view as a plain dict of floats
    c_tcu.s = {k: (float(v) if k != "stale" else v) for k, v in c_tcu.s.items()}
    assert_same_state(c_tcu, py)
    return loop.recorded(), compared


# ---------------------------------------------------------------------------
# the TCU, period by period (lockstep)
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def wltc_c():
    """The whole WLTC in the C loop (C driver), as run_offline gives it."""
    return maneuver_run("wltc", tcu_impl="c")


# the first 300 s (urban phase and the start of the next: 150 k periods, about a
# sixth of the time) in scripts/test; the whole cycle (900 k periods) in scripts/test-long
@pytest.mark.slow
@pytest.mark.parametrize("duration_s", [pytest.param(300.0, id="first-300-s"),
                                        pytest.param(None, id="whole", marks=pytest.mark.long)])
def test_lockstep_wltc_python_driver_same_commands_every_period_and_same_run_as_the_c_driver(
        wltc_c, duration_s):
    rec, n = lockstep("wltc", duration_s, python_driver=True)
    assert n == (150_000 if duration_s else 900_000)
    # the Python driver (called every 10 ms) and the C driver give the same closed loop: the
    # section's recording is the start of the whole cycle's
    size = len(rec["time_s"])
    assert size > 0 and (duration_s or size == len(wltc_c["time_s"]))
    for k in ("time_s", "vehicle_speed_kmh", "fuel_l", "gear", "accel_pedal_pct", "brake_pedal_pct",
              "tcu_target_gear"):
        assert np.array_equal(rec[k], wltc_c[k][:size]), k


@pytest.mark.slow
@pytest.mark.parametrize("name", ["paper-cycle", "0-100"])
def test_lockstep_paper_cycle_and_0_100_same_commands_every_period(name):
    rec, n = lockstep(name)
    assert n == int(round(get_maneuver(name).duration_s / logic.PERIOD_S))
    assert len(set(rec["tcu_gear"])) >= 4                        # it went through the gears


def _creep_driver(t_s, outputs):
    """On the brake, released (creep), on the brake to a stop, released, then a light launch."""
    if t_s < 2.0 or 9.0 <= t_s < 12.0:
        return 0.0, 40.0
    return (25.0, 0.0) if t_s >= 16.0 else (0.0, 0.0)


def _hill_driver(t_s, outputs):
    """On the brake, the brake let go over 0.3 s, then the accelerator."""
    if t_s < 2.0:
        return 0.0, 60.0
    if t_s < 2.3:
        return 0.0, 60.0 * (2.3 - t_s) / 0.3
    return (0.0, 0.0) if t_s < 3.0 else (40.0, 0.0)


@pytest.mark.parametrize("name, driver, inputs, duration_s", [
    ("creep", _creep_driver, {}, 20.0),
    ("hill-start-20pct", _hill_driver, {"road_grade_pct": 20.0}, 8.0),
])
def test_lockstep_creep_and_hill_start_same_commands_every_period(name, driver, inputs, duration_s):
    rec, n = lockstep(name, duration_s, driver=driver, inputs=inputs)
    assert n == int(round(duration_s / logic.PERIOD_S))
    phases = set(rec["tcu_phase"].astype(int))
    assert logic.PHASE_CODES["standstill"] in phases and logic.PHASE_CODES["launch"] in phases
    assert rec["vehicle_speed_kmh"].max() > 4.0                 # it crept / pulled away


def _stop_and_go(t_s, outputs):
    """Stops on the brake (7 s: the kiss point is learnt) between creep (3 s) and a light pedal (2 s)."""
    c = t_s % 12.0
    if c < 7.0:
        return 0.0, 40.0
    return (0.0, 0.0) if c < 10.0 else (15.0, 0.0)


COLD = {"coolant_temp_degc": 5.0, "engine_oil_temp_degc": 5.0, "trans_oil_temp_degc": 5.0}


@pytest.mark.slow
def test_lockstep_kiss_adaptation_from_a_cold_start_same_commands_every_period():
    kiss = (logic.CLUTCH_KISS_BAR[0] + 0.4, logic.CLUTCH_KISS_BAR[1])
    rec, _ = lockstep("kiss-adaptation", 48.0, driver=_stop_and_go, reset=COLD,
                      calibration={"CLUTCH_KISS_BAR": kiss})
    assert rec["vehicle_speed_kmh"].max() > 1.0           # cold: it creeps slowly


def test_lockstep_reverse_park_and_a_refused_r_same_commands_every_period():
    from plant.driver import ScriptedDriver

    rec, _ = lockstep("reverse-park")
    assert (rec["tcu_gear"] == -1).any() and rec["vehicle_speed_kmh"].min() < -3.0
    selector = ScriptedDriver([(0.0, 40.0, 0.0, "D"), (5.0, 0.0, 0.0, "R"), (7.0, 0.0, 30.0, "R"),
                               (12.0, 0.0, 0.0, "R"), (15.0, 0.0, 30.0, "D"), (18.0, 0.0, 0.0, "N")])
    rec, _ = lockstep("refused-r", 20.0, driver=selector)
    assert (rec["tcu_target_gear"] == 0).any() and (rec["tcu_gear"] == -1).any()


def test_lockstep_paper_cycle_from_a_cold_start_same_commands_every_period():
    # the oil temperature in the torque-to-pressure gain and the fill time
    rec, _ = lockstep("paper-cycle", 30.0, reset=COLD)
    assert len(set(rec["tcu_gear"])) >= 3


@pytest.mark.parametrize("faults, dtc", [
    ((0.0, {"fork_jammed": {1: 1}}), "gear_engagement"),      # 2nd/4th inhibited, interrupted 1-3
    ((6.5, {"friction_loss": {0: 0.8}}), "clutch1_slip"),     # K1 slips: pressure raised, limp home
    ((8.0, {"solenoid_open": {1: 1}}), "clutch2_pressure"),   # K2 without current: limp home on K1
    ((8.0, {"line_pressure_loss": 0.6}), "line_pressure"),    # the safe state
])
def test_lockstep_with_plant_faults_the_diagnostics_react_alike(faults, dtc):
    from tcu_stub import diagnostics as D

    rec, _ = lockstep("paper-cycle", 30.0, faults=faults)
    bit = D.DTC_NAMES.index(dtc)
    assert (rec["tcu_active_faults"].astype(int) >> bit & 1).any(), f"{dtc} never set"


# ---------------------------------------------------------------------------
# the link
# ---------------------------------------------------------------------------

class _Inputs(dict):
    """A stand-in plant for offline.apply_commands: inputs only."""

    @property
    def inputs(self):
        return self


def _random_value(rng, sig):
    lo = sig.minimum if sig.minimum is not None else -1e4
    hi = sig.maximum if sig.maximum is not None else 1e4
    span = hi - lo
    pick = rng.integers(4)
    if pick == 0:                                              # beyond the range
        return float(rng.uniform(lo - 0.3 * span, hi + 0.3 * span))
    if pick == 1:                                              # on a half raw step (ties)
        raw = int(rng.integers(int(lo / sig.scale), int(hi / sig.scale) + 1))
        return (raw + 0.5) * sig.scale + sig.offset
    return float(rng.uniform(lo, hi))


def test_link_gives_the_dbc_codec_values_at_each_message_cycle_and_phase():
    ffi, lib = fast._lib()
    link = ffi.new("tcu_link *")
    fast.fill_link(link)
    py_link = offline.ContractLink()
    rng = np.random.default_rng(7)
    out_index = {n: i for i, n in enumerate(OUTPUT_NAMES)}
    sensors_c = ffi.new("double[]", lib.TCU_N_SENSORS)
    names = fast.sensor_names()
    commands = fast.command_names()
    plant_sigs = {s.name: s for m in codec.messages("PLANT") for s in m.signals}
    tcu_sigs = {s.name: s for m in codec.messages("TCU") for s in m.signals}
    for k in range(400):
        outputs = np.zeros(len(OUTPUT_NAMES))
        for _, _, fields in contract_link.PLANT_MESSAGES:
            for sig, field in fields.items():
                outputs[out_index[field]] = _random_value(rng, plant_sigs[sig])
        lib.tcu_link_sensors(link, ffi.cast("double *", ffi.from_buffer(outputs)), k, sensors_c)
        view = py_link.sensors({n: outputs[i] for n, i in out_index.items()}, k)
        got = [sensors_c[i] for i in range(len(names))]
        assert got == [float(view[n]) for n in names], k
        cmds = [_random_value(rng, tcu_sigs[n]) for n in commands]
        inputs = np.full(len(INPUT_NAMES), -7.0)
        lib.tcu_link_apply(link, ffi.cast("double *", ffi.from_buffer(np.array(cmds))), k,
                           ffi.cast("double *", ffi.from_buffer(inputs)))
        plant = _Inputs({n: -7.0 for n in INPUT_NAMES})
        py_link.apply(plant, dict(zip(commands, cmds)), k)
        assert inputs.tolist() == [float(plant[n]) for n in INPUT_NAMES], k


# ---------------------------------------------------------------------------
# closed loops, C against Python
# ---------------------------------------------------------------------------

# the whole paper-cycle; 0-100 past 100 km/h; the start of the WLTC (the whole cycles: lockstep)
@pytest.mark.slow
@pytest.mark.parametrize("name, duration_s", [("paper-cycle", None), ("0-100", 20.0), ("wltc", 60.0)])
def test_closed_loop_c_equals_python_with_the_same_figures(name, duration_s):
    c = maneuver_run(name, duration_s, tcu_impl="c")
    py = maneuver_run(name, duration_s, tcu_impl="python")
    assert_same_run(c, py)
    m = get_maneuver(name)
    assert report(m, c) == report(m, py)
    assert len(c["shifts"]) == len(py["shifts"]) > 0


@pytest.mark.slow
def test_wltc_figures_of_the_c_loop(wltc_c):
    # equal to the Python loop by the lockstep test above; here what they are
    m = get_maneuver("wltc")
    fig = report(m, wltc_c)
    assert fig["rms_speed_error_kmh"] < 1.0 and 5.0 < fig["fuel_l_per_100km"] < 7.5
    assert abs(fig["distance_km"] - 23.27) < 0.2
    assert 100 < len(wltc_c["shifts"]) < 250 and wltc_c["gear_clashes"][-1] == 0
    assert not wltc_c["tcu_active_faults"].any()


@pytest.mark.slow
def test_plant_fault_set_while_running_same_in_both_loops():
    def run(impl):
        m = get_maneuver("paper-cycle")
        plant = Plant()
        tcu = TcuLogic()
        k_f = int(round(8.0 / logic.PERIOD_S))
        if impl == "python":
            def on_period(k, p):
                if k == k_f:
                    p.set_faults(line_pressure_loss=0.6)
            rec = run_offline(plant, m.driver, 12.0, tcu=tcu, on_period=on_period)
        else:                 # the C loop stopped at the period, the fault set, then on
            loop = fast.FastLoop(plant, m.driver, 12.0, tcu=tcu, record_outputs=offline.RECORDED)
            loop.step(k_f)
            plant.set_faults(line_pressure_loss=0.6)
            loop.step()
            rec = loop.recorded()
        return rec, tcu

    (c, c_tcu), (py, py_tcu) = run("c"), run("python")
    for k in ("time_s", "vehicle_speed_kmh", "clutch1_pressure_bar", "tcu_active_faults", "tcu_phase"):
        assert np.array_equal(np.asarray(c[k], dtype=float),
                              np.array([logic.PHASE_CODES[p] for p in py[k]], dtype=float)
                              if k == "tcu_phase" else np.asarray(py[k], dtype=float)), k
    assert c_tcu.phase == py_tcu.phase == "safe"
    assert_same_state(c_tcu, py_tcu)


@pytest.mark.slow
def test_a_tcu_passed_in_ends_as_the_python_loop_leaves_it_and_runs_on_in_either_loop():
    m1, m2 = get_maneuver("paper-cycle"), get_maneuver("paper-cycle")
    p1, p2 = Plant(), Plant()
    t1, t2 = TcuLogic(), TcuLogic()
    a = run_offline(p1, m1.driver, 20.0, tcu=t1, tcu_impl="c")
    b = run_offline(p2, m2.driver, 20.0, tcu=t2, tcu_impl="python")
    assert_same_run(a, b)
    assert_same_state(t1, t2)
    # on from there: the C-run TCU in the Python loop, the Python-run TCU in the C loop
    a = run_offline(p1, m1.driver, 10.0, tcu=t1, tcu_impl="python")
    b = run_offline(p2, m2.driver, 10.0, tcu=t2, tcu_impl="c")
    assert_same_run(a, b)
    assert_same_state(t1, t2)
    assert len(t1.events) >= 5 and t1.t_s == pytest.approx(10.0 - logic.PERIOD_S)   # run time


@pytest.mark.slow
def test_a_python_driver_runs_between_c_calls_with_the_same_result():
    def driver(t_s, outputs):
        return (80.0, 0.0) if t_s < 9.0 else (0.0, 35.0)

    assert_same_run(run_offline(Plant(), driver, 14.0, tcu_impl="c"),
                    run_offline(Plant(), driver, 14.0, tcu_impl="python"))


@pytest.mark.slow
def test_a_speed_tracking_driver_goes_on_from_where_the_c_loop_left_it():
    m1, m2 = get_maneuver("wltc"), get_maneuver("wltc")
    run_offline(Plant(), m1.driver, 12.0, tcu_impl="c")
    run_offline(Plant(), m2.driver, 12.0, tcu_impl="python")
    assert (m1.driver._integral, m1.driver._t_last) == (m2.driver._integral, m2.driver._t_last)
    assert m1.driver._t_last is not None


def test_auto_runs_the_python_loop_for_what_only_it_can_do():
    stale = maneuver_run("0-100", 8.0, stale_fn=lambda t: 5.0 < t < 5.5)
    assert "stale" in stale["tcu_phase"]
    with pytest.raises(ValueError, match="stale_fn needs the Python loop"):
        maneuver_run("0-100", 1.0, tcu_impl="c", stale_fn=lambda t: False)

    class Mine(TcuLogic):
        pass

    assert fast.c_compatible(Mine()) is not None
    with pytest.raises(ValueError, match="not tcu_stub/logic.py's TcuLogic"):
        maneuver_run("0-100", 1.0, tcu_impl="c", tcu=Mine())
    with pytest.raises(ValueError, match="tcu_impl must be one of"):
        maneuver_run("0-100", 1.0, tcu_impl="fortran")


# ---------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------

def test_the_calibration_is_every_module_constant_of_the_logic_but_its_structure():
    constants = {n for n, v in vars(logic).items() if n.isupper() and not n.startswith("_")}
    assert set(fast.CALIBRATION_NAMES) == constants - fast.STRUCTURAL
    gear_ratio, rpm_per_kmh = fast.derived(fast.TcuCalibration().resolved())
    assert gear_ratio == logic.GEAR_RATIO and rpm_per_kmh == logic.RPM_PER_KMH


CAL = {"LAUNCH_RPM_MIN": 1400.0, "UPSHIFT_RPM": ((0, 1700), (25, 1900), (50, 2400), (75, 3800), (100, 5800)),
       "GEAR_OVERALL_RATIO": {1: 14.0, 2: 8.6, 3: 5.353, 4: 3.714, 5: 2.781, 6: 2.301}}


@pytest.mark.slow
@pytest.mark.parametrize("form", ["dict", "dataclass"])
def test_a_calibration_changes_both_loops_alike(form):
    cal = CAL if form == "dict" else fast.TcuCalibration(**{k.lower(): v for k, v in CAL.items()})
    c = maneuver_run("paper-cycle", 15.0, tcu_impl="c", calibration=cal)
    py = maneuver_run("paper-cycle", 15.0, tcu_impl="python", calibration=cal)
    assert_same_run(c, py)
    default = maneuver_run("paper-cycle", 15.0, tcu_impl="c")
    assert c["shifts"][0][0] < default["shifts"][0][0]          # earlier upshift line
    assert logic.LAUNCH_RPM_MIN == 1100.0 and logic.UPSHIFT_RPM[-1] == (100.0, 6300.0)   # untouched


@pytest.mark.slow
def test_a_private_copy_of_the_logic_runs_in_c_with_its_constants():
    tcu = fast.python_tcu({"PEDAL_ON_PCT": 5.0, "LOCK_RAMP_BAR_PER_S": 40.0})
    assert type(tcu) is not TcuLogic and fast.c_compatible(tcu) is None
    py_tcu = fast.python_tcu({"PEDAL_ON_PCT": 5.0, "LOCK_RAMP_BAR_PER_S": 40.0})
    assert_same_run(maneuver_run("0-100", 15.0, tcu=tcu, tcu_impl="c"),
                    maneuver_run("0-100", 15.0, tcu=py_tcu, tcu_impl="python"))
    assert_same_state(tcu, py_tcu)


@pytest.mark.slow
def test_a_module_constant_changed_counts_in_both_loops(monkeypatch):
    monkeypatch.setattr(logic, "KICKDOWN_PCT", 101.0)
    monkeypatch.setattr(logic, "UPSHIFT_RPM", ((0.0, 1500.0), (100.0, 5000.0)))
    assert_same_run(maneuver_run("paper-cycle", 20.0, tcu_impl="c"),
                    maneuver_run("paper-cycle", 20.0, tcu_impl="python"))


@pytest.mark.parametrize("cal, message", [
    ({"LAUNCH_RPM": 1.0}, "unknown TCU calibration value 'LAUNCH_RPM'"),
    ({"launch_rpm_min": "fast"}, "launch_rpm_min: 'fast' is not a number"),
    ({"launch_rpm_min": math.nan}, "launch_rpm_min: nan is not finite"),
    ({"upshift_rpm": ((50, 2000), (10, 3000))}, "upshift_rpm: x must increase"),
    ({"final_drive": (4.1,)}, "final_drive: two numbers"),
    ({"gear_overall_ratio": {1: 3.0}}, "gear_overall_ratio: needs gears 1..6"),
    ([1, 2], "a TcuCalibration or a dict"),
])
def test_bad_calibration_is_one_line(cal, message):
    with pytest.raises(ValueError, match=message) as e:
        run_offline(Plant(), lambda t, o: (0.0, 0.0), 0.1, calibration=cal)
    assert "\n" not in str(e.value)


def test_calibration_or_tcu_not_both():
    with pytest.raises(ValueError, match="not both"):
        run_offline(Plant(), lambda t, o: (0.0, 0.0), 0.1, calibration={}, tcu=TcuLogic())


def test_calibration_is_a_frozen_picklable_value():
    import pickle

    cal = fast.TcuCalibration(launch_rpm_min=1200.0)
    assert pickle.loads(pickle.dumps(cal)) == cal
    with pytest.raises(dataclasses.FrozenInstanceError):
        cal.launch_rpm_min = 1.0
    assert cal.changed() == {"LAUNCH_RPM_MIN": 1200.0}


# ---------------------------------------------------------------------------
# errors and interruptions in the C loop
# ---------------------------------------------------------------------------

def test_a_plant_error_in_the_c_loop_raises_and_keeps_the_rows_and_the_tcu_state():
    plant = Plant()
    tcu = TcuLogic()
    loop = fast.FastLoop(plant, get_maneuver("0-100").driver, 5.0, tcu=tcu, record_outputs=["gear"])
    loop.step(1000)
    plant.inputs["road_grade_pct"] = math.nan
    with pytest.raises(PlantError, match="road_grade_pct is not finite"):
        loop.step()
    assert loop.k == 1001 and len(loop.recorded()["time_s"]) == 201
    assert tcu.t_s == pytest.approx(1000 * logic.PERIOD_S)


@pytest.mark.slow
def test_simulate_c_and_python_write_the_same_csv(tmp_path, capsys):
    from dct_hil import cli

    paths = {}
    for impl in ("c", "python"):
        paths[impl] = tmp_path / f"{impl}.csv"
        code = cli.main(["simulate", "--scenario", "paper-cycle", "--duration", "20",
                         "--out", str(paths[impl]), "--tcu-impl", impl])
        out = capsys.readouterr().out
        assert code == 0 and {"c": "compiled loop", "python": "Python loop"}[impl] in out
    assert paths["c"].read_bytes() == paths["python"].read_bytes()


def test_simulate_with_mapping_takes_the_python_loop_and_refuses_c(tmp_path, capsys):
    from dct_hil import cli

    code = cli.main(["simulate", "--scenario", "0-100", "--duration", "0.5", "--mapping", "vehicle"])
    assert code == 0 and "Python loop" in capsys.readouterr().out
    code = cli.main(["simulate", "--scenario", "0-100", "--duration", "0.5", "--mapping", "vehicle",
                     "--tcu-impl", "c"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--tcu-impl c" in err


def test_ctrl_c_in_the_c_loop_exits_130_and_keeps_the_partial_csv(tmp_path, capsys, monkeypatch):
    from dct_hil import cli

    calls = []
    real = fast.FastLoop._chunk

    def chunk(self, count):
        calls.append(count)
        if len(calls) == 10:
            raise KeyboardInterrupt
        return real(self, count)

    monkeypatch.setattr(fast, "CHUNK_PERIODS", 5)
    monkeypatch.setattr(fast.FastLoop, "_chunk", chunk)
    out_csv = tmp_path / "partial.csv"
    code = cli.main(["simulate", "--scenario", "paper-cycle", "--out", str(out_csv)])
    err = capsys.readouterr().err
    assert code == 130 and "interrupted" in err and str(out_csv) in err
    data = np.loadtxt(out_csv, delimiter=",", skiprows=1, ndmin=2)
    assert data.shape[0] == 9                      # rows of periods 0, 5, ..., 40


def test_an_extension_built_for_another_plant_runs_the_python_loop_or_is_refused(monkeypatch):
    fast._layout_mismatch.cache_clear()
    assert fast.unavailable() is None                      # this build fits
    monkeypatch.setattr(fast, "_layout_mismatch", lambda: "built with another dct_plant.h")
    with pytest.warns(RuntimeWarning, match="another dct_plant.h"):
        r = maneuver_run("0-100", 0.5)
    assert_same_run(r, maneuver_run("0-100", 0.5, tcu_impl="python"))
    with pytest.raises(ValueError, match="tcu_impl 'c': built with another dct_plant.h"):
        maneuver_run("0-100", 0.5, tcu_impl="c")
