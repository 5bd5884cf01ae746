"""The rig's frames and the transforms between them: one place for every convention.

Frames (paper eq. 11–16; y is up, the platform turns about y):

- *scan frame*: the 2-D scanner's own plane. A return at range r and beam angle α lies at
  ``(r sin α, r cos α, 0)``; α = 0 points along +y (up when the scanner is mounted upright).
- *platform frame*: turns with the platform. The scanner's mounting pose maps the scan frame
  into it: ``p_platform = R_mount @ p_scan + t_mount``. With the default (zero) pose the two
  frames coincide.
- *rig frame*: fixed to the ground, y = motor axis. ``p_rig = R_platform(β) @ p_platform`` with
  ``x' = x cos β − z sin β, y' = y, z' = x sin β + z cos β``, which reproduces the paper's
  ``x = r sin α cos β, y = r cos α, z = r sin α sin β``.
- *camera frame*: OpenCV's (x right, y down, z forward). A camera with zero rotation looks
  along +z of the platform with image-up along +y; its pose rotates that base view.

Euler angles everywhere are ``(rx, ry, rz)`` in degrees about the parent's fixed axes, applied
x first, then y, then z: ``R = Rz @ Ry @ Rx``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

#: Maps OpenCV camera axes (x right, y down, z forward) to a view along +z with up = +y.
CAMERA_BASE: F64 = np.diag([-1.0, -1.0, 1.0])


def rotation_matrix_deg(rotation_deg: ArrayLike) -> F64:
    """Rotation matrix ``Rz @ Ry @ Rx`` for Euler angles ``(rx, ry, rz)`` in degrees."""
    rx, ry, rz = np.radians(np.asarray(rotation_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return np.asarray(r_z @ r_y @ r_x, dtype=np.float64)


def platform_rotation(beta_deg: ArrayLike) -> F64:
    """Rotation(s) from the platform frame to the rig frame for platform angle(s) β.

    Returns shape ``(3, 3)`` for a scalar β, ``(..., 3, 3)`` for an array.
    """
    beta = np.radians(np.asarray(beta_deg, dtype=np.float64))
    c, s = np.cos(beta), np.sin(beta)
    zero, one = np.zeros_like(beta), np.ones_like(beta)
    rows = [
        np.stack([c, zero, -s], -1),
        np.stack([zero, one, zero], -1),
        np.stack([s, zero, c], -1),
    ]
    return np.stack(rows, -2)


def scan_plane_direction(alpha_deg: ArrayLike) -> F64:
    """Unit beam direction(s) in the scan frame for beam angle(s) α: ``(sin α, cos α, 0)``."""
    alpha = np.radians(np.asarray(alpha_deg, dtype=np.float64))
    return np.stack([np.sin(alpha), np.cos(alpha), np.zeros_like(alpha)], -1)


def scan_point_to_rig(
    range_m: float,
    alpha_deg: float,
    beta_deg: float,
    mount_translation_m: ArrayLike = (0.0, 0.0, 0.0),
    mount_rotation_deg: ArrayLike = (0.0, 0.0, 0.0),
) -> F64:
    """One return to rig coordinates, straight from the definitions (the slow reference)."""
    p_scan = range_m * scan_plane_direction(alpha_deg)
    p_platform = rotation_matrix_deg(mount_rotation_deg) @ p_scan + np.asarray(
        mount_translation_m, dtype=np.float64
    )
    return np.asarray(platform_rotation(beta_deg) @ p_platform, dtype=np.float64)


def sensor_origin_in_rig(beta_deg: ArrayLike, mount_translation_m: ArrayLike) -> F64:
    """Where the scanner's optical centre is in the rig frame at platform angle(s) β."""
    t = np.asarray(mount_translation_m, dtype=np.float64)
    return np.asarray(platform_rotation(beta_deg) @ t, dtype=np.float64)


def camera_to_platform(rotation_deg: ArrayLike) -> F64:
    """Rotation from OpenCV camera axes to the platform frame for a camera pose's Euler angles."""
    return rotation_matrix_deg(rotation_deg) @ CAMERA_BASE


def rows_matmul(rows: NDArray[np.floating], matrix: NDArray[np.floating]) -> F64:
    """``rows @ matrix`` for an (N, 3) array and a 3×3 matrix, written out in columns.

    Threaded BLAS runs this shape 3–7× slower than three broadcast products (measured on the
    2-core workstation), and it is in the hot path of projection and rendering.
    """
    r = np.asarray(rows, dtype=np.float64)
    m = np.asarray(matrix, dtype=np.float64)
    return np.asarray(r[:, :1] * m[0] + r[:, 1:2] * m[1] + r[:, 2:3] * m[2], dtype=np.float64)
