"""A stage's artifacts are replaced together, and writers on one workdir take turns.

Stand-in stages over real Parquet for the write protocol (fast); real processes, real
``fcntl`` locks and real SIGKILLs for the lock and the crash recovery.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import scanpipe
from scanpipe import artifacts
from scanpipe.artifacts import STATE_DIR, read_provenance
from scanpipe.errors import ArtifactError
from scanpipe.params import Params
from scanpipe.pipeline import Stage, StageResult, execute, registry, run_chain
from scanpipe.progress import ProgressFn
from scanpipe.schema import ArtifactSchema, Column
from scanpipe.workdir import workdir_lock

SRC = str(Path(scanpipe.__file__).parents[1])
ENV = {**os.environ, "PYTHONPATH": SRC}


class ReadParams(Params):
    scale: float = 1.0


def _read(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn) -> StageResult:
    values = [float(b) * params.scale for b in Path(inputs["recording"]).read_bytes()]
    table = pa.table({"v": values})
    return StageResult({"a": table, "b": table, "c": table}, {"scale": params.scale},
                       files={"note.txt": f"scale {params.scale}".encode()})


TOY = tuple(ArtifactSchema(n, (Column("v", pa.float64()),), "a toy table") for n in "abc")
READ = Stage("read", 1, ReadParams, ("recording",), ("a", "b", "c"), _read,  # type: ignore[arg-type]
             "three tables and a file", schemas=TOY)


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` except the lock, by relative path."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != "lock"}


def _scales(folder: Path) -> set[float]:
    return {read_provenance(folder / f"{n}.parquet")["params"]["scale"] for n in "abc"}


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "rec.bin"
    path.write_bytes(bytes([1, 2, 3]))
    return path


def _fail_on_call(monkeypatch: pytest.MonkeyPatch, number: int, code: int) -> None:
    """Make the ``number``-th Parquet write raise OSError(``code``) (its file begun)."""
    calls = [0]
    write_table = artifacts.pq.write_table

    def failing(table: Any, where: Any, *args: Any, **kwargs: Any) -> None:
        calls[0] += 1
        if calls[0] == number:
            Path(where).write_bytes(b"PAR1")  # begun, then the disk fails
            raise OSError(code, os.strerror(code))
        write_table(table, where, *args, **kwargs)

    monkeypatch.setattr(artifacts.pq, "write_table", failing)


@pytest.mark.parametrize("replace_folder", [True, False])
@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EIO, errno.EACCES])
def test_oserror_part_way_keeps_the_previous_set(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        replace_folder: bool, code: int) -> None:
    out = tmp_path / "w" / "read"
    execute(READ, {"recording": recording}, out, ReadParams(scale=1.0),
            replace_folder=replace_folder)
    before = _snapshot(out.parent)
    _fail_on_call(monkeypatch, 2, code)  # after table "a" is written
    with pytest.raises(ArtifactError) as info:
        execute(READ, {"recording": recording}, out, ReadParams(scale=2.0), force=True,
                replace_folder=replace_folder)
    message = str(info.value)
    assert "\n" not in message
    assert f"{out / 'b.parquet'}: cannot be written ({os.strerror(code)})" in message
    assert "previous read artifacts are kept" in message
    assert _snapshot(out.parent) == before  # the old set, and no staging left behind
    assert _scales(out) == {1.0}
    monkeypatch.undo()
    execute(READ, {"recording": recording}, out, ReadParams(scale=2.0),
            replace_folder=replace_folder)
    assert _scales(out) == {2.0}
    assert (out / "note.txt").read_text() == "scale 2.0"


@pytest.mark.parametrize("replace_folder", [True, False])
def test_every_staged_file_and_its_folder_are_flushed_before_the_swap(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        replace_folder: bool) -> None:
    """The flushes run concurrently, but every one of them (each file, then the staging
    folder's names) has finished before the set is renamed into place."""
    out = tmp_path / "w" / "read"
    events: list[tuple[str, str]] = []
    real_fsync, real_rename = artifacts._fsync, artifacts.os.rename

    def fsync(path: Path) -> None:
        time.sleep(0.02)  # a slow disk: a swap that did not wait would come first
        real_fsync(path)
        events.append(("fsync", Path(path).name))

    def rename(src: Any, dst: Any) -> None:
        events.append(("rename", Path(src).name))
        real_rename(src, dst)

    monkeypatch.setattr(artifacts, "_fsync", fsync)
    monkeypatch.setattr(artifacts.os, "rename", rename)
    execute(READ, {"recording": recording}, out, ReadParams(scale=3.0),
            replace_folder=replace_folder)
    staged = [e for e in events if e[1].startswith("tmp-read-")]
    first_rename = next(i for i, e in enumerate(events) if e[0] == "rename"
                        and e[1].startswith("tmp-read-"))
    flushed = {name for kind, name in events[:first_rename] if kind == "fsync"}
    assert {"a.parquet", "b.parquet", "c.parquet", "note.txt"} <= flushed
    assert staged[0][0] == "fsync"  # the staging folder itself, before it moves
    assert _scales(out) == {3.0}


def test_a_chain_flushes_its_workdir_after_each_swap_before_it_returns(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In a chain the workdir's flush after each stage's swap runs in the background, but
    every one has finished when run_chain returns (and they still come after each swap)."""
    work = tmp_path / "w"
    flushed: list[Path] = []
    real_fsync = artifacts._fsync

    def fsync(path: Path) -> None:
        if Path(path) == work:
            time.sleep(0.05)  # a slow disk: a chain that did not wait returns first
        real_fsync(path)
        flushed.append(Path(path))

    monkeypatch.setattr(artifacts, "_fsync", fsync)
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ, COPY])
    assert flushed.count(work) == 2  # once per stage's swap, all done
    assert not artifacts._STATE.deferred
    assert _scales(work / "read") == {1.0}


def _copy(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn) -> StageResult:
    return StageResult({"d": inputs["a"]}, {})


COPY = Stage("copy", 1, ReadParams, ("a",), ("d",), _copy,  # type: ignore[arg-type]
             "a copy", schemas=(TOY[0], ArtifactSchema("d", (Column("v", pa.float64()),),
                                                       "a copy")))


def test_the_next_stage_runs_while_the_previous_set_is_flushed_and_swapped_in(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In a chain a stage's folder is flushed and swapped in by a background thread while the
    next stage computes from the tables in memory; keys and files are those of a plain run."""
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ, COPY])
    real_fsync = artifacts._fsync
    seen: list[set[float]] = []

    def fsync(path: Path) -> None:
        time.sleep(0.1)  # a slow disk
        real_fsync(path)

    def copy(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn
             ) -> StageResult:
        seen.append(_scales(work / "read"))  # what is on disk while this stage computes
        return _copy(inputs, params, progress)

    monkeypatch.setattr(artifacts, "_fsync", fsync)
    slow_copy = Stage("copy", 1, ReadParams, ("a",), ("d",), copy,  # type: ignore[arg-type]
                      "a copy", schemas=COPY.schemas)
    records = run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ, slow_copy])
    assert seen == [{1.0}]  # the previous set was still in place: the commit overlapped
    assert _scales(work / "read") == {2.0}  # and everything is in place on return
    copied = read_provenance(work / "copy" / "d.parquet")
    assert copied["inputs"] == {"a": read_provenance(work / "read" / "a.parquet")["key"]}
    assert copied["inputs"] == {"a": records[0].key}
    assert not list((work / STATE_DIR).glob("tmp-*"))


def test_a_background_commit_that_fails_stops_the_chain_and_keeps_every_previous_set(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ, COPY])
    before = _snapshot(work)
    real = os.rename

    def rename(src: Any, dst: Any) -> None:
        if Path(src).name.startswith("tmp-read-"):  # the read stage's new folder moving in
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real(src, dst)

    monkeypatch.setattr(artifacts.os, "rename", rename)
    with pytest.raises(ArtifactError) as info:
        run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ, COPY])
    assert str(info.value) == (f"{work / 'read'}: cannot be written (Input/output error); "
                               "the previous read artifacts are kept")
    assert _snapshot(work) == before  # read's old set, copy's old set: nothing of the new
    assert not list((work / STATE_DIR).glob("tmp-*"))
    monkeypatch.undo()
    run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ, COPY])
    assert _scales(work / "read") == {2.0}


def test_a_failed_commit_stops_the_chain_before_its_next_stage(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Once a set failed to commit the chain computes no further stage (their results could
    not be kept anyway): it stops at the next one instead of at its end."""
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ, COPY])
    real = os.rename

    def rename(src: Any, dst: Any) -> None:
        if Path(src).name.startswith("tmp-read-"):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real(src, dst)

    def copy(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn
             ) -> StageResult:
        deadline = time.monotonic() + 20  # until the read set's commit has failed
        while artifacts._STATE.commits[-1]._failed is None and time.monotonic() < deadline:
            time.sleep(0.005)
        return _copy(inputs, params, progress)

    ran: list[str] = []

    def last(inputs: Mapping[str, Any], params: ReadParams, progress: ProgressFn
             ) -> StageResult:
        ran.append("last")
        return StageResult({"e": inputs["d"]}, {})

    waiting_copy = Stage("copy", 1, ReadParams, ("a",), ("d",),  # type: ignore[arg-type]
                         copy, "a copy", schemas=COPY.schemas)
    third = Stage("last", 1, ReadParams, ("d",), ("e",), last,  # type: ignore[arg-type]
                  "a last copy", schemas=(COPY.schemas[1], ArtifactSchema(
                      "e", (Column("v", pa.float64()),), "a last copy")))
    monkeypatch.setattr(artifacts.os, "rename", rename)
    with pytest.raises(ArtifactError, match="the previous read artifacts are kept"):
        run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ, waiting_copy, third])
    assert ran == []


def test_a_failed_flush_names_the_file_and_keeps_the_previous_set(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "w" / "read"
    execute(READ, {"recording": recording}, out, ReadParams(scale=1.0), replace_folder=True)
    before = _snapshot(out.parent)
    real_fsync = artifacts._fsync

    def fsync(path: Path) -> None:
        if Path(path).name == "b.parquet":
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real_fsync(path)

    monkeypatch.setattr(artifacts, "_fsync", fsync)
    with pytest.raises(ArtifactError) as info:
        execute(READ, {"recording": recording}, out, ReadParams(scale=2.0), force=True,
                replace_folder=True)
    assert str(info.value) == (f"{out / 'b.parquet'}: cannot be written (Input/output error); "
                               "the previous read artifacts are kept")
    assert _snapshot(out.parent) == before
    assert _scales(out) == {1.0}


def test_failed_swap_puts_the_old_folder_back(recording: Path, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ])
    before = _snapshot(work)
    real = os.rename

    def rename(src: Any, dst: Any) -> None:
        if Path(src).name.startswith("tmp-"):  # the new folder moving in
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real(src, dst)

    monkeypatch.setattr(artifacts.os, "rename", rename)
    with pytest.raises(ArtifactError, match=r"cannot be written \(Input/output error\)"):
        run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ])
    assert _snapshot(work) == before


def test_flat_folder_keeps_other_files(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "flat"
    out.mkdir()
    (out / "mine.txt").write_text("the user's")
    execute(READ, {"recording": recording}, out, ReadParams(scale=3.0))
    assert (out / "mine.txt").read_text() == "the user's"
    assert _scales(out) == {3.0}
    assert sorted(p.name for p in (out / STATE_DIR).iterdir()) == ["lock"]


# --- real processes -------------------------------------------------------------------------

CHILD = """
import os, signal, sys
from pathlib import Path
sys.path.insert(0, {tests!r})
import test_workdir_safety as t
from scanpipe import artifacts
from scanpipe.pipeline import execute, run_chain

def die():
    os.kill(os.getpid(), signal.SIGKILL)

{patch}
rec, out = Path({rec!r}), Path({out!r})
if {chain!r}:
    run_chain(rec, out, {{"read": t.ReadParams(scale=2.0)}}, [t.READ])
else:
    execute(t.READ, {{"recording": rec}}, out, t.ReadParams(scale=2.0), force=True)
"""

#: Where the child kills itself: part-way through the staged writes, between the two renames of
#: the folder swap, and part-way through rolling a committed flat set into place.
KILL_POINTS = {
    "staging": """
real = artifacts._write_parquet
calls = [0]
def write(*args, **kwargs):
    calls[0] += 1
    if calls[0] == 2:
        die()
    real(*args, **kwargs)
artifacts._write_parquet = write
""",
    "swap": """
real = os.rename
def rename(src, dst):
    real(src, dst)
    if Path(dst).name.startswith("old-"):
        die()
artifacts.os.rename = rename
""",
    "roll-forward": """
real = os.replace
calls = [0]
def replace(src, dst):
    calls[0] += 1
    if calls[0] == 2:
        die()
    real(src, dst)
artifacts.os.replace = replace
""",
}


@pytest.mark.parametrize(("point", "chain"), [("staging", True), ("swap", True),
                                              ("staging", False), ("roll-forward", False)])
def test_killed_writer_leaves_a_consistent_folder(recording: Path, tmp_path: Path,
                                                  point: str, chain: bool) -> None:
    work = tmp_path / "w"
    out = work if chain else work / "read"
    if chain:
        run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ])
    else:
        execute(READ, {"recording": recording}, out, ReadParams(scale=1.0))
    code = CHILD.format(tests=str(Path(__file__).parent), patch=KILL_POINTS[point],
                        rec=str(recording), out=str(out), chain=chain)
    child = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True,
                           timeout=60)
    assert child.returncode == -signal.SIGKILL, child.stderr.decode()
    folder = work / "read"
    leftovers = sorted(p.name for p in (folder.parent if chain else folder).joinpath(
        STATE_DIR).iterdir())
    assert leftovers != ["lock"]  # the kill did leave work for the recovery
    if point == "swap":
        assert not folder.exists()  # a reader sees no folder, never a mix
    elif point == "roll-forward":
        assert len(_scales(folder)) == 2  # committed, half moved: the recovery must finish it
    else:
        assert _scales(folder) == {1.0}
    # The next writer recovers first: the previous set back (staging, swap) or the committed
    # one finished (roll-forward), then it runs as usual.
    expected = {"staging": 1.0, "swap": 1.0, "roll-forward": 2.0}[point]
    if chain:
        records = run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ])
        assert records[0].reused and _scales(folder) == {expected}
    else:
        execute(READ, {"recording": recording}, folder, ReadParams(scale=expected))
        assert _scales(folder) == {expected}
    assert sorted(p.name for p in (folder.parent if chain else folder).joinpath(
        STATE_DIR).iterdir()) == ["lock"]


HOLDER = """
import sys, time
from pathlib import Path
from scanpipe.workdir import workdir_lock
with workdir_lock(Path(sys.argv[1])):
    print("locked", flush=True)
    time.sleep(60)
"""


def _hold_lock(work: Path) -> subprocess.Popen[str]:
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(work)], env=ENV,
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
    return holder


def test_second_writer_refuses_or_waits_naming_the_holder(recording: Path, tmp_path: Path,
                                                          cli) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "w"
    holder = _hold_lock(work)
    try:
        refused = cli("run", recording, "--workdir", work, "--wait", "0", "-q")
        assert refused.code == 1
        assert refused.err.count("\n") == 1
        assert f"scanpipe: error: {work}: in use by pid {holder.pid} (" in refused.err
        started = time.monotonic()
        waited = cli("run", recording, "--workdir", work, "--wait", "0.5", "-q")
        assert time.monotonic() - started >= 0.5
        assert f"scanpipe: waiting for {work}: in use by pid {holder.pid}" in waited.err
        assert "gave up after 0.5 s" in waited.err and waited.code == 1
        # A single-stage command writing into a stage folder of that workdir waits for it too.
        with pytest.raises(ArtifactError, match=f"in use by pid {holder.pid}"):
            execute(READ, {"recording": recording}, work / "read", ReadParams(),
                    lock_wait_s=0)
        assert not (work / "read").exists()
    finally:
        holder.kill()
        holder.wait()
    # The holder died (SIGKILL): the kernel released its lock, which is simply taken.
    with workdir_lock(work, wait_s=0):
        pass
    assert run_chain(recording, work, {}, [READ], lock_wait_s=0)[0].reused is False


# --- the real chain: concurrent runs and a real kill ------------------------------------------

@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from scanpipe.sim.direct import simulate_direct
    from scanpipe.sim.options import SimOptions

    root = tmp_path_factory.mktemp("scan")
    path = root / "scan.mcap"
    simulate_direct(path, root / "truth", SimOptions(
        beam_step_deg=2.0, motor_step_deg=6.0, camera_scale=0.1, camera_fps=0.2, seed=3))
    return path


def assert_consistent(work: Path) -> int:
    """Every stage folder holds one generation (one key), its listed files exist, and its inputs
    are the artifacts of the upstream folders present; returns how many folders were checked."""
    produced: dict[str, str] = {}
    checked = 0
    for stage in registry().values():
        folder = work / stage.name
        if not folder.exists():
            continue
        records = [read_provenance(folder / f"{name}.parquet") for name in stage.outputs]
        assert len({r["key"] for r in records}) == 1, f"{folder}: mixed generations"
        for record in records:
            for name, key in record["inputs"].items():
                if name != "recording":
                    assert produced.get(name) == key, f"{folder}: input {name} not present"
            assert all((folder / f).is_file() for f in record["files"])
        produced.update({name: records[0]["key"] for name in stage.outputs})
        checked += 1
    return checked


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "scanpipe.cli.main", *map(str, args)]


@pytest.mark.slow
def test_concurrent_runs_with_different_parameters_do_not_mix(scan: Path,
                                                              tmp_path: Path) -> None:
    work = tmp_path / "w"
    runs = [subprocess.Popen(_cli("run", scan, "--workdir", work, "-q", "--set",
                                  f"filter.grid_median.max_deviation_m={0.02 + 0.01 * i}",
                                  "--set", f"mesh.method={'grid' if i % 2 else 'auto'}"),
                             env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for i in range(10)]
    results = [(run.wait(timeout=300), run.stderr.read() if run.stderr else "") for run in runs]
    failures = [err for code, err in results if code != 0]
    assert failures == []
    assert any("waiting for" in err for _, err in results)
    assert assert_consistent(work) == 7  # the chain: 7 stages
    assert sorted(p.name for p in (work / STATE_DIR).iterdir()) == ["lock"]


@pytest.mark.slow
def test_sigkill_during_a_stage_then_the_next_run_completes(scan: Path, tmp_path: Path) -> None:
    work = tmp_path / "w"
    for attempt in range(3):
        run = subprocess.Popen(_cli("run", scan, "--workdir", work, "-q", "--set",
                                    f"filter.grid_median.max_deviation_m={0.03 + attempt / 100}"),
                               env=ENV, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 60
        staged: list[Path] = []
        while not staged and run.poll() is None and time.monotonic() < deadline:
            # A stage is writing: kill it there, mid-stage, as a crash would.
            staged = list((work / STATE_DIR).glob("tmp-*")) if (work / STATE_DIR).is_dir() else []
        run.send_signal(signal.SIGKILL)
        run.wait()
        assert staged, "the run finished before it could be killed"
        assert_consistent(work)
    finished = subprocess.run(_cli("run", scan, "--workdir", work, "-q"), env=ENV,
                              capture_output=True, text=True, timeout=300)
    assert finished.returncode == 0, finished.stderr
    assert assert_consistent(work) == 7
    assert sorted(p.name for p in (work / STATE_DIR).iterdir()) == ["lock"]


@pytest.mark.parametrize("command", ["decode", "run"])
def test_cli_disk_full_is_one_line_and_keeps_the_previous_set(
        cli, scan: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,  # type: ignore[no-untyped-def]
        command: str) -> None:
    out = tmp_path / "out"
    args: list[str | Path] = (["decode", scan, "--out", out] if command == "decode" else
                              ["run", scan, "--workdir", out, "--to", "decode"])
    change = "checksum=lenient" if command == "decode" else "decode.checksum=lenient"
    assert cli(*args, "-q").code == 0
    before = _snapshot(out)
    _fail_on_call(monkeypatch, 3, errno.ENOSPC)  # two tables written, then the disk fills
    failed = cli(*args, "-q", "--set", change)
    folder = out if command == "decode" else out / "decode"
    assert failed.code == 1
    assert failed.err == (f"scanpipe: error: {folder / 'frames.parquet'}: cannot be written "
                          "(No space left on device); the previous decode artifacts are kept\n")
    assert "Traceback" not in failed.err
    assert _snapshot(out) == before


@pytest.mark.parametrize(("threads", "where"), [("2", "commit"), ("1", "MainThread")])
def test_a_chains_tables_are_encoded_in_the_background_unless_one_thread(
        recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads: str,
        where: str) -> None:
    """With more than one thread a stage's tables (a set of tables only) are encoded and
    written by the committer while the next stage computes; at one thread (a batch worker's
    share of a core) in place. The same files either way."""
    import threading

    monkeypatch.setenv("OMP_NUM_THREADS", threads)
    writers: list[str] = []
    real = artifacts._write_parquet

    def write(path: Path, table: Any, provenance: Any) -> None:
        writers.append(threading.current_thread().name)
        real(path, table, provenance)

    monkeypatch.setattr(artifacts, "_write_parquet", write)
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=2.0)}, [READ, COPY])
    # read's set has a file besides its tables (made while written: always in place)
    assert writers[:3] == ["MainThread"] * 3 and writers[3].startswith(where)
    monkeypatch.undo()
    plain = tmp_path / "plain"
    for stage, params in ((READ, ReadParams(scale=2.0)), (COPY, ReadParams())):
        inputs = {"recording": recording} if stage is READ else {"a": plain / "read" / "a.parquet"}
        execute(stage, inputs, plain / stage.name, params, replace_folder=True)
    for name in ("read/a.parquet", "read/b.parquet", "read/c.parquet", "copy/d.parquet"):
        ours, theirs = read_provenance(work / name), read_provenance(plain / name)
        assert ours["key"] == theirs["key"] and ours["inputs"] == theirs["inputs"]
        assert pq.read_table(work / name).equals(pq.read_table(plain / name))


def test_two_chains_in_two_threads_each_commit_their_own_sets(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A library caller running two chains at once in threads (two workdirs): each chain's
    background commits are its own, so a chain returns with its sets in place (another
    thread's chain, started later and still running, must not take them over)."""
    import threading

    first_in, second_in, first_done = threading.Event(), threading.Event(), threading.Event()
    real_fsync = artifacts._fsync

    def fsync(path: Path) -> None:
        if "first" in str(path):
            time.sleep(0.3)  # a slow disk under the first chain's workdir
        real_fsync(path)

    def read_first(inputs: Mapping[str, Any], params: ReadParams,
                   progress: ProgressFn) -> StageResult:
        first_in.set()
        assert second_in.wait(10)  # the second chain has begun: its commits are set up
        return _read(inputs, params, progress)

    def read_second(inputs: Mapping[str, Any], params: ReadParams,
                    progress: ProgressFn) -> StageResult:
        second_in.set()
        assert first_done.wait(10)  # still running when the first chain returns
        return _read(inputs, params, progress)

    def stage(func: Any) -> Stage:
        return Stage("read", 1, ReadParams, ("recording",), ("a", "b", "c"), func,
                     "three tables and a file", schemas=TOY)

    recordings = {}
    for name in ("first", "second"):
        recordings[name] = tmp_path / f"{name}.bin"
        recordings[name].write_bytes(bytes([1, 2, 3]))
    monkeypatch.setattr(artifacts, "_fsync", fsync)
    seen: list[Any] = []

    def second() -> None:
        assert first_in.wait(10)  # after the first chain began
        run_chain(recordings["second"], tmp_path / "second", {"read": ReadParams()},
                  [stage(read_second)])

    thread = threading.Thread(target=second)
    thread.start()
    try:
        run_chain(recordings["first"], tmp_path / "first", {"read": ReadParams(scale=2.0)},
                  [stage(read_first)])
        seen.append((tmp_path / "first" / "read" / "a.parquet").is_file())
    finally:
        first_done.set()
        thread.join(20)
    assert seen == [True]  # in place when its chain returned
    assert _scales(tmp_path / "first" / "read") == {2.0}
    assert _scales(tmp_path / "second" / "read") == {1.0}


def test_a_chain_recovers_what_a_killed_process_of_its_own_pid_left(
        recording: Path, tmp_path: Path) -> None:
    """Recovery passes over the sets this process is committing, not every entry with its pid:
    a container restarted after a kill runs scanpipe under the same pid again, and the staging
    folder and the set moved aside that the killed run left must still be recovered."""
    work = tmp_path / "w"
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ, COPY])
    state = work / STATE_DIR
    pid = os.getpid()
    (state / f"tmp-read-{pid}").mkdir()  # killed while staging read's set
    (state / f"tmp-read-{pid}" / "a.parquet").write_bytes(b"PAR1")
    os.rename(work / "copy", state / f"old-copy-{pid}")  # killed between the swap's renames
    run_chain(recording, work, {"read": ReadParams(scale=1.0)}, [READ])  # reused, copy not run
    assert sorted(p.name for p in state.iterdir() if p.name != "lock") == []
    assert read_provenance(work / "copy" / "d.parquet")["stage"] == "copy"  # put back
