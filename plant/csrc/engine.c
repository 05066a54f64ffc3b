/*
 * engine.c - the engine as a torque source with lag (reference paper,
 * section 4): full-load and drag torque over speed from tables, the demanded
 * torque delivered through a first-order lag whose time constant differs for
 * rise and fall (and, turbocharged, is longer above the naturally aspirated
 * share: boost build-up); the rotating inertia of crank, flywheel and clutch
 * drum at the clutch input; an idle governor (PI on speed) in the engine's
 * own control; fuel flow from a BSFC map integrated to grams.
 *
 * Torque structure: brake torque = combustion torque (lagged, >= 0) + drag
 * torque (<= 0, instantaneous). The pedal asks for a share of the combustion
 * torque range [0, full load - drag], so pedal 0 gives drag, pedal 100 full
 * load. A TCU torque request, when active, replaces the pedal demand (the
 * idle governor keeps priority so that an intervention cannot stall it).
 * A request below the driver's torque is met as an engine control unit
 * does for a shift: spark retard cuts the torque (in and out within
 * tau_fall) while the air path, and so the boost, stays at the driver's
 * torque, as far as the retard can cut (spark_cut_max_share of the air-path
 * torque); the torque is back at once when the request ends, without a new
 * turbo lag. The retarded spark burns the air path's fuel. A request above
 * the driver's opens the air path (with its lags).
 *
 * Thermal effects (thermal.c) come in as inputs, all 0 for the warm engine:
 * the drag curve x (1 + drag_excess), the idle target + idle_rise_rpm, the
 * fuel x (1 + fuel_enrichment) (the extra fuel does not burn: no torque).
 * Accessories (alternator, power steering, A/C, the transmission's oil
 * pump) take accessory_torque_nm from the crank. The full-load curve is the
 * engine's rated brake torque, its own friction (the drag) in it: pedal 100 %
 * gives full load minus the accessories at the clutch; a torque request is
 * a brake torque at the clutch (the accessories covered, within full load);
 * the idle governor holds the idle speed against them.
 */
#include "dct_plant.h"
#include "dct_util.h"

double dct_curve_eval(const dct_torque_curve *c, double speed_rpm)
{
    return dct_interp1(c->speed_rpm, c->torque_nm, c->n, speed_rpm);
}

/* index i and fraction f so that x lies between axis[i] and axis[i+1] */
static void axis_locate(const double *axis, int n, double x, int *i, double *f)
{
    if (n < 2 || x <= axis[0]) {
        *i = 0;
        *f = 0.0;
        return;
    }
    if (x >= axis[n - 1]) {
        *i = n - 2;
        *f = 1.0;
        return;
    }
    int k = 0;
    while (k < n - 2 && x > axis[k + 1])
        k++;
    *i = k;
    *f = (x - axis[k]) / (axis[k + 1] - axis[k]);
}

double dct_bsfc_eval(const dct_bsfc_map *m, double speed_rpm, double torque_nm)
{
    int i, j;
    double fx, fy;
    if (m->n_speed_rpm < 1 || m->n_torque_nm < 1)
        return 0.0;
    if (m->n_speed_rpm < 2 || m->n_torque_nm < 2)
        return m->bsfc_g_per_kwh[0][0];
    axis_locate(m->speed_rpm, m->n_speed_rpm, speed_rpm, &i, &fx);
    axis_locate(m->torque_nm, m->n_torque_nm, torque_nm, &j, &fy);
    double a = m->bsfc_g_per_kwh[j][i] + fx * (m->bsfc_g_per_kwh[j][i + 1] - m->bsfc_g_per_kwh[j][i]);
    double b = m->bsfc_g_per_kwh[j + 1][i] +
               fx * (m->bsfc_g_per_kwh[j + 1][i + 1] - m->bsfc_g_per_kwh[j + 1][i]);
    return a + fy * (b - a);
}

static double drag_torque(const dct_engine_params *p, double speed_rad_s, double factor)
{
    double n = speed_rad_s * DCT_RPM_PER_RAD_S;
    /* the curve is given for forward rotation; the drag always opposes the
     * rotation and fades out at standstill */
    return factor * dct_curve_eval(&p->drag, fabs(n)) * dct_smooth_sign(speed_rad_s, p->drag_smoothing_rad_s);
}

void dct_engine_init(const dct_engine_params *p, dct_engine_state *s, double speed_rad_s, int running)
{
    s->speed_rad_s = speed_rad_s;
    s->fuel_g = 0.0;
    s->running = running ? 1.0 : 0.0;
    s->spark_cut_nm = 0.0;
    /* running: start with the combustion torque that holds this speed
     * unloaded, and the governor integrator holding idle */
    double hold = running ? -drag_torque(p, speed_rad_s, 1.0) : 0.0;
    s->combustion_torque_nm = hold;
    double idle_hold = -drag_torque(p, p->idle_speed_rpm * DCT_RAD_S_PER_RPM, 1.0);
    s->idle_integral_nm = running ? dct_clamp(idle_hold, 0.0, p->idle_torque_max_nm) : 0.0;
}

void dct_engine_output_eval(const dct_engine_params *p, const dct_engine_state *s,
                            const dct_engine_input *in, dct_engine_output *out)
{
    double w = s->speed_rad_s;
    double n = w * DCT_RPM_PER_RAD_S;
    double factor = 1.0 + in->drag_excess;
    double drag = drag_torque(p, w, factor);
    double acc = in->accessory_torque_nm * dct_smooth_sign(w, p->drag_smoothing_rad_s);
    double full = dct_curve_eval(&p->full_load, n);
    /* the full-load curve is the brake torque of the engine as rated (its
     * friction in it): the combustion torque can reach full load + the
     * drag; what the accessories take comes off the brake torque at the
     * clutch at full load, and the pedal spans that range */
    double drag_need = -factor * dct_curve_eval(&p->drag, fabs(n));
    double range = full + drag_need;
    if (range < 0.0)
        range = 0.0;
    double demand = 0.0, air = 0.0;
    int fired = s->running > 0.5 && in->engine_on > 0.5;
    if (fired) {
        double err = p->idle_speed_rpm + in->idle_rise_rpm - n;
        double gov = dct_clamp(p->idle_kp_nm_per_rpm * err + s->idle_integral_nm, 0.0,
                               p->idle_torque_max_nm);
        double driver = dct_clamp(0.01 * in->accel_pedal_pct * range + gov, 0.0, range);
        demand = air = driver;
        if (in->torque_request_active > 0.5) {
            /* a request is a brake torque at the clutch: accessories covered */
            double req = in->torque_request_nm + drag_need + in->accessory_torque_nm;
            demand = dct_clamp(req > gov ? req : gov, 0.0, range);
            /* the air path keeps the driver's torque as long as spark
             * retard can cut the rest; a request above it opens the air path */
            double keep = demand / (1.0 - p->spark_cut_max_share);
            air = driver < keep ? driver : keep;
            if (demand > air)
                air = demand;
        }
        if (n > p->rev_limit_rpm)
            demand = air = 0.0; /* fuel cut */
    }
    out->demand_nm = demand;
    out->air_demand_nm = air;
    out->drag_nm = drag;
    double comb = s->combustion_torque_nm - s->spark_cut_nm;
    out->combustion_torque_nm = comb;
    out->torque_nm = comb + drag - acc;
    out->accessory_torque_nm = acc;
    double fuel = 0.0;
    if (fired && demand > 0.0 && w > 0.0) {
        /* below the map's lowest torque row (idle, light load) the engine
         * still burns what that row needs: idle consumption. The work of
         * the accessories is the engine's work too. */
        /* spark retard wastes fuel: the air and fuel of the air-path torque burn */
        double t = out->torque_nm + acc + s->spark_cut_nm;
        if (t < p->bsfc.torque_nm[0])
            t = p->bsfc.torque_nm[0];
        fuel = dct_bsfc_eval(&p->bsfc, n, t) * t * w / 3.6e6;
    }
    out->burnt_fuel_rate_g_s = fuel;
    out->fuel_rate_g_s = fuel * (1.0 + in->fuel_enrichment);
    out->speed_deriv_rad_s2 = (out->torque_nm - in->load_torque_nm) / p->inertia_kgm2;
}

void dct_engine_advance(const dct_engine_params *p, dct_engine_state *s,
                        const dct_engine_input *in, const dct_engine_output *out, double h)
{
    double w = s->speed_rad_s;
    double n = w * DCT_RPM_PER_RAD_S;
    double comb = s->combustion_torque_nm;
    double target = out->air_demand_nm;
    double tau;
    if (target > comb) {
        tau = p->tau_rise_s;
        if (p->turbocharged > 0.5 &&
            comb > p->na_torque_fraction * dct_curve_eval(&p->full_load, n))
            tau = p->tau_boost_s;
    } else {
        tau = p->tau_fall_s;
    }
    /* exact discretisation of the lag would need exp(); h/tau <= 1 is
     * guaranteed by the parameter ranges, so Euler is monotone here */
    s->combustion_torque_nm = comb + (h / tau) * (target - comb);
    /* spark retard: while a TCU request holds the torque below the air
     * path's, it cuts the difference (up to its share), in and out within
     * tau_fall; without a request it goes back to 0 as fast */
    double cut = 0.0;
    if (in->torque_request_active > 0.5) {
        cut = dct_clamp(s->combustion_torque_nm - out->demand_nm, 0.0,
                        p->spark_cut_max_share * s->combustion_torque_nm);
    }
    s->spark_cut_nm += (h / p->tau_fall_s) * (cut - s->spark_cut_nm);
    s->speed_rad_s = w + h * out->speed_deriv_rad_s2;
    s->fuel_g += h * out->fuel_rate_g_s;

    int fired = s->running > 0.5 && in->engine_on > 0.5;
    if (fired) {
        /* governor integrator with clamping anti-windup */
        double err = p->idle_speed_rpm + in->idle_rise_rpm - n;
        double i_new = s->idle_integral_nm + h * p->idle_ki_nm_per_rpm_s * err;
        s->idle_integral_nm = dct_clamp(i_new, 0.0, p->idle_torque_max_nm);
    }
    if (s->running > 0.5 && n < p->stall_speed_rpm) {
        s->running = 0.0; /* stalled: stays off until the plant is reset */
        s->idle_integral_nm = 0.0;
    }
}
