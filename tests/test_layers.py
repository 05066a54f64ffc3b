"""The layers hold: plant <- can_dbc <- tcu_stub <- rt_loop | dct_hil.studies | validation <- dct_hil.

scripts/test's lint stage runs ruff and import-linter with the contracts in
pyproject.toml; these tests show that the contracts pass on the project and
fail when a layer is broken (in a temporary copy of the packages), and hold
the imports the tool cannot see, those of the compiled extensions (a
``from rt_loop._rt_loop import ...`` names no Python file), to the same layers.
"""

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import requires

ROOT = Path(__file__).resolve().parent.parent
#: the layers, lowest first; one layer may hold several packages
LAYERS = [("plant",), ("can_dbc",), ("tcu_stub",), ("rt_loop", "dct_hil.studies", "validation"), ("dct_hil",)]
LEVEL = {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}
TOP = sorted({pkg.split(".")[0] for pkg in LEVEL})       # the top-level packages
#: the compiled extensions (setup.py's cffi_modules)
EXTENSIONS = ("plant._dct_plant", "can_dbc._can_table", "rt_loop._rt_loop", "tcu_stub._tcu_fast")


def _lint_imports(cwd):
    exe = Path(sys.executable).parent / "lint-imports"
    if not exe.exists():
        requires.missing("lint-imports (import-linter)", requires.SETUP)
    env = dict(os.environ, PYTHONPATH=str(cwd))
    return subprocess.run([str(exe), "--no-cache"], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120, check=False)


def _copy(tmp_path):
    """The packages' Python files and pyproject.toml in ``tmp_path``."""
    for pkg in TOP:
        shutil.copytree(ROOT / pkg, tmp_path / pkg,
                        ignore=lambda d, names: [n for n in names
                                                 if not (n.endswith(".py") or os.path.isdir(os.path.join(d, n)))
                                                 or n == "__pycache__"])
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    return tmp_path


def _append(path, line):
    with open(path, "a", encoding="utf-8") as f:
        f.write(f"\n{line}\n")


def test_the_contracts_hold_on_the_project():
    r = _lint_imports(ROOT)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "2 kept, 0 broken" in r.stdout


def test_an_upward_import_breaks_the_layers(tmp_path):
    copy = _copy(tmp_path)
    assert _lint_imports(copy).returncode == 0        # the copy holds, as the project does
    _append(copy / "can_dbc" / "codec.py", "from tcu_stub import logic  # upward")
    r = _lint_imports(copy)
    assert r.returncode != 0
    assert "can_dbc is not allowed to import tcu_stub" in r.stdout
    assert "can_dbc.codec -> tcu_stub.logic" in r.stdout


def test_an_import_cycle_between_modules_breaks_the_contract(tmp_path):
    copy = _copy(tmp_path)
    # tcu_stub.offline imports tcu_stub.fast; the way back closes a loop
    _append(copy / "tcu_stub" / "fast.py", "from tcu_stub import offline  # a cycle")
    r = _lint_imports(copy)
    assert r.returncode != 0
    assert "No cycles are allowed in tcu_stub" in r.stdout


def _imports(path, root):
    """(line, module) of every import in the file, at any depth (lazy ones too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    pkg = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            yield node.lineno, base
            for a in node.names:                       # from rt_loop import _rt_loop
                yield node.lineno, f"{base}.{a.name}"


def extension_imports_across_layers(root=ROOT):
    """'file:line imports X' for every import of a compiled extension from a lower layer."""
    found = []
    for pkg, level in LEVEL.items():
        for path in sorted((root / pkg.replace(".", "/")).rglob("*.py")):
            seen = set()
            for line, name in _imports(path, root):
                ext = next((e for e in EXTENSIONS if name == e or name.startswith(e + ".")), None)
                if ext and LEVEL[ext.split(".")[0]] > level and (line, ext) not in seen:
                    seen.add((line, ext))
                    found.append(f"{path.relative_to(root)}:{line} imports {ext}")
    return found


def test_no_compiled_extension_is_imported_from_a_lower_layer():
    assert extension_imports_across_layers() == []


def test_the_extension_check_finds_an_upward_extension_import(tmp_path):
    copy = _copy(tmp_path)
    _append(copy / "can_dbc" / "table.py", "def _loop():\n    from rt_loop._rt_loop import lib\n    return lib")
    _append(copy / "tcu_stub" / "fast.py", "from rt_loop import _rt_loop")
    found = extension_imports_across_layers(copy)
    assert len(found) == 2
    assert found[0].startswith("can_dbc/table.py:") and found[0].endswith("imports rt_loop._rt_loop")
    assert found[1].startswith("tcu_stub/fast.py:")


def test_every_package_has_a_layer():
    """A new top-level package is given a layer, here and in pyproject.toml."""
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages == set(TOP)
    contract = (ROOT / "pyproject.toml").read_text(encoding="utf-8").split("[tool.importlinter]")[1]
    for pkg in packages:
        assert f'"{pkg}"' in contract, pkg
    # dct_hil's modules are layered one by one (its studies lower than the rest)
    children = {p.stem for p in (ROOT / "dct_hil").glob("*.py")} - {"__init__"} | {
        p.parent.name for p in (ROOT / "dct_hil").glob("*/__init__.py")}
    for child in children:
        assert f"dct_hil.{child}" in contract, child


def test_the_studies_may_not_import_the_command_line(tmp_path):
    copy = _copy(tmp_path)
    _append(copy / "dct_hil" / "studies" / "keys.py", "from dct_hil.commands import options  # upward")
    r = _lint_imports(copy)
    assert r.returncode != 0
    assert "dct_hil.studies.keys -> dct_hil.commands.options" in r.stdout
