"""``scanpipe simulate``: a scan of a virtual rig, with its ground truth.

``--direct`` computes the recording without sockets (:func:`scanpipe.sim.direct.simulate_direct`);
without it the emulators run on loopback and a pseudo-terminal and ``record``'s recorder drives
them (:func:`simulate_live`).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import JSON, QUIET, RIG, print_json
from scanpipe.errors import UsageError


def sim_options(scene: str, rig_path: Path | None, motor_step: float,
                scanner_step: float | None, noise_mm: float, no_cameras: bool, seed: int,
                mode: str, camera_scale: float, camera_fps: float | None) -> Any:
    """Validated :class:`~scanpipe.sim.options.SimOptions` from command-line values."""
    from scanpipe.params import validate
    from scanpipe.rig import load_rig
    from scanpipe.sim.options import SimOptions

    return validate(SimOptions, {
        "scene": scene, "rig": load_rig(rig_path), "motor_step_deg": motor_step,
        "scanner_step_deg": scanner_step, "noise_sigma_m": noise_mm / 1000.0,
        "cameras": not no_cameras, "seed": seed, "mode": mode, "camera_scale": camera_scale,
        "camera_fps": camera_fps,
    }, "simulate options")


def simulate_live(out: Path, truth: Path, options: Any, speedup: float, quiet: bool,
                  as_json: bool) -> int:
    """Run the emulators and record them through the acquisition recorder; write the truth."""
    from scanpipe.acquire.recorder import Recorder, RecordOptions
    from scanpipe.cli.acquire import run_recorder
    from scanpipe.sim.emulators import VirtualRig

    with VirtualRig(options, speedup=speedup) as virtual:
        record_options = RecordOptions(
            mode=options.mode, step_angle_deg=options.motor_step_deg, cameras=options.cameras,
            jpeg_quality=options.jpeg_quality, speedup=speedup)
        recorder = Recorder(virtual.client_rig(), out, record_options,
                            camera_opener=lambda cam: virtual.camera(cam.source))
        code = run_recorder(recorder, quiet, as_json)
        virtual.stop()
        virtual.write_truth(truth, {"recording": str(out), "speedup": speedup})
    return code


def simulate(
    direct: bool = typer.Option(False, "--direct",
                                help="Compute the recording without sockets (fast)."),
    out: Path = typer.Option(..., "--out", help="The recording to write (.mcap)."),
    truth: Path = typer.Option(..., "--truth", help="The ground-truth folder to write."),
    scene: str = typer.Option("room", "--scene",
                              help="room, box, or a scene file (.obj, .glb, .gltf) in metres."),
    rig_path: Path | None = RIG,
    motor_step: float = typer.Option(0.108, "--motor-step",
                                     help="Motor step in degrees (closest achievable is used)."),
    scanner_step: float | None = typer.Option(None, "--scanner-step",
                                              help="Scanner angular step in degrees "
                                                   "(default: the rig's)."),
    noise_mm: float = typer.Option(10.0, "--noise-mm", help="Range noise σ in millimetres."),
    no_cameras: bool = typer.Option(False, "--no-cameras", help="Simulate no cameras."),
    camera_scale: float = typer.Option(0.5, "--camera-scale",
                                       help="Camera resolution as a fraction of the rig's."),
    camera_fps: float = typer.Option(1.0, "--camera-fps", help="Camera frame rate."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed, the same bytes."),
    mode: str = typer.Option("step", "--mode", help="step (step-and-scan) or continuous."),
    speedup: float = typer.Option(10.0, "--speedup",
                                  help="Without --direct: the emulators' clock speed-up."),
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Simulate a scan of a virtual rig: a recording plus its ground truth."""
    from scanpipe.progress import rich_progress
    from scanpipe.sim.direct import simulate_direct

    if out.exists() and out.is_dir():
        raise UsageError(f"--out {out}: is a directory; give a file name such as scan.mcap")
    if truth.exists() and not truth.is_dir():
        raise UsageError(f"--truth {truth}: exists and is not a folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    options = sim_options(scene, rig_path, motor_step, scanner_step, noise_mm, no_cameras, seed,
                          mode, camera_scale, camera_fps)
    if not direct:
        code = simulate_live(out, truth, options, speedup, quiet, as_json)
        if code:
            raise typer.Exit(code)
        return
    with rich_progress(quiet) as progress:
        summary = simulate_direct(out, truth, options, progress)
    if as_json:
        print_json(summary)
    elif not quiet:
        sys.stderr.write(
            f"simulate: {summary['profiles']} profiles × {summary['samples_per_profile']} "
            f"samples, {summary['motor_states']} motor states, {summary['frames']} frames "
            f"in {summary['seconds']:.1f} s → {out}, truth in {truth}\n")


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the main app."""
    app.command("simulate")(simulate)
