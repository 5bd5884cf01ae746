"""The shell of ``scanpipe register``: scans of a site (workdirs) → poses, merged cloud, model.

```
SITE_DIR/poses.parquet     one pose per scan (rig → site), covariance where available
SITE_DIR/points.parquet    every scan's filtered points in the site frame, double coverage
                           between scans resolved (the best view kept per voxel)
SITE_DIR/mesh/ …           the mesh stage over the merged points (Poisson: no single grid)
SITE_DIR/site.e57          one scan per position with its pose (each in its own frame)
SITE_DIR/site.las, site.glb, site.obj (+ .mtl)
```

Scans imported from georeferenced files (``import-points``, shifted by a georeference offset)
must share one offset (``import-points --offset``): scans with different offsets are refused
in one line naming both; the merged points carry the shared offset, so the exports add it back.

Double coverage between scans is resolved like the filter's ``best`` view within one scan: in
each voxel of ``merge_voxel_m`` seen by several scans, only the scan whose beams meet the surface
closest to head-on (ties: the nearer scanner) keeps its points.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.artifacts import artifact_key, read_artifact, write_artifact
from scanpipe.errors import ArtifactError, UsageError
from scanpipe.poses import pose_errors, poses_from_table, poses_table
from scanpipe.registration import (
    RegisterParams,
    ScanClouds,
    plane_projected_points,
    prepare_scan,
    register_scans,
)
from scanpipe.schema import (
    ORIGIN,
    POINTS,
    POSES,
    XYZ,
    common_crs,
    common_offset,
    offset_z_up,
    with_crs,
    with_offset,
)
from scanpipe.workdir import find_artifact

F64 = NDArray[np.float64]
POSES_FILE = "poses.parquet"
POINTS_FILE = "points.parquet"
#: Voxel edge (m) within which two scans' points count as the same surface.
MERGE_VOXEL_M = 0.03


def scan_points(workdir: Path) -> tuple[pa.Table, str]:
    """The (filtered) points of one scan's workdir and their key."""
    if not workdir.is_dir():
        raise UsageError(f"{workdir}: not a folder (give the workdir of each scan)")
    path = find_artifact(workdir, "points")
    if path is None:
        raise UsageError(f"{workdir}: no points artifact; run `scanpipe run RECORDING "
                         f"--workdir {workdir} --to filter` first")
    table, provenance = read_artifact(path, POINTS)
    return table, str(provenance.get("key", path))


def unsmoothed_points(workdir: Path, table: pa.Table) -> tuple[F64, F64] | None:
    """The positions and beam origins that the filter's points (``table``, from
    :func:`scan_points`) had in the filter's input — before its range smoothing moved them —
    matched by grid cell; None when the workdir does not hold that input readably (the
    artifact whose key the filter's provenance names) or the points have no grid."""
    from scanpipe.artifacts import read_provenance

    def key_of(candidate: Path) -> object:
        try:
            return read_provenance(candidate).get("key")
        except ArtifactError:  # an unreadable file is not the input we look for
            return None

    path = find_artifact(workdir, "points")
    profile = table.column("profile").to_numpy().astype(np.int64)
    sample = table.column("sample").to_numpy().astype(np.int64)
    if path is None or len(profile) == 0 or profile.min() < 0 or sample.min() < 0:
        return None
    try:
        wanted = read_provenance(path).get("inputs", {}).get("points")
    except ArtifactError:
        return None
    source = next((p for p in sorted(workdir.glob(f"*/{POINTS_FILE}"))
                   if p != path and wanted is not None and key_of(p) == wanted), None)
    if source is None:
        return None
    try:
        raw, _ = read_artifact(source, POINTS)
    except ArtifactError:
        return None
    width = int(max(sample.max(), raw.column("sample").to_numpy().max())) + 1
    raw_cell = (raw.column("profile").to_numpy().astype(np.int64) * width
                + raw.column("sample").to_numpy().astype(np.int64))
    cell = profile * width + sample
    order = np.argsort(raw_cell, kind="stable")
    at = order[np.minimum(np.searchsorted(raw_cell[order], cell), len(order) - 1)]
    if not np.array_equal(raw_cell[at], cell):
        return None  # a cell the input does not have: not this filter's input
    return _columns(raw, XYZ)[at], _columns(raw, ORIGIN)[at]


def registration_cloud(name: str, workdir: Path, table: pa.Table, params: RegisterParams
                       ) -> tuple[ScanClouds, str | None]:
    """One scan prepared for registration (:func:`~scanpipe.registration.prepare_scan`) with
    the grid normals of its filtered points and, with ``positions`` "unsmoothed", fine clouds
    at the positions of :func:`unsmoothed_points` averaged along their beams
    (:func:`~scanpipe.registration.plane_projected_points`); and a warning when those
    positions could not be had (the filtered points are used then)."""
    from scanpipe.normals import estimate_normals

    normals = estimate_normals(table)[0].astype(np.float64)
    xyz, origin = _columns(table, XYZ), _columns(table, ORIGIN)
    warning, fine = None, None
    if params.positions == "unsmoothed":
        raw = unsmoothed_points(workdir, table)
        if raw is None:
            warning = (f"{name}: the filter's input points (the assemble stage's) are not in "
                       f"{workdir} or not readable: registered on the smoothed points, which "
                       "lie mm behind far and oblique surfaces on coarse scans (docs/sites.md)")
        else:
            fine = plane_projected_points(raw[0], raw[1], normals,
                                          table.column("profile").to_numpy(),
                                          table.column("sample").to_numpy(),
                                          params.fine_distance_m)
    return prepare_scan(name, xyz, origin, params, normals, fine), warning


def _columns(table: pa.Table, names: Sequence[str]) -> F64:
    return np.stack([table.column(n).to_numpy(zero_copy_only=False) for n in names],
                    axis=1).astype(np.float64)


def match_scan_names(names: Sequence[str], known: Sequence[str]) -> dict[str, str]:
    """Scan name → the name it has in ``known`` (a poses artifact, a truth folder): the same
    name, else the name without a batch workdir's ``-<8 hex>`` suffix (``pos03-1a2b3c4d`` →
    ``pos03``, see :func:`scanpipe.batch.workdir_name`). Names with no match are left out."""
    present = set(known)
    matched = {}
    for name in names:
        stem, tail = name[:-9], name[-9:]
        if name in present:
            matched[name] = name
        elif (tail.startswith("-") and all(c in "0123456789abcdef" for c in tail[1:])
              and stem in present):
            matched[name] = stem
    return matched


def read_prior(path: Path, names: list[str]) -> list[F64]:
    """Prior poses for ``names`` from a ``poses`` artifact (every scan must have one)."""
    if not path.is_file():
        raise UsageError(f"--prior {path}: not found (a poses Parquet file)")
    table, _ = read_artifact(path)
    poses = poses_from_table(table, where=f"--prior {path}")
    matched = match_scan_names(names, list(poses))
    missing = [n for n in names if n not in matched]
    if missing:
        raise UsageError(f"--prior {path}: no pose for scans {', '.join(missing)} (it has "
                         f"{', '.join(sorted(poses)) or 'none'}); scans are named after their "
                         "workdir folders")
    return [poses[matched[n]] for n in names]


def _transform(xyz: F64, pose: F64) -> F64:
    return np.asarray(xyz @ pose[:3, :3].T + pose[:3, 3], np.float64)


def view_quality(xyz: F64, origin: F64, normals: F64) -> F64:
    """|cos| of the incidence of each beam on the surface divided by the range (higher is
    better: head-on and near)."""
    beam = xyz - origin
    distance = np.linalg.norm(beam, axis=1)
    cosine = np.abs(np.einsum("ij,ij->i", beam, normals)) / np.maximum(distance, 1e-9)
    return np.asarray(cosine / np.maximum(distance, 1e-3), np.float64)


def voxel_winners(xyz: F64, scans: NDArray[np.int64], score: F64, count: int, voxel_m: float
                  ) -> NDArray[np.bool_]:
    """Which rows belong to the scan that wins their voxel: per voxel of ``voxel_m`` the scan
    (of ``count``) with the highest mean ``score`` over its rows there wins."""
    keys = np.floor(xyz / voxel_m).astype(np.int64)
    _, voxel = np.unique(keys, axis=0, return_inverse=True)
    voxel = voxel.ravel()
    pair = voxel * count + scans
    pair_ids, pair_of = np.unique(pair, return_inverse=True)
    pair_of = pair_of.ravel()
    mean = np.bincount(pair_of, weights=score) / np.bincount(pair_of)
    pair_voxel = pair_ids // count
    order = np.lexsort((-mean, pair_voxel))
    first = np.concatenate([[True], pair_voxel[order][1:] != pair_voxel[order][:-1]])
    winner = np.zeros(len(pair_ids), bool)
    winner[order[first]] = True
    return np.asarray(winner[pair_of])


def merge_scans(tables: list[pa.Table], poses: list[F64], voxel_m: float = MERGE_VOXEL_M
                ) -> tuple[pa.Table, dict[str, Any]]:
    """All scans' points in the site frame; per voxel seen by several scans, only the scan
    with the best mean :func:`view_quality` keeps its points (no grid: profile = sample = −1)."""
    from scanpipe.normals import knn_normals

    parts, quality, scan_id = [], [], []
    for k, (table, pose) in enumerate(zip(tables, poses, strict=True)):
        xyz = _transform(_columns(table, XYZ), pose)
        origin = _transform(_columns(table, ORIGIN), pose)
        finite = np.all(np.isfinite(xyz), axis=1)
        table, xyz, origin = table.filter(pa.array(finite)), xyz[finite], origin[finite]
        normals = knn_normals(xyz.astype(np.float32), origin.astype(np.float32), 12)
        quality.append(view_quality(xyz, origin, normals.astype(np.float64)))
        scan_id.append(np.full(len(xyz), k, np.int64))
        columns = {name: table.column(name) for name in table.column_names}
        for axis, name in enumerate(XYZ):
            columns[name] = pa.array(xyz[:, axis].astype(np.float32))
        for axis, name in enumerate(ORIGIN):
            columns[name] = pa.array(origin[:, axis].astype(np.float32))
        columns["profile"] = pa.array(np.full(len(xyz), -1, np.int32))
        columns["sample"] = pa.array(np.full(len(xyz), -1, np.int32))
        columns.pop("filtered_by", None)
        parts.append(pa.table(columns))
    merged = pa.concat_tables(parts, promote_options="permissive")
    xyz = _columns(merged, XYZ)
    scans = np.concatenate(scan_id)
    score = np.concatenate(quality)
    keep = voxel_winners(xyz, scans, score, len(tables), voxel_m)
    report = {"points_in": len(xyz), "points_out": int(keep.sum()),
              "double_coverage_taken": int((~keep).sum()), "merge_voxel_m": voxel_m}
    return merged.filter(pa.array(keep)), report


def read_true_poses(path: Path) -> dict[str, F64]:
    """True poses (scan name → pose) from a truth folder of ``simulate --site`` or a poses
    file."""
    file = path / "poses.parquet" if path.is_dir() else path
    if not file.is_file():
        raise UsageError(f"--truth {path}: no poses.parquet (give the truth folder of "
                         "`scanpipe simulate --site` or a poses Parquet file)")
    table, _ = read_artifact(file)
    return poses_from_table(table, where=f"--truth {file}")


def scan_workdirs(paths: list[Path], command: str) -> tuple[list[Path], list[str]]:
    """The scans' workdirs among ``paths`` and their names (the folder names), for
    ``register`` and ``site-model``. The batch summary (``batch.json``, which ``work/*`` picks
    up beside a batch's workdirs) is passed over; any other non-folder, or two workdirs of one
    name, is a one-line usage error."""
    from scanpipe.batch import MANIFEST

    workdirs = [p for p in paths if not (p.name == MANIFEST and p.is_file())]
    for workdir in workdirs:
        if not workdir.is_dir():
            raise UsageError(f"{workdir}: not a folder (give the workdir of each scan)")
    names = [w.resolve().name for w in workdirs]
    if len(set(names)) != len(names):
        raise UsageError(f"{command}: two workdirs share a folder name ("
                         f"{', '.join(sorted({n for n in names if names.count(n) > 1}))}); "
                         "scans are named after their workdir folders")
    return workdirs, names


def register_site(workdirs: list[Path], out: Path, params: RegisterParams,
                  prior_path: Path | None = None, force: bool = False,
                  progress: Any = None, truth_path: Path | None = None) -> dict[str, Any]:
    """``scanpipe register``: register the scans, write the poses and the merged points; with
    ``truth_path``, each pose's error against the true one (relative to the first scan) in
    ``report["pose_errors"]``."""
    from scanpipe.outpaths import check_output_files, check_output_folder

    workdirs, names = scan_workdirs(workdirs, "register")
    if len(workdirs) < 2:
        raise UsageError(f"register: {len(workdirs)} workdir given; a site needs at least 2")
    check_output_folder(out, "--out", workdirs)
    check_output_files([out / POSES_FILE, out / POINTS_FILE], "--out", force, workdirs)
    loaded = [scan_points(w) for w in workdirs]
    # georeferenced imports: one offset for all, else their frames differ by whole metres
    named = [(str(w), t) for w, (t, _) in zip(workdirs, loaded, strict=True)]
    offset = common_offset(named, "register", UsageError)
    crs = common_crs(named, "register", UsageError)
    prior = read_prior(prior_path, names) if prior_path is not None else None
    truth = read_true_poses(truth_path) if truth_path is not None else None
    prepared = [registration_cloud(n, w, t, params)
                for n, w, (t, _) in zip(names, workdirs, loaded, strict=True)]
    clouds = [cloud for cloud, _ in prepared]
    poses, covs, report = register_scans(clouds, params, prior, progress)
    report["warnings"] = [w for _, w in prepared if w is not None] + report["warnings"]
    if any(offset):
        report["offset_z_up_m"] = list(offset_z_up(offset))
    done = [k for k, p in enumerate(poses) if p is not None]
    if len(done) < 2:
        shown = "; ".join(f"{p['target']}–{p['source']}: {p['reason']}"
                          for p in report["pairs"][:3])
        more = len(report["pairs"]) - 3
        raise ArtifactError("register: no two scans could be placed unambiguously ("
                            + shown + (f"; {more} more pairs left out" if more > 0 else "")
                            + ")")
    key = artifact_key("register", 3, params.model_dump(mode="json"),
                       {n: k for n, (_, k) in zip(names, loaded, strict=True)}, {})
    provenance = {"stage": "register", "key": key, "params": params.model_dump(mode="json"),
                  "inputs": [str(w) for w in workdirs], "report": report}
    table = poses_table([names[k] for k in done], [poses[k] for k in done],  # type: ignore[misc]
                        [covs[k] for k in done])
    POSES.check(table)
    out.mkdir(parents=True, exist_ok=True)
    merged, merge_report = merge_scans([loaded[k][0] for k in done],
                                       [poses[k] for k in done])  # type: ignore[misc]
    write_artifact(out / POSES_FILE, table, provenance)
    merged = with_crs(with_offset(merged, offset), crs)
    write_artifact(out / POINTS_FILE, merged, {**provenance, "stage": "merge",
                                               "report": merge_report})
    report["merge"] = merge_report
    if truth is not None:
        report["pose_errors"] = pose_errors({names[k]: poses[k] for k in done},  # type: ignore[misc]
                                            {n: truth[n] for n in names if n in truth})
    report["poses"] = str(out / POSES_FILE)
    report["points"] = str(out / POINTS_FILE)
    return report
