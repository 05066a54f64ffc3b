"""The CAN contract between the plant server and the TCU.

- ``dct_hil.dbc``: the single source of truth (messages, signals, units,
  ranges, senders, GenMsgCycleTime).
- ``codec``: the DBC through cantools plus the end-to-end protection (CRC-8/
  SAE-J1850 and AliveCounter), the E2E receiver and the bus load figure.
- ``peer``: an E2E-aware node for either side on any python-can bus.
- ``protection``: a message's end-to-end protection as a mapping file names
  it (the project's CRC, AUTOSAR E2E Profiles 1 and 2, XOR, counter).
- ``mapping``: mapping files (``mappings/``): a vehicle's CAN matrix (DBC
  files, ``matrices/`` holds an example) and what the plant sends and
  receives on it; ``dct-hil mapping template|check|show``.
- ``table``: the table-driven codec (``csrc/can_table.{h,c}``): any DBC
  layout packed and unpacked in C from flat tables built at start-up; the
  one codec of the real-time loop (``rt_loop/channels.py``), for the
  contract (``mappings/dct_hil.toml``) and any vehicle matrix alike.
- ``own_frames``: the echoes of a node's own frames on a bus that loops them
  back (udp_multicast).
- ``python -m can_dbc``: a summary of the contract and its bus load.
"""
