"""The ground-truth scene: a textured triangle mesh in metres, in the rig frame (y up).

A :class:`Scene` holds triangles with per-corner texture coordinates (glTF convention: v = 0 at
the image top) and one RGB texture image per material. Rays are cast with Open3D's
``RaycastingScene``; the colour of a hit comes from its triangle and barycentric coordinates.
"""

from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import Image

from scanpipe.errors import SimulationError
from scanpipe.geometry import rotation_matrix_deg
from scanpipe.images import MAX_TEXTURE_PX, check_pixels, limit_text, probe_image
from scanpipe.rig import Pose

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]

#: Open3D's marker for "no triangle hit".
_INVALID_ID = 4294967295


@dataclass(frozen=True)
class RayHits:
    """What a batch of rays hit: distance (inf = miss), triangle (−1 = miss), barycentrics
    ``(u, v)`` (the hit is ``(1−u−v)·p0 + u·p1 + v·p2``) and the triangle's unit normal."""

    t_hit_m: F64
    triangle_id: I64
    barycentric: F32
    normal: F32

    @property
    def hit(self) -> NDArray[np.bool_]:
        """True where the ray hit a triangle."""
        return self.triangle_id >= 0


@dataclass
class Scene:
    """A textured triangle mesh in metres (rig frame, y up)."""

    vertices: F64
    triangles: NDArray[np.int32]
    triangle_uvs: F32
    triangle_material: NDArray[np.int32]
    textures: list[U8]
    material_names: list[str] = field(default_factory=list)
    #: What the loader could not use (dropped faces, textures not found …), one line each.
    warnings: list[str] = field(default_factory=list, compare=False)
    _raycaster: Any = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int32).reshape(-1, 3)
        self.triangle_uvs = np.asarray(self.triangle_uvs, dtype=np.float32).reshape(-1, 3, 2)
        self.triangle_material = np.asarray(self.triangle_material, dtype=np.int32).reshape(-1)
        n = len(self.triangles)
        if len(self.triangle_uvs) != n or len(self.triangle_material) != n:
            raise SimulationError(
                f"scene: {n} triangles but {len(self.triangle_uvs)} uv triples and "
                f"{len(self.triangle_material)} material ids; they must match"
            )
        if n == 0:
            raise SimulationError("scene: has no triangles")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices):
            raise SimulationError("scene: a triangle refers to a vertex that does not exist")
        if self.triangle_material.min() < 0 or self.triangle_material.max() >= len(self.textures):
            raise SimulationError("scene: a triangle refers to a material that does not exist")
        if not self.material_names:
            self.material_names = [f"material_{i}" for i in range(len(self.textures))]

    # -- geometry ------------------------------------------------------------------------
    @property
    def bounds(self) -> F64:
        """``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def _scene(self) -> Any:
        if self._raycaster is None:
            import open3d as o3d

            raycaster = o3d.t.geometry.RaycastingScene()
            raycaster.add_triangles(
                o3d.core.Tensor(self.vertices.astype(np.float32)),  # type: ignore[call-overload]
                o3d.core.Tensor(self.triangles.astype(np.uint32)),  # type: ignore[call-overload]
            )
            self._raycaster = raycaster
        return self._raycaster

    def cast(self, origins: ArrayLike, directions: ArrayLike) -> RayHits:
        """Cast rays (``origins`` (N, 3) or (3,), unit ``directions`` (N, 3)) in one call."""
        import open3d as o3d

        directions_arr = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
        origins_arr = np.broadcast_to(
            np.asarray(origins, dtype=np.float32), directions_arr.shape
        )
        rays = np.concatenate([origins_arr, directions_arr], axis=1)
        answer = self._scene().cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
        ids = answer["primitive_ids"].numpy().astype(np.int64)
        ids[ids == _INVALID_ID] = -1
        return RayHits(
            t_hit_m=answer["t_hit"].numpy().astype(np.float64),
            triangle_id=ids,
            barycentric=answer["primitive_uvs"].numpy(),
            normal=answer["primitive_normals"].numpy(),
        )

    def distance_m(self, points: ArrayLike) -> F64:
        """Unsigned distance from each point (N, 3) to the nearest surface."""
        import open3d as o3d

        query = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        result = self._scene().compute_distance(
            o3d.core.Tensor(query))  # type: ignore[call-overload]
        return np.asarray(result.numpy(), dtype=np.float64)

    def triangle_areas(self) -> F64:
        """Area of every triangle in m²."""
        p = self.vertices[self.triangles]
        return np.asarray(
            0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1),
            dtype=np.float64,
        )

    def sample_surface(self, n: int, seed: int = 0) -> F64:
        """``n`` points spread uniformly over the surface (area-weighted), deterministic."""
        rng = np.random.default_rng(seed)
        areas = self.triangle_areas()
        tri = rng.choice(len(areas), size=n, p=areas / areas.sum())
        a, b = rng.random(n), rng.random(n)
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        p = self.vertices[self.triangles[tri]]
        return np.asarray(
            p[:, 0] + a[:, None] * (p[:, 1] - p[:, 0]) + b[:, None] * (p[:, 2] - p[:, 0]),
            dtype=np.float64,
        )

    # -- texture -------------------------------------------------------------------------
    def uv_at(self, triangle_id: ArrayLike, barycentric: ArrayLike) -> F32:
        """Texture coordinates (glTF: v = 0 at the image top) of hits; NaN for misses."""
        ids = np.asarray(triangle_id, dtype=np.int64)
        bary = np.asarray(barycentric, dtype=np.float32).reshape(-1, 2)
        hit = ids >= 0
        corners = self.triangle_uvs[np.where(hit, ids, 0)]
        w1, w2 = bary[:, :1], bary[:, 1:]
        uv = (1 - w1 - w2) * corners[:, 0] + w1 * corners[:, 1] + w2 * corners[:, 2]
        uv[~hit] = np.nan
        return np.asarray(uv, dtype=np.float32)

    def color_at(self, triangle_id: ArrayLike, barycentric: ArrayLike,
                 miss_rgb: tuple[int, int, int] = (0, 0, 0)) -> U8:
        """RGB (N, 3) uint8 of the texture at each hit (nearest texel, wrapped); misses get
        ``miss_rgb``."""
        ids = np.asarray(triangle_id, dtype=np.int64)
        uv = self.uv_at(ids, barycentric)
        hit = ids >= 0
        colors = np.empty((len(ids), 3), dtype=np.uint8)
        colors[:] = miss_rgb
        materials = self.triangle_material[ids[hit]]
        uv_hit = uv[hit]
        out = np.empty((int(hit.sum()), 3), dtype=np.uint8)
        for m in np.unique(materials):
            sel = materials == m
            image = self.textures[int(m)]
            h, w = image.shape[:2]
            cols = np.floor(np.mod(uv_hit[sel, 0], 1.0) * w).astype(np.int64).clip(0, w - 1)
            rows = np.floor(np.mod(uv_hit[sel, 1], 1.0) * h).astype(np.int64).clip(0, h - 1)
            out[sel] = image[rows, cols]
        colors[hit] = out
        return colors

    # -- export --------------------------------------------------------------------------
    def to_trimesh(self) -> Any:
        """A ``trimesh.Scene`` with one textured mesh per material (for GLB and OBJ export)."""
        import trimesh

        scene = trimesh.Scene()
        for m, image in enumerate(self.textures):
            faces = np.flatnonzero(self.triangle_material == m)
            if len(faces) == 0:
                continue
            corners = self.triangles[faces].reshape(-1)
            uv = self.triangle_uvs[faces].reshape(-1, 2).astype(np.float64).copy()
            uv[:, 1] = 1.0 - uv[:, 1]  # trimesh uses the OBJ convention (v = 0 at the bottom)
            texture = Image.fromarray(image)
            texture.__class__ = _FastPngImage
            material = trimesh.visual.material.SimpleMaterial(  # type: ignore[no-untyped-call]
                image=texture)
            mesh = trimesh.Trimesh(
                vertices=self.vertices[corners],
                faces=np.arange(len(corners)).reshape(-1, 3),
                visual=trimesh.visual.TextureVisuals(  # type: ignore[no-untyped-call]
                    uv=uv, material=material),
                process=False,
            )
            scene.add_geometry(mesh, geom_name=self.material_names[m])
        return scene

    def save_glb(self, path: Path | str) -> None:
        """Write the scene with its textures as binary glTF (readable by trimesh, viewers)."""
        path = Path(path)
        try:
            data = self.to_trimesh().export(file_type="glb")
            path.write_bytes(data)
        except OSError as err:
            raise SimulationError(f"{path}: cannot write the scene: {err}") from err


class _FastPngImage(Image.Image):
    """A PIL image that saves PNG with fast compression: the glTF exporter always writes PNG,
    and zlib's default level makes writing the truth scene several times slower."""

    def save(self, fp: Any, format: Any = None, **params: Any) -> None:
        params.setdefault("compress_level", 1)
        super().save(fp, format, **params)


# ---------------------------------------------------------------------------------------------
# Loading user scenes
# ---------------------------------------------------------------------------------------------

def _rgb_array(image: Image.Image, rows_per_strip: int = 512) -> U8:
    """An RGB array of a Pillow image, converted strip by strip: ``np.asarray(image)`` goes
    through ``tobytes`` and ``convert`` copies the whole image, each a second full copy."""
    width, height = image.size
    out = np.empty((height, width, 3), dtype=np.uint8)
    for top in range(0, height, rows_per_strip):
        strip = image.crop((0, top, width, min(height, top + rows_per_strip)))
        out[top:top + strip.height] = np.asarray(strip.convert("RGB"), dtype=np.uint8)
    return out


def _material_image(visual: Any, what: str, max_texture_px: int) -> U8:
    """The RGB texture of a trimesh visual, or a small uniform image of its colour.

    The size is checked before the pixels are touched (trimesh opens OBJ textures lazily).
    """
    material = getattr(visual, "material", None)
    image = None
    if material is not None:
        image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    if image is not None:
        check_pixels(image.width, image.height, f"{what}: texture", max_texture_px,
                     SimulationError)
        return _rgb_array(image)
    color = None
    if material is not None:
        color = getattr(material, "baseColorFactor", None)
        if color is None:
            color = getattr(material, "diffuse", None)
    if color is None and hasattr(visual, "face_colors"):
        color = np.asarray(visual.face_colors).reshape(-1, 4)[0]
    rgb_value = np.asarray(color if color is not None else (200, 200, 200), dtype=np.float64)
    rgb_value = rgb_value[:3] * (255 if rgb_value[:3].max() <= 1.0 else 1)
    return np.full((4, 4, 3), np.clip(rgb_value, 0, 255).astype(np.uint8), dtype=np.uint8)


def _placed_meshes(loaded: Any) -> list[tuple[Any, F64, str | None]]:
    """``(geometry, 4×4 transform, name)`` of every instance in a trimesh scene, or the one mesh.

    Unlike ``Scene.dump`` nothing is copied: a copy of a material copies its texture, and
    Pillow decodes an image to copy it.
    """
    import trimesh

    if not isinstance(loaded, trimesh.Scene):
        return [(loaded, np.eye(4), None)]
    placed: list[tuple[Any, F64, str | None]] = []
    for node in loaded.graph.nodes_geometry:
        transform, geometry_name = loaded.graph[node]
        placed.append((loaded.geometry[geometry_name], np.asarray(transform, dtype=np.float64),
                       str(geometry_name)))
    return placed


def scene_from_trimesh(loaded: Any, source: str = "scene",
                       max_texture_px: int = MAX_TEXTURE_PX) -> Scene:
    """Convert a ``trimesh.Scene`` or ``Trimesh`` (textured or not) into a :class:`Scene`;
    :class:`SimulationError` for a texture of more than ``max_texture_px`` pixels."""
    import trimesh

    meshes = _placed_meshes(loaded)
    vertices: list[F64] = []
    triangles: list[NDArray[np.int64]] = []
    uvs: list[F64] = []
    materials: list[NDArray[np.int32]] = []
    textures: list[U8] = []
    names: list[str] = []
    offset = 0
    skipped: list[str] = []
    for index, (mesh, transform, placed_name) in enumerate(meshes):
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            skipped.append(f"{placed_name or index!s} ({type(mesh).__name__})")
            continue
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if np.linalg.det(transform[:3, :3]) < 0:  # a mirroring node turns the faces inside out
            faces = faces[:, ::-1]
        visual = mesh.visual
        vertex_uv = getattr(visual, "uv", None)
        if vertex_uv is not None and len(vertex_uv) == len(mesh.vertices):
            tri_uv = np.asarray(vertex_uv, dtype=np.float64)[faces].copy()
            tri_uv[..., 1] = 1.0 - tri_uv[..., 1]  # to the glTF convention
        else:
            tri_uv = np.full((len(faces), 3, 2), 0.5)
        corners = np.asarray(mesh.vertices, dtype=np.float64)
        vertices.append(corners @ transform[:3, :3].T + transform[:3, 3])
        triangles.append(faces + offset)
        uvs.append(tri_uv)
        materials.append(np.full(len(faces), len(textures), dtype=np.int32))
        name = placed_name or str(mesh.metadata.get("name", f"mesh_{index}"))
        textures.append(_material_image(visual, f"{source}: mesh {name!r}", max_texture_px))
        names.append(name)
        offset += len(mesh.vertices)
    if not triangles:
        raise SimulationError(f"{source}: contains no triangles")
    scene = Scene(np.concatenate(vertices), np.concatenate(triangles), np.concatenate(uvs),
                  np.concatenate(materials), textures, names)
    if skipped:
        scene.warnings.append(f"{source}: {len(skipped)} geometries without triangles dropped "
                              f"(lines or points): {', '.join(skipped[:5])}"
                              + (" …" if len(skipped) > 5 else ""))
    return scene


def _glb_chunks(data: bytes, path: Path) -> tuple[dict[str, Any], bytes]:
    """The JSON and BIN chunks of a binary glTF."""
    magic, _, length = struct.unpack_from("<4sII", data)
    if magic != b"glTF" or length > len(data):
        raise SimulationError(f"{path}: not a binary glTF (bad header)")
    json_length = struct.unpack_from("<I", data, 12)[0]
    tree = json.loads(data[20:20 + json_length])
    binary = b""
    at = 20 + json_length
    if at + 8 <= len(data):
        bin_length, _ = struct.unpack_from("<II", data, at)
        binary = data[at + 8:at + 8 + bin_length]
    return tree, binary


def _check_gltf_images(path: Path, max_texture_px: int) -> None:
    """Check every image of a glTF/GLB (embedded, base64 or beside it) from its header.

    trimesh decodes glTF images while loading, so this runs before it.
    """
    import trimesh

    resolver = trimesh.resolvers.FilePathResolver(str(path))
    try:
        data = path.read_bytes()
        if path.suffix.lower() == ".glb":
            tree, binary = _glb_chunks(data, path)
        else:
            tree, binary = json.loads(data), b""

        def uri_bytes(uri: str) -> bytes:
            marker = uri.find("base64,")
            if marker >= 0:
                return base64.b64decode(uri[marker + 7:])
            return bytes(resolver.get(uri))

        buffers = [uri_bytes(b["uri"]) if "uri" in b else binary
                   for b in tree.get("buffers", [])]
        for i, image in enumerate(tree.get("images", [])):
            label = image.get("name") or image.get("uri", "")[:60] or f"#{i}"
            what = f"{path}: texture {label!r}"
            if "bufferView" in image:
                view = tree["bufferViews"][image["bufferView"]]
                start = int(view.get("byteOffset", 0))
                blob = buffers[view["buffer"]][start:start + int(view["byteLength"])]
            elif "uri" in image:
                blob = uri_bytes(image["uri"])
            else:
                continue
            if image.get("mimeType") != "image/ktx2":  # trimesh skips KTX2
                probe_image(blob, what, max_texture_px, SimulationError)
    except SimulationError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError, struct.error) as err:
        raise SimulationError(f"{path}: cannot read the scene's images "
                              f"({type(err).__name__}: {err})") from None


# ---------------------------------------------------------------------------------------------
# OBJ / MTL
# ---------------------------------------------------------------------------------------------

#: Options of an MTL texture statement (``map_Kd -s 2 2 1 -o 0 0 0 file.png``) and how many
#: values each takes; ``-s``/``-o`` take 1 to 3 numbers.
_MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1,
                "-imfchan": 1, "-mm": 2, "-texres": 1, "-type": 1, "-s": 3, "-o": 3, "-t": 3}
#: The colour of faces without a material (grey, as most viewers draw them).
_DEFAULT_RGB = (200, 200, 200)


@dataclass
class _Material:
    """One MTL material: diffuse colour, texture file (None: none or not found), uv scale and
    offset of ``map_Kd``."""

    kd_rgb: tuple[float, float, float] = (_DEFAULT_RGB[0] / 255, _DEFAULT_RGB[1] / 255,
                                          _DEFAULT_RGB[2] / 255)
    texture: Path | None = None
    texture_name: str = ""
    uv_scale: tuple[float, float] = (1.0, 1.0)
    uv_offset: tuple[float, float] = (0.0, 0.0)


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _split_map_statement(args: list[str]) -> tuple[dict[str, list[float]], str]:
    """The options (``-s``, ``-o`` …) and the file name of an MTL ``map_*`` statement (the
    name is the rest of the line: it may contain spaces)."""
    options: dict[str, list[float]] = {}
    i = 0
    while i < len(args) and args[i].lower() in _MAP_OPTIONS:
        flag = args[i].lower()
        count = _MAP_OPTIONS[flag]
        values = args[i + 1:i + 1 + count]
        if flag in ("-s", "-o", "-t", "-mm"):  # numbers only, 1 to 3 of them
            taken = 0
            while taken < len(values) and _is_number(values[taken]):
                taken += 1
            values = values[:taken]
            options[flag] = [float(v) for v in values]
        i += 1 + len(values)
    return options, " ".join(args[i:])


def _find_texture(name: str, mtl_dir: Path) -> Path | None:
    """The image file an MTL names: as written (absolute or relative to the MTL's folder), with
    Windows separators turned round, else its bare name beside the MTL (files copied from
    another machine keep an absolute path that does not exist here)."""
    name = name.strip().strip('"')
    if not name:
        return None
    unix = name.replace("\\", "/")
    candidates = [Path(unix)] if Path(unix).is_absolute() else []
    candidates += [mtl_dir / unix, mtl_dir / Path(unix).name]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


def _read_mtl(path: Path, warnings: list[str]) -> dict[str, _Material]:
    """The materials of an MTL file; a texture that cannot be found is a warning."""
    materials: dict[str, _Material] = {}
    current: _Material | None = None
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        warnings.append(f"{path}: material library cannot be read ({err.strerror or err}); "
                        "its faces are grey")
        return materials
    for number, raw in enumerate(text.splitlines(), 1):
        fields = raw.split("#", 1)[0].split() if not raw.lstrip().startswith("map") else \
            raw.split()
        if not fields:
            continue
        head = fields[0].lower()
        if head == "newmtl":
            current = materials.setdefault(" ".join(fields[1:]), _Material())
        elif current is None:
            continue
        elif head == "kd" and len(fields) >= 4 and all(_is_number(f) for f in fields[1:4]):
            r, g, b = (float(f) for f in fields[1:4])
            current.kd_rgb = (r, g, b)
        elif head == "map_kd":
            options, name = _split_map_statement(fields[1:])
            found = _find_texture(name, path.parent)
            if found is None:
                warnings.append(f"{path} line {number}: texture {name!r} not found (looked "
                                f"beside the MTL in {path.parent}); its faces get the flat "
                                "colour Kd")
            current.texture, current.texture_name = found, name
            scale = options.get("-s", [1.0, 1.0])
            offset = options.get("-o", [0.0, 0.0])
            current.uv_scale = (scale[0], scale[1] if len(scale) > 1 else 1.0)
            current.uv_offset = (offset[0], offset[1] if len(offset) > 1 else 0.0)
    return materials


def _float_rows(rows: list[list[str]], width: int, what: str, path: Path) -> F64:
    """The first ``width`` numbers of each row as an (N, width) array."""
    if not rows:
        return np.zeros((0, width))
    try:
        return np.array([row[:width] for row in rows], dtype=np.float64).reshape(-1, width)
    except ValueError as err:
        raise SimulationError(f"{path}: a {what} line has fewer than {width} numbers or a word "
                              f"that is not a number ({err})") from None


def read_obj(path: Path, max_texture_px: int = MAX_TEXTURE_PX) -> Scene:
    """Read a Wavefront OBJ (+MTL + images) into a :class:`Scene`, following the format as
    other tools write it: fields split by any whitespace (tabs, several spaces), negative
    (relative) indices, ``v``, ``v/vt``, ``v//vn`` and ``v/vt/vn`` corners, polygons
    (fan-triangulated), texture paths relative to the MTL's folder, absolute or Windows-style,
    ``map_Kd`` options (``-s``/``-o`` scale and offset the uv).

    What cannot be used is kept in ``Scene.warnings``: lines and points, faces of fewer than
    three corners, degenerate triangles, a missing MTL, textures not found, unknown materials.
    """
    text = path.read_text(encoding="utf-8", errors="replace")
    v_rows: list[list[str]] = []
    vt_rows: list[list[str]] = []
    counts = {"v": 0, "vt": 0, "vn": 0}
    corners_v: list[int] = []
    corners_vt: list[int] = []
    face_sizes: list[int] = []
    face_material: list[str] = []
    libraries: list[str] = []
    material = ""
    dropped = {"lines (l)": 0, "points (p)": 0, "faces of fewer than 3 corners": 0,
               "curves and surfaces": 0}
    for number, raw in enumerate(text.splitlines(), 1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        head = fields[0]
        if head == "v":
            v_rows.append(fields[1:4])
            counts["v"] += 1
        elif head == "vt":
            vt_rows.append([*fields[1:3], "0"][:2])
            counts["vt"] += 1
        elif head == "vn":
            counts["vn"] += 1
        elif head == "f":
            tokens = fields[1:]
            if len(tokens) < 3:
                dropped["faces of fewer than 3 corners"] += 1
                continue
            for token in tokens:
                parts = token.split("/")
                try:
                    vi = int(parts[0])
                    ti = int(parts[1]) if len(parts) > 1 and parts[1] else 0
                except ValueError:
                    raise SimulationError(f"{path} line {number}: cannot read face corner "
                                          f"{token!r} (allowed: v, v/vt, v//vn, v/vt/vn)"
                                          ) from None
                vi = vi - 1 if vi > 0 else counts["v"] + vi
                ti = ti - 1 if ti > 0 else (counts["vt"] + ti if ti < 0 else -1)
                if not 0 <= vi < counts["v"]:
                    raise SimulationError(f"{path} line {number}: face corner {token!r} refers "
                                          "to a vertex that is not defined (there are "
                                          f"{counts['v']} so far)")
                if ti >= counts["vt"] or ti < -1:
                    raise SimulationError(f"{path} line {number}: face corner {token!r} refers "
                                          "to a texture coordinate that is not defined")
                corners_v.append(vi)
                corners_vt.append(ti)
            face_sizes.append(len(tokens))
            face_material.append(material)
        elif head == "usemtl":
            material = " ".join(fields[1:])
        elif head == "mtllib":
            libraries.append(" ".join(fields[1:]))
        elif head == "l":
            dropped["lines (l)"] += 1
        elif head == "p":
            dropped["points (p)"] += 1
        elif head in ("curv", "curv2", "surf"):
            dropped["curves and surfaces"] += 1
    warnings: list[str] = [f"{path}: {n} {what} dropped (only triangles and polygons are "
                           "scanned)" for what, n in dropped.items() if n]
    vertices = _float_rows(v_rows, 3, "v", path)
    uv_table = _float_rows(vt_rows, 2, "vt", path)

    # Fan triangulation of every polygon, vectorised over corners.
    sizes = np.asarray(face_sizes, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    per_face = sizes - 2
    face_of = np.repeat(np.arange(len(sizes)), per_face)
    k = np.arange(int(per_face.sum())) - np.repeat(np.cumsum(per_face) - per_face, per_face)
    first = starts[face_of]
    corner_index = np.stack([first, first + k + 1, first + k + 2], axis=1)
    cv = np.asarray(corners_v, dtype=np.int64)
    ct = np.asarray(corners_vt, dtype=np.int64)
    triangles = cv[corner_index] if len(cv) else np.zeros((0, 3), dtype=np.int64)
    tri_vt = ct[corner_index] if len(ct) else np.zeros((0, 3), dtype=np.int64)

    p = vertices[triangles]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1) \
        if len(triangles) else np.zeros(0)
    scale = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    degenerate = ((triangles[:, 0] == triangles[:, 1]) | (triangles[:, 1] == triangles[:, 2])
                  | (triangles[:, 0] == triangles[:, 2]) | (area2 <= (scale * 1e-9) ** 2))
    if degenerate.any():
        warnings.append(f"{path}: {int(degenerate.sum())} degenerate triangles (zero area) "
                        "dropped")
    keep = ~degenerate
    triangles, tri_vt, face_of = triangles[keep], tri_vt[keep], face_of[keep]
    if len(triangles) == 0:
        raise SimulationError(f"{path}: contains no triangles"
                              + (f" ({'; '.join(warnings)})" if warnings else ""))

    materials: dict[str, _Material] = {}
    for library in libraries:
        mtl = _find_texture(library, path.parent)
        if mtl is None:
            warnings.append(f"{path}: material library {library!r} not found beside it; "
                            "its materials are grey")
            continue
        materials.update(_read_mtl(mtl, warnings))

    # One Scene material per OBJ material used.
    used = sorted(set(face_material), key=face_material.index)
    names = np.asarray(face_material, dtype=object)
    material_of_face = np.zeros(len(face_material), dtype=np.int32)
    textures: list[U8] = []
    uv = np.full((len(triangles), 3, 2), 0.5)
    has_vt = (tri_vt >= 0).all(axis=1)
    if len(uv_table):
        uv[has_vt] = uv_table[tri_vt[has_vt]]
    unknown = [name for name in used if name and name not in materials]
    if unknown:
        warnings.append(f"{path}: material(s) {', '.join(map(repr, unknown))} not defined in "
                        "the material library; their faces are grey")
    for index, name in enumerate(used):
        material_of_face[names == name] = index
        spec = materials.get(name, _Material())
        on_tri = material_of_face[face_of] == index
        uv[on_tri] = uv[on_tri] * spec.uv_scale + spec.uv_offset
        textures.append(_obj_texture(spec, path, max_texture_px))
    uv[..., 1] = 1.0 - uv[..., 1]  # OBJ has v = 0 at the image bottom, the Scene glTF's top
    scene = Scene(vertices, triangles, uv, material_of_face[face_of], textures,
                  [name or "default" for name in used])
    scene.warnings = warnings
    return scene


def _obj_texture(spec: _Material, path: Path, max_texture_px: int) -> U8:
    """The RGB image of a material: its texture (checked from the header first, then decoded)
    times nothing (Kd is ignored under a texture, as most viewers do), or its flat Kd."""
    if spec.texture is not None:
        what = f"{path}: texture {spec.texture_name!r}"
        probe_image(spec.texture, what, max_texture_px, SimulationError)
        try:
            with Image.open(spec.texture) as image:
                image.load()
                return _rgb_array(image)
        except (OSError, ValueError, Image.DecompressionBombError) as err:
            raise SimulationError(f"{what}: cannot be decoded ({err})") from None
    rgb = np.clip(np.asarray(spec.kd_rgb, dtype=np.float64) * 255, 0, 255).astype(np.uint8)
    return np.full((4, 4, 3), rgb, dtype=np.uint8)


#: The axis that is up in a scene file: y (OBJ, glTF) or z (CAD, many scanner tools).
SceneUp = Literal["y", "z"]


def load_scene(path: Path | str, pose: Pose | None = None,
               max_texture_px: int = MAX_TEXTURE_PX, up: SceneUp = "y") -> Scene:
    """Load an OBJ (+MTL + images) or GLB/glTF scene in metres into the rig frame (y up).

    ``up = "z"`` turns a z-up file to y up (x, z, −y) first; then ``pose`` moves it (rotation
    then translation). What could not be used is listed in ``Scene.warnings``.

    Every texture is checked from its header before it is decoded: one of more than
    ``max_texture_px`` pixels (default 8192², the largest atlas page) is a
    :class:`SimulationError` naming it, its size and the limit. The limit can be raised up to
    Pillow's ``Image.MAX_IMAGE_PIXELS``.
    """
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".obj", ".glb", ".gltf"):
        raise SimulationError(f"{path}: unsupported scene format {suffix!r}; allowed: "
                              ".obj, .glb, .gltf")
    if not path.is_file():
        raise SimulationError(f"{path}: scene file not found")
    pillow_limit = Image.MAX_IMAGE_PIXELS or max_texture_px
    if not 0 < max_texture_px <= pillow_limit:
        raise SimulationError(f"max_texture_px {max_texture_px}: allowed 1 to "
                              f"{limit_text(pillow_limit)} (Pillow's MAX_IMAGE_PIXELS)")
    if suffix == ".obj":
        try:
            scene = read_obj(path, max_texture_px)
        except OSError as err:
            raise SimulationError(f"{path}: cannot read the scene: {err}") from err
    else:
        try:
            _check_gltf_images(path, max_texture_px)
            loaded = trimesh.load(str(path), process=False)
        except SimulationError:
            raise
        except Exception as err:  # trimesh raises many types on bad files
            raise SimulationError(f"{path}: cannot read the scene: {err}") from err
        scene = scene_from_trimesh(loaded, str(path), max_texture_px)
    if up == "z":
        x, y, z = scene.vertices.T
        scene.vertices = np.stack([x, z, -y], axis=1)
    if pose is not None:
        rotation = rotation_matrix_deg(pose.rotation_deg)
        scene.vertices = scene.vertices @ rotation.T + np.asarray(pose.translation_m)
    return scene
