"""Projective texturing: the best frame for every face, and colours for points.

For each chosen frame the vertices within the camera's azimuth window are projected at once with
the calibrated camera model at the frame's platform angle (:func:`scanpipe.camera.project_columns`,
in float32).
A face's score in a frame is

    score = cos θ · centrality · sharpness_rel ** sharpness_weight

with θ the angle between the face normal and the direction to the camera centre, centrality
``1 − ½ r²`` (r the distance of the face's image from the principal point, in half image sizes,
floored at 0.05) and sharpness relative to the sharpest frame of that camera. A face scores 0
where a corner falls outside the image (less a margin), behind the camera, or where it is seen
at more than ``acos(min_cos)``. Only each face's best :attr:`FaceScores.keep` frames are kept
(:class:`FaceScores`), taken while the frames are scored (:class:`BestFrames`): a dense
frames × faces matrix is gigabytes at lab scale. Faces then take their best frame in which
they are really visible: in rounds, the best remaining candidate of every unresolved face (of its
``max_candidates`` best) is tested against the mesh (one batch of rays per round); an occluded
candidate is struck out.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.camera import (
    FloatT,
    camera_columns,
    camera_pose_in_rig,
    intrinsic_matrix,
    normalized_columns,
    normalized_to_pixels,
    project_columns,
)
from scanpipe.errors import StageError
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.rig import CameraConfig, Rig
from scanpipe.texturing.frames import FrameSet, choose_frames, worker_count
from scanpipe.texturing.groups import FaceGroups, ragged_slots, single_faces
from scanpipe.texturing.visibility import MeshOcclusion, face_centroids
from scanpipe.threads import thread_pool

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
#: A 360° camera turning on the axis sees the whole room in every frame: one frame per this many
#: degrees of platform angle serves (the texture stage's ``equirect_spacing_deg`` default).
EQUIRECT_SPACING_DEG = 20.0
#: Points projected at once when colouring a cloud: the temporaries of a piece fit the cache.
COLOUR_CHUNK_POINTS = 1 << 16
#: Vertices or faces :func:`face_scores` looks at at once: a whole 360° view of a lab-scale mesh
#: at once held ~0.4 GB of temporaries per thread.
SCORE_CHUNK = 1 << 18
#: A pinhole frame's faces are gathered from its vertices in view when those are fewer than
#: this share of the faces in its azimuth window (else the window is scored whole, in slices).
IN_VIEW_SHARE = 0.5
#: Faces whose kept frames :meth:`FaceScores.best_first` orders at once (cache-sized blocks).
SORT_CHUNK_FACES = 1 << 16
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]


@dataclass
class FaceScores:
    """Each face's best ``keep`` frames by score instead of a dense ``(frames, faces)`` matrix.

    ``frame`` ``(faces, keep)`` int32 (−1 = none) and ``score`` ``(faces, keep)`` float32
    (0 = none or struck out), best first (ties: the lower frame number, as an argmax over the
    dense matrix would take). Built frame by frame by :class:`BestFrames`. A frame not kept for
    a face scores 0 there.
    """

    frame: I32
    score: F32

    @classmethod
    def from_dense(cls, scores: NDArray[np.floating], keep: int) -> FaceScores:
        """From a ``(frames, faces)`` matrix (tests, small inputs)."""
        best = BestFrames(scores.shape[1], keep)
        for i, row in enumerate(np.asarray(scores, np.float32)):
            face = np.flatnonzero(row > 0)
            best.add(i, face, row[face])
        return best.result()

    @property
    def keep(self) -> int:
        """Frames kept per face."""
        return int(self.frame.shape[1])

    def best_first(self, rows: I64 | None = None) -> FaceScores:
        """Order every row by score, best first (empty slots last): in place, returning self
        (frames held in a smaller integer type than int32 go into a new int32 array); or,
        given ``rows`` (a permutation of the faces), into a new one whose row ``rows[k]`` is
        this one's row ``k`` ordered (one pass over the rows for both).

        The float32 score's bits (positive: ordered as integers) and the frame's complement
        pack into one int64 key per slot, so a plain sort of each row orders both.
        """
        n_faces, keep = self.frame.shape
        if rows is not None:
            out = FaceScores(np.empty(self.frame.shape, np.int32), np.empty_like(self.score))
        elif self.frame.dtype != np.int32:  # each block's rows are read before written
            out = FaceScores(np.empty(self.frame.shape, np.int32), self.score)
        else:
            out = self
        if keep == 0:
            return out
        top = np.int64(np.iinfo(np.int32).max)

        def order(start: int) -> None:
            stop = min(start + SORT_CHUNK_FACES, n_faces)
            target = slice(start, stop) if rows is None else rows[start:stop]
            score = self.score[start:stop]
            # in place on one temporary (half the passes of building it by np.where and
            # sorting its negation)
            key = score.view(np.int32).astype(np.int64)
            key <<= 32
            key |= top - self.frame[start:stop]
            key[score <= 0] = 0
            key.sort(axis=1)
            key = key[:, ::-1]  # descending
            out.score[target] = (key >> 32).astype(np.int32).view(np.float32)
            frame = top - (key & 0xFFFFFFFF)
            frame[key == 0] = -1
            out.frame[target] = frame

        # blocks of faces on a thread per core (numpy releases the GIL; each its own rows)
        with thread_pool(worker_count(-(-n_faces // SORT_CHUNK_FACES))
                                ) as pool:
            list(pool.map(order, range(0, n_faces, SORT_CHUNK_FACES)))
        return out

    def lookup(self, frame: I64, face: I64) -> F32:
        """Score of frame ``frame[i]`` for face ``face[i]`` (0 where not kept or struck)."""
        return self.lookup_rows(frame, self.frame[face], self.score[face])

    @staticmethod
    def lookup_rows(frame: I64, rows_frame: I32, rows_score: F32) -> F32:
        """:meth:`lookup` on rows already gathered (``self.frame[face]``, ``self.score[face]``)."""
        match = (rows_frame == frame[:, None]) & (frame[:, None] >= 0)
        slot = np.argmax(match, axis=1)
        found = rows_score[np.arange(len(frame)), slot]
        return np.asarray(np.where(match.any(axis=1), found, np.float32(0.0)), dtype=np.float32)

    def strike(self, frame: I64, face: I64) -> None:
        """Score 0 for frame ``frame[i]`` of face ``face[i]`` (an occluded candidate)."""
        match = (self.frame[face] == frame[:, None]) & (frame[:, None] >= 0)
        has = match.any(axis=1)
        self.score[face[has], np.argmax(match[has], axis=1)] = 0.0

    @property
    def faces(self) -> int:
        """Rows (faces, or groups)."""
        return int(self.frame.shape[0])

    def rows(self, face: NDArray[np.integer]) -> tuple[I32, F32]:
        """The kept frames and scores of faces ``face`` (copies)."""
        return self.frame[face], self.score[face]

    def first(self, face: slice) -> tuple[I32, F32]:
        """The best kept frame and its score of the faces ``face`` (a slice)."""
        return self.frame[face, 0], self.score[face, 0]

    def slot(self, face: NDArray[np.integer], slot: int) -> I32:
        """The frame in slot ``slot`` of faces ``face`` (−1 = none)."""
        return np.asarray(self.frame[face, slot], dtype=np.int32)

    def has_candidates(self) -> NDArray[np.bool_]:
        """Per face: some frame kept."""
        return np.asarray((self.frame >= 0).any(axis=1))

    def strike_slot(self, face: NDArray[np.integer], slot: int) -> None:
        """Score 0 for slot ``slot`` of faces ``face`` (an occluded candidate)."""
        self.score[face, slot] = 0.0


class GroupedScores:
    """Each face's kept frames as its group's (:class:`FaceScores` of the groups, one row per
    group), and per face the slots struck out for it alone (an occluded candidate: a bit per
    slot). The methods of :class:`FaceScores` the visibility and seam steps read, per face:
    a lab-scale mesh's faces hold 4 + a few bytes each here instead of 112 (14 kept frames).
    """

    def __init__(self, groups: FaceScores, of: I32) -> None:
        self.groups = groups
        self.of = of
        keep = groups.keep
        self._bits = next((bits for bits in (8, 16, 32, 64) if keep <= bits), 64)
        self._words = max(1, -(-keep // self._bits))
        word = {8: np.uint8, 16: np.uint16, 32: np.uint32, 64: np.uint64}[self._bits]
        #: Per face (and word of slots): bit k set where slot k is struck for that face.
        self.struck = np.zeros((len(of), self._words), dtype=word)

    @property
    def keep(self) -> int:
        """Frames kept per face."""
        return self.groups.keep

    @property
    def faces(self) -> int:
        """Faces."""
        return len(self.of)

    def _struck_mask(self, face: NDArray[np.integer]) -> NDArray[np.bool_]:
        """``(len(face), keep)``: the slots struck for each face."""
        slots = np.arange(self.keep)
        words = self.struck[face][:, slots // self._bits]
        shift = (slots % self._bits).astype(words.dtype)
        return np.asarray((words >> shift) & words.dtype.type(1), dtype=bool)

    def rows(self, face: NDArray[np.integer]) -> tuple[I32, F32]:
        """The kept frames and scores of faces ``face`` (copies; struck slots score 0)."""
        group = self.of[face]
        frame, score = self.groups.frame[group], self.groups.score[group]
        struck = self._struck_mask(face)
        if struck.any():
            score[struck] = 0.0
        return frame, score

    def first(self, face: slice) -> tuple[I32, F32]:
        """The best kept frame and its score of the faces ``face`` (a slice)."""
        group = self.of[face]
        frame, score = self.groups.frame[group, 0], self.groups.score[group, 0]
        struck = (self.struck[face, 0] & self.struck.dtype.type(1)) != 0
        return frame, np.where(struck, np.float32(0.0), score)

    def slot(self, face: NDArray[np.integer], slot: int) -> I32:
        """The frame in slot ``slot`` of faces ``face`` (−1 = none)."""
        return np.asarray(self.groups.frame[self.of[face], slot], dtype=np.int32)

    def has_candidates(self) -> NDArray[np.bool_]:
        """Per face: some frame kept for its group."""
        return self.groups.has_candidates()[self.of]

    def strike_slot(self, face: NDArray[np.integer], slot: int) -> None:
        """Slot ``slot`` struck for faces ``face`` (not for the rest of their groups)."""
        word = self.struck.dtype.type(1) << self.struck.dtype.type(slot % self._bits)
        self.struck[face, slot // self._bits] |= word

    def lookup(self, frame: I64, face: I64) -> F32:
        """Score of frame ``frame[i]`` for face ``face[i]`` (0 where not kept or struck)."""
        return FaceScores.lookup_rows(frame, *self.rows(face))

    def strike(self, frame: I64, face: I64) -> None:
        """Frame ``frame[i]`` struck for face ``face[i]`` (an occluded candidate)."""
        rows_frame, _ = self.rows(face)
        match = (rows_frame == frame[:, None]) & (frame[:, None] >= 0)
        has = match.any(axis=1)
        slot = np.argmax(match[has], axis=1)
        for k in np.unique(slot).tolist():  # a pass per distinct slot (≤ keep)
            self.strike_slot(face[has][slot == k], k)


#: What the visibility and seam steps read: per face (:class:`FaceScores`) or per group.
Scores = FaceScores | GroupedScores


class BestFrames:
    """Keeps each face's best ``keep`` frames while frames are offered one after another
    (:meth:`add`), for :class:`FaceScores`. Per face: the slots filled so far, and once all
    are, the lowest kept score and its slot: a score must beat it to be kept. ``small``: fewer
    than 2¹⁵ frames, held as int16 (a quarter less memory; :meth:`result` gives int32 as
    :class:`FaceScores` holds them). The slot counts and numbers are int8 (up to
    127 kept): 50 MB less than int32 and int64 at lab scale, and less to stream per offer."""

    def __init__(self, n_faces: int, keep: int, small: bool = False) -> None:
        self.keep = keep
        self.frame = np.full((n_faces, keep), -1, dtype=np.int16 if small else np.int32)
        self.score = np.zeros((n_faces, keep), dtype=np.float32)
        slot_type = np.int8 if keep < 128 else np.int32
        self._filled: NDArray[np.signedinteger[Any]] = np.zeros(n_faces, dtype=slot_type)
        self._floor = np.zeros(n_faces, dtype=np.float32)  # 0 while a slot is free
        # the slot of the lowest kept score
        self._low: NDArray[np.signedinteger[Any]] = np.zeros(n_faces, dtype=slot_type)

    def add(self, frame: int, face: NDArray[np.integer], score: F32) -> None:
        """Offer frame ``frame``'s positive scores of (distinct) faces ``face``: into a free
        slot, else into the slot of the face's lowest kept score when higher (an equal score
        keeps the earlier, lower frame)."""
        if self.keep == 0:
            return
        # one conversion to the index type for the several look-ups below (numpy converts
        # any other integer index array at every look-up)
        face = np.asarray(face, dtype=np.intp)
        better = score > self._floor.take(face)  # take: a little cheaper than indexing
        if not better.all():
            face, score = face[better], score[better]
        filled: NDArray[np.signedinteger[Any]] = self._filled.take(face)
        free = filled < self.keep
        # flat slot of each kept score: the next free one, or the lowest one's
        flat = face * self.keep
        if free.all():  # most offers of the lab's 360° frames
            flat += filled
        else:
            low: NDArray[np.signedinteger[Any]] = self._low.take(face)
            flat += np.where(free, filled, low)
        self.score.reshape(-1)[flat] = score
        self.frame.reshape(-1)[flat] = frame
        filled += free
        self._filled[face] = filled
        # the faces whose lowest slot may have changed: those just full and those replaced
        redo = face[filled == self.keep]
        if len(redo):
            rows = self.score[redo]
            slot = np.argmin(rows, axis=1)
            self._low[redo] = slot
            self._floor[redo] = rows[np.arange(len(redo)), slot]

    def result(self, rows: I64 | None = None) -> FaceScores:
        """The kept frames, best first (the builder's scores, not a copy; its frames too when
        int32); given ``rows``, a copy with the builder's row ``k`` as row ``rows[k]``
        (:meth:`FaceScores.best_first`)."""
        # done with: not held through the copy
        self._filled, self._low = np.zeros(0, np.int8), np.zeros(0, np.int8)
        self._floor = np.zeros(0, np.float32)
        return FaceScores(self.frame, self.score).best_first(rows)


@lru_cache(maxsize=64)
def _normalized_limits(cam: CameraConfig) -> tuple[float, float]:
    """How far (|x/z|, |y/z|) the image border reaches once the lens distortion is undone."""
    w, h = cam.width, cam.height
    border = np.concatenate([
        np.stack([np.linspace(0, w - 1, 33), np.zeros(33)], 1),
        np.stack([np.linspace(0, w - 1, 33), np.full(33, h - 1.0)], 1),
        np.stack([np.zeros(33), np.linspace(0, h - 1, 33)], 1),
        np.stack([np.full(33, w - 1.0), np.linspace(0, h - 1, 33)], 1),
    ]).reshape(-1, 1, 2)
    normalized = cv2.undistortPoints(border, intrinsic_matrix(cam),
                                     np.asarray(cam.distortion, np.float64)).reshape(-1, 2)
    return float(np.abs(normalized[:, 0]).max()) * 1.05, float(np.abs(normalized[:, 1]).max()
                                                              ) * 1.05


def project_valid(points: NDArray[np.floating], cam: CameraConfig, beta_deg: float,
                  margin_px: float = 2.0, near_m: float = 0.05
                  ) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Project points; ``valid`` where in front of the camera and inside the image
    (:func:`project_valid_columns` in float64, ``uv`` as ``(N, 2)``)."""
    points = np.asarray(points)
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    u, v, depth, valid = project_valid_columns(x, y, z, cam, beta_deg, margin_px, near_m)
    uv = np.empty((len(depth), 2), dtype=np.float64)
    uv[:, 0], uv[:, 1] = u, v
    return uv, depth, valid


def project_valid_columns(x: NDArray[FloatT], y: NDArray[FloatT], z: NDArray[FloatT],
                          cam: CameraConfig, beta_deg: float, margin_px: float = 2.0,
                          near_m: float = 0.05
                          ) -> tuple[NDArray[FloatT], NDArray[FloatT], NDArray[FloatT],
                                     NDArray[np.bool_]]:
    """Project point columns, in their dtype (float32 for speed: see
    :func:`scanpipe.camera.project_columns`): ``(u, v, depth, valid)``, ``valid`` where in
    front of the camera and inside the image, ``margin_px`` in from its border.

    With lens distortion the polynomial folds back far outside the field of view, so a point
    must also lie inside the undistorted image border (its normalized coordinates are tested
    before the distortion).
    """
    if cam.model == "equirect":
        u, v, depth = project_columns(x, y, z, cam, beta_deg)
        valid = depth > near_m
    else:
        across, down, depth = camera_columns(x, y, z, cam, beta_deg)
        across, down = normalized_columns(across, down, depth)
        valid = depth > near_m
        if any(cam.distortion):
            limit_x, limit_y = _normalized_limits(cam)
            valid &= np.abs(across) <= limit_x
            valid &= np.abs(down) <= limit_y
        u, v = normalized_to_pixels(across, down, cam)
    valid &= u >= margin_px
    valid &= u <= cam.width - 1 - margin_px
    valid &= v >= margin_px
    valid &= v <= cam.height - 1 - margin_px
    return u, v, depth, valid


def centrality(uv: F64, cam: CameraConfig) -> F64:
    """``1 − ½ r²`` floored at 0.05, r = distance from the principal point in half image sizes;
    1 everywhere for an equirect camera (it has no centre: its resolution is the same in every
    direction, and more across near the poles)."""
    if cam.model == "equirect":
        return np.ones(len(uv))
    return pinhole_centrality(uv[:, 0], uv[:, 1], cam)


def pinhole_centrality(u: F64, v: F64, cam: CameraConfig) -> F64:
    """:func:`centrality` of a pinhole camera from the pixel columns ``u`` and ``v``."""
    rr = ((u - cam.cx) / (cam.width / 2)) ** 2 + ((v - cam.cy) / (cam.height / 2)) ** 2
    return np.asarray(np.clip(1.0 - 0.5 * rr, 0.05, 1.0))


def view_window(cam: CameraConfig, beta_deg: float) -> tuple[float, float] | None:
    """Azimuth (atan2(x, z), degrees) of a camera's view and a half width that holds every
    direction it sees; None when straight up or down is in view (then every azimuth is).

    The corners of the undistorted image rectangle bound the azimuths: each image edge is an arc
    of a great circle, along which the azimuth is monotonic unless it passes a pole.
    """
    if cam.model == "equirect":
        return None
    rotation, _ = camera_pose_in_rig(cam, beta_deg)
    limit_x, limit_y = _normalized_limits(cam)
    for pole in (rotation[1], -rotation[1]):  # the rig's ±y in camera coordinates
        if pole[2] > 0 and abs(pole[0] / pole[2]) <= limit_x and abs(pole[1] / pole[2]) <= limit_y:
            return None
    corners = np.array([[sx * limit_x, sy * limit_y, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
    rays = np.einsum("ij,kj->ki", rotation, corners)
    axis = rotation[:, 2]
    centre = math.degrees(math.atan2(axis[0], axis[2]))
    azimuths = np.degrees(np.arctan2(rays[:, 0], rays[:, 2]))
    half = float(np.abs((azimuths - centre + 180.0) % 360.0 - 180.0).max())
    return centre, half + 2.0


class AzimuthIndex:
    """Items (vertices, faces) ordered by azimuth about the motor axis, those near the axis
    first, so that the ones inside a camera's azimuth window are a few contiguous ranges of
    :attr:`order` (items near the axis are always taken)."""

    def __init__(self, points: NDArray[np.floating], near_m: float) -> None:
        azimuth = np.degrees(np.arctan2(points[:, 0], points[:, 2]))
        near = np.hypot(points[:, 0], points[:, 2]) < near_m
        far = np.flatnonzero(~near)
        by_azimuth = far[np.argsort(azimuth[far], kind="stable")]
        self.n_near = len(points) - len(far)
        #: Item indices: those near the axis, then the others by azimuth.
        self.order = np.concatenate([np.flatnonzero(near), by_azimuth])
        self.sorted_deg = azimuth[by_azimuth]
        self.count = len(points)

    def ranges(self, centre_deg: float, half_deg: float) -> list[tuple[int, int]]:
        """Ranges ``[start, stop)`` of :attr:`order` with the items whose azimuth is within
        ``half_deg`` of ``centre_deg``, and those near the axis."""
        if half_deg >= 180.0:
            return [(0, self.count)]
        lo, hi = centre_deg - half_deg, centre_deg + half_deg
        parts = [(0, self.n_near)] if self.n_near else []
        for a, b in ((lo, hi), (lo + 360.0, hi + 360.0), (lo - 360.0, hi - 360.0)):
            i, j = np.searchsorted(self.sorted_deg, (a, b))
            if j > i:
                parts.append((self.n_near + int(i), self.n_near + int(j)))
        return parts

    def window(self, centre_deg: float, half_deg: float) -> NDArray[np.int64]:
        """Indices with azimuth within ``half_deg`` of ``centre_deg`` (plus those near the axis)."""
        parts = [self.order[a:b] for a, b in self.ranges(centre_deg, half_deg)]
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _window_margins(cameras: list[CameraConfig]) -> tuple[float, float]:
    """``(near_m, parallax_deg)`` for :class:`AzimuthIndex` windows of these cameras: a point
    farther than ``near_m`` from the axis is seen from a camera centre at most
    ``parallax_deg`` of azimuth away from where the axis sees it (the cameras sit off the
    axis); nearer points are always taken."""
    offset = max((math.hypot(c.pose.translation_m[0], c.pose.translation_m[2])
                  for c in cameras), default=0.0)
    near_m = 4 * offset + 0.3
    return near_m, math.degrees(math.asin(offset / near_m))


def resolution_weights(cameras: list[CameraConfig]) -> F64:
    """Each camera's angular resolution relative to the finest (1 = finest): a 360° camera
    beside phones is used where they do not reach."""
    res = np.array([c.px_per_rad for c in cameras], dtype=np.float64)
    return res / res.max() if len(res) else res


def wraps(u0: F64, u1: F64, u2: F64, cam: CameraConfig) -> NDArray[np.bool_]:
    """Faces (their corners' image columns ``u0``, ``u1``, ``u2``) that cross an equirect
    image's left/right wrap (or sit so near a pole that they spread across a quarter of it):
    they cannot be cut from it (none for a pinhole camera)."""
    if cam.model != "equirect":
        return np.zeros(len(u0), dtype=bool)
    spread = np.maximum(np.maximum(u0, u1), u2) - np.minimum(np.minimum(u0, u1), u2)
    return np.asarray(spread > cam.width / 4)


def _pieces(ranges: list[tuple[int, int]], size: int = SCORE_CHUNK) -> list[tuple[int, int]]:
    """``ranges`` cut into pieces of at most ``size`` items."""
    return [(start, min(start + size, b)) for a, b in ranges for start in range(a, b, size)]


def face_scores(vertices: NDArray[np.floating], faces: NDArray[np.integer], normals: F64,
                frames: FrameSet, *, min_cos: float = 0.2, margin_px: float = 2.0,
                sharpness_weight: float = 1.0, two_sided: bool = False,
                progress: ProgressFn = no_progress, centroids: F64 | None = None,
                keep: int = 14) -> FaceScores:
    """Each face's best ``keep`` frames by score, best first (see the module docstring): the
    per-face path, :func:`group_scores` with every face a group of its own.

    ``keep``: the texture stage passes ``max_views + max_candidates``, every frame a face's
    later steps read but ICM's (which then may move a face only to one of these frames).
    """
    faces = np.asarray(faces, np.int64)
    if centroids is None:
        centroids = face_centroids(np.asarray(vertices, np.float64), faces)
    return group_scores(vertices, single_faces(faces, normals, centroids), frames,
                        min_cos=min_cos, margin_px=margin_px,
                        sharpness_weight=sharpness_weight, two_sided=two_sided,
                        progress=progress, keep=keep)


def group_scores(vertices: NDArray[np.floating], groups: FaceGroups, frames: FrameSet, *,
                 min_cos: float = 0.2, margin_px: float = 2.0, sharpness_weight: float = 1.0,
                 two_sided: bool = False, progress: ProgressFn = no_progress,
                 keep: int = 14) -> FaceScores:
    """Each group's best ``keep`` frames by score, best first (rows: the groups): a frame
    scores a group when it holds every corner of the group inside its image (then it holds
    each of its faces whole), from the group's normal and centroid, and the mean image
    position of its corners (a group of one face: exactly the face's score).

    The frames are scored on threads, a frame each, and offered to :class:`BestFrames` in
    frame order on this thread (the result does not depend on the threads).

    Per frame only the vertices within the camera's azimuth window (plus those near the axis,
    where the camera's offset from the axis matters) are projected, and only the groups whose
    first corner is one of them are looked at (a group in view has every corner in view).
    Vertices are renumbered by azimuth once and groups by their first corner, so that a window
    is a few contiguous slices of every per-vertex and per-group array (a phone's groups are
    gathered from its vertices in view instead: most of its window is out of its view). The
    kept frames are held in group order (each frame's offers renumbered on its thread).
    """
    return _kept_by_azimuth(
        vertices, groups, frames, min_cos=min_cos, margin_px=margin_px,
        sharpness_weight=sharpness_weight, two_sided=two_sided, progress=progress,
        keep=keep).result()


def _kept_by_azimuth(vertices: NDArray[np.floating], groups: FaceGroups, frames: FrameSet, *,
                     min_cos: float, margin_px: float, sharpness_weight: float,
                     two_sided: bool, progress: ProgressFn, keep: int) -> BestFrames:
    """:func:`group_scores`' frames kept for the groups (in group order; scored in azimuth
    order, :attr:`AzimuthIndex.order`)."""
    vertices = np.asarray(vertices, np.float64)
    if 4 * len(groups.corners) < len(vertices):
        # a few faces of a large mesh (those scored alone): only their vertices projected
        used, corners_used = np.unique(groups.corners, return_inverse=True)
        vertices = vertices[used]
        groups = replace(groups, corners=corners_used.astype(np.int32).reshape(-1))
    sharp = frames.relative_sharpness() ** sharpness_weight * resolution_weights(frames.cameras)
    near_m, parallax_deg = _window_margins(frames.cameras)
    vertex_index = AzimuthIndex(vertices, near_m)
    n_groups = groups.count
    # everything below in azimuth order: vertex k is vertices[vertex_index.order[k]], group
    # position k is group face_ids[k], the groups ordered by their first corner's position:
    # the groups whose first corner lies in a range of vertices are a range of groups
    position = np.empty(len(vertices), dtype=np.int64)
    position[vertex_index.order] = np.arange(len(vertices))
    face_ids = np.argsort(position[groups.corners[groups.corner_start[:-1]]], kind="stable")
    # the group of each position as offered (int32 when it fits: the scores of up to three
    # frames are in flight, ~5 M for a 360° frame at lab scale)
    face_of = face_ids.astype(np.int32) if n_groups < 2 ** 31 else face_ids
    corner_count = np.diff(groups.corner_start)[face_ids]
    # every group three corners (faces): a column per corner, as the per-face path always
    # was; else the corners of a group in a ragged row (group positions' rows in order)
    triangles = bool((corner_count == 3).all())
    flat_corners = np.ascontiguousarray(
        position[groups.corners[ragged_slots(groups.corner_start, face_ids)]], dtype=np.int32)
    corner_start = np.zeros(n_groups + 1, np.int64)
    np.cumsum(corner_count, out=corner_start[1:])
    del corner_count
    corners = ([np.ascontiguousarray(flat_corners[k::3]) for k in range(3)] if triangles
               else [flat_corners[corner_start[:-1]]])
    del position
    # float32 vertex columns: the projection streams them for every frame (twice as fast as
    # float64, and well under 10⁻³ px off it: scanpipe.camera.project_columns)
    point_of = [np.ascontiguousarray(vertices[vertex_index.order, k], dtype=np.float32)
                for k in range(3)]
    centre_of = [np.ascontiguousarray(groups.centroid[face_ids, k], dtype=np.float32)
                 for k in range(3)]
    normal_of = [np.ascontiguousarray(groups.normal[face_ids, k], dtype=np.float32)
                 for k in range(3)]
    # cos θ = (n·c − n·p) / |c − p| from per-group constants and two dot products per frame
    n_dot_p = sum((normal_of[k] * centre_of[k] for k in range(1, 3)), normal_of[0] * centre_of[0])
    p_squared = sum((centre_of[k] * centre_of[k] for k in range(1, 3)), centre_of[0] * centre_of[0])
    kept = BestFrames(n_groups, keep, small=len(frames) < 2 ** 15)
    scratch = threading.local()  # per thread: u, v and valid of every vertex (azimuth order)

    # where the groups of each vertex position (as first corner) start: a frame's groups are
    # those of its window's vertices (a group wholly in view has its first corner in view)
    # (counted: the positions are small integers; a search for each took 8× as long)
    first_of = np.zeros(len(vertices) + 1, np.int64)
    np.cumsum(np.bincount(corners[0], minlength=len(vertices)), out=first_of[1:])

    def faces_in_view(seen: I64) -> I64:
        """Positions of the groups whose first corner is one of the vertex positions ``seen``
        (ascending, as ``seen``): every group with all its corners in view, and others. (Most
        of a phone's azimuth window is floor and ceiling outside its view.)"""
        start = first_of[seen]
        count = first_of[seen + 1] - start
        ragged = np.repeat(start - (np.cumsum(count) - count), count)
        ragged += np.arange(len(ragged))
        return ragged

    def cosines(select: slice | I64, centre: F32) -> F32:
        """cos θ of the faces at positions ``select`` (a slice, or gathered) seen from
        ``centre`` (in place, in the thread's buffers)."""
        size = len(p_squared[select])
        cos: F32 = scratch.cos[:size]
        distance: F32 = scratch.distance[:size]
        np.multiply(centre_of[0][select], centre[0], out=distance)
        distance += centre_of[1][select] * centre[1]
        distance += centre_of[2][select] * centre[2]
        distance *= np.float32(-2.0)
        distance += p_squared[select]
        distance += np.float32(centre @ centre)
        np.maximum(distance, np.float32(1e-24), out=distance)
        np.sqrt(distance, out=distance)
        np.multiply(normal_of[0][select], centre[0], out=cos)
        cos += normal_of[1][select] * centre[1]
        cos += normal_of[2][select] * centre[2]
        cos -= n_dot_p[select]
        cos /= distance
        if two_sided:
            np.abs(cos, out=cos)
        return cos

    def score_frame(i: int) -> list[tuple[I64, F32]]:
        if not hasattr(scratch, "u"):
            n_points = len(vertices)
            scratch.u = np.zeros(n_points, np.float32)
            scratch.v = np.zeros(n_points, np.float32)
            scratch.valid = np.zeros(n_points, dtype=bool)
            scratch.cos = np.empty(SCORE_CHUNK, np.float32)
            scratch.distance = np.empty(SCORE_CHUNK, np.float32)
        u, v, valid = scratch.u, scratch.v, scratch.valid
        cam = frames.cameras[i]
        beta = float(frames.beta_deg[i])
        window = view_window(cam, beta)
        if window is None:  # every direction in view
            vertex_ranges = [(0, len(vertices))]
            face_ranges = [(0, len(face_of))]
        else:
            window = (window[0], window[1] + parallax_deg)
            vertex_ranges = vertex_index.ranges(*window)
            face_ranges = [(int(first_of[a]), int(first_of[b])) for a, b in vertex_ranges]
            valid[:] = False
        for a, b in _pieces(vertex_ranges):
            x, y, z = (column[a:b] for column in point_of)
            u[a:b], v[a:b], _, valid[a:b] = project_valid_columns(x, y, z, cam, beta, margin_px)
        centre = frames.centre(i).astype(np.float32)
        weight = np.float32(sharp[i])
        out: list[tuple[I64, F32]] = []
        if window is not None and cam.model == "pinhole":
            # few of the window's faces in view: those of its vertices in view, gathered
            # (the same faces and scores, ~4× fewer looked at by a phone at lab scale)
            seen = np.flatnonzero(valid)
            if (first_of[seen + 1] - first_of[seen]).sum() < IN_VIEW_SHARE * sum(
                    b - a for a, b in face_ranges):
                return score_in_view(faces_in_view(seen), cam, centre, weight, u, v, valid)
        every_valid = window is None and bool(valid.all())
        all_positive = surely_positive(weight)
        for a, b in _pieces(face_ranges):
            # the angle first, over the contiguous slice; the corner look-ups then only for
            # the faces that face the camera
            cos = cosines(slice(a, b), centre)
            facing = np.flatnonzero(cos >= min_cos)
            if not triangles:  # groups: their corners in ragged rows, the slice's in a row
                first, last = int(corner_start[a]), int(corner_start[b])
                offset = corner_start[a:b] - first
                at = flat_corners[first:last]
                if not every_valid:
                    inside = np.logical_and.reduceat(valid[at], offset)
                    facing = facing[inside[facing]]
                score = cos[facing] * weight
                # (the image columns of corners out of view are any numbers: not used)
                with np.errstate(invalid="ignore", over="ignore"):
                    if cam.model == "equirect":
                        column = u[at]
                        spread = np.maximum.reduceat(column, offset)
                        spread -= np.minimum.reduceat(column, offset)
                        whole = spread[facing] <= cam.width / 4
                        facing, score = facing[whole], score[whole]
                    else:
                        count = np.diff(corner_start[a:b + 1]).astype(np.float32)
                        mean_u = np.add.reduceat(u[at], offset)[facing] / count[facing]
                        mean_v = np.add.reduceat(v[at], offset)[facing] / count[facing]
                        score *= pinhole_centrality(mean_u, mean_v, cam)
            elif cam.model == "equirect":
                # a 360° frame sees about every vertex: their look-ups only when some not
                # (each corner then looked up once: no conversion to the index type first)
                k0, k1, k2 = (corner[a:b][facing] for corner in corners)
                inside = ~wraps(u[k0], u[k1], u[k2], cam)
                if not every_valid:
                    inside &= valid[k0] & valid[k1] & valid[k2]
                facing = facing[inside]
                score = cos[facing] * weight
            else:
                c0, c1, c2 = (corner[a:b][facing].astype(np.intp) for corner in corners)
                inside = valid[c0] & valid[c1] & valid[c2]
                facing, c0, c1, c2 = facing[inside], c0[inside], c1[inside], c2[inside]
                score = cos[facing] * weight
                mean_u = (u[c0] + u[c1] + u[c2]) / 3
                mean_v = (v[c0] + v[c1] + v[c2]) / 3
                score *= pinhole_centrality(mean_u, mean_v, cam)
            if not all_positive:
                positive = score > 0  # a frame of sharpness 0 is of no use
                facing, score = facing[positive], score[positive]
            out.append((facing + a, np.asarray(score, dtype=np.float32)))
        return out

    def score_in_view(candidates: I64, cam: CameraConfig, centre: F32, weight: np.float32,
                      u: F32, v: F32, valid: NDArray[np.bool_]) -> list[tuple[I64, F32]]:
        """A pinhole frame's scores of the faces at positions ``candidates`` (as the loop
        over the window computes them: the same operations, on gathered per-face values)."""
        out: list[tuple[I64, F32]] = []
        for start in range(0, len(candidates), SCORE_CHUNK):
            face = candidates[start:start + SCORE_CHUNK]
            if not triangles and len(face):  # groups: their corners in ragged rows
                slots = ragged_slots(corner_start, face)
                count = corner_start[face + 1] - corner_start[face]
                offset = np.cumsum(count) - count
                at = flat_corners[slots]
                del slots
                held = np.flatnonzero(np.logical_and.reduceat(valid[at], offset))
                face = face[held]
                cos = cosines(face, centre)
                facing = np.flatnonzero(cos >= min_cos)
                face, kept_rows = face[facing], held[facing]
                score = cos[facing] * weight
                # (the image columns of corners out of view are any numbers: not used)
                with np.errstate(invalid="ignore", over="ignore"):
                    per = count[kept_rows].astype(np.float32)
                    mean_u = np.add.reduceat(u[at], offset)[kept_rows] / per
                    mean_v = np.add.reduceat(v[at], offset)[kept_rows] / per
                score *= pinhole_centrality(mean_u, mean_v, cam)
                if not surely_positive(weight):
                    positive = score > 0
                    face, score = face[positive], score[positive]
                out.append((face, np.asarray(score, dtype=np.float32)))
                continue
            if not triangles:
                continue
            # positions as the index type once (numpy converts int32 at every look-up)
            c0, c1, c2 = (corner[face].astype(np.intp) for corner in corners)
            inside = valid[c0] & valid[c1] & valid[c2]
            face, c0, c1, c2 = face[inside], c0[inside], c1[inside], c2[inside]
            cos = cosines(face, centre)
            facing = np.flatnonzero(cos >= min_cos)
            face, c0, c1, c2 = face[facing], c0[facing], c1[facing], c2[facing]
            score = cos[facing] * weight
            mean_u = (u[c0] + u[c1] + u[c2]) / 3
            mean_v = (v[c0] + v[c1] + v[c2]) / 3
            score *= pinhole_centrality(mean_u, mean_v, cam)
            if not surely_positive(weight):
                positive = score > 0
                face, score = face[positive], score[positive]
            out.append((face, np.asarray(score, dtype=np.float32)))
        return out

    def surely_positive(weight: np.float32) -> bool:
        """Whether every score of a face facing the camera is positive: each is at least
        min_cos × weight × 0.05 (the centrality's floor), here far from float32's underflow."""
        return min_cos * float(weight) * 0.05 > 1e-30

    def offers(i: int) -> list[tuple[NDArray[np.integer], F32]]:
        """Frame ``i``'s scores by face (renumbered from positions on the worker thread)."""
        return [(face_of[position], score) for position, score in score_frame(i)]

    del face_ids
    workers = worker_count(len(frames))
    # one frame per thread (numpy and OpenCV release the GIL); offered in frame order here, at
    # most one frame ahead (a 360° frame's scores are ~40 MB at lab scale)
    with thread_pool(workers) as pool:
        pending: deque[Future[list[tuple[NDArray[np.integer], F32]]]] = deque()
        submitted = 0
        for done in range(len(frames)):
            while submitted < len(frames) and len(pending) < workers + 1:
                pending.append(pool.submit(offers, submitted))
                submitted += 1
            for face, score in pending.popleft().result():
                kept.add(done, face, score)
            progress("score frames", done + 1, len(frames))
    return kept


@dataclass
class Selection:
    """The frame chosen for every face (−1: none), and what the occlusion test struck out."""

    frame: NDArray[np.int64]
    occluded_candidates: int
    rays_cast: int
    #: Candidates struck because the face itself turns its back on the frame (``facing``).
    backfacing_candidates: int = 0


#: Whether each face of the first array turns its front to the centre of the frame of the second.
Facing = Callable[[NDArray[np.integer], NDArray[np.integer]], NDArray[np.bool_]]


def select_frames_per_face(scores: Scores, frames: FrameSet, occlusion: MeshOcclusion,
                           progress: ProgressFn = no_progress,
                           faces: NDArray[np.integer] | None = None,
                           facing: Facing | None = None) -> Selection:
    """Each face's best frame in which it is wholly visible (see module docstring), from its
    kept frames (best first, −1 = none or struck out); only of the faces ``faces`` when given
    (the others −1). With ``facing``, a candidate the face turns its back on is struck before
    any ray is cast (a group's frames were scored by the group's mean normal: a member at a
    crease may face away from one of them).

    ``scores`` is modified: occluded (and back-facing) candidates are struck out.
    """
    n_faces, k = scores.faces, scores.keep
    chosen = np.full(n_faces, -1, dtype=np.int64)
    if len(frames) == 0 or n_faces == 0:
        return Selection(chosen, 0, 0)
    centres = np.stack([frames.centre(i) for i in range(len(frames))])
    has = scores.has_candidates()
    pending = (np.flatnonzero(has) if faces is None
               else np.sort(np.asarray(faces, np.int64)[has[faces]]))
    occluded = backfacing = 0
    rays_before = occlusion.rays_cast
    for slot in range(k):
        if len(pending) == 0:
            break
        best = scores.slot(pending, slot)
        struck = best < 0  # none left, or an outlier: try the next
        waiting, pending, best = pending[struck], pending[~struck], best[~struck]
        if facing is None:
            visible = occlusion.faces_visible_from(centres, best, pending)
        else:
            front = facing(pending, best)
            backfacing += int(len(front) - np.count_nonzero(front))
            visible = np.zeros(len(pending), dtype=bool)
            visible[front] = occlusion.faces_visible_from(centres, best[front], pending[front])
        chosen[pending[visible]] = best[visible]
        blocked = ~visible
        scores.strike_slot(pending[blocked], slot)
        occluded += int(blocked.sum())
        pending = np.sort(np.concatenate([pending[blocked], waiting]))
        progress("visibility", slot + 1, k)
    return Selection(chosen, occluded - backfacing, occlusion.rays_cast - rays_before,
                     backfacing)


def _turned_360_frames(cameras: list[CameraConfig], beta_deg: F64) -> dict[int, tuple[int, float]]:
    """Frames of a 360° camera that are another frame of it turned about the camera's own
    vertical axis (its centre on the motor axis, its y axis along it: the usual mount), as
    ``{frame: (first frame, column shift px)}``: their pixels are the first frame's, ``u``
    shifted (and wrapped), ``v`` and the distance the same. A camera any of whose frames is
    not so (a tilted or off-axis mount) is not listed: its frames are projected each."""
    first: dict[str, int] = {}
    turned: dict[int, tuple[int, float]] = {}
    bad: set[str] = set()
    for i, cam in enumerate(cameras):
        if cam.model != "equirect" or cam.id in bad:
            continue
        ref = first.setdefault(cam.id, i)
        r_ref, t_ref = camera_pose_in_rig(cameras[ref], float(beta_deg[ref]))
        r_i, t_i = camera_pose_in_rig(cam, float(beta_deg[i]))
        turn = r_i.T @ r_ref  # camera coordinates of frame i from those of frame ref
        about_y = np.array([[turn[0, 0], 0.0, turn[0, 2]], [0.0, 1.0, 0.0],
                            [-turn[0, 2], 0.0, turn[0, 0]]])
        # 10⁻⁹ rad off a turn about y moves a pixel by under 10⁻⁵ of a pixel
        if (cam != cameras[ref] or np.abs(turn - about_y).max() > 1e-9
                or np.abs(t_i - t_ref).max() > 1e-9):
            bad.add(cam.id)
            continue
        # longitude atan2(x, z) grows by the turn's angle
        shift_rad = math.atan2(turn[0, 2], turn[0, 0])  # within ±π: u moves under a width
        turned[i] = (ref, shift_rad * cam.width / (2 * math.pi))
    return {i: v for i, v in turned.items() if cameras[i].id not in bad}


def colorize_points(
    points: pa.Table,
    frames: pa.Table,
    motor: pa.Table,
    rig: Rig,
    *,
    spacing_deg: float = 5.0,
    neutral_rgb: tuple[int, int, int] = (128, 128, 128),
    cell_px: int = 6,
    progress: ProgressFn = no_progress,
    frames_chosen: Callable[[], object] | None = None,
) -> pa.Table:
    """``points`` with ``red``, ``green``, ``blue`` (uint8) from the camera frames.

    Each point takes the pixel of the frame (one per ``spacing_deg`` of platform angle and
    camera, the sharpest; for a 360° camera one per :data:`EQUIRECT_SPACING_DEG`) where it
    lies nearest the image centre (weighed by the camera's angular resolution) among the
    frames that see it.
    Occlusion is a z-buffer of the points themselves in ``cell_px`` cells: a point more than
    3 cm + 1 % behind the nearest point of its cell is hidden. Points no frame sees get
    ``neutral_rgb``. Called by the export stage for coloured point clouds (PLY, LAS, E57).

    Only the points inside a frame's azimuth window (:func:`view_window`, widened by the
    camera's parallax; those near the axis always) are projected into it: the points are
    sorted by azimuth once, so a window is a few contiguous slices. Every point a frame sees
    is in its window, so the colours are those of projecting every point into every frame.
    A 360° camera upright on the axis is projected once (:func:`_turned_360_frames`).
    Each frame is decoded once, and only when it gives some point its colour; the frames one
    at a time. ``frames_chosen`` is called once the frames are chosen (their bytes copied):
    from then on this function holds no reference to ``frames``, so a caller that drops its
    own lets the table go while the points are coloured (the export stage).
    """
    for name in ("x", "y", "z"):
        if name not in points.column_names:
            raise StageError(f"points: missing column {name!r}")
    columns = [points.column(n).to_numpy(zero_copy_only=False) for n in "xyz"]
    chosen = choose_frames(frames, motor, rig, spacing_deg, progress=progress,
                           equirect_spacing_deg=max(spacing_deg, EQUIRECT_SPACING_DEG))
    del frames
    if frames_chosen is not None:
        frames_chosen()
    # each frame is decoded once and used at once: no decoded frame is kept beside it
    chosen.cache_size = 0
    resolution = resolution_weights(chosen.cameras)
    near_m, parallax_deg = _window_margins(chosen.cameras)
    # float64 azimuths: searchsorted then never converts them
    index = AzimuthIndex(np.stack(columns, axis=1).astype(np.float64), near_m)
    # every per-point array below is in azimuth order: position k is point index.order[k];
    # the coordinate columns as the artifact holds them, projected in float32 as the texture
    # stage projects (:func:`scanpipe.camera.project_columns`: well under 10⁻³ px off float64,
    # twice as fast)
    ordered = [np.asarray(c, dtype=np.float32)[index.order] for c in columns]
    del columns
    count = len(ordered[0])
    # (position, pixel row × width + col, score: one for all of a 360° frame's points)
    Piece = tuple[NDArray[np.int64], I32, "F64 | float"]

    # a 360° camera's frames see every point: where they are one frame turned (the usual
    # mount), every point is projected once, into the first, and the others' columns shifted
    turned = _turned_360_frames(chosen.cameras, chosen.beta_deg)
    first_views: dict[int, tuple[F32, F32, F32]] = {}
    for ref in sorted({ref for ref, _ in turned.values()}):
        views = [project_valid_columns(
            ordered[0][a:b], ordered[1][a:b], ordered[2][a:b], chosen.cameras[ref],
            float(chosen.beta_deg[ref]), 0.0)[:3] for a, b in _pieces([(0, count)])]
        first_views[ref] = (np.concatenate([w[0] for w in views]),
                            np.concatenate([w[1] for w in views]),
                            np.concatenate([w[2] for w in views]))
        del views

    def turned_columns(i: int, start: int, stop: int
                       ) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any], NDArray[np.bool_]]:
        """:func:`project_valid_columns` (margin 0) of positions ``start:stop`` in a turned
        360° frame ``i``, from its first frame's projection."""
        cam = chosen.cameras[i]
        ref, shift_px = turned[i]
        u0, v, depth = (view[start:stop] for view in first_views[ref])
        u = u0 + np.float32(shift_px)
        # back into the image's columns (−½, width − ½], as the longitude wraps
        np.subtract(u, np.float32(cam.width), out=u, where=u > cam.width - 0.5)
        np.add(u, np.float32(cam.width), out=u, where=u <= -0.5)
        valid = depth > 0.05  # project_valid_columns' near_m
        valid &= u >= 0.0
        valid &= u <= cam.width - 1
        valid &= v >= 0.0
        valid &= v <= cam.height - 1
        return u, v, depth, valid

    def visible(i: int) -> list[Piece]:
        """Frame ``i``'s points in front (z-buffer) that it colours better than so far, as
        pieces ``(position, pixel, score)``: first the z-buffer over every point of the
        window, in cache-sized pieces (the projection's temporaries then stay in the cache:
        several times faster)."""
        cam, beta = chosen.cameras[i], float(chosen.beta_deg[i])
        window = view_window(cam, beta)
        ranges = ([(0, count)] if window is None
                  else index.ranges(window[0], window[1] + parallax_deg))
        cells_w = cam.width // cell_px + 1
        nearest = np.full((cam.height // cell_px + 1) * cells_w, np.inf, np.float32)
        pieces = []
        for a, b in ranges:
            for start in range(a, b, COLOUR_CHUNK_POINTS):
                stop = min(b, start + COLOUR_CHUNK_POINTS)
                if i in turned:
                    u, v, depth, valid = turned_columns(i, start, stop)
                else:
                    u, v, depth, valid = project_valid_columns(
                        ordered[0][start:stop], ordered[1][start:stop],
                        ordered[2][start:stop], cam, beta, 0.0)
                local = np.flatnonzero(valid)
                if len(local) == 0:
                    continue
                if len(local) < len(valid):  # a 360° camera's frame sees every point
                    u, v, depth = u[local], v[local], depth[local]
                # valid (margin 0) keeps 0 ≤ u ≤ width − 1 and 0 ≤ v ≤ height − 1: no clip
                col = np.rint(u).astype(np.int32)
                row = np.rint(v).astype(np.int32)
                cell = row // cell_px
                cell *= cells_w
                cell += col // cell_px
                np.minimum.at(nearest, cell, depth)
                score: F64 | float = (
                    float(resolution[i]) if cam.model == "equirect"
                    else pinhole_centrality(u, v, cam) * resolution[i])
                row *= cam.width
                row += col
                pieces.append((local + start, depth, cell, row, score))
        out: list[Piece] = []
        while pieces:  # each piece's arrays go as its visible part is kept
            idx, depth, cell, pixel, score = pieces.pop(0)
            limit = nearest[cell]
            limit += 0.03
            limit += 0.01 * depth
            # in front, and better than the point's colour so far (a point is in one piece
            # of a frame: ``best`` changes for it only after this test)
            better = depth <= limit
            better &= best[idx] < score
            out.append((idx[better], pixel[better],
                        score if isinstance(score, float) else score[better]))
        return out

    best = np.zeros(count, dtype=np.float64)
    # colours as the frames hold them (BGR), one 3-byte item per point: gathering and
    # scattering whole pixels is several times faster than (n, 3) fancy indexing
    bgr = np.tile(np.asarray(neutral_rgb[::-1], dtype=np.uint8), (count, 1))
    bgr_items = bgr.reshape(-1).view("V3")
    # one frame at a time: projecting frames on worker threads gave no CPU back and kept
    # ~400 MB more resident (per-thread malloc arenas) into the rest of the export. Only the
    # frame's decode (OpenCV, without the GIL) runs on a thread of its own, beside its
    # projection, when there is a core for it (else it is decoded only if it gives a colour):
    # one decoded frame more at a time (≤ 22 MB, 33 MB traced at lab scale), below the
    # export's peak, which is later.
    from concurrent.futures import ThreadPoolExecutor

    ahead = worker_count(len(chosen), limit=2) > 1
    decoder = ThreadPoolExecutor(1, thread_name_prefix="decode") if ahead else None
    try:
        for i in range(len(chosen)):
            decoding = decoder.submit(chosen.image, i) if decoder is not None else None
            pixels = None
            for idx, pixel, score in visible(i):
                if len(idx) == 0:
                    continue
                if pixels is None:
                    image = chosen.image(i) if decoding is None else decoding.result()
                    pixels = np.ascontiguousarray(image).reshape(-1).view("V3")
                    del image
                best[idx] = score
                bgr_items[idx] = pixels[pixel]
            del decoding, pixels  # a frame that gave no colour: its image goes now
            progress("colour points", i + 1, len(chosen))
    finally:
        if decoder is not None:
            decoder.shutdown(wait=True)
    colours = np.empty_like(bgr)
    colours.reshape(-1).view("V3")[index.order] = bgr_items
    del bgr, bgr_items
    table = points
    for k, name in enumerate(("red", "green", "blue")):
        column = pa.array(colours[:, 2 - k], pa.uint8())
        if name in table.column_names:
            table = table.set_column(table.column_names.index(name), name, column)
        else:
            table = table.append_column(name, column)
    return table
