"""cffi builder for the C core (build time only; never imported at run time).

setup.py names it in ``cffi_modules``; ``scripts/setup`` (or any ``pip
install``) runs it and compiles plant/_dct_plant*.so. The cdef is the public
headers themselves, so the C contract is written once: every preprocessor
line is dropped except ``#define NAME <integer>``, which cffi turns into
constants.
"""

import glob
import os
import re

from cffi import FFI

_HERE = os.path.dirname(os.path.abspath(__file__))
_CSRC = os.path.join(_HERE, "csrc")
_HEADERS = ("dct_plant.h", "dct_bench.h")
# -flto: the components' small functions (piston, chamber, friction laws) are
# inlined into the assembly across files; the link repeats -O3 for that. No
# option here changes a floating-point result (no -ffast-math, no FMA
# contraction on the x86-64 baseline): validation/pyplant.py stays equal.
COMPILE_ARGS = ["-O3", "-std=c11", "-fno-math-errno", "-Wall", "-Wextra", "-flto=auto"]
LINK_ARGS = ["-O3", "-flto=auto"]

#: DCT_HIL_SANITIZE=thread|address builds every extension (this builder's options
#: serve all four) with ThreadSanitizer, or AddressSanitizer + UndefinedBehaviorSanitizer
#: (with float-cast-overflow: a physical value out of a raw field's range is UB in C), at
#: -O1 with frames and no LTO, for readable reports. Only scripts/sanitize sets it, building
#: into build/sanitize-<kind>/: never the working tree's extensions (such a build needs the
#: sanitizer's runtime preloaded into Python, rt_loop/tools/sanitize_run.py).
SANITIZERS = {"thread": "thread", "address": "address,undefined,float-cast-overflow"}
SANITIZE = os.environ.get("DCT_HIL_SANITIZE", "")
if SANITIZE:
    if SANITIZE not in SANITIZERS:
        raise SystemExit(f"DCT_HIL_SANITIZE must be one of {', '.join(SANITIZERS)}, "
                         f"got {SANITIZE!r}")
    # -fsanitize-recover=address: ASan may go on after a report (ASAN_OPTIONS=halt_on_error=0)
    _san = ["-O1", "-g", "-fno-omit-frame-pointer", f"-fsanitize={SANITIZERS[SANITIZE]}"] + (
        ["-fsanitize-recover=address"] if SANITIZE == "address" else [])
    COMPILE_ARGS = [a for a in COMPILE_ARGS if a not in ("-O3", "-flto=auto")] + _san
    LINK_ARGS = [f"-fsanitize={SANITIZERS[SANITIZE]}"]

_INT_DEFINE = re.compile(
    r"^\s*#\s*define\s+[A-Za-z_]\w*\s+-?(0[xX][0-9a-fA-F]+|\d+)[uUlL]*\s*(/\*.*\*/)?\s*$"
)


def cdef_text(path):
    """The header at ``path`` with every ``#`` line dropped except integer #defines."""
    kept = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.lstrip().startswith("#") and not _INT_DEFINE.match(line):
                continue
            kept.append(line)
    return "".join(kept)


def rel(path):
    """``path`` as setuptools wants a source: relative to the project root (the
    cwd when pip builds); absolute when the builder is loaded from elsewhere.
    The builders of the extensions above (can_dbc, rt_loop, tcu_stub) use this
    and ``cdef_text``, ``COMPILE_ARGS``, ``LINK_ARGS`` from here."""
    relative = os.path.relpath(path)
    return path if relative.startswith(os.pardir) else relative


def make_builder():
    ffi = FFI()
    ffi.cdef("\n".join(cdef_text(os.path.join(_CSRC, h)) for h in _HEADERS))
    ffi.set_source(
        "plant._dct_plant",
        '#include "dct_plant.h"\n#include "dct_bench.h"',
        sources=[rel(p) for p in sorted(glob.glob(os.path.join(_CSRC, "*.c")))],
        include_dirs=[rel(_CSRC)],
        extra_compile_args=COMPILE_ARGS,
        # recorded by dct_bench_build_info() for the benchmark report
        define_macros=[("DCT_CFLAGS", '"' + " ".join(COMPILE_ARGS) + '"')],
        libraries=["m"],
        extra_link_args=LINK_ARGS,
    )
    return ffi


ffibuilder = make_builder()
