"""The built-in scenes, generated procedurally and deterministically (no files, no downloads).

The room is about 6 × 4 × 3 m around the motor axis (the scanner sits 1.2 m above the floor):
floor, ceiling and four walls, a doorway into an alcove (a depth discontinuity), a table, boxes at
several distances and an octagonal column. Every surface has its own texture, built from
multi-octave noise, patches and printed labels, so no two places look alike and a misplaced
texture is visible and measurable.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.rig import Pose
from scanpipe.sim.scene import Scene, SceneUp, load_scene

U8 = NDArray[np.uint8]
Vec = tuple[float, float, float]

FLOOR_Y_M = -1.2
CEILING_Y_M = 1.8
ROOM_X_M = (-3.2, 2.8)
ROOM_Z_M = (-1.8, 2.2)
DOOR_X_M = (0.6, 1.5)
DOOR_TOP_Y_M = 0.9
ALCOVE_DEPTH_M = 1.4


def make_texture(name: str, seed: int, size: tuple[int, int] = (256, 256)) -> U8:
    """A non-repetitive RGB texture: coloured multi-octave noise, patches and labels."""
    rng = np.random.default_rng(seed)
    height, width = size
    base = rng.uniform(40, 215, size=3)
    accent = rng.uniform(20, 235, size=3)
    noise = np.zeros((height, width), dtype=np.float32)
    for octave, weight in ((3, 0.5), (7, 0.25), (17, 0.15), (41, 0.1)):
        small = rng.random((octave, octave)).astype(np.float32)
        noise += weight * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    noise = (noise - noise.min()) / max(float(np.ptp(noise)), 1e-6)
    image = base[None, None, :] * (1 - noise[..., None]) + accent[None, None, :] * noise[..., None]
    image = np.ascontiguousarray(np.clip(image, 0, 255).astype(np.uint8))
    for _ in range(6):  # patches: sharp edges to find misplacements by
        x0, y0 = int(rng.integers(0, width - 8)), int(rng.integers(0, height - 8))
        w = int(rng.integers(width // 16, width // 4))
        h = int(rng.integers(height // 16, height // 4))
        color = tuple(int(c) for c in rng.integers(0, 256, size=3))
        if rng.random() < 0.5:
            cv2.rectangle(image, (x0, y0), (x0 + w, y0 + h), color, -1)
        else:
            cv2.circle(image, (x0, y0), max(w, h) // 2, color, -1)
    scale = max(width, height) / 512
    for row in range(4):  # labels say where on which surface a texel is
        for col in range(4):
            x = int((col + 0.1) * width / 4)
            y = int((row + 0.6) * height / 4)
            cv2.putText(image, f"{name}{row}{col}", (x, y), cv2.FONT_HERSHEY_SIMPLEX,
                        0.8 * scale, (255 - int(base[0]), 255 - int(base[1]), 255 - int(base[2])),
                        max(1, int(2 * scale)), cv2.LINE_AA)
    return image


@dataclass
class _Builder:
    """Collects textured quads into the arrays of a :class:`Scene`."""

    vertices: list[Vec] = field(default_factory=list)
    triangles: list[tuple[int, int, int]] = field(default_factory=list)
    uvs: list[tuple[tuple[float, float], ...]] = field(default_factory=list)
    materials: list[int] = field(default_factory=list)
    textures: list[U8] = field(default_factory=list)
    names: list[str] = field(default_factory=list)

    def material(self, name: str, size: tuple[int, int] = (256, 256)) -> int:
        self.textures.append(make_texture(name, seed=len(self.textures) + 1000, size=size))
        self.names.append(name)
        return len(self.textures) - 1

    def quad(self, origin: Vec, u_axis: Vec, v_axis: Vec, material: int,
             uv_rect: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)) -> None:
        """A parallelogram ``origin + s·u + t·v``; the texture's sub-rectangle ``uv_rect``
        ``(u0, v0, u1, v1)`` (in the texture's [0, 1]², v = 0 at the top) is laid upright with
        the image's up along ``v_axis``."""
        o, u, v = np.asarray(origin), np.asarray(u_axis), np.asarray(v_axis)
        start = len(self.vertices)
        for corner in (o, o + u, o + u + v, o + v):
            self.vertices.append((float(corner[0]), float(corner[1]), float(corner[2])))
        u0, v0, u1, v1 = uv_rect
        corners_uv = ((u0, v1), (u1, v1), (u1, v0), (u0, v0))
        for a, b, c in ((0, 1, 2), (0, 2, 3)):
            self.triangles.append((start + a, start + b, start + c))
            self.uvs.append((corners_uv[a], corners_uv[b], corners_uv[c]))
            self.materials.append(material)

    def wall(self, origin: Vec, u_axis: Vec, v_axis: Vec, material: int,
             holes: tuple[tuple[float, float, float, float], ...] = ()) -> None:
        """A rectangle, minus rectangular holes given as fractions ``(s0, t0, s1, t1)`` of the
        u and v extents; the texture spans the whole rectangle, holes included."""
        s_cuts = sorted({0.0, 1.0, *(h[0] for h in holes), *(h[2] for h in holes)})
        t_cuts = sorted({0.0, 1.0, *(h[1] for h in holes), *(h[3] for h in holes)})
        o, u, v = np.asarray(origin), np.asarray(u_axis), np.asarray(v_axis)
        for s0, s1 in itertools.pairwise(s_cuts):
            for t0, t1 in itertools.pairwise(t_cuts):
                centre = ((s0 + s1) / 2, (t0 + t1) / 2)
                if any(h[0] <= centre[0] <= h[2] and h[1] <= centre[1] <= h[3] for h in holes):
                    continue
                corner = o + s0 * u + t0 * v
                self.quad(tuple(corner), tuple((s1 - s0) * u), tuple((t1 - t0) * v), material,
                          (s0, 1 - t1, s1, 1 - t0))

    def box(self, centre_xz: tuple[float, float], size: Vec, bottom_y: float, name: str,
            yaw_deg: float = 0.0) -> None:
        """A closed cuboid standing on ``bottom_y``; each face gets its own part of one texture."""
        material = self.material(name, (384, 256))
        sx, sy, sz = size
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        ex = np.array([c, 0.0, -s]) * sx
        ez = np.array([s, 0.0, c]) * sz
        ey = np.array([0.0, sy, 0.0])
        base = np.array([centre_xz[0], bottom_y, centre_xz[1]]) - ex / 2 - ez / 2
        cells = [(i % 3 / 3, i // 3 / 2, (i % 3 + 1) / 3, (i // 3 + 1) / 2) for i in range(6)]
        faces = (
            (base + ez, ex, ey),            # front (+z side)
            (base + ex, -ex, ey),           # back
            (base, ez, ey),                 # left
            (base + ex + ez, -ez, ey),      # right
            (base + ey + ez, ex, -ez),      # top
            (base, ex, ez),                 # bottom
        )
        for (origin, u, v), rect in zip(faces, cells, strict=True):
            self.quad(tuple(origin), tuple(u), tuple(v), material, rect)

    def prism(self, centre_xz: tuple[float, float], radius: float, y_range: tuple[float, float],
              sides: int, name: str) -> None:
        """A vertical regular prism (a column) with the texture wrapped once around it."""
        material = self.material(name, (256, 512))
        angles = np.linspace(0, -2 * np.pi, sides + 1)  # clockwise from above: text reads right
        height = y_range[1] - y_range[0]
        for i in range(sides):
            p0 = (centre_xz[0] + radius * np.cos(angles[i]), y_range[0],
                  centre_xz[1] + radius * np.sin(angles[i]))
            p1 = (centre_xz[0] + radius * np.cos(angles[i + 1]), y_range[0],
                  centre_xz[1] + radius * np.sin(angles[i + 1]))
            u = (p1[0] - p0[0], 0.0, p1[2] - p0[2])
            self.quad((float(p0[0]), float(p0[1]), float(p0[2])), u, (0.0, height, 0.0),
                      material, (i / sides, 0.0, (i + 1) / sides, 1.0))

    def scene(self) -> Scene:
        return Scene(np.asarray(self.vertices), np.asarray(self.triangles),
                     np.asarray(self.uvs), np.asarray(self.materials), self.textures, self.names)


def _room_shell(b: _Builder, x_range: tuple[float, float], z_range: tuple[float, float],
                y_range: tuple[float, float], prefix: str,
                door_hole: tuple[float, float, float, float] | None = None,
                open_side: str | None = None) -> None:
    """Floor, ceiling and four walls of an axis-aligned room, textured from the inside."""
    (x0, x1), (y0, y1), (z0, z1) = x_range, y_range, z_range
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    big = (512, 512)
    b.wall((x0, y0, z1), (dx, 0, 0), (0, 0, -dz), b.material(f"{prefix}F", big))
    b.wall((x0, y1, z0), (dx, 0, 0), (0, 0, dz), b.material(f"{prefix}C", big))
    walls = {
        "north": ((x1, y0, z1), (-dx, 0, 0), (0, dy, 0)),  # at z1, seen from inside (−z side)
        "south": ((x0, y0, z0), (dx, 0, 0), (0, dy, 0)),
        "west": ((x0, y0, z1), (0, 0, -dz), (0, dy, 0)),
        "east": ((x1, y0, z0), (0, 0, dz), (0, dy, 0)),
    }
    for side, (origin, u, v) in walls.items():
        if side == open_side:
            continue
        holes = (door_hole,) if door_hole is not None and side == "north" else ()
        b.wall(origin, u, v, b.material(f"{prefix}{side[0].upper()}", big), holes)


@lru_cache(maxsize=1)
def _room_cached() -> Scene:
    b = _Builder()
    x0, x1 = ROOM_X_M
    z1 = ROOM_Z_M[1]
    width = x1 - x0
    # the doorway is in the north wall (z = z1); its u axis runs from x1 towards x0
    door = ((x1 - DOOR_X_M[1]) / width, 0.0, (x1 - DOOR_X_M[0]) / width,
            (DOOR_TOP_Y_M - FLOOR_Y_M) / (CEILING_Y_M - FLOOR_Y_M))
    _room_shell(b, ROOM_X_M, ROOM_Z_M, (FLOOR_Y_M, CEILING_Y_M), "R", door)
    _room_shell(b, (DOOR_X_M[0] - 0.3, DOOR_X_M[1] + 0.3), (z1, z1 + ALCOVE_DEPTH_M),
                (FLOOR_Y_M, DOOR_TOP_Y_M + 0.2), "A", open_side="south")
    # a table: top and four legs
    top_y = FLOOR_Y_M + 0.75
    b.box((-1.7, 1.1), (1.2, 0.04, 0.8), top_y - 0.04, "T", yaw_deg=10)
    for lx, lz in ((-2.2, 0.85), (-1.25, 0.7), (-2.14, 1.5), (-1.18, 1.34)):
        b.box((lx, lz), (0.05, 0.71, 0.05), FLOOR_Y_M, "L", yaw_deg=10)
    b.box((-1.55, 1.1), (0.3, 0.2, 0.25), top_y, "S", yaw_deg=-20)  # a small box on the table
    # boxes at several distances
    b.box((1.7, -1.1), (0.6, 0.5, 0.4), FLOOR_Y_M, "B", yaw_deg=25)
    b.box((-2.5, -1.2), (0.5, 0.9, 0.5), FLOOR_Y_M, "K")
    b.box((2.2, 1.4), (0.4, 1.4, 0.4), FLOOR_Y_M, "H", yaw_deg=-15)
    b.prism((0.9, -0.7), 0.18, (FLOOR_Y_M, CEILING_Y_M), 8, "P")
    return b.scene()


def builtin_room() -> Scene:
    """The built-in room (about 6 × 4 × 3 m, furnished, textured); a fresh copy (callers may
    move its vertices)."""
    cached = _room_cached()
    return Scene(cached.vertices.copy(), cached.triangles, cached.triangle_uvs,
                 cached.triangle_material, cached.textures, list(cached.material_names))


def box_room(size_m: tuple[float, float, float] = (6.0, 3.0, 4.0),
             floor_y_m: float = -1.2) -> Scene:
    """An empty textured room ``size_m = (x, y, z)`` centred on the motor axis, floor at
    ``floor_y_m`` (for analytic tests)."""
    b = _Builder()
    sx, sy, sz = size_m
    _room_shell(b, (-sx / 2, sx / 2), (-sz / 2, sz / 2), (floor_y_m, floor_y_m + sy), "X")
    return b.scene()


@lru_cache(maxsize=1)
def _site_cached() -> Scene:
    """The site of :mod:`scanpipe.sim.site` (x: room A −7…−2, corridor −2…2, room B 2…7)."""
    b = _Builder()
    y0, y1 = FLOOR_Y_M, CEILING_Y_M
    height = y1 - y0
    big = (512, 512)
    x0, x1, z0, z1 = -7.0, 7.0, -3.0, 3.0
    dx, dz = x1 - x0, z1 - z0
    b.wall((x0, y0, z1), (dx, 0, 0), (0, 0, -dz), b.material("SF", big))      # floor
    b.wall((x0, y1, z0), (dx, 0, 0), (0, 0, dz), b.material("SC", big))       # ceiling
    b.wall((x1, y0, z1), (-dx, 0, 0), (0, height, 0), b.material("SN", big))  # north, z = 3
    b.wall((x0, y0, z0), (dx, 0, 0), (0, height, 0), b.material("SS", big))   # south, z = −3
    b.wall((x0, y0, z1), (0, 0, -dz), (0, height, 0), b.material("SW", big))  # west, x = −7
    b.wall((x1, y0, z0), (0, 0, dz), (0, height, 0), b.material("SE", big))  # east, x = 7
    door_top = (0.95 - y0) / height
    # partitions at x = ±2 from z = −3 to 3, each with a door into the corridor (z in [−1, 1])
    b.wall((-2.0, y0, z0), (0, 0, dz), (0, height, 0), b.material("PA", big),
           ((2.3 / dz, 0.0, 3.6 / dz, door_top),))     # door z ∈ [−0.7, 0.6]
    b.wall((2.0, y0, z0), (0, 0, dz), (0, height, 0), b.material("PB", big),
           ((2.4 / dz, 0.0, 3.8 / dz, door_top),))     # door z ∈ [−0.6, 0.8]
    # corridor walls at z = ±1 between the partitions; a niche in the north one
    b.wall((-2.0, y0, 1.0), (4.0, 0, 0), (0, height, 0), b.material("CN", big),
           ((0.55, 0.0, 0.75, door_top),))
    b.wall((-2.0, y0, -1.0), (4.0, 0, 0), (0, height, 0), b.material("CS", big))
    b.wall((0.2, y0, 1.0), (0, 0, 0.5), (0, 2.15, 0), b.material("CW", big))   # niche sides
    b.wall((1.0, y0, 1.0), (0, 0, 0.5), (0, 2.15, 0), b.material("CE", big))
    b.wall((0.2, y0, 1.5), (0.8, 0, 0), (0, 2.15, 0), b.material("CB", big))
    # room A: a table, boxes, a column
    top_y = y0 + 0.75
    b.box((-5.6, 1.6), (1.4, 0.04, 0.8), top_y - 0.04, "T", yaw_deg=12)
    for lx, lz in ((-6.2, 1.3), (-5.0, 1.2), (-6.1, 2.0), (-4.9, 1.9)):
        b.box((lx, lz), (0.05, 0.71, 0.05), y0, "L", yaw_deg=12)
    b.box((-4.2, -2.2), (0.8, 0.6, 0.5), y0, "B", yaw_deg=25)
    b.box((-6.3, -2.3), (0.5, 1.2, 0.5), y0, "K")
    b.prism((-3.6, -0.6), 0.2, (y0, y1), 8, "P")
    b.box((-2.6, 2.4), (0.6, 1.8, 0.4), y0, "W", yaw_deg=-8)
    # corridor: a low cabinet and a pillar
    b.box((-0.6, -0.75), (0.9, 0.8, 0.35), y0, "C")
    b.prism((1.5, 0.6), 0.12, (y0, y1), 6, "Q")
    # room B: shelves, boxes, a round column, a slanted board
    b.box((5.9, -2.5), (1.6, 2.0, 0.4), y0, "S", yaw_deg=4)
    b.box((3.4, 2.3), (0.7, 0.9, 0.7), y0, "D", yaw_deg=-30)
    b.box((6.3, 1.2), (0.5, 0.5, 0.5), y0, "E", yaw_deg=40)
    b.box((4.4, -1.8), (0.4, 0.45, 0.9), y0, "G", yaw_deg=10)
    b.prism((4.3, 0.9), 0.25, (y0, y1), 12, "R")
    b.quad((2.6, y0, -2.6), (0.0, 1.6, 0.0), (1.2, 0.0, 0.6), b.material("V"))
    return b.scene()




def builtin_site() -> Scene:
    """The built-in site (two rooms and a corridor, 14 × 6 × 3 m) in the site frame; a fresh
    copy (callers may move its vertices)."""
    cached = _site_cached()
    return Scene(cached.vertices.copy(), cached.triangles, cached.triangle_uvs,
                 cached.triangle_material, cached.textures, list(cached.material_names))


def resolve_scene(name_or_path: str, pose: Pose | None = None, up: SceneUp = "y") -> Scene:
    """A built-in scene by name (``room``, ``box``, ``site``) or a scene file (OBJ, GLB, glTF)
    with its up axis ``up``; ``pose`` moves a built-in scene too (rotation, then translation)."""
    if name_or_path in ("room", "box", "site"):
        if name_or_path == "site":
            scene = builtin_site()
        else:
            scene = builtin_room() if name_or_path == "room" else box_room()
        if pose is not None:
            from scanpipe.geometry import rotation_matrix_deg

            rotation = rotation_matrix_deg(pose.rotation_deg)
            scene.vertices = scene.vertices @ rotation.T + np.asarray(pose.translation_m)
        return scene
    return load_scene(name_or_path, pose, up=up)
