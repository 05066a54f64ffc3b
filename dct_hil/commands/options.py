"""What several dct-hil commands share: the one-line user error, the early
check that an output can be written, and the option groups of the CAN matrix
(--mapping, --dbc, --bus), the control channel, the bench view in the browser
and PM QoS."""

import os

from can_dbc.options import add_matrix_options
from plant import argtypes
from plant.extras import require


class UserError(Exception):
    """Bad command line or environment; reported as one line, exit 2."""


def check_writable(path, option):
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


def run_study(name, args):
    """``dct_hil.studies.cli``'s ``sweep`` or ``fit`` (the studies extra checked first)."""
    require("dask", "distributed", "pandas", "pyarrow", "scipy", "matplotlib")
    from dct_hil.studies import StudyError, cli

    try:
        return getattr(cli, name)(args)
    except StudyError as e:
        raise UserError(str(e)) from None


def loop_rate():
    """The option type of the loop's rate (--rate): the server's limits."""
    from rt_loop.server import MAX_RATE_HZ, MIN_RATE_HZ

    return argtypes.loop_rate(MIN_RATE_HZ, MAX_RATE_HZ)


def add_mapping_options(p, what):
    add_matrix_options(
        p, mapping_help=f"the CAN matrix {what} plays: a mapping file (DBC per bus, what is "
                        "sent and received, sources and targets) or a shipped one: dct_hil (the "
                        "project's own contract, the default) or vehicle (an example powertrain "
                        "CAN at 500 kbit/s and an I/O bus)",
        bus_help="the CAN channel of a bus of the mapping other than the first (which is on "
                 "--channel); repeatable. Default on interfaces other than socketcan: "
                 "CHANNEL-NAME")


def add_strict_option(parser):
    parser.add_argument("--strict", action="store_true",
                        help="exit 3 when the run's timing verdict is INVALID (without it the "
                             "verdict is printed with a warning and the exit status stays)")


def add_control_option(parser, tcp=False):
    parser.add_argument("--control", metavar="PATH",
                        help="serve the control channel on the Unix socket PATH (mode 0600, "
                             "removed on exit): scripted tests read values, set plant inputs, "
                             "inject faults and wait on conditions (dct_hil.bench.Bench.attach)")
    if not tcp:
        return
    parser.add_argument("--control-tcp", metavar="[HOST:]PORT",
                        help="serve the control channel over TCP too, for tests on another "
                             "machine (Bench.attach(\"tcp://HOST:PORT\"), pytest --bench-url); "
                             "binds 127.0.0.1 unless HOST is given, beyond loopback only with "
                             "--control-token-file")
    parser.add_argument("--control-token-file", metavar="FILE",
                        help="with --control-tcp: a client first says hello with the token in "
                             "the first line of FILE (at least 8 characters); a wrong one is "
                             "refused, counted and logged")
    parser.add_argument("--control-tls-cert", metavar="PEM",
                        help="with --control-tcp: speak TLS with this certificate (chain); the "
                             "clients connect to tls://HOST:PORT")
    parser.add_argument("--control-tls-key", metavar="PEM",
                        help="the certificate's private key (default: in the certificate's file)")


def control_settings(args):
    """The Server keywords of --control, --control-tcp, --control-token-file and
    --control-tls-cert/-key, checked (the address parsed, the token read, the
    certificate loaded, a token beyond loopback)."""
    from rt_loop import access

    out = {"control_path": args.control}
    tcp = getattr(args, "control_tcp", None)
    token_file = getattr(args, "control_token_file", None)
    cert = getattr(args, "control_tls_cert", None)
    key = getattr(args, "control_tls_key", None)
    if tcp is None:
        given = [o for o, v in (("--control-token-file", token_file), ("--control-tls-cert", cert),
                                ("--control-tls-key", key)) if v is not None]
        if given:
            raise UserError(f"{', '.join(given)} need --control-tcp")
        return out
    if key is not None and cert is None:
        raise UserError("--control-tls-key needs --control-tls-cert")
    try:
        host, port = access.parse_address(tcp, "--control-tcp")
        token = None if token_file is None else access.read_token_file(token_file,
                                                                       "--control-token-file")
        if token is None and not access.is_loopback(host, access.resolve(host, port,
                                                                         "--control-tcp")):
            raise access.AccessError(f"--control-tcp {host}:{port}: beyond loopback only with "
                                     "--control-token-file")
        tls = None if cert is None else access.server_tls_context(cert, key, "--control-tls-cert")
    except access.AccessError as e:
        raise UserError(str(e)) from None
    out.update(control_tcp=(host, port), control_token=token, control_tls=tls)
    return out


UI_DEFAULT = "127.0.0.1:5006"


def add_ui_options(parser, demo):
    what = ("the live bench view in the browser: traces, instruments, timing, bus, controls "
            "(the manual: docs/bench-view.md); binds 127.0.0.1 unless HOST is given, "
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


def ui_settings(args):
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
    require("bokeh", "tornado")
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


def start_ui(server, ui, recordings_dir, title):
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


def add_pm_qos_options(parser):
    qos = parser.add_mutually_exclusive_group()
    qos.add_argument("--pm-qos-us", type=argtypes.pm_qos_us, default="auto", metavar="US",
                     help="hold /dev/cpu_dma_latency at US for the run (PM QoS: idle CPUs stay "
                          "in states that wake up within US; default 0 under SCHED_FIFO, as "
                          "cyclictest does, none with --priority 0)")
    qos.add_argument("--no-pm-qos", dest="pm_qos_us", action="store_const", const=None,
                     help="make no PM QoS request (idle CPUs may wake up late)")


def mapping_from_args(args, rate_hz):
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
