"""The protobuf messages of the recording format, built from descriptors in code.

No protoc is needed at run time: the file descriptors below are the code form of
``schemas/scanpipe/recording.proto`` and ``schemas/foxglove/CompressedImage.proto`` (a test
renders them with :func:`proto_source` and compares with the files). They live in a private
descriptor pool, so another package registering ``foxglove.CompressedImage`` cannot clash.

Message classes: :data:`ByteChunk`, :data:`MotorState`, :data:`Event`, :data:`CompressedImage`.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory, timestamp_pb2

FieldProto = descriptor_pb2.FieldDescriptorProto

#: Direction of a byte chunk, as in ``scanpipe.Direction``.
RX = 0
TX = 1

_SCALARS = {
    "uint64": FieldProto.TYPE_UINT64,
    "int64": FieldProto.TYPE_INT64,
    "bool": FieldProto.TYPE_BOOL,
    "bytes": FieldProto.TYPE_BYTES,
    "string": FieldProto.TYPE_STRING,
}

# (message name, [(field type, field name, number)]) in declaration order.
_SCANPIPE_MESSAGES: list[tuple[str, list[tuple[str, str, int]]]] = [
    ("ByteChunk", [("uint64", "seq", 1), ("bytes", "data", 2), (".scanpipe.Direction",
                                                               "direction", 3)]),
    ("MotorState", [("int64", "step_count", 1), ("int64", "target_step_count", 2),
                    ("bool", "moving", 3), ("uint64", "device_time_us", 4)]),
    ("Event", [("string", "kind", 1), ("string", "message", 2), ("string", "data_json", 3)]),
]
_FOXGLOVE_MESSAGES: list[tuple[str, list[tuple[str, str, int]]]] = [
    ("CompressedImage", [(".google.protobuf.Timestamp", "timestamp", 1),
                         ("string", "frame_id", 4), ("bytes", "data", 2),
                         ("string", "format", 3)]),
]


def _message(name: str, fields: list[tuple[str, str, int]]) -> descriptor_pb2.DescriptorProto:
    message = descriptor_pb2.DescriptorProto(name=name)
    for type_name, field_name, number in fields:
        field = message.field.add(name=field_name, number=number,
                                  label=FieldProto.LABEL_OPTIONAL, json_name=_camel(field_name))
        if type_name in _SCALARS:
            field.type = _SCALARS[type_name]
        elif type_name.endswith("Direction"):
            field.type = FieldProto.TYPE_ENUM
            field.type_name = type_name
        else:
            field.type = FieldProto.TYPE_MESSAGE
            field.type_name = type_name
    return message


def _camel(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part.title() for part in rest)


def scanpipe_file() -> descriptor_pb2.FileDescriptorProto:
    """``scanpipe/recording.proto``: Direction, ByteChunk, MotorState, Event."""
    proto = descriptor_pb2.FileDescriptorProto(name="scanpipe/recording.proto",
                                               package="scanpipe", syntax="proto3")
    direction = proto.enum_type.add(name="Direction")
    direction.value.add(name="RX", number=RX)
    direction.value.add(name="TX", number=TX)
    proto.message_type.extend(_message(n, f) for n, f in _SCANPIPE_MESSAGES)
    return proto


def foxglove_file() -> descriptor_pb2.FileDescriptorProto:
    """``foxglove/CompressedImage.proto``: the published Foxglove schema."""
    proto = descriptor_pb2.FileDescriptorProto(name="foxglove/CompressedImage.proto",
                                               package="foxglove", syntax="proto3")
    proto.dependency.append("google/protobuf/timestamp.proto")
    proto.message_type.extend(_message(n, f) for n, f in _FOXGLOVE_MESSAGES)
    return proto


def _build_pool() -> descriptor_pool.DescriptorPool:
    pool = descriptor_pool.DescriptorPool()
    timestamp = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.DESCRIPTOR.CopyToProto(timestamp)
    for proto in (timestamp, scanpipe_file(), foxglove_file()):
        pool.Add(proto)
    return pool


POOL = _build_pool()


def _class(full_name: str) -> Any:
    return message_factory.GetMessageClass(POOL.FindMessageTypeByName(full_name))


ByteChunk: Any = _class("scanpipe.ByteChunk")
MotorState: Any = _class("scanpipe.MotorState")
Event: Any = _class("scanpipe.Event")
CompressedImage: Any = _class("foxglove.CompressedImage")


def file_descriptor_set(message_class: Any) -> bytes:
    """The serialized FileDescriptorSet of a message class and its dependencies: the MCAP
    schema data of the ``protobuf`` encoding."""
    file_set = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(file_descriptor: Any) -> None:
        for dependency in file_descriptor.dependencies:
            if dependency.name not in seen:
                seen.add(dependency.name)
                add(dependency)
        file_descriptor.CopyToProto(file_set.file.add())

    add(message_class.DESCRIPTOR.file)
    return file_set.SerializeToString()  # type: ignore[no-any-return]


def proto_source(proto: descriptor_pb2.FileDescriptorProto) -> str:
    """The ``.proto`` text of a file descriptor (declarations only, no comments)."""
    names = {v: k for k, v in _SCALARS.items()}
    lines = [f'syntax = "{proto.syntax}";', f"package {proto.package};"]
    lines += [f'import "{d}";' for d in proto.dependency]
    for enum in proto.enum_type:
        lines.append(f"enum {enum.name} {{")
        lines += [f"  {v.name} = {v.number};" for v in enum.value]
        lines.append("}")
    for message in proto.message_type:
        lines.append(f"message {message.name} {{")
        for field in message.field:
            type_name = names.get(field.type) or field.type_name.rsplit(".", 1)[-1]
            if field.type_name.startswith(".google."):
                type_name = field.type_name.lstrip(".")
            lines.append(f"  {type_name} {field.name} = {field.number};")
        lines.append("}")
    return "\n".join(lines) + "\n"
