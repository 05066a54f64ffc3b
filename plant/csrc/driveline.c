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
 *
 * Powertrain roll: the gear train multiplies the torque against its housing,
 * so the half-shafts' torque (2 T on the carrier) is reacted by the engine
 * and gearbox housings, which sit on rubber mounts (engine and gearbox
 * mounts, the pendulum support): they roll about an axis parallel to the
 * shafts,
 *   J_pt d2phi/dt2 = -k_m d - k_s (|d| - phi_s)+ sgn(d) - c_m dd/dt - 2 T,
 *   d = phi + theta (the mounts' deflection: theta the body's pitch, nose up)
 * (the rubber's stiffness k_m for small roll, progressive stops k_s beyond
 * phi_s, which carry the full drive torque)
 * and the carrier turns with them: its speed in the half-shafts' twist is the
 * gearbox's (relative to its housing) + dphi/dt. The rotating parts' own
 * angular momentum change is left out of the roll balance (it is the
 * half-shafts' torque over the overall ratio, a few %: the fast parts are
 * light). The mounts' torque acts on the body (vehicle pitch).
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_driveline_init(const dct_driveline_params *p, dct_driveline_state *s)
{
    (void)p;
    s->left_twist_rad = 0.0;
    s->right_twist_rad = 0.0;
    s->roll_rad = 0.0;
    s->roll_rate_rad_s = 0.0;
}

void dct_driveline_output_eval(const dct_driveline_params *p, const dct_driveline_state *s,
                               const dct_driveline_input *in, dct_driveline_output *out)
{
    double kl = p->left_stiffness_nm_per_rad, cl = p->left_damping_nms_per_rad;
    double kr = p->right_stiffness_nm_per_rad, cr = p->right_damping_nms_per_rad;
    double wc = in->carrier_speed_rad_s + s->roll_rate_rad_s;
    double d = (kr * s->right_twist_rad - kl * s->left_twist_rad +
                cr * (wc - in->right_wheel_speed_rad_s) - cl * (wc - in->left_wheel_speed_rad_s)) /
               (cl + cr);
    out->left_side_speed_rad_s = wc + d;
    out->right_side_speed_rad_s = wc - d;
    out->shaft_torque_nm = kl * s->left_twist_rad + cl * (wc + d - in->left_wheel_speed_rad_s);
    out->carrier_load_nm = 2.0 * out->shaft_torque_nm;
    /* the mounts' deflection: the roll against the body (a nose-up pitch
     * turns the body against the wheels' forward sense) */
    double phi = s->roll_rad + in->body_pitch_rad, over = fabs(phi) - p->mount_roll_stop_rad;
    double stop = over > 0.0 ? p->mount_roll_stop_stiffness_nm_per_rad * over : 0.0;
    out->mount_torque_nm = -p->mount_roll_stiffness_nm_per_rad * phi - (phi > 0.0 ? stop : -stop) -
                           p->mount_roll_damping_nms_per_rad * (s->roll_rate_rad_s + in->body_pitch_rate_rad_s);
    out->roll_accel_rad_s2 = (out->mount_torque_nm - out->carrier_load_nm) / p->powertrain_roll_inertia_kgm2;
}

void dct_driveline_advance(const dct_driveline_params *p, dct_driveline_state *s,
                           const dct_driveline_input *in, const dct_driveline_output *out, double h)
{
    (void)p;
    s->left_twist_rad += h * (out->left_side_speed_rad_s - in->left_wheel_speed_rad_s);
    s->right_twist_rad += h * (out->right_side_speed_rad_s - in->right_wheel_speed_rad_s);
    s->roll_rad += h * s->roll_rate_rad_s;
    s->roll_rate_rad_s += h * out->roll_accel_rad_s2;
}

double dct_driveline_mount_energy(const dct_driveline_params *p, double deflection_rad)
{
    double over = fabs(deflection_rad) - p->mount_roll_stop_rad;
    double e = 0.5 * p->mount_roll_stiffness_nm_per_rad * deflection_rad * deflection_rad;
    if (over > 0.0)
        e += 0.5 * p->mount_roll_stop_stiffness_nm_per_rad * over * over;
    return e;
}
