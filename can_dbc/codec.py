"""The CAN contract in Python: the DBC through cantools, plus the end-to-end
protection every message carries.

The DBC (``DBC_PATH``) is the truth: message names, identifiers, lengths,
cycle times, signal layout, scaling and ranges all come from it. This module
adds what a DBC cannot say, the same algorithm as the protection kind
``dct`` of the table codec (can_dbc/protection.py, can_dbc/csrc/can_table.c):

* byte 0, signal ``CRC``: CRC-8/SAE-J1850 (polynomial 0x1D, initial value
  0xFF, final XOR 0xFF, not reflected) over the identifier as two bytes (low
  byte first) followed by data bytes 1 .. len-1;
* byte 1 bits 0-3, signal ``AliveCounter``: +1 per frame, wrapping 15 -> 0.

A receiver (:class:`E2eReceiver`) rejects a frame whose length is not the
DBC's, whose CRC is wrong, or whose counter repeats or jumps by more than 2;
the counter state moves on only with an accepted frame.

AUTOSAR E2E Profiles 5, 4 and 7 in Python (``p5_protect``, ``p5_check``,
``p4_protect``, ``p4_check``, ``p7_protect``, ``p7_check``,
``crc16_ccitt_false``, ``crc32_p4``, ``crc64``) compute what the table codec's
protection kinds ``p5``, ``p4`` and ``p7`` write, for offline tools and tests.
"""

import functools
import math
import os

DBC_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "dct_hil.dbc")

CRC_SIGNAL = "CRC"
COUNTER_SIGNAL = "AliveCounter"
E2E_SIGNALS = (CRC_SIGNAL, COUNTER_SIGNAL)

# results of E2eReceiver.check (the same order as CT_RX_* in can_table.h)
OK = "ok"
UNKNOWN_ID = "unknown_id"
BAD_LENGTH = "bad_length"
BAD_CRC = "bad_crc"
BAD_COUNTER = "bad_counter"
STATUSES = (OK, UNKNOWN_ID, BAD_LENGTH, BAD_CRC, BAD_COUNTER)
REJECTS = (BAD_LENGTH, BAD_CRC, BAD_COUNTER)

COUNTER_MAX_JUMP = 2          # a counter may advance by 1 or 2 (one frame lost)

# What the contract's mapping (mappings/dct_hil.toml) maps, for Python-side tools and tests
# (tests/test_mapping.py holds the two together):
# plant message signal -> field of dct_outputs ("o.") or the simulator's status ("st.")
PLANT_SIGNAL_SOURCES = {
    "DCT_ShaftSpeeds": {"EngineSpeed": "o.engine_speed_rpm", "InputShaft1Speed": "o.input_shaft1_speed_rpm",
                        "InputShaft2Speed": "o.input_shaft2_speed_rpm"},
    "DCT_OutputSpeeds": {"OutputShaft1Speed": "o.output_shaft1_speed_rpm",
                         "OutputShaft2Speed": "o.output_shaft2_speed_rpm"},
    "DCT_Clutch": {"ClutchPressure1": "o.clutch1_pressure_bar", "ClutchPressure2": "o.clutch2_pressure_bar",
                   "LinePressure": "o.line_pressure_bar"},
    "DCT_Shift": {"ForkPosition1": "o.fork1_position_mm", "ForkPosition2": "o.fork2_position_mm",
                  "ForkPosition3": "o.fork3_position_mm", "ForkPosition4": "o.fork4_position_mm",
                  "SyncState1": "o.sync1_state", "SyncState2": "o.sync2_state",
                  "SyncState3": "o.sync3_state", "SyncState4": "o.sync4_state",
                  "TransOilTemp": "o.trans_oil_temp_degc"},
    "VEH_Motion": {"VehicleSpeed": "o.vehicle_speed_kmh", "LongAccel": "o.vehicle_accel_mps2",
                   "RoadGrade": "o.road_grade_pct"},
    "VEH_Driver": {"AccelPedal": "o.accel_pedal_pct", "BrakePedal": "o.brake_pedal_pct",
                   "EngineTorque": "o.engine_torque_nm", "SelectorLever": "o.selector_lever"},
    "SIM_Status": {"SimTime": "st.sim_time_s", "OverrunCount": "st.overrun_count",
                   "TurnaroundMax": "st.turnaround_max_us", "SimState": "st.sim_state"},
}
# TCU message signal -> the command value it sets (and the dct_inputs field it drives;
# None for a signal the plant does not act on, recorded with the commands only: TargetGear
# and the TCU's diagnosis, TCU_Status, which a TCU may leave out: optional in the mapping)
TCU_SIGNAL_TARGETS = {
    "TCU_ClutchCmd": {"SolenoidCurrent1": ("solenoid_current1_a", "solenoid_current1_a"),
                      "SolenoidCurrent2": ("solenoid_current2_a", "solenoid_current2_a"),
                      "LineSolenoidCurrent": ("line_solenoid_current_a", "line_solenoid_current_a")},
    "TCU_ShiftCmd": {"ForkForce1": ("fork_force_n[0]", "fork_force1_n"),
                     "ForkForce2": ("fork_force_n[1]", "fork_force2_n"),
                     "ForkForce3": ("fork_force_n[2]", "fork_force3_n"),
                     "ForkForce4": ("fork_force_n[3]", "fork_force4_n")},
    "TCU_EngineCmd": {"EngineTorqueRequest": ("engine_torque_request_nm", "engine_torque_request_nm"),
                      "TorqueRequestActive": ("torque_request_active", "torque_request_active"),
                      "TargetGear": ("target_gear", None)},
    "TCU_Status": {"ActiveFaults": ("tcu_active_faults", None),
                   "InhibitedGears": ("tcu_inhibited_gears", None),
                   "LimpHome": ("tcu_limp_home", None),
                   "ShiftActive": ("tcu_shift_active", None),
                   "TcuPhase": ("tcu_phase", None),
                   "TcuState": ("tcu_state", None),
                   "FaultCount": ("tcu_fault_count", None),
                   "LastFault": ("tcu_last_fault", None)},
}
# safe values while a TCU message is timed out (the mapping's safe values)
TCU_SAFE_VALUES = {
    "TCU_ClutchCmd": {"SolenoidCurrent1": 0.0, "SolenoidCurrent2": 0.0, "LineSolenoidCurrent": 0.0},
    "TCU_ShiftCmd": {"ForkForce1": 0.0, "ForkForce2": 0.0, "ForkForce3": 0.0, "ForkForce4": 0.0},
    "TCU_EngineCmd": {"EngineTorqueRequest": 0.0, "TorqueRequestActive": 0, "TargetGear": 0},
    "TCU_Status": {"ActiveFaults": 0, "InhibitedGears": 0, "LimpHome": 0, "ShiftActive": 0, "TcuPhase": 0,
                   "TcuState": 0, "FaultCount": 0, "LastFault": 0},
}


def dbc_encoding(path):
    """The text encoding of the DBC at ``path``: ``utf-8`` when its bytes are valid
    UTF-8 (``utf-8-sig`` with a byte order mark), else ``cp1252`` (the DBC
    editors' default, which cantools assumes for every DBC). OSError when it cannot
    be read."""
    with open(path, "rb") as f:
        data = f.read()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return "cp1252"
    return "utf-8-sig" if data.startswith(b"\xef\xbb\xbf") else "utf-8"


def load_database(path):
    """The cantools database of the DBC at ``path`` (strict checks: no overlapping
    signals), its text decoded as :func:`dbc_encoding` says."""
    from can_dbc.python_can import python_can

    python_can()  # cantools imports can: without asammdf (can_dbc.python_can)
    import cantools

    try:
        return cantools.database.load_file(path, database_format="dbc", encoding=dbc_encoding(path),
                                           strict=True)
    except OSError as e:
        raise ValueError(f"cannot read DBC {path}: {e.strerror}") from None
    except Exception as e:  # cantools raises its own parse errors
        raise ValueError(f"bad DBC {path}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None


@functools.cache
def database():
    """The cantools database of can_dbc/dct_hil.dbc (loaded once)."""
    return load_database(DBC_PATH)


def message(name_or_id):
    """The cantools message of a name (``"TCU_ClutchCmd"``) or frame id (``0x080``)."""
    db = database()
    try:
        if isinstance(name_or_id, str):
            return db.get_message_by_name(name_or_id)
        return db.get_message_by_frame_id(int(name_or_id))
    except KeyError:
        what = name_or_id if isinstance(name_or_id, str) else f"frame id 0x{int(name_or_id):03X}"
        raise ValueError(f"unknown message {what} (not in {os.path.basename(DBC_PATH)})") from None


def messages(sender=None):
    """The DBC's messages, all or only those sent by node ``sender`` ("PLANT" or "TCU")."""
    msgs = database().messages
    if sender is None:
        return list(msgs)
    if sender not in [n.name for n in database().nodes]:
        raise ValueError(f"unknown node {sender!r} (the DBC has {', '.join(n.name for n in database().nodes)})")
    return [m for m in msgs if sender in m.senders]


def signal_bits(signal):
    """The frame bits (8 * byte + bit) a cantools signal occupies, in its own order."""
    if signal.byte_order == "little_endian":
        return list(range(signal.start, signal.start + signal.length))
    msb = 8 * (signal.start // 8) + 7 - signal.start % 8       # in network order
    return [8 * (k // 8) + 7 - k % 8 for k in range(msb, msb + signal.length)]


def payload_signals(msg):
    """The signals of a message other than CRC and AliveCounter."""
    return [s for s in msg.signals if s.name not in E2E_SIGNALS]


# ---------------------------------------------------------------------------
# CRC and end-to-end protection
# ---------------------------------------------------------------------------

def _crc8_table():
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC8_TABLE = _crc8_table()


def crc8_j1850(data):
    """CRC-8/SAE-J1850 of ``data`` (bytes-like): poly 0x1D, init 0xFF, xorout 0xFF.
    The standard check string b"123456789" gives 0x4B."""
    crc = 0xFF
    for b in bytes(data):
        crc = _CRC8_TABLE[crc ^ b]
    return crc ^ 0xFF


def _crc16_table():
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table.append(crc)
    return tuple(table)


_CRC16_TABLE = _crc16_table()


def crc16_ccitt_false(data, crc=0xFFFF):
    """CRC-16/CCITT-FALSE of ``data``: poly 0x1021, init 0xFFFF (or ``crc``, to
    go on from a previous part), not reflected, no final XOR; b"123456789"
    gives 0x29B1. The CRC of AUTOSAR E2E Profile 5."""
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _CRC16_TABLE[(crc >> 8) ^ b]
    return crc


def p5_crc(data, data_id, offset_bits=0):
    """The E2E Profile 5 CRC of a frame whose 3-byte header (CRC low, CRC high,
    counter) starts at bit ``offset_bits``: over the bytes before the header,
    the bytes after the CRC (the counter first), then the Data ID's low and
    high byte (the protection kind ``p5`` of can_dbc/protection.py)."""
    data = bytes(data)
    h = int(offset_bits) // 8
    crc = crc16_ccitt_false(data[:h])
    crc = crc16_ccitt_false(data[h + 2:], crc)
    return crc16_ccitt_false(bytes((data_id & 0xFF, (data_id >> 8) & 0xFF)), crc)


def p5_protect(data, data_id, counter, offset_bits=0):
    """``data`` with E2E Profile 5's counter (``counter`` mod 256) and CRC
    written into its header at bit ``offset_bits``."""
    buf = bytearray(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 3 > len(buf):
        raise ValueError(f"E2E Profile 5 header at bit {offset_bits} does not fit {len(buf)} data bytes")
    buf[h + 2] = int(counter) & 0xFF
    crc = p5_crc(buf, data_id, offset_bits)
    buf[h], buf[h + 1] = crc & 0xFF, crc >> 8
    return bytes(buf)


def p5_check(data, data_id, offset_bits=0):
    """(CRC right, counter) of a received E2E Profile 5 frame; the counter
    check against the last one is the receiver's (``max_delta_counter``)."""
    data = bytes(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 3 > len(data):
        return False, None
    crc = p5_crc(data, data_id, offset_bits)
    return (data[h] == crc & 0xFF and data[h + 1] == crc >> 8), data[h + 2]


def _reflected_crc_table(poly_reflected):
    """The byte table of a reflected CRC with this (reflected) polynomial."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ poly_reflected if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC32_P4_TABLE = _reflected_crc_table(0xC8DF352F)


def crc32_p4(data, crc=0xFFFFFFFF):
    """CRC-32P4 register over ``data`` (poly 0xF4ACFB13 reflected, init
    0xFFFFFFFF or ``crc`` to go on); the CRC is the result XOR 0xFFFFFFFF:
    b"123456789" gives 0x1697D06A. The CRC of AUTOSAR E2E Profile 4."""
    for b in bytes(data):
        crc = (crc >> 8) ^ _CRC32_P4_TABLE[(crc ^ b) & 0xFF]
    return crc


_CRC64_TABLE = _reflected_crc_table(0xC96C5795D7870F42)
_ONES64 = 0xFFFFFFFFFFFFFFFF


def crc64(data, crc=_ONES64):
    """CRC-64 register over ``data`` (ECMA-182 poly 0x42F0E1EBA9EA3693 reflected,
    init all ones or ``crc`` to go on); the CRC is the result XOR all ones:
    b"123456789" gives 0x995DC9BBDF1939FA (CRC-64/XZ). The CRC of E2E Profile 7."""
    for b in bytes(data):
        crc = (crc >> 8) ^ _CRC64_TABLE[(crc ^ b) & 0xFF]
    return crc


def p7_protect(data, data_id, counter, offset_bits=0):
    """``data`` with E2E Profile 7's header written at bit ``offset_bits``: the
    CRC-64 over every byte but its own, the length, the counter (``counter``
    mod 2^32) and the 32-bit Data ID, each big endian."""
    buf = bytearray(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 20 > len(buf):
        raise ValueError(f"E2E Profile 7 header at bit {offset_bits} does not fit {len(buf)} data bytes")
    buf[h + 8:h + 20] = (len(buf).to_bytes(4, "big") + (int(counter) & 0xFFFFFFFF).to_bytes(4, "big")
                         + int(data_id).to_bytes(4, "big"))
    crc = crc64(buf[h + 8:], crc64(buf[:h])) ^ _ONES64
    buf[h:h + 8] = crc.to_bytes(8, "big")
    return bytes(buf)


def p7_check(data, data_id, offset_bits=0):
    """(length, Data ID and CRC right, counter) of a received E2E Profile 7 frame."""
    data = bytes(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 20 > len(data):
        return False, None
    counter = int.from_bytes(data[h + 12:h + 16], "big")
    return data == p7_protect(data, data_id, counter, offset_bits), counter


def p4_protect(data, data_id, counter, offset_bits=0):
    """``data`` with E2E Profile 4's header written at bit ``offset_bits``: the
    length, the counter (``counter`` mod 65536), the 32-bit Data ID and the
    CRC-32P4 over every byte but the CRC's, each big endian."""
    buf = bytearray(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 12 > len(buf):
        raise ValueError(f"E2E Profile 4 header at bit {offset_bits} does not fit {len(buf)} data bytes")
    buf[h:h + 8] = (len(buf).to_bytes(2, "big") + (int(counter) & 0xFFFF).to_bytes(2, "big")
                    + int(data_id).to_bytes(4, "big"))
    crc = crc32_p4(buf[h + 12:], crc32_p4(buf[:h + 8])) ^ 0xFFFFFFFF
    buf[h + 8:h + 12] = crc.to_bytes(4, "big")
    return bytes(buf)


def p4_check(data, data_id, offset_bits=0):
    """(length, Data ID and CRC right, counter) of a received E2E Profile 4 frame."""
    data = bytes(data)
    h = int(offset_bits) // 8
    if offset_bits % 8 or h + 12 > len(data):
        return False, None
    return data == p4_protect(data, data_id, int.from_bytes(data[h + 2:h + 4], "big"), offset_bits), \
        int.from_bytes(data[h + 2:h + 4], "big")


def e2e_crc(frame_id, data):
    """The CRC byte of a frame: over id low byte, id high byte, data[1:]."""
    frame_id = int(frame_id)
    return crc8_j1850(bytes((frame_id & 0xFF, (frame_id >> 8) & 0xFF)) + bytes(data)[1:])


def protect(frame_id, data, counter):
    """``data`` with AliveCounter ``counter`` in byte 1 low nibble and the CRC in byte 0."""
    counter = _counter(counter)
    buf = bytearray(data)
    if len(buf) < 2:
        raise ValueError(f"frame 0x{int(frame_id):03X}: {len(buf)} data bytes, E2E needs at least 2")
    buf[1] = (buf[1] & 0xF0) | counter
    buf[0] = e2e_crc(frame_id, buf)
    return bytes(buf)


def _counter(counter):
    if isinstance(counter, bool) or not isinstance(counter, int) or not 0 <= counter <= 15:
        raise ValueError(f"AliveCounter must be an integer 0..15, got {counter!r}")
    return counter


# ---------------------------------------------------------------------------
# Encoding and decoding
# ---------------------------------------------------------------------------

def start_value(signal):
    """The physical value a sender sends for ``signal`` before it knows one: the
    DBC's GenSigStartValue (raw) scaled, or 0 for a signal without one (limited
    to the range by ``encode``). SelectorLever starts in D, TransOilTemp warm."""
    raw = signal.raw_initial
    if raw is None:
        return 0.0
    return float(raw) * signal.scale + signal.offset


def limit(signal, value):
    """``value`` limited to the signal's DBC range [minimum, maximum].

    A choice name (e.g. "engaged") is turned into its number first; +-inf go
    to the range ends; NaN and anything not a number raise ValueError."""
    if isinstance(value, str):
        choices = signal.choices or {}
        for number, name in choices.items():
            if str(name) == value:
                value = number
                break
        else:
            raise ValueError(f"signal {signal.name}: {value!r} is not one of its values "
                             f"({', '.join(str(n) for n in choices.values()) or 'no named values'})")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"signal {signal.name}: {value!r} is not a number") from None
    if math.isnan(v):
        raise ValueError(f"signal {signal.name}: value is NaN")
    lo = signal.minimum if signal.minimum is not None else -math.inf
    hi = signal.maximum if signal.maximum is not None else math.inf
    return min(max(v, lo), hi)


def encode(name, signals, counter):
    """One protected frame's data bytes of message ``name`` (or its frame id).

    ``signals`` maps payload signal names to physical values. Each value is
    limited to its signal's DBC range (``limit``: values below the minimum
    become the minimum, above the maximum the maximum), then cantools packs
    it, rounding to the nearest raw step. Payload signals not given are sent
    at their start value (``start_value``: the GenSigStartValue, else 0, limited
    to the range). Then AliveCounter = ``counter`` (0..15) and
    the CRC are written. Unknown signal names, CRC or AliveCounter among the
    signals, NaN and non-numbers raise ValueError."""
    msg = message(name)
    given = dict(signals or {})
    for key in given:
        if key in E2E_SIGNALS:
            raise ValueError(f"{msg.name}: {key} is written by encode, not given as a signal")
    known = {s.name: s for s in payload_signals(msg)}
    unknown = [k for k in given if k not in known]
    if unknown:
        raise ValueError(f"{msg.name} has no signal {unknown[0]} (it has {', '.join(known)})")
    values = {CRC_SIGNAL: 0, COUNTER_SIGNAL: _counter(counter)}
    for sig_name, sig in known.items():
        values[sig_name] = limit(sig, given[sig_name] if sig_name in given else start_value(sig))
    data = msg.encode(values, scaling=True, padding=False, strict=True)
    return protect(msg.frame_id, data, counter)


def decode(frame_id, data):
    """(message name, {signal: physical value}) of a frame; CRC and
    AliveCounter included. Does not check the E2E protection (see
    E2eReceiver). Unknown ids and wrong lengths raise ValueError."""
    msg = message(frame_id)
    data = bytes(data)
    if len(data) != msg.length:
        raise ValueError(f"frame 0x{msg.frame_id:03X} {msg.name}: {len(data)} data bytes, the DBC says {msg.length}")
    return msg.name, dict(msg.decode(data, decode_choices=False, scaling=True))


class E2eReceiver:
    """End-to-end check of received frames, per message (as ct_check for the kind ``dct``).

    ``names``: the messages it accepts (default: all of the DBC's, or those
    sent by node ``sender``). ``check(frame_id, data)`` returns one of
    STATUSES: ``unknown_id`` for an id not among them, ``bad_length`` when
    the length is not the DBC's, ``bad_crc``, ``bad_counter`` when the
    AliveCounter repeats or jumps by more than 2 (the first frame, and the
    first after ``reset``, is accepted with any counter), else ``ok``. The
    counter state moves on only with an accepted frame.

    ``counts[name]`` holds per message: received, and one count per status
    (ok, bad_length, bad_crc, bad_counter); ``unknown`` counts the frames
    with an id it does not accept."""

    def __init__(self, names=None, sender=None):
        if names is None:
            msgs = messages(sender)
        else:
            msgs = [message(n) for n in names]
        self._by_id = {m.frame_id: m for m in msgs}
        self.names = [m.name for m in msgs]
        self.last_counter = {m.name: -1 for m in msgs}
        self.counts = {m.name: {"received": 0, OK: 0, BAD_LENGTH: 0, BAD_CRC: 0, BAD_COUNTER: 0} for m in msgs}
        self.unknown = 0

    def reset(self, name=None):
        """Forget the counter state of one message (or of all): the next frame is accepted with any counter."""
        for n in ([name] if name is not None else self.names):
            self.last_counter[message(n).name] = -1

    def check(self, frame_id, data, is_extended_id=False):
        status, _msg = self._check(frame_id, data, is_extended_id)
        return status

    def receive(self, frame_id, data, is_extended_id=False):
        """(status, message name or None, decoded values or None): check, then decode an accepted frame."""
        status, msg = self._check(frame_id, data, is_extended_id)
        if status != OK:
            return status, (msg.name if msg is not None else None), None
        return status, msg.name, dict(msg.decode(bytes(data), decode_choices=False, scaling=True))

    def _check(self, frame_id, data, is_extended_id):
        msg = None if is_extended_id else self._by_id.get(int(frame_id))
        if msg is None:
            self.unknown += 1
            return UNKNOWN_ID, None
        status = self._status(msg, bytes(data))
        c = self.counts[msg.name]
        c["received"] += 1
        c[status] += 1
        return status, msg

    def _status(self, msg, data):
        if len(data) != msg.length:
            return BAD_LENGTH
        if data[0] != e2e_crc(msg.frame_id, data):
            return BAD_CRC
        counter = data[1] & 0x0F
        last = self.last_counter[msg.name]
        if last >= 0:
            step = (counter - last) % 16
            if step == 0 or step > COUNTER_MAX_JUMP:
                return BAD_COUNTER
        self.last_counter[msg.name] = counter
        return OK


# ---------------------------------------------------------------------------
# Bus load
# ---------------------------------------------------------------------------

def frame_bits_worst_case(data_bytes=8):
    """Bits of a classic CAN data frame with a standard 11-bit id and
    ``data_bytes`` data bytes, with worst-case bit stuffing:
    47 + 8 n + floor((34 + 8 n - 1) / 4). 8 bytes: 135 bits."""
    n = int(data_bytes)
    if not 0 <= n <= 8:
        raise ValueError(f"classic CAN carries 0..8 data bytes, not {data_bytes}")
    return 47 + 8 * n + (34 + 8 * n - 1) // 4


def bus_load(bitrate=1_000_000):
    """Worst-case bus load of the DBC's traffic as a fraction of ``bitrate``
    (0.339 = 33.9 %): sum over messages of frame_bits_worst_case(length) *
    1000 / GenMsgCycleTime[ms], divided by the bitrate."""
    if not bitrate or bitrate <= 0:
        raise ValueError(f"bitrate must be positive, got {bitrate!r}")
    bits_per_s = 0.0
    for m in database().messages:
        if not m.cycle_time:
            raise ValueError(f"message {m.name} has no GenMsgCycleTime")
        bits_per_s += frame_bits_worst_case(m.length) * 1000.0 / m.cycle_time
    return bits_per_s / bitrate
