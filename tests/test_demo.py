"""dct-hil demo on the host: the embedded transport (no CAN in this kernel).

The run over SocketCAN, with the TCU as a second process, is in
tests/vcan/test_demo_over_can.py. The verdict's rules one by one are in
tests/test_verdict.py; here a demo whose TCU is starved on purpose
(``CanTcu.pause``) must say so in its verdict and fail under --strict.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import requires

from dct_hil import cli, demo
from rt_loop import verdict as vd

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "dct_hil.cli", "demo", *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


def test_without_vcan0_the_demo_takes_the_embedded_transport_and_says_why():
    if demo.can_netdev_up("vcan0"):
        pytest.skip("this kernel has vcan0 up: the demo takes SocketCAN here")
    iface, chan, why, two = demo.choose_transport(None, None)
    assert (iface, two) == ("virtual", False)
    assert "no vcan0" in why and "embedded" in why

def _assert_shifts_as_offline(summary, duration_s=8.0):
    """The demo's shifts over CAN are the offline run's of paper-cycle's first
    ``duration_s`` (two shifts), each within 30 ms."""
    from plant.maneuvers import compare_shifts, gear_shifts, get_maneuver
    from plant.model import Plant
    from tcu_stub.offline import run_offline

    over_can = [(s["time_s"], s["from"], s["to"]) for s in summary["shifts"]]
    m = get_maneuver("paper-cycle")
    plant = Plant(overrides={"hydraulics": {"pressure_commanded": 0}})
    plant.reset(**m.reset_kwargs)
    rec = run_offline(plant, m.driver, duration_s, record_every_s=0.002)
    offline = gear_shifts(rec["time_s"], rec["gear"])
    same, diffs = compare_shifts(offline, over_can)
    assert same and len(offline) == 2, (offline, over_can)
    assert max(abs(d) for d in diffs) <= 0.030, (diffs, offline, over_can)



def test_a_channel_that_is_no_can_interface_is_a_one_line_error():
    assert not demo.can_netdev_up("lo")
    with pytest.raises(demo.DemoError) as e:
        demo.choose_transport("lo", None)
    assert "not a CAN network interface" in str(e.value) and "\n" not in str(e.value)


def test_an_explicit_interface_is_taken_as_given():
    assert demo.choose_transport(None, "virtual")[:2] == ("virtual", demo.EMBEDDED_CHANNEL)
    iface, chan, _, two = demo.choose_transport("PCAN_USBBUS1", "pcan")
    assert (iface, chan, two) == ("pcan", "PCAN_USBBUS1", True)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = run_cli("--duration", "6", "--out", str(out), "--priority", "0", "--quiet")
    return proc, out


@pytest.mark.slow
def test_a_short_demo_launches_shifts_and_writes_everything(short_run):
    proc, out = short_run
    assert proc.returncode == 0, proc.stderr
    assert "embedded transport" in proc.stdout or "SocketCAN" in proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["maneuver_time_s"] == pytest.approx(6.0, abs=0.01)
    assert [(s["from"], s["to"]) for s in summary["shifts"]][:1] == [(1, 2)]
    assert 3.5 < summary["shifts"][0]["time_s"] < 5.0
    assert summary["gear_clashes"] == 0 and summary["rx"]["rejected"] == 0
    for key in ("recording", "can_log", "stats", "tcu_report", "summary"):
        path = Path(summary["files"][key])
        assert path.stat().st_size > 0 and str(path) in proc.stdout, key
    assert summary["files"]["plots"] and all(Path(p).exists() for p in summary["files"]["plots"])
    tcu = json.loads((out / "tcu-report.json").read_text())
    assert tcu["error"] is None and tcu["ticks"] > 1000
    stats = json.loads((out / "serve-stats.json").read_text())
    assert stats["run"]["maneuver"] == "done" and stats["record"]["dropped"] == 0


@pytest.mark.slow
def test_a_short_demo_ends_with_its_verdict_and_exit_0_without_strict(short_run):
    """Whether this run's timing held depends on the machine: the test checks that the
    verdict is there, consistent, printed last and warned about, never what it is."""
    proc, out = short_run
    summary = json.loads((out / "summary.json").read_text())
    v = summary["verdict"]
    assert set(v) == {"valid", "findings", "notes"} and v["valid"] == (not v["findings"])
    assert [(s["from"], s["to"]) for s in summary["offline_shifts"]] == [(1, 2)]
    lines = proc.stdout.strip().splitlines()
    assert lines[-(1 + len(v["findings"]) + len(v["notes"]))] == vd.verdict_lines(v)[0]
    assert lines[-(1 + len(v["findings"]) + len(v["notes"]))].startswith(
        "timing: VALID" if v["valid"] else "timing: INVALID - ")
    warned = "dct-hil: warning: timing INVALID" in proc.stderr
    assert warned == (not v["valid"]) and proc.returncode == 0
    stats = json.loads((out / "serve-stats.json").read_text())
    assert set(stats["verdict"]) == {"valid", "findings", "notes"}
    assert stats["rings"]["samples"] > 0


@pytest.mark.slow
def test_the_recording_starts_before_the_tcu_and_plays_the_pedals_from_its_first_frame(short_run):
    from rt_loop.measure.recorder import read_recording

    _, out = short_run
    rec = read_recording(out / "plant.csv")
    started = rec["maneuver_time_s"] >= 0
    assert started[-1] and rec["maneuver_time_s"][-1] == pytest.approx(6.0, abs=0.003)
    mt = rec["maneuver_time_s"][started]
    accel = rec["accel_pedal_pct"][started]
    assert (accel[mt < 0.99] == 0).all() and (accel[mt > 1.01] == 100).all()   # paper-cycle
    assert rec["vehicle_speed_kmh"][-1] > 40


@pytest.mark.slow
def test_ctrl_c_stops_the_demo_with_everything_written(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "dct_hil.cli", "demo", "--out", str(tmp_path),
                             "--priority", "0", "--quiet"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (tmp_path / "plant.csv").exists() or (tmp_path / "plant.csv").stat().st_size < 10_000:
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert not summary["completed"]
    assert (tmp_path / "serve-stats.json").exists() and (tmp_path / "tcu-report.json").exists()
    assert "Traceback" not in err


@pytest.mark.parametrize("args, words", [
    (["--maneuver", "wltc"], "invalid choice"),
    (["--time-scale", "0"], "--time-scale"),
    (["--duration", "-1"], "--duration"),
    (["--channel", "lo"], "not a CAN network interface"),
    (["--mapping", "no_such_mapping"], "no_such_mapping"),
    (["--mapping", "vehicle", "--bus", "xx=demo-x"], "bus 'xx'"),
    (["--mapping", "vehicle", "--bus", "io"], "NAME=CHANNEL"),
    (["--mapping", "vehicle", "--dbc", "io=no_such.dbc"], "no_such.dbc"),
])
@pytest.mark.slow
def test_bad_options_are_one_line_errors(tmp_path, args, words):
    proc = run_cli(*args, "--out", str(tmp_path), "--priority", "0", timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], proc.stderr


@pytest.mark.slow
def test_slow_motion_with_the_bus_clock_gives_the_offline_shifts_within_30_ms(tmp_path):
    """Half speed, the TCU ticking on the plant's 2 ms frames: the first shifts of
    paper-cycle land where the in-process run puts them. Over the bus the full-load
    upshifts come 8-13 ms early (frame timing, measured since the demo exists) and,
    since the TCU's clutch gain follows the oil temperature, the 2-3 up to 21-23 ms
    early here and 24.5 ms in the emulated guest over vcan0 (cause not established):
    30 ms."""

    proc = run_cli("--duration", "8", "--time-scale", "0.5", "--out", str(tmp_path),
                   "--priority", "0", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "TCU clock         bus" in proc.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["tcu_clock"] == "bus" and summary["tcu"]["clock"] == "bus"
    _assert_shifts_as_offline(summary)


PAUSE_AT_S = 4.0      # TCU time: the 1-2 upshift of paper-cycle is under way (offline: 3.99-4.07 s)
PAUSE_S = 0.5


@pytest.mark.slow
def test_a_demo_with_a_starved_tcu_is_invalid_names_why_and_strict_exits_3(
        tmp_path, monkeypatch, capsys):
    """The TCU thread starves for 0.5 s in the middle of the first upshift: the server
    times its messages out, the TCU goes stale, the shifts move. The verdict says all
    three and --strict turns the run into exit 3."""
    paused = []

    class StarvedTcu(demo._TcuThread):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            threading.Thread(target=self._starve_once, daemon=True).start()

        def _starve_once(self):
            while self.tcu.running and self.tcu.t_s < PAUSE_AT_S:
                time.sleep(0.002)
            if self.tcu.running:
                self.tcu.pause(PAUSE_S)
                paused.append(self.tcu.t_s)

    monkeypatch.setattr(demo, "_TcuThread", StarvedTcu)
    code = cli.main(["demo", "--duration", "8", "--priority", "0", "--quiet", "--strict", "--tcu-impl", "python",
                     "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert paused, "the TCU was never paused"
    assert code == vd.EXIT_INVALID == 3, err
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["completed"]
    v = summary["verdict"]
    assert not v["valid"]
    findings = "\n".join(v["findings"])
    assert "TCU messages timed out during the maneuver (TCU_ClutchCmd" in findings
    stale = [f for f in v["findings"] if f.startswith("TCU stale")]
    assert stale and "timeout: DCT_ShaftSpeeds" in stale[0]
    assert any(f.startswith(("shift sequence differs from the offline run",
                             "shift times differ from the offline run")) for f in v["findings"])
    assert any(n.startswith("TCU paused on request once, 0.5 s") for n in v["notes"])
    tcu = summary["tcu"]
    assert tcu["pauses"] == {"count": 1, "total_s": 0.5}
    assert any(ep["start_s"] >= PAUSE_AT_S and "timeout" in ep["causes"].values()
               for ep in tcu["stale"]["episodes"])
    assert "timing: INVALID - " in out
    assert err.strip().splitlines()[-1].endswith("(--strict: exit 3)")


@pytest.mark.parametrize("seconds", [0, -1, float("nan"), 61, "x"])
def test_a_tcu_pause_outside_0_to_60_s_is_refused(seconds):
    from tcu_stub.can_tcu import CanTcu

    tcu = CanTcu.open("virtual", f"pause-{os.getpid()}", start=False)
    try:
        with pytest.raises(ValueError) as e:
            tcu.pause(seconds)
        assert "pause" in str(e.value) and "\n" not in str(e.value)
    finally:
        tcu.close()


@pytest.mark.slow
def test_over_the_vehicle_matrix_the_demo_shifts_as_the_offline_run_of_the_contract(tmp_path):
    """The plant and the TCU stub (a CAN node) over the example vehicle matrix, two
    buses on the embedded transport, half speed with the bus clock: every message
    of both buses goes both ways unrejected, and the first shifts of paper-cycle
    land where the in-process run over the project's own contract puts them."""

    proc = run_cli("--mapping", "vehicle", "--duration", "8", "--time-scale", "0.5",
                   "--out", str(tmp_path), "--priority", "0", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "CAN matrix" in proc.stdout and "vehicle.toml" in proc.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["mapping"].endswith("vehicle.toml")
    assert set(summary["buses"]) == {"pt", "io"}
    stats = json.loads((tmp_path / "serve-stats.json").read_text())
    counts = stats["counts"]
    assert set(counts["channels"]) == {"pt", "io"}
    for name, c in counts["tcu_messages"].items():
        assert c["accepted"] > 0 and c["bad_crc"] == c["bad_counter"] == c["bad_length"] == 0, name
    for name, c in counts["plant_messages"].items():
        assert c["sent"] > 0, name
    for name, r in summary["tcu"]["received"].items():
        assert r["accepted"] > 0 and not any(r["rejected"].values()), (name, r)
    _assert_shifts_as_offline(summary)


@pytest.mark.slow
def test_a_demo_recorded_to_mf4_opens_in_asammdf_with_units_and_decoded_can(tmp_path):
    asammdf = requires.module("asammdf")
    from can_dbc import codec

    proc = run_cli("--mf4", "--duration", "6", "--out", str(tmp_path), "--priority", "0",
                   "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["files"]["recording"].endswith("plant.mf4") and summary["shifts"]
    with asammdf.MDF(str(tmp_path / "plant.mf4")) as mdf:
        plant = next(g for g in mdf.groups if g.channel_group.acq_name == "plant")
        names = {c.name for c in plant.channels}
        outputs = [n for n, _ in __import__("rt_loop._rt_loop", fromlist=["ffi"]).ffi.typeof(
            "dct_outputs").fields]
        assert set(outputs) <= names and "maneuver_time_s" in names
        assert mdf.get("vehicle_speed_kmh").unit == "km/h"
        assert mdf.get("clutch1_pressure_bar").unit == "bar"
        decoded = mdf.extract_bus_logging({"CAN": [(codec.DBC_PATH, 0)]})
        signals = {c.name for g in decoded.groups for c in g.channels}
    assert {"EngineSpeed", "VehicleSpeed", "SolenoidCurrent1", "ForkForce1"} <= signals
