"""The paper's texture method (eq. 17–21): central strips of chosen frames joined into a
cylindrical panorama about the motor axis, mapped onto the model from the axis.

- eq. 17–19: the width of scene a camera of horizontal field of view α sees at distance r,
  ``iw = 2 · (r / cos(α/2)) · sin(α/2) = 2 r tan(α/2)``;
- eq. 20–21: with the camera moving across the scene at v (m/s) and recording ``fps`` frames
  per second, a new view of width iw is reached every ``f_si = iw · fps / v`` frames.

Choices the paper leaves open (docs/texture.md): v = ω · r with ω the platform's median
angular speed while moving, so selecting every f_si-th frame is the same as selecting a frame
per ``iw / r`` radians of platform angle; we select in angle (per strip of ``strip_deg``, the
sharpest frame), which also holds when the platform stops and goes. The strip is the turn
between two consecutive frames (narrow strips: little parallax and lens distortion), at least
0.5°. The panorama is a cylinder about the motor axis centred at the cameras' mean height:
column = azimuth θ = atan2(−x, z) (growing to the right as seen from the axis, so the image is
not mirrored), row = tan(elevation) (a cylindrical projection), sampled from
each frame with the calibrated camera model at distance r. The model takes its texture by the
same cylindrical projection of its vertices; faces outside the panorama's rows, facing away,
or hidden from the camera that filled their column get the neutral colour.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from scanpipe.camera import camera_pose_in_rig, pixel_rays, project_points
from scanpipe.errors import StageError
from scanpipe.progress import ProgressFn
from scanpipe.rig import MotorConfig, Rig
from scanpipe.texturing.exposure import sample_mean_colour, shrink, solve_gains
from scanpipe.texturing.frames import FrameSet, choose_frames
from scanpipe.texturing.visibility import MeshOcclusion, face_centroids

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
MAX_PAGE_PX = 8192
NEUTRAL_ROWS = 8
MIN_STRIP_DEG = 0.5


def visible_width_m(distance_m: float, hfov_deg: float) -> float:
    """Eq. 17–19: the width of scene seen at ``distance_m``: 2 (r / cos(α/2)) sin(α/2)."""
    half = math.radians(hfov_deg) / 2
    prone_m = distance_m / math.cos(half)  # eq. 18
    return 2 * math.sin(half) * prone_m  # eq. 17


def selection_interval_frames(image_width_m: float, fps: float, speed_m_s: float) -> float:
    """Eq. 20: frames between selected images, ``f_si = iw · fps / v`` (inf when not moving)."""
    return math.inf if speed_m_s <= 0 else image_width_m * fps / speed_m_s


def platform_speed_deg_s(motor_table: pa.Table, motor: MotorConfig) -> float:
    """Median angular speed of the platform between motor states while it moves (°/s)."""
    t = motor_table.column("log_time_ns").to_numpy().astype(np.int64)
    steps = motor_table.column("step_count").to_numpy().astype(np.float64)
    order = np.argsort(t, kind="stable")
    dt = np.diff(t[order]).astype(np.float64) / 1e9
    dbeta = np.abs(np.diff(steps[order])) * motor.pulse_step_deg
    moving = (dt > 0) & (dbeta > 0)
    return float(np.median(dbeta[moving] / dt[moving])) if moving.any() else 0.0


def recorded_fps(frames: pa.Table, camera_id: str) -> float | None:
    """Frames per second of one camera from its capture times (median interval); None if
    fewer than two frames."""
    times = frames.filter(pc.equal(frames.column("camera_id"), camera_id)).column(
        "log_time_ns").to_numpy()
    steps = np.diff(np.sort(times))
    steps = steps[steps > 0]
    return float(1e9 / np.median(steps)) if len(steps) else None


def cylinder_coordinates(points: NDArray[np.floating], centre: F64) -> tuple[F64, F64, F64]:
    """Azimuth θ (degrees, atan2(−x, z)), height ratio h = dy / ρ, and ρ about the axis."""
    d = np.asarray(points, np.float64) - centre
    rho = np.hypot(d[:, 0], d[:, 2])
    theta = np.degrees(np.arctan2(-d[:, 0], d[:, 2]))
    return theta, d[:, 1] / np.maximum(rho, 1e-9), rho


def optical_azimuth_deg(frames: FrameSet) -> F64:
    """Azimuth (atan2(−x, z), degrees) of each frame's optical axis in the rig frame."""
    result = np.empty(len(frames))
    for i, cam in enumerate(frames.cameras):
        rotation, _ = camera_pose_in_rig(cam, float(frames.beta_deg[i]))
        axis = rotation[:, 2]
        result[i] = math.degrees(math.atan2(-axis[0], axis[2]))
    return result


def height_range(frames: FrameSet, centre: F64) -> tuple[float, float]:
    """The h = tan(elevation) range every frame's image covers at its central column."""
    low, high = -math.inf, math.inf
    for cam in {c.id: c for c in frames.cameras}.values():
        _, rays = pixel_rays(cam, 0.0, stride=max(1, cam.height - 1))
        middle = rays[:, rays.shape[1] // 2]
        h = middle[:, 1] / np.hypot(middle[:, 0], middle[:, 2])
        low, high = max(low, float(h.min())), min(high, float(h.max()))
    return low, high


def angular_difference(a: F64, b: F64) -> F64:
    """Signed a − b wrapped into (−180°, 180°]."""
    return np.asarray((a - b + 180.0) % 360.0 - 180.0)


def build_panorama(frames: FrameSet, centre: F64, distance_m: float, px_per_deg: float,
                   h_range: tuple[float, float], wrap_deg: float, progress: ProgressFn
                   ) -> tuple[NDArray[np.uint8], I64, F64]:
    """The panorama (BGR), the frame that filled each column (−1: none), column azimuths."""
    width = math.ceil((360.0 + wrap_deg) * px_per_deg)
    rows_per_h = px_per_deg * 180.0 / math.pi  # equal scale at the horizon
    height = max(2, math.ceil((h_range[1] - h_range[0]) * rows_per_h))
    theta = np.asarray(-180.0 + (np.arange(width) + 0.5) / px_per_deg, dtype=np.float64)
    h = h_range[1] - (np.arange(height) + 0.5) / rows_per_h
    azimuth = optical_azimuth_deg(frames)
    hfov = np.array([c.hfov_deg for c in frames.cameras])
    off = np.abs(angular_difference(theta[:, None], azimuth[None, :]))
    column_frame = np.argmin(off, axis=1).astype(np.int64)
    column_frame[off[np.arange(width), column_frame] > hfov[column_frame] / 2] = -1
    panorama = np.zeros((height, width, 3), dtype=np.uint8)
    starts = np.flatnonzero(np.r_[True, column_frame[1:] != column_frame[:-1]])
    ends = np.r_[starts[1:], width]
    for k, (c0, c1) in enumerate(zip(starts, ends, strict=True)):
        i = int(column_frame[c0])
        if i < 0:
            continue
        t = np.radians(theta[c0:c1])
        points = centre + distance_m * np.stack(np.broadcast_arrays(
            -np.sin(t)[None, :], h[:, None], np.cos(t)[None, :]), axis=-1).reshape(-1, 3)
        uv, depth = project_points(points, frames.cameras[i], float(frames.beta_deg[i]))
        uv[depth <= 0] = -1e6
        maps = uv.reshape(height, c1 - c0, 2).astype(np.float32)
        panorama[:, c0:c1] = cv2.remap(frames.image(i), maps[..., 0], maps[..., 1],
                                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        progress("panorama strips", k + 1, len(starts))
    return panorama, column_frame, theta


def strip_gains(panorama_frames: I64, theta: F64, h_range: tuple[float, float],
                frames: FrameSet, centre: F64, distance_m: float) -> F64:
    """Per-frame gains from the colours both neighbours see at each strip boundary."""
    boundaries = np.flatnonzero(panorama_frames[1:] != panorama_frames[:-1])
    boundaries = boundaries[(panorama_frames[boundaries] >= 0)
                            & (panorama_frames[boundaries + 1] >= 0)]
    hs = np.linspace(h_range[0], h_range[1], 34)[1:-1]
    fa_list, fb_list, ca_list, cb_list = [], [], [], []
    small: dict[int, NDArray[np.uint8]] = {}
    for b in boundaries:
        a_i, b_i = int(panorama_frames[b]), int(panorama_frames[b + 1])
        small = {k: v for k, v in small.items() if k in (a_i, b_i)}  # boundaries come in order
        t = math.radians(0.5 * (theta[b] + theta[b + 1]))
        points = centre + distance_m * np.stack(
            [np.full_like(hs, -math.sin(t)), hs, np.full_like(hs, math.cos(t))], axis=1)
        colours = []
        for i in (a_i, b_i):
            cam = frames.cameras[i]
            if i not in small:
                small[i] = shrink(frames.image(i), 4)
            uv, _ = project_points(points, cam, float(frames.beta_deg[i]))
            colours.append(sample_mean_colour(small[i], uv, 4))
        fa_list.append(np.full(len(hs), a_i))
        fb_list.append(np.full(len(hs), b_i))
        ca_list.append(colours[0])
        cb_list.append(colours[1])
    if not fa_list:
        return np.ones((len(frames), 3))
    ca, cb = np.concatenate(ca_list), np.concatenate(cb_list)
    usable = np.all((ca > 4) & (ca < 251) & (cb > 4) & (cb < 251), axis=1)
    return solve_gains(np.concatenate(fa_list)[usable], np.concatenate(fb_list)[usable],
                       ca[usable], cb[usable], len(frames))


class PanoramaOptions(Protocol):
    """The texture parameters the panorama reads (``TextureParams`` has them all)."""

    @property
    def panorama_distance_m(self) -> float: ...
    @property
    def panorama_strip_deg(self) -> float: ...
    @property
    def panorama_px_per_deg(self) -> float: ...
    @property
    def frame_stride(self) -> int: ...
    @property
    def exposure(self) -> bool: ...
    @property
    def min_cos(self) -> float: ...
    @property
    def two_sided(self) -> bool: ...
    @property
    def neutral_rgb(self) -> tuple[int, int, int]: ...


@dataclass(frozen=True)
class Panorama:
    """The panorama method's result as arrays: one atlas page, the faces mapped onto it."""

    face_page: NDArray[np.int16]  # 0, or −1 for untextured faces
    face_uv: NDArray[np.float32]  # (F, 3, 2) in [0, 1] of the page, v = 0 at the top
    face_frame: I64  # index into ``frames``, −1 untextured
    page: NDArray[np.uint8]  # the panorama plus a neutral band, BGR
    panorama: NDArray[np.uint8]  # the panorama alone, BGR (panorama.png)
    frames: FrameSet
    report: dict[str, Any]


def texture_panorama(vertices: F64, faces: I64, normals: F64, inputs: Mapping[str, Any],
                     rig: Rig, params: PanoramaOptions, progress: ProgressFn) -> Panorama:
    """The panorama method of the texture stage (see the module docstring)."""
    started = time.perf_counter()
    cam0 = rig.cameras[0]
    recorded = inputs["frames"]
    centre_guess = np.array([0.0, float(np.mean([c.pose.translation_m[1] for c in rig.cameras])),
                             0.0])
    _, _, rho = cylinder_coordinates(vertices, centre_guess)
    distance_m = params.panorama_distance_m or float(np.median(rho)) if len(rho) else 1.0
    speed_deg_s = platform_speed_deg_s(inputs["motor"], rig.motor)
    speed_m_s = math.radians(speed_deg_s) * distance_m
    fps = recorded_fps(recorded, cam0.id) or cam0.fps
    iw_m = visible_width_m(distance_m, cam0.hfov_deg)
    f_si = selection_interval_frames(iw_m, fps, speed_m_s)
    strip_deg = params.panorama_strip_deg or max(MIN_STRIP_DEG, speed_deg_s / fps)
    frames = choose_frames(recorded, inputs["motor"], rig, strip_deg, params.frame_stride,
                           progress)
    centre = np.array([0.0, float(np.mean([frames.centre(i)[1] for i in range(len(frames))])),
                       0.0])
    theta_v, h_v, rho_v = cylinder_coordinates(vertices, centre)
    corner_theta = theta_v[faces]
    span = corner_theta.max(axis=1) - corner_theta.min(axis=1)
    wraps = span > 180.0
    corner_theta = np.where(wraps[:, None] & (corner_theta < 0), corner_theta + 360.0,
                            corner_theta)
    wrap_deg = float(np.ptp(corner_theta[wraps], axis=1).max()) if wraps.any() else 0.0
    wrap_deg = min(wrap_deg + 1.0, 30.0)
    native = max(c.fx for c in frames.cameras) * math.pi / 180.0
    px_per_deg = params.panorama_px_per_deg or native
    px_per_deg = min(px_per_deg, (MAX_PAGE_PX - 1) / (360.0 + wrap_deg))
    h_range = height_range(frames, centre)
    rows_per_h = px_per_deg * 180.0 / math.pi
    if (h_range[1] - h_range[0]) * rows_per_h > MAX_PAGE_PX - NEUTRAL_ROWS:
        raise StageError("texture: the panorama would be taller than 8192 px; lower "
                         "panorama_px_per_deg")
    panorama, column_frame, theta = build_panorama(frames, centre, distance_m, px_per_deg,
                                                   h_range, wrap_deg, progress)
    gains = np.ones((len(frames), 3))
    if params.exposure:
        gains = strip_gains(column_frame, theta, h_range, frames, centre, distance_m)
        per_column = np.where(column_frame[:, None] >= 0, gains[column_frame], 1.0)
        panorama = np.clip(panorama * per_column[None, :, :].astype(np.float32) + 0.5, 0, 255
                           ).astype(np.uint8)
    height, width = panorama.shape[:2]
    # faces: cylindrical projection of the corners; column of the centroid names the frame
    u_px = (corner_theta + 180.0) * px_per_deg
    v_px = (h_range[1] - h_v[faces]) * rows_per_h
    centroid_col = np.clip(np.floor(u_px.mean(axis=1)).astype(np.int64), 0, width - 1)
    face_frame = column_frame[centroid_col].copy()
    inside = ((v_px.min(axis=1) >= 0.5) & (v_px.max(axis=1) <= height - 0.5)
              & (rho_v[faces].min(axis=1) > 1e-3) & (u_px.max(axis=1) <= width - 0.5))
    face_frame[~inside] = -1
    centroids = face_centroids(vertices, faces)
    to_axis = centre - centroids
    cos = np.einsum("ij,ij->i", normals, to_axis) / np.maximum(
        np.linalg.norm(to_axis, axis=1), 1e-12)
    if params.two_sided:
        cos = np.abs(cos)
    face_frame[cos < params.min_cos] = -1
    candidates = np.flatnonzero(face_frame >= 0)
    occlusion = MeshOcclusion(vertices, faces)
    centres = np.stack([frames.centre(i) for i in range(len(frames))]) if len(frames) else (
        np.zeros((0, 3)))
    visible = occlusion.faces_visible_from(centres, face_frame[candidates], candidates)
    face_frame[candidates[~visible]] = -1
    page = np.empty((height + NEUTRAL_ROWS, width, 3), dtype=np.uint8)
    page[:height] = panorama
    page[height:] = tuple(reversed(params.neutral_rgb))
    face_uv = np.empty((len(faces), 3, 2), dtype=np.float32)
    face_uv[:, :, 0] = (u_px + 0.0) / width
    face_uv[:, :, 1] = v_px / (height + NEUTRAL_ROWS)
    untextured = face_frame < 0
    face_uv[untextured, :, 0] = 0.5 / width
    face_uv[untextured, :, 1] = (height + NEUTRAL_ROWS / 2) / (height + NEUTRAL_ROWS)
    face_page = np.where(untextured, -1, 0).astype(np.int16)
    used = np.unique(face_frame[face_frame >= 0])
    report = {
        "method": "panorama",
        "frames_in_recording": frames.considered,
        "frames_considered": len(frames),
        "frames_used": len(used),
        "occluded_faces": int((~visible).sum()),
        "distance_m": round(distance_m, 4),
        "visible_width_m": round(iw_m, 4),
        "platform_speed_deg_s": round(speed_deg_s, 4),
        "camera_speed_m_s": round(speed_m_s, 4),
        "fps": round(fps, 3),
        "f_si_frames": round(f_si, 3) if math.isfinite(f_si) else None,
        "strip_deg": round(strip_deg, 4),
        "strip_px": round(strip_deg * px_per_deg, 2),
        "panorama_px": [width, height],
        "px_per_deg": round(px_per_deg, 3),
        "pages": 1,
        "neutral_rgb": list(params.neutral_rgb),
        "seconds": round(time.perf_counter() - started, 3),
    }
    return Panorama(face_page, face_uv, face_frame, page, panorama, frames, report)
