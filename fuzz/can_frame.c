/*
 * can_frame.c - libFuzzer target: CAN frames found, checked (CRC, counter,
 * E2E profiles) and decoded against a table the input describes.
 *
 * The C codec trusts its tables: no C function validates a ct_table, the
 * Python builder (can_dbc/table.py _check_layout, _check_protection) is
 * the one gate. So the table is built here within what the builder
 * allows (signals inside the frame, float signals of 32 or 64 bits, finite
 * non-zero factors, multiplexers that are unmultiplexed signals of the
 * same message, checksums filling one byte, 4-bit counters for dct/P1/P2,
 * E2E headers inside the frame), with every other field arbitrary.
 * Then each frame of the rest of the input goes through ct_find, ct_check
 * (with a receive state) and ct_decode; and a frame this codec encoded and
 * protected must pass its own check (the one oracle beyond the sanitizers).
 */
#include <math.h>
#include <stdlib.h>

#include "can_table.h"
#include "fuzz_input.h"

#define MAX_MSGS 4
#define MAX_SIGS 8
#define MAX_MUX 4

static const uint8_t header_bytes[] = {[CT_PROT_P5] = 3, [CT_PROT_P4] = 12, [CT_PROT_P7] = 20};

/* DBC start bit of a field whose most significant bit is linear bit msb
 * (Motorola, sawtooth numbering) */
static uint16_t motorola_start(unsigned msb) { return (uint16_t)(8 * (msb / 8) + 7 - msb % 8); }

static double finite_or(double v, double dflt) { return isfinite(v) ? v : dflt; }

static void fill_signal(fz_in *in, ct_signal *s, unsigned frame_bits)
{
    memset(s, 0, sizeof *s);
    s->mux_signal = -1;
    uint8_t kind = fz_u8(in);
    s->is_float = (kind & 1) && frame_bits >= 32;
    if (s->is_float)
        s->length = (kind & 2) && frame_bits >= 64 ? 64 : 32;
    else
        s->length = (uint8_t)(1 + fz_u8(in) % (frame_bits < 64 ? frame_bits : 64));
    s->big_endian = (kind >> 2) & 1;
    s->is_signed = (kind >> 3) & 1;
    unsigned pos = fz_u8(in) % (frame_bits - s->length + 1);
    s->start = s->big_endian ? motorola_start(pos) : (uint16_t)pos;
    switch ((kind >> 4) & 3) {
    case CT_CONV_IDENTITY:
        s->conversion = CT_CONV_IDENTITY;
        s->factor = 1.0;
        break;
    case CT_CONV_INTEGER:
    case CT_CONV_INT_FACTOR: {
        int64_t f = (int8_t)fz_u8(in);
        if (f == 0)
            f = 1;
        s->conversion = (kind >> 4) & 3;
        s->factor_int = f;
        s->factor = (double)f;
        if (s->conversion == CT_CONV_INTEGER) {
            s->offset_int = (int16_t)fz_u16(in);
            s->offset = (double)s->offset_int;
        } else {
            s->offset = finite_or(fz_f64(in), 0.5);
        }
        s->exact_raw = (1ull << 53) / (uint64_t)(llabs(f) + llabs(s->offset_int) + 1);
        break;
    }
    default:
        s->conversion = CT_CONV_LINEAR;
        s->factor = finite_or(fz_f64(in), 0.1);
        if (s->factor == 0.0)
            s->factor = 0.1;
        s->offset = finite_or(fz_f64(in), 0.0);
        break;
    }
    if (kind & 0x40) {
        double a = finite_or(fz_f64(in), -1.0), b = finite_or(fz_f64(in), 1.0);
        s->minimum = a < b ? a : b;
        s->maximum = a < b ? b : a;
        s->limited = s->minimum < s->maximum;
    }
    if (!s->is_float) {
        s->raw_min = s->is_signed ? -ldexp(1.0, s->length - 1) : 0.0;
        s->raw_end = s->is_signed ? ldexp(1.0, s->length - 1) : ldexp(1.0, s->length);
    }
}

/* a plain integer signal of `bits` at linear bit `pos` (little endian) */
static void plain_field(ct_signal *s, unsigned pos, unsigned bits)
{
    memset(s, 0, sizeof *s);
    s->start = (uint16_t)pos;
    s->length = (uint8_t)bits;
    s->conversion = CT_CONV_IDENTITY;
    s->factor = 1.0;
    s->raw_end = ldexp(1.0, bits);
    s->mux_signal = -1;
}

static void fill_protection(fz_in *in, ct_message *m, ct_signal *sig, uint32_t n)
/* checksum, counter and nibble signals replace the message's first signals */
{
    m->crc_signal = m->counter_signal = m->nibble_signal = m->crc_byte = -1;
    m->counter_modulus = 0;
    m->max_delta_counter = fz_u8(in);
    uint8_t kind = (uint8_t)fz_below(in, CT_PROT_P7 + 1);
    m->protection = CT_PROT_NONE;
    if (kind == CT_PROT_P5 || kind == CT_PROT_P4 || kind == CT_PROT_P7) {
        unsigned size = header_bytes[kind];
        if (m->length < size)
            return;
        m->protection = kind;
        m->crc_byte = (int32_t)(fz_u8(in) % (m->length - size + 1));
        m->counter_modulus = kind == CT_PROT_P5 ? 256 : kind == CT_PROT_P4 ? 65536 : 0xFFFFFFFFu;
        m->data_id = fz_u16(in);
        fz_bytes(in, m->data_id_list, 4);
        /* signals may lie on the header: the builder refuses them, the codec
         * overwrites them (ct_protect writes the header last) */
        return;
    }
    int needs_crc = kind == CT_PROT_DCT || kind == CT_PROT_P1 || kind == CT_PROT_P2 ||
                    kind == CT_PROT_XOR;
    int needs_counter = kind != CT_PROT_XOR && kind != CT_PROT_NONE;
    if (kind == CT_PROT_NONE || n < (uint32_t)(needs_crc + needs_counter) || m->length < 1 ||
        (needs_crc && needs_counter && m->length < 2))
        return;
    m->protection = kind;
    uint32_t at = 0;
    if (needs_crc) { /* the checksum: one whole byte, an unmultiplexed signal */
        m->crc_signal = (int32_t)at;
        m->crc_byte = (int32_t)(fz_u8(in) % m->length);
        plain_field(&sig[at], 8u * (unsigned)m->crc_byte, 8);
        at++;
    }
    unsigned cbits = kind == CT_PROT_COUNTER ? 1 + fz_u8(in) % 16 : 4;
    if (needs_counter || (kind == CT_PROT_XOR && (fz_u8(in) & 1) && n > at)) {
        unsigned byte = m->crc_byte >= 0 ? (unsigned)(m->crc_byte + 1) % m->length : 0;
        if (8 * byte + cbits > 8u * m->length)
            byte = 0;
        if ((int)byte == m->crc_byte) { /* a one-byte frame: no room for both */
            m->protection = CT_PROT_NONE;
            m->crc_signal = -1;
            m->crc_byte = -1;
            return;
        }
        m->counter_signal = (int32_t)at;
        plain_field(&sig[at], 8 * byte, cbits);
        m->counter_modulus = kind == CT_PROT_P1 ? 15 : (kind == CT_PROT_DCT || kind == CT_PROT_P2)
                                                          ? 16
                                                          : (1u << cbits);
    }
    if (kind == CT_PROT_P1) {
        m->data_id = fz_u16(in);
        m->data_id_mode = (uint8_t)fz_below(in, 4);
        if (m->data_id_mode == CT_P1_NIBBLE) {
            if (n < 3 || 8u * m->length < 12) {
                m->data_id_mode = CT_P1_BOTH;
            } else {
                m->nibble_signal = 2;
                plain_field(&sig[2], m->counter_signal >= 0 ? sig[m->counter_signal].start + 4 : 0, 4);
            }
        }
    }
    if (kind == CT_PROT_P2)
        fz_bytes(in, m->data_id_list, 16);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fz_in in = {data, size};
    ct_message msgs[MAX_MSGS];
    ct_signal sigs[MAX_MSGS * MAX_SIGS];
    ct_mux_range mux[MAX_MSGS * MAX_SIGS * MAX_MUX];
    memset(msgs, 0, sizeof msgs);
    uint32_t n_sig = 0, n_mux = 0;
    int n_msgs = 1 + (int)fz_below(&in, MAX_MSGS);
    for (int mi = 0; mi < n_msgs; mi++) {
        ct_message *m = &msgs[mi];
        uint8_t f = fz_u8(&in);
        m->extended = f & 1;
        m->fd = (f >> 1) & 1;
        m->id = fz_u32(&in) & (m->extended ? 0x1FFFFFFFu : 0x7FFu);
        m->length = (uint8_t)(fz_u8(&in) % ((m->fd ? CT_MAX_LENGTH : 8) + 1));
        m->first_signal = n_sig;
        m->n_signals = m->length ? fz_below(&in, MAX_SIGS + 1) : 0;
        ct_signal *s = &sigs[n_sig];
        for (uint32_t i = 0; i < m->n_signals; i++)
            fill_signal(&in, &s[i], 8u * m->length);
        fill_protection(&in, m, s, m->n_signals);
        for (uint32_t i = 0; i < m->n_signals; i++) { /* multiplexed by an unmultiplexed signal */
            uint8_t sel = fz_u8(&in);
            if (!(sel & 0x80) || s[i].mux_signal >= 0)
                continue;
            uint32_t j = (sel & 0x7f) % m->n_signals;
            if (j == i || s[j].mux_signal >= 0 || (int32_t)i == m->crc_signal ||
                (int32_t)i == m->counter_signal || (int32_t)i == m->nibble_signal)
                continue;
            s[i].mux_signal = (int32_t)j;
            s[i].mux_first = n_mux;
            s[i].mux_count = 1 + fz_below(&in, MAX_MUX);
            for (uint32_t k = 0; k < s[i].mux_count; k++) {
                int64_t lo = (int8_t)fz_u8(&in), hi = lo + fz_u8(&in);
                mux[n_mux + k].lo = lo;
                mux[n_mux + k].hi = hi;
            }
            n_mux += s[i].mux_count;
        }
        /* a selector may itself have been chosen multiplexed before: unmultiplex it */
        for (uint32_t i = 0; i < m->n_signals; i++)
            if (s[i].mux_signal >= 0 && s[s[i].mux_signal].mux_signal >= 0)
                s[i].mux_signal = -1;
        n_sig += m->n_signals;
    }
    ct_table t = {msgs, sigs, mux, n_msgs};
    ct_rx_state st[MAX_MSGS];
    for (int i = 0; i < MAX_MSGS; i++)
        st[i].last_counter = -1;
    double values[MAX_SIGS];
    uint8_t written[MAX_SIGS];

    /* the codec against itself: what it encodes and protects, it accepts */
    for (int mi = 0; mi < n_msgs; mi++) {
        uint8_t frame[CT_MAX_LENGTH] = {0};
        for (uint32_t i = 0; i < msgs[mi].n_signals; i++)
            values[i] = fz_f64(&in);
        if (ct_encode(&t, mi, values, frame) != msgs[mi].length)
            abort();
        int counter = ct_protect(&t, mi, frame, fz_u32(&in));
        if (counter < 0)
            abort();
        ct_rx_state fresh = {-1};
        if (ct_check(&t, mi, frame, msgs[mi].length, &fresh) != CT_RX_OK)
            abort();
        ct_decode(&t, mi, frame, msgs[mi].length, values, written);
    }
    /* then the frames of the input */
    while (fz_left(&in) > 0) {
        uint8_t head = fz_u8(&in);
        uint32_t id = head & 0x80 ? msgs[head % n_msgs].id : fz_u32(&in);
        int extended = head & 0x80 ? msgs[head % n_msgs].extended : head & 1;
        int len = (int)(fz_u8(&in) % (CT_MAX_LENGTH + 1));
        uint8_t frame[CT_MAX_LENGTH];
        fz_bytes(&in, frame, (size_t)len);
        int mi = ct_find(&t, id, extended);
        if (mi < -1 || mi >= n_msgs)
            abort();
        if (mi < 0)
            continue;
        int rc = ct_check(&t, mi, frame, len, &st[mi]);
        if (rc < CT_RX_OK || rc > CT_RX_BAD_COUNTER)
            abort();
        int n = ct_decode(&t, mi, frame, len, values, written);
        if (n > (int)msgs[mi].n_signals || (n < 0 && len == msgs[mi].length))
            abort();
    }
    return 0;
}
