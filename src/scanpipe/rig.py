"""The rig: scanner, motor, cameras and their calibration, read from and written to TOML.

The default is the paper's rig: a SICK LD-OEM 1000 at 0.25°, a Vexta PK566 (0.72° full step)
behind a 20:1 gearbox, a controller that refuses more than 5000 pulses, and two Full-HD cameras
facing opposite ways so that 180° of platform travel sees the whole room.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from scanpipe.errors import ParameterError, RigError
from scanpipe.params import Params, load_toml, parse_toml, to_toml, validate
from scanpipe.scanner_models import DIALECT_NAMES, SCANNER_MODELS, get_model, limit_problems

#: How far from the motor axis a scanner or camera can sit on a turntable rig (and how far the
#: simulator's scene may be moved): anything farther is a typo in metres (millimetres meant?).
MAX_OFFSET_M = 100.0
Metres = Annotated[float, Field(ge=-MAX_OFFSET_M, le=MAX_OFFSET_M)]
Degrees = Annotated[float, Field(ge=-360, le=360)]
Vec3 = tuple[float, float, float]
RIG_FORMAT_VERSION = 1


#: What a pulse can turn the platform by: below 1e-6° no gearbox is that fine, above 90° a
#: "turntable" step is a quarter turn.
MIN_PLATFORM_STEP_DEG = 1e-6
MAX_PLATFORM_STEP_DEG = 90.0
#: The field of view a pinhole camera model can describe (per axis).
MIN_FOV_DEG = 0.5
MAX_FOV_DEG = 170.0
#: The share of the image (per axis, centred) where a lens's principal point lies: a real
#: lens's is within a few percent of the centre. One outside the middle half is another
#: convention (Metashape's offset from the centre, near 0), another image's size, or a crop of
#: the sensor (a ROS ROI): :func:`camera_warnings` says so; outside the image it is refused.
PRINCIPAL_POINT_SPAN = 0.5


def principal_point_problem(axis: str, centre: float, size_px: int, plausible: bool) -> str:
    """What is wrong with ``c{axis} = centre`` over an image ``size_px`` wide (or high), or "".

    ``plausible=False`` checks that it lies within the image (pixel centres 0 … size − 1, edges
    at −0.5 and size − 0.5); ``plausible=True`` that it lies in the image's middle half.
    """
    if plausible:
        half = size_px * PRINCIPAL_POINT_SPAN / 2
        low, high = (size_px - 1) / 2 - half, (size_px - 1) / 2 + half
        where = f"the middle {PRINCIPAL_POINT_SPAN:.0%} of the image, where a lens's lies"
    else:
        low, high = -0.5, size_px - 0.5
        where = "the image"
    if low <= centre <= high:
        return ""
    if abs(centre) < size_px * PRINCIPAL_POINT_SPAN / 2:
        why = ("a value near 0 is likely an offset from the image centre (Metashape's cx, cy), "
               "not a position: import the calibration with `scanpipe rig intrinsics`")
    else:
        why = "intrinsics for another image size or orientation?"
    return (f"c{axis} = {centre:g} px is {abs(centre - (size_px - 1) / 2):.4g} px from the centre "
            f"of the {size_px} px image; allowed: {low:g} to {high:g} ({where}); {why}")


#: OpenCV's k1 k2 p1 p2 k3 of any real lens are far below this.
Coefficient = Annotated[float, Field(ge=-1000, le=1000)]


class Pose(Params):
    """A rigid pose in the parent frame: translation, then Euler angles (rx, ry, rz) in degrees.

    See :mod:`scanpipe.geometry` for the frames and the rotation order.
    """

    translation_m: tuple[Metres, Metres, Metres] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[Degrees, Degrees, Degrees] = (0.0, 0.0, 0.0)


#: Keys of ``[scanner]`` renamed since rig files were first written: old name → new name. Old
#: rig files, and the rig TOML stored in old recordings, still load.
SCANNER_KEY_RENAMES = {"angular_step_deg": "beam_step_deg"}


class ScannerConfig(Params):
    """The 2-D laser scanner: how to reach it, how it scans, and how it is mounted.

    ``beam_step_deg`` is the beam step: the angle between two samples of a profile.
    """

    #: A row of :data:`scanpipe.scanner_models.SCANNER_MODELS` ("" = unnamed; an ``ldoem``
    #: dialect without a model is the LD-OEM 1000).
    model: str = ""
    dialect: str = "ldoem"
    #: How the scanner is reached: ``tcp`` (host, port) or ``serial`` (serial_url, baudrate).
    transport: Literal["tcp", "serial"] = "tcp"
    host: str = Field("192.168.0.1", min_length=1)
    port: int = Field(49152, ge=1, le=65535)
    serial_url: str = Field("/dev/ttyUSB0", min_length=1)
    baudrate: int = Field(230400, ge=50, le=12_000_000)
    beam_step_deg: float = Field(0.25, gt=0, le=90)
    #: Negative starts describe scanners whose zero is the middle of their field of view
    #: (a Hokuyo: −135°…+135°); the LD-OEM's own angles run 0…360°.
    start_angle_deg: float = Field(0.0, ge=-360, lt=360)
    end_angle_deg: float = Field(360.0, gt=-360, le=360)
    scan_hz: float = Field(5.0, gt=0, le=100)
    min_range_m: float = Field(0.5, ge=0, le=255.99609375)
    max_range_m: float = Field(250.0, gt=0, le=255.99609375)
    alpha_offset_deg: float = Field(0.0, ge=-180, le=180)
    mount: Pose = Pose()

    @model_validator(mode="before")
    @classmethod
    def _renamed_keys(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        for old, new in SCANNER_KEY_RENAMES.items():
            if old in data and new in data:
                raise ValueError(f"{old} is the old name of {new}: give only {new}")
        return {SCANNER_KEY_RENAMES.get(k, k): v for k, v in data.items()}

    @field_validator("dialect")
    @classmethod
    def _known_dialect(cls, value: str) -> str:
        if value not in DIALECT_NAMES:
            raise ValueError(f"unknown dialect {value!r}; allowed: {', '.join(DIALECT_NAMES)}")
        return value

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        if value and value not in SCANNER_MODELS:
            raise ValueError(f"unknown scanner model {value!r}; allowed: "
                             f"{', '.join(SCANNER_MODELS)} (or leave it out)")
        return value

    @model_validator(mode="after")
    def _ranges_ordered(self) -> ScannerConfig:
        if self.model and self.dialect not in get_model(self.model).dialects:
            raise ValueError(f"model {self.model} speaks dialect "
                             f"{' or '.join(get_model(self.model).dialects)}, not {self.dialect}")
        if self.end_angle_deg <= self.start_angle_deg:
            raise ValueError(
                f"end_angle_deg ({self.end_angle_deg}) must be greater than "
                f"start_angle_deg ({self.start_angle_deg})"
            )
        if self.end_angle_deg - self.start_angle_deg > 360.0 + 1e-9:
            raise ValueError(
                f"end_angle_deg − start_angle_deg = {self.end_angle_deg - self.start_angle_deg:g}"
                "° is more than a full turn (360°)")
        if self.dialect == "ldoem" and self.start_angle_deg < 0:
            raise ValueError(
                f"start_angle_deg ({self.start_angle_deg:g}) is negative; the LD-OEM's angles "
                "run 0…360° (a scanner centred on 0°, e.g. −135…135, uses dialect = paper)")
        if self.max_range_m <= self.min_range_m:
            raise ValueError(
                f"max_range_m ({self.max_range_m}) must be greater than "
                f"min_range_m ({self.min_range_m})"
            )
        return self

    @property
    def samples_per_profile(self) -> int:
        """Samples in one profile: the covered sector divided by the beam step."""
        return round((self.end_angle_deg - self.start_angle_deg) / self.beam_step_deg)


#: The largest pulse count any controller can hold: its count is a signed 32-bit integer.
MAX_PULSE_COUNT = 2**31 - 1
#: The most a platform WITHOUT a slip ring may turn from home: two whole turns. Its cables (power,
#: USB, the scanner's Ethernet) wind round the axis; no cable guide takes more, and a larger
#: limit is a typo (1e17) or a platform that may turn freely, which must say so
#: (``unlimited_travel = true``).
MAX_LIMITED_TRAVEL_DEG = 720.0


class MotorConfig(Params):
    """The stepper, its gearbox and the controller that counts pulses.

    ``pulse_limit`` is the platform's travel from home (the controller's power-on position), in
    pulses: neither the controller nor the host sends it past, and a scan sweeps from home up
    to it. ``unlimited_travel`` says the platform may turn any amount (a slip ring): then nothing
    limits travel on the rig's side and ``pulse_limit`` is only the sweep of one scan.
    """

    full_step_deg: float = Field(0.72, gt=0, le=90)
    gear_ratio: float = Field(20.0, ge=0.001, le=100_000)
    unlimited_travel: bool = Field(False, strict=True)
    pulse_limit: int = Field(5000, ge=1, le=MAX_PULSE_COUNT, strict=True)
    pulse_rate_hz: float = Field(1000.0, gt=0, le=100_000)
    accel_hz_per_s: float = Field(5000.0, ge=1, le=10_000_000)
    settle_s: float = Field(0.05, ge=0, le=10)
    serial_url: str = Field("/dev/ttyUSB0", min_length=1)
    baudrate: int = Field(115200, ge=50, le=12_000_000)
    beta_offset_deg: float = Field(0.0, ge=-180, le=180)

    @field_validator("pulse_limit", mode="before")
    @classmethod
    def _whole_pulses(cls, value: Any) -> Any:
        # bool is an int in Python: `pulse_limit = true` would be taken as 1 pulse.
        if isinstance(value, bool) or not isinstance(value, int):
            kind = "a boolean" if isinstance(value, bool) else f"a {type(value).__name__}"
            raise ValueError(f"must be a whole number of pulses (1 … {MAX_PULSE_COUNT}), not "
                             f"{kind}; a platform that may turn freely sets "
                             "motor.unlimited_travel = true")
        if value > MAX_PULSE_COUNT:
            raise ValueError(f"more pulses than a controller counts (at most {MAX_PULSE_COUNT}, "
                             "a signed 32-bit count)")
        return value

    @field_validator("pulse_limit")
    @classmethod
    def _travel_a_cable_takes(cls, value: int, info: ValidationInfo) -> int:
        full, ratio = info.data.get("full_step_deg"), info.data.get("gear_ratio")
        if info.data.get("unlimited_travel", False) or full is None or ratio is None:
            return value
        travel_deg = value * full / ratio
        if travel_deg > MAX_LIMITED_TRAVEL_DEG:
            raise ValueError(
                f"{travel_deg:g}° of travel ({value} × {full / ratio:g}°) is more than "
                f"{MAX_LIMITED_TRAVEL_DEG:g}° (two platform turns), more than any cabled platform "
                "turns; give at most "
                f"{math.floor(MAX_LIMITED_TRAVEL_DEG * ratio / full + 1e-9)} pulses, or set "
                "motor.unlimited_travel = true for a platform on a slip ring")
        return value

    @model_validator(mode="after")
    def _platform_step_possible(self) -> MotorConfig:
        if not MIN_PLATFORM_STEP_DEG <= self.pulse_step_deg <= MAX_PLATFORM_STEP_DEG:
            raise ValueError(
                f"pulse step full_step_deg / gear_ratio = {self.full_step_deg:g} / "
                f"{self.gear_ratio:g} = {self.pulse_step_deg:g}°; allowed: "
                f"{MIN_PLATFORM_STEP_DEG:g}° to {MAX_PLATFORM_STEP_DEG:g}° per pulse"
            )
        return self

    @property
    def pulse_step_deg(self) -> float:
        """The pulse step: platform rotation per pulse (paper eq. 1, its "minimum step"), full
        step / gear ratio. A scan's motor step is a whole number of these."""
        return self.full_step_deg / self.gear_ratio

    @property
    def travel_limit(self) -> int | None:
        """The rig's travel limit in pulses from home; None when the platform turns freely."""
        return None if self.unlimited_travel else self.pulse_limit


#: The camera models a rig may give: an OpenCV pinhole with distortion, or a 360° camera's
#: equirectangular image (longitude across, latitude down; see :mod:`scanpipe.camera`).
CAMERA_MODELS = ("pinhole", "equirect")


class CameraConfig(Params):
    """One camera on the platform: source, model, image size, rate, intrinsics and pose.

    ``model = "equirect"`` is a 360° camera's stitched equirectangular image: the whole sphere,
    width = 2 × height; ``fx``, ``fy``, ``cx``, ``cy`` are not used and ``distortion`` must be 0.
    """

    id: str = Field("cam0", pattern=r"^[A-Za-z0-9_-]+$")
    source: str = Field("0", min_length=1)
    model: Literal["pinhole", "equirect"] = "pinhole"
    width: int = Field(1920, ge=16, le=16384)
    height: int = Field(1080, ge=16, le=16384)
    fps: float = Field(30.0, gt=0, le=1000)
    fx: float = Field(1507.0, ge=1, le=1_000_000)
    fy: float = Field(1507.0, ge=1, le=1_000_000)
    cx: float = Field(959.5, ge=-16384, le=32768)
    cy: float = Field(539.5, ge=-16384, le=32768)
    distortion: tuple[Coefficient, Coefficient, Coefficient, Coefficient, Coefficient] = (
        0.0, 0.0, 0.0, 0.0, 0.0)
    pose: Pose = Pose()

    @model_validator(mode="after")
    def _pinhole_possible(self, info: ValidationInfo) -> CameraConfig:
        problems = []
        if self.model == "equirect":
            if abs(self.width - 2 * self.height) > 1:
                problems.append(f"an equirect image spans 360° × 180°: width must be twice the "
                                f"height; found {self.width} × {self.height}")
            if any(self.distortion):
                problems.append("distortion must be [0, 0, 0, 0, 0] for an equirect camera "
                                "(its image is already stitched and undistorted)")
            if problems:
                raise ValueError("; ".join(problems))
            return self
        for axis, size, focal in (("x", self.width, self.fx), ("y", self.height, self.fy)):
            fov_deg = math.degrees(2 * math.atan(size / (2 * focal)))
            if not MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG:
                problems.append(
                    f"f{axis} = {focal:g} px over {size} px gives a {fov_deg:.3g}° field of view; "
                    f"allowed: {MIN_FOV_DEG:g}° to {MAX_FOV_DEG:g}° (a pinhole lens)")
        recorded = bool(info.context and info.context.get("recorded"))
        for axis, size, centre in (("x", self.width, self.cx), ("y", self.height, self.cy)):
            problem = principal_point_problem(axis, centre, size, plausible=False)
            if problem and not recorded:
                problems.append(problem)
        if problems:
            raise ValueError("; ".join(problems))
        return self

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view (360 for an equirect camera)."""
        if self.model == "equirect":
            return 360.0
        return math.degrees(2 * math.atan(self.width / (2 * self.fx)))

    @property
    def px_per_rad(self) -> float:
        """Angular resolution at the image centre, pixels per radian."""
        if self.model == "equirect":
            return self.width / (2 * math.pi)
        return math.sqrt(self.fx * self.fy)


class Rig(Params):
    """The whole rig description, one TOML file."""

    format_version: int = RIG_FORMAT_VERSION
    name: str = "paper-lab"
    scanner: ScannerConfig = ScannerConfig()
    motor: MotorConfig = MotorConfig()
    cameras: tuple[CameraConfig, ...] = ()

    @field_validator("format_version")
    @classmethod
    def _known_version(cls, value: int) -> int:
        if value != RIG_FORMAT_VERSION:
            raise ValueError(f"unsupported rig format version; allowed: {RIG_FORMAT_VERSION}")
        return value

    @model_validator(mode="after")
    def _unique_camera_ids(self) -> Rig:
        ids = [c.id for c in self.cameras]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"camera ids must be unique; repeated: {', '.join(duplicates)}")
        return self

    def camera(self, camera_id: str) -> CameraConfig:
        """The camera with ``camera_id``; :class:`RigError` naming the known ids otherwise."""
        for cam in self.cameras:
            if cam.id == camera_id:
                return cam
        known = ", ".join(c.id for c in self.cameras) or "none"
        raise RigError([f"no camera {camera_id!r} (cameras: {known})"], "rig")


def camera_warnings(rig: Rig) -> list[str]:
    """Valid but unlikely camera values, one line each: a principal point outside the image's
    middle half (an offset from the centre typed as a position, or a crop of the sensor)."""
    warnings = []
    for cam in rig.cameras:
        if cam.model != "pinhole":
            continue
        for axis, size, centre in (("x", cam.width, cam.cx), ("y", cam.height, cam.cy)):
            problem = principal_point_problem(axis, centre, size, plausible=True)
            if problem:
                warnings.append(f"camera {cam.id}: {problem} (right only for a crop of the "
                                "sensor, such as a ROS ROI)")
    return warnings


def default_cameras() -> tuple[CameraConfig, ...]:
    """Two Full-HD phones above the scanner, upright (portrait), facing opposite ways, and a
    360° camera (4K equirect video) on a short pole above them.

    Upright, the 65° side of the field of view is vertical, so the sweep of the platform sees
    from well down the walls to well up them; the 39° side only sets how much each frame shows
    of the sweep. Facing opposite ways, 180° of travel shows the whole horizon. The phones
    (26 px/°) texture that band; the 360° camera (10.7 px/°) the floor around the rig and the
    ceiling, which no level pinhole sees (docs/texture.md, "Cameras").
    """
    upright = {"width": 1080, "height": 1920, "cx": 539.5, "cy": 959.5}
    return (
        CameraConfig(id="cam0", pose=Pose(translation_m=(0.0, 0.25, 0.0)), **upright),
        CameraConfig(
            id="cam1", source="1", **upright,
            pose=Pose(translation_m=(0.0, 0.25, 0.0), rotation_deg=(0.0, 180.0, 0.0)),
        ),
        # fx … cy are unused by an equirect camera; these are its natural values, for readers
        CameraConfig(id="cam360", source="2", model="equirect", width=3840, height=1920,
                     fx=611.2, fy=611.2, cx=1919.5, cy=959.5,
                     pose=Pose(translation_m=(0.0, 0.40, 0.0))),
    )


def default_rig(scanner_model: str | None = None) -> Rig:
    """The paper's rig (LD-OEM 1000 at 0.25°, PK566 with 20:1, 5000 pulses) with two cameras;
    with ``scanner_model``, that model's scanner (:mod:`scanpipe.scanner_models`) on it."""
    if scanner_model is None:
        return Rig(cameras=default_cameras())
    return Rig(cameras=default_cameras(), scanner=scanner_for_model(scanner_model))


def scanner_for_model(name: str, mount: Pose | None = None) -> ScannerConfig:
    """The scanner section for a model in its default mode (:class:`RigError` if unknown)."""
    try:
        model = get_model(name)
    except KeyError as err:
        raise RigError([str(err.args[0])], "--scanner") from None
    values = model.rig_values()
    if mount is not None:
        values["mount"] = mount
    return ScannerConfig.model_validate(values)


#: Validation context of a rig stored in a recording: it holds what was accepted when the
#: recording was made, so checks added since then (a principal point within the image) do not
#: make an existing recording unreadable; `rig check` and new rig files still apply them.
RECORDED = {"recorded": True}


def rig_from_dict(data: dict[str, Any], source: str = "rig",
                  context: dict[str, Any] | None = None) -> Rig:
    """Validate a rig from plain data, reporting every problem (device limits too) at once;
    ``context`` :data:`RECORDED` for a rig stored in a recording."""

    problems: list[str] = []
    rig: Rig | None = None
    try:
        rig = validate(Rig, data, source, context=context)
    except ParameterError as err:
        problems.extend(err.problems)
    scanner_data = data.get("scanner", {}) if isinstance(data, dict) else {}
    if isinstance(scanner_data, dict):  # unknown keys are reported above; check limits anyway
        scanner_data = {k: v for k, v in scanner_data.items()
                        if k in ScannerConfig.model_fields or k in SCANNER_KEY_RENAMES}
    try:
        scanner = rig.scanner if rig else validate(ScannerConfig, scanner_data, source)
    except ParameterError:
        scanner = None  # its problems are already in the list above
    if scanner is not None:
        problems.extend(limit_problems(scanner))
    if problems or rig is None:
        raise RigError(problems, source)
    return rig


def rig_from_toml(text: str, source: str = "rig", empty_hint: str = "",
                  context: dict[str, Any] | None = None) -> Rig:
    """Parse and validate a rig TOML text; an empty one (no keys at all) is an error too.

    An empty rig file would silently be the built-in rig without cameras, which is never what
    was meant; ``empty_hint`` says what to do instead.
    """
    try:
        data = parse_toml(text, source)
    except ParameterError as err:
        raise RigError(err.problems, err.source) from None
    if not data:
        raise RigError(["the rig is empty (no keys in it)" + (f"; {empty_hint}" if empty_hint
                                                                else "")], source)
    return rig_from_dict(data, source, context)


def load_rig(path: Path | str | None) -> Rig:
    """Load and validate a rig TOML file; ``None`` gives the default rig."""
    if path is None:
        return default_rig()
    path = Path(path)
    try:
        data = load_toml(path)
    except ParameterError as err:
        raise RigError(err.problems, err.source) from None
    if not data:
        raise RigError([f"the file is empty (no keys in it); write the default rig with "
                        f"`scanpipe rig init --force {path}` and edit it"], str(path))
    return rig_from_dict(data, str(path))


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    """Plain data of a rig, in TOML-friendly types."""
    return rig.model_dump(mode="json")


_COMMENTS = {
    "format_version": "scanpipe rig description; see docs/rig.md for every key",
    "scanner": "The 2-D laser scanner. model: see docs/rig.md (ldoem1000, lms111, tim571, …); "
               "dialect: its wire format; transport: tcp (host, port) or serial (serial_url, "
               "baudrate)",
    "scanner.beam_step_deg": "beam step (between samples); LD-OEM: a multiple of 0.125",
    "scanner.scan_hz": "head rotation rate; LD-OEM: 5–20 Hz in whole Hz",
    "scanner.alpha_offset_deg": "calibration: zero offset added to every beam angle",
    "scanner.mount": "calibration: scan frame → platform frame (offset from the motor axis, tilt)",
    "motor": "Stepper + gearbox + pulse-counting controller",
    "motor.unlimited_travel": "true only for a platform that may turn without limit (slip ring)",
    "motor.pulse_limit": "travel from home in pulses, never passed (5000 × 0.036° = 180°)",
    "motor.serial_url": "pyserial URL of the controller (a device, a pty, or loop://)",
    "motor.beta_offset_deg": "calibration: zero offset added to every platform angle",
    "cameras": "A camera on the platform: model pinhole (OpenCV intrinsics, distortion k1 k2 p1 "
               "p2 k3) or equirect (a 360° camera: width = 2 × height, intrinsics unused), pose",
}


def rig_to_toml(rig: Rig) -> str:
    """The rig as a commented TOML document that :func:`load_rig` reads back unchanged."""
    return to_toml(rig_to_dict(rig), _COMMENTS)


def rig_table(rig: Rig) -> Any:
    """The ``rig`` artifact: one row, column ``toml``, so later stages carry the calibration."""
    import pyarrow as pa

    return pa.table({"toml": pa.array([rig_to_toml(rig)], pa.string())})


def rig_from_table(table: Any, source: str = "rig artifact") -> Rig:
    """The rig stored in a ``rig`` artifact (see :func:`rig_table`), validated like a rig file.

    An artifact written by an older scanpipe, or by hand, may hold values a rig file may not
    (NaN calibration): those are refused here, before any stage computes with them.
    """
    try:
        text = table.column("toml")[0].as_py()
    except (KeyError, IndexError) as err:
        raise RigError([f"not a rig artifact ({err})"], source) from None
    if not isinstance(text, str):
        raise RigError([f"not a rig artifact (toml is {text!r})"], source)
    hint = "run decode again or pass a corrected rig file with --rig"
    try:
        return rig_from_toml(text, source, hint)
    except RigError as err:
        if err.problems and hint in err.problems[-1]:
            raise
        raise RigError([*err.problems[:-1], f"{err.problems[-1]}; {hint}"], source) from None
