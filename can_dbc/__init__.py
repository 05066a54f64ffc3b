"""The CAN contract between the plant server and the TCU.

- ``dct_hil.dbc``: the single source of truth (messages, signals, units,
  ranges, senders, GenMsgCycleTime).
- ``codec``: the DBC through cantools plus the end-to-end protection (CRC-8/
  SAE-J1850 and AliveCounter), the E2E receiver and the bus load figure.
- ``generate``: the C pack/unpack code in ``generated/``, generated from the
  DBC by cantools (``python -m can_dbc.generate --check`` verifies it).
- ``csrc/dct_can.{h,c}``: the C facade the real-time loop uses.
- ``peer``: an E2E-aware node for either side on any python-can bus.
- ``python -m can_dbc``: a summary of the contract and its bus load.
"""
