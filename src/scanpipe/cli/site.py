"""``scanpipe register``: the scans of a site aligned into one frame (see docs/sites.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from scanpipe.cli.common import (
    JSON,
    PARAMS_FILE,
    QUIET,
    SET,
    build_params,
    print_json,
    print_warnings,
)


def register_command(
    workdirs: list[Path] = typer.Argument(..., help="The workdir of each scan (after filter)."),
    out: Path = typer.Option(..., "--out", help="The site folder to write."),
    prior: Path | None = typer.Option(None, "--prior", help="Prior poses (a poses Parquet "
                                                            "file), e.g. from odometry."),
    force: bool = typer.Option(False, "--force", help="Overwrite an earlier site result."),
    truth: Path | None = typer.Option(None, "--truth", help="True poses (the truth folder of "
                                      "`simulate --site`): report each pose's error."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Register the scans of a site: pairwise alignment, pose graph, merged points."""
    from scanpipe.registration import RegisterParams
    from scanpipe.site import register_site

    params = build_params(RegisterParams, params_file, assignments, None)
    report = register_site(list(workdirs), out, params, prior, force, truth_path=truth)
    print_warnings("register", report)
    if as_json:
        print_json(report)
    elif not quiet:
        for pair in report["pairs"]:
            state = "kept" if pair["accepted"] else f"left out ({pair['reason']})"
            # a pair refused before its fine ICP has no residual
            residual = (f", residual {pair['rmse_m'] * 1000:.1f} mm" if pair["rmse_m"] > 0
                        else "")
            sys.stderr.write(f"register: {pair['target']}–{pair['source']}: overlap "
                             f"{pair['overlap']:.1%}{residual}, {state}\n")
        for row in report.get("pose_errors", []):
            error = ("n/a" if row["translation_m"] is None else
                     f"{row['translation_m'] * 1000:.2f} mm / {row['rotation_deg']:.4f}°")
            sys.stderr.write(f"register: {row['scan']} pose error {error}"
                             f"{' (' + row['note'] + ')' if row['note'] else ''}\n")
        sys.stderr.write(f"register: {len(report['scans']) - len(report['unregistered'])} of "
                         f"{len(report['scans'])} scans → {report['poses']}, merged "
                         f"{report['merge']['points_out']} points → {report['points']}\n")


def site_model_command(
    workdirs: list[Path] = typer.Argument(..., help="The workdir of each scan (after texture)."),
    out: Path = typer.Option(..., "--out", help="The site folder (from scanpipe register)."),
    poses: Path | None = typer.Option(None, "--poses", help="Poses to use instead of "
                                      "OUT/poses.parquet (a poses Parquet file)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an earlier model."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """The merged model of a site: fused textured mesh, merged cloud, E57/LAS/GLB/OBJ."""
    from scanpipe.progress import rich_progress
    from scanpipe.site_model import SiteModelParams, build_site_model, model_summary

    params = build_params(SiteModelParams, params_file, assignments, None)
    with rich_progress(quiet or as_json) as progress:
        report = build_site_model(list(workdirs), out, params, poses, force, progress)
    print_warnings("site-model", report)
    if as_json:
        print_json(report)
    elif not quiet:
        sys.stderr.write(model_summary(report) + "\n")


def register(app: typer.Typer) -> None:
    """Add ``register`` and ``site-model`` to the main app."""
    app.command("register")(register_command)
    app.command("site-model")(site_model_command)
