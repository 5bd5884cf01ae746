"""The protobuf messages of the recording format, built from descriptors in code.

No protoc is needed at run time: the file descriptors below are the code form of
``schemas/scanpipe/recording.proto`` and ``schemas/foxglove/CompressedImage.proto`` (a test
renders them with :func:`proto_source` and compares with the files); :mod:`scanpipe.protobuf`
builds them, in a private descriptor pool.

Message classes: :data:`ByteChunk`, :data:`MotorState`, :data:`Event`, :data:`Profile` (an
already-decoded profile, e.g. imported from a ROS bag), :data:`CompressedImage`.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2

from scanpipe.protobuf import (
    MessageSpec,
    build_pool,
    file_descriptor_set,
    file_proto,
    message_class,
    proto_source,
)

__all__ = [
    "POOL",
    "RX",
    "TX",
    "ByteChunk",
    "CompressedImage",
    "Event",
    "MotorState",
    "Profile",
    "file_descriptor_set",
    "foxglove_file",
    "proto_source",
    "scanpipe_file",
]

#: Direction of a byte chunk, as in ``scanpipe.Direction``.
RX = 0
TX = 1

# (message name, [(field type, field name, number, repeated)], nested enums) in declaration order.
_SCANPIPE_MESSAGES: list[MessageSpec] = [
    ("ByteChunk", [("uint64", "seq", 1, False), ("bytes", "data", 2, False),
                   (".scanpipe.Direction", "direction", 3, False)], {}),
    ("MotorState", [("int64", "step_count", 1, False), ("int64", "target_step_count", 2, False),
                    ("bool", "moving", 3, False), ("uint64", "device_time_us", 4, False)], {}),
    ("Event", [("string", "kind", 1, False), ("string", "message", 2, False),
               ("string", "data_json", 3, False)], {}),
    ("Profile", [("uint64", "device_time_ns", 1, False), ("uint64", "device_end_time_ns", 2, False),
                 ("uint64", "frame", 3, False), ("double", "start_angle_deg", 4, False),
                 ("double", "step_deg", 5, False), ("float", "ranges_m", 6, True),
                 ("float", "intensities", 7, True)], {}),
]
_FOXGLOVE_MESSAGES: list[MessageSpec] = [
    ("CompressedImage", [(".google.protobuf.Timestamp", "timestamp", 1, False),
                         ("string", "frame_id", 4, False), ("bytes", "data", 2, False),
                         ("string", "format", 3, False)], {}),
]


def scanpipe_file() -> descriptor_pb2.FileDescriptorProto:
    """``scanpipe/recording.proto``: Direction, ByteChunk, MotorState, Event, Profile."""
    return file_proto("scanpipe/recording.proto", "scanpipe", _SCANPIPE_MESSAGES,
                      {"Direction": [("RX", RX), ("TX", TX)]})


def foxglove_file() -> descriptor_pb2.FileDescriptorProto:
    """``foxglove/CompressedImage.proto``: the published Foxglove schema."""
    return file_proto("foxglove/CompressedImage.proto", "foxglove", _FOXGLOVE_MESSAGES)


POOL = build_pool([scanpipe_file(), foxglove_file()])

ByteChunk: Any = message_class(POOL, "scanpipe.ByteChunk")
MotorState: Any = message_class(POOL, "scanpipe.MotorState")
Event: Any = message_class(POOL, "scanpipe.Event")
Profile: Any = message_class(POOL, "scanpipe.Profile")
CompressedImage: Any = message_class(POOL, "foxglove.CompressedImage")
