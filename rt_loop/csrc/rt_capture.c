/*
 * rt_capture.c - chosen loop values copied at every tick (or every k-th)
 * into the capture ring, for captures with triggers and pre-trigger history
 * cut out by a reader that never makes the tick wait (see rt_loop.h,
 * "captures"); the configuration's hand-over between Python
 * (rt_capture_publish) and the tick (rt_capture_acked).
 */
#include "rt_internal.h"

#include <stddef.h>
#include <time.h>

_Static_assert((RT_CAPTURE_RING_SIZE & (RT_CAPTURE_RING_SIZE - 1)) == 0,
               "RT_CAPTURE_RING_SIZE must be a power of two");

static int config_ok(const rt_capture_config *c)
{
    if (c->n > RT_CAPTURE_SIGNALS || c->every < 1 || c->every > RT_CAPTURE_MAX_EVERY)
        return 0;
    for (uint32_t i = 0; i < c->n; i++) {
        uint32_t src = c->source[i];
        if (src & RT_CAPTURE_CMD) {
            if ((src & ~RT_CAPTURE_CMD) >= RT_MAX_COMMANDS)
                return 0;
        } else if (src % 8u != 0 || (size_t)src + sizeof(double) > sizeof(rt_loop)) {
            return 0;
        }
    }
    return 1;
}

/* a configuration published since the last look: taken whole or refused */
static void pickup(rt_capture_run *s, rt_loop *l, uint32_t gen)
{
    const rt_capture_config *c = &l->capture_cfg[gen & 1u];
    s->gen = gen;
    if (config_ok(c)) {
        s->n = c->n;
        s->every = c->every;
        memcpy(s->source, c->source, sizeof s->source);
    } else {
        s->n = 0;
        atomic_store_explicit(A64(&l->capture_refused),
                              atomic_load_explicit(A64(&l->capture_refused), RELAXED) + 1u,
                              RELAXED);
    }
    atomic_store_explicit(A32(&l->capture_ack), gen, RELEASE);
}

RT_TICK_CODE
void rtc_tick(rt_capture_run *s, rt_loop *l, const double *cmd, uint64_t tick, double time_s)
{
    uint32_t gen = atomic_load_explicit(A32(&l->capture_gen), ACQUIRE);
    if (gen != s->gen)
        pickup(s, l, gen);
    if (s->n == 0 || tick % s->every != 0)
        return;
    rt_capture_ring *g = &l->capture;
    uint32_t head;
    if (!ring_slot(&g->head, &g->tail, RT_CAPTURE_RING_SIZE, &g->dropped, &head))
        return;
    rt_capture_record *e = &g->records[head & (RT_CAPTURE_RING_SIZE - 1u)];
    const char *base = (const char *)l;
    for (uint32_t i = 0; i < s->n; i++) {
        uint32_t src = s->source[i];
        if (src & RT_CAPTURE_CMD)
            e->values[i] = cmd[src & ~RT_CAPTURE_CMD];
        else
            memcpy(&e->values[i], base + src, sizeof(double));
    }
    e->tick = tick;
    e->time_s = time_s;
    e->gen = s->gen;
    e->n = s->n;
    atomic_store_explicit(A32(&g->head), head + 1u, RELEASE);
}

void rt_capture_publish(rt_loop *l, uint32_t gen)
{
    atomic_store_explicit(A32(&l->capture_gen), gen, RELEASE);
}

uint32_t rt_capture_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->capture_ack), ACQUIRE);
}

double rt_capture_bench(rt_loop *l, int64_t iterations)
{
    if (!l || iterations < 1)
        return -1.0;
    rt_capture_run s;                 /* benchmark only: not the loop's */
    memset(&s, 0, sizeof s);
    s.gen = atomic_load_explicit(A32(&l->capture_gen), ACQUIRE) - 1u;   /* taken at the first */
    static double cmd[RT_MAX_COMMANDS];
    rt_capture_ring *g = &l->capture;
    uint64_t dropped0 = g->dropped;
    uint32_t refused0 = (uint32_t)l->capture_refused;
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int64_t i = 0; i < iterations; i++) {
        rtc_tick(&s, l, cmd, (uint64_t)i, (double)i);
        atomic_store_explicit(A32(&g->tail), atomic_load_explicit(A32(&g->head), RELAXED), RELEASE);
    }
    clock_gettime(CLOCK_MONOTONIC, &b);
    g->dropped = dropped0;
    int bad = (uint32_t)l->capture_refused != refused0;
    double ns = (double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec);
    return bad ? -1.0 : ns / (double)iterations;
}
