"""dct-hil command line.

    dct-hil simulate --scenario launch-1st --out out/launch-1st.csv
    dct-hil bench --steps 200000 --check          # figures in out/bench.json

User errors (bad options, parameter files, scenarios, a plant that blows up)
print one line ``dct-hil: error: <cause>`` and exit 2; Ctrl-C exits 130.
``serve`` and ``demo`` with ``--strict`` exit 3 when their timing verdict is
INVALID (``rt_loop.verdict``).
"""

import argparse
import json
import math
import os
import sys

from dct_hil import __version__
from plant import argtypes

TARGET_MEDIAN_US = 2.0   # step-cost target of the real-time loop (0.5 ms step)
MAX_BENCH_STEPS = 100_000_000


class UserError(Exception):
    """Bad command line or environment; reported as one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UserError(message)


def _duration(text):
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0, got {text}")
    return x


_steps = argtypes.whole_number(1, MAX_BENCH_STEPS)
_repeats = argtypes.whole_number(1, 20)


def _check_writable(path, option):
    """Fail early (before a long run) if ``path`` cannot be written; make its folder."""
    full = os.path.abspath(path)
    folder = os.path.dirname(full)
    if os.path.isdir(full):
        raise UserError(f"{option} {path}: is a directory")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        raise UserError(f"{option} {path}: cannot create folder {folder}: {e.strerror}") from None
    if not os.access(folder, os.W_OK | os.X_OK) or (
        os.path.exists(full) and not os.access(full, os.W_OK)
    ):
        raise UserError(f"{option} {path}: not writable")


def build_parser():
    parser = _Parser(
        prog="dct-hil",
        description="Plant server for the VW DSG 02E dual clutch transmission.",
    )
    parser.add_argument("--version", action="version", version=f"dct-hil {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    sim = sub.add_parser("simulate", help="run a scenario offline, as fast as possible")
    sim.add_argument("--scenario", required=True, metavar="NAME_OR_FILE",
                     help="a maneuver (" + ", ".join(MANEUVER_NAMES) + "), a shipped scenario name "
                          "(plant/scenarios) or a CSV file")
    sim.add_argument("--duration", type=_duration, metavar="S",
                     help="simulated seconds (default: the scenario's length; the last row holds)")
    sim.add_argument("--out", metavar="FILE.csv", help="write the outputs every 10 ms to this CSV")
    sim.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    sim.add_argument("--tcu", choices=("stub", "none"), default=None,
                     help="stub: the in-process TCU stub drives clutches and forks (default when "
                          "the scenario scripts neither, and for the maneuvers); none: play the "
                          "scenario's own clutch and fork columns")
    sim.add_argument("--plot", action="store_true",
                     help="write PNG plots next to the CSV (or in out/NAME/ without --out)")
    sim.add_argument("--mapping", metavar="FILE_OR_NAME",
                     help="the TCU stub talks to the plant through this vehicle matrix (a "
                          "mapping file, or a shipped one: dct_hil, vehicle) instead of the "
                          "project's own contract")
    sim.add_argument("--dbc", action="append", default=[], metavar="[BUS=]FILE",
                     help="with --mapping: read this DBC instead of the one the mapping names for "
                          "BUS (without BUS=: the first bus); repeatable")
    sim.add_argument("--tcu-impl", choices=("c", "python"), default=None,
                     help="the TCU stub's loop: c, the reference TCU, driver and CAN contract "
                          "compiled (tcu_stub/fast.py; the default, except with --mapping), or "
                          "python (tcu_stub/logic.py stepped from Python; same results, about 30x "
                          "slower)")
    sim.set_defaults(func=cmd_simulate)

    bench = sub.add_parser("bench", help="measure the cost of one plant step")
    bench.add_argument("--steps", type=_steps, default=200_000, metavar="N",
                       help="steps to time (default 200000)")
    bench.add_argument("--json", default="out/bench.json", metavar="FILE",
                       help="write the figures here (default out/bench.json; the folder is created)")
    bench.add_argument("--scenario", default="launch-1st", metavar="NAME_OR_FILE",
                       help="inputs to play while timing (default launch-1st)")
    bench.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    bench.add_argument("--repeat", type=_repeats, default=1, metavar="K",
                       help="time the run K times (default 1); every run's figures are kept, "
                            "the report and --check take the run with the lowest median "
                            "(the code's cost, with the least interference from the machine)")
    bench.add_argument("--check", action="store_true",
                       help=f"exit 1 if the median step cost is above {TARGET_MEDIAN_US} us")
    bench.set_defaults(func=cmd_bench)

    valve = sub.add_parser("valve", help="clutch valve characteristic and step responses (CSV, PNG)")
    valve.add_argument("--out-dir", default="out/valve", metavar="DIR",
                       help="where to write the files (default out/valve)")
    valve.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    valve.set_defaults(func=cmd_valve)

    serve = sub.add_parser(
        "serve", help="serve the plant to a TCU over CAN in real time (live status, JSON stats)",
        description="Serve the plant to a TCU over CAN: one tick per period in a SCHED_FIFO "
                    "thread (receive, check, step, send). SocketCAN is hard real time; any "
                    "other python-can interface goes through a bridge thread (soft real time). "
                    "Ctrl-C (exit 130) or SIGTERM (exit 0) stop it with everything written. It "
                    "ends with a verdict on its own timing (timing: VALID, or INVALID with the "
                    "findings: overruns, TCU timeouts, lost frames, no TCU). Exit status: 0 done, "
                    "1 the loop, transport or traffic log failed, 2 bad options, 3 timing "
                    "INVALID with --strict, 130 Ctrl-C.")
    serve.add_argument("--channel", default="vcan0", metavar="NAME",
                       help="CAN channel: a network interface for socketcan (can0, vcan0), "
                            "the python-can channel otherwise (default vcan0)")
    serve.add_argument("--interface", metavar="NAME",
                       help="socketcan (hard real time) or any python-can interface, e.g. "
                            "virtual, udp_multicast, pcan, kvaser (bridged, soft real time); "
                            "default: socketcan if the channel is a CAN network interface, "
                            "else virtual")
    serve.add_argument("--rate", type=_serve_rate, default=2000.0, metavar="HZ",
                       help=f"ticks per second, {SERVE_MIN_RATE_HZ:g} to {SERVE_MAX_RATE_HZ:g} "
                            "(default 2000: 0.5 ms)")
    serve.add_argument("--priority", type=_serve_priority, default=80, metavar="1..99",
                       help="SCHED_FIFO priority of the loop, with mlockall (default 80); "
                            "0: normal scheduling, no privileges needed, not real time")
    serve.add_argument("--cpu", type=argtypes.cpu, metavar="N", help="pin the loop to CPU N")
    serve.add_argument("--duration", type=argtypes.seconds, metavar="S",
                       help="stop after S seconds (default: run until Ctrl-C or SIGTERM)")
    serve.add_argument("--stats", default="out/serve-stats.json", metavar="FILE.json",
                       help="statistics written on exit (default out/serve-stats.json)")
    serve.add_argument("--log", metavar="FILE",
                       help="record the CAN traffic, both directions; the suffix picks the "
                            "format: .log (candump), .blf, .asc, .mf4 (needs asammdf), .csv, .trc")
    serve.add_argument("--params", metavar="FILE.toml", help="parameter override file")
    serve.add_argument("--overrun", choices=("skip", "stop"), default="skip",
                       help="on an overrun: count it and skip the missed ticks (default), "
                            "or stop (exit 1)")
    serve.add_argument("--spin-us", type=float, default=None, metavar="US",
                       help="wake this long before each deadline and busy-wait to it, so the "
                            "OS's wake-up latency stays out of the tick; costs that share of a CPU "
                            "(default 300 us, at most 60 %% of the period, with SCHED_FIFO; 0 without)")
    serve.add_argument("--bitrate", type=argtypes.bitrate, metavar="BPS",
                       help="bit rate passed to the python-can bus (bridged interfaces only)")
    serve.add_argument("--time-scale", type=argtypes.time_scale, default=1.0, metavar="X",
                       help="run slower than real time: the same 1/rate plant step every "
                            "1/(rate x X) s of wall time; bus cycles and timeouts stretch by 1/X "
                            "(0 < X <= 1, default 1: real time). For machines too slow for real "
                            "time; the TCU must run at the same scale")
    serve.add_argument("--maneuver", choices=SCRIPTED_MANEUVERS, metavar="NAME",
                       help="the driver inside the loop plays a scripted maneuver ("
                            + ", ".join(SCRIPTED_MANEUVERS) + ") from the first accepted TCU "
                            "frame; the run ends with it")
    serve.add_argument("--record", metavar="FILE.csv|FILE.mf4",
                       help="record every plant output (the columns of dct-hil simulate) in plant "
                            "time: a CSV, or ASAM MDF4 (.mf4) with units, comments and the CAN "
                            "traffic of every bus as bus logging in the same file")
    serve.add_argument("--record-every", type=argtypes.record_interval, default=0.002, metavar="S",
                       help="recording interval in plant time (default 0.002)")
    serve.add_argument("--quiet", action="store_true",
                       help="no live status (the banner, warnings and summary stay)")
    serve.add_argument("--strict", action="store_true",
                       help="exit 3 when the run's timing verdict is INVALID (without it the "
                            "verdict is printed with a warning and the exit status stays)")
    _add_pm_qos_options(serve)
    _add_mapping_options(serve, "the plant")
    serve.add_argument("--xcp", metavar="[HOST:]PORT",
                       help="serve the loop's memory to an XCP master (XCP on Ethernet: measurement "
                            "with DAQ, calibration, the A2L on GET_ID); binds to 127.0.0.1 unless "
                            "HOST is given")
    serve.add_argument("--xcp-tcp", action="store_true", help="XCP on TCP instead of UDP")
    serve.add_argument("--stimulus", metavar="FILE.csv|FILE.mf4",
                       help="play recorded channels (a CSV with time_s, or an MF4 recording) into "
                            "the running loop: plant inputs and the parameters marked online, each "
                            "value at its plant time")
    serve.add_argument("--stimulus-start", choices=("plant", "maneuver"), default="plant",
                       help="stimulus time 0: plant time 0 (default) or the maneuver's start")
    serve.add_argument("--xcp-key", metavar="FILE",
                       help="seed & key: the secret in FILE (at least 16 bytes) locks calibration "
                            "and DAQ until the master unlocks them (HMAC-SHA256 of the seed)")
    _add_control_option(serve)
    serve.add_argument("--faults", metavar="FILE.toml",
                       help="inject the faults of a [[fault]] file (rt_loop.faults: kind, target, "
                            "parameters, start_s / when / duration_s), checked whole before the run")
    _add_ui_options(serve, demo=False)
    serve.set_defaults(func=cmd_serve)

    from tcu_stub import can_tcu

    tcu = sub.add_parser(
        "tcu", help="the reference TCU stub on a CAN bus, against dct-hil serve",
        description="The reference TCU (tcu_stub.logic) as a CAN node: reads only the plant's "
                    "DBC messages, sends TCU_ClutchCmd, TCU_ShiftCmd and TCU_EngineCmd with "
                    "AliveCounter and CRC; or, with --mapping, the messages a vehicle matrix's "
                    "mapping file gives the TCU, one CAN channel per bus (--bus NAME=CHANNEL), "
                    "each frame protected and checked as the mapping says. Ctrl-C or SIGTERM "
                    "send safe values and stop.")
    can_tcu.add_arguments(tcu)
    tcu.set_defaults(func=cmd_tcu)

    demo = sub.add_parser(
        "demo", help="the plant server and the TCU stub over CAN, a maneuver in real time, "
                     "then plots and logs",
        description="Runs the plant server and the TCU stub as two processes on vcan0 when "
                    "vcan0 is up, otherwise on the embedded transport (python-can's in-process "
                    "virtual bus, the TCU in a thread); plays the maneuver with a live status, "
                    "then writes the plots, the recording, the CAN log and the statistics. It "
                    "ends with a verdict on the run's timing (timing: VALID, or INVALID with the "
                    "findings: overruns, TCU timeouts and stale episodes, lost frames, shifts "
                    "unlike the offline run of the same maneuver). Exit status: 0 done, 1 the "
                    "run failed or the maneuver did not complete, 2 bad options, 3 timing "
                    "INVALID with --strict, 130 Ctrl-C.")
    demo.add_argument("--maneuver", choices=SCRIPTED_MANEUVERS, default="paper-cycle",
                      metavar="NAME", help="paper-cycle (default), " + ", ".join(SCRIPTED_MANEUVERS[1:]))
    demo.add_argument("--out", default="out/demo", metavar="DIR",
                      help="where to write everything (default out/demo)")
    demo.add_argument("--channel", metavar="NAME",
                      help="a CAN network interface that is up (default: vcan0 if it is, else "
                           "the embedded transport)")
    demo.add_argument("--interface", metavar="NAME",
                      help="python-can interface (default: socketcan on a CAN network "
                           "interface, else virtual)")
    demo.add_argument("--time-scale", type=argtypes.time_scale, default=1.0, metavar="X",
                      help="slow motion for machines too slow for real time (0 < X <= 1)")
    demo.add_argument("--priority", type=_serve_priority, default=None, metavar="0..99",
                      help="SCHED_FIFO priority of the loop (default 80 as root, else 0)")
    demo.add_argument("--tcu-clock", choices=("wall", "bus"), default=None,
                      help="the TCU stub's task clock: wall (2 ms of wall time, the default in "
                           "real time) or bus (a tick per 2 ms plant frame, the default with "
                           "--time-scale below 1)")
    demo.add_argument("--duration", type=argtypes.seconds, metavar="S",
                      help="play only the first S seconds of the maneuver")
    demo.add_argument("--quiet", action="store_true", help="no live status")
    demo.add_argument("--strict", action="store_true",
                      help="exit 3 when the run's timing verdict is INVALID (without it the "
                           "verdict is printed with a warning and the exit status stays)")
    _add_pm_qos_options(demo)
    _add_mapping_options(demo, "the plant and the TCU stub")
    demo.add_argument("--mf4", action="store_true",
                      help="record plant.mf4 (ASAM MDF4: every plant output with its unit and the "
                           "CAN traffic as bus logging) instead of plant.csv")
    _add_control_option(demo)
    _add_ui_options(demo, demo=True)
    demo.set_defaults(func=cmd_demo)

    doctor = sub.add_parser(
        "doctor", help="how ready this PC is for the real-time loop: findings and fixes",
        description="Checks the kernel's preemption model, RT throttling, CPU isolation, "
                    "frequency governor, idle states, SMT, the CAN interface and its interrupts, "
                    "transparent huge pages, swap, memory locking and SCHED_FIFO rights, then "
                    "measures the machine's wake-up floor with and without PM QoS. Exit 1 when "
                    "an item fails.")
    doctor.add_argument("--cpu", type=argtypes.cpu, metavar="N",
                        help="the CPU the loop will be pinned to (dct-hil serve --cpu)")
    doctor.add_argument("--channel", metavar="NAME",
                        help="the CAN network interface (default: vcan0 if it exists)")
    doctor.add_argument("--priority", type=_serve_priority, default=80, metavar="1..99",
                        help="the loop's SCHED_FIFO priority (default 80)")
    doctor.add_argument("--rate", type=_serve_rate, default=2000.0, metavar="HZ",
                        help="the loop's rate (default 2000)")
    doctor.add_argument("--floor-s", type=argtypes.seconds, default=10.0, metavar="S",
                        help="length of each wake-up floor measurement (default 10)")
    doctor.add_argument("--no-floor", action="store_true", help="skip the floor measurement")
    doctor.add_argument("--json", nargs="?", const="-", metavar="FILE|-",
                        help="write the report as JSON to FILE, or to stdout (-, or no FILE) "
                             "instead of the table")
    doctor.set_defaults(func=cmd_doctor)

    from rt_loop.measure.xcp import a2l as a2l_module

    a2l_cmd = sub.add_parser(
        "a2l", help="write the A2L (ASAP2) file of the loop's memory for an XCP master",
        description="Writes the A2L file (ASAM MCD-2 MC 1.71) of the real-time loop's memory: plant "
                    "inputs, outputs, state and parameters, the statistics, the received values and "
                    "every CAN signal's last value; writable: the inputs a test may override and the "
                    "parameters marked online in plant/data/ranges.toml. dct-hil serve --xcp serves "
                    "the same file on GET_ID. Exit status: 0 written, 1 the C extension is not "
                    "built, 2 bad options.")
    a2l_module.add_arguments(a2l_cmd)
    a2l_cmd.set_defaults(func=cmd_a2l)

    from plant.fmu import build as fmu_module

    fmu_cmd = sub.add_parser(
        "fmu", help="write the plant as a co-simulation FMU (FMI 2.0 or 3.0)",
        description="Builds a co-simulation FMU of the plant from its own C core (compiled with "
                    "the system's C compiler, $CC or cc): modelDescription.xml with every input, "
                    "output, parameter (fixed, or tunable where plant/data/ranges.toml marks it "
                    "online), fault and initial condition; the binary for this platform; sources/ "
                    "to build it elsewhere. Internal step 0.5 ms; communication steps must be "
                    "multiples of it. Exit status: 0 written, 1 not built (the cause on one line), "
                    "2 bad options.")
    fmu_module.add_arguments(fmu_cmd)
    fmu_cmd.set_defaults(func=cmd_fmu)

    mapping = sub.add_parser(
        "mapping", help="vehicle CAN matrices: write, check and show mapping files",
        description="A mapping file (TOML) says what the plant sends and receives on a vehicle's "
                    "DBC (README: Vehicle CAN matrices).")
    msub = mapping.add_subparsers(dest="mapping_command", metavar="ACTION")
    tpl = msub.add_parser("template", help="a commented mapping skeleton for a DBC")
    tpl.add_argument("dbc", metavar="VEHICLE.dbc")
    tpl.add_argument("--tcu-node", action="append", default=[], metavar="NAME",
                     help="a DBC node of the TCU (its messages are received); repeatable")
    tpl.add_argument("--tcu-messages", default="", metavar="A,B,...",
                     help="messages the TCU sends (for a DBC without node names)")
    tpl.add_argument("--plant-node", action="append", default=[], metavar="NAME",
                     help="a DBC node the plant plays (default: the senders of what the TCU receives)")
    tpl.add_argument("--bitrate", type=argtypes.bitrate, metavar="BIT/S",
                     help="the bus's bit rate (default: the DBC's Baudrate)")
    tpl.add_argument("--out", metavar="FILE", help="write it to FILE (default: stdout)")
    for action, text in (("check", "validate a mapping file; a summary with the bus load per bus"),
                         ("show", "what goes where: per bus and message, each signal's source or target")):
        p = msub.add_parser(action, help=text)
        p.add_argument("mapping", metavar="MAPPING.toml",
                       help="a mapping file, or a shipped one by name (dct_hil, vehicle)")
        p.add_argument("--rate", type=_serve_rate, default=2000.0, metavar="HZ",
                       help="the loop's rate: cycle times must be whole ticks (default 2000)")
    mapping.set_defaults(func=cmd_mapping)

    from studies import cli as studies_cli

    sweep = sub.add_parser(
        "sweep", help="run a parameter sweep (grid, random, Latin hypercube) on Dask",
        description="Runs every point of SPEC.toml (plant parameters, TCU calibration values, "
                    "maneuvers or scenarios) on a local Dask cluster or --scheduler; results "
                    "as Parquet and CSV, resumable, plots (README: Sweeps and fits).")
    studies_cli.sweep_arguments(sweep)
    sweep.set_defaults(func=cmd_sweep)

    fit = sub.add_parser(
        "fit", help="identify plant parameters from a recorded run (least squares on Dask)",
        description="Fits the chosen plant parameters to recorded runs (CSV or MF4, a car's "
                    "signals through --mapping) by least squares, the candidate runs on Dask; "
                    "prints the values with 95 %% confidence intervals, writes the residual "
                    "plot (README: Sweeps and fits).")
    studies_cli.fit_arguments(fit)
    fit.set_defaults(func=cmd_fit)
    return parser


def _add_mapping_options(p, what):
    p.add_argument("--mapping", metavar="FILE_OR_NAME",
                   help=f"the CAN matrix {what} plays: a mapping file (DBC per bus, what is sent "
                        "and received, sources and targets) or a shipped one: dct_hil (the "
                        "project's own contract, the default) or vehicle (an example powertrain "
                        "CAN at 500 kbit/s and an I/O bus)")
    p.add_argument("--dbc", action="append", default=[], metavar="[BUS=]FILE",
                   help="read this DBC instead of the one the mapping names for BUS (without "
                        "BUS=: the first bus); repeatable")
    p.add_argument("--bus", action="append", default=[], metavar="NAME=CHANNEL",
                   help="the CAN channel of a bus of the mapping other than the first (which is "
                        "on --channel); repeatable. Default on interfaces other than socketcan: "
                        "CHANNEL-NAME")


def _add_control_option(parser):
    parser.add_argument("--control", metavar="PATH",
                        help="serve the control channel on the Unix socket PATH (mode 0600, "
                             "removed on exit): scripted tests read values, set plant inputs, "
                             "inject faults and wait on conditions (dct_hil.bench.Bench.attach)")


UI_DEFAULT = "127.0.0.1:5006"


def _add_ui_options(parser, demo):
    what = ("the live bench view in the browser: traces, instruments, timing, bus, controls "
            "(README: Live bench view in the browser); binds 127.0.0.1 unless HOST is given, "
            "beyond loopback only with a token")
    if demo:
        parser.add_argument("--ui", nargs="?", const=UI_DEFAULT, metavar="[HOST:]PORT",
                            help=f"serve {what} (default {UI_DEFAULT}); after the maneuver the "
                                 "page stays until Ctrl-C")
    else:
        parser.add_argument("--ui", metavar="[HOST:]PORT", help=f"serve {what}")
    token = parser.add_mutually_exclusive_group()
    token.add_argument("--ui-token", metavar="TOKEN",
                       help="with --ui: the page asks for this token (at least 8 characters; "
                            "needed to bind beyond loopback)")
    token.add_argument("--ui-token-file", metavar="FILE",
                       help="with --ui: the token in the first line of FILE (not on the command "
                            "line, where ps shows it)")


def _ui_settings(args):
    """(host, port, token) of --ui, --ui-token and --ui-token-file, checked
    (the address parsed, the host resolved, a token beyond loopback), or None."""
    from dct_hil.ui.server import (
        UiError,
        check_token,
        is_loopback,
        parse_address,
        read_token_file,
        resolve,
    )

    if args.ui is None:
        if args.ui_token is not None or args.ui_token_file is not None:
            raise UserError("--ui-token and --ui-token-file need --ui")
        return None
    try:
        host, port = parse_address(args.ui)
        token = (check_token(args.ui_token) if args.ui_token is not None else
                 read_token_file(args.ui_token_file) if args.ui_token_file is not None else None)
        if token is None and not is_loopback(host, resolve(host, port)):
            raise UiError(f"UI on {host}:{port}: binding beyond loopback needs --ui-token or "
                          "--ui-token-file")
    except UiError as e:
        raise UserError(str(e)) from None
    return host, port, token


def _start_ui(server, ui, recordings_dir, title):
    """The live view of ``server``, listening (a port in use: UserError, nothing started)."""
    from dct_hil.ui.server import UiError, UiServer

    host, port, token = ui
    try:
        view = UiServer(server, (host, port), token=token, recordings_dir=recordings_dir,
                        title=title)
        view.start()
    except UiError as e:
        raise UserError(str(e)) from None
    return view


def _add_pm_qos_options(parser):
    qos = parser.add_mutually_exclusive_group()
    qos.add_argument("--pm-qos-us", type=argtypes.pm_qos_us, default="auto", metavar="US",
                     help="hold /dev/cpu_dma_latency at US for the run (PM QoS: idle CPUs stay "
                          "in states that wake up within US; default 0 under SCHED_FIFO, as "
                          "cyclictest does, none with --priority 0)")
    qos.add_argument("--no-pm-qos", dest="pm_qos_us", action="store_const", const=None,
                     help="make no PM QoS request (idle CPUs may wake up late)")


# --------------------------------------------------------------------- simulate
MANEUVER_NAMES = ("paper-cycle", "wltc", "nedc", "0-100", "creep", "reverse-park", "hill-start")
SCRIPTED_MANEUVERS = ("paper-cycle", "0-100", "creep", "reverse-park",
                      "hill-start")                 # tables the loop plays itself
RECORD_EVERY_S = 0.01


def _tcu_columns():
    """Scenario columns the stub TCU drives itself: clutches, forks, engine requests."""
    from can_dbc import codec
    from plant.scenario import PRESSURE_COLUMNS

    cols = set(PRESSURE_COLUMNS)
    for targets in codec.TCU_SIGNAL_TARGETS.values():
        cols.update(input_name for _, input_name in targets.values())
    return cols


def _run_with_stub(plant, duration_s, out_path, pedals_fn=None, scenario=None,
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
    from tcu_stub.logic import PERIOD_S, TcuLogic
    from tcu_stub.offline import DRIVER_PERIOD_S, ContractLink

    if tcu_impl == "c":
        return _run_with_stub_c(plant, duration_s, out_path, pedals_fn, scenario, csv_target_gear)
    tcu = TcuLogic()
    link = ContractLink() if link is None else link
    steps_per_tick = max(1, int(round(PERIOD_S / plant.step_s)))
    tick_s = steps_per_tick * plant.step_s
    ticks_per_record = max(1, int(round(RECORD_EVERY_S / tick_s)))
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
    """_run_with_stub's loop in C: the same rows (every plant output and the TCU's
    target gear before its step, every 10 ms, and the end state)."""
    import time

    from plant.model import PlantError
    from plant.simulate import write_csv
    from tcu_stub.fast import FastLoop
    from tcu_stub.logic import PERIOD_S

    steps_per_tick = max(1, int(round(PERIOD_S / plant.step_s)))
    names = list(plant.output_names) + ["tcu_target_gear"]
    n_out = len(plant.output_names)
    n_csv = len(names) if csv_target_gear else n_out
    loop = FastLoop(plant, pedals_fn, duration_s, RECORD_EVERY_S, record_outputs=names[1:n_out],
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
    from plant.maneuvers import format_report, get_maneuver, report
    from plant.model import Plant

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
        names, data, shifts, wall = _guarded_run(plant, args, _run_with_stub, plant, duration,
                                                 args.out, pedals_fn=m.driver, link=link,
                                                 tcu_impl=impl)
    except _Interrupted as e:
        return e.code
    print(f"maneuver          {m.name}  ({m.description})")
    print(f"tcu               stub (in-process, through {through}; {_IMPL_TEXT[impl]})")
    _print_run(plant, float(data[-1, 0]), wall, len(data), args)
    rec = {n: data[:, k] for k, n in enumerate(names)}
    figures = report(m, rec)
    clashes = float(rec["gear_clashes"][-1] - rec["gear_clashes"][0])
    print(f"report            {format_report(m.name, figures)}, gear_clashes = {clashes:.0f}, "
          f"shifts = {len(shifts)}")
    if args.plot:
        _plots(args, names, data, m.name)
    return 0


def cmd_simulate(args):
    from plant.model import Plant
    from plant.scenario import ScenarioError, load_scenario
    from plant.simulate import run

    if args.out:
        _check_writable(args.out, "--out")
    if args.dbc and not args.mapping:
        raise UserError("--dbc goes with --mapping (the project's own contract has its own DBC)")
    if args.scenario in MANEUVER_NAMES:
        return _simulate_maneuver(args)
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as e:
        if str(e).startswith("unknown scenario"):
            raise ScenarioError(f"{e}; maneuvers: {', '.join(MANEUVER_NAMES)}") from None
        raise
    scripted = sorted(set(scenario.columns) & _tcu_columns())
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
                plant, args, _run_with_stub, plant, duration, args.out, scenario=scenario,
                csv_target_gear=False, link=link, tcu_impl=impl)
        except _Interrupted as e:
            return e.code
        print(f"scenario          {scenario.name}  ({scenario.path})")
        print(f"tcu               stub (in-process, through {through}; {_IMPL_TEXT[impl]}): "
              "clutches and forks")
        _print_run(plant, float(data[-1, 0]), wall, len(data), args)
        if args.plot:
            _plots(args, names, data, scenario.name)
        return 0

    try:
        res = _guarded_run(plant, args, run, plant, scenario, duration_s=args.duration,
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


# ------------------------------------------------------------------------ bench
def bench_figures(step_ns, step_s):
    """Summary of per-step costs (ns) in microseconds."""
    import numpy as np

    us = np.asarray(step_ns) / 1e3
    mean = float(us.mean())
    return {
        "median_us": float(np.median(us)),
        "p90_us": float(np.percentile(us, 90)),
        "p99_us": float(np.percentile(us, 99)),
        "p99_9_us": float(np.percentile(us, 99.9)),
        "max_us": float(us.max()),
        "mean_us": mean,
        "real_time_factor": step_s * 1e6 / mean if mean > 0 else math.inf,
        "steps_per_s": 1e6 / mean if mean > 0 else math.inf,
    }


def cmd_bench(args):
    from plant.machine import machine_info
    from plant.model import Plant
    from plant.scenario import load_scenario
    from plant.simulate import bench

    _check_writable(args.json, "--json")
    scenario = load_scenario(args.scenario)
    runs = []
    for _ in range(args.repeat):
        plant = Plant(args.params, scenario.param_overrides())
        runs.append(bench_figures(bench(plant, scenario, args.steps), plant.step_s))
    best = min(range(len(runs)), key=lambda k: runs[k]["median_us"])
    fig = runs[best]
    report = {
        "steps": args.steps,
        "scenario": scenario.name,
        "step_s": plant.step_s,
        **fig,
        "repeat": args.repeat,
        "best_run": best + 1,
        "runs": runs,
        "target_median_us": TARGET_MEDIAN_US,
        "machine": machine_info(build=True),
    }
    with open(args.json, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=2)
        f.write("\n")

    print(f"bench             {scenario.name}, {args.steps} steps of {plant.step_s * 1e3:g} ms")
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
        if fig["median_us"] > TARGET_MEDIAN_US:
            print(
                f"dct-hil: bench check failed: median step cost {fig['median_us']:.3f} us "
                f"is above the {TARGET_MEDIAN_US} us target",
                file=sys.stderr,
            )
            return 1
        print(f"check             passed (median <= {TARGET_MEDIAN_US} us)")
    return 0


# ------------------------------------------------------------------------ valve
VALVE_STEPS = ((0.0, 0.6), (0.6, 0.0), (0.3, 0.7), (0.7, 0.3), (0.0, 1.0))


def cmd_valve(args):
    import numpy as np

    from plant.model import Plant
    from plant.valve_report import steady_state_curve, step_response

    os.makedirs(args.out_dir, exist_ok=True)
    _check_writable(os.path.join(args.out_dir, "valve_curve.csv"), "--out-dir")
    plant = Plant(args.params, {"hydraulics": {"pressure_commanded": 0}})
    currents, up, down, line = steady_state_curve(plant)
    curve_csv = os.path.join(args.out_dir, "valve_curve.csv")
    np.savetxt(curve_csv, np.column_stack([currents, up, down]), fmt="%.6g", delimiter=",",
               header="solenoid_current_a,pressure_rising_bar,pressure_falling_bar", comments="")
    steps = [step_response(a, b, params_path=args.params,
                           overrides={"hydraulics": {"pressure_commanded": 0}}) for a, b in VALVE_STEPS]
    step_csv = os.path.join(args.out_dir, "valve_steps.csv")
    cols, names = [steps[0].time_s], ["time_s"]
    for (a, b), r in zip(VALVE_STEPS, steps):
        tag = f"{a:g}_to_{b:g}a"
        cols += [r.pressure_bar, r.piston_mm]
        names += [f"pressure_{tag}_bar", f"piston_{tag}_mm"]
    np.savetxt(step_csv, np.column_stack(cols), fmt="%.6g", delimiter=",", header=",".join(names),
               comments="")
    png = _valve_plots(args.out_dir, currents, up, down, line, steps)

    print(f"line pressure     {line:.2f} bar")
    print(f"pressure at 0 A   {up[0]:.3f} bar; at {currents[-1]:g} A {up[-1]:.2f} bar")
    hyst = float(np.max(np.abs(up - down)))
    print(f"hysteresis        {hyst:.3f} bar (largest rising/falling difference)")
    for (a, b), r in zip(VALVE_STEPS, steps):
        print(f"step {a:g} -> {b:g} A   {r.start_bar:5.2f} -> {r.final_bar:5.2f} bar, "
              f"90 % in {r.time_to(0.9) * 1e3:5.1f} ms, overshoot {r.overshoot * 100:.2f} %")
    print(f"csv               {curve_csv}, {step_csv}")
    print(f"png               {', '.join(png)}")
    return 0


def _valve_plots(out_dir, currents, up, down, line, steps):
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


# ------------------------------------------------------------------------ serve
SERVE_MIN_RATE_HZ = 100.0      # the loop's periods: 10 ms .. 50 us
SERVE_MAX_RATE_HZ = 20_000.0


def _serve_rate(text):
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(x) and SERVE_MIN_RATE_HZ <= x <= SERVE_MAX_RATE_HZ):
        raise argparse.ArgumentTypeError(
            f"must be {SERVE_MIN_RATE_HZ:g} to {SERVE_MAX_RATE_HZ:g} Hz (a period of 10 ms to "
            f"50 us), got {text}")
    return x


def _serve_priority(text):
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 <= n <= 99:
        raise argparse.ArgumentTypeError(
            f"must be a SCHED_FIFO priority 1..99 (or 0: normal scheduling), got {text}")
    return n







def _mapping_from_args(args, rate_hz):
    """(Mapping, {bus: channel}) of --mapping, --dbc and --bus; (None, {...}) when
    neither --mapping nor --dbc is given: the project's own contract, served and
    spoken as it always is."""
    from can_dbc.mapping import MappingError, load_options, parse_pairs

    try:
        buses = parse_pairs(args.bus, "--bus", "NAME=CHANNEL")
        if args.mapping is None and not args.dbc:
            return None, buses
        return load_options(args.mapping, args.dbc, rate_hz=rate_hz), buses
    except MappingError as e:
        raise UserError(str(e)) from None


def cmd_serve(args):
    from rt_loop.console import run_console
    from rt_loop.server import Server, ServerError
    from rt_loop.transport import TransportError, check_interface

    mapping, bus_channels = _mapping_from_args(args, args.rate)
    ui = _ui_settings(args)
    try:
        if args.interface is not None:
            check_interface(args.interface)
        _check_writable(args.stats, "--stats")
        if args.log:
            _check_writable(args.log, "--log")
        if args.record:
            _check_writable(args.record, "--record")
        driver = end = fixed = None
        if args.maneuver:
            from plant.maneuvers import get_maneuver

            m = get_maneuver(args.maneuver)
            driver, end, fixed = m.driver, m.duration_s, m.inputs
        server = Server(
            args.channel, interface=args.interface, rate_hz=args.rate, priority=args.priority,
            cpu=args.cpu, duration_s=args.duration, params_path=args.params, log_path=args.log,
            overrun_policy=args.overrun,
            bus_kwargs={"bitrate": args.bitrate} if args.bitrate else None,
            spin_us=args.spin_us, time_scale=args.time_scale, driver=driver,
            maneuver_end_s=end, record_path=args.record, record_every_s=args.record_every,
            pm_qos_us=args.pm_qos_us, mapping=mapping, bus_channels=bus_channels,
            xcp=args.xcp, xcp_protocol="tcp" if args.xcp_tcp else "udp", xcp_key=args.xcp_key,
            stimulus_path=args.stimulus, stimulus_start=args.stimulus_start,
            faults_path=args.faults, control_path=args.control, maneuver_inputs=fixed,
        )
        if ui is not None:
            recordings = os.path.join(os.path.dirname(os.path.abspath(args.stats)), "recordings")
            view = _start_ui(server, ui, recordings, "dct-hil bench")
            view.stop_before(server)        # Ctrl-C, SIGTERM, the end: the page goes first
            print(f"live view         {view.url}"
                  + (" (asks for the token)" if view.token else "")
                  + f"; recordings from the page in {recordings}", flush=True)
        return run_console(server, args.stats, quiet=args.quiet, strict=args.strict)
    except (ServerError, TransportError) as e:
        raise UserError(str(e)) from None


# -------------------------------------------------------------------- tcu, demo
def cmd_tcu(args):
    from tcu_stub import can_tcu

    return can_tcu.run(args)


def cmd_demo(args):
    from dct_hil.demo import DemoError, run_demo
    from rt_loop.server import ServerError
    from rt_loop.transport import TransportError

    _check_writable(os.path.join(args.out, "summary.json"), "--out")
    mapping, bus_channels = _mapping_from_args(args, 2000.0)
    ui = _ui_settings(args)
    try:
        return run_demo(args.maneuver, args.out, channel=args.channel, interface=args.interface,
                        time_scale=args.time_scale, priority=args.priority, quiet=args.quiet,
                        duration_s=args.duration, tcu_clock=args.tcu_clock,
                        pm_qos_us=args.pm_qos_us, strict=args.strict, mapping=mapping,
                        bus_channels=bus_channels, mf4=args.mf4, control_path=args.control,
                        ui=ui)
    except (DemoError, ServerError, TransportError) as e:
        raise UserError(str(e)) from None


def cmd_fmu(args):
    from plant.fmu import build

    return build.run(args)


def cmd_a2l(args):
    from rt_loop.measure.xcp import a2l

    return a2l.run(args)


def cmd_doctor(args):
    from rt_loop.tools.doctor import DoctorError, run_doctor

    to_file = args.json not in (None, "-")
    if to_file:
        _check_writable(args.json, "--json")
    try:
        report = run_doctor(cpu=args.cpu, channel=args.channel, priority=args.priority,
                            rate_hz=args.rate, floor_s=args.floor_s, floor=not args.no_floor,
                            progress=lambda line: print(f"dct-hil doctor: {line}",
                                                        file=sys.stderr, flush=True))
    except DoctorError as e:
        raise UserError(str(e)) from None
    if args.json == "-":
        sys.stdout.write(report.json_text())
        return report.exit_code
    sys.stdout.write(report.text())
    if to_file:
        with open(args.json, "w", encoding="utf-8") as f:
            f.write(report.json_text())
        print(f"json: {args.json}")
    return report.exit_code


def cmd_sweep(args):
    from studies import StudyError
    from studies import cli as studies_cli

    try:
        return studies_cli.sweep(args)
    except StudyError as e:
        raise UserError(str(e)) from None


def cmd_fit(args):
    from studies import StudyError
    from studies import cli as studies_cli

    try:
        return studies_cli.fit(args)
    except StudyError as e:
        raise UserError(str(e)) from None


# ---------------------------------------------------------------------- mapping
def cmd_mapping(args):
    from can_dbc import mapping

    if args.mapping_command is None:
        raise UserError("choose an action: dct-hil mapping template, check or show")
    try:
        if args.mapping_command == "template":
            if args.out:
                _check_writable(args.out, "--out")
            text = mapping.template(
                args.dbc, tcu_nodes=args.tcu_node, plant_nodes=args.plant_node,
                tcu_messages=[n.strip() for n in args.tcu_messages.split(",") if n.strip()],
                bitrate=args.bitrate, out_path=args.out)
            if not args.out:
                sys.stdout.write(text)
                return 0
            with open(args.out, "w", encoding="utf-8") as f:
                f.write(text)
            print(f"template: {args.out}")
            return 0
        m = mapping.load(mapping.find_mapping(args.mapping), rate_hz=args.rate)
    except mapping.MappingError as e:
        raise UserError(str(e)) from None
    sys.stdout.write(mapping.check_report(m) if args.mapping_command == "check" else mapping.show(m))
    return 0


# ------------------------------------------------------------------------- main
def _one_line(text):
    return " ".join(str(text).split())


def _user_errors():
    """Exception types that mean 'the user gave something unusable'."""
    from plant.model import PlantError
    from plant.params import ParamError
    from plant.scenario import ScenarioError

    return (UserError, ParamError, ScenarioError, PlantError, OSError)


def main(argv=None):
    def fail(message):
        print(f"dct-hil: error: {_one_line(message)}", file=sys.stderr)
        return 2

    try:
        parser = build_parser()     # a Ctrl-C this early is one line too
        args = parser.parse_args(argv)
        if args.command is None:
            raise UserError("choose a command: demo, simulate, serve, tcu, bench, valve, doctor, "
                            "mapping or a2l (dct-hil --help)")
        try:
            user_errors = _user_errors()
        except ImportError as e:
            return fail(f"the plant package is not built or incomplete ({e}); run scripts/setup")
        try:
            return args.func(args)
        except user_errors as e:
            if isinstance(e, OSError) and e.filename is not None:
                return fail(f"{e.filename}: {e.strerror or e}")
            return fail(e)
    except UserError as e:
        return fail(e)
    except KeyboardInterrupt:
        print("dct-hil: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
