"""``scanpipe batch`` on real simulated recordings: workdir names, failure isolation, the cache,
the missing-Ray message, and equal artifacts from the local pool and a local Ray."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest

from scanpipe.artifacts import read_artifact
from scanpipe.batch import (
    largest_first,
    plan_batch,
    run_batch,
    start_local_ray,
    workdir_name,
    worker_threads,
)
from scanpipe.cli.pipeline import pipeline_params_from_cli
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions

pytestmark = pytest.mark.slow
GRID = ["mesh.method=grid"]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two small recordings with the same file name in two folders, and a damaged one."""
    root = tmp_path_factory.mktemp("recs")
    paths = []
    for seed, folder in ((1, "x"), (2, "y")):
        path = root / folder / "scan.mcap"
        path.parent.mkdir()
        simulate_direct(path, root / folder / "truth", SimOptions(
            beam_step_deg=4.0, motor_step_deg=6.0, cameras=False, seed=seed))
        paths.append(path)
    bad = root / "bad.mcap"
    bad.write_bytes(b"not a recording")
    return [*paths, bad]


@pytest.fixture(scope="module")
def ray_local() -> Iterator[Any]:
    """One local Ray for the module, with 2 CPUs (starting one takes seconds)."""
    import ray

    start_local_ray(2)
    yield ray
    ray.shutdown()


def _tables(workdir: Path) -> dict[str, Any]:
    return {str(p.relative_to(workdir)): read_artifact(p)[0]
            for p in sorted(workdir.glob("*/*.parquet"))}


def _same(a: Any, b: Any) -> bool:
    """Equal tables, bit for bit (``Table.equals`` says NaN differs from itself), metadata
    (provenance: times, paths) aside."""
    def data(table: Any) -> bytes:
        sink = pa.BufferOutputStream()
        table = table.replace_schema_metadata(None).combine_chunks()
        with pa.ipc.new_stream(sink, table.schema) as writer:
            writer.write_table(table)
        return bytes(sink.getvalue())
    return data(a) == data(b)


def test_names_keep_equal_file_names_apart(recordings: list[Path], tmp_path: Path) -> None:
    items = plan_batch(recordings, tmp_path / "w")
    names = [i.name for i in items]
    assert len(set(names)) == 3
    assert names[0].startswith("scan-") and names[1].startswith("scan-")
    assert names[0] == workdir_name(recordings[0])  # stable: independent of the rest


def test_local_isolates_a_failure_and_reuses_the_cache(cli, recordings: list[Path],  # type: ignore[no-untyped-def]
                                                      tmp_path: Path) -> None:
    work = tmp_path / "w"
    missing = tmp_path / "nope.mcap"
    first = cli("batch", *recordings, missing, "--workdir", work, "--workers", "2",
                "--set", *GRID, "--to", "filter")
    assert first.code == 1
    assert first.err.strip().splitlines()[-1] == (
        f"scanpipe: error: 2 of 4 recordings failed ({workdir_name(recordings[2])}, "
        f"{workdir_name(missing)}); re-run the same command after fixing them: finished "
        "stages are reused")
    assert f"FAILED  {recordings[2]}: not an MCAP file (bad magic bytes)" in first.err
    assert f"FAILED  {missing}: recording not found" in first.err
    assert "Traceback" not in first.err
    summary = json.loads((work / "batch.json").read_text())
    assert [i["ok"] for i in summary["items"]] == [True, True, False, False]
    assert [s["stage"] for s in summary["items"][0]["stages"]] == ["decode", "calibrate",
                                                                     "assemble", "filter"]
    assert (work / workdir_name(recordings[0]) / "filter" / "points.parquet").is_file()
    # the re-run continues where the first stopped: four stages reused, three run
    again = cli("batch", *recordings[:2], "--workdir", work, "--workers", "1",
                "--set", *GRID, "--json")
    assert again.code == 0, again.err
    result = json.loads(again.out)
    for item in result["items"]:
        assert [s["reused"] for s in item["stages"]] == [True] * 4 + [False] * 3
    assert (work / workdir_name(recordings[1]) / "export" / "model.glb").is_file()


def test_local_and_ray_give_the_same_artifacts(recordings: list[Path], ray_local: Any,
                                               tmp_path: Path) -> None:
    params = pipeline_params_from_cli(None, GRID)
    local = run_batch(recordings, tmp_path / "local", params, workers=2)
    calls: list[tuple[str, float, float | None]] = []
    on_ray = run_batch(recordings, tmp_path / "ray", params, engine="ray", workers=2,
                       progress=lambda task, done, total=None: calls.append((task, done, total)))
    # 3 recordings × 7 stages (decode, calibrate, assemble, filter, mesh, texture, export)
    assert calls[-1] == ("recordings", 3, 3) or calls[-1] == ("stages", 21, 21)
    assert ("recordings", 3, 3) in calls and ("stages", 21, 21) in calls
    assert [i["ok"] for i in on_ray["items"]] == [True, True, False]
    assert on_ray["items"][2]["error"] == local["items"][2]["error"]
    for a, b in zip(local["items"], on_ray["items"], strict=True):
        assert [(s["stage"], s["key"]) for s in a["stages"]] == \
            [(s["stage"], s["key"]) for s in b["stages"]]
    for item in local["items"][:2]:
        tables_local = _tables(Path(item["workdir"]))
        tables_ray = _tables(tmp_path / "ray" / item["name"])
        assert len(tables_local) >= 10 and tables_local.keys() == tables_ray.keys()
        for name, table in tables_local.items():
            assert _same(table, tables_ray[name]), name
    again = run_batch(recordings[:1], tmp_path / "ray", params, engine="ray")
    assert all(s["reused"] for s in again["items"][0]["stages"])
    _check_cpu_accounting(local, "local")
    _check_cpu_accounting(on_ray, "ray")


def _check_cpu_accounting(summary: dict[str, Any], engine: str) -> None:
    """Every stage's CPU and process, each worker's CPU, the parent's: where the time went."""
    assert summary["parent_cpu_s"] >= 0
    assert summary["threads"] == (worker_threads(2, None) if engine == "local" else 1)
    stage_cpu = 0.0
    pids = set()
    for item in summary["items"][:2]:
        assert item["cpu_s"] > 0
        for stage in item["stages"]:
            assert stage["cpu_s"] >= 0 and isinstance(stage["pid"], int)
            # the worker's own waits (disk flushes, its helper threads); Linux says
            assert stage["blocked_s"] >= 0 and stage["blocked_s"] <= item["seconds"]
            stage_cpu += stage["cpu_s"]
            pids.add(str(stage["pid"]))
        starts = item["worker_start_cpu_s"]
        # a worker's start (local: interpreter and imports; Ray: the chain's imports in its
        # Ray worker) is its own figure: local, with each of the worker's recordings; Ray,
        # with the first recording a worker started in this batch ran
        assert all(v > 0 for v in starts.values())
        assert set(starts) <= {str(s["pid"]) for s in item["stages"]}
        assert len(starts) == 1 if engine == "local" else len(starts) <= 1
    if engine == "ray":  # once per worker, every worker new in this batch
        started = [p for i in summary["items"] for p in i["worker_start_cpu_s"]]
        ran = {str(s["pid"]) for i in summary["items"] for s in i["stages"]}
        assert len(started) == len(set(started)) and ran <= set(started)
    assert pids <= set(summary["workers_cpu_s"])
    assert sum(summary["workers_cpu_s"].values()) >= stage_cpu - 1e-3


def test_local_workers_fork_from_a_warm_server(recordings: list[Path], tmp_path: Path) -> None:
    """The local pool's workers are forked from one fork server that imported the chain: a
    worker's own start costs little CPU (a spawned one paid ~2 s: interpreter, the chain,
    Open3D, SciPy), a second batch in the process reuses the server, and a batch with another
    thread count gets a new one (its libraries sized their thread pools when it started)."""
    from multiprocessing import forkserver

    from scanpipe.batch import pool_context, stop_pool_server

    assert pool_context(1).get_start_method() == "forkserver"  # on Linux
    params = pipeline_params_from_cli(None, GRID)
    stop_pool_server()
    first = run_batch(recordings[:1], tmp_path / "a", params, workers=1, threads=1,
                      to="decode")
    server = forkserver._forkserver._forkserver_pid  # type: ignore[attr-defined]
    second = run_batch(recordings[:1], tmp_path / "b", params, workers=1, threads=1,
                       to="decode")
    assert forkserver._forkserver._forkserver_pid == server  # type: ignore[attr-defined]
    for summary in (first, second):
        assert summary["failed"] == 0
        (start,) = summary["items"][0]["worker_start_cpu_s"].values()
        assert 0 < start < 0.8, start
    run_batch(recordings[:1], tmp_path / "c", params, workers=1, threads=2, to="decode")
    assert forkserver._forkserver._forkserver_pid != server  # type: ignore[attr-defined]


def test_largest_recording_starts_first(tmp_path: Path) -> None:
    sizes = {"small.mcap": 10, "big.mcap": 300, "mid.mcap": 100}
    for name, size in sizes.items():
        (tmp_path / name).write_bytes(b"x" * size)
    items = plan_batch([tmp_path / n for n in ("small.mcap", "missing.mcap", "big.mcap",
                                               "mid.mcap")], tmp_path / "w")
    assert [i.recording.name for i in largest_first(items)] == [
        "big.mcap", "mid.mcap", "small.mcap", "missing.mcap"]


def test_ray_missing_says_how_to_install(cli, recordings: list[Path], tmp_path: Path,  # type: ignore[no-untyped-def]
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray → ImportError
    result = cli("batch", recordings[0], "--workdir", tmp_path / "w", "--engine", "ray")
    assert result.code == 2
    assert result.err.strip() == ("scanpipe: error: --engine ray needs Ray, which is not "
                                  "installed: pip install 'scanpipe[ray]'")
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize(("extra", "needle"), [
    (["--engine", "spark"], "--engine 'spark': use one of local, ray"),
    (["--address", "10.0.0.1:6379"], "--address is for --engine ray"),
    (["--to", "mesher"], "--to 'mesher': not a stage"),
    (["TWICE"], "given twice"),
])
def test_bad_usage(cli, recordings: list[Path], tmp_path: Path, extra: list[str],  # type: ignore[no-untyped-def]
                   needle: str) -> None:
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "keep.txt").write_text("mine")
    args = [str(recordings[0]) if a == "TWICE" else a for a in extra]
    result = cli("batch", recordings[0], "--workdir", tmp_path / "w", *args)
    assert result.code == 2
    assert result.err.count("\n") == 1 and needle in result.err, result.err
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["keep.txt"]


def test_ray_threads_above_the_largest_node_are_refused(cli, recordings: list[Path],  # type: ignore[no-untyped-def]
                                                       ray_local: Any, tmp_path: Path) -> None:
    # the module's local Ray has 2 CPUs: a task asking for 3 would never be scheduled
    result = cli("batch", recordings[0], "--workdir", tmp_path / "w", "--engine", "ray",
                 "--threads", "3")
    assert result.code == 2
    assert result.err.count("\n") == 1, result.err
    assert "--threads 3: more than the 2 CPUs of the largest Ray node" in result.err
    assert not (tmp_path / "w").exists()


def test_workdir_that_is_a_file_is_refused(cli, recordings: list[Path], tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    target = tmp_path / "w"
    target.write_text("mine")
    result = cli("batch", recordings[0], "--workdir", target)
    assert result.code == 2 and "exists and is not a folder" in result.err
    assert target.read_text() == "mine"


def test_foreign_batch_json_is_kept(cli, recordings: list[Path], tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "batch.json").write_text("my notes")
    result = cli("batch", recordings[0], "--workdir", tmp_path / "w")
    assert result.code == 2 and "batch.json: exists and is not a scanpipe batch summary" in \
        result.err
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["batch.json"]
    assert (tmp_path / "w" / "batch.json").read_text() == "my notes"


def test_ray_runs_a_recordings_stages_in_one_kept_worker(recordings: list[Path], ray_local: Any,
                                                         tmp_path: Path) -> None:
    """Each recording's stage tasks run in one Ray worker (its outputs reach the next stage in
    memory); ``keep_workers`` keeps that worker, with the chain imported, for the next batch;
    :func:`stop_ray_workers` ends it."""
    import os
    import signal

    from scanpipe.batch import stop_ray_workers

    params = pipeline_params_from_cli(None, GRID)
    stop_ray_workers()
    first = run_batch(recordings[:1], tmp_path / "a", params, engine="ray", workers=1,
                      to="assemble", keep_workers=True)
    second = run_batch(recordings[1:2], tmp_path / "b", params, engine="ray", workers=1,
                       to="assemble", keep_workers=True)
    (one,), (two,) = first["items"], second["items"]
    assert one["ok"] and two["ok"]
    assert [s["stage"] for s in one["stages"]] == ["decode", "calibrate", "assemble"]
    pids = {s["pid"] for s in one["stages"]} | {s["pid"] for s in two["stages"]}
    assert len(pids) == 1  # one worker for both recordings, every stage
    (start,) = one["worker_start_cpu_s"].values()
    assert start > 0 and two["worker_start_cpu_s"] == {}  # started once, in the first batch
    # a kept worker that died meanwhile (out of memory, say) is replaced, not used
    os.kill(pids.pop(), signal.SIGKILL)
    third = run_batch(recordings[:1], tmp_path / "c", params, engine="ray", workers=1,
                      to="decode", keep_workers=True)
    (three,) = third["items"]
    assert three["ok"], three["error"]
    (new_pid, new_start), = three["worker_start_cpu_s"].items()
    assert new_start > 0 and new_pid == str(three["stages"][0]["pid"])
    assert stop_ray_workers() == 1 and stop_ray_workers() == 0


def test_ray_worker_lost_fails_its_recording_only(recordings: list[Path], ray_local: Any,
                                                 tmp_path: Path) -> None:
    """A Ray worker killed while it runs a recording (out of memory, a lost node) fails that
    recording with a one-line reason; a new worker runs the others, and a re-run finishes it
    from its cache."""
    import os
    import signal

    params = pipeline_params_from_cli(None, GRID)
    first = largest_first(plan_batch(recordings, tmp_path / "w"))[0].name
    killed: list[int] = []

    def kill_the_running_worker(task: str, done: float, total: float | None = None) -> None:
        if task == "stages" and done == 1 and not killed:  # the first recording's decode
            # the worker holds the recording's workdir lock from its first stage to its last
            lock = tmp_path / "w" / first / ".scanpipe" / "lock"
            pid = json.loads(lock.read_text())["pid"]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    summary = run_batch(recordings, tmp_path / "w", params, engine="ray", workers=1,
                        progress=kill_the_running_worker)
    by_name = {i["name"]: i for i in summary["items"]}
    lost = by_name.pop(first)
    bad = summary["items"][2]
    (other,) = (i for i in by_name.values() if i is not bad)
    assert killed and not lost["ok"] and other["ok"] and not bad["ok"]
    assert lost["error"].startswith("the Ray worker running this recording was lost (")
    assert lost["error"].endswith("re-run the batch to retry it: finished stages are reused")
    assert "\n" not in lost["error"]
    assert [s["stage"] for s in lost["stages"]] == ["decode"]
    assert killed[0] not in {s["pid"] for s in other["stages"]}
    assert bad["error"] == f"{recordings[2]}: not an MCAP file (bad magic bytes)"
    again = {i["name"]: i for i in run_batch(recordings[:2], tmp_path / "w", params,
                                              engine="ray", workers=1)["items"]}
    assert all(i["ok"] for i in again.values())
    # (its decode was committed in the background: kept or not, never half-written)
    assert [s["reused"] for s in again[first]["stages"]][1:] == [False] * 6
    assert (tmp_path / "w" / first / "export" / "model.glb").is_file()
    assert all(s["reused"] for s in again[other["name"]]["stages"])
