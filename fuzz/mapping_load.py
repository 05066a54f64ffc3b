"""atheris target: the mapping loader (can_dbc.mapping.load) on arbitrary TOML
and DBC text, through the matrix reader (can_dbc.matrix) and the table
builder.

The input is the mapping file's text, then (after a NUL byte each) the text
of a.dbc and b.dbc, which the mapping may name. The loader must return a
Mapping or raise MappingError of one line; any other exception is a finding.
"""

from __future__ import annotations

import os

import _atheris

mapping = None
DIR = _atheris.scratch("mapping")


def _import() -> None:
    global mapping
    import can_dbc.matrix
    import can_dbc.table  # noqa: F401
    from can_dbc import mapping as m
    mapping = m


def TestOneInput(data: bytes) -> None:
    if mapping is None:
        _import()
    parts = data.split(b"\0", 2) + [b"", b""]
    for name, text in zip(("mapping.toml", "a.dbc", "b.dbc"), parts):
        with open(os.path.join(DIR, name), "wb") as f:
            f.write(text)
    try:
        mapping.load(os.path.join(DIR, "mapping.toml"))
    except mapping.MappingError as e:
        _atheris.one_line(e)


if __name__ == "__main__":
    _atheris.run(TestOneInput, _import)
