/*
 * synchronizer.c - the hybrid three-phase synchronizer of the reference
 * paper (eqs. 1-6), driven by a fork force through a sleeve travel state.
 *
 *   disengaged     no torque (eq. 2); the sleeve moves under the fork force
 *                  against its damping and the neutral detent
 *   synchronizing  the sleeve rests on the cone (blocked); the cone torque
 *                  T_s = mu r_s / sin(alpha) F (eq. 6) acts through a tanh
 *                  friction law T = T_s tanh(2 w_r / w_0) (eq. 3); the
 *                  angular deformation follows theta_r = T / k
 *   engaged        the blocker has released (slip below the lock speed, or
 *                  the cone holding a settled load below the chamfers'
 *                  index torque: cone_holds_load): the
 *                  gear is locked through the dog teeth, a spring-damper of
 *                  the shaft and gear stiffness, T = k theta_r + b w_r (eq. 4),
 *                  theta_r carried over from the synchronizing phase; the
 *                  sleeve travels on to full engagement; dog-tooth friction
 *                  (mu_d |T| / r_d) holds a loaded gear in; until the
 *                  sleeve has passed the blocker ring (ring_pass_travel_mm
 *                  beyond the cone travel) it turns the ring back out of its
 *                  way, and with it, through the still stuck cone, the gear
 *                  side: an axial travel dx turns them by dx tan(beta) / r_b,
 *                  so the sleeve, pushing in, also moves the gear side's
 *                  inertia J as a mass J tan^2(beta) / r_b^2 (J from the
 *                  assembly: dct_sync_input.gear_inertia_*_kgm2); after a
 *                  clash too, where the slipping cone would pass on less
 *                  (a simplification: clashes are rare and counted)
 *
 * A fork force above the blocker's strength pushes the sleeve through before
 * the speeds match: an engagement with a slip above the clash speed is
 * counted as a clash.
 * A jammed sleeve (fault, dct_sync_input.fork_jammed) stays where it is in
 * every phase: on the cone it cannot pass the blocker, engaged it cannot be
 * pulled out; its phase, twist and torques evolve as they would.
 * Sign: w_r = gear speed - shaft speed; the torque acts + on the shaft.
 */
#include "dct_plant.h"
#include "dct_util.h"

#define DETENT_TRAVEL_M 0.0002 /* the detent force is reached 0.2 mm from neutral */

double dct_sync_cone_torque(const dct_sync_params *p, double force_n)
{
    return p->cone_mu * p->cone_radius_m / sin(p->cone_half_angle_deg * (DCT_PI / 180.0)) * force_n;
}

void dct_sync_init(const dct_sync_params *p, dct_sync_state *s, int side_engaged)
{
    s->velocity_m_s = 0.0;
    s->twist_rad = 0.0;
    s->clashes = 0.0;
    if (side_engaged != 0) {
        double side = side_engaged > 0 ? 1.0 : -1.0;
        s->phase = DCT_SYNC_ENGAGED;
        s->side = side;
        s->position_m = side * p->engaged_travel_mm * 1e-3;
    } else {
        s->phase = DCT_SYNC_DISENGAGED;
        s->side = 0.0;
        s->position_m = 0.0;
    }
}

void dct_sync_output_eval(const dct_sync_params *p, const dct_sync_state *s,
                          const dct_sync_input *in, dct_sync_output *out)
{
    double side = s->side;
    double slip = side > 0.0 ? in->slip_pos_rad_s : (side < 0.0 ? in->slip_neg_rad_s : 0.0);
    out->side = side;
    out->slip_rad_s = slip;
    out->cone_torque_nm = 0.0;
    if (s->phase == DCT_SYNC_SYNCHRONIZING) {
        double f = in->fork_force_n * side;
        double ts = dct_sync_cone_torque(p, f > 0.0 ? f : 0.0);
        out->cone_torque_nm = ts;
        out->torque_nm = ts * tanh(2.0 * slip / p->tanh_speed_rad_s);
    } else if (s->phase == DCT_SYNC_ENGAGED) {
        out->torque_nm = p->stiffness_nm_per_rad * s->twist_rad + p->damping_nms_per_rad * slip;
    } else {
        out->torque_nm = 0.0;
    }
}

/* velocity after a step under force f, damping, and a Coulomb friction
 * force of magnitude fc applied as an impulse that can stop but not reverse
 * the motion */
static double sleeve_velocity(const dct_sync_params *p, double m, double v, double f, double fc,
                              double h)
{
    double v1 = v + h * (f - p->sleeve_damping_ns_per_m * v) / m;
    double dv = h * fc / m;
    if (fabs(v1) <= dv)
        return 0.0;
    return v1 - dct_sign(v1) * dv;
}

/* The cone holds a load the blocker ring can be indexed against: the slip
 * has settled (the cone torque holds a drag on the gear side rather than
 * slowing its inertia: |J dw/dt| at most SETTLED_SHARE of it) and that torque
 * is below the index torque the fork force gives on the ring's chamfers,
 * F r_d / tan(beta). A real cone holding a load below its capacity sticks
 * (Coulomb friction) and the chamfers then turn the ring and gear back; the
 * tanh law of eq. 3 lets the cone creep instead, at the slip where
 * T_s tanh(2 w / w_0) equals the load, above the lock speed once the load
 * exceeds T_s tanh(2 lock / w_0) (0.38 T_s): by the lock speed alone a cold
 * open clutch's drag would hold the blocker shut for ever. Frictionless
 * chamfers. The previous step's slip comes from its torque (twist_rad = T / k,
 * eq. 3) at this step's fork force. */
#define SETTLED_SHARE 0.1 /* a slip settled to within a tenth of the cone torque: no inertial sync slows this little */

static int cone_holds_load(const dct_sync_params *p, const dct_sync_state *s,
                           const dct_sync_input *in, const dct_sync_output *out, double h)
{
    double ts = out->cone_torque_nm;
    double t = out->torque_nm;
    double t_prev = s->twist_rad * p->stiffness_nm_per_rad;
    if (!(ts > 0.0) || t_prev == 0.0 || !(fabs(t_prev) < ts))
        return 0; /* the first step on the cone, or the fork force dropped */
    double index = fabs(in->fork_force_n) * p->dog_radius_m /
                   tan(p->ring_chamfer_angle_deg * (DCT_PI / 180.0));
    if (!(fabs(t) < index))
        return 0;
    double slip_prev = 0.5 * p->tanh_speed_rad_s * atanh(t_prev / ts);
    double j = s->side > 0.0 ? in->gear_inertia_pos_kgm2 : in->gear_inertia_neg_kgm2;
    return fabs(j * (out->slip_rad_s - slip_prev) / h) <= SETTLED_SHARE * fabs(t);
}

static void engage(const dct_sync_params *p, dct_sync_state *s, const dct_sync_output *out)
{
    if (fabs(out->slip_rad_s) > p->clash_speed_rad_s)
        s->clashes += 1.0;
    s->phase = DCT_SYNC_ENGAGED;
    s->twist_rad = out->torque_nm / p->stiffness_nm_per_rad; /* eq. 3 carried over */
}

void dct_sync_advance(const dct_sync_params *p, dct_sync_state *s,
                      const dct_sync_input *in, const dct_sync_output *out, double h)
{
    double f = in->fork_force_n;
    double cone = p->cone_travel_mm * 1e-3;
    double full = p->engaged_travel_mm * 1e-3;
    double x = s->position_m, v = s->velocity_m_s;

    if (s->phase == DCT_SYNC_SYNCHRONIZING) {
        double side = s->side;
        if (f * side <= 0.0) {
            /* force released or reversed: the sleeve leaves the cone */
            s->phase = DCT_SYNC_DISENGAGED;
            s->side = 0.0;
            s->twist_rad = 0.0;
        } else if (!(in->fork_jammed > 0.5) && (fabs(out->slip_rad_s) <= p->lock_speed_rad_s ||
                                                 fabs(f) > p->blocker_force_max_n ||
                                                 cone_holds_load(p, s, in, out, h))) {
            /* (a jammed sleeve cannot move through the blocker) */
            engage(p, s, out);
        } else {
            s->twist_rad = out->torque_nm / p->stiffness_nm_per_rad; /* eq. 3 */
        }
        return; /* blocked on the cone this step */
    }

    if (s->phase == DCT_SYNC_ENGAGED) {
        double side = s->side;
        /* eq. 4: the deformation integrates the slip */
        s->twist_rad += h * out->slip_rad_s;
        double fdog = p->dog_friction_mu * fabs(out->torque_nm) / p->dog_radius_m;
        double m = p->sleeve_mass_kg;
        /* ring turn-back: while the sleeve pushes in (moving in, or at rest
         * with the fork pushing it in) and has not yet passed the ring */
        if (x * side < cone + p->ring_pass_travel_mm * 1e-3 &&
            (v * side > 0.0 || (v == 0.0 && f * side > 0.0))) {
            double j = side > 0.0 ? in->gear_inertia_pos_kgm2 : in->gear_inertia_neg_kgm2;
            double tb = tan(p->ring_chamfer_angle_deg * (DCT_PI / 180.0)) / p->dog_radius_m;
            m += j * tb * tb;
        }
        double v1 = sleeve_velocity(p, m, v, f, fdog, h);
        double x1 = x + h * v;
        if (x1 * side >= full) {
            x1 = side * full;
            if (v1 * side > 0.0)
                v1 = 0.0;
        }
        if (in->fork_jammed > 0.5) {
            x1 = x; /* jammed (fault): held, and so held in gear */
            v1 = 0.0;
        }
        s->position_m = x1;
        s->velocity_m_s = v1;
        if (x1 * side < cone) {
            /* pulled out of the dog teeth */
            s->phase = DCT_SYNC_DISENGAGED;
            s->side = 0.0;
            s->twist_rad = 0.0;
        }
        return;
    }

    /* disengaged: free sleeve with the neutral detent */
    double detent = -dct_clamp(x / DETENT_TRAVEL_M, -1.0, 1.0) * p->detent_force_n;
    double v1 = sleeve_velocity(p, p->sleeve_mass_kg, v, f + detent, 0.0, h);
    double x1 = x + h * v;
    if (!(in->has_neg > 0.5) && x1 < 0.0) {
        /* 6-N sleeve: nothing on the negative side, neutral is its end stop */
        x1 = 0.0;
        if (v1 < 0.0)
            v1 = 0.0;
    }
    if (in->fork_jammed > 0.5) {
        x1 = x; /* jammed (fault): held, whatever the fork force */
        v1 = 0.0;
    }
    s->position_m = x1;
    s->velocity_m_s = v1;
    if (fabs(x1) >= cone) {
        double side = x1 > 0.0 ? 1.0 : -1.0;
        s->position_m = side * cone;
        if (v1 * side > 0.0)
            s->velocity_m_s = 0.0; /* stopped by the cone; a sleeve pulled back keeps moving */
        if (f * side > 0.0) {
            s->phase = DCT_SYNC_SYNCHRONIZING;
            s->side = side;
            s->twist_rad = 0.0;
        }
    }
}
