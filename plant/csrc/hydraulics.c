/*
 * hydraulics.c - the clutch hydraulic system of one DSG 02E (reference
 * paper, Fig. 3): a line pressure supply (pressure over the line-solenoid
 * current from a map, behind the regulator's first-order lag; a tank at
 * atmospheric pressure), and per clutch a proportional pressure control
 * valve feeding the clutch chamber and piston.
 *
 * Chamber: the oil between valve and piston (lines, chamber) is
 * compressible, with entrained air; the piston takes volume as it strokes
 * (eq. 8: v = Q / A). The state is the oil volume fed in, dV/dt = Q_valve;
 * the pressure is the one at which oil, air and piston take that volume:
 *   V(p) = V_c (1 - a) p / beta + a V_c (1 - p_atm / p_abs) + A x(p)
 * (air isothermal: small bubbles). So the flow first fills the gap at the
 * low pressure of the return spring, then the pressure rises on the
 * stiffness of the clamped pack.
 *
 * The hydraulics run at their own sub-step (params.substeps per plant
 * sub-step); they drive the mechanics one way, through the clamp forces.
 */
#include "dct_plant.h"
#include "dct_util.h"

#define P_ATM 1.0e5
#define P_MIN (-0.9e5) /* the chamber cannot be pulled below (about) vapour pressure */

double dct_chamber_volume(const dct_oil_params *oil, const dct_clutch_params *clutch,
                          double chamber_m3, double pressure_pa)
{
    double a = oil->air_fraction;
    double p = pressure_pa > P_MIN ? pressure_pa : P_MIN;
    dct_piston_output po;
    dct_piston_eval(clutch, p, &po);
    return chamber_m3 * ((1.0 - a) * p / oil->bulk_modulus_pa + a * (1.0 - P_ATM / (p + P_ATM))) +
           clutch->piston_area_m2 * po.position_m;
}

/* In each piece of the piston law A x(p) = c1 p + c0 is linear, so
 * V = k p + a V_c p / (p + P) + c0 (k = oil + c1) is a quadratic in p:
 *   k p^2 + (k P + a V_c + c0 - V) p + (c0 - V) P = 0, the larger root. */
static double piece_pressure(double k, double av, double c0, double v)
{
    double b = k * P_ATM + av + c0 - v;
    double c = (c0 - v) * P_ATM;
    double disc = b * b - 4.0 * k * c;
    double root = sqrt(disc > 0.0 ? disc : 0.0);
    /* numerically stable form of (-b + root) / (2k) */
    return b > 0.0 ? (2.0 * -c) / (b + root) : (-b + root) / (2.0 * k);
}

void dct_chamber_prepare(const dct_oil_params *oil, const dct_clutch_params *clutch,
                         double chamber_m3, dct_chamber_derived *d)
{
    double a = oil->air_fraction, area = clutch->piston_area_m2;
    double gap = clutch->pack_gap_mm * 1e-3;
    double kr = clutch->return_spring_n_per_m, kt = kr + clutch->pack_stiffness_n_per_m;
    double p_kiss = clutch->return_spring_n / area;
    double p_closed = (clutch->return_spring_n + kr * gap) / area;
    d->min_m3 = dct_chamber_volume(oil, clutch, chamber_m3, P_MIN);
    d->kiss_m3 = dct_chamber_volume(oil, clutch, chamber_m3, p_kiss);
    d->closed_m3 = dct_chamber_volume(oil, clutch, chamber_m3, p_closed);
    d->oil_m3_per_pa = chamber_m3 * (1.0 - a) / oil->bulk_modulus_pa;
    d->air_m3 = a * chamber_m3;
    d->stroke_m3_per_pa = area * area / kr;
    d->stroke_m3 = -d->stroke_m3_per_pa * p_kiss;
    d->clamped_m3_per_pa = area * area / kt;
    d->clamped_m3 = area * (clutch->pack_stiffness_n_per_m * gap - clutch->return_spring_n) / kt;
}

double dct_chamber_pressure(const dct_chamber_derived *d, double volume_m3)
{
    if (volume_m3 <= d->min_m3)
        return P_MIN;
    if (volume_m3 <= d->kiss_m3)
        return piece_pressure(d->oil_m3_per_pa, d->air_m3, 0.0, volume_m3);
    if (volume_m3 <= d->closed_m3)
        return piece_pressure(d->oil_m3_per_pa + d->stroke_m3_per_pa, d->air_m3, d->stroke_m3, volume_m3);
    return piece_pressure(d->oil_m3_per_pa + d->clamped_m3_per_pa, d->air_m3, d->clamped_m3, volume_m3);
}

void dct_hydraulics_prepare(const dct_hydraulics_params *p, const dct_clutch_params clutch[2],
                            dct_hydraulics_derived *d)
{
    for (int k = 0; k < 2; k++)
        dct_chamber_prepare(&p->oil, &clutch[k], p->chamber_volume_cm3[k] * 1e-6, &d->chamber[k]);
}

void dct_hydraulics_init(const dct_hydraulics_params *p, dct_hydraulics_state *s)
{
    s->line_pressure_pa = dct_pressure_map_eval(&p->supply.line, 0.0) * DCT_PA_PER_BAR;
    for (int k = 0; k < 2; k++) {
        s->clutch_oil_m3[k] = 0.0;
        dct_valve_init(&p->valve, &s->valve[k]);
    }
}

void dct_hydraulics_output_eval(const dct_hydraulics_params *p, const dct_hydraulics_derived *d,
                                const dct_clutch_params clutch[2], const dct_hydraulics_state *s,
                                dct_hydraulics_output *out)
{
    (void)p;
    for (int k = 0; k < 2; k++) {
        double pk = dct_chamber_pressure(&d->chamber[k], s->clutch_oil_m3[k]);
        dct_piston_output po;
        dct_piston_eval(&clutch[k], pk, &po);
        out->clamp_force_n[k] = po.clamp_force_n;
        out->piston_position_m[k] = po.position_m;
        out->clutch_pressure_pa[k] = pk;
    }
}

void dct_hydraulics_advance(const dct_hydraulics_params *p, const dct_hydraulics_derived *d,
                            dct_hydraulics_state *s, const dct_hydraulics_input *in, double h)
{
    int n = (int)p->substeps;
    double hh = h / n;
    double line_target = dct_pressure_map_eval(&p->supply.line, in->line_current_a) * DCT_PA_PER_BAR;
    /* the oil at its temperature now (thermal.c) */
    dct_oil_params oil = p->oil;
    if (in->oil_viscosity_m2_s > 0.0)
        oil.viscosity_m2_s = in->oil_viscosity_m2_s;
    for (int i = 0; i < n; i++) {
        dct_valve_output vo[2];
        for (int k = 0; k < 2; k++) {
            double pk = i == 0 && in->pressure_known > 0.5 ? in->pressure_pa[k]
                                                          : dct_chamber_pressure(&d->chamber[k], s->clutch_oil_m3[k]);
            dct_valve_input vi = {in->current_a[k], s->line_pressure_pa, pk};
            dct_valve_output_eval(&p->valve, &oil, &s->valve[k], &vi, &vo[k]);
        }
        for (int k = 0; k < 2; k++) {
            double held_m = s->valve[k].spool_position_m;
            dct_valve_advance(&p->valve, &s->valve[k], &vo[k], hh);
            if (in->spool_stuck[k] > 0.5) {
                /* a stuck spool (fault): the forces on it no longer move
                 * it; the solenoid force still follows the current and the
                 * edges meter at the held opening */
                s->valve[k].spool_position_m = held_m;
                s->valve[k].spool_velocity_m_s = 0.0;
            }
            s->clutch_oil_m3[k] += hh * vo[k].flow_m3_s;
        }
        s->line_pressure_pa += hh * (line_target - s->line_pressure_pa) / p->supply.tau_s;
    }
}
