"""Face groups: small, spatially coherent sets of faces that the texture stage scores, samples
and ranks frames for together (docs/texture.md, "Face groups").

A lab-scale mesh has millions of faces of a few frame pixels each: a frame choice cannot tell
neighbours apart, yet scoring every face in every frame was most of the stage. Faces are
grouped by a voxel of their centroid (any mesh, not only a scan grid), each voxel's faces cut
into runs of at most ``max_faces``; a face turned far from its voxel's mean normal (a crease)
goes alone. A group is held by its
distinct corners (a frame holds a group whole when it holds every one of them: then it holds
each of its faces whole, exactly), its area-weighted normal and centroid. Groups of one face
are the faces themselves: their corners in the face's order, their own normal and centroid,
so that scoring them is today's per-face scoring, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]

#: The voxel side is this many times the side of a square of ``max_faces`` median faces
#: (a voxel cuts a surface obliquely and at its edges: it holds fewer faces than its area).
VOXEL_SCALE = 2.0
#: A group spans at most about this many pixels of the finest camera at the surface's median
#: distance (a frame choice at a few pixels is as fine as one per face: the lab's 2-pixel
#: faces are grouped, a coarse mesh's faces are not).
GROUP_PX = 24.0
#: A face whose normal is further than acos(this) ≈ 60° from its voxel's mean goes alone.
CREASE_COS = 0.5


@dataclass
class FaceGroups:
    """A partition of a mesh's faces into groups.

    ``of`` ``(faces,)`` the group of each face; ``members`` the faces group by group, group
    ``g``'s in ``members[member_start[g]:member_start[g + 1]]``; ``corners`` the distinct
    corner vertices group by group, ``corner_start`` likewise; ``normal`` and ``centroid``
    ``(groups, 3)``.
    """

    of: I32
    members: I64
    member_start: I64
    corners: I32
    corner_start: I64
    normal: F64
    centroid: F64
    @property
    def count(self) -> int:
        """Number of groups."""
        return len(self.member_start) - 1

    @property
    def sizes(self) -> I64:
        """Faces per group."""
        return np.diff(self.member_start)

    def faces_of(self, groups: NDArray[np.integer]) -> I64:
        """The faces of ``groups``, group by group."""
        return self.members[ragged_slots(self.member_start, np.asarray(groups, np.int64))]


def ragged_slots(start: I64, rows: I64) -> I64:
    """Flat positions of rows ``rows`` of a ragged array whose row ``r`` is
    ``[start[r], start[r + 1])``, row after row."""
    first = start[rows]
    count = start[rows + 1] - first
    offset = np.cumsum(count) - count
    slots = np.repeat(first - offset, count)
    slots += np.arange(len(slots))
    return slots


def single_faces(faces: NDArray[np.integer], normals: F64, centroids: F64,
                 face_ids: NDArray[np.integer] | None = None) -> FaceGroups:
    """Every face (or every face in ``face_ids``) its own group (today's per-face path):
    corners in the face's order, its own normal and centroid."""
    ids = (np.arange(len(faces), dtype=np.int64) if face_ids is None
           else np.asarray(face_ids, np.int64))
    n = len(ids)
    of = np.full(len(faces), -1, np.int32)
    of[ids] = np.arange(n, dtype=np.int32)
    corners = np.ascontiguousarray(np.asarray(faces)[ids], dtype=np.int32).reshape(-1)
    return FaceGroups(of, ids, np.arange(n + 1, dtype=np.int64), corners,
                      3 * np.arange(n + 1, dtype=np.int64), normals[ids], centroids[ids])


def face_groups(faces: NDArray[np.integer], normals: F64, areas: F64, centroids: F64,
                max_faces: int, max_voxel_m: float = math.inf) -> FaceGroups:
    """Group the faces (see the module docstring); ``max_faces`` ≤ 1: every face alone.
    ``max_voxel_m`` caps the voxel's side (the stage: what spans ``group_px`` frame pixels,
    :data:`GROUP_PX` by default), so that coarse faces, each already many pixels, are not
    grouped further."""
    faces = np.asarray(faces)
    n = len(faces)
    if max_faces <= 1 or n == 0:
        return single_faces(faces, normals, centroids)
    positive = areas[::16][areas[::16] > 0]  # a sample is enough for a typical face
    face_side = float(np.sqrt(np.median(positive))) if len(positive) else 1.0
    voxel_m = max(min(VOXEL_SCALE * face_side * math.sqrt(max_faces), max_voxel_m), 1e-9)
    if voxel_m < 2.0 * face_side:  # a voxel of a few faces at most: every face alone
        return single_faces(faces, normals, centroids)
    lo = centroids.min(axis=0)
    # the voxel's cell on each axis, packed with the normal's bucket into one int64 key
    hi = centroids.max(axis=0)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        return single_faces(faces, normals, centroids)  # a vertex not finite: no voxels
    while sum(max(1, int((hi[k] - lo[k]) / voxel_m).bit_length()) for k in range(3)) > 40:
        voxel_m *= 2.0  # a huge room of tiny faces: coarser voxels rather than an overflow
    bits = [max(1, int((hi[k] - lo[k]) / voxel_m).bit_length()) for k in range(3)]
    key = np.zeros(n, np.int64)
    for k in range(3):  # a column at a time: no (faces, 3) temporaries
        key <<= bits[k]
        cell = centroids[:, k] - lo[k]
        cell /= voxel_m
        key |= cell.astype(np.int64)  # ≥ 0: truncation is the floor
    del cell
    order = _radix_order(key, sum(bits))
    sorted_key = key[order]
    del key
    new_run = np.empty(n, dtype=bool)
    new_run[0] = True
    np.not_equal(sorted_key[1:], sorted_key[:-1], out=new_run[1:])
    del sorted_key
    # a face turned far from its voxel's mean normal (a crease: a wall meets the floor, an
    # object's edge) is not scored by that mean: it goes alone, after the others
    run_of = np.cumsum(new_run) - 1
    run_start = np.flatnonzero(new_run)
    mean = np.empty((len(run_start), 3))
    for c in range(3):
        mean[:, c] = np.add.reduceat(normals[order, c], run_start)
    mean /= np.maximum(np.sqrt(np.einsum("ij,ij->i", mean, mean)), 1e-20)[:, None]
    dot = np.zeros(n)
    for c in range(3):
        dot += normals[order, c] * mean[run_of, c]
    crease = dot < CREASE_COS
    del dot, mean
    if crease.any():
        order = np.r_[order[~crease], order[crease]]
        run_of = np.r_[run_of[~crease], len(run_start) + np.arange(int(crease.sum()))]
        new_run = np.r_[True, run_of[1:] != run_of[:-1]]
        run_start = np.flatnonzero(new_run)
        run_of = np.cumsum(new_run) - 1
    del crease
    # a run longer than max_faces is cut into pieces of at most max_faces, in its order
    within = np.arange(n) - run_start[run_of]
    new_group = new_run | (within % max_faces == 0)
    del new_run, run_of, within, run_start
    member_start = np.r_[np.flatnonzero(new_group), n].astype(np.int64)
    group_sorted = (np.cumsum(new_group) - 1).astype(np.int32)
    del new_group
    of = np.empty(n, np.int32)
    of[order] = group_sorted
    sizes = np.diff(member_start)
    # area-weighted normal and centroid of every group (a singleton's are its face's own)
    weight = areas[order]
    weight_sum = np.add.reduceat(weight, member_start[:-1])
    safe = np.where(weight_sum > 0, weight_sum, 1.0)
    normal = np.empty((len(sizes), 3))
    centroid = np.empty((len(sizes), 3))
    plain = weight_sum <= 0  # faces of no area: the plain mean
    for c in range(3):
        column = normals[order, c]
        normal[:, c] = np.add.reduceat(column * weight, member_start[:-1])
        if plain.any():
            normal[plain, c] = np.add.reduceat(column, member_start[:-1])[plain]
        column = centroids[order, c]
        centroid[:, c] = np.add.reduceat(column * weight, member_start[:-1]) / safe
        if plain.any():
            centroid[plain, c] = (np.add.reduceat(column, member_start[:-1])[plain]
                                  / sizes[plain])
    normal /= np.maximum(np.sqrt(np.einsum("ij,ij->i", normal, normal)), 1e-20)[:, None]
    single = np.flatnonzero(sizes == 1)
    normal[single] = normals[order[member_start[single]]]
    centroid[single] = centroids[order[member_start[single]]]
    corners = np.ascontiguousarray(np.asarray(faces)[order], dtype=np.int32).reshape(-1)
    return FaceGroups(of, order.astype(np.int64), member_start, corners, 3 * member_start,
                      normal, centroid)


def _radix_order(key: I64, bits: int) -> I64:
    """A stable order of the non-negative ``key`` (``bits`` wide): least significant 16 bits
    first, each digit by numpy's stable sort of uint16 (a radix sort: a few times faster than
    a comparison sort of the int64 keys)."""
    order = np.arange(len(key))
    for shift in range(0, max(bits, 1), 16):
        digit = ((key[order] >> shift) & 0xFFFF).astype(np.uint16)
        order = order[np.argsort(digit, kind="stable")]
    return order


def split_into_singles(groups: FaceGroups, faces: NDArray[np.integer], face_ids: I64,
                       normals: F64, centroids: F64) -> tuple[FaceGroups, I64]:
    """``groups`` with each face of ``face_ids`` moved into a new group of its own (appended,
    in ``face_ids``' order; ``normals`` and ``centroids`` theirs, a row each); the old groups
    keep their numbers (a group left empty keeps its corners: it is no face's). Also the new
    groups' numbers."""
    ids = np.asarray(face_ids, np.int64)
    first = groups.count
    singles = single_faces(np.asarray(faces)[ids], normals, centroids)
    of = groups.of.copy()
    of[ids] = first + np.arange(len(ids), dtype=np.int32)
    # members: the moved faces taken out of their old groups
    moved = np.zeros(len(of), dtype=bool)
    moved[ids] = True
    stay = ~moved[groups.members]
    group_of_member = np.repeat(np.arange(first), np.diff(groups.member_start))
    kept_per_group = np.bincount(group_of_member[stay], minlength=first).astype(np.int64)
    member_start = np.zeros(first + len(ids) + 1, np.int64)
    np.cumsum(np.r_[kept_per_group, np.ones(len(ids), np.int64)], out=member_start[1:])
    result = FaceGroups(
        of, np.r_[groups.members[stay], ids], member_start,
        np.r_[groups.corners, singles.corners].astype(np.int32),
        np.r_[groups.corner_start, groups.corner_start[-1] + singles.corner_start[1:]],
        np.concatenate([groups.normal, singles.normal]),
        np.concatenate([groups.centroid, singles.centroid]))
    return result, first + np.arange(len(ids), dtype=np.int64)
