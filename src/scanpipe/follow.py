"""Processing while recording: ``scanpipe run REC --follow``.

The follower tails a recording while its writer appends to it (``scanpipe record`` writes to
its name; ``scanpipe simulate`` to a temporary name beside it, renamed when it ends) and works
as the data arrives, so the model is ready seconds after the last profile:

- **incremental** while the scan runs: the MCAP records completed since the last poll are parsed
  (:class:`~scanpipe.recording.reader.RecordingTail`: new chunks only, in the batch reader's
  order) and the new scanner bytes are fed to one stream decoder (the decoders are split
  invariant: any cut of a stream decodes the same); a live preview assembles, filters and
  grid-meshes the new platform positions plus a seam of the previous ones
  (:class:`LivePreview`), for the coverage, point and face counts shown while recording.
- **the model** when the recorder writes its ``scan_end`` event (the scanner stream stopped;
  the platform's way back to the start still to come): the chain up to the mesh on the
  recording so far, in memory, the mesh written to ``W/follow/model.ply``
  (:class:`ScanEndModel`).
- **finalised** when the end record arrives, by the batch computations, because they use the
  whole scan: decode's tables (the device clock's unwrap and fit, the frame counter's unwrap,
  the report) from the frames decoded already; assemble (the clock fit that places every
  profile in time, the step/continuous choice, the grid's layout); filter (double coverage pairs
  a position with the one 180° away; the outlier and voxel filters are global); mesh (the
  stride chosen from the point count, the seam closed between the last and first position,
  the clean-up's small-component removal, one vertex numbering). A stage whose inputs are
  then bit for bit those it had at ``scan_end`` takes that result. Then the rest of the chain.

So the artifacts equal a batch ``scanpipe run`` on the finished file, keys included: a later
``scanpipe run`` on the same workdir reuses them. Anything the tail cannot read as the batch
reader would (damage, a stream that arrives out of order, a dialect the first bytes do not
decide) makes the follower read the finished file as the batch does. A file that stops
growing without an end record (a killed recorder) is processed as it is after
``timeout_s`` without growth, with a warning.
"""

from __future__ import annotations

import copy
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from scanpipe.artifacts import PROVENANCE_KEY, stream_key
from scanpipe.errors import ProtocolError, RecordingError, ScanpipeError, StageError, UsageError
from scanpipe.meshing.mesh import Mesh
from scanpipe.params import Params
from scanpipe.pipeline import (
    RunRecord,
    chain_to,
    check_recording,
    run_locked_chain,
    stage_params,
)
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.protocol.registry import (
    DETECT_BYTES,
    DecodedFrame,
    Dialect,
    StreamDecoder,
    detect_dialect,
    get_dialect,
    resolve_dialect,
)
from scanpipe.recording.reader import (
    Recording,
    RecordingTail,
    StreamData,
    read_recording,
    writer_finished,
)
from scanpipe.recording.schemas import RX
from scanpipe.recording.writer import RIG_KEY, RIG_METADATA, SCAN_END_EVENT, SESSION_METADATA
from scanpipe.rig import Rig
from scanpipe.stage import Stage, StageResult
from scanpipe.stages.decode import DecodedStream, DecodeParams, decode_recording
from scanpipe.workdir import DEFAULT_LOCK_WAIT_S, workdir_lock

#: Seconds between two looks at the file.
DEFAULT_POLL_S = 0.2
#: Seconds without growth (or without the file appearing) before the follower stops waiting.
DEFAULT_FOLLOW_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class FollowStatus:
    """What the follower has seen so far (its progress lines)."""

    elapsed_s: float
    file_bytes: int
    profiles: int
    motor_states: int
    #: The live preview: platform positions assembled, the share of the planned platform range
    #: they cover (None when the recording does not say), points kept and faces meshed.
    positions: int = 0
    coverage: float | None = None
    points: int = 0
    faces: int = 0
    lag_s: float | None = None  # wall clock now minus the newest profile's receive time


@dataclass
class FollowResult:
    """What :func:`follow_chain` did."""

    recording: Path
    records: list[RunRecord]
    #: True when the writer finished the file (its end record was read); False when it stopped
    #: growing without one and was processed as it was.
    complete: bool
    #: How decode was finalised: ``incremental`` (the stream decoded while it grew) or
    #: ``batch`` (the finished file read and decoded again) and why.
    decode: str
    #: Host clock (ns) of the newest profile received, and when the mesh was written.
    last_profile_ns: int | None = None
    model_ready_ns: int | None = None
    end_seen_ns: int | None = None
    scan_end_seen_ns: int | None = None
    #: The stages whose results at the scan's end were the batch results (equal inputs).
    reused_from_scan_end: list[str] = field(default_factory=list)
    #: The stages that ran again, with the inputs (and their columns) that had changed.
    changed_after_scan_end: dict[str, dict[str, list[str]]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    preview: dict[str, Any] = field(default_factory=dict)
    #: Per poll that found new profiles: seconds from the newest one's receipt to reading it.
    visible_lag_s: list[float] = field(default_factory=list)

    @property
    def model_latency_s(self) -> float | None:
        """Seconds from the last profile's receipt to the written mesh."""
        if self.last_profile_ns is None or self.model_ready_ns is None:
            return None
        return (self.model_ready_ns - self.last_profile_ns) / 1e9


def temporary_names(recording: Path) -> list[Path]:
    """The temporary files a writer of ``recording`` may be writing now, newest first:
    ``scanpipe simulate`` writes ``.<name>.<random>.tmp`` beside it
    (:func:`scanpipe.artifacts.atomic_path`) and renames it when it ends."""
    found = list(recording.parent.glob(f".{recording.name}.*.tmp"))
    return sorted(found, key=lambda p: p.stat().st_mtime if p.exists() else 0, reverse=True)


def open_growing(recording: Path, timeout_s: float, poll_s: float = DEFAULT_POLL_S
                 ) -> tuple[Path, IO[bytes]]:
    """The file to tail and an open handle on it: the temporary file of a writer that will
    rename it to ``recording`` (first: it replaces an older file of that name), or
    ``recording`` itself; waits up to ``timeout_s`` for either to appear."""
    check_recording_shape(recording)
    deadline = time.monotonic() + timeout_s
    while True:
        for path in [*temporary_names(recording), recording]:
            try:
                return path, path.open("rb")
            except FileNotFoundError:
                continue
            except OSError as err:
                raise RecordingError(f"{path}: cannot be read ({err.strerror or err})"
                                     ) from None
        if time.monotonic() >= deadline:
            raise RecordingError(
                f"{recording}: no recording appeared within {timeout_s:g} s (--follow waits for "
                f"the file, or a writer's temporary .{recording.name}.*.tmp beside it; start "
                "the recording first or raise --follow-timeout)")
        time.sleep(poll_s)


def check_recording_shape(recording: Path) -> None:
    """Refuse in one line what cannot become a recording file (a folder, a ROS 2 bag)."""
    if recording.is_dir():
        if (recording / "metadata.yaml").is_file():
            check_recording(recording)  # names a ROS 2 bag as one, with the way in
        raise RecordingError(f"{recording}: is a directory, expected an MCAP recording")


class StreamFollower:
    """The scanner stream decoded as it grows: the bytes of each new chunk go to one decoder.

    ``valid`` turns False when what was fed could differ from what the batch decode reads (a
    chunk arriving out of sequence order, a dialect the first bytes do not decide); the
    finished file is then decoded as a whole.
    """

    def __init__(self, params: DecodeParams) -> None:
        self.params = params
        self.dialect: Dialect | None = None
        self.decoder: StreamDecoder | None = None
        self.frames: list[DecodedFrame] = []
        self.profiles = 0
        self.fed_bytes = 0
        self.last_seq = -1
        self.valid = True
        self.why = ""
        self.newest_receive_ns: int | None = None  # host time of the newest complete frame
        self._chunk_end: list[int] = []
        self._chunk_ns: list[int] = []
        self._pending = bytearray()

    def receive_times(self) -> StreamData:
        """The chunks fed so far, for the frames' receive times (without their bytes)."""
        return StreamData(b"", np.array(self._chunk_end, np.int64),
                          np.array(self._chunk_ns, np.int64))

    def add(self, parts: list[tuple[int, int, bytes]]) -> list[DecodedFrame]:
        """Feed new chunks ``(seq, log time, bytes)``; the frames they completed."""
        new: list[DecodedFrame] = []
        for seq, log_time_ns, data in parts:
            if not self.valid:
                return new
            if seq <= self.last_seq:
                self._give_up(f"scanner chunk {seq} arrived after chunk {self.last_seq}")
                return new
            self.last_seq = seq
            self.fed_bytes += len(data)
            if self.decoder is None:
                self._pending += data
                self._choose_dialect()
                if self.decoder is None:
                    continue
                completed = self.decoder.feed_frames(bytes(self._pending))
                self._pending = bytearray()
            else:
                completed = self.decoder.feed_frames(data)
            self._chunk_end.append(self.fed_bytes)
            self._chunk_ns.append(log_time_ns)
            if completed:  # the chunk that completes a frame gives its receive time
                self.newest_receive_ns = log_time_ns
                new += completed
        self.frames += new
        self.profiles += sum(len(f.profiles) for f in new)
        return new

    def _give_up(self, why: str) -> None:
        self.valid, self.why = False, why
        self.decoder = None
        self.frames = []
        self._pending = bytearray()

    def _choose_dialect(self) -> None:
        """The dialect as soon as the bytes so far name one; :meth:`finish` checks that the
        whole stream names the same (else the batch decode runs)."""
        if self.params.dialect != "auto":
            self._start(get_dialect(self.params.dialect))
            return
        try:
            self._start(get_dialect(detect_dialect(bytes(self._pending))))
        except ProtocolError:
            if len(self._pending) > DETECT_BYTES[-1]:  # the batch detection looks no further
                self._give_up("the first bytes of the scanner stream name no dialect")

    def _start(self, dialect: Dialect) -> None:
        self.dialect = dialect
        self.decoder = StreamDecoder(dialect, self.params.checksum, self.params.max_frame_bytes)

    def snapshot(self) -> DecodedStream | None:
        """The stream so far, decoded as if it ended here (the live decoder goes on)."""
        if not self.valid or self.decoder is None or self.dialect is None:
            return None
        decoder = copy.deepcopy(self.decoder)
        return DecodedStream(self.dialect, decoder, self.frames + decoder.finish_frames())

    def finish(self, data: bytes) -> DecodedStream | None:
        """The whole stream decoded, when it equals the batch decode of ``data`` (the finished
        recording's scanner bytes); None when the batch decode must run (and why in ``why``)."""
        if not self.valid:
            return None
        if self.fed_bytes != len(data):
            self.why = f"{self.fed_bytes} scanner bytes followed, {len(data)} in the file"
            return None
        if self.decoder is None or self.dialect is None:
            self.why = "too few scanner bytes to decide the dialect while recording"
            return None
        try:
            if resolve_dialect(self.params.dialect, data).name != self.dialect.name:
                self.why = "the whole stream names another dialect"
                return None
        except ProtocolError:
            self.why = "the whole stream names no dialect"
            return None
        frames = self.frames + self.decoder.finish_frames()
        return DecodedStream(self.dialect, self.decoder, frames)


def _session_part(tail: RecordingTail) -> str | None:
    return tail.metadata.get(SESSION_METADATA, {}).get("part")


def follow_chain(
    recording: Path,
    workdir: Path,
    params: Mapping[str, Params],
    stages: list[Stage] | None = None,
    to: str | None = None,
    force: bool = False,
    rig_override: Path | None = None,
    progress: ProgressFn = no_progress,
    on_stage: Callable[[RunRecord], None] | None = None,
    on_status: Callable[[FollowStatus], None] | None = None,
    lock_wait_s: float = DEFAULT_LOCK_WAIT_S,
    timeout_s: float = DEFAULT_FOLLOW_TIMEOUT_S,
    poll_s: float = DEFAULT_POLL_S,
    preview: bool = True,
) -> FollowResult:
    """Follow a recording being written and run the chain on it (see the module docstring).

    Returns when the chain has run on the finished recording. ``on_status`` is called after
    every poll that found new data. The workdir's lock is held from the start.
    """
    chain = chain_to(stages, to)
    if not timeout_s > 0:
        raise UsageError(f"--follow-timeout {timeout_s!r}: must be > 0 (seconds)")
    if not poll_s > 0:
        raise UsageError(f"poll_s {poll_s!r}: must be > 0 (seconds)")
    if rig_override is not None:
        from scanpipe.rig import load_rig

        load_rig(rig_override)
    decode_params = params.get("decode") or DecodeParams()
    assert isinstance(decode_params, DecodeParams)
    with workdir_lock(workdir, lock_wait_s):
        _warm_up(chain)
        source, handle = open_growing(recording, timeout_s, poll_s)
        with handle:
            tail = RecordingTail(recording, handle)
            stream = StreamFollower(decode_params)
            live = LivePreview(params) if preview and _preview_possible(chain) else None
            model = ScanEndModel(chain, params, rig_override, workdir / FOLLOW_FOLDER)
            result = _follow(tail, stream, live, recording, source, handle, timeout_s,
                             poll_s, on_status, lambda: model.build(tail, stream))
            if model.ready_ns is not None:
                result.model_ready_ns = model.ready_ns
            compute = model.reuse()
            if result.complete and tail.stuck is None:
                whole = tail.recording()
                decoded = stream.finish(whole.stream("scanner", RX).data)
                if decoded is not None:
                    result.decode = "incremental"
                    compute["decode"] = _decode_from(whole, decode_params, decoded)
                else:
                    result.decode = f"batch ({stream.why})"
            else:
                result.decode = "batch (" + (f"the tail stopped: {tail.stuck}" if tail.stuck
                                             else "no end record") + ")"
            if "decode" not in compute:
                # The file as the batch reads it, through the handle: the writer may be
                # renaming it, and a file of the final name may be an older recording.
                compute["decode"] = _decode_from(read_recording(recording, handle),
                                                 decode_params, None)
            keys = {"recording": stream_key(handle)}
        if live is not None:
            result.preview = live.summary()
            if live.problem is not None:
                result.warnings.append(f"the live preview stopped: {live.problem}")

        def noted(record: RunRecord) -> None:
            if record.stage == "mesh" and result.model_ready_ns is None:
                result.model_ready_ns = time.time_ns()
            if on_stage is not None:
                on_stage(record)

        result.records = run_locked_chain(chain, recording, workdir, params, force,
                                           rig_override, progress, noted, compute=compute,
                                           in_memory=True, raw_keys=keys)
    if source != recording:
        result.warnings += _check_renamed(recording, source, timeout_s, poll_s)
    result.reused_from_scan_end = model.reused
    result.changed_after_scan_end = model.changed
    if model.problem is not None:
        result.warnings.append(f"the model at the scan's end failed: {model.problem}")
    return result


#: The folder of a workdir where the follower writes the model at the scan's end.
FOLLOW_FOLDER = "follow"
#: The model at the scan's end, in that folder (binary PLY: vertices, normals, faces).
MODEL_FILE = "model.ply"


class ScanEndModel:
    """The model as soon as the recorder says the scan has ended (the ``scan_end`` event), while
    it still records the platform's way back to the start: the chain up to the mesh run in
    memory on what was recorded so far, the mesh written to ``folder/model.ply``.

    When the recording ends the chain runs on the finished file as the batch does; a stage
    whose inputs are then identical to the ones it had here (the way back adds motor states,
    so decode and assemble run again; the points they give are normally the same) takes its
    result from here: the same pure function of the same inputs (:meth:`reuse`).
    """

    def __init__(self, chain: list[Stage], params: Mapping[str, Params],
                 rig_override: Path | None, folder: Path) -> None:
        names = [s.name for s in chain]
        self.chain = chain[: names.index("mesh") + 1] if "mesh" in names else chain
        self.params, self.rig_override, self.folder = params, rig_override, folder
        self.results: dict[str, StageResult] = {}
        self.inputs: dict[str, dict[str, Any]] = {}
        self.ready_ns: int | None = None
        self.problem: str | None = None
        self.reused: list[str] = []
        #: Per stage that ran again: the inputs whose columns changed after the scan's end.
        self.changed: dict[str, dict[str, list[str]]] = {}

    def build(self, tail: RecordingTail, stream: StreamFollower) -> None:
        """Run the chain up to the mesh on the recording so far and write the model."""
        try:
            self._build(tail, stream)
        except ScanpipeError as err:  # the finished recording gets the batch run and its error
            self.problem = str(err)
            self.results, self.inputs = {}, {}
        except OSError as err:  # the model file: the artifacts still come at the end
            self.problem = f"{self.folder / MODEL_FILE}: cannot be written ({err})"

    def _build(self, tail: RecordingTail, stream: StreamFollower) -> None:
        from scanpipe.artifacts import atomic_write_bytes
        from scanpipe.exporters.model import mesh_from_tables
        from scanpipe.exporters.ply import ply_mesh_bytes

        tables: dict[str, Any] = {}
        for stage in self.chain:
            params = stage_params(stage, self.params)
            if stage.name == "decode":
                assert isinstance(params, DecodeParams)
                result = decode_recording(tail.snapshot(), params, decoded=stream.snapshot())
            else:
                if any(n not in tables for n in stage.inputs):
                    return
                inputs = {n: tables[n] for n in stage.inputs}
                result = stage.call(inputs, params)
                self.inputs[stage.name] = inputs
            self.results[stage.name] = result
            tables.update(result.tables)
            if stage.name == "decode" and self.rig_override is not None:
                from scanpipe.rig import load_rig, rig_table

                tables["rig"] = rig_table(load_rig(self.rig_override))
        if "mesh_vertices" in tables:
            mesh = mesh_from_tables(tables["mesh_vertices"], tables["mesh_faces"])
            atomic_write_bytes(self.folder / MODEL_FILE, ply_mesh_bytes(mesh))
            self.ready_ns = time.time_ns()

    def reuse(self) -> dict[str, Callable[[Mapping[str, Any]], StageResult]]:
        """Computations for the final chain: a stage's result from the scan's end when its
        inputs are identical, else its own call."""
        compute: dict[str, Callable[[Mapping[str, Any]], StageResult]] = {}
        for stage in self.chain:
            if stage.name in self.inputs:
                compute[stage.name] = self._reuse_or_call(stage)
        return compute

    def _reuse_or_call(self, stage: Stage) -> Callable[[Mapping[str, Any]], StageResult]:
        def compute(loaded: Mapping[str, Any]) -> StageResult:
            before = self.inputs[stage.name]
            changed = {n: _changed_columns(loaded[n], before[n]) for n in stage.inputs}
            if not any(changed.values()):
                self.reused.append(stage.name)
                return self.results[stage.name]
            self.changed[stage.name] = {n: c for n, c in changed.items() if c}
            return stage.call(loaded, stage_params(stage, self.params))

        return compute


def tables_identical(a: pa.Table, b: pa.Table) -> bool:
    """Whether two tables are identical: schema with its metadata, and every value's bits
    (a NaN equals the same NaN), so a pure function gives the same result on either."""
    if a is b:
        return True
    if not a.schema.equals(b.schema, check_metadata=True) or a.num_rows != b.num_rows:
        return False
    return all(_arrays_identical(a.column(i).combine_chunks(), b.column(i).combine_chunks())
               for i in range(a.num_columns))


def _changed_columns(a: pa.Table, b: pa.Table) -> list[str]:
    """What differs between two tables: rows, schema, or the names of the columns.

    The runner stamps its provenance (where and when a table was made) into the schema of a
    table it hands on; that says nothing of the content the stages up to the mesh compute from
    (only export reads it, and export is never taken from the scan's end), so it is not compared:
    with it, every table differed and no stage was ever taken from the scan's end."""
    if a.num_rows != b.num_rows:
        return [f"rows {b.num_rows} → {a.num_rows}"]
    if not _without_provenance(a.schema).equals(_without_provenance(b.schema),
                                                check_metadata=True):
        return ["schema"]
    return [name for i, name in enumerate(a.column_names)
            if not _arrays_identical(a.column(i).combine_chunks(), b.column(i).combine_chunks())]


def _without_provenance(schema: pa.Schema) -> pa.Schema:
    metadata = {k: v for k, v in (schema.metadata or {}).items() if k != PROVENANCE_KEY}
    return schema.with_metadata(metadata) if metadata else schema.remove_metadata()


def _arrays_identical(a: pa.Array, b: pa.Array) -> bool:
    if a.null_count != b.null_count or (a.null_count and not a.is_null().equals(b.is_null())):
        return False
    if pa.types.is_list(a.type):
        return bool(pc.list_value_length(a).fill_null(0).equals(
            pc.list_value_length(b).fill_null(0))) and _arrays_identical(
            pc.list_flatten(a), pc.list_flatten(b))
    if pa.types.is_floating(a.type) or pa.types.is_integer(a.type):
        x = a.fill_null(0).to_numpy(zero_copy_only=False)
        y = b.fill_null(0).to_numpy(zero_copy_only=False)
        return bool(np.array_equal(x.view(np.uint8), y.view(np.uint8)))
    return bool(a.equals(b))


def _warm_up(chain: list[Stage]) -> None:
    """Import the libraries the chain's stages load on first use (Open3D takes seconds) while
    the recording runs, so the finished recording does not wait for them."""
    import importlib
    import threading

    def load() -> None:
        for name in sorted({lib for stage in chain for lib in stage.libraries}):
            try:
                importlib.import_module(name)
            except ImportError:  # an optional library: the stage says so if it needs it
                continue

    threading.Thread(target=load, name="scanpipe-follow-warm-up", daemon=True).start()


def _decode_from(recording: Recording, params: DecodeParams, decoded: DecodedStream | None
                 ) -> Callable[[Mapping[str, Any]], StageResult]:
    def compute(_: Mapping[str, Any]) -> StageResult:
        return decode_recording(recording, params, decoded=decoded)

    return compute


def _follow(tail: RecordingTail, stream: StreamFollower, live: LivePreview | None,
            recording: Path, source: Path, handle: IO[bytes], timeout_s: float,
            poll_s: float, on_status: Callable[[FollowStatus], None] | None,
            at_scan_end: Callable[[], None]) -> FollowResult:
    """Poll until the end record, a stuck tail whose writer finished, or no growth; call
    ``at_scan_end`` once when the recorder says the scan has ended."""
    started = time.monotonic()
    result = FollowResult(recording, [], complete=False, decode="")
    last_size, last_growth = -1, time.monotonic()
    scan_ended = False
    lags_s = result.visible_lag_s
    while True:
        size = tail.size
        if size != last_size:
            last_size, last_growth = size, time.monotonic()
        if tail.poll():
            if _session_part(tail) is not None:
                raise UsageError(f"{recording}: part {_session_part(tail)} of a split "
                                 "recording; --follow follows one unsplit recording (record "
                                 "without --split-size-mb / --split-duration), a split one "
                                 "is processed part by part after it ends")
            new = stream.add(tail.new_stream_parts("scanner", RX))
            if new and stream.newest_receive_ns is not None:
                result.last_profile_ns = stream.newest_receive_ns
                lags_s.append((time.time_ns() - stream.newest_receive_ns) / 1e9)
            if not scan_ended and SCAN_END_EVENT in tail.event_kinds():
                scan_ended = True
                result.scan_end_seen_ns = time.time_ns()
                at_scan_end()
            elif live is not None:
                live.update(tail, stream)
            if on_status is not None:
                on_status(_status(tail, stream, live, started, result.last_profile_ns))
        if tail.complete or (tail.stuck is not None and writer_finished(handle)):
            result.complete = True
            result.end_seen_ns = time.time_ns()
            _wait_finished(handle, recording, timeout_s, poll_s, result.warnings)
            return result
        if time.monotonic() - last_growth >= timeout_s:
            if os.fstat(handle.fileno()).st_nlink == 0:
                raise RecordingError(f"{source}: deleted by its writer before it finished (the "
                                     "recording was abandoned); nothing was processed")
            result.warnings.append(
                f"{recording}: stopped growing {timeout_s:g} s ago without an end record (the "
                "recorder was killed or lost the disk?); processed what it holds — the "
                "decode report lists what was lost")
            return result
        time.sleep(poll_s)


def _wait_finished(handle: IO[bytes], recording: Path, timeout_s: float, poll_s: float,
                   warnings: list[str]) -> None:
    """After the data end record the writer adds the summary and the footer: the recording's
    key is the hash of the finished file, so wait for its closing bytes."""
    deadline = time.monotonic() + timeout_s
    while not writer_finished(handle):
        if time.monotonic() >= deadline:
            warnings.append(f"{recording}: its writer has not finished the file (summary, "
                            f"footer) {timeout_s:g} s after its data end; processed as it is")
            return
        time.sleep(poll_s / 4)


def _status(tail: RecordingTail, stream: StreamFollower, live: LivePreview | None,
            started: float, last_ns: int | None) -> FollowStatus:
    return FollowStatus(
        elapsed_s=time.monotonic() - started, file_bytes=tail.position,
        profiles=stream.profiles, motor_states=tail.motor_states,
        positions=live.positions if live else 0, coverage=live.coverage if live else None,
        points=live.points if live else 0, faces=live.faces if live else 0,
        lag_s=None if last_ns is None else (time.time_ns() - last_ns) / 1e9)


def _check_renamed(recording: Path, source: Path, timeout_s: float, poll_s: float) -> list[str]:
    """The writer renames its temporary file into place when it ends: wait for that."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if recording.exists() and not source.exists():
            return []
        time.sleep(poll_s)
    return [f"{recording}: its writer has not renamed {source.name} into place within "
            f"{timeout_s:g} s; the artifacts name {recording.name} (processed from "
            f"{source.name})"]


def _preview_possible(chain: list[Stage]) -> bool:
    names = [s.name for s in chain]
    return "assemble" in names


class LivePreview:
    """The model while the scan runs: new platform positions assembled, filtered and
    grid-meshed with a seam to the previous ones, never the whole scan again.

    Each :meth:`update` (at most every ``interval_s``) assembles the profiles so far (assemble
    is cheap: its clock fit and layout need every profile), then filters only the positions
    whose filtered values can no longer change — all but the last ``halo`` (the reach of the
    grid filters' windows), in a window that starts ``halo`` positions before them so their
    neighbourhoods are whole — and grid-meshes those positions together with the last position
    meshed before (the seam). The preview is what an operator watches; the artifacts are the
    batch computation's (see the module docstring). A failure in the preview stops the preview
    (``problem``), never the follow.
    """

    def __init__(self, params: Mapping[str, Params], interval_s: float = 1.0) -> None:
        from scanpipe.stages.assemble import AssembleParams
        from scanpipe.stages.filter import FilterParams
        from scanpipe.stages.mesh import MeshParams

        assemble = params.get("assemble") or AssembleParams()
        filters = params.get("filter") or FilterParams()
        mesh = params.get("mesh") or MeshParams()
        assert isinstance(assemble, AssembleParams) and isinstance(filters, FilterParams)
        assert isinstance(mesh, MeshParams)
        self.assemble_params, self.filter_params = assemble, filters
        self.mesh_params = mesh.model_copy(update={"method": "grid"})
        smoothing = filters.smoothing
        self.halo = 2 + (smoothing.radius * smoothing.iterations if smoothing.enabled else 0)
        self.interval_s = interval_s
        self.filtered_to = 0  # positions below this are filtered in the preview
        self.positions = 0
        self.coverage: float | None = None
        self.points = 0
        self.faces = 0
        self.updates = 0
        self.seconds = 0.0
        self.problem: str | None = None
        self._last = -float("inf")
        self._seam: pa.Table | None = None  # the last filtered position, meshed again
        self._meshes: list[Mesh] = []
        self._rig: Rig | None = None
        self._rig_table: pa.Table | None = None

    def update(self, tail: RecordingTail, stream: StreamFollower) -> None:
        """Take the new data into the live model."""
        now = time.monotonic()
        if self.problem is not None or now - self._last < self.interval_s:
            return
        self._last = now
        try:
            self._update(tail, stream)
        except ScanpipeError:  # too early (no motor state yet …): the next update tries again
            pass
        except Exception as err:  # the preview must never stop the follow: reported
            self.problem = f"{type(err).__name__}: {err}"
        self.seconds += time.monotonic() - now

    def _update(self, tail: RecordingTail, stream: StreamFollower) -> None:
        from scanpipe.rig import default_rig, rig_from_toml, rig_table
        from scanpipe.stages.assemble import assemble_stage
        from scanpipe.stages.decode import motor_states_table, profiles_table
        from scanpipe.stages.filter import filter_stage

        if not stream.frames or stream.dialect is None:
            return
        motor = tail.motor()
        if self._rig is None:  # the metadata come first in the file
            rig_toml = tail.metadata.get(RIG_METADATA, {}).get(RIG_KEY)
            self._rig = rig_from_toml(rig_toml) if rig_toml else default_rig()
            self._rig_table = rig_table(self._rig)
        rig = self._rig
        if motor.step_count.size and rig.motor.pulse_limit > 0:
            travel = float(motor.step_count.max() - motor.step_count[0])
            self.coverage = min(1.0, travel / rig.motor.pulse_limit)
        profiles, _ = profiles_table(stream.frames, stream.receive_times(), stream.dialect.name)
        points = assemble_stage({"profiles": profiles, "motor": motor_states_table(motor),
                                 "rig": self._rig_table}, self.assemble_params,
                                no_progress).tables["points"]
        self.positions = _positions(points)
        ready = self.positions - self.halo
        if ready <= self.filtered_to:
            return
        start = max(0, self.filtered_to - 2 * self.halo)
        window = _renumbered(_positions_between(points, start, self.positions), start)
        filtered = filter_stage({"points": window}, self.filter_params,
                                no_progress).tables["points"]
        new = _renumbered(_positions_between(filtered, self.filtered_to - start,
                                             ready - start), -start)
        self.filtered_to = ready
        self.points += new.num_rows
        self._mesh(new)
        self.updates += 1

    def _mesh(self, new: pa.Table) -> None:
        from scanpipe.stages.mesh import mesh_points

        if new.num_rows == 0:
            return
        band = new if self._seam is None else pa.concat_tables([self._seam, new])
        last = _positions(new) - 1
        self._seam = _positions_between(new, last, last + 1)
        first = int(pc.min(band.column("profile")).as_py())
        try:
            mesh, _ = mesh_points(_renumbered(band, first), self.mesh_params)
        except StageError:  # a band without a face (a position without returns)
            return
        self._meshes.append(mesh)
        self.faces += len(mesh.faces)

    def mesh(self) -> Mesh | None:
        """The live model so far: the bands' meshes joined (vertices on a seam appear in
        both of its bands); None before the first faces."""
        if not self._meshes:
            return None
        offsets = np.cumsum([0] + [len(m.vertices) for m in self._meshes[:-1]])
        return Mesh(np.concatenate([m.vertices for m in self._meshes]),
                    np.concatenate([m.faces + np.int32(o)
                                    for m, o in zip(self._meshes, offsets, strict=True)]))

    def summary(self) -> dict[str, Any]:
        """Counts and costs of the preview, for the report."""
        return {"positions": self.positions, "positions_filtered": self.filtered_to,
                "coverage": self.coverage, "points": self.points, "faces": self.faces,
                "updates": self.updates, "seconds": round(self.seconds, 3),
                "problem": self.problem}


def _positions(points: pa.Table) -> int:
    """The number of grid positions (profiles) of a points table: its largest index + 1."""
    if points.num_rows == 0:
        return 0
    return int(pc.max(points.column("profile")).as_py()) + 1


def _positions_between(points: pa.Table, start: int, stop: int) -> pa.Table:
    """The rows of grid positions ``start`` … ``stop − 1``."""
    profile = points.column("profile")
    return points.filter(pc.and_(pc.greater_equal(profile, start), pc.less(profile, stop)))


def _renumbered(points: pa.Table, first: int) -> pa.Table:
    """The table with its positions numbered from ``first`` = 0 (grids start at 0)."""
    if first == 0:
        return points
    index = points.schema.get_field_index("profile")
    shifted = pc.subtract(points.column("profile"), pa.scalar(first, pa.int32()))
    return points.set_column(index, "profile", shifted.cast(pa.int32()))
