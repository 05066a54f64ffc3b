/*
 * plant.c - the assembly: engine -> K1/K2 -> gearbox -> differential and
 * half-shafts -> wheels and brakes -> tyres -> vehicle body.
 *
 * One sub-step of explicit Euler: every component's coupling outputs
 * (torques, forces) are evaluated from the state at the start of the
 * sub-step, then every component advances its own states. The step of
 * params.solver.step_s (0.5 ms, the reference paper's real-time solver) is
 * made of params.solver.substeps such sub-steps. No allocation, no clock:
 * time is a state advanced by the step.
 */
#include <stddef.h>
#include <string.h>

#include "dct_plant.h"
#include "dct_util.h"

#define N_STATE ((int)(sizeof(dct_state) / sizeof(double)))
#define N_INPUT ((int)(sizeof(dct_inputs) / sizeof(double)))

int dct_plant_state_size(void) { return N_STATE; }
int dct_plant_input_size(void) { return N_INPUT; }

/* every coupling variable of one evaluation */
typedef struct {
    const dct_clutch_params *clutch_params; /* the two clutches with the pack gap at this oil temperature */
    const dct_hydraulics_derived *chamber;
    dct_hydraulics_input hydraulics_in;
    dct_hydraulics_output hydraulics;
    dct_clutch_input clutch_in[2];
    dct_clutch_output clutch[2];
    dct_engine_input engine_in;
    dct_engine_output engine;
    dct_driveline_input driveline_in;
    dct_driveline_output driveline;
    dct_gearbox_input gearbox_in;
    dct_gearbox_output gearbox;
    dct_tyre_input tyre_in[3];
    dct_tyre_output tyre[3];
    dct_wheel_input wheel_in[3];
    dct_wheel_output wheel[3];
    dct_vehicle_input vehicle_in;
    dct_vehicle_output vehicle;
    dct_thermal_effects thermal_fx;
    dct_thermal_input thermal_in;
    dct_thermal_output thermal;
    double pump_torque_nm;                /* the transmission's oil pump on the crank */
} coupling;

/* accessories on the crank (a torque that opposes the rotation): the
 * alternator's electrical load over its efficiency at the crank speed
 * (limited to what it takes at 500 rpm), the power steering pump and the
 * A/C compressor while switched on */
static double accessory_torque(const dct_thermal_params *p, double speed_rad_s)
{
    double w = fabs(speed_rad_s);
    double w_min = 500.0 * DCT_RAD_S_PER_RPM;
    double alt = p->alternator_load_w / p->alternator_efficiency / (w > w_min ? w : w_min);
    double t = alt + p->power_steering_nm + (p->ac_on > 0.5 ? p->ac_torque_nm : 0.0);
    return t * dct_smooth_sign(w, p->accessory_smoothing_rad_s);
}

/* the transmission's oil pump on the crank: it delivers its displacement
 * every revolution against the line pressure (the regulator spills what the
 * clutches do not take), so it takes line pressure x displacement / 2 pi
 * over its efficiency; all of it ends as heat in the transmission oil */
static double pump_torque(const dct_supply_params *p, double line_pressure_pa, double speed_rad_s,
                          double smoothing_rad_s)
{
    double pa = line_pressure_pa > 0.0 ? line_pressure_pa : 0.0;
    return pa * p->pump_displacement_cm3 * 1e-6 / (2.0 * DCT_PI * p->pump_efficiency) *
           dct_smooth_sign(speed_rad_s, smoothing_rad_s);
}

/* What the temperatures change: the thermal effects, the pack gaps at this
 * oil temperature and the chamber law that goes with them. The temperatures
 * move by millikelvin a second: taken once a step, at its start, for all its
 * sub-steps (plant_steps), and computed again only when a temperature
 * rounded to thermal.effects_resolution_k changed (pl->thermal) */
static void refresh_thermal(dct_plant *pl)
{
    const dct_params *p = &pl->effective;
    dct_thermal_cache *t = &pl->thermal;
    const dct_thermal_state *now = &pl->state.thermal;
    /* within 0.49 of the resolution of the key the rounded temperatures
     * are the key itself: no rounding needed (most steps) */
    double near = 0.49 * p->thermal.effects_resolution_k;
    if (t->valid > 0.5 && fabs(now->coolant_temp_degc - t->key[0]) < near &&
        fabs(now->engine_oil_temp_degc - t->key[1]) < near && fabs(now->trans_oil_temp_degc - t->key[2]) < near)
        return;
    double key[3];
    dct_thermal_effects_key(&p->thermal, now, key);
    if (t->valid > 0.5 && key[0] == t->key[0] && key[1] == t->key[1] && key[2] == t->key[2])
        return;
    dct_thermal_effects_eval(&p->thermal, &pl->derived.thermal, &p->hydraulics.oil, &pl->state.thermal, &t->fx);
    /* the pack gaps at this oil temperature (thermal expansion), and the
     * chamber law that goes with them; at the reference temperature the
     * prepared one */
    for (int k = 0; k < 2; k++) {
        t->clutch[k] = p->clutch[k];
        double gap = p->clutch[k].pack_gap_mm + t->fx.clutch_gap_change_mm;
        t->clutch[k].pack_gap_mm = gap > 0.0 ? gap : 0.0;
    }
    t->own_chambers = t->fx.clutch_gap_change_mm != 0.0 ? 1.0 : 0.0;
    if (t->own_chambers > 0.5)
        dct_hydraulics_prepare(&p->hydraulics, t->clutch, &t->chambers);
    for (int i = 0; i < 3; i++)
        t->key[i] = key[i];
    t->valid = 1.0;
}

/* the thermal part of the couplings, from pl->thermal (refresh_thermal) */
static void evaluate_thermal(const dct_plant *pl, coupling *c)
{
    const dct_thermal_cache *t = &pl->thermal;
    c->thermal_fx = t->fx;
    c->hydraulics_in.oil_viscosity_m2_s = t->fx.trans_oil_viscosity_m2_s;
    c->clutch_params = t->clutch;
    c->chamber = t->own_chambers > 0.5 ? &t->chambers : &pl->derived.hydraulics;
}

/* every coupling of one sub-step, the thermal part (evaluate_thermal) given */
static void evaluate_at(const dct_plant *pl, const dct_inputs *u, coupling *c)
{
    const dct_params *p = &pl->effective;
    const dct_state *s = &pl->state;
    /* hydraulics: clamp forces from the chamber pressures, or from the
     * commanded pressures through the same pistons */
    c->hydraulics_in.current_a[0] = u->solenoid_current1_a;
    c->hydraulics_in.current_a[1] = u->solenoid_current2_a;
    c->hydraulics_in.line_current_a = u->line_solenoid_current_a;
    /* a stuck spool, a jammed fork (faults.c); without faults none, at no cost */
    if (pl->derived.faults_on > 0.5) {
        dct_faults_apply_couplings(&pl->derived.faults, &c->hydraulics_in, &c->gearbox_in);
    } else {
        c->hydraulics_in.spool_stuck[0] = c->hydraulics_in.spool_stuck[1] = 0.0;
        for (int k = 0; k < DCT_N_SLEEVES; k++)
            c->gearbox_in.fork_jammed[k] = 0.0;
    }
    if (p->hydraulics.pressure_commanded > 0.5) {
        double pressure[2] = {u->clutch1_pressure_bar, u->clutch2_pressure_bar};
        for (int k = 0; k < 2; k++) {
            dct_piston_output po;
            dct_piston_eval(&c->clutch_params[k], pressure[k] * DCT_PA_PER_BAR, &po);
            c->hydraulics.clamp_force_n[k] = po.clamp_force_n;
            c->hydraulics.piston_position_m[k] = po.position_m;
            c->hydraulics.clutch_pressure_pa[k] = pressure[k] * DCT_PA_PER_BAR;
        }
    } else {
        dct_hydraulics_output_eval(&p->hydraulics, c->chamber, c->clutch_params, &s->hydraulics,
                                   &c->hydraulics);
    }
    /* the advance's first sub-step starts from these pressures */
    c->hydraulics_in.pressure_known = p->hydraulics.pressure_commanded > 0.5 ? 0.0 : 1.0;
    c->hydraulics_in.pressure_pa[0] = c->hydraulics.clutch_pressure_pa[0];
    c->hydraulics_in.pressure_pa[1] = c->hydraulics.clutch_pressure_pa[1];

    /* clutches: engine drum to the input shafts */
    for (int k = 0; k < 2; k++) {
        c->clutch_in[k].clamp_force_n = c->hydraulics.clamp_force_n[k];
        c->clutch_in[k].drive_speed_rad_s = s->engine.speed_rad_s;
        c->clutch_in[k].driven_speed_rad_s = s->gearbox.input_speed_rad_s[k];
        c->clutch_in[k].drag_excess = c->thermal_fx.clutch_drag_factor - 1.0;
        c->clutch_in[k].mu_excess = c->thermal_fx.clutch_mu_factor - 1.0;
        dct_clutch_output_eval(&p->clutch[k], &s->clutch[k], &c->clutch_in[k], &c->clutch[k]);
    }

    /* engine, loaded by both clutches */
    c->engine_in.accel_pedal_pct = u->accel_pedal_pct;
    c->engine_in.torque_request_nm = u->engine_torque_request_nm;
    c->engine_in.torque_request_active = u->torque_request_active;
    c->engine_in.engine_on = u->engine_on;
    c->engine_in.load_torque_nm = c->clutch[0].torque_nm + c->clutch[1].torque_nm;
    c->engine_in.drag_excess = c->thermal_fx.engine_drag_factor - 1.0;
    c->engine_in.idle_rise_rpm = c->thermal_fx.idle_rise_rpm;
    c->engine_in.fuel_enrichment = c->thermal_fx.fuel_enrichment;
    c->pump_torque_nm = pump_torque(&p->hydraulics.supply, s->hydraulics.line_pressure_pa,
                                    s->engine.speed_rad_s, p->thermal.accessory_smoothing_rad_s);
    c->engine_in.accessory_torque_nm = accessory_torque(&p->thermal, s->engine.speed_rad_s) +
                                       c->pump_torque_nm;
    dct_engine_output_eval(&p->engine, &s->engine, &c->engine_in, &c->engine);

    /* differential and half-shafts */
    c->driveline_in.carrier_speed_rad_s = s->gearbox.carrier_speed_rad_s;
    c->driveline_in.left_wheel_speed_rad_s = s->wheel[0].speed_rad_s;
    c->driveline_in.right_wheel_speed_rad_s = s->wheel[1].speed_rad_s;
    c->driveline_in.body_pitch_rad = s->vehicle.pitch_rad;
    c->driveline_in.body_pitch_rate_rad_s = s->vehicle.pitch_rate_rad_s;
    dct_driveline_output_eval(&p->driveline, &s->driveline, &c->driveline_in, &c->driveline);

    /* gearbox */
    c->gearbox_in.clutch_torque_nm[0] = c->clutch[0].torque_nm;
    c->gearbox_in.clutch_torque_nm[1] = c->clutch[1].torque_nm;
    c->gearbox_in.fork_force_n[0] = u->fork_force1_n;
    c->gearbox_in.fork_force_n[1] = u->fork_force2_n;
    c->gearbox_in.fork_force_n[2] = u->fork_force3_n;
    c->gearbox_in.fork_force_n[3] = u->fork_force4_n;
    c->gearbox_in.load_torque_nm = c->driveline.carrier_load_nm;
    c->gearbox_in.viscous_drag_excess = c->thermal_fx.churning_factor - 1.0;
    for (int k = 0; k < 2; k++)
        c->gearbox_in.clutch_damping_nms_per_rad[k] =
            c->clutch[k].friction.sliding > 0.5 ? 0.0 : p->clutch[k].friction.damping_nms_per_rad;
    dct_gearbox_output_eval(&p->gearbox, &pl->derived.gearbox, &s->gearbox, &c->gearbox_in,
                            &c->gearbox);

    /* tyres: normal forces from the suspension state */
    double fz_front, fz_rear;
    dct_vehicle_tyre_loads(&p->vehicle, &s->vehicle, u->road_grade_pct, &fz_front, &fz_rear);
    double fz[3] = {0.5 * fz_front, 0.5 * fz_front, fz_rear};
    double count[3] = {1.0, 1.0, 2.0};
    double shaft[3] = {c->driveline.shaft_torque_nm, c->driveline.shaft_torque_nm, 0.0};
    /* the magic formula's coefficients per load: the front tyres share theirs */
    dct_tyre_load load[2];
    for (int a = 0; a < 2; a++) {
        int i = a == 0 ? 0 : 2;
        dct_tyre_load_eval(&p->tyre, (fz[i] > 0.0 ? fz[i] : 0.0) / count[i], &load[a]);
    }
    for (int i = 0; i < 3; i++) {
        c->tyre_in[i].wheel_speed_rad_s = s->wheel[i].speed_rad_s;
        c->tyre_in[i].ground_speed_m_s = s->vehicle.speed_m_s;
        c->tyre_in[i].normal_force_n = fz[i];
        c->tyre_in[i].count = count[i];
        dct_tyre_output_eval_at(&p->tyre, &s->tyre[i], &c->tyre_in[i], &load[i < 2 ? 0 : 1], &c->tyre[i]);

        c->wheel_in[i].drive_torque_nm = shaft[i];
        c->wheel_in[i].tyre_force_n = c->tyre[i].force_n;
        c->wheel_in[i].tyre_radius_m = p->tyre.radius_m;
        c->wheel_in[i].rolling_moment_nm = c->tyre[i].rolling_moment_nm;
        c->wheel_in[i].brake_pedal_pct = u->brake_pedal_pct;
        c->wheel_in[i].park_lock = u->selector_lever == DCT_SELECTOR_P ? 1.0 : 0.0;
        const dct_wheel_params *wp = i < 2 ? &p->front_wheel : &p->rear_wheels;
        dct_wheel_output_eval(wp, &s->wheel[i], &c->wheel_in[i], &c->wheel[i]);
    }

    /* body */
    c->vehicle_in.front_tyre_force_n = c->tyre[0].force_n + c->tyre[1].force_n;
    c->vehicle_in.rear_tyre_force_n = c->tyre[2].force_n;
    /* the front wheels take the brakes' torques from the body; the
     * half-shafts' reaction reaches it through the powertrain mounts */
    c->vehicle_in.front_wheel_torque_nm = c->wheel[0].body_torque_nm + c->wheel[1].body_torque_nm -
                                          c->driveline.carrier_load_nm + c->driveline.mount_torque_nm;
    c->vehicle_in.rear_wheel_torque_nm = c->wheel[2].body_torque_nm;
    c->vehicle_in.road_grade_pct = u->road_grade_pct;
    dct_vehicle_output_eval(&p->vehicle, &s->vehicle, &c->vehicle_in, &c->vehicle);

    /* heat: the engine's unused fuel energy and friction, the clutches'
     * slip and the gearbox's losses */
    double w = s->engine.speed_rad_s;
    c->thermal_in.fuel_heat_w = c->engine.burnt_fuel_rate_g_s * p->thermal.fuel_lhv_j_per_g;
    c->thermal_in.combustion_power_w = c->engine.combustion_torque_nm * w;
    c->thermal_in.friction_power_w = -c->engine.drag_nm * w;
    c->thermal_in.trans_heat_w = c->clutch[0].heat_w + c->clutch[1].heat_w + c->gearbox.power_loss_w +
                                 c->pump_torque_nm * w;
    c->thermal_in.vehicle_speed_m_s = s->vehicle.speed_m_s;
    dct_thermal_output_eval(&p->thermal, &s->thermal, &c->thermal_fx, &c->thermal_in, &c->thermal);
}

static void evaluate(const dct_plant *pl, const dct_inputs *u, coupling *c)
{
    evaluate_thermal(pl, c);
    evaluate_at(pl, u, c);
}

static void advance(dct_plant *pl, const coupling *c, double h)
{
    const dct_params *p = &pl->effective;
    dct_state *s = &pl->state;
    if (!(p->hydraulics.pressure_commanded > 0.5))
        dct_hydraulics_advance(&p->hydraulics, c->chamber, &s->hydraulics, &c->hydraulics_in, h);
    dct_engine_advance(&p->engine, &s->engine, &c->engine_in, &c->engine, h);
    for (int k = 0; k < 2; k++)
        dct_clutch_advance(&p->clutch[k], &s->clutch[k], &c->clutch[k], h);
    dct_gearbox_advance(&p->gearbox, &pl->derived.gearbox, &s->gearbox, &c->gearbox_in,
                        &c->gearbox, h);
    dct_driveline_advance(&p->driveline, &s->driveline, &c->driveline_in, &c->driveline, h);
    for (int i = 0; i < 3; i++) {
        const dct_wheel_params *wp = i < 2 ? &p->front_wheel : &p->rear_wheels;
        dct_wheel_advance(wp, &s->wheel[i], &c->wheel_in[i], &c->wheel[i], h);
        dct_tyre_advance(&p->tyre, &s->tyre[i], &c->tyre[i], h);
    }
    dct_vehicle_advance(&p->vehicle, &s->vehicle, &c->vehicle_in, &c->vehicle, h);
    dct_thermal_advance(&p->thermal, &s->thermal, &c->thermal, h);
    s->time_s += h;
}

static double sync_gear_number(const dct_sync_state *s, int sleeve)
{
    int g = dct_sleeve_gear(sleeve, (int)s->side);
    if (g < 0 || s->phase == DCT_SYNC_DISENGAGED)
        return 0.0;
    return g == DCT_GEAR_R ? -1.0 : (double)(g + 1);
}

/* clutch torque (transmitted, and capacity) below which a clutch is taken to
 * carry no drive torque */
#define GEAR_TORQUE_MIN_NM 2.0

/* the input shaft (0 K1, 1 K2) whose clutch carries the drive torque now: of
 * the clamped clutches (capacity >= GEAR_TORQUE_MIN_NM; the drag of an open
 * pack does not count), the one with the larger torque, if that is at least
 * GEAR_TORQUE_MIN_NM; -1 when none does (both open, or the torque of the
 * closed one crossing zero while coasting) */
static int drive_shaft(const coupling *c)
{
    int shaft = -1;
    double best = 0.0;
    for (int k = 0; k < 2; k++) {
        double t = fabs(c->clutch[k].torque_nm);
        if (c->clutch[k].capacity_nm < GEAR_TORQUE_MIN_NM || t < GEAR_TORQUE_MIN_NM)
            continue;
        if (shaft < 0 || t > best) {
            shaft = k;
            best = t;
        }
    }
    return shaft;
}

/* the gear engaged (synchronizer engaged) on an input shaft: 1..6, -1 R, 0 none */
static double shaft_gear(const dct_state *s, int shaft)
{
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        const dct_sync_state *y = &s->gearbox.sync[k];
        int g = dct_sleeve_gear(k, (int)y->side);
        if (g < 0 || y->phase != DCT_SYNC_ENGAGED || dct_gear_input_shaft(g) != shaft)
            continue;
        return g == DCT_GEAR_R ? -1.0 : (double)(g + 1);
    }
    return 0.0;
}

/* the engaged gear (output "gear"): the gear engaged on the active input
 * shaft, the one whose clutch carries the drive torque now or, while no clutch
 * does, carried it last (pl->active_shaft); 0 before any clutch has carried
 * torque since the reset, or when the active shaft has no gear engaged */
static double engaged_gear(const dct_plant *pl, const coupling *c)
{
    int shaft = drive_shaft(c);
    if (shaft < 0)
        shaft = (int)pl->active_shaft;
    return shaft < 0 ? 0.0 : shaft_gear(&pl->state, shaft);
}

/* the chamber pressure at which the piston has closed the pack gap (the
 * kiss point): return spring preload and its rate over the gap (piston.c) */
static double pack_closed_pressure_pa(const dct_clutch_params *cp)
{
    return (cp->return_spring_n + cp->return_spring_n_per_m * cp->pack_gap_mm * 1e-3) / cp->piston_area_m2;
}

static void write_outputs(dct_plant *pl, const coupling *c)
{
    const dct_params *p = &pl->effective;
    const dct_state *s = &pl->state;
    dct_outputs *o = &pl->outputs;
    const dct_gearbox_state *g = &s->gearbox;
    /* the chambers' pressures (and the pistons on them) at the state now,
     * as the spools' and the line's: the couplings are those of the last
     * step's start, a whole step older */
    dct_hydraulics_output hy = c->hydraulics;
    if (!(p->hydraulics.pressure_commanded > 0.5))
        dct_hydraulics_output_eval(&p->hydraulics, c->chamber, c->clutch_params, &s->hydraulics, &hy);
    o->time_s = s->time_s;
    o->engine_speed_rpm = s->engine.speed_rad_s * DCT_RPM_PER_RAD_S;
    o->engine_torque_nm = c->engine.torque_nm;
    o->engine_running = s->engine.running;
    o->input_shaft1_speed_rpm = g->input_speed_rad_s[0] * DCT_RPM_PER_RAD_S;
    o->input_shaft2_speed_rpm = g->input_speed_rad_s[1] * DCT_RPM_PER_RAD_S;
    o->output_shaft1_speed_rpm = g->carrier_speed_rad_s * p->gearbox.final_drive[0] * DCT_RPM_PER_RAD_S;
    o->output_shaft2_speed_rpm = g->carrier_speed_rad_s * p->gearbox.final_drive[1] * DCT_RPM_PER_RAD_S;
    o->solenoid_current1_a = pl->applied.solenoid_current1_a;
    o->solenoid_current2_a = pl->applied.solenoid_current2_a;
    o->line_solenoid_current_a = pl->applied.line_solenoid_current_a;
    o->line_pressure_bar = s->hydraulics.line_pressure_pa / DCT_PA_PER_BAR;
    o->clutch1_pressure_bar = hy.clutch_pressure_pa[0] / DCT_PA_PER_BAR;
    o->clutch2_pressure_bar = hy.clutch_pressure_pa[1] / DCT_PA_PER_BAR;
    o->piston1_position_mm = hy.piston_position_m[0] * 1e3;
    o->piston2_position_mm = hy.piston_position_m[1] * 1e3;
    o->spool1_position_mm = s->hydraulics.valve[0].spool_position_m * 1e3;
    o->spool2_position_mm = s->hydraulics.valve[1].spool_position_m * 1e3;
    o->clutch1_clamp_force_n = hy.clamp_force_n[0];
    o->clutch2_clamp_force_n = hy.clamp_force_n[1];
    o->clutch1_torque_nm = c->clutch[0].torque_nm;
    o->clutch2_torque_nm = c->clutch[1].torque_nm;
    o->clutch1_slip_rpm = (s->engine.speed_rad_s - g->input_speed_rad_s[0]) * DCT_RPM_PER_RAD_S;
    o->clutch2_slip_rpm = (s->engine.speed_rad_s - g->input_speed_rad_s[1]) * DCT_RPM_PER_RAD_S;
    o->clutch1_capacity_nm = c->clutch[0].capacity_nm;
    o->clutch2_capacity_nm = c->clutch[1].capacity_nm;
    o->vehicle_speed_kmh = s->vehicle.speed_m_s * 3.6;
    o->vehicle_accel_mps2 = c->vehicle.accel_m_s2;
    o->distance_m = s->vehicle.position_m;
    o->pitch_deg = s->vehicle.pitch_rad * (180.0 / DCT_PI);
    o->heave_mm = s->vehicle.heave_m * 1e3;
    double *state_out = &o->sync1_state, *gear_out = &o->sync1_gear, *fork_out = &o->fork1_position_mm;
    double clashes = 0.0;
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        state_out[k] = g->sync[k].phase;
        gear_out[k] = sync_gear_number(&g->sync[k], k);
        fork_out[k] = g->sync[k].position_m * 1e3;
        clashes += g->sync[k].clashes;
    }
    o->gear_clashes = clashes;
    o->fuel_l = s->engine.fuel_g * 1e-3 / p->engine.fuel_density_kg_per_l;
    o->fuel_rate_lph = c->engine.fuel_rate_g_s * 3.6 / p->engine.fuel_density_kg_per_l;
    o->wheel_speed_fl_rpm = s->wheel[0].speed_rad_s * DCT_RPM_PER_RAD_S;
    o->wheel_speed_fr_rpm = s->wheel[1].speed_rad_s * DCT_RPM_PER_RAD_S;
    o->wheel_speed_rear_rpm = s->wheel[2].speed_rad_s * DCT_RPM_PER_RAD_S;
    o->halfshaft_torque_nm = c->driveline.shaft_torque_nm;
    o->front_tyre_slip = c->tyre[0].slip;
    o->front_axle_load_n = c->vehicle.front_normal_force_n;
    o->rear_axle_load_n = c->vehicle.rear_normal_force_n;
    o->brake_torque_nm = c->wheel[0].brake_torque_nm + c->wheel[1].brake_torque_nm +
                         c->wheel[2].brake_torque_nm;
    o->road_grade_pct = pl->applied.road_grade_pct;
    o->accel_pedal_pct = pl->applied.accel_pedal_pct;
    o->brake_pedal_pct = pl->applied.brake_pedal_pct;
    o->input_clamps = pl->input_clamps;
    o->coolant_temp_degc = s->thermal.coolant_temp_degc;
    o->engine_oil_temp_degc = s->thermal.engine_oil_temp_degc;
    o->trans_oil_temp_degc = s->thermal.trans_oil_temp_degc;
    o->thermostat_opening = c->thermal_fx.thermostat_opening;
    o->engine_heat_in_w = c->thermal.coolant_heat_in_w + c->thermal.engine_oil_heat_in_w;
    o->trans_heat_in_w = c->thermal.trans_heat_in_w;
    o->heat_rejected_w = c->thermal.radiator_w + c->thermal.engine_ambient_w + c->thermal.trans_ambient_w;
    o->trans_oil_viscosity_mm2_s = c->thermal_fx.trans_oil_viscosity_m2_s * 1e6;
    o->accessory_torque_nm = c->engine.accessory_torque_nm - c->pump_torque_nm;
    o->trans_pump_torque_nm = c->pump_torque_nm;
    o->gear = engaged_gear(pl, c);
    o->selector_lever = pl->applied.selector_lever;
    o->park_lock_engaged = c->wheel[0].park_locked > 0.5 || c->wheel[1].park_locked > 0.5 ? 1.0 : 0.0;
    double *kiss_out = &o->clutch1_kiss_pressure_bar, *mu_out = &o->clutch1_friction_coeff;
    double *drag_out = &o->clutch1_drag_torque_nm;
    for (int k = 0; k < 2; k++) {
        kiss_out[k] = pack_closed_pressure_pa(&c->clutch_params[k]) / DCT_PA_PER_BAR;
        mu_out[k] = c->clutch[k].mu_kinetic;
        drag_out[k] = c->clutch[k].drag_torque_nm;
    }
}

/* limit one input to [lo, hi], counting the values that had to be limited */
static double limit(dct_plant *pl, double x, double lo, double hi)
{
    if (x < lo) {
        pl->input_clamps += 1.0;
        return lo;
    }
    if (x > hi) {
        pl->input_clamps += 1.0;
        return hi;
    }
    return x;
}

/* checks the inputs (non-finite: error) and writes the limited copy the
 * components use; the caller's struct is left as it was given */
static int apply_inputs(dct_plant *pl)
{
    const double *raw = (const double *)&pl->inputs;
    for (int i = 0; i < N_INPUT; i++) {
        if (!isfinite(raw[i])) {
            pl->error_index = i;
            return DCT_ERR_INPUT;
        }
    }
    const dct_params *p = &pl->effective;
    const dct_inputs *u = &pl->inputs;
    dct_inputs *a = &pl->applied;
    double fmax = p->gearbox.max_fork_force_n;
    a->accel_pedal_pct = limit(pl, u->accel_pedal_pct, 0.0, 100.0);
    a->brake_pedal_pct = limit(pl, u->brake_pedal_pct, 0.0, 100.0);
    double imax = p->hydraulics.valve.max_current_a;
    a->solenoid_current1_a = limit(pl, u->solenoid_current1_a, 0.0, imax);
    a->solenoid_current2_a = limit(pl, u->solenoid_current2_a, 0.0, imax);
    a->line_solenoid_current_a = limit(pl, u->line_solenoid_current_a, 0.0, p->hydraulics.supply.max_current_a);
    a->clutch1_pressure_bar = limit(pl, u->clutch1_pressure_bar, 0.0, p->clutch[0].max_pressure_bar);
    a->clutch2_pressure_bar = limit(pl, u->clutch2_pressure_bar, 0.0, p->clutch[1].max_pressure_bar);
    a->fork_force1_n = limit(pl, u->fork_force1_n, -fmax, fmax);
    a->fork_force2_n = limit(pl, u->fork_force2_n, -fmax, fmax);
    a->fork_force3_n = limit(pl, u->fork_force3_n, -fmax, fmax);
    a->fork_force4_n = limit(pl, u->fork_force4_n, -fmax, fmax);
    a->road_grade_pct = limit(pl, u->road_grade_pct, -40.0, 40.0);
    a->engine_torque_request_nm = limit(pl, u->engine_torque_request_nm, -200.0, 1000.0);
    a->torque_request_active = u->torque_request_active > 0.5 ? 1.0 : 0.0;
    a->engine_on = u->engine_on > 0.5 ? 1.0 : 0.0;
    /* the lever is in one of its positions: the nearest, within P..D */
    a->selector_lever = floor(limit(pl, u->selector_lever, DCT_SELECTOR_P, DCT_SELECTOR_D) + 0.5);
    if (pl->derived.faults_on > 0.5)
        dct_faults_apply_inputs(&pl->derived.faults, a);
    return DCT_OK;
}

static int check_state(dct_plant *pl)
{
    const double *x = (const double *)&pl->state;
    for (int i = 0; i < N_STATE; i++) {
        if (!isfinite(x[i])) {
            pl->error_index = i;
            return DCT_ERR_STATE;
        }
    }
    return DCT_OK;
}

/* the state's discrete values are among their values (a state written from
 * outside, XCP or a saved FMU state, may hold anything; they index tables) */
static int check_discrete(dct_plant *pl)
{
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        const dct_sync_state *y = &pl->state.gearbox.sync[k];
        if (!(y->side == -1.0 || y->side == 0.0 || y->side == 1.0) ||
            !(y->phase == DCT_SYNC_DISENGAGED || y->phase == DCT_SYNC_SYNCHRONIZING ||
              y->phase == DCT_SYNC_ENGAGED)) {
            pl->error_index = (int)((const double *)&y->side - (const double *)&pl->state);
            return DCT_ERR_STATE;
        }
    }
    if (!(pl->active_shaft == -1.0 || pl->active_shaft == 0.0 || pl->active_shaft == 1.0))
        return DCT_ERR_STATE;
    return DCT_OK;
}

static int plant_steps(dct_plant *pl, int n)
{
    coupling c;
    int st = check_discrete(pl);
    if (st != DCT_OK)
        return st;
    int sub = (int)pl->effective.solver.substeps;
    double h = pl->effective.solver.step_s / sub;
    st = apply_inputs(pl);
    if (st != DCT_OK)
        return st;
    for (int i = 0; i < n; i++) {
        refresh_thermal(pl);
        evaluate_thermal(pl, &c);
        for (int j = 0; j < sub; j++) {
            evaluate_at(pl, &pl->applied, &c);
            advance(pl, &c, h);
        }
        pl->step_count += 1.0;
        int shaft = drive_shaft(&c);
        if (shaft >= 0)
            pl->active_shaft = shaft;
        st = check_state(pl);
        if (st != DCT_OK)
            return st;
    }
    if (n > 0)
        write_outputs(pl, &c);
    return DCT_OK;
}

/* the steps with subnormals flushed (dct_util.h: dct_fp_flush_begin) */
int dct_plant_step(dct_plant *pl, int n)
{
    dct_fp_mode mode = dct_fp_flush_begin();
    int st = plant_steps(pl, n);
    dct_fp_flush_end(mode);
    return st;
}

void dct_plant_update_outputs(dct_plant *pl)
{
    coupling c;
    dct_fp_mode mode = dct_fp_flush_begin();
    refresh_thermal(pl);
    evaluate(pl, &pl->applied, &c);
    write_outputs(pl, &c);
    dct_fp_flush_end(mode);
}

static int check_params(const dct_params *p)
{
    if (!(p->solver.step_s > 0.0) || !(p->solver.substeps >= 1.0) || p->solver.substeps > 1000.0)
        return DCT_ERR_PARAM;
    if (!(p->engine.inertia_kgm2 > 0.0) || p->engine.full_load.n < 1 || p->engine.drag.n < 1 ||
        p->engine.full_load.n > DCT_CURVE_MAX || p->engine.drag.n > DCT_CURVE_MAX)
        return DCT_ERR_PARAM;
    if (p->engine.bsfc.n_speed_rpm < 1 || p->engine.bsfc.n_torque_nm < 1 ||
        p->engine.bsfc.n_speed_rpm > DCT_MAP_MAX || p->engine.bsfc.n_torque_nm > DCT_MAP_MAX)
        return DCT_ERR_PARAM;
    if (!(p->engine.tau_rise_s > 0.0) || !(p->engine.tau_fall_s > 0.0) || !(p->engine.tau_boost_s > 0.0))
        return DCT_ERR_PARAM;
    for (int k = 0; k < 2; k++) {
        if (!(p->clutch[k].friction.stiffness_nm_per_rad > 0.0) || !(p->clutch[k].stribeck_speed_rad_s > 0.0))
            return DCT_ERR_PARAM;
        if (!(p->gearbox.input_shaft_inertia_kgm2[k] > 0.0) || !(p->gearbox.final_drive[k] > 0.0))
            return DCT_ERR_PARAM;
    }
    for (int g = 0; g < DCT_N_GEARS; g++)
        if (!(p->gearbox.ratio[g] > 0.0) || !(p->gearbox.mesh_efficiency[g] > 0.0))
            return DCT_ERR_PARAM;
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        const dct_sync_params *sp = &p->gearbox.sync[k];
        if (!(sp->stiffness_nm_per_rad > 0.0) || !(sp->sleeve_mass_kg > 0.0) ||
            !(sp->tanh_speed_rad_s > 0.0) || !(sp->dog_radius_m > 0.0) ||
            !(sp->engaged_travel_mm > sp->cone_travel_mm) || !(sp->cone_travel_mm > 0.0) ||
            !(sp->ring_chamfer_angle_deg >= 0.0 && sp->ring_chamfer_angle_deg < 90.0) ||
            !(sp->ring_pass_travel_mm >= 0.0))
            return DCT_ERR_PARAM;
    }
    const dct_hydraulics_params *hy = &p->hydraulics;
    if (!(hy->substeps >= 1.0) || hy->substeps > 1000.0 || hy->supply.line.n < 1 ||
        hy->supply.line.n > DCT_CURVE_MAX || !(hy->supply.tau_s > 0.0) ||
        !(hy->valve.spool_mass_kg > 0.0) || !(hy->valve.solenoid_tau_s > 0.0) ||
        !(hy->valve.friction_tau_s > 0.0) || !(hy->valve.spool_diameter_mm > hy->valve.rod_diameter_mm) ||
        !(hy->oil.density_kg_m3 > 0.0) || !(hy->oil.viscosity_m2_s > 0.0) ||
        !(hy->oil.bulk_modulus_pa > 0.0) || !(hy->chamber_volume_cm3[0] > 0.0) ||
        !(hy->chamber_volume_cm3[1] > 0.0))
        return DCT_ERR_PARAM;
    for (int k = 0; k < 2; k++)
        if (!(p->clutch[k].piston_area_m2 > 0.0) || !(p->clutch[k].return_spring_n_per_m > 0.0) ||
            !(p->clutch[k].pack_stiffness_n_per_m > 0.0))
            return DCT_ERR_PARAM;
    if (!(p->driveline.left_damping_nms_per_rad + p->driveline.right_damping_nms_per_rad > 0.0) ||
        !(p->driveline.powertrain_roll_inertia_kgm2 > 0.0))
        return DCT_ERR_PARAM;
    const dct_thermal_params *th = &p->thermal;
    if (!(th->coolant_heat_capacity_j_per_k > 0.0) || !(th->engine_oil_heat_capacity_j_per_k > 0.0) ||
        !(th->trans_heat_capacity_j_per_k > 0.0) || !(th->thermostat_full_degc > th->thermostat_open_degc) ||
        !(th->idle_warm_degc > th->idle_cold_degc) || !(th->alternator_efficiency > 0.0) ||
        !(th->accessory_smoothing_rad_s > 0.0) || !(th->engine_oil_viscosity_40c_mm2_s > th->engine_oil_viscosity_100c_mm2_s) ||
        !(th->engine_oil_viscosity_100c_mm2_s > 0.0) ||
        !(th->trans_oil_viscosity_40c_mm2_s > th->trans_oil_viscosity_100c_mm2_s) ||
        !(th->trans_oil_viscosity_100c_mm2_s > 0.0) || !(th->effects_resolution_k >= 0.0))
        return DCT_ERR_PARAM;
    if (!(p->front_wheel.inertia_kgm2 > 0.0) || !(p->rear_wheels.inertia_kgm2 > 0.0) ||
        !(p->front_wheel.brake.stiffness_nm_per_rad > 0.0) || !(p->rear_wheels.brake.stiffness_nm_per_rad > 0.0))
        return DCT_ERR_PARAM;
    if (!(p->tyre.radius_m > 0.0) || !(p->tyre.relaxation_length_m > 0.0) ||
        !(p->tyre.nominal_load_n > 0.0) || !(p->tyre.low_speed_limit_m_s > 0.0))
        return DCT_ERR_PARAM;
    const dct_vehicle_params *v = &p->vehicle;
    if (!(v->mass_kg > v->front_unsprung_kg + v->rear_unsprung_kg) || !(v->front_unsprung_kg > 0.0) ||
        !(v->rear_unsprung_kg > 0.0) || !(v->wheelbase_m > v->cg_to_front_axle_m) ||
        !(v->cg_to_front_axle_m > 0.0) || !(v->pitch_inertia_kgm2 > 0.0))
        return DCT_ERR_PARAM;
    return DCT_OK;
}

/* params is the car as loaded (and calibrated); effective, params with the
 * faults applied, is what runs, so clearing the faults gives the car back
 * exactly */
int dct_plant_prepare(dct_plant *pl)
{
    int st = check_params(&pl->params);
    if (st != DCT_OK)
        return st;
    st = dct_faults_prepare(&pl->faults, &pl->params, &pl->effective, &pl->derived.faults,
                            &pl->error_index);
    if (st != DCT_OK)
        return st;
    const double *f = (const double *)&pl->derived.faults;
    pl->derived.faults_on = 0.0;
    for (size_t i = 0; i < sizeof pl->derived.faults / sizeof *f; i++)
        if (f[i] != 0.0)
            pl->derived.faults_on = 1.0;
    const dct_params *p = &pl->effective;
    dct_gearbox_prepare(&p->gearbox, &pl->derived.gearbox);
    dct_hydraulics_prepare(&p->hydraulics, p->clutch, &pl->derived.hydraulics);
    dct_thermal_prepare(&p->thermal, &pl->derived.thermal);
    pl->derived.front_static_n = dct_vehicle_static_front_n(&p->vehicle);
    pl->derived.rear_static_n = dct_vehicle_static_rear_n(&p->vehicle);
    pl->thermal.valid = 0.0; /* the effects of the new parameters */
    return DCT_OK;
}

int dct_plant_init(dct_plant *pl)
{
    int st = dct_plant_prepare(pl);
    if (st != DCT_OK)
        return st;
    memset(&pl->inputs, 0, sizeof pl->inputs);
    pl->inputs.engine_on = 1.0;
    pl->inputs.selector_lever = DCT_SELECTOR_D;
    dct_initial init;
    memset(&init, 0, sizeof init);
    init.engine_on = 1.0;
    return dct_plant_reset(pl, &init);
}

int dct_plant_reset(dct_plant *pl, const dct_initial *init)
{
    const dct_params *p = &pl->effective;
    dct_state *s = &pl->state;
    const dct_gearbox_derived *d = &pl->derived.gearbox;
    memset(s, 0, sizeof *s);
    double v = init->vehicle_speed_kmh / 3.6;
    double w_wheel = v / p->tyre.radius_m;
    double w_car = w_wheel;
    if (init->temperatures_given > 0.5)
        dct_thermal_init(&p->thermal, &s->thermal, init->coolant_temp_degc, init->engine_oil_temp_degc,
                         init->trans_oil_temp_degc);
    else
        dct_thermal_init(&p->thermal, &s->thermal, p->thermal.initial_coolant_temp_degc,
                         p->thermal.initial_engine_oil_temp_degc, p->thermal.initial_trans_oil_temp_degc);
    dct_thermal_effects fx;
    dct_thermal_effects_eval(&p->thermal, &pl->derived.thermal, &p->hydraulics.oil, &s->thermal, &fx);
    int engine_on = init->engine_on > 0.5;
    double w_idle = engine_on ? (p->engine.idle_speed_rpm + fx.idle_rise_rpm) * DCT_RAD_S_PER_RPM : 0.0;

    /* input shafts follow an engaged gear, else the engine */
    double w_in[2] = {-1.0, -1.0};
    int engaged[2] = {0, 0};
    for (int k = 0; k < DCT_N_SLEEVES; k++) {
        int side = init->sleeve_side[k] > 0.5 ? 1 : (init->sleeve_side[k] < -0.5 ? -1 : 0);
        int g = dct_sleeve_gear(k, side);
        if (g < 0)
            side = 0;
        dct_sync_init(&p->gearbox.sync[k], &s->gearbox.sync[k], side);
        if (g >= 0) {
            int shaft = dct_gear_input_shaft(g);
            w_in[shaft] = w_car * p->gearbox.final_drive[dct_gear_output_shaft(g)] * d->signed_ratio[g];
            engaged[shaft] = 1;
        }
    }
    double w_eng = w_idle;
    pl->active_shaft = -1.0;
    for (int k = 0; k < 2; k++)
        if (init->clutch_locked[k] > 0.5 && engaged[k]) {
            w_eng = w_in[k];
            pl->active_shaft = k;
            break;
        }
    for (int k = 0; k < 2; k++)
        s->gearbox.input_speed_rad_s[k] = engaged[k] ? w_in[k] : w_eng;
    s->gearbox.carrier_speed_rad_s = w_car;
    dct_engine_init(&p->engine, &s->engine, w_eng, engine_on);
    if (engine_on) {
        /* the engine holds its speed against the drag at this temperature
         * and the accessories too (dct_engine_init: the warm drag alone) */
        double k = fx.engine_drag_factor - 1.0;
        double w_i = (p->engine.idle_speed_rpm + fx.idle_rise_rpm) * DCT_RAD_S_PER_RPM;
        double n_e = fabs(w_eng) * DCT_RPM_PER_RAD_S, n_i = w_i * DCT_RPM_PER_RAD_S;
        double line_pa = dct_pressure_map_eval(&p->hydraulics.supply.line, 0.0) * DCT_PA_PER_BAR;
        double sm = p->thermal.accessory_smoothing_rad_s;
        s->engine.combustion_torque_nm += -k * dct_curve_eval(&p->engine.drag, n_e) *
                                              dct_smooth_sign(w_eng, p->engine.drag_smoothing_rad_s) +
                                          accessory_torque(&p->thermal, w_eng) +
                                          pump_torque(&p->hydraulics.supply, line_pa, w_eng, sm);
        s->engine.idle_integral_nm = dct_clamp(-(1.0 + k) * dct_curve_eval(&p->engine.drag, n_i) +
                                                   accessory_torque(&p->thermal, w_i) +
                                                   pump_torque(&p->hydraulics.supply, line_pa, w_i, sm),
                                               0.0, p->engine.idle_torque_max_nm);
    }
    for (int k = 0; k < 2; k++)
        dct_clutch_init(&p->clutch[k], &s->clutch[k]);
    dct_hydraulics_init(&p->hydraulics, &s->hydraulics);
    dct_driveline_init(&p->driveline, &s->driveline);
    for (int i = 0; i < 3; i++) {
        dct_wheel_init(i < 2 ? &p->front_wheel : &p->rear_wheels, &s->wheel[i], w_wheel);
        dct_tyre_init(&p->tyre, &s->tyre[i]);
    }
    dct_vehicle_init(&p->vehicle, &s->vehicle, v);
    pl->step_count = 0.0;
    pl->input_clamps = 0.0;
    pl->error_index = -1;
    pl->inputs.engine_on = engine_on ? 1.0 : 0.0;
    int st = apply_inputs(pl);
    if (st != DCT_OK) {
        memset(&pl->applied, 0, sizeof pl->applied);
        pl->applied.engine_on = pl->inputs.engine_on;
        pl->applied.selector_lever = DCT_SELECTOR_D;
    }
    pl->input_clamps = 0.0;
    dct_plant_update_outputs(pl);
    return DCT_OK;
}

double dct_plant_energy(const dct_plant *pl)
{
    const dct_params *p = &pl->effective;
    const dct_state *s = &pl->state;
    const dct_gearbox_derived *d = &pl->derived.gearbox;
    double e = 0.5 * p->engine.inertia_kgm2 * dct_sq(s->engine.speed_rad_s);
    for (int k = 0; k < 2; k++) {
        e += 0.5 * d->input_inertia_kgm2[k] * dct_sq(s->gearbox.input_speed_rad_s[k]);
        e += 0.5 * p->clutch[k].friction.stiffness_nm_per_rad * dct_sq(s->clutch[k].twist_rad);
    }
    e += 0.5 * d->carrier_inertia_kgm2 * dct_sq(s->gearbox.carrier_speed_rad_s);
    for (int k = 0; k < DCT_N_SLEEVES; k++)
        if (s->gearbox.sync[k].phase == DCT_SYNC_ENGAGED)
            e += 0.5 * p->gearbox.sync[k].stiffness_nm_per_rad * dct_sq(s->gearbox.sync[k].twist_rad);
    e += 0.5 * p->driveline.left_stiffness_nm_per_rad * dct_sq(s->driveline.left_twist_rad);
    e += 0.5 * p->driveline.right_stiffness_nm_per_rad * dct_sq(s->driveline.right_twist_rad);
    e += 0.5 * p->driveline.powertrain_roll_inertia_kgm2 * dct_sq(s->driveline.roll_rate_rad_s);
    e += dct_driveline_mount_energy(&p->driveline, s->driveline.roll_rad + s->vehicle.pitch_rad);
    double fz_front, fz_rear;
    dct_vehicle_tyre_loads(&p->vehicle, &s->vehicle, pl->applied.road_grade_pct, &fz_front, &fz_rear);
    double fz[3] = {0.5 * fz_front, 0.5 * fz_front, fz_rear};
    double count[3] = {1.0, 1.0, 2.0};
    for (int i = 0; i < 3; i++) {
        const dct_wheel_params *wp = i < 2 ? &p->front_wheel : &p->rear_wheels;
        e += 0.5 * wp->inertia_kgm2 * dct_sq(s->wheel[i].speed_rad_s);
        e += 0.5 * wp->brake.stiffness_nm_per_rad * dct_sq(s->wheel[i].brake_twist_rad);
        e += dct_tyre_deflection_energy(&p->tyre, s->tyre[i].deflection_m, fz[i], count[i]);
    }
    e += dct_vehicle_energy(&p->vehicle, &s->vehicle, pl->applied.road_grade_pct);
    return e;
}
