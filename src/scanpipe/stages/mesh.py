"""Mesh: a surface from the points, by Open3D Poisson or by triangulating the scan grid.

``poisson`` works on any cloud: oriented normals (grid or KNN, facing each point's sensor),
screened Poisson, then trims by density and visibility (docs/meshing.md). ``grid`` needs the
scan grid: it connects neighbouring samples of adjacent profiles, breaks at depth
discontinuities, closes the seam and the poles and meshes each direction once; it keeps the
measured points as vertices, so its smoothness is the filter stage's (``smoothing``). Both end
with the same clean-up and an optional quadric decimation. Rows the filter stage only marked
(``filtered_by`` not null) are left out.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.grid import scan_grid, subsample
from scanpipe.meshing.cleanup import CleanupParams, clean_mesh
from scanpipe.meshing.grid_mesh import GridMeshParams, grid_surface
from scanpipe.meshing.mesh import Mesh
from scanpipe.meshing.poisson import PoissonParams, poisson_mesh
from scanpipe.normals import NormalParams, column_f32, estimate_normals
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.schema import ORIGIN, POINTS, RGB, XYZ
from scanpipe.stage import Stage, StageResult


class MeshParams(Params):
    """Parameters of the mesh stage: the method, each method's settings, the clean-up."""

    method: Literal["auto", "poisson", "grid"] = Field(
        "auto", description="surface method; auto: grid when the points keep their scan grid, "
                            "else Poisson")
    normals: NormalParams = Field(default_factory=NormalParams)
    poisson: PoissonParams = Field(default_factory=PoissonParams)
    grid: GridMeshParams = Field(default_factory=GridMeshParams)
    cleanup: CleanupParams = Field(default_factory=CleanupParams)


def usable_points(table: pa.Table) -> pa.Table:
    """The rows to mesh: without the ones a filter marked, and with finite coordinates."""
    if "filtered_by" in table.column_names and table.column("filtered_by").null_count < len(
            table):
        table = table.filter(pc.is_null(table.column("filtered_by")))
    finite = pc.and_(pc.and_(pc.is_finite(table.column("x")), pc.is_finite(table.column("y"))),
                     pc.is_finite(table.column("z")))
    if pc.all(finite).as_py() is not False:
        return table  # nothing to drop: no copy
    return table.filter(finite)


def _colors(table: pa.Table) -> np.ndarray[Any, np.dtype[np.uint8]] | None:
    if not all(name in table.column_names for name in RGB):
        return None
    return np.stack([table.column(name).to_numpy(zero_copy_only=False).astype(np.uint8)
                     for name in RGB], axis=1)


def mesh_points(table: pa.Table, params: MeshParams,
                progress: ProgressFn | None = None) -> tuple[Mesh, dict[str, Any]]:
    """The mesh of a points table and a report (counts, what clean-up removed, times)."""
    POINTS.check(table)
    table = usable_points(table)
    if table.num_rows == 0:
        raise StageError("points: no usable points to mesh (empty, or every row filtered)")
    grid = scan_grid(table)
    method = params.method if params.method != "auto" else ("grid" if grid else "poisson")
    report: dict[str, Any] = {"method": method, "points": table.num_rows}
    seconds: dict[str, float] = {}
    cpu_seconds: dict[str, float] = {}  # beside wall time: not inflated by a loaded machine
    tick, cpu_tick = time.perf_counter(), time.process_time()

    def step(name: str, done: int) -> None:
        nonlocal tick, cpu_tick
        now, cpu_now = time.perf_counter(), time.process_time()
        seconds[name] = round(now - tick, 4)
        cpu_seconds[name] = round(cpu_now - cpu_tick, 4)
        tick, cpu_tick = now, cpu_now
        if progress is not None:
            progress("mesh", done, 4)

    if method == "grid" and grid is None:
        raise StageError("points: method 'grid' needs the scan grid, but these points have "
                         "none (profile/sample are −1); use --method poisson")
    if method == "grid":
        stride = params.grid.stride_for(table.num_rows)
        report["grid_stride"] = stride
        if stride > 1:
            table = subsample(table, stride)
            grid = scan_grid(table)
            report["points_meshed"] = table.num_rows
    # Each column read once (a chunked column is concatenated on every read).
    columns = {name: column_f32(table, name) for name in (*XYZ, *ORIGIN)}
    points = np.stack([columns[name] for name in XYZ], axis=1)
    origins = np.stack([columns[name] for name in ORIGIN], axis=1)
    normals, normal_counts = estimate_normals(table, params.normals, grid, columns)
    del columns
    report["normals"] = normal_counts
    step("normals", 1)

    colors = _colors(table)
    if method == "grid":
        assert grid is not None
        # The grid triangulation cleans itself on the grid (zero-area faces, small pieces,
        # unused points); the generic clean-up then only decimates, if asked.
        surface = grid_surface(points, origins, grid, params.grid,
                               min_component_faces=params.cleanup.min_component_faces,
                               compact=True, remove_zero_area=params.cleanup.remove_degenerate)
        report["triangulation"] = surface.report
        if surface.kept is not None:
            # np.compress: a boolean index of an (N, 3) array is ~4× slower.
            normals = np.compress(surface.kept, normals, axis=0)
            colors = None if colors is None else np.compress(surface.kept, colors, axis=0)
        mesh = Mesh(surface.vertices, surface.faces, normals, colors)
    else:
        steps = (grid.alpha_step_deg, grid.beta_step_deg) if grid is not None else None
        mesh, poisson_report = poisson_mesh(points, normals, origins, colors, params.poisson,
                                            steps)
        report["poisson"] = poisson_report
    step("surface", 2)

    if method == "grid":
        tri = surface.report
        done = {"degenerate_faces_removed": tri.get("zero_area_faces_removed", 0),
                "small_component_faces_removed": tri.get("small_component_faces_removed", 0),
                "unreferenced_vertices_removed": tri["unreferenced_vertices_removed"]}
        mesh, cleanup_report = clean_mesh(mesh, params.cleanup, manifold_by_construction=True,
                                          done=done)
    else:
        mesh, cleanup_report = clean_mesh(mesh, params.cleanup)
    report["cleanup"] = cleanup_report
    if method == "poisson" or "faces_removed_by_decimation" in cleanup_report:
        mesh = mesh.with_vertex_normals()
    step("cleanup", 3)
    if len(mesh.faces) == 0:
        raise StageError(f"mesh: no faces left after meshing and clean-up "
                         f"(method {method!r}); see the report's counts")
    report["vertices"] = len(mesh.vertices)
    report["faces"] = len(mesh.faces)
    report["seconds"] = seconds
    report["cpu_seconds"] = cpu_seconds
    return mesh, report


def mesh_stage(inputs: Mapping[str, Any], params: MeshParams,
             progress: ProgressFn) -> StageResult:
    """The stage function: ``points`` → ``mesh_vertices``, ``mesh_faces``."""
    mesh, report = mesh_points(inputs["points"], params, progress)
    vertices, faces = mesh.to_tables()
    progress("mesh", 4, 4)
    return StageResult(tables={"mesh_vertices": vertices, "mesh_faces": faces}, report=report)


STAGE = Stage(
    name="mesh",
    version=2,
    params=MeshParams,
    inputs=("points",),
    outputs=("mesh_vertices", "mesh_faces"),
    func=mesh_stage,
    description="surface from the points: Open3D Poisson or the organized scan grid",
    libraries=("numpy", "pyarrow", "open3d", "scipy"),
)
