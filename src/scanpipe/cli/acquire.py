"""``scanpipe record``, ``scanpipe info`` and ``scanpipe import-video``: the robot side."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import (
    FORCE,
    JSON,
    LIVE,
    LIVE_HOST,
    MOTOR_STEP,
    QUIET,
    RIG,
    deprecated_alias,
    live_taps,
    print_error,
    print_json,
    print_warnings,
    take_alias,
)
from scanpipe.errors import UsageError

#: Exit codes of ``record`` by final status (a finished file in every case).
RECORD_EXIT_CODES = {"complete": 0, "interrupted": 130, "failed": 1, "scanner_disconnected": 3}


def record_options(
    mode: str, motor_step_deg: float, profiles_per_position: int, cameras: bool,
    split_size_mb: float | None, split_duration_s: float | None, speedup: float = 1.0,
    with_echo: bool = False, home_first: bool = False,
) -> Any:
    """Validated :class:`~scanpipe.acquire.recorder.RecordOptions` from command-line values."""
    from scanpipe.acquire.recorder import RecordOptions
    from scanpipe.params import validate

    return validate(RecordOptions, {
        "mode": mode, "motor_step_deg": motor_step_deg,
        "profiles_per_position": profiles_per_position, "cameras": cameras,
        "split_size_mb": split_size_mb, "split_duration_s": split_duration_s,
        "speedup": speedup, "with_echo": with_echo, "home_first": home_first,
    }, "record options")


def run_recorder(recorder: Any, quiet: bool, as_json: bool,
                 renamed: dict[str, str] | None = None) -> int:
    """Run a recorder with the live display, print the summary; the exit code by status.

    ``renamed`` maps a temporary file the recorder writes to the name it gets afterwards.
    """
    from scanpipe.acquire.display import format_summary, live_display

    with live_display(recorder.live_status, quiet):
        summary = recorder.run()
    if renamed:
        summary["files"] = [renamed.get(name, name) for name in summary["files"]]
    if as_json:
        print_json(summary)
    elif not quiet:
        sys.stderr.write(format_summary(summary) + "\n")
    if summary["status"] != "complete" and summary.get("reason"):
        print_error(f"recording {summary['status']}: {summary['reason']} "
                    f"(the file is finished: {', '.join(summary['files'])})")
    return RECORD_EXIT_CODES.get(summary["status"], 1)


def record(
    ctx: typer.Context,
    out: Path = typer.Option(..., "--out", help="The recording to write (.mcap)."),
    rig_path: Path | None = RIG,
    mode: str = typer.Option("step", "--mode", help="step (step-and-scan) or continuous."),
    motor_step_deg: float = MOTOR_STEP,
    profiles_per_position: int = typer.Option(1, "--profiles-per-position",
                                              help="Complete profiles per position (step mode)."),
    no_cameras: bool = typer.Option(False, "--no-cameras", help="Do not record the cameras."),
    echo: bool = typer.Option(True, "--echo/--no-echo",
                              help="ldoem: record echo amplitudes (format mask 0x3DFF) or "
                                   "ranges only (0x39FF)."),
    split_size_mb: float | None = typer.Option(None, "--split-size-mb",
                                               help="Start a new file part after this many MB."),
    split_duration_s: float | None = typer.Option(None, "--split-duration",
                                                  help="Start a new file part after this many s."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing recording."),
    home_first: bool = typer.Option(False, "--home-first",
                                    help="Bring a platform that stands away from home back "
                                         "home before scanning (otherwise refused)."),
    speedup: float = typer.Option(1.0, "--speedup", hidden=True,
                                  help="Device time runs this much faster (virtual rig only)."),
    live: int | None = LIVE,
    live_host: str = LIVE_HOST,
    quiet: bool = QUIET,
    as_json: bool = JSON,
    step_angle: float | None = deprecated_alias("--motor-step", "--step-angle"),
) -> None:
    """Record a scan: scanner, motor and cameras, raw and timestamped, into one MCAP file."""
    from scanpipe.acquire.recorder import Recorder
    from scanpipe.outpaths import check_output_file
    from scanpipe.rig import load_rig

    motor_step_deg = take_alias(ctx, "motor_step_deg", motor_step_deg, step_angle, "--motor-step",
                                "--step-angle")
    # A recording is streamed to its name (crash-safe, so a killed recorder keeps what it got).
    check_output_file(out, "--out", (".mcap",), force, [rig_path] if rig_path else [])
    rig = load_rig(rig_path)
    options = record_options(mode, motor_step_deg, profiles_per_position, not no_cameras,
                             split_size_mb, split_duration_s, speedup, echo, home_first)
    with live_taps(rig, live, live_host, quiet) as taps:
        code = run_recorder(Recorder(rig, out, options, taps=taps), quiet, as_json)
    if code:
        raise typer.Exit(code)


def info(
    recording: Path = typer.Argument(..., help="The recording, or any MCAP file (.mcap)."),
    gap: float = typer.Option(1.0, "--gap", help="Count pauses longer than this many seconds."),
    as_json: bool = JSON,
) -> None:
    """Channels, counts, durations, rates, gaps, events and the rig of a recording; for any
    other MCAP file its channels, schemas, message counts and time range (like mcap info)."""
    from scanpipe.acquire.info import format_info, recording_info
    from scanpipe.recording.catalogue import catalogue_info, format_catalogue
    from scanpipe.recording.reader import (
        header_profile,
        read_catalogue,
        read_recording_and_catalogue,
    )
    from scanpipe.recording.writer import PROFILE

    if gap <= 0:
        raise UsageError(f"--gap {gap!r}: must be greater than 0 seconds")
    profile = header_profile(recording)
    if profile != PROFILE:  # not a scanpipe recording: the generic view
        catalogue = catalogue_info(read_catalogue(recording))
        if as_json:
            print_json({"recording": False, "mcap": catalogue})
        else:
            typer.echo(format_catalogue(catalogue))
        if profile in ("ros1", "ros2"):
            sys.stderr.write(f"{recording}: a ROS bag, not a scanpipe recording: `scanpipe "
                             "import-bag` makes a recording of its LaserScan, joint and image "
                             "topics\n")
        return
    read, catalogue_read = read_recording_and_catalogue(recording)
    result = {"recording": True, **recording_info(read, gap),
              "mcap": catalogue_info(catalogue_read)}
    if as_json:
        print_json(result)
    else:
        typer.echo(format_info(result))


def recover(
    damaged: Path = typer.Argument(..., help="The damaged MCAP file."),
    out: Path = typer.Option(..., "--out", "-o", help="The new MCAP file to write."),
    force: bool = FORCE,
    as_json: bool = JSON,
) -> None:
    """Copy every message that can be read from a damaged MCAP file (a killed writer, a cut
    copy, damaged chunks) into a new, valid MCAP file."""
    from scanpipe.outpaths import check_output_file
    from scanpipe.recording.catalogue import recover_mcap

    check_output_file(out, "--out", (".mcap",), force, inputs=[damaged])
    report = recover_mcap(damaged, out)
    if as_json:
        print_json(report)
        return
    loss = report["loss"]
    bound = "" if loss["exact"] else "at least "
    typer.echo(f"{out}: {report['messages']} messages on {report['channels']} channels "
               f"recovered from {damaged}; lost {bound}{loss['chunks']} chunks "
               f"({loss['bytes']} bytes)")
    for warning in report["warnings"]:
        sys.stderr.write(f"warning: recover: {warning}\n")


def import_video(
    video: Path = typer.Argument(..., help="The video file (any container OpenCV reads)."),
    into: Path = typer.Option(..., "--into", help="The recording to add the frames to."),
    start_time: str = typer.Option(..., "--start-time",
                                   help="When the video's first frame was taken: ISO 8601, "
                                        "seconds or ns since the epoch, or 'recording'."),
    offset: float = typer.Option(0.0, "--offset", help="Seconds added to every frame time "
                                 "(with --refine: a rough value, within --window)."),
    refine: bool = typer.Option(False, "--refine", help="Find the exact offset from the data "
                                "(the scan's depth edges against the video's image edges)."),
    window: float = typer.Option(1.0, "--window", min=0.05, max=30.0,
                                 help="With --refine: search ± this many seconds."),
    camera: str | None = typer.Option(None, "--camera",
                                      help="Camera id in the recording's rig "
                                           "(default: its first camera)."),
    quality: int = typer.Option(90, "--jpeg-quality", help="JPEG quality 1–100."),
    replace: bool = typer.Option(False, "--replace", help="Drop the frames the recording "
                                 "already holds for this camera (a video imported before)."),
    as_json: bool = JSON,
) -> None:
    """Add a separately recorded video to a recording as camera frames with timestamps."""
    from scanpipe.acquire.video_import import (
        first_frame_ns,
        parse_start_time,
        recording_start_ns,
    )
    from scanpipe.acquire.video_import import import_video as run_import
    from scanpipe.outpaths import check_input_file, check_not_input
    from scanpipe.recording.reader import read_recording

    if not 1 <= quality <= 100:
        raise UsageError(f"--jpeg-quality {quality}: allowed 1…100")
    check_input_file(into, "--into")  # rewritten in place (temporary name, then rename)
    check_not_input(into, [video], "--into")
    recorded = read_recording(into)
    if not recorded.complete:
        raise UsageError(f"{into}: the recording is incomplete (its writer did not finish); "
                         "import into a complete recording")
    rig = recorded.rig()
    if camera is None:
        if not rig.cameras:
            raise UsageError(f"{into}: the recording's rig has no cameras; add the camera to "
                             "the rig (its intrinsics are needed for texturing)")
        camera = rig.cameras[0].id
    rig.camera(camera)  # an unknown id is an error naming the known ones
    held = sum(1 for i in recorded.images if i.camera_id == camera)
    if held and not replace:
        raise UsageError(f"{into}: already holds {held} frames of camera {camera} (recorded, "
                         "or a video imported before): two takes under one camera would be "
                         "mixed; pass --replace to drop them, or import as another camera of "
                         "the rig")
    start = parse_start_time(start_time, recording_start_ns(into) if start_time.strip()
                             == "recording" else None)
    refined = None
    if refine:
        from scanpipe.acquire.video_import import refine_offset

        refined = refine_offset(video, into, first_frame_ns(start, offset, start_time), camera,
                                window)
        offset += refined["offset_s"]
    report = run_import(video, into, first_frame_ns(start, offset, start_time), camera,
                        quality, rig.camera(camera), replace=replace)
    print_warnings("import-video", report)
    if refined is not None:
        report["offset_s"] = offset
        report["refined"] = refined
        for warning in refined["warnings"]:
            typer.echo(f"warning: {warning}", err=True)
    if as_json:
        print_json(report)
    else:
        if refined is not None:
            before = refined["alignment_before"]["edge_median_px"]
            after = refined["alignment_after"]["edge_median_px"]
            typer.echo(f"offset refined: {offset:+.3f} s ± "
                       f"{(refined['offset_sigma_s'] or 0) * 1000:.1f} ms (edges: median "
                       f"{before if before is None else round(before, 2)} → "
                       f"{after if after is None else round(after, 2)} px)")
        typer.echo(f"{into}: added {report['frames']} frames of {video} as camera {camera} "
                   f"({report['first_time_ns']} … {report['last_time_ns']} ns)")


def register(app: typer.Typer) -> None:
    """Add ``record``, ``info`` and ``import-video`` to the main app."""
    app.command("record")(record)
    app.command("info")(info)
    app.command("recover")(recover)
    app.command("import-video")(import_video)
