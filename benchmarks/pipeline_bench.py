"""Every stage on one simulated scan, the Open3D-only baseline beside it, and end to end.

1. The scan is simulated once and cached (:mod:`benchmarks.scans`); the chain is run once with
   the defaults into the cache to give each stage its inputs (reused by key on later runs).
2. Each stage is timed in memory (``Stage.run``, no Parquet I/O) in a forked child: median of
   the runs, throughput, peak-RSS growth (:func:`benchmarks.harness.measure`).
3. The Open3D-only baseline (:mod:`benchmarks.baseline`) on the same assembled points, timed the
   same way, its mesh kept for the accuracy figures.
4. End to end, recording → textured GLB through the runner (Parquet and files included), on the
   default path (the grid mesh at full resolution: every kept point), with Poisson (the
   baseline's method), the grid mesh at half resolution (stride 2, the old default) and the
   explicit grid path (see :func:`chain_paths`); accuracy of each against the truth, and the
   peak memory of each run (growth of the child's peak RSS, ``resource.getrusage``).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from benchmarks.baseline import BaselineMesh, baseline_summary, finite_xyz, open3d_baseline
from benchmarks.harness import Measurement, made, measure, table
from benchmarks.scans import CACHE_DIR, BenchScan, ScanFiles, cached_scan
from scanpipe.artifacts import read_artifact
from scanpipe.evaluate import evaluate_result, load_reference, mesh_metrics, stage_times
from scanpipe.params import Params
from scanpipe.pipeline import RunRecord, registry, run_chain, validate_pipeline_params
from scanpipe.protocol.registry import decode_bytes, resolve_dialect
from scanpipe.recording.reader import read_recording
from scanpipe.recording.schemas import RX
from scanpipe.render import RenderMesh
from scanpipe.rig import rig_from_table
from scanpipe.sim.options import SimOptions
from scanpipe.stages.export import export_files
from scanpipe.workdir import read_provenance

#: Stages whose input artifacts the stage benchmarks read from the cached default chain.
CHAIN_ARTIFACTS = {
    "decode": ("profiles", "motor", "frames", "rig"),
    "assemble": ("points",),
    "filter": ("points",),
    "mesh": ("mesh_vertices", "mesh_faces"),
    "texture": ("textured_faces", "texture_pages"),
}

#: Accuracy figures compared between scanpipe and the baseline (lower is better first).
LOWER_IS_BETTER = ("mesh_mean_m",)
HIGHER_IS_BETTER = ("completeness", "precision")

#: The issue's targets (issue 20: full resolution at the defaults, lab scale, 2 cores).
GRID_MESH_TARGET_S = 1.5
CHAIN_PEAK_TARGET_MB = 1536.0
END_TO_END_OVER_ACQUISITION = 1 / 20
SPEEDUP_TARGET = 5.0


def chain_params(overrides: Mapping[str, Any]) -> dict[str, Params]:
    """Validated parameters of every stage: the defaults with ``overrides``."""
    return validate_pipeline_params(list(registry().values()), overrides, "benchmark")


def chain_tables(recording: Path, workdir: Path) -> dict[str, dict[str, pa.Table]]:
    """Run (or reuse) the default chain into ``workdir``; every stage's outputs, by stage."""
    run_chain(recording, workdir, chain_params({}))
    return {stage: {name: read_artifact(workdir / stage / f"{name}.parquet")[0]
                    for name in names} for stage, names in CHAIN_ARTIFACTS.items()}


def chain_paths() -> dict[str, Mapping[str, Any]]:
    """The end-to-end paths: the defaults, Poisson (the baseline's method) and the grid mesh at
    half resolution (``mesh.grid.stride=2``, the default before issue 20); a path whose filter
    and mesh parameters equal the defaults' is left out (it would time the same work twice).
    The explicit grid path (``mesh.method=grid``) is not a path: ``auto`` meshes a scan with a
    grid by the grid, so it is the defaults' work under another key."""
    candidates: dict[str, Mapping[str, Any]] = {
        "default": {},
        "poisson": {"mesh": {"method": "poisson"}},
        "grid_stride2": {"mesh": {"method": "grid", "grid": {"stride": 2}}},
    }
    default = chain_params({})
    paths: dict[str, Mapping[str, Any]] = {}
    for name, overrides in candidates.items():
        chosen = chain_params(overrides)
        same = all(chosen[s] == default[s] for s in ("filter", "mesh"))
        if name == "default" or not same:
            paths[name] = overrides
    return paths


def stage_measurements(recording: Path, tables: Mapping[str, Mapping[str, pa.Table]],
                       scan: BenchScan, repeats: int, heavy_repeats: int) -> list[Measurement]:
    """Time each stage in memory on the cached chain's artifacts."""
    stages = registry()
    decoded, assembled = tables["decode"], tables["assemble"]["points"]
    filtered = tables["filter"]["points"]
    mesh = tables["mesh"]
    samples = pc.sum(pc.list_value_length(decoded["profiles"].column("ranges_m"))).as_py()
    # Each artifact from the nearest upstream stage that makes it (filter's points over
    # assemble's), as run_chain does.
    latest = {name: t for stage_tables in tables.values() for name, t in stage_tables.items()}
    texture_inputs = {name: latest[name] for name in stages["texture"].inputs}
    export_inputs = {name: latest[name] for name in stages["export"].inputs}
    export_tables = {**mesh, **tables["texture"]}
    faces = mesh["mesh_faces"].num_rows

    def stage(name: str, inputs: Mapping[str, Any], **overrides: Any) -> Callable[[], Any]:
        return lambda: stages[name].run(inputs, **overrides)

    # The decode stage reads the whole recording, camera frames and all (on the lab scan 95 %
    # of its bytes are JPEG frames): its samples/s are not the scanner decoder's. The decoder
    # alone (the dialect on the recorded scanner stream, what issue 17's ≥ 10 M samples/s is
    # about) is its own row.
    stream = read_recording(recording).stream("scanner", RX).data
    dialect = resolve_dialect("auto", stream)
    results = [
        measure("decode", stage("decode", {"recording": recording}), samples, "samples",
                repeats),
        measure(f"decode scanner stream ({dialect.name})",
                lambda: decode_bytes(stream, dialect), samples, "samples", repeats),
        measure("assemble", stage("assemble", {k: decoded[k] for k in ("profiles", "motor",
                                                                       "rig")}),
                assembled.num_rows, "points", repeats),
        measure("filter (defaults)", stage("filter", {"points": assembled}),
                assembled.num_rows, "points", repeats),
        measure("filter without smoothing", stage(
            "filter", {"points": assembled}, smoothing={"enabled": False}),
            assembled.num_rows, "points", repeats),
        measure("mesh grid", stage("mesh", {"points": filtered}, method="grid"),
                filtered.num_rows, "points", repeats),
    ]
    for depth in scan.poisson_depths:
        results.append(measure(f"mesh Poisson depth {depth}", stage(
            "mesh", {"points": filtered}, method="poisson", poisson={"depth": depth}),
            filtered.num_rows,
            "points", heavy_repeats))
    results += [
        measure("texture (projective)", stage("texture", texture_inputs), faces, "faces",
                heavy_repeats),
        measure("export OBJ (+MTL, PNG)",
                lambda: made(export_files(export_tables, "obj", "model")),
                faces, "faces", repeats),
        measure("export GLB", lambda: made(export_files(export_tables, "glb", "model")), faces,
                "faces", repeats),
        measure("export stage (defaults)", stage("export", export_inputs), faces, "faces",
                heavy_repeats),
    ]
    return results


def scanner_centre(rig_table: pa.Table) -> tuple[float, float, float]:
    """Where the scanner's optical centre is on the axis (its height above the rig origin)."""
    rig = rig_from_table(rig_table)
    return (0.0, float(rig.scanner.mount.translation_m[1]), 0.0)


def run_baseline(tables: Mapping[str, Mapping[str, pa.Table]], scan: BenchScan,
                 out: Path, repeats: int) -> tuple[Measurement, BaselineMesh]:
    """Time the Open3D-only baseline on the assembled points; its mesh is saved in ``out``."""
    decoded = tables["decode"]
    xyz = finite_xyz(tables["assemble"]["points"])
    rig = rig_from_table(decoded["rig"])
    centre = scanner_centre(decoded["rig"])
    depth = max(scan.poisson_depths)
    saved = out / "baseline.npz"

    def work() -> None:
        result = open3d_baseline(xyz, centre, decoded["frames"], decoded["motor"], rig,
                                 scan.baseline_voxel_m, scan.baseline_knn, depth)
        np.savez(saved, vertices=result.vertices, faces=result.faces, colors=result.colors,
                 steps=json.dumps({"steps_s": result.steps_s, "counts": result.counts}))

    measurement = measure(f"Open3D baseline (Poisson depth {depth})", work, len(xyz), "points",
                          repeats)
    with np.load(saved) as data:
        extra = json.loads(str(data["steps"]))
        result = BaselineMesh(data["vertices"], data["faces"], data["colors"],
                              extra["steps_s"], extra["counts"])
    return measurement, result


def run_end_to_end(recording: Path, out: Path, name: str, overrides: Mapping[str, Any],
                   repeats: int, to: str | None = None) -> tuple[Measurement, dict[str, float]]:
    """Time recording → textured GLB (or up to stage ``to``) through the runner, every stage
    recomputed; also the CPU seconds of each stage in the last run (process time between the
    runner's per-stage callbacks: the stage with its Parquet I/O, all threads)."""
    params = chain_params(overrides)
    workdir = out / name
    cpu_file = out / f"{name}-stage-cpu.json"

    def work() -> None:
        per_stage: dict[str, float] = {}
        clock = time.process_time()

        def on_stage(record: RunRecord) -> None:
            nonlocal clock
            now = time.process_time()
            per_stage[record.stage] = round(now - clock, 3)
            clock = now

        with runner_share() as share:
            run_chain(recording, workdir, params, force=True, to=to, on_stage=on_stage)
        cpu_file.write_text(json.dumps(per_stage))
        (out / f"{name}-runner.json").write_text(json.dumps(share))

    measurement = measure(f"end to end: {name}", work, 1.0, "runs", repeats)
    stage_cpu: dict[str, float] = json.loads(cpu_file.read_text())
    return measurement, stage_cpu


def _main_thread_s() -> tuple[float, float]:
    """(wall, run-queue) seconds of the calling thread: its time less its waits for a core is
    what the load of other processes does not lengthen (Linux; run-queue 0 elsewhere)."""
    try:
        with open("/proc/thread-self/schedstat") as handle:
            queued = int(handle.read().split()[1]) / 1e9
    except (OSError, ValueError, IndexError):
        queued = 0.0
    return time.perf_counter(), queued


@contextmanager
def runner_share() -> Iterator[dict[str, float]]:
    """The runner's share of a chain run in this block, filled in at its end: CPU (all threads)
    and the main thread's time (less its waits for a core) spent outside the stages' own
    calls (``Stage.call``): reading inputs, keys, writing and flushing outputs, provenance,
    handing memory back — the runner overhead of issue 20."""
    from scanpipe.stage import Stage

    share: dict[str, float] = {}
    inside = {"cpu": 0.0, "time": 0.0}
    real = Stage.call

    def timed(self: Stage, *args: Any, **kwargs: Any) -> Any:
        cpu, (wall, queued) = time.process_time(), _main_thread_s()
        try:
            return real(self, *args, **kwargs)
        finally:
            now_wall, now_queued = _main_thread_s()
            inside["cpu"] += time.process_time() - cpu
            inside["time"] += (now_wall - wall) - (now_queued - queued)

    cpu, (wall, queued) = time.process_time(), _main_thread_s()
    Stage.call = timed  # type: ignore[method-assign]
    try:
        yield share
    finally:
        Stage.call = real  # type: ignore[method-assign]
        now_wall, now_queued = _main_thread_s()
        total_time = (now_wall - wall) - (now_queued - queued)
        share.update(runner_cpu_s=round(time.process_time() - cpu - inside["cpu"], 3),
                     runner_time_s=round(total_time - inside["time"], 3),
                     stages_cpu_s=round(inside["cpu"], 3),
                     stages_time_s=round(inside["time"], 3))


#: Runs one chain in a fresh interpreter and prints its figures as JSON (see chain_memory).
#: Peaks come from the kernel's high-water mark of this process's memory (VmHWM), not from
#: ``getrusage``: a child started by fork/vfork + exec inherits its parent's ``ru_maxrss``
#: (Linux keeps the larger of the old and the new address space's), so a benchmark process
#: that had used 9 GB made every chain it started report 9 GB. Each stage's own peak: the mark
#: is reset after each stage (writing 5 to /proc/self/clear_refs); without that permission the
#: stage's peak is the peak so far.
_CHAIN_CHILD = """
import scanpipe  # first, as a user's ``scanpipe run`` has it (the allocator's set-up)
import json, sys, threading, time
from pathlib import Path
import benchmarks.pipeline_bench as bench
from scanpipe.pipeline import chain_to
import scipy.ndimage, scipy.sparse.csgraph, open3d, cv2  # the stages' imports: before the base
recording, workdir, to, overrides = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4]
def status_mb(*fields):
    # every field from one read: VmHWM and VmRSS of one moment (read apart, a background
    # commit thread's allocation in between made the RSS "after" exceed the peak)
    with open("/proc/self/status") as status:
        found = {l.split(":")[0]: int(l.split()[1]) / 1024 for l in status
                 if l.split(":")[0] in fields}
    return found[fields[0]] if len(fields) == 1 else tuple(found[f] for f in fields)
def reset_peak():
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
        return True
    except OSError:
        return False
base = status_mb("VmRSS")
resets = reset_peak()
stages, clock, so_far = {}, time.process_time(), base
# the timeline: the RSS every 20 ms, by stage and by its progress task (what it was doing)
order = [s.name for s in chain_to(None, to or None)]
now_in = {"stage": order[0], "task": "(start)"}
timeline, sampling = {}, True
def take_sample():
    rss = status_mb("VmRSS")
    at = timeline.setdefault(now_in["stage"], {"entry_mb": rss, "peak_mb": rss, "tasks": {}})
    at["peak_mb"] = max(at["peak_mb"], rss)
    at["tasks"][now_in["task"]] = max(at["tasks"].get(now_in["task"], 0), rss)
def sample():
    while sampling:
        take_sample()
        time.sleep(0.02)
def progress(task, done, total=None):
    now_in["task"] = task
def on_stage(record):
    global clock, so_far
    following = order.index(record.stage) + 1
    now_in.update(stage=order[following] if following < len(order) else "(end)", task="(start)")
    take_sample()  # every stage has an entry, however short it is
    now = time.process_time()
    peak, rss = status_mb("VmHWM", "VmRSS")
    so_far = max(so_far, peak)
    stages[record.stage] = {
        "cpu_s": round(now - clock, 3), "seconds": round(record.seconds, 3),
        "peak_rss_mb": peak, "rss_after_mb": rss, "peak_rss_mb_so_far": so_far}
    clock = now
    reset_peak()
take_sample()
sampler = threading.Thread(target=sample, daemon=True)
sampler.start()
wall, cpu = time.perf_counter(), time.process_time()
bench.run_chain(recording, workdir, bench.chain_params(json.loads(overrides)), force=True,
                to=to or None, on_stage=on_stage, progress=progress)
seconds, cpu_s = time.perf_counter() - wall, time.process_time() - cpu
sampling = False
sampler.join()
print(json.dumps({"seconds": seconds, "cpu_s": cpu_s,
                  "rss_after_imports_mb": base, "per_stage_peaks": resets,
                  "peak_rss_mb": max(so_far, status_mb("VmHWM")), "stages": stages,
                  "timeline": timeline}))
"""


def chain_memory(recording: Path, workdir: Path, overrides: Mapping[str, Any],
                 to: str | None = None) -> dict[str, Any]:
    """Peak memory of one chain run (every stage recomputed) in a fresh interpreter, as a user's
    ``scanpipe run`` has it: the absolute peak RSS, the RSS after the imports, the growth,
    per stage the CPU seconds and the peak so far, and the ``timeline``: per stage its RSS at
    entry and its peak, and the peak during each of its progress tasks (what it was doing).
    A forked child's growth would start from the benchmark's own (larger) peak and hide the
    chain's."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run(
        [sys.executable, "-c", _CHAIN_CHILD, str(recording), str(workdir), to or "",
         json.dumps(overrides)], capture_output=True, text=True, env=env, cwd=root, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"chain memory run failed: {done.stderr.strip()[-2000:]}")
    figures: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    figures["growth_mb"] = figures["peak_rss_mb"] - figures["rss_after_imports_mb"]
    return figures


def mesh_resolution(workdir: Path) -> dict[str, Any]:
    """What the run's mesh stage meshed (its report in the artifact's provenance): the method,
    the grid stride and how many of the usable points became vertices; ``full_resolution``
    when nothing was left out by a stride (no hidden downsampling)."""
    report = read_provenance(workdir / "mesh" / "mesh_vertices.parquet").get("report", {})
    stride = report.get("grid_stride")
    points = report.get("points")
    meshed = report.get("points_meshed", points)
    return {"method": report.get("method"), "grid_stride": stride, "points": points,
            "points_meshed": meshed, "vertices": report.get("vertices"),
            "faces": report.get("faces"), "mesh_cpu_seconds": report.get("cpu_seconds"),
            "full_resolution": report.get("method") == "grid" and stride == 1
            and meshed == points}


def baseline_accuracy(result: BaselineMesh, truth: Path, samples: int) -> dict[str, Any]:
    """Mesh accuracy of the baseline against the truth (scanpipe.evaluate)."""
    mesh = RenderMesh(result.vertices.astype(np.float32), result.faces.astype(np.int32),
                      vertex_colors=result.colors)
    return mesh_metrics(mesh, load_reference(truth), 0.02, samples)


def at_least_as_accurate(ours: Mapping[str, Any], theirs: Mapping[str, Any]) -> bool:
    """Equal or better on mean distance, completeness and precision (1 mm / 1 % slack)."""
    lower = all(ours[k] <= theirs[k] + 0.001 for k in LOWER_IS_BETTER)
    higher = all(ours[k] >= theirs[k] - 0.01 for k in HIGHER_IS_BETTER)
    return lower and higher


def better_than(ours: Mapping[str, Any], theirs: Mapping[str, Any]) -> bool:
    """Better without slack: a smaller mean distance, a larger completeness, and a precision
    at least as large (it saturates at 1)."""
    if any(ours[k] is None for k in (*LOWER_IS_BETTER, *HIGHER_IS_BETTER)):
        return False
    return (ours["mesh_mean_m"] < theirs["mesh_mean_m"]
            and ours["completeness"] > theirs["completeness"]
            and ours["precision"] >= theirs["precision"])


def mesh_size(workdir: Path) -> dict[str, int]:
    """Vertex and face counts of a run's mesh artifacts (from the Parquet footers)."""
    return {name: pq.read_metadata(workdir / "mesh" / f"mesh_{name}.parquet").num_rows
            for name in ("vertices", "faces")}


def acquisition_seconds(files: ScanFiles) -> dict[str, float]:
    """How long acquiring the scan takes: positions / scan rate (one profile per position, the
    issue's measure), and the simulated step-and-scan session (moves and settling included)."""
    scan_hz = float(files.options["rig"]["scanner"]["scan_hz"])
    return {"positions": float(files.summary["positions"]), "scan_hz": scan_hz,
            "profiles_over_scan_hz_s": files.summary["positions"] / scan_hz,
            "session_s": float(files.summary["duration_s"])}


def target(name: str, value: float | None, limit: float, unit: str,
           at_least: bool = False) -> dict[str, Any]:
    """One target row: met when ``value`` is within ``limit`` (≤, or ≥ with ``at_least``)."""
    met = value is not None and (value >= limit if at_least else value <= limit)
    return {"name": name, "value": value, "target": f"{'≥' if at_least else '≤'} {limit:g}",
            "unit": unit, "met": met}


def targets(by_name: Mapping[str, Measurement], e2e_s: float, acquisition_s: float,
            speedup: float, better: bool, chain_peak_mb: float,
            cpu: Mapping[str, float] | None = None,
            stage_peaks_mb: Mapping[str, float] | None = None) -> list[dict[str, Any]]:
    """The issues' targets against the figures (issue 20's for mesh, end to end, memory).

    ``cpu``: the same figures in CPU seconds (``e2e_s``, ``speedup``, ``mesh_peak_mb``): rows
    beside the wall-time ones, for a loaded machine where wall time counts other processes.
    ``stage_peaks_mb``: each stage's own peak in the whole chain (``chain_memory``): a row for
    the chain outside the texture stage (the runner, export and the stages before texture).
    """

    def seconds(name: str) -> float | None:
        return by_name[name].median_s if name in by_name else None

    cpu_rows = []
    if cpu is not None:
        mesh = by_name.get("mesh grid")
        cpu_rows = [
            target("grid mesh at full resolution (CPU)", mesh.cpu_median_s if mesh else None,
                   GRID_MESH_TARGET_S, "s CPU"),
            target("end to end / acquisition (CPU)", cpu["e2e_s"] / acquisition_s,
                   END_TO_END_OVER_ACQUISITION, "×"),
            target("speed-up over the Open3D baseline (CPU)", cpu["speedup"], SPEEDUP_TARGET,
                   "×", at_least=True),
            target("peak memory of the default chain up to the mesh (peak RSS)",
                   cpu["mesh_peak_mb"], CHAIN_PEAK_TARGET_MB, "MB"),
        ]

    poisson9 = by_name.get("mesh Poisson depth 9")
    return [
        target("decode scanner stream", next(
            m for name, m in by_name.items() if name.startswith("decode scanner stream")
        ).throughput / 1e6, 10, "M samples/s", at_least=True),
        target("assemble", by_name["assemble"].throughput / 1e6, 20, "M points/s",
               at_least=True),
        target("grid filters", seconds("filter (defaults)"), 1, "s"),
        target("grid mesh at full resolution", seconds("mesh grid"), GRID_MESH_TARGET_S, "s"),
        target("Poisson depth 9 time", poisson9.median_s if poisson9 else None, 60, "s"),
        target("Poisson depth 9 memory", poisson9.peak_rss_mb if poisson9 else None, 2048, "MB"),
        target("texture", seconds("texture (projective)"), 60, "s"),
        target("GLB export", seconds("export GLB"), 2, "s"),
        target("end to end / acquisition", e2e_s / acquisition_s, END_TO_END_OVER_ACQUISITION,
               "×"),
        target("peak memory of the default chain (peak RSS, fresh process)", chain_peak_mb,
               CHAIN_PEAK_TARGET_MB, "MB"),
        target("speed-up over the Open3D baseline", speedup, SPEEDUP_TARGET, "×",
               at_least=True),
        {"name": "mesh mean distance, completeness and precision better than the baseline",
         "value": better, "target": "true", "unit": "", "met": better},
        *cpu_rows,
        *([target("peak memory of the default chain outside texture (each stage's own peak)",
                  max((v for k, v in stage_peaks_mb.items() if k != "texture"), default=None),
                  CHAIN_PEAK_TARGET_MB, "MB")] if stage_peaks_mb is not None else []),
    ]


def run(scan: BenchScan, repeats: int = 3, cache_dir: Path = CACHE_DIR,
        say: Callable[[str], None] = print) -> dict[str, Any]:
    """The whole benchmark on ``scan``; returns the figures (see docs/performance.md)."""
    heavy = max(1, repeats // 3)
    load_start = os.getloadavg()
    say(f"scan {scan.name}: simulating (or reusing the cache in {cache_dir})")
    files = cached_scan(scan, cache_dir)
    folder = files.recording.parent
    say("running the default chain once for the stages' inputs (cached by key)")
    tables = chain_tables(files.recording, folder / "chain")
    say("timing the stages")
    stages = stage_measurements(files.recording, tables, scan, repeats, heavy)
    by_name = {m.name: m for m in stages}
    out = folder / "runs"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    say("timing the Open3D-only baseline")
    baseline_m, baseline = run_baseline(tables, scan, out, heavy)
    say(f"timing end to end ({', '.join(chain_paths())})")
    paths = chain_paths()
    e2e, stage_cpu = {}, {}
    for name, overrides in paths.items():
        e2e[name], stage_cpu[name] = run_end_to_end(files.recording, out, name, overrides,
                                                    heavy)
    say("peak memory of the default chain, whole and up to the mesh (fresh interpreters)")
    memory = {"whole": chain_memory(files.recording, out / "memory_whole", {}),
              "to_mesh": chain_memory(files.recording, out / "memory_to_mesh", {}, to="mesh")}
    say("evaluating against the truth")
    truth_baseline = baseline_accuracy(baseline, files.truth, scan.eval_samples)
    comparison: dict[str, Any] = {"baseline": {
        "seconds": baseline_m.median_s, "cpu_s": baseline_m.cpu_median_s,
        "peak_rss_mb": baseline_m.peak_rss_mb,
        **baseline_summary(baseline), "accuracy": truth_baseline}}
    span = ("filter", "mesh", "texture")
    for name in paths:
        workdir = out / name
        evaluation = evaluate_result(workdir, files.truth, samples=scan.eval_samples)
        times = stage_times(workdir)
        points_to_mesh_s = sum(times.get(s, 0.0) for s in span)
        points_to_mesh_cpu_s = sum(stage_cpu[name].get(s, 0.0) for s in span)
        comparison[name] = {
            "end_to_end_s": e2e[name].median_s, "end_to_end_cpu_s": e2e[name].cpu_median_s,
            "peak_rss_mb": e2e[name].peak_rss_mb,
            "stage_seconds": times, "stage_cpu_seconds": stage_cpu[name],
            # the runner's own share (outside the stages' calls), last run
            "runner": json.loads((out / f"{name}-runner.json").read_text()),
            "points_to_textured_mesh_s": points_to_mesh_s,
            "points_to_textured_mesh_cpu_s": points_to_mesh_cpu_s,
            "speedup_over_baseline": baseline_m.median_s / points_to_mesh_s,
            "speedup_over_baseline_cpu": baseline_m.cpu_median_s / points_to_mesh_cpu_s,
            "mesh_resolution": mesh_resolution(workdir),
            "glb": str(workdir / "export" / "model.glb"),
            "glb_exists": (workdir / "export" / "model.glb").is_file(),
            "mesh": mesh_size(workdir),
            "accuracy": {k: evaluation[k] for k in (
                "mesh_mean_m", "mesh_rms_m", "precision", "completeness", "fscore",
                "texture_psnr_db", "points_mean_m")},
            "at_least_as_accurate_as_baseline": at_least_as_accurate(evaluation,
                                                                     truth_baseline),
            "better_than_baseline": better_than(evaluation, truth_baseline),
        }
    acquisition = acquisition_seconds(files)
    default = comparison["default"]
    frame_sizes = _frame_sizes(tables["decode"]["frames"])
    # The rig's cameras before the simulator scales them (SimOptions.camera_scale).
    rig_sizes = {cam.id: [cam.width, cam.height]
                 for cam in SimOptions.model_validate(files.options).rig.cameras}
    return {
        "scan": asdict(scan),
        "simulation": {**{k: v for k, v in files.summary.items()
                          if k not in ("options", "recording", "truth")},
                       "reused": files.reused,
                       "frame_size": _frame_size(tables["decode"]["frames"]),
                       "frame_sizes": frame_sizes,
                       "rig_camera_sizes": rig_sizes,
                       # Every camera's frames at its rig resolution (Full HD for the
                       # pinhole cameras), none scaled down.
                       "frames_at_rig_resolution": bool(frame_sizes) and all(
                           rig_sizes.get(k) == v for k, v in frame_sizes.items()),
                       "camera_fps": files.options["camera_fps"],
                       "frames_per_camera": scan.video_s * scan.video_fps},
        "repeats": {"light": repeats, "heavy": heavy},
        "stages": stages,
        "baseline_measurement": baseline_m,
        "end_to_end_measurements": list(e2e.values()),
        "comparison": comparison,
        "chain_memory": memory,
        "acquisition": acquisition,
        "end_to_end_over_acquisition": {
            name: comparison[name]["end_to_end_s"] / acquisition["profiles_over_scan_hz_s"]
            for name in paths},
        "end_to_end_cpu_over_acquisition": {
            name: comparison[name]["end_to_end_cpu_s"] / acquisition["profiles_over_scan_hz_s"]
            for name in paths},
        "targets": targets(by_name, default["end_to_end_s"],
                           acquisition["profiles_over_scan_hz_s"],
                           default["speedup_over_baseline"],
                           default["better_than_baseline"], memory["whole"]["peak_rss_mb"],
                           cpu={"e2e_s": default["end_to_end_cpu_s"],
                                "speedup": default["speedup_over_baseline_cpu"],
                                "mesh_peak_mb": memory["to_mesh"]["peak_rss_mb"]},
                           stage_peaks_mb={
                               k: v.get("peak_rss_mb", v["peak_rss_mb_so_far"])
                               for k, v in memory["whole"]["stages"].items()}),
        "load_average_start": load_start,
        "load_average_end": os.getloadavg(),
    }


def _frame_sizes(frames: pa.Table) -> dict[str, list[int]]:
    """``[width, height]`` of each camera's frames (its first frame)."""
    sizes: dict[str, list[int]] = {}
    ids = frames.column("camera_id").to_pylist()
    widths, heights = frames.column("width").to_pylist(), frames.column("height").to_pylist()
    for camera, width, height in zip(ids, widths, heights, strict=True):
        sizes.setdefault(str(camera), [int(width), int(height)])
    return sizes


def _frame_size(frames: pa.Table) -> list[int]:
    if frames.num_rows == 0:
        return [0, 0]
    return [int(frames.column("width")[0].as_py()), int(frames.column("height")[0].as_py())]


def _fmt(value: Any, unit: str = "") -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}{unit}"
    return f"{value}{unit}"


def report(results: Mapping[str, Any]) -> str:
    """The results as text tables: stages, baseline vs scanpipe, end to end, targets."""
    stages: list[Measurement] = results["stages"]
    rows: list[tuple[str, ...]] = [
        (m.name, f"{m.median_s:.3f} s", f"{m.cpu_median_s:.3f} s",
         f"{m.throughput / 1e6:.2f} M {m.unit}/s", f"{m.peak_rss_mb:.0f} MB",
         str(len(m.runs_s))) for m in stages]
    parts = [table(rows, ("stage (in memory)", "median", "CPU", "throughput", "peak RSS",
                          "runs"))]
    comparison = results["comparison"]
    base = comparison["baseline"]
    rows = [("Open3D baseline", f"{base['seconds']:.1f} s / {base['cpu_s']:.1f} s", "-",
             "1", f"{base['counts']['faces'] / 1e6:.2f} M", f"{base['peak_rss_mb']:.0f} MB",
             _fmt(base["accuracy"]["mesh_mean_m"] * 1000, " mm"),
             _fmt(base["accuracy"]["completeness"]), _fmt(base["accuracy"]["precision"]), "-")]
    for name in results["end_to_end_over_acquisition"]:
        path = comparison[name]
        acc = path["accuracy"]
        rows.append((f"scanpipe {name}", f"{path['points_to_textured_mesh_s']:.1f} s / "
                                         f"{path['points_to_textured_mesh_cpu_s']:.1f} s",
                     f"{path['end_to_end_s']:.1f} s / {path['end_to_end_cpu_s']:.1f} s",
                     f"{path['speedup_over_baseline']:.2f}× / "
                     f"{path['speedup_over_baseline_cpu']:.2f}×",
                     f"{path['mesh']['faces'] / 1e6:.2f} M", f"{path['peak_rss_mb']:.0f} MB",
                     _fmt(acc["mesh_mean_m"] * 1000 if acc["mesh_mean_m"] is not None
                          else None, " mm"),
                     _fmt(acc["completeness"]), _fmt(acc["precision"]),
                     _fmt(acc["texture_psnr_db"], " dB")))
    parts.append("the runner outside the stages' calls (reading, keys, writing, flushing; "
                 "main thread's time less its waits for a core / CPU): " + ", ".join(
                     f"{name} {comparison[name]['runner']['runner_time_s']:.1f} s / "
                     f"{comparison[name]['runner']['runner_cpu_s']:.1f} s"
                     for name in results["end_to_end_over_acquisition"]))
    parts.append(table(rows, ("path", "points → coloured mesh (wall / CPU)",
                              "end to end (wall / CPU)", "speed-up (wall / CPU)", "faces",
                              "peak RSS", "mesh mean", "completeness@2cm", "precision@2cm",
                              "PSNR")))
    default = comparison["default"]
    stage_names = list(default["stage_cpu_seconds"])
    total_cpu = sum(default["stage_cpu_seconds"].values()) or 1.0
    rows = [(stage, _fmt(default["stage_seconds"].get(stage), " s"),
             f"{default['stage_cpu_seconds'][stage]:.2f} s",
             f"{100 * default['stage_cpu_seconds'][stage] / total_cpu:.0f} %")
            for stage in stage_names]
    parts.append(table(rows, ("default path, by stage (end to end)", "wall", "CPU",
                              "share of CPU")))
    resolution = default["mesh_resolution"]
    sim = results["simulation"]
    parts.append(
        f"default mesh: {resolution['method']}, stride {resolution['grid_stride']}, "
        f"{resolution['points_meshed']} of {resolution['points']} usable points meshed → "
        f"{resolution['faces']} faces (full resolution: "
        f"{_fmt(resolution['full_resolution'])}); frames per camera "
        + ", ".join(f"{k} {w}×{h}" for k, (w, h) in sim["frame_sizes"].items())
        + f" (each at its rig camera's resolution: {_fmt(sim['frames_at_rig_resolution'])})")
    for name, label in (("whole", "the default chain"), ("to_mesh", "decode → mesh")):
        run = results["chain_memory"][name]
        parts.append(
            f"peak memory of {label} (fresh process): {run['peak_rss_mb']:.0f} MB "
            f"({run['rss_after_imports_mb']:.0f} MB after the imports); peak so far after "
            + ", ".join(f"{k} {v['peak_rss_mb_so_far']:.0f}" for k, v in run["stages"].items())
            + " MB; each stage's own peak: "
            + ", ".join(f"{k} {v.get('peak_rss_mb', v['peak_rss_mb_so_far']):.0f}"
                        for k, v in run["stages"].items()) + " MB")
    acq = results["acquisition"]
    parts.append(
        f"acquisition: {acq['positions']:.0f} positions / {acq['scan_hz']:g} Hz = "
        f"{acq['profiles_over_scan_hz_s']:.0f} s (simulated step-and-scan session "
        f"{acq['session_s']:.0f} s); end to end / acquisition: " + ", ".join(
            f"{k} {v:.3f}" for k, v in results["end_to_end_over_acquisition"].items())
        + "; in CPU time: " + ", ".join(
            f"{k} {v:.3f}" for k, v in results["end_to_end_cpu_over_acquisition"].items()))
    rows = [(str(t["name"]), _fmt(t["value"], f" {t['unit']}" if t["unit"] else ""), t["target"],
             "met" if t["met"] else "MISSED") for t in results["targets"]]
    parts.append(table(rows, ("target", "measured", "target", "")))
    if results.get("quick"):
        parts.append("(--quick: the targets are for the lab-scale scan; this run only shows that "
                     "everything works)")
    return "\n\n".join(parts)
