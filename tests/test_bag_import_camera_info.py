"""``import-bag``: a camera's intrinsics from the CameraInfo beside its image topic, as ROS's
image_geometry reads them: the lens model, rectified topics (P, no distortion), ROI and
binning, an uncalibrated camera (K zero). A lens scanpipe's pinhole cannot describe is refused
in one line instead of being read as another lens."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from test_bag_import import T0, _header, turntable_messages, write_bag

from scanpipe.recording.reader import read_recording

K = [500.0, 0.0, 320.0, 0.0, 502.0, 240.0, 0.0, 0.0, 1.0]
P = [480.0, 0.0, 316.0, 0.0, 0.0, 481.0, 244.0, 0.0, 0.0, 0.0, 1.0, 0.0]


def camera_bag(tmp_path: Path, topic: str, width: int = 640, height: int = 480,
               **info: Any) -> Path:
    """A turntable bag with 2 JPEG images on ``topic`` (``width`` × ``height``) and a
    CameraInfo (640 × 480, K, P, plumb_bob D = 0 unless ``info`` says) beside it."""
    ok, jpeg = cv2.imencode(".jpg", np.zeros((height, width, 3), np.uint8))
    assert ok

    def messages(ts: Any) -> list[Any]:
        names = [f[0] for f in ts.fielddefs["sensor_msgs/msg/CameraInfo"][1]]
        lower = "k" in names
        out = turntable_messages(ts, "joint")
        for i in range(2):
            out.append((topic, "sensor_msgs/msg/CompressedImage", 0.5 * i,
                        ts.types["sensor_msgs/msg/CompressedImage"](
                            header=_header(ts, 0.5 * i, "cam"), format="jpeg",
                            data=np.frombuffer(jpeg.tobytes(), np.uint8))))
        roi = info.pop("roi", (0, 0, 0, 0))
        values: dict[str, Any] = {
            "header": _header(ts, 0.0, "cam"), "height": 480, "width": 640,
            "distortion_model": "plumb_bob", "binning_x": 0, "binning_y": 0,
            "roi": ts.types["sensor_msgs/msg/RegionOfInterest"](
                x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3],
                do_rectify=False)}
        values.update(info)
        for key, default in (("d", np.zeros(5)), ("k", K), ("r", np.eye(3).ravel()),
                             ("p", P)):
            values[key if lower else key.upper()] = np.asarray(values.pop(key, default),
                                                               np.float64)
        base = topic.rsplit("/", 2)[0] if topic.endswith("/compressed") else \
            topic.rsplit("/", 1)[0]
        out.append((f"{base}/camera_info", "sensor_msgs/msg/CameraInfo", 0.0,
                    ts.types["sensor_msgs/msg/CameraInfo"](**values)))
        return sorted(out, key=lambda m: m[2])

    return write_bag(tmp_path, "ros1", messages)


def _camera(cli: Any, bag: Path, topic: str, out: Path) -> tuple[Any, Any]:
    result = cli("import-bag", bag, "--out", out, "--image", topic)
    assert result.code == 0, result.err
    camera_id = topic.strip("/").replace("/", "_")
    return read_recording(out).rig().camera(camera_id), result


def test_raw_topic_takes_k_and_d(tmp_path: Path, cli: Any) -> None:
    d = [-0.2, 0.05, 0.001, -0.002, 0.01]
    bag = camera_bag(tmp_path, "/cam/image_raw/compressed", d=d)
    cam, _ = _camera(cli, bag, "/cam/image_raw/compressed", tmp_path / "r.mcap")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 502.0, 320.0, 240.0)
    assert list(cam.distortion) == pytest.approx(d)


def test_rectified_topic_takes_p_without_distortion(tmp_path: Path, cli: Any) -> None:
    """K and D describe the raw image: applied to image_rect they distorted it twice."""
    bag = camera_bag(tmp_path, "/cam/image_rect_color/compressed",
                     d=[-0.2, 0.05, 0.0, 0.0, 0.0])
    cam, _ = _camera(cli, bag, "/cam/image_rect_color/compressed", tmp_path / "r.mcap")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (480.0, 481.0, 316.0, 244.0)
    assert list(cam.distortion) == [0.0] * 5


def test_roi_and_binning_give_the_published_images_intrinsics(tmp_path: Path, cli: Any
                                                              ) -> None:
    bag = camera_bag(tmp_path, "/cam/image_raw/compressed", width=160, height=120,
                     roi=(100, 40, 320, 240), binning_x=2, binning_y=2)
    cam, _ = _camera(cli, bag, "/cam/image_raw/compressed", tmp_path / "r.mcap")
    assert (cam.width, cam.height) == (160, 120)
    assert (cam.fx, cam.fy) == (250.0, 251.0)
    assert (cam.cx, cam.cy) == pytest.approx(((220 + 0.5) / 2 - 0.5, (200 + 0.5) / 2 - 0.5))


def test_uncalibrated_camera_info_is_a_warned_guess(tmp_path: Path, cli: Any) -> None:
    bag = camera_bag(tmp_path, "/cam/image_raw/compressed", k=np.zeros(9), p=np.zeros(12),
                     distortion_model="")
    cam, result = _camera(cli, bag, "/cam/image_raw/compressed", tmp_path / "r.mcap")
    assert "holds no calibration (K is zero" in result.err
    assert cam.width == 640 and cam.fx == pytest.approx(320 / np.tan(np.radians(30)))


@pytest.mark.parametrize(("model", "d", "named"), [
    ("equidistant", [0.1, -0.02, 0.003, -0.001], "'equidistant'"),
    ("rational_polynomial", [-0.2, 0.05, 0.0, 0.0, 0.0, 0.3, 0.01, 0.0], "'rational_polynomial'"),
])
def test_lens_the_pinhole_cannot_describe_is_refused(tmp_path: Path, cli: Any, model: str,
                                                     d: list[float], named: str) -> None:
    """A fisheye's k1…k4 were read as k1 k2 p1 p2, a rational model's k4…k6 dropped: texture
    would have projected through another lens without a word."""
    bag = camera_bag(tmp_path, "/cam/image_raw/compressed", d=d, distortion_model=model)
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/cam/image_raw/compressed")
    assert result.code == 1, result.err
    assert f"its CameraInfo's lens model is {named}" in result.err
    assert "pass --rig" in result.err and result.err.count("\n") == 1
    assert not out.exists()


def test_rational_model_with_zero_k4_to_k6_is_taken(tmp_path: Path, cli: Any) -> None:
    d = [-0.2, 0.05, 0.001, 0.0, 0.01, 0.0, 0.0, 0.0]
    bag = camera_bag(tmp_path, "/cam/image_raw/compressed", d=d,
                     distortion_model="rational_polynomial")
    cam, _ = _camera(cli, bag, "/cam/image_raw/compressed", tmp_path / "r.mcap")
    assert list(cam.distortion) == pytest.approx(d[:5])


@pytest.mark.parametrize("encoding", ["bgra8", "rgba8"])
def test_four_channel_raw_images_are_taken(tmp_path: Path, cli: Any, encoding: str) -> None:
    """ZED and Gazebo cameras publish bgra8 / rgba8: they were skipped (a count, no frames)."""
    bgr = np.zeros((48, 64, 3), np.uint8)
    bgr[:, :32] = (0, 0, 255)  # red left half
    order = [0, 1, 2] if encoding == "bgra8" else [2, 1, 0]
    pixels = np.concatenate([bgr[:, :, order], np.full((48, 64, 1), 255, np.uint8)], axis=2)

    def messages(ts: Any) -> list[Any]:
        out = turntable_messages(ts, "joint")
        out.append(("/zed/image_raw", "sensor_msgs/msg/Image", 0.2, ts.types[
            "sensor_msgs/msg/Image"](header=_header(ts, 0.2, "zed"), height=48, width=64,
                                     encoding=encoding, is_bigendian=0, step=64 * 4,
                                     data=pixels.ravel().copy())))
        return sorted(out, key=lambda m: m[2])

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/zed/image_raw")
    assert result.code == 0, result.err
    images = read_recording(out).images
    assert len(images) == 1
    decoded = cv2.imdecode(np.frombuffer(images[0].data, np.uint8), cv2.IMREAD_COLOR)
    assert tuple(decoded[0, 0]) == (0, 0, 255) and tuple(decoded[0, 63]) == (0, 0, 0)


def test_sixteen_bit_png_is_a_depth_image_not_a_frame(tmp_path: Path, cli: Any) -> None:
    """A depth camera's compressed 16UC1 PNG on --image: OpenCV read its high bytes as a grey
    picture, textured as if it were a colour frame."""
    ok, depth = cv2.imencode(".png", np.full((48, 64), 1234, np.uint16))
    assert ok

    def messages(ts: Any) -> list[Any]:
        out = turntable_messages(ts, "joint")
        out.append(("/depth/image/compressed", "sensor_msgs/msg/CompressedImage", 0.2,
                    ts.types["sensor_msgs/msg/CompressedImage"](
                        header=_header(ts, 0.2, "depth"), format="16UC1; png",
                        data=np.frombuffer(depth.tobytes(), np.uint8))))
        return sorted(out, key=lambda m: m[2])

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/depth/image/compressed")
    assert result.code == 0, result.err
    assert not read_recording(out).images
    assert "/depth/image/compressed: 1 images in an encoding not taken" in result.err


def test_exif_orientation_in_a_compressed_image_is_removed(tmp_path: Path, cli: Any) -> None:
    """A JPEG with EXIF orientation 3 (a half turn): ROS shows its pixels as stored; OpenCV's
    frame decoding turned them upside down, with intrinsics still for the stored pixels."""
    from io import BytesIO

    from PIL import Image

    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[:12, :16] = 255  # a white box top-left as stored
    exif = Image.Exif()
    exif[0x0112] = 3
    buffer = BytesIO()
    Image.fromarray(rgb).save(buffer, "JPEG", quality=95, exif=exif)
    jpeg = buffer.getvalue()

    def messages(ts: Any) -> list[Any]:
        out = turntable_messages(ts, "joint")
        out.append(("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", 0.2,
                    ts.types["sensor_msgs/msg/CompressedImage"](
                        header=_header(ts, 0.2, "cam"), format="jpeg",
                        data=np.frombuffer(jpeg, np.uint8))))
        return sorted(out, key=lambda m: m[2])

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/cam/image_raw/compressed")
    assert result.code == 0, result.err
    assert "1 images carried an EXIF orientation tag: removed" in result.err
    data = read_recording(out).images[0].data
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded[:12, :16].mean() > 240 and decoded[-12:, -16:].mean() < 15
    stored = cv2.imdecode(np.frombuffer(jpeg, np.uint8),
                          cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    assert np.array_equal(decoded, stored)  # the pixels unchanged


def _uptime_header(ts: Any, seconds: float, frame: str) -> Any:
    """A header stamped by another clock: seconds since the camera booted."""
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=int(seconds),
                                                    nanosec=int(seconds % 1 * 1e9))
    if "seq" in ts.fielddefs["std_msgs/msg/Header"][1][0]:
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def test_images_stamped_by_another_clock_take_the_bags_log_times(tmp_path: Path,
                                                                  cli: Any) -> None:
    """A camera stamping its own uptime: every frame 56 years before the scan, textured at
    the platform's first angle without a word."""
    ok, jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))
    assert ok

    def messages(ts: Any) -> list[Any]:
        out = turntable_messages(ts, "joint")
        for i, (topic, t) in enumerate([("/cam/image/compressed", 0.5),
                                        ("/cam/image/compressed", 1.5),
                                        ("/late/image/compressed", 100.0)]):
            header = (_uptime_header(ts, 40.0 + i, "cam") if topic.startswith("/cam") else
                      _header(ts, t, "late"))
            out.append((topic, "sensor_msgs/msg/CompressedImage", t,
                        ts.types["sensor_msgs/msg/CompressedImage"](
                            header=header, format="jpeg",
                            data=np.frombuffer(jpeg.tobytes(), np.uint8))))
        return sorted(out, key=lambda m: m[2])

    bag = write_bag(tmp_path, "ros1", messages)
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", "/cam/image/compressed",
                 "--image", "/late/image/compressed")
    assert result.code == 0, result.err
    assert "/cam/image/compressed: none of its 2 header stamps falls within the scan's " \
           "time" in result.err
    assert "/late/image/compressed: none of its 1 images was taken during the scan" \
        in result.err
    images = read_recording(out).images
    assert [i.camera_id for i in images] == ["cam_image_compressed"] * 2
    assert [i.log_time_ns for i in images] == [T0 + 500_001_000, T0 + 1_500_001_000]


def test_camera_info_the_rig_refuses_is_one_line(tmp_path: Path, cli: Any) -> None:
    """A ROI that leaves the principal point outside the published image gives a camera the
    rig refuses: one line naming the topic, not a pydantic traceback; nothing written."""
    topic = "/cam/image_raw/compressed"
    bag = camera_bag(tmp_path, topic, width=100, height=80, roi=(400, 300, 100, 80))
    out = tmp_path / "r.mcap"
    result = cli("import-bag", bag, "--out", out, "--image", topic)
    assert result.code != 0
    assert "Traceback" not in result.err
    message = result.err.strip().splitlines()
    assert len(message) == 1 and topic in message[0] and "cx" in message[0], result.err
    assert not out.exists()


def test_exif_is_cut_out_past_fill_bytes() -> None:
    """JPEG allows 0xFF fill bytes before a marker: the segment
    walk read a fill byte as a marker, kept the Exif segment, and the frame decoded turned
    without a word."""
    from io import BytesIO

    from PIL import Image

    from scanpipe.bagio import without_exif

    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[:12, :16] = 255
    exif = Image.Exif()
    exif[0x0112] = 6  # a quarter turn: a turned decode changes the shape
    buffer = BytesIO()
    Image.fromarray(rgb).save(buffer, "JPEG", quality=95, exif=exif)
    jpeg = buffer.getvalue()
    for variant in (jpeg, jpeg[:2] + b"\xff\xff" + jpeg[2:]):
        assert cv2.imdecode(np.frombuffer(variant, np.uint8), cv2.IMREAD_COLOR).shape[:2] \
            == (64, 48)  # OpenCV turns it by the tag
        stripped = without_exif(variant)
        assert stripped is not None
        decoded = cv2.imdecode(np.frombuffer(stripped, np.uint8), cv2.IMREAD_COLOR)
        assert decoded.shape[:2] == (48, 64)
        assert decoded[:12, :16].mean() > 200 and decoded[24:, 32:].mean() < 50


def test_exif_orientation_is_cut_out_of_a_png_too() -> None:
    """OpenCV turns a PNG by its eXIf chunk's orientation as it turns a JPEG."""
    from io import BytesIO

    from PIL import Image

    from scanpipe.bagio import without_exif

    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[:12, :16] = 255
    exif = Image.Exif()
    exif[0x0112] = 6
    buffer = BytesIO()
    Image.fromarray(rgb).save(buffer, "PNG", exif=exif)
    png = buffer.getvalue()
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).shape[:2] == (64, 48)
    stripped = without_exif(png)
    assert stripped is not None
    decoded = cv2.imdecode(np.frombuffer(stripped, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape[:2] == (48, 64) and decoded[:12, :16].mean() > 200
    assert without_exif(without_exif(png) or b"") is None  # nothing left to cut
