"""The runner: one stage with caching (:func:`execute`) and the chain (:func:`run_chain`).

A stage (:mod:`scanpipe.stage`, declared in :mod:`scanpipe.stages`) is a pure function over
Arrow tables and one frozen parameter model; it never opens files. The runner loads its
inputs, checks them and its outputs against their schemas (:mod:`scanpipe.schema`), computes
the output key, reuses outputs whose key is unchanged, and writes new ones with provenance —
here and nowhere else. Raw inputs (a recording, a point file) reach a stage as paths.

Writers hold the folder's lock (:func:`scanpipe.workdir.workdir_lock`) and replace a stage's
artifacts together (:func:`scanpipe.artifacts.write_together`).
"""

from __future__ import annotations

import difflib
import time
from collections.abc import Callable, Generator, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pyarrow as pa

from scanpipe import __version__
from scanpipe.artifacts import (
    artifact_key,
    background_commits,
    committing,
    file_key,
    library_versions,
    raise_commit_failure,
    read_artifact,
    read_provenance,
    recover,
    release_free_memory,
    settle_commits,
    with_provenance,
    write_artifact,
    write_together,
)
from scanpipe.errors import ArtifactError, ParameterError
from scanpipe.params import Params, validate
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stage import RAW_INPUTS, Inputs, Stage, StageResult
from scanpipe.stages import chain_stages, get_stage, registry
from scanpipe.workdir import DEFAULT_LOCK_WAIT_S, lock_root, workdir_lock

__all__ = ["InMemory", "RunRecord", "Stage", "StageResult", "chain_step", "chain_to",
           "check_recording", "execute", "get_stage", "iter_chain", "iter_locked_chain",
           "registry", "rig_override_artifact", "run_chain", "run_locked_chain",
           "validate_pipeline_params"]


@dataclass(frozen=True)
class RunRecord:
    """What :func:`execute` did for one stage."""

    stage: str
    key: str
    reused: bool
    seconds: float
    outputs: dict[str, Path]
    report: dict[str, Any]
    #: The output tables in memory, and the input tables the stage read, when the caller asked
    #: to keep them (``keep_tables``) and the stage ran; empty otherwise (read them from
    #: ``outputs``).
    tables: Mapping[str, pa.Table] = field(default_factory=dict, repr=False, compare=False)


def input_key(name: str, path: Path) -> str:
    """The key of one input: the hash of a raw file, or an artifact's recorded key."""
    if not path.exists():
        raise ArtifactError(f"{path}: not found (input {name!r})")
    if name in RAW_INPUTS:
        return file_key(path)
    recorded = read_provenance(path).get("key")
    return str(recorded) if recorded else file_key(path)


def output_paths(stage: Stage, out_dir: Path) -> dict[str, Path]:
    """Where a stage's output artifacts live in ``out_dir``."""
    return {name: out_dir / f"{name}.parquet" for name in stage.outputs}


def execute(
    stage: Stage,
    inputs: Mapping[str, Path],
    out_dir: Path,
    params: Params,
    progress: ProgressFn = no_progress,
    force: bool = False,
    replace_folder: bool = False,
    lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
    hold: InMemory | None = None,
) -> RunRecord:
    """Run ``stage`` on artifact files, reusing outputs whose key is unchanged.

    The outputs replace the previous ones together, under the lock of ``out_dir``'s workdir.
    ``replace_folder``: ``out_dir`` is the stage's own folder in a workdir (``W/<stage>/``),
    replaced as a whole; otherwise only the stage's files in ``out_dir`` are replaced.
    ``hold``: inputs already in memory, a computation replacing the stage's call, and whether
    to keep the outputs in memory (see :class:`InMemory`).
    """
    missing = [name for name in stage.inputs if name not in inputs]
    if missing:
        raise ArtifactError(f"stage {stage.name!r} needs inputs: {', '.join(missing)}")
    with workdir_lock(lock_root(out_dir, replace_folder), lock_wait_s):
        recover(out_dir.parent if replace_folder else out_dir)
        return _execute_locked(stage, inputs, out_dir, params, progress, force, replace_folder,
                               hold or InMemory())


@dataclass(frozen=True)
class InMemory:
    """What a caller that holds artifacts in memory gives :func:`execute`
    (``scanpipe run --follow``): nothing here changes a key or a written byte.

    ``tables``: inputs already in memory, equal to their files (not read again); ``compute``:
    computes the stage's result from its loaded inputs instead of the stage's own call — the
    same result by construction (the follow runner's decode of a stream decoded as it grew);
    ``keep_tables``: return the outputs in :attr:`RunRecord.tables`; ``keys``: the keys of raw
    inputs computed already from the same bytes (the file may not be at its path yet);
    ``release``: inputs the caller keeps no other reference to, which the stage may release
    while it runs (:func:`scanpipe.stage.release_inputs`; a released one is then not among
    the kept tables: a later stage that takes it reads it from its file);
    ``handed_over``: the caller keeps no other reference to ``tables`` (a dict): the stage
    takes them out of it (those it never took, a reused stage's, stay in it).
    """

    tables: Mapping[str, pa.Table] = field(default_factory=dict)
    keys: Mapping[str, str] = field(default_factory=dict)
    compute: Callable[[Mapping[str, Any]], StageResult] | None = None
    keep_tables: bool = False
    release: frozenset[str] = frozenset()
    handed_over: bool = False


def _execute_locked(stage: Stage, inputs: Mapping[str, Path], out_dir: Path, params: Params,
                    progress: ProgressFn, force: bool, replace_folder: bool,
                    hold: InMemory) -> RunRecord:
    keys = {name: hold.keys.get(name) or input_key(name, inputs[name]) for name in stage.inputs}
    libraries = library_versions(stage.libraries)
    params_data = params.model_dump(mode="json")
    key = artifact_key(stage.name, stage.version, params_data, keys, libraries)
    outputs = output_paths(stage, out_dir)
    if not force and _reusable(outputs, out_dir, key):
        report = read_provenance(next(iter(outputs.values()))).get("report", {})
        return RunRecord(stage.name, key, True, 0.0, outputs, report)

    # the stage may release the inputs named so, and those read here when the tables are not
    # kept (no one else holds them)
    read_here = {n for n in stage.inputs if n not in RAW_INPUTS and n not in hold.tables}
    loaded = Inputs({}, releasable=hold.release | (set() if hold.keep_tables else read_here))
    given = hold.tables
    take = given.pop if hold.handed_over and isinstance(given, dict) else given.get
    for name in stage.inputs:
        if name in RAW_INPUTS:
            loaded[name] = inputs[name]
        else:  # no local name keeps a table: the stage may release it
            loaded[name] = take(name, None)
            if loaded[name] is None:
                loaded[name] = read_artifact(inputs[name])[0]
    started = time.perf_counter()
    if hold.compute is not None:
        result = hold.compute(loaded)
        stage.check_result(result)
    else:  # inputs and outputs checked by schema; a files manifest is made while writing
        result = stage.call(loaded, params, progress, write_manifest=True)
    seconds = time.perf_counter() - started
    provenance = {
        "key": key,
        "stage": stage.name,
        "stage_version": stage.version,
        "params": params_data,
        "inputs": keys,
        "input_paths": {name: str(path) for name, path in inputs.items()},
        "libraries": libraries,
        "scanpipe": __version__,
        "created_ns": time.time_ns(),
        "seconds": round(seconds, 4),
        "report": result.report,
        "files": sorted(result.files),
    }
    tables = {name: (table, {**provenance, "artifact": name, "rows": table.num_rows})
              for name, table in result.tables.items()}
    manifest = result.manifest if result.manifest not in result.tables else None
    made = write_together(out_dir, stage.name, tables, result.files, replace_folder,
                          None if manifest is None else (manifest, {**provenance,
                                                                    "artifact": manifest}))
    if made is not None and manifest is not None:
        result.tables[manifest] = made
    # the record's time includes writing: a streamed file is made then
    seconds = time.perf_counter() - started
    kept = {name: with_provenance(table, tables[name][1]) if name in tables else table
            for name, table in result.tables.items()} if hold.keep_tables else {}
    if hold.keep_tables:  # and the inputs it read, as read (the next stage may take them
        # too), except those it released or narrowed: a later stage reads them from the file
        kept.update({name: loaded[name] for name in stage.inputs
                     if name not in RAW_INPUTS and name not in kept
                     and name not in loaded.released})
    return RunRecord(stage.name, key, False, seconds, outputs, result.report, kept)


def _reusable(outputs: Mapping[str, Path], out_dir: Path, key: str) -> bool:
    """True when every output exists with ``key`` and the files it lists exist too."""
    for path in outputs.values():
        if not path.exists():
            return False
        try:
            provenance = read_provenance(path)
        except ArtifactError:
            return False  # a damaged artifact is recomputed, not served
        if provenance.get("key") != key:
            return False
        if not all((out_dir / name).exists() for name in provenance.get("files", [])):
            return False
    return True


def validate_pipeline_params(
    stages: Sequence[Stage], data: Mapping[str, Any], source: str = "parameters"
) -> dict[str, Params]:
    """Parameters for every stage from ``{stage: {key: value}}``, every problem reported at once.

    Unknown stage names are errors too, with the closest valid names.
    """
    names = [s.name for s in stages]
    problems: list[str] = []
    for unknown in sorted(set(data) - set(names)):
        close = difflib.get_close_matches(unknown, names, n=2)
        hint = f"did you mean {', '.join(close)}?; " if close else ""
        problems.append(f"unknown stage {unknown!r} ({hint}stages: {', '.join(names)})")
    result: dict[str, Params] = {}
    for stage in stages:
        own = data.get(stage.name, {})
        for name in stage.borrows:
            if isinstance(own, Mapping) and name in own:
                problems.append(f"{stage.name}.{name}: set by the run from its {name} "
                                f"parameters; set {name}.KEY instead")
        try:
            result[stage.name] = validate(stage.params, data.get(stage.name, {}), source,
                                          prefix=f"{stage.name}.")
        except ParameterError as err:
            problems.extend(err.problems)
    if problems:
        raise ParameterError(problems, source)
    return result


def run_chain(
    recording: Path,
    workdir: Path,
    params: Mapping[str, Params],
    stages: Sequence[Stage] | None = None,
    to: str | None = None,
    force: bool = False,
    rig_override: Path | None = None,
    progress: ProgressFn = no_progress,
    on_stage: Callable[[RunRecord], None] | None = None,
    lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
) -> list[RunRecord]:
    """Run the stages in order from a recording, each into ``workdir/<stage>/``.

    Each input is taken from the nearest upstream stage that produces it. A stage is reused
    when its output key is unchanged (see :func:`execute`); change one parameter and that stage
    and what follows it rerun. ``rig_override`` replaces the rig that decode found in the
    recording (a corrected calibration) for every later stage.

    The whole chain holds the workdir's lock, so a second run on the same workdir waits up to
    ``lock_wait_s`` seconds (then :class:`ArtifactError`) and two runs never mix artifacts.
    """
    return _collect(iter_chain(recording, workdir, params, stages, to, force, rig_override,
                               progress, lock_wait_s), on_stage)


def _collect(steps: Generator[RunRecord, None, None],
             on_stage: Callable[[RunRecord], None] | None) -> list[RunRecord]:
    """Every record of a chain run one stage at a time, each given to ``on_stage`` too."""
    records: list[RunRecord] = []
    with closing(steps):
        for record in steps:
            records.append(record)
            if on_stage is not None:
                on_stage(record)
    return records


def iter_chain(
    recording: Path,
    workdir: Path,
    params: Mapping[str, Params],
    stages: Sequence[Stage] | None = None,
    to: str | None = None,
    force: bool = False,
    rig_override: Path | None = None,
    progress: ProgressFn = no_progress,
    lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
) -> Generator[RunRecord, None, None]:
    """:func:`run_chain` one stage at a time: each ``next()`` runs the next stage and gives its
    record (a Ray batch runs each stage as its own task in one worker this way). The workdir's
    lock and the background commits are held from the first ``next()`` until the iterator is
    exhausted — which waits until every stage folder is in place and raises a failed commit —
    or closed (always close it: :func:`contextlib.closing`)."""
    chain = chain_to(stages, to)
    check_recording(recording)
    if rig_override is not None:
        from scanpipe.rig import load_rig

        load_rig(rig_override)  # a bad rig file is refused before the workdir is touched
    with workdir_lock(workdir, lock_wait_s), background_commits():
        yield from iter_locked_chain(chain, recording, workdir, params, force, rig_override,
                                     progress)


def chain_to(stages: Sequence[Stage] | None, to: str | None) -> list[Stage]:
    """The stages of a chain from a recording (``stages``, else the registry's), up to ``to``."""
    chain = list(stages if stages is not None else chain_stages("recording"))
    names = [s.name for s in chain]
    if to is not None and to not in names:
        raise ParameterError([f"--to {to!r}: not a stage; stages: {', '.join(names)}"], "run")
    return chain if to is None else chain[: names.index(to) + 1]


def run_locked_chain(chain: Sequence[Stage], recording: Path, workdir: Path,
                      params: Mapping[str, Params], force: bool, rig_override: Path | None,
                      progress: ProgressFn, on_stage: Callable[[RunRecord], None] | None,
                      compute: Mapping[str, Callable[[Mapping[str, Any]], StageResult]]
                      | None = None, in_memory: bool = False,
                      raw_keys: Mapping[str, str] | None = None) -> list[RunRecord]:
    """The chain, while the caller holds the workdir's lock (:func:`iter_locked_chain`, each
    record also given to ``on_stage``)."""
    return _collect(iter_locked_chain(chain, recording, workdir, params, force, rig_override,
                                      progress, compute, in_memory, raw_keys), on_stage)


def iter_locked_chain(chain: Sequence[Stage], recording: Path, workdir: Path,
                      params: Mapping[str, Params], force: bool, rig_override: Path | None,
                      progress: ProgressFn,
                      compute: Mapping[str, Callable[[Mapping[str, Any]], StageResult]]
                      | None = None, in_memory: bool = False,
                      raw_keys: Mapping[str, str] | None = None
                      ) -> Generator[RunRecord, None, None]:
    """The chain, one stage per ``next()``, while the caller holds the workdir's lock.
    ``compute``: a stage's result computed otherwise (see :class:`InMemory`); ``in_memory``:
    each stage's outputs are handed to every later stage in memory as well as written
    (``scanpipe run --follow``), not read back.

    Otherwise the outputs a stage computed, and the inputs it read, are handed in memory to
    the *next* stage only (as well as written): it would read them back at once, which cost
    ~2 s of CPU per lab-scale chain (points into filter and mesh, the mesh into texture,
    texture's outputs, the mesh and the camera frames into export).
    A table is never kept across a stage that does not take it, so no stage holds more than
    it would have read: the chain's peak memory stays its largest stage's. A stage may
    release a table it is done with although the next stage takes it too (the texture stage
    its frames and mesh tables): that stage then reads it from its file. The same tables
    either way (``run --follow`` relies on it and its tests compare every artifact)."""
    available: dict[str, Path] = {"recording": recording}
    tables: dict[str, pa.Table] = {}
    override_path = rig_override_artifact(rig_override, workdir) if rig_override else None
    rig_made = False
    # the key of every artifact this chain produced or reused (its provenance's "key" is its
    # stage's key): a stage folder may still be being committed (background_commits)
    keys: dict[str, str] = dict(raw_keys or {})
    for index, stage in enumerate(chain):
        raise_commit_failure()  # a set failed to commit: stop before computing more
        next_inputs = set(chain[index + 1].inputs) if index + 1 < len(chain) else set()
        if any(committing(available[n]) for n in stage.inputs
               if n not in tables and n in available):
            settle_commits()  # a file to read is not in place yet
        # handed over, not shared: a stage may release an input while it runs (what the next
        # stage takes comes back in the record's tables unless the stage released it)
        hold = InMemory(tables={n: tables.pop(n) for n in stage.inputs if n in tables},
                        compute=(compute or {}).get(stage.name),
                        keep_tables=in_memory or bool(
                            next_inputs & {*stage.outputs, *stage.inputs}),
                        keys={n: k for n, k in keys.items() if n in stage.inputs},
                        # a stage may release any table handed to it: one the next stage
                        # takes too is then read back from its file (texture lets the camera
                        # frames and the mesh tables go after its first steps; export reads
                        # them again: ~0.4 GB less at texture's peak for ~0.3 s of reading)
                        release=frozenset() if in_memory else frozenset(
                            n for n in stage.inputs if n not in RAW_INPUTS),
                        handed_over=True)
        record = chain_step(stage, available, workdir, params, force, progress, hold=hold)
        tables.update(hold.tables)  # what the stage did not take (reused): as before
        available.update(record.outputs)
        keys.update(dict.fromkeys(record.outputs, record.key))
        for name in record.outputs:  # reused outputs are read back from their files
            tables.pop(name, None)
        tables.update(record.tables)
        # The override replaces the recording's rig (decode's), not a rig a later stage
        # derives from it (calibrate's).
        if override_path is not None and "rig" in record.outputs and not rig_made:
            from scanpipe.rig import load_rig
            from scanpipe.stages.decode import check_rig_override

            assert rig_override is not None  # decode reads the stored rig: the same scanner?
            check_rig_override(record.report, load_rig(rig_override), f"--rig {rig_override}")
            available["rig"] = override_path
            tables.pop("rig", None)
            keys.pop("rig", None)  # the override's own key, from its file
        rig_made = rig_made or "rig" in record.outputs
        needed = ({n for later in chain[index + 1:] for n in later.inputs} if in_memory
                  else next_inputs)
        tables = {n: t for n, t in tables.items() if n in needed}
        record = replace(record, tables={})  # the chain's records hold no tables
        release_free_memory()
        yield record


def check_recording(recording: Path) -> None:
    """Refuse what is not a recording file (a missing path, a ROS 2 bag folder) in one line."""
    if recording.is_dir() and (recording / "metadata.yaml").is_file():
        raise ArtifactError(f"{recording}: is a ROS 2 bag, not a scanpipe recording; convert "
                            f"it with: scanpipe import-bag {recording} --out REC.mcap")
    if not recording.is_file():
        raise ArtifactError(f"{recording}: recording not found")


def chain_step(stage: Stage, available: Mapping[str, Path], workdir: Path,
               params: Mapping[str, Params], force: bool = False,
               progress: ProgressFn = no_progress,
               lock_wait_s: float = DEFAULT_LOCK_WAIT_S, hold: InMemory | None = None
               ) -> RunRecord:
    """One stage of the chain into ``workdir/<stage>/``, its inputs taken from ``available``
    (artifact name → path of the nearest upstream producer). :func:`run_chain` calls it per
    stage (so does a Ray batch's worker, through :func:`iter_chain`)."""
    missing = [n for n in stage.inputs if n not in available]
    if missing:
        raise ArtifactError(f"stage {stage.name!r} needs {', '.join(missing)}, "
                            "which no earlier stage produces")
    return execute(stage, {n: available[n] for n in stage.inputs}, workdir / stage.name,
                   stage_params(stage, params), progress, force,
                   replace_folder=True, lock_wait_s=lock_wait_s, hold=hold)


def stage_params(stage: Stage, params: Mapping[str, Params]) -> Params:
    """A stage's parameters in a run: its own, with the parameters it borrows from other
    stages (:attr:`Stage.borrows`) filled from the run's (their defaults when not given)."""
    own = params.get(stage.name) or stage.params()
    if not stage.borrows:
        return own
    return own.model_copy(update={name: params.get(name) or get_stage(name).params()
                                  for name in stage.borrows})


def rig_override_artifact(path: Path, workdir: Path) -> Path:
    """The rig file as a ``rig`` artifact in ``workdir/rig/``, keyed by its content."""
    from scanpipe.rig import load_rig, rig_table, rig_to_toml

    rig = load_rig(path)
    out = workdir / "rig" / "rig.parquet"
    key = artifact_key("rig", 1, {"toml": rig_to_toml(rig)}, {}, {})
    if not (out.exists() and read_provenance(out).get("key") == key):
        write_artifact(out, rig_table(rig), {"key": key, "stage": "rig", "source": str(path)})
    return out
