/*
 * tcu_clutch.c - clutch pressure loop and clutch model of the reference TCU
 * (logic.ClutchLoop, TcuLogic.torque_to_bar).
 */
#include "tcu_fast.h"
#include "tcu_util.h"

void tcu_clutch_reset(tcu_clutch_loop *loop)
{
    loop->integral_a = 0.0;
    loop->fill_left_s = 0.0;
    loop->target_bar = 0.0;
}

/* target pressure -> solenoid current: valve feed-forward + PI on the measured
   pressure; a fill pulse first when the clutch was open and its chamber empty */
double tcu_clutch_current(const tcu_cal *cal, tcu_clutch_loop *loop, double target_bar,
                          double measured_bar, double dt, double fill_time_s)
{
    target_bar = py_min(py_max(target_bar, 0.0), cal->clutch_max_bar);
    int was_open = loop->target_bar <= 0.0;
    loop->target_bar = target_bar;
    if (target_bar <= 0.0) {
        loop->integral_a = 0.0;
        loop->fill_left_s = 0.0;
        return 0.0;
    }
    if (was_open && measured_bar < cal->empty_bar)
        loop->fill_left_s = fill_time_s;
    if (loop->fill_left_s > 0.0) {
        loop->fill_left_s -= dt;
        return cal->fill_current_a;
    }
    double feed = (target_bar * 1e5 * cal->valve_feedback_area_m2 + cal->valve_spring_n) /
                  cal->valve_gain_n_per_a;
    double err = target_bar - measured_bar;
    loop->integral_a = py_min(py_max(loop->integral_a + cal->pressure_ki_a_per_bar_s * err * dt,
                                     -cal->pressure_i_limit_a),
                              cal->pressure_i_limit_a);
    return py_min(py_max(feed + cal->pressure_kp_a_per_bar * err + loop->integral_a, 0.0),
                  cal->valve_max_a);
}

/* TcuLogic.torque_to_bar: pressure for a clutch capacity with the adapted kiss point and the
   gain at the oil temperature, bar */
double tcu_torque_to_bar(const tcu_cal *cal, const tcu_state *s, int clutch, double torque_nm)
{
    if (torque_nm <= 0.0)
        return s->kiss_bar[clutch];
    return s->kiss_bar[clutch] + torque_nm / tcu_nm_per_bar(cal, s, clutch);
}
