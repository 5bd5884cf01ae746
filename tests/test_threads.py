"""The thread pool sized by a worker's share of the cores: one thread means the caller's own."""

from __future__ import annotations

import concurrent.futures as cf
import threading

import pytest

from scanpipe.threads import InlineExecutor, thread_pool


def test_one_worker_runs_in_the_callers_thread_in_order() -> None:
    seen: list[tuple[int, int | None]] = []

    def task(i: int) -> int:
        seen.append((i, threading.get_ident()))
        return i * i

    with thread_pool(1) as pool:
        assert isinstance(pool, InlineExecutor)
        assert list(pool.map(task, range(5))) == [0, 1, 4, 9, 16]
        future = pool.submit(task, 7)
        assert future.done() and future.result() == 49
    assert seen == [(i, threading.get_ident()) for i in (0, 1, 2, 3, 4, 7)]


def test_a_failing_task_raises_where_its_result_is_taken() -> None:
    def task(i: int) -> int:
        if i == 2:
            raise ValueError(f"bad {i}")
        return i

    for workers in (1, 2):
        with thread_pool(workers) as pool:
            future = pool.submit(task, 2)
            with pytest.raises(ValueError, match="bad 2"):
                future.result()
            with pytest.raises(ValueError, match="bad 2"):
                list(pool.map(task, range(4)))


def test_more_workers_are_threads() -> None:
    with thread_pool(2) as pool:
        assert isinstance(pool, cf.ThreadPoolExecutor)
        assert pool.submit(threading.get_ident).result() != threading.get_ident()
