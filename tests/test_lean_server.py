"""A lean server process: ``dct-hil serve`` locks all its memory (mlockall), so what it
loads and maps it holds resident. python-can without asammdf until MF4 is asked for
(``can_dbc.python_can``), and the resident memory of a plain ``serve`` read from /proc
while its loop runs (docs/server.md, "Memory")."""

import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest
import requires


def _python(code: str) -> str:
    """Runs ``code`` in a fresh interpreter (nothing imported yet); its stdout."""
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_python_can_leaves_asammdf_out_until_mf4_is_asked_for(tmp_path):
    requires.module("asammdf")                     # the mdf extra: what would be dragged in
    out = _python(f"""
        import sys
        from can_dbc.python_can import python_can
        from can_dbc import codec
        can = python_can()
        codec.database()                           # cantools imports can too
        print("before", sorted(m for m in ("asammdf", "pandas", "pyarrow", "lxml")
                                if m in sys.modules))
        assert can.io.mf4.asammdf is None
        import asammdf                             # a recording asks for it: works as ever
        assert can.io.mf4.asammdf is asammdf       # and python-can's MF4 classes have it
        path = {str(tmp_path / "log.mf4")!r}
        w = can.Logger(path)
        w.on_message_received(can.Message(arbitration_id=0x80, data=b"\\x01\\x02"))
        w.stop()
        print("read", [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(path)])
    """)
    assert "before []" in out
    assert "read [(128, b'\\x01\\x02')]" in out


def test_python_can_mf4_imports_asammdf_first(tmp_path):
    requires.module("asammdf")
    out = _python("""
        import sys
        from can_dbc.python_can import python_can
        can = python_can(mf4=True)
        print("mf4", can.io.mf4.asammdf is sys.modules["asammdf"])
    """)
    assert "mf4 True" in out


#: the bound of issue 26: a plain serve (the contract, no options) resident in MB
SERVE_RSS_LIMIT_MB = 150.0


def _status_kb(pid: int) -> dict:
    out = {}
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmLck", "VmHWM"):
                out[key] = int(value.split()[0])
    return out


def _may_lock() -> bool:
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    return os.geteuid() == 0 or soft == resource.RLIM_INFINITY


@pytest.mark.slow
def test_a_plain_serve_holds_at_most_150_mb_while_its_loop_runs(tmp_path):
    """``dct-hil serve`` with the contract and no options (priority 80 with mlockall, as
    a user starts it): VmRSS read from /proc while the loop runs, and no asammdf,
    pandas or pyarrow mapped into the process."""
    proc = subprocess.Popen([sys.executable, "-m", "dct_hil.cli", "serve"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    try:
        line = proc.stdout.readline()
        assert line.startswith("dct-hil serve"), line + proc.stderr.read()
        while not (line.startswith("t=") and not line.startswith("t=0.0s")):
            line = proc.stdout.readline()      # a status line after the first: the loop runs
            assert line, proc.stderr.read()
        mem = _status_kb(proc.pid)
        with open(f"/proc/{proc.pid}/maps", encoding="ascii") as f:
            maps = f.read()
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode in (0, 1), err            # 1: no CAN interface in the guest
    if _may_lock():
        assert mem["VmLck"] > 0, (mem, out)          # the memory is locked: the case that counts
    assert mem["VmRSS"] <= SERVE_RSS_LIMIT_MB * 1024, mem
    for lib in ("/asammdf/", "/pandas/", "/pyarrow/", "/lxml/", "/numexpr/"):
        assert lib not in maps, f"{lib} is mapped into a plain serve"
    report = json.loads((tmp_path / "out" / "serve-stats.json").read_text())
    assert report["run"]["start_to_first_tick_s"] > 0
    assert report["memory"]["vm_rss_mb"] <= SERVE_RSS_LIMIT_MB
    assert "start-up          first tick" in out
