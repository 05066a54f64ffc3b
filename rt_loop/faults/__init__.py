"""Failure simulation: faults injected inside the loop's tick while the TCU drives.

A fault is data: a kind, what it acts on, its parameters and when it
applies. ``parse_fault(spec, names)`` checks a spec (a dict, e.g. a
``[[fault]]`` table of a TOML file or the keyword arguments of the test API)
against the served mapping and the plant, and turns it into the C loop's
``rt_fault_def``; ``FaultManager`` (one per ``rt_loop.server.Server``,
``server.faults``) queues it into the loop's fault command ring, reads the
loop's start and end events and its per-fault figures, and clears faults.
The loop applies commands at the next tick boundary and never waits for
Python (``rt_loop/csrc/rt_faults.c``).

Kinds (``KINDS`` holds each one's parameters, units and meaning):

=============================  ====================================================
``can.omit``                   a message the plant sends is not sent
``can.freeze_counter``         its alive counter stays at the value it had
``can.bad_crc``                its checksum is wrong (inverted)
``can.late``                   sent ``delay_ms`` later than its cycle, every cycle
``can.too_often``              sent ``factor`` times as often as its cycle
``can.length``                 sent with ``length`` data bytes
``can.bus_off``                no frame of the plant on ``bus`` (every bus if none)
``signal.hold``                a sent or received signal stuck at its last value
``signal.value``               ... stuck at ``value``
``signal.offset``              ... plus ``offset``
``signal.gain``                ... times ``gain``
``signal.noise``               ... plus Gaussian noise of ``sigma`` (``seed``)
``signal.invalid``             ... its invalid value (the DBC's, ``invalid_value``)
``valve.spool_stuck``          the ``clutch`` (1, 2) valve's spool does not move
``valve.solenoid_open``        open circuit: no current in its solenoid
``clutch.friction_fade``       the ``clutch``'s friction coefficient loses ``loss``
``clutch.kiss_drift``          its pack gap grows by ``gap_mm`` (kiss point later)
``hydraulics.line_pressure_loss``  the line pressure loses ``loss`` (1: all)
``fork.jammed``                the ``sleeve``'s fork does not move
``sync.blocker_failed``        the ``sleeve`` engages without synchronizing
``engine.torque_limit``        the engine's torque limited to ``max_nm``
=============================  ====================================================

Schedule, for every kind: ``start_s`` (plant time it may start at; default
at once), ``when`` (a condition that must hold too, e.g. ``"gear == 3"``,
``"TCU_Status.ShiftActive == 1 and vehicle_speed_kmh > 30"``), and
``duration_s`` (default: until cleared). A condition is up to four
comparisons (``<``, ``<=``, ``>``, ``>=``, ``==``, ``!=`` against a number)
joined by ``and`` or by ``or``; a name is a plant output (``gear``,
``vehicle_speed_kmh``, ...), ``maneuver_time_s``, a received value as
``cmd.<name>`` (``cmd.target_gear``), or a CAN signal as
``Message.Signal`` (``bus:Message.Signal`` on a matrix of several buses).

Every error names its cause in one line (``FaultError``); a file of faults
is checked whole before any of it reaches the loop.
"""

from rt_loop.faults.manager import FaultManager
from rt_loop.faults.spec import (
    KINDS,
    Fault,
    FaultError,
    Names,
    invalid_value,
    load_faults,
    parse_condition,
    parse_fault,
)

__all__ = ["KINDS", "Fault", "FaultError", "FaultManager", "Names", "invalid_value", "load_faults",
           "parse_condition", "parse_fault"]

