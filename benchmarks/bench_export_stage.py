"""Benchmark: the export stage on a finished run's artifacts, part by part (issue 20).

The default export of ``scanpipe run`` at lab scale: colouring the cloud from the camera
frames (the frame choice, which rates every frame's sharpness, apart), the textured mesh's OBJ
and GLB, the cloud's PLY, and the whole stage. Each part runs in a forked child (peak RSS is
the child's growth over the loaded inputs) and reports wall and CPU seconds.

``python benchmarks/bench_export_stage.py [--workdir RUN] [--repeats N]``: ``RUN`` is a
workdir of ``scanpipe run`` (default: the lab scan's default run in ``benchmarks/cache``,
made by ``python -m benchmarks``). The artifacts are only read. Saves JSON into
``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import scanpipe  # noqa: F401, I001  (first: Arrow's allocator set up as in ``scanpipe run``)
from harness import made, measure, save, table

from scanpipe.artifacts import read_artifact
from scanpipe.rig import rig_from_table
from scanpipe.stages import export as ex
from scanpipe.workdir import find_artifacts

CACHE_DIR = Path(__file__).parent / "cache"


def default_workdir() -> Path | None:
    """The lab scan's default run in the benchmark cache, if ``python -m benchmarks`` made
    one."""
    runs = sorted(CACHE_DIR.glob("lab-*/runs/default"), key=lambda p: p.stat().st_mtime)
    return runs[-1] if runs else None


def load_inputs(workdir: Path) -> dict[str, Any]:
    """The export stage's input tables from a run's workdir (the newest of each artifact)."""
    names = tuple(ex.STAGE.inputs)
    found = find_artifacts(workdir, names)
    missing = sorted(set(names) - set(found))
    if missing:
        raise SystemExit(f"{workdir}: no {', '.join(missing)} artifact; run the chain first")
    return {name: read_artifact(path)[0] for name, path in found.items()}


def run(workdir: Path, repeats: int) -> dict[str, Any]:
    """Measure the parts of the export stage on ``workdir``'s artifacts."""
    tables = load_inputs(workdir)
    faces = tables["mesh_faces"].num_rows
    points = tables["points"].num_rows
    params = ex.ExportStageParams()
    prepared, _ = ex.prepare_tables(tables, colors=False)
    mesh_tables = {k: v for k, v in prepared.items() if k in (*ex.MESH_ARTIFACTS,
                                                              *ex.TEXTURE_ARTIFACTS)}
    mesh = ex.models_from_tables(mesh_tables)[0]
    cloud_tables = {"points": prepared["points"]}
    cloud = ex.models_from_tables(cloud_tables)[1]
    rig = rig_from_table(tables["rig"])

    from scanpipe.texturing import projective
    from scanpipe.texturing.frames import choose_frames

    def choose() -> object:
        return choose_frames(tables["frames"], tables["motor"], rig, ex.FRAME_SPACING_DEG,
                             equirect_spacing_deg=max(ex.FRAME_SPACING_DEG,
                                                      projective.EQUIRECT_SPACING_DEG))

    chosen = choose()

    def colour_only() -> object:
        # the frames chosen once, outside the measurement: this is the colouring itself
        projective.choose_frames = lambda *a, **k: chosen  # type: ignore[assignment]
        chosen._cache.clear()  # type: ignore[attr-defined]
        return projective.colorize_points(tables["points"], tables["frames"], tables["motor"],
                                          rig, spacing_deg=ex.FRAME_SPACING_DEG)

    results = [
        measure("choose frames (rate sharpness)", choose, len(tables["frames"]), "frames",
                repeats),
        measure("colour the cloud (frames chosen)", colour_only, points, "points", repeats),
        measure("colour the cloud (whole)", lambda: ex.prepare_tables(tables), points,
                "points", repeats),
        measure("obj (+mtl, png)", lambda: made(ex.export_files(mesh_tables, "obj", "model",
                                                            models=(mesh, None))),
                faces, "faces", repeats),
        measure("glb", lambda: made(ex.export_files(mesh_tables, "glb", "model",
                                               models=(mesh, None))),
                faces, "faces", repeats),
        measure("ply (cloud)", lambda: made(ex.export_files(cloud_tables, "ply", "cloud",
                                                       models=(None, cloud))),
                points, "points", repeats),
        measure("mesh model from tables", lambda: ex.models_from_tables(mesh_tables), faces,
                "faces", repeats),
        # the stage with its files made and hashed, as the runner does while writing them
        measure("export stage (defaults)",
                lambda: ex.STAGE.call(tables, params), faces, "faces", repeats),
    ]
    figures: dict[str, Any] = {
        "workdir": str(workdir),
        "faces": faces,
        "points": points,
        "frames": len(tables["frames"]),
        "measurements": results,
        "cpu_s": {m.name: m.cpu_median_s for m in results},
        "wall_s": {m.name: m.median_s for m in results},
        "peak_rss_mb": {m.name: m.peak_rss_mb for m in results},
        "load_average_1min": os.getloadavg()[0],
    }
    print(table([(m.name, f"{m.median_s:.2f} s", f"{m.cpu_median_s:.2f} s",
                  f"{m.peak_rss_mb:.0f} MB") for m in results],
                ("part", "wall", "CPU", "peak RSS")))
    print(f"load average {os.getloadavg()[0]:.1f}")
    return figures


def main() -> None:
    """Command line: ``--workdir``, ``--repeats``; saves ``results/export-stage-<date>.json``."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=None,
                        help="a finished run's workdir (default: the lab scan's default run)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per part (median)")
    args = parser.parse_args()
    workdir = args.workdir or default_workdir()
    if workdir is None:
        raise SystemExit("no lab run in benchmarks/cache: run python -m benchmarks first or "
                         "pass --workdir")
    start = time.perf_counter()
    figures = run(workdir, max(1, args.repeats))
    figures["benchmark_s"] = time.perf_counter() - start
    print(f"saved {save(figures, f'export-stage-{dt.date.today().isoformat()}')}")


if __name__ == "__main__":
    main()
