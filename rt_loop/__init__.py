"""The 2 kHz real-time loop: receive CAN frames, step the plant every 0.5 ms, send the due frames (to come)."""
