/*
 * faults.c - physical faults of the car (failure simulation): the one place
 * the plant reads dct_plant.faults.
 *
 * Parametric faults become the parameters the step runs on (dct_plant_prepare
 * builds dct_plant.effective from params):
 *   friction_loss       clutch k's mu_static and mu_kinetic times (1 - loss):
 *                       lining fade, the same clamp force gives less capacity
 *   pack_gap_offset_mm  added to clutch k's pack gap: the kiss point drifts,
 *                       the piston strokes further (and the pressure rises
 *                       by offset x return spring rate / area) before the
 *                       pack clamps
 *   line_pressure_loss  the line pressure map's pressures times (1 - loss):
 *                       the supply target falls and the line pressure decays
 *                       to it behind the regulator's own lag
 *   blocker_failed      sleeve k's blocker_force_max_n = 0: any fork force
 *                       pushes the sleeve through at its first step on the
 *                       cone, whatever the slip (the blocker releases only at
 *                       the lock speed otherwise); above the clash speed the
 *                       engagement counts as a clash
 *   engine_torque_limited  the full-load curve capped at engine_torque_max_nm:
 *                       the pedal's and the TCU request's demand are both
 *                       limited to full load - drag (engine.c), so the brake
 *                       torque never exceeds the cap
 * The others act on the step's component inputs:
 *   solenoid_open       valve k's applied current 0 A (the output shows it,
 *                       as a current measurement would)
 *   spool_stuck         valve k's spool held where it is (hydraulics.c)
 *   fork_jammed         sleeve k held where it is (synchronizer.c)
 * Only nonzero faults touch a parameter, so with all faults zero effective is
 * params byte for byte and the step is the healthy car's, bit for bit.
 */
#include <stddef.h>
#include <string.h>

#include "dct_plant.h"
#include "dct_util.h"

#define FAULT_INDEX(field) ((int)(offsetof(dct_faults, field) / sizeof(double)))

static int on(double flag) { return flag > 0.5; }

/* 0..1, NaN refused */
static int in_unit(double x) { return x >= 0.0 && x <= 1.0; }

int dct_faults_check(const dct_faults *f, const dct_params *p, int *bad_index)
{
    int bad = -1;
    for (int k = 0; k < 2 && bad < 0; k++) {
        if (!in_unit(f->spool_stuck[k]))
            bad = FAULT_INDEX(spool_stuck) + k;
        else if (!in_unit(f->solenoid_open[k]))
            bad = FAULT_INDEX(solenoid_open) + k;
        else if (!in_unit(f->friction_loss[k]))
            bad = FAULT_INDEX(friction_loss) + k;
        /* the gap may close to nothing (a piston touching the pack at rest),
         * never below: the pack would clamp with no pressure */
        else if (!isfinite(f->pack_gap_offset_mm[k]) ||
                 !(p->clutch[k].pack_gap_mm + f->pack_gap_offset_mm[k] >= 0.0))
            bad = FAULT_INDEX(pack_gap_offset_mm) + k;
    }
    if (bad < 0 && !in_unit(f->line_pressure_loss))
        bad = FAULT_INDEX(line_pressure_loss);
    for (int k = 0; k < DCT_N_SLEEVES && bad < 0; k++) {
        if (!in_unit(f->fork_jammed[k]))
            bad = FAULT_INDEX(fork_jammed) + k;
        else if (!in_unit(f->blocker_failed[k]))
            bad = FAULT_INDEX(blocker_failed) + k;
    }
    if (bad < 0 && !in_unit(f->engine_torque_limited))
        bad = FAULT_INDEX(engine_torque_limited);
    if (bad < 0 && !(f->engine_torque_max_nm >= 0.0 && isfinite(f->engine_torque_max_nm)))
        bad = FAULT_INDEX(engine_torque_max_nm);
    if (bad < 0)
        return DCT_OK;
    if (bad_index)
        *bad_index = bad;
    return DCT_ERR_PARAM;
}

static void apply_params(const dct_faults *f, dct_params *e)
{
    for (int k = 0; k < 2; k++) {
        dct_clutch_params *c = &e->clutch[k];
        if (f->friction_loss[k] != 0.0) {
            c->mu_static *= 1.0 - f->friction_loss[k];
            c->mu_kinetic *= 1.0 - f->friction_loss[k];
        }
        if (f->pack_gap_offset_mm[k] != 0.0)
            c->pack_gap_mm += f->pack_gap_offset_mm[k];
    }
    if (f->line_pressure_loss != 0.0) {
        dct_pressure_map *m = &e->hydraulics.supply.line;
        for (int i = 0; i < m->n && i < DCT_CURVE_MAX; i++)
            m->pressure_bar[i] *= 1.0 - f->line_pressure_loss;
    }
    for (int k = 0; k < DCT_N_SLEEVES; k++)
        if (on(f->blocker_failed[k]))
            e->gearbox.sync[k].blocker_force_max_n = 0.0;
    if (on(f->engine_torque_limited)) {
        dct_torque_curve *c = &e->engine.full_load;
        for (int i = 0; i < c->n && i < DCT_CURVE_MAX; i++)
            if (c->torque_nm[i] > f->engine_torque_max_nm)
                c->torque_nm[i] = f->engine_torque_max_nm;
    }
}

int dct_faults_prepare(const dct_faults *faults, const dct_params *params, dct_params *effective,
                       dct_faults *in_effect, int *bad_index)
{
    int st = dct_faults_check(faults, params, bad_index);
    if (st != DCT_OK)
        return st;
    memcpy(effective, params, sizeof *effective);
    apply_params(faults, effective);
    memcpy(in_effect, faults, sizeof *in_effect);
    return DCT_OK;
}

void dct_faults_apply_inputs(const dct_faults *f, dct_inputs *applied)
{
    if (on(f->solenoid_open[0]))
        applied->solenoid_current1_a = 0.0;
    if (on(f->solenoid_open[1]))
        applied->solenoid_current2_a = 0.0;
}

void dct_faults_apply_couplings(const dct_faults *f, dct_hydraulics_input *hydraulics_in,
                                dct_gearbox_input *gearbox_in)
{
    for (int k = 0; k < 2; k++)
        hydraulics_in->spool_stuck[k] = on(f->spool_stuck[k]) ? 1.0 : 0.0;
    for (int k = 0; k < DCT_N_SLEEVES; k++)
        gearbox_in->fork_jammed[k] = on(f->fork_jammed[k]) ? 1.0 : 0.0;
}
