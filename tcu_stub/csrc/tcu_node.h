/*
 * tcu_node.h - the reference TCU as a CAN node in C: a thread of its own
 * runs the 2 ms task of tcu_stub/can_tcu.py (CanTcu) with no Python in it.
 *
 * Each period (absolute deadlines on CLOCK_MONOTONIC, period 2 ms / time
 * scale; or with the bus clock a tick per frame of the clock message): every
 * frame waiting on each bus is taken in, found in the bus's codec table
 * (can_table.c), checked (length, CRC, counter) and decoded; each needed
 * plant message is missing, timed out (10 cycle times), rejected (3 frames
 * in a row) or fine; the sensors are read from the last accepted values
 * through the routing tables (scaling undone); the TCU steps
 * (tcu_step_node: stale handling and the message trouble codes included);
 * the TCU messages due are encoded, protected and sent. At stop one frame of
 * each TCU message with its safe values. Python (tcu_stub/c_node.py) builds
 * every table from the contract or a mapping (TcuMatrix), starts and stops
 * the thread and reads its figures: a sequence-counted copy written at the
 * end of each period (tcu_node_figures_read), and logs that only grow.
 *
 * Frames come and go through ports (tcu_port.c): a CAN_RAW socket, or a pair
 * of functions with a context each (frame rings: the node's own, served by a
 * Python bridge for other python-can interfaces, or a plant loop's rings
 * when the connector in the layer above wires them). tcu_frame has the
 * layout of the loop's rt_frame (the connector checks it).
 *
 * Read by cffi like tcu_fast.h: plain structs, integer #defines, prototypes.
 */
#ifndef TCU_NODE_H
#define TCU_NODE_H

#include <stdint.h>

#include "can_table.h"
#include "tcu_fast.h"

#define TCU_NODE_MAX_BUSES 4
#define TCU_NODE_MAX_TABLE 256        /* messages of one bus's codec table */
#define TCU_NODE_MAX_RX 32            /* plant messages received */
#define TCU_NODE_MAX_TX 16            /* TCU messages sent */
#define TCU_NODE_MAX_SIGNALS 64       /* signals of one message */
#define TCU_NODE_MAX_READS 40         /* quantities read (sensors, SimTime) */
#define TCU_NODE_MAX_CODES 8          /* negative codes of a direction signal */
#define TCU_NODE_MAX_PAIRS 256        /* (value, signal value) pairs of recorded commands */
#define TCU_NODE_MAX_EPISODES 1000    /* stale episodes kept (all are counted) */
#define TCU_NODE_MAX_SHIFTS 4096      /* shifts kept */
#define TCU_NODE_MAX_EVENTS 1000      /* trouble code events kept */
#define TCU_NODE_HIST_BINS 5000       /* 10 us bins up to 50 ms */
#define TCU_NODE_MAX_STALLS 256       /* the last stalls kept (a ring; all are counted) */
#define TCU_NODE_STALL_PERIODS 5      /* a wake-up later than this many periods is a stall */
#define TCU_NODE_BATCH 64             /* frames taken from a port per call */
#define TCU_RING_SIZE 4096            /* frames of a node's own ring, a power of two */

#define TCU_FRAME_FD 1                /* a CAN FD frame */
#define TCU_FRAME_BRS 2               /* CAN FD bit rate switch */
#define TCU_FRAME_EFF 0x80000000      /* SocketCAN's flags in tcu_frame.id */
#define TCU_FRAME_RTR 0x40000000
#define TCU_FRAME_ERR 0x20000000

#define TCU_CLOCK_WALL 0
#define TCU_CLOCK_BUS 1

/* the kinds of a TCU message's signal (tcu_node_tx.kind) */
#define TCU_TX_CONST 0                /* its start value (a protection field: the codec's) */
#define TCU_TX_LINEAR 1               /* (command - bias) / gain, not finite: the start value */
#define TCU_TX_TABLE 2                /* the signal value of the first pair whose value is the command */

/* one CAN or CAN FD frame: the layout of the plant loop's rt_frame */
#define TCU_NODE_STACK_BYTES (1024 * 1024) /* the node thread's stack: ample for a period (its arrays are of sensors, signals and frames), an eighth of the default */

typedef struct {
    uint32_t id;                      /* identifier with TCU_FRAME_EFF/RTR/ERR */
    uint8_t len;
    uint8_t flags;                    /* TCU_FRAME_FD, TCU_FRAME_BRS */
    uint8_t channel;
    uint8_t reserved;
    uint8_t data[CT_MAX_LENGTH];
} tcu_frame;

/* frames in (recv: up to n into f) or out (send: n from f); returns how many were moved */
typedef int (*tcu_frame_fn)(void *ctx, tcu_frame *f, int n);

/* where one bus's frames come from and go to */
typedef struct {
    int32_t fd;                       /* a bound CAN_RAW socket, or -1: the functions */
    int32_t fd_frames;                /* the socket carries CAN FD frames (CAN_RAW_FD_FRAMES on) */
    tcu_frame_fn recv;
    void *recv_ctx;
    tcu_frame_fn send;
    void *send_ctx;
    int32_t last_errno;               /* the last failed send's errno (0: none) */
} tcu_port;

/* a node's own single-producer single-consumer ring of frames (lock-free) */
typedef struct {
    uint32_t head;                    /* written by the producer only */
    uint32_t tail;                    /* written by the consumer only */
    uint64_t dropped;                 /* pushes refused because the ring was full */
    tcu_frame frames[TCU_RING_SIZE];
} tcu_ring;

/* a plant message the node receives */
typedef struct {
    int32_t bus;
    int32_t msg;                      /* index in the bus's codec table */
    int32_t needed;                   /* the TCU reads it: its loss makes the TCU stale */
    int32_t engine;                   /* needed, carrying only the engine's quantities */
    double timeout_s;                 /* wall time without an accepted frame that times it out */
} tcu_node_rx;

/* a quantity read: a signal of a received message, the mapping's scaling undone */
typedef struct {
    int32_t slot;                     /* sensor slot (TCU_S_*), or -1: the plant's SimTime */
    int32_t rx;                       /* index in tcu_node.rx */
    int32_t sig;                      /* the signal's index in its message */
    int32_t dir_sig;                  /* the direction signal (-1: none) */
    double gain;                      /* value = (signal - bias) / gain */
    double bias;
    int32_t n_codes;                  /* direction codes that mean negative */
    double codes[TCU_NODE_MAX_CODES];
} tcu_node_read;

/* a TCU message the node sends */
typedef struct {
    int32_t bus;
    int32_t msg;                      /* index in the bus's codec table */
    int32_t every;                    /* TCU periods between two frames */
    int32_t n_signals;
    int32_t kind[TCU_NODE_MAX_SIGNALS];     /* TCU_TX_* */
    int32_t slot[TCU_NODE_MAX_SIGNALS];     /* command slot (TCU_C_*) */
    double gain[TCU_NODE_MAX_SIGNALS];
    double bias[TCU_NODE_MAX_SIGNALS];
    double start[TCU_NODE_MAX_SIGNALS];     /* start value (GenSigStartValue, else 0) */
    double safe[TCU_NODE_MAX_SIGNALS];      /* the value of the safe final frame */
    int32_t pair_first[TCU_NODE_MAX_SIGNALS];
    int32_t pair_count[TCU_NODE_MAX_SIGNALS];
} tcu_node_tx;

/* counts of a received message */
typedef struct {
    uint64_t received;
    uint64_t accepted;
    uint64_t bad_length;
    uint64_t bad_crc;
    uint64_t bad_counter;
    double first_t;                   /* node time of the first accepted frame */
    double last_t;                    /* ... of the last one */
    double max_interval_s;
} tcu_node_rx_counts;

/* what Python reads while the node runs: one consistent copy a period */
typedef struct {
    int64_t ticks;
    int64_t skipped_ticks;
    int64_t tick_index;
    double t_s;                       /* TCU time of the last period */
    int32_t stale;
    int32_t stale_causes[TCU_NODE_MAX_RX];  /* TCU_MSG_* of the last period */
    int64_t stale_ticks;
    int64_t episode_count;
    int32_t n_episodes;               /* kept in tcu_node.episodes */
    int32_t n_shifts;                 /* kept in tcu_node.shift_log */
    int32_t shifts_lost;
    int32_t n_events;                 /* kept in tcu_node.event_log */
    int32_t events_lost;
    int32_t have_sim_time;
    double sim_time_s;
    int32_t have_sensors;
    double sensors[TCU_N_SENSORS];
    double commands[TCU_N_COMMANDS];
    int32_t phase;
    int32_t gear;
    int32_t target_gear;
    int32_t active_bits;
    int32_t stored_bits;
    int32_t fault_count;
    int32_t inhibited;
    int32_t limp_home;
    int32_t safe_state;
    tcu_node_rx_counts rx[TCU_NODE_MAX_RX];
    uint64_t sent[TCU_NODE_MAX_TX];
    uint64_t send_errors[TCU_NODE_MAX_TX];
    uint64_t saturated[TCU_NODE_MAX_TX];  /* values the codec limited to their signal's range
                                             or bit field (ct_encode_counted), frames sent */
    int32_t last_send_error_tx;       /* the message of the last failed send (-1: none) */
    int32_t last_send_errno;
    uint64_t unknown[TCU_NODE_MAX_BUSES];
    uint64_t error_frames[TCU_NODE_MAX_BUSES];
    uint64_t drained_at_start;        /* frames queued before the thread's start, discarded */
    int64_t pauses;
    double paused_s;
    int32_t running;                  /* the thread runs its periods */
    int32_t final_safe_frames;        /* -1 not sent yet, 0 a send failed, 1 sent */
    double stall_max_s;               /* the latest any wake-up of the thread came (the
                                         scheduler's or the machine's hold, before missed
                                         periods are skipped; not a pause asked for) */
    int64_t n_stalls;                 /* wake-ups later than TCU_NODE_STALL_PERIODS periods;
                                         the last TCU_NODE_MAX_STALLS in tcu_node.stall_log */
} tcu_node_figures;

/* a wake-up of the node's thread later than TCU_NODE_STALL_PERIODS periods */
typedef struct {
    int64_t index;                    /* its number from 0: stall_log[index % TCU_NODE_MAX_STALLS] */
    double at_s;                      /* node time when the thread woke */
    double late_s;                    /* how late it woke */
} tcu_node_stall;

typedef struct {
    double start_s;
    double end_s;
    int32_t open;                     /* still going on */
    uint8_t causes[TCU_NODE_MAX_RX];  /* per received message: TCU_MSG_* (first cause seen) */
} tcu_node_episode;

typedef struct {
    uint32_t n;
    uint64_t bins[TCU_NODE_HIST_BINS];
    double total;
    double max;
} tcu_node_hist;

typedef struct {
    /* set before tcu_node_start */
    const tcu_cal *cal;
    tcu_state *tcu;
    int32_t n_buses;
    const ct_table *tables[TCU_NODE_MAX_BUSES];
    tcu_port ports[TCU_NODE_MAX_BUSES];
    int32_t rx_of[TCU_NODE_MAX_BUSES][TCU_NODE_MAX_TABLE];   /* table index -> rx index, -1 */
    int32_t n_rx;
    tcu_node_rx rx[TCU_NODE_MAX_RX];
    int32_t n_reads;
    tcu_node_read reads[TCU_NODE_MAX_READS];
    int32_t line_slot_read;           /* 1: LinePressure has a reader */
    double defaults[TCU_N_SENSORS];   /* a sensor's value before its message is received */
    int32_t n_tx;
    tcu_node_tx tx[TCU_NODE_MAX_TX];
    double pairs[TCU_NODE_MAX_PAIRS][2];   /* (command value, signal value) */
    double period_s;                  /* TCU time of a period (logic.PERIOD_S) */
    int64_t period_ns;                /* wall time of a period (PERIOD_S / time scale) */
    int32_t clock;                    /* TCU_CLOCK_* */
    int32_t clock_rx;                 /* bus clock: the message that ticks it */
    int32_t clock_ticks;              /* ... periods per frame of it */
    int32_t priority;                 /* SCHED_FIFO priority asked for, 0: normal scheduling */
    int32_t rejects_to_stale;
    /* phase_ref_ns > 0: the periods start on phase_ref_ns + phase_offset_ns
     * + k phase_step_ns (CLOCK_MONOTONIC; embedded: the loop's ticks, half a
     * tick after one, so the commands a period sends are in the rings a
     * half tick before the next tick reads them); 0: from the start */
    int64_t phase_ref_ns;
    int64_t phase_step_ns;
    int64_t phase_offset_ns;
    /* the thread's (read by Python through figures and the logs) */
    int32_t stop;                     /* set by tcu_node_stop */
    int64_t pause_ns;                 /* a starvation asked for (tcu_node_pause) */
    int32_t started;
    int32_t sched_fifo;               /* 1: the thread runs SCHED_FIFO at priority */
    int32_t start_errno;
    uint32_t seq;                     /* odd while figures are written */
    tcu_node_figures fig;             /* written by the thread only */
    tcu_node_figures pub;             /* the published copy (seq) */
    ct_rx_state rx_state[TCU_NODE_MAX_RX];
    int32_t has_values[TCU_NODE_MAX_RX];
    int32_t rejects_in_row[TCU_NODE_MAX_RX];
    int32_t last_reject[TCU_NODE_MAX_RX];  /* TCU_MSG_BAD_* */
    double values[TCU_NODE_MAX_RX][TCU_NODE_MAX_SIGNALS];
    uint32_t counter[TCU_NODE_MAX_TX];
    int64_t next_due[TCU_NODE_MAX_TX];
    double t0;                        /* CLOCK_MONOTONIC at start, s */
    double start_time_s;              /* CLOCK_MONOTONIC of the start, s (for Python) */
    double stop_time_s;
    tcu_node_episode episodes[TCU_NODE_MAX_EPISODES];
    tcu_shift shift_log[TCU_NODE_MAX_SHIFTS];
    tcu_diag_event event_log[TCU_NODE_MAX_EVENTS];
    tcu_node_stall stall_log[TCU_NODE_MAX_STALLS];  /* a ring: entry written, then n_stalls counted */
    tcu_node_hist exec_us;
    tcu_node_hist late_us;
    int32_t open_episode;             /* index of the episode going on, -1: none */
    uint64_t thread;                  /* pthread_t */
} tcu_node;

/* resets the running state (counts, logs, states); the tables stay */
void tcu_node_reset(tcu_node *n);
/* starts the thread: 0, or an errno (start_errno); SCHED_FIFO refused falls back to normal */
int tcu_node_start(tcu_node *n);
/* ends the thread (the safe final frames sent by it) and joins it */
void tcu_node_stop(tcu_node *n);
/* starves the node for seconds from its next period (tcu_stub.can_tcu.CanTcu.pause) */
void tcu_node_pause(tcu_node *n, double seconds);
/* one consistent copy of the figures */
void tcu_node_figures_read(tcu_node *n, tcu_node_figures *out);
/* takes in every frame waiting on the ports at node time now_s, without the thread (tests) */
void tcu_node_receive(tcu_node *n, double now_s);
/* one period without the thread, at node time now_s (tests): 0 */
int tcu_node_period(tcu_node *n, int64_t k, double now_s);
/* the safe final frames without the thread (after a run of tcu_node_period) */
int tcu_node_send_safe(tcu_node *n);
/* CLOCK_MONOTONIC, s */
double tcu_node_now(void);

/* ports (tcu_port.c) */
int tcu_port_recv(tcu_port *p, tcu_frame *f, int n);
int tcu_port_send(tcu_port *p, const tcu_frame *f);
int tcu_ring_push_many(tcu_ring *r, const tcu_frame *f, int n);
int tcu_ring_pop_many(tcu_ring *r, tcu_frame *f, int n);
/* the functions' addresses, for a port's recv and send */
tcu_frame_fn tcu_ring_pop_fn(void);
tcu_frame_fn tcu_ring_push_fn(void);
/* sizeof(tcu_frame), offsetof id, len, flags, channel, data: the connector compares */
#define TCU_N_FRAME_LAYOUT 6
void tcu_frame_layout(int64_t *out);

#endif
