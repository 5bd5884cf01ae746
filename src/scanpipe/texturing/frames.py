"""Camera frames for texturing: decode, place at the platform angle, rate sharpness, choose.

A frame is placed by the platform angle at its capture time (:func:`scanpipe.motion.beta_deg_at`)
and the pose of its camera on the platform (:func:`scanpipe.camera.camera_pose_in_rig`).
Sharpness is the variance of the Laplacian of a quarter-size grey decode: cheap enough to rate
every frame of a video, and low for frames smeared by the turning platform.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from scanpipe.camera import camera_pose_in_rig
from scanpipe.errors import StageError
from scanpipe.images import MAX_FRAME_PX, decode_image_bytes
from scanpipe.motion import beta_deg_at
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.rig import CameraConfig, Rig
from scanpipe.schema import FRAMES
from scanpipe.threads import omp_threads, thread_pool

U8 = NDArray[np.uint8]
F64 = NDArray[np.float64]

#: How much :meth:`FrameSet.reduced` shrinks a frame (OpenCV's reduced JPEG decode).
REDUCED_FACTOR = 4

#: The frame columns texturing reads (see :data:`scanpipe.schema.FRAMES`).
FRAME_COLUMNS = ("camera_id", "log_time_ns", "sequence", "data")


@dataclass
class FrameSet:
    """The frames chosen for texturing, one entry per frame; images decoded on demand (BGR).

    A few decoded images are cached (the stages walk the frames in order), so a video's worth
    of Full-HD frames never sits in memory at once.
    """

    camera_ids: list[str]
    cameras: list[CameraConfig]
    sequences: NDArray[np.int64]
    times_ns: NDArray[np.int64]
    beta_deg: F64
    sharpness: F64
    encoded: list[bytes] = field(repr=False)
    #: Frames in the artifact before the choice (for the report).
    considered: int = 0
    cache_size: int = 8
    _cache: OrderedDict[int, U8] = field(default_factory=OrderedDict, repr=False)
    _reduced: dict[int, U8] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __len__(self) -> int:
        return len(self.encoded)

    def image(self, index: int) -> U8:
        """Frame ``index`` decoded (BGR), the size its camera says (safe from several threads:
        the cache is locked, the decode is not)."""
        with self._lock:
            if index in self._cache:
                self._cache.move_to_end(index)
                return self._cache[index]
        image = decode_image(self.encoded[index], f"frame {self.sequences[index]} of "
                                                   f"{self.cameras[index].id!r}")
        cam = self.cameras[index]
        if image.shape[:2] != (cam.height, cam.width):
            raise StageError(f"frames: frame {self.sequences[index]} of {cam.id!r} is "
                             f"{image.shape[1]}×{image.shape[0]}, its other frames "
                             f"{cam.width}×{cam.height}")
        with self._lock:
            self._cache[index] = image
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return image

    def reduced(self, index: int) -> U8:
        """Frame ``index`` decoded at a quarter of its size (BGR; :data:`REDUCED_FACTOR`), for
        colour samples (JPEG decodes this 5–10× faster than in full). Kept: they are small."""
        if index not in self._reduced:
            cam = self.cameras[index]
            image = decode_image_bytes(self.encoded[index], f"frames: frame "
                                       f"{self.sequences[index]} of {cam.id!r}", MAX_FRAME_PX,
                                       cv2.IMREAD_REDUCED_COLOR_4, StageError)
            expected = (-(-cam.height // REDUCED_FACTOR), -(-cam.width // REDUCED_FACTOR))
            if image.shape[:2] != expected:  # a PNG or an odd size: reduce the full decode
                image = np.asarray(cv2.resize(self.image(index), expected[::-1],
                                              interpolation=cv2.INTER_AREA), dtype=np.uint8)
            self._reduced[index] = image
        return self._reduced[index]

    def centre(self, index: int) -> F64:
        """The camera centre of frame ``index`` in the rig frame."""
        return camera_pose_in_rig(self.cameras[index], float(self.beta_deg[index]))[1]

    def relative_sharpness(self) -> F64:
        """Sharpness divided by the sharpest frame of the same camera (1 = sharpest)."""
        result = np.ones(len(self), dtype=np.float64)
        ids = np.asarray(self.camera_ids)
        for cam_id in set(self.camera_ids):
            mask = ids == cam_id
            best = float(self.sharpness[mask].max())
            if best > 0:
                result[mask] = self.sharpness[mask] / best
        return result


def worker_count(items: int, limit: int = 4) -> int:
    """Threads for the texture stage's parallel loops over ``items``: ``OMP_NUM_THREADS`` when
    set (:func:`scanpipe.threads.omp_threads`: a batch worker's share of the cores, as
    :func:`scanpipe.batch.worker_threads` reads it), else the CPU count; at most ``limit`` and
    ``items``, at least 1."""
    cores = omp_threads() or os.cpu_count() or 1
    return max(1, min(cores, limit, items))


def camera_for_size(cam: CameraConfig, width: int, height: int) -> CameraConfig:
    """``cam`` with intrinsics scaled to frames of ``width`` × ``height`` (same aspect ratio).

    A camera calibrated at Full HD and recorded at 1280 × 720 keeps its lens; only the pixel
    grid changes. A different aspect ratio is a crop we cannot know: :class:`StageError`.
    """
    if (width, height) == (cam.width, cam.height):
        return cam
    sx, sy = width / cam.width, height / cam.height
    if abs(sx - sy) > 0.01 * max(sx, sy):
        raise StageError(
            f"frames: camera {cam.id!r} recorded {width}×{height}, the rig says "
            f"{cam.width}×{cam.height} (a different aspect ratio); recalibrate with "
            "scanpipe calibrate-camera"
        )
    return cam.model_copy(update={
        "width": width, "height": height, "fx": cam.fx * sx, "fy": cam.fy * sy,
        "cx": (cam.cx + 0.5) * sx - 0.5, "cy": (cam.cy + 0.5) * sy - 0.5,
    })


def decode_image(data: bytes, what: str) -> U8:
    """A colour (BGR) image from encoded bytes; :class:`StageError` naming ``what`` if broken
    or larger than :data:`~scanpipe.images.MAX_FRAME_PX` (checked before decoding)."""
    return decode_image_bytes(data, f"frames: {what}", MAX_FRAME_PX, cv2.IMREAD_COLOR,
                              StageError)


def sharpness_of(data: bytes, what: str) -> float:
    """Variance of the Laplacian of a quarter-size grey decode (higher is sharper)."""
    grey = decode_image_bytes(data, f"frames: {what}", MAX_FRAME_PX,
                              cv2.IMREAD_REDUCED_GRAYSCALE_4, StageError)
    # OpenCV's mean and deviation in one pass: a third of numpy's var here
    _, deviation = cv2.meanStdDev(cv2.Laplacian(grey, cv2.CV_32F))
    return float(deviation[0, 0]) ** 2


#: Sharpness of encoded frames already rated in this process, by a digest of their bytes: the
#: texture and export stages of one run both choose frames from the same video (~5 s of CPU
#: each at lab scale). By content, so a different frame can never take another's rating.
_RATED: dict[bytes, float] = {}
#: Ratings kept at most (a float and a 32-byte digest each); the cache starts over when full.
RATED_LIMIT = 1 << 16


def _content_key(data: bytes | pa.Buffer) -> bytes:
    """The key of an encoded frame in :data:`_RATED`: a SHA-256 digest of its bytes (read in
    place from an Arrow buffer: no copy into a Python ``bytes``; on CPUs with SHA
    instructions twice as fast as BLAKE2b, 0.4 ms for a 600 KB 360° frame)."""
    return hashlib.sha256(memoryview(data)).digest()


def rate_frames(data: pa.ChunkedArray, rows: NDArray[np.int64], sequences: NDArray[np.int64],
                camera_ids: NDArray[np.object_], progress: ProgressFn = no_progress) -> F64:
    """:func:`sharpness_of` of each of ``rows`` of the encoded frames ``data``, on one thread
    per core (OpenCV decodes without the GIL: a video's worth of frames is most of the wall
    time of choosing); each distinct content is rated once, also across calls in this process
    (:data:`_RATED`); the first broken frame raises its :class:`StageError`."""
    workers = worker_count(len(rows))
    with thread_pool(workers) as pool:
        keys = list(pool.map(lambda row: _content_key(data[int(row)].as_buffer()), rows))
        ratings = {key: _RATED[key] for key in set(keys) if key in _RATED}
        # one row per content not rated yet: identical frames (a still platform) are decoded
        # once, never by two threads at a time
        todo: dict[bytes, int] = {}
        for index, key in enumerate(keys):
            if key not in ratings and key not in todo:
                todo[key] = index
        pending = list(todo.items())
        batch = 16
        for start in range(0, len(pending), batch):
            block = pending[start:start + batch]
            values = pool.map(lambda item: sharpness_of(
                data[int(rows[item[1]])].as_py(),
                f"frame {sequences[rows[item[1]]]} of {camera_ids[rows[item[1]]]!r}"), block)
            ratings.update(zip((key for key, _ in block), values, strict=True))
            progress("rate frames", len(rows) - len(pending) + start + len(block), len(rows))
        if not pending:  # every content rated before: the bar still ends
            progress("rate frames", len(rows), len(rows))
    if len(_RATED) + len(todo) > RATED_LIMIT:
        _RATED.clear()
    _RATED.update((key, ratings[key]) for key in todo)
    return np.array([ratings[key] for key in keys], dtype=np.float64)


def _shown_id(camera_id: str, limit: int = 60) -> str:
    """A camera id for a message: quoted and escaped (``repr``), long ones cut short."""
    text = repr(camera_id)
    return text if len(text) <= limit else f"{text[:limit - 1]}…({len(camera_id)} characters)"


def known_camera_frames(frames: pa.Table, rig: Rig) -> tuple[pa.Table, list[str]]:
    """The frames of cameras the rig knows, and one warning per camera id it does not know.

    A camera id comes from the recording's channel name (``/camera/<id>/image``), which
    anything may have written: a path-like, very long or unicode id is skipped, named, never
    used as a path.
    """
    FRAMES.check(frames, FRAME_COLUMNS)
    known = {c.id for c in rig.cameras}
    ids = frames.column("camera_id")
    counts = Counter(ids.to_pylist())
    unknown = sorted((c for c in counts if c not in known), key=str)
    if not unknown:
        return frames, []
    keep = pc.is_in(ids, value_set=pa.array(sorted(known), pa.string()))
    warnings = [f"frames: skipped {counts[c]} frame(s) of camera {_shown_id(str(c))}: not in "
                f"the rig (cameras: {', '.join(sorted(known)) or 'none'})" for c in unknown]
    return frames.filter(pc.fill_null(keep, False)), warnings


def pinhole_frames(frames: pa.Table, rig: Rig) -> tuple[pa.Table, Rig, list[str]]:
    """The frames and the rig without the 360° (equirect) cameras, and those cameras' ids: for
    what only a pinhole describes (the paper's panorama, COLMAP, E57 pinhole images)."""
    equirect = [c.id for c in rig.cameras if c.model == "equirect"]
    if not equirect:
        return frames, rig, []
    keep = pc.invert(pc.is_in(frames.column("camera_id"), value_set=pa.array(equirect)))
    pinholes = tuple(c for c in rig.cameras if c.model == "pinhole")
    return (frames.filter(pc.fill_null(keep, False)), rig.model_copy(update={"cameras": pinholes}),
            equirect)


def choose_frames(
    frames: pa.Table,
    motor: pa.Table,
    rig: Rig,
    spacing_deg: float,
    stride: int = 1,
    progress: ProgressFn = no_progress,
    equirect_spacing_deg: float | None = None,
) -> FrameSet:
    """The sharpest frame per camera in every ``spacing_deg`` bin of platform angle.

    ``stride`` first keeps every n-th frame of each camera (in time order); ``spacing_deg`` 0
    keeps every remaining frame. A 360° camera's frames all see the whole room, so fewer
    serve: ``equirect_spacing_deg`` (when given) is their bin instead. Frames of cameras the
    rig does not know are an error.
    """
    FRAMES.check(frames, FRAME_COLUMNS)
    if frames.num_rows == 0:
        raise StageError("frames: the recording has no camera frames; nothing to texture from")
    camera_ids = np.asarray(frames.column("camera_id").to_pylist(), dtype=object)
    times = frames.column("log_time_ns").to_numpy().astype(np.int64)
    sequences = frames.column("sequence").to_numpy().astype(np.int64)
    known = {c.id for c in rig.cameras}
    unknown = sorted(set(camera_ids.tolist()) - known)
    if unknown:
        shown = ", ".join(_shown_id(str(c)) for c in unknown)
        raise StageError(f"frames: camera(s) {shown} are not in the rig "
                         f"(cameras: {', '.join(sorted(known)) or 'none'})")
    order = np.lexsort((times, camera_ids.astype(str)))
    rank = np.empty(len(order), dtype=np.int64)
    cam_sorted = camera_ids[order]
    starts = np.r_[0, np.flatnonzero(cam_sorted[1:] != cam_sorted[:-1]) + 1]
    run_start = np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    rank[order] = np.arange(len(order)) - run_start
    kept = np.flatnonzero(rank % max(1, stride) == 0)

    beta = beta_deg_at(times[kept], motor, rig.motor)
    data = frames.column("data")
    sharp = rate_frames(data, kept, sequences, camera_ids, progress)
    spacing = np.full(len(kept), spacing_deg)
    if equirect_spacing_deg is not None:
        equirect = {c.id for c in rig.cameras if c.model == "equirect"}
        spacing[np.isin(camera_ids[kept].astype(str), sorted(equirect))] = equirect_spacing_deg
    if spacing_deg > 0 or equirect_spacing_deg:
        bins = np.where(spacing > 0, np.round(beta / np.where(spacing > 0, spacing, 1.0)),
                        np.arange(len(kept))).astype(np.int64)
        group = np.lexsort((-sharp, bins, camera_ids[kept].astype(str)))
        key_cam, key_bin = camera_ids[kept][group], bins[group]
        first = np.r_[True, (key_cam[1:] != key_cam[:-1]) | (key_bin[1:] != key_bin[:-1])]
        chosen = np.sort(group[first])
    else:
        chosen = np.arange(len(kept))
    rows = kept[chosen]
    encoded = [data[int(row)].as_py() for row in rows]
    sized: dict[str, CameraConfig] = {}
    for cam in rig.cameras:  # the first frame of each camera gives the size of all its frames
        first = next((k for k, row in enumerate(rows) if camera_ids[row] == cam.id), None)
        if first is not None:
            height, width = decode_image(
                encoded[first], f"frame {sequences[rows[first]]} of {cam.id!r}").shape[:2]
            sized[cam.id] = camera_for_size(cam, width, height)
    return FrameSet(
        camera_ids=[str(c) for c in camera_ids[rows]],
        cameras=[sized[str(c)] for c in camera_ids[rows]],
        sequences=sequences[rows], times_ns=times[rows], beta_deg=beta[chosen],
        sharpness=sharp[chosen], encoded=encoded, considered=frames.num_rows,
    )
