"""Writes the seed corpora of the fuzz targets (fuzz/corpus/<target>/) from the
project's real tables, parameters, mappings and requests:

    .venv/bin/python fuzz/make_corpus.py

Each seed is in its target's input format (the comment at the top of each
fuzz/<target>.c or .py); the files are small and deterministic, so running
this again changes nothing unless the tables or parameters did.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
CORPUS = os.path.join(ROOT, "fuzz", "corpus")


def _write(target: str, seeds: dict[str, bytes]) -> None:
    d = os.path.join(CORPUS, target)
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    for name, data in seeds.items():
        with open(os.path.join(d, name), "wb") as f:
            f.write(data)
    print(f"fuzz/corpus/{target}: {len(seeds)} seeds, {sum(map(len, seeds.values()))} bytes")


# ---------------------------------------------------------------- C targets
def _contract():
    from can_dbc import mapping
    from rt_loop._rt_loop import ffi, lib
    from rt_loop.channels import LoopChannels
    return LoopChannels(mapping.load(), ffi, lib), ffi


def can_frame() -> dict[str, bytes]:
    """fuzz/can_frame.c: the contract's messages (up to 8 signals), dct-protected."""
    lc, ffi = _contract()
    t = lc.table(0)
    msgs = t.table[0].messages
    sigs = t.table[0].signals
    seeds = {}
    for i in range(t.table[0].n_messages):
        m = msgs[i]
        if m.n_signals > 8:
            continue
        b = bytearray([0])                                   # one message
        b += bytes([m.extended | (m.fd << 1)]) + struct.pack("<I", m.id) + bytes([m.length, m.n_signals])
        for k in range(m.n_signals):
            s = sigs[m.first_signal + k]
            conv = {0: 0, 1: 1, 2: 2, 3: 3}[s.conversion]
            b.append(s.is_float | (int(s.length == 64) << 1) | (s.big_endian << 2) | (s.is_signed << 3)
                     | (conv << 4) | (s.limited << 6))
            if not s.is_float:
                b.append(s.length - 1)
            pos = 8 * (s.start // 8) + 7 - s.start % 8 if s.big_endian else s.start
            b.append(pos)
            if conv in (1, 3):
                b += struct.pack("<b", max(-128, min(127, s.factor_int)))
                b += struct.pack("<h", s.offset_int) if conv == 1 else struct.pack("<d", s.offset)
            elif conv == 0:
                b += struct.pack("<dd", s.factor, s.offset)
            if s.limited:
                b += struct.pack("<dd", s.minimum, s.maximum)
        b += bytes([m.max_delta_counter, m.protection, max(m.crc_byte, 0)])
        b += bytes(m.n_signals)                              # no multiplexers
        b += b"".join(struct.pack("<d", float(k)) for k in range(m.n_signals)) + struct.pack("<I", 3)
        for c in range(3):                                   # frames of it: zeros, then ones
            b += bytes([0x80, m.length]) + bytes([0xFF * (c & 1)] * m.length)
        seeds[f"contract-{i:02d}"] = bytes(b)
    return seeds


def rt_prepare() -> dict[str, bytes]:
    """fuzz/rt_prepare.c: the contract's and the vehicle mapping's channels as
    channels.py lays them out, byte for byte."""
    from can_dbc import mapping
    from rt_loop._rt_loop import ffi, lib
    from rt_loop.channels import LoopChannels
    seeds = {}
    for name in ("dct_hil", "vehicle"):
        lc = LoopChannels(mapping.load(os.path.join(mapping.MAPPINGS_DIR, f"{name}.toml")), ffi, lib)
        loop = ffi.new("rt_loop *")
        lc.install(loop)
        b = bytearray([0])                                   # no configuration patches
        b += struct.pack("<b", loop.n_commands)
        b += bytes(ffi.buffer(loop.command_input))
        b += bytes([0x80]) * lib.RT_MAX_COMMANDS             # command inputs as they are
        b += struct.pack("<b", 0) + bytes(8 * ffi.sizeof("rt_region"))
        b.append(loop.n_channels)
        for c in range(loop.n_channels):
            ch = loop.chan[c]
            n_msgs = ch.table.n_messages
            msgs = [ch.table.messages[m] for m in range(n_msgs)]
            n_sig = sum(m.n_signals for m in msgs)
            b.append(0x0C)                                   # plausible, protection and mux kept
            b += struct.pack("<b", n_msgs)
            b += bytes(m.n_signals for m in msgs)
            b += struct.pack("<b", ch.n_ranges)
            b += bytes(ffi.buffer(ch.table.messages, n_msgs * ffi.sizeof("ct_message")))
            b += bytes(ffi.buffer(ch.table.signals, n_sig * ffi.sizeof("ct_signal")))
            n_mux = sum(ch.table.signals[k].mux_count for k in range(n_sig)
                        if ch.table.signals[k].mux_signal >= 0)
            b += bytes(ffi.buffer(ch.table.mux, n_mux * ffi.sizeof("ct_mux_range")))
            b += bytes(ffi.buffer(ch.msgs, n_msgs * ffi.sizeof("rt_msg")))
            b += bytes(ffi.buffer(ch.sources, n_sig * ffi.sizeof("rt_source")))
            b += bytes(ffi.buffer(ch.targets, n_sig * ffi.sizeof("rt_target")))
            b += bytes(ffi.buffer(ch.ranges, ch.n_ranges * ffi.sizeof("rt_range")))
        seeds[name] = bytes(b)
    return seeds


def _param_doubles():
    from plant.model import ffi
    from plant.params import fill_params, load_params
    p = ffi.new("dct_params *")
    fill_params(ffi, p, load_params(None, ffi, None))
    raw = bytes(ffi.buffer(p))
    return struct.unpack(f"<{len(raw) // 8}d", raw)


def plant_prepare() -> dict[str, bytes]:
    """fuzz/plant_prepare.c: one parameter of the default car at a time, scaled."""
    values = _param_doubles()
    seeds = {"defaults": bytes([0, 0, 0, 0, 0]) + struct.pack("<d", values[0])}
    for i in range(0, len(values), max(1, len(values) // 40)):
        for tag, scale in (("x10", 10.0), ("zero", 0.0), ("neg", -1.0)):
            seeds[f"param{i:04d}-{tag}"] = bytes([0, 0]) + struct.pack("<H", i) + bytes([0]) + \
                struct.pack("<d", values[i] * scale)
    return seeds


def fmu_state() -> dict[str, bytes]:
    """fuzz/fmu_state.c: the real state unpatched, patched once, and bare headers."""
    return {"pristine": b"\x01", "patched": b"\x01" + struct.pack("<I", 4096) + b"\x07" + b"\x00" * 8,
            "header": b"\x00DCT-FMUS" + struct.pack("<II", 1, 0x01020304),
            "empty": b"\x00"}


# ---------------------------------------------------------------- Python targets
def xcp_packet() -> dict[str, bytes]:
    from rt_loop.measure.xcp import protocol as xp

    def packets(*ps):
        return b"\x01" + b"".join(bytes([len(p)]) + bytes(p) for p in ps)
    return {
        "status": packets([xp.GET_STATUS], [xp.GET_COMM_MODE_INFO]),
        "upload": packets([xp.SET_MTA, 0, 0, 0, 0, 4, 0, 0], [xp.UPLOAD, 8], [xp.SHORT_UPLOAD, 4, 0, 0, 0, 4, 0, 0]),
        "download": packets([xp.SET_MTA, 0, 0, 0, 0, 4, 0, 0], [xp.DOWNLOAD, 2, 1, 2]),
        "daq": packets([xp.FREE_DAQ], [xp.ALLOC_DAQ, 0, 1, 0], [xp.ALLOC_ODT, 0, 0, 0, 1],
                       [xp.ALLOC_ODT_ENTRY, 0, 0, 0, 0, 1], [xp.SET_DAQ_PTR, 0, 0, 0, 0, 0],
                       [xp.WRITE_DAQ, 0xFF, 4, 0, 0, 0, 0, 0], [xp.START_STOP_SYNCH, 1]),
        "disconnect": packets([xp.DISCONNECT], [xp.GET_STATUS]),
    }


def mapping_load() -> dict[str, bytes]:
    """fuzz/mapping_load.py: the shipped mappings with their DBCs as a.dbc, b.dbc."""
    from can_dbc import mapping
    seeds = {}
    for name in ("dct_hil", "vehicle"):
        path = os.path.join(mapping.MAPPINGS_DIR, f"{name}.toml")
        text = open(path, encoding="utf-8").read()
        dbcs = []
        for line in text.splitlines():
            if line.strip().startswith("dbc ="):
                dbcs.append(line.split("=", 1)[1].strip().strip('"'))
        for k, rel in enumerate(dbcs):
            text = text.replace(f'"{rel}"', f'"{"ab"[k]}.dbc"')
        parts = [text.encode()] + [open(os.path.join(mapping.MAPPINGS_DIR, rel), "rb").read()
                                   for rel in dbcs]
        seeds[name] = b"\0".join(parts)
    return seeds


def stimulus_load() -> dict[str, bytes]:
    """fuzz/stimulus_load.py: a CSV of two plant inputs; the same as MF4."""
    csv = b"time_s,accel_pedal_pct,brake_pedal_pct\n0,0,0\n0.5,20,0\n1.0,20,10\n"
    seeds = {"csv": b"\x00" + csv}
    try:
        import numpy as np
        from asammdf import MDF, Signal
    except ImportError:
        return seeds
    with tempfile.TemporaryDirectory() as d:
        t = np.array([0.0, 0.5, 1.0])
        mdf = MDF()
        mdf.append([Signal(np.array([0.0, 20.0, 20.0]), t, name="accel_pedal_pct")])
        path = os.path.join(d, "s.mf4")
        mdf.save(path, overwrite=True)
        seeds["mf4"] = b"\x01" + open(path, "rb").read()
    return seeds


def control_request() -> dict[str, bytes]:
    """fuzz/control_request.py: the requests of tests/test_control.py."""
    reqs = [{"op": "ping"}, {"op": "snapshot"}, {"op": "config"}, {"op": "faults"}, {"op": "events"},
            {"op": "read", "names": ["time_s", "vehicle_speed_kmh", "cmd.target_gear",
                                     "DCT_ShaftSpeeds.EngineSpeed", "maneuver_time_s"]},
            {"op": "set", "name": "road_grade_pct", "value": 4.5},
            {"op": "set", "name": "override.accel_pedal_pct", "value": 10},
            {"op": "inject", "spec": {"kind": "can.omit", "message": "VEH_Driver", "duration_s": 0.05}},
            {"op": "watch", "when": "time_s > 0.3"}, {"op": "clear", "id": 1}, {"op": "clear_all"},
            {"op": "capture", "signals": ["vehicle_speed_kmh", "cmd.target_gear"],
             "every_s": 0.001, "start_when": "time_s > 0.2", "pre_s": 0.1, "duration_s": 0.1},
            {"op": "capture_status", "id": 1}, {"op": "capture_fetch", "id": 1},
            {"op": "capture_stop", "id": 1}, {"op": "capture_clear", "id": 1},
            {"op": "reset_plant"},
            {"op": "set", "name": "params.engine.idle_speed_rpm", "value": 900},
            {"op": "read", "names": ["params.engine.idle_speed_rpm", "params.clutch[1].mu_static"]},
            {"op": "restore_params"}]
    return {f"{k:02d}-{r['op']}": json.dumps(r).encode() for k, r in enumerate(reqs)}


def control_stream() -> dict[str, bytes]:
    """fuzz/control_stream.py: a client's bytes (the first bytes choose the hello and the
    cuts): requests whole, pipelined, cut, too long, not JSON."""
    lines = [b'{"op": "ping"}\n', b'{"op": "read", "names": ["gear"]}\n{"op": "faults"}\n',
             b'{"op": "set", "name": "road_grade_pct", "va', b'not json\n\n{"op": 1}\n',
             b'{"op": "capture", "signals": ["gear"], "duration_s": 0.01}\n'
             b'{"op": "capture_fetch", "id": 1}\n', b'{"op": "hello", "token": "x"}\n']
    return {f"{k:02d}": bytes([1, 2, 0, 9, 40]) + line for k, line in enumerate(lines)}


TARGETS = {"can_frame": can_frame, "rt_prepare": rt_prepare, "plant_prepare": plant_prepare,
           "fmu_state": fmu_state, "xcp_packet": xcp_packet, "mapping_load": mapping_load,
           "stimulus_load": stimulus_load, "control_request": control_request,
           "control_stream": control_stream}

if __name__ == "__main__":
    for name in sys.argv[1:] or TARGETS:
        _write(name, TARGETS[name]())
