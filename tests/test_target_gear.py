"""The TCU's target gear in the demo's recording and plot: the TCU sends it in
TCU_EngineCmd (TargetGear), the loop records it with the commands it applied
(``cmd_target_gear``) and the gear panel draws it as for an offline run."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from plant.plots import _plot
from rt_loop.measure.recorder import read_recording

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_demo_records_the_tcus_target_gear_ahead_of_the_engaged_gear(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", "--duration", "5",
                           "--out", str(tmp_path), "--priority", "0", "--quiet"],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    rec = read_recording(tmp_path / "plant.csv")
    assert "cmd_target_gear" in rec
    started = rec["maneuver_time_s"] >= 0
    target, gear = rec["cmd_target_gear"][started], rec["gear"][started]
    assert target[0] == 1 and set(np.unique(target)) == {1.0, 2.0}
    # the TCU targets 2nd when it starts the shift, the plant engages it later
    assert np.argmax(target == 2) < np.argmax(gear == 2)
    assert (gear[np.argmax(gear == 2):] == 2).all() and (target[np.argmax(target == 2):] == 2).all()


def _gear_panel_lines(rec):
    fig = _plot(rec, "x")
    try:
        ax = fig.axes[3]
        return {line.get_label(): line.get_ydata() for line in ax.get_lines()}
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)


def test_the_gear_panel_draws_the_target_gear_of_a_recording_as_of_an_offline_run():
    t = np.arange(0.0, 1.0, 0.01)
    base = {"time_s": t, "vehicle_speed_kmh": 10 * t, "engine_speed_rpm": 2000 + 0 * t,
            "clutch1_pressure_bar": 5 + 0 * t, "gear": np.where(t < 0.6, 1.0, 2.0)}
    target = np.where(t < 0.5, 1.0, 2.0)
    for column in ("tcu_target_gear", "cmd_target_gear"):
        lines = _gear_panel_lines({**base, column: target})
        np.testing.assert_array_equal(lines["TCU target gear"], target)
        np.testing.assert_array_equal(lines["engaged gear"], base["gear"])
    assert "TCU target gear" not in _gear_panel_lines(base)
