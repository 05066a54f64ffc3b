"""HiL tests of the reference TCU: driving behaviour and reactions to faults.

Each test gets a fresh bench (the ``bench`` fixture of ``dct_hil.pytest_plugin``:
the plant server on the embedded transport and the reference TCU in a thread,
or with ``--bench-tcu=external`` / ``@pytest.mark.tcu_under_test`` the TCU on
the bus) and drives it in plant time: ``bench.set`` for the pedals,
``bench.wait_until`` for a condition checked by the loop every tick (it
returns the plant time the condition first held), ``bench.inject`` for a
fault. Times below are plant seconds; on the embedded transport the loop runs
in real time, so each test takes a few seconds. The reference TCU ticks on
the plant's frames (``bench(tcu_clock="bus")``): its timers and so every
reaction bound are plant time, also on a machine busy with other work (on
the wall clock a starved Python TCU skips ticks and its reactions come late).

To test another TCU: copy this file, put your TCU on the bus (``pytest
--bench-transport socketcan --bench-channel can0 --bench-tcu external``) and
adapt the limits and the DTC names (``DTC``) to its specification.

The TCU's diagnosis comes in its ``TCU_Status`` message (ActiveFaults,
LimpHome, ShiftActive, TcuPhase, InhibitedGears; the DTC table of
``tcu_stub.diagnostics``).
"""

from __future__ import annotations

import pytest

import tcu_stub.diagnostics as diagnostics
from dct_hil.bench import BenchTimeout

pytestmark = [pytest.mark.hil, pytest.mark.slow, pytest.mark.bench(tcu_clock="bus")]

# ---------------------------------------------------------------- the TCU's specification
LAUNCH_MOVE_S = 1.5          # pedal 30 % at standstill -> the car moves (> 2 km/h) within
UPSHIFT_12_S = 6.0           # ... -> 2nd within (plant time from the pedal)
UPSHIFT_23_S = 5.0           # 2nd -> 3rd within, pedal 30 %
KICKDOWN_S = 1.0             # full pedal at cruise in 3rd -> a lower gear within
COAST_DOWNSHIFT_S = 4.0      # pedal off, brake 30 % in 3rd -> a lower gear within
ENGINE_MSG_TIMEOUT_S = 0.15  # VEH_Driver (10 ms cycle) lost -> no torque request within
SPEED_MSG_TIMEOUT_S = 0.05   # DCT_ShaftSpeeds (2 ms cycle) lost -> both clutches open within
E2E_DEBOUNCE_S = 0.03        # CRC / counter errors on a 2 ms message -> reaction within
RECOVERY_S = 1.5             # plant messages back -> a clutch drives again within
DIAG_S = 1.0                 # a diagnosed fault -> reported in TCU_Status within

CLUTCHES_OPEN = ("TCU_ClutchCmd.SolenoidCurrent1 == 0 and "
                 "TCU_ClutchCmd.SolenoidCurrent2 == 0")
CLUTCH_DRIVES = ("TCU_ClutchCmd.SolenoidCurrent1 > 0.3 or "
                 "TCU_ClutchCmd.SolenoidCurrent2 > 0.3")


def DTC(name: str) -> str:  # reads like the table it names
    """A DTC's name as the TCU reports it (``tcu_status()["dtcs"]``), checked
    against the TCU's table when it has one."""
    assert name in diagnostics.DTC_NAMES, f"{name!r} is not in the TCU's DTC table"
    return name


# ---------------------------------------------------------------- helpers
def drive_to_gear(bench, gear: int, pedal_pct: float = 30.0, timeout_s: float = 12.0) -> float:
    bench.set("accel_pedal_pct", pedal_pct)
    return bench.wait_until(f"gear == {gear}", timeout_s=timeout_s)


def fault_start(bench, fault_id: int) -> float:
    """Plant time the fault started (waits for the loop to start it)."""
    for _ in range(1000):
        f = next(x for x in bench.faults() if x["id"] == fault_id)
        if f["started_s"] is not None:
            return f["started_s"]
        bench.sleep(0.002)
    raise AssertionError(f"fault {fault_id} never started")


def reaction(bench, condition: str, limit_s: float, kind: str, **params) -> float:
    """Injects a fault, waits for ``condition``; the reaction time (plant s)
    from the fault's start, asserted within ``limit_s``."""
    fid = bench.inject(kind, **params)
    t = bench.wait_until(condition, timeout_s=limit_s + 0.5)
    dt = t - fault_start(bench, fid)
    assert dt <= limit_s, f"{kind}: {condition} after {dt * 1e3:.1f} ms (limit {limit_s * 1e3:.0f} ms)"
    return dt


def holds_not(bench, condition: str, for_s: float) -> None:
    """``condition`` does not hold for ``for_s`` of plant time."""
    with pytest.raises(BenchTimeout):
        bench.wait_until(condition, timeout_s=for_s)


def has_dtc(name: str) -> str:
    """A condition that holds while the TCU reports ``name`` (its bit of
    TCU_Status.ActiveFaults), whatever else it reports: a loaded host may add
    a CAN timeout of its own."""
    bit = next(b for b, d in diagnostics.DTCS.items() if d.name == DTC(name))
    return f"TCU_Status.ActiveFaults & {1 << bit:#x}"


def dtcs(bench) -> set:
    return set(bench.tcu_status().get("dtcs", []))


def reported(bench, name: str, within_s: float = 0.1) -> None:
    """``name`` is among the TCU's active DTCs within ``within_s`` of plant
    time (TCU_Status comes every 10 ms)."""
    end = bench.time_s + within_s
    while DTC(name) not in dtcs(bench):
        assert bench.time_s < end, f"{name} not reported within {within_s:g} s: {bench.tcu_status()}"
        bench.sleep(0.005)


# ---------------------------------------------------------------- driving
def test_launch_moves_off_and_shifts_1_2(bench):
    t0 = bench.time_s
    bench.set("accel_pedal_pct", 30)
    t_move = bench.wait_until("vehicle_speed_kmh > 2", timeout_s=LAUNCH_MOVE_S)
    assert bench.read("gear") == 1, "the car must move off in 1st"
    t2 = bench.wait_until("gear == 2", timeout_s=UPSHIFT_12_S)
    assert t_move - t0 <= LAUNCH_MOVE_S and t2 - t0 <= UPSHIFT_12_S
    v = bench.read_many(["vehicle_speed_kmh", "gear_clashes", "engine_speed_rpm"])
    assert v["vehicle_speed_kmh"] > 10
    assert v["gear_clashes"] == 0
    assert 1000 < v["engine_speed_rpm"] < 3000, "a part-load 1-2 shift keeps the engine in range"


def test_upshifts_1_2_3_under_part_load(bench):
    t2 = drive_to_gear(bench, 2, timeout_s=UPSHIFT_12_S)
    t3 = bench.wait_until("gear == 3", timeout_s=UPSHIFT_23_S)
    assert t3 > t2
    assert bench.read("TCU_EngineCmd.TargetGear") == 3
    assert bench.read("gear_clashes") == 0
    holds_not(bench, "gear < 3", 0.5)              # no hunting back at a steady pedal


def test_kickdown_from_cruise(bench):
    drive_to_gear(bench, 3)
    bench.sleep(0.5)
    t0 = bench.time_s
    bench.set("accel_pedal_pct", 100)
    t = bench.wait_until("gear < 3", timeout_s=KICKDOWN_S)
    assert t - t0 <= KICKDOWN_S
    assert bench.read("engine_speed_rpm") < 6500


def test_coast_downshift_when_braking(bench):
    drive_to_gear(bench, 3)
    bench.sleep(1.0)
    bench.set("accel_pedal_pct", 0)
    bench.set("brake_pedal_pct", 30)
    t0 = bench.time_s
    t = bench.wait_until("gear < 3 and gear > 0", timeout_s=COAST_DOWNSHIFT_S)
    assert t - t0 <= COAST_DOWNSHIFT_S


def test_upshift_again_after_kickdown(bench):
    drive_to_gear(bench, 3)
    bench.set("accel_pedal_pct", 100)
    bench.wait_until("gear < 3", timeout_s=KICKDOWN_S)
    bench.sleep(2.0)
    bench.set("accel_pedal_pct", 30)
    bench.wait_until("gear >= 3", timeout_s=2.0)


# ---------------------------------------------------------------- faults: CAN
def test_engine_message_lost_ends_torque_request(bench):
    bench.set("accel_pedal_pct", 100)         # full-pedal launch: the traction limit requests torque
    bench.wait_until("TCU_EngineCmd.TorqueRequestActive == 1", timeout_s=1.5)
    fid = bench.inject("can.omit", message="VEH_Driver")
    t0 = fault_start(bench, fid)
    bench.sleep(max(0.0, t0 + ENGINE_MSG_TIMEOUT_S - bench.time_s))
    # from the limit on no torque request while the engine's message is missing
    holds_not(bench, "TCU_EngineCmd.TorqueRequestActive == 1", 0.5)
    reported(bench, "engine_message")
    # the last values stand in: the gearbox drives on
    currents = bench.read_many(["TCU_ClutchCmd.SolenoidCurrent1", "TCU_ClutchCmd.SolenoidCurrent2"])
    assert max(currents.values()) > 0.3, f"no clutch driving: {currents}"


def test_shaft_speeds_lost_open_both_clutches(bench):
    drive_to_gear(bench, 2)
    reaction(bench, CLUTCHES_OPEN, SPEED_MSG_TIMEOUT_S, "can.omit", message="DCT_ShaftSpeeds")
    holds_not(bench, CLUTCH_DRIVES, 0.3)      # stays open while the message is missing
    reported(bench, "can_timeout")


def test_single_crc_error_is_debounced(bench):
    drive_to_gear(bench, 2)
    bench.inject("can.bad_crc", message="DCT_ShaftSpeeds", duration_s=0.002)  # one frame
    holds_not(bench, CLUTCHES_OPEN, 0.3)
    assert bench.read("gear") == 2


def test_crc_errors_open_both_clutches(bench):
    drive_to_gear(bench, 2)
    reaction(bench, CLUTCHES_OPEN, E2E_DEBOUNCE_S, "can.bad_crc", message="DCT_ShaftSpeeds")
    reported(bench, "can_crc")


def test_frozen_counter_opens_both_clutches(bench):
    drive_to_gear(bench, 2)
    reaction(bench, CLUTCHES_OPEN, E2E_DEBOUNCE_S, "can.freeze_counter", message="DCT_Clutch")
    reported(bench, "can_counter")


def test_recovers_when_the_message_returns(bench):
    drive_to_gear(bench, 2)
    fid = bench.inject("can.omit", message="DCT_ShaftSpeeds", duration_s=0.2)
    bench.wait_until(CLUTCHES_OPEN, timeout_s=SPEED_MSG_TIMEOUT_S + 0.5)
    end = fault_start(bench, fid) + 0.2
    t = bench.wait_until(CLUTCH_DRIVES, timeout_s=RECOVERY_S + 0.5)
    assert t >= end, "no clutch may close while the speeds are missing"
    assert t - end <= RECOVERY_S
    v0 = bench.read("vehicle_speed_kmh")
    bench.sleep(1.0)
    assert bench.read("vehicle_speed_kmh") > v0, "driving again after the recovery"


# ---------------------------------------------------------------- faults: signals and hardware
def test_input_shaft2_speed_invalid_avoids_even_gears(bench):
    bench.inject("signal.invalid", signal="DCT_ShaftSpeeds.InputShaft2Speed")
    bench.set("accel_pedal_pct", 30)
    bench.wait_until(has_dtc("input_speed2"), timeout_s=1.0)
    bench.wait_until("gear == 3", timeout_s=12.0)       # 1 -> 3 on input shaft 1 only
    holds_not(bench, "gear == 2 or gear == 4 or gear == 6", 2.0)


def test_clutch2_pressure_stuck_while_shifting_limp_home(bench):
    bench.inject("signal.hold", signal="DCT_Clutch.ClutchPressure2",
                 when="TCU_Status.ShiftActive == 1")
    bench.set("accel_pedal_pct", 30)
    bench.wait_until("TCU_Status.LimpHome == 1", timeout_s=8.0)
    reported(bench, "clutch2_pressure")


def test_line_pressure_loss_limp_home(bench):
    drive_to_gear(bench, 2)
    reaction(bench, "TCU_Status.LimpHome == 1", DIAG_S, "hydraulics.line_pressure_loss", loss=0.8)
    reported(bench, "line_pressure")
    bench.wait_until(CLUTCHES_OPEN, timeout_s=0.1)      # the safe state


def test_fork_jammed_reports_engagement_failure_and_uses_another_gear(bench):
    bench.inject("fork.jammed", sleeve="2-4")
    bench.set("accel_pedal_pct", 30)
    bench.wait_until(has_dtc("gear_engagement"), timeout_s=3.0)
    bench.wait_until("gear == 3", timeout_s=12.0)        # 2nd cannot engage: 1 -> 3
    assert int(bench.tcu_status()["InhibitedGears"]) & 0b10, "2nd must stay inhibited"


def test_solenoid_open_reports_pressure_implausible(bench):
    drive_to_gear(bench, 2)
    reaction(bench, has_dtc("clutch2_pressure"), DIAG_S, "valve.solenoid_open", clutch=2)


def test_clutch_friction_fade_is_diagnosed_as_slip(bench):
    drive_to_gear(bench, 3)                   # 3rd: K1 closed, about 60 Nm at 30 % pedal
    bench.wait_until("TCU_Status.ShiftActive == 0", timeout_s=2.0)
    bench.sleep(0.5)                          # K1 at its lock pressure
    # 95 % of the friction lost: K1 holds about 20 Nm at its lock pressure, it slips
    reaction(bench, has_dtc("clutch1_slip"), DIAG_S, "clutch.friction_fade", clutch=1,
             loss=0.95)
