"""Even out exposure and white balance: one gain per frame and colour channel, from overlaps.

A surface point seen in frames a and b (a face's centroid in two of its candidate frames,
:mod:`scanpipe.texturing.photometric`) gives, per channel, one equation
``log g_a + log I_a = log g_b + log I_b``. The gains solve all equations in least squares with
a weak pull towards 1 (which fixes the free overall level), once more after dropping outliers
(misregistration, specular spots), and are limited to [0.5, 2]. Per channel, so a camera's
white balance is levelled with its exposure.
"""

from __future__ import annotations

from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.texturing.visibility import mesh_edges

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
PixelT = TypeVar("PixelT", np.uint8, np.uint32)


def shared_edges(faces: NDArray[np.integer]) -> tuple[I64, I64]:
    """Pairs of faces sharing an edge: ``(face_pairs (E, 2), edge_vertices (E, 2))``.

    Edges used by more than two faces (non-manifold) are left out. (The texture stage takes
    both from its one :class:`~scanpipe.texturing.visibility.MeshEdges`.)
    """
    faces = np.asarray(faces, dtype=np.int64)
    edges = mesh_edges(faces)
    return edges.pairs(), edges.vertices(faces)


def shrink(image: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """``image`` reduced ``factor`` times by area averaging (a cheap local mean)."""
    h, w = image.shape[:2]
    return np.asarray(cv2.resize(image, (w // factor, h // factor),
                                 interpolation=cv2.INTER_AREA), dtype=np.uint8)


def sample_mean_colour(small: NDArray[np.uint8], uv: F64, factor: int) -> F64:
    """Colours at full-size pixel positions ``uv`` from an image shrunk by ``factor``."""
    return np.asarray(sample_pixels(small, uv, factor), dtype=np.float64)


def sample_pixels(small: NDArray[np.uint8], uv: F64, factor: int) -> NDArray[np.uint8]:
    """:func:`sample_mean_colour` as the image's own uint8 pixels, ``(n, channels)`` (``(n,)``
    from a one-channel image): one flat look-up per point."""
    return sample_pixels_at(small, uv[:, 0], uv[:, 1], factor)


def sample_pixels_at(small: NDArray[PixelT], u: NDArray[np.floating], v: NDArray[np.floating],
                     factor: int) -> NDArray[PixelT]:
    """:func:`sample_pixels` at full-size pixel columns ``u``, ``v`` (float32 or float64), of
    any pixel type (uint8 channels, or packed uint32 pixels)."""
    h, w = small.shape[:2]
    # clipped to the image first, so that truncation is the floor
    col = np.clip((u + 0.5) / factor, 0, w - 1).astype(np.int64)
    row = np.clip((v + 0.5) / factor, 0, h - 1).astype(np.int64)
    row *= w
    row += col
    return np.asarray(small.reshape(h * w, *small.shape[2:])[row])


def solve_gains(frame_a: I64, frame_b: I64, colour_a: F64, colour_b: F64, n_frames: int,
                prior_weight: float = 1.0, limits: tuple[float, float] = (0.5, 2.0)) -> F64:
    """Per-frame, per-channel gains ``(n_frames, 3)`` that equalise the paired colours."""
    gains = np.ones((n_frames, 3))
    if len(frame_a) == 0 or n_frames == 0:
        return gains
    keep = np.ones(len(frame_a), dtype=bool)
    for _ in range(2):
        a, b = frame_a[keep], frame_b[keep]
        # sums by bincount (np.add.at is ~20× slower on 200 000 pairs)
        size = n_frames * n_frames
        normal = (np.bincount(a * n_frames + a, minlength=size)
                  + np.bincount(b * n_frames + b, minlength=size)
                  - np.bincount(a * n_frames + b, minlength=size)
                  - np.bincount(b * n_frames + a, minlength=size)
                  ).reshape(n_frames, n_frames).astype(np.float64)
        normal += prior_weight * np.eye(n_frames)
        rhs_pair = np.log(colour_b[keep]) - np.log(colour_a[keep])  # g_a − g_b = this
        rhs = np.stack([np.bincount(a, rhs_pair[:, c], n_frames)
                        - np.bincount(b, rhs_pair[:, c], n_frames) for c in range(3)], 1)
        log_gains = np.linalg.solve(normal, rhs)
        residual = (log_gains[frame_a] - log_gains[frame_b]) - (
            np.log(colour_b) - np.log(colour_a))
        spread = np.median(np.abs(residual), axis=0) * 1.4826
        keep = np.all(np.abs(residual) <= np.maximum(3 * spread, 0.05), axis=1)
        gains = np.exp(log_gains)
    return np.asarray(np.clip(gains, *limits))
