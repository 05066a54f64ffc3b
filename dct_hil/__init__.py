"""dct-hil: hardware-in-the-loop plant server for the VW DSG 02E dual clutch transmission."""

__version__ = "0.1.0"
