"""MkDocs hook: the generated parts of the format reference pages, written at build
time from the code and data they describe, so that they cannot fall behind:

- ``<!-- generated: mapping format -->`` (reference/mapping-format.md): the format
  with every key and its rules, from the docstring of ``can_dbc.mapping``; the units
  a mapping converts (``can_dbc.mapping.UNITS``), the name suffixes
  (``plant.describe.SUFFIX_UNITS``) and the status fields;
  ``<!-- generated: protection kinds -->``: the protection kinds, from the docstring of
  ``can_dbc.protection``.
- ``<!-- generated: parameter table -->`` (reference/parameter-format.md): every
  value of the default car (``plant/data/golf_mk5_gti_dsg.toml``) with its allowed
  range, whether it may change while the loop runs (``plant/data/ranges.toml``) and
  its comment (unit and source).
"""

from __future__ import annotations

import html
import re
import sys
import tomllib
from pathlib import Path

from mkdocs.exceptions import PluginError

ROOT = Path(__file__).resolve().parents[2]
CAR = ROOT / "plant" / "data" / "golf_mk5_gti_dsg.toml"


def _imports():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))


def _cell(s: str) -> str:
    s = html.escape(str(s), quote=False)
    return re.sub(r"([\\`*_\[\]|])", r"\\\1", s)


def _inline(s: str) -> str:
    """reST-style ``code`` and :class:`X` as Markdown code spans."""
    s = re.sub(r":\w+:`([^`]+)`", r"`\1`", s)
    return s.replace("``", "`")


def mapping_format() -> str:
    _imports()
    from can_dbc import mapping
    from plant.describe import SUFFIX_UNITS
    doc = mapping.__doc__ or ""
    out: list[str] = []
    lines = doc.strip("\n").splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.rstrip().endswith("::"):                 # a literal block: the TOML example
            text = line.rstrip()[:-2].rstrip()
            out += [_inline(text) + ":", "", "```toml"]
            i += 1
            while i < len(lines) and not lines[i].strip():
                i += 1
            while i < len(lines) and (not lines[i].strip() or lines[i].startswith("    ")):
                out.append(lines[i][4:])
                i += 1
            while out[-1] == "":
                out.pop()
            out += ["```", ""]
            continue
        out.append(_inline(line))
        i += 1
    out += ["", "### Units a mapping converts", "",
            "`unit = \"...\"` on a signal names its unit on the bus; within one quantity "
            "these convert (`can_dbc.mapping.UNITS`):", "",
            "| quantity | units |", "|---|---|"]
    for quantity, units in mapping.UNITS.items():
        out.append(f"| {quantity} | {', '.join(f'`{u}`' for u in units)} |")
    out += ["", "The unit of a plant output or input is its name's last part "
            "(`plant.describe.SUFFIX_UNITS`):", "", "| suffix | unit |", "|---|---|"]
    out += [f"| `_{s}` | `{u}` |" for s, u in SUFFIX_UNITS.items()]
    out += ["", "Status fields (`{ status = \"...\" }`): "
            + ", ".join(f"`{f}`" for f in mapping.STATUS_FIELDS) + ".", ""]
    return "\n".join(out)


def protection_kinds() -> str:
    """The kinds of can_dbc/protection.py's docstring (``kind`` then its indented
    description) as a list; the text after them as a paragraph."""
    _imports()
    from can_dbc import protection
    lines = (protection.__doc__ or "").splitlines()
    out: list[str] = []
    start = next(i for i, line in enumerate(lines) if line.strip() == "Kinds:") + 1
    i = start
    while i < len(lines):
        line = lines[i]
        m = re.match(r"^``(\w+)``\s*$", line)
        if m:
            text = []
            i += 1
            while i < len(lines) and lines[i].startswith("    "):
                text.append(lines[i].strip())
                i += 1
            out.append(f"- `{m.group(1)}`: {_inline(' '.join(text))}")
            continue
        if line.strip():
            if out and out[-1] and not out[-1].startswith("- "):
                out[-1] += " " + _inline(line.strip())
            else:
                out += ["", _inline(line.strip())]
        i += 1
    return "\n".join(out) + "\n"


def _flatten(value, path=()):
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _flatten(v, path + (k,))
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        for i, v in enumerate(value):
            yield from _flatten(v, path + (i,))
    else:
        yield path, value


def _dotted(path) -> str:
    out = ""
    for item in path:
        out += f"[{item}]" if isinstance(item, int) else ("." if out else "") + item
    return out


def _number(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def parameter_table() -> str:
    _imports()
    from plant import describe
    with open(CAR, "rb") as f:
        car = tomllib.load(f)
    comments = describe.toml_comments(CAR)
    ranges = describe.ranges()
    online = describe.online_keys()
    out = ["| key | default car | range | online | unit and source |", "|---|---|---|---|---|"]
    for path, value in _flatten(car):
        key = _dotted(path)
        rkey = describe.range_key(path)
        lo_hi = ranges.get(rkey)
        shown = (f"{len(value)} values" if isinstance(value, list) and len(value) > 4
                 else ", ".join(_number(v) for v in value) if isinstance(value, list)
                 else _number(value))
        rng = f"{_number(lo_hi[0])} .. {_number(lo_hi[1])}" if lo_hi else ""
        out.append(f"| `{key}` | {_cell(shown)} | {rng} | {'yes' if rkey in online else ''} "
                   f"| {_cell(comments.get(key, ''))} |")
    return "\n".join(out) + "\n"


GENERATORS = {
    "<!-- generated: mapping format -->": mapping_format,
    "<!-- generated: protection kinds -->": protection_kinds,
    "<!-- generated: parameter table -->": parameter_table,
}


def on_page_markdown(markdown, page, config, files):
    for marker, fn in GENERATORS.items():
        if marker in markdown:
            try:
                markdown = markdown.replace(marker, fn())
            except Exception as e:  # the build fails with the reason in one line
                raise PluginError(f"format_reference: {fn.__name__} failed: "
                                  f"{type(e).__name__}: {e}") from e
    return markdown
