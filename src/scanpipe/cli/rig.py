"""``scanpipe rig init|check``: write the default rig, validate a rig file."""

from __future__ import annotations

from pathlib import Path

import typer

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.cli.common import JSON, print_json
from scanpipe.errors import UsageError
from scanpipe.outpaths import check_output_file
from scanpipe.rig import default_rig, load_rig, rig_to_dict, rig_to_toml
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
    if as_json:  # valid (a bad file is the one-line error and exit code 2, as without --json)
        print_json({"path": str(path), "valid": True, "rig": rig_to_dict(rig)})
        return
    cams = ", ".join(c.id for c in rig.cameras) or "no cameras"
    typer.echo(
        f"{path}: ok — {rig.scanner.model or rig.scanner.dialect} scanner at "
        f"{rig.scanner.beam_step_deg:g}° and "
        f"{rig.scanner.scan_hz:g} Hz, motor step {rig.motor.pulse_step_deg:g}°, "
        f"pulse limit {rig.motor.pulse_limit}, {cams}"
    )


def register(app: typer.Typer) -> None:
    """Add the ``rig`` group to the main app."""
    app.add_typer(rig_app, name="rig")
