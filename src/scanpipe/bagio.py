"""ROS bags in: a ROS 1 ``.bag`` or a ROS 2 bag (SQLite ``.db3`` or MCAP) to a recording.

Read with ``rosbags`` (pure Python, no ROS install). What is taken (docs/import.md):

- **profiles** from ``sensor_msgs/LaserScan`` (or ``MultiEchoLaserScan``: its first echo), one
  ``scanpipe.Profile`` per message on ``/scanner/profiles``. A range outside
  ``[range_min, range_max]``, NaN or ±inf is no return (NaN). Times: the header stamp is the
  first ray's time (ROS convention), the last ray's is ``stamp + (n − 1) · time_increment``
  (unknown when ``time_increment`` is 0); a zero stamp falls back to the bag's log time.
- **the beam angle**: a LaserScan angle θ is counter-clockwise about the scanner's z from its
  +x. scanpipe's scan frame has the return at ``(r sin α, r cos α, 0)``; with
  ``α = θ + 90°`` that is ``(r cos θ, −r sin θ, 0)``, the ROS point turned 180° about x. So
  α grows with θ (the beam step is ``angle_increment``, in degrees) and the mount carries the
  turn: ``p_scan = F · p_laser``, ``F = diag(1, −1, −1)``.
- **the platform angle** β from ``sensor_msgs/JointState`` (the position of one joint, radians)
  or from TF (the yaw of CHILD in PARENT). ROS is z-up; scanpipe's rig frame is y-up with the
  platform turning about y. The rig frame is the ROS base frame mapped by
  ``G: (x, y, z)_ros → (x, z, −y)_scanpipe`` (a proper rotation, −90° about x). A positive
  (counter-clockwise seen from above, right-handed about +z) turn ψ of the platform is the
  right-handed turn about +y in the rig frame, which scanpipe writes as ``β = −ψ``
  (:func:`scanpipe.geometry.platform_rotation` turns by −β about +y).
- **motor states**: β as ``MotorState.step_count = round(β / pulse step)`` with a pulse step of
  :data:`PULSE_STEP_DEG` (1e-4°, i.e. ≤ 0.9 µm at 500 m … 1.7 µm at 1 m: far below any
  scanner's noise), ``moving = true`` throughout: the assemble stage runs in continuous mode and
  interpolates β per sample between the angle reports.
- **the mount**: with ``--tf PARENT:CHILD`` the laser's pose in the platform frame comes from
  TF (CHILD → the scan's ``frame_id``, static transforms, composed); scanpipe's mount is then
  ``R = G · R_platform_laser · F``, ``t = G · t_platform_laser``. Otherwise the zero mount
  (the paper's): the laser's +x horizontal along the platform's x, its +y pointing down, its
  scan plane holding the motor axis. ``--rig`` gives a calibrated rig instead (its motor step
  is replaced by :data:`PULSE_STEP_DEG`, the step the angles are written in).
- **frames** from ``sensor_msgs/CompressedImage`` (JPEG and 8-bit PNG kept as they are; a
  16-bit PNG is a depth image, skipped) and ``sensor_msgs/Image`` (``rgb8``, ``bgr8``,
  ``rgba8``, ``bgra8``, ``mono8`` encoded to PNG); a ``CameraInfo`` beside
  the image topic gives the camera's intrinsics (its pose stays the default: pass ``--rig``).
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections import Counter, defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from scanpipe.errors import RecordingError, UsageError
from scanpipe.images import encode_png
from scanpipe.intrinsics_io import ros_roi_binning
from scanpipe.motion import beyond_log
from scanpipe.params import describe_validation_error
from scanpipe.protocol.profile import ECHO_FULL_SCALE, are_fractions, ranges_between
from scanpipe.recording import schemas
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import CameraConfig, Rig, default_rig, rig_from_dict, rig_to_dict

F64 = NDArray[np.float64]

LASER_SCAN = "sensor_msgs/msg/LaserScan"
MULTI_ECHO = "sensor_msgs/msg/MultiEchoLaserScan"
JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
RAW_IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
SCAN_TYPES = (LASER_SCAN, MULTI_ECHO)
IMAGE_TYPES = (COMPRESSED_IMAGE, RAW_IMAGE)
#: The platform turn per pulse the imported angles are written in (see the module docstring).
PULSE_STEP_DEG = 1e-4
#: ROS base frame (z up) → scanpipe rig frame (y up): (x, y, z) → (x, z, −y).
G: F64 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: ROS laser frame → scanpipe scan frame for α = θ + 90°: a half turn about x.
F: F64 = np.diag([1.0, -1.0, -1.0])
#: A joint counts as moving when its position spans more than this (radians).
_MOVING_RAD = 1e-6
_MAX_STEPS = 2**31 - 1


class BagError(RecordingError):
    """A ROS bag that cannot be imported (unreadable, no laser scan, ambiguous topics …)."""


@dataclass(frozen=True)
class Topic:
    """One topic of a bag: its message type and message count."""

    name: str
    msgtype: str
    count: int

    def __str__(self) -> str:
        return f"{self.name} ({self.msgtype.replace('/msg/', '/')}, {self.count})"


#: The echo's (u16) full scale: intensities normalised to 0…1 are fractions of it.
#: Beam steps that differ by up to this share from scan to scan are one step that follows the
#: head's measured speed (LDRobot's ldlidar ROS drivers): resampled onto one grid. More is two
#: settings in one bag, refused.
MAX_STEP_SPREAD = 0.05


@dataclass
class BagContent:
    """What :func:`import_bag` read from a bag before writing the recording."""

    profiles: list[Any] = field(default_factory=list)  # (log_ns, schemas.Profile)
    angles: list[tuple[int, float]] = field(default_factory=list)  # (time_ns, β in degrees)
    images: list[tuple[str, int, bytes, str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _stamp_ns(header: Any, log_time_ns: int) -> int:
    stamp = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return stamp if stamp > 0 else int(log_time_ns)


def _frame(name: str) -> str:
    return name.lstrip("/")


#: A bag's kind by its first bytes: rosbags chooses its reader by the name's suffix.
_MAGIC = ((b"#ROSBAG V2.0\n", ".bag"), (b"\x89MCAP0\r\n", ".mcap"),
          (b"SQLite format 3\x00", ".db3"))
_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _kind(path: Path) -> str | None:
    """``.bag``, ``.mcap`` or ``.db3`` by the file's first bytes; None for anything else."""
    with path.open("rb") as handle:
        head = handle.read(16)
    return next((suffix for magic, suffix in _MAGIC if head.startswith(magic)), None)


def _split_index(path: Path) -> tuple[int, str]:
    """rosbag2 names a split bag's files NAME_0, NAME_1 …: their order."""
    match = re.search(r"_(\d+)$", path.stem)
    return (int(match.group(1)) if match else -1, path.name)


#: Split parts of one ROS 1 recording follow each other: the next part's first message comes
#: within this of the previous part's last (rosbag record switches files between two messages).
_SPLIT_GAP_NS = 2_000_000_000


def _ros1_span_ns(path: Path) -> tuple[int, int] | None:
    """(first, last) message time of a ROS 1 bag from its index; None if it cannot be read."""
    from rosbags.rosbag1 import Reader

    try:
        with Reader(path) as reader:
            return int(reader.start_time), int(reader.end_time)
    except Exception:  # rosbags raises several types for damaged files
        return None


def _split_parts(path: Path, warnings: list[str]) -> list[Path]:
    """The parts of the split recording ``path`` belongs to, in order: ``NAME_0.bag``,
    ``NAME_1.bag`` … (``rosbag record --split``), or rosbag2's ``NAME_0.db3`` / ``.mcap`` …
    beside each other. Given one part, only that part's share of the scan was imported. A ROS 1
    part is joined by the neighbours whose times continue it (two scans named ``scan_0.bag``,
    ``scan_1.bag`` by hand are not one recording: the gap between them tells, and the part is
    read alone, warned); rosbag2 writes a bag's parts into its own folder, so its siblings
    are its parts. ``[path]`` when it is not a part."""
    match = re.fullmatch(r"(.*)_(\d+)", path.stem)
    kind = _kind(path) if path.is_file() else None
    if match is None or kind is None:
        return [path]
    prefix, suffix = match.group(1), path.suffix
    siblings = {}
    for candidate in path.parent.glob(f"{glob_escape(prefix)}_*{glob_escape(suffix)}"):
        number = re.fullmatch(rf"{re.escape(prefix)}_(\d+)", candidate.stem)
        if number and candidate.is_file() and _kind(candidate) == kind:
            siblings[int(number.group(1))] = candidate
    own = int(match.group(2))
    run = [own]  # the consecutive numbers around the given part
    while run[0] - 1 in siblings:
        run.insert(0, run[0] - 1)
    while run[-1] + 1 in siblings:
        run.append(run[-1] + 1)
    parts = [siblings[n] for n in run]
    if kind == ".bag" and len(parts) > 1:
        spans = [_ros1_span_ns(part) for part in parts]
        start = end = run.index(own)
        while start > 0 and _continues(spans[start - 1], spans[start]):
            start -= 1
        while end < len(parts) - 1 and _continues(spans[end], spans[end + 1]):
            end += 1
        if start == end:
            warnings.append(
                f"{path.name}: files named like parts of a split recording lie beside it "
                f"({', '.join(p.name for p in parts if p != path)}), but their times do not "
                "continue it: read alone")
            return [path]
        parts = parts[start:end + 1]
    if len(parts) > 1:
        warnings.append(f"{path.name}: one part of a split recording: read with its parts "
                        f"{', '.join(p.name for p in parts)}")
    unclosed = path.parent / f"{prefix}_{run[-1] + 1}{suffix}.active"
    if kind == ".bag" and parts[-1] == siblings[run[-1]] and unclosed.is_file():
        warnings.append(f"{unclosed.name}: the next part, left unclosed by its recorder (no "
                        "index), is not read: run `rosbag reindex` on it and import again to "
                        "include the end of the scan")
    return parts


def _continues(before: tuple[int, int] | None, after: tuple[int, int] | None) -> bool:
    """The bag with span ``after`` continues the one with span ``before`` (split parts)."""
    if before is None or after is None:
        return False
    gap = after[0] - before[1]
    return -_SPLIT_GAP_NS // 4 <= gap <= _SPLIT_GAP_NS


def _mcap_complete(path: Path) -> bool:
    """An MCAP file that ends in its magic (a recorder killed mid-write leaves none)."""
    size = path.stat().st_size
    with path.open("rb") as handle:
        handle.seek(max(size - len(_MCAP_MAGIC), 0))
        return size > 2 * len(_MCAP_MAGIC) and handle.read() == _MCAP_MAGIC


def _storage_paths(path: Path, scratch: Path, warnings: list[str]) -> list[Path]:
    """What to hand rosbags for ``path``: the bag folder itself when it is whole, else its
    storage files, each under a name rosbags reads (its suffix) and each MCAP cut before its
    end recovered into ``scratch`` (the bag is never changed). Warnings say what was done."""
    if path.is_dir():
        files = sorted((p for p in path.iterdir() if p.is_file() and _kind(p) in (".db3", ".mcap")),
                       key=_split_index)
        has_metadata = (path / "metadata.yaml").is_file()
        if has_metadata and all(_mcap_complete(f) for f in files if _kind(f) == ".mcap"):
            return [path]
        if not files:
            raise BagError(f"{path}: a folder with no metadata.yaml and no .db3 or .mcap file; "
                           "expected a ROS 2 bag folder (metadata.yaml and its storage files)")
        if not has_metadata:
            warnings.append(f"{path}: no metadata.yaml (its recorder was stopped before writing "
                            f"it?): read from its storage files {', '.join(f.name for f in files)}")
    else:
        files = _split_parts(path, warnings)
    kinds = {f: _kind(f) for f in files}
    if None in kinds.values():
        raise BagError(f"{path}: not a readable ROS bag (it starts with neither '#ROSBAG "
                       "V2.0' (ROS 1), 'SQLite format 3' (a ROS 2 .db3) nor the MCAP magic "
                       "(a ROS 2 .mcap))")
    if len(set(kinds.values())) > 1:
        raise BagError(f"{path}: storage files of different kinds "
                       f"({', '.join(f'{f.name}: {k}' for f, k in kinds.items())}); "
                       "one bag has one")
    paths = []
    for file, kind in kinds.items():
        if kind == ".mcap" and not _mcap_complete(file):
            paths.append(_recovered_mcap(file, scratch, warnings))
        elif file.suffix != kind:
            link = scratch / f"{file.name}{kind}"
            link.symlink_to(file.resolve())
            paths.append(link)
        else:
            paths.append(file)
    return paths


def _recovered_mcap(file: Path, scratch: Path, warnings: list[str]) -> Path:
    """The complete chunks of an MCAP bag cut before its end, copied into ``scratch``."""
    from scanpipe.recording.catalogue import RecoveryWriteError, recover_mcap

    out = scratch / f"{file.stem}-{len(list(scratch.iterdir()))}.mcap"
    try:
        report = recover_mcap(file, out)
    except RecoveryWriteError as err:
        raise BagError(f"{file}: its complete chunks cannot be copied into the scratch folder "
                       f"{scratch} to be read ({err.reason}); make "
                       "room there or set TMPDIR to a folder with room for the bag") from err
    except RecordingError as err:
        raise BagError(f"{file}: an MCAP bag cut before its end with nothing readable in it "
                       f"({err})") from err
    lost = report["loss"]
    warnings.append(f"{file.name}: cut before its end (no summary: its recorder was stopped "
                    f"mid-write): {report['messages']} messages of its complete chunks read, "
                    f"about {lost['bytes']} bytes lost at the cut")
    return out


_IDL_SEPARATOR = "=" * 80 + "\n"


def _definition_types(connection: Any) -> dict[str, Any]:
    """The types one connection's own message definition declares (rosbags' parsers).

    rosbag2 stores a type defined in IDL as its .idl files verbatim, ``#include`` lines and
    all, which rosbags' IDL parser rejects: they are dropped (the included types come as their
    own parts of the definition)."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    definition = connection.msgdef
    if definition.format == MessageDefinitionFormat.MSG:
        return dict(get_types_from_msg(definition.data, connection.msgtype))
    text = str(definition.data)
    parts = ([part.split("\n", 1)[1] for part in text.split(_IDL_SEPARATOR)[1:]]
             if text.startswith(f"{_IDL_SEPARATOR}IDL: ") else [text])
    types: dict[str, Any] = {}
    for part in parts:
        types.update(get_types_from_idl(re.sub(r"(?m)^[ \t]*#[ \t]*include\b.*$", "", part)))
    return types


def _tolerant_reader(paths: Sequence[Path], warnings: list[str]) -> Any:
    """A rosbags AnyReader that parses each connection's message definition on its own.

    AnyReader parses every topic's definition when it opens and refuses the whole bag when one
    fails (a custom type defined in IDL, a definition its parser does not know) or when a
    stored type hash differs from its own: a bag with an unrelated odd topic could not be
    imported. Here a definition that fails is reported and its topic left to ROS 2 Humble's
    types (ROS 2) or unreadable; the bag's own definitions override Humble's."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores, get_typestore

    humble = get_typestore(Stores.ROS2_HUMBLE)

    class TolerantReader(AnyReader):  # type: ignore[misc]
        def _open(self) -> None:
            assert self.stack
            for reader in self.readers:
                self.stack.enter_context(reader)
            connections = [c for reader in self.readers for c in reader.connections]
            types: dict[str, Any] = dict(humble.fielddefs) if self.is2 else {}
            failed: dict[str, str] = {}
            for connection in connections:
                if connection.msgdef.format == MessageDefinitionFormat.NONE:
                    continue
                try:
                    types.update(_definition_types(connection))
                except Exception:  # rosbags' parsers raise several types
                    failed[connection.topic] = connection.msgtype
            typestore = get_typestore(Stores.EMPTY)
            typestore.register(types)
            for topic, msgtype in sorted(failed.items()):
                fallback = ("read with ROS 2 Humble's definition" if msgtype in types
                            else "its messages cannot be read")
                warnings.append(f"{topic} ({msgtype}): its message definition cannot be "
                                f"parsed: {fallback}")
            self.connections = connections
            self.typestore = typestore

    return TolerantReader(paths)


def open_bag(path: Path, scratch: Path, warnings: list[str]) -> Any:
    """An opened ``rosbags`` AnyReader; every failure is one :class:`BagError` line.

    ``scratch`` is an empty folder that outlives the reader (links and recovered copies go
    there); what was done to read a damaged bag goes into ``warnings``.
    """
    if not path.exists():
        raise BagError(f"{path}: not found")
    try:
        paths = _storage_paths(path, scratch, warnings)
        reader = _tolerant_reader(paths, warnings)
        reader.open()
    except BagError:
        raise
    except Exception as err:  # rosbags raises many types for damaged files
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        if "not indexed" in reason:
            raise BagError(f"{path}: a ROS 1 bag without its index (its recorder was stopped "
                           "before closing it, as NAME.bag.active is): run `rosbag reindex` on "
                           "it and import the result") from err
        raise BagError(f"{path}: not a readable ROS bag ({reason}); expected a ROS 1 .bag or "
                       "a ROS 2 bag (a folder with metadata.yaml, or its .db3/.mcap)") from err
    return reader


def bag_topics(reader: Any) -> list[Topic]:
    """Every topic of an opened bag, with its type and count, by name."""
    counts: Counter[tuple[str, str]] = Counter()
    for c in reader.connections:
        counts[(c.topic, c.msgtype)] += int(c.msgcount)
    return [Topic(t, m, n) for (t, m), n in sorted(counts.items())]


def _listing(topics: Sequence[Topic]) -> str:
    return "; ".join(str(t) for t in topics) if topics else "no topics"


def choose_scan_topic(path: Path, topics: Sequence[Topic], requested: str | None) -> Topic:
    """The laser scan topic: the one requested, or the only one; else one error line."""
    scans = [t for t in topics if t.msgtype in SCAN_TYPES]
    if requested is not None:
        match = [t for t in topics if t.name == requested]
        if not match:
            raise BagError(f"{path}: --scan {requested}: no such topic; laser scan topics: "
                           f"{_listing(scans)}")
        if match[0].msgtype not in SCAN_TYPES:
            raise BagError(f"{path}: --scan {requested}: is {match[0].msgtype}, not a "
                           f"LaserScan; laser scan topics: {_listing(scans)}")
        return match[0]
    if not scans:
        clouds = [t for t in topics if t.msgtype == POINT_CLOUD]
        hint = ("; sensor_msgs/PointCloud2 is not taken (assembled or converted scans, "
                "laser_assembler's: no beam grid to rebuild a profile from, usually in a moving "
                "frame): export it to PCD/PLY with ROS tools and use scanpipe import-points"
                if clouds else "")
        raise BagError(f"{path}: no laser scan (sensor_msgs/LaserScan or MultiEchoLaserScan) "
                       f"in the bag; found: {_listing(topics)}{hint}")
    if len(scans) > 1:
        raise BagError(f"{path}: {len(scans)} laser scan topics; choose one with --scan: "
                       f"{_listing(scans)}")
    return scans[0]


def _messages(reader: Any, topics: Sequence[str]) -> Iterator[tuple[Any, int, Any]]:
    """(connection, log time, message) of the named topics, in log-time order."""
    connections = [c for c in reader.connections if c.topic in topics]
    if not connections:
        return
    for connection, log_time, raw in reader.messages(connections=connections):
        yield connection, int(log_time), reader.deserialize(raw, connection.msgtype)


def _profile(msg: Any, msgtype: str, log_time_ns: int, index: int
             ) -> tuple[int, Any, dict[str, float]]:
    """One LaserScan / MultiEchoLaserScan as (log time, schemas.Profile, its scan facts)."""
    if msgtype == MULTI_ECHO:
        ranges = np.array([e.echoes[0] if len(e.echoes) else np.nan for e in msg.ranges],
                          np.float64)
        intensities = np.array([e.echoes[0] if len(e.echoes) else 0.0
                                for e in msg.intensities], np.float64)
    else:
        ranges = np.asarray(msg.ranges, np.float64)
        intensities = np.asarray(msg.intensities, np.float64)
    lo, hi = float(msg.range_min), float(msg.range_max)
    with np.errstate(invalid="ignore"):
        # range_max itself is a no-return too: drivers that do not follow REP 117's +inf
        # (LMS1xx's default, Gazebo's laser plugin) publish exactly range_max for no echo
        at_max = ranges == np.float64(np.float32(hi))
        no_return = ~np.isfinite(ranges) | (ranges < lo) | (ranges > hi) | at_max
    ranges = np.where(no_return, np.nan, ranges)
    start = _stamp_ns(msg.header, log_time_ns)
    n = ranges.size
    dt = float(msg.time_increment)
    # dt < 0: the beams were taken from the last to the first (ranges[0] last, at the stamp)
    end = start + round(max(n - 1, 0) * dt * 1e9) if dt != 0 and math.isfinite(dt) else 0
    profile = schemas.Profile(
        device_time_ns=start, device_end_time_ns=end, frame=index,
        start_angle_deg=math.degrees(float(msg.angle_min)) + 90.0,
        step_deg=math.degrees(float(msg.angle_increment)),
        ranges_m=ranges.astype(np.float32).tolist(),
        intensities=(intensities.astype(np.float32).tolist()
                     if intensities.size == n else []))
    facts = {"samples": float(n), "step_deg": profile.step_deg,
             "angle_min_deg": math.degrees(float(msg.angle_min)),
             "scan_time_s": float(msg.scan_time), "range_min_m": lo, "range_max_m": hi,
             "at_range_max": float(np.count_nonzero(at_max))}
    return (end or start), profile, facts


def on_one_beam_grid(profiles: Sequence[tuple[int, Any]], label: str = "") -> str:
    """Resample profiles whose beam step follows the head's speed scan by scan (LDRobot's
    ldlidar ROS drivers set ``angle_increment`` to the measured speed ÷ the sample rate, and
    ``angle_min`` to the first sample's angle) onto one grid: the median step from the median
    start, over the median span, in place. A grid beam gets the range between its two nearest
    samples by :func:`~scanpipe.protocol.profile.ranges_between` (as the LDRobot dialect's
    revolutions), the nearer sample's echo, NaN farther than half a step (the scan's own when
    wider) from every sample; the device times move to the grid's first and last beams.
    Returns the warning to give."""
    starts = np.array([p.start_angle_deg for _, p in profiles], np.float64)
    steps = np.array([p.step_deg for _, p in profiles], np.float64)
    counts = np.array([len(p.ranges_m) for _, p in profiles], np.int64)
    step = float(np.median(steps))
    start = float(np.median(starts))
    beams = round(float(np.median(starts + (counts - 1) * steps) - start) / step) + 1
    grid = start + np.arange(beams) * step
    for _, profile in profiles:
        n = len(profile.ranges_m)
        if n == 0:
            profile.start_angle_deg, profile.step_deg = start, step
            continue
        ranges = np.asarray(profile.ranges_m, np.float32)
        angles = profile.start_angle_deg + np.arange(n) * profile.step_deg
        right = np.clip(np.searchsorted(angles, grid), 1, n - 1) if n > 1 else \
            np.zeros(beams, np.int64)
        left = np.maximum(right - 1, 0)
        gap = np.maximum(angles[right] - angles[left], 1e-12)
        fraction = np.clip((grid - angles[left]) / gap, 0.0, 1.0).astype(np.float32)
        out = ranges_between(ranges[left], ranges[right], fraction)
        nearer = np.where(fraction > 0.5, right, left)
        # Measured: within half a step (the scan's own when it is wider) of a sample.
        out[np.abs(grid - angles[nearer]) > 0.5 * max(step, profile.step_deg)] = np.nan
        if n > 1 and profile.device_end_time_ns:
            per_deg = (profile.device_end_time_ns - profile.device_time_ns) / (angles[-1]
                                                                              - angles[0])
            first_ns = profile.device_time_ns + round((grid[0] - angles[0]) * per_deg)
            profile.device_end_time_ns = first_ns + round((grid[-1] - grid[0]) * per_deg)
            profile.device_time_ns = first_ns
        if len(profile.intensities) == n:
            echo = np.asarray(profile.intensities, np.float32)[nearer]
            del profile.intensities[:]
            profile.intensities.extend(echo.tolist())
        del profile.ranges_m[:]
        profile.ranges_m.extend(out.tolist())
        profile.start_angle_deg, profile.step_deg = start, step
    return (f"{label}angle_increment follows the head's speed scan by scan "
            f"({steps.min():.6g}…{steps.max():.6g}°, as LDRobot's ldlidar ROS drivers set it): "
            f"every scan resampled onto one grid of {beams} beams of {step:.6g}° from "
            f"{start:.6g}° (linear on one surface, the nearer sample across a depth jump)")


def _scale_fraction_intensities(content: BagContent) -> None:
    """Intensities a driver normalised to 0…1 become fractions of the echo's 0…65535 (decode
    rounds the echo to whole numbers: they would all be 0 or 1); warned."""
    values = [np.asarray(p.intensities, np.float64) for _, p in content.profiles]
    if not are_fractions(np.concatenate(values) if values else np.zeros(0)):
        return
    for (_, profile), value in zip(content.profiles, values, strict=True):
        if value.size:
            del profile.intensities[:]
            profile.intensities.extend((value * ECHO_FULL_SCALE).astype(np.float32).tolist())
    content.warnings.append(f"intensities in 0…1 (normalised by the driver): scaled to the "
                            f"echo's 0…{ECHO_FULL_SCALE:g}")


def _keep_scans_within_angles(bag: Path, content: BagContent, scan_time_s: float) -> None:
    """Drop the scans reaching beyond the platform angle reports at an end where the platform
    was turning (:func:`scanpipe.motion.beyond_log`), warned: assemble holds the nearest angle
    there, which smears them (a publisher that starts late or stops early, a bag cut). At an
    end at rest the held angle is right and the scans are kept. None kept: refused (two
    clocks)."""
    order = sorted(range(len(content.angles)), key=lambda i: content.angles[i][0])
    times = np.array([content.angles[i][0] for i in order], np.int64)
    angles = np.array([content.angles[i][1] for i in order], np.float64)
    first, last = int(times[0]), int(times[-1])
    span_ns = round(scan_time_s * 1e9) if math.isfinite(scan_time_s) and scan_time_s > 0 else 0
    starts = np.array([p.device_time_ns for _, p in content.profiles], np.int64)
    ends = np.array([p.device_end_time_ns or p.device_time_ns + span_ns
                     for _, p in content.profiles], np.int64)
    inside = ~beyond_log(starts, ends, times, angles)
    if inside.all():
        return
    t0 = int(min(starts.min(), first))

    def s(t: int) -> str:
        return f"{(t - t0) / 1e9:.6g}"

    what = (f"(scans {s(int(starts.min()))} … {s(int(ends.max()))} s, angle reports "
            f"{s(first)} … {s(last)} s after {t0} ns)")
    if not inside.any():
        raise BagError(f"{bag}: no scan lies within the platform angle reports {what}: are the "
                       "scans and the angles stamped by different clocks?")
    dropped = int(np.count_nonzero(~inside))
    content.profiles[:] = [p for p, keep in zip(content.profiles, inside, strict=True) if keep]
    content.warnings.append(f"{dropped} scans outside the platform angle reports "
                            f"({s(first)} … {s(last)} s; scans {s(int(starts.min()))} … "
                            f"{s(int(ends.max()))} s) dropped: the platform was turning there, "
                            "so their platform angle is unknown")


def quaternion_matrix(x: float, y: float, z: float, w: float) -> F64:
    """Rotation matrix of a (not necessarily unit) quaternion."""
    q = np.array([w, x, y, z], np.float64)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def euler_deg(matrix: F64) -> list[float]:
    """Euler angles ``(rx, ry, rz)`` in degrees with ``R = Rz·Ry·Rx`` (scanpipe's order)."""
    ry = math.asin(max(-1.0, min(1.0, -float(matrix[2, 0]))))
    if abs(float(matrix[2, 0])) < 1 - 1e-12:
        rx = math.atan2(float(matrix[2, 1]), float(matrix[2, 2]))
        rz = math.atan2(float(matrix[1, 0]), float(matrix[0, 0]))
    else:  # gimbal lock: put the whole turn about z into rx
        rz = 0.0
        rx = math.atan2(-float(matrix[1, 2]), float(matrix[1, 1]))
    return [math.degrees(rx), math.degrees(ry), math.degrees(rz)]


@dataclass(frozen=True)
class Transform:
    """One TF transform: parent → child rotation and translation, at a time."""

    time_ns: int
    parent: str
    child: str
    rotation: F64
    translation: F64


def _transform(t: Any, log_time_ns: int) -> Transform:
    r, v = t.transform.rotation, t.transform.translation
    return Transform(_stamp_ns(t.header, log_time_ns), _frame(t.header.frame_id),
                     _frame(t.child_frame_id), quaternion_matrix(r.x, r.y, r.z, r.w),
                     np.array([v.x, v.y, v.z], np.float64))


def static_chain(path: Path, statics: dict[str, Transform], parent: str, child: str
                 ) -> tuple[F64, F64]:
    """Pose of ``child`` in ``parent`` composed from static transforms (child → parent walk)."""
    rotation, translation = np.eye(3), np.zeros(3)
    frame, seen = child, set()
    while frame != parent:
        if frame in seen or frame not in statics:
            raise BagError(f"{path}: no static transform chain from {parent!r} to the scan's "
                           f"frame {child!r} in /tf_static or /tf (frames with a static "
                           f"parent: {sorted(statics) or 'none'}); pass the mount with --rig")
        seen.add(frame)
        t = statics[frame]
        rotation, translation = t.rotation @ rotation, t.rotation @ translation + t.translation
        frame = t.parent
    return rotation, translation


def _yaw_rad(rotation: F64) -> float:
    """The z part of a ZYX (yaw, pitch, roll) decomposition: exact for turns about z."""
    return math.atan2(float(rotation[1, 0]), float(rotation[0, 0]))


def tf_angles(path: Path, transforms: Sequence[Transform], parent: str, child: str
              ) -> tuple[list[tuple[int, float]], F64, F64]:
    """β over time from the yaw of ``child`` in ``parent``, and ``child``'s pose on the platform.

    The platform frame is ``parent`` turned by the yaw ψ (β = −ψ, module docstring); ``child``
    sits in it at ``Rz(−ψ) · pose``, which must not change over the scan (a warning would not
    do: a tilting child is not a turntable).
    """
    moving = [t for t in transforms if t.parent == parent and t.child == child]
    if not moving:
        pairs = sorted({f"{t.parent}:{t.child}" for t in transforms})
        raise BagError(f"{path}: --tf {parent}:{child}: no such transform in /tf; "
                       f"transforms found: {', '.join(pairs) or 'none'}")
    moving.sort(key=lambda t: t.time_ns)
    yaw = np.unwrap(np.array([_yaw_rad(t.rotation) for t in moving]))
    first = moving[0]
    c, s = math.cos(-yaw[0]), math.sin(-yaw[0])
    unturn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    # The child's pose with its yaw taken out must stay put: anything else is no turntable.
    cos_y, sin_y = np.cos(yaw - yaw[0]), np.sin(yaw - yaw[0])
    rotations = np.stack([t.rotation for t in moving])
    translations = np.stack([t.translation for t in moving])
    turn_back = np.zeros((yaw.size, 3, 3))
    turn_back[:, 0, 0], turn_back[:, 0, 1] = cos_y, sin_y
    turn_back[:, 1, 0], turn_back[:, 1, 1] = -sin_y, cos_y
    turn_back[:, 2, 2] = 1.0
    tilt = np.abs(turn_back @ rotations - first.rotation).max()
    shift = np.abs(np.einsum("nij,nj->ni", turn_back, translations) - first.translation).max()
    if tilt > 1e-3 or shift > 1e-3:
        raise BagError(f"{path}: --tf {parent}:{child}: {child} does not only turn about "
                       f"{parent}'s z (its tilt or offset changes by up to {tilt:.3g} / "
                       f"{shift:.3g} m over the bag); not a turntable about the vertical")
    return ([(t.time_ns, -math.degrees(float(a))) for t, a in zip(moving, yaw, strict=True)],
            unturn @ first.rotation, unturn @ first.translation)


def joint_angles(path: Path, reader: Any, topics: Sequence[Topic], joint: str | None,
                 warnings: list[str] | None = None
                 ) -> tuple[list[tuple[int, float]], str, str]:
    """β over time from one joint's position: (angles, joint name, topic). Non-finite
    positions (a driver's unhomed joint) are left out, counted in ``warnings``."""
    joint_topics = [t for t in topics if t.msgtype == JOINT_STATE]
    positions: dict[tuple[str, str], list[tuple[int, float]]] = defaultdict(list)
    not_finite: Counter[tuple[str, str]] = Counter()
    for connection, log_time, msg in _messages(reader, [t.name for t in joint_topics]):
        stamp = _stamp_ns(msg.header, log_time)
        for name, value in zip(msg.name, msg.position, strict=False):
            if joint is None or name == joint:
                key = (connection.topic, str(name))
                if math.isfinite(float(value)):
                    positions[key].append((stamp, float(value)))
                else:
                    not_finite[key] += 1
    if joint is not None:
        found = [k for k in positions if k[1] == joint]
        if not found:
            raise BagError(f"{path}: --joint {joint}: no JointState reports it; JointState "
                           f"topics: {_listing(joint_topics)}")
        if len(found) > 1:
            raise BagError(f"{path}: --joint {joint}: reported on {len(found)} topics "
                           f"({', '.join(k[0] for k in found)}); keep one in the bag")
        key = found[0]
    else:
        moving = [k for k, v in positions.items()
                  if np.ptp([p for _, p in v]) > _MOVING_RAD]
        if len(moving) != 1:
            what = ("no JointState in the bag" if not joint_topics else
                    "no JointState joint moves" if not moving else
                    f"{len(moving)} joints move: {', '.join(f'{k[1]} on {k[0]}' for k in moving)}")
            raise BagError(f"{path}: no platform angle chosen ({what}); pass --joint NAME or "
                           f"--tf PARENT:CHILD; found: {_listing(topics)}")
        key = moving[0]
    if not_finite[key] and warnings is not None:
        warnings.append(f"joint {key[1]} on {key[0]}: {not_finite[key]} reports with a "
                        "non-finite position (NaN/inf: not homed?) left out")
    values = sorted(positions[key])
    # A continuous joint's driver may wrap its position into (−π, π]: a platform cannot turn
    # half a turn between two reports, so a jump of more than π is the wrap (as TF's yaw).
    unwrapped = np.unwrap(np.array([p for _, p in values], np.float64))
    return ([(t, -math.degrees(float(p))) for (t, _), p in zip(values, unwrapped, strict=True)],
            key[1], key[0])


def _camera_id(topic: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_-]+", "_", topic.strip("/"))
    return name or "camera"


def without_exif(jpeg: bytes) -> bytes | None:
    """``jpeg`` without its Exif APP1 segments when one holds an orientation other than 1
    (the pixels untouched: the segments are cut out); None when there is nothing to remove.
    A PNG (OpenCV turns it by its eXIf chunk alike) loses its eXIf chunk the same way.

    ROS's image_transport decodes a CompressedImage as stored (OpenCV's IMREAD_UNCHANGED), and
    its CameraInfo describes those pixels; scanpipe's frame decoding would turn them by the
    tag."""
    from io import BytesIO

    from PIL import Image

    try:
        with Image.open(BytesIO(jpeg)) as image:
            orientation = image.getexif().get(0x0112, 1)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        return None  # Pillow's errors: the frame decode checks the size and will say
    if orientation in (1, None):
        return None
    if jpeg[:8] == PNG_SIGNATURE:
        return _png_without_exif(jpeg)
    out, at = [jpeg[:2]], 2
    while at + 2 <= len(jpeg) and jpeg[at] == 0xFF:
        marker = jpeg[at + 1]
        if marker == 0xFF:  # a fill byte before a marker (allowed): dropped
            at += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # a marker without a length
            out.append(jpeg[at:at + 2])
            at += 2
            continue
        if marker == 0xDA or at + 4 > len(jpeg):  # start of scan: the rest is image data
            break
        length = int.from_bytes(jpeg[at + 2:at + 4], "big")
        segment = jpeg[at:at + 2 + length]
        if not (marker == 0xE1 and segment[4:10] == b"Exif\x00\x00"):
            out.append(segment)
        at += 2 + length
    out.append(jpeg[at:])
    return b"".join(out)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_without_exif(png: bytes) -> bytes:
    """A PNG without its eXIf chunks (each chunk: length, type, data, CRC)."""
    out, at = [png[:8]], 8
    while at + 12 <= len(png):
        end = at + 12 + int.from_bytes(png[at:at + 4], "big")
        if png[at + 4:at + 8] != b"eXIf":
            out.append(png[at:end])
        at = end
    out.append(png[at:])
    return b"".join(out)


def _image_bytes(msg: Any, msgtype: str) -> tuple[bytes, str] | None:
    """(encoded bytes, jpeg|png) of an image message; None for an encoding not taken."""
    if msgtype == COMPRESSED_IMAGE:
        data = bytes(msg.data)
        if data[:3] == b"\xff\xd8\xff":
            return data, "jpeg"
        if data[:8] == PNG_SIGNATURE:
            # 16 bits per sample (IHDR's bit depth): a depth image (compressed 16UC1), not a
            # camera frame; OpenCV would read its high bytes as a grey picture
            return (data, "png") if len(data) > 24 and data[24] <= 8 else None
        return None
    encoding = str(msg.encoding).lower()
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}.get(encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    raw = np.asarray(msg.data, np.uint8)
    if channels is None or step < width * channels or raw.size < height * step:
        return None
    pixels = raw[:height * step].reshape(height, step)[:, :width * channels]
    image = pixels.reshape(height, width, channels)[:, :, :3] if channels > 1 else pixels
    if encoding.startswith("rgb"):
        image = image[:, :, ::-1]  # encode_png takes BGR
    return encode_png(np.ascontiguousarray(image)), "png"


def _camera_info(reader: Any, topics: Sequence[Topic], image_topic: str) -> Any | None:
    """The first CameraInfo of the image topic's namespace (…/camera_info beside it)."""
    parts = image_topic.rstrip("/").split("/")
    candidates = []
    for depth in (1, 2):
        if len(parts) > depth:
            candidates.append("/".join([*parts[:-depth], "camera_info"]))
    infos = [t.name for t in topics if t.msgtype == CAMERA_INFO and t.name in candidates]
    for _, _, msg in _messages(reader, infos[:1]):
        return msg
    return None


#: CameraInfo distortion models that are OpenCV's pinhole (k1 k2 p1 p2 k3 [k4 k5 k6]).
_PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "")


def _rectified(image_topic: str) -> bool:
    """An image topic that carries rectified images (image_proc's ``image_rect``,
    ``image_rect_color``, also behind ``/compressed``): no distortion left, intrinsics in P."""
    return re.search(r"(^|[_/])rect", "/".join(image_topic.split("/")[-2:])) is not None


def camera_intrinsics(info: Any, image_topic: str, bag: Path) -> dict[str, Any] | None:
    """A rig camera's ``width height fx fy cx cy distortion`` from a CameraInfo, or None when
    it holds no calibration (K zero). :class:`BagError` for a lens scanpipe's OpenCV pinhole
    cannot describe (fisheye ``equidistant``, a rational model using k4…k6, an unknown model).

    A rectified image topic takes P (its undistorted projection) with zero distortion: K and D
    describe the raw image, and would distort a rectified one a second time. The ROI (in
    full-resolution, unbinned pixels) and the binning (ROS's image_geometry applies them in
    that order) are applied, as the images published have that size."""
    k = [float(v) for v in getattr(info, "k", getattr(info, "K", []))]
    if len(k) != 9 or not k[0] > 0 or not int(info.width):
        return None
    d = [float(v) for v in getattr(info, "d", getattr(info, "D", []))]
    model = str(info.distortion_model).strip().lower()
    width, height = int(info.width), int(info.height)
    if _rectified(image_topic):
        p = [float(v) for v in getattr(info, "p", getattr(info, "P", []))]
        fx, fy, cx, cy = (p[0], p[5], p[2], p[6]) if len(p) == 12 and p[0] > 0 else (
            k[0], k[4], k[2], k[5])
        distortion = [0.0] * 5
    else:
        fx, fy, cx, cy = k[0], k[4], k[2], k[5]
        extra = [v for v in d[5:] if v != 0.0]
        if (model not in _PINHOLE_MODELS and any(d)) or extra:
            raise BagError(
                f"{bag}: {image_topic}: its CameraInfo's lens model is {model or '(none)'!r} "
                f"with distortion {d}; scanpipe's cameras are OpenCV's pinhole with k1 k2 p1 "
                "p2 k3 only (plumb_bob, or rational_polynomial with k4…k6 zero): pass --rig "
                "with this camera calibrated in that model (scanpipe calibrate-camera), import "
                "its rectified topic (image_rect), or leave --image out")
        distortion = (d + [0.0] * 5)[:5]
    roi = getattr(info, "roi", None)
    roi_box = (0, 0, 0, 0) if roi is None else (
        int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    binning = (int(getattr(info, "binning_x", 0) or 0), int(getattr(info, "binning_y", 0) or 0))
    width, height, fx, fy, cx, cy = ros_roi_binning(width, height, fx, fy, cx, cy, roi_box,
                                                    binning)
    return {"width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "distortion": distortion}


def _camera(camera_id: str, intrinsics: dict[str, Any] | None, size: tuple[int, int] | None,
            base: CameraConfig) -> CameraConfig:
    """A camera of the imported rig: intrinsics from CameraInfo when present, else a guess."""
    data = base.model_dump()
    data["id"] = camera_id
    data["source"] = "bag"
    if intrinsics is not None:
        data.update(intrinsics)
    elif size is not None:
        w, h = size
        focal = 0.5 * w / math.tan(math.radians(30.0))  # 60° horizontal: a guess, say so
        data.update(width=w, height=h, fx=focal, fy=focal, cx=(w - 1) / 2, cy=(h - 1) / 2)
    return CameraConfig.model_validate(data)


def _place_images(content: BagContent, first: int, log_times: Sequence[int],
                  scan_span: tuple[int, int], topic: str) -> None:
    """Check the times of one image topic's images (``content.images[first:]``) against the
    scan's: header stamps from another clock than the scan's (a camera stamping its own uptime)
    put every frame before or after the scan, where texture would show it at the platform's
    first or last angle. Then the bag's log times are used when they meet the scan, else the
    images are dropped; a warning says which."""
    images = content.images[first:]
    lo, hi = scan_span
    if not images or any(lo <= image[1] <= hi for image in images):
        return
    if any(lo <= t <= hi for t in log_times):
        content.images[first:] = [(c, t, d, f, i) for (c, _, d, f, i), t
                                  in zip(images, log_times, strict=True)]
        content.warnings.append(
            f"{topic}: none of its {len(images)} header stamps falls within the scan's time "
            "(another clock: a camera stamping its own time?): the bag's log times are used")
        return
    del content.images[first:]
    content.warnings.append(
        f"{topic}: none of its {len(images)} images was taken during the scan (by header stamp "
        "or bag log time): dropped (texture would have shown them at the platform's first or "
        "last angle)")


def build_rig(path: Path, facts: dict[str, float], rate_hz: float, mount: tuple[F64, F64] | None,
              cameras: Sequence[CameraConfig], given: Rig | None, max_steps: int) -> Rig:
    """The rig of the recording: from the bag (or ``given``), motor step :data:`PULSE_STEP_DEG`."""
    data = rig_to_dict(given if given is not None else default_rig())
    motor = data["motor"]
    motor.update(full_step_deg=PULSE_STEP_DEG, gear_ratio=1.0, unlimited_travel=True,
                 pulse_limit=max(1, min(max_steps, _MAX_STEPS)))
    if given is None:
        scan_hz = 1.0 / facts["scan_time_s"] if facts["scan_time_s"] > 0 else rate_hz
        start = facts["angle_min_deg"] + 90.0
        fov = facts["step_deg"] * max(facts["samples"] - 1, 1)
        lo = min(max(facts["range_min_m"], 0.0), 255.0)
        hi = min(max(facts["range_max_m"], lo + 0.001), 255.99609375)
        data["name"] = f"ros-bag-{_camera_id(path.stem)}"[:64]
        data["scanner"].update(
            dialect="paper", beam_step_deg=facts["step_deg"],
            start_angle_deg=start % 360.0, end_angle_deg=min(start % 360.0 + fov, 360.0),
            scan_hz=min(max(scan_hz, 0.01), 100.0), min_range_m=lo, max_range_m=hi)
        if mount is not None:
            rotation, translation = mount
            data["scanner"]["mount"] = {
                "rotation_deg": euler_deg(G @ rotation @ F),
                "translation_m": (G @ translation).tolist()}
        data["cameras"] = [rig_to_dict_camera(c) for c in cameras]
    elif cameras:
        known = {c["id"] for c in data.get("cameras", [])}
        data["cameras"] = [*data.get("cameras", []),
                           *(rig_to_dict_camera(c) for c in cameras if c.id not in known)]
    return rig_from_dict(data, f"{path} (the rig built from the bag)")


def rig_to_dict_camera(camera: CameraConfig) -> dict[str, Any]:
    """A camera as the rig file writes it."""
    return camera.model_dump(mode="json")


def import_bag(bag: Path, out: Path, scan_topic: str | None = None, joint: str | None = None,
               tf: str | None = None, image_topics: Sequence[str] = (), rig: Rig | None = None
               ) -> dict[str, Any]:
    """Write the recording ``out`` from the ROS bag ``bag``; returns a report.

    ``out`` is written beside itself first and renamed into place, so a failed import leaves
    no file (the output-path policy is the caller's: :func:`scanpipe.outpaths.check_output_file`).
    """
    if joint is not None and tf is not None:
        raise UsageError("--joint and --tf both give the platform angle; pass one")
    if tf is not None and (tf.count(":") != 1 or not all(tf.split(":"))):
        raise UsageError(f"--tf {tf!r}: expected PARENT:CHILD (two TF frame names)")
    warnings: list[str] = []
    with tempfile.TemporaryDirectory(prefix="scanpipe-bag-") as scratch:
        reader = open_bag(bag, Path(scratch), warnings)
        read = {Path(p).resolve() for p in reader.paths}
        read |= {f.resolve() for p in read if p.is_dir() for f in p.iterdir()}
        if out.resolve() in read:
            reader.close()
            raise UsageError(f"--out {out}: is a file of the bag being imported (a part of a "
                             "split recording); choose another name")
        try:
            return _import(reader, bag, out, scan_topic, joint, tf, image_topics, rig, warnings)
        except (BagError, UsageError):
            raise
        except Exception as err:  # a damaged message deep in a bag
            reason = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise BagError(f"{bag}: cannot be read ({type(err).__name__}: {reason})") from err
        finally:
            reader.close()


def _import(reader: Any, bag: Path, out: Path, scan_topic: str | None, joint: str | None,
            tf: str | None, image_topics: Sequence[str], given: Rig | None,
            warnings: Sequence[str] = ()) -> dict[str, Any]:
    topics = bag_topics(reader)
    scan = choose_scan_topic(bag, topics, scan_topic)
    for name in image_topics:
        match = [t for t in topics if t.name == name]
        if not match or match[0].msgtype not in IMAGE_TYPES:
            images = [t for t in topics if t.msgtype in IMAGE_TYPES]
            raise BagError(f"{bag}: --image {name}: not an image topic; image topics: "
                           f"{_listing(images)}")
    content = BagContent(warnings=list(warnings))
    facts: dict[str, float] = {}
    frame_ids: Counter[str] = Counter()
    steps_seen: set[float] = set()
    at_max = 0
    for _, log_time, msg in _messages(reader, [scan.name]):
        log_ns, profile, f = _profile(msg, scan.msgtype, log_time, len(content.profiles))
        facts = facts or f
        at_max += int(f["at_range_max"])
        steps_seen.add(round(profile.step_deg, 9))
        frame_ids[_frame(msg.header.frame_id)] += 1
        content.profiles.append((log_ns, profile))
    if not content.profiles:
        raise BagError(f"{bag}: {scan}: no messages")
    if len(frame_ids) > 1:
        frames = ", ".join(f"{name or '(empty)'}: {n}" for name, n in sorted(frame_ids.items()))
        raise BagError(f"{bag}: {scan.name}: scans from {len(frame_ids)} frames ({frames}): "
                       "several scanners on one topic; a recording holds one scanner's scans")
    bad_steps = [s for s in steps_seen if not (math.isfinite(s) and s > 0)]
    if bad_steps:
        raise BagError(f"{bag}: {scan.name}: angle_increment {bad_steps[0]:g}°: only "
                       "scans with a positive angle_increment are taken")
    if len(steps_seen) > 1:
        low, high = min(steps_seen), max(steps_seen)
        if (high - low) / high > MAX_STEP_SPREAD:
            raise BagError(f"{bag}: {scan.name}: angle_increment changes during the bag "
                           f"({low:.6g}…{high:.6g}°, {(high - low) / high:.2%}; up to "
                           f"{MAX_STEP_SPREAD:.0%} is taken as one step following the head's "
                           "speed): one scan must use one beam step")
        content.warnings.append(on_one_beam_grid(content.profiles, f"{scan.name}: "))
    if at_max:
        content.warnings.append(
            f"{scan.name}: {at_max} ranges equal to range_max ({facts['range_max_m']:g} m) "
            "taken as no return (drivers that do not publish REP 117's +inf, such as LMS1xx's "
            "default and Gazebo's laser plugin, put range_max there)")
    _scale_fraction_intensities(content)
    if scan.msgtype == MULTI_ECHO:
        content.warnings.append(f"{scan.name}: MultiEchoLaserScan: the first echo of each "
                                "beam is taken, the others are dropped")

    mount: tuple[F64, F64] | None = None
    source: dict[str, Any]
    if tf is not None:
        parent, child = (_frame(p) for p in tf.split(":"))
        transforms: list[Transform] = []
        statics: dict[str, Transform] = {}
        tf_topics = [t.name for t in topics if t.msgtype == TF_MESSAGE]
        for connection, log_time, msg in _messages(reader, tf_topics):
            for t in msg.transforms:
                transform = _transform(t, log_time)
                if connection.topic.endswith("tf_static") or transform.child != child:
                    statics.setdefault(transform.child, transform)
                if not connection.topic.endswith("tf_static"):
                    transforms.append(transform)
        content.angles, child_rotation, child_translation = tf_angles(
            bag, transforms, parent, child)
        laser_frame = frame_ids.most_common(1)[0][0]
        statics.pop(child, None)
        rotation, translation = static_chain(bag, statics, child, laser_frame)
        mount = (child_rotation @ rotation, child_rotation @ translation + child_translation)
        source = {"tf": f"{parent}:{child}", "laser_frame": laser_frame}
    else:
        content.angles, joint_name, joint_topic = joint_angles(bag, reader, topics, joint,
                                                               content.warnings)
        source = {"joint": joint_name, "topic": joint_topic}
    if len(content.angles) < 2:
        raise BagError(f"{bag}: {len(content.angles)} platform angle reports; need at least "
                       "2 to interpolate the angle over the scan")
    _keep_scans_within_angles(bag, content, facts["scan_time_s"])

    cameras: list[CameraConfig] = []
    skipped: Counter[str] = Counter()
    turned: Counter[str] = Counter()
    scan_times = [t for t, _ in content.profiles]
    scan_span = (min(scan_times), max(scan_times))
    for name in image_topics:
        topic = next(t for t in topics if t.name == name)
        camera_id = _camera_id(name)
        size: tuple[int, int] | None = None
        first = len(content.images)
        log_times: list[int] = []
        for _, log_time, msg in _messages(reader, [name]):
            encoded = _image_bytes(msg, topic.msgtype)
            if encoded is None:
                skipped[name] += 1
                continue
            if size is None and topic.msgtype == RAW_IMAGE:
                size = (int(msg.width), int(msg.height))
            if size is None:
                from scanpipe.images import image_size
                size = image_size(encoded[0])
            data = encoded[0]
            if encoded[1] in ("jpeg", "png"):
                stripped = without_exif(data)
                if stripped is not None:
                    data = stripped
                    turned[name] += 1
            content.images.append((camera_id, _stamp_ns(msg.header, log_time), data,
                                   encoded[1], _frame(msg.header.frame_id)))
            log_times.append(log_time)
        _place_images(content, first, log_times, scan_span, name)
        if given is not None and any(c.id == camera_id for c in given.cameras):
            continue  # --rig's own camera: its calibration, not the bag's
        info = _camera_info(reader, topics, name)
        intrinsics = None if info is None else camera_intrinsics(info, name, bag)
        if info is None:
            content.warnings.append(f"{name}: no CameraInfo beside it: intrinsics guessed "
                                    "(60° horizontal field of view); pass --rig")
        elif intrinsics is None:
            content.warnings.append(f"{name}: its CameraInfo holds no calibration (K is "
                                    "zero: an uncalibrated camera): intrinsics guessed (60° "
                                    "horizontal field of view); pass --rig")
        try:
            cameras.append(_camera(camera_id, intrinsics, size, default_rig().cameras[0]))
        except ValidationError as err:
            raise BagError(f"{bag}: {name}: its CameraInfo gives a camera the rig refuses: "
                           + "; ".join(describe_validation_error(err, CameraConfig))
                           + "; pass --rig with this camera calibrated") from None
    for name, n in turned.items():
        content.warnings.append(f"{name}: {n} images carried an EXIF orientation tag: "
                                "removed (the pixels are unchanged), as ROS's image_transport "
                                "ignores it and the CameraInfo describes the pixels as stored")
    for name, n in skipped.items():
        content.warnings.append(f"{name}: {n} images in an encoding not taken (only "
                                "JPEG/8-bit PNG CompressedImage and rgb8/bgr8/rgba8/bgra8/"
                                "mono8 Image)")

    times = np.array([t for t, _ in content.profiles], np.int64)
    rate_hz = (1e9 / float(np.median(np.diff(np.sort(times)))) if times.size > 1
               and np.median(np.diff(np.sort(times))) > 0 else 10.0)
    beta = np.array([b for _, b in content.angles])
    steps = np.rint(beta / PULSE_STEP_DEG)
    if np.any(np.abs(steps) > _MAX_STEPS):
        raise BagError(f"{bag}: platform angle reaches {np.max(np.abs(beta)):.0f}°; at most "
                       f"{_MAX_STEPS * PULSE_STEP_DEG:.0f}° can be imported")
    rig = build_rig(bag, facts, rate_hz, mount, cameras, given, int(np.max(np.abs(steps))))
    session = {"mode": "import-bag", "source": str(bag), "scan_topic": scan.name,
               "angle_source": source}
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    try:
        with RecordingWriter(partial, rig, session) as writer:
            for log_ns, profile in content.profiles:
                writer.write_profile(log_ns, profile)
            for (t, _), count in zip(content.angles, steps, strict=True):
                writer.write_motor_state(t, int(count), int(count), True, 0)
            for camera_id, t, data, image_format, frame_id in content.images:
                writer.write_image(camera_id, t, data, frame_id, image_format)
        os.replace(partial, out)
    except OSError as err:
        raise RecordingError(f"{out}: cannot be written ({err.strerror or err})") from None
    finally:
        partial.unlink(missing_ok=True)
    samples = int(facts["samples"])
    return {
        "bag": str(bag), "out": str(out), "scan_topic": str(scan), "angle_source": source,
        "profiles": len(content.profiles), "samples_per_profile": samples,
        "angle_reports": len(content.angles),
        "beta_deg_range": [float(beta.min()), float(beta.max())],
        "alpha_deg_range": [facts["angle_min_deg"] + 90.0,
                            facts["angle_min_deg"] + 90.0 + facts["step_deg"] * (samples - 1)],
        "images": dict(Counter(i[0] for i in content.images)),
        "mount": rig_to_dict(rig)["scanner"]["mount"],
        "topics": [str(t) for t in topics], "warnings": content.warnings,
    }


__all__ = ["BagError", "Topic", "bag_topics", "build_rig", "choose_scan_topic", "euler_deg",
           "import_bag", "open_bag", "quaternion_matrix"]
