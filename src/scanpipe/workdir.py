"""Finding artifacts in a result folder: a pipeline workdir or a flat folder of artifacts.

The pipeline runner lays a workdir out as ``W/<stage>/<artifact>.parquet``; a user may also
gather artifacts in one folder. Where several stages wrote the same artifact (``points`` by
assemble and by filter), the later stage's wins.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from scanpipe.artifacts import read_provenance
from scanpipe.errors import ArtifactError

#: Stage folders in pipeline order; a later stage's artifact is preferred.
STAGE_ORDER = ("decode", "import-points", "import_points", "assemble", "filter", "mesh",
               "texture")


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
