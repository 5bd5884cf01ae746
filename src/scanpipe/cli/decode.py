"""``scanpipe frames`` (decode a raw byte capture) and ``scanpipe decode`` (the decode stage)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import typer

from scanpipe.cli.common import JSON, PARAMS_FILE, QUIET, SET, print_json, run_stage_command
from scanpipe.errors import ProtocolError, UsageError
from scanpipe.protocol.registry import (
    DIALECTS,
    DecodedFrame,
    Dialect,
    StreamDecoder,
    describe_bytes,
    resolve_dialect,
)


def _floats(values: Any) -> list[float | None]:
    return [None if math.isnan(v) else v for v in values.tolist()]


def frame_records(frames: list[DecodedFrame]) -> list[dict[str, Any]]:
    """One JSON-ready record per profile sector (NaN ranges as null)."""
    records = []
    for frame in frames:
        for p in frame.profiles:
            records.append({
                "frame": p.frame, "sector": p.sector,
                "start_angle_deg": p.start_angle_deg, "step_deg": p.step_deg,
                "samples": len(p.ranges_m), "ranges_m": _floats(p.ranges_m),
                "echo": None if p.echo is None else p.echo.tolist(),
                "device_time_ms": p.device_time_ms, "device_end_time_ms": p.device_end_time_ms,
                "device_tick_ns": p.device_tick_ns,
                "checksum_ok": p.checksum_ok,
                "received_checksum": frame.received_checksum,
                "computed_checksum": frame.computed_checksum,
                "offset": frame.start_offset,
            })
    return records


def _format_frame(r: dict[str, Any]) -> str:
    check = ("ok" if r["checksum_ok"] else
             f"MISMATCH (received {r['received_checksum']:#04x}, computed "
             f"{r['computed_checksum']:#04x})")
    ranges = ", ".join("-" if v is None else f"{v:g}" for v in r["ranges_m"][:8])
    more = " …" if r["samples"] > 8 else ""
    unit = {1_000_000: "ms", 1000: "µs"}.get(r.get("device_tick_ns", 1_000_000),
                                             f"× {r.get('device_tick_ns')} ns")
    time = "" if r["device_time_ms"] is None else f"  t {r['device_time_ms']} {unit}"
    return (f"@{r['offset']:<8d} frame {r['frame']:<6d} sector {r['sector']}  start "
            f"{r['start_angle_deg']:g}°  step {r['step_deg']:g}°  {r['samples']} samples"
            f"{time}  checksum {check}\n    ranges_m: {ranges}{more}")


def _request_records(data: bytes, dialect: Dialect) -> tuple[list[dict[str, Any]], dict[str, int]]:
    """The frames the host sent (requests), each with its offset and payload, and the counters."""
    reader = dialect.frame_reader()
    raw = reader.feed(data) + reader.finish()
    records = [{"offset": r.start_offset, "checksum_ok": r.checksum_ok,
                "payload_hex": r.payload.hex(" ")} for r in raw]
    return records, reader.counters.as_dict()


def _no_frame(source: str, dialect: Dialect, data: bytes, counters: dict[str, int]) -> str:
    failed = counters.get("checksum_failures", 0)
    hint = (f" ({failed} frames failed the checksum: --checksum lenient shows them)"
            if failed else f"; {describe_bytes(data)}")
    return (f"{source}: --dialect {dialect.name}: no {dialect.name} frame in its "
            f"{len(data)} bytes{hint}; try --dialect auto")


def frames(
    capture: Path = typer.Argument(..., help="A raw byte capture of a scanner stream, or a "
                                             "network capture (.pcap, .pcapng) of its TCP link."),
    dialect: str = typer.Option("auto", "--dialect",
                                help="paper, ldoem, cola_b, cola_a, ldrobot, ldrobot_ld14, scip "
                                     "or auto."),
    checksum: str = typer.Option("lenient", "--checksum",
                                 help="lenient shows damaged frames marked; strict drops them."),
    port: int | None = typer.Option(None, "--port",
                                    help="Network capture: the scanner's TCP port."),
    stream: str | None = typer.Option(None, "--stream",
                                      help="Network capture: the scanner's end, HOST:PORT."),
    as_json: bool = JSON,
) -> None:
    """Decode a raw byte capture and print each frame and the decoder's counters.

    A network capture (pcap, pcapng) is read as its scanner TCP stream, reassembled: the replies
    (scanner → host) are decoded as profiles, the requests (host → scanner) listed."""
    from scanpipe.captureio import is_capture, load_scanner_capture, parse_endpoint

    if checksum not in ("strict", "lenient"):
        raise UsageError(f"--checksum {checksum!r}: allowed strict, lenient")
    if dialect != "auto" and dialect not in DIALECTS:
        raise UsageError(f"--dialect {dialect!r}: allowed {', '.join(DIALECTS)}, auto")
    try:
        data = capture.read_bytes()
    except OSError as err:
        raise UsageError(f"{capture}: cannot be read ({err.strerror or err})") from None
    scan = None
    if is_capture(data[:4]):
        scan = load_scanner_capture(capture, port, None if stream is None
                                    else parse_endpoint(stream))
        data = scan.received.data
        source = f"{capture} (scanner {scan.summary()['scanner']})"
    elif port is not None or stream is not None:
        raise UsageError(f"--port/--stream: {capture} is not a network capture (pcap, pcapng); "
                         "they choose a TCP stream of one")
    else:
        source = str(capture)
    try:
        chosen = resolve_dialect(dialect, data)
    except ProtocolError as err:
        raise ProtocolError(f"{source}: {err}") from None
    decoder = StreamDecoder(chosen, "strict" if checksum == "strict" else "lenient")
    decoded = decoder.feed_frames(data) + decoder.finish_frames()
    records = frame_records(decoded)
    counters = decoder.counters.as_dict()
    if dialect != "auto" and data and counters["frames_decoded"] == 0:
        raise ProtocolError(_no_frame(source, chosen, data, counters))
    requests: list[dict[str, Any]] = []
    request_counters: dict[str, int] = {}
    if scan is not None:
        requests, request_counters = _request_records(scan.sent.data, chosen)
        for warning in scan.warnings:
            sys.stderr.write(f"warning: frames: {warning}\n")
    if as_json:
        result: dict[str, Any] = {"dialect": chosen.name, "frames": records, "counters": counters}
        if scan is not None:
            result.update(capture=scan.summary(), requests=requests,
                          request_counters=request_counters)
        print_json(result)
        return
    if scan is None:
        typer.echo(f"{capture}: {len(data)} bytes, dialect {chosen.name}")
    else:
        rx, tx = scan.received, scan.sent
        typer.echo(f"{capture}: {scan.kind} capture, stream {scan.stream.describe()}; scanner "
                   f"{scan.summary()['scanner']}: {rx.byte_count} bytes received, "
                   f"{tx.byte_count} sent, {len(rx.gaps) + len(tx.gaps)} gaps; dialect "
                   f"{chosen.name}")
        typer.echo("replies (scanner → host):")
    for record in records:
        typer.echo(_format_frame(record))
    typer.echo("counters: " + ", ".join(f"{k} {v}" for k, v in counters.items()))
    if scan is not None:
        typer.echo(f"requests (host → scanner): {len(requests)} frames")
        for req in requests:
            check = "" if req["checksum_ok"] else "  checksum MISMATCH"
            typer.echo(f"@{req['offset']:<8d} payload {req['payload_hex'][:48]}"
                       f"{' …' if len(req['payload_hex']) > 48 else ''}{check}")


def format_report(report: dict[str, Any]) -> str:
    """The decode report as text for a terminal."""
    counts, counters = report["counts"], report["counters"]
    span, rates, gaps = report["time_span"], report["rates"], report["gaps"]
    rec = report["recording"]
    lines = [
        f"dialect             {report['dialect']}"
        f"{' (detected)' if report['dialect_detected'] else ''}, checksum "
        f"{report['checksum_mode']}",
        f"profiles            {counts['profiles']} ({counts['frames']} frames, "
        f"{counts['samples']:,} samples)",
        f"motor states        {counts['motor_states']}",
        "camera frames       " + (", ".join(f"{k} {v}" for k, v in counts["images"].items())
                                   or "none"),
        f"events              {counts['events']}",
        f"time span           {span['duration_s']:.3f} s",
        f"rates               {rates['profiles_per_s']} profiles/s, "
        f"{rates['scanner_bytes_per_s']} B/s",
        f"gaps                {gaps['count']} (max interval {gaps['max_interval_s']} s, "
        f"{gaps['missing_stream_chunks']} stream chunks missing)",
        f"checksum failures   {counters['checksum_failures']} "
        f"({counts['checksum_failed_rows']} kept)",
        f"resyncs             {counters['resyncs']}, bytes skipped {counters['bytes_skipped']}, "
        f"malformed {counters['malformed_frames']}, other frames {counters['other_frames']}",
        f"rejected frames     {counters['length_mismatches']} length mismatches, "
        f"{counters['implausible_frames']} implausible (checksum passed)",
        f"recording           {'complete' if rec['complete'] else 'INCOMPLETE'}, "
        f"{rec['bytes_read']} of {rec['file_size']} bytes, {rec['chunks_read']} chunks "
        f"({rec['chunks_damaged']} damaged)",
    ]
    return "\n".join(lines)  # the warnings go to stderr (run_stage_command)


def decode(
    recording: Path = typer.Argument(..., help="The recording (MCAP)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the artifacts."),
    assignments: list[str] | None = SET,
    params_file: Path | None = PARAMS_FILE,
    quiet: bool = QUIET,
    as_json: bool = JSON,
) -> None:
    """Decode a recording into profiles, motor, frames and rig artifacts, and print the report."""
    report = run_stage_command("decode", {"recording": recording}, out, params_file,
                               assignments, quiet)
    if as_json:
        print_json(report)
    else:
        typer.echo(format_report(report))


def register(app: typer.Typer) -> None:
    """Add ``frames`` and ``decode`` to the main app."""
    app.command("frames")(frames)
    app.command("decode")(decode)
