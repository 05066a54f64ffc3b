/*
 * wheel.c - a wheel position (one front wheel, or the rear axle lumped) with
 * its friction brake. The brake is the reset-integrator friction element
 * between the wheel and the knuckle, capacity proportional to the pedal: it
 * holds a parked car (sticks) and slides at its capacity when braking.
 *   J dw/dt = T_shaft - F_x R - M_rr - T_brake
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_wheel_init(const dct_wheel_params *p, dct_wheel_state *s, double speed_rad_s)
{
    (void)p;
    s->speed_rad_s = speed_rad_s;
    s->brake_twist_rad = 0.0;
}

void dct_wheel_output_eval(const dct_wheel_params *p, const dct_wheel_state *s,
                           const dct_wheel_input *in, dct_wheel_output *out)
{
    double cap = 0.01 * in->brake_pedal_pct * p->brake_torque_max_nm;
    dct_friction_eval(&p->brake, s->brake_twist_rad, s->speed_rad_s, cap, &out->brake);
    out->brake_torque_nm = out->brake.torque_nm;
    out->body_torque_nm = in->drive_torque_nm - out->brake.torque_nm;
    out->speed_deriv_rad_s2 = (out->body_torque_nm - in->tyre_force_n * in->tyre_radius_m -
                               in->rolling_moment_nm) / p->inertia_kgm2;
}

void dct_wheel_advance(const dct_wheel_params *p, dct_wheel_state *s,
                       const dct_wheel_input *in, const dct_wheel_output *out, double h)
{
    double cap = 0.01 * in->brake_pedal_pct * p->brake_torque_max_nm;
    s->brake_twist_rad = dct_friction_advance(&p->brake, s->brake_twist_rad, &out->brake, cap, h);
    s->speed_rad_s += h * out->speed_deriv_rad_s2;
}
