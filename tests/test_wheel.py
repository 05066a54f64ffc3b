"""The wheel as a user installs it: built from this checkout, installed with only
its core dependencies into a fresh virtual environment outside the checkout, and
run from another directory; then with the mdf extra.

The core serves a TCU, runs the demo and offline runs; a command that needs a
missing extra ends with one line naming it (exit 2). pip takes the packages
from the configured index (its cache makes a second run quick)."""

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from requires import c_compiler

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

ROOT = Path(__file__).resolve().parent.parent
CORE = {"cffi", "numpy", "python-can", "cantools"}
EXTRAS_ONLY = {"asammdf", "bokeh", "matplotlib", "dask", "distributed", "pandas", "pyarrow", "scipy",
               "tornado"}


def _run(cmd, cwd, timeout=300):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, check=False)


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    """(python, dct-hil, wheel, work dir): the wheel installed alone in a new venv."""
    base = tmp_path_factory.mktemp("wheel")
    dist = base / "dist"
    r = _run([sys.executable, "-m", "pip", "wheel", ROOT, "--no-deps", "--no-build-isolation",
              "-q", "-w", dist], cwd=base, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    (wheel,) = dist.glob("dct_hil-*.whl")
    r = _run([sys.executable, "-m", "venv", base / "venv"], cwd=base)
    assert r.returncode == 0, r.stderr
    python = base / "venv" / "bin" / "python"
    r = _run([python, "-m", "pip", "install", "-q", wheel], cwd=base, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    work = base / "elsewhere"
    work.mkdir()
    return python, base / "venv" / "bin" / "dct-hil", wheel, work


def _installed(python, cwd):
    r = _run([python, "-m", "pip", "list", "--format=freeze"], cwd=cwd)
    assert r.returncode == 0, r.stderr
    return {line.split("==")[0].lower().replace("_", "-") for line in r.stdout.split()}


def _one_line_error(r):
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: "), r.stderr
    return lines[0]


def test_the_wheel_holds_the_product_packages_only(venv):
    *_, wheel, _ = venv
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.startswith("dct_hil-")}
    assert tops == {"plant", "can_dbc", "rt_loop", "tcu_stub", "dct_hil"}
    packages = {p.parent.relative_to(ROOT).as_posix() for top in tops
                for p in (ROOT / top).rglob("__init__.py")}
    missing = sorted(p for p in packages if f"{p}/__init__.py" not in names)
    assert not missing, f"packages of the checkout not in the wheel (pyproject.toml): {missing}"
    for ext in ("plant/_dct_plant", "can_dbc/_can_table", "rt_loop/_rt_loop", "tcu_stub/_tcu_fast"):
        assert any(n.startswith(ext) and n.endswith(".so") for n in names), ext
    assert "dct_hil/studies/examples/shift_map.toml" in names
    shipped = {f"can_dbc/{d}/{f}" for d in ("matrices", "mappings")
               for f in os.listdir(ROOT / "can_dbc" / d) if not f.startswith((".", "__"))}
    assert shipped <= set(names), shipped - set(names)          # every matrix and mapping
    assert not any("/generated/" in n for n in names)


def test_the_core_install_pulls_only_the_core_dependencies(venv):
    python, _, _, work = venv
    installed = _installed(python, work)
    assert CORE <= installed
    assert not installed & EXTRAS_ONLY, installed & EXTRAS_ONLY
    r = _run([python, "-c", "import plant, rt_loop; print(plant.__file__, rt_loop.__file__)"], cwd=work)
    assert r.returncode == 0 and str(ROOT) not in r.stdout, r.stdout + r.stderr   # not the checkout


def test_simulate_serve_and_tcu_run_from_another_directory(venv):
    _, dct_hil, _, work = venv
    r = _run([dct_hil, "simulate", "--scenario", "0-100", "--out", "run.csv"], cwd=work)
    assert r.returncode == 0, r.stderr
    assert "zero_to_100_s" in r.stdout and (work / "run.csv").read_text().startswith("time_s,")
    r = _run([dct_hil, "serve", "--interface", "virtual", "--duration", "5", "--priority", "0",
              "--quiet", "--stats", "serve.json"], cwd=work)
    assert r.returncode == 0, r.stderr
    assert (work / "serve.json").exists()
    r = _run([dct_hil, "tcu", "--interface", "virtual", "--duration", "2", "--quiet",
              "--report", "tcu.json"], cwd=work)
    assert r.returncode == 0, r.stderr
    assert (work / "tcu.json").exists()
    for mapping in ("vehicle", "vehicle_arxml"):                # the shipped DBC and ARXML matrices
        r = _run([dct_hil, "mapping", "check", mapping], cwd=work)
        assert r.returncode == 0, r.stdout + r.stderr


def test_the_demo_runs_on_the_core_without_its_plots(venv):
    _, dct_hil, _, work = venv
    r = _run([dct_hil, "demo", "--duration", "3", "--quiet", "--out", "demo"], cwd=work)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "no matplotlib: pip install 'dct-hil[plots]'" in r.stdout
    assert (work / "demo" / "summary.json").exists()


@pytest.mark.parametrize("args, extra", [
    (["sweep", ROOT / "dct_hil" / "studies" / "examples" / "shift_map.toml"], "studies"),
    (["fit", "nothing.csv", "--params", "vehicle.mass_kg"], "studies"),
    (["simulate", "--scenario", "0-100", "--plot"], "plots"),
    (["valve"], "plots"),
    (["serve", "--interface", "virtual", "--duration", "1", "--record", "r.mf4"], "mdf"),
    (["serve", "--interface", "virtual", "--duration", "1", "--ui", "127.0.0.1:0"], "ui"),
    (["demo", "--mf4"], "mdf"),
])
def test_a_missing_extra_is_named_in_one_line(venv, args, extra):
    _, dct_hil, _, work = venv
    line = _one_line_error(_run([dct_hil, *args], cwd=work))
    assert f"needs the {extra} extra" in line and f"pip install 'dct-hil[{extra}]'" in line, line


def test_with_the_mdf_extra_fmu_a2l_and_an_mf4_recording(venv):
    python, dct_hil, wheel, work = venv
    c_compiler()                                   # dct-hil fmu compiles the plant
    r = _run([python, "-m", "pip", "install", "-q", f"{wheel}[mdf]"], cwd=work, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "asammdf" in _installed(python, work)
    r = _run([dct_hil, "fmu", "plant.fmu"], cwd=work)
    assert r.returncode == 0, r.stderr
    assert zipfile.ZipFile(work / "plant.fmu").read("modelDescription.xml").startswith(b"<?xml")
    r = _run([dct_hil, "a2l", "loop.a2l"], cwd=work)
    assert r.returncode == 0, r.stderr
    assert "ASAP2_VERSION" in (work / "loop.a2l").read_text()
    r = _run([dct_hil, "serve", "--interface", "virtual", "--duration", "2", "--priority", "0",
              "--quiet", "--record", "rec.mf4", "--stats", "rec.json"], cwd=work)
    assert r.returncode == 0, r.stderr
    r = _run([python, "-c", "from asammdf import MDF; m = MDF('rec.mf4'); "
                            "print(len(m.get('vehicle_speed_kmh').samples))"], cwd=work)
    assert r.returncode == 0 and int(r.stdout) > 100, r.stdout + r.stderr
