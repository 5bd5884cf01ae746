"""Helpers of the acquisition tests: a small video file, a rig for the virtual devices."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scanpipe.rig import CameraConfig, Rig, default_rig


def write_video(path: Path, frames: int = 12, fps: float = 10.0, size: tuple[int, int] = (64, 48)
                ) -> Path:
    """An MJPG .avi whose frame i is filled with grey level 20·i (so frames can be told apart)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    assert writer.isOpened()
    for i in range(frames):
        writer.write(np.full((size[1], size[0], 3), (20 * i) % 256, np.uint8))
    writer.release()
    return path


def small_camera(camera_id: str = "cam0", source: str = "0", fps: float = 10.0) -> CameraConfig:
    """A tiny camera (64 × 48) so that tests encode little."""
    return CameraConfig(id=camera_id, source=source, width=64, height=48, fps=fps, fx=60.0,
                        fy=60.0, cx=31.5, cy=23.5)


def rig_with_cameras(*cameras: CameraConfig) -> Rig:
    """The default rig with the given cameras."""
    return default_rig().model_copy(update={"cameras": tuple(cameras)})


def sim_options(dialect: str = "ldoem", mode: str = "step", cameras: bool = False,
                pulse_limit: int = 1000, seed: int = 3) -> Any:
    """A small virtual-rig scan: 2° beam step, 5° motor step (139 pulses), box room."""
    from scanpipe.sim.options import SimOptions

    rig = default_rig()
    rig = rig.model_copy(update={
        "scanner": rig.scanner.model_copy(update={"dialect": dialect}),
        "motor": rig.motor.model_copy(update={"pulse_limit": pulse_limit}),
    })
    return SimOptions(rig=rig, scene="box", mode=mode, motor_step_deg=5.0, beam_step_deg=2.0,
                      cameras=cameras, camera_scale=0.04, camera_fps=2.0, seed=seed)


def record_against(virtual_rig: Any, out: Path, rig: Rig | None = None, **options: Any
                   ) -> dict[str, Any]:
    """Run the recorder against a started virtual rig (its speed-up, its cameras)."""
    from scanpipe.acquire.recorder import Recorder, RecordOptions

    settings = {"mode": virtual_rig.options.mode, "motor_step_deg": 5.0,
                "speedup": virtual_rig.clock.speedup, "install_signal_handlers": False,
                "cameras": virtual_rig.options.cameras, **options}
    recorder = Recorder(rig or virtual_rig.client_rig(), out, RecordOptions(**settings),
                        camera_opener=lambda cam: virtual_rig.camera(cam.source))
    return recorder.run()
