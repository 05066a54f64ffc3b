"""The reference TCU of the DSG 02E, written once and free of I/O.

``TcuLogic.step(t_s, sensors)`` runs every ``PERIOD_S`` (2 ms). ``sensors``
holds the DBC signals of the plant messages (EngineSpeed, InputShaft1Speed,
..., SyncState1..4, AccelPedal, BrakePedal, EngineTorque) plus ``stale``
(True when a plant message is missing or was rejected). The result holds the
TCU command signals (SolenoidCurrent1/2, LineSolenoidCurrent, ForkForce1..4,
EngineTorqueRequest, TorqueRequestActive) and TargetGear (``target_gear``, for
the engine and the bench; the plant does not act on it).

Control structure, from the top:

1. Phase machine (``phase``): ``standstill`` (clutches open, 1st and 2nd
   pre-selected), ``launch`` (the clutch slips and holds the engine at a
   speed that rises with the pedal, then locks), ``drive`` (a clutch locked
   in ``gear``), ``upshift_torque`` / ``upshift_inertia`` (clutch-to-clutch
   power upshift), ``downshift_inertia`` / ``downshift_torque``
   (clutch-to-clutch downshift under power, e.g. kick-down; coasting, both
   clutches open while a torque request blips the engine up to the lower
   gear's shaft, then the on-coming clutch closes), ``stale``
   (plant messages missing: both clutches open, 0 A; when they return the
   TCU picks the gear for the speed and closes its clutch by slip control),
   ``shift_open`` (an interrupted shift: both clutches open, the engine held
   at the new gear's shaft speed by a torque request, then ``launch`` closes
   the clutch by slip control: the shift into a gear of the same half, and
   the way out of a gear the diagnostics took away), ``safe`` (the safe
   state: both clutches open, no fork force, no torque request, held until
   reset).
2. Shift schedule: up and down engine-speed lines over the pedal, turned
   into vehicle-speed thresholds per gear; the down line sits well below the
   up line divided by the gear step (hysteresis). Kick-down at full pedal
   goes down as far as the engine stays below ``KICKDOWN_MAX_RPM``.
3. Pre-selection: the gear next to ``gear`` (up when driving, down when
   slowing) is synchronised on the idle input shaft by fork force; the
   sleeve that carries another gear of that shaft is pushed to neutral
   first (a position loop designed for the 10 ms fork messages, so it does
   not overshoot onto the other cone);
   a sleeve that is synchronising is never released before it engages; a
   shift starts only when ForkPosition and SyncState say the new gear is
   engaged.
4. Clutch torque -> pressure through the TCU's clutch model (kiss point
   and Nm per bar), pressure -> current through the valve characteristic
   (feed-forward) plus PI feedback on the measured ClutchPressure; a fill
   pulse strokes an empty piston before the first torque.
5. Engine interventions through EngineTorqueRequest (it replaces the
   pedal demand): the torque cut of the inertia phase of an upshift, the
   blip of a coast downshift, and a traction limit (feed-forward from the
   tyre force the front axle carries, trimmed on the driven-wheel slip seen
   as output-shaft speed against VehicleSpeed) while launching and driving.

The schedule and the slip estimate use the output shaft speed (wheel speed
as the gearbox sees it), not VehicleSpeed, so a spinning wheel cannot keep
the engine on the rev limiter. ``events`` lists every shift started.

Diagnostics (tcu_stub/diagnostics.py, ``self.diag``): monitors of the input
shaft speeds, the clutch and line pressures, clutch slip, gear engagement and
the plant messages set trouble codes (TCU_Status.ActiveFaults) and latch
reactions the phases apply: gears inhibited (a half avoided, a gear that did
not engage), limp home in one gear of the healthy half, the lock pressure
raised, torque requests off while the engine message is lost, the safe
state. With gears inhibited the schedule is the restricted one
(``_restricted_schedule``): the next allowed gear, a gear of the same half
reached by an interrupted shift, hysteresis kept across the skipped gears,
in limp home upshifts only to protect the engine. In a healthy run no trouble
code sets and nothing of this acts. ``sensors["stale_messages"]`` ({message:
cause}, from the CAN node) tells the stale messages apart: the engine
message's loss is ridden out, any other stale message is ``stale`` as before.
The result also carries the TCU_Status signals (ActiveFaults, InhibitedGears,
LimpHome, ShiftActive, TcuPhase, TcuState, FaultCount, LastFault).
"""

import math

from tcu_stub.diagnostics import SPEED_INVALID_RPM, Diagnostics

# ------------------------------------------------------------------ timing
PERIOD_S = 0.002                    # TCU task period, s

# ------------------------------------------------------------ the car (TCU calibration)
GEAR_OVERALL_RATIO = {1: 14.257, 2: 8.442, 3: 5.353, 4: 3.714, 5: 2.781, 6: 2.301}  # gear x final drive
FINAL_DRIVE = (4.118, 3.043)        # output shaft 1 (gears 1-4), output shaft 2 (5, 6)
TYRE_RADIUS_M = 0.316
TOP_GEAR = 6
REVERSE = -1                        # the reverse gear's number (TargetGear -1)
# gear -> (input shaft 0/1, sleeve 0..3, side +1/-1); R: the 5-R sleeve's other side, on K1
GEAR_LAYOUT = {1: (0, 0, 1), 2: (1, 1, 1), 3: (0, 0, -1), 4: (1, 1, -1), 5: (0, 2, 1), 6: (1, 3, 1), REVERSE: (0, 2, -1)}
REVERSE_OVERALL_RATIO = 12.142      # R x final drive of output shaft 2 (3.990 x 3.043)
SHAFT_SLEEVES = {0: (0, 2), 1: (1, 3)}
SHAFT_GEARS = {0: (1, 3, 5), 1: (2, 4, 6)}
# gear -> input shaft speed / its output shaft's speed (gears 1-4 on output shaft 1, 5 and 6 on 2)
GEAR_RATIO = {g: r / FINAL_DRIVE[0 if g <= 4 else 1] for g, r in GEAR_OVERALL_RATIO.items()}
ENGINE_INERTIA_KGM2 = 0.20          # crank + flywheel + clutch drum
IDLE_RPM = 750.0

# ------------------------------------------------------------ clutch model, K1 and K2
CLUTCH_KISS_BAR = (1.56, 1.27)      # pressure at which the pack closes (return spring / piston area): the
                                    # adaptation's start value (TcuLogic.kiss_bar, learnt at a stop on the brake)
CLUTCH_NM_PER_BAR = (35.6, 36.3)    # capacity gain above the kiss point (static mu)
# friction over transmission oil temperature (degC, factor on CLUTCH_NM_PER_BAR): the TCU's own table;
# wet paper linings grip a little more in cold, viscous oil (bench data of such linings: a few % per 50 K)
CLUTCH_MU_OVER_TEMP = ((-20.0, 1.08), (20.0, 1.05), (80.0, 1.0), (120.0, 0.97))
OIL_DEFAULT_DEGC = 90.0             # TransOilTemp not received (an older plant or matrix): warm
CLUTCH_LOCK_BAR = 14.0              # clamp pressure of a locked clutch
CLUTCH_MAX_BAR = 19.0

# ------------------------------------------------------------ valve and pressure loop
VALVE_FEEDBACK_AREA_M2 = 15.7e-6    # i = (p * A + F0) / k
VALVE_SPRING_N = 3.0
VALVE_GAIN_N_PER_A = 36.0
VALVE_MAX_A = 1.0
PRESSURE_KP_A_PER_BAR = 0.01
PRESSURE_KI_A_PER_BAR_S = 0.4
PRESSURE_I_LIMIT_A = 0.08
FILL_CURRENT_A = 0.5                # fill pulse current
FILL_TIME_S = 0.036                 # fill pulse length (piston stroke about 40 ms at 0.5 A), warm oil
# fill pulse length factor over oil temperature (degC, factor): viscous oil flows slower through the
# valve's metering edges and channels, the piston strokes later
FILL_TIME_OVER_TEMP = ((-20.0, 1.8), (20.0, 1.25), (60.0, 1.0))
EMPTY_BAR = 0.5                     # below this measured pressure an open clutch counts as empty
LINE_CURRENT_A = 0.0                # line pressure solenoid: 0 A = 20 bar

# ------------------------------------------------------------ forks
FORK_ENGAGE_N = 900.0               # below the blocker overpower force: no clash
FORK_HOLD_N = 80.0                  # keeps an engaged sleeve home
# P position loop back to neutral. ForkPosition arrives every 10 ms and a fork
# force holds for 10 ms (DCT_Shift, TCU_ShiftCmd), so the loop is designed
# for that sample time: with the actuator's damping c (2000 N s/m) the sleeve
# follows x' = -(k / c) x, a factor 1 - k T / c = 0.75 per 10 ms at k = 50 N/mm,
# without overshoot even when the position seen is one sample old. No
# derivative term: a difference of 10 ms samples taken every 2 ms is noise.
FORK_NEUTRAL_N_PER_MM = 50.0
FORK_NEUTRAL_NS_PER_MM = 0.0
FORK_NEUTRAL_MAX_N = 600.0
FORK_ENGAGED_MM = 7.0               # |position| beyond which a sleeve with SyncState 2 is engaged
FORK_NEUTRAL_MM = 0.6               # |position| within which a sleeve is in neutral
SYNC_ENGAGED = 2

# ------------------------------------------------------------ launch and drive
PEDAL_ON_PCT = 2.0                  # pedal above this starts a launch
BRAKE_ON_PCT = 2.0
LAUNCH_RPM_MIN = 1100.0             # engine speed held by clutch slip at a light pedal
LAUNCH_RPM_MAX = 3400.0             # ... and at full pedal
LAUNCH_KP_NM_PER_RPM = 0.25         # clutch torque correction over engine speed error
LAUNCH_LOCK_SLIP_RPM = 80.0         # slip below which the launch clutch locks
LOCK_RAMP_BAR_PER_S = 60.0          # pressure rise from slip control to clamp
OPEN_BELOW_INPUT_RPM = 900.0        # pedal released in 1st below this input speed: open the clutch

# ------------------------------------------------------------ selector lever (VEH_Driver.SelectorLever)
SELECTOR_P, SELECTOR_R, SELECTOR_N, SELECTOR_D = 0, 1, 2, 3
REVERSE_MAX_KMH = 3.0               # R engages only below this forward speed (else neutral, clutches open)
NEUTRAL_RESUME_KMH = 10.0           # D again above this speed (after N or a refused R): the gear for the speed

# ------------------------------------------------------------ creep and hill start (standstill, launch)
CREEP_NM = 20.0                     # launch clutch torque, brake released, no pedal: rolls the car at idle speed in 1st
CREEP_HOLD_NM = 3.0                 # ... on the brake: the pack kept just past its kiss point (about 240 W of slip at idle)
CREEP_RAMP_NM_PER_S = 40.0          # creep torque rate (3 -> 20 Nm in 0.4 s after the brake is released: no jerk)
CREEP_MAX_KMH = 8.0                 # creep torque fades to 0 over CREEP_FADE_KMH up to this speed (a cold, fast idle)
CREEP_FADE_KMH = 2.0
VEHICLE_WEIGHT_N = 14200.0          # the car with a driver as the TCU knows it (1450 kg): the grade's force
HILL_MARGIN = 1.25                  # holding torque over the grade's (unknown load, mesh losses, grade signal)
HILL_MIN_PCT = 2.0                  # uphill grade (in the direction of the gear) below which creep alone holds
HILL_KP_NM_PER_RPM = 0.3            # engine torque request while holding: per rpm below idle (the idle governor's
                                    # 60 Nm cannot carry a 20 % grade's torque: the engine would stall)
HILL_STALL_RPM = 600.0              # the holding torque at most the engine's torque + HILL_KP_NM_PER_RPM x the
                                    # engine speed above this: the clutch cannot pull the engine into a stall
                                    # while its torque builds up (the turbo engine's lag)
BRAKE_NM_PER_PCT = 25.0             # wheel brake torque per brake pedal %, as the TCU estimates it (below the car's
                                    # 31 Nm/%: the clutch takes over before the brake lets go)

# ------------------------------------------------------------ kiss point adaptation (stopped on the brake: K1 and K2 in turn)
ADAPT_OPEN_S = 1.0                  # the clutch held open this long once stopped on the brake: the engine's torque is its idle load
ADAPT_SETTLE_S = 1.0                # then CREEP_HOLD_NM this long before learning (fill, pressure loop, idle governor)
ADAPT_MAX_KMH = 1.0                 # stopped: VehicleSpeed below this (not the output shaft: it rings as K1 closes)
ADAPT_TORQUE_TAU_S = 0.1            # low-pass of EngineTorque (a 10 ms signal in 0.1 Nm steps)
ADAPT_SPEED_TAU_S = 0.2             # low-pass of the engine speed ...
ADAPT_STEADY_RPM = 15.0             # ... the engine within this of it: steady (its torque is the clutch's then)
ADAPT_GAIN_PER_S = 2.0              # kiss point rate per bar of torque error (error / Nm per bar)
ADAPT_MAX_BAR_PER_S = 0.2           # kiss point rate limit (a wrong torque reading cannot throw it far)
ADAPT_RANGE_BAR = 1.0               # the adapted kiss point stays within this of CLUTCH_KISS_BAR

# ------------------------------------------------------------ shifts
# (accelerator pedal %, engine speed rpm in the present gear): up and down lines
UPSHIFT_RPM = ((0.0, 1900.0), (25.0, 2100.0), (50.0, 2700.0), (75.0, 4200.0), (100.0, 6300.0))
DOWNSHIFT_RPM = ((0.0, 1050.0), (25.0, 1150.0), (50.0, 1400.0), (75.0, 2000.0), (100.0, 2800.0))
KICKDOWN_PCT = 95.0
KICKDOWN_MAX_RPM = 5200.0
TORQUE_PHASE_S = 0.12               # on-coming takes over the engine torque in this time
TORQUE_MARGIN = 1.15                # sum of capacities >= margin x engine torque
TORQUE_MARGIN_NM = 15.0
INERTIA_PHASE_S = 0.25              # engine speed pulled to the new shaft in this time
SYNC_DONE_RPM = 60.0                # slip below which the on-coming clutch locks
COAST_PULL_NM = 35.0                # on-coming torque that holds the engine once a coast downshift is through
BLIP_KP_NM_PER_RPM = 0.3            # coast downshift: engine torque request per rpm below the new shaft
BLIP_MAX_NM = 150.0                 # ... at most (the engine's lag makes it a 0.07 s speed loop)
DOWN_OFFGOING_SHARE = 0.6           # off-going capacity share of engine torque in a power downshift
SHIFT_TIMEOUT_S = 1.5
PRESELECT_MAX_RPM = 5000.0          # a lower gear is pre-selected only if its shaft stays below this

# ------------------------------------------------------------ restricted schedule (gears inhibited)
RESTRICTED_UP_MIN_RPM = 1300.0      # skipping gears up: the new gear's engine speed at least this
RESTRICTED_UP_DOWN_FACTOR = 1.2     # ... and this factor above the down line (no shift back)
RESTRICTED_DOWN_MAX_RPM = 4000.0    # skipping gears down: the new gear's engine speed at most this
LIMP_UPSHIFT_RPM = 5500.0           # limp home: shift up only above this (engine protection)
SELECT_MAX_RPM = 4500.0             # a gear picked for the speed (leaving a gear): at most this
LEAVE_STANDSTILL_KMH = 5.0          # a gear taken away below this speed: standstill, launch again
OPEN_SYNC_RPM = 120.0               # interrupted shift: the engine up to this below the shaft: close
OPEN_SYNC_S = 1.0                   # ... or after this long
TIED_BAR = 0.5                      # ... but not while the other half holds a gear with this above its kiss point

# ------------------------------------------------------------ traction (drive slip) limit
TRACTION_FORCE_N = 7500.0           # drive force the front tyres carry near peak slip (calibration)
TRACTION_ACCEL_MPS2 = 5.0           # vehicle acceleration at that force
MESH_EFFICIENCY = 0.97
ASR_SLIP_TARGET = 0.12              # driven-wheel slip held by the feedback trim
ASR_MIN_SPEED_KMH = 3.0
ASR_KI_NM_PER_S = 1500.0            # trim change per unit slip error and second
ASR_TRIM_MAX_NM = 150.0
ASR_KP_NM = 300.0                   # immediate torque cut per unit slip above the target
ASR_MIN_NM = 40.0
# the engine's full-load torque as the TCU knows it (rpm, Nm): estimates the driver's demand
ENGINE_FULL_LOAD = ((600.0, 120.0), (1000.0, 170.0), (1500.0, 240.0), (1800.0, 280.0), (5000.0, 280.0),
                    (5500.0, 255.0), (6000.0, 234.0), (6500.0, 200.0), (7000.0, 0.0))

RPM_PER_KMH = 1.0 / 3.6 / TYRE_RADIUS_M * 60.0 / (2.0 * math.pi)  # wheel rpm per km/h

#: TCU_Status.TcuPhase: the phase names in their code order
PHASES = ("standstill", "launch", "drive", "upshift_torque", "upshift_inertia", "downshift_inertia",
          "downshift_torque", "shift_open", "stale", "safe")
PHASE_CODES = {name: i for i, name in enumerate(PHASES)}
SHIFT_PHASES = frozenset(("upshift_torque", "upshift_inertia", "downshift_inertia", "downshift_torque",
                          "shift_open"))
FAULT_COUNT_MAX = 255               # TCU_Status.FaultCount saturates here
_SLEEVE_SHAFT = (0, 1, 0, 1)        # sleeve -> input shaft
# input shaft -> ((gear, sleeve, side), ...)
_SHAFT_SLEEVE_SIDES = {shaft: tuple((g,) + GEAR_LAYOUT[g][1:] for g in gears + ((REVERSE,) if shaft == 0 else ()))
                       for shaft, gears in SHAFT_GEARS.items()}


def _interp(x, table):
    if x <= table[0][0]:
        return table[0][1]
    for (x0, y0), (x1, y1) in zip(table, table[1:]):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return table[-1][1]


def _ramp(value, target, rate, dt):
    step = rate * dt
    return min(value + step, target) if target > value else max(value - step, target)


def _overall_ratio(gear):
    return REVERSE_OVERALL_RATIO if gear == REVERSE else GEAR_OVERALL_RATIO[gear]


def gear_rpm(gear, vehicle_speed_kmh):
    """Input shaft speed of ``gear`` at a vehicle speed, rpm."""
    return vehicle_speed_kmh * RPM_PER_KMH * GEAR_OVERALL_RATIO[gear]


class ClutchLoop:
    """Target pressure -> solenoid current: valve feed-forward + PI on the measured pressure."""

    def __init__(self, index):
        self.index = index
        self.integral_a = 0.0
        self.fill_left_s = 0.0
        self.target_bar = 0.0

    def reset(self):
        self.integral_a = 0.0
        self.fill_left_s = 0.0
        self.target_bar = 0.0

    def current(self, target_bar, measured_bar, dt, fill_time_s=FILL_TIME_S):
        target_bar = min(max(target_bar, 0.0), CLUTCH_MAX_BAR)
        was_open = self.target_bar <= 0.0
        self.target_bar = target_bar
        if target_bar <= 0.0:
            self.integral_a = 0.0
            self.fill_left_s = 0.0
            return 0.0
        if was_open and measured_bar < EMPTY_BAR:
            self.fill_left_s = fill_time_s
        if self.fill_left_s > 0.0:
            self.fill_left_s -= dt
            return FILL_CURRENT_A
        feed = (target_bar * 1e5 * VALVE_FEEDBACK_AREA_M2 + VALVE_SPRING_N) / VALVE_GAIN_N_PER_A
        err = target_bar - measured_bar
        self.integral_a = min(max(self.integral_a + PRESSURE_KI_A_PER_BAR_S * err * dt,
                                  -PRESSURE_I_LIMIT_A), PRESSURE_I_LIMIT_A)
        return min(max(feed + PRESSURE_KP_A_PER_BAR * err + self.integral_a, 0.0), VALVE_MAX_A)


def torque_to_bar(clutch, torque_nm):
    """Pressure for a clutch capacity, bar (0 = open)."""
    if torque_nm <= 0.0:
        return CLUTCH_KISS_BAR[clutch]
    return CLUTCH_KISS_BAR[clutch] + torque_nm / CLUTCH_NM_PER_BAR[clutch]


class TcuLogic:
    """The TCU: ``step`` every PERIOD_S with the plant signals, returns the commands."""

    def torque_to_bar(self, clutch, torque_nm):
        """Pressure for a clutch capacity with the adapted kiss point and the gain at the oil
        temperature, bar."""
        if torque_nm <= 0.0:
            return self.kiss_bar[clutch]
        return self.kiss_bar[clutch] + torque_nm / self.nm_per_bar(clutch)

    def nm_per_bar(self, clutch):
        """Capacity gain above the kiss point at the oil temperature, Nm/bar."""
        return CLUTCH_NM_PER_BAR[clutch] * _interp(self.oil_degc, CLUTCH_MU_OVER_TEMP)

    PERIOD_S = PERIOD_S
    GEAR_LAYOUT = GEAR_LAYOUT
    GEAR_RATIO = GEAR_RATIO
    CLUTCH_LOCK_BAR = CLUTCH_LOCK_BAR

    def __init__(self):
        self.loops = (ClutchLoop(0), ClutchLoop(1))
        self.diag = Diagnostics()
        self._handlers = {
            "standstill": self._standstill,
            "launch": self._launch,
            "drive": self._drive,
            "upshift_torque": self._upshift_torque,
            "upshift_inertia": self._upshift_inertia,
            "downshift_inertia": self._downshift_inertia,
            "downshift_torque": self._downshift_torque,
            "shift_open": self._shift_open,
        }
        self.reset()

    def reset(self):
        self.phase = "standstill"
        self.gear = 1                 # gear the TCU drives in (or will launch in)
        self.target_gear = 1
        self.preselect = 2
        self.pressure_bar = [0.0, 0.0]
        self.sleeve_side = [0, 0, 0, 0]
        self.fork_pos_prev = [0.0, 0.0, 0.0, 0.0]
        self.torque_request_nm = None
        self.shift_t0 = 0.0
        self.shift_from = 1
        self.latched_torque_nm = 0.0
        self.shift_slip0_rpm = 0.0
        self.asr_trim_nm = 0.0
        self.asr_cut_nm = 0.0
        self.launch_rpm = LAUNCH_RPM_MIN
        self.creep_nm = 0.0           # creep torque on the launch clutch (ramped), Nm
        self.hill_nm = 0.0            # holding torque of the grade the brake no longer holds, Nm
        self.kiss_bar = list(CLUTCH_KISS_BAR)   # adapted kiss points of K1, K2, bar
        self.oil_degc = OIL_DEFAULT_DEGC    # transmission oil temperature as last read, degC
        self.selector = SELECTOR_D    # selector lever as last read
        self.adapt_t_s = 0.0          # time stopped on the brake (the adaptation's sequence), s
        self.adapt_shaft = 0          # the clutch the next stop learns (0: K1 in 1st, 1: K2 in 2nd)
        self.te_filt_nm = 0.0         # EngineTorque low-pass, Nm
        self.n_filt_rpm = 0.0         # engine speed low-pass, rpm
        self.idle_load_nm = 0.0       # the engine's torque with K1 open at the stop, Nm
        self.t_s = 0.0
        self.events = []              # (time_s, from_gear, to_gear) of every shift started
        self.held = (0.0, 0.0, 0.0)   # pedal, brake, engine torque last received (the engine message lost)
        self.n_shaft = (0.0, 0.0)
        for loop in self.loops:
            loop.reset()
        self.diag.reset()

    # ---------------------------------------------------------- sensors
    def _read(self, s):
        self.s = s
        if self.diag.engine_lost:             # the engine message stale: its last values stand in
            self.pedal, self.brake, self.t_engine = self.held
        else:
            self.pedal = float(s.get("AccelPedal", 0.0))
            self.brake = float(s.get("BrakePedal", 0.0))
            self.t_engine = float(s.get("EngineTorque", 0.0))
            self.held = (self.pedal, self.brake, self.t_engine)
        self.n_engine = float(s.get("EngineSpeed", 0.0))
        self.n_out = (float(s.get("OutputShaft1Speed", 0.0)), float(s.get("OutputShaft2Speed", 0.0)))
        self.v_kmh = float(s.get("VehicleSpeed", 0.0))
        self.grade_pct = float(s.get("RoadGrade", 0.0))
        self.oil_degc = float(s.get("TransOilTemp", OIL_DEFAULT_DEGC))
        self.selector = int(round(float(s.get("SelectorLever", SELECTOR_D))))
        # the schedule runs on the output shaft speed (driven wheels), as the gearbox sees it
        self.v_sched_kmh = self.n_out[0] / FINAL_DRIVE[0] / RPM_PER_KMH
        self.p_meas = (float(s.get("ClutchPressure1", 0.0)), float(s.get("ClutchPressure2", 0.0)))
        line = s.get("LinePressure")
        self.line_bar = None if line is None else float(line)
        get = s.get
        self.fork_mm = (float(get("ForkPosition1", 0.0)), float(get("ForkPosition2", 0.0)),
                        float(get("ForkPosition3", 0.0)), float(get("ForkPosition4", 0.0)))
        self.sync_state = (int(round(float(get("SyncState1", 0)))), int(round(float(get("SyncState2", 0)))),
                           int(round(float(get("SyncState3", 0)))), int(round(float(get("SyncState4", 0)))))
        self.engaged_gear = (self._engaged_on(0), self._engaged_on(1))
        # input shaft speeds as received (the diagnostics judge these) and as used: an
        # invalid value (the DBC's invalid code, not finite) is replaced at once by the
        # speed of the gear engaged on that shaft, else by the last valid one
        self.n_shaft_raw = (float(s.get("InputShaft1Speed", 0.0)), float(s.get("InputShaft2Speed", 0.0)))
        n1, n2 = self.n_shaft_raw
        if not (abs(n1) <= SPEED_INVALID_RPM) or not (abs(n2) <= SPEED_INVALID_RPM):
            n1, n2 = self._substitute(0, n1), self._substitute(1, n2)
        self.n_shaft = (n1, n2)

    def _substitute(self, shaft, n):
        if abs(n) <= SPEED_INVALID_RPM:
            return n
        g = self.engaged_gear[shaft]
        if g:
            return self.gear_input_rpm(g)
        return self.n_shaft[shaft]

    def gear_input_rpm(self, g):
        """Input shaft speed that the output shafts give through gear ``g`` (R turns it
        against output shaft 2), rpm."""
        if g == REVERSE:
            return -self.n_out[1] * (REVERSE_OVERALL_RATIO / FINAL_DRIVE[1])
        return self.n_out[0 if g <= 4 else 1] * GEAR_RATIO[g]

    def _engaged_on(self, shaft):
        """The gear engaged on an input shaft (0: none)."""
        for g, sleeve, side in _SHAFT_SLEEVE_SIDES[shaft]:
            if self.sync_state[sleeve] == SYNC_ENGAGED and self.fork_mm[sleeve] * side >= FORK_ENGAGED_MM:
                return g
        return 0

    def _sleeve_engaged(self, sleeve, side):
        return self.sync_state[sleeve] == SYNC_ENGAGED and self.fork_mm[sleeve] * side >= FORK_ENGAGED_MM

    def _sleeve_neutral(self, sleeve):
        return abs(self.fork_mm[sleeve]) <= FORK_NEUTRAL_MM + 0.5

    def gear_ready(self, gear):
        """``gear`` engaged and the other sleeve of its shaft in neutral."""
        shaft, sleeve, side = GEAR_LAYOUT[gear]
        others = [k for k in SHAFT_SLEEVES[shaft] if k != sleeve]
        return self._sleeve_engaged(sleeve, side) and all(self._sleeve_neutral(k) for k in others)

    # ---------------------------------------------------------- forks
    def _want_gears(self, *gears):
        """Sleeve sides for the given gears (one per input shaft); everything else neutral."""
        sides = [0, 0, 0, 0]
        for g in gears:
            if g:
                _, sleeve, side = GEAR_LAYOUT[g]
                sides[sleeve] = side
        self.sleeve_side = sides

    def _neutral_force(self, k, pos):
        """Position loop that brings sleeve ``k`` to neutral without overshooting onto the other cone."""
        vel = (pos - self.fork_pos_prev[k]) / PERIOD_S
        if abs(pos) <= FORK_NEUTRAL_MM and abs(vel) < 20.0:
            return 0.0
        f = -FORK_NEUTRAL_N_PER_MM * pos - FORK_NEUTRAL_NS_PER_MM * vel
        return min(max(f, -FORK_NEUTRAL_MAX_N), FORK_NEUTRAL_MAX_N)

    def requested_gear(self, shaft):
        """The gear the forks are asked to engage on an input shaft (0: neutral, or the safe state)."""
        if self.phase == "safe" or self.phase == "stale":
            return 0
        sides = self.sleeve_side
        for g, sleeve, side in _SHAFT_SLEEVE_SIDES[shaft]:
            if sides[sleeve] == side:
                return g
        return 0

    def _fork_forces(self):
        forces = []
        release = self.diag.release_s
        for k, side in enumerate(self.sleeve_side):
            pos = self.fork_mm[k]
            state = self.sync_state[k]
            if release[_SLEEVE_SHAFT[k]] > 0.0:
                # a gear that did not engage: its shaft's sleeves let go for a retry
                # (a synchronisation that cannot finish, its gear's speed running away)
                f = self._neutral_force(k, pos)
                forces.append(f)
                self.fork_pos_prev[k] = pos
                continue
            if state == 1 and pos != 0.0 and side != (1 if pos > 0 else -1):
                # never let go of a sleeve on its cone: finish that synchronisation first
                side = 1 if pos > 0 else -1
            if side == 0:
                f = self._neutral_force(k, pos)
            else:
                # a sleeve that still sits on the other gear of its shaft first goes to neutral
                shaft = 0 if k in SHAFT_SLEEVES[0] else 1
                blocked = any(not self._sleeve_neutral(j) and self.sleeve_side[j] == 0
                              for j in SHAFT_SLEEVES[shaft] if j != k)
                if blocked:
                    f = self._neutral_force(k, pos)
                elif self._sleeve_engaged(k, side):
                    f = side * FORK_HOLD_N
                else:
                    f = side * FORK_ENGAGE_N
            forces.append(f)
            self.fork_pos_prev[k] = pos
        return forces

    # ---------------------------------------------------------- schedule
    def _scheduled_gear(self):
        """Gear the shift map asks for from ``gear`` (one step at a time, kick-down several)."""
        g = self.gear
        up_rpm = _interp(self.pedal, UPSHIFT_RPM)
        down_rpm = _interp(self.pedal, DOWNSHIFT_RPM)
        braking = self.brake > BRAKE_ON_PCT
        if g < TOP_GEAR and gear_rpm(g, self.v_sched_kmh) > up_rpm and not braking:
            return g + 1
        if self.pedal >= KICKDOWN_PCT:
            lower = g
            while lower > 1 and gear_rpm(lower - 1, self.v_sched_kmh) < KICKDOWN_MAX_RPM and \
                    gear_rpm(lower, self.v_sched_kmh) < 0.75 * up_rpm:
                lower -= 1
            if lower < g:
                return lower
        if g > 1 and gear_rpm(g, self.v_sched_kmh) < down_rpm:
            return g - 1
        return g

    def _preselection(self):
        g = self.gear
        if g == REVERSE:
            return 2
        if self.target_gear != g:
            return self.target_gear
        rising = self.pedal > PEDAL_ON_PCT and self.brake < BRAKE_ON_PCT
        if self.diag.inhibited:
            return self._restricted_preselection(g, rising)
        if g == 1:
            return 2
        if not rising and gear_rpm(g - 1, self.v_sched_kmh) < PRESELECT_MAX_RPM:
            return g - 1
        return g + 1 if g < TOP_GEAR else 0

    # ---------------------------------------------------------- gears inhibited (diagnostics)
    def allowed(self, gear):
        """``gear`` (1..6) is not inhibited by the diagnostics (R is never inhibited)."""
        return gear < 0 or not (self.diag.inhibited >> (gear - 1)) & 1

    def _next_allowed(self, g, step, shaft=None):
        """The next allowed gear from ``g`` in direction ``step`` (+1/-1), on ``shaft`` if given; 0: none."""
        n = g + step
        while 1 <= n <= TOP_GEAR:
            if self.allowed(n) and (shaft is None or GEAR_LAYOUT[n][0] == shaft):
                return n
            n += step
        return 0

    def _restricted_preselection(self, g, rising):
        """The allowed gear to pre-select on the other input shaft (0: none: its sleeves neutral)."""
        other = 1 - GEAR_LAYOUT[g][0]
        up = self._next_allowed(g, 1, other)
        down = self._next_allowed(g, -1, other)
        if down and not rising and gear_rpm(down, self.v_sched_kmh) < PRESELECT_MAX_RPM:
            return down
        if up:
            return up
        if down and gear_rpm(down, self.v_sched_kmh) < PRESELECT_MAX_RPM:
            return down
        return 0

    def _restricted_schedule(self, g=None):
        """The schedule over the allowed gears from ``g`` (default ``gear``): the next allowed
        gear up or down; a skip of gears keeps the hysteresis (the new gear lands between the
        lines); in limp home up only above LIMP_UPSHIFT_RPM."""
        g = self.gear if g is None else g
        up_rpm = _interp(self.pedal, UPSHIFT_RPM)
        down_rpm = _interp(self.pedal, DOWNSHIFT_RPM)
        rpm = gear_rpm(g, self.v_sched_kmh)
        up = self._next_allowed(g, 1)
        if up and self.brake <= BRAKE_ON_PCT:
            high = rpm > (LIMP_UPSHIFT_RPM if self.diag.limp_home else up_rpm)
            lands = up == g + 1 or gear_rpm(up, self.v_sched_kmh) > max(RESTRICTED_UP_MIN_RPM,
                                                                         RESTRICTED_UP_DOWN_FACTOR * down_rpm)
            if high and lands:
                return up
        down = self._next_allowed(g, -1)
        if down and rpm < down_rpm and (down == g - 1 or
                                        gear_rpm(down, self.v_sched_kmh) < RESTRICTED_DOWN_MAX_RPM):
            return down
        return g

    def _gear_for_speed(self):
        """The lowest allowed gear the restricted schedule would hold at this speed, with
        the engine at most SELECT_MAX_RPM; else the lowest allowed gear below that speed,
        else the highest allowed gear; 0 when none is allowed."""
        below = highest = 0
        for g in range(1, TOP_GEAR + 1):
            if not self.allowed(g):
                continue
            highest = g
            if gear_rpm(g, self.v_sched_kmh) <= SELECT_MAX_RPM:
                if self._restricted_schedule(g) == g:
                    return g
                below = below or g
        return below or highest

    def _gear_taken(self):
        """The phase drives (or shifts) through a gear the diagnostics inhibited."""
        p = self.phase
        if p in ("standstill", "stale", "safe"):
            return False
        if p == "shift_open":
            return not self.allowed(self.target_gear)
        if not self.allowed(self.gear):
            return True
        if p in SHIFT_PHASES:
            return not self.allowed(self.target_gear) or not self.allowed(self.shift_from)
        return False

    def _leave_gear(self):
        """Out of an inhibited gear: its clutch open now; slow: standstill (launch again in
        an allowed gear), else the allowed gear for the speed by an interrupted shift."""
        self.torque_request_nm = None
        if self.v_sched_kmh < LEAVE_STANDSTILL_KMH:
            self.phase = "standstill"
            self.pressure_bar = [0.0, 0.0]
            return
        g = self._gear_for_speed()
        if g:
            self._start_open_shift(g)

    def _start_open_shift(self, gear):
        if gear != self.gear:
            self.events.append((self.t_s, self.gear, gear))
        self.shift_from = self.gear
        self.target_gear = gear
        self.shift_t0 = self.t_s
        self.phase = "shift_open"
        self.pressure_bar = [0.0, 0.0]

    def _shift_open(self):
        """Interrupted shift: both clutches open, the new gear engaged, the engine brought to
        its shaft speed by a torque request; then its clutch closes by the lock ramp of
        ``drive``: at once when the engine is at or above the shaft (the clutch pulls it
        down, as in an upshift's inertia phase), else when the engine has come up to it or
        after OPEN_SYNC_S; a shaft too slow for that: ``launch`` (slip control)."""
        target = self.target_gear
        shaft = GEAR_LAYOUT[target][0]
        other = 1 - shaft
        self._want_gears(target)
        self.pressure_bar = [0.0, 0.0]
        # the other half still drives (its clutch did not open: a valve stuck, a pressure
        # that stays): no tie-up; no engine torque, so its sleeve can leave its gear
        tied = self.p_meas[other] > self.kiss_bar[other] + TIED_BAR and not all(
            self._sleeve_neutral(k) and self.sync_state[k] != SYNC_ENGAGED for k in SHAFT_SLEEVES[other])
        if tied:
            self.torque_request_nm = 0.0
            return
        # the request is the engine's net torque: below zero its drag pulls it down
        below = gear_rpm(target, self.v_sched_kmh) - self.n_engine
        self.torque_request_nm = min(max(BLIP_KP_NM_PER_RPM * below, -BLIP_MAX_NM), BLIP_MAX_NM)
        if not self.gear_ready(target):
            return
        n_in = self.n_shaft[shaft]
        slow = n_in < LAUNCH_RPM_MIN
        if not slow and self.n_engine < n_in - OPEN_SYNC_RPM and self.t_s - self.shift_t0 < OPEN_SYNC_S:
            return                                # the engine still on its way up to the shaft
        self.gear = target
        self.torque_request_nm = None
        if slow:
            self.phase = "launch"
        else:
            self.phase = "drive"
            self.pressure_bar[shaft] = self.torque_to_bar(shaft, 0.0)

    # ---------------------------------------------------------- phases
    def _standstill(self):
        sel = self.selector
        if sel == SELECTOR_D and self.v_sched_kmh > NEUTRAL_RESUME_KMH:
            self._recover()                     # D again while rolling: the gear for the speed, by slip
            return
        if sel != SELECTOR_D and (sel != SELECTOR_R or self.v_sched_kmh > REVERSE_MAX_KMH):
            # P, N, or R refused while rolling forward: both clutches open, no torque request
            if sel == SELECTOR_R:
                self._want_gears()              # neutral until slow enough for R
            elif self.gear == REVERSE:
                self._want_gears(REVERSE, 2)    # the gears may stay engaged
            else:
                self._want_gears(1, 2)
            self.target_gear = 0
            self.pressure_bar = [0.0, 0.0]
            self.torque_request_nm = None
            self.creep_nm = 0.0
            return
        first = REVERSE if sel == SELECTOR_R else 1
        if sel == SELECTOR_R:
            self._want_gears(REVERSE, 2)
        elif self.diag.inhibited:               # launch in the lowest allowed gear
            first = self._next_allowed(0, 1)
            if not first:
                return
            self._want_gears(first, self._next_allowed(first, 1, 1 - GEAR_LAYOUT[first][0]))
        else:
            self._want_gears(1, 2)
        self.gear = self.target_gear = first
        floor = self._creep(first)
        # every other stop on the brake in D learns K2's kiss point in the pre-selected 2nd
        learn = 2 if first == 1 and sel == SELECTOR_D and self.adapt_shaft == 1 and self.allowed(2) else first
        if self._adapt_kiss(learn):
            floor = 0.0                         # the clutch open: the engine's idle load
        hold = learn if self.adapt_t_s > 0.0 else first
        bars = [0.0, 0.0]
        if floor > 0.0 and self.gear_ready(hold):
            shaft = GEAR_LAYOUT[hold][0]
            bars[shaft] = self.torque_to_bar(shaft, floor)
        self.pressure_bar = bars
        self.torque_request_nm = self._hold_request_nm() if bars != [0.0, 0.0] else None
        if self.pedal > PEDAL_ON_PCT and self.brake < BRAKE_ON_PCT and self.gear_ready(first):
            self._start_launch()

    def _hold_request_nm(self):
        """Engine torque request while the clutch holds a grade (None: no grade to hold): the
        holding torque plus a speed loop to idle or, if more, the pedal's demand on top, Nm."""
        if self.hill_nm <= 0.0:
            return None
        demand = self.pedal / 100.0 * _interp(self.n_engine, ENGINE_FULL_LOAD)
        return max(self.hill_nm + max(HILL_KP_NM_PER_RPM * (IDLE_RPM - self.n_engine), demand), 0.0)

    def _creep(self, gear):
        """The launch clutch's least torque at low speed, Nm: creep (brake released: CREEP_NM,
        fading out toward CREEP_MAX_KMH; on the brake: CREEP_HOLD_NM), ramped; and at once
        the holding torque of an uphill grade as far as the brake does not hold it. Speed and
        grade in the gear's direction (R: backwards)."""
        v = -self.v_sched_kmh if gear == REVERSE else self.v_sched_kmh
        if self.brake >= BRAKE_ON_PCT:
            target = CREEP_HOLD_NM
        else:
            target = CREEP_NM * min(max((CREEP_MAX_KMH - v) / CREEP_FADE_KMH, 0.0), 1.0)
        self.creep_nm = _ramp(self.creep_nm, target, CREEP_RAMP_NM_PER_S, PERIOD_S)
        self.hill_nm = self._hill_hold_nm(gear, v)
        return max(self.creep_nm, self.hill_nm)

    def _adapt_kiss(self, gear):
        """Kiss point adaptation of ``gear``'s clutch, stopped on the brake: the clutch open for
        ADAPT_OPEN_S (the engine's torque then is its idle load), then CREEP_HOLD_NM; once
        settled, the clutch's torque is the engine's above that idle load, and the kiss point
        moves by ADAPT_GAIN_PER_S x (commanded - estimated torque) / Nm per bar, rate and range
        bounded. True while the clutch is to be held open."""
        shaft = GEAR_LAYOUT[gear][0]
        self.te_filt_nm += PERIOD_S / ADAPT_TORQUE_TAU_S * (self.t_engine - self.te_filt_nm)
        self.n_filt_rpm += PERIOD_S / ADAPT_SPEED_TAU_S * (self.n_engine - self.n_filt_rpm)
        stopped = self.brake >= BRAKE_ON_PCT and self.pedal <= PEDAL_ON_PCT and \
            abs(self.v_kmh) < ADAPT_MAX_KMH and self.hill_nm <= 0.0 and self.gear_ready(gear)
        if not stopped:
            if self.adapt_t_s >= ADAPT_OPEN_S + ADAPT_SETTLE_S:
                self.adapt_shaft = 1 - self.adapt_shaft     # the other clutch at the next stop
            self.adapt_t_s = 0.0
            return False
        self.adapt_t_s += PERIOD_S
        steady = abs(self.n_engine - self.n_filt_rpm) < ADAPT_STEADY_RPM
        if self.adapt_t_s < ADAPT_OPEN_S:
            if steady:
                self.idle_load_nm = self.te_filt_nm
            return True
        if self.adapt_t_s >= ADAPT_OPEN_S + ADAPT_SETTLE_S and steady and self.creep_nm == CREEP_HOLD_NM:
            error_nm = self.creep_nm - (self.te_filt_nm - self.idle_load_nm)
            rate = min(max(ADAPT_GAIN_PER_S * error_nm / self.nm_per_bar(shaft), -ADAPT_MAX_BAR_PER_S),
                       ADAPT_MAX_BAR_PER_S)
            self.kiss_bar[shaft] = min(max(self.kiss_bar[shaft] + rate * PERIOD_S,
                                           CLUTCH_KISS_BAR[shaft] - ADAPT_RANGE_BAR),
                                       CLUTCH_KISS_BAR[shaft] + ADAPT_RANGE_BAR)
        return False

    def _hill_hold_nm(self, gear, v):
        """Clutch torque that holds the car on the grade with the brake's share taken off, Nm
        (grade force x tyre radius / overall ratio x HILL_MARGIN, less the brake's torque);
        ``v``: the speed in the gear's direction, km/h."""
        grade = -self.grade_pct if gear == REVERSE else self.grade_pct
        if grade < HILL_MIN_PCT or v >= CREEP_MAX_KMH:
            return 0.0
        ratio = _overall_ratio(gear)
        force_n = VEHICLE_WEIGHT_N * grade / math.sqrt(10000.0 + grade * grade)     # m g sin(atan(grade))
        need = HILL_MARGIN * force_n * TYRE_RADIUS_M / ratio
        hold = max(need - BRAKE_NM_PER_PCT * self.brake / ratio, 0.0)
        return min(hold, max(max(self.t_engine, 0.0) + HILL_KP_NM_PER_RPM * (self.n_engine - HILL_STALL_RPM), 0.0))

    def _start_launch(self):
        self.phase = "launch"

    def _selector_away(self):
        """The lever left the gear's direction (N, P, R while in a forward gear, D while in R):
        both clutches open, standstill (which engages what the lever asks for). True then."""
        if (self.selector == SELECTOR_D and self.gear != REVERSE) or \
                (self.selector == SELECTOR_R and self.gear == REVERSE):
            return False
        self.phase = "standstill"
        self.pressure_bar = [0.0, 0.0]
        self.torque_request_nm = None
        return True

    def _launch(self):
        """Slip the clutch of ``gear``, holding the engine at a speed that rises with the pedal."""
        if self._selector_away():
            return
        shaft = GEAR_LAYOUT[self.gear][0]
        self._want_gears(self.gear, self._preselection())
        if self.pedal <= PEDAL_ON_PCT and self.n_shaft[shaft] < OPEN_BELOW_INPUT_RPM:
            self.phase = "standstill"
            return
        n_target = LAUNCH_RPM_MIN + (LAUNCH_RPM_MAX - LAUNCH_RPM_MIN) * min(self.pedal, 100.0) / 100.0
        n_target = max(n_target, self.n_shaft[shaft])
        self.launch_rpm = n_target
        err = self.n_engine - n_target
        # the clutch takes the engine torque in proportion to how far the engine has risen
        share = min(max((self.n_engine - IDLE_RPM) / max(n_target - IDLE_RPM, 1.0), 0.0), 1.0)
        torque = share * max(self.t_engine, 0.0) + LAUNCH_KP_NM_PER_RPM * max(err, 0.0)
        torque = min(max(torque, 0.0), self._traction_clutch_nm(self.gear))
        torque = max(torque, self._creep(self.gear))    # creep and a grade's holding torque at least
        self.torque_request_nm = self._hold_request_nm()
        slip = self.n_engine - self.n_shaft[shaft]
        if abs(slip) < LAUNCH_LOCK_SLIP_RPM and self.n_engine > LAUNCH_RPM_MIN - 200:
            self.phase = "drive"
            self.torque_request_nm = None
        bars = [0.0, 0.0]
        if self.gear_ready(self.gear):          # no torque on a shaft without its gear
            bars[shaft] = self.torque_to_bar(shaft, torque)
        self.pressure_bar = bars

    def _drive(self):
        if self._selector_away():
            return
        shaft = GEAR_LAYOUT[self.gear][0]
        other = 1 - shaft
        bars = [0.0, 0.0]
        lock = CLUTCH_MAX_BAR if self.diag.boost[shaft] else CLUTCH_LOCK_BAR
        bars[shaft] = _ramp(self.pressure_bar[shaft], lock, LOCK_RAMP_BAR_PER_S, PERIOD_S)
        self.pressure_bar = bars
        if self.gear == REVERSE:                # R: no schedule, back to standstill when released
            self.target_gear = REVERSE
            self._want_gears(REVERSE, 2)
            if self.pedal <= PEDAL_ON_PCT and self.n_shaft[shaft] < OPEN_BELOW_INPUT_RPM:
                self.phase = "standstill"
            return
        if self.gear == 1 and self.pedal <= PEDAL_ON_PCT and self.n_shaft[shaft] < OPEN_BELOW_INPUT_RPM:
            self.phase = "standstill"
            return
        if self.gear > 1 and self.n_shaft[shaft] < IDLE_RPM + 50:
            # too slow for this gear (a missed downshift): slip it like a launch
            self._start_launch()
            return
        if self.diag.inhibited:
            target = self._restricted_schedule()
            if target != self.gear and GEAR_LAYOUT[target][0] != other:
                self._start_open_shift(target)    # a gear of the same half: an interrupted shift
                return
        else:
            target = self._scheduled_gear()
            if target != self.gear and GEAR_LAYOUT[target][0] != other:
                # kick-down over two steps lands on the same shaft: go one step now
                target = self.gear - 1 if target < self.gear else self.gear + 1
        self.target_gear = target
        self._want_gears(self.gear, self._preselection())
        if target != self.gear and self.gear_ready(target):
            self._start_shift()

    def _start_shift(self):
        self.shift_from = self.gear
        self.shift_t0 = self.t_s
        self.latched_torque_nm = max(self.t_engine, 0.0)
        up = self.target_gear > self.gear
        self.phase = "upshift_torque" if up else "downshift_inertia"
        self.events.append((self.t_s, self.gear, self.target_gear))

    def _shift_shafts(self):
        return GEAR_LAYOUT[self.shift_from][0], GEAR_LAYOUT[self.target_gear][0]

    def _upshift_torque(self):
        """Off-going pressure down while on-coming pressure up; sum of capacities >= engine torque."""
        off, on = self._shift_shafts()
        self._want_gears(self.shift_from, self.target_gear)
        t_e = max(self.t_engine, 0.0)
        frac = min((self.t_s - self.shift_t0) / TORQUE_PHASE_S, 1.0)
        need = TORQUE_MARGIN * t_e + TORQUE_MARGIN_NM
        t_on = frac * need
        t_off = max(need - t_on, 0.0)
        bars = [0.0, 0.0]
        bars[on] = self.torque_to_bar(on, t_on)
        bars[off] = min(self.torque_to_bar(off, t_off), self.pressure_bar[off]) if frac < 1.0 else 0.0
        self.pressure_bar = bars
        if frac >= 1.0:
            self.phase = "upshift_inertia"
            self.gear = self.target_gear
            self.shift_t0 = self.t_s
            self.latched_torque_nm = t_e
            self.shift_slip0_rpm = max(self.n_engine - self.n_shaft[on], 1.0)

    def _upshift_inertia(self):
        """Pull the engine to the new shaft: on-coming holds the drive torque, the engine gives less."""
        off, on = self._shift_shafts()
        self._want_gears(self.target_gear, self.shift_from)
        slip = self.n_engine - self.n_shaft[on]
        t_clutch = TORQUE_MARGIN * self.latched_torque_nm + TORQUE_MARGIN_NM
        rate_target = self.shift_slip0_rpm / INERTIA_PHASE_S        # rpm/s wanted
        j_torque = ENGINE_INERTIA_KGM2 * rate_target * 2.0 * math.pi / 60.0
        request = t_clutch - j_torque
        self.torque_request_nm = max(min(request, self.latched_torque_nm), 0.0)
        bars = [0.0, 0.0]
        bars[on] = self.torque_to_bar(on, t_clutch)
        self.pressure_bar = bars
        if slip < SYNC_DONE_RPM or self.t_s - self.shift_t0 > SHIFT_TIMEOUT_S:
            self._finish_shift()

    def _downshift_inertia(self):
        """Let the engine rise to the lower gear's shaft. Power downshift: the off-going
        clutch slips and the engine's own torque lifts it. Coast downshift: both clutches
        open (on-coming filled to its kiss point) and an engine torque request blips the
        engine up, so the car's momentum does not have to (no deceleration jerk)."""
        off, on = self._shift_shafts()
        self._want_gears(self.shift_from, self.target_gear)
        t_e = max(self.t_engine, 0.0)
        bars = [0.0, 0.0]
        no_blip = False
        if self.torque_request_nm is None and t_e > 2 * COAST_PULL_NM:
            bars[off] = self.torque_to_bar(off, DOWN_OFFGOING_SHARE * t_e)
            bars[on] = self.torque_to_bar(on, 0.0)
        else:
            bars[on] = self.torque_to_bar(on, 0.0)
            below = self.n_shaft[on] - self.n_engine
            self.torque_request_nm = min(max(BLIP_KP_NM_PER_RPM * below, 0.0), BLIP_MAX_NM)
            # no torque requests (engine message lost): the on-coming clutch pulls the engine up
            no_blip = not self.diag.torque_ok
        self.pressure_bar = bars
        if self.n_engine > self.n_shaft[on] - SYNC_DONE_RPM or self.t_s - self.shift_t0 > SHIFT_TIMEOUT_S \
                or no_blip:
            self.phase = "downshift_torque"
            self.gear = self.target_gear
            self.shift_t0 = self.t_s
            self.latched_torque_nm = bars[off]
            self.torque_request_nm = None

    def _downshift_torque(self):
        off, on = self._shift_shafts()
        self._want_gears(self.target_gear, self.shift_from)
        t_e = max(self.t_engine, 0.0)
        frac = min((self.t_s - self.shift_t0) / TORQUE_PHASE_S, 1.0)
        need = TORQUE_MARGIN * t_e + TORQUE_MARGIN_NM
        bars = [0.0, 0.0]
        bars[on] = self.torque_to_bar(on, max(frac * need, COAST_PULL_NM))
        bars[off] = self.torque_to_bar(off, (1.0 - frac) * DOWN_OFFGOING_SHARE * t_e) if frac < 1.0 and \
            self.latched_torque_nm > 0 else 0.0
        self.pressure_bar = bars
        if frac >= 1.0:
            self._finish_shift()

    def _finish_shift(self):
        self.gear = self.target_gear
        self.torque_request_nm = None
        self.phase = "drive"

    def _update_slip_trim(self):
        """Feedback on the driven-wheel slip: integral trim plus an immediate cut."""
        self.asr_cut_nm = 0.0
        if self.v_kmh < ASR_MIN_SPEED_KMH or self.pedal <= PEDAL_ON_PCT:
            return
        slip = (self.v_sched_kmh - self.v_kmh) / max(self.v_kmh, ASR_MIN_SPEED_KMH)
        err = ASR_SLIP_TARGET - slip
        self.asr_trim_nm += ASR_KI_NM_PER_S * err * PERIOD_S
        self.asr_trim_nm = min(max(self.asr_trim_nm, -ASR_TRIM_MAX_NM), ASR_TRIM_MAX_NM)
        self.asr_cut_nm = min(ASR_KP_NM * err, 0.0)

    def _traction_clutch_nm(self, gear):
        """Clutch torque the tyres can take in ``gear`` (feed-forward + slip trim), Nm."""
        ratio = _overall_ratio(gear)
        return TRACTION_FORCE_N * TYRE_RADIUS_M / (ratio * MESH_EFFICIENCY) + self.asr_trim_nm + \
            self.asr_cut_nm

    def _traction_limit(self):
        """Engine torque limit that keeps the driven wheels near the peak of the tyre force
        (None: the driver asks for less, no limit)."""
        if self.pedal <= PEDAL_ON_PCT or self.phase not in ("launch", "drive"):
            self.asr_trim_nm = self.asr_cut_nm = 0.0
            return None
        self._update_slip_trim()
        ratio = _overall_ratio(self.gear)
        limit = self._traction_clutch_nm(self.gear)
        if self.phase == "drive":     # the engine also accelerates its own inertia
            limit += ENGINE_INERTIA_KGM2 * TRACTION_ACCEL_MPS2 * ratio / TYRE_RADIUS_M
        else:                         # launch: the engine torque holds the launch speed
            limit += LAUNCH_KP_NM_PER_RPM * (self.launch_rpm - self.n_engine)
        demand = self.pedal / 100.0 * _interp(self.n_engine, ENGINE_FULL_LOAD)
        if limit >= demand:
            return None
        return max(limit, ASR_MIN_NM)

    def _stale(self):
        self.pressure_bar = [0.0, 0.0]
        self.torque_request_nm = None

    # ---------------------------------------------------------- step
    def step(self, t_s, sensors):
        """One TCU period: sensors (DBC signal names) -> commands (DBC signal names)."""
        self.t_s = float(t_s)
        stale = self.diag.messages(self.t_s, sensors)
        self._read(sensors)
        if stale:
            if self.phase != "stale" and self.phase != "safe":
                self.phase = "stale"
            self._stale()
            return self._commands(stale=True)
        self.diag.monitor(self.t_s, self)
        if self.diag.safe_state:
            self.phase = "safe"
            self._stale()
            return self._commands(stale=True)
        if self.phase == "stale":
            self._recover()
        if self.diag.inhibited and self._gear_taken():
            self._leave_gear()
        self._handlers[self.phase]()
        return self._commands()

    def _recover(self):
        """Plant messages back: re-engage by slip control in the gear the speed asks for."""
        for loop in self.loops:
            loop.reset()
        self.torque_request_nm = None
        if self.v_kmh < 5.0:
            self.phase = "standstill"
            return
        if self.diag.inhibited:
            g = self._gear_for_speed()
            if not g:
                self.phase = "standstill"
                return
        else:
            g = 1
            while g < TOP_GEAR and gear_rpm(g, self.v_sched_kmh) > _interp(self.pedal, UPSHIFT_RPM):
                g += 1
        self.gear = self.target_gear = g
        self.phase = "launch"
        self._want_gears(g, self._preselection())

    def _commands(self, stale=False):
        dt = PERIOD_S
        if stale:
            i1 = i2 = 0.0
            for loop in self.loops:
                loop.reset()
            forces = [0.0] * 4
        else:
            fill_s = FILL_TIME_S * _interp(self.oil_degc, FILL_TIME_OVER_TEMP)
            i1 = self.loops[0].current(self.pressure_bar[0], self.p_meas[0], dt, fill_s)
            i2 = self.loops[1].current(self.pressure_bar[1], self.p_meas[1], dt, fill_s)
            forces = self._fork_forces()
        request = self.torque_request_nm
        if not stale:
            limit = self._traction_limit()
            if limit is not None:
                request = limit if request is None else min(request, limit)
        active = request is not None and not stale and self.diag.torque_ok
        d = self.diag
        return {
            "SolenoidCurrent1": i1,
            "SolenoidCurrent2": i2,
            "LineSolenoidCurrent": LINE_CURRENT_A,
            "ForkForce1": forces[0],
            "ForkForce2": forces[1],
            "ForkForce3": forces[2],
            "ForkForce4": forces[3],
            "EngineTorqueRequest": request if active else 0.0,
            "TorqueRequestActive": 1 if active else 0,
            "TargetGear": self.target_gear,
            "ActiveFaults": d.active_bits,
            "FaultCount": min(d.fault_count, FAULT_COUNT_MAX),
            "LastFault": d.last_fault,
            "InhibitedGears": d.inhibited,
            "LimpHome": 1 if d.limp_home else 0,
            "ShiftActive": 1 if self.phase in SHIFT_PHASES else 0,
            "TcuPhase": PHASE_CODES[self.phase],
            "TcuState": d.state(self.phase),
        }
