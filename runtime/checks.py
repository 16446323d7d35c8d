"""Checks of values from users: the one place that says what a usable number, array or count is.

Every input is checked in the precision it is used in: lighting, materials and cameras end up
in float32 (shader uniforms, the CPU shading's products), so a value that is finite in float64
but overflows float32 (``1e39``) is as unusable as NaN.  Failures are one-line project errors
naming the field: :class:`~prt.runtime.errors.InputError`, or
:class:`~prt.runtime.errors.ArgumentTypeError` for a value of the wrong type.
"""

from __future__ import annotations

import operator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ArgumentTypeError, InputError

__all__ = ["FLOAT32_MAX", "finite_array", "check_finite", "positive_int", "count_nonfinite", "read_text", "unusable_json_number"]

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""The largest finite float32: a number beyond it becomes Inf where the runtime uses it."""


def _clip(value: Any, limit: int = 60) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def finite_array(value: Any, name: str, shape: tuple | None = None, dtype=np.float32, *, minimum: float | None = None) -> np.ndarray:
    """``value`` as a float64 array whose every element is finite in ``dtype``.

    Parameters
    ----------
    value : array_like
    name : str
        The field or argument, for the message (e.g. ``"Material.albedo"``).
    shape : tuple, optional
        Required shape (``-1`` for any length along an axis).
    dtype : numpy dtype
        The precision the value is used in (float32: shader uniforms, CPU shading).
    minimum : float, optional
        Least allowed value.

    Raises
    ------
    ArgumentTypeError
        If ``value`` is not numbers (a string, None, an object).
    InputError
        If the shape is wrong, or a value is NaN, Inf, beyond ``dtype`` or below ``minimum``.
    """
    if isinstance(value, (str, bytes)) or value is None:
        raise ArgumentTypeError(f"{name} must be numbers, got {_clip(value)}")
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ArgumentTypeError(f"{name} must be numbers, got {_clip(value)}") from None
    if shape is not None and (arr.ndim != len(shape) or any(s not in (-1, a) for s, a in zip(shape, arr.shape))):
        want = "(" + ", ".join("n" if s == -1 else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise InputError(f"{name} must have shape {want}, got {arr.shape}")
    check_finite(arr, name, dtype)
    if minimum is not None and arr.size and float(arr.min()) < minimum:
        raise InputError(f"{name} must be >= {minimum:g}, got {_clip(value)}")
    return arr


def check_finite(arr: np.ndarray, name: str, dtype=np.float32) -> None:
    """InputError unless every element of ``arr`` is finite, also once converted to ``dtype``."""
    limit = float(np.finfo(dtype).max)
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(arr) <= limit)  # NaN compares False
    if bad.any():
        first = arr[np.unravel_index(int(np.argmax(bad)), arr.shape)] if arr.ndim else arr
        what = "NaN or Inf" if not np.isfinite(first) else f"beyond the {np.dtype(dtype).name} range (|x| <= {limit:.4g})"
        raise InputError(f"{name}: {int(bad.sum())} value(s) {what}, e.g. {float(first)!r}")


def count_nonfinite(arr: np.ndarray) -> int:
    """How many elements of ``arr`` are NaN or Inf."""
    return int(arr.size - np.count_nonzero(np.isfinite(arr)))


def positive_int(value: Any, name: str, *, minimum: int = 1, maximum: int | None = None) -> int:
    """``value`` as an int in ``[minimum, maximum]``; bools, floats and strings are refused.

    Raises
    ------
    ArgumentTypeError
        If ``value`` is not an integer (``operator.index`` fails, or it is a bool).
    InputError
        If it is out of range.
    """
    if isinstance(value, bool):
        raise ArgumentTypeError(f"{name} must be an integer, got {value!r}")
    try:
        number = operator.index(value)
    except TypeError:
        raise ArgumentTypeError(f"{name} must be an integer, got {_clip(value)}") from None
    if number < minimum or (maximum is not None and number > maximum):
        bound = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"
        raise InputError(f"{name} must be {bound}, got {number}")
    return int(number)


def read_text(path, what: str) -> str:
    """The UTF-8 text of a user's file (a scene's GLSL), or an InputError naming it."""
    try:
        data = Path(path).read_bytes()
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise InputError(f"{path}: cannot read {what} ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: {what} is not UTF-8 text (byte {exc.start})") from None


def unusable_json_number(value: Any, parts: tuple = ()) -> tuple[list, str] | None:
    """The first number of parsed JSON that the runtime cannot use, as (field path, message):
    a float not finite in float32 (lighting, camera and material reach shaders in float32, where
    ``1e39`` is Inf) or an integer beyond int64; None if every number is usable."""
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        if isinstance(value, float) and not abs(value) <= FLOAT32_MAX:
            return list(parts), f"number {value!r} is not finite in float32 (|x| <= {FLOAT32_MAX:.4g})"
        if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**63:
            return list(parts), f"integer {_clip(value, 40)} is out of range (64-bit)"
        return None
    for key, item in items:
        found = unusable_json_number(item, (*parts, key))
        if found is not None:
            return found
    return None
