/*
 * rt_faults.h - the loop's side of failure simulation (private to the loop;
 * the contract with Python is in rt_loop.h: rt_fault_def, the command and
 * event rings, rt_fault_stats).
 *
 * rt_fault_run holds the slots as the tick sees them and the effects of the
 * active faults, in the form each reader needs them: per sent message what
 * happens to its frames, per message how many signal faults touch it, per
 * channel whether the plant node is off the bus, and the plant's own
 * dct_faults. The effects are computed again only when a fault starts, ends
 * or is cleared (rtf_tick returns which parts changed); between changes the
 * readers pay one test each.
 */
#ifndef RT_FAULTS_H
#define RT_FAULTS_H

#include <stdint.h>

#include "rt_loop.h"

/* rt_fault_run.msg_flags */
#define RTF_OMIT 1u
#define RTF_FREEZE 2u
#define RTF_BAD_CRC 4u
#define RTF_LENGTH 8u
#define RTF_CYCLE 16u

/* what changed in rtf_tick (bits of its return value) */
#define RTF_CHANGED 1                 /* a fault started, ended, or a slot was set or cleared */
#define RTF_CYCLES_CHANGED 2          /* the send cycle of some message changed */

typedef struct {
    uint8_t used;                     /* armed, active or ended */
    uint8_t state;                    /* RT_FSTATE_* */
    rt_fault_def def;
    uint32_t activations;
    double started_s;
    double ended_s;
    uint64_t hits;
    double held;                      /* RT_FAULT_SIG_HOLD: the value it holds (NaN: the next one) */
    uint64_t rng;                     /* RT_FAULT_SIG_NOISE: xorshift64* state */
    int has_spare;                    /* ... the second normal value of a Box-Muller pair */
    double spare;
} rtf_slot;

typedef struct {
    int n_used;                       /* slots armed, active or ended */
    int n_timed;                      /* slots whose state may change by themselves: armed, or
                                         active with a duration */
    uint64_t mask;                    /* active slots */
    uint64_t changes;                 /* starts and ends so far */
    int tx_any;                       /* the send path has something to do (CAN faults, a bus
                                         off, signal faults on sent messages) */
    int n_signal;                     /* active signal faults, in signal_slots */
    uint8_t signal_slots[RT_MAX_FAULTS];
    uint8_t msg_flags[RT_MAX_MESSAGES];         /* RTF_* of each sent message */
    uint8_t msg_length[RT_MAX_MESSAGES];        /* RTF_LENGTH: its data bytes */
    double msg_cycle_s[RT_MAX_MESSAGES];        /* RTF_CYCLE: its cycle */
    uint64_t msg_frozen_seq[RT_MAX_MESSAGES];   /* RTF_FREEZE: the frame number it repeats */
    uint8_t msg_signal_faults[RT_MAX_MESSAGES]; /* active signal faults on its signals */
    uint8_t msg_invalid[RT_MAX_MESSAGES];       /* 1: one of them writes an invalid raw value */
    uint8_t msg_fault_slot[RT_MAX_MESSAGES][5]; /* the slot behind each RTF_* flag (hits) */
    uint8_t chan_off[RT_MAX_CHANNELS];          /* 1: the plant node is off this bus */
    uint8_t chan_off_slot[RT_MAX_CHANNELS];
    rtf_slot slots[RT_MAX_FAULTS];
} rt_fault_run;

void rtf_init(rt_fault_run *f);
/* At the start of a tick, after the received frames (the conditions see this
 * tick's command and signal values and the plant outputs of the last step):
 * takes the queued commands, starts and ends faults, and when anything
 * changed computes the effects again (the plant's faults applied with
 * dct_plant_prepare). Returns RTF_* bits. cmd: the command values. */
int rtf_tick(rt_fault_run *f, rt_loop *l, const double *cmd, double maneuver_time_s);
/* the signal faults of message g (loop-wide index) on its values (n signals,
 * written[k] 0: signal k not in this frame, NULL: all are) */
void rtf_signals(rt_fault_run *f, int g, double *values, const uint8_t *written, uint32_t n);
/* the raw values of the invalid-value faults on sent message g (channel
 * table t, message m), written into its encoded frame */
void rtf_raw(rt_fault_run *f, const ct_table *t, int m, int g, uint8_t *data);
/* counts a frame a CAN fault changed: flag RTF_* of message g, or the bus off of channel c */
void rtf_hit_message(rt_fault_run *f, int g, unsigned flag);
void rtf_hit_channel(rt_fault_run *f, int c);
/* the published copy (inside the statistics' write section): every slot
 * after a change, else only the hits of the active ones */
void rtf_publish(const rt_fault_run *f, rt_stats *s, int changed);

#endif
