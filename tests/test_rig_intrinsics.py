"""`scanpipe rig intrinsics`: camera intrinsics written by OpenCV, ROS, COLMAP and Metashape,
converted to the rig's conventions (OpenCV pinhole, top-left pixel centre at 0).

Public files other tools wrote (tests/fixtures/intrinsics/, sources in tests/fixtures/README.md),
round trips through each format written the way its tool writes it, the projection of points
by each tool's own formula against scanpipe's, and every bad input refused in one line (exit
code 2) with nothing overwritten.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from scanpipe.camera import normalized_to_pixels
from scanpipe.exporters.colmap import _camera_line
from scanpipe.rig import CameraConfig, load_rig, rig_to_toml

FIXTURES = Path(__file__).parent / "fixtures" / "intrinsics"
#: A camera with everything a convention can get wrong: fx ≠ fy, an off-centre principal
#: point, all five coefficients (p1 ≠ p2, so a swap shows).
CAM = CameraConfig(id="cam0", width=1280, height=720, fx=1010.25, fy=1003.5, cx=652.375,
                   cy=351.625, distortion=(-0.21, 0.083, 0.0012, -0.0007, -0.011))

Cli = Callable[..., Any]


def _rig(tmp_path: Path, *cams: CameraConfig) -> Path:
    """A rig file with these cameras (default scanner and motor)."""
    from scanpipe.rig import Rig

    path = tmp_path / "rig.toml"
    path.write_text(rig_to_toml(Rig(cameras=cams or (CAM,))))
    return path


def _blank(cam: CameraConfig, cam_id: str | None = None) -> CameraConfig:
    """``cam`` with centred, undistorted default intrinsics (what the import must replace)."""
    return cam.model_copy(update={
        "id": cam_id or cam.id, "fx": cam.width * 0.8, "fy": cam.width * 0.8,
        "cx": (cam.width - 1) / 2, "cy": (cam.height - 1) / 2, "distortion": (0.0,) * 5})


def _imported(cli: Cli, tmp_path: Path, file: Path, cam: CameraConfig, *extra: str
              ) -> CameraConfig:
    rig = _rig(tmp_path, _blank(cam))
    out = tmp_path / "new.toml"
    result = cli("rig", "intrinsics", file, "--rig", rig, "--camera", cam.id, "--out", out,
                 *extra)
    assert result.code == 0, result.err
    assert f"wrote {out}" in result.out
    return load_rig(out).camera(cam.id)


def _assert_same(found: CameraConfig, cam: CameraConfig) -> None:
    assert (found.width, found.height) == (cam.width, cam.height)
    np.testing.assert_allclose([found.fx, found.fy, found.cx, found.cy],
                               [cam.fx, cam.fy, cam.cx, cam.cy], rtol=0, atol=1e-9)
    np.testing.assert_allclose(found.distortion, cam.distortion, rtol=0, atol=1e-12)


# --- public files written by the tools -------------------------------------------------------


def test_opencv_sample_out_camera_data(cli: Cli, tmp_path: Path) -> None:
    cam = CameraConfig(id="c", width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
    found = _imported(cli, tmp_path, FIXTURES / "opencv_out_camera_data.yml", cam)
    assert (found.fx, found.fy, found.cx, found.cy) == (
        pytest.approx(657.46697810243404), pytest.approx(657.46697810243404), 319.5, 239.5)
    assert found.distortion == pytest.approx(
        (-0.41802327018241026, 0.50715243805833121, 0.0, 0.0, -0.57843596847939704))


def test_ros_usb_cam_camera_info(cli: Cli, tmp_path: Path) -> None:
    cam = CameraConfig(id="c", width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
    found = _imported(cli, tmp_path, FIXTURES / "ros_usb_cam_camera_info.yaml", cam)
    assert (found.fx, found.fy, found.cx, found.cy) == (438.783367, 437.302876, 305.593336,
                                                        243.738352)
    assert found.distortion == (-0.361976, 0.110510, 0.001014, 0.000505, 0.0)


def test_colmap_documentation_cameras_each_model(cli: Cli, tmp_path: Path) -> None:
    cam = CameraConfig(id="c", width=3072, height=2304, fx=2000.0, fy=2000.0, cx=1535.5,
                       cy=1151.5)
    expected = {"1": (2559.81, 2559.81, 0.0), "2": (2560.56, 2560.56, 0.0),
                "3": (2559.69, 2559.69, -0.0218531)}
    for camera_id, (fx, fy, k1) in expected.items():
        found = _imported(cli, tmp_path, FIXTURES / "colmap_format_cameras.txt", cam,
                          "--file-camera", camera_id, "--force")
        # COLMAP's (1536, 1152) is the image centre in its pixel-corner frame: 1535.5, 1151.5
        assert (found.fx, found.fy, found.cx, found.cy) == (fx, fy, 1535.5, 1151.5)
        assert found.distortion == (k1, 0.0, 0.0, 0.0, 0.0)


def test_metashape_sensor_export(cli: Cli, tmp_path: Path) -> None:
    cam = CameraConfig(id="c", width=5472, height=3648, fx=3000.0, fy=3000.0, cx=2735.5,
                       cy=1823.5)
    file = FIXTURES / "metashape_easyidp_sensors.xml"
    found = _imported(cli, tmp_path, file, cam)  # sensor 0 has no calibration: 1 is taken
    assert found.fx == found.fy == 3239.2350850187408
    assert found.cx == pytest.approx(5472 / 2 - 17.266617222361305 - 0.5)
    assert found.cy == pytest.approx(3648 / 2 + 51.627079230267093 - 0.5)
    # Metashape's p1, p2 are OpenCV's p2, p1
    assert found.distortion == (-0.0061748904544724733, 0.0085312948846406767,
                                0.00036559169480901107, 0.0038636434570336977,
                                -0.0059426077261182687)


def test_prints_what_changed_and_writes_nothing_without_out(cli: Cli, tmp_path: Path) -> None:
    cam = CameraConfig(id="c", width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)
    rig = _rig(tmp_path, cam)
    before = sorted(tmp_path.iterdir())
    result = cli("rig", "intrinsics", FIXTURES / "ros_usb_cam_camera_info.yaml", "--rig", rig,
                 "--camera", "c")
    assert result.code == 0, result.err
    assert "cx         319.5 → 305.593" in result.out
    assert "distortion [0, 0, 0, 0, 0] → [-0.361976, 0.11051, 0.001014, 0.000505, 0]" in (
        result.out)
    assert "nothing written" in result.out
    assert sorted(tmp_path.iterdir()) == before
    result = cli("rig", "intrinsics", FIXTURES / "ros_usb_cam_camera_info.yaml", "--rig", rig,
                 "--camera", "c", "--json")
    import json

    report = json.loads(result.out)
    assert report["format"] == "ros" and report["written"] is None
    assert report["changes"]["fx"] == [500.0, 438.783367]


# --- round trips: our camera → each tool's file (written as the tool writes it) → import ------


def _write_opencv(path: Path, cam: CameraConfig) -> None:
    """As OpenCV's calibration sample writes it (cv2.FileStorage, YAML or XML by suffix)."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", cam.width)
    storage.write("image_height", cam.height)
    storage.write("camera_matrix", np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy],
                                             [0, 0, 1]], dtype=np.float64))
    storage.write("distortion_coefficients", np.array(cam.distortion, np.float64).reshape(5, 1))
    storage.write("avg_reprojection_error", 0.31)
    storage.release()


def _write_ros(path: Path, cam: CameraConfig) -> None:
    """As camera_calibration_parsers' writeCalibrationYml writes it."""
    def matrix(name: str, rows: int, cols: int, data: list[float]) -> str:
        values = ", ".join(f"{v:.17g}" for v in data)
        return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{values}]\n"

    k = [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1]
    p = [cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0]
    path.write_text(f"image_width: {cam.width}\nimage_height: {cam.height}\ncamera_name: "
                    f"{cam.id}\n" + matrix("camera_matrix", 3, 3, k)
                    + "distortion_model: plumb_bob\n"
                    + matrix("distortion_coefficients", 1, 5, list(cam.distortion))
                    + matrix("rectification_matrix", 3, 3, [1, 0, 0, 0, 1, 0, 0, 0, 1])
                    + matrix("projection_matrix", 3, 4, p))


def _write_ros_echo(path: Path, cam: CameraConfig) -> None:
    """A CameraInfo as ``ros2 topic echo --once`` prints it (lower-case k, d; block lists)."""
    lines = ["header:", "  stamp:", "    sec: 0", "    nanosec: 0", "  frame_id: cam",
             f"height: {cam.height}", f"width: {cam.width}", "distortion_model: plumb_bob", "d:"]
    lines += [f"- {v!r}" for v in cam.distortion]
    lines += ["k:"] + [f"- {float(v)!r}" for v in (cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0,
                                                    1)]
    lines += ["binning_x: 0", "binning_y: 0", "roi:", "  x_offset: 0", "  y_offset: 0",
              "  height: 0", "  width: 0", "  do_rectify: false", "---"]
    path.write_text("\n".join(lines) + "\n")


def _write_colmap(path: Path, cam: CameraConfig) -> None:
    """As COLMAP writes cameras.txt (the line from scanpipe's own COLMAP exporter)."""
    path.write_text("# Camera list with one line of data per camera:\n"
                    "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                    + _camera_line(1, cam) + "\n")


def _write_colmap_binary(path: Path, cam: CameraConfig) -> None:
    """As COLMAP writes cameras.bin (WriteCamerasBinary): one OPENCV/FULL_OPENCV camera."""
    import struct

    fields = _camera_line(1, cam).split()
    model_id = {"OPENCV": 4, "FULL_OPENCV": 6}[fields[1]]
    params = [float(v) for v in fields[4:]]
    path.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 1, model_id, cam.width,
                                                         cam.height)
                     + struct.pack(f"<{len(params)}d", *params))


def _write_metashape(path: Path, cam: CameraConfig) -> None:
    """As Metashape's Export Cameras writes a frame sensor (offsets from the centre, its own
    p1/p2 order, fx − fy as the affinity b1)."""
    k1, k2, p1, p2, k3 = cam.distortion
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="2.0.0">
  <chunk label="Chunk 1" enabled="true">
    <sensors next_id="1">
      <sensor id="0" label="phone (4.2mm)" type="frame">
        <resolution width="{cam.width}" height="{cam.height}"/>
        <calibration type="frame" class="adjusted">
          <resolution width="{cam.width}" height="{cam.height}"/>
          <f>{cam.fy!r}</f>
          <cx>{cam.cx + 0.5 - cam.width / 2!r}</cx>
          <cy>{cam.cy + 0.5 - cam.height / 2!r}</cy>
          <b1>{cam.fx - cam.fy!r}</b1>
          <k1>{k1!r}</k1>
          <k2>{k2!r}</k2>
          <k3>{k3!r}</k3>
          <p1>{p2!r}</p1>
          <p2>{p1!r}</p2>
        </calibration>
      </sensor>
    </sensors>
  </chunk>
</document>
""")


def _write_metashape_calibration(path: Path, cam: CameraConfig) -> None:
    """As Metashape's Camera Calibration → Export (Agisoft calibration XML) writes it."""
    k1, k2, p1, p2, k3 = cam.distortion
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8"?>
<calibration>
  <projection>frame</projection>
  <width>{cam.width}</width>
  <height>{cam.height}</height>
  <f>{cam.fy!r}</f>
  <cx>{cam.cx + 0.5 - cam.width / 2!r}</cx>
  <cy>{cam.cy + 0.5 - cam.height / 2!r}</cy>
  <b1>{cam.fx - cam.fy!r}</b1>
  <b2>0</b2>
  <k1>{k1!r}</k1>
  <k2>{k2!r}</k2>
  <k3>{k3!r}</k3>
  <k4>0</k4>
  <p1>{p2!r}</p1>
  <p2>{p1!r}</p2>
  <date>2024-02-05T21:40:39Z</date>
</calibration>
""")


def _write_photoscan_legacy(path: Path, cam: CameraConfig) -> None:
    """As PhotoScan before 1.3 (and Agisoft Lens) wrote it: fx, fy, absolute cx, cy in its
    pixel-corner frame, skew, p1 p2 in OpenCV's order."""
    k1, k2, p1, p2, k3 = cam.distortion
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8"?>
<calibration>
  <projection>frame</projection>
  <width>{cam.width}</width>
  <height>{cam.height}</height>
  <fx>{cam.fx!r}</fx>
  <fy>{cam.fy!r}</fy>
  <cx>{cam.cx + 0.5!r}</cx>
  <cy>{cam.cy + 0.5!r}</cy>
  <skew>0</skew>
  <k1>{k1!r}</k1>
  <k2>{k2!r}</k2>
  <k3>{k3!r}</k3>
  <p1>{p1!r}</p1>
  <p2>{p2!r}</p2>
  <date>2015-05-17T11:13:14Z</date>
</calibration>
""")


@pytest.mark.parametrize(("name", "writer"), [
    ("calib.yml", _write_opencv), ("calib.xml", _write_opencv), ("camera.yaml", _write_ros),
    ("info.yaml", _write_ros_echo), ("cameras.txt", _write_colmap),
    ("cameras.bin", _write_colmap_binary),
    ("cameras.xml", _write_metashape), ("calibration.xml", _write_metashape_calibration),
    ("lens.xml", _write_photoscan_legacy)])
def test_round_trip_through_each_format(cli: Cli, tmp_path: Path, name: str,
                                        writer: Callable[[Path, CameraConfig], None]) -> None:
    file = tmp_path / name
    writer(file, CAM)
    _assert_same(_imported(cli, tmp_path, file, CAM), CAM)


def test_colmap_full_opencv_round_trip(cli: Cli, tmp_path: Path) -> None:
    file = tmp_path / "cameras.txt"
    _write_colmap(file, CAM)
    assert " FULL_OPENCV " in file.read_text()  # k3 ≠ 0
    no_k3 = CAM.model_copy(update={"distortion": (*CAM.distortion[:4], 0.0)})
    _write_colmap(file, no_k3)
    assert " OPENCV " in file.read_text()
    _assert_same(_imported(cli, tmp_path, file, no_k3), no_k3)


def _metashape_pixels(cam: CameraConfig, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Metashape's frame camera (its manual, appendix C), in its pixel-corner frame, with the
    parameters as _write_metashape stores them."""
    k1, k2, p1_cv, p2_cv, k3 = cam.distortion
    p1, p2 = p2_cv, p1_cv
    f, b1 = cam.fy, cam.fx - cam.fy
    cx, cy = cam.cx + 0.5 - cam.width / 2, cam.cy + 0.5 - cam.height / 2
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    return np.stack([cam.width * 0.5 + cx + xd * (f + b1), cam.height * 0.5 + cy + yd * f], 1)


def _colmap_pixels(cam: CameraConfig, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """COLMAP's OPENCV / FULL_OPENCV model (its camera_models.h), in its pixel-corner frame."""
    fields = _camera_line(1, cam).split()
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = [float(v) for v in fields[4:13]]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    return np.stack([fx * xd + cx, fy * yd + cy], 1)


@pytest.mark.parametrize(("name", "writer", "their_pixels"), [
    ("cameras.xml", _write_metashape, _metashape_pixels),
    ("cameras.txt", _write_colmap, _colmap_pixels)])
def test_imported_camera_projects_where_the_tool_does(
        cli: Cli, tmp_path: Path, name: str, writer: Callable[[Path, CameraConfig], None],
        their_pixels: Callable[[CameraConfig, np.ndarray, np.ndarray], np.ndarray]) -> None:
    """The tool's own projection formula, in its own pixel frame, lands 0.5 px right and down
    of scanpipe's with the imported camera: a swapped p1/p2 or a missing half pixel shows."""
    file = tmp_path / name
    writer(file, CAM)
    found = _imported(cli, tmp_path, file, CAM)
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-0.6, 0.6, 200), rng.uniform(-0.35, 0.35, 200)
    u, v = normalized_to_pixels(x.copy(), y.copy(), found)
    np.testing.assert_allclose(np.stack([u, v], 1) + 0.5, their_pixels(CAM, x, y), atol=1e-6)


def test_other_resolution_same_aspect_is_scaled_with_a_warning(cli: Cli, tmp_path: Path
                                                                ) -> None:
    half = CAM.model_copy(update={"width": 640, "height": 360})
    rig = _rig(tmp_path, _blank(half))
    file = tmp_path / "calib.yml"
    _write_opencv(file, CAM)  # calibrated at 1280 × 720
    out = tmp_path / "new.toml"
    result = cli("rig", "intrinsics", file, "--rig", rig, "--camera", "cam0", "--out", out)
    assert result.code == 0, result.err
    assert "calibrated at 1280×720; scaled by 0.5 to camera cam0's 640×360" in result.err
    found = load_rig(out).camera("cam0")
    np.testing.assert_allclose([found.fx, found.fy, found.cx, found.cy],
                               [CAM.fx / 2, CAM.fy / 2, (CAM.cx + 0.5) / 2 - 0.5,
                                (CAM.cy + 0.5) / 2 - 0.5])
    assert found.distortion == CAM.distortion


def test_file_without_size_or_distortion_is_taken_at_the_cameras_size_with_a_warning(
        cli: Cli, tmp_path: Path) -> None:
    file = _file(tmp_path, "K.yml", "%YAML:1.0\nK: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
                 "   dt: d\n   data: [ 1000., 0., 641.5, 0., 1001., 358.25, 0., 0., 1. ]\n")
    rig = _rig(tmp_path, _blank(CAM))
    result = cli("rig", "intrinsics", file, "--rig", rig, "--camera", "cam0")
    assert result.code == 0, result.err
    assert f"{file} gives no image size; taken to be camera cam0's 1280×720" in result.err
    assert "no distortion coefficients: taken as 0" in result.out
    assert "cx         639.5 → 641.5" in result.out


# --- bad inputs: one line, exit code 2, nothing overwritten ----------------------------------


def _refused(cli: Cli, tmp_path: Path, file: Path, *args: str, rig: Path | None = None) -> str:
    rig = rig or _rig(tmp_path, _blank(CAM))
    rig_text = rig.read_text()
    out = tmp_path / "kept.toml"
    out.write_text("# a valid file the failed command must not touch\n")
    result = cli("rig", "intrinsics", file, "--rig", rig, "--out", out, "--force", *args)
    assert result.code == 2, (result.out, result.err)
    assert result.err.startswith("scanpipe: error: ") and result.err.count("\n") == 1, result.err
    assert "Traceback" not in result.err
    assert out.read_text() == "# a valid file the failed command must not touch\n"
    assert rig.read_text() == rig_text
    return str(result.err)


def _file(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_unknown_format_option(cli: Cli, tmp_path: Path) -> None:
    file = tmp_path / "calib.yml"
    _write_opencv(file, CAM)
    err = _refused(cli, tmp_path, file, "--camera", "cam0", "--format", "kalibr")
    assert "--format 'kalibr': unknown; allowed: auto, opencv, ros, colmap, metashape" in err


def test_unrecognised_file(cli: Cli, tmp_path: Path) -> None:
    file = _file(tmp_path, "notes.txt", "fx is about 1000\n")
    err = _refused(cli, tmp_path, file, "--camera", "cam0")
    assert f"{file}: not an intrinsics file this command knows" in err


def test_file_in_another_format_than_given(cli: Cli, tmp_path: Path) -> None:
    err = _refused(cli, tmp_path, FIXTURES / "colmap_format_cameras.txt", "--camera", "cam0",
                   "--format", "opencv")
    assert "not an OpenCV FileStorage file" in err


def test_wrong_rig_camera_id(cli: Cli, tmp_path: Path) -> None:
    file = tmp_path / "calib.yml"
    _write_opencv(file, CAM)
    err = _refused(cli, tmp_path, file, "--camera", "cam7")
    assert "--camera 'cam7': not in" in err and "(its cameras: cam0)" in err


def test_wrong_file_camera(cli: Cli, tmp_path: Path) -> None:
    rig = _rig(tmp_path, _blank(CAM.model_copy(update={"width": 3072, "height": 2304,
                                                       "cx": 1535.5, "cy": 1151.5})))
    file = FIXTURES / "colmap_format_cameras.txt"
    err = _refused(cli, tmp_path, file, "--camera", "cam0", rig=rig)
    assert "holds 3 cameras (CAMERA_ID 1, 2, 3); choose one with --file-camera" in err
    err = _refused(cli, tmp_path, file, "--camera", "cam0", "--file-camera", "9", rig=rig)
    assert "--file-camera '9': not in" in err and "its cameras: 1, 2, 3" in err


def test_equirect_rig_camera_refused(cli: Cli, tmp_path: Path) -> None:
    from scanpipe.rig import default_cameras

    rig = _rig(tmp_path, default_cameras()[2])
    err = _refused(cli, tmp_path, FIXTURES / "ros_usb_cam_camera_info.yaml", "--camera",
                   "cam360", rig=rig)
    assert "camera cam360 is an equirect camera" in err


UNSUPPORTED = [
    ("cameras.txt", "1 OPENCV_FISHEYE 1280 720 1000 1000 640 360 0.1 0.01 0 0\n",
     "COLMAP model OPENCV_FISHEYE cannot be described by the rig's pinhole"),
    ("cameras.txt", "1 FULL_OPENCV 1280 720 1000 1000 640 360 0.1 0.01 0 0 0 0.2 0 0\n",
     "uses coefficients beyond k1 k2 p1 p2 k3 (k4… = [0.2, 0.0, 0.0])"),
    ("cameras.txt", "1 PINHOLE 1280 720 1000 1000 640\n",
     "camera 1: PINHOLE has 4 parameters (fx fy cx cy), found 3"),
    ("info.yaml", "image_width: 1280\nimage_height: 720\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
     "  data: [1000, 0, 640, 0, 1000, 360, 0, 0, 1]\ndistortion_model: equidistant\n"
     "distortion_coefficients:\n  rows: 1\n  cols: 4\n  data: [0.1, 0.01, 0, 0]\n",
     "distortion_model 'equidistant' cannot be described by the rig's pinhole"),
    ("info.yaml", "image_width: 1280\nimage_height: 720\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
     "  data: [1000, 0, 640, 0, 1000, 360, 0, 0, 1]\ndistortion_model: rational_polynomial\n"
     "distortion_coefficients:\n  rows: 1\n  cols: 8\n  data: [0.1, 0.01, 0, 0, 0, 0.3, 0, 0]\n",
     "uses coefficients beyond k1 k2 p1 p2 k3"),
    ("calib.yml", "%YAML:1.0\n---\nimage_width: 1280\nimage_height: 720\nfisheye_model: 1\n"
     "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
     "   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0., 1. ]\n"
     "distortion_coefficients: !!opencv-matrix\n   rows: 4\n   cols: 1\n   dt: d\n"
     "   data: [ 0.1, 0.01, 0., 0. ]\n",
     "fisheye_model is set: OpenCV's fisheye (equidistant) lens model"),
    ("cameras.xml", "<document><chunk><sensors><sensor id='0' type='frame'>"
     "<calibration type='frame' class='adjusted'><resolution width='1280' height='720'/>"
     "<f>1000</f><k1>0.1</k1><k4>-0.07</k4></calibration></sensor></sensors></chunk></document>",
     "sensor 0: k4 = -0.07; the rig's pinhole has k1 k2 p1 p2 k3 only"),
    ("cameras.xml", "<document><chunk><sensors><sensor id='0' type='fisheye'>"
     "<calibration type='fisheye' class='adjusted'><resolution width='1280' height='720'/>"
     "<f>1000</f></calibration></sensor></sensors></chunk></document>",
     "sensor 0: a 'fisheye' camera; the rig's pinhole holds Metashape's 'frame' cameras only"),
    ("cameras.xml", "<document><chunk><sensors><sensor id='0' type='frame'>"
     "<calibration type='frame' class='adjusted'><resolution width='1280' height='720'/>"
     "<f>1000</f><b2>4.5</b2></calibration></sensor></sensors></chunk></document>",
     "skew b2 = 4.5 px shifts the image's edge by 1.6 px"),
    ("calibration.xml", "<calibration><projection>frame</projection><width>1920</width>"
     "<height>1080</height><f>1430.15</f><cx>-24.13</cx><cy>17.55</cy><b2>-4.25</b2>"
     "<k1>-0.118</k1></calibration>",
     "calibration: skew b2 = -4.25 px shifts the image's edge by 1.6 px"),
    ("lens.xml", "<calibration><projection>frame</projection><width>1280</width>"
     "<height>720</height><fx>1000</fx><fy>1000</fy><cx>640</cx><cy>360</cy>"
     "<skew>2.2</skew></calibration>",
     "calibration: skew = 2.2 px shifts the image's edge by 0.79 px"),
    ("calibration.xml", "<calibration><projection>frame</projection><f>1000</f>"
     "</calibration>", "calibration: no image size"),
    ("calib.yml", "%YAML:1.0\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [ 1000., 0., 0., 0., 1000., 0., 640., 360., 1. ]\n",
     "is not [fx 0 cx; 0 fy cy; 0 0 1] (transposed, or scaled?)"),
    ("info.yaml", "image_width: 1280\nimage_height: 720\ncamera_matrix:\n  rows: 3\n"
     "  cols: 3\n  data: [1000, 3.5, 640, 0, 1000, 360, 0, 0, 1]\n",
     "the camera matrix has a skew of 3.5 px"),
    ("info.yaml", "image_width: 1280\nimage_height: 720\ncamera_matrix:\n  rows: 3\n"
     "  cols: 3\n  data: [0, 0, 0, 0, 0, 0, 0, 0, 0]\n",
     "holds no calibration (fx = 0, fy = 0"),
    ("cameras.txt", "1 PINHOLE 1280 720 1000 1000 abc 360\n", "a parameter is not a number"),
    ("cameras.xml", "<document><chunk><sensors><sensor id='0' type='frame'>"
     "<calibration type='frame' class='adjusted'><resolution width='wide' height='720'/>"
     "<f>1000</f></calibration></sensor></sensors></chunk></document>",
     "image size 'wide' × '720' is not a whole number of pixels"),
    ("broken.xml", "<document><chunk><sensors>", "not valid XML"),
    ("cameras.bin", "\x02\x00\x00\x00\x00\x00\x00\x00\x01\x00",
     "not a COLMAP cameras.bin (ends inside a camera record after 0 cameras)"),
    ("info.yaml", "camera_matrix: [1, 2\n", "not valid YAML"),
    # a matrix whose data does not fill its rows × cols (OpenCV's read asserts)
    ("calib.yml", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0. ]\n",
     "camera_matrix cannot be read as a matrix"),
    ("calib.yml", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0., 1. ]\n"
     "distortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
     "   data: [ 0.1, 0.01 ]\n", "distortion_coefficients cannot be read as a matrix"),
    # an image size that is not a positive whole number of pixels (scaling divided by it)
    ("calib.yml", "%YAML:1.0\n---\nimage_width: 0\nimage_height: 720\n"
     "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
     "   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0., 1. ]\n",
     "image size 0 × 720: not a positive whole number of pixels"),
    ("calib.yml", "%YAML:1.0\n---\nimage_width: wide\nimage_height: 720\n"
     "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
     "   data: [ 1000., 0., 640., 0., 1000., 360., 0., 0., 1. ]\n",
     "image_width is not a number"),
    ("cameras.txt", "1 PINHOLE 0 720 1000 1000 640 360\n",
     "image size 0 × 720: not a positive whole number of pixels"),
    ("cameras.xml", "<calibration><projection>frame</projection><width>-1280</width>"
     "<height>720</height><f>1000</f></calibration>",
     "image size -1280 × 720: not a positive whole number of pixels"),
    ("cameras.xml", "<calibration><projection>frame</projection><width>inf</width>"
     "<height>720</height><f>1000</f></calibration>",
     "image size 'inf' × '720' is not a whole number of pixels"),
    ("cameras.xml", "<calibration><projection>frame</projection><width>1280.5</width>"
     "<height>720</height><f>1000</f></calibration>",
     "image size '1280.5' × '720' is not a whole number of pixels"),
]


@pytest.mark.parametrize(("name", "text", "needle"), UNSUPPORTED,
                         ids=[n[:40] for _, _, n in UNSUPPORTED])
def test_model_the_rig_cannot_represent(cli: Cli, tmp_path: Path, name: str, text: str,
                                        needle: str) -> None:
    err = _refused(cli, tmp_path, _file(tmp_path, name, text), "--camera", "cam0")
    assert needle in err


def test_other_aspect_ratio_refused(cli: Cli, tmp_path: Path) -> None:
    file = tmp_path / "calib.yml"
    _write_opencv(file, CAM.model_copy(update={"width": 1280, "height": 960, "cy": 479.5}))
    err = _refused(cli, tmp_path, file, "--camera", "cam0")
    assert "calibrated at 1280×960, camera cam0 records 1280×720: another aspect ratio" in err
    upright = tmp_path / "upright.yml"
    _write_opencv(upright, CAM.model_copy(update={"width": 720, "height": 1280, "cx": 359.5,
                                                  "cy": 639.5}))
    err = _refused(cli, tmp_path, upright, "--camera", "cam0")
    assert "turned a quarter" in err


def test_out_onto_an_input_refused(cli: Cli, tmp_path: Path) -> None:
    rig = _rig(tmp_path, _blank(CAM))
    text = rig.read_text()
    file = tmp_path / "calib.yml"
    _write_opencv(file, CAM)
    alias = tmp_path / "alias.toml"
    alias.hardlink_to(rig)  # the same file under another name is an input too
    for target in (rig, alias):
        result = cli("rig", "intrinsics", file, "--rig", rig, "--camera", "cam0", "--out",
                     target, "--force")
        assert result.code == 2 and "is also an input of this command" in result.err
    assert rig.read_text() == text
    existing = tmp_path / "other.toml"
    existing.write_text("x = 1\n")
    result = cli("rig", "intrinsics", file, "--rig", rig, "--camera", "cam0", "--out", existing)
    assert result.code == 2 and "already exists; pass --force" in result.err
    assert existing.read_text() == "x = 1\n"


def test_centre_offset_typed_as_position_is_refused_or_warned(cli: Cli, tmp_path: Path) -> None:
    """Metashape's cx (an offset from the centre) typed into a rig by hand: negative, it lies
    outside the image and the rig is refused; positive and small, `rig check` warns."""
    negative = _rig(tmp_path, CAM)
    assert "cx = 652.375\n" in negative.read_text()
    negative.write_text(negative.read_text().replace("cx = 652.375\n", "cx = -17.27\n"))
    result = cli("rig", "check", negative)
    assert result.code == 2
    assert "cx = -17.27 px" in result.err and "offset from the image centre" in result.err
    positive = _rig(tmp_path, CAM.model_copy(update={"cx": 15.06}))
    result = cli("rig", "check", positive)
    assert result.code == 0
    assert "warning:" in result.err and "camera cam0: cx = 15.06 px" in result.err
    assert "offset from the image centre" in result.err
    assert "warning" not in cli("rig", "check", _rig(tmp_path, CAM)).err


# --- the user's path: a scan → its COLMAP model (for an SfM/MVS tool) → back into a rig -------


def test_colmap_model_of_a_run_imports_back_into_the_recorded_rig(cli: Cli, tmp_path: Path
                                                                   ) -> None:
    """simulate → run (COLMAP export of the frames) → `rig intrinsics` of its
    sparse/0/cameras.txt into the recording's rig with the cameras blanked: equal to the
    recorded cameras; into a rig whose cameras record 8× larger (the phone's full resolution):
    scaled up with a warning."""
    import pyarrow.parquet as pq

    from scanpipe.rig import Rig, rig_from_table
    from scanpipe.sim.direct import SimOptions, simulate_direct

    simulate_direct(tmp_path / "scan.mcap", tmp_path / "truth", SimOptions(
        beam_step_deg=6.0, motor_step_deg=15.0, camera_scale=0.125, camera_fps=0.5, seed=4))
    work = tmp_path / "w"
    done = cli("run", tmp_path / "scan.mcap", "--workdir", work, "--set", "mesh.method=grid",
               "--set", 'export.cloud_formats=["colmap"]', "--set", "export.mesh_formats=[]")
    assert done.code == 0, done.err
    recorded = rig_from_table(pq.read_table(work / "decode" / "rig.parquet"))
    cameras_txt = work / "export" / "cloud_colmap" / "sparse" / "0" / "cameras.txt"
    lines = [ln.split() for ln in cameras_txt.read_text().splitlines() if ln[:1].isdigit()]
    pinholes = [c for c in recorded.cameras if c.model == "pinhole"]
    assert len(lines) == len(pinholes) >= 2
    for scale in (1, 8):
        blank = Rig(cameras=tuple(
            _blank(c.model_copy(update={"width": c.width * scale, "height": c.height * scale}))
            if c.model == "pinhole" else c for c in recorded.cameras))
        rig = tmp_path / f"blank{scale}.toml"
        rig.write_text(rig_to_toml(blank))
        for fields, cam in zip(lines, pinholes, strict=True):
            assert (int(fields[2]), int(fields[3])) == (cam.width, cam.height)
            out = tmp_path / f"{cam.id}-{scale}.toml"
            result = cli("rig", "intrinsics", cameras_txt, "--rig", rig, "--camera", cam.id,
                         "--file-camera", fields[0], "--out", out)
            assert result.code == 0, result.err
            scaled = f"scaled by 8 to camera {cam.id}'s {cam.width * 8}×{cam.height * 8}"
            assert (scaled in result.err) == (scale == 8), result.err
            found = load_rig(out).camera(cam.id)
            np.testing.assert_allclose(
                [found.fx, found.fy, found.cx, found.cy],
                [cam.fx * scale, cam.fy * scale, (cam.cx + 0.5) * scale - 0.5,
                 (cam.cy + 0.5) * scale - 0.5], atol=1e-6)
            np.testing.assert_allclose(found.distortion, cam.distortion, atol=1e-12)
