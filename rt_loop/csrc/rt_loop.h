/*
 * rt_loop.h - the 2 kHz real-time loop of the plant server.
 *
 * One tick every period on absolute deadlines (CLOCK_MONOTONIC,
 * clock_nanosleep TIMER_ABSTIME), in a thread of its own under SCHED_FIFO:
 *   wait for the deadline                       -> wake-up latency
 *     (sleep to deadline - spin_us, then busy-wait to the deadline)
 *   on every channel: drain received frames, check their protection,
 *     decode them and turn their signals into command values
 *   timeouts: a received message missing for its timeout -> safe values
 *   scripted driver (optional): pedals from a table over maneuver time
 *   command values -> plant inputs, plant step (step_s of simulated time)
 *   on every channel: the frames due this tick, each signal from its source
 *     (plant output, status, constant, counter), encoded and protected
 *   recorder (optional): a copy of the plant outputs every record_every ticks
 *   statistics: turnaround = end - deadline, execution = end - wake-up,
 *               overrun = the tick ends after the next deadline
 * What goes on the buses is data, not code: per channel a table-driven codec
 * (can_table.h: any DBC's layouts and protections) and per signal where its
 * value comes from or what it drives (rt_source, rt_target), built by Python
 * from a DBC and a mapping file (rt_loop/channels.py) before the loop starts.
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

#include "can_table.h"
#include "dct_plant.h"

#define RT_TRANSPORT_SOCKETCAN 0      /* the channel's fd is a bound, non-blocking CAN_RAW socket */
#define RT_TRANSPORT_RING 1           /* frames through the channel's rx/tx rings (bridge to python-can) */

#define RT_MAX_CHANNELS 4             /* CAN buses served by one loop */
#define RT_MAX_MESSAGES 128           /* messages of all channels together */
#define RT_MAX_COMMANDS 32            /* values the received signals drive (inputs) or record */
#define RT_MAX_MSG_SIGNALS 512        /* signals of one message (64 bytes of 1-bit signals) */
#define RT_RING_SIZE 8192             /* frames, a power of two */
#define RT_LOG_SIZE 65536             /* log entries, a power of two */
#define RT_REC_SIZE 4096              /* recorder samples, a power of two */
#define RT_DRIVER_ROWS 64             /* rows of the in-loop pedal table */
#define RT_HIST_BINS 5000             /* 1 us bins, 0 .. 4.999 ms; the last bin holds everything above */
#define RT_TIMEOUT_CYCLES 10          /* the default timeout of a received message, in its cycles */

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
#define RT_MANEUVER_DONE 3            /* end_s reached (the loop stopped unless keep_running) or stopped */

#define RT_DIR_RX 0
#define RT_DIR_TX 1

/* rt_frame.flags */
#define RT_FRAME_FD 1                 /* a CAN FD frame */
#define RT_FRAME_BRS 2                /* CAN FD bit rate switch */

/* where a sent signal's value comes from (rt_source.kind) */
/* RT_SRC_VALUE: a fixed value (a constant, the DBC start value; 0 for the
 * protection's fields, which ct_protect writes) */
#define RT_SRC_VALUE 0
#define RT_SRC_OUTPUT 1               /* a plant output (the field-th double of dct_outputs) */
#define RT_SRC_STATUS 2               /* the simulator's status (RT_STATUS_*) */
#define RT_SRC_TOGGLE 3               /* 0, 1, 0, ... per frame of the message */
#define RT_SRC_COUNTER 4              /* 0 .. modulus-1 per frame of the message */

/* status sources (rt_source.field with RT_SRC_STATUS), as can_dbc.mapping.STATUS_FIELDS */
#define RT_STATUS_SIM_TIME_S 0
#define RT_STATUS_OVERRUN_COUNT 1
#define RT_STATUS_TURNAROUND_MAX_US 2
#define RT_STATUS_SIM_STATE 3         /* 0 starting, 1 running, 2 stopping, 3 fault */
#define RT_N_STATUS 4

/* what a received signal drives (rt_target.kind) */
#define RT_TGT_NONE 0                 /* nothing */
#define RT_TGT_COMMAND 1              /* the command value rt_target.command */

/* one CAN or CAN FD frame as the loop moves it */
typedef struct {
    uint32_t id;                      /* identifier with SocketCAN's flags: CAN_EFF_FLAG (29-bit),
                                         CAN_RTR_FLAG, CAN_ERR_FLAG */
    uint8_t len;                      /* data bytes: 0..8, CAN FD up to 64 */
    uint8_t flags;                    /* RT_FRAME_* */
    uint8_t channel;                  /* the bus (index of rt_loop.chan) it was received on or
                                         sent to */
    uint8_t reserved;
    uint8_t data[CT_MAX_LENGTH];
} rt_frame;

/* a whole number key lo..hi (inclusive; +-inf: open) of a value table */
typedef struct {
    double lo;
    double hi;
    double value;
} rt_range;

/* a value table: the key (the value rounded half to even to a whole number)
 * picks the first of ranges[first .. first + count - 1] that holds it, else
 * (or for a non-finite key) the default */
typedef struct {
    uint32_t first;
    uint32_t count;                   /* 0: no table */
    double fallback;
} rt_lookup;

/* where a sent signal's value comes from: one per signal of the channel's table */
typedef struct {
    uint8_t kind;                     /* RT_SRC_* */
    uint8_t absolute;                 /* take the magnitude of the output or status first */
    uint16_t field;                   /* RT_SRC_OUTPUT: index of the dct_outputs double;
                                         RT_SRC_STATUS: RT_STATUS_* */
    uint32_t modulus;                 /* RT_SRC_COUNTER: the counter's values 0 .. modulus-1 */
    double gain;                      /* signal = gain * source + bias (without a table) */
    double bias;
    double value;                     /* RT_SRC_VALUE */
    rt_lookup table;                  /* with a table: signal = the table's value for the source */
} rt_source;

/* what a received signal drives: one per signal of the channel's table */
typedef struct {
    uint8_t kind;                     /* RT_TGT_* */
    uint8_t reserved;
    uint16_t command;                 /* RT_TGT_COMMAND: index of rt_loop.commands */
    double gain;                      /* value = gain * signal + bias (without a table), */
    double bias;
    double minimum;                   /* then limited to [minimum, maximum] (+-inf: no limit) */
    double maximum;
    double safe;                      /* the value while the message is timed out (and at start) */
    rt_lookup table;
} rt_target;

/* the loop's side of one message of a channel's table */
typedef struct {
    uint8_t direction;                /* RT_DIR_TX: the plant sends it; RT_DIR_RX: it receives it */
    uint8_t final_frame;              /* sent: it carries RT_STATUS_SIM_STATE, so one more frame
                                         goes out when the loop ends (with the state it ends in) */
    uint8_t flags;                    /* sent: RT_FRAME_* of its frames */
    uint8_t reserved;
    uint32_t timeout_cycles;          /* received: timed out after this many cycles without an
                                         accepted frame (0: RT_TIMEOUT_CYCLES) */
    double cycle_s;                   /* cycle time in simulated time */
} rt_msg;

/* one CAN bus the loop serves: filled by Python (rt_loop/channels.py) before
 * rt_loop_prepare; the arrays belong to Python and live as long as the loop */
typedef struct {
    int transport;                    /* RT_TRANSPORT_* */
    int fd;                           /* the CAN_RAW socket (RT_TRANSPORT_SOCKETCAN) */
    int fd_frames;                    /* 1: the socket carries CAN FD frames (CAN_RAW_FD_FRAMES
                                         is on): frames are read and sent as struct canfd_frame */
    int first_message;                /* set by rt_loop_prepare: index of the channel's first
                                         message in the loop-wide numbering (stats.msgs) */
    int first_signal_value;           /* set by rt_loop_prepare: index of its first signal in
                                         rt_loop.signal_values */
    ct_table table;                   /* the bus's messages (can_dbc/table.py CodecTable) */
    const rt_msg *msgs;               /* one per message of table */
    const rt_source *sources;         /* one per signal of table (used for sent messages) */
    const rt_target *targets;         /* one per signal of table (used for received messages) */
    const rt_range *ranges;           /* the value tables' ranges */
    int32_t n_ranges;
} rt_channel;

/* ---- measurement, calibration and stimulus (XCP: rt_loop/measure/xcp/) -------------
 *
 * The loop's memory is the address space of measurement and calibration: an
 * address is a byte offset from the start of the rt_loop (XCP address
 * extension 0), so the A2L describes the C structs as they are (plant
 * inputs, outputs, state, parameters, the statistics, the CAN signals'
 * last values).
 *
 * DAQ: Python (the XCP slave's thread) writes a DAQ configuration (lists of
 * ODTs of entries: offset and size) into the slot daq[(daq_gen + 1) & 1],
 * then increments daq_gen (release). Each tick loads daq_gen (acquire),
 * checks a configuration it has not seen before once (entries inside the
 * loop, ODTs within RT_DAQ_ODT_BYTES; a bad one is ignored and counted in
 * daq_refused), and at its end copies, for every running list whose event
 * fires, each ODT's entries into one rt_dto of the daq ring (a full ring
 * drops the DTO and counts it in daq_ring.dropped: the overload
 * indication). It then stores the generation it used in daq_ack (release):
 * Python writes the other slot again only once daq_ack == daq_gen.
 * Events (rt_daq_list.event): RT_EVENT_TICK every executed tick,
 * RT_EVENT_10MS and RT_EVENT_100MS every 10 / 100 ms of plant time
 * (20 / 200 ticks at 2 kHz), each list with its prescaler (1: every time).
 * A DTO carries the tick's deadline (CLOCK_MONOTONIC, ns): the DAQ clock.
 * The copy runs at the end of the tick, inside its measured time (its cost
 * shows in the turnaround), after the plant step and the frames sent: plant
 * values are this tick's, the statistics (rt_stats) as the previous tick
 * published them.
 *
 * Writes: rt_write entries in two single-producer rings: cal (calibration:
 * applied at the next tick boundary, before the plant step) and stim
 * (stimulus: applied at the first tick whose plant time before the step is
 * at least time_s, in ring order). A write is applied whole (all its bytes
 * in the same tick, never torn) when its bytes lie inside one of the
 * writable regions (set by Python before rt_loop_prepare); a write into a
 * RT_REGION_PARAM region is followed by dct_plant_prepare (the parameters
 * checked, derived values computed again; the state is kept) and undone
 * when the plant refuses the new parameters. Refused writes are counted
 * (write_refused), applied ones too (write_applied). */
#define RT_DAQ_MAX_LISTS 32
#define RT_DAQ_MAX_ODTS 512
#define RT_DAQ_MAX_ENTRIES 4096
#define RT_DAQ_ODT_BYTES 248          /* data bytes of one DTO (an XCP MAX_DTO of 256) */
#define RT_DAQ_RING_SIZE 16384        /* DTOs, a power of two */
#define RT_EVENT_TICK 0
#define RT_EVENT_10MS 1
#define RT_EVENT_100MS 2
#define RT_N_EVENTS 3
#define RT_WRITE_RING_SIZE 4096       /* writes, a power of two */
#define RT_WRITE_BYTES 64             /* bytes of one write at most */
#define RT_WRITES_PER_TICK 64         /* applied per ring and tick at most; the rest waits */
#define RT_MAX_REGIONS 256
#define RT_REGION_DATA 0              /* plain data (plant inputs): the bytes are enough */
#define RT_REGION_PARAM 1             /* plant parameters: dct_plant_prepare after the write */
#define RT_MAX_SIGNAL_VALUES 4096     /* the CAN signals' last values, all channels */

typedef struct {
    uint32_t offset;                  /* bytes from the start of the rt_loop */
    uint32_t size;                    /* bytes, 1..RT_DAQ_ODT_BYTES */
} rt_odt_entry;

typedef struct {
    uint32_t first_entry;             /* rt_daq_config.entries[first_entry .. + n_entries - 1] */
    uint32_t n_entries;
} rt_odt;

typedef struct {
    uint32_t first_odt;               /* rt_daq_config.odts[first_odt .. + n_odts - 1] */
    uint32_t n_odts;
    uint16_t event;                   /* RT_EVENT_* */
    uint16_t prescaler;               /* 1: every time the event fires, n: every n-th */
    uint32_t running;                 /* 1: copied when its event fires */
} rt_daq_list;

typedef struct {
    uint32_t n_lists;
    rt_daq_list lists[RT_DAQ_MAX_LISTS];
    rt_odt odts[RT_DAQ_MAX_ODTS];
    rt_odt_entry entries[RT_DAQ_MAX_ENTRIES];
} rt_daq_config;

/* one ODT's data from one tick */
typedef struct {
    int64_t time_ns;                  /* the tick's deadline, CLOCK_MONOTONIC */
    uint64_t tick;                    /* executed tick index */
    uint16_t list;
    uint16_t odt;
    uint16_t len;                     /* data bytes */
    uint16_t reserved;
    uint8_t data[RT_DAQ_ODT_BYTES];
} rt_dto;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* DTOs lost because the ring was full (overload) */
    rt_dto dtos[RT_DAQ_RING_SIZE];
} rt_daq_ring;

/* bytes written into the loop's memory at a tick boundary */
typedef struct {
    double time_s;                    /* stim: plant time to apply it at; cal: ignored */
    uint32_t offset;                  /* bytes from the start of the rt_loop */
    uint32_t len;                     /* 1..RT_WRITE_BYTES */
    uint64_t id;                      /* the producer's number for it (reported back in
                                         last_applied_id / last_refused_id) */
    uint8_t data[RT_WRITE_BYTES];
} rt_write;

typedef struct {
    uint32_t head;                    /* producer (Python) */
    uint32_t tail;                    /* consumer (the loop) */
    uint64_t dropped;                 /* writes the producer could not queue (full) */
    uint64_t applied;                 /* written by the loop */
    uint64_t refused;                 /* outside every region, or parameters the plant refused */
    uint64_t last_applied_id;
    uint64_t last_refused_id;
    rt_write writes[RT_WRITE_RING_SIZE];
} rt_write_ring;

/* a part of the loop's memory that writes may change */
typedef struct {
    uint32_t offset;
    uint32_t size;
    uint32_t kind;                    /* RT_REGION_* */
} rt_region;

/* ---- failure simulation: faults inside the tick ---------------------------
 *
 * Faults are data: a table of RT_MAX_FAULTS slots the tick walks. Python
 * (rt_loop/faults/) queues commands (arm a slot with a fault, clear a
 * slot, clear all) in the single-producer ring fault_cmds; the loop applies
 * them at the start of the next tick, so a fault can be switched while the
 * loop runs and the loop never waits for Python.
 *
 * An armed fault starts at the first tick whose plant time (before the
 * step) is at least start_s and whose condition holds (rt_condition: up to
 * RT_COND_TERMS comparisons of plant outputs, command values, CAN signal
 * values or the maneuver time, all of them or any of them), and stays
 * active for duration_s of plant time (<= 0 or inf: until cleared). A watch
 * (RT_FAULT_WATCH) has no effect: it latches the plant time its condition
 * first held (the test API's wait_until).
 *
 * Effects, each read in one place:
 *   CAN faults (the plant's sent messages): in the tick's send schedule and
 *     frame builder (omit, counter frozen, checksum corrupted, cycle
 *     changed: late or too often, wrong length, bus off of the plant node);
 *   signal faults (any sent or received signal): on the signal's physical
 *     value between codec and plant, for received signals before they
 *     become command values, for sent signals before they are encoded;
 *   physical faults: dct_plant.faults, then dct_plant_prepare (the plant's
 *     own one place, plant/csrc/faults.c), only when a fault starts or ends.
 * Every start and end goes into the event ring fault_events (plant time,
 * slot, id, kind) and into the statistics (stats.faults, stats.fault_mask:
 * the slots active after this tick), and each recorder sample carries the
 * mask of the faults active in its tick. With no fault armed the tick pays
 * one load of the command ring's head and one test. */
#define RT_MAX_FAULTS 64
#define RT_FAULT_CMD_RING_SIZE 256    /* commands, a power of two */
#define RT_FAULT_EVENT_RING_SIZE 4096 /* events, a power of two */
#define RT_COND_TERMS 4

/* rt_fault_def.kind */
#define RT_FAULT_NONE 0
/* CAN: a message the plant sends (message: loop-wide index; bus off: channel) */
#define RT_FAULT_CAN_OMIT 1           /* not sent */
#define RT_FAULT_CAN_FREEZE_COUNTER 2 /* its alive counter stays at the value it had */
#define RT_FAULT_CAN_BAD_CRC 3        /* its checksum byte inverted */
/* RT_FAULT_CAN_CYCLE: sent every value seconds (late: longer than its cycle, too often: shorter) */
#define RT_FAULT_CAN_CYCLE 4
#define RT_FAULT_CAN_LENGTH 5         /* sent with value data bytes (padded with zeros or cut) */
#define RT_FAULT_CAN_BUS_OFF 6        /* no frame of the plant on the channel */
/* signal: signal = index into rt_loop.signal_values (its channel's first + its table index) */
#define RT_FAULT_SIG_HOLD 10          /* stuck at the value it had when the fault started */
#define RT_FAULT_SIG_VALUE 11         /* stuck at value */
#define RT_FAULT_SIG_OFFSET 12        /* + value */
#define RT_FAULT_SIG_GAIN 13          /* x value */
#define RT_FAULT_SIG_NOISE 14         /* + Gaussian noise of standard deviation value (seeded) */
#define RT_FAULT_SIG_INVALID 15       /* the signal's invalid value (value, physical) */
/* physical: target = clutch / valve 0..1 or sleeve 0..3 */
#define RT_FAULT_SPOOL_STUCK 20
#define RT_FAULT_SOLENOID_OPEN 21
#define RT_FAULT_FRICTION_FADE 22     /* value: share of the friction coefficient lost, 0..1 */
#define RT_FAULT_KISS_DRIFT 23        /* value: mm added to the pack gap */
#define RT_FAULT_LINE_PRESSURE_LOSS 24 /* value: share of the line pressure lost, 0..1 */
#define RT_FAULT_FORK_JAMMED 25
#define RT_FAULT_BLOCKER_FAILED 26
#define RT_FAULT_ENGINE_TORQUE_LIMIT 27 /* value: Nm the combustion torque is limited to */
#define RT_FAULT_WATCH 30             /* no effect: latches when its condition first holds */

/* rt_term.source */
#define RT_OPD_OUTPUT 0               /* index: a dct_outputs double */
#define RT_OPD_COMMAND 1              /* index: a command value (received, as applied) */
#define RT_OPD_SIGNAL 2               /* index: rt_loop.signal_values (last value on the bus) */
#define RT_OPD_MANEUVER_TIME 3        /* the maneuver time (< 0 before it started) */
/* rt_term.op */
#define RT_OP_LT 0
#define RT_OP_LE 1
#define RT_OP_GT 2
#define RT_OP_GE 3
#define RT_OP_EQ 4                    /* within 1e-9 of the value (relative above 1) */
#define RT_OP_NE 5
/* RT_OP_BITS: any bit of value (an integer mask) set in the value read, truncated to an
 * integer (below 1 or NaN: no bit) */
#define RT_OP_BITS 6

/* rt_fault_cmd.op */
#define RT_FCMD_SET 1                 /* arm slot with def (a fault in the slot ends first) */
#define RT_FCMD_CLEAR 2               /* end slot's fault (if active) and free the slot */
#define RT_FCMD_CLEAR_ALL 3

/* rt_fault_stats.state */
#define RT_FSTATE_FREE 0
#define RT_FSTATE_ARMED 1             /* waiting for its start time and condition */
#define RT_FSTATE_ACTIVE 2
#define RT_FSTATE_ENDED 3             /* its duration is over; the slot stays until cleared */

/* rt_fault_event.what */
#define RT_FEV_START 1
#define RT_FEV_END 2                  /* duration over */
#define RT_FEV_CLEARED 3              /* cleared while active */

typedef struct {
    uint8_t source;                   /* RT_OPD_* */
    uint8_t op;                       /* RT_OP_* */
    uint16_t reserved;
    uint32_t index;
    double value;
} rt_term;

typedef struct {
    uint32_t n_terms;                 /* 0: always true */
    uint32_t any;                     /* 0: every term holds; 1: at least one */
    rt_term terms[RT_COND_TERMS];
} rt_condition;

typedef struct {
    uint64_t id;                      /* the producer's number for it */
    uint16_t kind;                    /* RT_FAULT_* */
    uint16_t reserved;
    int32_t channel;                  /* CAN bus off: the channel */
    int32_t message;                  /* CAN and signal faults: loop-wide message index */
    int32_t signal;                   /* signal faults: index into rt_loop.signal_values */
    int32_t local_signal;             /* signal faults: index among its message's signals */
    int32_t target;                   /* physical: clutch / valve 0..1, sleeve 0..3 */
    double value;
    int64_t raw;                      /* signal.invalid on a sent signal: the raw value written */
    uint64_t seed;                    /* noise */
    double start_s;                   /* plant time it may start at (-inf: at once) */
    double duration_s;                /* active this long; <= 0 or inf: until cleared */
    rt_condition when;                /* and this holds (n_terms 0: nothing more) */
} rt_fault_def;

typedef struct {
    uint32_t op;                      /* RT_FCMD_* */
    uint32_t slot;
    rt_fault_def fault;
} rt_fault_cmd;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;
    uint64_t applied;                 /* written by the loop */
    uint64_t refused;                 /* bad slot, kind or index */
    uint64_t last_id;                 /* id of the last command the loop took (applied or refused) */
    rt_fault_cmd cmds[RT_FAULT_CMD_RING_SIZE];
} rt_fault_cmd_ring;

typedef struct {
    double time_s;                    /* plant time of the tick (before its step) */
    uint64_t id;
    uint16_t slot;
    uint16_t kind;
    uint32_t what;                    /* RT_FEV_* */
} rt_fault_event;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;
    rt_fault_event events[RT_FAULT_EVENT_RING_SIZE];
} rt_fault_event_ring;

/* one slot, as published (stats.faults) */
typedef struct {
    uint64_t id;
    uint16_t kind;
    uint16_t state;                   /* RT_FSTATE_* */
    uint32_t activations;
    double started_s;                 /* plant time of the last start (NaN: never) */
    double ended_s;                   /* ... of the last end (NaN: not ended) */
    uint64_t hits;                    /* frames or values it changed (CAN, signal) */
} rt_fault_stats;

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
    int log_frames;                   /* 1: copy every received and sent frame to the log ring
                                         (read every frame: may change while the loop runs) */
    double spin_us;                   /* wake this long before each deadline and busy-wait to it:
                                         hides the OS wake-up latency up to spin_us (0: sleep only) */
    int record_every;                 /* push a recorder sample every this many ticks (0: off;
                                         read every tick: a recording may start and stop while
                                         the loop runs) */
    uint32_t release_rings;           /* RT_RELEASE_*: rings this run does not use when it
                                         starts; with lock_memory, their storage is left out
                                         of the locked memory (rt_loop_hold_rings takes it
                                         back before a feature that uses one starts) */
} rt_config;

/* rt_config.release_rings: the log, recorder, DAQ and capture rings (the rx and tx rings of the
   channels beyond n_channels are always released: no run uses them) */
#define RT_RELEASE_LOG 1
#define RT_RELEASE_REC 2
#define RT_RELEASE_DAQ 4
#define RT_RELEASE_CAPTURE 8

/* the driver of a scripted maneuver, played by the loop itself: pedals (and
 * the selector lever, when the table has it) as a function of maneuver time,
 * so that a run does not depend on when a Python thread gets the CPU; the
 * maneuver's road grade set once, at prepare and at its start */
typedef struct {
    int rows;                         /* 0: no table (RT_MANEUVER_NONE) */
    int linear;                       /* 0: each row held until the next; 1: linear between rows */
    int start_on_tcu;                 /* 1: maneuver time 0 is the first tick after the first
                                         accepted TCU frame; 0: the first tick */
    double end_s;                     /* maneuver time at which the loop stops (<= 0: never;
                                         the last row is held) */
    int keep_running;                 /* 1: at end_s the maneuver is done and the loop goes on
                                         (the last row's pedals held until set otherwise) */
    double t_s[RT_DRIVER_ROWS];       /* strictly increasing */
    double accel_pedal_pct[RT_DRIVER_ROWS];
    double brake_pedal_pct[RT_DRIVER_ROWS];
    int has_selector;                 /* 1: selector_lever[] is played (each row held until
                                         the next, also with linear); 0: left alone */
    double selector_lever[RT_DRIVER_ROWS];  /* DCT_SELECTOR_*: 0 P, 1 R, 2 N, 3 D */
    int has_grade;                    /* 1: road_grade_pct is set at prepare and at the start */
    double road_grade_pct;
} rt_driver;

/* one recorder sample: the plant after a tick's step */
typedef struct {
    uint64_t tick;                    /* executed tick index */
    double time_s;                    /* plant time after the step */
    double maneuver_time_s;           /* plant time since the maneuver started (< 0: not yet) */
    dct_outputs outputs;
    double commands[RT_MAX_COMMANDS]; /* the received values as applied in this tick */
    uint64_t fault_mask;              /* fault slots active in this tick (bit = slot) */
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
    rt_frame frames[RT_RING_SIZE];
} rt_ring;

typedef struct {
    double time_s;                    /* loop time since start (tick deadline) */
    uint32_t dir;                     /* RT_DIR_* */
    rt_frame frame;
} rt_log_entry;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* entries lost because the reader fell behind */
    rt_log_entry entries[RT_LOG_SIZE];
} rt_log_ring;

/* counts of one message (stats.msgs) */
typedef struct {
    uint64_t frames;                  /* received: accepted; sent: sent */
    uint64_t bad_length;              /* received: rejected, by reason */
    uint64_t bad_crc;
    uint64_t bad_counter;
    uint64_t timeouts;                /* received: times it timed out */
    uint64_t dropped;                 /* sent: refused by a full socket buffer or ring */
    uint64_t saturated;               /* sent: values the codec limited to their signal's
                                         range or bit field, in the frames made (ct_encode_counted) */
    int32_t timed_out;                /* received: 1 while timed out (all are at start) */
    int32_t reserved;
} rt_msg_stats;

/* counts of one channel (stats.chan); the totals in rt_stats are their sums */
typedef struct {
    uint64_t rx_frames;
    uint64_t rx_accepted;
    uint64_t rx_unknown_id;
    uint64_t rx_bad_length;
    uint64_t rx_bad_crc;
    uint64_t rx_bad_counter;
    uint64_t rx_overflow;
    uint64_t tx_frames;
    uint64_t tx_dropped;
} rt_chan_stats;

typedef struct {
    uint32_t seq;                     /* odd while the loop is writing */
    int state;                        /* RT_STATE_* */
    int error;                        /* errno of a fatal transport error */
    int rt_policy_ok;                 /* SCHED_FIFO was granted */
    int memory_locked;                /* mlockall succeeded */
    int affinity_ok;
    int startup_phase;                /* RT_START_* */
    int64_t t0_ns;                    /* the first tick's deadline (CLOCK_MONOTONIC, ns; 0 before
                                         RT_START_READY): the ticks fall on t0_ns + k period */
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
    int32_t n_channels;
    int32_t n_messages;               /* of all channels, channel by channel in table order */
    rt_chan_stats chan[RT_MAX_CHANNELS];
    rt_msg_stats msgs[RT_MAX_MESSAGES];
    double commands[RT_MAX_COMMANDS]; /* the received values as applied this tick */
    dct_outputs outputs;              /* the plant's outputs after this tick */
    uint64_t fault_mask;              /* fault slots active after this tick (bit = slot) */
    uint64_t fault_changes;           /* starts and ends so far (stats.faults changed) */
    rt_fault_stats faults[RT_MAX_FAULTS];
} rt_stats;

/* ---- the scope: min and max of chosen values over buckets of ticks -------
 *
 * For a live view that must not hide a one-tick spike: Python writes a
 * configuration (up to RT_SCOPE_TRACES byte offsets of doubles in the
 * rt_loop, and the ticks per bucket) into scope_cfg[(gen + 1) & 1] and
 * publishes gen + 1 (rt_scope_publish). Each tick loads the generation
 * (acquire); a new one is checked once (offsets inside the loop and
 * 8-aligned, 1..RT_SCOPE_MAX_BUCKET ticks; a bad one is refused, counted in
 * scope_refused, and tracing stops) and acknowledged (scope_ack, release).
 * At the end of every executed tick the values are read and their min and
 * max kept (NaN values are left out); every bucket_ticks ticks one
 * rt_scope_bucket goes into the scope ring (full: dropped and counted).
 * With no trace configured the tick pays one load. */
#define RT_SCOPE_TRACES 32
#define RT_SCOPE_MAX_BUCKET 2000      /* ticks */
#define RT_SCOPE_RING_SIZE 2048       /* buckets, a power of two */

typedef struct {
    uint32_t n;                       /* traces, 0..RT_SCOPE_TRACES (0: off) */
    uint32_t bucket_ticks;            /* executed ticks per bucket */
    uint32_t offset[RT_SCOPE_TRACES]; /* bytes from the start of the rt_loop of a double */
} rt_scope_config;

typedef struct {
    uint64_t tick;                    /* the bucket's last executed tick */
    double time_s;                    /* plant time after that tick's step */
    uint32_t gen;                     /* the configuration's generation */
    uint32_t ticks;                   /* ticks in the bucket */
    double min[RT_SCOPE_TRACES];      /* +inf / -inf: no finite value in the bucket */
    double max[RT_SCOPE_TRACES];
} rt_scope_bucket;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* buckets lost because the reader fell behind */
    rt_scope_bucket buckets[RT_SCOPE_RING_SIZE];
} rt_scope_ring;

/* ---- captures: chosen values at every tick, for triggered captures -------
 *
 * Python writes a configuration (up to RT_CAPTURE_SIGNALS sources and the
 * ticks between records) into capture_cfg[(gen + 1) & 1] and publishes gen
 * + 1 (rt_capture_publish); the tick takes a new generation whole after a
 * check (offsets of doubles inside the loop, 8-aligned; command indexes
 * below RT_MAX_COMMANDS; 1..RT_CAPTURE_MAX_EVERY ticks; a bad one is
 * refused, counted in capture_refused, and capturing stops) and
 * acknowledges it (capture_ack, release). A source is a byte offset into
 * the rt_loop of a double (a plant output or input, a CAN signal's last
 * value, a statistic of the tick before) or RT_CAPTURE_CMD | k, the k-th
 * received value as applied in this tick. Every `every` executed ticks one
 * rt_capture_record (the plant after the tick's step, as the recorder's
 * sample) goes into the capture ring (full: dropped and counted); the
 * reader (rt_loop.measure.capture) cuts the captures out of it by their
 * triggers. With nothing configured the tick pays one load. */
#define RT_CAPTURE_SIGNALS 64
#define RT_CAPTURE_MAX_EVERY 20000    /* ticks */
#define RT_CAPTURE_RING_SIZE 4096     /* records, a power of two */
#define RT_CAPTURE_CMD 0x80000000u    /* source flag: a received value, not an offset */

typedef struct {
    uint32_t n;                       /* sources, 0..RT_CAPTURE_SIGNALS (0: off) */
    uint32_t every;                   /* executed ticks between records */
    uint32_t source[RT_CAPTURE_SIGNALS];
} rt_capture_config;

typedef struct {
    uint64_t tick;                    /* executed tick index */
    double time_s;                    /* plant time after its step */
    uint32_t gen;                     /* the configuration (its sources, in order) */
    uint32_t n;
    double values[RT_CAPTURE_SIGNALS];
} rt_capture_record;

typedef struct {
    uint32_t head;
    uint32_t tail;
    uint64_t dropped;                 /* records lost because the reader fell behind */
    rt_capture_record records[RT_CAPTURE_RING_SIZE];
} rt_capture_ring;

/* ---- a maneuver started and stopped while the loop runs ------------------
 *
 * Python writes maneuver_op (RT_MCMD_*) and, for a start, the table into
 * maneuver_next, then publishes maneuver_seq + 1 (rt_maneuver_publish); the
 * next tick takes it (before the driver runs) and stores the sequence in
 * maneuver_ack (release); Python writes again only once the two are equal.
 * A start with a bad table is refused (maneuver_refused). A start plays
 * the table from this tick (maneuver time 0; keep_running as the table
 * says), replacing any maneuver; a stop ends the one playing (state
 * RT_MANEUVER_DONE, the accelerator released, the brake held as it was).
 * A plant reset puts the plant back at rest as it starts (dct_plant_reset:
 * standing, engine idling, every sleeve in neutral, clutches open, the
 * initial temperatures), its time going on; the inputs stay as they are. */
#define RT_MCMD_START 1
#define RT_MCMD_STOP 2
#define RT_MCMD_RESET_PLANT 3

typedef struct {
    rt_config cfg;
    dct_plant plant;                  /* params filled by Python before rt_loop_prepare() */
    rt_stats stats;
    int stop_request;                 /* set by rt_loop_request_stop() */
    int n_channels;                   /* 1 .. RT_MAX_CHANNELS, filled by Python */
    rt_channel chan[RT_MAX_CHANNELS];
    int n_commands;                   /* 0 .. RT_MAX_COMMANDS, filled by Python */
    int32_t command_input[RT_MAX_COMMANDS];  /* the dct_inputs double each command value
                                                drives, -1: recorded only */
    /* per message (loop-wide numbering), the loop's own */
    ct_rx_state rx_state[RT_MAX_MESSAGES];
    uint64_t last_rx_tick[RT_MAX_MESSAGES];
    uint64_t tx_count[RT_MAX_MESSAGES];      /* frames made so far (counters, toggles) */
    rt_ring rx[RT_MAX_CHANNELS];      /* bridge: python-can -> loop, per channel */
    rt_ring tx[RT_MAX_CHANNELS];      /* bridge: loop -> python-can, per channel */
    rt_log_ring log;                  /* loop -> traffic log writer */
    rt_driver driver;                 /* filled by Python before rt_loop_prepare() */
    rt_rec_ring rec;                  /* loop -> recorder */
    /* measurement, calibration, stimulus (see above) */
    int n_regions;                    /* filled by Python before rt_loop_prepare */
    rt_region regions[RT_MAX_REGIONS];
    uint32_t daq_gen;                 /* written by Python: the configuration in daq[gen & 1] */
    uint32_t daq_ack;                 /* written by the loop: the generation its last tick used */
    uint64_t daq_refused;             /* configurations the loop found bad and ignored */
    rt_daq_config daq[2];
    rt_daq_ring daq_ring;             /* loop -> the XCP slave's sender (rt_xcp_send.h) */
    rt_write_ring cal;                /* calibration writes: Python -> loop */
    rt_write_ring stim;               /* stimulus writes: Python -> loop */
    int n_signal_values;              /* set by rt_loop_prepare: signals of all channels */
    double signal_values[RT_MAX_SIGNAL_VALUES];  /* each CAN signal's last value (physical),
                                         NaN until its first frame: channel c's signal k
                                         at chan[c].first_signal_value + k */
    /* failure simulation (see above) */
    rt_fault_cmd_ring fault_cmds;     /* Python -> loop */
    rt_fault_event_ring fault_events; /* loop -> Python */
    /* the scope (see above) */
    rt_scope_config scope_cfg[2];
    uint32_t scope_gen;               /* written by Python: the configuration in scope_cfg[gen & 1] */
    uint32_t scope_ack;               /* written by the loop: the generation it took */
    uint64_t scope_refused;           /* configurations refused */
    rt_scope_ring scope;              /* loop -> Python */
    /* captures (see above) */
    rt_capture_config capture_cfg[2];
    uint32_t capture_gen;             /* written by Python */
    uint32_t capture_ack;             /* written by the loop: the generation it took */
    uint64_t capture_refused;         /* configurations refused */
    rt_capture_ring capture;          /* loop -> Python */
    /* maneuvers while running (see above) */
    rt_driver maneuver_next;
    uint32_t maneuver_op;             /* RT_MCMD_* */
    uint32_t maneuver_seq;            /* written by Python */
    uint32_t maneuver_ack;            /* written by the loop */
    uint32_t maneuver_refused;        /* starts refused (a bad table) */
} rt_loop;

/* validates cfg, the channels' tables and the commands, initialises the
 * plant (dct_plant_init) with its step set to the period, the statistics,
 * the counters' state and the command values (the targets' safe values);
 * returns 0 or a negative errno-style code. After a failed prepare
 * rt_loop_run refuses the loop (-EINVAL) until a prepare succeeds. */
int rt_loop_prepare(rt_loop *l);
/* runs the loop in the calling thread until stopped; returns the final state */
int rt_loop_run(rt_loop *l);
/* locks (and so touches) the storage of the RT_RELEASE_* rings in ``rings`` again, so
   that the tick never faults on it: called outside the tick, before a feature that uses
   a ring the run released starts (a recording while the loop runs); 0 or -errno */
int rt_loop_hold_rings(rt_loop *l, uint32_t rings);
void rt_loop_request_stop(rt_loop *l);
/* a consistent copy of the statistics without stopping the loop; 0 ok,
 * -1 if the loop kept writing through every retry (1000 and 2 s at least) */
int rt_stats_read(rt_loop *l, rt_stats *copy);

int rt_ring_push(rt_ring *r, const rt_frame *f);   /* 0, or -1 full (counted) */
int rt_ring_pop(rt_ring *r, rt_frame *f);              /* 0, or -1 empty */
int rt_log_pop(rt_log_ring *r, rt_log_entry *e);        /* 0, or -1 empty */
/* up to n frames at once (bridge thread): returns how many */
int rt_ring_push_many(rt_ring *r, const rt_frame *f, int n);
int rt_ring_pop_many(rt_ring *r, rt_frame *f, int n);
int rt_log_pop_many(rt_log_ring *r, rt_log_entry *e, int n);
int rt_rec_pop_many(rt_rec_ring *r, rt_sample *s, int n);
int rt_daq_pop_many(rt_daq_ring *r, rt_dto *d, int n);
/* queues writes (the ring's only producer); returns how many were queued
 * (the rest counted in dropped) */
int rt_write_push_many(rt_write_ring *r, const rt_write *w, int n);
/* fault commands in (the ring's only producer), fault events out */
int rt_fault_push_many(rt_fault_cmd_ring *r, const rt_fault_cmd *c, int n);
int rt_fault_events_pop_many(rt_fault_event_ring *r, rt_fault_event *e, int n);
/* the DAQ hand-over with the memory order it needs on any CPU: publish the
 * generation whose slot Python has just written (release), read the one the
 * loop last used (acquire) */
void rt_daq_publish(rt_loop *l, uint32_t gen);
uint32_t rt_daq_acked(rt_loop *l);
/* the same hand-over for the scope's configuration and for maneuver commands */
void rt_scope_publish(rt_loop *l, uint32_t gen);
uint32_t rt_scope_acked(rt_loop *l);
int rt_scope_pop_many(rt_scope_ring *r, rt_scope_bucket *b, int n);
void rt_capture_publish(rt_loop *l, uint32_t gen);
uint32_t rt_capture_acked(rt_loop *l);
int rt_capture_pop_many(rt_capture_ring *r, rt_capture_record *c, int n);
void rt_maneuver_publish(rt_loop *l, uint32_t seq);
uint32_t rt_maneuver_acked(rt_loop *l);
/* Benchmark only (reads the clock; the loop must not be running): the DAQ
 * copy of the published configuration (every list, every event firing),
 * `iterations` times into the DAQ ring, which is emptied after each; returns
 * ns per copy, -1 for a bad configuration or argument. */
double rt_daq_bench(rt_loop *l, int64_t iterations);
/* Benchmark only (the loop must not be running): the capture's work of one
 * tick with the published configuration (every call due), `iterations`
 * times into the capture ring, emptied after each; ns per tick, -1 for a
 * refused configuration or a bad argument. */
double rt_capture_bench(rt_loop *l, int64_t iterations);

#endif
