"""Frozen, validated parameter models and the one way to report what is wrong with them.

Every stage, the rig and the CLI use :class:`Params`: unknown keys are errors, models are
immutable, and validation reports every problem at once with the key, the bad value and what is
allowed. The same model is fed from Python keyword arguments, TOML files and ``--set a.b=1``.

Numbers are checked strictly for every model: NaN and ±inf are refused (no parameter means
"unbounded" by inf), ``true``/``false`` is not a number and a number is not a boolean. Data nested
more than :data:`MAX_NESTING` levels deep is refused before pydantic sees it, and a TOML text
nested deeper than the TOML reader can follow is a one-line error, not a ``RecursionError``.
"""

from __future__ import annotations

import difflib
import json
import math
import tomllib
import types
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

import annotated_types
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails, PydanticCustomError

from scanpipe.errors import ParameterError

P = TypeVar("P", bound="Params")

#: Deepest nesting of tables and arrays accepted anywhere (the rig needs 5 levels).
MAX_NESTING = 32
#: Longest rendering of a bad value in a message.
_SHOWN_CHARS = 60
#: Error types whose message gets the field's allowed range appended.
_RANGE_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}
_NUMBER_ERRORS = {"finite_number", "bool_not_number", "float_parsing", "int_parsing",
                  "float_type", "int_type", "int_from_float", *_RANGE_ERRORS}


class Params(BaseModel):
    """Base for every parameter model: frozen, no unknown keys, validated defaults.

    Floats must be finite (``allow_inf_nan=False``); booleans and numbers are not interchangeable.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True,
                              allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _booleans_are_not_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        field = cls.model_fields.get(info.field_name or "")
        if field is not None:
            _check_bool_number(field.annotation, value)
        return value


def _scalar_kinds(annotation: Any) -> set[str]:
    """What a scalar annotation accepts: ``bool``, ``number`` and/or ``other``."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return _scalar_kinds(get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        kinds: set[str] = set()
        for arm in get_args(annotation):
            if arm is not type(None):
                kinds |= _scalar_kinds(arm)
        return kinds
    if origin is Literal:
        return {"bool" if isinstance(v, bool) else "number" if isinstance(v, int | float)
                else "other" for v in get_args(annotation)}
    if annotation is bool:
        return {"bool"}
    if annotation in (int, float):
        return {"number"}
    return {"other"}


def _check_bool_number(annotation: Any, value: Any) -> None:
    """Raise when ``value`` (or an item of it) is a boolean for a number or a number for a boolean.

    pydantic would turn ``true`` into 1 and ``1`` into ``true``; in a parameter file either is
    a mistake.
    """
    origin = get_origin(annotation)
    if origin is Annotated:
        _check_bool_number(get_args(annotation)[0], value)
        return
    if origin in (Union, types.UnionType):
        arms = [a for a in get_args(annotation) if a is not type(None)]
        if len(arms) == 1:
            _check_bool_number(arms[0], value)
            return
    if origin in (tuple, list) and isinstance(value, list | tuple):
        args = get_args(annotation)
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            items = [args[0] if args else Any] * len(value)
        else:
            items = list(args)
        for index, (item, element) in enumerate(zip(items, value, strict=False)):
            try:
                _check_bool_number(item, element)
            except PydanticCustomError as err:
                raise PydanticCustomError(err.type, f"item {index}: {err.message()}") from None
        return
    kinds = _scalar_kinds(annotation)
    if isinstance(value, bool) and "number" in kinds and "bool" not in kinds:
        raise PydanticCustomError("bool_not_number", "expected a number, not true/false")
    if (isinstance(value, int | float) and not isinstance(value, bool)
            and kinds == {"bool"}):
        raise PydanticCustomError("number_not_bool", "expected true or false, not a number")


def _walk(model: type[BaseModel], loc: tuple[Any, ...]
          ) -> tuple[type[BaseModel] | None, FieldInfo | None]:
    """The model that holds the last key of ``loc`` and that key's field (None where unknown)."""
    keys = [part for part in loc if not isinstance(part, int)]
    current: type[BaseModel] | None = model
    field: FieldInfo | None = None
    for index, part in enumerate(keys):
        field = current.model_fields.get(part) if current is not None else None
        if field is None:
            return None, None
        if index < len(keys) - 1:
            current = _nested_model(field)
    return current, field


def _nested_model(field: FieldInfo) -> type[BaseModel] | None:
    """The model a field holds (directly, optionally, or as the items of a tuple)."""
    for candidate in (field.annotation, *get_args(field.annotation)):
        if isinstance(candidate, type) and issubclass(candidate, BaseModel):
            return candidate
    return None


def _known_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The field names valid at ``loc`` (the parent of an unknown key), for suggestions."""
    if not [part for part in loc if not isinstance(part, int)]:
        return list(model.model_fields)
    _, field = _walk(model, loc)
    nested = _nested_model(field) if field is not None else None
    return list(nested.model_fields) if nested is not None else []


def _bounds(field: FieldInfo | None) -> str:
    """The allowed range of a numeric field, e.g. ``"a finite number > 0 and ≤ 90"``.

    For a tuple of numbers the bounds of its items are given.
    """
    if field is None:
        return "a finite number"
    annotation: Any = field.annotation
    metadata = list(field.metadata)
    if get_origin(annotation) is tuple and get_args(annotation):
        annotation = get_args(annotation)[0]
    if get_origin(annotation) is Annotated:
        annotation, *extra = get_args(annotation)
        for item in extra:
            metadata += getattr(item, "metadata", [item])
    parts: list[str] = []
    for item in metadata:
        if not isinstance(item, annotated_types.BaseMetadata):
            continue
        for attr, sign in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
            bound = getattr(item, attr, None)
            if bound is not None:
                plain = float(bound)
                parts.append(f"{sign} {int(plain) if plain.is_integer() else plain!r}")
    kind = "a whole number" if annotation is int else "a finite number"
    return kind + (" " + " and ".join(parts) if parts else "")


def show_value(value: Any) -> str:
    """A value as a user typed it (TOML spelling for nan, inf and booleans), cut to one line."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, Mapping):
        return "{…}"
    shown = json.dumps(value, default=str)
    return shown if len(shown) <= _SHOWN_CHARS else shown[:_SHOWN_CHARS - 1] + "…"


def describe_validation_error(
    err: ValidationError, model: type[BaseModel], prefix: str = ""
) -> list[str]:
    """One line per problem: ``key = value: what is wrong (what is allowed)``.

    ``prefix`` (e.g. ``"filter."``) is put before every key, for models nested in a larger file.
    """
    return describe_errors(err.errors(), model, prefix)


def describe_errors(
    errors: Iterable[ErrorDetails], model: type[BaseModel], prefix: str = ""
) -> list[str]:
    """:func:`describe_validation_error` for a list of pydantic error details."""
    problems: list[str] = []
    for item in errors:
        loc = tuple(item["loc"])
        key = prefix + (".".join(str(p) for p in loc) or "(top level)")
        if item["type"] == "extra_forbidden":
            known = _known_keys(model, loc[:-1])
            close = difflib.get_close_matches(str(loc[-1]), known, n=3)
            hint = f"did you mean {', '.join(close)}?" if close else ""
            allowed = f"allowed: {', '.join(known)}" if known else ""
            tail = "; ".join(s for s in (hint, allowed) if s)
            problems.append(f"unknown key {key!r}" + (f" ({tail})" if tail else ""))
        elif item["type"] == "missing":
            problems.append(f"{key}: required key is missing")
        else:
            message = item["msg"].removeprefix("Value error, ")
            if item["type"] == "finite_number":
                message = "nan and inf are not allowed"
            elif item["type"] in _RANGE_ERRORS:
                message = "out of range"
            if item["type"] in _NUMBER_ERRORS:
                message += f" (allowed: {_bounds(_walk(model, loc)[1])})"
            value = item.get("input")
            if isinstance(value, Mapping):  # a check over a whole table: its message says all
                problems.append(f"{key}: {message}")
            else:
                problems.append(f"{key} = {show_value(value)}: {message}")
    return problems


def _prune_deep(value: Any, depth: int, path: tuple[Any, ...], cut: list[tuple[Any, ...]]
                ) -> Any:
    """A copy of ``value`` with every table or array deeper than :data:`MAX_NESTING` replaced by
    None; the paths replaced go to ``cut``. Recursion is bounded by the limit itself."""
    if not isinstance(value, Mapping | list | tuple):
        return value
    if depth >= MAX_NESTING:
        cut.append(path)
        return None
    if isinstance(value, Mapping):
        return {k: _prune_deep(v, depth + 1, (*path, k), cut) for k, v in value.items()}
    items = [_prune_deep(v, depth + 1, (*path, i), cut) for i, v in enumerate(value)]
    return tuple(items) if isinstance(value, tuple) else items


def _on_path(loc: tuple[Any, ...], path: tuple[Any, ...]) -> bool:
    """True when ``loc`` lies inside ``path`` or on the way to it."""
    return loc[:len(path)] == path or path[:len(loc)] == loc


def _dotted(path: tuple[Any, ...], prefix: str = "", parts: int = 6) -> str:
    shown = ".".join(str(p) for p in path[:parts]) + (".…" if len(path) > parts else "")
    return prefix + (shown or "(top level)")


def nesting_problems(data: Any, prefix: str = "") -> list[str]:
    """One line per place in ``data`` nested deeper than :data:`MAX_NESTING` (none: [])."""
    cut: list[tuple[Any, ...]] = []
    _prune_deep(data, 0, (), cut)
    return [_nesting_message(path, prefix) for path in cut]


def _nesting_message(path: tuple[Any, ...], prefix: str) -> str:
    return (f"{_dotted(path, prefix)}: nested more than {MAX_NESTING} levels deep (arrays or "
            "tables inside each other); no setting nests that deep")


def validate(
    model: type[P], data: Mapping[str, Any], source: str = "parameters", prefix: str = "",
    context: Mapping[str, Any] | None = None,
) -> P:
    """Build ``model`` from ``data`` or raise :class:`ParameterError` listing every problem;
    ``context`` goes to the model's validators (pydantic's validation context).

    Parts nested deeper than :data:`MAX_NESTING` are reported and left out before pydantic
    validates the rest, so absurd nesting cannot exhaust the stack.
    """
    if not isinstance(data, Mapping):
        raise ParameterError([f"{prefix.rstrip('.') or 'parameters'}: expected a table, "
                              f"got {show_value(data)}"], source)
    cut: list[tuple[Any, ...]] = []
    pruned = _prune_deep(data, 0, (), cut)
    problems = [_nesting_message(path, prefix) for path in cut]
    try:
        result = model.model_validate(pruned, context=context)
    except ValidationError as err:
        # What was cut is reported once above, not again as "expected a list".
        kept = [e for e in err.errors() if not any(_on_path(tuple(e["loc"]), path)
                                                   for path in cut)]
        problems += describe_errors(kept, model, prefix)
    if problems:
        raise ParameterError(problems, source)
    return result


def parse_assignment(text: str) -> tuple[list[str], Any]:
    """Parse ``a.b=value`` into a key path and a value (TOML syntax, bare words are strings)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ParameterError([f"{text!r} is not key=value (for example filter.voxel_size_m=0.01)"],
                             "--set")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    except RecursionError:
        raise ParameterError([_nesting_message(tuple(key.split(".")), "")], "--set") from None
    deep = nesting_problems(value, key + ".")
    if deep:
        raise ParameterError(deep, "--set")
    return key.split("."), value


def apply_assignments(data: Mapping[str, Any], assignments: Iterable[str]) -> dict[str, Any]:
    """Return a copy of nested ``data`` with every ``a.b=value`` assignment applied."""
    result: dict[str, Any] = json.loads(json.dumps(data, default=list))
    for text in assignments:
        path, value = parse_assignment(text)
        node = result
        for part in path[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ParameterError([f"{'.'.join(path)}: {part!r} is not a table"], "--set")
            node = child
        node[path[-1]] = value
    return result


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """Parse TOML text, turning every failure into a one-line :class:`ParameterError`.

    tomllib recurses once per level of nested arrays and inline tables, so a few hundred
    levels exhaust the stack: that is reported like any other malformed file.
    """
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ParameterError([f"not valid TOML: {err}"], source) from None
    except RecursionError:
        raise ParameterError([f"arrays or tables nested too deeply to read (no setting nests "
                              f"more than {MAX_NESTING} levels)"], source) from None


def load_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file, turning every failure into a one-line :class:`ParameterError`."""
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ParameterError(["file not found"], str(path)) from None
    except IsADirectoryError:
        raise ParameterError(["is a directory, expected a TOML file"], str(path)) from None
    except UnicodeDecodeError as err:
        raise ParameterError([f"not UTF-8 text ({err.reason} at byte {err.start})"],
                             str(path)) from None
    except OSError as err:
        raise ParameterError([f"cannot be read: {err.strerror or err}"], str(path)) from None
    return parse_toml(text, str(path))


def to_toml(data: Mapping[str, Any], comments: Mapping[str, str] | None = None) -> str:
    """Write nested plain data (tables, arrays of tables, scalars, lists) as TOML.

    ``comments`` maps dotted keys (``motor.gear_ratio``) or table names to a comment line
    written above the key. Enough for rig files and parameter files; not a general writer.
    """
    comments = comments or {}
    lines: list[str] = []

    def scalar(value: Any) -> str:
        if isinstance(value, bool):
            return "true" if value else "false"
        if isinstance(value, int | float):
            return repr(value)
        if isinstance(value, str):
            return json.dumps(value)
        if isinstance(value, list | tuple):
            return "[" + ", ".join(scalar(v) for v in value) + "]"
        raise TypeError(f"cannot write {value!r} as TOML")

    def table(prefix: str, node: Mapping[str, Any], header: str | None) -> None:
        simple = {k: v for k, v in node.items() if not _is_table(v) and not _is_table_array(v)}
        nested = {k: v for k, v in node.items() if k not in simple}
        if header is not None:
            if lines:
                lines.append("")
            if prefix in comments:
                lines.append(f"# {comments[prefix]}")
            lines.append(header)
        for key, value in simple.items():
            dotted = f"{prefix}.{key}" if prefix else key
            if value is None:
                continue
            if dotted in comments:
                lines.append(f"# {comments[dotted]}")
            lines.append(f"{key} = {scalar(value)}")
        for key, value in nested.items():
            dotted = f"{prefix}.{key}" if prefix else key
            if _is_table(value):
                table(dotted, value, f"[{dotted}]")
            else:
                for item in value:
                    table(dotted, item, f"[[{dotted}]]")

    table("", data, None)
    return "\n".join(lines) + "\n"


def _is_table(value: Any) -> bool:
    return isinstance(value, Mapping)


def _is_table_array(value: Any) -> bool:
    return isinstance(value, list | tuple) and bool(value) and all(
        isinstance(v, Mapping) for v in value
    )
