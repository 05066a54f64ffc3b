"""cffi builder of the real-time loop (build time only; never imported at run time).

setup.py names it in ``cffi_modules``; ``scripts/setup`` (or any ``pip
install``) compiles ``rt_loop/_rt_loop*.so``: the loop itself, the
table-driven CAN codec and the plant core, in one extension, so the whole
tick runs in C without crossing into Python. The cdef is the public headers
themselves (dct_plant.h, can_table.h, rt_loop.h, rt_floor.h), read the same way as
plant/_build.py reads dct_plant.h: every preprocessor line dropped except
``#define NAME <integer>``.
"""

import glob
import importlib.util
import os

from cffi import FFI

_HERE = os.path.dirname(os.path.abspath(__file__))
_ROOT = os.path.dirname(_HERE)
_PLANT_CSRC = os.path.join(_ROOT, "plant", "csrc")
_CAN_CSRC = os.path.join(_ROOT, "can_dbc", "csrc")
_RT_CSRC = os.path.join(_HERE, "csrc")
# in dependency order: each header's types are declared before their use
_HEADERS = (
    os.path.join(_PLANT_CSRC, "dct_plant.h"),
    os.path.join(_CAN_CSRC, "can_table.h"),
    os.path.join(_RT_CSRC, "rt_loop.h"),
    os.path.join(_RT_CSRC, "rt_floor.h"),
)
_COMPILE_ARGS = ["-O2", "-std=c11", "-fno-math-errno", "-Wall", "-Wextra"]


def _plant_build():
    # plant/_build.py is not importable as a package module at build time
    # (setuptools runs this file by path), so load it by path too.
    path = os.path.join(_ROOT, "plant", "_build.py")
    spec = importlib.util.spec_from_file_location("_dct_plant_build", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_cdef_text = _plant_build().cdef_text


def _rel(path):
    # setuptools wants sources relative to the project root (the cwd when pip
    # builds); absolute paths when the builder is loaded from elsewhere.
    rel = os.path.relpath(path)
    return path if rel.startswith(os.pardir) else rel


def _sources():
    plant = [p for p in sorted(glob.glob(os.path.join(_PLANT_CSRC, "*.c")))
             if os.path.basename(p) != "dct_bench.c"]   # the only file that reads a clock
    can = sorted(glob.glob(os.path.join(_CAN_CSRC, "*.c")))
    loop = sorted(glob.glob(os.path.join(_RT_CSRC, "*.c")))
    return [_rel(p) for p in plant + can + loop]


def make_builder():
    ffi = FFI()
    ffi.cdef("\n".join(_cdef_text(h) for h in _HEADERS))
    ffi.set_source(
        "rt_loop._rt_loop",
        '#include "rt_loop.h"\n#include "rt_floor.h"\n#include "can_table.h"',
        sources=_sources(),
        include_dirs=[_rel(d) for d in (_RT_CSRC, _CAN_CSRC, _PLANT_CSRC)],
        extra_compile_args=_COMPILE_ARGS,
        define_macros=[("_GNU_SOURCE", None)],   # recvmmsg, sendmmsg, CPU_SET
        libraries=["m", "pthread"],
    )
    return ffi


ffibuilder = make_builder()
