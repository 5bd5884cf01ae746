"""The ground-truth scene: a textured triangle mesh in metres, in the rig frame (y up).

A :class:`Scene` holds triangles with per-corner texture coordinates (glTF convention: v = 0 at
the image top) and one RGB texture image per material. Rays are cast with Open3D's
``RaycastingScene``; the colour of a hit comes from its triangle and barycentric coordinates.
"""

from __future__ import annotations

import base64
import io
import json
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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

_FACE_TOKEN = re.compile(r"^(-?\d+)(?:/(-?\d*))?(?:/(-?\d*))?$")


def resolve_obj_negative_indices(text: str) -> tuple[str, int]:
    """Rewrite OBJ face indices that are negative (relative) as absolute ones.

    Returns the text and how many indices were rewritten. trimesh mis-reads some files with
    relative indices, so they are resolved here, against the vertices defined so far.
    """
    counts = {"v": 0, "vt": 0, "vn": 0}
    rewritten = 0
    lines = text.splitlines()
    for i, line in enumerate(lines):
        head, _, rest = line.strip().partition(" ")
        if head in counts:
            counts[head] += 1
        elif head == "f" and "-" in rest:
            tokens = []
            for token in rest.split():
                match = _FACE_TOKEN.match(token)
                if match is None:
                    raise SimulationError(f"OBJ line {i + 1}: cannot read face index {token!r}")
                parts = []
                for kind, value in zip(("v", "vt", "vn"), match.groups(), strict=True):
                    if value is None:
                        continue
                    if value.startswith("-"):
                        value = str(counts[kind] + 1 + int(value))
                        rewritten += 1
                        if int(value) < 1:
                            raise SimulationError(
                                f"OBJ line {i + 1}: relative index {token!r} points before the "
                                f"first {kind}"
                            )
                    parts.append(value)
                tokens.append("/".join(parts))
            lines[i] = "f " + " ".join(tokens)
    return "\n".join(lines) + "\n", rewritten


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
    for index, (mesh, transform, placed_name) in enumerate(meshes):
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
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
    return Scene(np.concatenate(vertices), np.concatenate(triangles), np.concatenate(uvs),
                 np.concatenate(materials), textures, names)


def _texture_resolver(path: Path, max_texture_px: int, materials: set[str]) -> Any:
    """A trimesh file resolver that checks every image it hands out from the header, before
    trimesh decodes it: trimesh swallows errors in textures (Pillow's decompression-bomb error
    too) and drops the texture without a word, so the problems are kept and raised after."""
    import trimesh

    class Resolver(trimesh.resolvers.FilePathResolver):  # type: ignore[misc]
        def __init__(self, source: str) -> None:
            super().__init__(source)
            self.problems: list[SimulationError] = []

        def get(self, name: str) -> bytes:
            data: bytes = super().get(name)
            if name not in materials:
                try:
                    probe_image(data, f"{path}: texture {name!r}", max_texture_px,
                                SimulationError)
                except SimulationError as err:
                    self.problems.append(err)
                    raise
            return data

    return Resolver(str(path))


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


def load_scene(path: Path | str, pose: Pose | None = None,
               max_texture_px: int = MAX_TEXTURE_PX) -> Scene:
    """Load an OBJ (+MTL + images) or GLB/glTF scene in metres, optionally moved by ``pose``
    (rotation then translation, into the rig frame).

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
    problems: list[SimulationError] = []
    try:
        if suffix == ".obj":
            text = path.read_text(encoding="utf-8", errors="replace")
            text, _ = resolve_obj_negative_indices(text)
            materials = {line.strip()[6:].strip() for line in text.splitlines()
                         if line.strip().startswith("mtllib")}
            resolver = _texture_resolver(path, max_texture_px, materials)
            problems = resolver.problems
            loaded = trimesh.load(io.BytesIO(text.encode()), file_type="obj", resolver=resolver,
                                  process=False, maintain_order=True)
        else:
            _check_gltf_images(path, max_texture_px)
            loaded = trimesh.load(str(path), process=False)
    except SimulationError:
        raise
    except Exception as err:  # trimesh raises many types on bad files
        raise SimulationError(f"{path}: cannot read the scene: {err}") from err
    if problems:
        raise problems[0]
    scene = scene_from_trimesh(loaded, str(path), max_texture_px)
    if pose is not None:
        rotation = rotation_matrix_deg(pose.rotation_deg)
        scene.vertices = scene.vertices @ rotation.T + np.asarray(pose.translation_m)
    return scene
