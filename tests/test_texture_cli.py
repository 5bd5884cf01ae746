"""``scanpipe texture`` end to end on Parquet artifacts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from texture_scene import Recording, mesh_tables, record, room_mesh, small_rig

from scanpipe.artifacts import read_artifact, read_provenance, write_artifact
from scanpipe.pipeline import registry
from scanpipe.rig import rig_table, rig_to_toml


@pytest.fixture(scope="module")
def recording() -> Recording:
    return record(small_rig(), beta_step_deg=10.0)


@pytest.fixture
def workdir(tmp_path: Path, recording: Recording) -> Path:
    """A pipeline workdir: mesh/ and decode/ hold the inputs."""
    vt, ft = mesh_tables(*room_mesh(0.5))
    for folder, name, table in (("mesh", "mesh_vertices", vt), ("mesh", "mesh_faces", ft),
                                ("decode", "frames", recording.frames),
                                ("decode", "motor", recording.motor),
                                ("decode", "rig", rig_table(recording.rig))):
        write_artifact(tmp_path / "w" / folder / f"{name}.parquet", table,
                       {"key": f"{name}-key", "stage": folder})
    return tmp_path / "w"


def test_texture_is_registered_after_mesh_inputs() -> None:
    stage = registry()["texture"]
    assert stage.inputs == ("mesh_vertices", "mesh_faces", "frames", "motor", "rig")
    assert stage.outputs == ("textured_faces", "texture_pages")


def test_cli_projective_and_panorama(cli, workdir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = cli("texture", workdir, "--out", out, "--json", "-q")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["method"] == "projective" and report["faces_textured"] > 0
    faces, provenance = read_artifact(out / "textured_faces.parquet")
    assert faces.num_rows == report["faces"]
    assert provenance["report"]["coverage"] == report["coverage"]
    assert provenance["inputs"]["frames"] == "frames-key"
    assert (out / "texture_pages.parquet").is_file()
    assert not (out / "panorama.png").exists()

    pano = tmp_path / "pano"
    text = cli("texture", workdir / "mesh", workdir / "decode", "--out", pano,
               "--method", "panorama", "--set", "panorama_strip_deg=5", "-q")
    assert text.code == 0, text.err
    assert text.out.startswith("panorama: ") and "coverage" in text.out
    assert (pano / "panorama.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert read_provenance(pano / "texture_pages.parquet")["params"]["method"] == "panorama"


def test_cli_rig_override(cli, workdir: Path, tmp_path: Path, recording: Recording) -> None:
    rig_path = tmp_path / "rig.toml"
    one_camera = recording.rig.model_copy(update={"cameras": recording.rig.cameras[:1]})
    rig_path.write_text(rig_to_toml(one_camera))
    out = tmp_path / "out"
    result = cli("texture", workdir, "--out", out, "--rig", rig_path, "--json", "-q")
    # the recording has cam1 frames, the override rig does not know cam1: skipped, named
    assert result.code == 0, result.err
    assert "warning: texture: frames: skipped" in result.err
    assert "camera 'cam1': not in the rig" in result.err
    report = json.loads(result.out)
    assert report["faces_textured"] > 0 and "'cam1'" in report["warnings"][0]


def test_cli_errors(cli, workdir: Path, tmp_path: Path) -> None:
    (workdir / "decode" / "motor.parquet").unlink()
    missing = cli("texture", workdir, "--out", tmp_path / "o", "-q")
    assert missing.code == 1 and "texture needs motor (.parquet)" in missing.err
    bad_method = cli("texture", workdir, "--out", tmp_path / "o", "--method", "cubist", "-q")
    assert bad_method.code == 2 and "method" in bad_method.err
    bad_key = cli("texture", workdir, "--out", tmp_path / "o", "--set", "page_size=100", "-q")
    assert bad_key.code == 2 and "page_size_px" in bad_key.err
    not_dir = cli("texture", tmp_path / "nowhere", "--out", tmp_path / "o", "-q")
    assert not_dir.code == 1 and "not a folder" in not_dir.err
    assert "Traceback" not in missing.err + bad_method.err + bad_key.err + not_dir.err
    assert not (tmp_path / "o" / "textured_faces.parquet").exists()
