/*
 * tcu_logic.c - the reference TCU's logic (logic.TcuLogic): phase machine,
 * shift schedule, pre-selection, clutch-to-clutch shifts, fork control,
 * engine interventions, the restricted schedule of the diagnostics.
 *
 * A line-by-line port: each function carries the name of the method it
 * ports, and each expression keeps Python's order of operations, so the
 * results are the same doubles. Python's None torque request is has_request 0.
 */
#include <string.h>

#include "tcu_fast.h"
#include "tcu_util.h"

static const char *const SENSOR_NAMES[TCU_N_SENSORS] = {
    "EngineSpeed", "InputShaft1Speed", "InputShaft2Speed", "OutputShaft1Speed", "OutputShaft2Speed",
    "ClutchPressure1", "ClutchPressure2", "LinePressure",
    "ForkPosition1", "ForkPosition2", "ForkPosition3", "ForkPosition4",
    "SyncState1", "SyncState2", "SyncState3", "SyncState4",
    "VehicleSpeed", "LongAccel", "RoadGrade", "AccelPedal", "BrakePedal", "EngineTorque",
    "SelectorLever", "TransOilTemp",
};

static const char *const COMMAND_NAMES[TCU_N_COMMANDS] = {
    "SolenoidCurrent1", "SolenoidCurrent2", "LineSolenoidCurrent",
    "ForkForce1", "ForkForce2", "ForkForce3", "ForkForce4",
    "EngineTorqueRequest", "TorqueRequestActive", "TargetGear",
    "ActiveFaults", "FaultCount", "LastFault", "InhibitedGears", "LimpHome", "ShiftActive",
    "TcuPhase", "TcuState",
};

static const char *const PHASE_NAMES[TCU_N_PHASES] = {
    "standstill", "launch", "drive", "upshift_torque", "upshift_inertia", "downshift_inertia",
    "downshift_torque", "shift_open", "stale", "safe",
};

const char *tcu_sensor_name(int i) { return 0 <= i && i < TCU_N_SENSORS ? SENSOR_NAMES[i] : ""; }
const char *tcu_command_name(int i) { return 0 <= i && i < TCU_N_COMMANDS ? COMMAND_NAMES[i] : ""; }
const char *tcu_phase_name(int i) { return 0 <= i && i < TCU_N_PHASES ? PHASE_NAMES[i] : ""; }

static int shift_phase(int phase)
{
    return phase == TCU_UPSHIFT_TORQUE || phase == TCU_UPSHIFT_INERTIA ||
           phase == TCU_DOWNSHIFT_INERTIA || phase == TCU_DOWNSHIFT_TORQUE || phase == TCU_SHIFT_OPEN;
}

/* logic._interp: piecewise linear over (x, y) rows, the ends held */
static double interp(double x, const double table[][2], int n)
{
    if (x <= table[0][0])
        return table[0][1];
    for (int i = 0; i + 1 < n; i++) {
        double x0 = table[i][0], y0 = table[i][1], x1 = table[i + 1][0], y1 = table[i + 1][1];
        if (x <= x1)
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0);
    }
    return table[n - 1][1];
}

/* TcuLogic.nm_per_bar: capacity gain above the kiss point at the oil temperature */
double tcu_nm_per_bar(const tcu_cal *cal, const tcu_state *s, int clutch)
{
    return cal->clutch_nm_per_bar[clutch] *
           interp(s->oil_degc, cal->clutch_mu_over_temp, cal->clutch_mu_over_temp_n);
}

static double ramp(double value, double target, double rate, double dt)
{
    double step = rate * dt;
    return target > value ? py_min(value + step, target) : py_max(value - step, target);
}

/* logic.gear_rpm: input shaft speed of gear at a vehicle speed */
static double gear_rpm(const tcu_cal *cal, int gear, double vehicle_speed_kmh)
{
    return vehicle_speed_kmh * cal->rpm_per_kmh * cal->gear_overall_ratio[gear - 1];
}

static void add_shift(tcu_state *s, int from, int to)
{
    if (s->n_shifts >= TCU_MAX_SHIFTS) {
        s->shifts_lost++;
        return;
    }
    tcu_shift *e = &s->shifts[s->n_shifts++];
    e->t_s = s->t_s;
    e->from_gear = from;
    e->to_gear = to;
}

void tcu_reset(const tcu_cal *cal, tcu_state *s)
{
    memset(s, 0, sizeof *s);
    s->phase = TCU_STANDSTILL;
    s->gear = 1;
    s->target_gear = 1;
    s->shift_from = 1;
    s->launch_rpm = cal->launch_rpm_min;
    s->kiss_bar[0] = cal->clutch_kiss_bar[0];
    s->kiss_bar[1] = cal->clutch_kiss_bar[1];
    s->oil_degc = cal->oil_default_degc;
    s->selector = TCU_SELECTOR_D;
    for (int i = 0; i < 2; i++)
        tcu_clutch_reset(&s->loops[i]);
    tcu_diag_reset(cal, &s->diag);
}

/* ------------------------------------------------------------------ sensors */
static int sleeve_engaged(const tcu_cal *cal, const tcu_state *s, int sleeve, int side)
{
    return s->sync_state[sleeve] == TCU_SYNC_ENGAGED && s->fork_mm[sleeve] * side >= cal->fork_engaged_mm;
}

static int sleeve_neutral(const tcu_cal *cal, const tcu_state *s, int sleeve)
{
    return fabs(s->fork_mm[sleeve]) <= cal->fork_neutral_mm + 0.5;
}

/* _engaged_on: the gear engaged on an input shaft (0: none) */
static int engaged_on(const tcu_cal *cal, const tcu_state *s, int shaft)
{
    for (int i = 0; i < 4; i++) {
        int g = TCU_SHAFT_GEARS[shaft][i];
        if (g && sleeve_engaged(cal, s, TCU_GEAR_SLEEVE[tcu_gi(g)], TCU_GEAR_SIDE[tcu_gi(g)]))
            return g;
    }
    return 0;
}

/* TcuLogic.gear_input_rpm: the input shaft speed the output shafts give through gear g */
double tcu_gear_input_rpm(const tcu_cal *cal, const tcu_state *s, int g)
{
    if (g == TCU_REVERSE)
        return -s->n_out[1] * (cal->reverse_overall_ratio / cal->final_drive[1]);
    return s->n_out[g <= 4 ? 0 : 1] * cal->gear_ratio[g - 1];
}

/* logic._overall_ratio */
static double overall_ratio(const tcu_cal *cal, int gear)
{
    return gear == TCU_REVERSE ? cal->reverse_overall_ratio : cal->gear_overall_ratio[gear - 1];
}

static double substitute(const tcu_cal *cal, const tcu_state *s, int shaft, double n)
{
    if (fabs(n) <= cal->speed_invalid_rpm)
        return n;
    int g = s->engaged_gear[shaft];
    if (g)
        return tcu_gear_input_rpm(cal, s, g);
    return s->n_shaft[shaft];
}

/* _read: the engine message stale, its last values stand in */
static void read_sensors(const tcu_cal *cal, tcu_state *s, const double *x)
{
    if (s->diag.engine_lost) {
        s->pedal = s->held[0];
        s->brake = s->held[1];
        s->t_engine = s->held[2];
    } else {
        s->pedal = x[TCU_S_ACCEL_PEDAL];
        s->brake = x[TCU_S_BRAKE_PEDAL];
        s->t_engine = x[TCU_S_ENGINE_TORQUE];
        s->held[0] = s->pedal;
        s->held[1] = s->brake;
        s->held[2] = s->t_engine;
    }
    s->n_engine = x[TCU_S_ENGINE_SPEED];
    s->n_out[0] = x[TCU_S_OUTPUT_SHAFT1_SPEED];
    s->n_out[1] = x[TCU_S_OUTPUT_SHAFT2_SPEED];
    s->v_kmh = x[TCU_S_VEHICLE_SPEED];
    s->grade_pct = x[TCU_S_ROAD_GRADE];
    s->oil_degc = x[TCU_S_TRANS_OIL_TEMP];
    s->selector = (int)nearbyint(x[TCU_S_SELECTOR_LEVER]);
    /* the schedule runs on the output shaft speed (driven wheels), as the gearbox sees it */
    s->v_sched_kmh = s->n_out[0] / cal->final_drive[0] / cal->rpm_per_kmh;
    s->p_meas[0] = x[TCU_S_CLUTCH_PRESSURE1];
    s->p_meas[1] = x[TCU_S_CLUTCH_PRESSURE2];
    s->line_bar = x[TCU_S_LINE_PRESSURE];
    for (int k = 0; k < 4; k++) {
        s->fork_mm[k] = x[TCU_S_FORK_POSITION1 + k];
        s->sync_state[k] = (int)nearbyint(x[TCU_S_SYNC_STATE1 + k]);   /* round(): half to even */
    }
    s->engaged_gear[0] = engaged_on(cal, s, 0);
    s->engaged_gear[1] = engaged_on(cal, s, 1);
    /* an invalid input shaft speed is replaced at once by the engaged gear's, else the last valid */
    s->n_shaft_raw[0] = x[TCU_S_INPUT_SHAFT1_SPEED];
    s->n_shaft_raw[1] = x[TCU_S_INPUT_SHAFT2_SPEED];
    double n1 = s->n_shaft_raw[0], n2 = s->n_shaft_raw[1];
    if (!(fabs(n1) <= cal->speed_invalid_rpm) || !(fabs(n2) <= cal->speed_invalid_rpm)) {
        n1 = substitute(cal, s, 0, n1);
        n2 = substitute(cal, s, 1, n2);
    }
    s->n_shaft[0] = n1;
    s->n_shaft[1] = n2;
}

/* gear_ready: gear engaged and the other sleeve of its shaft in neutral */
static int gear_ready(const tcu_cal *cal, const tcu_state *s, int gear)
{
    int shaft = TCU_GEAR_SHAFT[tcu_gi(gear)], sleeve = TCU_GEAR_SLEEVE[tcu_gi(gear)];
    if (!sleeve_engaged(cal, s, sleeve, TCU_GEAR_SIDE[tcu_gi(gear)]))
        return 0;
    for (int i = 0; i < 2; i++) {
        int k = TCU_SHAFT_SLEEVES[shaft][i];
        if (k != sleeve && !sleeve_neutral(cal, s, k))
            return 0;
    }
    return 1;
}

/* ------------------------------------------------------------------ forks */
/* _want_gears: sleeve sides for the given gears (0: none); everything else neutral */
static void want_gears(tcu_state *s, int g1, int g2)
{
    int gears[2] = {g1, g2};
    for (int k = 0; k < 4; k++)
        s->sleeve_side[k] = 0;
    for (int i = 0; i < 2; i++)
        if (gears[i])
            s->sleeve_side[TCU_GEAR_SLEEVE[tcu_gi(gears[i])]] = TCU_GEAR_SIDE[tcu_gi(gears[i])];
}

/* _neutral_force: position loop to neutral, without overshooting onto the other cone */
static double neutral_force(const tcu_cal *cal, const tcu_state *s, int k, double pos)
{
    double vel = (pos - s->fork_pos_prev[k]) / cal->period_s;
    if (fabs(pos) <= cal->fork_neutral_mm && fabs(vel) < 20.0)
        return 0.0;
    double f = -cal->fork_neutral_n_per_mm * pos - cal->fork_neutral_ns_per_mm * vel;
    return py_min(py_max(f, -cal->fork_neutral_max_n), cal->fork_neutral_max_n);
}

int tcu_requested_gear(const tcu_state *s, int shaft)
{
    if (s->phase == TCU_SAFE || s->phase == TCU_STALE)
        return 0;
    for (int i = 0; i < 4; i++) {
        int g = TCU_SHAFT_GEARS[shaft][i];
        if (g && s->sleeve_side[TCU_GEAR_SLEEVE[tcu_gi(g)]] == TCU_GEAR_SIDE[tcu_gi(g)])
            return g;
    }
    return 0;
}

static void fork_forces(const tcu_cal *cal, tcu_state *s, double *forces)
{
    for (int k = 0; k < 4; k++) {
        int side = s->sleeve_side[k];
        double pos = s->fork_mm[k];
        int state = s->sync_state[k];
        double f;
        if (s->diag.release_s[TCU_SLEEVE_SHAFT[k]] > 0.0) {
            /* a gear that did not engage: its shaft's sleeves let go for a retry */
            forces[k] = neutral_force(cal, s, k, pos);
            s->fork_pos_prev[k] = pos;
            continue;
        }
        if (state == 1 && pos != 0.0 && side != (pos > 0 ? 1 : -1))
            side = pos > 0 ? 1 : -1;   /* never let go of a sleeve on its cone */
        if (side == 0) {
            f = neutral_force(cal, s, k, pos);
        } else {
            /* a sleeve that still sits on the other gear of its shaft first goes to neutral */
            int shaft = (k == TCU_SHAFT_SLEEVES[0][0] || k == TCU_SHAFT_SLEEVES[0][1]) ? 0 : 1;
            int blocked = 0;
            for (int i = 0; i < 2; i++) {
                int j = TCU_SHAFT_SLEEVES[shaft][i];
                if (j != k && !sleeve_neutral(cal, s, j) && s->sleeve_side[j] == 0)
                    blocked = 1;
            }
            if (blocked)
                f = neutral_force(cal, s, k, pos);
            else if (sleeve_engaged(cal, s, k, side))
                f = side * cal->fork_hold_n;
            else
                f = side * cal->fork_engage_n;
        }
        forces[k] = f;
        s->fork_pos_prev[k] = pos;
    }
}

/* ------------------------------------------------------------------ schedule */
static int scheduled_gear(const tcu_cal *cal, const tcu_state *s)
{
    int g = s->gear;
    double up_rpm = interp(s->pedal, cal->upshift_rpm, cal->upshift_n);
    double down_rpm = interp(s->pedal, cal->downshift_rpm, cal->downshift_n);
    int braking = s->brake > cal->brake_on_pct;
    if (g < TCU_TOP_GEAR && gear_rpm(cal, g, s->v_sched_kmh) > up_rpm && !braking)
        return g + 1;
    if (s->pedal >= cal->kickdown_pct) {
        int lower = g;
        while (lower > 1 && gear_rpm(cal, lower - 1, s->v_sched_kmh) < cal->kickdown_max_rpm &&
               gear_rpm(cal, lower, s->v_sched_kmh) < 0.75 * up_rpm)
            lower -= 1;
        if (lower < g)
            return lower;
    }
    if (g > 1 && gear_rpm(cal, g, s->v_sched_kmh) < down_rpm)
        return g - 1;
    return g;
}

static int allowed(const tcu_state *s, int gear)
{
    return gear < 0 || !((s->diag.inhibited >> (gear - 1)) & 1);
}

/* _next_allowed: the next allowed gear from g in direction step, on shaft (-1: any); 0: none */
static int next_allowed(const tcu_state *s, int g, int step, int shaft)
{
    int n = g + step;
    while (1 <= n && n <= TCU_TOP_GEAR) {
        if (allowed(s, n) && (shaft < 0 || TCU_GEAR_SHAFT[tcu_gi(n)] == shaft))
            return n;
        n += step;
    }
    return 0;
}

static int restricted_preselection(const tcu_cal *cal, const tcu_state *s, int g, int rising)
{
    int other = 1 - TCU_GEAR_SHAFT[tcu_gi(g)];
    int up = next_allowed(s, g, 1, other);
    int down = next_allowed(s, g, -1, other);
    if (down && !rising && gear_rpm(cal, down, s->v_sched_kmh) < cal->preselect_max_rpm)
        return down;
    if (up)
        return up;
    if (down && gear_rpm(cal, down, s->v_sched_kmh) < cal->preselect_max_rpm)
        return down;
    return 0;
}

static int preselection(const tcu_cal *cal, const tcu_state *s)
{
    int g = s->gear;
    if (g == TCU_REVERSE)
        return 2;
    if (s->target_gear != g)
        return s->target_gear;
    int rising = s->pedal > cal->pedal_on_pct && s->brake < cal->brake_on_pct;
    if (s->diag.inhibited)
        return restricted_preselection(cal, s, g, rising);
    if (g == 1)
        return 2;
    if (!rising && gear_rpm(cal, g - 1, s->v_sched_kmh) < cal->preselect_max_rpm)
        return g - 1;
    return g < TCU_TOP_GEAR ? g + 1 : 0;
}

/* _restricted_schedule from gear g */
static int restricted_schedule(const tcu_cal *cal, const tcu_state *s, int g)
{
    double up_rpm = interp(s->pedal, cal->upshift_rpm, cal->upshift_n);
    double down_rpm = interp(s->pedal, cal->downshift_rpm, cal->downshift_n);
    double rpm = gear_rpm(cal, g, s->v_sched_kmh);
    int up = next_allowed(s, g, 1, -1);
    if (up && s->brake <= cal->brake_on_pct) {
        int high = rpm > (s->diag.limp_home ? cal->limp_upshift_rpm : up_rpm);
        int lands = up == g + 1 ||
                    gear_rpm(cal, up, s->v_sched_kmh) >
                        py_max(cal->restricted_up_min_rpm, cal->restricted_up_down_factor * down_rpm);
        if (high && lands)
            return up;
    }
    int down = next_allowed(s, g, -1, -1);
    if (down && rpm < down_rpm &&
        (down == g - 1 || gear_rpm(cal, down, s->v_sched_kmh) < cal->restricted_down_max_rpm))
        return down;
    return g;
}

static int gear_for_speed(const tcu_cal *cal, const tcu_state *s)
{
    int below = 0, highest = 0;
    for (int g = 1; g <= TCU_TOP_GEAR; g++) {
        if (!allowed(s, g))
            continue;
        highest = g;
        if (gear_rpm(cal, g, s->v_sched_kmh) <= cal->select_max_rpm) {
            if (restricted_schedule(cal, s, g) == g)
                return g;
            below = below ? below : g;
        }
    }
    return below ? below : highest;
}

static int gear_taken(const tcu_state *s)
{
    int p = s->phase;
    if (p == TCU_STANDSTILL || p == TCU_STALE || p == TCU_SAFE)
        return 0;
    if (p == TCU_SHIFT_OPEN)
        return !allowed(s, s->target_gear);
    if (!allowed(s, s->gear))
        return 1;
    if (shift_phase(p))
        return !allowed(s, s->target_gear) || !allowed(s, s->shift_from);
    return 0;
}

static void start_open_shift(tcu_state *s, int gear)
{
    if (gear != s->gear)
        add_shift(s, s->gear, gear);
    s->shift_from = s->gear;
    s->target_gear = gear;
    s->shift_t0 = s->t_s;
    s->phase = TCU_SHIFT_OPEN;
    s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
}

static void leave_gear(const tcu_cal *cal, tcu_state *s)
{
    s->has_request = 0;
    if (s->v_sched_kmh < cal->leave_standstill_kmh) {
        s->phase = TCU_STANDSTILL;
        s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
        return;
    }
    int g = gear_for_speed(cal, s);
    if (g)
        start_open_shift(s, g);
}

/* ------------------------------------------------------------------ phases */
static void shift_open(const tcu_cal *cal, tcu_state *s)
{
    int target = s->target_gear;
    int shaft = TCU_GEAR_SHAFT[tcu_gi(target)];
    int other = 1 - shaft;
    want_gears(s, target, 0);
    s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
    /* the other half still drives: no tie-up, no engine torque so its sleeve can leave */
    int all_free = 1;
    for (int i = 0; i < 2; i++) {
        int k = TCU_SHAFT_SLEEVES[other][i];
        if (!(sleeve_neutral(cal, s, k) && s->sync_state[k] != TCU_SYNC_ENGAGED))
            all_free = 0;
    }
    int tied = s->p_meas[other] > s->kiss_bar[other] + cal->tied_bar && !all_free;
    if (tied) {
        s->has_request = 1;
        s->torque_request_nm = 0.0;
        return;
    }
    /* the request is the engine's net torque: below zero its drag pulls it down */
    double below = gear_rpm(cal, target, s->v_sched_kmh) - s->n_engine;
    s->has_request = 1;
    s->torque_request_nm = py_min(py_max(cal->blip_kp_nm_per_rpm * below, -cal->blip_max_nm),
                                  cal->blip_max_nm);
    if (!gear_ready(cal, s, target))
        return;
    double n_in = s->n_shaft[shaft];
    int slow = n_in < cal->launch_rpm_min;
    if (!slow && s->n_engine < n_in - cal->open_sync_rpm && s->t_s - s->shift_t0 < cal->open_sync_s)
        return;                   /* the engine still on its way up to the shaft */
    s->gear = target;
    s->has_request = 0;
    if (slow) {
        s->phase = TCU_LAUNCH;
    } else {
        s->phase = TCU_DRIVE;
        s->pressure_bar[shaft] = tcu_torque_to_bar(cal, s, shaft, 0.0);
    }
}

/* _hill_hold_nm: clutch torque that holds the car on the grade, the brake's share taken off */
static double hill_hold_nm(const tcu_cal *cal, const tcu_state *s, int gear, double v)
{
    double grade = gear == TCU_REVERSE ? -s->grade_pct : s->grade_pct;
    if (grade < cal->hill_min_pct || v >= cal->creep_max_kmh)
        return 0.0;
    double ratio = overall_ratio(cal, gear);
    double force_n = cal->vehicle_weight_n * grade / sqrt(10000.0 + grade * grade);
    double need = cal->hill_margin * force_n * cal->tyre_radius_m / ratio;
    double hold = py_max(need - cal->brake_nm_per_pct * s->brake / ratio, 0.0);
    /* at most what the engine gives, so the clutch cannot pull it into a stall */
    return py_min(hold, py_max(py_max(s->t_engine, 0.0) + cal->hill_kp_nm_per_rpm * (s->n_engine - cal->hill_stall_rpm),
                               0.0));
}

/* _creep: the launch clutch's least torque at low speed (creep ramped, the grade's hold at once) */
static double creep(const tcu_cal *cal, tcu_state *s, int gear)
{
    double v = gear == TCU_REVERSE ? -s->v_sched_kmh : s->v_sched_kmh;   /* in the gear's direction */
    double target;
    if (s->brake >= cal->brake_on_pct)
        target = cal->creep_hold_nm;
    else
        target = cal->creep_nm * py_min(py_max((cal->creep_max_kmh - v) / cal->creep_fade_kmh, 0.0), 1.0);
    s->creep_nm = ramp(s->creep_nm, target, cal->creep_ramp_nm_per_s, cal->period_s);
    s->hill_nm = hill_hold_nm(cal, s, gear, v);
    return py_max(s->creep_nm, s->hill_nm);
}

/* _adapt_kiss: kiss point adaptation of gear's clutch stopped on the brake; 1 while it is held open */
static int adapt_kiss(const tcu_cal *cal, tcu_state *s, int gear)
{
    int shaft = TCU_GEAR_SHAFT[tcu_gi(gear)];
    s->te_filt_nm += cal->period_s / cal->adapt_torque_tau_s * (s->t_engine - s->te_filt_nm);
    s->n_filt_rpm += cal->period_s / cal->adapt_speed_tau_s * (s->n_engine - s->n_filt_rpm);
    int stopped = s->brake >= cal->brake_on_pct && s->pedal <= cal->pedal_on_pct &&
                  fabs(s->v_kmh) < cal->adapt_max_kmh && s->hill_nm <= 0.0 && gear_ready(cal, s, gear);
    if (!stopped) {
        if (s->adapt_t_s >= cal->adapt_open_s + cal->adapt_settle_s)
            s->adapt_shaft = 1 - s->adapt_shaft;   /* the other clutch at the next stop */
        s->adapt_t_s = 0.0;
        return 0;
    }
    s->adapt_t_s += cal->period_s;
    int steady = fabs(s->n_engine - s->n_filt_rpm) < cal->adapt_steady_rpm;
    if (s->adapt_t_s < cal->adapt_open_s) {
        if (steady)
            s->idle_load_nm = s->te_filt_nm;
        return 1;
    }
    if (s->adapt_t_s >= cal->adapt_open_s + cal->adapt_settle_s && steady && s->creep_nm == cal->creep_hold_nm) {
        double error_nm = s->creep_nm - (s->te_filt_nm - s->idle_load_nm);
        double rate = py_min(py_max(cal->adapt_gain_per_s * error_nm / tcu_nm_per_bar(cal, s, shaft),
                                    -cal->adapt_max_bar_per_s),
                             cal->adapt_max_bar_per_s);
        s->kiss_bar[shaft] = py_min(py_max(s->kiss_bar[shaft] + rate * cal->period_s,
                                           cal->clutch_kiss_bar[shaft] - cal->adapt_range_bar),
                                    cal->clutch_kiss_bar[shaft] + cal->adapt_range_bar);
    }
    return 0;
}

/* _hold_request_nm: engine torque request while the clutch holds a grade (0: none) */
static int hold_request(const tcu_cal *cal, const tcu_state *s, double *request_nm)
{
    if (s->hill_nm <= 0.0)
        return 0;
    double demand = s->pedal / 100.0 * interp(s->n_engine, cal->engine_full_load, cal->engine_full_load_n);
    *request_nm = py_max(s->hill_nm + py_max(cal->hill_kp_nm_per_rpm * (cal->idle_rpm - s->n_engine), demand),
                         0.0);
    return 1;
}

/* _recover (plant messages back, or D again while rolling): re-engage by slip control in the gear for the speed */
static void recover(const tcu_cal *cal, tcu_state *s)
{
    for (int i = 0; i < 2; i++)
        tcu_clutch_reset(&s->loops[i]);
    s->has_request = 0;
    if (s->v_kmh < 5.0) {
        s->phase = TCU_STANDSTILL;
        return;
    }
    int g;
    if (s->diag.inhibited) {
        g = gear_for_speed(cal, s);
        if (!g) {
            s->phase = TCU_STANDSTILL;
            return;
        }
    } else {
        g = 1;
        while (g < TCU_TOP_GEAR &&
               gear_rpm(cal, g, s->v_sched_kmh) > interp(s->pedal, cal->upshift_rpm, cal->upshift_n))
            g += 1;
    }
    s->gear = s->target_gear = g;
    s->phase = TCU_LAUNCH;
    want_gears(s, g, preselection(cal, s));
}

static void standstill(const tcu_cal *cal, tcu_state *s)
{
    int sel = s->selector;
    if (sel == TCU_SELECTOR_D && s->v_sched_kmh > cal->neutral_resume_kmh) {
        recover(cal, s);          /* D again while rolling: the gear for the speed, by slip */
        return;
    }
    if (sel != TCU_SELECTOR_D && (sel != TCU_SELECTOR_R || s->v_sched_kmh > cal->reverse_max_kmh)) {
        /* P, N, or R refused while rolling forward: both clutches open, no torque request */
        if (sel == TCU_SELECTOR_R)
            want_gears(s, 0, 0);  /* neutral until slow enough for R */
        else if (s->gear == TCU_REVERSE)
            want_gears(s, TCU_REVERSE, 2);
        else
            want_gears(s, 1, 2);
        s->target_gear = 0;
        s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
        s->has_request = 0;
        s->creep_nm = 0.0;
        return;
    }
    int first = sel == TCU_SELECTOR_R ? TCU_REVERSE : 1;
    if (sel == TCU_SELECTOR_R) {
        want_gears(s, TCU_REVERSE, 2);
    } else if (s->diag.inhibited) {      /* launch in the lowest allowed gear */
        first = next_allowed(s, 0, 1, -1);
        if (!first)
            return;
        want_gears(s, first, next_allowed(s, first, 1, 1 - TCU_GEAR_SHAFT[tcu_gi(first)]));
    } else {
        want_gears(s, 1, 2);
    }
    s->gear = s->target_gear = first;
    double floor = creep(cal, s, first);
    /* every other stop on the brake in D learns K2's kiss point in the pre-selected 2nd */
    int learn = first == 1 && sel == TCU_SELECTOR_D && s->adapt_shaft == 1 && allowed(s, 2) ? 2 : first;
    if (adapt_kiss(cal, s, learn))
        floor = 0.0;              /* the clutch open: the engine's idle load */
    int hold = s->adapt_t_s > 0.0 ? learn : first;
    double bars[2] = {0.0, 0.0};
    if (floor > 0.0 && gear_ready(cal, s, hold)) {
        int shaft = TCU_GEAR_SHAFT[tcu_gi(hold)];
        bars[shaft] = tcu_torque_to_bar(cal, s, shaft, floor);
    }
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    s->has_request = 0;
    if (bars[0] != 0.0 || bars[1] != 0.0)
        s->has_request = hold_request(cal, s, &s->torque_request_nm);
    if (s->pedal > cal->pedal_on_pct && s->brake < cal->brake_on_pct && gear_ready(cal, s, first))
        s->phase = TCU_LAUNCH;
}

static double traction_clutch_nm(const tcu_cal *cal, const tcu_state *s, int gear)
{
    double ratio = overall_ratio(cal, gear);
    return cal->traction_force_n * cal->tyre_radius_m / (ratio * cal->mesh_efficiency) +
           s->asr_trim_nm + s->asr_cut_nm;
}

/* _launch: slip the clutch of gear, holding the engine at a speed that rises with the pedal */
/* _selector_away: the lever left the gear's direction: both clutches open, standstill; 1 then */
static int selector_away(tcu_state *s)
{
    if ((s->selector == TCU_SELECTOR_D && s->gear != TCU_REVERSE) ||
        (s->selector == TCU_SELECTOR_R && s->gear == TCU_REVERSE))
        return 0;
    s->phase = TCU_STANDSTILL;
    s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
    s->has_request = 0;
    return 1;
}

static void launch(const tcu_cal *cal, tcu_state *s)
{
    if (selector_away(s))
        return;
    int shaft = TCU_GEAR_SHAFT[tcu_gi(s->gear)];
    want_gears(s, s->gear, preselection(cal, s));
    if (s->pedal <= cal->pedal_on_pct && s->n_shaft[shaft] < cal->open_below_input_rpm) {
        s->phase = TCU_STANDSTILL;
        return;
    }
    double n_target = cal->launch_rpm_min +
                      (cal->launch_rpm_max - cal->launch_rpm_min) * py_min(s->pedal, 100.0) / 100.0;
    n_target = py_max(n_target, s->n_shaft[shaft]);
    s->launch_rpm = n_target;
    double err = s->n_engine - n_target;
    /* the clutch takes the engine torque in proportion to how far the engine has risen */
    double share = py_min(py_max((s->n_engine - cal->idle_rpm) / py_max(n_target - cal->idle_rpm, 1.0),
                                 0.0), 1.0);
    double torque = share * py_max(s->t_engine, 0.0) + cal->launch_kp_nm_per_rpm * py_max(err, 0.0);
    torque = py_min(py_max(torque, 0.0), traction_clutch_nm(cal, s, s->gear));
    torque = py_max(torque, creep(cal, s, s->gear));   /* creep and a grade's holding torque at least */
    s->has_request = hold_request(cal, s, &s->torque_request_nm);
    double slip = s->n_engine - s->n_shaft[shaft];
    if (fabs(slip) < cal->launch_lock_slip_rpm && s->n_engine > cal->launch_rpm_min - 200) {
        s->phase = TCU_DRIVE;
        s->has_request = 0;
    }
    double bars[2] = {0.0, 0.0};
    if (gear_ready(cal, s, s->gear))   /* no torque on a shaft without its gear */
        bars[shaft] = tcu_torque_to_bar(cal, s, shaft, torque);
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
}

static void start_shift(tcu_state *s)
{
    s->shift_from = s->gear;
    s->shift_t0 = s->t_s;
    s->latched_torque_nm = py_max(s->t_engine, 0.0);
    int up = s->target_gear > s->gear;
    s->phase = up ? TCU_UPSHIFT_TORQUE : TCU_DOWNSHIFT_INERTIA;
    add_shift(s, s->gear, s->target_gear);
}

static void drive(const tcu_cal *cal, tcu_state *s)
{
    if (selector_away(s))
        return;
    int shaft = TCU_GEAR_SHAFT[tcu_gi(s->gear)];
    int other = 1 - shaft;
    double lock = s->diag.boost[shaft] ? cal->clutch_max_bar : cal->clutch_lock_bar;
    double bars[2] = {0.0, 0.0};
    bars[shaft] = ramp(s->pressure_bar[shaft], lock, cal->lock_ramp_bar_per_s, cal->period_s);
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    if (s->gear == TCU_REVERSE) { /* R: no schedule, back to standstill when released */
        s->target_gear = TCU_REVERSE;
        want_gears(s, TCU_REVERSE, 2);
        if (s->pedal <= cal->pedal_on_pct && s->n_shaft[shaft] < cal->open_below_input_rpm)
            s->phase = TCU_STANDSTILL;
        return;
    }
    if (s->gear == 1 && s->pedal <= cal->pedal_on_pct && s->n_shaft[shaft] < cal->open_below_input_rpm) {
        s->phase = TCU_STANDSTILL;
        return;
    }
    if (s->gear > 1 && s->n_shaft[shaft] < cal->idle_rpm + 50) {
        s->phase = TCU_LAUNCH;    /* too slow for this gear (a missed downshift): slip it */
        return;
    }
    int target;
    if (s->diag.inhibited) {
        target = restricted_schedule(cal, s, s->gear);
        if (target != s->gear && TCU_GEAR_SHAFT[tcu_gi(target)] != other) {
            start_open_shift(s, target);   /* a gear of the same half: an interrupted shift */
            return;
        }
    } else {
        target = scheduled_gear(cal, s);
        if (target != s->gear && TCU_GEAR_SHAFT[tcu_gi(target)] != other)
            /* kick-down over two steps lands on the same shaft: go one step now */
            target = target < s->gear ? s->gear - 1 : s->gear + 1;
    }
    s->target_gear = target;
    want_gears(s, s->gear, preselection(cal, s));
    if (target != s->gear && gear_ready(cal, s, target))
        start_shift(s);
}

static void upshift_torque(const tcu_cal *cal, tcu_state *s)
{
    int off = TCU_GEAR_SHAFT[tcu_gi(s->shift_from)], on = TCU_GEAR_SHAFT[tcu_gi(s->target_gear)];
    want_gears(s, s->shift_from, s->target_gear);
    double t_e = py_max(s->t_engine, 0.0);
    double frac = py_min((s->t_s - s->shift_t0) / cal->torque_phase_s, 1.0);
    double need = cal->torque_margin * t_e + cal->torque_margin_nm;
    double t_on = frac * need;
    double t_off = py_max(need - t_on, 0.0);
    double bars[2] = {0.0, 0.0};
    bars[on] = tcu_torque_to_bar(cal, s, on, t_on);
    bars[off] = frac < 1.0 ? py_min(tcu_torque_to_bar(cal, s, off, t_off), s->pressure_bar[off]) : 0.0;
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    if (frac >= 1.0) {
        s->phase = TCU_UPSHIFT_INERTIA;
        s->gear = s->target_gear;
        s->shift_t0 = s->t_s;
        s->latched_torque_nm = t_e;
        s->shift_slip0_rpm = py_max(s->n_engine - s->n_shaft[on], 1.0);
    }
}

static void finish_shift(tcu_state *s)
{
    s->gear = s->target_gear;
    s->has_request = 0;
    s->phase = TCU_DRIVE;
}

/* pull the engine to the new shaft: on-coming holds the drive torque, the engine gives less */
static void upshift_inertia(const tcu_cal *cal, tcu_state *s)
{
    int on = TCU_GEAR_SHAFT[tcu_gi(s->target_gear)];
    want_gears(s, s->target_gear, s->shift_from);
    double slip = s->n_engine - s->n_shaft[on];
    double t_clutch = cal->torque_margin * s->latched_torque_nm + cal->torque_margin_nm;
    double rate_target = s->shift_slip0_rpm / cal->inertia_phase_s;
    double j_torque = cal->engine_inertia_kgm2 * rate_target * 2.0 * TCU_PI / 60.0;
    double request = t_clutch - j_torque;
    s->has_request = 1;
    s->torque_request_nm = py_max(py_min(request, s->latched_torque_nm), 0.0);
    double bars[2] = {0.0, 0.0};
    bars[on] = tcu_torque_to_bar(cal, s, on, t_clutch);
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    if (slip < cal->sync_done_rpm || s->t_s - s->shift_t0 > cal->shift_timeout_s)
        finish_shift(s);
}

/* let the engine rise to the lower gear's shaft: the off-going clutch slips under
   power, or both open and a torque request blips the engine up when coasting */
static void downshift_inertia(const tcu_cal *cal, tcu_state *s)
{
    int off = TCU_GEAR_SHAFT[tcu_gi(s->shift_from)], on = TCU_GEAR_SHAFT[tcu_gi(s->target_gear)];
    want_gears(s, s->shift_from, s->target_gear);
    double t_e = py_max(s->t_engine, 0.0);
    double bars[2] = {0.0, 0.0};
    if (!s->has_request && t_e > 2 * cal->coast_pull_nm) {
        bars[off] = tcu_torque_to_bar(cal, s, off, cal->down_offgoing_share * t_e);
        bars[on] = tcu_torque_to_bar(cal, s, on, 0.0);
    } else {
        bars[on] = tcu_torque_to_bar(cal, s, on, 0.0);
        double below = s->n_shaft[on] - s->n_engine;
        s->has_request = 1;
        s->torque_request_nm = py_min(py_max(cal->blip_kp_nm_per_rpm * below, 0.0), cal->blip_max_nm);
        /* torque requests are always allowed in process (no engine message lost) */
    }
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    if (s->n_engine > s->n_shaft[on] - cal->sync_done_rpm || s->t_s - s->shift_t0 > cal->shift_timeout_s) {
        s->phase = TCU_DOWNSHIFT_TORQUE;
        s->gear = s->target_gear;
        s->shift_t0 = s->t_s;
        s->latched_torque_nm = bars[off];
        s->has_request = 0;
    }
}

static void downshift_torque(const tcu_cal *cal, tcu_state *s)
{
    int off = TCU_GEAR_SHAFT[tcu_gi(s->shift_from)], on = TCU_GEAR_SHAFT[tcu_gi(s->target_gear)];
    want_gears(s, s->target_gear, s->shift_from);
    double t_e = py_max(s->t_engine, 0.0);
    double frac = py_min((s->t_s - s->shift_t0) / cal->torque_phase_s, 1.0);
    double need = cal->torque_margin * t_e + cal->torque_margin_nm;
    double bars[2] = {0.0, 0.0};
    bars[on] = tcu_torque_to_bar(cal, s, on, py_max(frac * need, cal->coast_pull_nm));
    bars[off] = frac < 1.0 && s->latched_torque_nm > 0
                    ? tcu_torque_to_bar(cal, s, off, (1.0 - frac) * cal->down_offgoing_share * t_e)
                    : 0.0;
    s->pressure_bar[0] = bars[0];
    s->pressure_bar[1] = bars[1];
    if (frac >= 1.0)
        finish_shift(s);
}

/* ------------------------------------------------------------------ traction */
static void update_slip_trim(const tcu_cal *cal, tcu_state *s)
{
    s->asr_cut_nm = 0.0;
    if (s->v_kmh < cal->asr_min_speed_kmh || s->pedal <= cal->pedal_on_pct)
        return;
    double slip = (s->v_sched_kmh - s->v_kmh) / py_max(s->v_kmh, cal->asr_min_speed_kmh);
    double err = cal->asr_slip_target - slip;
    s->asr_trim_nm += cal->asr_ki_nm_per_s * err * cal->period_s;
    s->asr_trim_nm = py_min(py_max(s->asr_trim_nm, -cal->asr_trim_max_nm), cal->asr_trim_max_nm);
    s->asr_cut_nm = py_min(cal->asr_kp_nm * err, 0.0);
}

/* _traction_limit: engine torque limit near the tyres' peak force; 0: no limit */
static int traction_limit(const tcu_cal *cal, tcu_state *s, double *limit_nm)
{
    if (s->pedal <= cal->pedal_on_pct || (s->phase != TCU_LAUNCH && s->phase != TCU_DRIVE)) {
        s->asr_trim_nm = s->asr_cut_nm = 0.0;
        return 0;
    }
    update_slip_trim(cal, s);
    double ratio = overall_ratio(cal, s->gear);
    double limit = traction_clutch_nm(cal, s, s->gear);
    if (s->phase == TCU_DRIVE)    /* the engine also accelerates its own inertia */
        limit += cal->engine_inertia_kgm2 * cal->traction_accel_mps2 * ratio / cal->tyre_radius_m;
    else                          /* launch: the engine torque holds the launch speed */
        limit += cal->launch_kp_nm_per_rpm * (s->launch_rpm - s->n_engine);
    double demand = s->pedal / 100.0 * interp(s->n_engine, cal->engine_full_load, cal->engine_full_load_n);
    if (limit >= demand)
        return 0;
    *limit_nm = py_max(limit, cal->asr_min_nm);
    return 1;
}

/* ------------------------------------------------------------------ step */
static void stale_outputs(tcu_state *s)
{
    s->pressure_bar[0] = s->pressure_bar[1] = 0.0;
    s->has_request = 0;
}

static void commands_out(const tcu_cal *cal, tcu_state *s, int stale, double *c)
{
    double dt = cal->period_s;
    double i1, i2, forces[4];
    if (stale) {
        i1 = i2 = 0.0;
        for (int i = 0; i < 2; i++)
            tcu_clutch_reset(&s->loops[i]);
        for (int k = 0; k < 4; k++)
            forces[k] = 0.0;
    } else {
        double fill_s = cal->fill_time_s * interp(s->oil_degc, cal->fill_time_over_temp, cal->fill_time_over_temp_n);
        i1 = tcu_clutch_current(cal, &s->loops[0], s->pressure_bar[0], s->p_meas[0], dt, fill_s);
        i2 = tcu_clutch_current(cal, &s->loops[1], s->pressure_bar[1], s->p_meas[1], dt, fill_s);
        fork_forces(cal, s, forces);
    }
    int has = s->has_request;
    double request = s->torque_request_nm;
    if (!stale) {
        double limit;
        if (traction_limit(cal, s, &limit)) {
            request = !has ? limit : py_min(request, limit);
            has = 1;
        }
    }
    const tcu_diag *d = &s->diag;
    int active = has && !stale && d->torque_ok;
    c[TCU_C_SOLENOID_CURRENT1] = i1;
    c[TCU_C_SOLENOID_CURRENT2] = i2;
    c[TCU_C_LINE_SOLENOID_CURRENT] = cal->line_current_a;
    for (int k = 0; k < 4; k++)
        c[TCU_C_FORK_FORCE1 + k] = forces[k];
    c[TCU_C_ENGINE_TORQUE_REQUEST] = active ? request : 0.0;
    c[TCU_C_TORQUE_REQUEST_ACTIVE] = active ? 1 : 0;
    c[TCU_C_TARGET_GEAR] = s->target_gear;
    c[TCU_C_ACTIVE_FAULTS] = d->active_bits;
    c[TCU_C_FAULT_COUNT] = d->fault_count < TCU_FAULT_COUNT_MAX ? d->fault_count : TCU_FAULT_COUNT_MAX;
    c[TCU_C_LAST_FAULT] = d->last_fault;
    c[TCU_C_INHIBITED_GEARS] = d->inhibited;
    c[TCU_C_LIMP_HOME] = d->limp_home ? 1 : 0;
    c[TCU_C_SHIFT_ACTIVE] = shift_phase(s->phase) ? 1 : 0;
    c[TCU_C_TCU_PHASE] = s->phase;
    c[TCU_C_TCU_STATE] = tcu_diag_state(d, s->phase);
}

void tcu_step_node(const tcu_cal *cal, tcu_state *s, double t_s, const double *sensors,
                   const tcu_msgs *msgs, double *commands)
{
    s->t_s = t_s;
    int stale = 0;
    if (msgs == NULL) {
        tcu_diag_messages(cal, &s->diag, t_s);
        s->line_absent = 0;
    } else {
        stale = tcu_diag_node(cal, &s->diag, t_s, msgs);
        s->line_absent = msgs->line_absent;
    }
    read_sensors(cal, s, sensors);
    if (stale) {
        if (s->phase != TCU_STALE && s->phase != TCU_SAFE)
            s->phase = TCU_STALE;
        stale_outputs(s);
        commands_out(cal, s, 1, commands);
        return;
    }
    tcu_diag_monitor(cal, s);
    if (s->diag.safe_state) {
        s->phase = TCU_SAFE;
        stale_outputs(s);
        commands_out(cal, s, 1, commands);
        return;
    }
    if (s->phase == TCU_STALE)
        recover(cal, s);          /* plant messages back: the gear for the speed, by slip */
    if (s->diag.inhibited && gear_taken(s))
        leave_gear(cal, s);
    switch (s->phase) {
    case TCU_STANDSTILL: standstill(cal, s); break;
    case TCU_LAUNCH: launch(cal, s); break;
    case TCU_DRIVE: drive(cal, s); break;
    case TCU_UPSHIFT_TORQUE: upshift_torque(cal, s); break;
    case TCU_UPSHIFT_INERTIA: upshift_inertia(cal, s); break;
    case TCU_DOWNSHIFT_INERTIA: downshift_inertia(cal, s); break;
    case TCU_DOWNSHIFT_TORQUE: downshift_torque(cal, s); break;
    case TCU_SHIFT_OPEN: shift_open(cal, s); break;
    default: break;               /* stale and safe have no handler (never reached here) */
    }
    commands_out(cal, s, 0, commands);
}

void tcu_step(const tcu_cal *cal, tcu_state *s, double t_s, const double *sensors, double *commands)
{
    tcu_step_node(cal, s, t_s, sensors, NULL, commands);
}

int tcu_gear_layout(int gear, int32_t *shaft, int32_t *sleeve, int32_t *side)
{
    if ((gear < 1 || gear > TCU_TOP_GEAR) && gear != TCU_REVERSE)
        return -1;
    *shaft = TCU_GEAR_SHAFT[tcu_gi(gear)];
    *sleeve = TCU_GEAR_SLEEVE[tcu_gi(gear)];
    *side = TCU_GEAR_SIDE[tcu_gi(gear)];
    return 0;
}
