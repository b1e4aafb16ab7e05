"""argparse `type=` callables shared by every `tacf` command, so that a bad value is a usage error (exit 2, one
line naming the option) when the command line is parsed, not a traceback or a silent oddity later.

Numbers that are times, rates or sizes must be finite: float() takes 'nan' and 'inf', and NaN passes any
`value <= 0` check (every comparison with it is false), then waits for ever or overflows a timeout. A finite one
overflowed too when huge: those of positive_number and seconds are at most LARGEST.

Only argparse at import time: `tacf --help` loads every command's arguments.
"""
from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable

Box = tuple[float, float, float, float]
# What argparse takes for a negative number rather than an option, as from Python 3.14 on: before, only "-5" or
# "-.5" itself, and a box across the left or top border, "--box -5,20,40,30", was an option ("expected one argument").
NEGATIVE_NUMBER = re.compile(r"-\.?\d")
# The largest time or rate taken, 31 years in seconds: a wait past threading.TIMEOUT_MAX (9.2e9 s on Linux) raised
# an OverflowError (nodes --follow --duration 1e10, a start on `serve --init-wait 1e10`), a Zenoh query timeout past
# 1.8e19 s a ValueError (list --timeout 1e20).
LARGEST = 1e9


def _number(text: str, expected: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
    return value


def positive_number(text: str) -> float:
    """A rate, a timeout, a duration that must pass: > 0 and <= LARGEST."""
    expected = f"a finite number > 0 and <= {LARGEST:g}"
    value = _number(text, expected)
    if not 0 < value <= LARGEST:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
    return value


def positive_up_to(maximum: float) -> Callable[[str], float]:
    """A finite number > 0 and <= maximum."""
    expected = f"a number > 0 and <= {maximum:g}"

    def parse(text: str) -> float:
        value = _number(text, expected)
        if not 0 < value <= maximum:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
        return value

    return parse


def seconds(text: str) -> float:
    """A wait that may be none: a number of seconds >= 0 and <= LARGEST."""
    expected = f"a finite number of seconds >= 0 and <= {LARGEST:g}"
    value = _number(text, expected)
    if not 0 <= value <= LARGEST:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
    return value


def integer(minimum: int | None = None, maximum: int | None = None,
            what: str = "an integer") -> Callable[[str], int]:
    """An integer within [minimum, maximum] (either bound may be left open); `what` names it in the message."""
    if minimum is not None and maximum is not None:
        expected = f"{what} {minimum}-{maximum}"
    elif minimum is not None:
        expected = f"{what} >= {minimum}"
    elif maximum is not None:
        expected = f"{what} <= {maximum}"
    else:
        expected = what

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}") from None
        if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
        return value

    return parse


port = integer(0, 65535, "a port number")       # 0: any free port
quality = integer(1, 100, "a JPEG quality")


def box(text: str) -> Box:
    """'x,y,w,h' (commas and/or spaces) in pixels: four finite numbers with w and h > 0."""
    expected = "x,y,w,h: four finite numbers with w and h > 0"
    parts = text.replace(",", " ").split()
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}") from None
    if len(values) != 4 or not all(map(math.isfinite, values)) or values[2] <= 0 or values[3] <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
    return values  # type: ignore[return-value]


def not_empty(expected: str) -> Callable[[str], str]:
    """A name that must be given, refused when empty, as "$VIDEO" is when the variable is unset: an empty SOURCE was
    the current folder, read as a folder of images; an empty --zenoh-config no file to the service and the current
    folder to the clients ("Is a directory")."""
    def check(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError(f"'': expected {expected}, not an empty name")
        return text
    return check


source = not_empty("a source to read frames from")          # file, folder, camera, URL
config_file = not_empty("a Zenoh JSON5 config file")


def endpoint(text: str) -> str:
    """A Zenoh endpoint for --connect or --listen: one that names no port, or no number for one, is refused here
    (tacf.zenoh_options.endpoint_problem)."""
    from tacf.zenoh_options import endpoint_problem

    if problem := endpoint_problem(text):
        raise argparse.ArgumentTypeError(problem)
    return text


def take_negative_numbers(parser: argparse.ArgumentParser) -> None:
    """Let `parser`'s option values start with a negative number, "-5,20,40,30" as "-5" (argparse's own test)."""
    parser._negative_number_matcher = NEGATIVE_NUMBER
