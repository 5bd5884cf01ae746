"""Texture atlas: the image regions that faces were textured from, packed into pages.

Per frame, the faces that chose it cover a set of pixel boxes. The boxes are painted onto a
coarse grid of ``cell_px`` cells and joined into 8-connected regions (a sparse one, whose cells
fill less than :data:`SPLIT_FILL` of its box, cut into tiles of :data:`SPLIT_CELLS` cells: the
atlas then holds ~25 % less image no face uses); each region's tight box
(plus ``pad_px`` of real image around it, so that filtering at chart borders samples real
pixels) is cut out, multiplied by the frame's exposure gain, scaled by ``texel_scale`` and placed
into pages by shelf packing (tallest first). Page 0 begins with a neutral-colour strip where the
UVs of untextured faces point; unused page area is neutral too. UVs follow glTF: v = 0 at the
top, texel centres at ``(i + 0.5) / size``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import cv2
import numpy as np
from numpy.typing import NDArray

from scanpipe.camera import project_points
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.texturing.frames import FrameSet, worker_count
from scanpipe.texturing.patches import Patches
from scanpipe.texturing.seams import SeamCorrections, correction_field
from scanpipe.threads import thread_pool

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]
#: Width of the neutral strip at the left of page 0.
NEUTRAL_PX = 8
#: Faces whose atlas UVs are computed at once.
UV_BLOCK_FACES = 1 << 18
#: Faces whose pixel boxes :func:`vertex_regions` finds at once.
REGION_BLOCK_FACES = 1 << 18
#: Vertices a frame's projection takes at once (bounded float64 temporaries).
PROJECT_BLOCK_VERTICES = 1 << 18
#: A region whose cells fill less than this share of its box is cut into tiles ...
SPLIT_FILL = 0.7
#: ... of this many cells a side.
SPLIT_CELLS = 8


@dataclass
class Atlas:
    """Pages (BGR images) and, per face, its page (−1 = untextured) and corner UVs."""

    pages: list[U8]
    face_page: NDArray[np.int16]
    face_uv: NDArray[np.float32]  # (faces, 3, 2)
    regions: int


def frame_regions(corner_uv: F64, width: int, height: int, cell_px: int = 32,
                  pad_px: int = 3) -> tuple[I64, I64]:
    """Group faces (corner pixels ``(k, 3, 2)``) of one frame into regions.

    Returns ``(region_of_face (k,), boxes (R, 4))`` with boxes ``x0, y0, x1, y1`` (x1, y1
    exclusive), clipped to the image (:func:`vertex_regions` with a pixel per corner).
    """
    k = len(corner_uv)
    return vertex_regions(np.asarray(corner_uv, np.float64).reshape(-1, 2),
                          np.arange(3 * k, dtype=np.int64).reshape(k, 3), width, height,
                          cell_px, pad_px)


def vertex_regions(vertex_uv: F64, corner: NDArray[np.integer], width: int, height: int,
                   cell_px: int = 32, pad_px: int = 3) -> tuple[I64, I64]:
    """:func:`frame_regions` of the faces whose corner ``j`` lies at pixel
    ``vertex_uv[corner[:, j]]``; in blocks of :data:`REGION_BLOCK_FACES` faces (a 360° frame
    holds most of a lab mesh: its whole-frame temporaries were ~0.5 GB)."""
    k = len(corner)
    gw, gh = math.ceil(width / cell_px), math.ceil(height / cell_px)

    # the pixel coordinates a column each (1-D gathers: ~2× faster than gathering (k, 3, 2)
    # rows of corners; the same numbers)
    columns = [np.ascontiguousarray(vertex_uv[:, axis]) for axis in (0, 1)]

    def face_boxes(rows: slice) -> tuple[list[I64], list[I64]]:
        """The faces' pixel boxes ``lo``, ``hi`` (exclusive) per axis, padded and clipped."""
        block = corner[rows]
        at = [np.ascontiguousarray(block[:, j]) for j in range(3)]
        lo, hi = [], []
        for column, size in zip(columns, (width, height), strict=True):
            p0, p1, p2 = column[at[0]], column[at[1]], column[at[2]]
            low = np.minimum(np.minimum(p0, p1), p2)
            high = np.maximum(np.maximum(p0, p1), p2)
            del p0, p1, p2
            first = np.floor(low, out=low).astype(np.int64)
            last = np.ceil(high, out=high).astype(np.int64)
            first -= pad_px
            last += pad_px + 1
            np.clip(first, 0, size - 1, out=first)
            np.clip(last, first + 1, size, out=last)
            lo.append(first)
            hi.append(last)
        return lo, hi

    # one pass over the faces, in blocks: each face's box of cells as +1/−1 at its corners
    # of a difference grid (bincounts), the cell of its box's first corner (which decides its
    # region), and per such cell the box around its faces (min and max: any order)
    cells = (gh + 1) * (gw + 1)
    diff = np.zeros(cells, dtype=np.int64)
    face_cell = np.empty(k, dtype=np.int32)
    cell_box = np.empty((4, gh * gw), dtype=np.int64)
    cell_box[:2] = np.iinfo(np.int64).max
    cell_box[2:] = np.iinfo(np.int64).min
    for start in range(0, k, REGION_BLOCK_FACES):
        rows = slice(start, start + REGION_BLOCK_FACES)
        (lo_x, lo_y), (hi_x, hi_y) = face_boxes(rows)
        row0, col0 = lo_y // cell_px * (gw + 1), lo_x // cell_px
        row1, col1 = ((hi_y - 1) // cell_px + 1) * (gw + 1), (hi_x - 1) // cell_px + 1
        diff += (np.bincount(row0 + col0, minlength=cells)
                 - np.bincount(row0 + col1, minlength=cells)
                 - np.bincount(row1 + col0, minlength=cells)
                 + np.bincount(row1 + col1, minlength=cells))
        cell = lo_y // cell_px * gw + col0
        face_cell[rows] = cell
        np.minimum.at(cell_box[0], cell, lo_x)
        np.minimum.at(cell_box[1], cell, lo_y)
        np.maximum.at(cell_box[2], cell, hi_x)
        np.maximum.at(cell_box[3], cell, hi_y)
    covered = (diff.reshape(gh + 1, gw + 1).cumsum(0).cumsum(1)[:gh, :gw] > 0).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(covered, connectivity=8)
    # a sparse region (a diagonal band, an L) is cut into tiles of SPLIT_CELLS cells (by the
    # cell of each face's first corner): its box would be mostly image that no face uses
    box_cells = stats[:, cv2.CC_STAT_WIDTH] * stats[:, cv2.CC_STAT_HEIGHT]
    sparse = (stats[:, cv2.CC_STAT_AREA] < SPLIT_FILL * box_cells) & (
        np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) > SPLIT_CELLS)
    tiles_w = -(-gw // SPLIT_CELLS)
    tiles = tiles_w * (-(-gh // SPLIT_CELLS)) + 1
    cell_row, cell_col = np.divmod(np.arange(gh * gw), gw)
    component = labels.reshape(-1).astype(np.int64)
    tile = (cell_row // SPLIT_CELLS) * tiles_w + cell_col // SPLIT_CELLS + 1
    cell_label = component * tiles + np.where(sparse[component], tile, 0)
    # the labels in use (of cells that are some face's first), numbered in order
    has_face = cell_box[0] != np.iinfo(np.int64).max
    present = np.zeros(len(stats) * tiles, dtype=bool)
    present[cell_label[has_face]] = True
    used = np.flatnonzero(present)
    number = np.cumsum(present) - 1
    boxes = np.empty((len(used), 4), dtype=np.int64)
    boxes[:, :2] = np.iinfo(np.int64).max
    boxes[:, 2:] = np.iinfo(np.int64).min
    cell_region = number[cell_label[has_face]]
    for j, reduce in enumerate((np.minimum, np.minimum, np.maximum, np.maximum)):
        reduce.at(boxes[:, j], cell_region, cell_box[j][has_face])
    region = number[cell_label][face_cell]
    return region, boxes


def pack_shelves(sizes: I64, page_px: int, first: tuple[int, int] | None = None
                 ) -> tuple[I64, I64, I64, list[tuple[int, int]]]:
    """Shelf-pack rectangles ``(R, 2)`` (w, h) into square pages of ``page_px``.

    ``first`` is a rectangle reserved at the start of page 0. Returns ``page, x, y`` per
    rectangle and each page's used ``(width, height)``. Every rectangle must fit a page.
    """
    order = np.argsort(-sizes[:, 1], kind="stable")
    page = np.zeros(len(sizes), dtype=np.int64)
    xs = np.zeros(len(sizes), dtype=np.int64)
    ys = np.zeros(len(sizes), dtype=np.int64)
    used: list[tuple[int, int]] = [(0, 0)]
    current, x, y, shelf_h = 0, 0, 0, 0
    if first is not None:
        x, shelf_h = first[0] + 1, first[1]
        used[0] = first
    for r in order:
        w, h = int(sizes[r, 0]), int(sizes[r, 1])
        if x + w > page_px:  # next shelf
            y, x, shelf_h = y + shelf_h + 1, 0, 0
        if y + h > page_px:  # next page
            current, x, y, shelf_h = current + 1, 0, 0, 0
            used.append((0, 0))
        if shelf_h == 0:
            shelf_h = h
        page[r], xs[r], ys[r] = current, x, y
        used[current] = (max(used[current][0], x + w), max(used[current][1], y + h))
        x += w + 1
    return page, xs, ys, used


#: Per used frame: its faces, their vertices' pixels, each corner's row in them, and the
#: faces' regions (numbered over all frames).
Chart = tuple[I64, F64, NDArray[np.int32], NDArray[np.int32]]


@dataclass
class Charts:
    """What :func:`build_atlas` cuts: per used frame its :data:`Chart`, and per region its
    frame and pixel box ``x0, y0, x1, y1`` (found with ``pad_px`` and ``cell_px``)."""

    charts: list[Chart]
    frame_of: I64
    boxes: I64
    pad_px: int
    cell_px: int


def frame_charts(vertices: NDArray[np.floating], faces: NDArray[np.integer], chosen: I64,
                 frames: FrameSet, *, pad_px: int = 3, cell_px: int = 32) -> Charts:
    """The regions of every used frame (:func:`vertex_regions`), the first step of
    :func:`build_atlas`: it reads only the frame choice (no image), so the texture stage
    finds them on a second thread while the seams are measured."""
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)  # int32 or int64 as given: no copy of the mesh's corners
    # per used frame: its faces, their vertices' pixels with each corner's row in them, and
    # the faces' regions (numbered over all frames); not the corners' pixels (~0.3 GB at lab
    # scale): gathered again per block of faces once the pages are packed
    charts: list[Chart] = []
    region_frame: list[I64] = []
    region_boxes: list[I64] = []
    count = 0
    used_frames = np.unique(chosen[chosen >= 0])
    textured = np.flatnonzero(chosen >= 0)
    # the faces of each used frame: one stable sort (frame numbers are small: a radix sort)
    by_frame = textured[np.argsort(chosen[textured].astype(np.int16) if len(frames) < 2 ** 15
                                   else chosen[textured], kind="stable")]
    bounds = [*np.searchsorted(chosen[by_frame], used_frames).tolist(), len(by_frame)]

    def regions_of(k: int) -> tuple[I64, F64, NDArray[np.int32], NDArray[np.int32], I64]:
        i = int(used_frames[k])
        idx = by_frame[bounds[k]:bounds[k + 1]]
        cam = frames.cameras[i]
        # each vertex of these faces projected once (a scan-grid vertex has six faces), then
        # gathered per corner: the same numbers as projecting every corner
        tri = faces[idx]
        used = np.zeros(len(vertices), dtype=bool)
        used[tri.reshape(-1)] = True
        points = np.flatnonzero(used)
        local = np.zeros(len(vertices), dtype=np.int32)
        local[points] = np.arange(len(points), dtype=np.int32)
        vertex_uv = np.empty((len(points), 2), dtype=np.float64)
        for start in range(0, len(points), PROJECT_BLOCK_VERTICES):  # a point at a time
            part = points[start:start + PROJECT_BLOCK_VERTICES]
            vertex_uv[start:start + len(part)] = project_points(
                vertices[part], cam, float(frames.beta_deg[i]))[0]
        corner = local[tri]
        del tri, used, local
        region, boxes = vertex_regions(vertex_uv, corner, cam.width, cam.height, cell_px,
                                       pad_px)
        return idx, vertex_uv, corner, region.astype(np.int32), boxes

    # a frame per thread (numpy and OpenCV release the GIL); regions numbered in frame order,
    # each frame's faces, corner pixels and regions kept for its UVs once the pages are packed
    with thread_pool(worker_count(len(used_frames))) as pool:
        for i, (idx, vertex_uv, corner, region, boxes) in zip(
                used_frames, pool.map(regions_of, range(len(used_frames))), strict=True):
            region += count
            charts.append((idx, vertex_uv, corner, region))
            region_frame.append(np.full(len(boxes), i, dtype=np.int64))
            region_boxes.append(boxes)
            count += len(boxes)
            del idx, vertex_uv, corner, region
    frame_of = np.concatenate(region_frame) if region_frame else np.zeros(0, np.int64)
    boxes = np.concatenate(region_boxes) if region_boxes else np.zeros((0, 4), np.int64)
    return Charts(charts, frame_of, boxes, pad_px, cell_px)


def build_atlas(vertices: NDArray[np.floating], faces: NDArray[np.integer], chosen: I64,
                frames: FrameSet, gains: F64, *, page_px: int = 4096, texel_scale: float = 1.0,
                pad_px: int = 3, cell_px: int = 32,
                neutral_bgr: tuple[int, int, int] = (128, 128, 128),
                seams: SeamCorrections | None = None, strip_px: float = 20.0,
                patches: Patches | None = None, charts: Charts | None = None,
                progress: ProgressFn = no_progress) -> Atlas:
    """Cut, scale, expose and pack the regions of every used frame; UVs for every face.

    With ``seams``, each region also gets its frame's seam corrections faded over
    ``strip_px`` (:func:`scanpipe.texturing.seams.correction_field`), after the gain.
    ``patches`` (faces textured texel by texel, :mod:`scanpipe.texturing.patches`; their
    ``chosen`` is −1) are packed as squares with a one-texel border. ``charts``: the
    :func:`frame_charts` of ``chosen`` with the same ``pad_px`` and ``cell_px``, when already
    found.
    """
    n_faces = len(faces)
    if charts is None:
        charts = frame_charts(vertices, faces, chosen, frames, pad_px=pad_px, cell_px=cell_px)
    elif (charts.pad_px, charts.cell_px) != (pad_px, cell_px):
        raise ValueError("build_atlas: charts found with another pad_px or cell_px")
    frame_of, boxes = charts.frame_of, charts.boxes
    src_w, src_h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    limit = page_px - 2
    scale = np.minimum(texel_scale, np.minimum(limit / src_w.clip(1), limit / src_h.clip(1)))
    dst = np.stack([np.maximum(1, np.ceil(src_w * scale)),
                    np.maximum(1, np.ceil(src_h * scale))], axis=1).astype(np.int64)
    n_regions = len(dst)
    if patches is not None and len(patches.face):
        side = patches.texels.shape[1] + 2
        dst = np.concatenate([dst, np.full((len(patches.face), 2), side, np.int64)])
    first_h = int(max(NEUTRAL_PX, dst[:, 1].max() if len(dst) else NEUTRAL_PX))
    page, ox, oy, used = pack_shelves(dst, page_px, first=(NEUTRAL_PX, first_h))
    sizes = [(_round_up(w, 4), _round_up(h, 4)) for w, h in used]
    pages = [np.empty((h, w, 3), dtype=np.uint8) for w, h in sizes]
    for p in pages:
        p[:] = neutral_bgr
    levels = np.arange(256, dtype=np.float32)[:, None]

    def cut(r: int) -> None:
        """Region ``r`` cut from its frame, levelled, blended and placed on its page."""
        x0, y0, x1, y1 = (int(b) for b in boxes[r])
        frame = int(frame_of[r])
        source = frames.image(frame)[y0:y1, x0:x1]
        # the gain as a look-up table per channel (one pass, no float image where there is
        # no seam correction); the same float32 arithmetic as the image-wide product
        gained = (levels * gains[frame].astype(np.float32)).reshape(1, 256, 3)
        field = None
        if seams is not None and strip_px > 0 and frame in seams.uv:
            field = correction_field(seams.uv[frame], seams.delta[frame], (x0, y0, x1, y1),
                                     strip_px)
        if field is None:
            patch = cv2.LUT(source, np.clip(gained + 0.5, 0, 255).astype(np.uint8))
        else:
            crop = np.asarray(cv2.LUT(source, gained), dtype=np.float32)
            crop += field
            crop += 0.5
            patch = np.clip(crop, 0, 255, out=crop).astype(np.uint8)
        w, h = int(dst[r, 0]), int(dst[r, 1])
        if (w, h) != (x1 - x0, y1 - y0):
            patch = cv2.resize(patch, (w, h), interpolation=cv2.INTER_AREA)
        pages[page[r]][oy[r]:oy[r] + h, ox[r]:ox[r] + w] = patch

    def cut_frame(rows: range) -> int:
        for r in rows:
            cut(r)
        return rows.stop

    # a frame's regions per thread (each frame decoded once; OpenCV and numpy release the
    # GIL; regions never overlap on the pages); progress from this thread only
    changes = np.flatnonzero(np.diff(frame_of[:n_regions])) + 1
    edges = [0, *changes.tolist(), n_regions] if n_regions else [0]
    runs = [range(a, b) for a, b in pairwise(edges)]
    with thread_pool(worker_count(len(runs))) as pool:
        for finished in pool.map(cut_frame, runs):
            progress("atlas", finished, len(boxes))
    progress("atlas", len(boxes), len(boxes))
    if patches is not None and len(patches.face):
        at = np.arange(n_regions, len(dst))
        for r, square in zip(at.tolist(), patches.texels, strict=True):
            side = square.shape[0] + 2
            pages[page[r]][oy[r]:oy[r] + side, ox[r]:ox[r] + side] = cv2.copyMakeBorder(
                square, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    face_page = np.full(n_faces, -1, dtype=np.int16)
    face_uv = np.empty((n_faces, 3, 2), dtype=np.float32)
    face_uv[:, :, 0] = (NEUTRAL_PX / 2) / sizes[0][0]
    face_uv[:, :, 1] = (NEUTRAL_PX / 2) / sizes[0][1]
    page_width = np.array([s[0] for s in sizes], dtype=np.float64)
    page_height = np.array([s[1] for s in sizes], dtype=np.float64)
    # per region: its page position, box corner, scale and page size, as float64 (exact for
    # these integers: the same arithmetic as on the integer arrays), gathered once per face;
    # u and v apart, from a column of the vertices' pixels each: contiguous (faces, 3) arrays
    # (~25 % faster than strided halves of (faces, 3, 2) ones; the same numbers)
    placed = np.stack([ox[:n_regions], boxes[:, 0], dst[:n_regions, 0] / src_w,
                       page_width[page[:n_regions]], oy[:n_regions], boxes[:, 1],
                       dst[:n_regions, 1] / src_h, page_height[page[:n_regions]]])
    region_page = page[:n_regions].astype(np.int16)
    # per frame, in blocks of faces: the whole mesh's float64 temporaries at once were ~1 GB
    for idx, vertex_uv, corner, region in charts.charts:
        for axis in (0, 1):
            coordinate = np.ascontiguousarray(vertex_uv[:, axis])
            offset, box_corner, scale_of, size = placed[4 * axis:4 * axis + 4]
            for start in range(0, len(idx), UV_BLOCK_FACES):
                reg = region[start:start + UV_BLOCK_FACES]
                uv = coordinate[corner[start:start + UV_BLOCK_FACES]]  # (b, 3)
                uv -= box_corner[reg][:, None]
                uv += 0.5
                uv *= scale_of[reg][:, None]
                uv += offset[reg][:, None]
                uv /= size[reg][:, None]
                done = idx[start:start + UV_BLOCK_FACES]
                face_uv[done, :, axis] = uv
                if axis == 0:
                    face_page[done] = region_page[reg]
    charts.charts.clear()  # consumed: its memory goes now, not when the caller lets go
    if patches is not None and len(patches.face):
        texels = float(patches.texels.shape[1])
        at = np.arange(n_regions, len(dst))
        local = np.array([[0.0, 0.0], [texels, 0.0], [0.0, texels]])  # corners 0, 1, 2
        page_w = np.array([s[0] for s in sizes], dtype=np.float64)[page[at]]
        page_h = np.array([s[1] for s in sizes], dtype=np.float64)[page[at]]
        face_uv[patches.face, :, 0] = (ox[at, None] + 1 + local[None, :, 0]) / page_w[:, None]
        face_uv[patches.face, :, 1] = (oy[at, None] + 1 + local[None, :, 1]) / page_h[:, None]
        face_page[patches.face] = page[at]
    return Atlas(pages, face_page, face_uv, n_regions)


def _round_up(value: int, multiple: int) -> int:
    return max(multiple, -(-value // multiple) * multiple)
