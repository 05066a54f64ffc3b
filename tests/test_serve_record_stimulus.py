"""dct-hil serve --record FILE.mf4 and --stimulus: the server with the TCU stub.

A short run over python-can's virtual bus with the reference TCU as a CAN
node, recorded to MF4: the file opens in asammdf with every plant output and
its unit, and its CAN bus logging decodes with the DBC. A stimulus CSV steps
the road grade at a plant time; the recording shows the plant taking it
there. Nothing is timed.
"""

import uuid

import numpy as np
import pytest
import requires

requires.module("asammdf")

from asammdf import MDF
from waiting import wait_until

from can_dbc import codec
from rt_loop.server import Server, ServerError
from tcu_stub.can_tcu import CanTcu


@pytest.mark.slow
def test_an_mf4_recording_with_the_can_traffic_and_a_stimulus_step(tmp_path):
    stim = tmp_path / "grade.csv"
    stim.write_text("time_s,road_grade_pct\n0.0,0.0\n1.0,6.0\n")
    rec = tmp_path / "run.mf4"
    channel = f"mf4-{uuid.uuid4().hex[:8]}"
    srv = Server(channel, interface="virtual", priority=0, record_path=rec,
                 record_every_s=0.01, stimulus_path=stim)
    srv.start()
    tcu = CanTcu.open("virtual", channel)
    try:
        assert wait_until(lambda: srv.snapshot()["sim_time_s"] > 2.0, timeout=60)
    finally:
        tcu.close()
        srv.stop()
    report = srv.report()
    assert report["stimulus"]["applied"] >= 2 and report["stimulus"]["refused"] == 0
    assert report["record"]["dropped"] == 0
    with MDF(str(rec)) as mdf:
        grade = mdf.get("road_grade_pct")
        assert grade.unit == "%"
        t, v = grade.timestamps, grade.samples
        assert np.all(v[t < 0.999] == 0.0) and np.all(v[t > 1.0011] == 6.0)
        assert mdf.get("engine_speed_rpm").unit == "rpm"
        assert len(mdf.get("engine_speed_rpm").samples) >= 150
        decoded = mdf.extract_bus_logging({"CAN": [(codec.DBC_PATH, 0)]})
        names = {ch.name for group in decoded.groups for ch in group.channels}
    assert "EngineSpeed" in names and "SolenoidCurrent1" in names


def test_a_stimulus_file_with_an_unknown_channel_or_nan_is_one_line(tmp_path):
    for text, words in (("time_s,no_such_input\n0,1\n", "no_such_input"),
                        ("time_s,road_grade_pct\n0,nan\n", "road_grade_pct")):
        path = tmp_path / "bad.csv"
        path.write_text(text)
        with pytest.raises(ServerError) as e:
            Server("stim-bad", interface="virtual", priority=0, stimulus_path=path)
        assert words in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_an_unwritable_mf4_path_is_one_line(tmp_path):
    (tmp_path / "file").write_text("")
    srv = Server("mf4-bad", interface="virtual", priority=0,
                 record_path=tmp_path / "file" / "run.mf4")
    with pytest.raises(ServerError) as e:
        srv.start()
    assert "run.mf4" in str(e.value) and "\n" not in str(e.value)
