/*
 * rt_loop.c - the real-time loop of the plant server (contract: rt_loop.h).
 *
 * The tick, on absolute deadlines t0 + n x period (n: the deadline index):
 *
 *   clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, deadline)  (EINTR: again)
 *   wake   = now                     latency    = wake - deadline
 *   drain the received frames        channel by channel, at most
 *                                    RT_RX_MAX_PER_TICK per channel and tick,
 *                                    the rest stays queued for the next tick
 *     each: classify (unknown id, bad length or frame format), ct_check
 *     (checksum, counter), count the outcome per channel and message; an
 *     accepted frame is decoded (ct_decode) and each signal with a target
 *     sets its command value (scaled or looked up, limited), stamps
 *     last_rx_tick = the deadline index of the drain's time (n, or more
 *     in a tick woken late) and ends a timeout of its message
 *   timeouts                         a message not accepted for more than
 *                                    its timeout_cycles (RT_TIMEOUT_CYCLES by
 *                                    default) cycle times is timed out: its
 *                                    commands take their safe values
 *   command values -> plant inputs, dct_plant_step(plant, 1)
 *   the frames due at executed tick k, channel by channel: each signal's
 *     value from its source (plant output, status, fixed value, toggle,
 *     counter), ct_encode, ct_protect (counter = frames made so far), send
 *   end    = now                     turnaround = end - deadline
 *                                    execution  = end - wake
 *   publish the statistics (sequence counter)
 *   overrun if end > the next deadline:
 *     overrun_stop = 1: stop, RT_STATE_OVERRUN_STOP
 *     overrun_stop = 0: count it and skip ahead to the first deadline still
 *                       in the future. The deadlines jumped over are counted
 *                       in skipped_ticks (with a duration, only those before
 *                       its end, so ticks + skipped_ticks = duration / period
 *                       when the duration ends the run) and are NOT
 *                       simulated: the plant advances one step per executed
 *                       tick, so sim time = ticks x period and falls behind
 *                       the wall clock by skipped_ticks x period.
 *
 * Two clocks, on purpose:
 *   - the send schedule and the plant follow the executed ticks k: a message
 *     of cycle c is due when k % div == offset, div = round(c / period) (at
 *     least 1: a cycle shorter than the period is sent every tick). A skipped
 *     deadline delays the due frames by one tick instead of losing them.
 *   - the receive timeouts follow the deadline index n (wall time): a TCU
 *     silent for 10 of its cycle times is timed out however many ticks the
 *     loop skipped. The frames queued meanwhile are drained first and stamped
 *     with the index of the time they were drained at, so a late loop does
 *     not time out a TCU that kept sending.
 *
 * Time scale: cfg.step_s is the simulated time of one tick (the plant step),
 * cfg.period_s the wall-clock time between deadlines. Equal, the run is real
 * time; a longer period runs the same ticks in slow motion (a machine too
 * slow for real time, an emulated test kernel). Everything the bus sees
 * counts ticks, so cycle times and timeouts stretch with the period: the
 * send divisors (rt_tx.c) and the receive timeouts are computed from step_s.
 *
 * Recorder (cfg.record_every > 0): after the step of every record_every-th
 * executed tick, a sample (plant time, maneuver time, all plant outputs, the
 * commands applied) goes into the rec ring; a Python thread writes it to a
 * file. A full ring drops the sample and counts it (rec.dropped).
 *
 * stats.error: the errno of a fatal transport error (> 0), or minus the
 * dct_plant_step status (< 0) when the plant stopped the loop
 * (RT_STATE_ERROR either way); rt_loop_prepare also sets it to minus the
 * dct_plant_init status when it returns -EDOM.
 *
 * The stages, each in a file of its own: the receive drain and timeouts
 * (rt_rx.c), faults (rt_faults.c), the scripted driver (rt_maneuver.c), DAQ
 * (rt_daq.c), calibration and stimulus writes (rt_writes.c), the send
 * (rt_tx.c), the scope (rt_scope.c), the captures (rt_capture.c), the statistics
 * (rt_stats.c); what they
 * share is rt_internal.h. rt_loop_prepare is in rt_prepare.c, with the
 * return codes of both.
 *
 * Concurrency (C11 atomics on the plain fields of rt_loop.h, through
 * pointer casts to _Atomic types of the same size and alignment): stats
 * behind a sequence counter (rt_stats.c), single-producer single-consumer
 * rings (rt_ring.c); stop_request: an atomic int.
 *
 * Nothing in the tick allocates, prints or takes a lock.
 *
 * Python's side of the contract:
 *   - fill plant.params and cfg, then call rt_loop_prepare() BEFORE starting
 *     the bridge and log threads (it resets the rings, which also faults
 *     their pages in); prepare zeroes plant.inputs (dct_plant_init), so the
 *     driver inputs (pedals, road grade, engine_on) are written after it.
 *     While the loop runs Python may write those driver inputs (single
 *     aligned doubles the plant reads every step); the TCU-driven inputs are
 *     overwritten by the loop every tick.
 *   - the SocketCAN socket: created, bound and given its filters by Python;
 *     rt_loop_prepare enables SO_RXQ_OVFL and enlarges the socket buffers
 *     (SO_RCVBUFFORCE / SO_SNDBUFFORCE when allowed, else SO_RCVBUF /
 *     SO_SNDBUF, which the kernel caps at net.core.rmem_max / wmem_max).
 *     Any message-preserving socket carrying struct can_frame datagrams is
 *     accepted (the host tests use an AF_UNIX datagram socket pair).
 *   - rt_loop_run restores the thread's scheduling policy and CPU affinity
 *     when it returns; mlockall stays in force (it is process-wide).
 */
#include "rt_internal.h"

#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <unistd.h>
#include <time.h>

#define RT_STACK_PREFAULT (128 * 1024)
#define RT_NS_PER_S 1000000000LL

void rt_loop_request_stop(rt_loop *l)
{
    atomic_store_explicit(AINT(&l->stop_request), 1, RELEASE);
}

static inline int stop_requested(rt_loop *l)
{
    return atomic_load_explicit(AINT(&l->stop_request), ACQUIRE) != 0;
}

static inline int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * RT_NS_PER_S + ts.tv_nsec;
}

/* the index of the last deadline at or before t_ns (t_ns >= t0_ns) */
static inline uint64_t deadline_index(const rt_run *r, int64_t t_ns)
{
    return (uint64_t)((t_ns - r->t0_ns) / r->period_ns);
}

static inline void sleep_until(int64_t t_ns)
{
    struct timespec ts = {(time_t)(t_ns / RT_NS_PER_S), (long)(t_ns % RT_NS_PER_S)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

/* the cache lines of [p, p + n) requested (prefetch: no fault, no wait) */
static inline void warm(const void *p, size_t n)
{
    const char *c = (const char *)p;
    for (size_t i = 0; i < n; i += 64)
        __builtin_prefetch(c + i, 0, 3);
    if (n)
        __builtin_prefetch(c + n - 1, 0, 3);
}

/* one message's tables: its ct_message, signals, sources or targets, rt_msg */
static inline void warm_message(const rt_channel *ch, int m)
{
    const ct_message *cm = &ch->table.messages[m];
    warm(cm, sizeof *cm);
    warm(&ch->msgs[m], sizeof ch->msgs[m]);
    warm(ch->table.signals + cm->first_signal, cm->n_signals * sizeof(ct_signal));
    if (ch->msgs[m].direction == RT_DIR_TX)
        warm(ch->sources + cm->first_signal, cm->n_signals * sizeof(rt_source));
    else
        warm(ch->targets + cm->first_signal, cm->n_signals * sizeof(rt_target));
}

/* In the early wake-up (spin_us > 0), before the spin to the deadline: the
 * tables tick k will read (the messages due to be sent, every received
 * message's, the rings' heads) are brought into the cache, so that the tick
 * after the deadline does not wait for memory the sleep let go cold. It
 * writes nothing and costs the tick nothing: it runs before the deadline. */
static void warm_tick(const rt_run *r)
{
    const rt_loop *l = r->l;
    for (int i = 0; i < r->n_tx; i++)
        if (r->tx_wait[i] == 0)
            warm_message(&l->chan[r->tx_chan[i]], r->tx_local[i]);
    for (int i = 0; i < r->n_rx; i++)
        warm_message(&l->chan[r->rx_chan[i]], r->rx_local[i]);
    for (int c = 0; c < l->n_channels; c++) {
        warm(&l->chan[c], sizeof l->chan[c]);
        warm(&l->rx[c].head, 2 * sizeof(uint32_t));
        warm(&l->tx[c].head, 2 * sizeof(uint32_t));
        if (l->chan[c].transport == RT_TRANSPORT_RING) /* the next slot the tick may fill */
            __builtin_prefetch(&l->tx[c].frames[l->tx[c].head & (RT_RING_SIZE - 1u)], 1, 3);
    }
    warm(&l->stats, 256); /* the sequence counter and the counts published every tick */
}

/* touches the stack the tick will use, so it does not fault in later */
__attribute__((noinline)) static void prefault_stack(void)
{
    volatile unsigned char buf[RT_STACK_PREFAULT];
    for (size_t i = 0; i < sizeof buf; i += 256)
        buf[i] = 0;
}

/* the whole pages inside [p, p + n) */
static int inner_pages(void *p, size_t n, uintptr_t *lo, uintptr_t *hi)
{
    uintptr_t page = (uintptr_t)sysconf(_SC_PAGESIZE);
    *lo = ((uintptr_t)p + page - 1) & ~(page - 1);
    *hi = ((uintptr_t)p + n) & ~(page - 1);
    return *hi > *lo;
}

/* gives back the pages of a ring's storage that mlockall made resident: the ring was
   never written (zeroed, untouched by this run), so they read as zeros again later */
static void release_storage(void *p, size_t n)
{
    uintptr_t lo, hi;
    if (inner_pages(p, n, &lo, &hi)) {
        (void)munlock((void *)lo, hi - lo);
        (void)madvise((void *)lo, hi - lo, MADV_DONTNEED);
    }
}

/* before the first tick, after mlockall: the rings this run does not use stay out of
   the locked memory (rt_config.release_rings; docs/server.md, "Memory") */
static void release_unused_rings(rt_loop *l)
{
    for (int c = l->n_channels; c < RT_MAX_CHANNELS; c++) {
        release_storage(l->rx[c].frames, sizeof l->rx[c].frames);
        release_storage(l->tx[c].frames, sizeof l->tx[c].frames);
    }
    /* (not when a recording started meanwhile, from another thread) */
    if ((l->cfg.release_rings & RT_RELEASE_LOG) && !l->cfg.log_frames)
        release_storage(l->log.entries, sizeof l->log.entries);
    if ((l->cfg.release_rings & RT_RELEASE_REC) && !l->cfg.record_every)
        release_storage(l->rec.samples, sizeof l->rec.samples);
    if (l->cfg.release_rings & RT_RELEASE_DAQ)
        release_storage(l->daq_ring.dtos, sizeof l->daq_ring.dtos);
    if (l->cfg.release_rings & RT_RELEASE_CAPTURE)
        release_storage(l->capture.records, sizeof l->capture.records);
}

static int hold_storage(void *p, size_t n)
{
    uintptr_t lo, hi;
    if (inner_pages(p, n, &lo, &hi) && mlock((void *)lo, hi - lo) != 0)
        return -errno;
    return 0;
}

int rt_loop_hold_rings(rt_loop *l, uint32_t rings)
{
    int rc = 0;
    if (!l)
        return -EINVAL;
    if (!l->cfg.lock_memory)
        return 0;
    if (rings & RT_RELEASE_LOG)
        rc = rc ? rc : hold_storage(l->log.entries, sizeof l->log.entries);
    if (rings & RT_RELEASE_REC)
        rc = rc ? rc : hold_storage(l->rec.samples, sizeof l->rec.samples);
    if (rings & RT_RELEASE_DAQ)
        rc = rc ? rc : hold_storage(l->daq_ring.dtos, sizeof l->daq_ring.dtos);
    if (rings & RT_RELEASE_CAPTURE)
        rc = rc ? rc : hold_storage(l->capture.records, sizeof l->capture.records);
    return rc;
}

typedef struct {
    int policy_set;
    int old_policy;
    struct sched_param old_param;
    int affinity_set;
    cpu_set_t old_cpus;
} rt_thread_saved;

static void thread_setup(rt_loop *l, rt_thread_saved *sv, int *policy_ok, int *affinity_ok,
                         int *memory_locked)
{
    pthread_t self = pthread_self();
    memset(sv, 0, sizeof *sv);
    *policy_ok = *affinity_ok = *memory_locked = 0;
    rt_stats_publish_phase(l, RT_START_SCHEDULING);
    if (l->cfg.priority > 0 && pthread_getschedparam(self, &sv->old_policy, &sv->old_param) == 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = l->cfg.priority;
        if (pthread_setschedparam(self, SCHED_FIFO, &sp) == 0)
            *policy_ok = sv->policy_set = 1;
    }
    rt_stats_publish_phase(l, RT_START_PINNING);
    if (l->cfg.cpu >= 0 && pthread_getaffinity_np(self, sizeof sv->old_cpus, &sv->old_cpus) == 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(l->cfg.cpu, &set);
        if (pthread_setaffinity_np(self, sizeof set, &set) == 0)
            *affinity_ok = sv->affinity_set = 1;
    }
    rt_stats_publish_phase(l, RT_START_LOCKING_MEMORY);
    if (l->cfg.lock_memory && mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
        *memory_locked = 1;
        release_unused_rings(l);
    }
    rt_stats_publish_phase(l, RT_START_PREFAULTING);
    prefault_stack();
}

static void thread_restore(const rt_thread_saved *sv)
{
    pthread_t self = pthread_self();
    if (sv->policy_set)
        (void)pthread_setschedparam(self, sv->old_policy, &sv->old_param);
    if (sv->affinity_set)
        (void)pthread_setaffinity_np(self, sizeof sv->old_cpus, &sv->old_cpus);
}

RT_TICK_CODE
int rt_loop_run(rt_loop *l)
{
    /* not prepared, or already run since rt_loop_prepare */
    if (!l || atomic_load_explicit(AINT(&l->stats.state), RELAXED) != RT_STATE_IDLE ||
        !(l->cfg.period_s >= RT_PERIOD_MIN_S && l->cfg.period_s <= RT_PERIOD_MAX_S) ||
        l->stats.n_channels < 1 || l->stats.n_channels != l->n_channels)
        return -EINVAL;

    rt_run r;
    memset(&r, 0, sizeof r);
    r.l = l;
    r.period_ns = llround(l->cfg.period_s * 1e9);
    r.step_ns = llround(l->plant.params.solver.step_s * 1e9);
    r.maneuver_state = l->stats.maneuver_state;
    r.maneuver_time_s = -1.0;
    r.maneuver_seq = atomic_load_explicit(A32(&l->maneuver_ack), ACQUIRE);
    r.scope.gen = atomic_load_explicit(A32(&l->scope_ack), ACQUIRE);
    r.capture.gen = atomic_load_explicit(A32(&l->capture_ack), ACQUIRE);
    r.spin_ns = llround(l->cfg.spin_us * 1e3);
    rt_tx_plan(&r);
    rt_rx_plan(&r);
    static const double event_s[RT_N_EVENTS] = {0.0, 0.010, 0.100};
    for (int e = 0; e < RT_N_EVENTS; e++) {
        double ticks = event_s[e] * 1e9 / (double)r.step_ns;
        r.ev_div[e] = ticks < 1.5 ? 1u : (uint32_t)llround(ticks);
        r.ev_wait[e] = 0;             /* every event fires at the first tick */
    }
    memcpy(r.cmd, l->stats.commands, sizeof r.cmd);
    memcpy(r.c.msgs, l->stats.msgs, sizeof r.c.msgs);

    uint64_t limit = 0; /* deadlines to run, 0: until stopped */
    if (l->cfg.duration_s > 0.0 && isfinite(l->cfg.duration_s)) {
        double d = l->cfg.duration_s / l->cfg.period_s;
        limit = d >= 1.0 ? (uint64_t)llround(d) : 1u;
    }

    rt_thread_saved saved;
    int policy_ok, affinity_ok, memory_locked;
    thread_setup(l, &saved, &policy_ok, &affinity_ok, &memory_locked);
    stats_write_begin(&l->stats);
    l->stats.rt_policy_ok = policy_ok;
    l->stats.affinity_ok = affinity_ok;
    l->stats.memory_locked = memory_locked;
    l->stats.state = RT_STATE_RUNNING;
    l->stats.startup_phase = RT_START_READY;
    r.t0_ns = now_ns() + r.period_ns;
    l->stats.t0_ns = r.t0_ns;
    stats_write_end(&l->stats);

    int state = RT_STATE_STOPPED, error = 0;
    double final_sim_state = RT_SIM_STOPPING;
    uint64_t n = 0; /* deadline index */
    for (;;) {
        if (stop_requested(l) || (limit && n >= limit))
            break;
        int64_t deadline = r.t0_ns + (int64_t)n * r.period_ns;
        int64_t wake_at = deadline - r.spin_ns;
        sleep_until(wake_at);
        int64_t wake = now_ns();
        int64_t start = wake;
        /* early wake-up: warm the tick's tables, then spin the rest of the
         * way so that the OS wake-up latency (up to spin_us) does not reach
         * the tick */
        if (r.spin_ns > 0 && wake < deadline)
            warm_tick(&r);
        while (start < deadline)
            start = now_ns();
        if (stop_requested(l))
            break;
        r.time_s = (double)(deadline - r.t0_ns) / 1e9;
        /* the receive clock: the deadline index of now, not of this tick. A tick
         * woken late (the thread held) drains what the TCU sent meanwhile; stamped
         * with its own n they would look as old as the lateness once the ticks
         * missed are skipped, and the next tick would time out a TCU that kept
         * sending */
        uint64_t rx_n = deadline_index(&r, start);
        if (rx_n < n)
            rx_n = n;

        int err = 0;
        for (int c = 0; c < l->n_channels && !err; c++)
            err = rt_rx_drain(&r, c, rx_n);
        if (err) {
            state = RT_STATE_ERROR;
            error = err;
            final_sim_state = -1.0;
            break;
        }
        rt_rx_timeouts(&r, rx_n);
        /* faults: nothing set and no command queued costs two loads */
        int fc = r.f.n_used || atomic_load_explicit(A32(&l->fault_cmds.head), ACQUIRE) !=
                                   atomic_load_explicit(A32(&l->fault_cmds.tail), RELAXED)
                     ? rtf_tick(&r.f, l, r.cmd, r.maneuver_time_s) : 0;
        if (fc) {
            r.faults_dirty = 1;
            if (fc & RTF_CYCLES_CHANGED)
                rt_tx_replan(&r);
        }
        rt_drive(&r);
        rt_daq_pickup(&r);
        rt_apply_writes(l, &l->cal, 0);
        rt_apply_writes(l, &l->stim, 1);
        apply_commands(l, r.cmd);
        int st = dct_plant_step(&l->plant, 1);
        if (st != DCT_OK) {
            state = RT_STATE_ERROR;
            error = -st;
            final_sim_state = RT_SIM_FAULT;
            break;
        }
        if (r.maneuver_state == RT_MANEUVER_RUNNING)
            r.maneuver_time_s = l->plant.state.time_s - r.maneuver_t0_s;
        int record_every = atomic_load_explicit(AINT(&l->cfg.record_every), RELAXED);
        if (record_every > 0 && r.c.ticks % (uint64_t)record_every == 0)
            rec_push(&l->rec, r.c.ticks, l->plant.state.time_s, r.maneuver_time_s,
                     &l->plant.outputs, r.cmd, l->n_commands, r.f.mask);
        err = rt_tx_tick(&r);
        r.c.ticks++;
        if (err) {
            state = RT_STATE_ERROR;
            error = err;
            final_sim_state = -1.0;
            break;
        }
        int maneuver_done = r.maneuver_state == RT_MANEUVER_RUNNING && l->driver.end_s > 0.0 &&
                            r.maneuver_time_s >= l->driver.end_s - 0.5 * (double)r.step_ns * 1e-9;
        if (maneuver_done)
            r.maneuver_state = RT_MANEUVER_DONE;
        rt_daq_copy(&r, deadline, r.c.ticks - 1u);
        rts_tick(&r.scope, l, r.c.ticks - 1u, l->plant.state.time_s);
        rtc_tick(&r.capture, l, r.cmd, r.c.ticks - 1u, l->plant.state.time_s);

        int64_t end = now_ns();
        double turnaround_us = (double)(end - deadline) / 1e3;
        double exec_us = (double)(end - start) / 1e3;
        double latency_us = (double)(wake - wake_at) / 1e3; /* the OS's, as cyclictest measures it */
        if (turnaround_us > r.c.turnaround_max_us)
            r.c.turnaround_max_us = turnaround_us;
        if (exec_us > r.c.exec_max_us)
            r.c.exec_max_us = exec_us;
        if (latency_us > r.c.latency_max_us)
            r.c.latency_max_us = latency_us;
        uint64_t next = n + 1;
        int overrun = end > deadline + r.period_ns;
        if (overrun) {
            r.c.overruns++;
            if (!l->cfg.overrun_stop) {
                /* the first deadline after the end of this tick */
                next = deadline_index(&r, end) + 1u;
                if (limit && next > limit)
                    next = limit; /* only deadlines of the run count as skipped */
                r.c.skipped_ticks += next - (n + 1);
            }
        }
        rt_stats_publish_tick(&r, turnaround_us, exec_us, latency_us);
        if (maneuver_done && !l->driver.keep_running)
            break;
        if (overrun && l->cfg.overrun_stop) {
            state = RT_STATE_OVERRUN_STOP;
            final_sim_state = RT_SIM_FAULT;
            break;
        }
        n = next;
    }

    if (final_sim_state >= 0.0)
        rt_tx_final(&r, final_sim_state);
    rt_stats_publish_state(&r, state, error);
    thread_restore(&saved);
    return state;
}
