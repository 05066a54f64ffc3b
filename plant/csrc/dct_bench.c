/*
 * dct_bench.c - times single plant steps, and each component's share of a
 * step, with the monotonic clock.
 */
#define _POSIX_C_SOURCE 199309L

#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "dct_bench.h"
#include "dct_util.h"

#ifndef DCT_CFLAGS
#define DCT_CFLAGS "unknown"
#endif

#if defined(__clang__)
#define DCT_COMPILER "clang " __clang_version__
#elif defined(__GNUC__)
#define DCT_COMPILER "gcc " __VERSION__
#else
#define DCT_COMPILER "unknown compiler"
#endif

int dct_bench_steps(dct_plant *plant, int n, double *step_ns)
{
    struct timespec t0, t1;
    int i;

    for (i = 0; i < n; i++) {
        int status;

        clock_gettime(CLOCK_MONOTONIC, &t0);
        status = dct_plant_step(plant, 1);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        step_ns[i] = (double)(t1.tv_sec - t0.tv_sec) * 1e9 + (double)(t1.tv_nsec - t0.tv_nsec);
        if (status != 0)
            return status;
    }
    return 0;
}

/* ---------------------------------------------------------------------- */
/* per-component cost                                                     */
/* ---------------------------------------------------------------------- */

enum {
    COMP_HYDRAULICS,
    COMP_CLUTCHES,
    COMP_ENGINE,
    COMP_DRIVELINE,
    COMP_GEARBOX,
    COMP_TYRES,
    COMP_WHEELS,
    COMP_VEHICLE,
    COMP_THERMAL
};

static const char *const COMPONENT_NAMES[DCT_BENCH_N_COMPONENTS] = {
    "hydraulics", "clutches", "engine", "driveline", "gearbox", "tyres", "wheels", "vehicle",
    "thermal",
};

const char *dct_bench_component_name(int i)
{
    return (i >= 0 && i < DCT_BENCH_N_COMPONENTS) ? COMPONENT_NAMES[i] : NULL;
}

#define BENCH_BATCHES 15
#define BENCH_RESTORE_EVERY 8 /* calls between restoring the state copy */

/* the inputs every component gets from the others, evaluated once from the
 * plant's state as plant.c evaluates them (held while timing) */
typedef struct {
    double pressure_pa[2];
    dct_hydraulics_input hydraulics_in;
    dct_clutch_input clutch_in[2];
    dct_engine_input engine_in;
    dct_driveline_input driveline_in;
    dct_gearbox_input gearbox_in;
    dct_tyre_input tyre_in[3];
    dct_wheel_input wheel_in[3];
    dct_vehicle_input vehicle_in;
    dct_thermal_input thermal_in;
} bench_inputs;

static void bench_couplings(const dct_plant *pl, bench_inputs *b)
{
    const dct_params *p = &pl->effective;
    const dct_state *s = &pl->state;
    const dct_inputs *u = &pl->applied;
    dct_hydraulics_output hy;
    dct_clutch_output co[2];
    dct_driveline_output dl;
    dct_tyre_output to[3];
    dct_wheel_output wo[3];

    memset(b, 0, sizeof *b);
    b->pressure_pa[0] = u->clutch1_pressure_bar * DCT_PA_PER_BAR;
    b->pressure_pa[1] = u->clutch2_pressure_bar * DCT_PA_PER_BAR;
    b->hydraulics_in.current_a[0] = u->solenoid_current1_a;
    b->hydraulics_in.current_a[1] = u->solenoid_current2_a;
    b->hydraulics_in.line_current_a = u->line_solenoid_current_a;
    dct_faults_apply_couplings(&pl->derived.faults, &b->hydraulics_in, &b->gearbox_in);
    if (p->hydraulics.pressure_commanded > 0.5) {
        for (int k = 0; k < 2; k++) {
            dct_piston_output po;
            dct_piston_eval(&p->clutch[k], b->pressure_pa[k], &po);
            hy.clamp_force_n[k] = po.clamp_force_n;
        }
    } else {
        dct_hydraulics_output_eval(&p->hydraulics, &pl->derived.hydraulics, p->clutch, &s->hydraulics, &hy);
    }
    for (int k = 0; k < 2; k++) {
        b->clutch_in[k].clamp_force_n = hy.clamp_force_n[k];
        b->clutch_in[k].drive_speed_rad_s = s->engine.speed_rad_s;
        b->clutch_in[k].driven_speed_rad_s = s->gearbox.input_speed_rad_s[k];
        dct_clutch_output_eval(&p->clutch[k], &s->clutch[k], &b->clutch_in[k], &co[k]);
    }
    b->engine_in.accel_pedal_pct = u->accel_pedal_pct;
    b->engine_in.torque_request_nm = u->engine_torque_request_nm;
    b->engine_in.torque_request_active = u->torque_request_active;
    b->engine_in.engine_on = u->engine_on;
    b->engine_in.load_torque_nm = co[0].torque_nm + co[1].torque_nm;
    b->driveline_in.carrier_speed_rad_s = s->gearbox.carrier_speed_rad_s;
    b->driveline_in.left_wheel_speed_rad_s = s->wheel[0].speed_rad_s;
    b->driveline_in.right_wheel_speed_rad_s = s->wheel[1].speed_rad_s;
    b->driveline_in.body_pitch_rad = s->vehicle.pitch_rad;
    b->driveline_in.body_pitch_rate_rad_s = s->vehicle.pitch_rate_rad_s;
    dct_driveline_output_eval(&p->driveline, &s->driveline, &b->driveline_in, &dl);
    b->gearbox_in.clutch_torque_nm[0] = co[0].torque_nm;
    b->gearbox_in.clutch_torque_nm[1] = co[1].torque_nm;
    b->gearbox_in.fork_force_n[0] = u->fork_force1_n;
    b->gearbox_in.fork_force_n[1] = u->fork_force2_n;
    b->gearbox_in.fork_force_n[2] = u->fork_force3_n;
    b->gearbox_in.fork_force_n[3] = u->fork_force4_n;
    b->gearbox_in.load_torque_nm = dl.carrier_load_nm;
    double fz_front, fz_rear;
    dct_vehicle_tyre_loads(&p->vehicle, &s->vehicle, u->road_grade_pct, &fz_front, &fz_rear);
    double fz[3] = {0.5 * fz_front, 0.5 * fz_front, fz_rear};
    double count[3] = {1.0, 1.0, 2.0};
    double shaft[3] = {dl.shaft_torque_nm, dl.shaft_torque_nm, 0.0};
    for (int i = 0; i < 3; i++) {
        b->tyre_in[i].wheel_speed_rad_s = s->wheel[i].speed_rad_s;
        b->tyre_in[i].ground_speed_m_s = s->vehicle.speed_m_s;
        b->tyre_in[i].normal_force_n = fz[i];
        b->tyre_in[i].count = count[i];
        dct_tyre_output_eval(&p->tyre, &s->tyre[i], &b->tyre_in[i], &to[i]);
        b->wheel_in[i].drive_torque_nm = shaft[i];
        b->wheel_in[i].tyre_force_n = to[i].force_n;
        b->wheel_in[i].tyre_radius_m = p->tyre.radius_m;
        b->wheel_in[i].rolling_moment_nm = to[i].rolling_moment_nm;
        b->wheel_in[i].brake_pedal_pct = u->brake_pedal_pct;
        b->wheel_in[i].park_lock = u->selector_lever == DCT_SELECTOR_P ? 1.0 : 0.0;
        dct_wheel_output_eval(i < 2 ? &p->front_wheel : &p->rear_wheels, &s->wheel[i],
                              &b->wheel_in[i], &wo[i]);
    }
    b->vehicle_in.front_tyre_force_n = to[0].force_n + to[1].force_n;
    b->vehicle_in.rear_tyre_force_n = to[2].force_n;
    b->vehicle_in.front_wheel_torque_nm = wo[0].body_torque_nm + wo[1].body_torque_nm -
                                          dl.carrier_load_nm + dl.mount_torque_nm;
    b->vehicle_in.rear_wheel_torque_nm = wo[2].body_torque_nm;
    b->vehicle_in.road_grade_pct = u->road_grade_pct;
    {
        /* heat flows as plant.c gives them */
        dct_engine_output eo;
        dct_gearbox_output go;
        dct_engine_output_eval(&p->engine, &s->engine, &b->engine_in, &eo);
        dct_gearbox_output_eval(&p->gearbox, &pl->derived.gearbox, &s->gearbox, &b->gearbox_in, &go);
        double w = s->engine.speed_rad_s;
        b->thermal_in.fuel_heat_w = eo.burnt_fuel_rate_g_s * p->thermal.fuel_lhv_j_per_g;
        b->thermal_in.combustion_power_w = eo.combustion_torque_nm * w;
        b->thermal_in.friction_power_w = -eo.drag_nm * w;
        b->thermal_in.trans_heat_w = co[0].heat_w + co[1].heat_w + go.power_loss_w;
        b->thermal_in.vehicle_speed_m_s = s->vehicle.speed_m_s;
    }
}

/* one sub-step of component c on the state copy x: its outputs, then its
 * advance, with the couplings held */
static void component_substep(const dct_plant *pl, const bench_inputs *b, int c, dct_state *x, double h)
{
    const dct_params *p = &pl->effective;
    switch (c) {
    case COMP_HYDRAULICS:
        if (p->hydraulics.pressure_commanded > 0.5) {
            for (int k = 0; k < 2; k++) {
                dct_piston_output po;
                dct_piston_eval(&p->clutch[k], b->pressure_pa[k], &po);
            }
        } else {
            dct_hydraulics_output hy;
            dct_hydraulics_output_eval(&p->hydraulics, &pl->derived.hydraulics, p->clutch,
                                       &x->hydraulics, &hy);
            dct_hydraulics_advance(&p->hydraulics, &pl->derived.hydraulics, &x->hydraulics,
                                   &b->hydraulics_in, h);
        }
        break;
    case COMP_CLUTCHES:
        for (int k = 0; k < 2; k++) {
            dct_clutch_output co;
            dct_clutch_output_eval(&p->clutch[k], &x->clutch[k], &b->clutch_in[k], &co);
            dct_clutch_advance(&p->clutch[k], &x->clutch[k], &co, h);
        }
        break;
    case COMP_ENGINE: {
        dct_engine_output eo;
        dct_engine_output_eval(&p->engine, &x->engine, &b->engine_in, &eo);
        dct_engine_advance(&p->engine, &x->engine, &b->engine_in, &eo, h);
        break;
    }
    case COMP_DRIVELINE: {
        dct_driveline_output dl;
        dct_driveline_output_eval(&p->driveline, &x->driveline, &b->driveline_in, &dl);
        dct_driveline_advance(&p->driveline, &x->driveline, &b->driveline_in, &dl, h);
        break;
    }
    case COMP_GEARBOX: {
        dct_gearbox_output go;
        dct_gearbox_output_eval(&p->gearbox, &pl->derived.gearbox, &x->gearbox, &b->gearbox_in, &go);
        dct_gearbox_advance(&p->gearbox, &pl->derived.gearbox, &x->gearbox, &b->gearbox_in, &go, h);
        break;
    }
    case COMP_TYRES:
        for (int i = 0; i < 3; i++) {
            dct_tyre_output to;
            dct_tyre_output_eval(&p->tyre, &x->tyre[i], &b->tyre_in[i], &to);
            dct_tyre_advance(&p->tyre, &x->tyre[i], &to, h);
        }
        break;
    case COMP_WHEELS:
        for (int i = 0; i < 3; i++) {
            const dct_wheel_params *wp = i < 2 ? &p->front_wheel : &p->rear_wheels;
            dct_wheel_output wo;
            dct_wheel_output_eval(wp, &x->wheel[i], &b->wheel_in[i], &wo);
            dct_wheel_advance(wp, &x->wheel[i], &b->wheel_in[i], &wo, h);
        }
        break;
    case COMP_THERMAL: {
        /* the effects the others read, then the heat balances */
        dct_thermal_effects fx;
        dct_thermal_output th;
        dct_thermal_effects_eval(&p->thermal, &pl->derived.thermal, &p->hydraulics.oil, &x->thermal, &fx);
        dct_thermal_output_eval(&p->thermal, &x->thermal, &fx, &b->thermal_in, &th);
        dct_thermal_advance(&p->thermal, &x->thermal, &th, h);
        break;
    }
    default: {
        /* the tyre loads are the body's: evaluated from its state */
        double fz_front, fz_rear;
        dct_vehicle_output vo;
        dct_vehicle_tyre_loads(&p->vehicle, &x->vehicle, b->vehicle_in.road_grade_pct, &fz_front, &fz_rear);
        dct_vehicle_output_eval(&p->vehicle, &x->vehicle, &b->vehicle_in, &vo);
        dct_vehicle_advance(&p->vehicle, &x->vehicle, &b->vehicle_in, &vo, h);
        break;
    }
    }
}

/* puts component c's part of the state back */
static void restore(int c, dct_state *x, const dct_state *s)
{
    switch (c) {
    case COMP_HYDRAULICS: x->hydraulics = s->hydraulics; break;
    case COMP_CLUTCHES: x->clutch[0] = s->clutch[0]; x->clutch[1] = s->clutch[1]; break;
    case COMP_ENGINE: x->engine = s->engine; break;
    case COMP_DRIVELINE: x->driveline = s->driveline; break;
    case COMP_GEARBOX: x->gearbox = s->gearbox; break;
    case COMP_TYRES: memcpy(x->tyre, s->tyre, sizeof x->tyre); break;
    case COMP_WHEELS: memcpy(x->wheel, s->wheel, sizeof x->wheel); break;
    case COMP_THERMAL: x->thermal = s->thermal; break;
    default: x->vehicle = s->vehicle; break;
    }
}

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e9 + (double)t.tv_nsec;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int dct_bench_components(const dct_plant *plant, int n, double *ns_per_substep)
{
    if (n < 1)
        return DCT_ERR_INPUT;
    bench_inputs b;
    bench_couplings(plant, &b);
    double h = plant->effective.solver.step_s / (int)plant->effective.solver.substeps;
    int per_batch = (n + BENCH_BATCHES - 1) / BENCH_BATCHES;
    int rounds = (per_batch + BENCH_RESTORE_EVERY - 1) / BENCH_RESTORE_EVERY;
    dct_state copy = plant->state;
    for (int c = 0; c < DCT_BENCH_N_COMPONENTS; c++) {
        double sample[BENCH_BATCHES];
        for (int k = 0; k < BENCH_BATCHES; k++) {
            double t0 = now_ns();
            for (int r = 0; r < rounds; r++) {
                restore(c, &copy, &plant->state);
                for (int i = 0; i < BENCH_RESTORE_EVERY; i++)
                    component_substep(plant, &b, c, &copy, h);
            }
            double t1 = now_ns();
            sample[k] = (t1 - t0) / (double)(rounds * BENCH_RESTORE_EVERY);
        }
        qsort(sample, BENCH_BATCHES, sizeof sample[0], cmp_double);
        ns_per_substep[c] = sample[BENCH_BATCHES / 2];
    }
    return DCT_OK;
}

const char *dct_bench_build_info(void)
{
    return DCT_COMPILER "; " DCT_CFLAGS;
}
