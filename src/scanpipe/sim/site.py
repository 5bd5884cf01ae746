"""The built-in site: two furnished rooms joined by a corridor through doors, and scans of it
from several positions at known poses (``scanpipe simulate --site N``).

Site frame: y up, metres, floor at ``FLOOR_Y_M`` (the scanner's rig origin stands 1.2 m above
it, as in the built-in room). Room A spans x ∈ [−7, −2], the corridor x ∈ [−2, 2] (z ∈ [−1, 1]),
room B x ∈ [2, 7]; both rooms are 6 m deep (z ∈ [−3, 3]). Each space has its own furniture so
no two places look alike to a geometric matcher (a bare corridor slides along itself).

A site simulation writes, for positions ``0 … N−1`` along a path through the three spaces:

```
OUT/pos00.mcap …               one recording per position (the rig frame of each is its own)
OUT/prior_poses.parquet        (with a prior) the rough odometry poses, a ``poses`` artifact
TRUTH/pos00/ …                 the truth folder of each recording (scene in its rig frame)
TRUTH/poses.parquet            the true poses (rig → site), a ``poses`` artifact
TRUTH/site_scene.glb           the scene in the site frame
TRUTH/site.json                positions, prior error, seed
```
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import SimulationError
from scanpipe.poses import euler_deg, invert, pose_matrix, poses_table
from scanpipe.rig import Pose
from scanpipe.sim.room import builtin_site

F64 = NDArray[np.float64]

SITE_SCENE_FILE = "site_scene.glb"
SITE_POSES_FILE = "poses.parquet"
SITE_META_FILE = "site.json"
PRIOR_POSES_FILE = "prior_poses.parquet"

#: The path the positions are spread along (x, z in the site frame): room A, the corridor,
#: room B. Six positions land on its corners.
SITE_PATH_XZ = ((-5.3, -1.2), (-3.2, 0.9), (-1.2, -0.1), (1.1, 0.2), (3.2, -0.9), (5.2, 1.1))
#: How far a simulated position strays from the path (m) and how far from level (degrees).
POSITION_JITTER_M = 0.15
TILT_DEG = 0.3


def site_positions(count: int, seed: int = 0) -> list[F64]:
    """``count`` true poses (rig → site) spread evenly along :data:`SITE_PATH_XZ`, each
    jittered, turned to a random heading and tilted a little (a scanner set down by hand)."""
    if count < 2:
        raise SimulationError(f"--site {count}: a site needs at least 2 positions")
    path = np.asarray(SITE_PATH_XZ, dtype=np.float64)
    lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    stations = np.linspace(0.0, along[-1], count)
    xz = np.stack([np.interp(stations, along, path[:, k]) for k in range(2)], axis=1)
    rng = np.random.default_rng([seed, 21])
    poses = []
    for x, z in xz:
        jitter = rng.uniform(-POSITION_JITTER_M, POSITION_JITTER_M, 2)
        # stay away from the partitions (x = ±2), where a jitter could put the scanner in a wall
        px = float(x + jitter[0])
        if abs(abs(px) - 2.0) < 0.6:
            px = float(x)
        rotation = (rng.uniform(-TILT_DEG, TILT_DEG), rng.uniform(-180.0, 180.0),
                    rng.uniform(-TILT_DEG, TILT_DEG))
        poses.append(pose_matrix(rotation, (px, 0.0, float(z + jitter[1]))))
    return poses


def prior_poses(true_poses: list[F64], error_m: float, error_deg: float, seed: int = 0
                ) -> list[F64]:
    """A rough odometry prior: each true pose moved by up to ``error_m`` horizontally and
    turned by up to ``error_deg`` about the vertical (uniform, independent per position)."""
    rng = np.random.default_rng([seed, 22])
    prior = []
    for pose in true_poses:
        offset = rng.uniform(-error_m, error_m, 2)
        turn = pose_matrix((0.0, rng.uniform(-error_deg, error_deg), 0.0), (0.0, 0.0, 0.0))
        moved = pose @ turn
        moved[:3, 3] = pose[:3, 3] + np.array([offset[0], 0.0, offset[1]])
        prior.append(moved)
    return prior


def scene_pose_for(pose: F64) -> Pose:
    """The ``scene_pose`` that puts the site scene into the rig frame of a scan at ``pose``."""
    inverse = invert(pose)
    return Pose(translation_m=tuple(float(v) for v in inverse[:3, 3]),  # type: ignore[arg-type]
                rotation_deg=euler_deg(inverse[:3, :3]))


def position_name(index: int) -> str:
    """The name of position ``index`` (its recording and truth folder)."""
    return f"pos{index:02d}"


def simulate_site(out_dir: Path, truth_dir: Path, options: Any, count: int,
                  prior_error_m: float | None = None, prior_error_deg: float = 10.0,
                  simulate_one: Callable[..., dict[str, Any]] | None = None,
                  progress: Any = None) -> dict[str, Any]:
    """Simulate ``count`` positions of the built-in site (see the module docstring).

    ``options`` are the :class:`~scanpipe.sim.options.SimOptions` of every position (its
    ``scene`` and ``scene_pose`` are replaced; the seed advances per position).
    """
    from scanpipe.artifacts import write_artifact
    from scanpipe.sim.direct import simulate_direct

    run = simulate_one or simulate_direct
    truth_poses = site_positions(count, options.seed)
    names = [position_name(i) for i in range(count)]
    summaries = []
    for i, (name, pose) in enumerate(zip(names, truth_poses, strict=True)):
        position = options.model_copy(update={"scene": "site", "scene_pose": scene_pose_for(pose),
                                              "scene_up": "y", "seed": options.seed + i})
        kwargs = {} if progress is None else {"progress": progress}
        summary = run(out_dir / f"{name}.mcap", truth_dir / name, position, **kwargs)
        summaries.append(summary)
    provenance = {"stage": "simulate-site", "seed": options.seed, "positions": count}
    write_artifact(truth_dir / SITE_POSES_FILE, poses_table(names, truth_poses), provenance)
    builtin_site().save_glb(truth_dir / SITE_SCENE_FILE)
    meta: dict[str, Any] = {"positions": names, "seed": options.seed,
                            "prior_error_m": prior_error_m, "prior_error_deg": prior_error_deg}
    if prior_error_m is not None:
        prior = prior_poses(truth_poses, prior_error_m, prior_error_deg, options.seed)
        write_artifact(out_dir / PRIOR_POSES_FILE, poses_table(names, prior),
                       {**provenance, "prior_error_m": prior_error_m,
                        "prior_error_deg": prior_error_deg})
    from scanpipe.artifacts import atomic_write_bytes

    atomic_write_bytes(truth_dir / SITE_META_FILE,
                       (json.dumps(meta, indent=2, sort_keys=True) + "\n").encode())
    return {"positions": count, "recordings": [str(out_dir / f"{n}.mcap") for n in names],
            "truth": str(truth_dir), "seconds": sum(float(s.get("seconds", 0.0))
                                                     for s in summaries),
            "prior": str(out_dir / PRIOR_POSES_FILE) if prior_error_m is not None else None,
            "warnings": [w for s in summaries for w in s.get("warnings", [])]}


def yaw_deg(pose: F64) -> float:
    """The heading of a pose about the vertical (degrees)."""
    return math.degrees(math.atan2(float(pose[0, 2]), float(pose[2, 2])))
