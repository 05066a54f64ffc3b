"""Whole-plant behaviour: kinematics, synchronizer timing (eq. 6), clutch
stick-slip, coastdown, parking on a grade, energy.

Each test drives the assembled plant through its public inputs only, at the
real step of 0.5 ms, and compares with a law computed independently from the
parameters.
"""

import math

import numpy as np
import pytest

from plant import Plant

RPM = 30.0 / math.pi  # rpm per rad/s
GEARS = ["1", "2", "3", "4", "5", "6", "R"]
# (sleeve index, side, output shaft 1/2) of each gear in the DSG 02E
LAYOUT = {"1": (0, 1, 1), "2": (1, 1, 1), "3": (0, -1, 1), "4": (1, -1, 1),
          "5": (2, 1, 2), "6": (3, 1, 2), "R": (2, -1, 2)}
INPUT_SHAFT = {"1": 1, "3": 1, "5": 1, "R": 1, "2": 2, "4": 2, "6": 2}


def pressure_plant(params_path=None):
    """The mechanics are tested with the clutch pressures as inputs (the
    pressure-commanded mode): the hydraulics have tests of their own."""
    return Plant(params_path, overrides={"hydraulics": {"pressure_commanded": 1}})


def run(plant, seconds, **inputs):
    for name, value in inputs.items():
        plant.inputs[name] = value
    plant.step(int(round(seconds / plant.step_s)))


def record(plant, seconds, names, **inputs):
    """Step one 0.5 ms step at a time and return the named outputs per step."""
    for name, value in inputs.items():
        plant.inputs[name] = value
    n = int(round(seconds / plant.step_s))
    out = np.empty((n, len(names)))
    for i in range(n):
        plant.step(1)
        out[i] = [plant.outputs[k] for k in names]
    return out


def write_override(tmp_path, text):
    path = tmp_path / "override.toml"
    path.write_text(text)
    return path


# ---------------------------------------------------------------- kinematics


@pytest.mark.parametrize("gear", GEARS)
def test_locked_gear_speed_ratio_is_the_gear_ratio(gear):
    """Gear engaged, its clutch locked, light throttle: input / output shaft
    speed = gear ratio within 0.5 % (the shaft and gear stiffness only twists
    under a steady torque, so the speeds match once transients have died)."""
    plant = pressure_plant()
    gb = plant.params["gearbox"]
    idx = GEARS.index(gear)
    sleeve, side, out_shaft = LAYOUT[gear]
    shaft = INPUT_SHAFT[gear]
    ratio = gb["ratio"][idx] * (-1 if gear == "R" else 1)
    fd = gb["final_drive"][out_shaft - 1]
    radius = plant.params["tyre"]["radius_m"]
    # engine at 2500 rpm
    v_kmh = 2500 / RPM / (ratio * fd) * radius * 3.6
    sleeves = [0, 0, 0, 0]
    sleeves[sleeve] = side
    locked = [0, 0]
    locked[shaft - 1] = 1
    plant.reset(vehicle_speed_kmh=v_kmh, sleeves=sleeves, clutch_locked=locked)
    run(plant, 2.0, accel_pedal_pct=25.0, **{f"clutch{shaft}_pressure_bar": 20.0})
    o = plant.outputs
    w_in = float(o[f"input_shaft{shaft}_speed_rpm"])
    w_out = float(o[f"output_shaft{out_shaft}_speed_rpm"])
    assert w_in / w_out == pytest.approx(ratio, rel=0.005)
    assert abs(float(o[f"clutch{shaft}_slip_rpm"])) < 1.0
    assert float(o[f"sync{sleeve + 1}_gear"]) == (-1 if gear == "R" else int(gear))
    # wheels: carrier speed = output shaft / final drive; ground speed =
    # wheel speed x radius at the low slip of light throttle (< 1 %)
    w_wheel = 0.5 * (float(o["wheel_speed_fl_rpm"]) + float(o["wheel_speed_fr_rpm"]))
    assert w_wheel == pytest.approx(w_out / fd, rel=0.005)
    v = float(o["vehicle_speed_kmh"]) / 3.6
    assert w_wheel / RPM * radius == pytest.approx(v, rel=0.01)


# ------------------------------------------------------------- synchronizer

NO_DRAG = """
[gearbox]
input_drag_nm = [0.0, 0.0]
input_drag_nms_per_rad = [0.0, 0.0]
mesh_efficiency = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
idle_gear_drag_nms_per_rad = 0.0
[[clutch]]
drag_nms_per_rad = 0.0
[[clutch]]
drag_nms_per_rad = 0.0
"""


def synchronizing_time(tmp_path, force_n, cone_angle_deg=None):
    """Engage 2nd (sleeve 2-4, +) while coasting at 30 km/h in neutral with
    the engine off, so input shaft 2 starts at rest. Returns the measured
    phase times and the eq. 6 prediction."""
    text = NO_DRAG
    if cone_angle_deg is not None:
        text += f"[[gearbox.sync]]\n[[gearbox.sync]]\ncone_half_angle_deg = {cone_angle_deg}\n"
    plant = pressure_plant(write_override(tmp_path, text))
    plant.reset(vehicle_speed_kmh=30.0, engine_on=0)
    names = ["time_s", "sync2_state", "fork2_position_mm", "input_shaft2_speed_rpm",
             "output_shaft1_speed_rpm"]
    trace = record(plant, 2.0, names, engine_on=0, fork_force2_n=force_n)
    phase = trace[:, 1]
    t_sync = trace[np.argmax(phase >= 1), 0]
    t_engaged = trace[np.argmax(phase >= 2), 0]
    # order: never back to a lower phase, all three phases seen
    assert np.all(np.diff(phase) >= 0) and phase[0] == 0 and phase[-1] == 2
    # eq. 6: T_s = mu r_s / sin(alpha) F; the loose gear with input shaft 2
    # (J reduced to the gear: J2 r^2) is brought to the output shaft speed
    p = plant.params
    gb, sync = p["gearbox"], p["gearbox"]["sync"][1]
    r2 = gb["ratio"][1]
    j2 = gb["input_shaft_inertia_kgm2"][1] + sum(
        gb["idle_gear_inertia_kgm2"][g] / gb["ratio"][g] ** 2 for g in (1, 3, 5))
    alpha = math.radians(sync["cone_half_angle_deg"])
    t_s = sync["cone_mu"] * sync["cone_radius_m"] / math.sin(alpha) * force_n
    i0 = np.argmax(phase >= 1)
    slip0 = trace[i0, 4] / RPM  # the gear (input shaft at rest) against the shaft
    predicted = j2 * r2**2 * slip0 / t_s
    return t_engaged - t_sync, predicted, trace


@pytest.mark.parametrize("force_n", [200.0, 400.0, 800.0])
def test_synchronizing_time_follows_eq6_over_force(tmp_path, force_n):
    """Measured synchronizing time within 5 % of J w_r / T_s with T_s from
    eq. 6 (the tanh of eq. 3 adds about w_0/2 ln(...) / w_r, under 2 %)."""
    measured, predicted, trace = synchronizing_time(tmp_path, force_n)
    assert measured == pytest.approx(predicted, rel=0.05)
    # the sleeve ends fully engaged, the gear turning with its shaft
    assert trace[-1, 2] == pytest.approx(8.5, abs=1e-6)
    r2 = pressure_plant().params["gearbox"]["ratio"][1]
    assert trace[-1, 3] / r2 == pytest.approx(trace[-1, 4], rel=0.005)


def test_synchronizing_time_scales_with_cone_angle(tmp_path):
    """Eq. 6: the time scales with sin(alpha) at equal force, for cones that still
    block: the cone torque mu r_s F / sin(alpha) must exceed the index torque of the
    ring's chamfers, F r_d / tan(beta) (10.4 N m at 400 N), or the ring indexes
    before the speeds are equal. 8 degrees: 11.5 N m, blocks (9 degrees, 10.2 N m,
    would not)."""
    sync = pressure_plant().params["gearbox"]["sync"][1]
    cone = sync["cone_mu"] * sync["cone_radius_m"] / math.sin(math.radians(8.0))
    index = sync["dog_radius_m"] / math.tan(math.radians(sync["ring_chamfer_angle_deg"]))
    assert cone > index
    t_65, _, _ = synchronizing_time(tmp_path, 400.0)
    t_8, _, _ = synchronizing_time(tmp_path, 400.0, cone_angle_deg=8.0)
    assert t_8 / t_65 == pytest.approx(math.sin(math.radians(8.0)) / math.sin(math.radians(6.5)),
                                       rel=0.03)


def test_pushing_through_the_blocker_counts_a_clash():
    """A fork force above the blocker's strength engages before the speeds
    match: counted as a clash; a normal force never is."""
    plant = pressure_plant()
    plant.reset(vehicle_speed_kmh=30.0, sleeves=(1, 0, 0, 0), clutch_locked=(1, 0))
    run(plant, 1.0, clutch1_pressure_bar=20.0, accel_pedal_pct=20.0, fork_force2_n=400.0)
    assert float(plant.outputs["sync2_state"]) == 2
    assert float(plant.outputs["gear_clashes"]) == 0
    blocker = plant.params["gearbox"]["sync"][2]["blocker_force_max_n"]
    run(plant, 0.5, fork_force3_n=blocker + 100.0)  # 5th with input shaft 1 in 1st
    assert float(plant.outputs["gear_clashes"]) == 1


# -------------------------------------------------------------------- clutch


def third_gear_plant(pressure_bar):
    plant = pressure_plant()
    plant.reset(vehicle_speed_kmh=60.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0))
    plant.inputs["clutch1_pressure_bar"] = pressure_bar
    return plant


def test_clutch_below_capacity_stays_locked_above_slips():
    """K1 in 3rd at 60 km/h: with a capacity above the engine's full-load
    torque it stays locked at full throttle; below it, it slips."""
    plant = third_gear_plant(20.0)
    run(plant, 1.0, accel_pedal_pct=100.0)
    o = plant.outputs
    assert float(o["clutch1_capacity_nm"]) > 400.0
    assert abs(float(o["clutch1_slip_rpm"])) < 1.0
    plant = third_gear_plant(5.5)  # about 150 Nm of capacity
    run(plant, 1.0, accel_pedal_pct=100.0)
    o = plant.outputs
    assert float(o["clutch1_capacity_nm"]) < float(o["engine_torque_nm"])
    assert float(o["clutch1_slip_rpm"]) > 100.0
    # sliding at the capacity (Stribeck: mu_kinetic >= mu_static here)
    assert float(o["clutch1_torque_nm"]) >= float(o["clutch1_capacity_nm"])


def test_clutch_torque_is_continuous_through_stick_slip_stick():
    """Pressure ramps from 20 bar down to 4 and back at full throttle in 3rd:
    the clutch sticks, slips and sticks again. Sampled at every 0.5 ms step,
    the transmitted torque never jumps: at the re-lock it falls from the
    sliding capacity (about 520 Nm) to what the locked shafts need (about
    270 Nm) through the stick stiffness, over the stuck mode's period
    (about 5 ms, 10 steps). An ideal switch would drop by the whole
    250 Nm in one step; we allow 5 % of the capacity per step."""
    plant = third_gear_plant(20.0)
    run(plant, 0.5, accel_pedal_pct=100.0)
    names = ["clutch1_torque_nm", "clutch1_slip_rpm"]
    traces = []
    for p in np.concatenate([np.linspace(20, 4, 800), np.full(400, 4.0), np.linspace(4, 20, 800),
                             np.full(1000, 20.0)]):
        traces.append(record(plant, plant.step_s, names, clutch1_pressure_bar=p))
    trace = np.vstack(traces)
    torque, slip = trace[:, 0], trace[:, 1]
    assert np.abs(slip[:100]).max() < 1.0            # stuck at first
    assert slip.max() > 200.0                        # slipping in the middle
    assert np.abs(slip[-200:]).max() < 1.0           # stuck again at the end
    capacity = float(plant.outputs["clutch1_capacity_nm"])
    assert np.abs(np.diff(torque)).max() < 0.05 * capacity


# ------------------------------------------------------------------ vehicle


def test_coastdown_matches_drag_and_rolling_resistance():
    """In neutral from 100 km/h: m_eff dv/dt = -(c_rr(v) m g + rho/2 Cd A v^2
    + T_diff / R), m_eff with the wheels, carrier and output shafts turning
    with the car, T_diff the differential's bearing drag. Within 5 % at every
    speed down to 40 km/h; what is left (about 3 %) is the drag of the loose
    gears, which turn against the output shafts at input-shaft speeds."""
    plant = pressure_plant()
    plant.reset(vehicle_speed_kmh=100.0)
    p = plant.params
    veh, tyre = p["vehicle"], p["tyre"]
    r = tyre["radius_m"]
    gb = p["gearbox"]
    j_carrier = gb["differential_inertia_kgm2"] + sum(
        j * fd**2 for j, fd in zip(gb["output_shaft_inertia_kgm2"], gb["final_drive"]))
    j_wheels = 2 * p["front_wheel"]["inertia_kgm2"] + p["rear_wheels"]["inertia_kgm2"]
    m_eff = veh["mass_kg"] + (j_wheels + j_carrier) / r**2
    run(plant, 1.0)  # let the start transient (tyre deflections) settle
    checked = 0
    while float(plant.outputs["vehicle_speed_kmh"]) > 40.0:
        run(plant, 2.0)
        v = float(plant.outputs["vehicle_speed_kmh"]) / 3.6
        w_carrier = v / r
        f_rr = tyre["rolling_resistance"] + tyre["rolling_resistance_speed"] * (
            v / tyre["rolling_resistance_ref_speed_m_s"]) ** 2.5
        resist = f_rr * veh["mass_kg"] * veh["gravity_m_s2"] + 0.5 * veh[
            "air_density_kg_m3"] * veh["drag_coefficient"] * veh["frontal_area_m2"] * v * v + (
            gb["output_drag_nm"] + gb["output_drag_nms_per_rad"] * w_carrier) / r
        assert float(plant.outputs["vehicle_accel_mps2"]) == pytest.approx(-resist / m_eff, rel=0.05)
        checked += 1
    assert checked > 20


def test_parked_on_a_10_percent_grade_with_the_brake_does_not_creep():
    """10 % grade, brake pedal 50 %, neutral, engine idling: once the tyres
    and brakes have taken the load (1 s), the car moves less than 1 mm in
    10 s, and it does not ring."""
    plant = pressure_plant()
    plant.reset()
    run(plant, 1.0, road_grade_pct=10.0, brake_pedal_pct=50.0)
    x0 = float(plant.outputs["distance_m"])
    trace = record(plant, 10.0, ["distance_m", "vehicle_speed_kmh"])
    assert np.abs(trace[:, 0] - x0).max() < 1e-3
    assert np.abs(trace[:, 1]).max() < 0.01  # km/h
    # the settling itself is the tyres' and brakes' compliance: millimetres
    assert abs(x0) < 5e-3


def test_standing_car_without_brake_stays_put():
    """Level road, neutral, no brake: no creeping (the tyre contact is a
    spring-damper near standstill, rolling resistance holds as static
    friction). The rolling resistance fades out over the wheel speed
    tyre.rolling_smoothing_rad_s (0.008 rad/s, 2.5 mm/s at the road), so the
    gearbox's drags turn the wheels at a small share of that: measured
    0.155 mm in 5 s (0.03 mm/s, 1.2 % of the smoothing speed); at most 0.2 mm."""
    plant = pressure_plant()
    plant.reset()
    trace = record(plant, 5.0, ["distance_m"])
    assert np.abs(trace[:, 0]).max() < 2e-4


def test_load_transfer_under_acceleration():
    """Full throttle in 2nd: the front axle unloads by about m a h / L (2D
    body on springs; within 10 %: tyre forces act at the wheel centres and
    the pitch is still settling)."""
    plant = pressure_plant()
    plant.reset(vehicle_speed_kmh=40.0, sleeves=(0, 1, 0, 0), clutch_locked=(0, 1))
    static_front = float(plant.outputs["front_axle_load_n"])
    run(plant, 1.5, clutch2_pressure_bar=20.0, accel_pedal_pct=100.0)
    veh = plant.params["vehicle"]
    a = float(plant.outputs["vehicle_accel_mps2"])
    expected = veh["mass_kg"] * a * veh["cg_height_m"] / veh["wheelbase_m"]
    drop = static_front - float(plant.outputs["front_axle_load_n"])
    assert a > 2.0
    assert drop == pytest.approx(expected, rel=0.10)
    assert float(plant.outputs["pitch_deg"]) > 0.0  # squat: nose up


# ------------------------------------------------------------------- energy

SOURCES_OFF = dict(accel_pedal_pct=0.0, brake_pedal_pct=0.0, engine_on=0.0, road_grade_pct=0.0,
                   fork_force1_n=0.0, fork_force2_n=0.0, fork_force3_n=0.0, fork_force4_n=0.0)


@pytest.mark.parametrize("case", ["third-gear-locked", "neutral", "twisted-driveline"])
def test_stored_energy_never_grows_with_all_sources_off(case):
    """Engine off, no pedal, no fork force, level road: the stored energy
    (kinetic energy of every inertia and mass + every spring: clutch and
    brake stick, sync, half-shafts, tyres, suspension + gravity) sampled at
    the 10 ms output rate never grows (tolerance: rounding, 1e-9 of it).
    Within single steps explicit Euler itself adds (h w)^2 of a spring's
    energy at a turning point (w the mode's frequency; the stiffest one
    wound up here is the engaged 1st gear's synchronizer spring on the input
    shaft: sqrt(15000 / (0.0164 x 3.462^2)) = 277 rad/s, (h w)^2 = 1.9 % per
    0.5 ms step; measured 1.25 %), so a single step may grow it by at most 2 %."""
    plant = pressure_plant()
    if case == "third-gear-locked":
        plant.reset(vehicle_speed_kmh=50.0, sleeves=(-1, 0, 0, 0), clutch_locked=(1, 0), engine_on=0)
        plant.inputs["clutch1_pressure_bar"] = 20.0
    elif case == "neutral":
        plant.reset(vehicle_speed_kmh=50.0, engine_on=0)
    else:
        # at rest in 1st, clutch open, with the half-shafts wound up: all the
        # energy is in springs and must ring down
        plant.reset(vehicle_speed_kmh=0.0, sleeves=(1, 0, 0, 0), engine_on=0)
        names = plant.state_names
        plant.state[names.index("driveline.left_twist_rad")] = 0.02
        plant.state[names.index("driveline.right_twist_rad")] = 0.03
    for name, value in SOURCES_OFF.items():
        plant.inputs[name] = value
    energy = [plant.energy()]
    for _ in range(6000):
        plant.step(1)
        energy.append(plant.energy())
    energy = np.array(energy)
    assert energy[-1] < energy[0]
    assert np.diff(energy[::20]).max() <= 1e-9 * energy[0]
    assert np.diff(energy).max() <= 2e-2 * energy[0]
