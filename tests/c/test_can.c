/*
 * test_can.c - the CAN facade (can_dbc/csrc/dct_can.c over the code
 * generated from the DBC) without Python: CRC, end-to-end protection and
 * check, counter rules, encode/decode of every TCU message, limits of the
 * plant messages (built by `make -C plant/csrc test` under the sanitizers).
 */
#include <fenv.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "dct_can.h"
#include "dct_hil.h"

#include "check.h"

static void test_crc(void)
{
    const uint8_t check[] = {'1', '2', '3', '4', '5', '6', '7', '8', '9'};
    CHECK(dct_crc8_j1850(check, sizeof check) == 0x4B, "check value 0x%02X", dct_crc8_j1850(check, sizeof check));
    CHECK(dct_crc8_j1850(check, 0) == 0x00, "empty: init 0xFF xor 0xFF");

    /* the frame CRC covers id low, id high, data[1..len-1]; never data[0] */
    uint8_t data[8] = {0xAA, 1, 2, 3, 4, 5, 6, 7};
    uint8_t ref[9] = {0x80, 0x00, 1, 2, 3, 4, 5, 6, 7};
    CHECK(dct_e2e_crc(0x080, data, 8) == dct_crc8_j1850(ref, 9), "frame crc");
    data[0] = 0x55;
    CHECK(dct_e2e_crc(0x080, data, 8) == dct_crc8_j1850(ref, 9), "byte 0 not covered");
    uint8_t ref_hi[9] = {0xF0, 0x01, 1, 2, 3, 4, 5, 6, 7};
    CHECK(dct_e2e_crc(0x1F0, data, 8) == dct_crc8_j1850(ref_hi, 9), "id high byte covered");
    for (int i = 1; i < 8; i++) {
        uint8_t d2[8];
        memcpy(d2, data, 8);
        d2[i] ^= 0x10;
        CHECK(dct_e2e_crc(0x080, d2, 8) != dct_e2e_crc(0x080, data, 8), "byte %d covered", i);
    }
}

static dct_can_frame rx_frame(int msg, uint8_t counter)
{
    dct_can_frame f;
    memset(&f, 0, sizeof f);
    f.id = dct_can_rx_id(msg);
    f.len = (uint8_t)dct_can_rx_length(msg);
    f.data[1] = 0xA0;                 /* the free high nibble must survive */
    dct_e2e_protect(&f, counter);
    return f;
}

static void test_protect_check(void)
{
    dct_e2e_rx st = {-1};
    dct_can_frame f = rx_frame(DCT_RX_CLUTCH_CMD, 7);
    CHECK((f.data[1] & 0x0F) == 7 && (f.data[1] & 0xF0) == 0xA0, "counter nibble 0x%02X", f.data[1]);
    CHECK(f.data[0] == dct_e2e_crc(f.id, f.data, f.len), "crc written");
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &f, &st) == DCT_RX_OK && st.last_counter == 7, "accepted");

    /* wrong length, wrong CRC, wrong id: rejected, state unchanged */
    dct_can_frame g = rx_frame(DCT_RX_CLUTCH_CMD, 8);
    g.len = 7;
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &g, &st) == DCT_RX_BAD_LENGTH, "length");
    g = rx_frame(DCT_RX_CLUTCH_CMD, 8);
    g.data[0] ^= 1;
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &g, &st) == DCT_RX_BAD_CRC, "crc");
    g = rx_frame(DCT_RX_CLUTCH_CMD, 8);
    g.data[5] ^= 0x40;
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &g, &st) == DCT_RX_BAD_CRC, "payload corrupted");
    g = rx_frame(DCT_RX_SHIFT_CMD, 8);
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &g, &st) == DCT_RX_UNKNOWN_ID, "other id");
    CHECK(dct_e2e_check(DCT_CAN_N_RX, &f, &st) == DCT_RX_UNKNOWN_ID, "bad index");
    CHECK(st.last_counter == 7, "rejects leave the state");
}

static void test_counter_rules(void)
{
    dct_e2e_rx st = {-1};
    dct_can_frame f = rx_frame(DCT_RX_ENGINE_CMD, 13);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK, "first frame, any counter");
    f = rx_frame(DCT_RX_ENGINE_CMD, 13);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_BAD_COUNTER, "repeat");
    f = rx_frame(DCT_RX_ENGINE_CMD, 0);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_BAD_COUNTER, "jump by 3 (13 -> 0)");
    f = rx_frame(DCT_RX_ENGINE_CMD, 14);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK, "jump by 1");
    f = rx_frame(DCT_RX_ENGINE_CMD, 15);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK, "jump by 1");
    f = rx_frame(DCT_RX_ENGINE_CMD, 0);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK, "wrap 15 -> 0");
    f = rx_frame(DCT_RX_ENGINE_CMD, 2);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK, "jump by 2 (one lost)");
    f = rx_frame(DCT_RX_ENGINE_CMD, 1);
    CHECK(dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_BAD_COUNTER, "backwards");
    CHECK(st.last_counter == 2, "state %d", st.last_counter);
    /* a full wrap at +1 is accepted throughout */
    int ok = 1;
    for (int i = 0; i < 40; i++) {
        f = rx_frame(DCT_RX_ENGINE_CMD, (uint8_t)((3 + i) & 0x0F));
        ok &= dct_e2e_check(DCT_RX_ENGINE_CMD, &f, &st) == DCT_RX_OK;
    }
    CHECK(ok, "40 frames in sequence");
}

static void test_tables(void)
{
    CHECK(dct_can_rx_id(DCT_RX_CLUTCH_CMD) == 0x080 && dct_can_rx_id(DCT_RX_SHIFT_CMD) == 0x090 &&
          dct_can_rx_id(DCT_RX_ENGINE_CMD) == 0x091, "rx ids");
    CHECK(dct_can_tx_id(DCT_TX_SHAFT_SPEEDS) == 0x100 && dct_can_tx_id(DCT_TX_SIM_STATUS) == 0x1F0, "tx ids");
    CHECK(dct_can_rx_index(0x091) == DCT_RX_ENGINE_CMD && dct_can_rx_index(0x100) == -1 &&
          dct_can_rx_index(0x7FF) == -1, "rx index");
    for (int i = 0; i < DCT_CAN_N_TX; i++) {
        CHECK(dct_can_tx_length(i) == 8 && dct_can_tx_cycle_ms(i) > 0, "tx %d", i);
    }
    CHECK(dct_can_tx_id(-1) == 0 && dct_can_tx_length(DCT_CAN_N_TX) == 0 && dct_can_rx_cycle_ms(9) == 0,
          "out of range indices");
}

/* one frame of each TCU message, built with the generated packers */
static void test_decode_rx(void)
{
    dct_tcu_commands cmd;
    memset(&cmd, 0, sizeof cmd);
    dct_can_frame f;

    struct dct_hil_tcu_clutch_cmd_t c = {0};
    c.solenoid_current1 = dct_hil_tcu_clutch_cmd_solenoid_current1_encode(0.6);
    c.solenoid_current2 = dct_hil_tcu_clutch_cmd_solenoid_current2_encode(0.1234);
    c.line_solenoid_current = dct_hil_tcu_clutch_cmd_line_solenoid_current_encode(0.95);
    f.id = 0x080;
    f.len = 8;
    dct_hil_tcu_clutch_cmd_pack(f.data, &c, 8);
    dct_e2e_protect(&f, 1);
    dct_e2e_rx st = {-1};
    CHECK(dct_e2e_check(DCT_RX_CLUTCH_CMD, &f, &st) == DCT_RX_OK, "clutch frame accepted");
    dct_can_decode_rx(DCT_RX_CLUTCH_CMD, &f, &cmd);
    CHECK(fabs(cmd.solenoid_current1_a - 0.6) < 1e-9 && fabs(cmd.solenoid_current2_a - 0.1234) < 1e-9 &&
          fabs(cmd.line_solenoid_current_a - 0.95) < 1e-9, "currents %g %g %g", cmd.solenoid_current1_a,
          cmd.solenoid_current2_a, cmd.line_solenoid_current_a);

    struct dct_hil_tcu_shift_cmd_t s = {0};
    s.fork_force1 = 800;
    s.fork_force2 = -1500;
    s.fork_force3 = -2047;
    s.fork_force4 = 2047;
    f.id = 0x090;
    dct_hil_tcu_shift_cmd_pack(f.data, &s, 8);
    dct_e2e_protect(&f, 2);
    dct_can_decode_rx(DCT_RX_SHIFT_CMD, &f, &cmd);
    CHECK(cmd.fork_force_n[0] == 800 && cmd.fork_force_n[1] == -1500 && cmd.fork_force_n[2] == -2047 &&
          cmd.fork_force_n[3] == 2047, "forks %g %g %g %g", cmd.fork_force_n[0], cmd.fork_force_n[1],
          cmd.fork_force_n[2], cmd.fork_force_n[3]);

    struct dct_hil_tcu_engine_cmd_t e = {0};
    e.engine_torque_request = dct_hil_tcu_engine_cmd_engine_torque_request_encode(-55.3);
    e.torque_request_active = 1;
    f.id = 0x091;
    dct_hil_tcu_engine_cmd_pack(f.data, &e, 8);
    dct_e2e_protect(&f, 3);
    dct_can_decode_rx(DCT_RX_ENGINE_CMD, &f, &cmd);
    CHECK(fabs(cmd.engine_torque_request_nm + 55.3) < 1e-9 && cmd.torque_request_active == 1.0, "engine %g %g",
          cmd.engine_torque_request_nm, cmd.torque_request_active);

    /* into the plant inputs */
    dct_inputs in;
    memset(&in, 0, sizeof in);
    in.accel_pedal_pct = 33.0;
    dct_can_apply_commands(&cmd, &in);
    CHECK(fabs(in.solenoid_current1_a - 0.6) < 1e-9 && in.fork_force2_n == -1500 && in.fork_force4_n == 2047 &&
          fabs(in.engine_torque_request_nm + 55.3) < 1e-9 && in.torque_request_active == 1.0 &&
          in.accel_pedal_pct == 33.0, "applied");

    /* safe values, message by message */
    dct_can_safe_rx(DCT_RX_SHIFT_CMD, &cmd);
    CHECK(cmd.fork_force_n[0] == 0 && cmd.fork_force_n[3] == 0 && cmd.solenoid_current1_a > 0.5 &&
          cmd.torque_request_active == 1.0, "safe shift only");
    dct_can_safe_rx(DCT_RX_CLUTCH_CMD, &cmd);
    dct_can_safe_rx(DCT_RX_ENGINE_CMD, &cmd);
    CHECK(cmd.solenoid_current1_a == 0 && cmd.solenoid_current2_a == 0 && cmd.line_solenoid_current_a == 0 &&
          cmd.engine_torque_request_nm == 0 && cmd.torque_request_active == 0, "safe all");

    /* a short frame leaves the commands alone */
    cmd.fork_force_n[0] = 123.0;
    f.id = 0x090;
    f.len = 4;
    dct_can_decode_rx(DCT_RX_SHIFT_CMD, &f, &cmd);
    CHECK(cmd.fork_force_n[0] == 123.0, "short frame ignored");
}

static void test_encode_tx(void)
{
    dct_outputs o;
    memset(&o, 0, sizeof o);
    o.engine_speed_rpm = 2345.6;
    o.input_shaft1_speed_rpm = 1e9;          /* limited to the DBC maximum */
    o.input_shaft2_speed_rpm = -INFINITY;    /* and minimum */
    o.clutch1_pressure_bar = 12.3456;
    o.clutch2_pressure_bar = -3.0;
    o.line_pressure_bar = NAN;               /* sent as 0 */
    o.fork1_position_mm = -8.5;
    o.sync1_state = 2;
    o.sync4_state = 7;
    dct_sim_status st = {12.34, 99999.0, 41.0, 1.0};
    dct_can_frame f;
    struct dct_hil_dct_shaft_speeds_t ss;
    struct dct_hil_dct_clutch_t cl;
    struct dct_hil_dct_shift_t sh;
    struct dct_hil_sim_status_t ss2;

    dct_can_encode_tx(DCT_TX_SHAFT_SPEEDS, &o, &st, 9, &f);
    CHECK(f.id == 0x100 && f.len == 8 && (f.data[1] & 0x0F) == 9 && f.data[0] == dct_e2e_crc(f.id, f.data, f.len),
          "shaft speeds header");
    dct_hil_dct_shaft_speeds_unpack(&ss, f.data, f.len);
    CHECK(fabs(dct_hil_dct_shaft_speeds_engine_speed_decode(ss.engine_speed) - 2345.5) < 1e-9, "engine speed");
    CHECK(dct_hil_dct_shaft_speeds_input_shaft1_speed_decode(ss.input_shaft1_speed) == 16383.5 &&
          dct_hil_dct_shaft_speeds_input_shaft2_speed_decode(ss.input_shaft2_speed) == -16383.5, "speed limits");

    dct_can_encode_tx(DCT_TX_CLUTCH, &o, &st, 0, &f);
    dct_hil_dct_clutch_unpack(&cl, f.data, f.len);
    CHECK(cl.clutch_pressure1 == 12346 && cl.clutch_pressure2 == 0 && cl.line_pressure == 0, "pressures %u %u %u",
          cl.clutch_pressure1, cl.clutch_pressure2, cl.line_pressure);

    dct_can_encode_tx(DCT_TX_SHIFT, &o, &st, 0, &f);
    dct_hil_dct_shift_unpack(&sh, f.data, f.len);
    CHECK(sh.fork_position1 == -85 && sh.sync_state1 == 2 && sh.sync_state4 == 2, "shift %d %u %u",
          sh.fork_position1, sh.sync_state1, sh.sync_state4);

    dct_can_encode_tx(DCT_TX_SIM_STATUS, &o, &st, 0, &f);
    dct_hil_sim_status_unpack(&ss2, f.data, f.len);
    CHECK(ss2.sim_time == 1234 && ss2.overrun_count == 4095 && ss2.turnaround_max == 21 && ss2.sim_state == 1,
          "status %u %u %u %u", ss2.sim_time, ss2.overrun_count, ss2.turnaround_max, ss2.sim_state);

    /* NaN and infinities everywhere: limited before any conversion, so no
     * invalid-operation or overflow exception is raised */
    dct_outputs bad;
    double *raw = (double *)&bad;
    for (size_t k = 0; k < sizeof bad / sizeof(double); k++) {
        raw[k] = (k % 3 == 0) ? NAN : (k % 3 == 1) ? INFINITY : -INFINITY;
    }
    dct_sim_status bad_st = {NAN, INFINITY, -INFINITY, NAN};
    feclearexcept(FE_ALL_EXCEPT);
    for (int i = 0; i < DCT_CAN_N_TX; i++) {
        dct_can_encode_tx(i, &bad, &bad_st, 0, &f);
    }
    CHECK(!fetestexcept(FE_INVALID | FE_OVERFLOW | FE_DIVBYZERO), "floating-point exception raised");

    for (int i = 0; i < DCT_CAN_N_TX; i++) {
        dct_can_encode_tx(i, &o, &st, (uint8_t)i, &f);
        CHECK(f.id == dct_can_tx_id(i) && f.len == dct_can_tx_length(i) && (f.data[1] & 0x0F) == i &&
              f.data[0] == dct_e2e_crc(f.id, f.data, f.len), "tx %d protected", i);
    }
    dct_can_encode_tx(DCT_CAN_N_TX, &o, &st, 0, &f);
    CHECK(f.id == 0 && f.len == 0, "bad index gives an empty frame");
}

int main(void)
{
    test_crc();
    test_protect_check();
    test_counter_rules();
    test_tables();
    test_decode_rx();
    test_encode_tx();
    printf("%d passed, %d failed\n", checks - failures, failures);
    return failures ? 1 : 0;
}
