"""Closed loop of the plant and the stub TCU in one process, without a back door.

Every TCU period the plant outputs go through the CAN contract: each plant
message is encoded with ``can_dbc.codec.encode`` and decoded again, so the TCU
sees exactly the quantized signals it would receive on CAN; its commands are
encoded and decoded the same way before they drive the plant inputs.
"""

import numpy as np

from can_dbc import codec
from tcu_stub.logic import PERIOD_S, TcuLogic

DRIVER_PERIOD_S = 0.01


def _plant_messages():
    out = []
    for name, sources in codec.PLANT_SIGNAL_SOURCES.items():
        fields = {sig: src[2:] for sig, src in sources.items() if src.startswith("o.")}
        if fields:
            out.append((name, codec.message(name).frame_id, fields))
    return out


_PLANT_MESSAGES = _plant_messages()
_TCU_MESSAGES = [(name, codec.message(name).frame_id, targets)
                 for name, targets in codec.TCU_SIGNAL_TARGETS.items()]


def sensors_from_plant(outputs, counter=0):
    """The TCU's view of the plant outputs: every plant message through encode/decode."""
    sensors = {}
    for name, frame_id, fields in _PLANT_MESSAGES:
        values = {sig: float(outputs[field]) for sig, field in fields.items()}
        _, decoded = codec.decode(frame_id, codec.encode(name, values, counter))
        for sig in fields:
            sensors[sig] = decoded[sig]
    sensors["stale"] = False
    return sensors


def apply_commands(plant, commands, counter=0):
    """Write the TCU commands, quantized by the CAN contract, into the plant inputs."""
    for name, frame_id, targets in _TCU_MESSAGES:
        values = {sig: float(commands[sig]) for sig in targets}
        _, decoded = codec.decode(frame_id, codec.encode(name, values, counter))
        for sig, (_, input_name) in targets.items():
            plant.inputs[input_name] = decoded[sig]


RECORDED = ("vehicle_speed_kmh", "vehicle_accel_mps2", "engine_speed_rpm", "input_shaft1_speed_rpm",
            "input_shaft2_speed_rpm", "clutch1_pressure_bar", "clutch2_pressure_bar",
            "solenoid_current1_a", "solenoid_current2_a", "engine_torque_nm", "accel_pedal_pct",
            "brake_pedal_pct", "gear_clashes", "fuel_l", "distance_m", "gear")


def run_offline(plant, driver_fn, duration_s, record_every_s=0.01, tcu=None, stale_fn=None):
    """Run plant + stub TCU for ``duration_s``.

    ``driver_fn(t_s, plant_outputs) -> (accel_pedal_pct, brake_pedal_pct)`` is
    called every 10 ms. ``stale_fn(t_s) -> bool`` (optional) marks the plant
    messages as missing. Returns a dict of arrays (``time_s``, the names in
    ``RECORDED``, ``tcu_target_gear``, ``tcu_gear``, ``tcu_phase``) and
    ``shifts``: a list of (time_s, from_gear, to_gear)."""
    if duration_s <= 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    tcu = tcu or TcuLogic()
    steps_per_tcu = max(1, int(round(PERIOD_S / plant.step_s)))
    tcu_per_driver = max(1, int(round(DRIVER_PERIOD_S / PERIOD_S)))
    tcu_per_record = max(1, int(round(record_every_s / PERIOD_S)))
    n = int(round(duration_s / PERIOD_S))
    rec = {k: [] for k in ("time_s",) + RECORDED + ("tcu_target_gear", "tcu_gear", "tcu_phase")}
    t0 = plant.time_s
    for k in range(n):
        t = plant.time_s - t0
        out = plant.outputs
        if k % tcu_per_driver == 0:
            accel, brake = driver_fn(t, out)
            plant.inputs["accel_pedal_pct"] = accel
            plant.inputs["brake_pedal_pct"] = brake
            plant.update_outputs()
        sensors = sensors_from_plant(out, k % 16)
        if stale_fn is not None and stale_fn(t):
            sensors["stale"] = True
        cmd = tcu.step(t, sensors)
        apply_commands(plant, cmd, k % 16)
        if k % tcu_per_record == 0:
            rec["time_s"].append(t)
            for name in RECORDED:
                rec[name].append(float(out[name]))
            rec["tcu_target_gear"].append(tcu.target_gear)
            rec["tcu_gear"].append(tcu.gear)
            rec["tcu_phase"].append(tcu.phase)
        plant.step(steps_per_tcu)
    result = {k: (np.array(v) if k != "tcu_phase" else v) for k, v in rec.items()}
    result["shifts"] = list(tcu.events)
    return result
