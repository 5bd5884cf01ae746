"""What every command shares: error printing, output, common options, parameter assembly."""

from __future__ import annotations

import inspect
import json
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import typer
from pydantic import BaseModel

from scanpipe.errors import UsageError
from scanpipe.params import Params, apply_assignments, load_toml, validate
from scanpipe.planning import DEFAULT_MOTOR_STEP_DEG

P = TypeVar("P", bound=Params)

QUIET = typer.Option(False, "--quiet", "-q", help="No progress display.")
JSON = typer.Option(False, "--json", help="Print one JSON object instead of a table.")
#: ``--json`` of a command whose report is always one JSON object on stdout (the single-stage
#: commands): accepted, so that a script can pass ``--json`` to every command.
JSON_ALWAYS = typer.Option(True, "--json", help="Print one JSON object (always, for this "
                                                  "command).")
SET = typer.Option(None, "--set", help="Override a parameter: key=value (repeatable).")
PARAMS_FILE = typer.Option(None, "--params", help="TOML file of parameters.")
RIG = typer.Option(None, "--rig", help="Rig TOML file (default: the paper's rig).")
FORCE = typer.Option(False, "--force", help="Overwrite existing output files.")
#: The port of ``--live`` given without one (Foxglove's default WebSocket port).
LIVE_DEFAULT_PORT = 8765
LIVE = typer.Option(None, "--live", min=0, max=65535, metavar="[PORT]",
                    help=f"Serve the scan as it grows to Foxglove (WebSocket) on PORT (default "
                         f"{LIVE_DEFAULT_PORT}; 0: any free port): the cloud so far, the platform "
                         "angle, the camera images and the events. Needs scanpipe[live].")
LIVE_HOST = typer.Option("127.0.0.1", "--live-host",
                         help="Address the live view listens on (0.0.0.0: every interface).")
MOTOR_STEP = typer.Option(DEFAULT_MOTOR_STEP_DEG, "--motor-step",
                          help="Motor step in degrees: the platform turn between profiles (the "
                               "closest achievable is used; see scanpipe plan).")


def deprecated_alias(new_flag: str, old_flag: str) -> Any:
    """A hidden option for the old spelling ``old_flag`` of ``new_flag``; see
    :func:`take_alias`."""
    return typer.Option(None, old_flag, hidden=True, help=f"Deprecated: use {new_flag}.")


def take_alias(ctx: typer.Context, new_name: str, new_value: Any, old_value: Any,
               new_flag: str, old_flag: str) -> Any:
    """The value of an option (parameter ``new_name``) that also has a deprecated spelling.

    ``old_value`` (None when the old spelling was not given) wins with a one-line deprecation
    note on stderr; both spellings at once are a usage error.
    """
    if old_value is None:
        return new_value
    source = ctx.get_parameter_source(new_name)
    if source is not None and source.name == "COMMANDLINE":
        raise UsageError(f"{old_flag} is the old name of {new_flag}: give only {new_flag}")
    sys.stderr.write(f"scanpipe: warning: {old_flag} is deprecated; use {new_flag}\n")
    return old_value


def model_flag(field_name: str) -> str:
    """The command-line spelling of a model field: kebab case, without the unit ``_deg``
    (``motor_step_deg`` → ``--motor-step``); a boolean gets its ``--no-`` form too."""
    return "--" + field_name.removesuffix("_deg").replace("_", "-")


def model_options(model: type[BaseModel], fields: Sequence[str]) -> list[inspect.Parameter]:
    """Keyword parameters of a typer command, one per field of ``model``: the field's name,
    type, default and description (the help), so that the command repeats none of them."""
    params = []
    for name in fields:
        info = model.model_fields[name]
        flag = model_flag(name)
        if info.annotation is bool:
            flag = f"{flag}/--no-{flag[2:]}"
        option = typer.Option(info.get_default(call_default_factory=True), flag,
                              help=info.description)
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY,
                                        annotation=info.annotation, default=option))
    return params


def with_model_options(model: type[BaseModel], fields: Sequence[str]) -> Callable[
        [Callable[..., Any]], Callable[..., Any]]:
    """Give a command that takes ``**values`` one option per field of ``model`` in ``fields``
    (see :func:`model_options`); typer reads the signature set here."""
    def decorate(command: Callable[..., Any]) -> Callable[..., Any]:
        own = [p for p in inspect.signature(command).parameters.values()
               if p.kind is not inspect.Parameter.VAR_KEYWORD]
        command.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
            [*own, *model_options(model, fields)])
        return command
    return decorate


def expand_optional_values(args: list[str]) -> list[str]:
    """``--live`` without a port (the next word is not a number) means the default port."""
    expanded = []
    for index, arg in enumerate(args):
        expanded.append(arg)
        if arg == "--":
            return expanded + args[index + 1:]
        if arg == "--live" and not (index + 1 < len(args) and args[index + 1].isdigit()):
            expanded.append(str(LIVE_DEFAULT_PORT))
    return expanded


@contextmanager
def live_taps(rig: Any, port: int | None, host: str, quiet: bool) -> Iterator[list[Any]]:
    """The sink taps of ``--live``: a started :class:`~scanpipe.live.LiveView` (stopped on
    exit), or none when ``port`` is None."""
    if port is None:
        yield []
        return
    from scanpipe.live import LiveView

    view = LiveView(rig, port, host)
    sys.stderr.write(f"live: serving the scan on {view.url} (Foxglove: Open connection → "
                     "Foxglove WebSocket)\n")
    try:
        yield [view]
    finally:
        view.close()
        if not quiet and (view.dropped or view.errors):
            sys.stderr.write(f"warning: live: {view.dropped} items dropped (the view fell "
                             f"behind), {view.errors} could not be shown\n")


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
