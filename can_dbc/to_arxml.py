"""A bus of a mapping file as an AUTOSAR 4 system description (ARXML).

``arxml_text(mapping, bus)`` writes the bus's matrix (its DBC, as cantools
reads it) in AUTOSAR R4 form, with the mapping's end-to-end protection where
AUTOSAR has it (Profiles 1, 2, 4, 5 and 7 as E2E transformers):

* ``<package>/Units``, ``CompuMethods`` (factor and offset as a LINEAR scale
  over the raw range, value names as TEXTTABLE scales beside it), ``BaseTypes``
  (unsigned, two's complement or IEEE 754 of each length);
* ``SystemSignals`` and ``ISignals`` (length, base type, raw start value),
  ``ISignalGroups`` (one per protected message, with its
  END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS: transformer and Data IDs) and
  ``Transformers`` (a DATA-TRANSFORMATION-SET: one E2E transformation
  technology per profile configuration: CRC, counter and Data ID nibble
  offsets, Data ID mode, max delta counter; Profiles 4, 5 and 7 their
  header's OFFSET);
* ``Pdus``: an I-SIGNAL-I-PDU per message (length, cycle time, unused bits 0,
  I-signal-to-PDU mappings with start position and packing byte order), a
  MULTIPLEXED-I-PDU with one alternative I-SIGNAL-I-PDU per branch for a
  multiplexed message; ``PduGroups``: each ECU's sent (OUT) and received (IN)
  PDUs;
* ``Frames`` (CAN-FRAME, its PDU mapping), ``Ecus`` (ECU-INSTANCE with a CAN
  controller, a connector, a frame port and an I-PDU port per frame it sends
  or receives, and its PDU groups), ``Clusters`` (CAN-CLUSTER with the baud
  rate, a physical channel, a frame triggering per message: identifier,
  addressing mode, CAN 2.0 or CAN FD, the ports; its PDU triggerings) and a
  SYSTEM naming them.

``python -m can_dbc.to_arxml`` writes the shipped example: the example
vehicle matrix's pt bus (can_dbc/mappings/vehicle.toml) as
can_dbc/matrices/vehicle_pt.arxml, and can_dbc/mappings/vehicle_arxml.toml,
vehicle.toml with the pt bus on the ARXML and without the ``protection`` of
the messages whose E2E protection the ARXML carries (the others, XOR and
counter only, keep theirs: AUTOSAR has no profile for them). ``--check``
exits 1 when the shipped files differ from what it would write.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import xml.etree.ElementTree as ET

from .codec import signal_bits
from .matrix import read_matrix

__all__ = ["E2E_KINDS", "arxml_text", "example_mapping_text", "main"]

NS = "http://autosar.org/schema/r4.0"
SCHEMA = "http://autosar.org/schema/r4.0 AUTOSAR_4-2-2.xsd"
#: the protection kinds an ARXML can carry, as AUTOSAR profile names
E2E_KINDS = {"p1": "PROFILE_01", "p2": "PROFILE_02", "p4": "PROFILE_04", "p5": "PROFILE_05",
             "p7": "PROFILE_07"}
_P1_MODES = {"both": "ALL_16_BIT", "alt": "ALTERNATING_8_BIT", "low": "LOWER_8_BIT",
             "nibble": "LOWER_12_BIT"}

HERE = os.path.dirname(os.path.abspath(__file__))
EXAMPLE_MAPPING = os.path.join(HERE, "mappings", "vehicle.toml")
EXAMPLE_ARXML = os.path.join(HERE, "matrices", "vehicle_pt.arxml")
EXAMPLE_ARXML_MAPPING = os.path.join(HERE, "mappings", "vehicle_arxml.toml")


def _e(parent, tag, text=None, **attrs):
    el = ET.SubElement(parent, tag, {k.replace("_", "-"): v for k, v in attrs.items()})
    if text is not None:
        el.text = str(text)
    return el


def _named(parent, tag, name):
    el = _e(parent, tag)
    _e(el, "SHORT-NAME", name)
    return el


def _desc(el, text):
    if text:
        _e(_e(el, "DESC"), "L-2", " ".join(str(text).split()), L="EN")


def _num(x):
    """A number as ARXML text: whole numbers without a point, others with repr's digits."""
    if isinstance(x, bool):
        return str(int(x))
    if isinstance(x, int) or (isinstance(x, float) and x.is_integer() and abs(x) < 2 ** 53):
        return str(int(x))
    return repr(float(x))


def _ident(name):
    return re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "x"


class _Writer:
    def __init__(self, mapping, bus, package):
        self.mapping = mapping
        self.bus = mapping.bus(bus)
        self.db = read_matrix(self.bus.dbc)
        self.pkg = "/" + package
        self.used = {m.name: m for m in mapping.codec_order(bus)}
        self.root = ET.Element("AUTOSAR", {"xmlns": NS,
                                           "xmlns:xsi": "http://www.w3.org/2001/XMLSchema-instance",
                                           "xsi:schemaLocation": SCHEMA})
        top = _named(_e(self.root, "AR-PACKAGES"), "AR-PACKAGE", package)
        self.packages = _e(top, "AR-PACKAGES")
        self._pkgs = {}
        self.units = {}
        self.base_types = {}
        self.compu = {}
        self.transformers = {}

    def package(self, name):
        if name not in self._pkgs:
            self._pkgs[name] = _e(_named(self.packages, "AR-PACKAGE", name), "ELEMENTS")
        return self._pkgs[name]

    def path(self, package, name):
        return f"{self.pkg}/{package}/{name}"

    # ------------------------------------------------------------ signals
    def unit(self, text):
        text = (text or "").strip()
        if not text:
            return None
        if text not in self.units:
            name = "U_" + _ident(text.replace("%", "pct").replace("/", "_per_"))
            el = _named(self.package("Units"), "UNIT", name)
            _e(el, "DISPLAY-NAME", text)
            self.units[text] = self.path("Units", name)
        return self.units[text]

    def base_type(self, sig):
        enc = "IEEE754" if sig.is_float else "2C" if sig.is_signed else "NONE"
        key = (enc, sig.length)
        if key not in self.base_types:
            name = {"IEEE754": "float", "2C": "sint", "NONE": "uint"}[enc] + str(sig.length)
            el = _named(self.package("BaseTypes"), "SW-BASE-TYPE", name)
            _e(el, "CATEGORY", "FIXED_LENGTH")
            _e(el, "BASE-TYPE-SIZE", sig.length)
            _e(el, "BASE-TYPE-ENCODING", enc)
            self.base_types[key] = self.path("BaseTypes", name)
        return self.base_types[key]

    def compu_method(self, msg, sig):
        """The path of a compu method for the signal's scaling, range, unit and
        value names: shared by every signal with the same (named after the first)."""
        choices = dict(sig.choices or {})
        limits = None
        if sig.minimum is not None and sig.maximum is not None:
            lo = round((sig.minimum - sig.offset) / sig.scale)
            hi = round((sig.maximum - sig.offset) / sig.scale)
            limits = (min(lo, hi), max(lo, hi))
        key = (float(sig.scale), float(sig.offset), (sig.unit or "").strip(), limits,
               tuple(sorted((k, str(v)) for k, v in choices.items())))
        if key in self.compu:
            return self.compu[key]
        name = f"CM_{msg.name}_{sig.name}"
        self.compu[key] = self.path("CompuMethods", name)
        el = _named(self.package("CompuMethods"), "COMPU-METHOD", name)
        _e(el, "CATEGORY", "SCALE_LINEAR_AND_TEXTTABLE" if choices else "LINEAR")
        unit = self.unit(sig.unit)
        if unit:
            _e(el, "UNIT-REF", unit, DEST="UNIT")
        scales = _e(_e(el, "COMPU-INTERNAL-TO-PHYS"), "COMPU-SCALES")
        for raw, text in sorted(choices.items()):
            sc = _e(scales, "COMPU-SCALE")
            _e(sc, "SHORT-LABEL", _ident(text))
            _e(sc, "LOWER-LIMIT", _num(raw), INTERVAL_TYPE="CLOSED")
            _e(sc, "UPPER-LIMIT", _num(raw), INTERVAL_TYPE="CLOSED")
            _e(_e(sc, "COMPU-CONST"), "VT", str(text))
        sc = _e(scales, "COMPU-SCALE")
        if limits is not None:
            _e(sc, "LOWER-LIMIT", _num(limits[0]), INTERVAL_TYPE="CLOSED")
            _e(sc, "UPPER-LIMIT", _num(limits[1]), INTERVAL_TYPE="CLOSED")
        coeffs = _e(sc, "COMPU-RATIONAL-COEFFS")
        num = _e(coeffs, "COMPU-NUMERATOR")
        _e(num, "V", _num(sig.offset))
        _e(num, "V", _num(sig.scale))
        _e(_e(coeffs, "COMPU-DENOMINATOR"), "V", "1")
        return self.compu[key]

    def system_signal_name(self, msg, sig):
        """The I-signal's and system signal's name: the signal's name in the
        matrix (cantools reads the I-signal's as the signal's), prefixed by the
        message's where it is not unique."""
        unique = sum(1 for m in self.db.messages for s in m.signals if s.name == sig.name) == 1
        return sig.name if unique else f"{msg.name}_{sig.name}"

    def signal(self, msg, sig):
        """The I-SIGNAL (and its system signal) of one signal; returns its path."""
        name = ss_name = self.system_signal_name(msg, sig)
        cm = self.compu_method(msg, sig)
        ss = _named(self.package("SystemSignals"), "SYSTEM-SIGNAL", ss_name)
        _desc(ss, sig.comment)
        cond = _e(_e(_e(ss, "PHYSICAL-PROPS"), "SW-DATA-DEF-PROPS-VARIANTS"), "SW-DATA-DEF-PROPS-CONDITIONAL")
        _e(cond, "COMPU-METHOD-REF", cm, DEST="COMPU-METHOD")
        isig = _named(self.package("ISignals"), "I-SIGNAL", name)
        _e(isig, "DATA-TYPE-POLICY", "LEGACY")
        if sig.raw_initial is not None:
            _e(_e(_e(isig, "INIT-VALUE"), "NUMERICAL-VALUE-SPECIFICATION"), "VALUE", _num(sig.raw_initial))
        _e(isig, "LENGTH", sig.length)
        cond = _e(_e(_e(isig, "NETWORK-REPRESENTATION-PROPS"), "SW-DATA-DEF-PROPS-VARIANTS"),
                  "SW-DATA-DEF-PROPS-CONDITIONAL")
        _e(cond, "BASE-TYPE-REF", self.base_type(sig), DEST="SW-BASE-TYPE")
        _e(isig, "SYSTEM-SIGNAL-REF", self.path("SystemSignals", ss_name), DEST="SYSTEM-SIGNAL")
        return self.path("ISignals", name)

    # ------------------------------------------------------------ E2E
    def e2e(self, msg, prot):
        """The transformer path and Data IDs of a message's protection, or None."""
        if prot.kind not in E2E_KINDS:
            return None
        sigs = {s.name: s for s in msg.signals}
        fields = {"PROFILE-NAME": E2E_KINDS[prot.kind], "MAX-DELTA-COUNTER": prot.max_delta_counter}
        if prot.kind == "p1":
            fields["CRC-OFFSET"] = min(signal_bits(sigs[prot.crc_signal]))
            fields["COUNTER-OFFSET"] = min(signal_bits(sigs[prot.counter_signal]))
            fields["DATA-ID-MODE"] = _P1_MODES[prot.data_id_mode]
            if prot.data_id_mode == "nibble":
                fields["DATA-ID-NIBBLE-OFFSET"] = min(signal_bits(sigs[prot.data_id_nibble_signal]))
        if prot.kind in ("p4", "p5", "p7"):
            fields["OFFSET"] = prot.offset_bits
        key = tuple(sorted(fields.items()))
        if key not in self.transformers:
            name = f"E2E_{len(self.transformers) + 1}_{fields['PROFILE-NAME']}"
            self.transformers[key] = (name, fields)
        ids = list(prot.data_id_list) if prot.kind == "p2" else [prot.data_id]
        return self.path("Transformers", "E2E/" + self.transformers[key][0]), ids

    def write_transformers(self):
        if not self.transformers:
            return
        dts = _named(self.package("Transformers"), "DATA-TRANSFORMATION-SET", "E2E")
        techs = _e(dts, "TRANSFORMATION-TECHNOLOGYS")
        for name, fields in self.transformers.values():
            t = _named(techs, "TRANSFORMATION-TECHNOLOGY", name)
            _e(t, "PROTOCOL", "E2E")
            desc = _e(_e(t, "TRANSFORMATION-DESCRIPTIONS"), "END-TO-END-TRANSFORMATION-DESCRIPTION")
            for k in sorted(fields):
                _e(desc, k, fields[k])
            _e(t, "TRANSFORMER-CLASS", "SAFETY")
            _e(t, "VERSION", "1.0.0")

    # ------------------------------------------------------------ PDUs
    def pdu(self, name, length, cycle_ms, signals, msg, group=None):
        el = _named(self.package("Pdus"), "I-SIGNAL-I-PDU", name)
        _e(el, "LENGTH", length)
        if cycle_ms:
            timing = _e(_e(el, "I-PDU-TIMING-SPECIFICATIONS"), "I-PDU-TIMING")
            cyc = _e(_e(_e(timing, "TRANSMISSION-MODE-DECLARATION"), "TRANSMISSION-MODE-TRUE-TIMING"),
                     "CYCLIC-TIMING")
            _e(_e(cyc, "TIME-PERIOD"), "VALUE", _num(cycle_ms / 1000.0))
        maps = _e(el, "I-SIGNAL-TO-PDU-MAPPINGS")
        if group is not None:
            gm = _named(maps, "I-SIGNAL-TO-I-PDU-MAPPING", f"{name}_E2E")
            _e(gm, "I-SIGNAL-GROUP-REF", group, DEST="I-SIGNAL-GROUP")
        for sig, ref in signals:
            m = _named(maps, "I-SIGNAL-TO-I-PDU-MAPPING", f"{name}_{sig.name}")
            _e(m, "I-SIGNAL-REF", ref, DEST="I-SIGNAL")
            _e(m, "PACKING-BYTE-ORDER", "MOST-SIGNIFICANT-BYTE-FIRST" if sig.byte_order == "big_endian"
               else "MOST-SIGNIFICANT-BYTE-LAST")
            _e(m, "START-POSITION", sig.start)
            _e(m, "TRANSFER-PROPERTY", "PENDING")
        _e(el, "UNUSED-BIT-PATTERN", 0)
        return self.path("Pdus", name), "I-SIGNAL-I-PDU"

    def message_pdu(self, msg, refs):
        used = self.used.get(msg.name)
        cycle = used.cycle_ms if used is not None else msg.cycle_time
        group = None
        e2e = self.e2e(msg, used.protection) if used is not None else None
        if e2e is not None:
            transformer, ids = e2e
            g = _named(self.package("ISignalGroups"), "I-SIGNAL-GROUP", f"{msg.name}_E2E")
            irefs = _e(g, "I-SIGNAL-REFS")
            for sig in msg.signals:
                _e(irefs, "I-SIGNAL-REF", refs[sig.name], DEST="I-SIGNAL")
            _e(g, "SYSTEM-SIGNAL-GROUP-REF", self.path("SystemSignalGroups", f"{msg.name}_E2E"),
               DEST="SYSTEM-SIGNAL-GROUP")
            props = _e(_e(_e(_e(g, "TRANSFORMATION-I-SIGNAL-PROPSS"), "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS"),
                          "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-VARIANTS"),
                       "END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS-CONDITIONAL")
            _e(props, "TRANSFORMER-REF", transformer, DEST="TRANSFORMATION-TECHNOLOGY")
            did = _e(props, "DATA-IDS")
            for d in ids:
                _e(did, "DATA-ID", d)
            _e(props, "DATA-LENGTH", 8 * msg.length)
            ssg = _named(self.package("SystemSignalGroups"), "SYSTEM-SIGNAL-GROUP", f"{msg.name}_E2E")
            srefs = _e(ssg, "SYSTEM-SIGNAL-REFS")
            for sig in msg.signals:
                _e(srefs, "SYSTEM-SIGNAL-REF", self.path("SystemSignals", self.system_signal_name(msg, sig)),
                   DEST="SYSTEM-SIGNAL")
            group = self.path("ISignalGroups", f"{msg.name}_E2E")
        mux = [s for s in msg.signals if s.is_multiplexer]
        if not mux:
            return self.pdu(msg.name, msg.length, cycle, [(s, refs[s.name]) for s in msg.signals], msg, group)
        if len(mux) != 1 or any(s.multiplexer_signal not in (None, mux[0].name) for s in msg.signals):
            raise ValueError(f"{msg.name}: one multiplexer per message only (no nested multiplexers)")
        sel = mux[0]
        static = [s for s in msg.signals if s.multiplexer_signal is None and s is not sel]
        el = _named(self.package("Pdus"), "MULTIPLEXED-I-PDU", msg.name)
        _e(el, "LENGTH", msg.length)
        if cycle:
            timing = _e(_e(el, "I-PDU-TIMING-SPECIFICATIONS"), "I-PDU-TIMING")
            cyc = _e(_e(_e(timing, "TRANSMISSION-MODE-DECLARATION"), "TRANSMISSION-MODE-TRUE-TIMING"),
                     "CYCLIC-TIMING")
            _e(_e(cyc, "TIME-PERIOD"), "VALUE", _num(cycle / 1000.0))
        alts = _e(_e(_e(el, "DYNAMIC-PARTS"), "DYNAMIC-PART"), "DYNAMIC-PART-ALTERNATIVES")
        codes = sorted({i for s in msg.signals for i in (s.multiplexer_ids or ())})
        initial = sel.raw_initial if sel.raw_initial is not None else codes[0]
        for code in codes:
            branch = [s for s in msg.signals if s.multiplexer_ids and code in s.multiplexer_ids]
            path, _ = self.pdu(f"{msg.name}_{code}", msg.length, cycle,
                               [(sel, refs[sel.name])] + [(s, refs[s.name]) for s in branch], msg)
            alt = _e(alts, "DYNAMIC-PART-ALTERNATIVE")
            _e(alt, "I-PDU-REF", path, DEST="I-SIGNAL-I-PDU")
            _e(alt, "INITIAL-DYNAMIC-PART", "true" if code == initial else "false")
            _e(alt, "SELECTOR-FIELD-CODE", code)
        _e(el, "SELECTOR-FIELD-BYTE-ORDER", "MOST-SIGNIFICANT-BYTE-FIRST" if sel.byte_order == "big_endian"
           else "MOST-SIGNIFICANT-BYTE-LAST")
        _e(el, "SELECTOR-FIELD-LENGTH", sel.length)
        _e(el, "SELECTOR-FIELD-START-POSITION", sel.start)
        if static:
            spath, _ = self.pdu(f"{msg.name}_static", msg.length, cycle, [(s, refs[s.name]) for s in static], msg)
            _e(_e(_e(el, "STATIC-PARTS"), "STATIC-PART"), "I-PDU-REF", spath, DEST="I-SIGNAL-I-PDU")
        _e(el, "UNUSED-BIT-PATTERN", 0)
        return self.path("Pdus", msg.name), "MULTIPLEXED-I-PDU"

    # ------------------------------------------------------------ the whole
    def write(self):
        msgs = list(self.db.messages)
        nodes = [n.name for n in self.db.nodes]
        pdus = {}
        for msg in msgs:
            refs = {sig.name: self.signal(msg, sig) for sig in msg.signals}
            pdus[msg.name] = self.message_pdu(msg, refs)
        self.write_transformers()
        # frames
        for msg in msgs:
            fr = _named(self.package("Frames"), "CAN-FRAME", msg.name)
            _desc(fr, msg.comment)
            _e(fr, "FRAME-LENGTH", msg.length)
            pm = _named(_e(fr, "PDU-TO-FRAME-MAPPINGS"), "PDU-TO-FRAME-MAPPING", msg.name)
            _e(pm, "PACKING-BYTE-ORDER", "MOST-SIGNIFICANT-BYTE-LAST")
            path, dest = pdus[msg.name]
            _e(pm, "PDU-REF", path, DEST=dest)
            _e(pm, "START-POSITION", 0)
        # who sends and who receives what
        sends = {n: [m for m in msgs if n in m.senders] for n in nodes}
        receives = {n: [m for m in msgs if n not in m.senders and any(n in s.receivers for s in m.signals)]
                    for n in nodes}
        cluster = _ident(self.bus.name.upper() + "_CAN")
        channel = self.path("Clusters", f"{cluster}/{cluster}/{cluster}_Channel")
        ports = {m.name: [] for m in msgs}
        pdu_ports = {m.name: [] for m in msgs}
        node_comments = {n.name: n.comment for n in self.db.nodes}
        for n in nodes:
            for direction, group in (("OUT", sends[n]), ("IN", receives[n])):
                g = _named(self.package("PduGroups"), "I-SIGNAL-I-PDU-GROUP", f"{n}_{direction.title()}")
                _e(g, "COMMUNICATION-DIRECTION", direction)
                _e(g, "COMMUNICATION-MODE", "CAN")
                lst = _e(g, "I-SIGNAL-I-PDUS")
                for m in group:
                    path, dest = pdus[m.name]
                    _e(_e(lst, "I-SIGNAL-I-PDU-REF-CONDITIONAL"), "I-SIGNAL-I-PDU-REF", path, DEST=dest)
            ecu = _named(self.package("Ecus"), "ECU-INSTANCE", n)
            _desc(ecu, node_comments.get(n))
            refs = _e(ecu, "ASSOCIATED-COM-I-PDU-GROUP-REFS")
            for direction in ("Out", "In"):
                _e(refs, "ASSOCIATED-COM-I-PDU-GROUP-REF", self.path("PduGroups", f"{n}_{direction}"),
                   DEST="I-SIGNAL-I-PDU-GROUP")
            ctrl = _named(_e(ecu, "COMM-CONTROLLERS"), "CAN-COMMUNICATION-CONTROLLER", f"{n}_Controller")
            _e(_e(ctrl, "CAN-COMMUNICATION-CONTROLLER-VARIANTS"), "CAN-COMMUNICATION-CONTROLLER-CONDITIONAL")
            conn = _named(_e(ecu, "CONNECTORS"), "CAN-COMMUNICATION-CONNECTOR", f"{n}_Connector")
            _e(conn, "COMM-CONTROLLER-REF", self.path("Ecus", f"{n}/{n}_Controller"),
               DEST="CAN-COMMUNICATION-CONTROLLER")
            inst = _e(conn, "ECU-COMM-PORT-INSTANCES")
            for direction, group in (("OUT", sends[n]), ("IN", receives[n])):
                for m in group:
                    fp = _named(inst, "FRAME-PORT", f"FP_{m.name}_{direction.title()}")
                    _e(fp, "COMMUNICATION-DIRECTION", direction)
                    ports[m.name].append(self.path("Ecus", f"{n}/{n}_Connector/FP_{m.name}_{direction.title()}"))
                    pp = _named(inst, "I-PDU-PORT", f"PP_{m.name}_{direction.title()}")
                    _e(pp, "COMMUNICATION-DIRECTION", direction)
                    pdu_ports[m.name].append(self.path("Ecus", f"{n}/{n}_Connector/PP_{m.name}_{direction.title()}"))
            _e(ecu, "SLEEP-MODE-SUPPORTED", "false")
            _e(ecu, "WAKE-UP-OVER-BUS-SUPPORTED", "false")
        # the cluster
        cl = _named(self.package("Clusters"), "CAN-CLUSTER", cluster)
        cond = _e(_e(cl, "CAN-CLUSTER-VARIANTS"), "CAN-CLUSTER-CONDITIONAL")
        _e(cond, "BAUDRATE", self.bus.bitrate)
        chan = _named(_e(cond, "PHYSICAL-CHANNELS"), "CAN-PHYSICAL-CHANNEL", f"{cluster}_Channel")
        conns = _e(chan, "COMM-CONNECTORS")
        for n in nodes:
            _e(_e(conns, "COMMUNICATION-CONNECTOR-REF-CONDITIONAL"), "COMMUNICATION-CONNECTOR-REF",
               self.path("Ecus", f"{n}/{n}_Connector"), DEST="CAN-COMMUNICATION-CONNECTOR")
        trigs = _e(chan, "FRAME-TRIGGERINGS")
        for msg in msgs:
            ft = _named(trigs, "CAN-FRAME-TRIGGERING", f"FT_{msg.name}")
            prefs = _e(ft, "FRAME-PORT-REFS")
            for p in ports[msg.name]:
                _e(prefs, "FRAME-PORT-REF", p, DEST="FRAME-PORT")
            _e(ft, "FRAME-REF", self.path("Frames", msg.name), DEST="CAN-FRAME")
            _e(_e(_e(ft, "PDU-TRIGGERINGS"), "PDU-TRIGGERING-REF-CONDITIONAL"), "PDU-TRIGGERING-REF",
               f"{channel}/PT_{msg.name}", DEST="PDU-TRIGGERING")
            _e(ft, "CAN-ADDRESSING-MODE", "EXTENDED" if msg.is_extended_frame else "STANDARD")
            behavior = "CAN-FD" if msg.is_fd else "CAN-20"
            _e(ft, "CAN-FRAME-RX-BEHAVIOR", behavior)
            _e(ft, "CAN-FRAME-TX-BEHAVIOR", behavior)
            _e(ft, "IDENTIFIER", msg.frame_id)
        ptrigs = _e(chan, "PDU-TRIGGERINGS")
        for msg in msgs:
            pt = _named(ptrigs, "PDU-TRIGGERING", f"PT_{msg.name}")
            prefs = _e(pt, "I-PDU-PORT-REFS")
            for p in pdu_ports[msg.name]:
                _e(prefs, "I-PDU-PORT-REF", p, DEST="I-PDU-PORT")
            path, dest = pdus[msg.name]
            _e(pt, "I-PDU-REF", path, DEST=dest)
        _e(cond, "PROTOCOL-NAME", "CAN")
        _e(cond, "PROTOCOL-VERSION", "FD" if self.bus.fd else "2.0")
        if self.bus.data_bitrate:
            _e(cond, "CAN-FD-BAUDRATE", self.bus.data_bitrate)
        # the system
        system = _named(self.package("System"), "SYSTEM", f"{_ident(self.bus.name)}_System")
        fibex = _e(system, "FIBEX-ELEMENTS")
        refs = [(self.path("Clusters", cluster), "CAN-CLUSTER")]
        refs += [(self.path("Ecus", n), "ECU-INSTANCE") for n in nodes]
        refs += [(self.path("Frames", m.name), "CAN-FRAME") for m in msgs]
        refs += [(pdus[m.name][0], pdus[m.name][1]) for m in msgs]
        for path, dest in refs:
            _e(_e(fibex, "FIBEX-ELEMENT-REF-CONDITIONAL"), "FIBEX-ELEMENT-REF", path, DEST=dest)
        ET.indent(self.root, space="  ")
        return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(self.root, encoding="unicode") + "\n"


def arxml_text(mapping, bus, package=None):
    """The ARXML (AUTOSAR 4) of bus ``bus`` of a loaded mapping (see the
    module's text); ``package`` the top package's name (default the bus's
    matrix file's name)."""
    b = mapping.bus(bus)
    if package is None:
        package = _ident(os.path.splitext(os.path.basename(b.dbc))[0])
    return _Writer(mapping, bus, package).write()


def example_mapping_text(mapping_text, arxml_name, protected):
    """``vehicle.toml``'s text with the pt bus on ``arxml_name`` and without
    the ``protection`` of the messages in ``protected`` (the ARXML carries it)."""
    out = ["# The example vehicle matrix with its pt bus as an AUTOSAR system description",
           f"# (can_dbc/matrices/{arxml_name}): written by `python -m can_dbc.to_arxml` from",
           "# vehicle.toml. The ARXML carries the E2E protection of",
           f"# {', '.join(sorted(protected))};",
           "# this file the XOR and counter protections, which AUTOSAR has no profile for. Its frames",
           "# are vehicle.toml's, bit for bit (tests/test_arxml.py).",
           "#"]
    current = None
    for line in mapping_text.splitlines():
        m = re.match(r"^\[message\.([A-Za-z0-9_:]+)\]\s*$", line)
        if m:
            current = m.group(1)
        elif line.startswith("["):
            current = None
        if line.strip() == 'dbc = "../matrices/vehicle_pt.dbc"':
            line = f'dbc = "../matrices/{arxml_name}"'
        if current in protected and line.startswith("protection = "):
            line = f"# protection: the E2E transformer of {arxml_name}"
        out.append(line)
    return "\n".join(out) + "\n"


def _example():
    from .mapping import load

    m = load(EXAMPLE_MAPPING)
    arxml = arxml_text(m, "pt", package="VehiclePt")
    protected = {x.name for x in m.codec_order("pt") if x.protection.kind in E2E_KINDS}
    with open(EXAMPLE_MAPPING, encoding="utf-8") as f:
        text = example_mapping_text(f.read(), os.path.basename(EXAMPLE_ARXML), protected)
    return {EXAMPLE_ARXML: arxml, EXAMPLE_ARXML_MAPPING: text}


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m can_dbc.to_arxml", description=__doc__.split("\n\n")[0])
    parser.add_argument("--mapping", help="a mapping file (or a shipped mapping's name); default: write the "
                                          "shipped example (vehicle_pt.arxml, vehicle_arxml.toml)")
    parser.add_argument("--bus", help="the mapping's bus to write (default: its first)")
    parser.add_argument("--out", help="the ARXML to write (with --mapping; default: standard output)")
    parser.add_argument("--check", action="store_true",
                        help="write nothing; exit 1 when the shipped example differs from what would be written")
    args = parser.parse_args(argv)
    from .mapping import MappingError, find_mapping, load

    try:
        if args.mapping:
            m = load(find_mapping(args.mapping))
            text = arxml_text(m, args.bus or m.buses[0].name)
            if args.out:
                with open(args.out, "w", encoding="utf-8") as f:
                    f.write(text)
            else:
                sys.stdout.write(text)
            return 0
        files = _example()
    except (MappingError, ValueError, KeyError, OSError) as e:
        print(f"python -m can_dbc.to_arxml: {e}", file=sys.stderr)
        return 2
    stale = []
    for path, text in files.items():
        try:
            with open(path, encoding="utf-8") as f:
                same = f.read() == text
        except OSError:
            same = False
        if args.check:
            if not same:
                stale.append(path)
        elif not same:
            with open(path, "w", encoding="utf-8") as f:
                f.write(text)
            print(f"wrote {os.path.relpath(path)}")
    if stale:
        print(f"python -m can_dbc.to_arxml: differs from what it writes: {', '.join(stale)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
