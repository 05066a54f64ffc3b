/*
 * valve.c - proportional pressure control valve (direct-acting solenoid,
 * spool pressure-reducing valve) and the sharp-edged annular orifice of its
 * metering edges, after the reference paper's real-time submodels.
 *
 *   solenoid   dF_e/dt = (k_f |i| - F_e) / tau_e                      (eq. 9)
 *   spool      m dv/dt = F_e - p_c A_fb - (F_0 + k x) - F_friction(v_f) - F_stops
 *              dv_f/dt = (v - v_f) / tau  (friction velocity lagged,   eq. 10:
 *              no algebraic loop); elastic end stops on both sides
 *   edges      x > overlap opens supply -> clutch, x < -overlap opens
 *              clutch -> tank; metering notches of a given width opened by
 *              |x| - overlap, flow by eqs. 11-13; laminar land leakage
 *   feedback   the controlled pressure acts on A_fb = pi/4 (d_s^2 - d_r^2);
 *              the spool displacing that chamber adds v A_fb to the clutch
 *              flow (eq. 14)
 * In steady state p_c = (k_f i - F_0 - k x) / A_fb: pressure proportional to
 * current, capped by the line pressure when the supply edge is wide open.
 */
#include "dct_plant.h"
#include "dct_util.h"

#define P_ATM 1.0e5

double dct_orifice_flow(const dct_oil_params *oil, double cd_max, double transition_reynolds,
                        double width_m, double opening_m, double p1_pa, double p2_pa)
{
    if (opening_m <= 0.0)
        return 0.0;
    double dp = p1_pa - p2_pa;
    double area = width_m * opening_m;
    double v_ideal = sqrt(2.0 * fabs(dp) / oil->density_kg_m3);
    /* eq. 11; hydraulic diameter of a narrow slot = 2 x opening. The flow
     * coefficient falls to zero with the Reynolds number, so the flow is
     * laminar (proportional to dp) near dp = 0: no infinite gain there. */
    double re = 2.0 * opening_m * v_ideal / oil->viscosity_m2_s;
    double cd = cd_max * dct_smooth_sign(2.0 * re, transition_reynolds);
    /* eq. 13 with the density ratio at the mean pressure (eq. 12) */
    double pm = 0.5 * (p1_pa + p2_pa);
    double q = cd * area * v_ideal * (1.0 + pm / oil->bulk_modulus_pa);
    return dp >= 0.0 ? q : -q;
}

double dct_pressure_map_eval(const dct_pressure_map *m, double current_a)
{
    return dct_interp1(m->current_a, m->pressure_bar, m->n, current_a);
}

void dct_valve_init(const dct_valve_params *p, dct_valve_state *s)
{
    s->solenoid_force_n = 0.0;
    /* at rest with no current the spring holds the spool on its tank-side stop */
    s->spool_position_m = -p->spool_travel_mm * 1e-3;
    s->spool_velocity_m_s = 0.0;
    s->friction_velocity_m_s = 0.0;
}

void dct_valve_output_eval(const dct_valve_params *p, const dct_oil_params *oil,
                           const dct_valve_state *s, const dct_valve_input *in,
                           dct_valve_output *out)
{
    double ds = p->spool_diameter_mm * 1e-3, dr = p->rod_diameter_mm * 1e-3;
    double a_fb = 0.25 * DCT_PI * (ds * ds - dr * dr);
    double x = s->spool_position_m, v = s->spool_velocity_m_s, vf = s->friction_velocity_m_s;
    double travel = p->spool_travel_mm * 1e-3, lap = p->overlap_mm * 1e-3;
    double pc = in->control_pa;

    /* forces on the spool, + towards opening the supply edge */
    double f = s->solenoid_force_n - pc * a_fb - (p->spring_preload_n + p->spring_n_per_m * x);
    f -= p->viscous_friction_ns_per_m * vf + p->coulomb_friction_n * dct_smooth_sign(vf, p->friction_speed_m_s);
    if (x > travel)
        f -= p->stop_stiffness_n_per_m * (x - travel) + p->stop_damping_ns_per_m * v;
    else if (x < -travel)
        f += p->stop_stiffness_n_per_m * (-travel - x) - p->stop_damping_ns_per_m * v;
    out->spool_accel_m_s2 = f / p->spool_mass_kg;
    out->friction_accel_m_s2 = (v - vf) / p->friction_tau_s;
    out->solenoid_force_rate_n_s =
        (p->solenoid_gain_n_per_a * fabs(in->current_a) - s->solenoid_force_n) / p->solenoid_tau_s;

    /* metering edges and leakage */
    double w = p->edge_width_mm * 1e-3;
    double q_in = dct_orifice_flow(oil, p->cd_max, p->transition_reynolds, w, x - lap, in->supply_pa, pc);
    double q_out = dct_orifice_flow(oil, p->cd_max, p->transition_reynolds, w, -x - lap, pc, 0.0);
    q_in += p->leakage_m3_per_s_per_pa * (in->supply_pa - pc);
    q_out += p->leakage_m3_per_s_per_pa * pc;
    out->supply_flow_m3_s = q_in;
    out->tank_flow_m3_s = q_out;
    /* eq. 14: the spool moving towards the supply side shrinks the feedback
     * chamber, which is open to the clutch port */
    out->flow_m3_s = q_in - q_out + v * a_fb * (1.0 + pc / oil->bulk_modulus_pa);
}

void dct_valve_advance(const dct_valve_params *p, dct_valve_state *s,
                       const dct_valve_output *out, double h)
{
    (void)p;
    s->spool_position_m += h * s->spool_velocity_m_s;
    s->spool_velocity_m_s += h * out->spool_accel_m_s2;
    s->friction_velocity_m_s += h * out->friction_accel_m_s2;
    s->solenoid_force_n += h * out->solenoid_force_rate_n_s;
}
