/*
 * rt_prepare.c - rt_loop_prepare (contract: rt_loop.h): the configuration,
 * the channel tables, the writable regions and the sockets checked before a
 * run, then the plant initialised, every received message timed out (its
 * commands at their safe values) and the rings reset.
 *
 * Return codes: rt_loop_prepare gives -EINVAL (a cfg field out of range:
 * period outside 50 us .. 100 ms, a step outside 50 us .. 10 ms or longer
 * than the period, a negative record_every, a driver table with more than
 * RT_DRIVER_ROWS rows, times not increasing, pedals outside 0..100 %, a
 * selector code other than P, R, N, D or a grade outside -40..40 %,
 * priority outside 0..99, cpu < -1, NaN duration; channel tables missing,
 * too many messages or commands, an unknown transport, source, target,
 * output, status or input index, a value table outside the ranges, a cycle
 * time that is not a positive number, min above max, a codec table not laid
 * out as can_dbc/table.py lays it out (check_table), a CAN FD message on a
 * SocketCAN channel without fd_frames), -EBADF (fd < 0), -ENOTSOCK /
 * -EPROTOTYPE (fd not
 * a datagram socket), another -errno (SO_RXQ_OVFL refused) or -EDOM (the
 * plant rejected its parameters). rt_loop_run gives -EINVAL when the loop
 * was not prepared since its last run (stats.state is not RT_STATE_IDLE, or
 * its last rt_loop_prepare failed: stats.n_channels is then 0),
 * else the final state. A duration <= 0 or infinite runs until
 * rt_loop_request_stop().
 */
#include "rt_internal.h"

#include <errno.h>
#include <sched.h>

#define RT_STEP_MIN_S 50e-6
#define RT_STEP_MAX_S 10e-3
#define RT_PRIORITY_MAX 99
#define RT_RCVBUF_BYTES (8 * 1024 * 1024)
#define RT_SNDBUF_BYTES (1024 * 1024)

#define RT_N_OUTPUTS ((int)(sizeof(dct_outputs) / sizeof(double)))
#define RT_N_INPUTS ((int)(sizeof(dct_inputs) / sizeof(double)))
_Static_assert(sizeof(dct_outputs) % sizeof(double) == 0, "dct_outputs must be doubles only");
_Static_assert(sizeof(dct_inputs) % sizeof(double) == 0, "dct_inputs must be doubles only");

static int check_lookup(const rt_lookup *t, const rt_channel *ch)
{
    if (t->count == 0)
        return 0;
    if (!ch->ranges || ch->n_ranges < 0 || t->first > (uint32_t)ch->n_ranges ||
        t->count > (uint32_t)ch->n_ranges - t->first)
        return -1;
    return 0;
}

/* 1 if signal s of a message of len bytes lies inside its frame */
static int signal_fits(const ct_signal *s, unsigned len)
{
    if (s->length < 1 || s->length > 64 || (s->is_float && s->length != 32 && s->length != 64) ||
        s->conversion > CT_CONV_INT_FACTOR)
        return 0;
    if (!isfinite(s->factor) || s->factor == 0.0 || !isfinite(s->offset) ||
        (s->limited && !(s->minimum < s->maximum)))
        return 0;
    const int64_t big = (int64_t)1 << 53; /* integer_value's bound */
    if (s->factor_int < -big || s->factor_int > big || s->offset_int < -big || s->offset_int > big)
        return 0;
    if (!s->is_float) { /* the field's raw range, as the builder computes it */
        double half = ldexp(1.0, s->length - 1);
        if (s->raw_min != (s->is_signed ? -half : 0.0) || s->raw_end != (s->is_signed ? half : 2 * half))
            return 0;
    }
    unsigned first = s->big_endian ? 8u * (s->start / 8u) + 7u - s->start % 8u : s->start;
    return first + s->length <= 8u * len;
}

/* a codec table as can_dbc/table.py lays it out: each message's signals
 * right after the previous message's, each multiplexed signal's ranges
 * right after the previous one's, every index inside its message and every
 * field inside its frame; *n_signals receives the signals of the table.
 * The codec trusts its tables: this is what lets the loop trust one. */
static int check_table(const ct_table *t, uint32_t *n_signals)
{
    uint32_t n_sig = 0, n_mux = 0;
    for (int m = 0; m < t->n_messages; m++) {
        const ct_message *cm = &t->messages[m];
        if (cm->first_signal != n_sig || cm->n_signals > RT_MAX_MSG_SIGNALS ||
            cm->length > CT_MAX_LENGTH || cm->protection > CT_PROT_P7)
            return -1;
        const int32_t n = (int32_t)cm->n_signals;
        if (cm->crc_signal < -1 || cm->crc_signal >= n || cm->counter_signal < -1 ||
            cm->counter_signal >= n || cm->nibble_signal < -1 || cm->nibble_signal >= n ||
            cm->crc_byte < -1 || cm->crc_byte >= (int32_t)cm->length)
            return -1;
        for (uint32_t i = 0; i < cm->n_signals; i++) {
            const ct_signal *s = &t->signals[n_sig + i];
            if (!signal_fits(s, cm->length) || s->mux_signal < -1 || s->mux_signal >= n ||
                s->mux_signal == (int32_t)i)
                return -1;
            if (s->mux_signal >= 0) {
                if (s->mux_first != n_mux || !t->mux || s->mux_count > RT_MAX_MSG_SIGNALS)
                    return -1;
                n_mux += s->mux_count;
            }
        }
        n_sig += cm->n_signals;
    }
    *n_signals = n_sig;
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
        uint32_t n_sig = 0;
        if (check_table(t, &n_sig) != 0)
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
    if (rt_driver_check(&l->driver) != 0)
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
            rt_safe_values(l, ch, m, l->stats.commands);
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
        rt_driver_fixed_inputs(l, &l->driver);
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
