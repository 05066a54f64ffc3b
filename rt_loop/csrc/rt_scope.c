/*
 * rt_scope.c - min and max of chosen loop values over buckets of ticks, for
 * a live view that reads every tick without the tick waiting for it (see
 * rt_loop.h, "the scope"); the configuration's hand-over between Python
 * (rt_scope_publish) and the tick (rt_scope_acked).
 */
#include "rt_internal.h"

#include <stddef.h>

static void bucket_reset(rt_scope_run *s)
{
    s->filled = 0;
    for (uint32_t i = 0; i < s->n; i++) {
        s->min[i] = INFINITY;
        s->max[i] = -INFINITY;
    }
}

static int config_ok(const rt_scope_config *c)
{
    if (c->n > RT_SCOPE_TRACES || c->bucket_ticks < 1 || c->bucket_ticks > RT_SCOPE_MAX_BUCKET)
        return 0;
    for (uint32_t i = 0; i < c->n; i++)
        if (c->offset[i] % 8u != 0 || (size_t)c->offset[i] + sizeof(double) > sizeof(rt_loop))
            return 0;
    return 1;
}

/* a configuration published since the last look: taken whole or refused */
static void pickup(rt_scope_run *s, rt_loop *l, uint32_t gen)
{
    const rt_scope_config *c = &l->scope_cfg[gen & 1u];
    s->gen = gen;
    if (config_ok(c)) {
        s->n = c->n;
        s->bucket_ticks = c->bucket_ticks;
        memcpy(s->offset, c->offset, sizeof s->offset);
    } else {
        s->n = 0;
        atomic_store_explicit(A64(&l->scope_refused),
                              atomic_load_explicit(A64(&l->scope_refused), memory_order_relaxed) +
                                  1u,
                              memory_order_relaxed);
    }
    bucket_reset(s);
    atomic_store_explicit(A32(&l->scope_ack), gen, memory_order_release);
}

static void push(rt_scope_run *s, rt_loop *l, uint64_t tick, double time_s)
{
    rt_scope_ring *g = &l->scope;
    uint32_t head = atomic_load_explicit(A32(&g->head), memory_order_relaxed);
    uint32_t tail = atomic_load_explicit(A32(&g->tail), memory_order_acquire);
    if (head - tail >= RT_SCOPE_RING_SIZE) {
        atomic_store_explicit(A64(&g->dropped),
                              atomic_load_explicit(A64(&g->dropped), memory_order_relaxed) + 1u,
                              memory_order_relaxed);
        return;
    }
    rt_scope_bucket *b = &g->buckets[head & (RT_SCOPE_RING_SIZE - 1u)];
    b->tick = tick;
    b->time_s = time_s;
    b->gen = s->gen;
    b->ticks = s->filled;
    memcpy(b->min, s->min, s->n * sizeof(double));
    memcpy(b->max, s->max, s->n * sizeof(double));
    atomic_store_explicit(A32(&g->head), head + 1u, memory_order_release);
}

RT_TICK_CODE
void rts_tick(rt_scope_run *s, rt_loop *l, uint64_t tick, double time_s)
{
    uint32_t gen = atomic_load_explicit(A32(&l->scope_gen), memory_order_acquire);
    if (gen != s->gen)
        pickup(s, l, gen);
    if (s->n == 0)
        return;
    const char *base = (const char *)l;
    for (uint32_t i = 0; i < s->n; i++) {
        double v;
        memcpy(&v, base + s->offset[i], sizeof v);
        if (v < s->min[i])            /* NaN compares false: left out */
            s->min[i] = v;
        if (v > s->max[i])
            s->max[i] = v;
    }
    if (++s->filled >= s->bucket_ticks) {
        push(s, l, tick, time_s);
        bucket_reset(s);
    }
}

void rt_scope_publish(rt_loop *l, uint32_t gen)
{
    atomic_store_explicit(A32(&l->scope_gen), gen, memory_order_release);
}

uint32_t rt_scope_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->scope_ack), memory_order_acquire);
}
