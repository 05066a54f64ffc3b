/*
 * rt_capture.h - the loop's side of the captures (private to the loop; the
 * contract with Python is in rt_loop.h: rt_capture_config, rt_capture_record,
 * the capture ring and its hand-over).
 *
 * rt_capture_run holds the configuration in use (a copy, checked once when
 * its generation is new). rtc_tick is called once at the end of every
 * executed tick, inside its measured execution time.
 */
#ifndef RT_CAPTURE_H
#define RT_CAPTURE_H

#include <stdint.h>

#include "rt_loop.h"

typedef struct {
    uint32_t gen;                     /* the last generation looked at */
    uint32_t n;                       /* sources in use (0: off) */
    uint32_t every;
    uint32_t source[RT_CAPTURE_SIGNALS];
} rt_capture_run;

/* takes a new configuration when one was published, then (when capturing
 * and due) pushes one record: `cmd` the received values as applied in this
 * tick, `tick` the executed tick, `time_s` the plant time after its step */
void rtc_tick(rt_capture_run *s, rt_loop *l, const double *cmd, uint64_t tick, double time_s);

#endif
