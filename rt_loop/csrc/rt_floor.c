/*
 * rt_floor.c - the wake-up floor loop (contract: rt_floor.h).
 *
 * Per deadline: sleep to it, latency = wake - deadline (the OS's share, as
 * cyclictest reports it and as the plant loop reports its own wake-up
 * latency when it does not spin). No work in between: what is left is the
 * scheduler, the timer interrupt, power management and the hypervisor.
 */
#include "rt_floor.h"

#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>

#define FLOOR_PERIOD_MIN_S 50e-6
#define FLOOR_PERIOD_MAX_S 0.1

static inline int64_t floor_now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static inline void floor_sleep_until(int64_t t_ns)
{
    struct timespec ts = {.tv_sec = t_ns / 1000000000, .tv_nsec = t_ns % 1000000000};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR)
        ;
}

int rt_floor_run(const rt_floor_config *cfg, rt_floor_result *res, int *stop)
{
    if (!cfg || !res || !(cfg->period_s >= FLOOR_PERIOD_MIN_S && cfg->period_s <= FLOOR_PERIOD_MAX_S) ||
        !(cfg->duration_s > 0.0) || cfg->priority < 0 || cfg->priority > 99)
        return -EINVAL;
    memset(res, 0, sizeof *res);

    pthread_t self = pthread_self();
    int old_policy = 0, policy_set = 0, affinity_set = 0;
    struct sched_param old_param;
    cpu_set_t old_cpus;
    memset(&old_param, 0, sizeof old_param);
    if (cfg->priority > 0 && pthread_getschedparam(self, &old_policy, &old_param) == 0) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = cfg->priority;
        if (pthread_setschedparam(self, SCHED_FIFO, &sp) == 0)
            res->rt_policy_ok = policy_set = 1;
    }
    if (cfg->cpu >= 0 && pthread_getaffinity_np(self, sizeof old_cpus, &old_cpus) == 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cfg->cpu, &set);
        if (pthread_setaffinity_np(self, sizeof set, &set) == 0)
            res->affinity_ok = affinity_set = 1;
    }
    if (cfg->lock_memory && mlockall(MCL_CURRENT | MCL_FUTURE) == 0)
        res->memory_locked = 1;

    int64_t period_ns = (int64_t)(cfg->period_s * 1e9 + 0.5);
    uint64_t limit = (uint64_t)(cfg->duration_s / cfg->period_s + 0.5);
    if (limit < 1)
        limit = 1;
    int64_t t0 = floor_now_ns() + period_ns;
    for (uint64_t n = 0; n < limit;) {
        if (stop && atomic_load_explicit((_Atomic int *)stop, memory_order_relaxed))
            break;
        int64_t deadline = t0 + (int64_t)n * period_ns;
        floor_sleep_until(deadline);
        int64_t wake = floor_now_ns();
        double us = (double)(wake - deadline) / 1e3;
        if (us < 0.0)
            us = 0.0;
        int bin = (int)us;
        if (bin >= RT_HIST_BINS)
            bin = RT_HIST_BINS - 1;
        res->hist[bin]++;
        res->samples++;
        res->sum_us += us;
        if (us > res->max_us)
            res->max_us = us;
        uint64_t next = n + 1;
        if (wake > deadline + period_ns) {
            res->late_wakeups++;
            next = (uint64_t)((wake - t0) / period_ns) + 1u;
            if (next > limit)
                next = limit;
            res->skipped += next - (n + 1);
        }
        n = next;
    }

    if (policy_set)
        (void)pthread_setschedparam(self, old_policy, &old_param);
    if (affinity_set)
        (void)pthread_setaffinity_np(self, sizeof old_cpus, &old_cpus);
    return 0;
}
