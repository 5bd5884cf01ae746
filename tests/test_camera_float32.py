"""The float32 projection texturing uses (scanpipe.camera.project_columns): as the float64 one
to well under a thousandth of a pixel out to the far wall of a large room, for a pinhole, a
distorted pinhole and a 360° camera; the float64 one as OpenCV projects."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from scanpipe.camera import (
    _pose_as,
    angles_of,
    camera_columns,
    camera_pose_in_rig,
    intrinsic_matrix,
    project_columns,
    project_points,
)
from scanpipe.rig import CameraConfig, Pose, default_rig
from scanpipe.texturing.projective import project_valid, project_valid_columns

#: The far wall of the lab room is ~4 m from the rig; this room is twice that.
ROOM_M = 8.0


def room_points(count: int = 200_000, seed: int = 3) -> np.ndarray:
    """Points on the walls, floor and ceiling of a box ±ROOM_M wide, −1.5…2.5 m high, and some
    near the rig, as float32 (a mesh's vertices are stored so)."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    reach = np.minimum(ROOM_M / np.maximum(np.abs(directions[:, [0, 2]]).max(axis=1), 1e-9),
                       np.where(directions[:, 1] > 0, 2.5, 1.5) / np.abs(directions[:, 1]))
    reach[: count // 20] *= rng.uniform(0.05, 0.5, count // 20)  # near the rig, and behind it
    return (directions * reach[:, None]).astype(np.float32)


def cameras() -> list[CameraConfig]:
    phone, _, pano = default_rig().cameras
    distorted = phone.model_copy(update={
        "id": "distorted", "distortion": (-0.12, 0.03, 0.001, -0.001, 0.002),
        "pose": Pose(translation_m=(0.1, 0.3, -0.05), rotation_deg=(20.0, 30.0, 5.0))})
    return [phone, distorted, pano]


@pytest.mark.parametrize("cam", cameras(), ids=lambda c: c.id)
def test_float32_is_float64_to_a_thousandth_of_a_pixel(cam: CameraConfig) -> None:
    points = room_points()
    columns = [np.ascontiguousarray(points[:, k]) for k in range(3)]
    for beta in (0.0, 37.5, 181.0, 300.25):
        uv, depth, valid = project_valid(points, cam, beta, 0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # far outside a distorted view: no overflow warning
            u, v, depth32, valid32 = project_valid_columns(*columns, cam, beta, 0.0)
        assert u.dtype == v.dtype == depth32.dtype == np.float32
        assert valid.sum() > 1000
        both = valid & valid32
        error_px = np.hypot(u[both] - uv[both, 0], v[both] - uv[both, 1])
        assert error_px.max() < 1e-3, (cam.id, beta, error_px.max())
        far = both & (depth > 0.9 * depth[valid].max())
        assert far.sum() > 10  # the far wall is in the test
        np.testing.assert_allclose(depth32[both], depth[both], rtol=1e-6)
        # the masks differ only where a point lies within float noise of the image border
        differ = valid != valid32
        border = np.minimum.reduce([uv[:, 0], cam.width - 1 - uv[:, 0], uv[:, 1],
                                    cam.height - 1 - uv[:, 1]])
        assert (np.abs(border[differ]) < 1e-3).all()


def test_float64_projection_is_opencvs() -> None:
    cam = cameras()[1]  # distorted, tilted, off the axis
    points = room_points(20_000).astype(np.float64)
    beta = 123.0
    uv, depth = project_points(points, cam, beta)
    rotation, translation = camera_pose_in_rig(cam, beta)
    ahead = depth > 0.5
    # a point's camera coordinates: R.T (p − t)
    in_camera = (points[ahead] - translation) @ rotation
    opencv, _ = cv2.projectPoints(in_camera, np.zeros(3), np.zeros(3), intrinsic_matrix(cam),
                                  np.asarray(cam.distortion, np.float64))
    inside = ((np.abs(in_camera[:, 0] / in_camera[:, 2]) < 0.6)
              & (np.abs(in_camera[:, 1] / in_camera[:, 2]) < 0.6))
    assert inside.sum() > 1000
    np.testing.assert_allclose(uv[ahead][inside], opencv.reshape(-1, 2)[inside], atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_angles_are_arctan2s_also_at_signed_zeros(dtype: type) -> None:
    values = np.array([0.0, -0.0, 1.0, -1.0, 2.5, -0.3])
    across, down, depth = (g.ravel().astype(dtype) for g in np.meshgrid(values, values, values))
    rng = np.random.default_rng(0)
    across, down, depth = (np.concatenate([c, rng.normal(size=10_000).astype(dtype)])
                           for c in (across, down, depth))
    longitude, latitude = angles_of(across, down, depth)
    tolerance = 1e-15 if dtype == np.float64 else 5e-7
    np.testing.assert_allclose(longitude, np.arctan2(across, depth), rtol=0, atol=tolerance)
    np.testing.assert_allclose(latitude, np.arctan2(down, np.hypot(across, depth)), rtol=0,
                               atol=tolerance)
    # exactly ±π behind the camera, on the side of across's sign
    behind = (across == 0) & (depth < 0)
    np.testing.assert_array_equal(longitude[behind],
                                  np.copysign(dtype(np.pi), across[behind]))


def test_pose_is_computed_once_per_camera_and_angle_and_cannot_be_changed() -> None:
    cam = cameras()[1]
    x, y, z = (np.ascontiguousarray(c) for c in room_points(1000).T)
    first = camera_columns(x, y, z, cam, 30.0)
    r32, t32 = _pose_as(cam, 30.0, "f")
    assert _pose_as(cam, 30.0, "f") is _pose_as(cam, 30.0, "f")
    with pytest.raises(ValueError, match="read-only"):
        r32[0, 0] = 2.0
    rotation, translation = camera_pose_in_rig(cam, 30.0)
    np.testing.assert_array_equal(r32, rotation.astype(np.float32))
    np.testing.assert_array_equal(t32, translation.astype(np.float32))
    # another angle, another camera: another pose
    assert not np.array_equal(camera_columns(x, y, z, cam, 31.0)[2], first[2])
    moved = cam.model_copy(update={"pose": Pose(translation_m=(0.5, 0.3, -0.05),
                                                rotation_deg=cam.pose.rotation_deg)})
    assert not np.array_equal(camera_columns(x, y, z, moved, 30.0)[0], first[0])


def test_360_distance_is_the_float64_distance() -> None:
    pano = cameras()[2]
    points = room_points(20_000)
    x, y, z = (np.ascontiguousarray(c) for c in points.T)
    _, _, distance = project_columns(x, y, z, pano, 47.0)
    _, translation = camera_pose_in_rig(pano, 47.0)
    expected = np.linalg.norm(points.astype(np.float64) - translation, axis=1)
    np.testing.assert_allclose(distance, expected, rtol=1e-6)
    # bit for bit the sum the texture stage's results were made with
    across, down, depth = camera_columns(x, y, z, pano, 47.0)
    np.testing.assert_array_equal(distance,
                                  np.sqrt(across * across + down * down + depth * depth))
