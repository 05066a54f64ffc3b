/*
 * tcu_driver.c - the drivers of plant/driver.py: ScriptedDriver (a pedal
 * table, step-wise or linear, with an optional selector lever column held
 * from its row on) and SpeedTrackingDriver (PI on the speed error
 * with feed-forward), called every 10 ms with the plant outputs.
 *
 * numpy.interp is ported with its arithmetic (numpy's compiled_base.c), so
 * the pedals are the Python drivers' to the bit; the trace acceleration
 * (numpy.gradient) comes from the Python driver itself.
 */
#include "tcu_fast.h"
#include "tcu_util.h"

double tcu_np_interp(double x, const double *xp, const double *fp, int n)
{
    if (isnan(x))
        return x;
    if (n == 1)
        return fp[0];             /* numpy's left and right values are fp[0] too */
    if (x < xp[0])
        return fp[0];
    if (x > xp[n - 1])
        return fp[n - 1];
    if (x == xp[n - 1])
        return fp[n - 1];
    /* xp[j] <= x < xp[j + 1] */
    int lo = 0, hi = n - 1;
    while (hi - lo > 1) {
        int mid = lo + (hi - lo) / 2;
        if (x < xp[mid])
            hi = mid;
        else
            lo = mid;
    }
    int j = lo;
    if (xp[j] == x)
        return fp[j];
    double slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]);
    double y = slope * (x - xp[j]) + fp[j];
    if (isnan(y)) {               /* numpy: try the other end */
        y = slope * (x - xp[j + 1]) + fp[j + 1];
        if (isnan(y) && fp[j] == fp[j + 1])
            y = fp[j];
    }
    return y;
}

/* ScriptedDriver._row: the last row at or before t (the first row before it) */
static int scripted_row(const tcu_driver *d, double t)
{
    int k = 0;
    for (int i = 0; i < d->n; i++)           /* searchsorted(side="right") - 1 */
        if (d->t_s[i] <= t)
            k = i;
        else
            break;
    return k;
}

/* ScriptedDriver "step" */
static void scripted_step(const tcu_driver *d, double t, double *accel, double *brake)
{
    int k = scripted_row(d, t);
    *accel = d->a[k];
    *brake = d->b[k];
}

double tcu_driver_selector(const tcu_driver *d, double t_s)
{
    if ((d->kind != TCU_DRIVER_STEP && d->kind != TCU_DRIVER_LINEAR) || d->sel == NULL)
        return -1.0;
    return d->sel[scripted_row(d, t_s)];
}

/* CarData.resistance_n: rolling and air resistance on a level road */
static double resistance_n(const tcu_driver *d, double speed_mps)
{
    double roll = speed_mps > 0.05 ? d->rolling_resistance * d->mass_kg * d->g_mps2 : 0.0;
    return roll + 0.5 * d->air_density_kg_m3 * d->drag_area_m2 * speed_mps * speed_mps;
}

/* SpeedTrackingDriver.__call__ */
static void speed_tracking(tcu_driver *d, double t, const dct_outputs *out, double *accel_pct,
                           double *brake_pct)
{
    double dt = !d->has_t_last ? 0.0 : py_max(0.0, t - d->t_last);
    d->t_last = t;
    d->has_t_last = 1;
    double v_kmh = out->vehicle_speed_kmh;
    double v_mps = v_kmh / 3.6;
    double ref_now = tcu_np_interp(t, d->t_s, d->a, d->n);
    double t_ahead = t + d->lookahead_s;
    double ref_ahead = tcu_np_interp(t_ahead, d->t_s, d->a, d->n);
    double a_ref = tcu_np_interp(t_ahead, d->t_s, d->b, d->n);
    double err = ref_now - v_kmh;

    /* standing still on a stopped trace: hold the brake, forget the integral */
    if (ref_now < 0.1 && ref_ahead < 0.1 && v_kmh < 2.0) {
        d->integral = 0.0;
        *accel_pct = 0.0;
        *brake_pct = d->hold_brake_pct;
        return;
    }
    double force_ff = d->rotating_mass_factor * d->mass_kg * a_ref +
                      resistance_n(d, py_max(ref_ahead, 0.0) / 3.6);
    double force = force_ff + d->kp * err + d->ki * d->integral;

    /* present overall ratio and engine torque range */
    double wheel_rad_s = v_mps / d->wheel_radius_m;
    double engine_rpm = out->engine_speed_rpm;
    double ratio = wheel_rad_s > 0.5 ? engine_rpm * TCU_PI / 30.0 / wheel_rad_s : d->launch_ratio;
    if (!(2.0 <= ratio && ratio <= 1.5 * d->launch_ratio))
        ratio = d->launch_ratio;
    double rpm = py_max(engine_rpm, 1500.0);
    double full_nm = tcu_np_interp(rpm, d->full_load_rpm, d->full_load_nm, d->n_full);
    double drag_nm = tcu_np_interp(rpm, d->drag_rpm, d->drag_nm, d->n_drag);
    double k = ratio * d->driveline_efficiency / d->wheel_radius_m;
    double force_drag = drag_nm * k;
    double force_full = full_nm * k;
    double brake_force_max = d->brake_torque_max_nm / d->wheel_radius_m;

    double accel = 0.0, brake = 0.0;
    if (force >= 0.0)
        accel = 100.0 * (force - force_drag) / py_max(force_full - force_drag, 1.0);
    else if (force > force_drag)
        accel = 100.0 * (force - force_drag) / py_max(force_full - force_drag, 1.0);
    else
        brake = 100.0 * (force_drag - force) / brake_force_max;
    int saturated_up = accel >= 100.0 && err > 0;
    int saturated_down = brake >= 100.0 && err < 0;
    accel = py_min(py_max(accel, 0.0), 100.0);
    brake = py_min(py_max(brake, 0.0), 100.0);

    if (d->ki > 0 && !(saturated_up || saturated_down)) {
        double lim = d->integral_limit_n / d->ki;
        d->integral = py_min(py_max(d->integral + err * dt, -lim), lim);
    }
    *accel_pct = accel;
    *brake_pct = brake;
}

void tcu_driver_pedals(tcu_driver *d, double t_s, const dct_outputs *out, double *accel_pct,
                       double *brake_pct)
{
    switch (d->kind) {
    case TCU_DRIVER_STEP:
        scripted_step(d, t_s, accel_pct, brake_pct);
        break;
    case TCU_DRIVER_LINEAR:
        *accel_pct = tcu_np_interp(t_s, d->t_s, d->a, d->n);
        *brake_pct = tcu_np_interp(t_s, d->t_s, d->b, d->n);
        break;
    case TCU_DRIVER_SPEED:
        speed_tracking(d, t_s, out, accel_pct, brake_pct);
        break;
    default:
        break;
    }
}
