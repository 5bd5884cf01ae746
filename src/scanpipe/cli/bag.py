"""``scanpipe import-bag``: a ROS bag (ROS 1 or ROS 2) to a scanpipe recording."""

from __future__ import annotations

from pathlib import Path

import typer

from scanpipe.cli.common import FORCE, JSON, print_json, print_warnings


def import_bag(
    bag: Path = typer.Argument(..., help="The ROS bag: a ROS 1 .bag, or a ROS 2 bag (its folder "
                                         "with metadata.yaml, or its .db3/.mcap file)."),
    out: Path = typer.Option(..., "--out", help="The recording to write (.mcap)."),
    scan: str | None = typer.Option(None, "--scan", help="LaserScan topic (default: the only "
                                                         "one)."),
    joint: str | None = typer.Option(None, "--joint", help="Platform angle: this joint's "
                                                           "position in JointState (radians)."),
    tf: str | None = typer.Option(None, "--tf", help="Platform angle: the yaw of CHILD in "
                                                     "PARENT, as PARENT:CHILD; also gives the "
                                                     "scanner's mount from TF."),
    image: list[str] = typer.Option([], "--image", help="Image topic to import as a camera "
                                                        "(repeatable)."),
    rig: Path | None = typer.Option(None, "--rig", help="Rig TOML file to store instead of "
                                                        "the one built from the bag."),
    force: bool = FORCE,
    as_json: bool = JSON,
) -> None:
    """Import a ROS bag (LaserScan, JointState or TF, images) as a recording `run` takes."""
    from scanpipe.bagio import import_bag as run_import
    from scanpipe.outpaths import check_output_file
    from scanpipe.rig import load_rig

    check_output_file(out, "--out", (".mcap",), force, [bag])
    given = load_rig(rig) if rig is not None else None
    report = run_import(bag, out, scan, joint, tf, image, given)
    if as_json:
        print_json(report)
        return
    lo, hi = report["beta_deg_range"]
    images = ", ".join(f"{k}: {v}" for k, v in report["images"].items()) or "no images"
    # Texturing needs camera frames: without them the chain ends at the mesh.
    until = "" if report["images"] else " --to mesh"
    typer.echo(f"{out}: {report['profiles']} profiles × {report['samples_per_profile']} "
               f"samples from {report['scan_topic']}, {report['angle_reports']} platform "
               f"angles ({lo:.1f}° … {hi:.1f}°), {images}; next: scanpipe run {out} "
               f"--workdir W{until}")
    print_warnings("import-bag", report)


def register(app: typer.Typer) -> None:
    """Add ``import-bag`` to the main app."""
    app.command("import-bag")(import_bag)
