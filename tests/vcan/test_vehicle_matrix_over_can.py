"""The example vehicle matrix served over two real SocketCAN buses.

``dct-hil serve --mapping vehicle`` plays the engine, ABS/ESP, cluster and
gateway on the powertrain bus (vcan0) and the transmission's inside on the
I/O bus (vcan1, created here), both read and written by the C loop itself;
``dct-hil tcu --mapping vehicle`` is the TCU on the same two buses, as a
second process. Slowed down (--time-scale 0.1) as every guest run is. The
test reads both JSON reports: every message of the matrix went both ways on
its own bus, no frame was rejected by either side (AUTOSAR E2E Profile 1
with a Data ID, the XOR checksum and the counters checked on real sockets),
and each bus's counts are its own. Nothing is timed.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from can_dbc import mapping as mapping_mod

pytestmark = pytest.mark.vcan

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WAIT_S = 300.0
RUN_S = 20.0          # wall time the two run together (2 s of plant time at 0.1: 20 cycles of
                      # the matrix's slowest message, 100 ms; every message both ways many times)


@pytest.fixture(scope="module")
def vcan1(vcan0):
    """A second vcan interface, up (created when missing: the guest runs as root)."""
    if not os.path.exists("/sys/class/net/vcan1"):
        subprocess.run(["ip", "link", "add", "dev", "vcan1", "type", "vcan"], check=True)
    subprocess.run(["ip", "link", "set", "up", "vcan1"], check=True)
    return "vcan1"


def _wait(proc, what, err_path):
    try:
        return proc.wait(timeout=WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"{what} did not stop within {WAIT_S:g} s: {err_path.read_text()[-2000:]}")


def test_the_vehicle_matrix_runs_on_two_socketcan_buses(vcan0, vcan1, tmp_path):
    stats_path, tcu_path = tmp_path / "stats.json", tmp_path / "tcu.json"
    serve_err, tcu_err = tmp_path / "serve.err", tmp_path / "tcu.err"
    buses = ["--mapping", "vehicle", "--interface", "socketcan", "--channel", vcan0,
             "--bus", f"io={vcan1}", "--time-scale", "0.1"]
    serve = subprocess.Popen(
        [sys.executable, "-m", "dct_hil.cli", "serve", *buses, "--priority", "0",
         "--duration", "3600", "--quiet", "--stats", str(stats_path)],
        stdout=subprocess.DEVNULL, stderr=open(serve_err, "w", encoding="utf-8"), cwd=REPO)
    tcu = None
    try:
        time.sleep(5.0)             # the server's start (not a measurement: the TCU may come first)
        tcu = subprocess.Popen(
            [sys.executable, "-m", "tcu_stub.can_tcu", *buses, "--clock", "bus",
             "--duration", str(RUN_S), "--quiet", "--report", str(tcu_path)],
            stdout=subprocess.DEVNULL, stderr=open(tcu_err, "w", encoding="utf-8"), cwd=REPO)
        assert _wait(tcu, "the TCU", tcu_err) == 0, tcu_err.read_text()[-2000:]
        serve.send_signal(signal.SIGTERM)
        assert _wait(serve, "the server", serve_err) == 0, serve_err.read_text()[-2000:]
    finally:
        for p in (tcu, serve):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()

    stats = json.loads(stats_path.read_text())
    counts = stats["counts"]
    m = mapping_mod.load(mapping_mod.find_mapping("vehicle"))
    assert stats["config"]["transport"] == "socketcan"
    assert {b["name"]: (b["channel"], b["transport"]) for b in stats["config"]["buses"]} == {
        "pt": (vcan0, "socketcan"), "io": (vcan1, "socketcan")}
    # the plant received every TCU message on its own bus, none rejected, never lost
    received = [f"{x.bus}:{x.name}" for x in m.messages if x.direction == "receive"]
    assert sorted(counts["tcu_messages"]) == sorted(received)
    for name, c in counts["tcu_messages"].items():
        assert c["accepted"] > 0, (name, c)
        assert c["bad_length"] == c["bad_crc"] == c["bad_counter"] == 0, (name, c)
    assert counts["rx"]["rejected"] == 0 and counts["rx"]["lost"] == 0, counts["rx"]
    # and sent every message of its nodes on its own bus
    sent = [f"{x.bus}:{x.name}" for x in m.messages if x.direction == "send"]
    assert sorted(counts["plant_messages"]) == sorted(sent)
    assert all(c["sent"] > 0 and c["dropped"] == 0 for c in counts["plant_messages"].values())
    for bus in ("pt", "io"):
        ch = counts["channels"][bus]
        n_rx = sum(c["accepted"] for k, c in counts["tcu_messages"].items() if k.startswith(bus + ":"))
        n_tx = sum(c["sent"] for k, c in counts["plant_messages"].items() if k.startswith(bus + ":"))
        assert ch["rx"]["accepted"] == n_rx and ch["tx"]["frames"] == n_tx, (bus, ch)
        assert ch["rx"]["unknown_id"] == 0, (bus, ch)  # no frame of the other bus leaked over

    # the TCU accepted every plant message it reads, on both buses, without rejections
    rep = json.loads(tcu_path.read_text())
    assert sorted(rep["received"]) == sorted(sent)
    for name, r in rep["received"].items():
        assert r["accepted"] > 0 and not any(r["rejected"].values()), (name, r)
    assert rep["unknown_frames"] == 0
    assert {b: x["channel"] for b, x in rep["buses"].items()} == {"pt": vcan0, "io": vcan1}
    assert sorted(rep["sent"]) == sorted(received)
