"""The live bench view without a browser: addresses and their errors, the
token, the command line's refusals (before anything starts), what the
panels show (dct_hil.ui.figures), and bad control input from the page
refused with nothing changed."""

import math
import os
import socket
import threading

import numpy as np
import pytest

from dct_hil.cli import main
from dct_hil.ui import figures as fg
from dct_hil.ui.server import (
    UiError,
    UiServer,
    check_token,
    is_loopback,
    origins_for,
    parse_address,
    read_token_file,
)

# ---------------------------------------------------------------- addresses


@pytest.mark.parametrize("text, expected", [
    ("5006", ("127.0.0.1", 5006)),
    ("0", ("127.0.0.1", 0)),
    ("0.0.0.0:8080", ("0.0.0.0", 8080)),
    ("localhost:80", ("localhost", 80)),
    (" bench-pc:65535 ", ("bench-pc", 65535)),
])
def test_parse_address(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize("text, says", [
    ("1.2.3.4:99999", "port 99999 is outside 0..65535"),
    ("abc", "port 'abc' is not a number"),
    (":8080", "the host before ':' is empty"),
    ("host:", "port '' is not a number"),
    ("[::1]:8080", "IPv6"),
    ("::1", "IPv6"),
    ("", "give [HOST:]PORT"),
    ("a/b:80", "is not a host name or address"),
])
def test_bad_addresses_are_one_line_errors(text, says):
    with pytest.raises(UiError) as e:
        parse_address(text)
    assert says in str(e.value) and "\n" not in str(e.value)


def test_loopback_and_origins():
    assert is_loopback("127.0.0.1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    assert set(origins_for("127.0.0.1", 5006)) == {"127.0.0.1:5006", "localhost:5006"}
    assert origins_for("10.1.2.3", 80) == ["10.1.2.3:80"]
    wild = origins_for("0.0.0.0", 5006)
    assert socket.gethostname().lower() + ":5006" in wild and "0.0.0.0:5006" not in wild


def test_tokens(tmp_path):
    assert check_token("s3cret-token") == "s3cret-token"
    for bad, says in (("short", "at least 8"), ("has a space", "no spaces"), ("", "give a")):
        with pytest.raises(UiError, match=says):
            check_token(bad)
    f = tmp_path / "token"
    f.write_text("from-a-file-123\nignored\n")
    assert read_token_file(f) == "from-a-file-123"
    f.write_text("short\n")
    with pytest.raises(UiError, match=r"--ui-token-file .*at least 8"):
        read_token_file(f)
    with pytest.raises(UiError, match="No such file"):
        read_token_file(tmp_path / "missing")


class _FakeServer:
    pass


def test_ui_beyond_loopback_needs_a_token():
    with pytest.raises(UiError, match="beyond loopback needs --ui-token"):
        UiServer(_FakeServer(), ("0.0.0.0", 5006))
    ui = UiServer(_FakeServer(), ("0.0.0.0", 5006), token="long-enough-token")
    assert not ui.loopback and ui.token_ok("long-enough-token") and not ui.token_ok("nope")
    assert not ui.token_ok(None)


@pytest.mark.slow
def test_a_port_in_use_is_refused_and_nothing_is_left_running():
    from rt_loop.server import Server

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        server = Server(f"ui-{os.getpid()}", interface="virtual", priority=0)
        ui = UiServer(server, ("127.0.0.1", port))
        with pytest.raises(UiError, match=f"UI on 127.0.0.1:{port}: Address already in use"):
            ui.start()
    assert not any(t.name == "ui-bokeh" for t in threading.enumerate())
    assert not server.running


# ---------------------------------------------------------------- the command line


@pytest.mark.parametrize("args, says", [
    (["--ui", "nosuchhost.invalid:8080"], "host 'nosuchhost.invalid' does not resolve"),
    (["--ui", "1.2.3.4:99999"], "port 99999 is outside 0..65535"),
    (["--ui", "0.0.0.0:8080"], "binding beyond loopback needs --ui-token"),
    (["--ui", "1.2.3.4:8080", "--ui-token", "long-enough-1"], "Cannot assign requested address"),
    (["--ui-token", "long-enough-1"], "--ui-token and --ui-token-file need --ui"),
    (["--ui", "5006", "--ui-token", "short"], "at least 8 characters"),
])
def test_serve_ui_errors_exit_2_with_one_line(args, says, capsys, tmp_path):
    code = main(["serve", "--interface", "virtual", "--channel", f"ui-cli-{os.getpid()}",
                 "--priority", "0", "--duration", "1", "--quiet",
                 "--stats", str(tmp_path / "s.json"), *args])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: ") and says in lines[0], err
    assert not (tmp_path / "s.json").exists()           # the server never ran


def test_serve_ui_port_in_use_exits_2_before_the_loop(capsys, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        code = main(["serve", "--interface", "virtual", "--channel", f"ui-cli-{os.getpid()}",
                     "--priority", "0", "--duration", "1", "--quiet",
                     "--stats", str(tmp_path / "s.json"), "--ui", str(port)])
    err = capsys.readouterr().err
    assert code == 2 and f"UI on 127.0.0.1:{port}: Address already in use" in err
    assert not (tmp_path / "s.json").exists()


def test_demo_ui_errors_exit_2(capsys, tmp_path):
    code = main(["demo", "--out", str(tmp_path), "--ui", "0.0.0.0:8080"])
    assert code == 2 and "beyond loopback" in capsys.readouterr().err
    args = __import__("dct_hil.cli", fromlist=["build_parser"]).build_parser().parse_args(
        ["demo", "--ui"])
    assert args.ui == "127.0.0.1:5006"


@pytest.mark.slow
def test_serve_ui_runs_with_the_server_and_stops_first(capsys, tmp_path):
    """serve --ui: the page is up while the loop runs and gone when serve returns."""
    import urllib.request

    from dct_hil.ui import server as ui_server

    seen = {}
    start = ui_server.UiServer.start

    def start_and_fetch(self):
        start(self)
        seen["ui"] = self

    ui_server.UiServer.start = start_and_fetch
    try:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        fetched = {}

        def fetch():
            import time
            deadline = time.monotonic() + 20
            while "ui" not in seen and time.monotonic() < deadline:
                time.sleep(0.05)
            while time.monotonic() < deadline:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as r:
                        fetched["status"] = r.status
                        fetched["running"] = seen["ui"].server.running
                        return
                except OSError:
                    time.sleep(0.1)

        t = threading.Thread(target=fetch)
        t.start()
        code = main(["serve", "--interface", "virtual", "--channel", f"ui-run-{os.getpid()}",
                     "--priority", "0", "--duration", "3", "--quiet",
                     "--stats", str(tmp_path / "s.json"), "--ui", str(port)])
        t.join()
    finally:
        ui_server.UiServer.start = start
    out = capsys.readouterr().out
    assert code == 0 and f"live view         http://127.0.0.1:{port}/" in out
    assert fetched == {"status": 200, "running": True}
    ui = seen["ui"]
    assert ui.frozen and not ui._thread.is_alive()
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2)


# ---------------------------------------------------------------- figures


def test_min_max_merger_keeps_a_spike_of_one_bucket():
    m = fg.MinMaxMerger(group_ticks=40)           # 4 buckets of 10 ticks
    ticks = np.arange(10, 130, 10)                # 12 buckets: groups end at 40, 80, 120
    values = np.zeros(len(ticks))
    values[5] = 7.0                               # one bucket's spike (ticks 51..60)
    out = m.feed(ticks, ticks * 0.0005, {"x": values - 1}, {"x": values + 1})
    assert list(out["tick"]) == [40, 80]          # the third group waits for a later bucket
    assert list(out["max"]["x"]) == [1.0, 8.0] and list(out["min"]["x"]) == [-1.0, -1.0]
    out = m.feed([130], [0.065], {"x": [0.0]}, {"x": [0.0]})
    assert list(out["tick"]) == [120] and list(out["max"]["x"]) == [1.0]
    out = m.feed([170, 180], [0.085, 0.09], {"x": [math.nan, 2.0]}, {"x": [math.nan, 2.5]})
    assert list(out["tick"]) == [130] and list(out["min"]["x"]) == [0.0]
    out = m.feed([210], [0.105], {"x": [0.0]}, {"x": [0.0]})
    assert list(out["tick"]) == [180] and list(out["min"]["x"]) == [2.0]   # NaN left out
    assert list(out["max"]["x"]) == [2.5]
    assert fg.MinMaxMerger(1).feed([10, 20], [0, 1], {"a": [1, 2]}, {"a": [3, 4]})["tick"].tolist() \
        == [10, 20]


def test_histogram_view():
    h = np.zeros(5000, dtype=np.uint64)
    h[[3, 4, 250]] = [10, 5, 1]
    v = fg.histogram_view(h, max_bars=100)            # 251 bins in groups of 3
    assert v == {"left": [3.0, 249.0], "right": [6.0, 252.0], "count": [15.0, 1.0],
                 "overflow": 0}
    assert all(c > 0 for c in v["count"])              # bars with samples only (log axis)
    h[-1] = 2                                          # above the last bin
    assert fg.histogram_view(h)["overflow"] == 2
    assert fg.histogram_view(np.zeros(10)) == {"left": [], "right": [], "count": [],
                                               "overflow": 0}
    small = fg.histogram_view(np.array([0, 3, 1] + [0] * 100))
    assert small["left"] == [1.0, 2.0] and small["right"] == [2.0, 3.0]


def test_timing_table_and_lines():
    from rt_loop.stats import hist_percentiles

    h = np.zeros(100, dtype=np.uint64)
    h[5], h[40] = 999, 1
    timing = {"turnaround": hist_percentiles(h, 40.5), "execution": hist_percentiles(h, 40.5),
              "wakeup_latency": hist_percentiles(h, 320.0)}
    t = fg.timing_table(timing)
    assert t["time"] == ["turnaround", "execution", "wake-up latency"]
    assert t["p50"][0] == "6" and t["p99_9"][0] == "6" and t["max"][0] == "40.5"
    assert t["samples"] == [1000, 1000, 1000]
    lines = fg.timing_lines(timing, {"overruns": 2, "skipped_ticks": 3, "ticks": 1000}, 500.0,
                            spin_us=100.0)
    assert lines[0] == "period 500 us, early wake-up 100 us"
    assert lines[1] == "overruns 2, skipped ticks 3, ticks 1000"
    assert "wake-up latency max 320.0 us (220.0 us past the early wake-up) = 44 % of the period"\
        in lines[2] and lines[2].endswith("within half the period")
    empty = fg.timing_table({})
    assert empty["p50"] == ["-", "-", "-"] and "no tick yet" in fg.timing_lines({}, {}, 500)[2]


def test_bus_rows():
    info = [fg.MessageInfo("DCT_Clutch", "can", "DCT_Clutch", "send", 2.0, False),
            fg.MessageInfo("TCU_ClutchCmd", "can", "TCU_ClutchCmd", "receive", 2.0, False),
            fg.MessageInfo("TCU_Status", "can", "TCU_Status", "receive", 10.0, True),
            fg.MessageInfo("TCU_ShiftCmd", "can", "TCU_ShiftCmd", "receive", 10.0, False)]
    counts = {"tcu_messages": {
        "TCU_ClutchCmd": {"accepted": 1000, "bad_length": 1, "bad_crc": 2, "bad_counter": 3,
                          "timeouts": 1, "timed_out": False},
        "TCU_Status": {"accepted": 0, "timeouts": 0, "timed_out": False},
        "TCU_ShiftCmd": {"accepted": 50, "timeouts": 2, "timed_out": True}},
        "plant_messages": {"DCT_Clutch": {"sent": 1200, "dropped": 0}}}
    cols, frames = fg.bus_rows(info, counts, None, 0.0)
    assert cols["message"] == ["TCU_ClutchCmd", "TCU_Status", "TCU_ShiftCmd", "DCT_Clutch"]
    assert cols["rate_hz"] == ["", "", "", ""] and cols["expected_hz"][0] == "500.0"
    assert cols["state"] == ["ok", "optional, none yet", "TIMED OUT", "ok"]
    assert (cols["bad_length"][0], cols["bad_crc"][0], cols["bad_counter"][0]) == ("1", "2", "3")
    assert cols["timed_out"] == ["no", "no", "yes", ""] and cols["dropped"][3] == "0"
    assert frames == {"TCU_ClutchCmd": 1000, "TCU_Status": 0, "TCU_ShiftCmd": 50,
                      "DCT_Clutch": 1200}
    counts["tcu_messages"]["TCU_ClutchCmd"]["accepted"] = 1300     # 300 in 1 s: low
    counts["plant_messages"]["DCT_Clutch"]["sent"] = 1700           # 500 in 1 s: ok
    cols, _ = fg.bus_rows(info, counts, frames, 1.0)
    assert cols["rate_hz"][0] == "300.0" and cols["state"][0] == "rate low"
    assert cols["rate_hz"][3] == "500.0" and cols["state"][3] == "ok"
    slow, _ = fg.bus_rows(info, counts, frames, 1.0, time_scale=0.5)
    assert slow["expected_hz"][3] == "250.0" and slow["state"][3] == "rate high"


def test_fault_spec_from_the_form():
    assert fg.fault_spec("can.omit", "message=VEH_Driver duration_s=2") == \
        {"kind": "can.omit", "message": "VEH_Driver", "duration_s": 2}
    assert fg.fault_spec("signal.hold", "signal=DCT_Clutch.ClutchPressure2 when=gear == 3 and "
                                        "vehicle_speed_kmh >= 30, start_s=1.5") == \
        {"kind": "signal.hold", "signal": "DCT_Clutch.ClutchPressure2",
         "when": "gear == 3 and vehicle_speed_kmh >= 30", "start_s": 1.5}
    assert fg.fault_spec("valve.spool_stuck", "clutch=1; sleeve=5-R") == \
        {"kind": "valve.spool_stuck", "clutch": 1, "sleeve": "5-R"}
    assert fg.fault_spec("x", '{"kind": "can.bad_crc", "message": "DCT_Clutch"}') == \
        {"kind": "can.bad_crc", "message": "DCT_Clutch"}
    assert fg.fault_spec("can.bus_off", "  ") == {"kind": "can.bus_off"}
    for bad, says in (("message", "is not NAME=VALUE"), ("{nope", "not a JSON object"),
                      ("[1]", "is not NAME=VALUE"), ("message=", "has no value")):
        with pytest.raises(ValueError, match=says):
            fg.fault_spec("can.omit", bad)


def test_instrument_items():
    items = dict((k, v) for k, _, v in fg.instrument_items({
        "vehicle_speed_kmh": 42.04, "gear": -1.0, "engine_speed_rpm": 2000.4,
        "clutch1_pressure_bar": -0.0, "clutch2_pressure_bar": 11.5, "tcu_phase": 2.0,
        "tcu_phase_choices": {2: "drive"}, "maneuver": "running", "maneuver_time_s": 3.25,
        "maneuver_name": "0-100", "state": "running", "sim_time_s": 12.5}))
    assert items == {"speed": "42.0 km/h", "gear": "R", "engine": "2000 rpm", "k1": "0.00 bar",
                     "k2": "11.50 bar", "phase": "drive (2)", "maneuver": "0-100: running 3.25 s",
                     "loop": "running, t 12.50 s"}
    none = dict((k, v) for k, _, v in fg.instrument_items({"tcu_phase_known": False,
                                                          "gear": 0}))
    assert none["phase"] == "not in the mapping" and none["gear"] == "N"
    assert none["speed"] == "- km/h" and none["maneuver"] == "none"


# ---------------------------------------------------------------- writes from the page


@pytest.fixture
def served_ui():
    from rt_loop.server import Server

    server = Server(f"ui-w-{os.getpid()}", interface="virtual", priority=0)
    ui = UiServer(server, ("127.0.0.1", 0), log=lambda _l: None)
    from dct_hil.ui.app import Hub

    ui.hub = Hub(ui)                 # the page's hub, without serving it
    server.start()
    yield server, ui
    server.stop()


def test_bad_control_input_from_the_page_is_refused_and_changes_nothing(served_ui):
    from bokeh.document import Document

    from dct_hil.ui.app import BenchView

    server, ui = served_ui
    view = BenchView(Document(), ui)

    applied = float(server._l.plant.inputs.road_grade_pct)
    reply = ui.hub.request({"op": "set", "name": "no_such_signal", "value": 1})
    assert reply["ok"] is False and "not a plant input" in reply["error"]
    reply = ui.hub.request({"op": "set", "name": "road_grade_pct", "value": 99})
    assert reply == {"ok": False, "error": "set: road_grade_pct = 99 is outside -40 .. 40"}
    view.grade.value = 55.0                          # the slider, as the browser moves it
    assert "outside -40 .. 40" in view.message.text and view.grade.value == 0
    view.set_name.value, view.set_value.value = "road_grade_pct", "abc"
    view._set_any()
    assert "must be a number" in view.message.text
    view.fault_kind.value, view.fault_params.value = "can.omit", "message=NoSuchMessage"
    view._inject()
    assert "is not in the served mapping" in view.message.text
    assert server.faults.status() == []
    assert float(server._l.plant.inputs.road_grade_pct) == applied == 0.0
    view.grade.value = 4.5                           # and a good one goes through
    assert "road_grade_pct = 4.5" in view.message.text
    assert float(server._l.plant.inputs.road_grade_pct) == 4.5
    assert ui.hub.control.counts["refused"] == 5 and ui.hub.control.counts["writes"] == 1
    ui.freeze()
    assert ui.hub.request({"op": "clear_all"})["error"].startswith("the loop has stopped")


@pytest.mark.slow
def test_stopping_the_ui_finalises_its_recording(served_ui, tmp_path):
    """Ctrl-C, SIGTERM or the end of the run stop the page first: a recording
    started on it is stopped and its file complete."""
    from bokeh.document import Document

    from dct_hil.ui.app import BenchView
    from rt_loop.measure.recorder import read_recording

    server, ui = served_ui
    ui.recordings_dir = str(tmp_path)
    view = BenchView(Document(), ui)
    view.rec_format.value = "csv"
    view._start_recording()
    assert "recording bench-" in view.message.text
    path = ui.recording_path
    assert path is not None and server.recording["path"] == path
    t0 = server.snapshot()["sim_time_s"]
    while server.snapshot()["sim_time_s"] < t0 + 0.3:
        pass
    ui.stop()
    assert server.recording is None and ui.recording_path is None
    assert ui.recorded == {os.path.basename(path): path}
    rec = read_recording(path)
    assert len(rec["time_s"]) >= 20 and (np.diff(rec["time_s"]) > 0).all()


def test_pedal_sliders_are_off_while_a_maneuver_plays(served_ui):
    from bokeh.document import Document

    from dct_hil.ui.app import BenchView

    server, ui = served_ui
    view = BenchView(Document(), ui)
    assert view.maneuver.options == server.loop_maneuvers() and "0-100" in view.maneuver.options
    assert not view.accel.disabled and not view.brake.disabled and view.m_stop.disabled
    view.maneuver.value = "0-100"
    view._start_maneuver()
    assert "maneuver 0-100 started" in view.message.text and server.maneuver_playing
    ui.hub._t_fast = ui.hub._t_slow = -math.inf
    view._update_slow()
    assert view.accel.disabled and view.brake.disabled and not view.grade.disabled
    assert not view.m_stop.disabled
    assert ui.hub.request({"op": "set", "name": "accel_pedal_pct", "value": 5})["ok"] is False
    view._stop_maneuver()
    assert "maneuver stopped" in view.message.text and not server.maneuver_playing
    ui.hub._t_fast = ui.hub._t_slow = -math.inf
    view._update_slow()
    assert not view.accel.disabled
    view.accel.value = 12.0                           # the pedal is the page's again
    assert "accel_pedal_pct = 12" in view.message.text
