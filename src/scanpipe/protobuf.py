"""Protobuf message classes from file descriptors written in code: no protoc at run time.

The builder behind the recording format (:mod:`scanpipe.recording.schemas`); the Foxglove
exports use the official ``foxglove-schemas-protobuf`` classes. A message is a name,
its fields ``(type, name, number, repeated)`` in declaration order and its nested enums; a field
type is a scalar name (``"uint64"``) or a full name (``".foxglove.Pose"``). Each module keeps its
classes in a private descriptor pool, so another package registering the same names (say
``foxglove.CompressedImage``) cannot clash.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from google.protobuf import (
    descriptor_pb2,
    descriptor_pool,
    duration_pb2,
    message_factory,
    timestamp_pb2,
)

FieldProto = descriptor_pb2.FieldDescriptorProto
#: ``(type, name, number, repeated)``.
FieldSpec = tuple[str, str, int, bool]
#: Enum name → its values ``(name, number)``.
EnumSpecs = Mapping[str, Sequence[tuple[str, int]]]
#: ``(message name, fields, nested enums)``.
MessageSpec = tuple[str, Sequence[FieldSpec], EnumSpecs]

SCALARS = {
    "double": FieldProto.TYPE_DOUBLE,
    "float": FieldProto.TYPE_FLOAT,
    "fixed32": FieldProto.TYPE_FIXED32,
    "uint64": FieldProto.TYPE_UINT64,
    "int64": FieldProto.TYPE_INT64,
    "bool": FieldProto.TYPE_BOOL,
    "bytes": FieldProto.TYPE_BYTES,
    "string": FieldProto.TYPE_STRING,
}
#: The well-known types a schema may use, by full name, with their modules.
WELL_KNOWN = {".google.protobuf.Timestamp": timestamp_pb2,
              ".google.protobuf.Duration": duration_pb2}


def _camel(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part.title() for part in rest)


def _add_enums(parent: Any, enums: EnumSpecs) -> None:
    for enum_name, values in enums.items():
        enum = parent.enum_type.add(name=enum_name)
        for value_name, number in values:
            enum.value.add(name=value_name, number=number)


def file_proto(name: str, package: str, messages: Sequence[MessageSpec],
               enums: EnumSpecs | None = None) -> descriptor_pb2.FileDescriptorProto:
    """A proto3 file descriptor: top-level ``enums``, then ``messages``.

    Its imports follow from the field types: a well-known type imports its Google file, a
    message of the package not declared here imports ``<package>/<Message>.proto`` (the
    one-message-per-file layout of the Foxglove schemas).
    """
    proto = descriptor_pb2.FileDescriptorProto(name=name, package=package, syntax="proto3")
    _add_enums(proto, enums or {})
    local_enums = {f".{package}.{e}" for e in enums or {}}
    local_enums |= {f".{package}.{m}.{e}" for m, _, nested in messages for e in nested}
    local = local_enums | {f".{package}.{m}" for m, _, _ in messages}
    imports: list[str] = []
    for message_name, fields, nested in messages:
        message = proto.message_type.add(name=message_name)
        _add_enums(message, nested)
        for type_name, field_name, number, repeated in fields:
            field = message.field.add(
                name=field_name, number=number, json_name=_camel(field_name),
                label=FieldProto.LABEL_REPEATED if repeated else FieldProto.LABEL_OPTIONAL)
            if type_name in SCALARS:
                field.type = SCALARS[type_name]
                continue
            field.type_name = type_name
            field.type = FieldProto.TYPE_ENUM if type_name in local_enums else \
                FieldProto.TYPE_MESSAGE
            if type_name in local:
                continue
            if type_name in WELL_KNOWN:
                dependency = WELL_KNOWN[type_name].DESCRIPTOR.name
            else:
                dependency = f"{package}/{type_name.rsplit('.', 1)[-1]}.proto"
            if dependency not in imports:
                imports.append(dependency)
    proto.dependency.extend(sorted(imports))
    return proto


def build_pool(files: Iterable[descriptor_pb2.FileDescriptorProto]
               ) -> descriptor_pool.DescriptorPool:
    """A private descriptor pool holding the well-known types and ``files`` (in dependency
    order)."""
    pool = descriptor_pool.DescriptorPool()
    for module in WELL_KNOWN.values():
        proto = descriptor_pb2.FileDescriptorProto()
        module.DESCRIPTOR.CopyToProto(proto)
        pool.Add(proto)
    for proto in files:
        pool.Add(proto)
    return pool


def message_class(pool: descriptor_pool.DescriptorPool, full_name: str) -> Any:
    """The message class of ``full_name`` (``"foxglove.PointCloud"``) in ``pool``."""
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(full_name))


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
    names = {v: k for k, v in SCALARS.items()}
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
            label = "repeated " if field.label == FieldProto.LABEL_REPEATED else ""
            lines.append(f"  {label}{type_name} {field.name} = {field.number};")
        lines.append("}")
    return "\n".join(lines) + "\n"
