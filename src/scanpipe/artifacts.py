"""Parquet artifacts: atomic writes, provenance in the schema metadata, keys, checked reads.

An artifact is one Parquet file named after what it holds (``profiles.parquet``,
``points.parquet`` …). Its schema metadata carries one JSON record under
:data:`PROVENANCE_KEY`: the stage and its version, the parameters with defaults filled in, the
keys of its inputs, the library versions that change its result, times and counts, and its own
``key``, the hash of all that determines its content.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from scanpipe.errors import ArtifactError

PROVENANCE_KEY = b"scanpipe.provenance"


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
    result = {}
    for name in names:
        try:
            result[name] = version(_DISTRIBUTIONS.get(name, name))
        except PackageNotFoundError:
            result[name] = "absent"
    return result


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
    digest = hashlib.sha256()
    try:
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError as err:
        raise ArtifactError(f"{path}: cannot be read ({err.strerror or err})") from None
    return digest.hexdigest()[:24]


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


def write_artifact(path: Path, table: pa.Table, provenance: Mapping[str, Any]) -> None:
    """Write ``table`` to ``path`` atomically, with ``provenance`` in the schema metadata."""
    metadata = dict(table.schema.metadata or {})
    metadata[PROVENANCE_KEY] = canonical_json(provenance).encode()
    table = table.replace_schema_metadata(metadata)
    # Dictionary encoding of float columns costs 4–5× write time for no gain.
    dictionary_columns = [
        f.name for f in table.schema if pa.types.is_string(f.type) or pa.types.is_boolean(f.type)
    ]
    try:
        with atomic_path(path) as tmp:
            pq.write_table(table, tmp, compression="zstd", compression_level=1,
                           use_dictionary=dictionary_columns or False)
    except OSError as err:
        raise ArtifactError(f"{path}: cannot be written ({err.strerror or err})") from None


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
    path: Path, columns: Mapping[str, pa.DataType] | None = None
) -> tuple[pa.Table, dict[str, Any]]:
    """Read an artifact and its provenance; check that ``columns`` exist with those types."""
    provenance = read_provenance(path)
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as err:
        raise ArtifactError(f"{path}: not a readable Parquet file ({err})") from None
    if columns:
        check_columns(table, columns, str(path))
    return table, provenance


def check_columns(table: pa.Table, columns: Mapping[str, pa.DataType], where: str) -> None:
    """Raise :class:`ArtifactError` naming every missing column or column of the wrong type."""
    problems = []
    for name, dtype in columns.items():
        if name not in table.column_names:
            problems.append(f"missing column {name!r} ({dtype})")
        elif not table.schema.field(name).type.equals(dtype):
            problems.append(f"column {name!r} is {table.schema.field(name).type}, expected {dtype}")
    if problems:
        raise ArtifactError(f"{where}: " + "; ".join(problems))
