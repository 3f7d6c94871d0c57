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

#: The range of every integer a user gives (int64, what tensors, files and numpy take).
INT64_MIN, INT64_MAX = -(1 << 63), (1 << 63) - 1

#: Most iterations of any training loop: 10^9 iterations take weeks even on a GPU; more is a typo.
MAX_ITERATIONS = 10**9

#: Largest finite float32: values (fill values, offsets, error bounds) become float32 next to the data.
FLOAT32_MAX = 3.4028234663852886e38


def check_int(name: str, value, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int in ``[low, high]`` (either bound may be None) and within int64.

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
    problem = _int_problem(value, low, high)
    if problem:
        raise InvalidArgument(f"{name}={value!r}: {problem}", arguments=(name,))
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


def int_type(low: int | None = None, high: int | None = None):
    """An argparse ``type``: the text as an int in ``[low, high]``, and always within int64.

    A text that is no integer raises ``ValueError`` (argparse then says ``invalid int value``); one out of
    range raises ``argparse.ArgumentTypeError`` naming the range.
    """

    def parse(text: str) -> int:
        value = int(text)  # ValueError for "abc", "1e3", "2.5" and texts of thousands of digits
        problem = _int_problem(value, low, high)
        if problem:
            raise _type_error(f"{text}: {problem}")
        return value

    parse.__name__ = "int"  # what argparse names in "invalid int value"
    return parse


def number_type(low: float | None = None, high: float | None = None, low_open: bool = False,
                high_open: bool = False):
    """An argparse ``type``: the text as a finite float within bounds (NaN, infinities and overflows such as
    ``1e400`` are refused), as :func:`check_number` checks a Python value."""

    def parse(text: str) -> float:
        value = float(text)  # ValueError for "abc"
        try:
            return check_number(text, value, low, high, low_open, high_open)
        except InvalidArgument as exc:
            raise _type_error(f"{text}: {str(exc).split(': ', 1)[1]}") from None

    parse.__name__ = "float"
    return parse


def _type_error(message: str) -> Exception:
    import argparse

    return argparse.ArgumentTypeError(message)


def check_choice(name: str, value, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices``.

    Raises:
        InvalidArgument: anything else.
    """
    if not isinstance(value, str) or value not in choices:
        raise InvalidArgument(f"{name}={value!r}: must be one of {', '.join(choices)}", arguments=(name,))
    return value


def _range_text(low: int | None, high: int | None) -> str:
    """``"an integer from 1 to 10"``, ``"an integer >= 1"``...; int64's own ends are not repeated."""
    low = None if low is None or low <= INT64_MIN else low
    high = None if high is None or high >= INT64_MAX else high
    if low is not None and high is not None:
        return f"an integer from {low} to {high}"
    if low is not None:
        return f"an integer >= {low}"
    if high is not None:
        return f"an integer <= {high}"
    return "an integer"


def _int_problem(value: int, low: int | None, high: int | None) -> str | None:
    """Why ``value`` is out of ``[low, high]`` and int64, or None."""
    if (low is not None and value < low) or (high is not None and value > high):
        return f"must be {_range_text(low, high)}"
    if not INT64_MIN <= value <= INT64_MAX:
        return f"must be {_range_text(low, high)} within int64 ({INT64_MIN} to {INT64_MAX})"
    return None


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
