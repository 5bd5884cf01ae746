"""COLMAP sparse model (text form) of the camera frames, their poses and the points, for
multi-view stereo and Gaussian-splatting tools.

Layout (COLMAP's own, so ``colmap`` / ``pycolmap`` / nerfstudio open the folder as is)::

    <stem>_colmap/images/<camera>_<sequence>.<jpg|png>   the frames as recorded
    <stem>_colmap/sparse/0/cameras.txt    CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    <stem>_colmap/sparse/0/images.txt     IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then an
                                          empty POINTS2D line (no feature tracks)
    <stem>_colmap/sparse/0/points3D.txt   POINT3D_ID X Y Z R G B ERROR (empty TRACK[])

World frame: the rig frame (metres, y up). A pose is world → camera (COLMAP's convention:
``x_cam = R · x_world + t``, camera axes as OpenCV: x right, y down, z forward). Cameras use the
``OPENCV`` model (fx fy cx cy k1 k2 p1 p2), or ``FULL_OPENCV`` when k3 ≠ 0. COLMAP's image
coordinates put the centre of the top-left pixel at (0.5, 0.5), scanpipe's (as OpenCV's and
ROS CameraInfo's) at (0, 0): the principal point is written as ``(cx + 0.5, cy + 0.5)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from scanpipe.exporters.model import CloudModel
from scanpipe.exporters.textfmt import Fixed, Ints, Part, render_lines
from scanpipe.rig import CameraConfig

F64 = NDArray[np.float64]


def quaternion_wxyz(rotation: F64) -> F64:
    """A unit quaternion (w, x, y, z, w ≥ 0) of a 3×3 rotation matrix."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = np.sqrt(1.0 + trace) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.asarray(q, dtype=np.float64)
    quat /= np.linalg.norm(quat)
    return -quat if quat[0] < 0 else quat


def _camera_line(camera_id: int, cam: CameraConfig) -> str:
    k1, k2, p1, p2, k3 = (float(v) for v in cam.distortion)
    # COLMAP puts the centre of the top-left pixel at (0.5, 0.5), scanpipe (OpenCV, ROS) at 0.
    params = [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, k1, k2, p1, p2]
    model = "OPENCV"
    if k3 != 0.0:
        model, params = "FULL_OPENCV", [*params, k3, 0.0, 0.0, 0.0]
    return f"{camera_id} {model} {cam.width} {cam.height} " + " ".join(
        f"{float(v):.17g}" for v in params)


def colmap_files(
    stem: str,
    cameras: Sequence[CameraConfig],
    poses_cam_to_rig: Sequence[tuple[F64, F64]],
    images: Sequence[bytes],
    image_names: Sequence[str],
    cloud: CloudModel | None,
    comment: str = "",
) -> dict[str, bytes]:
    """The COLMAP text model and the images, by file name relative to the export folder.

    ``poses_cam_to_rig[i]`` is ``(R, t)`` with ``p_rig = R @ p_cam + t`` (as
    :func:`scanpipe.camera.camera_pose_in_rig`); ``image_names[i]`` the file name in
    ``images/``.
    """
    root = f"{stem}_colmap"
    header = f"# scanpipe COLMAP export{(': ' + comment) if comment else ''}\n"
    camera_ids: dict[str, int] = {}
    camera_lines = []
    for cam in cameras:
        if cam.id not in camera_ids:
            camera_ids[cam.id] = len(camera_ids) + 1
            camera_lines.append(_camera_line(camera_ids[cam.id], cam))
    files: dict[str, bytes] = {}
    image_lines = []
    for i, (cam, (rotation, translation), data, name) in enumerate(
            zip(cameras, poses_cam_to_rig, images, image_names, strict=True)):
        r_cw = np.asarray(rotation, dtype=np.float64).T
        t_cw = -r_cw @ np.asarray(translation, dtype=np.float64)
        q = quaternion_wxyz(r_cw)
        values = " ".join(f"{v:.17g}" for v in (*q, *t_cw))
        image_lines.append(f"{i + 1} {values} {camera_ids[cam.id]} {name}\n")
        files[f"{root}/images/{name}"] = data
    files[f"{root}/sparse/0/cameras.txt"] = (
        header + "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        + f"# Number of cameras: {len(camera_lines)}\n"
        + "".join(line + "\n" for line in camera_lines)).encode()
    files[f"{root}/sparse/0/images.txt"] = (
        header + "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        + "# POINTS2D[] as (X, Y, POINT3D_ID)\n"
        + f"# Number of images: {len(image_lines)}\n"
        + "".join(line + "\n" for line in image_lines)).encode()
    files[f"{root}/sparse/0/points3D.txt"] = header.encode() + _points_text(cloud)
    return files


def _points_text(cloud: CloudModel | None) -> bytes:
    """``POINT3D_ID X Y Z R G B ERROR`` lines (no track), built column-wise."""
    head = b"# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
    if cloud is None or len(cloud.xyz) == 0:
        return head + b"# Number of points: 0\n"
    n = len(cloud.xyz)
    rgb = np.full((n, 3), 128, np.int64) if cloud.colors is None else cloud.colors.astype(np.int64)
    xyz = cloud.xyz.astype(np.float64)
    parts: list[Part] = [Ints(np.arange(1, n + 1, dtype=np.int64))]
    for k in range(3):
        parts += [b" ", Fixed(xyz[:, k], 6)]
    for k in range(3):
        parts += [b" ", Ints(rgb[:, k])]
    parts.append(b" 0")
    return head + f"# Number of points: {n}\n".encode() + render_lines(n, parts)
