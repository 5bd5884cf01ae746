"""The camera models, posed on the turning platform: OpenCV pinhole with distortion, and the
equirectangular image of a 360° camera.

Used both to render (the virtual camera casts a ray per pixel) and to texture (project model
points into a frame). Frames and rotation order: :mod:`scanpipe.geometry`.

Equirect (``CameraConfig.model == "equirect"``): a direction ``(x, y, z)`` in the camera frame
(x right, y down, z forward) has longitude ``λ = atan2(x, z)`` and latitude
``φ = atan2(y, hypot(x, z))`` (positive downwards); its pixel is
``u = (λ / 2π + ½) · width − ½``, ``v = (φ / π + ½) · height − ½``. The image centre looks
along the camera's z axis, its left and right edges meet straight behind it (the *wrap*), the
top row is straight up. Its "depth" is the distance from the camera centre.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.geometry import camera_to_platform, platform_rotation, rows_matmul
from scanpipe.rig import CameraConfig

F64 = NDArray[np.float64]


def intrinsic_matrix(cam: CameraConfig) -> F64:
    """The 3×3 camera matrix K."""
    return np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])


def camera_pose_in_rig(cam: CameraConfig, beta_deg: float) -> tuple[F64, F64]:
    """``(R, t)`` mapping camera coordinates to the rig frame at platform angle β:
    ``p_rig = R @ p_cam + t``."""
    r_platform = platform_rotation(beta_deg)
    rotation = r_platform @ camera_to_platform(cam.pose.rotation_deg)
    translation = r_platform @ np.asarray(cam.pose.translation_m, dtype=np.float64)
    return np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64)


def project_points(
    points_rig: NDArray[np.floating], cam: CameraConfig, beta_deg: float
) -> tuple[F64, F64]:
    """Project rig-frame points into the image: ``(uv (N, 2) pixels, depth (N,) metres)``.

    Pinhole: points behind the camera get depth ≤ 0; their uv is meaningless and must be
    masked. Equirect: every point has a pixel; depth is its distance from the camera centre.
    """
    rotation, translation = camera_pose_in_rig(cam, beta_deg)
    points = np.asarray(points_rig)
    # Column arithmetic on 1-D arrays: (N, 3) temporaries and small matrix products cost
    # several times more (this runs for every frame over every point when colouring clouds).
    dx, dy, dz = (points[:, k].astype(np.float64) - translation[k] for k in range(3))
    depth = dx * rotation[0, 2] + dy * rotation[1, 2] + dz * rotation[2, 2]
    if cam.model == "equirect":
        x = dx * rotation[0, 0] + dy * rotation[1, 0] + dz * rotation[2, 0]
        y = dx * rotation[0, 1] + dy * rotation[1, 1] + dz * rotation[2, 1]
        across = np.hypot(x, depth)
        uv = np.empty((len(depth), 2), dtype=np.float64)
        uv[:, 0] = (np.arctan2(x, depth) / (2 * np.pi) + 0.5) * cam.width - 0.5
        uv[:, 1] = (np.arctan2(y, across) / np.pi + 0.5) * cam.height - 0.5
        return uv, np.hypot(across, y)
    inverse = 1.0 / np.where(np.abs(depth) < 1e-9, 1e-9, depth)
    x = (dx * rotation[0, 0] + dy * rotation[1, 0] + dz * rotation[2, 0]) * inverse
    y = (dx * rotation[0, 1] + dy * rotation[1, 1] + dz * rotation[2, 1]) * inverse
    k1, k2, p1, p2, k3 = cam.distortion
    if any(cam.distortion):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
    uv = np.empty((len(depth), 2), dtype=np.float64)
    uv[:, 0] = cam.fx * x + cam.cx
    uv[:, 1] = cam.fy * y + cam.cy
    return uv, depth


def pixel_rays(cam: CameraConfig, beta_deg: float, stride: int = 1) -> tuple[F64, F64]:
    """Ray origin (3,) and unit directions (H/stride, W/stride, 3) in the rig frame for pixel
    centres, with the lens distortion undone (so rendering matches :func:`project_points`)."""
    us = np.arange(0, cam.width, stride, dtype=np.float64)
    vs = np.arange(0, cam.height, stride, dtype=np.float64)
    if cam.model == "equirect":
        rotation, origin = camera_pose_in_rig(cam, beta_deg)
        lon = (us + 0.5) / cam.width * 2 * np.pi - np.pi
        lat = (vs + 0.5) / cam.height * np.pi - np.pi / 2
        lon_grid, lat_grid = np.meshgrid(lon, lat)
        directions_cam = np.stack([np.cos(lat_grid) * np.sin(lon_grid), np.sin(lat_grid),
                                   np.cos(lat_grid) * np.cos(lon_grid)], -1).reshape(-1, 3)
        directions = rows_matmul(directions_cam, rotation.T).reshape(len(vs), len(us), 3)
        return origin, directions
    grid = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 1, 2)
    if any(cam.distortion):
        normalized = cv2.undistortPoints(
            grid, intrinsic_matrix(cam), np.asarray(cam.distortion, dtype=np.float64)
        ).reshape(-1, 2)
    else:
        flat = grid.reshape(-1, 2)
        normalized = np.stack([(flat[:, 0] - cam.cx) / cam.fx, (flat[:, 1] - cam.cy) / cam.fy], 1)
    directions_cam = np.concatenate([normalized, np.ones((normalized.shape[0], 1))], axis=1)
    directions_cam /= np.linalg.norm(directions_cam, axis=1, keepdims=True)
    rotation, origin = camera_pose_in_rig(cam, beta_deg)
    directions = rows_matmul(directions_cam, rotation.T).reshape(len(vs), len(us), 3)
    return origin, directions
