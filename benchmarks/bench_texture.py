"""Benchmark: texture a lab-scale mesh from 10 s of video at 30 fps per camera, every frame at
the rig's own resolution (Full HD for the phones, 3840 × 1920 for the 360° camera).

Target (issue 19): ≤ 30 s, textured share of the surface ≥ 95 %, PSNR over the whole visible
surface ≥ 28 dB. The mesh is a scanner grid (0.5° × 0.25°, about 1 M faces) cast against the
built-in room of the virtual rig from the scanner's centre, so all of it is surface the scanner
sees; the default cameras (two phones and the 360° camera) record 300 frames each while the
platform turns 180° in 10 s. Frames are rendered at ``--render-scale`` of their size (default
0.25) and scaled up to the rig's resolution before JPEG encoding (rendering 900 frames in full
takes far longer than the benchmark; ``--render-scale 1`` does it); the stage always decodes
and textures frames of the rig's full resolution. Also reported: texture PSNR over 8 matched
views inside the room (over the textured pixels, and over all of the visible surface with
unseen faces as error), both methods, and the CPU seconds (all threads) beside the wall time
(the machine is shared; CPU time depends far less on the load), in all and per phase of the
projective method (``phase_s``, ``phase_cpu_s``: frames, score, photometric, ray_scene,
visibility, icm, patches, seam_strip, atlas, png), and each phase's peak resident memory
(``phase_peak_rss_mb``: the process's RSS sampled every few ms, so a phase's peak includes
what earlier phases still hold).
``python benchmarks/bench_texture.py [--quick] [--render-scale S]`` prints the figures and
saves JSON into ``benchmarks/results/``.

``--lab RUN`` instead textures a finished chain's artifacts (``RUN``: a workdir such as
``benchmarks/cache/lab-…/runs/default``, read only: the mesh, the decoded frames and motor, the
calibrated rig) with the default parameters, once, and reports the stage's wall and CPU seconds,
per phase with each phase's peak RSS and its rise over the RSS the phase started with
(``phase_rise_rss_mb``), and its coverage and counts
(``results/texture-lab-<date>.json``): the lab-scale figures of the texture phases; also a
digest of the ``textured_faces`` table and the frames it uses, so that two versions of the
code can be shown to texture alike.
"""

from __future__ import annotations

import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parent))

from harness import cli, table

from scanpipe.evaluate import Reference, texture_psnr
from scanpipe.render import RenderMesh, render_mesh_from_scene
from scanpipe.rig import Rig, default_rig, rig_table
from scanpipe.sim.camera import render_rgb, scaled_camera
from scanpipe.sim.room import builtin_room
from scanpipe.sim.scene import Scene
from scanpipe.stages import texture as texture_module
from scanpipe.stages.texture import STAGE, TextureParams

T0_NS = 1_700_000_000_000_000_000


def grid_mesh(scene: Scene, alpha_step_deg: float, beta_step_deg: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scanner-grid mesh of ``scene`` from the origin: vertices, faces, normals."""
    alpha = np.radians(np.arange(0.0, 360.0, alpha_step_deg))
    beta = np.radians(np.arange(0.0, 180.0, beta_step_deg))
    a, b = np.meshgrid(alpha, beta)  # (profiles, samples)
    directions = np.stack([np.sin(a) * np.cos(b), np.cos(a), np.sin(a) * np.sin(b)], -1)
    hits = scene.cast(np.zeros((directions.size // 3, 3)), directions.reshape(-1, 3))
    t = np.asarray(hits.t_hit_m).reshape(a.shape)
    points = directions * t[..., None]
    normals = -directions
    p, s = a.shape
    idx = np.arange(p * s).reshape(p, s)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    depth = t.reshape(-1)[faces]
    ok = np.isfinite(depth).all(1) & (depth.max(1) < 1.1 * depth.min(1))  # no depth edges
    return points.reshape(-1, 3), faces[ok], normals.reshape(-1, 3)


def video(scene: Scene, rig: Rig, seconds: float, fps: float, render_scale: float
          ) -> tuple[pa.Table, pa.Table]:
    """``frames`` and ``motor`` tables: the platform turns 180° in ``seconds``."""
    steps = round(180.0 / rig.motor.pulse_step_deg)
    motor_t = T0_NS + np.linspace(0, seconds * 1e9, 501).astype(np.int64)
    motor = pa.table({
        "log_time_ns": motor_t, "step_count": np.linspace(0, steps, 501).round().astype(np.int64),
        "target_step_count": np.full(501, steps), "moving": np.ones(501, bool),
        "device_time_us": (motor_t - T0_NS) // 1000,
    })
    rows: dict[str, list[Any]] = {k: [] for k in ("camera_id", "log_time_ns", "sequence", "data")}
    count = round(seconds * fps)
    for cam in rig.cameras:
        small = scaled_camera(cam, render_scale)
        for k in range(count):
            time_ns = T0_NS + round(k / fps * 1e9)
            beta = 180.0 * (time_ns - T0_NS) / (seconds * 1e9)
            rgb = render_rgb(scene, small, beta)
            full = cv2.resize(rgb[:, :, ::-1], (cam.width, cam.height),
                              interpolation=cv2.INTER_LINEAR)
            ok, jpeg = cv2.imencode(".jpg", full, [cv2.IMWRITE_JPEG_QUALITY, 90])
            assert ok
            rows["camera_id"].append(cam.id)
            rows["log_time_ns"].append(time_ns)
            rows["sequence"].append(k)
            rows["data"].append(jpeg.tobytes())
    n = len(rows["data"])
    size = {c.id: (c.width, c.height) for c in rig.cameras}
    frames = pa.table({
        "camera_id": pa.array(rows["camera_id"], pa.string()),
        "log_time_ns": pa.array(rows["log_time_ns"], pa.int64()),
        "sequence": pa.array(rows["sequence"], pa.int64()),
        "format": pa.array(["jpeg"] * n, pa.string()),
        "width": pa.array([size[c][0] for c in rows["camera_id"]], pa.int32()),
        "height": pa.array([size[c][1] for c in rows["camera_id"]], pa.int32()),
        "data": pa.array(rows["data"], pa.binary()),
    })
    return frames, motor


def psnr_db(result: Any, vertices: np.ndarray, faces: np.ndarray, reference: Reference
            ) -> dict[str, Any]:
    """Texture PSNR over 8 matched views (scanpipe.evaluate): textured pixels, and all of the
    visible surface."""
    tf = result.tables["textured_faces"]
    uv = np.stack([np.stack([tf.column(f"u{k}").to_numpy(), tf.column(f"v{k}").to_numpy()], 1)
                   for k in range(3)], 1)
    pages = {i: cv2.imdecode(np.frombuffer(p.as_py(), np.uint8), 1)[:, :, ::-1].copy()
             for i, p in enumerate(result.tables["texture_pages"].column("png"))}
    mesh = RenderMesh(vertices.astype(np.float32), faces.astype(np.int32),
                      face_uvs=uv.astype(np.float32),
                      face_pages=tf.column("page").to_numpy().astype(np.int32), pages=pages)
    return texture_psnr(mesh, reference, views=8, width=320)


def _rss_mb() -> float:
    """The process's resident memory now (Linux: /proc/self/statm), in MB."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


@contextmanager
def phase_peaks(interval_s: float = 0.003, rises: dict[str, float] | None = None
                ) -> Iterator[dict[str, float]]:
    """Each texture phase's peak RSS (MB) while the block runs, by phase name: a thread samples
    the RSS and the stage's :class:`~scanpipe.stages.texture.PhaseClock` laps close a phase
    (empty where /proc is missing). ``rises``, when given, gets each phase's peak less the RSS
    it started with (what the phase itself adds: the absolute RSS of the same input moves by
    a few hundred MB between runs, with what the allocators keep)."""
    peaks: dict[str, float] = {}
    if not os.path.exists("/proc/self/statm"):
        yield peaks
        return
    current = [_rss_mb()]
    stop = threading.Event()
    lock = threading.Lock()  # a sample taken before a lap must not land in the next phase

    def sample() -> None:
        while not stop.wait(interval_s):
            with lock:
                current[0] = max(current[0], _rss_mb())

    lap: Callable[[Any, str], None] = texture_module.PhaseClock.lap

    started = [current[0]]

    def lap_with_peak(clock: Any, phase: str) -> None:
        lap(clock, phase)
        with lock:
            now = _rss_mb()
            peaks[phase] = round(max(peaks.get(phase, 0.0), current[0], now))
            if rises is not None:
                rises[phase] = round(max(rises.get(phase, 0.0), peaks[phase] - started[0]))
            current[0] = started[0] = now

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    setattr(texture_module.PhaseClock, "lap", lap_with_peak)  # noqa: B010
    try:
        yield peaks
    finally:
        setattr(texture_module.PhaseClock, "lap", lap)  # noqa: B010
        stop.set()
        sampler.join()


def run(quick: bool = False, render_scale: float | None = None) -> dict[str, Any]:
    """Texture a lab-scale mesh from video at the rig's resolution; return the figures."""
    scene = builtin_room()
    rig = default_rig()
    started = time.perf_counter()
    alpha_step, beta_step = (1.0, 1.0) if quick else (0.5, 0.25)
    vertices, faces, normals = grid_mesh(scene, alpha_step, beta_step)
    seconds = 2.0 if quick else 10.0
    scale = render_scale or (0.125 if quick else 0.25)
    frames, motor = video(scene, rig, seconds, 30.0, scale)
    prepared_s = time.perf_counter() - started
    inputs = {
        "mesh_vertices": pa.table({**{c: vertices[:, k].astype(np.float32)
                                      for k, c in enumerate("xyz")},
                                   **{c: normals[:, k].astype(np.float32)
                                      for k, c in enumerate(("nx", "ny", "nz"))}}),
        "mesh_faces": pa.table({c: faces[:, k].astype(np.int32)
                                for k, c in enumerate(("v0", "v1", "v2"))}),
        "frames": frames, "motor": motor, "rig": rig_table(rig),
    }
    reference = Reference(render_mesh_from_scene(scene))
    figures: dict[str, Any] = {
        "faces": len(faces), "vertices": len(vertices), "frames": frames.num_rows,
        "frame_sizes": {c.id: [c.width, c.height] for c in rig.cameras}, "video_s": seconds,
        "render_scale": scale, "fps": 30.0, "prepare_s": round(prepared_s, 1),
        "target_s": 30.0, "target_coverage": 0.95, "target_psnr_visible_db": 28.0,
        "methods": {},
    }
    rows = []
    for method in ("projective", "panorama"):
        params = TextureParams(method=method)  # type: ignore[arg-type]
        wall0, cpu0 = time.perf_counter(), time.process_time()
        with phase_peaks() as peaks:
            result = STAGE.run(inputs, params)
        wall_s, cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        report = result.report
        quality = psnr_db(result, vertices, faces, reference)
        psnr, visible = quality["texture_psnr_db"], quality["texture_psnr_visible_db"]
        figures["methods"][method] = {"seconds": round(wall_s, 2), "cpu_seconds": round(cpu_s, 2),
                                      "phase_s": report.get("phase_s", {}),
                                      "phase_cpu_s": report.get("phase_cpu_s", {}),
                                      "phase_peak_rss_mb": peaks,
                                      "process_peak_rss_mb": round(peak_mb), **quality,
                                      "report": report}
        rows.append((method, f"{wall_s:.1f} s", f"{cpu_s:.1f} s", f"{peak_mb:.0f} MB",
                     f"{report['coverage']:.3f}", str(report["faces_untextured"]),
                     str(report["frames_used"]), f"{psnr:.1f} dB" if psnr else "-",
                     f"{visible:.1f} dB" if visible else "-"))
    figures["load_average"] = os.getloadavg()
    sizes = ", ".join(f"{c.id} {c.width}×{c.height}" for c in rig.cameras)
    print(f"{len(faces):,} faces, {frames.num_rows} frames ({sizes}; rendered at {scale:g} of "
          f"that) (prepared in {prepared_s:.0f} s)")
    print(table(rows, ("method", "wall", "CPU", "process peak RSS", "coverage", "untextured",
                       "frames used", "PSNR textured", "PSNR visible")))
    phases = figures["methods"]["projective"]
    print(table([(name, f"{phases['phase_s'][name]:.2f} s", f"{cpu:.2f} s",
                  f"{phases['phase_peak_rss_mb'].get(name, 0):.0f} MB")
                 for name, cpu in phases["phase_cpu_s"].items()],
                ("projective phase", "wall", "CPU", "peak RSS")))
    return figures


#: The artifacts the texture stage reads from a finished chain's workdir.
LAB_INPUTS = {"mesh_vertices": "mesh/mesh_vertices.parquet",
              "mesh_faces": "mesh/mesh_faces.parquet", "frames": "decode/frames.parquet",
              "motor": "decode/motor.parquet", "rig": "calibrate/rig.parquet"}


def textured_faces_digest(table: pa.Table) -> dict[str, Any]:
    """Digests of a ``textured_faces`` table, to tell runs of the same inputs apart: the
    whole table (faces, pages, UVs, cameras, frames) and the set of frames it uses."""
    import hashlib

    import pyarrow.compute as pc

    whole = hashlib.sha256()
    for name in table.column_names:
        column = table.column(name).combine_chunks()
        if pa.types.is_string(column.type):
            encoded = pc.dictionary_encode(column)
            whole.update(repr(encoded.dictionary.to_pylist()).encode())
            column = encoded.indices
        whole.update(name.encode())
        whole.update(np.asarray(column.to_numpy(zero_copy_only=False)).tobytes())
    pairs = sorted({f"{cam}:{frame}" for cam, frame in zip(
        table.column("camera_id").to_pylist(), table.column("frame").to_pylist(), strict=True)
        if cam is not None})
    return {"textured_faces_sha256": whole.hexdigest()[:16], "frames_used_list": pairs}


def run_lab(run_dir: Path) -> dict[str, Any]:
    """Texture a finished chain's mesh from its frames once (the default parameters): wall,
    CPU and peak RSS in all and per phase, and the report's coverage and counts."""
    import pyarrow.parquet as pq

    missing = [name for name in LAB_INPUTS.values() if not (run_dir / name).is_file()]
    if missing:
        sys.exit(f"bench_texture: {run_dir} lacks {', '.join(missing)} (a finished chain's "
                 "workdir, e.g. benchmarks/cache/lab-…/runs/default)")
    inputs = {key: pq.read_table(run_dir / name) for key, name in LAB_INPUTS.items()}
    rss_before = _rss_mb()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    rises: dict[str, float] = {}
    with phase_peaks(rises=rises) as peaks:
        result = STAGE.run(inputs, TextureParams())
    wall_s, cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
    report = result.report
    kept = ("coverage", "faces", "faces_textured", "frames_considered", "frames_used",
            "occluded_candidates", "rays_cast", "exposure_pairs", "photometric_outliers",
            "faces_multiview", "face_groups", "faces_scored_alone", "seam_edges_best_frame",
            "seam_edges", "seam_faces_moved",
            "seam_points", "regions", "pages", "gain_min", "gain_max")
    figures: dict[str, Any] = {
        "run": str(run_dir), "seconds": round(wall_s, 2), "cpu_seconds": round(cpu_s, 2),
        "rss_before_mb": round(rss_before),
        "process_peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "phase_s": report.get("phase_s", {}), "phase_cpu_s": report.get("phase_cpu_s", {}),
        "phase_peak_rss_mb": peaks, "phase_rise_rss_mb": rises,
        **{k: report[k] for k in kept if k in report},
        **textured_faces_digest(result.tables["textured_faces"]),
        "load_average": os.getloadavg()}
    print(f"texture of {run_dir}: {wall_s:.1f} s wall, {cpu_s:.1f} s CPU, process peak RSS "
          f"{figures['process_peak_rss_mb']} MB (inputs held: {rss_before:.0f} MB), coverage "
          f"{report.get('coverage')}")
    print(table([(name, f"{figures['phase_s'][name]:.2f} s", f"{cpu:.2f} s",
                  f"{peaks.get(name, 0):.0f} MB", f"{rises.get(name, 0):+.0f} MB")
                 for name, cpu in figures["phase_cpu_s"].items()],
                ("phase", "wall", "CPU", "peak RSS", "rise over its start")))
    return figures


def _lab_option() -> Path | None:
    """``--lab RUN`` taken off the command line."""
    if "--lab" not in sys.argv:
        return None
    at = sys.argv.index("--lab")
    if at + 1 >= len(sys.argv):
        sys.exit("bench_texture: --lab needs a workdir of a finished chain")
    value = Path(sys.argv[at + 1])
    del sys.argv[at:at + 2]
    return value


def _render_scale_option() -> float | None:
    """``--render-scale S`` taken off the command line (the shared harness knows --quick)."""
    if "--render-scale" not in sys.argv:
        return None
    at = sys.argv.index("--render-scale")
    try:
        value = float(sys.argv[at + 1])
    except (IndexError, ValueError):
        sys.exit("bench_texture: --render-scale needs a number in (0, 1]")
    if not 0 < value <= 1:
        sys.exit("bench_texture: --render-scale needs a number in (0, 1]")
    del sys.argv[at:at + 2]
    return value


if __name__ == "__main__":
    LAB = _lab_option()
    if LAB is not None:
        import datetime as dt

        from harness import save

        print(f"saved {save(run_lab(LAB), f'texture-lab-{dt.date.today().isoformat()}')}")
        sys.exit(0)
    SCALE = _render_scale_option()
    cli("texture", lambda quick: run(quick, SCALE), __doc__ or "",
        "a coarser mesh and 2 s of video")
