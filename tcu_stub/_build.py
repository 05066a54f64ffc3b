"""cffi builder of the compiled TCU (build time only; never imported at run time).

setup.py names it in ``cffi_modules``; ``scripts/setup`` (or any ``pip
install``) compiles ``tcu_stub/_tcu_fast*.so``: the reference TCU, the
in-process CAN contract, the drivers and the closed loop in C
and the TCU as a CAN node on a thread of its own (``tcu_stub/csrc/``), with the table codec of ``can_dbc/csrc/can_table.c``
compiled in and its types from ``can_dbc._can_table`` (``ffi.include``).
The plant is not compiled in: the loop steps it through function pointers
taken from ``plant._dct_plant``, the code ``Plant.step`` runs; the plant's
structs are declared to cffi by name only (their layout comes from
``dct_plant.h`` when the C compiles). The cdef is the public header,
read as plant/_build.py reads dct_plant.h.
"""

import os
import runpy
from types import SimpleNamespace

from cffi import FFI

_HERE = os.path.dirname(os.path.abspath(__file__))
_ROOT = os.path.dirname(_HERE)
_PLANT_CSRC = os.path.join(_ROOT, "plant", "csrc")
_CAN_CSRC = os.path.join(_ROOT, "can_dbc", "csrc")
_TCU_CSRC = os.path.join(_HERE, "csrc")
_SOURCES = ("tcu_clutch.c", "tcu_diag.c", "tcu_logic.c", "tcu_link.c", "tcu_driver.c", "tcu_run.c",
            "tcu_node.c", "tcu_port.c")
# the plant's structs, their layout left to the compiler (cffi's "...")
_PLANT_TYPES = """
#define DCT_OK 0
typedef struct { ...; } dct_outputs;
typedef struct { ...; } dct_plant;
"""

# loaded by path: setuptools runs build files by path, not as package modules
_can = SimpleNamespace(**runpy.run_path(os.path.join(_ROOT, "can_dbc", "_build.py")))
_rel = _can.rel


def make_builder():
    ffi = FFI()
    ffi.include(_can.ffibuilder)
    ffi.cdef(_PLANT_TYPES + _can.cdef_text(os.path.join(_TCU_CSRC, "tcu_fast.h"))
             + _can.cdef_text(os.path.join(_TCU_CSRC, "tcu_node.h")))
    ffi.set_source(
        "tcu_stub._tcu_fast",
        '#include "tcu_fast.h"\n#include "tcu_node.h"',
        sources=[_rel(os.path.join(_TCU_CSRC, f)) for f in _SOURCES]
        + [_rel(_can.SOURCE)],
        include_dirs=[_rel(d) for d in (_TCU_CSRC, _CAN_CSRC, _PLANT_CSRC)],
        # the headers too: a changed dct_plant.h (the plant's layout) must rebuild this
        # extension, not only plant._dct_plant (tcu_stub/fast.py refuses a mismatch)
        depends=[_rel(p) for p in (os.path.join(_PLANT_CSRC, "dct_plant.h"),
                                   os.path.join(_CAN_CSRC, "can_table.h"),
                                   os.path.join(_TCU_CSRC, "tcu_fast.h"),
                                   os.path.join(_TCU_CSRC, "tcu_node.h"),
                                   os.path.join(_TCU_CSRC, "tcu_util.h"))],
        extra_compile_args=_can.COMPILE_ARGS,
        extra_link_args=_can.LINK_ARGS,
        libraries=["m", "pthread"],
    )
    return ffi


ffibuilder = make_builder()
