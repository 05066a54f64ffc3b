/*
 * rt_writes.c - writes into the running loop (contract: rt_loop.h, the write
 * rings and the regions): calibration writes (XCP) applied as they come,
 * stimulus writes when their plant time has come; each applied whole inside
 * one writable region, a parameter write only when the plant accepts it
 * (dct_plant_prepare), refused and counted otherwise.
 */
#include "rt_internal.h"

static const rt_region *region_of(const rt_loop *l, uint32_t offset, uint32_t len)
{
    for (int i = 0; i < l->n_regions; i++) {
        const rt_region *g = &l->regions[i];
        if (offset >= g->offset && len <= g->size && offset - g->offset <= g->size - len)
            return g;
    }
    return NULL;
}

/* one write, whole; 0 applied, -1 refused */
static int apply_write(rt_loop *l, const rt_write *w)
{
    if (w->len == 0 || w->len > RT_WRITE_BYTES)
        return -1;
    const rt_region *g = region_of(l, w->offset, w->len);
    if (!g)
        return -1;
    uint8_t *dst = (uint8_t *)(void *)l + w->offset;
    if (g->kind != RT_REGION_PARAM) {
        memcpy(dst, w->data, w->len);
        return 0;
    }
    uint8_t old[RT_WRITE_BYTES];
    memcpy(old, dst, w->len);
    memcpy(dst, w->data, w->len);
    if (dct_plant_prepare(&l->plant) != DCT_OK) {
        memcpy(dst, old, w->len);     /* the plant refused them: as before */
        return -1;
    }
    return 0;
}

/* applies the writes due: every queued calibration write, and the stimulus
 * writes whose time has come (plant time before this tick's step) */
RT_TICK_CODE
void rt_apply_writes(rt_loop *l, rt_write_ring *ring, int timed)
{
    uint32_t tail = atomic_load_explicit(A32(&ring->tail), RELAXED);
    uint32_t head = atomic_load_explicit(A32(&ring->head), ACQUIRE);
    double now_s = l->plant.state.time_s + 1e-9;
    int n = 0;
    while (tail != head && n < RT_WRITES_PER_TICK) {
        const rt_write *w = &ring->writes[tail & (RT_WRITE_RING_SIZE - 1u)];
        if (timed && !(w->time_s <= now_s))
            break;                    /* not yet (NaN: never) */
        if (apply_write(l, w) == 0) {
            atomic_store_explicit(A64(&ring->applied),
                                  atomic_load_explicit(A64(&ring->applied), RELAXED) + 1u, RELAXED);
            atomic_store_explicit(A64(&ring->last_applied_id), w->id, RELAXED);
        } else {
            atomic_store_explicit(A64(&ring->refused),
                                  atomic_load_explicit(A64(&ring->refused), RELAXED) + 1u, RELAXED);
            atomic_store_explicit(A64(&ring->last_refused_id), w->id, RELAXED);
        }
        tail++;
        n++;
    }
    atomic_store_explicit(A32(&ring->tail), tail, RELEASE);
}
