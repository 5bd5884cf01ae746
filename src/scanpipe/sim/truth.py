"""The ground-truth folder of a simulated scan.

```
truth/
  scene.glb       the scene with its textures (rig frame, metres, y up)
  rig.toml        the TRUE rig, mounting pose and offsets as they really were
  truth.parquet   one row per profile the scanner sent, in order: profile (int32), time_ns
                  (int64, the host-clock time of the profile's first sample), time_end_ns
                  (int64, of its last sample), beta_deg (float64, the true platform angle at the
                  first sample), beta_end_deg (float64, at the last sample), ranges_true_m
                  (list<float32>, noise-free and un-quantised; NaN = no hit or outside the
                  scanner's range)
  meta.json       seed, options, versions, counts
```
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.errors import SimulationError
from scanpipe.rig import Rig, rig_from_dict, rig_to_toml
from scanpipe.sim.scene import Scene, load_scene

SCENE_FILE = "scene.glb"
RIG_FILE = "rig.toml"
PROFILES_FILE = "truth.parquet"
META_FILE = "meta.json"

TRUTH_SCHEMA = pa.schema([
    ("profile", pa.int32()),
    ("time_ns", pa.int64()),
    ("time_end_ns", pa.int64()),
    ("beta_deg", pa.float64()),
    ("beta_end_deg", pa.float64()),
    ("ranges_true_m", pa.list_(pa.float32())),
])


def truth_table(time_ns: NDArray[np.int64], time_end_ns: NDArray[np.int64],
                beta_deg: NDArray[np.float64], beta_end_deg: NDArray[np.float64],
                ranges_true_m: NDArray[np.floating], first_profile: int = 0) -> pa.Table:
    """Per-profile truth as an Arrow table (``ranges_true_m`` is (profiles, samples))."""
    ranges = np.asarray(ranges_true_m, dtype=np.float32)
    n, samples = ranges.shape
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * samples, pa.int32())
    ranges_list = pa.ListArray.from_arrays(offsets, pa.array(ranges.reshape(-1), pa.float32()))
    return pa.Table.from_arrays([
        pa.array(np.arange(first_profile, first_profile + n, dtype=np.int32)),
        pa.array(np.asarray(time_ns, dtype=np.int64)),
        pa.array(np.asarray(time_end_ns, dtype=np.int64)),
        pa.array(np.asarray(beta_deg, dtype=np.float64)),
        pa.array(np.asarray(beta_end_deg, dtype=np.float64)),
        ranges_list,
    ], schema=TRUTH_SCHEMA)


def write_truth(folder: Path, scene: Scene, true_rig: Rig, profiles: pa.Table,
                meta: dict[str, Any]) -> None:
    """Write the ground-truth folder (each file atomically)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise SimulationError(f"{folder}: cannot create the truth folder: {err}") from err
    scene.save_glb(folder / SCENE_FILE)
    atomic_write_bytes(folder / RIG_FILE, rig_to_toml(true_rig).encode())
    sink = pa.BufferOutputStream()
    pq.write_table(profiles.cast(TRUTH_SCHEMA), sink, use_dictionary=False)
    atomic_write_bytes(folder / PROFILES_FILE, sink.getvalue().to_pybytes())
    atomic_write_bytes(folder / META_FILE,
                       (json.dumps(meta, indent=2, sort_keys=True, default=str) + "\n").encode())


@dataclass
class Truth:
    """A loaded ground-truth folder."""

    scene: Scene
    rig: Rig
    profiles: pa.Table
    meta: dict[str, Any]

    def ranges_true_m(self) -> NDArray[np.float32]:
        """The noise-free ranges as a (profiles, samples) float32 array."""
        column = self.profiles.column("ranges_true_m").combine_chunks()
        n = len(column)
        values = column.flatten().to_numpy(zero_copy_only=False).astype(np.float32)
        return np.asarray(values.reshape(n, -1) if n else values.reshape(0, 0), dtype=np.float32)


def load_truth(folder: Path | str) -> Truth:
    """Read a ground-truth folder written by :func:`write_truth`."""
    folder = Path(folder)
    missing = [name for name in (SCENE_FILE, RIG_FILE, PROFILES_FILE, META_FILE)
               if not (folder / name).is_file()]
    if missing:
        raise SimulationError(f"{folder}: not a truth folder (missing {', '.join(missing)})")
    try:
        rig = rig_from_dict(tomllib.loads((folder / RIG_FILE).read_text()), str(folder / RIG_FILE))
        profiles = pq.read_table(folder / PROFILES_FILE)
        meta = json.loads((folder / META_FILE).read_text())
    except (OSError, ValueError, pa.ArrowException) as err:
        raise SimulationError(f"{folder}: cannot read the truth folder: {err}") from err
    if profiles.schema.names != TRUTH_SCHEMA.names:
        raise SimulationError(f"{folder / PROFILES_FILE}: columns {profiles.schema.names}, "
                              f"expected {TRUTH_SCHEMA.names}")
    return Truth(load_scene(folder / SCENE_FILE), rig, profiles, meta)
