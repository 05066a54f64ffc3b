"""What a production DBC found (issue 27, item 4), one test a finding, on the small
matrices of tests/data/production/ (written for these tests: a production-like
powertrain matrix with a UTF-8 degree sign, an unsigned torque signal, a unit the
unit table does not know)."""

import os
import shutil

import pytest

from can_dbc import codec
from can_dbc import mapping as M
from dct_hil import cli

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "production")
PT_TOML = os.path.join(DATA, "prod_pt.toml")


def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def prod(tmp_path):
    """A copy of tests/data/production in tmp_path: edit(name, old, new) -> path."""
    for name in os.listdir(DATA):
        shutil.copy(os.path.join(DATA, name), tmp_path / name)

    def edit(name, old=None, new=None):
        path = tmp_path / name
        if old is not None:
            text = path.read_text(encoding="utf-8")
            assert old in text, old
            path.write_text(text.replace(old, new), encoding="utf-8")
        return str(path)
    return edit


# ------------------------------------------------------------ (a) the DBC's text encoding

def test_a_utf8_dbc_is_read_as_utf8_and_any_other_as_cp1252(prod, capsys):
    with open(os.path.join(DATA, "prod_pt.dbc"), "rb") as f:
        assert "°C".encode() in f.read()                       # the file is UTF-8
    code, out, err = run_cli(capsys, "mapping", "show", PT_TOML)
    assert code == 0, err
    assert "°C" in out and "Â" not in out
    m = M.load(PT_TOML)
    assert m.message("Motor_1").signal("Temperatur").signal.unit == "°C"
    # the same matrix in cp1252 (a byte 0xB0 for the degree sign): read as cp1252
    cp = prod("prod_pt.toml", 'dbc = "prod_pt.dbc"', 'dbc = "prod_pt_cp1252.dbc"')
    with open(os.path.join(DATA, "prod_pt_cp1252.dbc"), "rb") as f:
        assert b"\xb0C" in f.read() and "°C".encode() not in f.read()
    assert M.load(cp).message("Motor_1").signal("Temperatur").signal.unit == "°C"
    # the strict reader of the project's contract decodes the same way
    assert codec.load_database(os.path.join(DATA, "prod_pt.dbc")).get_message_by_name(
        "Motor_1").get_signal_by_name("Temperatur").unit == "°C"
    assert M.dbc_encoding(os.path.join(DATA, "prod_pt.dbc")) == "utf-8"
    assert M.dbc_encoding(os.path.join(DATA, "prod_pt_cp1252.dbc")) == "cp1252"
