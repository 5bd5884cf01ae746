"""The live display of a recording (rich, on stderr) and the summary printed at the end."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class RecorderStatus:
    """A snapshot of a recording under way, for the display."""

    mode: str
    phase: str
    elapsed_s: float
    profiles: int
    positions_done: int
    positions_total: int | None
    step_count: int
    pulse_limit: int
    beta_deg: float
    frames: Mapping[str, int] = field(default_factory=dict)
    dropped_frames: int = 0
    data_rate_bps: float = 0.0
    total_bytes: int = 0
    time_left_s: float | None = None
    events: int = 0
    last_event: str = ""
    #: The controller's count where the scan started (None before it starts), and the samples
    #: of one profile: the coverage so far (share of the planned range, points).
    start_count: int | None = None
    samples_per_profile: int = 0


def coverage(status: RecorderStatus) -> tuple[float | None, int]:
    """``(share of the planned platform range covered, points so far)``.

    The range runs from the scan's start count to ``pulse_limit`` (the sweep's end count); the
    share is None before the scan starts. Points: one profile per position in step mode
    (``positions_done``), every profile in continuous mode, times the samples of a profile.
    """
    profiles = status.positions_done if status.mode == "step" else status.profiles
    points = profiles * status.samples_per_profile
    if status.start_count is None:
        return None, points
    planned = status.pulse_limit - status.start_count
    done = status.step_count - status.start_count
    return (min(1.0, max(0.0, done / planned)) if planned > 0 else None), points


def format_bytes(n: float) -> str:
    """``1234567`` → ``1.2 MB``."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"  # pragma: no cover - the loop always returns


def format_duration(seconds: float | None) -> str:
    """``75.2`` → ``1:15``; None → ``?``."""
    if seconds is None:
        return "?"
    seconds = max(0.0, seconds)
    minutes, secs = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def status_lines(status: RecorderStatus) -> list[tuple[str, str]]:
    """The display's rows as (label, value) pairs (also used by tests)."""
    positions = (f"{status.positions_done}/{status.positions_total}"
                 if status.positions_total else str(status.positions_done))
    frames = ", ".join(f"{cam} {n}" for cam, n in status.frames.items()) or "no cameras"
    if status.dropped_frames:
        frames += f" ({status.dropped_frames} dropped)"
    share, points = coverage(status)
    covered = "?" if share is None else f"{share:.0%} of the planned range"
    return [
        ("mode", f"{status.mode} — {status.phase}"),
        ("coverage", f"{covered}, {points:,} points so far"),
        ("elapsed", format_duration(status.elapsed_s)),
        ("time left", format_duration(status.time_left_s)),
        ("profiles", str(status.profiles)),
        ("positions", positions),
        ("motor", f"{status.step_count}/{status.pulse_limit} pulses, β = {status.beta_deg:.3f}°"),
        ("frames", frames),
        ("data", f"{format_bytes(status.total_bytes)} at {format_bytes(status.data_rate_bps)}/s"),
        ("events", f"{status.events}" + (f" — last: {status.last_event}"
                                         if status.last_event else "")),
    ]


@contextmanager
def live_display(get_status: Callable[[], RecorderStatus], quiet: bool = False) -> Iterator[None]:
    """Redraw ``get_status()`` a few times a second on stderr while the block runs.

    Nothing is drawn with ``quiet`` or when stderr is not a terminal.
    """
    if quiet or not sys.stderr.isatty():
        yield
        return
    from rich.console import Console
    from rich.live import Live

    class _View:
        def __rich__(self) -> Any:
            return status_table(get_status())

    with Live(_View(), console=Console(stderr=True), refresh_per_second=4, transient=False):
        yield


def status_table(status: RecorderStatus) -> Any:
    """The display as a rich table (label, value)."""
    from rich.table import Table

    table = Table.grid(padding=(0, 2))
    table.add_column(style="bold")
    table.add_column()
    for label, value in status_lines(status):
        table.add_row(label, value)
    return table


def format_summary(summary: Mapping[str, Any]) -> str:
    """The end-of-recording summary as text."""
    lines = [
        f"recording   {', '.join(summary['files'])}",
        f"status      {summary['status']}" + (f" ({summary['reason']})"
                                               if summary.get("reason") else ""),
        f"mode        {summary['mode']}, {summary['dialect']} scanner",
        f"duration    {summary['duration_s']:.2f} s",
        f"profiles    {summary['profiles']} ({summary['positions']} positions)",
        f"motor       {summary['final_step_count']}/{summary['pulse_limit']} pulses "
        f"({summary['final_beta_deg']:.3f}°), {summary['motor_states']} position reports",
    ]
    frames = summary.get("frames", {})
    if frames:
        dropped = summary.get("dropped_frames", {})
        lines.append("frames      " + ", ".join(
            f"{cam} {n}" + (f" ({dropped[cam]} dropped)" if dropped.get(cam) else "")
            for cam, n in frames.items()))
    lines.append("bytes       " + ", ".join(
        f"{link} {format_bytes(n)}" for link, n in summary.get("stream_bytes", {}).items()))
    events = summary.get("events", {})
    lines.append("events      " + (", ".join(f"{kind} ×{n}" for kind, n in events.items())
                                   or "none"))
    return "\n".join(lines)
