"""``scanpipe import-capture``: a network capture (pcap, pcapng) of the scanner's TCP link into a
recording."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from scanpipe.cli.common import JSON, RIG, print_json


def import_capture(
    capture: Path = typer.Argument(..., help="The capture (.pcap or .pcapng, e.g. Wireshark's)."),
    out: Path = typer.Option(..., "--out", "-o", help="The recording to write (.mcap)."),
    rig_path: Path | None = RIG,
    port: int | None = typer.Option(None, "--port",
                                    help="The scanner's TCP port (default: the stream whose "
                                         "bytes decode as a known dialect)."),
    stream: str | None = typer.Option(None, "--stream",
                                      help="The scanner's end of the stream, HOST:PORT "
                                           "([V6HOST]:PORT)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing recording."),
    as_json: bool = JSON,
) -> None:
    """Put the scanner's TCP stream of a network capture into a recording (scanner channel,
    both directions, capture times); then `scanpipe frames` or `scanpipe decode` read it."""
    from scanpipe.captureio import load_scanner_capture, parse_endpoint, write_capture_recording
    from scanpipe.outpaths import check_input_file, check_output_file
    from scanpipe.rig import load_rig

    check_input_file(capture, "CAPTURE")
    inputs = [capture, *([rig_path] if rig_path else [])]
    check_output_file(out, "--out", (".mcap",), force, inputs)
    rig = load_rig(rig_path)
    endpoint = parse_endpoint(stream) if stream is not None else None
    scan = load_scanner_capture(capture, port, endpoint)
    warnings = list(scan.warnings)
    if scan.dialect is None:
        warnings.append(f"{capture}: the bytes from {scan.summary()['scanner']} hold no frame "
                        "of a known dialect; written as they are")
    if rig_path is None:
        if scan.dialect is not None and scan.dialect != rig.scanner.dialect:
            rig = rig.model_copy(update={"scanner": rig.scanner.model_copy(
                update={"dialect": scan.dialect})})
        warnings.append("no --rig: the default rig is stored; a capture has no motor states, so "
                        "only `frames` and `decode` are meaningful (assemble needs a recording "
                        "with the motor's states)")
    elif scan.dialect is not None and scan.dialect != rig.scanner.dialect:
        warnings.append(f"{rig_path}: the rig's scanner dialect is {rig.scanner.dialect!r}, the "
                        f"capture's frames are {scan.dialect!r}; decode with --set "
                        f"decode.dialect={scan.dialect} or fix the rig")
    summary = scan.summary()
    summary["warnings"] = warnings
    session: dict[str, object] = {"source": "import-capture", "capture": str(capture),
                                  "capture_summary": summary}
    write_capture_recording(scan, out, rig, session)
    for warning in warnings:
        sys.stderr.write(f"warning: import-capture: {warning}\n")
    if as_json:
        print_json({"out": str(out), **summary})
        return
    rx, tx = scan.received, scan.sent
    gaps = len(rx.gaps) + len(tx.gaps)
    typer.echo(f"{out}: scanner {summary['scanner']} ({scan.dialect or 'unknown dialect'}) ↔ "
               f"host {summary['host']}: {rx.byte_count:,} bytes received in {len(rx.chunks)} "
               f"chunks, {tx.byte_count:,} sent; {gaps} gaps "
               f"({sum(g.missing_bytes for g in rx.gaps + tx.gaps):,} bytes missing), "
               f"{rx.retransmitted_bytes + tx.retransmitted_bytes:,} bytes retransmitted, "
               f"{rx.out_of_order_segments + tx.out_of_order_segments} segments out of order")


def register(app: typer.Typer) -> None:
    """Add ``import-capture`` to the main app."""
    app.command("import-capture")(import_capture)
