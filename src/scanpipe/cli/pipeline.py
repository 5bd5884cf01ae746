"""``scanpipe run``, ``show`` and ``stages``: the cached chain and what it knows about itself."""

from __future__ import annotations

import datetime as dt
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import pyarrow.parquet as pq
import typer
from pydantic import BaseModel

from scanpipe.artifacts import read_provenance
from scanpipe.cli.common import (
    JSON,
    PARAMS_FILE,
    QUIET,
    SET,
    print_json,
    print_warnings,
)
from scanpipe.errors import ArtifactError
from scanpipe.follow import DEFAULT_FOLLOW_TIMEOUT_S, FollowResult, FollowStatus, follow_chain
from scanpipe.params import apply_assignments, load_toml
from scanpipe.pipeline import RunRecord, Stage, registry, run_chain, validate_pipeline_params
from scanpipe.progress import rich_progress
from scanpipe.stages import chain_stages
from scanpipe.workdir import DEFAULT_LOCK_WAIT_S

#: The options of the cached chain that ``run`` and ``batch`` share (one definition each).
TO = typer.Option(None, "--to", help="Stop after this stage.")
RECOMPUTE = typer.Option(False, "--force", help="Recompute every stage.")
WAIT = typer.Option(DEFAULT_LOCK_WAIT_S, "--wait", min=0.0,
                    help="Seconds to wait while another scanpipe writes into a workdir (0: give "
                         "up at once; in a batch, that recording fails and the others go on).")


def pipeline_params_from_cli(params_file: Path | None, assignments: list[str] | None
                             ) -> dict[str, Any]:
    """Per-stage parameters from ``--params FILE`` then ``--set stage.key=value``, validated."""
    data: dict[str, Any] = load_toml(params_file) if params_file else {}
    data = apply_assignments(data, assignments or [])
    return validate_pipeline_params(chain_stages(), data,
                                    str(params_file) if params_file else "--set")


def _print_record(record: RunRecord, quiet: bool) -> None:
    if not quiet:
        state = "reused" if record.reused else f"ran in {record.seconds:.2f} s"
        sys.stderr.write(f"  {record.stage:<10} {state:<16} key {record.key[:12]}\n")
    if not record.reused:  # a reused stage's warnings were shown when it ran
        print_warnings(record.stage, record.report)


def run(
    recording: Path = typer.Argument(..., help="The recording (MCAP)."),
    workdir: Path = typer.Option(..., "--workdir", "-w", help="Folder for every stage's output."),
    to: str | None = TO,
    force: bool = RECOMPUTE,
    rig: Path | None = typer.Option(None, "--rig", help="Rig TOML overriding the recording's."),
    wait_s: float = WAIT,
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
    follow: bool = typer.Option(
        False, "--follow", help="Process the recording while it is being written (record, "
                                "simulate): the model is ready seconds after the scan ends, "
                                "equal to a run on the finished file."),
    follow_timeout_s: float = typer.Option(
        DEFAULT_FOLLOW_TIMEOUT_S, "--follow-timeout", min=0.1,
        help="With --follow: seconds to wait for the recording to appear, and without growth "
             "before a recording that never ends (a killed recorder) is processed as it is."),
) -> None:
    """Run the chain decode → … → export, reusing every artifact whose key is unchanged."""
    params = pipeline_params_from_cli(params_file, assignments)
    if not quiet:
        sys.stderr.write(f"scanpipe run {recording} → {workdir}"
                         + (" (following the recording)" if follow else "") + "\n")
    followed: FollowResult | None = None
    with rich_progress(quiet) as progress:
        if follow:
            followed = follow_chain(recording, workdir, params, to=to, force=force,
                                    rig_override=rig, progress=progress,
                                    on_stage=lambda record: _print_record(record, quiet),
                                    on_status=_status_printer(quiet), lock_wait_s=wait_s,
                                    timeout_s=follow_timeout_s)
            records = followed.records
            print_warnings("follow", {"warnings": followed.warnings})
        else:
            records = run_chain(recording, workdir, params, to=to, force=force,
                                rig_override=rig, progress=progress,
                                on_stage=lambda record: _print_record(record, quiet),
                                lock_wait_s=wait_s)
    ran = sum(not r.reused for r in records)
    total = sum(r.seconds for r in records)
    if not quiet:
        sys.stderr.write(f"{ran} ran, {len(records) - ran} reused, {total:.2f} s\n")
        if followed is not None and followed.model_latency_s is not None:
            sys.stderr.write(f"follow: the model was ready {followed.model_latency_s:.2f} s "
                             f"after the last profile; decode {followed.decode}; taken from "
                             "the scan's end: "
                             f"{', '.join(followed.reused_from_scan_end) or 'nothing'}\n")
    if as_json:
        info: dict[str, Any] = {
            "recording": str(recording), "workdir": str(workdir), "ran": ran,
            "reused": len(records) - ran, "seconds": total,
            "stages": [{"stage": r.stage, "key": r.key, "reused": r.reused,
                        "seconds": r.seconds,
                        "outputs": {k: str(v) for k, v in r.outputs.items()},
                        "report": r.report} for r in records]}
        if followed is not None:
            info["follow"] = {
                "complete": followed.complete, "decode": followed.decode,
                "last_profile_ns": followed.last_profile_ns,
                "end_seen_ns": followed.end_seen_ns,
                "scan_end_seen_ns": followed.scan_end_seen_ns,
                "reused_from_scan_end": followed.reused_from_scan_end,
                "changed_after_scan_end": followed.changed_after_scan_end,
                "model_ready_ns": followed.model_ready_ns,
                "model_latency_s": followed.model_latency_s,
                "warnings": followed.warnings, "preview": followed.preview,
                "visible_lag_s": _spread(followed.visible_lag_s)}
        print_json(info)


def _spread(values: list[float]) -> dict[str, float | int | None]:
    """Count, median and maximum of some seconds."""
    ordered = sorted(values)
    return {"count": len(ordered),
            "median": ordered[len(ordered) // 2] if ordered else None,
            "max": ordered[-1] if ordered else None}


def _status_printer(quiet: bool) -> Callable[[FollowStatus], None]:
    """One line on stderr per tenth of the platform range covered (or per 10 s without a plan)."""
    shown = {"step": -1}

    def show(status: FollowStatus) -> None:
        if quiet or not status.profiles:
            return
        step = (int(status.coverage * 10) if status.coverage is not None
                else int(status.elapsed_s // 10))
        if step <= shown["step"]:
            return
        shown["step"] = step
        share = f"{status.coverage:.0%} of the platform range, " if status.coverage else ""
        lag = f", {status.lag_s:.1f} s behind" if status.lag_s is not None else ""
        sys.stderr.write(f"  follow     {share}{status.profiles} profiles, "
                         f"{status.positions} positions, {status.points} points, "
                         f"{status.faces} faces{lag}\n")

    return show


def show(
    artifact: Path = typer.Argument(..., help="An artifact (.parquet)."),
    as_json: bool = JSON,
) -> None:
    """Print an artifact's provenance: stage, parameters, inputs, versions, times, report."""
    provenance = read_provenance(artifact)
    if not provenance:
        raise ArtifactError(f"{artifact}: a Parquet file without scanpipe provenance")
    metadata = pq.read_metadata(artifact)
    schema = pq.read_schema(artifact)
    info = {
        **provenance,
        "rows": metadata.num_rows,
        "columns": {f.name: str(f.type) for f in schema},
    }
    if as_json:
        print_json(info)
        return
    created = provenance.get("created_ns")
    when = dt.datetime.fromtimestamp(created / 1e9, dt.UTC).isoformat() if created else "?"
    lines = [
        f"{artifact}",
        f"  artifact   {provenance.get('artifact', '?')} ({metadata.num_rows} rows)",
        f"  stage      {provenance.get('stage')} v{provenance.get('stage_version', '?')}",
        f"  key        {provenance.get('key')}",
        f"  created    {when} in {provenance.get('seconds', '?')} s",
        "  inputs",
        *[f"    {k}: {v}" for k, v in provenance.get("inputs", {}).items()],
        "  parameters",
        *[f"    {k} = {v}" for k, v in _flatten(provenance.get("params", {})).items()],
        "  libraries  " + ", ".join(f"{k} {v}" for k, v in provenance.get("libraries", {}).items()),
        "  columns    " + ", ".join(f"{k}: {v}" for k, v in info["columns"].items()),
        "  report",
        *[f"    {k} = {v}" for k, v in _flatten(provenance.get("report", {})).items()],
    ]
    typer.echo("\n".join(lines))


def _flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        return {prefix: data}
    flat: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        flat.update(_flatten(value, name) if isinstance(value, dict) else {name: value})
    return flat


def describe_params(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str, str, str]]:
    """``(key, type, default, meaning)`` for every leaf parameter of a model."""
    rows: list[tuple[str, str, str, str]] = []
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            rows.extend(describe_params(annotation, f"{key}."))
            continue
        rows.append((key, _type_name(annotation), repr(field.default), field.description or ""))
    return rows


def _type_name(annotation: Any) -> str:
    """``a|b|c`` for a Literal, the bare name for a class, else the typing text."""
    if get_origin(annotation) is Literal:
        return "|".join(str(a) for a in get_args(annotation))
    if get_origin(annotation) is tuple:
        items = [a for a in get_args(annotation) if a is not Ellipsis]
        return "list of " + ", ".join(_type_name(a) for a in items)
    name = getattr(annotation, "__name__", None)
    return str(name) if name and get_origin(annotation) is None else str(annotation).replace(
        "typing.", "")


def stages(as_json: bool = JSON) -> None:
    """List the stages with their inputs, outputs and parameters (defaults, meaning)."""
    catalogue: list[Stage] = list(registry().values())
    if as_json:
        print_json([
            {"name": s.name, "version": s.version, "description": s.description,
             "inputs": list(s.inputs), "outputs": list(s.outputs),
             "params": [dict(zip(("key", "type", "default", "meaning"), row, strict=True))
                        for row in describe_params(s.params)]}
            for s in catalogue
        ])
        return
    for s in catalogue:
        typer.echo(f"{s.name} (v{s.version}): {s.description}")
        typer.echo(f"  {', '.join(s.inputs)} → {', '.join(s.outputs)}")
        for key, type_name, default, meaning in describe_params(s.params):
            tail = f"  {meaning}" if meaning else ""
            typer.echo(f"    {s.name}.{key}: {type_name} = {default}{tail}")


def register(app: typer.Typer) -> None:
    """Add ``run``, ``show`` and ``stages`` to the main app."""
    app.command("run")(run)
    app.command("show")(show)
    app.command("stages")(stages)
