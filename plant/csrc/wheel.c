/*
 * wheel.c - a wheel position (one front wheel, or the rear axle lumped) with
 * its friction brake. The brake is the reset-integrator friction element
 * between the wheel and the knuckle, capacity proportional to the pedal: it
 * holds a parked car (sticks) and slides at its capacity when braking.
 *   J dw/dt = T_shaft - F_x R - M_rr - T_brake
 * The parking lock (selector lever in P) acts through the same element: the
 * pawl in the parking gear holds the driven wheels up to its capacity
 * (park_lock_torque_nm, added to the brake's), but it engages only below
 * park_lock_max_speed_kmh: faster, the gear's teeth push it back out
 * (it ratchets) and it holds nothing.
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_wheel_init(const dct_wheel_params *p, dct_wheel_state *s, double speed_rad_s)
{
    (void)p;
    s->speed_rad_s = speed_rad_s;
    s->brake_twist_rad = 0.0;
}

/* 1 while the parking lock holds this wheel position: lever in P, a lock
 * on this position, and the wheel slow enough for the pawl to engage */
static int park_locked(const dct_wheel_params *p, const dct_wheel_state *s, const dct_wheel_input *in)
{
    return in->park_lock > 0.5 && p->park_lock_torque_nm > 0.0 &&
           fabs(s->speed_rad_s) * in->tyre_radius_m < p->park_lock_max_speed_kmh / 3.6;
}

static double capacity(const dct_wheel_params *p, const dct_wheel_state *s, const dct_wheel_input *in)
{
    double cap = 0.01 * in->brake_pedal_pct * p->brake_torque_max_nm;
    if (park_locked(p, s, in))
        cap += p->park_lock_torque_nm;
    return cap;
}

void dct_wheel_output_eval(const dct_wheel_params *p, const dct_wheel_state *s,
                           const dct_wheel_input *in, dct_wheel_output *out)
{
    double cap = capacity(p, s, in);
    out->capacity_nm = cap;
    out->park_locked = park_locked(p, s, in) ? 1.0 : 0.0;
    dct_friction_eval(&p->brake, s->brake_twist_rad, s->speed_rad_s, cap, &out->brake);
    out->brake_torque_nm = out->brake.torque_nm;
    out->body_torque_nm = in->drive_torque_nm - out->brake.torque_nm;
    out->speed_deriv_rad_s2 = (out->body_torque_nm - in->tyre_force_n * in->tyre_radius_m -
                               in->rolling_moment_nm) / p->inertia_kgm2;
}

void dct_wheel_advance(const dct_wheel_params *p, dct_wheel_state *s,
                       const dct_wheel_input *in, const dct_wheel_output *out, double h)
{
    (void)in;
    s->brake_twist_rad = dct_friction_advance(&p->brake, s->brake_twist_rad, &out->brake,
                                              out->capacity_nm, h);
    s->speed_rad_s += h * out->speed_deriv_rad_s2;
}
