"""What a stage is: a pure function over Arrow tables and one frozen parameter model.

This module sits below the stages (they import it) and below the runner (``pipeline.py``),
so nothing here imports a stage. A stage declares its inputs and outputs by artifact name
(:mod:`scanpipe.schema`); raw files that are not artifacts (a recording, a point file from
another tool) reach a stage as paths and are named in :data:`RAW_INPUTS`.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

import pyarrow as pa

from scanpipe.artifacts import (
    PROVENANCE_KEY,
    FileData,
    file_digest,
    files_manifest,
    release_free_memory,
)
from scanpipe.errors import ArtifactError
from scanpipe.params import Params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.schema import (
    ARTIFACTS,
    CRS_KEY,
    OFFSET_KEY,
    ArtifactSchema,
    artifact_schema,
    common_crs,
    common_offset,
    with_crs,
    with_offset,
)

#: Inputs that are raw files, not Parquet artifacts: passed as paths, keyed by their bytes.
RAW_INPUTS = frozenset({"recording", "point_file", "profile_file"})


@dataclass
class StageResult:
    """What a stage returns: output tables by artifact name, extra files (bytes, or
    :class:`scanpipe.artifacts.Pieces` / :class:`scanpipe.artifacts.Stream` for a large one),
    and a report."""

    tables: dict[str, pa.Table]
    report: dict[str, Any] = field(default_factory=dict)
    files: dict[str, FileData] = field(default_factory=dict)
    #: An output artifact that is the manifest of ``files`` (name, size, SHA-256 of each:
    #: :func:`scanpipe.artifacts.files_manifest`), made as they are written, so a streamed
    #: file is formatted once; it is then not in ``tables`` (:meth:`Stage.call` makes it in
    #: memory unless the runner writes the files).
    manifest: str | None = None


def complete_manifest(result: StageResult) -> None:
    """Put the manifest of ``result``'s files into its tables when the stage left it to the
    writer (streamed files are made once more, to hash them)."""
    if result.manifest is not None and result.manifest not in result.tables:
        result.tables[result.manifest] = files_manifest(
            {name: file_digest(data) for name, data in result.files.items()})


def carry_offset(stage: Stage, inputs: Mapping[str, Any], result: StageResult) -> None:
    """Pass the inputs' georeference offset (:data:`scanpipe.schema.OFFSET_KEY`) and
    coordinate system (:data:`~scanpipe.schema.CRS_KEY`) on to every output table that does
    not set its own, so no stage drops them; inputs that differ are refused (one line naming
    both)."""
    given = [(n, t) for n, t in inputs.items() if n not in RAW_INPUTS and isinstance(t, pa.Table)]
    for name, table in given:
        refuse_uncarried_offset(f"stage {stage.name!r}: input {name}", table)
    where = f"stage {stage.name!r}"
    with_key = [(f"input {n}", t) for n, t in given if OFFSET_KEY in (t.schema.metadata or {})]
    if with_key:
        offset = common_offset(with_key, where)
        for name, table in result.tables.items():
            if OFFSET_KEY not in (table.schema.metadata or {}):
                result.tables[name] = with_offset(table, offset)
    with_key = [(f"input {n}", t) for n, t in given if CRS_KEY in (t.schema.metadata or {})]
    if with_key:
        crs = common_crs(with_key, where)
        for name, table in result.tables.items():
            if CRS_KEY not in (table.schema.metadata or {}):
                result.tables[name] = with_crs(table, crs)


def refuse_uncarried_offset(where: str, table: pa.Table) -> None:
    """Refuse points that ``import-points`` shifted before the offset travelled with them
    (its report names an ``offset_m``, the table carries none): everything made from them
    would land at the shifted coordinates."""
    if OFFSET_KEY in (table.schema.metadata or {}):
        return
    raw = (table.schema.metadata or {}).get(PROVENANCE_KEY)
    try:
        record = json.loads(raw) if raw is not None else {}
    except ValueError:
        return
    if not isinstance(record, dict):
        return
    report = record.get("report")
    offset = report.get("offset_m") if isinstance(report, dict) else None
    if record.get("stage") == "import-points" and isinstance(offset, list) and any(offset):
        raise ArtifactError(f"{where}: imported by an older scanpipe that shifted it by "
                            f"offset_m {offset} (rig frame) without carrying the offset; what "
                            "is made from it would land at the shifted coordinates: re-run "
                            "import-points, then the later stages")


StageFn = Callable[[Mapping[str, Any], Any, ProgressFn], StageResult]


class Inputs(dict[str, Any]):
    """A stage's inputs as the runner hands them over: the stage may :func:`release_inputs`
    a table once it is done with it, so its memory goes back before the stage ends (the
    texture stage's camera frames once it has chosen its own and the mesh tables once it has
    its arrays; the export stage's frames after colouring the points, its tables once its
    models are built) instead of at the stage's end. A released table is replaced by an empty
    table of its schema (its metadata, provenance and georeference offset kept:
    :func:`carry_offset` and provenance still read them). A later stage that takes a released
    (or narrowed) table reads it back from its file: the runner hands on only what
    :attr:`released` does not name."""

    def __init__(self, tables: Mapping[str, Any], releasable: Collection[str] = ()) -> None:
        super().__init__(tables)
        #: The inputs the caller keeps no other reference to (a later stage that takes one
        #: reads it from its file if the stage released it).
        self.releasable = frozenset(releasable)
        #: The inputs the stage released or narrowed: no longer the artifact as written.
        self.released: set[str] = set()


def narrow_input(inputs: Mapping[str, Any], name: str, columns: Collection[str]) -> bool:
    """Keep only ``columns`` of an input table the stage reads nothing else of, where its
    caller handed it over (as :func:`release_inputs`; schema metadata kept), and hand the
    freed memory back; returns whether any column went."""
    table = inputs.get(name)
    if (not isinstance(inputs, Inputs) or name not in inputs.releasable
            or not isinstance(table, pa.Table)):
        return False
    kept = [c for c in table.column_names if c in columns]
    if len(kept) == table.num_columns:
        return False
    inputs[name] = table.select(kept)
    inputs.released.add(name)
    del table
    release_free_memory()
    return True


def release_inputs(inputs: Mapping[str, Any], *names: str) -> bool:
    """Drop the named input tables a stage is done with, where its caller handed them over
    (:attr:`Inputs.releasable`; a plain mapping — a notebook's, a test's — is left as it is),
    and hand the freed memory back; returns whether any was released. The stage must hold no
    other reference to a table's data for its memory to go."""
    if not isinstance(inputs, Inputs):
        return False
    released = False
    for name in names:
        table = inputs.get(name)
        if name in inputs.releasable and isinstance(table, pa.Table) and table.num_rows:
            inputs[name] = table.schema.empty_table()
            inputs.released.add(name)
            released = True
    if released:
        release_free_memory()
    return released


@dataclass(frozen=True)
class Stage:
    """A stage declared once: name, version, parameters, inputs, outputs, function."""

    name: str
    version: int
    params: type[Params]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    func: StageFn
    description: str
    #: Import names of libraries whose version can change the result.
    libraries: tuple[str, ...] = ("numpy", "pyarrow")
    #: Schemas of artifacts that only this stage's world knows (a plugin, a test's toy
    #: stages); the product's artifacts are in :data:`scanpipe.schema.ARTIFACTS`.
    schemas: tuple[ArtifactSchema, ...] = ()
    #: Other stages whose parameters this one uses (its model holds each under a field of
    #: that stage's name): the runner fills them with the run's own, so they enter this
    #: stage's key, and refuses them set under this stage.
    borrows: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.outputs:
            raise ValueError(f"stage {self.name!r} must declare at least one output artifact")
        known = {*ARTIFACTS, *RAW_INPUTS, *(s.name for s in self.schemas)}
        unknown = [n for n in (*self.inputs, *self.outputs) if n not in known]
        if unknown:
            raise ValueError(f"stage {self.name!r}: {unknown} are neither artifacts "
                             f"({', '.join(ARTIFACTS)}) nor raw inputs")

    def schema(self, name: str) -> ArtifactSchema:
        """The schema of one of this stage's artifacts."""
        for own in self.schemas:
            if own.name == name:
                return own
        return artifact_schema(name)

    def check_inputs(self, inputs: Mapping[str, Any]) -> None:
        """Every declared input is there, and every table matches its artifact's schema."""
        missing = [n for n in self.inputs if n not in inputs]
        if missing:
            raise ArtifactError(f"stage {self.name!r} needs inputs: {', '.join(missing)}")
        for name in self.inputs:
            if name not in RAW_INPUTS:
                self.schema(name).check(inputs[name])

    def check_result(self, result: StageResult) -> None:
        """The stage produced exactly its declared outputs (its files' manifest may be left
        to the writer: :attr:`StageResult.manifest`), each matching its schema."""
        made = set(result.tables)
        if result.manifest is not None and result.manifest not in made:
            made.add(result.manifest)
        if made != set(self.outputs):
            raise ArtifactError(f"stage {self.name!r} produced {sorted(result.tables)}, "
                                f"declared {list(self.outputs)}")
        for name, table in result.tables.items():
            self.schema(name).check(table, where=f"{self.name} output {name}")

    def call(self, inputs: Mapping[str, Any], params: Params,
             progress: ProgressFn = no_progress, write_manifest: bool = False) -> StageResult:
        """Run the function with the inputs and the result checked against the schemas.
        ``write_manifest``: the caller writes the files and makes their manifest then
        (:func:`scanpipe.artifacts.write_together`); otherwise it is made here, in memory."""
        self.check_inputs(inputs)
        result = self.func(inputs, params, progress)
        self.check_result(result)
        carry_offset(self, inputs, result)
        if not write_manifest:
            complete_manifest(result)
        return result

    def run(self, inputs: Mapping[str, Any], params: Params | None = None,
            progress: ProgressFn = no_progress, **overrides: Any) -> StageResult:
        """Run in memory (notebooks): ``params`` or keyword overrides of the defaults."""
        chosen = params if params is not None else self.params(**overrides)
        return self.call(inputs, chosen, progress)
