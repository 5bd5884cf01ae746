"""The contract layer: artifact schemas, the stage registry, and the module structure."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest

from benchmarks.structure import (
    canonical_name,
    hidden_cli_flags,
    import_circles,
    import_graph,
    motor_step_spellings,
    points_column_declarations,
)
from scanpipe.artifacts import write_artifact
from scanpipe.errors import ArtifactError
from scanpipe.params import Params
from scanpipe.pipeline import execute
from scanpipe.progress import ProgressFn
from scanpipe.schema import ARTIFACTS, POINTS
from scanpipe.stage import RAW_INPUTS, Stage, StageResult
from scanpipe.stages import chain_stages, registry
from scanpipe.workdir import STAGE_ORDER

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_no_import_circles_in_src() -> None:
    assert import_circles(import_graph()) == []


def test_points_columns_are_declared_only_in_the_schema() -> None:
    assert points_column_declarations() == []


def test_the_motor_step_has_one_name_besides_hidden_deprecated_aliases() -> None:
    hidden = hidden_cli_flags()
    assert {"--step-angle", "--angle"} <= hidden
    names = {canonical_name(s) for s in motor_step_spellings() if s not in hidden}
    assert names == {"motor_step"}


def test_every_stage_speaks_in_known_artifacts() -> None:
    for stage in registry().values():
        for name in (*stage.inputs, *stage.outputs):
            assert name in ARTIFACTS or name in RAW_INPUTS, (stage.name, name)


def test_the_chain_and_the_workdir_order_come_from_the_registry() -> None:
    assert [s.name for s in chain_stages()] == ["decode", "calibrate", "assemble", "filter",
                                                 "mesh", "texture", "export"]
    assert [s.name for s in chain_stages("point_file")] == ["import-points", "filter", "mesh"]
    assert tuple(registry()) == STAGE_ORDER


def test_every_artifact_is_documented() -> None:
    text = (DOCS / "artifacts.md").read_text()
    for name, schema in ARTIFACTS.items():
        assert f"`{name}`" in text, name
        for column in schema.columns:
            assert f"`{column.name}`" in text, (name, column.name)


class NoParams(Params):
    pass


def _wrong_type(inputs: Mapping[str, Any], params: NoParams, progress: ProgressFn
                ) -> StageResult:
    points = inputs["points"]
    x = points.schema.get_field_index("x")
    bad = points.set_column(x, "x", points.column("x").cast(pa.float64()))
    return StageResult({"points": bad})


def _points() -> pa.Table:
    columns = {c.name: pa.array([0], c.type) for c in POINTS.columns if c.required}
    return pa.table(columns)


def test_a_stage_output_of_the_wrong_type_names_artifact_column_and_type() -> None:
    stage = Stage("bad", 1, NoParams, ("points",), ("points",), _wrong_type, "casts x")  # type: ignore[arg-type]
    with pytest.raises(ArtifactError) as info:
        stage.run({"points": _points()})
    assert str(info.value) == "bad output points: column 'x' is double, expected float"


def test_an_input_artifact_missing_a_column_is_named_on_read(tmp_path: Path) -> None:
    stage = registry()["filter"]
    path = tmp_path / "points.parquet"
    write_artifact(path, _points().drop_columns(["origin_y"]), {"key": "k"})
    with pytest.raises(ArtifactError, match=r"^points: missing column 'origin_y' \(float\)$"):
        execute(stage, {"points": path}, tmp_path / "out", stage.params())
    assert not (tmp_path / "out" / "points.parquet").exists()


def test_the_command_line_starts_without_the_heavy_libraries() -> None:
    # Open3D alone costs ~0.8 s and ~250 MB at import; rig check and record must not pay it.
    import subprocess
    import sys

    code = ("import sys, scanpipe.cli.main; "
            "print(sorted(m for m in ('open3d', 'laspy', 'pye57', 'trimesh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"
