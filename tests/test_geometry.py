"""Frames and transforms: the paper's eq. 14–16 test vectors and the pose conventions."""

from __future__ import annotations

import numpy as np
import pytest

from scanpipe.geometry import (
    camera_to_platform,
    platform_rotation,
    rotation_matrix_deg,
    scan_point_to_rig,
    sensor_origin_in_rig,
)

PAPER_VECTORS = [
    (2.0, 90.0, 0.0, (2.0, 0.0, 0.0)),
    (2.0, 90.0, 90.0, (0.0, 0.0, 2.0)),
    (2.0, 0.0, 37.0, (0.0, 2.0, 0.0)),
    (2.0, 30.0, 45.0, (0.70711, 1.73205, 0.70711)),
    (1.5, 200.0, 120.0, (0.25652, -1.40954, -0.44430)),
]


@pytest.mark.parametrize(("r", "alpha", "beta", "expected"), PAPER_VECTORS)
def test_paper_vectors(r: float, alpha: float, beta: float, expected: tuple[float, ...]) -> None:
    np.testing.assert_allclose(scan_point_to_rig(r, alpha, beta), expected, atol=1e-5)


def test_platform_rotation_is_orthonormal_and_batched() -> None:
    rs = platform_rotation(np.array([0.0, 33.0, 180.0]))
    assert rs.shape == (3, 3, 3)
    for r in rs:
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_rotation_order_is_x_then_y_then_z() -> None:
    r = rotation_matrix_deg((90.0, 90.0, 0.0))
    # x first: +y → +z; then y: +z → +x.
    np.testing.assert_allclose(r @ [0, 1, 0], [1, 0, 0], atol=1e-12)


def test_mount_offset_moves_the_sensor_origin() -> None:
    np.testing.assert_allclose(sensor_origin_in_rig(90.0, (0.1, 0.0, 0.0)), [0, 0, 0.1], atol=1e-12)
    p = scan_point_to_rig(1.0, 90.0, 0.0, mount_translation_m=(0.0, 0.2, 0.0))
    np.testing.assert_allclose(p, [1.0, 0.2, 0.0], atol=1e-12)


def test_camera_base_view_looks_along_z_with_y_up() -> None:
    r = camera_to_platform((0.0, 0.0, 0.0))
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 0, 1], atol=1e-12)  # forward
    np.testing.assert_allclose(r @ [0, -1, 0], [0, 1, 0], atol=1e-12)  # image up = +y
    assert np.linalg.det(r) == pytest.approx(1.0)
