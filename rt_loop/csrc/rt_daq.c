/*
 * rt_daq.c - XCP DAQ inside the loop (contract: rt_loop.h, "DAQ"): a new
 * configuration taken at the start of a tick (checked once, refused whole),
 * the ODTs of every list whose event fires copied into the DAQ ring at its
 * end; the configuration's hand-over and a benchmark of the copy.
 */
#include "rt_internal.h"

#include <time.h>

/* a configuration the tick may copy from: every index inside its arrays,
 * every entry inside the loop, every ODT within one DTO */
static int daq_config_ok(const rt_daq_config *c)
{
    if (c->n_lists > RT_DAQ_MAX_LISTS)
        return 0;
    for (uint32_t i = 0; i < c->n_lists; i++) {
        const rt_daq_list *d = &c->lists[i];
        if (d->event >= RT_N_EVENTS || d->first_odt > RT_DAQ_MAX_ODTS ||
            d->n_odts > RT_DAQ_MAX_ODTS - d->first_odt)
            return 0;
        for (uint32_t o = d->first_odt; o < d->first_odt + d->n_odts; o++) {
            const rt_odt *t = &c->odts[o];
            if (t->first_entry > RT_DAQ_MAX_ENTRIES || t->n_entries > RT_DAQ_MAX_ENTRIES - t->first_entry)
                return 0;
            uint32_t bytes = 0;
            for (uint32_t e = t->first_entry; e < t->first_entry + t->n_entries; e++) {
                const rt_odt_entry *x = &c->entries[e];
                if (x->size == 0 || x->size > RT_DAQ_ODT_BYTES || x->offset > sizeof(rt_loop) ||
                    x->size > sizeof(rt_loop) - x->offset)
                    return 0;
                bytes += x->size;
            }
            if (bytes > RT_DAQ_ODT_BYTES)
                return 0;
        }
    }
    return 1;
}

/* at the start of a tick: a new configuration published since the last one? */
RT_TICK_CODE
void rt_daq_pickup(rt_run *r)
{
    rt_loop *l = r->l;
    uint32_t gen = atomic_load_explicit(A32(&l->daq_gen), ACQUIRE);
    if (gen == r->daq_gen)
        return;                       /* nothing new (a refused one is counted once) */
    r->daq_gen = gen;
    const rt_daq_config *c = &l->daq[gen & 1u];
    if (daq_config_ok(c)) {
        r->daq = c->n_lists ? c : NULL;
    } else {
        r->daq = NULL;
        atomic_store_explicit(A64(&l->daq_refused),
                              atomic_load_explicit(A64(&l->daq_refused), RELAXED) + 1u, RELAXED);
    }
    for (int i = 0; i < RT_DAQ_MAX_LISTS; i++)
        r->daq_pre[i] = 0;            /* each list fires at its first event */
}

/* at the end of a tick (inside its measured time): the ODTs of every running
 * list whose event fires now, into the DAQ ring; then the generation used */
RT_TICK_CODE
void rt_daq_copy(rt_run *r, int64_t deadline_ns, uint64_t tick)
{
    rt_loop *l = r->l;
    const rt_daq_config *c = r->daq;
    if (c) {
        rt_daq_ring *g = &l->daq_ring;
        const uint8_t *base = (const uint8_t *)(const void *)l;
        uint32_t head = atomic_load_explicit(A32(&g->head), RELAXED);
        uint32_t tail = atomic_load_explicit(A32(&g->tail), ACQUIRE);
        uint64_t dropped = 0;
        for (uint32_t i = 0; i < c->n_lists; i++) {
            const rt_daq_list *d = &c->lists[i];
            if (!d->running || r->ev_wait[d->event] != 0)
                continue;
            if (r->daq_pre[i] > 0) {
                r->daq_pre[i]--;
                continue;
            }
            r->daq_pre[i] = (uint16_t)(d->prescaler > 1 ? d->prescaler - 1 : 0);
            for (uint32_t o = 0; o < d->n_odts; o++) {
                if (head - tail >= RT_DAQ_RING_SIZE) {
                    dropped++;
                    continue;
                }
                rt_dto *x = &g->dtos[head & (RT_DAQ_RING_SIZE - 1u)];
                const rt_odt *t = &c->odts[d->first_odt + o];
                uint32_t len = 0;
                for (uint32_t e = t->first_entry; e < t->first_entry + t->n_entries; e++) {
                    const rt_odt_entry *y = &c->entries[e];
                    memcpy(x->data + len, base + y->offset, y->size);
                    len += y->size;
                }
                x->time_ns = deadline_ns;
                x->tick = tick;
                x->list = (uint16_t)i;
                x->odt = (uint16_t)o;
                x->len = (uint16_t)len;
                x->reserved = 0;
                head++;
            }
        }
        atomic_store_explicit(A32(&g->head), head, RELEASE);
        if (dropped)
            count_dropped(&g->dropped, dropped);
    }
    for (int e = 0; e < RT_N_EVENTS; e++)
        r->ev_wait[e] = r->ev_wait[e] ? r->ev_wait[e] - 1u : r->ev_div[e] - 1u;
    atomic_store_explicit(A32(&l->daq_ack), r->daq_gen, RELEASE);
}

void rt_daq_publish(rt_loop *l, uint32_t gen)
{
    atomic_store_explicit(A32(&l->daq_gen), gen, RELEASE);
}

uint32_t rt_daq_acked(rt_loop *l)
{
    return atomic_load_explicit(A32(&l->daq_ack), ACQUIRE);
}

double rt_daq_bench(rt_loop *l, int64_t iterations)
{
    if (!l || iterations < 1)
        return -1.0;
    uint32_t gen = atomic_load_explicit(A32(&l->daq_gen), ACQUIRE);
    const rt_daq_config *c = &l->daq[gen & 1u];
    if (!daq_config_ok(c))
        return -1.0;
    static rt_run r;                  /* benchmark only: not reentrant, not the loop's */
    memset(&r, 0, sizeof r);
    r.l = l;
    r.daq = c;
    r.daq_gen = gen;
    for (int e = 0; e < RT_N_EVENTS; e++)
        r.ev_div[e] = 1;              /* every event fires at every call */
    rt_daq_ring *g = &l->daq_ring;
    uint64_t dropped0 = g->dropped;
    struct timespec a, b;
    clock_gettime(CLOCK_MONOTONIC, &a);
    for (int64_t i = 0; i < iterations; i++) {
        rt_daq_copy(&r, 0, (uint64_t)i);
        atomic_store_explicit(A32(&g->tail), atomic_load_explicit(A32(&g->head), RELAXED), RELEASE);
    }
    clock_gettime(CLOCK_MONOTONIC, &b);
    g->dropped = dropped0;
    double ns = (double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec);
    return ns / (double)iterations;
}
