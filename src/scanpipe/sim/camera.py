"""The simulated camera: render the textured scene through the rig's camera model.

A ray per pixel (:func:`scanpipe.camera.pixel_rays`, lens distortion undone, so the render
matches :func:`scanpipe.camera.project_points`), the texel at each hit, optional sensor noise
and an exposure gain, then JPEG with OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from scanpipe.camera import pixel_rays
from scanpipe.geometry import platform_rotation
from scanpipe.rig import CameraConfig
from scanpipe.sim.scene import Scene

U8 = NDArray[np.uint8]

#: What a pixel sees where no surface is (an open scene's sky).
BACKGROUND_RGB = (0, 0, 0)


@dataclass(frozen=True)
class CameraModel:
    """Image effects: sensor noise (σ in 8-bit levels), exposure gain, its frame-to-frame
    change (relative σ: auto-exposure hunting), JPEG quality."""

    noise_sigma: float = 0.0
    exposure_gain: float = 1.0
    exposure_jitter: float = 0.0
    jpeg_quality: int = 90


def render_rgb(scene: Scene, cam: CameraConfig, beta_deg: float, model: CameraModel = CameraModel(),
               rng: np.random.Generator | None = None) -> U8:
    """The image (height, width, 3) RGB uint8 the camera sees at platform angle ``beta_deg``."""
    origin0, directions0 = _rays_at_zero(cam)
    rotation = platform_rotation(beta_deg).astype(np.float32)
    # einsum: numpy's matmul is several times slower for (N, 3) @ (3, 3) in float32
    hits = scene.cast(rotation @ origin0, np.einsum("ij,kj->ik", directions0, rotation))
    rgb = scene.color_at(hits.triangle_id, hits.barycentric, BACKGROUND_RGB)
    image = rgb.reshape(cam.height, cam.width, 3)
    if model.exposure_gain != 1.0 or model.noise_sigma > 0 or model.exposure_jitter > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        gain = model.exposure_gain * max(0.0, 1.0 + model.exposure_jitter * rng.standard_normal())
        value = image.astype(np.float32) * np.float32(gain)
        if model.noise_sigma > 0:
            value += rng.standard_normal(value.shape, dtype=np.float32) * np.float32(
                model.noise_sigma)
        image = np.clip(np.rint(value), 0, 255).astype(np.uint8)
    return image


@lru_cache(maxsize=8)
def _rays_at_zero(cam: CameraConfig) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The camera's pixel rays at β = 0 (at β they turn with the platform: R(β) · ray)."""
    origin, directions = pixel_rays(cam, 0.0)
    return origin.astype(np.float32), directions.reshape(-1, 3).astype(np.float32)


def scaled_camera(cam: CameraConfig, scale: float) -> CameraConfig:
    """The same camera at ``scale`` × the resolution (intrinsics scaled with it)."""
    if scale == 1.0:
        return cam
    width, height = max(16, round(cam.width * scale)), max(16, round(cam.height * scale))
    sx, sy = width / cam.width, height / cam.height
    return cam.model_copy(update={
        "width": width, "height": height, "fx": cam.fx * sx, "fy": cam.fy * sy,
        "cx": (cam.cx + 0.5) * sx - 0.5, "cy": (cam.cy + 0.5) * sy - 0.5,
    })
