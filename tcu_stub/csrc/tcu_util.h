/*
 * tcu_util.h - Python's arithmetic where C's differs, for the TCU port.
 *
 * Python's min(a, b) returns a unless b < a, max(a, b) a unless b > a; C's
 * fmin/fmax may pick either zero of -0.0 and 0.0 and treat NaN otherwise.
 * The port uses these so every value matches logic.py's to the bit.
 */
#ifndef TCU_UTIL_H
#define TCU_UTIL_H

#include <math.h>

static inline double py_min(double a, double b) { return b < a ? b : a; }
static inline double py_max(double a, double b) { return b > a ? b : a; }
/* math.pi */
#define TCU_PI 3.141592653589793

/* logic.GEAR_LAYOUT: gear (index 1..6, R at 7: tcu_gi) -> input shaft 0/1, sleeve 0..3, side +1/-1 */
#define TCU_REVERSE (-1)
static inline int tcu_gi(int gear) { return gear < 0 ? 7 : gear; }
static const int TCU_GEAR_SHAFT[8] = {0, 0, 1, 0, 1, 0, 1, 0};
static const int TCU_GEAR_SLEEVE[8] = {0, 0, 1, 0, 1, 2, 3, 2};
static const int TCU_GEAR_SIDE[8] = {0, 1, 1, -1, -1, 1, 1, -1};
/* logic.SHAFT_SLEEVES, logic._SHAFT_SLEEVE_SIDES' gears (0: none), logic._SLEEVE_SHAFT */
static const int TCU_SHAFT_SLEEVES[2][2] = {{0, 2}, {1, 3}};
static const int TCU_SHAFT_GEARS[2][4] = {{1, 3, 5, TCU_REVERSE}, {2, 4, 6, 0}};
/* logic.SELECTOR_* (VEH_Driver.SelectorLever) */
#define TCU_SELECTOR_P 0
#define TCU_SELECTOR_R 1
#define TCU_SELECTOR_N 2
#define TCU_SELECTOR_D 3
static const int TCU_SLEEVE_SHAFT[4] = {0, 1, 0, 1};
#define TCU_SYNC_ENGAGED 2
#define TCU_TOP_GEAR 6
#define TCU_FAULT_COUNT_MAX 255
/* diagnostics.DTC_* bits */
#define TCU_DTC_INPUT_SPEED1 0
#define TCU_DTC_CLUTCH1_PRESSURE 2
#define TCU_DTC_LINE_PRESSURE 4
#define TCU_DTC_CLUTCH1_SLIP 5
#define TCU_DTC_GEAR_ENGAGEMENT 7
#define TCU_DTC_ENGINE_MESSAGE 8
#define TCU_DTC_CAN_CRC 9
#define TCU_DTC_CAN_COUNTER 10
#define TCU_DTC_CAN_LENGTH 11
#define TCU_DTC_CAN_TIMEOUT 12

#endif
