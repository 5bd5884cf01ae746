"""Camera calibration from chessboard images (OpenCV), written into the rig file.

The intrinsics (fx, fy, cx, cy) and the distortion (k1, k2, p1, p2, k3) come from
``cv2.calibrateCamera`` on the inner corners of a chessboard seen in several images. The
camera's pose on the platform is not calibrated here: it stays as the rig file says.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.errors import ParameterError, RigError, StageError, UsageError
from scanpipe.images import MAX_FRAME_PX, read_image_file
from scanpipe.params import load_toml
from scanpipe.rig import Rig, rig_from_dict, rig_to_toml

F64 = NDArray[np.float64]
#: Fewer views than this cannot separate focal length, principal point and distortion.
MIN_VIEWS = 3


@dataclass
class Calibration:
    """What calibration found: intrinsics, distortion and the RMS reprojection error (px)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]
    rms_px: float
    used: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        """Plain data for ``--json``."""
        return {
            "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
            "cx": self.cx, "cy": self.cy, "distortion": list(self.distortion),
            "reprojection_error_px": self.rms_px, "images_used": self.used,
            "images_without_board": self.rejected,
        }


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` → (9, 6): inner corners per row and per column."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not match or min(int(match[1]), int(match[2])) < 2:
        raise UsageError(f"--board {text!r}: expected inner corners as COLSxROWS, e.g. 9x6 "
                         "(each at least 2)")
    return int(match[1]), int(match[2])


def board_points(board: tuple[int, int], square_m: float) -> NDArray[np.float32]:
    """The inner corners in the board's own plane (z = 0), row by row, in metres."""
    cols, rows = board
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    return np.concatenate([grid, np.zeros((len(grid), 1))], axis=1).astype(np.float32)


def find_corners(grey: NDArray[np.uint8], board: tuple[int, int]) -> NDArray[np.float32] | None:
    """The board's inner corners in a grey image to sub-pixel accuracy, or None."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, board, flags=flags)
    if found:
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
        return np.asarray(corners, dtype=np.float32)
    found, corners = cv2.findChessboardCornersSB(grey, board, flags=cv2.CALIB_CB_ACCURACY)
    return np.asarray(corners, dtype=np.float32) if found else None


def calibrate(images: Sequence[tuple[str, NDArray[np.uint8]]], board: tuple[int, int],
              square_m: float, fix_k3: bool = True) -> Calibration:
    """Calibrate from named images (grey or BGR) of a chessboard with ``board`` inner corners."""
    if square_m <= 0:
        raise UsageError(f"--square-m {square_m}: must be positive (metres)")
    sizes = {(img.shape[1], img.shape[0]) for _, img in images}
    if len(sizes) > 1:
        listed = ", ".join(f"{w}×{h}" for w, h in sorted(sizes))
        raise UsageError(f"calibration images differ in size ({listed}); use one camera mode")
    object_points, image_points, used, rejected = [], [], [], []
    reference = board_points(board, square_m)
    for name, image in images:
        grey = np.asarray(image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY),
                          dtype=np.uint8)
        corners = find_corners(grey, board)
        if corners is None:
            rejected.append(name)
            continue
        object_points.append(reference)
        image_points.append(corners)
        used.append(name)
    if len(used) < MIN_VIEWS:
        raise StageError(f"calibration: the {board[0]}x{board[1]} board was found in {len(used)} "
                         f"of {len(images)} images; at least {MIN_VIEWS} are needed "
                         f"(not found in: {', '.join(rejected) or 'none'})")
    width, height = next(iter(sizes))
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    try:
        rms, matrix, dist, _, _ = cv2.calibrateCamera(object_points, image_points,
                                                      (width, height), None, None, flags=flags)
    except cv2.error as err:
        raise StageError(f"calibration: OpenCV failed ({err.msg.strip()})") from err
    d = [float(v) for v in np.asarray(dist).ravel()[:5]] + [0.0] * 5
    return Calibration(
        width=width, height=height, fx=float(matrix[0, 0]), fy=float(matrix[1, 1]),
        cx=float(matrix[0, 2]), cy=float(matrix[1, 2]),
        distortion=(d[0], d[1], d[2], d[3], d[4]), rms_px=float(rms), used=used,
        rejected=rejected,
    )


#: EXIF's Orientation tag (0x0112): how a viewer should turn the stored pixels.
_EXIF_ORIENTATION = 0x0112


def exif_orientation(path: Path) -> int:
    """A JPEG's (or TIFF's) EXIF orientation, 1 (as stored) when it has none or is unreadable."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            value = image.getexif().get(_EXIF_ORIENTATION, 1)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):  # decode says
        return 1
    return int(value) if isinstance(value, int) and 1 <= value <= 8 else 1


def read_images(paths: Sequence[Path]) -> list[tuple[str, NDArray[np.uint8]]]:
    """Grey images from files, upright (a JPEG's EXIF orientation applied, as frames are taken:
    import-video applies a video's display rotation); :class:`UsageError` naming a file that is
    missing, unreadable or larger than :data:`~scanpipe.images.MAX_FRAME_PX` (checked from its
    header, before decoding: calibration images come from the camera that records the frames).

    Images whose EXIF orientations differ are refused: turned a half turn (3 against 1, or 8
    against 6) a photo keeps its size but the lens's centre and distortion land mirrored in the
    upright picture, and one fit over both averaged them without a word."""
    # each file's size is checked from its header (and it is decoded) before Pillow opens it
    images = [(str(path), read_image_file(path, MAX_FRAME_PX, cv2.IMREAD_GRAYSCALE, UsageError))
              for path in paths]
    groups: dict[int, list[str]] = {}
    for path in paths:
        groups.setdefault(exif_orientation(path), []).append(path.name)
    if len(groups) > 1:
        listed = "; ".join(f"{_ORIENTATIONS.get(k, k)}: {', '.join(v[:3])}"
                           f"{' …' if len(v) > 3 else ''}" for k, v in sorted(groups.items()))
        raise UsageError(
            f"calibration images were taken with the camera turned differently (EXIF "
            f"orientation {listed}): turned, the lens's centre and distortion land elsewhere "
            "in the upright picture; calibrate from images taken the one way the camera is "
            "held for the scan")
    return images


#: EXIF orientations by what they mean for the camera.
_ORIENTATIONS = {1: "1 (as stored)", 3: "3 (half turn)", 6: "6 (quarter turn)",
                 8: "8 (quarter turn the other way)"}


def apply_calibration(rig_path: Path, camera_id: str, calibration: Calibration) -> Rig:
    """Write the calibration into camera ``camera_id`` of the rig file, atomically.

    Everything else in the file is kept (its values; the file is rewritten in the standard
    layout with the standard comments). Returns the new rig.
    """
    try:
        data = load_toml(rig_path)
    except ParameterError as err:
        raise RigError(err.problems, err.source) from None
    rig_from_dict(data, str(rig_path))  # the file must be valid before we touch it
    cameras = data.get("cameras", [])
    matches = [c for c in cameras if isinstance(c, dict) and c.get("id", "cam0") == camera_id]
    if not matches:
        known = ", ".join(str(c.get("id", "cam0")) for c in cameras if isinstance(c, dict))
        raise RigError([f"no camera {camera_id!r} (cameras: {known or 'none'})"], str(rig_path))
    matches[0].update({
        "width": calibration.width, "height": calibration.height,
        "fx": calibration.fx, "fy": calibration.fy, "cx": calibration.cx, "cy": calibration.cy,
        "distortion": list(calibration.distortion),
    })
    rig = rig_from_dict(data, str(rig_path))
    atomic_write_bytes(rig_path, rig_to_toml(rig).encode())
    return rig
