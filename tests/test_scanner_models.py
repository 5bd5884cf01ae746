"""Scanner models: rig init/check/plan per model, partial (270°) fields of view through the
grid, the mesh and the chain, and the SICK devices live (emulator on TCP → record → run)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from scanpipe.artifacts import read_provenance
from scanpipe.evaluate import SurfaceDistance, load_reference
from scanpipe.grid import scan_grid
from scanpipe.meshing.grid_mesh import GridMeshParams, triangulate_grid
from scanpipe.meshing.synthetic import BoxRoom, scan_table
from scanpipe.normals import points_origins, points_xyz
from scanpipe.protocol.registry import DIALECTS
from scanpipe.rig import load_rig, rig_to_toml
from scanpipe.scanner_models import DIALECT_NAMES, SCANNER_MODELS


def test_every_dialect_name_has_a_decoder_and_every_model_a_known_dialect() -> None:
    assert set(DIALECT_NAMES) == set(DIALECTS)
    assert all(m.dialect in DIALECT_NAMES for m in SCANNER_MODELS.values())


@pytest.mark.parametrize("name, samples, start, hz", [
    ("lms111", 541, -45.0, 25.0), ("tim571", 811, -45.0, 15.0), ("ldoem1000", 1440, 0.0, 5.0)])
def test_rig_init_writes_each_model(tmp_path: Path, cli: Callable[..., Any], name: str,
                                    samples: int, start: float, hz: float) -> None:
    path = tmp_path / "rig.toml"
    result = cli("rig", "init", path, "--scanner", name)
    assert result.code == 0, result.err
    rig = load_rig(path)
    assert rig.scanner.model == name and rig.scanner.samples_per_profile == samples
    assert rig.scanner.start_angle_deg == start and rig.scanner.scan_hz == hz
    assert rig.scanner.dialect == SCANNER_MODELS[name].dialect
    plan = cli("plan", "--rig", path)
    assert plan.code == 0 and "device limits" in plan.out and "FAIL" not in plan.out


def test_unknown_scanner_is_a_usage_error_and_writes_nothing(tmp_path: Path,
                                                             cli: Callable[..., Any]) -> None:
    path = tmp_path / "rig.toml"
    path.write_text("keep me")
    result = cli("rig", "init", path, "--scanner", "lms999", "--force")
    assert result.code == 2
    assert "--scanner 'lms999': unknown; allowed: ldoem1000, lms111, tim571" in result.err
    assert path.read_text() == "keep me"
    result = cli("simulate", "--direct", "--scanner", "lms999", "--out", tmp_path / "a.mcap",
                 "--truth", tmp_path / "t")
    assert result.code == 2 and "--scanner 'lms999'" in result.err
    assert not (tmp_path / "a.mcap").exists()


def test_model_limits_are_checked_in_the_rig(tmp_path: Path, cli: Callable[..., Any]) -> None:
    path = tmp_path / "rig.toml"
    assert cli("rig", "init", path, "--scanner", "lms111").code == 0
    text = path.read_text().replace("scan_hz = 25.0", "scan_hz = 30.0")
    path.write_text(text)
    result = cli("rig", "check", path)
    assert result.code == 2
    assert "scanner.scan_hz: scan_hz = 30 is outside the LMS111 limit (one of 25 Hz at 0.5°" \
        in result.err
    assert "beam_step_deg" not in result.err  # 0.5° is right; only the rate is wrong
    assert path.read_text() == text
    # a rate it has with a step it lacks at that rate: the step alone is named, not the rate
    path.write_text(text.replace("scan_hz = 30.0", "scan_hz = 25.0").replace(
        "beam_step_deg = 0.5", "beam_step_deg = 0.3"))
    result = cli("rig", "check", path)
    assert result.code == 2 and "scan_hz" not in result.err
    assert "beam_step_deg = 0.3 is outside the LMS111 limit (at 25 Hz: one of 0.5°, 0.25°)" \
        in result.err
    bad = text.replace('dialect = "cola_b"', 'dialect = "ldoem"')
    path.write_text(bad)
    result = cli("rig", "check", path)
    assert result.code == 2 and "model lms111 speaks dialect cola_b or cola_a, not ldoem" \
        in result.err
    # the LMS1xx's other flavour is accepted; a TiM571 (CoLa-B only here) refuses it
    path.write_text(text.replace("scan_hz = 30.0", "scan_hz = 25.0").replace(
        'dialect = "cola_b"', 'dialect = "cola_a"'))
    assert cli("rig", "check", path).code == 0
    assert cli("rig", "init", path, "--scanner", "tim571", "--force").code == 0
    path.write_text(path.read_text().replace('dialect = "cola_b"', 'dialect = "cola_a"'))
    result = cli("rig", "check", path)
    assert result.code == 2 and "model tim571 speaks dialect cola_b, not cola_a" in result.err


def test_old_rig_files_load_as_the_ld_oem(tmp_path: Path) -> None:
    path = tmp_path / "old.toml"
    path.write_text('[scanner]\ndialect = "ldoem"\nangular_step_deg = 0.25\n')
    rig = load_rig(path)
    assert rig.scanner.model == "" and rig.scanner.transport == "tcp"
    assert load_rig(path).scanner == load_rig(None).scanner.model_copy(
        update={"beam_step_deg": 0.25})


def _partial(table: pa.Table, span_deg: float) -> pa.Table:
    """Keep the samples within ``span_deg`` (a 270° scanner) and renumber them."""
    alpha = table.column("alpha_deg").to_numpy()
    keep = alpha < span_deg
    out = table.filter(pa.array(keep))
    return out.set_column(out.schema.get_field_index("sample"), "sample",
                          pa.array(np.rint(out.column("alpha_deg").to_numpy() / 2.0)
                                   .astype(out.schema.field("sample").type.to_pandas_dtype())))


def test_a_270_degree_grid_has_no_seam_and_no_face_across_the_gap() -> None:
    table = _partial(scan_table(BoxRoom(), alpha_step_deg=2.0, beta_step_deg=5.0,
                                noise_m=0.003), 270.0 + 1e-9)
    grid = scan_grid(table)
    assert grid is not None and grid.shape[1] == 136 and not grid.wraps_alpha
    _, faces, report = triangulate_grid(points_xyz(table), points_origins(table), grid,
                                        GridMeshParams())
    assert report["seam_closed"] is False and len(faces) > 0
    sample = table.column("sample").to_numpy()[faces]
    assert int((sample.max(axis=1) - sample.min(axis=1)).max()) <= 1  # neighbours only


def test_a_simulated_270_degree_scanner_runs_the_whole_chain(tmp_path: Path,
                                                             cli: Callable[..., Any]) -> None:
    rec, truth, work = tmp_path / "s.mcap", tmp_path / "t", tmp_path / "w"
    result = cli("simulate", "--direct", "--scanner", "tim571", "--out", rec, "--truth", truth,
                 "--motor-step", "5", "--no-cameras", "--quiet")
    assert result.code == 0, result.err
    assert cli("run", rec, "--workdir", work, "--quiet").code == 0
    points = pq.read_table(work / "filter" / "points.parquet")
    alpha = points.column("alpha_deg").to_numpy()
    assert alpha.min() >= -45.0 - 1e-6 and alpha.max() <= 225.0 + 1e-6
    report = read_provenance(work / "mesh" / "mesh_faces.parquet")["report"]
    assert report["triangulation"]["seam_closed"] is False


@pytest.mark.slow
@pytest.mark.parametrize(("model", "dialect", "motor_step"), [
    ("lms111", "cola_b", "1.44"), ("lms111", "cola_a", "1.44"), ("tim571", "cola_b", "1")])
def test_sick_live_through_the_emulator_and_run(tmp_path: Path, cli: Callable[..., Any],
                                                model: str, dialect: str,
                                                motor_step: str) -> None:
    """The user's path: simulate live (CoLa-B on TCP 2112, or CoLa-A on 2111 selected by the
    rig's dialect; sEN LMDscandata) → run; points within 1.1 σ of the device's noise (LMS111
    12 mm, TiM571 20 mm), intensities kept as echo."""
    from scanpipe.rig import default_rig, scanner_for_model

    rec, truth, work = tmp_path / "s.mcap", tmp_path / "t", tmp_path / "w"
    rig = tmp_path / "rig.toml"
    scanner = scanner_for_model(model).model_copy(update={
        "dialect": dialect, "port": SCANNER_MODELS[model].rig_values(dialect)["port"]})
    rig.write_text(rig_to_toml(default_rig().model_copy(update={"scanner": scanner})))
    result = cli("simulate", "--rig", rig, "--out", rec, "--truth", truth,
                 "--mode", "continuous", "--motor-step", motor_step, "--no-cameras",
                 "--speedup", "2", "--seed", "4", "--quiet")
    assert result.code == 0, result.err
    result = cli("run", rec, "--workdir", work, "--quiet")
    assert result.code == 0 and "Traceback" not in result.err
    profiles = pq.read_table(work / "decode" / "profiles.parquet")
    assert set(profiles.column("dialect").to_pylist()) == {dialect}
    assert profiles.column("echo").null_count == 0
    report = read_provenance(work / "assemble" / "points.parquet")["report"]
    assert report["time_source"] == "device"
    assert report["clock"]["rate"] == pytest.approx(0.5, rel=0.01)
    table = pq.read_table(work / "assemble" / "points.parquet", columns=["x", "y", "z"])
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    rms = float(np.sqrt(np.mean(np.square(
        SurfaceDistance(load_reference(truth).mesh).distance_m(xyz)))))
    sigma = SCANNER_MODELS[model].noise_sigma_m
    assert rms <= 1.1 * sigma, f"RMS {rms * 1e3:.2f} mm = {rms / sigma:.3f} σ"


def test_rig_toml_round_trips_the_new_keys(tmp_path: Path) -> None:
    from scanpipe.rig import default_rig

    rig = default_rig("tim571")
    path = tmp_path / "r.toml"
    path.write_text(rig_to_toml(rig))
    assert load_rig(path) == rig
