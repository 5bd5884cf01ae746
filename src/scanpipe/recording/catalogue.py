"""Any MCAP file, not only recordings: what ``scanpipe info`` lists and ``scanpipe recover`` saves.

:func:`catalogue_info` is the plain-data view of :func:`~scanpipe.recording.reader.read_catalogue`
(channels, schemas, message counts, log-time range, like ``mcap info``), and
:func:`recover_mcap` copies every message the tolerant reader can read out of a damaged file
into a new, valid MCAP file (schemas, channels, metadata and attachments included).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from scanpipe.errors import RecordingError
from scanpipe.recording.reader import McapCatalogue, read_catalogue


class RecoveryWriteError(RecordingError):
    """The copy :func:`recover_mcap` writes cannot be written (a full disk, a size limit): the
    damaged file itself may be fine to read. ``reason``: the system's words."""

    def __init__(self, out: Path, err: OSError) -> None:
        self.reason = err.strerror or str(err)
        super().__init__(f"{out}: cannot be written ({self.reason})")


def catalogue_info(catalogue: McapCatalogue) -> dict[str, Any]:
    """The catalogue as plain data (what ``scanpipe info --json`` prints under ``"mcap"``)."""
    firsts = [c.first_ns for c in catalogue.channels.values() if c.first_ns is not None]
    lasts = [c.last_ns for c in catalogue.channels.values() if c.last_ns is not None]
    start_ns, end_ns = (min(firsts), max(lasts)) if firsts else (None, None)
    channels = []
    for channel in sorted(catalogue.channels.values(), key=lambda c: c.id):
        schema = catalogue.schemas.get(channel.schema_id)
        channels.append({
            "id": channel.id, "topic": channel.topic,
            "message_encoding": channel.message_encoding,
            "schema_id": channel.schema_id,
            "schema": schema.name if schema is not None else None,
            "messages": channel.messages,
            "first_ns": channel.first_ns, "last_ns": channel.last_ns,
            "metadata": channel.metadata,
        })
    return {
        "path": str(catalogue.path),
        "profile": catalogue.profile,
        "library": catalogue.library,
        "complete": catalogue.complete,
        "file_size": catalogue.file_size,
        "bytes_read": catalogue.bytes_read,
        "chunks_read": catalogue.chunks_read,
        "chunks_damaged": catalogue.chunks_damaged,
        "loss": catalogue.loss.as_dict(),
        "messages": catalogue.messages,
        "unknown_channel_messages": catalogue.unknown_channel_messages,
        "start_ns": start_ns,
        "end_ns": end_ns,
        "duration_s": (end_ns - start_ns) / 1e9 if start_ns is not None and end_ns is not None
        else 0.0,
        "schemas": [{"id": s.id, "name": s.name, "encoding": s.encoding, "bytes": len(s.data)}
                    for s in sorted(catalogue.schemas.values(), key=lambda s: s.id)],
        "channels": channels,
        "metadata": {name: sorted(values) for name, values in catalogue.metadata.items()},
        "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data)}
                        for a in catalogue.attachments],
        "warnings": list(catalogue.warnings),
    }


def format_catalogue(info: dict[str, Any]) -> str:
    """The catalogue as text for a terminal, in the manner of ``mcap info``."""
    state = "complete" if info["complete"] else "INCOMPLETE (no data end record)"
    lines = [
        f"file        {info['path']} — {state}",
        f"header      profile {info['profile']!r}, library {info['library']!r}",
        f"size        {info['file_size']} bytes, {info['chunks_read']} chunks read"
        + (f", {info['chunks_damaged']} damaged" if info["chunks_damaged"] else ""),
        f"messages    {info['messages']}",
    ]
    if info["start_ns"] is not None:
        lines.append(f"log time    {info['start_ns']} … {info['end_ns']} ns "
                     f"({info['duration_s']:.3f} s)")
    loss = info["loss"]
    if loss["chunks"] or loss["bytes"]:
        bound = "" if loss["exact"] else "at least "
        lines.append(f"lost        {bound}{loss['chunks']} chunks, {loss['bytes']} bytes")
    lines.append("channels:")
    width = max([len(c["topic"]) for c in info["channels"]] + [5])
    lines.append(f"  {'id':>4} {'topic':{width}} {'messages':>9}  {'encoding':10} schema")
    for channel in info["channels"]:
        lines.append(f"  {channel['id']:>4} {channel['topic']:{width}} "
                     f"{channel['messages']:>9}  {channel['message_encoding']:10} "
                     f"{channel['schema'] or '(none)'}")
    lines.append("schemas:")
    for schema in info["schemas"]:
        lines.append(f"  {schema['id']:>4} {schema['name']} ({schema['encoding']}, "
                     f"{schema['bytes']} bytes)")
    if info["metadata"]:
        lines.append("metadata:   " + ", ".join(sorted(info["metadata"])))
    if info["attachments"]:
        lines.append("attachments: " + ", ".join(a["name"] for a in info["attachments"]))
    lines += [f"warning: {w}" for w in info["warnings"]]
    return "\n".join(lines)


def recover_mcap(source: Path, out: Path) -> dict[str, Any]:
    """Copy every message the tolerant reader recovers from ``source`` into a new MCAP file
    ``out`` (written to a temporary name and renamed), with the header, schemas, channels,
    metadata and attachments read. Returns the figures of what was saved and lost.

    The caller checks ``out`` (the outpaths policy). A file with nothing recoverable raises
    :class:`RecordingError` and writes nothing; a copy that cannot be written raises
    :class:`RecoveryWriteError` naming ``out`` (and leaves nothing either).
    """
    catalogue = read_catalogue(source)  # first pass: the channels and schemas to declare
    if not catalogue.messages and not catalogue.metadata and not catalogue.attachments:
        raise RecordingError(f"{source}: no message, metadata or attachment could be read; "
                             "nothing to recover")
    try:
        written = _copy_catalogue(source, out, catalogue)
    except OSError as err:
        raise RecoveryWriteError(out, err) from None
    return {
        "source": str(source), "out": str(out), "messages": written,
        "channels": len(catalogue.channels), "schemas": len(catalogue.schemas),
        "metadata": len(catalogue.metadata), "attachments": len(catalogue.attachments),
        "source_complete": catalogue.complete, "chunks_damaged": catalogue.chunks_damaged,
        "loss": catalogue.loss.as_dict(),
        "unknown_channel_messages": catalogue.unknown_channel_messages,
        "warnings": list(catalogue.warnings),
    }


def _copy_catalogue(source: Path, out: Path, catalogue: McapCatalogue) -> int:
    """Write ``out`` (atomically) from ``catalogue`` and the messages read again from
    ``source``; returns how many messages were written. A failed write is an OSError, or (while
    the messages are read, where the reader takes an OSError for its own) a
    :class:`RecoveryWriteError`."""
    from mcap.writer import CompressionType, Writer

    from scanpipe.artifacts import atomic_path

    written = 0
    with atomic_path(out) as tmp, tmp.open("wb") as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD)
        writer.start(profile=catalogue.profile, library=catalogue.library)
        schema_ids: dict[int, int] = {}
        for schema in catalogue.schemas.values():
            schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                           schema.data)
        channel_ids: dict[int, int] = {}
        for channel in catalogue.channels.values():
            channel_ids[channel.id] = writer.register_channel(
                channel.topic, channel.message_encoding,
                schema_ids.get(channel.schema_id, 0), channel.metadata)

        def copy(channel_id: int, sequence: int, log_time_ns: int, publish_time_ns: int,
                 data: bytes) -> None:
            nonlocal written
            try:
                writer.add_message(channel_ids[channel_id], log_time_ns, data,
                                   publish_time_ns, sequence)
            except OSError as err:  # not the source's: the reader would say it cannot be read
                raise RecoveryWriteError(out, err) from None
            written += 1

        read_catalogue(source, on_message=copy)
        for name, values in catalogue.metadata.items():
            writer.add_metadata(name, values)
        for attachment in catalogue.attachments:
            writer.add_attachment(attachment.create_time_ns, attachment.log_time_ns,
                                  attachment.name, attachment.media_type, attachment.data)
        writer.finish()  # type: ignore[no-untyped-call]
    return written
