"""Sites: the built-in site, simulate --site, the poses artifact, register's refusals."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from scanpipe.poses import (
    euler_deg,
    invert,
    pose_error,
    pose_matrix,
    poses_from_table,
    poses_table,
    quaternion_from_rotation,
    rotation_from_quaternion,
)
from scanpipe.registration import PairResult, covariances
from scanpipe.sim.site import prior_poses, scene_pose_for, site_positions


def test_pose_round_trips() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        angles = rng.uniform(-170, 170, 3) * np.array([0.5, 0.5, 1.0])
        pose = pose_matrix(angles, rng.uniform(-5, 5, 3))
        assert np.allclose(pose_matrix(euler_deg(pose[:3, :3]), pose[:3, 3]), pose)
        q = quaternion_from_rotation(pose[:3, :3])
        assert np.allclose(rotation_from_quaternion(q), pose[:3, :3])
        assert np.allclose(invert(pose) @ pose, np.eye(4))
    table = poses_table(["a", "b"], [np.eye(4), pose], [None, np.eye(6)])
    back = poses_from_table(table)
    assert np.allclose(back["b"], pose) and np.allclose(back["a"], np.eye(4))


def test_site_positions_and_prior_error() -> None:
    true = site_positions(6, seed=0)
    assert len(true) == 6
    prior = prior_poses(true, 0.5, 10.0, seed=0)
    errors = [pose_error(p, t) for p, t in zip(prior, true, strict=True)]
    assert all(dt <= 0.5 * np.sqrt(2) + 1e-9 and dr <= 10.0 + 1e-9 for dt, dr in errors)
    assert max(dt for dt, _ in errors) > 0.1  # the prior is really wrong
    # the scene pose is the inverse of the scanner's pose
    pose = true[3]
    scene = scene_pose_for(pose)
    assert np.allclose(pose_matrix(scene.rotation_deg, scene.translation_m) @ pose, np.eye(4))


def test_covariance_shrinks_with_more_information() -> None:
    poses = [np.eye(4), pose_matrix((0, 30, 0), (1, 0, 0))]
    one = PairResult(0, 1, poses[1], 0.5, 0.01, "ransac", True, "", np.eye(6))
    two = PairResult(0, 1, poses[1], 0.5, 0.01, "ransac", True, "", 4 * np.eye(6))
    c1, c2 = covariances(poses, [one])[1], covariances(poses, [two])[1]
    assert c1 is not None and c2 is not None
    assert np.allclose(c2, c1 / 4)


def test_simulate_site_writes_recordings_truth_and_prior(
        cli: Callable[..., Any], tmp_path: Path) -> None:
    out, truth = tmp_path / "recs", tmp_path / "truth"
    result = cli("simulate", "--site", "2", "--direct", "--out", str(out), "--truth", str(truth),
                 "--motor-step", "12", "--beam-step", "6", "--no-cameras", "--prior-error-m",
                 "0.5", "-q")
    assert result.code == 0, result.err
    assert (out / "pos00.mcap").is_file() and (out / "pos01.mcap").is_file()
    true = poses_from_table(pq.read_table(truth / "poses.parquet"))
    prior = poses_from_table(pq.read_table(out / "prior_poses.parquet"))
    assert set(true) == set(prior) == {"pos00", "pos01"}
    assert (truth / "site_scene.glb").is_file() and (truth / "pos01" / "scene.glb").is_file()
    before = (out / "pos00.mcap").read_bytes()
    again = cli("simulate", "--site", "2", "--direct", "--out", str(out), "--truth", str(truth),
                "--motor-step", "12", "--beam-step", "6", "--no-cameras", "-q")
    assert again.code == 2 and "--force" in again.err
    assert (out / "pos00.mcap").read_bytes() == before


def test_simulate_site_refusals(cli: Callable[..., Any], tmp_path: Path) -> None:
    args = ("simulate", "--out", str(tmp_path / "r"), "--truth", str(tmp_path / "t"))
    live = cli(*args, "--site", "3")
    assert live.code == 2 and "--site: only with --direct" in live.err
    prior = cli(*args, "--direct", "--prior-error-m", "0.5")
    assert prior.code == 2 and "--prior-error-m: only with --site" in prior.err
    assert not (tmp_path / "r").exists()


def test_register_refusals(cli: Callable[..., Any], tmp_path: Path) -> None:
    one = cli("register", str(tmp_path), "--out", str(tmp_path / "site"))
    assert one.code == 2 and "at least 2" in one.err
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    empty = cli("register", str(tmp_path / "a"), str(tmp_path / "b"), "--out",
                str(tmp_path / "site"))
    assert empty.code == 2 and "no points artifact" in empty.err
    assert not (tmp_path / "site" / "poses.parquet").exists()


def test_scan_workdirs_pass_over_the_batch_summary(tmp_path: Path) -> None:
    """`register work/*` after `batch` also names work/batch.json: it is passed over; any
    other file is refused in one line, as are two workdirs of one name."""
    import pytest

    from scanpipe.errors import UsageError
    from scanpipe.site import scan_workdirs

    for name in ("pos00-1a2b", "pos01-3c4d"):
        (tmp_path / "work" / name).mkdir(parents=True)
    (tmp_path / "work" / "batch.json").write_text("{}")
    paths = sorted((tmp_path / "work").iterdir())
    workdirs, names = scan_workdirs(paths, "register")
    assert names == ["pos00-1a2b", "pos01-3c4d"] and all(w.is_dir() for w in workdirs)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(UsageError, match=r"notes\.txt: not a folder"):
        scan_workdirs([*paths, tmp_path / "notes.txt"], "register")
    (tmp_path / "other" / "pos00-1a2b").mkdir(parents=True)
    with pytest.raises(UsageError, match="register: two workdirs share a folder name"):
        scan_workdirs([*paths, tmp_path / "other" / "pos00-1a2b"], "register")
