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
visibility, icm, patches, seam_strip, atlas, png).
``python benchmarks/bench_texture.py [--quick] [--render-scale S]`` prints the figures and
saves JSON into ``benchmarks/results/``.

``--lab RUN`` instead textures a finished lab-scale run's mesh and frames (a workdir with
``mesh/``, ``decode/`` and ``calibrate/``, e.g. ``benchmarks/cache/lab-*/runs/default``: 4.76 M
faces, Full-HD frames) and reports the stage's wall and CPU seconds per phase, the process's peak
RSS and the counts that must not change (coverage, seam edges, rays), as ``texture-lab-<date>``.
"""

from __future__ import annotations

import os
import resource
import sys
import time
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
        result = STAGE.run(inputs, params)
        wall_s, cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        report = result.report
        quality = psnr_db(result, vertices, faces, reference)
        psnr, visible = quality["texture_psnr_db"], quality["texture_psnr_visible_db"]
        figures["methods"][method] = {"seconds": round(wall_s, 2), "cpu_seconds": round(cpu_s, 2),
                                      "phase_s": report.get("phase_s", {}),
                                      "phase_cpu_s": report.get("phase_cpu_s", {}),
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
    print(table([(name, f"{phases['phase_s'][name]:.2f} s", f"{cpu:.2f} s")
                 for name, cpu in phases["phase_cpu_s"].items()],
                ("projective phase", "wall", "CPU")))
    return figures


def run_lab(workdir: Path) -> dict[str, Any]:
    """The projective texture stage on a finished lab-scale run (see the module docstring)."""
    import pyarrow.parquet as pq

    def read(stage: str, name: str) -> pa.Table:
        return pq.read_table(workdir / stage / f"{name}.parquet")

    rig_stage = "calibrate" if (workdir / "calibrate" / "rig.parquet").exists() else "decode"
    inputs = {"mesh_vertices": read("mesh", "mesh_vertices"),
              "mesh_faces": read("mesh", "mesh_faces"), "frames": read("decode", "frames"),
              "motor": read("decode", "motor"), "rig": read(rig_stage, "rig")}
    inputs_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    wall0, cpu0 = time.perf_counter(), time.process_time()
    report = STAGE.run(inputs, TextureParams()).report
    wall_s, cpu_s = time.perf_counter() - wall0, time.process_time() - cpu0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    keys = ("faces", "coverage", "faces_untextured", "frames_considered", "frames_used",
            "occluded_candidates", "rays_cast", "regions", "pages", "photometric_outliers",
            "faces_multiview", "seam_edges_best_frame", "seam_edges", "seam_faces_moved",
            "seam_points")
    figures = {"workdir": str(workdir), "seconds": round(wall_s, 2),
               "cpu_seconds": round(cpu_s, 2), "phase_s": report["phase_s"],
               "phase_cpu_s": report["phase_cpu_s"], "inputs_peak_rss_mb": round(inputs_mb),
               "process_peak_rss_mb": round(peak_mb), "load_average": os.getloadavg(),
               **{k: report[k] for k in keys}}
    print(f"{report['faces']:,} faces, texture {wall_s:.1f} s wall, {cpu_s:.1f} s CPU, "
          f"process peak RSS {peak_mb:.0f} MB (inputs {inputs_mb:.0f} MB)")
    print(table([(name, f"{report['phase_s'][name]:.2f} s", f"{cpu:.2f} s")
                 for name, cpu in report["phase_cpu_s"].items()], ("phase", "wall", "CPU")))
    return figures


def _lab_option() -> Path | None:
    """``--lab RUN`` taken off the command line."""
    if "--lab" not in sys.argv:
        return None
    at = sys.argv.index("--lab")
    if at + 1 >= len(sys.argv) or not (Path(sys.argv[at + 1]) / "mesh").is_dir():
        sys.exit("bench_texture: --lab needs a run folder with mesh/, decode/ (and calibrate/)")
    path = Path(sys.argv[at + 1])
    del sys.argv[at:at + 2]
    return path


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
    SCALE = _render_scale_option()
    if LAB is not None:
        cli("texture-lab", lambda _quick: run_lab(LAB), __doc__ or "", "(ignored with --lab)")
    else:
        cli("texture", lambda quick: run(quick, SCALE), __doc__ or "",
            "a coarser mesh and 2 s of video")
