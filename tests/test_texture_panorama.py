"""The paper's panorama method (eq. 17–21) on the analytic box room."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pyarrow as pa
import pytest
from test_texture_projective import assert_seen, colour_errors
from texture_scene import Caster, Recording, mesh_tables, record, room_mesh, small_rig

from scanpipe.rig import CameraConfig, default_rig
from scanpipe.stages.texture import STAGE
from scanpipe.texturing.panorama import (
    cylinder_coordinates,
    platform_speed_deg_s,
    selection_interval_frames,
    visible_width_m,
)


def test_equations_17_to_21_golden_values() -> None:
    hfov = CameraConfig().hfov_deg  # LG G3 in Full HD, landscape as in the paper: about 65°
    assert hfov == pytest.approx(65.0, abs=0.05)
    # eq. 18: pr = r / cos(α/2); eq. 17: iw = 2 sin(α/2) pr
    r = 3.0
    prone = r / math.cos(math.radians(hfov / 2))
    assert visible_width_m(r, hfov) == pytest.approx(2 * math.sin(math.radians(hfov / 2)) * prone)
    assert visible_width_m(r, 65.0) == pytest.approx(3.8224, abs=1e-3)
    assert visible_width_m(2.0, 90.0) == pytest.approx(4.0)
    # eq. 20–21: the platform at 1000 pulses/s × 0.036° = 36°/s moves a wall 3 m away at ωr
    v = math.radians(36.0) * r
    assert selection_interval_frames(visible_width_m(r, 65.0), 30.0, v) == pytest.approx(
        60.84, abs=0.05)
    # r cancels: f_si = 2 tan(α/2) fps / ω, whatever the distance
    assert selection_interval_frames(visible_width_m(7.0, 65.0), 30.0,
                                     math.radians(36.0) * 7.0) == pytest.approx(60.84, abs=0.05)
    assert selection_interval_frames(1.0, 30.0, 0.0) == math.inf


def test_platform_speed_from_motor_states() -> None:
    rig = default_rig()
    t = np.array([0, 1, 2, 3, 4], dtype=np.int64) * 1_000_000_000
    steps = np.array([0, 1000, 2000, 2000, 3000])  # 36°/s with a pause
    table = pa.table({"log_time_ns": t, "step_count": steps})
    assert platform_speed_deg_s(table, rig.motor) == pytest.approx(36.0)


def test_cylinder_coordinates() -> None:
    theta, h, rho = cylinder_coordinates(np.array([[0.0, 1.0, 2.0], [2.0, 0.0, 0.0]]),
                                         np.array([0.0, 0.0, 0.0]))
    np.testing.assert_allclose(theta, [0.0, -90.0])  # +x is on the left looking along +z
    np.testing.assert_allclose(h, [0.5, 0.0])
    np.testing.assert_allclose(rho, [2.0, 2.0])


@pytest.fixture(scope="module")
def caster() -> Caster:
    return Caster()


@pytest.fixture(scope="module")
def recording(caster: Caster) -> Recording:
    return record(small_rig(), beta_step_deg=4.0, caster=caster)


def test_panorama_texture_matches_truth(recording: Recording, caster: Caster) -> None:
    vertices, faces, normals = room_mesh(0.25)
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run(recording.inputs(vt, ft), method="panorama")
    report = result.report
    assert report["method"] == "panorama"
    assert 0.2 < report["coverage"] < 0.6
    assert report["occluded_faces"] > 0  # the pillar hides a part of the wall behind it
    # frames every 4° at 10°/s: 2.5 fps (the rig says 30; the recording decides), 4° strips
    assert report["fps"] == pytest.approx(2.5)
    assert report["strip_deg"] == pytest.approx(4.0)
    assert report["f_si_frames"] == pytest.approx(
        selection_interval_frames(report["visible_width_m"], 2.5, report["camera_speed_m_s"]),
        rel=1e-3)
    panorama = cv2.imdecode(np.frombuffer(result.files["panorama.png"], np.uint8), 1)
    assert list(panorama.shape[1::-1]) == report["panorama_px"]
    pages = result.tables["texture_pages"]
    assert pages.num_rows == 1 and pages.column("width")[0].as_py() <= 8192
    errors = colour_errors(result.tables, vertices, faces)
    assert errors.mean() < 6.0 and np.percentile(errors, 95) < 16.0
    assert_seen(result.tables["textured_faces"], vertices, faces, recording, caster)


def test_panorama_strip_parameter_and_resolution(recording: Recording) -> None:
    vertices, faces, normals = room_mesh(0.5)
    vt, ft = mesh_tables(vertices, faces, normals)
    result = STAGE.run(recording.inputs(vt, ft), method="panorama", panorama_strip_deg=6.0,
                       panorama_px_per_deg=2.0, exposure=False)
    assert result.report["strip_deg"] == 6.0
    assert result.report["frames_considered"] == pytest.approx(2 * 180 / 6 + 2, abs=2)
    assert 720 <= result.report["panorama_px"][0] <= 2 * (360 + 31)
