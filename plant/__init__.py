"""The powertrain plant: a C core (plant/csrc) stepped from Python.

``Plant`` owns one C plant and shows its inputs, outputs and state as NumPy
views; ``load_params`` reads the TOML parameter sets. The names are loaded on
first use, so ``plant.params`` and ``plant.scenario`` import without the
compiled extension.

``__version__`` is the dct-hil distribution's version, written only here
(pyproject.toml reads it; every layer above imports it from here).
"""

__version__ = "0.1.0"

__all__ = ["Plant", "PlantError", "load_params", "ParamError", "__version__"]

_WHERE = {
    "Plant": "plant.model",
    "PlantError": "plant.model",
    "load_params": "plant.params",
    "ParamError": "plant.params",
}


def __getattr__(name):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'plant' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(list(globals()) + __all__)
