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

from functools import lru_cache
from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.geometry import camera_to_platform, platform_rotation, rows_matmul
from scanpipe.rig import CameraConfig

F64 = NDArray[np.float64]
FloatT = TypeVar("FloatT", np.float32, np.float64)


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
    Computed in float64 (:func:`project_columns` does float32 columns).
    """
    points = np.asarray(points_rig)
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    u, v, depth = project_columns(x, y, z, cam, beta_deg)
    uv = np.empty((len(depth), 2), dtype=np.float64)
    uv[:, 0], uv[:, 1] = u, v
    return uv, depth


@lru_cache(maxsize=1024)
def _pose_as(cam: CameraConfig, beta_deg: float, dtype: str
             ) -> tuple[NDArray[np.floating], NDArray[np.floating]]:
    """:func:`camera_pose_in_rig` in ``dtype`` (read-only), once per camera and angle: the
    projections run for a frame in cache-sized pieces, each of which needs it."""
    rotation, translation = camera_pose_in_rig(cam, beta_deg)
    r, t = rotation.astype(dtype), translation.astype(dtype)
    r.setflags(write=False)
    t.setflags(write=False)
    return r, t


def camera_columns(x: NDArray[FloatT], y: NDArray[FloatT], z: NDArray[FloatT],
                   cam: CameraConfig, beta_deg: float
                   ) -> tuple[NDArray[FloatT], NDArray[FloatT], NDArray[FloatT]]:
    """Rig-frame point columns in the camera frame at platform angle β: ``(x, y, depth)``,
    computed in the columns' dtype (float32 or float64)."""
    r, t = _pose_as(cam, float(beta_deg), x.dtype.char)
    # Column arithmetic on 1-D arrays: (N, 3) temporaries and small matrix products cost
    # several times more (this runs for every frame over every point when colouring clouds).
    dx, dy, dz = x - t[0], y - t[1], z - t[2]
    depth = dx * r[0, 2]
    depth += dy * r[1, 2]
    depth += dz * r[2, 2]
    across = dx * r[0, 0]
    across += dy * r[1, 0]
    across += dz * r[2, 0]
    down = dx * r[0, 1]
    down += dy * r[1, 1]
    down += dz * r[2, 1]
    return across, down, depth


def project_columns(x: NDArray[FloatT], y: NDArray[FloatT], z: NDArray[FloatT],
                    cam: CameraConfig, beta_deg: float
                    ) -> tuple[NDArray[FloatT], NDArray[FloatT], NDArray[FloatT]]:
    """:func:`project_points` of point columns, ``(u, v, depth)`` in the columns' dtype.

    float32 is exact enough for texturing (at 10 m and Full HD well under 10⁻³ px off
    float64) and twice as fast; a pinhole point far outside a distorted lens's view may
    come out as inf or NaN there (the polynomial overflows), as meaningless as its float64
    pixel, and must be masked the same way (:func:`scanpipe.texturing.projective.project_valid`).
    """
    across, down, depth = camera_columns(x, y, z, cam, beta_deg)
    dtype = x.dtype.type
    if cam.model == "equirect":
        longitude, latitude, distance = _angles(across, down, depth, distance=True)
        longitude *= dtype(cam.width / (2 * np.pi))
        longitude += dtype(0.5 * cam.width - 0.5)
        latitude *= dtype(cam.height / np.pi)
        latitude += dtype(0.5 * cam.height - 0.5)
        return longitude, latitude, distance
    u, v = normalized_to_pixels(*normalized_columns(across, down, depth), cam)
    return u, v, depth


def angles_of(across: NDArray[FloatT], down: NDArray[FloatT], depth: NDArray[FloatT]
              ) -> tuple[NDArray[FloatT], NDArray[FloatT]]:
    """Longitude ``atan2(across, depth)`` and latitude ``atan2(down, hypot(across, depth))``
    (radians) of camera-frame columns, as ``arctan2`` gives them (also at ±0; in float32 not
    within 10⁻¹⁹ m of the centre, where squares underflow), from ``arctan``
    of the ratios: NumPy's ``arctan`` is vectorised, its ``arctan2`` is not (4–5× slower in
    float32, where it dominated projecting a 360° frame)."""
    longitude, latitude, _ = _angles(across, down, depth, distance=False)
    return longitude, latitude


def _angles(across: NDArray[FloatT], down: NDArray[FloatT], depth: NDArray[FloatT],
            distance: bool) -> tuple[NDArray[FloatT], NDArray[FloatT], NDArray[FloatT]]:
    """:func:`angles_of`, and the distance from the camera centre when ``distance`` (else an
    empty array): every 360° frame projects every point, so each pass over the columns
    counts (no temporaries beyond the results)."""
    dtype = depth.dtype.type
    squares = across * across
    squares += depth * depth
    with np.errstate(divide="ignore", invalid="ignore"):  # 0 / 0 at the centre: NaN, then 0
        longitude = np.divide(across, depth)
        np.arctan(longitude, out=longitude)
        latitude = np.sqrt(squares)
        np.divide(down, latitude, out=latitude)
        np.arctan(latitude, out=latitude)
    # arctan gives no infinities: only the centre's NaN is mended
    np.copyto(longitude, dtype(0.0), where=np.isnan(longitude))
    np.copyto(latitude, dtype(0.0), where=np.isnan(latitude))
    # the half behind the camera (depth < 0, also −0) lies π further round, on across's side
    np.add(longitude, np.copysign(dtype(np.pi), across), out=longitude,
           where=np.signbit(depth))
    if not distance:
        return longitude, latitude, squares[:0]
    # summed in this order as before: the texture stage's results stay bit for bit
    np.multiply(across, across, out=squares)
    squares += down * down
    squares += depth * depth
    return longitude, latitude, np.sqrt(squares, out=squares)


def normalized_columns(across: NDArray[FloatT], down: NDArray[FloatT], depth: NDArray[FloatT]
                       ) -> tuple[NDArray[FloatT], NDArray[FloatT]]:
    """A pinhole's normalized image coordinates ``(x / z, y / z)`` of camera-frame columns
    (``across`` and ``down`` are divided in place); a point on the camera plane is taken
    10⁻⁹ m in front."""
    dtype = depth.dtype.type
    inverse = np.where(np.abs(depth) < 1e-9, dtype(1e-9), depth)
    np.divide(dtype(1.0), inverse, out=inverse)
    across *= inverse
    down *= inverse
    return across, down


def normalized_to_pixels(x: NDArray[FloatT], y: NDArray[FloatT], cam: CameraConfig
                         ) -> tuple[NDArray[FloatT], NDArray[FloatT]]:
    """Pixels ``(u, v)`` of a pinhole's normalized image coordinates: lens distortion
    (OpenCV's k1, k2, p1, p2, k3), then the camera matrix."""
    dtype = x.dtype.type
    with np.errstate(over="ignore", invalid="ignore"):  # far outside the view: see above
        if any(cam.distortion):
            k1, k2, p1, p2, k3 = (dtype(c) for c in cam.distortion)
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
        u = x * dtype(cam.fx)
        u += dtype(cam.cx)
        v = y * dtype(cam.fy)
        v += dtype(cam.cy)
    return u, v


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
