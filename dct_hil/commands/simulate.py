"""dct-hil simulate: a scenario or a maneuver offline, as fast as the CPU goes
(``plant.simulate.run`` without a TCU, ``tcu_stub.offline.run_with_stub`` with
the TCU stub), then the run's figures, the CSV and the plots."""

import math
import os
import sys

from can_dbc.options import add_matrix_options
from plant import argtypes
from plant.extras import require
from plant.maneuvers import MANEUVERS

from .options import UserError, check_writable


def add_parser(sub):
    sim = sub.add_parser("simulate", help="run a scenario offline, as fast as possible")
    sim.add_argument("--scenario", required=True, metavar="NAME_OR_FILE",
                     help="a maneuver (" + ", ".join(MANEUVERS) + "), a shipped scenario name "
                          "(plant/scenarios) or a CSV file")
    sim.add_argument("--duration", type=argtypes.seconds_or_zero, metavar="S",
                     help="simulated seconds (default: the scenario's length; the last row holds)")
    sim.add_argument("--out", metavar="FILE.csv", help="write the outputs every 10 ms to this CSV")
    sim.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    sim.add_argument("--tcu", choices=("stub", "none"), default=None,
                     help="stub: the in-process TCU stub drives clutches and forks (default when "
                          "the scenario scripts neither, and for the maneuvers); none: play the "
                          "scenario's own clutch and fork columns")
    sim.add_argument("--plot", action="store_true",
                     help="write PNG plots next to the CSV (or in out/NAME/ without --out)")
    add_matrix_options(
        sim, needs_mapping=True,
        mapping_help="the TCU stub talks to the plant through this vehicle matrix (a mapping "
                     "file, or a shipped one: dct_hil, vehicle) instead of the project's own "
                     "contract")
    sim.add_argument("--tcu-impl", choices=("c", "python"), default=None,
                     help="the TCU stub's loop: c, the reference TCU, driver and CAN contract "
                          "compiled (tcu_stub/fast.py; the default, except with --mapping), or "
                          "python (tcu_stub/logic.py stepped from Python; same results, about 30x "
                          "slower)")
    sim.set_defaults(func=run)


_IMPL_TEXT = {"c": "compiled loop", "python": "Python loop"}


def _tcu_impl(args):
    """The loop of the TCU stub: "c" unless --tcu-impl python or --mapping."""
    if args.tcu_impl == "c" and args.mapping:
        raise UserError("--tcu-impl c: the compiled loop speaks the project's own contract only; "
                        "drop --mapping or use --tcu-impl python")
    if args.tcu_impl is None and not args.mapping:
        from tcu_stub.fast import unavailable

        missing = unavailable()
        if missing:
            print(f"dct-hil: note: the Python loop: {missing}", file=sys.stderr)
            return "python"
    return args.tcu_impl or ("python" if args.mapping else "c")


def _plots(args, names, data, title):
    from plant.plots import write_plots

    if args.out:
        out_dir = os.path.dirname(os.path.abspath(args.out))
    else:
        out_dir = os.path.join("out", title)
    rec = {n: data[:, k] for k, n in enumerate(names)}
    try:
        paths = write_plots(rec, out_dir, title=title)
    except ValueError as e:
        raise UserError(f"--plot: {e}") from None
    for p in paths:
        print(f"plot              {p}")


def _print_run(plant, simulated_s, wall_s, rows, args):
    print(f"simulated         {simulated_s:.3f} s  ({int(round(simulated_s / plant.step_s))} steps "
          f"of {plant.step_s * 1e3:g} ms)")
    print(f"wall time         {wall_s:.3f} s")
    rtf = simulated_s / wall_s if wall_s > 0 else math.inf
    print(f"real-time factor  {rtf:.0f}x")
    if args.out:
        print(f"csv               {args.out}  ({rows} rows, every 10 ms)")
    else:
        print("csv               not written (use --out FILE.csv)")
    out = plant.outputs
    print(
        f"end state         {float(out['vehicle_speed_kmh']) + 0.0:.1f} km/h, "
        f"engine {float(out['engine_speed_rpm']):.0f} rpm, "
        f"gear {float(out['gear']):.0f}, "
        f"fuel {float(out['fuel_l']):.4f} l, "
        f"gear clashes {float(out['gear_clashes']):.0f}"
    )


def _print_saturated(link):
    """With --mapping: the values the matrix's codec limited to their signal's
    range or bit field (as the real-time loop limits them), per signal."""
    counts = getattr(link, "saturated", None)
    if counts is None:
        return
    if not counts:
        print("saturated         none (every value within its signal's range)")
        return
    total = sum(counts.values())
    worst = sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))
    shown = ", ".join(f"{k} {n}" for k, n in worst[:5]) + (", ..." if len(worst) > 5 else "")
    print(f"saturated         {total} values limited to their signal's range (as the loop sends "
          f"them): {shown}")


def _interrupted(plant, args):
    where = f"; partial CSV in {args.out}" if args.out else ""
    print(f"dct-hil: interrupted at t={plant.time_s:.3f} s{where}", file=sys.stderr)
    return 130


class _Interrupted(Exception):
    """Ctrl-C during a run; carries the exit code."""

    def __init__(self, code):
        super().__init__(code)
        self.code = code


def _guarded_run(plant, args, fn, *a, **kw):
    """Runs ``fn``; Ctrl-C becomes _Interrupted (the run has written the rows
    recorded so far) and a plant error names the partial CSV."""
    from plant.model import PlantError

    try:
        return fn(*a, **kw)
    except KeyboardInterrupt:
        raise _Interrupted(_interrupted(plant, args)) from None
    except PlantError as e:
        if args.out:
            raise PlantError(f"{e} (outputs up to then in {args.out})") from None
        raise


def _stub_link(args):
    """(link, description) of the matrix between the plant and the TCU stub."""
    if not getattr(args, "mapping", None):
        return None, "the CAN contract"
    from can_dbc.mapping import MappingError, load_options
    from tcu_stub.mapped_link import MappedLink, MissingSignalError

    try:
        m = load_options(args.mapping, args.dbc)
        return MappedLink(m), f"the matrix of {m.path}"
    except (MappingError, MissingSignalError) as e:
        raise UserError(str(e)) from None


def _simulate_maneuver(args):
    from plant.maneuvers import format_report, gear_shifts, get_maneuver, report
    from plant.model import Plant
    from tcu_stub.offline import run_with_stub

    if args.tcu == "none":
        raise UserError(f"--tcu none: maneuver {args.scenario} needs the TCU stub "
                        "(give a CSV scenario to play without a TCU)")
    try:
        m = get_maneuver(args.scenario)
    except ValueError as e:
        raise UserError(str(e)) from None
    duration = m.duration_s if args.duration is None else args.duration
    if duration <= 0:
        raise UserError(f"--duration must be > 0 for maneuver {m.name}")
    impl = _tcu_impl(args)
    link, through = _stub_link(args)
    plant = Plant(args.params)
    m.start(plant)                      # its reset and fixed inputs (the road grade)
    try:
        names, data, shifts, wall = _guarded_run(plant, args, run_with_stub, plant, duration,
                                                 args.out, pedals_fn=m.driver, link=link,
                                                 tcu_impl=impl)
    except _Interrupted as e:
        return e.code
    print(f"maneuver          {m.name}  ({m.description})")
    print(f"tcu               stub (in-process, through {through}; {_IMPL_TEXT[impl]})")
    _print_run(plant, float(data[-1, 0]), wall, len(data), args)
    _print_saturated(link)
    rec = {n: data[:, k] for k, n in enumerate(names)}
    figures = report(m, rec)
    clashes = float(rec["gear_clashes"][-1] - rec["gear_clashes"][0])
    # shifts as the CSV shows them: the gear column's changes (plant.maneuvers.gear_shifts).
    # The TCU's count differs: the gear carrying the torque can change without a shift
    # (wltc: four 1-2-1 handovers while creeping), a shift taken back changes none
    print(f"report            {format_report(m.name, figures)}, gear_clashes = {clashes:.0f}, "
          f"shifts = {len(gear_shifts(rec['time_s'], rec['gear']))} (the gear column; "
          f"the TCU started {len(shifts)})")
    if args.plot:
        _plots(args, names, data, m.name)
    return 0


def run(args):
    from plant.model import Plant
    from plant.scenario import ScenarioError, load_scenario
    from plant.simulate import run as play_scenario
    from tcu_stub.offline import run_with_stub, stub_columns

    if args.plot:
        require("matplotlib")
    if args.out:
        check_writable(args.out, "--out")
    if args.dbc and not args.mapping:
        raise UserError("--dbc goes with --mapping (the project's own contract has its own DBC)")
    if args.scenario in MANEUVERS:
        return _simulate_maneuver(args)
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as e:
        if str(e).startswith("unknown scenario"):
            raise ScenarioError(f"{e}; maneuvers: {', '.join(MANEUVERS)}") from None
        raise
    scripted = sorted(set(scenario.columns) & stub_columns())
    tcu = args.tcu or ("none" if scripted else "stub")
    if tcu == "stub" and scripted:
        raise UserError(f"--tcu stub: scenario {scenario.name} scripts {', '.join(scripted)}, "
                        "which the stub drives; use --tcu none or drop those columns")
    if tcu == "none" and args.mapping:
        raise UserError(f"--mapping: scenario {scenario.name} runs without the TCU stub "
                        "(--tcu none), and the mapping is the stub's matrix")
    if tcu == "none" and args.tcu_impl:
        raise UserError(f"--tcu-impl: scenario {scenario.name} runs without the TCU stub (--tcu none)")
    link, through = _stub_link(args) if tcu == "stub" else (None, None)
    plant = Plant(args.params, scenario.param_overrides())
    if tcu == "stub":
        from plant.simulate import start

        impl = _tcu_impl(args)
        duration = scenario.duration_s if args.duration is None else args.duration
        start(plant, scenario)
        try:
            names, data, _shifts, wall = _guarded_run(
                plant, args, run_with_stub, plant, duration, args.out, scenario=scenario,
                csv_target_gear=False, link=link, tcu_impl=impl)
        except _Interrupted as e:
            return e.code
        print(f"scenario          {scenario.name}  ({scenario.path})")
        print(f"tcu               stub (in-process, through {through}; {_IMPL_TEXT[impl]}): "
              "clutches and forks")
        _print_run(plant, float(data[-1, 0]), wall, len(data), args)
        _print_saturated(link)
        if args.plot:
            _plots(args, names, data, scenario.name)
        return 0

    try:
        res = _guarded_run(plant, args, play_scenario, plant, scenario, duration_s=args.duration,
                           out_path=args.out)
    except _Interrupted as e:
        return e.code

    print(f"scenario          {scenario.name}  ({scenario.path})")
    mode = ("clutch pressures commanded (hydraulics bypassed)"
            if plant.params["hydraulics"]["pressure_commanded"]
            else "valve currents through the clutch hydraulics")
    print(f"clutch command    {mode}")
    print("tcu               none (the scenario scripts the clutches and forks)")
    _print_run(plant, res.simulated_s, res.wall_s, len(res.data), args)
    if args.plot:
        _plots(args, res.names, res.data, scenario.name)
    return 0
