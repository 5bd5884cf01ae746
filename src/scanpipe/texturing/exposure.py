"""Even out exposure across seams: one gain per frame and colour channel, from overlaps.

Where two neighbouring faces were textured from different frames a and b, the midpoint of
their shared edge is seen in both. Its colour (a 4 × 4 pixel mean) in each frame gives one
equation ``log g_a + log I_a = log g_b + log I_b``. The gains solve all equations in least
squares with a weak pull towards 1 (which fixes the free overall level), once more after
dropping outliers (misregistration, specular spots), and are limited to [0.5, 2].
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.texturing.frames import FrameSet

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def shared_edges(faces: NDArray[np.integer]) -> tuple[I64, I64]:
    """Pairs of faces sharing an edge: ``(face_pairs (E, 2), edge_vertices (E, 2))``.

    Edges used by more than two faces (non-manifold) are left out.
    """
    faces = np.asarray(faces, dtype=np.int64)
    n = len(faces)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges.sort(axis=1)
    owner = np.tile(np.arange(n, dtype=np.int64), 3)
    key = edges[:, 0] * (int(faces.max(initial=0)) + 1) + edges[:, 1]  # 1-D: fast to sort
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    twice = counts[inverse] == 2
    order = np.argsort(inverse[twice], kind="stable")
    owners = owner[twice][order].reshape(-1, 2)
    vertices = edges[twice][order].reshape(-1, 2, 2)[:, 0]
    return owners, vertices


def shrink(image: NDArray[np.uint8], factor: int) -> NDArray[np.uint8]:
    """``image`` reduced ``factor`` times by area averaging (a cheap local mean)."""
    h, w = image.shape[:2]
    return np.asarray(cv2.resize(image, (w // factor, h // factor),
                                 interpolation=cv2.INTER_AREA), dtype=np.uint8)


def sample_mean_colour(small: NDArray[np.uint8], uv: F64, factor: int) -> F64:
    """Colours at full-size pixel positions ``uv`` from an image shrunk by ``factor``."""
    h, w = small.shape[:2]
    col = np.clip(np.floor((uv[:, 0] + 0.5) / factor), 0, w - 1).astype(np.int64)
    row = np.clip(np.floor((uv[:, 1] + 0.5) / factor), 0, h - 1).astype(np.int64)
    return np.asarray(small[row, col], dtype=np.float64)


def seam_colour_pairs(vertices: NDArray[np.floating], faces: NDArray[np.integer],
                      chosen: I64, frames: FrameSet, max_pairs: int = 200_000,
                      factor: int = 4) -> tuple[I64, I64, F64, F64]:
    """``(frame_a, frame_b, colour_a, colour_b)`` at the midpoints of seam edges."""
    from scanpipe.texturing.projective import project_valid

    pairs, edge_vertices = shared_edges(faces)
    fa, fb = chosen[pairs[:, 0]], chosen[pairs[:, 1]]
    seam = (fa >= 0) & (fb >= 0) & (fa != fb)
    fa, fb, edge_vertices = fa[seam], fb[seam], edge_vertices[seam]
    if len(fa) > max_pairs:
        keep = np.random.default_rng(0).choice(len(fa), max_pairs, replace=False)
        fa, fb, edge_vertices = fa[keep], fb[keep], edge_vertices[keep]
    midpoints = np.asarray(vertices, np.float64)[edge_vertices].mean(axis=1)
    colour_a = np.zeros((len(fa), 3))
    colour_b = np.zeros((len(fa), 3))
    ok = np.ones(len(fa), dtype=bool)
    for i in np.unique(np.concatenate([fa, fb])):
        cam = frames.cameras[i]
        small = shrink(frames.image(int(i)), factor)
        for side, target in ((fa, colour_a), (fb, colour_b)):
            idx = np.flatnonzero(side == i)
            uv, _, valid = project_valid(midpoints[idx], cam, float(frames.beta_deg[i]), 0.0)
            target[idx] = sample_mean_colour(small, uv, factor)
            ok[idx[~valid]] = False
    usable = ok & np.all((colour_a > 4) & (colour_a < 251) & (colour_b > 4) & (colour_b < 251),
                         axis=1)
    return fa[usable], fb[usable], colour_a[usable], colour_b[usable]


def solve_gains(frame_a: I64, frame_b: I64, colour_a: F64, colour_b: F64, n_frames: int,
                prior_weight: float = 1.0, limits: tuple[float, float] = (0.5, 2.0)) -> F64:
    """Per-frame, per-channel gains ``(n_frames, 3)`` that equalise the paired colours."""
    gains = np.ones((n_frames, 3))
    if len(frame_a) == 0 or n_frames == 0:
        return gains
    keep = np.ones(len(frame_a), dtype=bool)
    for _ in range(2):
        a, b = frame_a[keep], frame_b[keep]
        normal = np.zeros((n_frames, n_frames))
        np.add.at(normal, (a, a), 1.0)
        np.add.at(normal, (b, b), 1.0)
        np.add.at(normal, (a, b), -1.0)
        np.add.at(normal, (b, a), -1.0)
        normal += prior_weight * np.eye(n_frames)
        rhs_pair = np.log(colour_b[keep]) - np.log(colour_a[keep])  # g_a − g_b = this
        rhs = np.zeros((n_frames, 3))
        np.add.at(rhs, a, rhs_pair)
        np.add.at(rhs, b, -rhs_pair)
        log_gains = np.linalg.solve(normal, rhs)
        residual = (log_gains[frame_a] - log_gains[frame_b]) - (
            np.log(colour_b) - np.log(colour_a))
        spread = np.median(np.abs(residual), axis=0) * 1.4826
        keep = np.all(np.abs(residual) <= np.maximum(3 * spread, 0.05), axis=1)
        gains = np.exp(log_gains)
    return np.asarray(np.clip(gains, *limits))
