"""Foxglove MCAP export: read back with the mcap reader, decoded from the embedded schemas."""

from __future__ import annotations

import io
from collections import defaultdict
from pathlib import Path

import numpy as np
import trimesh
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from result_tables import points_table, textured_quad

from scanpipe.exporters.foxglove_schemas import POOL
from scanpipe.exporters.mcap_foxglove import quaternion_from_matrix
from scanpipe.exporting import write_files
from scanpipe.geometry import platform_rotation, rotation_matrix_deg
from scanpipe.stages.export import export_files


def _read(path: Path) -> dict[str, list]:
    messages: dict[str, list] = defaultdict(list)
    with path.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            messages[channel.topic].append((schema.name, message.log_time, decoded))
    return messages


def _cloud_xyz(message) -> np.ndarray:  # type: ignore[no-untyped-def]
    offsets = {f.name: f.offset for f in message.fields}
    raw = np.frombuffer(message.data, np.uint8).reshape(-1, message.point_stride)
    return np.stack([raw[:, offsets[c]:offsets[c] + 4].copy().view(np.float32)[:, 0]
                     for c in "xyz"], 1)


def _rotate(q, v: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    x, y, z, w = q.x, q.y, q.z, q.w
    matrix = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                       [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                       [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return v @ matrix.T


def test_scan_profiles_transforms_cloud_and_model(tmp_path: Path) -> None:
    table = points_table(profiles=6, samples=10)
    tables = {"points": table, **textured_quad()}
    write_files(export_files(tables, "mcap", "scan"), tmp_path)
    messages = _read(tmp_path / "scan.mcap")
    assert set(messages) == {"/tf", "/scan/profile", "/scan/cloud", "/model"}
    assert {m[0] for m in messages["/tf"]} == {"foxglove.FrameTransform"}
    assert {m[0] for m in messages["/scan/profile"]} == {"foxglove.PointCloud"}
    assert {m[0] for m in messages["/model"]} == {"foxglove.SceneUpdate"}
    assert len(messages["/scan/profile"]) == 6
    assert len(messages["/tf"]) == 1 + 6

    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], 1)
    (_, _, cloud), = messages["/scan/cloud"]
    assert cloud.frame_id == "rig"
    np.testing.assert_allclose(_cloud_xyz(cloud), xyz, atol=1e-6)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity", "red", "green", "blue",
                                              "alpha"]

    # Each profile, taken through its rig → platform transform, lands on the rig-frame points.
    transforms = {m[1]: m[2] for m in messages["/tf"] if m[2].child_frame_id == "platform"}
    beta = table.column("beta_deg").to_numpy()
    for index, (_, log_time, profile) in enumerate(messages["/scan/profile"]):
        assert profile.frame_id == "platform"
        transform = transforms[log_time]
        assert transform.parent_frame_id == "rig"
        rows = slice(index * 10, (index + 1) * 10)
        np.testing.assert_allclose(_rotate(transform.rotation, _cloud_xyz(profile)), xyz[rows],
                                   atol=1e-5)
        np.testing.assert_allclose(
            quaternion_from_matrix(platform_rotation(beta[rows][0])),
            (transform.rotation.x, transform.rotation.y, transform.rotation.z,
             transform.rotation.w), atol=1e-12)

    world = next(m[2] for m in messages["/tf"] if m[2].child_frame_id == "rig")
    assert world.parent_frame_id == "world"
    np.testing.assert_allclose(_rotate(world.rotation, np.array([[0.0, 1.0, 0.0]])),
                               [[0, 0, 1]], atol=1e-12)  # rig up (y) is Foxglove's up (z)

    (_, _, update), = messages["/model"]
    (entity,) = update.entities
    (model,) = entity.models
    assert model.media_type == "model/gltf-binary" and model.data[:4] == b"glTF"
    scene = trimesh.load(io.BytesIO(model.data), file_type="glb")
    assert sum(len(g.faces) for g in scene.geometry.values()) == 2


def test_schemas_are_the_published_foxglove_names() -> None:
    names = {"foxglove.PointCloud", "foxglove.FrameTransform", "foxglove.SceneUpdate",
             "foxglove.PackedElementField", "foxglove.ModelPrimitive", "foxglove.SceneEntity"}
    for name in names:
        assert POOL.FindMessageTypeByName(name).full_name == name
    fields = {f.name: f.number for f in POOL.FindMessageTypeByName("foxglove.SceneEntity").fields}
    assert fields["models"] == 14 and fields["frame_locked"] == 5
    cloud = {f.name: f.number for f in POOL.FindMessageTypeByName("foxglove.PointCloud").fields}
    assert cloud == {"timestamp": 1, "frame_id": 2, "pose": 3, "point_stride": 4, "fields": 5,
                     "data": 6}


def test_quaternion_from_matrix_matches_rotations() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        matrix = rotation_matrix_deg(rng.uniform(-180, 180, 3))
        x, y, z, w = quaternion_from_matrix(matrix)

        class Q:  # a stand-in with the message's attribute names
            pass

        q = Q()
        q.x, q.y, q.z, q.w = x, y, z, w  # type: ignore[attr-defined]
        vectors = rng.normal(size=(4, 3))
        np.testing.assert_allclose(_rotate(q, vectors), vectors @ matrix.T, atol=1e-9)


def test_mcap_of_points_only_and_of_a_cloud_without_grid(tmp_path: Path) -> None:
    table = points_table()
    no_grid = table.set_column(table.schema.get_field_index("profile"), "profile",
                               [np.full(table.num_rows, -1, np.int32)])
    write_files(export_files({"points": no_grid}, "mcap", "flat"), tmp_path)
    messages = _read(tmp_path / "flat.mcap")
    assert set(messages) == {"/tf", "/scan/cloud"}
