"""Clutch valve characteristics measured on the plant: the steady-state
clutch pressure over solenoid current (the reference paper's Fig. 8) and
current step responses. Used by ``dct-hil valve`` and the tests."""

import os
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


# -------------------------------------------------------------- dct-hil valve
VALVE_STEPS = ((0.0, 0.6), (0.6, 0.0), (0.3, 0.7), (0.7, 0.3), (0.0, 1.0))   # A -> A


@dataclass
class ValveReport:
    line_bar: float
    currents_a: np.ndarray
    up_bar: np.ndarray
    down_bar: np.ndarray
    steps: list               # (from A, to A, StepResponse)
    files: list               # the CSVs, then the PNGs


def write_valve_report(out_dir, params_path=None):
    """The steady-state curve and the step responses of ``VALVE_STEPS`` with the
    hydraulics on (valve currents, not commanded pressures), written to
    ``out_dir`` as valve_curve.csv, valve_steps.csv and their PNG plots."""
    overrides = {"hydraulics": {"pressure_commanded": 0}}
    plant = Plant(params_path, overrides)
    currents, up, down, line = steady_state_curve(plant)
    curve_csv = os.path.join(out_dir, "valve_curve.csv")
    np.savetxt(curve_csv, np.column_stack([currents, up, down]), fmt="%.6g", delimiter=",",
               header="solenoid_current_a,pressure_rising_bar,pressure_falling_bar", comments="")
    steps = [step_response(a, b, params_path=params_path, overrides=overrides) for a, b in VALVE_STEPS]
    step_csv = os.path.join(out_dir, "valve_steps.csv")
    cols, names = [steps[0].time_s], ["time_s"]
    for (a, b), r in zip(VALVE_STEPS, steps):
        tag = f"{a:g}_to_{b:g}a"
        cols += [r.pressure_bar, r.piston_mm]
        names += [f"pressure_{tag}_bar", f"piston_{tag}_mm"]
    np.savetxt(step_csv, np.column_stack(cols), fmt="%.6g", delimiter=",", header=",".join(names),
               comments="")
    png = valve_plots(out_dir, currents, up, down, line, steps)
    return ValveReport(line, currents, up, down, [(a, b, r) for (a, b), r in zip(VALVE_STEPS, steps)],
                       [curve_csv, step_csv, *png])


def valve_plots(out_dir, currents, up, down, line, steps):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.plot(currents, up, label="current rising")
    ax.plot(currents, down, "--", label="current falling")
    ax.axhline(line, color="grey", lw=0.8, ls=":", label="line pressure")
    ax.set_xlabel("solenoid current (A)")
    ax.set_ylabel("clutch pressure (bar)")
    ax.set_title("Clutch valve: steady-state pressure over current")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    files.append(os.path.join(out_dir, "valve_curve.png"))
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for (a, b), r in zip(VALVE_STEPS, steps):
        ax1.plot(r.time_s * 1e3, r.pressure_bar, label=f"{a:g} -> {b:g} A")
        ax2.plot(r.time_s * 1e3, r.piston_mm)
    ax1.set_ylabel("clutch pressure (bar)")
    ax1.set_title("Clutch valve: current step responses")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("piston (mm)")
    ax2.set_xlabel("time after the step (ms)")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    files.append(os.path.join(out_dir, "valve_steps.png"))
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    return files
