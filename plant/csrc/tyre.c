/*
 * tyre.c - longitudinal tyre force: Pacejka magic formula (pure slip, with
 * load dependency of peak friction, curvature and slip stiffness) applied to
 * a transient slip from a carcass deflection state (relaxation length), and
 * a spring-damper contact near standstill.
 *
 *   du/dt = (w R - V) - (1 - fade(V)) V_ref u / sigma,  V_ref = max(|V|, |w R|)
 *   kappa = u / sigma,  F = n MF(kappa, Fz / n) + n c_low fade(V) (w R - V)
 *
 * Rolling: in steady state kappa is the slip (w R - V) / V_ref (V_ref uses
 * the larger of the two speeds so the slip stays bounded when a wheel spins).
 * Near standstill (fade(V) -> 1 below low_speed_limit) the relaxation term
 * fades out and the contact becomes a spring of stiffness K_kappa / sigma
 * with the low-speed damping: the car stands on its tyres without creeping
 * and without ringing. That spring holds only what friction can: its
 * deflection is limited to the peak-force slip of the magic formula (beyond
 * it the contact patch slides), the limit widening as the speed rises and
 * the relaxation takes over.
 * The carcass damps its deflection: + n c_c du/dt (Kelvin-Voigt carcass).
 * Rolling resistance is a moment c_rr Fz R opposing the rotation, c_rr rising
 * with the speed.
 * n tyres lumped in one position (the rear axle) each carry Fz / n.
 */
#include "dct_plant.h"
#include "dct_util.h"

void dct_tyre_load_eval(const dct_tyre_params *p, double fz, dct_tyre_load *l)
{
    l->fz = fz;
    if (fz <= 0.0)
        return;
    double dfz = (fz - p->nominal_load_n) / p->nominal_load_n;
    double c = p->pcx1;
    double mu = p->pdx1 + p->pdx2 * dfz;
    double d = mu * fz;
    double e = p->pex1 + p->pex2 * dfz;
    if (e > 1.0)
        e = 1.0;
    double k = fz * (p->pkx1 + p->pkx2 * dfz) * exp(p->pkx3 * dfz);
    l->c = c;
    l->d = d;
    l->e = e;
    l->b = k / (c * d);
}

double dct_magic_formula_at(const dct_tyre_load *l, double slip)
{
    if (l->fz <= 0.0)
        return 0.0;
    double bx = l->b * slip;
    return l->d * sin(l->c * atan(bx - l->e * (bx - atan(bx))));
}

double dct_magic_formula(const dct_tyre_params *p, double slip, double fz)
{
    dct_tyre_load l;
    dct_tyre_load_eval(p, fz, &l);
    return dct_magic_formula_at(&l, slip);
}

/* slip of the force peak: D sin(C atan(x - E (x - atan x))) peaks where
 * x - E (x - atan x) = tan(pi / (2 C)), x = B kappa (Newton, from x = rhs) */
double dct_magic_formula_peak_slip(const dct_tyre_params *p, double fz)
{
    double c = p->pcx1;
    if (c <= 1.0 || fz <= 0.0)
        return 1e9; /* no peak: the force rises monotonically */
    double dfz = (fz - p->nominal_load_n) / p->nominal_load_n;
    double d = (p->pdx1 + p->pdx2 * dfz) * fz;
    double e = p->pex1 + p->pex2 * dfz;
    if (e > 1.0)
        e = 1.0;
    double k = fz * (p->pkx1 + p->pkx2 * dfz) * exp(p->pkx3 * dfz);
    double b = k / (c * d);
    double rhs = tan(DCT_PI / (2.0 * c));
    double x = rhs;
    for (int i = 0; i < 6; i++) {
        double g = x * (1.0 - e) + e * atan(x) - rhs;
        double dg = (1.0 - e) + e / (1.0 + x * x);
        x -= g / dg;
    }
    return x / b;
}

void dct_tyre_init(const dct_tyre_params *p, dct_tyre_state *s)
{
    (void)p;
    s->deflection_m = 0.0;
}

void dct_tyre_output_eval(const dct_tyre_params *p, const dct_tyre_state *s,
                          const dct_tyre_input *in, dct_tyre_output *out)
{
    double fz = in->normal_force_n > 0.0 ? in->normal_force_n : 0.0;
    dct_tyre_load load;
    dct_tyre_load_eval(p, fz / in->count, &load);
    dct_tyre_output_eval_at(p, s, in, &load, out);
}

void dct_tyre_output_eval_at(const dct_tyre_params *p, const dct_tyre_state *s,
                             const dct_tyre_input *in, const dct_tyre_load *load, dct_tyre_output *out)
{
    double n = in->count;
    double v = in->ground_speed_m_s;
    double wr = in->wheel_speed_rad_s * p->radius_m;
    double slip_speed = wr - v;
    double vref = fabs(v) > fabs(wr) ? fabs(v) : fabs(wr);
    double kappa = s->deflection_m / p->relaxation_length_m;
    double fz = in->normal_force_n > 0.0 ? in->normal_force_n : 0.0;
    double f = n * dct_magic_formula_at(load, kappa);
    double w = dct_fade(v, p->low_speed_limit_m_s);
    f += n * p->low_speed_damping_ns_per_m * w * slip_speed;
    out->force_n = f;
    out->slip = kappa;
    out->slip_speed_m_s = slip_speed;
    out->deflection_rate_m_s = slip_speed - (1.0 - w) * vref * s->deflection_m / p->relaxation_length_m;
    /* the carcass's own damping (rubber hysteresis), in parallel with its
     * spring: without it the deflection is an undamped spring at low speed,
     * where the relaxation (V / sigma) no longer damps the driveline's modes */
    f += n * p->carcass_damping_ns_per_m * out->deflection_rate_m_s;
    out->force_n = f;
    out->contact_weight = w;
    out->tyre_load_n = fz / n;
    /* the carcass's hysteresis loss per metre grows with speed (standing
     * waves at the end): f = f0 + fs (V / V_ref)^2.5 (Gillespie, Fundamentals
     * of Vehicle Dynamics, eq. 4-3) */
    double x = fabs(v) / p->rolling_resistance_ref_speed_m_s;
    double f_rr = p->rolling_resistance + p->rolling_resistance_speed * x * x * sqrt(x);
    out->rolling_moment_nm = f_rr * fz * p->radius_m *
                             dct_smooth_sign(in->wheel_speed_rad_s, p->rolling_smoothing_rad_s);
}

void dct_tyre_advance(const dct_tyre_params *p, dct_tyre_state *s,
                      const dct_tyre_output *out, double h)
{
    double u = s->deflection_m + h * out->deflection_rate_m_s;
    double w = out->contact_weight;
    /* friction limit of the spring contact: |u| <= sigma kappa_peak / w.
     * No tyre peaks below 2 % slip, so the Newton solve for the peak is
     * only needed beyond that (launching, braking to a stop). */
    if (w > 0.0 && fabs(u) * w > 0.02 * p->relaxation_length_m) {
        double lim = p->relaxation_length_m * dct_magic_formula_peak_slip(p, out->tyre_load_n) / w;
        u = dct_clamp(u, -lim, lim);
    }
    s->deflection_m = u;
}

double dct_tyre_deflection_energy(const dct_tyre_params *p, double deflection_m,
                                  double normal_force_n, double count)
{
    /* integral of the magic formula force over the deflection, 4-point
     * Gauss-Legendre on [0, u] */
    static const double x[4] = {-0.8611363115940526, -0.3399810435848563, 0.3399810435848563,
                                0.8611363115940526};
    static const double w[4] = {0.3478548451374538, 0.6521451548625461, 0.6521451548625461,
                                0.3478548451374538};
    double u = deflection_m, sum = 0.0;
    for (int i = 0; i < 4; i++) {
        double ui = 0.5 * u * (x[i] + 1.0);
        sum += w[i] * dct_magic_formula(p, ui / p->relaxation_length_m, normal_force_n / count);
    }
    return count * 0.5 * u * sum;
}
