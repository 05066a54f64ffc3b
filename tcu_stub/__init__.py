"""The reference TCU (stub): drives the plant through the CAN contract only.

``tcu_stub.logic.TcuLogic`` is the TCU written once, without I/O (2 ms task:
DBC plant signals in, DBC command signals out). ``tcu_stub.offline.run_offline``
closes the loop with a ``Plant`` in-process, every signal going through the DBC
codec, so the TCU sees exactly what it would see on CAN.
"""

from tcu_stub.logic import PERIOD_S, TcuLogic

__all__ = ["PERIOD_S", "TcuLogic"]
