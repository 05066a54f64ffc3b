/*
 * piston.c - clutch piston in the real-time form of the reference paper
 * (eq. 8, model BAP10RT): no piston mass; the flow into the chamber moves
 * the piston (v = Q / A) and the pressure results from the force balance
 *   p A = F0 + k_r x                      while the pack gap is open
 *   p A = F0 + k_r x + k_pack (x - gap)   once the pack is clamped
 * (return spring preload F0 and rate k_r; the clamped pack is an elastic end
 * stop of stiffness k_pack, whose force is the clamp force of the clutch).
 * Below the preload the piston rests on its stop. Written the other way
 * round (position from pressure) it gives the compliance A dx/dp that the
 * chamber pressure equation needs: piecewise linear and continuous.
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_piston_eval(const dct_clutch_params *p, double pressure_pa, dct_piston_output *out)
{
    double a = p->piston_area_m2;
    double f = pressure_pa * a - p->return_spring_n; /* force beyond the preload */
    double gap = p->pack_gap_mm * 1e-3;
    double kr = p->return_spring_n_per_m, kp = p->pack_stiffness_n_per_m;
    if (f <= 0.0) {
        out->position_m = 0.0;
        out->clamp_force_n = 0.0;
        out->compliance_m3_per_pa = 0.0;
    } else if (f <= kr * gap) {
        out->position_m = f / kr;
        out->clamp_force_n = 0.0;
        out->compliance_m3_per_pa = a * a / kr;
    } else {
        double x = (f + kp * gap) / (kr + kp);
        out->position_m = x;
        out->clamp_force_n = kp * (x - gap);
        out->compliance_m3_per_pa = a * a / (kr + kp);
    }
}
