"""``scanpipe demo``: the whole product on the virtual rig, from simulation to report.

Simulates the built-in room, runs the cached chain (decode → assemble → filter → mesh → texture
→ export), renders previews, evaluates against the ground truth and writes the HTML report. The
default resolution is chosen so that all of it takes well under three minutes on two cores.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field

from scanpipe.artifacts import atomic_write_bytes
from scanpipe.params import Params
from scanpipe.pipeline import RunRecord, run_chain, validate_pipeline_params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stages import chain_stages


class DemoOptions(Params):
    """The demo's scan: coarser than the paper's lab scan so that it runs in about a minute."""

    beam_step_deg: float = Field(0.5, gt=0, le=10, description="beam step of the scan")
    motor_step_deg: float = Field(0.36, gt=0, le=10, description="motor step between profiles")
    noise_sigma_m: float = Field(0.010, ge=0, le=0.2, description="range noise σ")
    # The demo scan takes ~200 simulated seconds: 0.2 fps is a frame per ~4.5° of travel.
    camera_fps: float = Field(0.2, gt=0, le=30, description="frames per second per camera")
    camera_scale: float = Field(0.5, gt=0, le=1, description="camera resolution scale")
    seed: int = Field(0, ge=0, description="random seed of the simulation")


@dataclass
class DemoResult:
    """What the demo made and how long each part took."""

    out: Path
    files: dict[str, Path]
    seconds: dict[str, float]
    records: list[RunRecord] = field(default_factory=list)
    evaluation: dict[str, Any] = field(default_factory=dict)


#: The chain's parameters for the demo, beyond each stage's defaults.
#: The defaults (grid mesh over the smoothed range image), plus a LAS copy of the cloud.
DEMO_STAGE_PARAMS: dict[str, Any] = {
    "export": {"mesh_formats": ["obj", "glb"], "cloud_formats": ["ply", "las"]},
}


def run_demo(out: Path, options: DemoOptions | None = None,
             progress: ProgressFn = no_progress,
             on_step: Any = None) -> DemoResult:
    """Run everything into ``out``; returns the files made, the times and the evaluation."""
    from scanpipe.evaluate import evaluate_result
    from scanpipe.render import render_previews
    from scanpipe.report import write_report
    from scanpipe.sim.direct import simulate_direct
    from scanpipe.sim.options import SimOptions

    options = options or DemoOptions()
    say = on_step or (lambda text: None)
    out.mkdir(parents=True, exist_ok=True)
    recording, truth, work = out / "scan.mcap", out / "truth", out / "work"
    seconds: dict[str, float] = {}

    started = time.perf_counter()
    say(f"simulating the built-in room → {recording}")
    simulate_direct(recording, truth, SimOptions(
        beam_step_deg=options.beam_step_deg, motor_step_deg=options.motor_step_deg,
        noise_sigma_m=options.noise_sigma_m, camera_fps=options.camera_fps,
        camera_scale=options.camera_scale, seed=options.seed), progress)
    seconds["simulate"] = time.perf_counter() - started

    stages = chain_stages()
    params = validate_pipeline_params(stages, DEMO_STAGE_PARAMS, "demo")
    say(f"running the pipeline → {work}")
    records = run_chain(recording, work, params, stages, progress=progress,
                        on_stage=lambda r: say(f"  {r.stage:<9} "
                                               f"{'reused' if r.reused else f'{r.seconds:.1f} s'}"))
    for record in records:
        seconds[record.stage] = record.seconds

    files: dict[str, Path] = {}
    export_dir = work / "export"
    for path in sorted(export_dir.iterdir()):
        if path.suffix in (".obj", ".mtl", ".png", ".glb", ".ply", ".las"):
            target = out / path.name
            shutil.copyfile(path, target)
            files[path.name] = target

    started = time.perf_counter()
    say("rendering previews")
    for path in render_previews(work, out / "previews", width=640):
        files[f"previews/{path.name}"] = path
    seconds["render"] = time.perf_counter() - started

    started = time.perf_counter()
    say("evaluating against the ground truth")
    evaluation = evaluate_result(work, truth)
    atomic_write_bytes(out / "eval.json", json.dumps(evaluation, indent=2, default=str).encode())
    files["eval.json"] = out / "eval.json"
    seconds["eval"] = time.perf_counter() - started

    started = time.perf_counter()
    say("writing the report")
    files["report.html"] = write_report(work, out / "report.html", truth)
    seconds["report"] = time.perf_counter() - started
    return DemoResult(out, files, seconds, records, evaluation)
