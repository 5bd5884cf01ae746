"""``scanpipe export | render | eval | report``: results out of the pipeline, and their quality."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import FORCE, JSON, QUIET, print_json


def _report_written(paths: list[Path], quiet: bool, as_json: bool,
                    extra: dict[str, Any] | None = None) -> None:
    """The files a command wrote: one JSON object on stdout with ``--json``, else a line each
    on stderr (none with ``--quiet``)."""
    if as_json:
        print_json({**(extra or {}), "files": [str(p) for p in paths],
                    "bytes": {str(p): p.stat().st_size for p in paths if p.is_file()}})
    elif not quiet:
        for path in paths:
            sys.stderr.write(f"wrote {path}\n")


def export(
    folder: Path = typer.Argument(..., help="Folder with the artifacts (a workdir or flat)."),
    fmt: str = typer.Option(..., "--format", "-f",
                            help="obj | glb | ply | las | laz | copc | e57 | mcap | colmap"),
    out: Path = typer.Option(..., "--out", "-o",
                             help="Output file ending in the format's suffix (its stem names "
                                  "every file written), or a folder (a path without a suffix)."),
    las_version: str = typer.Option("1.2", "--las-version",
                                    help="LAS/LAZ version: 1.2 (point formats 0-3, read by "
                                         "most tools) or 1.4 (formats 6-7)."),
    draco: bool = typer.Option(False, "--draco",
                               help="GLB only: Draco-compress the geometry (about 8x smaller; "
                                    "the reader must support KHR_draco_mesh_compression)."),
    force: bool = FORCE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Write the mesh (OBJ/GLB/PLY), the points (LAS/LAZ/E57/PLY), both (MCAP, Foxglove) or
    the frames with their poses and the points (COLMAP)."""
    from scanpipe.cli.common import print_warnings
    from scanpipe.exporting import export_folder

    report: dict[str, Any] = {}
    written = export_folder(folder, fmt, out, force, las_version, draco=draco, report=report)
    print_warnings("export", report)
    offsets = report.get("offset_z_up_m", {})
    if offsets and not (quiet or as_json):
        sys.stderr.write("georeferenced: import offset (x,y,z z-up, m) "
                         + "; ".join(f"{k} {','.join(f'{v:.17g}' for v in o)}"
                                     for k, o in offsets.items())
                         + ", added back or recorded (docs/export.md)\n")
    _report_written(written, quiet, as_json, {"format": fmt.lower().lstrip("."),
                                              **({"offset_z_up_m": offsets} if offsets else {})})


def render(
    folder: Path = typer.Argument(..., help="Folder with the mesh artifacts, or a mesh file."),
    out: Path = typer.Option(..., "--out", "-o",
                             help="A folder (every view) or one .png (the first view)."),
    width: int = typer.Option(640, "--width", min=16, max=8192, help="Image width in pixels."),
    views: str = typer.Option("perspective,plan,panorama", "--views",
                              help="Comma-separated: perspective, plan, panorama."),
    eye: str | None = typer.Option(None, "--eye", help="Perspective eye x,y,z (rig frame, m)."),
    target: str | None = typer.Option(None, "--target", help="Perspective target x,y,z."),
    fov: float = typer.Option(70.0, "--fov", min=1.0, max=170.0,
                              help="Horizontal field of view (degrees)."),
    force: bool = FORCE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """PNG previews by ray casting: perspective views, a plan view, a panorama from the origin."""
    from scanpipe.render import render_previews

    written = render_previews(folder, out, width=width, views=views, eye=eye, target=target,
                              fov_deg=fov, overwrite=force)
    _report_written(written, quiet, as_json)


def evaluate(
    result: Path = typer.Argument(..., help="A workdir or folder of artifacts."),
    truth: Path = typer.Option(..., "--truth", help="Truth folder (virtual rig or site) or a "
                                                    "mesh file."),
    tau_m: float = typer.Option(0.02, "--tau", min=1e-6, help="F-score threshold τ in metres."),
    as_json: bool = JSON,
) -> None:
    """Accuracy against ground truth: points, mesh (F-score at τ), texture PSNR, stage times;
    on a site (a site truth folder): pose errors and the merged model against the scene."""
    from scanpipe.evaluate import (
        evaluate_result,
        evaluate_site,
        format_evaluation,
        format_site_evaluation,
        is_site_truth,
    )

    site = is_site_truth(truth)
    report = (evaluate_site(result, truth, tau_m=tau_m) if site
              else evaluate_result(result, truth, tau_m=tau_m))
    if as_json:
        print_json(report)
    else:
        typer.echo(format_site_evaluation(report) if site else format_evaluation(report))


def report(
    workdir: Path = typer.Argument(..., help="A workdir or folder of artifacts."),
    out: Path | None = typer.Option(None, "--out", "-o",
                                    help="The HTML file (default: WORKDIR/report.html)."),
    truth: Path | None = typer.Option(None, "--truth",
                                      help="Truth folder or mesh (default: WORKDIR/truth "
                                           "if present)."),
    viewer: bool = typer.Option(True, "--viewer/--no-viewer",
                                help="Include the interactive 3-D view of the model (the "
                                     "model and three.js inside the page, ~0.6 MB + model)."),
    force: bool = FORCE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """One self-contained HTML report: summary, counts, 3-D view, plots, previews, evaluation."""
    from scanpipe.outpaths import check_output_file, folder_inputs
    from scanpipe.report import write_report

    if out is not None:
        # The default WORKDIR/report.html is this command's own file, replaced on every run.
        inputs = folder_inputs(workdir)
        if truth is not None:
            inputs += [truth, *folder_inputs(truth)] if truth.is_dir() else [truth]
        check_output_file(out, "--out", (".html", ".htm"), force, inputs)
    path = write_report(workdir, out, truth, viewer=viewer)
    _report_written([path], quiet, as_json)


def register(app: typer.Typer) -> None:
    """Add ``export``, ``render``, ``eval`` and ``report`` to the main app."""
    app.command("export")(export)
    app.command("render")(render)
    app.command("eval")(evaluate)
    app.command("report")(report)
