"""``scanpipe export``: a folder of artifacts to files on disk, all or nothing.

The shell around the pure :func:`scanpipe.stages.export.export_files`: find the artifacts
(a workdir or a flat folder), check the output paths (:mod:`scanpipe.outpaths`), and write
every file to a temporary name first, renaming only when all were written, so an error never
leaves a half export.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa

from scanpipe.artifacts import FILE_MODE, FileData, read_artifact, write_file_data
from scanpipe.errors import ArtifactError, ExportError
from scanpipe.outpaths import (
    check_output_file,
    check_output_files,
    check_output_folder,
    folder_inputs,
)
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stage import refuse_uncarried_offset
from scanpipe.stages.export import (
    CAMERA_ARTIFACTS,
    INPUT_ARTIFACTS,
    MESH_ARTIFACTS,
    SUFFIXES,
    TEXTURE_ARTIFACTS,
    FormatError,
    check_format,
    check_las_version,
    export_files,
    georeference_report,
    models_from_tables,
    prepare_tables,
)
from scanpipe.workdir import find_artifacts


def write_files(files: Mapping[str, FileData], out_dir: Path) -> list[Path]:
    """Write every file (bytes or pieces: :func:`scanpipe.artifacts.write_file_data`) into
    ``out_dir``, all or nothing; returns the paths written."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ExportError(f"{out_dir}: cannot create the folder ({err.strerror or err})") from None
    staged: list[tuple[Path, Path]] = []
    try:
        for name, data in files.items():
            target = out_dir / name
            target.parent.mkdir(parents=True, exist_ok=True)  # COLMAP's images/, sparse/0/
            fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp",
                                            dir=target.parent)
            staged.append((Path(tmp_name), target))
            os.fchmod(fd, FILE_MODE)
            with os.fdopen(fd, "wb") as handle:
                write_file_data(handle, data)
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
    wanted = SUFFIXES.get(fmt, f".{fmt}")  # ``.copc.laz`` for copc
    if out.is_dir():
        return "scan", out
    if out.name.lower().endswith(wanted) and len(out.name) > len(wanted):
        if out.exists():
            check_output_file(out, "--out", (wanted,), force=True)  # a device, a FIFO …
        return out.name[:-len(wanted)], out.parent
    suffix = out.suffix.lower()
    if suffix:
        raise FormatError(f"--out {out}: the extension {suffix} does not match --format {fmt} "
                          f"(expected a name ending in {wanted})")
    if out.exists():
        check_output_file(out, "--out", (wanted,), force=True)
        raise FormatError(f"--out {out}: is a file without a suffix; give a file name "
                          f"ending in {wanted}, or a folder")
    return "scan", out


def load_tables(folder: Path, fmt: str) -> dict[str, pa.Table]:
    """The artifacts an export of ``fmt`` can use from ``folder`` (flat or per stage)."""
    found = find_artifacts(folder, (*INPUT_ARTIFACTS, *CAMERA_ARTIFACTS))
    if not set(found) & set(INPUT_ARTIFACTS) and fmt != "colmap":
        raise ArtifactError(f"{folder}: no artifacts to export (looked for "
                            f"{', '.join(INPUT_ARTIFACTS)} as <name>.parquet or "
                            "<stage>/<name>.parquet)")
    # the camera artifacts colour the points (as in ``run``) and pose the COLMAP frames
    wanted: tuple[str, ...] = (*INPUT_ARTIFACTS, *CAMERA_ARTIFACTS)
    if fmt in ("las", "laz", "copc", "e57", "colmap"):
        wanted = ("points", *CAMERA_ARTIFACTS)
    elif fmt in ("obj", "glb"):
        wanted = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS)
    elif fmt == "ply":
        wanted = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points")
    tables = {name: read_artifact(path)[0] for name, path in found.items() if name in wanted}
    for name, table in tables.items():
        refuse_uncarried_offset(str(found[name]), table)
    return tables


def export_folder(folder: Path, fmt: str, out: Path, force: bool = False,
                  las_version: str = "1.2", progress: ProgressFn = no_progress,
                  draco: bool = False, report: dict[str, Any] | None = None) -> list[Path]:
    """``scanpipe export``: read the artifacts in ``folder`` and write ``fmt`` to ``out``.

    The points are coloured from the camera frames as ``scanpipe run`` does (one code path:
    :func:`scanpipe.stages.export.prepare_tables`).

    No existing file is replaced without ``force``, and none may be one of the inputs (an
    artifact, or the recording a workdir was made from), even with it. ``report``, when
    given, receives what the export stage reports of a georeferenced model (its offset and
    warnings: :func:`scanpipe.stages.export.georeference_report`).
    """
    fmt = check_format(fmt)
    check_las_version(las_version)
    if draco and fmt != "glb":
        raise FormatError(f"--draco compresses GLB files; --format is {fmt!r}")
    stem, out_dir = stem_and_folder(out, fmt)
    check_output_folder(out_dir)
    inputs = folder_inputs(folder)
    # The main file first, before the (slow) reading; then every file the export makes.
    main = out_dir / (f"{stem}_colmap" if fmt == "colmap"
                      else f"{stem}{SUFFIXES.get(fmt, '.' + fmt)}")
    if fmt != "colmap":
        check_output_files([main], "--out", force, inputs)
    tables, _ = prepare_tables(load_tables(folder, fmt), progress=progress)
    models = models_from_tables(tables)
    files = export_files(tables, fmt, stem, las_version, draco, models)
    if report is not None:
        mesh, cloud = models
        report.update(georeference_report(
            mesh if fmt in ("obj", "glb", "ply", "mcap") else None,
            None if fmt in ("obj", "glb") or (fmt == "ply" and mesh is not None) else cloud,
            [fmt]))
    check_output_files([out_dir / name for name in files], "--out", force, inputs)
    return write_files(files, out_dir)
