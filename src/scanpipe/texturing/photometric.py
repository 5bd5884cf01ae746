"""What several frames say about one face: colour samples, global levelling, outlier rejection.

For every face its best ``max_views`` frames by score
(:class:`~scanpipe.texturing.projective.FaceScores`) are sampled at
the face's centroid (:func:`sample_views`: a 4 × 4 pixel mean from a shrunk image), each
sample packed in one uint32 (:func:`pack_levels`: a quarter of three float32). These
overlaps serve twice (Waechter et al. 2014, sections 4.1 and 5):

- **global levelling**: each face seen by frames a and b gives
  ``log g_a + log I_a = log g_b + log I_b`` per channel; the per-frame, per-channel gains (an
  exposure gain times a white balance) solve all of them in least squares
  (:func:`scanpipe.texturing.exposure.solve_gains`);
- **photometric outliers**: where at least three frames see a face, a frame whose levelled
  colour lies more than ``max(outlier_levels, 3 × MAD)`` from the median of the others (a
  person walking through that frame, a reflection) is struck out for that face.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.texturing.exposure import sample_pixels_at
from scanpipe.texturing.frames import REDUCED_FACTOR, FrameSet, worker_count
from scanpipe.threads import thread_pool

F32 = NDArray[np.float32]
FloatT = TypeVar("FloatT", np.float32, np.float64)
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U32 = NDArray[np.uint32]
#: Frame numbers per face (int32 as kept by FaceScores, or int64).
FrameIds = NDArray[np.signedinteger[Any]]

#: Colours this dark or bright are clipped in some channel: no use for gains.
USABLE_LEVELS = (4.0, 251.0)
#: Faces :func:`sample_views` projects at once (bounded temporaries per thread).
SAMPLE_CHUNK = 1 << 18
#: Faces judged at once by :func:`photometric_outliers` (cache-sized blocks).
OUTLIER_CHUNK = 1 << 16
#: Candidates per face up to which :func:`sort_small_axis0` uses a sorting network.
NETWORK_SLOTS = 8


#: The top byte of a packed sample (:func:`pack_levels`): set for every sampled colour, so
#: that 0 means "not sampled".
SAMPLED = np.uint32(0xFF000000)


def pack_levels(colour: NDArray[np.floating]) -> U32:
    """``(..., 3)`` colours in 8-bit levels (NaN = not sampled) as ``(...)`` uint32: the three
    levels in the low bytes (rounded, clipped to 0–255; as recorded, whole levels) and
    :data:`SAMPLED` on top; 0 where not sampled."""
    colour = np.asarray(colour)
    sampled = np.isfinite(colour).all(axis=-1)
    levels = np.clip(np.rint(np.nan_to_num(colour)), 0, 255).astype(np.uint32)
    packed = levels[..., 0] | (levels[..., 1] << 8) | (levels[..., 2] << 16) | SAMPLED
    return np.asarray(np.where(sampled, packed, np.uint32(0)), dtype=np.uint32)


def unpack_levels(packed: U32) -> F32:
    """:func:`pack_levels` undone: ``(..., 3)`` float32 levels, NaN where not sampled."""
    packed = np.ascontiguousarray(packed, dtype=np.uint32)
    # a little-endian uint32's bytes in order: the three levels, then the flag
    stored = packed if np.little_endian else packed.byteswap()
    colour = stored.view(np.uint8).reshape(*packed.shape, 4)[..., :3].astype(np.float32)
    colour[packed == 0] = np.nan
    return colour


@dataclass
class Views:
    """Per face its candidate frames (best first, −1 = none) and their sampled colours."""

    frame: FrameIds  # (faces, K)
    # (faces, K) the colours in 8-bit levels (as recorded, before gains), packed
    # (:func:`pack_levels`; 0 = not sampled): 4 bytes a sample instead of three float32
    packed: U32

    @classmethod
    def from_levels(cls, frame: FrameIds, colour: NDArray[np.floating]) -> Views:
        """From ``(faces, K, 3)`` colours in levels (NaN = not sampled; rounded)."""
        return cls(frame, pack_levels(colour))

    @property
    def colour(self) -> F32:
        """``(faces, K, 3)`` float32 levels, NaN where not sampled (a copy: for small sets)."""
        return unpack_levels(self.packed)

    @property
    def count(self) -> I64:
        """How many candidates each face has."""
        return np.asarray((self.frame >= 0).sum(axis=1), dtype=np.int64)


def packed_image(image: NDArray[np.uint8]) -> U32:
    """A BGR image as ``(h, w)`` uint32 pixels packed as :func:`pack_levels` packs (one
    look-up per sample instead of three bytes)."""
    bgra = np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_BGR2BGRA))  # alpha 255
    packed = bgra.view(np.uint32).reshape(bgra.shape[:2])
    if not np.little_endian:  # the bytes B, G, R, A are the value's high to low byte there
        packed = packed.byteswap()
    return np.asarray(packed, dtype=np.uint32)


def sample_views(points: F64, frame: FrameIds, frames: FrameSet) -> U32:
    """``(faces, K)`` packed colours (:func:`pack_levels`; BGR order as decoded) of
    ``points[f]`` in frame ``frame[f, k]``; 0 where there is no candidate or the point leaves
    the image.

    Slot by slot, the faces are grouped by frame (a stable sort of small frame numbers) and
    each frame's faces are sampled in pieces of :data:`SAMPLE_CHUNK` on a thread per core
    (a 360° frame holds millions: whole, its projection's temporaries were ~0.5 GB a thread).
    """
    from scanpipe.texturing.projective import project_valid_columns

    n_faces, k = frame.shape
    colour = np.zeros((n_faces, k), dtype=np.uint32)
    # float32 columns: projected into up to K frames each (scanpipe.camera.project_columns)
    columns = [np.ascontiguousarray(points[:, c], dtype=np.float32) for c in range(3)]
    images: dict[int, U32] = {}  # each frame's packed pixels, made once

    def load(i: int) -> None:
        images[i] = packed_image(frames.reduced(i))

    with thread_pool(worker_count(len(frames))) as pool:
        for slot in range(k):
            column = frame[:, slot]
            # frame numbers are small: a stable sort of int8 or int16 is a radix sort (of one
            # byte: one pass)
            small = (np.int8 if len(frames) < 2 ** 7 else np.int16 if len(frames) < 2 ** 15
                     else None)
            order = np.argsort(column if small is None else column.astype(small),
                               kind="stable")
            # where each frame's faces start in ``order`` (after those with none, −1): counted
            # (a searchsorted of int64 frame numbers cast the whole column every slot)
            bounds = np.cumsum(np.bincount(column + 1, minlength=len(frames) + 1))
            # each frame decoded once (kept), before its pieces are spread over the threads
            list(pool.map(load, [i for i in np.flatnonzero(np.diff(bounds)).tolist()
                                 if i not in images]))

            def sample(piece: tuple[int, int, int], slot: int = slot, order: I64 = order
                       ) -> None:
                i, start, stop = piece
                face = order[start:stop]
                x, y, z = (column[face] for column in columns)
                u, v, _, valid = project_valid_columns(x, y, z, frames.cameras[i],
                                                       float(frames.beta_deg[i]), 0.0)
                colour[face[valid], slot] = sample_pixels_at(images[i], u[valid], v[valid],
                                                             REDUCED_FACTOR)

            list(pool.map(sample, [(i, start, min(start + SAMPLE_CHUNK, int(bounds[i + 1])))
                                   for i in range(len(frames))
                                   for start in range(int(bounds[i]), int(bounds[i + 1]),
                                                      SAMPLE_CHUNK)]))
    return colour


def overlap_pairs(views: Views, max_pairs: int = 200_000, seed: int = 0
                  ) -> tuple[I64, I64, F64, F64]:
    """``(frame_a, frame_b, colour_a, colour_b)``: each face's best frame against each other
    frame that sees it, where both colours are unclipped; from a random subset of faces, so
    that there are at most about ``max_pairs``."""
    n_faces, k = views.frame.shape
    rows = np.arange(n_faces)
    per_face = max(1, k - 1)
    if n_faces * per_face > max_pairs:
        rows = np.sort(np.random.default_rng(seed).choice(n_faces, max_pairs // per_face,
                                                         replace=False))
    frame, colour = views.frame[rows], unpack_levels(views.packed[rows])
    lo, hi = USABLE_LEVELS
    with np.errstate(invalid="ignore"):
        usable = (frame >= 0) & np.all((colour > lo) & (colour < hi), axis=2)
    ok = usable[:, :1] & usable[:, 1:] & (frame[:, 1:] != frame[:, :1])  # (rows, k − 1)
    face, slot = np.nonzero(ok)
    return (frame[face, 0].astype(np.int64), frame[face, slot + 1].astype(np.int64),
            colour[face, 0].astype(np.float64),
            colour[face, slot + 1].astype(np.float64))


def nan_median(values: NDArray[FloatT], axis: int) -> NDArray[FloatT]:
    """Median along ``axis`` ignoring NaN (NaN where all are NaN): sort, NaNs last, take the
    middle of the finite ones (numpy's nanmedian goes through masked arrays: many times
    slower on millions of short rows)."""
    ordered = np.sort(values, axis=axis)
    count = np.isfinite(ordered).sum(axis=axis, keepdims=True)
    lower = np.take_along_axis(ordered, np.maximum((count - 1) // 2, 0), axis=axis)
    upper = np.take_along_axis(ordered, np.maximum(count // 2, 0), axis=axis)
    return np.asarray(np.where(count > 0, 0.5 * (lower + upper), np.nan), dtype=values.dtype)


def sort_small_axis0(values: NDArray[FloatT]) -> NDArray[FloatT]:
    """``values`` sorted along a short first axis, in place (no NaN: they do not order):
    for up to :data:`NETWORK_SLOTS` an odd-even transposition network of elementwise
    minima and maxima over whole slices, 4× faster than ``np.sort`` of millions of short
    rows; else ``np.sort``."""
    count = values.shape[0]
    if count > NETWORK_SLOTS:
        values.sort(axis=0)
        return values
    low = np.empty_like(values[0])
    for round_ in range(count):
        for j in range(round_ % 2, count - 1, 2):
            np.minimum(values[j], values[j + 1], out=low)
            np.maximum(values[j], values[j + 1], out=values[j + 1])
            values[j] = low
    return values


def photometric_outliers(views: Views, gains: F64, outlier_levels: float = 40.0
                         ) -> NDArray[np.bool_]:
    """``(faces, K)`` True where a candidate's levelled colour disagrees with the others.

    Only faces with at least three sampled candidates are judged: the median of the levelled
    colours per channel is the consensus; a candidate further than
    ``max(outlier_levels, 3 × 1.4826 × MAD)`` (largest channel) from it is an outlier.
    """
    frame = views.frame
    # a candidate is sampled in all channels or none; counted column by column (a sum
    # along rows of six is 4× slower)
    nonzero = views.packed != 0
    sampled = np.zeros(len(frame), np.int32)
    for slot in range(frame.shape[1]):
        np.add(sampled, nonzero[:, slot], out=sampled)
    del nonzero
    judged = np.flatnonzero(sampled >= 3)
    outlier = np.zeros(frame.shape, dtype=bool)
    if len(judged) == 0:
        return outlier

    slots = frame.shape[1]
    # A face whose levelled colours all lie within ``outlier_levels`` of each other in every
    # channel has no outlier (no colour is further than that from a median between them, in
    # float32 as well): most faces, found from the recorded levels' range per channel (one
    # byte each) and the smallest and largest gain; ``margin`` covers the float32 roundings
    # of the levels below (≤ 3 of ≤ 255 × the largest gain)
    gain_low, gain_high = np.min(gains, axis=0), np.max(gains, axis=0)
    margin = 1e-4 * 255.0 * max(1.0, float(gain_high.max()))
    not_sampled = np.uint32(0xFFFFFFFF)  # the lowest level is taken over these: none

    def judge(start: int) -> None:
        faces = judged[start:start + OUTLIER_CHUNK]
        packed = np.ascontiguousarray(views.packed[faces].T)  # (candidate, face)
        stored = packed if np.little_endian else packed.byteswap()
        levels = stored.view(np.uint8).reshape(slots, len(faces), 4)
        high = levels[0].copy()  # not sampled: 0, never the highest
        for slot in range(1, slots):
            np.maximum(high, levels[slot], out=high)
        levels = np.where(packed == 0, not_sampled, stored).view(np.uint8).reshape(
            slots, len(faces), 4)
        low = levels[0].copy()
        for slot in range(1, slots):
            np.minimum(low, levels[slot], out=low)
        bound = high[:, :3] * gain_high - low[:, :3] * gain_low
        uneven = np.flatnonzero(bound.max(axis=1) > outlier_levels - margin)
        if len(uneven) == 0:
            return
        faces = faces[uneven]
        frame_of, colour = frame[faces], unpack_levels(views.packed[faces])
        # (candidate, face, channel) float32: each candidate a contiguous block for the
        # sorting network; not sampled: +inf, which sorts last as NaN would
        level = np.empty((slots, len(faces), 3), np.float32)
        for slot in range(slots):
            np.multiply(colour[:, slot], gains[np.maximum(frame_of[:, slot], 0)],
                        out=level[slot], casting="same_kind")
        missing = np.isnan(level[:, :, 0])
        level[missing] = np.inf
        # the median with the count known (every face here has ≥ 3 samples, in all
        # channels): the middle of the sorted finite values
        rows = np.arange(len(faces))
        lower, upper = (sampled[faces] - 1) // 2, sampled[faces] // 2
        ordered = sort_small_axis0(level.copy())
        median = 0.5 * (ordered[lower, rows] + ordered[upper, rows])  # (faces, channel)
        # the largest channel's deviation, +inf where not sampled
        deviation = np.abs(level[:, :, 0] - median[:, 0])
        for channel in range(1, 3):
            np.maximum(deviation, np.abs(level[:, :, channel] - median[:, channel]),
                       out=deviation)
        ordered = sort_small_axis0(deviation.copy())
        mad = 0.5 * (ordered[lower, rows] + ordered[upper, rows]) * 1.4826
        limit = np.maximum(outlier_levels, 3 * mad)
        outlier[faces] = ((deviation > limit) & ~missing).T

    # blocks of faces on a thread per core (numpy releases the GIL; each writes its own rows)
    with thread_pool(worker_count(-(-len(judged) // OUTLIER_CHUNK))) as pool:
        list(pool.map(judge, range(0, len(judged), OUTLIER_CHUNK)))
    return outlier
