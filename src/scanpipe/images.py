"""Images: the one place that turns pixel arrays into JPEG and PNG bytes (OpenCV), and that
reads images with a limit in pixels checked from the header before anything is decoded.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
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


def encode_png(bgr: NDArray[Any], level: int = 1, fast: bool = False) -> bytes:
    """PNG bytes of a BGR (or grey) image at zlib compression ``level`` (0–9).

    ``fast``: the "up" row filter and run-length deflate instead of trying every filter per
    row; on photographic atlas pages 2–3× faster to encode and no larger (still lossless).
    """
    flags = [cv2.IMWRITE_PNG_COMPRESSION, int(level)]
    if fast and hasattr(cv2, "IMWRITE_PNG_FILTER"):  # OpenCV ≥ 4.11
        flags += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP,
                  cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    return _encode(".png", bgr, flags)


# ---------------------------------------------------------------------------------------------
# Reading: every image read checks its size in pixels from the header, before decoding
# ---------------------------------------------------------------------------------------------

#: Scene textures: the largest atlas page the texture stage writes (``page_size_px`` ≤ 8192).
#: Decoded as RGB that is 192 MiB; a 445 KB PNG can claim 40 000² (4.5 GiB).
MAX_TEXTURE_PX = 8192 * 8192
#: Camera frames (recordings, imported videos) and calibration images: 8K UHD, the largest
#: video mode of current cameras (95 MiB as BGR). Calibration images come from the camera that
#: records the frames, so they share the limit.
MAX_FRAME_PX = 7680 * 4320

_LIMIT_NAMES = {MAX_TEXTURE_PX: "8192×8192", MAX_FRAME_PX: "8K UHD, 7680×4320"}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Bytes of a file read to find its size; a JPEG's SOF may follow 64 KiB EXIF segments.
_HEADER_BYTES = 1 << 20


def image_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a JPEG's SOF segment or a PNG's IHDR; None if not found."""
    if data[:8] == _PNG_SIGNATURE and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            pos += 2
            continue
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 9 > len(data):
                return None
            height = int.from_bytes(data[pos + 5:pos + 7], "big")
            width = int.from_bytes(data[pos + 7:pos + 9], "big")
            return width, height
        if marker == 0xDA or length < 2:  # start of scan before any SOF: give up
            return None
        pos += 2 + length
    return None


def _pixels_text(width: int, height: int) -> str:
    return f"{width}×{height} px ({width * height / 1e6:.1f} Mpx)"


def limit_text(max_px: int) -> str:
    """A pixel limit for messages: ``33.2 Mpx (8K UHD, 7680×4320)``, the name when known."""
    name = _LIMIT_NAMES.get(max_px)
    return f"{max_px / 1e6:.1f} Mpx" + (f" ({name})" if name else "")


def probe_image(source: bytes | Path, what: str, max_px: int,
                error: type[ScanpipeError] = ScanpipeError) -> tuple[int, int]:
    """``(width, height)`` of an encoded image (bytes or a file) read from its header only;
    ``error`` naming ``what``, the size and ``max_px`` when it has more pixels than that.

    PNG and JPEG are parsed here; other formats go through Pillow, which reads only the header
    in ``Image.open``. Nothing is decoded, so a small file claiming a huge size costs nothing.
    """
    if isinstance(source, Path):
        try:
            with source.open("rb") as handle:
                head = handle.read(_HEADER_BYTES)
        except OSError as err:
            raise error(f"{what}: cannot read ({err.strerror or err})") from None
    else:
        head = source
    size = image_size(head)
    if size is None:
        size = _pillow_size(source, what, max_px, error)
    check_pixels(*size, what, max_px, error)
    return size


def check_pixels(width: int, height: int, what: str, max_px: int,
                 error: type[ScanpipeError] = ScanpipeError) -> None:
    """``error`` naming ``what``, its size and the limit when ``width × height`` is empty or
    more than ``max_px`` pixels (the one size check of every image read)."""
    if width <= 0 or height <= 0:
        raise error(f"{what}: the image header claims {width}×{height} px; not an image")
    if width * height > max_px:
        raise error(f"{what}: the image is {_pixels_text(width, height)}, more than the limit "
                    f"of {limit_text(max_px)} (decoded it would take "
                    f"{width * height * 3 / 2**20:.0f} MiB); downscale it")


def _pillow_size(source: bytes | Path, what: str, max_px: int,
                 error: type[ScanpipeError]) -> tuple[int, int]:
    """The size Pillow reads from a header (``Image.open`` does not decode)."""
    from PIL import Image

    stream = source if isinstance(source, Path) else io.BytesIO(source)
    try:
        with warnings.catch_warnings():  # our own limit decides, not Pillow's bomb warning
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(stream) as image:
                return int(image.width), int(image.height)
    except Image.DecompressionBombError:
        bomb_px = 2 * (Image.MAX_IMAGE_PIXELS or 0)
        raise error(f"{what}: the image has more than {bomb_px / 1e6:.0f} Mpx; the limit is "
                    f"{limit_text(max_px)}; downscale it") from None
    except (OSError, ValueError, SyntaxError) as err:  # Pillow's "cannot identify" and kin
        raise error(f"{what}: not a decodable image ({err})") from None


def decode_image_bytes(data: bytes, what: str, max_px: int = MAX_FRAME_PX,
                       flags: int = cv2.IMREAD_COLOR,
                       error: type[ScanpipeError] = ScanpipeError,
                       upright: bool = False) -> NDArray[np.uint8]:
    """Decode image bytes with OpenCV (``flags``: colour BGR, grey, reduced …) after checking
    the size in the header against ``max_px``; ``error`` naming ``what`` on any failure.

    The pixels come as stored: a JPEG's (or PNG's) EXIF orientation is ignored unless
    ``upright``. A recording's frames are a camera's pixels — their size in the frames table is
    the header's and the rig's intrinsics describe them — and OpenCV would otherwise turn a
    frame carrying an orientation tag (a half turn, or any turn of a square frame, keeps the
    size: nothing would say so). Photos read as files (:func:`read_image_file`) are upright."""
    probe_image(data, what, max_px, error)
    if not upright:
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as err:
        raise error(f"{what}: not a decodable image ({err.msg.strip()})") from None
    if image is None:
        raise error(f"{what}: not a decodable image")
    return np.asarray(image, dtype=np.uint8)


def read_image_file(path: Path, max_px: int = MAX_FRAME_PX, flags: int = cv2.IMREAD_COLOR,
                    error: type[ScanpipeError] = ScanpipeError) -> NDArray[np.uint8]:
    """Decode an image file (see :func:`decode_image_bytes`) upright: its EXIF orientation
    applied, as a viewer shows a photo (``calibrate-camera``'s images);
    ``error`` naming the file if it is missing, unreadable, not an image or larger than
    ``max_px``."""
    what = str(path)
    if not path.is_file():
        raise error(f"{what}: image not found")
    probe_image(path, what, max_px, error)  # before reading a large file whole
    try:
        data = path.read_bytes()
    except OSError as err:
        raise error(f"{what}: cannot read ({err.strerror or err})") from None
    return decode_image_bytes(data, what, max_px, flags, error, upright=True)
