/*
 * rt_faults.c - failure simulation inside the tick (contract: rt_loop.h,
 * "failure simulation"; the loop's side: rt_faults.h).
 *
 * Per tick (rtf_tick), with nothing armed: one acquire load of the command
 * ring's head. Otherwise:
 *   1. the queued commands (set, clear, clear all), each checked whole
 *      (kind, indices, condition) before it touches a slot: a bad one is
 *      refused and counted, the slot left as it was;
 *   2. armed slots whose start time has come and whose condition holds
 *      start; active slots whose duration is over end (plant time before
 *      this tick's step); each start and end is an event;
 *   3. when anything changed, the effects are computed again from the
 *      active slots alone (so overlapping faults add up and an ended one
 *      leaves nothing behind): the per-message flags of the send path, the
 *      list of signal faults, the buses the plant node is off, and the
 *      plant's dct_faults followed by dct_plant_prepare.
 * No allocation, no system call, no lock.
 */
#include "rt_faults.h"

#include <math.h>
#include <stdatomic.h>
#include <string.h>

#define A32(p) ((_Atomic uint32_t *)(void *)(p))
#define A64(p) ((_Atomic uint64_t *)(void *)(p))
#define RELAXED memory_order_relaxed
#define ACQUIRE memory_order_acquire
#define RELEASE memory_order_release

#define N_OUTPUTS ((uint32_t)(sizeof(dct_outputs) / sizeof(double)))
#define CMDS_PER_TICK 64              /* commands taken per tick at most; the rest waits */

static inline void add64(uint64_t *p, uint64_t n)
{
    atomic_store_explicit(A64(p), atomic_load_explicit(A64(p), RELAXED) + n, RELAXED);
}

static void event(rt_loop *l, const rtf_slot *s, int slot, uint32_t what, double time_s)
{
    rt_fault_event_ring *g = &l->fault_events;
    uint32_t head = atomic_load_explicit(A32(&g->head), RELAXED);
    uint32_t tail = atomic_load_explicit(A32(&g->tail), ACQUIRE);
    if (head - tail >= RT_FAULT_EVENT_RING_SIZE) {
        add64(&g->dropped, 1);
        return;
    }
    rt_fault_event *e = &g->events[head & (RT_FAULT_EVENT_RING_SIZE - 1u)];
    e->time_s = time_s;
    e->id = s->def.id;
    e->slot = (uint16_t)slot;
    e->kind = s->def.kind;
    e->what = what;
    atomic_store_explicit(A32(&g->head), head + 1, RELEASE);
}

void rtf_init(rt_fault_run *f)
{
    memset(f, 0, sizeof *f);
}

/* ------------------------------------------------------------------ */
/* Checking a definition                                               */
/* ------------------------------------------------------------------ */

static int is_can(int kind) { return kind >= RT_FAULT_CAN_OMIT && kind <= RT_FAULT_CAN_BUS_OFF; }
static int is_signal(int kind) { return kind >= RT_FAULT_SIG_HOLD && kind <= RT_FAULT_SIG_INVALID; }
static int is_physical(int kind)
{
    return kind >= RT_FAULT_SPOOL_STUCK && kind <= RT_FAULT_ENGINE_TORQUE_LIMIT;
}

/* the channel message g (loop-wide) belongs to, -1: none */
static int channel_of(const rt_loop *l, int g)
{
    for (int c = 0; c < l->n_channels; c++) {
        const rt_channel *ch = &l->chan[c];
        if (g >= ch->first_message && g < ch->first_message + (int)ch->table.n_messages)
            return c;
    }
    return -1;
}

static int condition_ok(const rt_loop *l, const rt_condition *w)
{
    if (w->n_terms > RT_COND_TERMS || w->any > 1)
        return 0;
    for (uint32_t i = 0; i < w->n_terms; i++) {
        const rt_term *t = &w->terms[i];
        if (t->op > RT_OP_BITS || isnan(t->value)
            || (t->op == RT_OP_BITS && !(t->value >= 1.0 && t->value < 18446744073709551616.0)))
            return 0;
        switch (t->source) {
        case RT_OPD_OUTPUT:
            if (t->index >= N_OUTPUTS)
                return 0;
            break;
        case RT_OPD_COMMAND:
            if (t->index >= (uint32_t)l->n_commands)
                return 0;
            break;
        case RT_OPD_SIGNAL:
            if (t->index >= (uint32_t)l->n_signal_values)
                return 0;
            break;
        case RT_OPD_MANEUVER_TIME:
            break;
        default:
            return 0;
        }
    }
    return 1;
}

static int def_ok(const rt_loop *l, const rt_fault_def *d)
{
    int k = d->kind;
    if (isnan(d->start_s) || isnan(d->duration_s) || !condition_ok(l, &d->when))
        return 0;
    if (k == RT_FAULT_WATCH)
        return 1;
    if (k == RT_FAULT_CAN_BUS_OFF)
        return d->channel >= -1 && d->channel < l->n_channels;
    if (is_can(k) || is_signal(k)) {
        int c = d->message >= 0 ? channel_of(l, d->message) : -1;
        if (c < 0)
            return 0;
        const rt_channel *ch = &l->chan[c];
        int m = d->message - ch->first_message;
        const ct_message *cm = &ch->table.messages[m];
        if (is_can(k)) {
            if (ch->msgs[m].direction != RT_DIR_TX)
                return 0;
            if (k == RT_FAULT_CAN_BAD_CRC && cm->crc_byte < 0)
                return 0;
            if (k == RT_FAULT_CAN_CYCLE && !(d->value > 0.0 && isfinite(d->value)))
                return 0;
            if (k == RT_FAULT_CAN_LENGTH && !(d->value >= 0.0 && d->value <= CT_MAX_LENGTH))
                return 0;
            return 1;
        }
        if (d->local_signal < 0 || d->local_signal >= (int)cm->n_signals ||
            d->signal != ch->first_signal_value + (int)cm->first_signal + d->local_signal)
            return 0;
        if (k != RT_FAULT_SIG_HOLD && !isfinite(d->value))
            return 0;
        return 1;
    }
    if (!is_physical(k) || !isfinite(d->value))
        return 0;
    switch (k) {
    case RT_FAULT_SPOOL_STUCK:
    case RT_FAULT_SOLENOID_OPEN:
    case RT_FAULT_KISS_DRIFT:
        return d->target >= 0 && d->target < 2;
    case RT_FAULT_FRICTION_FADE:
        return d->target >= 0 && d->target < 2 && d->value >= 0.0 && d->value <= 1.0;
    case RT_FAULT_LINE_PRESSURE_LOSS:
        return d->value >= 0.0 && d->value <= 1.0;
    case RT_FAULT_FORK_JAMMED:
    case RT_FAULT_BLOCKER_FAILED:
        return d->target >= 0 && d->target < DCT_N_SLEEVES;
    case RT_FAULT_ENGINE_TORQUE_LIMIT:
        return d->value >= 0.0;
    default:
        return 0;
    }
}

/* ------------------------------------------------------------------ */
/* Starting, ending, clearing                                          */
/* ------------------------------------------------------------------ */

static inline int timed(const rtf_slot *s)
{
    return s->state == RT_FSTATE_ARMED ||
           (s->state == RT_FSTATE_ACTIVE && s->def.duration_s > 0.0 && isfinite(s->def.duration_s));
}

static void start(rt_fault_run *f, rt_loop *l, int i, double now_s)
{
    rtf_slot *s = &f->slots[i];
    s->state = RT_FSTATE_ACTIVE;
    s->started_s = now_s;
    s->ended_s = NAN;
    s->activations++;
    if (s->def.kind == RT_FAULT_SIG_HOLD)
        s->held = l->signal_values[s->def.signal];  /* NaN before any value: the next one */
    if (s->def.kind == RT_FAULT_CAN_FREEZE_COUNTER) {
        uint64_t n = l->tx_count[s->def.message];
        f->msg_frozen_seq[s->def.message] = n ? n - 1u : 0u;
    }
    f->mask |= 1ull << i;
    f->changes++;
    event(l, s, i, RT_FEV_START, now_s);
}

static void stop(rt_fault_run *f, rt_loop *l, int i, double now_s, uint32_t what)
{
    rtf_slot *s = &f->slots[i];
    s->state = RT_FSTATE_ENDED;
    s->ended_s = now_s;
    f->mask &= ~(1ull << i);
    f->changes++;
    event(l, s, i, what, now_s);
}

static void free_slot(rt_fault_run *f, rt_loop *l, int i, double now_s)
{
    rtf_slot *s = &f->slots[i];
    if (!s->used)
        return;
    if (s->state == RT_FSTATE_ACTIVE)
        stop(f, l, i, now_s, RT_FEV_CLEARED);
    s->used = 0;
    s->state = RT_FSTATE_FREE;
    f->n_used--;
}

/* takes the queued commands; returns 1 when a slot changed */
static int take_commands(rt_fault_run *f, rt_loop *l, double now_s)
{
    rt_fault_cmd_ring *r = &l->fault_cmds;
    uint32_t tail = atomic_load_explicit(A32(&r->tail), RELAXED);
    uint32_t head = atomic_load_explicit(A32(&r->head), ACQUIRE);
    if (tail == head)
        return 0;
    int changed = 0, n = 0;
    while (tail != head && n < CMDS_PER_TICK) {
        const rt_fault_cmd *c = &r->cmds[tail & (RT_FAULT_CMD_RING_SIZE - 1u)];
        int ok = 1;
        if (c->op == RT_FCMD_SET && c->slot < RT_MAX_FAULTS && def_ok(l, &c->fault)) {
            free_slot(f, l, (int)c->slot, now_s);
            rtf_slot *s = &f->slots[c->slot];
            memset(s, 0, sizeof *s);
            s->used = 1;
            s->state = RT_FSTATE_ARMED;
            s->def = c->fault;
            s->started_s = s->ended_s = NAN;
            s->held = NAN;
            s->rng = c->fault.seed ? c->fault.seed : 0x9E3779B97F4A7C15ull;
            f->n_used++;
        } else if (c->op == RT_FCMD_CLEAR && c->slot < RT_MAX_FAULTS) {
            free_slot(f, l, (int)c->slot, now_s);
        } else if (c->op == RT_FCMD_CLEAR_ALL) {
            for (int i = 0; i < RT_MAX_FAULTS; i++)
                free_slot(f, l, i, now_s);
        } else {
            ok = 0;
        }
        if (ok) {
            add64(&r->applied, 1);
            changed = 1;
        } else {
            add64(&r->refused, 1);
        }
        atomic_store_explicit(A64(&r->last_id), c->fault.id, RELAXED);
        tail++;
        n++;
    }
    atomic_store_explicit(A32(&r->tail), tail, RELEASE);
    return changed;
}

static inline int compare(uint8_t op, double x, double v)
{
    switch (op) {
    case RT_OP_LT:
        return x < v;
    case RT_OP_LE:
        return x <= v;
    case RT_OP_GT:
        return x > v;
    case RT_OP_GE:
        return x >= v;
    case RT_OP_EQ:
        return fabs(x - v) <= 1e-9 * (fabs(v) > 1.0 ? fabs(v) : 1.0);
    case RT_OP_BITS:
        return x >= 1.0 && x < 18446744073709551616.0 && ((uint64_t)x & (uint64_t)v) != 0;
    default:
        return !(fabs(x - v) <= 1e-9 * (fabs(v) > 1.0 ? fabs(v) : 1.0));
    }
}

static int holds(const rt_loop *l, const rt_condition *w, const double *cmd,
                 double maneuver_time_s)
{
    if (w->n_terms == 0)
        return 1;
    for (uint32_t i = 0; i < w->n_terms; i++) {
        const rt_term *t = &w->terms[i];
        double x;
        switch (t->source) {
        case RT_OPD_OUTPUT:
            x = ((const double *)(const void *)&l->plant.outputs)[t->index];
            break;
        case RT_OPD_COMMAND:
            x = cmd[t->index];
            break;
        case RT_OPD_SIGNAL:
            x = l->signal_values[t->index];
            break;
        default:
            x = maneuver_time_s;
            break;
        }
        int h = compare(t->op, x, t->value);
        if (w->any && h)
            return 1;
        if (!w->any && !h)
            return 0;
    }
    return !w->any;
}

/* ------------------------------------------------------------------ */
/* Effects                                                             */
/* ------------------------------------------------------------------ */

static void set_flag(rt_fault_run *f, int g, unsigned flag, int bit, int slot)
{
    f->msg_flags[g] |= (uint8_t)flag;
    f->msg_fault_slot[g][bit] = (uint8_t)slot;
}

/* the effects of the active slots; returns RTF_CYCLES_CHANGED when a
 * message's cycle changed, -1 when the plant refused its faults */
static int effects(rt_fault_run *f, rt_loop *l)
{
    int n_msgs = l->stats.n_messages;
    uint8_t had_cycle[RT_MAX_MESSAGES];
    double old_cycle[RT_MAX_MESSAGES];
    for (int g = 0; g < n_msgs; g++) {
        had_cycle[g] = f->msg_flags[g] & RTF_CYCLE;
        old_cycle[g] = f->msg_cycle_s[g];
    }
    memset(f->msg_flags, 0, sizeof f->msg_flags);
    memset(f->msg_signal_faults, 0, sizeof f->msg_signal_faults);
    memset(f->msg_invalid, 0, sizeof f->msg_invalid);
    memset(f->chan_off, 0, sizeof f->chan_off);
    f->n_signal = 0;
    dct_faults pf;
    memset(&pf, 0, sizeof pf);
    int tx_signal = 0;
    for (int i = 0; i < RT_MAX_FAULTS; i++) {
        const rtf_slot *s = &f->slots[i];
        if (!s->used || s->state != RT_FSTATE_ACTIVE)
            continue;
        const rt_fault_def *d = &s->def;
        int t = d->target;
        switch (d->kind) {
        case RT_FAULT_CAN_OMIT:
            set_flag(f, d->message, RTF_OMIT, 0, i);
            break;
        case RT_FAULT_CAN_FREEZE_COUNTER:
            set_flag(f, d->message, RTF_FREEZE, 1, i);
            break;
        case RT_FAULT_CAN_BAD_CRC:
            set_flag(f, d->message, RTF_BAD_CRC, 2, i);
            break;
        case RT_FAULT_CAN_LENGTH:
            set_flag(f, d->message, RTF_LENGTH, 3, i);
            f->msg_length[d->message] = (uint8_t)d->value;
            break;
        case RT_FAULT_CAN_CYCLE:
            set_flag(f, d->message, RTF_CYCLE, 4, i);
            f->msg_cycle_s[d->message] = d->value;
            break;
        case RT_FAULT_CAN_BUS_OFF:
            for (int c = 0; c < l->n_channels; c++)
                if (d->channel < 0 || d->channel == c) {
                    f->chan_off[c] = 1;
                    f->chan_off_slot[c] = (uint8_t)i;
                }
            break;
        case RT_FAULT_SPOOL_STUCK:
            pf.spool_stuck[t] = 1.0;
            break;
        case RT_FAULT_SOLENOID_OPEN:
            pf.solenoid_open[t] = 1.0;
            break;
        case RT_FAULT_FRICTION_FADE: /* two fades: what is left of the first, faded again */
            pf.friction_loss[t] = 1.0 - (1.0 - pf.friction_loss[t]) * (1.0 - d->value);
            break;
        case RT_FAULT_KISS_DRIFT:
            pf.pack_gap_offset_mm[t] += d->value;
            break;
        case RT_FAULT_LINE_PRESSURE_LOSS:
            pf.line_pressure_loss = 1.0 - (1.0 - pf.line_pressure_loss) * (1.0 - d->value);
            break;
        case RT_FAULT_FORK_JAMMED:
            pf.fork_jammed[t] = 1.0;
            break;
        case RT_FAULT_BLOCKER_FAILED:
            pf.blocker_failed[t] = 1.0;
            break;
        case RT_FAULT_ENGINE_TORQUE_LIMIT:
            if (!(pf.engine_torque_limited > 0.5) || d->value < pf.engine_torque_max_nm)
                pf.engine_torque_max_nm = d->value;
            pf.engine_torque_limited = 1.0;
            break;
        default:
            if (is_signal(d->kind)) {
                f->signal_slots[f->n_signal++] = (uint8_t)i;
                if (f->msg_signal_faults[d->message] < 255)
                    f->msg_signal_faults[d->message]++;
                if (d->kind == RT_FAULT_SIG_INVALID)
                    f->msg_invalid[d->message] = 1;
                int c = channel_of(l, d->message);
                if (l->chan[c].msgs[d->message - l->chan[c].first_message].direction == RT_DIR_TX)
                    tx_signal = 1;
            }
            break;
        }
    }
    int any = tx_signal;
    for (int g = 0; g < n_msgs && !any; g++)
        any = f->msg_flags[g] != 0;
    for (int c = 0; c < l->n_channels && !any; c++)
        any = f->chan_off[c];
    f->tx_any = any;

    int rc = 0;
    for (int g = 0; g < n_msgs; g++)
        if ((f->msg_flags[g] & RTF_CYCLE) != had_cycle[g] ||
            (had_cycle[g] && f->msg_cycle_s[g] != old_cycle[g]))
            rc = RTF_CYCLES_CHANGED;
    if (memcmp(&pf, &l->plant.faults, sizeof pf) != 0) {
        dct_faults before = l->plant.faults;
        l->plant.faults = pf;
        if (dct_plant_prepare(&l->plant) != DCT_OK) {
            l->plant.faults = before;   /* refused: as before (the checks make this rare) */
            (void)dct_plant_prepare(&l->plant);
            return -1;
        }
    }
    return rc;
}

int rtf_tick(rt_fault_run *f, rt_loop *l, const double *cmd, double maneuver_time_s)
{
    double now_s = l->plant.state.time_s;
    int changed = take_commands(f, l, now_s);
    if (f->n_used == 0 && !changed)
        return 0;
    if (f->n_timed > 0 || changed) {
        for (int i = 0; i < RT_MAX_FAULTS; i++) {
            rtf_slot *s = &f->slots[i];
            if (!s->used)
                continue;
            if (s->state == RT_FSTATE_ARMED) {
                if (now_s + 1e-9 >= s->def.start_s && holds(l, &s->def.when, cmd, maneuver_time_s)) {
                    start(f, l, i, now_s);
                    changed = 1;
                }
            } else if (s->state == RT_FSTATE_ACTIVE && s->def.duration_s > 0.0 &&
                       isfinite(s->def.duration_s) &&
                       now_s - s->started_s >= s->def.duration_s - 1e-9) {
                stop(f, l, i, now_s, RT_FEV_END);
                changed = 1;
            }
        }
    }
    if (!changed)
        return 0;
    int n_timed = 0;
    for (int i = 0; i < RT_MAX_FAULTS; i++)
        n_timed += f->slots[i].used && timed(&f->slots[i]);
    f->n_timed = n_timed;
    int rc = effects(f, l);
    if (rc < 0) {                     /* the plant refused: end the physical faults just started */
        for (int i = 0; i < RT_MAX_FAULTS; i++) {
            rtf_slot *s = &f->slots[i];
            if (s->used && s->state == RT_FSTATE_ACTIVE && is_physical(s->def.kind) &&
                s->started_s == now_s)
                stop(f, l, i, now_s, RT_FEV_END);
        }
        rc = effects(f, l);
        if (rc < 0)
            rc = 0;
    }
    return RTF_CHANGED | rc;
}

/* ------------------------------------------------------------------ */
/* Signal faults                                                       */
/* ------------------------------------------------------------------ */

/* xorshift64*: uniform in (0, 1) */
static inline double uniform(uint64_t *state)
{
    uint64_t x = *state;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    *state = x;
    return ((double)((x * 0x2545F4914F6CDD1Dull) >> 11) + 0.5) * (1.0 / 9007199254740992.0);
}

/* a standard normal value (Box-Muller, the pair's second value kept) */
static double normal(rtf_slot *s)
{
    if (s->has_spare) {
        s->has_spare = 0;
        return s->spare;
    }
    double u1 = uniform(&s->rng), u2 = uniform(&s->rng);
    double r = sqrt(-2.0 * log(u1)), a = 2.0 * 3.14159265358979323846 * u2;
    s->spare = r * sin(a);
    s->has_spare = 1;
    return r * cos(a);
}

void rtf_signals(rt_fault_run *f, int g, double *values, const uint8_t *written, uint32_t n)
{
    for (int j = 0; j < f->n_signal; j++) {
        rtf_slot *s = &f->slots[f->signal_slots[j]];
        const rt_fault_def *d = &s->def;
        if (d->message != g || (uint32_t)d->local_signal >= n ||
            (written && !written[d->local_signal]))
            continue;
        double *v = &values[d->local_signal];
        switch (d->kind) {
        case RT_FAULT_SIG_HOLD:
            if (isnan(s->held))
                s->held = *v;
            *v = s->held;
            break;
        case RT_FAULT_SIG_VALUE:
        case RT_FAULT_SIG_INVALID:
            *v = d->value;
            break;
        case RT_FAULT_SIG_OFFSET:
            *v += d->value;
            break;
        case RT_FAULT_SIG_GAIN:
            *v *= d->value;
            break;
        case RT_FAULT_SIG_NOISE:
            *v += d->value * normal(s);
            break;
        default:
            continue;
        }
        s->hits++;
    }
}

void rtf_raw(rt_fault_run *f, const ct_table *t, int m, int g, uint8_t *data)
{
    if (!f->msg_invalid[g])
        return;
    for (int j = 0; j < f->n_signal; j++) {
        const rt_fault_def *d = &f->slots[f->signal_slots[j]].def;
        if (d->message == g && d->kind == RT_FAULT_SIG_INVALID)
            (void)ct_put_raw(t, m, d->local_signal, d->raw, data);
    }
}

void rtf_hit_message(rt_fault_run *f, int g, unsigned flag)
{
    int bit = flag == RTF_OMIT ? 0 : flag == RTF_FREEZE ? 1 : flag == RTF_BAD_CRC ? 2
            : flag == RTF_LENGTH ? 3 : 4;
    f->slots[f->msg_fault_slot[g][bit]].hits++;
}

void rtf_hit_channel(rt_fault_run *f, int c)
{
    f->slots[f->chan_off_slot[c]].hits++;
}

void rtf_publish(const rt_fault_run *f, rt_stats *s, int changed)
{
    s->fault_mask = f->mask;
    s->fault_changes = f->changes;
    if (!changed) {                   /* only the hits of the active faults move */
        for (uint64_t m = f->mask; m; m &= m - 1u) {
            int i = __builtin_ctzll(m);
            s->faults[i].hits = f->slots[i].hits;
        }
        return;
    }
    for (int i = 0; i < RT_MAX_FAULTS; i++) {
        const rtf_slot *x = &f->slots[i];
        rt_fault_stats *o = &s->faults[i];
        if (!x->used) {
            if (o->state != RT_FSTATE_FREE)
                o->state = RT_FSTATE_FREE;
            continue;
        }
        o->id = x->def.id;
        o->kind = x->def.kind;
        o->state = x->state;
        o->activations = x->activations;
        o->started_s = x->started_s;
        o->ended_s = x->ended_s;
        o->hits = x->hits;
    }
}
