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
 *     last_rx_tick = n and ends a timeout of its message
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
 *     loop skipped. The frames queued meanwhile are drained first, so a late
 *     loop does not time out a TCU that kept sending.
 *
 * Time scale: cfg.step_s is the simulated time of one tick (the plant step),
 * cfg.period_s the wall-clock time between deadlines. Equal, the run is real
 * time; a longer period runs the same ticks in slow motion (a machine too
 * slow for real time, an emulated test kernel). Everything the bus sees
 * counts ticks, so cycle times and timeouts stretch with the period: the
 * divisors below and the receive timeouts are computed from step_s.
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
 *
 * Recorder (cfg.record_every > 0): after the step of every record_every-th
 * executed tick, a sample (plant time, maneuver time, all plant outputs, the
 * commands applied) goes into the rec ring; a Python thread writes it to a
 * file. A full ring drops the sample and counts it (rec.dropped).
 *
 * Offsets: computed once at the start of rt_loop_run over the sent messages
 * of all channels, shortest cycle first; each message takes the offset whose
 * ticks it shares with the fewest frames already planned (two messages of
 * divisors a and b with offsets x and y meet when x = y mod gcd(a, b)). With
 * the project's own contract at 2 kHz the three 2 ms messages go to ticks
 * 0, 1, 2 (mod 4), the three 10 ms ones to 3, 7, 11 (mod 20) and SIM_Status
 * to 15 (mod 200): at most one frame per tick.
 *
 * End-to-end: an accepted frame updates the message's counter state
 * (ct_check); when a message times out its counter state is reset to -1, so
 * the first frame after the TCU comes back is accepted whatever its counter
 * (as at start). A sent message's counter is the number of frames made so
 * far (a 64-bit count) modulo the protection's counter range; toggles and
 * counter sources count the same frames.
 *
 * Status sources (RT_STATUS_*): sim_state is 0 until the first frame of a
 * received message is accepted, then 1; when the loop ends, one last frame
 * of every sent message with final_frame (those carrying sim_state) goes out
 * with 2 (stopped by request or duration) or 3 (overrun stop, plant error);
 * none after a transport error.
 *
 * Values: a received signal's command value is gain * signal + bias, or its
 * value table's entry, limited to [minimum, maximum]; a NaN (a float signal)
 * gives the safe value. A command value drives the plant input
 * command_input[i] every tick (or only the recording, -1); at prepare and
 * while its message is timed out it holds the target's safe value.
 *
 * Return codes: rt_loop_prepare gives -EINVAL (a cfg field out of range:
 * period outside 50 us .. 100 ms, a step outside 50 us .. 10 ms or longer
 * than the period, a negative record_every, a driver table with more than
 * RT_DRIVER_ROWS rows, times not increasing, pedals outside 0..100 %, a
 * selector code other than P, R, N, D or a grade outside -40..40 %,
 * priority outside 0..99, cpu < -1, NaN duration; channel tables missing,
 * too many messages or commands, an unknown transport, source, target,
 * output, status or input index, a value table outside the ranges, a cycle
 * time that is not a positive number, min above max, a CAN FD message on a
 * SocketCAN channel without fd_frames), -EBADF (fd < 0), -ENOTSOCK /
 * -EPROTOTYPE (fd not
 * a datagram socket), another -errno (SO_RXQ_OVFL refused) or -EDOM (the
 * plant rejected its parameters). rt_loop_run gives -EINVAL when the loop
 * was not prepared since its last run (stats.state is not RT_STATE_IDLE, or
 * its last rt_loop_prepare failed: stats.n_channels is then 0),
 * else the final state. A duration <= 0 or infinite runs until
 * rt_loop_request_stop().
 *
 * Lost frames: rx_overflow is, for SocketCAN, the kernel's drop count of the
 * socket (SO_RXQ_OVFL); the kernel reports it with the next frame received,
 * so drops show up when the next frame arrives. For the ring transport it is
 * the channel's rx ring's dropped (pushes the bridge could not make).
 * tx_dropped counts sends
 * refused with EAGAIN / ENOBUFS or by a full tx ring; the loop never blocks
 * on a send, and the AliveCounter still advances, so the TCU sees the gap.
 *
 * stats.error: the errno of a fatal transport error (> 0), or minus the
 * dct_plant_step status (< 0) when the plant stopped the loop
 * (RT_STATE_ERROR either way); rt_loop_prepare also sets it to minus the
 * dct_plant_init status when it returns -EDOM.
 *
 * Frames are counted once each, per channel (stats.chan; the rt_stats
 * totals are their sums): rx_frames = rx_accepted + rx_unknown_id +
 * rx_bad_length + rx_bad_crc + rx_bad_counter; per received message
 * (stats.msgs) accepted frames, rejections by reason, timeouts; per sent
 * message frames sent and dropped. A frame is an unknown id if its id has
 * the error flag (SocketCAN's CAN_ERR_FLAG, also in the rings' frames) or is
 * not a message the channel receives (identifier and its 11/29-bit format);
 * a received message's frame with the RTR flag, the wrong format (classic /
 * CAN FD) or not the DBC's length is a bad length. stats.msgs is published
 * only for the messages whose counts changed in a tick.
 *
 * Concurrency (C11 atomics on the plain fields of rt_loop.h, through
 * pointer casts to _Atomic types of the same size and alignment):
 *   - stats: one writer (the loop), a sequence counter. The writer makes seq
 *     odd, fences (release), writes, then makes seq even (release store).
 *     rt_stats_read loads seq (acquire), copies, fences (acquire), loads seq
 *     again and keeps the copy when both are equal and even. The loop never
 *     waits for a reader. The loop works on local copies and publishes them
 *     once per tick in a short write section.
 *   - rings: single producer, single consumer; head is written by the
 *     producer (release) and read by the consumer (acquire), tail the other
 *     way round; indices run freely over uint32_t, masked by the power-of-two
 *     size. A full ring refuses the push and counts it in dropped (written by
 *     the producer only). Rings: rx (producer: the bridge thread, consumer:
 *     the loop), tx and log (producer: the loop, consumer: a Python thread).
 *   - stop_request: an atomic int.
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
#ifndef _GNU_SOURCE
#define _GNU_SOURCE /* recvmmsg, sendmmsg, CPU_SET, pthread_*affinity_np */
#endif

#include "rt_loop.h"
#include "rt_faults.h"
#include "rt_scope.h"

#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <time.h>

#include <linux/can.h>

#define RT_STEP_MIN_S 50e-6
#define RT_STEP_MAX_S 10e-3
#define RT_PERIOD_MIN_S 50e-6
#define RT_PERIOD_MAX_S 0.1           /* a slowed-down run: step_s / period_s down to 1/2000 */
#define RT_PRIORITY_MAX 99
#define RT_RX_BATCH 64                  /* frames per recvmmsg / ring pop */
#define RT_RX_MAX_PER_TICK 256          /* drained per tick at most */
#define RT_STACK_PREFAULT (128 * 1024)
#define RT_READ_RETRIES 1000            /* a copy is tried at least this often ... */
#define RT_READ_BUDGET_NS 2000000000LL  /* ... and for at least this long (a starved reader) */
#define RT_RCVBUF_BYTES (8 * 1024 * 1024)
#define RT_SNDBUF_BYTES (1024 * 1024)
#define RT_NS_PER_S 1000000000LL
#define RT_SIM_STARTING 0.0
#define RT_SIM_RUNNING 1.0
#define RT_SIM_STOPPING 2.0
#define RT_SIM_FAULT 3.0

_Static_assert((RT_RING_SIZE & (RT_RING_SIZE - 1)) == 0, "RT_RING_SIZE must be a power of two");
_Static_assert((RT_LOG_SIZE & (RT_LOG_SIZE - 1)) == 0, "RT_LOG_SIZE must be a power of two");
_Static_assert((RT_REC_SIZE & (RT_REC_SIZE - 1)) == 0, "RT_REC_SIZE must be a power of two");
_Static_assert((RT_DAQ_RING_SIZE & (RT_DAQ_RING_SIZE - 1)) == 0, "RT_DAQ_RING_SIZE: a power of two");
_Static_assert((RT_WRITE_RING_SIZE & (RT_WRITE_RING_SIZE - 1)) == 0,
               "RT_WRITE_RING_SIZE must be a power of two");
_Static_assert(sizeof(rt_loop) < 0xFFFFFFFFu, "offsets into rt_loop must fit 32 bits");
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
/* Rings                                                               */
/* ------------------------------------------------------------------ */

/* dropped is written by the producer only */
static inline void count_dropped(uint64_t *dropped, uint64_t n)
{
    atomic_store_explicit(A64(dropped), atomic_load_explicit(A64(dropped), RELAXED) + n, RELAXED);
}

/* The producer's side of each single-producer single-consumer ring: copies
 * up to n entries in, then publishes them; what does not fit is counted in
 * dropped; returns how many went in. */
#define RT_DEFINE_PUSH_MANY(fn, ring_t, entry_t, items, size)                     \
    int fn(ring_t *r, const entry_t *in, int n)                                 \
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

RT_DEFINE_PUSH_MANY(rt_ring_push_many, rt_ring, rt_frame, frames, RT_RING_SIZE)
RT_DEFINE_PUSH_MANY(rt_write_push_many, rt_write_ring, rt_write, writes, RT_WRITE_RING_SIZE)
RT_DEFINE_PUSH_MANY(rt_fault_push_many, rt_fault_cmd_ring, rt_fault_cmd, cmds,
                    RT_FAULT_CMD_RING_SIZE)

/* The consumer's side of each single-producer single-consumer ring: copies
 * up to n entries out, then frees their slots; returns how many. */
#define RT_DEFINE_POP_MANY(fn, ring_t, entry_t, items, size)                      \
    int fn(ring_t *r, entry_t *out, int n)                                      \
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

RT_DEFINE_POP_MANY(rt_ring_pop_many, rt_ring, rt_frame, frames, RT_RING_SIZE)
RT_DEFINE_POP_MANY(rt_log_pop_many, rt_log_ring, rt_log_entry, entries, RT_LOG_SIZE)
RT_DEFINE_POP_MANY(rt_rec_pop_many, rt_rec_ring, rt_sample, samples, RT_REC_SIZE)
RT_DEFINE_POP_MANY(rt_daq_pop_many, rt_daq_ring, rt_dto, dtos, RT_DAQ_RING_SIZE)
RT_DEFINE_POP_MANY(rt_fault_events_pop_many, rt_fault_event_ring, rt_fault_event, events,
                   RT_FAULT_EVENT_RING_SIZE)
RT_DEFINE_POP_MANY(rt_scope_pop_many, rt_scope_ring, rt_scope_bucket, buckets,
                   RT_SCOPE_RING_SIZE)

int rt_ring_push(rt_ring *r, const rt_frame *f)
{
    return rt_ring_push_many(r, f, 1) == 1 ? 0 : -1;
}

int rt_ring_pop(rt_ring *r, rt_frame *f)
{
    return rt_ring_pop_many(r, f, 1) == 1 ? 0 : -1;
}

/* the loop is the log's only producer */
static inline void log_push(rt_log_ring *g, double time_s, uint32_t dir, const rt_frame *f)
{
    uint32_t head = atomic_load_explicit(A32(&g->head), RELAXED);
    uint32_t tail = atomic_load_explicit(A32(&g->tail), ACQUIRE);
    if (head - tail >= RT_LOG_SIZE) {
        count_dropped(&g->dropped, 1);
        return;
    }
    rt_log_entry *e = &g->entries[head & (RT_LOG_SIZE - 1u)];
    e->time_s = time_s;
    e->dir = dir;
    e->frame = *f;
    if (e->frame.len > CT_MAX_LENGTH)
        e->frame.len = CT_MAX_LENGTH;
    atomic_store_explicit(A32(&g->head), head + 1, RELEASE);
}

int rt_log_pop(rt_log_ring *r, rt_log_entry *e)
{
    return rt_log_pop_many(r, e, 1) == 1 ? 0 : -1;
}

static inline void rec_push(rt_rec_ring *g, uint64_t tick, double time_s, double maneuver_time_s,
                            const dct_outputs *o, const double *commands, int n_commands,
                            uint64_t fault_mask)
{
    uint32_t head = atomic_load_explicit(A32(&g->head), RELAXED);
    uint32_t tail = atomic_load_explicit(A32(&g->tail), ACQUIRE);
    if (head - tail >= RT_REC_SIZE) {
        count_dropped(&g->dropped, 1);
        return;
    }
    rt_sample *e = &g->samples[head & (RT_REC_SIZE - 1u)];
    e->tick = tick;
    e->time_s = time_s;
    e->maneuver_time_s = maneuver_time_s;
    e->outputs = *o;
    memcpy(e->commands, commands, (size_t)n_commands * sizeof *commands);
    e->fault_mask = fault_mask;
    atomic_store_explicit(A32(&g->head), head + 1, RELEASE);
}


/* ------------------------------------------------------------------ */
/* Statistics: sequence counter                                        */
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

/* A reader the host starves (its copy of ~130 kB outlasting a tick again and
 * again) keeps trying for RT_READ_BUDGET_NS, not just RT_READ_RETRIES times:
 * a few hundred torn copies in a row are seen on a loaded shared host. */
int rt_stats_read(rt_loop *l, rt_stats *copy)
{
    struct timespec t0;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (long attempt = 0;; attempt++) {
        if (attempt >= RT_READ_RETRIES) {
            struct timespec t;
            clock_gettime(CLOCK_MONOTONIC, &t);
            if ((int64_t)(t.tv_sec - t0.tv_sec) * 1000000000LL + (t.tv_nsec - t0.tv_nsec)
                > RT_READ_BUDGET_NS)
                break;
        }
        uint32_t before = atomic_load_explicit(A32(&l->stats.seq), ACQUIRE);
        if (before & 1u) {
            sched_yield();
            continue;
        }
        memcpy(copy, &l->stats, sizeof *copy);
        atomic_thread_fence(ACQUIRE);
        uint32_t after = atomic_load_explicit(A32(&l->stats.seq), RELAXED);
        if (after == before) {
            copy->seq = before;
            return 0;
        }
    }
    return -1;
}

void rt_loop_request_stop(rt_loop *l)
{
    atomic_store_explicit(AINT(&l->stop_request), 1, RELEASE);
}

static inline int stop_requested(rt_loop *l)
{
    return atomic_load_explicit(AINT(&l->stop_request), ACQUIRE) != 0;
}

/* ------------------------------------------------------------------ */
/* Prepare                                                             */
/* ------------------------------------------------------------------ */

#define RT_N_OUTPUTS ((int)(sizeof(dct_outputs) / sizeof(double)))
#define RT_N_INPUTS ((int)(sizeof(dct_inputs) / sizeof(double)))
_Static_assert(sizeof(dct_outputs) % sizeof(double) == 0, "dct_outputs must be doubles only");
_Static_assert(sizeof(dct_inputs) % sizeof(double) == 0, "dct_inputs must be doubles only");

/* rows within 1..RT_DRIVER_ROWS (or 0), times finite and strictly
 * increasing, pedals within 0..100 %, selector codes P..D, the grade within
 * -40..40 %, end_s finite */
static int check_driver(const rt_driver *d)
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
static void driver_fixed_inputs(rt_loop *l, const rt_driver *d)
{
    if (d->has_selector)
        l->plant.inputs.selector_lever = d->selector_lever[0];
    if (d->has_grade)
        l->plant.inputs.road_grade_pct = d->road_grade_pct;
}

static int check_lookup(const rt_lookup *t, const rt_channel *ch)
{
    if (t->count == 0)
        return 0;
    if (!ch->ranges || ch->n_ranges < 0 || t->first > (uint32_t)ch->n_ranges ||
        t->count > (uint32_t)ch->n_ranges - t->first)
        return -1;
    return 0;
}

/* the tables of every channel are complete and consistent; fills
 * first_message and stats.n_messages */
static int check_channels(rt_loop *l)
{
    if (l->n_channels < 1 || l->n_channels > RT_MAX_CHANNELS)
        return -1;
    if (l->n_commands < 0 || l->n_commands > RT_MAX_COMMANDS)
        return -1;
    for (int i = 0; i < l->n_commands; i++)
        if (l->command_input[i] < -1 || l->command_input[i] >= RT_N_INPUTS)
            return -1;
    int total = 0, n_values = 0;
    for (int c = 0; c < l->n_channels; c++) {
        rt_channel *ch = &l->chan[c];
        const ct_table *t = &ch->table;
        if (!t->messages || !t->signals || t->n_messages < 1 || !ch->msgs || !ch->sources ||
            !ch->targets || t->n_messages > RT_MAX_MESSAGES - total)
            return -1;
        if (ch->transport != RT_TRANSPORT_SOCKETCAN && ch->transport != RT_TRANSPORT_RING)
            return -1;
        ch->first_message = total;
        ch->first_signal_value = n_values;
        for (int m = 0; m < t->n_messages; m++) {
            const ct_message *cm = &t->messages[m];
            const rt_msg *mm = &ch->msgs[m];
            if (cm->n_signals > RT_MAX_MSG_SIGNALS || cm->length > CT_MAX_LENGTH)
                return -1;
            if (mm->direction != RT_DIR_RX && mm->direction != RT_DIR_TX)
                return -1;
            if (!(isfinite(mm->cycle_s) && mm->cycle_s > 0.0))
                return -1;
            if (mm->direction == RT_DIR_TX && (mm->flags & RT_FRAME_FD) &&
                ch->transport == RT_TRANSPORT_SOCKETCAN && !ch->fd_frames)
                return -1; /* a CAN FD frame on a socket without CAN_RAW_FD_FRAMES */
            for (uint32_t k = cm->first_signal; k < cm->first_signal + cm->n_signals; k++) {
                const rt_source *src = &ch->sources[k];
                const rt_target *tgt = &ch->targets[k];
                if (mm->direction == RT_DIR_TX) {
                    if (src->kind > RT_SRC_COUNTER || check_lookup(&src->table, ch) != 0)
                        return -1;
                    if (src->kind == RT_SRC_OUTPUT && src->field >= RT_N_OUTPUTS)
                        return -1;
                    if (src->kind == RT_SRC_STATUS && src->field >= RT_N_STATUS)
                        return -1;
                    if (src->kind == RT_SRC_COUNTER && src->modulus < 1)
                        return -1;
                } else {
                    if (tgt->kind > RT_TGT_COMMAND || check_lookup(&tgt->table, ch) != 0)
                        return -1;
                    if (tgt->kind == RT_TGT_COMMAND && tgt->command >= l->n_commands)
                        return -1;
                    if (isnan(tgt->minimum) || isnan(tgt->maximum) || tgt->minimum > tgt->maximum)
                        return -1;
                }
            }
        }
        total += t->n_messages;
        const ct_message *last = &t->messages[t->n_messages - 1];
        uint32_t n_sig = last->first_signal + last->n_signals;
        if (n_sig > (uint32_t)(RT_MAX_SIGNAL_VALUES - n_values))
            return -1;
        n_values += (int)n_sig;
    }
    l->n_signal_values = n_values;
    l->stats.n_messages = total;
    l->stats.n_channels = l->n_channels;
    return 0;
}

/* the writable regions lie inside the loop, with a known kind */
static int check_regions(const rt_loop *l)
{
    if (l->n_regions < 0 || l->n_regions > RT_MAX_REGIONS)
        return -1;
    for (int i = 0; i < l->n_regions; i++) {
        const rt_region *g = &l->regions[i];
        if (g->size == 0 || g->offset > sizeof(rt_loop) || g->size > sizeof(rt_loop) - g->offset ||
            (g->kind != RT_REGION_DATA && g->kind != RT_REGION_PARAM))
            return -1;
    }
    return 0;
}

static int prepare_socket(int fd)
{
    int type = 0;
    socklen_t len = sizeof type;
    if (getsockopt(fd, SOL_SOCKET, SO_TYPE, &type, &len) != 0)
        return -errno;                  /* EBADF, ENOTSOCK */
    if (type != SOCK_RAW && type != SOCK_DGRAM && type != SOCK_SEQPACKET)
        return -EPROTOTYPE;             /* frames need a message-preserving socket */
    int one = 1;
    if (setsockopt(fd, SOL_SOCKET, SO_RXQ_OVFL, &one, sizeof one) != 0)
        return -errno;
    int rcv = RT_RCVBUF_BYTES, snd = RT_SNDBUF_BYTES;
    /* the FORCE variants need CAP_NET_ADMIN; the plain ones are capped by
     * net.core.rmem_max / wmem_max. Not fatal: drops are counted anyway. */
    if (setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &rcv, sizeof rcv) != 0)
        (void)setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcv, sizeof rcv);
    if (setsockopt(fd, SOL_SOCKET, SO_SNDBUFFORCE, &snd, sizeof snd) != 0)
        (void)setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &snd, sizeof snd);
    return 0;
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

/* the safe values of every command a received message drives */
static void safe_values(const rt_loop *l, const rt_channel *ch, int m, double *cmd)
{
    const ct_message *cm = &ch->table.messages[m];
    for (uint32_t k = cm->first_signal; k < cm->first_signal + cm->n_signals; k++)
        if (ch->targets[k].kind == RT_TGT_COMMAND)
            cmd[ch->targets[k].command] = ch->targets[k].safe;
    (void)l;
}

static inline void apply_commands(rt_loop *l, const double *cmd)
{
    double *in = (double *)(void *)&l->plant.inputs;
    for (int i = 0; i < l->n_commands; i++)
        if (l->command_input[i] >= 0)
            in[l->command_input[i]] = cmd[i];
}

static int prepare_loop(rt_loop *l)
{
    const rt_config *c = &l->cfg;
    if (!(c->period_s >= RT_PERIOD_MIN_S && c->period_s <= RT_PERIOD_MAX_S))
        return -EINVAL;
    double step_s = c->step_s > 0.0 ? c->step_s : c->period_s;
    if (!(step_s >= RT_STEP_MIN_S && step_s <= RT_STEP_MAX_S && step_s <= c->period_s * (1.0 + 1e-9)))
        return -EINVAL; /* a tick may run slower than real time, never faster */
    if (c->record_every < 0)
        return -EINVAL;
    if (check_driver(&l->driver) != 0)
        return -EINVAL;
    if (c->priority < 0 || c->priority > RT_PRIORITY_MAX)
        return -EINVAL;
    if (c->cpu < -1 || c->cpu >= CPU_SETSIZE)
        return -EINVAL;
    if (isnan(c->duration_s))
        return -EINVAL;
    if (!(c->spin_us >= 0.0 && c->spin_us * 1e-6 < c->period_s))
        return -EINVAL; /* the early wake-up must stay inside the period */
    memset(&l->stats, 0, sizeof l->stats);
    if (check_regions(l) != 0)
        return -EINVAL;
    if (check_channels(l) != 0) {
        memset(&l->stats, 0, sizeof l->stats);
        return -EINVAL;
    }
    for (int ci = 0; ci < l->n_channels; ci++) {
        if (l->chan[ci].transport != RT_TRANSPORT_SOCKETCAN)
            continue;
        if (l->chan[ci].fd < 0)
            return -EBADF;
        int rc = prepare_socket(l->chan[ci].fd);
        if (rc != 0)
            return rc;
    }

    int n_messages = l->stats.n_messages, n_channels = l->stats.n_channels;
    memset(&l->stats, 0, sizeof l->stats);
    l->stats.n_messages = n_messages;
    l->stats.n_channels = n_channels;
    l->stats.state = RT_STATE_IDLE;
    l->plant.params.solver.step_s = step_s;
    int st = dct_plant_init(&l->plant);
    if (st != DCT_OK) {
        l->stats.error = -st;
        return -EDOM;
    }
    /* every received message starts timed out: its commands at their safe values */
    memset(l->stats.commands, 0, sizeof l->stats.commands);
    for (int ci = 0; ci < l->n_channels; ci++) {
        const rt_channel *ch = &l->chan[ci];
        for (int m = 0; m < ch->table.n_messages; m++) {
            int g = ch->first_message + m;
            l->rx_state[g].last_counter = -1;
            l->last_rx_tick[g] = 0;
            l->tx_count[g] = 0;
            if (ch->msgs[m].direction != RT_DIR_RX)
                continue;
            l->stats.msgs[g].timed_out = 1;
            safe_values(l, ch, m, l->stats.commands);
        }
    }
    apply_commands(l, l->stats.commands);
    dct_plant_update_outputs(&l->plant);
    l->stats.outputs = l->plant.outputs;
    l->stats.sim_time_s = l->plant.state.time_s;
    /* resets the rings; writing them also faults their pages in */
    memset(l->rx, 0, sizeof l->rx);
    memset(l->tx, 0, sizeof l->tx);
    memset(&l->log, 0, sizeof l->log);
    memset(&l->rec, 0, sizeof l->rec);
    memset(&l->daq_ring, 0, sizeof l->daq_ring);
    memset(&l->cal, 0, sizeof l->cal);
    memset(&l->stim, 0, sizeof l->stim);
    memset(l->daq, 0, sizeof l->daq);
    for (int i = 0; i < RT_MAX_SIGNAL_VALUES; i++)
        l->signal_values[i] = NAN;    /* no value until the signal's first frame */
    l->daq_gen = l->daq_ack = 0;      /* daq[0]: no lists */
    l->daq_refused = 0;
    l->stats.maneuver_state = l->driver.rows > 0 ? RT_MANEUVER_WAITING : RT_MANEUVER_NONE;
    l->stats.maneuver_time_s = -1.0;
    if (l->driver.rows > 0) { /* the pedals of the first row until the maneuver starts */
        l->plant.inputs.accel_pedal_pct = l->driver.accel_pedal_pct[0];
        l->plant.inputs.brake_pedal_pct = l->driver.brake_pedal_pct[0];
        driver_fixed_inputs(l, &l->driver);
        dct_plant_update_outputs(&l->plant);
        l->stats.outputs = l->plant.outputs;
    }
    atomic_store_explicit(AINT(&l->stop_request), 0, RELEASE);
    return 0;
}

int rt_loop_prepare(rt_loop *l)
{
    if (!l)
        return -EINVAL;
    int rc = prepare_loop(l);
    if (rc != 0)
        l->stats.n_channels = 0; /* not prepared: rt_loop_run refuses it */
    return rc;
}

/* ------------------------------------------------------------------ */
/* The run                                                             */
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
    /* maneuver commands */
    uint32_t maneuver_seq;           /* the last command sequence taken */
} rt_run;

static inline int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * RT_NS_PER_S + ts.tv_nsec;
}

static inline void sleep_until(int64_t t_ns)
{
    struct timespec ts = {(time_t)(t_ns / RT_NS_PER_S), (long)(t_ns % RT_NS_PER_S)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

static uint32_t gcd_u32(uint32_t a, uint32_t b)
{
    while (b) {
        uint32_t t = a % b;
        a = b;
        b = t;
    }
    return a;
}

static inline void mark(rt_run *r, int g)
{
    if (!r->is_dirty[g]) {
        r->is_dirty[g] = 1;
        r->dirty[r->n_dirty++] = g;
    }
}

static inline double tx_cycle_s(const rt_run *r, int i)
{
    return r->l->chan[r->tx_chan[i]].msgs[r->tx_local[i]].cycle_s;
}

/* divisors and staggered offsets of the sent messages of every channel (see the top) */
static void plan_tx(rt_run *r)
{
    rt_loop *l = r->l;
    r->n_tx = 0;
    for (int c = 0; c < l->n_channels; c++)
        for (int m = 0; m < l->chan[c].table.n_messages; m++)
            if (l->chan[c].msgs[m].direction == RT_DIR_TX) {
                r->tx_chan[r->n_tx] = (uint8_t)c;
                r->tx_local[r->n_tx] = (uint8_t)m;
                r->n_tx++;
            }
    for (int i = 1; i < r->n_tx; i++) /* stable sort by cycle time */
        for (int j = i; j > 0 && tx_cycle_s(r, j) < tx_cycle_s(r, j - 1); j--) {
            uint8_t tc = r->tx_chan[j], tm = r->tx_local[j];
            r->tx_chan[j] = r->tx_chan[j - 1];
            r->tx_local[j] = r->tx_local[j - 1];
            r->tx_chan[j - 1] = tc;
            r->tx_local[j - 1] = tm;
        }
    for (int i = 0; i < r->n_tx; i++) {
        double ticks = tx_cycle_s(r, i) * 1e9 / (double)r->step_ns;
        uint32_t div = ticks < 1.5 ? 1u : (uint32_t)llround(ticks);
        uint32_t best = 0;
        double best_cost = INFINITY;
        for (uint32_t off = 0; off < div; off++) {
            double cost = 0.0;
            for (int j = 0; j < i; j++) {
                uint32_t g = gcd_u32(div, r->tx_div[j]);
                if (off % g == r->tx_off[j] % g)
                    cost += 1.0 / r->tx_div[j];
            }
            if (cost < best_cost - 1e-12) {
                best_cost = cost;
                best = off;
            }
        }
        r->tx_div[i] = r->tx_div_plan[i] = div;
        r->tx_off[i] = best;
        r->tx_wait[i] = best;           /* tick 0 is the first executed tick */
    }
}

static void plan_rx(rt_run *r)
{
    rt_loop *l = r->l;
    r->n_rx = 0;
    for (int c = 0; c < l->n_channels; c++)
        for (int m = 0; m < l->chan[c].table.n_messages; m++) {
            const rt_msg *mm = &l->chan[c].msgs[m];
            if (mm->direction != RT_DIR_RX)
                continue;
            r->rx_chan[r->n_rx] = (uint8_t)c;
            r->rx_local[r->n_rx] = (uint8_t)m;
            r->n_rx++;
            uint32_t cycles = mm->timeout_cycles ? mm->timeout_cycles : RT_TIMEOUT_CYCLES;
            double ticks = (double)cycles * mm->cycle_s * 1e9 / (double)r->step_ns;
            r->rx_timeout_ticks[l->chan[c].first_message + m] = (uint64_t)ceil(ticks - 1e-9);
        }
}

/* a received signal's value turned into its command value */
static inline double target_value(const rt_target *t, const rt_range *ranges, double x)
{
    double v = t->table.count ? lookup(&t->table, ranges, x) : t->gain * x + t->bias;
    if (isnan(v))
        return t->safe;
    if (v < t->minimum)
        v = t->minimum;
    if (v > t->maximum)
        v = t->maximum;
    return v;
}

/* one received frame of channel c; well_formed: the transport delivered a whole frame */
static inline void rx_one(rt_run *r, int c, rt_frame *f, int well_formed, uint64_t n)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    rt_chan_stats *cs = &r->c.chan[c];
    f->channel = (uint8_t)c;
    cs->rx_frames++;
    if (atomic_load_explicit(AINT(&l->cfg.log_frames), RELAXED))
        log_push(&l->log, r->time_s, RT_DIR_RX, f);

    uint32_t id = f->id;
    int extended = (id & CAN_EFF_FLAG) != 0;
    uint32_t base = id & (extended ? CAN_EFF_MASK : CAN_SFF_MASK);
    int m = -1;
    if (!(id & CAN_ERR_FLAG) && (extended || (id & ~(uint32_t)CAN_RTR_FLAG) <= CAN_SFF_MASK))
        m = ct_find(&ch->table, base, extended);
    if (m < 0 || ch->msgs[m].direction != RT_DIR_RX) {
        cs->rx_unknown_id++;
        return;
    }
    int g = ch->first_message + m;
    rt_msg_stats *ms = &r->c.msgs[g];
    mark(r, g);
    const ct_message *cm = &ch->table.messages[m];
    if (!well_formed || (id & CAN_RTR_FLAG) || f->len > CT_MAX_LENGTH ||
        ((f->flags & RT_FRAME_FD) != 0) != (cm->fd != 0)) {
        cs->rx_bad_length++;
        ms->bad_length++;
        return;
    }
    switch (ct_check(&ch->table, m, f->data, f->len, &l->rx_state[g])) {
    case CT_RX_OK: {
        cs->rx_accepted++;
        ms->frames++;
        (void)ct_decode(&ch->table, m, f->data, f->len, r->values, r->written);
        if (r->f.msg_signal_faults[g])
            rtf_signals(&r->f, g, r->values, r->written, cm->n_signals);
        double *shown = l->signal_values + ch->first_signal_value + cm->first_signal;
        for (uint32_t k = 0; k < cm->n_signals; k++) {
            if (!r->written[k])
                continue;
            shown[k] = r->values[k];
            const rt_target *t = &ch->targets[cm->first_signal + k];
            if (t->kind == RT_TGT_COMMAND)
                r->cmd[t->command] = target_value(t, ch->ranges, r->values[k]);
        }
        l->last_rx_tick[g] = n;
        ms->timed_out = 0;
        r->tcu_heard = 1;
        break;
    }
    case CT_RX_BAD_CRC:
        cs->rx_bad_crc++;
        ms->bad_crc++;
        break;
    case CT_RX_BAD_COUNTER:
        cs->rx_bad_counter++;
        ms->bad_counter++;
        break;
    case CT_RX_BAD_LENGTH:
    default:
        cs->rx_bad_length++;
        ms->bad_length++;
        break;
    }
}

/* drains channel c's received frames; returns 0, or the errno of a fatal transport error */
static int rx_drain(rt_run *r, int c, uint64_t n)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    int budget = RT_RX_MAX_PER_TICK;
    if (ch->transport == RT_TRANSPORT_RING) {
        while (budget > 0) {
            int want = budget < RT_RX_BATCH ? budget : RT_RX_BATCH;
            int got = rt_ring_pop_many(&l->rx[c], r->rx_frames, want);
            for (int i = 0; i < got; i++)
                rx_one(r, c, &r->rx_frames[i], 1, n);
            budget -= got;
            if (got < want)
                break;
        }
        r->c.chan[c].rx_overflow = atomic_load_explicit(A64(&l->rx[c].dropped), RELAXED);
        return 0;
    }

    int interrupted = 0;
    while (budget > 0) {
        int want = budget < RT_RX_BATCH ? budget : RT_RX_BATCH;
        for (int i = 0; i < want; i++) {
            r->rx_iov[i].iov_base = &r->rx_cf[i];
            r->rx_iov[i].iov_len = sizeof r->rx_cf[i];
            memset(&r->rx_msg[i], 0, sizeof r->rx_msg[i]);
            r->rx_msg[i].msg_hdr.msg_iov = &r->rx_iov[i];
            r->rx_msg[i].msg_hdr.msg_iovlen = 1;
            r->rx_msg[i].msg_hdr.msg_control = r->rx_ctrl[i].bytes;
            r->rx_msg[i].msg_hdr.msg_controllen = sizeof r->rx_ctrl[i].bytes;
        }
        int got = recvmmsg(ch->fd, r->rx_msg, (unsigned)want, MSG_DONTWAIT, NULL);
        if (got < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK)
                break;
            if (errno == EINTR && ++interrupted < 4)
                continue;
            return errno;
        }
        for (int i = 0; i < got; i++) {
            struct msghdr *h = &r->rx_msg[i].msg_hdr;
            for (struct cmsghdr *cm = CMSG_FIRSTHDR(h); cm; cm = CMSG_NXTHDR(h, cm)) {
                if (cm->cmsg_level == SOL_SOCKET && cm->cmsg_type == SO_RXQ_OVFL &&
                    cm->cmsg_len >= CMSG_LEN(sizeof(uint32_t))) {
                    uint32_t drops;
                    memcpy(&drops, CMSG_DATA(cm), sizeof drops);
                    r->ovfl_total[c] += (uint32_t)(drops - r->ovfl_last[c]);
                    r->ovfl_last[c] = drops;
                }
            }
            const struct canfd_frame *cf = &r->rx_cf[i];
            unsigned size = r->rx_msg[i].msg_len;
            int fd_frame = size == CANFD_MTU;
            int well_formed = !(h->msg_flags & MSG_TRUNC) &&
                              (size == CAN_MTU || (fd_frame && ch->fd_frames)) &&
                              cf->len <= (fd_frame ? CANFD_MAX_DLEN : CAN_MAX_DLEN);
            rt_frame f;
            f.id = cf->can_id;
            f.len = cf->len <= CT_MAX_LENGTH ? cf->len : CT_MAX_LENGTH;
            f.flags = (uint8_t)((fd_frame ? RT_FRAME_FD : 0) |
                                (fd_frame && (cf->flags & CANFD_BRS) ? RT_FRAME_BRS : 0));
            f.reserved = 0;
            memcpy(f.data, cf->data, f.len);
            rx_one(r, c, &f, well_formed, n);
        }
        budget -= got;
        if (got < want)
            break;
    }
    r->c.chan[c].rx_overflow = r->ovfl_total[c];
    return 0;
}

static void check_timeouts(rt_run *r, uint64_t n)
{
    rt_loop *l = r->l;
    for (int i = 0; i < r->n_rx; i++) {
        const rt_channel *ch = &l->chan[r->rx_chan[i]];
        int m = r->rx_local[i];
        int g = ch->first_message + m;
        rt_msg_stats *ms = &r->c.msgs[g];
        if (ms->timed_out || n - l->last_rx_tick[g] <= r->rx_timeout_ticks[g])
            continue;
        ms->timed_out = 1;
        ms->timeouts++;
        mark(r, g);
        safe_values(l, ch, m, r->cmd);
        l->rx_state[g].last_counter = -1;
    }
}

/* sends tx_frames[0 .. nf) on channel c; returns 0 or the errno of a fatal error */
static int tx_send(rt_run *r, int c, int nf)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    int sent = 0, err = 0;
    if (nf <= 0)
        return 0;
    if (ch->transport == RT_TRANSPORT_RING) {
        sent = rt_ring_push_many(&l->tx[c], r->tx_frames, nf);
    } else {
        for (int i = 0; i < nf; i++) {
            struct canfd_frame *cf = &r->tx_cf[i];
            const rt_frame *f = &r->tx_frames[i];
            int fd_frame = (f->flags & RT_FRAME_FD) != 0;
            memset(cf, 0, sizeof *cf);
            cf->can_id = f->id;
            cf->len = f->len;
            if (fd_frame && (f->flags & RT_FRAME_BRS))
                cf->flags = CANFD_BRS;
            memcpy(cf->data, f->data, f->len);
            r->tx_iov[i].iov_base = cf;
            r->tx_iov[i].iov_len = fd_frame ? CANFD_MTU : CAN_MTU;
            memset(&r->tx_msg[i], 0, sizeof r->tx_msg[i]);
            r->tx_msg[i].msg_hdr.msg_iov = &r->tx_iov[i];
            r->tx_msg[i].msg_hdr.msg_iovlen = 1;
        }
        int interrupted = 0;
        while (sent < nf) {
            int rc = sendmmsg(ch->fd, r->tx_msg + sent, (unsigned)(nf - sent), MSG_DONTWAIT);
            if (rc > 0) {
                sent += rc;
                continue;
            }
            if (rc < 0 && errno == EINTR && ++interrupted < 4)
                continue;
            if (rc == 0 || errno == EAGAIN || errno == EWOULDBLOCK || errno == ENOBUFS || errno == EINTR)
                break; /* never block: the rest is dropped */
            err = errno;
            break;
        }
    }
    r->c.chan[c].tx_frames += (uint64_t)sent;
    r->c.chan[c].tx_dropped += (uint64_t)(nf - sent);
    for (int i = 0; i < nf; i++) {
        int g = r->tx_frame_msg[i];
        if (i < sent)
            r->c.msgs[g].frames++;
        else
            r->c.msgs[g].dropped++;
        mark(r, g);
    }
    if (atomic_load_explicit(AINT(&l->cfg.log_frames), RELAXED))
        for (int i = 0; i < sent; i++)
            log_push(&l->log, r->time_s, RT_DIR_TX, &r->tx_frames[i]);
    return err;
}

static void sim_status(rt_run *r, double state)
{
    r->status[RT_STATUS_SIM_TIME_S] = r->l->plant.state.time_s;
    r->status[RT_STATUS_OVERRUN_COUNT] = (double)r->c.overruns;
    r->status[RT_STATUS_TURNAROUND_MAX_US] = r->c.turnaround_max_us;
    r->status[RT_STATUS_SIM_STATE] = state;
}

/* a sent signal's value */
static inline double source_value(const rt_run *r, const rt_source *s, const rt_range *ranges,
                                  uint64_t seq)
{
    double x;
    switch (s->kind) {
    case RT_SRC_OUTPUT:
        x = ((const double *)(const void *)&r->l->plant.outputs)[s->field];
        break;
    case RT_SRC_STATUS:
        x = r->status[s->field];
        break;
    case RT_SRC_TOGGLE:
        return (double)(seq & 1u);
    case RT_SRC_COUNTER:
        return (double)(seq % s->modulus);
    case RT_SRC_VALUE:
    default:
        return s->value;
    }
    if (s->absolute)
        x = fabs(x);
    return s->table.count ? lookup(&s->table, ranges, x) : s->gain * x + s->bias;
}

/* the CAN faults of sent message g on its frame (after encoding and protection) */
static void fault_frame(rt_run *r, int g, const ct_message *cm, rt_frame *f, unsigned fault)
{
    if (fault & RTF_FREEZE)
        rtf_hit_message(&r->f, g, RTF_FREEZE);
    if ((fault & RTF_BAD_CRC) && cm->crc_byte >= 0 && (uint32_t)cm->crc_byte < f->len) {
        f->data[cm->crc_byte] ^= 0xFFu;
        rtf_hit_message(&r->f, g, RTF_BAD_CRC);
    }
    if (fault & RTF_LENGTH) {
        uint8_t len = r->f.msg_length[g];
        if (len > f->len)
            memset(f->data + f->len, 0, (size_t)(len - f->len));
        f->len = len;
        rtf_hit_message(&r->f, g, RTF_LENGTH);
    }
}

/* the next frame of sent message m of channel c, into tx_frames[nf] */
static void make_frame(rt_run *r, int c, int m, int nf)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    const ct_message *cm = &ch->table.messages[m];
    int g = ch->first_message + m;
    uint64_t seq = l->tx_count[g];
    unsigned fault = r->f.tx_any ? r->f.msg_flags[g] : 0u;
    uint64_t shown_seq = fault & RTF_FREEZE ? r->f.msg_frozen_seq[g] : seq;
    const rt_source *src = ch->sources + cm->first_signal;
    double *shown = l->signal_values + ch->first_signal_value + cm->first_signal;
    if (r->f.msg_signal_faults[g]) {
        for (uint32_t k = 0; k < cm->n_signals; k++)
            r->values[k] = source_value(r, &src[k], ch->ranges, shown_seq);
        rtf_signals(&r->f, g, r->values, NULL, cm->n_signals);
        memcpy(shown, r->values, cm->n_signals * sizeof r->values[0]);
    } else {
        for (uint32_t k = 0; k < cm->n_signals; k++)
            shown[k] = r->values[k] = source_value(r, &src[k], ch->ranges, shown_seq);
    }
    rt_frame *f = &r->tx_frames[nf];
    f->id = cm->id | (cm->extended ? CAN_EFF_FLAG : 0u);
    f->flags = ch->msgs[m].flags;
    f->channel = (uint8_t)c;
    f->reserved = 0;
    f->len = cm->length;
    (void)ct_encode(&ch->table, m, r->values, f->data);
    if (r->f.msg_signal_faults[g])
        rtf_raw(&r->f, &ch->table, m, g, f->data);
    /* the counter in 64 bits first: it wraps at its own modulus, never at 2^32 */
    (void)ct_protect(&ch->table, m, f->data,
                     (uint32_t)(cm->counter_modulus ? shown_seq % cm->counter_modulus : 0u));
    if (fault)
        fault_frame(r, g, cm, f, fault);
    l->tx_count[g] = seq + 1;
    r->tx_frame_msg[nf] = g;
}

/* a frame a CAN fault keeps off the bus (counted as the fault's hit) */
static int fault_skips(rt_run *r, int c, int g)
{
    if (r->f.chan_off[c]) {
        rtf_hit_channel(&r->f, c);
        return 1;
    }
    if (r->f.msg_flags[g] & RTF_OMIT) {
        rtf_hit_message(&r->f, g, RTF_OMIT);
        return 1;
    }
    return 0;
}

/* a cycle fault started or ended: each sent message's divisor from its
 * faulted cycle or as planned; a message due later than its new cycle is
 * due at the end of it */
static void replan_cycles(rt_run *r)
{
    for (int i = 0; i < r->n_tx; i++) {
        int g = r->l->chan[r->tx_chan[i]].first_message + r->tx_local[i];
        uint32_t div = r->tx_div_plan[i];
        if (r->f.msg_flags[g] & RTF_CYCLE) {
            double ticks = r->f.msg_cycle_s[g] * 1e9 / (double)r->step_ns;
            div = ticks < 1.5 ? 1u : (uint32_t)llround(ticks);
        }
        r->tx_div[i] = div;
        if (r->tx_wait[i] >= div)
            r->tx_wait[i] = div - 1u;
    }
}

/* encodes and sends the frames due at this executed tick, channel by channel
 * (called once per executed tick: tx_wait counts the ticks down) */
static int tx_tick(rt_run *r)
{
    rt_loop *l = r->l;
    sim_status(r, r->tcu_heard ? RT_SIM_RUNNING : RT_SIM_STARTING);
    int err = 0;
    for (int c = 0; c < l->n_channels; c++) {
        int nf = 0;
        for (int i = 0; i < r->n_tx; i++)
            if (r->tx_chan[i] == c && r->tx_wait[i] == 0) {
                if (r->f.tx_any && fault_skips(r, c, l->chan[c].first_message + r->tx_local[i]))
                    continue;
                make_frame(r, c, r->tx_local[i], nf++);
            }
        int e = tx_send(r, c, nf);
        if (e && !err)
            err = e;
    }
    for (int i = 0; i < r->n_tx; i++)
        r->tx_wait[i] = r->tx_wait[i] ? r->tx_wait[i] - 1u : r->tx_div[i] - 1u;
    return err;
}

/* one last frame of each message carrying the simulator's state, with the
 * state the loop ends in */
static void tx_final(rt_run *r, double state)
{
    rt_loop *l = r->l;
    sim_status(r, state);
    for (int c = 0; c < l->n_channels; c++) {
        int nf = 0;
        for (int i = 0; i < r->n_tx; i++)
            if (r->tx_chan[i] == c && l->chan[c].msgs[r->tx_local[i]].final_frame)
                make_frame(r, c, r->tx_local[i], nf++);
        (void)tx_send(r, c, nf);
    }
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

/* ------------------------------------------------------------------ */
/* Writes (calibration, stimulus) and DAQ                              */
/* ------------------------------------------------------------------ */

static const rt_region *region_of(const rt_loop *l, uint32_t offset, uint32_t len)
{
    for (int i = 0; i < l->n_regions; i++) {
        const rt_region *g = &l->regions[i];
        if (offset >= g->offset && len <= g->size && offset - g->offset <= g->size - len)
            return g;
    }
    return NULL;
}

/* one write, whole; 0 applied, -1 refused */
static int apply_write(rt_loop *l, const rt_write *w)
{
    if (w->len == 0 || w->len > RT_WRITE_BYTES)
        return -1;
    const rt_region *g = region_of(l, w->offset, w->len);
    if (!g)
        return -1;
    uint8_t *dst = (uint8_t *)(void *)l + w->offset;
    if (g->kind != RT_REGION_PARAM) {
        memcpy(dst, w->data, w->len);
        return 0;
    }
    uint8_t old[RT_WRITE_BYTES];
    memcpy(old, dst, w->len);
    memcpy(dst, w->data, w->len);
    if (dct_plant_prepare(&l->plant) != DCT_OK) {
        memcpy(dst, old, w->len);     /* the plant refused them: as before */
        return -1;
    }
    return 0;
}

/* applies the writes due: every queued calibration write, and the stimulus
 * writes whose time has come (plant time before this tick's step) */
static void apply_writes(rt_loop *l, rt_write_ring *ring, int timed)
{
    uint32_t tail = atomic_load_explicit(A32(&ring->tail), RELAXED);
    uint32_t head = atomic_load_explicit(A32(&ring->head), ACQUIRE);
    double now_s = l->plant.state.time_s + 1e-9;
    int n = 0;
    while (tail != head && n < RT_WRITES_PER_TICK) {
        const rt_write *w = &ring->writes[tail & (RT_WRITE_RING_SIZE - 1u)];
        if (timed && !(w->time_s <= now_s))
            break;                    /* not yet (NaN: never) */
        if (apply_write(l, w) == 0) {
            atomic_store_explicit(A64(&ring->applied),
                                  atomic_load_explicit(A64(&ring->applied), RELAXED) + 1u, RELAXED);
            atomic_store_explicit(A64(&ring->last_applied_id), w->id, RELAXED);
        } else {
            atomic_store_explicit(A64(&ring->refused),
                                  atomic_load_explicit(A64(&ring->refused), RELAXED) + 1u, RELAXED);
            atomic_store_explicit(A64(&ring->last_refused_id), w->id, RELAXED);
        }
        tail++;
        n++;
    }
    atomic_store_explicit(A32(&ring->tail), tail, RELEASE);
}

/* a configuration the tick may copy from: every index inside its arrays,
 * every entry inside the loop, every ODT within one DTO */
static int daq_config_ok(const rt_daq_config *c)
{
    if (c->n_lists > RT_DAQ_MAX_LISTS)
        return 0;
    for (uint32_t i = 0; i < c->n_lists; i++) {
        const rt_daq_list *d = &c->lists[i];
        if (d->event >= RT_N_EVENTS || d->first_odt > RT_DAQ_MAX_ODTS ||
            d->n_odts > RT_DAQ_MAX_ODTS - d->first_odt)
            return 0;
        for (uint32_t o = d->first_odt; o < d->first_odt + d->n_odts; o++) {
            const rt_odt *t = &c->odts[o];
            if (t->first_entry > RT_DAQ_MAX_ENTRIES || t->n_entries > RT_DAQ_MAX_ENTRIES - t->first_entry)
                return 0;
            uint32_t bytes = 0;
            for (uint32_t e = t->first_entry; e < t->first_entry + t->n_entries; e++) {
                const rt_odt_entry *x = &c->entries[e];
                if (x->size == 0 || x->size > RT_DAQ_ODT_BYTES || x->offset > sizeof(rt_loop) ||
                    x->size > sizeof(rt_loop) - x->offset)
                    return 0;
                bytes += x->size;
            }
            if (bytes > RT_DAQ_ODT_BYTES)
                return 0;
        }
    }
    return 1;
}

/* at the start of a tick: a new configuration published since the last one? */
static void daq_pickup(rt_run *r)
{
    rt_loop *l = r->l;
    uint32_t gen = atomic_load_explicit(A32(&l->daq_gen), ACQUIRE);
    if (gen == r->daq_gen)
        return;                       /* nothing new (a refused one is counted once) */
    r->daq_gen = gen;
    const rt_daq_config *c = &l->daq[gen & 1u];
    if (daq_config_ok(c)) {
        r->daq = c->n_lists ? c : NULL;
    } else {
        r->daq = NULL;
        atomic_store_explicit(A64(&l->daq_refused),
                              atomic_load_explicit(A64(&l->daq_refused), RELAXED) + 1u, RELAXED);
    }
    for (int i = 0; i < RT_DAQ_MAX_LISTS; i++)
        r->daq_pre[i] = 0;            /* each list fires at its first event */
}

/* at the end of a tick (inside its measured time): the ODTs of every running
 * list whose event fires now, into the DAQ ring; then the generation used */
static void daq_copy(rt_run *r, int64_t deadline_ns, uint64_t tick)
{
    rt_loop *l = r->l;
    const rt_daq_config *c = r->daq;
    if (c) {
        rt_daq_ring *g = &l->daq_ring;
        const uint8_t *base = (const uint8_t *)(const void *)l;
        uint32_t head = atomic_load_explicit(A32(&g->head), RELAXED);
        uint32_t tail = atomic_load_explicit(A32(&g->tail), ACQUIRE);
        uint64_t dropped = 0;
        for (uint32_t i = 0; i < c->n_lists; i++) {
            const rt_daq_list *d = &c->lists[i];
            if (!d->running || r->ev_wait[d->event] != 0)
                continue;
            if (r->daq_pre[i] > 0) {
                r->daq_pre[i]--;
                continue;
            }
            r->daq_pre[i] = (uint16_t)(d->prescaler > 1 ? d->prescaler - 1 : 0);
            for (uint32_t o = 0; o < d->n_odts; o++) {
                if (head - tail >= RT_DAQ_RING_SIZE) {
                    dropped++;
                    continue;
                }
                rt_dto *x = &g->dtos[head & (RT_DAQ_RING_SIZE - 1u)];
                const rt_odt *t = &c->odts[d->first_odt + o];
                uint32_t len = 0;
                for (uint32_t e = t->first_entry; e < t->first_entry + t->n_entries; e++) {
                    const rt_odt_entry *y = &c->entries[e];
                    memcpy(x->data + len, base + y->offset, y->size);
                    len += y->size;
                }
                x->time_ns = deadline_ns;
                x->tick = tick;
                x->list = (uint16_t)i;
                x->odt = (uint16_t)o;
                x->len = (uint16_t)len;
                x->reserved = 0;
                head++;
            }
        }
        atomic_store_explicit(A32(&g->head), head, RELEASE);
        if (dropped)
            count_dropped(&g->dropped, dropped);
    }
    for (int e = 0; e < RT_N_EVENTS; e++)
        r->ev_wait[e] = r->ev_wait[e] ? r->ev_wait[e] - 1u : r->ev_div[e] - 1u;
    atomic_store_explicit(A32(&l->daq_ack), r->daq_gen, RELEASE);
}

void rt_daq_publish(rt_loop *l, uint32_t gen)
{
    atomic_store_explicit(A32(&l->daq_gen), gen, RELEASE);
}

uint32_t rt_daq_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->daq_ack), ACQUIRE);
}

void rt_scope_publish(rt_loop *l, uint32_t gen)
{
    atomic_store_explicit(A32(&l->scope_gen), gen, RELEASE);
}

uint32_t rt_scope_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->scope_ack), ACQUIRE);
}

void rt_maneuver_publish(rt_loop *l, uint32_t seq)
{
    atomic_store_explicit(A32(&l->maneuver_seq), seq, RELEASE);
}

uint32_t rt_maneuver_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->maneuver_ack), ACQUIRE);
}

double rt_daq_bench(rt_loop *l, int64_t iterations)
{
    if (!l || iterations < 1)
        return -1.0;
    uint32_t gen = atomic_load_explicit(A32(&l->daq_gen), ACQUIRE);
    const rt_daq_config *c = &l->daq[gen & 1u];
    if (!daq_config_ok(c))
        return -1.0;
    static rt_run r;                  /* benchmark only: not reentrant, not the loop's */
    memset(&r, 0, sizeof r);
    r.l = l;
    r.daq = c;
    r.daq_gen = gen;
    for (int e = 0; e < RT_N_EVENTS; e++)
        r.ev_div[e] = 1;              /* every event fires at every call */
    rt_daq_ring *g = &l->daq_ring;
    uint64_t dropped0 = g->dropped;
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int64_t i = 0; i < iterations; i++) {
        daq_copy(&r, 0, (uint64_t)i);
        atomic_store_explicit(A32(&g->tail), atomic_load_explicit(A32(&g->head), RELAXED), RELEASE);
    }
    clock_gettime(CLOCK_MONOTONIC, &b);
    g->dropped = dropped0;
    double ns = (double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec);
    return ns / (double)iterations;
}

/* a maneuver command published since the last tick (rt_loop.h): a start
 * plays the new table from this tick, a stop ends the maneuver playing */
static void maneuver_command(rt_run *r, uint32_t seq)
{
    rt_loop *l = r->l;
    r->maneuver_seq = seq;
    uint32_t op = l->maneuver_op;
    if (op == RT_MCMD_START && l->maneuver_next.rows > 0 && check_driver(&l->maneuver_next) == 0) {
        l->driver = l->maneuver_next;
        driver_fixed_inputs(l, &l->driver);
        r->maneuver_state = RT_MANEUVER_RUNNING;
        r->maneuver_t0_s = l->plant.state.time_s;
        r->maneuver_time_s = 0.0;
    } else if (op == RT_MCMD_STOP) {
        if (r->maneuver_state == RT_MANEUVER_RUNNING || r->maneuver_state == RT_MANEUVER_WAITING) {
            r->maneuver_state = RT_MANEUVER_DONE;
            l->plant.inputs.accel_pedal_pct = 0.0;
        }
    } else {
        atomic_store_explicit(A32(&l->maneuver_refused),
                              atomic_load_explicit(A32(&l->maneuver_refused), RELAXED) + 1u,
                              RELAXED);
    }
    atomic_store_explicit(A32(&l->maneuver_ack), seq, RELEASE);
}

/* the scripted driver: starts the maneuver when due, writes the pedals of
 * the maneuver time of this tick (the plant time before its step) */
static void drive(rt_run *r)
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

static inline int hist_bin(double us)
{
    if (!(us > 0.0))
        return 0;
    if (us >= RT_HIST_BINS - 1)
        return RT_HIST_BINS - 1;
    return (int)us;
}

/* inside a write section: the counts, the messages whose counts changed, the plant */
static void copy_counts(rt_stats *s, rt_run *r)
{
    const rt_counts *c = &r->c;
    rt_loop *l = r->l;
    s->ticks = c->ticks;
    s->overruns = c->overruns;
    s->skipped_ticks = c->skipped_ticks;
    s->turnaround_max_us = c->turnaround_max_us;
    s->exec_max_us = c->exec_max_us;
    s->latency_max_us = c->latency_max_us;
    rt_chan_stats sum;
    memset(&sum, 0, sizeof sum);
    for (int ch = 0; ch < l->n_channels; ch++) {
        const rt_chan_stats *x = &c->chan[ch];
        s->chan[ch] = *x;
        sum.rx_frames += x->rx_frames;
        sum.rx_accepted += x->rx_accepted;
        sum.rx_unknown_id += x->rx_unknown_id;
        sum.rx_bad_length += x->rx_bad_length;
        sum.rx_bad_crc += x->rx_bad_crc;
        sum.rx_bad_counter += x->rx_bad_counter;
        sum.rx_overflow += x->rx_overflow;
        sum.tx_frames += x->tx_frames;
        sum.tx_dropped += x->tx_dropped;
    }
    s->rx_frames = sum.rx_frames;
    s->rx_accepted = sum.rx_accepted;
    s->rx_unknown_id = sum.rx_unknown_id;
    s->rx_bad_length = sum.rx_bad_length;
    s->rx_bad_crc = sum.rx_bad_crc;
    s->rx_bad_counter = sum.rx_bad_counter;
    s->rx_overflow = sum.rx_overflow;
    s->tx_frames = sum.tx_frames;
    s->tx_dropped = sum.tx_dropped;
    for (int i = 0; i < r->n_dirty; i++) {
        int g = r->dirty[i];
        s->msgs[g] = c->msgs[g];
        r->is_dirty[g] = 0;
    }
    r->n_dirty = 0;
    memcpy(s->commands, r->cmd, (size_t)l->n_commands * sizeof r->cmd[0]);
    s->outputs = l->plant.outputs;
    s->sim_time_s = l->plant.state.time_s;
    s->maneuver_state = r->maneuver_state;
    s->maneuver_time_s = r->maneuver_time_s;
    if (r->faults_dirty || r->f.mask) {  /* starts, ends, and the hits of active faults */
        rtf_publish(&r->f, s, r->faults_dirty);
        r->faults_dirty = 0;
    }
}

static void publish_tick(rt_run *r, double turnaround_us, double exec_us, double latency_us)
{
    rt_stats *s = &r->l->stats;
    stats_write_begin(s);
    copy_counts(s, r);
    s->turnaround_us = turnaround_us;
    s->exec_us = exec_us;
    s->latency_us = latency_us;
    s->turnaround_hist[hist_bin(turnaround_us)]++;
    s->exec_hist[hist_bin(exec_us)]++;
    s->latency_hist[hist_bin(latency_us)]++;
    stats_write_end(s);
}

static void publish_state(rt_run *r, int state, int error)
{
    rt_stats *s = &r->l->stats;
    stats_write_begin(s);
    copy_counts(s, r);
    s->state = state;
    s->error = error;
    stats_write_end(s);
}

/* touches the stack the tick will use, so it does not fault in later */
__attribute__((noinline)) static void prefault_stack(void)
{
    volatile unsigned char buf[RT_STACK_PREFAULT];
    for (size_t i = 0; i < sizeof buf; i += 256)
        buf[i] = 0;
}

typedef struct {
    int policy_set;
    int old_policy;
    struct sched_param old_param;
    int affinity_set;
    cpu_set_t old_cpus;
} rt_thread_saved;

static void publish_phase(rt_loop *l, int phase)
{
    stats_write_begin(&l->stats);
    l->stats.startup_phase = phase;
    stats_write_end(&l->stats);
}

static void thread_setup(rt_loop *l, rt_thread_saved *sv, int *policy_ok, int *affinity_ok,
                         int *memory_locked)
{
    pthread_t self = pthread_self();
    memset(sv, 0, sizeof *sv);
    *policy_ok = *affinity_ok = *memory_locked = 0;
    publish_phase(l, RT_START_SCHEDULING);
    if (l->cfg.priority > 0 && pthread_getschedparam(self, &sv->old_policy, &sv->old_param) == 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = l->cfg.priority;
        if (pthread_setschedparam(self, SCHED_FIFO, &sp) == 0)
            *policy_ok = sv->policy_set = 1;
    }
    publish_phase(l, RT_START_PINNING);
    if (l->cfg.cpu >= 0 && pthread_getaffinity_np(self, sizeof sv->old_cpus, &sv->old_cpus) == 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(l->cfg.cpu, &set);
        if (pthread_setaffinity_np(self, sizeof set, &set) == 0)
            *affinity_ok = sv->affinity_set = 1;
    }
    publish_phase(l, RT_START_LOCKING_MEMORY);
    if (l->cfg.lock_memory && mlockall(MCL_CURRENT | MCL_FUTURE) == 0)
        *memory_locked = 1;
    publish_phase(l, RT_START_PREFAULTING);
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
    r.spin_ns = llround(l->cfg.spin_us * 1e3);
    plan_tx(&r);
    plan_rx(&r);
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
    stats_write_end(&l->stats);

    int state = RT_STATE_STOPPED, error = 0;
    double final_sim_state = RT_SIM_STOPPING;
    uint64_t n = 0; /* deadline index */
    r.t0_ns = now_ns() + r.period_ns;
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

        int err = 0;
        for (int c = 0; c < l->n_channels && !err; c++)
            err = rx_drain(&r, c, n);
        if (err) {
            state = RT_STATE_ERROR;
            error = err;
            final_sim_state = -1.0;
            break;
        }
        check_timeouts(&r, n);
        /* faults: nothing set and no command queued costs two loads */
        int fc = r.f.n_used || atomic_load_explicit(A32(&l->fault_cmds.head), ACQUIRE) !=
                                   atomic_load_explicit(A32(&l->fault_cmds.tail), RELAXED)
                     ? rtf_tick(&r.f, l, r.cmd, r.maneuver_time_s) : 0;
        if (fc) {
            r.faults_dirty = 1;
            if (fc & RTF_CYCLES_CHANGED)
                replan_cycles(&r);
        }
        drive(&r);
        daq_pickup(&r);
        apply_writes(l, &l->cal, 0);
        apply_writes(l, &l->stim, 1);
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
        err = tx_tick(&r);
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
        daq_copy(&r, deadline, r.c.ticks - 1u);
        rts_tick(&r.scope, l, r.c.ticks - 1u, l->plant.state.time_s);

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
                next = (uint64_t)((end - r.t0_ns) / r.period_ns) + 1u;
                if (limit && next > limit)
                    next = limit; /* only deadlines of the run count as skipped */
                r.c.skipped_ticks += next - (n + 1);
            }
        }
        publish_tick(&r, turnaround_us, exec_us, latency_us);
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
        tx_final(&r, final_sim_state);
    publish_state(&r, state, error);
    thread_restore(&saved);
    return state;
}
