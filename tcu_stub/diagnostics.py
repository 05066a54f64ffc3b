"""The reference TCU's on-board diagnostics: monitors, trouble codes, reactions; free of I/O.

``TcuLogic`` (tcu_stub/logic.py) owns one ``Diagnostics`` and calls it every
period (2 ms): ``messages(t_s, sensors)`` first (which plant messages are
stale, and why), then, when the plant's frames are there, ``monitor(t_s,
logic)`` on the signals the logic has just read. Each monitor tests one
condition per period and debounces it (``Monitor``: the condition's time
counts up while it holds and down while it does not; the trouble code sets
when the count reaches the monitor's detection time and heals after its heal
time without the condition). Every trouble code (DTC) is one bit of
``TCU_Status.ActiveFaults`` (set now); ``FaultCount`` counts the settings
since the TCU was reset and ``LastFault`` names the latest (1 + its bit), so
a bench condition such as ``TCU_Status.LastFault == 4`` waits for one code;
the node's report also keeps every code set since the reset (``stored``).

The reactions the logic applies are latched for the driving cycle (until
``TcuLogic.reset``, the next ignition cycle): a DTC that heals clears its bit,
not its reaction, except the engine message's (torque requests come back when
it heals) and the CAN ones (the stale handling of the plant messages, as
before: the logic recovers as soon as the messages are back).

=== ======================= ================================================ ============= =====================
bit name                    condition                                        detection     reaction
=== ======================= ================================================ ============= =====================
0   input_speed1            InputShaft1Speed invalid (not finite, or beyond  20 ms;        half 1 (K1: 1, 3, 5)
                            SPEED_INVALID_RPM: the DBC's invalid raw value   100 ms        avoided (below)
                            0x8000 is -16384 rpm), or off OutputShaftSpeed x
                            the ratio of the gear engaged on input shaft 1
                            by more than max(200 rpm, 5 %)
1   input_speed2            the same for input shaft 2                       20; 100 ms    half 2 (K2: 2, 4, 6)
                                                                                           avoided
2   clutch1_pressure        ClutchPressure1 off the pressure the TCU         200 ms        K1 opened, limp home
                            commands by more than max(3 bar, 25 %), or                     on K2 in 2nd
                            invalid (not finite, above 65 bar: raw 0xFFFF)
3   clutch2_pressure        the same for K2                                  200 ms        K2 opened, limp home
                                                                                           on K1 in 3rd
4   line_pressure           LinePressure below 15 bar (20 bar nominal, the   100 ms        safe state: both
                            clamp pressure is 14 bar)                                      clutches open, no fork
                                                                                           force, limp home
5   clutch1_slip            K1 commanded closed (drive, lock pressure) and   200 ms        K1 lock pressure
                            EngineSpeed - InputShaft1Speed beyond 100 rpm                  raised to 19 bar; slip
                            (friction fade)                                                on for 500 ms more:
                                                                                           limp home on K2
6   clutch2_slip            the same for K2                                  200 ms        the same, on K1
7   gear_engagement         a gear the TCU asks for (pre-selection, launch   1000 ms       its shaft's sleeves
                            or shift gear) not engaged (SyncState engaged,                 let go (0.1 s), the
                            fork beyond 7 mm) after ENGAGE_SET_S of                        gear asked again; a
                            continuous request (a jammed fork; a failed                    second failure in a
                            blocker ring engages, with a clash the TCU                     row: the gear inhibited
                            does not see)                                                  (InhibitedGears), the
                                                                                           next allowed gear used
8   engine_message          the engine message (VEH_Driver: EngineTorque,    the node's    torque requests off
                            the pedals) stale: timed out or rejected         stale time    (TorqueRequestActive
                                                                             (10 cycles,   0) until it heals; the
                                                                             3 rejects)    last values stand in;
                                                                                           the gearbox drives on
9   can_crc                 a plant message stale by bad CRCs                 3 frames      plant message stale:
10  can_counter             ... by bad AliveCounters                          3 frames      as before (clutches
11  can_length              ... by wrong lengths                              3 frames      open, recovery when
12  can_timeout             ... timed out (10 cycles), or missing 1 s after   10 cycles     back) unless it is
                            the plant's first frames                                       the engine message
=== ======================= ================================================ ============= =====================

Heal times: 1 s without the condition (``HEAL_S``). A monitor is not
evaluated (its count frozen) while its inputs cannot tell: the speed
plausibility without a gear engaged on that shaft, the clutch pressures while
the line pressure is low, the slip unless the clutch is commanded closed and
its shaft speed is healthy, nothing while the plant messages are stale. A
message missing since the start (no frame yet) is the start-up, not a fault,
for ``STARTUP_S`` after the plant's first frames.

An invalid input shaft speed is replaced at once (before its DTC sets) by
the speed of the gear engaged on that shaft, else by the last valid value.

Avoiding a half (input speed, clutch pressure, slip limp home): its gears are
inhibited and its sleeves go to neutral; a drive in one of its gears opens
that clutch in the TCU period the DTC sets (0 A at once) and the TCU engages
the gear for the speed on the other half (``shift_open``: both clutches open,
the engine brought to the new gear's shaft speed by a torque request), then
closes its clutch by the lock ramp (by slip control, ``launch``, below 1100
rpm). While the avoided half still holds a gear with its clutch pressure up
(a valve stuck closed), the TCU requests zero engine torque, so that sleeve
can leave its gear, and keeps the other clutch open: no tie-up. Limp home
(``LimpHome`` 1) also inhibits the healthy half's gears below the limp gear
(``LIMP_GEAR``: 2nd on K2, 3rd on K1) and shifts up only to protect the
engine (``logic.LIMP_UPSHIFT_RPM``). Shifts between two gears of one half are
interrupted shifts (``shift_open``). With no gear left, or the line pressure
low, the TCU holds the safe state (phase ``safe``, TcuState 4 "fault").
"""

import math

# ------------------------------------------------------------------ trouble codes (bits)
DTC_INPUT_SPEED1 = 0
DTC_INPUT_SPEED2 = 1
DTC_CLUTCH1_PRESSURE = 2
DTC_CLUTCH2_PRESSURE = 3
DTC_LINE_PRESSURE = 4
DTC_CLUTCH1_SLIP = 5
DTC_CLUTCH2_SLIP = 6
DTC_GEAR_ENGAGEMENT = 7
DTC_ENGINE_MESSAGE = 8
DTC_CAN_CRC = 9
DTC_CAN_COUNTER = 10
DTC_CAN_LENGTH = 11
DTC_CAN_TIMEOUT = 12

# ------------------------------------------------------------------ detection and heal times
HEAL_S = 1.0                        # every DTC heals after this long without its condition
SPEED_INVALID_RPM = 16383.0         # beyond: invalid (range +-16383.5 rpm; invalid raw 0x8000 = -16384 rpm)
SPEED_INVALID_SET_S = 0.02
SPEED_TOLERANCE_RPM = 200.0         # healthy runs: at most 58 rpm off (paper cycle, 0-100, WLTC)
SPEED_TOLERANCE_SHARE = 0.05
SPEED_IMPLAUSIBLE_SET_S = 0.1
PRESSURE_INVALID_BAR = 65.0         # above: invalid (the raw 0xFFFF is 65.535 bar)
PRESSURE_TOLERANCE_BAR = 3.0        # healthy runs: beyond max(3 bar, 25 %) for at most 36 ms
PRESSURE_TOLERANCE_SHARE = 0.25
PRESSURE_SET_S = 0.2
LINE_LOW_BAR = 15.0                 # healthy runs: 20 bar throughout
LINE_SET_S = 0.1
SLIP_RPM = 100.0                    # healthy runs: a locked clutch slips at most 5 rpm
SLIP_SET_S = 0.2
SLIP_LIMP_S = 0.5                   # slip still there this long with the raised pressure: limp home
ENGAGE_SET_S = 1.0                  # healthy runs: a requested gear engages within 0.56 s
ENGAGE_RELEASE_S = 0.1              # a first failure: the shaft's sleeves go to neutral this long, then a retry
STARTUP_S = 1.0                     # a message never received counts as lost this long after the plant's first frames
MAX_DT_S = 0.02                     # longest time one period counts (a TCU paused for longer)
PERIOD_FIRST_S = 0.002              # the first period's time (no earlier period to measure from)

#: the gear each healthy half limps home in: K1 (input shaft 1) healthy -> 3rd, K2 -> 2nd
LIMP_GEAR = (3, 2)
#: plant messages whose loss the TCU rides out (their signals are these only)
ENGINE_MESSAGES = ("VEH_Driver",)
ENGINE_SIGNALS = ("AccelPedal", "BrakePedal", "EngineTorque", "SelectorLever")   # the driver's, with the engine's torque

# gear -> input shaft 0/1 (as logic.GEAR_LAYOUT)
_GEAR_SHAFT = {1: 0, 2: 1, 3: 0, 4: 1, 5: 0, 6: 1}
_SHAFT_GEARS_MASK = (0b010101, 0b101010)     # gears 1, 3, 5 / 2, 4, 6 as InhibitedGears bits
# a stale message's cause (can_tcu: missing, timeout, or the reject kind) -> DTC bit
_CAUSE_DTC = {"timeout": DTC_CAN_TIMEOUT, "missing": DTC_CAN_TIMEOUT, "rejected": DTC_CAN_CRC,
              "bad_crc": DTC_CAN_CRC, "bad_counter": DTC_CAN_COUNTER, "bad_length": DTC_CAN_LENGTH}

#: TcuState (TCU_Status; the vehicle matrix's TCU_Gear.TcuState has the same values)
STATE_INITIALISING, STATE_NORMAL, STATE_SUBSTITUTE, STATE_LIMP_HOME, STATE_FAULT = 0, 1, 2, 3, 4


class Dtc:
    """One trouble code: its bit, name, what sets it, how fast, and the reaction."""
    __slots__ = ("bit", "name", "condition", "detection", "reaction")

    def __init__(self, bit, name, condition, detection, reaction):
        self.bit, self.name, self.condition, self.detection, self.reaction = bit, name, condition, detection, reaction

    def __repr__(self):
        return f"Dtc({self.bit}, {self.name!r})"


#: bit -> Dtc, the table of the module's text
DTCS = {d.bit: d for d in (
    Dtc(DTC_INPUT_SPEED1, "input_speed1",
        "InputShaft1Speed invalid, or off OutputShaftSpeed x the engaged gear's ratio by more than "
        "max(200 rpm, 5 %)", "20 ms invalid, 100 ms implausible",
        "half 1 (K1: gears 1, 3, 5) avoided: K1 opened, the gear for the speed engaged on K2"),
    Dtc(DTC_INPUT_SPEED2, "input_speed2",
        "InputShaft2Speed invalid, or off OutputShaftSpeed x the engaged gear's ratio by more than "
        "max(200 rpm, 5 %)", "20 ms invalid, 100 ms implausible",
        "half 2 (K2: gears 2, 4, 6) avoided: K2 opened, the gear for the speed engaged on K1"),
    Dtc(DTC_CLUTCH1_PRESSURE, "clutch1_pressure",
        "ClutchPressure1 off the commanded pressure by more than max(3 bar, 25 %), or invalid", "200 ms",
        "K1 opened, limp home on K2 in 2nd (LimpHome 1)"),
    Dtc(DTC_CLUTCH2_PRESSURE, "clutch2_pressure",
        "ClutchPressure2 off the commanded pressure by more than max(3 bar, 25 %), or invalid", "200 ms",
        "K2 opened, limp home on K1 in 3rd (LimpHome 1)"),
    Dtc(DTC_LINE_PRESSURE, "line_pressure", "LinePressure below 15 bar", "100 ms",
        "safe state: both clutches open, no fork force, no torque request (LimpHome 1)"),
    Dtc(DTC_CLUTCH1_SLIP, "clutch1_slip", "K1 commanded closed and slipping by more than 100 rpm", "200 ms",
        "K1 lock pressure raised to 19 bar; still slipping 500 ms later: limp home on K2"),
    Dtc(DTC_CLUTCH2_SLIP, "clutch2_slip", "K2 commanded closed and slipping by more than 100 rpm", "200 ms",
        "K2 lock pressure raised to 19 bar; still slipping 500 ms later: limp home on K1"),
    Dtc(DTC_GEAR_ENGAGEMENT, "gear_engagement", "a requested gear not engaged after 1 s of request",
        "1000 ms", "its shaft's sleeves let go for 0.1 s and the gear asked again; failing again: "
        "the gear inhibited (InhibitedGears), the next allowed gear used"),
    Dtc(DTC_ENGINE_MESSAGE, "engine_message", "the engine message (VEH_Driver) timed out or rejected",
        "the node's: 10 cycles or 3 rejected frames",
        "no torque requests (TorqueRequestActive 0) until it heals; the last values stand in"),
    Dtc(DTC_CAN_CRC, "can_crc", "a plant message stale by bad CRCs", "3 frames in a row",
        "that message stale (clutches open unless it is the engine message)"),
    Dtc(DTC_CAN_COUNTER, "can_counter", "a plant message stale by bad AliveCounters", "3 frames in a row",
        "that message stale (clutches open unless it is the engine message)"),
    Dtc(DTC_CAN_LENGTH, "can_length", "a plant message stale by wrong lengths", "3 frames in a row",
        "that message stale (clutches open unless it is the engine message)"),
    Dtc(DTC_CAN_TIMEOUT, "can_timeout", "a plant message timed out (or never received 1 s after the others)",
        "10 cycle times", "that message stale (clutches open unless it is the engine message)"),
)}
DTC_NAMES = tuple(DTCS[b].name for b in sorted(DTCS))


def decode_active_faults(bits):
    """The DTC names of an ActiveFaults value (or of ``Diagnostics.stored_bits``), lowest bit first."""
    bits = int(bits)
    return [d.name for b, d in sorted(DTCS.items()) if bits >> b & 1]


def gear_mask(gears):
    """InhibitedGears bits of an iterable of gears 1..6."""
    mask = 0
    for g in gears:
        mask |= 1 << (int(g) - 1)
    return mask


def inhibited_gears(mask):
    """The gears of an InhibitedGears value."""
    return [g for g in range(1, 7) if int(mask) >> (g - 1) & 1]


class Monitor:
    """Debounce of one condition: ``update(failing, t_s, dt)`` each period with
    True (the condition holds), False (it does not) or None (not evaluated:
    nothing counts). The condition's time counts up while it holds and down
    (to 0) while it does not; the monitor sets when it reaches ``set_s`` (0:
    at the first period) and heals after ``heal_s`` in a row without it."""
    __slots__ = ("bit", "set_s", "heal_s", "fail_s", "pass_s", "active")

    def __init__(self, bit, set_s, heal_s=HEAL_S):
        self.bit, self.set_s, self.heal_s = bit, set_s, heal_s
        self.reset()

    def reset(self):
        self.fail_s = 0.0
        self.pass_s = 0.0
        self.active = False

    def update(self, failing, dt):
        """True in the period the monitor sets."""
        if failing is None:
            return False
        if failing:
            self.pass_s = 0.0
            if not self.active:
                self.fail_s += dt
                if self.fail_s >= self.set_s - 1e-9:
                    self.active = True
                    return True
            return False
        if self.fail_s > 0.0:
            self.fail_s = max(self.fail_s - dt, 0.0)
        if self.active:
            self.pass_s += dt
            if self.pass_s >= self.heal_s - 1e-9:
                self.active = False
                self.fail_s = 0.0
        return False


class Diagnostics:
    """The monitors and the reactions they latch (see the module's text).

    For the logic: ``stale`` (plant messages lost: clutches open),
    ``engine_lost`` (the engine message stale now: hold its last values),
    ``torque_ok`` (torque requests allowed), ``inhibited`` (gear bits),
    ``limp_home``, ``safe_state``, ``boost`` (per clutch: lock pressure
    raised). For TCU_Status: ``active_bits``, ``fault_count``,
    ``last_fault`` (1 + the bit set last); ``stored_bits``: every bit set
    since the reset (the node's report). ``events``: (TCU time s, DTC name, "set" or "healed"),
    ``set_t_s``: {DTC name: TCU time it last set}.

    ``engine_messages``: the plant messages whose loss the TCU rides out (the
    contract's ``VEH_Driver``; a node on another matrix names its own)."""

    MAX_EVENTS = 1000

    def __init__(self, engine_messages=ENGINE_MESSAGES):
        self.engine_messages = frozenset(engine_messages)
        b = DTC_INPUT_SPEED1
        self._speed_invalid = (Monitor(b, SPEED_INVALID_SET_S), Monitor(b + 1, SPEED_INVALID_SET_S))
        self._speed_plausible = (Monitor(b, SPEED_IMPLAUSIBLE_SET_S), Monitor(b + 1, SPEED_IMPLAUSIBLE_SET_S))
        self._pressure = (Monitor(DTC_CLUTCH1_PRESSURE, PRESSURE_SET_S), Monitor(DTC_CLUTCH2_PRESSURE, PRESSURE_SET_S))
        self._line = Monitor(DTC_LINE_PRESSURE, LINE_SET_S)
        self._slip = (Monitor(DTC_CLUTCH1_SLIP, SLIP_SET_S), Monitor(DTC_CLUTCH2_SLIP, SLIP_SET_S))
        self._engage = Monitor(DTC_GEAR_ENGAGEMENT, 0.0)
        self._engine = Monitor(DTC_ENGINE_MESSAGE, 0.0)
        self._can = tuple(Monitor(bit, 0.0) for bit in (DTC_CAN_CRC, DTC_CAN_COUNTER, DTC_CAN_LENGTH,
                                                         DTC_CAN_TIMEOUT))
        self._monitors = (self._speed_invalid + self._speed_plausible + self._pressure + (self._line,)
                          + self._slip + (self._engage, self._engine) + self._can)
        self.reset()

    def reset(self):
        for m in self._monitors:
            m.reset()
        self.active_bits = 0
        self.stored_bits = 0
        self.fault_count = 0
        self.last_fault = 0              # 1 + the bit of the DTC set last (0: none)
        self.events = []
        self.set_t_s = {}
        self.stale = False
        self.engine_lost = False
        self.torque_ok = True
        self.inhibited = 0
        self.blocked_shafts = 0          # bit 0: input shaft 1's half avoided, bit 1: shaft 2's
        self.limp_home = False
        self.safe_state = False
        self.boost = [False, False]
        self.plant_seen_t_s = None       # TCU time of the first period with the plant's frames
        self._t_prev = None
        self._dt = 0.0
        self._can_busy = False
        self._engage_gear = [0, 0]
        self._engage_wait_s = [0.0, 0.0]
        self._engage_failed = 0          # gear bits: failed once since they last engaged
        self.release_s = [0.0, 0.0]      # per input shaft: its sleeves let go (to neutral) this long
        self._slip_limp_s = [0.0, 0.0]

    # ------------------------------------------------------------ messages
    def messages(self, t_s, sensors):
        """Which plant messages are stale (``sensors["stale_messages"]``:
        {name: "missing" | "timeout" | "bad_crc" | "bad_counter" | "bad_length"
        | "rejected"}; without it ``sensors["stale"]``: all of them, cause
        unknown). Updates the CAN and engine message DTCs; returns True when
        the logic must treat the plant as lost (any message but the engine
        message stale)."""
        dt = PERIOD_FIRST_S if self._t_prev is None else min(max(t_s - self._t_prev, 0.0), MAX_DT_S)
        self._t_prev = t_s
        self._dt = dt
        causes = sensors.get("stale_messages")
        seen = self.plant_seen_t_s
        late = seen is not None and t_s - seen >= STARTUP_S - 1e-9
        kinds = 0
        engine = engine_fault = False
        if causes is None:
            stale = bool(sensors.get("stale"))
            if stale and seen is not None:
                kinds = 1 << DTC_CAN_TIMEOUT
        else:
            stale = False
            for name, why in causes.items():
                counts = why != "missing" or late
                if name in self.engine_messages:
                    engine = True
                    engine_fault = engine_fault or counts
                else:
                    stale = True
                if counts:
                    kinds |= 1 << _CAUSE_DTC.get(why, DTC_CAN_TIMEOUT)
        if not stale and seen is None:
            self.plant_seen_t_s = seen = t_s
        self.stale = stale
        self.engine_lost = engine
        if kinds or self._can_busy:
            busy = False
            for m in self._can:
                self._update(m, bool(kinds >> m.bit & 1), t_s)
                busy = busy or m.active or m.fail_s > 0.0
            self._can_busy = busy
        self._update(self._engine, engine_fault if seen is not None else None, t_s)
        self.torque_ok = not engine and not self._engine.active
        return stale

    # ------------------------------------------------------------ signals
    def monitor(self, t_s, logic):
        """The signal monitors on what ``logic`` read this period (its
        ``_read``) and commanded last period; then the reactions."""
        dt = self._dt
        layout = logic.GEAR_LAYOUT
        # line pressure first: the clutch pressures mean nothing without it
        line = logic.line_bar
        if line is None:
            self._update(self._line, None, t_s)
        else:
            self._update(self._line, not (line >= LINE_LOW_BAR), t_s)
        line_low = self._line.active or self._line.fail_s > 0.0
        speed_bad = [False, False]
        for s in (0, 1):
            n = logic.n_shaft_raw[s]
            invalid = not math.isfinite(n) or abs(n) > SPEED_INVALID_RPM
            self._update(self._speed_invalid[s], invalid, t_s)
            g = logic.engaged_gear[s]
            if invalid:
                plausible_fail = None            # the invalid monitor's case
            elif g:
                expect = logic.gear_input_rpm(g)
                plausible_fail = abs(n - expect) > max(SPEED_TOLERANCE_RPM, SPEED_TOLERANCE_SHARE * abs(expect))
            else:
                plausible_fail = None
            self._update(self._speed_plausible[s], plausible_fail, t_s)
            speed_bad[s] = (invalid or plausible_fail is True or self._speed_invalid[s].active
                            or self._speed_plausible[s].active)
            # clutch pressure against the target of the last period
            p = logic.p_meas[s]
            target = logic.loops[s].target_bar
            if not math.isfinite(p) or p > PRESSURE_INVALID_BAR:
                fail = True
            elif line_low:
                fail = None
            else:
                fail = abs(p - target) > max(PRESSURE_TOLERANCE_BAR, PRESSURE_TOLERANCE_SHARE * target)
            self._update(self._pressure[s], fail, t_s)
            # slip of the clutch commanded closed
            slip_fail = None
            if (logic.phase == "drive" and layout[logic.gear][0] == s and not speed_bad[s]
                    and logic.pressure_bar[s] >= logic.CLUTCH_LOCK_BAR - 1e-9 and fail is False):
                slip_fail = abs(logic.n_engine - n) > SLIP_RPM
            if self._update(self._slip[s], slip_fail, t_s):
                self.boost[s] = True
            if slip_fail and self.boost[s] and self._slip[s].active:
                self._slip_limp_s[s] += dt
                if self._slip_limp_s[s] >= SLIP_LIMP_S - 1e-9:
                    self._limp(s)
            elif slip_fail is False:
                self._slip_limp_s[s] = 0.0
            # gear engagement: the gear asked for on this shaft (not counted while its
            # sleeves are let go for a retry)
            want = logic.requested_gear(s)
            if want != self._engage_gear[s]:
                self._engage_gear[s] = want
                self._engage_wait_s[s] = 0.0
            if self.release_s[s] > 0.0:
                self.release_s[s] = max(self.release_s[s] - dt, 0.0)
                self._engage_wait_s[s] = 0.0
            elif want > 0 and want != g:               # R is not monitored
                self._engage_wait_s[s] += dt
            else:
                self._engage_wait_s[s] = 0.0
                if want > 0:
                    self._engage_failed &= ~(1 << (want - 1))     # engaged: a retry again next time
        engage_fail = False
        for s in (0, 1):
            if self._engage_wait_s[s] >= ENGAGE_SET_S - 1e-9:
                engage_fail = True
                bit = 1 << (self._engage_gear[s] - 1)
                if self._engage_failed & bit:
                    self.inhibited |= bit                      # the retry failed too
                else:
                    self._engage_failed |= bit                 # let the sleeves go, then once more
                    self.release_s[s] = ENGAGE_RELEASE_S
                self._engage_wait_s[s] = 0.0
        self._update(self._engage, engage_fail, t_s)
        # reactions
        for s in (0, 1):
            if self._speed_invalid[s].active or self._speed_plausible[s].active:
                self._block(s)
            if self._pressure[s].active:
                self._limp(s)
        if self._line.active:
            self.safe_state = True
            self.limp_home = True
        if self.inhibited & 0b111111 == 0b111111:
            self.safe_state = True

    def _block(self, shaft):
        self.blocked_shafts |= 1 << shaft
        self.inhibited |= _SHAFT_GEARS_MASK[shaft]

    def _limp(self, shaft):
        """Limp home on the other half: this half avoided, the other half's gears below its limp gear too."""
        self._block(shaft)
        if not self.limp_home:
            self.limp_home = True
            healthy = 1 - shaft
            for g in range(1, LIMP_GEAR[healthy]):
                if _GEAR_SHAFT[g] == healthy:
                    self.inhibited |= 1 << (g - 1)

    def _update(self, monitor, failing, t_s):
        """Debounce one monitor, keep the bits and the events; True when it set."""
        if not failing and not monitor.active and monitor.fail_s == 0.0:
            return False                  # healthy and idle, or not evaluated: nothing to count
        was = monitor.active
        new = monitor.update(failing, self._dt)
        if monitor.active != was:
            self._recount(monitor.bit, t_s)
        return new

    def _recount(self, bit, t_s):
        mask = 1 << bit
        now = any(m.active for m in self._monitors if m.bit == bit)
        before = bool(self.active_bits & mask)
        if now == before:
            return
        name = DTCS[bit].name
        if now:
            self.active_bits |= mask
            self.stored_bits |= mask
            self.fault_count += 1
            self.last_fault = bit + 1
            self.set_t_s[name] = t_s
        else:
            self.active_bits &= ~mask
        if len(self.events) < self.MAX_EVENTS:
            self.events.append((t_s, name, "set" if now else "healed"))

    # ------------------------------------------------------------ views
    def state(self, phase):
        """TcuState: 0 initialising, 1 normal, 2 substitute program, 3 limp home, 4 fault."""
        if self.plant_seen_t_s is None:
            return STATE_INITIALISING
        if self.safe_state or phase == "stale":
            return STATE_FAULT
        if self.limp_home:
            return STATE_LIMP_HOME
        if self.active_bits or self.inhibited or not self.torque_ok:
            return STATE_SUBSTITUTE
        return STATE_NORMAL

    def report(self):
        """JSON-ready: active and stored DTC names, the count, inhibited gears, the reactions, events."""
        return {
            "active": decode_active_faults(self.active_bits),
            "stored": decode_active_faults(self.stored_bits),
            "fault_count": self.fault_count,
            "inhibited_gears": inhibited_gears(self.inhibited),
            "limp_home": self.limp_home,
            "safe_state": self.safe_state,
            "events": [{"t_s": round(t, 4), "dtc": name, "what": what} for t, name, what in self.events],
        }

