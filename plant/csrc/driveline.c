/*
 * driveline.c - open differential and two half-shafts (front-wheel drive).
 *
 * The side gears and spider are taken as massless, so an open differential
 * splits the torque equally: both half-shafts carry the same torque T, and
 * the side gear speeds w_L = w_c + d, w_R = w_c - d follow from that
 * condition. Each half-shaft is a torsional spring-damper (the right shaft of
 * the Golf is longer, so it may be softer); its twist is a state:
 *   T = k_L phi_L + c_L (w_L - w_wheel_L) = k_R phi_R + c_R (w_R - w_wheel_R)
 * which gives d in closed form (no algebraic loop, no stiff spider mode).
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_driveline_init(const dct_driveline_params *p, dct_driveline_state *s)
{
    (void)p;
    s->left_twist_rad = 0.0;
    s->right_twist_rad = 0.0;
}

void dct_driveline_output_eval(const dct_driveline_params *p, const dct_driveline_state *s,
                               const dct_driveline_input *in, dct_driveline_output *out)
{
    double kl = p->left_stiffness_nm_per_rad, cl = p->left_damping_nms_per_rad;
    double kr = p->right_stiffness_nm_per_rad, cr = p->right_damping_nms_per_rad;
    double wc = in->carrier_speed_rad_s;
    double d = (kr * s->right_twist_rad - kl * s->left_twist_rad +
                cr * (wc - in->right_wheel_speed_rad_s) - cl * (wc - in->left_wheel_speed_rad_s)) /
               (cl + cr);
    out->left_side_speed_rad_s = wc + d;
    out->right_side_speed_rad_s = wc - d;
    out->shaft_torque_nm = kl * s->left_twist_rad + cl * (wc + d - in->left_wheel_speed_rad_s);
    out->carrier_load_nm = 2.0 * out->shaft_torque_nm;
}

void dct_driveline_advance(const dct_driveline_params *p, dct_driveline_state *s,
                           const dct_driveline_input *in, const dct_driveline_output *out, double h)
{
    (void)p;
    s->left_twist_rad += h * (out->left_side_speed_rad_s - in->left_wheel_speed_rad_s);
    s->right_twist_rad += h * (out->right_side_speed_rad_s - in->right_wheel_speed_rad_s);
}
