"""The texture stage: mesh + camera frames + motor states + rig → UVs and atlas pages.

Two methods (docs/texture.md):

- ``projective`` (default): every face's frame is chosen by quality against seams (a Potts
  MRF by ICM over the best frames that really see it, occlusion tested against the mesh, with
  photometric outliers struck out); per-frame gains level exposure and white balance over all
  overlaps, a strip along every seam blends the rest, and the used image regions are packed
  into atlas pages.
- ``panorama``: the paper's method (eq. 17–21): frames chosen by f_si, central strips joined
  into a cylindrical panorama about the motor axis, mapped onto the model by a cylindrical
  projection from the axis. The panorama is also written as ``panorama.png``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Annotated, Any, Literal

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import StageError
from scanpipe.images import encode_png
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.rig import Rig, rig_from_table
from scanpipe.schema import (
    FACE_CORNERS,
    MESH_FACES,
    MESH_VERTICES,
    NORMAL,
    TEXTURE_PAGES,
    TEXTURED_FACES,
    XYZ,
)
from scanpipe.stage import Stage, StageResult, release_inputs
from scanpipe.texturing.atlas import build_atlas, frame_charts
from scanpipe.texturing.exposure import solve_gains
from scanpipe.texturing.frames import (
    FrameSet,
    choose_frames,
    known_camera_frames,
    pinhole_frames,
    worker_count,
)
from scanpipe.texturing.groups import (
    GROUP_PX,
    FaceGroups,
    face_groups,
    single_faces,
    split_into_singles,
)
from scanpipe.texturing.labels import smooth_labels
from scanpipe.texturing.panorama import texture_panorama
from scanpipe.texturing.patches import bake_patches, partial_candidates
from scanpipe.texturing.photometric import (
    Views,
    overlap_pairs,
    photometric_outliers,
    sample_views,
)
from scanpipe.texturing.projective import (
    EQUIRECT_SPACING_DEG,
    FaceScores,
    Facing,
    GroupedScores,
    Scores,
    Selection,
    colorize_points,
    group_scores,
    resolution_weights,
    select_frames_per_face,
)
from scanpipe.texturing.seams import seam_corrections
from scanpipe.texturing.visibility import (
    MeshOcclusion,
    face_centroids,
    face_normals,
    mesh_edges,
)
from scanpipe.threads import thread_pool

__all__ = ["STAGE", "TextureParams", "colorize_points", "texture_stage"]



Channel = Annotated[int, Field(ge=0, le=255)]


class TextureParams(Params):
    """Parameters of the texture stage."""

    method: Literal["projective", "panorama"] = Field(
        "projective", description="projective (best frame per face, atlas) or panorama (paper)")
    frame_stride: int = Field(1, ge=1, description="consider every n-th frame of each camera")
    frame_spacing_deg: float = Field(
        4.0, ge=0, le=90, description="projective: keep the sharpest frame per camera in every "
        "bin of this many degrees of platform angle (0 = every frame)")
    equirect_spacing_deg: float = Field(
        EQUIRECT_SPACING_DEG, ge=0, le=180, description="projective: the same for 360° "
        "(equirect) cameras, whose every frame sees the whole room (0 = every frame)")
    min_cos: float = Field(0.2, ge=0, lt=1,
                           description="faces seen more obliquely than acos(min_cos) are skipped")
    sharpness_weight: float = Field(1.0, ge=0, description="exponent of relative sharpness")
    margin_px: float = Field(2.0, ge=0, description="keep face corners this far inside the image")
    max_candidates: int = Field(8, ge=1, le=64,
                                description="frames tested for occlusion per face at most "
                                "(its best by score; the seam step may test others)")
    two_sided: bool = Field(False, description="texture faces seen from behind (no normals)")
    page_size_px: int = Field(4096, ge=256, le=8192, description="atlas page size (square max)")
    texel_scale: float = Field(1.0, gt=0, le=1, description="scale of image regions in the atlas")
    pad_px: int = Field(3, ge=1, le=32, description="real image kept around each region")
    neutral_rgb: tuple[Channel, Channel, Channel] = Field(
        (128, 128, 128), description="colour of faces no camera saw")
    exposure: bool = Field(True, description="level exposure and white balance with per-frame, "
                           "per-channel gains from the overlaps")
    seam_weight: float = Field(0.3, ge=0, le=10, description="Potts weight of a seam edge "
                               "against the loss of quality (0 = each face its best frame)")
    seam_rounds: int = Field(10, ge=1, le=100, description="ICM rounds of the frame choice")
    seam_strip_px: float = Field(20.0, ge=0, le=200, description="seam blending strip width in "
                                 "frame pixels (0 = off)")
    face_group: int = Field(16, ge=1, le=64, description="faces scored, sampled and ranked "
                            "together at most (a voxel of a few faces of one orientation; 1 = "
                            "every face alone)")
    group_px: float = Field(GROUP_PX, ge=0, le=1000, description="a face group spans at most "
                            "about this many pixels of the finest camera at the surface's "
                            "median distance (coarse faces stay alone; 0 = no limit)")
    max_views: int = Field(6, ge=1, le=32, description="frames sampled per face for levelling "
                           "and outlier rejection")
    patch_texels: int = Field(8, ge=0, le=64, description="faces no frame holds whole are "
                              "textured texel by texel from several frames in a square of "
                              "this many texels a side (0 = they stay untextured)")
    outlier_levels: float = Field(40.0, ge=0, le=255, description="a frame whose colour of a face "
                                  "differs this much from the others' median is not used for it "
                                  "(0 = off; needs ≥ 3 frames)")
    png_compression: int = Field(1, ge=0, le=9, description="PNG compression level (1–3: a "
                                 "fast row filter, 4–9: every filter tried, smaller and slower)")
    panorama_distance_m: float = Field(
        0.0, ge=0, description="panorama: the distance r of eq. 17–21 (0 = median of the mesh)")
    panorama_strip_deg: float = Field(
        0.0, ge=0, le=90, description="panorama: strip width in platform degrees (0 = from "
        "eq. 20–21 with the recorded speed, at least 0.5°)")
    panorama_px_per_deg: float = Field(
        0.0, ge=0, le=200, description="panorama resolution (0 = the camera's, capped at 8192 px)")


def _mesh_arrays(inputs: Mapping[str, Any]) -> tuple[NDArray[np.float64], NDArray[np.int64],
                                                      NDArray[np.float64] | None]:
    vertices_table, faces_table = inputs["mesh_vertices"], inputs["mesh_faces"]
    MESH_VERTICES.check(vertices_table, XYZ)  # normals are optional here
    MESH_FACES.check(faces_table)
    vertices = np.stack([vertices_table.column(c).to_numpy() for c in XYZ], 1).astype(np.float64)
    faces = np.stack([faces_table.column(c).to_numpy() for c in FACE_CORNERS], 1)
    faces = faces.astype(np.int64)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise StageError(f"mesh_faces: vertex indices must lie in [0, {len(vertices) - 1}]; "
                         f"found {faces.min()}..{faces.max()}")
    normals = None
    if all(c in vertices_table.column_names for c in NORMAL):
        normals = np.stack([vertices_table.column(c).to_numpy() for c in NORMAL], 1)
        normals = normals.astype(np.float64)
        if not np.isfinite(normals).all() or not np.abs(normals).sum():
            normals = None
    return vertices, faces, normals


def textured_faces_table(face_page: NDArray[np.int16], face_uv: NDArray[np.float32],
                         face_frame: NDArray[np.int64], camera_ids: list[str],
                         sequences: NDArray[np.int64]) -> pa.Table:
    """The ``textured_faces`` artifact from per-face page, UVs and chosen frame index."""
    n = len(face_page)
    textured = face_frame >= 0
    seq = np.where(textured, np.r_[sequences, -1][face_frame], -1)
    columns: dict[str, Any] = {"face": pa.array(np.arange(n, dtype=np.int32)),
                               "page": pa.array(face_page.astype(np.int16))}
    for k in range(3):
        columns[f"u{k}"] = pa.array(face_uv[:, k, 0].astype(np.float32))
        columns[f"v{k}"] = pa.array(face_uv[:, k, 1].astype(np.float32))
    # camera ids by a take in Arrow (no Python string per face; null where untextured)
    columns["camera_id"] = pa.array(camera_ids, pa.string()).take(
        pa.array(np.where(textured, face_frame, 0).astype(np.int32), mask=~textured))
    columns["frame"] = pa.array(seq.astype(np.int64))
    return pa.table(columns, schema=TEXTURED_FACES.arrow_schema)


def pages_table(pages: list[NDArray[np.uint8]], level: int) -> pa.Table:
    """The ``texture_pages`` artifact; pages are encoded on one thread per core (OpenCV
    releases the GIL), levels 1–3 with the fast PNG filter (:func:`scanpipe.images.encode_png`:
    as small as level 3 with every filter tried, 2–3× faster)."""
    fast = 1 <= level <= 3
    with thread_pool(worker_count(len(pages), limit=8)) as pool:
        encoded = list(pool.map(lambda page: encode_png(page, level, fast=fast), pages))
    return pa.table({
        "page": pa.array(np.arange(len(pages), dtype=np.int16)),
        "width": pa.array([p.shape[1] for p in pages], pa.int32()),
        "height": pa.array([p.shape[0] for p in pages], pa.int32()),
        "png": pa.array(encoded, pa.binary()),
    }, schema=TEXTURE_PAGES.arrow_schema)


def coverage_report(areas: NDArray[np.float64], face_frame: NDArray[np.int64]) -> dict[str, Any]:
    """Share of surface area textured (``coverage``) and unseen (``unseen_share``, m² in
    ``unseen_area_m2``), and the face counts."""
    total = float(areas.sum())
    textured = face_frame >= 0
    coverage = round(float(areas[textured].sum()) / total, 6) if total > 0 else 0.0
    return {
        "faces": len(face_frame),
        "faces_textured": int(textured.sum()),
        "faces_untextured": int((~textured).sum()),
        "coverage": coverage,
        "unseen_share": round(1.0 - coverage, 6) if total > 0 else 0.0,
        "unseen_area_m2": round(float(areas[~textured].sum()), 4),
    }


def orient_towards_rig(centroids: NDArray[np.float64], normals: NDArray[np.float64],
                       areas: NDArray[np.float64], rig: Rig) -> bool:
    """Flip ``normals`` in place when most of the surface faces away from the cameras.

    Every surface the cameras can see faces the rig, so a mesh whose normals mostly point away
    has the opposite convention (inward-facing Poisson normals, say); True when flipped.
    """
    height = float(np.mean([c.pose.translation_m[1] for c in rig.cameras]))
    to_rig = np.array([0.0, height, 0.0]) - centroids
    facing = np.einsum("ij,ij->i", normals, to_rig) > 0
    if float(areas[facing].sum()) >= 0.5 * float(areas.sum()):
        return False
    normals *= -1
    return True


def group_voxel_m(centroids: NDArray[np.float64], rig: Rig, group_px: float) -> float:
    """The largest voxel side of a face group: ``group_px`` pixels of the finest camera at
    the median distance of the surface from the rig's axis at the cameras' height (0: no
    limit)."""
    if group_px <= 0:
        return math.inf
    height = float(np.mean([c.pose.translation_m[1] for c in rig.cameras]))
    sample = centroids[::16] - np.array([0.0, height, 0.0])
    distance = float(np.median(np.sqrt(np.einsum("ij,ij->i", sample, sample)))) \
        if len(sample) else 1.0
    return group_px * distance / max(c.px_per_rad for c in rig.cameras)


def pinhole_frames_only(inputs: Mapping[str, Any], rig: Rig
                        ) -> tuple[dict[str, Any], Rig, list[str]]:
    """The inputs and the rig with only the pinhole cameras, for the paper's panorama
    (eq. 17–21 assume a pinhole's field of view), and one warning per 360° camera left out."""
    frames, pinholes, equirect = pinhole_frames(inputs["frames"], rig)
    if equirect and frames.num_rows == 0:
        raise StageError(f"texture: method panorama needs a pinhole camera; the rig's cameras "
                         f"({', '.join(equirect)}) are 360° (equirect): use method=projective")
    return {**inputs, "frames": frames}, pinholes, [
        f"panorama: camera {cam_id!r} skipped: the paper's panorama method takes pinhole "
        "cameras (method=projective uses it)" for cam_id in equirect]


def untextured_result(n_faces: int, reason: str, png_compression: int) -> StageResult:
    """Every face untextured (page −1, no frame) and no atlas page: the export then writes the
    model without texture. The report says why, as a warning."""
    return StageResult(
        tables={"textured_faces": textured_faces_table(
                    np.full(n_faces, -1, np.int16), np.zeros((n_faces, 3, 2), np.float32),
                    np.full(n_faces, -1, np.int64), [], np.zeros(0, np.int64)),
                "texture_pages": pages_table([], png_compression)},
        report={"untextured": True, "faces": n_faces, "textured_faces": 0,
                "warnings": [f"untextured: {reason}; the model is exported without texture"]})


def _select_alone(alone: NDArray[np.int64], selection: Selection, scores: GroupedScores,
                  vertices: NDArray[np.float64],
                  faces: NDArray[np.signedinteger[Any]],
                  vertex_normals: NDArray[np.floating[Any]] | None, flipped: bool,
                  scored: Callable[[FaceGroups], FaceScores], frames: FrameSet,
                  occlusion: MeshOcclusion, progress: ProgressFn
                  ) -> tuple[Selection, GroupedScores]:
    """The faces ``alone`` (of groups, left without a frame by the ray test) scored and
    tested each alone, as the per-face path does: the selection and scores with them as
    groups of their own, numbered after the others as :func:`split_into_singles` numbers
    them (their normals and centroids found again, bit for bit). Only the faces' group
    numbers are needed here, not the groups' members and corners (~0.1 GB at lab scale)."""
    normals = face_normals(vertices, faces[alone],
                           None if vertex_normals is None else vertex_normals)[0]
    if flipped:
        normals *= -1
    centroids = face_centroids(vertices, faces[alone])
    alone_kept = scored(single_faces(faces[alone], normals, centroids))
    of = scores.of.copy()
    of[alone] = scores.groups.faces + np.arange(len(alone), dtype=np.int32)
    merged = GroupedScores(FaceScores(np.concatenate([scores.groups.frame, alone_kept.frame]),
                                      np.concatenate([scores.groups.score, alone_kept.score])),
                           of)
    merged.struck[...] = scores.struck
    merged.struck[alone] = 0
    again = select_frames_per_face(merged, frames, occlusion, progress, faces=alone)
    chosen = selection.frame.copy()
    chosen[alone] = again.frame[alone]
    return (Selection(chosen, selection.occluded_candidates + again.occluded_candidates,
                      selection.rays_cast + again.rays_cast,
                      selection.backfacing_candidates + again.backfacing_candidates), merged)


def _facing(vertices: NDArray[np.float64], faces: NDArray[np.signedinteger[Any]],
            vertex_normals: NDArray[np.floating[Any]], flipped: bool, frames: FrameSet,
            chunk: int = 1 << 20) -> Facing:
    """Whether a face turns its front to a frame's centre, by the mean of its corners' normals
    (the surface's side as the mesh stage oriented it; a face's own cross product is range
    noise on a scan): a group's frames were scored by its mean normal, and a member at a
    crease (up to 60° off it) may be seen from behind, which the ray test does not strike on
    an open surface. In pieces of ``chunk`` faces (a sign is asked: float32 normals)."""
    centres = np.stack([frames.centre(i) for i in range(len(frames))])
    given = [np.ascontiguousarray(vertex_normals[:, c], np.float32) for c in range(3)]
    sign = -1.0 if flipped else 1.0

    def facing(face_ids: NDArray[np.integer], frame_ids: NDArray[np.integer]) -> NDArray[np.bool_]:
        front = np.empty(len(face_ids), dtype=bool)
        for start in range(0, len(face_ids), chunk):
            corners = faces[face_ids[start:start + chunk]]
            to_frame = centres[frame_ids[start:start + chunk]] - face_centroids(vertices, corners)
            dot = np.zeros(len(corners))
            for c in range(3):
                normal = given[c][corners[:, 0]] + given[c][corners[:, 1]] + given[c][corners[:, 2]]
                dot += normal * to_frame[:, c]
            front[start:start + chunk] = sign * dot > 0
        return front

    return facing


class PhaseClock:
    """Wall and CPU seconds (all threads of the process) of the stage's phases, in order."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}
        self._wall0 = self._wall = time.perf_counter()
        self._cpu0 = self._cpu = time.process_time()

    def lap(self, phase: str) -> None:
        """Close ``phase``: the time since the previous lap (or the start) is its."""
        wall, cpu = time.perf_counter(), time.process_time()
        self.wall_s[phase] = self.wall_s.get(phase, 0.0) + wall - self._wall
        self.cpu_s[phase] = self.cpu_s.get(phase, 0.0) + cpu - self._cpu
        self._wall, self._cpu = wall, cpu

    def report(self) -> dict[str, Any]:
        """``phase_s`` and ``phase_cpu_s`` per phase, ``seconds`` and ``cpu_seconds`` in all."""
        return {"phase_s": {k: round(v, 3) for k, v in self.wall_s.items()},
                "phase_cpu_s": {k: round(v, 3) for k, v in self.cpu_s.items()},
                "seconds": round(time.perf_counter() - self._wall0, 3),
                "cpu_seconds": round(time.process_time() - self._cpu0, 3)}


def texture_stage(inputs: Mapping[str, Any], params: TextureParams, progress: ProgressFn
            ) -> StageResult:
    """Texture the mesh from the camera frames (the stage function)."""
    clock = PhaseClock()
    vertices, faces, vertex_normals = _mesh_arrays(inputs)
    # the arrays are copies: the tables go (export reads them back), as do the frames below
    handed = inputs
    release_inputs(handed, "mesh_vertices", "mesh_faces")
    rig = rig_from_table(inputs["rig"])
    if not rig.cameras:  # a scan without cameras (simulate --no-cameras): geometry only
        return untextured_result(len(faces), "the rig has no cameras", params.png_compression)
    known_frames, warnings = known_camera_frames(inputs["frames"], rig)
    if warnings and known_frames.num_rows == 0:
        raise StageError(f"frames: none of the rig's cameras "
                         f"({', '.join(c.id for c in rig.cameras)}) has frames; "
                         + "; ".join(w.removeprefix("frames: ") for w in warnings))
    inputs = {**inputs, "frames": known_frames}
    normals, areas = face_normals(vertices, faces, vertex_normals)
    centroids = face_centroids(vertices, faces)
    flipped = orient_towards_rig(centroids, normals, areas, rig)
    if params.method == "panorama":
        inputs, rig, skipped = pinhole_frames_only(inputs, rig)
        warnings += skipped
        pano = texture_panorama(vertices, faces, normals, inputs, rig, params, progress)
        return StageResult(
            tables={"textured_faces": textured_faces_table(
                        pano.face_page, pano.face_uv, pano.face_frame, pano.frames.camera_ids,
                        pano.frames.sequences),
                    "texture_pages": pages_table([pano.page], params.png_compression)},
            report={**pano.report, **coverage_report(areas, pano.face_frame),
                    "normals_flipped": flipped, "warnings": warnings},
            files={"panorama.png": encode_png(pano.panorama, params.png_compression)},
        )
    frames = choose_frames(inputs["frames"], inputs["motor"], rig, params.frame_spacing_deg,
                           params.frame_stride, progress, params.equirect_spacing_deg)
    del inputs, known_frames  # the chosen frames' bytes are copies
    release_inputs(handed, "frames")
    clock.lap("frames")
    # each group's best frames only, not a frames × faces matrix (1.9 GB at lab scale); the
    # faces of a group no frame holds whole are scored alone (a frame may hold some whole)
    two_sided = params.two_sided or vertex_normals is None

    def scored(of: FaceGroups) -> FaceScores:
        return group_scores(vertices, of, frames, min_cos=params.min_cos,
                            margin_px=params.margin_px, sharpness_weight=params.sharpness_weight,
                            two_sided=two_sided, progress=progress,
                            keep=params.max_views + params.max_candidates)

    groups = face_groups(faces, normals, areas, centroids, params.face_group,
                         group_voxel_m(centroids, rig, params.group_px))
    group_count = groups.count
    kept = scored(groups)
    split = np.flatnonzero((kept.frame[:, 0] < 0) & (groups.sizes > 1))
    split_faces = groups.faces_of(split)
    if len(split_faces):
        groups, _ = split_into_singles(groups, faces, split_faces, normals[split_faces],
                                       centroids[split_faces])
        alone = scored(single_faces(faces, normals, centroids, split_faces))
        kept = FaceScores(np.concatenate([kept.frame, alone.frame]),
                          np.concatenate([kept.score, alone.score]))
        del alone
    clock.lap("score")
    candidates = kept.frame  # per group, best first, −1 = none
    whole = (candidates[:, 0] >= 0)[groups.of]  # some frame holds the face whole
    views = Views(candidates[:, :params.max_views],
                  sample_views(groups.centroid, candidates[:, :params.max_views], frames))
    del centroids
    gains = np.ones((len(frames), 3))
    fa = np.zeros(0, np.int64)
    if params.exposure:
        fa, fb, ca, cb = overlap_pairs(views)
        gains = solve_gains(fa, fb, ca, cb, len(frames))
    outliers = 0
    if params.outlier_levels > 0:
        face_of, slot = np.nonzero(photometric_outliers(views, gains, params.outlier_levels))
        kept.score[face_of, slot] = 0.0
        candidates[face_of, slot] = -1
        outliers = int(groups.sizes[face_of].sum())  # faces, as the per-face path counts
    del views
    clock.lap("photometric")
    # the stage's peak is the ray scene and the rays beside it: before it is built, the mesh is
    # cut to what the steps below read (int32 corners, shared with the scene; the normals of
    # the faces no frame holds whole, for the multi-view patches), and the edges' sort is done
    # the vertex normals (float32, as read) stay for faces scored alone after the ray test
    if vertex_normals is not None:
        vertex_normals = vertex_normals.astype(np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    partial_pool = np.flatnonzero(~whole)
    partial_normals = normals[partial_pool]
    del normals, whole
    # of the groups, only each face's group and the groups' sizes are read from here on
    # (not their members, corners, normals, centroids: ~0.1 GB at lab scale)
    per_face = groups.count == len(faces) and params.face_group == 1
    group_of, in_group = groups.of, (groups.sizes > 1)[groups.of]
    del groups
    edges = mesh_edges(faces, len(vertices))  # once: rays, seam step, seam strip
    occlusion = MeshOcclusion(vertices, faces, edges)  # the tree is built here, not at a ray
    clock.lap("ray_scene")
    scores: Scores = kept if per_face else GroupedScores(kept, group_of)
    del group_of
    del kept
    facing = None
    if isinstance(scores, GroupedScores) and not two_sided and vertex_normals is not None:
        facing = _facing(vertices, faces, vertex_normals, flipped, frames)
    selection = select_frames_per_face(scores, frames, occlusion, progress, facing=facing)
    del candidates, facing
    # faces of a group hidden (in part) in every frame kept for it: scored and tested alone,
    # as the per-face path does (a half-hidden group's hidden half from another frame)
    alone_faces = np.zeros(0, np.int64)
    if isinstance(scores, GroupedScores):
        alone_faces = np.flatnonzero((selection.frame < 0) & scores.has_candidates()
                                     & in_group)
    if isinstance(scores, GroupedScores) and len(alone_faces):
        selection, scores = _select_alone(
            alone_faces, selection, scores, vertices, faces, vertex_normals, flipped,
            scored, frames, occlusion, progress)
    del vertex_normals, in_group
    clock.lap("visibility")
    smoothing = smooth_labels(scores, selection.frame, edges, frames,
                              occlusion, params.seam_weight, params.seam_rounds,
                              progress=progress)
    labels = smoothing.labels
    # the ray test's choice (ICM's copy is the labels): only its count is reported
    occluded_candidates = selection.occluded_candidates
    backfacing_candidates = selection.backfacing_candidates
    del scores, selection
    clock.lap("icm")
    # the atlas's regions read only the frame choice: found on a second thread while the
    # seams are measured, once the ray scene is gone (beside the patches, which cast rays,
    # the scene (~0.5 GB at lab scale) and the regions' temporaries and charts (~0.5 GB)
    # were the stage's peak)
    with thread_pool(worker_count(2, limit=2)) as side:  # waits for it on an error
        patches = None
        if params.patch_texels > 0:
            untextured = labels[partial_pool] < 0  # a face no frame holds whole, still without one
            straddling = partial_pool[untextured]
            partial = partial_candidates(
                vertices, faces, partial_normals[untextured], straddling, frames,
                frames.relative_sharpness() ** params.sharpness_weight
                * resolution_weights(frames.cameras), params.min_cos)
            straddling, partial = straddling[partial[:, 0] >= 0], partial[partial[:, 0] >= 0]
            patches = bake_patches(vertices, faces, straddling, partial, frames, gains, occlusion,
                                   params.patch_texels)
        rays_cast = occlusion.rays_cast
        del occlusion, partial_normals  # the ray scene (~0.4 GB at lab scale): not in the atlas
        clock.lap("patches")
        charts_job = side.submit(frame_charts, vertices, faces, labels, frames,
                                 pad_px=params.pad_px)
        seams = None
        if params.seam_strip_px > 0:
            seams = seam_corrections(vertices, faces, labels, frames, gains, edges=edges)
        del edges
        clock.lap("seam_strip")
        charts = charts_job.result()
        del charts_job
    red, green, blue = params.neutral_rgb
    atlas = build_atlas(vertices, faces, labels, frames, gains,
                        page_px=params.page_size_px, texel_scale=params.texel_scale,
                        pad_px=params.pad_px, neutral_bgr=(blue, green, red), seams=seams,
                        strip_px=params.seam_strip_px, patches=patches, charts=charts,
                        progress=progress)
    del charts
    if patches is not None:
        labels = labels.copy()
        labels[patches.face] = patches.frame
    faces_table = textured_faces_table(atlas.face_page, atlas.face_uv, labels,
                                       frames.camera_ids, frames.sequences)
    clock.lap("atlas")
    pages = pages_table(atlas.pages, params.png_compression)
    clock.lap("png")
    used = np.unique(labels[labels >= 0])
    used_gains = gains[used] if len(used) else np.ones((1, 3))
    report = {
        "method": "projective",
        **coverage_report(areas, labels),
        "cameras": {c.id: c.model for c in rig.cameras},
        "frames_in_recording": frames.considered,
        "frames_considered": len(frames),
        "frames_used": len(used),
        "occluded_candidates": occluded_candidates,
        "backfacing_candidates": backfacing_candidates,
        "rays_cast": rays_cast,
        "regions": atlas.regions,
        "pages": len(atlas.pages),
        "page_sizes": [[int(p.shape[1]), int(p.shape[0])] for p in atlas.pages],
        "exposure_pairs": len(fa),
        "photometric_outliers": outliers,
        "faces_multiview": 0 if patches is None else len(patches.face),
        "face_groups": group_count,
        "faces_scored_alone": len(split_faces) + len(alone_faces),
        "seam_edges_best_frame": smoothing.seam_edges_before,
        "seam_edges": smoothing.seam_edges_after,
        "seam_faces_moved": smoothing.moved,
        "seam_rounds": smoothing.rounds,
        "seam_points": seams.points if seams is not None else 0,
        "gain_min": round(float(used_gains.min()), 4),
        "gain_max": round(float(used_gains.max()), 4),
        "neutral_rgb": list(params.neutral_rgb),
        "normals_flipped": flipped,
        "warnings": warnings,
        **clock.report(),
    }
    return StageResult(tables={"textured_faces": faces_table, "texture_pages": pages},
                       report=report)


STAGE = Stage(
    name="texture",
    version=5,  # 5: a grouped face's frame it turns its back on is struck; 4: frames scored
    # per face group (a face may take another frame); 3: occlusion
    # tested at exact shared corners and edge middles: no cached texture of 3 is reused
    params=TextureParams,
    inputs=("mesh_vertices", "mesh_faces", "frames", "motor", "rig"),
    outputs=("textured_faces", "texture_pages"),
    func=texture_stage,
    description="camera frames onto the mesh: per-face UVs and PNG atlas pages",
    libraries=("numpy", "pyarrow", "open3d", "cv2"),
)
