"""Frozen, validated parameter models and the one way to report what is wrong with them.

Every stage, the rig and the CLI use :class:`Params`: unknown keys are errors, models are
immutable, and validation reports every problem at once with the key, the bad value and what is
allowed. The same model is fed from Python keyword arguments, TOML files and ``--set a.b=1``.
"""

from __future__ import annotations

import difflib
import json
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from scanpipe.errors import ParameterError

P = TypeVar("P", bound="Params")


class Params(BaseModel):
    """Base for every parameter model: frozen, no unknown keys, validated defaults."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)


def _known_keys(model: type[BaseModel], loc: tuple[Any, ...]) -> list[str]:
    """The field names valid at ``loc`` (the parent of an unknown key), for suggestions."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        field = getattr(current, "model_fields", {}).get(part)
        if field is None:
            return []
        annotation = field.annotation
        for candidate in (annotation, *getattr(annotation, "__args__", ())):
            if isinstance(candidate, type) and issubclass(candidate, BaseModel):
                current = candidate
                break
        else:
            return []
    return list(getattr(current, "model_fields", {}))


def describe_validation_error(
    err: ValidationError, model: type[BaseModel], prefix: str = ""
) -> list[str]:
    """One line per problem: ``key = value: what is wrong (what is allowed)``.

    ``prefix`` (e.g. ``"filter."``) is put before every key, for models nested in a larger file.
    """
    problems: list[str] = []
    for item in err.errors():
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
            value = item.get("input")
            shown = json.dumps(value, default=str) if not isinstance(value, Mapping) else "{…}"
            message = item["msg"].removeprefix("Value error, ")
            problems.append(f"{key} = {shown}: {message}")
    return problems


def validate(
    model: type[P], data: Mapping[str, Any], source: str = "parameters", prefix: str = ""
) -> P:
    """Build ``model`` from ``data`` or raise :class:`ParameterError` listing every problem."""
    if not isinstance(data, Mapping):
        raise ParameterError([f"{prefix.rstrip('.') or 'parameters'}: expected a table, "
                              f"got {data!r}"], source)
    try:
        return model.model_validate(dict(data))
    except ValidationError as err:
        raise ParameterError(describe_validation_error(err, model, prefix), source) from None


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


def load_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file, turning every failure into a one-line :class:`ParameterError`."""
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ParameterError(["file not found"], str(path)) from None
    except IsADirectoryError:
        raise ParameterError(["is a directory, expected a TOML file"], str(path)) from None
    except tomllib.TOMLDecodeError as err:
        raise ParameterError([f"not valid TOML: {err}"], str(path)) from None
    except (OSError, UnicodeDecodeError) as err:
        raise ParameterError([f"cannot be read: {err}"], str(path)) from None


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
