"""Option types shared by every command line of the project (dct-hil's
subcommands, the TCU node, the loop's tools, the studies): each turns the text
of an option into a value or raises ``argparse.ArgumentTypeError`` with the
reason, which argparse prints as one line naming the option. In the lowest
layer so that every command line takes its options with the same rules, written
once."""

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


def real(lo=None, hi=None, *, above=False, what="", unit=""):
    """A finite number from ``lo`` (exclusive with ``above``) to ``hi``: an option
    type. ``what`` names the value in the error ("a number of seconds")."""
    name = f"{what} " if what else ""
    suffix = f" {unit}" if unit else ""

    def parse(text):
        x = _float(text)
        ok = math.isfinite(x) and (lo is None or (x > lo if above else x >= lo)) and (
            hi is None or x <= hi)
        if not ok:
            if lo is not None and hi is not None:
                bound = (f"above {lo:g} and at most {hi:g}{suffix}" if above
                         else f"{lo:g} to {hi:g}{suffix}")
            elif lo is not None:
                bound = f"above {lo:g}{suffix}" if above else f">= {lo:g}{suffix}"
            else:
                bound = f"at most {hi:g}{suffix}"
            raise argparse.ArgumentTypeError(f"must be {name}{bound}, got {text}")
        return x
    return parse


def whole_number(lo, hi=None, what="a whole number"):
    """A whole number from ``lo`` to ``hi`` (no upper bound without it): an option type."""
    def parse(text):
        n = _int(text, what)
        if n < lo or (hi is not None and n > hi):
            bound = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return n
    return parse


def count(text):
    """A count of things, 0 or more; "1e7" is 10000000."""
    x = _float(text)
    if not (math.isfinite(x) and x >= 0 and x == int(x)):
        raise argparse.ArgumentTypeError(f"must be a whole number 0 or more, got {text!r}")
    return int(x)


seconds = real(0, above=True, what="a number of seconds")          # a duration above 0
seconds_or_zero = real(0, what="a number of seconds")              # 0: none
positive = real(0, above=True)                                      # any number above 0
non_negative = real(0)                                              # any number >= 0
microseconds = real(0, what="a number of microseconds")            # a busy-wait, a margin
record_interval = real(0, 10, above=True, what="a number of seconds")
time_scale = real(0, 1, above=True, what="a time scale (1: real time)")
rate_hz = real(0, above=True, what="a rate", unit="Hz")


def loop_rate(lo_hz, hi_hz):
    """The real-time loop's rate, ``lo_hz`` to ``hi_hz`` (its periods' limits)."""
    def parse(text):
        x = _float(text)
        if not (math.isfinite(x) and lo_hz <= x <= hi_hz):
            raise argparse.ArgumentTypeError(
                f"must be {lo_hz:g} to {hi_hz:g} Hz (a period of {1e3 / lo_hz:g} ms to "
                f"{1e6 / hi_hz:g} us), got {text}")
        return x
    return parse


def priority(text):
    """A SCHED_FIFO priority 1..99, or 0 for normal scheduling."""
    n = _int(text)
    if not 0 <= n <= 99:
        raise argparse.ArgumentTypeError(
            f"must be a SCHED_FIFO priority 1..99 (or 0: normal scheduling), got {text}")
    return n


def port(lo=1):
    """A TCP/UDP port, ``lo``..65535 (0: any free port, where the caller allows it)."""
    def parse(text):
        n = _int(text, "a port number")
        if not lo <= n <= 65535:
            raise argparse.ArgumentTypeError(f"must be a port {lo}..65535, got {text}")
        return n
    return parse


def pm_qos_us(text):
    """A PM QoS CPU wake-up latency: a whole number of microseconds, 0..1000000,
    or "auto" (0 under SCHED_FIFO, no request under normal scheduling)."""
    if text == "auto":
        return text
    n = _int(text, 'a whole number of microseconds or "auto"')
    if not 0 <= n <= 1_000_000:
        raise argparse.ArgumentTypeError(f"must be 0..1000000 us, got {text}")
    return n


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
