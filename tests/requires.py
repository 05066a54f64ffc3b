"""What the tests need, checked in one place: a missing test dependency or a
stale build FAILS with the one line that fixes it, it never skips. A suite
that skips what it cannot run passes on a machine that tested nothing.

    from requires import module, c_compiler, built_with

    pyxcp = module("pyxcp")                    # at module level or in a fixture
    cc = c_compiler()
    lib = built_with(lib, "rt_daq_pop_many")   # the compiled extension is current
"""

import importlib
import shutil

import pytest

#: how each test dependency gets onto the machine
SETUP = "scripts/setup installs it (pip install -e '.[all,docs,test]')"
REBUILD = ("the compiled extension is older than its C sources: rebuild it with scripts/setup "
           "(or pip install -e '.[all,docs,test]')")
HOW = {
    "pyxcp": SETUP, "pya2l": SETUP, "fmpy": SETUP, "selenium": SETUP, "hypothesis": SETUP,
    "pytest_timeout": SETUP,
    "asammdf": SETUP, "cantools": SETUP, "msgpack": "pip install 'python-can[multicast]' "
                                                   "(a dependency of dct-hil: scripts/setup)",
    "can_dbc._can_table": "the C extension is built by scripts/setup",
    "rt_loop._rt_loop": "the C extension is built by scripts/setup",
    "plant._dct_plant": "the C extension is built by scripts/setup",
    "tcu_stub._tcu_fast": "the C extension is built by scripts/setup",
}


def missing(what, how):
    """Fails the test (or the module, at collection) naming ``what`` and ``how``."""
    pytest.fail(f"{what} missing: {how}", pytrace=False)


def module(name):
    """``import name``, or fail naming it and how to install it."""
    try:
        return importlib.import_module(name)
    except ImportError as e:
        missing(f"{name} ({e})", HOW.get(name, SETUP))


def tool(name, how):
    """The path of the program ``name`` on PATH, or fail naming it and ``how``."""
    path = shutil.which(name)
    if path is None:
        missing(f"the program {name}", how)
    return path


def c_compiler():
    """The system C compiler: ``cc``, else ``gcc``; or fail (as scripts/setup does)."""
    path = shutil.which("cc") or shutil.which("gcc")
    if path is None:
        missing("a C compiler (cc or gcc)", "install one, e.g. apt-get install gcc")
    return path


def built_with(lib, *names):
    """``lib`` when the compiled extension has every function ``names``; else the
    build is stale: fail with the command that rebuilds it."""
    absent = [n for n in names if not hasattr(lib, n)]
    if absent:
        missing(f"{', '.join(absent)} in the compiled extension", REBUILD)
    return lib
