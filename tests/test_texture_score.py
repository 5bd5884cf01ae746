"""The texture stage's score and photometric phases against plain references: each face's kept
frames are those of a dense score matrix built straight from the formula (every vertex
projected into every frame), the colour samples those of a per-sample look-up, and one
reading of OMP_NUM_THREADS sizes both the batch workers and the texture threads."""

from __future__ import annotations

import math

import numpy as np
import pytest
from texture_scene import Caster, record, room_mesh, small_rig

from scanpipe.batch import worker_threads
from scanpipe.rig import Pose, Rig, default_rig
from scanpipe.sim.camera import scaled_camera
from scanpipe.texturing.frames import REDUCED_FACTOR, FrameSet, choose_frames, worker_count
from scanpipe.texturing.photometric import sample_views, unpack_levels
from scanpipe.texturing.projective import (
    face_scores,
    project_valid,
    project_valid_columns,
    resolution_weights,
)
from scanpipe.texturing.visibility import face_centroids, face_normals
from scanpipe.threads import omp_threads


def mixed_rig() -> Rig:
    """A distorted phone on the axis, a tilted phone off the axis (its window needs the
    parallax margin) and a small 360° camera (every frame sees every direction)."""
    base = small_rig(distortion=(-0.12, 0.03, 0.001, -0.001, 0.0))
    phone, other = base.cameras
    tilted = other.model_copy(update={"id": "tilted", "pose": Pose(
        translation_m=(0.12, 0.3, -0.08), rotation_deg=(25.0, 150.0, 0.0))})
    pano = scaled_camera(default_rig().cameras[2], 0.1)
    return base.model_copy(update={"cameras": (phone, tilted, pano)})


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, FrameSet]:
    rec = record(mixed_rig(), beta_step_deg=15.0, caster=Caster())
    vertices, faces, vertex_normals = room_mesh(0.2)
    normals, _ = face_normals(vertices, faces, vertex_normals)
    return vertices, faces, normals, choose_frames(rec.frames, rec.motor, rec.rig, 15.0)


def plain_scores(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray,
                 frames: FrameSet, min_cos: float = 0.2, margin_px: float = 2.0) -> np.ndarray:
    """``(frames, faces)`` scores from the module docstring's formula, in float64, every
    vertex projected into every frame (no windows, no threads)."""
    centroids = face_centroids(vertices, faces)
    sharp = frames.relative_sharpness() * resolution_weights(frames.cameras)
    dense = np.zeros((len(frames), len(faces)))
    for i, cam in enumerate(frames.cameras):
        uv, _, valid = project_valid(vertices, cam, float(frames.beta_deg[i]), margin_px)
        to_camera = frames.centre(i) - centroids
        cos = np.einsum("ij,ij->i", normals, to_camera) / np.linalg.norm(to_camera, axis=1)
        ok = (cos >= min_cos) & valid[faces].all(axis=1)
        corner_u = uv[faces, 0]
        if cam.model == "equirect":
            ok &= np.ptp(corner_u, axis=1) <= cam.width / 4
            centrality = np.ones(len(faces))
        else:
            mean = uv[faces].mean(axis=1)
            r2 = (((mean[:, 0] - cam.cx) / (cam.width / 2)) ** 2
                  + ((mean[:, 1] - cam.cy) / (cam.height / 2)) ** 2)
            centrality = np.clip(1 - 0.5 * r2, 0.05, 1.0)
        dense[i] = np.where(ok, cos * sharp[i] * centrality, 0.0)
    return dense


def test_kept_frames_are_the_plain_dense_best(scene) -> None:
    vertices, faces, normals, frames = scene
    assert {c.model for c in frames.cameras} == {"pinhole", "equirect"}
    keep = 5
    kept = face_scores(vertices, faces, normals, frames, keep=keep)
    dense = plain_scores(vertices, faces, normals, frames)
    ranked = np.argsort(-dense, axis=0, kind="stable")[:keep].T  # ties: the lower frame
    best = np.take_along_axis(dense.T, ranked, axis=1)
    expected = np.where(best > 0, ranked, -1)
    assert (expected[:, 0] >= 0).sum() > 0.8 * len(faces)
    assert (expected[:, keep - 1] >= 0).sum() > 100  # faces seen by more frames than kept
    np.testing.assert_allclose(kept.score, np.where(best > 0, best, 0.0), rtol=2e-5, atol=1e-7)
    # the same frames in the same order, but where two scores agree to float32 noise
    near_tie = np.zeros_like(best, dtype=bool)
    close = np.isclose(best[:, 1:], best[:, :-1], rtol=1e-5) & (best[:, 1:] > 0)
    near_tie[:, 1:] |= close
    near_tie[:, :-1] |= close
    assert near_tie.mean() < 0.01
    np.testing.assert_array_equal(kept.frame[~near_tie], expected[~near_tie])


def test_faces_in_view_gathered_or_sliced_score_the_same(scene, monkeypatch) -> None:
    """A pinhole frame's faces gathered from its vertices in view, or its whole azimuth
    window in slices: the same kept frames and scores, bit for bit."""
    from scanpipe.texturing import projective

    vertices, faces, normals, frames = scene
    results = []
    for share in (0.0, 1e9):  # never gathered, always gathered
        monkeypatch.setattr(projective, "IN_VIEW_SHARE", share)
        results.append(face_scores(vertices, faces, normals, frames, keep=5))
    sliced, gathered = results
    assert (sliced.frame >= 0).sum() > 1000
    np.testing.assert_array_equal(gathered.frame, sliced.frame)
    np.testing.assert_array_equal(gathered.score, sliced.score)


def test_views_are_the_plain_per_sample_pixels(scene) -> None:
    vertices, faces, normals, frames = scene
    centroids = face_centroids(vertices, faces)
    candidates = face_scores(vertices, faces, normals, frames, keep=4).frame
    packed = sample_views(centroids, candidates, frames)
    assert packed.shape == (len(faces), 4) and packed.dtype == np.uint32
    colour = unpack_levels(packed)
    # a plain look-up for every candidate of every 5th face (and no colour without one)
    faces_checked = np.arange(0, len(faces), 5)
    expected = np.full((len(faces_checked), 4, 3), np.nan, np.float32)
    for row, face in enumerate(faces_checked):
        for slot in np.flatnonzero(candidates[face] >= 0):
            i = int(candidates[face, slot])
            # float32 as sample_views projects (its precision: test_camera_float32)
            u, v, _, valid = project_valid_columns(
                *(centroids[face:face + 1, k].astype(np.float32) for k in range(3)),
                frames.cameras[i], float(frames.beta_deg[i]), 0.0)
            if valid[0]:
                small = frames.reduced(i)
                col = min(max(math.floor((float(u[0]) + 0.5) / REDUCED_FACTOR), 0),
                          small.shape[1] - 1)
                row_px = min(max(math.floor((float(v[0]) + 0.5) / REDUCED_FACTOR), 0),
                             small.shape[0] - 1)
                expected[row, slot] = small[row_px, col]
    assert np.isfinite(expected[:, :, 0]).sum() > 500
    np.testing.assert_array_equal(colour[faces_checked], expected)
    assert np.isnan(colour[candidates < 0]).all()


@pytest.mark.parametrize(("given", "threads"), [
    ("3", 3), (" 2 ", 2), ("1", 1), ("0", None), ("-2", None), ("two", None), ("", None),
    (None, None)])
def test_one_reading_of_omp_num_threads(monkeypatch: pytest.MonkeyPatch, given: str | None,
                                        threads: int | None) -> None:
    if given is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", given)
    assert omp_threads() == threads
    if threads is not None:  # a batch worker's share and the texture stage's threads agree
        assert worker_threads(4, None) == threads
        assert worker_count(100, limit=64) == threads
    else:
        assert worker_threads(1, None) >= 1
        assert 1 <= worker_count(100) <= 4
