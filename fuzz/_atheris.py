"""What the atheris targets share: running one under libFuzzer's flags, the
checkout on sys.path, one-line error checks, a scratch folder."""

from __future__ import annotations

import os
import shlex
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for p in (ROOT, os.path.join(ROOT, "tests")):
    if p not in sys.path:
        sys.path.insert(0, p)


class Finding(BaseException):
    """Raised by a target for behaviour that is wrong without an exception of
    its own (a message of several lines, an answer the protocol forbids);
    a BaseException, so no ``except Exception`` of the code under test hides it."""


def one_line(e: BaseException) -> None:
    """The loader's error must be one line naming the cause."""
    text = str(e)
    if not text.strip() or "\n" in text:
        raise Finding(f"{type(e).__name__} is not one line: {text!r}")


def scratch(name: str) -> str:
    """A folder of this process for the files a target writes."""
    d = os.path.join(tempfile.gettempdir(), f"dct-fuzz-{name}-{os.getpid()}")
    os.makedirs(d, exist_ok=True)
    return d


def run(test_one_input, instrument, after=None) -> None:
    """atheris with this interpreter's argv (libFuzzer flags, corpus folders):
    ``instrument`` imports the code under test (its bytecode instrumented),
    ``after`` what only drives it (test fakes, a server), not instrumented."""
    import atheris
    with atheris.instrument_imports():
        instrument()
    if after is not None:
        after()
    # libFuzzer runs argv[0] again as a shell command for -merge=1 (and -fork):
    # this interpreter and the target, quoted, not the script alone
    argv = [f"{shlex.quote(sys.executable)} {shlex.quote(os.path.abspath(sys.argv[0]))}",
            *sys.argv[1:]]
    atheris.Setup(argv, test_one_input)
    atheris.Fuzz()
