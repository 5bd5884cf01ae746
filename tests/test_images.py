"""Image bombs: every image read checks its size in pixels from the header, before decoding.

Scene textures, camera frames of recordings, calibration images and imported videos; the
hostile files are a few hundred KB claiming 16 000² to 65 000² pixels (hostile_images.py).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from benchmarks.hostile import black_png, glb_with_image, jpeg_header, obj_scene
from scanpipe.errors import ScanpipeError, SimulationError, StageError, UsageError
from scanpipe.images import (
    MAX_FRAME_PX,
    MAX_TEXTURE_PX,
    decode_image_bytes,
    image_size,
    probe_image,
    read_image_file,
)
from scanpipe.sim.scene import load_scene
from scanpipe.texturing.frames import decode_image, sharpness_of

SRC = Path(__file__).resolve().parents[1] / "src"
TESTS = Path(__file__).resolve().parent
#: What loading or refusing one hostile image may add to the peak memory of a process.
PEAK_BOUND_MB = 300


def test_hostile_png_is_valid_and_small() -> None:
    small = black_png(300, 200, channels=3)
    decoded = cv2.imdecode(np.frombuffer(small, np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded.shape == (200, 300, 3) and decoded.max() == 0
    big = black_png(16_000, 16_000)
    assert len(big) < 400_000 and image_size(big) == (16_000, 16_000)


def test_sizes_come_from_the_header(tmp_path: Path) -> None:
    assert image_size(jpeg_header(65_000, 64_000)) == (65_000, 64_000)
    assert image_size(black_png(7, 5)) == (7, 5)
    assert image_size(b"\x89PNG\r\n\x1a\n" + bytes(16)) is None  # no IHDR
    webp = tmp_path / "a.webp"
    Image.new("RGB", (33, 21)).save(webp)  # not PNG/JPEG: Pillow reads the header
    assert probe_image(webp, "a.webp", 1000) == (33, 21)
    assert probe_image(webp.read_bytes(), "a.webp", 1000) == (33, 21)
    with pytest.raises(UsageError, match=r"^x: the image is 33×21 px \(0.0 Mpx\), more than the "
                       r"limit of 0.0 Mpx .*downscale it$"):
        probe_image(webp, "x", 100, UsageError)
    with pytest.raises(ScanpipeError, match=r"^junk: not a decodable image"):
        probe_image(b"no image here", "junk", 1000)
    with pytest.raises(ScanpipeError, match="claims 0×5 px"):
        probe_image(black_png(7, 5)[:16] + (0).to_bytes(4, "big") + (5).to_bytes(4, "big"),
                    "zero", 1000)


def test_pillow_bomb_error_is_wrapped() -> None:
    """A format only Pillow reads, beyond Pillow's own bomb limit: one line, no traceback."""
    import io

    buffer = io.BytesIO()
    Image.new("1", (8, 8)).save(buffer, format="BMP")
    data = bytearray(buffer.getvalue())
    data[18:26] = (40_000).to_bytes(4, "little") + (40_000).to_bytes(4, "little")
    with pytest.raises(StageError, match=r"^bmp: the image has more than 179 Mpx; the limit"):
        probe_image(bytes(data), "bmp", MAX_FRAME_PX, StageError)


@pytest.mark.parametrize("side", [12_000, 16_000, 40_000])
def test_scene_texture_over_the_limit_is_an_error(tmp_path: Path, side: int) -> None:
    obj = obj_scene(tmp_path / "obj", black_png(side, side))
    with pytest.raises(SimulationError) as err:
        load_scene(obj)
    assert str(err.value) == (
        f"{obj}: texture 'tex.png': the image is {side}×{side} px ({side * side / 1e6:.1f} "
        f"Mpx), more than the limit of 67.1 Mpx (8192×8192) (decoded it would take "
        f"{side * side * 3 / 2**20:.0f} MiB); downscale it")
    glb = tmp_path / "scene.glb"
    glb.write_bytes(glb_with_image(black_png(side, side)))
    with pytest.raises(SimulationError, match=rf"scene.glb: texture '#0': the image is "
                       rf"{side}×{side} px"):
        load_scene(glb)


def test_scene_texture_limit_is_a_parameter(tmp_path: Path) -> None:
    obj = obj_scene(tmp_path / "obj", black_png(64, 32, channels=3))
    assert load_scene(obj).textures[0].shape == (32, 64, 3)
    with pytest.raises(SimulationError, match=r"64×32 px .* more than the limit of 0.0 Mpx"):
        load_scene(obj, max_texture_px=2000)
    with pytest.raises(SimulationError, match="max_texture_px 1000000000: allowed 1 to"):
        load_scene(obj, max_texture_px=10**9)
    glb = tmp_path / "jpeg.glb"
    glb.write_bytes(glb_with_image(jpeg_header(65_000, 65_000), "image/jpeg"))
    with pytest.raises(SimulationError, match="65000×65000 px"):
        load_scene(glb)
    assert MAX_TEXTURE_PX == 8192 * 8192


def test_material_file_of_any_name_is_not_taken_for_a_texture(tmp_path: Path) -> None:
    obj = obj_scene(tmp_path / "obj", black_png(16, 8, channels=3))
    (obj.parent / "scene.mtl").rename(obj.parent / "materials.txt")
    obj.write_text(obj.read_text().replace("mtllib scene.mtl", "mtllib materials.txt"))
    assert load_scene(obj).textures[0].shape == (8, 16, 3)


def test_unreadable_texture_is_an_error_not_dropped(tmp_path: Path) -> None:
    obj = obj_scene(tmp_path / "obj", b"this is not an image")
    with pytest.raises(SimulationError, match=r"texture 'tex.png': not a decodable image"):
        load_scene(obj)


def test_hostile_camera_frames_are_stage_errors() -> None:
    for data, size in ((black_png(16_000, 16_000), "16000×16000"),
                       (jpeg_header(65_000, 65_000), "65000×65000"),
                       (black_png(7681, 4320, channels=3), "7681×4320")):
        with pytest.raises(StageError, match=rf"^frames: frame 3 of 'cam0': the image is {size} "
                           r"px .* limit of 33.2 Mpx \(8K UHD, 7680×4320\)"):
            decode_image(data, "frame 3 of 'cam0'")
        with pytest.raises(StageError, match=f"the image is {size} px"):
            sharpness_of(data, "frame 3 of 'cam0'")
    truncated = black_png(64, 48)[:60]
    with pytest.raises(StageError, match=r"^frames: f: not a decodable image$"):
        decode_image(truncated, "f")
    ok = decode_image_bytes(black_png(64, 48, channels=3), "ok", MAX_FRAME_PX)
    assert ok.shape == (48, 64, 3)


def test_hostile_calibration_image_is_refused_by_the_cli(cli, tmp_path: Path) -> None:
    from scanpipe.rig import default_rig, rig_to_toml

    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(rig_to_toml(default_rig()))
    before = rig_path.read_bytes()
    bomb = tmp_path / "board.png"
    bomb.write_bytes(black_png(40_000, 40_000))
    result = cli("calibrate-camera", bomb, "--rig", rig_path)
    assert result.code == 2
    assert result.err.strip().splitlines() == [
        f"scanpipe: error: {bomb}: the image is 40000×40000 px (1600.0 Mpx), more than the limit "
        "of 33.2 Mpx (8K UHD, 7680×4320) (decoded it would take 4578 MiB); downscale it"]
    assert rig_path.read_bytes() == before
    with pytest.raises(UsageError, match="not a decodable image"):
        read_image_file(rig_path, error=UsageError)


_MEASURE = r"""
import json, resource, sys
from pathlib import Path
resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30))  # a regression must not eat the host
import cv2, numpy, trimesh, PIL.Image  # imported before the baseline
from scanpipe.calibration import read_images
from scanpipe.errors import ScanpipeError
from scanpipe.sim.scene import load_scene
from scanpipe.texturing.frames import decode_image, sharpness_of

def peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

results = {}
for kind, path in json.loads(sys.argv[1]):
    base = peak_mb()
    try:
        if kind == "scene":
            load_scene(path)
        elif kind == "frame":
            decode_image(Path(path).read_bytes(), path)
        elif kind == "sharpness":
            sharpness_of(Path(path).read_bytes(), path)
        else:
            read_images([Path(path)])
        outcome = "loaded"
    except ScanpipeError as err:
        outcome = str(err)
    results[f"{kind} {Path(path).parent.name}/{Path(path).name}"] = [peak_mb() - base, outcome]
print(json.dumps(results))
"""


def test_peak_memory_of_hostile_images_is_bounded(tmp_path: Path) -> None:
    """Refusing a hostile image costs its header: peak RSS growth in a fresh process."""
    files = {"png16000.png": black_png(16_000, 16_000, channels=3),
             "png40000.png": black_png(40_000, 40_000),
             "jpeg65000.jpg": jpeg_header(65_000, 65_000)}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    cases = []
    for name in files:
        obj = obj_scene(tmp_path / f"obj_{Path(name).stem}", files[name], name)
        glb = tmp_path / f"{Path(name).stem}.glb"
        glb.write_bytes(glb_with_image(files[name], "image/jpeg" if "jpeg" in name
                                       else "image/png"))
        cases += [("scene", str(obj)), ("scene", str(glb)), ("frame", str(tmp_path / name)),
                  ("sharpness", str(tmp_path / name)), ("calibration", str(tmp_path / name))]
    run = subprocess.run([sys.executable, "-c", _MEASURE, json.dumps(cases)],
                         capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": f"{SRC}:{TESTS}", "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr
    results = json.loads(run.stdout)
    assert len(results) == len(cases)
    for case, (growth_mb, outcome) in results.items():
        assert growth_mb < PEAK_BOUND_MB, (case, growth_mb)
        assert "the image is" in outcome and "more than the limit" in outcome, (case, outcome)


def test_texture_page_bomb_is_an_export_error() -> None:
    """Texture pages read back from artifacts (PLY colours, previews) are held to the limit."""
    from scanpipe.errors import ExportError
    from scanpipe.exporters.ply import decode_png

    with pytest.raises(ExportError, match=r"^texture page 0: the image is 40000×40000 px"):
        decode_png(black_png(40_000, 40_000), "texture page 0")
    assert decode_png(black_png(8, 4, channels=3), "page").shape == (4, 8, 3)


def test_imported_video_over_the_limit_leaves_the_recording_untouched(
        cli, tmp_path: Path) -> None:
    from acquire_helpers import rig_with_cameras, small_camera, write_video

    from scanpipe.recording.writer import RecordingWriter

    rec = tmp_path / "rec.mcap"
    with RecordingWriter(rec, rig_with_cameras(small_camera("phone")), {"mode": "step"}) as w:
        w.write_motor_state(1_767_225_600_000_000_000, 0, 0, False, 0)
    before = rec.read_bytes()
    video = write_video(tmp_path / "big.avi", frames=1, size=(7696, 4320))  # just over 8K UHD
    result = cli("import-video", video, "--into", rec, "--start-time", "recording",
                 "--camera", "phone")
    assert result.code == 2
    assert result.err.strip().splitlines() == [
        f"scanpipe: error: {video}: the image is 7696×4320 px (33.2 Mpx), more than the limit of "
        "33.2 Mpx (8K UHD, 7680×4320) (decoded it would take 95 MiB); downscale it"]
    assert rec.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.avi", "rec.mcap"]
