"""Accuracy on the virtual rig: the built-in room at the default noise σ, both methods.

Targets (issue 7): mean distance from the mesh to the true surface ≤ 0.5 σ; at τ = 2 cm,
completeness ≥ 95 % of the true surface the scanner could see, precision ≥ 98 %. The scan is
coarser than the paper's (0.5° beam step × 1° platform step, 130 k points) to keep the test
short; Poisson runs at depth 8 to match that sampling (depth 9 on it over-fits the noise into
fragments). The grid method uses the filter stage's edge-preserving smoothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.evaluate import SurfaceDistance, load_reference, mesh_metrics
from scanpipe.pipeline import get_stage
from scanpipe.render import RenderMesh
from scanpipe.sim.direct import simulate_direct
from scanpipe.sim.options import SimOptions

SIGMA_M = SimOptions().noise_sigma_m


@pytest.fixture(scope="module")
def scanned_room(tmp_path_factory: pytest.TempPathFactory) -> tuple[pa.Table, Path]:
    folder = tmp_path_factory.mktemp("room")
    options = SimOptions(motor_step_deg=1.0, beam_step_deg=0.5, cameras=False)
    simulate_direct(folder / "scan.mcap", folder / "truth", options)
    decoded = get_stage("decode").run({"recording": folder / "scan.mcap"}).tables
    points = get_stage("assemble").run(
        {name: decoded[name] for name in ("profiles", "motor", "rig")}).tables["points"]
    return points, folder / "truth"


def metrics(tables: dict[str, pa.Table], truth: Path) -> dict[str, float]:
    vertices, faces = tables["mesh_vertices"], tables["mesh_faces"]
    mesh = RenderMesh(
        vertices=np.stack([vertices.column(c).to_numpy() for c in "xyz"], axis=1),
        faces=np.stack([faces.column(c).to_numpy() for c in ("v0", "v1", "v2")], axis=1))
    reference = load_reference(truth)
    return mesh_metrics(mesh, reference, tau_m=0.02, samples=50_000,
                        truth_surface=SurfaceDistance(reference.mesh))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("method", "filter_params", "mesh_params"),
    [
        ("grid", {"smoothing": {"enabled": True}}, {}),
        ("poisson", {}, {"poisson": {"depth": 8}}),
    ],
)
def test_mesh_accuracy_on_the_builtin_room(scanned_room: tuple[pa.Table, Path], method: str,
                                           filter_params: dict, mesh_params: dict) -> None:
    points, truth = scanned_room
    filtered = get_stage("filter").run({"points": points}, **filter_params).tables["points"]
    result = get_stage("mesh").run({"points": filtered}, method=method, **mesh_params)
    found = metrics(result.tables, truth)
    assert found["mesh_mean_m"] <= 0.5 * SIGMA_M
    assert found["completeness"] >= 0.95
    assert found["precision"] >= 0.98
