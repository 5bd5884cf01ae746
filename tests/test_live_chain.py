"""The user's path end to end: the recorder over real sockets and ptys, then ``scanpipe run``.

``scanpipe simulate`` without ``--direct`` records the emulated scanner (TCP) and motor
controller (pty) through the same recorder as ``scanpipe record``. Its device clock runs in
simulated time, ``--speedup`` times faster than the host clock: exactly the kind of clock the
chain must fit rather than assume (a recording like this crashed the mesh stage once).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from scanpipe.artifacts import read_provenance
from scanpipe.evaluate import SurfaceDistance, load_reference
from scanpipe.rig import default_rig, rig_to_toml

NOISE_M = 0.01
#: The emulators' clock speed-up per dialect. The LD-OEM stamps its sectors, so its times do
#: not depend on when the host reads them. The paper dialect has no device time: the receive
#: times are its clock (the frame counter fitted to them), so the host's latency lands in the
#: scan scaled by the speed-up; at 10× a turn is 20 ms of host time, and a loaded host's median
#: latency passes the half turn beyond which the frame clock is refused (receipts that do not
#: follow one clock): a fresh-clone run under load failed so. 5× keeps the same check with a
#: 20 ms margin.
SPEEDUP = {"ldoem": 10.0, "paper": 5.0}


def _simulate_and_run(tmp_path: Path, cli: Callable[..., Any], dialect: str, mode: str,
                      direct: bool = False) -> tuple[Path, Path]:
    rig = default_rig()
    rig = rig.model_copy(update={"scanner": rig.scanner.model_copy(update={"dialect": dialect})})
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    recording, truth, work = tmp_path / "scan.mcap", tmp_path / "truth", tmp_path / "work"
    args = ["simulate", "--out", recording, "--truth", truth, "--rig", rig_file,
            "--motor-step", "3", "--beam-step", "1", "--camera-scale", "0.05",
            "--mode", mode, "--seed", "3", "--quiet"]
    args += ["--direct"] if direct else ["--speedup", str(SPEEDUP[dialect])]
    result = cli(*args)
    assert result.code == 0, result.err
    result = cli("run", recording, "--workdir", work, "--quiet")
    assert result.code == 0, result.err
    assert "Traceback" not in result.err
    return work, truth


def _assembled_rms_m(work: Path, truth: Path) -> float:
    table = pq.read_table(work / "assemble" / "points.parquet", columns=["x", "y", "z"])
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    distances = SurfaceDistance(load_reference(truth).mesh).distance_m(xyz)
    return float(np.sqrt(np.mean(np.square(distances))))


@pytest.mark.slow
@pytest.mark.parametrize("dialect", ["ldoem", "paper"])
@pytest.mark.parametrize("mode", ["step", "continuous"])
def test_live_recording_runs_the_whole_chain(tmp_path: Path, cli: Callable[..., Any],
                                             dialect: str, mode: str) -> None:
    work, truth = _simulate_and_run(tmp_path, cli, dialect, mode)
    report = read_provenance(work / "assemble" / "points.parquet")["report"]
    # The association found the mode the rig recorded in, and says why.
    assert report["mode"] == mode, report["mode_reason"]
    if mode == "step":
        assert report["positions_without_profile"] <= 2, report
    # The fitted clock shows the speed-up: from the device's sector timestamps (ldoem), or
    # from the frame counter against the receive times (paper: no device time).
    assert report["time_source"] == ("device" if dialect == "ldoem" else "receive")
    assert report["clock"] is not None, report
    assert report["clock"]["rate"] == pytest.approx(1 / SPEEDUP[dialect], rel=0.01), report
    assert report["head_turn_s"] == pytest.approx(0.2 / SPEEDUP[dialect], rel=0.01)
    assert any("simulated speed-up" in w for w in report["warnings"])
    # Every point where it belongs: the raw (unsmoothed) cloud within the noise.
    assert _assembled_rms_m(work, truth) <= 1.1 * NOISE_M
    for artifact in ("mesh/mesh_faces.parquet", "texture/textured_faces.parquet"):
        assert (work / artifact).is_file()


@pytest.mark.slow
def test_direct_recording_runs_the_whole_chain(tmp_path: Path,
                                               cli: Callable[..., Any]) -> None:
    work, truth = _simulate_and_run(tmp_path, cli, "ldoem", "step", direct=True)
    report = read_provenance(work / "assemble" / "points.parquet")["report"]
    assert report["mode"] == "step" and report["warnings"] == []
    assert report["clock"]["rate"] == pytest.approx(1.0, abs=1e-6)
    assert _assembled_rms_m(work, truth) <= 1.1 * NOISE_M
