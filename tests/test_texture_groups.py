"""Face groups (docs/texture.md, "Face groups"): the faces are scored, sampled and ranked in
small groups, and the per-face path stays as the fallback and the reference: groups of one face
texture exactly as the per-face code did, a group's frame holds each of its faces whole, and a
face of a half-hidden group takes a frame it is really seen in."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from texture_scene import Caster, Recording, mesh_tables, record, room_mesh, small_rig

from scanpipe.artifacts import write_artifact
from scanpipe.rig import rig_table
from scanpipe.stages.texture import STAGE
from scanpipe.texturing.frames import choose_frames
from scanpipe.texturing.groups import face_groups, single_faces, split_into_singles
from scanpipe.texturing.projective import (
    FaceScores,
    GroupedScores,
    face_scores,
    group_scores,
    project_valid,
)
from scanpipe.texturing.visibility import MeshOcclusion, face_centroids, face_normals

#: The digest (:func:`table_digest`) of the ``textured_faces`` the per-face code (before face
#: groups, commit ec230f6) made of this scene: groups of one face must reproduce it exactly.
PER_FACE_DIGEST = "4668b50fb27e9ded"


def table_digest(table: pa.Table) -> str:
    """Every column's values, in order (floats by their repr: exact)."""
    whole = hashlib.sha256()
    for name in table.column_names:
        whole.update(name.encode())
        whole.update(repr(table.column(name).combine_chunks().to_pylist()).encode())
    return whole.hexdigest()[:16]


@pytest.fixture(scope="module")
def recording() -> Recording:
    return record(small_rig(), beta_step_deg=6.0, caster=Caster())


@pytest.fixture(scope="module")
def mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return room_mesh(0.25)


def test_groups_of_one_face_texture_as_the_per_face_code(recording: Recording, mesh) -> None:
    """The slow reference: every face its own group is today's per-face path, bit for bit."""
    result = STAGE.run(recording.inputs(*mesh_tables(*mesh)), STAGE.params(face_group=1))
    assert table_digest(result.tables["textured_faces"]) == PER_FACE_DIGEST
    assert result.report["face_groups"] == len(mesh[1])
    assert result.report["faces_scored_alone"] == 0


def test_groups_partition_the_faces_by_place_and_orientation(mesh) -> None:
    vertices, faces, vertex_normals = mesh
    normals, areas = face_normals(vertices, faces, vertex_normals)
    centroids = face_centroids(vertices, faces)
    groups = face_groups(faces, normals, areas, centroids, 8)
    assert 1 < groups.count < len(faces) / 2  # groups of several faces
    assert groups.sizes.max() <= 8
    assert np.array_equal(np.sort(groups.members), np.arange(len(faces)))
    for g in range(groups.count):  # the slow, obvious reference
        members = groups.members[groups.member_start[g]:groups.member_start[g + 1]]
        assert (groups.of[members] == g).all()
        corners = groups.corners[groups.corner_start[g]:groups.corner_start[g + 1]]
        assert corners.tolist() == faces[members].ravel().tolist()  # each face's, in order
        # one orientation: a face turned ~60° from its voxel's mean goes alone
        if len(members) > 1:
            assert (normals[members] @ groups.normal[g] > 0).all()
        if len(members) == 1:  # a face alone: its own corners (in order), normal, centroid
            assert corners.tolist() == faces[members[0]].tolist()
            assert np.array_equal(groups.normal[g], normals[members[0]])
            assert np.array_equal(groups.centroid[g], centroids[members[0]])
    alone = groups.faces_of(np.array([0, 1]))
    split, new = split_into_singles(groups, faces, alone, normals[alone], centroids[alone])
    assert np.array_equal(split.of[alone], new)
    assert np.array_equal(np.sort(split.members), np.arange(len(faces)))
    assert np.array_equal(split.corners[split.corner_start[new[0]]:split.corner_start[new[0] + 1]],
                          faces[alone[0]])


def test_a_group_frame_holds_each_of_its_faces_whole(recording: Recording, mesh) -> None:
    """A frame kept for a group has every corner of every face of the group in the image
    (margin included): exact, not an estimate from the group's centre."""
    vertices, faces, vertex_normals = mesh
    normals, areas = face_normals(vertices, faces, vertex_normals)
    centroids = face_centroids(vertices, faces)
    groups = face_groups(faces, normals, areas, centroids, 16)
    frames = choose_frames(recording.frames, recording.motor, recording.rig, 4.0)
    kept = group_scores(vertices, groups, frames, keep=len(frames))
    checked = 0
    for g in np.flatnonzero(kept.frame[:, 0] >= 0)[::7]:
        members = groups.members[groups.member_start[g]:groups.member_start[g + 1]]
        for i in kept.frame[g][kept.frame[g] >= 0]:
            _, _, valid = project_valid(vertices[faces[members]].reshape(-1, 3),
                                        frames.cameras[i], float(frames.beta_deg[i]), 2.0)
            assert valid.all()
            checked += 1
    assert checked > 20
    # and the per-face path is the groups-of-one path
    alone = face_scores(vertices, faces, normals, frames, keep=5)
    ones = group_scores(vertices, single_faces(faces, normals, centroids), frames, keep=5)
    assert np.array_equal(alone.frame, ones.frame) and np.array_equal(alone.score, ones.score)


def test_a_face_struck_alone_leaves_its_group_mates_their_frames() -> None:
    groups = FaceScores(np.array([[3, 1, -1], [2, -1, -1]], np.int32),
                        np.array([[0.9, 0.5, 0.0], [0.7, 0.0, 0.0]], np.float32))
    scores = GroupedScores(groups, np.array([0, 0, 1, 0], np.int32))
    scores.strike_slot(np.array([1]), 0)
    scores.strike(np.array([1]), np.array([3]))
    frame, score = scores.rows(np.arange(4))
    assert frame.tolist() == [[3, 1, -1], [3, 1, -1], [2, -1, -1], [3, 1, -1]]
    assert np.allclose(score, [[0.9, 0.5, 0], [0, 0.5, 0], [0.7, 0, 0], [0.9, 0, 0]])
    assert scores.lookup(np.array([3, 3, 1]), np.array([0, 1, 3])).tolist() == pytest.approx(
        [0.9, 0.0, 0.0])
    first, first_score = scores.first(slice(0, 4))
    assert first.tolist() == [3, 3, 2, 3]
    assert first_score.tolist() == pytest.approx([0.9, 0.0, 0.7, 0.9])
    assert groups.score[0].tolist() == pytest.approx([0.9, 0.5, 0.0])  # the group's own: kept


def test_half_hidden_groups_take_frames_their_faces_are_seen_in(recording: Recording,
                                                                 mesh) -> None:
    """Large groups behind the pillar's edge are hidden in part: every textured face is
    visible from its frame (the hidden part of a group from another frame, or alone), and no
    less surface is textured than face by face."""
    vertices, faces, _ = mesh
    inputs = recording.inputs(*mesh_tables(*mesh))
    grouped = STAGE.run(inputs, STAGE.params(face_group=64, group_px=0, seam_weight=0.0))
    alone = STAGE.run(inputs, STAGE.params(face_group=1, seam_weight=0.0))
    table = grouped.tables["textured_faces"]
    frame_of = np.asarray(table.column("frame").to_numpy(zero_copy_only=False))
    textured = np.flatnonzero(frame_of >= 0)
    assert grouped.report["faces_scored_alone"] > 0  # some group was split
    assert grouped.report["occluded_candidates"] > 0
    frames = choose_frames(recording.frames, recording.motor, recording.rig, 4.0)
    sequence = {(c, int(s)): i for i, (c, s) in enumerate(zip(
        frames.camera_ids, frames.sequences.tolist(), strict=True))}
    cams = table.column("camera_id").to_pylist()
    index = np.array([sequence[(cams[f], int(frame_of[f]))] for f in textured])
    centres = np.stack([frames.centre(i) for i in range(len(frames))])
    occlusion = MeshOcclusion(vertices, faces)
    assert occlusion.faces_visible(centres[index], textured).all()
    assert grouped.report["coverage"] >= alone.report["coverage"]


def test_cli_refuses_a_bad_group_size(cli, recording: Recording, tmp_path: Path) -> None:
    work = tmp_path / "w"
    vt, ft = mesh_tables(*room_mesh(0.5))
    for folder, name, table in (("mesh", "mesh_vertices", vt), ("mesh", "mesh_faces", ft),
                                ("decode", "frames", recording.frames),
                                ("decode", "motor", recording.motor),
                                ("decode", "rig", rig_table(recording.rig))):
        write_artifact(work / folder / f"{name}.parquet", table, {"key": name, "stage": folder})
    out = tmp_path / "o"
    good = cli("texture", work, "--out", out, "--set", "face_group=4", "--set", "group_px=0",
               "--json", "-q")
    assert good.code == 0, good.err
    assert 0 < json.loads(good.out)["face_groups"] < 0.5 * ft.num_rows
    before = (out / "textured_faces.parquet").read_bytes()
    for key, value in (("face_group", "0"), ("face_group", "65"), ("face_group", "many"),
                       ("group_px", "-1")):
        bad = cli("texture", work, "--out", out, "--set", f"{key}={value}", "-q")
        assert bad.code == 2 and key in bad.err, bad.err
        assert "Traceback" not in bad.err and len(bad.err.strip().splitlines()) == 1
    assert (out / "textured_faces.parquet").read_bytes() == before


def test_coarse_faces_stay_alone_at_the_defaults(recording: Recording, mesh) -> None:
    """Faces already many frame pixels wide (this scene's, ~45 px) are not grouped at the
    defaults (``group_px``): the per-face result, bit for bit."""
    result = STAGE.run(recording.inputs(*mesh_tables(*mesh)))
    assert result.report["face_groups"] == len(mesh[1])
    assert table_digest(result.tables["textured_faces"]) == PER_FACE_DIGEST


def test_groups_of_odd_meshes() -> None:
    """No faces, one face, faces of no area, a vertex not finite: groups (or every face
    alone) without an error."""
    for faces, vertices in ((np.zeros((0, 3), np.int64), np.zeros((0, 3))),
                            (np.array([[0, 1, 2]]), np.eye(3)),
                            (np.array([[0, 1, 2], [0, 1, 3]]), np.zeros((4, 3))),
                            (np.array([[0, 1, 2], [1, 2, 3]]),
                             np.r_[np.eye(3), [[np.nan, 0.0, 0.0]]])):
        normals, areas = face_normals(vertices, faces)
        centroids = face_centroids(vertices, faces)
        groups = face_groups(faces, normals, areas, centroids, 16)
        assert np.array_equal(np.sort(groups.members), np.arange(len(faces)))
        assert len(groups.corners) == 3 * len(faces)


def test_a_frame_behind_a_face_is_struck_before_any_ray(recording: Recording, mesh) -> None:
    """A group's frames are scored by its mean normal: a member at a crease may turn its back
    on one of them, which the ray test does not see on an open surface. The facing test
    (its corners' mean normal towards the frame's centre) strikes it first."""
    from scanpipe.stages.texture import _facing
    from scanpipe.texturing.projective import FaceScores, select_frames_per_face

    vertices, faces, normals_in = mesh
    frames = choose_frames(recording.frames, recording.motor, recording.rig, 4.0)
    facing = _facing(vertices, faces.astype(np.int32), normals_in, False, frames)
    rng = np.random.default_rng(5)
    face_ids = rng.integers(0, len(faces), 400)
    frame_ids = rng.integers(0, len(frames), 400)
    centroids = face_centroids(vertices, faces)
    slow = np.array([float(np.dot(normals_in[faces[f]].sum(0),
                                  frames.centre(int(i)) - centroids[f])) > 0
                     for f, i in zip(face_ids, frame_ids, strict=True)])
    assert np.array_equal(facing(face_ids, frame_ids), slow)
    assert 0 < slow.sum() < len(slow)  # both kinds drawn
    # an open sheet 1 m out that turns its back on the rig (its normal +x, away from the
    # cameras near the axis): nothing occludes it, only the facing test strikes its frames
    sheet = np.array([[1.0, 0.5, -0.5], [1.0, 0.5, 0.5], [1.0, 1.5, -0.5], [1.0, 1.5, 0.5]])
    corners = np.array([[0, 2, 1], [1, 2, 3]])
    assert (face_normals(sheet, corners)[0][:, 0] > 0).all()
    frame = np.zeros((2, 1), np.int32)
    back = _facing(sheet, corners.astype(np.int32), np.tile([1.0, 0.0, 0.0], (4, 1)), False,
                   frames)
    checked = select_frames_per_face(FaceScores(frame.copy(), np.ones((2, 1), np.float32)),
                                     frames, MeshOcclusion(sheet, corners), facing=back)
    assert checked.frame.tolist() == [-1, -1] and checked.backfacing_candidates == 2
    unchecked = select_frames_per_face(FaceScores(frame.copy(), np.ones((2, 1), np.float32)),
                                       frames, MeshOcclusion(sheet, corners))
    assert unchecked.frame.tolist() == [0, 0]  # the ray test alone keeps the back
