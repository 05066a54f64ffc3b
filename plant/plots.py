"""PNG plots of a recorded run, laid out like the reference paper's Figs. 10 and 11.

One figure, four stacked axes sharing time: vehicle speed and acceleration;
engine and input-shaft speeds; clutch pressures; the engaged gear (the plant's
``gear``: the gear engaged on the input shaft whose clutch carries the drive
torque or, while neither clutch does, carried it last) and the TCU's target
gear (``tcu_target_gear`` of an offline run, or ``cmd_target_gear`` of a plant
server recording: the TargetGear signal of TCU_EngineCmd as the loop received
it). ``write_plots`` writes it for the whole run and, when the gear changes,
once more zoomed on the first upshift.
"""

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from plant.maneuvers import as_arrays

REQUIRED = ("time_s", "vehicle_speed_kmh")
#: columns that hold the TCU's target gear, the first one present is plotted
TARGET_GEAR_COLUMNS = ("tcu_target_gear", "cmd_target_gear")


def _plot(rec, title, window=None):
    t = rec["time_s"]
    sel = np.ones(len(t), dtype=bool) if window is None else (t >= window[0]) & (t <= window[1])
    ts = t[sel]

    def has(name):
        return name in rec

    def y(name):
        return rec[name][sel]

    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(10, 10), constrained_layout=True)
    ax = axes[0]
    ax.plot(ts, y("vehicle_speed_kmh"), color="tab:blue", label="vehicle speed")
    ax.set_ylabel("speed [km/h]", color="tab:blue")
    if has("vehicle_accel_mps2"):
        ax2 = ax.twinx()
        ax2.plot(ts, y("vehicle_accel_mps2"), color="tab:red", lw=0.8, label="acceleration")
        ax2.set_ylabel("acceleration [m/s²]", color="tab:red")
    ax.set_title(title)

    ax = axes[1]
    for name, label in (("engine_speed_rpm", "engine"), ("input_shaft1_speed_rpm", "input shaft 1 (K1)"),
                        ("input_shaft2_speed_rpm", "input shaft 2 (K2)")):
        if has(name):
            ax.plot(ts, y(name), lw=1.0, label=label)
    ax.set_ylabel("speed [rpm]")
    ax.legend(loc="upper right", fontsize="small")

    ax = axes[2]
    for name, label in (("clutch1_pressure_bar", "K1"), ("clutch2_pressure_bar", "K2")):
        if has(name):
            ax.plot(ts, y(name), lw=1.0, label=label)
    ax.set_ylabel("clutch pressure [bar]")
    ax.legend(loc="upper right", fontsize="small")

    ax = axes[3]
    if has("gear"):
        ax.step(ts, y("gear"), where="post", lw=1.2, label="engaged gear")
    target = next((name for name in TARGET_GEAR_COLUMNS if has(name)), None)
    if target is not None:
        ax.step(ts, y(target), where="post", lw=1.0, ls="--", label="TCU target gear")
    ax.set_ylabel("gear")
    ax.set_yticks(range(-1, 7))
    ax.set_ylim(-1.5, 6.5)
    ax.set_xlabel("time [s]")
    ax.legend(loc="upper right", fontsize="small")
    for a in axes:
        a.grid(True, alpha=0.3)
    return fig


def first_upshift_s(rec):
    """Time of the first rise of ``gear`` (else ``tcu_gear``) to a higher gear, or None."""
    g = rec.get("gear", rec.get("tcu_gear"))
    if g is None:
        return None
    held = g[0]
    for k in range(1, len(g)):
        if g[k] <= 0:
            continue
        if held > 0 and g[k] > held:
            return float(rec["time_s"][k])
        held = g[k]
    return None


def write_plots(recorded, out_dir, title="dct-hil run"):
    """Write the PNGs of a recorded run into ``out_dir``; returns their paths."""
    rec = as_arrays(recorded)
    for name in REQUIRED:
        if name not in rec:
            raise ValueError(f"recorded run has no '{name}' to plot")
    if len(rec["time_s"]) < 2:
        raise ValueError("recorded run needs at least 2 samples to plot")
    out = Path(out_dir)
    os.makedirs(out, exist_ok=True)
    stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in title).strip("_") or "run"
    paths = []
    fig = _plot(rec, title)
    p = out / f"{stem}.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(str(p))
    t_shift = first_upshift_s(rec)
    if t_shift is not None:
        fig = _plot(rec, f"{title}: first upshift", window=(t_shift - 1.0, t_shift + 1.0))
        p = out / f"{stem}_upshift.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(str(p))
    return paths
