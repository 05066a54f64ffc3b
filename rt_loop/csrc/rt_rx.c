/*
 * rt_rx.c - the loop's receive side: each channel's frames drained at the
 * start of a tick, each classified, checked (ct_check), counted and, when
 * accepted, decoded into its signals' command values; the receive timeouts.
 *
 * End-to-end: an accepted frame updates the message's counter state
 * (ct_check); when a message times out its counter state is reset to -1, so
 * the first frame after the TCU comes back is accepted whatever its counter
 * (as at start). A sent message's counter is the number of frames made so
 * far (a 64-bit count) modulo the protection's counter range; toggles and
 * counter sources count the same frames.
 *
 * Values: a received signal's command value is gain * signal + bias, or its
 * value table's entry, limited to [minimum, maximum]; a NaN (a float signal)
 * gives the safe value. A command value drives the plant input
 * command_input[i] every tick (or only the recording, -1); at prepare and
 * while its message is timed out it holds the target's safe value.
 *
 * Lost frames: rx_overflow is, for SocketCAN, the kernel's drop count of the
 * socket (SO_RXQ_OVFL); the kernel reports it with the next frame received,
 * so drops show up when the next frame arrives. For the ring transport it is
 * the channel's rx ring's dropped (pushes the bridge could not make).
 * tx_dropped counts sends
 * refused with EAGAIN / ENOBUFS or by a full tx ring; the loop never blocks
 * on a send, and the AliveCounter still advances, so the TCU sees the gap.
 */
#include "rt_internal.h"

#include <errno.h>

#define RT_RX_MAX_PER_TICK 256          /* drained per tick at most */

/* the safe values of every command a received message drives */
void rt_safe_values(const rt_loop *l, const rt_channel *ch, int m, double *cmd)
{
    const ct_message *cm = &ch->table.messages[m];
    for (uint32_t k = cm->first_signal; k < cm->first_signal + cm->n_signals; k++)
        if (ch->targets[k].kind == RT_TGT_COMMAND)
            cmd[ch->targets[k].command] = ch->targets[k].safe;
    (void)l;
}

void rt_rx_plan(rt_run *r)
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
RT_TICK_CODE
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
RT_TICK_CODE
int rt_rx_drain(rt_run *r, int c, uint64_t n)
{
    rt_loop *l = r->l;
    const rt_channel *ch = &l->chan[c];
    int budget = RT_RX_MAX_PER_TICK;
    if (ch->transport == RT_TRANSPORT_RING) {
        while (budget > 0) {
            int want = budget < RT_RX_BATCH ? budget : RT_RX_BATCH;
            int got = rt_frames_pop(&l->rx[c], r->rx_frames, want);
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

RT_TICK_CODE
void rt_rx_timeouts(rt_run *r, uint64_t n)
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
        rt_safe_values(l, ch, m, r->cmd);
        l->rx_state[g].last_counter = -1;
    }
}
