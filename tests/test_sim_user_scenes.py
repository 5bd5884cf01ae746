"""``simulate`` on user scene files: warnings printed, --scene-pose/--scene-up move the truth,
a scene the scanner cannot see is a one-line error."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanpipe.sim.truth import load_truth

CORNELL = Path(__file__).parent / "fixtures" / "cornell" / "CornellBox-Original.obj"
FAST = ("--direct", "--motor-step", "30", "--beam-step", "2", "--no-cameras", "-q")


def scaled_cornell(folder: Path, factor: float) -> Path:
    """The Cornell box with every vertex times ``factor`` (1000: as if written in mm)."""
    folder.mkdir()
    lines = []
    for line in CORNELL.read_text().splitlines():
        fields = line.split()
        if fields and fields[0] == "v":
            line = "v " + " ".join(str(float(x) * factor) for x in fields[1:4])
        lines.append(line)
    path = folder / "box.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_scene_touching_the_scanner_is_a_one_line_error(cli: Callable[..., Any],
                                                        tmp_path: Path) -> None:
    # The Cornell box as published has its floor at y = 0: the scanner sits in the floor.
    result = cli("simulate", *FAST, "--scene", CORNELL, "--out", tmp_path / "s.mcap",
                 "--truth", tmp_path / "t")
    assert result.code != 0 and result.err.count("\n") == 1
    assert "0.0% of the scanner's rays return (100% hit nearer than its minimum range" in \
        result.err


def test_scene_in_millimetres_is_a_one_line_error(cli: Callable[..., Any],
                                                  tmp_path: Path) -> None:
    scene = scaled_cornell(tmp_path / "mm", 1000.0)
    result = cli("simulate", *FAST, "--scene", scene, "--out", tmp_path / "s.mcap",
                 "--truth", tmp_path / "t")
    assert result.code != 0
    assert result.err.startswith("scanpipe: error: scene ") and result.err.count("\n") == 1
    assert "0.0% of the scanner's rays return" in result.err and "millimetres" in result.err
    assert not (tmp_path / "s.mcap").exists() and not (tmp_path / "t" / "scene.glb").exists()


def test_scene_pose_and_up_move_the_truth(cli: Callable[..., Any], tmp_path: Path) -> None:
    result = cli("simulate", *FAST, "--scene", CORNELL, "--scene-pose", "0.5,-0.25,0,0,90,0",
                 "--out", tmp_path / "s.mcap", "--truth", tmp_path / "t")
    assert result.code == 0, result.err
    assert "warning" not in result.err
    truth = load_truth(tmp_path / "t").scene
    # Rotated 90° about y: x ← z, z ← −x; then moved.
    np.testing.assert_allclose(truth.bounds, [[-1.04 + 0.5, -0.25, -1.0], [0.99 + 0.5, 1.74,
                                                                            1.02]], atol=1e-5)
    result = cli("simulate", *FAST, "--scene", CORNELL, "--scene-up", "z", "--scene-pose",
                 "0,0,-1", "--out",
                 tmp_path / "z.mcap", "--truth", tmp_path / "tz")
    assert result.code == 0, result.err
    np.testing.assert_allclose(load_truth(tmp_path / "tz").scene.bounds[:, 1], [-1.04, 0.99],
                               atol=1e-5)


def test_scene_warnings_are_printed(cli: Callable[..., Any], tmp_path: Path) -> None:
    scene = scaled_cornell(tmp_path / "box", 1.0)
    scene.write_text(scene.read_text() + "f 1 2\nl 1 2 3\n")
    result = cli("simulate", *FAST, "--scene", scene, "--scene-pose", "0,-0.5,0", "--out",
                 tmp_path / "s.mcap", "--truth", tmp_path / "t")
    assert result.code == 0, result.err
    lines = result.err.splitlines()
    assert any(line.startswith("warning: simulate: ") and "material library "
               "'CornellBox-Original.mtl' not found" in line for line in lines)
    assert any("1 faces of fewer than 3 corners dropped" in line for line in lines)
    assert any("1 lines (l) dropped" in line for line in lines)


@pytest.mark.parametrize("pose", ["1,2", "a,b,c", "0,0,0,0,0", "nan,0,0"])
def test_bad_scene_pose_is_a_usage_error(cli: Callable[..., Any], tmp_path: Path,
                                         pose: str) -> None:
    result = cli("simulate", *FAST, "--scene", CORNELL, "--scene-pose", pose,
                 "--out", tmp_path / "s.mcap", "--truth", tmp_path / "t")
    assert result.code == 2
    assert "--scene-pose" in result.err and result.err.count("\n") == 1


def test_run_without_cameras_exports_an_untextured_model(cli: Callable[..., Any],
                                                         tmp_path: Path) -> None:
    import trimesh

    result = cli("simulate", *FAST, "--motor-step", "20", "--out", tmp_path / "s.mcap",
                 "--truth", tmp_path / "t")
    assert result.code == 0, result.err
    result = cli("run", tmp_path / "s.mcap", "--workdir", tmp_path / "w", "-q")
    assert result.code == 0, result.err
    assert ("warning: texture: untextured: the rig has no cameras; the model is exported "
            "without texture") in result.err
    export = tmp_path / "w" / "export"
    assert {p.name for p in export.iterdir()} >= {"model.obj", "model.glb", "cloud.ply"}
    assert "mtllib" not in (export / "model.obj").read_text()
    assert not list(export.glob("*.png")) and not list(export.glob("*.mtl"))
    glb = trimesh.load(export / "model.glb", force="mesh")
    assert len(glb.faces) > 100
