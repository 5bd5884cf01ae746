"""Vectorised text formatting: numbers to ASCII with numpy, no per-line Python.

Text formats (OBJ) need millions of lines per second. Python's ``%`` formatting manages about
0.5 M faces/s. Here a number becomes a few 32-bit *words* of ASCII, each one lookup in a small
table (three or four digits at a time, no per-digit arithmetic), with NUL where a leading zero
or an unused place is dropped. A line is a row of words, a one-byte separator after a number
goes into the spare top byte of the number's last word, and the NUL bytes are removed at the
end in one C pass (``bytes.translate``). Rows are formatted in blocks, column by column (the
words of one column are contiguous), and each block transposed once (OpenCV), so the
temporaries stay small whatever the number of rows.

A line is described by a list of parts: ``bytes`` (the same on every row), :class:`Ints`
(non-negative integers) or :class:`Fixed` (floats in fixed-point notation: ``%.Nf``, with a
minus sign only on a non-zero result).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

U32 = NDArray[np.uint32]
#: Rows formatted at once: big enough for numpy's per-call cost not to matter, small enough
#: for a block to stay in the cache.
BLOCK_ROWS = 1 << 15


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


def _words(chars: NDArray[np.integer]) -> U32:
    """``(n, 4)`` byte values to little-endian words (byte 0 is the first character)."""
    return np.ascontiguousarray(chars, dtype=np.uint8).view("<u4").ravel().astype(np.uint32)


@lru_cache(maxsize=1)
def _tables() -> dict[str, U32]:
    """The digit tables, ASCII in little-endian words (NUL where nothing is printed).

    - ``units[c + 1000·padded]``: the last three digits of an integer in bytes 0–2 (byte 3
      spare); without ``padded`` leading zeros are NUL but the last digit stays (0 → "0").
    - ``high[c + 10000·padded]``: four more significant digits; without ``padded`` leading
      zeros are NUL and 0 is all NUL.
    - ``signed[w + 1000·negative]``: a whole part below 1000 right-aligned in four bytes,
      the minus sign just before its first digit.
    - ``point[f]``: ``.`` and three decimals.
    """
    def digits(values: NDArray[np.int64], count: int) -> NDArray[np.int64]:
        places = 10 ** np.arange(count - 1, -1, -1)
        return np.asarray(values[:, None] // places % 10 + ord("0"), dtype=np.int64)

    def shown(values: NDArray[np.int64], count: int, keep_last: bool) -> NDArray[np.bool_]:
        places = 10 ** np.arange(count - 1, -1, -1)
        visible = values[:, None] >= places
        if keep_last:
            visible[:, -1] = True
        return np.asarray(visible)

    three, four = np.arange(1000), np.arange(10000)
    zero = np.zeros((1000, 1), np.int64)
    d3, d4 = digits(three, 3), digits(four, 4)
    units = np.concatenate([_words(np.hstack([np.where(shown(three, 3, True), d3, 0), zero])),
                            _words(np.hstack([d3, zero]))])
    high = np.concatenate([_words(np.where(shown(four, 4, False), d4, 0)), _words(d4)])
    plain = np.hstack([zero, np.where(shown(three, 3, True), d3, 0)])
    first = np.argmax(plain > 0, axis=1)  # the first printed byte
    minus = plain.copy()
    minus[np.arange(1000), first - 1] = ord("-")
    signed = np.concatenate([_words(plain), _words(minus)])
    point = _words(np.hstack([np.full((1000, 1), ord(".")), d3]))
    return {"units": units, "high": high, "signed": signed, "point": point}


def _int_word_count(top: int) -> int:
    digits = len(str(top))
    return 1 + max(0, -(-(digits - 3) // 4))


def _int_words(values: NDArray[np.integer], count: int, out: U32) -> None:
    """Write the ``count`` words of each integer (most significant first) into the rows of
    ``out``; ``values`` below 10⁹ use 32-bit arithmetic."""
    tables = _tables()
    rest: NDArray[Any] = values.astype(np.uint32 if count <= 2 else np.int64)
    higher = rest // 1000
    np.take(tables["units"], (rest - higher * 1000) + 1000 * np.minimum(higher, 1),
            out=out[count - 1])
    rest = higher
    for k in range(count - 2, -1, -1):
        higher = rest // 10000
        np.take(tables["high"], (rest - higher * 10000) + 10000 * np.minimum(higher, 1),
                out=out[k])
        rest = higher


def _fixed_word_count(top_whole: int, decimals: int) -> int:
    whole = 1 if top_whole < 1000 else 1 + _int_word_count(top_whole)
    return whole + (0 if decimals == 0 else 1 + -(-(decimals - min(3, decimals)) // 3))


def _fixed_words(values: NDArray[np.float64], decimals: int, top_whole: int,
                 out: U32) -> None:
    """Write the words of ``%.{decimals}f`` into the rows of ``out``: the whole part (with
    the sign; a sign word of its own from 1000 up), ``.`` and three decimals, then the other
    decimals three at a time."""
    tables = _tables()
    scale = 10 ** decimals
    quantised = np.rint(np.abs(values) * scale).astype(np.int64)
    negative = (values < 0) & (quantised != 0)
    whole = quantised // scale
    if top_whole < 1000:
        np.take(tables["signed"], whole + 1000 * negative, out=out[0])
        row = 1
    else:
        out[0] = np.where(negative, np.uint32(ord("-")), np.uint32(0))
        count = _int_word_count(top_whole)
        _int_words(whole, count, out[1:1 + count])
        row = 1 + count
    if decimals == 0:
        return
    frac = quantised - whole * scale
    width = min(3, decimals)
    group = frac // 10 ** (decimals - width) * 10 ** (3 - width)
    np.take(tables["point"], group, out=out[row])
    if width < 3:  # drop the zeros the shift to three places added
        out[row] &= np.uint32((1 << (8 * (1 + width))) - 1)
    done = width
    while done < decimals:
        row += 1
        width = min(3, decimals - done)
        group = frac // 10 ** (decimals - done - width) % 10 ** width * 10 ** (3 - width)
        np.take(tables["units"], 1000 + group, out=out[row])
        if width < 3:
            out[row] &= np.uint32((1 << (8 * width)) - 1)
        done += width


@dataclass
class _Column:
    """One part of a line: where its words start, how many, and how to make them."""

    part: Part
    row: int
    count: int
    values: NDArray[Any] | None = None  # the numbers, one contiguous array
    top: int = 0  # Fixed: the largest whole part
    literal: U32 | None = None  # bytes: its words; None for one byte folded into a number


def _plan(rows: int, parts: Sequence[Part]) -> tuple[list[_Column], int]:
    """Check the parts and lay a line out in words; returns the columns and words per line."""
    columns: list[_Column] = []
    row = 0
    spare = False  # the last word is a number's, with its top byte free
    for part in [*parts, b"\n"]:
        if isinstance(part, bytes):
            if b"\0" in part:
                raise ValueError("literal parts must not contain NUL bytes")
            if len(part) == 1 and spare:
                columns.append(_Column(part, row - 1, 0))
            else:
                literal = _words(np.frombuffer(part + b"\0" * (-len(part) % 4), np.uint8)
                                 .reshape(-1, 4))
                columns.append(_Column(part, row, len(literal), literal=literal))
                row += len(literal)
            spare = False
            continue
        if isinstance(part, Ints):
            values = np.ascontiguousarray(part.values).ravel()
            if values.size != rows:
                raise ValueError(f"column has {values.size} rows, expected {rows}")
            if int(values.min()) < 0:
                raise ValueError("Ints formats non-negative integers only")
            column = _Column(part, row, _int_word_count(int(values.max())), values)
            spare = True
        else:
            values = np.ascontiguousarray(part.values, dtype=np.float64).ravel()
            if values.size != rows:
                raise ValueError(f"column has {values.size} rows, expected {rows}")
            scale = 10 ** part.decimals
            top = int(np.rint(np.abs(values).max() * scale)) // scale
            column = _Column(part, row, _fixed_word_count(top, part.decimals), values, top)
            # the last word has a free top byte unless it is a signed whole part (no
            # decimals, below 1000) or "." and three decimals
            spare = top >= 1000 if part.decimals == 0 else part.decimals != 3
        columns.append(column)
        row += column.count
    return columns, row


def render_lines(rows: int, parts: Sequence[Part]) -> bytes:
    """Format ``rows`` lines, each the concatenation of ``parts``, ending with ``\\n``."""
    return b"".join(iter_blocks(rows, parts))


def iter_blocks(rows: int, parts: Sequence[Part]) -> Iterator[bytes]:
    """:func:`render_lines` as consecutive blocks of whole lines, each made when asked for: a
    caller that writes (or hashes) and drops each block holds one block of text, not the
    whole text."""
    if rows == 0:
        return
    columns, width = _plan(rows, parts)
    words = np.empty((width, min(rows, BLOCK_ROWS)), dtype=np.uint32)
    for start in range(0, rows, BLOCK_ROWS):
        stop = min(rows, start + BLOCK_ROWS)
        block = words[:, :stop - start]
        done: dict[int, int] = {}  # a number repeated in a line (v/vt/v) is formatted once
        # numbers first: a repeated one is copied before separators go into spare bytes
        for column in sorted(columns, key=lambda c: c.values is None):
            target = block[column.row:column.row + column.count]
            if column.literal is not None:
                target[...] = column.literal[:, None]
            elif column.values is None:  # one byte into the previous number's spare byte
                assert isinstance(column.part, bytes)
                block[column.row] |= np.uint32(column.part[0] << 24)
            elif id(column.part) in done:
                target[...] = block[done[id(column.part)]:][:column.count]
            else:
                done[id(column.part)] = column.row
                values = column.values[start:stop]
                if isinstance(column.part, Ints):
                    _int_words(values, column.count, target)
                elif isinstance(column.part, Fixed):
                    _fixed_words(values, column.part.decimals, column.top, target)
        lines = cv2.transpose(np.ascontiguousarray(block).view(np.int32))
        yield lines.tobytes().translate(None, b"\0")


def float_rows(prefix: bytes, values: NDArray[np.floating], decimals: int = 6
               ) -> Iterator[bytes]:
    """Lines ``prefix a b c`` for each row of a 2-D float array (as :func:`iter_blocks`)."""
    parts: list[Part] = [prefix]
    for j in range(values.shape[1]):
        if j:
            parts.append(b" ")
        parts.append(Fixed(values[:, j], decimals))
    return iter_blocks(values.shape[0], parts)
