"""The texture stage keeps each face's best frames (FaceScores), not a frames × faces matrix:
the kept frames are the dense matrix's best, in its order, and lookups and strikes see them.
Frames are rated once per content in a process."""

from __future__ import annotations

import cv2
import numpy as np
import pyarrow as pa
import pytest
from texture_scene import Caster, record, room_mesh, small_rig

import scanpipe.texturing.frames as frames_module
from scanpipe.texturing.frames import choose_frames
from scanpipe.texturing.projective import BestFrames, FaceScores, face_scores
from scanpipe.texturing.visibility import face_normals


def dense_best(scores: np.ndarray, keep: int) -> np.ndarray:
    """``(faces, keep)`` frames best first by a full sort of each face's column (ties: the
    lower frame), −1 past the positive ones."""
    order = np.lexsort((np.broadcast_to(np.arange(scores.shape[0])[:, None], scores.shape),
                        -scores), axis=0)[:keep].T
    best = np.take_along_axis(scores.T, order, axis=1)
    return np.where(best > 0, order, -1)


def test_kept_frames_are_the_dense_best_in_order() -> None:
    rng = np.random.default_rng(3)
    scores = rng.uniform(0.05, 1.0, (40, 500)).astype(np.float32)
    scores[rng.random(scores.shape) < 0.6] = 0.0  # most frames do not see a face
    scores[:, :20] = 0.0  # faces no frame sees
    scores[:, 20:40] = 0.0
    scores[[3, 7, 11], 20:40] = 0.5  # ties: the lower frame first, as an argmax would take
    kept = FaceScores.from_dense(scores, 6)
    expected = dense_best(scores, 6)
    np.testing.assert_array_equal(kept.frame, expected)
    np.testing.assert_array_equal(kept.frame[20:40, :4], np.tile([3, 7, 11, -1], (20, 1)))
    np.testing.assert_array_equal(
        kept.score, np.where(expected >= 0, np.take_along_axis(
            scores.T, np.maximum(expected, 0), axis=1), 0.0))
    assert kept.frame.dtype == np.int32 and kept.score.dtype == np.float32


def test_lookup_and_strike() -> None:
    scores = np.array([[0.9, 0.0, 0.2], [0.5, 0.4, 0.0], [0.1, 0.8, 0.3]], np.float32)
    kept = FaceScores.from_dense(scores, 2)  # face 0 keeps frames 0, 1; face 1: 2, 1
    frame = np.array([0, 2, 1, 2, -1, 0])
    face = np.array([0, 0, 1, 2, 0, 2])
    # frame 2 of face 0 (0.1) is not kept: 0, as a frame that does not see the face
    np.testing.assert_allclose(kept.lookup(frame, face), [0.9, 0.0, 0.4, 0.3, 0.0, 0.2])
    kept.strike(np.array([0, 1]), np.array([0, 0]))
    kept.strike(np.array([0]), np.array([1]))  # not kept: nothing to strike
    np.testing.assert_allclose(kept.lookup(np.array([0, 1, 1]), np.array([0, 0, 1])),
                               [0.0, 0.0, 0.4])
    np.testing.assert_array_equal(kept.frame[0], [0, 1])  # struck frames keep their slot


def test_face_scores_keeps_the_best_of_every_frame_scored() -> None:
    """The scores of the real loop (frames scored on threads, offered in frame order): a
    shorter list is the longer one's head, and keeping every frame matches scoring each
    frame alone."""
    rec = record(small_rig(), beta_step_deg=10.0, caster=Caster())
    vertices, faces, normals = room_mesh(0.25)
    frames = choose_frames(rec.frames, rec.motor, rec.rig, 10.0)
    n, _ = face_normals(vertices, faces, normals)
    every = face_scores(vertices, faces, n, frames, keep=len(frames))
    few = face_scores(vertices, faces, n, frames, keep=3)
    assert (every.frame[:, 3] >= 0).sum() > 100  # faces seen by more frames than kept
    np.testing.assert_array_equal(few.frame, every.frame[:, :3])
    np.testing.assert_array_equal(few.score, every.score[:, :3])
    dense = np.zeros((len(frames), len(faces)), np.float32)
    rows = np.repeat(np.arange(len(faces))[:, None], len(frames), axis=1)
    seen = every.frame >= 0
    dense[every.frame[seen], rows[seen]] = every.score[seen]
    np.testing.assert_array_equal(dense_best(dense, len(frames)), every.frame)
    assert (np.diff(every.score, axis=1) <= 0).all()  # best first
    # held as int16 while built (few frames), handed on as int32 as FaceScores says
    assert every.frame.dtype == few.frame.dtype == np.int32


@pytest.mark.parametrize("small", [False, True])
@pytest.mark.parametrize("keep", [3, 130])
def test_the_keeper_in_any_offer_pieces_is_the_dense_best(small: bool, keep: int) -> None:
    """Offers in pieces of any size and order of faces (as the frames' threads hand them
    on), frames held as int16 or int32, more than 127 kept (wider slot counters): the
    dense best, in int32."""
    rng = np.random.default_rng(keep)
    n_frames, n_faces = 140, 300
    scores = rng.uniform(0.05, 1.0, (n_frames, n_faces)).astype(np.float32)
    scores[rng.random(scores.shape) < 0.3] = 0.0
    scores[5:9, :50] = 0.25  # ties: the lower frame first
    best = BestFrames(n_faces, keep, small=small)
    for i, row in enumerate(scores):
        face = rng.permutation(np.flatnonzero(row > 0)).astype(np.int32)
        for piece in np.array_split(face, 3):
            best.add(i, piece, row[piece])
    kept = best.result()
    assert kept.frame.dtype == np.int32
    np.testing.assert_array_equal(kept.frame, dense_best(scores, keep))


def test_frames_are_rated_once_per_content(monkeypatch: pytest.MonkeyPatch) -> None:
    """The texture and export stages of one run both choose frames: the second choice takes
    the ratings of the same bytes, a changed frame is rated anew."""
    monkeypatch.setattr(frames_module, "_RATED", {})
    decoded: list[int] = []
    plain = frames_module.sharpness_of

    def counting(data: bytes, what: str) -> float:
        decoded.append(len(data))
        return plain(data, what)

    monkeypatch.setattr(frames_module, "sharpness_of", counting)
    rec = record(small_rig(), beta_step_deg=10.0, caster=Caster())
    first = choose_frames(rec.frames, rec.motor, rec.rig, 10.0)
    rated = len(decoded)
    # identical frames (the simulator renders a still platform alike) are rated once
    assert rated == len(set(rec.frames.column("data").to_pylist())) > 20
    again = choose_frames(rec.frames, rec.motor, rec.rig, 10.0)
    assert len(decoded) == rated  # nothing decoded twice
    np.testing.assert_array_equal(again.sharpness, first.sharpness)
    data = rec.frames.column("data").to_pylist()
    blurred = cv2.imencode(".jpg", cv2.GaussianBlur(
        cv2.imdecode(np.frombuffer(data[0], np.uint8), cv2.IMREAD_COLOR), (9, 9), 3))[1]
    changed = rec.frames.set_column(
        rec.frames.schema.get_field_index("data"), "data",
        pa.array([blurred.tobytes(), *data[1:]], pa.binary()))
    third = frames_module.rate_frames(changed.column("data"), np.arange(2),
                                      np.arange(2), np.array(["a", "a"], dtype=object))
    assert len(decoded) == rated + 1  # only the changed frame
    assert third[0] < frames_module.rate_frames(
        rec.frames.column("data"), np.arange(1), np.arange(1), np.array(["a"], dtype=object))[0]
