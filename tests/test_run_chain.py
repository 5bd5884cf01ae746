"""``scanpipe run`` / ``show`` / ``stages`` / ``demo`` on the real stages and a simulated scan."""

from __future__ import annotations

import json
from pathlib import Path

import open3d as o3d
import pytest
import trimesh

from scanpipe.artifacts import read_provenance
from scanpipe.demo import DemoOptions, run_demo
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.stages.decode import STAGE as DECODE_STAGE

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    path = root / "scan.mcap"
    simulate_direct(path, root / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=3.0, camera_scale=0.125, camera_fps=0.5, seed=4))
    return path


def _ran(err: str) -> list[str]:
    return [line.split()[0] for line in err.splitlines() if " ran in " in line]


def _reused(err: str) -> list[str]:
    return [line.split()[0] for line in err.splitlines() if " reused " in line]


def test_caching_rules_on_the_real_chain(cli, recording: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "w"
    grid = ("--set", "mesh.method=grid")
    first = cli("run", recording, "--workdir", work, *grid)
    assert first.code == 0, first.err
    assert _ran(first.err) == ["decode", "calibrate", "assemble", "filter", "mesh", "texture",
                               "export"]
    assert (work / "export" / "model.obj").is_file() and (work / "export" / "model.glb").is_file()

    again = cli("run", recording, "--workdir", work, *grid)
    assert again.code == 0 and _ran(again.err) == []
    assert len(_reused(again.err)) == 7

    changed = cli("run", recording, "--workdir", work, *grid,
                  "--set", "filter.grid_median.max_deviation_m=0.05")
    assert changed.code == 0
    assert _reused(changed.err)[:3] == ["decode", "calibrate", "assemble"]
    assert _ran(changed.err)[0] == "filter"
    provenance = read_provenance(work / "filter" / "points.parquet")
    assert provenance["params"]["grid_median"]["max_deviation_m"] == 0.05

    partial = cli("run", recording, "--workdir", tmp_path / "w2", "--to", "assemble")
    assert _ran(partial.err) == ["decode", "calibrate", "assemble"]
    assert not (tmp_path / "w2" / "filter").exists()


def test_show_and_stages(cli, recording: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "w"
    assert cli("run", recording, "--workdir", work, "--to", "assemble").code == 0
    shown = cli("show", work / "assemble" / "points.parquet", "--json")
    assert shown.code == 0
    info = json.loads(shown.out)
    assert info["stage"] == "assemble" and info["rows"] > 0
    assert set(info["inputs"]) == {"profiles", "motor", "rig"}
    text = cli("show", work / "decode" / "profiles.parquet")
    assert f"stage      decode v{DECODE_STAGE.version}" in text.out
    listed = cli("stages")
    for name in ("decode", "assemble", "filter", "mesh", "texture", "export"):
        assert f"{name} (v" in listed.out
    assert "filter.voxel.size_m" in listed.out


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (("--set", "filtr.voxel.size_m=0.01"), "unknown stage 'filtr' (did you mean filter?"),
        (("--set", "filter.voxel.sise_m=0.01"), "did you mean size_m"),
        (("--set", "filter.voxel.size_m=-1"), "filter.voxel.size_m = -1"),
        (("--to", "mush"), "--to 'mush': not a stage"),
    ],
)
def test_bad_parameters_are_one_clear_error(cli, recording: Path, tmp_path: Path,  # type: ignore[no-untyped-def]
                                            args: tuple[str, ...], needle: str) -> None:
    result = cli("run", recording, "--workdir", tmp_path / "w", *args)
    assert result.code == 2
    assert needle in result.err and "Traceback" not in result.err
    assert not (tmp_path / "w").exists()  # nothing written before the parameters are valid


def test_wrong_inputs(cli, recording: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    missing = cli("run", tmp_path / "nope.mcap", "--workdir", tmp_path / "w")
    assert missing.code != 0 and "nope.mcap" in missing.err and "Traceback" not in missing.err
    not_mcap = tmp_path / "not.mcap"
    not_mcap.write_bytes(b"this is not a recording")
    bad = cli("run", not_mcap, "--workdir", tmp_path / "w")
    assert bad.code != 0 and "not.mcap" in bad.err and "Traceback" not in bad.err
    not_artifact = cli("show", recording)
    assert not_artifact.code != 0 and "Traceback" not in not_artifact.err


def test_schema_mismatch_is_named(cli, recording: Path, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "w"
    assert cli("run", recording, "--workdir", work, "--to", "decode").code == 0
    # The motor artifact where profiles are expected: assemble must say what is wrong.
    fake = tmp_path / "fake"
    fake.mkdir()
    for name in ("profiles", "motor", "rig"):
        source = "motor" if name == "profiles" else name
        (fake / f"{name}.parquet").write_bytes((work / "decode" / f"{source}.parquet").read_bytes())
    result = cli("assemble", fake, "--out", tmp_path / "out")
    assert result.code != 0
    assert "profiles" in result.err and "Traceback" not in result.err
    assert not (tmp_path / "out" / "points.parquet").exists()


def test_demo_outputs_open_in_trimesh_and_open3d(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    result = run_demo(out, DemoOptions(beam_step_deg=2.0, motor_step_deg=2.0, camera_fps=0.2,
                                       camera_scale=0.25))
    for name in ("model.obj", "model.mtl", "model.glb", "cloud.ply", "cloud.las", "report.html",
                 "eval.json", "previews/plan.png"):
        assert (out / name).is_file(), name
    loaded = trimesh.load(out / "model.obj", force="mesh")
    assert len(loaded.faces) > 1000
    glb = trimesh.load(out / "model.glb", force="mesh")
    assert len(glb.faces) == len(loaded.faces)
    mesh = o3d.io.read_triangle_mesh(str(out / "model.obj"), True)
    assert len(mesh.triangles) == len(loaded.faces) and mesh.has_textures()
    cloud = o3d.io.read_point_cloud(str(out / "cloud.ply"))
    assert len(cloud.points) > 1000
    assert result.evaluation["points_rms_m"] < 0.02
