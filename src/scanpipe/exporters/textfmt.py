"""Vectorised text formatting: numbers to ASCII with numpy, no per-line Python.

Text formats (OBJ) need millions of lines per second. Python's ``%`` formatting manages about
0.5 M faces/s; writing the digits of every column into one ``(rows, width)`` byte matrix and
dropping the padding with one boolean mask is several times faster.

A line is described by a list of parts: ``bytes`` (the same on every row), :class:`Ints`
(non-negative integers) or :class:`Fixed` (floats in fixed-point notation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Ints:
    """A column of non-negative integers, printed without leading zeros."""

    values: NDArray[np.integer]


@dataclass(frozen=True)
class Fixed:
    """A column of finite floats printed as ``-12.345678`` with ``decimals`` digits."""

    values: NDArray[np.floating]
    decimals: int = 6


Part = bytes | Ints | Fixed


def _digits(values: NDArray[np.int64], width: int) -> NDArray[np.uint8]:
    """``(width, n)`` decimal digits (as numbers 0–9) of non-negative integers."""
    digits = np.empty((width, values.size), dtype=np.uint8)
    small = int(values.max(initial=0)) < 2**32
    rest: NDArray[Any] = values.astype(np.uint32 if small else np.int64)
    for k in range(width - 1, -1, -1):
        quotient = rest // 10
        digits[k] = rest - quotient * 10
        rest = quotient
    return digits


def _blank_leading_zeros(chars: NDArray[np.uint8], values: NDArray[np.int64]) -> None:
    """Set the leading-zero places of each value's ``(width, n)`` ASCII digits to 0 (dropped
    later); the last digit always stays."""
    width = chars.shape[0]
    for k in range(width - 1):
        # place k (from the left) is a leading zero when the value has fewer than width−k digits
        # (a multiply by the mask is ~3x faster than a boolean-indexed assignment)
        np.multiply(chars[k], values >= 10 ** (width - 1 - k), out=chars[k])


def _width(top: int) -> int:
    return max(1, len(str(top)))


def render_lines(rows: int, parts: Sequence[Part]) -> bytes:
    """Format ``rows`` lines, each the concatenation of ``parts``, ending with ``\\n``."""
    if rows == 0:
        return b""
    plan: list[tuple[Part, int, object]] = []
    for part in parts:
        if isinstance(part, bytes):
            if b"\0" in part:
                raise ValueError("literal parts must not contain NUL bytes")
            plan.append((part, len(part), None))
        elif isinstance(part, Ints):
            values = np.asarray(part.values).astype(np.int64, copy=False).ravel()
            if values.size != rows:
                raise ValueError(f"column has {values.size} rows, expected {rows}")
            if values.size and int(values.min()) < 0:
                raise ValueError("Ints formats non-negative integers only")
            plan.append((part, _width(int(values.max(initial=0))), values))
        else:
            x = np.asarray(part.values, dtype=np.float64).ravel()
            if x.size != rows:
                raise ValueError(f"column has {x.size} rows, expected {rows}")
            scale = 10 ** part.decimals
            quantised = np.rint(np.abs(x) * scale).astype(np.int64)
            whole = quantised // scale
            negative = (x < 0) & (quantised != 0)
            width = 1 + _width(int(whole.max(initial=0))) + (
                1 + part.decimals if part.decimals else 0)
            plan.append((part, width, (whole, quantised % scale, negative)))
    line_width = sum(w for _, w, _ in plan) + 1
    # Planar (column-major) buffer: each column is written contiguously, and padding is NUL,
    # which one transpose and one comparison remove.
    chars = np.empty((line_width, rows), dtype=np.uint8)
    cache: dict[int, NDArray[np.uint8]] = {}
    col = 0
    for part, width, data in plan:
        block = chars[col:col + width]
        if isinstance(part, bytes):
            block[...] = np.frombuffer(part, dtype=np.uint8)[:, None]
        elif isinstance(part, Ints):
            assert isinstance(data, np.ndarray)
            key = id(part.values)
            if key not in cache:
                digits = _digits(data, width) + np.uint8(48)
                _blank_leading_zeros(digits, data)
                cache[key] = digits
            block[...] = cache[key]
        else:
            whole, frac, negative = cast(
                tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]], data)
            whole_width = width - 1 - (1 + part.decimals if part.decimals else 0)
            block[0] = np.where(negative, np.uint8(ord("-")), np.uint8(0))
            digits = _digits(whole, whole_width) + np.uint8(48)
            _blank_leading_zeros(digits, whole)
            block[1:1 + whole_width] = digits
            if part.decimals:
                block[1 + whole_width] = ord(".")
                block[2 + whole_width:] = _digits(frac, part.decimals) + np.uint8(48)
        col += width
    chars[col] = ord("\n")
    # bytes.translate drops the NULs in one C pass, faster than a numpy boolean mask
    return np.ascontiguousarray(chars.T).tobytes().translate(None, b"\0")


def float_rows(prefix: bytes, values: NDArray[np.floating], decimals: int = 6) -> bytes:
    """Lines ``prefix a b c`` for each row of a 2-D float array."""
    parts: list[Part] = [prefix]
    for j in range(values.shape[1]):
        if j:
            parts.append(b" ")
        parts.append(Fixed(values[:, j], decimals))
    return render_lines(values.shape[0], parts)
