"""`scanpipe assemble` and `scanpipe filter` on real Parquet artifacts, and their errors."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scan_tables import make_rig, positions_scan

from scanpipe.artifacts import read_artifact, write_artifact
from scanpipe.rig import rig_to_toml


def write_inputs(folder: Path) -> None:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=10.0)
    ranges = np.full((5, 36), 3.0)
    ranges[0, 0] = np.nan
    for name, table in positions_scan(rig, [0, 1, 2, 3, 4], ranges).items():
        write_artifact(folder / f"{name}.parquet", table, {"key": f"{name}-key", "stage": "test"})


def test_assemble_then_filter(tmp_path: Path, cli: Callable[..., Any]) -> None:
    write_inputs(tmp_path / "dec")
    result = cli("assemble", tmp_path / "dec", "--out", tmp_path / "asm", "-q")
    assert result.code == 0, result.err
    report = json.loads(result.out)
    assert report["grid"] == {"profiles": 5, "samples": 36} and report["no_return"] == 1
    points, provenance = read_artifact(tmp_path / "asm" / "points.parquet")
    assert points.num_rows == 180
    assert provenance["stage"] == "assemble" and provenance["report"]["grid"]["samples"] == 36
    assert provenance["inputs"] == {"profiles": "profiles-key", "motor": "motor-key",
                                    "rig": "rig-key"}

    result = cli("filter", tmp_path / "asm", "--out", tmp_path / "flt", "--set", "mode=mark",
                 "-q")
    assert result.code == 0, result.err
    assert json.loads(result.out)["filters"]["no_return"]["taken"] == 1
    filtered, provenance = read_artifact(tmp_path / "flt" / "points.parquet")
    assert filtered.num_rows == 180 and filtered.column("filtered_by").null_count == 179
    assert provenance["params"]["mode"] == "mark"


def test_assemble_with_a_rig_file_uses_its_calibration(tmp_path: Path,
                                                       cli: Callable[..., Any]) -> None:
    write_inputs(tmp_path / "dec")
    rig_path = tmp_path / "calibrated.toml"
    rig_path.write_text(rig_to_toml(make_rig(pulse_step_deg=2.0, beam_step_deg=10.0,
                                             translation_m=(0.0, 0.25, 0.0))))
    plain = cli("assemble", tmp_path / "dec", "--out", tmp_path / "a", "-q")
    shifted = cli("assemble", tmp_path / "dec", "--out", tmp_path / "b", "--rig", rig_path,
                  "-q")
    assert plain.code == 0 and shifted.code == 0, shifted.err
    y_a = read_artifact(tmp_path / "a" / "points.parquet")[0].column("y").to_numpy()
    y_b = read_artifact(tmp_path / "b" / "points.parquet")[0].column("y").to_numpy()
    np.testing.assert_allclose((y_b - y_a)[1:], 0.25, atol=1e-6)  # [0] is a no-return


def test_bad_parameters_and_missing_inputs(tmp_path: Path, cli: Callable[..., Any]) -> None:
    write_inputs(tmp_path / "dec")
    bad = cli("assemble", tmp_path / "dec", "--out", tmp_path / "a", "--set", "mode=spiral",
              "--set", "setle_s=1")
    assert bad.code == 2
    assert "mode" in bad.err and "did you mean settle_s" in bad.err
    assert "Traceback" not in bad.err
    missing = cli("assemble", tmp_path / "nowhere", "--out", tmp_path / "a")
    assert missing.code == 2 and "profiles.parquet: not found" in missing.err
    same = cli("filter", tmp_path / "dec", "--out", tmp_path / "dec")
    assert same.code == 2 and "must differ from the input folder" in same.err
    bad_rig = tmp_path / "bad.toml"
    bad_rig.write_text("[scanner]\nscan_hz = -1\n")
    rig_error = cli("assemble", tmp_path / "dec", "--out", tmp_path / "a", "--rig", bad_rig)
    assert rig_error.code == 2 and "scanner.scan_hz" in rig_error.err
    assert not (tmp_path / "a" / "points.parquet").exists()
