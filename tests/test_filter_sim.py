"""Filters on the virtual rig: mixed pixels at the room's depth edges, and smoothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.pipeline import get_stage
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.truth import load_truth


def distances(points: pa.Table, truth_dir: Path) -> np.ndarray:
    xyz = np.stack([points.column(c).to_numpy() for c in "xyz"], axis=1)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return np.asarray(load_truth(truth_dir).scene.distance_m(xyz))


@pytest.mark.slow
def test_filters_remove_mixed_pixels_and_smoothing_reduces_noise(tmp_path: Path) -> None:
    sim = SimOptions(motor_step_deg=5.0, beam_step_deg=1.0, cameras=False, mixed_pixels=True)
    simulate_direct(tmp_path / "scan.mcap", tmp_path / "truth", sim)
    decoded = get_stage("decode").run({"recording": tmp_path / "scan.mcap"}).tables
    points = get_stage("assemble").run(
        {name: decoded[name] for name in ("profiles", "motor", "rig")}).tables["points"]
    raw = distances(points, tmp_path / "truth")
    filtered = get_stage("filter").run({"points": points}, smoothing={"enabled": False})
    cleaned = distances(filtered.tables["points"], tmp_path / "truth")
    assert filtered.report["filters"]["depth_edges"]["taken"] > 0
    far = 0.05  # 5 σ: a mixed pixel, not noise
    assert np.count_nonzero(cleaned > far) < 0.5 * np.count_nonzero(raw > far)
    assert np.sqrt(np.mean(cleaned**2)) < np.sqrt(np.mean(raw**2))
    smoothed = get_stage("filter").run({"points": points})  # smoothing is on by default
    rms_smoothed = np.sqrt(np.mean(distances(smoothed.tables["points"], tmp_path / "truth") ** 2))
    assert rms_smoothed < 0.85 * np.sqrt(np.mean(cleaned**2))
