"""The bench over real SocketCAN: the plant server in the test's process, the
reference TCU as a second process on vcan0, as a HiL test of a TCU on the bus
runs (``dct_hil.bench.Bench`` with transport "socketcan").

The guest kernel is slow (User-mode Linux or emulated), so the whole HiL runs
in slow motion (DCT_VCAN_TIME_SCALE, default 0.1) and the TCU ticks on the plant's frames;
the limits are plant time, as on the embedded transport.
"""

import os

import pytest

from dct_hil.bench import Bench

pytestmark = pytest.mark.vcan

TIME_SCALE = float(os.environ.get("DCT_VCAN_TIME_SCALE", "0.1"))


@pytest.fixture
def can_bench(vcan0, tmp_path):
    b = Bench.start(transport="socketcan", channel=vcan0, time_scale=TIME_SCALE,
                    record=tmp_path / "run.mf4", tcu_timeout_s=120)
    yield b
    b.stop()


def test_launch_to_second_then_shaft_speeds_lost_open_both_clutches_over_socketcan(can_bench):
    """One bench for both (a second bench in the emulated guest costs a minute and a half
    of start-up and shows nothing more): the launch, the 1-2 upshift, then the reaction."""
    can_bench.set("accel_pedal_pct", 30)
    can_bench.wait_until("vehicle_speed_kmh > 2", timeout_s=1.5)
    can_bench.wait_until("gear == 2 and vehicle_speed_kmh > 5", timeout_s=6.0)
    fid = can_bench.inject("can.omit", message="DCT_ShaftSpeeds")
    t = can_bench.wait_until("TCU_ClutchCmd.SolenoidCurrent1 == 0 and "
                             "TCU_ClutchCmd.SolenoidCurrent2 == 0", timeout_s=1.0)
    start = next(f for f in can_bench.faults() if f["id"] == fid)["started_s"]
    assert t - start <= 0.05
    can_bench.stop()
    rec = can_bench.recording()
    assert rec["gear"].max() == 2
