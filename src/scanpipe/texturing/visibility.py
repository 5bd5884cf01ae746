"""Is a surface point seen from a camera centre? Rays against the mesh (Open3D RaycastingScene).

A face counts as visible from a camera only when points on it are all unobstructed: its
centroid, its corners and the middles of its edges — seven points — and for a face with an edge
longer than :data:`DENSE_EDGE_M` also points at a quarter and three quarters of each edge
(pulled 5 % towards the centroid; thirteen), so that a sliver hidden along an edge of a large
face is found. A face half hidden behind an edge or a thin object is not textured from that
frame. Faces tested from the same camera centre share the rays to their common corners and
edge middles (a corner of a scan-grid mesh belongs to six faces, an edge to two: about three
rays per face instead of seven); a ray that reaches the point but hits a neighbouring face
there is within the distance tolerance.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import StageError
from scanpipe.texturing.frames import worker_count
from scanpipe.threads import thread_pool

F64 = NDArray[np.float64]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]
#: Where the corner samples sit between the centroid (0) and the corner (1).
CORNER_INSET = 0.95
#: Faces with an edge longer than this (m) are tested at 13 points, others at 7.
DENSE_EDGE_M = 0.05
#: Of :meth:`MeshOcclusion.face_samples`, the seven tested on every face.
BASE_SAMPLES = np.array([0, 1, 2, 3, 7, 8, 9])
#: Of :meth:`MeshOcclusion.face_samples`, the six more tested on faces with long edges.
DENSE_SAMPLES = np.array([4, 5, 6, 10, 11, 12])
#: Face slots whose edge keys :func:`mesh_edges` compares at once.
EDGE_BLOCK_SLOTS = 1 << 21
#: Faces whose neighbours :meth:`MeshEdges.neighbours` finds at once.
NEIGHBOUR_BLOCK_FACES = 1 << 20
#: Faces whose rays :meth:`MeshOcclusion.faces_visible` casts at once (≤ 1.7 M rays; at lab
#: scale 0.2 % more rays than blocks twice as large, whose temporaries held 0.13 GB more).
FACES_PER_CAST = 1 << 17


def _sample_weights() -> NDArray[np.float32]:
    """``(13, 3)``: each of :meth:`MeshOcclusion.face_samples` as weights of the corners."""
    corners = np.eye(3)
    centroid = corners.mean(axis=0)
    following = np.roll(corners, -1, axis=0)
    edge_points = [(1 - t) * corners + t * following for t in (0.25, 0.5, 0.75)]
    inset = centroid + CORNER_INSET * (np.concatenate([corners, *edge_points]) - centroid)
    return np.concatenate([centroid[None], inset]).astype(np.float32)


SAMPLE_WEIGHTS = _sample_weights()
BASE_WEIGHTS = SAMPLE_WEIGHTS[BASE_SAMPLES]
DENSE_WEIGHTS = SAMPLE_WEIGHTS[DENSE_SAMPLES]


@dataclass
class MeshEdges:
    """The undirected edges of a triangle mesh, found once for the occlusion test, the face
    neighbours of the seam step and the seam strip.

    ``ids`` ``(faces, 3)``: an id per edge (numbered in the order of ``lo · V + hi`` of its
    vertices), the edge from corner k to k + 1; ``count`` edges. ``pair_slots`` ``(E, 2)``: per
    edge used by exactly two faces (non-manifold edges left out), in edge-id order, the two
    face slots ``k · faces + face`` that use it, the lower first (int32 where they fit).
    """

    ids: I32
    count: int
    pair_slots: NDArray[np.signedinteger[Any]]
    _edge_pair: I32 | None = field(default=None, repr=False)  # per edge, its pair or −1

    def pairs(self) -> I64:
        """``(E, 2)`` the faces sharing each two-face edge; the pairs of
        :func:`scanpipe.texturing.exposure.shared_edges`, in its order."""
        return np.asarray(self.pair_slots % max(len(self.ids), 1), dtype=np.int64)

    def vertices(self, faces: NDArray[np.integer], rows: NDArray[np.integer] | None = None
                 ) -> I64:
        """``(E, 2)`` the vertices of each two-face edge (or of the edges ``rows`` of
        :meth:`pairs`), lower first (as ``shared_edges``)."""
        n = len(self.ids)
        slot = self.pair_slots[:, 0] if rows is None else self.pair_slots[rows, 0]
        face, corner = slot % max(n, 1), slot // max(n, 1)
        a = faces[face, corner].astype(np.int64)
        b = faces[face, (corner + 1) % 3].astype(np.int64)
        return np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)

    def neighbours(self, rows: NDArray[np.integer] | None = None) -> I64:
        """``(faces, 3)`` the faces sharing a two-face edge with each face (or each face in
        ``rows``), −1 padded: first the pairs the face is first in, then those it is second
        in, each in edge order (the order a stable sort of both directions of :meth:`pairs`
        by face gives), without a sort."""
        n = len(self.ids)
        if self._edge_pair is None:
            # per edge (not per face slot: half the memory) its pair, −1 for an edge of one
            # face or of three and more
            edge_pair = np.full(self.count, -1, dtype=np.int32)
            slot = self.pair_slots[:, 0]
            edge_pair[self.ids[slot % max(n, 1), slot // max(n, 1)]] = np.arange(
                len(self.pair_slots), dtype=np.int32)
            self._edge_pair = edge_pair
        faces = np.arange(n) if rows is None else np.asarray(rows, dtype=np.int64)
        if len(self.pair_slots) == 0:  # no face shares an edge
            return np.full((len(faces), 3), -1, dtype=np.int64)
        result = np.empty((len(faces), 3), dtype=np.int64)
        big = 2 * len(self.pair_slots) + 2
        # in blocks of faces: the temporaries of the whole mesh at once were ~0.6 GB at lab scale
        for start in range(0, len(faces), NEIGHBOUR_BLOCK_FACES):
            block = faces[start:start + NEIGHBOUR_BLOCK_FACES]
            pair = self._edge_pair[self.ids[block]]  # (faces, 3) by corner k
            has = pair >= 0
            safe = np.maximum(pair, 0)
            first_slot, second_slot = self.pair_slots[safe, 0], self.pair_slots[safe, 1]
            second = second_slot == block[:, None] + n * np.arange(3)
            # the other face of the pair: its slot modulo the face count
            other = np.where(second, first_slot, second_slot) % max(n, 1)
            other[~has] = -1
            # a face's edges in order: first-owned before second-owned, then by edge order,
            # the unpaired last (by corner): distinct keys within a face, ranks 0, 1, 2
            key = np.where(has, second * (len(self.pair_slots) + 1) + pair,
                           big + np.arange(3, dtype=np.int64))
            rank = (key[:, :, None] > key[:, None, :]).sum(axis=2)
            np.put_along_axis(result[start:start + len(block)], rank, other, axis=1)
        return result

    def seam_faces(self, labels: I64) -> tuple[I64, int]:
        """The faces (ascending) on an edge between two labelled faces (label ≥ 0) of
        different labels, and the number of such edges; in blocks of edges."""
        n = len(self.ids)
        on_seam = np.zeros(n, dtype=bool)
        count = 0
        for start in range(0, len(self.pair_slots), NEIGHBOUR_BLOCK_FACES):
            slots = self.pair_slots[start:start + NEIGHBOUR_BLOCK_FACES]
            a, b = slots[:, 0] % max(n, 1), slots[:, 1] % max(n, 1)
            la, lb = labels[a], labels[b]
            seam = (la >= 0) & (lb >= 0) & (la != lb)
            count += int(seam.sum())
            on_seam[a[seam]] = True
            on_seam[b[seam]] = True
        return np.flatnonzero(on_seam), count

def mesh_edges(faces: NDArray[np.integer], n_vertices: int | None = None) -> MeshEdges:
    """The :class:`MeshEdges` of ``faces`` (one sort of the face slots' edge keys)."""
    faces = np.asarray(faces)
    n = len(faces)
    if n_vertices is None:
        n_vertices = int(faces.max(initial=-1)) + 1
    key = np.empty((3, n), dtype=np.int64)  # edge-major: slot k · n + face
    for k in range(3):
        a, b = faces[:, k], faces[:, (k + 1) % 3]
        key[k] = np.minimum(a, b)  # in the faces' own type, widened on the store
        key[k] *= max(n_vertices, 1)
        key[k] += np.maximum(a, b)
    flat = key.reshape(-1)
    order = np.argsort(flat, kind="stable")
    # where the sorted keys change, in blocks (no sorted copy of all keys beside them)
    new = np.empty(len(order), dtype=bool)
    for start in range(0, len(order), EDGE_BLOCK_SLOTS):
        block = flat[order[start:start + EDGE_BLOCK_SLOTS]]
        new[start] = start == 0 or bool(block[0] != flat[order[start - 1]])
        np.not_equal(block[1:], block[:-1], out=new[start + 1:start + len(block)])
    del key, flat
    starts = np.flatnonzero(new)
    ids = np.empty(3 * n, dtype=np.int32)
    number = np.cumsum(new, dtype=np.int32)
    number -= 1
    ids[order] = number
    del new, number
    count = len(starts)
    first = starts[np.diff(starts, append=3 * n) == 2]  # edges of exactly two face slots
    del starts
    # slots (< 3 · faces) as int32 where they fit: the pairs are held through rays and seams
    pair_slots = np.empty((len(first), 2), dtype=np.int32 if 3 * n < 2 ** 31 else np.int64)
    pair_slots[:, 0] = order[first]
    first += 1
    pair_slots[:, 1] = order[first]
    del order, first
    by_face = np.ascontiguousarray(ids.reshape(3, n).T)
    return MeshEdges(by_face, count, pair_slots)


class MeshOcclusion:
    """Occlusion tests against one triangle mesh."""

    def __init__(self, vertices: NDArray[np.floating], faces: NDArray[np.integer],
                 edges: MeshEdges | None = None) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.asarray(faces)
        # int32 faces (the stage's) are shared, not copied: indices are never negative
        self.faces = (faces.view(np.uint32) if faces.dtype == np.int32
                      and faces.flags.c_contiguous else np.ascontiguousarray(faces, np.uint32))
        #: Rays cast so far.
        self.rays_cast = 0
        self._edges = edges
        self._dense: NDArray[np.bool_] | None = None
        self._rank: I32 | None = None
        self._vertex_columns: list[NDArray[np.float32]] | None = None
        # per thread: scratch for sharing points between the faces of a block (_visible_from)
        self._scratch = threading.local()
        self._lock = threading.Lock()
        if edges is not None and len(self.faces):
            # the per-face flags before the tree: their temporaries are gone when it is built
            # (the peak of the stage is the tree and what the rays hold beside it)
            self.dense_faces()
            self.locality_rank()
        import open3d as o3d  # here, not at import: every command would pay ~0.8 s for it

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        if len(self.faces):
            try:
                self._scene.add_triangles(o3d.core.Tensor.from_numpy(self.vertices),
                                          o3d.core.Tensor.from_numpy(self.faces))
                # Embree builds its tree at the first query: here, so that the time and the
                # memory show where the scene is made
                probe = np.zeros((1, 6), np.float32)
                self._scene.test_occlusions(o3d.core.Tensor.from_numpy(probe))
            except RuntimeError as err:
                raise StageError(f"mesh: Open3D could not build a ray-casting scene ({err})"
                                 ) from err

    @property
    def edges(self) -> MeshEdges:
        """The mesh's :class:`MeshEdges` (found at the first use)."""
        if self._edges is None:
            self._edges = mesh_edges(self.faces, len(self.vertices))
        return self._edges

    def face_samples(self, face_ids: NDArray[np.integer]) -> NDArray[np.float32]:
        """``(len(face_ids), 13, 3)``: centroid, inset corners, inset points at ¼, ½ and ¾ of
        each edge, per face (:data:`BASE_SAMPLES` picks centroid, corners and middles)."""
        return np.asarray(np.matmul(SAMPLE_WEIGHTS, self.vertices[self.faces[face_ids]]),
                          dtype=np.float32)

    def unobstructed(self, origins: NDArray[np.floating], points: NDArray[np.floating],
                     abs_tol_m: float = 0.01, rel_tol: float = 0.005) -> NDArray[np.bool_]:
        """True where the segment origin → point reaches the point first.

        ``origins`` (``(M, 3)`` or one ``(3,)``) and ``points`` ``(M, 3)``, points on the mesh. A
        hit no closer than ``abs_tol_m + rel_tol · distance`` before the point counts as
        unobstructed. Open3D's any-hit occlusion test over the segment up to that limit (Embree
        stops at the first hit it finds; 10× cheaper than finding the nearest hit): the face a
        point lies on can only be hit at the point itself, beyond the limit.
        """
        if len(points) == 0:
            return np.zeros(0, dtype=bool)
        # float32 throughout (what Open3D casts in; µm at room scale): this runs on millions
        start = np.asarray(origins, np.float32)
        delta = np.subtract(np.asarray(points).T, start.T if start.ndim == 2 else start[:, None],
                            dtype=np.float32)
        return self._cast(start, delta, abs_tol_m, rel_tol)

    def _cast(self, origins: NDArray[np.float32], delta: NDArray[np.float32], abs_tol_m: float,
              rel_tol: float) -> NDArray[np.bool_]:
        """:meth:`unobstructed` of the segments from ``origins`` (``(3,)`` or ``(M, 3)``) by
        ``delta`` ``(3, M)`` (point − origin, a row per coordinate: each pass over contiguous
        numbers; the same float32 sums as over (M, 3) rows)."""
        rays = np.empty((delta.shape[1], 6), dtype=np.float32)
        rays[:, :3] = origins
        distance = delta[0] * delta[0]
        for c in (1, 2):
            distance += delta[c] * delta[c]
        np.sqrt(distance, out=distance)
        limit = distance * np.float32(1 - rel_tol)
        limit -= np.float32(abs_tol_m)
        # the direction spans the segment up to the limit: t in [0, 1] for every ray
        scale = np.maximum(limit, 0.0)
        scale /= np.maximum(distance, 1e-12)
        del distance
        for c in range(3):
            np.multiply(delta[c], scale, out=rays[:, 3 + c])
        with self._lock:
            self.rays_cast += len(rays)
        occluded = self._scene.test_occlusions(self._o3d.core.Tensor.from_numpy(rays),
                                               tnear=0.0, tfar=1.0).numpy()
        return np.asarray(~occluded | (limit <= 0))

    def faces_visible(self, origins: NDArray[np.floating], face_ids: NDArray[np.integer],
                      abs_tol_m: float = 0.01, rel_tol: float = 0.005,
                      views: NDArray[np.integer] | None = None) -> NDArray[np.bool_]:
        """True where face ``face_ids[i]`` is wholly visible from camera centre ``origins[i]``.

        ``views[i]`` names the origin (a frame number; found from ``origins`` when not given):
        faces tested from the same origin share the rays to their common corners and edge
        middles. Cast in blocks of at most :data:`FACES_PER_CAST` faces: the rays of millions
        of faces at once would hold gigabytes of temporaries, for no speed.
        """
        origins = np.asarray(origins, np.float32).reshape(-1, 3)
        if views is None:
            origins, views = np.unique(origins, axis=0, return_inverse=True)
            return self.faces_visible_from(origins, views, face_ids, abs_tol_m, rel_tol)
        # views numbered 0, 1, …, each with its origin (its first face's: they share it)
        _, first, number = np.unique(np.asarray(views).reshape(-1), return_index=True,
                                     return_inverse=True)
        return self.faces_visible_from(origins[first], number.reshape(-1), face_ids, abs_tol_m,
                                       rel_tol)

    def faces_visible_from(self, centres: NDArray[np.floating], views: NDArray[np.integer],
                           face_ids: NDArray[np.integer], abs_tol_m: float = 0.01,
                           rel_tol: float = 0.005) -> NDArray[np.bool_]:
        """:meth:`faces_visible` with the origin of face ``face_ids[i]`` given as
        ``centres[views[i]]`` (a frame's camera centre): no per-face copy of the origins."""
        ids: NDArray[np.int64] = np.asarray(face_ids, dtype=np.int64)
        origins = np.asarray(centres, np.float32).reshape(-1, 3)
        result = np.ones(len(ids), dtype=bool)
        if len(ids) == 0:
            return result
        views = np.asarray(views).reshape(-1)
        # the faces of a view in the mesh's locality order (neighbours in one block: they
        # share their corners' and edges' rays), then by view: frame numbers are small, a
        # stable sort of int16 is a radix sort
        local = self._locality_sorted(ids)
        small = views.max(initial=0) < 2 ** 15 and views.min(initial=0) >= 0
        key = views.astype(np.int16) if small else views  # int16: an eighth of the memory
        order = local[np.argsort(key[local], kind="stable")]
        del local
        ordered = key[order]
        starts = np.r_[0, np.flatnonzero(ordered[1:] != ordered[:-1]) + 1, len(order)]
        blocks = [order[start:min(b, start + FACES_PER_CAST)]
                  for a, b in zip(starts[:-1].tolist(), starts[1:].tolist(), strict=True)
                  for start in range(a, b, FACES_PER_CAST)]
        edge_ids = self.edges.ids
        self.dense_faces()  # found once, before the threads

        def test(rows: NDArray[np.signedinteger[Any]]) -> None:
            result[rows] = self._visible_from(origins[views[rows[0]]], ids[rows], edge_ids,
                                              abs_tol_m, rel_tol)

        # blocks on a thread per core: Open3D casts on all cores, the numpy around it on one
        with thread_pool(worker_count(len(blocks))) as pool:
            list(pool.map(test, blocks))
        return result

    def locality_rank(self) -> I32:
        """Per face its position in an order that keeps neighbours together: by its lowest
        vertex, in buckets of consecutive vertices few enough for a 16-bit key (a stable
        radix sort). A mesh's faces are often not in such an order — a scan grid's two
        triangles of a quad lie half the mesh apart — and a block of faces cast at once
        shares a corner's or an edge's ray only between the faces in it (at lab scale 4.9
        rays per face in face order, ~3 in this one). Found once."""
        with self._lock:
            if self._rank is None:
                faces = self.faces
                lowest = np.minimum(np.minimum(faces[:, 0], faces[:, 1]), faces[:, 2])
                shift = max(0, int(len(self.vertices) - 1).bit_length() - 16)
                lowest >>= shift
                order = np.argsort(lowest.astype(np.uint16), kind="stable")
                del lowest
                rank = np.empty(len(faces), dtype=np.int32)
                rank[order] = np.arange(len(faces), dtype=np.int32)
                self._rank = rank
            return self._rank

    def _locality_sorted(self, ids: I64) -> NDArray[np.signedinteger[Any]]:
        """The positions in ``ids`` (face numbers) ordered by :meth:`locality_rank`: for many
        distinct faces by a pass over the ranks (no sort), else a sort of theirs."""
        rank = self.locality_rank()[ids]
        n = len(self.faces)
        if 16 * len(ids) >= n:
            at: NDArray[np.signedinteger[Any]] = np.full(
                n, -1, dtype=np.int32 if len(ids) < 2 ** 31 else np.int64)
            at[rank] = np.arange(len(ids), dtype=at.dtype)
            ordered = at[at >= 0]
            if len(ordered) == len(ids):  # else a face twice: sorted below
                return ordered  # int32 where it fits: held through the rays
        return np.argsort(rank, kind="stable")

    def dense_faces(self) -> NDArray[np.bool_]:
        """Per face: an edge longer than :data:`DENSE_EDGE_M` (tested at 13 points, not 7);
        found once, in blocks of faces."""
        with self._lock:
            if self._dense is None:
                dense = np.empty(len(self.faces), dtype=bool)
                # one coordinate at a time (1-D gathers from contiguous columns): ~2.5× faster
                # than gathering rows of corners and an einsum over them (0.3 s at lab scale)
                columns = [np.ascontiguousarray(self.vertices[:, c]) for c in range(3)]
                for start in range(0, len(self.faces), FACES_PER_CAST):
                    tri = self.faces[start:start + FACES_PER_CAST]
                    corner = [[column[tri[:, k]] for column in columns] for k in range(3)]
                    longest = np.zeros(len(tri), dtype=np.float32)
                    for k in range(3):  # the squared edge from corner k to k + 1
                        a, b = corner[k], corner[(k + 1) % 3]
                        step = b[0] - a[0]
                        squared = step * step
                        for c in (1, 2):
                            step = b[c] - a[c]
                            squared += step * step
                        np.maximum(longest, squared, out=longest)
                    dense[start:start + FACES_PER_CAST] = np.sqrt(longest) > DENSE_EDGE_M
                del columns
                self._dense = dense
            return self._dense

    def _columns(self) -> list[NDArray[np.float32]]:
        """The vertices' x, y and z, each contiguous (found once)."""
        with self._lock:
            if self._vertex_columns is None:
                self._vertex_columns = [np.ascontiguousarray(self.vertices[:, c])
                                        for c in range(3)]
            return self._vertex_columns

    def _scratch_array(self, kind: str, size: int) -> I32:
        """This thread's scratch array ``kind`` of at least ``size`` int32 (kept, grown)."""
        held: I32 | None = getattr(self._scratch, kind, None)
        if held is None or len(held) < size:
            held = np.empty(size, dtype=np.int32)
            setattr(self._scratch, kind, held)
        return held

    def _visible_from(self, origin: NDArray[np.float32], face_ids: NDArray[np.int64],
                      edge_ids: I32, abs_tol_m: float, rel_tol: float) -> NDArray[np.bool_]:
        """:meth:`faces_visible` for faces seen from one origin: their centroids, corners and
        edge middles, each corner and edge once, and the inset points of long-edged faces."""
        n = len(face_ids)
        if n == 0:
            return np.ones(0, dtype=bool)
        tri = self.faces[face_ids]  # (n, 3)
        slots = np.arange(3 * n, dtype=np.int32)
        # a corner or an edge shared by faces of this block is one point: the last slot that
        # names it (a scatter into a per-vertex / per-edge scratch array, no sort); the
        # scratch spans only the block's numbers (a block of neighbours spans few: a small
        # array the scatter stays in the cache of, not 38 MB per thread at lab scale)
        shared: list[tuple[NDArray[np.signedinteger[Any]], NDArray[np.signedinteger[Any]]]] = []
        for kind, ids in (("vertex", tri.reshape(-1)), ("edge", edge_ids[face_ids].reshape(-1))):
            low, span = int(ids.min()), int(ids.max()) - int(ids.min()) + 1
            if span > 16 * len(ids) + 4096:
                # scattered faces (ICM's movers): a sort of a few numbers, not a mesh-sized
                # scratch array whose touched pages fault in at every call (~20 ms each)
                _, first, point = np.unique(ids, return_index=True, return_inverse=True)
                shared.append((first, point.reshape(-1)))
                continue
            scratch = self._scratch_array(kind, span)
            local = np.subtract(ids, low, dtype=np.int64 if low > 2 ** 31 else np.int32)
            scratch[local] = slots
            owner_slot = scratch[local]
            del local
            is_first = owner_slot == slots
            first = np.flatnonzero(is_first)
            compact = np.cumsum(is_first, dtype=np.int32)
            compact -= 1
            shared.append((first, compact[owner_slot]))
        (vertex_first, vertex_point), (edge_first, edge_point) = shared
        # the points from the block's corners, each gathered from the vertices once (no
        # (n, 3, 3) corner array): centroids (as a mean over the corners), the shared
        # corners, the shared edges' middles (slot k of a face runs from its corner k to
        # k + 1); a coordinate at a time from the vertices' columns (1-D gathers and passes
        # over contiguous numbers), less the origin: the same float32 numbers as from rows
        flat = tri.reshape(-1)
        dense = np.flatnonzero(self.dense_faces()[face_ids])
        n_vertex, n_edge = len(vertex_first), len(edge_first)
        vertex_base, edge_base = n, n + n_vertex
        dense_base = edge_base + n_edge
        at = vertex_point.reshape(n, 3)  # each face's corners, as rows of the corners
        corner_of = [np.ascontiguousarray(at[:, k]) for k in range(3)]
        following = np.roll(at, -1, axis=1).reshape(-1)  # the corner an edge slot runs to
        edge_from, edge_to = vertex_point[edge_first], following[edge_first]
        vertex_ids = flat[vertex_first]
        dense_points = (np.matmul(DENSE_WEIGHTS, self.vertices[tri[dense]]).reshape(-1, 3)
                 if len(dense) else None)
        # written in place into one array per coordinate (no pieces to concatenate)
        delta = np.empty((3, dense_base + len(dense) * len(DENSE_WEIGHTS)), dtype=np.float32)
        for c, column in enumerate(self._columns()):
            row = delta[c]
            corner = row[vertex_base:edge_base]
            np.take(column, vertex_ids, out=corner)
            centroid = row[:n]
            np.add(corner[corner_of[0]], corner[corner_of[1]], out=centroid)
            centroid += corner[corner_of[2]]
            centroid /= 3
            middle = row[edge_base:dense_base]
            np.add(corner[edge_from], corner[edge_to], out=middle)
            middle *= np.float32(0.5)
            if dense_points is not None:
                row[dense_base:] = dense_points[:, c]
            row -= origin[c]
        ok = self._cast(origin, delta, abs_tol_m, rel_tol)
        # all of a face's points seen: its columns and-ed (a reduction over rows of three is
        # several times slower)
        visible = ok[:n].copy()
        for base, point in ((vertex_base, vertex_point), (edge_base, edge_point)):
            seen = ok[base + point].reshape(n, 3)
            for k in range(3):
                visible &= seen[:, k]
        if len(dense):
            extra = ok[dense_base:].reshape(len(dense), -1).all(axis=1)
            visible[dense] &= extra
        return visible


def face_centroids(vertices: NDArray[np.floating], faces: NDArray[np.integer]) -> F64:
    """``(faces, 3)`` the mean of each face's corners (float64; as ``vertices[faces].mean(1)``
    without its ``(faces, 3, 3)`` temporary)."""
    points = np.asarray(vertices, np.float64)
    # a coordinate at a time (1-D gathers from contiguous columns: ~25 % less CPU than rows)
    corner = [np.ascontiguousarray(faces[:, k]) for k in range(3)]
    result = np.empty((len(faces), 3))
    for c in range(3):
        column = np.ascontiguousarray(points[:, c])
        total = column[corner[0]] + column[corner[1]]
        total += column[corner[2]]
        total /= 3.0
        result[:, c] = total
    return result


def face_normals(vertices: NDArray[np.floating], faces: NDArray[np.integer],
                 vertex_normals: NDArray[np.floating] | None = None) -> tuple[F64, F64]:
    """Unit face normals and face areas (m²).

    The winding decides a normal's sign unless ``vertex_normals`` are given: then each face
    normal is turned to agree with the mean of its vertices' normals (the mesh stage's normals
    point towards the scanner), and where the two differ by more than 60° the mean is taken: a
    sliver (a scan grid's faces where the profiles meet on the motor axis, straight above and
    below the rig) has a cross product that range noise turns any way.
    """
    # one coordinate at a time (1-D gathers and products): the (faces, 3, 3) corner and
    # vertex-normal temporaries and np.cross took ~2.4 s of CPU at lab scale (4.8 M faces)
    points = np.asarray(vertices, np.float64)
    corner = [faces[:, k] for k in range(3)]

    def edges(c: int) -> tuple[F64, F64]:
        column = np.ascontiguousarray(points[:, c])
        first = column[corner[0]]
        return column[corner[1]] - first, column[corner[2]] - first

    (ax, bx), (ay, by), (az, bz) = edges(0), edges(1), edges(2)
    normals = np.empty((len(faces), 3))
    normals[:, 0] = ay * bz - az * by  # as np.cross
    normals[:, 1] = az * bx - ax * bz
    normals[:, 2] = ax * by - ay * bx
    del ax, bx, ay, by, az, bz
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    normals /= np.maximum(length, 1e-20)[:, None]
    if vertex_normals is not None:
        given = np.asarray(vertex_normals, np.float64)
        mean = np.empty((len(faces), 3))
        for c in range(3):
            column = np.ascontiguousarray(given[:, c])
            mean[:, c] = column[corner[0]] + column[corner[1]] + column[corner[2]]
        mean_length = np.sqrt(np.einsum("ij,ij->i", mean, mean))
        agreement = np.einsum("ij,ij->i", normals, mean)
        normals[agreement < 0] *= -1
        unreliable = np.flatnonzero((np.abs(agreement) < 0.5 * mean_length)
                                    & (mean_length > 1e-12))
        normals[unreliable] = mean[unreliable] / mean_length[unreliable, None]
    return normals, 0.5 * length
