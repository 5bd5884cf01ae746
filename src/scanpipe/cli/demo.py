"""``scanpipe demo``: simulate the built-in room and build everything from it."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from scanpipe.cli.common import JSON, PARAMS_FILE, QUIET, SET, build_params, print_json
from scanpipe.demo import DemoOptions, run_demo
from scanpipe.progress import rich_progress


def demo(
    out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="Folder for everything."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Simulate the built-in room, run the whole pipeline, export, render, evaluate, report."""
    options = build_params(DemoOptions, params_file, assignments)
    started = time.perf_counter()

    def say(text: str) -> None:
        if not quiet:
            sys.stderr.write(f"{text}\n")

    with rich_progress(quiet) as progress:
        result = run_demo(out, options, progress, say)
    e = result.evaluation
    if as_json:
        print_json({"out": str(out), "seconds": time.perf_counter() - started,
                    "files": {k: str(v) for k, v in result.files.items()},
                    "stage_seconds": result.seconds, "evaluation": e})
        return

    def metric(key: str, scale: float = 1.0, unit: str = "", digits: int = 1) -> str:
        value = e.get(key)
        return "n/a" if value is None else f"{value * scale:.{digits}f}{unit}"

    lines = [
        f"demo finished in {time.perf_counter() - started:.0f} s → {out}",
        *[f"  {name}" for name in result.files],
        f"points RMS to truth {metric('points_rms_m', 1000, ' mm')}, "
        f"mesh mean {metric('mesh_mean_m', 1000, ' mm')}, "
        f"completeness {metric('completeness', 100, ' %')}, "
        f"precision {metric('precision', 100, ' %')}, "
        f"texture PSNR {metric('texture_psnr_db', 1, ' dB')}",
        f"open {out / 'report.html'} in a browser, {out / 'model.obj'} in MeshLab or Blender",
    ]
    typer.echo("\n".join(lines))


def register(app: typer.Typer) -> None:
    """Add ``demo`` to the main app."""
    app.command("demo")(demo)
