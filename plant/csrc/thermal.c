/*
 * thermal.c - lumped temperatures of the engine coolant, the engine oil and
 * the transmission (DSG) oil, and what they change in the other components.
 *
 * Heat balances (explicit Euler like every other state):
 *   C_c dT_c/dt = f_w (P_fuel - P_comb) + (1 - s_o) P_fric + Q_oc + Q_tc
 *                 - UA_rad(v) o(T_c) (T_c - T_a) - UA_e (T_c - T_a)
 *   C_o dT_o/dt = s_o P_fric - Q_oc,            Q_oc = UA_oc (T_o - T_c)
 *   C_t dT_t/dt = P_clutch + P_gearbox - Q_tc - UA_t(v) (T_t - T_a),
 *                                               Q_tc = UA_tc (T_t - T_c)
 * P_fuel: the fuel burnt x its lower heating value; P_comb: the combustion
 * torque x crank speed; f_w: the share of the unused fuel energy that goes
 * through the walls (the rest leaves with the exhaust); P_fric: the engine's
 * drag power, s_o of it into the oil. The thermostat opens the radiator
 * linearly from T_open to T_full (o = min_opening .. 1); the radiator's and
 * the gearbox housing's conductance grow with the vehicle speed (ram air).
 * Cabin heater off.
 *
 * Effects, from the state alone (evaluated before anything advances):
 *   oil viscosities by Walther (ASTM D341): log log (nu + 0.7) = A - B log T
 *   through the oil's 40 and 100 degC data points;
 *   engine drag x (1 + s_r ((nu_o / nu_o,ref)^n - 1)): the rubbing share s_r
 *   of the drag curve follows the oil viscosity, pumping does not;
 *   idle target + rise and fuel x (1 + enrichment), both ramping linearly
 *   from 0 at idle_warm_degc to full at idle_cold_degc (coolant);
 *   transmission: valve viscosity nu_t(T) = nu_ref (nu_t(T) / nu_t(T_ref)),
 *   open-pack drag x r^n_c, viscous gearbox drags x r^n_g, friction
 *   coefficients x (1 + c_mu (T - T_ref)); the clutch pack gap
 *   + (alpha_housing - alpha_plates) L (T - T_ref) (thermal expansion: the
 *   kiss point moves with the oil temperature).
 */
#include "dct_plant.h"
#include "dct_util.h"

#define KELVIN 273.15

/* Walther: log10 log10 (nu + 0.7) linear in log10 T (kelvin) */
void dct_walther_line_of(double nu40_mm2_s, double nu100_mm2_s, dct_walther_line *line)
{
    double w40 = log10(log10(nu40_mm2_s + 0.7));
    double w100 = log10(log10(nu100_mm2_s + 0.7));
    double l40 = log10(40.0 + KELVIN), l100 = log10(100.0 + KELVIN);
    line->w40 = w40;
    line->dw = w100 - w40;
    line->l40 = l40;
    line->dl = l100 - l40;
}

double dct_walther_at(const dct_walther_line *line, double temp_degc)
{
    double t = temp_degc + KELVIN;
    if (t < 150.0)
        t = 150.0; /* the law's range ends long before: keeps the log finite */
    double w = line->w40 + line->dw * (log10(t) - line->l40) / line->dl;
    return pow(10.0, pow(10.0, w)) - 0.7;
}

double dct_walther_viscosity(double nu40_mm2_s, double nu100_mm2_s, double temp_degc)
{
    dct_walther_line line;
    dct_walther_line_of(nu40_mm2_s, nu100_mm2_s, &line);
    return dct_walther_at(&line, temp_degc);
}

void dct_thermal_init(const dct_thermal_params *p, dct_thermal_state *s, double coolant_degc,
                      double engine_oil_degc, double trans_oil_degc)
{
    (void)p;
    s->coolant_temp_degc = coolant_degc;
    s->engine_oil_temp_degc = engine_oil_degc;
    s->trans_oil_temp_degc = trans_oil_degc;
}

/* 0 at warm and above, 1 at cold and below, linear in between */
static double coldness(const dct_thermal_params *p, double t)
{
    double span = p->idle_warm_degc - p->idle_cold_degc;
    return dct_clamp((p->idle_warm_degc - t) / span, 0.0, 1.0);
}

void dct_thermal_prepare(const dct_thermal_params *p, dct_thermal_derived *d)
{
    dct_walther_line_of(p->engine_oil_viscosity_40c_mm2_s, p->engine_oil_viscosity_100c_mm2_s,
                        &d->engine_oil);
    dct_walther_line_of(p->trans_oil_viscosity_40c_mm2_s, p->trans_oil_viscosity_100c_mm2_s,
                        &d->trans_oil);
    d->engine_oil_ref_mm2_s = dct_walther_at(&d->engine_oil, p->engine_ref_temp_degc);
    d->trans_oil_ref_mm2_s = dct_walther_at(&d->trans_oil, p->trans_ref_temp_degc);
}

/* t rounded to the nearest multiple of q (q = 0: t) */
static double rounded(double t, double q)
{
    return q > 0.0 ? floor(t / q + 0.5) * q : t;
}

void dct_thermal_effects_key(const dct_thermal_params *p, const dct_thermal_state *s, double key[3])
{
    double q = p->effects_resolution_k;
    key[0] = rounded(s->coolant_temp_degc, q);
    key[1] = rounded(s->engine_oil_temp_degc, q);
    key[2] = rounded(s->trans_oil_temp_degc, q);
}

void dct_thermal_effects_eval(const dct_thermal_params *p, const dct_thermal_derived *d,
                              const dct_oil_params *trans_oil, const dct_thermal_state *state,
                              dct_thermal_effects *fx)
{
    /* at the rounded temperatures (effects_resolution_k) */
    double key[3];
    dct_thermal_effects_key(p, state, key);
    dct_thermal_state at = {key[0], key[1], key[2]};
    const dct_thermal_state *s = &at;
    double ro = dct_walther_at(&d->engine_oil, s->engine_oil_temp_degc) / d->engine_oil_ref_mm2_s;
    double rt = dct_walther_at(&d->trans_oil, s->trans_oil_temp_degc) / d->trans_oil_ref_mm2_s;
    double lo = log(ro), lt = log(rt);
    fx->engine_oil_viscosity_ratio = ro;
    fx->engine_drag_factor = 1.0 + p->engine_rubbing_share * (exp(p->engine_friction_viscosity_exponent * lo) - 1.0);
    double cold = coldness(p, s->coolant_temp_degc);
    fx->idle_rise_rpm = p->idle_cold_rise_rpm * cold;
    fx->fuel_enrichment = p->cold_enrichment * cold;
    fx->trans_viscosity_ratio = rt;
    fx->trans_oil_viscosity_m2_s = trans_oil->viscosity_m2_s * rt;
    fx->clutch_drag_factor = exp(p->clutch_drag_viscosity_exponent * lt);
    fx->churning_factor = exp(p->churning_viscosity_exponent * lt);
    double dt = s->trans_oil_temp_degc - p->trans_ref_temp_degc;
    fx->clutch_mu_factor = 1.0 + p->clutch_mu_change_per_k * dt;
    fx->clutch_gap_change_mm = p->clutch_gap_expansion_per_k * p->clutch_gap_length_mm * dt;
    fx->thermostat_opening = dct_clamp((s->coolant_temp_degc - p->thermostat_open_degc) /
                                           (p->thermostat_full_degc - p->thermostat_open_degc),
                                       p->thermostat_min_opening, 1.0);
}

void dct_thermal_output_eval(const dct_thermal_params *p, const dct_thermal_state *s,
                             const dct_thermal_effects *fx, const dct_thermal_input *in,
                             dct_thermal_output *out)
{
    double ta = p->ambient_temp_degc;
    double tc = s->coolant_temp_degc, to = s->engine_oil_temp_degc, tt = s->trans_oil_temp_degc;
    double v = fabs(in->vehicle_speed_m_s);
    double unused = in->fuel_heat_w - in->combustion_power_w;
    if (unused < 0.0)
        unused = 0.0; /* the lag's torque after a fuel cut: no heat from nothing */
    double fric = in->friction_power_w > 0.0 ? in->friction_power_w : 0.0;
    out->coolant_heat_in_w = p->wall_heat_fraction * unused + (1.0 - p->friction_heat_oil_share) * fric;
    out->engine_oil_heat_in_w = p->friction_heat_oil_share * fric;
    out->trans_heat_in_w = in->trans_heat_w;
    out->radiator_w = (p->radiator_ua_w_per_k + p->radiator_ua_per_speed_ws_per_km * v) *
                      fx->thermostat_opening * (tc - ta);
    out->engine_ambient_w = p->engine_ambient_ua_w_per_k * (tc - ta);
    out->trans_ambient_w = (p->trans_ambient_ua_w_per_k + p->trans_ambient_ua_per_speed_ws_per_km * v) * (tt - ta);
    out->oil_to_coolant_w = p->oil_coolant_ua_w_per_k * (to - tc);
    out->trans_to_coolant_w = p->trans_cooler_ua_w_per_k * (tt - tc);
    out->coolant_rate_k_s = (out->coolant_heat_in_w + out->oil_to_coolant_w + out->trans_to_coolant_w -
                             out->radiator_w - out->engine_ambient_w) /
                            p->coolant_heat_capacity_j_per_k;
    out->engine_oil_rate_k_s = (out->engine_oil_heat_in_w - out->oil_to_coolant_w) /
                               p->engine_oil_heat_capacity_j_per_k;
    out->trans_oil_rate_k_s = (out->trans_heat_in_w - out->trans_to_coolant_w - out->trans_ambient_w) /
                              p->trans_heat_capacity_j_per_k;
}

void dct_thermal_advance(const dct_thermal_params *p, dct_thermal_state *s,
                         const dct_thermal_output *out, double h)
{
    (void)p;
    s->coolant_temp_degc += h * out->coolant_rate_k_s;
    s->engine_oil_temp_degc += h * out->engine_oil_rate_k_s;
    s->trans_oil_temp_degc += h * out->trans_oil_rate_k_s;
}
