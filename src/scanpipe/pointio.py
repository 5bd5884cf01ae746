"""Import point clouds from other tools into a ``points`` artifact (without a grid).

Formats, by file extension:

- ``.ply``: through Open3D (binary or ASCII; vertex colours are kept).
- ``.xyz``, ``.txt``, ``.csv``, ``.pts``: text, one point a line, separated by commas,
  semicolons or white space. With a header line (any non-numeric token) the columns are found
  by name (``x, y, z`` and ``red, green, blue`` or ``r, g, b``; case and a leading ``//`` are
  ignored); without one the first three columns are x, y, z and, when the next three hold only
  integers in 0–255, they are the colour.
- ``.las``, ``.laz``: through laspy (LAZ with lazrs); 16-bit colours become 8-bit.

LAS is z-up; scanpipe's rig frame is y-up, so a z-up file maps as ``(x, y, z) → (x, z, −y)``,
the inverse of the export's ``(x, y, z) → (x, −z, y)``. ``up = auto`` treats LAS/LAZ as z-up
and the rest as y-up. Every point gets ``profile = sample = −1`` (no grid), the sensor origin
given (default the rig origin), ``range_m`` and the angles ``α, β`` of its direction from that
origin by inverting the paper's eq. 14–16, and ``time_ns`` 0.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import ArtifactError, UsageError
from scanpipe.params import Params

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
SUFFIXES = (".ply", *TEXT_SUFFIXES, ".las", ".laz")


class ImportParams(Params):
    """How a foreign point cloud enters the rig frame."""

    origin_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="sensor origin of every point, in the rig frame")
    up: Literal["auto", "y", "z"] = Field(
        "auto", description="the file's up axis; auto = z for LAS/LAZ, y otherwise")


def read_point_file(path: Path) -> tuple[F64, U8 | None, bool]:
    """Points ``(N, 3)`` float64, colours ``(N, 3)`` uint8 or None, and whether it is z-up."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise UsageError(f"{path}: unknown point file type {suffix!r}; "
                         f"allowed: {', '.join(SUFFIXES)}")
    if not path.is_file():
        raise UsageError(f"{path}: not found")
    if suffix == ".ply":
        return (*_read_ply(path), False)
    if suffix in (".las", ".laz"):
        return (*_read_las(path), True)
    return (*_read_text(path), False)


def _read_ply(path: Path) -> tuple[F64, U8 | None]:
    import open3d as o3d

    with path.open("rb") as handle:
        if handle.read(3) != b"ply":
            raise ArtifactError(f"{path}: not a PLY file (no 'ply' magic)")
    cloud = o3d.io.read_point_cloud(str(path), format="ply")  # type: ignore[arg-type]
    points = np.asarray(cloud.points, dtype=np.float64)
    if points.size == 0:
        raise ArtifactError(f"{path}: no vertices could be read from this PLY file")
    colours = None
    if cloud.has_colors():
        colours = np.clip(np.rint(np.asarray(cloud.colors) * 255), 0, 255).astype(np.uint8)
    return points, colours


def _read_las(path: Path) -> tuple[F64, U8 | None]:
    import laspy

    try:
        las = laspy.read(str(path))
    except (laspy.LaspyException, OSError, ValueError) as err:
        raise ArtifactError(f"{path}: not a readable LAS/LAZ file ({err})") from err
    points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    colours = None
    names = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=1)
        # LAS stores 16-bit colour; some writers put 8-bit values there anyway.
        colours = (rgb >> 8 if rgb.max(initial=0) > 255 else rgb).astype(np.uint8)
    return points.astype(np.float64), colours


_NAMES = {"x": ("x",), "y": ("y",), "z": ("z",), "red": ("red", "r"), "green": ("green", "g"),
          "blue": ("blue", "b")}


def _read_text(path: Path) -> tuple[F64, U8 | None]:
    try:
        with path.open("r", encoding="utf-8", errors="strict") as handle:
            first = handle.readline()
    except (OSError, UnicodeDecodeError) as err:
        raise ArtifactError(f"{path}: not a readable text point file ({err})") from err
    delimiter = "," if "," in first else ";" if ";" in first else None
    tokens = [t.strip() for t in (first.split(delimiter) if delimiter else first.split())]
    header = not all(_is_number(t) for t in tokens if t)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": below
            data = np.loadtxt(path, delimiter=delimiter, skiprows=1 if header else 0, ndmin=2,
                              dtype=np.float64, comments="#")
    except ValueError as err:
        raise ArtifactError(f"{path}: not a table of numbers ({err})") from err
    if data.shape[0] == 0:
        raise ArtifactError(f"{path}: no points")
    if header:
        names = [re.sub(r"^//", "", t).strip().lower() for t in tokens]
        columns = {key: next((names.index(a) for a in aliases if a in names), None)
                   for key, aliases in _NAMES.items()}
        missing = [k for k in "xyz" if columns[k] is None]
        if missing:
            raise ArtifactError(f"{path}: header has no column {', '.join(missing)} "
                                f"(found: {', '.join(names)})")
        xyz_index = [columns[k] for k in "xyz"]
        rgb_index = [columns[k] for k in ("red", "green", "blue")]
    else:
        if data.shape[1] < 3:
            raise ArtifactError(f"{path}: {data.shape[1]} columns; need at least x, y, z")
        xyz_index, rgb_index = [0, 1, 2], [3, 4, 5] if data.shape[1] >= 6 else [None]
    points = data[:, [int(i) for i in xyz_index if i is not None]]
    colours = None
    if all(i is not None for i in rgb_index):
        rgb = data[:, [int(i) for i in rgb_index if i is not None]]
        if header or (np.all(rgb == np.round(rgb)) and rgb.min() >= 0 and rgb.max() <= 255):
            colours = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    return points, colours


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def points_table(points: F64, colours: U8 | None, origin_m: tuple[float, float, float]) -> pa.Table:
    """A ``points`` artifact without a grid from rig-frame coordinates (see the module doc)."""
    origin = np.asarray(origin_m, dtype=np.float64)
    rel = points - origin
    range_m = np.linalg.norm(rel, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.degrees(np.arccos(np.clip(rel[:, 1] / range_m, -1.0, 1.0)))
    beta = np.degrees(np.arctan2(rel[:, 2], rel[:, 0]))
    n = len(points)
    minus_one = np.full(n, -1, np.int32)
    columns: dict[str, pa.Array] = {
        "x": pa.array(points[:, 0].astype(np.float32)),
        "y": pa.array(points[:, 1].astype(np.float32)),
        "z": pa.array(points[:, 2].astype(np.float32)),
        "range_m": pa.array(range_m.astype(np.float32)),
        "alpha_deg": pa.array(np.nan_to_num(alpha, nan=0.0)),
        "beta_deg": pa.array(beta),
        "time_ns": pa.array(np.zeros(n, np.int64)),
        "profile": pa.array(minus_one),
        "sample": pa.array(minus_one),
    }
    for k, name in enumerate(("origin_x", "origin_y", "origin_z")):
        columns[name] = pa.array(np.full(n, origin[k], np.float32))
    if colours is not None:
        for k, name in enumerate(("red", "green", "blue")):
            columns[name] = pa.array(np.ascontiguousarray(colours[:, k]))
    return pa.table(columns)


def import_points(path: Path, params: ImportParams) -> tuple[pa.Table, dict[str, object]]:
    """Read a point file into a ``points`` table (rig frame, no grid) and a short report."""
    raw, colours, z_up = read_point_file(path)
    z_up = z_up if params.up == "auto" else params.up == "z"
    points = np.stack([raw[:, 0], raw[:, 2], -raw[:, 1]], axis=1) if z_up else raw
    finite = np.isfinite(points).all(axis=1)
    points = points[finite]
    colours = colours[finite] if colours is not None else None
    table = points_table(points, colours, params.origin_m)
    report: dict[str, object] = {
        "file": str(path),
        "format": path.suffix.lower().lstrip("."),
        "points": table.num_rows,
        "dropped_not_finite": int(np.count_nonzero(~finite)),
        "z_up_converted": z_up,
        "colours": colours is not None,
        "grid": None,
        "bounds_min": points.min(axis=0).tolist() if len(points) else None,
        "bounds_max": points.max(axis=0).tolist() if len(points) else None,
    }
    return table, report
