"""python -m can_dbc: a one-screen summary of the CAN contract (messages,
cycle times, senders, signals) and its worst-case bus load."""

import argparse
import sys

from . import codec


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m can_dbc", description="Summary of the dct-hil CAN contract.")
    parser.add_argument("--bitrate", type=int, default=1_000_000, help="bit rate for the bus load (default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        load = codec.bus_load(args.bitrate)
        msgs = sorted(codec.messages(), key=lambda m: m.frame_id)
    except ValueError as e:
        print(f"can_dbc: {e}", file=sys.stderr)
        return 2
    print(f"{codec.DBC_PATH}")
    for m in msgs:
        print(f"0x{m.frame_id:03X} {m.name:<17} {m.senders[0]:<5} {m.cycle_time:>4} ms  {m.length} B")
        for s in codec.payload_signals(m):
            print(f"        {s.name:<20} {s.minimum:>10.10g} .. {s.maximum:<10.10g} {s.unit:<5} step {s.scale:g}")
    print(f"worst-case bus load at {args.bitrate / 1e6:g} Mbit/s: {100 * load:.2f} % "
          f"({codec.frame_bits_worst_case(8)} bits per 8-byte frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
