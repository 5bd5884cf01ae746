"""The result for Foxglove: the scan as it was built up, the camera images, and the model, in
one MCAP file, with a Foxglove layout beside it.

Messages are protobuf, of the official Foxglove schemas (the ``foxglove-schemas-protobuf``
package); each schema is registered once. The MCAP profile is :data:`EXPORT_PROFILE`. Topics:

- ``/tf`` (``foxglove.FrameTransform``): ``world`` → ``rig`` once (world is Foxglove's z-up
  frame, rig is scanpipe's y-up frame: a +90° turn about x), ``rig`` → ``platform`` at every
  profile's and every camera frame's time (the platform angle β about y), so scrubbing the
  timeline turns the platform, and ``platform`` → ``camera_<id>`` once per camera (its pose on
  the platform; the camera frame is OpenCV's optical frame: x right, y down, z forward).
- ``/scan/profile`` (``foxglove.PointCloud``): one message per profile in the ``platform``
  frame, at the profile's time (needs the grid indices; with a decay time the scan builds up).
- ``/scan/cloud`` (``foxglove.PointCloud``): the whole cloud in the ``rig`` frame, once, at the
  end of the scan. Clouds carry x, y, z and, where the points have them, intensity and
  red/green/blue/alpha.
- ``/camera/<id>/image`` (``foxglove.CompressedImage``) and ``/camera/<id>/calibration``
  (``foxglove.CameraCalibration``, plumb-bob model): every camera frame with its calibration
  (none for a 360° equirect camera, which Foxglove has no model for).
- ``/model`` (``foxglove.SceneUpdate``): the mesh as an entity with one embedded GLB model. glTF
  is y-up and Foxglove turns glTF models y-up → z-up itself, so the entity is placed in
  ``world`` with an identity pose and lands exactly on the rig-frame cloud.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.errors import ExportError, RigError
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.model import CloudModel, MeshModel, provenance_bytes
from scanpipe.geometry import camera_to_platform, platform_rotation
from scanpipe.protobuf import file_descriptor_set
from scanpipe.rig import CameraConfig, Rig

#: The MCAP profile of a Foxglove export: a custom profile (the MCAP specification allows them)
#: saying "protobuf messages of the official Foxglove schemas, frames world/rig/platform/camera_*".
#: It tells an export apart from a recording (profile ``scanpipe``) for ``scanpipe info``.
EXPORT_PROFILE = "scanpipe.foxglove"
#: The MCAP metadata record holding the export's provenance (one key, ``json``).
PROVENANCE_METADATA = "scanpipe.provenance"
WORLD_FRAME, RIG_FRAME, PLATFORM_FRAME = "world", "rig", "platform"
#: world (z up) ← rig (y up): (x, y, z) ↦ (x, −z, y), a +90° rotation about x.
WORLD_FROM_RIG = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_FLOAT32 = PackedElementField.NumericType.FLOAT32
_UINT16 = PackedElementField.NumericType.UINT16
_UINT8 = PackedElementField.NumericType.UINT8


def quaternion_from_matrix(rotation: NDArray[np.floating]) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a proper rotation matrix (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = s / 4
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = (v[0], v[1], v[2], (m[k, j] - m[j, k]) / s)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _stamp(message: Any, time_ns: int) -> None:
    message.timestamp.seconds = time_ns // 1_000_000_000
    message.timestamp.nanos = time_ns % 1_000_000_000


def _transform(time_ns: int, parent: str, child: str, rotation: NDArray[np.floating],
               translation: NDArray[np.floating] | None = None) -> Any:
    message = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    _stamp(message, time_ns)
    x, y, z, w = quaternion_from_matrix(rotation)
    message.rotation.x, message.rotation.y, message.rotation.z, message.rotation.w = x, y, z, w
    if translation is not None:
        t = np.asarray(translation, np.float64)
        message.translation.x, message.translation.y, message.translation.z = map(float, t)
    return message


def camera_frame(camera_id: str) -> str:
    """The Foxglove frame id of a camera's optical frame."""
    return f"camera_{camera_id}"


def camera_transform(time_ns: int, cam: CameraConfig) -> Any:
    """``platform`` → ``camera_<id>``: the camera's pose on the platform."""
    return _transform(time_ns, PLATFORM_FRAME, camera_frame(cam.id),
                      camera_to_platform(cam.pose.rotation_deg),
                      np.asarray(cam.pose.translation_m, np.float64))


def camera_calibration(time_ns: int, cam: CameraConfig) -> Any:
    """The ``foxglove.CameraCalibration`` of a camera: OpenCV pinhole + plumb-bob distortion."""
    message = CameraCalibration(
        frame_id=camera_frame(cam.id), width=cam.width, height=cam.height,
        distortion_model="plumb_bob", D=list(cam.distortion),
        K=[cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    _stamp(message, time_ns)
    return message


def compressed_image(time_ns: int, camera_id: str, data: bytes, image_format: str) -> Any:
    """A ``foxglove.CompressedImage`` of one encoded frame (``jpeg`` or ``png``)."""
    message = CompressedImage(frame_id=camera_frame(camera_id), data=data,
                              format=image_format or "jpeg")
    _stamp(message, time_ns)
    return message


def platform_transform(time_ns: int, beta_deg: float) -> Any:
    """``rig`` → ``platform`` at platform angle β."""
    return _transform(time_ns, RIG_FRAME, PLATFORM_FRAME, platform_rotation(beta_deg))


def world_transform(time_ns: int) -> Any:
    """``world`` (z up) → ``rig`` (y up)."""
    return _transform(time_ns, WORLD_FRAME, RIG_FRAME, WORLD_FROM_RIG)


def cloud_message(time_ns: int, frame: str, xyz: NDArray[np.floating],
                   intensity: NDArray[np.uint16] | None,
                   colors: NDArray[np.uint8] | None) -> Any:
    fields: list[tuple[str, str, int]] = [("x", "<f4", _FLOAT32), ("y", "<f4", _FLOAT32),
                                          ("z", "<f4", _FLOAT32)]
    if intensity is not None:
        fields.append(("intensity", "<u2", _UINT16))
    if colors is not None:
        fields += [("red", "u1", _UINT8), ("green", "u1", _UINT8), ("blue", "u1", _UINT8),
                   ("alpha", "u1", _UINT8)]
    packed = np.zeros(len(xyz), dtype=[(n, t) for n, t, _ in fields])
    for j, name in enumerate(("x", "y", "z")):
        packed[name] = xyz[:, j]
    if intensity is not None:
        packed["intensity"] = intensity
    if colors is not None:
        for j, name in enumerate(("red", "green", "blue")):
            packed[name] = colors[:, j]
        packed["alpha"] = 255
    message = PointCloud(frame_id=frame, point_stride=packed.dtype.itemsize,
                             data=packed.tobytes())
    _stamp(message, time_ns)
    message.pose.orientation.w = 1.0
    layout = packed.dtype.fields
    assert layout is not None
    for name, _, numeric in fields:
        message.fields.add(name=name, offset=layout[name][1], type=numeric)
    return message


class _Topics:
    """Registers each schema and each topic's channel once."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.sequence = 0

    def write(self, topic: str, message: Any, time_ns: int) -> None:
        if topic not in self.channels:
            name = message.DESCRIPTOR.full_name
            if name not in self.schemas:
                self.schemas[name] = self.writer.register_schema(
                    name=name, encoding="protobuf", data=file_descriptor_set(type(message)))
            self.channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=self.schemas[name])
        self.sequence += 1
        self.writer.add_message(self.channels[topic], log_time=time_ns, publish_time=time_ns,
                                data=message.SerializeToString(), sequence=self.sequence)


@dataclass(frozen=True)
class CameraViews:
    """The camera frames of a scan with what places them: the rig (intrinsics, poses) and the
    motor states (the platform angle at each frame's time; None: not known)."""

    rig: Rig
    frames: pa.Table
    motor: pa.Table | None = None


def camera_views_from_tables(tables: Mapping[str, pa.Table]) -> CameraViews | None:
    """The camera views of the ``frames``, ``rig`` and ``motor`` artifacts, when there are
    frames and a rig (None otherwise)."""
    frames, rig_table = tables.get("frames"), tables.get("rig")
    if frames is None or rig_table is None or frames.num_rows == 0:
        return None
    from scanpipe.rig import rig_from_table

    motor = tables.get("motor")
    return CameraViews(rig_from_table(rig_table), frames,
                       motor if motor is not None and motor.num_rows else None)


def foxglove_mcap_bytes(cloud: CloudModel | None, mesh: MeshModel | None,
                        name: str = "scan", cameras: CameraViews | None = None,
                        provenance: Mapping[str, Any] | None = None) -> bytes:
    """The Foxglove MCAP file (bytes) of a cloud, a mesh, or both, with the camera frames
    when ``cameras`` is given and the ``provenance`` record as the metadata record
    ``scanpipe.provenance`` (key ``json``)."""
    if cloud is None and mesh is None and cameras is None:
        raise ExportError("mcap export needs points, a mesh or camera frames; found none")
    now_ns = time.time_ns()
    times = [cloud.time_ns] if cloud is not None and cloud.time_ns is not None else []
    if cameras is not None:
        times.append(cameras.frames.column("log_time_ns").to_numpy())
    times = [t for t in times if len(t)]
    start_ns = min(int(t.min()) for t in times) if times else now_ns
    end_ns = max(int(t.max()) for t in times) if times else now_ns
    stream = io.BytesIO()
    writer = Writer(stream, compression=CompressionType.ZSTD)
    writer.start(profile=EXPORT_PROFILE, library=f"scanpipe {__version__}")
    writer.add_metadata(PROVENANCE_METADATA,  # type: ignore[no-untyped-call]
                        {"json": provenance_bytes(provenance or {}).decode()})
    topics = _Topics(writer)
    topics.write("/tf", world_transform(start_ns), start_ns)
    if cloud is not None and len(cloud.xyz):
        _write_profiles(topics, cloud, start_ns)
        topics.write("/scan/cloud", cloud_message(end_ns, RIG_FRAME, cloud.xyz,
                                                  cloud.intensity, cloud.colors), end_ns)
    if cameras is not None:
        _write_cameras(topics, cameras, start_ns)
    if mesh is not None:
        update = SceneUpdate()
        entity = update.entities.add(frame_id=WORLD_FRAME, id="model", frame_locked=True)
        _stamp(entity, end_ns)
        entity.metadata.add(key="source", value=f"scanpipe {__version__}: {name}")
        model = entity.models.add(media_type="model/gltf-binary",
                                  data=glb_bytes(mesh, name, provenance))
        model.pose.orientation.w = 1.0
        model.scale.x = model.scale.y = model.scale.z = 1.0
        topics.write("/model", update, end_ns)
    writer.finish()  # type: ignore[no-untyped-call]
    return stream.getvalue()


def foxglove_export_files(cloud: CloudModel | None, mesh: MeshModel | None, stem: str,
                          cameras: CameraViews | None = None,
                          provenance: Mapping[str, Any] | None = None) -> dict[str, bytes]:
    """``{stem}.mcap`` and the Foxglove layout ``{stem}.layout.json`` that shows it."""
    data = foxglove_mcap_bytes(cloud, mesh, stem, cameras, provenance)
    camera_ids = ([] if cameras is None else
                  sorted(set(cameras.frames.column("camera_id").to_pylist())))
    layout = foxglove_layout(
        clouds=[t for t, present in (("/scan/profile", cloud is not None),
                                     ("/scan/cloud", cloud is not None)) if present],
        camera_ids=camera_ids, model=mesh is not None)
    return {f"{stem}.mcap": data,
            f"{stem}.layout.json": (json.dumps(layout, indent=2) + "\n").encode()}


def foxglove_layout(clouds: list[str], camera_ids: list[str], model: bool = False,
                    log_topic: str | None = None) -> dict[str, Any]:
    """A Foxglove layout (File → Import layout): a 3-D panel following ``world`` with the
    clouds (coloured by their colour fields), the model and the camera frames, and one Image
    panel per camera with its calibration; a Log panel for ``log_topic`` when given."""
    topics: dict[str, Any] = {topic: {"visible": True, "colorMode": "rgba-fields",
                                      "pointSize": 3 if topic == "/scan/cloud" else 2,
                                      "decayTime": 1e9 if topic == "/scan/profile" else 0}
                              for topic in clouds}
    if model:
        topics["/model"] = {"visible": True}
    config: dict[str, Any] = {"3D!scan": {
        "followTf": WORLD_FRAME, "topics": topics,
        "transforms": {f"frame:{camera_frame(c)}": {"visible": True} for c in camera_ids},
        "cameraState": {"distance": 6, "phi": 60, "thetaOffset": 45, "target": [0, 0, 0]},
    }}
    panels = ["3D!scan"]
    for camera_id in camera_ids:
        key = f"Image!{camera_id}"
        config[key] = {"imageMode": {"imageTopic": f"/camera/{camera_id}/image",
                                     "calibrationTopic": f"/camera/{camera_id}/calibration"}}
        panels.append(key)
    if log_topic is not None:
        config["Log!events"] = {"topicToRender": log_topic}
        panels.append("Log!events")
    layout: Any = panels[-1]
    for panel in reversed(panels[:-1]):
        layout = {"first": panel, "second": layout, "direction": "row" if panel == panels[0]
                  else "column", "splitPercentage": 60 if panel == panels[0] else 50}
    return {"configById": config, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1.0}, "layout": layout}


def _write_cameras(topics: _Topics, cameras: CameraViews, start_ns: int) -> None:
    """Every frame as a CompressedImage with its calibration, the camera's pose on the platform
    once, and the platform angle at each frame's time (when the motor states are known)."""
    frames = cameras.frames
    ids = frames.column("camera_id").to_pylist()
    times = frames.column("log_time_ns").to_numpy().astype(np.int64)
    formats = (frames.column("format").to_pylist() if "format" in frames.column_names
               else ["jpeg"] * len(ids))
    data = frames.column("data")
    known: dict[str, CameraConfig] = {}
    for camera_id in sorted(set(ids)):
        try:
            known[camera_id] = cameras.rig.camera(camera_id)
        except RigError:
            continue  # a frame of a camera the rig lacks: shown without calibration or pose
        topics.write("/tf", camera_transform(start_ns, known[camera_id]), start_ns)
    betas = None
    if cameras.motor is not None:
        from scanpipe.motion import beta_deg_at

        betas = beta_deg_at(times, cameras.motor, cameras.rig.motor)
    for row in np.argsort(times, kind="stable").tolist():
        time_ns, camera_id = int(times[row]), str(ids[row])
        if betas is not None:
            topics.write("/tf", platform_transform(time_ns, float(betas[row])), time_ns)
        if camera_id in known and known[camera_id].model == "pinhole":  # none for a 360° image
            topics.write(f"/camera/{camera_id}/calibration",
                         camera_calibration(time_ns, known[camera_id]), time_ns)
        topics.write(f"/camera/{camera_id}/image",
                     compressed_image(time_ns, camera_id, data[row].as_py(),
                                      str(formats[row] or "jpeg")), time_ns)


def _write_profiles(topics: _Topics, cloud: CloudModel, start_ns: int) -> None:
    """One platform-frame PointCloud and one rig → platform transform per profile."""
    if cloud.profile is None or cloud.beta_deg is None or np.any(cloud.profile < 0):
        return
    order = np.argsort(cloud.profile, kind="stable")
    profiles, starts = np.unique(cloud.profile[order], return_index=True)
    bounds = [*starts.tolist(), len(order)]
    for index in range(len(profiles)):
        rows = order[bounds[index]:bounds[index + 1]]
        time_ns = (int(np.median(cloud.time_ns[rows])) if cloud.time_ns is not None
                   else start_ns + index)
        beta = float(np.mean(cloud.beta_deg[rows]))
        rotation = platform_rotation(beta)
        topics.write("/tf", platform_transform(time_ns, beta), time_ns)
        # Row vectors: p_platform = R^T p_rig  ⇔  p_platform_row = p_rig_row @ R.
        xyz_platform = cloud.xyz[rows].astype(np.float64) @ rotation
        topics.write("/scan/profile", cloud_message(
            time_ns, PLATFORM_FRAME, xyz_platform,
            None if cloud.intensity is None else cloud.intensity[rows],
            None if cloud.colors is None else cloud.colors[rows]), time_ns)
