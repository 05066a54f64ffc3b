"""The optional parts of the installation: which extra of the distribution
brings which module. The core (``pip install dct-hil``) serves a TCU, runs the
demo and offline runs; the rest comes with an extra:

    mdf      asammdf: MF4 recording, MF4 stimulus, MF4 traffic logs, fits from MF4
    ui       bokeh (tornado): the live bench view in the browser (--ui)
    plots    matplotlib: PNG plots (simulate --plot, valve, the demo's plots)
    studies  dask, distributed, pandas, pyarrow, scipy, matplotlib: sweep, fit
    all      every one of them

A command that reaches a module of a missing extra ends with one line naming
the extra (``dct_hil.cli``: exit 2)."""

EXTRA_OF_MODULE = {
    "asammdf": "mdf",
    "bokeh": "ui",
    "tornado": "ui",
    "matplotlib": "plots",
    "dask": "studies",
    "distributed": "studies",
    "pandas": "studies",
    "pyarrow": "studies",
    "scipy": "studies",
}


def missing_extra(exc):
    """The extra whose module ``exc`` (an ImportError) did not find, or None
    when the missing module is not one an extra brings."""
    name = getattr(exc, "name", None) or ""
    return EXTRA_OF_MODULE.get(name.split(".")[0])


def install_hint(extra):
    """The command that installs ``extra``."""
    return f"pip install 'dct-hil[{extra}]'"


def require(*modules):
    """ModuleNotFoundError for the first of ``modules`` that is not installed:
    a command checks what its options need before it starts its work."""
    import importlib.util

    for module in modules:
        if importlib.util.find_spec(module) is None:
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)


def mf4_paths(*paths):
    """True when one of ``paths`` (None for none) is an MF4 file."""
    return any(p is not None and str(p).lower().endswith((".mf4", ".mdf")) for p in paths)
