"""dct-hil serve --xcp: pyxcp as the master against a running plant server.

The server runs on python-can's virtual bus without a TCU (priority 0: the
host's timing is not asserted). pyxcp connects, uploads the A2L, measures 20
signals at the tick event (2 kHz) for 10 s, calibrates the road grade and
sees the vehicle roll, is refused an out-of-range value, and disconnects in
the middle of a DAQ; the loop goes on. Nothing is timed: the DTOs are counted
and their timestamps compared with the loop's deadlines.
"""

import math
import struct
import uuid

import pytest
import requires

requires.module("pyxcp")

import logging

from pyxcp.config import create_application_from_config, set_application
from pyxcp.daq_stim import DaqList
from pyxcp.types import XcpResponseError
from test_xcp_protocol import Measured, error_of, pyxcp_master
from waiting import wait_until

from rt_loop._rt_loop import ffi, lib
from rt_loop.measure.xcp import a2l
from rt_loop.server import Server, ServerError

OUT = ("plant", "outputs")
SIGNALS = ["engine_speed_rpm", "engine_torque_nm", "input_shaft1_speed_rpm",
           "input_shaft2_speed_rpm", "output_shaft1_speed_rpm", "output_shaft2_speed_rpm",
           "clutch1_pressure_bar", "clutch2_pressure_bar", "line_pressure_bar",
           "vehicle_speed_kmh", "vehicle_accel_mps2", "road_grade_pct", "fork1_position_mm",
           "fork2_position_mm", "fork3_position_mm", "fork4_position_mm", "gear",
           "wheel_speed_fl_rpm", "fuel_rate_lph"]           # 19 outputs + the tick counter


def region(name):
    for off, _size, _kind, n, lo, hi, _t in a2l.calibration_regions(ffi, lib):
        if n == name:
            return off, lo, hi
    raise KeyError(name)


@pytest.fixture
def server():
    srv = Server(f"xcp-{uuid.uuid4().hex[:8]}", interface="virtual", priority=0,
                 xcp="127.0.0.1:0")
    srv.start()
    yield srv
    srv.stop()


def measured(srv, lists):
    """pyxcp's DAQ decoding (Measured) for lists; it asks pyxcp for an application
    when made, so one for this server is set first (pyxcp_master makes its own)."""
    host, port = srv.address
    set_application(create_application_from_config(
        {"Transport": {"Eth": {"host": host, "port": port, "protocol": srv.protocol.upper()}},
         "General": {"disable_error_handling": True}}, log_level=logging.CRITICAL))
    return Measured(lists)


def measurements():
    meas = [("ticks", ffi.offsetof("rt_loop", "stats", "ticks"), 0, "U64")]
    return meas + [(n, ffi.offsetof("rt_loop", *OUT, n), 0, "F64") for n in SIGNALS]


def daq_list():
    meas = measurements()
    return DaqList(name="tick", event_num=0, stim=False, enable_timestamps=True,
                   measurements=meas, priority=0, prescaler=1)


@pytest.mark.slow
def test_pyxcp_measures_20_signals_at_2_khz_and_calibrates_the_grade(server):
    x_srv = server.xcp
    assert x_srv is not None and x_srv.address[0] == "127.0.0.1"
    policy = measured(server.xcp, [daq_list()])
    grade_at, lo, hi = region("override.road_grade_pct")
    accel_at = ffi.offsetof("rt_loop", *OUT, "vehicle_accel_mps2")
    with pyxcp_master(x_srv, policy=policy) as x:
        x.connect()
        text = x.identifier(4)
        assert "ASAP2_VERSION" in text and "override.road_grade_pct" in text
        assert f"ADDRESS 0x{grade_at:X}" in text or f"0x{grade_at:X}" in text
        # 10 s of DAQ on the tick event: every tick once, on the loop's deadlines
        policy.setup()
        policy.start()
        t0 = int(server.snapshot()["counts"]["ticks"])
        wait_until(lambda: server.snapshot()["counts"]["ticks"] > t0 + 20_000, timeout=120)
        policy.stop()
        rows = list(policy.rows)
        # the grade: the car at rest rolls back down it; beyond the A2L's range: refused
        x.shortDownload(grade_at, 0, struct.pack("<d", 10.0))
        assert wait_until(lambda: struct.unpack("<d", x.shortUpload(8, accel_at))[0] < -0.5,
                          timeout=10)
        with pytest.raises(XcpResponseError) as e:
            x.shortDownload(grade_at, 0, struct.pack("<d", hi + 1.0))
        assert "ERR_OUT_OF_RANGE" in error_of(e)
        assert struct.unpack("<d", x.shortUpload(8, grade_at))[0] == 10.0
        x.disconnect()
    # about 20 000 ticks measured; that none is lost under any load is the XCP benchmark's
    # figure (python -m rt_loop.tools.xcp_bench: DTOs received and lost), not this test's
    assert len(rows) >= 19_000
    # pyxcp hands the values over in the order it packed them: by address
    addresses = sorted(m[1] for m in measurements())
    at = addresses.index(ffi.offsetof("rt_loop", "stats", "ticks"))
    ticks = [int(r[2][at]) for r in rows]
    assert all(b > a for a, b in zip(ticks, ticks[1:])), rows[:3]     # in order, none twice
    missing = ticks[-1] - ticks[0] + 1 - len(ticks)
    print(f"DAQ: {len(ticks)} ticks measured, {missing} missing between the first and the last")
    stamps = [int(r[1]) for r in rows]
    steps = [b - a for a, b in zip(stamps, stamps[1:])]
    # timestamps (pyxcp gives ns) of the tick deadlines: 500 us apart, a skipped deadline or
    # a missing tick a multiple of it
    assert all(s > 0 and s % 500_000 == 0 for s in steps), sorted(set(steps))[:10]
    skipped = int(server.snapshot()["counts"]["skipped_ticks"])
    assert sum(s // 500_000 - 1 for s in steps) <= skipped + missing
    for _, _, values in rows[-10:]:
        assert all(math.isfinite(v) for v in values)
    c = server.xcp_counters()
    assert c["loop"]["dto_ring_dropped"] <= missing and c["loop"]["cal_applied"] == 1
    assert c["protocol"]["errors"].get("ERR_OUT_OF_RANGE") == 1


@pytest.mark.slow
def test_a_master_that_leaves_in_the_middle_of_a_daq_leaves_the_loop_running(server):
    policy = measured(server.xcp, [daq_list()])
    with pyxcp_master(server.xcp, policy=policy) as x:
        x.connect()
        policy.setup()
        policy.start()
        assert wait_until(lambda: len(policy.rows) > 200, timeout=30)
        # gone without STOP or DISCONNECT: the transport closes under the master
    before = server.snapshot()
    assert wait_until(lambda: server.snapshot()["counts"]["ticks"] > before["counts"]["ticks"] + 2000,
                      timeout=60)
    after = server.snapshot()
    assert after["state"] == "running"
    # a new master connects and finds no DAQ left running from the first
    with pyxcp_master(server.xcp) as x:
        x.connect()
        x.disconnect()
    head = int(server._l.daq_ring.head)
    wait_until(lambda: server.snapshot()["counts"]["ticks"] > after["counts"]["ticks"] + 200,
               timeout=30)
    assert int(server._l.daq_ring.head) == head                  # nothing measured any more


def test_bad_xcp_options_are_one_line():
    for kwargs, words in (({"xcp": "host:port"}, "[HOST:]PORT"),
                          ({"xcp": "70000"}, "70000"),
                          ({"xcp": "5555", "xcp_protocol": "can"}, "udp or tcp"),
                          ({"xcp_key": "/nonexistent/key"}, "--xcp"),
                          ({"xcp": "5555", "xcp_key": "/nonexistent/key"}, "key")):
        with pytest.raises(ServerError) as e:
            Server("xcp-bad", interface="virtual", priority=0, **kwargs)
        assert words in str(e.value) and "\n" not in str(e.value), (kwargs, str(e.value))


def test_a_taken_port_is_one_line_and_nothing_is_left_running():
    first = Server(f"xcp-{uuid.uuid4().hex[:8]}", interface="virtual", priority=0, xcp="0")
    first.start()
    try:
        port = first.xcp.address[1]
        second = Server(f"xcp-{uuid.uuid4().hex[:8]}", interface="virtual", priority=0,
                        xcp=f"127.0.0.1:{port}")
        with pytest.raises(ServerError) as e:
            second.start()
        assert f"{port}" in str(e.value) and "\n" not in str(e.value)
        assert not second.running
    finally:
        first.stop()


@pytest.mark.slow
def test_the_xcp_benchmark_writes_its_figures(tmp_path):
    """python -m rt_loop.tools.xcp_bench in its shortest form: the figures are there (never judged)."""
    import json

    from rt_loop.tools import xcp_bench as bench

    out = tmp_path / "bench-xcp.json"
    assert bench.main(["--signals", "30", "--pairs", "1", "--round-s", "1", "--priority", "0",
                       "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["signals"] == 30 and rep["odts"] == 1 and rep["daq_copy_ns"] > 0
    assert [r["xcp"] for r in rep["rounds"]] == [False, True]
    assert rep["rounds"][1]["dtos_received"] > 0 and rep["rounds"][1]["dtos_lost_in_loop"] == 0
    names = [n for n, _ in bench.measurable_doubles(ffi, 100)]
    assert len(names) == 100 and len(set(names)) == 100 and names[0].startswith("outputs.")
