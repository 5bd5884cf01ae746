"""``scanpipe texture`` and ``scanpipe calibrate-camera``."""

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
    run_stage_command,
)
from scanpipe.errors import ArtifactError

TEXTURE_INPUTS = ("mesh_vertices", "mesh_faces", "frames", "motor", "rig")


def find_inputs(dirs: list[Path], names: tuple[str, ...]) -> dict[str, Path]:
    """Each artifact from the first folder holding it, flat (``D/x.parquet``) or in a workdir
    (``D/<stage>/x.parquet``); :class:`ArtifactError` naming what is missing."""
    for directory in dirs:
        if not directory.is_dir():
            raise ArtifactError(f"{directory}: not a folder")
    found: dict[str, Path] = {}
    for name in names:
        for directory in dirs:
            candidates = [directory / f"{name}.parquet",
                          *sorted(directory.glob(f"*/{name}.parquet"))]
            hit = next((c for c in candidates if c.is_file()), None)
            if hit is not None:
                found[name] = hit
                break
    missing = [n for n in names if n not in found]
    if missing:
        where = ", ".join(str(d) for d in dirs)
        raise ArtifactError(f"texture needs {', '.join(missing)} (.parquet); not found in {where}")
    return found


def texture(
    dirs: list[Path] = typer.Argument(
        ..., metavar="DIR...",
        help="Folders with the mesh and the decoded recording (flat or a workdir)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    method: str | None = typer.Option(None, "--method",
                                      help="projective (default) or panorama (the paper's)."),
    rig_path: Path | None = typer.Option(None, "--rig", help="Rig TOML overriding the "
                                         "recording's (e.g. after calibrate-camera)."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    as_json: bool = JSON,
    quiet: bool = QUIET,
) -> None:
    """Texture a mesh from the camera frames: UVs and PNG atlas pages."""
    from scanpipe.pipeline import rig_override_artifact
    from scanpipe.stages.texture import TextureParams

    base = {"method": method} if method is not None else None
    build_params(TextureParams, params_file, assignments, base)  # bad parameters first
    names = TEXTURE_INPUTS if rig_path is None else TEXTURE_INPUTS[:-1]
    inputs = find_inputs(dirs, names)
    if rig_path is not None:
        inputs["rig"] = rig_override_artifact(rig_path, out)
    report = run_stage_command("texture", inputs, out, params_file, assignments, quiet, base)
    if as_json:
        print_json(report)
    else:
        typer.echo(
            f"{report['method']}: {report['faces_textured']} of {report['faces']} faces textured "
            f"(coverage {100 * report['coverage']:.1f} % of the surface), "
            f"{report['faces_untextured']} untextured, {report['frames_used']} frames used, "
            f"{report['pages']} page(s)"
        )


def calibrate_camera(
    images: list[Path] = typer.Argument(..., help="Chessboard images (PNG, JPEG …)."),
    board: str = typer.Option("9x6", "--board", help="Inner corners, COLSxROWS."),
    square_m: float = typer.Option(0.025, "--square-m", help="Square size in metres."),
    rig_path: Path = typer.Option(..., "--rig", help="Rig TOML file to update."),
    camera: str = typer.Option("cam0", "--camera", help="Camera id in the rig."),
    free_k3: bool = typer.Option(False, "--free-k3", help="Also fit k3 (needs many views)."),
    as_json: bool = JSON,
) -> None:
    """Calibrate a camera from chessboard images; write intrinsics and distortion to the rig."""
    from scanpipe.calibration import apply_calibration, calibrate, parse_board, read_images
    from scanpipe.outpaths import check_input_file, check_not_input
    from scanpipe.rig import load_rig

    pattern = parse_board(board)
    check_input_file(rig_path, "--rig")  # rewritten in place (temporary name, then rename)
    check_not_input(rig_path, images, "--rig")
    before = load_rig(rig_path).camera(camera)  # fail before the slow part on a bad rig
    warnings: list[str] = []
    result = calibrate(read_images(images), pattern, square_m, fix_k3=not free_k3)
    if abs(result.width / result.height - before.width / before.height) > 0.01:
        turned = abs(result.width / result.height - before.height / before.width) <= 0.01
        why = ("the camera held the other way (upright against level)" if turned else
               "a photo mode rather than the video mode?")
        warnings.append(
            f"the images are {result.width}×{result.height}, camera {camera} was "
            f"{before.width}×{before.height} in the rig (another aspect ratio: {why}); the rig "
            f"now says {result.width}×{result.height}, and frames of another aspect ratio will "
            "be refused by texture: calibrate on images taken the way and in the mode the "
            "frames are recorded")
    for warning in warnings:
        sys.stderr.write(f"warning: calibrate-camera: {warning}\n")
    apply_calibration(rig_path, camera, result)
    if as_json:
        print_json({"rig": str(rig_path), "camera": camera, **result.to_json(),
                    "warnings": warnings})
        return
    k1, k2, p1, p2, k3 = result.distortion
    typer.echo(
        f"{camera}: fx {result.fx:.2f}  fy {result.fy:.2f}  cx {result.cx:.2f}  "
        f"cy {result.cy:.2f}  distortion [{k1:.5f}, {k2:.5f}, {p1:.5f}, {p2:.5f}, {k3:.5f}]\n"
        f"reprojection error {result.rms_px:.3f} px from {len(result.used)} of {len(images)} "
        f"images; written to {rig_path}"
    )
    if result.rejected:
        sys.stderr.write(f"no board found in: {', '.join(result.rejected)}\n")


def register(app: typer.Typer) -> None:
    """Add ``texture`` and ``calibrate-camera`` to the main app."""
    app.command("texture")(texture)
    app.command("calibrate-camera")(calibrate_camera)
