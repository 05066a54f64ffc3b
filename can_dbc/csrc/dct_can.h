/*
 * dct_can.h - the CAN contract in C, for the real-time path.
 *
 * The truth is can_dbc/dct_hil.dbc. The pack/unpack code under
 * can_dbc/generated/ is generated from it by cantools and never edited by
 * hand; this facade maps DBC signals to the plant's inputs and outputs,
 * and implements the end-to-end protection every message carries:
 *   byte 0           CRC: CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF)
 *                    over the identifier as two bytes (low byte first)
 *                    followed by payload bytes 1 .. len-1
 *   byte 1, bits 0-3 AliveCounter, +1 per frame, wrapping 15 -> 0
 * A received frame is rejected (and counted) when its length is not the
 * DBC's, its CRC is wrong, or its counter repeats or jumps by more than 2.
 *
 * Read by cffi like dct_plant.h: plain structs, integer #defines, prototypes.
 */
#ifndef DCT_CAN_H
#define DCT_CAN_H

#include <stddef.h>
#include <stdint.h>

#include "dct_plant.h"

/* plant -> TCU messages (index into the tx tables) */
#define DCT_TX_SHAFT_SPEEDS 0
#define DCT_TX_OUTPUT_SPEEDS 1
#define DCT_TX_CLUTCH 2
#define DCT_TX_SHIFT 3
#define DCT_TX_VEH_MOTION 4
#define DCT_TX_VEH_DRIVER 5
#define DCT_TX_SIM_STATUS 6
#define DCT_CAN_N_TX 7

/* TCU -> plant messages (index into the rx tables) */
#define DCT_RX_CLUTCH_CMD 0
#define DCT_RX_SHIFT_CMD 1
#define DCT_RX_ENGINE_CMD 2
#define DCT_CAN_N_RX 3

/* result of checking a received frame */
#define DCT_RX_OK 0
#define DCT_RX_UNKNOWN_ID 1
#define DCT_RX_BAD_LENGTH 2
#define DCT_RX_BAD_CRC 3
#define DCT_RX_BAD_COUNTER 4

typedef struct {
    uint32_t id;              /* 11-bit identifier */
    uint8_t len;              /* data length code, 0..8 (classic CAN) */
    uint8_t data[8];
} dct_can_frame;

/* what the TCU commands, in physical units (the DBC's) */
typedef struct {
    double solenoid_current1_a;
    double solenoid_current2_a;
    double line_solenoid_current_a;
    double fork_force_n[4];
    double engine_torque_request_nm;
    double torque_request_active;
    double target_gear;       /* the TCU's target gear (1..6, -1 R, 0 N): recorded, drives no input */
} dct_tcu_commands;

/* the simulator's own status, sent in SIM_Status */
typedef struct {
    double sim_time_s;
    double overrun_count;
    double turnaround_max_us;
    double sim_state;         /* 0 starting, 1 running, 2 stopping, 3 fault */
} dct_sim_status;

/* receive-side end-to-end state of one message */
typedef struct {
    int last_counter;         /* -1 before the first accepted frame */
} dct_e2e_rx;

/* tables from the DBC */
uint32_t dct_can_tx_id(int msg);
int dct_can_tx_cycle_ms(int msg);
int dct_can_tx_length(int msg);
uint32_t dct_can_rx_id(int msg);
int dct_can_rx_cycle_ms(int msg);
int dct_can_rx_length(int msg);
int dct_can_rx_index(uint32_t id);          /* -1 if the id is not a TCU message */

/* end-to-end protection */
uint8_t dct_crc8_j1850(const uint8_t *bytes, size_t n);
uint8_t dct_e2e_crc(uint32_t id, const uint8_t *data, uint8_t len);
void dct_e2e_protect(dct_can_frame *f, uint8_t counter);   /* writes counter, then CRC */
/* checks length, CRC and counter of a frame of rx message msg and
 * updates the counter state only if the frame is accepted */
int dct_e2e_check(int msg, const dct_can_frame *f, dct_e2e_rx *state);

/* packing (values outside a signal's DBC range are limited to it) */
void dct_can_encode_tx(int msg, const dct_outputs *o, const dct_sim_status *st,
                       uint8_t counter, dct_can_frame *f);
/* decodes an accepted frame of rx message msg into the commands */
void dct_can_decode_rx(int msg, const dct_can_frame *f, dct_tcu_commands *cmd);
/* the safe values used while a message is timed out:
 * 0 A, no fork force, no torque request (target gear 0) */
void dct_can_safe_rx(int msg, dct_tcu_commands *cmd);
/* writes the commands into the plant inputs they drive */
void dct_can_apply_commands(const dct_tcu_commands *cmd, dct_inputs *in);

#endif
