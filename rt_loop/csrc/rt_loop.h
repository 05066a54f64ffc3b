/*
 * rt_loop.h - the 2 kHz real-time loop of the plant server.
 *
 * One tick every period on absolute deadlines (CLOCK_MONOTONIC,
 * clock_nanosleep TIMER_ABSTIME), in a thread of its own under SCHED_FIFO:
 *   wait for the deadline                       -> wake-up latency
 *     (sleep to deadline - spin_us, then busy-wait to the deadline)
 *   drain received frames, E2E check, decode    -> TCU commands
 *   timeouts: a TCU message missing for 10 of its cycles -> safe values
 *   scripted driver (optional): pedals from a table over maneuver time
 *   plant step (one step = step_s of simulated time)
 *   encode and send the frames due this tick
 *   recorder (optional): a copy of the plant outputs every record_every ticks
 *   statistics: turnaround = end - deadline, execution = end - wake-up,
 *               overrun = the tick ends after the next deadline
 * No Python, no allocation, no locks, no logging per tick. Python starts
 * rt_loop_run() in a thread of its own (cffi releases the GIL for the call),
 * reads the statistics with rt_stats_read() (a sequence counter: the loop
 * never waits for the reader), and moves frames in and out of the rings for
 * the bridge transport and the traffic log.
 *
 * Read by cffi: plain structs, integer #defines, prototypes.
 */
#ifndef RT_LOOP_H
#define RT_LOOP_H

#include <stdint.h>

#include "dct_can.h"
#include "dct_plant.h"

#define RT_TRANSPORT_SOCKETCAN 0      /* cfg.fd is a bound, non-blocking CAN_RAW socket */
#define RT_TRANSPORT_RING 1           /* frames through rx/tx rings (bridge to python-can) */

#define RT_RING_SIZE 8192             /* frames, a power of two */
#define RT_LOG_SIZE 65536             /* log entries, a power of two */
#define RT_REC_SIZE 4096              /* recorder samples, a power of two */
#define RT_DRIVER_ROWS 64             /* rows of the in-loop pedal table */
#define RT_HIST_BINS 5000             /* 1 us bins, 0 .. 4.999 ms; the last bin holds everything above */
#define RT_TIMEOUT_CYCLES 10

#define RT_STATE_IDLE 0
#define RT_STATE_RUNNING 1
#define RT_STATE_STOPPED 2            /* stop requested or duration reached */
#define RT_STATE_OVERRUN_STOP 3       /* stopped by the overrun policy */
#define RT_STATE_ERROR 4              /* transport error (errno in stats.error) */

/* what the loop thread is doing before its first tick (rt_stats.startup_phase):
 * Python waits for RT_STATE_RUNNING and names the phase while it waits */
#define RT_START_NOT_STARTED 0        /* rt_loop_run not entered yet */
#define RT_START_SCHEDULING 1         /* pthread_setschedparam SCHED_FIFO */
#define RT_START_PINNING 2            /* pthread_setaffinity_np */
#define RT_START_LOCKING_MEMORY 3     /* mlockall: slow for a large process on a slow machine */
#define RT_START_PREFAULTING 4        /* touching the stack */
#define RT_START_READY 5              /* the first deadline is set: ticking */

#define RT_MANEUVER_NONE 0            /* no pedal table: the pedals stay as Python writes them */
#define RT_MANEUVER_WAITING 1         /* table loaded, waiting for the first TCU frame */
#define RT_MANEUVER_RUNNING 2
#define RT_MANEUVER_DONE 3            /* end_s reached: the loop stopped */

#define RT_DIR_RX 0
#define RT_DIR_TX 1

typedef struct {
    double period_s;                  /* wall-clock time between deadlines: 0.0005 for 2 kHz */
    double step_s;                    /* simulated time per tick (the plant step; the CAN
                                         cycles and timeouts count it): 0 means period_s.
                                         step_s / period_s is the time scale: 1 is real
                                         time, 0.1 a ten times slower run of the same ticks */
    int priority;                     /* SCHED_FIFO priority, 0: leave the policy alone */
    int cpu;                          /* CPU to pin the loop to, -1: any */
    int lock_memory;                  /* 1: mlockall(MCL_CURRENT | MCL_FUTURE) */
    int overrun_stop;                 /* 1: stop at the first overrun; 0: count, skip ahead */
    double duration_s;                /* <= 0: until rt_loop_request_stop() */
    int transport;                    /* RT_TRANSPORT_* */
    int fd;                           /* the CAN_RAW socket (RT_TRANSPORT_SOCKETCAN) */
    int log_frames;                   /* 1: copy every received and sent frame to the log ring */
    double spin_us;                   /* wake this long before each deadline and busy-wait to it:
                                         hides the OS wake-up latency up to spin_us (0: sleep only) */
    int record_every;                 /* push a recorder sample every this many ticks (0: off) */
} rt_config;

/* the driver of a scripted maneuver, played by the loop itself: pedals as a
 * function of maneuver time, so that a run does not depend on when a Python
 * thread gets the CPU */
typedef struct {
    int rows;                         /* 0: no table (RT_MANEUVER_NONE) */
    int linear;                       /* 0: each row held until the next; 1: linear between rows */
    int start_on_tcu;                 /* 1: maneuver time 0 is the first tick after the first
                                         accepted TCU frame; 0: the first tick */
    double end_s;                     /* maneuver time at which the loop stops (<= 0: never;
                                         the last row is held) */
    double t_s[RT_DRIVER_ROWS];       /* strictly increasing */
    double accel_pedal_pct[RT_DRIVER_ROWS];
    double brake_pedal_pct[RT_DRIVER_ROWS];
} rt_driver;

/* one recorder sample: the plant after a tick's step */
typedef struct {
    uint64_t tick;                    /* executed tick index */
    double time_s;                    /* plant time after the step */
    double maneuver_time_s;           /* plant time since the maneuver started (< 0: not yet) */
    dct_outputs outputs;
    dct_tcu_commands commands;        /* as applied in this tick */
} rt_sample;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* samples lost because the reader fell behind */
    rt_sample samples[RT_REC_SIZE];
} rt_rec_ring;

/* single-producer single-consumer ring of frames (lock-free) */
typedef struct {
    uint32_t head;                    /* written by the producer only */
    uint32_t tail;                    /* written by the consumer only */
    uint64_t dropped;                 /* pushes refused because the ring was full */
    dct_can_frame frames[RT_RING_SIZE];
} rt_ring;

typedef struct {
    double time_s;                    /* loop time since start (tick deadline) */
    uint32_t dir;                     /* RT_DIR_* */
    dct_can_frame frame;
} rt_log_entry;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* entries lost because the reader fell behind */
    rt_log_entry entries[RT_LOG_SIZE];
} rt_log_ring;

typedef struct {
    uint32_t seq;                     /* odd while the loop is writing */
    int state;                        /* RT_STATE_* */
    int error;                        /* errno of a fatal transport error */
    int rt_policy_ok;                 /* SCHED_FIFO was granted */
    int memory_locked;                /* mlockall succeeded */
    int affinity_ok;
    int startup_phase;                /* RT_START_* */
    uint64_t ticks;                   /* ticks executed (plant steps) */
    uint64_t overruns;                /* ticks that ended after the next deadline */
    uint64_t skipped_ticks;           /* deadlines skipped to catch up after overruns */
    double sim_time_s;
    int maneuver_state;               /* RT_MANEUVER_* */
    double maneuver_time_s;           /* < 0 before the maneuver started */
    double turnaround_us;             /* last tick */
    double turnaround_max_us;
    double exec_us;
    double exec_max_us;
    double latency_us;                /* wake-up latency of the last tick */
    double latency_max_us;
    uint64_t turnaround_hist[RT_HIST_BINS];
    uint64_t exec_hist[RT_HIST_BINS];
    uint64_t latency_hist[RT_HIST_BINS];
    uint64_t rx_frames;               /* all frames read from the transport */
    uint64_t rx_accepted;
    uint64_t rx_unknown_id;
    uint64_t rx_bad_length;
    uint64_t rx_bad_crc;
    uint64_t rx_bad_counter;
    uint64_t rx_overflow;             /* frames the kernel dropped (SO_RXQ_OVFL) or ring drops */
    uint64_t tx_frames;
    uint64_t tx_dropped;              /* sends refused (full socket buffer or ring) */
    uint64_t rx_per_msg[DCT_CAN_N_RX];
    uint64_t timeout_events[DCT_CAN_N_RX];
    int timed_out[DCT_CAN_N_RX];      /* 1 while the message is timed out (all are at start) */
    dct_tcu_commands commands;        /* as applied this tick */
    dct_outputs outputs;              /* the plant's outputs after this tick */
} rt_stats;

typedef struct {
    rt_config cfg;
    dct_plant plant;                  /* params filled by Python before rt_loop_prepare() */
    rt_stats stats;
    int stop_request;                 /* set by rt_loop_request_stop() */
    dct_e2e_rx e2e[DCT_CAN_N_RX];
    uint64_t last_rx_tick[DCT_CAN_N_RX];
    uint8_t tx_counter[DCT_CAN_N_TX];
    rt_ring rx;                       /* bridge: python-can -> loop */
    rt_ring tx;                       /* bridge: loop -> python-can */
    rt_log_ring log;                  /* loop -> traffic log writer */
    rt_driver driver;                 /* filled by Python before rt_loop_prepare() */
    rt_rec_ring rec;                  /* loop -> recorder */
} rt_loop;

/* validates cfg, initialises the plant (dct_plant_init) with its step set
 * to the period, the statistics and the E2E state; returns 0 or a negative
 * errno-style code */
int rt_loop_prepare(rt_loop *l);
/* runs the loop in the calling thread until stopped; returns the final state */
int rt_loop_run(rt_loop *l);
void rt_loop_request_stop(rt_loop *l);
/* a consistent copy of the statistics without stopping the loop; 0 ok,
 * -1 if the loop kept writing through every retry */
int rt_stats_read(rt_loop *l, rt_stats *copy);

int rt_ring_push(rt_ring *r, const dct_can_frame *f);   /* 0, or -1 full (counted) */
int rt_ring_pop(rt_ring *r, dct_can_frame *f);          /* 0, or -1 empty */
int rt_log_pop(rt_log_ring *r, rt_log_entry *e);        /* 0, or -1 empty */
/* up to n frames at once (bridge thread): returns how many */
int rt_ring_push_many(rt_ring *r, const dct_can_frame *f, int n);
int rt_ring_pop_many(rt_ring *r, dct_can_frame *f, int n);
int rt_log_pop_many(rt_log_ring *r, rt_log_entry *e, int n);
int rt_rec_pop_many(rt_rec_ring *r, rt_sample *s, int n);

#endif
