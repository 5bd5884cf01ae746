"""The simulated echo amplitude: the lidar equation per sample, and on the wire end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions
from scanpipe.sim.scanner import (
    ECHO_AT_1M,
    MIN_REFLECTANCE,
    TrueProfiles,
    echo_amplitude,
    surface_reflectance,
)


def _truth(ranges: list[float], cosines: list[float], rho: list[float]) -> TrueProfiles:
    return TrueProfiles(np.array([ranges]), np.array([cosines], np.float32),
                        np.array([rho], np.float32))


def test_echo_falls_with_range_incidence_and_darkness() -> None:
    measured = np.array([[1.0, 2.0, 2.0, 2.0, np.nan]], np.float32)
    truth = _truth([1.0, 2.0, 2.0, 2.0, 2.0], [1.0, 1.0, 0.5, 1.0, 1.0],
                   [1.0, 1.0, 1.0, 0.25, 1.0])
    echo = echo_amplitude(measured, truth)[0].astype(float)
    # the documented scale (docs/simulation.md): a white wall head-on at 1 m gives 40 000
    assert echo[0] == ECHO_AT_1M == 40_000
    assert echo[1] == ECHO_AT_1M / 4          # 1/r²
    assert echo[2] == ECHO_AT_1M / 8          # cos θ
    assert echo[3] == ECHO_AT_1M / 16         # reflectance
    assert echo[4] == 0                       # no return, no echo
    rho = surface_reflectance(np.array([[255, 255, 255], [0, 0, 0]], np.uint8))
    np.testing.assert_allclose(rho, [1.0, MIN_REFLECTANCE], rtol=1e-6)


def test_simulated_recording_carries_the_echo_into_the_points(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "scan.mcap"
    simulate_direct(path, tmp_path / "truth", SimOptions(
        beam_step_deg=4.0, motor_step_deg=10.0, cameras=False, seed=1))
    done = cli("run", path, "--workdir", tmp_path / "w", "--to", "assemble")
    assert done.code == 0, done.err
    points = pq.read_table(tmp_path / "w" / "assemble" / "points.parquet")
    echo = points.column("echo").to_numpy().astype(float)
    r = points.column("range_m").to_numpy()
    hit = np.isfinite(r)
    assert np.all(echo[~hit] == 0) and np.all(echo[hit] > 0)
    # the range fall-off dominates a room's echo (texture and incidence vary around it)
    assert np.corrcoef(np.log(echo[hit]), np.log(r[hit]))[0, 1] < -0.5
