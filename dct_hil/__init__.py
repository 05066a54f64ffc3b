"""dct-hil: hardware-in-the-loop plant server for the VW DSG 02E dual clutch transmission."""

from plant import __version__

__all__ = ["__version__"]
