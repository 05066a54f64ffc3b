/*
 * clutch.c - wet multi-plate clutch (K1 or K2 of the DSG 02E).
 *
 * The clamp force comes from the piston (piston.c): the hydraulics, or a
 * commanded pressure through the same piston force balance.
 * Capacity = surfaces x mu(slip) x effective radius x clamp force, with a
 * Stribeck curve mu(w) = mu_k + (mu_s - mu_k) exp(-(w / w_s)^2); for wet
 * clutches mu_k >= mu_s (a rising curve avoids shudder). Friction by the
 * reset-integrator element; plus the viscous drag of the open wet pack.
 * Thermal effects (thermal.c): the oil temperature scales both friction
 * coefficients (mu_excess) and the drag (drag_excess); 0 when warm.
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_clutch_init(const dct_clutch_params *p, dct_clutch_state *s)
{
    (void)p;
    s->twist_rad = 0.0;
}

static double clutch_mu(const dct_clutch_params *p, double slip_rad_s)
{
    return p->mu_kinetic +
           (p->mu_static - p->mu_kinetic) * dct_gauss(slip_rad_s / p->stribeck_speed_rad_s);
}

void dct_clutch_output_eval(const dct_clutch_params *p, const dct_clutch_state *s,
                            const dct_clutch_input *in, dct_clutch_output *out)
{
    double slip = in->drive_speed_rad_s - in->driven_speed_rad_s;
    double force = in->clamp_force_n > 0.0 ? in->clamp_force_n : 0.0;
    double lever = p->surfaces * p->radius_m * force;
    double mu_factor = 1.0 + in->mu_excess;
    double cap = lever * (clutch_mu(p, slip) * mu_factor);
    dct_friction_eval(&p->friction, s->twist_rad, slip, cap, &out->friction);
    out->clamp_force_n = force;
    out->capacity_nm = lever * (p->mu_static * mu_factor);
    out->slide_capacity_nm = cap;
    out->slip_rad_s = slip;
    double drag = p->drag_nms_per_rad * (1.0 + in->drag_excess) * slip;
    out->drag_torque_nm = drag;
    out->mu_kinetic = p->mu_kinetic * mu_factor;
    out->torque_nm = out->friction.torque_nm + drag;
    /* heat: sliding at the capacity; sticking, what the element takes
     * (torque x slip) less what its spring stores (k z dz/dt, dz/dt = slip):
     * the stick damper's c slip^2, or less while the torque is held at the
     * capacity (a capacity that grows step by step keeps the twist just
     * below its limit); and the drag */
    double fr = out->friction.sliding > 0.5
                    ? out->friction.torque_nm * slip
                    : (out->friction.torque_nm - p->friction.stiffness_nm_per_rad * s->twist_rad) * slip;
    out->heat_w = fr + drag * slip;
}

void dct_clutch_advance(const dct_clutch_params *p, dct_clutch_state *s,
                        const dct_clutch_output *out, double h)
{
    s->twist_rad = dct_friction_advance(&p->friction, s->twist_rad, &out->friction,
                                        out->slide_capacity_nm, h);
}
