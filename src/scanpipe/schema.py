"""Every artifact's Arrow schema, named once: its columns, their units and types, what it carries.

A stage declares its inputs and outputs by artifact name (:attr:`scanpipe.stage.Stage.inputs`);
the runner checks each table against its schema when it reads and when it writes one, and
names the artifact, the column and the type on a mismatch. Code that reads a table refers to
the schema (``POINTS.names("xyz")``, ``POINTS.check(table)``) rather than spelling columns
out again. To add a column: add it here (required only if every writer writes it), then write
and read it; docs/artifacts.md describes each artifact for people.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import pyarrow as pa

from scanpipe.errors import ArtifactError, ScanpipeError


@dataclass(frozen=True)
class Column:
    """One column: name (with its unit), Arrow type, whether every writer writes it."""

    name: str
    type: pa.DataType
    required: bool = True
    description: str = ""


@dataclass(frozen=True)
class ArtifactSchema:
    """An artifact: its columns in order, and what its provenance report carries."""

    name: str
    columns: tuple[Column, ...]
    description: str
    #: Keys of the provenance report readers rely on (beyond the runner's own record).
    metadata: tuple[str, ...] = ()

    def column(self, name: str) -> Column:
        """The column called ``name`` (:class:`ArtifactError` when the artifact has none)."""
        for column in self.columns:
            if column.name == name:
                return column
        raise ArtifactError(f"{self.name}: no column {name!r} in its schema; columns: "
                            f"{', '.join(c.name for c in self.columns)}")

    def names(self, names: Iterable[str] | None = None) -> tuple[str, ...]:
        """Column names: all of them, or the given ones after checking that they exist.

        A string of one-letter names works too: ``POINTS.names("xyz")``.
        """
        if names is None:
            return tuple(c.name for c in self.columns)
        return tuple(self.column(n).name for n in names)

    def types(self, names: Iterable[str] | None = None) -> dict[str, pa.DataType]:
        """Name → type of the given columns (default: the required ones)."""
        chosen = [c for c in self.columns if c.required] if names is None else [
            self.column(n) for n in names]
        return {c.name: c.type for c in chosen}

    @property
    def arrow_schema(self) -> pa.Schema:
        """The full schema, optional columns included (what a writer of all of it uses)."""
        return pa.schema([pa.field(c.name, c.type) for c in self.columns])

    def check(self, table: pa.Table, columns: Iterable[str] | None = None,
              where: str | None = None) -> None:
        """Raise :class:`ArtifactError` naming every missing column and every wrong type.

        ``columns`` limits the check to what a reader needs (default: every required column,
        and the type of every optional column present).
        """
        label = where or self.name
        wanted = self.types(columns) if columns is not None else self.types()
        problems = []
        for name, dtype in wanted.items():
            if name not in table.column_names:
                problems.append(f"missing column {name!r} ({dtype})")
            elif not table.schema.field(name).type.equals(dtype):
                problems.append(f"column {name!r} is {table.schema.field(name).type}, "
                                f"expected {dtype}")
        if columns is None:
            for column in self.columns:
                if column.required or column.name not in table.column_names:
                    continue
                actual = table.schema.field(column.name).type
                if not actual.equals(column.type):
                    problems.append(f"column {column.name!r} is {actual}, expected "
                                    f"{column.type}")
        if problems:
            raise ArtifactError(f"{label}: " + "; ".join(problems))


def _columns(types: Mapping[str, pa.DataType], required: bool = True,
             description: str = "") -> tuple[Column, ...]:
    return tuple(Column(name, dtype, required, description) for name, dtype in types.items())


F32, F64, I64, I32 = pa.float32(), pa.float64(), pa.int64(), pa.int32()
#: Column groups that several artifacts share, named once.
XYZ = ("x", "y", "z")
ORIGIN = ("origin_x", "origin_y", "origin_z")
NORMAL = ("nx", "ny", "nz")
RGB = ("red", "green", "blue")
FACE_CORNERS = ("v0", "v1", "v2")

RIG = ArtifactSchema(
    "rig", _columns({"toml": pa.string()}),
    "one row: the rig TOML (scanner, motor, cameras, calibration) the later stages compute with",
)
CALIBRATION = ArtifactSchema(
    "calibration",
    (Column("parameter", pa.string()), Column("value", F64), Column("sigma", F64),
     Column("observable", pa.bool_()), Column("unit", pa.string()),
     Column("note", pa.string())),
    "the mount self-calibration: one row per parameter (value, 1σ from the fit's covariance, "
    "null when unobservable; whether the scan constrains it); empty when calibrate is off",
)
PROFILES = ArtifactSchema(
    "profiles",
    (
        Column("recv_time_ns", I64, description="host time the frame was complete"),
        Column("device_time_ns", I64, False, "the sector's start on the device clock (null: "
                                             "the dialect has none)"),
        Column("device_end_time_ns", I64, False, "the sector's end on the device clock"),
        Column("frame", I64, False, "frame (head turn) number, unwrapped"),
        Column("sector", I32, False, "sector of the frame"),
        Column("start_angle_deg", F64, description="beam angle of the first sample"),
        Column("step_deg", F64, description="beam step"),
        Column("ranges_m", pa.list_(F32), description="one range per sample, NaN = no return"),
        Column("echo", pa.list_(pa.uint16()), False, "echo amplitude per sample (null: none)"),
        Column("checksum_ok", pa.bool_(), False, "the frame's checksum held"),
        Column("dialect", pa.string(), False, "the wire format it was decoded from"),
    ),
    "one row per profile sector, in receive order",
    ("device_clock", "counters", "counts"),
)
MOTOR = ArtifactSchema(
    "motor",
    (
        Column("log_time_ns", I64, description="host time the state was read"),
        Column("step_count", I64, description="pulses from the scan start"),
        Column("target_step_count", I64, False, "where the platform is going"),
        Column("moving", pa.bool_(), description="the platform is moving"),
        Column("device_time_us", I64, False, "the controller's own clock"),
    ),
    "every motor state report in log-time order",
)
FRAMES = ArtifactSchema(
    "frames",
    (
        Column("camera_id", pa.string()),
        Column("log_time_ns", I64, description="capture time (host clock)"),
        Column("sequence", I64),
        Column("format", pa.string(), False, "jpeg or png"),
        Column("width", I32, False, "pixels, −1 when unreadable"),
        Column("height", I32, False, "pixels, −1 when unreadable"),
        Column("data", pa.binary(), description="the encoded image"),
    ),
    "camera frames as recorded",
)
POINTS = ArtifactSchema(
    "points",
    (
        *_columns(dict.fromkeys(XYZ, F32), description="rig frame, metres"),
        Column("range_m", F32, description="measured range, NaN = no return"),
        Column("alpha_deg", F64, description="beam angle"),
        Column("beta_deg", F64, description="platform angle"),
        Column("time_ns", I64, description="when the sample was measured (host clock)"),
        Column("profile", I32, description="grid row, −1 for clouds without a grid"),
        Column("sample", I32, description="grid column, −1 for clouds without a grid"),
        *_columns(dict.fromkeys(ORIGIN, F32),
                  description="the sensor's optical centre when the point was measured"),
        Column("echo", pa.uint16(), False, "echo amplitude"),
        *_columns(dict.fromkeys(RGB, pa.uint8()), False, "colour"),
        Column("filtered_by", pa.string(), False, "filter mark mode: the filter that took "
                                                  "the point (null = kept)"),
    ),
    "a point cloud that keeps the scan grid (profile × sample) where it has one",
    ("grid",),
)
MESH_VERTICES = ArtifactSchema(
    "mesh_vertices",
    (*_columns(dict.fromkeys((*XYZ, *NORMAL), F32)),
     *_columns(dict.fromkeys(RGB, pa.uint8()), False, "colour")),
    "vertices with unit normals, rig frame",
)
MESH_FACES = ArtifactSchema(
    "mesh_faces", _columns(dict.fromkeys(FACE_CORNERS, I32), description="vertex index"),
    "triangles, counter-clockwise seen from outside",
)
TEXTURED_FACES = ArtifactSchema(
    "textured_faces",
    (
        Column("face", I32),
        Column("page", pa.int16(), description="atlas page, −1 = untextured"),
        *_columns({n: F32 for n in ("u0", "v0", "u1", "v1", "u2", "v2")},
                  description="texture coordinates, glTF convention (v = 0 at the top)"),
        Column("camera_id", pa.string(), False, "the source frame's camera"),
        Column("frame", I64, False, "the source frame's sequence, −1 when untextured"),
    ),
    "per face: its atlas page and texture coordinates",
)
TEXTURE_PAGES = ArtifactSchema(
    "texture_pages",
    (Column("page", pa.int16()), Column("width", I32), Column("height", I32),
     Column("png", pa.binary())),
    "the atlas pages as PNG",
)
EXPORT_MANIFEST = ArtifactSchema(
    "export_manifest",
    (Column("file", pa.string()), Column("bytes", I64), Column("sha256", pa.string())),
    "the files the export stage wrote beside it",
)
POSES = ArtifactSchema(
    "poses",
    (
        Column("scan", pa.string(), description="the scan (its workdir or recording name)"),
        *_columns(dict.fromkeys(("tx_m", "ty_m", "tz_m"), F64),
                  description="translation: where the scan's rig origin is in the site frame"),
        *_columns(dict.fromkeys(("qw", "qx", "qy", "qz"), F64),
                  description="rotation rig → site as a unit quaternion"),
        Column("covariance", pa.list_(F64), False, "6 × 6 row-major, site frame, twist order "
                                                   "rx, ry, rz, tx, ty, tz (rad², m²); null: none"),
    ),
    "one rigid pose per scan of a site: p_site = R p_rig + t",
)

#: Every artifact by name.
ARTIFACTS: dict[str, ArtifactSchema] = {s.name: s for s in (
    RIG, CALIBRATION, PROFILES, MOTOR, FRAMES, POINTS, MESH_VERTICES, MESH_FACES, TEXTURED_FACES,
    TEXTURE_PAGES, EXPORT_MANIFEST, POSES)}


#: Table metadata key of the georeference offset: whole metres (rig frame, x y z) that were
#: subtracted from a georeferenced cloud so float32 keeps 0.1 mm (``import-points``). The
#: coordinates a surveyor's tools expect are the artifact's plus this offset; exporters add it
#: back (docs/export.md "Georeferenced output"). Every stage passes it from its inputs to its
#: outputs (:meth:`scanpipe.stage.Stage.call`); a table without it has offset 0.
OFFSET_KEY = b"scanpipe.offset_m"
Offset = tuple[float, float, float]
ZERO_OFFSET: Offset = (0.0, 0.0, 0.0)


#: Table metadata key of the coordinate system (WKT) of a georeferenced import whose
#: coordinates are in metres on every axis and in the file's own axes: LAS/LAZ/COPC exports
#: write it instead of a local frame, so GIS tools place them without being told. Passed on
#: like :data:`OFFSET_KEY`.
CRS_KEY = b"scanpipe.crs_wkt"


def crs_of(table: pa.Table) -> str | None:
    """The coordinate system (WKT) a table carries (:data:`CRS_KEY`), None without one."""
    raw = (table.schema.metadata or {}).get(CRS_KEY)
    return None if raw is None else raw.decode("utf-8", "replace")


def with_crs(table: pa.Table, wkt: str | None) -> pa.Table:
    """``table`` carrying the coordinate system ``wkt`` (None: none)."""
    metadata = dict(table.schema.metadata or {})
    metadata.pop(CRS_KEY, None)
    if wkt:
        metadata[CRS_KEY] = wkt.encode()
    return table.replace_schema_metadata(metadata or None)


def common_crs(named: Sequence[tuple[str, pa.Table]], what: str,
               error: type[ScanpipeError] = ArtifactError) -> str | None:
    """The one coordinate system all ``(name, table)`` share (None: none of them has one);
    ``error`` naming two that differ, or one with and one without."""
    if not named:
        return None
    first_name, first = named[0][0], crs_of(named[0][1])
    for name, table in named[1:]:
        other = crs_of(table)
        if other != first:
            def label(wkt: str | None) -> str:
                return "none" if wkt is None else repr(wkt[:60] + ("…" if len(wkt) > 60 else ""))
            raise error(f"{what}: {first_name} has the coordinate system {label(first)} and "
                        f"{name} {label(other)}: import every file of one site from files in "
                        "one coordinate system")
    return first


def offset_of(table: pa.Table) -> Offset:
    """The georeference offset a table carries (:data:`OFFSET_KEY`), (0, 0, 0) without one."""
    raw = (table.schema.metadata or {}).get(OFFSET_KEY)
    if raw is None:
        return ZERO_OFFSET
    try:
        values = [float(v) for v in json.loads(raw)]
    except (ValueError, TypeError):
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ArtifactError(f"table metadata {OFFSET_KEY.decode()!r} is {raw[:80]!r}; expected "
                            "a JSON list of three finite numbers (metres)")
    return values[0], values[1], values[2]


def with_offset(table: pa.Table, offset: Iterable[float]) -> pa.Table:
    """``table`` carrying ``offset`` (:data:`OFFSET_KEY`); a zero offset is not written, so
    tables of clouds that were never shifted stay as they were."""
    values = tuple(float(v) for v in offset)
    metadata = dict(table.schema.metadata or {})
    metadata.pop(OFFSET_KEY, None)
    if any(values):
        metadata[OFFSET_KEY] = json.dumps(list(values)).encode()
    return table.replace_schema_metadata(metadata or None)


def offset_z_up(offset: Iterable[float]) -> Offset:
    """A rig-frame offset in the z-up frame of LAS/E57 exports, ``(x, −z, y)`` (as
    :func:`scanpipe.exporters.model.rig_to_z_up` maps points): what ``import-points --offset``
    takes (for a z-up file, its own x, y, z)."""
    x, y, z = (float(v) for v in offset)
    return x + 0.0, -z + 0.0, y + 0.0  # + 0.0: no −0


def offset_from_z_up(offset: Iterable[float]) -> Offset:
    """The inverse of :func:`offset_z_up`: a z-up offset in the rig frame, ``(x, z, −y)``."""
    x, y, z = (float(v) for v in offset)
    return x + 0.0, z + 0.0, -y + 0.0


def format_offset(offset: Iterable[float]) -> str:
    """A rig-frame offset as ``x,y,z`` in the z-up frame (:func:`offset_z_up`; ``%.17g``):
    the form ``import-points --offset`` takes."""
    return ",".join(f"{v:.17g}" for v in offset_z_up(offset))


def common_offset(named: Sequence[tuple[str, pa.Table]], what: str,
                  error: type[ScanpipeError] = ArtifactError) -> Offset:
    """The one offset all ``(name, table)`` share; ``error`` naming the first two that differ
    (their relative positions would be wrong by the difference)."""
    if not named:
        return ZERO_OFFSET
    first_name, first = named[0][0], offset_of(named[0][1])
    for name, table in named[1:]:
        other = offset_of(table)
        if other != first:
            raise error(
                f"{what}: {first_name} is shifted by offset {format_offset(first)} m and {name} "
                f"by {format_offset(other)} m (x,y,z z-up): merged they would be off by the "
                "difference; import every file of one site with one "
                f"`import-points --offset {format_offset(first)}`")
    return first


def artifact_schema(name: str) -> ArtifactSchema:
    """The schema of artifact ``name``."""
    if name not in ARTIFACTS:
        raise ArtifactError(f"unknown artifact {name!r}; artifacts: {', '.join(ARTIFACTS)}")
    return ARTIFACTS[name]
