"""Small files that claim huge images: what an image bomb looks like, made in milliseconds.

Shared by the chaos suite (``benchmarks/chaos.py``) and the image tests.

A black PNG compresses about 1000:1, and its deflate stream is one full-flush segment repeated
(a full flush drops the back-references), so a 40 000² PNG is written without ever holding or
compressing its 1.6 GB of pixels. The zlib checksum of zeros is known in closed form.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import trimesh
from PIL import Image

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def black_png(width: int, height: int, channels: int = 1) -> bytes:
    """A valid, fully decodable black PNG (grey or RGB) of ``width`` × ``height`` pixels."""
    row = bytes(1 + width * channels)  # filter byte 0 + black pixels
    rows_per_segment = max(1, min(height, (4 << 20) // len(row)))
    compressor = zlib.compressobj(9)
    stream = compressor.compress(row * rows_per_segment) + compressor.flush(zlib.Z_FULL_FLUSH)
    header, segment = stream[:2], stream[2:]
    count, rest = divmod(height, rows_per_segment)
    tail = zlib.compressobj(9)
    last = (tail.compress(row * rest) if rest else b"") + tail.flush(zlib.Z_FINISH)
    adler = ((len(row) * height) % 65521) << 16 | 1  # Adler-32 of zeros
    colour_type = {1: 0, 3: 2}[channels]
    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return b"".join([PNG_SIGNATURE, _chunk(b"IHDR", ihdr), _chunk(b"IDAT", header),
                     *[_chunk(b"IDAT", segment)] * count,
                     _chunk(b"IDAT", last[2:-4] + struct.pack(">I", adler)),
                     _chunk(b"IEND", b"")])


def jpeg_header(width: int, height: int) -> bytes:
    """A JPEG that is only a header claiming ``width`` × ``height`` (baseline, 3 channels)."""
    sof = struct.pack(">BHHB", 8, height, width, 3) + b"\x01\x11\x00\x02\x11\x00\x03\x11\x00"
    return b"\xff\xd8\xff\xc0" + struct.pack(">H", len(sof) + 2) + sof + b"\xff\xd9"


def obj_scene(folder: Path, texture: bytes, texture_name: str = "tex.png") -> Path:
    """A one-triangle OBJ + MTL whose ``map_Kd`` is ``texture``; returns the OBJ path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / texture_name).write_bytes(texture)
    (folder / "scene.mtl").write_text(f"newmtl m\nKd 1 1 1\nmap_Kd {texture_name}\n")
    obj = folder / "scene.obj"
    obj.write_text("mtllib scene.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
                   "usemtl m\nf 1/1 2/2 3/3\n")
    return obj


def glb_with_image(image: bytes, mime: str = "image/png") -> bytes:
    """A one-triangle GLB whose texture is ``image`` (any bytes), embedded in its BIN chunk."""
    mesh = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]],
                           process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [0, 1]],
                                                image=Image.new("RGB", (4, 4)))
    glb = mesh.export(file_type="glb")
    json_length = struct.unpack_from("<I", glb, 12)[0]
    tree = json.loads(glb[20:20 + json_length])
    bin_at = 20 + json_length
    binary = glb[bin_at + 8:bin_at + 8 + struct.unpack_from("<I", glb, bin_at)[0]]
    view = tree["images"][0]["bufferView"]
    tree["images"][0]["mimeType"] = mime
    tree["bufferViews"][view] = {"buffer": 0, "byteOffset": len(binary),
                                 "byteLength": len(image)}
    binary += image + b"\0" * (-len(image) % 4)
    tree["buffers"][0]["byteLength"] = len(binary)
    text = json.dumps(tree).encode()
    text += b" " * (-len(text) % 4)
    body = (struct.pack("<II", len(text), 0x4E4F534A) + text
            + struct.pack("<II", len(binary), 0x004E4942) + binary)
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body
