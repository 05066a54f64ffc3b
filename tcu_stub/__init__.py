"""A simple reference TCU that drives the plant over CAN, for testing without real hardware (to come)."""
