"""Import point clouds from other tools into a ``points`` artifact (docs/import.md).

Formats, by file extension or ``format``:

- ``ply``: binary or ASCII, read with numpy (vertex colours are kept).
- ``xyz`` / ``csv`` (``.xyz``, ``.txt``, ``.csv``, ``.pts``): text, one point a line, separated
  by commas, semicolons or white space. ``columns`` names each column's role; else a header
  line (any non-numeric token) names them (``x, y, z``, ``red, green, blue`` or ``r, g, b``,
  ``intensity``, ``range, azimuth, elevation``; case and a leading ``//`` are ignored), with a
  warning when the header is not plain ``x,y,z[,rgb]`` and a check against the polar columns
  when it has both; without a header the first three columns are x, y, z and, when the next
  three hold only integers in 0–255, they are the colour.
- ``3d``: 3DTK's ``scanNNN.3d`` (left-handed, y up, centimetres; a first line that is not three
  numbers is the resolution and skipped), with its ``.pose`` (:func:`read_pose`).
- ``las`` (``.las``, ``.laz``): through laspy (LAZ with lazrs); 16-bit colours become 8-bit,
  the intensity the echo.
- ``pts`` (Leica PTS): an optional point-count line, then x y z [intensity] [r g b].

Coordinates are stored as float32: an axis beyond ±2048 m (a georeferenced file) is shifted
by whole kilometres (:func:`float32_safe_offset`), or by the user's ``offset_m``; the shift is
carried with the points (:data:`scanpipe.schema.OFFSET_KEY`) and exporters add it back.

No header is trusted: every count a header states is checked against the file's size before
anything is allocated (a binary PLY needs count × record size bytes, an ASCII value at least two
characters, a LAS file offset + count × record length), so memory stays bounded by the file.
Every parse failure is an :class:`~scanpipe.errors.ArtifactError` naming the file (and the field).

Per file: pose (file frame and units) → metres → z mirrored when left-handed → rig axes. LAS is
z-up; scanpipe's rig frame is y-up, so a z-up file maps as ``(x, y, z) → (x, z, −y)``, the
inverse of the export's ``(x, y, z) → (x, −z, y)``. ``up = auto``: LAS/LAZ z-up, 3DTK y-up,
else :func:`detect_z_up`. No-returns (range 0, at/above ``max_range_m``) are dropped and
counted. Points get ``profile = sample = −1`` unless ``organised`` gives the grid, the sensor
origin of their file's pose (else ``origin_m``), ``range_m`` and the angles ``α, β`` of their
direction from that origin by inverting the paper's eq. 14–16, and ``time_ns`` 0.
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
from scanpipe.protocol.profile import ECHO_FULL_SCALE, are_fractions
from scanpipe.schema import (
    ORIGIN,
    RGB,
    format_offset,
    offset_from_z_up,
    offset_z_up,
    with_crs,
    with_offset,
)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
#: Leica PTS intensities run −2048…2047; shifted by this into the echo's 0…4095.
PTS_INTENSITY_SHIFT = 2048
SUFFIXES = (".ply", *TEXT_SUFFIXES, ".las", ".laz")


class ImportParams(Params):
    """How a foreign point cloud enters the rig frame."""

    origin_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="sensor origin of every point, in the rig frame")
    up: Literal["auto", "y", "z"] = Field(
        "auto", description="the file's up axis; auto = z for LAS/LAZ, y for 3DTK .3d, "
                            "else detected from the cloud (see detect_z_up)")
    format: Literal["auto", "xyz", "csv", "pts", "ply", "las", "e57", "pcd", "3d"] = Field(
        "auto", description="file format; auto = from the extension")
    columns: str | None = Field(
        None, description="text columns: each column's role in order (x,y,z,-,intensity; "
                          "- skips) or ROLE=INDEX pairs; roles x y z red green blue intensity "
                          "range azimuth elevation")
    units: Literal["auto", "m", "cm", "mm", "ft", "us-ft"] = Field(
        "auto", description="length unit of the file (and its pose); auto = cm for 3DTK .3d, "
                            "m otherwise")
    axes: str | None = Field(
        None, description="which file axis becomes rig x, y, z, signed (e.g. x,z,-y)")
    left_handed: bool | None = Field(
        None, description="the file's frame is left-handed (its z is mirrored); None = true "
                          "for 3DTK .3d")
    organised: str | None = Field(
        None, description="ROWSxCOLS: the file is a grid in row order (profile = row, "
                          "sample = column)")
    max_range_m: float | None = Field(
        None, gt=0, description="ranges at or above this are no-returns (dropped, counted)")
    offset_m: tuple[float, float, float] | None = Field(
        None, description="georeference offset subtracted from every point (x, y, z in metres "
                          "in the z-up frame of LAS/E57 exports: a z-up file's own x, y, z; "
                          "after --units); None = chosen per cloud (float32_safe_offset)")
    extra_files: tuple[str, ...] = Field((), description="more point files merged in")
    poses: tuple[str, ...] = Field(
        (), description="one pose file per file (first, then extra_files); '' = none")
    content_keys: tuple[str, ...] = Field(
        (), description="content keys of extra_files and poses (the CLI fills them in): the "
                        "cached artifact follows the files' bytes, not only their names")


def read_point_file(path: Path) -> tuple[F64, U8 | None, bool]:
    """Points ``(N, 3)`` float64 in the file's own units, colours ``(N, 3)`` uint8 or None, and
    whether it is z-up."""
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise UsageError(f"{path}: unknown point file type {suffix!r}; "
                         f"allowed: {', '.join(SUFFIXES)}")
    if not path.is_file():
        raise UsageError(f"{path}: not found")
    if suffix == ".ply":
        points, colours, _ = _read_ply(path)
        return points, colours, False
    if suffix in (".las", ".laz"):
        points, colours, _, _, _ = _read_las(path)
        return points, colours, True
    fmt = "pts" if suffix == ".pts" else "xyz"
    table = _read_text(path, fmt)
    points, colours, _, _ = _map_columns(path, table, ImportParams(), [], fmt)
    return points, colours, False


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


#: PLY vertex properties that hold the intensity (lower case): PDAL's, CloudCompare's
#: scalar field, and others' spellings.
_PLY_INTENSITY = ("intensity", "scalar_intensity", "reflectance", "scalar_reflectance")


def _read_ply(path: Path) -> tuple[F64, U8 | None, F64 | None]:
    """Points, 8-bit colours (or None) and the intensity property's values (or None)."""
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
    lower = {name.lower(): name for name, _ in vertex.properties}
    found = next((lower[n] for n in _PLY_INTENSITY if n in lower), None)
    intensity = None if found is None else np.asarray(data[found], np.float64)
    return points, _ply_colours(data, vertex), intensity


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


def _read_las(path: Path, warnings_out: list[str] | None = None
              ) -> tuple[F64, U8 | None, NDArray[np.uint16], tuple[str, str, str] | None,
                         str | None]:
    """Points, 8-bit colours (or None), the intensity (u16, LAS's own type), the length
    units its coordinate system states (:func:`las_units`), or None, and its WKT (or None)."""
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
        intensity = np.asarray(las.intensity, np.uint16)
        crs_units = las_units(path, las.header, [] if warnings_out is None else warnings_out)
        wkt = las_wkt(las.header)
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
    return points.astype(np.float64), colours, intensity, crs_units, wkt


#: EPSG length units of GeoTIFF's ProjLinearUnitsGeoKey (3076) / VerticalUnitsGeoKey (4099).
_EPSG_UNITS = {9001: "m", 9002: "ft", 9003: "us-ft"}
_GEOKEY_LINEAR, _GEOKEY_VERTICAL = 3076, 4099
_WKT_UNIT = re.compile(r'(?:LENGTH)?UNIT\[\s*"([^"]*)"\s*,\s*([-+0-9.eE]+)')
_ANGULAR = re.compile(r"degree|radian|grad|arc|second|minute|unity|ppm|per", re.IGNORECASE)


def _unit_key(factor_m: float) -> str | None:
    """The ``UNIT_SCALE`` key of a length unit given in metres, if it is one of them."""
    return next((k for k, v in UNIT_SCALE.items() if abs(v - factor_m) <= 1e-9 * v), None)


def _wkt_length_unit(text: str) -> tuple[str, float] | None:
    """The last length unit (name, metres) of a WKT 1 or 2 text (its CS's unit comes last)."""
    found = [(n, float(f)) for n, f in _WKT_UNIT.findall(text) if not _ANGULAR.search(n)]
    return found[-1] if found else None


def _verb(source: str, verb: str = "state") -> str:
    """``state``/``states`` (or another verb) agreeing with "its WKT" / "its GeoTIFF keys"."""
    return verb if source.endswith("keys") else f"{verb}s"


def _unit_by_name(name: str) -> str | None:
    """The ``UNIT_SCALE`` key a WKT unit name spells, if any."""
    low = name.lower().replace("_", " ")
    if "us survey" in low or "ftus" in low or "foot us" in low:
        return "us-ft"
    if low in ("foot", "feet", "international foot", "ft"):
        return "ft"
    if low in ("metre", "meter", "m"):
        return "m"
    return None


def _wkt_unit_key(path: Path, unit: tuple[str, float], warnings_out: list[str]
                  ) -> tuple[str, float, str | None]:
    """(name, metres, key) of a WKT unit; a known name whose factor disagrees with it (liblas
    wrote ``UNIT["US survey foot",1.0]``) is taken by its name, with a warning."""
    name, factor = unit
    by_name, by_factor = _unit_by_name(name), _unit_key(factor)
    if by_name is not None and by_factor != by_name:
        warnings_out.append(f"{path}: its WKT's UNIT[\"{name}\",{factor!r}]: the name and "
                            f"the factor disagree; taken as {UNIT_NAMES[by_name]} "
                            f"({UNIT_SCALE[by_name]:.10g} m)")
        return name, UNIT_SCALE[by_name], by_name
    return name, factor, by_factor


def las_wkt(header: object) -> str | None:
    """The WKT of a LAS header's coordinate system (``LASF_Projection``/``liblas`` 2112; the
    last one), or None."""
    wkt = None
    for vlr in getattr(header, "vlrs", []):
        if getattr(vlr, "record_id", None) == 2112:
            data = getattr(vlr, "record_data", None)
            text = getattr(vlr, "string", None) or (bytes(data).decode("utf-8", "replace")
                                                    if data is not None else "")
            wkt = text.rstrip("\0") or wkt
    return wkt


def las_units(path: Path, header: object, warnings_out: list[str]) -> tuple[str, str, str] | None:
    """The horizontal and vertical length units (``UNIT_SCALE`` keys) a LAS header's CRS
    states and where it says so: its WKT (``LASF_Projection``/``liblas`` 2112; a ``VERT_CS``
    or ``VERTCRS`` part gives the vertical unit) or else its GeoTIFF keys 3076 / 4099. None
    when it states none; a unit scanpipe does not know is warned about and read as metres."""
    wkt, keys = las_wkt(header), {}
    for vlr in getattr(header, "vlrs", []):
        for key in getattr(vlr, "geo_keys", []) or []:
            if key.tiff_tag_location == 0:
                keys[int(key.id)] = int(key.value_offset)
    if wkt:
        split = re.search(r"VERT_?CS|VERTCRS", wkt)
        horizontal = _wkt_length_unit(wkt[:split.start()] if split else wkt)
        vertical = _wkt_length_unit(wkt[split.start():]) if split else None
        if horizontal is None:
            return None
        vertical = vertical or horizontal
        named = [_wkt_unit_key(path, unit, warnings_out) for unit in (horizontal, vertical)]
        source = "its WKT"
    elif _GEOKEY_LINEAR in keys:
        codes = (keys[_GEOKEY_LINEAR], keys.get(_GEOKEY_VERTICAL, keys[_GEOKEY_LINEAR]))
        named = [(f"EPSG:{c}", UNIT_SCALE.get(_EPSG_UNITS.get(c, ""), float("nan")),
                  _EPSG_UNITS.get(c)) for c in codes]
        source = "its GeoTIFF keys"
    else:
        return None
    unknown = list(dict.fromkeys(
        f"{name} ({factor:g} m)" if np.isfinite(factor) else
        f"{name} (not a length unit code: a CRS? EPSG 9001 metre, 9002 foot, 9003 US survey "
        "foot)" for name, factor, key in named if key is None))
    if unknown:
        warnings_out.append(f"{path}: {source} {_verb(source)} a length unit scanpipe does "
                            f"not know: {', '.join(unknown)}; read as metres: give --units")
    h_key, v_key = (key or "m" for _, _, key in named)
    return h_key, v_key, source


#: Column roles ``--columns`` and a header may name (aliases in the header, lower case).
ROLES = {"x": ("x",), "y": ("y",), "z": ("z",), "red": ("red", "r"), "green": ("green", "g"),
         "blue": ("blue", "b"), "intensity": ("intensity", "reflectance", "i"),
         "range": ("range", "range_m", "r_m", "distance"),
         "azimuth": ("azimuth", "azimuth_deg", "az"),
         "elevation": ("elevation", "elevation_deg", "el")}
_STANDARD_HEADERS = ({"x", "y", "z"}, {"x", "y", "z", "red", "green", "blue"})


@dataclass
class _Table:
    """A text point file's numbers and, when it has one, its header's column names."""

    data: F64
    names: list[str] | None


def _read_text(path: Path, fmt: str = "xyz", warnings_out: list[str] | None = None
               ) -> _Table:
    """A text table. ``3d``: a first line that is not three numbers is dropped (3DTK's ``.3d``
    files start with a resolution line). A first line holding one whole number followed by
    rows of three or more numbers is a point count (Leica PTS writes one): it is dropped and
    compared with the rows (a warning when they differ)."""
    try:
        with path.open("r", encoding="utf-8", errors="strict") as handle:
            first = handle.readline()
    except (OSError, UnicodeDecodeError) as err:
        raise ArtifactError(f"{path}: not a readable text point file ({err})") from err
    delimiter = "," if "," in first else ";" if ";" in first else None
    tokens = [t.strip() for t in (first.split(delimiter) if delimiter else first.split())]
    tokens = [t for t in tokens if t]
    header = not all(_is_number(t) for t in tokens)
    count_line = (not header and len(tokens) == 1 and tokens[0].isdigit()
                  and fmt in ("xyz", "csv", "pts"))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": below
            data = np.loadtxt(path, delimiter=delimiter, ndmin=2, dtype=np.float64,
                              skiprows=1 if header or count_line else 0, comments="#")
    except ValueError as err:
        raise ArtifactError(f"{path}: not a table of numbers ({err})") from err
    if data.shape[0] == 0:
        raise ArtifactError(f"{path}: no points")
    if count_line and data.shape[0] != int(tokens[0]) and warnings_out is not None:
        warnings_out.append(f"{path}: its first line says {int(tokens[0])} points but "
                            f"{data.shape[0]} rows follow; all rows were read")
    names = None
    if header and fmt != "3d":
        names = [re.sub(r"^//", "", t).strip().lower() for t in tokens]
    return _Table(data, names)


def parse_columns(text: str, count: int, where: str) -> dict[str, int]:
    """Role → column index from ``--columns``: each file column's role in order (``-`` skips
    one: ``x,y,z,-,intensity``) or ``ROLE=INDEX`` pairs (``x=0,y=2,z=1``)."""
    items = [t.strip().lower() for t in text.split(",")]
    mapping: dict[str, int] = {}
    for position, item in enumerate(items):
        role, _, index = item.partition("=")
        if item == "-":
            continue
        if role not in ROLES:
            raise UsageError(f"--columns {text!r}: unknown column {role!r}; allowed: "
                             f"{', '.join(ROLES)}, - (skip) or ROLE=INDEX")
        try:
            column = int(index) if index else position
        except ValueError:
            raise UsageError(f"--columns {text!r}: {item!r} is not ROLE=INDEX") from None
        if not 0 <= column < count:
            raise UsageError(f"--columns {text!r}: column {column} of {role!r} is not in "
                             f"{where} ({count} columns)")
        if role in mapping:
            raise UsageError(f"--columns {text!r}: {role!r} given twice")
        mapping[role] = column
    if not ({"x", "y", "z"} <= set(mapping) or {"range", "azimuth", "elevation"} <= set(mapping)):
        raise UsageError(f"--columns {text!r}: need x, y, z or range, azimuth, elevation")
    return mapping


def polar_to_xyz(range_m: F64, azimuth_deg: F64, elevation_deg: F64) -> F64:
    """Points from polar columns, in the file's own z-up frame: azimuth counter-clockwise
    about z from +x towards +y, elevation up from the x-y plane towards +z (degrees)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack([range_m * np.cos(el) * np.cos(az), range_m * np.cos(el) * np.sin(az),
                     range_m * np.sin(el)], axis=1)


_PERMUTATIONS = (("x", "y", "z"), ("x", "z", "y"), ("y", "x", "z"), ("y", "z", "x"),
                 ("z", "x", "y"), ("z", "y", "x"))


def _check_header_against_polar(path: Path, xyz: F64, polar: F64, ok: NDArray[np.bool_],
                                warnings_out: list[str]) -> None:
    """Warn when the named x, y, z disagree with the file's own range/azimuth/elevation."""
    if not ok.any():
        return
    a, b = xyz[ok], polar[ok]
    scale = max(float(np.median(np.linalg.norm(b, axis=1))), 1e-9)
    error = float(np.mean(np.linalg.norm(a - b, axis=1)))
    if error <= 0.01 * scale:
        return
    best = min(_PERMUTATIONS, key=lambda p: float(np.mean(np.linalg.norm(
        a[:, ["xyz".index(c) for c in p]] - b, axis=1))))
    best_error = float(np.mean(np.linalg.norm(a[:, ["xyz".index(c) for c in best]] - b,
                                              axis=1)))
    hint = (f"its columns named {','.join(best)} fit them as x,y,z (mean {best_error:.3g}); "
            "the header is probably mislabelled: give --columns"
            if best_error <= 0.01 * scale else
            "the polar columns may follow another convention; check and give --columns")
    warnings_out.append(f"{path}: the header's x, y, z disagree with its range/azimuth/"
                        f"elevation columns (mean {error:.3g} in file units); {hint}")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def points_table(points: F64, colours: U8 | None,
                 origin_m: tuple[float, float, float] | F64,
                 echo: NDArray[np.uint16] | None = None) -> pa.Table:
    """A ``points`` artifact without a grid from rig-frame coordinates (see the module doc);
    ``origin_m`` is one origin or one per point."""
    origin = np.broadcast_to(np.asarray(origin_m, dtype=np.float64), points.shape)
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
        columns[name] = pa.array(np.ascontiguousarray(origin[:, k], np.float32))
    if echo is not None:
        columns["echo"] = pa.array(echo)
    if colours is not None:
        for k, name in enumerate(RGB):
            columns[name] = pa.array(np.ascontiguousarray(colours[:, k]))
    return pa.table(columns)


#: Metres per file unit.
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048, "us-ft": 1200.0 / 3937.0}
#: Names of the length units (WKT ``UNIT``/``LENGTHUNIT``, EPSG codes in GeoTIFF keys).
UNIT_NAMES = {"m": "metre", "cm": "centimetre", "mm": "millimetre", "ft": "foot",
              "us-ft": "US survey foot"}
#: Extents (metres) outside which a cloud is implausible for its units.
MAX_PLAUSIBLE_EXTENT_M = 500.0
MIN_PLAUSIBLE_EXTENT_M = 0.05
#: Artifacts hold float32 coordinates: an axis whose values would be rounded by more than this
#: (beyond ±2048 m) is shifted (georeferenced files: UTM eastings are ~10⁵–10⁶ m).
MAX_FLOAT32_ERROR_M = 1e-4
#: The grid an automatic georeference offset is rounded to: files of one site (positions
#: within a few hundred metres) mostly get the same offset (a site whose files straddle a
#: kilometre line gets two, which register refuses to merge: give --offset).
OFFSET_GRID_M = 1000.0
#: Fewer points than this cannot tell z-up from y-up.
MIN_POINTS_FOR_UP = 200


@dataclass
class _Scan:
    """One file's points in its own frame and units, before any mapping."""

    points: F64
    colours: U8 | None
    echo: NDArray[np.uint16] | None
    grid: tuple[NDArray[np.int32], NDArray[np.int32]] | None
    z_up: bool | None  # the format says (LAS: z-up, 3DTK: y-up); None: unknown
    units: str
    left_handed: bool
    no_return: int
    #: Each point's sensor origin in the file's frame when the file says (E57 scan poses).
    origins: F64 | None = None
    #: The unit of the file's z (LAS: its CRS's vertical unit), when not ``units``.
    vertical_units: str | None = None
    #: The file itself states its unit (a LAS CRS): no plausibility guess about it.
    units_stated: bool = False
    #: The WKT of the file's coordinate system (LAS/LAZ), when it has one.
    crs_wkt: str | None = None


def _format_of(path: Path, params: ImportParams) -> str:
    if params.format != "auto":
        return params.format
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return "ply"
    if suffix in (".las", ".laz"):
        return "las"
    if suffix in (".e57", ".pcd"):
        return suffix[1:]
    if suffix == ".3d":
        return "3d"
    if suffix == ".pts":
        return "pts"
    if suffix in TEXT_SUFFIXES:
        return "xyz"
    raise UsageError(f"{path}: unknown point file type {suffix!r}; allowed: "
                     f"{', '.join((*SUFFIXES, '.e57', '.pcd', '.3d'))}, or name the format "
                     "with --format xyz|csv|pts|ply|las|e57|pcd|3d")


def parse_organised(text: str) -> tuple[int, int]:
    """``ROWSxCOLS`` → (rows, columns)."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not match or 0 in (int(match[1]), int(match[2])):
        raise UsageError(f"--organised {text!r}: expected ROWSxCOLS, e.g. 180x1081")
    return int(match[1]), int(match[2])


def _read_scan(path: Path, params: ImportParams, warnings_out: list[str]) -> _Scan:
    if not path.is_file():
        raise UsageError(f"{path}: not found")
    fmt = _format_of(path, params)
    units: str = params.units if params.units != "auto" else ("cm" if fmt == "3d" else "m")
    vertical_units = units
    units_stated = False
    left = params.left_handed if params.left_handed is not None else fmt == "3d"
    echo = None
    crs_wkt: str | None = None
    origins: F64 | None = None
    file_grid: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None
    no_return_file = 0
    if fmt in ("ply", "las", "e57", "pcd"):
        if params.columns:
            raise UsageError(f"--columns applies to text files, not {fmt} ({path})")
        if fmt == "ply":
            raw, colours, intensity = _read_ply(path)
            if intensity is not None:
                echo = _intensity_to_echo(path, intensity, fmt, warnings_out)
        elif fmt == "las":
            raw, colours, echo, crs, crs_wkt = _read_las(path, warnings_out)
            units, vertical_units = _las_file_units(path, params, crs, units, warnings_out)
            units_stated = crs is not None and params.units == "auto"
        else:
            cloud = (_read_pcd(path, warnings_out) if fmt == "pcd"
                     else _read_e57(path, warnings_out))
            raw, colours, echo, origins = cloud.points, cloud.colours, cloud.echo, cloud.origins
            file_grid, no_return_file = cloud.grid, cloud.invalid
        table_range: F64 | None = None
        z_up: bool | None = True if fmt in ("las", "e57") else None
    else:
        table = _read_text(path, fmt, warnings_out)
        raw, colours, echo, table_range = _map_columns(path, table, params, warnings_out, fmt)
        z_up = False if fmt == "3d" else (True if table_range is not None and params.columns
                                          and "x" not in params.columns else None)
    n = len(raw)
    grid = file_grid
    if params.organised:
        rows, cols = parse_organised(params.organised)
        if rows * cols != n:
            raise UsageError(f"--organised {params.organised}: {rows} × {cols} = {rows * cols} "
                             f"cells but {path} has {n} points")
        index = np.arange(n, dtype=np.int32)
        grid = (index // cols, index % cols)
    # No return: a range of 0 (a point at the sensor), or at/above the maximum range.
    range_file = (table_range if table_range is not None else
                  np.linalg.norm(raw if origins is None else raw - origins, axis=1))
    finite = np.isfinite(raw).all(axis=1) & np.isfinite(range_file)
    with np.errstate(invalid="ignore"):
        no_return = finite & (range_file <= 0)
        if params.max_range_m is not None:
            no_return |= finite & (range_file * UNIT_SCALE[units] >= params.max_range_m)
    keep = finite & ~no_return
    if np.count_nonzero(~finite):
        warnings_out.append(f"{path}: {np.count_nonzero(~finite)} rows with NaN/inf dropped")
    return _Scan(raw[keep], None if colours is None else colours[keep],
                 None if echo is None else echo[keep],
                 None if grid is None else (grid[0][keep], grid[1][keep]), z_up, units, left,
                 int(np.count_nonzero(no_return)) + no_return_file,
                 None if origins is None else origins[keep], vertical_units, units_stated,
                 crs_wkt)


def _las_file_units(path: Path, params: ImportParams, crs: tuple[str, str, str] | None,
                    units: str, warnings_out: list[str]) -> tuple[str, str]:
    """The units a LAS file is read in: its CRS's (horizontal, vertical) unless ``--units``
    says otherwise (then warned when they differ)."""
    if crs is None:
        return units, units
    horizontal, vertical, source = crs
    said = (UNIT_NAMES[horizontal] if horizontal == vertical else
            f"{UNIT_NAMES[horizontal]} horizontally, {UNIT_NAMES[vertical]} vertically")
    if params.units != "auto":
        if {horizontal, vertical} != {params.units}:
            warnings_out.append(f"{path}: --units {params.units} given, but {source} "
                                f"{_verb(source, 'say')} {said}; read in "
                                f"{UNIT_NAMES[params.units]} as asked")
        return units, units
    if {horizontal, vertical} != {"m"}:
        factors = ", ".join(f"{UNIT_NAMES[k]} = {UNIT_SCALE[k]:.10g} m"
                            for k in dict.fromkeys((horizontal, vertical)) if k != "m")
        warnings_out.append(f"{path}: {source} {_verb(source)} the unit: {said} ({factors}); "
                            "converted to metres")
    return horizontal, vertical


def _map_columns(path: Path, table: _Table, params: ImportParams, warnings_out: list[str],
                 fmt: str = "xyz"
                 ) -> tuple[F64, U8 | None, NDArray[np.uint16] | None, F64 | None]:
    """Points (file frame), colours, intensity and the polar range column of a text table.

    Without a header: x, y, z first; Leica PTS (``fmt`` ``pts``) then has ``intensity`` and
    ``r g b`` (4, 6 or 7 columns: x y z i, x y z r g b, x y z i r g b); other text takes
    columns 4–6 as colours when they hold only whole numbers in 0–255, with a warning when
    columns 5–7 would qualify too (the PTS order, which CloudCompare also writes)."""
    data, names = table.data, table.names
    if params.columns:
        roles = parse_columns(params.columns, data.shape[1], str(path))
    elif names is not None:
        roles = {}
        for role, aliases in ROLES.items():
            found = next((names.index(a) for a in aliases if a in names), None)
            if found is not None:
                roles[role] = found
        missing = [k for k in "xyz" if k not in roles]
        polar = {"range", "azimuth", "elevation"} <= set(roles)
        if missing and not polar:
            raise ArtifactError(f"{path}: header has no column {', '.join(missing)} "
                                f"(found: {', '.join(names)})")
        known = set(roles) | {"-"}
        ordered = [n for n in names if n in ("x", "y", "z")]
        if set(names) - {a for r in roles for a in ROLES[r]} - known or ordered != sorted(
                ordered) or set(roles) not in _STANDARD_HEADERS:
            warnings_out.append(f"{path}: columns taken by the header's names "
                                f"({', '.join(names)}); a header is not checked against the "
                                "data: confirm with --columns")
    else:
        if data.shape[1] < 3:
            raise ArtifactError(f"{path}: {data.shape[1]} columns; need at least x, y, z")
        roles = {"x": 0, "y": 1, "z": 2}
        width = data.shape[1]
        if fmt == "pts":
            if width in (4, 7):
                roles["intensity"] = 3
            if width in (6, 7):
                roles.update(red=width - 3, green=width - 2, blue=width - 1)
        elif width >= 6 and _bytes_only(data[:, 3:6]):
            roles.update(red=3, green=4, blue=5)
            if width >= 7 and _bytes_only(data[:, 4:7]):
                warnings_out.append(
                    f"{path}: no header; columns 4–6 taken as red, green, blue, but columns "
                    "5–7 could be the colours as well (x y z intensity r g b, as Leica PTS and "
                    "CloudCompare write): if so, give --columns x,y,z,intensity,red,green,blue")
    polar_xyz = None
    # A range column alone still tells no-returns (0) from points.
    range_col = data[:, roles["range"]] if "range" in roles else None
    if range_col is not None and {"azimuth", "elevation"} <= set(roles):
        polar_xyz = polar_to_xyz(range_col, data[:, roles["azimuth"]],
                                 data[:, roles["elevation"]])
    if all(k in roles for k in "xyz"):
        points = data[:, [roles["x"], roles["y"], roles["z"]]]
        if polar_xyz is not None and range_col is not None and not params.columns:
            _check_header_against_polar(path, points, polar_xyz, range_col > 0, warnings_out)
    else:
        assert polar_xyz is not None
        points = polar_xyz
    colours = None
    if all(k in roles for k in ("red", "green", "blue")):
        rgb = data[:, [roles["red"], roles["green"], roles["blue"]]]
        colours = np.clip(np.rint(np.nan_to_num(rgb)), 0, 255).astype(np.uint8)
    echo = None
    if "intensity" in roles:
        echo = _intensity_to_echo(path, data[:, roles["intensity"]], fmt, warnings_out)
    return points, colours, echo, range_col


def _bytes_only(values: F64) -> bool:
    """Whether every value is a whole number in 0…255 (an 8-bit colour channel)."""
    return bool(np.all(values == np.round(values)) and values.min() >= 0
                and values.max() <= 255)


def _intensity_to_echo(path: Path, values: F64, fmt: str, warnings_out: list[str]
                       ) -> NDArray[np.uint16]:
    """An intensity column as the ``echo`` (u16), never silently truncated: a 0…1 fraction is
    scaled to 0…65535, PTS's −2048…2047 shifted into 0…4095 (both warned), any other negative
    or too large value clipped with a warning."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return np.zeros(len(values), np.uint16)
    low, high = float(finite.min()), float(finite.max())
    if fmt == "pts" and -PTS_INTENSITY_SHIFT <= low < 0 and high < PTS_INTENSITY_SHIFT:
        values = values + PTS_INTENSITY_SHIFT
    elif are_fractions(finite):
        values = values * ECHO_FULL_SCALE
        warnings_out.append(f"{path}: intensity in 0…1 (fractions): scaled to the echo's "
                            f"0…{ECHO_FULL_SCALE:g}")
    else:
        clipped = int(np.count_nonzero((finite < -0.5) | (finite > ECHO_FULL_SCALE + 0.5)))
        if clipped:
            warnings_out.append(f"{path}: {clipped} intensities outside the echo's "
                                f"0…{ECHO_FULL_SCALE:g} (negative or too large; "
                                f"{low:g}…{high:g}) clipped to it")
    return np.clip(np.rint(np.nan_to_num(values)), 0, ECHO_FULL_SCALE).astype(np.uint16)


def read_pose(path: Path) -> F64:
    """A 4×4 pose (file frame → common frame, file units) from a pose file: a 4×4 matrix
    (16 numbers, row-major) or a 3DTK ``.pose`` (line 1 position x y z, line 2 Euler angles
    θx θy θz in degrees; rotation ``Rx·Ry·Rz``, as 3DTK's ``EulerToMatrix4``)."""
    try:
        values = np.array(path.read_text(encoding="utf-8").split(), dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise UsageError(f"--pose {path}: not a readable pose file ({err})") from None
    if values.size == 16:
        matrix = values.reshape(4, 4)
        if not np.allclose(matrix[3], (0, 0, 0, 1)):
            raise UsageError(f"--pose {path}: last row of the 4×4 matrix must be 0 0 0 1")
        return matrix
    if values.size != 6:
        raise UsageError(f"--pose {path}: {values.size} numbers; expected 6 (3DTK .pose: "
                         "x y z, then θx θy θz in degrees) or 16 (a 4×4 matrix)")
    if not np.isfinite(values).all():
        raise UsageError(f"--pose {path}: values must be finite")
    sx, sy, sz = np.sin(np.radians(values[3:]))
    cx, cy, cz = np.cos(np.radians(values[3:]))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    matrix = np.eye(4)
    matrix[:3, :3] = rx @ ry @ rz
    matrix[:3, 3] = values[:3]
    return matrix


def parse_axes(text: str) -> NDArray[np.float64]:
    """``--axes x,z,-y``: which file axis (with sign) becomes rig x, y, z; a 3×3 matrix."""
    items = [t.strip().lower() for t in text.split(",")]
    matrix = np.zeros((3, 3))
    axes = [i.lstrip("+-") for i in items]
    if len(items) != 3 or sorted(axes) != ["x", "y", "z"]:
        raise UsageError(f"--axes {text!r}: expected a signed permutation of x,y,z "
                         "(e.g. x,z,-y: rig x = file x, rig y = file z, rig z = −file y)")
    for row, item in enumerate(items):
        matrix[row, "xyz".index(axes[row])] = -1.0 if item.startswith("-") else 1.0
    return matrix


Z_UP_AXES = "x,z,-y"


def detect_z_up(points: F64) -> tuple[bool, str]:
    """Whether a cloud is z-up rather than y-up, and why.

    The vertical axis of a room or a site is the shorter of y and z (rooms are wider than
    high); when the two are within 25 %, the axis whose lowest 3 % of its extent holds more
    points (a floor) wins.
    """
    if len(points) < MIN_POINTS_FOR_UP:
        return False, f"fewer than {MIN_POINTS_FOR_UP} points: assumed y-up"
    low, high = np.percentile(points[:, 1:], [1, 99], axis=0)
    extent = high - low
    if extent.min() <= 0:
        return bool(extent[1] <= 0), "one of y, z is flat"
    ratio = extent[1] / extent[0]
    if ratio < 0.8 or ratio > 1.25:
        return bool(ratio < 1), (f"extent y {extent[0]:.3g}, z {extent[1]:.3g}: the shorter is "
                                 "vertical")
    floor = [float(np.mean(points[:, 1 + k] <= low[k] + 0.03 * extent[k])) for k in range(2)]
    return floor[1] > floor[0], (f"extents alike; floor share y {floor[0]:.2f}, "
                                 f"z {floor[1]:.2f}")


def float32_error_m(coordinate_m: float) -> float:
    """The largest rounding error of a coordinate this far from the origin, as float32."""
    return float(np.spacing(np.float32(abs(coordinate_m)))) / 2.0


def float32_safe_offset(points: F64) -> F64:
    """What to subtract per axis so float32 keeps ``MAX_FLOAT32_ERROR_M``: zero on an axis
    that needs nothing; else the centre of the bounds rounded to :data:`OFFSET_GRID_M` (so
    nearby files share it), or to whole metres when the cloud is too large for that."""
    if len(points) == 0:
        return np.zeros(3)
    low, high = points.min(axis=0), points.max(axis=0)
    offset = np.zeros(3)
    for axis in range(3):
        if not _float32_loses(low[axis], high[axis]):
            continue
        centre = (low[axis] + high[axis]) / 2.0
        coarse = float(np.round(centre / OFFSET_GRID_M) * OFFSET_GRID_M)
        offset[axis] = (coarse if not _float32_loses(low[axis] - coarse, high[axis] - coarse)
                        else float(np.round(centre)))
    return offset


def _carried_crs(scans: list[_Scan], params: ImportParams, axes: F64
                 ) -> tuple[str | None, str | None]:
    """The coordinate system (WKT) the points keep for the exports, and a note when a file's
    is dropped: kept only when every file states the same one, in metres on every axis (so
    no unit was converted), and the points keep the file's own axes (z-up, no pose, no
    mirror): the exported LAS then holds the file's own coordinates in its own CRS."""
    wkts = {s.crs_wkt for s in scans}
    if wkts == {None}:
        return None, None
    why = None
    # What the user may assign in another tool depends on why: a CRS in feet does not fit the
    # metre coordinates (assigned as is, the cloud lands 3.28× too far out), moved points fit
    # no CRS of the file's.
    advice = "assign the CRS there"
    if len(wkts) > 1:
        why = "the files state different coordinate systems (or some none)"
    elif not all(s.units_stated and s.units == "m" and (s.vertical_units or "m") == "m"
                 for s in scans):
        why = "its unit is not the metre (the exports are in metres)"
        advice = ("assign the metre equivalent of the file's CRS there, not the file's own "
                  "(a CRS in feet on these metre coordinates puts the cloud 3.28× too far out)")
    elif any(params.poses) or any(s.left_handed for s in scans) or not np.array_equal(
            axes, parse_axes(Z_UP_AXES)):
        why = "--pose/--axes/--up/--left-handed moved the points out of its axes"
        advice = "the file's CRS no longer fits them"
    if why is None:
        return next(iter(wkts)), None
    return None, (f"the file's coordinate system is not carried to the exports ({why}): "
                  f"LAS/LAZ/COPC say 'imported coordinates in metres'; {advice}")


def _rig_centre(points: F64) -> F64:
    """The centre of a rig-frame cloud's bounds, in whole metres."""
    return np.asarray(np.round((points.min(axis=0) + points.max(axis=0)) / 2.0), np.float64)


def _float32_loses(low: float, high: float) -> bool:
    """Whether float32 rounds coordinates in ``[low, high]`` by more than
    ``MAX_FLOAT32_ERROR_M``."""
    return float32_error_m(max(abs(float(low)), abs(float(high)))) > MAX_FLOAT32_ERROR_M


def import_points(path: Path, params: ImportParams) -> tuple[pa.Table, dict[str, object]]:
    """Read point files into one ``points`` table (rig frame) and a short report.

    ``path`` is the first file, ``params.extra_files`` the others; ``params.poses`` gives each
    its pose file (empty: none). Per file: pose (file frame and units) → metres → right-handed
    (a left-handed file's z mirrored) → rig axes (``axes``, else ``up``).
    """
    files = [path, *(Path(f) for f in params.extra_files)]
    if params.poses and len(params.poses) != len(files):
        raise UsageError(f"--pose given {len(params.poses)} times for {len(files)} files; give "
                         "one per file (in order) or none")
    notes: list[str] = []
    scans = [_read_scan(f, params, notes) for f in files]
    if params.axes and params.up != "auto":
        raise UsageError("--axes and --up both given; --axes says it all (z-up is "
                         f"--axes {Z_UP_AXES})")
    parts: list[F64] = []
    origins: list[F64] = []
    own_origin: list[NDArray[np.bool_]] = []
    for k, scan in enumerate(scans):
        pose = read_pose(Path(params.poses[k])) if params.poses and params.poses[k] else None
        pts = scan.points
        origin = scan.origins if scan.origins is not None else np.zeros((1, 3))
        if pose is not None:
            pts = pts @ pose[:3, :3].T + pose[:3, 3]
            origin = origin @ pose[:3, :3].T + pose[:3, 3]
        scale = np.array([UNIT_SCALE[scan.units], UNIT_SCALE[scan.units],
                          UNIT_SCALE[scan.vertical_units or scan.units]])
        pts, origin = pts * scale, origin * scale
        if scan.left_handed:
            pts = pts * (1.0, 1.0, -1.0)
            origin = origin * (1.0, 1.0, -1.0)
        parts.append(pts)
        origins.append(np.broadcast_to(origin, pts.shape))
        # A file's sensor origins are its own when a pose or the file (E57) gives them.
        own_origin.append(np.full(len(pts), bool(any(params.poses))
                                  or scan.origins is not None))
    points = np.concatenate(parts)
    if len(points) == 0:
        dropped = sum(s.no_return for s in scans)
        raise ArtifactError(f"{', '.join(str(f) for f in files)}: no points"
                            + (f" left ({dropped} no-returns dropped)" if dropped else ""))
    origin_file = np.concatenate(origins)
    own = np.concatenate(own_origin)
    up_reason = "given"
    if params.axes:
        axes = parse_axes(params.axes)
    else:
        hints = {s.z_up for s in scans}
        if params.up != "auto":
            z_up = params.up == "z"
        elif hints <= {True, False} and len(hints) == 1:
            z_up = bool(hints.pop())
            up_reason = "the format's convention"
        else:
            z_up, up_reason = detect_z_up(points)
            notes.append(f"--up auto chose {'z' if z_up else 'y'}-up ({up_reason}); give --up "
                         "to override")
        axes = parse_axes(Z_UP_AXES if z_up else "x,y,z")
    points = points @ axes.T
    origin_rig = np.where(own[:, None], origin_file @ axes.T,
                          np.asarray(params.origin_m, np.float64))
    if params.offset_m is not None:
        # given in the z-up frame of LAS/E57 (a z-up file's own): to the rig frame
        given = np.asarray(params.offset_m, np.float64)
        offset = np.asarray(offset_from_z_up(given), np.float64)
        low, high = (points - offset).min(axis=0), (points - offset).max(axis=0)
        if any(_float32_loses(a, b) for a, b in zip(low, high, strict=True)):
            far = float(np.max(np.maximum(np.abs(low), np.abs(high))))
            raise UsageError(
                f"--offset {','.join(f'{v:g}' for v in given)}: leaves points up to {far:.6g} m "
                f"from the origin, which float32 rounds by up to "
                f"{float32_error_m(far) * 1000:.2g} mm; give an offset within 2048 m of every "
                f"point (the cloud's centre is {format_offset(_rig_centre(points))}, z-up)")
    else:
        offset = float32_safe_offset(points)
    if offset.any():
        points, origin_rig = points - offset, origin_rig - offset
        how = "as given (--offset)" if params.offset_m is not None else (
            "chosen for this cloud; give --offset with it to every file of the same site")
        notes.append(f"georeferenced coordinates: shifted by −{format_offset(offset)} m (x,y,z "
                     f"z-up; {how}) so float32 keeps 0.1 mm; the points carry the offset and "
                     "exports add it back (LAS/LAZ/COPC/E57/PLY) or record it (OBJ, GLB)")
    colours = (np.concatenate([s.colours for s in scans if s.colours is not None])
               if all(s.colours is not None for s in scans) else None)
    echo = (np.concatenate([s.echo for s in scans if s.echo is not None])
            if all(s.echo is not None for s in scans) else None)
    crs, crs_note = _carried_crs(scans, params, axes)
    if crs_note:
        notes.append(crs_note)
    table = with_crs(with_offset(points_table(points, colours, origin_rig, echo), offset), crs)
    grid = None
    if len(scans) == 1 and scans[0].grid is not None and len(scans[0].grid[0]):
        profile, sample = scans[0].grid
        table = table.set_column(table.column_names.index("profile"), "profile",
                                 pa.array(profile))
        table = table.set_column(table.column_names.index("sample"), "sample",
                                 pa.array(sample))
        grid = {"profiles": int(profile.max()) + 1, "samples": int(sample.max()) + 1}
    elif params.organised and len(scans) > 1:
        notes.append("--organised with several files: the grid is not kept (one grid per file)")
    if len(points) and not all(s.units_stated for s in scans):
        extent = float(np.max(np.ptp(points, axis=0)))
        units = sorted({s.units for s in scans})
        if extent > MAX_PLAUSIBLE_EXTENT_M:
            notes.append(f"the cloud is {extent:.4g} m across read as {'/'.join(units)}: "
                         "implausible for a scan from one position; a site, or another "
                         "unit (feet, centimetres, millimetres)? give --units m|cm|mm|ft|us-ft")
        elif extent < MIN_PLAUSIBLE_EXTENT_M:
            notes.append(f"the cloud is {extent:.3g} m across read as {'/'.join(units)}: "
                         "implausibly small; the wrong unit? give --units")
    report: dict[str, object] = {
        "file": str(path),
        "files": [str(f) for f in files],
        "format": [_format_of(f, params) for f in files],
        "units": [s.units for s in scans],
        "left_handed": [s.left_handed for s in scans],
        "points": table.num_rows,
        "dropped_no_return": sum(s.no_return for s in scans),
        "axes": axes.astype(int).tolist(),
        "up_reason": up_reason,
        "z_up_converted": bool(axes[1, 2] != 0),
        "colours": colours is not None,
        "grid": grid,
        "bounds_min": points.min(axis=0).tolist() if len(points) else None,
        "bounds_max": points.max(axis=0).tolist() if len(points) else None,
        "offset_m": offset.tolist(),
        "offset_z_up_m": list(offset_z_up(offset)),
        "crs_carried": crs is not None,
        "warnings": notes,
    }
    return table, report



# -- E57 (pye57 / libE57Format) -----------------------------------------------------------------

#: A point takes at least one bit of an E57 compressed vector: a larger recordCount is a lie,
#: refused before pye57 allocates its buffers.
_E57_MAX_POINTS_PER_BYTE = 8


@dataclass
class _FileCloud:
    """A format's points with what it says besides xyz (file frame and units)."""

    points: F64
    colours: U8 | None
    echo: NDArray[np.uint16] | None
    origins: F64 | None = None
    grid: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None
    invalid: int = 0


def _read_e57(path: Path, warnings_out: list[str]) -> _FileCloud:
    """Every ``data3D`` scan of an E57 file in the file's frame (each scan's pose applied),
    each point's sensor origin (its scan's pose translation), intensity (whole numbers in
    0…65535 kept, else scaled by ``intensityLimits``), 8-bit colour and, for a single scan,
    its ``rowIndex``/``columnIndex`` grid. Invalid points (``…InvalidState`` ≠ 0) are
    no-returns."""
    import pye57

    with path.open("rb") as handle:
        if handle.read(8) != b"ASTM-E57":
            raise ArtifactError(f"{path}: not an E57 file (no 'ASTM-E57' signature)")
    try:
        reader = pye57.E57(str(path))
    except Exception as err:  # libE57Format raises its own exception types
        raise ArtifactError(f"{path}: not a readable E57 file ({_first_line(err)})") from None
    try:
        scans = [_e57_scan(path, reader, index, warnings_out)
                 for index in range(reader.scan_count)]
    except ArtifactError:
        raise
    except Exception as err:  # libE57Format's types, ValueError, KeyError from pye57
        raise ArtifactError(f"{path}: not a readable E57 file "
                            f"({type(err).__name__}: {_first_line(err)})") from None
    finally:
        reader.close()
    if not scans:
        raise ArtifactError(f"{path}: E57 file has no scan (its data3D is empty)")
    grid = scans[0].grid if len(scans) == 1 else None
    if len(scans) > 1:
        warnings_out.append(f"{path}: {len(scans)} E57 scans merged in the file's frame, each "
                            "with its scan position as the sensor origin (no grid kept)")
    colours = (np.concatenate([s.colours for s in scans if s.colours is not None])
               if all(s.colours is not None for s in scans) else None)
    echo = (np.concatenate([s.echo for s in scans if s.echo is not None])
            if all(s.echo is not None for s in scans) else None)
    return _FileCloud(np.concatenate([s.points for s in scans]), colours, echo,
                      np.concatenate([s.origins for s in scans if s.origins is not None]),
                      grid, sum(s.invalid for s in scans))


def _first_line(err: Exception) -> str:
    """libE57Format's messages run over many lines (debug context); the first says it."""
    lines = str(err).strip().splitlines()
    return lines[0].strip() if lines else type(err).__name__


def _e57_limits(header: object, node: str, low: str, high: str) -> tuple[float, float] | None:
    """A ``…Limits`` structure's (minimum, maximum), or None when the scan has none."""
    scan = header.node  # type: ignore[attr-defined]
    if not scan.isDefined(node):
        return None
    limits = scan[node]
    if not (limits.isDefined(low) and limits.isDefined(high)):
        return None
    return float(limits[low].value()), float(limits[high].value())


#: E57 fields read and the numpy type of their buffer (libE57Format converts into it): wide
#: integers, so 16-bit colours and more than 65535 rows fit (pye57's own buffers are uint8
#: and uint16 and fail on them).
_E57_FIELDS = {"cartesianX": "d", "cartesianY": "d", "cartesianZ": "d",
               "sphericalRange": "d", "sphericalAzimuth": "d", "sphericalElevation": "d",
               "cartesianInvalidState": "q", "sphericalInvalidState": "q", "intensity": "d",
               "colorRed": "q", "colorGreen": "q", "colorBlue": "q", "rowIndex": "q",
               "columnIndex": "q"}


def _e57_fields(reader: object, header: object, count: int) -> dict[str, NDArray[np.generic]]:
    """The scan's fields that scanpipe uses, read into buffers of :data:`_E57_FIELDS`."""
    from pye57 import libe57

    data: dict[str, NDArray[np.generic]] = {}
    buffers = libe57.VectorSourceDestBuffer()
    for name in header.point_fields:  # type: ignore[attr-defined]
        if name in _E57_FIELDS:
            data[name] = np.empty(count, _E57_FIELDS[name])
            buffers.append(libe57.SourceDestBuffer(reader.image_file,  # type: ignore
                                                   name, data[name], count, True, True))
    if count:
        vector_reader = header.points.reader(buffers)  # type: ignore[attr-defined]
        try:
            vector_reader.read()
        finally:
            vector_reader.close()
    return data


def _e57_field_maximum(header: object, name: str) -> float | None:
    """The maximum an integer field's prototype declares, or None."""
    from pye57 import libe57

    prototype = libe57.StructureNode(header.points.prototype())  # type: ignore[attr-defined]
    if not prototype.isDefined(name):
        return None
    node = prototype.get(name)
    if node.type() != libe57.NodeType.E57_INTEGER:
        return None
    return float(libe57.IntegerNode(node).maximum())


def _e57_scan(path: Path, reader: object, index: int, warnings_out: list[str]) -> _FileCloud:
    header = reader.get_header(index)  # type: ignore[attr-defined]
    count = int(header.point_count)
    if count > path.stat().st_size * _E57_MAX_POINTS_PER_BYTE:
        raise ArtifactError(f"{path}: E57 scan {index} claims {count} points; the file's "
                            f"{path.stat().st_size} bytes cannot hold that many")
    fields = set(header.point_fields)
    data = _e57_fields(reader, header, count)
    if {"cartesianX", "cartesianY", "cartesianZ"} <= fields:
        xyz = np.stack([np.asarray(data[f"cartesian{a}"], np.float64) for a in "XYZ"], axis=1)
        state = data.get("cartesianInvalidState")
    elif {"sphericalRange", "sphericalAzimuth", "sphericalElevation"} <= fields:
        # E57 angles are radians: azimuth from +x towards +y, elevation from the x-y plane.
        xyz = polar_to_xyz(np.asarray(data["sphericalRange"], np.float64),
                           np.degrees(np.asarray(data["sphericalAzimuth"], np.float64)),
                           np.degrees(np.asarray(data["sphericalElevation"], np.float64)))
        state = data.get("sphericalInvalidState")
    else:
        raise ArtifactError(f"{path}: E57 scan {index} has neither cartesianX/Y/Z nor "
                            f"sphericalRange/Azimuth/Elevation (fields: "
                            f"{', '.join(sorted(fields)) or 'none'})")
    valid = np.ones(count, bool) if state is None else np.asarray(state) == 0
    rotation = np.asarray(header.rotation_matrix, np.float64)
    translation = np.asarray(header.translation, np.float64)
    points = xyz[valid] @ rotation.T + translation
    where = f"{path} scan {index}"
    echo = None
    if "intensity" in data:
        values = np.asarray(data["intensity"], np.float64)[valid]
        limits = _e57_limits(header, "intensityLimits", "intensityMinimum", "intensityMaximum")
        whole = values.size == 0 or bool(np.all(values == np.round(values))
                                         and values.min() >= 0
                                         and values.max() <= ECHO_FULL_SCALE)
        if not whole and limits is not None and limits[1] > limits[0]:
            values = (values - limits[0]) / (limits[1] - limits[0])
            warnings_out.append(f"{where}: intensity scaled from its intensityLimits "
                                f"{limits[0]:g}…{limits[1]:g} to the echo's "
                                f"0…{ECHO_FULL_SCALE:g}")
            values = values * ECHO_FULL_SCALE
            echo = np.clip(np.rint(values), 0, ECHO_FULL_SCALE).astype(np.uint16)
        else:
            echo = _intensity_to_echo(Path(where), values, "e57", warnings_out)
    colours = None
    if {"colorRed", "colorGreen", "colorBlue"} <= set(data):
        rgb = np.stack([np.asarray(data[f"color{c}"], np.int64)[valid]
                        for c in ("Red", "Green", "Blue")], axis=1)
        # The colour's range: colorLimits, else the field's own (its prototype's maximum).
        limits = _e57_limits(header, "colorLimits", "colorRedMinimum", "colorRedMaximum")
        top = limits[1] if limits is not None else _e57_field_maximum(header, "colorRed")
        if top is None:
            top = 65535.0 if rgb.size and rgb.max() > 255 else 255.0
        if top == 65535.0:  # 16 bits: the high byte (exact for both c·256 and c·257)
            colours = (np.clip(rgb, 0, 65535) >> 8).astype(np.uint8)
        elif top > 255.0:
            colours = np.clip(np.rint(rgb * 255.0 / top), 0, 255).astype(np.uint8)
        else:
            colours = np.clip(rgb, 0, 255).astype(np.uint8)
    grid = None
    if "rowIndex" in data and "columnIndex" in data:
        grid = (np.asarray(data["rowIndex"], np.int32)[valid],
                np.asarray(data["columnIndex"], np.int32)[valid])
    return _FileCloud(points, colours, echo, np.broadcast_to(translation, points.shape).copy(),
                      grid, int(count - np.count_nonzero(valid)))


# -- PCD (PCL's point cloud data) ---------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
_PCD_HEADER_MAX_BYTES = 1 << 16
#: LZF (binary_compressed) shrinks constant data ~100×; no real file gets near this.
_PCD_MAX_COMPRESSION = 1024


@dataclass(frozen=True)
class _PcdHeader:
    fields: tuple[str, ...]
    dtype: np.dtype[np.void]
    width: int
    height: int
    points: int
    viewpoint: tuple[float, ...]
    data: str
    header_bytes: int


def _pcd_header(path: Path) -> _PcdHeader:
    with path.open("rb") as handle:
        head = handle.read(_PCD_HEADER_MAX_BYTES)
    values: dict[str, list[str]] = {}
    offset = 0
    for raw_line in head.split(b"\n"):
        offset += len(raw_line) + 1
        try:
            words = raw_line.decode("ascii").split()
        except UnicodeDecodeError:
            break
        if not words or words[0].startswith("#"):
            continue
        values[words[0].upper()] = words[1:]
        if words[0].upper() == "DATA":
            break
    if "DATA" not in values or "FIELDS" not in values:
        raise ArtifactError(f"{path}: not a PCD file (no FIELDS and DATA lines in its header)")
    try:
        fields = values["FIELDS"]
        sizes = [int(v) for v in values.get("SIZE", [])]
        types = values.get("TYPE", [])
        counts = [int(v) for v in values.get("COUNT", ["1"] * len(fields))]
        width, height = int(values["WIDTH"][0]), int(values.get("HEIGHT", ["1"])[0])
        points = int(values.get("POINTS", [str(width * height)])[0])
        viewpoint = tuple(float(v) for v in values.get("VIEWPOINT", ["0"] * 3 + ["1"]
                                                             + ["0"] * 3))
        data = values["DATA"][0].lower()
        if not (len(sizes) == len(types) == len(counts) == len(fields)) or min(counts) < 1:
            raise ValueError("FIELDS, SIZE, TYPE and COUNT differ in length")
        if points < 0 or width < 0 or height < 0 or len(viewpoint) != 7:
            raise ValueError("negative POINTS/WIDTH/HEIGHT or a VIEWPOINT of not 7 numbers")
        names = [f"{name}_{k}" if name == "_" else name for k, name in enumerate(fields)]
        dtype = np.dtype([(n, "<" + _PCD_TYPES[(t.upper(), s)], (c,)) if c > 1 else
                          (n, "<" + _PCD_TYPES[(t.upper(), s)])
                          for n, t, s, c in zip(names, types, sizes, counts, strict=True)])
    except (KeyError, ValueError, IndexError) as err:
        raise ArtifactError(f"{path}: PCD header is not valid ({err}); need FIELDS, SIZE, TYPE "
                            "(F, I or U), COUNT, WIDTH, POINTS and DATA") from None
    if data not in ("ascii", "binary", "binary_compressed"):
        raise ArtifactError(f"{path}: PCD DATA {data!r}; allowed: ascii, binary, "
                            "binary_compressed")
    return _PcdHeader(tuple(names), dtype, width, height, points, viewpoint, data, offset)


def _read_pcd(path: Path, warnings_out: list[str]) -> _FileCloud:
    """A PCD file (ascii, binary; binary_compressed through Open3D): x y z, ``rgb``/``rgba``
    (packed; PCL writes it as an unsigned integer in ASCII files although its TYPE is F —
    Open3D's reader then makes wrong colours, so ASCII is read here), ``intensity``, the grid
    of an organised cloud (HEIGHT > 1) and the VIEWPOINT's position, unless 0 0 0, as the
    sensor origin."""
    header = _pcd_header(path)
    if not {"x", "y", "z"} <= set(header.fields):
        raise ArtifactError(f"{path}: PCD FIELDS has no x, y, z ({' '.join(header.fields)})")
    if header.points == 0:
        raise ArtifactError(f"{path}: PCD file has 0 points")
    available = path.stat().st_size - header.header_bytes
    per_point = {"ascii": 2 * sum(max(1, int(np.prod(header.dtype[n].shape)))
                                  for n in header.fields),
                 "binary": header.dtype.itemsize,
                 "binary_compressed": header.dtype.itemsize / _PCD_MAX_COMPRESSION}[header.data]
    if header.points * per_point > available:
        raise ArtifactError(f"{path}: PCD header field 'POINTS {header.points}' needs at least "
                            f"{header.points * per_point:.0f} bytes of {header.data} data but "
                            f"the file has {available} after its header")
    rgb_bits: NDArray[np.uint32] | None = None
    intensity: F64 | None = None
    if header.data == "binary_compressed":
        points, colours, intensity = _pcd_open3d(path, header)
    else:
        if header.data == "binary":
            records = np.fromfile(path, dtype=header.dtype, count=header.points,
                                  offset=header.header_bytes)
            columns = {n: np.asarray(records[n]) for n in header.fields}
        else:
            columns = _pcd_ascii(path, header)
        points = np.stack([np.asarray(columns[a], np.float64).reshape(-1) for a in "xyz"],
                          axis=1)
        packed = next((n for n in ("rgb", "rgba") if n in columns), None)
        if packed is not None:
            rgb_bits = _pcd_packed(columns[packed], header.data)
        if "intensity" in columns:
            intensity = np.asarray(columns["intensity"], np.float64).reshape(-1)
        colours = None
        if rgb_bits is not None:
            colours = np.stack([(rgb_bits >> 16) & 255, (rgb_bits >> 8) & 255, rgb_bits & 255],
                               axis=1).astype(np.uint8)
    echo = (None if intensity is None
            else _intensity_to_echo(path, intensity, "pcd", warnings_out))
    grid = None
    if header.height > 1 and header.width * header.height == len(points):
        index = np.arange(len(points), dtype=np.int32)
        grid = (index // header.width, index % header.width)
    # PCL writes VIEWPOINT 0 0 0 1 0 0 0 whatever the sensor was: only a position stated
    # elsewhere is the sensor's; at the origin the user's --origin applies.
    origins = (np.broadcast_to(np.asarray(header.viewpoint[:3], np.float64), points.shape).copy()
               if any(header.viewpoint[:3]) else None)
    return _FileCloud(points, colours, echo, origins, grid)


def _pcd_ascii(path: Path, header: _PcdHeader) -> dict[str, F64]:
    try:
        with path.open("rb") as raw:
            raw.seek(header.header_bytes)
            text = io.TextIOWrapper(raw, encoding="ascii", errors="strict")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                values = np.loadtxt(text, dtype=np.float64, max_rows=header.points, ndmin=2)
    except ValueError as err:  # UnicodeDecodeError included
        raise ArtifactError(f"{path}: PCD ascii data is not a table of numbers ({err})") from None
    widths = [max(1, int(np.prod(header.dtype[n].shape))) for n in header.fields]
    if values.shape != (header.points, sum(widths)):
        raise ArtifactError(f"{path}: PCD header says {header.points} points of {sum(widths)} "
                            f"values; the data has {values.shape[0]} lines of "
                            f"{values.shape[1] if values.ndim == 2 else 0}")
    starts = np.cumsum([0, *widths])
    return {n: values[:, starts[k]:starts[k + 1]] for k, n in enumerate(header.fields)}


def _pcd_packed(values: NDArray[np.generic], data: str) -> NDArray[np.uint32]:
    """Packed 0xAARRGGBB colours. Binary: the field's bits. ASCII: a whole number is the
    integer PCL writes; anything else is the float whose bits hold the colour."""
    flat = np.asarray(values).reshape(-1)
    if data == "binary":
        return flat.view(np.uint32) if flat.dtype.itemsize == 4 else flat.astype(np.uint32)
    numbers = np.asarray(flat, np.float64)
    whole = np.isfinite(numbers) & (numbers == np.round(numbers)) & (numbers >= 0) & (
        numbers < 2.0**32)
    bits = np.asarray(numbers, np.float32).view(np.uint32)
    return np.where(whole, np.where(whole, numbers, 0).astype(np.uint32), bits)


def _pcd_open3d(path: Path, header: _PcdHeader) -> tuple[F64, U8 | None, F64 | None]:
    """binary_compressed (LZF) through Open3D, which keeps every point in order."""
    import open3d as o3d

    cloud = o3d.t.io.read_point_cloud(path, remove_nan_points=False,
                                      remove_infinite_points=False)
    attributes = set(cloud.point)
    if "positions" not in attributes or len(cloud.point.positions) != header.points:
        raise ArtifactError(f"{path}: PCD binary_compressed data could not be read (Open3D read "
                            f"{len(cloud.point.positions) if 'positions' in attributes else 0} "
                            f"of {header.points} points)")
    points = np.asarray(cloud.point.positions.numpy(), np.float64)
    colours = None
    if "colors" in attributes:
        rgb = cloud.point.colors.numpy()
        colours = (rgb if rgb.dtype == np.uint8 else
                   np.clip(np.rint(np.asarray(rgb, np.float64) * 255.0), 0, 255)
                   ).astype(np.uint8)
    intensity = (np.asarray(cloud.point.intensity.numpy(), np.float64).reshape(-1)
                 if "intensity" in attributes else None)
    return points, colours, intensity
