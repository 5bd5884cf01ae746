"""The merged model of a site: the scans' own textured grid meshes fused in the site frame, the
merged cloud, and the exports (``scanpipe site-model``).

```
SITE/model/poses.parquet          the poses the model was built with (rig → site)
SITE/model/points.parquet         the merged cloud (coloured from each scan's own frames)
SITE/model/mesh_vertices.parquet, mesh_faces.parquet, textured_faces.parquet,
           texture_pages.parquet  the fused textured mesh (site frame, y up)
SITE/site.e57                     one data3D scan per position (its own frame, grid, intensity,
                                  colour) with its pose, and its camera frames as images2D
SITE/site.las (+ .pipeline.json)  the merged cloud, z up
SITE/site.glb, site.obj/.mtl/_page*.png   the fused mesh with its texture
```

**Why fused per-scan meshes, not Poisson over the merged cloud.** Each scan's mesh stage has
already triangulated its own grid (measured points as vertices, ~30× faster than Poisson and as
accurate), and its texture stage has already textured that mesh from the same position's camera
frames, with occlusion tested from where the camera really stood. Fusing keeps both: no
surface is re-estimated, no second texturer is needed, and the cost is a voxel vote. Poisson
over a whole site needs depth 11–12 for 1–2 cm cells over 15 m (minutes and gigabytes) and
would need every camera re-posed across scans to texture it.

**The fusion rule** is the merged cloud's (:func:`scanpipe.site.voxel_winners`): in each voxel
of ``fuse_voxel_m`` several scans cover, the scan that sees it best (beams closest to head-on,
then nearest; mean over its vertices there) wins; a face is kept when any of its corners lies
in a voxel its scan won. Faces at the border between two scans' voxels may then overlap by up
to one face, never leave a gap.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.artifacts import (
    PROVENANCE_KEY,
    FileData,
    artifact_key,
    canonical_json,
    read_artifact,
    write_artifact,
)
from scanpipe.errors import UsageError
from scanpipe.exporters.e57 import E57Image, E57Scan, write_e57
from scanpipe.exporters.model import MeshModel, cloud_from_table, mesh_from_tables, unit_normals
from scanpipe.params import Params
from scanpipe.poses import poses_from_table, poses_table, quaternion_from_rotation
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.schema import (
    ORIGIN,
    TEXTURE_PAGES,
    TEXTURED_FACES,
    ZERO_OFFSET,
    common_crs,
    common_offset,
    offset_z_up,
    with_crs,
    with_offset,
)
from scanpipe.site import (
    MERGE_VOXEL_M,
    POSES_FILE,
    match_scan_names,
    merge_scans,
    scan_workdirs,
    view_quality,
    voxel_winners,
)
from scanpipe.workdir import find_artifacts

F64 = NDArray[np.float64]

MODEL_FOLDER = "model"
#: The stem of the exported files (``site.e57``, ``site.las`` …).
MODEL_STEM = "site"
MODEL_VERSION = 1
#: What each scan's workdir must have (the mesh), may have (texture, camera frames).
SCAN_ARTIFACTS = ("points", "mesh_vertices", "mesh_faces", "textured_faces", "texture_pages",
                  "frames", "motor", "rig")
MODEL_ARTIFACTS = ("poses", "points", "mesh_vertices", "mesh_faces", "textured_faces",
                   "texture_pages")
#: z-up file frame of LAS and E57 from the rig frame: (x, y, z) → (x, −z, y).
Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class SiteModelParams(Params):
    """Parameters of ``scanpipe site-model``."""

    merge_voxel_m: float = Field(MERGE_VOXEL_M, gt=0, le=1.0, description=(
        "merged cloud: voxel within which two scans' points are the same surface (the best "
        "view keeps its points)"))
    fuse_voxel_m: float = Field(0.1, gt=0, le=2.0, description=(
        "fused mesh: voxel within which two scans' faces are the same surface (the best view "
        "keeps its faces)"))
    las_version: Literal["1.2", "1.4"] = Field("1.2", description="LAS version of site.las")
    images: bool = Field(True, description="carry each scan's camera frames into site.e57")


@dataclass(frozen=True)
class SiteScan:
    """One scan of the site: its name, workdir, pose (rig → site) and artifacts."""

    name: str
    workdir: Path
    pose: F64
    tables: dict[str, pa.Table]
    keys: dict[str, str]


def _transform(xyz: NDArray[np.floating], pose: F64) -> F64:
    return np.asarray(np.asarray(xyz, np.float64) @ pose[:3, :3].T + pose[:3, 3], np.float64)


def load_scan(workdir: Path, name: str, pose: F64) -> SiteScan:
    """A scan's artifacts; its points and mesh are required (``scanpipe run`` makes them)."""
    if not workdir.is_dir():
        raise UsageError(f"{workdir}: not a folder (give the workdir of each scan)")
    found = find_artifacts(workdir, SCAN_ARTIFACTS)
    missing = [n for n in ("points", "mesh_vertices", "mesh_faces") if n not in found]
    if missing:
        raise UsageError(f"{workdir}: no {', '.join(missing)} artifact; run `scanpipe run "
                         f"RECORDING --workdir {workdir}` (through mesh and texture) first")
    tables, keys = {}, {}
    for artifact, path in found.items():
        table, provenance = read_artifact(path)
        tables[artifact] = table
        keys[artifact] = str(provenance.get("key", path))
    return SiteScan(name, workdir, pose, tables, keys)


def scanner_position(scan: SiteScan) -> F64:
    """Where the scanner stood in the site frame: the mean of its points' optical centres."""
    from scanpipe.stages.mesh import usable_points

    points = usable_points(scan.tables["points"])
    origin = np.stack([points.column(n).to_numpy(zero_copy_only=False) for n in ORIGIN], 1)
    centre = origin.astype(np.float64).mean(axis=0)
    return np.asarray(scan.pose[:3, :3] @ centre + scan.pose[:3, 3], np.float64)


def _scan_mesh(scan: SiteScan) -> tuple[MeshModel, NDArray[np.object_], NDArray[np.int64]]:
    """The scan's mesh (and texture) in the site frame, and each face's source camera
    (``scan/camera``, None when untextured) and frame sequence (−1)."""
    t = scan.tables
    textured = "textured_faces" in t and "texture_pages" in t
    mesh = mesh_from_tables(t["mesh_vertices"], t["mesh_faces"],
                            t["textured_faces"] if textured else None,
                            t["texture_pages"] if textured else None)
    camera = np.full(len(mesh.faces), None, dtype=object)
    frame = np.full(len(mesh.faces), -1, dtype=np.int64)
    if textured:
        faces = t["textured_faces"]
        index = faces.column("face").to_numpy()
        if "camera_id" in faces.column_names:
            ids = np.asarray(faces.column("camera_id").to_pylist(), dtype=object)
            camera[index] = [None if c is None else f"{scan.name}/{c}" for c in ids]
        if "frame" in faces.column_names:
            frame[index] = faces.column("frame").fill_null(-1).to_numpy(zero_copy_only=False)
    rotation = scan.pose[:3, :3]
    normals = unit_normals(mesh).astype(np.float64) @ rotation.T
    placed = MeshModel(_transform(mesh.vertices, scan.pose).astype(np.float32), mesh.faces,
                       normals.astype(np.float32), mesh.colors, mesh.face_pages, mesh.face_uvs,
                       mesh.pages)
    return placed, camera, frame


def fuse_meshes(meshes: list[MeshModel], origins: list[F64], voxel_m: float,
                cameras: list[NDArray[np.object_]] | None = None,
                frames: list[NDArray[np.int64]] | None = None
                ) -> tuple[MeshModel, NDArray[np.object_], NDArray[np.int64], dict[str, Any]]:
    """One mesh from several scans' meshes in the site frame (see the module docstring):
    the faces each scan keeps, its texture pages renumbered, and per face the source camera and
    frame; with a report (faces in and out per scan)."""
    count = len(meshes)
    cameras = cameras or [np.full(len(m.faces), None, dtype=object) for m in meshes]
    frames = frames or [np.full(len(m.faces), -1, dtype=np.int64) for m in meshes]
    xyz = np.concatenate([m.vertices.astype(np.float64) for m in meshes])
    normals = np.concatenate([unit_normals(m).astype(np.float64) for m in meshes])
    origin = np.concatenate([np.broadcast_to(o, (len(m.vertices), 3))
                             for m, o in zip(meshes, origins, strict=True)])
    scan_of = np.concatenate([np.full(len(m.vertices), k, np.int64)
                              for k, m in enumerate(meshes)])
    wins = voxel_winners(xyz, scan_of, view_quality(xyz, origin, normals), count, voxel_m)
    vertices, faces, vertex_normals, colors, pages_of, uvs_of = [], [], [], [], [], []
    face_camera, face_frame, per_scan = [], [], []
    pages: dict[int, bytes] = {}
    start = offset = 0
    colored = all(m.colors is not None for m in meshes)
    for k, mesh in enumerate(meshes):
        won = wins[start:start + len(mesh.vertices)]
        start += len(mesh.vertices)
        keep = won[mesh.faces].any(axis=1)
        used = np.zeros(len(mesh.vertices), bool)
        used[mesh.faces[keep].ravel()] = True
        remap = np.cumsum(used) - 1 + offset
        vertices.append(mesh.vertices[used])
        vertex_normals.append(unit_normals(mesh)[used])
        if colored:
            assert mesh.colors is not None
            colors.append(mesh.colors[used])
        faces.append(remap[mesh.faces[keep]])
        page = (np.full(int(keep.sum()), -1, np.int16) if mesh.face_pages is None
                else mesh.face_pages[keep].copy())
        uv = (np.zeros((int(keep.sum()), 3, 2), np.float32) if mesh.face_uvs is None
              else mesh.face_uvs[keep])
        # renumber the pages this scan still uses after the pages of the scans before it
        page_ids = sorted(set(np.unique(page[page >= 0]).tolist()))
        renumber = {old: len(pages) + i for i, old in enumerate(page_ids)}
        for old, new in renumber.items():
            pages[new] = mesh.pages[old]
        if page_ids:
            lookup = np.full(max(page_ids) + 1, -1, np.int16)
            lookup[page_ids] = [renumber[p] for p in page_ids]
            page[page >= 0] = lookup[page[page >= 0]]
        pages_of.append(page)
        uvs_of.append(uv)
        face_camera.append(cameras[k][keep])
        face_frame.append(frames[k][keep])
        offset += int(used.sum())
        per_scan.append({"faces_in": len(mesh.faces), "faces_kept": int(keep.sum())})
    fused = MeshModel(np.concatenate(vertices).astype(np.float32),
                      np.concatenate(faces).astype(np.int32),
                      np.concatenate(vertex_normals).astype(np.float32),
                      np.concatenate(colors) if colored else None,
                      np.concatenate(pages_of), np.concatenate(uvs_of), pages)
    report = {"fuse_voxel_m": voxel_m, "faces": len(fused.faces),
              "vertices": len(fused.vertices), "pages": len(pages), "scans": per_scan}
    return fused, np.concatenate(face_camera), np.concatenate(face_frame), report


def mesh_tables(mesh: MeshModel, camera: NDArray[np.object_], frame: NDArray[np.int64]
                ) -> dict[str, pa.Table]:
    """The ``mesh_vertices``, ``mesh_faces``, ``textured_faces`` and ``texture_pages`` tables
    of a fused mesh."""
    from scanpipe.images import MAX_TEXTURE_PX, probe_image
    from scanpipe.meshing.mesh import Mesh

    vertices, faces = Mesh(mesh.vertices, mesh.faces, mesh.normals, mesh.colors).to_tables()
    n = len(mesh.faces)
    page = mesh.face_pages if mesh.face_pages is not None else np.full(n, -1, np.int16)
    uv = mesh.face_uvs if mesh.face_uvs is not None else np.zeros((n, 3, 2), np.float32)
    columns: dict[str, Any] = {"face": pa.array(np.arange(n, dtype=np.int32)),
                               "page": pa.array(page.astype(np.int16))}
    for k in range(3):
        columns[f"u{k}"] = pa.array(uv[:, k, 0].astype(np.float32))
        columns[f"v{k}"] = pa.array(uv[:, k, 1].astype(np.float32))
    columns["camera_id"] = pa.array(camera.tolist(), pa.string())
    columns["frame"] = pa.array(frame.astype(np.int64))
    ids = sorted(mesh.pages)
    sizes = [probe_image(mesh.pages[p], f"texture page {p}", MAX_TEXTURE_PX) for p in ids]
    pages = pa.table({"page": pa.array(ids, pa.int16()),
                      "width": pa.array([s[0] for s in sizes], pa.int32()),
                      "height": pa.array([s[1] for s in sizes], pa.int32()),
                      "png": pa.array([mesh.pages[p] for p in ids], pa.binary())},
                     schema=TEXTURE_PAGES.arrow_schema)
    return {"mesh_vertices": vertices, "mesh_faces": faces,
            "textured_faces": pa.table(columns, schema=TEXTURED_FACES.arrow_schema),
            "texture_pages": pages}


def z_up_pose(pose: F64) -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
    """A rig → site pose as E57 wants it: the scan's z-up frame → the file's (site's) z-up
    frame, as a quaternion (w, x, y, z) and a translation."""
    rotation = Z_UP @ pose[:3, :3] @ Z_UP.T
    q = quaternion_from_rotation(rotation)
    t = Z_UP @ pose[:3, 3]
    return ((float(q[0]), float(q[1]), float(q[2]), float(q[3])),
            (float(t[0]), float(t[1]), float(t[2])))


def _compose(pose_zup: tuple[tuple[float, ...], tuple[float, ...]], image: E57Image,
             scan: str) -> E57Image:
    """``image`` (posed in its scan's z-up frame) posed in the file's frame."""
    from dataclasses import replace

    from scanpipe.poses import rotation_from_quaternion

    rotation = rotation_from_quaternion(pose_zup[0])
    q = quaternion_from_rotation(rotation @ rotation_from_quaternion(image.rotation_wxyz))
    t = rotation @ np.asarray(image.translation_m) + np.asarray(pose_zup[1])
    return replace(image, rotation_wxyz=(float(q[0]), float(q[1]), float(q[2]), float(q[3])),
                   translation_m=(float(t[0]), float(t[1]), float(t[2])),
                   name=f"{scan}_{image.name}")


def scan_e57(scan: SiteScan, points: pa.Table, images: bool
             ) -> tuple[E57Scan, list[E57Image]]:
    """One position's E57 scan (its own frame, its pose, the provenance of its points) and,
    with ``images``, its camera frames posed in the file's (site's) frame. The scans' shared
    georeference offset is in the site frame: it is added to the pose's translation."""
    from dataclasses import replace

    from scanpipe.stages.export import e57_images, provenance_of

    rotation, translation = z_up_pose(scan.pose)
    cloud = cloud_from_table(points)
    shift = offset_z_up(cloud.offset_m)
    pose = (rotation, (translation[0] + shift[0], translation[1] + shift[1],
                       translation[2] + shift[2]))
    record = canonical_json(provenance_of({"points": points}))  # as the one-scan E57 has it
    entry = E57Scan(replace(cloud, offset_m=ZERO_OFFSET), scan.name, pose[0], pose[1], record)
    pictures = ([_compose(pose, image, scan.name)
                 for image in e57_images({**scan.tables, "points": points})] if images else [])
    return entry, pictures


def site_e57_bytes(scans: list[E57Scan], images: list[E57Image]) -> bytes:
    """The site as one E57 file: a data3D scan per position, then the images
    (libE57Format writes only to paths: via a temporary file)."""
    with tempfile.TemporaryDirectory(prefix="scanpipe-site-e57-") as tmp:
        path = Path(tmp) / "site.e57"
        write_e57(path, scans, images)
        return path.read_bytes()


def read_site_poses(path: Path, option: str) -> pa.Table:
    """A ``poses`` artifact (checked), or a one-line error naming ``option``."""
    if not path.is_file():
        raise UsageError(f"{option} {path}: not found (a poses Parquet file: run `scanpipe "
                         "register WORKDIR... --out SITE` first, or give --poses)")
    table, _ = read_artifact(path)
    poses_from_table(table, where=f"{option} {path}")
    return table


def build_site_model(workdirs: list[Path], out: Path, params: SiteModelParams,
                     poses_path: Path | None = None, force: bool = False,
                     progress: ProgressFn = no_progress) -> dict[str, Any]:
    """``scanpipe site-model``: the merged model of the scans in ``workdirs`` at their poses
    (``poses_path``, default ``out/poses.parquet`` from ``scanpipe register``), written into
    ``out`` (see the module docstring). Scans without a pose are left out with a warning."""
    from scanpipe.exporting import write_files
    from scanpipe.outpaths import check_output_files, check_output_folder
    from scanpipe.stages.export import export_files, prepare_tables
    from scanpipe.stages.mesh import usable_points

    workdirs, names = scan_workdirs(workdirs, "site-model")
    if not workdirs:
        raise UsageError("site-model: no workdir given")
    option = "--poses" if poses_path is not None else "--out"
    poses_path = poses_path if poses_path is not None else out / POSES_FILE
    poses_in = read_site_poses(poses_path, option)
    poses = poses_from_table(poses_in)
    check_output_folder(out, "--out", workdirs)
    model_dir = out / MODEL_FOLDER
    check_output_folder(model_dir, "--out", workdirs)
    matched = match_scan_names(names, list(poses))
    warnings = [f"{n}: no pose in {poses_path}; left out of the model" for n in names
                if n not in matched]
    chosen = [(w, n) for w, n in zip(workdirs, names, strict=True) if n in matched]
    if not chosen:
        raise UsageError(f"{poses_path}: none of the scans {', '.join(names)} has a pose (it "
                         f"has {', '.join(sorted(poses)) or 'none'}); scans are named after "
                         "their workdir folders")
    export_names = [f"{MODEL_STEM}.e57", f"{MODEL_STEM}.las", f"{MODEL_STEM}.las.pipeline.json",
                    f"{MODEL_STEM}.glb", f"{MODEL_STEM}.obj", f"{MODEL_STEM}.mtl"]
    check_output_files([out / f for f in export_names]
                       + [model_dir / f"{a}.parquet" for a in MODEL_ARTIFACTS],
                       "--out", force, [*workdirs, poses_path])
    steps = 4 + len(chosen)
    # one scan at a time: only what the model needs is kept (not the scan's camera frames)
    names_kept, poses_kept, keys, coloured, placed, positions = [], [], [], [], [], []
    e57_scans: list[E57Scan] = []
    e57_pictures: list[E57Image] = []
    first: tuple[str, pa.Table] | None = None
    offset = ZERO_OFFSET
    crs: str | None = None
    for done, (workdir, name) in enumerate(chosen):
        progress("site-model", done, steps)
        scan = load_scan(workdir, name, poses[matched[name]])
        # georeferenced imports: one offset for all (the site frame is one scan's)
        first = first or (str(workdir), scan.tables["points"])
        offset = common_offset([first, (str(workdir), scan.tables["points"])], "site-model",
                               UsageError)
        crs = common_crs([first, (str(workdir), scan.tables["points"])], "site-model",
                         UsageError)
        if "texture_pages" not in scan.tables:
            warnings.append(f"{scan.name}: no texture artifacts; its part of the model is "
                            "untextured")
        # its points coloured from its own frames (as `scanpipe run` exports them)
        tables, _ = prepare_tables({**scan.tables, "points": usable_points(scan.tables["points"])})
        coloured.append(tables["points"])
        entry, pictures = scan_e57(scan, tables["points"], params.images)
        e57_scans.append(entry)
        e57_pictures += pictures
        placed.append(_scan_mesh(scan))
        positions.append(scanner_position(scan))
        names_kept.append(scan.name)
        poses_kept.append(scan.pose)
        keys.append((scan.name, scan.keys, str(scan.workdir)))
        del scan, tables
    progress("site-model", len(chosen), steps)
    merged, merge_report = merge_scans(coloured, poses_kept, params.merge_voxel_m)
    progress("site-model", len(chosen) + 1, steps)
    mesh, camera, frame, fuse_report = fuse_meshes(
        [p[0] for p in placed], positions, params.fuse_voxel_m,
        [p[1] for p in placed], [p[2] for p in placed])
    del placed
    progress("site-model", len(chosen) + 2, steps)
    inputs = {f"{n}/{a}": k for n, scan_keys, _ in keys for a, k in scan_keys.items()}
    used_poses = poses_table(names_kept, poses_kept)
    inputs["poses"] = hashlib.sha256(canonical_json(used_poses.to_pydict()).encode()
                                     ).hexdigest()[:24]
    key = artifact_key("site-model", MODEL_VERSION, params.model_dump(mode="json"), inputs, {})
    report: dict[str, Any] = {"scans": names_kept, "merge": merge_report,
                              "fuse": fuse_report, "poses": str(poses_path),
                              **({"offset_z_up_m": list(offset_z_up(offset))}
                                 if any(offset) else {})}
    provenance = {"stage": "site-model", "key": key, "params": params.model_dump(mode="json"),
                  "inputs": {n: w for n, _, w in keys}, "report": report}
    tables = {"poses": used_poses, "points": merged, **mesh_tables(mesh, camera, frame)}
    tables = {n: with_crs(with_offset(t.replace_schema_metadata({PROVENANCE_KEY: json.dumps(
        {**provenance, "stage": f"site-model/{n}"})}), offset), crs) for n, t in tables.items()}
    files: dict[str, FileData] = {}
    files.update(export_files(tables, "las", MODEL_STEM, params.las_version))
    files.update(export_files(tables, "glb", MODEL_STEM))
    files.update(export_files(tables, "obj", MODEL_STEM))
    files[f"{MODEL_STEM}.e57"] = site_e57_bytes(e57_scans, e57_pictures)
    progress("site-model", len(chosen) + 3, steps)
    check_output_files([out / f for f in files if f not in export_names], "--out", force,
                       [*workdirs, poses_path])
    for name, table in tables.items():
        write_artifact(model_dir / f"{name}.parquet", table, {**provenance,
                                                               "stage": f"site-model/{name}"})
    written = write_files(files, out)
    progress("site-model", steps, steps)
    report.update(warnings=warnings, model=str(model_dir), files=[str(p) for p in written],
                  faces=fuse_report["faces"], points=merge_report["points_out"])
    return report


def model_summary(report: Mapping[str, Any]) -> str:
    """One line on what ``site-model`` made."""
    return (f"site-model: {len(report['scans'])} scans → {report['faces']} faces, "
            f"{report['points']} points → {report['model']}; "
            f"{', '.join(Path(f).name for f in report['files'] if not f.endswith('.png'))}")

