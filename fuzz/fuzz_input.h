/*
 * fuzz_input.h - reading a libFuzzer input as a stream of small fields.
 *
 * Every read succeeds: past the end of the input it gives zeros, so a
 * short input is a valid (mostly empty) case and the targets need no
 * length checks of their own.
 */
#ifndef FUZZ_INPUT_H
#define FUZZ_INPUT_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

typedef struct {
    const uint8_t *p;
    size_t n;
} fz_in;

static inline size_t fz_left(const fz_in *in) { return in->n; }

static inline void fz_bytes(fz_in *in, void *out, size_t k)
{
    size_t take = k < in->n ? k : in->n;
    memcpy(out, in->p, take);
    memset((uint8_t *)out + take, 0, k - take);
    in->p += take;
    in->n -= take;
}

static inline uint8_t fz_u8(fz_in *in)
{
    uint8_t v;
    fz_bytes(in, &v, 1);
    return v;
}

static inline uint16_t fz_u16(fz_in *in)
{
    uint16_t v;
    fz_bytes(in, &v, 2);
    return v;
}

static inline uint32_t fz_u32(fz_in *in)
{
    uint32_t v;
    fz_bytes(in, &v, 4);
    return v;
}

static inline uint64_t fz_u64(fz_in *in)
{
    uint64_t v;
    fz_bytes(in, &v, 8);
    return v;
}

static inline double fz_f64(fz_in *in)
{
    double v;
    fz_bytes(in, &v, 8);
    return v;
}

/* 0 .. n-1 (n > 0) */
static inline uint32_t fz_below(fz_in *in, uint32_t n) { return fz_u8(in) % n; }

#endif
