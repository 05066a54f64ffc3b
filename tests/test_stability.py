"""Explicit Euler stability of the default car, and convergence of the step.

Every stiff coupling of the plant is a damped oscillator or a first-order
lag; explicit Euler with sub-step h is stable for a mode lambda when
|1 + lambda h| < 1. These tests compute lambda for each coupling from the
parameters (the stiffest configuration of each: the lightest inertia behind
it) and requires that Euler keeps at least half of the mode's physical
decay per sub-step: 1 - |1 + lambda h| >= 0.5 (1 - |exp(lambda h)|). A
parameter change that would make the real-time step ring or diverge fails
here with the coupling named. The last test checks the step itself: the default sub-step against a
ten times finer one over a whole launch.
"""

import itertools
import math

import numpy as np
import pytest

from plant import Plant
from plant.params import load_params

P = load_params()
H = P["solver"]["step_s"] / P["solver"]["substeps"]
GB = P["gearbox"]


def margin(roots):
    """Smallest share of the exact per-step decay that Euler keeps."""
    return min((1 - abs(1 + r * H)) / (1 - abs(np.exp(r * H))) for r in np.atleast_1d(roots))


def amplification(mass, damping, stiffness):
    """margin of the roots of m s^2 + c s + k."""
    return margin(np.roots([mass, damping, stiffness]))


def lag(rate):
    """margin of the first-order mode -rate."""
    return margin(-rate)


def input_inertia(shaft):
    gears = (0, 2, 4, 6) if shaft == 0 else (1, 3, 5)
    return GB["input_shaft_inertia_kgm2"][shaft] + sum(
        GB["idle_gear_inertia_kgm2"][g] / GB["ratio"][g] ** 2 for g in gears)


def modes():
    """(name, margin) of every stiff coupling."""
    out = []
    je = P["engine"]["inertia_kgm2"]
    for k, clutch in enumerate(P["clutch"]):
        ji = input_inertia(k)
        j = je * ji / (je + ji)
        f = clutch["friction"]
        out.append((f"clutch[{k}] stick", amplification(j, f["damping_nms_per_rad"], f["stiffness_nm_per_rad"])))
    shaft_of_gear = (0, 1, 0, 1, 0, 1, 0)
    sleeve_of_gear = (0, 1, 0, 1, 2, 3, 2)
    for g in range(7):
        # the light input shaft between its stuck clutch and the engaged gear:
        # both springs and both dampers act on it, the engine and the car
        # (heavy) held; the dampers together set its fastest root
        k = shaft_of_gear[g]
        f, s = P["clutch"][k]["friction"], GB["sync"][sleeve_of_gear[g]]
        r2 = GB["ratio"][g] ** 2  # the gear's spring acts on the gear's side: seen from the input shaft / r^2
        out.append((f"input shaft {k + 1} between K{k + 1} stuck and gear {g + 1}",
                    amplification(input_inertia(k), f["damping_nms_per_rad"] + s["damping_nms_per_rad"] / r2,
                                  f["stiffness_nm_per_rad"] + s["stiffness_nm_per_rad"] / r2)))
    for g in range(7):
        s = GB["sync"][sleeve_of_gear[g]]
        j = input_inertia(shaft_of_gear[g]) * GB["ratio"][g] ** 2  # reduced to the output shaft
        out.append((f"gear {g + 1} engaged", amplification(j, s["damping_nms_per_rad"], s["stiffness_nm_per_rad"])))
        ts = s["cone_mu"] * s["cone_radius_m"] / math.sin(math.radians(s["cone_half_angle_deg"])) \
            * GB["max_fork_force_n"]
        rate = 2 * ts / (s["tanh_speed_rad_s"] * j)  # slope of T_s tanh(2 w / w0)
        out.append((f"gear {g + 1} synchronizing", lag(rate)))
    for name, s in zip(("1-3", "2-4", "5-R", "6-N"), GB["sync"]):
        detent_k = s["detent_force_n"] / 0.2e-3  # reached 0.2 mm from neutral (synchronizer.c)
        out.append((f"sleeve {name} detent", amplification(s["sleeve_mass_kg"], s["sleeve_damping_ns_per_m"], detent_k)))
    dl = P["driveline"]
    jw = P["front_wheel"]["inertia_kgm2"]
    for side in ("left", "right"):
        out.append((f"{side} half-shaft", amplification(jw, dl[f"{side}_damping_nms_per_rad"],
                                                        dl[f"{side}_stiffness_nm_per_rad"])))
    tyre = P["tyre"]
    r = tyre["radius_m"]
    k_contact = tyre["pkx1"] * tyre["nominal_load_n"] * 1.5 / tyre["relaxation_length_m"]  # 1.5 x load
    for name, wheel, count in (("front", P["front_wheel"], 1), ("rear", P["rear_wheels"], 2)):
        b = wheel["brake"]
        out.append((f"{name} brake stick", amplification(wheel["inertia_kgm2"], b["damping_nms_per_rad"],
                                                         b["stiffness_nm_per_rad"])))
        m = wheel["inertia_kgm2"] / r**2
        out.append((f"{name} tyre contact at standstill",
                    amplification(m, count * tyre["low_speed_damping_ns_per_m"], count * k_contact)))
        fz = 1.5 * tyre["nominal_load_n"] * count
        rr = tyre["rolling_resistance"] * fz * r / tyre["rolling_smoothing_rad_s"]
        out.append((f"{name} rolling resistance at standstill", lag(rr / wheel["inertia_kgm2"])))
    out.append(("tyre relaxation at 70 m/s", lag(70.0 / tyre["relaxation_length_m"])))
    v = P["vehicle"]
    for axle in ("front", "rear"):
        k = v[f"{axle}_tyre_vertical_n_per_m"] + v[f"{axle}_spring_n_per_m"]
        c = v["tyre_vertical_damping_ns_per_m"] + v[f"{axle}_damper_ns_per_m"]
        out.append((f"{axle} spindle hop", amplification(v[f"{axle}_unsprung_kg"], c, k)))
    e = P["engine"]
    for tau in ("tau_rise_s", "tau_boost_s", "tau_fall_s"):
        out.append((f"engine {tau}", lag(1.0 / e[tau])))
    out += hydraulic_modes()
    return out


def hydraulic_modes():
    """The hydraulics run at their own sub-step H / hydraulics.substeps."""
    hy = P["hydraulics"]
    v, oil = hy["valve"], hy["oil"]
    hh = H / hy["substeps"]
    scale = hh / H  # margin() uses H: scale the roots instead

    def at_hh(roots):
        return margin(np.atleast_1d(roots) * scale)

    m, c, k = v["spool_mass_kg"], v["viscous_friction_ns_per_m"], v["spring_n_per_m"]
    out = [("valve spool on its spring", at_hh(np.roots([m, c, k]))),
           ("valve spool on an end stop", at_hh(np.roots([m, c + v["stop_damping_ns_per_m"],
                                                          k + v["stop_stiffness_n_per_m"]]))),
           ("valve friction lag (eq. 10)", at_hh(-1.0 / v["friction_tau_s"])),
           ("solenoid lag (eq. 9)", at_hh(-1.0 / v["solenoid_tau_s"])),
           ("line pressure lag", at_hh(-1.0 / hy["supply"]["tau_s"]))]
    width = v["edge_width_mm"] * 1e-3
    a_fb = math.pi / 4 * (v["spool_diameter_mm"] ** 2 - v["rod_diameter_mm"] ** 2) * 1e-6
    line = hy["supply"]["line"]["pressure_bar"][0] * 1e5
    for k_clutch, clutch in enumerate(P["clutch"]):
        vol = hy["chamber_volume_cm3"][k_clutch] * 1e-6
        area = clutch["piston_area_m2"]
        stiff = clutch["return_spring_n_per_m"] + clutch["pack_stiffness_n_per_m"]
        for bar in (5.0, 10.0, 19.0):
            # pressure loop with the pack clamped: m s^3 + c s^2 + k s + K,
            # K = A_fb (dQ/dx) / C: spool -> flow -> pressure -> spool force
            p_abs = bar * 1e5 + 1e5
            compliance = area**2 / stiff + vol * ((1 - oil["air_fraction"]) / oil["bulk_modulus_pa"]
                                                  + oil["air_fraction"] * 1e5 / p_abs**2)
            kq = v["cd_max"] * width * math.sqrt(2 * (line - bar * 1e5) / oil["density_kg_m3"])
            loop = a_fb * kq / compliance
            out.append((f"K{k_clutch + 1} pressure loop at {bar:g} bar", at_hh(np.roots([m, c, k, loop]))))
        # chamber emptying at 0 bar through the wide-open tank edge: laminar
        # conductance (C_d ~ 2 Re / Re_t) over the air's compliance
        opening = v["spool_travel_mm"] * 1e-3
        g = v["cd_max"] * 2 / v["transition_reynolds"] * (2 * opening / oil["viscosity_m2_s"]) \
            * width * opening * 2 / oil["density_kg_m3"]
        c0 = vol * oil["air_fraction"] / 1e5
        out.append((f"K{k_clutch + 1} chamber draining at 0 bar", at_hh(-g / c0)))
    return out


SHAFT_OF_GEAR = (0, 1, 0, 1, 0, 1, 0)
SLEEVE_OF_GEAR = (0, 1, 0, 1, 2, 3, 2)


def tie_up_radius(clutches, gears):
    """Spectral radius of the step's map for the engine, both input shafts,
    the carrier and the two front wheels, with the stuck clutches and the
    engaged gears given, and the half-shafts. Two gears engaged on one input
    shaft lock it to the output at two ratios (a tie-up: a faulty TCU or bad
    frames can command one); then, as gearbox.c does, the tied shafts and the
    carrier take their dampers implicitly (the step divides by the inertia
    plus h x the dampers); everything else is explicit Euler."""
    je, jw = P["engine"]["inertia_kgm2"], P["front_wheel"]["inertia_kgm2"]
    fd, ratio = GB["final_drive"], GB["ratio"]
    jc = GB["differential_inertia_kgm2"] + sum(j * f * f for j, f in zip(GB["output_shaft_inertia_kgm2"], fd))
    m = np.diag([je, input_inertia(0), input_inertia(1), jc, jw, jw])
    k_mat, c_mat = np.zeros((6, 6)), np.zeros((6, 6))

    def link(i, j, k, c, ri=1.0, rj=1.0):   # torque k (ri x_i - rj x_j) + c (ri v_i - rj v_j)
        v = np.zeros(6)
        v[i] += ri
        v[j] -= rj
        k_mat[:] += k * np.outer(v, v)
        c_mat[:] += c * np.outer(v, v)
    for k in clutches:
        f = P["clutch"][k]["friction"]
        link(0, 1 + k, f["stiffness_nm_per_rad"], f["damping_nms_per_rad"])
    for g in gears:
        s = GB["sync"][SLEEVE_OF_GEAR[g]]
        link(1 + SHAFT_OF_GEAR[g], 3, s["stiffness_nm_per_rad"], s["damping_nms_per_rad"],
             1 / ratio[g], fd[0 if g < 4 else 1])
    dl = P["driveline"]
    link(3, 4, dl["left_stiffness_nm_per_rad"], dl["left_damping_nms_per_rad"])
    link(3, 5, dl["right_stiffness_nm_per_rad"], dl["right_damping_nms_per_rad"])
    step_m = m.copy()
    tied = [sum(1 for g in gears if SHAFT_OF_GEAR[g] == shaft) > 1 for shaft in (0, 1)]
    if any(tied):
        for shaft in (0, 1):
            if tied[shaft]:
                c = sum(GB["sync"][SLEEVE_OF_GEAR[g]]["damping_nms_per_rad"] / ratio[g] ** 2
                        for g in gears if SHAFT_OF_GEAR[g] == shaft)
                c += P["clutch"][shaft]["friction"]["damping_nms_per_rad"] if shaft in clutches else 0.0
                step_m[1 + shaft, 1 + shaft] += H * c
        step_m[3, 3] += H * sum(GB["sync"][SLEEVE_OF_GEAR[g]]["damping_nms_per_rad"] * fd[0 if g < 4 else 1] ** 2
                                for g in gears)
    inv = np.linalg.inv(step_m)
    a = np.block([[np.eye(6), H * np.eye(6)], [-H * inv @ k_mat, np.eye(6) - H * inv @ c_mat]])
    return float(np.abs(np.linalg.eigvals(a)).max())


def tie_ups():
    """Every combination: each clutch stuck or not, each sleeve in neutral or
    on either of its gears."""
    sleeves = ((0, 2), (1, 3), (4, 6), (5,))
    for clutches in ((), (0,), (1,), (0, 1)):
        for choice in itertools.product(*[(None, *g) for g in sleeves]):
            yield clutches, tuple(g for g in choice if g is not None)


def test_every_tie_up_is_stable():
    """Any gears engaged, either clutch stuck: the step never amplifies (the
    largest eigenvalue of its map is the rigid turning of everything, 1, to
    rounding). All explicit, 105 of these combinations (each with two gears
    on one input shaft) grow at 0.5 ms, the worst (both clutches stuck, four
    gears in) 2.9x a step: a fuzz run's random frames found it."""
    worst = max((tie_up_radius(c, g), c, g) for c, g in tie_ups())
    assert worst[0] <= 1.0 + 1e-6, f"clutches {worst[1]} stuck, gears {worst[2]}: x{worst[0]:.3f} per step"


def test_without_a_tie_up_explicit_euler_is_stable():
    """Every gearbox state a TCU uses (at most one gear on each input shaft)
    is stable with the explicit step gearbox.c keeps there
    (tests/test_components.py: no implicit dampers without a tie-up)."""
    assert all(tie_up_radius(c, g) <= 1.0 + 1e-6 for c, g in tie_ups()
               if all(sum(1 for x in g if SHAFT_OF_GEAR[x] == s) <= 1 for s in (0, 1)))


@pytest.mark.parametrize("name,kept", modes(), ids=[m[0] for m in modes()])
def test_every_coupling_is_stable_at_the_sub_step(name, kept):
    assert kept >= 0.5, f"{name}: Euler keeps {kept:.0%} of the decay at h = {H * 1e3:.3f} ms"


def launch(tmp_path, substeps):
    path = tmp_path / f"sub{substeps}.toml"
    path.write_text(f"[solver]\nsubsteps = {substeps}\n")
    from plant.scenario import load_scenario
    from plant.simulate import run
    plant = Plant(path)
    result = run(plant, load_scenario("launch-1st"))
    names = list(result.names)
    data = np.asarray(result.data)
    return {n: data[:, names.index(n)] for n in
            ("vehicle_speed_kmh", "engine_speed_rpm", "vehicle_accel_mps2")}


def test_default_step_converges_to_a_finer_step(tmp_path):
    """launch-1st with the default sub-step and one ten times finer: the
    vehicle speed agrees within 0.2 % of its peak, the engine speed within
    0.5 % of its peak, the acceleration RMS within 1 % of its peak. Measured
    at 0.5 ms: 0.055 %, 0.33 % and 0.31 %; the bounds leave room for
    parameter changes but catch a step that is too coarse for the model."""
    coarse = launch(tmp_path, P["solver"]["substeps"])
    fine = launch(tmp_path, 10 * P["solver"]["substeps"])
    for name, bound in (("vehicle_speed_kmh", 0.002), ("engine_speed_rpm", 0.005)):
        a, b = coarse[name], fine[name]
        assert np.abs(a - b).max() < bound * np.abs(b).max(), name
    a, b = coarse["vehicle_accel_mps2"], fine["vehicle_accel_mps2"]
    assert np.sqrt(np.mean((a - b) ** 2)) < 0.01 * np.abs(b).max()
