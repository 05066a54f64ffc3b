/*
 * rt_tx.c - the loop's send side: the send plan (each sent message's divisor
 * of the tick and its offset), the frames due at an executed tick (each
 * signal's value from its source, encoded, protected, the CAN faults
 * applied) and their send; one last frame with the simulator's state when
 * the loop ends.
 *
 * Offsets: computed once at the start of rt_loop_run over the sent messages
 * of all channels, shortest cycle first; each message takes the offset whose
 * ticks it shares with the fewest frames already planned (two messages of
 * divisors a and b with offsets x and y meet when x = y mod gcd(a, b)). With
 * the project's own contract at 2 kHz the three 2 ms messages go to ticks
 * 0, 1, 2 (mod 4), the three 10 ms ones to 3, 7, 11 (mod 20) and SIM_Status
 * to 15 (mod 200): at most one frame per tick.
 *
 * Status sources (RT_STATUS_*): sim_state is 0 until the first frame of a
 * received message is accepted, then 1; when the loop ends, one last frame
 * of every sent message with final_frame (those carrying sim_state) goes out
 * with 2 (stopped by request or duration) or 3 (overrun stop, plant error);
 * none after a transport error.
 */
#include "rt_internal.h"

#include <errno.h>

static uint32_t gcd_u32(uint32_t a, uint32_t b)
{
    while (b) {
        uint32_t t = a % b;
        a = b;
        b = t;
    }
    return a;
}

static inline double tx_cycle_s(const rt_run *r, int i)
{
    return r->l->chan[r->tx_chan[i]].msgs[r->tx_local[i]].cycle_s;
}

/* divisors and staggered offsets of the sent messages of every channel (see the top) */
void rt_tx_plan(rt_run *r)
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

/* sends tx_frames[0 .. nf) on channel c; returns 0 or the errno of a fatal error */
RT_TICK_CODE
static int tx_send(rt_run *r, int c, int nf)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    int sent = 0, err = 0;
    if (nf <= 0)
        return 0;
    if (ch->transport == RT_TRANSPORT_RING) {
        sent = rt_frames_push(&l->tx[c], r->tx_frames, nf);
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

RT_TICK_CODE
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
RT_TICK_CODE
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
    uint32_t saturated = 0;
    (void)ct_encode_counted(&ch->table, m, r->values, f->data, &saturated);
    r->c.msgs[g].saturated += saturated;
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
void rt_tx_replan(rt_run *r)
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
RT_TICK_CODE
int rt_tx_tick(rt_run *r)
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
void rt_tx_final(rt_run *r, double state)
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
