"""Camera intrinsics written by other tools, converted to the rig's conventions.

The rig's camera (:class:`scanpipe.rig.CameraConfig`) is OpenCV's pinhole: ``fx fy cx cy`` in
pixels with the centre of the top-left pixel at (0, 0), and distortion ``k1 k2 p1 p2 k3``.
Four formats are read, and each differs from that in its own, silent way:

``opencv``
    OpenCV FileStorage YAML (``%YAML:1.0``, ``!!opencv-matrix``) or XML (``<opencv_storage>``),
    as OpenCV's calibration samples write it (``camera_matrix`` / ``Camera_Matrix``,
    ``distortion_coefficients``, ``image_width`` …). Same conventions as the rig; 8, 12 or 14
    coefficients (rational k4…k6, thin prism, tilt) only when the extra ones are 0; a
    ``fisheye_model`` file is refused.
``ros``
    A ROS camera_info YAML: camera_calibration_parsers' file (``camera_matrix``,
    ``distortion_coefficients``, ``distortion_model``) or a ``CameraInfo`` message as
    ``rostopic echo`` / ``ros2 topic echo`` prints it (``K``/``k``, ``D``/``d``). Pixel
    convention as OpenCV's; ``plumb_bob``, or ``rational_polynomial`` with k4…k6 = 0;
    ``equidistant`` (fisheye) is refused. The message's ROI and binning are applied.
``colmap``
    COLMAP's ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``) or ``cameras.bin``.
    COLMAP puts the centre of the top-left pixel at (0.5, 0.5): ``cx, cy`` are moved by
    −0.5 px. ``SIMPLE_PINHOLE``,
    ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV`` (k4…k6 = 0); the
    fisheye and other models are refused.
``metashape``
    Agisoft Metashape (PhotoScan) XML: a cameras export (``<document><chunk><sensors>``) or a
    camera calibration export (``<calibration>`` at the root). Its ``cx, cy`` are offsets from
    the image centre in a pixel-corner frame (``u = w/2 + cx + x'(f + b1) + y'b2``), so the
    rig's ``cx = w/2 + cx − 0.5``; its ``p1, p2`` are OpenCV's ``p2, p1``; ``fx = f + b1``,
    ``fy = f``. PhotoScan before 1.3 (and Agisoft Lens) wrote ``fx, fy``, an absolute ``cx, cy``
    (same pixel-corner origin) and ``skew``, with ``p1, p2`` in OpenCV's order. ``k4``, ``p3``,
    ``p4`` must be 0, and the skew (``b2``) small enough to drop (under 0.5 px at the image's
    edge); other sensor types (fisheye, spherical …) are refused.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scanpipe.errors import UsageError
from scanpipe.rig import CameraConfig

#: The formats :func:`read_intrinsics` reads (``auto`` detects one of them).
FORMATS = ("opencv", "ros", "colmap", "metashape")
#: Skew a Metashape ``b2`` may cause at the image's edge and still be dropped (the rig's camera
#: matrix has no skew term).
MAX_DROPPED_SKEW_PX = 0.5
#: The largest image side a file may give (pixels): far beyond any camera's.
MAX_IMAGE_SIDE_PX = 1 << 20
#: Two image sizes have "the same aspect ratio" when scaling one to the other moves the far
#: corner by less than this (rounding of an odd size when a camera bins or scales).
ASPECT_TOLERANCE_PX = 1.0


class IntrinsicsError(UsageError):
    """An intrinsics file that cannot be read or converted to the rig's camera model."""


@dataclass
class Intrinsics:
    """A camera's intrinsics in the rig's conventions, and how they were converted."""

    format: str
    camera: str
    width: int | None
    height: int | None
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]
    #: What the conversion did (a shifted principal point, swapped coefficients …).
    notes: list[str] = field(default_factory=list)


def _fail(path: Path, message: str) -> IntrinsicsError:
    return IntrinsicsError(f"{path}: {message}")


def detect_format(path: Path, text: str) -> str:
    """The format of an intrinsics file from its content (:class:`IntrinsicsError` if none)."""
    head = text.lstrip()[:4000]
    ros_keys = re.search(r"^(camera_matrix|K|k|distortion_model)\s*:", text, re.MULTILINE)
    if "<opencv_storage" in head or "!!opencv-matrix" in text or (
            head.startswith("%YAML") and not ros_keys):
        return "opencv"
    if head.startswith("<"):
        if re.search(r"<(document|calibration|sensors)\b", head):
            return "metashape"
    elif re.search(r"^\s*\d+\s+[A-Z_]+\s+\d+\s+\d+(\s+\S+)+\s*$", text, re.MULTILINE):
        return "colmap"
    elif ros_keys:
        return "ros"
    raise _fail(path, "not an intrinsics file this command knows (OpenCV YAML/XML, ROS "
                      "camera_info YAML, COLMAP cameras.txt, Metashape XML); give --format if "
                      "it is one of them")


def read_intrinsics(path: Path, fmt: str = "auto", file_camera: str | None = None
                    ) -> Intrinsics:
    """Read one camera's intrinsics from ``path`` and convert them to the rig's conventions.

    ``file_camera`` picks a camera in a file that holds several (a COLMAP ``CAMERA_ID``, a
    Metashape sensor id or label); a file with one camera needs none.
    """
    if fmt != "auto" and fmt not in FORMATS:
        raise IntrinsicsError(f"--format {fmt!r}: unknown; allowed: auto, {', '.join(FORMATS)}")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise IntrinsicsError(f"{path}: not found") from None
    except OSError as err:
        raise _fail(path, f"cannot be read ({err.strerror or err})") from None
    return _checked_size(path, _read_format(path, data, fmt, file_camera))


def _checked_size(path: Path, found: Intrinsics) -> Intrinsics:
    """``found``, refused when its image size is not a positive whole number of pixels (a
    calibration at another size is scaled by it)."""
    sizes = (found.width, found.height)
    if found.width is not None and found.height is not None and not all(
            isinstance(n, int) and 0 < n <= MAX_IMAGE_SIDE_PX for n in sizes):
        raise _fail(path, f"image size {found.width} × {found.height}: not a positive whole "
                          f"number of pixels (at most {MAX_IMAGE_SIDE_PX} a side)")
    return found


def _read_format(path: Path, data: bytes, fmt: str, file_camera: str | None) -> Intrinsics:
    """The intrinsics of ``data`` (the file's bytes) in ``fmt`` (or the one detected)."""
    if path.suffix.lower() == ".bin" and fmt in ("auto", "colmap"):
        return _choose_colmap(path, _colmap_binary(path, data), file_camera)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise _fail(path, "not a text file (COLMAP's binary cameras.bin is read from a file "
                          "whose name ends in .bin)") from None
    if fmt == "auto":
        fmt = detect_format(path, text)
    if fmt == "opencv":
        if file_camera is not None:
            raise IntrinsicsError("--file-camera: an OpenCV file holds one camera; leave it out")
        return _read_opencv(path)
    if fmt == "ros":
        if file_camera is not None:
            raise IntrinsicsError("--file-camera: a ROS camera_info file holds one camera; "
                                  "leave it out")
        return _read_ros(path, text)
    if fmt == "colmap":
        return _read_colmap(path, text, file_camera)
    return _read_metashape(path, text, file_camera)


def _pinhole_distortion(path: Path, coefficients: Sequence[float], what: str
                        ) -> tuple[float, float, float, float, float]:
    """OpenCV's k1 k2 p1 p2 k3 of a coefficient list; refused when k4… are not 0."""
    values = [float(c) for c in coefficients]
    if not all(math.isfinite(v) for v in values):
        raise _fail(path, f"{what} has a non-finite value: {values}")
    if len(values) not in (0, 4, 5, 8, 12, 14):
        raise _fail(path, f"{what} has {len(values)} values; OpenCV's distortion has 4, 5, "
                          "8, 12 or 14")
    extra = values[5:]
    if any(extra):
        raise _fail(path, f"{what} uses coefficients beyond k1 k2 p1 p2 k3 (k4… = "
                          f"{[round(v, 9) for v in extra]}); the rig's cameras are OpenCV's "
                          "5-coefficient pinhole: recalibrate with k4…k6 fixed at 0 "
                          "(scanpipe calibrate-camera)")
    k1, k2, p1, p2, k3 = (values + [0.0] * 5)[:5]
    return k1, k2, p1, p2, k3


# --- OpenCV FileStorage ---------------------------------------------------------------------


def _norm(key: str) -> str:
    return key.replace("_", "").lower()


def _read_opencv(path: Path) -> Intrinsics:
    import cv2
    import numpy as np

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:
        detail = str(err.__cause__ or err).strip().splitlines()[-1][:200]
        raise _fail(path, f"not an OpenCV FileStorage file ({detail})") from err
    try:
        if not storage.isOpened():
            raise _fail(path, "cannot be opened as an OpenCV FileStorage file")
        root = storage.root()
        keys = {_norm(k): k for k in root.keys()}  # noqa: SIM118 (a cv2.FileNode, not a dict)

        def node(*names: str) -> Any:
            for name in names:
                if name in keys:
                    return storage.getNode(keys[name])
            return None

        matrix_node = node("cameramatrix", "k", "intrinsicmatrix", "intrinsics", "mtx")
        if matrix_node is None or matrix_node.empty():
            raise _fail(path, f"no camera matrix (looked for camera_matrix, Camera_Matrix, K; "
                              f"the file has {', '.join(root.keys()) or 'no keys'})")
        matrix = _opencv_mat(path, matrix_node, "camera_matrix")
        if matrix is None or np.asarray(matrix).shape != (3, 3):
            raise _fail(path, "the camera matrix is not a 3×3 !!opencv-matrix")
        k = np.asarray(matrix, dtype=np.float64)
        fisheye = node("fisheyemodel")
        if fisheye is not None and fisheye.real() != 0:
            raise _fail(path, "fisheye_model is set: OpenCV's fisheye (equidistant) lens model "
                              "cannot be described by the rig's pinhole k1 k2 p1 p2 k3; "
                              "recalibrate without the fisheye model")
        dist_node = node("distortioncoefficients", "distcoeffs", "distortion", "d", "dist")
        coefficients: list[float] = []
        if dist_node is not None and not dist_node.empty():
            dist = _opencv_mat(path, dist_node, "distortion_coefficients")
            coefficients = [] if dist is None else [float(v) for v in np.ravel(dist)]
        size = _opencv_size(path, node)
    finally:
        storage.release()
    _check_camera_matrix(path, [float(v) for v in k.ravel()])
    distortion = _pinhole_distortion(path, coefficients, "distortion_coefficients")
    width, height = size if size is not None else (None, None)
    notes = ["OpenCV: same pixel convention and coefficients as the rig"]
    if not coefficients:
        notes.append("the file gives no distortion coefficients: taken as 0 (an ideal lens)")
    return Intrinsics("opencv", "", width, height, float(k[0, 0]), float(k[1, 1]),
                      float(k[0, 2]), float(k[1, 2]), distortion, notes)


def _check_camera_matrix(path: Path, k: Sequence[float]) -> None:
    """Refuse a 3×3 camera matrix (row by row) that is not ``[[fx 0 cx] [0 fy cy] [0 0 1]]``:
    a skew the rig cannot hold, or a matrix scaled or transposed."""
    if abs(k[1]) > 1e-9 * max(abs(k[0]), 1.0):
        raise _fail(path, f"the camera matrix has a skew of {k[1]:g} px; the rig's camera "
                          "matrix has none: recalibrate with zero skew")
    if k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
        raise _fail(path, f"the camera matrix {list(k)} is not [fx 0 cx; 0 fy cy; 0 0 1] "
                          "(transposed, or scaled?)")


def _opencv_mat(path: Path, node: Any, name: str) -> Any:
    """A FileStorage node's matrix; a matrix whose data does not fill its rows × cols (which
    OpenCV's read asserts on) refused in one line."""
    import cv2

    try:
        return node.mat()
    except cv2.error as err:
        detail = (str(err).strip().splitlines() or [""])[-1][:200]
        raise _fail(path, f"{name} cannot be read as a matrix (its data does not fill its "
                          f"rows × cols? {detail})") from err


def _opencv_number(path: Path, node: Any, name: str) -> int:
    """A size node's whole number (a non-number refused: ``real()`` reads it as nonsense)."""
    if not (node.isInt() or node.isReal()):
        raise _fail(path, f"{name} is not a number")
    value = float(node.real())
    if not (math.isfinite(value) and value.is_integer()):
        raise _fail(path, f"{name} = {value:g} is not a whole number of pixels")
    return int(value)


def _opencv_size(path: Path, node: Any) -> tuple[int, int] | None:
    width, height = node("imagewidth"), node("imageheight")
    if width is not None and height is not None and not width.empty() and not height.empty():
        return (_opencv_number(path, width, "image_width"),
                _opencv_number(path, height, "image_height"))
    size = node("imagesize")
    if size is not None and size.isSeq() and size.size() == 2:
        return (_opencv_number(path, size.at(0), "image_size"),
                _opencv_number(path, size.at(1), "image_size"))
    return None


# --- ROS camera_info ------------------------------------------------------------------------


def _ros_list(data: dict[str, Any], *names: str) -> list[float] | None:
    for name in names:
        if name in data:
            value = data[name]
            if isinstance(value, dict):
                value = value.get("data")
            if value is None:
                return []
            if not isinstance(value, list):
                raise IntrinsicsError(f"{name} is {value!r}, not a list of numbers")
            return [float(v) for v in value]
    return None


def _whole(value: Any) -> int | None:
    """A size written as a whole number (640 or 640.0); None otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return int(value) if float(value).is_integer() else None


def ros_roi_binning(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                    roi: tuple[int, ...], binning: tuple[int, int], notes: list[str] | None = None
                    ) -> tuple[int, int, float, float, float, float]:
    """A CameraInfo's size and intrinsics for the images it describes, as ROS's image_geometry
    applies them: the ROI ``(x_offset, y_offset, width, height)`` in full-resolution pixels
    first (a zero width means none), then the binning (0 or 1: none). ``notes`` gets a line
    for each one applied."""
    x_offset, y_offset, roi_width, roi_height = roi
    if roi_width > 0 and roi_height > 0:
        cx, cy = cx - x_offset, cy - y_offset
        width, height = roi_width, roi_height
        if notes is not None:
            notes.append(f"the ROI's offset ({x_offset}, {y_offset}) subtracted")
    bx, by = max(binning[0], 1), max(binning[1], 1)
    if (bx, by) != (1, 1):
        fx, fy = fx / bx, fy / by
        cx, cy = (cx + 0.5) / bx - 0.5, (cy + 0.5) / by - 0.5
        width, height = width // bx, height // by
        if notes is not None:
            notes.append(f"binning {bx}×{by} applied")
    return width, height, fx, fy, cx, cy


def _read_ros(path: Path, text: str) -> Intrinsics:
    import yaml  # type: ignore[import-untyped]

    # OpenCV-style "%YAML:1.0" (no space) is not a YAML 1.1 directive PyYAML accepts
    text = re.sub(r"\A\s*%YAML:\S*[^\n]*\n", "", text)
    try:
        documents = [d for d in yaml.safe_load_all(text) if d is not None]
    except yaml.YAMLError as err:
        raise _fail(path, f"not valid YAML ({str(err).splitlines()[0]})") from err
    if len(documents) != 1 or not isinstance(documents[0], dict):
        raise _fail(path, f"expected one camera_info mapping, found {len(documents)} YAML "
                          "documents")
    data: dict[str, Any] = documents[0]
    try:
        k = _ros_list(data, "camera_matrix", "K", "k")
        d = _ros_list(data, "distortion_coefficients", "D", "d") or []
    except (IntrinsicsError, TypeError, ValueError) as err:
        raise _fail(path, f"camera_info: {err}") from None
    if k is None or len(k) != 9:
        raise _fail(path, "no 3×3 camera_matrix (or K) with 9 numbers")
    if not k[0] > 0 or not k[4] > 0:
        raise _fail(path, f"the camera matrix holds no calibration (fx = {k[0]:g}, "
                          f"fy = {k[4]:g}: an uncalibrated camera publishes K = 0)")
    _check_camera_matrix(path, k)
    model = str(data.get("distortion_model", "") or "").strip().lower()
    if model == "equidistant" or (model not in ("plumb_bob", "rational_polynomial", "")
                                  and any(d)):
        raise _fail(path, f"distortion_model {model!r} cannot be described by the rig's "
                          "pinhole k1 k2 p1 p2 k3 (OpenCV's plumb_bob); recalibrate with "
                          "plumb_bob, or use the rectified images with P")
    distortion = _pinhole_distortion(path, d, f"distortion ({model or 'no model'})")
    width = _whole(data.get("image_width", data.get("width")))
    height = _whole(data.get("image_height", data.get("height")))
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    notes = ["ROS: same pixel convention and coefficients as the rig"]
    if width is not None and height is not None and width > 0 and height > 0:
        found_roi = data.get("roi")
        roi: dict[str, Any] = found_roi if isinstance(found_roi, dict) else {}
        binning = (int(data.get("binning_x", 0) or 0), int(data.get("binning_y", 0) or 0))
        roi_box = tuple(int(roi.get(key, 0) or 0)
                        for key in ("x_offset", "y_offset", "width", "height"))
        width, height, fx, fy, cx, cy = ros_roi_binning(
            width, height, fx, fy, cx, cy, roi_box, binning, notes)
        size: tuple[int | None, int | None] = (width, height)
    else:
        size = (None, None)
    name = str(data.get("camera_name", "") or "")
    return Intrinsics("ros", name, size[0], size[1], fx, fy, cx, cy, distortion, notes)


# --- COLMAP cameras.txt ---------------------------------------------------------------------

#: COLMAP's models the rig's pinhole can hold: parameter names in COLMAP's order.
COLMAP_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


#: COLMAP's model ids in cameras.bin (its camera_models.h), with their parameter counts.
COLMAP_MODEL_IDS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}

ColmapCameras = dict[str, tuple[str, int, int, list[str]]]


def _colmap_binary(path: Path, data: bytes) -> ColmapCameras:
    """cameras.bin as COLMAP writes it (little-endian): uint64 count, then per camera uint32
    id, int32 model id, uint64 width, uint64 height, float64 parameters."""
    import struct

    cameras: ColmapCameras = {}
    try:
        (count,), offset = struct.unpack_from("<Q", data, 0), 8
        for _ in range(count):
            camera_id, model_id, width, height = struct.unpack_from("<IiQQ", data, offset)
            offset += 24
            if model_id not in COLMAP_MODEL_IDS:
                raise _fail(path, f"camera {camera_id}: unknown COLMAP model id {model_id}; "
                                  "known: " + ", ".join(f"{i} {n}" for i, (n, _)
                                                        in COLMAP_MODEL_IDS.items()))
            model, n = COLMAP_MODEL_IDS[model_id]
            params = struct.unpack_from(f"<{n}d", data, offset)
            offset += 8 * n
            cameras[str(camera_id)] = (model, width, height, [repr(v) for v in params])
    except struct.error:
        raise _fail(path, f"not a COLMAP cameras.bin (ends inside a camera record after "
                          f"{len(cameras)} cameras)") from None
    if offset != len(data):
        raise _fail(path, f"not a COLMAP cameras.bin ({len(data) - offset} bytes after its "
                          f"{len(cameras)} cameras)")
    return cameras


def _read_colmap(path: Path, text: str, file_camera: str | None) -> Intrinsics:
    cameras: ColmapCameras = {}
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < 5 or not fields[0].isdigit():
            raise _fail(path, f"line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT "
                              f"PARAMS[], found {line.strip()[:80]!r}")
        try:
            cameras[fields[0]] = (fields[1], int(fields[2]), int(fields[3]), fields[4:])
        except ValueError:
            raise _fail(path, f"line {number}: WIDTH and HEIGHT must be whole numbers, "
                              f"found {fields[2]!r} {fields[3]!r}") from None
    if not cameras:
        raise _fail(path, "no camera line (CAMERA_ID MODEL WIDTH HEIGHT PARAMS[])")
    return _choose_colmap(path, cameras, file_camera)


def _choose_colmap(path: Path, cameras: ColmapCameras, file_camera: str | None) -> Intrinsics:
    """The camera ``file_camera`` (or the only one) of a COLMAP model, converted."""
    if not cameras:
        raise _fail(path, "holds no camera")
    camera_id = _pick(path, sorted(cameras, key=int), file_camera, "CAMERA_ID")
    model, width, height, raw = cameras[camera_id]
    names = COLMAP_MODELS.get(model)
    if names is None:
        raise _fail(path, f"camera {camera_id}: COLMAP model {model} cannot be described by "
                          f"the rig's pinhole k1 k2 p1 p2 k3; allowed: "
                          f"{', '.join(COLMAP_MODELS)} (re-run COLMAP with one of them)")
    if len(raw) != len(names):
        raise _fail(path, f"camera {camera_id}: {model} has {len(names)} parameters "
                          f"({' '.join(names)}), found {len(raw)}")
    try:
        values = dict(zip(names, (float(v) for v in raw), strict=True))
    except ValueError:
        raise _fail(path, f"camera {camera_id}: a parameter is not a number: "
                          f"{' '.join(raw)}") from None
    fx = values.get("fx", values.get("f", 0.0))
    fy = values.get("fy", values.get("f", 0.0))
    coefficients = [values.get(n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3", "k4", "k5",
                                                  "k6")]
    distortion = _pinhole_distortion(path, coefficients, f"camera {camera_id} ({model})")
    return Intrinsics("colmap", camera_id, width, height, fx, fy, values["cx"] - 0.5,
                      values["cy"] - 0.5, distortion,
                      ["COLMAP: principal point moved by −0.5 px (COLMAP's top-left pixel "
                       "centre is at (0.5, 0.5), the rig's at (0, 0))"])


def _pick(path: Path, ids: Sequence[str], wanted: str | None, what: str,
          labels: dict[str, str] | None = None) -> str:
    """The camera ``wanted`` names (an id or a label), or the file's only camera."""
    labels = labels or {}
    listed = ", ".join(f"{i} ({labels[i]})" if labels.get(i) else i for i in ids)
    if wanted is None:
        if len(ids) == 1:
            return ids[0]
        raise IntrinsicsError(f"{path}: holds {len(ids)} cameras ({what} {listed}); choose "
                              "one with --file-camera")
    if wanted in ids:
        return wanted
    by_label = [i for i in ids if labels.get(i) == wanted]
    if len(by_label) == 1:
        return by_label[0]
    raise IntrinsicsError(f"--file-camera {wanted!r}: not in {path}; its cameras: {listed}")


# --- Agisoft Metashape XML ------------------------------------------------------------------


def _xml_float(element: ET.Element, name: str) -> float:
    child = element.find(name)
    if child is None or child.text is None or not child.text.strip():
        return 0.0
    return float(child.text)


def _xml_size(path: Path, width: str | None, height: str | None
              ) -> tuple[int | None, int | None]:
    """An image size from XML text (None where absent or 0)."""

    def side(text: str | None) -> int | None:
        if not text:
            return None
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value.is_integer()):
            raise _fail(path, f"image size {width!r} × {height!r} is not a whole number of "
                              "pixels")
        return int(value) or None

    return side(width), side(height)


def _read_metashape(path: Path, text: str, file_camera: str | None) -> Intrinsics:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise _fail(path, f"not valid XML ({err})") from None
    if root.tag == "calibration":  # Tools → Camera Calibration → export (Agisoft calibration)
        if file_camera is not None:
            raise IntrinsicsError("--file-camera: a Metashape calibration file holds one "
                                  "camera; leave it out")
        kind = (root.findtext("projection") or "frame").strip()
        width, height = _xml_size(path, root.findtext("width"), root.findtext("height"))
        return _metashape_calibration(path, root, kind, "", width, height)
    sensors = root.findall(".//sensors/sensor")
    calibrated = {s.get("id", str(n)): s for n, s in enumerate(sensors)
                  if s.find("calibration") is not None}
    if not calibrated:
        raise _fail(path, f"no <sensor> with a <calibration> ({len(sensors)} sensors, none "
                          "calibrated: align the photos in Metashape before exporting cameras)")
    labels = {i: s.get("label", "") for i, s in calibrated.items()}
    bare = [s.get("id", str(n)) for n, s in enumerate(sensors) if s.find("calibration") is None]
    if file_camera is not None and file_camera in bare:
        raise IntrinsicsError(f"--file-camera {file_camera}: sensor {file_camera} of {path} has "
                              f"no <calibration>; calibrated: {', '.join(calibrated)}")
    sensor_id = _pick(path, list(calibrated), file_camera, "sensor", labels)
    sensor = calibrated[sensor_id]
    calibrations = sensor.findall("calibration")
    chosen = next((c for c in calibrations if c.get("class") == "adjusted"), calibrations[0])
    resolution = chosen.find("resolution")
    if resolution is None:
        resolution = sensor.find("resolution")
    width = height = None
    if resolution is not None:
        width, height = _xml_size(path, resolution.get("width"), resolution.get("height"))
    kind = chosen.get("type", sensor.get("type", "frame"))
    return _metashape_calibration(path, chosen, kind, sensor_id, width, height)


def _metashape_calibration(path: Path, element: ET.Element, kind: str, sensor_id: str,
                           width: int | None, height: int | None) -> Intrinsics:
    where = f"sensor {sensor_id}" if sensor_id else "calibration"
    if kind != "frame":
        raise _fail(path, f"{where}: a {kind!r} camera; the rig's pinhole holds Metashape's "
                          "'frame' cameras only")
    if width is None or height is None:
        raise _fail(path, f"{where}: no image size (<resolution width height> or "
                          "<width>/<height>); Metashape's cx, cy are offsets from the image "
                          "centre and mean nothing without it")
    # PhotoScan before 1.3 and Agisoft Lens wrote fx, fy, an absolute cx, cy and skew, with
    # p1, p2 in OpenCV's order (Agisoft: F = fy, B1 = fx − fy, B2 = skew)
    legacy = element.find("f") is None and element.find("fx") is not None
    names = ("fx", "fy", "cx", "cy", "skew") if legacy else ("f", "f", "cx", "cy", "b2")
    try:
        fx, fy, cx, cy, skew = (_xml_float(element, n) for n in names)
        if not legacy:
            fx += _xml_float(element, "b1")
        k1, k2, k3, k4 = (_xml_float(element, n) for n in ("k1", "k2", "k3", "k4"))
        p1, p2, p3, p4 = (_xml_float(element, n) for n in ("p1", "p2", "p3", "p4"))
    except ValueError as err:
        raise _fail(path, f"{where}: a value is not a number ({err})") from None
    if not (fx > 0 and fy > 0):
        raise _fail(path, f"{where}: no focal length (<f>, or <fx> and <fy>)")
    unsupported = {n: v for n, v in (("k4", k4), ("p3", p3), ("p4", p4)) if v}
    if unsupported:
        shown = ", ".join(f"{n} = {v:g}" for n, v in unsupported.items())
        raise _fail(path, f"{where}: {shown}; the rig's pinhole has k1 k2 p1 p2 k3 only: "
                          "re-optimise in Metashape with k4, p3, p4 fixed at 0")
    skew_name = "skew" if legacy else "skew b2"
    edge_skew_px = abs(skew) * (height / 2) / fy
    if edge_skew_px > MAX_DROPPED_SKEW_PX:
        raise _fail(path, f"{where}: {skew_name} = {skew:g} px shifts the image's edge by "
                          f"{edge_skew_px:.2g} px; the rig's camera matrix has no skew "
                          f"(at most {MAX_DROPPED_SKEW_PX:g} px is dropped): re-optimise "
                          "in Metashape with it fixed at 0")
    if legacy:
        notes = ["PhotoScan (before 1.3): cx, cy − 0.5 px (pixel-corner origin → the rig's "
                 "pixel-centre origin); p1, p2 already in OpenCV's order"]
        distortion = (k1, k2, p1, p2, k3)
    else:
        notes = [f"Metashape: cx, cy are offsets from the image centre: cx = {width}/2 "
                 f"{cx:+g} − 0.5, cy = {height}/2 {cy:+g} − 0.5 (pixel-corner origin → the "
                 "rig's pixel-centre origin)",
                 "Metashape: p1, p2 swapped into OpenCV's order"]
        if fx != fy:
            notes.append(f"Metashape: fx = f + b1 = {fx:g}")
        cx, cy = width / 2 + cx, height / 2 + cy
        distortion = (k1, k2, p2, p1, k3)
    if skew:
        notes.append(f"{skew_name} = {skew:g} dropped ({edge_skew_px:.2g} px at the edge)")
    return Intrinsics("metashape", sensor_id, width, height, fx, fy, cx - 0.5, cy - 0.5,
                      distortion, notes)


# --- fitting to the rig's camera ------------------------------------------------------------


def fit_to_camera(found: Intrinsics, cam: CameraConfig, path: Path
                  ) -> tuple[dict[str, Any], list[str]]:
    """The rig camera's new ``fx fy cx cy distortion`` (a dict to update it with) and warnings.

    A calibration at another resolution of the same aspect ratio is scaled to the camera's
    (pixel centres kept: ``c' = (c + 0.5)·s − 0.5``), with a warning; another aspect ratio is
    refused. A file without an image size is taken to be at the camera's, with a warning.
    """
    if cam.model != "pinhole":
        raise IntrinsicsError(f"camera {cam.id} is an {cam.model} camera (a 360° image: its "
                              "intrinsics are not used); import pinhole intrinsics into a "
                              "pinhole camera")
    warnings: list[str] = []
    fx, fy, cx, cy = found.fx, found.fy, found.cx, found.cy
    if found.width is None or found.height is None:
        warnings.append(f"{path} gives no image size; taken to be camera {cam.id}'s "
                        f"{cam.width}×{cam.height}: check that it was calibrated at that size")
    elif (found.width, found.height) != (cam.width, cam.height):
        sx, sy = cam.width / found.width, cam.height / found.height
        if abs(sx - sy) * max(found.width, found.height) >= ASPECT_TOLERANCE_PX:
            turned = abs(cam.width / cam.height - found.height / found.width) < 1e-3
            why = (" (the same size turned a quarter: calibrated with the camera held the "
                   "other way?)" if turned else " (another mode of the camera, which crops "
                   "its sensor differently)")
            raise IntrinsicsError(
                f"{path}: calibrated at {found.width}×{found.height}, camera {cam.id} records "
                f"{cam.width}×{cam.height}: another aspect ratio{why}; intrinsics cannot be "
                "scaled across a crop: calibrate at the size the camera records")
        fx, fy = fx * sx, fy * sy
        cx, cy = (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5
        warnings.append(f"{path} was calibrated at {found.width}×{found.height}; scaled by "
                        f"{sx:.6g} to camera {cam.id}'s {cam.width}×{cam.height} (same aspect "
                        "ratio; check that the camera scales, not crops, at this size)")
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "distortion": list(found.distortion)}
    return values, warnings
