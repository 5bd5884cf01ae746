"""PNG previews without a display: ray casting a (textured) mesh with Open3D.

One renderer serves the previews (``scanpipe render``, the report) and the texture evaluation,
which renders the result and the truth scene from the same viewpoints. Views:

- :class:`PerspectiveView`: a pinhole camera (eye, target, up, horizontal field of view);
- :class:`PlanView`: orthographic, looking down −y from a cut height (the ceiling is removed);
- :class:`PanoramaView`: equirectangular 360° × 180° from a point (the scanner's position).

Colour: the texture (bilinear) where a face has one, else vertex colours, else grey; faces
without texture are shaded by the angle to the ray so the shape reads. Image right is
``forward × up`` (not mirrored), rows go top to bottom.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.errors import ArtifactError, ExportError, UsageError

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

BACKGROUND_RGB = (24, 26, 32)
UNTEXTURED_GREY = 180


@dataclass(frozen=True)
class RenderMesh:
    """What the renderer draws: triangles, optional vertex colours, optional textures.

    ``face_uvs`` (M, 3, 2) are in glTF convention (v = 0 at the image top); ``face_pages[i]``
    indexes ``pages`` (RGB images), −1 for an untextured face.
    """

    vertices: F32
    faces: NDArray[np.int32]
    vertex_colors: U8 | None = None
    face_uvs: F32 | None = None
    face_pages: NDArray[np.int32] | None = None
    pages: dict[int, U8] = field(default_factory=dict)

    @property
    def textured(self) -> bool:
        """Whether any face has a texture."""
        return self.face_pages is not None and bool(np.any(self.face_pages >= 0))

    @property
    def bounds(self) -> F64:
        """``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``."""
        v = self.vertices.astype(np.float64)
        return np.stack([v.min(axis=0), v.max(axis=0)])


@dataclass(frozen=True)
class PerspectiveView:
    """A pinhole camera at ``eye`` looking at ``target``; ``fov_deg`` is horizontal."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    width: int = 640
    height: int = 480
    fov_deg: float = 70.0
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    name: str = "perspective"


@dataclass(frozen=True)
class PlanView:
    """Top-down orthographic view of the x–z extent, rays starting at ``cut_y_m`` downwards."""

    width: int = 640
    cut_y_m: float | None = None
    name: str = "plan"


@dataclass(frozen=True)
class PanoramaView:
    """Equirectangular panorama (width × width/2) from ``origin``; the centre looks along +z."""

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    width: int = 1024
    name: str = "panorama"


View = PerspectiveView | PlanView | PanoramaView


@dataclass(frozen=True)
class Rendering:
    """An image (H, W, 3), the hit distance (inf = background), the hit mask, and which pixels
    show a texture (as opposed to vertex colours or shading)."""

    rgb: U8
    depth_m: F32
    hit: NDArray[np.bool_]
    textured: NDArray[np.bool_]

    def png(self) -> bytes:
        """The image as PNG bytes."""
        buffer = io.BytesIO()
        Image.fromarray(self.rgb).save(buffer, format="PNG", compress_level=3)
        return buffer.getvalue()


def _normalise(v: F64) -> F64:
    return np.asarray(v / np.linalg.norm(v, axis=-1, keepdims=True), dtype=np.float64)


def perspective_rays(view: PerspectiveView) -> tuple[F64, F64]:
    """Ray origins (3,) and unit directions (H, W, 3) of a perspective view."""
    eye = np.asarray(view.eye, dtype=np.float64)
    forward = np.asarray(view.target, dtype=np.float64) - eye
    if np.linalg.norm(forward) < 1e-9:
        raise UsageError("render: the eye and the target are the same point")
    forward = _normalise(forward)
    right = np.cross(forward, np.asarray(view.up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: pick another up
        right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right = _normalise(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(view.fov_deg) / 2)
    xs = ((np.arange(view.width) + 0.5) / view.width * 2 - 1) * half
    ys = (1 - (np.arange(view.height) + 0.5) / view.height * 2) * half * view.height / view.width
    directions = (forward[None, None, :] + xs[None, :, None] * right[None, None, :]
                  + ys[:, None, None] * up[None, None, :])
    return eye, _normalise(directions)


def plan_rays(view: PlanView, bounds: F64) -> tuple[F64, F64]:
    """Ray origins (H, W, 3) and directions (H, W, 3) of a plan view over ``bounds``.

    Image right is +x and image up is −z (seen from above with y up, not mirrored).
    """
    (x0, y0, z0), (x1, y1, z1) = bounds
    margin = 0.02 * max(x1 - x0, z1 - z0, 1e-6)
    x0, x1, z0, z1 = x0 - margin, x1 + margin, z0 - margin, z1 + margin
    height = max(1, round(view.width * (z1 - z0) / max(x1 - x0, 1e-9)))
    cut = view.cut_y_m if view.cut_y_m is not None else y0 + 0.8 * (y1 - y0)
    xs = x0 + (np.arange(view.width) + 0.5) / view.width * (x1 - x0)
    zs = z0 + (np.arange(height) + 0.5) / height * (z1 - z0)
    grid_x, grid_z = np.meshgrid(xs, zs)
    origins = np.stack([grid_x, np.full_like(grid_x, cut), grid_z], axis=-1)
    directions = np.broadcast_to(np.array([0.0, -1.0, 0.0]), origins.shape)
    return origins, directions


def panorama_rays(view: PanoramaView) -> tuple[F64, F64]:
    """Ray origin (3,) and directions (W/2, W, 3): longitude −180°…180° left to right (turning
    right from +z), latitude +90° (up) at the top row."""
    height = max(1, view.width // 2)
    lon = ((np.arange(view.width) + 0.5) / view.width * 2 - 1) * np.pi
    lat = (0.5 - (np.arange(height) + 0.5) / height) * np.pi
    lon_g, lat_g = np.meshgrid(lon, lat)
    directions = np.stack([-np.cos(lat_g) * np.sin(lon_g), np.sin(lat_g),
                           np.cos(lat_g) * np.cos(lon_g)], axis=-1)
    return np.asarray(view.origin, dtype=np.float64), directions


def bilinear(image: U8, uv: F64) -> F64:
    """Bilinear texture look-up at glTF-convention UVs (v = 0 at the top), clamped at edges."""
    height, width = image.shape[:2]
    x = np.clip(uv[:, 0] * width - 0.5, 0.0, width - 1.0)
    y = np.clip(uv[:, 1] * height - 0.5, 0.0, height - 1.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.astype(np.float64)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return np.asarray(top * (1 - fy) + bottom * fy, dtype=np.float64)


class Renderer:
    """Ray casts one :class:`RenderMesh`; build once, render many views."""

    def __init__(self, mesh: RenderMesh) -> None:
        import importlib

        o3d: Any = importlib.import_module("open3d")
        if len(mesh.faces) == 0:
            raise ArtifactError("render: the mesh has no faces")
        self.mesh = mesh
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices,
                                                                       dtype=np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(mesh.faces,
                                                                       dtype=np.uint32)))

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> dict[str, Any]:
        """Cast rays: ``t_hit`` (inf = miss), ``face`` (−1 = miss), ``bary``, ``normal``."""
        dirs = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
        orig = np.broadcast_to(np.asarray(origins, dtype=np.float32).reshape(-1, 3)
                               if np.ndim(origins) > 1 else np.asarray(origins, np.float32),
                               dirs.shape)
        answer = self._scene.cast_rays(self._o3d.core.Tensor(
            np.ascontiguousarray(np.concatenate([orig, dirs], axis=1))))
        face = answer["primitive_ids"].numpy().astype(np.int64)
        face[face == 4294967295] = -1
        return {"t_hit": answer["t_hit"].numpy(), "face": face,
                "bary": answer["primitive_uvs"].numpy(), "normal": answer["primitive_normals"]
                .numpy(), "directions": dirs}

    def colors(self, hits: dict[str, Any]) -> tuple[U8, NDArray[np.bool_]]:
        """RGB per ray from the texture, vertex colours or shading (background for misses),
        and which rays took their colour from a texture."""
        mesh = self.mesh
        face, bary = hits["face"], hits["bary"].astype(np.float64)
        rgb = np.empty((len(face), 3), dtype=np.float64)
        rgb[:] = BACKGROUND_RGB
        hit = face >= 0
        w1, w2 = bary[:, 0:1], bary[:, 1:2]
        weights = np.concatenate([1 - w1 - w2, w1, w2], axis=1)
        cosine = np.abs(np.einsum("ij,ij->i", hits["normal"].astype(np.float64),
                                  hits["directions"].astype(np.float64)))
        shade = (0.35 + 0.65 * cosine)[:, None]
        textured = np.zeros(len(face), dtype=bool)
        if mesh.face_pages is not None and mesh.face_uvs is not None:
            page_of_hit = np.where(hit, mesh.face_pages[np.where(hit, face, 0)], -1)
            for page in np.unique(page_of_hit[page_of_hit >= 0]):
                sel = np.flatnonzero(page_of_hit == page)
                corners = mesh.face_uvs[face[sel]].astype(np.float64)
                uv = np.einsum("nk,nkc->nc", weights[sel], corners)
                rgb[sel] = bilinear(mesh.pages[int(page)], uv)
                textured[sel] = True
        plain = hit & ~textured
        if np.any(plain):
            if mesh.vertex_colors is not None:
                corner_colors = mesh.vertex_colors[mesh.faces[face[plain]]].astype(np.float64)
                base = np.einsum("nk,nkc->nc", weights[plain], corner_colors)
            else:
                base = np.full((int(plain.sum()), 3), float(UNTEXTURED_GREY))
            rgb[plain] = base * shade[plain]
        return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), textured

    def render(self, view: View) -> Rendering:
        """Render one view."""
        if isinstance(view, PerspectiveView):
            origins, directions = perspective_rays(view)
        elif isinstance(view, PlanView):
            origins, directions = plan_rays(view, self.mesh.bounds)
        else:
            origins, directions = panorama_rays(view)
        shape = directions.shape[:2]
        hits = self.cast(origins if origins.ndim == 1 else origins.reshape(-1, 3),
                         directions.reshape(-1, 3))
        rgb, textured = self.colors(hits)
        depth = hits["t_hit"].astype(np.float32).reshape(shape)
        return Rendering(rgb.reshape(*shape, 3), depth, np.isfinite(depth),
                         textured.reshape(shape))


# -- loading what to render ------------------------------------------------------------------


def decode_pages(pages: dict[int, bytes]) -> dict[int, U8]:
    """PNG pages to RGB arrays."""
    from scanpipe.exporters.ply import decode_png

    return {page: decode_png(data, f"texture page {page}") for page, data in pages.items()}


def render_mesh_from_model(mesh: Any) -> RenderMesh:
    """A :class:`RenderMesh` from an exporter :class:`~scanpipe.exporters.model.MeshModel`."""
    return RenderMesh(
        vertices=mesh.vertices.astype(np.float32), faces=mesh.faces.astype(np.int32),
        vertex_colors=mesh.colors,
        face_uvs=mesh.face_uvs if mesh.textured else None,
        face_pages=mesh.face_pages.astype(np.int32) if mesh.textured else None,
        pages=decode_pages(mesh.pages) if mesh.textured else {},
    )


def render_mesh_from_scene(scene: Any) -> RenderMesh:
    """A :class:`RenderMesh` from a :class:`scanpipe.sim.scene.Scene` (the truth)."""
    return RenderMesh(
        vertices=np.asarray(scene.vertices, dtype=np.float32),
        faces=np.asarray(scene.triangles, dtype=np.int32),
        face_uvs=np.asarray(scene.triangle_uvs, dtype=np.float32),
        face_pages=np.asarray(scene.triangle_material, dtype=np.int32),
        pages={i: np.asarray(image, dtype=np.uint8) for i, image in enumerate(scene.textures)},
    )


def load_mesh_file(path: Path) -> RenderMesh:
    """A mesh file: OBJ/GLB/glTF (with textures) or PLY/STL/OFF (vertex colours at most)."""
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ArtifactError(f"{path}: mesh file not found")
    if suffix in (".obj", ".glb", ".gltf"):
        from scanpipe.errors import SimulationError
        from scanpipe.sim.scene import load_scene

        try:
            return render_mesh_from_scene(load_scene(path))
        except SimulationError as err:
            raise ArtifactError(str(err)) from None
    if suffix in (".ply", ".stl", ".off"):
        import trimesh

        try:
            loaded: Any = trimesh.load(str(path), process=False, force="mesh")
        except Exception as err:  # trimesh raises many types on bad files
            raise ArtifactError(f"{path}: cannot read the mesh: {err}") from err
        colors = None
        visual: Any = getattr(loaded, "visual", None)
        if getattr(visual, "kind", None) == "vertex":
            colors = np.asarray(visual.vertex_colors, dtype=np.uint8)[:, :3]
        return RenderMesh(np.asarray(loaded.vertices, np.float32),
                          np.asarray(loaded.faces, np.int32), colors)
    raise UsageError(f"{path}: unsupported mesh format {suffix!r}; allowed: .obj, .glb, "
                     ".gltf, .ply, .stl, .off")


def load_render_mesh(source: Path) -> RenderMesh:
    """The mesh (and texture) in a folder of artifacts, or a mesh file."""
    if source.is_file():
        return load_mesh_file(source)
    from scanpipe.artifacts import read_artifact
    from scanpipe.stages.export import MESH_ARTIFACTS, TEXTURE_ARTIFACTS, models_from_tables
    from scanpipe.workdir import find_artifacts

    found = find_artifacts(source, (*MESH_ARTIFACTS, *TEXTURE_ARTIFACTS))
    missing = [name for name in MESH_ARTIFACTS if name not in found]
    if missing:
        raise ArtifactError(f"{source}: no mesh to render (missing {', '.join(missing)}; "
                            "looked for <name>.parquet and <stage>/<name>.parquet)")
    tables = {name: read_artifact(path)[0] for name, path in found.items()}
    mesh, _ = models_from_tables(tables)
    assert mesh is not None
    return render_mesh_from_model(mesh)


# -- default views and the command -----------------------------------------------------------


#: Below this length of the mean horizontal direction to the data, the data is all around the
#: scanner (a room) and the front view looks along +z.
ALL_AROUND = 0.25


def data_direction(vertices: NDArray[np.floating], faces: NDArray[np.integer], origin: F64
                   ) -> F64:
    """The unit horizontal (x, z) direction from ``origin`` towards where the surface is: the
    area-weighted mean of the unit directions to the face centres; +z when it is all around."""
    corners = np.asarray(vertices, dtype=np.float64)[faces]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                          corners[:, 2] - corners[:, 0]), axis=1)
    offsets = corners.mean(axis=1)[:, [0, 2]] - origin[[0, 2]]
    lengths = np.linalg.norm(offsets, axis=1)
    use = (lengths > 0) & (areas > 0)
    offsets = offsets[use] / lengths[use, None]
    mean = (np.average(offsets, axis=0, weights=areas[use]) if use.any() else np.zeros(2))
    if float(np.linalg.norm(mean)) < ALL_AROUND:
        return np.array([0.0, 0.0, 1.0])
    mean /= np.linalg.norm(mean)
    return np.array([mean[0], 0.0, mean[1]])


def default_perspectives(bounds: F64, origin: Sequence[float] = (0.0, 0.0, 0.0),
                         width: int = 640, fov_deg: float = 80.0,
                         mesh: RenderMesh | None = None) -> list[PerspectiveView]:
    """Two views from the scanner when it stands inside the model's bounds (a room): the front
    one looks towards where the surface of ``mesh`` is (+z when it is all around, or not
    given), the back one the other way; else one overview from outside a corner, looking at
    the centre of the bounds."""
    height = max(1, width * 3 // 4)
    o = np.asarray(origin, dtype=np.float64)
    inside = bool(np.all(o > bounds[0]) and np.all(o < bounds[1]))
    if inside:
        eye = vec3(o)
        ahead = (data_direction(mesh.vertices, mesh.faces, o)
                 if mesh is not None and len(mesh.faces) else np.array([0.0, 0.0, 1.0]))
        return [PerspectiveView(eye, vec3(o + ahead), width, height, fov_deg,
                                name="view_front"),
                PerspectiveView(eye, vec3(o - ahead), width, height, fov_deg,
                                name="view_back")]
    centre = bounds.mean(axis=0)
    extent = float(np.linalg.norm(bounds[1] - bounds[0]))
    eye_arr = centre + np.array([0.8, 0.6, 1.0]) / np.linalg.norm([0.8, 0.6, 1.0]) * extent
    return [PerspectiveView(vec3(eye_arr), vec3(centre), width, height, 50.0,
                            name="view_overview")]


def vec3(values: Sequence[float] | NDArray[np.floating]) -> tuple[float, float, float]:
    """Three numbers as a plain (x, y, z) tuple."""
    return float(values[0]), float(values[1]), float(values[2])


def _triple(text: str, option: str) -> tuple[float, float, float]:
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise UsageError(f"{option} {text!r}: expected three numbers x,y,z")
    return values[0], values[1], values[2]


def preview_views(mesh: RenderMesh, views: str = "perspective,plan,panorama", width: int = 640,
                  eye: str | None = None, target: str | None = None,
                  fov_deg: float = 70.0) -> list[View]:
    """The views ``scanpipe render`` draws, from its options."""
    names = [v.strip().lower() for v in views.split(",") if v.strip()]
    unknown = sorted(set(names) - {"perspective", "plan", "panorama"})
    if unknown or not names:
        raise UsageError(f"--views {views!r}: allowed: perspective, plan, panorama")
    chosen: list[View] = []
    for name in names:
        if name == "perspective":
            if eye is not None or target is not None:
                eye_xyz = _triple(eye, "--eye") if eye else (0.0, 0.0, 0.0)
                target_xyz = (_triple(target, "--target") if target
                              else vec3(mesh.bounds.mean(axis=0)))
                chosen.append(PerspectiveView(eye_xyz, target_xyz,
                                              width, max(1, width * 3 // 4), fov_deg))
            else:
                chosen += default_perspectives(mesh.bounds, width=width,
                                               mesh=mesh)
        elif name == "plan":
            chosen.append(PlanView(width))
        else:
            chosen.append(PanoramaView((0.0, 0.0, 0.0), width))
    return chosen


#: Image suffixes other than PNG: ``--out x.jpg`` would otherwise become a folder "x.jpg".
_IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".gif", ".bmp", ".tif", ".tiff", ".webp"})


def render_previews(source: Path, out: Path, width: int = 640,
                    views: str = "perspective,plan,panorama", eye: str | None = None,
                    target: str | None = None, fov_deg: float = 70.0,
                    overwrite: bool = True) -> list[Path]:
    """``scanpipe render``: PNGs into the folder ``out``, or the first view into ``out.png``.

    ``out`` is used as given: a ``.png`` path is one image, anything else a folder (another
    image suffix is refused). Existing images are replaced only with ``overwrite``; an input
    is never replaced (:mod:`scanpipe.outpaths`).
    """
    from scanpipe.outpaths import (
        check_output_file,
        check_output_files,
        check_output_folder,
        folder_inputs,
    )

    single = out.suffix.lower() == ".png"
    if not single and out.suffix.lower() in _IMAGE_SUFFIXES and not out.is_dir():
        check_output_file(out, "--out", (".png",))
    inputs = folder_inputs(source)
    if single:
        check_output_file(out, "--out", (".png",), overwrite, inputs)
    else:
        check_output_folder(out, "--out", inputs)
    mesh = load_render_mesh(source)
    chosen = preview_views(mesh, views, width, eye, target, fov_deg)
    renderer = Renderer(mesh)
    targets = [out] if single else [out / f"{view.name}.png" for view in chosen]
    check_output_files(targets, "--out", overwrite, inputs)
    written = []
    for view, path in zip(chosen, targets, strict=False):
        data = renderer.render(view).png()
        try:
            atomic_write_bytes(path, data)
        except OSError as err:
            raise ExportError(f"{path}: cannot write the preview ({err.strerror or err})"
                              ) from None
        written.append(path)
    return written
