"""Camera calibration from synthetic chessboard images rendered through a known lens."""

from __future__ import annotations

import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from scanpipe.calibration import calibrate, parse_board
from scanpipe.camera import pixel_rays
from scanpipe.errors import StageError, UsageError
from scanpipe.geometry import rotation_matrix_deg
from scanpipe.rig import CameraConfig, default_rig, load_rig, rig_to_toml

TRUE = CameraConfig(id="cam0", width=640, height=480, fx=610.0, fy=606.0, cx=323.0, cy=236.5,
                    distortion=(-0.21, 0.08, 0.0012, -0.0009, 0.0))
BOARD = (9, 6)
SQUARE_M = 0.025
POSES = [  # (rotation of the board in degrees, its centre in the camera's view frame)
    ((0, 0, 0), (0.0, 0.0, 0.4)), ((25, 0, 0), (0.1, 0.07, 0.4)),
    ((-25, 10, 0), (-0.1, -0.07, 0.4)), ((0, 30, 5), (0.1, -0.07, 0.42)),
    ((0, -30, -5), (-0.1, 0.07, 0.42)), ((20, 20, 10), (0.0, 0.08, 0.45)),
    ((-15, -25, 15), (0.12, 0.0, 0.45)), ((10, -10, 30), (-0.12, 0.0, 0.45)),
    ((-30, 15, -20), (0.0, -0.08, 0.45)), ((5, 35, 0), (-0.03, 0.0, 0.36)),
]


def render_board(rotation_deg: tuple[float, float, float], centre: tuple[float, float, float],
                 origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """A grey image of a 10 × 7-square board (with a white margin), 2 × 2 supersampled from
    the pixel rays ``origin, dirs`` of the true camera at twice the resolution."""
    # pixel_rays puts image-right along −x (geometry.CAMERA_BASE); board frame: x right, y down
    base = np.diag([-1.0, -1.0, 1.0])
    rotation = base @ rotation_matrix_deg(rotation_deg)
    cols, rows = BOARD[0] + 1, BOARD[1] + 1
    half = np.array([cols * SQUARE_M / 2, rows * SQUARE_M / 2, 0.0])
    centre_rig = base @ np.asarray(centre)
    normal = rotation[:, 2]
    d = dirs.reshape(-1, 3)
    t = ((centre_rig - origin) @ normal) / np.einsum("ij,j->i", d, normal)
    hit = origin + d * t[:, None]
    # board coordinates, corner (0, 0) at a square (einsum: a thin matmul is slow in OpenBLAS)
    local = np.einsum("ij,jk->ik", hit - centre_rig, rotation) + half
    sx, sy = np.floor(local[:, 0] / SQUARE_M), np.floor(local[:, 1] / SQUARE_M)
    on_board = (sx >= 0) & (sx < cols) & (sy >= 0) & (sy < rows)
    margin = (local[:, 0] > -SQUARE_M) & (local[:, 0] < (cols + 1) * SQUARE_M) & (
        local[:, 1] > -SQUARE_M) & (local[:, 1] < (rows + 1) * SQUARE_M)
    grey = np.full(len(d), 90.0)
    grey[margin] = 235.0
    grey[on_board & ((sx + sy) % 2 == 0)] = 20.0
    image = grey.reshape(960, 1280).astype(np.float32)
    return np.asarray(cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA) + 0.5,
                      dtype=np.uint8)


@pytest.fixture(scope="module")
def board_images(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    folder = tmp_path_factory.mktemp("boards")
    big = TRUE.model_copy(update={"width": 1280, "height": 960, "fx": TRUE.fx * 2,
                                  "fy": TRUE.fy * 2, "cx": TRUE.cx * 2 + 0.5,
                                  "cy": TRUE.cy * 2 + 0.5})
    origin, dirs = pixel_rays(big, 0.0)  # zero pose: camera at the origin looking along +z
    paths = []
    for k, (rotation, centre) in enumerate(POSES):
        path = folder / f"board{k:02d}.png"
        cv2.imwrite(str(path), render_board(rotation, centre, origin, dirs))
        paths.append(path)
    return paths


def test_calibration_recovers_the_lens(board_images: list[Path]) -> None:
    images = [(p.name, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in board_images]
    result = calibrate(images, BOARD, SQUARE_M)
    assert len(result.used) == len(POSES)
    assert result.rms_px < 0.3
    assert result.fx == pytest.approx(TRUE.fx, rel=0.01)
    assert result.fy == pytest.approx(TRUE.fy, rel=0.01)
    assert result.cx == pytest.approx(TRUE.cx, abs=3.0)
    assert result.cy == pytest.approx(TRUE.cy, abs=3.0)
    assert result.distortion[0] == pytest.approx(TRUE.distortion[0], abs=0.03)
    # k1 and k2 trade off against each other; what matters is the mapping over the image
    grid = np.stack(np.meshgrid(np.linspace(30, 610, 12), np.linspace(30, 450, 9)), -1)
    grid = grid.reshape(-1, 1, 2).astype(np.float64)

    def undistorted(cam: CameraConfig) -> np.ndarray:
        k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
        return cv2.undistortPoints(grid, k, np.array(cam.distortion), P=k).reshape(-1, 2)

    found = TRUE.model_copy(update={"fx": result.fx, "fy": result.fy, "cx": result.cx,
                                    "cy": result.cy, "distortion": result.distortion})
    assert np.abs(undistorted(found) - undistorted(TRUE)).max() < 1.0


def test_cli_writes_the_rig_atomically(cli, board_images: list[Path], tmp_path: Path) -> None:
    rig_path = tmp_path / "rig.toml"
    rig = default_rig()
    rig_path.write_text(rig_to_toml(rig.model_copy(update={"name": "my-lab"})))
    result = cli("calibrate-camera", *board_images, "--board", "9x6", "--square-m", "0.025",
                 "--rig", rig_path, "--camera", "cam1")
    assert result.code == 0, result.err
    assert "reprojection error" in result.out
    updated = load_rig(rig_path)
    assert updated.name == "my-lab"
    assert updated.camera("cam0") == rig.camera("cam0")  # the other camera is untouched
    cam1 = updated.camera("cam1")
    assert (cam1.width, cam1.height) == (640, 480)
    assert cam1.fx == pytest.approx(TRUE.fx, rel=0.01)
    assert cam1.pose == rig.camera("cam1").pose  # the pose is not calibrated here
    assert not list(tmp_path.glob(".rig.toml.*"))  # no temporary left behind
    as_json = cli("calibrate-camera", *board_images[:4], "--rig", rig_path, "--json")
    assert as_json.code == 0 and '"reprojection_error_px"' in as_json.out


def test_cli_errors(cli, board_images: list[Path], tmp_path: Path) -> None:
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_to_toml(default_rig()))
    before = rig_path.read_bytes()
    bad_board = cli("calibrate-camera", *board_images, "--board", "9by6", "--rig", rig_path)
    assert bad_board.code == 2 and "--board '9by6'" in bad_board.err
    unknown = cli("calibrate-camera", *board_images, "--rig", rig_path, "--camera", "cam7")
    assert unknown.code == 2 and "no camera 'cam7'" in unknown.err
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    too_few = cli("calibrate-camera", blank, *board_images[:2], "--rig", rig_path)
    assert too_few.code == 1 and "found in 2 of 3 images" in too_few.err
    assert "blank.png" in too_few.err
    missing = cli("calibrate-camera", tmp_path / "nope.png", "--rig", rig_path)
    assert missing.code == 2 and "nope.png: image not found" in missing.err
    assert rig_path.read_bytes() == before
    assert "Traceback" not in too_few.err + missing.err
    assert tomllib.loads(before.decode())  # still a valid file


def test_parse_board() -> None:
    assert parse_board("9x6") == (9, 6)
    assert parse_board(" 7 X 5 ") == (7, 5)
    with pytest.raises(UsageError):
        parse_board("1x6")


def test_mixed_image_sizes_are_refused() -> None:
    with pytest.raises(UsageError, match="differ in size"):
        calibrate([("a", np.zeros((10, 20), np.uint8)), ("b", np.zeros((20, 10), np.uint8))],
                  BOARD, SQUARE_M)
    with pytest.raises(StageError, match="found in 0 of 1"):
        calibrate([("a", np.zeros((48, 64), np.uint8))], BOARD, SQUARE_M)


def _tagged(board_images: list[Path], folder: Path, orientations: tuple[int, ...]
            ) -> list[Path]:
    """The boards as JPEGs with EXIF orientation tags (pixels as stored), cycling through
    ``orientations``."""
    from PIL import Image

    paths = []
    for k, png in enumerate(board_images):
        exif = Image.Exif()
        exif[0x0112] = orientations[k % len(orientations)]
        path = folder / f"{png.stem}.jpg"
        with Image.open(png) as image:
            image.save(path, quality=97, exif=exif)
        paths.append(path)
    return paths


def test_images_turned_differently_are_refused(cli, board_images: list[Path],
                                               tmp_path: Path) -> None:
    """A phone turned a half turn between shots keeps the size; upright, its lens's centre
    lands mirrored, and one fit over both averaged two centres without a word."""
    paths = _tagged(board_images, tmp_path, (1, 3))
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_to_toml(default_rig()))
    before = rig_path.read_bytes()
    result = cli("calibrate-camera", *paths, "--rig", rig_path, "--camera", "cam1")
    assert result.code == 2
    assert "taken with the camera turned differently (EXIF orientation 1 (as stored): " \
           "board00.jpg, board02.jpg, board04.jpg …; 3 (half turn): board01.jpg" in result.err
    assert result.err.count("\n") == 1 and rig_path.read_bytes() == before


def test_images_turned_alike_calibrate_the_upright_picture(cli, board_images: list[Path],
                                                           tmp_path: Path) -> None:
    """All shot with the phone upright (stored landscape, tagged 6): the intrinsics are for
    the upright picture, as import-video's frames are (the display rotation applied)."""
    paths = _tagged(board_images, tmp_path, (6,))
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_to_toml(default_rig()))
    result = cli("calibrate-camera", *paths, "--rig", rig_path, "--camera", "cam1")
    assert result.code == 0, result.err
    cam1 = load_rig(rig_path).camera("cam1")
    # orientation 6 turns the stored picture a quarter turn clockwise: x' = H − 1 − y, y' = x
    assert (cam1.width, cam1.height) == (480, 640)
    assert cam1.cx == pytest.approx(479 - TRUE.cy, abs=3.0)
    assert cam1.cy == pytest.approx(TRUE.cx, abs=3.0)
    assert cam1.fx == pytest.approx(TRUE.fy, rel=0.01)
    assert cam1.fy == pytest.approx(TRUE.fx, rel=0.01)
    assert "turned differently" not in result.err


def test_another_aspect_ratio_than_the_rigs_camera_is_warned(
        cli, board_images: list[Path], tmp_path: Path) -> None:
    """Photos (4:3) calibrating a camera that records 9:16 video: the intrinsics are for
    another crop of the sensor."""
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_to_toml(default_rig()))  # cam1: an upright phone, 1080 × 1920
    result = cli("calibrate-camera", *board_images, "--rig", rig_path, "--camera", "cam1")
    assert result.code == 0, result.err
    assert "the images are 640×480, camera cam1 was 1080×1920 in the rig (another aspect " \
           "ratio: a photo mode rather than the video mode?)" in result.err
    assert load_rig(rig_path).camera("cam1").width == 640
