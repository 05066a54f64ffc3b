"""cffi builder of the table codec (build time only; never imported at run time).

setup.py names it in ``cffi_modules``; ``scripts/setup`` (or any ``pip
install``) compiles ``can_dbc/_can_table*.so``: ``can_dbc/csrc/can_table.c``,
the codec ``can_dbc.table.CodecTable`` drives from Python. The extensions
above it (``rt_loop._rt_loop``, ``tcu_stub._tcu_fast``) compile the same
source into themselves, so that their C calls the codec directly, and
``include`` this builder: a table made here is of their own types, passed to
their functions as it is. The cdef is the public header, read as
plant/_build.py reads dct_plant.h.
"""

import os
import runpy
from types import SimpleNamespace

from cffi import FFI

_HERE = os.path.dirname(os.path.abspath(__file__))
_ROOT = os.path.dirname(_HERE)
_CSRC = os.path.join(_HERE, "csrc")

# loaded by path: setuptools runs build files by path, not as package modules
_plant = SimpleNamespace(**runpy.run_path(os.path.join(_ROOT, "plant", "_build.py")))
# the plant builder's helpers, for this builder and the ones that load it
cdef_text, rel, COMPILE_ARGS, LINK_ARGS = _plant.cdef_text, _plant.rel, _plant.COMPILE_ARGS, _plant.LINK_ARGS
#: the codec's C source and header, for the extensions that compile it in
SOURCE = os.path.join(_CSRC, "can_table.c")
HEADER = os.path.join(_CSRC, "can_table.h")


def make_builder():
    ffi = FFI()
    ffi.cdef(cdef_text(HEADER))
    ffi.set_source(
        "can_dbc._can_table",
        '#include "can_table.h"',
        sources=[rel(SOURCE)],
        include_dirs=[rel(_CSRC)],
        depends=[rel(HEADER)],
        extra_compile_args=COMPILE_ARGS,
        extra_link_args=LINK_ARGS,
        libraries=["m"],
    )
    return ffi


ffibuilder = make_builder()
