"""Foxglove MCAP export: read back with the mcap reader, decoded from the embedded schemas."""

from __future__ import annotations

import io
import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import trimesh
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from result_tables import points_table, textured_quad

from scanpipe.camera import project_points
from scanpipe.exporters.mcap_foxglove import EXPORT_PROFILE, quaternion_from_matrix
from scanpipe.exporting import write_files
from scanpipe.geometry import platform_rotation, rotation_matrix_deg
from scanpipe.motion import beta_deg_at
from scanpipe.protobuf import file_descriptor_set
from scanpipe.rig import default_rig, rig_table
from scanpipe.schema import FRAMES, MOTOR
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


def test_official_schemas_registered_once_and_profile_set(tmp_path: Path) -> None:
    tables = {"points": points_table(profiles=4, samples=5), **textured_quad()}
    write_files(export_files(tables, "mcap", "scan"), tmp_path)
    with (tmp_path / "scan.mcap").open("rb") as handle:
        reader = make_reader(handle)
        assert reader.get_header().profile == EXPORT_PROFILE
        summary = reader.get_summary()
    assert summary is not None
    names = [schema.name for schema in summary.schemas.values()]
    assert sorted(names) == sorted(set(names))  # each schema once, though two topics share one
    by_name = {schema.name: schema for schema in summary.schemas.values()}
    # The schema data is the official package's descriptor set, byte for byte.
    assert by_name["foxglove.PointCloud"].data == file_descriptor_set(PointCloud)
    assert by_name["foxglove.SceneUpdate"].data == file_descriptor_set(SceneUpdate)
    cloud_schemas = {c.schema_id for c in summary.channels.values()
                     if c.topic in ("/scan/profile", "/scan/cloud")}
    assert len(cloud_schemas) == 1


def _camera_tables(rig, frames_per_camera: int = 3):  # type: ignore[no-untyped-def]
    """frames (a JPEG per frame), motor (a turn over 1 s) and rig artifacts."""
    t0 = 1_700_000_000_000_000_000
    ok, jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))
    assert ok
    rows = [(cam.id, t0 + (i + 1) * 200_000_000, i) for cam in rig.cameras
            for i in range(frames_per_camera)]
    frames = pa.table({
        "camera_id": [r[0] for r in rows], "log_time_ns": [r[1] for r in rows],
        "sequence": [r[2] for r in rows], "format": ["jpeg"] * len(rows),
        "width": pa.array([64] * len(rows), pa.int32()),
        "height": pa.array([48] * len(rows), pa.int32()),
        "data": pa.array([jpeg.tobytes()] * len(rows), pa.binary())},
        schema=FRAMES.arrow_schema)
    steps = np.arange(0, 11) * 100
    motor = pa.table({"log_time_ns": t0 + np.arange(11) * 100_000_000, "step_count": steps,
                      "target_step_count": np.full(11, 1000), "moving": np.ones(11, bool),
                      "device_time_us": pa.nulls(11, pa.int64())}, schema=MOTOR.arrow_schema)
    return {"frames": frames, "motor": motor, "rig": rig_table(rig)}


def test_camera_images_calibration_and_transforms(tmp_path: Path) -> None:
    rig = default_rig()
    tables = {"points": points_table(profiles=4, samples=5), **_camera_tables(rig)}
    files = export_files(tables, "mcap", "scan")
    assert list(files) == ["scan.mcap", "scan.layout.json"]
    write_files(files, tmp_path)
    messages = _read(tmp_path / "scan.mcap")
    assert len(messages["/camera/cam360/image"]) == 3  # the 360° camera: images, no calibration
    assert "/camera/cam360/calibration" not in messages
    for cam in rig.cameras[:2]:
        images = messages[f"/camera/{cam.id}/image"]
        calibrations = messages[f"/camera/{cam.id}/calibration"]
        assert len(images) == len(calibrations) == 3
        assert {m[0] for m in images} == {"foxglove.CompressedImage"}
        assert {m[0] for m in calibrations} == {"foxglove.CameraCalibration"}
        _, log_time, image = images[1]
        assert image.format == "jpeg" and image.frame_id == f"camera_{cam.id}"
        assert cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR).shape == (
            48, 64, 3)
        calibration = calibrations[1][2]
        assert calibration.distortion_model == "plumb_bob"
        assert (calibration.width, calibration.height) == (cam.width, cam.height)
        camera_tf = next(m[2] for m in messages["/tf"]
                         if m[2].child_frame_id == f"camera_{cam.id}")
        assert camera_tf.parent_frame_id == "platform"
        platform_tf = next(m[2] for m in messages["/tf"]
                           if m[2].child_frame_id == "platform" and m[1] == log_time)
        # A rig point through the published transforms and calibration lands on the pixel
        # scanpipe's own camera model gives (the motor turns 100 steps per 100 ms).
        beta = float(beta_deg_at(np.array([log_time]), tables["motor"], rig.motor)[0])
        point = np.array([[0.3, 0.2, 2.5]])
        uv, depth = project_points(point, cam, beta)
        t = np.array([camera_tf.translation.x, camera_tf.translation.y, camera_tf.translation.z])
        in_platform = _rotate_inverse(platform_tf.rotation, point)
        in_camera = _rotate_inverse(camera_tf.rotation, in_platform - t)
        k = np.array(calibration.K).reshape(3, 3)
        pixel = (k @ (in_camera[0] / in_camera[0, 2]))[:2]
        if depth[0] > 0:
            np.testing.assert_allclose(pixel, uv[0], atol=1e-6)
        np.testing.assert_allclose(in_camera[0, 2], depth[0], atol=1e-9)
    layout = json.loads((tmp_path / "scan.layout.json").read_text())
    assert layout["configById"]["3D!scan"]["followTf"] == "world"
    assert "/scan/cloud" in layout["configById"]["3D!scan"]["topics"]
    image_panels = {k: v for k, v in layout["configById"].items() if k.startswith("Image!")}
    assert {v["imageMode"]["imageTopic"] for v in image_panels.values()} == {
        f"/camera/{c.id}/image" for c in rig.cameras}
    panel_ids = json.dumps(layout["layout"])
    assert all(k in panel_ids for k in layout["configById"])


def _rotate_inverse(q, v: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    return _rotate(type("Q", (), {"x": -q.x, "y": -q.y, "z": -q.z, "w": q.w})(), v)


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


def test_export_stage_mcap_carries_the_cloud_and_cameras() -> None:
    from scanpipe.progress import no_progress
    from scanpipe.stages.export import ExportStageParams, export_stage

    rig = default_rig()
    inputs = {"points": points_table(profiles=4, samples=5), **textured_quad(),
              **_camera_tables(rig)}
    result = export_stage(inputs, ExportStageParams(mesh_formats=("mcap",), cloud_formats=(),
                                                    cloud_colors=False), no_progress)
    assert set(result.files) == {"model.mcap", "model.layout.json"}
    reader = make_reader(io.BytesIO(result.files["model.mcap"]))
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {summary.channels[i].topic: n
              for i, n in summary.statistics.channel_message_counts.items()}
    assert counts["/scan/cloud"] == 1 and counts["/model"] == 1
    assert counts["/camera/cam0/image"] == 3
