"""How many threads a piece of work may use: the one reading of ``OMP_NUM_THREADS``, and the
thread pool sized by it."""

from __future__ import annotations

import concurrent.futures as cf
import os
from collections.abc import Callable
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_T = TypeVar("_T")


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive whole number (a batch worker's share of the
    cores, or the user's own limit), else None: the caller then decides from the CPU count."""
    given = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(given) if given.isdigit() and int(given) > 0 else None


class InlineExecutor(cf.Executor):
    """A pool of one thread without the thread: each task runs when it is submitted, in the
    caller's thread, its result or exception kept in its future. The same order and results
    as ``ThreadPoolExecutor(1)`` (which runs the tasks one by one in submission order), without
    handing every task to another thread and back."""

    def submit(self, fn: Callable[_P, _T], /, *args: _P.args, **kwargs: _P.kwargs
               ) -> cf.Future[_T]:
        """Run ``fn(*args, **kwargs)`` now; its future is already done."""
        future: cf.Future[_T] = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as err:  # kept for .result(), as a pool keeps it
            future.set_exception(err)
        return future


def thread_pool(workers: int) -> cf.Executor:
    """A pool of ``workers`` threads, or with one worker the caller's own thread
    (:class:`InlineExecutor`): in a batch worker limited to one thread (``OMP_NUM_THREADS=1``)
    the texture stage's loops handed ~400 tasks per small recording to a single pool thread
    and waited on each, ~30 ms of CPU of ~600 (5 %) for nothing."""
    if workers <= 1:
        return InlineExecutor()
    return cf.ThreadPoolExecutor(max_workers=workers)
