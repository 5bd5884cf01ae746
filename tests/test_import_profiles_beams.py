"""import-profiles, long layout, beam angles as other tools write them: per-profile float
noise in the last digits (once a crash: the 'step' became 1e-8° and the grid 10¹⁰ columns) and
a beam off the equal-step grid (once silently moved to the nearest column)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from scanpipe.artifacts import read_artifact

RNG = np.random.default_rng(2)


def write_long(path: Path, beams: list[np.ndarray], ranges: list[np.ndarray]) -> None:
    lines = ["profile,beam_deg,platform_deg,range_m"]
    for k, (beam, r) in enumerate(zip(beams, ranges, strict=True)):
        lines += [f"{k},{b!r},{k * 0.5},{v!r}" for b, v in zip(beam.tolist(), r.tolist(),
                                                               strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_float_noise_in_beam_angles_is_one_grid(tmp_path: Path, cli: Any) -> None:
    # Angles computed in float32 per profile and printed at full precision: the same beam
    # differs in the 8th digit from profile to profile.
    nominal = -135.0 + np.arange(1081) * 0.25
    beams = [nominal.astype(np.float32).astype(np.float64) + RNG.normal(0, 2e-6, nominal.size)
             for _ in range(4)]
    ranges = [RNG.uniform(0.5, 5.0, nominal.size) for _ in range(4)]
    path = tmp_path / "noisy.csv"
    write_long(path, beams, ranges)
    result = cli("import-profiles", path, "--out", tmp_path / "out", "-q")
    assert result.code == 0, result.err
    profiles, _ = read_artifact(tmp_path / "out" / "profiles.parquet")
    assert profiles.num_rows == 4
    assert abs(profiles.column("step_deg")[0].as_py() - 0.25) < 1e-5
    for k in range(4):
        np.testing.assert_allclose(profiles.column("ranges_m")[k].values.to_numpy(), ranges[k],
                                   rtol=1e-6)


def test_a_beam_off_the_equal_step_grid_is_refused(tmp_path: Path, cli: Any) -> None:
    beams = [np.array([0.0, 0.5, 1.0, 1.7, 2.0])] * 2
    ranges = [np.full(5, 2.0)] * 2
    path = tmp_path / "uneven.csv"
    write_long(path, beams, ranges)
    out = tmp_path / "out"
    result = cli("import-profiles", path, "--out", out, "-q")
    assert result.code != 0 and result.err.count("\n") == 1, result.err
    assert "beam_deg" in result.err and "not on the equal-step grid" in result.err
    assert not (out / "profiles.parquet").exists()


def test_wide_npz_with_float32_beam_angles(tmp_path: Path, cli: Any) -> None:
    # np.linspace in float32, as many tools store angles: steps differ by ~1e-5°.
    beam = np.linspace(-45.0, 225.0, 811, dtype=np.float32)  # a SICK TiM's 1/3°
    ranges = RNG.uniform(0.5, 5.0, (3, beam.size))
    path = tmp_path / "scan.npz"
    np.savez(path, ranges=ranges, beam_deg=beam, platform_deg=np.array([0.0, 1.0, 2.0]))
    result = cli("import-profiles", path, "--out", tmp_path / "out", "-q")
    assert result.code == 0, result.err
    profiles, _ = read_artifact(tmp_path / "out" / "profiles.parquet")
    assert abs(profiles.column("step_deg")[0].as_py() - 1 / 3) < 1e-6
    assert abs(profiles.column("start_angle_deg")[0].as_py() + 45.0) < 1e-4
    uneven = tmp_path / "uneven.npz"
    bad = np.array([0.0, 0.5, 1.0, 1.7, 2.0])
    np.savez(uneven, ranges=np.ones((1, 5)), beam_deg=bad, platform_deg=np.zeros(1))
    result = cli("import-profiles", uneven, "--out", tmp_path / "bad", "-q")
    assert result.code != 0 and "equal steps" in result.err
