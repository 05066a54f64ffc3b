/*
 * dct_bench.c - times single plant steps with the monotonic clock.
 */
#define _POSIX_C_SOURCE 199309L

#include <time.h>

#include "dct_bench.h"

#ifndef DCT_CFLAGS
#define DCT_CFLAGS "unknown"
#endif

#if defined(__clang__)
#define DCT_COMPILER "clang " __clang_version__
#elif defined(__GNUC__)
#define DCT_COMPILER "gcc " __VERSION__
#else
#define DCT_COMPILER "unknown compiler"
#endif

int dct_bench_steps(dct_plant *plant, int n, double *step_ns)
{
    struct timespec t0, t1;
    int i;

    for (i = 0; i < n; i++) {
        int status;

        clock_gettime(CLOCK_MONOTONIC, &t0);
        status = dct_plant_step(plant, 1);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        step_ns[i] = (double)(t1.tv_sec - t0.tv_sec) * 1e9 + (double)(t1.tv_nsec - t0.tv_nsec);
        if (status != 0)
            return status;
    }
    return 0;
}

const char *dct_bench_build_info(void)
{
    return DCT_COMPILER "; " DCT_CFLAGS;
}
