"""Option types shared by the dct-hil commands: each turns the text of an
option into a value or raises ``argparse.ArgumentTypeError`` with the reason,
which argparse prints as one line naming the option. In the lowest layer so
that every command line (the plant's, the TCU's, the loop's tools, dct-hil's)
takes its options with the same rules."""

import argparse
import math


def _float(text):
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def _int(text, what="a whole number"):
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None


def seconds(text):
    """A duration: a finite number of seconds above 0."""
    x = _float(text)
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0, got {text}")
    return x


def record_interval(text):
    """A recording interval: above 0, at most 10 s."""
    x = _float(text)
    if not (math.isfinite(x) and 0 < x <= 10):
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0 and at most 10, "
                                         f"got {text}")
    return x


def pm_qos_us(text):
    """A PM QoS CPU wake-up latency: a whole number of microseconds, 0..1000000,
    or "auto" (0 under SCHED_FIFO, no request under normal scheduling)."""
    if text == "auto":
        return text
    n = _int(text, 'a whole number of microseconds or "auto"')
    if not 0 <= n <= 1_000_000:
        raise argparse.ArgumentTypeError(f"must be 0..1000000 us, got {text}")
    return n


def time_scale(text):
    """Slow motion: above 0, at most 1 (1 is real time)."""
    x = _float(text)
    if not (math.isfinite(x) and 0 < x <= 1):
        raise argparse.ArgumentTypeError(f"must be above 0 and at most 1 (1: real time), got {text}")
    return x


def bitrate(text):
    """A CAN bit rate, 1 kbit/s to 8 Mbit/s."""
    n = _int(text)
    if not 1_000 <= n <= 8_000_000:
        raise argparse.ArgumentTypeError(f"must be 1000..8000000 bit/s, got {text}")
    return n


def cpu(text):
    """A CPU number."""
    n = _int(text, "a CPU number")
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be a CPU number >= 0, got {text}")
    return n


def whole_number(lo, hi):
    """A whole number from ``lo`` to ``hi`` (an option type)."""
    def parse(text):
        n = _int(text)
        if not lo <= n <= hi:
            raise argparse.ArgumentTypeError(f"must be between {lo} and {hi}, got {text}")
        return n
    return parse
