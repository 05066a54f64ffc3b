"""The XCP 1.4 protocol layer of the plant server's slave.

Independent of the transport and of the loop: a ``Slave`` takes one command
packet (CTO) at a time (``handle``) and returns the packets to send back
(a positive response, an error, or nothing). Memory and measurement go
through two pluggable backends:

* ``Memory``: ``read(address, n)`` (bytes, or an XCP error code),
  ``write(address, data)`` (``OK`` or an XCP error code: ERR_WRITE_PROTECTED,
  ERR_OUT_OF_RANGE, ERR_ACCESS_DENIED, ...), ``write_queued`` (the same for
  STIM, without waiting for the write to be applied) and ``cal_regions()``
  (the calibration regions, for the reference page). Address extension 0 only.
* ``Daq``: ``apply(lists)`` (a whole DAQ configuration with each list's
  running flag: starting and stopping lists is applying a new one),
  ``pop(n)`` (the measured ODTs, ``Dto``) and ``dropped()`` (ODTs lost by the
  producer: the overload indication).

What the slave declares (CONNECT and the GET_*_INFO commands):

* resources CAL/PAG and DAQ, and STIM when an event channel takes STIM
  lists (``stim_events``; STIM is not locked apart by seed & key: a STIM
  list needs DAQ and CAL/PAG unlocked); Intel byte order; address granularity BYTE;
  master block mode (DOWNLOAD + DOWNLOAD_NEXT, MAX_BS 2, MIN_ST 0), no slave
  block mode, no interleaved mode; MAX_CTO 252 (a multiple of 4, one
  command fits any UDP datagram);
* MAX_DTO 252 = the 4-byte identification field + ``Limits.odt_bytes``
  (248, RT_DAQ_ODT_BYTES): a master filling an ODT up to MAX_DTO never
  exceeds what one loop DTO carries; the first ODT of a list with
  timestamps holds 4 bytes less;
* DTO identification field: relative ODT number and absolute DAQ list
  number, word aligned (``[odt, 0, daq lo, daq hi]``); timestamps selectable
  per list (SET_DAQ_LIST_MODE bit 4), 4 bytes, unit 1 us, in the first ODT
  after the identification field;
* the DAQ clock is CLOCK_MONOTONIC (``time.monotonic_ns``) in 1 us
  (GET_DAQ_CLOCK, GET_DAQ_RESOLUTION_INFO, the DTOs' timestamps: the low
  32 bits of the tick deadline in us). TIME_CORRELATION_PROPERTIES (XCP
  1.3): the clock is the XCP slave's own, free running, readable at any
  time, never synchronised (no grandmaster, no ECU clock, no time sync
  bridge); a master asking for the extended response format gets
  GET_DAQ_CLOCK as trigger info, payload format and the clock's full 64 bits
  (DLONG) with the sync state, until the next CONNECT (legacy: the low 32
  bits). Its clock information (GET_CLK_INFO, then UPLOAD of 24 bytes at the
  MTA): an EUI-64 of the host's boot (``clock_uuid``: CLOCK_MONOTONIC is one
  clock per boot), 1 tick of 1 us, stratum unknown (255), native size 8
  bytes, no wrap-around before 2**64 - 1; CLOCK_MONOTONIC counts from an
  arbitrary origin (the boot), which the slave clock's information has no
  field for (the standard gives an epoch to a grandmaster's clock only). A
  cluster id is kept and answered; GET_DAQ_CLOCK_MULTICAST is not served;
* dynamic DAQ (FREE_DAQ, ALLOC_DAQ, ALLOC_ODT, ALLOC_ODT_ENTRY) within the
  loop's limits (``Limits``: RT_DAQ_MAX_LISTS / ODTS / ENTRIES, ODT bytes);
  more is refused with ERR_MEMORY_OVERFLOW; prescaler supported; overload
  indicated by the event EV_DAQ_OVERLOAD;
* STIM (with ``stim_events``): SET_DAQ_LIST_MODE's DIRECTION bit makes a
  list a STIM list, on an event channel that takes STIM (GET_DAQ_EVENT_INFO,
  GET_DAQ_LIST_INFO say which), without timestamp or prescaler; starting one
  checks that every entry lies in a calibration region (else
  ERR_WRITE_PROTECTED) and that its ODT numbers stay below 0xC0. A STIM DTO
  from the master (a packet whose first byte, the relative ODT number, is
  below 0xC0, with the DAQ list number as the DTOs' identification field
  has it, no timestamp) is decoded by its list's ODT and written like a
  DOWNLOAD (page rules, the backend's region and range checks; adjacent
  entries of an ODT in one write, applied whole at one tick boundary by the
  loop) with ``Memory.write_queued``: nobody waits for it to be applied;
  it gets no answer. A STIM DTO for no running STIM list, an unknown
  ODT, a wrong length, or a value refused, is dropped and counted by reason
  (``counters()``: ``ignored`` as ``stim_REASON``, and ``stim``);
* BUILD_CHECKSUM: XCP_CRC_32 (the CRC-32 of IEEE 802.3, zlib's) over the
  MTA's next ``block size`` bytes as UPLOAD reads them; the MTA advances past
  them; at most ``MAX_CHECKSUM_BLOCK`` bytes (more: ERR_OUT_OF_RANGE with
  that maximum, as the standard has it);
* MODIFY_BITS: the 32-bit value at the MTA (Intel order) becomes
  ``(value & ~(~MA << S)) ^ (MX << S)``, written like a DOWNLOAD (only the
  bytes the masks touch; the MTA stays);
* DOWNLOAD of more than MAX_CTO - 2 bytes (at most 255) starts a master
  block: the rest follows in DOWNLOAD_NEXT packets, each with the count still
  to come; only the last is answered, and the whole block is one write.
  A DOWNLOAD_NEXT with a wrong count (or without a block) answers
  ERR_SEQUENCE with the count expected, and the block is dropped; any other
  command drops it too (a DOWNLOAD answers ERR_SEQUENCE: it would write at
  the block's start), except a DOWNLOAD carrying exactly the count still to
  come, taken as the block's last packet (pyxcp 0.29's ``push`` sends a
  two-packet block's end so);
* one calibration segment (0) spanning the calibration regions, two pages:
  0 the working page (the loop's memory), 1 the reference page (read only:
  the regions' values when the slave was made). ECU page 1 puts the
  reference values into the loop and keeps the working values aside until
  ECU page 0; COPY_CAL_PAGE 1 -> 0 writes the reference values back.

GET_ID: type 0 the slave's name, type 1 the A2L file's name (without path
and extension), type 4 the A2L file itself by UPLOAD (the response gives its
length and sets the MTA to its start, as XCPlite does; the text comes from
a callable, asked at each GET_ID 4), type 5 the EPK (the A2L's MOD_PAR EPK,
when given). Other types: length 0 (not available). The EPK is also memory:
UPLOAD and SHORT_UPLOAD within its bytes at ``EPK_ADDRESS`` (the A2L's
ADDR_EPK) answer them, as a calibration tool reads it to check the A2L
against the slave; writes there are refused (ERR_WRITE_PROTECTED).

Seed & key (only with a secret, e.g. from ``--xcp-key FILE``): CAL/PAG and
DAQ start locked at every CONNECT. GET_SEED gives 16 random bytes; the key
is the first 16 bytes of HMAC-SHA256(secret, seed) (``compute_key``; the
master's side is ``seed_n_key_function`` for pyxcp). A wrong key answers
ERR_ACCESS_LOCKED and ends the session, as the standard says.

Before CONNECT every command but CONNECT is ignored (no answer). Unknown
commands answer ERR_CMD_UNKNOWN, packets too short for their command
ERR_CMD_SYNTAX (trailing bytes are allowed: some masters pad). Every packet
not answered positively is counted by reason (``counters()``; a master
block's packets are answered together, by the answer to its last).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

__all__ = [
    "Slave", "Memory", "Daq", "Dto", "DaqEntry", "DaqListConfig", "Event", "Limits",
    "OK", "MAX_CTO", "DTO_HEADER_BYTES", "EPK_ADDRESS", "TIMESTAMP_BYTES", "TIMESTAMP_UNIT_NS",
    "DEFAULT_EVENTS", "CHECKSUM_TYPE", "MAX_CHECKSUM_BLOCK", "MAX_BS", "MIN_ST", "checksum",
    "default_clock_uuid", "KEY_BYTES", "SEED_BYTES", "compute_key", "seed_n_key_function",
    "read_secret", "error_name", "merge_ranges",
]

# ---- packet identifiers -----------------------------------------------------
PID_RES = 0xFF
PID_ERR = 0xFE
PID_EV = 0xFD
PID_SERV = 0xFC

EV_DAQ_OVERLOAD = 0x06
EV_SESSION_TERMINATED = 0x07

# ---- commands ---------------------------------------------------------------
CONNECT = 0xFF
DISCONNECT = 0xFE
GET_STATUS = 0xFD
SYNCH = 0xFC
GET_COMM_MODE_INFO = 0xFB
GET_ID = 0xFA
GET_SEED = 0xF8
UNLOCK = 0xF7
SET_MTA = 0xF6
UPLOAD = 0xF5
SHORT_UPLOAD = 0xF4
BUILD_CHECKSUM = 0xF3
DOWNLOAD = 0xF0
DOWNLOAD_NEXT = 0xEF
SHORT_DOWNLOAD = 0xED
MODIFY_BITS = 0xEC
SET_CAL_PAGE = 0xEB
GET_CAL_PAGE = 0xEA
GET_PAG_PROCESSOR_INFO = 0xE9
GET_SEGMENT_INFO = 0xE8
GET_PAGE_INFO = 0xE7
COPY_CAL_PAGE = 0xE4
CLEAR_DAQ_LIST = 0xE3
SET_DAQ_PTR = 0xE2
WRITE_DAQ = 0xE1
SET_DAQ_LIST_MODE = 0xE0
GET_DAQ_LIST_MODE = 0xDF
START_STOP_DAQ_LIST = 0xDE
START_STOP_SYNCH = 0xDD
GET_DAQ_CLOCK = 0xDC
READ_DAQ = 0xDB
GET_DAQ_PROCESSOR_INFO = 0xDA
GET_DAQ_RESOLUTION_INFO = 0xD9
GET_DAQ_LIST_INFO = 0xD8
GET_DAQ_EVENT_INFO = 0xD7
FREE_DAQ = 0xD6
ALLOC_DAQ = 0xD5
ALLOC_ODT = 0xD4
ALLOC_ODT_ENTRY = 0xD3
WRITE_DAQ_MULTIPLE = 0xC7
TIME_CORRELATION_PROPERTIES = 0xC6
LEVEL_1 = 0xC0                       # two-byte commands: 0xC0 then the sub-command
#: packets from the master below this are STIM DTOs (their first byte the ODT number)
FIRST_CMD_PID = 0xC0
GET_VERSION_SUB = 0x00

# ---- errors -----------------------------------------------------------------
ERR_CMD_SYNCH = 0x00
ERR_CMD_BUSY = 0x10
ERR_DAQ_ACTIVE = 0x11
ERR_PGM_ACTIVE = 0x12
ERR_CMD_UNKNOWN = 0x20
ERR_CMD_SYNTAX = 0x21
ERR_OUT_OF_RANGE = 0x22
ERR_WRITE_PROTECTED = 0x23
ERR_ACCESS_DENIED = 0x24
ERR_ACCESS_LOCKED = 0x25
ERR_PAGE_NOT_VALID = 0x26
ERR_MODE_NOT_VALID = 0x27
ERR_SEGMENT_NOT_VALID = 0x28
ERR_SEQUENCE = 0x29
ERR_DAQ_CONFIG = 0x2A
ERR_MEMORY_OVERFLOW = 0x30
ERR_GENERIC = 0x31
ERR_VERIFY = 0x32
ERR_RESOURCE_TEMPORARY_NOT_ACCESSIBLE = 0x33

_ERROR_NAMES = {v: k for k, v in globals().items() if k.startswith("ERR_") and isinstance(v, int)}


def error_name(code: int) -> str:
    return _ERROR_NAMES.get(code, f"ERR_0x{code:02X}")


OK = None                            # Memory.write and Daq.apply: done

# ---- resources --------------------------------------------------------------
RES_CALPAG = 0x01
RES_DAQ = 0x04
RES_STIM = 0x08
RES_PGM = 0x10
RES_DBG = 0x20
_RESOURCES = (RES_CALPAG, RES_DAQ, RES_STIM, RES_PGM, RES_DBG)

# ---- what the slave declares ------------------------------------------------
MAX_CTO = 252
DTO_HEADER_BYTES = 4                 # relative ODT, fill, absolute DAQ list (word, aligned)
TIMESTAMP_BYTES = 4
TIMESTAMP_UNIT_NS = 1000             # 1 us
#: where the slave answers the EPK as memory (the A2L's MOD_PAR ADDR_EPK; address
#: extension 0): far beyond the rt_loop struct, read only, the EPK's ASCII bytes
EPK_ADDRESS = 0x80000000
_TS_UNIT_CODE = 3                    # DAQ_TIMESTAMP_UNIT_1US
_TS_SIZE_CODE = 4                    # 4 bytes
_IDF_REL_ODT_ABS_DAQ_WORD_ALIGNED = 0b11
_AE_SAME_FOR_ALL_DAQ = 0b11
_PROTOCOL_LAYER_VERSION = 1
_TRANSPORT_LAYER_VERSION = 1
_DRIVER_VERSION = 0x14               # 1.4
SEED_BYTES = 16
KEY_BYTES = 16
_MAX_ODTS_PER_LIST = 0xFC            # relative ODT numbers 0..0xFB (0xFC.. are the CTO PIDs)
_MAX_STIM_ODTS = FIRST_CMD_PID       # a STIM DTO's ODT number is below the commands' codes
#: BUILD_CHECKSUM: XCP_CRC_32 (the standard's code 0x09: CRC-32 as zlib.crc32)
CHECKSUM_TYPE = 0x09
MAX_CHECKSUM_BLOCK = 0x100000        # bytes of one BUILD_CHECKSUM at most
#: master block mode: the most packets of one block (a block holds at most 255
#: bytes, MAX_CTO - 2 in each packet) and the least time between them (100 us units)
MAX_BS = -(-255 // (MAX_CTO - 2))
MIN_ST = 0
_MASTER_BLOCK_MODE = 0x01            # COMM_MODE_OPTIONAL
_MODE_STIM = 0x02                    # SET_DAQ_LIST_MODE: DIRECTION
_MODE_TIMESTAMP = 0x10
# TIME_CORRELATION_PROPERTIES and GET_DAQ_CLOCK (XCP 1.3)
_TRIGGER_INFO = 0x00                 # sampled during the command's processing
_PAYLOAD_SLAVE_DWORD = 0x01          # PAYLOAD_FMT: the slave clock's timestamp, 4 bytes
_PAYLOAD_SLAVE_DLONG = 0x02          # ... 8 bytes
_SYNC_STATE = 0x07                   # SLV_CLK_SYNC_STATE: synchronisation not supported
_OBSERVABLE_CLOCKS = 0x00            # slave clock free running and readable; no GM, no ECU
_CLOCK_INFO_SLAVE = 0x01             # the slave clock's information can be uploaded
_STRATUM_UNKNOWN = 255


@dataclass(frozen=True)
class Limits:
    """The DAQ producer's limits (the loop's: rt_loop.h)."""

    max_lists: int = 32              # RT_DAQ_MAX_LISTS
    max_odts: int = 512              # RT_DAQ_MAX_ODTS (all lists)
    max_entries: int = 4096          # RT_DAQ_MAX_ENTRIES (all ODTs)
    odt_bytes: int = 248             # RT_DAQ_ODT_BYTES (data of one DTO)


@dataclass(frozen=True)
class Event:
    """A DAQ event channel: its name and its cycle in seconds (0: not cyclic)."""

    name: str
    cycle_s: float


DEFAULT_EVENTS = (Event("tick", 0.0005), Event("10ms", 0.01), Event("100ms", 0.1))


class DaqEntry(NamedTuple):
    address: int
    size: int


@dataclass(frozen=True)
class DaqListConfig:
    """One DAQ list as the producer gets it: its ODTs (each a tuple of
    entries), event channel, prescaler (1: every time) and whether it runs."""

    odts: tuple[tuple[DaqEntry, ...], ...]
    event: int
    prescaler: int
    running: bool


class Dto(NamedTuple):
    """One ODT's data measured at one event: list, ODT (relative to the
    list), the time (CLOCK_MONOTONIC, ns) and the bytes of its entries."""

    list: int
    odt: int
    time_ns: int
    data: bytes


class Memory:
    """The slave's memory (address extension 0). Subclasses override."""

    def read(self, address: int, n: int) -> bytes | int:
        """``n`` bytes at ``address``, or an XCP error code (ERR_ACCESS_DENIED)."""
        return ERR_ACCESS_DENIED

    def write(self, address: int, data: bytes) -> int | None:
        """``OK`` (None) once written, else an XCP error code."""
        return ERR_WRITE_PROTECTED

    def write_queued(self, address: int, data: bytes) -> int | None:
        """A write no answer waits for (STIM): ``OK`` once accepted, else an XCP
        error code; a backend that queues writes returns before they are
        applied. By default ``write``."""
        return self.write(address, data)

    def cal_regions(self) -> list[tuple[int, int]]:
        """The calibration regions (address, size): the pages' contents."""
        return []


class Daq:
    """The DAQ producer. Subclasses override."""

    def apply(self, lists: Sequence[DaqListConfig]) -> int | None:
        """Use this configuration from now on; ``OK`` or an XCP error code
        (the producer busy, the configuration refused)."""
        return OK

    def pop(self, n: int) -> list[Dto]:
        """Up to ``n`` measured ODTs, oldest first (one consumer only)."""
        return []

    def dropped(self) -> int:
        """ODTs the producer lost so far (its queue was full)."""
        return 0


# ---- seed & key -------------------------------------------------------------

def compute_key(secret: bytes, seed: bytes) -> bytes:
    """The key for a seed: the first KEY_BYTES of HMAC-SHA256(secret, seed)."""
    return hmac.new(secret, seed, hashlib.sha256).digest()[:KEY_BYTES]


def seed_n_key_function(secret: bytes) -> Callable[[int, bytes], bytes]:
    """The master's side, as pyxcp's ``General.seed_n_key_function`` takes it."""

    def key_for(resource: int, seed: bytes) -> bytes:  # same key for every resource
        return compute_key(secret, bytes(seed))

    return key_for


def read_secret(path: str | os.PathLike) -> bytes:
    """The shared secret of a key file: its bytes, surrounding whitespace
    removed; at least 16 bytes."""
    with open(path, "rb") as f:
        secret = f.read().strip()
    if len(secret) < 16:
        raise ValueError(f"{os.fspath(path)}: the XCP key needs at least 16 bytes, "
                         f"it has {len(secret)}")
    return secret


# ---- BUILD_CHECKSUM and the clock ---------------------------------------------

def checksum(data: bytes) -> int:
    """BUILD_CHECKSUM's value over ``data`` (CHECKSUM_TYPE: XCP_CRC_32)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def default_clock_uuid() -> bytes:
    """An EUI-64 naming CLOCK_MONOTONIC of this boot of this host (the kernel's
    boot id hashed; locally administered, unicast): slaves on the same host
    share it, as they share the clock. Without a boot id, a random one."""
    try:
        with open("/proc/sys/kernel/random/boot_id", "rb") as f:
            boot = f.read().strip()
    except OSError:
        boot = b""
    digest = hashlib.sha256(b"CLOCK_MONOTONIC " + (boot or os.urandom(16))).digest()
    return bytes([(digest[0] | 0x02) & 0xFE]) + digest[1:8]


# ---- the slave --------------------------------------------------------------

class _Refused(Exception):
    """A negative response: the error code and what follows it (some errors
    carry a value: ERR_SEQUENCE the count expected, ERR_OUT_OF_RANGE of
    BUILD_CHECKSUM the largest block)."""

    def __init__(self, code: int, extra: bytes = b"") -> None:
        super().__init__(code)
        self.code = code
        self.extra = extra


def _check(code: int | None) -> None:
    if code is not None:
        raise _Refused(code)


_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


def _u16(p: bytes, at: int) -> int:
    return _U16.unpack_from(p, at)[0]


def _u32(p: bytes, at: int) -> int:
    return _U32.unpack_from(p, at)[0]


def event_cycle(cycle_s: float) -> tuple[int, int]:
    """An event cycle as XCP's (cycle 1..255, unit 0 = 1 ns .. 9 = 1 s): the
    coarsest unit that gives it exactly, else the finest that holds it."""
    if cycle_s <= 0:
        return 0, 0                        # not cyclic
    ns = round(cycle_s * 1e9)
    for unit in range(9, -1, -1):
        step = 10 ** unit
        if ns % step == 0 and 1 <= ns // step <= 255:
            return ns // step, unit
    for unit in range(10):
        if round(ns / 10 ** unit) <= 255:
            return max(1, round(ns / 10 ** unit)), unit
    return 255, 9


def merge_ranges(ranges: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[list[int]] = []
    for start, size in sorted((int(a), int(n)) for a, n in ranges if n > 0):
        if out and start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], start + size)
        else:
            out.append([start, start + size])
    return [(a, b - a) for a, b in out]


@dataclass
class _List:
    odts: list[list[DaqEntry | None]] = field(default_factory=list)
    event: int = 0
    prescaler: int = 1
    priority: int = 0
    timestamp: bool = False
    stim: bool = False               # DIRECTION: the master writes (STIM), else DAQ
    running: bool = False
    selected: bool = False


@dataclass
class _Block:
    """A master block (DOWNLOAD + DOWNLOAD_NEXT) being received."""

    address: int
    total: int
    data: bytearray


class _DtoView(NamedTuple):
    running: bool
    timestamp: bool
    sizes: tuple[int, ...]
    headers: tuple[bytes, ...]


class Slave:
    """The XCP slave's protocol state for one master at a time.

    ``handle`` is called by one thread (the transport's receiver: commands
    and STIM DTOs); ``dto_packet`` and ``overload_events`` by the sender;
    ``reset`` by either. Thread-safe.

    ``stim_events``: the event channels STIM lists may use (none: the slave
    declares no STIM); ``clock_uuid``: the DAQ clock's EUI-64 (8 bytes; default
    ``default_clock_uuid()``)."""

    def __init__(
        self,
        memory: Memory,
        daq: Daq,
        *,
        name: str = "dct-hil",
        a2l_name: str | None = None,
        a2l_text: Callable[[], str | bytes] | None = None,
        epk: str | None = None,
        events: Sequence[Event] = DEFAULT_EVENTS,
        secret: bytes | None = None,
        limits: Limits = Limits(),
        clock_ns: Callable[[], int] = time.monotonic_ns,
        stim_events: Sequence[int] = (),
        clock_uuid: bytes | None = None,
    ) -> None:
        self.memory = memory
        self.daq = daq
        self.name = name
        self.a2l_name = a2l_name if a2l_name is not None else name
        self.a2l_text = a2l_text
        self.epk = epk
        self.events = tuple(events)
        if not self.events:
            raise ValueError("an XCP slave needs at least one event channel")
        self.secret = secret
        self.limits = limits
        self.clock_ns = clock_ns
        self.stim_events = frozenset(stim_events)
        if any(not 0 <= n < len(self.events) for n in self.stim_events):
            raise ValueError(f"STIM event channels {sorted(self.stim_events)}: the slave has "
                             f"{len(self.events)} event channels")
        uuid = default_clock_uuid() if clock_uuid is None else bytes(clock_uuid)
        if len(uuid) != 8:
            raise ValueError(f"the clock's UUID is an EUI-64 (8 bytes), got {len(uuid)}")
        # the slave clock's information (TIME_CORRELATION_PROPERTIES GET_CLK_INFO)
        self._clock_info = uuid + _U16.pack(1) + bytes([_TS_UNIT_CODE, _STRATUM_UNKNOWN, 8]) + \
            bytes(3) + _U64.pack(0xFFFF_FFFF_FFFF_FFFF)
        self.max_cto = MAX_CTO
        self.max_dto = DTO_HEADER_BYTES + limits.odt_bytes
        self._lock = threading.RLock()
        self._counts: dict[str, int] = {"commands": 0, "positive": 0, "sessions": 0,
                                        "unlocked": 0, "dtos": 0, "daq_stop_failed": 0}
        self._errors: dict[str, int] = {}
        self._ignored: dict[str, int] = {}
        self._session_ends: dict[str, int] = {}
        self._dto_dropped = {"not_running": 0, "stale": 0}
        self._stim: dict[str, int] = {"dtos": 0, "written": 0}   # dropped: in _ignored, stim_*
        self._overloads_seen = 0
        self._overload_events = 0
        # calibration pages: the reference page is the regions' values now
        self._regions = merge_ranges(memory.cal_regions())
        self._reference = self._snapshot()
        self._saved_working: dict[int, bytearray] | None = None   # while the ECU uses page 1
        self._ecu_page = 0
        self._xcp_page = 0
        self._dispatch = self._commands()
        self._dto_views: tuple[_DtoView, ...] = ()
        self._new_session()

    # ---- session --------------------------------------------------------
    def _new_session(self) -> None:
        self.connected = False
        self._resources = RES_CALPAG | RES_DAQ | (RES_STIM if self.stim_events else 0)
        # STIM is not locked apart: a STIM list needs DAQ and CAL/PAG unlocked
        self._protection = (RES_CALPAG | RES_DAQ) if self.secret else 0
        self._block: _Block | None = None
        self._clock_format = 0        # TIME_CORRELATION_PROPERTIES' RESPONSE_FMT: 0 legacy
        self._cluster_id = 0
        self._seed: tuple[int, bytes] | None = None
        self._key_total = 0
        self._key = bytearray()
        self._mta: tuple[bytes | None, int] = (None, 0)
        self._lists: list[_List] = []
        self._alloc = "free"          # free -> daq -> odt -> entry
        self._n_odts = 0
        self._n_entries = 0
        self._ptr: list[int] | None = None

    def reset(self, reason: str = "master gone") -> None:
        """Ends the session (the master disconnected, vanished or was
        replaced): its DAQ lists stop, its configuration is freed, the
        resources are locked again. The calibration pages stay as they are."""
        with self._lock:
            was_running = any(d.running for d in self._lists)
            if self.connected:
                self._bump(self._session_ends, reason.replace(" ", "_"))
            self._new_session()
            self._dto_views = ()
            if was_running:                    # the producer stops copying (it may be busy)
                if all(self.daq.apply(()) is not OK for _ in range(5)):
                    self._counts["daq_stop_failed"] += 1

    @property
    def daq_running(self) -> bool:
        return any(v.running for v in self._dto_views)

    @property
    def dto_layout(self) -> tuple:
        """The DTO layout of the session (one view per DAQ list: running, timestamp,
        its packets' headers, each ODT's size): a new tuple whenever it changes, for a
        sender that packs the DTOs elsewhere (the transport's C sender)."""
        return self._dto_views

    def count_dtos_sent_elsewhere(self, packed: int, not_running: int, stale: int,
                                  overload_events: int) -> None:
        """The counts of a sender that packs the DTOs itself (totals since the
        slave was made): they stand in ``counters()`` where ``dto_packet`` and
        ``overload_events`` would have counted."""
        self._counts["dtos"] = int(packed)
        self._dto_dropped = {"not_running": int(not_running), "stale": int(stale)}
        self._overload_events = int(overload_events)

    # ---- counting -------------------------------------------------------
    @staticmethod
    def _bump(d: dict[str, int], key: str, by: int = 1) -> None:
        d[key] = d.get(key, 0) + by

    def counters(self) -> dict:
        """Commands, positive responses, errors by name, packets ignored by
        reason, sessions ended by reason, DTOs sent and dropped by reason,
        STIM DTOs received, written and dropped by reason, overloads. Never
        waits (the copies are taken under the GIL)."""
        return {
            **self._counts,
            "errors": dict(self._errors),
            "ignored": dict(self._ignored),
            "session_ends": dict(self._session_ends),
            "dto_dropped": dict(self._dto_dropped),
            "stim": {**self._stim, "dropped": {k[5:]: v for k, v in list(self._ignored.items())
                                               if k.startswith("stim_")}},
            "overload_events": self._overload_events,
            "connected": self.connected,
            "daq_running": self.daq_running,
        }

    # ---- the command processor -------------------------------------------
    def handle(self, cto: bytes) -> list[bytes]:
        """The packets answering one packet from the master: a command (CTO),
        or a STIM DTO (no answer). None when ignored."""
        cto = bytes(cto)
        with self._lock:
            if not cto:
                self._bump(self._ignored, "empty")
                return []
            cmd = cto[0]
            if cmd < FIRST_CMD_PID:
                self._stim_dto(cto)
                return []
            self._counts["commands"] += 1
            if not self.connected and cmd != CONNECT:
                self._bump(self._ignored, "not_connected")
                return []
            if cmd == LEVEL_1:
                if len(cto) < 2:
                    return [self._error(ERR_CMD_SYNTAX)]
                key: int = (LEVEL_1 << 8) | cto[1]
            else:
                key = cmd
            if self._block is not None and key != DOWNLOAD_NEXT:
                remaining = self._block.total - len(self._block.data)
                if key == DOWNLOAD and len(cto) >= 2 and cto[1] == remaining:
                    key = DOWNLOAD_NEXT        # the block's last packet sent as DOWNLOAD
                else:
                    self._block = None         # a block interrupted: never written
                    self._bump(self._ignored, "download_block_dropped")
                    if key == DOWNLOAD:
                        return [self._error(ERR_SEQUENCE)]
            entry = self._dispatch.get(key)
            if entry is None:
                return [self._error(ERR_CMD_UNKNOWN)]
            method, min_len, resource = entry
            if len(cto) < min_len:
                return [self._error(ERR_CMD_SYNTAX)]
            if resource & self._protection:
                return [self._error(ERR_ACCESS_LOCKED)]
            try:
                payload = method(cto)
            except _Refused as e:
                return [self._error(e.code, e.extra)]
            except Exception:  # a backend's bug must not stop the slave
                self._block = None
                self._bump(self._ignored, "internal_error")
                return [self._error(ERR_GENERIC)]
            if payload is None:
                return []                      # inside a master block: no answer yet
            self._counts["positive"] += 1
            return [bytes([PID_RES]) + payload]

    def _error(self, code: int, extra: bytes = b"") -> bytes:
        self._bump(self._errors, error_name(code))
        return bytes([PID_ERR, code]) + extra

    def _commands(self) -> dict[int, tuple[Callable[[bytes], bytes | None], int, int]]:
        c, d = RES_CALPAG, RES_DAQ
        return {
            CONNECT: (self._connect, 2, 0),
            DISCONNECT: (self._disconnect, 1, 0),
            GET_STATUS: (self._get_status, 1, 0),
            SYNCH: (self._synch, 1, 0),
            GET_COMM_MODE_INFO: (self._get_comm_mode_info, 1, 0),
            GET_ID: (self._get_id, 2, 0),
            GET_SEED: (self._get_seed, 3, 0),
            UNLOCK: (self._unlock, 2, 0),
            SET_MTA: (self._set_mta, 8, 0),
            UPLOAD: (self._upload, 2, 0),
            SHORT_UPLOAD: (self._short_upload, 8, 0),
            BUILD_CHECKSUM: (self._build_checksum, 8, 0),
            DOWNLOAD: (self._download, 2, c),
            DOWNLOAD_NEXT: (self._download_next, 2, c),
            SHORT_DOWNLOAD: (self._short_download, 8, c),
            MODIFY_BITS: (self._modify_bits, 6, c),
            SET_CAL_PAGE: (self._set_cal_page, 4, c),
            GET_CAL_PAGE: (self._get_cal_page, 3, 0),
            GET_PAG_PROCESSOR_INFO: (self._get_pag_processor_info, 1, 0),
            GET_SEGMENT_INFO: (self._get_segment_info, 5, 0),
            GET_PAGE_INFO: (self._get_page_info, 4, 0),
            COPY_CAL_PAGE: (self._copy_cal_page, 5, c),
            CLEAR_DAQ_LIST: (self._clear_daq_list, 4, d),
            SET_DAQ_PTR: (self._set_daq_ptr, 6, d),
            WRITE_DAQ: (self._write_daq, 8, d),
            WRITE_DAQ_MULTIPLE: (self._write_daq_multiple, 2, d),
            SET_DAQ_LIST_MODE: (self._set_daq_list_mode, 8, d),
            GET_DAQ_LIST_MODE: (self._get_daq_list_mode, 4, 0),
            START_STOP_DAQ_LIST: (self._start_stop_daq_list, 4, d),
            START_STOP_SYNCH: (self._start_stop_synch, 2, d),
            GET_DAQ_CLOCK: (self._get_daq_clock, 1, 0),
            TIME_CORRELATION_PROPERTIES: (self._time_correlation_properties, 6, 0),
            READ_DAQ: (self._read_daq, 1, d),
            GET_DAQ_PROCESSOR_INFO: (self._get_daq_processor_info, 1, 0),
            GET_DAQ_RESOLUTION_INFO: (self._get_daq_resolution_info, 1, 0),
            GET_DAQ_LIST_INFO: (self._get_daq_list_info, 4, 0),
            GET_DAQ_EVENT_INFO: (self._get_daq_event_info, 4, 0),
            FREE_DAQ: (self._free_daq, 1, d),
            ALLOC_DAQ: (self._alloc_daq, 4, d),
            ALLOC_ODT: (self._alloc_odt, 5, d),
            ALLOC_ODT_ENTRY: (self._alloc_odt_entry, 6, d),
            (LEVEL_1 << 8) | GET_VERSION_SUB: (self._get_version, 2, 0),
        }

    # ---- standard commands ------------------------------------------------
    def _connect(self, p: bytes) -> bytes:
        if p[1] not in (0, 1):               # 0 normal, 1 user defined (taken as normal)
            raise _Refused(ERR_OUT_OF_RANGE)
        if not self.connected:
            self._new_session()
            self.connected = True
            self._counts["sessions"] += 1
        comm_mode_basic = 0x80                 # OPTIONAL (GET_COMM_MODE_INFO); Intel, BYTE
        return bytes([self._resources, comm_mode_basic, self.max_cto]) + \
            _U16.pack(self.max_dto) + \
            bytes([_PROTOCOL_LAYER_VERSION, _TRANSPORT_LAYER_VERSION])

    def _disconnect(self, p: bytes) -> bytes:
        self.reset("disconnect")
        return b""

    def _get_status(self, p: bytes) -> bytes:
        session = 0x40 if any(d.running for d in self._lists) else 0
        return bytes([session, self._protection, 0]) + _U16.pack(0)

    def _synch(self, p: bytes) -> bytes:
        raise _Refused(ERR_CMD_SYNCH)

    def _get_comm_mode_info(self, p: bytes) -> bytes:
        # COMM_MODE_OPTIONAL: master block mode; MAX_BS, MIN_ST; no interleaved mode (queue 0)
        return bytes([0, _MASTER_BLOCK_MODE, 0, MAX_BS, MIN_ST, 0, _DRIVER_VERSION])

    def _get_version(self, p: bytes) -> bytes:
        return bytes([0, 1, 4, 1, 0])

    def _get_id(self, p: bytes) -> bytes:
        kind = p[1]
        if kind == 0:
            text = self.name.encode("ascii", "replace")
        elif kind == 1:
            text = self.a2l_name.encode("ascii", "replace")
        elif kind == 5 and self.epk is not None:
            text = self.epk.encode("ascii", "replace")
        elif kind == 4 and self.a2l_text is not None:
            a2l = self.a2l_text()
            text = a2l.encode("utf-8") if isinstance(a2l, str) else bytes(a2l)
            self._mta = (text, 0)
            return bytes([0, 0, 0]) + _U32.pack(len(text))
        else:
            return bytes([0, 0, 0]) + _U32.pack(0)   # not available
        if len(text) <= self.max_cto - 8:
            return bytes([1, 0, 0]) + _U32.pack(len(text)) + text
        self._mta = (text, 0)
        return bytes([0, 0, 0]) + _U32.pack(len(text))

    # ---- seed & key ---------------------------------------------------------
    def _get_seed(self, p: bytes) -> bytes:
        mode, resource = p[1], p[2]
        if mode == 1:
            if self._seed is None:
                raise _Refused(ERR_SEQUENCE)
            return bytes([0])                  # the whole seed went with the first part
        if mode != 0 or resource not in _RESOURCES:
            raise _Refused(ERR_OUT_OF_RANGE)
        if not resource & self._protection:
            self._seed = None
            return bytes([0])                  # not protected: nothing to unlock
        seed = os.urandom(SEED_BYTES)
        self._seed = (resource, seed)
        self._key_total = 0
        self._key = bytearray()
        return bytes([len(seed)]) + seed

    def _unlock(self, p: bytes) -> bytes:
        if self._seed is None:
            raise _Refused(ERR_SEQUENCE)
        remaining = p[1]
        if not self._key:
            self._key_total = remaining
        elif remaining != self._key_total - len(self._key):
            self._seed = None
            raise _Refused(ERR_SEQUENCE)
        chunk = min(remaining, len(p) - 2)      # a master may send less than MAX_CTO - 2
        if chunk < 1:
            raise _Refused(ERR_CMD_SYNTAX)
        self._key += p[2:2 + chunk]
        if len(self._key) < self._key_total:
            return bytes([self._protection])
        resource, seed = self._seed
        self._seed = None
        key, self._key = bytes(self._key), bytearray()
        assert self.secret is not None
        if not hmac.compare_digest(key, compute_key(self.secret, seed)):
            self._bump(self._ignored, "unlock_wrong_key")
            self.reset("wrong key")            # the standard: the slave disconnects
            raise _Refused(ERR_ACCESS_LOCKED)
        self._protection &= ~resource
        self._counts["unlocked"] += 1
        return bytes([self._protection])

    # ---- memory -------------------------------------------------------------
    def _set_mta(self, p: bytes) -> bytes:
        if p[3] != 0:
            raise _Refused(ERR_OUT_OF_RANGE)
        self._mta = (None, _u32(p, 4))
        return b""

    def _upload_from(self, space: bytes | None, address: int, n: int) -> bytes:
        if not 1 <= n <= self.max_cto - 1:
            raise _Refused(ERR_OUT_OF_RANGE)
        if space is not None:
            if address + n > len(space):
                raise _Refused(ERR_OUT_OF_RANGE)
            data = space[address:address + n]
        else:
            data = self._read(address, n)
        self._mta = (space, address + n)
        return data

    def _upload(self, p: bytes) -> bytes:
        space, address = self._mta
        return self._upload_from(space, address, p[1])

    def _short_upload(self, p: bytes) -> bytes:
        if p[3] != 0:
            raise _Refused(ERR_OUT_OF_RANGE)
        return self._upload_from(None, _u32(p, 4), p[1])

    def _download(self, p: bytes) -> bytes | None:
        n = p[1]                               # the block's bytes (master block mode: all)
        if n < 1:
            raise _Refused(ERR_OUT_OF_RANGE)
        first = min(n, self.max_cto - 2)
        if len(p) < 2 + first:
            raise _Refused(ERR_CMD_SYNTAX)
        space, address = self._mta
        if space is not None:
            raise _Refused(ERR_WRITE_PROTECTED)
        if n > first:                          # a master block: the rest in DOWNLOAD_NEXT
            self._block = _Block(address, n, bytearray(p[2:2 + first]))
            return None
        self._write(address, p[2:2 + n])
        self._mta = (None, address + n)
        return b""

    def _download_next(self, p: bytes) -> bytes | None:
        n, block = p[1], self._block
        expected = block.total - len(block.data) if block is not None else 0
        if block is None or n != expected:
            self._block = None
            raise _Refused(ERR_SEQUENCE, bytes([expected]))
        chunk = min(n, self.max_cto - 2)
        if len(p) < 2 + chunk:
            self._block = None
            raise _Refused(ERR_CMD_SYNTAX)
        block.data += p[2:2 + chunk]
        if len(block.data) < block.total:
            return None
        self._block = None
        self._write(block.address, bytes(block.data))       # the whole block: one write
        self._mta = (None, block.address + block.total)
        return b""

    def _modify_bits(self, p: bytes) -> bytes:
        shift, and_mask, xor_mask = p[1], _u16(p, 2), _u16(p, 4)
        if shift > 31:
            raise _Refused(ERR_OUT_OF_RANGE)
        space, address = self._mta
        if space is not None:
            raise _Refused(ERR_WRITE_PROTECTED)
        clear = ((~and_mask & 0xFFFF) << shift) & 0xFFFFFFFF
        flip = (xor_mask << shift) & 0xFFFFFFFF
        touched = clear | flip
        if not touched:
            return b""                         # the value stays as it is
        lo = ((touched & -touched).bit_length() - 1) // 8      # the bytes the masks touch
        hi = (touched.bit_length() - 1) // 8
        old = self._read(address + lo, hi - lo + 1)
        value = int.from_bytes(bytes(lo) + old + bytes(3 - hi), "little")
        new = ((value & ~clear) ^ flip) & 0xFFFFFFFF
        self._write(address + lo, new.to_bytes(4, "little")[lo:hi + 1])
        return b""

    def _build_checksum(self, p: bytes) -> bytes:
        size = _u32(p, 4)
        if not 1 <= size <= MAX_CHECKSUM_BLOCK:
            raise _Refused(ERR_OUT_OF_RANGE, bytes(2) + _U32.pack(MAX_CHECKSUM_BLOCK))
        space, address = self._mta
        if space is not None:
            if address + size > len(space):
                raise _Refused(ERR_OUT_OF_RANGE)
            data = space[address:address + size]
        else:
            data = self._read(address, size)
        self._mta = (space, address + size)
        return bytes([CHECKSUM_TYPE, 0, 0]) + _U32.pack(checksum(data))

    def _short_download(self, p: bytes) -> bytes:
        n = p[1]
        if not 1 <= n <= self.max_cto - 8:
            raise _Refused(ERR_OUT_OF_RANGE)
        if len(p) < 8 + n:
            raise _Refused(ERR_CMD_SYNTAX)
        if p[3] != 0:
            raise _Refused(ERR_OUT_OF_RANGE)
        address = _u32(p, 4)
        self._write(address, p[8:8 + n])
        self._mta = (None, address + n)
        return b""

    # the pages: reads and writes of the XCP page --------------------------------
    def _snapshot(self) -> dict[int, bytes]:
        out = {}
        for start, size in self._regions:
            data = self.memory.read(start, size)
            if isinstance(data, int):
                raise ValueError(f"the calibration region at {start:#x} ({size} bytes) "
                                 f"cannot be read: {error_name(data)}")
            out[start] = bytes(data)
        return out

    def _overlay(self) -> dict[int, bytes] | dict[int, bytearray] | None:
        if self._xcp_page == 1:
            return self._reference
        if self._ecu_page == 1:
            return self._saved_working
        return None

    def _epk_span(self, address: int, n: int) -> bytes | None:
        """The EPK's bytes at ``address``..+n, None outside the EPK's address range
        (ERR_OUT_OF_RANGE for a read that begins in it and runs past its end)."""
        if self.epk is None or not EPK_ADDRESS <= address < EPK_ADDRESS + 0x10000:
            return None
        text = self.epk.encode("ascii", "replace")
        at = address - EPK_ADDRESS
        if at + n > len(text):
            raise _Refused(ERR_OUT_OF_RANGE)
        return text[at:at + n]

    def _read(self, address: int, n: int) -> bytes:
        epk = self._epk_span(address, n)
        if epk is not None:
            return epk
        data = self.memory.read(address, n)
        if isinstance(data, int):
            raise _Refused(data)
        if len(data) != n:
            raise _Refused(ERR_ACCESS_DENIED)
        overlay = self._overlay()
        if not overlay:
            return bytes(data)
        out = bytearray(data)
        for start, blob in overlay.items():
            lo, hi = max(address, start), min(address + n, start + len(blob))
            if lo < hi:
                out[lo - address:hi - address] = blob[lo - start:hi - start]
        return bytes(out)

    def _write(self, address: int, data: bytes, queued: bool = False) -> None:
        if self.epk is not None and EPK_ADDRESS <= address < EPK_ADDRESS + 0x10000:
            raise _Refused(ERR_WRITE_PROTECTED)      # the EPK is read only
        if self._xcp_page == 1:
            raise _Refused(ERR_WRITE_PROTECTED)      # the reference page is read only
        if self._ecu_page == 1 and self._saved_working is not None:
            for start, blob in self._saved_working.items():
                if start <= address and address + len(data) <= start + len(blob):
                    blob[address - start:address - start + len(data)] = data
                    return
                if address < start + len(blob) and start < address + len(data):
                    raise _Refused(ERR_WRITE_PROTECTED)  # across a region's border
        write = self.memory.write_queued if queued else self.memory.write
        _check(write(address, bytes(data)))

    def _write_regions(self, values: dict[int, bytes] | dict[int, bytearray]) -> None:
        for start, blob in values.items():
            _check(self.memory.write(start, bytes(blob)))

    # ---- calibration pages ----------------------------------------------------------
    def _segment(self, segment: int) -> None:
        if segment != 0:
            raise _Refused(ERR_SEGMENT_NOT_VALID)

    def _set_cal_page(self, p: bytes) -> bytes:
        mode, segment, page = p[1], p[2], p[3]
        if not mode & 0x80:
            self._segment(segment)
        if not mode & 0x03:
            raise _Refused(ERR_MODE_NOT_VALID)
        if page > 1:
            raise _Refused(ERR_PAGE_NOT_VALID)
        if mode & 0x01 and page != self._ecu_page:
            if page == 1:
                saved = {a: bytearray(b) for a, b in self._snapshot().items()}
                self._write_regions(self._reference)
                self._saved_working = saved
            else:
                assert self._saved_working is not None
                self._write_regions(self._saved_working)
                self._saved_working = None
            self._ecu_page = page
        if mode & 0x02:
            self._xcp_page = page
        return b""

    def _get_cal_page(self, p: bytes) -> bytes:
        mode, segment = p[1], p[2]
        self._segment(segment)
        if mode == 0x01:
            page = self._ecu_page
        elif mode == 0x02:
            page = self._xcp_page
        else:
            raise _Refused(ERR_MODE_NOT_VALID)
        return bytes([0, 0, page])

    def _get_pag_processor_info(self, p: bytes) -> bytes:
        return bytes([1, 0])                   # one segment, no freeze

    def _get_segment_info(self, p: bytes) -> bytes:
        mode, segment, info, _mapping = p[1], p[2], p[3], p[4]   # p[4]: a short packet fails here
        self._segment(segment)
        if mode == 0:
            start = self._regions[0][0] if self._regions else 0
            end = self._regions[-1][0] + self._regions[-1][1] if self._regions else 0
            if info == 0:
                return bytes(3) + _U32.pack(start)
            if info == 1:
                return bytes(3) + _U32.pack(end - start)
            raise _Refused(ERR_OUT_OF_RANGE)
        if mode == 1:
            return bytes([2, 0, 0, 0, 0])     # 2 pages, extension 0, no mapping
        if mode == 2:
            raise _Refused(ERR_OUT_OF_RANGE)   # no address mapping (MAX_MAPPING 0)
        raise _Refused(ERR_MODE_NOT_VALID)

    def _get_page_info(self, p: bytes) -> bytes:
        segment, page = p[2], p[3]
        self._segment(segment)
        if page > 1:
            raise _Refused(ERR_PAGE_NOT_VALID)
        # ECU and XCP reads: don't care; XCP writes: page 0 don't care, page 1 never
        return bytes([0x3F if page == 0 else 0x0F, 0])   # init segment 0

    def _copy_cal_page(self, p: bytes) -> bytes:
        src_seg, src_page, dst_seg, dst_page = p[1], p[2], p[3], p[4]
        self._segment(src_seg)
        self._segment(dst_seg)
        if src_page > 1 or dst_page > 1:
            raise _Refused(ERR_PAGE_NOT_VALID)
        if src_page == dst_page:
            return b""
        if dst_page == 1:
            raise _Refused(ERR_WRITE_PROTECTED)   # the reference page is read only
        if self._ecu_page == 1 and self._saved_working is not None:
            self._saved_working = {a: bytearray(b) for a, b in self._reference.items()}
        else:
            self._write_regions(self._reference)
        return b""

    # ---- DAQ: allocation --------------------------------------------------------
    def _list(self, n: int) -> _List:
        if n >= len(self._lists):
            raise _Refused(ERR_OUT_OF_RANGE)
        return self._lists[n]

    def _free_daq(self, p: bytes) -> bytes:
        if any(d.running for d in self._lists):
            self._set_running({k: False for k in range(len(self._lists))})
        self._lists = []
        self._alloc = "free"
        self._n_odts = self._n_entries = 0
        self._ptr = None
        self._dto_views = ()
        return b""

    def _alloc_daq(self, p: bytes) -> bytes:
        if self._alloc != "free":
            raise _Refused(ERR_SEQUENCE)
        n = _u16(p, 2)
        if n > self.limits.max_lists:
            raise _Refused(ERR_MEMORY_OVERFLOW)
        self._lists = [_List() for _ in range(n)]
        self._alloc = "daq"
        return b""

    def _alloc_odt(self, p: bytes) -> bytes:
        if self._alloc not in ("daq", "odt"):
            raise _Refused(ERR_SEQUENCE)
        d = self._list(_u16(p, 2))
        n = p[4]
        if d.odts:
            raise _Refused(ERR_SEQUENCE)
        if n > _MAX_ODTS_PER_LIST or self._n_odts + n > self.limits.max_odts:
            raise _Refused(ERR_MEMORY_OVERFLOW)
        d.odts = [[] for _ in range(n)]
        self._n_odts += n
        self._alloc = "odt"
        return b""

    def _alloc_odt_entry(self, p: bytes) -> bytes:
        if self._alloc not in ("odt", "entry"):
            raise _Refused(ERR_SEQUENCE)
        d = self._list(_u16(p, 2))
        odt, n = p[4], p[5]
        if odt >= len(d.odts):
            raise _Refused(ERR_OUT_OF_RANGE)
        if d.odts[odt]:
            raise _Refused(ERR_SEQUENCE)
        if n > self.limits.odt_bytes or self._n_entries + n > self.limits.max_entries:
            raise _Refused(ERR_MEMORY_OVERFLOW)
        d.odts[odt] = [None] * n
        self._n_entries += n
        self._alloc = "entry"
        return b""

    # ---- DAQ: the lists' contents ---------------------------------------------------
    def _set_daq_ptr(self, p: bytes) -> bytes:
        n, odt, entry = _u16(p, 2), p[4], p[5]
        d = self._list(n)
        if odt >= len(d.odts) or entry >= len(d.odts[odt]):
            raise _Refused(ERR_OUT_OF_RANGE)
        if d.running:
            raise _Refused(ERR_DAQ_ACTIVE)
        self._ptr = [n, odt, entry]
        return b""

    def _write_entry(self, bit_offset: int, size: int, ext: int, address: int) -> None:
        if self._ptr is None:
            raise _Refused(ERR_SEQUENCE)
        n, odt, entry = self._ptr
        d = self._lists[n]
        if d.running:
            raise _Refused(ERR_DAQ_ACTIVE)
        entries = d.odts[odt]
        if entry >= len(entries):
            raise _Refused(ERR_OUT_OF_RANGE)     # past the ODT's last entry
        if bit_offset != 0xFF or ext != 0 or not 1 <= size <= self.limits.odt_bytes:
            raise _Refused(ERR_OUT_OF_RANGE)
        used = sum(e.size for k, e in enumerate(entries) if e is not None and k != entry)
        if used + size > self.limits.odt_bytes:
            raise _Refused(ERR_MEMORY_OVERFLOW)
        data = self.memory.read(address, size)
        if isinstance(data, int):
            raise _Refused(data)
        entries[entry] = DaqEntry(address, size)
        self._ptr[2] += 1

    def _write_daq(self, p: bytes) -> bytes:
        self._write_entry(p[1], p[2], p[3], _u32(p, 4))
        return b""

    def _write_daq_multiple(self, p: bytes) -> bytes:
        n = p[1]
        if len(p) < 2 + 8 * n:
            raise _Refused(ERR_CMD_SYNTAX)
        for k in range(n):
            at = 2 + 8 * k
            # bit offset, size, address (dword), extension, dummy
            self._write_entry(p[at], p[at + 1], p[at + 6], _u32(p, at + 2))
        return b""

    def _read_daq(self, p: bytes) -> bytes:
        if self._ptr is None:
            raise _Refused(ERR_SEQUENCE)
        n, odt, entry = self._ptr
        entries = self._lists[n].odts[odt]
        if entry >= len(entries):
            raise _Refused(ERR_OUT_OF_RANGE)
        e = entries[entry] or DaqEntry(0, 0)
        self._ptr[2] += 1
        return bytes([0xFF, e.size, 0]) + _U32.pack(e.address)

    def _clear_daq_list(self, p: bytes) -> bytes:
        n = _u16(p, 2)
        d = self._list(n)
        self._set_running({n: False})
        d.selected = False
        for entries in d.odts:
            entries[:] = [None] * len(entries)
        return b""

    def _set_daq_list_mode(self, p: bytes) -> bytes:
        mode = p[1]
        d = self._list(_u16(p, 2))
        event, prescaler, priority = _u16(p, 4), p[6], p[7]
        if mode & ~(_MODE_TIMESTAMP | _MODE_STIM) & 0xFF:   # no PID_OFF, no alternating
            raise _Refused(ERR_OUT_OF_RANGE)
        if event >= len(self.events) or prescaler < 1:
            raise _Refused(ERR_OUT_OF_RANGE)
        stim = bool(mode & _MODE_STIM)
        if stim:
            if RES_CALPAG & self._protection:  # its values are calibration writes
                raise _Refused(ERR_ACCESS_LOCKED)
            # STIM only on an event channel that takes it; STIM DTOs carry no timestamp
            if event not in self.stim_events or mode & _MODE_TIMESTAMP:
                raise _Refused(ERR_OUT_OF_RANGE)
        if d.running:
            raise _Refused(ERR_DAQ_ACTIVE)
        d.timestamp = bool(mode & _MODE_TIMESTAMP)
        d.stim = stim
        d.event, d.prescaler, d.priority = event, prescaler, priority
        return b""

    def _get_daq_list_mode(self, p: bytes) -> bytes:
        d = self._list(_u16(p, 2))
        mode = (0x01 if d.selected else 0) | (_MODE_STIM if d.stim else 0) | \
            (_MODE_TIMESTAMP if d.timestamp else 0) | (0x40 if d.running else 0)
        return bytes([mode, 0, 0]) + _U16.pack(d.event) + bytes([d.prescaler, d.priority])

    # ---- DAQ: start and stop -----------------------------------------------------
    def _startable(self, d: _List) -> None:
        if not d.odts or any(not entries or None in entries for entries in d.odts):
            raise _Refused(ERR_DAQ_CONFIG)    # an ODT without entries, or one not written
        if d.stim:
            if len(d.odts) > _MAX_STIM_ODTS:
                raise _Refused(ERR_DAQ_CONFIG)   # its DTOs' first byte would be a command's
            for entries in d.odts:
                for e in entries:
                    if not any(a <= e.address and e.address + e.size <= a + n
                               for a, n in self._regions):
                        raise _Refused(ERR_WRITE_PROTECTED)   # STIM writes calibration only
            return
        first = sum(e.size for e in d.odts[0] if e is not None)
        if d.timestamp and first + TIMESTAMP_BYTES > self.max_dto - DTO_HEADER_BYTES:
            raise _Refused(ERR_DAQ_CONFIG)    # the timestamp does not fit the first ODT

    def _set_running(self, wanted: dict[int, bool]) -> None:
        before = {k: d.running for k, d in enumerate(self._lists)}
        for k, run in wanted.items():
            self._lists[k].running = run
        if all(before[k] == self._lists[k].running for k in wanted):
            return
        try:
            self._apply()
        except _Refused:
            for k, run in before.items():
                self._lists[k].running = run
            raise

    def _start_stop_daq_list(self, p: bytes) -> bytes:
        mode, n = p[1], _u16(p, 2)
        d = self._list(n)
        if mode == 0:
            self._set_running({n: False})
        elif mode == 1:
            self._startable(d)
            self._set_running({n: True})
        elif mode == 2:
            self._startable(d)
            d.selected = True
        else:
            raise _Refused(ERR_MODE_NOT_VALID)
        return bytes([0])                      # FIRST_PID: ODT numbers are relative

    def _start_stop_synch(self, p: bytes) -> bytes:
        mode = p[1]
        if mode == 0:
            wanted = {k: False for k in range(len(self._lists))}
        elif mode in (1, 2):
            wanted = {k: mode == 1 for k, d in enumerate(self._lists) if d.selected}
        else:
            raise _Refused(ERR_MODE_NOT_VALID)
        self._set_running(wanted)
        for d in self._lists:
            d.selected = False
        return b""

    def _apply(self) -> None:
        """Hands the whole configuration to the producer; refreshes the
        sender's view of it."""
        # a STIM list is not measured: the producer has it as not running
        lists = tuple(
            DaqListConfig(
                odts=tuple(tuple(e for e in entries if e is not None) for entries in d.odts),
                event=d.event, prescaler=d.prescaler, running=d.running and not d.stim)
            for d in self._lists)
        _check(self.daq.apply(lists))
        self._dto_views = tuple(
            _DtoView(
                running=d.running and not d.stim,
                timestamp=d.timestamp,
                sizes=tuple(sum(e.size for e in entries if e is not None) for entries in d.odts),
                headers=tuple(bytes([odt, 0]) + _U16.pack(k) for odt in range(len(d.odts))))
            for k, d in enumerate(self._lists))

    # ---- the clock ---------------------------------------------------------------
    def _get_daq_clock(self, p: bytes) -> bytes:
        now = self.clock_ns() // TIMESTAMP_UNIT_NS
        if not self._clock_format:             # legacy: the low 32 bits
            return bytes([0, _TRIGGER_INFO, _PAYLOAD_SLAVE_DWORD]) + _U32.pack(now & 0xFFFFFFFF)
        return bytes([0, _TRIGGER_INFO, _PAYLOAD_SLAVE_DLONG]) + \
            _U64.pack(now & 0xFFFF_FFFF_FFFF_FFFF) + bytes([_SYNC_STATE])

    def _time_correlation_properties(self, p: bytes) -> bytes:
        setting, request, cluster = p[1], p[2], _u16(p, 4)
        response_fmt, bridge = setting & 0x03, (setting >> 2) & 0x03
        if response_fmt == 3 or bridge:        # reserved; no time sync bridge to switch
            raise _Refused(ERR_OUT_OF_RANGE)
        if response_fmt:
            self._clock_format = response_fmt
        if setting & 0x10:                     # SET_CLUSTER_ID
            self._cluster_id = cluster
        if request & 0x01:                     # GET_CLK_INFO: the slave clock's, by UPLOAD
            self._mta = (self._clock_info, 0)
        # SLAVE_CONFIG: the response format, DAQ timestamps of the slave clock, no bridge
        return bytes([self._clock_format, _OBSERVABLE_CLOCKS, _SYNC_STATE, _CLOCK_INFO_SLAVE,
                      0]) + _U16.pack(self._cluster_id)

    # ---- DAQ: information ---------------------------------------------------------

    def _get_daq_processor_info(self, p: bytes) -> bytes:
        # OVERLOAD_EVENT, TIMESTAMP_SUPPORTED, PRESCALER_SUPPORTED, DYNAMIC
        properties = 0x80 | 0x10 | 0x02 | 0x01
        key = (_IDF_REL_ODT_ABS_DAQ_WORD_ALIGNED << 6) | (_AE_SAME_FOR_ALL_DAQ << 4)
        return bytes([properties]) + _U16.pack(self.limits.max_lists) + \
            _U16.pack(len(self.events)) + bytes([0, key])

    def _get_daq_resolution_info(self, p: bytes) -> bytes:
        ts_mode = (_TS_UNIT_CODE << 4) | _TS_SIZE_CODE    # not fixed: selectable per list
        entry = min(self.limits.odt_bytes, 255)
        return bytes([1, entry, 1, entry if self.stim_events else 0, ts_mode]) + _U16.pack(1)

    def _get_daq_list_info(self, p: bytes) -> bytes:
        d = self._list(_u16(p, 2))
        kind = 0x0C if self.stim_events else 0x04   # DAQ, and STIM when some event takes it
        return bytes([kind, len(d.odts), max((len(e) for e in d.odts), default=0)]) + \
            _U16.pack(0)                        # no fixed event

    def _get_daq_event_info(self, p: bytes) -> bytes:
        n = _u16(p, 2)
        if n >= len(self.events):
            raise _Refused(ERR_OUT_OF_RANGE)
        event = self.events[n]
        name = event.name.encode("ascii", "replace")[:255]
        cycle, unit = event_cycle(event.cycle_s)
        self._mta = (name, 0)
        # DAQ (and STIM), consistency per event channel; any number of lists; priority 0
        properties = 0x84 | (0x08 if n in self.stim_events else 0)
        return bytes([properties, 0xFF, len(name), cycle, unit, 0])

    # ---- STIM: DTOs from the master -------------------------------------------------
    def _stim_drop(self, reason: str) -> None:
        self._bump(self._ignored, "stim_" + reason)    # a packet ignored, as every other

    def _stim_dto(self, p: bytes) -> None:
        """Writes one STIM DTO's values (``[odt, fill, list lo, list hi, data]``)."""
        self._stim["dtos"] += 1
        if not self.connected:
            return self._stim_drop("not_connected")
        if len(p) < DTO_HEADER_BYTES:
            return self._stim_drop("bad_length")
        odt, n = p[0], _u16(p, 2)
        if n >= len(self._lists):
            return self._stim_drop("unknown_list")
        d = self._lists[n]
        if not d.stim or not d.running:
            return self._stim_drop("not_running")
        if odt >= len(d.odts):
            return self._stim_drop("unknown_odt")
        entries = d.odts[odt]
        if len(p) != DTO_HEADER_BYTES + sum(e.size for e in entries):
            return self._stim_drop("bad_length")
        spans: list[list] = []                 # adjacent entries: one write
        at = DTO_HEADER_BYTES
        for e in entries:
            value = p[at:at + e.size]
            at += e.size
            if spans and spans[-1][0] + len(spans[-1][1]) == e.address:
                spans[-1][1] += value
            else:
                spans.append([e.address, bytearray(value)])
        try:
            for address, data in spans:
                self._write(address, bytes(data), queued=True)
        except _Refused as e:
            return self._stim_drop(error_name(e.code))
        except Exception:  # a backend's bug must not stop the slave
            return self._stim_drop("internal_error")
        self._stim["written"] += 1

    # ---- the sender's side ----------------------------------------------------------
    def dto_packet(self, dto: Dto) -> bytes | None:
        """The DTO packet for one measured ODT, or None when its list is not
        running (any more) or the ODT does not match the list's configuration
        (a DTO of an older configuration): dropped and counted."""
        views = self._dto_views
        if dto.list >= len(views) or not views[dto.list].running:
            self._dto_dropped["not_running"] += 1
            return None
        v = views[dto.list]
        if dto.odt >= len(v.sizes) or len(dto.data) != v.sizes[dto.odt]:
            self._dto_dropped["stale"] += 1
            return None
        self._counts["dtos"] += 1
        if dto.odt == 0 and v.timestamp:
            ts = (dto.time_ns // TIMESTAMP_UNIT_NS) & 0xFFFFFFFF
            return v.headers[0] + _U32.pack(ts) + dto.data
        return v.headers[dto.odt] + dto.data

    def overload_events(self, dropped: int) -> list[bytes]:
        """EV_DAQ_OVERLOAD when the producer lost DTOs since the last call."""
        if dropped <= self._overloads_seen:
            self._overloads_seen = dropped
            return []
        self._overloads_seen = dropped
        if not self.daq_running:
            return []
        self._overload_events += 1
        return [bytes([PID_EV, EV_DAQ_OVERLOAD])]
