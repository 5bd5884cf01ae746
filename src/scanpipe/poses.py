"""Rigid poses of scans in a site: 4×4 matrices ↔ the ``poses`` artifact, and their errors.

A pose maps a scan's rig frame into the site frame: ``p_site = R @ p_rig + t``. The ``poses``
artifact stores ``t`` (metres) and ``R`` as a unit quaternion (w, x, y, z), one row per scan,
with an optional 6 × 6 covariance in the site frame (twist order rx, ry, rz, tx, ty, tz; rad²,
m²).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.geometry import rotation_matrix_deg
from scanpipe.schema import POSES

F64 = NDArray[np.float64]


def pose_matrix(rotation_deg: Sequence[float], translation_m: Sequence[float]) -> F64:
    """A 4×4 pose from Euler angles ``(rx, ry, rz)`` (degrees, ``Rz @ Ry @ Rx``) and a
    translation."""
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_matrix_deg(rotation_deg)
    matrix[:3, 3] = np.asarray(translation_m, dtype=np.float64)
    return matrix


def euler_deg(rotation: F64) -> tuple[float, float, float]:
    """Euler angles ``(rx, ry, rz)`` in degrees of a rotation ``Rz @ Ry @ Rx``."""
    ry = -math.asin(float(np.clip(rotation[2, 0], -1.0, 1.0)))
    rx = math.atan2(float(rotation[2, 1]), float(rotation[2, 2]))
    rz = math.atan2(float(rotation[1, 0]), float(rotation[0, 0]))
    return math.degrees(rx), math.degrees(ry), math.degrees(rz)


def invert(pose: F64) -> F64:
    """The inverse of a rigid 4×4 pose."""
    inverse = np.eye(4)
    inverse[:3, :3] = pose[:3, :3].T
    inverse[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inverse


def quaternion_from_rotation(rotation: F64) -> F64:
    """Unit quaternion (w, x, y, z), w ≥ 0, of a rotation matrix (Shepperd's method)."""
    m = rotation
    trace = float(m[0, 0] + m[1, 1] + m[2, 2])
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s,
                      (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = np.zeros(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def rotation_from_quaternion(q: Sequence[float]) -> F64:
    """The rotation matrix of a quaternion (w, x, y, z) (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def poses_table(names: Sequence[str], poses: Sequence[F64],
                covariances: Sequence[F64 | None] | None = None) -> pa.Table:
    """The ``poses`` artifact of scans ``names`` at 4×4 ``poses``."""
    quats = np.array([quaternion_from_rotation(p[:3, :3]) for p in poses]).reshape(-1, 4)
    trans = np.array([p[:3, 3] for p in poses], dtype=np.float64).reshape(-1, 3)
    columns: dict[str, pa.Array] = {"scan": pa.array(list(names), pa.string())}
    for k, name in enumerate(("tx_m", "ty_m", "tz_m")):
        columns[name] = pa.array(trans[:, k], pa.float64())
    for k, name in enumerate(("qw", "qx", "qy", "qz")):
        columns[name] = pa.array(quats[:, k], pa.float64())
    if covariances is not None:
        columns["covariance"] = pa.array(
            [None if c is None else np.asarray(c, np.float64).ravel().tolist()
             for c in covariances], pa.list_(pa.float64()))
    table = pa.table(columns)
    POSES.check(table)
    return table


def poses_from_table(table: pa.Table, where: str = "poses") -> dict[str, F64]:
    """Scan name → 4×4 pose from a ``poses`` table (checked against its schema)."""
    POSES.check(table, where=where)
    data = table.to_pydict()
    result: dict[str, F64] = {}
    for i, name in enumerate(data["scan"]):
        pose = np.eye(4)
        pose[:3, :3] = rotation_from_quaternion([data[k][i] for k in ("qw", "qx", "qy", "qz")])
        pose[:3, 3] = [data[k][i] for k in ("tx_m", "ty_m", "tz_m")]
        result[str(name)] = pose
    return result


def pose_error(estimate: F64, truth: F64) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) of ``truth⁻¹ · estimate``."""
    delta = invert(truth) @ estimate
    cosine = float(np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.linalg.norm(delta[:3, 3])), math.degrees(math.acos(cosine))


def pose_errors(estimated: dict[str, F64], truth: dict[str, F64],
                reference: str | None = None) -> list[dict[str, object]]:
    """Each scan's translation (m) and rotation (degrees) error against the truth, the two
    frames tied together at ``reference`` (default: the first estimated scan that has a true
    pose) — a registration fixes poses only up to the site frame, so errors are relative to
    that scan, whose own error is 0 by definition. Scans without an estimate or a true pose
    are listed with ``None`` errors."""
    shared = [name for name in estimated if name in truth]
    if reference is None:
        reference = shared[0] if shared else None
    rows: list[dict[str, object]] = []
    gauge = (truth[reference] @ invert(estimated[reference])
             if reference in estimated and reference in truth else None)
    for name in sorted(set(estimated) | set(truth)):
        row: dict[str, object] = {"scan": name, "translation_m": None, "rotation_deg": None}
        if gauge is not None and name in estimated and name in truth:
            dt, dr = pose_error(gauge @ estimated[name], truth[name])
            row["translation_m"], row["rotation_deg"] = dt, dr
        row["note"] = ("reference" if name == reference else
                       "not registered" if name not in estimated else
                       "no true pose" if name not in truth else "")
        rows.append(row)
    return rows
