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


# ------------------------------------------------------------ (b) out-of-range values offline

VEHICLE = M.find_mapping("vehicle")
VEHICLE_PT = os.path.join(M.MAPPINGS_DIR, "..", "matrices", "vehicle_pt.dbc")


def _unsigned_torque_dbc(tmp_path):
    """The example pt matrix with the engine's torque as an unsigned signal (as a
    production matrix had it): 0 .. 409.5 %."""
    text = open(VEHICLE_PT, encoding="utf-8").read()
    old = 'SG_ EngTorqueActual : 12|12@1- (0.1,0) [-204.8|204.7] "%"'
    assert old in text
    path = tmp_path / "pt_unsigned.dbc"
    path.write_text(text.replace(old, 'SG_ EngTorqueActual : 12|12@1+ (0.1,0) [0|409.5] "%"'),
                    encoding="utf-8")
    return str(path)


def test_a_negative_value_into_an_unsigned_signal_offline_saturates_as_the_loop_does_and_is_counted(tmp_path):
    from can_dbc.table import CodecTable
    from plant.model import Plant
    from tcu_stub.mapped_link import MappedLink

    m = M.load_options(VEHICLE, [f"pt={_unsigned_torque_dbc(tmp_path)}"])
    link = MappedLink(m)
    plant = Plant()
    out = plant.outputs.copy()
    out["engine_torque_nm"] = -40.0                 # overrun: the engine drags
    view = link.sensors(out, 0)                     # no OverflowError
    assert view["EngineTorque"] == 0.0               # limited to the signal's minimum, 0 %
    assert link.saturated == {"pt:ECM_Torque.EngTorqueActual": 1}
    # the real-time codec (the loop's table) sends the same frame for the same values
    msg = m.message("ECM_Torque")
    table = CodecTable([(msg.message, msg.protection)])
    values = {"EngTorqueActual": -40.0 / 280.0 * 100.0}
    assert table.decode(0, table.encode(0, values))["EngTorqueActual"] == 0.0
    assert table.saturated(0, values) == ["EngTorqueActual"]
    assert table.saturated(0, {"EngTorqueActual": 50.0}) == []
    # above the range too, and into the raw field of a signal without a range
    out["engine_torque_nm"] = 2000.0
    link.refresh(out, [("pt", "ECM_Torque")])
    assert link.view()["EngineTorque"] == pytest.approx(409.5 / 100 * 280, abs=0.3)
    assert link.saturated == {"pt:ECM_Torque.EngTorqueActual": 2}


def test_simulate_through_a_matrix_with_an_unsigned_torque_runs_and_reports_the_saturated_values(tmp_path, capsys):
    code, out, err = run_cli(capsys, "simulate", "--scenario", "paper-cycle",
                             "--mapping", VEHICLE, "--dbc", f"pt={_unsigned_torque_dbc(tmp_path)}")
    assert code == 0, err
    line = [x for x in out.splitlines() if x.startswith("saturated")]
    assert len(line) == 1, out
    assert "pt:ECM_Torque.EngTorqueActual" in line[0], line


# ------------------------------------------------------------ (c) a lower-case multiplexer

MUX_TOML = os.path.join(DATA, "mux_lower.toml")


@pytest.mark.parametrize("argv", [
    ["mapping", "check", MUX_TOML],
    ["mapping", "show", MUX_TOML],
    ["simulate", "--scenario", "paper-cycle", "--duration", "1", "--mapping", MUX_TOML],
    ["serve", "--mapping", MUX_TOML, "--interface", "virtual", "--channel", "mux-test", "--duration", "1"],
    ["demo", "--mapping", MUX_TOML],
    ["tcu", "--mapping", MUX_TOML, "--interface", "virtual", "--channel", "mux-test"],
])
def test_a_lower_case_multiplexer_is_refused_by_every_command_in_the_same_line(argv, capsys):
    """Info_Mux is written "m" (not "M") in its SG_ line while SG_MUL_VAL_ makes it the
    switch of Oeltemp and Kuehltemp: the loader judges it once, for every command."""
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, (out, err)
    lines = err.splitlines()
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith(("dct-hil: error: ", "dct-hil tcu: error: ")), err
    for words in ("mux_lower.dbc", "bus pt", "message Motor_Info", "Info_Mux", "'M'",
                  "Oeltemp, Kuehltemp", 'direction = "ignore"'):
        assert words in line, (words, line)


# ------------------------------------------------------------ (d) a unit the unit table does not know

def test_an_unknown_dbc_unit_without_a_mapping_unit_is_a_warning_naming_both(prod, capsys):
    """Moment_MDI's DBC unit "MDI" is no unit the table knows; mapped to the
    engine torque (Nm) without ``unit``, the value goes as it is: a warning in
    ``mapping check`` naming both units; none with a factor or without the entry."""
    path = prod("prod_pt.toml", 'Motormoment = { output = "engine_torque_nm" }',
                'Motormoment = { output = "engine_torque_nm" }\n'
                'Moment_MDI = { output = "engine_torque_nm" }')
    m = M.load(path)
    assert len(m.warnings) == 1 and "'MDI'" in m.warnings[0] and "'Nm'" in m.warnings[0]
    assert "Moment_MDI" in m.warnings[0] and "\n" not in m.warnings[0]
    code, out, err = run_cli(capsys, "mapping", "check", path)
    assert code == 0 and "warning:" in out and "'MDI'" in out and "'Nm'" in out, out
    with_factor = prod("prod_pt.toml", 'Moment_MDI = { output = "engine_torque_nm" }',
                       'Moment_MDI = { output = "engine_torque_nm", factor = 0.35 }')
    assert M.load(with_factor).warnings == ()
    assert M.load(PT_TOML).warnings == ()
