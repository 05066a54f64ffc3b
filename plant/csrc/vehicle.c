/*
 * vehicle.c - the car body in the vertical plane (reference paper, section
 * 4): longitudinal, vertical (heave) and pitch freedom of the sprung mass;
 * front and rear suspension as spring-dampers carrying spindle masses that
 * move vertically on the tyres' vertical stiffness; aerodynamic drag and road
 * grade. Load transfer is not prescribed: it comes out of the pitch and
 * heave motion on the springs.
 *
 * Frame: x along the road (forward), z normal to it (up), pitch + nose up.
 * Coordinates are measured from the static equilibrium on a level road, so
 * the spring preloads are the static loads.
 *   m dv/dt         = F_xf + F_xr - F_aero - m g sin(grade)
 *   m_s d2z/dt2     = F_sf + F_sr - m_s g cos(grade)
 *   I d2theta/dt2   = a F_sf - b F_sr + (F_xf + F_xr)(h - R) + T_wf + T_wr
 * T_w are the torques the wheels take from the body side (drive shafts,
 * brakes): their reactions act on the body, so with F_x at the wheel centres
 * the pitch moment in steady state is (F_xf + F_xr) h: the classic transfer
 * m a h / L. Small pitch angles.
 */
#include "dct_plant.h"
#include "dct_util.h"

double dct_vehicle_static_front_n(const dct_vehicle_params *p)
{
    double ms = p->mass_kg - p->front_unsprung_kg - p->rear_unsprung_kg;
    double b = p->wheelbase_m - p->cg_to_front_axle_m;
    return ms * p->gravity_m_s2 * b / p->wheelbase_m + p->front_unsprung_kg * p->gravity_m_s2;
}

double dct_vehicle_static_rear_n(const dct_vehicle_params *p)
{
    double ms = p->mass_kg - p->front_unsprung_kg - p->rear_unsprung_kg;
    return ms * p->gravity_m_s2 * p->cg_to_front_axle_m / p->wheelbase_m +
           p->rear_unsprung_kg * p->gravity_m_s2;
}

static double sprung_mass(const dct_vehicle_params *p)
{
    return p->mass_kg - p->front_unsprung_kg - p->rear_unsprung_kg;
}

/* spring preloads: the static loads of the sprung mass on a level road */
static void spring_preloads(const dct_vehicle_params *p, double *front, double *rear)
{
    double ms = sprung_mass(p), l = p->wheelbase_m, a = p->cg_to_front_axle_m;
    *front = ms * p->gravity_m_s2 * (l - a) / l;
    *rear = ms * p->gravity_m_s2 * a / l;
}

static void suspension_forces(const dct_vehicle_params *p, const dct_vehicle_state *s,
                              double *front, double *rear)
{
    double a = p->cg_to_front_axle_m, b = p->wheelbase_m - a;
    double pf, pr;
    spring_preloads(p, &pf, &pr);
    double zf = s->heave_m + a * s->pitch_rad, vf = s->heave_rate_m_s + a * s->pitch_rate_rad_s;
    double zr = s->heave_m - b * s->pitch_rad, vr = s->heave_rate_m_s - b * s->pitch_rate_rad_s;
    *front = pf + p->front_spring_n_per_m * (s->front_spindle_m - zf) +
             p->front_damper_ns_per_m * (s->front_spindle_rate_m_s - vf);
    *rear = pr + p->rear_spring_n_per_m * (s->rear_spindle_m - zr) +
            p->rear_damper_ns_per_m * (s->rear_spindle_rate_m_s - vr);
}

void dct_vehicle_tyre_loads(const dct_vehicle_params *p, const dct_vehicle_state *s,
                            double road_grade_pct, double *front_n, double *rear_n)
{
    (void)road_grade_pct; /* the preloads are those of a level road; the spindle
                             position carries the rest */
    double f = dct_vehicle_static_front_n(p) - p->front_tyre_vertical_n_per_m * s->front_spindle_m -
               p->tyre_vertical_damping_ns_per_m * s->front_spindle_rate_m_s;
    double r = dct_vehicle_static_rear_n(p) - p->rear_tyre_vertical_n_per_m * s->rear_spindle_m -
               p->tyre_vertical_damping_ns_per_m * s->rear_spindle_rate_m_s;
    *front_n = f > 0.0 ? f : 0.0; /* a tyre can push, not pull */
    *rear_n = r > 0.0 ? r : 0.0;
}

void dct_vehicle_init(const dct_vehicle_params *p, dct_vehicle_state *s, double speed_m_s)
{
    (void)p;
    s->position_m = 0.0;
    s->speed_m_s = speed_m_s;
    s->heave_m = 0.0;
    s->heave_rate_m_s = 0.0;
    s->pitch_rad = 0.0;
    s->pitch_rate_rad_s = 0.0;
    s->front_spindle_m = 0.0;
    s->front_spindle_rate_m_s = 0.0;
    s->rear_spindle_m = 0.0;
    s->rear_spindle_rate_m_s = 0.0;
}

void dct_vehicle_output_eval(const dct_vehicle_params *p, const dct_vehicle_state *s,
                             const dct_vehicle_input *in, dct_vehicle_output *out)
{
    double a = p->cg_to_front_axle_m, b = p->wheelbase_m - a;
    /* grade = tan(angle): cos and sin without trigonometric calls */
    double slope = 0.01 * in->road_grade_pct;
    double cos_a = 1.0 / sqrt(1.0 + slope * slope);
    double gn = p->gravity_m_s2 * cos_a;
    double ms = sprung_mass(p);
    double fsf, fsr, ftf, ftr;
    suspension_forces(p, s, &fsf, &fsr);
    dct_vehicle_tyre_loads(p, s, in->road_grade_pct, &ftf, &ftr);
    double fx = in->front_tyre_force_n + in->rear_tyre_force_n;
    out->heave_accel_m_s2 = (fsf + fsr - ms * gn) / ms;
    out->pitch_accel_rad_s2 = (a * fsf - b * fsr + fx * (p->cg_height_m - p->wheel_centre_height_m) +
                  in->front_wheel_torque_nm + in->rear_wheel_torque_nm) /
                 p->pitch_inertia_kgm2;
    out->front_spindle_accel_m_s2 = (ftf - fsf - p->front_unsprung_kg * gn) / p->front_unsprung_kg;
    out->rear_spindle_accel_m_s2 = (ftr - fsr - p->rear_unsprung_kg * gn) / p->rear_unsprung_kg;
    out->front_normal_force_n = ftf;
    out->rear_normal_force_n = ftr;
    out->front_suspension_force_n = fsf;
    out->rear_suspension_force_n = fsr;
    double v = s->speed_m_s;
    out->aero_force_n = 0.5 * p->air_density_kg_m3 * p->drag_coefficient * p->frontal_area_m2 * v * fabs(v);
    out->accel_m_s2 = (in->front_tyre_force_n + in->rear_tyre_force_n - out->aero_force_n -
                       p->mass_kg * p->gravity_m_s2 * slope * cos_a) /
                      p->mass_kg;
}

void dct_vehicle_advance(const dct_vehicle_params *p, dct_vehicle_state *s,
                         const dct_vehicle_input *in, const dct_vehicle_output *out, double h)
{
    (void)p;
    (void)in;
    s->position_m += h * s->speed_m_s;
    s->speed_m_s += h * out->accel_m_s2;
    s->heave_m += h * s->heave_rate_m_s;
    s->heave_rate_m_s += h * out->heave_accel_m_s2;
    s->pitch_rad += h * s->pitch_rate_rad_s;
    s->pitch_rate_rad_s += h * out->pitch_accel_rad_s2;
    s->front_spindle_m += h * s->front_spindle_rate_m_s;
    s->front_spindle_rate_m_s += h * out->front_spindle_accel_m_s2;
    s->rear_spindle_m += h * s->rear_spindle_rate_m_s;
    s->rear_spindle_rate_m_s += h * out->rear_spindle_accel_m_s2;
}

double dct_vehicle_energy(const dct_vehicle_params *p, const dct_vehicle_state *s,
                          double road_grade_pct)
{
    double a = p->cg_to_front_axle_m, b = p->wheelbase_m - a;
    double grade = atan(0.01 * road_grade_pct);
    double gn = p->gravity_m_s2 * cos(grade), gt = p->gravity_m_s2 * sin(grade);
    double ms = sprung_mass(p), mf = p->front_unsprung_kg, mr = p->rear_unsprung_kg;
    double pf, pr;
    spring_preloads(p, &pf, &pr);
    double kinetic = 0.5 * p->mass_kg * dct_sq(s->speed_m_s) + 0.5 * ms * dct_sq(s->heave_rate_m_s) +
                     0.5 * p->pitch_inertia_kgm2 * dct_sq(s->pitch_rate_rad_s) +
                     0.5 * mf * dct_sq(s->front_spindle_rate_m_s) +
                     0.5 * mr * dct_sq(s->rear_spindle_rate_m_s);
    double df = s->front_spindle_m - (s->heave_m + a * s->pitch_rad);
    double dr = s->rear_spindle_m - (s->heave_m - b * s->pitch_rad);
    double springs = pf * df + 0.5 * p->front_spring_n_per_m * df * df + pr * dr +
                     0.5 * p->rear_spring_n_per_m * dr * dr;
    /* tyre springs (force static - k z while in contact) */
    double tf = 0.0, tr = 0.0;
    double ptf = dct_vehicle_static_front_n(p), ptr = dct_vehicle_static_rear_n(p);
    double zf = s->front_spindle_m, zr = s->rear_spindle_m;
    double kf = p->front_tyre_vertical_n_per_m, kr = p->rear_tyre_vertical_n_per_m;
    double zf_lift = ptf / kf, zr_lift = ptr / kr;
    tf = zf < zf_lift ? -ptf * zf + 0.5 * kf * zf * zf : -ptf * zf_lift + 0.5 * kf * zf_lift * zf_lift;
    tr = zr < zr_lift ? -ptr * zr + 0.5 * kr * zr * zr : -ptr * zr_lift + 0.5 * kr * zr_lift * zr_lift;
    double gravity = ms * gn * s->heave_m + mf * gn * zf + mr * gn * zr + p->mass_kg * gt * s->position_m;
    return kinetic + springs + tf + tr + gravity;
}
