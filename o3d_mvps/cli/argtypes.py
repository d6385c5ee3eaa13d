"""argparse value types shared by the subcommands (bad values exit with code 2 and a message
that argparse prefixes with the option, e.g. ``argument --workers: expected an integer >= 1, got '0'``).

Every numeric option of the command line and of the pipelines takes one of these, so a value
that the code would silently change (``--workers 0`` read as the default, ``--frames 2.5``
truncated, a negative ``--tau``) is refused before any work, naming the option.
"""

from __future__ import annotations

import argparse
import math


def image_size(text: str) -> tuple[int, int]:
    """'640x480' -> (640, 480): width x height in pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x480, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {text!r}")
    return w, h


def _integer(text: str, low: int) -> int:
    """``text`` as a whole number >= ``low``; '2.0' and '2.5' are refused (no silent truncation)."""
    try:
        value = int(text.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
    return value


def _real(text: str, low: float, *, low_open: bool, high: float = math.inf, high_open: bool = True) -> float:
    """``text`` as a finite number in the range; the message states the range."""
    lo, hi = ("(" if low_open else "[") + f"{low:g}", f"{high:g}" + (")" if high_open else "]")
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    ok = math.isfinite(value) and (value > low if low_open else value >= low) and (
        value < high if high_open else value <= high)
    if not ok:
        raise argparse.ArgumentTypeError(f"expected a number in {lo}, {hi}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """A whole number >= 1 (frame counts, workers, levels, iterations)."""
    return _integer(text, 1)


def nonnegative_int(text: str) -> int:
    """A whole number >= 0 (e.g. ``--texture-px 0``: no texture)."""
    return _integer(text, 0)


def integer_at_least(low: int):
    """The type of a whole number >= ``low`` (e.g. ``--frames-per-reference``, >= 2)."""

    def parse(text: str) -> int:
        return _integer(text, low)

    parse.__name__ = f"integer >= {low}"
    return parse


def positive_float(text: str) -> float:
    """A finite number > 0 (weights, sizes in mm, seconds)."""
    return _real(text, 0.0, low_open=True)


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    return _real(text, 0.0, low_open=False)


def metres_offset(text: str) -> float:
    """One coordinate of an offset from the camera in metres: finite, within 1 m (a value like
    30 is millimetres, and refused saying so)."""
    value = _real(text, -math.inf, low_open=True)
    if abs(value) > 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} is more than 1 m; give metres, not millimetres ({text} mm is "
                                         f"{value / 1000:g} m)")
    return value


def unit_interval(text: str) -> float:
    """A number in [0, 1) (relative tolerances)."""
    return _real(text, 0.0, low_open=False, high=1.0, high_open=True)


def frame_count_fits(flag: str, count: int | None, available: int, what: str) -> None:
    """Raise ValueError naming ``flag`` when ``count`` frames are asked of ``what`` holding ``available``."""
    if count is not None and count > available:
        raise ValueError(f"{flag} {count}: {what} has {available} frames; pass {flag} 1..{available} "
                         "or leave it out to use them all")


def deprecated_alias(new_flag: str):
    """An argparse action for an old option spelling: it stores its value where ``new_flag`` does
    (pass the same ``dest``) and prints ``PROG: warning: OLD is deprecated; use NEW`` to stderr."""

    class DeprecatedAlias(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            import sys

            print(f"{parser.prog}: warning: {option_string} is deprecated; use {new_flag} "
                  f"(e.g. {new_flag.split()[0]} {values})", file=sys.stderr)
            setattr(namespace, self.dest, values)

    return DeprecatedAlias
