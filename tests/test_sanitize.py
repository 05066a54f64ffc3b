"""The sanitizer runs' parts that need no instrumented build: the builders' switch
(plant/_build.py, DCT_HIL_SANITIZE) and the reading of the sanitizers' logs
(rt_loop.tools.sanitize_run). The runs themselves: scripts/sanitize."""

import os
import runpy
import subprocess
import sys

import pytest

from rt_loop.tools import sanitize_run as sr

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUILDER = os.path.join(ROOT, "plant", "_build.py")


def builder_args(monkeypatch, value):
    if value is None:
        monkeypatch.delenv("DCT_HIL_SANITIZE", raising=False)
    else:
        monkeypatch.setenv("DCT_HIL_SANITIZE", value)
    ns = runpy.run_path(BUILDER)
    return ns["COMPILE_ARGS"], ns["LINK_ARGS"]


def test_the_switch_builds_with_the_sanitizer_asked_for_and_leaves_the_default_alone(monkeypatch):
    plain, plain_link = builder_args(monkeypatch, None)
    assert "-O3" in plain and "-flto=auto" in plain and not any("sanitize" in a for a in plain)
    thread, thread_link = builder_args(monkeypatch, "thread")
    assert "-fsanitize=thread" in thread and "-fsanitize=thread" in thread_link
    assert "-O3" not in thread and "-flto=auto" not in thread and "-g" in thread
    address, address_link = builder_args(monkeypatch, "address")
    assert "-fsanitize=address,undefined,float-cast-overflow" in address
    assert "-fsanitize-recover=address" in address
    assert address_link == ["-fsanitize=address,undefined,float-cast-overflow"]


def test_an_unknown_sanitizer_is_one_line_naming_the_choices():
    env = dict(os.environ, DCT_HIL_SANITIZE="memory")
    p = subprocess.run([sys.executable, BUILDER], env=env, capture_output=True, text=True)
    assert p.returncode != 0
    assert p.stderr.strip() == "DCT_HIL_SANITIZE must be one of thread, address, got 'memory'"


TSAN_LOG = """\
==================
WARNING: ThreadSanitizer: data race (pid=18449)
  Write of size 4 at 0x7f19ba6fe0bc by thread T17:
    #0 rt_loop_run rt_loop/csrc/rt_loop.c:335 (_rt_loop.abi3.so+0x11a38)
    #1 _cffi_f_rt_loop_run build/rt_loop._rt_loop.c:8576 (_rt_loop.abi3.so+0x1d9b1)

  Previous read of size 8 at 0x7f19ba6fe0b8 by main thread:
    #0 memcpy sanitizer_common_interceptors.inc:827 (libtsan.so.2.0.0+0x5dda6)
SUMMARY: ThreadSanitizer: data race rt_loop/csrc/rt_loop.c:335 in rt_loop_run
==================
==================
WARNING: ThreadSanitizer: data race (pid=18449)
  Write of size 4 at 0x7f19ba6fe0bc by thread T17:
    #0 rt_loop_run rt_loop/csrc/rt_loop.c:335 (_rt_loop.abi3.so+0x11a38)
==================
"""

ASAN_LOG = """\
=================================================================
==77==ERROR: AddressSanitizer: heap-buffer-overflow on address 0x602000000018 at pc 0x7f
READ of size 8 at 0x602000000018 thread T3
    #0 0x7f1 in can_decode can_dbc/csrc/can_table.c:210
    #1 0x7f2 in rt_rx_drain rt_loop/csrc/rt_rx.c:99
rt_loop/csrc/rt_tx.c:120:17: runtime error: 1e+300 is outside the range of representable values of type 'int'
    #0 0x7f3 in encode_signal rt_loop/csrc/rt_tx.c:120
"""


def test_reports_are_counted_with_their_kind_and_first_frame():
    r = sr.parse_reports(TSAN_LOG)
    assert len(r) == 2
    assert r[0] == {"sanitizer": "TSan", "what": "data race",
                    "first_frame": "rt_loop_run rt_loop/csrc/rt_loop.c:335 (_rt_loop.abi3.so+0x11a38)"}
    distinct = sr.summarize(r)
    assert len(distinct) == 1 and distinct[0]["count"] == 2
    a = sr.parse_reports(ASAN_LOG)
    assert [(x["sanitizer"], x["what"]) for x in a] == [
        ("ASan", "heap-buffer-overflow"),
        ("UBSan", "1e+300 is outside the range of representable values of type 'int'")]
    assert a[0]["first_frame"] == "can_decode can_dbc/csrc/can_table.c:210"
    assert a[1]["first_frame"] == "rt_loop/csrc/rt_tx.c:120:17"
    assert sr.parse_reports("nothing to see\n") == []


def test_the_runs_environment_preloads_the_runtime_and_logs_beside_the_figures(tmp_path):
    for kind in sr.KINDS:
        try:
            env = sr.sanitizer_env(kind, tmp_path / "lib", tmp_path)
        except sr.SanitizeError as e:           # a compiler without the runtime: one line
            assert "apt-get install" in str(e)
            continue
        assert env["PYTHONPATH"].split(os.pathsep)[0] == str(tmp_path / "lib")
        assert os.path.exists(env["LD_PRELOAD"])
        opts = env["TSAN_OPTIONS" if kind == "thread" else "ASAN_OPTIONS"]
        assert "halt_on_error=0" in opts and f"log_path={tmp_path}/log" in opts
    supp = (tmp_path / "tsan.supp").read_text()
    rules = [ln for ln in supp.splitlines() if ln and not ln.startswith("#")]
    assert rules == ["race:PyBytes_FromStringAndSize"]       # Python's own code only


@pytest.mark.parametrize("argv, message", [
    (["--short", "--seconds", "5"], "--short sets the length itself"),
    (["--json", "x.json"], "--json names one file"),
])
def test_bad_arguments_are_one_line(capsys, argv, message):
    assert sr.main(argv) == 2
    assert message in capsys.readouterr().err
