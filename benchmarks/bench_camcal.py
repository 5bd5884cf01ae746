"""Benchmark: camera self-calibration (issue 19) — a camera mount and a video clock recovered.

The built-in room is simulated directly with the TRUE rig (its cameras render the frames); the
fit starts from a WRONG rig: camera ``cam0`` turned by 2° about a random axis and moved by 3 cm.
Three cases per seed:

- **mount**: the recorded frames of cam0 (stamped by the recorder, no clock error);
- **mount360**: the recorded frames of the 360° camera cam360 (equirect; no focal length to
  fit), its mount turned and moved alike;
- **video**: a phone video of cam0 that runs from 4 s before the scan to 4 s after it, its frames
  stamped 0.5 s late (the rough ``import-video --offset``). Of the video, ``--frames`` frames
  spread over the scan, a quarter as many before and after it, and every 30 fps frame within
  1.6 s of the platform's start and stop are rendered (a phone has them all). The clock is
  read from the video's own motion around the start and stop
  (:func:`scanpipe.camera_selfcal.motion_clock`) and the mount fitted at it; ``--edge-clock``:
  the clock fitted to the edges with the mount instead (the fallback).

Reported: the rotation error (the angle between the fitted and the true camera rotation, and as
a rotation vector in the platform frame: which axis), the translation and focal errors (as
vectors too), the clock error, the edge alignment (median distance of the
scan's depth edges to the image edges, share within 2 px) before and after, the seconds.
Targets: rotation within 0.1°, clock within 20 ms, median ≤ 1.5 px, ≥ 70 % within 2 px.

``python benchmarks/bench_camcal.py --seeds 3 [--motor-step 0.25 --beam-step 0.25
--camera-scale 0.25]`` prints a table and saves JSON (per seed and case: the errors, the fitted
changes with their 1σ, the alignment before and after, wall and CPU seconds) into
``benchmarks/results/``; per case over the seeds, the mean and spread of each error (a mean
far above the spread is a bias of the method, not noise) and their correlation matrix.
``--sim-cache DIR`` reuses simulated scans; seeds may run in separate processes
(``--first-seed``) and ``--merge FILE...`` joins their results with statistics over all.
The scan limits the rotation: its edges' placement errors are the same in every frame
(docs/calibration.md "Cameras").
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import save, table

from scanpipe.camera_selfcal import calibrate_cameras, camera_with
from scanpipe.geometry import camera_to_platform
from scanpipe.images import encode_jpeg_rgb
from scanpipe.rig import CameraConfig, Pose, Rig
from scanpipe.sim.camera import render_rgb
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.session import plan_session
from scanpipe.stages.assemble import STAGE as ASSEMBLE
from scanpipe.stages.decode import STAGE as DECODE

ANGLE_TOL_DEG, TIME_TOL_S = 0.1, 0.020
MEDIAN_TOL_PX, WITHIN_MIN = 1.5, 0.70
VIDEO_ERROR_S = 0.5
VIDEO_MARGIN_S = 4.0
#: The video's rate and how long either side of the platform's start and stop its every frame
#: is offered to the fit (the clock's search window, ±1 s, and the 0.5 s error, with room).
VIDEO_FPS = 30.0
VIDEO_DENSE_S = 1.6


def perturbed(camera: CameraConfig, seed: int, angle_deg: float = 2.0,
              offset_m: float = 0.03) -> CameraConfig:
    """``camera`` turned by ``angle_deg`` about a random axis and moved by ``offset_m``."""
    rng = np.random.default_rng([seed, 19])
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    x = np.zeros(8)
    x[:3] = angle_deg * axis / np.linalg.norm(axis)
    x[3:6] = offset_m * shift / np.linalg.norm(shift)
    x[6] = 1.0
    return camera_with(camera, x)


def error_vector(fitted: CameraConfig, true: CameraConfig) -> list[float]:
    """The fit's error as (rotation vector in the platform frame (°), translation (m), focal
    scale − 1): the fit's own parameters, so their correlations read as the fit's valleys."""
    from scipy.spatial.transform import Rotation

    relative = camera_to_platform(fitted.pose.rotation_deg) @ camera_to_platform(
        true.pose.rotation_deg).T
    rotation = np.degrees(Rotation.from_matrix(relative).as_rotvec())
    shift = np.subtract(fitted.pose.translation_m, true.pose.translation_m)
    return [*map(float, rotation), *map(float, shift), fitted.fx / true.fx - 1.0]


ERROR_NAMES = ("rot_x_deg", "rot_y_deg", "rot_z_deg", "tx_m", "ty_m", "tz_m", "focal_scale")


def error_statistics(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean, spread (1σ over seeds), covariance and correlation matrix of the error
    vectors."""
    values = np.array([r["error_vector"] for r in runs])
    if len(values) < 2:
        return {"runs": len(values)}
    spread = values.std(axis=0, ddof=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.corrcoef(values, rowvar=False)
    return {"runs": len(values), "names": list(ERROR_NAMES),
            "mean": values.mean(axis=0).tolist(), "spread": spread.tolist(),
            "covariance": np.cov(values, rowvar=False).tolist(),
            "correlation": np.nan_to_num(corr).round(3).tolist()}


def error_over_sigma(errors: list[float], report: dict[str, Any]) -> list[float | None]:
    """Each error of :data:`ERROR_NAMES` over the 1σ the fit reported for it (None where the
    value was not fitted or has no 1σ): an honest 1σ keeps these mostly within ±2."""
    sigmas = {p["name"]: p["sigma"] for p in report["parameters"]}
    out: list[float | None] = []
    for name, error in zip(ERROR_NAMES, errors, strict=True):
        sigma = sigmas.get(name)
        out.append(error / sigma if sigma else None)
    return out


def rotation_error_deg(a: CameraConfig, b: CameraConfig) -> float:
    """The angle of the rotation between two cameras' orientations."""
    relative = camera_to_platform(a.pose.rotation_deg).T @ camera_to_platform(b.pose.rotation_deg)
    return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(relative) - 1) / 2))))


def with_camera(rig: Rig, camera: CameraConfig) -> Rig:
    """``rig`` with the camera of the same id replaced."""
    cameras = tuple(camera if c.id == camera.id else c for c in rig.cameras)
    return rig.model_copy(update={"cameras": cameras})


def simulate(folder: Path, options: SimOptions, cache: Path | None = None
             ) -> dict[str, pa.Table]:
    """Simulate, decode and assemble in memory: points, frames, motor, rig. With ``cache``, the
    tables are read from there when an earlier run left them (same options), else saved."""
    import json

    import pyarrow.parquet as pq

    names = ("points", "frames", "motor")
    key = None
    if cache is not None:
        import hashlib

        key = cache / hashlib.sha256(options.model_dump_json().encode()).hexdigest()[:16]
        if all((key / f"{n}.parquet").exists() for n in names):
            return {n: pq.read_table(key / f"{n}.parquet") for n in names}
    simulate_direct(folder / "scan.mcap", folder / "truth", options)
    tables = dict(DECODE.run({"recording": folder / "scan.mcap"}).tables)
    tables["points"] = ASSEMBLE.run({n: tables[n] for n in ("profiles", "motor", "rig")}
                                    ).tables["points"]
    if key is not None:
        key.mkdir(parents=True, exist_ok=True)
        for n in names:
            pq.write_table(tables[n], key / f"{n}.parquet")
        (key / "options.json").write_text(json.dumps(options.model_dump(mode="json")))
    return tables


def video_frames(options: SimOptions, camera: CameraConfig, count: int,
                 late_s: float, scan_frames: int | None = None) -> pa.Table:
    """A ``frames`` table of a video of ``camera`` from :data:`VIDEO_MARGIN_S` before the
    session to as long after it, stamped ``late_s`` late: a quarter of ``count`` frames each
    before and after the scan, ``scan_frames`` (default: the rest of ``count``) spread over
    it and, as a phone records them, every frame at :data:`VIDEO_FPS` within
    :data:`VIDEO_DENSE_S` of the platform's start and stop (the fit chooses among them)."""
    true_rig = options.true_rig()
    session = plan_session(options, true_rig)
    scene = resolve_scene(options.scene, options.scene_pose, options.scene_up)
    # a real video has every frame at 30 fps: here a quarter of ``count`` each before and
    # after the scan, ``scan_frames`` (default: the rest of ``count``) spread over it, and
    # every frame around the start and stop
    still = max(1, count // 4)
    during = count - 2 * still if scan_frames is None else scan_frames
    dense = np.arange(-VIDEO_DENSE_S, VIDEO_DENSE_S, 1.0 / VIDEO_FPS)
    times = np.unique(np.concatenate([
        np.linspace(-VIDEO_MARGIN_S, -0.1, still),
        np.linspace(0.0, session.end_s, during),
        np.linspace(session.end_s + 0.1, session.end_s + VIDEO_MARGIN_S, still),
        dense, session.end_s + dense]))
    pulse = options.rig.motor.pulse_step_deg
    betas = session.timeline.steps_at(np.clip(times, 0.0, session.end_s)) * pulse \
        + true_rig.motor.beta_offset_deg
    rng = np.random.default_rng([options.seed, 23])
    data = [encode_jpeg_rgb(render_rgb(scene, camera, float(b), options.camera_model(), rng),
                            options.jpeg_quality) for b in betas]
    stamps = [options.start_time_ns + round((t + late_s) * 1e9) for t in times]
    return pa.table({"camera_id": pa.array([camera.id] * len(times), pa.string()),
                     "log_time_ns": pa.array(stamps, pa.int64()),
                     "sequence": pa.array(range(len(times)), pa.int64()),
                     "data": pa.array(data, pa.binary())})


def write_video(options: SimOptions, camera: CameraConfig, path: Path, fps: float) -> int:
    """An MJPG video of ``camera`` at ``fps`` from :data:`VIDEO_MARGIN_S` before the session to
    as long after it (what a phone filming the scan records); returns the host time (ns) of its
    first frame."""
    import cv2

    true_rig = options.true_rig()
    session = plan_session(options, true_rig)
    scene = resolve_scene(options.scene, options.scene_pose, options.scene_up)
    times = np.arange(-VIDEO_MARGIN_S, session.end_s + VIDEO_MARGIN_S, 1.0 / fps)
    pulse = options.rig.motor.pulse_step_deg
    betas = session.timeline.steps_at(np.clip(times, 0.0, session.end_s)) * pulse \
        + true_rig.motor.beta_offset_deg
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps,
                             (camera.width, camera.height))
    rng = np.random.default_rng([options.seed, 29])
    try:
        for beta in betas:
            rgb = render_rgb(scene, camera, float(beta), options.camera_model(), rng)
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return options.start_time_ns + round(float(times[0]) * 1e9)


CASES = ("mount", "video", "mount360")


def room_phase_deg(seed: int, motor_step: float) -> float:
    """A turn of the room about the axis within one motor step, drawn per seed: without it
    every seed samples the room's silhouettes at the same platform angles, and their
    placement errors (each to ± half a cell, the same in every frame) are one draw shared by
    all seeds — a common bias over the seeds that is the scan's, not the method's."""
    return float(np.random.default_rng([seed, 31]).uniform(0.0, motor_step))


def one(seed: int, motor_step: float, beam_step: float, camera_scale: float, frames: int,
        folder: Path, cases: tuple[str, ...] = CASES, cache: Path | None = None,
        random_phase: bool = False, clock_from_motion: bool = True) -> list[dict[str, Any]]:
    scene_pose = None
    if random_phase:
        scene_pose = Pose(translation_m=(0.0, 0.0, 0.0),
                          rotation_deg=(0.0, room_phase_deg(seed, motor_step), 0.0))
    options = SimOptions(motor_step_deg=motor_step, beam_step_deg=beam_step,
                         camera_scale=camera_scale, camera_fps=0.5, seed=seed,
                         scene_pose=scene_pose)
    tables = simulate(folder, options, cache)
    true_rig = options.true_rig()
    runs = []
    for case in cases:
        camera_id = "cam360" if case == "mount360" else "cam0"
        true_cam = true_rig.camera(camera_id)
        wrong_rig = with_camera(true_rig, perturbed(true_cam, seed))
        frames_table = tables["frames"]
        if case == "video":
            frames_table = video_frames(options, true_cam, frames, VIDEO_ERROR_S,
                                        scan_frames=frames)
        started, cpu_started = time.perf_counter(), time.process_time()
        result = calibrate_cameras(tables["points"], frames_table, tables["motor"], wrong_rig,
                                   [camera_id], fit_time_offset=case == "video",
                                   max_frames=frames, clock_from_motion=clock_from_motion)[0]
        seconds = time.perf_counter() - started
        cpu_seconds = time.process_time() - cpu_started
        after, before = result.alignment_after.as_dict(), result.alignment_before.as_dict()
        run: dict[str, Any] = {
            "seed": seed, "case": case, "seconds": seconds, "cpu_seconds": cpu_seconds,
            "room_phase_deg": scene_pose.rotation_deg[1] if scene_pose is not None else 0.0,
            "camera_id": camera_id,
            "rotation_error_before_deg": rotation_error_deg(wrong_rig.camera(camera_id),
                                                            true_cam),
            "rotation_error_deg": rotation_error_deg(result.after, true_cam),
            "translation_error_m": float(np.linalg.norm(np.subtract(
                result.after.pose.translation_m, true_cam.pose.translation_m))),
            "focal_error": result.after.fx / true_cam.fx - 1.0,
            "error_vector": error_vector(result.after, true_cam),
            "time_error_s": (None if result.time_offset_s is None
                             else result.time_offset_s + VIDEO_ERROR_S),
            "alignment_before": before, "alignment_after": after,
            "report": result.report()}
        run["error_over_sigma"] = error_over_sigma(run["error_vector"], run["report"])
        run["within_targets"] = bool(
            run["rotation_error_deg"] <= ANGLE_TOL_DEG
            and (run["time_error_s"] is None or (abs(run["time_error_s"]) <= TIME_TOL_S
                                                 and result.time_offset_determined is True))
            and (after["edge_median_px"] or math.inf) <= MEDIAN_TOL_PX
            and (after["edge_within_2px"] or 0.0) >= WITHIN_MIN)
        runs.append(run)
    return runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--motor-step", type=float, default=0.25)
    parser.add_argument("--beam-step", type=float, default=0.25)
    parser.add_argument("--camera-scale", type=float, default=0.25)
    parser.add_argument("--frames", type=int, default=48, help="frames per camera used")
    parser.add_argument("--cases", default=",".join(CASES),
                        help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--sim-cache", type=Path, default=None,
                        help="keep the simulated tables here and reuse them (same options)")
    parser.add_argument("--random-phase", action="store_true",
                        help="turn the room by a random fraction of a motor step per seed (the "
                             "seeds then also draw where the scan samples its silhouettes)")
    parser.add_argument("--edge-clock", action="store_true",
                        help="video: fit the clock to the edges with the mount (the fallback "
                             "when a video does not film the platform's start and stop), not "
                             "from the video's own motion")
    parser.add_argument("--label", default="",
                        help="appended to the result file's name (runs of one day kept apart)")
    parser.add_argument("--merge", type=Path, nargs="+", default=None,
                        help="no fits: merge these result files (runs split over processes) "
                             "into one, with the statistics over all their seeds")
    args = parser.parse_args()
    if args.merge:
        merge(args.merge)
        return
    cases = tuple(c for c in args.cases.split(",") if c)
    unknown = [c for c in cases if c not in CASES]
    if unknown or not cases:
        parser.error(f"--cases: unknown {', '.join(unknown) or '(none)'}; "
                     f"allowed: {', '.join(CASES)}")
    runs: list[dict[str, Any]] = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        with tempfile.TemporaryDirectory() as tmp:
            runs += one(seed, args.motor_step, args.beam_step, args.camera_scale, args.frames,
                        Path(tmp), cases, args.sim_cache, args.random_phase,
                        not args.edge_clock)
        for r in runs[-len(cases):]:
            time_error = "" if r["time_error_s"] is None else \
                f" clock {r['time_error_s'] * 1000:+.1f} ms"
            print(f"seed {seed} {r['case']}: rotation {r['rotation_error_before_deg']:.2f}° → "
                  f"{r['rotation_error_deg']:.3f}°{time_error}, edges median "
                  f"{r['alignment_before']['edge_median_px']:.2f} → "
                  f"{r['alignment_after']['edge_median_px']:.2f} px, within 2 px "
                  f"{r['alignment_after']['edge_within_2px'] * 100:.0f} %, pan error/1σ "
                  f"{_ratio(r['error_over_sigma'][1])} "
                  f"({r['seconds']:.1f} s, cpu {r['cpu_seconds']:.1f} s)", flush=True)
    summarise(runs, cases, vars(args), stem_for(args.motor_step, args.first_seed, cases,
                                                args.label))


def _ratio(value: float | None) -> str:
    return "—" if value is None else f"{value:+.2f}"


def stem_for(motor_step: float, first_seed: int, cases: tuple[str, ...] = CASES,
             label: str = "") -> str:
    """The result file's name."""
    stem = f"camcal-{dt.date.today().isoformat()}-step-{motor_step:g}"
    if label:
        stem += f"-{label}"
    if cases != CASES:
        stem += "-" + "-".join(cases)
    return stem + (f"-from-seed-{first_seed}" if first_seed else "")


def merge(paths: list[Path]) -> None:
    """One result file from several (seeds run in separate processes)."""
    import json

    loaded = [json.loads(p.read_text()) for p in paths]
    runs = sorted((r for d in loaded for r in d["runs"]), key=lambda r: (r["seed"], r["case"]))
    cases = tuple(c for c in CASES if any(r["case"] == c for r in runs))
    args = {**loaded[0]["args"], "merged": [str(p) for p in paths],
            "seeds": len({r["seed"] for r in runs}), "first_seed": min(r["seed"] for r in runs)}
    summarise(runs, cases, args, stem_for(args["motor_step"], 0, cases,
                                          args.get("label") or "") + "-merged")


def summarise(runs: list[dict[str, Any]], cases: tuple[str, ...], args: dict[str, Any],
              stem: str) -> None:
    """Print the table and the error statistics; save the JSON."""
    rows = []
    statistics = {}
    for case in cases:
        mine = [r for r in runs if r["case"] == case]
        statistics[case] = error_statistics(mine)
        clock = [abs(r["time_error_s"]) for r in mine if r["time_error_s"] is not None]
        rows.append((case, f"{sum(r['within_targets'] for r in mine)}/{len(mine)}",
                     f"{max(r['rotation_error_deg'] for r in mine):.3f}",
                     f"{max(r['translation_error_m'] for r in mine) * 1000:.1f}",
                     f"{max(abs(r['focal_error']) for r in mine) * 100:.2f}",
                     f"{max(clock) * 1000:.1f}" if clock else "—",
                     f"{max(r['alignment_after']['edge_median_px'] for r in mine):.2f}",
                     f"{min(r['alignment_after']['edge_within_2px'] for r in mine) * 100:.0f}",
                     f"{max(r['seconds'] for r in mine):.1f}"))
    print(table(rows, ("case", "within", "worst rot°", "worst t mm", "worst f %",
                       "worst clock ms", "worst median px", "least ≤2px %", "worst s")))
    for case, stats in statistics.items():
        if "mean" in stats:
            print(f"{case}: error mean ± spread over seeds: " + ", ".join(
                f"{n} {m:+.4g} ± {s:.2g}" for n, m, s in
                zip(stats["names"], stats["mean"], stats["spread"], strict=True)))
    for case in cases:
        ratios = [r.get("error_over_sigma") for r in runs if r["case"] == case]
        if ratios and all(ratios):
            print(f"{case}: rotation error / its 1σ per seed (rot_x, rot_y, rot_z): " + "; ".join(
                ", ".join(_ratio(v) for v in ratio[:3]) for ratio in ratios if ratio))
    print(f"saved {save({'args': args, 'runs': runs, 'statistics': statistics}, stem)}")


if __name__ == "__main__":
    main()
