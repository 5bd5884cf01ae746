"""``scanpipe rig init|check|intrinsics``: write the default rig, validate a rig file, import
a camera's intrinsics written by another tool."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import typer

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.cli.common import JSON, print_json
from scanpipe.errors import UsageError
from scanpipe.outpaths import check_output_file
from scanpipe.rig import camera_warnings, default_rig, load_rig, rig_to_dict, rig_to_toml
from scanpipe.scanner_models import SCANNER_MODELS

rig_app = typer.Typer(help="Write and check rig descriptions (TOML).", no_args_is_help=True)


@rig_app.command("init")
def init(
    path: Path = typer.Argument(Path("rig.toml"), help="Where to write the rig file."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing file."),
    scanner: str | None = typer.Option(
        None, "--scanner", help="A scanner model for the rig: " + ", ".join(SCANNER_MODELS)
        + " (default: the paper's LD-OEM 1000)."),
    as_json: bool = JSON,
) -> None:
    """Write the default rig (the paper's) as a commented TOML file; ``--scanner`` puts
    another scanner model on it (its dialect, transport, field of view, rate and ranges).

    Never overwrites a file without ``--force``, never replaces a folder, and does not create
    missing folders (a typo in the folder should not scatter rig files around).
    """
    if not path.parent.is_dir():
        raise UsageError(f"{path}: folder {path.parent} does not exist; create it first")
    if scanner is not None and scanner not in SCANNER_MODELS:
        raise UsageError(f"--scanner {scanner!r}: unknown; allowed: {', '.join(SCANNER_MODELS)}")
    check_output_file(path, "", (".toml",), force)
    try:
        atomic_write_bytes(path, rig_to_toml(default_rig(scanner)).encode())
    except OSError as err:
        raise UsageError(f"{path}: cannot be written ({err.strerror or err})") from None
    if as_json:
        print_json({"wrote": str(path)})
    else:
        typer.echo(f"wrote {path}")


@rig_app.command("check")
def check(path: Path = typer.Argument(..., help="Rig TOML file to validate."),
          as_json: bool = JSON) -> None:
    """Validate a rig file; report every problem at once (file, key, value, what is allowed)."""
    rig = load_rig(path)
    warnings = camera_warnings(rig)
    for warning in warnings:
        sys.stderr.write(f"warning: {path}: {warning}\n")
    if as_json:  # valid (a bad file is the one-line error and exit code 2, as without --json)
        print_json({"path": str(path), "valid": True, "rig": rig_to_dict(rig),
                    "warnings": warnings})
        return
    cams = ", ".join(c.id for c in rig.cameras) or "no cameras"
    typer.echo(
        f"{path}: ok — {rig.scanner.model or rig.scanner.dialect} scanner at "
        f"{rig.scanner.beam_step_deg:g}° and "
        f"{rig.scanner.scan_hz:g} Hz, motor step {rig.motor.pulse_step_deg:g}°, "
        f"pulse limit {rig.motor.pulse_limit}, {cams}"
    )


@rig_app.command("intrinsics")
def intrinsics(
    file: Path = typer.Argument(..., help="The intrinsics file: OpenCV YAML/XML, ROS "
                                "camera_info YAML, COLMAP cameras.txt or Metashape XML."),
    rig_path: Path = typer.Option(..., "--rig", help="The rig TOML file (read, never written)."),
    camera: str = typer.Option(..., "--camera", help="The camera id in the rig."),
    fmt: str = typer.Option("auto", "--format", help="auto, opencv, ros, colmap or metashape."),
    file_camera: str | None = typer.Option(
        None, "--file-camera", help="The camera in a file that holds several (COLMAP "
        "CAMERA_ID, Metashape sensor id or label)."),
    out: Path | None = typer.Option(None, "--out", help="Write the rig with the new "
                                    "intrinsics here (a new TOML file; never an input)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing --out file."),
    as_json: bool = JSON,
) -> None:
    """Read a camera's intrinsics written by another tool, convert them to the rig's
    conventions (OpenCV pinhole, k1 k2 p1 p2 k3, top-left pixel centre at 0) and show what
    changes; ``--out`` writes the rig with them. See docs/calibration.md ("Intrinsics from
    other tools")."""
    from scanpipe.intrinsics_io import fit_to_camera, read_intrinsics
    from scanpipe.outpaths import check_input_file

    check_input_file(file)
    check_input_file(rig_path, "--rig")
    if out is not None:
        check_output_file(out, "--out", (".toml",), force, [file, rig_path])
        if not out.parent.is_dir():
            raise UsageError(f"--out {out}: folder {out.parent} does not exist; create it first")
    rig = load_rig(rig_path)
    if camera not in [c.id for c in rig.cameras]:
        known = ", ".join(c.id for c in rig.cameras) or "none"
        raise UsageError(f"--camera {camera!r}: not in {rig_path} (its cameras: {known})")
    before = rig.camera(camera)
    found = read_intrinsics(file, fmt, file_camera)
    values, warnings = fit_to_camera(found, before, file)
    new_rig = _with_camera_values(rig_path, camera, values, file)
    after = new_rig.camera(camera)
    changes = _changes(before.model_dump(mode="json"), after.model_dump(mode="json"))
    warnings += [w for w in camera_warnings(new_rig) if w.startswith(f"camera {camera}:")]
    if out is not None:
        try:
            atomic_write_bytes(out, rig_to_toml(new_rig).encode())
        except OSError as err:
            raise UsageError(f"--out {out}: cannot be written ({err.strerror or err})") from None
    for warning in warnings:
        sys.stderr.write(f"warning: rig intrinsics: {warning}\n")
    if as_json:
        print_json({"file": str(file), "format": found.format, "file_camera": found.camera,
                    "camera": camera, "conversions": found.notes, "changes": changes,
                    "warnings": warnings, "written": str(out) if out is not None else None})
        return
    source = f" camera {found.camera}" if found.camera else ""
    typer.echo(f"{file}: {found.format}{source} → rig camera {camera}")
    for note in found.notes:
        typer.echo(f"  {note}")
    if not changes:
        typer.echo("no change: the rig already holds these intrinsics")
    for key, (old, new) in changes.items():
        typer.echo(f"  {key:10s} {_shown(old)} → {_shown(new)}")
    if out is not None:
        typer.echo(f"wrote {out}")
    else:
        typer.echo("nothing written: pass --out NEW.toml to write the rig with these values")


def _with_camera_values(rig_path: Path, camera_id: str, values: dict[str, Any], source: Path
                        ) -> Any:
    """The rig of ``rig_path`` (its values as written) with camera ``camera_id`` updated,
    validated like a rig file (a value the rig refuses names the imported file)."""
    from scanpipe.errors import ParameterError, RigError
    from scanpipe.params import load_toml
    from scanpipe.rig import rig_from_dict

    try:
        data = load_toml(rig_path)
    except ParameterError as err:
        raise RigError(err.problems, err.source) from None
    for cam in data.get("cameras", []):
        if isinstance(cam, dict) and cam.get("id", "cam0") == camera_id:
            cam.update(values)
    try:
        return rig_from_dict(data, str(rig_path))
    except RigError as err:
        problems = "; ".join(err.problems)
        raise UsageError(f"{source}: its intrinsics do not fit camera {camera_id} of "
                         f"{rig_path}: {problems}") from None


def _changes(before: dict[str, Any], after: dict[str, Any]) -> dict[str, tuple[Any, Any]]:
    """The keys whose values differ: ``key → (old, new)``."""
    return {k: (before[k], after[k]) for k in after if before.get(k) != after[k]}


def _shown(value: Any) -> str:
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def register(app: typer.Typer) -> None:
    """Add the ``rig`` group to the main app."""
    app.add_typer(rig_app, name="rig")
