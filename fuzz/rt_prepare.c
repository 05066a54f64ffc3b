/*
 * rt_prepare.c - libFuzzer target: rt_loop_prepare on arbitrary
 * configurations and channel tables.
 *
 * The input fills the loop's configuration, its driver table, the
 * writable regions, the commands and up to RT_MAX_CHANNELS + 1 channels,
 * each with a codec table and the loop's per-message and per-signal
 * arrays. Every array is allocated at the length the table's own counts
 * give it (as rt_loop/channels.py does: one ct_signal, rt_source and
 * rt_target per signal of the messages, the mux ranges the signals count,
 * n_ranges value-table ranges), so AddressSanitizer sees any read beyond.
 * Fields are raw bytes of the input; a flag byte per channel makes some of
 * them plausible (contiguous signals, short frames, known kinds) so that
 * the checks after the first ones are reached too.
 *
 * rt_loop_prepare must return 0 or a negative errno and never crash; a
 * table it accepts must then go through the codec (encode, protect,
 * check, decode every message) without reading outside its arrays.
 */
#include <errno.h>
#include <stdlib.h>

#include "rt_internal.h"
#include "fmu_model.h"
#include "fuzz_input.h"

#define MAX_FUZZ_MSGS 16
#define MAX_FUZZ_SIGS 32

static rt_loop *loop;

typedef struct {
    ct_message *messages;
    ct_signal *signals;
    ct_mux_range *mux;
    rt_msg *msgs;
    rt_source *sources;
    rt_target *targets;
    rt_range *ranges;
} owned;

static void *fill(fz_in *in, size_t n, size_t size)
{
    void *p = malloc(n * size ? n * size : 1);
    fz_bytes(in, p, n * size);
    return p;
}

static void fill_channel(fz_in *in, rt_channel *ch, owned *o)
{
    uint8_t flags = fz_u8(in);
    int plausible = !(flags & 1);
    memset(ch, 0, sizeof *ch);
    ch->transport = plausible ? RT_TRANSPORT_RING : (int)(int8_t)fz_u8(in);
    ch->fd = -1;
    ch->fd_frames = (flags >> 1) & 1;
    int n_msgs = (int)(int8_t)fz_u8(in) % (MAX_FUZZ_MSGS + 1);
    if (plausible && n_msgs < 1)
        n_msgs = 1 + (-n_msgs) % MAX_FUZZ_MSGS;
    uint32_t counts[MAX_FUZZ_MSGS] = {0};
    for (int m = 0; m < n_msgs; m++)
        counts[m] = fz_u8(in) % (MAX_FUZZ_SIGS + 1);
    int32_t n_ranges = (int32_t)(int8_t)fz_u8(in) % 8;
    size_t nm = n_msgs > 0 ? (size_t)n_msgs : 0;
    o->messages = fill(in, nm, sizeof(ct_message));
    /* the signal arrays are as long as the messages' counts say (Python's
     * layout); raw counts beyond RT_MAX_MSG_SIGNALS stay, to be refused */
    uint32_t n_sig = 0;
    for (int m = 0; m < n_msgs; m++) {
        if (plausible)
            o->messages[m].n_signals = counts[m];
        else if (o->messages[m].n_signals > RT_MAX_MSG_SIGNALS + 1)
            o->messages[m].n_signals %= RT_MAX_MSG_SIGNALS + 2;
        n_sig += o->messages[m].n_signals;
    }
    o->signals = fill(in, n_sig, sizeof(ct_signal));
    uint64_t n_mux = 0; /* the ranges the multiplexed signals count */
    for (uint32_t k = 0; k < n_sig; k++) {
        if (plausible && !(flags & 8))
            o->signals[k].mux_signal = -1;
        if (o->signals[k].mux_signal < 0)
            continue;
        if (plausible)
            o->signals[k].mux_count %= 3;
        n_mux += o->signals[k].mux_count;
    }
    if (n_mux > 4096) {
        n_mux = 0;
        for (uint32_t k = 0; k < n_sig; k++)
            if (o->signals[k].mux_signal >= 0)
                n_mux += o->signals[k].mux_count %= 4;
    }
    o->mux = fill(in, (size_t)n_mux, sizeof(ct_mux_range));
    o->msgs = fill(in, nm, sizeof(rt_msg));
    o->sources = fill(in, n_sig, sizeof(rt_source));
    o->targets = fill(in, n_sig, sizeof(rt_target));
    o->ranges = fill(in, n_ranges > 0 ? (size_t)n_ranges : 0, sizeof(rt_range));
    if (plausible) {
        uint32_t first = 0, mux_at = 0;
        for (int m = 0; m < n_msgs; m++) {
            ct_message *cm = &o->messages[m];
            rt_msg *mm = &o->msgs[m];
            cm->first_signal = first;
            cm->length %= CT_MAX_LENGTH + 1;
            cm->protection %= CT_PROT_P7 + 2;
            if (!(flags & 4)) { /* no protection, the loop's fields sane */
                cm->protection = CT_PROT_NONE;
                cm->crc_signal = cm->counter_signal = cm->nibble_signal = cm->crc_byte = -1;
                cm->counter_modulus = 0;
            }
            mm->direction &= 1;
            mm->flags &= (uint8_t)~RT_FRAME_FD;
            if (!(mm->cycle_s > 0.0 && mm->cycle_s < 1e3))
                mm->cycle_s = 0.01;
            for (uint32_t k = first; k < first + counts[m]; k++) {
                ct_signal *s = &o->signals[k];
                s->length = (uint8_t)(1 + s->length % 64);
                s->start %= 8 * CT_MAX_LENGTH;
                s->conversion %= 4;
                if (s->mux_signal >= 0) {
                    s->mux_signal %= (int32_t)counts[m];
                    s->mux_first = mux_at;
                    mux_at += s->mux_count;
                }
                o->sources[k].kind %= RT_SRC_COUNTER + 1;
                o->sources[k].field %= 64;
                o->sources[k].table.count %= 3;
                o->sources[k].table.first %= 8;
                if (o->sources[k].modulus == 0)
                    o->sources[k].modulus = 16;
                o->targets[k].kind %= RT_TGT_COMMAND + 1;
                o->targets[k].command %= RT_MAX_COMMANDS;
                o->targets[k].table.count %= 3;
                o->targets[k].table.first %= 8;
                if (!(o->targets[k].minimum <= o->targets[k].maximum)) {
                    o->targets[k].minimum = -INFINITY;
                    o->targets[k].maximum = INFINITY;
                }
            }
            first += counts[m];
        }
    }
    ch->table.messages = n_msgs > 0 || !(flags & 16) ? o->messages : NULL;
    ch->table.signals = o->signals;
    ch->table.mux = o->mux;
    ch->table.n_messages = n_msgs; /* the count Python allocates (negative: none) */
    ch->msgs = o->msgs;
    ch->sources = o->sources;
    ch->targets = o->targets;
    ch->ranges = o->ranges;
    ch->n_ranges = n_ranges;
}

static void free_owned(owned *o)
{
    free(o->messages);
    free(o->signals);
    free(o->mux);
    free(o->msgs);
    free(o->sources);
    free(o->targets);
    free(o->ranges);
}

/* a table the loop accepted goes through the codec */
static void use_table(const rt_channel *ch)
{
    const ct_table *t = &ch->table;
    for (int m = 0; m < t->n_messages; m++) {
        static double values[RT_MAX_MSG_SIGNALS];
        static uint8_t written[RT_MAX_MSG_SIGNALS];
        uint8_t frame[CT_MAX_LENGTH] = {0};
        uint32_t n = t->messages[m].n_signals;
        for (uint32_t i = 0; i < n; i++)
            values[i] = (double)i;
        int len = ct_encode(t, m, values, frame);
        ct_protect(t, m, frame, (uint32_t)m);
        ct_rx_state st = {-1};
        ct_check(t, m, frame, len, &st);
        ct_decode(t, m, frame, len, values, written);
        ct_find(t, t->messages[m].id, t->messages[m].extended);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (!loop && !(loop = calloc(1, sizeof *loop)))
        abort();
    fz_in in = {data, size};
    rt_loop *l = loop;
    memset(&l->cfg, 0, sizeof l->cfg);
    l->cfg.period_s = 500e-6;
    l->cfg.cpu = -1;
    l->cfg.duration_s = 1.0;
    memset(&l->driver, 0, sizeof l->driver);
    memcpy(&l->plant.params, &fmu_params, sizeof fmu_params);
    /* patches over the configuration and the driver table */
    int n_patch = fz_u8(&in) % 6;
    for (int i = 0; i < n_patch; i++) {
        int into_driver = fz_u8(&in) & 1;
        uint8_t *base = into_driver ? (uint8_t *)&l->driver : (uint8_t *)&l->cfg;
        size_t span = into_driver ? sizeof l->driver : sizeof l->cfg;
        size_t off = fz_u16(&in) % span, len = 1 + fz_u8(&in) % 8;
        if (len > span - off)
            len = span - off;
        fz_bytes(&in, base + off, len);
    }
    l->n_commands = (int)(int8_t)fz_u8(&in) % (RT_MAX_COMMANDS + 4);
    fz_bytes(&in, l->command_input, sizeof l->command_input);
    for (int i = 0; i < RT_MAX_COMMANDS; i++)
        if (!(fz_u8(&in) & 0x80))
            l->command_input[i] %= 40;
    l->n_regions = (int)(int8_t)fz_u8(&in) % 8;
    fz_bytes(&in, l->regions, sizeof(rt_region) * 8);
    l->n_channels = fz_u8(&in) % (RT_MAX_CHANNELS + 2);
    owned own[RT_MAX_CHANNELS];
    memset(own, 0, sizeof own);
    memset(l->chan, 0, sizeof l->chan);
    int filled = l->n_channels < RT_MAX_CHANNELS ? l->n_channels : RT_MAX_CHANNELS;
    for (int c = 0; c < filled; c++)
        fill_channel(&in, &l->chan[c], &own[c]);
    int rc = rt_loop_prepare(l);
    if (rc > 0 || (rc != 0 && rc != -EINVAL && rc != -EBADF && rc != -EDOM && rc != -ENOTSOCK &&
                   rc != -EPROTOTYPE))
        abort();
    if (rc == 0)
        for (int c = 0; c < l->n_channels; c++)
            use_table(&l->chan[c]);
    for (int c = 0; c < filled; c++)
        free_owned(&own[c]);
    return 0;
}
