"""A cold start at 23 degC (coolant, engine oil and transmission oil): the car
engages 1st at standstill and launches in 1st, as a real DQ250 does.

At 23 degC the open K1 drags input shaft 1 with the idling engine (about 5 N m
at about 930 rpm of slip, 2.5 x the warm drag: plant/data/golf_mk5_gti_dsg.toml,
thermal.clutch_drag_viscosity_exponent). The 1-3 synchronizer's cone (31.8 N m
at 900 N of fork force) holds that drag (17 N m at the gear) below the index
torque of the blocker ring's chamfers (23.4 N m at 900 N), so the ring is
turned back and the sleeve passes (plant/csrc/synchronizer.c,
cone_holds_load). The tanh friction law lets the cone creep at 0.66 rad/s of
slip under that load, above the 0.5 rad/s lock speed: by the lock speed alone
the blocker never released, the gear_engagement DTC set at about 2.1 s and the
car launched in 2nd.

Not yet passing (xfail, strict): pre-selecting 1st in 2nd at about 21 km/h
(18.3 s): K1 drags input shaft 1 down by about 1000 rpm (5-6 N m, with the
shaft's own drag about 26 N m at the gear), above the index torque: the
blocker keeps blocking, gear_engagement sets at 19.4 s and heals when 3rd is
pre-selected instead.
"""

import numpy as np
import pytest

from plant.maneuvers import get_maneuver
from plant.model import Plant
from tcu_stub.diagnostics import DTC_GEAR_ENGAGEMENT
from tcu_stub.offline import run_offline

COLD_DEGC = 23.0
DURATION_S = 30.0


@pytest.fixture(scope="module")
def cold_run():
    p = Plant()
    m = get_maneuver("wltc")
    m.start(p)
    p.reset(**m.reset_kwargs, coolant_temp_degc=COLD_DEGC, engine_oil_temp_degc=COLD_DEGC,
            trans_oil_temp_degc=COLD_DEGC)
    return run_offline(p, m.driver, DURATION_S)


def _engagement_dtc(rec):
    return (np.asarray(rec["tcu_active_faults"]).astype(np.int64) >> DTC_GEAR_ENGAGEMENT) & 1


def test_cold_car_engages_first_and_launches_in_first(cold_run):
    rec = cold_run
    t = np.asarray(rec["time_s"])
    gear = np.asarray(rec["gear"])
    speed = np.asarray(rec["vehicle_speed_kmh"])
    assert rec["shifts"], "no shift within 30 s"
    t_up, g_from, g_to = rec["shifts"][0]
    assert (g_from, g_to) == (1, 2)                       # launched in 1st, then up to 2nd
    first = np.nonzero(gear == 1)[0]
    assert first.size and t[first[0]] < 2.0               # 1st engaged at standstill within 2 s
    moving = np.nonzero(speed > 1.0)[0]
    assert moving.size and gear[moving[0]] == 1           # the car starts to move in 1st
    launch = t < t_up
    assert not _engagement_dtc(rec)[launch].any()         # no gear_engagement DTC up to the 1-2 shift


@pytest.mark.xfail(strict=True, reason="pre-selecting 1st in 2nd when cold: K1's drag at 1000 rpm "
                   "of slip exceeds the blocker's index torque (module docstring)")
def test_cold_run_sets_no_gear_engagement_dtc(cold_run):
    assert not _engagement_dtc(cold_run).any()
