"""The result for Foxglove: the scan as it was built up, and the model, in one MCAP file.

Topics (protobuf encoding, the published Foxglove schemas of
:mod:`scanpipe.exporters.foxglove_schemas`):

- ``/tf`` (``foxglove.FrameTransform``): ``world`` → ``rig`` once (world is Foxglove's z-up
  frame, rig is scanpipe's y-up frame: a +90° turn about x) and ``rig`` → ``platform`` at every
  profile's time (the platform angle β about y), so scrubbing the timeline turns the platform.
- ``/scan/profile`` (``foxglove.PointCloud``): one message per profile in the ``platform``
  frame, at the profile's time (needs the grid indices; with a decay time the scan builds up).
- ``/scan/cloud`` (``foxglove.PointCloud``): the whole cloud in the ``rig`` frame, once, at the
  end of the scan.
- ``/model`` (``foxglove.SceneUpdate``): the mesh as an entity with one embedded GLB model. glTF
  is y-up and Foxglove turns glTF models y-up → z-up itself, so the entity is placed in
  ``world`` with an identity pose and lands exactly on the rig-frame cloud.
"""

from __future__ import annotations

import io
import time
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from scanpipe import __version__
from scanpipe.errors import ExportError
from scanpipe.exporters import foxglove_schemas as fox
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.model import CloudModel, MeshModel
from scanpipe.geometry import platform_rotation
from scanpipe.protobuf import file_descriptor_set

WORLD_FRAME, RIG_FRAME, PLATFORM_FRAME = "world", "rig", "platform"
#: world (z up) ← rig (y up): (x, y, z) ↦ (x, −z, y), a +90° rotation about x.
WORLD_FROM_RIG = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
_FLOAT32, _UINT16, _UINT8 = 7, 3, 1


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


def _transform(time_ns: int, parent: str, child: str, rotation: NDArray[np.floating]) -> Any:
    message = fox.FrameTransform(parent_frame_id=parent, child_frame_id=child)
    _stamp(message, time_ns)
    x, y, z, w = quaternion_from_matrix(rotation)
    message.rotation.x, message.rotation.y, message.rotation.z, message.rotation.w = x, y, z, w
    return message


def _cloud_message(time_ns: int, frame: str, xyz: NDArray[np.floating],
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
    message = fox.PointCloud(frame_id=frame, point_stride=packed.dtype.itemsize,
                             data=packed.tobytes())
    _stamp(message, time_ns)
    message.pose.orientation.w = 1.0
    layout = packed.dtype.fields
    assert layout is not None
    for name, _, numeric in fields:
        message.fields.add(name=name, offset=layout[name][1], type=numeric)
    return message


class _Topics:
    """Registers each topic's schema and channel once; writes messages in time order."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.channels: dict[str, int] = {}
        self.sequence = 0

    def write(self, topic: str, message: Any, time_ns: int) -> None:
        if topic not in self.channels:
            schema = self.writer.register_schema(
                name=message.DESCRIPTOR.full_name, encoding="protobuf",
                data=file_descriptor_set(type(message)))
            self.channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=schema)
        self.sequence += 1
        self.writer.add_message(self.channels[topic], log_time=time_ns, publish_time=time_ns,
                                data=message.SerializeToString(), sequence=self.sequence)


def foxglove_mcap_bytes(cloud: CloudModel | None, mesh: MeshModel | None,
                        name: str = "scan") -> bytes:
    """The Foxglove MCAP file (bytes) of a cloud, a mesh, or both."""
    if cloud is None and mesh is None:
        raise ExportError("mcap export needs points or a mesh; found neither")
    now_ns = time.time_ns()
    times = cloud.time_ns if cloud is not None and cloud.time_ns is not None else None
    start_ns = int(times.min()) if times is not None and len(times) else now_ns
    end_ns = int(times.max()) if times is not None and len(times) else now_ns
    stream = io.BytesIO()
    writer = Writer(stream, compression=CompressionType.ZSTD)
    writer.start(profile="", library=f"scanpipe {__version__}")
    topics = _Topics(writer)
    topics.write("/tf", _transform(start_ns, WORLD_FRAME, RIG_FRAME, WORLD_FROM_RIG), start_ns)
    if cloud is not None and len(cloud.xyz):
        _write_profiles(topics, cloud, start_ns)
        topics.write("/scan/cloud", _cloud_message(end_ns, RIG_FRAME, cloud.xyz,
                                                   cloud.intensity, cloud.colors), end_ns)
    if mesh is not None:
        update = fox.SceneUpdate()
        entity = update.entities.add(frame_id=WORLD_FRAME, id="model", frame_locked=True)
        _stamp(entity, end_ns)
        entity.metadata.add(key="source", value=f"scanpipe {__version__}: {name}")
        model = entity.models.add(media_type="model/gltf-binary", data=glb_bytes(mesh, name))
        model.pose.orientation.w = 1.0
        model.scale.x = model.scale.y = model.scale.z = 1.0
        topics.write("/model", update, end_ns)
    writer.finish()  # type: ignore[no-untyped-call]
    return stream.getvalue()


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
        topics.write("/tf", _transform(time_ns, RIG_FRAME, PLATFORM_FRAME, rotation), time_ns)
        # Row vectors: p_platform = R^T p_rig  ⇔  p_platform_row = p_rig_row @ R.
        xyz_platform = cloud.xyz[rows].astype(np.float64) @ rotation
        topics.write("/scan/profile", _cloud_message(
            time_ns, PLATFORM_FRAME, xyz_platform,
            None if cloud.intensity is None else cloud.intensity[rows],
            None if cloud.colors is None else cloud.colors[rows]), time_ns)
