"""cffi builder of the real-time loop (build time only; never imported at run time).

setup.py names it in ``cffi_modules``; ``scripts/setup`` (or any ``pip
install``) compiles ``rt_loop/_rt_loop*.so``: the loop itself with the
table-driven CAN codec and the plant core compiled in, so the whole tick
runs in C without crossing into Python. The codec's types come from
``can_dbc._can_table`` (``ffi.include``): a ``can_dbc.table.CodecTable`` is
passed to the loop as it is. The cdef is the loop's public headers
(dct_plant.h, rt_loop.h, rt_floor.h, and rt_xcp_send.h: the XCP sender
thread), read the same way as plant/_build.py reads dct_plant.h: every
preprocessor line dropped except ``#define NAME <integer>``. The sources are every ``csrc/*.c`` (the loop one component a
file, listed in ``csrc/rt_internal.h``); the private headers (rt_internal.h,
rt_faults.h, rt_scope.h) are never read by the cdef.
"""

import glob
import os
import runpy
from types import SimpleNamespace

from cffi import FFI

_HERE = os.path.dirname(os.path.abspath(__file__))
_ROOT = os.path.dirname(_HERE)
_PLANT_CSRC = os.path.join(_ROOT, "plant", "csrc")
_CAN_CSRC = os.path.join(_ROOT, "can_dbc", "csrc")
_RT_CSRC = os.path.join(_HERE, "csrc")
# in dependency order: each header's types are declared before their use
_HEADERS = (
    os.path.join(_PLANT_CSRC, "dct_plant.h"),
    os.path.join(_RT_CSRC, "rt_loop.h"),
    os.path.join(_RT_CSRC, "rt_floor.h"),
    os.path.join(_RT_CSRC, "rt_xcp_send.h"),
)

# loaded by path: setuptools runs build files by path, not as package modules
_can = SimpleNamespace(**runpy.run_path(os.path.join(_ROOT, "can_dbc", "_build.py")))


def _sources():
    plant = [p for p in sorted(glob.glob(os.path.join(_PLANT_CSRC, "*.c")))
             if os.path.basename(p) != "dct_bench.c"]   # the only file that reads a clock
    loop = sorted(glob.glob(os.path.join(_RT_CSRC, "*.c")))
    return [_can.rel(p) for p in [*plant, _can.SOURCE, *loop]]


def make_builder():
    ffi = FFI()
    ffi.include(_can.ffibuilder)
    ffi.cdef("\n".join(_can.cdef_text(h) for h in _HEADERS))
    ffi.set_source(
        "rt_loop._rt_loop",
        '#include "rt_loop.h"\n#include "rt_floor.h"\n#include "rt_xcp_send.h"\n#include "can_table.h"',
        sources=_sources(),
        include_dirs=[_can.rel(d) for d in (_RT_CSRC, _CAN_CSRC, _PLANT_CSRC)],
        extra_compile_args=_can.COMPILE_ARGS,
        extra_link_args=_can.LINK_ARGS,
        define_macros=[("_GNU_SOURCE", None)],   # recvmmsg, sendmmsg, CPU_SET
        libraries=["m", "pthread"],
    )
    return ffi


ffibuilder = make_builder()
