/*
 * rt_internal.h - what the loop's source files share (private to the loop;
 * the contract with Python is rt_loop.h, the only one of these headers cffi
 * reads besides rt_floor.h).
 *
 * The loop, one component a file:
 *   rt_loop.c      the tick and rt_loop_run: deadlines, the thread, the order
 *                  of a tick's stages
 *   rt_prepare.c   rt_loop_prepare: the configuration, the channel tables and
 *                  the sockets checked, the loop reset for a run
 *   rt_rx.c        receiving: each channel's drain, a frame's classification
 *                  and decoding into command values, the receive timeouts
 *   rt_tx.c        sending: the send plan (divisors, offsets), the frames due
 *                  at a tick encoded and protected, the send
 *   rt_ring.c      the single-producer single-consumer rings
 *   rt_stats.c     the statistics: the sequence counter, the counts and
 *                  histograms published every tick
 *   rt_writes.c    calibration and stimulus writes into the writable regions
 *   rt_daq.c       XCP DAQ: the lists' configuration taken, their ODTs copied
 *                  into the DAQ ring at the end of a tick
 *   rt_maneuver.c  the scripted driver (a pedal table played in the tick) and
 *                  its start and stop commands
 *   rt_faults.c, rt_scope.c, rt_capture.c, rt_floor.c: failure simulation, the scope,
 *   the captures, the
 *                  machine's wake-up floor (their own headers)
 *   rt_xcp_send.c  not the tick's: the XCP slave's sender thread, the DAQ
 *                  ring's consumer (rt_xcp_send.h, read by cffi too)
 *
 * The tick calls each stage once (the functions at the end, hidden in the
 * extension: direct calls, no PLT); what a stage calls per frame or per
 * signal is static inline, here or in the stage's own file, so the stages'
 * inner loops make no call across files.
 */
#ifndef RT_INTERNAL_H
#define RT_INTERNAL_H

#ifndef _GNU_SOURCE
#define _GNU_SOURCE /* recvmmsg, sendmmsg, CPU_SET, pthread_*affinity_np */
#endif

#include "rt_loop.h"
#include "rt_faults.h"
#include "rt_capture.h"
#include "rt_scope.h"

#include <math.h>
#include <stdatomic.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/uio.h>

#include <linux/can.h>

#define RT_PERIOD_MIN_S 50e-6
#define RT_PERIOD_MAX_S 0.1           /* a slowed-down run: step_s / period_s down to 1/2000 */
#define RT_RX_BATCH 64                  /* frames per recvmmsg / ring pop */
#define RT_SIM_STARTING 0.0
#define RT_SIM_RUNNING 1.0
#define RT_SIM_STOPPING 2.0
#define RT_SIM_FAULT 3.0

_Static_assert(sizeof(_Atomic uint32_t) == sizeof(uint32_t) &&
                   _Alignof(_Atomic uint32_t) == _Alignof(uint32_t),
               "atomic uint32_t must have the layout of uint32_t");
_Static_assert(sizeof(_Atomic uint64_t) == sizeof(uint64_t) &&
                   _Alignof(_Atomic uint64_t) == _Alignof(uint64_t),
               "atomic uint64_t must have the layout of uint64_t");
_Static_assert(sizeof(_Atomic int) == sizeof(int) && _Alignof(_Atomic int) == _Alignof(int),
               "atomic int must have the layout of int");

#define A32(p) ((_Atomic uint32_t *)(void *)(p))
#define A64(p) ((_Atomic uint64_t *)(void *)(p))
#define AINT(p) ((_Atomic int *)(void *)(p))
#define RELAXED memory_order_relaxed
#define ACQUIRE memory_order_acquire
#define RELEASE memory_order_release

/* ------------------------------------------------------------------ */
/* The rings' code (their functions: rt_ring.c), the loop's producers  */
/* ------------------------------------------------------------------ */

/* dropped is written by the producer only */
static inline void count_dropped(uint64_t *dropped, uint64_t n)
{
    atomic_store_explicit(A64(dropped), atomic_load_explicit(A64(dropped), RELAXED) + n, RELAXED);
}

/* The producer's side of each single-producer single-consumer ring: copies
 * up to n entries in, then publishes them; what does not fit is counted in
 * dropped; returns how many went in. */
#define RT_DEFINE_PUSH_MANY(linkage, fn, ring_t, entry_t, items, size)          \
    linkage int fn(ring_t *r, const entry_t *in, int n)                         \
    {                                                                           \
        if (n <= 0)                                                             \
            return 0;                                                           \
        uint32_t head = atomic_load_explicit(A32(&r->head), RELAXED);           \
        uint32_t tail = atomic_load_explicit(A32(&r->tail), ACQUIRE);           \
        uint32_t space = (size) - (head - tail);                                \
        uint32_t k = (uint32_t)n < space ? (uint32_t)n : space;                 \
        for (uint32_t i = 0; i < k; i++)                                        \
            r->items[(head + i) & ((size) - 1u)] = in[i];                       \
        atomic_store_explicit(A32(&r->head), head + k, RELEASE);                \
        if (k < (uint32_t)n)                                                    \
            count_dropped(&r->dropped, (uint64_t)n - k);                        \
        return (int)k;                                                          \
    }

/* The consumer's side of each single-producer single-consumer ring: copies
 * up to n entries out, then frees their slots; returns how many. */
#define RT_DEFINE_POP_MANY(linkage, fn, ring_t, entry_t, items, size)           \
    linkage int fn(ring_t *r, entry_t *out, int n)                              \
    {                                                                           \
        if (n <= 0)                                                             \
            return 0;                                                           \
        uint32_t tail = atomic_load_explicit(A32(&r->tail), RELAXED);           \
        uint32_t head = atomic_load_explicit(A32(&r->head), ACQUIRE);           \
        uint32_t avail = head - tail;                                           \
        uint32_t k = (uint32_t)n < avail ? (uint32_t)n : avail;                 \
        for (uint32_t i = 0; i < k; i++)                                        \
            out[i] = r->items[(tail + i) & ((size) - 1u)];                      \
        atomic_store_explicit(A32(&r->tail), tail + k, RELEASE);                \
        return (int)k;                                                          \
    }

/* the frame rings as the tick uses them (the same code as rt_ring_pop_many
 * and rt_ring_push_many, without a call) */
RT_DEFINE_POP_MANY(static inline, rt_frames_pop, rt_ring, rt_frame, frames, RT_RING_SIZE)
RT_DEFINE_PUSH_MANY(static inline, rt_frames_push, rt_ring, rt_frame, frames, RT_RING_SIZE)

/* a single producer's next free slot: 1 and *head set, or 0 when the ring
 * is full (counted in dropped); the entry is published by storing head + 1
 * (release) */
static inline int ring_slot(uint32_t *head_p, uint32_t *tail_p, uint32_t size, uint64_t *dropped,
                            uint32_t *head)
{
    *head = atomic_load_explicit(A32(head_p), RELAXED);
    uint32_t tail = atomic_load_explicit(A32(tail_p), ACQUIRE);
    if (*head - tail >= size) {
        count_dropped(dropped, 1);
        return 0;
    }
    return 1;
}

/* the loop is the log's only producer */
static inline void log_push(rt_log_ring *g, double time_s, uint32_t dir, const rt_frame *f)
{
    uint32_t head;
    if (!ring_slot(&g->head, &g->tail, RT_LOG_SIZE, &g->dropped, &head))
        return;
    rt_log_entry *e = &g->entries[head & (RT_LOG_SIZE - 1u)];
    e->time_s = time_s;
    e->dir = dir;
    e->frame = *f;
    if (e->frame.len > CT_MAX_LENGTH)
        e->frame.len = CT_MAX_LENGTH;
    atomic_store_explicit(A32(&g->head), head + 1, RELEASE);
}

static inline void rec_push(rt_rec_ring *g, uint64_t tick, double time_s, double maneuver_time_s,
                            const dct_outputs *o, const double *commands, int n_commands,
                            uint64_t fault_mask)
{
    uint32_t head;
    if (!ring_slot(&g->head, &g->tail, RT_REC_SIZE, &g->dropped, &head))
        return;
    rt_sample *e = &g->samples[head & (RT_REC_SIZE - 1u)];
    memcpy(e->commands, commands, (size_t)n_commands * sizeof *commands);
    e->tick = tick;
    e->time_s = time_s;
    e->maneuver_time_s = maneuver_time_s;
    e->outputs = *o;
    e->fault_mask = fault_mask;
    atomic_store_explicit(A32(&g->head), head + 1, RELEASE);
}

/* ------------------------------------------------------------------ */
/* The statistics' writer (the sequence counter: rt_stats.c)           */
/* ------------------------------------------------------------------ */

static inline void stats_write_begin(rt_stats *s)
{
    uint32_t q = atomic_load_explicit(A32(&s->seq), RELAXED);
    atomic_store_explicit(A32(&s->seq), q + 1u, RELAXED);
    atomic_thread_fence(RELEASE);
}

static inline void stats_write_end(rt_stats *s)
{
    uint32_t q = atomic_load_explicit(A32(&s->seq), RELAXED);
    atomic_store_explicit(A32(&s->seq), q + 1u, RELEASE);
}

/* ------------------------------------------------------------------ */
/* A run's state                                                       */
/* ------------------------------------------------------------------ */

typedef struct {
    uint64_t ticks, overruns, skipped_ticks;
    double turnaround_max_us, exec_max_us, latency_max_us;
    rt_chan_stats chan[RT_MAX_CHANNELS];
    rt_msg_stats msgs[RT_MAX_MESSAGES];
} rt_counts;

typedef struct {
    _Alignas(struct cmsghdr) unsigned char bytes[CMSG_SPACE(sizeof(uint32_t)) + 64]; /* and a timestamp */
} rt_cmsg_buf;

typedef struct {
    rt_loop *l;
    int64_t period_ns;               /* wall clock between deadlines */
    int64_t step_ns;                 /* simulated time per tick */
    int64_t spin_ns;                 /* early wake-up before each deadline */
    int64_t t0_ns;                   /* first deadline */
    int n_tx;                        /* sent messages, in the order of tx_chan/tx_msg */
    uint8_t tx_chan[RT_MAX_MESSAGES];
    uint8_t tx_local[RT_MAX_MESSAGES];  /* index in its channel's table */
    uint32_t tx_div[RT_MAX_MESSAGES];
    uint32_t tx_div_plan[RT_MAX_MESSAGES];  /* tx_div as planned (a cycle fault changes tx_div) */
    uint32_t tx_off[RT_MAX_MESSAGES];
    uint32_t tx_wait[RT_MAX_MESSAGES];  /* executed ticks until it is due (0: this tick):
                                           k % div == off without a division per tick */
    int n_rx;                        /* received messages */
    uint8_t rx_chan[RT_MAX_MESSAGES];
    uint8_t rx_local[RT_MAX_MESSAGES];
    uint64_t rx_timeout_ticks[RT_MAX_MESSAGES];  /* by loop-wide message index */
    uint32_t ovfl_last[RT_MAX_CHANNELS];  /* last SO_RXQ_OVFL drop count seen */
    uint64_t ovfl_total[RT_MAX_CHANNELS];
    int tcu_heard;                   /* a frame of a received message was accepted */
    int maneuver_state;              /* RT_MANEUVER_* */
    double maneuver_t0_s;            /* plant time at which the maneuver started */
    double maneuver_time_s;          /* after this tick's step; < 0 before the start */
    double time_s;                   /* deadline of this tick since t0 */
    rt_counts c;
    double cmd[RT_MAX_COMMANDS];
    double status[RT_N_STATUS];
    /* messages whose counts changed since the last publication */
    int n_dirty;
    int32_t dirty[RT_MAX_MESSAGES];
    uint8_t is_dirty[RT_MAX_MESSAGES];
    /* one message's signal values */
    double values[RT_MAX_MSG_SIGNALS];
    uint8_t written[RT_MAX_MSG_SIGNALS];
    /* SocketCAN batches (struct canfd_frame holds a classic frame too) */
    struct canfd_frame rx_cf[RT_RX_BATCH];
    struct iovec rx_iov[RT_RX_BATCH];
    struct mmsghdr rx_msg[RT_RX_BATCH];
    rt_cmsg_buf rx_ctrl[RT_RX_BATCH];
    struct canfd_frame tx_cf[RT_MAX_MESSAGES];
    struct iovec tx_iov[RT_MAX_MESSAGES];
    struct mmsghdr tx_msg[RT_MAX_MESSAGES];
    /* frames of this tick */
    rt_frame rx_frames[RT_RX_BATCH];
    rt_frame tx_frames[RT_MAX_MESSAGES];
    int32_t tx_frame_msg[RT_MAX_MESSAGES];  /* loop-wide message index of each tx frame */
    /* DAQ */
    const rt_daq_config *daq;        /* the configuration in use, NULL: none */
    uint32_t daq_gen;                /* its generation (the last one looked at) */
    uint32_t ev_div[RT_N_EVENTS];    /* ticks between an event's firings */
    uint32_t ev_wait[RT_N_EVENTS];   /* ticks until it fires (0: this tick) */
    uint16_t daq_pre[RT_DAQ_MAX_LISTS];  /* prescaler countdown of each list */
    /* failure simulation */
    rt_fault_run f;
    int faults_dirty;                /* a fault changed since the last publication */
    /* the scope */
    rt_scope_run scope;
    /* captures */
    rt_capture_run capture;
    /* maneuver commands */
    uint32_t maneuver_seq;           /* the last command sequence taken */
} rt_run;

/* ------------------------------------------------------------------ */
/* Helpers of the stages' inner loops                                  */
/* ------------------------------------------------------------------ */

static inline void mark(rt_run *r, int g)
{
    if (!r->is_dirty[g]) {
        r->is_dirty[g] = 1;
        r->dirty[r->n_dirty++] = g;
    }
}

/* the value table's entry for x (see rt_lookup) */
static inline double lookup(const rt_lookup *t, const rt_range *ranges, double x)
{
    if (!isfinite(x))
        return t->fallback;
    double key = rint(x); /* half to even, as Python's round() */
    const rt_range *g = ranges + t->first;
    for (uint32_t i = 0; i < t->count; i++)
        if (key >= g[i].lo && key <= g[i].hi)
            return g[i].value;
    return t->fallback;
}

static inline void apply_commands(rt_loop *l, const double *cmd)
{
    double *in = (double *)(void *)&l->plant.inputs;
    for (int i = 0; i < l->n_commands; i++)
        if (l->command_input[i] >= 0)
            in[l->command_input[i]] = cmd[i];
}

/* ------------------------------------------------------------------ */
/* The stages                                                          */
/* ------------------------------------------------------------------ */

/* the code a tick runs, kept together in the extension: the linker groups
 * the .text.hot sections of every object file, so that a tick after its
 * sleep touches as few code pages as when the loop was one file */
#define RT_TICK_CODE __attribute__((section(".text.hot.rt_tick")))

#pragma GCC visibility push(hidden)

/* rt_rx.c */
void rt_rx_plan(rt_run *r);
int rt_rx_drain(rt_run *r, int c, uint64_t n);
void rt_rx_timeouts(rt_run *r, uint64_t n);
void rt_safe_values(const rt_loop *l, const rt_channel *ch, int m, double *cmd);

/* rt_tx.c */
void rt_tx_plan(rt_run *r);
void rt_tx_replan(rt_run *r);
int rt_tx_tick(rt_run *r);
void rt_tx_final(rt_run *r, double state);

/* rt_stats.c */
void rt_stats_publish_tick(rt_run *r, double turnaround_us, double exec_us, double latency_us);
void rt_stats_publish_state(rt_run *r, int state, int error);
void rt_stats_publish_phase(rt_loop *l, int phase);

/* rt_writes.c */
void rt_apply_writes(rt_loop *l, rt_write_ring *ring, int timed);

/* rt_daq.c */
void rt_daq_pickup(rt_run *r);
void rt_daq_copy(rt_run *r, int64_t deadline_ns, uint64_t tick);

/* rt_maneuver.c */
int rt_driver_check(const rt_driver *d);
void rt_driver_fixed_inputs(rt_loop *l, const rt_driver *d);
void rt_drive(rt_run *r);

#pragma GCC visibility pop

#endif
