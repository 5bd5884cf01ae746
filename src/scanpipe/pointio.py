"""Import point clouds from other tools into a ``points`` artifact (without a grid).

Formats, by file extension:

- ``.ply``: binary or ASCII, read with numpy (vertex colours are kept).
- ``.xyz``, ``.txt``, ``.csv``, ``.pts``: text, one point a line, separated by commas,
  semicolons or white space. With a header line (any non-numeric token) the columns are found
  by name (``x, y, z`` and ``red, green, blue`` or ``r, g, b``; case and a leading ``//`` are
  ignored); without one the first three columns are x, y, z and, when the next three hold only
  integers in 0–255, they are the colour.
- ``.las``, ``.laz``: through laspy (LAZ with lazrs); 16-bit colours become 8-bit.

No header is trusted: every count a header states is checked against the file's size before
anything is allocated (a binary PLY needs count × record size bytes, an ASCII value at least two
characters, a LAS file offset + count × record length), so memory stays bounded by the file.
Every parse failure is an :class:`~scanpipe.errors.ArtifactError` naming the file (and the field).

LAS is z-up; scanpipe's rig frame is y-up, so a z-up file maps as ``(x, y, z) → (x, z, −y)``,
the inverse of the export's ``(x, y, z) → (x, −z, y)``. ``up = auto`` treats LAS/LAZ as z-up
and the rest as y-up. Every point gets ``profile = sample = −1`` (no grid), the sensor origin
given (default the rig origin), ``range_m`` and the angles ``α, β`` of its direction from that
origin by inverting the paper's eq. 14–16, and ``time_ns`` 0.
"""

from __future__ import annotations

import io
import itertools
import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import ArtifactError, UsageError
from scanpipe.params import Params
from scanpipe.schema import ORIGIN, RGB

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


#: PLY scalar types and their numpy codes (both spellings of the PLY specification).
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}
#: A PLY header longer than this is not a point cloud (it protects the header read).
_PLY_HEADER_MAX_BYTES = 1 << 16
#: An ASCII number takes at least one character and one separator.
_ASCII_BYTES_PER_VALUE = 2


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    #: (name, numpy code) of scalar properties; a list property is (name, None).
    properties: tuple[tuple[str, str | None], ...]
    #: Bytes of one record at least (a list counts its length field only).
    min_record_bytes: int


def _ply_header(path: Path, head: bytes) -> tuple[str, int, list[_PlyElement]]:
    """Format, header length in bytes and elements of a PLY file, from its first bytes."""
    end = head.find(b"end_header")
    newline = head.find(b"\n", end) if end >= 0 else -1
    if newline < 0:
        raise ArtifactError(f"{path}: PLY header has no 'end_header' line in its first "
                            f"{_PLY_HEADER_MAX_BYTES} bytes")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError as err:
        raise ArtifactError(f"{path}: PLY header is not ASCII text ({err.reason} at byte "
                            f"{err.start})") from None
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str | None]], int]] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                count = int(words[2])
                if count < 0:
                    raise ValueError("negative count")
                elements.append((words[1], count, [], 0))
            elif words[0] == "property" and elements:
                name, count, props, size = elements[-1]
                if words[1] == "list":
                    count_code = _PLY_TYPES[words[2]]
                    _PLY_TYPES[words[3]]  # a known item type
                    props.append((words[4], None))
                    size += int(count_code[1])
                else:
                    code = _PLY_TYPES[words[1]]
                    props.append((words[2], code))
                    size += int(code[1])
                elements[-1] = (name, count, props, size)
            else:
                raise ValueError("unexpected line")
        except (IndexError, KeyError, ValueError):
            raise ArtifactError(f"{path}: PLY header line {number} {line.strip()!r} is not "
                                "valid (element NAME COUNT, property TYPE NAME, or property "
                                "list TYPE TYPE NAME)") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ArtifactError(f"{path}: PLY format {fmt or 'missing'!r}; allowed: ascii, "
                            "binary_little_endian, binary_big_endian")
    return fmt, newline + 1, [_PlyElement(n, c, tuple(p), b) for n, c, p, b in elements]


def _read_ply(path: Path) -> tuple[F64, U8 | None]:
    size = path.stat().st_size
    with path.open("rb") as handle:
        head = handle.read(_PLY_HEADER_MAX_BYTES)
    if not head.startswith(b"ply"):
        raise ArtifactError(f"{path}: not a PLY file (no 'ply' magic)")
    fmt, header_bytes, elements = _ply_header(path, head)
    # Every record must fit in the file before anything is allocated: a header may lie.
    available = size - header_bytes
    needed = 0
    for element in elements:
        per_value = (_ASCII_BYTES_PER_VALUE * len(element.properties) if fmt == "ascii"
                     else element.min_record_bytes)
        needed += element.count * per_value
        if needed > available:
            raise ArtifactError(
                f"{path}: PLY header field 'element {element.name} {element.count}' needs at "
                f"least {needed} bytes of data but the file has {available} after its header")
    index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if index is None:
        raise ArtifactError(f"{path}: PLY file has no 'vertex' element")
    vertex = elements[index]
    names = [name for name, _ in vertex.properties]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise ArtifactError(f"{path}: PLY vertex element has no property "
                            f"{', '.join(missing)} (found: {', '.join(names) or 'none'})")
    if vertex.count == 0:
        raise ArtifactError(f"{path}: PLY file has 0 vertices")
    before = elements[:index]
    if fmt == "ascii":
        data = _ply_ascii_vertices(path, header_bytes, before, vertex)
    else:
        if any(code is None for e in (*before, vertex) for _, code in e.properties):
            raise ArtifactError(f"{path}: binary PLY with list properties before or in the "
                                "vertex element is not supported")
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + str(code)) for name, code in vertex.properties])
        offset = header_bytes + sum(e.count * e.min_record_bytes for e in before)
        data = np.fromfile(path, dtype=dtype, count=vertex.count, offset=offset)
        if len(data) != vertex.count:  # the size check makes this unreachable; keep it honest
            raise ArtifactError(f"{path}: PLY data ends after {len(data)} of {vertex.count} "
                                "vertices")
    points = np.stack([np.asarray(data[a], np.float64) for a in "xyz"], axis=1)
    return points, _ply_colours(data, vertex)


def _ply_ascii_vertices(path: Path, header_bytes: int, before: list[_PlyElement],
                        vertex: _PlyElement) -> NDArray[np.void]:
    """The vertex records of an ASCII PLY as a structured array (columns by property name)."""
    if any(code is None for _, code in vertex.properties):
        raise ArtifactError(f"{path}: ASCII PLY with list properties in the vertex element "
                            "is not supported")
    try:
        with path.open("rb") as raw:
            raw.seek(header_bytes)
            text = io.TextIOWrapper(raw, encoding="ascii", errors="strict")
            for _ in itertools.islice(text, sum(e.count for e in before)):
                pass
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
                values = np.loadtxt(text, dtype=np.float64, max_rows=vertex.count, ndmin=2)
    except ValueError as err:  # UnicodeDecodeError included
        raise ArtifactError(f"{path}: ASCII PLY vertex data is not a table of "
                            f"{len(vertex.properties)} numbers per line ({err})") from None
    if values.shape[0] != vertex.count or values.shape[1] != len(vertex.properties):
        raise ArtifactError(f"{path}: PLY header field 'element vertex {vertex.count}' with "
                            f"{len(vertex.properties)} properties, but the data has "
                            f"{values.shape[0]} lines of {values.shape[1]} numbers")
    dtype = np.dtype([(name, "f8") for name, _ in vertex.properties])
    return np.ascontiguousarray(values).view(dtype).reshape(-1)


def _ply_colours(data: NDArray[np.void], vertex: _PlyElement) -> U8 | None:
    """8-bit colours from ``red/green/blue`` (or ``diffuse_*``): 8-bit as is, 16-bit shifted,
    floats taken as 0–1."""
    codes = dict(vertex.properties)
    for prefix in ("", "diffuse_"):
        channels = [f"{prefix}{c}" for c in ("red", "green", "blue")]
        if all(c in codes for c in channels):
            rgb = np.stack([np.asarray(data[c], np.float64) for c in channels], axis=1)
            code = codes[channels[0]] or ""
            if code.startswith("f"):
                rgb = rgb * 255.0
            elif code in ("u2", "i2"):
                rgb = rgb / 256.0
            return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    return None


#: The smallest point record of each LAS point format (0–10), in bytes.
_LAS_RECORD_BYTES = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
_LAS_HEADER_MIN_BYTES = 227
#: LAZ bounds the claimed point count by its size: constant points compress to ~0.01 byte
#: each (laszip, measured); no real file gets near 256 points per byte.
_LAZ_MAX_POINTS_PER_BYTE = 256


def _check_las_header(path: Path) -> int:
    """Check a LAS/LAZ header against the file's size before laspy allocates; the point count."""
    size = path.stat().st_size
    with path.open("rb") as handle:
        head = handle.read(375)
    if len(head) < _LAS_HEADER_MIN_BYTES or not head.startswith(b"LASF"):
        raise ArtifactError(f"{path}: not a readable LAS/LAZ file (no 'LASF' signature or "
                            f"a header shorter than {_LAS_HEADER_MIN_BYTES} bytes)")
    minor = head[25]
    header_size, offset = struct.unpack_from("<HI", head, 94)
    point_format, record_bytes, count = struct.unpack_from("<BHI", head, 104)
    if minor >= 4 and header_size >= 375 and len(head) >= 255:
        count = struct.unpack_from("<Q", head, 247)[0] or count
    compressed = bool(point_format & 0xC0)
    base = point_format & 0x3F
    if not _LAS_HEADER_MIN_BYTES <= header_size <= size:
        raise ArtifactError(f"{path}: LAS header field 'header size' is {header_size}; "
                            f"allowed {_LAS_HEADER_MIN_BYTES}…{size} (the file's size)")
    if not header_size <= offset <= size:
        raise ArtifactError(f"{path}: LAS header field 'offset to point data' is {offset}; "
                            f"allowed {header_size}…{size} (header size … file size)")
    if base >= len(_LAS_RECORD_BYTES):
        raise ArtifactError(f"{path}: LAS header field 'point data format' is {base}; "
                            "allowed 0…10")
    if record_bytes < _LAS_RECORD_BYTES[base]:
        raise ArtifactError(f"{path}: LAS header field 'point record length' is {record_bytes}; "
                            f"point format {base} needs at least {_LAS_RECORD_BYTES[base]}")
    if count == 0:
        raise ArtifactError(f"{path}: LAS header field 'number of point records' is 0: no points")
    data_bytes = size - offset
    if compressed and count > data_bytes * _LAZ_MAX_POINTS_PER_BYTE:
        raise ArtifactError(f"{path}: LAS header field 'number of point records' is {count}; "
                            f"{data_bytes} bytes of compressed data cannot hold that many")
    if not compressed and count * record_bytes > data_bytes:
        raise ArtifactError(f"{path}: LAS header field 'number of point records' is {count}: "
                            f"{count} × {record_bytes} bytes from offset {offset} exceed the "
                            f"file's {size} bytes")
    return int(count)


def _read_las(path: Path) -> tuple[F64, U8 | None]:
    import laspy

    count = _check_las_header(path)
    try:
        import lazrs  # type: ignore[import-untyped]

        lazrs_errors: tuple[type[Exception], ...] = (lazrs.LazrsError,)
    except ImportError:
        lazrs_errors = ()
    try:
        las = laspy.read(str(path))
        points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
        names = set(las.point_format.dimension_names)
        rgb = (np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)],
                        axis=1) if {"red", "green", "blue"} <= names else None)
    except (laspy.LaspyException, OSError, ValueError, struct.error, EOFError, IndexError,
            KeyError, OverflowError, TypeError, *lazrs_errors) as err:
        raise ArtifactError(f"{path}: not a readable LAS/LAZ file "
                            f"({type(err).__name__}: {err})") from None
    if len(points) != count:
        raise ArtifactError(f"{path}: LAS header field 'number of point records' is {count} "
                            f"but {len(points)} points could be read")
    colours = None
    if rgb is not None:
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
    for k, name in enumerate(ORIGIN):
        columns[name] = pa.array(np.full(n, origin[k], np.float32))
    if colours is not None:
        for k, name in enumerate(RGB):
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
