"""python-can without asammdf until MF4 is asked for: the one place that imports ``can``
for the project (and so ``cantools``, which imports ``can`` itself).

Why: python-can's ``can/io/__init__.py`` imports its MF4 reader and writer eagerly, and
``can/io/mf4.py`` imports asammdf at module level (inside ``try: ... except ImportError``).
With the ``mdf`` extra installed, a plain ``import can`` therefore loads asammdf and with it
pandas, pyarrow, lxml, numexpr, zstd and lz4: about 190 MB resident in ``dct-hil serve``,
which locks all its memory (mlockall) and so pays for every page of them, for a feature
the run does not use (python-can 4.6, asammdf 8.8; measured in ``docs/server.md``).

What: ``python_can()`` imports ``can`` with asammdf hidden (``sys.modules["asammdf"] =
None`` makes ``import asammdf`` raise ImportError, which ``can/io/mf4.py`` catches and
leaves its MF4 classes without a backend), then removes the block at once: a later
``import asammdf`` works as ever. The first such import (an MF4 recording, traffic log or
stimulus, or anyone's) re-runs ``can/io/mf4.py`` once it has loaded (``importlib.reload``
executes it again in the same module dictionary, so python-can's ``MF4Writer`` and
``MF4Reader``, wherever referenced, find asammdf from then on). When asammdf is already
loaded, or ``can`` already imported, nothing is hidden.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import threading
from types import ModuleType
from typing import Any

__all__ = ["python_can"]

_lock = threading.Lock()


def python_can(mf4: bool = False) -> ModuleType:
    """The ``can`` module, imported without asammdf unless asammdf is already loaded.

    ``mf4`` True: for python-can's MF4 writer or reader, also imports asammdf (if
    installed; else python-can's MF4 classes say it is missing)."""
    if mf4 and "asammdf" not in sys.modules:
        try:
            import asammdf  # noqa: F401  (completes can.io.mf4 if can was imported without it)
        except ImportError:
            pass
    can = sys.modules.get("can")
    if can is not None:
        return can
    with _lock:
        if "can" in sys.modules or "asammdf" in sys.modules:
            import can
            return can
        sys.modules["asammdf"] = None          # type: ignore[assignment]  # import -> ImportError
        try:
            import can
        finally:
            if "asammdf" in sys.modules and sys.modules["asammdf"] is None:
                del sys.modules["asammdf"]
        mf4 = sys.modules.get("can.io.mf4")
        if mf4 is not None and getattr(mf4, "asammdf", True) is None \
                and importlib.util.find_spec("asammdf") is not None:
            sys.meta_path.insert(0, _CompleteMf4())
        return can


class _CompleteMf4(importlib.abc.MetaPathFinder):
    """At the first ``import asammdf``: lets the real finder find it, and after its module
    has run, re-runs ``can.io.mf4`` (once; then leaves ``sys.meta_path``)."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != "asammdf":
            return None
        try:
            sys.meta_path.remove(self)
        except ValueError:
            return None
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        spec.loader = _ThenReloadMf4(spec.loader)
        return spec


class _ThenReloadMf4(importlib.abc.Loader):
    def __init__(self, loader: Any) -> None:
        self.loader = loader

    def create_module(self, spec: Any) -> Any:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        # asammdf sees its own loader (resources, reloads), not this wrapper
        module.__loader__ = module.__spec__.loader = self.loader
        self.loader.exec_module(module)
        mf4 = sys.modules.get("can.io.mf4")
        if mf4 is not None and getattr(mf4, "asammdf", True) is None:
            importlib.reload(mf4)
