/*
 * can_table.h - one table-driven CAN codec for any vehicle's matrix.
 *
 * A DBC (plus a mapping file) is turned into flat arrays by Python at
 * start-up (can_dbc/table.py, from cantools' parse): one ct_message per
 * message, one ct_signal per signal (a message's signals one after the
 * other, in cantools' order), one ct_mux_range per run of multiplexer
 * values. The functions here pack, unpack, protect and check frames from
 * those arrays alone: no code generation, no compiler, no Python, no
 * allocation, no clock (except ct_bench_tick, which only benchmarks).
 *
 * Values are physical, one double per signal, in the message's signal
 * order, with cantools' arithmetic so frames and values are bit-exact with
 * cantools' encode/decode:
 *   encode  NaN is sent as 0; the value is limited to [minimum, maximum]
 *           when minimum < maximum (the DBC's range; the contract's senders
 *           limit values to it); raw = (value - offset) / factor, rounded
 *           half to even (Python's round(); rint() in the default rounding
 *           mode), then limited to the bit field's range so it never
 *           overflows it; float signals store raw as IEEE 754 float32 or
 *           float64 unrounded.
 *   decode  raw * factor + offset in double; where cantools multiplies
 *           Python integers (an integer factor: raw * factor exact, and with
 *           an integer offset the sum exact too) the exact result rounded
 *           once to double; float signals with factor 1 and offset 0 return
 *           the stored float itself.
 * A multiplexed signal is encoded and decoded only while its multiplexer
 * (selector) is: the selector's physical value, truncated to an integer
 * (cantools' int()), must lie in one of the signal's ranges. On encode the
 * selector's value is the one actually written (limited and rounded), so
 * the frame and its branch always agree.
 *
 * Read by cffi like dct_plant.h: plain structs, integer #defines, prototypes.
 */
#ifndef CAN_TABLE_H
#define CAN_TABLE_H

#include <stddef.h>
#include <stdint.h>

/* longest frame (CAN FD), bytes */
#define CT_MAX_LENGTH 64

/* results of ct_check (can_dbc/codec.py STATUSES in this order) */
#define CT_RX_OK 0
#define CT_RX_UNKNOWN_ID 1
#define CT_RX_BAD_LENGTH 2
#define CT_RX_BAD_CRC 3
#define CT_RX_BAD_COUNTER 4

/* protection kinds, in the order of can_dbc/protection.py KINDS */
#define CT_PROT_NONE 0
#define CT_PROT_COUNTER 1
#define CT_PROT_DCT 2
#define CT_PROT_P1 3
#define CT_PROT_P2 4
#define CT_PROT_XOR 5
#define CT_PROT_P5 6
#define CT_PROT_P4 7
#define CT_PROT_P7 8

/* AUTOSAR E2E Profile 1 Data ID modes, in the order of P1_DATA_ID_MODES */
#define CT_P1_BOTH 0
#define CT_P1_ALT 1
#define CT_P1_LOW 2
#define CT_P1_NIBBLE 3

/* how raw values become physical ones (cantools' conversion classes) */
#define CT_CONV_LINEAR 0      /* raw * factor + offset in double */
#define CT_CONV_INTEGER 1     /* integer factor and offset: exact, rounded once */
#define CT_CONV_IDENTITY 2    /* factor 1, offset 0: the raw value itself */
/* integer factor, fractional offset: the exact product rounded once, plus offset in double */
#define CT_CONV_INT_FACTOR 3

/* multiplexer values lo..hi (inclusive) */
typedef struct {
    int64_t lo;
    int64_t hi;
} ct_mux_range;

typedef struct {
    uint16_t start;           /* DBC start bit (cantools' start): the LSB for
                                 little endian (Intel), the MSB for big
                                 endian (Motorola), bit b of byte B = 8 B + b */
    uint8_t length;           /* bits, 1..64 (float signals 32 or 64) */
    uint8_t big_endian;       /* 1: Motorola byte order */
    uint8_t is_signed;        /* two's complement */
    uint8_t is_float;         /* IEEE 754 float32/float64 (DBC SIG_VALTYPE_) */
    uint8_t conversion;       /* CT_CONV_* */
    uint8_t limited;          /* 1: minimum < maximum, values limited to them on encode */
    double factor;
    double offset;
    int64_t factor_int;       /* CT_CONV_INTEGER, CT_CONV_INT_FACTOR: the factor as an integer */
    int64_t offset_int;       /* CT_CONV_INTEGER: the offset as an integer (else 0) */
    uint64_t exact_raw;       /* CT_CONV_INTEGER, CT_CONV_INT_FACTOR: |raw| up to this
                                 gives an exact product (and sum) in double */
    double minimum;           /* physical range, used when limited */
    double maximum;
    double raw_min;           /* integer fields: the smallest raw value (0 or -2^(length-1)) */
    double raw_end;           /* integer fields: one past the largest (2^length or 2^(length-1)) */
    int32_t mux_signal;       /* index within the message of its multiplexer, -1: not multiplexed */
    uint32_t mux_first;       /* its multiplexer values: ct_table.mux[mux_first .. + mux_count - 1] */
    uint32_t mux_count;
} ct_signal;

typedef struct {
    uint32_t id;
    uint8_t extended;         /* 29-bit identifier */
    uint8_t fd;               /* CAN FD frame */
    uint8_t length;           /* data bytes, 0..64 */
    uint8_t protection;       /* CT_PROT_* */
    uint32_t first_signal;    /* its signals: ct_table.signals[first_signal .. + n_signals - 1] */
    uint32_t n_signals;
    int32_t crc_signal;       /* indices within the message, -1: none */
    int32_t counter_signal;
    int32_t nibble_signal;    /* P1 nibble mode: carries the Data ID's high nibble */
    int32_t crc_byte;         /* the byte the checksum fills (crc_signal's), -1: none;
                                 P5, P4, P7: the first byte of their header (P5: CRC
                                 low, CRC high, counter; P4: length, counter, Data ID,
                                 CRC; P7: CRC, length, counter, Data ID) */
    uint32_t counter_modulus; /* counter values 0 .. modulus-1 (P1 15, dct and P2 16,
                                 counter and xor 2^length, P5 256, P4 65536; P7
                                 0xFFFFFFFF: its 32-bit counter, written as given),
                                 0: no counter */
    uint16_t data_id;         /* P1, P5 */
    uint8_t data_id_mode;     /* P1: CT_P1_* */
    uint8_t max_delta_counter;/* a received counter may advance by 1 .. this */
    uint8_t data_id_list[16]; /* P2: the Data ID of each counter value; P4, P7: [0..3]
                                 the 32-bit Data ID, low byte first */
} ct_message;

typedef struct {
    const ct_message *messages;
    const ct_signal *signals;
    const ct_mux_range *mux;
    int32_t n_messages;
} ct_table;

/* receive-side state of one message */
typedef struct {
    int32_t last_counter;     /* -1 before the first accepted frame */
} ct_rx_state;

/* CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF; "123456789" -> 0x4B) */
uint8_t ct_crc8_j1850(const uint8_t *bytes, size_t n);
/* CRC-8H2F of AUTOSAR (poly 0x2F, init 0xFF, xorout 0xFF; "123456789" -> 0xDF) */
uint8_t ct_crc8_h2f(const uint8_t *bytes, size_t n);

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0;
 * "123456789" -> 0x29B1), the CRC of AUTOSAR E2E Profile 5 */
uint16_t ct_crc16_ccitt_false(const uint8_t *bytes, size_t n);
/* CRC-32P4 (poly 0xF4ACFB13, reflected, init and xorout 0xFFFFFFFF;
 * "123456789" -> 0x1697D06A), the CRC of AUTOSAR E2E Profile 4 */
uint32_t ct_crc32_p4(const uint8_t *bytes, size_t n);
/* CRC-64/XZ (ECMA-182 poly 0x42F0E1EBA9EA3693, reflected, init and xorout
 * all ones; "123456789" -> 0x995DC9BBDF1939FA), the CRC of E2E Profile 7 */
uint64_t ct_crc64(const uint8_t *bytes, size_t n);

/* index of the message with this identifier, -1 if none */
int ct_find(const ct_table *t, uint32_t id, int extended);

/* Packs values (one per signal of message msg, physical) into data
 * (length bytes, the rest untouched); bits no active signal covers are 0.
 * The protection signals are packed like any other: ct_protect overwrites
 * them. Returns the length, -1 for a bad msg. */
int ct_encode(const ct_table *t, int msg, const double *values, uint8_t *data);

/* ct_encode, adding to *saturated (if not NULL) the number of values it
 * limited to their signal's [minimum, maximum] or bit field (NaN, sent as 0,
 * not counted; signals of branches the frame does not carry not counted) */
int ct_encode_counted(const ct_table *t, int msg, const double *values, uint8_t *data,
                      uint32_t *saturated);

/* Unpacks data (len bytes) into values (one per signal, physical).
 * Multiplexed signals whose branch the frame does not select are left
 * untouched; written (if not NULL, one byte per signal) is set to 1 for
 * each signal written, 0 for the others. Returns the number of signals
 * written, -1 when msg is bad or len is not the message's length. */
/* Writes a raw value into signal `signal` (index within message msg) of an
 * encoded frame, as it is, masked to the bit field: no limiting (the value
 * a sender uses for "invalid" may lie outside the DBC's range). Returns 0,
 * -1 for a bad msg or signal. */
int ct_put_raw(const ct_table *t, int msg, int signal, int64_t raw, uint8_t *data);
int ct_decode(const ct_table *t, int msg, const uint8_t *data, int len, double *values,
              uint8_t *written);

/* Writes the counter (counter modulo counter_modulus), for P1 nibble mode
 * the Data ID nibble, then the checksum, as the message's protection says
 * (P5: counter byte, then the CRC's two bytes; P4: length, counter, Data ID,
 * then the CRC; P7 as P4, its 32-bit counter as given; whatever signals lie
 * there). P7 returns its counter's low 31 bits.
 * Returns the counter value written (0 without a counter), -1 for a bad msg. */
int ct_protect(const ct_table *t, int msg, uint8_t *data, uint32_t counter);

/* Checks a received frame of message msg (P5: the counter is its header's
 * byte, 0..255; P4: its 16-bit field, P7: its 32-bit field, compared modulo
 * 2^32, and a length or Data ID field other than the message's is
 * CT_RX_BAD_CRC): CT_RX_BAD_LENGTH when len is not
 * the message's length, CT_RX_BAD_CRC when the checksum (or P1's Data ID
 * nibble) is wrong, CT_RX_BAD_COUNTER when the counter is out of its range
 * (P1: 15), repeats, or advances by more than max_delta_counter; else
 * CT_RX_OK. The first frame (last_counter -1) is accepted with any valid
 * counter. state (may be NULL: no counter check) moves on only when the
 * frame is accepted. CT_RX_UNKNOWN_ID for a bad msg. */
int ct_check(const ct_table *t, int msg, const uint8_t *data, int len, ct_rx_state *state);

/* Benchmark only (reads the clock): the CAN work of one tick, repeated
 * `iterations` times between two CLOCK_MONOTONIC readings: encode and
 * protect each of the n_tx messages tx[] from tx_values (their signals'
 * values one message after the other), then check and decode each of the
 * n_rx messages rx[] (at most 8) from frames prepared beforehand from
 * rx_values (encoded and protected with successive counters: at most 16,
 * the receive state starting again at each run of them when the counter's
 * range is longer), into rx_out (as long as rx_values). *accepted receives the number of frames the
 * checks accepted. Returns nanoseconds per tick, -1 on bad arguments. */
#define CT_BENCH_MAX_RX 8
double ct_bench_tick(const ct_table *t, const int32_t *tx, int32_t n_tx, const double *tx_values,
                     const int32_t *rx, int32_t n_rx, const double *rx_values, double *rx_out,
                     int64_t iterations, int64_t *accepted);

#endif
