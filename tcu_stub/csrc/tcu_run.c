/*
 * tcu_run.c - the closed loop of plant, driver, contract link and TCU
 * (offline.run_offline), many TCU periods in one call.
 *
 * Each TCU period k, in run_offline's order: scenario rows due and, every
 * tcu_per_driver periods, the driver's pedals (and the selector lever of a
 * table with one) into the plant inputs (then the
 * outputs recomputed, so the pedals are in them); the TCU's view through the
 * link; its step; its commands due through the link into the inputs; a row
 * recorded every tcu_per_record periods; the plant steps one TCU period.
 */
#define _POSIX_C_SOURCE 199309L   /* clock_gettime */
#include <stddef.h>
#include <string.h>
#include <time.h>

#include "tcu_fast.h"

#define TRACE_WIDTH (1 + TCU_N_SENSORS + TCU_N_COMMANDS)

static int record(tcu_run *r, double t)
{
    if (r->rec == NULL)
        return DCT_OK;
    if (r->rec_n >= r->rec_cap)
        return TCU_RUN_ERR_RECORD;
    int width = 1 + r->n_rec_outputs + TCU_RUN_N_TCU_COLUMNS;
    double *row = r->rec + r->rec_n * width;
    const double *out = (const double *)&r->plant->outputs;
    row[0] = t;
    for (int i = 0; i < r->n_rec_outputs; i++)
        row[1 + i] = out[r->rec_outputs[i]];
    double *tcu = row + 1 + r->n_rec_outputs;
    tcu[0] = r->tcu->target_gear;
    tcu[1] = r->tcu->gear;
    tcu[2] = r->tcu->phase;
    tcu[3] = r->tcu->diag.active_bits;
    tcu[4] = r->tcu->diag.limp_home ? 1 : 0;
    tcu[5] = r->tcu->kiss_bar[0];
    tcu[6] = r->tcu->kiss_bar[1];
    r->rec_n++;
    return DCT_OK;
}

void tcu_plant_layout(int64_t *out)
{
    out[0] = sizeof(dct_plant);
    out[1] = offsetof(dct_plant, state);
    out[2] = offsetof(dct_plant, inputs);
    out[3] = offsetof(dct_plant, outputs);
    out[4] = sizeof(dct_inputs);
    out[5] = sizeof(dct_outputs);
    out[6] = offsetof(dct_state, time_s);
    out[7] = offsetof(dct_inputs, accel_pedal_pct);
    out[8] = offsetof(dct_inputs, brake_pedal_pct);
    out[9] = offsetof(dct_outputs, vehicle_speed_kmh);
    out[10] = offsetof(dct_outputs, engine_speed_rpm);
}

void tcu_run_inputs(tcu_run *r)
{
    dct_plant *p = r->plant;
    double *inputs = (double *)&p->inputs;
    int64_t k = r->k;
    int changed = 0;
    while (r->row < r->n_rows && r->row_t[r->row] <= k * r->tick_s + 1e-9) {
        const double *v = r->row_values + (int64_t)r->row * r->n_row_columns;
        for (int c = 0; c < r->n_row_columns; c++)
            inputs[r->row_inputs[c]] = v[c];
        r->row++;
        changed = 1;
    }
    if (r->driver->kind != TCU_DRIVER_EXTERNAL && k % r->tcu_per_driver == 0) {
        double accel, brake;
        tcu_driver_pedals(r->driver, p->state.time_s - r->t0_s, &p->outputs, &accel, &brake);
        p->inputs.accel_pedal_pct = accel;
        p->inputs.brake_pedal_pct = brake;
        double selector = tcu_driver_selector(r->driver, p->state.time_s - r->t0_s);
        if (selector >= 0.0)
            p->inputs.selector_lever = selector;
        changed = 1;
    }
    if (changed)
        r->plant_update_outputs(p);
}

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

int tcu_run_periods(tcu_run *r, int64_t n)
{
    double t_start = r->time_split ? now_s() : 0.0;
    dct_plant *p = r->plant;
    double *inputs = (double *)&p->inputs;
    const double *outputs = (const double *)&p->outputs;
    for (int64_t i = 0; i < n; i++) {
        int64_t k = r->k;
        double t = p->state.time_s - r->t0_s;
        tcu_run_inputs(r);
        int status;
        if (r->record_before_tcu && k % r->tcu_per_record == 0 && (status = record(r, t)) != DCT_OK)
            return status;
        tcu_link_sensors(r->link, outputs, k, r->sensors);
        tcu_step(r->cal, r->tcu, t, r->sensors, r->commands);
        tcu_link_apply(r->link, r->commands, k, inputs);
        if (r->trace != NULL && r->trace_n < r->trace_cap) {
            double *row = r->trace + r->trace_n * TRACE_WIDTH;
            row[0] = t;
            memcpy(row + 1, r->sensors, sizeof r->sensors);
            memcpy(row + 1 + TCU_N_SENSORS, r->commands, sizeof r->commands);
            r->trace_n++;
        }
        if (!r->record_before_tcu && k % r->tcu_per_record == 0 && (status = record(r, t)) != DCT_OK)
            return status;
        if (r->time_split) {
            double t1 = now_s();
            status = r->plant_step(p, r->steps_per_tcu);
            double t2 = now_s();
            r->other_s += t1 - t_start;
            r->plant_s += t2 - t1;
            t_start = t2;
        } else {
            status = r->plant_step(p, r->steps_per_tcu);
        }
        r->k = k + 1;
        if (status != DCT_OK)
            return status;
    }
    return DCT_OK;
}
