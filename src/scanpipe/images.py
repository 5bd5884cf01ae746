"""Image encoding: the one place that turns pixel arrays into JPEG and PNG bytes (OpenCV)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import ScanpipeError


def _encode(extension: str, image: NDArray[Any], flags: list[int]) -> bytes:
    ok, buffer = cv2.imencode(extension, np.ascontiguousarray(image), flags)
    if not ok:
        raise ScanpipeError(f"OpenCV could not encode an image of shape {image.shape} as "
                            f"{extension.lstrip('.').upper()}")
    return bytes(buffer.tobytes())


def encode_jpeg(bgr: NDArray[Any], quality: int = 90) -> bytes:
    """JPEG bytes of a BGR (or grey) image."""
    return _encode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])


def encode_jpeg_rgb(rgb: NDArray[Any], quality: int = 90) -> bytes:
    """JPEG bytes of an RGB image."""
    return encode_jpeg(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), quality)


def encode_png(bgr: NDArray[Any], level: int = 1) -> bytes:
    """PNG bytes of a BGR (or grey) image at zlib compression ``level`` (0–9)."""
    return _encode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, int(level)])
