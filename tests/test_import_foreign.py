"""Issue 16: other rigs' data in the shapes users have it (3DTK .3d/.pose, mislabelled CSV,
polar columns, zero ranges, several posed scans, organised grids, 270° rotating profiles)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from scanpipe.artifacts import read_artifact
from scanpipe.errors import UsageError
from scanpipe.pointio import ImportParams, detect_z_up, import_points, read_pose
from scanpipe.rig import load_rig

Cli = Callable[..., Any]
#: Box room, rig frame (y up): x −2…3, y −1…1.5, z −4…2.5 (metres).
BOX_LO, BOX_HI = np.array([-2.0, -1.0, -4.0]), np.array([3.0, 1.5, 2.5])


def box_hits(directions: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Distance along each unit direction from ``origin`` (inside) to the box's walls."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(directions > 0, (BOX_HI - origin) / directions,
                     (BOX_LO - origin) / directions)
    return np.nanmin(np.where(t > 0, t, np.inf), axis=1)


def xyz(table: pa.Table) -> np.ndarray:
    return np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)


def room_points(origin: np.ndarray, n: int = 4000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return origin + d * box_hits(d, origin)[:, None]


def to_3dtk(points_m: np.ndarray) -> np.ndarray:
    """Rig frame (right-handed, y up, m) → 3DTK (left-handed: z mirrored, cm)."""
    return points_m * (1, 1, -1) * 100.0


def test_3dtk_pairs_in_cm_left_handed_merge_in_one_frame_in_metres(tmp_path: Path) -> None:
    # Two scans of the box from two positions, each stored in its own scan frame with a
    # 3DTK .pose (cm, degrees, Rx·Ry·Rz) that puts it back.
    files, poses, truths = [], [], []
    for k, (pos_m, theta_deg) in enumerate([((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                             ((1.0, 0.2, -1.5), (0.0, 30.0, 0.0))]):
        truth = room_points(np.array(pos_m), seed=k)
        pose_path = tmp_path / f"scan{k:03d}.pose"
        pose_path.write_text(f"{pos_m[0] * 100} {pos_m[1] * 100} {-pos_m[2] * 100}\n"
                             f"{theta_deg[0]} {theta_deg[1]} {theta_deg[2]}\n")
        m = read_pose(pose_path)
        world_3dtk = to_3dtk(truth)
        local = (world_3dtk - m[:3, 3]) @ m[:3, :3]  # inverse pose
        path = tmp_path / f"scan{k:03d}.3d"
        np.savetxt(path, local, fmt="%.3f", header="361 x 12", comments="")
        files.append(path)
        poses.append(str(pose_path))
        truths.append(truth)
    table, report = import_points(files[0], ImportParams(extra_files=(str(files[1]),),
                                                         poses=tuple(poses)))
    # 0.001 cm in the file; float32 in the artifact.
    np.testing.assert_allclose(xyz(table), np.concatenate(truths), atol=2e-5)
    assert report["units"] == ["cm", "cm"] and report["left_handed"] == [True, True]
    origins = np.stack([table.column(c).to_numpy() for c in ("origin_x", "origin_y",
                                                               "origin_z")], 1)
    np.testing.assert_allclose(origins[-1], (1.0, 0.2, -1.5), atol=1e-6)
    np.testing.assert_allclose(origins[0], 0.0)


def test_3d_renamed_xyz_in_cm_warns_implausible_extent(tmp_path: Path) -> None:
    path = tmp_path / "scan000.xyz"
    np.savetxt(path, to_3dtk(room_points(np.zeros(3))) * 100)  # mm: a 650 m "room"
    _, report = import_points(path, ImportParams())
    assert any("implausible" in w and "--units" in w for w in report["warnings"])


def test_mislabelled_header_is_warned_and_columns_fix_it(tmp_path: Path) -> None:
    truth = room_points(np.zeros(3)) * (1, 1, 1)
    # z-up polar columns of the file's own frame: the true (x, y, z) of a z-up cloud.
    z_up = truth[:, [0, 2, 1]] * (1, -1, 1)
    r = np.linalg.norm(z_up, axis=1)
    az = np.degrees(np.arctan2(z_up[:, 1], z_up[:, 0]))
    el = np.degrees(np.arcsin(z_up[:, 2] / r))
    r[:5] = 0.0  # no-returns
    data = np.column_stack([z_up[:, 0], z_up[:, 2], z_up[:, 1], r, az, el])  # y, z swapped
    path = tmp_path / "scan.csv"
    np.savetxt(path, data, delimiter=",", header="x,y,z,range,azimuth,elevation",
               comments="", fmt="%.6f")
    _, report = import_points(path, ImportParams(up="z"))
    assert any("mislabelled" in w and "x,z,y" in w for w in report["warnings"])
    fixed, report = import_points(path, ImportParams(up="z", columns="x,z,y,range,-,-"))
    np.testing.assert_allclose(xyz(fixed), truth[5:], atol=1e-5)
    assert report["dropped_no_return"] == 5
    assert not np.any(np.all(xyz(fixed) == 0, axis=1))
    polar, report = import_points(path, ImportParams(
        columns="-,-,-,range,azimuth,elevation"))
    np.testing.assert_allclose(xyz(polar), truth[5:], atol=1e-5)
    assert "z-up" in str(report["warnings"]) or report["z_up_converted"]


def test_a_non_standard_header_without_columns_is_warned(tmp_path: Path) -> None:
    path = tmp_path / "h.csv"
    np.savetxt(path, room_points(np.zeros(3)), delimiter=",", header="x,z,y", comments="")
    _, report = import_points(path, ImportParams())
    assert any("taken by the header's names (x, z, y)" in w for w in report["warnings"])
    plain = tmp_path / "p.csv"
    np.savetxt(plain, room_points(np.zeros(3)), delimiter=",", header="x,y,z", comments="")
    _, report = import_points(plain, ImportParams())
    assert not any("header" in w for w in report["warnings"])


def test_up_auto_recognises_a_z_up_cloud() -> None:
    truth = room_points(np.zeros(3))
    z_up = truth[:, [0, 2, 1]] * (1, -1, 1)
    assert detect_z_up(z_up)[0] is True
    assert detect_z_up(truth)[0] is False


def test_organised_keeps_the_grid_and_meshes_with_the_grid_mesher(tmp_path: Path,
                                                                  cli: Cli) -> None:
    alpha = np.radians(np.linspace(10, 170, 60))
    beta = np.radians(np.linspace(0, 170, 40))
    d = np.stack([np.sin(alpha)[None, :] * np.cos(beta)[:, None],
                  np.broadcast_to(np.cos(alpha)[None, :], (40, 60)),
                  np.sin(alpha)[None, :] * np.sin(beta)[:, None]], -1).reshape(-1, 3)
    pts = d * box_hits(d, np.zeros(3))[:, None]
    pts[7] = 0.0  # a no-return stored as the origin
    path = tmp_path / "grid.txt"
    np.savetxt(path, pts)
    out = tmp_path / "pts"
    assert cli("import-points", path, "--out", out, "--organised", "40x60", "--up", "y",
               "-q").code == 0
    table, prov = read_artifact(out / "points.parquet")
    assert prov["report"]["grid"] == {"profiles": 40, "samples": 60}
    assert prov["report"]["dropped_no_return"] == 1 and table.num_rows == 2399
    assert table.column("profile").to_numpy()[60] == 1
    mesh = cli("mesh", out, "--out", tmp_path / "mesh", "--method", "grid", "-q")
    assert mesh.code == 0, mesh.err
    bad = cli("import-points", path, "--out", tmp_path / "x", "--organised", "40x61", "-q")
    assert bad.code == 2 and "2400 points" in bad.err


def test_bad_arguments_are_one_line(tmp_path: Path, cli: Cli) -> None:
    path = tmp_path / "a.dat"
    np.savetxt(path, np.eye(3))
    refused = cli("import-points", path, "--out", tmp_path / "o", "-q")
    assert refused.code == 2 and "--format" in refused.err
    ok = cli("import-points", path, "--out", tmp_path / "o", "--format", "xyz", "-q")
    assert ok.code == 0, ok.err
    for args, needle in ((["--columns", "x,y,q"], "unknown column 'q'"),
                         (["--axes", "x,x,y"], "signed permutation"),
                         (["--pose", str(path)], "9 numbers")):
        result = cli("import-points", path, "--out", tmp_path / "p", "--format", "xyz", *args)
        assert result.code == 2 and needle in result.err and "Traceback" not in result.err
    assert not (tmp_path / "p" / "points.parquet").exists()
    with pytest.raises(UsageError, match="one per file"):
        import_points(path, ImportParams(format="xyz", poses=("a", "b")))


def hokuyo_scan() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 270° scanner (−135°…+135° at 0.5°) turned 0…180° in 3° steps inside the box."""
    beam = np.arange(-135.0, 135.0, 0.5)
    platform = np.arange(0.0, 180.0, 3.0)
    a, b = np.radians(beam)[None, :], np.radians(platform)[:, None]
    d = np.stack([np.sin(a) * np.cos(b), np.broadcast_to(np.cos(a), (b.size, a.size)),
                  np.sin(a) * np.sin(b)], -1)
    ranges = box_hits(d.reshape(-1, 3), np.zeros(3)).reshape(d.shape[:2])
    return ranges, beam, platform


def test_hokuyo_like_270_degree_data_through_assemble_and_mesh(tmp_path: Path,
                                                               cli: Cli) -> None:
    ranges, beam, platform = hokuyo_scan()
    ranges[3, 10] = 0.0  # no return
    p, s = np.meshgrid(np.arange(platform.size), np.arange(beam.size), indexing="ij")
    table = pa.table({"profile": p.ravel(), "beam_deg": beam[s].ravel(),
                      "platform_deg": platform[p].ravel(), "range_m": ranges.ravel()})
    path = tmp_path / "hokuyo.parquet"
    pq.write_table(table, path)
    raw = tmp_path / "raw"
    result = cli("import-profiles", path, "--out", raw, "-q")
    assert result.code == 0, result.err
    rig = raw / "rig.toml"
    rig.write_text(read_artifact(raw / "rig.parquet")[0].column("toml")[0].as_py())
    assert load_rig(rig).scanner.start_angle_deg == -135.0
    assert cli("rig", "check", rig).code == 0
    pts = tmp_path / "pts"
    result = cli("assemble", raw, "--out", pts, "-q")
    assert result.code == 0, result.err
    points, prov = read_artifact(pts / "points.parquet")
    assert prov["report"]["mode"] == "step"
    assert prov["report"]["grid"] == {"profiles": platform.size, "samples": beam.size}
    got = xyz(points).reshape(platform.size, beam.size, 3)
    a, b = np.radians(beam)[None, :], np.radians(platform)[:, None]
    truth = ranges[..., None] * np.stack(
        [np.sin(a) * np.cos(b), np.broadcast_to(np.cos(a), ranges.shape),
         np.sin(a) * np.sin(b)], -1)
    ok = ranges > 0
    rms = float(np.sqrt(np.mean(np.sum((got[ok] - truth[ok]) ** 2, axis=1))))
    assert rms < 1e-4 and np.isnan(got[3, 10]).all()
    mesh = cli("mesh", pts, "--out", tmp_path / "mesh", "--method", "grid", "-q")
    assert mesh.code == 0, mesh.err


def test_wide_npz_and_bad_profile_files(tmp_path: Path, cli: Cli) -> None:
    ranges, beam, platform = hokuyo_scan()
    path = tmp_path / "scan.npz"
    np.savez(path, ranges=ranges * 1000, beam_deg=beam, platform_deg=platform)
    out = tmp_path / "raw"
    assert cli("import-profiles", path, "--out", out, "--units", "mm", "-q").code == 0
    profiles, _ = read_artifact(out / "profiles.parquet")
    np.testing.assert_allclose(profiles.column("ranges_m")[0].values.to_numpy(), ranges[0],
                               rtol=1e-6)
    bad = tmp_path / "bad.csv"
    bad.write_text("profile,beam,range_m\n0,1,2\n")
    result = cli("import-profiles", bad, "--out", tmp_path / "b", "-q")
    assert result.code != 0 and "no column beam_deg, platform_deg" in result.err
    assert not (tmp_path / "b" / "profiles.parquet").exists()


def test_rig_accepts_negative_start_for_a_centred_scanner_not_for_the_ldoem(
        tmp_path: Path, cli: Cli) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text('[scanner]\ndialect = "paper"\nstart_angle_deg = -119.53\n'
                   'end_angle_deg = 119.53\n')
    assert cli("rig", "check", rig).code == 0
    rig.write_text('[scanner]\nstart_angle_deg = -119.53\nend_angle_deg = 119.53\n')
    result = cli("rig", "check", rig)
    assert result.code == 2 and "LD-OEM's angles run 0…360" in result.err


def test_the_cached_import_follows_the_contents_of_pose_files(tmp_path: Path) -> None:
    # A pose file edited in place must give a new key, not the artifact of the old pose.
    from scanpipe.artifacts import read_provenance
    from scanpipe.cli.main import main

    cloud = tmp_path / "a.xyz"
    np.savetxt(cloud, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    pose = tmp_path / "a.pose"
    pose.write_text("0 0 0\n0 0 0\n")
    args = ["import-points", str(cloud), "--pose", str(pose), "--format", "3d", "--out",
            str(tmp_path / "o"), "--force", "-q"]
    assert main(args) == 0
    first = read_provenance(tmp_path / "o" / "points.parquet")["key"]
    pose.write_text("100 0 0\n0 0 0\n")
    assert main(args) == 0
    assert read_provenance(tmp_path / "o" / "points.parquet")["key"] != first
