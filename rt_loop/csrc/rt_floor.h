/*
 * rt_floor.h - the machine's own wake-up floor: a C loop that only sleeps.
 *
 * What cyclictest measures, without the plant: a thread (SCHED_FIFO at the
 * loop's priority, optionally pinned, with mlockall) sleeps to absolute
 * deadlines t0 + n x period (clock_nanosleep, CLOCK_MONOTONIC,
 * TIMER_ABSTIME) and records how late it woke (1 us histogram). A wake-up
 * later than the next deadline skips ahead to the first deadline still in the
 * future, as the plant loop's "skip" policy does, and is counted in
 * late_wakeups; so the two are compared like for like. `dct-hil doctor` and
 * the loop benchmark (rt_loop.floor) run it alone, with and without PM QoS.
 *
 * Read by cffi: plain structs, integer #defines, prototypes.
 */
#ifndef RT_FLOOR_H
#define RT_FLOOR_H

#include <stdint.h>

#include "rt_loop.h"

typedef struct {
    double period_s;                  /* 50 us .. 100 ms */
    double duration_s;                /* > 0 */
    int priority;                     /* SCHED_FIFO priority, 0: leave the policy alone */
    int cpu;                          /* CPU to pin to, -1: any */
    int lock_memory;                  /* 1: mlockall(MCL_CURRENT | MCL_FUTURE) */
} rt_floor_config;

typedef struct {
    int rt_policy_ok;
    int affinity_ok;
    int memory_locked;
    uint64_t samples;                 /* wake-ups measured */
    uint64_t late_wakeups;            /* wake-ups after the next deadline (a tick would overrun) */
    uint64_t skipped;                 /* deadlines skipped after late wake-ups */
    double max_us;
    double sum_us;
    uint64_t hist[RT_HIST_BINS];      /* 1 us bins, the last holds everything above */
} rt_floor_result;

/* runs in the calling thread until duration_s has passed or *stop becomes
 * non-zero; restores the thread's policy and affinity. 0, or -EINVAL for a
 * bad configuration */
int rt_floor_run(const rt_floor_config *cfg, rt_floor_result *res, int *stop);

#endif
