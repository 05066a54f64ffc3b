/*
 * dct_can.c - the CAN facade of dct_can.h over the code cantools generates
 * from can_dbc/dct_hil.dbc (can_dbc/generated/dct_hil.{c,h}).
 *
 * Identifiers, lengths and cycle times come from the generated #defines, so
 * the tables are the DBC's. Bit layout and scaling are the generated
 * pack/unpack and encode/decode functions (encode rounds to the nearest raw
 * step). What a DBC cannot say is here:
 *   - the physical range of every transmitted signal, used to limit a value
 *     before it is encoded (NaN is sent as 0, limited to the range); these
 *     limits are the DBC's [minimum|maximum] (tests/test_can_dbc.py checks
 *     that the extremes sent are exactly the DBC's);
 *   - the end-to-end protection (CRC and AliveCounter);
 *   - which plant output feeds which signal, and which command drives which
 *     plant input.
 * Received values are decoded as they are on the wire; the plant limits its
 * inputs to its own ranges.
 *
 * No allocation, no clock, no floating-point exception: every double that
 * is converted to an integer has been limited to its range first.
 */
#include <math.h>
#include <string.h>

#include "dct_can.h"
#include "dct_hil.h"

typedef struct {
    uint32_t id;
    int cycle_ms;
    int length;
} msg_info;

static const msg_info tx_table[DCT_CAN_N_TX] = {
    [DCT_TX_SHAFT_SPEEDS] = {DCT_HIL_DCT_SHAFT_SPEEDS_FRAME_ID, DCT_HIL_DCT_SHAFT_SPEEDS_CYCLE_TIME_MS,
                             DCT_HIL_DCT_SHAFT_SPEEDS_LENGTH},
    [DCT_TX_OUTPUT_SPEEDS] = {DCT_HIL_DCT_OUTPUT_SPEEDS_FRAME_ID, DCT_HIL_DCT_OUTPUT_SPEEDS_CYCLE_TIME_MS,
                              DCT_HIL_DCT_OUTPUT_SPEEDS_LENGTH},
    [DCT_TX_CLUTCH] = {DCT_HIL_DCT_CLUTCH_FRAME_ID, DCT_HIL_DCT_CLUTCH_CYCLE_TIME_MS, DCT_HIL_DCT_CLUTCH_LENGTH},
    [DCT_TX_SHIFT] = {DCT_HIL_DCT_SHIFT_FRAME_ID, DCT_HIL_DCT_SHIFT_CYCLE_TIME_MS, DCT_HIL_DCT_SHIFT_LENGTH},
    [DCT_TX_VEH_MOTION] = {DCT_HIL_VEH_MOTION_FRAME_ID, DCT_HIL_VEH_MOTION_CYCLE_TIME_MS,
                           DCT_HIL_VEH_MOTION_LENGTH},
    [DCT_TX_VEH_DRIVER] = {DCT_HIL_VEH_DRIVER_FRAME_ID, DCT_HIL_VEH_DRIVER_CYCLE_TIME_MS,
                           DCT_HIL_VEH_DRIVER_LENGTH},
    [DCT_TX_SIM_STATUS] = {DCT_HIL_SIM_STATUS_FRAME_ID, DCT_HIL_SIM_STATUS_CYCLE_TIME_MS,
                           DCT_HIL_SIM_STATUS_LENGTH},
};

static const msg_info rx_table[DCT_CAN_N_RX] = {
    [DCT_RX_CLUTCH_CMD] = {DCT_HIL_TCU_CLUTCH_CMD_FRAME_ID, DCT_HIL_TCU_CLUTCH_CMD_CYCLE_TIME_MS,
                           DCT_HIL_TCU_CLUTCH_CMD_LENGTH},
    [DCT_RX_SHIFT_CMD] = {DCT_HIL_TCU_SHIFT_CMD_FRAME_ID, DCT_HIL_TCU_SHIFT_CMD_CYCLE_TIME_MS,
                          DCT_HIL_TCU_SHIFT_CMD_LENGTH},
    [DCT_RX_ENGINE_CMD] = {DCT_HIL_TCU_ENGINE_CMD_FRAME_ID, DCT_HIL_TCU_ENGINE_CMD_CYCLE_TIME_MS,
                           DCT_HIL_TCU_ENGINE_CMD_LENGTH},
};

static int tx_ok(int msg) { return msg >= 0 && msg < DCT_CAN_N_TX; }
static int rx_ok(int msg) { return msg >= 0 && msg < DCT_CAN_N_RX; }

uint32_t dct_can_tx_id(int msg) { return tx_ok(msg) ? tx_table[msg].id : 0u; }
int dct_can_tx_cycle_ms(int msg) { return tx_ok(msg) ? tx_table[msg].cycle_ms : 0; }
int dct_can_tx_length(int msg) { return tx_ok(msg) ? tx_table[msg].length : 0; }
uint32_t dct_can_rx_id(int msg) { return rx_ok(msg) ? rx_table[msg].id : 0u; }
int dct_can_rx_cycle_ms(int msg) { return rx_ok(msg) ? rx_table[msg].cycle_ms : 0; }
int dct_can_rx_length(int msg) { return rx_ok(msg) ? rx_table[msg].length : 0; }

int dct_can_rx_index(uint32_t id)
{
    for (int i = 0; i < DCT_CAN_N_RX; i++) {
        if (rx_table[i].id == id) {
            return i;
        }
    }
    return -1;
}

/* ------------------------------------------------------------------ */
/* End-to-end protection                                               */
/* ------------------------------------------------------------------ */

uint8_t dct_crc8_j1850(const uint8_t *bytes, size_t n)
{
    uint8_t crc = 0xFFu;
    for (size_t i = 0; i < n; i++) {
        crc ^= bytes[i];
        for (int b = 0; b < 8; b++) {
            crc = (crc & 0x80u) ? (uint8_t)((crc << 1) ^ 0x1Du) : (uint8_t)(crc << 1);
        }
    }
    return (uint8_t)(crc ^ 0xFFu);
}

uint8_t dct_e2e_crc(uint32_t id, const uint8_t *data, uint8_t len)
{
    uint8_t buf[2 + 7];
    size_t n = 0;
    buf[n++] = (uint8_t)(id & 0xFFu);
    buf[n++] = (uint8_t)((id >> 8) & 0xFFu);
    if (len > 8u) {
        len = 8u;
    }
    for (uint8_t i = 1; i < len; i++) {
        buf[n++] = data[i];
    }
    return dct_crc8_j1850(buf, n);
}

void dct_e2e_protect(dct_can_frame *f, uint8_t counter)
{
    f->data[1] = (uint8_t)((f->data[1] & 0xF0u) | (counter & 0x0Fu));
    f->data[0] = dct_e2e_crc(f->id, f->data, f->len);
}

int dct_e2e_check(int msg, const dct_can_frame *f, dct_e2e_rx *state)
{
    if (!rx_ok(msg) || f->id != rx_table[msg].id) {
        return DCT_RX_UNKNOWN_ID;
    }
    if ((int)f->len != rx_table[msg].length) {
        return DCT_RX_BAD_LENGTH;
    }
    if (f->data[0] != dct_e2e_crc(f->id, f->data, f->len)) {
        return DCT_RX_BAD_CRC;
    }
    int counter = f->data[1] & 0x0F;
    if (state != NULL) {
        if (state->last_counter >= 0) {
            int step = (counter - state->last_counter) & 0x0F;
            if (step == 0 || step > 2) {
                return DCT_RX_BAD_COUNTER;
            }
        }
        state->last_counter = counter;
    }
    return DCT_RX_OK;
}

/* ------------------------------------------------------------------ */
/* Plant outputs -> plant messages                                     */
/* ------------------------------------------------------------------ */

/* v limited to [lo, hi]; NaN counts as 0 (quiet test first: no FE_INVALID) */
static double lim(double v, double lo, double hi)
{
    if (isnan(v)) {
        v = 0.0;
    }
    if (v < lo) {
        return lo;
    }
    if (v > hi) {
        return hi;
    }
    return v;
}

/* physical ranges of the transmitted signals, as in the DBC */
#define SPEED_MIN_RPM (-16383.5)
#define SPEED_MAX_RPM 16383.5
#define PRESSURE_MAX_BAR 65.535
#define FORK_POSITION_MAX_MM 12.7
#define SYNC_STATE_MAX 2.0
#define VEHICLE_SPEED_MAX_KMH 327.67
#define ACCEL_MAX_MPS2 32.767
#define GRADE_MAX_PCT 327.67
#define PEDAL_MAX_PCT 100.0
#define TORQUE_MAX_NM 3276.7
#define SIM_TIME_MAX_S 167772.15
#define OVERRUN_COUNT_MAX 4095.0
#define TURNAROUND_MAX_US 2046.0
#define SIM_STATE_MAX 3.0

/* m.sig = encoded value of v limited to [lo, hi] (generated function of message pre) */
#define ENC(pre, sig, v, lo, hi) (m.sig = dct_hil_##pre##_##sig##_encode(lim((v), (lo), (hi))))

void dct_can_encode_tx(int msg, const dct_outputs *o, const dct_sim_status *st,
                       uint8_t counter, dct_can_frame *f)
{
    static const dct_outputs no_outputs;
    static const dct_sim_status no_status;
    if (o == NULL) {
        o = &no_outputs;
    }
    if (st == NULL) {
        st = &no_status;
    }
    memset(f, 0, sizeof *f);
    if (!tx_ok(msg)) {
        return;                       /* id 0, length 0 */
    }
    f->id = tx_table[msg].id;
    f->len = (uint8_t)tx_table[msg].length;

    switch (msg) {
    case DCT_TX_SHAFT_SPEEDS: {
        struct dct_hil_dct_shaft_speeds_t m;
        dct_hil_dct_shaft_speeds_init(&m);
        ENC(dct_shaft_speeds, engine_speed, o->engine_speed_rpm, SPEED_MIN_RPM, SPEED_MAX_RPM);
        ENC(dct_shaft_speeds, input_shaft1_speed, o->input_shaft1_speed_rpm, SPEED_MIN_RPM, SPEED_MAX_RPM);
        ENC(dct_shaft_speeds, input_shaft2_speed, o->input_shaft2_speed_rpm, SPEED_MIN_RPM, SPEED_MAX_RPM);
        (void)dct_hil_dct_shaft_speeds_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_OUTPUT_SPEEDS: {
        struct dct_hil_dct_output_speeds_t m;
        dct_hil_dct_output_speeds_init(&m);
        ENC(dct_output_speeds, output_shaft1_speed, o->output_shaft1_speed_rpm, SPEED_MIN_RPM, SPEED_MAX_RPM);
        ENC(dct_output_speeds, output_shaft2_speed, o->output_shaft2_speed_rpm, SPEED_MIN_RPM, SPEED_MAX_RPM);
        (void)dct_hil_dct_output_speeds_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_CLUTCH: {
        struct dct_hil_dct_clutch_t m;
        dct_hil_dct_clutch_init(&m);
        ENC(dct_clutch, clutch_pressure1, o->clutch1_pressure_bar, 0.0, PRESSURE_MAX_BAR);
        ENC(dct_clutch, clutch_pressure2, o->clutch2_pressure_bar, 0.0, PRESSURE_MAX_BAR);
        ENC(dct_clutch, line_pressure, o->line_pressure_bar, 0.0, PRESSURE_MAX_BAR);
        (void)dct_hil_dct_clutch_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_SHIFT: {
        struct dct_hil_dct_shift_t m;
        dct_hil_dct_shift_init(&m);
        ENC(dct_shift, fork_position1, o->fork1_position_mm, -FORK_POSITION_MAX_MM, FORK_POSITION_MAX_MM);
        ENC(dct_shift, fork_position2, o->fork2_position_mm, -FORK_POSITION_MAX_MM, FORK_POSITION_MAX_MM);
        ENC(dct_shift, fork_position3, o->fork3_position_mm, -FORK_POSITION_MAX_MM, FORK_POSITION_MAX_MM);
        ENC(dct_shift, fork_position4, o->fork4_position_mm, -FORK_POSITION_MAX_MM, FORK_POSITION_MAX_MM);
        ENC(dct_shift, sync_state1, o->sync1_state, 0.0, SYNC_STATE_MAX);
        ENC(dct_shift, sync_state2, o->sync2_state, 0.0, SYNC_STATE_MAX);
        ENC(dct_shift, sync_state3, o->sync3_state, 0.0, SYNC_STATE_MAX);
        ENC(dct_shift, sync_state4, o->sync4_state, 0.0, SYNC_STATE_MAX);
        (void)dct_hil_dct_shift_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_VEH_MOTION: {
        struct dct_hil_veh_motion_t m;
        dct_hil_veh_motion_init(&m);
        ENC(veh_motion, vehicle_speed, o->vehicle_speed_kmh, -VEHICLE_SPEED_MAX_KMH, VEHICLE_SPEED_MAX_KMH);
        ENC(veh_motion, long_accel, o->vehicle_accel_mps2, -ACCEL_MAX_MPS2, ACCEL_MAX_MPS2);
        ENC(veh_motion, road_grade, o->road_grade_pct, -GRADE_MAX_PCT, GRADE_MAX_PCT);
        (void)dct_hil_veh_motion_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_VEH_DRIVER: {
        struct dct_hil_veh_driver_t m;
        dct_hil_veh_driver_init(&m);
        ENC(veh_driver, accel_pedal, o->accel_pedal_pct, 0.0, PEDAL_MAX_PCT);
        ENC(veh_driver, brake_pedal, o->brake_pedal_pct, 0.0, PEDAL_MAX_PCT);
        ENC(veh_driver, engine_torque, o->engine_torque_nm, -TORQUE_MAX_NM, TORQUE_MAX_NM);
        (void)dct_hil_veh_driver_pack(f->data, &m, sizeof f->data);
        break;
    }
    case DCT_TX_SIM_STATUS: {
        struct dct_hil_sim_status_t m;
        dct_hil_sim_status_init(&m);
        ENC(sim_status, sim_time, st->sim_time_s, 0.0, SIM_TIME_MAX_S);
        ENC(sim_status, overrun_count, st->overrun_count, 0.0, OVERRUN_COUNT_MAX);
        ENC(sim_status, turnaround_max, st->turnaround_max_us, 0.0, TURNAROUND_MAX_US);
        ENC(sim_status, sim_state, st->sim_state, 0.0, SIM_STATE_MAX);
        (void)dct_hil_sim_status_pack(f->data, &m, sizeof f->data);
        break;
    }
    default:
        break;
    }
    dct_e2e_protect(f, counter);
}

/* ------------------------------------------------------------------ */
/* TCU messages -> commands -> plant inputs                            */
/* ------------------------------------------------------------------ */

#define DEC(pre, sig) dct_hil_##pre##_##sig##_decode(m.sig)

void dct_can_decode_rx(int msg, const dct_can_frame *f, dct_tcu_commands *cmd)
{
    switch (msg) {
    case DCT_RX_CLUTCH_CMD: {
        struct dct_hil_tcu_clutch_cmd_t m;
        if (dct_hil_tcu_clutch_cmd_unpack(&m, f->data, f->len) < 0) {
            return;
        }
        cmd->solenoid_current1_a = DEC(tcu_clutch_cmd, solenoid_current1);
        cmd->solenoid_current2_a = DEC(tcu_clutch_cmd, solenoid_current2);
        cmd->line_solenoid_current_a = DEC(tcu_clutch_cmd, line_solenoid_current);
        break;
    }
    case DCT_RX_SHIFT_CMD: {
        struct dct_hil_tcu_shift_cmd_t m;
        if (dct_hil_tcu_shift_cmd_unpack(&m, f->data, f->len) < 0) {
            return;
        }
        cmd->fork_force_n[0] = DEC(tcu_shift_cmd, fork_force1);
        cmd->fork_force_n[1] = DEC(tcu_shift_cmd, fork_force2);
        cmd->fork_force_n[2] = DEC(tcu_shift_cmd, fork_force3);
        cmd->fork_force_n[3] = DEC(tcu_shift_cmd, fork_force4);
        break;
    }
    case DCT_RX_ENGINE_CMD: {
        struct dct_hil_tcu_engine_cmd_t m;
        if (dct_hil_tcu_engine_cmd_unpack(&m, f->data, f->len) < 0) {
            return;
        }
        cmd->engine_torque_request_nm = DEC(tcu_engine_cmd, engine_torque_request);
        cmd->torque_request_active = DEC(tcu_engine_cmd, torque_request_active);
        cmd->target_gear = DEC(tcu_engine_cmd, target_gear);
        break;
    }
    default:
        break;
    }
}

void dct_can_safe_rx(int msg, dct_tcu_commands *cmd)
{
    switch (msg) {
    case DCT_RX_CLUTCH_CMD:
        cmd->solenoid_current1_a = 0.0;
        cmd->solenoid_current2_a = 0.0;
        cmd->line_solenoid_current_a = 0.0;
        break;
    case DCT_RX_SHIFT_CMD:
        for (int i = 0; i < 4; i++) {
            cmd->fork_force_n[i] = 0.0;
        }
        break;
    case DCT_RX_ENGINE_CMD:
        cmd->engine_torque_request_nm = 0.0;
        cmd->torque_request_active = 0.0;
        cmd->target_gear = 0.0;
        break;
    default:
        break;
    }
}

void dct_can_apply_commands(const dct_tcu_commands *cmd, dct_inputs *in)
{
    in->solenoid_current1_a = cmd->solenoid_current1_a;
    in->solenoid_current2_a = cmd->solenoid_current2_a;
    in->line_solenoid_current_a = cmd->line_solenoid_current_a;
    in->fork_force1_n = cmd->fork_force_n[0];
    in->fork_force2_n = cmd->fork_force_n[1];
    in->fork_force3_n = cmd->fork_force_n[2];
    in->fork_force4_n = cmd->fork_force_n[3];
    in->engine_torque_request_nm = cmd->engine_torque_request_nm;
    in->torque_request_active = cmd->torque_request_active;
    /* target_gear drives no input: the plant does not act on it */
}
