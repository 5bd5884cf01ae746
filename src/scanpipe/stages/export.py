"""Export: artifacts to files other tools open (OBJ, GLB, PLY, LAS/LAZ, E57, Foxglove MCAP).

Two layers. :func:`export_files` is pure: tables in, ``{file name: bytes}`` out (the same shape
as :attr:`scanpipe.pipeline.StageResult.files`). :func:`write_files` puts them on disk all or
nothing: every file goes to a temporary name first and is renamed only when all were written,
so an error never leaves a half export. :func:`export_folder` does both for a folder of
artifacts, the ``scanpipe export`` command.

What each format takes: ``obj`` and ``glb`` the mesh (+ texture when present); ``las``,
``laz`` and ``e57`` the points; ``ply`` the mesh, or the points when there is no mesh;
``mcap`` both when present (the points for scrubbing the scan, the mesh as a model).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

import pyarrow as pa
from pydantic import Field

from scanpipe.artifacts import FILE_MODE, read_artifact
from scanpipe.errors import ArtifactError, ExportError, UsageError
from scanpipe.exporters.e57 import e57_bytes
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.las import las_bytes
from scanpipe.exporters.mcap_foxglove import foxglove_mcap_bytes
from scanpipe.exporters.model import CloudModel, MeshModel, cloud_from_table, mesh_from_tables
from scanpipe.exporters.obj import obj_files
from scanpipe.exporters.ply import ply_cloud_bytes, ply_mesh_bytes
from scanpipe.outpaths import (
    check_output_file,
    check_output_files,
    check_output_folder,
    folder_inputs,
)
from scanpipe.params import Params
from scanpipe.pipeline import Stage, StageResult
from scanpipe.progress import ProgressFn
from scanpipe.workdir import find_artifacts

Format = Literal["obj", "glb", "ply", "las", "laz", "e57", "mcap"]
FORMATS: tuple[str, ...] = ("obj", "glb", "ply", "las", "laz", "e57", "mcap")
MESH_ARTIFACTS = ("mesh_vertices", "mesh_faces")
TEXTURE_ARTIFACTS = ("textured_faces", "texture_pages")
INPUT_ARTIFACTS = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points")


class FormatError(ExportError, UsageError):
    """An unknown export format, or an output name that contradicts it (a usage error: exit 2)."""

    exit_code = 2


class ExportParams(Params):
    """What to write: the format, and the stem every file name derives from."""

    format: Format = "obj"
    name: str = "scan"


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
        return {f"{stem}.mcap": foxglove_mcap_bytes(cloud, mesh, stem)}
    if cloud is None:
        raise ArtifactError(f"{fmt} export needs a points artifact; found: "
                            f"{', '.join(sorted(tables)) or 'nothing'}")
    if fmt == "ply":
        return {f"{stem}.ply": ply_cloud_bytes(cloud)}
    if fmt in ("las", "laz"):
        return {f"{stem}.{fmt}": las_bytes(cloud, compressed=fmt == "laz")}
    return {f"{stem}.e57": e57_bytes(cloud, stem)}


def write_files(files: Mapping[str, bytes], out_dir: Path) -> list[Path]:
    """Write every file into ``out_dir``, all or nothing; returns the paths written."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ExportError(f"{out_dir}: cannot create the folder ({err.strerror or err})") from None
    staged: list[tuple[Path, Path]] = []
    try:
        for name, data in files.items():
            target = out_dir / name
            fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=out_dir)
            staged.append((Path(tmp_name), target))
            os.fchmod(fd, FILE_MODE)
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
        for _, target in staged:
            if target.is_dir():
                raise ExportError(f"{target}: is a folder; choose another --out")
        for tmp, target in staged:
            os.replace(tmp, target)
    except OSError as err:
        raise ExportError(f"{out_dir}: cannot write the export "
                          f"({err.strerror or err})") from None
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
    return [target for _, target in staged]


def stem_and_folder(out: Path, fmt: str) -> tuple[str, Path]:
    """``--out`` as (stem, folder): ``room.obj`` → ("room", .); a path without a suffix is a
    folder (created if needed) → ("scan", that folder). Nothing is appended to a path, and a
    device or a file where a folder is meant is refused (see :mod:`scanpipe.outpaths`)."""
    suffix = out.suffix.lower().lstrip(".")
    if out.is_dir():
        return "scan", out
    if suffix and suffix != fmt:
        raise FormatError(f"--out {out}: the extension .{suffix} does not match --format {fmt}")
    if out.exists():
        check_output_file(out, "--out", (f".{fmt}",), force=True)  # a device, a FIFO …
    if not suffix:
        if out.exists():
            raise FormatError(f"--out {out}: is a file without a suffix; give a file name "
                              f"ending in .{fmt}, or a folder")
        return "scan", out
    return out.stem, out.parent


def load_tables(folder: Path, fmt: str) -> dict[str, pa.Table]:
    """The artifacts an export of ``fmt`` can use from ``folder`` (flat or per stage)."""
    found = find_artifacts(folder, INPUT_ARTIFACTS)
    if not found:
        raise ArtifactError(f"{folder}: no artifacts to export (looked for "
                            f"{', '.join(INPUT_ARTIFACTS)} as <name>.parquet or "
                            "<stage>/<name>.parquet)")
    wanted: tuple[str, ...] = INPUT_ARTIFACTS
    if fmt in ("las", "laz", "e57"):
        wanted = ("points",)
    elif fmt in ("obj", "glb"):
        wanted = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS)
    return {name: read_artifact(path)[0] for name, path in found.items() if name in wanted}


def export_folder(folder: Path, fmt: str, out: Path, force: bool = False) -> list[Path]:
    """``scanpipe export``: read the artifacts in ``folder`` and write ``fmt`` to ``out``.

    No existing file is replaced without ``force``, and none may be one of the inputs (an
    artifact, or the recording a workdir was made from), even with it.
    """
    fmt = check_format(fmt)
    stem, out_dir = stem_and_folder(out, fmt)
    check_output_folder(out_dir)
    inputs = folder_inputs(folder)
    # The main file first, before the (slow) reading; then every file the export makes.
    check_output_files([out_dir / f"{stem}.{fmt}"], "--out", force, inputs)
    tables = load_tables(folder, fmt)
    files = export_files(tables, fmt, stem)
    check_output_files([out_dir / name for name in files], "--out", force, inputs)
    return write_files(files, out_dir)


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
    jobs: list[tuple[str, Mapping[str, pa.Table], str]] = [
        (fmt, mesh_tables, params.name) for fmt in params.mesh_formats]
    points = inputs["points"]
    coloured = False
    if params.cloud_formats and params.cloud_colors and inputs["frames"].num_rows:
        from scanpipe.rig import rig_from_table
        from scanpipe.texturing.projective import colorize_points

        points = colorize_points(points, inputs["frames"], inputs["motor"],
                                 rig_from_table(inputs["rig"]), progress=progress)
        coloured = True
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
    version=1,
    params=ExportStageParams,
    inputs=(*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points", "frames", "motor", "rig"),
    outputs=("export_manifest",),
    func=export_stage,  # type: ignore[arg-type]
    description="write the textured mesh (OBJ+MTL+PNG, GLB) and the cloud (PLY, LAS, E57)",
    libraries=("numpy", "pyarrow", "cv2", "laspy", "pye57"),
)
