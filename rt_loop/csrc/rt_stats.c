/*
 * rt_stats.c - the loop's statistics (rt_stats in rt_loop.h): the counts,
 * the last tick's times and their histograms, published once per tick.
 *
 * One writer (the loop), a sequence counter. The writer makes seq odd,
 * fences (release), writes, then makes seq even (release store).
 * rt_stats_read loads seq (acquire), copies, fences (acquire), loads seq
 * again and keeps the copy when both are equal and even. The loop never
 * waits for a reader. The loop works on local copies and publishes them
 * once per tick in a short write section.
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
 */
#include "rt_internal.h"

#include <sched.h>
#include <time.h>

/* The reader's copy is optimistic: it may overlap the writer's section, and is then
 * thrown away (the counter moved). ThreadSanitizer does not model the fences that make
 * that safe and would report every overlap as a race; in a sanitizer build
 * (DCT_HIL_SANITIZE=thread, plant/_build.py) the copy alone is left out of its view
 * (its dynamic annotations, as for any sequence lock). Every other access to the
 * statistics, the counter's included, stays checked. No code in other builds. */
#if defined(__SANITIZE_THREAD__)
void AnnotateIgnoreReadsBegin(const char *file, int line);
void AnnotateIgnoreReadsEnd(const char *file, int line);
#define SEQ_COPY_BEGIN() AnnotateIgnoreReadsBegin(__FILE__, __LINE__)
#define SEQ_COPY_END() AnnotateIgnoreReadsEnd(__FILE__, __LINE__)
#else
#define SEQ_COPY_BEGIN() ((void)0)
#define SEQ_COPY_END() ((void)0)
#endif

#define RT_READ_RETRIES 1000            /* a copy is tried at least this often ... */
#define RT_READ_BUDGET_NS 2000000000LL  /* ... and for at least this long (a starved reader) */

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
        SEQ_COPY_BEGIN();
        memcpy(copy, &l->stats, sizeof *copy);
        SEQ_COPY_END();
        atomic_thread_fence(ACQUIRE);
        uint32_t after = atomic_load_explicit(A32(&l->stats.seq), RELAXED);
        if (after == before) {
            copy->seq = before;
            return 0;
        }
    }
    return -1;
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
RT_TICK_CODE
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

RT_TICK_CODE
void rt_stats_publish_tick(rt_run *r, double turnaround_us, double exec_us, double latency_us)
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

void rt_stats_publish_state(rt_run *r, int state, int error)
{
    rt_stats *s = &r->l->stats;
    stats_write_begin(s);
    copy_counts(s, r);
    s->state = state;
    s->error = error;
    stats_write_end(s);
}

void rt_stats_publish_phase(rt_loop *l, int phase)
{
    stats_write_begin(&l->stats);
    l->stats.startup_phase = phase;
    stats_write_end(&l->stats);
}
