"""Detailed synchronizer reference model and its comparison with the plant's hybrid model.

The plant's synchronizer (``plant/csrc/synchronizer.c``) is the reference
paper's hybrid model: three phases, the cone torque of eq. 6 through a tanh
friction law, a blocker that releases at a lock speed. The paper checks its
hybrid model against a complex five-degree-of-freedom model (3 %
coupling-time error; 0.036 s against 4.018 s of computing for 0.8 s
simulated). This module is such a detailed model, written for that check, and
the comparison.

Detailed model: one single-cone synchronizer of the 2-4 sleeve and its gear
(2nd), five degrees of freedom, eleven states:

  sleeve translation      x_s, v_s  fork force, actuator damping, pre-synchronizing
                                    struts, chamfer and flank contacts with the
                                    blocker ring and the gear's dog teeth, end stop
  blocker-ring translation x_r, v_r struts push it onto the cone (axial contact,
                                    a penalty spring-damper), the sleeve's chamfers push it
  blocker-ring rotation   phi_r, w_r cone friction from the gear, indexing slot in
                                    the hub (penalty stops), chamfer and flank contacts
  gear rotation           phi_g, w_g the gear with its cone, the idle input shaft
                                    reflected to it, drag, dog-tooth contacts
  hub rotation            phi_h, w_h sleeve, hub and the shaft side (the car
                                    reflected to the output shaft)
  cone twist              z         the stick state of the cone friction

Cone friction is a reset-integrator stick-slip element (the plant's clutch
friction law, ``friction.c``): it sticks with a stiff spring-damper and slides
at mu r_c N, with N the normal force of the axial cone contact
(N = F_axial / sin(alpha)). Teeth are roof-shaped (two chamfer faces, then
flanks); a contact between two rows of teeth is found by separating axes (the
face normal against the flank normal, the smaller penetration wins) and acts
as a penalty spring-damper with Coulomb friction along the face (regularized
below ``friction_speed_m_s``). Nothing of eq. 6 is imposed: the axial force on
the ring, the blocking (cone torque against the chamfers' indexing torque),
the ring's turn-back with the gear once the speeds match, the sleeve's passage
through the ring and the dog-tooth alignment all come out of the contacts.
Integration: semi-implicit (symplectic) Euler at a fixed 4 us step, a
fiftieth of the period of the stiffest contact (the ring on its cone seat,
0.22 ms); it keeps angular momentum exactly. SciPy is not installed and not
needed: the coupling times agree with a 1 us step within 0.01 %
(``tests/test_sync_detailed.py``).

Coupling time (both models): from the first fork force until both the slip has
fallen below the lock speed and the sleeve has passed through the blocker
ring (its chamfers past the ring's: the sleeve travel ``through_travel_m`` of
the detailed geometry, 3.86 mm; the hybrid model's sleeve is timed at the
same travel).

What the comparison shows: the synchronizing (slip) phases agree within
about 1 % (the hybrid model's tanh tail and lock speed add 2-8 ms); after
the speeds match the detailed model's sleeve must turn the blocker ring back
out of its way, and with it, through the still stuck cone, the gear and the
idle input shaft (0.07 kg m^2 at the gear): 17-30 ms. The plant's hybrid
model has this ring turn-back term: in the engaged phase, until the sleeve
has passed the ring (``ring_pass_travel_mm`` beyond the cone travel), its
mass includes the gear side's inertia felt through the chamfers,
J tan^2(beta) / r_b^2 (``ring_chamfer_angle_deg``, r_b = ``dog_radius_m``,
J = ``dct_sync_input.gear_inertia_*_kgm2`` from the gearbox). Without it the
hybrid sleeve moves on at once and the coupling time comes out short by
1-7 %, most at high force and small slip; with it the coupling times agree
within 3 %. ``propose`` shows both, in a Python replica of synchronizer.c.

API: ``compare(fork_force_n, slip_rpm, quick=False)``, ``compute_times(sim_s)``,
``cases(quick)``; the models: ``simulate_detailed``, ``simulate_hybrid_c``,
``simulate_hybrid_py`` with ``DetailedParams`` and ``Case``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

RAD_S_PER_RPM = math.pi / 30.0
SLEEVE = 1          # sleeve 2-4 of output shaft 1; its + side is 2nd gear
GEAR = 1            # gear index of 2nd
INPUT2_GEARS = (1, 3, 5)   # 2nd, 4th and 6th ride on input shaft 2
DETENT_TRAVEL_MM = 0.2     # synchronizer.c: full detent force 0.2 mm from neutral
SHAFT_INERTIA_KGM2 = 8.5   # output shaft 1 with the car reflected to it: 1400 kg on 0.316 m
                           # tyres through 4.118 (8.2) + wheels and differential (0.3)
RECORD_S = 0.0005          # time-series sample interval (the plant's step)


# ---------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class DetailedParams:
    """Detailed synchronizer: the plant's values plus the geometry the hybrid model does not need."""
    # --- the plant's synchronizer values ([[gearbox.sync]], filled by from_plant)
    cone_mu: float = 0.10
    cone_radius_m: float = 0.040
    cone_half_angle_deg: float = 6.5
    sleeve_mass_kg: float = 1.5
    sleeve_damping_ns_per_m: float = 2000.0
    cone_travel_mm: float = 3.0          # sleeve travel at which its chamfers block on the ring
    engaged_travel_mm: float = 8.5       # sleeve end stop, full dog engagement
    detent_force_n: float = 60.0         # the struts' ball detent
    lock_speed_rad_s: float = 0.5        # only for the coupling-time criterion
    dog_friction_mu: float = 0.15        # dog-tooth chamfer and flank friction
    tooth_radius_m: float = 0.045        # sleeve, ring and dog teeth (the plant's dog_radius_m)
    # --- geometry and contact values of the detailed model (estimates)
    teeth: int = 36                      # estimate: sleeve spline teeth (pitch 7.85 mm at 45 mm)
    chamfer_angle_deg: float = 60.0      # estimate: sleeve and ring chamfer face from the axis (120 deg
                                         # roof); the plant's ring_chamfer_angle_deg
    dog_chamfer_angle_deg: float = 60.0  # estimate: dog-tooth chamfer face from the axis
    tooth_width_pitch: float = 0.44      # estimate: tooth width / pitch (sleeve, ring, dog)
    slot_play_pitch: float = 0.25        # estimate: ring turns a quarter pitch either way in its slot
    ring_mass_kg: float = 0.06           # estimate: brass ring, 42 mm radius
    ring_inertia_kgm2: float = 1.0e-4    # estimate: 0.06 kg at about 41 mm
    ring_axial_play_mm: float = 0.5      # estimate: ring lift-off from the cone in neutral
    dog_tip_mm: float = 5.0              # estimate: sleeve travel where its apexes meet the dog apexes
    chamfer_mu: float = 0.10             # estimate: steel sleeve on brass ring chamfers, in oil
    friction_speed_m_s: float = 0.02     # tooth friction regularization (stability at the step)
    contact_stiffness_n_per_m: float = 2.0e7   # estimate: tooth contact, softened penalty
    contact_damping_ns_per_m: float = 600.0    # damping ratio about 0.3 on the ring
    dog_damping_ns_per_m: float = 6000.0       # estimate: restitution about 0.7 of the gear on a dog flank
    cone_axial_stiffness_n_per_m: float = 5.0e7  # estimate: cone seat, axial
    cone_axial_damping_ns_per_m: float = 1000.0
    cone_stick_stiffness_nm_per_rad: float = 2000.0  # estimate: ring and cone torsion while stuck
    cone_stick_damping_nms_per_rad: float = 0.45     # damping ratio about 0.5 on the ring
    stop_stiffness_n_per_m: float = 2.0e7      # slot stops, ring seat, sleeve end stop
    stop_damping_ns_per_m: float = 600.0
    strut_damping_ns_per_m: float = 130.0      # damping ratio about 0.5 of the ring on the strut spring
    step_s: float = 4.0e-6

    @classmethod
    def from_plant(cls, params: dict | None = None, sleeve: int = SLEEVE, **overrides):
        """The plant's synchronizer values (the default car unless ``params`` is given)."""
        if params is None:
            from plant.params import load_params
            params = load_params()
        s = params["gearbox"]["sync"][sleeve]
        keys = ("cone_mu", "cone_radius_m", "cone_half_angle_deg", "sleeve_mass_kg",
                "sleeve_damping_ns_per_m", "cone_travel_mm", "engaged_travel_mm",
                "detent_force_n", "lock_speed_rad_s", "dog_friction_mu")
        values = {k: float(s[k]) for k in keys}
        values["tooth_radius_m"] = float(s["dog_radius_m"])
        values["chamfer_angle_deg"] = float(s["ring_chamfer_angle_deg"])
        values.update(overrides)
        return cls(**values)

    # derived geometry -------------------------------------------------------
    @property
    def pitch_m(self) -> float:
        return 2.0 * math.pi * self.tooth_radius_m / self.teeth

    @property
    def blocking_offset_m(self) -> float:
        """Circumferential distance of the facing apexes with the ring at its slot end."""
        return self.pitch_m * (0.5 - self.slot_play_pitch)

    @property
    def ring_apex_offset_m(self) -> float:
        """Ring apex ahead of the ring's axial position, set so the sleeve blocks at cone_travel_mm."""
        cot = 1.0 / math.tan(math.radians(self.chamfer_angle_deg))
        return (self.cone_travel_mm - self.ring_axial_play_mm) * 1e-3 - self.blocking_offset_m * cot

    @property
    def through_travel_m(self) -> float:
        """Sleeve travel at which its chamfers have passed the ring's (ring on its cone,
        turned back to where the chamfers clear: apexes a tooth width apart)."""
        cot = 1.0 / math.tan(math.radians(self.chamfer_angle_deg))
        return (self.ring_axial_play_mm * 1e-3 + self.ring_apex_offset_m
                + self.tooth_width_pitch * self.pitch_m * cot)

    @property
    def ring_pass_travel_mm(self) -> float:
        """Sleeve travel from blocking to through the ring: (tooth width - blocking
        offset) / tan(beta); the plant's ring_pass_travel_mm."""
        return (self.through_travel_m - self.cone_travel_mm * 1e-3) * 1e3


@dataclass(frozen=True)
class Case:
    """One synchronization: 2nd gear (idle input shaft 2) onto output shaft 1."""
    fork_force_n: float = 600.0
    slip_rpm: float = 1000.0             # initial gear speed - shaft speed, at the synchronizer
    shaft_speed_rpm: float = 1000.0      # output shaft 1 (about 29 km/h)
    ramp_s: float = 0.005                # estimate: fork force rise of the shift cylinder
    gear_inertia_kgm2: float = 0.0       # 0: from the plant (gear + input shaft 2 reflected)
    shaft_inertia_kgm2: float = SHAFT_INERTIA_KGM2
    gear_drag_nm: float = -1.0           # <0: from the plant (input shaft 2 drag reflected)
    gear_drag_nms_per_rad: float = -1.0
    drag_smoothing_rad_s: float = -1.0   # <0: from the plant (reflected to the gear)
    dog_phase_pitch: float = 0.0         # initial dog-tooth misalignment, fraction of a pitch

    def resolved(self, params: dict | None = None) -> Case:
        """The case with the plant's inertia and drag filled in where left at their defaults."""
        if min(self.gear_inertia_kgm2, self.gear_drag_nm + 1.0, self.gear_drag_nms_per_rad + 1.0,
               self.drag_smoothing_rad_s) > 0.0 and self.gear_drag_nm >= 0.0 \
                and self.gear_drag_nms_per_rad >= 0.0:
            return self
        if params is None:
            from plant.params import load_params
            params = load_params()
        gb = params["gearbox"]
        r = gb["ratio"][GEAR]
        changes = {}
        if self.gear_inertia_kgm2 <= 0.0:
            changes["gear_inertia_kgm2"] = gear_side_inertia_kgm2(GEAR, params)
        if self.gear_drag_nm < 0.0:
            changes["gear_drag_nm"] = gb["input_drag_nm"][1] * r
        if self.gear_drag_nms_per_rad < 0.0:
            changes["gear_drag_nms_per_rad"] = gb["input_drag_nms_per_rad"][1] * r * r
        if self.drag_smoothing_rad_s <= 0.0:
            changes["drag_smoothing_rad_s"] = gb["drag_smoothing_rad_s"] / r
        return replace(self, **changes)


def gear_side_inertia_kgm2(gear: int, params: dict | None = None) -> float:
    """What a synchronizer turns at gear index ``gear`` (2nd, 4th, 6th: input shaft 2):
    the input shaft with its fixed gears and the loose gears meshing with them,
    reflected through the gear's ratio, as the plant's gearbox.c computes it."""
    if params is None:
        from plant.params import load_params
        params = load_params()
    if gear not in INPUT2_GEARS:
        raise ValueError(f"gear index must be one of {INPUT2_GEARS} (input shaft 2), got {gear!r}")
    gb = params["gearbox"]
    j_in = gb["input_shaft_inertia_kgm2"][1] + sum(
        gb["idle_gear_inertia_kgm2"][g] / gb["ratio"][g] ** 2 for g in INPUT2_GEARS)
    return j_in * gb["ratio"][gear] ** 2


def _check_case(case: Case) -> None:
    if not (math.isfinite(case.fork_force_n) and case.fork_force_n > 0.0):
        raise ValueError(f"fork_force_n must be a positive number, got {case.fork_force_n!r}")
    if not math.isfinite(case.slip_rpm):
        raise ValueError(f"slip_rpm must be finite, got {case.slip_rpm!r}")
    if not (case.ramp_s > 0.0 and case.shaft_inertia_kgm2 > 0.0):
        raise ValueError(f"ramp_s and shaft_inertia_kgm2 must be positive, got "
                         f"{case.ramp_s!r}, {case.shaft_inertia_kgm2!r}")


def _fork_force(case: Case, t: float) -> float:
    return case.fork_force_n * (t / case.ramp_s if t < case.ramp_s else 1.0)


def _gear_drag(case: Case, w: float) -> float:
    a = w / case.drag_smoothing_rad_s
    s = 1.0 if a > 20.0 else (-1.0 if a < -20.0 else math.tanh(a))
    return case.gear_drag_nm * s + case.gear_drag_nms_per_rad * w


@dataclass
class Run:
    """One simulated synchronization: event times (s, nan when not reached) and the series."""
    model: str
    t_block_s: float = math.nan       # sleeve first on the blocker ring (on the cone)
    t_sync_s: float = math.nan        # slip first below the lock speed
    t_through_s: float = math.nan     # sleeve through the blocker ring
    t_full_s: float = math.nan        # sleeve at full engagement
    t_end_s: float = 0.0
    steps: int = 0
    series: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def coupling_time_s(self) -> float:
        return max(self.t_sync_s, self.t_through_s)


# ---------------------------------------------------------------------------
# the detailed model
# ---------------------------------------------------------------------------

def _teeth(X, Xd, E, Ed, tw, sn, cs, k, c, mu, veps):
    """Contact of a sleeve apex with the nearer facing tooth.

    X: axial advance of the sleeve apex past the facing apex, E: their
    circumferential distance (the facing tooth on the side of the contact),
    tw: one tooth width (the two half widths that meet). Returns the
    generalized forces (Q_X on the sleeve's axial coordinate, Q_E on E)."""
    dk = tw - E                       # flank overlap (circumferential)
    if dk <= 0.0:
        return 0.0, 0.0
    df = X * sn - E * cs              # chamfer overlap along the face normal
    if df <= 0.0:
        return 0.0, 0.0
    if df < dk:                       # chamfer faces
        n = k * df + c * (Xd * sn - Ed * cs)
        if n <= 0.0:
            return 0.0, 0.0
        s = (Xd * cs + Ed * sn) / veps
        f = mu * n * (1.0 if s > 1.0 else (-1.0 if s < -1.0 else s))
        return -n * sn - f * cs, n * cs - f * sn
    n = k * dk - c * Ed               # flanks
    if n <= 0.0:
        return 0.0, 0.0
    s = Xd / veps
    return -mu * n * (1.0 if s > 1.0 else (-1.0 if s < -1.0 else s)), n


def simulate_detailed(case: Case, p: DetailedParams | None = None, t_end_s: float = 1.0,
                      step_s: float | None = None, stop_after_s: float | None = 0.02,
                      record: bool = True, friction: bool = True, drag: bool = True,
                      initial: dict | None = None) -> Run:
    """Integrate the detailed model.

    stop_after_s: stop this long after full engagement (None: run to t_end_s).
    friction=False removes cone and tooth friction, drag=False the gear drag
    (the conservation check). ``initial`` overrides initial states by name
    (x_s, v_s, x_r, v_r, phi_r, w_r, phi_g, w_g, phi_h, w_h, z)."""
    _check_case(case)
    case = case.resolved()
    p = p or DetailedParams.from_plant()
    h = step_s or p.step_s
    if not (h > 0.0 and t_end_s > 0.0):
        raise ValueError(f"step_s and t_end_s must be positive, got {h!r}, {t_end_s!r}")

    # constants
    ms, mr, jr = p.sleeve_mass_kg, p.ring_mass_kg, p.ring_inertia_kgm2
    jg, jh = case.gear_inertia_kgm2, case.shaft_inertia_kgm2
    cs_ = p.sleeve_damping_ns_per_m
    rb = p.tooth_radius_m
    pitch = p.pitch_m
    half_p = 0.5 * pitch
    tw = p.tooth_width_pitch * pitch    # apexes clear when further apart than a tooth width
    u_slot = p.slot_play_pitch * pitch
    th_c = math.radians(p.chamfer_angle_deg)
    sn_c, cs_c = math.sin(th_c), math.cos(th_c)
    th_d = math.radians(p.dog_chamfer_angle_deg)
    sn_d, cs_d = math.sin(th_d), math.cos(th_d)
    kc, cc = p.contact_stiffness_n_per_m, p.contact_damping_ns_per_m
    cd = p.dog_damping_ns_per_m
    mu_c = p.chamfer_mu if friction else 0.0
    mu_d = p.dog_friction_mu if friction else 0.0
    mu_cone = p.cone_mu if friction else 0.0
    veps = p.friction_speed_m_s
    ks, css = p.stop_stiffness_n_per_m, p.stop_damping_ns_per_m
    kca, cca = p.cone_axial_stiffness_n_per_m, p.cone_axial_damping_ns_per_m
    kt, ct = p.cone_stick_stiffness_nm_per_rad, p.cone_stick_damping_nms_per_rad
    cone_gain = p.cone_radius_m / math.sin(math.radians(p.cone_half_angle_deg))
    play = p.ring_axial_play_mm * 1e-3
    a_r0 = p.ring_apex_offset_m
    a_d = p.dog_tip_mm * 1e-3
    x_full = p.engaged_travel_mm * 1e-3
    x_through = p.through_travel_m
    k_st = p.detent_force_n / (DETENT_TRAVEL_MM * 1e-3)
    c_st = p.strut_damping_ns_per_m
    f_det = p.detent_force_n
    fade_m = 0.5e-3                    # struts pressed down once the sleeve is past the ring
    lock = p.lock_speed_rad_s
    ramp, f_fork = case.ramp_s, case.fork_force_n
    c0, c1 = (case.gear_drag_nm, case.gear_drag_nms_per_rad) if drag else (0.0, 0.0)
    dsm = case.drag_smoothing_rad_s

    wh0 = case.shaft_speed_rpm * RAD_S_PER_RPM
    st = dict(x_s=0.0, v_s=0.0, x_r=0.0, v_r=0.0, phi_r=0.0, w_r=wh0,
              phi_g=case.dog_phase_pitch * pitch / rb, w_g=wh0 + case.slip_rpm * RAD_S_PER_RPM,
              phi_h=0.0, w_h=wh0, z=0.0)
    if initial:
        unknown = set(initial) - set(st)
        if unknown:
            raise ValueError(f"unknown initial state(s): {', '.join(sorted(unknown))}")
        st.update(initial)
    xs, vs, xr, vr = st["x_s"], st["v_s"], st["x_r"], st["v_r"]
    phr, wr, phg, wg, phh, wh, z = (st["phi_r"], st["w_r"], st["phi_g"], st["w_g"],
                                    st["phi_h"], st["w_h"], st["z"])

    n = int(round(t_end_s / h))
    every = max(1, int(round(RECORD_S / h)))
    rec = [] if record else None
    t_block = t_sync = t_through = t_full = math.nan
    t_stop = math.inf
    i = 0
    tc = 0.0
    f_ax = 0.0
    for i in range(n):
        t = i * h
        ff = f_fork * (t / ramp if t < ramp else 1.0)
        fs = ff - cs_ * vs             # sleeve axial
        fr = 0.0                       # ring axial
        tr = tg = th = 0.0             # torques on ring, gear, hub

        # struts: a saturating spring from the sleeve onto the ring (ball detent)
        d = xs - xr
        if d > 0.0 and xs < x_through + fade_m:
            f = k_st * d + c_st * (vs - vr)
            f = 0.0 if f < 0.0 else (f_det if f > f_det else f)
            if xs > x_through:
                f *= (x_through + fade_m - xs) / fade_m
            fs -= f
            fr += f

        # ring seat on the hub (x_r >= 0) and on the cone (x_r >= play)
        if xr < 0.0:
            f = -ks * xr - css * vr
            if f > 0.0:
                fr += f
        f_ax = 0.0
        d = xr - play
        if d > 0.0:
            f_ax = kca * d + cca * vr
            if f_ax < 0.0:
                f_ax = 0.0
            fr -= f_ax

        # cone friction: reset integrator, capacity mu r_c N, N = F_axial / sin(alpha)
        cap = mu_cone * cone_gain * f_ax
        lim = cap / kt
        wc = wg - wr
        if (z >= lim and wc > 0.0) or (z <= -lim and wc < 0.0):
            tc = cap if wc > 0.0 else -cap
            zd = 0.0
        else:
            tc = kt * z + ct * wc
            tc = cap if tc > cap else (-cap if tc < -cap else tc)
            zd = wc
        tr += tc
        tg -= tc

        # ring in its hub slot
        u = rb * (phr - phh)
        ud = rb * (wr - wh)
        if u > u_slot:
            f = ks * (u - u_slot) + css * ud
            if f > 0.0:
                tr -= rb * f
                th += rb * f
        elif u < -u_slot:
            f = ks * (-u_slot - u) - css * ud
            if f > 0.0:
                tr += rb * f
                th -= rb * f

        # sleeve chamfers and flanks on the ring teeth
        if u != 0.0:
            sg = -1.0 if u > 0.0 else 1.0
            qx, qe = _teeth(xs - xr - a_r0, vs - vr, half_p + sg * u, sg * ud, tw,
                            sn_c, cs_c, kc, cc, mu_c, veps)
            if qx != 0.0 or qe != 0.0:
                fs += qx
                fr -= qx
                tr += sg * rb * qe
                th -= sg * rb * qe
                if t_block != t_block:
                    t_block = t

        # sleeve on the gear's dog teeth
        if xs > a_d - 2e-3:
            v = rb * (phg - phh)
            v -= pitch * math.floor(v / pitch + 0.5)
            sg = -1.0 if v > 0.0 else 1.0
            qx, qe = _teeth(xs - a_d, vs, half_p + sg * v, sg * rb * (wg - wh), tw,
                            sn_d, cs_d, kc, cd, mu_d, veps)
            if qx != 0.0 or qe != 0.0:
                fs += qx
                tg += sg * rb * qe
                th -= sg * rb * qe

        # sleeve end stop
        if xs > x_full:
            f = ks * (xs - x_full) + css * vs
            if f > 0.0:
                fs -= f

        # gear drag (input shaft 2 reflected)
        if c0 != 0.0 or c1 != 0.0:
            a = wg / dsm
            tg -= c0 * (1.0 if a > 20.0 else (-1.0 if a < -20.0 else math.tanh(a))) + c1 * wg

        if rec is not None and i % every == 0:
            v = rb * (phg - phh)
            rec.append((t, xs, wg - wh, tc, ff, f_ax, u, wr - wh,
                        v - pitch * math.floor(v / pitch + 0.5)))

        # semi-implicit Euler
        vs += h * fs / ms
        xs += h * vs
        vr += h * fr / mr
        xr += h * vr
        wr += h * tr / jr
        phr += h * wr
        wg += h * tg / jg
        phg += h * wg
        wh += h * th / jh
        phh += h * wh
        z += h * zd
        lim = cap / kt
        z = lim if z > lim else (-lim if z < -lim else z)

        tn = t + h
        if t_sync != t_sync and abs(wg - wh) <= lock:
            t_sync = tn
        if t_through != t_through and xs >= x_through:
            t_through = tn
        if t_full != t_full and xs >= x_full - 0.05e-3:
            t_full = tn
            if stop_after_s is not None:
                t_stop = tn + stop_after_s
        if tn >= t_stop:
            break

    run = Run("detailed", t_block, t_sync, t_through, t_full, (i + 1) * h, i + 1)
    run.extra = dict(x_s=xs, v_s=vs, x_r=xr, v_r=vr, phi_r=phr, w_r=wr, phi_g=phg, w_g=wg,
                     phi_h=phh, w_h=wh, z=z, x_through_m=x_through, pitch_m=pitch,
                     gear_inertia_kgm2=jg, shaft_inertia_kgm2=jh, ring_inertia_kgm2=jr)
    if rec is not None:
        a = np.array(rec) if rec else np.zeros((0, 9))
        run.series = {"time_s": a[:, 0], "sleeve_mm": a[:, 1] * 1e3,
                      "slip_rpm": a[:, 2] / RAD_S_PER_RPM, "cone_torque_nm": a[:, 3],
                      "fork_force_n": a[:, 4], "ring_axial_force_n": a[:, 5],
                      "ring_offset_mm": a[:, 6] * 1e3, "ring_slip_rpm": a[:, 7] / RAD_S_PER_RPM,
                      "dog_offset_mm": a[:, 8] * 1e3}
    return run


# ---------------------------------------------------------------------------
# the hybrid model: the plant's C component, and a Python replica of it
# ---------------------------------------------------------------------------

_C = {}


def _c_plant():
    """ffi, lib and a filled dct_params of the default car (built once)."""
    if not _C:
        from plant._dct_plant import ffi, lib
        from plant.params import fill_params, load_params
        params = ffi.new("dct_params *")
        fill_params(ffi, params, load_params())
        _C.update(ffi=ffi, lib=lib, params=params)
    return _C["ffi"], _C["lib"], _C["params"]


def plant_substep_s() -> float:
    _, _, params = _c_plant()
    return params.solver.step_s / params.solver.substeps


def _hybrid_events(run: Run, t, slip, x, lock, x_through, x_full):
    if run.t_sync_s != run.t_sync_s and abs(slip) <= lock:
        run.t_sync_s = t
    if run.t_through_s != run.t_through_s and x >= x_through:
        run.t_through_s = t
    if run.t_full_s != run.t_full_s and x >= x_full - 0.05e-3:
        run.t_full_s = t


def simulate_hybrid_c(case: Case, t_end_s: float = 1.0, step_s: float | None = None,
                      stop_after_s: float | None = 0.02, record: bool = True,
                      x_through_m: float | None = None) -> Run:
    """The plant's synchronizer (dct_sync_output_eval / dct_sync_advance) between the
    two inertias of ``case``, explicit Euler at the plant's sub-step as in plant.c."""
    _check_case(case)
    case = case.resolved()
    ffi, lib, params = _c_plant()
    p = ffi.addressof(params[0].gearbox.sync, SLEEVE)
    h = step_s or plant_substep_s()
    s = ffi.new("dct_sync_state *")
    lib.dct_sync_init(p, s, 0)
    # the gear side's inertia, as gearbox.c passes it in: + side the case's gear
    # (2nd), - side 4th
    inp = ffi.new("dct_sync_input *", {"has_neg": 1.0,
                                       "gear_inertia_pos_kgm2": case.gear_inertia_kgm2,
                                       "gear_inertia_neg_kgm2": gear_side_inertia_kgm2(3)})
    out = ffi.new("dct_sync_output *")
    jg, jh = case.gear_inertia_kgm2, case.shaft_inertia_kgm2
    wh = case.shaft_speed_rpm * RAD_S_PER_RPM
    wg = wh + case.slip_rpm * RAD_S_PER_RPM
    lock = p.lock_speed_rad_s
    x_through = DetailedParams.from_plant().through_travel_m if x_through_m is None else x_through_m
    x_full = p.engaged_travel_mm * 1e-3
    run = Run("hybrid (C)")
    n = int(round(t_end_s / h))
    every = max(1, int(round(RECORD_S / h)))
    rec = [] if record else None
    t_stop = math.inf
    i = 0
    for i in range(n):
        t = i * h
        ff = _fork_force(case, t)
        inp.fork_force_n = ff
        inp.slip_pos_rad_s = wg - wh
        lib.dct_sync_output_eval(p, s, inp, out)
        torque = out.torque_nm
        if rec is not None and i % every == 0:
            rec.append((t, s.position_m, wg - wh,
                        torque if s.phase == lib.DCT_SYNC_SYNCHRONIZING else 0.0, ff, s.phase))
        dwg = (-torque - _gear_drag(case, wg)) / jg
        dwh = torque / jh
        lib.dct_sync_advance(p, s, inp, out, h)
        if run.t_block_s != run.t_block_s and s.phase >= lib.DCT_SYNC_SYNCHRONIZING:
            run.t_block_s = t + h
        wg += h * dwg
        wh += h * dwh
        _hybrid_events(run, t + h, wg - wh, s.position_m, lock, x_through, x_full)
        if run.t_full_s == run.t_full_s and stop_after_s is not None and t_stop == math.inf:
            t_stop = run.t_full_s + stop_after_s
        if t + h >= t_stop:
            break
    run.t_end_s, run.steps = (i + 1) * h, i + 1
    run.extra = dict(w_g=wg, w_h=wh, phase=s.phase, clashes=s.clashes, x_s=s.position_m)
    if rec is not None:
        a = np.array(rec)
        run.series = {"time_s": a[:, 0], "sleeve_mm": a[:, 1] * 1e3,
                      "slip_rpm": a[:, 2] / RAD_S_PER_RPM, "cone_torque_nm": a[:, 3],
                      "fork_force_n": a[:, 4], "phase": a[:, 5]}
    return run


def simulate_hybrid_py(case: Case, t_end_s: float = 1.0, step_s: float | None = None,
                       stop_after_s: float | None = 0.02, x_through_m: float | None = None,
                       turn_back: bool = True) -> Run:
    """A Python replica of synchronizer.c (+ side of a two-sided sleeve) in the same loop.

    turn_back=False leaves out the ring turn-back term (the plant's model
    before it, see ``propose``): in the engaged phase, until the sleeve has
    passed the ring, the sleeve also turns the gear back through the ring's
    chamfers (the gear's inertia reflected onto the sleeve travel)."""
    _check_case(case)
    case = case.resolved()
    _, _, params = _c_plant()
    p = params[0].gearbox.sync[SLEEVE]
    h = step_s or plant_substep_s()
    mu, r, alpha = p.cone_mu, p.cone_radius_m, math.radians(p.cone_half_angle_deg)
    w0, k, b = p.tanh_speed_rad_s, p.stiffness_nm_per_rad, p.damping_nms_per_rad
    m, c = p.sleeve_mass_kg, p.sleeve_damping_ns_per_m
    cone, full = p.cone_travel_mm * 1e-3, p.engaged_travel_mm * 1e-3
    det, lock, fmax, clash = p.detent_force_n, p.lock_speed_rad_s, p.blocker_force_max_n, \
        p.clash_speed_rad_s
    mud, rd = p.dog_friction_mu, p.dog_radius_m
    dp = DetailedParams.from_plant()
    x_through = dp.through_travel_m if x_through_m is None else x_through_m
    # turn-back: the sleeve's axial travel over the ring chamfers turns the gear by
    # tan(beta) / r_b per metre; its inertia adds J tan^2(beta) / r_b^2 to the sleeve
    tb = math.tan(math.radians(p.ring_chamfer_angle_deg)) / rd
    m_tb = m + case.gear_inertia_kgm2 * tb * tb
    x_tb_end = cone + p.ring_pass_travel_mm * 1e-3
    jg, jh = case.gear_inertia_kgm2, case.shaft_inertia_kgm2
    wh = case.shaft_speed_rpm * RAD_S_PER_RPM
    wg = wh + case.slip_rpm * RAD_S_PER_RPM
    phase, x, v, twist = 0, 0.0, 0.0, 0.0
    run = Run("hybrid (Python)" + ("" if turn_back else ", no turn-back"))
    n = int(round(t_end_s / h))
    t_stop = math.inf
    clashes = 0
    i = 0
    for i in range(n):
        t = i * h
        f = _fork_force(case, t)
        slip = wg - wh
        # output
        if phase == 1:
            ts = mu * r / math.sin(alpha) * (f if f > 0.0 else 0.0)
            torque = ts * math.tanh(2.0 * slip / w0)
        elif phase == 2:
            torque = k * twist + b * slip
        else:
            torque = 0.0
        dwg = (-torque - _gear_drag(case, wg)) / jg
        dwh = torque / jh
        # advance
        if phase == 1:
            if f <= 0.0:
                phase, twist = 0, 0.0
            elif abs(slip) <= lock or abs(f) > fmax:
                if abs(slip) > clash:
                    clashes += 1
                phase, twist = 2, torque / k
            else:
                twist = torque / k
        elif phase == 2:
            twist += h * slip
            fdog = mud * abs(torque) / rd
            pushing = v > 0.0 or (v == 0.0 and f > 0.0)
            mass = m_tb if (turn_back and x < x_tb_end and pushing) else m
            v1 = v + h * (f - c * v) / mass
            dv = h * fdog / mass
            v1 = 0.0 if abs(v1) <= dv else v1 - math.copysign(dv, v1)
            x1 = x + h * v
            if x1 >= full:
                x1 = full
                v1 = min(v1, 0.0)
            x, v = x1, v1
            if x1 < cone:
                phase, twist = 0, 0.0
        else:
            dt = -max(-1.0, min(1.0, x / (DETENT_TRAVEL_MM * 1e-3))) * det
            v1 = v + h * (f + dt - c * v) / m
            x1 = x + h * v
            x, v = x1, v1
            if abs(x1) >= cone:
                x = math.copysign(cone, x1)
                if v1 * x > 0.0:
                    v = 0.0
                if f * x > 0.0:
                    phase, twist = 1, 0.0
        if run.t_block_s != run.t_block_s and phase >= 1:
            run.t_block_s = t + h
        wg += h * dwg
        wh += h * dwh
        _hybrid_events(run, t + h, wg - wh, x, lock, x_through, full)
        if run.t_full_s == run.t_full_s and stop_after_s is not None and t_stop == math.inf:
            t_stop = run.t_full_s + stop_after_s
        if t + h >= t_stop:
            break
    run.t_end_s, run.steps = (i + 1) * h, i + 1
    run.extra = dict(w_g=wg, w_h=wh, phase=phase, clashes=clashes, x_s=x)
    return run


# ---------------------------------------------------------------------------
# comparison
# ---------------------------------------------------------------------------

FORCES_N = (300.0, 600.0, 900.0)


def cases(quick: bool = False) -> list[tuple[float, float]]:
    """(fork force N, slip rpm) of the comparison: three forces at two slips and more."""
    if quick:
        return [(600.0, 1000.0)]
    return [(f, s) for s in (1000.0, 2000.0) for f in FORCES_N] + [(600.0, 500.0)]


def _t_end(case: Case) -> float:
    """Simulated time that covers the synchronization of ``case`` with margin."""
    c = case.resolved()
    p = DetailedParams.from_plant()
    ts = p.cone_mu * p.cone_radius_m / math.sin(math.radians(p.cone_half_angle_deg)) \
        * c.fork_force_n
    return 1.6 * c.gear_inertia_kgm2 * abs(c.slip_rpm) * RAD_S_PER_RPM / ts + 0.15


def _pct(a: float, ref: float) -> float:
    return 100.0 * (a - ref) / ref if ref == ref and a == a and ref != 0.0 else math.nan


def compare(fork_force_n: float = 600.0, slip_rpm: float = 1000.0, quick: bool = False,
            **case_fields) -> dict:
    """Run one case through the detailed and the hybrid model.

    Returns the coupling times (s) of both, the error of the hybrid against the
    detailed model (%), the phase times behind them and the time series
    (time_s, sleeve_mm, slip_rpm, cone_torque_nm, fork_force_n per model).
    quick=True integrates the detailed model at twice the step (8 us)."""
    case = Case(fork_force_n=float(fork_force_n), slip_rpm=float(slip_rpm), **case_fields)
    _check_case(case)
    p = DetailedParams.from_plant()
    if quick:
        p = replace(p, step_s=2.0 * p.step_s)
    t_end = _t_end(case)
    d = simulate_detailed(case, p, t_end_s=t_end)
    hc = simulate_hybrid_c(case, t_end_s=t_end, x_through_m=p.through_travel_m)
    td, th = d.coupling_time_s, hc.coupling_time_s
    return {
        "fork_force_n": case.fork_force_n,
        "slip_rpm": case.slip_rpm,
        "coupling_time_detailed_s": td,
        "coupling_time_hybrid_s": th,
        "coupling_time_error_pct": _pct(th, td),
        "block_time_detailed_s": d.t_block_s,
        "block_time_hybrid_s": hc.t_block_s,
        "sync_time_detailed_s": d.t_sync_s,
        "sync_time_hybrid_s": hc.t_sync_s,
        "through_time_detailed_s": d.t_through_s,
        "through_time_hybrid_s": hc.t_through_s,
        "full_engagement_detailed_s": d.t_full_s,
        "full_engagement_hybrid_s": hc.t_full_s,
        "ring_pass_detailed_s": d.t_through_s - d.t_sync_s,
        "ring_pass_hybrid_s": hc.t_through_s - hc.t_sync_s,
        "detailed_step_s": p.step_s,
        "hybrid_step_s": plant_substep_s(),
        "hybrid_clashes": hc.extra["clashes"],
        "series": {"detailed": d.series, "hybrid": hc.series},
    }


def compare_all(quick: bool = False) -> list[dict]:
    return [compare(f, s, quick=quick) for f, s in cases(quick)]


def _timed(fn, repeat: int = 1) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def compute_times(sim_s: float = 0.8) -> dict:
    """Wall-clock compute time (s) for sim_s simulated seconds of the 600 N, 1000 rpm case.

    detailed_python_s: the detailed model (Python, 4 us step);
    hybrid_python_s: the Python replica of the hybrid model (same language, the
    plant's 0.25 ms sub-step): the like-for-like ratio;
    hybrid_c_from_python_s: the C component driven step by step from Python (cffi);
    plant_c_s: the whole C plant (all 67 states, four synchronizers) for sim_s.
    Every value but sim_s is a compute time in seconds."""
    if not (math.isfinite(sim_s) and sim_s > 0.0):
        raise ValueError(f"sim_s must be a positive number, got {sim_s!r}")
    case = Case(600.0, 1000.0).resolved()
    out = {"sim_s": float(sim_s)}
    out["detailed_python_s"] = _timed(
        lambda: simulate_detailed(case, t_end_s=sim_s, stop_after_s=None, record=False))
    out["hybrid_python_s"] = _timed(
        lambda: simulate_hybrid_py(case, t_end_s=sim_s, stop_after_s=None), repeat=3)
    out["hybrid_c_from_python_s"] = _timed(
        lambda: simulate_hybrid_c(case, t_end_s=sim_s, stop_after_s=None, record=False), repeat=3)
    try:
        from plant.model import Plant
        plant = Plant()
        steps = int(round(sim_s / plant.params["solver"]["step_s"]))
        plant.step(10)
        out["plant_c_s"] = _timed(lambda: plant.step(steps), repeat=3)
    except Exception:  # the plant is optional here: report what was measured
        pass
    return out


def propose(quick: bool = False) -> list[dict]:
    """Coupling times of the hybrid model without and with the ring turn-back term
    (Python replica; with it is the plant's model) against the detailed model."""
    rows = []
    p = DetailedParams.from_plant()
    for f, s in cases(quick):
        case = Case(f, s)
        t_end = _t_end(case)
        d = simulate_detailed(case, p if not quick else replace(p, step_s=2 * p.step_s),
                              t_end_s=t_end, record=False)
        hp = simulate_hybrid_py(case, t_end_s=t_end, turn_back=False)
        ht = simulate_hybrid_py(case, t_end_s=t_end)
        rows.append({"fork_force_n": f, "slip_rpm": s,
                     "coupling_time_detailed_s": d.coupling_time_s,
                     "coupling_time_hybrid_s": hp.coupling_time_s,
                     "coupling_time_turn_back_s": ht.coupling_time_s,
                     "error_pct": _pct(hp.coupling_time_s, d.coupling_time_s),
                     "error_turn_back_pct": _pct(ht.coupling_time_s, d.coupling_time_s)})
    return rows


SENSITIVITY = (
    ("chamfer_angle_deg", (55.0, 65.0)),
    ("slot_play_pitch", (0.20, 0.30)),
    ("tooth_width_pitch", (0.40, 0.48)),
    ("chamfer_mu", (0.05, 0.15)),
    ("ring_inertia_kgm2", (0.5e-4, 2.0e-4)),
    ("contact_stiffness_n_per_m", (1.0e7, 1.0e8)),
)


def sensitivity(fork_force_n: float = 600.0, slip_rpm: float = 1000.0) -> list[dict]:
    """Coupling-time error of the hybrid model when each estimated value of the
    detailed model's geometry is moved to either end of its plausible range."""
    case = Case(float(fork_force_n), float(slip_rpm))
    _check_case(case)
    t_end = _t_end(case)
    base = DetailedParams.from_plant()
    hyb = simulate_hybrid_c(case, t_end_s=t_end, record=False)
    rows = []
    for name, values in (("(as estimated)", (None,)),) + SENSITIVITY:
        for value in values:
            p = base if value is None else replace(base, **{name: value})
            if name == "contact_stiffness_n_per_m":   # stiffer contacts: a smaller step
                p = replace(p, step_s=p.step_s * min(1.0, math.sqrt(2.0e7 / value)))
            d = simulate_detailed(case, p, t_end_s=t_end, record=False)
            h = simulate_hybrid_c(case, t_end_s=t_end, record=False,
                                  x_through_m=p.through_travel_m) \
                if p.through_travel_m != base.through_travel_m else hyb
            rows.append({"parameter": name, "value": value,
                         "coupling_time_detailed_s": d.coupling_time_s,
                         "ring_pass_detailed_s": d.t_through_s - d.t_sync_s,
                         "coupling_time_error_pct": _pct(h.coupling_time_s, d.coupling_time_s)})
    return rows


def blocking_margin(p: DetailedParams | None = None) -> float:
    """Cone torque over the chamfers' indexing torque at the same axial force
    (> 1: the ring blocks the sleeve while the cone slips)."""
    p = p or DetailedParams.from_plant()
    a, b = math.radians(p.cone_half_angle_deg), math.radians(p.chamfer_angle_deg)
    cone = p.cone_mu * p.cone_radius_m / math.sin(a)
    index = p.tooth_radius_m * (math.cos(b) - p.chamfer_mu * math.sin(b)) / (
        math.sin(b) + p.chamfer_mu * math.cos(b))
    return cone / index


def main() -> None:
    t0 = time.perf_counter()
    print(f"blocking margin (cone torque / indexing torque): {blocking_margin():.2f}")
    print("force_N slip_rpm | coupling det_ms hyb_ms err_% | on ring det/hyb ms"
          " | slip phase det/hyb ms | ring pass det/hyb ms")
    for r in compare_all():
        ms = {k: 1e3 * v for k, v in r.items() if isinstance(v, float)}
        print(f"{r['fork_force_n']:7.0f} {r['slip_rpm']:8.0f} | {ms['coupling_time_detailed_s']:7.1f}"
              f" {ms['coupling_time_hybrid_s']:7.1f} {r['coupling_time_error_pct']:+6.2f} |"
              f" {ms['block_time_detailed_s']:5.1f}/{ms['block_time_hybrid_s']:5.1f} |"
              f" {ms['sync_time_detailed_s'] - ms['block_time_detailed_s']:6.1f}/"
              f"{ms['sync_time_hybrid_s'] - ms['block_time_hybrid_s']:6.1f} |"
              f" {ms['ring_pass_detailed_s']:5.1f}/{ms['ring_pass_hybrid_s']:4.1f}")
    print("ring turn-back term (Python replica), error without -> with (the plant's model):")
    for r in propose():
        print(f"  {r['fork_force_n']:5.0f} N {r['slip_rpm']:6.0f} rpm: error {r['error_pct']:+6.2f} %"
              f" -> {r['error_turn_back_pct']:+6.2f} %")
    print("sensitivity at 600 N, 1000 rpm:")
    for r in sensitivity():
        print(f"  {r['parameter']:26s} {r['value']!s:8s} ring pass {1e3 * r['ring_pass_detailed_s']:5.1f} ms"
              f"  error {r['coupling_time_error_pct']:+6.2f} %")
    print("compute times for 0.8 s simulated:", {k: round(v, 5) for k, v in compute_times().items()})
    print(f"wall {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
