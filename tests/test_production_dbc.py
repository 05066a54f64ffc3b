"""What a production DBC found (issue 27, item 4), one test a finding, on the small
matrices of tests/data/production/ (written for these tests: a production-like
powertrain matrix with a UTF-8 degree sign, an unsigned torque signal, a unit the
unit table does not know)."""

import os
import re
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


# ------------------------------------------------------------ (f) one port per udp_multicast bus

def test_each_udp_multicast_bus_gets_a_port_of_its_own():
    from can_dbc import channels as C

    m = M.load(M.find_mapping("vehicle"))
    # derived: the next group on the next port (the first bus keeps python-can's port, or the
    # one given in the channel or as the bus option)
    assert m.channels("239.74.163.2") == {"pt": "239.74.163.2", "io": "239.74.163.3:43114"}
    assert m.channels("239.9.9.9:40000") == {"pt": "239.9.9.9:40000", "io": "239.9.9.10:40001"}
    # named without a port: python-can's port + the bus's index; with one: as given
    assert m.channels("239.9.9.9", {"io": "239.1.1.1"}) == {"pt": "239.9.9.9", "io": "239.1.1.1:43114"}
    assert m.channels("239.9.9.9", {"io": "[ff15::1]:7"})["io"] == "[ff15::1]:7"
    # two buses on one port would hear each other's frames: refused in one line
    with pytest.raises(M.MappingError, match=r"buses 'pt' and 'io' are both on udp_multicast port 43114"
                                             r".*--bus io=239.2.2.2:43115"):
        m.channels("239.9.9.9:43114", {"io": "239.2.2.2"})
    # what python-can gets: the group as channel, the port as its option
    assert C.bus_arguments("udp_multicast", "239.9.9.9:40000") == ("239.9.9.9", {"port": 40000})
    assert C.bus_arguments("udp_multicast", "[ff15::1]:7", fd=True) == ("ff15::1", {"port": 7, "fd": True})
    assert C.bus_arguments("udp_multicast", "239.9.9.9", port=5) == ("239.9.9.9", {"port": 5})
    assert C.bus_arguments("virtual", "239.9.9.9:1") == ("239.9.9.9:1", {})
    for bad, words in (("10.0.0.1", "not a multicast group"), ("239.1.1.1:0", "port '0' is not 1..65535"),
                       ("239.1.1.1:x", "port 'x'"), ("[ff15::1", "[IPv6 GROUP]:PORT")):
        with pytest.raises(C.ChannelError, match=re.escape(words)):
            C.split_udp(bad)


def test_two_udp_multicast_buses_do_not_hear_each_other(udp_group):
    """The vehicle matrix's pt and io buses on udp_multicast (io derived): the
    plant and the TCU get only their own bus's frames, none of the other's as an
    unknown identifier (on one shared port every frame of one bus reached the other)."""
    from waiting import wait_until

    from rt_loop.server import Server
    from tcu_stub.can_tcu import CanTcu

    group, port = udp_group
    channel = f"{group}:{port}"
    m = M.load(M.find_mapping("vehicle"))
    srv = Server(channel, interface="udp_multicast", priority=0, mapping=m)
    try:
        srv.start()
        assert srv.bus_channels["io"].endswith(f":{port + 1}")
        with CanTcu.open("udp_multicast", channel, mapping=m) as tcu:
            assert wait_until(lambda: srv.snapshot()["counts"]["rx"]["accepted"] >= 1000, timeout=20)
            rep = tcu.report()
        rx = srv.report(histograms=False)["counts"]["rx"]
    finally:
        srv.stop()
    assert rx["unknown_id"] == 0 and rx["rejected"] == 0, rx
    assert rep["unknown_frames"] == 0, rep["buses"]
    assert {b: x["unknown_frames"] for b, x in rep["buses"].items()} == {"pt": 0, "io": 0}
    assert rep["buses"]["io"]["channel"] == srv.bus_channels["io"]


# ------------------------------------------------------------ (g) a missing --channel

def test_a_missing_channel_is_the_interfaces_default_or_one_line_saying_what_to_give(monkeypatch):
    from can_dbc import channels as C
    from can_dbc.python_can import python_can

    assert C.default_channel(None) == "vcan0" and C.default_channel("socketcan") == "vcan0"
    assert C.default_channel("virtual") == "vcan0"
    assert C.default_channel("udp_multicast") == "239.74.163.2"
    can = python_can()
    found = {"pcan": [], "kvaser": [{"interface": "kvaser", "channel": 0}],
             "ixxat": [{"channel": 0}, {"channel": 1}]}
    monkeypatch.setattr(can, "detect_available_configs", lambda interfaces: found[interfaces[0]])
    assert C.default_channel("kvaser") == "0"
    with pytest.raises(C.ChannelError, match=r"^interface ixxat: give --channel, one of 0, 1"):
        C.default_channel("ixxat")
    with pytest.raises(C.ChannelError, match=r"^interface pcan: give --channel .*found none"):
        C.default_channel("pcan")


@pytest.mark.parametrize("command", ["serve", "tcu"])
def test_serve_and_tcu_without_channel_on_udp_multicast_use_its_group(command, capsys):
    """Neither tries vcan0 as a multicast group: the bus opens on python-can's group."""
    argv = [command, "--interface", "udp_multicast", "--duration", "0.3", "--priority", "0"]
    if command == "serve":
        argv += ["--stats", os.devnull, "--quiet"]
    else:
        argv += ["--quiet"]
    code, out, err = run_cli(capsys, *argv)
    assert "Name or service not known" not in err and "vcan0" not in err
    assert code == 0, err


def test_a_channel_that_is_no_multicast_group_is_one_line(capsys):
    code, out, err = run_cli(capsys, "serve", "--interface", "udp_multicast", "--channel", "10.1.2.3",
                             "--duration", "0.2", "--priority", "0", "--stats", os.devnull)
    assert code == 2, err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "10.1.2.3" in lines[0] and "not a multicast group" in lines[0], err


# ------------------------------------------------------------ (e) shifts as the CSV shows them

def test_the_simulate_report_counts_the_shifts_its_csv_shows(tmp_path, capsys):
    import numpy as np

    from plant.maneuvers import gear_shifts

    out = tmp_path / "run.csv"
    code, text, err = run_cli(capsys, "simulate", "--scenario", "paper-cycle", "--out", out)
    assert code == 0, err
    line = next(x for x in text.splitlines() if x.startswith("report"))
    reported = int(re.search(r"shifts = (\d+) \(the gear column; the TCU started (\d+)\)", line).group(1))
    names = out.read_text().splitlines()[0].split(",")
    data = np.loadtxt(out, delimiter=",", skiprows=1, usecols=(names.index("time_s"), names.index("gear")))
    assert reported == len(gear_shifts(data[:, 0], data[:, 1])) > 3


def test_a_gear_held_exactly_the_hold_counts_the_same_in_the_run_and_its_csv():
    """A gear held 0.1 s (the hold) in 10 ms records: the run's times and the CSV's
    printed ones differ by rounding (up to 0.2 us); both count the shift."""
    import numpy as np

    from plant.maneuvers import SHIFT_MIN_HOLD_S, gear_shifts

    t = np.arange(0, 100) * 0.01
    gear = np.where(t < 0.3, 1, np.where(t < 0.3 + SHIFT_MIN_HOLD_S + 0.005, 2, 3))
    for jitter in (0.0, -2e-7, 2e-7):
        tt = t.copy()
        tt[30:] += jitter                       # the first sample of gear 2 printed late or early
        tt[40] -= jitter                        # its last one the other way
        assert [(a, b) for _, a, b in gear_shifts(tt, gear)] == [(1, 2), (2, 3)], jitter
    # a gear held one sample less is no shift
    gear_short = np.where(t < 0.3, 1, np.where(t < 0.3 + SHIFT_MIN_HOLD_S - 0.005, 2, 3))
    assert [(a, b) for _, a, b in gear_shifts(t, gear_short)] == [(1, 3)]


# ------------------------------------------------------------ saturation counted on every path

def test_the_c_codec_counts_what_it_limits_as_the_python_check_names_it():
    """ct_encode_counted (the loop's and the C node's encoder) counts the values
    CodecTable.saturated names, for random values in and out of every signal's
    range and bit field, on both shipped matrices and the production one."""
    import random

    from can_dbc.table import CodecTable

    rnd = random.Random(27)
    checked = 0
    for path in (M.find_mapping("vehicle"), M.find_mapping("dct_hil"), PT_TOML):
        m = M.load(path)
        for bus in m.buses:
            table = CodecTable([(x.message, x.protection) for x in m.codec_order(bus.name)])
            for i, msg in enumerate(table.messages):
                sigs = msg.signals
                for _ in range(40):
                    values = {}
                    for s in sigs:
                        lo = s.minimum if s.minimum is not None else -1000.0
                        hi = s.maximum if s.maximum is not None else 1000.0
                        span = max(hi - lo, 1.0)
                        values[s.name] = rnd.choice([lo, hi, rnd.uniform(lo, hi), lo - rnd.uniform(0, span),
                                                     hi + rnd.uniform(0, span), -abs(rnd.uniform(1, 1e6)),
                                                     float("nan")])
                    arr = table.ffi.new("double[]", len(sigs))
                    for k, s in enumerate(sigs):
                        arr[k] = values[s.name]
                    data = table.ffi.new("uint8_t[]", 64)
                    count = table.ffi.new("uint32_t *", 0)
                    table.lib.ct_encode_counted(table.table, i, arr, data, count)
                    expected = table.saturated(i, values)
                    assert count[0] == len(expected), (msg.name, values, expected)
                    checked += bool(expected)
    assert checked > 100


def _vehicle_narrowed(tmp_path, old, new):
    """The vehicle matrix (a copy in tmp_path) with one signal line of vehicle_pt.dbc replaced."""
    root = os.path.dirname(M.find_mapping("vehicle"))
    (tmp_path / "mappings").mkdir()
    (tmp_path / "matrices").mkdir()
    shutil.copy(os.path.join(root, "vehicle.toml"), tmp_path / "mappings" / "vehicle.toml")
    for name in ("vehicle_pt.dbc", "vehicle_io.dbc"):
        shutil.copy(os.path.join(root, "..", "matrices", name), tmp_path / "matrices" / name)
    dbc = tmp_path / "matrices" / "vehicle_pt.dbc"
    text = dbc.read_text()
    assert old in text
    dbc.write_text(text.replace(old, new))
    return M.load(str(tmp_path / "mappings" / "vehicle.toml"))


@pytest.fixture
def narrow_torque_request(tmp_path):
    """TCU_TorqueReq.TrqReqValue limited to 10..204.7 %: the reference TCU's 0 % (no
    request, at the start and while it has no plant) is out of range."""
    return _vehicle_narrowed(tmp_path, 'SG_ TrqReqValue : 12|12@1- (0.1,0) [-204.8|204.7] "%"',
                             'SG_ TrqReqValue : 12|12@1- (0.1,0) [10|204.7] "%"')


@pytest.mark.parametrize("impl", ["python", "c"])
def test_the_tcu_nodes_count_the_values_their_codec_limits(impl, narrow_torque_request):
    import time

    from tcu_stub.c_node import CTcuNode
    from tcu_stub.can_tcu import CanTcu

    opener = CanTcu.open if impl == "python" else CTcuNode.open
    kw = {} if impl == "python" else {"priority": 0}
    with opener("virtual", f"saturated-{impl}", mapping=narrow_torque_request, **kw) as tcu:
        deadline = time.monotonic() + 10
        while tcu.report()["sent"]["pt:TCU_TorqueReq"]["frames"] < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
    rep = tcu.report()
    req = rep["sent"]["pt:TCU_TorqueReq"]
    assert req["frames"] >= 20
    assert req["saturated"] == req["frames"]                 # its 0 % went out as 10 % in every frame
    assert rep["saturated"] == sum(s["saturated"] for s in rep["sent"].values()) == req["frames"]


def test_the_contract_peer_counts_the_values_its_encoder_limits():
    from can_dbc.peer import CanPeer

    with CanPeer.open(side="tcu", interface="virtual", channel="saturated-peer", send_thread=False) as peer:
        assert peer.send_now("TCU_ClutchCmd", {"SolenoidCurrent1": 0.5})
        assert peer.report()["sent"]["TCU_ClutchCmd"]["saturated"] == 0
        assert peer.send_now("TCU_ClutchCmd", {"SolenoidCurrent1": 99.0, "SolenoidCurrent2": -5.0})
        assert peer.send_now("TCU_ClutchCmd")
        rep = peer.report()["sent"]["TCU_ClutchCmd"]
    assert rep["frames"] == 3 and rep["saturated"] == 4


def test_the_loop_counts_the_values_its_codec_limits(tmp_path):
    """ECM_Speed.EngineSpeed limited to 1000..16383.75 rpm: the idling engine's 750 rpm
    goes out as 1000 rpm in every frame the loop makes, each counted."""
    import time

    from rt_loop.server import Server
    from rt_loop.status import summary_lines

    m = _vehicle_narrowed(tmp_path, 'SG_ EngineSpeed : 0|16@1+ (0.25,0) [0|16383.75] "rpm"',
                          'SG_ EngineSpeed : 0|16@1+ (0.25,0) [1000|16383.75] "rpm"')
    srv = Server("saturated-loop", interface="virtual", priority=0, mapping=m)
    try:
        srv.start()
        deadline = time.monotonic() + 10
        while srv.snapshot()["counts"]["plant_messages"]["pt:ECM_Speed"]["sent"] < 20 \
                and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        srv.stop()
    report = srv.report(histograms=False)
    c = report["counts"]
    speed = c["plant_messages"]["pt:ECM_Speed"]
    assert speed["sent"] >= 20 and speed["dropped"] == 0
    assert speed["saturated"] == speed["sent"]
    assert c["tx"]["saturated"] == speed["saturated"]           # nothing else out of range
    assert all(x["saturated"] == 0 for n, x in c["plant_messages"].items() if n != "pt:ECM_Speed")
    line = next(x for x in summary_lines(report, "stats.json") if x.startswith("sent"))
    assert f"{speed['saturated']} values saturated" in line and "pt:ECM_Speed" in line
