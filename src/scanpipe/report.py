"""``scanpipe report``: one self-contained HTML file about a workdir.

Everything is inside the file (images as base64 ``data:`` URIs, inline CSS, no links to other
files, nothing fetched from the network): the scan summary, an interactive 3-D view of the
textured model (:mod:`scanpipe.viewer`: three.js and the GLB inside the page; the only script),
the decode and filter counts from the provenance reports, plots (range histogram, coverage
over α × β, time-sync residuals, stage times),
rendered previews of the mesh, and the evaluation table when a truth is given or found
(``WORKDIR/truth``).
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from scanpipe import __version__
from scanpipe.artifacts import atomic_write_bytes, read_artifact
from scanpipe.errors import ArtifactError, ExportError, ScanpipeError, UsageError
from scanpipe.workdir import all_provenance, find_artifact

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; }
table { border-collapse: collapse; margin: .5em 0 1em; }
td, th { border: 1px solid #ddd; padding: .25em .6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { display: inline-block; margin: .5em; } figcaption { font-size: .85em; color: #555; }
img { max-width: 100%; border: 1px solid #ddd; } .note { color: #777; font-size: .9em; }
"""


def _png_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _figure(png: bytes, caption: str) -> str:
    return (f'<figure><img src="{_png_uri(png)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _table(rows: list[tuple[Any, ...]], header: tuple[str, ...]) -> str:
    def cell(value: Any) -> str:
        if isinstance(value, float):
            text = "n/a" if not math.isfinite(value) else f"{value:.4g}"
            return f'<td class="num">{text}</td>'
        if isinstance(value, int) and not isinstance(value, bool):
            return f'<td class="num">{value:,}</td>'
        if value is None:
            return "<td>n/a</td>"
        if isinstance(value, dict | list):
            value = json.dumps(value, default=str)
        return f"<td>{html.escape(str(value))}</td>"

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(cell(v) for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _plot(draw: Any, width_in: float = 6.0, height_in: float = 3.2) -> bytes:
    """Run ``draw(ax)`` on a fresh Agg figure and return the PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(width_in, height_in), dpi=100)
    try:
        draw(axes)
        figure.tight_layout()
        buffer = io.BytesIO()
        figure.savefig(buffer, format="png")
        return buffer.getvalue()
    finally:
        plt.close(figure)


def range_histogram(range_m: np.ndarray) -> bytes:
    """Histogram of measured ranges."""
    finite = range_m[np.isfinite(range_m)]

    def draw(ax: Any) -> None:
        ax.hist(finite, bins=100, color="#3b6ea5")
        ax.set_xlabel("range (m)")
        ax.set_ylabel("points")
        ax.set_title(f"Range histogram ({finite.size:,} returns)")

    return _plot(draw)


def _edges(values: np.ndarray, max_bins: int) -> np.ndarray:
    """Bin edges with one bin per distinct value (a scan is a grid) when there are few enough,
    else ``max_bins`` equal bins; aligning bins to the grid avoids aliasing stripes."""
    distinct = np.unique(np.round(values, 6))
    if 1 < len(distinct) <= max_bins:
        middle = (distinct[1:] + distinct[:-1]) / 2
        first = distinct[0] - (middle[0] - distinct[0])
        last = distinct[-1] + (distinct[-1] - middle[-1])
        return np.concatenate([[first], middle, [last]])
    low, high = float(values.min()), float(values.max())
    return np.linspace(low - 0.5, high + 0.5, 2) if low == high else np.linspace(
        low, high, max_bins + 1)


def coverage_map(alpha_deg: np.ndarray, beta_deg: np.ndarray) -> bytes:
    """Points per cell over beam angle α and platform angle β."""
    alpha = np.mod(alpha_deg, 360.0)

    def draw(ax: Any) -> None:
        counts, a_edges, b_edges = np.histogram2d(
            alpha, beta_deg, bins=(_edges(alpha, 360), _edges(beta_deg, 180)))
        image = ax.pcolormesh(a_edges, b_edges, counts.T, cmap="viridis", shading="flat")
        ax.figure.colorbar(image, ax=ax, label="points")
        ax.set_xlabel("α, beam angle (°)")
        ax.set_ylabel("β, platform angle (°)")
        ax.set_title("Coverage (valid returns per cell)")

    return _plot(draw)


def sync_residuals(profiles: pa.Table) -> tuple[bytes, dict[str, float]] | None:
    """Receive time against device time: residuals of a linear fit (clock offset and drift),
    when the dialect has device timestamps."""
    if "device_time_ns" not in profiles.column_names:
        return None
    device = profiles.column("device_time_ns")
    if device.null_count == len(device) or len(device) < 3:
        return None
    valid = ~np.asarray(device.is_null().to_numpy(zero_copy_only=False), dtype=bool)
    dev = np.asarray(device.to_numpy(zero_copy_only=False), dtype=np.float64)[valid]
    recv = profiles.column("recv_time_ns").to_numpy().astype(np.float64)[valid]
    if dev.size < 3 or np.ptp(dev) == 0:
        return None
    dev_s, recv_s = (dev - dev[0]) / 1e9, (recv - recv[0]) / 1e9
    slope, intercept = np.polyfit(dev_s, recv_s, 1)
    residual_ms = (recv_s - (slope * dev_s + intercept)) * 1e3
    stats = {"rms_ms": float(np.sqrt(np.mean(residual_ms**2))),
             "max_abs_ms": float(np.max(np.abs(residual_ms))),
             "drift_ppm": float((slope - 1.0) * 1e6)}

    def draw(ax: Any) -> None:
        ax.plot(dev_s, residual_ms, ".", markersize=2, color="#a5523b")
        ax.set_xlabel("device time (s)")
        ax.set_ylabel("residual (ms)")
        ax.set_title(f"Time sync: receive − fit(device), RMS {stats['rms_ms']:.2f} ms")

    return _plot(draw), stats


def stage_time_chart(times: dict[str, float]) -> bytes:
    """Bar chart of seconds per stage."""

    def draw(ax: Any) -> None:
        names = list(times)
        ax.barh(names, [times[n] for n in names], color="#5a9e5a")
        ax.invert_yaxis()
        ax.set_xlabel("seconds")
        ax.set_title("Stage times")

    return _plot(draw, height_in=1.6 + 0.3 * len(times))


def _points_section(workdir: Path, parts: list[str]) -> None:
    points_path = find_artifact(workdir, "points")
    if points_path is None:
        parts.append('<p class="note">No points artifact.</p>')
        return
    table, _ = read_artifact(points_path)
    figures = []
    if "range_m" in table.column_names:
        ranges = np.asarray(table.column("range_m").to_numpy(zero_copy_only=False), np.float64)
        if np.any(np.isfinite(ranges)):
            figures.append(_figure(range_histogram(ranges), "Range histogram"))
    if {"alpha_deg", "beta_deg", "x"} <= set(table.column_names):
        alpha = np.asarray(table.column("alpha_deg").to_numpy(zero_copy_only=False), np.float64)
        beta = np.asarray(table.column("beta_deg").to_numpy(zero_copy_only=False), np.float64)
        x = np.asarray(table.column("x").to_numpy(zero_copy_only=False), np.float64)
        ok = np.isfinite(alpha) & np.isfinite(beta) & np.isfinite(x)
        if np.any(ok):
            figures.append(_figure(coverage_map(alpha[ok], beta[ok]),
                                   "Coverage over α × β (valid returns)"))
    parts.append(f"<p>{html.escape(str(points_path.relative_to(workdir)))}: "
                 f"{table.num_rows:,} points.</p>" + "".join(figures))


#: The colour of faces no camera saw, in the report's unseen-surface picture.
UNSEEN_RGB = (255, 0, 255)


def _previews(workdir: Path, width: int) -> list[str]:
    from scanpipe.render import (
        PanoramaView,
        PlanView,
        Renderer,
        View,
        default_perspectives,
        load_render_mesh,
    )

    mesh = load_render_mesh(workdir)
    renderer = Renderer(mesh)
    views: list[View] = [*default_perspectives(mesh.bounds, width=width, mesh=mesh),
                         PlanView(width), PanoramaView((0.0, 0.0, 0.0), width)]
    figures = [_figure(renderer.render(view).png(), view.name.replace("_", " "))
               for view in views]
    pages = mesh.face_pages
    if mesh.textured and pages is not None and bool(np.any(pages < 0)):
        # the surface no camera saw, in magenta over the textured model (untextured faces
        # take the vertex colour)
        marked = dataclasses.replace(mesh, vertex_colors=np.tile(
            np.array(UNSEEN_RGB, np.uint8), (len(mesh.vertices), 1)))
        figures.append(_figure(Renderer(marked).render(PanoramaView((0.0, 0.0, 0.0), width))
                               .png(), "panorama: unseen by every camera (magenta)"))
    return figures


def build_report(workdir: Path, truth: Path | None = None, preview_width: int = 480,
                 viewer: bool = True) -> str:
    """The report's HTML text (``viewer``: with the interactive 3-D view of the model)."""
    from scanpipe.evaluate import evaluate_result, stage_times

    if not workdir.is_dir():
        raise UsageError(f"{workdir}: not a folder (give a workdir or a folder of artifacts)")
    records = all_provenance(workdir)
    if not records:
        raise ArtifactError(f"{workdir}: no scanpipe artifacts found (looked for *.parquet and "
                            "*/*.parquet with provenance)")
    parts = [f"<h1>scanpipe report: {html.escape(workdir.name or str(workdir))}</h1>",
             f'<p class="note">{html.escape(str(workdir))} · scanpipe {__version__}</p>']
    by_stage = {r.get("stage"): r for r in records.values()}
    reports = {stage: (r.get("report") or {}) for stage, r in by_stage.items()}

    # Evaluate first: its headline figures belong at the top, its table after the pictures.
    truth = truth if truth is not None else _found_truth(workdir)
    evaluation: dict[str, Any] | None = None
    evaluation_error = ""
    if truth is not None:
        try:
            evaluation = evaluate_result(workdir, truth)
        except ScanpipeError as err:
            evaluation_error = str(err)

    times = stage_times(workdir)
    parts.append("<h2>At a glance</h2>")
    parts.append(_table(_glance(reports, times, evaluation), ("what", "value")))

    has_mesh = bool(find_artifact(workdir, "mesh_vertices")
                    and find_artifact(workdir, "mesh_faces"))
    if has_mesh and viewer:
        from scanpipe.viewer import report_section

        parts.append("<h2>3-D view</h2>")
        parts.append(report_section(workdir))

    if has_mesh:
        parts.append("<h2>Previews</h2>")
        try:
            parts += _previews(workdir, preview_width)
        except ScanpipeError as err:
            parts.append(f'<p class="note">No previews: {html.escape(str(err))}</p>')

    if truth is not None:
        parts.append("<h2>Evaluation against ground truth</h2>")
        if evaluation is not None:
            rows = [(k, v) for k, v in evaluation.items() if k not in ("result", "stage_seconds")]
            parts.append(_table(rows, ("metric", "value")))
        else:
            parts.append(f'<p class="note">Evaluation failed: {html.escape(evaluation_error)}'
                         "</p>")

    parts.append("<h2>Points</h2>")
    _points_section(workdir, parts)

    profiles_path = find_artifact(workdir, "profiles")
    if profiles_path is not None:
        residuals = sync_residuals(read_artifact(profiles_path)[0])
        parts.append("<h2>Time synchronisation</h2>")
        if residuals is None:
            parts.append('<p class="note">The scanner dialect has no device timestamps.</p>')
        else:
            png, stats = residuals
            parts.append(_figure(png, "Receive-time residuals after a linear clock fit"))
            parts.append(_table(list(stats.items()), ("statistic", "value")))

    if times:
        parts.append("<h2>Stage times</h2>")
        parts.append(_figure(stage_time_chart(times), "Seconds per stage (from provenance)"))

    parts.append("<h2>Details</h2>")
    calibration = reports.get("calibrate", {})
    if calibration.get("enabled"):
        parts.append("<h2>Mount self-calibration</h2>")
        cal_rows: list[tuple[Any, ...]] = [
            (name, p.get("value"), p.get("sigma"), "yes" if p.get("observable") else "no",
             p.get("unit"), p.get("note", ""))
            for name, p in (calibration.get("parameters") or {}).items()]
        cal_rows.append(("plane thickness RMS before → after (m)",
                         calibration.get("residual_before_m"),
                         calibration.get("residual_after_m"), "", "m",
                         f"{calibration.get('planes')} planes"))
        parts.append(_table(cal_rows, ("parameter", "value", "1σ", "observable", "unit",
                                       "note")))
    parts.append("<details><summary>Every stage's report</summary>")
    summary: list[tuple[Any, ...]] = []
    decode = reports.get("decode", {})
    for key in ("dialect", "checksum_mode"):
        if key in decode:
            summary.append((f"decode: {key}", decode[key]))
    for section in ("counts", "counters", "time_span", "gaps"):
        for key, value in (decode.get(section) or {}).items():
            summary.append((f"decode {section}: {key}", value))
    for stage in ("calibrate", "assemble", "filter", "mesh", "texture", "export"):
        for key, value in reports.get(stage, {}).items():
            summary.append((f"{stage}: {key}", value))
    parts.append(_table(summary, ("what", "value")) if summary
                 else '<p class="note">No stage reports.</p>')
    parts.append("</details>")
    parts.append("<details><summary>Artifacts</summary>")
    parts.append(_table([(name, r.get("stage"), r.get("rows"), r.get("seconds"),
                          str(r.get("key", ""))[:12]) for name, r in records.items()],
                        ("artifact", "stage", "rows", "stage seconds", "key")))
    parts.append("</details>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>scanpipe report: {html.escape(workdir.name)}</title>"
            f"<style>{_CSS}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n")


def _glance(reports: dict[Any, dict[str, Any]], times: dict[str, float],
            evaluation: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The headline figures: what was scanned, what came out, how long, how good."""
    rows: list[tuple[str, str]] = []
    decode, assemble = reports.get("decode", {}), reports.get("assemble", {})
    filtered, mesh, texture = (reports.get(s, {}) for s in ("filter", "mesh", "texture"))
    counts = decode.get("counts") or {}
    if counts:
        rows.append(("recording", f"{counts.get('profiles', 0):,} profiles, "
                                  f"{counts.get('samples', 0):,} samples, "
                                  f"{sum((counts.get('images') or {}).values()):,} camera frames"))
    if "grid" in assemble:
        grid = assemble["grid"] or {}
        rows.append(("scan grid", f"{grid.get('profiles')} profiles × {grid.get('samples')} "
                                  f"samples ({assemble.get('mode', '?')} mode)"))
    if "points_out" in filtered:
        rows.append(("points", f"{filtered['points_out']:,} kept of {filtered['points_in']:,}"))
    if "faces" in mesh:
        rows.append(("mesh", f"{mesh['faces']:,} faces, {mesh.get('vertices', 0):,} vertices "
                             f"({mesh.get('method', '?')})"))
    if "coverage" in texture:
        unseen = texture.get("unseen_share")
        rows.append(("textured", f"{100 * texture['coverage']:.0f} % of the surface, "
                                 f"{texture.get('frames_used', '?')} frames used"
                                 + ("" if unseen is None else
                                    f"; {100 * unseen:.1f} % unseen (magenta in the "
                                    "previews)")))
    if times:
        rows.append(("processing", f"{sum(times.values()):.1f} s over {len(times)} stages"))
    if evaluation is not None:
        def mm(key: str) -> str:
            value = evaluation.get(key)
            return "n/a" if value is None else f"{1000 * value:.1f} mm"

        def pct(key: str) -> str:
            value = evaluation.get(key)
            return "n/a" if value is None else f"{100 * value:.1f} %"

        rows.append(("accuracy", f"points RMS {mm('points_rms_m')}, mesh mean "
                                 f"{mm('mesh_mean_m')}; completeness {pct('completeness')}, "
                                 f"precision {pct('precision')} at "
                                 f"{100 * evaluation.get('tau_m', 0.02):.0f} cm"))
        psnr = evaluation.get("texture_psnr_db")
        if psnr is not None:
            visible = evaluation.get("texture_psnr_visible_db")
            rows.append(("texture", f"PSNR {psnr:.1f} dB against the true scene"
                                    + ("" if visible is None else
                                       f", {visible:.1f} dB over all of the visible surface "
                                       "(unseen counted as error)")))
    return rows


def _found_truth(workdir: Path) -> Path | None:
    for candidate in (workdir / "truth", workdir.parent / "truth"):
        if (candidate / "scene.glb").is_file():
            return candidate
    return None


def write_report(workdir: Path, out: Path | None = None, truth: Path | None = None,
                 viewer: bool = True) -> Path:
    """Write the report (default ``WORKDIR/report.html``) atomically; returns its path."""
    path = out if out is not None else workdir / "report.html"
    text = build_report(workdir, truth, viewer=viewer)
    try:
        atomic_write_bytes(path, text.encode("utf-8"))
    except OSError as err:
        raise ExportError(f"{path}: cannot write the report ({err.strerror or err})") from None
    return path
