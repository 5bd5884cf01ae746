"""``scanpipe calibrate``: the scanner's mount fitted to one scan (no targets)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from scanpipe.artifacts import atomic_write_bytes, read_artifact
from scanpipe.cli.common import print_json
from scanpipe.errors import UsageError


def _assemble_params(source: Path) -> Any:
    """The assemble parameters a workdir's run used (its ``assemble`` provenance), or None
    (assemble's defaults) for a recording or a workdir not yet assembled."""
    from scanpipe.artifacts import read_provenance
    from scanpipe.params import validate
    from scanpipe.stages.assemble import AssembleParams

    points = source / "assemble" / "points.parquet"
    if not (source.is_dir() and points.is_file()):
        return None
    return validate(AssembleParams, read_provenance(points).get("params", {}), str(points),
                    prefix="assemble.")


def _tables(source: Path) -> dict[str, Any]:
    """profiles, motor, rig from a recording (decoded in memory) or a workdir/folder."""
    if source.is_dir():
        for folder in (source / "decode", source / "import-profiles", source):
            paths = {n: folder / f"{n}.parquet" for n in ("profiles", "motor", "rig")}
            if all(p.is_file() for p in paths.values()):
                return {n: read_artifact(p)[0] for n, p in paths.items()}
        raise UsageError(f"{source}: no profiles, motor and rig artifacts (looked in "
                         f"{source / 'decode'} and {source}); give a recording or a workdir "
                         "that `scanpipe run` decoded")
    if not source.is_file():
        raise UsageError(f"{source}: not found (expected a recording REC.mcap or a workdir)")
    from scanpipe.stages.decode import STAGE as DECODE

    return dict(DECODE.run({"recording": source}).tables)


def calibrate(
    source: Path = typer.Argument(..., help="A recording (REC.mcap) or a workdir of `run`."),
    rig_path: Path | None = typer.Option(None, "--rig", help="Start from this rig file "
                                         "instead of the recording's."),
    write: Path | None = typer.Option(None, "--write", help="Write the calibrated rig here "
                                      "(a new TOML file; never the input rig)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing --write file."),
    truth: Path | None = typer.Option(None, "--truth", help="A simulation's truth folder: "
                                      "also report the points' RMS to the true surface."),
    max_points: int = typer.Option(200_000, "--max-points", min=2_000, max=2_000_000,
                                   help="Returns drawn for the fit."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Fit the scanner's mount (tilt, α zero, offsets from the axis) to the scan's planes."""
    from scanpipe.outpaths import check_output_file
    from scanpipe.rig import load_rig, rig_table, rig_to_toml
    from scanpipe.stages.calibrate import rms_to_truth, run_fit

    if write is not None:
        inputs = [p for p in (source, rig_path) if p is not None]
        check_output_file(write, "--write", (".toml",), force, inputs)
        if not write.parent.is_dir():
            raise UsageError(f"--write {write}: folder {write.parent} does not exist")
    true_data = None
    if truth is not None:
        from scanpipe.sim.truth import load_truth

        true_data = load_truth(truth)
    tables = _tables(source)
    if rig_path is not None:
        tables["rig"] = rig_table(load_rig(rig_path))
    assemble_params = _assemble_params(source)
    fit = run_fit(tables, max_points, assemble_params)
    report: dict[str, Any] = {"source": str(source), **fit.report()}
    if true_data is not None:
        from scanpipe.rig import rig_from_table

        report["rms_to_truth_before_m"] = rms_to_truth(tables, rig_from_table(tables["rig"]),
                                                        true_data, params=assemble_params)
        report["rms_to_truth_after_m"] = rms_to_truth(tables, fit.rig, true_data,
                                                       params=assemble_params)
    if write is not None:
        try:
            atomic_write_bytes(write, rig_to_toml(fit.rig).encode())
        except OSError as err:
            raise UsageError(f"--write {write}: cannot be written ({err.strerror or err})"
                             ) from None
        report["written"] = str(write)
    for warning in fit.warnings:
        typer.echo(f"warning: {warning}", err=True)
    if as_json:
        print_json(report)
        return
    for p in fit.parameters:
        value = f"{p.value * 1000:+.2f} mm" if p.unit == "m" else f"{p.value:+.4f}°"
        if p.sigma is not None and p.observable:
            sigma = f"± {p.sigma * 1000:.2f} mm" if p.unit == "m" else f"± {p.sigma:.4f}°"
        else:
            sigma = "unobservable (kept)"
        typer.echo(f"{p.name:16s} {value:>14s}  {sigma}")
    typer.echo(f"plane thickness RMS {fit.residual_before_m * 1000:.2f} mm → "
               f"{fit.residual_after_m * 1000:.2f} mm over {fit.planes} planes "
               f"({fit.points} points)")
    if "rms_to_truth_after_m" in report:
        typer.echo(f"RMS to truth {report['rms_to_truth_before_m'] * 1000:.2f} mm → "
                   f"{report['rms_to_truth_after_m'] * 1000:.2f} mm")
    if write is not None:
        typer.echo(f"wrote {write}")


def _camera_tables(workdir: Path) -> dict[str, Any]:
    """points (with the grid), frames, motor, rig from a workdir of `scanpipe run`."""
    from scanpipe.workdir import find_artifact

    if not workdir.is_dir():
        raise UsageError(f"{workdir}: not a folder; give a workdir that `scanpipe run` (or "
                         "decode and assemble) filled")
    found: dict[str, Any] = {}
    for name, places in (("points", ("assemble",)), ("frames", ("decode",)),
                         ("motor", ("decode",)), ("rig", ("calibrate", "decode"))):
        path = next((workdir / p / f"{name}.parquet" for p in places
                     if (workdir / p / f"{name}.parquet").is_file()), None)
        path = path or find_artifact(workdir, name)
        if path is None:
            raise UsageError(f"{workdir}: no {name} artifact; run `scanpipe run REC --workdir "
                             f"{workdir}` (decode and assemble) first")
        found[name] = read_artifact(path)[0]
    return found


def calibrate_cameras(
    workdir: Path = typer.Argument(..., help="A workdir of `scanpipe run` (decode, assemble)."),
    rig_path: Path | None = typer.Option(None, "--rig", help="Start from this rig file "
                                         "instead of the workdir's."),
    camera: list[str] = typer.Option([], "--camera", help="Calibrate this camera (repeat; "
                                     "default: every camera with frames)."),
    time_offset: bool = typer.Option(False, "--time-offset", help="Also find each camera's "
                                     "clock offset (an imported video)."),
    window: float = typer.Option(1.0, "--window", min=0.05, max=30.0,
                                 help="With --time-offset: search ± this many seconds."),
    focal: bool = typer.Option(True, "--focal/--no-focal", help="Also fit the focal length "
                               "(--no-focal keeps the rig's, e.g. from calibrate-camera)."),
    frames: int = typer.Option(24, "--frames", min=3, max=500,
                               help="Frames per camera used (spread over its time)."),
    write: Path | None = typer.Option(None, "--write", help="Write the calibrated rig here "
                                      "(a new TOML file; never the input rig)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing --write file."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Fit each camera's mount, focal length (and clock offset) to the scan's depth edges."""
    from scanpipe.camera_selfcal import calibrate_cameras as run_calibration
    from scanpipe.camera_selfcal import calibrated_rig
    from scanpipe.outpaths import check_output_file
    from scanpipe.rig import load_rig, rig_from_table, rig_to_toml

    if write is not None:
        inputs = [p for p in (workdir, rig_path) if p is not None]
        check_output_file(write, "--write", (".toml",), force, inputs)
        if not write.parent.is_dir():
            raise UsageError(f"--write {write}: folder {write.parent} does not exist")
    tables = _camera_tables(workdir)
    rig = load_rig(rig_path) if rig_path is not None else rig_from_table(tables["rig"])
    for camera_id in camera:
        rig.camera(camera_id)  # an unknown id is an error naming the known ones
    results = run_calibration(tables["points"], tables["frames"], tables["motor"], rig,
                              camera or None, time_offset, window, frames, fit_focal=focal)
    new_rig = calibrated_rig(rig, results)
    report: dict[str, Any] = {"workdir": str(workdir),
                              "cameras": [r.report() for r in results]}
    if write is not None:
        try:
            atomic_write_bytes(write, rig_to_toml(new_rig).encode())
        except OSError as err:
            raise UsageError(f"--write {write}: cannot be written ({err.strerror or err})"
                             ) from None
        report["written"] = str(write)
    for result in results:
        for warning in result.warnings:
            typer.echo(f"warning: {warning}", err=True)
    if as_json:
        print_json(report)
        return
    for result in results:
        typer.echo(f"camera {result.camera_id} ({result.frames} frames)")
        for p in result.parameters:
            if p.name == "time_offset_s":
                value, sigma = f"{p.change:+.3f} s", f"± {(p.sigma or 0) * 1000:.1f} ms"
            elif p.name.endswith("_m"):
                value, sigma = f"{p.change * 1000:+.1f} mm", f"± {(p.sigma or 0) * 1000:.1f} mm"
            elif p.name == "focal_scale":
                value, sigma = f"{p.change * 100:+.2f} %", f"± {(p.sigma or 0) * 100:.2f} %"
            else:
                value, sigma = f"{p.change:+.3f}°", f"± {p.sigma or 0:.3f}°"
            shown = sigma if p.observable else (f"{sigma} over its limit (applied)" if p.applied
                                                else "unobservable (kept)")
            if p.name == "time_offset_s" and (result.motion_clock or {}).get("trusted"):
                shown += " (from the frames' motion at the platform's start and stop)"
            typer.echo(f"  {p.name:14s} {value:>12s}  {shown}")
        trades = result.trade_offs()
        if trades:
            listed = ", ".join(f"{x}–{y} {r:+.2f}" for x, y, r in trades)
            typer.echo(f"  trade-offs: {listed} (correlation: each pair is known only "
                       "together; a measured value of one pins the other)")
        b, a = result.alignment_before.as_dict(), result.alignment_after.as_dict()
        typer.echo(f"  edges: median {_px(b['edge_median_px'])} → {_px(a['edge_median_px'])}, "
                   f"within 2 px {_share(b['edge_within_2px'])} → "
                   f"{_share(a['edge_within_2px'])} ({a['edge_points']} edge points)")
    if write is not None:
        typer.echo(f"wrote {write}")


def _px(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f} px"


def _share(value: float | None) -> str:
    return "n/a" if value is None else f"{value * 100:.0f} %"


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` and ``calibrate-cameras`` to the main app."""
    app.command("calibrate")(calibrate)
    app.command("calibrate-cameras")(calibrate_cameras)
