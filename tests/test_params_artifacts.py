"""Parameter models, ``--set`` parsing, and artifacts with provenance and atomic writes."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pytest
from pydantic import Field

from scanpipe.artifacts import (
    artifact_key,
    atomic_path,
    read_artifact,
    read_provenance,
    write_artifact,
)
from scanpipe.errors import ArtifactError, ParameterError
from scanpipe.params import Params, apply_assignments, validate
from scanpipe.schema import ArtifactSchema, Column


class Inner(Params):
    size_m: float = Field(0.01, gt=0)


class Outer(Params):
    inner: Inner = Inner()
    mode: str = "a"


def test_assignments_parse_toml_values() -> None:
    data = apply_assignments({}, ["inner.size_m=0.5", "mode=b", "flag=true"])
    assert data == {"inner": {"size_m": 0.5}, "mode": "b", "flag": True}


def test_validation_lists_every_problem_with_suggestions() -> None:
    with pytest.raises(ParameterError) as info:
        validate(Outer, {"inner": {"size_m": -1, "sise_m": 2}, "mdoe": "x"}, "sweep.toml")
    text = str(info.value)
    assert "3 problems" in text
    assert "inner.size_m = -1" in text
    assert "did you mean size_m" in text
    assert "did you mean mode" in text


def test_params_are_frozen() -> None:
    p = Outer()
    with pytest.raises(Exception, match="frozen"):
        p.mode = "c"  # type: ignore[misc]


def test_bad_assignment() -> None:
    with pytest.raises(ParameterError, match="not key=value"):
        apply_assignments({}, ["novalue"])


def test_key_changes_with_any_part() -> None:
    base = artifact_key("s", 1, {"a": 1}, {"in": "k"}, {"numpy": "2"})
    assert base == artifact_key("s", 1, {"a": 1}, {"in": "k"}, {"numpy": "2"})
    assert base != artifact_key("s", 2, {"a": 1}, {"in": "k"}, {"numpy": "2"})
    assert base != artifact_key("s", 1, {"a": 2}, {"in": "k"}, {"numpy": "2"})
    assert base != artifact_key("s", 1, {"a": 1}, {"in": "j"}, {"numpy": "2"})
    assert base != artifact_key("s", 1, {"a": 1}, {"in": "k"}, {"numpy": "3"})


def test_artifact_round_trip_with_provenance(tmp_path: Path) -> None:
    path = tmp_path / "points.parquet"
    table = pa.table({"x": pa.array([1.0, 2.0], pa.float32()), "name": ["a", "b"]})
    write_artifact(path, table, {"key": "abc", "stage": "test"})
    def schema(**columns: pa.DataType) -> ArtifactSchema:
        return ArtifactSchema("t", tuple(Column(n, t) for n, t in columns.items()), "a test")

    loaded, provenance = read_artifact(path, schema(x=pa.float32()))
    assert loaded.column("x").to_pylist() == [1.0, 2.0]
    assert provenance == {"key": "abc", "stage": "test"}
    with pytest.raises(ArtifactError, match="missing column 'y'"):
        read_artifact(path, schema(y=pa.float32()))
    with pytest.raises(ArtifactError, match="is float, expected double"):
        read_artifact(path, schema(x=pa.float64()))


def test_failed_write_leaves_old_file(tmp_path: Path) -> None:
    path = tmp_path / "a.bin"
    path.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(path) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("interrupted")
    assert path.read_bytes() == b"old"
    assert list(tmp_path.iterdir()) == [path]


def test_not_parquet(tmp_path: Path) -> None:
    path = tmp_path / "x.parquet"
    path.write_bytes(b"garbage")
    with pytest.raises(ArtifactError, match="not a readable Parquet file"):
        read_provenance(path)
    with pytest.raises(ArtifactError, match="not found"):
        read_provenance(tmp_path / "missing.parquet")


def test_library_versions_are_the_installed_ones_looked_up_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The versions in keys are the installed distributions' (cached per process: the lookup
    parses metadata files, milliseconds per stage)."""
    from importlib.metadata import version

    from scanpipe import artifacts

    assert artifacts.library_versions(["numpy", "cv2", "no_such_library_x"]) == {
        "numpy": version("numpy"), "cv2": version("opencv-python-headless"),
        "no_such_library_x": "absent"}
    monkeypatch.setattr(artifacts, "version", lambda name: pytest.fail("looked up again"))
    assert artifacts.library_versions(["numpy"]) == {"numpy": version("numpy")}
