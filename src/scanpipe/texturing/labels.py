"""Frame choice that weighs quality against seams: a Potts MRF over the face adjacency,
minimised by iterated conditional modes (ICM).

Energy (Waechter et al. 2014, eq. 1, with our score as the data term)::

    E(l) = Σ_f D(f, l_f) + λ · Σ_(f,g adjacent) [l_f ≠ l_g]
    D(f, l) = 1 − score(l, f) / score(best visible frame of f)       (∞ where score is 0)

Scores are each face's best frames only (:class:`~scanpipe.texturing.projective.FaceScores`):
a frame not among them scores 0 for the face, so a face never moves to it.

Start: every face in its best visible frame
(:func:`scanpipe.texturing.projective.select_frames_per_face`).
Each round, every face on a seam may take the label of one of its neighbours when that lowers
the energy; a random half of the faces that would gain move (neighbours moving at once could
swap forever), after their new frame is tested against the mesh (the same ray test; a
hidden candidate is struck out). Faces without a label (untextured) do not count in the Potts
term. All arrays, no per-face Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanpipe.progress import ProgressFn, no_progress
from scanpipe.texturing.frames import FrameSet
from scanpipe.texturing.projective import FaceScores, Scores
from scanpipe.texturing.visibility import MeshEdges, MeshOcclusion, mesh_edges

F32 = NDArray[np.float32]
I32 = NDArray[np.int32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def face_neighbours(faces: NDArray[np.integer]) -> I64:
    """``(faces, 3)`` the faces sharing an edge with each face, −1 padded (manifold edges):
    :meth:`~scanpipe.texturing.visibility.MeshEdges.neighbours` (the stage takes them from its
    ray scene's edges, found once)."""
    return mesh_edges(faces).neighbours()


@dataclass
class Smoothing:
    """What ICM changed."""

    labels: I64
    rounds: int
    moved: int
    struck: int
    seam_edges_before: int
    seam_edges_after: int


#: Faces looked at at once by the passes over the whole mesh (bounded temporaries).
BLOCK_FACES = 1 << 20


def _seam_faces(labels: I64, neighbours: I64) -> tuple[I64, int]:
    """The textured faces with a textured neighbour of another frame (ascending) and the
    number of such edges, in blocks of faces (no ``(faces, 3)`` temporaries)."""
    padded = np.append(labels, -1)  # neighbour −1 reads −1
    faces: list[I64] = []
    ends = 0
    for start in range(0, len(labels), BLOCK_FACES):
        mine = labels[start:start + BLOCK_FACES, None]
        lab_n = padded[neighbours[start:start + BLOCK_FACES]]
        seam = (lab_n >= 0) & (mine >= 0) & (lab_n != mine)
        ends += int(seam.sum())
        faces.append(start + np.flatnonzero(seam.any(axis=1)))
    return (np.concatenate(faces) if faces else np.zeros(0, np.int64)), ends // 2


def seam_edge_count(labels: I64, neighbours: I64 | MeshEdges) -> int:
    """Edges between two textured faces with different frames."""
    if isinstance(neighbours, MeshEdges):
        return neighbours.seam_faces(labels)[1]
    return _seam_faces(labels, neighbours)[1]


def _reference_scores(scores: Scores, labels: I64) -> F64:
    """Each textured face's score in its frame (0 untextured), in blocks of faces; most faces
    are in their best frame (slot 0): only the others look through their kept frames."""
    reference = np.zeros(len(labels), dtype=np.float64)
    for start in range(0, len(labels), BLOCK_FACES):
        label = labels[start:start + BLOCK_FACES]
        first, first_score = scores.first(slice(start, start + len(label)))
        at_first = (first == label) & (label >= 0)
        reference[start:start + BLOCK_FACES][at_first] = first_score[at_first]
        other = np.flatnonzero(~at_first & (label >= 0))
        reference[start + other] = scores.lookup(label[other], start + other)
    return reference


def _cost(candidate: I64, rows_frame: I32, rows_score: F32, reference: F64, nb: I64,
          counted: NDArray[np.bool_], seam_weight: float) -> F64:
    """The energy terms of the faces of ``rows_frame``/``rows_score`` (their kept frames and
    scores) labelled ``candidate`` (∞ where not allowed); ``reference`` of those faces."""
    score = FaceScores.lookup_rows(candidate, rows_frame, rows_score).astype(np.float64)
    data = 1.0 - score / np.maximum(reference, 1e-12)
    data[(candidate < 0) | (score <= 0)] = np.inf
    potts = (counted & (nb != candidate[:, None])).sum(axis=1)
    return np.asarray(data + seam_weight * potts)


def smooth_labels(scores: Scores, labels: I64, neighbours: I64 | MeshEdges, frames: FrameSet,
                  occlusion: MeshOcclusion, seam_weight: float = 0.3, rounds: int = 10,
                  seed: int = 0, progress: ProgressFn = no_progress) -> Smoothing:
    """ICM on the Potts energy above, from ``labels``; ``scores`` is modified (hidden
    candidates set to 0). ``neighbours``: :func:`face_neighbours`, or the mesh's
    :class:`~scanpipe.texturing.visibility.MeshEdges` (then only the neighbours of the faces
    looked at are found)."""
    labels = labels.copy()
    if isinstance(neighbours, MeshEdges):
        edges = neighbours
        frontier, before = edges.seam_faces(labels)  # round 1 looks at these of all faces
        neighbours_of = edges.neighbours
    else:
        table = neighbours
        frontier, before = _seam_faces(labels, table)

        def neighbours_of(rows: NDArray[np.integer] | None = None) -> I64:
            return table if rows is None else table[rows]
    if seam_weight <= 0 or len(labels) == 0 or len(frames) == 0:
        return Smoothing(labels, 0, 0, 0, before, before)
    rng = np.random.default_rng(seed)
    reference = _reference_scores(scores, labels)
    centres = np.stack([frames.centre(i) for i in range(len(frames))])
    moved = struck = 0
    done = 0
    # only faces on a seam can move, and a face joins a seam only when it or a neighbour
    # changes frame: each round looks at the last round's seam faces and the neighbourhood of
    # the faces that moved (the same faces, in the same order, as a scan of the whole mesh)
    for done in range(1, rounds + 1):
        nbf = neighbours_of(frontier)
        lab_n = np.where(nbf >= 0, labels[np.maximum(nbf, 0)], -1)
        own_f = labels[frontier]
        lab_n[own_f < 0] = -1
        counted = lab_n >= 0
        on_seam = (own_f >= 0) & np.any(counted & (lab_n != own_f[:, None]), axis=1)
        active = frontier[on_seam]
        if len(active) == 0:
            break
        own = own_f[on_seam]
        nb = lab_n[on_seam]  # (A, 3) candidate labels
        cnt = counted[on_seam]

        (rows_frame, rows_score), ref = scores.rows(active), reference[active]
        current = _cost(own, rows_frame, rows_score, ref, nb, cnt, seam_weight)
        options = np.stack([_cost(nb[:, k], rows_frame, rows_score, ref, nb, cnt, seam_weight)
                            for k in range(nb.shape[1])], axis=1)
        options[nb == own[:, None]] = np.inf
        best = np.argmin(options, axis=1)
        gain = options[np.arange(len(active)), best] - current
        move = (gain < -1e-9) & (rng.random(len(active)) < 0.5)
        if not move.any():
            if not (gain < -1e-9).any():
                break
            frontier = active
            continue
        face, target = active[move], nb[move, best[move]]
        visible = occlusion.faces_visible_from(centres, target, face)
        labels[face[visible]] = target[visible]
        scores.strike(target[~visible], face[~visible])
        moved += int(visible.sum())
        struck += int((~visible).sum())
        changed = face[visible]
        around = neighbours_of(changed).ravel()
        frontier = np.unique(np.concatenate([active, changed, around[around >= 0]]))
        progress("seams", done, rounds)
    return Smoothing(labels, done, moved, struck, before, seam_edge_count(labels, neighbours))
