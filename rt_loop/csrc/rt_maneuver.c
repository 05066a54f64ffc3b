/*
 * rt_maneuver.c - the scripted driver and the maneuver commands that start
 * and stop it while the loop runs (contract: rt_loop.h).
 *
 * Scripted driver (l->driver, optional): a pedal table over maneuver time,
 * with an optional selector lever column and a road grade set once (at
 * prepare and when a maneuver starts), played in the tick before the plant
 * step. Maneuver time 0 is the first
 * tick (start_on_tcu = 0) or the first tick after the first accepted TCU
 * frame (start_on_tcu = 1: the plant idles on the first row's pedals until
 * the TCU is there). Maneuver time is plant time since the start, so a run
 * with skipped deadlines still plays the table against simulated time. At
 * end_s the loop stops as if its duration ended (RT_MANEUVER_DONE).
 */
#include <string.h>

#include "rt_internal.h"

/* rows within 1..RT_DRIVER_ROWS (or 0), times finite and strictly
 * increasing, pedals within 0..100 %, selector codes P..D, the grade within
 * -40..40 %, end_s finite */
int rt_driver_check(const rt_driver *d)
{
    if (d->rows == 0)
        return 0;
    if (d->rows < 0 || d->rows > RT_DRIVER_ROWS || !isfinite(d->end_s))
        return -1;
    if (d->has_grade && !(d->road_grade_pct >= -40.0 && d->road_grade_pct <= 40.0))
        return -1;
    for (int i = 0; i < d->rows; i++) {
        if (!isfinite(d->t_s[i]) || (i > 0 && !(d->t_s[i] > d->t_s[i - 1])))
            return -1;
        if (!(d->accel_pedal_pct[i] >= 0.0 && d->accel_pedal_pct[i] <= 100.0) ||
            !(d->brake_pedal_pct[i] >= 0.0 && d->brake_pedal_pct[i] <= 100.0))
            return -1;
        double sel = d->selector_lever[i];
        if (d->has_selector && !(sel == DCT_SELECTOR_P || sel == DCT_SELECTOR_R ||
                                 sel == DCT_SELECTOR_N || sel == DCT_SELECTOR_D))
            return -1;
    }
    return 0;
}

/* the maneuver's inputs before it plays (at prepare, waiting for the TCU) and as
 * it starts: the first row's selector and the road grade */
void rt_driver_fixed_inputs(rt_loop *l, const rt_driver *d)
{
    if (d->has_selector)
        l->plant.inputs.selector_lever = d->selector_lever[0];
    if (d->has_grade)
        l->plant.inputs.road_grade_pct = d->road_grade_pct;
}

void rt_maneuver_publish(rt_loop *l, uint32_t seq)
{
    atomic_store_explicit(A32(&l->maneuver_seq), seq, RELEASE);
}

uint32_t rt_maneuver_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->maneuver_ack), ACQUIRE);
}

/* the plant at rest as it starts (rt_loop.h RT_MCMD_RESET_PLANT): its time
 * and inputs kept */
static int reset_plant(dct_plant *pl)
{
    double t = pl->state.time_s;
    dct_inputs inputs = pl->inputs;
    dct_initial init;
    memset(&init, 0, sizeof init);
    init.engine_on = 1.0;
    int st = dct_plant_reset(pl, &init);
    pl->inputs = inputs;
    pl->state.time_s = t;
    dct_plant_update_outputs(pl);
    return st;
}

/* a maneuver command published since the last tick (rt_loop.h): a start
 * plays the new table from this tick, a stop ends the maneuver playing */
static void maneuver_command(rt_run *r, uint32_t seq)
{
    rt_loop *l = r->l;
    r->maneuver_seq = seq;
    uint32_t op = l->maneuver_op;
    if (op == RT_MCMD_START && l->maneuver_next.rows > 0 && rt_driver_check(&l->maneuver_next) == 0) {
        l->driver = l->maneuver_next;
        rt_driver_fixed_inputs(l, &l->driver);
        r->maneuver_state = RT_MANEUVER_RUNNING;
        r->maneuver_t0_s = l->plant.state.time_s;
        r->maneuver_time_s = 0.0;
    } else if (op == RT_MCMD_STOP) {
        if (r->maneuver_state == RT_MANEUVER_RUNNING || r->maneuver_state == RT_MANEUVER_WAITING) {
            r->maneuver_state = RT_MANEUVER_DONE;
            l->plant.inputs.accel_pedal_pct = 0.0;
        }
    } else if (op == RT_MCMD_RESET_PLANT && reset_plant(&l->plant) == DCT_OK) {
        /* done: the plant at rest, its time going on */
    } else {
        atomic_store_explicit(A32(&l->maneuver_refused),
                              atomic_load_explicit(A32(&l->maneuver_refused), RELAXED) + 1u,
                              RELAXED);
    }
    atomic_store_explicit(A32(&l->maneuver_ack), seq, RELEASE);
}

/* the scripted driver: starts the maneuver when due, writes the pedals of
 * the maneuver time of this tick (the plant time before its step) */
RT_TICK_CODE
void rt_drive(rt_run *r)
{
    rt_loop *l = r->l;
    const rt_driver *d = &l->driver;
    uint32_t seq = atomic_load_explicit(A32(&l->maneuver_seq), ACQUIRE);
    if (seq != r->maneuver_seq)
        maneuver_command(r, seq);
    if (r->maneuver_state == RT_MANEUVER_NONE || r->maneuver_state == RT_MANEUVER_DONE)
        return;
    if (r->maneuver_state == RT_MANEUVER_WAITING) {
        if (d->start_on_tcu && !r->tcu_heard)
            return;
        r->maneuver_state = RT_MANEUVER_RUNNING;
        r->maneuver_t0_s = l->plant.state.time_s;
        r->maneuver_time_s = 0.0;
    }
    double t = l->plant.state.time_s - r->maneuver_t0_s;
    int k = 0; /* the last row at or before t (the first row before it) */
    while (k + 1 < d->rows && d->t_s[k + 1] <= t)
        k++;
    double accel = d->accel_pedal_pct[k], brake = d->brake_pedal_pct[k];
    if (d->linear && k + 1 < d->rows && t > d->t_s[k]) {
        double w = (t - d->t_s[k]) / (d->t_s[k + 1] - d->t_s[k]);
        accel += w * (d->accel_pedal_pct[k + 1] - accel);
        brake += w * (d->brake_pedal_pct[k + 1] - brake);
    }
    l->plant.inputs.accel_pedal_pct = accel;
    l->plant.inputs.brake_pedal_pct = brake;
    if (d->has_selector)
        l->plant.inputs.selector_lever = d->selector_lever[k];
}
