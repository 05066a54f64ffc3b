/*
 * test_components.c - the C core's component laws, checked without Python
 * (built by `make -C plant/csrc test` with -Wall -Wextra -Werror and the
 * address and undefined-behaviour sanitizers).
 */
#include <math.h>
#include <stddef.h>
#include <stdio.h>
#include <string.h>

#include "dct_plant.h"

#include "check.h"

static void test_friction_stick_slip(void)
{
    dct_friction_params p = {20000.0, 40.0};
    dct_friction_output o;
    /* sticking: spring-damper on the twist */
    dct_friction_eval(&p, 0.001, 0.0, 100.0, &o);
    CHECK(fabs(o.torque_nm - 20.0) < 1e-9 && o.sliding == 0.0, "stick torque %g", o.torque_nm);
    /* at the limit with slip in the same direction: slides at capacity */
    dct_friction_eval(&p, 100.0 / 20000.0, 1.0, 100.0, &o);
    CHECK(o.sliding == 1.0 && fabs(o.torque_nm - 100.0) < 1e-9, "slide torque %g", o.torque_nm);
    /* slip reverses: sticks again, torque continuous (within c * slip) */
    dct_friction_eval(&p, 100.0 / 20000.0, -0.01, 100.0, &o);
    CHECK(o.sliding == 0.0 && fabs(o.torque_nm - 100.0) <= 40.0 * 0.01 + 1e-9, "re-stick %g", o.torque_nm);
    /* capacity drop resets the twist */
    double z = dct_friction_advance(&p, 0.004, &o, 10.0, 1e-4);
    CHECK(fabs(z) <= 10.0 / 20000.0 + 1e-15, "reset twist %g", z);
    /* zero capacity transmits nothing */
    dct_friction_eval(&p, 0.0, 5.0, 0.0, &o);
    CHECK(o.torque_nm == 0.0, "open %g", o.torque_nm);
}

static void test_curve(void)
{
    dct_torque_curve c;
    memset(&c, 0, sizeof c);
    c.n = 3;
    c.speed_rpm[0] = 1000; c.speed_rpm[1] = 2000; c.speed_rpm[2] = 4000;
    c.torque_nm[0] = 100; c.torque_nm[1] = 200; c.torque_nm[2] = 0;
    CHECK(fabs(dct_curve_eval(&c, 1500) - 150) < 1e-12, "interp");
    CHECK(fabs(dct_curve_eval(&c, 3000) - 100) < 1e-12, "interp 2");
    CHECK(dct_curve_eval(&c, 500) == 100 && dct_curve_eval(&c, 5000) == 0, "held flat outside");
}

static dct_sync_params sync_params(void)
{
    dct_sync_params p;
    memset(&p, 0, sizeof p);
    p.cone_mu = 0.1; p.cone_radius_m = 0.04; p.cone_half_angle_deg = 6.5;
    p.tanh_speed_rad_s = 1.0; p.stiffness_nm_per_rad = 15000; p.damping_nms_per_rad = 25;
    p.sleeve_mass_kg = 1.5; p.sleeve_damping_ns_per_m = 200; p.cone_travel_mm = 3;
    p.engaged_travel_mm = 8.5; p.detent_force_n = 60; p.lock_speed_rad_s = 0.5;
    p.blocker_force_max_n = 1300; p.clash_speed_rad_s = 10.5; p.dog_friction_mu = 0.15;
    p.dog_radius_m = 0.045; p.ring_chamfer_angle_deg = 60.0; p.ring_pass_travel_mm = 0.8616;
    return p;
}

/* a sleeve pushed onto a gear spinning freely with inertia j: the phases
 * come in order and the gear is synchronised by the cone torque of eq. 6 */
static void test_sync_phases(void)
{
    dct_sync_params p = sync_params();
    dct_sync_state s;
    dct_sync_init(&p, &s, 0);
    double j = 0.05;
    dct_sync_input in = {400.0, 50.0, 0.0, 1.0, j, j, 0.0};
    dct_sync_output o;
    double h = 1.25e-4, t = 0.0, t_sync = -1.0, t_eng = -1.0;
    int last_phase = 0, order_ok = 1;
    for (int i = 0; i < 40000; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        in.slip_pos_rad_s -= h * o.torque_nm / j; /* the gear is slowed by the cone */
        dct_sync_advance(&p, &s, &in, &o, h);
        t += h;
        if ((int)s.phase < last_phase)
            order_ok = 0;
        if (s.phase == DCT_SYNC_SYNCHRONIZING && t_sync < 0)
            t_sync = t;
        if (s.phase == DCT_SYNC_ENGAGED && t_eng < 0)
            t_eng = t;
        last_phase = (int)s.phase;
    }
    CHECK(order_ok && t_sync > 0 && t_eng > t_sync, "phases in order (%g, %g)", t_sync, t_eng);
    double ts = dct_sync_cone_torque(&p, 400.0);
    double expect = j * 50.0 / ts; /* constant torque while |w_r| >> w_0 */
    CHECK(fabs((t_eng - t_sync) - expect) < 0.05 * expect, "sync time %g expected %g", t_eng - t_sync, expect);
    CHECK(fabs(s.position_m - 8.5e-3) < 1e-9, "full travel %g", s.position_m);
    CHECK(s.clashes == 0.0, "no clash");
}

static void test_sync_clash(void)
{
    dct_sync_params p = sync_params();
    dct_sync_state s;
    dct_sync_init(&p, &s, 0);
    dct_sync_input in = {1500.0, 100.0, 0.0, 1.0, 0.05, 0.05, 0.0}; /* above the blocker's strength */
    dct_sync_output o;
    for (int i = 0; i < 2000 && s.phase != DCT_SYNC_ENGAGED; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.phase == DCT_SYNC_ENGAGED && s.clashes == 1.0, "clash counted (%g)", s.clashes);
}

/* a sleeve on the cone whose fork force reverses leaves the cone and
 * crosses neutral towards the other gear */
static void test_sync_released_from_the_cone(void)
{
    dct_sync_params p = sync_params();
    dct_sync_state s;
    dct_sync_init(&p, &s, 0);
    dct_sync_input in = {400.0, 200.0, 0.0, 1.0, 0.05, 0.05, 0.0};
    dct_sync_output o;
    for (int i = 0; i < 4000 && s.phase != DCT_SYNC_SYNCHRONIZING; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.phase == DCT_SYNC_SYNCHRONIZING, "on the cone");
    in.fork_force_n = -400.0;
    for (int i = 0; i < 4000; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.position_m < 0.0 && s.side <= 0.0, "pulled back across neutral: %g mm", s.position_m * 1e3);
}

/* time for an engaged sleeve, from rest at the cone, under a constant fork
 * force to travel dx_mm further: the gear is held at the shaft speed */
static double sleeve_travel_time(const dct_sync_params *p, double force_n, double j, double dx_mm,
                                 double h)
{
    dct_sync_state s;
    dct_sync_init(p, &s, 0);
    s.phase = DCT_SYNC_ENGAGED;
    s.side = 1.0;
    s.position_m = p->cone_travel_mm * 1e-3;
    dct_sync_input in = {force_n, 0.0, 0.0, 1.0, j, 0.0, 0.0};
    dct_sync_output o;
    double end = (p->cone_travel_mm + dx_mm) * 1e-3;
    for (int i = 1; i < 100000; i++) {
        dct_sync_output_eval(p, &s, &in, &o);
        dct_sync_advance(p, &s, &in, &o, h);
        if (s.position_m >= end)
            return i * h;
    }
    return -1.0;
}

/* ring turn-back: until the sleeve has passed the ring it moves the gear
 * side's inertia J as a mass J tan^2(beta) / r_b^2; beyond, its own mass */
static void test_sync_ring_turn_back(void)
{
    dct_sync_params p = sync_params();
    double h = 1.25e-4, f = 600.0, j = 0.07, pass = p.ring_pass_travel_mm;
    double tb = tan(p.ring_chamfer_angle_deg * (3.14159265358979323846 / 180.0)) / p.dog_radius_m;
    double m = p.sleeve_mass_kg + j * tb * tb; /* 105 kg */
    /* x = (F/c) (t - tau (1 - exp(-t/tau))), tau = m / c: solved for t by bisection */
    double c = p.sleeve_damping_ns_per_m, tau = m / c, lo = 0.0, hi = 1.0;
    for (int i = 0; i < 100; i++) {
        double t = 0.5 * (lo + hi);
        if (f / c * (t - tau * (1.0 - exp(-t / tau))) < pass * 1e-3)
            lo = t;
        else
            hi = t;
    }
    double t_pass = sleeve_travel_time(&p, f, j, pass, h);
    CHECK(fabs(t_pass - lo) < 0.02 * lo, "ring pass %g s expected %g s", t_pass, lo);
    /* no gear inertia, or no chamfer angle: the sleeve's own mass, far quicker */
    double t_free = sleeve_travel_time(&p, f, 0.0, pass, h);
    dct_sync_params flat = p;
    flat.ring_chamfer_angle_deg = 0.0;
    CHECK(t_free < 0.2 * t_pass && sleeve_travel_time(&flat, f, j, pass, h) == t_free,
          "no turn-back without inertia or chamfer (%g, %g)", t_free, t_pass);
    /* past the ring the sleeve is light again: the next 0.5 mm take the free time */
    double t_more = sleeve_travel_time(&p, f, j, pass + 0.5, h) - t_pass;
    CHECK(t_more < 0.5 * t_pass, "light past the ring (%g s)", t_more);
    /* pulled back out of an engaged gear, the sleeve leaves the ring: no turn-back */
    dct_sync_state s;
    dct_sync_init(&p, &s, 1);
    dct_sync_input in = {-f, 0.0, 0.0, 1.0, j, j, 0.0};
    dct_sync_output o;
    double t_out = -1.0, t_out_free = -1.0;
    for (int i = 1; i < 100000 && t_out < 0.0; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, h);
        if (s.phase == DCT_SYNC_DISENGAGED)
            t_out = i * h;
    }
    dct_sync_init(&p, &s, 1);
    in.gear_inertia_pos_kgm2 = 0.0;
    for (int i = 1; i < 100000 && t_out_free < 0.0; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, h);
        if (s.phase == DCT_SYNC_DISENGAGED)
            t_out_free = i * h;
    }
    CHECK(t_out > 0.0 && t_out == t_out_free, "pull-out unaffected (%g, %g)", t_out, t_out_free);
}

/* a jammed sleeve stays where it is in every phase: in neutral under a fork
 * force, on the cone (it cannot pass the blocker, however small the slip),
 * engaged under a pull-out force (it stays in gear) */
static void test_sync_jammed(void)
{
    dct_sync_params p = sync_params();
    dct_sync_state s;
    dct_sync_output o;
    dct_sync_init(&p, &s, 0);
    dct_sync_input in = {1000.0, 50.0, 0.0, 1.0, 0.05, 0.05, 1.0};
    for (int i = 0; i < 4000; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.position_m == 0.0 && s.velocity_m_s == 0.0 && s.phase == DCT_SYNC_DISENGAGED,
          "jammed in neutral: %g mm, phase %g", s.position_m * 1e3, s.phase);

    in.fork_jammed = 0.0;
    in.slip_pos_rad_s = 0.1; /* below the lock speed: would engage at once */
    for (int i = 0; i < 4000 && s.phase != DCT_SYNC_SYNCHRONIZING; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    double x_cone = s.position_m;
    in.fork_jammed = 1.0;
    for (int i = 0; i < 4000; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.phase == DCT_SYNC_SYNCHRONIZING && s.position_m == x_cone,
          "jammed on the cone: phase %g, %g mm", s.phase, s.position_m * 1e3);
    CHECK(s.twist_rad == o.torque_nm / p.stiffness_nm_per_rad, "cone twist still follows eq. 3");

    dct_sync_init(&p, &s, 1);
    in.fork_force_n = -1000.0;
    in.slip_pos_rad_s = 0.5;
    double twist0 = s.twist_rad;
    for (int i = 0; i < 4000; i++) {
        dct_sync_output_eval(&p, &s, &in, &o);
        dct_sync_advance(&p, &s, &in, &o, 1.25e-4);
    }
    CHECK(s.phase == DCT_SYNC_ENGAGED && s.position_m == 8.5e-3 && s.velocity_m_s == 0.0,
          "jammed in gear: phase %g, %g mm", s.phase, s.position_m * 1e3);
    CHECK(fabs(s.twist_rad - twist0 - 4000 * 1.25e-4 * 0.5) < 1e-12, "twist integrates the slip (%g)",
          s.twist_rad);
}

/* faults.c on a small parameter set: ranges, the parametric faults in the
 * parameters, the others in the inputs, all zero = the parameters as given */
static void test_faults(void)
{
    static dct_params p, e;
    dct_faults f, in_effect;
    memset(&p, 0, sizeof p);
    memset(&f, 0, sizeof f);
    for (int k = 0; k < 2; k++) {
        p.clutch[k].mu_static = 0.11;
        p.clutch[k].mu_kinetic = 0.12;
        p.clutch[k].pack_gap_mm = 1.5;
    }
    p.hydraulics.supply.line.n = 2;
    p.hydraulics.supply.line.pressure_bar[0] = 20.0;
    p.hydraulics.supply.line.pressure_bar[1] = 5.0;
    for (int k = 0; k < DCT_N_SLEEVES; k++)
        p.gearbox.sync[k].blocker_force_max_n = 1300.0;
    p.engine.full_load.n = 3;
    p.engine.full_load.torque_nm[0] = 150.0;
    p.engine.full_load.torque_nm[1] = 280.0;
    p.engine.full_load.torque_nm[2] = 250.0;

    int bad = -1;
    memset(&e, 0xff, sizeof e);
    CHECK(dct_faults_prepare(&f, &p, &e, &in_effect, &bad) == DCT_OK, "no fault accepted");
    CHECK(memcmp(&e, &p, sizeof p) == 0, "no fault: effective = params byte for byte");

    f.friction_loss[1] = 0.5;
    f.pack_gap_offset_mm[0] = 0.7;
    f.line_pressure_loss = 0.25;
    f.blocker_failed[2] = 1.0;
    f.engine_torque_limited = 1.0;
    f.engine_torque_max_nm = 200.0;
    CHECK(dct_faults_prepare(&f, &p, &e, &in_effect, &bad) == DCT_OK, "faults accepted");
    CHECK(e.clutch[1].mu_static == 0.055 && e.clutch[1].mu_kinetic == 0.06 && e.clutch[0].mu_static == 0.11,
          "friction fade %g %g", e.clutch[1].mu_static, e.clutch[1].mu_kinetic);
    CHECK(e.clutch[0].pack_gap_mm == 1.5 + 0.7 && e.clutch[1].pack_gap_mm == 1.5, "kiss point drift %g",
          e.clutch[0].pack_gap_mm);
    CHECK(e.hydraulics.supply.line.pressure_bar[0] == 15.0 && e.hydraulics.supply.line.pressure_bar[1] == 3.75,
          "line pressure loss");
    CHECK(e.gearbox.sync[2].blocker_force_max_n == 0.0 && e.gearbox.sync[1].blocker_force_max_n == 1300.0,
          "blocker failed");
    CHECK(e.engine.full_load.torque_nm[0] == 150.0 && e.engine.full_load.torque_nm[1] == 200.0 &&
          e.engine.full_load.torque_nm[2] == 200.0, "full load capped");
    CHECK(p.clutch[1].mu_static == 0.11 && p.engine.full_load.torque_nm[1] == 280.0, "params untouched");
    CHECK(memcmp(&in_effect, &f, sizeof f) == 0, "faults in effect");

    /* refused: the first bad value named, nothing written */
    dct_params before = e;
    dct_faults g = f;
    g.friction_loss[0] = 1.5;
    CHECK(dct_faults_prepare(&g, &p, &e, &in_effect, &bad) == DCT_ERR_PARAM &&
          bad == (int)(offsetof(dct_faults, friction_loss) / sizeof(double)), "loss > 1 refused (%d)", bad);
    CHECK(memcmp(&e, &before, sizeof e) == 0 && memcmp(&in_effect, &f, sizeof f) == 0, "refusal writes nothing");
    g = f;
    g.pack_gap_offset_mm[1] = -1.6;
    CHECK(dct_faults_check(&g, &p, &bad) == DCT_ERR_PARAM &&
          bad == (int)(offsetof(dct_faults, pack_gap_offset_mm) / sizeof(double)) + 1, "gap < 0 refused");
    g.pack_gap_offset_mm[1] = -1.5;
    CHECK(dct_faults_check(&g, &p, &bad) == DCT_OK, "gap closed to 0 accepted");
    g = f;
    g.engine_torque_max_nm = -1.0;
    CHECK(dct_faults_check(&g, &p, &bad) == DCT_ERR_PARAM &&
          bad == (int)(offsetof(dct_faults, engine_torque_max_nm) / sizeof(double)), "negative torque refused");
    g = f;
    g.fork_jammed[3] = NAN;
    CHECK(dct_faults_check(&g, &p, &bad) == DCT_ERR_PARAM &&
          bad == (int)(offsetof(dct_faults, fork_jammed) / sizeof(double)) + 3, "NaN refused");
    g = f;
    g.pack_gap_offset_mm[0] = INFINITY;
    CHECK(dct_faults_check(&g, &p, &bad) == DCT_ERR_PARAM, "infinite offset refused");

    /* the step's faults */
    memset(&f, 0, sizeof f);
    f.solenoid_open[1] = 1.0;
    f.spool_stuck[0] = 1.0;
    f.fork_jammed[2] = 0.7;
    dct_inputs u;
    memset(&u, 0, sizeof u);
    u.solenoid_current1_a = 0.6;
    u.solenoid_current2_a = 0.8;
    dct_faults_apply_inputs(&f, &u);
    CHECK(u.solenoid_current1_a == 0.6 && u.solenoid_current2_a == 0.0, "solenoid open");
    dct_hydraulics_input hi;
    dct_gearbox_input gi;
    memset(&hi, 0xff, sizeof hi);
    memset(&gi, 0xff, sizeof gi);
    dct_faults_apply_couplings(&f, &hi, &gi);
    CHECK(hi.spool_stuck[0] == 1.0 && hi.spool_stuck[1] == 0.0, "spool stuck");
    CHECK(gi.fork_jammed[0] == 0.0 && gi.fork_jammed[1] == 0.0 && gi.fork_jammed[2] == 1.0 &&
          gi.fork_jammed[3] == 0.0, "fork jammed");
}

static void test_magic_formula(void)
{
    dct_tyre_params p;
    memset(&p, 0, sizeof p);
    p.radius_m = 0.316; p.nominal_load_n = 4000; p.pcx1 = 1.65; p.pdx1 = 1.1; p.pdx2 = -0.08;
    p.pex1 = 0.3; p.pex2 = -0.1; p.pkx1 = 22; p.pkx3 = 0.1; p.relaxation_length_m = 0.25;
    CHECK(dct_magic_formula(&p, 0.0, 4000) == 0.0, "no slip no force");
    double k = (dct_magic_formula(&p, 1e-5, 4000) - dct_magic_formula(&p, -1e-5, 4000)) / 2e-5;
    CHECK(fabs(k - 22 * 4000) < 1e-3 * 22 * 4000, "slip stiffness %g", k);
    double peak = 0.0;
    for (int i = 0; i <= 1000; i++) {
        double f = dct_magic_formula(&p, i * 1e-3, 4000);
        if (f > peak)
            peak = f;
    }
    CHECK(fabs(peak - 1.1 * 4000) < 1.0, "peak %g", peak);
    CHECK(dct_magic_formula(&p, -0.1, 4000) == -dct_magic_formula(&p, 0.1, 4000), "odd");
}

static void test_differential(void)
{
    dct_driveline_params p = {9000, 25, 7000, 25, 18, 45000, 630, 0.015, 400000};
    dct_driveline_state s = {0.01, 0.0, 0.0, 0.0};
    dct_driveline_input in = {10.0, 9.0, 11.0, 0.0, 0.0};
    dct_driveline_output o;
    dct_driveline_output_eval(&p, &s, &in, &o);
    double tr = 7000 * s.right_twist_rad + 25 * (o.right_side_speed_rad_s - 11.0);
    CHECK(fabs(o.shaft_torque_nm - tr) < 1e-9, "equal torques %g %g", o.shaft_torque_nm, tr);
    CHECK(fabs(o.left_side_speed_rad_s + o.right_side_speed_rad_s - 20.0) < 1e-12, "carrier mean");
    /* the powertrain at rest on its mounts: the half-shafts' reaction alone rolls it */
    CHECK(o.mount_torque_nm == 0.0, "mount %g", o.mount_torque_nm);
    CHECK(fabs(o.roll_accel_rad_s2 + 2.0 * o.shaft_torque_nm / 18.0) < 1e-12, "roll accel %g",
          o.roll_accel_rad_s2);
}

/* powertrain roll: the carrier turns with the housing in the half-shafts'
 * twist; the mounts' rubber, then the progressive stop beyond phi_s */
static void test_powertrain_roll(void)
{
    dct_driveline_params p = {9000, 25, 7000, 25, 18, 45000, 630, 0.015, 400000};
    dct_driveline_input in = {10.0, 10.0, 10.0, 0.0, 0.0};
    dct_driveline_output o, o0;
    dct_driveline_state s0 = {0.0, 0.0, 0.0, 0.0};
    dct_driveline_state s = {0.0, 0.0, 0.0, 0.5};
    dct_driveline_output_eval(&p, &s0, &in, &o0);
    dct_driveline_output_eval(&p, &s, &in, &o);
    /* rolling at 0.5 rad/s twists both shafts as a carrier 0.5 rad/s faster would */
    CHECK(fabs(o.shaft_torque_nm - 25 * 0.5) < 1e-9, "roll rate in the twist %g", o.shaft_torque_nm);
    CHECK(fabs(o.mount_torque_nm + 630 * 0.5) < 1e-9, "mount damping %g", o.mount_torque_nm);
    dct_driveline_state a = {0.0, 0.0, 0.01, 0.0}, b = {0.0, 0.0, -0.025, 0.0};
    dct_driveline_output_eval(&p, &a, &in, &o);
    CHECK(fabs(o.mount_torque_nm + 45000 * 0.01) < 1e-9, "rubber %g", o.mount_torque_nm);
    dct_driveline_output_eval(&p, &b, &in, &o);
    CHECK(fabs(o.mount_torque_nm - (45000 * 0.025 + 400000 * 0.01)) < 1e-9, "stop %g", o.mount_torque_nm);
    double e = dct_driveline_mount_energy(&p, -0.025);
    CHECK(fabs(e - (0.5 * 45000 * 0.025 * 0.025 + 0.5 * 400000 * 0.01 * 0.01)) < 1e-12, "energy %g", e);
    (void)o0;
}

int main(void)
{
    test_powertrain_roll();
    test_friction_stick_slip();
    test_curve();
    test_sync_phases();
    test_sync_clash();
    test_sync_released_from_the_cone();
    test_sync_ring_turn_back();
    test_sync_jammed();
    test_faults();
    test_magic_formula();
    test_differential();
    printf("%d passed, %d failed\n", checks - failures, failures);
    return failures ? 1 : 0;
}
