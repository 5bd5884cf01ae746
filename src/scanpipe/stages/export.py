"""Export: artifacts to files other tools open (OBJ, GLB, PLY, LAS/LAZ, E57, Foxglove MCAP).

Pure: :func:`export_files` turns tables into ``{file name: bytes}`` (the shape of
:attr:`scanpipe.stage.StageResult.files`), and the chain's export stage is that plus a
manifest. Writing files for ``scanpipe export`` is the shell's: :mod:`scanpipe.exporting`.

What each format takes: ``obj`` and ``glb`` the mesh (+ texture when present); ``las``,
``laz`` and ``e57`` the points; ``ply`` the mesh, or the points when there is no mesh;
``mcap`` both when present (the points for scrubbing the scan, the mesh as a model).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from typing import Literal

import pyarrow as pa
from pydantic import Field

from scanpipe.errors import ArtifactError, ExportError, UsageError
from scanpipe.exporters.e57 import e57_bytes
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.las import las_bytes
from scanpipe.exporters.mcap_foxglove import camera_views_from_tables, foxglove_export_files
from scanpipe.exporters.model import CloudModel, MeshModel, cloud_from_table, mesh_from_tables
from scanpipe.exporters.obj import obj_files
from scanpipe.exporters.ply import ply_cloud_bytes, ply_mesh_bytes
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.stage import Stage, StageResult

FORMATS: tuple[str, ...] = ("obj", "glb", "ply", "las", "laz", "e57", "mcap")
MESH_ARTIFACTS = ("mesh_vertices", "mesh_faces")
TEXTURE_ARTIFACTS = ("textured_faces", "texture_pages")
#: What the Foxglove export shows besides the scan: the camera frames, placed by rig and motor.
CAMERA_ARTIFACTS = ("frames", "motor", "rig")
INPUT_ARTIFACTS = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points", *CAMERA_ARTIFACTS)


class FormatError(ExportError, UsageError):
    """An unknown export format, or an output name that contradicts it (a usage error: exit 2)."""

    exit_code = 2


def check_format(fmt: str) -> str:
    """The format name in lower case, or a FormatError listing the formats."""
    lowered = fmt.lower().lstrip(".")
    if lowered not in FORMATS:
        raise FormatError(f"--format {fmt!r}: unknown format; allowed: {', '.join(FORMATS)}")
    return lowered


def models_from_tables(tables: Mapping[str, pa.Table]) -> tuple[MeshModel | None,
                                                                   CloudModel | None]:
    """The mesh (with texture when both texture artifacts exist) and the cloud, where given."""
    mesh = None
    if all(name in tables for name in MESH_ARTIFACTS):
        textured = all(name in tables for name in TEXTURE_ARTIFACTS)
        mesh = mesh_from_tables(tables["mesh_vertices"], tables["mesh_faces"],
                                tables["textured_faces"] if textured else None,
                                tables["texture_pages"] if textured else None)
    cloud = cloud_from_table(tables["points"]) if "points" in tables else None
    return mesh, cloud


def export_files(tables: Mapping[str, pa.Table], fmt: str, stem: str) -> dict[str, bytes]:
    """The files of one export, by name; the first is the main file."""
    fmt = check_format(fmt)
    mesh, cloud = models_from_tables(tables)
    if fmt in ("obj", "glb") or (fmt == "ply" and mesh is not None):
        if mesh is None:
            raise ArtifactError(f"{fmt} export needs a mesh (mesh_vertices and mesh_faces "
                                f"artifacts); found: {', '.join(sorted(tables)) or 'nothing'}")
        if fmt == "obj":
            return obj_files(mesh, stem)
        if fmt == "glb":
            return {f"{stem}.glb": glb_bytes(mesh, stem)}
        return {f"{stem}.ply": ply_mesh_bytes(mesh)}
    if fmt == "mcap":
        return foxglove_export_files(cloud, mesh, stem, camera_views_from_tables(tables))
    if cloud is None:
        raise ArtifactError(f"{fmt} export needs a points artifact; found: "
                            f"{', '.join(sorted(tables)) or 'nothing'}")
    if fmt == "ply":
        return {f"{stem}.ply": ply_cloud_bytes(cloud)}
    if fmt in ("las", "laz"):
        return {f"{stem}.{fmt}": las_bytes(cloud, compressed=fmt == "laz")}
    return {f"{stem}.e57": e57_bytes(cloud, stem)}


MeshFormat = Literal["obj", "glb", "ply", "mcap"]
CloudFormat = Literal["ply", "las", "laz", "e57"]


class ExportStageParams(Params):
    """The export at the end of ``scanpipe run``: which files to write from the chain."""

    mesh_formats: tuple[MeshFormat, ...] = Field(
        ("obj", "glb"), description="formats of the textured mesh")
    cloud_formats: tuple[CloudFormat, ...] = Field(
        ("ply",), description="formats of the filtered point cloud")
    name: str = Field("model", pattern=r"^[A-Za-z0-9_.-]+$",
                      description="stem of the mesh files")
    cloud_name: str = Field("cloud", pattern=r"^[A-Za-z0-9_.-]+$",
                            description="stem of the point-cloud files")
    cloud_colors: bool = Field(
        True, description="colour the cloud from the camera frames (when there are frames)")


def export_stage(inputs: Mapping[str, pa.Table], params: ExportStageParams,
                 progress: ProgressFn) -> StageResult:
    """The chain's export: every requested file, and a manifest table naming them."""
    if params.name == params.cloud_name:
        raise UsageError(f"export.name and export.cloud_name are both {params.name!r}: "
                         "the mesh and the cloud files would overwrite each other")
    files: dict[str, bytes] = {}
    mesh_tables = {k: v for k, v in inputs.items() if k != "points"}
    points = inputs["points"]
    coloured = False
    wants_points = bool(params.cloud_formats) or "mcap" in params.mesh_formats
    if wants_points and params.cloud_colors and inputs["frames"].num_rows:
        from scanpipe.rig import rig_from_table
        from scanpipe.texturing.projective import colorize_points

        points = colorize_points(points, inputs["frames"], inputs["motor"],
                                 rig_from_table(inputs["rig"]), progress=progress)
        coloured = True
    # The Foxglove file shows the scan too: the mesh job of mcap gets the (coloured) points.
    jobs: list[tuple[str, Mapping[str, pa.Table], str]] = [
        (fmt, {**mesh_tables, "points": points} if fmt == "mcap" else mesh_tables, params.name)
        for fmt in params.mesh_formats]
    jobs += [(fmt, {"points": points}, params.cloud_name) for fmt in params.cloud_formats]
    for done, (fmt, tables, stem) in enumerate(jobs):
        progress("export", done, len(jobs))
        files.update(export_files(tables, fmt, stem))
    progress("export", len(jobs), len(jobs))
    manifest = pa.table({
        "file": pa.array(list(files), pa.string()),
        "bytes": pa.array([len(data) for data in files.values()], pa.int64()),
        "sha256": pa.array([hashlib.sha256(data).hexdigest() for data in files.values()],
                           pa.string()),
    })
    return StageResult({"export_manifest": manifest},
                       {"files": {name: len(data) for name, data in files.items()},
                        "cloud_coloured": coloured}, files)


STAGE = Stage(
    name="export",
    version=2,  # 2: the Foxglove file has the cloud, camera images and a layout beside it
    params=ExportStageParams,
    inputs=(*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points", "frames", "motor", "rig"),
    outputs=("export_manifest",),
    func=export_stage,  # type: ignore[arg-type]
    description="write the textured mesh (OBJ+MTL+PNG, GLB) and the cloud (PLY, LAS, E57)",
    libraries=("numpy", "pyarrow", "cv2", "laspy", "pye57"),
)
