"""``scanpipe plan``: the paper's step arithmetic and the scan it implies for a rig."""

from __future__ import annotations

from pathlib import Path

import typer

from scanpipe.cli.common import JSON, MOTOR_STEP, RIG, deprecated_alias, print_json, take_alias
from scanpipe.planning import ScanPlan, plan_scan
from scanpipe.rig import load_rig


def _format_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000
    return f"{n:.1f} GB"


def format_plan(plan: ScanPlan) -> str:
    """The plan as text for a terminal."""
    s = plan.steps
    lines = [
        f"pulse step          {s.pulse_step_deg:g}° (the minimum step)",
        f"steps per turn      {s.steps_per_turn}",
        f"requested           {s.requested_motor_step_deg:g}° = {s.requested_steps:g} steps",
        "possible angles:",
    ]
    for i, (steps, angle) in enumerate(zip(s.possible_steps, s.possible_angles_deg, strict=True)):
        mark = "  ← closest" if i == s.closest_index else ""
        lines.append(f"  {steps:6d} steps  {angle:8.3f}°{mark}")
    lines += [
        f"motor step          {plan.motor_step_count} steps = {plan.motor_step_deg:g}°",
        f"travel              {plan.travel_deg:g}° (pulse limit)",
        f"profiles            {plan.profiles}",
        f"samples / profile   {plan.samples_per_profile}",
        f"points              {plan.points:,}",
        f"raw data            {_format_bytes(plan.raw_bytes)} ({plan.frame_bytes} B / profile)",
        f"scan time           {plan.scan_time_s:.1f} s at the scan frequency, "
        f"~{plan.step_and_scan_time_s:.0f} s step-and-scan",
    ]
    if plan.device_limits:
        lines.append(f"{plan.device_model} device limits:")
        for c in plan.device_limits:
            lines.append(f"  {'ok  ' if c.ok else 'FAIL'} {c.name} = {c.value:g} ({c.limit})")
    return "\n".join(lines)


def plan(
    ctx: typer.Context,
    motor_step_deg: float = MOTOR_STEP,
    rig_path: Path | None = RIG,
    as_json: bool = JSON,
    angle: float | None = deprecated_alias("--motor-step", "--angle"),
) -> None:
    """The step arithmetic of paper eq. 1–4 for a motor step, and the scan it gives."""
    motor_step_deg = take_alias(ctx, "motor_step_deg", motor_step_deg, angle, "--motor-step",
                                "--angle")
    result = plan_scan(load_rig(rig_path), motor_step_deg)
    if as_json:
        print_json(result.to_json())
    else:
        typer.echo(format_plan(result))


def register(app: typer.Typer) -> None:
    """Add ``plan`` to the main app."""
    app.command("plan")(plan)
