"""The benchmark scans: what to simulate, and a cache so that each is simulated once.

A scan is simulated with :func:`scanpipe.sim.direct.simulate_direct` into
``benchmarks/cache/<name>-<hash of the options>/`` (``scan.mcap`` + ``truth/``); a changed option
gives a new folder, and a folder is only used once its ``done.json`` exists (written last).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from scanpipe.planning import DEFAULT_MOTOR_STEP_DEG
from scanpipe.sim.direct import checked_rigs, simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.session import plan_session

CACHE_DIR = Path(__file__).parent / "cache"


@dataclass(frozen=True)
class BenchScan:
    """One benchmark scan: the grid, the video, and the sizes of the work done on it."""

    name: str
    beam_step_deg: float
    motor_step_deg: float
    #: Video per camera: ``video_s × video_fps`` frames spread over the whole session.
    video_s: float
    video_fps: float
    #: Frames are rendered at this fraction of the rig cameras' 1920 × 1080.
    camera_scale: float
    poisson_depths: tuple[int, ...] = (8, 9)
    #: The Open3D baseline's voxel size and KNN neighbourhood.
    baseline_voxel_m: float = 0.01
    baseline_knn: int = 30
    #: Points sampled per surface for the accuracy figures.
    eval_samples: int = 100_000


#: The paper's lab scan: 0.25° beam step × 0.108° motor step = 1667 positions × 1440 samples,
#: with the rig's cameras at their real resolution (Full HD).
LAB = BenchScan("lab", 0.25, DEFAULT_MOTOR_STEP_DEG, video_s=10.0, video_fps=30.0, camera_scale=1.0)
#: A small scan for CI smoke runs (under a minute for everything).
QUICK = BenchScan("quick", 1.0, 1.08, video_s=2.0, video_fps=10.0, camera_scale=0.25,
                  poisson_depths=(6, 7), baseline_voxel_m=0.02, eval_samples=20_000)


def sim_options(scan: BenchScan) -> SimOptions:
    """The simulator's options for ``scan``, the camera rate chosen so that each camera records
    ``video_s × video_fps`` frames over the session (whose length depends on the grid)."""
    options = SimOptions(beam_step_deg=scan.beam_step_deg,
                         motor_step_deg=scan.motor_step_deg, camera_scale=scan.camera_scale)
    _, true_rig = checked_rigs(options)
    duration_s = plan_session(options, true_rig).end_s
    fps = scan.video_s * scan.video_fps / duration_s
    return options.model_copy(update={"camera_fps": fps})


@dataclass(frozen=True)
class ScanFiles:
    """A simulated scan on disk and what the simulator said about it."""

    recording: Path
    truth: Path
    summary: dict[str, Any]
    options: dict[str, Any]
    reused: bool


def options_key(scan: BenchScan, options: SimOptions) -> str:
    """The cache folder name: the scan's name and a hash of everything it depends on."""
    from scanpipe import __version__

    record = {"scan": asdict(scan), "options": json.loads(options.model_dump_json()),
              "scanpipe": __version__}
    digest = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:12]
    return f"{scan.name}-{digest}"


def cached_scan(scan: BenchScan, cache_dir: Path = CACHE_DIR) -> ScanFiles:
    """Simulate ``scan`` unless a finished copy with the same options is in ``cache_dir``."""
    options = sim_options(scan)
    folder = cache_dir / options_key(scan, options)
    done = folder / "done.json"
    if not done.is_file():
        partial = folder.with_name(folder.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
        started = time.perf_counter()
        summary = simulate_direct(partial / "scan.mcap", partial / "truth", options)
        summary["simulate_s"] = round(time.perf_counter() - started, 2)
        summary["options"] = json.loads(options.model_dump_json())
        (partial / "done.json").write_text(json.dumps(summary, indent=2, default=str))
        shutil.rmtree(folder, ignore_errors=True)
        partial.rename(folder)
        reused = False
    else:
        reused = True
    summary = json.loads(done.read_text())
    return ScanFiles(folder / "scan.mcap", folder / "truth", summary, summary["options"], reused)


if __name__ == "__main__":
    import sys

    chosen = QUICK if "--quick" in sys.argv else LAB
    files = cached_scan(chosen)
    print(json.dumps({k: v for k, v in files.summary.items() if k != "options"}, indent=2))
