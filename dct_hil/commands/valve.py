"""dct-hil valve: the clutch valve's steady-state characteristic and current
step responses (``plant.valve_report``), as CSV and PNG, and their figures."""

import os

import numpy as np

from plant.extras import require

from .options import check_writable


def add_parser(sub):
    valve = sub.add_parser("valve", help="clutch valve characteristic and step responses (CSV, PNG)")
    valve.add_argument("--out-dir", default="out/valve", metavar="DIR",
                       help="where to write the files (default out/valve)")
    valve.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    valve.set_defaults(func=run)


def run(args):
    from plant.valve_report import write_valve_report

    require("matplotlib")
    os.makedirs(args.out_dir, exist_ok=True)
    check_writable(os.path.join(args.out_dir, "valve_curve.csv"), "--out-dir")
    r = write_valve_report(args.out_dir, args.params)
    up, down, currents = r.up_bar, r.down_bar, r.currents_a
    print(f"line pressure     {r.line_bar:.2f} bar")
    print(f"pressure at 0 A   {up[0]:.3f} bar; at {currents[-1]:g} A {up[-1]:.2f} bar")
    hyst = float(np.max(np.abs(up - down)))
    print(f"hysteresis        {hyst:.3f} bar (largest rising/falling difference)")
    for a, b, s in r.steps:
        print(f"step {a:g} -> {b:g} A   {s.start_bar:5.2f} -> {s.final_bar:5.2f} bar, "
              f"90 % in {s.time_to(0.9) * 1e3:5.1f} ms, overshoot {s.overshoot * 100:.2f} %")
    print(f"csv               {', '.join(r.files[:2])}")
    print(f"png               {', '.join(r.files[2:])}")
    return 0
