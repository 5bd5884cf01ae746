"""A small analytic scene for the texture tests: a box room with a pillar and a solid texture.

The colour of a surface point is a smooth function of its 3-D position (a "solid texture"), so
any textured face can be checked against the truth at any point without a renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.camera import pixel_rays
from scanpipe.rig import CameraConfig, Rig, default_rig, rig_table

ROOM_LO = np.array([-3.0, -1.2, -2.0])
ROOM_HI = np.array([3.0, 1.8, 2.0])
PILLAR_LO = np.array([0.9, -1.2, 0.9])
PILLAR_HI = np.array([1.3, 1.8, 1.3])


def solid_colour(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """RGB in 0..255 of a surface point (smooth, non-repetitive over a room)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    r = 128 + 90 * np.sin(2.1 * x + 1.3 * y) * np.cos(1.7 * z - 0.6 * y)
    g = 128 + 90 * np.sin(1.4 * z + 2.2 * y + 0.5) * np.cos(0.9 * x)
    b = 128 + 90 * np.cos(1.9 * y - 1.1 * x + 1.5 * z)
    return np.stack([r, g, b], axis=1)


def box_mesh(lo: NDArray[np.float64], hi: NDArray[np.float64], cell_m: float, inward: bool
             ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """An axis-aligned box as a triangle grid: vertices, faces, vertex normals."""
    verts, faces, normals = [], [], []
    base = 0
    for axis in range(3):
        for side, value in ((-1, lo[axis]), (1, hi[axis])):
            a, b = [k for k in range(3) if k != axis]
            na = max(1, round((hi[a] - lo[a]) / cell_m))
            nb = max(1, round((hi[b] - lo[b]) / cell_m))
            ga, gb = np.meshgrid(np.linspace(lo[a], hi[a], na + 1),
                                 np.linspace(lo[b], hi[b], nb + 1), indexing="ij")
            p = np.zeros((ga.size, 3))
            p[:, axis], p[:, a], p[:, b] = value, ga.ravel(), gb.ravel()
            n = np.zeros(3)
            n[axis] = -side if inward else side
            idx = np.arange(ga.size).reshape(na + 1, nb + 1)
            q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)
            q = q.reshape(-1, 4)
            tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
            verts.append(p)
            faces.append(tri + base)
            normals.append(np.tile(n, (len(p), 1)))
            base += len(p)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(normals)


def room_mesh(cell_m: float = 0.25) -> tuple[NDArray[np.float64], NDArray[np.int64],
                                             NDArray[np.float64]]:
    """The room (normals inward) and the pillar (normals outward) as one mesh."""
    v1, f1, n1 = box_mesh(ROOM_LO, ROOM_HI, cell_m, inward=True)
    v2, f2, n2 = box_mesh(PILLAR_LO, PILLAR_HI, cell_m / 2, inward=False)
    return np.concatenate([v1, v2]), np.concatenate([f1, f2 + len(v1)]), np.concatenate([n1, n2])


def mesh_tables(vertices: NDArray[np.float64], faces: NDArray[np.int64],
                normals: NDArray[np.float64]) -> tuple[pa.Table, pa.Table]:
    """``mesh_vertices`` and ``mesh_faces`` artifacts."""
    vt = pa.table({**{c: pa.array(vertices[:, k].astype(np.float32)) for k, c in enumerate("xyz")},
                   **{c: pa.array(normals[:, k].astype(np.float32))
                      for k, c in enumerate(("nx", "ny", "nz"))}})
    ft = pa.table({c: pa.array(faces[:, k].astype(np.int32)) for k, c in enumerate(("v0", "v1",
                                                                                  "v2"))})
    return vt, ft


class Caster:
    """Ray casting against the analytic scene mesh (coarse room + pillar)."""

    def __init__(self) -> None:
        v, f, _ = room_mesh(cell_m=1.0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                 o3d.core.Tensor(f.astype(np.uint32)))

    def colour(self, origin: NDArray[np.float64], directions: NDArray[np.float64]
               ) -> NDArray[np.float64]:
        """RGB of what rays from ``origin`` hit."""
        rays = np.concatenate([np.broadcast_to(origin, directions.shape), directions], 1)
        t = self.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        return solid_colour(origin + directions * t[:, None].astype(np.float64))


def small_rig(width: int = 320, height: int = 180, distortion: tuple[float, ...] = (0,) * 5
              ) -> Rig:
    """The default rig's two phones as small cameras (same 65° field of view)."""
    scale = width / 1920
    cams = []
    for cam in default_rig().cameras[:2]:
        cams.append(cam.model_copy(update={
            "width": width, "height": height, "fx": 1507 * scale, "fy": 1507 * scale,
            "cx": (width - 1) / 2, "cy": (height - 1) / 2, "distortion": distortion}))
    return default_rig().model_copy(update={"cameras": tuple(cams)})


@dataclass
class Recording:
    rig: Rig
    frames: pa.Table
    motor: pa.Table

    def inputs(self, vertices: pa.Table, faces: pa.Table) -> dict[str, pa.Table]:
        return {"mesh_vertices": vertices, "mesh_faces": faces, "frames": self.frames,
                "motor": self.motor, "rig": rig_table(self.rig)}


def render(cam: CameraConfig, beta_deg: float, caster: Caster, gain: float = 1.0
           ) -> NDArray[np.uint8]:
    """A BGR frame of the scene (one ray per pixel centre)."""
    origin, dirs = pixel_rays(cam, beta_deg)
    rgb = caster.colour(origin, dirs.reshape(-1, 3)).reshape(cam.height, cam.width, 3) * gain
    return np.asarray(np.clip(rgb[:, :, ::-1] + 0.5, 0, 255), dtype=np.uint8)


def record(rig: Rig, beta_step_deg: float = 6.0, travel_deg: float = 180.0,
           gains: dict[str, float] | None = None, caster: Caster | None = None) -> Recording:
    """Frames every ``beta_step_deg`` while the platform turns through ``travel_deg``.

    The platform turns at 10°/s; each frame is rendered at the platform angle of its time.
    """
    caster = caster or Caster()
    t0 = 1_700_000_000_000_000_000
    step_deg = rig.motor.pulse_step_deg
    total_steps = round(travel_deg / step_deg)
    duration_ns = int(travel_deg / 10.0 * 1e9)
    motor_t = t0 + np.linspace(0, duration_ns, 11).astype(np.int64)
    motor_steps = np.linspace(0, total_steps, 11).round().astype(np.int64)
    motor = pa.table({
        "log_time_ns": pa.array(motor_t), "step_count": pa.array(motor_steps),
        "target_step_count": pa.array(np.full(11, total_steps)),
        "moving": pa.array(np.r_[np.ones(10, bool), False]),
        "device_time_us": pa.array((motor_t - t0) // 1000),
    })
    n = round(travel_deg / beta_step_deg) + 1
    rows: dict[str, list[object]] = {k: [] for k in ("camera_id", "log_time_ns", "sequence",
                                                      "format", "width", "height", "data")}
    for cam in rig.cameras:
        for k in range(n):
            beta = k * beta_step_deg
            steps = beta / step_deg
            time_ns = int(t0 + np.interp(steps, motor_steps, motor_t - t0))
            image = render(cam, float(np.interp(time_ns - t0, motor_t - t0, motor_steps)
                                      * step_deg), caster, (gains or {}).get(cam.id, 1.0))
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            rows["camera_id"].append(cam.id)
            rows["log_time_ns"].append(time_ns)
            rows["sequence"].append(k)
            rows["format"].append("jpeg")
            rows["width"].append(cam.width)
            rows["height"].append(cam.height)
            rows["data"].append(jpeg.tobytes())
    frames = pa.table({
        "camera_id": pa.array(rows["camera_id"], pa.string()),
        "log_time_ns": pa.array(rows["log_time_ns"], pa.int64()),
        "sequence": pa.array(rows["sequence"], pa.int64()),
        "format": pa.array(rows["format"], pa.string()),
        "width": pa.array(rows["width"], pa.int32()),
        "height": pa.array(rows["height"], pa.int32()),
        "data": pa.array(rows["data"], pa.binary()),
    })
    return Recording(rig, frames, motor)

