/*
 * rt_scope.h - the loop's side of the scope (private to the loop; the
 * contract with Python is in rt_loop.h: rt_scope_config, rt_scope_bucket,
 * the scope ring and its hand-over).
 *
 * rt_scope_run holds the configuration in use (a copy, checked once when
 * its generation is new) and the running min and max of the bucket being
 * filled. rts_tick is called once at the end of every executed tick.
 */
#ifndef RT_SCOPE_H
#define RT_SCOPE_H

#include <stdint.h>

#include "rt_loop.h"

typedef struct {
    uint32_t gen;                     /* the last generation looked at */
    uint32_t n;                       /* traces in use (0: off) */
    uint32_t bucket_ticks;
    uint32_t filled;                  /* ticks in the bucket so far */
    uint32_t offset[RT_SCOPE_TRACES];
    double min[RT_SCOPE_TRACES];
    double max[RT_SCOPE_TRACES];
} rt_scope_run;

/* takes a new configuration when one was published, then (when tracing)
 * adds this tick's values and pushes a full bucket; `tick` the executed
 * tick, `time_s` the plant time after its step */
void rts_tick(rt_scope_run *s, rt_loop *l, uint64_t tick, double time_s);

#endif
