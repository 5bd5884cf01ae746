"""The options of a simulated scan, shared by direct mode and the emulators."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from scanpipe.params import Params
from scanpipe.planning import DEFAULT_MOTOR_STEP_DEG, choose_steps
from scanpipe.rig import Pose, Rig, default_rig
from scanpipe.sim.camera import CameraModel, scaled_camera
from scanpipe.sim.scanner import MeasurementModel

#: 2026-01-01T00:00:00Z: the host clock of a simulated session starts here (deterministic).
DEFAULT_START_TIME_NS = 1_767_225_600_000_000_000


class SimOptions(Params):
    """Everything a simulated scan depends on (with the seed, it fixes every byte).

    ``rig`` is the NOMINAL rig: what the user believes and what the recording carries. The
    ``true_*`` options say how the rig really is (None: as nominal); the truth folder holds that
    true rig, so calibration can be tested against it.
    """

    scene: str = Field("room", description="room, box, or a scene file (.obj, .glb, .gltf) "
                                           "in metres.")
    scene_pose: Pose | None = Field(
        None, description="Where the scene file goes in the rig frame: rotation (degrees) then "
                          "translation (metres), after --scene-up.")
    scene_up: Literal["y", "z"] = Field(
        "y", description="The up axis of the scene file: y (OBJ, glTF) or z (z-up files; "
                         "turned to y up).")
    rig: Rig = Field(default_factory=default_rig)
    mode: Literal["step", "continuous"] = Field(
        "step", description="step (step-and-scan) or continuous.")
    motor_step_deg: float = Field(DEFAULT_MOTOR_STEP_DEG, gt=0, le=180,
                                  description="Motor step in degrees: the platform turn between "
                                              "profiles (the closest achievable is used).")
    beam_step_deg: float | None = Field(None, gt=0, le=90,
                                        description="Beam step in degrees: the angle between "
                                                    "samples of a profile (default: the rig's).")
    noise_sigma_m: float = Field(0.010, ge=0, le=1)
    dropout_rate: float = Field(0.002, ge=0, le=1)
    grazing_start_deg: float = Field(75.0, ge=0, le=90)
    mixed_pixels: bool = False
    mixed_pixel_rate: float = Field(0.5, ge=0, le=1)
    cameras: bool = Field(True, description="Simulate the rig's cameras.")
    camera_scale: float = Field(0.5, gt=0, le=1,
                                description="Camera resolution as a fraction of the rig's.")
    camera_fps: float | None = Field(1.0, gt=0, le=240,
                                     description="Camera frame rate (None: the rig's).")
    camera_noise_sigma: float = Field(1.0, ge=0, le=50)
    camera_exposure_gain: float = Field(1.0, gt=0, le=4)
    camera_exposure_jitter: float = Field(0.0, ge=0, le=1)
    jpeg_quality: int = Field(90, ge=1, le=100)
    true_mount: Pose | None = None
    true_alpha_offset_deg: float | None = Field(None, ge=-180, le=180)
    true_beta_offset_deg: float | None = Field(None, ge=-180, le=180)
    scip_protocol: Literal["2.0", "1.1", "1.1-silent", "1.1-only"] = Field(
        "2.0", description="A Hokuyo's protocol at power-on: 2.0, 1.1 (a URG-04LX of older "
                           "firmware: switches on 'SCIP2.0'), 1.1-silent (the same, SCIP 2.0 "
                           "commands unanswered) or 1.1-only (refuses the switch)")
    seed: int = Field(0, ge=0, description="Random seed: the same seed, the same bytes.")
    start_time_ns: int = Field(DEFAULT_START_TIME_NS, ge=0)
    report_interval_s: float = Field(0.02, gt=0, le=10)
    link_latency_s: float = Field(0.001, ge=0, le=1)

    def nominal_rig(self) -> Rig:
        """The rig the recording carries: ``rig`` with the beam step and camera overrides."""
        scanner = self.rig.scanner
        if self.beam_step_deg is not None:
            scanner = scanner.model_copy(update={"beam_step_deg": self.beam_step_deg})
        cameras = tuple(scaled_camera(c, self.camera_scale) for c in self.rig.cameras)
        if self.camera_fps is not None:
            cameras = tuple(c.model_copy(update={"fps": self.camera_fps}) for c in cameras)
        if not self.cameras:
            cameras = ()
        return self.rig.model_copy(update={"scanner": scanner, "cameras": cameras})

    def true_rig(self) -> Rig:
        """The rig as it really is: the nominal one with the ``true_*`` options applied."""
        nominal = self.nominal_rig()
        scanner_update: dict[str, object] = {}
        if self.true_mount is not None:
            scanner_update["mount"] = self.true_mount
        if self.true_alpha_offset_deg is not None:
            scanner_update["alpha_offset_deg"] = self.true_alpha_offset_deg
        motor = nominal.motor
        if self.true_beta_offset_deg is not None:
            motor = motor.model_copy(update={"beta_offset_deg": self.true_beta_offset_deg})
        scanner = nominal.scanner.model_copy(update=scanner_update)
        return nominal.model_copy(update={"scanner": scanner, "motor": motor})

    def motor_step_count(self) -> int:
        """Pulses per motor step: the achievable step closest to ``motor_step_deg``."""
        motor = self.rig.motor
        choice = choose_steps(self.motor_step_deg, motor.pulse_step_deg, motor.pulse_limit)
        return choice.chosen_steps

    def measurement(self) -> MeasurementModel:
        """The scanner's measurement model."""
        return MeasurementModel(
            noise_sigma_m=self.noise_sigma_m, dropout_rate=self.dropout_rate,
            grazing_start_deg=self.grazing_start_deg, mixed_pixels=self.mixed_pixels,
            mixed_pixel_rate=self.mixed_pixel_rate, seed=self.seed)

    def camera_model(self) -> CameraModel:
        """The cameras' image model."""
        return CameraModel(noise_sigma=self.camera_noise_sigma,
                           exposure_gain=self.camera_exposure_gain,
                           exposure_jitter=self.camera_exposure_jitter,
                           jpeg_quality=self.jpeg_quality)
