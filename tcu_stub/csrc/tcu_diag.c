/*
 * tcu_diag.c - the reference TCU's on-board diagnostics (diagnostics.py):
 * debounced monitors, trouble code bits, latched reactions.
 *
 * The signal monitors (input shaft speeds, clutch and line pressures,
 * clutch slip, gear engagement) and the message monitors (the engine
 * message, the CAN ones: tcu_diag_node, what a CAN node gives the TCU). In
 * process no message is lost, so Diagnostics.messages reduces to its timing
 * there (tcu_diag_messages).
 */
#include "tcu_fast.h"
#include "tcu_util.h"

/* failing: 1 the condition holds, 0 it does not, -1 not evaluated (Python's None) */
#define NOT_EVALUATED -1

static void monitor_init(tcu_monitor *m, int bit, double set_s, double heal_s)
{
    m->bit = bit;
    m->set_s = set_s;
    m->heal_s = heal_s;
    m->fail_s = 0.0;
    m->pass_s = 0.0;
    m->active = 0;
}

/* Monitor.update: 1 in the period the monitor sets */
static int monitor_update(tcu_monitor *m, int failing, double dt)
{
    if (failing == NOT_EVALUATED)
        return 0;
    if (failing) {
        m->pass_s = 0.0;
        if (!m->active) {
            m->fail_s += dt;
            if (m->fail_s >= m->set_s - 1e-9) {
                m->active = 1;
                return 1;
            }
        }
        return 0;
    }
    if (m->fail_s > 0.0)
        m->fail_s = py_max(m->fail_s - dt, 0.0);
    if (m->active) {
        m->pass_s += dt;
        if (m->pass_s >= m->heal_s - 1e-9) {
            m->active = 0;
            m->fail_s = 0.0;
        }
    }
    return 0;
}

static const tcu_monitor *monitor_at(const tcu_diag *d, int i)
{
    const tcu_monitor *all[TCU_N_MONITORS] = {
        &d->speed_invalid[0], &d->speed_invalid[1], &d->speed_plausible[0], &d->speed_plausible[1],
        &d->pressure[0], &d->pressure[1], &d->line, &d->slip[0], &d->slip[1], &d->engage,
    };
    return all[i];
}

/* Diagnostics._recount: the bit follows its monitors (two share bits 0 and 1) */
static void recount(tcu_diag *d, int bit)
{
    int mask = 1 << bit;
    int now = 0;
    for (int i = 0; i < TCU_N_MONITORS; i++) {
        const tcu_monitor *m = monitor_at(d, i);
        if (m->bit == bit && m->active)
            now = 1;
    }
    if (d->engine.bit == bit && d->engine.active)
        now = 1;
    for (int i = 0; i < 4; i++)
        if (d->can[i].bit == bit && d->can[i].active)
            now = 1;
    int before = (d->active_bits & mask) != 0;
    if (now == before)
        return;
    if (now) {
        d->active_bits |= mask;
        d->stored_bits |= mask;
        d->fault_count += 1;
        d->last_fault = bit + 1;
    } else {
        d->active_bits &= ~mask;
    }
    if (d->n_events >= TCU_MAX_DIAG_EVENTS) {
        d->events_lost++;
        return;
    }
    tcu_diag_event *e = &d->events[d->n_events++];
    e->t_s = d->t_s;
    e->bit = bit;
    e->set = now;
}

/* Diagnostics._update: debounce one monitor, keep the bits; 1 when it set */
static int update(tcu_diag *d, tcu_monitor *m, int failing)
{
    if (failing != 1 && !m->active && m->fail_s == 0.0)
        return 0;                 /* healthy and idle, or not evaluated: nothing to count */
    int was = m->active;
    int set = monitor_update(m, failing, d->dt);
    if (m->active != was)
        recount(d, m->bit);
    return set;
}

void tcu_diag_reset(const tcu_cal *cal, tcu_diag *d)
{
    for (int s = 0; s < 2; s++) {
        monitor_init(&d->speed_invalid[s], TCU_DTC_INPUT_SPEED1 + s, cal->speed_invalid_set_s,
                     cal->heal_s);
        monitor_init(&d->speed_plausible[s], TCU_DTC_INPUT_SPEED1 + s,
                     cal->speed_implausible_set_s, cal->heal_s);
        monitor_init(&d->pressure[s], TCU_DTC_CLUTCH1_PRESSURE + s, cal->pressure_set_s, cal->heal_s);
        monitor_init(&d->slip[s], TCU_DTC_CLUTCH1_SLIP + s, cal->slip_set_s, cal->heal_s);
        d->boost[s] = 0;
        d->engage_gear[s] = 0;
        d->engage_wait_s[s] = 0.0;
        d->release_s[s] = 0.0;
        d->slip_limp_s[s] = 0.0;
    }
    monitor_init(&d->line, TCU_DTC_LINE_PRESSURE, cal->line_set_s, cal->heal_s);
    monitor_init(&d->engage, TCU_DTC_GEAR_ENGAGEMENT, 0.0, cal->heal_s);
    monitor_init(&d->engine, TCU_DTC_ENGINE_MESSAGE, 0.0, cal->heal_s);
    for (int i = 0; i < 4; i++)
        monitor_init(&d->can[i], TCU_DTC_CAN_CRC + i, 0.0, cal->heal_s);
    d->can_busy = 0;
    d->stale = 0;
    d->engine_lost = 0;
    d->torque_ok = 1;
    d->active_bits = 0;
    d->stored_bits = 0;
    d->fault_count = 0;
    d->last_fault = 0;
    d->inhibited = 0;
    d->blocked_shafts = 0;
    d->limp_home = 0;
    d->safe_state = 0;
    d->plant_seen = 0;
    d->plant_seen_t_s = 0.0;
    d->have_t_prev = 0;
    d->t_prev = 0.0;
    d->dt = 0.0;
    d->engage_failed = 0;
    d->t_s = 0.0;
    d->n_events = 0;
    d->events_lost = 0;
}

/* Diagnostics.messages with every plant message received: the period's
   time step and the first period with the plant's frames */
void tcu_diag_messages(const tcu_cal *cal, tcu_diag *d, double t_s)
{
    double dt = !d->have_t_prev ? cal->period_first_s
                                : py_min(py_max(t_s - d->t_prev, 0.0), cal->max_dt_s);
    d->t_prev = t_s;
    d->have_t_prev = 1;
    d->dt = dt;
    d->t_s = t_s;
    if (!d->plant_seen) {
        d->plant_seen = 1;
        d->plant_seen_t_s = t_s;
    }
}

/* a stale message's cause -> its DTC bit (diagnostics._CAUSE_DTC) */
static int cause_dtc(int cause)
{
    switch (cause) {
    case TCU_MSG_BAD_COUNTER: return TCU_DTC_CAN_COUNTER;
    case TCU_MSG_BAD_LENGTH: return TCU_DTC_CAN_LENGTH;
    case TCU_MSG_BAD_CRC:
    case TCU_MSG_REJECTED: return TCU_DTC_CAN_CRC;
    default: return TCU_DTC_CAN_TIMEOUT;
    }
}

int tcu_diag_node(const tcu_cal *cal, tcu_diag *d, double t_s, const tcu_msgs *msgs)
{
    double dt = !d->have_t_prev ? cal->period_first_s
                                : py_min(py_max(t_s - d->t_prev, 0.0), cal->max_dt_s);
    d->t_prev = t_s;
    d->have_t_prev = 1;
    d->dt = dt;
    d->t_s = t_s;
    int seen = d->plant_seen;
    int late = seen && t_s - d->plant_seen_t_s >= cal->startup_s - 1e-9;
    int kinds = 0, engine = 0, engine_fault = 0, stale = 0;
    for (int i = 0; i < msgs->n; i++) {
        int why = msgs->cause[i];
        if (why == TCU_MSG_OK)
            continue;
        int counts = why != TCU_MSG_MISSING || late;
        if (msgs->engine[i]) {
            engine = 1;
            engine_fault = engine_fault || counts;
        } else {
            stale = 1;
        }
        if (counts)
            kinds |= 1 << cause_dtc(why);
    }
    if (!stale && !seen) {
        d->plant_seen = seen = 1;
        d->plant_seen_t_s = t_s;
    }
    d->stale = stale;
    d->engine_lost = engine;
    if (kinds || d->can_busy) {
        int busy = 0;
        for (int i = 0; i < 4; i++) {
            update(d, &d->can[i], (kinds >> d->can[i].bit) & 1);
            busy = busy || d->can[i].active || d->can[i].fail_s > 0.0;
        }
        d->can_busy = busy;
    }
    update(d, &d->engine, seen ? engine_fault : NOT_EVALUATED);
    d->torque_ok = !engine && !d->engine.active;
    return stale;
}

static void block(tcu_diag *d, int shaft)
{
    static const int shaft_gears_mask[2] = {0x15, 0x2A};   /* gears 1 3 5 / 2 4 6 */
    d->blocked_shafts |= 1 << shaft;
    d->inhibited |= shaft_gears_mask[shaft];
}

/* limp home on the other half: this half avoided, the other half's gears
   below its limp gear too */
static void limp(const tcu_cal *cal, tcu_diag *d, int shaft)
{
    block(d, shaft);
    if (!d->limp_home) {
        d->limp_home = 1;
        int healthy = 1 - shaft;
        for (int g = 1; g < cal->limp_gear[healthy]; g++)
            if (TCU_GEAR_SHAFT[tcu_gi(g)] == healthy)
                d->inhibited |= 1 << (g - 1);
    }
}

/* Diagnostics.monitor: the signal monitors on what the logic read this period
   and commanded last period, then the reactions */
void tcu_diag_monitor(const tcu_cal *cal, tcu_state *s)
{
    tcu_diag *d = &s->diag;
    double dt = d->dt;
    /* line pressure first: the clutch pressures mean nothing without it (the
       contract always carries LinePressure) */
    update(d, &d->line, s->line_absent ? NOT_EVALUATED : !(s->line_bar >= cal->line_low_bar));
    int line_low = d->line.active || d->line.fail_s > 0.0;
    int speed_bad[2] = {0, 0};
    for (int sh = 0; sh < 2; sh++) {
        double n = s->n_shaft_raw[sh];
        int invalid = !isfinite(n) || fabs(n) > cal->speed_invalid_rpm;
        update(d, &d->speed_invalid[sh], invalid);
        int g = s->engaged_gear[sh];
        int plausible_fail = NOT_EVALUATED;
        if (!invalid && g) {
            double expect = tcu_gear_input_rpm(cal, s, g);
            plausible_fail = fabs(n - expect) >
                             py_max(cal->speed_tolerance_rpm, cal->speed_tolerance_share * fabs(expect));
        }
        update(d, &d->speed_plausible[sh], plausible_fail);
        speed_bad[sh] = invalid || plausible_fail == 1 || d->speed_invalid[sh].active ||
                        d->speed_plausible[sh].active;
        /* clutch pressure against the target of the last period */
        double p = s->p_meas[sh];
        double target = s->loops[sh].target_bar;
        int fail;
        if (!isfinite(p) || p > cal->pressure_invalid_bar)
            fail = 1;
        else if (line_low)
            fail = NOT_EVALUATED;
        else
            fail = fabs(p - target) >
                   py_max(cal->pressure_tolerance_bar, cal->pressure_tolerance_share * target);
        update(d, &d->pressure[sh], fail);
        /* slip of the clutch commanded closed */
        int slip_fail = NOT_EVALUATED;
        if (s->phase == TCU_DRIVE && TCU_GEAR_SHAFT[tcu_gi(s->gear)] == sh && !speed_bad[sh] &&
            s->pressure_bar[sh] >= cal->clutch_lock_bar - 1e-9 && fail == 0)
            slip_fail = fabs(s->n_engine - n) > cal->slip_rpm;
        if (update(d, &d->slip[sh], slip_fail))
            d->boost[sh] = 1;
        if (slip_fail == 1 && d->boost[sh] && d->slip[sh].active) {
            d->slip_limp_s[sh] += dt;
            if (d->slip_limp_s[sh] >= cal->slip_limp_s - 1e-9)
                limp(cal, d, sh);
        } else if (slip_fail == 0) {
            d->slip_limp_s[sh] = 0.0;
        }
        /* gear engagement: the gear asked for on this shaft (not counted while
           its sleeves are let go for a retry) */
        int want = tcu_requested_gear(s, sh);
        if (want != d->engage_gear[sh]) {
            d->engage_gear[sh] = want;
            d->engage_wait_s[sh] = 0.0;
        }
        if (d->release_s[sh] > 0.0) {
            d->release_s[sh] = py_max(d->release_s[sh] - dt, 0.0);
            d->engage_wait_s[sh] = 0.0;
        } else if (want > 0 && want != g) {       /* R is not monitored */
            d->engage_wait_s[sh] += dt;
        } else {
            d->engage_wait_s[sh] = 0.0;
            if (want > 0)
                d->engage_failed &= ~(1 << (want - 1));   /* engaged: a retry again next time */
        }
    }
    int engage_fail = 0;
    for (int sh = 0; sh < 2; sh++) {
        if (d->engage_wait_s[sh] >= cal->engage_set_s - 1e-9) {
            engage_fail = 1;
            int bit = 1 << (d->engage_gear[sh] - 1);
            if (d->engage_failed & bit) {
                d->inhibited |= bit;                       /* the retry failed too */
            } else {
                d->engage_failed |= bit;                   /* let the sleeves go, then once more */
                d->release_s[sh] = cal->engage_release_s;
            }
            d->engage_wait_s[sh] = 0.0;
        }
    }
    update(d, &d->engage, engage_fail);
    /* reactions */
    for (int sh = 0; sh < 2; sh++) {
        if (d->speed_invalid[sh].active || d->speed_plausible[sh].active)
            block(d, sh);
        if (d->pressure[sh].active)
            limp(cal, d, sh);
    }
    if (d->line.active) {
        d->safe_state = 1;
        d->limp_home = 1;
    }
    if ((d->inhibited & 0x3F) == 0x3F)
        d->safe_state = 1;
}

/* Diagnostics.state: TcuState 0 initialising, 1 normal, 2 substitute, 3 limp home, 4 fault */
int tcu_diag_state(const tcu_diag *d, int phase)
{
    if (!d->plant_seen)
        return 0;
    if (d->safe_state || phase == TCU_STALE)
        return 4;
    if (d->limp_home)
        return 3;
    if (d->active_bits || d->inhibited || !d->torque_ok)
        return 2;
    return 1;
}
