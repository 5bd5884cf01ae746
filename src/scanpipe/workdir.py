"""Result folders: finding artifacts in a pipeline workdir or a flat folder, and locking one.

The pipeline runner lays a workdir out as ``W/<stage>/<artifact>.parquet``; a user may also
gather artifacts in one folder. Where several stages wrote the same artifact (``points`` by
assemble and by filter), the later stage's wins.

One writer at a time: :func:`workdir_lock` holds ``fcntl.flock`` on ``W/.scanpipe/lock``. The
kernel releases it when its process dies, so a crash never leaves a lock to clean up.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from scanpipe.artifacts import FILE_MODE, STATE_DIR, read_provenance
from scanpipe.errors import ArtifactError
from scanpipe.stages import registry

#: How long a writer waits for another one on the same workdir before giving up.
DEFAULT_LOCK_WAIT_S = 600.0
LOCK_FILE = "lock"
_POLL_S = 0.05

#: Locks this process holds, by real path, with how many times each is entered.
_held: dict[str, int] = {}


def _notice(message: str) -> None:
    sys.stderr.write(f"scanpipe: {message}\n")


def lock_root(out_dir: Path, replace_folder: bool = False) -> Path:
    """The folder whose lock guards writes into ``out_dir``: its workdir when ``out_dir`` is a
    stage folder (``replace_folder``, or its parent already holds a lock), else ``out_dir``."""
    parent = out_dir.parent
    if replace_folder or (parent / STATE_DIR / LOCK_FILE).is_file():
        return parent
    return out_dir


def _holder(fd: int) -> str:
    """Who holds the lock, from what the holder wrote into the lock file."""
    try:
        record = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return (f"pid {record['pid']} ({record['command']}, since {record['since']})"
                if isinstance(record, dict) else "another process")
    except (OSError, ValueError, KeyError):
        return "another process"


@contextmanager
def workdir_lock(root: Path, wait_s: float = DEFAULT_LOCK_WAIT_S,
                 notice: Callable[[str], None] = _notice) -> Iterator[None]:
    """Hold the write lock of ``root`` (re-entrant within a process).

    Another holder: say so once through ``notice`` and wait up to ``wait_s`` seconds, then
    raise :class:`ArtifactError` naming the folder and the holder's pid (``wait_s=0`` refuses
    at once). A holder that died released the lock with its process: it is simply taken.
    """
    state = root / STATE_DIR
    try:
        state.mkdir(parents=True, exist_ok=True)
        real = os.path.realpath(state)
        fd = -1 if real in _held else os.open(state / LOCK_FILE, os.O_RDWR | os.O_CREAT,
                                                FILE_MODE)
    except OSError as err:
        raise ArtifactError(f"{root}: cannot create the workdir lock "
                            f"({err.strerror or err})") from None
    if fd < 0:  # this process holds it already (run_chain, then execute)
        _held[real] += 1
        try:
            yield
        finally:
            _held[real] -= 1
        return
    try:
        _acquire(fd, root, wait_s, notice)
        command = " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
        record = {"pid": os.getpid(), "command": command[:300],
                  "since": dt.datetime.now().isoformat(timespec="seconds")}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(record).encode(), 0)
        except OSError:
            pass  # the record only feeds messages; the lock itself is held
        _held[real] = 1
        try:
            yield
        finally:
            del _held[real]
    finally:
        os.close(fd)  # releases the flock


def _acquire(fd: int, root: Path, wait_s: float, notice: Callable[[str], None]) -> None:
    deadline = time.monotonic() + wait_s
    told = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            pass
        except OSError as err:
            raise ArtifactError(f"{root}: cannot lock the workdir "
                                f"({err.strerror or err})") from None
        if time.monotonic() >= deadline:
            raise ArtifactError(
                f"{root}: in use by {_holder(fd)}; gave up after {wait_s:g} s (wait for it to "
                "finish or use another workdir)")
        if not told:
            notice(f"waiting for {root}: in use by {_holder(fd)} (up to {wait_s:g} s)")
            told = True
        time.sleep(_POLL_S)

#: Stage folders in pipeline order (the registry's); a later stage's artifact is preferred.
STAGE_ORDER: tuple[str, ...] = tuple(registry())


def find_artifact(root: Path, name: str) -> Path | None:
    """The path of artifact ``name`` under ``root`` (flat or per-stage), or None."""
    if not root.is_dir():
        raise ArtifactError(f"{root}: not a folder of artifacts")
    flat = root / f"{name}.parquet"
    if flat.is_file():
        return flat
    candidates = sorted(root.glob(f"*/{name}.parquet"))
    if not candidates:
        return None

    def rank(path: Path) -> tuple[int, str]:
        stage = path.parent.name
        return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else -1, stage)

    return max(candidates, key=rank)


def find_artifacts(root: Path, names: tuple[str, ...]) -> dict[str, Path]:
    """Every artifact of ``names`` found under ``root``."""
    found = {name: find_artifact(root, name) for name in names}
    return {name: path for name, path in found.items() if path is not None}


def all_provenance(root: Path) -> dict[str, dict[str, Any]]:
    """Provenance of every artifact under ``root`` (flat and one level down), keyed by a
    relative path; files without provenance are skipped."""
    records: dict[str, dict[str, Any]] = {}
    for path in sorted([*root.glob("*.parquet"), *root.glob("*/*.parquet")]):
        try:
            record = read_provenance(path)
        except ArtifactError:
            continue
        if record:
            records[str(path.relative_to(root))] = record
    return records
