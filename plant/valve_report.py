"""Clutch valve characteristics measured on the plant: the steady-state
clutch pressure over solenoid current (the reference paper's Fig. 8) and
current step responses. Used by ``dct-hil valve`` and the tests."""

from dataclasses import dataclass

import numpy as np

from plant.model import Plant


def steady_state_curve(plant=None, currents=None, settle_s=0.6, clutch=1):
    """Clutch pressure (bar) after ``settle_s`` at each current, swept up
    then down from the same plant (so any hysteresis shows). Returns
    (currents_a, up_bar, down_bar, line_bar)."""
    plant = plant or Plant()
    if currents is None:
        imax = plant.params["hydraulics"]["valve"]["max_current_a"]
        currents = np.linspace(0.0, imax, 41)
    currents = np.asarray(currents, dtype=float)
    plant.reset()
    name = f"solenoid_current{clutch}_a"
    n = int(round(settle_s / plant.step_s))

    def sweep(values):
        out = []
        for i in values:
            plant.inputs[name] = i
            plant.step(n)
            out.append(float(plant.outputs[f"clutch{clutch}_pressure_bar"]))
        return np.array(out)

    up = sweep(currents)
    down = sweep(currents[::-1])[::-1]
    return currents, up, down, float(plant.outputs["line_pressure_bar"])


@dataclass
class StepResponse:
    time_s: np.ndarray
    pressure_bar: np.ndarray
    piston_mm: np.ndarray
    spool_mm: np.ndarray
    start_bar: float
    final_bar: float

    def time_to(self, share):
        """Time after the step at which the pressure has covered ``share``
        of the way from start to final (s)."""
        frac = (self.pressure_bar - self.start_bar) / (self.final_bar - self.start_bar)
        i = int(np.argmax(frac >= share))
        return float(self.time_s[i])

    @property
    def overshoot(self):
        """Largest excursion past the final value, as a share of the step."""
        frac = (self.pressure_bar - self.start_bar) / (self.final_bar - self.start_bar)
        return max(float(frac.max()) - 1.0, 0.0)


def step_response(i_from, i_to, duration_s=0.4, params_path=None, overrides=None,
                  sample_s=0.0005, clutch=1):
    """Clutch pressure after a solenoid current step from ``i_from`` (held
    1 s first) to ``i_to``, sampled every ``sample_s``."""
    plant = Plant(params_path, overrides)
    plant.reset()
    name = f"solenoid_current{clutch}_a"
    plant.inputs[name] = i_from
    plant.step(int(round(1.0 / plant.step_s)))
    start = float(plant.outputs[f"clutch{clutch}_pressure_bar"])
    plant.inputs[name] = i_to
    every = max(1, int(round(sample_s / plant.step_s)))
    n = int(round(duration_s / (every * plant.step_s)))
    rows = np.empty((n, 4))
    for k in range(n):
        plant.step(every)
        o = plant.outputs
        rows[k] = ((k + 1) * every * plant.step_s, float(o[f"clutch{clutch}_pressure_bar"]),
                   float(o[f"piston{clutch}_position_mm"]), float(o[f"spool{clutch}_position_mm"]))
    return StepResponse(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], start, float(rows[-1, 1]))
