"""Faces that no frame holds whole: textured texel by texel from several frames (multi-view).

A face that crosses the border of every frame that sees it (a large face, a pinhole's top or
bottom edge) gets its own small square of ``P × P`` texels in the atlas, the triangle in its
lower-left half: texel ``(x, y)`` is the surface point at barycentric
``((x + ½) / P, (y + ½) / P)`` from corner 0 towards corners 1 and 2 (clamped onto the
triangle outside it, so that filtering at the long edge samples the surface). Each texel takes
its colour (bilinear, levelled by the frame's gains) from the best of the face's partial
frames — those that see at least one corner, in front, at a usable angle — in which it lies
inside the image and is unobstructed (a ray per texel against the mesh); seen in three or more,
the median of their colours (a passer-by in one frame does not decide). A face counts as
textured when at least :data:`MIN_FILLED` of its texels found a frame; the rest take the mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.texturing.frames import FrameSet
from scanpipe.texturing.photometric import nan_median
from scanpipe.texturing.visibility import MeshOcclusion, face_centroids

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

#: Frames looked at for the faces no frame holds whole.
MAX_PARTIAL_FRAMES = 32
#: Share of a patch's texels that must find a frame for the face to count as textured.
MIN_FILLED = 0.9
#: Faces whose partial frames :func:`partial_candidates` scores at once.
PARTIAL_BLOCK_FACES = 1 << 14


@dataclass
class Patches:
    """Per face in ``face``: its texels (``(n, P, P, 3)`` BGR) and the frame of most texels."""

    face: I64
    texels: U8
    frame: I64


def partial_candidates(vertices: F64, faces: I64, normals: F64, face_ids: I64,
                       frames: FrameSet, weights: F64, min_cos: float, count: int = 5) -> I64:
    """``(len(face_ids), count)`` frames (best first, −1 = none) that see at least one corner
    of each face, in front, at a usable angle; scored ``cos θ · corners inside / 3 ·
    weights[frame]``; ``normals`` ``(len(face_ids), 3)``: those faces' unit normals. At most
    about :data:`MAX_PARTIAL_FRAMES` frames are looked at, evenly spread over each camera's
    (neighbouring frames see nearly the same part of a face)."""
    from scanpipe.texturing.projective import project_valid

    n = len(face_ids)
    k = min(count, len(frames))
    if n == 0:
        return np.full((0, k), -1, dtype=np.int64)
    ids = np.asarray(frames.camera_ids)
    per_camera = max(1, MAX_PARTIAL_FRAMES // max(1, len(set(frames.camera_ids))))
    looked = []
    for cam_id in sorted(set(frames.camera_ids)):
        own = np.flatnonzero(ids == cam_id)
        looked += own[::max(1, -(-len(own) // per_camera))].tolist()
    result = np.empty((n, k), dtype=np.int64)
    # in blocks of faces: a (frames, faces) float64 score and its argsort for all of them
    # were ~2.5 kB per face (0.3 GB at lab scale) beside the ray scene; each face's column is
    # its own, so the blocks give the same frames
    for start in range(0, n, PARTIAL_BLOCK_FACES):
        block = slice(start, start + PARTIAL_BLOCK_FACES)
        tri = faces[face_ids[block]]
        m = len(tri)
        score = np.zeros((len(frames), m))
        corners = vertices[tri].reshape(-1, 3)
        centroid = face_centroids(vertices, tri)
        normals_of = np.asarray(normals[block], np.float64)
        for i in looked:
            cam = frames.cameras[i]
            _, _, valid = project_valid(corners, cam, float(frames.beta_deg[i]), 0.0)
            inside = valid.reshape(m, 3).sum(axis=1)
            to_cam = frames.centre(i) - centroid
            cos = np.einsum("ij,ij->i", normals_of, to_cam) / np.maximum(
                np.linalg.norm(to_cam, axis=1), 1e-12)
            ok = (inside > 0) & (cos >= min_cos)
            score[i, ok] = cos[ok] * inside[ok] / 3 * weights[i]
        order = np.argsort(-score, axis=0, kind="stable")[:k].T
        best = np.take_along_axis(score.T, order, axis=1)
        result[block] = np.where(best > 0, order, -1)
    return result


def remap_points(image: U8, uv: F64, width: int = 1024) -> U8:
    """Bilinear colours of ``image`` at pixel positions ``uv`` (N, 2): OpenCV's remap, the
    points laid out as rows of ``width`` (its maps may not exceed 32 767 a side); ``(N, C)``
    uint8, as the remap of a uint8 image rounds them."""
    n = len(uv)
    rows = -(-n // width)
    flat = np.zeros((rows * width, 2), np.float32)
    flat[:n] = uv
    maps = flat.reshape(rows, width, 2)
    out = cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
    return np.asarray(out.reshape(-1, image.shape[2])[:n], dtype=np.uint8)


#: Faces whose texels are combined at once (bounded float64 temporaries: 15 MB at 8 texels
#: a side and 5 frames).
COMBINE_BLOCK_FACES = 1 << 11


def bake_patches(vertices: F64, faces: NDArray[np.integer], face_ids: I64, candidates: I64,
                 frames: FrameSet, gains: F64, occlusion: MeshOcclusion, texels: int = 16
                 ) -> Patches:
    """The texels of every face in ``face_ids`` from its ``candidates`` (see the module
    docstring); only the faces that reach :data:`MIN_FILLED` are returned.

    A texel's sample in a frame is kept as the frame's uint8 colour and levelled (× the
    frame's gains, float64) only when the texels are combined, a block of faces at a time:
    the same numbers as levelling each sample at once, an eighth of the memory.
    """
    from scanpipe.texturing.projective import project_valid

    p = texels
    grid = (np.arange(p) + 0.5) / p
    b1, b2 = np.meshgrid(grid, grid)  # (P, P): x → corner 1, y → corner 2
    over = np.maximum(b1 + b2 - 1.0, 0.0)  # clamp onto the triangle
    b1c, b2c = b1 - over * b1 / np.maximum(b1 + b2, 1e-12), b2 - over * b2 / np.maximum(
        b1 + b2, 1e-12)
    bary = np.stack([1 - b1c - b2c, b1c, b2c], -1).reshape(-1, 3)  # (P², 3)
    inside = (b1 + b2 <= 1.0).reshape(-1)
    n, slots = len(face_ids), candidates.shape[1]
    values = np.zeros((n, p * p, slots, 3), dtype=np.uint8)  # colour in the slot's frame
    seen_in = np.zeros((n, p * p, slots), dtype=bool)  # ... where the texel is seen in it
    # texels seen per face and frame (≤ P² each: a frame fills one slot of a face); int16,
    # not int64 (0.8 kB per face at lab scale's 102 frames)
    votes = np.zeros((n, len(frames)), dtype=np.int16 if p * p < 2 ** 15 else np.int64)
    flat_values, flat_seen = values.reshape(-1, 3), seen_in.reshape(-1)  # views, not copies
    for slot in range(slots):
        frame_of = candidates[:, slot]
        for i in np.unique(frame_of[frame_of >= 0]):
            rows = np.flatnonzero(frame_of == i)
            face_of = np.repeat(rows, p * p)
            texel = np.tile(np.arange(p * p), len(rows))
            # the texels' surface points of these faces only (all faces' at once were
            # (n, P², 3) float64 held through the loop: 1.5 kB per face)
            where = np.einsum("tk,nkc->ntc", bary, vertices[faces[face_ids[rows]]]
                              ).reshape(-1, 3)
            cam = frames.cameras[int(i)]
            uv, _, valid = project_valid(where, cam, float(frames.beta_deg[i]), 0.5)
            seen = valid.copy()
            seen[valid] = occlusion.unobstructed(frames.centre(int(i)), where[valid])
            face_of, texel, uv = face_of[seen], texel[seen], uv[seen]
            if len(face_of) == 0:
                continue
            # one flat index into (faces, P², slots): ~3× faster than three index arrays
            at = face_of * (p * p) + texel
            at *= slots
            at += slot
            flat_values[at] = remap_points(frames.image(int(i)), uv)
            flat_seen[at] = True
            votes[:, int(i)] += np.bincount(face_of, minlength=n).astype(votes.dtype)
    texels_bgr = np.empty((n, p * p, 3), dtype=np.uint8)
    keep = np.empty(n, dtype=bool)
    for start in range(0, n, COMBINE_BLOCK_FACES):
        block = slice(start, start + COMBINE_BLOCK_FACES)
        texels_bgr[block], keep[block] = _combine(
            values[block], seen_in[block], gains[np.maximum(candidates[block], 0)], inside)
    return Patches(face_ids[keep], texels_bgr[keep].reshape(-1, p, p, 3),
                   np.argmax(votes[keep], axis=1))


def _combine(values: U8, seen_in: NDArray[np.bool_], gains: F64, inside: NDArray[np.bool_]
             ) -> tuple[U8, NDArray[np.bool_]]:
    """The texels ``(faces, P², 3)`` of a block of faces from their samples ``values``
    ``(faces, P², slots, 3)`` where ``seen_in``, levelled by ``gains`` ``(faces, slots, 3)``
    (the gains of each face's slot frame); and whether each face reaches :data:`MIN_FILLED`."""
    filled: NDArray[np.bool_] = np.asarray(seen_in.any(axis=2))
    # a texel seen in three or more frames takes their median: one frame with a passer-by
    # in it does not decide; with fewer, the best frame's colour. Levelled samples (uint8 ×
    # the frame's gains, float64) only where used: the first seen slot's of every texel, all
    # slots' of the texels with a median (the same products as levelling every sample)
    count = seen_in.sum(axis=2)
    first = np.argmax(seen_in, axis=2)
    colour = (np.take_along_axis(values, first[:, :, None, None], axis=2)[:, :, 0]
              * np.take_along_axis(gains, first[:, :, None], axis=1))
    many = np.nonzero(count >= 3)
    if len(many[0]):
        samples = np.where(seen_in[many][..., None], values[many] * gains[many[0]], np.nan)
        # each texel's samples of a channel contiguous: the row sorts are several times faster
        colour[many] = nan_median(samples.transpose(0, 2, 1).copy(), axis=2)[:, :, 0]
    share = (filled & inside).sum(axis=1) / max(1, int(inside.sum()))
    colour = np.where(filled[:, :, None], colour, 0.0)
    mean = colour.sum(axis=1) / np.maximum(filled.sum(axis=1), 1)[:, None]
    colour = np.where(filled[:, :, None], colour, mean[:, None, :])
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8), share >= MIN_FILLED
