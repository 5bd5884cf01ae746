"""``scanpipe simulate``: a scan of a virtual rig, with its ground truth.

``--direct`` computes the recording without sockets (:func:`scanpipe.sim.direct.simulate_direct`);
without it the emulators run on loopback and a pseudo-terminal and ``record``'s recorder drives
them (:func:`simulate_live`).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import (
    JSON,
    LIVE,
    LIVE_HOST,
    QUIET,
    RIG,
    deprecated_alias,
    live_taps,
    print_json,
    print_warnings,
    take_alias,
    with_model_options,
)
from scanpipe.errors import RecordingError, UsageError
from scanpipe.rig import Pose
from scanpipe.scanner_models import SCANNER_MODELS
from scanpipe.sim.options import SimOptions

#: The :class:`~scanpipe.sim.options.SimOptions` fields that are options of ``simulate``: their
#: flags, types, defaults and help come from the model (:func:`~scanpipe.cli.common.model_options`).
SIM_OPTION_FIELDS = ("scene", "scene_up", "mode", "motor_step_deg", "beam_step_deg", "cameras",
                     "camera_scale", "camera_fps", "seed")
#: ``--noise-mm`` is in millimetres, the model's ``noise_sigma_m`` in metres.
NOISE_DEFAULT_MM = SimOptions.model_fields["noise_sigma_m"].default * 1000.0


def sim_options(rig_path: Path | None, noise_mm: float | None, values: dict[str, Any],
                scanner: str | None = None) -> SimOptions:
    """Validated :class:`~scanpipe.sim.options.SimOptions` from command-line values (``values``
    by field name). ``scanner`` puts that model's scanner on the rig (its mount kept); the
    noise defaults to the σ of the rig's scanner model (10 mm for an unnamed scanner)."""
    from scanpipe.params import validate
    from scanpipe.rig import load_rig, scanner_for_model
    from scanpipe.scanner_models import model_of

    rig = load_rig(rig_path)
    if scanner is not None:
        if scanner not in SCANNER_MODELS:
            raise UsageError(f"--scanner {scanner!r}: unknown; allowed: "
                             f"{', '.join(SCANNER_MODELS)}")
        rig = rig.model_copy(update={"scanner": scanner_for_model(scanner, rig.scanner.mount)})
    if noise_mm is None:
        model = model_of(rig.scanner.model, rig.scanner.dialect)
        noise_m = model.noise_sigma_m if model is not None else NOISE_DEFAULT_MM / 1000.0
    else:
        noise_m = noise_mm / 1000.0
    return validate(SimOptions, {**values, "rig": rig, "noise_sigma_m": noise_m},
                    "simulate options")


def parse_scene_pose(text: str | None) -> Pose | None:
    """``--scene-pose "tx,ty,tz[,rx,ry,rz]"`` (metres, degrees) as a :class:`Pose`."""
    if text is None:
        return None
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (3, 6) or not all(math.isfinite(v) for v in values):
        raise UsageError(f"--scene-pose {text!r}: allowed 'tx,ty,tz' or 'tx,ty,tz,rx,ry,rz' "
                         "(translation in metres, rotation in degrees), finite numbers")
    rotation = (values[3], values[4], values[5]) if len(values) == 6 else (0.0, 0.0, 0.0)
    return Pose(translation_m=(values[0], values[1], values[2]), rotation_deg=rotation)


def check_outputs(out: Path, truth: Path, scene: str, rig_path: Path | None,
                  force: bool) -> None:
    """The output-path policy (:mod:`scanpipe.outpaths`) for ``--out`` and ``--truth``."""
    from scanpipe.outpaths import check_output_file, check_output_files, check_output_folder
    from scanpipe.sim.truth import META_FILE, PROFILES_FILE, RIG_FILE, SCENE_FILE

    inputs = [Path(scene)] + ([rig_path] if rig_path is not None else [])
    check_output_file(out, "--out", (".mcap",), force, inputs)
    check_output_folder(truth, "--truth", [out, *inputs])
    check_output_files([truth / name for name in (SCENE_FILE, RIG_FILE, PROFILES_FILE, META_FILE)],
                       "--truth", force, [out, *inputs])


def check_speedup(speedup: float) -> None:
    """``--speedup`` within what the recorder accepts (exit 2 otherwise, even with --direct)."""
    from scanpipe.acquire.recorder import RecordOptions
    from scanpipe.params import validate

    validate(RecordOptions, {"speedup": speedup}, "simulate options")


@contextmanager
def atomic_recording(out: Path) -> Iterator[Path]:
    """The recording is written under a temporary name and renamed when finished, so a failed
    or interrupted simulation leaves no half file and the previous recording intact."""
    from scanpipe.artifacts import atomic_path
    from scanpipe.recording.writer import RecordingWriteError

    try:
        with atomic_path(out) as tmp:
            yield tmp
    except OSError as err:
        raise UsageError(f"--out {out}: cannot be written ({err.strerror or err})") from None
    except RecordingWriteError as err:  # the temporary file is gone: say so, by the real name
        raise RecordingError(f"{out}: cannot be written ({err.reason}); nothing was written "
                             "and an earlier file of that name is unchanged") from None


def simulate_live(out: Path, truth: Path, options: SimOptions, speedup: float, quiet: bool,
                  as_json: bool, live: int | None = None, live_host: str = "127.0.0.1") -> int:
    """Run the emulators and record them through the acquisition recorder; write the truth."""
    from scanpipe.acquire.recorder import Recorder, RecordOptions
    from scanpipe.cli.acquire import run_recorder
    from scanpipe.sim.emulators import VirtualRig

    with VirtualRig(options, speedup=speedup) as virtual, atomic_recording(out) as tmp, \
            live_taps(options.rig, live, live_host, quiet) as taps:
        record_options = RecordOptions(
            mode=options.mode, motor_step_deg=options.motor_step_deg, cameras=options.cameras,
            jpeg_quality=options.jpeg_quality, speedup=speedup)
        recorder = Recorder(virtual.client_rig(), tmp, record_options,
                            camera_opener=lambda cam: virtual.camera(cam.source), taps=taps)
        print_warnings("simulate", {"warnings": virtual.scene.warnings})
        code = run_recorder(recorder, quiet, as_json, {str(tmp): str(out)})
        virtual.stop()
        virtual.write_truth(truth, {"recording": str(out), "speedup": speedup})
    return code


@with_model_options(SimOptions, SIM_OPTION_FIELDS)
def simulate(
    ctx: typer.Context,
    direct: bool = typer.Option(False, "--direct",
                                help="Compute the recording without sockets (fast)."),
    out: Path = typer.Option(..., "--out", help="The recording to write (.mcap)."),
    truth: Path = typer.Option(..., "--truth", help="The ground-truth folder to write."),
    rig_path: Path | None = RIG,
    noise_mm: float | None = typer.Option(
        None, "--noise-mm", help="Range noise σ in millimetres (default: the scanner model's, "
                                 f"{NOISE_DEFAULT_MM:g} for an unnamed scanner)."),
    scanner: str | None = typer.Option(
        None, "--scanner", help="Simulate this scanner model on the rig: "
                                + ", ".join(SCANNER_MODELS) + "."),
    speedup: float = typer.Option(10.0, "--speedup",
                                  help="Without --direct: the emulators' clock speed-up."),
    force: bool = typer.Option(False, "--force",
                               help="Overwrite an existing recording and truth files."),
    live: int | None = LIVE,
    live_host: str = LIVE_HOST,
    quiet: bool = QUIET,
    as_json: bool = JSON,
    scene_pose: str | None = typer.Option(
        None, "--scene-pose", help="Place the scene file: 'tx,ty,tz' metres, optionally "
                                   "',rx,ry,rz' degrees (rotation first, then translation)."),
    scanner_step: float | None = deprecated_alias("--beam-step", "--scanner-step"),
    site: int | None = typer.Option(
        None, "--site", min=2, max=200,
        help="Scan the built-in site from this many positions: --out is then a folder of "
             "recordings, --truth holds the true poses (see docs/sites.md); needs --direct."),
    prior_error_m: float | None = typer.Option(
        None, "--prior-error-m", min=0.0, max=10.0,
        help="With --site: also write a rough odometry prior, positions off by up to this."),
    prior_error_deg: float = typer.Option(
        10.0, "--prior-error-deg", min=0.0, max=180.0,
        help="With --prior-error-m: headings off by up to this many degrees."),
    **values: Any,
) -> None:
    """Simulate a scan of a virtual rig: a recording plus its ground truth."""
    from scanpipe.progress import rich_progress
    from scanpipe.sim.direct import simulate_direct

    values["beam_step_deg"] = take_alias(ctx, "beam_step_deg", values["beam_step_deg"],
                                         scanner_step, "--beam-step", "--scanner-step")
    values["scene_pose"] = parse_scene_pose(scene_pose)
    if site is not None:
        simulate_site_command(out, truth, site, direct, rig_path, noise_mm, values, force, quiet,
                              as_json, prior_error_m, prior_error_deg)
        return
    if prior_error_m is not None:
        raise UsageError("--prior-error-m: only with --site N")
    if direct and live is not None:
        raise UsageError("--live serves a scan as it is recorded; it cannot be combined with "
                         "--direct (drop one)")
    check_outputs(out, truth, values["scene"], rig_path, force)
    options = sim_options(rig_path, noise_mm, values, scanner)
    check_speedup(speedup)
    if not direct:
        code = simulate_live(out, truth, options, speedup, quiet, as_json, live, live_host)
        if code:
            raise typer.Exit(code)
        return
    with rich_progress(quiet) as progress, atomic_recording(out) as tmp:
        summary = simulate_direct(tmp, truth, options, progress, recording_name=str(out))
    summary["recording"] = str(out)
    print_warnings("simulate", summary)
    if as_json:
        print_json(summary)
    elif not quiet:
        sys.stderr.write(
            f"simulate: {summary['profiles']} profiles × {summary['samples_per_profile']} "
            f"samples, {summary['motor_states']} motor states, {summary['frames']} frames "
            f"in {summary['seconds']:.1f} s → {out}, truth in {truth}\n")


def simulate_site_command(out: Path, truth: Path, count: int, direct: bool,
                          rig_path: Path | None, noise_mm: float | None, values: dict[str, Any],
                          force: bool, quiet: bool, as_json: bool, prior_error_m: float | None,
                          prior_error_deg: float) -> None:
    """``simulate --site N``: N recordings of the built-in site, the true poses, a prior."""
    from scanpipe.outpaths import check_output_files, check_output_folder
    from scanpipe.progress import rich_progress
    from scanpipe.sim.site import (
        PRIOR_POSES_FILE,
        SITE_META_FILE,
        SITE_POSES_FILE,
        SITE_SCENE_FILE,
        position_name,
        simulate_site,
    )

    if not direct:
        raise UsageError("--site: only with --direct (the emulators scan one position)")
    if values["scene"] != "room" or values["scene_pose"] is not None:
        raise UsageError("--site: the site is the built-in one; leave out --scene and "
                         "--scene-pose")
    inputs = [rig_path] if rig_path is not None else []
    check_output_folder(out, "--out", inputs)
    check_output_folder(truth, "--truth", [out, *inputs])
    names = [position_name(i) for i in range(count)]
    files = [out / f"{n}.mcap" for n in names] + [out / PRIOR_POSES_FILE]
    files += [truth / f for f in (SITE_POSES_FILE, SITE_SCENE_FILE, SITE_META_FILE)]
    files += [truth / n / "scene.glb" for n in names]
    check_output_files(files, "--out/--truth", force, inputs)
    out.mkdir(parents=True, exist_ok=True)
    options = sim_options(rig_path, noise_mm, {**values, "scene_pose": None})
    with rich_progress(quiet) as progress:
        summary = simulate_site(out, truth, options, count, prior_error_m, prior_error_deg,
                                progress=progress)
    print_warnings("simulate", summary)
    if as_json:
        print_json(summary)
    elif not quiet:
        sys.stderr.write(f"simulate: {count} positions of the site in {summary['seconds']:.1f} s "
                         f"→ {out}, true poses in {truth / SITE_POSES_FILE}\n")


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the main app."""
    app.command("simulate")(simulate)
