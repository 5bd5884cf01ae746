"""Smoke test of the benchmark's core (``python -m benchmarks``) on a tiny simulated scan.

Asserts the structure of the results and that every figure is a positive number; never speed.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: `benchmarks`

from benchmarks import harness
from benchmarks.pipeline_bench import report, run
from benchmarks.scans import BenchScan, cached_scan, sim_options

TINY = BenchScan("tiny", 4.0, 3.6, video_s=1.0, video_fps=4.0, camera_scale=0.125,
                 poisson_depths=(5, 6), baseline_voxel_m=0.05, baseline_knn=10,
                 eval_samples=2000)


def positive(value: Any) -> bool:
    return isinstance(value, int | float) and math.isfinite(value) and value > 0


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    cache = tmp_path_factory.mktemp("bench-cache")
    figures = run(TINY, repeats=1, cache_dir=cache, say=lambda text: None)
    saved = harness.save(figures, "tiny", results_dir=cache / "results")
    loaded: dict[str, Any] = json.loads(saved.read_text())
    loaded["_report"] = report(figures)
    loaded["_cache"] = str(cache)
    return loaded


@pytest.mark.slow
def test_every_stage_is_measured_with_positive_figures(results: dict[str, Any]) -> None:
    names = [m["name"] for m in results["stages"]]
    assert names == ["decode", "decode scanner stream (ldoem)", "assemble", "filter (defaults)",
                     "filter without smoothing", "mesh grid", "mesh Poisson depth 5",
                     "mesh Poisson depth 6", "texture (projective)", "export OBJ (+MTL, PNG)",
                     "export GLB", "export stage (defaults)"]
    for m in results["stages"]:
        assert positive(m["median_s"]) and positive(m["throughput"]) and positive(m["items"])
        assert len(m["runs_s"]) == 1 and m["peak_rss_mb"] >= 0
        assert len(m["cpu_runs_s"]) == 1 and positive(m["cpu_median_s"])
    assert results["machine"]["cpus"] >= 1 and len(results["load_average_start"]) == 3


@pytest.mark.slow
def test_baseline_and_paths_are_compared_on_accuracy_and_time(results: dict[str, Any]
                                                              ) -> None:
    comparison = results["comparison"]
    base = comparison["baseline"]
    assert positive(base["seconds"])
    assert set(base["steps_s"]) == {"voxel_downsample", "statistical_outlier", "knn_normals",
                                    "poisson", "vertex_colour"}
    assert base["counts"]["after_voxel"] <= base["counts"]["points_in"]
    assert positive(base["counts"]["faces"])
    paths = [name for name in comparison if name != "baseline"]
    assert paths[0] == "default" and "poisson" in paths and "grid_stride2" in paths
    default_faces = comparison["default"]["mesh"]["faces"]
    assert comparison["grid_stride2"]["mesh"]["faces"] < 0.5 * default_faces  # half resolution
    for path in paths:
        entry = comparison[path]
        assert entry["glb_exists"] and Path(entry["glb"]).stat().st_size > 0
        assert positive(entry["end_to_end_s"]) and positive(entry["points_to_textured_mesh_s"])
        assert positive(entry["speedup_over_baseline"])
        runner = entry["runner"]  # the runner's share, outside the stages' own calls
        assert positive(runner["runner_cpu_s"]) and positive(runner["stages_cpu_s"])
        assert runner["runner_cpu_s"] + runner["stages_cpu_s"] <= entry["end_to_end_cpu_s"] * 1.5
        assert set(entry["stage_seconds"]) == {"decode", "calibrate", "assemble", "filter", "mesh",
                                               "texture", "export"}
        assert set(entry["stage_cpu_seconds"]) == set(entry["stage_seconds"])
        assert all(v >= 0 for v in entry["stage_cpu_seconds"].values())
        assert positive(entry["end_to_end_cpu_s"]) and positive(entry["speedup_over_baseline_cpu"])
        assert entry["points_to_textured_mesh_cpu_s"] <= entry["end_to_end_cpu_s"]
        assert isinstance(entry["at_least_as_accurate_as_baseline"], bool)
        assert isinstance(entry["better_than_baseline"], bool)
        assert positive(entry["mesh"]["faces"]) and positive(entry["mesh"]["vertices"])
    for acc in (base["accuracy"], comparison["default"]["accuracy"],
                comparison["poisson"]["accuracy"]):
        assert positive(acc["mesh_mean_m"]) and 0 < acc["completeness"] <= 1
        assert 0 < acc["precision"] <= 1
    assert positive(comparison["default"]["accuracy"]["texture_psnr_db"])
    # The default path meshes every usable point (no hidden stride); stride 2 does not.
    assert comparison["default"]["mesh_resolution"]["full_resolution"] is True
    assert comparison["default"]["mesh_resolution"]["grid_stride"] == 1
    assert comparison["grid_stride2"]["mesh_resolution"]["full_resolution"] is False
    assert positive(base["cpu_s"])
    memory = results["chain_memory"]
    assert list(memory["to_mesh"]["stages"]) == ["decode", "calibrate", "assemble", "filter",
                                                 "mesh"]
    assert list(memory["whole"]["stages"])[-2:] == ["texture", "export"]
    for chain in memory.values():  # a fresh process: its peak is above what the imports took
        assert chain["peak_rss_mb"] >= chain["rss_after_imports_mb"] > 50
        assert chain["growth_mb"] == pytest.approx(
            chain["peak_rss_mb"] - chain["rss_after_imports_mb"])
        assert positive(chain["cpu_s"]) and positive(chain["seconds"])
    assert memory["whole"]["peak_rss_mb"] >= memory["to_mesh"]["peak_rss_mb"] * 0.9


@pytest.mark.slow
def test_acquisition_targets_and_table(results: dict[str, Any]) -> None:
    acq = results["acquisition"]
    assert acq["profiles_over_scan_hz_s"] == pytest.approx(acq["positions"] / acq["scan_hz"])
    assert acq["session_s"] > acq["profiles_over_scan_hz_s"]
    assert all(positive(v) for v in results["end_to_end_over_acquisition"].values())
    simulation = results["simulation"]
    cameras = sim_options(TINY).nominal_rig().cameras
    assert simulation["frames"] == pytest.approx(
        len(cameras) * TINY.video_s * TINY.video_fps, abs=len(cameras))
    cam = cameras[0]  # the rig's camera at 1/8 scale
    assert simulation["frame_size"] == [cam.width, cam.height]
    assert max(cam.width, cam.height) == 240
    assert simulation["frame_sizes"][cam.id] == [cam.width, cam.height]
    assert simulation["frames_at_rig_resolution"] is False  # 1/8 scale
    rows = {t["name"]: t for t in results["targets"]}
    assert len(rows) == 17 and all(isinstance(t["met"], bool) for t in rows.values())
    outside = rows["peak memory of the default chain outside texture (each stage's own peak)"]
    stages = results["chain_memory"]["whole"]["stages"]
    assert positive(outside["value"]) and outside["value"] == max(
        v["peak_rss_mb"] for k, v in stages.items() if k != "texture")
    assert positive(rows["grid mesh at full resolution (CPU)"]["value"])
    assert positive(rows["decode scanner stream"]["value"])
    assert positive(rows["end to end / acquisition (CPU)"]["value"])
    assert positive(rows["peak memory of the default chain (peak RSS, fresh process)"]["value"])
    assert rows["Poisson depth 9 time"]["value"] is None  # the tiny scan stops at depth 6
    assert not rows["Poisson depth 9 time"]["met"]
    for heading in ("stage (in memory)", "Open3D baseline", "scanpipe poisson", "MISSED",
                    "default path, by stage", "default mesh: grid, stride 1",
                    "peak memory of decode → mesh"):
        assert heading in results["_report"]


@pytest.mark.slow
def test_the_scan_is_simulated_once_and_then_reused(results: dict[str, Any]) -> None:
    cache = Path(results["_cache"])
    again = cached_scan(TINY, cache)
    assert again.reused and again.recording.is_file()
    assert len([p for p in cache.iterdir() if p.name.startswith("tiny-")]) == 1
    assert not results["simulation"]["reused"]


def test_decode_benchmarks_report_through_the_shared_helpers(
        capsys: pytest.CaptureFixture[str]) -> None:
    """bench_sick / bench_scip / bench_ldrobot print their figures with the harness's table and
    throughput line (wall and CPU against the target, and the load)."""
    sys.path.insert(0, str(Path(harness.__file__).parent))
    from benchmarks import bench_ldrobot, bench_scip, bench_sick

    m = harness.Measurement("stream decoder", 0.5, [0.5], 12.0, 10e6, "samples")
    assert "20.0 M samples/s" in harness.measurement_table([m])
    line = harness.throughput_line("x", 20e6, 25e6, 10e6, 3.0)
    assert line == ("x: 20.0 M samples/s wall, 25.0 M per CPU second (target 10 M wall: met; "
                    "load average 3.0)")
    assert "NOT met" in harness.throughput_line("x", 9e6, 25e6, 10e6, 3.0)
    common = {"measurements": [m], "target_samples_per_s": 10e6, "load_average": (3.0, 2, 1)}
    bench_sick.show({**common, "cola_b_samples_per_s": 30e6, "cola_b_cpu_samples_per_s": 31e6,
                     "cola_a_samples_per_s": 9e6, "cola_a_cpu_samples_per_s": 15e6,
                     "recovery": {}, "fuzz": {}})
    bench_scip.show({**common, "scans": 5, "samples_per_scan": 1081, "stream_bytes": 1e6,
                     "samples_per_s": 20e6, "cpu_samples_per_s": 22e6,
                     "damage": {"recovered": 4, "intact": 4, "unsent_decoded": 0}})
    bench_ldrobot.show({**common, "seconds": 30.0, "samples": 1e6, "stream_bytes": 1e6,
                        "revolutions": 3, "samples_per_s": 20e6, "cpu_samples_per_s": 22e6,
                        "recovery": {"recovered": 9, "intact": 9, "recovered_share": 1.0,
                                     "false_packets": 0}})
    out = capsys.readouterr().out
    assert out.count("peak RSS") == 3
    assert "cola_b: 30.0 M samples/s wall, 31.0 M per CPU second (target 10 M wall: met" in out
    assert "cola_a: 9.0 M samples/s wall, 15.0 M per CPU second (target 10 M wall: NOT met" in out
    assert "22.0 M per CPU second" in out
