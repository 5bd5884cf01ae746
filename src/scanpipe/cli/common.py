"""What every command shares: error printing, output, common options, parameter assembly."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, TypeVar

import typer

from scanpipe.params import Params, apply_assignments, load_toml, validate

P = TypeVar("P", bound=Params)

QUIET = typer.Option(False, "--quiet", "-q", help="No progress display.")
JSON = typer.Option(False, "--json", help="Print one JSON object instead of a table.")
SET = typer.Option(None, "--set", help="Override a parameter: key=value (repeatable).")
PARAMS_FILE = typer.Option(None, "--params", help="TOML file of parameters.")
RIG = typer.Option(None, "--rig", help="Rig TOML file (default: the paper's rig).")
FORCE = typer.Option(False, "--force", help="Overwrite existing output files.")


def print_error(message: str) -> None:
    """One error message on stderr, prefixed so that scripts can grep it."""
    sys.stderr.write(f"scanpipe: error: {message}\n")


def print_json(data: Any) -> None:
    """One JSON object on stdout."""
    sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")


def print_warnings(stage_name: str, report: dict[str, Any]) -> None:
    """A stage report's warnings on stderr, one line each (shown even with ``--quiet``)."""
    for warning in report.get("warnings", []):
        sys.stderr.write(f"warning: {stage_name}: {warning}\n")


def build_params(
    model: type[P],
    params_file: Path | None = None,
    assignments: list[str] | None = None,
    base: dict[str, Any] | None = None,
) -> P:
    """Parameters from a TOML file, then ``--set`` overrides, validated all at once."""
    data: dict[str, Any] = dict(base or {})
    source = "--set" if assignments else "parameters"
    if params_file is not None:
        data.update(load_toml(params_file))
        source = str(params_file)
    data = apply_assignments(data, assignments or [])
    return validate(model, data, source)


def run_stage_command(
    stage_name: str,
    inputs: dict[str, Path],
    out_dir: Path,
    params_file: Path | None,
    assignments: list[str] | None,
    quiet: bool,
    base: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """What every standalone stage command does: build parameters, run, print a summary.

    Always recomputes (``force``): a user who names a stage wants it run. Returns the report.
    """
    from scanpipe.pipeline import execute, get_stage
    from scanpipe.progress import rich_progress

    stage = get_stage(stage_name)
    params = build_params(stage.params, params_file, assignments, base)
    with rich_progress(quiet) as progress:
        record = execute(stage, inputs, out_dir, params, progress, force=True)
    if not quiet:
        written = ", ".join(str(p) for p in record.outputs.values())
        sys.stderr.write(f"{stage_name}: {record.seconds:.2f} s → {written}\n")
    print_warnings(stage_name, record.report)
    return record.report
