"""Frame bytes decode as stored, whatever their EXIF orientation says; photo files upright.

A recording's frames are a camera's pixels: its frames table gives their size from the JPEG
header (as stored) and the rig's intrinsics describe those pixels. OpenCV's ``imdecode``
turns a JPEG by its EXIF orientation unless told not to, so a frame another tool wrote with
an orientation tag was turned before texturing, colouring and self-calibration: a half turn
(or any turn of a square frame) keeps the size, and nothing said so. Calibration photos keep
the viewer's upright picture (``read_image_file``), as ``calibrate-camera`` documents.

The fixtures are Pillow's own test images (a 128 × 128 JPEG with orientation 3 and 6).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

from scanpipe.images import MAX_FRAME_PX, decode_image_bytes, read_image_file
from scanpipe.texturing.frames import decode_image

EXIF = Path(__file__).parent / "fixtures" / "exif"


def _pillow(path: Path, upright: bool) -> np.ndarray:
    with Image.open(path) as image:
        if upright:
            image = ImageOps.exif_transpose(image)
        return np.asarray(image.convert("RGB"))[:, :, ::-1].astype(np.int16)


@pytest.mark.parametrize("orientation", [3, 6])
def test_frame_bytes_decode_as_stored(orientation: int) -> None:
    path = EXIF / f"hopper_orientation_{orientation}.jpg"
    with Image.open(path) as image:
        assert image.getexif().get(0x0112) == orientation  # the tag is there
    stored, upright = _pillow(path, False), _pillow(path, True)
    assert stored.shape == upright.shape == (128, 128, 3)  # square: a turn keeps the size
    assert np.abs(stored - upright).mean() > 20  # … but not the pixels
    for decoded in (decode_image_bytes(path.read_bytes(), "frame"),
                    decode_image(path.read_bytes(), "frame 0 of 'cam0'")):
        error = np.abs(decoded.astype(np.int16) - stored).mean()
        assert error < 2.0, f"decoded {error:.1f} grey levels from the stored pixels"
    # the reduced decodes (colour samples, sharpness) too
    reduced = decode_image_bytes(path.read_bytes(), "frame", MAX_FRAME_PX,
                                 cv2.IMREAD_REDUCED_COLOR_4)
    small = cv2.resize(stored.astype(np.uint8), (32, 32), interpolation=cv2.INTER_AREA)
    assert np.abs(reduced.astype(np.int16) - small).mean() < 4.0


@pytest.mark.parametrize("orientation", [3, 6])
def test_photo_files_read_upright(orientation: int) -> None:
    path = EXIF / f"hopper_orientation_{orientation}.jpg"
    grey = read_image_file(path, MAX_FRAME_PX, cv2.IMREAD_GRAYSCALE)
    upright = cv2.cvtColor(_pillow(path, True).astype(np.uint8), cv2.COLOR_BGR2GRAY)
    assert np.abs(grey.astype(np.int16) - upright).mean() < 2.0
