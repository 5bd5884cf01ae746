"""``scanpipe export``: folders (flat and per stage), bad arguments, unwritable paths, no half
files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import trimesh
from result_tables import points_table, textured_box, textured_quad

from scanpipe.artifacts import write_artifact
from scanpipe.exporting import write_files


def write_tables(folder: Path, tables: dict[str, pa.Table], stage: str = "test",
                 seconds: float = 0.5) -> None:
    for name, table in tables.items():
        write_artifact(folder / f"{name}.parquet", table,
                       {"stage": stage, "key": f"{stage}-key", "seconds": seconds,
                        "rows": table.num_rows, "report": {}})


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A pipeline-style workdir: W/<stage>/<artifact>.parquet."""
    root = tmp_path / "work"
    quad = textured_quad()
    write_tables(root / "assemble", {"points": points_table(seed=1)}, "assemble")
    write_tables(root / "filter", {"points": points_table(profiles=3, seed=2)}, "filter")
    write_tables(root / "mesh", {k: quad[k] for k in ("mesh_vertices", "mesh_faces")}, "mesh")
    write_tables(root / "texture", {k: quad[k] for k in ("textured_faces", "texture_pages")},
                 "texture")
    return root


def test_every_format_from_a_workdir(cli: Callable, workdir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    for fmt in ("obj", "glb", "ply", "las", "laz", "e57", "mcap"):
        result = cli("export", workdir, "--format", fmt, "--out", out / f"room.{fmt}")
        assert result.code == 0, result.err
        assert (out / f"room.{fmt}").stat().st_size > 0
    assert (out / "room_page0.png").is_file() and (out / "room.mtl").is_file()
    # ply took the mesh (a mesh is there); the LAS took the filter stage's points (3 profiles)
    assert len(trimesh.load(out / "room.ply", process=False).faces) == 2
    import laspy

    assert laspy.read(out / "room.las").header.point_count == 3 * 10


def test_flat_folder_and_output_folder(cli: Callable, tmp_path: Path) -> None:
    flat = tmp_path / "flat"
    write_tables(flat, textured_box())
    out = tmp_path / "exports"
    out.mkdir()
    result = cli("export", flat, "-f", "obj", "-o", out)
    assert result.code == 0, result.err
    assert sorted(p.name for p in out.iterdir()) == ["scan.mtl", "scan.obj", "scan_page0.png",
                                                     "scan_page1.png", "scan_untextured.png"]


def test_bad_format_is_a_usage_error(cli: Callable, workdir: Path, tmp_path: Path) -> None:
    result = cli("export", workdir, "--format", "fbx", "--out", tmp_path / "x.fbx")
    assert result.code == 2
    assert "unknown format" in result.err and "obj, glb, ply" in result.err
    assert "Traceback" not in result.err
    assert not (tmp_path / "x.fbx").exists()


def test_extension_must_match_the_format(cli: Callable, workdir: Path, tmp_path: Path) -> None:
    result = cli("export", workdir, "--format", "glb", "--out", tmp_path / "x.obj")
    assert result.code == 2 and "does not match --format glb" in result.err
    assert list(tmp_path.glob("x.*")) == []


def test_missing_artifacts_are_named(cli: Callable, tmp_path: Path) -> None:
    only_points = tmp_path / "pts"
    write_tables(only_points, {"points": points_table()})
    result = cli("export", only_points, "--format", "obj", "--out", tmp_path / "m.obj")
    assert result.code == 1
    assert "obj export needs a mesh" in result.err and "mesh_vertices" in result.err
    empty = tmp_path / "empty"
    empty.mkdir()
    result = cli("export", empty, "--format", "las", "--out", tmp_path / "p.las")
    assert result.code == 1 and "no artifacts to export" in result.err
    assert not (tmp_path / "m.obj").exists() and not (tmp_path / "p.las").exists()


def test_unwritable_path_gives_one_line_and_no_file(cli: Callable, workdir: Path,
                                                   tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where a folder should be")
    result = cli("export", workdir, "--format", "glb", "--out", blocker / "sub" / "m.glb")
    assert result.code == 2
    assert result.err.startswith("scanpipe: error: ") and result.err.count("\n") == 1
    assert f"{blocker} is a file, not a folder" in result.err
    assert blocker.read_text() == "a file where a folder should be"


def test_failure_midway_leaves_no_partial_export_and_keeps_old_files(
        cli: Callable, workdir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert cli("export", workdir, "-f", "obj", "-o", out / "room.obj").code == 0
    old = (out / "room.obj").read_bytes()
    (out / "room_page0.png").unlink()
    (out / "room_page0.png").mkdir()  # the second export cannot put its texture here
    (out / "room.obj").write_bytes(b"previous export")
    result = cli("export", workdir, "-f", "obj", "-o", out / "room.obj")
    assert result.code == 2 and "already exists; pass --force" in result.err
    result = cli("export", workdir, "-f", "obj", "-o", out / "room.obj", "--force")
    assert result.code == 2 and "room_page0.png: is a folder" in result.err
    assert (out / "room.obj").read_bytes() == b"previous export"
    assert sorted(p.name for p in out.iterdir()) == ["room.mtl", "room.obj", "room_page0.png"]
    assert old.startswith(b"# scanpipe")


def test_write_files_leaves_no_temporary_files_on_error(tmp_path: Path) -> None:
    from scanpipe.errors import ExportError

    (tmp_path / "b.bin").mkdir()
    with pytest.raises(ExportError):
        write_files({"a.bin": b"1", "b.bin": b"2"}, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin"]


def test_bad_format_in_the_library_is_an_export_error() -> None:
    from scanpipe.errors import ExportError
    from scanpipe.stages.export import export_files

    with pytest.raises(ExportError, match="unknown format"):
        export_files(textured_quad(), "stl", "x")


def test_broken_texture_reference_is_reported(tmp_path: Path) -> None:
    from scanpipe.errors import ArtifactError
    from scanpipe.stages.export import export_files

    tables = textured_quad()
    tables["texture_pages"] = tables["texture_pages"].set_column(
        0, "page", pa.array([5], pa.int16()))
    with pytest.raises(ArtifactError, match=r"pages \[0\] are not in texture_pages"):
        export_files(tables, "obj", "x")


def test_exports_get_ordinary_file_permissions(tmp_path: Path) -> None:
    import os

    from scanpipe.artifacts import FILE_MODE, atomic_write_bytes

    umask = os.umask(0o022)
    os.umask(umask)
    assert 0o666 & ~umask == FILE_MODE
    (path,) = write_files({"a.bin": b"1"}, tmp_path)
    assert path.stat().st_mode & 0o777 == FILE_MODE  # not mkstemp's 0o600
    atomic_write_bytes(tmp_path / "b.bin", b"2")
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == FILE_MODE


def test_non_finite_vertices_are_refused_for_obj(cli: Callable, tmp_path: Path) -> None:
    quad = textured_quad()
    x = quad["mesh_vertices"].column("x").to_numpy().copy()
    x[1] = np.nan
    folder = tmp_path / "nan"
    write_tables(folder, {**quad, "mesh_vertices": quad["mesh_vertices"].set_column(
        quad["mesh_vertices"].column_names.index("x"), "x", pa.array(x, pa.float32()))})
    out = tmp_path / "out"
    out.mkdir()
    (out / "m.obj").write_bytes(b"an earlier export")
    result = cli("export", folder, "-f", "obj", "-o", out / "m.obj", "--force")
    assert result.code == 1 and result.err.count("\n") == 1 and "Traceback" not in result.err
    assert ("mesh_vertices: 1 vertices have non-finite coordinates (first: vertex 1)"
            in result.err)
    assert (out / "m.obj").read_bytes() == b"an earlier export"
    assert sorted(p.name for p in out.iterdir()) == ["m.obj"]
