/*
 * dct_plant.h - public API of the dct-hil powertrain plant (VW DSG 02E in a
 * Golf Mk5 GTI by default).
 *
 * This header is the contract between the C core and everything else. It is
 * read as-is by the cffi builder (plant/_build.py), so it keeps to the subset
 * cffi parses: plain structs of double/int, integer #defines, prototypes.
 *
 * Conventions
 *   - SI units inside the core (rad/s, N m, N, m, kg); the unit is in every
 *     field name. Inputs and outputs use the units engineers read (rpm, bar,
 *     km/h, %), also named.
 *   - Every component is a params struct + a state struct + an input struct +
 *     an output struct, with three functions:
 *       init    - state at rest / at a given speed
 *       output  - coupling outputs (torques, forces) from state and inputs;
 *                 pure, writes only the output struct
 *       advance - one explicit-Euler step of length h of its own states,
 *                 followed by its discrete events (phase switches, resets)
 *     Components are coupled only through shaft torques and speeds. The
 *     assembly (plant.c) evaluates every output first, then advances every
 *     component: explicit Euler over the whole state.
 *   - State structs hold doubles only (discrete states too), so the whole
 *     plant state is one contiguous array of doubles (dct_state).
 *   - No component reads a clock or allocates memory. Time is a state.
 *   - Rotation: positive = forward driving direction of the car.
 */
#ifndef DCT_PLANT_H
#define DCT_PLANT_H

#define DCT_CURVE_MAX 24
#define DCT_MAP_MAX 12
#define DCT_N_GEARS 7
#define DCT_N_SLEEVES 4

/* status codes returned by dct_plant_* */
#define DCT_OK 0
#define DCT_ERR_INPUT 1
#define DCT_ERR_STATE 2
#define DCT_ERR_PARAM 3

/* synchronizer phases (eqs. 2-4 of the reference paper) */
#define DCT_SYNC_DISENGAGED 0
#define DCT_SYNC_SYNCHRONIZING 1
#define DCT_SYNC_ENGAGED 2

/* gear index in dct_gearbox_params.ratio[] etc.: 0..5 = gears 1..6, 6 = R */
#define DCT_GEAR_R 6

/* selector lever positions (input selector_lever; the codes of the CAN
 * signal VEH_Driver.SelectorLever) */
#define DCT_SELECTOR_P 0
#define DCT_SELECTOR_R 1
#define DCT_SELECTOR_N 2
#define DCT_SELECTOR_D 3

/* ------------------------------------------------------------------ */
/* Shared tables                                                       */
/* ------------------------------------------------------------------ */

/* A torque over speed curve, linear interpolation, held flat outside. */
typedef struct {
    int n;                                 /* points used (filled by the loader) */
    double speed_rpm[DCT_CURVE_MAX];
    double torque_nm[DCT_CURVE_MAX];
} dct_torque_curve;

/* Brake specific fuel consumption map, bilinear, held flat outside. */
typedef struct {
    int n_speed_rpm;
    int n_torque_nm;
    double speed_rpm[DCT_MAP_MAX];
    double torque_nm[DCT_MAP_MAX];
    double bsfc_g_per_kwh[DCT_MAP_MAX][DCT_MAP_MAX]; /* [torque row][speed column] */
} dct_bsfc_map;

/* ------------------------------------------------------------------ */
/* Friction element: reset integrator (Haessig and Friedland 1991)     */
/* with stick-slip and a Stribeck curve. Used by clutches and brakes.  */
/* ------------------------------------------------------------------ */
typedef struct {
    double stiffness_nm_per_rad;    /* stick stiffness of the reset integrator */
    double damping_nms_per_rad;     /* stick damping */
} dct_friction_params;

typedef struct {
    double torque_nm;     /* transmitted torque, positive when it drives the driven side forward */
    double twist_rate_rad_s; /* d(twist)/dt: slip speed while sticking, 0 while sliding */
    double sliding;       /* 1 while sliding at the capacity, 0 while sticking */
} dct_friction_output;

/* slip_rad_s = driving side speed - driven side speed.
 * cap_nm: torque capacity at this slip speed (>= 0); the caller's Stribeck
 * curve makes it the breakaway torque at zero slip, so the transmitted torque
 * is continuous through stick -> slip -> stick. */
void dct_friction_eval(const dct_friction_params *p, double twist_rad, double slip_rad_s,
                       double cap_nm, dct_friction_output *out);
/* Euler step of the twist followed by the reset to the current capacity. */
double dct_friction_advance(const dct_friction_params *p, double twist_rad,
                            const dct_friction_output *out, double cap_nm, double h);

/* ------------------------------------------------------------------ */
/* Engine                                                              */
/* ------------------------------------------------------------------ */
typedef struct {
    double inertia_kgm2;              /* crank, flywheel and clutch drum at the clutch input */
    dct_torque_curve full_load;       /* full-load brake torque over speed */
    dct_torque_curve drag;            /* motoring (drag) torque over speed, <= 0 */
    double turbocharged;              /* 1 turbo: slow boost build-up above na_torque_fraction; 0 NA */
    double na_torque_fraction;        /* share of full-load torque available without boost */
    double tau_rise_s;                /* torque build-up time constant (manifold filling) */
    double tau_boost_s;               /* build-up time constant above the NA share (turbo lag) */
    double tau_fall_s;                /* torque decay time constant (throttle closing; spark retard
                                         and its recovery) */
    double idle_speed_rpm;            /* idle governor target */
    double idle_kp_nm_per_rpm;
    double idle_ki_nm_per_rpm_s;
    double idle_torque_max_nm;        /* governor authority */
    double stall_speed_rpm;           /* below this the engine dies */
    double rev_limit_rpm;             /* fuel cut above */
    double drag_smoothing_rad_s;      /* drag torque fades to 0 at standstill over this speed */
    dct_bsfc_map bsfc;
    double fuel_density_kg_per_l;
    double spark_cut_max_share;       /* a TCU torque request below the driver's is met by spark
                                         retard, the air path (boost) held, up to this share of the
                                         air-path torque; below that the air path follows too */
} dct_engine_params;

typedef struct {
    double speed_rad_s;               /* crank speed (= clutch drum speed) */
    double combustion_torque_nm;      /* lagged air-path combustion torque (what the air and fuel
                                         give at best spark; brake torque minus drag, plus the cut) */
    double idle_integral_nm;          /* idle governor integrator */
    double fuel_g;                    /* fuel burnt */
    double running;                   /* 1 running, 0 stalled / switched off */
    double spark_cut_nm;              /* combustion torque taken off by spark retard (TCU request) */
} dct_engine_state;

typedef struct {
    double accel_pedal_pct;
    double torque_request_nm;         /* TCU torque intervention */
    double torque_request_active;     /* 0/1 */
    double engine_on;                 /* 0/1 ignition */
    double load_torque_nm;            /* torque taken by the clutches (sum) */
    double drag_excess;               /* thermal: drag curve x (1 + this); 0 at the reference */
    double idle_rise_rpm;             /* thermal: added to the idle target */
    double fuel_enrichment;           /* thermal: extra fuel share */
    double accessory_torque_nm;       /* accessories on the crank (>= 0, opposes the rotation) */
} dct_engine_input;

typedef struct {
    double torque_nm;                 /* brake torque on the crank (combustion + drag) */
    double demand_nm;                 /* combustion torque demanded (before the lag) */
    double air_demand_nm;             /* the air path's target (the driver's, or a request above it) */
    double combustion_torque_nm;      /* delivered: the air-path torque minus the spark cut */
    double drag_nm;                   /* drag torque at this speed (<= 0) */
    double fuel_rate_g_s;             /* with the enrichment */
    double burnt_fuel_rate_g_s;       /* without it: what burns */
    double accessory_torque_nm;       /* on the crank (opposes the rotation) */
    double speed_deriv_rad_s2;
} dct_engine_output;

void dct_engine_init(const dct_engine_params *p, dct_engine_state *s, double speed_rad_s, int running);
void dct_engine_output_eval(const dct_engine_params *p, const dct_engine_state *s,
                            const dct_engine_input *in, dct_engine_output *out);
void dct_engine_advance(const dct_engine_params *p, dct_engine_state *s,
                        const dct_engine_input *in, const dct_engine_output *out, double h);
double dct_curve_eval(const dct_torque_curve *c, double speed_rpm);
double dct_bsfc_eval(const dct_bsfc_map *m, double speed_rpm, double torque_nm);

/* ------------------------------------------------------------------ */
/* Wet multi-plate clutch (one of K1/K2)                               */
/* ------------------------------------------------------------------ */
typedef struct {
    double surfaces;                  /* number of friction surfaces */
    double radius_m;                  /* effective friction radius */
    double mu_static;                 /* friction coefficient at zero slip */
    double mu_kinetic;                /* friction coefficient at large slip */
    double stribeck_speed_rad_s;      /* slip speed of the static -> kinetic transition */
    double piston_area_m2;            /* clutch piston */
    double return_spring_n;           /* return spring preload (kiss point = preload / area) */
    double return_spring_n_per_m;     /* return spring rate over the piston travel */
    double pack_gap_mm;               /* piston travel that closes the clutch-pack clearance */
    double pack_stiffness_n_per_m;    /* elastic end stop: axial stiffness of the clamped pack */
    double drag_nms_per_rad;          /* viscous drag of the open wet pack */
    double max_pressure_bar;          /* input range */
    dct_friction_params friction;
} dct_clutch_params;

typedef struct {
    double twist_rad;                 /* reset-integrator state */
} dct_clutch_state;

typedef struct {
    double clamp_force_n;             /* from the piston */
    double drive_speed_rad_s;         /* engine / drum */
    double driven_speed_rad_s;        /* input shaft */
    double drag_excess;               /* thermal: open-pack drag x (1 + this) */
    double mu_excess;                 /* thermal: both friction coefficients x (1 + this) */
} dct_clutch_input;

typedef struct {
    double torque_nm;                 /* on the input shaft (+), reaction on the engine (-) */
    double clamp_force_n;
    double capacity_nm;               /* static capacity */
    double slide_capacity_nm;         /* capacity at this slip (Stribeck) */
    double slip_rad_s;
    double heat_w;                    /* dissipated: sliding friction, stick damping, drag */
    double drag_torque_nm;            /* viscous drag of the open pack (included in torque_nm) */
    double mu_kinetic;                /* kinetic friction coefficient with the thermal factor */
    dct_friction_output friction;
} dct_clutch_output;

/* Clutch piston (massless, the real-time form of the reference paper, eq. 8):
 * from the chamber pressure, the force balance p A = return spring + pack
 * gives the piston position; beyond the pack gap the pack is an elastic end
 * stop whose force is the clamp force. compliance = A dx/dp: the volume the
 * piston takes per unit pressure (the flow that moves it, eq. 8). */
typedef struct {
    double position_m;
    double clamp_force_n;
    double compliance_m3_per_pa;
} dct_piston_output;

void dct_piston_eval(const dct_clutch_params *p, double pressure_pa, dct_piston_output *out);

void dct_clutch_init(const dct_clutch_params *p, dct_clutch_state *s);
void dct_clutch_output_eval(const dct_clutch_params *p, const dct_clutch_state *s,
                            const dct_clutch_input *in, dct_clutch_output *out);
void dct_clutch_advance(const dct_clutch_params *p, dct_clutch_state *s,
                        const dct_clutch_output *out, double h);

/* ------------------------------------------------------------------ */
/* Synchronizer (hybrid three-phase model, eqs. 1-6)                   */
/* ------------------------------------------------------------------ */
typedef struct {
    double cone_mu;                   /* cone friction coefficient */
    double cone_radius_m;             /* mean cone radius r_s */
    double cone_half_angle_deg;       /* alpha */
    double tanh_speed_rad_s;          /* omega_0 of eq. 3 */
    double stiffness_nm_per_rad;      /* k: shaft and gear, at the output shaft */
    double damping_nms_per_rad;       /* b */
    double sleeve_mass_kg;            /* sleeve + fork + rail */
    double sleeve_damping_ns_per_m;
    double cone_travel_mm;            /* neutral to cone contact */
    double engaged_travel_mm;         /* neutral to full engagement */
    double detent_force_n;            /* neutral detent */
    double lock_speed_rad_s;          /* blocker releases below this slip */
    double blocker_force_max_n;       /* fork force that overpowers the blocker */
    double clash_speed_rad_s;         /* engaging above this slip counts as a clash */
    double dog_friction_mu;           /* dog-tooth friction: holds an engaged gear under load */
    double dog_radius_m;              /* r_b: pitch radius of the sleeve, blocker-ring and dog teeth */
    /* ring turn-back: once the blocker releases, the sleeve's chamfers turn the
     * ring, and through its still stuck cone the gear side, back out of the
     * way; until the sleeve has passed the ring its mass includes the gear
     * side's inertia felt through the chamfers, J tan^2(beta) / r_b^2 */
    double ring_chamfer_angle_deg;    /* beta: chamfer face of sleeve and ring teeth from the axis */
    double ring_pass_travel_mm;       /* sleeve travel beyond cone_travel_mm until its chamfers clear the ring's */
} dct_sync_params;

typedef struct {
    double position_m;                /* sleeve travel, + towards the first gear of the pair */
    double velocity_m_s;
    double phase;                     /* DCT_SYNC_* */
    double side;                      /* +1 first gear, -1 second gear, 0 none */
    double twist_rad;                 /* theta_r */
    double clashes;                   /* engagements with a large speed difference */
} dct_sync_state;

typedef struct {
    double fork_force_n;
    double slip_pos_rad_s;            /* first gear speed - shaft speed */
    double slip_neg_rad_s;            /* second gear speed - shaft speed */
    double has_neg;                   /* 0 for the 6-N sleeve */
    double gear_inertia_pos_kgm2;     /* gear side of the first gear, at the gear: what the cone turns
                                       * (loose gear, its input shaft and the gears that mesh with it) */
    double gear_inertia_neg_kgm2;     /* gear side of the second gear (0 for the 6-N sleeve) */
    double fork_jammed;               /* 1: the sleeve is held where it is (fault): it neither
                                         moves nor passes the blocker; the rest evolves */
} dct_sync_input;

typedef struct {
    double torque_nm;                 /* on the output shaft (+), reaction on the idle gear (-) */
    double side;                      /* which gear carries torque_nm */
    double slip_rad_s;                /* omega_r of the addressed gear */
    double cone_torque_nm;            /* T_s of eq. 6 */
} dct_sync_output;

void dct_sync_init(const dct_sync_params *p, dct_sync_state *s, int side_engaged);
void dct_sync_output_eval(const dct_sync_params *p, const dct_sync_state *s,
                          const dct_sync_input *in, dct_sync_output *out);
void dct_sync_advance(const dct_sync_params *p, dct_sync_state *s,
                      const dct_sync_input *in, const dct_sync_output *out, double h);
double dct_sync_cone_torque(const dct_sync_params *p, double force_n);

/* ------------------------------------------------------------------ */
/* Gearbox: two input shafts, two output shafts on one final drive,    */
/* gears 1-6 and R, four sleeves                                       */
/* ------------------------------------------------------------------ */
typedef struct {
    double ratio[DCT_N_GEARS];              /* gears 1..6, R (R entered positive, turns backwards) */
    double final_drive[2];                  /* output shaft 1 (gears 1-4), output shaft 2 (5, 6, R) */
    double mesh_efficiency[DCT_N_GEARS];    /* gear mesh + final drive, per gear */
    double efficiency_smoothing_w;          /* power scale of the driving/coasting switch */
    double input_shaft_inertia_kgm2[2];     /* shaft, clutch hub, fixed gears */
    double idle_gear_inertia_kgm2[DCT_N_GEARS]; /* loose gears on the output shafts */
    double output_shaft_inertia_kgm2[2];
    double differential_inertia_kgm2;       /* ring gear and carrier */
    double input_drag_nm[2];                /* constant bearing drag */
    double input_drag_nms_per_rad[2];       /* viscous churning drag */
    double output_drag_nm;                  /* at the differential */
    double output_drag_nms_per_rad;
    double idle_gear_drag_nms_per_rad;      /* loose gear needle bearing, relative speed */
    double drag_smoothing_rad_s;
    double max_fork_force_n;                /* input range */
    dct_sync_params sync[DCT_N_SLEEVES];    /* sleeves 1-3, 2-4, 5-R, 6-N */
} dct_gearbox_params;

typedef struct {
    double input_speed_rad_s[2];
    double carrier_speed_rad_s;             /* differential carrier; output shafts follow by final drive */
    dct_sync_state sync[DCT_N_SLEEVES];
} dct_gearbox_state;

typedef struct {
    double clutch_torque_nm[2];
    double fork_force_n[DCT_N_SLEEVES];
    double load_torque_nm;                  /* taken from the carrier by the differential */
    double fork_jammed[DCT_N_SLEEVES];      /* 1: that sleeve held where it is (fault) */
    double viscous_drag_excess;             /* thermal: viscous drags x (1 + this) */
    double clutch_damping_nms_per_rad[2];   /* a stuck clutch's damper on its input shaft (0: sliding) */
} dct_gearbox_input;

typedef struct {
    double gear_torque_nm[DCT_N_GEARS];     /* torque each gear puts on its output shaft */
    double input_torque_nm[2];              /* net torque on each input shaft */
    double carrier_torque_nm;               /* net torque on the carrier */
    double output_speed_rad_s[2];
    double power_loss_w;
    /* in a tie-up (two gears engaged on one input shaft) the dampers on the
     * tied shafts and the carrier (engaged synchronizers, a stuck clutch),
     * d(torque)/d(speed), which dct_gearbox_advance takes implicitly; 0
     * otherwise (explicit Euler) */
    double input_damping_nms_per_rad[2];
    double carrier_damping_nms_per_rad;
    dct_sync_output sync[DCT_N_SLEEVES];
    dct_sync_input sync_in[DCT_N_SLEEVES];
} dct_gearbox_output;

/* derived constants, computed once by dct_gearbox_prepare() */
typedef struct {
    double input_inertia_kgm2[2];           /* incl. loose gears reduced to the shaft */
    double gear_side_inertia_kgm2[DCT_N_GEARS]; /* what a synchronizer turns at gear g: its input shaft
                                              (incl. loose gears) reflected through g's ratio */
    double carrier_inertia_kgm2;            /* incl. output shafts reduced to the carrier */
    double signed_ratio[DCT_N_GEARS];       /* R negative */
} dct_gearbox_derived;

/* gear layout of the DSG 02E: input shaft (0/1), output shaft (0/1),
 * sleeve (0..3) and side (+1/-1) of each gear index */
int dct_gear_input_shaft(int gear);
int dct_gear_output_shaft(int gear);
int dct_gear_sleeve(int gear);
int dct_gear_side(int gear);
int dct_sleeve_gear(int sleeve, int side);  /* -1 for none (6-N, negative side) */

void dct_gearbox_prepare(const dct_gearbox_params *p, dct_gearbox_derived *d);
void dct_gearbox_output_eval(const dct_gearbox_params *p, const dct_gearbox_derived *d,
                             const dct_gearbox_state *s, const dct_gearbox_input *in,
                             dct_gearbox_output *out);
void dct_gearbox_advance(const dct_gearbox_params *p, const dct_gearbox_derived *d,
                         dct_gearbox_state *s, const dct_gearbox_input *in,
                         const dct_gearbox_output *out, double h);

/* ------------------------------------------------------------------ */
/* Driveline: open differential, two half-shafts (front-wheel drive)   */
/* ------------------------------------------------------------------ */
typedef struct {
    double left_stiffness_nm_per_rad;
    double left_damping_nms_per_rad;
    double right_stiffness_nm_per_rad;
    double right_damping_nms_per_rad;
    /* powertrain roll: engine and gearbox housings on their mounts, turning
     * about an axis parallel to the shafts; the gear train's reaction (the
     * half-shafts' torque) rolls them against the mounts */
    double powertrain_roll_inertia_kgm2;  /* engine and gearbox about the roll axis */
    double mount_roll_stiffness_nm_per_rad;   /* small roll: the mounts' rubber */
    double mount_roll_damping_nms_per_rad;
    double mount_roll_stop_rad;               /* free roll before the progressive stops take over */
    double mount_roll_stop_stiffness_nm_per_rad; /* added beyond mount_roll_stop_rad */
} dct_driveline_params;

typedef struct {
    double left_twist_rad;
    double right_twist_rad;
    double roll_rad;                  /* powertrain roll, + as the wheels turn forward (the mounts
                                         deflect by roll_rad + the body's pitch, nose up) */
    double roll_rate_rad_s;
} dct_driveline_state;

typedef struct {
    double carrier_speed_rad_s;
    double left_wheel_speed_rad_s;
    double right_wheel_speed_rad_s;
    double body_pitch_rad;            /* the body the mounts sit on (+ nose up) */
    double body_pitch_rate_rad_s;
} dct_driveline_input;

typedef struct {
    double shaft_torque_nm;           /* each half-shaft (equal: open differential) */
    double carrier_load_nm;           /* 2 x shaft torque, taken from the carrier */
    double left_side_speed_rad_s;     /* differential side gears */
    double right_side_speed_rad_s;
    double mount_torque_nm;           /* the mounts' torque on the powertrain (its reaction on the body) */
    double roll_accel_rad_s2;
} dct_driveline_output;

void dct_driveline_init(const dct_driveline_params *p, dct_driveline_state *s);
void dct_driveline_output_eval(const dct_driveline_params *p, const dct_driveline_state *s,
                               const dct_driveline_input *in, dct_driveline_output *out);
void dct_driveline_advance(const dct_driveline_params *p, dct_driveline_state *s,
                           const dct_driveline_input *in, const dct_driveline_output *out, double h);
/* potential energy of the powertrain mounts at this deflection (roll + pitch) */
double dct_driveline_mount_energy(const dct_driveline_params *p, double deflection_rad);

/* ------------------------------------------------------------------ */
/* Tyre: Pacejka magic formula (longitudinal, pure slip) with a        */
/* transient-slip deflection state; spring-damper near standstill      */
/* ------------------------------------------------------------------ */
typedef struct {
    double radius_m;                  /* effective rolling radius */
    double nominal_load_n;            /* Fz0 */
    double pcx1;                      /* shape factor C */
    double pdx1;                      /* peak friction at Fz0 */
    double pdx2;                      /* peak friction load dependency */
    double pex1;                      /* curvature E at Fz0 */
    double pex2;
    double pkx1;                      /* slip stiffness / Fz at Fz0 */
    double pkx2;
    double pkx3;
    double relaxation_length_m;
    double low_speed_damping_ns_per_m; /* contact damping near standstill */
    double low_speed_limit_m_s;       /* the damping fades out up to this speed */
    double carcass_damping_ns_per_m;  /* longitudinal carcass damping, in parallel with its
                                         stiffness (the deflection's spring), per tyre */
    double rolling_resistance;        /* coefficient at low speed */
    double rolling_smoothing_rad_s;   /* rolling resistance fades to 0 at standstill */
    double rolling_resistance_speed;  /* its rise with speed: + this x (V / ref speed)^2.5 */
    double rolling_resistance_ref_speed_m_s;
} dct_tyre_params;

typedef struct {
    double deflection_m;              /* longitudinal carcass deflection (transient slip) */
} dct_tyre_state;

typedef struct {
    double wheel_speed_rad_s;
    double ground_speed_m_s;          /* wheel centre speed along the road */
    double normal_force_n;            /* on all tyres of this wheel position */
    double count;                     /* tyres lumped in this position (1 or 2) */
} dct_tyre_input;

typedef struct {
    double force_n;                   /* longitudinal force on the car (+ forward) */
    double rolling_moment_nm;         /* opposes wheel rotation */
    double slip;                      /* transient slip ratio */
    double slip_speed_m_s;            /* omega R - V */
    double deflection_rate_m_s;
    double contact_weight;            /* 1 at standstill (spring contact), 0 from low_speed_limit */
    double tyre_load_n;               /* normal force per tyre */
} dct_tyre_output;

double dct_magic_formula(const dct_tyre_params *p, double slip, double normal_force_n);
/* the magic formula's coefficients at one tyre load (they hold an exp and
 * divisions; the two front tyres carry the same load and share them) */
typedef struct {
    double fz;                        /* normal force per tyre; <= 0: no force */
    double c, d, e, b;
} dct_tyre_load;
void dct_tyre_load_eval(const dct_tyre_params *p, double normal_force_n, dct_tyre_load *l);
double dct_magic_formula_at(const dct_tyre_load *l, double slip);
double dct_magic_formula_peak_slip(const dct_tyre_params *p, double normal_force_n);
void dct_tyre_init(const dct_tyre_params *p, dct_tyre_state *s);
void dct_tyre_output_eval(const dct_tyre_params *p, const dct_tyre_state *s,
                          const dct_tyre_input *in, dct_tyre_output *out);
/* the same with the load's coefficients given (dct_tyre_load_eval of
 * in->normal_force_n / in->count) */
void dct_tyre_output_eval_at(const dct_tyre_params *p, const dct_tyre_state *s,
                             const dct_tyre_input *in, const dct_tyre_load *load, dct_tyre_output *out);
void dct_tyre_advance(const dct_tyre_params *p, dct_tyre_state *s,
                      const dct_tyre_output *out, double h);
double dct_tyre_deflection_energy(const dct_tyre_params *p, double deflection_m,
                                  double normal_force_n, double count);

/* ------------------------------------------------------------------ */
/* Wheel with friction brake                                           */
/* ------------------------------------------------------------------ */
typedef struct {
    double inertia_kgm2;              /* wheel, tyre, hub, brake disc (all wheels of the position) */
    double brake_torque_max_nm;       /* at 100 % brake pedal */
    dct_friction_params brake;
    double park_lock_torque_nm;       /* holding capacity of the parking lock felt at this wheel
                                         position (0: not driven), added to the brake's */
    double park_lock_max_speed_kmh;   /* the pawl engages only below this speed (wheel speed x
                                         radius); above it ratchets over the parking gear */
} dct_wheel_params;

typedef struct {
    double speed_rad_s;
    double brake_twist_rad;
} dct_wheel_state;

typedef struct {
    double drive_torque_nm;           /* from the half-shaft */
    double tyre_force_n;
    double tyre_radius_m;
    double rolling_moment_nm;
    double brake_pedal_pct;
    double park_lock;                 /* 1: selector lever in P (the pawl is pushed on the gear) */
} dct_wheel_input;

typedef struct {
    double brake_torque_nm;           /* on the wheel, opposes rotation */
    double body_torque_nm;            /* torques the wheel takes from the body side (shaft + brake) */
    double speed_deriv_rad_s2;
    double capacity_nm;               /* friction capacity now: brake and, engaged, parking lock */
    double park_locked;               /* 1: the parking lock is engaged (P, below its speed) */
    dct_friction_output brake;
} dct_wheel_output;

void dct_wheel_init(const dct_wheel_params *p, dct_wheel_state *s, double speed_rad_s);
void dct_wheel_output_eval(const dct_wheel_params *p, const dct_wheel_state *s,
                           const dct_wheel_input *in, dct_wheel_output *out);
void dct_wheel_advance(const dct_wheel_params *p, dct_wheel_state *s,
                       const dct_wheel_input *in, const dct_wheel_output *out, double h);

/* ------------------------------------------------------------------ */
/* Vehicle: 2D body (longitudinal, vertical, pitch), front and rear    */
/* suspension with spindle masses, aerodynamic drag, road grade        */
/* ------------------------------------------------------------------ */
typedef struct {
    double mass_kg;                   /* whole car incl. unsprung masses and driver */
    double front_unsprung_kg;         /* both front spindles, wheels, brakes */
    double rear_unsprung_kg;
    double pitch_inertia_kgm2;        /* sprung mass about the CG */
    double cg_height_m;
    double wheelbase_m;
    double cg_to_front_axle_m;
    double drag_coefficient;
    double frontal_area_m2;
    double air_density_kg_m3;
    double front_spring_n_per_m;      /* per axle */
    double front_damper_ns_per_m;
    double rear_spring_n_per_m;
    double rear_damper_ns_per_m;
    double front_tyre_vertical_n_per_m; /* per axle */
    double rear_tyre_vertical_n_per_m;
    double tyre_vertical_damping_ns_per_m; /* per axle */
    double wheel_centre_height_m;     /* = tyre radius; lever of the tyre forces */
    double gravity_m_s2;
} dct_vehicle_params;

typedef struct {
    double position_m;
    double speed_m_s;
    double heave_m;                   /* body CG vertical, from static equilibrium on level road */
    double heave_rate_m_s;
    double pitch_rad;                 /* + nose up */
    double pitch_rate_rad_s;
    double front_spindle_m;
    double front_spindle_rate_m_s;
    double rear_spindle_m;
    double rear_spindle_rate_m_s;
} dct_vehicle_state;

typedef struct {
    double front_tyre_force_n;        /* sum of the front tyres */
    double rear_tyre_force_n;
    double front_wheel_torque_nm;     /* torques the front wheels take from the body side */
    double rear_wheel_torque_nm;
    double road_grade_pct;
} dct_vehicle_input;

typedef struct {
    double front_normal_force_n;      /* axle */
    double rear_normal_force_n;
    double accel_m_s2;
    double aero_force_n;
    double front_suspension_force_n;
    double rear_suspension_force_n;
    double heave_accel_m_s2;
    double pitch_accel_rad_s2;
    double front_spindle_accel_m_s2;
    double rear_spindle_accel_m_s2;
} dct_vehicle_output;

void dct_vehicle_init(const dct_vehicle_params *p, dct_vehicle_state *s, double speed_m_s);
void dct_vehicle_output_eval(const dct_vehicle_params *p, const dct_vehicle_state *s,
                             const dct_vehicle_input *in, dct_vehicle_output *out);
void dct_vehicle_advance(const dct_vehicle_params *p, dct_vehicle_state *s,
                         const dct_vehicle_input *in, const dct_vehicle_output *out, double h);
/* static normal forces on level road, per axle */
double dct_vehicle_static_front_n(const dct_vehicle_params *p);
double dct_vehicle_static_rear_n(const dct_vehicle_params *p);
/* tyre normal forces per axle from the state alone (needed before the tyres) */
void dct_vehicle_tyre_loads(const dct_vehicle_params *p, const dct_vehicle_state *s,
                            double road_grade_pct, double *front_n, double *rear_n);
double dct_vehicle_energy(const dct_vehicle_params *p, const dct_vehicle_state *s,
                          double road_grade_pct);

/* ------------------------------------------------------------------ */
/* Clutch hydraulics: line pressure supply, a proportional pressure     */
/* control valve per clutch, the clutch chamber (reference paper,       */
/* sections 3 and "Component models": eqs. 8-14)                        */
/* ------------------------------------------------------------------ */
typedef struct {
    double density_kg_m3;             /* at atmospheric pressure */
    double viscosity_m2_s;            /* kinematic, at operating temperature */
    double bulk_modulus_pa;           /* air-free oil */
    double air_fraction;              /* entrained air volume share at atmospheric pressure */
} dct_oil_params;

/* pressure over current, linear interpolation, held flat outside */
typedef struct {
    int n;
    double current_a[DCT_CURVE_MAX];
    double pressure_bar[DCT_CURVE_MAX];
} dct_pressure_map;

typedef struct {
    dct_pressure_map line;            /* line pressure over line-solenoid current */
    double tau_s;                     /* pressure regulator and pump lag */
    double max_current_a;
    double pump_displacement_cm3;     /* the transmission's oil pump, per crank revolution (it is
                                         driven by the engine): its torque on the crank is
                                         line pressure x displacement / (2 pi efficiency) */
    double pump_efficiency;           /* hydromechanical */
} dct_supply_params;

typedef struct {
    double solenoid_gain_n_per_a;     /* k_f of eq. 9 */
    double solenoid_tau_s;            /* tau_e of eq. 9 */
    double max_current_a;
    double spool_mass_kg;             /* spool + armature */
    double spring_n_per_m;
    double spring_preload_n;          /* current below preload / k_f gives no pressure */
    double spool_diameter_mm;         /* d_s: feedback land */
    double rod_diameter_mm;           /* d_r: feedback area = pi/4 (d_s^2 - d_r^2) */
    double spool_travel_mm;           /* end stops at +- travel */
    double overlap_mm;                /* land overlap of both metering edges (< 0: underlap) */
    double edge_width_mm;             /* width of the metering notches (at most pi d_s) */
    double viscous_friction_ns_per_m;
    double coulomb_friction_n;
    double friction_speed_m_s;        /* Coulomb friction smoothing */
    double friction_tau_s;            /* lag of the friction velocity, eq. 10 */
    double stop_stiffness_n_per_m;
    double stop_damping_ns_per_m;
    double cd_max;                    /* eq. 11 */
    double transition_reynolds;       /* eq. 11 */
    double leakage_m3_per_s_per_pa;   /* laminar leakage across each land */
} dct_valve_params;

typedef struct {
    double pressure_commanded;        /* 1: clutch pressures are plant inputs, no hydraulics */
    double substeps;                  /* hydraulic sub-steps per plant sub-step */
    dct_oil_params oil;
    dct_supply_params supply;
    dct_valve_params valve;           /* K1 and K2 valves are the same part */
    double chamber_volume_cm3[2];     /* oil between valve and piston, K1, K2 */
} dct_hydraulics_params;

typedef struct {
    double solenoid_force_n;
    double spool_position_m;          /* + opens supply -> clutch, - opens clutch -> tank */
    double spool_velocity_m_s;
    double friction_velocity_m_s;     /* lagged spool velocity, eq. 10 */
} dct_valve_state;

typedef struct {
    double line_pressure_pa;
    double clutch_oil_m3[2];          /* oil volume fed into each clutch chamber (0: at atmospheric) */
    dct_valve_state valve[2];
} dct_hydraulics_state;

typedef struct {
    double current_a;
    double supply_pa;
    double control_pa;                /* the controlled (clutch) pressure, fed back on the spool */
} dct_valve_input;

typedef struct {
    double flow_m3_s;                 /* into the clutch chamber (eq. 14 included) */
    double supply_flow_m3_s;          /* through the supply edge */
    double tank_flow_m3_s;            /* through the tank edge */
    double spool_accel_m_s2;
    double solenoid_force_rate_n_s;
    double friction_accel_m_s2;       /* d(friction velocity)/dt */
} dct_valve_output;

/* eqs. 11-13: flow through a sharp-edged slot of width width_m opened by
 * opening_m (<= 0: closed; narrow: hydraulic diameter 2 x opening), p1 to p2 */
double dct_orifice_flow(const dct_oil_params *oil, double cd_max, double transition_reynolds,
                        double width_m, double opening_m, double p1_pa, double p2_pa);
/* Clutch chamber: the oil volume that must be fed in to reach pressure p
 * (compressing the oil and its entrained air, stroking the piston), and its
 * inverse. Volume, not pressure, is the chamber's state: it is what the
 * flow integrates, so the fill conserves oil however fast the compliance
 * changes (nearly rigid before the piston moves, soft while it strokes,
 * stiff once the pack is clamped). */
double dct_chamber_volume(const dct_oil_params *oil, const dct_clutch_params *clutch,
                          double chamber_m3, double pressure_pa);
typedef struct {
    double min_m3;                    /* volume at the lowest pressure (vapour) */
    double kiss_m3;                   /* volume when the piston starts to move */
    double closed_m3;                 /* volume when the pack gap is closed */
    double oil_m3_per_pa;             /* V_c (1 - a) / beta */
    double air_m3;                    /* a V_c */
    double stroke_m3_per_pa;          /* A dx/dp while stroking, and its offset */
    double stroke_m3;
    double clamped_m3_per_pa;         /* A dx/dp once clamped, and its offset */
    double clamped_m3;
} dct_chamber_derived;

void dct_chamber_prepare(const dct_oil_params *oil, const dct_clutch_params *clutch,
                         double chamber_m3, dct_chamber_derived *d);
double dct_chamber_pressure(const dct_chamber_derived *d, double volume_m3);
double dct_pressure_map_eval(const dct_pressure_map *m, double current_a);
void dct_valve_init(const dct_valve_params *p, dct_valve_state *s);
void dct_valve_output_eval(const dct_valve_params *p, const dct_oil_params *oil,
                           const dct_valve_state *s, const dct_valve_input *in,
                           dct_valve_output *out);
void dct_valve_advance(const dct_valve_params *p, dct_valve_state *s,
                       const dct_valve_output *out, double h);

typedef struct {
    double current_a[2];              /* clutch valve solenoids */
    double line_current_a;
    double spool_stuck[2];            /* 1: that valve's spool held where it is (fault); its
                                         edges still meter at the held opening */
    double oil_viscosity_m2_s;        /* thermal: the oil's viscosity now (<= 0: oil.viscosity_m2_s) */
    double pressure_known;            /* 1: pressure_pa holds the chambers' pressures at the state
                                         (dct_hydraulics_output_eval's): the first sub-step takes them */
    double pressure_pa[2];
} dct_hydraulics_input;

typedef struct {
    double clamp_force_n[2];
    double piston_position_m[2];
    double clutch_pressure_pa[2];
} dct_hydraulics_output;

typedef struct {
    dct_chamber_derived chamber[2];
} dct_hydraulics_derived;

void dct_hydraulics_prepare(const dct_hydraulics_params *p, const dct_clutch_params clutch[2],
                            dct_hydraulics_derived *d);
void dct_hydraulics_init(const dct_hydraulics_params *p, dct_hydraulics_state *s);
/* the coupling outputs (clamp forces) from the state */
void dct_hydraulics_output_eval(const dct_hydraulics_params *p, const dct_hydraulics_derived *d,
                                const dct_clutch_params clutch[2], const dct_hydraulics_state *s,
                                dct_hydraulics_output *out);
/* advances supply, valves and chambers over h in params.substeps sub-steps */
void dct_hydraulics_advance(const dct_hydraulics_params *p, const dct_hydraulics_derived *d,
                            dct_hydraulics_state *s, const dct_hydraulics_input *in, double h);

/* ------------------------------------------------------------------ */
/* Thermal: lumped engine coolant, engine oil and transmission oil     */
/* temperatures, and what depends on them (thermal.c)                  */
/* ------------------------------------------------------------------ */
typedef struct {
    double ambient_temp_degc;             /* air around the car and through the radiator */
    double initial_coolant_temp_degc;     /* at a reset that does not give temperatures */
    double initial_engine_oil_temp_degc;
    double initial_trans_oil_temp_degc;
    /* engine heat: the fuel's energy not turned into combustion work goes
     * partly through the walls (the rest leaves with the exhaust); the
     * engine's friction work stays in the engine */
    double fuel_lhv_j_per_g;              /* lower heating value of the fuel */
    double wall_heat_fraction;            /* share of the fuel's unused energy into the walls */
    double friction_heat_oil_share;       /* share of the friction heat into the engine oil (rest coolant) */
    double coolant_heat_capacity_j_per_k; /* coolant and the engine metal it wets */
    double engine_oil_heat_capacity_j_per_k;
    double oil_coolant_ua_w_per_k;        /* engine oil - coolant heat exchanger */
    double engine_ambient_ua_w_per_k;     /* engine block and sump to the air */
    double thermostat_open_degc;          /* starts to open */
    double thermostat_full_degc;          /* fully open */
    double thermostat_min_opening;        /* share of the radiator flow while closed (bypass, leak) */
    double radiator_ua_w_per_k;           /* radiator at standstill (fan), fully open */
    double radiator_ua_per_speed_ws_per_km; /* ram air: added per m/s of vehicle speed, W/K per m/s */
    /* transmission: clutch slip and gearbox losses heat its oil; an
     * oil - coolant cooler and the housing reject it */
    double trans_heat_capacity_j_per_k;   /* DSG fluid and the housing, clutches and mechatronic it wets */
    double trans_cooler_ua_w_per_k;       /* transmission oil - engine coolant cooler */
    double trans_ambient_ua_w_per_k;      /* housing to the air at standstill */
    double trans_ambient_ua_per_speed_ws_per_km; /* added per m/s of vehicle speed, W/K per m/s */
    /* oil viscosities: Walther (ASTM D341) through two data points */
    double engine_oil_viscosity_40c_mm2_s;
    double engine_oil_viscosity_100c_mm2_s;
    double trans_oil_viscosity_40c_mm2_s;
    double trans_oil_viscosity_100c_mm2_s;
    /* engine: engine.drag holds at engine_ref_temp_degc (engine oil) */
    double engine_ref_temp_degc;
    double engine_rubbing_share;          /* share of the drag curve that is rubbing friction (rest: pumping) */
    double engine_friction_viscosity_exponent; /* rubbing friction ~ (nu / nu_ref)^n */
    double idle_warm_degc;                /* coolant: no idle rise and no enrichment from here up */
    double idle_cold_degc;                /* coolant: full idle rise and enrichment from here down */
    double idle_cold_rise_rpm;            /* idle target raised by this when cold */
    double cold_enrichment;               /* extra fuel share when cold (warm-up enrichment) */
    /* transmission: clutch.*, gearbox drags and hydraulics.oil.viscosity_m2_s
     * hold at trans_ref_temp_degc (transmission oil) */
    double trans_ref_temp_degc;
    double clutch_drag_viscosity_exponent;   /* open-pack drag ~ (nu / nu_ref)^n (Couette shear: 1) */
    double churning_viscosity_exponent;      /* viscous gearbox drags ~ (nu / nu_ref)^n */
    double clutch_mu_change_per_k;        /* relative change of the friction coefficients per K above the reference */
    /* clutch pack clearance: the aluminium parts that hold the pack (piston
     * bore, carrier) expand more than its steel plates, so the gap the
     * piston closes grows with the oil temperature:
     *   gap(T) = gap + (alpha_housing - alpha_plates) L (T - trans_ref_temp_degc) */
    double clutch_gap_expansion_per_k;    /* alpha_housing - alpha_plates, 1/K */
    double clutch_gap_length_mm;          /* L: effective axial length of the pack and its seat */
    /* the effects are taken at the temperatures rounded to this (0: as
     * they are): they move by millikelvin a second, and the rounded ones
     * change every few hundred steps, so the step computes the effects
     * (Walther, the pack gaps' chamber law) again only then */
    double effects_resolution_k;
    /* accessories on the crank */
    double alternator_load_w;             /* electrical load */
    double alternator_efficiency;
    double power_steering_nm;             /* engine-driven power steering pump */
    double ac_on;                         /* 0/1: A/C compressor engaged */
    double ac_torque_nm;                  /* A/C compressor torque while engaged */
    double accessory_smoothing_rad_s;     /* accessory torques fade to 0 at standstill over this speed */
} dct_thermal_params;

typedef struct {
    double coolant_temp_degc;
    double engine_oil_temp_degc;
    double trans_oil_temp_degc;
} dct_thermal_state;

/* what the temperatures do to the other components (from the state alone) */
typedef struct {
    double engine_drag_factor;            /* engine.drag x this */
    double idle_rise_rpm;                 /* added to engine.idle_speed_rpm */
    double fuel_enrichment;               /* extra fuel share */
    double trans_viscosity_ratio;         /* nu(T) / nu(T_ref) of the transmission oil */
    double trans_oil_viscosity_m2_s;      /* hydraulics.oil.viscosity_m2_s x the ratio */
    double engine_oil_viscosity_ratio;
    double clutch_drag_factor;
    double churning_factor;
    double clutch_mu_factor;              /* mu_static and mu_kinetic x this */
    double clutch_gap_change_mm;          /* added to both clutches' pack_gap_mm (thermal expansion) */
    double thermostat_opening;            /* 0..1 */
} dct_thermal_effects;

typedef struct {
    double fuel_heat_w;                   /* fuel burnt (without enrichment) x LHV */
    double combustion_power_w;            /* combustion torque x crank speed */
    double friction_power_w;              /* engine drag power (>= 0) */
    double trans_heat_w;                  /* clutch slip and gearbox losses */
    double vehicle_speed_m_s;
} dct_thermal_input;

typedef struct {
    double coolant_heat_in_w;             /* from the engine */
    double engine_oil_heat_in_w;
    double trans_heat_in_w;
    double radiator_w;                    /* rejected to the air */
    double engine_ambient_w;
    double trans_ambient_w;
    double oil_to_coolant_w;              /* engine oil -> coolant */
    double trans_to_coolant_w;            /* transmission oil -> coolant (cooler) */
    double coolant_rate_k_s;
    double engine_oil_rate_k_s;
    double trans_oil_rate_k_s;
} dct_thermal_output;

/* an oil's Walther line, the terms that do not depend on the temperature
 * (dct_walther_line): log10 log10 (nu + 0.7) at 40 and 100 degC and log10 of
 * those temperatures in kelvin */
typedef struct {
    double w40;                       /* log10 log10 (nu40 + 0.7) */
    double dw;                        /* w100 - w40 */
    double l40;                       /* log10 (313.15 K) */
    double dl;                        /* log10 (373.15 K) - l40 */
} dct_walther_line;

/* the oils' Walther lines and viscosities at their reference temperatures,
 * computed once */
typedef struct {
    double engine_oil_ref_mm2_s;
    double trans_oil_ref_mm2_s;
    dct_walther_line engine_oil;
    dct_walther_line trans_oil;
} dct_thermal_derived;

/* Walther (ASTM D341): kinematic viscosity in mm2/s at temp_degc through
 * (40 degC, nu40) and (100 degC, nu100); dct_walther_at the same from the
 * line computed once (the same number, four logarithms fewer a call) */
double dct_walther_viscosity(double nu40_mm2_s, double nu100_mm2_s, double temp_degc);
void dct_walther_line_of(double nu40_mm2_s, double nu100_mm2_s, dct_walther_line *line);
double dct_walther_at(const dct_walther_line *line, double temp_degc);
void dct_thermal_init(const dct_thermal_params *p, dct_thermal_state *s, double coolant_degc,
                      double engine_oil_degc, double trans_oil_degc);
void dct_thermal_prepare(const dct_thermal_params *p, dct_thermal_derived *d);
/* the temperatures the effects are taken at: coolant, engine oil,
 * transmission oil rounded to p->effects_resolution_k */
void dct_thermal_effects_key(const dct_thermal_params *p, const dct_thermal_state *s, double key[3]);
void dct_thermal_effects_eval(const dct_thermal_params *p, const dct_thermal_derived *d,
                              const dct_oil_params *trans_oil, const dct_thermal_state *s,
                              dct_thermal_effects *fx);
void dct_thermal_output_eval(const dct_thermal_params *p, const dct_thermal_state *s,
                             const dct_thermal_effects *fx, const dct_thermal_input *in,
                             dct_thermal_output *out);
void dct_thermal_advance(const dct_thermal_params *p, dct_thermal_state *s,
                         const dct_thermal_output *out, double h);

/* ------------------------------------------------------------------ */
/* Assembly                                                            */
/* ------------------------------------------------------------------ */
typedef struct {
    double step_s;                    /* fixed step (0.5 ms) */
    double substeps;                  /* Euler sub-steps per step (whole plant) */
} dct_solver_params;

typedef struct {
    dct_solver_params solver;
    dct_engine_params engine;
    dct_clutch_params clutch[2];      /* K1 (input shaft 1: gears 1 3 5 R), K2 (2 4 6) */
    dct_hydraulics_params hydraulics;
    dct_gearbox_params gearbox;
    dct_driveline_params driveline;
    dct_wheel_params front_wheel;     /* one front wheel */
    dct_wheel_params rear_wheels;     /* both rear wheels lumped */
    dct_tyre_params tyre;
    dct_vehicle_params vehicle;
    dct_thermal_params thermal;
} dct_params;

/* The whole state: doubles only, one contiguous array. */
typedef struct {
    double time_s;
    dct_engine_state engine;
    dct_clutch_state clutch[2];
    dct_hydraulics_state hydraulics;
    dct_gearbox_state gearbox;
    dct_driveline_state driveline;
    dct_wheel_state wheel[3];         /* front left, front right, rear axle */
    dct_tyre_state tyre[3];
    dct_vehicle_state vehicle;
    dct_thermal_state thermal;
} dct_state;

/* Plant inputs (what a TCU, a driver and the road give). */
typedef struct {
    double accel_pedal_pct;
    double brake_pedal_pct;
    double solenoid_current1_a;       /* K1 pressure valve */
    double solenoid_current2_a;       /* K2 pressure valve */
    double line_solenoid_current_a;   /* line pressure valve */
    double clutch1_pressure_bar;      /* used only when hydraulics.pressure_commanded = 1 */
    double clutch2_pressure_bar;
    double fork_force1_n;             /* sleeve 1-3: + gear 1, - gear 3 */
    double fork_force2_n;             /* sleeve 2-4: + gear 2, - gear 4 */
    double fork_force3_n;             /* sleeve 5-R: + gear 5, - gear R */
    double fork_force4_n;             /* sleeve 6-N: + gear 6, - neutral */
    double road_grade_pct;
    double engine_torque_request_nm;
    double torque_request_active;
    double engine_on;
    double selector_lever;            /* DCT_SELECTOR_*: 0 P, 1 R, 2 N, 3 D (default D); P engages
                                         the parking lock on the driven wheels */
} dct_inputs;

/* Plant outputs, refreshed after every step. */
typedef struct {
    double time_s;
    double engine_speed_rpm;
    double engine_torque_nm;
    double engine_running;
    double input_shaft1_speed_rpm;
    double input_shaft2_speed_rpm;
    double output_shaft1_speed_rpm;
    double output_shaft2_speed_rpm;
    double solenoid_current1_a;       /* as applied (limited to the valve's range) */
    double solenoid_current2_a;
    double line_solenoid_current_a;
    double line_pressure_bar;
    double clutch1_pressure_bar;      /* clutch chamber pressure */
    double clutch2_pressure_bar;
    double piston1_position_mm;
    double piston2_position_mm;
    double spool1_position_mm;
    double spool2_position_mm;
    double clutch1_clamp_force_n;
    double clutch2_clamp_force_n;
    double clutch1_torque_nm;
    double clutch2_torque_nm;
    double clutch1_slip_rpm;
    double clutch2_slip_rpm;
    double clutch1_capacity_nm;
    double clutch2_capacity_nm;
    double vehicle_speed_kmh;
    double vehicle_accel_mps2;
    double distance_m;
    double pitch_deg;
    double heave_mm;
    double sync1_state;
    double sync2_state;
    double sync3_state;
    double sync4_state;
    double sync1_gear;                /* gear the sleeve addresses: 1..6, -1 for R, 0 none */
    double sync2_gear;
    double sync3_gear;
    double sync4_gear;
    double fork1_position_mm;
    double fork2_position_mm;
    double fork3_position_mm;
    double fork4_position_mm;
    double gear_clashes;
    double fuel_l;
    double fuel_rate_lph;
    double wheel_speed_fl_rpm;
    double wheel_speed_fr_rpm;
    double wheel_speed_rear_rpm;
    double halfshaft_torque_nm;
    double front_tyre_slip;
    double front_axle_load_n;
    double rear_axle_load_n;
    double brake_torque_nm;           /* all wheels */
    double road_grade_pct;
    double accel_pedal_pct;           /* as applied */
    double brake_pedal_pct;
    double input_clamps;              /* inputs limited to their range so far */
    double coolant_temp_degc;         /* engine coolant */
    double engine_oil_temp_degc;
    double trans_oil_temp_degc;       /* transmission (DSG) oil */
    double thermostat_opening;        /* 0..1 */
    double engine_heat_in_w;          /* into coolant and engine oil */
    double trans_heat_in_w;           /* into the transmission oil: clutch slip, gearbox losses */
    double heat_rejected_w;           /* radiator, engine and gearbox housings to the air */
    double trans_oil_viscosity_mm2_s; /* kinematic, at trans_oil_temp_degc */
    double accessory_torque_nm;       /* alternator, power steering, A/C on the crank */
    double gear;                      /* engaged gear: 1..6, -1 R, 0 none. The gear engaged (its
                                         synchronizer engaged) on the active input shaft: the shaft
                                         whose clutch carries the drive torque (of the clamped
                                         clutches, capacity >= 2 Nm, the one with the larger torque,
                                         if >= 2 Nm) or, while none does (both clutches open in a
                                         coast downshift or at standstill, the torque of the closed
                                         clutch crossing zero while coasting), the shaft that
                                         carried it last. 0 before any clutch has carried torque
                                         since the reset (unless it locked a clutch in gear), or
                                         when the active shaft has no gear engaged */
    double selector_lever;            /* as applied: 0 P, 1 R, 2 N, 3 D */
    double park_lock_engaged;         /* 1: the parking lock holds the driven wheels */
    double clutch1_kiss_pressure_bar; /* chamber pressure at which the pack closes now (gap at
                                         this oil temperature, with the kiss-drift fault) */
    double clutch2_kiss_pressure_bar;
    double clutch1_friction_coeff;    /* kinetic friction coefficient now (temperature, fade) */
    double clutch2_friction_coeff;
    double clutch1_drag_torque_nm;    /* viscous drag of the open wet pack (in clutch1_torque_nm) */
    double clutch2_drag_torque_nm;
    double trans_pump_torque_nm;      /* the transmission's oil pump on the crank (not in
                                         accessory_torque_nm) */
} dct_outputs;

/* Physical faults (failure simulation, rt_loop's fault table or a test):
 * all zero is the healthy car. The plant reads them in one place
 * (faults.c): dct_plant_prepare turns the parametric ones into the
 * parameters the step uses (dct_plant.effective), the step turns the others
 * into its components' inputs (a spool or a sleeve held, a solenoid without
 * current). Set them, then call dct_plant_prepare: it checks them and puts
 * all of them in effect at once (dct_derived.faults), or refuses them
 * (DCT_ERR_PARAM, error_index = the index in doubles into dct_faults of the
 * first bad value) and leaves the faults in effect as they were. */
typedef struct {
    double spool_stuck[2];            /* 1: the K1 / K2 valve's spool does not move (held where it is) */
    double solenoid_open[2];          /* 1: open circuit: no current in the K1 / K2 valve solenoid */
    double friction_loss[2];          /* share of the K1 / K2 friction coefficients lost (fade), 0..1 */
    double pack_gap_offset_mm[2];     /* added to the K1 / K2 pack gap (kiss point drift) */
    double line_pressure_loss;        /* share of the line pressure lost (supply failing), 0..1 */
    double fork_jammed[DCT_N_SLEEVES];     /* 1: the sleeve does not move (held where it is) */
    double blocker_failed[DCT_N_SLEEVES];  /* 1: the blocker ring does not block: the sleeve
                                              engages without synchronizing */
    double engine_torque_limited;     /* 1: engine torque limited (limp home): the full-load
                                         curve capped at engine_torque_max_nm, so the brake
                                         torque never exceeds it, pedal or TCU request */
    double engine_torque_max_nm;      /* >= 0 */
} dct_faults;

/* faults.c. Ranges: the flags (stuck, open, jammed, failed, limited) 0..1,
 * in effect above 0.5; the losses 0..1; pack gap + offset >= 0;
 * engine_torque_max_nm >= 0; every value finite. */
/* DCT_OK, or DCT_ERR_PARAM with *bad_index = the first bad value's index
 * in doubles into dct_faults */
int dct_faults_check(const dct_faults *faults, const dct_params *params, int *bad_index);
/* checks the faults, then effective = params with the parametric faults
 * applied and in_effect = faults; refused: nothing written */
int dct_faults_prepare(const dct_faults *faults, const dct_params *params, dct_params *effective,
                       dct_faults *in_effect, int *bad_index);
/* an open solenoid circuit: no current in that valve, whatever is commanded */
void dct_faults_apply_inputs(const dct_faults *in_effect, dct_inputs *applied);
/* a stuck spool, a jammed fork: the hydraulics and gearbox inputs of one
 * evaluation (written in full, 0 or 1) */
void dct_faults_apply_couplings(const dct_faults *in_effect, dct_hydraulics_input *hydraulics_in,
                                dct_gearbox_input *gearbox_in);

/* Initial conditions for dct_plant_reset(). */
typedef struct {
    double vehicle_speed_kmh;
    double sleeve_side[DCT_N_SLEEVES]; /* +1 / -1 engaged, 0 neutral */
    double clutch_locked[2];          /* 1: engine speed follows that input shaft */
    double engine_on;
    double temperatures_given;        /* 1: the three temperatures below; 0: thermal.initial_* */
    double coolant_temp_degc;
    double engine_oil_temp_degc;
    double trans_oil_temp_degc;
} dct_initial;

typedef struct {
    dct_gearbox_derived gearbox;
    dct_hydraulics_derived hydraulics;
    dct_thermal_derived thermal;
    double front_static_n;            /* static axle loads on level road */
    double rear_static_n;
    dct_faults faults;                /* the faults dct_plant_prepare accepted: those in effect */
    double faults_on;                 /* 1: any of them is not zero (0: the step skips them) */
} dct_derived;

/* what the temperatures change (plant.c evaluate_thermal), kept from the
 * step that computed it: the effects, the clutches with their pack gaps and
 * the chamber law that goes with them, valid while the rounded temperatures
 * (dct_thermal_effects_key) stay key. A function of the state alone: a
 * restored state finds the same numbers. */
typedef struct {
    double valid;                     /* 0: compute at the next step (reset, dct_plant_prepare) */
    double key[3];
    dct_thermal_effects fx;
    dct_clutch_params clutch[2];
    double own_chambers;              /* 1: chambers below; 0: derived.hydraulics (gaps as given) */
    dct_hydraulics_derived chambers;
} dct_thermal_cache;

typedef struct {
    dct_params params;
    dct_derived derived;
    dct_state state;
    dct_inputs inputs;
    dct_outputs outputs;
    int error_index;                  /* index into inputs or state of the first bad value (or
                                         into faults: a fault dct_plant_prepare refused) */
    double step_count;                /* steps since reset */
    double input_clamps;              /* inputs limited to their range since reset */
    double active_shaft;              /* input shaft (0 K1, 1 K2) whose clutch carried the drive
                                         torque last, updated after each step (output gear);
                                         -1: none since the reset */
    dct_inputs applied;               /* the inputs as limited and used by the last step */
    dct_faults faults;                /* physical faults to put in effect (all zero: none), by
                                         dct_plant_prepare */
    dct_params effective;             /* params with the parametric faults applied: what the
                                         step uses (set by dct_plant_prepare) */
    dct_thermal_cache thermal;        /* the temperatures' effects (plant.c evaluate_thermal) */
} dct_plant;

int dct_plant_init(dct_plant *plant);            /* checks params, prepares, resets to rest */
/* checks params and faults, builds effective (params with the faults
 * applied) and computes the derived values again, the state untouched:
 * after a parameter or a fault changed while running (DCT_ERR_PARAM:
 * refused, effective and the derived values left as they were) */
int dct_plant_prepare(dct_plant *plant);
int dct_plant_reset(dct_plant *plant, const dct_initial *init);
int dct_plant_step(dct_plant *plant, int n);     /* n steps of params.solver.step_s */
void dct_plant_update_outputs(dct_plant *plant);
double dct_plant_energy(const dct_plant *plant); /* stored energy: kinetic + springs + gravity */
int dct_plant_state_size(void);                   /* doubles in dct_state */
int dct_plant_input_size(void);

#endif
