"""A lean server process: ``dct-hil serve`` locks all its memory (mlockall), so what it
loads and maps it holds resident. python-can without asammdf until MF4 is asked for
(``can_dbc.python_can``), and the resident memory of a plain ``serve`` read from /proc
while its loop runs (docs/server.md, "Memory")."""

import subprocess
import sys
import textwrap

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
