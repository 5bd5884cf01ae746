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
from scanpipe.registration import (
    PairResult,
    RegisterParams,
    close_loops,
    covariances,
    error_twists,
    information_covariance,
    joint_covariance,
    normalised_errors,
    pair_information,
    plane_projected_points,
    prepare_scan,
    refine,
    relative_covariance,
    variance_factor,
)
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
    one = PairResult(0, 1, poses[1], 0.5, 0.01, "ransac", True, "",
                     pose_information=np.eye(6))
    two = PairResult(0, 1, poses[1], 0.5, 0.01, "ransac", True, "",
                     pose_information=4 * np.eye(6))
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


def test_error_twists_and_normalised_errors() -> None:
    truth = [pose_matrix((0, 20, 0), (1, 0, 2)), pose_matrix((0, 80, 0), (4, 0, 1))]
    frame = pose_matrix((1, -30, 0), (10, 2, -3))  # the estimate's own site frame
    nudge = pose_matrix((0, 0, 0.01), (0.003, 0, -0.004))  # truth = nudge · estimate
    estimated = [frame @ truth[0], invert(nudge) @ frame @ truth[1]]
    twists = error_twists(estimated, truth)
    assert np.allclose(twists[0], 0, atol=1e-12)
    assert np.allclose(twists[1], [0, 0, np.radians(0.01), 0.003, 0, -0.004], atol=1e-9)
    z, m2 = normalised_errors(twists[1], np.diag([1e-8] * 3 + [1e-6] * 3))
    assert np.allclose(z[3:], [3, 0, -4]) and m2 == __import__("pytest").approx(
        25 + np.radians(0.01) ** 2 / 1e-8)


def _room(rng: np.random.Generator, count: int, cell_sigma_m: float, noise_m: float
          ) -> tuple[Any, Any]:
    """Points on the six faces of a 6 × 3 × 5 m room (normals inward), each displaced along
    its normal by white noise plus one offset per 0.5 m cell (correlated neighbours)."""
    faces = [((0, 1, 0), 0.0), ((0, -1, 0), -3.0), ((1, 0, 0), -3.0), ((-1, 0, 0), -3.0),
             ((0, 0, 1), -2.5), ((0, 0, -1), -2.5)]
    lows, highs = np.array([-3.0, 0.0, -2.5]), np.array([3.0, 3.0, 2.5])
    xyz, normals = [], []
    for normal, offset in faces:
        n = np.array(normal, float)
        points = rng.uniform(lows, highs, (count // 6, 3))
        axis = int(np.argmax(np.abs(n)))
        points[:, axis] = -offset * n[axis] if offset else 0.0
        xyz.append(points)
        normals.append(np.repeat(n[None], len(points), axis=0))
    xyz_all, normals_all = np.concatenate(xyz), np.concatenate(normals)
    _, cell = np.unique(np.floor(xyz_all / 0.5).astype(int), axis=0, return_inverse=True)
    shift = rng.normal(0, cell_sigma_m, cell.max() + 1)[cell.ravel()]
    shift += rng.normal(0, noise_m, len(xyz_all))
    return xyz_all + normals_all * shift[:, None], normals_all


def test_pose_covariance_covers_the_errors_of_correlated_points() -> None:
    """A room scanned twice, the points' errors correlated over 0.5 m cells (3 mm) on top of
    white noise (10 mm): over 4 seeds the registration errors' χ² (6 dof) against the pair's
    covariance stays within the 3 σ bound on average, while the covariance that treats the
    points as independent (one cell per point) is several times too small."""
    params = RegisterParams(fine_source_points=6000)
    chi2, chi2_naive = [], []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        clouds = []
        for name in ("a", "b"):
            xyz, normals = _room(rng, 12_000, 0.003, 0.01)
            origin = np.tile([0.0, 1.5, 0.0], (len(xyz), 1))
            clouds.append(prepare_scan(name, xyz, origin, params, normals))
        start = pose_matrix((0.3, -0.5, 0.2), (0.03, -0.02, 0.04))
        transform = refine(clouds[1], clouds[0], start, params)[0]
        twist = error_twists([np.eye(4), transform], [np.eye(4), np.eye(4)])[1]
        information = pair_information(clouds[1], clouds[0], transform, params)
        chi2.append(normalised_errors(twist, np.linalg.inv(information))[1])
        naive = pair_information(clouds[1], clouds[0], transform,
                                 params.model_copy(update={"covariance_cluster_m": 1e-4}))
        chi2_naive.append(normalised_errors(twist, np.linalg.inv(naive))[1])
    # measured at covariance_scale 1: 16.5, 17.0, 10.2, 8.9 (naive 62, 54, 31, 33)
    assert np.mean(chi2) <= 20.1, chi2  # χ²₆ at 3 σ
    assert np.mean(chi2_naive) > 2.5 * np.mean(chi2), (chi2_naive, chi2)


def test_variance_factor_measures_the_loops_misclosure() -> None:
    poses = [np.eye(4), pose_matrix((0, 30, 0), (2, 0, 0)), pose_matrix((0, -20, 0), (1, 0, 3))]
    error = pose_matrix((0, 0, 0), (0.003, 0, 0))  # one pair 3 mm off along x

    def pair(target: int, source: int, off: Any = None) -> PairResult:
        measured = invert(poses[target]) @ poses[source]
        return PairResult(target, source, measured if off is None else off @ measured, 0.5,
                          0.01, "ransac", True, "",
                          pose_information=np.eye(6) / 1e-6)  # σ 1 mm
    # no loop: nothing to measure
    assert variance_factor(poses, [pair(0, 1), pair(0, 2)]) == (1.0, 0)
    factor, dof = variance_factor(poses, [pair(0, 1), pair(0, 2), pair(1, 2, error)])
    assert dof == 6 and factor == __import__("pytest").approx(9.0 / 6.0, rel=1e-6)


def test_pose_graph_weighs_pairs_by_their_information() -> None:
    """The pose graph is the weighted least-squares optimum: two measurements of one pair,
    4 mm apart along x, weighted 3 : 1 land 1 mm from the stronger one; along a loop of three
    scans whose third pair is 6 mm off, the misclosure is shared in inverse proportion to
    the pairs' information, and the graph stays put where the pairs agree."""
    from scanpipe.registration import _optimise

    truth = [np.eye(4), pose_matrix((0, 30, 0), (2, 0, 0)), pose_matrix((0, -20, 0), (1, 0, 3))]

    def pair(target: int, source: int, weight: float, off: Any = None) -> PairResult:
        measured = invert(truth[target]) @ truth[source]
        return PairResult(target, source, measured if off is None else off @ measured, 0.5,
                          0.01, "ransac", True, "", pose_information=np.eye(6) * weight)

    shift = pose_matrix((0, 0, 0), (0.004, 0, 0))  # target frame: 4 mm along x
    start = [truth[0], truth[1] @ pose_matrix((0.5, -1, 0.2), (0.05, 0.02, -0.03))]
    two = _optimise(start, [pair(0, 1, 3e6), pair(0, 1, 1e6, shift)])
    assert pose_error(two[1], pose_matrix((0, 0, 0), (0.001, 0, 0)) @ truth[1])[0] < 1e-7
    assert np.allclose(two[0], truth[0])
    # a loop whose last pair is 6 mm off: the weakest pair takes most of the misclosure
    loop = _optimise(list(truth), [pair(0, 1, 1e6), pair(1, 2, 1e6),
                                   pair(0, 2, 1e4, pose_matrix((0, 0, 0), (0.006, 0, 0)))])
    assert pose_error(loop[2], truth[2])[0] < 0.006 * 0.03  # equal weights: a third
    agree = _optimise(list(truth), [pair(0, 1, 1e6), pair(1, 2, 1e6), pair(0, 2, 1e4)])
    assert all(pose_error(a, b)[0] < 1e-9 for a, b in zip(agree, truth, strict=True))


def test_relative_covariance_along_a_chain() -> None:
    """The covariance of the relative pose the graph implies: along a bare chain 0–1–2 it is
    the pair's own for neighbours, and Σ₀₁ + Ad(T₀₁) Σ₁₂ Ad(T₀₁)ᵀ for the ends."""
    from scanpipe.registration import _adjoint

    rng = np.random.default_rng(3)
    poses = [np.eye(4), pose_matrix((0, 30, 0), (2, 0, 0.5)),
             pose_matrix((0, -20, 5), (3, 0.4, 2))]
    informations = []
    for _ in range(2):
        a = rng.normal(size=(6, 6))
        informations.append(a @ a.T + 6 * np.eye(6))
    pairs = [PairResult(k, k + 1, invert(poses[k]) @ poses[k + 1], 0.5, 0.01, "ransac", True,
                        "", pose_information=informations[k]) for k in range(2)]
    joint = joint_covariance(poses, pairs)
    assert joint is not None and not joint[:6].any()  # scan 0 fixed
    sigma = [np.linalg.inv(i) for i in informations]
    assert np.allclose(relative_covariance(joint, poses, 1, 2), sigma[1], atol=1e-9)
    assert np.allclose(relative_covariance(joint, poses, 0, 1), sigma[0], atol=1e-9)
    turn = _adjoint(pairs[0].transform)
    assert np.allclose(relative_covariance(joint, poses, 0, 2),
                       sigma[0] + turn @ sigma[1] @ turn.T, atol=1e-9)
    # a direction a pair does not constrain gets a large variance, not zero (pinv's)
    flat = np.diag([1e6, 1e6, 1e6, 0.0, 1e6, 1e6])
    assert information_covariance(flat)[3, 3] >= 1e5


def _three_scans_of_a_room(params: RegisterParams) -> list[Any]:
    rng = np.random.default_rng(11)
    clouds = []
    for name in ("a", "b", "c"):
        xyz, normals = _room(rng, 6_000, 0.0, 0.01)
        origin = np.tile([0.0, 1.5, 0.0], (len(xyz), 1))
        clouds.append(prepare_scan(name, xyz, origin, params, normals))
    return clouds


def test_loop_closing_pair_is_gated_by_covariance() -> None:
    """Three scans of one room (all at the identity) chained a–b–c; the pair a–c had no valid
    hypothesis. Started from the pose the chain implies, it joins when it agrees with that pose
    within the covariances (χ² small); when the chain is 2 cm off (b–c measured 2 cm wrong, the
    graph sure of it), the ICP still finds the true placement, 2 cm from the implied pose:
    refused by the χ² gate with the reason, never averaged in."""
    params = RegisterParams(fine_source_points=6000)
    clouds = _three_scans_of_a_room(params)

    def attempt(shift: Any) -> tuple[list[dict[str, Any]], PairResult]:
        chain = [PairResult(0, 1, np.eye(4), 0.9, 0.01, "ransac", True),
                 PairResult(1, 2, shift, 0.9, 0.01, "ransac", True)]
        for p in chain:
            p.pose_information = pair_information(clouds[p.source], clouds[p.target],
                                                  np.eye(4), params)
        loop = PairResult(0, 2, np.eye(4), 0.0, 0.0, "none", False, "no hypothesis")
        poses = [np.eye(4), np.eye(4), shift]
        return close_loops(clouds, [*chain, loop], list(poses), chain, params), loop

    records, loop = attempt(np.eye(4))
    assert len(records) == 1 and records[0]["accepted"], records
    assert records[0]["chi2"] <= params.loop_gate_chi2
    assert loop.accepted and loop.init == "graph" and loop.pose_information.any()
    assert pose_error(loop.transform, np.eye(4))[0] < 0.005

    records, loop = attempt(pose_matrix((0, 0, 0), (0.02, 0, 0)))
    assert len(records) == 1 and not records[0]["accepted"], records
    assert records[0]["chi2"] > params.loop_gate_chi2
    assert "from the pose the graph implies" in records[0]["reason"]
    assert "loop_gate_chi2" in records[0]["reason"]
    assert 0.015 <= records[0]["from_graph_m"] <= 0.025
    assert not loop.accepted and loop.reason == "no hypothesis"


def _wall_grid(rng: np.random.Generator, distance_m: float, noise_m: float
               ) -> tuple[Any, Any, Any, Any, Any]:
    """A wall at ``distance_m`` (normal −z toward the scanner at the origin) seen over ±40° on a
    2° × 1° grid of beams, each range with Gaussian noise: (true ranges, measured points,
    beam directions, profile, sample)."""
    az, el = np.radians(np.arange(-40.0, 40.01, 2.0)), np.radians(np.arange(-30.0, 30.01, 1.0))
    profile, sample = (a.ravel() for a in np.meshgrid(np.arange(len(az)), np.arange(len(el)),
                                                        indexing="ij"))
    beam = np.stack([np.sin(az[profile]) * np.cos(el[sample]), np.sin(el[sample]),
                     np.cos(az[profile]) * np.cos(el[sample])], axis=1)
    true_range = distance_m / beam[:, 2]
    measured = true_range + rng.normal(0.0, noise_m, len(beam))
    return true_range, beam * measured[:, None], beam, profile, sample


def test_plane_projection_has_no_range_smoothing_bias() -> None:
    """Averaging a 3 × 3 window of *ranges* (the filter's smoothing) puts a far wall behind
    where it is — the range d / cos θ is convex in the beam angle — and by an amount that
    depends on the view, which biased the site's pairs; averaging the *points* along each
    beam does not, and still averages the noise."""
    rng = np.random.default_rng(3)
    distance_m, noise_m = 6.0, 0.01
    true_range, xyz, beam, profile, sample = _wall_grid(rng, distance_m, noise_m)
    ranges = np.full((profile.max() + 3, sample.max() + 3), np.nan)
    ranges[profile + 1, sample + 1] = np.linalg.norm(xyz, axis=1)
    window = [ranges[profile + 1 + i, sample + 1 + j] for i in (-1, 0, 1) for j in (-1, 0, 1)]
    smoothed = beam * np.nanmean(window, axis=0)[:, None]
    normals = np.tile([0.0, 0.0, -1.0], (len(xyz), 1))
    projected = plane_projected_points(xyz, np.zeros_like(xyz), normals, profile, sample, 0.03)
    inner = (profile > 0) & (profile < profile.max()) & (sample > 0) & (sample < sample.max())

    def behind_mm(points: Any) -> float:  # mean distance behind the wall (z > d)
        return float(np.mean(points[inner, 2] - distance_m) * 1000)

    assert behind_mm(smoothed) > 2.0  # the range average's bias (~3 mm here)
    assert abs(behind_mm(projected)) < 0.3
    assert abs(behind_mm(xyz)) < 0.3  # the raw points are unbiased too, but noisier:
    spread = np.std(projected[inner, 2] - distance_m)
    assert spread < 0.5 * np.std(xyz[inner, 2] - distance_m)
    # each point stays on its own beam
    along = np.cross(projected, beam)
    assert np.abs(along).max() < 1e-9
    assert np.allclose(np.linalg.norm(projected, axis=1)[inner], true_range[inner], atol=0.03)
