"""Parquet artifacts: atomic writes, provenance in the schema metadata, keys, checked reads.

An artifact is one Parquet file named after what it holds (``profiles.parquet``,
``points.parquet`` …). Its schema metadata carries one JSON record under
:data:`PROVENANCE_KEY`: the stage and its version, the parameters with defaults filled in, the
keys of its inputs, the library versions that change its result, times and counts, and its own
``key``, the hash of all that determines its content.

A stage's artifacts are replaced together (:func:`write_together`): everything is written and
fsynced into a staging folder under ``<folder>/.scanpipe/`` (same filesystem), then swapped in
by renames; :func:`recover` finishes or undoes what a killed writer left there. See
docs/artifacts.md for the protocol.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import hashlib
import json
import os
import shutil
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import IO, Any

import pyarrow as pa
import pyarrow.parquet as pq

from scanpipe.errors import ArtifactError
from scanpipe.schema import ArtifactSchema
from scanpipe.threads import omp_threads

PROVENANCE_KEY = b"scanpipe.provenance"

#: The hidden folder, in a workdir or an output folder, holding the lock and staging folders.
#: Two levels below the folder, so ``<folder>/*/<artifact>.parquet`` never sees staged files.
STATE_DIR = ".scanpipe"


def _file_mode() -> int:
    """What ``open()`` would give a new file: 0o666 less the umask (mkstemp gives 0o600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


#: Read once at import: changing the umask is process-wide, so not on every write.
FILE_MODE = _file_mode()

#: The distribution names behind the import names a stage may list as result-changing.
_DISTRIBUTIONS = {"cv2": "opencv-python-headless", "scanpipe": "scanpipe"}


def library_versions(names: Sequence[str]) -> dict[str, str]:
    """Installed versions of the named libraries (import names), for keys and provenance."""
    return {name: _library_version(name) for name in names}


@functools.cache
def _library_version(name: str) -> str:
    """One library's version, looked up once per process: ``importlib.metadata`` scans the
    installed distributions and parses a metadata file each time (4–7 ms of CPU per stage, 50 ms
    per small recording in a batch — 6 % of its work). A library upgraded on disk while a
    process runs is not the one that process computes with anyway: it keeps the module it
    imported, so the cached version is the one that made the result."""
    try:
        return version(_DISTRIBUTIONS.get(name, name))
    except PackageNotFoundError:
        return "absent"


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no spaces: the same data always hashes the same."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)


def artifact_key(
    stage: str,
    stage_version: int,
    params: Mapping[str, Any],
    input_keys: Mapping[str, str],
    libraries: Mapping[str, str],
) -> str:
    """The key of an artifact: a hash of everything that determines its content."""
    record = {
        "stage": stage,
        "version": stage_version,
        "params": params,
        "inputs": dict(input_keys),
        "libraries": dict(libraries),
    }
    return hashlib.sha256(canonical_json(record).encode()).hexdigest()[:24]


def file_key(path: Path) -> str:
    """The key of a raw input file: the hash of its bytes."""
    try:
        with path.open("rb") as handle:
            return stream_key(handle)
    except OSError as err:
        raise ArtifactError(f"{path}: cannot be read ({err.strerror or err})") from None


def stream_key(handle: IO[bytes]) -> str:
    """:func:`file_key` of an open file, read from its start (OSError propagates)."""
    digest = hashlib.sha256()
    handle.seek(0)
    for block in iter(lambda: handle.read(1 << 20), b""):
        digest.update(block)
    return digest.hexdigest()[:24]


@dataclass(frozen=True)
class Pieces:
    """A file's content as consecutive pieces that are never joined: a large file rendered in
    blocks (an OBJ's text) or assembled from arrays (a GLB's buffers) is held once, not once
    in pieces and again joined. Writing and hashing go piece by piece (:func:`write_file_data`,
    :func:`file_sha256`)."""

    parts: tuple[bytes | memoryview, ...]

    @property
    def nbytes(self) -> int:
        """The file's size in bytes."""
        return sum(memoryview(part).nbytes for part in self.parts)


@dataclass(frozen=True)
class Stream:
    """A file's content made piece by piece each time it is consumed, never held whole: a
    large text file (an OBJ's) is formatted block by block while it is written, and its
    digest taken on the way (:func:`write_file_data`). ``make()`` gives the pieces afresh."""

    make: Callable[[], Iterable[bytes | memoryview]]


#: A file's content: its bytes, :class:`Pieces` of them, or a :class:`Stream` (what a stage
#: hands back as :attr:`scanpipe.stage.StageResult.files` and an exporter returns).
FileData = bytes | Pieces | Stream


@dataclass(frozen=True)
class FileDigest:
    """A file's size and SHA-256 (hex)."""

    nbytes: int
    sha256: str


def file_pieces(data: FileData) -> Iterable[bytes | memoryview]:
    """The content in order, piece by piece (one piece for plain bytes; a :class:`Stream`
    makes its pieces now)."""
    if isinstance(data, Stream):
        return data.make()
    return data.parts if isinstance(data, Pieces) else (data,)


#: Pieces of a file written (and hashed) at once on their own threads while the next pieces
#: are made: a bound on the memory they hold beyond what the caller holds anyway.
PIECES_IN_FLIGHT = 4


def _consume(data: FileData, handle: IO[bytes] | None = None, hashed: bool = True
             ) -> FileDigest:
    """Hash (and write to ``handle``) the content piece by piece; ``hashed`` False: only
    write and count (the digest is then empty).

    Written to a file in several pieces, each piece is written on one thread and hashed on
    another (both release the GIL) while this thread makes the next one (a streamed OBJ is
    formatted here): the same bytes in the same order, in the time of the slowest of the
    three rather than their sum (lab export: 0.7 GB hashed and written behind 2 s of OBJ
    formatting)."""
    digest = hashlib.sha256()
    size = 0
    if handle is None or isinstance(data, bytes) or (
            isinstance(data, Pieces) and len(data.parts) < 2):
        for part in file_pieces(data):
            if hashed:
                digest.update(part)
            size += memoryview(part).nbytes
            if handle is not None:
                handle.write(part)
        return FileDigest(size, digest.hexdigest() if hashed else "")
    writer = cf.ThreadPoolExecutor(1, thread_name_prefix="write")
    hasher = cf.ThreadPoolExecutor(1, thread_name_prefix="hash") if hashed else None
    in_flight: deque[list[cf.Future[Any]]] = deque()
    try:
        for part in file_pieces(data):
            size += memoryview(part).nbytes
            # one thread each: the pieces are written, and hashed, in order
            in_flight.append([writer.submit(handle.write, part),
                              *([hasher.submit(digest.update, part)] if hasher else [])])
            while len(in_flight) > PIECES_IN_FLIGHT:
                for future in in_flight.popleft():
                    future.result()
        while in_flight:
            for future in in_flight.popleft():
                future.result()
    finally:  # on a failure (a write's OSError, a maker's error) the others finish first
        writer.shutdown(wait=True)
        if hasher is not None:
            hasher.shutdown(wait=True)
    return FileDigest(size, digest.hexdigest() if hashed else "")


def file_size(data: FileData) -> int:
    """The content's size in bytes (a :class:`Stream` is made to count it)."""
    if isinstance(data, Stream):
        return _consume(data).nbytes
    return data.nbytes if isinstance(data, Pieces) else len(data)


def file_digest(data: FileData) -> FileDigest:
    """The content's size and SHA-256, hashed piece by piece: the digest of the joined
    bytes."""
    return _consume(data)


def file_sha256(data: FileData) -> str:
    """The SHA-256 of the content (hex), hashed piece by piece: the same digest as of the
    joined bytes."""
    return _consume(data).sha256


def files_manifest(digests: Mapping[str, FileDigest]) -> pa.Table:
    """The ``export_manifest`` table of files: name, size and SHA-256 of each."""
    return pa.table({
        "file": pa.array(list(digests), pa.string()),
        "bytes": pa.array([d.nbytes for d in digests.values()], pa.int64()),
        "sha256": pa.array([d.sha256 for d in digests.values()], pa.string()),
    })


def file_bytes(data: FileData) -> bytes:
    """The content joined into one bytes object (a copy for :class:`Pieces` and
    :class:`Stream`: for small files and for reading an export in memory, not for writing
    one)."""
    return data if isinstance(data, bytes) else b"".join(file_pieces(data))


def write_file_data(handle: IO[bytes], data: FileData, hashed: bool = False) -> FileDigest:
    """Write the content to an open binary file piece by piece; its size and, with
    ``hashed``, its SHA-256 taken on the way (OSError propagates)."""
    return _consume(data, handle, hashed)


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it into place only if the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, FILE_MODE)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the whole new one."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


#: Rows per row group are chosen so a row group holds about this many bytes (of Arrow data):
#: readers decode one row group at a time, so reading an artifact peaks near its own size
#: (one 270 MB row group of camera frames took 1.4 GB to read, 16 MB ones about 360 MB).
ROW_GROUP_BYTES = 16 << 20


def row_group_rows(table: pa.Table, target_bytes: int | None = None) -> int:
    """Rows per row group for ``table``: about ``target_bytes`` (default
    :data:`ROW_GROUP_BYTES`) each, at least one row."""
    target_bytes = ROW_GROUP_BYTES if target_bytes is None else target_bytes
    rows = int(table.num_rows)
    if rows == 0:
        return 1
    per_row = max(1.0, int(table.nbytes) / rows)
    return max(1, min(rows, int(target_bytes / per_row)))


def release_free_memory() -> None:
    """Hand freed memory back to the system: Arrow's pool and the C heap (glibc's
    ``malloc_trim``) keep freed pages for reuse, so without this each stage starts from the
    previous stages' high-water marks (the lab chain's RSS between stages crept from 0.3 to
    1 GB). Costs 2–40 ms of CPU per call on the lab scan; a no-op where the calls do not
    exist. The runner calls it after each stage, a stage after releasing its inputs
    (:func:`scanpipe.stage.release_inputs`)."""
    pa.default_memory_pool().release_unused()
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is not None:
        trim(0)


@functools.cache
def _libc() -> object:
    """The process's C library (glibc's functions by name), or a plain object elsewhere."""
    import ctypes

    try:
        return ctypes.CDLL(None)
    except OSError:
        return object()


def _leaf_paths(field: pa.Field, prefix: str = "") -> list[str]:
    """The Parquet column paths of a field's leaves (a list's values are ``name.list.element``),
    as per-column writer options name them."""
    name = f"{prefix}{field.name}"
    kind = field.type
    if pa.types.is_list(kind) or pa.types.is_large_list(kind) or \
            pa.types.is_fixed_size_list(kind):
        return _leaf_paths(pa.field("element", kind.value_type), f"{name}.list.")
    if pa.types.is_struct(kind):
        return [p for i in range(kind.num_fields) for p in _leaf_paths(kind.field(i), f"{name}.")]
    return [name]


def with_provenance(table: pa.Table, provenance: Mapping[str, Any]) -> pa.Table:
    """``table`` with ``provenance`` in its schema metadata, as the artifact file holds it (no
    copy of the data): a table handed on in memory then reads as its file would."""
    metadata = dict(table.schema.metadata or {})
    metadata[PROVENANCE_KEY] = canonical_json(provenance).encode()
    return table.replace_schema_metadata(metadata)


def _write_parquet(path: Path, table: pa.Table, provenance: Mapping[str, Any]) -> None:
    """Write ``table`` to ``path`` (not atomically) with ``provenance`` in the schema metadata,
    in row groups of about :data:`ROW_GROUP_BYTES`."""
    table = with_provenance(table, provenance)
    # Dictionary encoding of float columns costs 4–5× write time for no gain.
    dictionary_columns = [
        f.name for f in table.schema if pa.types.is_string(f.type) or pa.types.is_boolean(f.type)
    ]
    # Binary columns hold encoded files (JPEG/PNG frames, textures): zstd gains nothing on
    # them and cost 1 s of CPU per 270 MB of frames.
    compression: str | dict[str, str] = "zstd"
    levels: int | dict[str, int] = 1
    if any(pa.types.is_binary(f.type) for f in table.schema):
        compression = {path: "none" if pa.types.is_binary(f.type) else "zstd"
                       for f in table.schema for path in _leaf_paths(f)}
        levels = {path: 1 for path, codec in compression.items() if codec == "zstd"}
    pq.write_table(table, path, row_group_size=row_group_rows(table), compression=compression,
                   compression_level=levels, use_dictionary=dictionary_columns or False)


def write_artifact(path: Path, table: pa.Table, provenance: Mapping[str, Any]) -> None:
    """Write ``table`` to ``path`` atomically, with ``provenance`` in the schema metadata."""
    try:
        with atomic_path(path) as tmp:
            _write_parquet(tmp, table, provenance)
    except OSError as err:
        raise ArtifactError(f"{path}: cannot be written ({err.strerror or err})") from None


def _fsync(path: Path) -> None:
    """Flush a file or a folder to disk (a folder: the names in it)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: Threads flushing one stage's staged files at once (waiting on the disk, not computing).
FLUSH_THREADS = 8


class _Flushes:
    """The fsyncs of a staged set, run concurrently on a few threads while the next file is
    written: the file system commits concurrent flushes together, so a stage's n files and
    its folder cost about one disk round trip instead of n + 1 in a row (measured on this
    machine's ext4: 4 files and their folder 30 ms one after the other, 5.5 ms at once). The
    same flushes as before, all finished before the set is swapped in (:meth:`wait`)."""

    def __init__(self) -> None:
        self._pool: cf.ThreadPoolExecutor | None = None
        self._pending: list[tuple[Path, cf.Future[None]]] = []
        #: The path whose flush failed (for the error message), once :meth:`wait` raised.
        self.failed: Path | None = None

    def start(self, path: Path) -> None:
        """Flush ``path`` (a written, closed file, or a folder) in the background."""
        if self._pool is None:
            self._pool = cf.ThreadPoolExecutor(FLUSH_THREADS, thread_name_prefix="fsync")
        self._pending.append((path, self._pool.submit(_fsync, path)))

    def wait(self) -> None:
        """Wait for every flush started; the first failure's OSError is raised (its path in
        :attr:`failed`)."""
        pending, self._pending = self._pending, []
        for path, future in pending:
            try:
                future.result()
            except OSError:
                self.failed = path
                raise

    def close(self) -> None:
        """Wait for every flush (failed or not) and stop the threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def write_together(
    out_dir: Path,
    stage: str,
    tables: Mapping[str, tuple[pa.Table, Mapping[str, Any]]],
    files: Mapping[str, FileData],
    replace_folder: bool,
    manifest: tuple[str, Mapping[str, Any]] | None = None,
    now: bool = False,
) -> pa.Table | None:
    """Write a stage's artifacts (``name.parquet``) and extra files (bytes, :class:`Pieces` or
    a :class:`Stream`, written piece by piece) so that they replace the previous set together;
    on any error the previous set is kept.

    ``manifest``: (artifact name, provenance) of a :func:`files_manifest` of the files, their
    sizes and digests taken while they are written (a streamed file is made once); it is
    written with the tables and returned.

    ``replace_folder``: ``out_dir`` belongs to the stage (``W/<stage>/`` of a workdir) and is
    replaced as a whole by two renames, so a reader sees the old set, the new set, or (for the
    instant between the renames) no folder — never a mix. Otherwise ``out_dir`` is a shared flat
    folder: the staged set is committed by one rename, then each file is renamed into place; a
    writer killed in between is completed by :func:`recover` before the next write.
    The caller holds the folder's lock (:func:`scanpipe.workdir.workdir_lock`).
    """
    commits = _STATE.commits
    if (replace_folder and not now and commits and commits[-1].encode and not files
            and manifest is None):
        # tables only: encoded and written by the committer too (see background_commits)
        commits[-1].submit_job(out_dir, lambda: write_together(
            out_dir, stage, tables, files, replace_folder, manifest, now=True))
        return None
    owner = out_dir.parent if replace_folder else out_dir
    state = owner / STATE_DIR
    staging = state / f"tmp-{stage}-{os.getpid()}"
    table_names = [*tables, *([manifest[0]] if manifest else [])]
    names = [*(f"{name}.parquet" for name in table_names), *files]
    commit = state / f"commit-{stage}-{os.getpid()}"
    for file_name in [] if replace_folder else names:
        if (out_dir / file_name).is_dir():
            raise ArtifactError(f"{out_dir / file_name}: is a folder; the {stage} output of "
                                "that name cannot replace it")
    where = out_dir
    made = None
    flushes = _Flushes()
    try:
        if staging.exists():
            shutil.rmtree(staging)
        staging.mkdir(parents=True)
        digests: dict[str, FileDigest] = {}
        for file_name, data in files.items():
            where = out_dir / file_name
            (staging / file_name).parent.mkdir(parents=True, exist_ok=True)
            with (staging / file_name).open("wb") as handle:
                digests[file_name] = write_file_data(handle, data, hashed=manifest is not None)
            flushes.start(staging / file_name)
        to_write = dict(tables)
        if manifest is not None:
            made = files_manifest(digests)
            to_write[manifest[0]] = (made, {**manifest[1], "rows": made.num_rows})
        for name, (table, provenance) in to_write.items():
            where = out_dir / f"{name}.parquet"
            _write_parquet(staging / f"{name}.parquet", table, provenance)
            flushes.start(staging / f"{name}.parquet")
        where = out_dir
        flushes.start(staging)  # its names: every file is in it by now
        if replace_folder and commits and not now:  # finished in the background, in order
            commits[-1].submit(out_dir, stage, staging, flushes,
                                state / f"old-{stage}-{os.getpid()}")
            flushes = _Flushes()  # the committer owns the pending ones now
            return made
        flushes.wait()
        if replace_folder:
            _swap_folder(staging, out_dir, state / f"old-{stage}-{os.getpid()}")
            return made
        os.rename(staging, commit)  # the commit point: from here on the new set wins
    except OSError as err:
        flushes.close()
        if flushes.failed is not None:  # name the file, as out_dir / its name
            where = out_dir / flushes.failed.relative_to(staging)
        shutil.rmtree(staging, ignore_errors=True)
        raise ArtifactError(f"{where}: cannot be written ({err.strerror or err}); the previous "
                            f"{stage} artifacts are kept") from None
    except BaseException:  # a streamed file's maker failed: nothing half-made stays
        flushes.close()
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finally:
        flushes.close()
    try:
        _fsync(state)
        _roll_forward(commit, out_dir)
    except OSError as err:
        raise ArtifactError(f"{out_dir}: replacing the {stage} artifacts was interrupted "
                            f"({err.strerror or err}); the next scanpipe command writing there "
                            "completes it") from None
    return made


def _swap_folder(staging: Path, target: Path, aside: Path) -> None:
    """Replace folder ``target`` by ``staging``: old aside, new in, old deleted."""
    if aside.exists():
        shutil.rmtree(aside)
    had_old = os.path.lexists(target)
    if had_old:
        os.rename(target, aside)
    try:
        os.rename(staging, target)
    except OSError:
        if had_old:
            os.rename(aside, target)
        raise
    # The swap is done; failing to flush the folder or delete the old set does not undo it.
    if _STATE.deferred:
        _STATE.deferred[-1].start(target.parent)
    else:
        with suppress(OSError):
            _fsync(target.parent)
    shutil.rmtree(aside, ignore_errors=True)


class _ChainState(threading.local):
    """The :func:`background_commits` in effect in the calling thread (each thread its own:
    a library caller may run chains on two workdirs in two threads at once, and each chain's
    sets must be committed, and in place, by the time its own block ends)."""

    def __init__(self) -> None:
        #: The innermost block's (a stack: they may nest) flushes after a swap; in a
        #: committer's thread, its block's.
        self.deferred: list[_Flushes] = []
        #: The innermost block's committer: where staged stage folders go.
        self.commits: list[_Committer] = []


_STATE = _ChainState()


def _defer_flushes(flushes: _Flushes) -> None:
    """Make the calling thread's swaps defer the workdir's flush to ``flushes``."""
    _STATE.deferred.append(flushes)


class _Committer:
    """One thread that finishes a chain's staged stage folders in the order they were staged:
    waits for each set's flushes, then swaps it in (:func:`_swap_folder`). After a failure the
    later sets are dropped (their staging folders deleted) and :meth:`settle` raises it."""

    def __init__(self, encode: bool, deferred: _Flushes) -> None:
        # the swaps on this thread defer the workdir's flush to the block's flushes
        self._pool = cf.ThreadPoolExecutor(1, thread_name_prefix="commit",
                                           initializer=_defer_flushes, initargs=(deferred,))
        self._pending: list[cf.Future[None]] = []
        self._failed: BaseException | None = None
        #: The stage folders staged (or to be written) and not yet swapped in.
        self.waiting: set[Path] = set()
        #: Whether a stage's tables are encoded and written here too (:meth:`submit_job`).
        self.encode = encode

    def submit_job(self, out_dir: Path, write: Callable[[], object]) -> None:
        """Write and swap in ``out_dir``'s set (``write`` does it all, as
        :func:`write_together` does in place) after the sets submitted before."""
        self.waiting.add(out_dir)

        def job() -> None:
            try:
                if self._failed is None:
                    write()
            except BaseException as err:  # an ArtifactError naming the file, or a bug
                self._failed = err
            finally:
                self.waiting.discard(out_dir)

        self._pending.append(self._pool.submit(job))

    def submit(self, out_dir: Path, stage: str, staging: Path, flushes: _Flushes,
               aside: Path) -> None:
        """Finish the set staged in ``staging`` for ``out_dir`` after those staged before."""
        self.waiting.add(out_dir)

        def commit() -> None:
            try:
                if self._failed is not None:
                    shutil.rmtree(staging, ignore_errors=True)
                    return
                try:
                    flushes.wait()
                    _swap_folder(staging, out_dir, aside)
                except OSError as err:
                    where = (out_dir if flushes.failed is None
                             else out_dir / flushes.failed.relative_to(staging))
                    shutil.rmtree(staging, ignore_errors=True)
                    self._failed = ArtifactError(
                        f"{where}: cannot be written ({err.strerror or err}); the previous "
                        f"{stage} artifacts are kept")
                except BaseException as err:  # a bug: kept as it is
                    shutil.rmtree(staging, ignore_errors=True)
                    self._failed = err
            finally:
                flushes.close()
                self.waiting.discard(out_dir)

        self._pending.append(self._pool.submit(commit))

    def raise_failure(self) -> None:
        """Raise a failure already met (without waiting for the sets still pending): a chain
        stops at its next stage instead of computing on for nothing."""
        if self._failed is not None:
            self.settle()

    def settle(self) -> None:
        """Wait until every set submitted is in place (or dropped); raise the first failure."""
        pending, self._pending = self._pending, []
        for future in pending:
            future.result()
        failed, self._failed = self._failed, None
        if failed is not None:
            raise failed

    def close(self) -> None:
        """Settle and stop the thread."""
        try:
            self.settle()
        finally:
            self._pool.shutdown(wait=True)


def settle_commits() -> None:
    """Wait until every stage folder staged in the innermost :func:`background_commits` is in
    place, raising the first failure (an :class:`ArtifactError` naming the file); a no-op
    outside one. Call it before reading a file a stage of the chain may still be committing."""
    if _STATE.commits:
        _STATE.commits[-1].settle()


def raise_commit_failure() -> None:
    """Raise a failed commit of the innermost :func:`background_commits` met so far (an
    :class:`ArtifactError` naming the file), without waiting for the sets still pending; a
    no-op outside one or when none failed. A chain calls it before each stage."""
    if _STATE.commits:
        _STATE.commits[-1].raise_failure()


def committing(path: Path) -> bool:
    """Whether ``path`` lies in a stage folder staged and not yet swapped in."""
    commits = _STATE.commits
    return bool(commits) and any(path.is_relative_to(d) for d in set(commits[-1].waiting))


@contextmanager
def background_commits() -> Iterator[None]:
    """While in effect in the calling thread (each thread its own), a stage folder it stages
    with :func:`write_together` (``replace_folder``) is flushed and swapped in by a background
    thread, in staging order, while the caller goes on to the next stage — a set of tables
    only is also encoded and written there when the process may use more than one thread
    (:func:`scanpipe.threads.omp_threads`; the tables are then held until written) — and
    the workdir's flush after each swap runs in the background.
    Every set is in place, and every flush done, when the block ends; a failed commit is
    raised there (or by :func:`settle_commits`), the later sets dropped.

    The disk's flushes then overlap the next stage's computation instead of idling the
    process (in a batch worker, a core): the same flushes, each set still flushed before it is
    swapped in, so a reader, a crash and :func:`recover` see exactly what they saw. The caller
    holds the workdir's lock for the whole block, hands the next stage its inputs in memory
    with their keys, and calls :func:`settle_commits` before reading a file still being
    committed (:func:`committing`) — the runner's chain does all of this."""
    flushes = _Flushes()
    # a stage's tables are encoded in the background too, unless the process is limited to
    # one thread (a batch worker's share of one core: a second busy thread would take the
    # other workers' core)
    committer = _Committer((omp_threads() or os.cpu_count() or 1) > 1, flushes)
    _STATE.deferred.append(flushes)
    _STATE.commits.append(committer)
    failing = True
    try:
        yield
        failing = False
    finally:
        _STATE.commits.remove(committer)
        try:
            committer.close()
        except BaseException:
            if not failing:  # else the block's own exception goes on
                raise
        finally:
            _STATE.deferred.remove(flushes)
            with suppress(OSError):  # as the flush in place: the swap is done either way
                flushes.wait()
            flushes.close()


def _roll_forward(commit: Path, out_dir: Path) -> None:
    """Rename every file of a committed staging folder into ``out_dir``, then remove it."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for path in sorted(commit.rglob("*")):
        if path.is_file():
            target = out_dir / path.relative_to(commit)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
    _fsync(out_dir)
    shutil.rmtree(commit)


def recover(owner: Path) -> None:
    """Finish or undo what a killed :func:`write_together` left in ``owner/.scanpipe/``.

    Incomplete staging folders (``tmp-*``) are deleted; committed ones (``commit-*``) are rolled
    forward into ``owner``; a stage folder moved aside (``old-<stage>-*``) goes back to
    ``owner/<stage>`` if the new one never arrived, else it is deleted. Call it holding the
    folder's lock, before deciding what is reusable.
    """
    state = owner / STATE_DIR
    try:
        # the sets this process is committing in the background, taken before the listing
        # (a set leaves it only once its entries are gone; none joins it meanwhile)
        busy = set(_STATE.commits[-1].waiting) if _STATE.commits else set()
        entries = sorted(state.iterdir()) if state.is_dir() else []
        for entry in entries:
            kind, _, rest = entry.name.partition("-")
            name, _, pid = rest.rpartition("-")
            if pid == str(os.getpid()) and owner / name in busy:
                # not every entry of this pid: a restarted container runs scanpipe under the
                # same pid, and what its killed run left is recovered as any other
                continue
            if kind == "tmp":
                shutil.rmtree(entry)
            elif kind == "commit":
                _roll_forward(entry, owner)
            elif kind == "old":
                target = owner / name
                if os.path.lexists(target):
                    shutil.rmtree(entry)
                else:
                    os.rename(entry, target)
    except OSError as err:
        raise ArtifactError(f"{state}: cannot clean up after an interrupted write "
                            f"({err.strerror or err})") from None


def read_provenance(path: Path) -> dict[str, Any]:
    """The provenance record of an artifact ({} for a Parquet file written elsewhere)."""
    try:
        schema = pq.read_schema(path)
    except FileNotFoundError:
        raise ArtifactError(f"{path}: not found") from None
    except (OSError, pa.ArrowException) as err:
        raise ArtifactError(f"{path}: not a readable Parquet file ({err})") from None
    raw = (schema.metadata or {}).get(PROVENANCE_KEY)
    if raw is None:
        return {}
    try:
        record = json.loads(raw)
    except ValueError:
        raise ArtifactError(f"{path}: provenance metadata is not valid JSON") from None
    return record if isinstance(record, dict) else {}


def read_artifact(
    path: Path, schema: ArtifactSchema | None = None
) -> tuple[pa.Table, dict[str, Any]]:
    """Read an artifact and its provenance; check it against ``schema`` when given."""
    provenance = read_provenance(path)
    try:
        # Row group by row group (no pre-buffering of the whole file): the peak stays near
        # the table's own size. On this thread: Arrow's allocator (mimalloc) gives back the
        # pages of a released table only from the heap of the thread that allocated them
        # (release_free_memory runs here), so a table read by Arrow's worker threads stayed
        # resident after a stage released it, in some runs (the same CPU either way).
        table = pq.read_table(path, pre_buffer=False, use_threads=False)
    except (OSError, pa.ArrowException) as err:
        raise ArtifactError(f"{path}: not a readable Parquet file ({err})") from None
    if schema is not None:
        schema.check(table, where=str(path))
    return table, provenance
