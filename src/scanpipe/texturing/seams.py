"""Local seam levelling: what is left of a colour step at a seam is spread over a strip.

After the global gains (:mod:`scanpipe.texturing.exposure`), two frames still disagree a little
along a seam (vignetting, the light seen from two sides). As in Waechter et al. 2014 (section
4.2, Poisson editing of a 20-pixel strip), each side is pulled to the mean of both at the seam
and the pull fades to nothing across a strip inside its own chart:

- :func:`seam_corrections`: at both ends and the middle of every seam edge, the levelled colour
  in each of the two frames (a 4 × 4 pixel mean); each frame gets ``δ = (other − own) / 2``
  there (limited to ±``max_levels``).
- :func:`correction_field`: for one atlas region (a box of one frame), the corrections of that
  frame are averaged smoothly along the seam (a normalised Gaussian of the scattered values)
  and multiplied by ``max(0, 1 − d / strip)``, d the distance to the nearest seam point; on a
  grid of ``step`` pixels, resized to the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.texturing.exposure import sample_mean_colour
from scanpipe.texturing.frames import REDUCED_FACTOR, FrameSet
from scanpipe.texturing.visibility import MeshEdges, mesh_edges

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class SeamCorrections:
    """Per frame the seam points (pixels) and their colour corrections (BGR levels)."""

    uv: dict[int, F64]
    delta: dict[int, F64]
    points: int

    def empty(self) -> bool:
        """True when there is nothing to correct."""
        return self.points == 0


def seam_corrections(vertices: NDArray[np.floating], faces: NDArray[np.integer],
                     labels: I64, frames: FrameSet, gains: F64, max_levels: float = 60.0,
                     edges: MeshEdges | None = None) -> SeamCorrections:
    """The corrections at the seam points of every frame (see the module docstring);
    ``edges``: the mesh's :class:`~scanpipe.texturing.visibility.MeshEdges` when already
    known (the corners are looked up for the seam edges only)."""
    from scanpipe.texturing.projective import project_valid

    if edges is None:
        edges = mesh_edges(faces)
    pairs = edges.pairs()
    la, lb = labels[pairs[:, 0]], labels[pairs[:, 1]]
    del pairs
    seam = (la >= 0) & (lb >= 0) & (la != lb)
    rows = np.flatnonzero(seam)
    la, lb, edge_vertices = la[rows], lb[rows], edges.vertices(faces, rows)
    vertices = np.asarray(vertices, np.float64)
    ends = vertices[edge_vertices]  # (E, 2, 3)
    points = np.concatenate([ends[:, 0], ends[:, 1], ends.mean(axis=1)])
    fa, fb = np.tile(la, 3), np.tile(lb, 3)
    n = len(points)
    colour = {side: np.full((n, 3), np.nan) for side in ("a", "b")}
    pixel = {side: np.zeros((n, 2)) for side in ("a", "b")}
    for i in np.unique(np.concatenate([fa, fb])) if n else []:
        cam = frames.cameras[int(i)]
        for side, label in (("a", fa), ("b", fb)):
            idx = np.flatnonzero(label == i)
            if len(idx) == 0:
                continue
            uv, _, valid = project_valid(points[idx], cam, float(frames.beta_deg[i]), 0.0)
            idx, uv = idx[valid], uv[valid]
            colour[side][idx] = sample_mean_colour(frames.reduced(int(i)), uv,
                                                   REDUCED_FACTOR) * gains[i]
            pixel[side][idx] = uv
    ok = np.all(np.isfinite(colour["a"]) & np.isfinite(colour["b"]), axis=1)
    half = np.clip((colour["b"] - colour["a"]) / 2, -max_levels, max_levels)
    uv_out: dict[int, list[F64]] = {}
    delta_out: dict[int, list[F64]] = {}
    for side, label, sign in (("a", fa, 1.0), ("b", fb, -1.0)):
        for i in np.unique(label[ok]):
            sel = ok & (label == i)
            uv_out.setdefault(int(i), []).append(pixel[side][sel])
            delta_out.setdefault(int(i), []).append(sign * half[sel])
    return SeamCorrections({k: np.concatenate(v) for k, v in uv_out.items()},
                           {k: np.concatenate(v) for k, v in delta_out.items()}, int(ok.sum()))


def correction_field(uv: F64, delta: F64, box: tuple[int, int, int, int], strip_px: float,
                     step_px: int = 4) -> F32 | None:
    """``(h, w, 3)`` float32 corrections for the image box ``x0, y0, x1, y1`` from seam points
    ``uv`` with corrections ``delta``; None when no seam point lies within ``strip_px``."""
    x0, y0, x1, y1 = box
    near = ((uv[:, 0] >= x0 - strip_px) & (uv[:, 0] < x1 + strip_px)
            & (uv[:, 1] >= y0 - strip_px) & (uv[:, 1] < y1 + strip_px))
    if not near.any():
        return None
    uv, delta = uv[near], delta[near]
    margin = int(np.ceil(strip_px / step_px)) + 1
    gw = (x1 - x0 + step_px - 1) // step_px + 2 * margin
    gh = (y1 - y0 + step_px - 1) // step_px + 2 * margin
    col = np.clip(np.floor((uv[:, 0] - x0) / step_px).astype(np.int64) + margin, 0, gw - 1)
    row = np.clip(np.floor((uv[:, 1] - y0) / step_px).astype(np.int64) + margin, 0, gh - 1)
    cell = row * gw + col
    weight = np.bincount(cell, minlength=gw * gh).astype(np.float32)
    total = np.stack([np.bincount(cell, delta[:, c], gw * gh) for c in range(3)], 1)
    sigma = max(1.0, strip_px / step_px / 2)
    den = cv2.GaussianBlur(weight.reshape(gh, gw), (0, 0), sigma)
    num = cv2.GaussianBlur(total.astype(np.float32).reshape(gh, gw, 3), (0, 0), sigma)
    value = num / np.maximum(den, 1e-6)[:, :, None]
    seam_free = np.where(weight.reshape(gh, gw) > 0, 0, 255).astype(np.uint8)
    distance = cv2.distanceTransform(seam_free, cv2.DIST_L2, 3) * step_px
    fade = np.clip(1.0 - distance / strip_px, 0.0, 1.0)
    field = (value * fade[:, :, None]).astype(np.float32)
    field = field[margin:gh - margin, margin:gw - margin]
    return np.asarray(cv2.resize(field, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR),
                      dtype=np.float32)
