"""Colouring the cloud from the camera frames: the windowed, chunked colouring gives exactly
the colours of projecting every point into every chosen frame (rendered frames of an analytic
room, real JPEGs)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from texture_scene import Caster, Recording, record, small_rig

from scanpipe.rig import Pose, Rig, default_rig
from scanpipe.texturing.frames import choose_frames
from scanpipe.texturing.projective import (
    EQUIRECT_SPACING_DEG,
    _turned_360_frames,
    centrality,
    colorize_points,
    project_valid,
    resolution_weights,
)


def reference_colours(points: pa.Table, recording: Recording, rig: Rig,
                      spacing_deg: float = 5.0, cell_px: int = 6) -> np.ndarray:
    """The slow, obvious colouring: every point into every chosen frame, one z-buffer over
    the whole cloud per frame, the best centrality × resolution wins."""
    xyz = np.stack([points.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
    chosen = choose_frames(recording.frames, recording.motor, rig, spacing_deg,
                           equirect_spacing_deg=max(spacing_deg, EQUIRECT_SPACING_DEG))
    resolution = resolution_weights(chosen.cameras)
    best = np.zeros(len(xyz))
    rgb = np.full((len(xyz), 3), 128, np.uint8)
    for i, cam in enumerate(chosen.cameras):
        uv, depth, valid = project_valid(xyz, cam, float(chosen.beta_deg[i]), 0.0)
        image = chosen.image(i)
        nearest: dict[int, float] = {}
        pixels = {}
        for k in np.flatnonzero(valid):
            col = int(np.clip(np.rint(uv[k, 0]), 0, cam.width - 1))
            row = int(np.clip(np.rint(uv[k, 1]), 0, cam.height - 1))
            cell = (row // cell_px) * (cam.width // cell_px + 1) + col // cell_px
            nearest[cell] = min(nearest.get(cell, np.inf), depth[k])
            pixels[k] = (row, col, cell)
        for k, (row, col, cell) in pixels.items():
            if depth[k] > nearest[cell] + 0.03 + 0.01 * depth[k]:
                continue
            score = centrality(uv[k:k + 1], cam)[0] * resolution[i]
            if score > best[k]:
                best[k] = score
                rgb[k] = image[row, col, ::-1]
    return rgb


@pytest.fixture(scope="module")
def caster() -> Caster:
    return Caster()


def room_points(count: int, seed: int) -> pa.Table:
    """Points on the room's walls, floor and ceiling all round the rig, and some near the
    motor axis (inside every window), as float32 like a points artifact."""
    rng = np.random.default_rng(seed)
    side = rng.integers(0, 4, count)
    along = rng.uniform(-2.4, 2.4, count)
    height = rng.uniform(-1.1, 1.1, count)
    wall = np.where(side[:, None] == 0, np.stack([along, height, np.full(count, 1.999)], 1),
                    np.where(side[:, None] == 1,
                             np.stack([along, height, np.full(count, -1.999)], 1),
                             np.where(side[:, None] == 2,
                                      np.stack([np.full(count, 2.499), height, along], 1),
                                      np.stack([np.full(count, -2.499), height, along], 1))))
    near = np.stack([rng.uniform(-0.2, 0.2, 60), rng.uniform(-1.19, -0.9, 60),
                     rng.uniform(-0.2, 0.2, 60)], 1)
    xyz = np.concatenate([wall, near]).astype(np.float32)
    return pa.table({c: pa.array(xyz[:, k]) for k, c in enumerate("xyz")})


@pytest.mark.parametrize("offset_m", [0.0, 0.3])
def test_windowed_colouring_equals_projecting_every_point(caster: Caster,
                                                          offset_m: float) -> None:
    # offset_m moves the cameras off the motor axis (sideways and back): the windows must
    # then widen by the parallax, or points at the window's edges lose their colour
    rig = small_rig()
    cams = tuple(c.model_copy(update={"pose": c.pose.model_copy(update={
        "translation_m": (offset_m, c.pose.translation_m[1], -offset_m / 2)})})
        for c in rig.cameras)
    rig = rig.model_copy(update={"cameras": cams})
    recording = record(rig, beta_step_deg=40.0, travel_deg=80.0, caster=caster)
    points = room_points(1500, seed=11)
    coloured = colorize_points(points, recording.frames, recording.motor, rig)
    got = np.stack([coloured.column(c).to_numpy() for c in ("red", "green", "blue")], 1)
    expected = reference_colours(points, recording, rig)
    assert (expected != 128).any(axis=1).mean() > 0.3  # many points are seen and coloured
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("pose", [Pose(translation_m=(0.0, 0.4, 0.0)),
                                  Pose(translation_m=(0.05, 0.4, -0.02),
                                       rotation_deg=(3.0, 10.0, -2.0))],
                         ids=["upright-on-axis", "tilted-off-axis"])
def test_colouring_with_a_360_camera_equals_projecting_every_point(caster: Caster,
                                                                   pose: Pose) -> None:
    # a 360° camera beside a phone: its frames see every point at one score (its resolution),
    # and colour where the phone's frames score lower or do not reach (floor, ceiling). On
    # the axis and upright its frames are the first one turned (projected once); else each
    # frame is projected
    phone = small_rig().cameras[0]
    pano = default_rig().cameras[2].model_copy(update={"width": 360, "height": 180,
                                                       "pose": pose})
    rig = small_rig().model_copy(update={"cameras": (phone, pano)})
    recording = record(rig, beta_step_deg=20.0, travel_deg=80.0, caster=caster)
    chosen = choose_frames(recording.frames, recording.motor, rig, 20.0,
                           equirect_spacing_deg=20.0)
    turned = _turned_360_frames(chosen.cameras, chosen.beta_deg)
    pano_frames = [i for i, c in enumerate(chosen.cameras) if c.model == "equirect"]
    assert len(pano_frames) == 5
    assert sorted(turned) == (pano_frames if pose.rotation_deg == (0.0, 0.0, 0.0) else [])
    points = room_points(1500, seed=5)
    coloured = colorize_points(points, recording.frames, recording.motor, rig, spacing_deg=20.0)
    got = np.stack([coloured.column(c).to_numpy() for c in ("red", "green", "blue")], 1)
    expected = reference_colours(points, recording, rig, spacing_deg=20.0)
    assert (expected != 128).any(axis=1).mean() > 0.8  # the 360° camera sees nearly all
    np.testing.assert_array_equal(got, expected)


def test_turned_360_frames_are_only_an_upright_camera_on_the_axis() -> None:
    pano = default_rig().cameras[2]
    beta = np.array([0.0, 20.0, 40.0, 200.0])
    turned = _turned_360_frames([pano] * 4, beta)
    assert sorted(turned) == [0, 1, 2, 3] and {ref for ref, _ in turned.values()} == {0}
    # the shift is the turn in columns, within half a width
    assert [round(turned[i][1], 6) for i in range(4)] == [
        0.0, round(-20 / 360 * pano.width, 6), round(-40 / 360 * pano.width, 6),
        round(160 / 360 * pano.width, 6)]
    for pose in (Pose(translation_m=(0.01, 0.4, 0.0)), Pose(rotation_deg=(0.5, 0.0, 0.0)),
                 Pose(rotation_deg=(0.0, 0.0, 0.5))):
        assert _turned_360_frames([pano.model_copy(update={"pose": pose})] * 4, beta) == {}
    assert _turned_360_frames([pano.model_copy(update={"pose": Pose(
        rotation_deg=(0.0, 30.0, 0.0))})] * 4, beta).keys() == {0, 1, 2, 3}
    # pinhole frames are never turned
    assert _turned_360_frames([default_rig().cameras[0]] * 4, beta) == {}
