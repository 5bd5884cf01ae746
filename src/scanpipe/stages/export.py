"""Export: artifacts to files other tools open (OBJ, GLB, PLY, LAS/LAZ, E57, Foxglove MCAP,
COLMAP).

Pure: :func:`export_files` turns tables into ``{file name: content}`` (bytes, or
:class:`~scanpipe.artifacts.Pieces` for the large OBJ/GLB/PLY files; the shape of
:attr:`scanpipe.stage.StageResult.files`), and the chain's export stage is that plus a
manifest. Writing files for ``scanpipe export`` is the shell's: :mod:`scanpipe.exporting`.

What each format takes: ``obj`` and ``glb`` the mesh (+ texture when present); ``las``,
``laz`` and ``e57`` the points (``e57`` also the camera frames when there are frames);
``ply`` the mesh, or the points when there is no mesh;
``mcap`` both when present (the points for scrubbing the scan, the mesh as a model);
``colmap`` the camera frames, their poses and the points.

One code path for ``scanpipe run`` and ``scanpipe export``: :func:`prepare_tables` colours the
points from the camera frames (when there are frames) for both, and :func:`export_files`
writes every format from the same tables, with the provenance of the exported artifacts
(:func:`provenance_of`) in the files' metadata where the format has room.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pyarrow as pa
from pydantic import Field

from scanpipe import __version__
from scanpipe.artifacts import PROVENANCE_KEY, FileData
from scanpipe.errors import ArtifactError, ExportError, UsageError
from scanpipe.exporters.e57 import E57Image, e57_bytes
from scanpipe.exporters.glb import glb_pieces
from scanpipe.exporters.las import LAS_VERSIONS, frame_wkt, las_bytes, pdal_pipeline_bytes
from scanpipe.exporters.mcap_foxglove import camera_views_from_tables, foxglove_export_files
from scanpipe.exporters.model import (
    CLOUD_COLUMNS,
    TEXTURED_FACE_COLUMNS,
    CloudModel,
    MeshModel,
    cloud_from_table,
    geo_z_up,
    mesh_from_tables,
    provenance_bytes,
    rig_to_z_up,
)
from scanpipe.exporters.obj import obj_files
from scanpipe.exporters.ply import ply_cloud_pieces, ply_mesh_pieces
from scanpipe.params import Params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.schema import ZERO_OFFSET, Offset, format_offset, offset_z_up
from scanpipe.stage import Inputs, Stage, StageResult, narrow_input, release_inputs

if TYPE_CHECKING:
    from scanpipe.camera import F64
    from scanpipe.rig import CameraConfig

FORMATS: tuple[str, ...] = ("obj", "glb", "ply", "las", "laz", "copc", "e57", "mcap", "colmap")
#: The file suffix of a format where it is not the format's name.
SUFFIXES = {"copc": ".copc.laz"}
MESH_ARTIFACTS = ("mesh_vertices", "mesh_faces")
TEXTURE_ARTIFACTS = ("textured_faces", "texture_pages")
#: What colouring the points and posing the frames need (optional for every format but colmap).
CAMERA_ARTIFACTS = ("frames", "motor", "rig")
INPUT_ARTIFACTS = (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points")
#: Formats that read the camera artifacts (beside the points' colours): the only ones that read
#: tables beyond the models and the tables' provenance.
CAMERA_FORMATS = frozenset({"mcap", "e57", "colmap"})
#: The frame spacing (degrees of platform angle) of point colouring and the COLMAP export.
FRAME_SPACING_DEG = 5.0


class FormatError(ExportError, UsageError):
    """An unknown export format, or an output name that contradicts it (a usage error: exit 2)."""

    exit_code = 2


def check_format(fmt: str) -> str:
    """The format name in lower case, or a FormatError listing the formats."""
    lowered = fmt.lower().lstrip(".")
    if lowered not in FORMATS:
        raise FormatError(f"--format {fmt!r}: unknown format; allowed: {', '.join(FORMATS)}")
    return lowered


def check_las_version(version: str) -> str:
    """``version`` when it is a LAS version the exporter writes, else a FormatError."""
    if version not in LAS_VERSIONS:
        raise FormatError(f"--las-version {version!r}: allowed: {', '.join(LAS_VERSIONS)}")
    return version


def models_from_tables(tables: Mapping[str, pa.Table]) -> tuple[MeshModel | None,
                                                                   CloudModel | None]:
    """The mesh (with texture when both texture artifacts exist) and the cloud, where given."""
    mesh = None
    if all(name in tables for name in MESH_ARTIFACTS):
        textured = all(name in tables for name in TEXTURE_ARTIFACTS)
        mesh = mesh_from_tables(tables["mesh_vertices"], tables["mesh_faces"],
                                tables["textured_faces"] if textured else None,
                                tables["texture_pages"] if textured else None)
    cloud = cloud_from_table(tables["points"]) if "points" in tables else None
    return mesh, cloud


def provenance_of(tables: Mapping[str, pa.Table]) -> dict[str, Any]:
    """What an exported file records about its making: the scanpipe version and, per artifact
    it was made from, the key, stage and parameters (from the artifact's Parquet metadata)."""
    record: dict[str, Any] = {"scanpipe": __version__, "artifacts": {}}
    for name, table in sorted(tables.items()):
        raw = (table.schema.metadata or {}).get(PROVENANCE_KEY)
        if raw is None:
            continue
        try:
            meta = json.loads(raw)
        except ValueError:
            continue
        if isinstance(meta, dict):
            record["artifacts"][name] = {k: meta.get(k) for k in ("key", "stage", "params")}
    return record


def prepare_tables(tables: Mapping[str, pa.Table], colors: bool = True,
                   progress: ProgressFn = no_progress, keep_frames: bool = True
                   ) -> tuple[dict[str, pa.Table], bool]:
    """The tables every export format reads, and whether the points were coloured: the points
    get ``red/green/blue`` from the camera frames when ``colors`` and there are frames (the
    same for ``run`` and ``export``; the points artifact's provenance is kept).

    Without ``keep_frames`` (no format reads the frames) the frames are released once the
    colouring has chosen its own (:func:`scanpipe.stage.release_inputs`, where ``tables`` were
    handed over) and are an empty table of their schema in the result."""
    out = dict(tables)
    points = out.get("points")
    if (not colors or points is None or not all(n in out for n in CAMERA_ARTIFACTS)
            or out["frames"].num_rows == 0):
        return out, False
    from scanpipe.rig import rig_from_table
    from scanpipe.texturing.projective import colorize_points

    def chosen() -> None:
        if not keep_frames:
            out["frames"] = out["frames"].schema.empty_table()
            release_inputs(tables, "frames")

    coloured = colorize_points(points, out["frames"], out["motor"], rig_from_table(out["rig"]),
                               spacing_deg=FRAME_SPACING_DEG, progress=progress,
                               frames_chosen=chosen)
    out["points"] = coloured.replace_schema_metadata(points.schema.metadata)
    return out, True


def export_files(tables: Mapping[str, pa.Table], fmt: str, stem: str,
                 las_version: str = "1.2", draco: bool = False,
                 models: tuple[MeshModel | None, CloudModel | None] | None = None
                 ) -> dict[str, FileData]:
    """The files of one export, by name; the first is the main file. ``tables`` as
    :func:`prepare_tables` gives them; ``draco`` compresses a GLB's geometry. ``models`` is
    :func:`models_from_tables` of ``tables`` when the caller has it (built once per stage)."""
    fmt = check_format(fmt)
    check_las_version(las_version)
    mesh, cloud = models_from_tables(tables) if models is None else models
    if fmt in ("obj", "glb") or (fmt == "ply" and mesh is not None):
        if mesh is None:
            raise ArtifactError(f"{fmt} export needs a mesh (mesh_vertices and mesh_faces "
                                f"artifacts); found: {', '.join(sorted(tables)) or 'nothing'}")
        provenance = provenance_of({k: v for k, v in tables.items()
                                    if k in (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS)})
        if fmt == "obj":
            return obj_files(mesh, stem, provenance)
        if fmt == "glb":
            return {f"{stem}.glb": glb_pieces(mesh, stem, provenance, draco)}
        return {f"{stem}.ply": ply_mesh_pieces(mesh, provenance)}
    if fmt == "mcap":
        return {**foxglove_export_files(cloud, mesh, stem, camera_views_from_tables(tables),
                                        provenance_of(tables))}
    provenance = provenance_of({k: v for k, v in tables.items() if k == "points"})
    if fmt == "colmap":
        return _colmap(tables, cloud, stem, provenance)
    if cloud is None:
        raise ArtifactError(f"{fmt} export needs a points artifact; found: "
                            f"{', '.join(sorted(tables)) or 'nothing'}")
    if fmt == "ply":
        return {f"{stem}.ply": ply_cloud_pieces(cloud, provenance)}
    if fmt in ("las", "laz"):
        return {f"{stem}.{fmt}": las_bytes(cloud, compressed=fmt == "laz", version=las_version,
                                           provenance=provenance),
                f"{stem}.{fmt}.pipeline.json": pdal_pipeline_bytes(f"{stem}.{fmt}",
                                                                   srs=frame_wkt(cloud))}
    if fmt == "copc":
        from scanpipe.exporters.copc import copc_bytes

        return {f"{stem}.copc.laz": copc_bytes(cloud, provenance),
                f"{stem}.copc.laz.pipeline.json": pdal_pipeline_bytes(
                    f"{stem}.copc.laz", "readers.copc", frame_wkt(cloud))}
    return {f"{stem}.e57": e57_bytes(cloud, stem, provenance_bytes(provenance).decode(),
                                     e57_images(tables, cloud.offset_m))}


def _chosen_frames(tables: Mapping[str, pa.Table]) -> tuple[
        list[CameraConfig], list[tuple[F64, F64]], list[bytes], list[str], list[str]]:
    """The frames COLMAP and E57 carry (the sharpest per camera every FRAME_SPACING_DEG):
    their cameras, poses camera → rig, encoded bytes, formats (jpeg/png) and file names.
    Only pinhole cameras: neither format has the 360° (equirect) model."""
    from scanpipe.camera import camera_pose_in_rig
    from scanpipe.rig import rig_from_table
    from scanpipe.texturing.frames import choose_frames, pinhole_frames

    frames, rig, _ = pinhole_frames(tables["frames"], rig_from_table(tables["rig"]))
    if frames.num_rows == 0:
        return [], [], [], [], []
    chosen = choose_frames(frames, tables["motor"], rig, FRAME_SPACING_DEG)
    formats = tables["frames"].column("format").to_pylist() if (
        "format" in tables["frames"].column_names) else []
    by_sequence = dict(zip(tables["frames"].column("sequence").to_pylist(),
                           formats or ["jpeg"] * tables["frames"].num_rows, strict=True))
    kinds = ["png" if by_sequence.get(int(seq)) == "png" else "jpeg"
             for seq in chosen.sequences]
    names = [f"{cam.id}_{int(seq):06d}.{'png' if kind == 'png' else 'jpg'}"
             for cam, seq, kind in zip(chosen.cameras, chosen.sequences, kinds, strict=True)]
    poses = [camera_pose_in_rig(cam, float(beta))
             for cam, beta in zip(chosen.cameras, chosen.beta_deg, strict=True)]
    return list(chosen.cameras), poses, list(chosen.encoded), kinds, names


def _colmap(tables: Mapping[str, pa.Table], cloud: CloudModel | None, stem: str,
            provenance: Mapping[str, Any]) -> dict[str, FileData]:
    missing = [n for n in CAMERA_ARTIFACTS if n not in tables]
    if missing or tables["frames"].num_rows == 0:
        raise ArtifactError("colmap export needs camera frames (frames, motor and rig "
                            f"artifacts with frames); found: {', '.join(sorted(tables))}")
    from scanpipe.exporters.colmap import colmap_files

    cameras, poses, encoded, _, names = _chosen_frames(tables)
    if not cameras:
        raise ArtifactError("colmap export needs frames of a pinhole camera; the rig's are "
                            "360° (equirect), which COLMAP has no model for")
    return {**colmap_files(stem, cameras, poses, encoded, names, cloud,
                           provenance_bytes(provenance).decode())}


#: The E57 camera frame as CloudCompare's E57 reader uses it (the image pose becomes a
#: ``ccCameraSensor`` unchanged; that sensor looks along −z with image y up:
#: ``u = cx + f·x/(−z)``, ``v = cy − f·y/(−z)``) in OpenCV's optical frame (x right, y down,
#: z forward): x kept, y and z negated.
E57_CAMERA_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


def pinhole_image(data: bytes, kind: str, cam: CameraConfig) -> bytes:
    """The frame as an exact pinhole image of ``cam``'s K: undistorted (same size and K) when
    the camera has distortion coefficients, re-encoded as ``kind`` (jpeg/png); unchanged
    otherwise. E57's pinhole model has no distortion terms."""
    if not any(cam.distortion):
        return data
    import cv2

    from scanpipe.camera import intrinsic_matrix
    from scanpipe.images import decode_image_bytes, encode_jpeg, encode_png

    image = decode_image_bytes(data, f"frame of camera {cam.id}")
    k = intrinsic_matrix(cam)
    flat = cv2.undistort(image, k, np.asarray(cam.distortion, np.float64), None, k)
    return encode_png(flat) if kind == "png" else encode_jpeg(flat, quality=95)


def e57_images(tables: Mapping[str, pa.Table], offset_m: Offset = ZERO_OFFSET
               ) -> list[E57Image]:
    """The camera frames as E57 images (none without frames), posed in the file's z-up frame
    (the frame the points are written in: :func:`rig_to_z_up`, plus the points' georeference
    offset ``offset_m``, rig frame) with CloudCompare's camera axes
    (:data:`E57_CAMERA_FROM_OPENCV`), undistorted when the lens has distortion."""
    if not all(n in tables for n in CAMERA_ARTIFACTS) or tables["frames"].num_rows == 0:
        return []
    from scanpipe.exporters.colmap import quaternion_wxyz

    images = []
    for cam, (rotation, translation), data, kind, name in zip(
            *_chosen_frames(tables), strict=True):
        # camera (E57 axes) → OpenCV axes → rig → file: M @ R @ E
        to_file = rig_to_z_up((np.asarray(rotation) @ E57_CAMERA_FROM_OPENCV).T).T
        q = quaternion_wxyz(to_file)
        t = geo_z_up(np.asarray(translation)[None, :], offset_m)[0]
        note = ("" if not any(cam.distortion) else
                "undistorted from OpenCV k1 k2 p1 p2 k3 = "
                + " ".join(f"{float(v):.17g}" for v in cam.distortion))
        images.append(E57Image(pinhole_image(data, kind, cam), cam.width, cam.height, cam.fx,
                               cam.fy, cam.cx, cam.cy,
                               (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
                               (float(t[0]), float(t[1]), float(t[2])), name, kind, note))
    return images


MeshFormat = Literal["obj", "glb", "ply", "mcap"]
CloudFormat = Literal["ply", "las", "laz", "copc", "e57", "colmap"]


class ExportStageParams(Params):
    """The export at the end of ``scanpipe run``: which files to write from the chain."""

    mesh_formats: tuple[MeshFormat, ...] = Field(
        ("obj", "glb"), description="formats of the textured mesh")
    cloud_formats: tuple[CloudFormat, ...] = Field(
        ("ply",), description="formats of the filtered point cloud")
    name: str = Field("model", pattern=r"^[A-Za-z0-9_.-]+$",
                      description="stem of the mesh files")
    cloud_name: str = Field("cloud", pattern=r"^[A-Za-z0-9_.-]+$",
                            description="stem of the point-cloud files")
    cloud_colors: bool = Field(
        True, description="colour the cloud from the camera frames (when there are frames)")
    las_version: Literal["1.2", "1.4"] = Field(
        "1.2", description="LAS version of las/laz: 1.2 (formats 0-3, widely read) or 1.4")
    glb_draco: bool = Field(
        False, description="Draco-compress the GLB's geometry (KHR_draco_mesh_compression)")


def export_stage(inputs: Mapping[str, pa.Table], params: ExportStageParams,
                 progress: ProgressFn) -> StageResult:
    """The chain's export: every requested file, and a manifest table naming them."""
    if params.name == params.cloud_name:
        raise UsageError(f"export.name and export.cloud_name are both {params.name!r}: "
                         "the mesh and the cloud files would overwrite each other")
    files: dict[str, FileData] = {}
    # only these formats read tables beyond the models: otherwise inputs go as they are used
    reads_tables = bool({*params.mesh_formats, *params.cloud_formats} & CAMERA_FORMATS)
    if not reads_tables:  # what no model is made of goes before the colouring
        narrow_input(inputs, "textured_faces", TEXTURED_FACE_COLUMNS)
        narrow_input(inputs, "points", CLOUD_COLUMNS)
    tables, coloured = prepare_tables(
        inputs, params.cloud_colors and bool(params.cloud_formats or "mcap" in
                                             params.mesh_formats), progress,
        keep_frames=reads_tables)
    if not reads_tables:  # the frames have coloured the points: done with them
        release_inputs(inputs, *CAMERA_ARTIFACTS)
        tables = {k: v for k, v in tables.items() if k not in CAMERA_ARTIFACTS}
    mesh_tables = {k: v for k, v in tables.items() if k not in ("points", *CAMERA_ARTIFACTS)}
    # a cloud format gets no mesh: ``ply`` of tables with a mesh is the mesh's PLY
    cloud_tables = {k: v for k, v in tables.items()
                    if k not in (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS)}
    # Each model is checked and built once for every format that needs it. The files refer
    # to its arrays (GLB and PLY pieces, the OBJ's stream) until they are written.
    use_mesh = bool(params.mesh_formats)
    use_cloud = bool(params.cloud_formats) or "mcap" in params.mesh_formats
    # Without a format that reads tables, the models hold copies of everything written and
    # the files need the tables' schemas alone (their provenance): each input is released
    # as soon as its model is built (the coloured points with the points), so the stage
    # never holds a table and its model for long. (Building the mesh first, to colour the
    # points without the mesh tables, measured a higher peak: 1.8 GB against 1.6 GB.)
    release = not reads_tables and isinstance(inputs, Inputs)
    cloud = models_from_tables(cloud_tables)[1] if use_cloud else None
    if release:
        tables = {}
        cloud_tables = _released(inputs, cloud_tables)
    mesh = models_from_tables(mesh_tables)[0] if use_mesh else None
    if release:
        mesh_tables = _released(inputs, mesh_tables)
    jobs: list[tuple[str, Mapping[str, pa.Table], str, tuple[MeshModel | None,
                                                             CloudModel | None]]] = [
        (fmt, tables if fmt == "mcap" else mesh_tables, params.name,
         (mesh, cloud if fmt == "mcap" else None)) for fmt in params.mesh_formats]
    jobs += [(fmt, cloud_tables, params.cloud_name, (None, cloud))
             for fmt in params.cloud_formats]
    for done, (fmt, job_tables, stem, models) in enumerate(jobs):
        progress("export", done, len(jobs))
        files.update(export_files(job_tables, fmt, stem, params.las_version, params.glb_draco,
                                  models))
    progress("export", len(jobs), len(jobs))
    report: dict[str, Any] = {"files": list(files), "cloud_coloured": coloured,
                              **georeference_report(mesh, cloud, [j[0] for j in jobs])}
    # the manifest (sizes, digests) is made as the files are written: the OBJ is streamed
    return StageResult({}, report, files, manifest="export_manifest")


def _released(inputs: Mapping[str, pa.Table], tables: Mapping[str, pa.Table]
              ) -> dict[str, pa.Table]:
    """``tables`` as empty tables of their schemas (provenance kept), the inputs of the same
    names released (:func:`release_inputs`)."""
    emptied = {k: v.schema.empty_table() for k, v in tables.items()}
    release_inputs(inputs, *tables)
    return emptied


#: Formats that write the model in the local (shifted) frame and do not record the offset.
LOCAL_ONLY_FORMATS = ("mcap", "colmap")


def georeference_report(mesh: MeshModel | None, cloud: CloudModel | None,
                        formats: list[str]) -> dict[str, Any]:
    """What an export of a georeferenced model says: the offset of its mesh and of its cloud
    (z-up, as LAS/E57 have it) that the files add back or record, and a warning for each
    format written in the local frame only; {} for a model that was never shifted."""
    named = {k: m.offset_m for k, m in (("mesh", mesh), ("cloud", cloud))
             if m is not None and any(m.offset_m)}
    if not named:
        return {}
    shown = ", ".join(sorted({format_offset(o) for o in named.values()}))
    local = sorted({f for f in formats if f in LOCAL_ONLY_FORMATS})
    return {"offset_z_up_m": {k: list(offset_z_up(o)) for k, o in named.items()},
            "warnings": [f"{fmt}: written in the local frame (the import's offset {shown} m "
                         "is not added back: the format has no place for it)" for fmt in local]}


STAGE = Stage(
    name="export",
    version=6,  # 2: coloured points in every format, LAS 1.2, COPC, COLMAP; 3: the Foxglove
    # file has the cloud, camera images and a layout beside it; 4: E57 carries the frames;
    # 5: the cloud PLY is the points (it was the mesh's PLY when the chain had a mesh);
    # 6: OBJ vt lines shared per atlas page (the UV split GLB uses, computed once)
    params=ExportStageParams,
    inputs=(*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS, "points", "frames", "motor", "rig"),
    outputs=("export_manifest",),
    func=export_stage,  # type: ignore[arg-type]
    description="write the textured mesh (OBJ+MTL+PNG, GLB) and the cloud (PLY, LAS, E57, "
                "COLMAP)",
    libraries=("numpy", "pyarrow", "cv2", "laspy", "pye57"),
)
