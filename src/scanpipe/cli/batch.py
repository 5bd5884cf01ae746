"""``scanpipe batch``: the chain over many recordings, in a local process pool or on Ray."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from scanpipe.batch import ENGINES, ItemResult, run_batch
from scanpipe.cli.common import JSON, PARAMS_FILE, QUIET, SET, print_json, print_warnings
from scanpipe.cli.pipeline import RECOMPUTE, TO, WAIT, pipeline_params_from_cli
from scanpipe.errors import StageError
from scanpipe.progress import rich_progress


def _print_item(result: ItemResult, quiet: bool) -> None:
    if result.ok:
        if not quiet:
            ran = sum(not s["reused"] for s in result.stages)
            sys.stderr.write(f"  {result.name:<28} ok      {ran} ran, "
                             f"{len(result.stages) - ran} reused, {result.seconds:.2f} s, "
                             f"{result.cpu_s:.2f} s CPU\n")
        for warning in result.warnings:
            stage, _, text = warning.partition(": ")
            print_warnings(f"{result.name}: {stage}", {"warnings": [text]})
    else:
        sys.stderr.write(f"  {result.name:<28} FAILED  {result.error}\n")


def batch(
    recordings: list[Path] = typer.Argument(..., help="The recordings (MCAP)."),
    workdir: Path = typer.Option(..., "--workdir", "-w",
                                 help="Folder holding one workdir per recording "
                                      "(<stem>-<hash of its path>) and batch.json."),
    engine: str = typer.Option("local", "--engine",
                               help=f"Where to run: {' or '.join(ENGINES)} (a process pool, or "
                                    "one Ray task per recording per stage)."),
    address: str | None = typer.Option(None, "--address",
                                       help="With --engine ray: the Ray cluster's address "
                                            "(default: start a local Ray)."),
    workers: int | None = typer.Option(None, "--workers", min=1,
                                       help="Recordings at once (default: the CPUs of this "
                                            "machine, or of the Ray cluster)."),
    threads: int | None = typer.Option(
        None, "--threads", min=1,
        help="Threads per worker (OpenMP, BLAS, OpenCV; on Ray the CPUs each task asks for). "
             "Default: OMP_NUM_THREADS when set, else the CPUs shared out among the workers "
             "(on Ray: 1)."),
    to: str | None = TO,
    force: bool = RECOMPUTE,
    wait_s: float = WAIT,
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Run the chain over many recordings, reusing every artifact whose key is unchanged; a
    failing recording is reported and the others finish (exit code 1 at the end)."""
    params = pipeline_params_from_cli(params_file, assignments)
    with rich_progress(quiet) as progress:
        summary = run_batch(recordings, workdir, params, engine=engine, workers=workers,
                            threads=threads,
                            address=address, to=to, force=force, lock_wait_s=wait_s,
                            progress=progress, on_item=lambda r: _print_item(r, quiet))
    if as_json:
        print_json(summary)
    elif not quiet:
        sys.stderr.write(f"{summary['recordings'] - summary['failed']} ok, "
                         f"{summary['failed']} failed, {summary['seconds']:.2f} s "
                         f"(summary: {workdir / 'batch.json'})\n")
    if summary["failed"]:
        names = [i["name"] for i in summary["items"] if not i["ok"]]
        raise StageError(f"{summary['failed']} of {summary['recordings']} recordings failed "
                         f"({', '.join(names)}); re-run the same command after fixing them: "
                         "finished stages are reused")


def register(app: typer.Typer) -> None:
    """Add ``batch`` to the main app."""
    app.command("batch")(batch)
