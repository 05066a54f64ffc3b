"""The test suite's own machinery: a hung test fails by its timeout with its
name, markers are strict, a missing test dependency fails (never skips), every
script sets itself up, and scripts/suite_times.py writes the suite's figures."""

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import requires

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = REPO / "scripts"


def _pytest(tmp_path, source, *args, timeout=120):
    (tmp_path / "test_sample.py").write_text(source)
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q",
                           "-c", str(REPO / "pyproject.toml"), "--rootdir", str(tmp_path),
                           *args, str(tmp_path / "test_sample.py")],
                          capture_output=True, text=True, cwd=tmp_path, timeout=timeout)


HUNG = """\
import time

def test_waits_for_nothing_forever():
    time.sleep(3600)

def test_after_the_hung_one():
    assert True
"""


@pytest.mark.slow
def test_a_hung_test_fails_by_its_timeout_with_its_name_and_the_run_goes_on(tmp_path):
    r = _pytest(tmp_path, HUNG, "-o", "timeout=2", "-rA")
    out = r.stdout + r.stderr
    assert r.returncode == 1, out
    assert re.search(r"FAILED \S*test_waits_for_nothing_forever - Failed: Timeout", out), out
    assert re.search(r"PASSED \S*test_after_the_hung_one", out), out
    assert "1 failed, 1 passed" in out, out


def test_the_suite_has_a_per_test_timeout_and_strict_markers():
    ini = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert 60 <= int(ini["timeout"]) <= 600, ini["timeout"]
    assert "--strict-markers" in ini["addopts"].split()
    names = {m.split(":")[0] for m in ini["markers"]}
    assert {"slow", "long", "vcan", "hil", "browser"} <= names
    # the guest stage is bounded well below CI's 90 minutes
    default = re.search(r"VCAN_VM_TIMEOUT:-(\d+)", (SCRIPTS / "vcan-vm").read_text()).group(1)
    assert int(default) <= 45 * 60


@pytest.mark.slow
def test_a_misspelt_marker_is_an_error(tmp_path):
    r = _pytest(tmp_path, "import pytest\n\n@pytest.mark.slwo\ndef test_x():\n    pass\n")
    assert r.returncode != 0
    assert "'slwo' not found in `markers` configuration option" in r.stdout + r.stderr


def test_a_missing_dependency_fails_naming_it_and_how_to_install_it():
    with pytest.raises(pytest.fail.Exception) as e:
        requires.module("no_such_test_dependency_xyz")
    assert "no_such_test_dependency_xyz" in str(e.value) and "scripts/setup" in str(e.value)
    with pytest.raises(pytest.fail.Exception) as e:
        requires.tool("no-such-program-xyz", "apt-get install it")
    assert "no-such-program-xyz" in str(e.value) and "apt-get install it" in str(e.value)

    class Lib:
        present = None
    assert requires.built_with(Lib, "present") is Lib
    with pytest.raises(pytest.fail.Exception) as e:
        requires.built_with(Lib, "present", "rt_new_function")
    assert "rt_new_function" in str(e.value) and "scripts/setup" in str(e.value)


def test_no_test_skips_for_a_missing_module():
    """importorskip turns a missing test dependency into a green run: requires.module fails."""
    found = [f"{p.relative_to(REPO)}:{n}" for p in (REPO / "tests").rglob("*.py")
             for n, line in enumerate(p.read_text().splitlines(), 1)
             if "importorskip(" in line and p.name != "test_suite_tools.py"]
    assert found == []


def test_every_script_that_runs_the_venv_sets_itself_up_first():
    """An interrupted install leaves .venv/bin/python without the packages: a script that
    only checks that it exists runs into an ImportError; scripts/setup is idempotent."""
    for path in sorted(SCRIPTS.iterdir()):
        text = path.read_text() if path.is_file() and not path.suffix else ""
        if ".venv/bin/" not in text or path.name == "setup":
            continue
        assert "[ -x .venv/bin/python ] ||" not in text, path.name
        # called unconditionally at the top level (not in a function, not after a test)
        assert re.search(r"^(stage setup - )?bash scripts/setup\b", text, re.M), \
            f"{path.name} uses .venv without calling scripts/setup first"


def _junit(path, cases):
    body = "".join(
        f'<testcase classname="tests.{mod}" name="{name}" time="{t}">{extra}</testcase>'
        for mod, name, t, extra in cases)
    path.write_text(f'<?xml version="1.0"?><testsuites><testsuite name="pytest">{body}'
                    f'</testsuite></testsuites>')


def test_suite_times_writes_stages_and_the_slowest_tests(tmp_path):
    host, guest = tmp_path / "host.xml", tmp_path / "guest.xml"
    _junit(host, [("test_a", "test_fast", 0.1, ""),
                  ("test_a", "test_slow", 12.5, "<failure message='x'/>"),
                  ("test_b", "test_skipped", 0.0, "<skipped/>")])
    _junit(guest, [("vcan.test_c", f"test_{i}", float(i), "") for i in range(30)])
    out = tmp_path / "out" / "test-times.json"
    r = subprocess.run([sys.executable, str(SCRIPTS / "suite_times.py"), "--elapsed", "320.04",
                        str(out), "full",
                        "setup=ok:1.25", "c=ok:10", f"host=failed:60.5:{host}",
                        f"guest=ok:300:{guest}", f"absent=ok:1:{tmp_path / 'none.xml'}"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["tier"] == "full" and doc["total_s"] == pytest.approx(1.2 + 10 + 60.5 + 300 + 1,
                                                                      abs=0.2)
    assert doc["elapsed_s"] == 320.0          # the guest ran beside the host: less than the sum
    stages = {s["name"]: s for s in doc["stages"]}
    assert stages["host"] == {"name": "host", "status": "failed", "wall_s": 60.5, "tests": 3,
                              "failed": 1, "skipped": 1}
    assert stages["guest"]["tests"] == 30 and "tests" not in stages["c"]
    assert stages["absent"]["junit"].startswith("missing")
    slowest = doc["slowest"]
    assert len(slowest) == 20 and slowest[0] == {"test": "tests.vcan.test_c::test_29",
                                                 "stage": "guest", "time_s": 29.0}
    assert [s["time_s"] for s in slowest] == sorted((s["time_s"] for s in slowest), reverse=True)
    assert "host" in r.stdout and "figures in" in r.stdout and "side by side" in r.stdout
