"""The published Foxglove schemas scanpipe writes, as protobuf classes built in code.

Foxglove recognises its well-known schemas only by exact name and field layout, so these are
transcriptions of the ``foxglove/*.proto`` files of the public ``foxglove/schemas`` repository
(one file descriptor per message, as published), built by :mod:`scanpipe.protobuf` into a
private descriptor pool, so they cannot clash with other registrations.

Classes: :data:`PointCloud`, :data:`FrameTransform`, :data:`SceneUpdate` and their parts.
"""

from __future__ import annotations

from typing import Any

from scanpipe.protobuf import EnumSpecs, FieldSpec, build_pool, file_proto
from scanpipe.protobuf import message_class as pool_message_class

_TIMESTAMP = ".google.protobuf.Timestamp"
_DURATION = ".google.protobuf.Duration"

#: message -> (nested enums {name: [(value, number)]}, [(type, name, number, repeated)]),
#: in dependency order.
_MESSAGES: dict[str, tuple[EnumSpecs, list[FieldSpec]]] = {
    "Vector3": ({}, [("double", "x", 1, False), ("double", "y", 2, False),
                     ("double", "z", 3, False)]),
    "Point3": ({}, [("double", "x", 1, False), ("double", "y", 2, False),
                    ("double", "z", 3, False)]),
    "Quaternion": ({}, [("double", "x", 1, False), ("double", "y", 2, False),
                        ("double", "z", 3, False), ("double", "w", 4, False)]),
    "Color": ({}, [("double", "r", 1, False), ("double", "g", 2, False),
                   ("double", "b", 3, False), ("double", "a", 4, False)]),
    "KeyValuePair": ({}, [("string", "key", 1, False), ("string", "value", 2, False)]),
    "Pose": ({}, [(".foxglove.Vector3", "position", 1, False),
                  (".foxglove.Quaternion", "orientation", 2, False)]),
    "PackedElementField": (
        {"NumericType": [("UNKNOWN", 0), ("UINT8", 1), ("INT8", 2), ("UINT16", 3),
                         ("INT16", 4), ("UINT32", 5), ("INT32", 6), ("FLOAT32", 7),
                         ("FLOAT64", 8)]},
        [("string", "name", 1, False), ("fixed32", "offset", 2, False),
         (".foxglove.PackedElementField.NumericType", "type", 3, False)]),
    "PointCloud": ({}, [(_TIMESTAMP, "timestamp", 1, False), ("string", "frame_id", 2, False),
                        (".foxglove.Pose", "pose", 3, False),
                        ("fixed32", "point_stride", 4, False),
                        (".foxglove.PackedElementField", "fields", 5, True),
                        ("bytes", "data", 6, False)]),
    "FrameTransform": ({}, [(_TIMESTAMP, "timestamp", 1, False),
                            ("string", "parent_frame_id", 2, False),
                            ("string", "child_frame_id", 3, False),
                            (".foxglove.Vector3", "translation", 4, False),
                            (".foxglove.Quaternion", "rotation", 5, False)]),
    "ArrowPrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                            ("double", "shaft_length", 2, False),
                            ("double", "shaft_diameter", 3, False),
                            ("double", "head_length", 4, False),
                            ("double", "head_diameter", 5, False),
                            (".foxglove.Color", "color", 6, False)]),
    "CubePrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                           (".foxglove.Vector3", "size", 2, False),
                           (".foxglove.Color", "color", 3, False)]),
    "SpherePrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                             (".foxglove.Vector3", "size", 2, False),
                             (".foxglove.Color", "color", 3, False)]),
    "CylinderPrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                               (".foxglove.Vector3", "size", 2, False),
                               ("double", "bottom_scale", 3, False),
                               ("double", "top_scale", 4, False),
                               (".foxglove.Color", "color", 5, False)]),
    "LinePrimitive": (
        {"Type": [("LINE_STRIP", 0), ("LINE_LOOP", 1), ("LINE_LIST", 2)]},
        [(".foxglove.LinePrimitive.Type", "type", 1, False), (".foxglove.Pose", "pose", 2, False),
         ("double", "thickness", 3, False), ("bool", "scale_invariant", 4, False),
         (".foxglove.Point3", "points", 5, True), (".foxglove.Color", "color", 6, False),
         (".foxglove.Color", "colors", 7, True), ("fixed32", "indices", 8, True)]),
    "TriangleListPrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                                   (".foxglove.Point3", "points", 2, True),
                                   (".foxglove.Color", "color", 3, False),
                                   (".foxglove.Color", "colors", 4, True),
                                   ("fixed32", "indices", 5, True)]),
    "TextPrimitive": ({}, [(".foxglove.Pose", "pose", 1, False), ("bool", "billboard", 2, False),
                           ("double", "font_size", 3, False),
                           ("bool", "scale_invariant", 4, False),
                           (".foxglove.Color", "color", 5, False), ("string", "text", 6, False)]),
    "ModelPrimitive": ({}, [(".foxglove.Pose", "pose", 1, False),
                            (".foxglove.Vector3", "scale", 2, False),
                            (".foxglove.Color", "color", 3, False),
                            ("bool", "override_color", 4, False), ("string", "url", 5, False),
                            ("string", "media_type", 6, False), ("bytes", "data", 7, False)]),
    "SceneEntity": ({}, [(_TIMESTAMP, "timestamp", 1, False), ("string", "frame_id", 2, False),
                         ("string", "id", 3, False), (_DURATION, "lifetime", 4, False),
                         ("bool", "frame_locked", 5, False),
                         (".foxglove.KeyValuePair", "metadata", 6, True),
                         (".foxglove.ArrowPrimitive", "arrows", 7, True),
                         (".foxglove.CubePrimitive", "cubes", 8, True),
                         (".foxglove.SpherePrimitive", "spheres", 9, True),
                         (".foxglove.CylinderPrimitive", "cylinders", 10, True),
                         (".foxglove.LinePrimitive", "lines", 11, True),
                         (".foxglove.TriangleListPrimitive", "triangles", 12, True),
                         (".foxglove.TextPrimitive", "texts", 13, True),
                         (".foxglove.ModelPrimitive", "models", 14, True)]),
    "SceneEntityDeletion": (
        {"Type": [("MATCHING_ID", 0), ("ALL", 1)]},
        [(_TIMESTAMP, "timestamp", 1, False),
         (".foxglove.SceneEntityDeletion.Type", "type", 2, False), ("string", "id", 3, False)]),
    "SceneUpdate": ({}, [(".foxglove.SceneEntityDeletion", "deletions", 1, True),
                         (".foxglove.SceneEntity", "entities", 2, True)]),
}


POOL = build_pool(file_proto(f"foxglove/{name}.proto", "foxglove", [(name, fields, enums)])
                  for name, (enums, fields) in _MESSAGES.items())


def message_class(name: str) -> Any:
    """The class of ``foxglove.<name>``."""
    return pool_message_class(POOL, f"foxglove.{name}")


PointCloud: Any = message_class("PointCloud")
PackedElementField: Any = message_class("PackedElementField")
FrameTransform: Any = message_class("FrameTransform")
SceneUpdate: Any = message_class("SceneUpdate")
SceneEntity: Any = message_class("SceneEntity")
ModelPrimitive: Any = message_class("ModelPrimitive")
