"""The project's CAN contract between plant and TCU in one process.

Every TCU period the plant outputs go through the contract: each plant
message is encoded with ``can_dbc.codec.encode`` and decoded again, so the TCU
sees exactly the quantized signals it would receive on CAN; its commands are
encoded and decoded the same way before they drive the plant inputs.

Each message also keeps its DBC cycle time, as on the bus: the TCU sees a
10 ms message (fork positions, vehicle speed, pedals) refreshed every fifth
period only, and its 10 ms commands (fork forces, engine torque request)
reach the plant every fifth period (``ContractLink``). The phase of each
message within its cycle follows the server's staggering, so an offline run
and a run over CAN see their data equally old. The closed loops in Python
(``tcu_stub.offline``) and in C (``tcu_stub.fast``) both take their plan and
routing from here.
"""

from can_dbc import codec
from tcu_stub.logic import PERIOD_S

__all__ = ["DRIVER_PERIOD_S", "PERIOD_S", "RECORDED", "ContractLink", "apply_commands",
           "sensors_from_plant"]

DRIVER_PERIOD_S = 0.01


def _plant_messages():
    out = []
    for name, sources in codec.PLANT_SIGNAL_SOURCES.items():
        fields = {sig: src[2:] for sig, src in sources.items() if src.startswith("o.")}
        if fields:
            out.append((name, codec.message(name).frame_id, fields))
    return out


PLANT_MESSAGES = _plant_messages()
TCU_MESSAGES = [(name, codec.message(name).frame_id, targets)
                 for name, targets in codec.TCU_SIGNAL_TARGETS.items()]


def _phase_plan(names):
    """{message: (divisor, offset)} in TCU periods: a 10 ms message every fifth
    period; messages of one cycle time take consecutive offsets (DBC order)."""
    plan, used = {}, {}
    for name in names:
        div = max(1, int(round(codec.message(name).cycle_time / 1000.0 / PERIOD_S)))
        off = used.get(div, 0)
        used[div] = off + 1
        plan[name] = (div, off % div)
    return plan


PLANT_PLAN = _phase_plan([m[0] for m in PLANT_MESSAGES])
TCU_PLAN = {name: (max(1, int(round(codec.message(name).cycle_time / 1000.0 / PERIOD_S))), 0)
             for name, _, _ in TCU_MESSAGES}


def _due(plan, name, k):
    div, off = plan[name]
    return k % div == off


def sensors_from_plant(outputs, counter=0, sensors=None, due=None):
    """The TCU's view of the plant outputs: the plant messages through encode/decode.

    ``sensors`` (a dict, updated in place) and ``due(name) -> bool`` refresh
    only the messages due now; by default every message is refreshed."""
    sensors = {} if sensors is None else sensors
    for name, frame_id, fields in PLANT_MESSAGES:
        if due is not None and not due(name):
            continue
        values = {sig: float(outputs[field]) for sig, field in fields.items()}
        _, decoded = codec.decode(frame_id, codec.encode(name, values, counter))
        for sig in fields:
            sensors[sig] = decoded[sig]
    sensors["stale"] = False
    return sensors


def apply_commands(plant, commands, counter=0, due=None):
    """Write the TCU commands, quantized by the CAN contract, into the plant inputs
    (only the messages for which ``due(name)`` is true, if given)."""
    for name, frame_id, targets in TCU_MESSAGES:
        if due is not None and not due(name):
            continue
        values = {sig: float(commands[sig]) for sig in targets}
        _, decoded = codec.decode(frame_id, codec.encode(name, values, counter))
        for sig, (_, input_name) in targets.items():
            if input_name is not None:
                plant.inputs[input_name] = decoded[sig]


class ContractLink:
    """The CAN contract between plant and TCU in one process, with cycle times.

    ``sensors(outputs, k)`` gives the TCU's view at TCU period ``k``: the plant
    messages due at ``k`` refreshed, the others as last received.
    ``apply(plant, commands, k)`` writes the TCU messages due at ``k``."""

    def __init__(self):
        self._sensors = {}

    def sensors(self, outputs, k):
        first = not self._sensors
        sensors_from_plant(outputs, k % 16, self._sensors,
                           None if first else (lambda name: _due(PLANT_PLAN, name, k)))
        return dict(self._sensors, stale=False)

    def apply(self, plant, commands, k):
        apply_commands(plant, commands, k % 16, lambda name: _due(TCU_PLAN, name, k))

    def refresh(self, outputs, due):
        """The plant messages named in ``due`` ((bus, message) pairs, as
        ``can_dbc.table.send_schedule`` gives them) sent now with ``outputs``:
        what the TCU reads of them until they are sent again (``view``)."""
        names = {name for _, name in due}
        if names:
            sensors_from_plant(outputs, 0, self._sensors, lambda name: name in names)

    def view(self):
        """The TCU's view: each plant message as last sent (``refresh``)."""
        return dict(self._sensors, stale=False)


RECORDED = ("vehicle_speed_kmh", "vehicle_accel_mps2", "engine_speed_rpm", "input_shaft1_speed_rpm",
            "input_shaft2_speed_rpm", "clutch1_pressure_bar", "clutch2_pressure_bar",
            "solenoid_current1_a", "solenoid_current2_a", "engine_torque_nm", "accel_pedal_pct",
            "brake_pedal_pct", "gear_clashes", "fuel_l", "distance_m", "gear",
            "coolant_temp_degc", "trans_oil_temp_degc", "clutch1_friction_coeff",
            "clutch2_friction_coeff", "clutch1_drag_torque_nm", "clutch2_drag_torque_nm",
            "clutch1_kiss_pressure_bar", "clutch2_kiss_pressure_bar")
