"""Measurement and calibration of a running loop, beside the tick, never in it.

``xcp`` (the XCP slave: protocol, transports, the loop's memory as XCP
addresses, the A2L that describes them), ``mdf_recorder`` (the recording as
ASAM MDF4), ``recorder`` (the recorder ring as CSV), ``stimulus`` (a file's
inputs played into the tick), ``scope`` (min/max traces for the live view).
Each reads the loop's lock-free rings or sequence-counted copies from a thread
of its own (rt_loop/csrc: rt_ring.c's rings, rt_scope.c).
"""
