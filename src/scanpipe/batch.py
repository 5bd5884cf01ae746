"""Batches: the chain over many recordings, one workdir each, in a process pool or on Ray.

Each recording gets its own workdir ``W/<stem>-<8 hex>`` (:func:`workdir_name`): the stem for
people, the hash of the recording's absolute path so that equal file names from different
folders never share a workdir, and a name that does not depend on the rest of the batch, so a
re-run with more or fewer recordings finds its cache. Each workdir has its own lock
(:func:`scanpipe.workdir.workdir_lock`), so workers never wait on each other.

``local`` runs :func:`scanpipe.pipeline.run_chain` per recording in a process pool of long-lived
workers limited to ``threads`` threads each (OpenMP, BLAS, OpenCV), so that workers do not fight
over the cores. On Linux the workers are forked from a *fork server* (:func:`pool_context`) that
imported the chain and its heavy libraries once: a worker then starts in milliseconds instead of
paying ~2 s of CPU for the interpreter and the imports (a spawned worker also re-imports the
command line's main module), the start is paid once per process rather than once per worker, and
a later batch in the same process (a notebook, a service, the benchmark) finds the server warm.
Elsewhere (macOS, Windows) the workers are spawned and import all of it in their initializer.
``ray`` runs one Ray task per recording per stage, in long-lived Ray workers (actors, one per
recording in flight, :class:`RecordingWorker`): a recording's stage tasks all go to one worker,
which runs them in order as one chain (:func:`scanpipe.pipeline.iter_chain`) — a stage's
outputs reach the next stage in memory and its folder is flushed and swapped in while the next
stage computes, exactly as a local worker does — and each task returns only the stage's small
record. So both engines give the same artifacts and keys, a re-run reuses them, and the workdir
must be on a file system every Ray node sees. The tasks go straight to their worker (no
scheduling by the raylet per task, no object store), which cut Ray's own CPU per stage task
from ~6 ms to a fraction. A failing recording is reported with its one-line error and the
others finish; a worker lost (its process or node died) fails the recording it ran, and a new
worker takes the rest.

Both engines start the largest recordings first (file size: a proxy for their work), so that a
long recording does not start last and leave the other workers idle at the end. Every stage
record carries its CPU seconds and the pid of the process that ran it, and the summary the
parent's CPU seconds, so that where the time goes can be read on a loaded machine too.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing as mp
import os
import re
import sys
import time
import traceback
from collections.abc import Callable, Generator, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.errors import ScanpipeError, UsageError
from scanpipe.params import Params
from scanpipe.pipeline import RunRecord, iter_chain, run_chain
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stages import chain_stages, get_stage
from scanpipe.threads import omp_threads
from scanpipe.workdir import DEFAULT_LOCK_WAIT_S

ENGINES = ("local", "ray")
RAY_INSTALL = "pip install 'scanpipe[ray]'"
#: The batch's summary, written into ``W`` at the end of every batch.
MANIFEST = "batch.json"
#: Environment variables that size the thread pools of numpy's BLAS, OpenMP (Open3D) and friends.
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class BatchItem:
    """One recording of a batch and its workdir."""

    recording: Path
    workdir: Path

    @property
    def name(self) -> str:
        """The workdir's folder name, which names the recording in messages."""
        return self.workdir.name


@dataclass
class ItemResult:
    """What the batch did for one recording."""

    name: str
    recording: str
    workdir: str
    ok: bool = True
    error: str = ""
    #: The traceback of an unexpected exception (a bug), kept in the manifest only.
    detail: str = ""
    stages: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    #: CPU seconds of the recording's work in its worker(s), every thread included.
    cpu_s: float = 0.0
    #: Worker pid → CPU seconds that worker spent starting (imports; local engine only).
    worker_start_cpu_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def workdir_name(recording: Path) -> str:
    """``<stem>-<first 8 hex of sha256(absolute path)>``, the stem reduced to ``[A-Za-z0-9._-]``."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", recording.stem).lstrip(".")[:60] or "recording"
    digest = hashlib.sha256(str(recording.resolve()).encode()).hexdigest()[:8]
    return f"{stem}-{digest}"


def plan_batch(recordings: Sequence[Path], root: Path) -> list[BatchItem]:
    """The batch's items in the given order; a recording given twice is a usage error.

    Missing recordings are not refused here: each is reported as a failed item.
    """
    if not recordings:
        raise UsageError("no recordings given")
    if root.exists() and not root.is_dir():
        raise UsageError(f"--workdir {root}: exists and is not a folder")
    items: list[BatchItem] = []
    seen: dict[Path, Path] = {}
    for recording in recordings:
        resolved = recording.resolve()
        if resolved in seen:
            raise UsageError(f"{recording}: given twice (also as {seen[resolved]})")
        seen[resolved] = recording
        items.append(BatchItem(resolved, root / workdir_name(recording)))
    return items


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    first = text[0] if text else ""
    if isinstance(err, ScanpipeError):
        return first if len(text) <= 1 else f"{first} {' '.join(t.strip() for t in text[1:])}"
    return f"internal error: {type(err).__name__}: {first}"


def _fail(result: ItemResult, err: BaseException) -> ItemResult:
    result.ok = False
    result.error = _one_line(err)
    if not isinstance(err, ScanpipeError):
        result.detail = "".join(traceback.format_exception(err))
    return result


def _record_dict(record: RunRecord, cpu_s: float, blocked_s: float | None) -> dict[str, Any]:
    """A stage as the summary shows it: ``seconds`` is the stage's own computation (wall),
    ``cpu_s`` the CPU of the whole step in its worker (cache look-up, reading and writing
    included), ``blocked_s`` the time the worker's main thread slept in the step (waiting on
    the disk or on its own helper threads; not waiting for a core: None where unknown)."""
    return {"stage": record.stage, "key": record.key, "reused": record.reused,
            "seconds": round(record.seconds, 4), "cpu_s": round(cpu_s, 4),
            "blocked_s": None if blocked_s is None else round(blocked_s, 4),
            "pid": os.getpid()}


class _Clock:
    """The CPU of this process and the time its calling thread slept, between two laps."""

    def __init__(self) -> None:
        self.cpu = time.process_time()
        self.sleep = _slept_s()

    def lap(self) -> tuple[float, float | None]:
        """(CPU seconds, seconds asleep or None) since the last lap."""
        cpu, sleep = time.process_time(), _slept_s()
        spent = (cpu - self.cpu,
                 None if sleep is None or self.sleep is None else max(0.0, sleep - self.sleep))
        self.cpu, self.sleep = cpu, sleep
        return spent


def _slept_s() -> float | None:
    """Seconds the calling thread has been neither running nor waiting for a core (Linux's
    ``/proc/thread-self/schedstat``: on-CPU and run-queue nanoseconds), counted from an
    arbitrary origin; None where the kernel does not say. Unlike wall time this does not grow
    when other processes take the cores: it is the waits a worker causes itself — flushes to
    disk, handing work to a thread and waiting for it — which idle a core when every core has
    its worker."""
    try:
        with open("/proc/thread-self/schedstat") as handle:
            on_cpu_ns, queued_ns = (int(v) for v in handle.read().split()[:2])
    except (OSError, ValueError):
        return None
    return time.perf_counter() - (on_cpu_ns + queued_ns) / 1e9


def _warnings(record: RunRecord) -> list[str]:
    if record.reused:  # a reused stage's warnings were shown when it ran
        return []
    return [f"{record.stage}: {w}" for w in record.report.get("warnings", [])]


def run_item(item: BatchItem, params: Mapping[str, Params], to: str | None = None,
             force: bool = False, lock_wait_s: float = DEFAULT_LOCK_WAIT_S) -> ItemResult:
    """The chain on one recording into its workdir; every failure is caught into the result."""
    result = ItemResult(item.name, str(item.recording), str(item.workdir))
    started = time.perf_counter()
    cpu_started = time.process_time()
    clock = _Clock()
    records: list[RunRecord] = []  # filled stage by stage: kept up to a failure

    def on_stage(record: RunRecord) -> None:
        records.append(record)
        result.stages.append(_record_dict(record, *clock.lap()))

    try:
        run_chain(item.recording, item.workdir, params, stages=_chain(to), force=force,
                  lock_wait_s=lock_wait_s, on_stage=on_stage)
    except Exception as err:  # isolate it: the batch reports it and goes on
        _fail(result, err)
    result.warnings = [w for r in records for w in _warnings(r)]
    result.seconds = round(time.perf_counter() - started, 4)
    result.cpu_s = round(time.process_time() - cpu_started, 4)
    if _WORKER_START_CPU_S is not None:
        result.worker_start_cpu_s = {str(os.getpid()): _WORKER_START_CPU_S}
    return result


def _chain(to: str | None) -> list[Any]:
    stages = list(chain_stages("recording"))
    names = [s.name for s in stages]
    if to is None:
        return stages
    if to not in names:
        raise UsageError(f"--to {to!r}: not a stage; stages: {', '.join(names)}")
    return stages[: names.index(to) + 1]


# -- local: a process pool -----------------------------------------------------------------------

#: In a local worker: the CPU seconds it spent starting (:func:`_start_worker`).
_WORKER_START_CPU_S: float | None = None


def limit_opencv_threads(threads: int) -> None:
    """OpenCV's own thread pool (it reads none of :data:`THREAD_VARS`)."""
    import cv2

    cv2.setNumThreads(threads)


#: What a worker needs before its first recording, imported once by the fork server (and by a
#: spawned worker's initializer): the chain, and what its stages import lazily (Open3D ~1 s,
#: SciPy's parts).
PRELOAD = ("scanpipe.batch", "scanpipe.stages", "open3d", "scipy.ndimage",
           "scipy.sparse.csgraph", "scipy.spatial")
#: The thread count the fork server of this process was started with (None: not started by us).
_FORKSERVER_THREADS: int | None = None


def _start_worker(threads: int) -> None:
    """Pool initializer: limit OpenCV's threads (the environment sized the others), then import
    :data:`PRELOAD` (already there in a worker forked from the fork server), so that no
    recording pays it and the stage times measure the stages."""
    global _WORKER_START_CPU_S
    import importlib

    limit_opencv_threads(threads)
    for name in PRELOAD:
        importlib.import_module(name)
    _WORKER_START_CPU_S = round(time.process_time(), 4)


def stop_pool_server() -> bool:
    """Stop this process's fork server (the next local batch starts it afresh: a *cold* start,
    as in a new ``scanpipe batch`` process); False when there is none we can stop."""
    global _FORKSERVER_THREADS
    from multiprocessing import forkserver

    stop = getattr(getattr(forkserver, "_forkserver", None), "_stop", None)
    if stop is None:
        return False
    stop()
    _FORKSERVER_THREADS = None
    return True


def pool_context(threads: int) -> mp.context.BaseContext:
    """The multiprocessing context of the local pool: ``forkserver`` preloading
    :data:`PRELOAD`, started (in the environment of :func:`_thread_env`, so its libraries size
    their thread pools for ``threads``) once per process and kept warm for later batches —
    restarted only when a batch asks for another thread count; ``spawn`` elsewhere than on
    Linux or when the server cannot be restarted."""
    global _FORKSERVER_THREADS
    # Linux only: on macOS a forked child of a process holding system frameworks (OpenCV,
    # Open3D) may crash, which is why Python spawns there by default
    if not sys.platform.startswith("linux") or "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    from multiprocessing import forkserver

    if (_FORKSERVER_THREADS is not None and threads != _FORKSERVER_THREADS
            and not stop_pool_server()):
        return mp.get_context("spawn")  # no way to restart it on this Python
    context = mp.get_context("forkserver")
    # "__main__" too (the default): else every worker re-imports the main module (the command
    # line, ~1 s) to set itself up
    context.set_forkserver_preload(["__main__", *PRELOAD])
    forkserver.ensure_running()
    _FORKSERVER_THREADS = threads
    return context


@contextmanager
def _thread_env(threads: int) -> Iterator[None]:
    """The thread variables, all ``threads``, for the workers spawned meanwhile."""
    saved = {name: os.environ.get(name) for name in THREAD_VARS}
    for name in THREAD_VARS:
        os.environ[name] = str(threads)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def worker_threads(workers: int, threads: int | None) -> int:
    """Threads per worker: ``threads``, else ``OMP_NUM_THREADS`` when the user set it, else the
    CPUs shared out among the workers (so 1 worker gets every core's threads)."""
    if threads is not None:
        return threads
    given = omp_threads()
    if given is not None:
        return given
    return max(1, (os.cpu_count() or 1) // workers)


def largest_first(items: Sequence[BatchItem]) -> list[BatchItem]:
    """The items in the order to start them: largest recording first (a missing one last)."""
    def size(item: BatchItem) -> int:
        try:
            return item.recording.stat().st_size
        except OSError:
            return -1
    return sorted(items, key=size, reverse=True)


def _run_local(items: Sequence[BatchItem], params: Mapping[str, Params], workers: int,
               threads: int | None, to: str | None, force: bool, lock_wait_s: float,
               done: Callable[[ItemResult], None]) -> None:
    per_worker = worker_threads(workers, threads)
    queue = list(reversed(largest_first(items)))
    with _thread_env(per_worker):
        while queue:
            # A worker killed by a signal breaks the pool: the items it held fail, the rest go
            # on in a new pool.
            pool = cf.ProcessPoolExecutor(workers, mp_context=pool_context(per_worker),
                                          initializer=_start_worker, initargs=(per_worker,))
            running: dict[cf.Future[ItemResult], BatchItem] = {}
            try:
                while queue or running:
                    while queue and len(running) < workers:
                        item = queue.pop()
                        running[pool.submit(run_item, item, params, to, force,
                                            lock_wait_s)] = item
                    finished, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                    for future in finished:
                        item = running.pop(future)
                        try:
                            done(future.result())
                        except cf.process.BrokenProcessPool:
                            lost = [item, *running.values()]
                            running.clear()
                            for other in lost:
                                done(_fail(ItemResult(other.name, str(other.recording),
                                                      str(other.workdir)),
                                           ScanpipeError(
                                               "the worker process died while this recording "
                                               f"ran (with {len(lost) - 1} other(s)); re-run "
                                               "the batch to retry it")))
                            raise
            except cf.process.BrokenProcessPool:
                continue
            finally:
                pool.shutdown(wait=True, cancel_futures=True)


# -- ray: one task per recording per stage, in long-lived workers --------------------------------

#: Ray's reporting that a local Ray started for a batch has no reader for (no dashboard, no
#: metrics scraper): task events (the dashboard's task view), metrics collection and export,
#: and the raylet's and GCS's event-loop statistics. Their CPU lands on the cores the stages use.
RAY_SYSTEM_CONFIG: dict[str, Any] = {"task_events_report_interval_ms": 0,
                                     "enable_metrics_collection": False,
                                     "event_stats": False}


def import_ray() -> Any:
    """The ``ray`` module, or a one-line :class:`UsageError` saying how to install it."""
    try:
        import ray
    except ImportError as err:
        raise UsageError(f"--engine ray needs Ray, which is not installed: {RAY_INSTALL}"
                         ) from err
    return ray


def start_local_ray(cpus: int | None) -> None:
    """Start a local Ray for batches with ``cpus`` CPUs (None: the machine's): no dashboard,
    no log forwarding, none of :data:`RAY_SYSTEM_CONFIG`'s reporting, no usage statistics
    (``RAY_USAGE_STATS_ENABLED=0``) and a log monitor that lists the log folder less often,
    unless the environment says otherwise."""
    import logging

    ray = import_ray()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # Ray's log monitor lists the log folder every 0.1 s while it holds fewer files than this,
    # every 0.5 s otherwise: 0.6 → 0.25 % of a core (measured); its lines go nowhere here
    os.environ.setdefault("RAY_LOG_MONITOR_MANY_FILES_THRESHOLD", "0")
    ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False,
             logging_level=logging.WARNING, _system_config=dict(RAY_SYSTEM_CONFIG))


class RecordingWorker:
    """A Ray actor (one per recording in flight) running the stage tasks of one recording at a
    time: the first task opens the recording's chain (:func:`scanpipe.pipeline.iter_chain`:
    the workdir's lock, background commits), each task runs the next stage, and the last one
    closes it (every stage folder in place, a failed commit reported). So a stage's outputs
    reach the next stage in memory and its folder is flushed and swapped in while the next
    stage computes, as in a local worker; the tasks return only small records.

    It relies on Ray running a plain (not async, max_concurrency 1) actor's tasks one after
    another on one thread: the open chain's background commits keep per-thread state across
    ``next()`` calls, so tasks spread over threads would fail the recording (an error, not a
    silent result)."""

    def __init__(self, threads: int) -> None:
        cpu_started = time.process_time()
        _start_worker(threads)
        #: CPU seconds the chain's imports took (Ray's own worker start is Ray's).
        self.start_cpu_s = round(time.process_time() - cpu_started, 4)
        self._steps: Generator[RunRecord, None, None] | None = None
        self._clock = _Clock()

    def ready(self) -> dict[str, Any]:
        """The worker's pid and start CPU, once it has started."""
        return {"pid": os.getpid(), "start_cpu_s": self.start_cpu_s}

    def _close(self) -> None:
        steps, self._steps = self._steps, None
        if steps is not None:
            with suppress(Exception):  # an abandoned chain: its own error was reported
                steps.close()

    def stage(self, name: str, last: bool, start: tuple[Any, ...] | None = None
              ) -> dict[str, Any]:
        """Run stage ``name`` of the current recording (``start``: a new recording's
        ``(item, params, stage names, force, lock_wait_s)``); ``last``: close the chain after
        it. Returns the stage's record, its warnings, or the recording's error (then the later
        tasks of the recording only say they were skipped)."""
        started, cpu_started = time.perf_counter(), time.process_time()
        out: dict[str, Any] = {"stage": name, "record": None, "warnings": [], "error": "",
                               "detail": ""}
        if start is not None:
            self._close()
            item, params, names, force, lock_wait_s = start
            self._clock = _Clock()
            self._steps = iter_chain(item.recording, item.workdir, params,
                                     [get_stage(n) for n in names], force=force,
                                     lock_wait_s=lock_wait_s)
        if self._steps is None:  # an earlier stage failed
            out.update(skipped=True, seconds=0.0, cpu_s=0.0)
            return out
        failed = ItemResult("", "", "")
        try:
            record = next(self._steps)
            if record.stage != name:  # the tasks of a recording run in the order submitted
                raise RuntimeError(f"stage task {name!r} ran stage {record.stage!r}")
            out["record"] = _record_dict(record, *self._clock.lap())
            out["warnings"] = _warnings(record)
            if last:  # waits until every stage folder is in place; raises a failed commit
                steps, self._steps = self._steps, None
                for extra in steps:
                    raise RuntimeError(f"stage {extra.stage!r} after the last stage task")
        except Exception as err:  # isolate it: the recording fails, the batch goes on
            self._close()
            _fail(failed, err)
            out.update(error=failed.error, detail=failed.detail)
        out["seconds"] = time.perf_counter() - started
        out["cpu_s"] = time.process_time() - cpu_started
        return out


@contextmanager
def ray_session(workers: int | None, address: str | None, threads: int = 1
                ) -> Iterator[Any]:
    """Ray, connected: the session already open in this process (tests), else a new one — a
    local Ray with ``workers × threads`` CPUs (:func:`start_local_ray`), or the cluster at
    ``address`` — shut down at the end."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    import logging

    try:
        if address is None:
            start_local_ray(None if workers is None else workers * threads)
        else:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    except Exception as err:  # Ray raises ConnectionError, ValueError, RuntimeError, …
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise UsageError(f"--engine ray: cannot start or reach {where}: {first}") from err
    try:
        yield ray
    finally:
        _KEPT_WORKERS.clear()  # they end with the session
        ray.shutdown()


def check_ray_threads(ray: Any, threads: int | None) -> None:
    """Refuse ``--threads`` above the CPUs of the largest live Ray node: a task asking for
    more CPUs than any node has is never scheduled, and the batch would wait for ever."""
    if threads is None:
        return
    largest = max((int(node.get("Resources", {}).get("CPU", 0)) for node in ray.nodes()
                   if node.get("Alive")), default=0)
    if threads > largest:
        raise UsageError(f"--threads {threads}: more than the {largest} CPUs of the largest Ray "
                         f"node (each task asks for --threads CPUs and could never start); "
                         f"give at most {largest}")


@dataclass
class _Actor:
    """A :class:`RecordingWorker` of the batch: its handle, and its pid and start CPU once it
    answered (``ready``: the ref of that answer until then)."""

    handle: Any
    ready: Any = None
    pid: str = ""
    start_cpu_s: float | None = None
    #: Lost while running a recording (its process or node died): not used again.
    lost: bool = False


#: The workers a batch kept for the next one (``keep_workers``): (Ray job id, threads) → them.
_KEPT_WORKERS: dict[tuple[str, int], list[_Actor]] = {}


def stop_ray_workers() -> int:
    """End the Ray workers kept by earlier batches (``run_batch(keep_workers=True)``), which
    hold their CPUs until then; returns how many there were."""
    kept = [actor for actors in _KEPT_WORKERS.values() for actor in actors]
    _KEPT_WORKERS.clear()
    if kept:
        ray = import_ray()
        for actor in kept:
            with suppress(Exception):  # gone already (the session ended)
                ray.kill(actor.handle)
    return len(kept)


@dataclass
class _InFlight:
    """A recording whose stage tasks were submitted to ``actor``."""

    item: BatchItem
    actor: _Actor
    result: ItemResult
    pending: int
    finished: bool = False


def _run_ray(items: Sequence[BatchItem], params: Mapping[str, Params], workers: int | None,
             threads: int | None, address: str | None, to: str | None, force: bool,
             lock_wait_s: float, done: Callable[[ItemResult], None],
             stage_done: Callable[[], None], keep_workers: bool) -> None:
    names = [s.name for s in _chain(to)]
    per_task = threads or 1
    with ray_session(workers, address, per_task) as ray:
        check_ray_threads(ray, threads)
        items[0].workdir.parent.mkdir(parents=True, exist_ok=True)
        limit = workers or max(1, int(ray.cluster_resources().get("CPU", 1)) // per_task)
        # each worker asks for its threads as CPUs: Ray then sets OMP_NUM_THREADS to them
        remote = ray.remote(num_cpus=per_task)(RecordingWorker)
        key = (ray.get_runtime_context().get_job_id(), per_task)
        kept = _KEPT_WORKERS.pop(key, [])
        stop_ray_workers()  # kept for another session or thread count
        # more kept than this batch uses: the spare ones wait, idle, for a later batch
        actors, spare = kept[:limit], kept[limit:]
        free: list[_Actor] = []
        starting: dict[Any, _Actor] = {}
        start_errors: list[str] = []
        for actor in actors:  # a kept worker may have died meanwhile: asked first
            actor.ready = actor.handle.ready.remote()
            starting[actor.ready] = actor

        def new_actor() -> None:
            handle = remote.remote(per_task)
            actor = _Actor(handle, handle.ready.remote())
            actors.append(actor)
            starting[actor.ready] = actor

        while len(actors) < limit:
            new_actor()
        queue = list(reversed(largest_first(items)))
        running: dict[Any, _InFlight] = {}
        try:
            while queue or running:
                while queue and free:
                    _submit(free.pop(), queue.pop(), params, names, force, lock_wait_s,
                            running)
                if not running and not starting:
                    raise UsageError("--engine ray: no Ray worker could start "
                                     f"({start_errors[-1] if start_errors else 'unknown'})")
                ready, _ = ray.wait([*running, *starting], num_returns=1)
                for ref in ready:
                    if ref in starting:
                        actor = starting.pop(ref)
                        if not _started(ray, ref, actor, free, actors, start_errors) \
                                and actor.pid and queue:
                            new_actor()  # in place of a kept one that died meanwhile
                        continue
                    flight = running.pop(ref)
                    stage_done()
                    if _stage_finished(ray, ref, flight, done, free) and queue:
                        new_actor()  # in place of the lost one (each loss fails a recording)
        finally:
            # kept: those started and idle (the batch ended normally); the others end
            keeping = ([*(a for a in actors if a.ready is None and not a.lost), *spare]
                       if keep_workers and not running else [])
            if keeping:
                _KEPT_WORKERS[key] = keeping
            for actor in [*actors, *spare]:
                if all(actor is not k for k in keeping):
                    with suppress(Exception):
                        ray.kill(actor.handle)


def _submit(actor: _Actor, item: BatchItem, params: Mapping[str, Params], names: list[str],
            force: bool, lock_wait_s: float, running: dict[Any, _InFlight]) -> None:
    """The stage tasks of one recording, all at once, to one worker (which runs them in that
    order): only the first carries the recording and the parameters."""
    flight = _InFlight(item, actor, ItemResult(item.name, str(item.recording),
                                               str(item.workdir)), len(names))
    if actor.start_cpu_s is not None:  # started in this batch: its imports, once
        flight.result.worker_start_cpu_s = {actor.pid: actor.start_cpu_s}
        actor.start_cpu_s = None
    start: tuple[Any, ...] | None = (item, params, names, force, lock_wait_s)
    for index, name in enumerate(names):
        running[actor.handle.stage.remote(name, index == len(names) - 1, start)] = flight
        start = None


def _started(ray: Any, ref: Any, actor: _Actor, free: list[_Actor], actors: list[_Actor],
             errors: list[str]) -> bool:
    """A worker answered (its start CPU to report unless it was reported already, when an
    earlier batch kept it), or failed to start or died (then it is dropped and its error
    kept: False)."""
    try:
        info = ray.get(ref)
    except Exception as err:  # Ray's: the actor could not start, or died since
        errors.append(f"{type(err).__name__}: "
                      f"{(str(err).strip().splitlines() or [''])[0]}")
        actors.remove(actor)
        with suppress(Exception):
            ray.kill(actor.handle)
        return False
    if not actor.pid:  # new: its start is this batch's
        actor.pid, actor.start_cpu_s = str(info["pid"]), info["start_cpu_s"]
    actor.ready = None
    free.append(actor)
    return True


def _stage_finished(ray: Any, ref: Any, flight: _InFlight, done: Callable[[ItemResult], None],
                    free: list[_Actor]) -> bool:
    """One stage task of ``flight`` returned: its record into the result; the last but one
    frees its worker for the next recording, the last one finishes the recording. True when
    this found the worker lost (its recordings fail; it is not used again)."""
    flight.pending -= 1
    result = flight.result
    try:
        out = ray.get(ref)
    except Exception as err:  # Ray's own failures: the worker (or its node) was lost
        actor, first_loss = flight.actor, not flight.actor.lost
        actor.lost = True
        if actor in free:  # freed for its next recording already
            free.remove(actor)
        if not flight.finished:
            first = (str(err).strip().splitlines() or [""])[0]
            result.ok = False
            result.error = (f"the Ray worker running this recording was lost "
                            f"({type(err).__name__}: {first}); re-run the batch to retry it: "
                            "finished stages are reused")
            flight.finished = True
            done(result)
        return first_loss
    if out["record"] is not None:
        result.stages.append(out["record"])
        result.warnings.extend(out["warnings"])
    result.seconds = round(result.seconds + out["seconds"], 4)
    result.cpu_s = round(result.cpu_s + out["cpu_s"], 4)
    if out["error"] and result.ok:
        result.ok, result.error, result.detail = False, out["error"], out["detail"]
    if flight.pending == 1 and not flight.finished and not flight.actor.lost:
        # its last task is running or queued: the worker's next recording queues behind it
        # now, so that the worker does not wait for the driver between recordings
        free.append(flight.actor)
    if flight.pending == 0 and not flight.finished:
        flight.finished = True
        done(result)
    return False


def workers_cpu(results: Sequence[ItemResult]) -> dict[str, float]:
    """Worker pid → CPU seconds it spent on this batch: its start (local) and its stages."""
    spent: dict[str, float] = {}
    for result in results:
        spent.update(result.worker_start_cpu_s)  # each worker's start, once
    for result in results:
        for stage in result.stages:
            pid = str(stage["pid"])
            spent[pid] = spent.get(pid, 0.0) + stage["cpu_s"]
        rest = result.cpu_s - sum(stage["cpu_s"] for stage in result.stages)
        if result.stages and rest > 0:  # the item's work outside its stages (local)
            pid = str(result.stages[-1]["pid"])
            spent[pid] += rest
    return {pid: round(value, 3) for pid, value in sorted(spent.items())}


def _check_manifest(path: Path) -> None:
    """Refuse to replace a ``batch.json`` that a batch did not write (someone's file)."""
    if not path.exists():
        return
    try:
        data = json.loads(path.read_text())
        ours = isinstance(data, dict) and {"engine", "items"} <= data.keys()
    except (OSError, UnicodeDecodeError, ValueError):
        ours = False
    if not ours:
        raise UsageError(f"{path}: exists and is not a scanpipe batch summary; use another "
                         "--workdir")


# -- the batch -----------------------------------------------------------------------------------

def run_batch(
    recordings: Sequence[Path],
    root: Path,
    params: Mapping[str, Params],
    engine: str = "local",
    workers: int | None = None,
    threads: int | None = None,
    address: str | None = None,
    to: str | None = None,
    force: bool = False,
    lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
    progress: ProgressFn = no_progress,
    on_item: Callable[[ItemResult], None] | None = None,
    keep_workers: bool = False,
) -> dict[str, Any]:
    """Run the chain over ``recordings`` into ``root/<workdir_name>/`` on ``engine``.

    ``workers``: processes (local; default the CPU count) or recordings in flight (Ray; default
    the cluster's CPUs). ``threads``: threads per worker (local: OpenMP, BLAS and OpenCV; Ray:
    the CPUs each task asks for); default: local, ``OMP_NUM_THREADS`` when set, else the CPUs
    shared out among the workers; Ray, 1. ``keep_workers`` (Ray, in a session this process
    opened before): keep the batch's Ray workers, with the chain imported, for the next batch
    with the same threads — they hold their CPUs until :func:`stop_ray_workers` or
    ``ray.shutdown()``; by default they end with the batch. Returns the summary also written to
    ``root/batch.json``: one entry per recording in the given order (``ok``, ``error``,
    per-stage keys, wall and CPU seconds), counts, wall time and the parent's CPU time.
    """
    if engine not in ENGINES:
        raise UsageError(f"--engine {engine!r}: use one of {', '.join(ENGINES)}")
    if address is not None and engine != "ray":
        raise UsageError("--address is for --engine ray")
    if workers is not None and workers < 1:
        raise UsageError(f"--workers {workers}: must be at least 1")
    if threads is not None and threads < 1:
        raise UsageError(f"--threads {threads}: must be at least 1")
    _chain(to)  # a bad --to is refused before any work
    items = plan_batch(recordings, root)
    _check_manifest(root / MANIFEST)
    if engine == "ray":
        import_ray()  # the install hint before any folder is made
    else:
        root.mkdir(parents=True, exist_ok=True)  # Ray's: once the cluster accepts the batch
    results: dict[str, ItemResult] = {}
    n_stages = len(_chain(to))
    counts = {"stages": 0}

    def done(result: ItemResult) -> None:
        results[result.name] = result
        progress("recordings", len(results), len(items))
        if on_item is not None:
            on_item(result)

    def stage_done() -> None:
        counts["stages"] += 1
        progress("stages", counts["stages"], len(items) * n_stages)

    started = time.perf_counter()
    cpu_started = time.process_time()
    progress("recordings", 0, len(items))
    pool_size = workers or os.cpu_count() or 1
    if engine == "local":
        _run_local(items, params, pool_size, threads, to, force, lock_wait_s, done)
    else:
        _run_ray(items, params, workers, threads, address, to, force, lock_wait_s, done,
                 stage_done, keep_workers)
    ordered = [results[item.name] for item in items]
    summary = {
        "engine": engine,
        "workers": workers,
        "threads": worker_threads(pool_size, threads) if engine == "local" else threads or 1,
        "address": address,
        "workdir": str(root),
        "recordings": len(items),
        "failed": sum(not r.ok for r in ordered),
        "seconds": round(time.perf_counter() - started, 3),
        "parent_cpu_s": round(time.process_time() - cpu_started, 3),
        "workers_cpu_s": workers_cpu(ordered),
        "items": [asdict(r) for r in ordered],
    }
    atomic_write_bytes(root / MANIFEST, json.dumps(summary, indent=2).encode())
    return summary
