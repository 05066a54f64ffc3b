"""Bad input to the dct-hil command line: one line, exit 2, never a traceback."""

from dct_hil.cli import main


def one_line_error(capsys, argv):
    """Runs ``dct-hil argv`` in this process; asserts exit 2 and a single
    ``dct-hil: error:`` line on stderr, and returns that line."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: "), err
    assert "Traceback" not in err
    return lines[0]
