"""Checks of the numbers a config, an env option or a checkpoint's saved env state gives: a
real number is not a bool or a string that numpy or `float` would quietly coerce, a range is
two finite numbers in order, and a saved array has the shape and bounds the env saves."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np


def is_real(value: Any) -> bool:
    """A real number (numpy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)


def whole_number(value: Any) -> int | None:
    """`value` as an int when it is a whole number (a float of one included), else None: a
    saved count of 1.5 or NaN is refused, not truncated."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return int(number) if math.isfinite(number) and number.is_integer() else None


def short(value: Any, limit: int = 60) -> str:
    """`repr(value)`, cut to `limit` characters: an error names a value, never echoes a huge one."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


def finite_range(value: Any, name: str) -> tuple[float, float]:
    """`value` as a (low, high) range: two finite real numbers with low <= high."""
    if (
        isinstance(value, str)
        or not isinstance(value, Sequence | np.ndarray)
        or len(value) != 2
        or not all(is_real(v) and math.isfinite(v) for v in value)
        or value[0] > value[1]
    ):
        raise ValueError(
            f"{name} must be [low, high], two finite numbers with low <= high, got {short(value)}"
        )
    return float(value[0]), float(value[1])


def saved_array(
    value: Any,
    shape: tuple[int, ...],
    what: str,
    bound: float = math.inf,
    nonnegative: bool = False,
):
    """`value`, read back from a checkpoint, as a float array of `shape`, finite, within
    +-`bound` and, with `nonnegative`, >= 0: a resumed env takes nothing that it could not
    have saved itself."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"a saved {what} must be numbers, got {short(value)}") from None
    if array.shape != tuple(shape) or not (
        np.isfinite(array).all()
        and (np.abs(array) <= bound).all()
        and not (nonnegative and (array < 0).any())
    ):
        within = f" within +-{bound:g}" if bound < math.inf else ""
        sign = " >= 0" if nonnegative else ""
        largest = np.abs(array).max(initial=0.0)  # NaN where any is NaN
        smallest = f", smallest {array.min(initial=0.0):.3g}" if nonnegative else ""
        raise ValueError(
            f"a saved {what} must be {math.prod(shape)} finite numbers{sign}{within} "
            f"(shape {tuple(shape)}), got shape {array.shape}, largest |value| "
            f"{largest:.3g}{smallest}"
        )
    return array


def saved_flag(value: Any, what: str) -> bool:
    """`value`, read back from a checkpoint, as a truth value: True or False, nothing that
    merely converts to one (a string, a list)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"a saved {what} must be True or False, got {short(value)}")
    return bool(value)


def saved_whole_number(value: Any, what: str, high: int | None = None) -> int:
    """`value`, read back from a checkpoint, as a whole number in 0..`high` (no bound: >= 0)."""
    number = whole_number(value)
    if number is None or number < 0 or (high is not None and number > high):
        bound = ">= 0" if high is None else f"in 0..{high}"
        raise ValueError(f"a saved {what} must be a whole number {bound}, got {short(value)}")
    return number


def set_random_state(random: np.random.RandomState | np.random.Generator, saved: Any) -> None:
    """`random` set to a stream's saved state; one that is not numpy's is refused naming it."""
    try:
        if isinstance(random, np.random.Generator):
            random.bit_generator.state = saved
        else:
            random.set_state(saved)
    except (TypeError, ValueError, IndexError, KeyError) as error:
        raise ValueError(
            f"a saved random stream must be numpy's generator state, got one it refuses "
            f"({type(error).__name__}: {short(str(error))})"
        ) from None
