"""The SocketCAN tests in the guest (scripts/vcan-vm) show their progress: each
test's verbose result carries its wall time, setup included, and the end
summary keeps pytest's plain words."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SAMPLE = """\
import pytest

@pytest.fixture(scope="module")
def run():
    return 1

def test_passes(run):
    assert run == 1

def test_fails(run):
    assert run == 2
"""


@pytest.mark.slow
def test_guest_tests_print_a_line_with_the_wall_time_per_test(tmp_path):
    shutil.copy(REPO / "tests" / "vcan" / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_sample.py").write_text(SAMPLE)
    r = subprocess.run([sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", str(tmp_path)],
                       capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    assert re.search(r"::test_passes PASSED \(\d+ s\)", r.stdout), r.stdout
    assert re.search(r"::test_fails FAILED \(\d+ s\)", r.stdout), r.stdout
    assert re.search(r"^FAILED \S+::test_fails - ", r.stdout, re.M), r.stdout


def test_vcan_vm_runs_the_guest_pytest_verbose_and_unbuffered():
    text = (REPO / "scripts" / "vcan-vm").read_text()
    cmd = re.search(r"^pytest_cmd=\((.*?)\)", text, re.M | re.S).group(1).split()
    assert "-v" in cmd and "-q" not in cmd
    inner = re.search(r'^inner="(.*)"$', text, re.M).group(1)
    assert inner.startswith("PYTHONUNBUFFERED=1 ") and inner.endswith("$inner")
    # both guests run it: QEMU's command and User-mode Linux's init
    assert "$inner;" in re.search(r"^guest_cmd=(.*)$", text, re.M).group(1)
    init = re.search(r'^    cat > "\$init" <<EOF\n(.*?)^EOF$', text, re.M | re.S).group(1)
    assert re.search(r"^\$inner$", init, re.M)
