"""Site registration on the virtual site: no prior, a wrong prior, and an ambiguous pair."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from scanpipe.poses import pose_errors, pose_matrix, poses_from_table
from scanpipe.rig import Pose
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions

#: Small scans (motor 2°, beam 1°: ~30 k points each) keep the test fast. The tolerances are
#: the issue's target, which these coarser scans meet too since the pose graph weighs pairs
#: by their information, the ICP pairs only compatible normals and its fine clouds carry no
#: range-smoothing bias (seed 0: ≤ 3.5 mm / 0.025° in both cases; seeds 0–4 ≤ 3.6 mm /
#: 0.048°; docs/sites.md).
SMALL_SITE = ("--motor-step", "2", "--beam-step", "1", "--no-cameras")
TOLERANCE_M, TOLERANCE_DEG = 0.005, 0.05
#: Fewer RANSAC rounds where a guess from the prior is there anyway.
FAST = ("--set", "hypotheses=6", "--set", "ransac_iterations=3000")


def test_pose_errors_are_relative_to_the_reference_scan() -> None:
    truth = {"a": pose_matrix((0, 10, 0), (1, 0, 0)), "b": pose_matrix((0, 50, 0), (3, 0, 1)),
             "c": np.eye(4)}
    frame = pose_matrix((0.1, 80, 0), (5, 1, -2))  # an arbitrary site frame
    moved = pose_matrix((0, 0.02, 0), (0.004, 0, 0))
    estimated = {"a": frame @ truth["a"], "b": frame @ truth["b"] @ moved}
    rows = {r["scan"]: r for r in pose_errors(estimated, truth)}
    assert rows["a"]["translation_m"] == pytest.approx(0, abs=1e-9)
    assert rows["a"]["note"] == "reference"
    assert rows["b"]["translation_m"] == pytest.approx(0.004, abs=1e-9)
    assert rows["b"]["rotation_deg"] == pytest.approx(0.02, abs=1e-6)
    assert rows["c"]["translation_m"] is None and rows["c"]["note"] == "not registered"


@pytest.fixture(scope="module")
def small_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six positions of the built-in site, run to filter, with a wrong prior (±0.5 m, ±10°)."""
    from scanpipe.cli.main import main

    root = tmp_path_factory.mktemp("site")
    assert main(["simulate", "--site", "6", "--direct", "--out", str(root / "recs"), "--truth",
                 str(root / "truth"), "--prior-error-m", "0.5", "--prior-error-deg", "10",
                 *SMALL_SITE, "-q"]) == 0
    for k in range(6):
        assert main(["run", str(root / "recs" / f"pos{k:02d}.mcap"), "--workdir",
                     str(root / "work" / f"pos{k:02d}"), "--to", "filter", "-q"]) == 0
    return root


def _register(cli: Callable[..., Any], root: Path, out: str, *extra: str
              ) -> dict[str, Any]:
    import json

    workdirs = [str(root / "work" / f"pos{k:02d}") for k in range(6)]
    result = cli("register", *workdirs, "--out", str(root / out), "--truth",
                 str(root / "truth"), "--json", *extra)
    assert result.code == 0, result.err
    report: dict[str, Any] = json.loads(result.out)
    return report


def _check_all_placed(report: dict[str, Any], root: Path, out: str) -> None:
    assert report["unregistered"] == [] and report["conflicts"] == []
    errors = report["pose_errors"]
    assert len(errors) == 6
    for row in errors:
        assert row["translation_m"] <= TOLERANCE_M, row
        assert row["rotation_deg"] <= TOLERANCE_DEG, row
    table = pq.read_table(root / out / "poses.parquet")
    written = poses_from_table(table)
    assert sorted(written) == [f"pos{k:02d}" for k in range(6)]
    # the covariance is honest: each scan's error within ~3 σ (χ², 6 dof: 20.1 at 3 σ; 25 has
    # probability 3e-4), and not absurdly large either (a covariance of metres would pass)
    from scanpipe.registration import error_twists, normalised_errors
    from scanpipe.site import read_true_poses

    truth = read_true_poses(root / "truth")
    names = sorted(written)
    twists = error_twists([written[n] for n in names], [truth[n] for n in names])
    covs = dict(zip(table.column("scan").to_pylist(), table.column("covariance").to_pylist(),
                    strict=True))
    for name, twist in zip(names[1:], twists[1:], strict=True):
        cov = np.asarray(covs[name]).reshape(6, 6)
        assert normalised_errors(twist, cov)[1] <= 25.0, (name, twist, np.diag(cov))
        assert np.sqrt(np.diag(cov)[3:]).max() <= 0.02, (name, np.diag(cov))


def test_register_site_without_prior(cli: Callable[..., Any], small_site: Path) -> None:
    report = _register(cli, small_site, "site_noprior")
    _check_all_placed(report, small_site, "site_noprior")
    assert not any("filter's input" in w for w in report["warnings"]), report["warnings"]
    # the look-alike rooms were offered and refused by free space, not silently taken
    refused = [p for p in report["pairs"] if "free space" in p["reason"]]
    assert refused, report["pairs"]
    # the pairs two steps apart that RANSAC gave no valid placement were tried again from the
    # graph's poses and joined within the χ² gate (seed 0: pos01–pos03), marked as such
    closed = [r for r in report["loop_closures"] if r["accepted"]]
    assert closed, report["loop_closures"]
    assert all(r["chi2"] <= 16.81 for r in closed)
    from_graph = [p for p in report["pairs"] if p["init"] == "graph"]
    assert len(from_graph) == len(closed) and all(p["accepted"] for p in from_graph)


def test_registration_takes_the_filters_unsmoothed_points(small_site: Path,
                                                           tmp_path: Path) -> None:
    """The fine clouds hold the filter's points where its input (assemble) had them, averaged
    along their beams — not the range-smoothed ones, which lie mm behind far surfaces; without
    that input, the smoothed points and a warning naming the scan."""
    import shutil

    from scanpipe.registration import RegisterParams
    from scanpipe.schema import XYZ
    from scanpipe.site import _columns, registration_cloud, scan_points, unsmoothed_points

    work = small_site / "work" / "pos00"
    table, _ = scan_points(work)
    params = RegisterParams()
    raw = unsmoothed_points(work, table)
    assert raw is not None
    assembled = pq.read_table(work / "assemble" / "points.parquet")
    cells = dict(zip(zip(assembled.column("profile").to_pylist(),
                         assembled.column("sample").to_pylist(), strict=True),
                     _columns(assembled, XYZ), strict=True))
    first = (table.column("profile")[0].as_py(), table.column("sample")[0].as_py())
    assert np.array_equal(raw[0][0], cells[first])
    smoothed = _columns(table, XYZ)
    moved = np.linalg.norm(raw[0] - smoothed, axis=1)
    assert np.median(moved) > 1e-4  # the filter smoothed them
    cloud, warning = registration_cloud("pos00", work, table, params)
    assert warning is None and cloud.points == len(table)
    # a workdir without the filter's input: the smoothed points, and a warning
    bare = tmp_path / "pos00"
    shutil.copytree(work, bare)
    shutil.rmtree(bare / "assemble")
    assert unsmoothed_points(bare, table) is None
    cloud, warning = registration_cloud("pos00", bare, table, params)
    assert warning is not None and warning.startswith("pos00: the filter's input points")
    assert np.allclose(np.asarray(cloud.fine.points), smoothed[np.isfinite(smoothed).all(1)])
    # a damaged input: the same, never a crash
    damaged = tmp_path / "damaged"
    shutil.copytree(work, damaged)
    (damaged / "assemble" / "points.parquet").write_bytes(b"not parquet")
    assert unsmoothed_points(damaged, table) is None
    _, warning = registration_cloud("pos00", damaged, table, params)
    assert warning is not None and "not readable" in warning
    # positions=filtered: as before, no warning
    _, warning = registration_cloud("pos00", bare, table, RegisterParams(positions="filtered"))
    assert warning is None


def test_register_site_with_wrong_prior(cli: Callable[..., Any], small_site: Path) -> None:
    report = _register(cli, small_site, "site_prior", "--prior",
                       str(small_site / "recs" / "prior_poses.parquet"), *FAST)
    _check_all_placed(report, small_site, "site_prior")


def test_register_refuses_an_ambiguous_pair(cli: Callable[..., Any], tmp_path: Path) -> None:
    """Two scans of a bare box room: the true placement and the box turned 180° fit equally;
    the pair is reported as ambiguous and nothing is written."""
    for name, pose in (("a", Pose()), ("b", Pose(translation_m=(-1.1, 0.0, 0.6),
                                                 rotation_deg=(0.0, 35.0, 0.0)))):
        simulate_direct(tmp_path / f"{name}.mcap", tmp_path / f"truth_{name}",
                        SimOptions(scene="box", scene_pose=pose, motor_step_deg=3.0,
                                   beam_step_deg=1.0, cameras=False))
        assert cli("run", tmp_path / f"{name}.mcap", "--workdir", tmp_path / f"w{name}",
                   "--to", "filter", "-q").code == 0
    result = cli("register", tmp_path / "wa", tmp_path / "wb", "--out", tmp_path / "site", *FAST)
    assert result.code != 0
    assert "ambiguous" in result.err and "placements fit" in result.err
    assert len(result.err.strip().splitlines()) == 1
    assert not (tmp_path / "site" / "poses.parquet").exists()
