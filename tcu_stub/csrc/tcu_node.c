/*
 * tcu_node.c - the reference TCU's CAN node in C: the 2 ms task of
 * tcu_stub/can_tcu.py (CanTcu) on a thread of its own, with no Python in it.
 *
 * A period: every frame waiting on each port is taken in and checked
 * (receive), each needed plant message judged (missing, rejected, timed
 * out), the sensors read from the last accepted values (read_sensors), the
 * TCU steps, the messages due are sent (send_due), the stale episodes kept
 * and the figures published under a sequence counter. Late periods skip the
 * missed deadlines and TCU time advances by the periods that really passed,
 * as in CanTcu._task; the bus clock ticks per frame of its message, as
 * CanTcu._task_bus. Every wake-up's lateness is taken before anything else
 * (note_wake): a wake-up later than a few periods is a stall, logged, so a
 * timeout on the other side can be told apart from the machine holding the
 * thread.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <string.h>
#include <time.h>

#include "tcu_node.h"

static void publish(tcu_node *n);

double tcu_node_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static void hist_add(tcu_node_hist *h, double us)
{
    h->n++;
    h->total += us;
    if (us > h->max)
        h->max = us;
    long i = (long)(us / 10.0);
    if (i < 0)
        i = 0;
    if (i >= TCU_NODE_HIST_BINS)
        i = TCU_NODE_HIST_BINS - 1;
    h->bins[i]++;
}

void tcu_node_reset(tcu_node *n)
{
    memset(&n->fig, 0, sizeof n->fig);
    n->fig.final_safe_frames = -1;
    n->fig.last_send_error_tx = -1;
    n->fig.stale = 1;
    for (int i = 0; i < TCU_NODE_MAX_RX; i++) {
        n->rx_state[i].last_counter = -1;
        n->has_values[i] = 0;
        n->rejects_in_row[i] = 0;
        n->last_reject[i] = 0;
    }
    for (int i = 0; i < TCU_NODE_MAX_TX; i++) {
        n->counter[i] = 0;
        n->next_due[i] = 0;
    }
    memset(&n->exec_us, 0, sizeof n->exec_us);
    memset(&n->late_us, 0, sizeof n->late_us);
    memset(n->stall_log, 0, sizeof n->stall_log);
    n->open_episode = -1;
    n->stop = 0;
    n->pause_ns = 0;
    n->seq = 0;
    n->pub = n->fig;
}

/* ------------------------------------------------------------------ receive */
static void take_frame(tcu_node *n, int bus, const tcu_frame *f, double now)
{
    tcu_node_figures *g = &n->fig;
    if (f->id & TCU_FRAME_ERR) {
        g->error_frames[bus]++;
        return;
    }
    int ext = (f->id & TCU_FRAME_EFF) != 0;
    uint32_t id = f->id & (ext ? 0x1FFFFFFFu : 0x7FFu);
    int m = ct_find(n->tables[bus], id, ext);
    int r = (m >= 0 && m < TCU_NODE_MAX_TABLE) ? n->rx_of[bus][m] : -1;
    if (r < 0) {
        g->unknown[bus]++;
        return;
    }
    tcu_node_rx_counts *c = &g->rx[r];
    c->received++;
    int len = (f->id & TCU_FRAME_RTR) ? 0 : f->len;
    static const uint8_t none[1] = {0};
    int status = ct_check(n->tables[bus], m, len ? f->data : none, len, &n->rx_state[r]);
    if (status != CT_RX_OK) {
        n->rejects_in_row[r]++;
        if (status == CT_RX_BAD_LENGTH) {
            c->bad_length++;
            n->last_reject[r] = TCU_MSG_BAD_LENGTH;
        } else if (status == CT_RX_BAD_CRC) {
            c->bad_crc++;
            n->last_reject[r] = TCU_MSG_BAD_CRC;
        } else {
            c->bad_counter++;
            n->last_reject[r] = TCU_MSG_BAD_COUNTER;
        }
        return;
    }
    ct_decode(n->tables[bus], m, f->data, len, n->values[r], NULL);
    n->has_values[r] = 1;
    n->rejects_in_row[r] = 0;
    c->accepted++;
    if (c->accepted > 1) {
        if (now - c->last_t > c->max_interval_s)
            c->max_interval_s = now - c->last_t;
    } else {
        c->first_t = now;
    }
    c->last_t = now;
}

void tcu_node_receive(tcu_node *n, double now)
{
    tcu_frame batch[TCU_NODE_BATCH];
    for (int b = 0; b < n->n_buses; b++) {
        for (;;) {
            int got = tcu_port_recv(&n->ports[b], batch, TCU_NODE_BATCH);
            for (int i = 0; i < got; i++)
                take_frame(n, b, &batch[i], now);
            if (got < TCU_NODE_BATCH)
                break;
        }
    }
}

/* ------------------------------------------------------------------ sensors */
static double read_value(const tcu_node *n, const tcu_node_read *rd)
{
    const double *v = n->values[rd->rx];
    double x = (v[rd->sig] - rd->bias) / rd->gain;
    if (rd->dir_sig >= 0) {
        double code = v[rd->dir_sig];
        for (int i = 0; i < rd->n_codes; i++)
            if (code == rd->codes[i]) {
                x = -x;
                break;
            }
    }
    return x;
}

/* the causes of the needed messages (TCU_MSG_*), 1 when any is stale */
static int judge(tcu_node *n, double now, int32_t *cause)
{
    int any = 0;
    for (int r = 0; r < n->n_rx; r++) {
        cause[r] = TCU_MSG_OK;
        if (!n->rx[r].needed)
            continue;
        if (!n->has_values[r])
            cause[r] = TCU_MSG_MISSING;
        else if (n->rejects_in_row[r] >= n->rejects_to_stale)
            cause[r] = n->last_reject[r] ? n->last_reject[r] : TCU_MSG_REJECTED;
        else if (now - n->fig.rx[r].last_t > n->rx[r].timeout_s)
            cause[r] = TCU_MSG_TIMEOUT;
        any = any || cause[r] != TCU_MSG_OK;
    }
    return any;
}

static void read_sensors(tcu_node *n, double *sensors, int *line_absent)
{
    tcu_node_figures *g = &n->fig;
    memcpy(sensors, n->defaults, sizeof n->defaults);
    *line_absent = 1;
    for (int i = 0; i < n->n_reads; i++) {
        const tcu_node_read *rd = &n->reads[i];
        if (!n->has_values[rd->rx])
            continue;
        double x = read_value(n, rd);
        if (rd->slot < 0) {
            g->have_sim_time = 1;
            g->sim_time_s = x;
        } else {
            sensors[rd->slot] = x;
            if (rd->slot == TCU_S_LINE_PRESSURE)
                *line_absent = 0;
        }
    }
}

/* ------------------------------------------------------------------ send */
static double tx_value(const tcu_node *n, const tcu_node_tx *t, int i, const double *commands)
{
    switch (t->kind[i]) {
    case TCU_TX_LINEAR: {
        double x = commands[t->slot[i]];
        if (!isfinite(x))
            return t->start[i];
        return (x - t->bias[i]) / t->gain[i];
    }
    case TCU_TX_TABLE: {
        double x = commands[t->slot[i]];
        for (int k = 0; k < t->pair_count[i]; k++) {
            const double *p = n->pairs[t->pair_first[i] + k];
            if (p[0] == x)
                return p[1];
        }
        return t->start[i];
    }
    default:
        return t->start[i];
    }
}

static int send_message(tcu_node *n, int j, const double *values)
{
    tcu_node_tx *t = &n->tx[j];
    const ct_table *table = n->tables[t->bus];
    const ct_message *m = &table->messages[t->msg];
    tcu_frame f;
    memset(&f, 0, sizeof f);
    f.id = m->id | (m->extended ? TCU_FRAME_EFF : 0);
    f.flags = m->fd ? TCU_FRAME_FD : 0;
    f.channel = (uint8_t)t->bus;
    uint32_t saturated = 0;
    int len = ct_encode_counted(table, t->msg, values, f.data, &saturated);
    ct_protect(table, t->msg, f.data, n->counter[j]);
    f.len = (uint8_t)len;
    tcu_node_figures *g = &n->fig;
    tcu_port *p = &n->ports[t->bus];
    if (tcu_port_send(p, &f) != 0) {
        g->send_errors[j]++;
        g->last_send_error_tx = j;
        g->last_send_errno = p->last_errno;
        return -1;
    }
    n->counter[j]++;
    g->sent[j]++;
    g->saturated[j] += saturated;
    return 0;
}

static void send_due(tcu_node *n, int64_t k, const double *commands)
{
    double values[TCU_NODE_MAX_SIGNALS];
    for (int j = 0; j < n->n_tx; j++) {
        tcu_node_tx *t = &n->tx[j];
        if (k < n->next_due[j])
            continue;
        for (int i = 0; i < t->n_signals; i++)
            values[i] = tx_value(n, t, i, commands);
        send_message(n, j, values);
        n->next_due[j] = (k / t->every + 1) * t->every;
    }
}

int tcu_node_send_safe(tcu_node *n)
{
    int ok = 1;
    for (int j = 0; j < n->n_tx; j++)
        ok = send_message(n, j, n->tx[j].safe) == 0 && ok;
    n->fig.final_safe_frames = ok;
    publish(n);
    return ok ? 0 : -1;
}

/* ------------------------------------------------------------------ publish */
static void publish(tcu_node *n)
{
    uint32_t s = n->seq;
    __atomic_store_n(&n->seq, s + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
    memcpy(&n->pub, &n->fig, sizeof n->fig);
    __atomic_store_n(&n->seq, s + 2, __ATOMIC_RELEASE);
}

void tcu_node_figures_read(tcu_node *n, tcu_node_figures *out)
{
    for (;;) {
        uint32_t a = __atomic_load_n(&n->seq, __ATOMIC_ACQUIRE);
        if (a & 1) {
            sched_yield();
            continue;
        }
        memcpy(out, &n->pub, sizeof *out);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (__atomic_load_n(&n->seq, __ATOMIC_RELAXED) == a)
            return;
    }
}

/* ------------------------------------------------------------------ a period */
static void drain_logs(tcu_node *n)
{
    tcu_state *s = n->tcu;
    tcu_node_figures *g = &n->fig;
    for (int i = 0; i < s->n_shifts; i++) {
        if (g->n_shifts < TCU_NODE_MAX_SHIFTS)
            n->shift_log[g->n_shifts++] = s->shifts[i];
        else
            g->shifts_lost++;
    }
    g->shifts_lost += s->shifts_lost;
    s->n_shifts = 0;
    s->shifts_lost = 0;
    tcu_diag *d = &s->diag;
    for (int i = 0; i < d->n_events; i++) {
        if (g->n_events < TCU_NODE_MAX_EVENTS)
            n->event_log[g->n_events++] = d->events[i];
        else
            g->events_lost++;
    }
    g->events_lost += d->events_lost;
    d->n_events = 0;
    d->events_lost = 0;
}

static void keep_episode(tcu_node *n, double t_s, int stale, const int32_t *cause)
{
    tcu_node_figures *g = &n->fig;
    if (stale) {
        g->stale_ticks++;
        if (n->open_episode < 0) {
            g->episode_count++;
            if (g->n_episodes < TCU_NODE_MAX_EPISODES) {
                tcu_node_episode *e = &n->episodes[g->n_episodes];
                memset(e, 0, sizeof *e);
                e->start_s = t_s;
                e->open = 1;
                n->open_episode = g->n_episodes++;
            } else {
                n->open_episode = TCU_NODE_MAX_EPISODES;     /* counted, not kept */
            }
        }
        if (n->open_episode < TCU_NODE_MAX_EPISODES) {
            tcu_node_episode *e = &n->episodes[n->open_episode];
            for (int r = 0; r < n->n_rx; r++)
                if (cause[r] != TCU_MSG_OK && e->causes[r] == TCU_MSG_OK)
                    e->causes[r] = (uint8_t)cause[r];
        }
    } else if (n->open_episode >= 0) {
        if (n->open_episode < TCU_NODE_MAX_EPISODES) {
            n->episodes[n->open_episode].end_s = t_s;
            n->episodes[n->open_episode].open = 0;
        }
        n->open_episode = -1;
    }
    g->stale = stale;
}

int tcu_node_period(tcu_node *n, int64_t k, double now)
{
    tcu_node_figures *g = &n->fig;
    double t_s = (double)k * n->period_s;
    int32_t cause[TCU_NODE_MAX_RX];
    int32_t engine[TCU_NODE_MAX_RX];
    int32_t needed_cause[TCU_NODE_MAX_RX];
    double sensors[TCU_N_SENSORS];
    double commands[TCU_N_COMMANDS];
    int line_absent;
    int stale = judge(n, now, cause);
    read_sensors(n, sensors, &line_absent);
    int m = 0;
    for (int r = 0; r < n->n_rx; r++)
        if (n->rx[r].needed) {
            needed_cause[m] = cause[r];
            engine[m] = n->rx[r].engine;
            m++;
        }
    tcu_msgs msgs = {m, needed_cause, engine, line_absent || !n->line_slot_read};
    tcu_step_node(n->cal, n->tcu, t_s, sensors, &msgs, commands);
    send_due(n, k, commands);
    drain_logs(n);
    keep_episode(n, t_s, stale, cause);
    memcpy(g->stale_causes, cause, sizeof cause);
    g->tick_index = k;
    g->t_s = t_s;
    g->ticks++;
    g->have_sensors = 1;
    memcpy(g->sensors, sensors, sizeof sensors);
    memcpy(g->commands, commands, sizeof commands);
    const tcu_state *s = n->tcu;
    g->phase = s->phase;
    g->gear = s->gear;
    g->target_gear = s->target_gear;
    g->active_bits = s->diag.active_bits;
    g->stored_bits = s->diag.stored_bits;
    g->fault_count = s->diag.fault_count;
    g->inhibited = s->diag.inhibited;
    g->limp_home = s->diag.limp_home;
    g->safe_state = s->diag.safe_state;
    publish(n);
    return 0;
}

/* ------------------------------------------------------------------ the thread */
static int stopping(tcu_node *n)
{
    return __atomic_load_n(&n->stop, __ATOMIC_ACQUIRE) != 0;
}

static void add_ns(struct timespec *t, int64_t ns)
{
    int64_t total = (int64_t)t->tv_nsec + ns;
    t->tv_sec += total / 1000000000;
    t->tv_nsec = total % 1000000000;
    if (t->tv_nsec < 0) {
        t->tv_nsec += 1000000000;
        t->tv_sec -= 1;
    }
}

static double ts_s(const struct timespec *t)
{
    return t->tv_sec + 1e-9 * t->tv_nsec;
}

/* sleeps until the absolute time t (CLOCK_MONOTONIC), waking at least every 20 ms
   to see a stop; 1 when stopped meanwhile */
static int sleep_until(tcu_node *n, const struct timespec *t)
{
    for (;;) {
        if (stopping(n))
            return 1;
        struct timespec now, step;
        clock_gettime(CLOCK_MONOTONIC, &now);
        if (ts_s(&now) >= ts_s(t))
            return 0;
        step = now;
        add_ns(&step, 20000000);
        const struct timespec *until = ts_s(&step) < ts_s(t) ? &step : t;
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, until, NULL) == EINTR)
            ;
    }
}

/* a wake-up late_s after its time (read before a pause asked for): the longest
   kept, one later than TCU_NODE_STALL_PERIODS periods logged. A reader of the
   log takes n_stalls from the figures, then the entries below it whose index
   still matches (the ring overwrites only entries TCU_NODE_MAX_STALLS older) */
static void note_wake(tcu_node *n, double late_s, double now)
{
    tcu_node_figures *g = &n->fig;
    if (late_s > g->stall_max_s)
        g->stall_max_s = late_s;
    if (late_s <= TCU_NODE_STALL_PERIODS * 1e-9 * (double)n->period_ns)
        return;
    tcu_node_stall *e = &n->stall_log[g->n_stalls % TCU_NODE_MAX_STALLS];
    e->index = g->n_stalls;
    e->at_s = now - n->t0;
    e->late_s = late_s;
    __atomic_thread_fence(__ATOMIC_RELEASE);
    g->n_stalls++;
}

/* a starvation asked for: the whole node waits, frames stay where they are */
static int starve(tcu_node *n)
{
    int64_t ns = __atomic_exchange_n(&n->pause_ns, 0, __ATOMIC_ACQ_REL);
    if (ns <= 0)
        return 0;
    struct timespec until;
    clock_gettime(CLOCK_MONOTONIC, &until);
    add_ns(&until, ns);
    sleep_until(n, &until);
    n->fig.pauses++;
    n->fig.paused_s += 1e-9 * (double)ns;
    return 1;
}

/* the first period's start: now, or the next instant on the phase grid */
static struct timespec first_deadline(const tcu_node *n)
{
    struct timespec t0;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    if (n->phase_ref_ns <= 0 || n->phase_step_ns <= 0)
        return t0;
    int64_t now = (int64_t)t0.tv_sec * 1000000000LL + t0.tv_nsec;
    int64_t base = n->phase_ref_ns + n->phase_offset_ns;
    int64_t at = base;
    if (now > base)
        at = base + ((now - base + n->phase_step_ns - 1) / n->phase_step_ns) * n->phase_step_ns;
    t0.tv_sec = (time_t)(at / 1000000000LL);
    t0.tv_nsec = (long)(at % 1000000000LL);
    return t0;
}

static void run_wall(tcu_node *n)
{
    struct timespec t0 = first_deadline(n);
    double period = 1e-9 * (double)n->period_ns;
    int64_t k = 0;
    while (!stopping(n)) {
        struct timespec deadline = t0;
        add_ns(&deadline, k * n->period_ns);
        if (sleep_until(n, &deadline))
            break;
        double woke = tcu_node_now();
        note_wake(n, woke - ts_s(&deadline), woke);
        int starved = starve(n);
        double now = tcu_node_now();
        double late = now - ts_s(&deadline);
        if (late > period) {              /* skip the missed deadlines, no burst */
            int64_t missed = (int64_t)floor(late / period);
            k += missed;
            late -= (double)missed * period;
            n->fig.skipped_ticks += missed;
        }
        if (!starved)
            tcu_node_receive(n, now - n->t0);
        tcu_node_period(n, k, now - n->t0);
        hist_add(&n->late_us, late * 1e6);
        hist_add(&n->exec_us, (tcu_node_now() - now) * 1e6);
        k++;
    }
}

/* a period per frame of the clock message (clock_ticks periods each); without it for
   its timeout one period anyway */
static void run_bus(tcu_node *n)
{
    int r = n->clock_rx;
    double wait_s = n->rx[r].timeout_s;
    int64_t poll_ns = n->period_ns / 4 > 0 ? n->period_ns / 4 : 1;
    uint64_t seen = n->fig.rx[r].accepted;
    double waited_from = tcu_node_now();
    int64_t k = 0;
    while (!stopping(n)) {
        struct timespec until;
        clock_gettime(CLOCK_MONOTONIC, &until);
        add_ns(&until, poll_ns);
        if (sleep_until(n, &until))
            break;
        double woke = tcu_node_now();
        note_wake(n, woke - ts_s(&until), woke);
        int starved = starve(n);
        double now = tcu_node_now();
        if (!starved)
            tcu_node_receive(n, now - n->t0);
        uint64_t accepted = n->fig.rx[r].accepted;
        int ticks;
        if (accepted > seen) {
            if (accepted > seen + 1 && k > 0) {       /* frames this task did not get to */
                int64_t missed = (int64_t)(accepted - seen - 1) * n->clock_ticks;
                n->fig.skipped_ticks += missed;
                k += missed;
            }
            seen = accepted;
            ticks = n->clock_ticks;
        } else if (now - waited_from >= wait_s) {
            ticks = 1;
        } else {
            continue;
        }
        waited_from = now;
        for (int i = 0; i < ticks; i++) {
            tcu_node_period(n, k, now - n->t0);
            hist_add(&n->exec_us, (tcu_node_now() - now) * 1e6);
            k++;
        }
    }
}

/* the frames queued in the ports before the thread started (a socket bound long
   before, a bridge's ring) are of another time: discarded, counted, so the first
   period reads only frames of its own (a burst of old ones, their counters cut
   where the socket overflowed, would be rejected and make the node stale at 0 s) */
static void drain_ports(tcu_node *n)
{
    tcu_frame batch[TCU_NODE_BATCH];
    for (int b = 0; b < n->n_buses; b++) {
        for (int rounds = 0; rounds < 4096; rounds++) {
            int got = tcu_port_recv(&n->ports[b], batch, TCU_NODE_BATCH);
            n->fig.drained_at_start += (uint64_t)(got > 0 ? got : 0);
            if (got < TCU_NODE_BATCH)
                break;
        }
    }
}

static void *thread_main(void *arg)
{
    tcu_node *n = arg;
    drain_ports(n);
    n->fig.running = 1;
    publish(n);
    if (n->clock == TCU_CLOCK_BUS)
        run_bus(n);
    else
        run_wall(n);
    tcu_node_send_safe(n);
    n->fig.running = 0;
    n->stop_time_s = tcu_node_now();
    publish(n);
    return NULL;
}

int tcu_node_start(tcu_node *n)
{
    if (n->started)
        return EALREADY;
    n->t0 = tcu_node_now();
    n->start_time_s = n->t0;
    n->sched_fifo = 0;
    pthread_t th;
    pthread_attr_t attr;
    int rc = -1;
    /* a stack of TCU_NODE_STACK_BYTES, not the default 8 MiB: a server that
     * locks its memory (mlockall) locks the whole stack of every thread */
    if (n->priority > 0) {
        struct sched_param sp = {.sched_priority = n->priority};
        pthread_attr_init(&attr);
        pthread_attr_setstacksize(&attr, TCU_NODE_STACK_BYTES);
        pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
        pthread_attr_setschedpolicy(&attr, SCHED_FIFO);
        pthread_attr_setschedparam(&attr, &sp);
        rc = pthread_create(&th, &attr, thread_main, n);
        pthread_attr_destroy(&attr);
        if (rc == 0)
            n->sched_fifo = 1;
    }
    if (rc != 0) {
        pthread_attr_init(&attr);
        pthread_attr_setstacksize(&attr, TCU_NODE_STACK_BYTES);
        rc = pthread_create(&th, &attr, thread_main, n);
        pthread_attr_destroy(&attr);
    }
    n->start_errno = rc;
    if (rc != 0)
        return rc;
    n->thread = (uint64_t)th;
    n->started = 1;
    return 0;
}

void tcu_node_stop(tcu_node *n)
{
    __atomic_store_n(&n->stop, 1, __ATOMIC_RELEASE);
    if (n->started == 1) {
        pthread_join((pthread_t)n->thread, NULL);
        n->started = 2;
    }
}

void tcu_node_pause(tcu_node *n, double seconds)
{
    __atomic_store_n(&n->pause_ns, (int64_t)(seconds * 1e9), __ATOMIC_RELEASE);
}
