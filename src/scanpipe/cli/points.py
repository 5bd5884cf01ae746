"""``scanpipe assemble | filter | import-points``: make and clean ``points`` artifacts."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from scanpipe.artifacts import file_key
from scanpipe.cli.common import JSON_ALWAYS, PARAMS_FILE, QUIET, SET, print_json, run_stage_command
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
    as_json: bool = JSON_ALWAYS,
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
    as_json: bool = JSON_ALWAYS,
) -> None:
    """Range gate, no-returns, depth edges, grid median, smoothing, double coverage, outliers,
    voxels: remove or mark points."""
    if out.resolve() == folder.resolve():
        raise UsageError(f"--out {out}: must differ from the input folder (it would replace "
                         "the points it reads)")
    inputs = {"points": _artifact_in(folder, "points")}
    report = run_stage_command("filter", inputs, out, params_file, assignments, quiet)
    print_json(report)


def _parse_triple(text: str, option: str, meaning: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise UsageError(f"{option} {text!r}: expected three numbers x,y,z in metres "
                         f"({meaning}; finite)")
    return values[0], values[1], values[2]


def import_points_command(
    files: list[Path] = typer.Argument(..., help="Point files: PLY, XYZ/CSV/TXT/PTS, LAS/LAZ, "
                                                  "E57, PCD, 3DTK .3d (several are merged)."),
    out: Path = OUT,
    origin: str = typer.Option("0,0,0", "--origin",
                               help="Sensor origin x,y,z in metres (rig frame) when no --pose."),
    up: str = typer.Option("auto", "--up", help="The file's up axis: auto, y or z."),
    file_format: str = typer.Option("auto", "--format",
                                    help="auto (from the extension), xyz, csv, pts, ply, las, "
                                         "e57, pcd or 3d."),
    columns: str | None = typer.Option(None, "--columns",
                                       help="Text columns: roles in order (x,y,z,-,intensity) "
                                            "or ROLE=INDEX; see docs/import.md."),
    units: str = typer.Option("auto", "--units", help="auto, m, cm, mm, ft or us-ft."),
    axes: str | None = typer.Option(None, "--axes",
                                    help="File axis for rig x,y,z, signed (e.g. x,z,-y)."),
    left_handed: bool | None = typer.Option(None, "--left-handed/--right-handed",
                                            help="The file's frame handedness (3DTK: left)."),
    organised: str | None = typer.Option(None, "--organised",
                                         help="ROWSxCOLS: keep the grid (profile = row)."),
    max_range: float | None = typer.Option(None, "--max-range",
                                           help="Ranges at/above this (metres) are no-returns."),
    offset: str | None = typer.Option(None, "--offset",
                                      help="Georeference offset X,Y,Z (metres, z-up: a LAS "
                                           "file's x,y,z) subtracted from every point and "
                                           "added back by exports; give one to every file "
                                           "of a site (default: chosen per cloud)."),
    pose: list[Path] | None = typer.Option(None, "--pose",
                                           help="Pose file per input, in order: 4x4 matrix or "
                                                "3DTK .pose."),
    force: bool = typer.Option(False, "--force",
                               help="Overwrite an existing OUT/points.parquet."),
    quiet: bool = QUIET,
    as_json: bool = JSON_ALWAYS,
) -> None:
    """Import foreign point clouds as one points artifact (grid kept with --organised)."""
    from scanpipe.outpaths import check_output_file, check_output_folder

    for file in [*files, *(pose or [])]:
        if not file.is_file():
            raise UsageError(f"{file}: not found (a point or pose file to import)")
    target = out / "points.parquet"
    check_output_folder(out, "--out", [*files, *(pose or [])])
    check_output_file(target, "--out", (".parquet",), force, [*files, *(pose or [])])
    base: dict[str, object] = {
        "origin_m": _parse_triple(origin, "--origin", "the sensor origin, rig frame"),
        "offset_m": None if offset is None else _parse_triple(
            offset, "--offset", "the georeference offset, z-up"),
        "up": up, "format": file_format, "columns": columns,
        "units": units, "axes": axes, "left_handed": left_handed, "organised": organised,
        "max_range_m": max_range, "extra_files": [str(f) for f in files[1:]],
        "poses": [str(p) for p in (pose or [])],
        "content_keys": [file_key(f) for f in [*files[1:], *(pose or [])]]}
    report = run_stage_command("import-points", {"point_file": files[0]}, out, None, None,
                               quiet, base)
    print_json(report)


def import_profiles_command(
    file: Path = typer.Argument(..., help="Long CSV/Parquet (profile, beam_deg, platform_deg, "
                                          "range_m) or wide NPZ (ranges, beam_deg, "
                                          "platform_deg)."),
    out: Path = OUT,
    rig_path: Path | None = typer.Option(None, "--rig", help="Rig TOML to start from (mount, "
                                                             "calibration, motor)."),
    ranges_col: str = typer.Option("range_m", "--ranges-col", help="Long layout: range column."),
    units: str = typer.Option("m", "--units", help="Unit of the ranges: m, cm or mm."),
    max_range: float | None = typer.Option(None, "--max-range",
                                           help="Ranges at/above this (metres) are no-returns."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing artifacts in OUT."),
    quiet: bool = QUIET,
    as_json: bool = JSON_ALWAYS,
) -> None:
    """Import ranges + beam and platform angles as profiles, motor and rig artifacts (then
    `scanpipe assemble OUT`)."""
    from scanpipe.outpaths import check_output_file, check_output_folder

    inputs = [file, *([rig_path] if rig_path else [])]
    for path in inputs:
        if not path.is_file():
            raise UsageError(f"{path}: not found")
    check_output_folder(out, "--out", inputs)
    for name in ("profiles", "motor", "rig"):
        check_output_file(out / f"{name}.parquet", "--out", (".parquet",), force, inputs)
    base: dict[str, object] = {"ranges_col": ranges_col, "units": units,
                               "max_range_m": max_range}
    if rig_path is not None:
        base["rig_toml"] = rig_path.read_text(encoding="utf-8")
    report = run_stage_command("import-profiles", {"profile_file": file}, out, None, None,
                               quiet, base)
    print_json(report)


def register(app: typer.Typer) -> None:
    """Add ``assemble``, ``filter``, ``import-points`` and ``import-profiles`` to the app."""
    app.command("assemble")(assemble)
    app.command("filter")(filter_command)
    app.command("import-points")(import_points_command)
    app.command("import-profiles")(import_profiles_command)
