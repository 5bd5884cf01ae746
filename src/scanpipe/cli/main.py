"""The ``scanpipe`` command: the typer app, command registration, and error handling.

A :class:`ScanpipeError` becomes one line on stderr and its exit code; a command-line usage error
one line and exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import typer

from scanpipe import __version__
from scanpipe.cli import (
    acquire,
    bag,
    batch,
    calibrate,
    capture,
    common,
    decode,
    demo,
    mesh,
    pipeline,
    plan,
    points,
    results,
    rig,
    simulate,
    site,
    texture,
    view,
)
from scanpipe.errors import ScanpipeError

app = typer.Typer(
    name="scanpipe",
    help="A 2-D laser scanner on a stepper turntable plus a camera, to a textured 3-D model.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

# Every command group, in the order `scanpipe --help` lists them.
for module in (demo, plan, rig, acquire, bag, capture, simulate, pipeline, batch, decode, points,
               calibrate, mesh, texture, results, site, view):
    module.register(app)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"scanpipe {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """scanpipe: record, simulate and process turntable laser scans."""


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the console script; returns the exit code."""
    args = common.expand_optional_values(list(sys.argv[1:] if argv is None else argv))
    try:
        result = app(args=args, prog_name="scanpipe", standalone_mode=False)
    except ScanpipeError as err:
        common.print_error(str(err))
        return err.exit_code
    except typer.Exit as err:
        return int(err.exit_code)
    except typer.TyperException as err:  # usage errors: bad option, bad value, missing argument
        formatter = getattr(err, "format_message", None)
        if type(err).__name__ == "NoArgsIsHelpError" and callable(formatter):
            # A bare `scanpipe` (or command group): its help on stdout and exit code 2, as
            # typer itself does (click vendored by typer: matched by name, not a private import).
            sys.stdout.write(str(formatter()).rstrip("\n") + "\n")
            return int(getattr(err, "exit_code", 2))
        formatter = getattr(err, "format_message", None)
        message = (formatter() if callable(formatter) else str(err)).replace("\n", " ")
        ctx = getattr(err, "ctx", None)
        hint = f" (see: {ctx.command_path} --help)" if ctx is not None else ""
        common.print_error(message + hint)
        return int(getattr(err, "exit_code", 2))
    except (typer.Abort, KeyboardInterrupt):
        common.print_error("interrupted")
        return 130
    return int(result) if isinstance(result, int) else 0


if __name__ == "__main__":
    sys.exit(main())
