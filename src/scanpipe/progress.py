"""Progress reporting: the core calls a plain callback; the CLI draws it with rich on stderr."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Protocol


class ProgressFn(Protocol):
    """``progress(task, done, total)``: ``total`` is None when unknown. Must be cheap."""

    def __call__(self, task: str, done: float, total: float | None = None) -> None: ...


def no_progress(task: str, done: float, total: float | None = None) -> None:
    """A progress callback that does nothing (the default for library calls and notebooks)."""


@contextmanager
def rich_progress(quiet: bool = False) -> Iterator[ProgressFn]:
    """A progress callback drawing one rich bar per task on stderr.

    Quiet (a no-op callback) with ``quiet`` or when stderr is not a terminal.
    """
    if quiet or not sys.stderr.isatty():
        yield no_progress
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TaskID,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    bars = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(),
        console=Console(stderr=True), transient=False,
    )
    tasks: dict[str, TaskID] = {}

    def update(task: str, done: float, total: float | None = None) -> None:
        if task not in tasks:
            tasks[task] = bars.add_task(task, total=total)
        bars.update(tasks[task], completed=done, total=total)

    with bars:
        yield update
