"""Checks of argument values shared by the library's configs: each refuses a bad value in one line that
names the argument as the caller wrote it (``lr=nan: must be a finite number > 0``).

Imports nothing heavy: configs of every layer use it, and the command line translates the names it
reports into its option names.
"""

from __future__ import annotations

import math
import numbers

from apmgsrn.errors import InvalidArgument

#: Most points one forward or training pass may take: 2^24 points already hold 200 MB of coordinates and
#: activations per layer of 64 units; a larger batch is a typo, not a setting.
MAX_BATCH_SIZE = 1 << 24


def check_int(name: str, value, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int in ``[low, high]`` (either bound may be None).

    Args:
        name: the argument, as the caller names it.
        value: what was given (bools and non-integral numbers are refused).
        low, high: inclusive bounds.

    Returns:
        The value as a plain int.

    Raises:
        InvalidArgument: not an integer, or out of bounds.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InvalidArgument(f"{name}={value!r}: must be an integer", arguments=(name,))
    value = int(value)
    if (low is not None and value < low) or (high is not None and value > high):
        raise InvalidArgument(f"{name}={value!r}: must be {_range_text(low, high)}", arguments=(name,))
    return value


def check_optional_int(name: str, value, low: int | None = None, high: int | None = None) -> int | None:
    """:func:`check_int`, with None allowed (a default chosen elsewhere)."""
    return None if value is None else check_int(name, value, low, high)


def check_number(
    name: str,
    value,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """``value`` as a finite float within bounds.

    Args:
        name: the argument, as the caller names it.
        value: what was given (NaN, infinities, bools and non-numbers are refused).
        low, high: bounds (None: unbounded on that side).
        low_open, high_open: exclude the bound itself.

    Returns:
        The value as a float.

    Raises:
        InvalidArgument: not a finite number, or out of bounds.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise InvalidArgument(f"{name}={value!r}: must be a finite number", arguments=(name,))
    value = float(value)
    below = low is not None and (value <= low if low_open else value < low)
    above = high is not None and (value >= high if high_open else value > high)
    if below or above:
        lower = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
        upper = "" if high is None else f"{'<' if high_open else '<='} {high:g}"
        bounds = " and ".join(text for text in (lower, upper) if text)
        raise InvalidArgument(f"{name}={value!r}: must be a finite number {bounds}", arguments=(name,))
    return value


def check_choice(name: str, value, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices``.

    Raises:
        InvalidArgument: anything else.
    """
    if not isinstance(value, str) or value not in choices:
        raise InvalidArgument(f"{name}={value!r}: must be one of {', '.join(choices)}", arguments=(name,))
    return value


def _range_text(low: int | None, high: int | None) -> str:
    if low is not None and high is not None:
        return f"an integer from {low} to {high}"
    if low is not None:
        return f"an integer >= {low}"
    return f"an integer <= {high}"


def parse_triple(value, name: str) -> tuple[int, int, int]:
    """Three positive sizes from ``R``, ``"R"``, ``"A,B,C"`` (or ``"AxBxC"``) or ``(A, B, C)``; one size means
    a cube.

    Raises:
        InvalidArgument: anything else (named as ``name=``).
    """
    if isinstance(value, str):
        try:
            values = [int(v) for v in value.replace("x", ",").split(",")]
        except ValueError:
            raise InvalidArgument(f"{name}={value!r}: expected an integer or three integers like 16,16,16",
                                  arguments=(name,)) from None
    elif isinstance(value, (int, tuple, list)) and not isinstance(value, bool):
        values = [value] if isinstance(value, int) else list(value)
    else:
        raise InvalidArgument(f"{name}={value!r}: give an integer or three", arguments=(name,))
    if len(values) == 1:
        values = values * 3
    if len(values) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) for v in values) or min(values) < 1:
        raise InvalidArgument(f"{name}={value!r}: expected an integer or three positive integers like 16,16,16",
                              arguments=(name,))
    return tuple(values)
