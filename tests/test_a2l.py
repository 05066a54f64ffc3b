"""Tests of rt_loop/measure/xcp/a2l.py: the A2L of the loop's memory and its writable regions.

The A2L is read back with an independent parser (pya2l, from PyPI), and on
its parse tree a strict structural check of our own (every reference
resolves, names unique, sizes and addresses inside the loop). Addresses are
checked against ``ffi.offsetof`` of the field each name stands for, derived
from the name here, independently of the generator. Everything runs twice:
with the compiled module's ffi and with an ABI-mode ffi of the headers as
they are now (the compiled module may lag behind rt_loop.h for a while).
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import re
import tomllib
from pathlib import Path

import pytest
import requires

from can_dbc import mapping as can_mapping
from rt_loop.channels import LoopChannels
from rt_loop.measure.xcp import a2l

ROOT = Path(__file__).resolve().parents[1]
HEADERS = (ROOT / "plant" / "csrc" / "dct_plant.h", ROOT / "can_dbc" / "csrc" / "can_table.h",
           ROOT / "rt_loop" / "csrc" / "rt_loop.h", ROOT / "rt_loop" / "csrc" / "rt_floor.h")
RANGES = ROOT / "plant" / "data" / "ranges.toml"

#: the parameters marked online in ranges.toml (reviewed: see the report of the
#: change that added them, and the comments in ranges.toml)
ONLINE = {
    "engine.full_load.torque_nm", "engine.drag.torque_nm", "engine.na_torque_fraction",
    "engine.tau_rise_s", "engine.tau_boost_s", "engine.tau_fall_s", "engine.idle_speed_rpm",
    "engine.idle_kp_nm_per_rpm", "engine.idle_ki_nm_per_rpm_s", "engine.idle_torque_max_nm",
    "engine.rev_limit_rpm",
    "clutch[].mu_static", "clutch[].mu_kinetic", "clutch[].stribeck_speed_rad_s",
    "clutch[].return_spring_n", "clutch[].drag_nms_per_rad",
    "hydraulics.oil.density_kg_m3", "hydraulics.oil.viscosity_m2_s", "hydraulics.supply.tau_s",
    "hydraulics.supply.line.pressure_bar", "hydraulics.valve.solenoid_gain_n_per_a",
    "hydraulics.valve.spring_preload_n", "hydraulics.valve.leakage_m3_per_s_per_pa",
    "gearbox.mesh_efficiency", "gearbox.input_drag_nm", "gearbox.input_drag_nms_per_rad",
    "gearbox.output_drag_nm", "gearbox.output_drag_nms_per_rad",
    "gearbox.idle_gear_drag_nms_per_rad", "gearbox.sync[].cone_mu",
    "gearbox.sync[].dog_friction_mu",
    "front_wheel.brake_torque_max_nm", "rear_wheels.brake_torque_max_nm",
    "tyre.pdx1", "tyre.rolling_resistance",
    "vehicle.mass_kg", "vehicle.drag_coefficient", "vehicle.frontal_area_m2",
    "vehicle.air_density_kg_m3",
    "thermal.ambient_temp_degc", "thermal.wall_heat_fraction", "thermal.radiator_ua_w_per_k",
    "thermal.trans_cooler_ua_w_per_k", "thermal.idle_cold_rise_rpm", "thermal.cold_enrichment",
    "thermal.alternator_load_w", "thermal.power_steering_nm", "thermal.ac_on",
    "thermal.ac_torque_nm",
}

SIZES = {"UBYTE": 1, "SBYTE": 1, "UWORD": 2, "SWORD": 2, "ULONG": 4, "SLONG": 4,
         "A_UINT64": 8, "A_INT64": 8, "FLOAT32_IEEE": 4, "FLOAT64_IEEE": 8}
C_TYPES = {"double": "FLOAT64_IEEE", "float": "FLOAT32_IEEE", "int": "SLONG",
           "int32_t": "SLONG", "uint32_t": "ULONG", "int64_t": "A_INT64", "uint64_t": "A_UINT64",
           "uint16_t": "UWORD", "int16_t": "SWORD", "uint8_t": "UBYTE", "int8_t": "SBYTE",
           "unsigned int": "ULONG"}


# ---------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------

def _header_ffi():
    """An ABI-mode FFI of the loop's headers as they are now, and its constants."""
    from cffi import FFI

    spec = importlib.util.spec_from_file_location("_plant_build", ROOT / "plant" / "_build.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    ffi = FFI()
    ffi.cdef("\n".join(build.cdef_text(str(h)) for h in HEADERS))
    return ffi, ffi.dlopen(None)


@pytest.fixture(scope="module", params=["compiled", "header"])
def c(request):
    """(ffi, lib): the compiled module's, or the headers' (ABI mode)."""
    if request.param == "compiled":
        from rt_loop._rt_loop import ffi, lib
        return ffi, lib
    return _header_ffi()


@pytest.fixture(scope="module")
def header():
    return _header_ffi()


def _channels(name, ffi, lib):
    return LoopChannels(can_mapping.load(can_mapping.find_mapping(name)), ffi, lib)


def _parse(parser, text):
    """The pya2l tree of ``text``. The IF_DATA blocks are checked apart (pya2l
    0.4 parses IF_DATA generically, with the file's A2ML or without, and warns
    about every /begin inside one as if it were repeated; tests/test_a2l_tools.py
    checks that its tree holds them all); everything else must parse with the
    version check on and without a single warning."""
    from pya2l.parser import A2lError

    lines = text.split("\n")
    blocks, begin = [], None
    for i, line in enumerate(lines):
        if line.strip() == "/begin IF_DATA XCP":
            assert begin is None, "IF_DATA inside IF_DATA"
            begin = i
        elif line.strip() == "/end IF_DATA":
            blocks.append((begin, i))
            begin = None
    assert begin is None and len(blocks) >= 1
    inside = {k for b, e in blocks for k in range(b, e + 1)}
    bare = "\n".join(line for k, line in enumerate(lines) if k not in inside)
    try:
        parser.tree_from_a2l(bare.encode(), enforce_version_check=True)
    except A2lError as e:
        pytest.fail(f"pya2l: {str(e)[:2000]}")
    assert parser.warnings == []
    tree = parser.tree_from_a2l(text.encode(), enforce_version_check=False)
    for warning in parser.warnings:
        m = re.match(r"(\d+):\d+ (\w+) may be used at most once here", warning)
        assert m, warning
        line = int(m.group(1)) - 1
        block = next(((b, e) for b, e in blocks if b < line < e), None)
        assert block, warning
        assert any(re.search(rf"/begin {m.group(2)}\b", lines[k]) for k in range(*block)), warning
    return tree


@pytest.fixture(scope="module")
def texts(c):
    ffi, lib = c
    return {name: a2l.generate(ffi, lib, channels=None if name is None else _channels(name, ffi, lib))
            for name in (None, "dct_hil", "vehicle")}


def _objects(tree):
    """name -> (kind, address, data type, size in bytes, node) from the parse tree."""
    module = tree.PROJECT.MODULE[0]
    layouts = {r.Name.Value: r for r in module.RECORD_LAYOUT}
    out = {}
    for m in module.MEASUREMENT:
        dt = m.DataType.Value
        assert m.MATRIX_DIM.is_none, m.Name.Value     # one value each
        assert m.Name.Value not in out, f"{m.Name.Value} twice"
        out[m.Name.Value] = ("MEASUREMENT", m.ECU_ADDRESS.Address.Value, dt, SIZES[dt], m)
    for ch in module.CHARACTERISTIC:
        rl = layouts[ch.Deposit.Value]
        dt = rl.FNC_VALUES.DataType.Value
        n = 1
        if ch.Type == "VAL_BLK":
            md = ch.MATRIX_DIM
            n = md.XDim.Value * max(1, md.YDim.Value) * max(1, md.ZDim.Value)
        assert ch.Name.Value not in out, f"{ch.Name.Value} twice"
        out[ch.Name.Value] = ("CHARACTERISTIC", ch.Address.Value, dt, SIZES[dt] * n, ch)
    return out


# ---------------------------------------------------------------------------
# the name -> the field, independently of the generator
# ---------------------------------------------------------------------------

PREFIX = {"inputs": ("plant", "inputs"), "override": ("plant", "inputs"),
          "applied": ("plant", "applied"), "outputs": ("plant", "outputs"),
          "state": ("plant", "state"), "derived": ("plant", "derived"),
          "params": ("plant", "params"), "plant": ("plant",), "stats": ("stats",), "loop": ()}


def _parts(text):
    out = []
    for part in text.split("."):
        m = re.fullmatch(r"([A-Za-z_]\w*)((?:\[\d+\])*)", part)
        assert m, part
        out.append(m.group(1))
        out += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    return out


def _path_of(name, channels):
    """The offsetof path of the field an A2L name stands for (None: a CAN signal)."""
    head, _, rest = name.partition(".")
    if head == "commands":
        cname = re.sub(r"\[\d+\]$", "", rest)
        k = int(rest[rest.index("[") + 1:-1]) if rest.endswith("]") else \
            channels.command_names.index(cname)
        assert channels.command_names[k] == cname
        return ("stats", "commands", k)
    if head == "stats" and channels is not None and rest.startswith("chan."):
        _, bus, fname = rest.split(".")
        return ("stats", "chan", channels.buses.index(bus), fname)
    if head == "stats" and rest.startswith("msgs."):
        _, bus, msg, fname = rest.split(".")
        k = next(i for i, (b, m) in enumerate(channels.messages) if b == bus and m.name == msg)
        return ("stats", "msgs", k, fname)
    if head not in PREFIX:
        return None
    return PREFIX[head] + tuple(_parts(rest))


def _signal_index(channels):
    """<bus>.<Message>.<Signal> -> its index in signal_values: the channels in
    order, each channel's signals in its table's order (as rt_loop_prepare)."""
    out, base = {}, 0
    for i, bus in enumerate(channels.buses):
        table = channels.table(i)
        for m in range(len(table)):
            for k, s in enumerate(table.signal_names(m)):
                out[f"{bus}.{table.messages[m].name}.{s}"] = base + k
            base += len(table.signal_names(m))
    return out


def _field_type(ffi, path):
    t = ffi.typeof("rt_loop")
    for item in path:
        t = t.item if isinstance(item, int) else dict(t.fields)[item].type
    return t


# ---------------------------------------------------------------------------
# parsing and structure
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("mapping", [None, "dct_hil", "vehicle"])
def test_parses_in_pya2l_and_every_reference_resolves(c, texts, parser, mapping):
    ffi, _lib = c
    text = texts[mapping]
    tree = _parse(parser, text)
    module = tree.PROJECT.MODULE[0]
    assert tree.ASAP2_VERSION.VersionNo.Value == 1 and tree.ASAP2_VERSION.UpgradeNo.Value == 71
    compu = {m.Name.Value: m for m in module.COMPU_METHOD}
    vtabs = {v.Name.Value for v in module.COMPU_VTAB}
    layouts = {r.Name.Value for r in module.RECORD_LAYOUT}
    assert len(compu) == len(module.COMPU_METHOD) and len(layouts) == len(module.RECORD_LAYOUT)
    for m in compu.values():
        if m.ConversionType == "TAB_VERB":
            assert m.COMPU_TAB_REF.ConversionTable.Value in vtabs
        else:
            assert m.ConversionType == "IDENTICAL"
    objs = _objects(tree)
    size = ffi.sizeof("rt_loop")
    for name, (kind, address, dt, nbytes, node) in objs.items():
        assert re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\[\]]*", name), name
        assert node.Conversion.Value in compu, name
        if kind == "CHARACTERISTIC":
            assert node.Deposit.Value in layouts, name
        assert 0 <= address and address + nbytes <= size, name
        assert address % min(SIZES[dt], 8) == 0, f"{name}: misaligned"
        lo, hi = float(node.LowerLimit.Source), float(node.UpperLimit.Source)
        assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi, name
    # groups name only objects that exist, and every object is in one
    grouped = []
    for g in module.GROUP:
        grouped += [i.Value for i in g.REF_MEASUREMENT.Identifier]
        grouped += [i.Value for i in g.REF_CHARACTERISTIC.Identifier]
    assert sorted(grouped) == sorted(objs)
    # /begin and /end balanced, properly nested
    stack = []
    for kw, word in re.findall(r"/(begin|end)\s+(\w+)", text):
        if kw == "begin":
            stack.append(word)
        else:
            assert stack and stack.pop() == word, word
    assert stack == []


def test_every_address_is_the_offset_of_its_field(c, texts, parser):
    ffi, lib = c
    channels = _channels("vehicle", ffi, lib)
    signals = _signal_index(channels)
    objs = _objects(_parse(parser, texts["vehicle"]))
    has_signals = "signal_values" in dict(ffi.typeof("rt_loop").fields)
    assert (set(signals) <= set(objs)) == has_signals
    for name, (_kind, address, dt, nbytes, _node) in objs.items():
        path = _path_of(name, channels)
        if path is None:
            assert name in signals, name
            path = ("signal_values", signals[name])
        assert address == ffi.offsetof("rt_loop", *path), name
        t = _field_type(ffi, path)
        n = 1
        while t.kind == "array":
            n *= t.length
            t = t.item
        assert t.kind == "primitive", name
        assert C_TYPES[t.cname] == dt, name
        assert nbytes == n * ffi.sizeof(t), name


def test_without_channels_commands_and_channels_go_by_index(c, texts, parser):
    ffi, lib = c
    objs = _objects(_parse(parser, texts[None]))
    n_cmd = lib.RT_MAX_COMMANDS
    for k in range(n_cmd):
        assert objs[f"stats.commands[{k}]"][1] == ffi.offsetof("rt_loop", "stats", "commands", k)
    assert objs["stats.chan[3].tx_frames"][1] == ffi.offsetof("rt_loop", "stats", "chan", 3,
                                                               "tx_frames")
    assert not [n for n in objs if n.startswith(("stats.msgs", "commands.", "pt.", "io."))]
    for name in objs:
        assert _path_of(name, None) is not None, name


def test_the_mapping_names_commands_channels_messages(c, texts, parser):
    ffi, lib = c
    channels = _channels("vehicle", ffi, lib)
    objs = _objects(_parse(parser, texts["vehicle"]))
    for k, name in enumerate(channels.command_names):
        assert objs[f"commands.{name}"][1] == ffi.offsetof("rt_loop", "stats", "commands", k)
    for i, bus in enumerate(channels.buses):
        assert objs[f"stats.chan.{bus}.rx_accepted"][1] == \
            ffi.offsetof("rt_loop", "stats", "chan", i, "rx_accepted")
    for k, (bus, msg) in enumerate(channels.messages):
        assert objs[f"stats.msgs.{bus}.{msg.name}.frames"][1] == \
            ffi.offsetof("rt_loop", "stats", "msgs", k, "frames")
        timeouts = f"stats.msgs.{bus}.{msg.name}.timeouts"
        assert (timeouts in objs) == (msg.direction == "receive")


def test_signal_values_named_bus_message_signal(header, parser):
    ffi, lib = header
    channels = _channels("vehicle", ffi, lib)
    text = a2l.generate(ffi, lib, channels=channels)
    objs = _objects(_parse(parser, text))
    signals = _signal_index(channels)
    assert len(signals) > 50 and len(channels.buses) == 2
    base = ffi.offsetof("rt_loop", "signal_values")
    for name, index in signals.items():
        kind, address, dt, _n, node = objs[name]
        assert (kind, dt, address) == ("MEASUREMENT", "FLOAT64_IEEE", base + 8 * index)
    # a signal of the second bus: its index counts every signal of the first
    bus = channels.buses[1]
    first = sum(len(channels.table(0).signal_names(m)) for m in range(len(channels.table(0))))
    table = channels.table(1)
    name = f"{bus}.{table.messages[0].name}.{table.signal_names(0)[0]}"
    assert objs[name][1] == base + 8 * first
    # the DBC's unit and range
    sig = table.messages[0].get_signal_by_name(table.signal_names(0)[0])
    node = objs[name][4]
    if sig.minimum is not None:
        assert float(node.LowerLimit.Source) == pytest.approx(sig.minimum)
    cms = {m.Name.Value: m for m in _parse(parser, text).PROJECT.MODULE[0].COMPU_METHOD}
    if sig.unit and not sig.choices:
        assert cms[node.Conversion.Value].Unit.Value == sig.unit


def _prepared_loop(ffi, lib, channels, regions=()):
    """A prepared rt_loop on the ring transport (no sockets), with ``regions``."""
    from plant.params import fill_params, load_params

    loop = ffi.new("rt_loop *")
    fill_params(ffi, loop.plant.params,
                load_params(None, ffi, {"hydraulics": {"pressure_commanded": 0}}))
    loop.cfg.period_s, loop.cfg.priority, loop.cfg.cpu = 0.0005, 0, -1
    channels.install(loop)
    for i in range(len(channels.buses)):
        loop.chan[i].transport, loop.chan[i].fd = lib.RT_TRANSPORT_RING, -1
    loop.n_regions = len(regions)
    for k, (offset, size, kind, *_rest) in enumerate(regions):
        loop.regions[k].offset, loop.regions[k].size, loop.regions[k].kind = offset, size, kind
    assert lib.rt_loop_prepare(loop) == 0
    return loop


def _compiled_with(*names):
    from rt_loop._rt_loop import ffi, lib

    fields = dict(ffi.typeof("rt_loop").fields)
    missing = [n for n in names if n not in fields and not hasattr(lib, n)]
    if missing:
        requires.missing(f"{', '.join(missing)} in the compiled extension", requires.REBUILD)
    return ffi, lib


def test_signal_numbering_is_the_loops():
    """rt_loop_prepare numbers the signal values channel by channel: the same as the A2L."""
    ffi, lib = _compiled_with("signal_values")
    channels = _channels("vehicle", ffi, lib)
    loop = _prepared_loop(ffi, lib, channels)
    signals = _signal_index(channels)
    assert loop.n_signal_values == len(signals)
    for i, bus in enumerate(channels.buses):
        table = channels.table(i)
        name = f"{bus}.{table.messages[0].name}.{table.signal_names(0)[0]}"
        assert loop.chan[i].first_signal_value == signals[name]


# ---------------------------------------------------------------------------
# calibration: the writable CHARACTERISTICs are the regions
# ---------------------------------------------------------------------------

def test_regions_cover_exactly_the_writable_characteristics(c, texts, parser):
    ffi, lib = c
    regions = a2l.calibration_regions(ffi, lib)
    objs = _objects(_parse(parser, texts["vehicle"]))
    writable = {n: o for n, o in objs.items()
                if o[0] == "CHARACTERISTIC" and not o[4].READ_ONLY.Present}
    assert {r[3] for r in regions} == set(writable)
    data = getattr(lib, "RT_REGION_DATA", 0)
    param = getattr(lib, "RT_REGION_PARAM", 1)
    for offset, size, kind, name, lo, hi, c_type in regions:
        _k, address, dt, nbytes, node = writable[name]
        assert (offset, size) == (address, nbytes), name
        assert (lo, hi) == (float(node.LowerLimit.Source), float(node.UpperLimit.Source)), name
        assert C_TYPES[c_type] == dt and size % ffi.sizeof(c_type) == 0, name
        assert kind == (data if name.startswith("override.") else param), name
        assert name.startswith(("override.", "params.")), name
    spans = sorted((r[0], r[0] + r[1]) for r in regions)
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:])), "regions overlap"
    assert len(regions) <= getattr(lib, "RT_MAX_REGIONS", 256)
    # the same regions whatever the mapping
    assert regions == a2l.calibration_regions(ffi, lib)


def test_the_loop_takes_every_region_and_only_those():
    """Every writable CHARACTERISTIC written through the loop's calibration
    ring (its value as it is: in range, accepted by the plant) is applied;
    a READ_ONLY parameter is refused."""
    import struct
    import threading
    import time

    ffi, lib = _compiled_with("regions", "cal", "rt_write_push_many", "rt_loop_run")
    regions = a2l.calibration_regions(ffi, lib)
    channels = _channels("dct_hil", ffi, lib)
    assert not set(channels.command_inputs) & set(a2l.OVERRIDABLE_INPUTS)   # nobody else drives them
    loop = _prepared_loop(ffi, lib, channels, regions)
    base = ffi.cast("char *", loop)
    writes = ffi.new("rt_write[]", len(regions) + 1)
    for k, (offset, size, _kind, _name, lo, hi, c_type) in enumerate(regions):
        n = min(size, int(lib.RT_WRITE_BYTES))
        w = writes[k]
        w.offset, w.len, w.id = offset, n, k + 1
        ffi.memmove(w.data, base + offset, n)
        # the whole block in range (the unused tail too): a master may write it back
        values = struct.unpack(f"<{size // 8}d", ffi.buffer(base + offset, size)[:])
        assert c_type == "double" and all(lo <= v <= hi for v in values), _name
    step = ffi.offsetof("rt_loop", "plant", "params", "solver", "step_s")
    last = writes[len(regions)]
    last.offset, last.len, last.id = step, 8, 999
    ffi.memmove(last.data, struct.pack("<d", 0.001), 8)
    thread = threading.Thread(target=lib.rt_loop_run, args=(loop,), daemon=True)
    thread.start()
    try:
        assert lib.rt_write_push_many(ffi.addressof(loop, "cal"), writes, len(regions) + 1) == \
            len(regions) + 1
        deadline = time.monotonic() + 30
        while int(loop.cal.applied) + int(loop.cal.refused) < len(regions) + 1:
            assert time.monotonic() < deadline, "the writes were not taken"
            time.sleep(0.01)
    finally:
        lib.rt_loop_request_stop(loop)
        thread.join(30)
    assert int(loop.cal.applied) == len(regions)
    assert (int(loop.cal.refused), int(loop.cal.last_refused_id)) == (1, 999)
    assert loop.plant.params.solver.step_s == 0.0005


def test_memory_segment_spans_the_regions(c, texts, parser):
    """The calibration segment is the slave's segment 0: first region to the last one's end."""
    ffi, lib = c
    regions = a2l.calibration_regions(ffi, lib)
    start = min(r[0] for r in regions)
    end = max(r[0] + r[1] for r in regions)
    module = _parse(parser, texts["dct_hil"]).PROJECT.MODULE[0]
    (segment,) = module.MOD_PAR.MEMORY_SEGMENT
    assert (segment.Address.Value, segment.Size.Value) == (start, end - start)
    assert (segment.PrgType, segment.MemoryType, segment.Attribute) == ("DATA", "RAM", "INTERN")
    assert "/begin SEGMENT 0 2 0 0 0" in texts["dct_hil"]


def test_overridable_inputs_and_tcu_inputs(c):
    ffi, lib = c
    names = {r[3]: r for r in a2l.calibration_regions(ffi, lib)}
    overrides = {n for n in names if n.startswith("override.")}
    assert overrides == {"override.accel_pedal_pct", "override.brake_pedal_pct",
                         "override.road_grade_pct", "override.engine_on"}
    for n in overrides:
        field = n.split(".", 1)[1]
        assert names[n][0] == ffi.offsetof("rt_loop", "plant", "inputs", field)
    assert names["override.road_grade_pct"][4:6] == (-40.0, 40.0)
    assert names["override.engine_on"][4:6] == (0.0, 1.0)
    # TCU-driven inputs stay measurement-only, every input is measured
    objs = {o.name: o for o in a2l.objects(ffi, lib)}
    for field, _f in ffi.typeof("dct_inputs").fields:
        assert objs[f"inputs.{field}"].kind == "MEASUREMENT"
        assert not objs[f"inputs.{field}"].writable


def test_online_parameters_are_the_marked_ones(c):
    ffi, lib = c
    assert a2l.online_keys() == ONLINE
    ranges = tomllib.loads(RANGES.read_text())
    assert ONLINE <= set(ranges)
    for key in ONLINE:       # no counts, no axes, no solver
        assert len(ranges[key]) == 2, key
        assert not key.startswith("solver."), key
        assert not re.search(r"\.(n|n_\w+)$", key), key
    for axis in ("engine.full_load.speed_rpm", "engine.drag.speed_rpm", "engine.bsfc.speed_rpm",
                 "engine.bsfc.torque_nm", "hydraulics.supply.line.current_a"):
        assert axis not in ONLINE
    regions = {r[3] for r in a2l.calibration_regions(ffi, lib)}
    params = [o for o in a2l.objects(ffi, lib) if o.name.startswith("params.")]
    assert params and all(o.kind == "CHARACTERISTIC" for o in params)
    for o in params:
        key = re.sub(r"\[\d+\]", "[]", o.name[len("params."):])
        assert (o.name in regions) == (key in ONLINE), o.name
        assert (o.lower, o.upper) == tuple(float(x) for x in ranges[key][:2]), o.name
    assert {"params.vehicle.mass_kg", "params.vehicle.drag_coefficient",
            "params.vehicle.frontal_area_m2", "params.tyre.rolling_resistance",
            "params.clutch[0].mu_static", "params.clutch[1].mu_kinetic"} <= regions


def test_every_parameter_field_is_described(c):
    """Every scalar of dct_params is a CHARACTERISTIC, a double array one VAL_BLK."""
    ffi, lib = c
    objs = {o.name: o for o in a2l.objects(ffi, lib)}
    assert objs["params.engine.full_load.torque_nm"].dims == (24,)
    assert objs["params.engine.bsfc.bsfc_g_per_kwh"].dims == (12, 12)
    assert objs["params.engine.bsfc.bsfc_g_per_kwh"].size == 12 * 12 * 8
    assert objs["params.solver.step_s"].writable is False
    assert objs["params.engine.full_load.n"].datatype == "SLONG"
    covered = set()
    for o in objs.values():
        if o.name.startswith("params."):
            covered.update(range(o.address, o.address + o.size))
    start = ffi.offsetof("rt_loop", "plant", "params")
    doubles_and_ints = 0
    for path, _n, _ptype, _d, _p, _f in a2l._leaves(ffi, ffi.typeof("dct_params"), (), ""):
        at = ffi.offsetof("rt_loop", "plant", "params", *path)
        assert at in covered, path
        doubles_and_ints += 1
    assert doubles_and_ints > 300 and start in covered


# ---------------------------------------------------------------------------
# units, comments, IF_DATA, EPK
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name, unit", [
    ("engine_speed_rpm", "rpm"), ("vehicle_speed_kmh", "km/h"), ("accel_pedal_pct", "%"),
    ("clutch1_pressure_bar", "bar"), ("time_s", "s"), ("turnaround_max_us", "us"),
    ("speed_rad_s", "rad/s"), ("accel_m_s2", "m/s2"), ("stiffness_nm_per_rad", "Nm/rad"),
    ("damping_nms_per_rad", "N m s/rad"), ("inertia_kgm2", "kg m2"),
    ("idle_ki_nm_per_rpm_s", "Nm/(rpm s)"), ("leakage_m3_per_s_per_pa", "m3/s/Pa"),
    ("density_kg_m3", "kg/m3"), ("fuel_density_kg_per_l", "kg/l"), ("bsfc_g_per_kwh", "g/kWh"),
    ("mu_static", ""), ("pcx1", ""), ("n", ""), ("ticks", ""), ("sync1_state", ""),
    ("wheel_speed_fl_rpm", "rpm"), ("fuel_rate_lph", "l/h"), ("return_spring_n", "N"),
])
def test_unit_of(name, unit):
    assert a2l.unit_of(name) == unit


def test_units_agree_with_the_mapping_and_are_present(c, texts, parser):
    ffi, lib = c
    tree = _parse(parser, texts["dct_hil"])
    module = tree.PROJECT.MODULE[0]
    units = {m.Name.Value: m.Unit.Value for m in module.COMPU_METHOD}
    objs = _objects(tree)
    with_unit = 0
    for name, (_k, _a, _dt, _n, node) in objs.items():
        last = re.sub(r"\[\d+\]", "", name.rsplit(".", 1)[-1])
        expected = can_mapping.unit_of_name(last)
        if expected and name.split(".")[0] in ("inputs", "applied", "outputs", "override"):
            assert units[node.Conversion.Value] == expected, name
        with_unit += bool(units[node.Conversion.Value])
    assert with_unit > 300
    assert units[objs["outputs.engine_speed_rpm"][4].Conversion.Value] == "rpm"
    assert units[objs["params.clutch[0].friction.stiffness_nm_per_rad"][4].Conversion.Value] \
        == "Nm/rad"
    assert units[objs["state.engine.speed_rad_s"][4].Conversion.Value] == "rad/s"
    assert units[objs["stats.turnaround_max_us"][4].Conversion.Value] == "us"


def test_comments_from_the_headers_and_the_parameter_file(c):
    ffi, lib = c
    objs = {o.name: o for o in a2l.objects(ffi, lib)}
    assert "friction coefficient at zero slip" in objs["params.clutch[0].mu_static"].comment
    assert "parameters.md" in objs["params.clutch[0].mu_static"].comment
    assert "changeable while running" in objs["params.vehicle.mass_kg"].comment
    assert "read only" in objs["params.solver.step_s"].comment
    assert "as applied" in objs["outputs.solenoid_current1_a"].comment
    assert "wake-up latency" in objs["stats.latency_us"].comment
    assert all('"' not in o.comment and len(o.comment) <= 255 for o in objs.values())
    custom = {o.name: o for o in a2l.objects(ffi, lib, params_doc={"vehicle.mass_kg": "my car"})}
    assert "my car" in custom["params.vehicle.mass_kg"].comment


def test_verbal_conversions(c, texts, parser):
    ffi, lib = c
    module = _parse(parser, texts[None]).PROJECT.MODULE[0]
    vtabs = {v.Name.Value: v for v in module.COMPU_VTAB}
    compu = {m.Name.Value: m for m in module.COMPU_METHOD}
    objs = _objects(_parse(parser, texts[None]))
    ref = compu[objs["stats.state"][4].Conversion.Value].COMPU_TAB_REF.ConversionTable.Value
    text = str(vtabs[ref])
    assert "RUNNING" in text and "OVERRUN_STOP" in text
    ref = compu[objs["outputs.sync1_state"][4].Conversion.Value].COMPU_TAB_REF.ConversionTable.Value
    assert "SYNCHRONIZING" in str(vtabs[ref])


def _if_data(text):
    """The module's IF_DATA XCP (after MOD_PAR and its memory segment's)."""
    start = text.index("/begin IF_DATA XCP", text.index("/end MOD_PAR"))
    return text[start:text.index("/end IF_DATA", start)]


def test_if_data_xcp(c):
    ffi, lib = c
    text = a2l.generate(ffi, lib, xcp={"address": "192.168.1.20", "port": 5566})
    block = _if_data(text)
    assert f"DYNAMIC {lib.RT_DAQ_MAX_LISTS} 3 0 " in block
    assert "BYTE_ORDER MSB_LAST" in text and "BYTE_ORDER_MSB_LAST" in block
    assert "PRESCALER_SUPPORTED" in block
    assert "/begin XCP_ON_UDP_IP 0x0104 5566 ADDRESS \"192.168.1.20\" /end XCP_ON_UDP_IP" in block
    assert "XCP_ON_TCP_IP" not in block
    events = re.findall(r'/begin EVENT "(\w+)" "\w+" (\d+) DAQ(?:_STIM)? 0xFF (\d+) (\d+) 0', block)
    # 2 kHz: 5 x 100 us, 1 x 10 ms, 1 x 100 ms
    assert events == [("tick", str(lib.RT_EVENT_TICK), "5", "5"),
                      ("10ms", str(lib.RT_EVENT_10MS), "1", "7"),
                      ("100ms", str(lib.RT_EVENT_100MS), "1", "8")]
    slow = _if_data(a2l.generate(ffi, lib, xcp={"rate_hz": 1000, "transport": "both",
                                                  "time_scale": 0.5, "address": "::1"}))
    events = re.findall(r'/begin EVENT "(\w+)" "\w+" \d+ DAQ(?:_STIM)? 0xFF (\d+) (\d+) 0', slow)
    # 1 kHz at half speed: a tick every 2 ms of wall time, 10 ms of plant time in 20 ms
    assert events == [("tick", "2", "6"), ("10ms", "2", "7"), ("100ms", "2", "8")]
    assert 'XCP_ON_UDP_IP 0x0104 5555 IPV6 "::1"' in slow and "XCP_ON_TCP_IP" in slow
    assert 'HOST_NAME "hil-rack"' in a2l.generate(ffi, lib, xcp={"address": "hil-rack"})


def test_if_data_matches_the_slave():
    """The defaults are what rt_loop/measure/xcp/protocol.py declares."""
    protocol = requires.module("rt_loop.measure.xcp.protocol")
    from rt_loop._rt_loop import ffi, lib

    block = _if_data(a2l.generate(ffi, lib))
    max_cto = getattr(protocol, "MAX_CTO", 252)
    max_dto = getattr(protocol, "DTO_HEADER_BYTES", 4) + lib.RT_DAQ_ODT_BYTES
    assert f" {max_cto} {max_dto} BYTE_ORDER_MSB_LAST" in block
    cycle_of = getattr(protocol, "_cycle", a2l._time_code)
    for event in getattr(protocol, "DEFAULT_EVENTS", ()):
        cycle, unit = cycle_of(event.cycle_s)
        assert f'"{event.name}" "{event.name[:8]}"' in block
        assert re.search(rf'"{event.name}" "\w+" \d+ DAQ(?:_STIM)? 0xFF {cycle} {unit} ', block)


@pytest.mark.parametrize("xcp, message", [
    ({"transport": "can"}, "transport"), ({"port": 0}, "port"), ({"port": "5555"}, "port"),
    ({"address": "a b"}, "address"), ({"rate_hz": -1}, "rate_hz"), ({"time_scale": 2}, "time_scale"),
    ({"prot": 5555}, "unknown setting"),
])
def test_bad_xcp_settings(c, xcp, message):
    ffi, lib = c
    with pytest.raises(ValueError, match=message):
        a2l.generate(ffi, lib, xcp=xcp)


def test_epk_identifies_the_layout(c, texts):
    ffi, lib = c
    epks = {k: re.search(r'EPK "([^"]+)"', t).group(1) for k, t in texts.items()}
    assert len(set(epks.values())) == 3
    assert all(e.startswith("dct-hil ") for e in epks.values())
    assert epks[None] == a2l.epk(ffi, lib)
    assert epks["vehicle"] == a2l.epk(ffi, lib, channels=_channels("vehicle", ffi, lib))


def test_fallback_constants_are_the_headers(header):
    _ffi, lib = header
    for name, value in a2l._FALLBACK.items():
        assert getattr(lib, name) == value, name


def test_a_stale_module_without_the_new_fields(header):
    """A cdef without signal_values and the region constants still gives an A2L."""
    ffi, lib = header

    class OldLib:
        def __getattr__(self, name):
            if name.startswith(("RT_REGION_", "RT_DAQ_", "RT_EVENT_", "RT_MAX_SIGNAL")):
                raise AttributeError(name)
            return getattr(lib, name)

    from cffi import FFI
    old = FFI()
    text = (ROOT / "rt_loop" / "csrc" / "rt_loop.h").read_text()
    assert "double signal_values[RT_MAX_SIGNAL_VALUES];" in text
    spec = importlib.util.spec_from_file_location("_plant_build", ROOT / "plant" / "_build.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    cdef = "\n".join(build.cdef_text(str(h)) for h in HEADERS)
    cdef = re.sub(r"\n\s*int n_signal_values;[^\n]*\n\s*double signal_values\[RT_MAX_SIGNAL_VALUES\];",
                  "\n", cdef)
    assert "signal_values[" not in cdef
    old.cdef(cdef)
    channels = _channels("vehicle", old, lib)
    out = a2l.generate(old, OldLib(), channels=channels)
    assert "MEASUREMENT pt.ECM_Speed." not in out and "stats.msgs.pt.ECM_Speed." in out
    assert "commands." in out
    regions = a2l.calibration_regions(old, OldLib())
    assert {r[2] for r in regions} == {0, 1}


# ---------------------------------------------------------------------------
# dct-hil a2l
# ---------------------------------------------------------------------------

def _args(*argv):
    p = argparse.ArgumentParser()
    a2l.add_arguments(p)
    return p.parse_args(argv)


def test_cli_writes_the_a2l(tmp_path, capsys, parser):
    out = tmp_path / "sub" / "loop.a2l"
    rc = a2l.run(_args(str(out), "--mapping", "vehicle", "--xcp-port", "6000",
                       "--xcp-transport", "tcp", "--rate", "1000"))
    assert rc == 0
    text = out.read_text()
    from rt_loop._rt_loop import ffi
    if "signal_values" in dict(ffi.typeof("rt_loop").fields):
        assert "pt.ECM_Speed.AccelPedalPos" in text
    assert "XCP_ON_TCP_IP 0x0104 6000" in text
    _parse(parser, text)
    line = capsys.readouterr().out
    assert line.count("\n") == 1 and str(out) in line and "writable" in line
    assert not list(out.parent.glob("*.tmp*"))


def test_cli_default_mapping(tmp_path, capsys):
    out = tmp_path / "loop.a2l"
    assert a2l.run(_args(str(out))) == 0
    assert "commands." in out.read_text()
    assert "dct_hil.toml" in capsys.readouterr().out


@pytest.mark.parametrize("where", ["directory", "under_a_file", "read_only"])
def test_cli_bad_path_is_one_line_exit_2(tmp_path, capsys, where):
    if where == "directory":
        target = tmp_path
    elif where == "under_a_file":
        (tmp_path / "file").write_text("x")
        target = tmp_path / "file" / "loop.a2l"
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        target = ro / "loop.a2l"
        import os
        if os.access(ro, os.W_OK):          # root ignores the mode
            pytest.skip("running as root: a read-only folder is writable")
    rc = a2l.run(_args(str(target)))
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("dct-hil a2l: error: ") and str(target) in err


def test_cli_bad_mapping_is_one_line_exit_2(tmp_path, capsys):
    rc = a2l.run(_args(str(tmp_path / "x.a2l"), "--mapping", str(tmp_path / "nope.toml")))
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "nope.toml" in err
    assert not (tmp_path / "x.a2l").exists()


def test_cli_bad_options_through_argparse():
    with pytest.raises(SystemExit):
        _args("x.a2l", "--xcp-port", "70000")
    with pytest.raises(SystemExit):
        _args("x.a2l", "--rate", "0")
