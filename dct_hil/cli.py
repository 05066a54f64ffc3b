"""dct-hil command line: the parser assembled from the subcommands'
modules (``dct_hil.commands``, one per command), and ``main``.

    dct-hil simulate --scenario launch-1st --out out/launch-1st.csv
    dct-hil bench --steps 200000 --check          # figures in out/bench.json

User errors (bad options, parameter files, scenarios, a plant that blows up)
print one line ``dct-hil: error: <cause>`` and exit 2; Ctrl-C exits 130.
``serve`` and ``demo`` with ``--strict`` exit 3 when their timing verdict is
INVALID (``rt_loop.verdict``).
"""

import argparse
import importlib
import os
import sys

from dct_hil import __version__
from dct_hil.commands import COMMANDS
from dct_hil.commands.options import UserError
from plant.extras import install_hint, missing_extra

#: commands whose process runs the real-time loop, which locks all its memory (mlockall)
LOOP_COMMANDS = ("serve", "demo")


def _single_threaded_blas(argv):
    """For a command that runs the loop: NumPy's OpenBLAS with one thread.

    OpenBLAS starts a thread per CPU when NumPy is imported, each with an 8 MB stack and
    a 32 MB buffer; under mlockall every page of them is resident (40 MB a CPU beyond
    the first, docs/server.md "Memory"), for linear algebra these commands never do.
    The variables must be set before NumPy is first imported (building the parser
    imports it); a value the user set is kept."""
    if "numpy" in sys.modules:
        return
    args = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in args if not a.startswith("-")), None)
    if command in LOOP_COMMANDS:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
            os.environ.setdefault(var, "1")


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UserError(message)


def _stacks_on_sigusr1():
    """``kill -USR1 <pid>`` prints every thread's Python stack to stderr: a process
    that hangs says where (the process goes on)."""
    import faulthandler
    import signal

    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (AttributeError, OSError, RuntimeError, ValueError):   # no stderr file (embedded)
        pass


def build_parser():
    """The whole command line: every subcommand of ``dct_hil.commands``."""
    parser = _Parser(
        prog="dct-hil",
        description="Plant server for the VW DSG 02E dual clutch transmission.",
    )
    parser.add_argument("--version", action="version", version=f"dct-hil {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"dct_hil.commands.{name}").add_parser(sub)
    return parser


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

    _single_threaded_blas(argv)
    _stacks_on_sigusr1()
    try:
        parser = build_parser()     # a Ctrl-C this early is one line too
        args = parser.parse_args(argv)
        if args.command is None:
            raise UserError(f"choose a command: {', '.join(COMMANDS)} (dct-hil --help)")
        try:
            user_errors = _user_errors()
        except ImportError as e:
            return fail(f"the plant package is not built or incomplete ({e}); run scripts/setup")
        try:
            return args.func(args)
        except ImportError as e:
            extra = missing_extra(e)
            if extra is None:
                raise
            return fail(f"dct-hil {args.command} needs the {extra} extra ({e.name} is not "
                        f"installed): {install_hint(extra)}")
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
