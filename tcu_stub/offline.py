"""Closed loop of the plant and the stub TCU in one process, without a back door.

Every TCU period the plant outputs reach the TCU, and its commands the plant,
through the CAN contract with its quantization and cycle times
(``tcu_stub.contract_link.ContractLink``: each message encoded and decoded
with the DBC, a 10 ms message refreshed every fifth period).

``run_offline`` runs this loop in C (``tcu_stub.fast``: the same link, driver
and TCU ported operation for operation, the same results to the bit) unless
what it is given needs the Python loop: ``stale_fn``, ``sensor_fault``,
``on_period``, another ``link``, or a ``tcu`` that is not the reference
TcuLogic. ``tcu_impl="python"`` runs the Python loop anyway.

``run_scheduled`` is the plant server's loop offline: tick by tick, each plant
message at the ticks the server sends it, the maneuver from the tick the live
run started it (the reference of ``dct-hil demo``).
"""

import warnings

import numpy as np

from plant.driver import driver_inputs
from tcu_stub.contract_link import (  # noqa: F401 (re-exported: the loop's public names)
    DRIVER_PERIOD_S,
    RECORDED,
    ContractLink,
    apply_commands,
    sensors_from_plant,
)
from tcu_stub.logic import PERIOD_S, TcuLogic

TCU_IMPLS = ("auto", "c", "python")


def _python_only(stale_fn, on_period, link, sensor_fault):
    """Why the C loop cannot run these options (None: it can)."""
    for name, value in (("stale_fn", stale_fn), ("on_period", on_period), ("link", link),
                        ("sensor_fault", sensor_fault)):
        if value is not None:
            return f"{name} needs the Python loop"
    return None


def run_offline(plant, driver_fn, duration_s, record_every_s=0.01, tcu=None, stale_fn=None,
                on_period=None, link=None, sensor_fault=None, calibration=None, tcu_impl="auto"):
    """Run plant + stub TCU for ``duration_s``.

    ``driver_fn(t_s, plant_outputs) -> (accel_pedal_pct, brake_pedal_pct)`` is
    called every 10 ms (a ScriptedDriver with a selector column also sets
    ``selector_lever``: ``plant.driver.driver_inputs``). The maneuver's fixed
    inputs (``Maneuver.start``: the road grade) are the plant's as given. ``stale_fn(t_s)`` (optional) marks plant messages as
    lost: True for all of them (cause unknown), or {message: cause} for some
    (causes as the CAN node gives them: "missing", "timeout", "bad_crc",
    "bad_counter", "bad_length"; ``sensors["stale_messages"]``); a false
    value for none. ``sensor_fault(t_s, sensors)`` (optional) edits the TCU's
    view each period before the TCU sees it (a signal fault on the sensor
    side: stuck, offset, the invalid value ...); it may return a dict to use
    instead. ``on_period(k, plant)`` (optional) is called every
    TCU period ``k`` once the pedals and commands are applied, before the
    plant steps (a copy of ``plant.inputs`` there replays the run). ``link``:
    the CAN matrix between them (default ``ContractLink``, the project's own
    contract; ``tcu_stub.mapped_link.MappedLink(mapping)`` for a vehicle's
    matrix described by a mapping file). Returns a
    dict of arrays (``time_s``, the names in
    ``RECORDED``, ``tcu_target_gear``, ``tcu_gear``, ``tcu_phase``,
    ``tcu_active_faults``, ``tcu_limp_home``, the adapted kiss points ``tcu_kiss1_bar``,
    ``tcu_kiss2_bar``) and ``shifts``: a list of
    (time_s, from_gear, to_gear).

    ``calibration``: TCU calibration values for this run
    (``tcu_stub.fast.TcuCalibration`` or a dict {constant name: value} of
    tcu_stub/logic.py's constants); not with ``tcu``. ``tcu_impl``: "auto"
    (the C loop when it can run the options given, else Python), "c" (the C
    loop or ValueError), "python" (the Python loop). Both give the same
    result; the TcuLogic (``tcu`` or a fresh one) ends in the same state."""
    if duration_s <= 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    if tcu_impl not in TCU_IMPLS:
        raise ValueError(f"tcu_impl must be one of {', '.join(TCU_IMPLS)}, got {tcu_impl!r}")
    if calibration is not None and tcu is not None:
        raise ValueError("give a calibration or a tcu, not both (a tcu has its module's calibration)")
    if calibration is not None:
        from tcu_stub.fast import python_tcu
        tcu = python_tcu(calibration)
    tcu = tcu or TcuLogic()
    if tcu_impl != "python":
        from tcu_stub import fast

        why = _python_only(stale_fn, on_period, link, sensor_fault)
        missing = None if why else fast.unavailable()
        if missing and tcu_impl == "auto":
            warnings.warn(f"run_offline runs the Python loop: {missing}", RuntimeWarning, stacklevel=2)
        why = why or missing or fast.c_compatible(tcu)
        if why is None:
            return fast.run_offline_c(plant, driver_fn, duration_s, record_every_s, tcu=tcu)
        if tcu_impl == "c":
            raise ValueError(f"tcu_impl 'c': {why}")
    steps_per_tcu = max(1, int(round(PERIOD_S / plant.step_s)))
    tcu_per_driver = max(1, int(round(DRIVER_PERIOD_S / PERIOD_S)))
    tcu_per_record = max(1, int(round(record_every_s / PERIOD_S)))
    n = int(round(duration_s / PERIOD_S))
    rec = {k: [] for k in ("time_s",) + RECORDED + ("tcu_target_gear", "tcu_gear", "tcu_phase",
                                                   "tcu_active_faults", "tcu_limp_home",
                                                   "tcu_kiss1_bar", "tcu_kiss2_bar")}
    t0 = plant.time_s
    link = ContractLink() if link is None else link
    for k in range(n):
        t = plant.time_s - t0
        out = plant.outputs
        if k % tcu_per_driver == 0:
            for name, value in driver_inputs(driver_fn, t, out).items():
                plant.inputs[name] = value
            plant.update_outputs()
        sensors = link.sensors(out, k)
        if stale_fn is not None:
            lost = stale_fn(t)
            if isinstance(lost, dict):
                if lost:
                    sensors["stale"] = True
                    sensors["stale_messages"] = dict(lost)
                else:
                    sensors["stale_messages"] = {}
            elif lost:
                sensors["stale"] = True
        if sensor_fault is not None:
            edited = sensor_fault(t, sensors)
            if edited is not None:
                sensors = edited
        cmd = tcu.step(t, sensors)
        link.apply(plant, cmd, k)
        if on_period is not None:
            on_period(k, plant)
        if k % tcu_per_record == 0:
            rec["time_s"].append(t)
            for name in RECORDED:
                rec[name].append(float(out[name]))
            rec["tcu_target_gear"].append(tcu.target_gear)
            rec["tcu_gear"].append(tcu.gear)
            rec["tcu_phase"].append(tcu.phase)
            rec["tcu_active_faults"].append(tcu.diag.active_bits)
            rec["tcu_limp_home"].append(1 if tcu.diag.limp_home else 0)
            rec["tcu_kiss1_bar"].append(tcu.kiss_bar[0])
            rec["tcu_kiss2_bar"].append(tcu.kiss_bar[1])
        plant.step(steps_per_tcu)
    result = {k: (np.array(v) if k != "tcu_phase" else v) for k, v in rec.items()}
    result["shifts"] = list(tcu.events)
    return result


# ------------------------------------------------- the server's loop, offline
def run_scheduled(plant, driver_fn, duration_s, schedule, start_tick=0, link=None,
                  record_every_ticks=4, tcu=None):
    """The plant server's loop and the reference TCU in one process, tick by
    tick as the server runs them, without a bus: the reference a run over CAN
    is compared with (``dct-hil demo``).

    ``run_offline`` steps the plant a TCU period at a time, the driver every
    10 ms, and shows the TCU every plant message as fresh at its period. The
    server does otherwise, and so does this loop: from its first tick (0) the
    plant sends each message at the ticks of ``schedule`` ((bus, message,
    divisor, offset): ``can_dbc.table.send_schedule`` of the live run's
    mapping; a message with divisor d and offset o is sent after the step of
    the ticks n with n % d == o, carrying the outputs of that step), and the
    TCU reads each message as last sent. Until ``start_tick`` the plant idles
    on the driver's first pedals with no TCU command (the server waiting for
    the TCU); from that tick the maneuver plays: the driver's pedals set
    before every step at maneuver time (the plant time since that tick, as
    the loop's pedal table), the TCU stepping every TCU period from that tick
    on (its commands driving the plant from the tick it steps at: the loop
    starts the maneuver at the first tick that applies a TCU frame), its 10 ms
    messages at every fifth period. The gear is recorded after the step of
    the ticks n with n % ``record_every_ticks`` == 0, at maneuver time (the
    server's recorder). ``link``: ``ContractLink`` (default) or
    ``tcu_stub.mapped_link.MappedLink``: the same matrix as the live run.

    What differs from a run over CAN is what a bus and two clocks add: the
    TCU reading its frames and its frames reaching the plant a tick or more
    later than the schedule (a late wake-up, a skipped tick or period), lost
    or rejected frames. Returns a dict of arrays (``time_s``: maneuver time,
    ``gear``, ``vehicle_speed_kmh``, ``tcu_target_gear``) and ``shifts`` (the
    TCU's events)."""
    import math

    if duration_s <= 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    if start_tick < 0 or record_every_ticks < 1:
        raise ValueError("start_tick must be >= 0 and record_every_ticks >= 1")
    tcu = tcu or TcuLogic()
    link = ContractLink() if link is None else link
    steps_per_tcu = max(1, int(round(PERIOD_S / plant.step_s)))
    plan = [(bus, name, int(div), int(off)) for bus, name, div, off in schedule]
    hyper = 1
    for _, _, div, _ in plan:
        hyper = hyper * div // math.gcd(hyper, div)
    table = None
    if hyper <= 100_000:
        table = [[(b, m) for b, m, d, o in plan if n % d == o] for n in range(hyper)]

    def due(n):
        return table[n % hyper] if table is not None else [(b, m) for b, m, d, o in plan if n % d == o]

    for name, value in driver_inputs(driver_fn, 0.0, plant.outputs).items():
        plant.inputs[name] = value
    plant.update_outputs()
    longest = max((div for _, _, div, _ in plan), default=1)
    quiet = max(0, start_tick - longest)       # nothing sent before that is read
    if quiet:
        plant.step(quiet)
    for n in range(quiet, start_tick):
        plant.step(1)
        link.refresh(plant.outputs, due(n))
    rec = {k: [] for k in ("time_s", "gear", "vehicle_speed_kmh", "tcu_target_gear")}
    t0 = plant.time_s
    out = plant.outputs
    for j in range(int(round(duration_s / plant.step_s))):
        n = start_tick + j
        t = plant.time_s - t0
        if j % steps_per_tcu == 0:
            k = j // steps_per_tcu
            cmd = tcu.step(t, link.view())
            link.apply(plant, cmd, k)
        for name, value in driver_inputs(driver_fn, t, out).items():
            plant.inputs[name] = value
        plant.step(1)
        if n % record_every_ticks == 0:
            rec["time_s"].append(plant.time_s - t0)
            rec["gear"].append(float(out["gear"]))
            rec["vehicle_speed_kmh"].append(float(out["vehicle_speed_kmh"]))
            rec["tcu_target_gear"].append(tcu.target_gear)
        link.refresh(out, due(n))
    result = {k: np.array(v) for k, v in rec.items()}
    result["shifts"] = list(tcu.events)
    return result


# --------------------------------------------------------- dct-hil simulate
# run_offline records the figures of a run (RECORDED, the TCU's state after its
# step); dct-hil simulate records every plant output with the TCU's target
# gear before its step, plays a scenario's rows, and keeps what it recorded
# when a run is stopped: the rows differ, so this is its own entry.
SIMULATE_RECORD_EVERY_S = 0.01


def stub_columns():
    """Scenario columns the stub TCU drives itself: clutches, forks, engine requests."""
    from can_dbc import codec
    from plant.scenario import PRESSURE_COLUMNS

    cols = set(PRESSURE_COLUMNS)
    for targets in codec.TCU_SIGNAL_TARGETS.values():
        cols.update(input_name for _, input_name in targets.values())
    return cols


def run_with_stub(plant, duration_s, out_path, pedals_fn=None, scenario=None,
                  csv_target_gear=True, link=None, tcu_impl="python"):
    """Plant + stub TCU in one process, every message through the CAN contract.

    Each 2 ms TCU tick: the scenario rows due (or, every 10 ms, ``pedals_fn``)
    set the driver inputs, the TCU reads the plant messages and writes its
    commands, the plant steps. Records all plant outputs plus ``tcu_target_gear``
    every 10 ms (the CSV has ``tcu_target_gear`` only with ``csv_target_gear``);
    the rows so far are written to ``out_path`` also when a KeyboardInterrupt or
    a PlantError stops the run (then re-raised). ``tcu_impl`` "c": the same loop
    in C (tcu_stub.fast.FastLoop), same rows.
    Returns (names, data, shifts, wall_s)."""
    import time

    import numpy as np

    from plant.driver import driver_inputs
    from plant.model import PlantError
    from plant.simulate import write_csv

    if tcu_impl == "c":
        return _run_with_stub_c(plant, duration_s, out_path, pedals_fn, scenario, csv_target_gear)
    tcu = TcuLogic()
    link = ContractLink() if link is None else link
    steps_per_tick = max(1, int(round(PERIOD_S / plant.step_s)))
    tick_s = steps_per_tick * plant.step_s
    ticks_per_record = max(1, int(round(SIMULATE_RECORD_EVERY_S / tick_s)))
    ticks_per_driver = max(1, int(round(DRIVER_PERIOD_S / tick_s)))
    n_ticks = int(round(duration_s / tick_s))
    names = list(plant.output_names) + ["tcu_target_gear"]
    n_out = len(plant.output_names)
    n_csv = len(names) if csv_target_gear else n_out
    data = np.empty((n_ticks // ticks_per_record + 1, len(names)))
    row_t = scenario.times if scenario is not None else ()
    row = 0
    j = 0
    t0 = plant.time_s
    wall0 = time.perf_counter()
    try:
        for k in range(n_ticks + 1):
            t = k * tick_s
            changed = False
            while row < len(row_t) and row_t[row] <= t + 1e-9:
                for name, value in zip(scenario.columns, scenario.values[row]):
                    plant.inputs[name] = value
                row += 1
                changed = True
            if pedals_fn is not None and k % ticks_per_driver == 0:
                for name, value in driver_inputs(pedals_fn, plant.time_s - t0, plant.outputs).items():
                    plant.inputs[name] = value          # the pedals, a table's selector lever
                changed = True
            if changed:
                plant.update_outputs()
            if k % ticks_per_record == 0:
                data[j, :n_out] = plant.output_values
                data[j, n_out] = tcu.target_gear
                data[j, 0] = plant.time_s - t0
                j += 1
            if k == n_ticks:
                break
            cmd = tcu.step(plant.time_s - t0, link.sensors(plant.outputs, k))
            link.apply(plant, cmd, k)
            plant.step(steps_per_tick)
    except (KeyboardInterrupt, PlantError):
        if out_path is not None:
            write_csv(out_path, names[:n_csv], data[:j, :n_csv])
        raise
    wall = time.perf_counter() - wall0
    if out_path is not None:
        write_csv(out_path, names[:n_csv], data[:j, :n_csv])
    return names, data[:j], list(tcu.events), wall


def _run_with_stub_c(plant, duration_s, out_path, pedals_fn, scenario, csv_target_gear):
    """run_with_stub's loop in C: the same rows (every plant output and the TCU's
    target gear before its step, every 10 ms, and the end state)."""
    import time

    from plant.model import PlantError
    from plant.simulate import write_csv
    from tcu_stub.fast import FastLoop

    steps_per_tick = max(1, int(round(PERIOD_S / plant.step_s)))
    names = list(plant.output_names) + ["tcu_target_gear"]
    n_out = len(plant.output_names)
    n_csv = len(names) if csv_target_gear else n_out
    loop = FastLoop(plant, pedals_fn, duration_s, SIMULATE_RECORD_EVERY_S, record_outputs=names[1:n_out],
                    record_before_tcu=True, scenario=scenario, period_s=steps_per_tick * plant.step_s)
    wall0 = time.perf_counter()
    try:
        loop.step()
    except (KeyboardInterrupt, PlantError):
        if out_path is not None:
            write_csv(out_path, names[:n_csv], loop.rec[:int(loop.run.rec_n), :n_csv])
        raise
    loop.finish()
    wall = time.perf_counter() - wall0
    data = loop.rec[:int(loop.run.rec_n), :n_out + 1]   # t, outputs, then the target gear
    if out_path is not None:
        write_csv(out_path, names[:n_csv], data[:, :n_csv])
    return names, data, loop.shifts, wall
