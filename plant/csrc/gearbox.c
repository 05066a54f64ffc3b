/*
 * gearbox.c - the DSG 02E gear train: two input shafts (K1: gears 1 3 5 R;
 * K2: gears 2 4 6), two output shafts (1: gears 1-4, final drive 4.118;
 * 2: gears 5 6 R, final drive 3.043) whose pinions drive the same ring gear,
 * four synchronizer sleeves (1-3 and 2-4 on output shaft 1, 5-R and 6-N on
 * output shaft 2).
 *
 * Degrees of freedom: the two input shaft speeds (fixed gears, and the loose
 * gears that always mesh with them, reduced to the shaft) and the
 * differential carrier speed (output shafts reduced through their final
 * drives; shaft and gear stiffness sit in the synchronizers, as in the paper).
 *
 * Each gear path: the synchronizer torque T acts on the output shaft; the
 * input shaft gives T f / i, where the efficiency factor f of the gear mesh
 * and final drive always opposes the power flow: 1/eta when the input drives
 * (T w_gear > 0), eta when the output drives (coasting), blended smoothly
 * through zero power, so the mesh loss T w_gear (f - 1) is never negative.
 * Losses: constant and viscous drag of the input shafts and at the
 * differential (bearings, churning), viscous drag of each loose gear on its
 * needle bearing (relative speed).
 */
#include "dct_plant.h"
#include "dct_util.h"

/* layout tables, index = gear (0..5 = 1st..6th, 6 = R) */
static const int GEAR_INPUT[DCT_N_GEARS] = {0, 1, 0, 1, 0, 1, 0};
static const int GEAR_OUTPUT[DCT_N_GEARS] = {0, 0, 0, 0, 1, 1, 1};
static const int GEAR_SLEEVE[DCT_N_GEARS] = {0, 1, 0, 1, 2, 3, 2};
static const int GEAR_SIDE[DCT_N_GEARS] = {1, 1, -1, -1, 1, 1, -1};
static const int SLEEVE_POS[DCT_N_SLEEVES] = {0, 1, 4, 5};   /* 1, 2, 5, 6 */
static const int SLEEVE_NEG[DCT_N_SLEEVES] = {2, 3, 6, -1};  /* 3, 4, R, neutral */
static const int SLEEVE_OUTPUT[DCT_N_SLEEVES] = {0, 0, 1, 1};

int dct_gear_input_shaft(int gear) { return (gear >= 0 && gear < DCT_N_GEARS) ? GEAR_INPUT[gear] : -1; }
int dct_gear_output_shaft(int gear) { return (gear >= 0 && gear < DCT_N_GEARS) ? GEAR_OUTPUT[gear] : -1; }
int dct_gear_sleeve(int gear) { return (gear >= 0 && gear < DCT_N_GEARS) ? GEAR_SLEEVE[gear] : -1; }
int dct_gear_side(int gear) { return (gear >= 0 && gear < DCT_N_GEARS) ? GEAR_SIDE[gear] : 0; }

int dct_sleeve_gear(int sleeve, int side)
{
    if (sleeve < 0 || sleeve >= DCT_N_SLEEVES || side == 0)
        return -1;
    return side > 0 ? SLEEVE_POS[sleeve] : SLEEVE_NEG[sleeve];
}

/* the gear side a synchronizer turns, at gear g: the input shaft that drives
 * g (shaft, clutch hub, fixed gears and the loose gears meshing with them;
 * its clutch open) reflected through g's ratio. It includes the loose gear
 * g itself. */
static double gear_side_inertia(const dct_gearbox_params *p, const dct_gearbox_derived *d, int g)
{
    return d->input_inertia_kgm2[GEAR_INPUT[g]] * dct_sq(p->ratio[g]);
}

void dct_gearbox_prepare(const dct_gearbox_params *p, dct_gearbox_derived *d)
{
    for (int k = 0; k < 2; k++)
        d->input_inertia_kgm2[k] = p->input_shaft_inertia_kgm2[k];
    for (int g = 0; g < DCT_N_GEARS; g++) {
        d->signed_ratio[g] = g == DCT_GEAR_R ? -p->ratio[g] : p->ratio[g];
        d->input_inertia_kgm2[GEAR_INPUT[g]] += p->idle_gear_inertia_kgm2[g] / dct_sq(p->ratio[g]);
    }
    for (int g = 0; g < DCT_N_GEARS; g++)
        d->gear_side_inertia_kgm2[g] = gear_side_inertia(p, d, g);
    d->carrier_inertia_kgm2 = p->differential_inertia_kgm2;
    for (int o = 0; o < 2; o++)
        d->carrier_inertia_kgm2 += p->output_shaft_inertia_kgm2[o] * dct_sq(p->final_drive[o]);
}

static double efficiency_factor(double eta, double power_w, double scale_w)
{
    double t = dct_smooth_sign(power_w, scale_w);
    if (t > 0.0)
        return 1.0 + (1.0 / eta - 1.0) * t;
    return 1.0 + (1.0 - eta) * t;
}

static double drag(double c0, double c1, double w, double smooth)
{
    return c0 * dct_smooth_sign(w, smooth) + c1 * w;
}

void dct_gearbox_output_eval(const dct_gearbox_params *p, const dct_gearbox_derived *d,
                             const dct_gearbox_state *s, const dct_gearbox_input *in,
                             dct_gearbox_output *out)
{
    double w_gear[DCT_N_GEARS];
    double w_out[2];
    double t_in[2], t_car, loss = 0.0;
    double visc = 1.0 + in->viscous_drag_excess; /* thermal: oil viscosity */
    for (int o = 0; o < 2; o++)
        w_out[o] = s->carrier_speed_rad_s * p->final_drive[o];
    for (int g = 0; g < DCT_N_GEARS; g++) {
        w_gear[g] = s->input_speed_rad_s[GEAR_INPUT[g]] / d->signed_ratio[g];
        out->gear_torque_nm[g] = 0.0;
    }
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        dct_sync_input *si = &out->sync_in[k];
        double wo = w_out[SLEEVE_OUTPUT[k]];
        si->fork_force_n = in->fork_force_n[k];
        si->fork_jammed = in->fork_jammed[k];
        si->slip_pos_rad_s = w_gear[SLEEVE_POS[k]] - wo;
        si->has_neg = SLEEVE_NEG[k] >= 0 ? 1.0 : 0.0;
        si->slip_neg_rad_s = SLEEVE_NEG[k] >= 0 ? w_gear[SLEEVE_NEG[k]] - wo : 0.0;
        si->gear_inertia_pos_kgm2 = d->gear_side_inertia_kgm2[SLEEVE_POS[k]];
        si->gear_inertia_neg_kgm2 = SLEEVE_NEG[k] >= 0 ? d->gear_side_inertia_kgm2[SLEEVE_NEG[k]] : 0.0;
        dct_sync_output_eval(&p->sync[k], &s->sync[k], si, &out->sync[k]);
        int g = dct_sleeve_gear(k, (int)out->sync[k].side);
        if (g >= 0)
            out->gear_torque_nm[g] += out->sync[k].torque_nm;
    }
    /* a tie-up: two gears engaged on one input shaft lock it to the
     * output at two ratios (a faulty TCU, bad frames). The synchronizers'
     * dampers then act on the light shaft and the carrier from several
     * sides at once, too stiff for the explicit 0.5 ms step: the tied
     * shafts and the carrier take their dampers (a stuck clutch's, each
     * engaged synchronizer's b: b / ratio^2 on the input shaft, b final
     * drive^2 on the carrier) implicitly (dct_gearbox_advance). Without a
     * tie-up (every gearbox state a TCU uses) none: explicit Euler. */
    int engaged[2] = {0, 0};
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        int g = dct_sleeve_gear(k, (int)out->sync[k].side);
        if (g >= 0 && s->sync[k].phase == DCT_SYNC_ENGAGED)
            engaged[GEAR_INPUT[g]] += 1;
    }
    double c_car = 0.0, c_in[2] = {0.0, 0.0};
    if (engaged[0] > 1 || engaged[1] > 1) {
        for (int k = 0; k < DCT_N_SLEEVES; k++) {
            int g = dct_sleeve_gear(k, (int)out->sync[k].side);
            if (g < 0 || s->sync[k].phase != DCT_SYNC_ENGAGED)
                continue;
            double b = p->sync[k].damping_nms_per_rad;
            c_in[GEAR_INPUT[g]] += b / dct_sq(p->ratio[g]);
            c_car += b * dct_sq(p->final_drive[GEAR_OUTPUT[g]]);
        }
        for (int k = 0; k < 2; k++)
            c_in[k] = engaged[k] > 1 ? c_in[k] + in->clutch_damping_nms_per_rad[k] : 0.0;
    }
    out->input_damping_nms_per_rad[0] = c_in[0];
    out->input_damping_nms_per_rad[1] = c_in[1];
    out->carrier_damping_nms_per_rad = c_car;
    for (int k = 0; k < 2; k++) {
        double w = s->input_speed_rad_s[k];
        double t = drag(p->input_drag_nm[k], p->input_drag_nms_per_rad[k] * visc, w, p->drag_smoothing_rad_s);
        loss += t * w;
        t_in[k] = in->clutch_torque_nm[k] - t;
    }
    {
        double w = s->carrier_speed_rad_s;
        double t = drag(p->output_drag_nm, p->output_drag_nms_per_rad * visc, w, p->drag_smoothing_rad_s);
        loss += t * w;
        t_car = -t - in->load_torque_nm;
    }
    for (int g = 0; g < DCT_N_GEARS; g++) {
        int o = GEAR_OUTPUT[g];
        double tg = out->gear_torque_nm[g];
        double rel = w_gear[g] - w_out[o];
        double tig = p->idle_gear_drag_nms_per_rad * visc * rel; /* loose gear bearing */
        double f = tg != 0.0 ? efficiency_factor(p->mesh_efficiency[g], tg * w_gear[g],
                                                 p->efficiency_smoothing_w)
                             : 1.0;
        loss += tg * w_gear[g] * (f - 1.0) + tig * rel;
        t_in[GEAR_INPUT[g]] -= (tg * f + tig) / d->signed_ratio[g];
        t_car += (tg + tig) * p->final_drive[o];
        out->gear_torque_nm[g] = tg + tig;
    }
    out->input_torque_nm[0] = t_in[0];
    out->input_torque_nm[1] = t_in[1];
    out->carrier_torque_nm = t_car;
    out->output_speed_rad_s[0] = w_out[0];
    out->output_speed_rad_s[1] = w_out[1];
    out->power_loss_w = loss;
}

void dct_gearbox_advance(const dct_gearbox_params *p, const dct_gearbox_derived *d,
                         dct_gearbox_state *s, const dct_gearbox_input *in,
                         const dct_gearbox_output *out, double h)
{
    (void)in;
    /* linearly implicit in a shaft's own dampers in a tie-up (the shaft's
     * inertia plus h x its dampers; dct_gearbox_output_eval), explicit
     * Euler otherwise (the dampers are 0 then) */
    for (int k = 0; k < 2; k++)
        s->input_speed_rad_s[k] +=
            h * out->input_torque_nm[k] / (d->input_inertia_kgm2[k] + h * out->input_damping_nms_per_rad[k]);
    s->carrier_speed_rad_s +=
        h * out->carrier_torque_nm / (d->carrier_inertia_kgm2 + h * out->carrier_damping_nms_per_rad);
    for (int k = 0; k < DCT_N_SLEEVES; k++)
        dct_sync_advance(&p->sync[k], &s->sync[k], &out->sync_in[k], &out->sync[k], h);
}
