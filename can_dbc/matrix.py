"""CAN matrix files: DBC, AUTOSAR system descriptions (ARXML), KCD and SYM.

``read_matrix(path)`` is the one reader every command's matrix goes through
(``can_dbc.mapping.read_dbc``: mapping check, show, template, simulate,
serve, demo, tcu): cantools reads the file leniently, its format by its
suffix (``.dbc``, ``.arxml``, ``.kcd``, ``.sym``; DBC for any other), its text as UTF-8 when it
is valid UTF-8, else as cp1252 (``can_dbc.codec.dbc_encoding``). Anything it
cannot read is a ValueError of one line naming the file and the cause.

``file_protections(db, path)`` gives the end-to-end protection an ARXML file
declares for its messages, as ``can_dbc.protection.Protection``: from an
E2E transformer (an I-signal group's END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS
and the END-TO-END-TRANSFORMATION-DESCRIPTION of its transformer) or from an
END-TO-END-PROTECTION-SET (END-TO-END-PROFILE, the PDUs it protects). The
profile names the kind (``PROFILE_01`` p1, ``PROFILE_02`` p2, ``PROFILE_04``
p4, ``PROFILE_05`` p5, ``PROFILE_07`` p7); DATA-IDS the Data ID (P1, P4, P5,
P7) or the 16 of P2; DATA-ID-MODE P1's mode
(ALL_16_BIT both, ALTERNATING_8_BIT alt, LOWER_8_BIT low, LOWER_12_BIT
nibble); MAX-DELTA-COUNTER (or MAX-DELTA-COUNTER-INIT) the counter's
largest step. The CRC and counter signals are the message's signals where
the profile puts them: P1 the CRC byte at CRC-OFFSET (bits, default 0), the
4-bit counter at COUNTER-OFFSET (default 8), the Data ID nibble at
DATA-ID-NIBBLE-OFFSET (default 12); P2 the CRC in byte 0, the counter in
the low nibble of byte 1; P5 the 16-bit CRC at OFFSET (bits, default 0),
low byte first, and the counter byte after it; P4 the 16-bit counter 2
bytes after OFFSET and the 32-bit CRC 8 bytes after it, big endian; P7 the
64-bit CRC at OFFSET and the 32-bit counter 12 bytes after it, big endian
(named when the message has signals there; the codec writes the header
either way). A profile the codec does not have (P6, P11, P22, ...) or a field
the message lacks is kept as the cause of a one-line error, raised only when
the message is used without a ``protection`` in the mapping.
"""

from __future__ import annotations

import logging
import os
import re
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from dataclasses import replace

from .codec import dbc_encoding, signal_bits
from .protection import HEADER_BYTES, Protection, header_field_bits
from .python_can import python_can

__all__ = ["FORMATS", "file_protections", "matrix_format", "read_matrix", "select_cluster"]

#: file suffix -> cantools database format
FORMATS = {".dbc": "dbc", ".arxml": "arxml", ".kcd": "kcd", ".sym": "sym"}
#: the ARXML profile numbers the codec has, as protection kinds
_PROFILES = {1: "p1", 2: "p2", 4: "p4", 5: "p5", 7: "p7"}
_P1_MODES = {"ALL_16_BIT": "both", "ALTERNATING_8_BIT": "alt", "LOWER_8_BIT": "low",
             "LOWER_12_BIT": "nibble"}


@contextmanager
def _quiet_cantools():
    log = logging.getLogger("cantools")
    before = log.disabled
    log.disabled = True
    try:
        yield
    finally:
        log.disabled = before


def matrix_format(path):
    """The cantools format of a matrix file by its suffix; DBC for any other."""
    return FORMATS.get(os.path.splitext(str(path))[1].lower(), "dbc")


def read_matrix(path):
    """The cantools database of a CAN matrix file, read leniently (see the
    module's text); ValueError with one line naming the file and the cause."""
    python_can()  # cantools imports can: without asammdf (can_dbc.python_can)
    import cantools

    fmt = matrix_format(path)
    try:
        encoding = dbc_encoding(path)
    except OSError as e:
        raise ValueError(f"cannot read {path}: {e.strerror}") from None
    try:
        with _quiet_cantools():
            return cantools.database.load_file(path, database_format=fmt, encoding=encoding,
                                               strict=False)
    except OSError as e:
        raise ValueError(f"cannot read {path}: {e.strerror}") from None
    except Exception as e:  # cantools' own parse errors, XML errors, assertions of its loaders
        text = " ".join(str(e).split()) or type(e).__name__
        raise ValueError(f"cantools cannot parse {path} as {fmt.upper()}: {text}") from None


def select_cluster(db, path, cluster):
    """The messages of one CAN cluster of an ARXML (``cluster``: its name;
    None: the file's only one) as a database of their own, or ValueError (one
    line) when the file has several and none is named, or not that one."""
    names = []
    for m in db.messages:
        if m.bus_name not in names:
            names.append(m.bus_name)
    if cluster is None:
        if len(names) <= 1:
            return db
        raise ValueError(f"{path} has the CAN clusters {', '.join(str(n) for n in names)}: give the "
                         "bus's cluster = \"NAME\"")
    if cluster not in names:
        raise ValueError(f"{path} has no CAN cluster {cluster!r} (its clusters: "
                         f"{', '.join(str(n) for n in names) or 'none'})")
    python_can()
    from cantools.database.can import Database

    return Database(messages=[m for m in db.messages if m.bus_name == cluster], nodes=list(db.nodes),
                    buses=[b for b in db.buses if b.name == cluster], version=db.version,
                    dbc_specifics=db.dbc, autosar_specifics=db.autosar, strict=False)


# ---------------------------------------------------------------------------
# E2E protection in an ARXML
# ---------------------------------------------------------------------------

class _Arxml:
    """The elements of an ARXML by their AUTOSAR path (/Package/Element/...)."""

    def __init__(self, path):
        self.root = ET.parse(path).getroot()
        m = re.match(r"^\{(.*)\}", self.root.tag)
        self.ns = m.group(1) if m else ""
        self.by_path = {}
        self._index(self.root, "")

    def tag(self, name):
        return f"{{{self.ns}}}{name}" if self.ns else name

    def _index(self, elem, prefix):
        name = elem.find(self.tag("SHORT-NAME"))
        here = prefix
        if name is not None and name.text:
            here = f"{prefix}/{name.text.strip()}"
            self.by_path[here] = elem
        for child in elem:
            self._index(child, here)

    def child(self, elem, *names):
        for n in names:
            if elem is None:
                return None
            elem = elem.find(self.tag(n))
        return elem

    def text(self, elem, *names):
        e = self.child(elem, *names)
        return None if e is None or e.text is None else e.text.strip()

    def number(self, elem, *names):
        t = self.text(elem, *names)
        if t is None:
            return None
        try:
            return int(t, 0)
        except ValueError:
            return None

    def ref(self, elem, *names):
        t = self.text(elem, *names)
        return None if t is None else self.by_path.get(t)

    def iter(self, elem, name):
        return elem.iter(self.tag(name))

    def data_ids(self, elem):
        ids = self.child(elem, "DATA-IDS")
        if ids is None:
            return []
        out = []
        for d in ids:
            try:
                out.append(int((d.text or "").strip(), 0))
            except ValueError:
                pass
        return out


def _profile_number(name):
    m = re.search(r"(\d+)\s*$", str(name or ""))
    return int(m.group(1)) if m else None


def _declared(ar):
    """{PDU path: (profile name, {field: value}, data ids)} from both styles."""
    found = {}
    # E2E transformer: a PDU's I-signal group with END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS
    for pdu in ar.iter(ar.root, "I-SIGNAL-I-PDU"):
        pdu_path = next((p for p, e in ar.by_path.items() if e is pdu), None)
        if pdu_path is None:
            continue
        for mapping in ar.iter(pdu, "I-SIGNAL-TO-I-PDU-MAPPING"):
            group = ar.ref(mapping, "I-SIGNAL-GROUP-REF")
            if group is None:
                continue
            for props in ar.iter(group, "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS"):
                cond = ar.child(props, "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-VARIANTS",
                                "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-CONDITIONAL")
                cond = props if cond is None else cond
                technology = ar.ref(cond, "TRANSFORMER-REF")
                desc = ar.child(technology, "TRANSFORMATION-DESCRIPTIONS",
                                "END-TO-END-TRANSFORMATION-DESCRIPTION")
                if desc is None:
                    continue
                found[pdu_path] = (ar.text(desc, "PROFILE-NAME"), _fields(ar, desc), ar.data_ids(cond))
    # END-TO-END-PROTECTION-SET: a profile and the PDUs it protects
    for protection in ar.iter(ar.root, "END-TO-END-PROTECTION"):
        profile = ar.child(protection, "END-TO-END-PROFILE")
        if profile is None:
            continue
        for ref in ar.iter(protection, "I-SIGNAL-I-PDU-REF"):
            path = (ref.text or "").strip()
            found.setdefault(path, (ar.text(profile, "CATEGORY"), _fields(ar, profile),
                                    ar.data_ids(profile)))
    return found


def _fields(ar, elem):
    out = {}
    for key in ("CRC-OFFSET", "COUNTER-OFFSET", "DATA-ID-NIBBLE-OFFSET", "OFFSET", "MAX-DELTA-COUNTER",
                "MAX-DELTA-COUNTER-INIT"):
        v = ar.number(elem, key)
        if v is not None:
            out[key] = v
    mode = ar.text(elem, "DATA-ID-MODE")
    if mode is not None:
        out["DATA-ID-MODE"] = mode
    return out


def _signal_at(msg, bits):
    """The message's signal that occupies exactly ``bits`` (frame bit numbers)."""
    want = set(bits)
    for s in msg.signals:
        if s.multiplexer_signal is None and set(signal_bits(s)) == want:
            return s.name
    return None


def _protection(msg, profile, fields, data_ids):
    """A Protection, or the cause (str) why the codec cannot take the file's."""
    number = _profile_number(profile)
    kind = _PROFILES.get(number)
    if kind is None:
        what = f"E2E profile {profile or '(unnamed)'}"
        return f"{what} is not supported: the codec has profiles 1, 2, 4, 5 and 7; give the message's protection"
    delta = fields.get("MAX-DELTA-COUNTER", fields.get("MAX-DELTA-COUNTER-INIT"))
    extra = {} if delta is None else {"max_delta_counter": delta}
    if kind in HEADER_BYTES:
        if len(data_ids) != 1:
            return f"E2E profile {number} needs one Data ID, the file gives {len(data_ids)}"
        offset = fields.get("OFFSET", 0)
        if offset % 8 or offset // 8 + HEADER_BYTES[kind] > msg.length:
            return (f"E2E profile {number} header ({HEADER_BYTES[kind]} bytes) at bit {offset} does not fit "
                    f"the {msg.length}-byte frame")
        if not 0 <= data_ids[0] < 2 ** (16 if kind == "p5" else 32):
            return f"E2E profile {number}'s Data ID {data_ids[0]} is out of range"
        prot = Protection(kind=kind, data_id=data_ids[0], offset_bits=offset, **extra)
        return replace(prot, crc_signal=_signal_at(msg, header_field_bits(prot, "crc")),
                       counter_signal=_signal_at(msg, header_field_bits(prot, "counter")))
    if kind == "p2":
        if len(data_ids) != 16:
            return f"E2E profile 2 needs 16 Data IDs, the file gives {len(data_ids)}"
        crc_at, counter_at = 0, 8
    else:
        if len(data_ids) != 1:
            return f"E2E profile 1 needs one Data ID, the file gives {len(data_ids)}"
        crc_at, counter_at = fields.get("CRC-OFFSET", 0), fields.get("COUNTER-OFFSET", 8)
    crc = _signal_at(msg, range(crc_at, crc_at + 8))
    counter = _signal_at(msg, range(counter_at, counter_at + 4))
    for role, name, at, n in (("CRC", crc, crc_at, 8), ("counter", counter, counter_at, 4)):
        if name is None:
            return (f"E2E profile {number} puts the {role} at bits {at}..{at + n - 1}, where the message "
                    f"has no {n}-bit signal")
    if kind == "p2":
        if any(not 0 <= d <= 255 for d in data_ids):
            return "E2E profile 2's Data IDs must be 8 bits each"
        return Protection(kind="p2", crc_signal=crc, counter_signal=counter, data_id_list=tuple(data_ids),
                          **extra)
    mode_text = fields.get("DATA-ID-MODE", "ALL_16_BIT")
    mode = _P1_MODES.get(mode_text)
    if mode is None:
        return f"E2E profile 1 DATA-ID-MODE {mode_text!r}: choose one of {', '.join(_P1_MODES)}"
    nibble = None
    if mode == "nibble":
        at = fields.get("DATA-ID-NIBBLE-OFFSET", 12)
        nibble = _signal_at(msg, range(at, at + 4))
        if nibble is None:
            return (f"E2E profile 1 puts the Data ID nibble at bits {at}..{at + 3}, where the message "
                    "has no 4-bit signal")
    if not 0 <= data_ids[0] <= 0xFFFF:
        return "E2E profile 1's Data ID must be 16 bits"
    return Protection(kind="p1", crc_signal=crc, counter_signal=counter, data_id=data_ids[0],
                      data_id_mode=mode, data_id_nibble_signal=nibble, **extra)


def file_protections(db, path):
    """{message name: Protection, or the one-line cause why it cannot be used}
    for the messages of ``db`` an ARXML at ``path`` protects end to end (empty
    for other formats); ValueError (one line) when the file cannot be read."""
    if matrix_format(path) != "arxml":
        return {}
    try:
        ar = _Arxml(path)
    except (OSError, ET.ParseError) as e:
        raise ValueError(f"cannot read the E2E protection of {path}: {e}") from None
    declared = _declared(ar)
    out = {}
    for msg in db.messages:
        autosar = getattr(msg, "autosar", None)
        paths = list(getattr(autosar, "pdu_paths", None) or [])
        hit = next((declared[p] for p in paths if p in declared), None)
        if hit is None:
            e2e = getattr(autosar, "e2e", None)
            if e2e is None or e2e.category is None:
                continue
            hit = (e2e.category, {}, list(e2e.data_ids or []))
        profile, fields, ids = hit
        out[msg.name] = _protection(msg, profile, fields, ids)
    return out
