"""A reference TCU with calibration values of a run's choosing.

The reference TCU (``tcu_stub/logic.py``) reads its calibration from module
constants. ``make_tcu(calibration)`` returns a ``TcuLogic`` whose constants
are the given ones and the others the defaults, without touching the shared
module: the module's source is compiled once more with those assignments
replaced (so values derived from them at import follow) into a private
module, cached per calibration. Its ``TcuLogic`` runs exactly the code of
``tcu_stub.logic``; pass the instance to ``tcu_stub.offline.run_offline(...,
tcu=...)``. An empty calibration gives the stock ``tcu_stub.logic.TcuLogic``.
"""

from __future__ import annotations

import ast
import itertools
import types
from functools import lru_cache

_serial = itertools.count()


def _freeze(calibration: dict) -> tuple:
    return tuple(sorted((str(k), v) for k, v in calibration.items()))


@lru_cache(maxsize=64)
def _module(frozen: tuple) -> types.ModuleType:
    from tcu_stub import logic

    values = dict(frozen)
    with open(logic.__file__, encoding="utf-8") as f:
        tree = ast.parse(f.read(), logic.__file__)
    seen = set()
    for node in tree.body:
        target = None
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target = node.targets[0]
        elif isinstance(node, ast.AnnAssign):
            target = node.target
        if isinstance(target, ast.Name) and target.id in values:
            node.value = ast.copy_location(ast.parse(repr(values[target.id]), mode="eval").body,
                                           node.value)
            seen.add(target.id)
    missing = set(values) - seen
    if missing:
        raise ValueError(f"tcu_stub/logic.py assigns no constant {', '.join(sorted(missing))}")
    ast.fix_missing_locations(tree)
    name = f"tcu_stub._calibrated_{next(_serial)}"
    mod = types.ModuleType(name, logic.__doc__)
    mod.__file__ = logic.__file__
    exec(compile(tree, logic.__file__, "exec"), mod.__dict__)  # the project's own file
    return mod


def make_tcu(calibration: dict | None = None):
    """A fresh TcuLogic with ``calibration`` ({CONSTANT: value}) applied."""
    if not calibration:
        from tcu_stub.logic import TcuLogic

        return TcuLogic()
    return _module(_freeze(calibration)).TcuLogic()


def calibrated_module(calibration: dict) -> types.ModuleType:
    """The private copy of tcu_stub.logic with ``calibration`` applied (for checks)."""
    return _module(_freeze(calibration))
