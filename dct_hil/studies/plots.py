"""PNG plots of the studies: a sweep's figures over its parameters, its Pareto front,
and a fit's measured and simulated signals with their residuals.

- ``figures_<case>.png``: one row per figure the case has (0-100 time, fuel, RMS
  speed error, shifts, gear clashes, max jerk, top speed), one column per swept
  parameter; each point's value (lines through the points of a one-parameter grid).
- ``pareto.png``: the two figures of ``[pareto]`` for every point, the Pareto front
  (both minimised) drawn through its points and labelled with their parameter values.
- ``fit_residuals.png`` (``fit_plot``): per measurement and signal, measured against
  simulated with the fitted and the start values, and the residuals underneath.
"""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from dct_hil.studies.runs import UNITS

MAIN_FIGURES = ("zero_to_100_s", "fuel_l_per_100km", "rms_speed_error_kmh", "shifts",
                "gear_clashes", "max_jerk_mps3", "top_speed_kmh")


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "case"


def _label(fig: str) -> str:
    unit = UNITS.get(fig, "")
    return f"{fig} [{unit}]" if unit else fig


def sweep_plots(spec, run_df, point_df, out: Path) -> list[Path]:
    """Write the sweep's plots into ``out``; returns their paths."""
    paths: list[Path] = []
    cols = [q.column for q in spec.parameters]
    ok = run_df[run_df["status"] == "ok"]
    if cols and not ok.empty:
        for case in spec.cases:
            sub = ok[ok["case"] == case.label]
            figs = [f for f in MAIN_FIGURES if np.isfinite(sub[f].to_numpy(dtype=float)).any()]
            if sub.empty or not figs:
                continue
            fig, axes = plt.subplots(len(figs), len(cols), squeeze=False,
                                     figsize=(max(6.0, 3.6 * len(cols) + 1.0), 2.1 * len(figs) + 0.8),
                                     constrained_layout=True)
            line = spec.sampling == "grid" and len(cols) == 1
            for r, f in enumerate(figs):
                for c, col in enumerate(cols):
                    ax = axes[r][c]
                    x = sub[col].to_numpy(dtype=float)
                    y = sub[f].to_numpy(dtype=float)
                    order = np.argsort(x, kind="stable")
                    ax.plot(x[order], y[order], "o-" if line else "o", ms=4, lw=1.0,
                            color="tab:blue")
                    ax.ticklabel_format(axis="y", useOffset=False)
                    if r == len(figs) - 1:
                        ax.set_xlabel(col)
                    if c == 0:
                        ax.set_ylabel(_label(f), fontsize="small")
                    ax.grid(True, alpha=0.3)
            n_failed = int((run_df[run_df["case"] == case.label]["status"] == "failed").sum())
            title = f"sweep {spec.name}: {case.label} ({len(sub)} runs"
            title += f", {n_failed} failed)" if n_failed else ")"
            fig.suptitle(title)
            path = out / f"figures_{_slug(case.label)}.png"
            fig.savefig(path, dpi=90)
            plt.close(fig)
            paths.append(path)
    if spec.pareto and "pareto" in point_df:
        paths.append(pareto_plot(spec, point_df, out / "pareto.png"))
    return paths


def pareto_plot(spec, point_df, path: Path) -> Path:
    x, y = spec.pareto
    cols = [q.column for q in spec.parameters]
    xs = point_df[x].to_numpy(dtype=float)
    ys = point_df[y].to_numpy(dtype=float)
    front = point_df["pareto"].to_numpy(dtype=bool)
    fig, ax = plt.subplots(figsize=(7.5, 5.5), constrained_layout=True)
    ok = np.isfinite(xs) & np.isfinite(ys)
    if len(cols) == 1 and ok.any():
        sc = ax.scatter(xs[ok], ys[ok], c=point_df[cols[0]].to_numpy(dtype=float)[ok],
                        cmap="viridis", s=30, zorder=2, label="points")
        fig.colorbar(sc, ax=ax, label=cols[0])
    else:
        ax.scatter(xs[ok], ys[ok], s=24, color="tab:gray", zorder=2, label="points")
    idx = np.flatnonzero(front)
    idx = idx[np.argsort(xs[idx])]
    if len(idx):
        ax.plot(xs[idx], ys[idx], "-", color="tab:red", lw=1.5, zorder=3)
        ax.scatter(xs[idx], ys[idx], s=60, facecolors="none", edgecolors="tab:red", lw=1.5,
                   zorder=4, label=f"Pareto front ({len(idx)} points)")
        for i in idx:
            text = ", ".join(f"{point_df[c].iloc[i]:.3g}" for c in cols)
            ax.annotate(text, (xs[i], ys[i]), textcoords="offset points", xytext=(5, 5),
                        fontsize="x-small", color="tab:red")
    ax.set_xlabel(_pareto_label(x))
    ax.set_ylabel(_pareto_label(y))
    ax.set_title(f"sweep {spec.name}: {y} against {x}\n(labels: {', '.join(cols) or 'point'})",
                 fontsize="medium")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _pareto_label(col: str) -> str:
    case, fig = col.rsplit(".", 1)
    return f"{case}: {_label(fig)}"


def fit_plot(path: Path, panels: list[dict], title: str) -> Path:
    """``panels``: {"title", "t", "measured", "start", "fitted", "unit"} per measurement
    and signal; two rows each: the signals, then the residuals (measured - fitted)."""
    n = len(panels)
    fig, axes = plt.subplots(2, n, squeeze=False, figsize=(5.5 * n + 0.5, 6.5),
                             constrained_layout=True, gridspec_kw={"height_ratios": [2, 1]})
    for c, p in enumerate(panels):
        ax = axes[0][c]
        ax.plot(p["t"], p["measured"], ".", ms=1.5, color="tab:gray", label="measured")
        if p.get("start") is not None:
            ax.plot(p["t"], p["start"], "--", lw=1.0, color="tab:orange", label="start values")
        ax.plot(p["t"], p["fitted"], "-", lw=1.2, color="tab:blue", label="fitted")
        ax.set_title(p["title"], fontsize="medium")
        ax.set_ylabel(p["unit"])
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
        ax = axes[1][c]
        res = np.asarray(p["measured"]) - np.asarray(p["fitted"])
        ax.plot(p["t"], res, ".", ms=1.5, color="tab:blue")
        ax.axhline(0.0, color="k", lw=0.8)
        rms = float(np.sqrt(np.mean(res ** 2))) if len(res) else float("nan")
        ax.set_title(f"residual, RMS {rms:.3g}", fontsize="small")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(p["unit"])
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
