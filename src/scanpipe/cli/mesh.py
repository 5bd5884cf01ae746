"""``scanpipe mesh``: a surface mesh from a points artifact (Poisson or the scan grid)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import JSON_ALWAYS, PARAMS_FILE, QUIET, SET, print_json, run_stage_command
from scanpipe.errors import UsageError
from scanpipe.workdir import find_artifact


def mesh_command(
    folder: Path = typer.Argument(..., help="Folder (or workdir) with a points artifact."),
    out: Path = typer.Option(..., "--out", help="Output folder for mesh_vertices/mesh_faces."),
    method: str | None = typer.Option(None, "--method",
                                      help="auto (grid when the points keep their scan "
                                           "grid, else poisson), poisson, or grid."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON_ALWAYS,
) -> None:
    """Points → triangle mesh: normals, Poisson or grid triangulation, clean-up, decimation."""
    if not folder.is_dir():
        raise UsageError(f"{folder}: not a folder (give the folder holding points.parquet)")
    points = find_artifact(folder, "points")
    if points is None:
        raise UsageError(f"{folder}: no points artifact (points.parquet) in it or its stage "
                         "folders")
    base: dict[str, Any] = {"method": method} if method is not None else {}
    report = run_stage_command("mesh", {"points": points}, out, params_file, assignments,
                               quiet, base=base)
    print_json(report)


def register(app: typer.Typer) -> None:
    """Add ``mesh`` to the app."""
    app.command("mesh")(mesh_command)
