"""The runner's caching rules, on small stand-in stages over real Parquet artifacts."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
from pydantic import Field

from scanpipe.errors import ArtifactError, ParameterError
from scanpipe.params import Params
from scanpipe.pipeline import (
    Stage,
    StageResult,
    run_chain,
    validate_pipeline_params,
)
from scanpipe.progress import ProgressFn
from scanpipe.schema import ArtifactSchema, Column

CALLS: list[str] = []
TOY = tuple(ArtifactSchema(n, (Column("v", pa.float64()),), "a toy table")
            for n in ("numbers", "scaled"))


class ReadParams(Params):
    scale: float = Field(1.0, gt=0)


class ScaleParams(Params):
    factor: float = 2.0


def _read(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn) -> StageResult:
    CALLS.append("read")
    values = [float(b) * params.scale for b in Path(inputs["recording"]).read_bytes()]
    return StageResult({"numbers": pa.table({"v": values})}, {"count": len(values)})


def _scale(inputs: Mapping[str, Any], params: ScaleParams, progress: ProgressFn) -> StageResult:
    CALLS.append("scale")
    table = inputs["numbers"]
    scaled = pa.table({"v": [v * params.factor for v in table.column("v").to_pylist()]})
    return StageResult({"scaled": scaled}, files={"sum.txt": str(sum(scaled["v"].to_pylist()))
                                                  .encode()})


def _stages(scale_version: int = 1) -> list[Stage]:
    return [
        Stage("read", 1, ReadParams, ("recording",), ("numbers",), _read, "read bytes",  # type: ignore[arg-type]
              schemas=TOY),
        Stage("scale", scale_version, ScaleParams, ("numbers",), ("scaled",), _scale,  # type: ignore[arg-type]
              "multiply", schemas=TOY),
    ]


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "rec.bin"
    path.write_bytes(bytes([1, 2, 3]))
    return path


def _run(recording: Path, workdir: Path, data: dict[str, Any] | None = None,
         version: int = 1, **kwargs: Any) -> list[str]:
    stages = _stages(version)
    params = validate_pipeline_params(stages, data or {})
    CALLS.clear()
    records = run_chain(recording, workdir, params, stages, **kwargs)
    return [r.stage for r in records if not r.reused]


def test_unchanged_reuses_everything(recording: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    assert _run(recording, work) == ["read", "scale"]
    assert _run(recording, work) == []
    assert CALLS == []
    assert (work / "scale" / "sum.txt").read_text() == "12.0"


def test_changed_parameter_reruns_that_stage_and_later(recording: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    _run(recording, work)
    assert _run(recording, work, {"scale": {"factor": 3.0}}) == ["scale"]
    assert (work / "scale" / "sum.txt").read_text() == "18.0"
    assert _run(recording, work, {"read": {"scale": 2.0}, "scale": {"factor": 3.0}}) == [
        "read", "scale"]


def test_changed_stage_version_reruns(recording: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    _run(recording, work)
    assert _run(recording, work, version=2) == ["scale"]


def test_changed_recording_reruns_all(recording: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    _run(recording, work)
    recording.write_bytes(bytes([4, 5]))
    assert _run(recording, work) == ["read", "scale"]


def test_missing_extra_file_or_damaged_artifact_is_recomputed(recording: Path,
                                                              tmp_path: Path) -> None:
    work = tmp_path / "w"
    _run(recording, work)
    (work / "scale" / "sum.txt").unlink()
    assert _run(recording, work) == ["scale"]
    (work / "read" / "numbers.parquet").write_bytes(b"not parquet")
    # The damaged artifact is recomputed; its key is the same, so "scale" stays valid.
    assert _run(recording, work) == ["read"]


def test_force_and_to(recording: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    assert _run(recording, work, to="read") == ["read"]
    assert not (work / "scale").exists()
    assert _run(recording, work, force=True) == ["read", "scale"]


def test_unknown_stage_and_keys_reported_together() -> None:
    with pytest.raises(ParameterError) as info:
        validate_pipeline_params(_stages(), {"scal": {"factor": 1}, "read": {"scael": 1,
                                                                             "scale": -1}})
    text = str(info.value)
    assert "unknown stage 'scal' (did you mean scale?" in text
    assert "unknown key 'read.scael'" in text and "did you mean scale" in text
    assert "read.scale = -1" in text


def test_missing_recording(tmp_path: Path) -> None:
    with pytest.raises(ArtifactError, match="recording not found"):
        run_chain(tmp_path / "nope.mcap", tmp_path / "w", {}, _stages())
