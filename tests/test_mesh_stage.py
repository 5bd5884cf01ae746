"""The mesh stage and ``scanpipe mesh``: artifacts, provenance, parameters, failures."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.artifacts import read_artifact, write_artifact
from scanpipe.errors import StageError
from scanpipe.meshing.mesh import Mesh
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.pipeline import get_stage, registry
from scanpipe.schema import MESH_FACES, MESH_VERTICES
from scanpipe.stages.mesh import MeshParams, mesh_points

ROOM = BoxRoom()


def small_scan(**kwargs: object) -> pa.Table:
    return scan_table(ROOM, alpha_step_deg=3.0, beta_step_deg=6.0, noise_m=0.002, **kwargs)


def write_points(folder: Path, table: pa.Table) -> Path:
    path = folder / "points.parquet"
    write_artifact(path, table, {"key": "points-test", "stage": "test"})
    return path


def test_mesh_is_registered_after_filter() -> None:
    names = list(registry())
    assert names.index("mesh") == names.index("filter") + 1
    stage = get_stage("mesh")
    assert stage.inputs == ("points",)
    assert stage.outputs == ("mesh_vertices", "mesh_faces")


def test_grid_stage_in_memory_keeps_colours_and_reports() -> None:
    table = small_scan()
    n = table.num_rows
    for name, value in (("red", 10), ("green", 20), ("blue", 30)):
        table = table.append_column(name, pa.array(np.full(n, value, np.uint8)))
    result = get_stage("mesh").run({"points": table}, method="grid")
    vertices, faces = result.tables["mesh_vertices"], result.tables["mesh_faces"]
    MESH_VERTICES.check(vertices)
    assert vertices.schema.field("green").type == pa.uint8()
    assert vertices.column("green").to_numpy().tolist() == [20] * vertices.num_rows
    MESH_FACES.check(faces)
    report = result.report
    assert report["faces"] == faces.num_rows and report["vertices"] == vertices.num_rows
    assert report["triangulation"]["seam_closed"] is True
    assert {"normals", "surface", "cleanup"} <= set(report["seconds"])
    assert set(report["cpu_seconds"]) == set(report["seconds"])
    assert report["cleanup"]["faces_out"] == faces.num_rows
    normals = np.stack([vertices.column(c).to_numpy() for c in ("nx", "ny", "nz")], axis=1)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)


def test_rows_marked_by_the_filter_are_not_meshed() -> None:
    table = small_scan()
    marks = np.full(table.num_rows, None, dtype=object)
    marks[::7] = "grid_median"
    marked = table.append_column("filtered_by", pa.array(marks, pa.string()))
    mesh, report = mesh_points(marked, MeshParams(method="grid"))
    assert report["points"] == table.num_rows - len(marks[::7])
    xyz = np.stack([marked.column(c).to_numpy() for c in "xyz"], axis=1)
    marked_points = {tuple(p) for p in xyz[::7].tolist()}
    assert not marked_points & {tuple(v) for v in mesh.vertices.tolist()}


def test_decimation_through_the_stage_recomputes_normals() -> None:
    mesh, report = mesh_points(small_scan(), MeshParams.model_validate(
        {"method": "grid", "cleanup": {"target_faces": 500}}))
    assert len(mesh.faces) <= 500
    assert report["cleanup"]["faces_removed_by_decimation"] > 0
    assert mesh.normals is not None
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-4)


def test_grid_method_needs_a_grid() -> None:
    table = small_scan()
    minus_one = pa.array(np.full(table.num_rows, -1, np.int32))
    table = table.set_column(table.schema.get_field_index("profile"), "profile", minus_one)
    with pytest.raises(StageError, match="--method poisson"):
        mesh_points(table, MeshParams(method="grid"))


def test_missing_columns_are_named() -> None:
    from scanpipe.errors import ArtifactError

    with pytest.raises(ArtifactError, match="origin_x"):
        mesh_points(small_scan().drop_columns(["origin_x"]), MeshParams(method="grid"))


def test_cli_writes_the_mesh_artifacts_with_provenance(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    write_points(tmp_path / "in", small_scan())
    result = cli("mesh", tmp_path / "in", "--method", "grid", "--out", tmp_path / "out",
                 "--set", "grid.jump_allowance_m=0.05", "-q")
    assert result.code == 0, result.err  # type: ignore[attr-defined]
    faces, provenance = read_artifact(tmp_path / "out" / "mesh_faces.parquet", MESH_FACES)
    vertices, _ = read_artifact(tmp_path / "out" / "mesh_vertices.parquet", MESH_VERTICES)
    assert provenance["stage"] == "mesh"
    assert provenance["params"]["method"] == "grid"
    assert provenance["params"]["grid"]["jump_allowance_m"] == 0.05
    assert provenance["report"]["faces"] == faces.num_rows
    assert int(pa.compute.max(faces.column("v0")).as_py()) < vertices.num_rows
    assert '"faces"' in result.out  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--method", "marching"], 2, "method"),
        (["--method", "grid", "--set", "grid.max_incidence_deg=95"], 2, "max_incidence_deg"),
        (["--set", "poisson.depht=8"], 2, "did you mean depth"),
    ],
)
def test_cli_rejects_bad_parameters_in_one_line(
        tmp_path: Path, cli: Callable[..., object], args: list[str], code: int,
        message: str) -> None:
    write_points(tmp_path / "in", small_scan())
    result = cli("mesh", tmp_path / "in", "--out", tmp_path / "out", *args)
    assert result.code == code  # type: ignore[attr-defined]
    assert message in result.err and "Traceback" not in result.err  # type: ignore[attr-defined]
    assert not (tmp_path / "out" / "mesh_faces.parquet").exists()


def test_cli_without_points_is_a_usage_error(tmp_path: Path,
                                             cli: Callable[..., object]) -> None:
    (tmp_path / "empty").mkdir()
    result = cli("mesh", tmp_path / "empty", "--out", tmp_path / "out")
    assert result.code == 2  # type: ignore[attr-defined]
    assert "no points artifact" in result.err  # type: ignore[attr-defined]


def test_cli_grid_on_a_cloud_without_grid_fails_cleanly(
        tmp_path: Path, cli: Callable[..., object]) -> None:
    table = small_scan()
    for column in ("profile", "sample"):
        table = table.set_column(table.schema.get_field_index(column), column,
                                 pa.array(np.full(table.num_rows, -1, np.int32)))
    write_points(tmp_path / "in", table)
    result = cli("mesh", tmp_path / "in", "--method", "grid", "--out", tmp_path / "out")
    assert result.code == 1  # type: ignore[attr-defined]
    assert "needs the scan grid" in result.err  # type: ignore[attr-defined]
    assert result.err.count("\n") == 1  # type: ignore[attr-defined]


def test_the_mesh_does_not_depend_on_the_row_order() -> None:
    """Rows in any order (a gather into the grid) give the same triangles and normals (up to
    the rounding of the pole centres, a mean summed in another order)."""
    table = small_scan()
    order = np.random.default_rng(4).permutation(table.num_rows)
    mesh, report = mesh_points(table, MeshParams(method="grid"))
    shuffled, shuffled_report = mesh_points(table.take(pa.array(order)), MeshParams(method="grid"))

    def triangles(m: Mesh) -> set[tuple[float, ...]]:
        corners = np.round(m.vertices[m.faces].reshape(len(m.faces), 9), 5) + 0.0
        return {tuple(row) for row in corners.tolist()}

    assert len(shuffled.faces) == len(mesh.faces) and triangles(shuffled) == triangles(mesh)
    assert report["cleanup"] == shuffled_report["cleanup"]
    assert mesh.normals is not None and shuffled.normals is not None
    by_position = {tuple(v): n for v, n in zip((np.round(mesh.vertices, 5) + 0.0).tolist(),
                                               mesh.normals, strict=True)}
    # A merged pole keeps the normal of its first point in table order: skip the two poles.
    for v, n in zip((np.round(shuffled.vertices, 5) + 0.0).tolist(), shuffled.normals,
                    strict=True):
        if abs(v[0]) + abs(v[2]) > 1e-4:
            assert np.allclose(by_position[tuple(v)], n, atol=1e-5)


def test_the_grid_clean_up_follows_the_clean_up_switches() -> None:
    """Zero-area faces (coinciding pole points of a noise-free scan, poles not merged) go
    only while ``cleanup.remove_degenerate`` says so; the report counts them as degenerate."""
    table = scan_table(ROOM, 3.0, 6.0)
    params = {"method": "grid", "grid": {"merge_poles": False}}
    mesh, report = mesh_points(table, MeshParams.model_validate(params))
    removed = report["cleanup"]["degenerate_faces_removed"]
    assert removed > 0
    kept, kept_report = mesh_points(table, MeshParams.model_validate(
        {**params, "cleanup": {"remove_degenerate": False, "min_component_faces": 0}}))
    assert "degenerate_faces_removed" not in kept_report["cleanup"]
    assert "small_component_faces_removed" not in kept_report["cleanup"]
    assert len(kept.faces) == len(mesh.faces) + removed
