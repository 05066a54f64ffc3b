"""The closed loop of plant, driver and reference TCU in C: offline runs at the plant's speed.

``tcu_stub.offline.run_offline`` and ``dct-hil simulate --scenario MANEUVER`` run
here by default. One C call (``tcu_stub/csrc/tcu_run.c``) runs many TCU periods
of what ``run_offline`` does in Python, in the same order: the driver's pedals
every 10 ms, the plant messages through the CAN contract at their cycle times
and phases (``contract_link.ContractLink``: packed and unpacked with the DBC's
scaling, offset and length by the table codec, bit-exact with cantools), the
TCU step every 2 ms (``tcu_stub/csrc/tcu_logic.c``, a port of
``tcu_stub/logic.py`` and ``tcu_stub/diagnostics.py``), its commands through
the contract, the plant stepping 2 ms (the plant's own C functions).

``tcu_stub/logic.py`` stays the reference. The port keeps its order of
operations in IEEE 754 double, so the same sensor values give the same
commands to the bit; tests/test_offline_fast.py steps both TCUs side by side
over whole cycles and compares every command of every period.

TCU calibration: ``TcuCalibration`` holds the values that are module
constants of ``tcu_stub/logic.py`` (shift lines, launch speeds, clutch model,
...). A field left None takes the module's value at the start of the run (so a
changed module constant counts in both implementations); a set field
overrides it for that run only, in both implementations::

    from tcu_stub.fast import TcuCalibration
    cal = TcuCalibration(launch_rpm_min=1300.0,
                         upshift_rpm=((0, 2000), (25, 2200), (50, 2800), (75, 4300), (100, 6300)))
    run_offline(plant, m.driver, m.duration_s, calibration=cal)     # or a dict:
    run_offline(plant, m.driver, m.duration_s, calibration={"LAUNCH_RPM_MIN": 1300.0})

Field names are the constants' names in lower case (``UPSHIFT_RPM`` ->
``upshift_rpm``); a dict may use either spelling. The Python TCU honours a
calibration through a private copy of the logic module with those values (the
shared module is never changed, so runs in threads do not disturb each other).

A ``tcu`` given to run_offline (a TcuLogic of logic.py, or of a private copy
of it such as ``python_tcu`` makes) runs in C with its module's constants and
its state, and gets the C's state back at the end: every attribute as the
Python loop would have left it.

What the C loop does not do (``run_offline`` then uses the Python loop, as
before): plant messages lost or rejected (``stale_fn``, a TCU in phase
"stale"), sensor faults (``sensor_fault``), another CAN matrix (``link``), a
look at every period (``on_period``), a ``tcu`` of another class
(``c_compatible`` says why).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import math
import os
from dataclasses import dataclass

import numpy as np

from plant.driver import driver_inputs
from tcu_stub import diagnostics as _diag
from tcu_stub import logic as _logic

# logic.py's module constants that are not calibration: the gearbox's layout, timing,
# names, values derived from others, and SPEED_INVALID_RPM (the DBC's, from diagnostics.py)
STRUCTURAL = frozenset(("PERIOD_S", "TOP_GEAR", "GEAR_LAYOUT", "SHAFT_SLEEVES", "SHAFT_GEARS",
                        "GEAR_RATIO", "RPM_PER_KMH", "SYNC_ENGAGED", "PHASES", "PHASE_CODES",
                        "SHIFT_PHASES", "FAULT_COUNT_MAX", "SPEED_INVALID_RPM", "REVERSE", "SELECTOR_P",
                        "SELECTOR_R", "SELECTOR_N", "SELECTOR_D"))


@dataclass(frozen=True)
class TcuCalibration:
    """TCU calibration for one run: ``tcu_stub/logic.py``'s module constants.

    None (the default of every field) is the module's value when the run
    starts. Units and meaning: the constant's comment in logic.py. Tables are
    sequences of (x, y) rows; ``gear_overall_ratio`` maps gear 1..6 to its
    ratio (or is a sequence of 6)."""
    # the car
    gear_overall_ratio: object = None
    final_drive: object = None
    tyre_radius_m: object = None
    engine_inertia_kgm2: object = None
    idle_rpm: object = None
    # clutch model
    clutch_kiss_bar: object = None
    clutch_mu_over_temp: object = None
    oil_default_degc: object = None
    clutch_nm_per_bar: object = None
    clutch_lock_bar: object = None
    clutch_max_bar: object = None
    # valve and pressure loop
    valve_feedback_area_m2: object = None
    valve_spring_n: object = None
    valve_gain_n_per_a: object = None
    valve_max_a: object = None
    pressure_kp_a_per_bar: object = None
    pressure_ki_a_per_bar_s: object = None
    pressure_i_limit_a: object = None
    fill_current_a: object = None
    fill_time_s: object = None
    fill_time_over_temp: object = None
    empty_bar: object = None
    line_current_a: object = None
    # forks
    fork_engage_n: object = None
    fork_hold_n: object = None
    fork_neutral_n_per_mm: object = None
    fork_neutral_ns_per_mm: object = None
    fork_neutral_max_n: object = None
    fork_engaged_mm: object = None
    fork_neutral_mm: object = None
    # launch and drive
    pedal_on_pct: object = None
    brake_on_pct: object = None
    launch_rpm_min: object = None
    launch_rpm_max: object = None
    launch_kp_nm_per_rpm: object = None
    launch_lock_slip_rpm: object = None
    lock_ramp_bar_per_s: object = None
    open_below_input_rpm: object = None
    # reverse and the selector lever
    reverse_overall_ratio: object = None
    reverse_max_kmh: object = None
    neutral_resume_kmh: object = None
    # creep and hill start
    creep_nm: object = None
    creep_hold_nm: object = None
    creep_ramp_nm_per_s: object = None
    creep_max_kmh: object = None
    creep_fade_kmh: object = None
    vehicle_weight_n: object = None
    hill_margin: object = None
    hill_min_pct: object = None
    hill_kp_nm_per_rpm: object = None
    hill_stall_rpm: object = None
    brake_nm_per_pct: object = None
    # kiss point adaptation
    adapt_open_s: object = None
    adapt_settle_s: object = None
    adapt_max_kmh: object = None
    adapt_torque_tau_s: object = None
    adapt_speed_tau_s: object = None
    adapt_steady_rpm: object = None
    adapt_gain_per_s: object = None
    adapt_max_bar_per_s: object = None
    adapt_range_bar: object = None
    # shifts
    upshift_rpm: object = None
    downshift_rpm: object = None
    kickdown_pct: object = None
    kickdown_max_rpm: object = None
    torque_phase_s: object = None
    torque_margin: object = None
    torque_margin_nm: object = None
    inertia_phase_s: object = None
    sync_done_rpm: object = None
    coast_pull_nm: object = None
    blip_kp_nm_per_rpm: object = None
    blip_max_nm: object = None
    down_offgoing_share: object = None
    shift_timeout_s: object = None
    preselect_max_rpm: object = None
    # restricted schedule (gears inhibited by the diagnostics)
    restricted_up_min_rpm: object = None
    restricted_up_down_factor: object = None
    restricted_down_max_rpm: object = None
    limp_upshift_rpm: object = None
    select_max_rpm: object = None
    leave_standstill_kmh: object = None
    open_sync_rpm: object = None
    open_sync_s: object = None
    tied_bar: object = None
    # traction limit
    traction_force_n: object = None
    traction_accel_mps2: object = None
    mesh_efficiency: object = None
    asr_slip_target: object = None
    asr_min_speed_kmh: object = None
    asr_ki_nm_per_s: object = None
    asr_trim_max_nm: object = None
    asr_kp_nm: object = None
    asr_min_nm: object = None
    engine_full_load: object = None

    @classmethod
    def of(cls, calibration):
        """A TcuCalibration from None, a TcuCalibration, or a dict (field or constant names)."""
        if calibration is None:
            return cls()
        if isinstance(calibration, cls):
            return calibration
        if not isinstance(calibration, dict):
            raise ValueError(f"TCU calibration must be a TcuCalibration or a dict, got "
                             f"{type(calibration).__name__}")
        fields = {f.name for f in dataclasses.fields(cls)}
        values = {}
        for key, value in calibration.items():
            name = str(key).lower()
            if name not in fields:
                raise ValueError(f"unknown TCU calibration value {key!r} (the module constants of "
                                 f"tcu_stub/logic.py, e.g. launch_rpm_min; see TcuCalibration)")
            values[name] = value
        return cls(**values)

    def resolved(self):
        """{CONSTANT_NAME: value} of every calibration value, checked: the set ones, the
        module's for the others."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            name = f.name.upper()
            out[name] = _check_value(name, getattr(_logic, name) if value is None else value)
        return out

    def changed(self):
        """{CONSTANT_NAME: value} of the fields set (not None)."""
        return {f.name.upper(): getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


CALIBRATION_NAMES = tuple(f.name.upper() for f in dataclasses.fields(TcuCalibration))
_TABLES = ("UPSHIFT_RPM", "DOWNSHIFT_RPM", "ENGINE_FULL_LOAD", "CLUTCH_MU_OVER_TEMP", "FILL_TIME_OVER_TEMP")
_TABLE_ROWS = {"UPSHIFT_RPM": "upshift_n", "DOWNSHIFT_RPM": "downshift_n",
               "ENGINE_FULL_LOAD": "engine_full_load_n", "CLUTCH_MU_OVER_TEMP": "clutch_mu_over_temp_n",
               "FILL_TIME_OVER_TEMP": "fill_time_over_temp_n"}     # tcu_cal's row counts
_PAIRS = ("FINAL_DRIVE", "CLUTCH_KISS_BAR", "CLUTCH_NM_PER_BAR")
MAX_TABLE_ROWS = 16


def _number(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"TCU calibration {name.lower()}: {value!r} is not a number")
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"TCU calibration {name.lower()}: {value!r} is not finite")
    return x


def _check_value(name, value):
    """The value in logic.py's own shape (floats, tuples, a gear dict), or ValueError."""
    if name == "GEAR_OVERALL_RATIO":
        if isinstance(value, dict):
            if sorted(value) != list(range(1, 7)):
                raise ValueError("TCU calibration gear_overall_ratio: needs gears 1..6")
            items = [value[g] for g in range(1, 7)]
        else:
            items = list(value) if isinstance(value, (list, tuple, np.ndarray)) else None
            if items is None or len(items) != 6:
                raise ValueError("TCU calibration gear_overall_ratio: a {gear: ratio} dict or 6 numbers")
        ratios = [_number(name, v) for v in items]
        if min(ratios) <= 0:
            raise ValueError("TCU calibration gear_overall_ratio: ratios must be > 0")
        return {g: r for g, r in zip(range(1, 7), ratios)}
    if name in _PAIRS:
        if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 2:
            raise ValueError(f"TCU calibration {name.lower()}: two numbers (K1, K2 or output shafts 1, 2)")
        return tuple(_number(name, v) for v in value)
    if name in _TABLES:
        rows = list(value) if isinstance(value, (list, tuple, np.ndarray)) else None
        if not rows or len(rows) > MAX_TABLE_ROWS or any(
                not isinstance(r, (list, tuple, np.ndarray)) or len(r) != 2 for r in rows):
            raise ValueError(f"TCU calibration {name.lower()}: 1 to {MAX_TABLE_ROWS} (x, y) rows")
        table = tuple((_number(name, x), _number(name, y)) for x, y in rows)
        if any(b[0] <= a[0] for a, b in zip(table, table[1:])):
            raise ValueError(f"TCU calibration {name.lower()}: x must increase from row to row")
        return table
    return _number(name, value)


def derived(values):
    """GEAR_RATIO and RPM_PER_KMH of resolved values, as logic.py derives them."""
    final = values["FINAL_DRIVE"]
    gear_ratio = {g: r / final[0 if g <= 4 else 1] for g, r in values["GEAR_OVERALL_RATIO"].items()}
    rpm_per_kmh = 1.0 / 3.6 / values["TYRE_RADIUS_M"] * 60.0 / (2.0 * math.pi)
    return gear_ratio, rpm_per_kmh


def _freeze(values):
    return tuple((k, tuple(sorted(v.items())) if isinstance(v, dict) else v) for k, v in sorted(values.items()))


@functools.lru_cache(maxsize=32)
def _logic_copy(frozen):
    """A private copy of tcu_stub/logic.py with the calibration values ``frozen``."""
    name = f"tcu_stub._logic_calibrated_{len(_COPIES)}"
    spec = importlib.util.spec_from_file_location(name, _logic.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    values = {k: (dict(v) if k == "GEAR_OVERALL_RATIO" else v) for k, v in frozen}
    for k, v in values.items():
        setattr(module, k, v)
    gear_ratio, rpm_per_kmh = derived(values)
    module.GEAR_RATIO = gear_ratio
    module.RPM_PER_KMH = rpm_per_kmh
    module.TcuLogic.GEAR_RATIO = gear_ratio
    module.TcuLogic.CLUTCH_LOCK_BAR = values["CLUTCH_LOCK_BAR"]
    _COPIES.append(module)
    return module


_COPIES = []


def python_tcu(calibration=None):
    """A reference TcuLogic (tcu_stub/logic.py) running with ``calibration``: the module's
    own class without one, else that of a private copy of the module with its values."""
    cal = TcuCalibration.of(calibration)
    if not cal.changed():
        return _logic.TcuLogic()
    return _logic_copy(_freeze(cal.resolved())).TcuLogic()


# ------------------------------------------------------------------ the C side
def _lib():
    from tcu_stub._tcu_fast import (  # built by scripts/setup (setup.py build_ext)
        ffi,
        lib,
    )
    return ffi, lib


def unavailable():
    """None when the compiled loop is there and fits the plant, else why not (one line)."""
    try:
        _lib()
    except ImportError as e:
        return f"tcu_stub._tcu_fast is not built ({e}; scripts/setup builds it)"
    return _layout_mismatch()


@functools.cache
def _layout_mismatch():
    """None when this extension and plant._dct_plant were compiled with the same dct_plant.h
    (the C loop steps plant._dct_plant's structs), else why not."""
    from plant._dct_plant import ffi as p

    ffi, lib = _lib()
    if not hasattr(lib, "tcu_plant_layout"):
        return "tcu_stub._tcu_fast is older than its sources: rebuild it (scripts/setup)"
    got = ffi.new("int64_t[]", lib.TCU_N_PLANT_LAYOUT)
    lib.tcu_plant_layout(got)
    want = [p.sizeof("dct_plant"), p.offsetof("dct_plant", "state"), p.offsetof("dct_plant", "inputs"),
            p.offsetof("dct_plant", "outputs"), p.sizeof("dct_inputs"), p.sizeof("dct_outputs"),
            p.offsetof("dct_state", "time_s"), p.offsetof("dct_inputs", "accel_pedal_pct"),
            p.offsetof("dct_inputs", "brake_pedal_pct"), p.offsetof("dct_outputs", "vehicle_speed_kmh"),
            p.offsetof("dct_outputs", "engine_speed_rpm")]
    if list(got) != want:
        return ("tcu_stub._tcu_fast was built with another plant/csrc/dct_plant.h than "
                "plant._dct_plant: rebuild both (scripts/setup, or setup.py build_ext --inplace)")
    return None


def _names(fn, n):
    ffi, _ = _lib()
    return [ffi.string(fn(i)).decode() for i in range(n)]


@functools.cache
def _layout():
    """Sensor, command and phase names of the C, checked against the Python."""
    ffi, lib = _lib()
    sensors = _names(lib.tcu_sensor_name, lib.TCU_N_SENSORS)
    commands = _names(lib.tcu_command_name, lib.TCU_N_COMMANDS)
    phases = _names(lib.tcu_phase_name, lib.TCU_N_PHASES)
    if tuple(phases) != tuple(_logic.PHASES):
        raise RuntimeError("tcu_stub/csrc: the phases differ from logic.PHASES; rebuild the extension")
    shaft, sleeve, side = ffi.new("int32_t *"), ffi.new("int32_t *"), ffi.new("int32_t *")
    for g, layout in _logic.GEAR_LAYOUT.items():
        lib.tcu_gear_layout(g, shaft, sleeve, side)
        if (shaft[0], sleeve[0], side[0]) != tuple(layout):
            raise RuntimeError(f"tcu_stub/csrc: gear {g}'s layout differs from logic.GEAR_LAYOUT")
    return sensors, commands, phases


def sensor_names():
    """The DBC signals of the C TCU's sensors array, in order."""
    return list(_layout()[0])


def command_names():
    """The DBC signals of the C TCU's commands array, in order."""
    return list(_layout()[1])


def fill_calibration(c, values, gear_ratio, rpm_per_kmh, diag=None):
    """Write resolved calibration values (``TcuCalibration.resolved()``), the derived
    GEAR_RATIO and RPM_PER_KMH and the diagnostics' thresholds (``diag``: the
    diagnostics module's namespace, default tcu_stub.diagnostics) into a ``tcu_cal``."""
    for name, value in values.items():
        field = name.lower()
        if name in _TABLES:
            setattr(c, field, [list(r) for r in value] + [[0.0, 0.0]] * (MAX_TABLE_ROWS - len(value)))
            setattr(c, _TABLE_ROWS[name], len(value))
        elif name == "GEAR_OVERALL_RATIO":
            c.gear_overall_ratio = [value[g] for g in range(1, 7)]
        else:
            setattr(c, field, value)
    c.gear_ratio = [gear_ratio[g] for g in range(1, 7)]
    c.rpm_per_kmh = rpm_per_kmh
    c.period_s = _logic.PERIOD_S
    d = vars(_diag) if diag is None else diag
    c.speed_invalid_rpm = d["SPEED_INVALID_RPM"]
    for name in ("HEAL_S", "SPEED_INVALID_SET_S", "SPEED_TOLERANCE_RPM", "SPEED_TOLERANCE_SHARE",
                 "SPEED_IMPLAUSIBLE_SET_S", "PRESSURE_INVALID_BAR", "PRESSURE_TOLERANCE_BAR",
                 "PRESSURE_TOLERANCE_SHARE", "PRESSURE_SET_S", "LINE_LOW_BAR", "LINE_SET_S", "SLIP_RPM",
                 "SLIP_SET_S", "SLIP_LIMP_S", "ENGAGE_SET_S", "ENGAGE_RELEASE_S", "MAX_DT_S",
                 "PERIOD_FIRST_S", "STARTUP_S"):
        setattr(c, name.lower(), d[name])
    c.limp_gear = list(d["LIMP_GEAR"])


class NotInC(ValueError):
    """The C loop cannot run this (one line: why)."""


_MONITORS = ("_speed_invalid", "_speed_plausible", "_pressure", "_line", "_slip", "_engage")
_IDLE_MONITORS = ("_engine", "_can")         # the message monitors: never counting in process


def _monitors(diag):
    """Diagnostics' monitors in the C's order (tcu_diag's fields), flattened."""
    out = []
    for name in _MONITORS:
        m = getattr(diag, name)
        out += list(m) if isinstance(m, tuple) else [m]
    return out


def tcu_values(tcu):
    """(values, GEAR_RATIO, RPM_PER_KMH, diagnostics namespace) the reference TcuLogic
    ``tcu`` runs with: the constants of its own module (logic.py or a private copy
    with other values); NotInC when the C cannot run it."""
    cls = type(tcu)
    g = getattr(getattr(cls, "step", None), "__globals__", None)
    if cls.__name__ != "TcuLogic" or g is None or g.get("TcuLogic") is not cls or \
            os.path.realpath(g.get("__file__") or "") != os.path.realpath(_logic.__file__):
        raise NotInC(f"tcu is a {cls.__module__}.{cls.__name__}, not tcu_stub/logic.py's TcuLogic")
    overridden = [n for n in vars(tcu) if callable(getattr(cls, n, None))]
    if overridden:
        raise NotInC(f"tcu overrides {overridden[0]} on the instance")
    for name in STRUCTURAL - {"GEAR_RATIO", "RPM_PER_KMH", "SPEED_INVALID_RPM"}:
        if g.get(name) != getattr(_logic, name):
            raise NotInC(f"tcu's module has another {name} than tcu_stub/logic.py")
    values = {name: _check_value(name, g[name]) for name in CALIBRATION_NAMES}
    gear_ratio, rpm_per_kmh = g["GEAR_RATIO"], g["RPM_PER_KMH"]
    if tcu.GEAR_RATIO != gear_ratio or tcu.CLUTCH_LOCK_BAR != g["CLUTCH_LOCK_BAR"]:
        raise NotInC("tcu's GEAR_RATIO or CLUTCH_LOCK_BAR differ from its module's")
    if sorted(gear_ratio) != list(range(1, 7)):
        raise NotInC("tcu's GEAR_RATIO needs gears 1..6")
    diag = tcu.diag
    dg = getattr(type(diag).monitor, "__globals__", None)
    if type(diag).__name__ != "Diagnostics" or dg is None or \
            os.path.realpath(dg.get("__file__") or "") != os.path.realpath(_diag.__file__):
        raise NotInC("tcu.diag is not tcu_stub/diagnostics.py's Diagnostics")
    if dg["SPEED_INVALID_RPM"] != g["SPEED_INVALID_RPM"]:
        raise NotInC("SPEED_INVALID_RPM differs between the logic and the diagnostics")
    return values, gear_ratio, rpm_per_kmh, dg


def c_compatible(tcu):
    """None when the C can take over the TcuLogic ``tcu`` (its code, calibration and
    state), else why not (one line)."""
    try:
        tcu_values(tcu)
    except NotInC as e:
        return str(e)
    if tcu.phase not in _logic.PHASE_CODES or tcu.phase == "stale":
        return f"tcu is in phase {tcu.phase!r} (the C has no lost plant messages)"
    d = tcu.diag
    if d.stale or d.engine_lost or not d.torque_ok or d._can_busy or any(
            m.active or m.fail_s or m.pass_s for n in _IDLE_MONITORS for m in
            (getattr(d, n) if isinstance(getattr(d, n), tuple) else (getattr(d, n),))):
        return "tcu's diagnostics count lost plant messages (the C has none)"
    return None


def load_state(c, tcu):
    """The TcuLogic ``tcu``'s state (what persists from one step to the next) into a
    ``tcu_state``."""
    c.phase = _logic.PHASE_CODES[tcu.phase]
    c.gear, c.target_gear, c.shift_from = tcu.gear, tcu.target_gear, tcu.shift_from
    c.pressure_bar = list(tcu.pressure_bar)
    c.sleeve_side = list(tcu.sleeve_side)
    c.fork_pos_prev = list(tcu.fork_pos_prev)
    c.has_request = tcu.torque_request_nm is not None
    c.torque_request_nm = tcu.torque_request_nm if tcu.torque_request_nm is not None else 0.0
    for name in ("shift_t0", "latched_torque_nm", "shift_slip0_rpm", "asr_trim_nm", "asr_cut_nm",
                 "launch_rpm", "creep_nm", "hill_nm", "adapt_t_s", "te_filt_nm", "n_filt_rpm",
                 "idle_load_nm", "t_s"):
        setattr(c, name, getattr(tcu, name))
    c.kiss_bar = list(tcu.kiss_bar)
    c.adapt_shaft = tcu.adapt_shaft
    c.oil_degc = tcu.oil_degc
    c.selector = tcu.selector
    c.held = list(tcu.held)
    c.n_shaft = list(tcu.n_shaft)
    for i, loop in enumerate(tcu.loops):
        c.loops[i].integral_a, c.loops[i].fill_left_s = loop.integral_a, loop.fill_left_s
        c.loops[i].target_bar = loop.target_bar
    d, cd = tcu.diag, c.diag
    monitors = [cd.speed_invalid[0], cd.speed_invalid[1], cd.speed_plausible[0], cd.speed_plausible[1],
                cd.pressure[0], cd.pressure[1], cd.line, cd.slip[0], cd.slip[1], cd.engage]
    for cm, m in zip(monitors, _monitors(d)):
        cm.bit, cm.active, cm.set_s, cm.heal_s = m.bit, m.active, m.set_s, m.heal_s
        cm.fail_s, cm.pass_s = m.fail_s, m.pass_s
    for name in ("active_bits", "stored_bits", "fault_count", "last_fault", "inhibited",
                 "blocked_shafts", "limp_home", "safe_state"):
        setattr(cd, name, int(getattr(d, name)))
    cd.boost = [int(b) for b in d.boost]
    cd.plant_seen = d.plant_seen_t_s is not None
    cd.plant_seen_t_s = d.plant_seen_t_s if d.plant_seen_t_s is not None else 0.0
    cd.have_t_prev = d._t_prev is not None
    cd.t_prev = d._t_prev if d._t_prev is not None else 0.0
    cd.dt = d._dt
    cd.engage_gear = list(d._engage_gear)
    cd.engage_wait_s = list(d._engage_wait_s)
    cd.engage_failed = d._engage_failed
    cd.release_s = list(d.release_s)
    cd.slip_limp_s = list(d._slip_limp_s)


def _sensor_value(name, value):
    """A decoded signal as cantools gives it: an int for a signal of factor 1, offset 0."""
    return int(value) if name in _integer_signals() else float(value)


@functools.cache
def _integer_signals():
    from can_dbc import codec
    return frozenset(s.name for m in codec.messages("PLANT") for s in m.signals
                     if s.scale == 1 and s.offset == int(s.offset) and not s.is_float)


def store_state(c, tcu, shifts, diag_events, sensors=None):
    """A ``tcu_state`` into the TcuLogic ``tcu``: every attribute as its own steps
    would have left it. ``shifts`` and ``diag_events`` (drained from the C) are
    appended to its events; ``sensors`` (the last period's array) becomes ``tcu.s``."""
    from tcu_stub import contract_link

    phases = _layout()[2]
    tcu.phase = phases[c.phase]
    tcu.gear, tcu.target_gear, tcu.shift_from = int(c.gear), int(c.target_gear), int(c.shift_from)
    tcu.pressure_bar = [float(x) for x in c.pressure_bar]
    tcu.sleeve_side = [int(x) for x in c.sleeve_side]
    tcu.fork_pos_prev = [float(x) for x in c.fork_pos_prev]
    tcu.torque_request_nm = float(c.torque_request_nm) if c.has_request else None
    for name in ("shift_t0", "latched_torque_nm", "shift_slip0_rpm", "asr_trim_nm", "asr_cut_nm",
                 "launch_rpm", "creep_nm", "hill_nm", "adapt_t_s", "te_filt_nm", "n_filt_rpm",
                 "idle_load_nm", "t_s"):
        setattr(tcu, name, float(getattr(c, name)))
    tcu.kiss_bar = [float(x) for x in c.kiss_bar]
    tcu.adapt_shaft = int(c.adapt_shaft)
    tcu.oil_degc = float(c.oil_degc)
    tcu.selector = int(c.selector)
    tcu.held = tuple(float(x) for x in c.held)
    tcu.n_shaft = tuple(float(x) for x in c.n_shaft)
    tcu.events += shifts
    for i, loop in enumerate(tcu.loops):
        cl = c.loops[i]
        loop.integral_a, loop.fill_left_s, loop.target_bar = (float(cl.integral_a), float(cl.fill_left_s),
                                                              float(cl.target_bar))
    if c.diag.have_t_prev:            # stepped: what _read took from the sensors
        if sensors is not None:
            names = sensor_names()
            s = {}
            for _, _, fields in contract_link.PLANT_MESSAGES:
                for sig in fields:
                    s[sig] = _sensor_value(sig, sensors[names.index(sig)])
            s["stale"] = False
            tcu.s = s
        tcu.pedal, tcu.brake, tcu.t_engine = float(c.pedal), float(c.brake), float(c.t_engine)
        tcu.n_engine = float(c.n_engine)
        tcu.n_out = tuple(float(x) for x in c.n_out)
        tcu.v_kmh, tcu.v_sched_kmh = float(c.v_kmh), float(c.v_sched_kmh)
        tcu.grade_pct = float(c.grade_pct)
        tcu.p_meas = tuple(float(x) for x in c.p_meas)
        tcu.line_bar = float(c.line_bar)
        tcu.fork_mm = tuple(float(x) for x in c.fork_mm)
        tcu.sync_state = tuple(int(x) for x in c.sync_state)
        tcu.engaged_gear = tuple(int(x) for x in c.engaged_gear)
        tcu.n_shaft_raw = tuple(float(x) for x in c.n_shaft_raw)
    d, cd = tcu.diag, c.diag
    monitors = [cd.speed_invalid[0], cd.speed_invalid[1], cd.speed_plausible[0], cd.speed_plausible[1],
                cd.pressure[0], cd.pressure[1], cd.line, cd.slip[0], cd.slip[1], cd.engage]
    for cm, m in zip(monitors, _monitors(d)):
        m.active, m.fail_s, m.pass_s = bool(cm.active), float(cm.fail_s), float(cm.pass_s)
    for name in ("active_bits", "stored_bits", "fault_count", "last_fault", "inhibited", "blocked_shafts"):
        setattr(d, name, int(getattr(cd, name)))
    d.limp_home, d.safe_state = bool(cd.limp_home), bool(cd.safe_state)
    d.boost = [bool(b) for b in cd.boost]
    d.plant_seen_t_s = float(cd.plant_seen_t_s) if cd.plant_seen else None
    d._t_prev = float(cd.t_prev) if cd.have_t_prev else None
    d._dt = float(cd.dt)
    d._engage_gear = [int(x) for x in cd.engage_gear]
    d._engage_wait_s = [float(x) for x in cd.engage_wait_s]
    d._engage_failed = int(cd.engage_failed)
    d.release_s = [float(x) for x in cd.release_s]
    d._slip_limp_s = [float(x) for x in cd.slip_limp_s]
    for t_s, bit, was_set in diag_events:
        name = _diag.DTCS[bit].name
        if was_set:
            d.set_t_s[name] = t_s
        if len(d.events) < d.MAX_EVENTS:
            d.events.append((t_s, name, "set" if was_set else "healed"))


class CTcu:
    """The C TCU on its own: ``step(t_s, sensors)`` as ``TcuLogic.step`` (sensors by
    DBC signal name, all of ``sensor_names()``), commands by DBC signal name.

    ``source``: None or a calibration (``TcuCalibration``, a dict) for a TCU
    fresh from reset; or a reference ``TcuLogic`` whose calibration (its
    module's constants) and state are taken over (``c_compatible`` says
    whether the C can run it). ``store(tcu)`` writes the C's state into a
    TcuLogic, so it goes on where the C stopped."""

    def __init__(self, source=None):
        ffi, lib = _lib()
        self._ffi, self._lib = ffi, lib
        self.sensor_names, self.command_names, self._phases = _layout()
        self.cal = ffi.new("tcu_cal *")
        self.state = ffi.new("tcu_state *")
        self._sensors = ffi.new("double[]", lib.TCU_N_SENSORS)
        self._commands = ffi.new("double[]", lib.TCU_N_COMMANDS)
        if source is None or isinstance(source, (TcuCalibration, dict)):
            values = TcuCalibration.of(source).resolved()
            fill_calibration(self.cal, values, *derived(values))
            lib.tcu_reset(self.cal, self.state)
        else:
            values, gear_ratio, rpm_per_kmh, diag = tcu_values(source)
            fill_calibration(self.cal, values, gear_ratio, rpm_per_kmh, diag)
            lib.tcu_reset(self.cal, self.state)
            load_state(self.state, source)
        self.shifts = []              # (t_s, from, to) drained from the C
        self.diag_events = []         # (t_s, bit, set) drained from the C

    def reset(self):
        self._lib.tcu_reset(self.cal, self.state)
        self.shifts, self.diag_events = [], []

    def step_array(self, t_s, sensors):
        """One period from a sensors array (``sensor_names()`` order); the commands array."""
        for i, v in enumerate(sensors):
            self._sensors[i] = v
        self._lib.tcu_step(self.cal, self.state, float(t_s), self._sensors, self._commands)
        self.drain()
        return [self._commands[i] for i in range(len(self.command_names))]

    def step(self, t_s, sensors):
        values = self.step_array(t_s, [float(sensors[n]) for n in self.sensor_names])
        return dict(zip(self.command_names, values))

    @property
    def phase(self):
        return self._phases[self.state.phase]

    @property
    def gear(self):
        return int(self.state.gear)

    @property
    def target_gear(self):
        return int(self.state.target_gear)

    def drain(self):
        """Moves the shifts and trouble code events of the C's buffers to ``shifts``, ``diag_events``."""
        s, d = self.state, self.state.diag
        if s.shifts_lost or d.events_lost:
            raise RuntimeError("the C TCU's shift or event buffer overflowed between two drains")
        for i in range(s.n_shifts):
            e = s.shifts[i]
            self.shifts.append((float(e.t_s), int(e.from_gear), int(e.to_gear)))
        for i in range(d.n_events):
            e = d.events[i]
            self.diag_events.append((float(e.t_s), int(e.bit), bool(e.set)))
        s.n_shifts = 0
        d.n_events = 0

    def store(self, tcu, sensors=None):
        """The C's state into the TcuLogic ``tcu`` (the one it was made from): every
        attribute as TcuLogic.step would have left it; ``sensors``: the last sensors
        array (``tcu.s``)."""
        self.drain()
        store_state(self.state, tcu, self.shifts, self.diag_events, sensors)
        self.shifts, self.diag_events = [], []


# ------------------------------------------------------------------ the link
@functools.cache
def _codec_table():
    """The contract's codec table (can_dbc.table) and its ct_table pointer: this
    extension takes the codec's types from can_dbc._can_table (ffi.include)."""
    from can_dbc.table import contract_table

    table = contract_table()
    return table, table.table


def fill_link(link):
    """The contract's plan and routing (contract_link.py's) into a ``tcu_link`` struct."""
    from plant.model import INPUT_NAMES, OUTPUT_NAMES
    from tcu_stub import contract_link

    table, c_table = _codec_table()
    sensors = {n: i for i, n in enumerate(sensor_names())}
    commands = {n: i for i, n in enumerate(command_names())}
    outputs = {n: i for i, n in enumerate(OUTPUT_NAMES)}
    inputs = {n: i for i, n in enumerate(INPUT_NAMES)}
    link.table = c_table
    plant = []
    for name, _, fields in contract_link.PLANT_MESSAGES:
        sigs = table.signal_names(name)
        div, off = contract_link.PLANT_PLAN[name]
        plant.append({"msg": table.index(name), "divisor": div, "offset": off, "n_signals": len(sigs),
                      "source": [outputs[fields[s]] if s in fields else -1 for s in sigs],
                      "target": [sensors[s] if s in fields else -1 for s in sigs]})
    tcu = []
    for name, _, targets in contract_link.TCU_MESSAGES:
        if not any(inp is not None for _, inp in targets.values()):
            continue                      # drives no plant input (TCU_Status)
        sigs = table.signal_names(name)
        div, off = contract_link.TCU_PLAN[name]
        tcu.append({"msg": table.index(name), "divisor": div, "offset": off, "n_signals": len(sigs),
                    "source": [commands[s] if s in targets else -1 for s in sigs],
                    "target": [inputs[targets[s][1]] if s in targets and targets[s][1] is not None
                               else -1 for s in sigs]})
    missing = set(sensors) - {s for _, _, f in contract_link.PLANT_MESSAGES for s in f}
    if missing:
        raise RuntimeError(f"the contract carries no {', '.join(sorted(missing))} for the C TCU")
    for i, m in enumerate(plant):
        _fill_message(link.plant[i], m)
    for i, m in enumerate(tcu):
        _fill_message(link.tcu[i], m)
    link.n_plant, link.n_tcu = len(plant), len(tcu)
    link.received = 0


def _fill_message(c, m):
    pad = [-1] * (16 - m["n_signals"])
    c.msg, c.divisor, c.offset, c.n_signals = m["msg"], m["divisor"], m["offset"], m["n_signals"]
    c.source = m["source"] + pad
    c.target = m["target"] + pad


# ------------------------------------------------------------------ drivers
def fill_driver(d, driver_fn, keep):
    """The C driver for ``driver_fn`` (a ScriptedDriver or SpeedTrackingDriver of
    plant.driver, exactly those classes); EXTERNAL for any other callable.
    ``keep``: a list that keeps the arrays the struct points to alive."""
    from plant import driver as drv

    ffi, lib = _lib()

    def arr(a):
        a = np.ascontiguousarray(a, dtype=np.float64)
        keep.append(a)
        return ffi.cast("double *", ffi.from_buffer(a))

    if type(driver_fn) is drv.ScriptedDriver:
        t = driver_fn.table
        d.kind = lib.TCU_DRIVER_STEP if driver_fn.mode == "step" else lib.TCU_DRIVER_LINEAR
        d.n = len(t)
        d.t_s, d.a, d.b = arr(t[:, 0]), arr(t[:, 1]), arr(t[:, 2])
        if driver_fn.selector_table is not None:
            d.sel = arr(driver_fn.selector_table)
        return True
    if type(driver_fn) is drv.SpeedTrackingDriver and type(driver_fn.car) is drv.CarData:
        c = driver_fn.car
        if max(len(c.full_load_rpm), len(c.drag_rpm)) > MAX_TABLE_ROWS:
            return _external(d, lib)
        d.kind = lib.TCU_DRIVER_SPEED
        d.n = len(driver_fn.trace_t_s)
        d.t_s, d.a = arr(driver_fn.trace_t_s), arr(driver_fn.trace_kmh)
        d.b = arr(driver_fn.trace_accel_mps2)
        for name in ("kp", "ki", "lookahead_s", "integral_limit_n", "hold_brake_pct"):
            setattr(d, name, float(getattr(driver_fn, name)))
        for name in ("mass_kg", "wheel_radius_m", "rolling_resistance", "drag_area_m2",
                     "brake_torque_max_nm", "launch_ratio", "driveline_efficiency", "rotating_mass_factor"):
            setattr(d, name, float(getattr(c, name)))
        d.air_density_kg_m3, d.g_mps2 = drv.AIR_DENSITY_KG_M3, drv.G_MPS2
        d.n_full, d.n_drag = len(c.full_load_rpm), len(c.drag_rpm)
        for name in ("full_load_rpm", "full_load_nm", "drag_rpm", "drag_nm"):
            v = [float(x) for x in getattr(c, name)]
            setattr(d, name, v + [0.0] * (MAX_TABLE_ROWS - len(v)))
        d.integral = float(driver_fn._integral)
        d.has_t_last = driver_fn._t_last is not None
        d.t_last = float(driver_fn._t_last) if driver_fn._t_last is not None else 0.0
        return True
    return _external(d, lib)


def _external(d, lib):
    d.kind = lib.TCU_DRIVER_EXTERNAL
    return False


def _store_driver(d, driver_fn):
    """The C driver's state back into the Python driver (it goes on where the run ended)."""
    from plant import driver as drv

    if type(driver_fn) is drv.SpeedTrackingDriver:
        driver_fn._integral = float(d.integral)
        driver_fn._t_last = float(d.t_last) if d.has_t_last else None


# ------------------------------------------------------------------ the loop
TCU_COLUMNS = ("tcu_target_gear", "tcu_gear", "tcu_phase", "tcu_active_faults", "tcu_limp_home",
               "tcu_kiss1_bar", "tcu_kiss2_bar")
TCU_FLOAT_COLUMNS = ("tcu_kiss1_bar", "tcu_kiss2_bar")     # the others are integers (phase: a name)
CHUNK_PERIODS = 500          # one C call: 1 s of plant time (Ctrl-C is seen between calls)


class FastLoop:
    """Plant + driver + reference TCU in C, ``run_offline``'s loop.

    ``plant``: a plant.model.Plant (reset as wanted; it is stepped in place).
    ``driver_fn``: as run_offline's; ScriptedDriver and SpeedTrackingDriver run
    in C, any other callable is called from Python every 10 ms between C calls.
    ``tcu``: a reference TcuLogic whose calibration and state the C takes over
    and into which it writes its state back (after each ``step``); default a
    fresh one with ``calibration`` (see the module's text).
    ``record_outputs``: the plant outputs recorded every ``record_every_s``
    (with ``time_s`` from the start and ``TCU_COLUMNS``), after the TCU's step
    (run_offline) or, with ``record_before_tcu``, before it (dct-hil
    simulate's CSV). ``scenario``: a plant.scenario.Scenario whose rows apply
    at their times (dct-hil simulate with a CSV). ``trace``: keep each
    period's time, sensors and commands for ``traced()`` (True: the whole run,
    a number: that many periods between two ``traced()``; tests). ``period_s``:
    the period the counts (periods, driver, record, scenario rows) are
    reckoned in: logic.PERIOD_S (run_offline), or dct-hil simulate's tick (the
    plant steps of one TCU period)."""

    def __init__(self, plant, driver_fn, duration_s, record_every_s=0.01, tcu=None, calibration=None,
                 record_outputs=None, record_before_tcu=False, scenario=None, trace=False,
                 period_s=None):
        from plant._dct_plant import ffi as p_ffi
        from plant._dct_plant import lib as p_lib
        from plant.model import OUTPUT_NAMES
        from tcu_stub import contract_link

        if not (isinstance(duration_s, (int, float)) and math.isfinite(duration_s) and duration_s > 0):
            raise ValueError(f"duration_s must be positive, got {duration_s}")
        if not (isinstance(record_every_s, (int, float)) and record_every_s > 0):
            raise ValueError(f"record_every_s must be positive, got {record_every_s}")
        if tcu is not None and calibration is not None:
            raise ValueError("give a calibration or a tcu, not both (a tcu has its module's calibration)")
        tcu = python_tcu(calibration) if tcu is None else tcu
        why = unavailable() or c_compatible(tcu)
        if why:
            raise NotInC(f"the C TCU cannot run this: {why}")
        ffi, lib = _lib()
        self._ffi, self._lib = ffi, lib
        self.plant = plant
        self.driver_fn = driver_fn
        self.py_tcu = tcu
        self.tcu = CTcu(tcu)
        self._keep = []
        steps_per_tcu = max(1, int(round(_logic.PERIOD_S / plant.step_s)))
        period = _logic.PERIOD_S if period_s is None else float(period_s)
        self.tcu_per_driver = max(1, int(round(contract_link.DRIVER_PERIOD_S / period)))
        tcu_per_record = max(1, int(round(record_every_s / period)))
        self.n_periods = int(round(duration_s / period))
        self.record_outputs = list(OUTPUT_NAMES if record_outputs is None else record_outputs)
        index = {n: i for i, n in enumerate(OUTPUT_NAMES)}
        unknown = [n for n in self.record_outputs if n not in index]
        if unknown:
            raise ValueError(f"no plant output {unknown[0]!r}")

        self.link = ffi.new("tcu_link *")
        fill_link(self.link)
        self.driver = ffi.new("tcu_driver *")
        self.driver_in_c = fill_driver(self.driver, driver_fn, self._keep)
        r = self.run = ffi.new("tcu_run *")
        r.plant = ffi.cast("dct_plant *", int(p_ffi.cast("uintptr_t", plant._p)))
        r.plant_step = ffi.cast("int(*)(dct_plant *, int)",
                                int(p_ffi.cast("uintptr_t", p_ffi.addressof(p_lib, "dct_plant_step"))))
        r.plant_update_outputs = ffi.cast(
            "void(*)(dct_plant *)",
            int(p_ffi.cast("uintptr_t", p_ffi.addressof(p_lib, "dct_plant_update_outputs"))))
        r.link, r.cal, r.tcu, r.driver = self.link, self.tcu.cal, self.tcu.state, self.driver
        r.steps_per_tcu, r.tcu_per_driver, r.tcu_per_record = steps_per_tcu, self.tcu_per_driver, tcu_per_record
        r.record_before_tcu = 1 if record_before_tcu else 0
        r.t0_s = plant.time_s
        r.k = 0
        r.tick_s = steps_per_tcu * plant.step_s
        if scenario is not None:
            if not self.driver_in_c and driver_fn is not None:
                raise ValueError("scenario rows go with a C driver or none, not a Python driver")
            from plant.model import INPUT_NAMES
            inputs = {n: i for i, n in enumerate(INPUT_NAMES)}
            times = np.ascontiguousarray(scenario.times, dtype=np.float64)
            values = np.ascontiguousarray(scenario.values, dtype=np.float64)
            columns = np.array([inputs[c] for c in scenario.columns], dtype=np.int32)
            self._keep += [times, values, columns]
            r.n_rows, r.n_row_columns = len(times), len(columns)
            r.row_t = ffi.cast("double *", ffi.from_buffer(times))
            r.row_values = ffi.cast("double *", ffi.from_buffer(values))
            r.row_inputs = ffi.cast("int32_t *", ffi.from_buffer(columns))
        self._rec_index = np.array([index[n] for n in self.record_outputs], dtype=np.int32)
        width = 1 + len(self.record_outputs) + len(TCU_COLUMNS)
        rows = self.n_periods // tcu_per_record + 2
        self.rec = np.zeros((rows, width))
        r.n_rec_outputs = len(self.record_outputs)
        r.rec_outputs = ffi.cast("int32_t *", ffi.from_buffer(self._rec_index))
        r.rec = ffi.cast("double *", ffi.from_buffer(self.rec))
        r.rec_cap = rows
        if trace:
            cap = self.n_periods if trace is True else int(trace)
            self._trace = np.zeros((cap, 1 + lib.TCU_N_SENSORS + lib.TCU_N_COMMANDS))
            r.trace = ffi.cast("double *", ffi.from_buffer(self._trace))
            r.trace_cap = cap
            self._trace_k = 0

    @property
    def k(self):
        """TCU periods run so far."""
        return int(self.run.k)

    @property
    def shifts(self):
        """Every shift the TCU started (the TcuLogic's events)."""
        return list(self.py_tcu.events)

    def step(self, n=None):
        """Runs ``n`` more TCU periods (default: to the end of the duration); the
        TcuLogic and a SpeedTrackingDriver then hold the state the C left (also
        when the plant refuses a step or Ctrl-C stops it)."""
        left = self.n_periods - self.k
        n = left if n is None else min(int(n), left)
        end = self.k + n
        plant, r = self.plant, self.run
        try:
            while self.k < end:
                if self.driver_in_c or self.driver_fn is None:
                    count = min(CHUNK_PERIODS, end - self.k)
                else:
                    k = self.k
                    count = min(self.tcu_per_driver - k % self.tcu_per_driver, end - k)
                    if k % self.tcu_per_driver == 0:
                        for name, value in driver_inputs(self.driver_fn, plant.time_s - float(r.t0_s),
                                                         plant.outputs).items():
                            plant.inputs[name] = value
                        plant.update_outputs()
                status = self._chunk(count)
                self.tcu.drain()
                if status == self._lib.TCU_RUN_ERR_RECORD:
                    raise RuntimeError("the C loop's record buffer is full")
                if status != 0:
                    plant._check(status)
        finally:
            self._store()

    def _chunk(self, count):
        """One C call: ``count`` periods; the plant's status."""
        return self._lib.tcu_run_periods(self.run, count)

    def _store(self):
        self.tcu.store(self.py_tcu, self.run.sensors if self.k else None)
        _store_driver(self.driver, self.driver_fn)

    def recorded(self):
        """{time_s, each recorded output, TCU_COLUMNS}: the rows so far (arrays, a copy)."""
        n = int(self.run.rec_n)
        data = self.rec[:n]
        out = {"time_s": data[:, 0].copy()}
        for j, name in enumerate(self.record_outputs):
            out[name] = data[:, 1 + j].copy()
        base = 1 + len(self.record_outputs)
        for j, name in enumerate(TCU_COLUMNS):
            out[name] = data[:, base + j].copy()
        return out

    def finish(self):
        """The last row as dct-hil simulate writes it: the inputs of the period after
        the last (scenario rows, pedals) applied, then a row if one is due."""
        r, plant = self.run, self.plant
        if not self.driver_in_c and self.driver_fn is not None and self.k % self.tcu_per_driver == 0:
            for name, value in driver_inputs(self.driver_fn, plant.time_s - float(r.t0_s),
                                             plant.outputs).items():
                plant.inputs[name] = value
            plant.update_outputs()
        self._lib.tcu_run_inputs(r)
        _store_driver(self.driver, self.driver_fn)
        if self.k % int(r.tcu_per_record) == 0:
            self._record_row()

    def _record_row(self):
        n = int(self.run.rec_n)
        row = self.rec[n]
        row[0] = self.plant.time_s - float(self.run.t0_s)
        row[1:1 + len(self._rec_index)] = self.plant.output_values[self._rec_index]
        s = self.tcu.state
        row[1 + len(self._rec_index):] = (s.target_gear, s.gear, s.phase, s.diag.active_bits,
                                          1 if s.diag.limp_home else 0, s.kiss_bar[0], s.kiss_bar[1])
        self.run.rec_n = n + 1

    def traced(self):
        """(time_s, sensors, commands) arrays of the periods run since the last call
        (copies; the trace buffer is then empty again)."""
        n = int(self.run.trace_n)
        if self.k - self._trace_k > len(self._trace):
            raise RuntimeError("the trace buffer was full: step fewer periods between traced() calls")
        t = self._trace[:n].copy()
        self.run.trace_n = 0
        self._trace_k = self.k
        ns = self._lib.TCU_N_SENSORS
        return t[:, 0], t[:, 1:1 + ns], t[:, 1 + ns:]


def run_offline_c(plant, driver_fn, duration_s, record_every_s=0.01, tcu=None, calibration=None):
    """``offline.run_offline`` in C: the arguments the C loop takes, the same result
    (NotInC, a ValueError, for a ``tcu`` it cannot run)."""
    from tcu_stub.contract_link import RECORDED

    loop = FastLoop(plant, driver_fn, duration_s, record_every_s, tcu=tcu, calibration=calibration,
                    record_outputs=RECORDED)
    loop.step()
    rec = loop.recorded()
    phases = _layout()[2]
    result = {"time_s": rec["time_s"]}
    for name in RECORDED:
        result[name] = rec[name]
    for name in TCU_COLUMNS:             # the Python loop's types: ints, phase names
        result[name] = ([phases[int(p)] for p in rec[name]] if name == "tcu_phase"
                        else rec[name] if name in TCU_FLOAT_COLUMNS or not len(rec[name])
                        else rec[name].astype(np.int64))
    result["shifts"] = loop.shifts
    return result

