/* dct_util.h - small helpers shared by the C core (internal, not part of the API). */
#ifndef DCT_UTIL_H
#define DCT_UTIL_H

#include <math.h>

#define DCT_PI 3.14159265358979323846
#define DCT_RPM_PER_RAD_S (30.0 / DCT_PI)
#define DCT_RAD_S_PER_RPM (DCT_PI / 30.0)
#define DCT_PA_PER_BAR 1.0e5

/* Subnormal numbers flushed to zero while the plant computes. A state that
 * decays towards zero (the speeds and torques of a stalled engine, a car
 * long at rest) reaches subnormal magnitudes after some minutes, and every
 * operation on them then takes the processor's slow path: measured, a step
 * of 1.2 us became 17.5 us. Below 2.2e-308 nothing is physical, so the
 * step runs with flush-to-zero and denormals-are-zero, and gives the
 * caller's floating-point mode back afterwards (a Python interpreter, an
 * FMU's host). Where the processor has no such mode, nothing changes. */
#if defined(__x86_64__) || defined(_M_X64) || (defined(__SSE2__) && !defined(__aarch64__))
#include <xmmintrin.h>
typedef unsigned int dct_fp_mode;
static inline dct_fp_mode dct_fp_flush_begin(void)
{
    unsigned int mode = _mm_getcsr();
    _mm_setcsr(mode | 0x8040u);           /* FTZ (bit 15) | DAZ (bit 6) */
    return mode;
}
static inline void dct_fp_flush_end(dct_fp_mode mode) { _mm_setcsr(mode); }
#elif defined(__aarch64__) && defined(__GNUC__)
typedef unsigned long dct_fp_mode;
static inline dct_fp_mode dct_fp_flush_begin(void)
{
    unsigned long fpcr;
    __asm__ __volatile__("mrs %0, fpcr" : "=r"(fpcr));
    __asm__ __volatile__("msr fpcr, %0" : : "r"(fpcr | (1ul << 24)));   /* FZ */
    return fpcr;
}
static inline void dct_fp_flush_end(dct_fp_mode mode)
{
    __asm__ __volatile__("msr fpcr, %0" : : "r"(mode));
}
#else
typedef int dct_fp_mode;
static inline dct_fp_mode dct_fp_flush_begin(void) { return 0; }
static inline void dct_fp_flush_end(dct_fp_mode mode) { (void)mode; }
#endif

static inline double dct_clamp(double x, double lo, double hi)
{
    return x < lo ? lo : (x > hi ? hi : x);
}

static inline double dct_sq(double x) { return x * x; }

static inline double dct_sign(double x) { return (x > 0.0) - (x < 0.0); }

/* tanh(x / width): a sign that fades through zero over `width`. Past
 * |x| = 20 width tanh is 1 to the last bit, so the call is skipped there:
 * most of the time shafts turn fast and this costs a compare. Within, tanh
 * as (1 - e) / (1 + e) with e = exp(-2 |a|): one exp (libm's tanh goes
 * through expm1 and costs about twice as much), odd to the bit, within
 * 1e-16 of tanh (near 0 the difference 1 - e loses the relative digits a
 * smoothing law does not need). validation/pyplant.py computes the same. */
static inline double dct_smooth_sign(double x, double width)
{
    double a = x / width;
    if (a > 20.0)
        return 1.0;
    if (a < -20.0)
        return -1.0;
    double e = exp(-2.0 * fabs(a));
    double t = (1.0 - e) / (1.0 + e);
    return a < 0.0 ? -t : t;
}

/* exp(-x^2), skipped where it underflows below 1e-17 */
static inline double dct_gauss(double x)
{
    double q = x * x;
    return q > 40.0 ? 0.0 : exp(-q);
}

/* linear interpolation in a table of n points (x increasing), held flat
 * outside; 0 for an empty table */
static inline double dct_interp1(const double *x, const double *y, int n, double xq)
{
    if (n <= 0)
        return 0.0;
    if (xq <= x[0])
        return y[0];
    if (xq >= x[n - 1])
        return y[n - 1];
    int i = 1;
    while (i < n - 1 && xq > x[i])
        i++;
    return y[i - 1] + (xq - x[i - 1]) / (x[i] - x[i - 1]) * (y[i] - y[i - 1]);
}

/* 1 at 0, 0 from `width` on, smooth (raised cosine) in between */
static inline double dct_fade(double x, double width)
{
    double a = fabs(x) / width;
    if (a >= 1.0)
        return 0.0;
    return 0.5 * (1.0 + cos(DCT_PI * a));
}

#endif
