"""The recording format (version 1): an MCAP file of protobuf messages in zstd chunks.

- :mod:`scanpipe.recording.schemas`: the protobuf messages (descriptors built in code).
- :mod:`scanpipe.recording.writer`: :class:`RecordingWriter`, crash-safe (regular fsync).
- :mod:`scanpipe.recording.reader`: :func:`read_recording`, tolerant of killed writers and damage.

See docs/recording-format.md.
"""
