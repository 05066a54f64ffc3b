/*
 * tcu_fast.h - the reference TCU, the in-process CAN contract and the drivers
 * in C, for offline closed-loop runs as fast as the plant allows.
 *
 * The truth is the Python: tcu_stub/logic.py and tcu_stub/diagnostics.py
 * (the TCU), tcu_stub/offline.py (ContractLink: each message at its cycle
 * time and phase, every value through the DBC's quantisation) and
 * plant/driver.py (the drivers). This is a port, operation for operation in
 * IEEE 754 double, so that the same inputs give the same commands to the bit
 * (tests/test_offline_fast.py holds the two together). Every calibration
 * value comes from Python at run start (tcu_stub/fast.py): nothing here
 * repeats a number of logic.py.
 *
 * What the port leaves out, because the in-process link cannot produce it:
 * lost or rejected plant messages (the phase "stale", the CAN and engine
 * message trouble codes). Runs that simulate them (run_offline's stale_fn,
 * sensor_fault, another link) use the Python TCU.
 *
 * The plant is stepped through function pointers taken from plant._dct_plant
 * (the very code Plant.step runs); the link packs and unpacks frames with the
 * table codec of can_dbc/csrc/can_table.c.
 *
 * Read by cffi like dct_plant.h: plain structs, integer #defines, prototypes.
 */
#ifndef TCU_FAST_H
#define TCU_FAST_H

#include <stdint.h>

#include "can_table.h"
#include "dct_plant.h"

/* phases, in the order of logic.PHASES (TCU_Status.TcuPhase) */
#define TCU_STANDSTILL 0
#define TCU_LAUNCH 1
#define TCU_DRIVE 2
#define TCU_UPSHIFT_TORQUE 3
#define TCU_UPSHIFT_INERTIA 4
#define TCU_DOWNSHIFT_INERTIA 5
#define TCU_DOWNSHIFT_TORQUE 6
#define TCU_SHIFT_OPEN 7
#define TCU_STALE 8
#define TCU_SAFE 9
#define TCU_N_PHASES 10

/* the plant signals the TCU reads (a sensors array), names: tcu_sensor_name() */
#define TCU_S_ENGINE_SPEED 0
#define TCU_S_INPUT_SHAFT1_SPEED 1
#define TCU_S_INPUT_SHAFT2_SPEED 2
#define TCU_S_OUTPUT_SHAFT1_SPEED 3
#define TCU_S_OUTPUT_SHAFT2_SPEED 4
#define TCU_S_CLUTCH_PRESSURE1 5
#define TCU_S_CLUTCH_PRESSURE2 6
#define TCU_S_LINE_PRESSURE 7
#define TCU_S_FORK_POSITION1 8
#define TCU_S_SYNC_STATE1 12
#define TCU_S_VEHICLE_SPEED 16
#define TCU_S_LONG_ACCEL 17
#define TCU_S_ROAD_GRADE 18
#define TCU_S_ACCEL_PEDAL 19
#define TCU_S_BRAKE_PEDAL 20
#define TCU_S_ENGINE_TORQUE 21
#define TCU_S_SELECTOR_LEVER 22       /* VEH_Driver.SelectorLever: 0 P, 1 R, 2 N, 3 D */
#define TCU_S_TRANS_OIL_TEMP 23       /* DCT_Shift.TransOilTemp, degC */
#define TCU_N_SENSORS 24

/* the TCU's command signals (a commands array), names: tcu_command_name() */
#define TCU_C_SOLENOID_CURRENT1 0
#define TCU_C_SOLENOID_CURRENT2 1
#define TCU_C_LINE_SOLENOID_CURRENT 2
#define TCU_C_FORK_FORCE1 3
#define TCU_C_ENGINE_TORQUE_REQUEST 7
#define TCU_C_TORQUE_REQUEST_ACTIVE 8
#define TCU_C_TARGET_GEAR 9
#define TCU_C_ACTIVE_FAULTS 10
#define TCU_C_FAULT_COUNT 11
#define TCU_C_LAST_FAULT 12
#define TCU_C_INHIBITED_GEARS 13
#define TCU_C_LIMP_HOME 14
#define TCU_C_SHIFT_ACTIVE 15
#define TCU_C_TCU_PHASE 16
#define TCU_C_TCU_STATE 17
#define TCU_N_COMMANDS 18

#define TCU_MAX_TABLE 16          /* points of a calibration table */
#define TCU_MAX_SHIFTS 1024       /* shifts kept between two drains (tcu_state.shifts) */
#define TCU_N_GEARS 6

/* ------------------------------------------------------------------ */
/* Calibration: logic.py's module constants (TcuCalibration in         */
/* tcu_stub/fast.py) and diagnostics.py's thresholds                    */
/* ------------------------------------------------------------------ */
typedef struct {
    /* the car */
    double gear_overall_ratio[TCU_N_GEARS];   /* gears 1..6 at [0..5] */
    double final_drive[2];
    double tyre_radius_m;
    double engine_inertia_kgm2;
    double idle_rpm;
    /* derived in Python exactly as logic.py derives them */
    double gear_ratio[TCU_N_GEARS];           /* GEAR_RATIO */
    double rpm_per_kmh;                       /* RPM_PER_KMH */
    /* clutch model */
    double clutch_kiss_bar[2];
    int32_t clutch_mu_over_temp_n;
    double clutch_mu_over_temp[TCU_MAX_TABLE][2];   /* (oil degC, factor on clutch_nm_per_bar) */
    double oil_default_degc;
    double clutch_nm_per_bar[2];
    double clutch_lock_bar;
    double clutch_max_bar;
    /* valve and pressure loop */
    double valve_feedback_area_m2;
    double valve_spring_n;
    double valve_gain_n_per_a;
    double valve_max_a;
    double pressure_kp_a_per_bar;
    double pressure_ki_a_per_bar_s;
    double pressure_i_limit_a;
    double fill_current_a;
    double fill_time_s;
    int32_t fill_time_over_temp_n;
    double fill_time_over_temp[TCU_MAX_TABLE][2];   /* (oil degC, factor on fill_time_s) */
    double empty_bar;
    double line_current_a;
    /* forks */
    double fork_engage_n;
    double fork_hold_n;
    double fork_neutral_n_per_mm;
    double fork_neutral_ns_per_mm;
    double fork_neutral_max_n;
    double fork_engaged_mm;
    double fork_neutral_mm;
    /* launch and drive */
    double pedal_on_pct;
    double brake_on_pct;
    double launch_rpm_min;
    double launch_rpm_max;
    double launch_kp_nm_per_rpm;
    double launch_lock_slip_rpm;
    double lock_ramp_bar_per_s;
    double open_below_input_rpm;
    /* reverse and the selector lever */
    double reverse_overall_ratio;
    double reverse_max_kmh;
    double neutral_resume_kmh;
    /* creep and hill start */
    double creep_nm;
    double creep_hold_nm;
    double creep_ramp_nm_per_s;
    double creep_max_kmh;
    double creep_fade_kmh;
    double vehicle_weight_n;
    double hill_margin;
    double hill_min_pct;
    double hill_kp_nm_per_rpm;
    double hill_stall_rpm;
    double brake_nm_per_pct;
    /* kiss point adaptation */
    double adapt_open_s;
    double adapt_settle_s;
    double adapt_max_kmh;
    double adapt_torque_tau_s;
    double adapt_speed_tau_s;
    double adapt_steady_rpm;
    double adapt_gain_per_s;
    double adapt_max_bar_per_s;
    double adapt_range_bar;
    /* shifts: (pedal %, rpm) tables */
    int32_t upshift_n;
    double upshift_rpm[TCU_MAX_TABLE][2];
    int32_t downshift_n;
    double downshift_rpm[TCU_MAX_TABLE][2];
    double kickdown_pct;
    double kickdown_max_rpm;
    double torque_phase_s;
    double torque_margin;
    double torque_margin_nm;
    double inertia_phase_s;
    double sync_done_rpm;
    double coast_pull_nm;
    double blip_kp_nm_per_rpm;
    double blip_max_nm;
    double down_offgoing_share;
    double shift_timeout_s;
    double preselect_max_rpm;
    /* restricted schedule */
    double restricted_up_min_rpm;
    double restricted_up_down_factor;
    double restricted_down_max_rpm;
    double limp_upshift_rpm;
    double select_max_rpm;
    double leave_standstill_kmh;
    double open_sync_rpm;
    double open_sync_s;
    double tied_bar;
    /* traction limit */
    double traction_force_n;
    double traction_accel_mps2;
    double mesh_efficiency;
    double asr_slip_target;
    double asr_min_speed_kmh;
    double asr_ki_nm_per_s;
    double asr_trim_max_nm;
    double asr_kp_nm;
    double asr_min_nm;
    int32_t engine_full_load_n;
    double engine_full_load[TCU_MAX_TABLE][2];
    /* timing (logic.PERIOD_S) */
    double period_s;
    /* diagnostics.py */
    double heal_s;
    double speed_invalid_rpm;
    double speed_invalid_set_s;
    double speed_tolerance_rpm;
    double speed_tolerance_share;
    double speed_implausible_set_s;
    double pressure_invalid_bar;
    double pressure_tolerance_bar;
    double pressure_tolerance_share;
    double pressure_set_s;
    double line_low_bar;
    double line_set_s;
    double slip_rpm;
    double slip_set_s;
    double slip_limp_s;
    double engage_set_s;
    double engage_release_s;
    double max_dt_s;
    double period_first_s;
    double startup_s;             /* a message never received counts as lost this long after
                                     the plant's first frames (diagnostics.STARTUP_S) */
    int32_t limp_gear[2];
} tcu_cal;

/* ------------------------------------------------------------------ */
/* State                                                               */
/* ------------------------------------------------------------------ */
typedef struct {                  /* diagnostics.Monitor */
    int32_t bit;
    int32_t active;
    double set_s;
    double heal_s;
    double fail_s;
    double pass_s;
} tcu_monitor;

#define TCU_N_MONITORS 10         /* the monitors a healthy link can trip */
#define TCU_MAX_DIAG_EVENTS 1024  /* trouble code events kept between two drains */

typedef struct {                  /* Diagnostics.events: a bit set (1) or healed (0) */
    double t_s;
    int32_t bit;
    int32_t set;
} tcu_diag_event;

typedef struct {                  /* diagnostics.Diagnostics, without the CAN monitors */
    tcu_monitor speed_invalid[2];
    tcu_monitor speed_plausible[2];
    tcu_monitor pressure[2];
    tcu_monitor line;
    tcu_monitor slip[2];
    tcu_monitor engage;
    int32_t active_bits;
    int32_t stored_bits;
    int32_t fault_count;
    int32_t last_fault;
    int32_t inhibited;
    int32_t blocked_shafts;
    int32_t limp_home;
    int32_t safe_state;
    int32_t boost[2];
    int32_t plant_seen;           /* plant_seen_t_s is not None */
    double plant_seen_t_s;
    int32_t have_t_prev;
    double t_prev;
    double dt;
    int32_t engage_gear[2];
    double engage_wait_s[2];
    int32_t engage_failed;
    double release_s[2];
    double slip_limp_s[2];
    /* the message monitors (Diagnostics.messages): only a CAN node counts them */
    tcu_monitor engine;           /* the engine message stale (DTC 8) */
    tcu_monitor can[4];           /* stale by bad CRC, bad counter, bad length, timeout (DTC 9..12) */
    int32_t can_busy;             /* a CAN monitor active or debouncing */
    int32_t stale;                /* plant messages lost: clutches open */
    int32_t engine_lost;          /* the engine message stale now: its last values stand in */
    int32_t torque_ok;            /* torque requests allowed */
    double t_s;                   /* the period's TCU time (the events') */
    int32_t n_events;             /* events since the last drain */
    int32_t events_lost;          /* events that did not fit */
    tcu_diag_event events[TCU_MAX_DIAG_EVENTS];
} tcu_diag;

typedef struct {                  /* logic.ClutchLoop */
    double integral_a;
    double fill_left_s;
    double target_bar;
} tcu_clutch_loop;

typedef struct {
    double t_s;
    int32_t from_gear;
    int32_t to_gear;
} tcu_shift;

typedef struct {                  /* logic.TcuLogic */
    int32_t phase;                /* TCU_* */
    int32_t gear;
    int32_t target_gear;
    double pressure_bar[2];
    int32_t sleeve_side[4];
    double fork_pos_prev[4];
    int32_t has_request;          /* torque_request_nm is not None */
    double torque_request_nm;
    double shift_t0;
    int32_t shift_from;
    double latched_torque_nm;
    double shift_slip0_rpm;
    double asr_trim_nm;
    double asr_cut_nm;
    double launch_rpm;
    double creep_nm;              /* creep torque on the launch clutch (ramped) */
    double hill_nm;               /* holding torque of the grade the brake does not hold */
    double kiss_bar[2];           /* adapted kiss points of K1, K2 */
    double oil_degc;              /* transmission oil temperature as last read */
    int32_t selector;             /* selector lever as last read: 0 P, 1 R, 2 N, 3 D */
    double adapt_t_s;             /* time stopped on the brake (the adaptation's sequence) */
    int32_t adapt_shaft;          /* the clutch the next stop learns: 0 K1 (1st), 1 K2 (2nd) */
    double te_filt_nm;            /* EngineTorque low-pass */
    double n_filt_rpm;            /* engine speed low-pass */
    double idle_load_nm;          /* the engine's torque with K1 open at the stop */
    double t_s;
    double held[3];               /* pedal, brake, engine torque last received */
    int32_t line_absent;          /* no LinePressure this period: its monitor not evaluated */
    tcu_clutch_loop loops[2];
    tcu_diag diag;
    /* what _read took from the sensors this period */
    double pedal, brake, t_engine, n_engine;
    double n_out[2];
    double v_kmh, v_sched_kmh;
    double grade_pct;
    double p_meas[2];
    double line_bar;
    double fork_mm[4];
    int32_t sync_state[4];
    int32_t engaged_gear[2];
    double n_shaft_raw[2];
    double n_shaft[2];
    /* shifts started since the last drain (logic.events) */
    int32_t n_shifts;
    int32_t shifts_lost;          /* shifts that did not fit */
    tcu_shift shifts[TCU_MAX_SHIFTS];
} tcu_state;

/* a plant message as the CAN node saw it this period (sensors["stale_messages"]) */
#define TCU_MSG_OK 0
#define TCU_MSG_MISSING 1
#define TCU_MSG_TIMEOUT 2
#define TCU_MSG_BAD_CRC 3
#define TCU_MSG_BAD_COUNTER 4
#define TCU_MSG_BAD_LENGTH 5
#define TCU_MSG_REJECTED 6

/* what a CAN node adds to a period's sensors: the needed plant messages' state */
typedef struct {
    int32_t n;                    /* plant messages the TCU needs */
    const int32_t *cause;         /* per message: TCU_MSG_* */
    const int32_t *engine;        /* per message: 1 when its loss is ridden out (the engine's) */
    int32_t line_absent;          /* LinePressure not received (Python's None) */
} tcu_msgs;

/* ------------------------------------------------------------------ */
/* The TCU (tcu_logic.c, tcu_clutch.c, tcu_diag.c)                     */
/* ------------------------------------------------------------------ */
const char *tcu_sensor_name(int i);       /* the DBC signal name of a sensor slot, "" if none */
const char *tcu_command_name(int i);      /* the DBC signal name of a command slot */
const char *tcu_phase_name(int i);        /* logic.PHASES[i] */
void tcu_reset(const tcu_cal *cal, tcu_state *s);
/* one period: sensors (TCU_N_SENSORS) -> commands (TCU_N_COMMANDS), as TcuLogic.step */
void tcu_step(const tcu_cal *cal, tcu_state *s, double t_s, const double *sensors, double *commands);
/* the same with the plant messages' state (a CAN node's period, TcuLogic.step with
   sensors["stale_messages"]); msgs NULL: every message received, as tcu_step */
void tcu_step_node(const tcu_cal *cal, tcu_state *s, double t_s, const double *sensors,
                   const tcu_msgs *msgs, double *commands);

/* internal to the TCU's files */
double tcu_clutch_current(const tcu_cal *cal, tcu_clutch_loop *loop, double target_bar,
                          double measured_bar, double dt, double fill_time_s);
void tcu_clutch_reset(tcu_clutch_loop *loop);
double tcu_torque_to_bar(const tcu_cal *cal, const tcu_state *s, int clutch, double torque_nm);
double tcu_nm_per_bar(const tcu_cal *cal, const tcu_state *s, int clutch);
double tcu_gear_input_rpm(const tcu_cal *cal, const tcu_state *s, int gear);
void tcu_diag_reset(const tcu_cal *cal, tcu_diag *d);
void tcu_diag_messages(const tcu_cal *cal, tcu_diag *d, double t_s);
/* Diagnostics.messages: 1 when the plant is lost (a needed message but the engine's stale) */
int tcu_diag_node(const tcu_cal *cal, tcu_diag *d, double t_s, const tcu_msgs *msgs);
void tcu_diag_monitor(const tcu_cal *cal, tcu_state *s);
int tcu_diag_state(const tcu_diag *d, int phase);
int tcu_requested_gear(const tcu_state *s, int shaft);
/* logic.GEAR_LAYOUT as the C has it (tcu_stub/fast.py checks them equal): 0, -1 for a bad gear */
int tcu_gear_layout(int gear, int32_t *shaft, int32_t *sleeve, int32_t *side);

/* ------------------------------------------------------------------ */
/* The CAN contract in process (tcu_link.c): offline.ContractLink       */
/* ------------------------------------------------------------------ */
#define TCU_LINK_MAX_MESSAGES 8
#define TCU_LINK_MAX_SIGNALS 16

typedef struct {
    int32_t msg;                  /* index in the codec table */
    int32_t divisor;              /* due in TCU period k when k % divisor == offset */
    int32_t offset;
    int32_t n_signals;            /* the message's signals, in the table's order */
    /* plant message: the dct_outputs index each signal carries (-1: sent as 0);
       TCU message: the command slot (-1: sent as 0) */
    int32_t source[TCU_LINK_MAX_SIGNALS];
    /* plant message: the sensor slot it fills (-1: none);
       TCU message: the dct_inputs index it drives (-1: none) */
    int32_t target[TCU_LINK_MAX_SIGNALS];
} tcu_link_message;

typedef struct {
    const ct_table *table;
    int32_t n_plant;
    int32_t n_tcu;
    tcu_link_message plant[TCU_LINK_MAX_MESSAGES];
    tcu_link_message tcu[TCU_LINK_MAX_MESSAGES];
    int32_t received;             /* 0 until the first sensors(): that one refreshes every message */
} tcu_link;

/* the TCU's view in period k: the plant messages due refreshed (all of them
   the first time), the others as last received */
void tcu_link_sensors(tcu_link *l, const double *outputs, int64_t k, double *sensors);
/* the TCU messages due in period k, quantised, into the plant inputs */
void tcu_link_apply(const tcu_link *l, const double *commands, int64_t k, double *inputs);

/* ------------------------------------------------------------------ */
/* Drivers (tcu_driver.c): plant/driver.py                             */
/* ------------------------------------------------------------------ */
#define TCU_DRIVER_EXTERNAL 0     /* pedals set by the caller (a Python driver) */
#define TCU_DRIVER_STEP 1         /* ScriptedDriver, mode "step" */
#define TCU_DRIVER_LINEAR 2       /* ScriptedDriver, mode "linear" */
#define TCU_DRIVER_SPEED 3        /* SpeedTrackingDriver */

typedef struct {
    int32_t kind;
    int32_t n;                    /* rows (scripted) or trace samples (speed) */
    const double *t_s;            /* row times / trace times */
    const double *a;              /* accel pedal % / trace speed km/h */
    const double *b;              /* brake pedal % / trace acceleration m/s2 */
    const double *sel;            /* scripted: selector code per row (0 P .. 3 D), or NULL */
    /* SpeedTrackingDriver */
    double kp;
    double ki;
    double lookahead_s;
    double integral_limit_n;
    double hold_brake_pct;
    /* its CarData */
    double mass_kg;
    double wheel_radius_m;
    double rolling_resistance;
    double drag_area_m2;
    double brake_torque_max_nm;
    double launch_ratio;
    double driveline_efficiency;
    double rotating_mass_factor;
    double air_density_kg_m3;
    double g_mps2;
    int32_t n_full;
    double full_load_rpm[TCU_MAX_TABLE];
    double full_load_nm[TCU_MAX_TABLE];
    int32_t n_drag;
    double drag_rpm[TCU_MAX_TABLE];
    double drag_nm[TCU_MAX_TABLE];
    /* state */
    double integral;
    int32_t has_t_last;
    double t_last;
} tcu_driver;

/* numpy.interp(x, xp, fp) for one x, the same arithmetic */
double tcu_np_interp(double x, const double *xp, const double *fp, int n);
/* the pedals at t_s from the plant outputs (kind EXTERNAL: leaves them) */
void tcu_driver_pedals(tcu_driver *d, double t_s, const dct_outputs *out, double *accel_pct,
                       double *brake_pct);
/* the selector lever's code at t_s of a scripted driver with a selector column
   (ScriptedDriver.selector: held from its row on), -1 for any other driver */
double tcu_driver_selector(const tcu_driver *d, double t_s);

/* The plant's layout this extension was compiled with, in doubles' bytes:
   sizeof(dct_plant), offsetof state, inputs, outputs, sizeof dct_inputs,
   dct_outputs, offsetof state.time_s, inputs.accel_pedal_pct,
   inputs.brake_pedal_pct, outputs.vehicle_speed_kmh, outputs.engine_speed_rpm.
   tcu_stub/fast.py compares them with plant._dct_plant's: a dct_plant.h
   changed since this extension was built must not go unnoticed. */
#define TCU_N_PLANT_LAYOUT 11
void tcu_plant_layout(int64_t *out);

/* ------------------------------------------------------------------ */
/* The closed loop (tcu_run.c): offline.run_offline in one call        */
/* ------------------------------------------------------------------ */
/* recorded after the outputs: target gear, gear, phase, active faults, limp home,
 * the adapted kiss points of K1 and K2 */
#define TCU_RUN_N_TCU_COLUMNS 7
#define TCU_RUN_ERR_RECORD -100   /* the record buffer is full */

typedef struct {
    dct_plant *plant;
    int (*plant_step)(dct_plant *, int);
    void (*plant_update_outputs)(dct_plant *);
    tcu_link *link;
    const tcu_cal *cal;
    tcu_state *tcu;
    tcu_driver *driver;
    int32_t steps_per_tcu;        /* plant steps per TCU period */
    int32_t tcu_per_driver;       /* TCU periods per driver call */
    int32_t tcu_per_record;       /* TCU periods per recorded row */
    int32_t record_before_tcu;    /* 1: rows before the TCU's step (dct-hil simulate's CSV),
                                     0: after its commands (run_offline) */
    double t0_s;                  /* plant time at the start */
    int64_t k;                    /* the next TCU period */
    /* scenario rows (dct-hil simulate with a CSV): row r applies in the first
       period whose k * tick_s + 1e-9 >= row_t[r] */
    double tick_s;
    int32_t n_rows;
    int32_t n_row_columns;
    const double *row_t;
    const double *row_values;     /* n_rows x n_row_columns */
    const int32_t *row_inputs;    /* dct_inputs index of each column */
    int32_t row;
    /* recording: t, then these outputs, then TCU_RUN_N_TCU_COLUMNS */
    int32_t n_rec_outputs;
    const int32_t *rec_outputs;
    double *rec;
    int64_t rec_cap;
    int64_t rec_n;
    /* optional trace of every period (tests): t, sensors, commands */
    double *trace;                /* trace_cap x (1 + TCU_N_SENSORS + TCU_N_COMMANDS), or NULL */
    int64_t trace_cap;
    int64_t trace_n;
    /* 1: time the plant's steps and the rest apart (the benchmark; two clock reads a period) */
    int32_t time_split;
    double plant_s;               /* time in the plant's steps */
    double other_s;               /* time in the rest of the loop */
    /* scratch */
    double sensors[TCU_N_SENSORS];
    double commands[TCU_N_COMMANDS];
} tcu_run;

/* The inputs of period run->k: the scenario rows due, the driver's pedals when
   due, the outputs recomputed if any changed (the first part of a period) */
void tcu_run_inputs(tcu_run *run);
/* Runs n TCU periods (or until the plant refuses a step): DCT_OK, the
   plant's status, or TCU_RUN_ERR_RECORD. run->k counts on. */
int tcu_run_periods(tcu_run *run, int64_t n);

#endif
