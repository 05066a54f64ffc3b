"""dct-hil bench: the cost of one plant step (``plant.simulate.bench_report``),
printed and written as JSON; --check fails above the real-time loop's target."""

import sys

from plant import argtypes, simulate
from plant.machine import write_figures

from .options import check_writable


def add_parser(sub):
    bench = sub.add_parser("bench", help="measure the cost of one plant step")
    bench.add_argument("--steps", type=argtypes.whole_number(1, simulate.MAX_BENCH_STEPS), default=200_000, metavar="N",
                       help="steps to time (default 200000)")
    bench.add_argument("--json", default="out/bench.json", metavar="FILE",
                       help="write the figures here (default out/bench.json; the folder is created)")
    bench.add_argument("--scenario", default="launch-1st", metavar="NAME_OR_FILE",
                       help="inputs to play while timing (default launch-1st)")
    bench.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    bench.add_argument("--repeat", type=argtypes.whole_number(1, 20), default=1, metavar="K",
                       help="time the run K times (default 1); every run's figures are kept, "
                            "the report and --check take the run with the lowest median "
                            "(the code's cost, with the least interference from the machine)")
    bench.add_argument("--check", action="store_true",
                       help=f"exit 1 if the median step cost is above {simulate.TARGET_MEDIAN_US} us")
    bench.set_defaults(func=run)


def run(args):
    from plant.scenario import load_scenario

    check_writable(args.json, "--json")
    scenario = load_scenario(args.scenario)
    report = simulate.bench_report(scenario, args.params, args.steps, args.repeat)
    write_figures(args.json, report)
    runs, fig, best = report["runs"], report, report["best_run"] - 1
    target = simulate.TARGET_MEDIAN_US
    print(f"bench             {scenario.name}, {args.steps} steps of {report['step_s'] * 1e3:g} ms")
    if args.repeat > 1:
        medians = ", ".join(f"{r['median_us']:.3f}" for r in runs)
        print(f"runs              {args.repeat}, medians {medians} us; run {best + 1} "
              "(the lowest median) below")
    print(
        f"step cost (us)    median {fig['median_us']:.3f}, p90 {fig['p90_us']:.3f}, "
        f"p99 {fig['p99_us']:.3f}, p99.9 {fig['p99_9_us']:.3f}, max {fig['max_us']:.1f}"
    )
    print(f"mean              {fig['mean_us']:.3f} us, {fig['steps_per_s']:.3g} steps/s")
    print(f"real-time factor  {fig['real_time_factor']:.0f}x  (step / mean step cost)")
    print(f"json              {args.json}")
    if args.check:
        if fig["median_us"] > target:
            print(
                f"dct-hil: bench check failed: median step cost {fig['median_us']:.3f} us "
                f"is above the {target} us target",
                file=sys.stderr,
            )
            return 1
        print(f"check             passed (median <= {target} us)")
    return 0
