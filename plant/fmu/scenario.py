"""A scenario (``plant/scenarios/*.csv``) as an FMU master takes it: the
input table (a NumPy structured array, ``time`` first, one column per
input; FMPy's ``simulate_fmu(input=...)``) and the start values of the
initial conditions (``start_values=...``).

The FMU's inputs are discrete: a master holds each row until the next, as
``dct-hil simulate`` does, so FMPy reproduces the offline run exactly when
the rows fall on communication points.
"""

from __future__ import annotations

import numpy as np

from plant.scenario import INITIAL_KEYS, TEMPERATURE_KEYS, Scenario, load_scenario


def start_values(scenario: Scenario) -> dict:
    """Start values: the ``initial.*`` of the scenario's ``# initial:`` line
    and the parameters it needs (the clutch command mode its columns script)."""
    init = {**INITIAL_KEYS, **scenario.initial}
    out = {f"{table}.{key}": float(value)
           for table, keys in scenario.param_overrides().items() for key, value in keys.items()}
    out |= {"initial.vehicle_speed_kmh": float(init["vehicle_speed_kmh"]),
           "initial.engine_on": float(init["engine_on"])}
    for i in range(4):
        out[f"initial.sleeve_side[{i}]"] = float(init[f"sleeve{i + 1}_side"])
    for i in range(2):
        out[f"initial.clutch_locked[{i}]"] = float(init[f"clutch{i + 1}_locked"])
    temps = scenario.reset_kwargs()
    if any(key in temps for key in TEMPERATURE_KEYS):
        # the temperatures the file does not give keep their start values:
        # the parameters' thermal.initial_*
        out["initial.temperatures_given"] = 1.0
        for key in TEMPERATURE_KEYS:
            if key in temps:
                out[f"initial.{key}"] = float(temps[key])
    return out


def input_table(scenario: Scenario) -> np.ndarray:
    """The scenario's rows as a structured array: ``time`` and its columns."""
    dtype = [("time", np.float64)] + [(c, np.float64) for c in scenario.columns]
    table = np.zeros(len(scenario.times), dtype=dtype)
    table["time"] = scenario.times
    for k, c in enumerate(scenario.columns):
        table[c] = scenario.values[:, k]
    return table


def for_fmpy(name_or_path: str) -> tuple[np.ndarray, dict, float]:
    """(input table, start values, duration in s) of a shipped scenario's
    name or a scenario file."""
    scenario = load_scenario(name_or_path)
    return input_table(scenario), start_values(scenario), scenario.duration_s
