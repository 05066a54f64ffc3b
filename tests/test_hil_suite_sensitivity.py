"""The HiL suite catches a broken TCU: with one of the reference TCU's
diagnostics broken, the suite's test of that reaction fails.

The suite file (tests/hil/test_reference_tcu.py) runs in pytester, in this
process (the bench fixture starts the TCU in a thread here), beside a
conftest that breaks one monitor for the run only: the line pressure
monitor's threshold below any pressure, so a line pressure loss is never
diagnosed as such (the TCU still ends in limp home, through the clutch
pressure it can no longer reach: the test fails on the missing trouble code).
The same test passes with the TCU as it is (the suite runs in CI).
"""

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

SUITE = Path(__file__).resolve().parent / "hil" / "test_reference_tcu.py"

BREAK_LINE_MONITOR = '''
import pytest
import tcu_stub.diagnostics as diagnostics


@pytest.fixture(autouse=True)
def broken_line_pressure_monitor(monkeypatch):
    monkeypatch.setattr(diagnostics, "LINE_LOW_BAR", -1.0)   # never below: never diagnosed
'''


@pytest.mark.slow
def test_breaking_the_line_pressure_diagnostic_fails_its_hil_test(pytester):
    pytester.makeconftest(BREAK_LINE_MONITOR)
    pytester.makepyfile(test_suite=SUITE.read_text())
    result = pytester.runpytest_inprocess("-p", "no:cacheprovider", "-q", "-W",
                                          "ignore::pytest.PytestUnknownMarkWarning",
                                          "test_suite.py::test_line_pressure_loss_limp_home")
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(["*line_pressure not reported within*"])
