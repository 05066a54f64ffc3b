"""CAN contract between the plant server and the TCU: the DBC file and the pack/unpack code generated from it (to come)."""
