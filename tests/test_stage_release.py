"""Inputs handed over: a stage releases the tables it is done with (the export stage its
frames, mesh and points) while it runs, and what it writes does not change."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.artifacts import PROVENANCE_KEY, read_artifact
from scanpipe.params import Params
from scanpipe.pipeline import Stage, StageResult, run_chain, validate_pipeline_params
from scanpipe.progress import ProgressFn
from scanpipe.schema import ArtifactSchema, Column
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.stage import Inputs, narrow_input, release_inputs
from scanpipe.stages import get_stage

TOY = tuple(ArtifactSchema(n, (Column("v", pa.float64()),), "a toy table")
            for n in ("numbers", "scaled", "summed"))
SEEN: dict[str, Any] = {}


class NoParams(Params):
    pass


def _read(inputs: Mapping[str, Any], params: NoParams, progress: ProgressFn) -> StageResult:
    # in Arrow's pool (a numpy array wrapped as it is would not count in it)
    values = pa.compute.add(pa.array(np.arange(2_000_000, dtype=np.float64)), 0.0)
    return StageResult({"numbers": pa.table({"v": values})})


def _scale(inputs: Mapping[str, Any], params: NoParams, progress: ProgressFn) -> StageResult:
    scaled = pa.table({"v": pa.compute.multiply(inputs["numbers"].column("v"), 2.0)})
    before = pa.total_allocated_bytes()
    SEEN["scale"] = (isinstance(inputs, Inputs) and "numbers" in inputs.releasable,
                     release_inputs(inputs, "numbers"), before - pa.total_allocated_bytes())
    return StageResult({"scaled": scaled})


def _sum(inputs: Mapping[str, Any], params: NoParams, progress: ProgressFn) -> StageResult:
    total = pa.compute.sum(inputs["scaled"].column("v")).as_py()
    if "numbers" in inputs:  # released by scale: read back from its file, whole
        SEEN["numbers_rows"] = inputs["numbers"].num_rows
    SEEN["sum"] = release_inputs(inputs, "scaled")
    return StageResult({"summed": pa.table({"v": [float(total)]})})


def _toy_chain(sum_reads_numbers: bool) -> list[Stage]:
    return [
        Stage("read", 1, NoParams, ("recording",), ("numbers",), _read, "numbers",  # type: ignore[arg-type]
              schemas=TOY),
        Stage("scale", 1, NoParams, ("numbers",), ("scaled",), _scale, "twice",  # type: ignore[arg-type]
              schemas=TOY),
        Stage("sum", 1, NoParams,
              ("scaled", "numbers") if sum_reads_numbers else ("scaled",), ("summed",),
              _sum, "sum", schemas=TOY),  # type: ignore[arg-type]
    ]


def test_release_inputs_keeps_schema_and_provenance() -> None:
    table = pa.table({"v": [1.0, 2.0]}).replace_schema_metadata({PROVENANCE_KEY: b"{}"})
    handed = Inputs({"numbers": table, "recording": Path("x")}, {"numbers", "recording"})
    assert release_inputs(handed, "numbers", "recording", "absent")
    assert handed["numbers"].num_rows == 0 and handed["numbers"].schema == table.schema
    assert handed["numbers"].schema.metadata == {PROVENANCE_KEY: b"{}"}
    assert handed["recording"] == Path("x")
    assert not release_inputs(handed, "numbers")  # nothing left to release
    kept = Inputs({"numbers": table})  # a later stage takes it
    plain = {"numbers": table}  # a notebook's own dict
    assert not release_inputs(kept, "numbers") and not release_inputs(plain, "numbers")
    assert kept["numbers"] is table and plain["numbers"] is table


def test_the_chain_hands_over_every_table_and_reads_back_what_was_released(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stage may release a table the next stage takes too (the texture stage its frames
    and mesh): that stage then gets it whole, from its file, never the empty stand-in."""
    # tables written in this thread: a committer's worker drops a written set's tables a
    # moment after the settle returns, which would race the count of freed bytes
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    rec = tmp_path / "rec.bin"
    rec.write_bytes(b"x")
    for reads in (False, True):
        stages = _toy_chain(reads)
        work = tmp_path / f"w{reads}"
        SEEN.clear()
        run_chain(rec, work, validate_pipeline_params(stages, {}), stages)
        releasable, released, freed = SEEN["scale"]
        # numbers (16 MB) is scale's to release, also when sum takes it
        assert releasable is True and released is True
        assert freed >= 15_000_000, freed
        assert SEEN.get("numbers_rows") == (2_000_000 if reads else None)
        assert SEEN["sum"] is True  # the last stage's inputs are always its own
        summed = read_artifact(work / "sum" / "summed.parquet")[0]
        assert summed.column("v").to_pylist() == [2.0 * 1_999_999 * 2_000_000 / 2]
        # the reused chain serves the same artifacts
        again = run_chain(rec, work, validate_pipeline_params(stages, {}), stages)
        assert all(r.reused for r in again)


@pytest.mark.slow
def test_export_in_the_chain_writes_what_it_writes_unreleased(tmp_path: Path) -> None:
    """The chain's export releases its inputs as it goes (frames after colouring, each table
    once its model is built); every file is byte for byte that of the stage run on tables
    nobody releases."""
    rec = tmp_path / "scan.mcap"
    simulate_direct(rec, tmp_path / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=3.0, camera_scale=0.125, camera_fps=0.5, seed=4))
    work = tmp_path / "w"
    run_chain(rec, work, {})
    manifest = read_artifact(work / "export" / "export_manifest.parquet")[0]
    written = dict(zip(manifest.column("file").to_pylist(),
                       manifest.column("sha256").to_pylist(), strict=True))
    assert {"model.obj", "model.glb", "cloud.ply"} <= set(written)
    stage = get_stage("export")
    producers = {"mesh_vertices": "mesh", "mesh_faces": "mesh", "textured_faces": "texture",
                 "texture_pages": "texture", "points": "filter", "frames": "decode",
                 "motor": "decode", "rig": "calibrate"}
    tables = {n: read_artifact(work / d / f"{n}.parquet")[0] for n, d in producers.items()}
    result = stage.run(tables)
    again = result.tables["export_manifest"]
    assert dict(zip(again.column("file").to_pylist(), again.column("sha256").to_pylist(),
                    strict=True)) == written
    assert all(t.num_rows for t in tables.values())  # a plain dict is never released


def test_narrow_input_keeps_the_named_columns_of_a_handed_over_table() -> None:
    table = pa.table({"x": [1.0], "origin_x": [0.0], "face": [3]}).replace_schema_metadata(
        {PROVENANCE_KEY: b'{"key": "k"}'})
    handed = Inputs({"points": table}, {"points"})
    assert narrow_input(handed, "points", ("x", "face", "absent"))
    assert handed["points"].column_names == ["x", "face"]
    assert handed["points"].schema.metadata == table.schema.metadata
    assert not narrow_input(handed, "points", ("x", "face"))  # nothing more to drop
    for other in (Inputs({"points": table}), {"points": table}):  # not handed over
        assert not narrow_input(other, "points", ("x",)) and other["points"] is table


@pytest.mark.slow
def test_colouring_lets_the_frames_go_once_it_has_chosen_its_own(tmp_path: Path) -> None:
    """``prepare_tables(keep_frames=False)`` on handed-over inputs: the frames are released
    (the colouring copied the bytes of the frames it chose) and the colours are those made
    with the frames kept."""
    from scanpipe.stages.export import prepare_tables

    rec = tmp_path / "scan.mcap"
    simulate_direct(rec, tmp_path / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=3.0, camera_scale=0.125, camera_fps=0.5, seed=4))
    run_chain(rec, tmp_path / "w", {}, to="filter")
    producers = {"points": "filter", "frames": "decode", "motor": "decode", "rig": "calibrate"}
    tables = {n: read_artifact(tmp_path / "w" / d / f"{n}.parquet")[0]
              for n, d in producers.items()}
    kept, coloured = prepare_tables(tables)
    assert coloured and kept["frames"].num_rows == tables["frames"].num_rows > 0
    handed = Inputs(tables, set(tables))
    released, coloured = prepare_tables(handed, keep_frames=False)
    assert coloured and handed["frames"].num_rows == 0 and released["frames"].num_rows == 0
    assert released["frames"].schema == tables["frames"].schema
    assert released["points"].equals(kept["points"])
    assert handed["points"].num_rows == tables["points"].num_rows  # only the frames went


def test_execute_hands_over_the_inputs_it_read_itself(tmp_path: Path) -> None:
    """A stage run alone (``execute`` on files: ``scanpipe mesh``, a batch's task) may release
    the tables the runner read for it; not those a caller keeps (``keep_tables``)."""
    from scanpipe.artifacts import write_artifact
    from scanpipe.pipeline import InMemory, execute

    numbers = tmp_path / "numbers.parquet"
    write_artifact(numbers, pa.table({"v": [1.0, 2.0]}), {"key": "k", "stage": "read"})
    scale = _toy_chain(False)[1]
    for keep in (False, True):
        SEEN.clear()
        record = execute(scale, {"numbers": numbers}, tmp_path / f"out{keep}", NoParams(),
                         force=True, hold=InMemory(keep_tables=keep))
        assert SEEN["scale"][:2] == (not keep, not keep)
        assert record.tables.get("numbers") is None or record.tables["numbers"].num_rows == 2
        assert read_artifact(tmp_path / f"out{keep}" / "scaled.parquet")[0].column(
            "v").to_pylist() == [2.0, 4.0]


@pytest.mark.slow
def test_texture_lets_frames_and_mesh_go_and_textures_the_same(tmp_path: Path) -> None:
    """Handed over, the texture stage releases the camera frames once it has chosen its own
    and the mesh tables once it has its arrays (the chain then reads them back for export
    instead of holding them through texture's peak); its outputs are those of the stage run
    on tables nobody releases."""
    rec = tmp_path / "scan.mcap"
    simulate_direct(rec, tmp_path / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=3.0, camera_scale=0.125, camera_fps=0.5, seed=4))
    work = tmp_path / "w"
    run_chain(rec, work, {}, to="mesh")
    producers = {"mesh_vertices": "mesh", "mesh_faces": "mesh", "frames": "decode",
                 "motor": "decode", "rig": "calibrate"}
    tables = {n: read_artifact(work / d / f"{n}.parquet")[0] for n, d in producers.items()}
    stage = get_stage("texture")
    kept = stage.run(dict(tables))
    handed = Inputs(dict(tables), set(tables))
    released = stage.run(handed)
    assert handed.released == {"frames", "mesh_vertices", "mesh_faces"}
    assert all(handed[n].num_rows == 0 and handed[n].schema == tables[n].schema
               for n in handed.released)
    assert handed["motor"].num_rows == tables["motor"].num_rows  # still read by nobody else
    for name in ("textured_faces", "texture_pages"):
        assert released.tables[name].equals(kept.tables[name]), name
