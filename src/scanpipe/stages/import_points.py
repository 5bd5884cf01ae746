"""Import points: another tool's point file (PLY, XYZ/CSV/PTS, LAS/LAZ, E57, PCD) to ``points``.

A stage with a raw input, like decode: the file reaches it as a path and is keyed by its
bytes. The reading and the frame conversion are :mod:`scanpipe.pointio`'s.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from scanpipe.errors import StageError
from scanpipe.pointio import ImportParams, import_points
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stage import Stage, StageResult


def import_points_stage(inputs: Mapping[str, Any], params: ImportParams,
                        progress: ProgressFn = no_progress) -> StageResult:
    """Stage function: ``inputs["point_file"]`` is the path of the point file."""
    path = inputs.get("point_file")
    if not isinstance(path, str | Path):
        raise StageError("import-points needs inputs['point_file']: the path of a point file")
    progress("import points", 0, 1)
    table, report = import_points(Path(path), params)
    progress("import points", 1, 1)
    return StageResult(tables={"points": table}, report=report)


STAGE = Stage(
    name="import-points",
    version=4,  # 4: the georeference offset travels with the points (schema.OFFSET_KEY),
    # rounded to whole kilometres (nearby files share it) or given (offset_m)
    params=ImportParams,
    inputs=("point_file",),
    outputs=("points",),
    func=import_points_stage,
    description="a point file from another tool (PLY, XYZ/CSV/PTS, LAS/LAZ, E57, PCD) → points",
    libraries=("numpy", "pyarrow", "laspy", "pye57", "open3d"),
)
