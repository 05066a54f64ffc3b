"""Kiss point adaptation of the reference TCU (tcu_stub/logic.py): its kiss pressures are
state (TcuLogic.kiss_bar), started at CLUTCH_KISS_BAR and learnt stopped on the brake, K1 (in 1st) and K2 (in
the pre-selected 2nd) at every other stop: the clutch open for ADAPT_OPEN_S (the engine's torque then is its idle load), then CREEP_HOLD_NM
commanded; the clutch's torque estimated as EngineTorque above that idle load, the engine
speed steady; kiss += gain x (commanded - estimated) / Nm per bar, rate and range bounded.
The TCU does not know the plant's kiss points; the plant's outputs clutch1_kiss_pressure_bar and
clutch2_kiss_pressure_bar (where the packs close) are what it must find. Run in the compiled loop (equal to the
Python TCU to the bit: tests/test_offline_fast.py)."""

import numpy as np
import pytest

from plant.model import Plant
from tcu_stub import fast, logic

TOLERANCE_BAR = 0.05
CYCLE_S = 12.0


def stop_and_go(t_s, outputs):
    """Stops on the brake (7 s) between creeping (3 s) and a light pedal (2 s)."""
    c = t_s % CYCLE_S
    if c < 7.0:
        return 0.0, 40.0
    return (0.0, 0.0) if c < 10.0 else (15.0, 0.0)


def run(offset_bar, duration_s, reset=None, clutch=0):
    kiss = list(logic.CLUTCH_KISS_BAR)
    kiss[clutch] += offset_bar
    plant = Plant()
    plant.reset(**(reset or {}))
    tcu = fast.python_tcu({"CLUTCH_KISS_BAR": tuple(kiss)})
    out = f"clutch{clutch + 1}_kiss_pressure_bar"
    loop = fast.FastLoop(plant, stop_and_go, duration_s, record_every_s=0.1, tcu=tcu,
                         record_outputs=[out, "vehicle_speed_kmh"])
    history = []
    while loop.k < loop.n_periods:
        loop.step(int(round(CYCLE_S / logic.PERIOD_S)))
        history.append((loop.k * logic.PERIOD_S, tcu.kiss_bar[clutch], float(plant.outputs[out])))
    return history, loop.recorded(), tcu


@pytest.mark.slow
@pytest.mark.parametrize("clutch, offset_bar", [(0, 0.5), (0, -0.5), (1, 0.5), (1, -0.5)])
def test_the_kiss_point_started_half_a_bar_off_converges_to_the_plants(clutch, offset_bar):
    # the stops learn K1 (in 1st) and K2 (in the pre-selected 2nd) in turn
    history, rec, tcu = run(offset_bar, 12 * CYCLE_S, clutch=clutch)
    t, kiss, plant_kiss = np.array(history).T
    error = np.abs(kiss - plant_kiss)
    assert error[-1] < TOLERANCE_BAR, list(zip(t, kiss, plant_kiss))
    assert error[-3:].max() < TOLERANCE_BAR                  # and stays there
    other = 1 - clutch
    assert abs(tcu.kiss_bar[other] - logic.CLUTCH_KISS_BAR[other]) < 0.1   # the other from its calibration
    assert rec["vehicle_speed_kmh"].max() > 4.0               # creeping and driving between the stops


def test_without_adaptation_the_error_stays():
    kiss = (logic.CLUTCH_KISS_BAR[0] + 0.5, logic.CLUTCH_KISS_BAR[1])
    plant = Plant()
    tcu = fast.python_tcu({"CLUTCH_KISS_BAR": kiss, "ADAPT_GAIN_PER_S": 0.0})
    fast.FastLoop(plant, stop_and_go, 3 * CYCLE_S, tcu=tcu, record_outputs=["gear"]).step()
    assert abs(tcu.kiss_bar[0] - plant.outputs["clutch1_kiss_pressure_bar"]) > 0.4


def test_the_adapted_kiss_point_is_used_for_the_pressure():
    tcu = logic.TcuLogic()
    tcu.kiss_bar[0] = 1.9
    assert tcu.torque_to_bar(0, 0.0) == 1.9
    assert tcu.torque_to_bar(0, 35.6) == 1.9 + 35.6 / tcu.nm_per_bar(0)


# ---------------------------------------------------------------------------
# oil temperature: the torque-to-pressure gain and the fill time follow TransOilTemp
# ---------------------------------------------------------------------------

def _stepped(oil_degc=None):
    from plant.model import Plant as P
    from tcu_stub.offline import sensors_from_plant

    plant = P()
    s = sensors_from_plant(plant.outputs)
    s.pop("TransOilTemp", None)
    if oil_degc is not None:
        s["TransOilTemp"] = oil_degc
    tcu = logic.TcuLogic()
    tcu.step(0.0, s)
    return tcu


def test_without_trans_oil_temp_the_tcu_takes_warm_oil():
    tcu = _stepped()
    assert tcu.oil_degc == logic.OIL_DEFAULT_DEGC == 90.0


def test_cold_oil_grips_more_so_less_pressure_per_nm_and_fills_longer():
    cold, warm = _stepped(-20.0), _stepped(80.0)
    assert cold.nm_per_bar(0) == pytest.approx(1.08 * logic.CLUTCH_NM_PER_BAR[0])
    assert warm.nm_per_bar(0) == logic.CLUTCH_NM_PER_BAR[0]
    assert cold.torque_to_bar(0, 100.0) < warm.torque_to_bar(0, 100.0) - 0.2
    # the fill pulse: 1.8 x FILL_TIME_S at -20 degC
    for tcu, factor in ((cold, 1.8), (warm, 1.0)):
        tcu.loops[0].reset()
        tcu.pressure_bar = [3.0, 0.0]
        tcu.p_meas = (0.0, 0.0)
        tcu._commands()
        assert tcu.loops[0].fill_left_s == pytest.approx(factor * logic.FILL_TIME_S - logic.PERIOD_S)
