"""``scanpipe assemble | filter | import-points``: make and clean ``points`` artifacts."""

from __future__ import annotations

from pathlib import Path

import typer

from scanpipe.cli.common import PARAMS_FILE, QUIET, SET, print_json, run_stage_command
from scanpipe.errors import UsageError
from scanpipe.pipeline import rig_override_artifact

OUT = typer.Option(..., "--out", help="Output folder.")


def _artifact_in(folder: Path, name: str) -> Path:
    path = folder / f"{name}.parquet"
    if not path.is_file():
        raise UsageError(f"{path}: not found (expected the {name!r} artifact in {folder})")
    return path


def assemble(
    folder: Path = typer.Argument(..., help="Folder with profiles, motor and rig artifacts."),
    out: Path = OUT,
    rig_path: Path | None = typer.Option(None, "--rig",
                                         help="Rig TOML whose calibration replaces the "
                                              "recording's."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
) -> None:
    """Profiles + motor states → calibrated points on the profile × sample grid."""
    inputs = {name: _artifact_in(folder, name) for name in ("profiles", "motor")}
    # The same rig artifact `scanpipe run --rig` writes: OUT/rig/rig.parquet, keyed by content.
    inputs["rig"] = (rig_override_artifact(rig_path, out) if rig_path is not None
                     else _artifact_in(folder, "rig"))
    report = run_stage_command("assemble", inputs, out, params_file, assignments, quiet)
    print_json(report)


def filter_command(
    folder: Path = typer.Argument(..., help="Folder with a points artifact."),
    out: Path = OUT,
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
) -> None:
    """Range gate, no-returns, depth edges, grid median, smoothing, double coverage, outliers,
    voxels: remove or mark points."""
    if out.resolve() == folder.resolve():
        raise UsageError(f"--out {out}: must differ from the input folder (it would replace "
                         "the points it reads)")
    inputs = {"points": _artifact_in(folder, "points")}
    report = run_stage_command("filter", inputs, out, params_file, assignments, quiet)
    print_json(report)


def _parse_origin(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise UsageError(f"--origin {text!r}: expected three numbers x,y,z in metres")
    return values[0], values[1], values[2]


def import_points_command(
    file: Path = typer.Argument(..., help="PLY, XYZ/CSV/TXT/PTS or LAS/LAZ file."),
    out: Path = OUT,
    origin: str = typer.Option("0,0,0", "--origin",
                               help="Sensor origin x,y,z in metres (rig frame)."),
    up: str = typer.Option("auto", "--up", help="The file's up axis: auto, y or z."),
    force: bool = typer.Option(False, "--force",
                               help="Overwrite an existing OUT/points.parquet."),
    quiet: bool = QUIET,
) -> None:
    """Import a foreign point cloud as a points artifact (no grid)."""
    from scanpipe.outpaths import check_output_file, check_output_folder

    if not file.is_file():
        raise UsageError(f"{file}: not found (the point file to import)")
    target = out / "points.parquet"
    check_output_folder(out, "--out", [file])
    check_output_file(target, "--out", (".parquet",), force, [file])
    report = run_stage_command("import-points", {"point_file": file}, out, None, None, quiet,
                               {"origin_m": _parse_origin(origin), "up": up})
    print_json(report)


def register(app: typer.Typer) -> None:
    """Add ``assemble``, ``filter`` and ``import-points`` to the main app."""
    app.command("assemble")(assemble)
    app.command("filter")(filter_command)
    app.command("import-points")(import_points_command)
