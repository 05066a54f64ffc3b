/*
 * friction.c - reset-integrator friction element (Haessig and Friedland,
 * 1991), the real-time friction model chosen by the reference paper for its
 * clutches; used here for the wet clutches and the wheel brakes.
 *
 * A twist state z integrates the slip while the element sticks; the torque is
 * a stiff spring-damper on it, k z + c dz/dt, limited to the capacity. When
 * |z| reaches capacity / k in the direction of the slip, the integrator stops
 * (dz/dt = 0) and the element slides at the capacity. When the slip reverses,
 * integration resumes: the element sticks again. The capacity comes from the
 * caller's Stribeck curve, equal to the breakaway torque at zero slip, so the
 * transmitted torque is continuous through stick -> slip -> stick.
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_friction_eval(const dct_friction_params *p, double twist_rad, double slip_rad_s,
                       double cap_nm, dct_friction_output *out)
{
    double cap = cap_nm > 0.0 ? cap_nm : 0.0;
    double limit = cap / p->stiffness_nm_per_rad;
    int sliding = (twist_rad >= limit && slip_rad_s > 0.0) ||
                  (twist_rad <= -limit && slip_rad_s < 0.0);
    if (sliding) {
        out->torque_nm = slip_rad_s > 0.0 ? cap : -cap;
        out->twist_rate_rad_s = 0.0;
        out->sliding = 1.0;
    } else {
        double t = p->stiffness_nm_per_rad * twist_rad + p->damping_nms_per_rad * slip_rad_s;
        out->torque_nm = dct_clamp(t, -cap, cap);
        out->twist_rate_rad_s = slip_rad_s;
        out->sliding = 0.0;
    }
}

double dct_friction_advance(const dct_friction_params *p, double twist_rad,
                            const dct_friction_output *out, double cap_nm, double h)
{
    double limit = (cap_nm > 0.0 ? cap_nm : 0.0) / p->stiffness_nm_per_rad;
    /* Euler step, then the reset: the twist never exceeds what the
     * capacity can hold (the capacity may also have dropped). */
    return dct_clamp(twist_rad + h * out->twist_rate_rad_s, -limit, limit);
}
