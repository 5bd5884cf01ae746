"""The one output-path policy of every command that writes a file or folder the user named.

- A path is used exactly as given: nothing is appended. When a format needs a suffix and the
  path has another one, the command refuses and says which suffix it expects.
- Devices, pipes, sockets and folders are refused where a file is wanted (``/dev/full``, a
  FIFO); a file is refused where a folder is wanted.
- An existing file is replaced only with ``--force``.
- An output may never be one of the command's inputs (the same file after resolving links,
  ``os.path.samefile``), ``--force`` or not: for a folder of artifacts the inputs include the
  raw files its artifacts were made from (a workdir's recording), see :func:`folder_inputs`.

Writing itself goes through a temporary name and a rename (:func:`scanpipe.artifacts.atomic_path`),
so a failed command leaves the previous file as it was. These checks run before any slow work.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable, Sequence
from pathlib import Path

from scanpipe.errors import UsageError


def same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file (hard links and symlinks included)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def _kind(mode: int) -> str:
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a pipe (FIFO)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _label(option: str, path: Path) -> str:
    return f"{option} {path}" if option else str(path)


def _stat_mode(path: Path, label: str) -> int | None:
    """The mode of ``path`` (following links), None when it does not exist yet."""
    try:
        return path.stat().st_mode
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        blocker = next((p for p in path.parents if p.exists() and not p.is_dir()), path.parent)
        raise UsageError(f"{label}: {blocker} is a file, not a folder") from None
    except OSError as err:
        raise UsageError(f"{label}: cannot be checked ({err.strerror or err})") from None


def check_not_input(path: Path, inputs: Iterable[Path], option: str = "--out") -> None:
    """Refuse an output that is the same file as one of ``inputs``."""
    for source in inputs:
        if same_file(path, source):
            raise UsageError(f"{_label(option, path)}: is also an input of this command "
                             f"({source}); writing it would destroy what is read; choose "
                             "another path")


def check_output_file(
    path: Path,
    option: str = "--out",
    suffixes: Sequence[str] = (),
    force: bool = False,
    inputs: Iterable[Path] = (),
) -> Path:
    """Check a file path the user named for writing; returns it unchanged.

    ``suffixes`` (lower case, with the dot) are the ones the format accepts: another suffix is
    refused, no suffix is accepted as given. ``force`` allows replacing an existing regular file.
    """
    label = _label(option, path)
    suffix = path.suffix.lower()
    if suffixes and suffix and suffix not in suffixes:
        raise UsageError(f"{label}: expected a file name ending in {' or '.join(suffixes)}, "
                         f"not {suffix!r} (nothing is appended to a path)")
    mode = _stat_mode(path, label)
    if mode is not None:
        if stat.S_ISDIR(mode):
            example = f" such as {path / ('out' + suffixes[0])}" if suffixes else ""
            raise UsageError(f"{label}: is a folder; give a file name{example}")
        if not stat.S_ISREG(mode):
            raise UsageError(f"{label}: is {_kind(mode)}; give the path of a regular file")
    check_not_input(path, inputs, option)
    if mode is not None and not force:
        raise UsageError(f"{label}: already exists; pass --force to overwrite it")
    return path


def check_output_files(
    paths: Sequence[Path],
    option: str = "--out",
    force: bool = False,
    inputs: Iterable[Path] = (),
) -> None:
    """:func:`check_output_file` for every file one command writes (their suffixes are its own)."""
    sources = list(inputs)
    for path in paths:
        check_output_file(path, option, (), force, sources)


def check_output_folder(path: Path, option: str = "--out", inputs: Iterable[Path] = ()) -> Path:
    """Check a folder path for writing into: it is a folder or does not exist yet."""
    label = _label(option, path)
    mode = _stat_mode(path, label)
    if mode is not None and not stat.S_ISDIR(mode):
        what = "a file" if stat.S_ISREG(mode) else _kind(mode)
        raise UsageError(f"{label}: is {what}; give a folder")
    check_not_input(path, inputs, option)
    return path


def check_input_file(path: Path, option: str = "") -> Path:
    """A file that a command reads and rewrites in place must be a regular file."""
    label = _label(option, path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise UsageError(f"{label}: not found") from None
    except OSError as err:
        raise UsageError(f"{label}: cannot be read ({err.strerror or err})") from None
    if not stat.S_ISREG(mode):
        what = "a folder" if stat.S_ISDIR(mode) else _kind(mode)
        raise UsageError(f"{label}: is {what}; give the path of a regular file")
    return path


def folder_inputs(folder: Path) -> list[Path]:
    """What a command reading a folder of artifacts reads: the Parquet files (flat and one level
    down) and the files their provenance names as inputs (a workdir's recording)."""
    if not folder.is_dir():
        return [folder] if folder.exists() else []
    from scanpipe.workdir import all_provenance

    paths = [*folder.glob("*.parquet"), *folder.glob("*/*.parquet")]
    for record in all_provenance(folder).values():
        named = record.get("input_paths")
        if isinstance(named, dict):
            paths += [Path(p) for p in named.values() if isinstance(p, str)]
    return [p for p in paths if p.exists()]
