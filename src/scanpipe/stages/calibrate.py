"""Calibrate: the scanner's mount fitted to the scan itself (see :mod:`scanpipe.mount_calibration`).

Off by default: the stage then passes the rig through unchanged and writes an empty
``calibration``. On (``--set calibrate.enabled=true``) it assembles the scan with the rig it is
given and the run's own assemble parameters (the runner fills ``assemble``, see
:attr:`scanpipe.stage.Stage.borrows`, so they are part of this stage's key), fits the tilt,
the α zero and the offsets perpendicular to the motor axis to the flatness of the scan's
planes, and hands assemble the calibrated rig. Being a stage of its own, it is cached: a
re-run with other filter or mesh parameters reuses the fit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pyarrow as pa
from pydantic import Field

from scanpipe.mount_calibration import MountFit, fit_mount, samples_from_points
from scanpipe.params import Params
from scanpipe.progress import ProgressFn
from scanpipe.rig import Rig, rig_from_table, rig_table
from scanpipe.schema import CALIBRATION
from scanpipe.stage import Stage, StageResult
from scanpipe.stages.assemble import STAGE as ASSEMBLE
from scanpipe.stages.assemble import AssembleParams


class CalibrateParams(Params):
    """Whether to self-calibrate the mount, and how many returns the fit uses."""

    enabled: bool = Field(False, strict=True,
                          description="fit the mount to the scan and give assemble the result")
    max_points: int = Field(200_000, ge=2_000, le=2_000_000,
                            description="returns drawn (at random, fixed seed) for the fit")
    assemble: AssembleParams | None = Field(
        None, description="the run's assemble parameters, filled by the runner (set "
                          "assemble.KEY); None = assemble's defaults")


def calibration_table(fit: MountFit | None) -> pa.Table:
    """The ``calibration`` artifact: one row per parameter (empty without a fit)."""
    rows = [] if fit is None else fit.parameters
    return pa.table({
        "parameter": pa.array([p.name for p in rows], pa.string()),
        "value": pa.array([p.value for p in rows], pa.float64()),
        "sigma": pa.array([p.sigma for p in rows], pa.float64()),
        "observable": pa.array([p.observable for p in rows], pa.bool_()),
        "unit": pa.array([p.unit for p in rows], pa.string()),
        "note": pa.array([p.note for p in rows], pa.string()),
    }, schema=CALIBRATION.arrow_schema)


def assembled(inputs: Mapping[str, Any], rig: Rig,
              params: AssembleParams | None = None) -> pa.Table:
    """The ``points`` that assemble makes of ``inputs`` (profiles, motor) with ``rig``."""
    return ASSEMBLE.run({"profiles": inputs["profiles"], "motor": inputs["motor"],
                         "rig": rig_table(rig)}, params).tables["points"]


def rms_to_truth(inputs: Mapping[str, Any], rig: Rig, truth: Any,
                 limit: int = 200_000, params: AssembleParams | None = None) -> float:
    """The RMS distance (m) to the true scene of the points ``rig`` assembles from ``inputs``
    (profiles, motor), over at most ``limit`` points drawn at random (seeded)."""
    import numpy as np

    points = assembled(inputs, rig, params)
    xyz = np.stack([points.column(c).to_numpy(zero_copy_only=False) for c in "xyz"], 1)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) > limit:
        xyz = xyz[np.random.default_rng(0).choice(len(xyz), limit, replace=False)]
    return float(np.sqrt(np.mean(truth.scene.distance_m(xyz) ** 2)))


def run_fit(inputs: Mapping[str, Any], max_points: int,
            params: AssembleParams | None = None) -> MountFit:
    """Assemble with the given rig and assemble ``params`` and fit the mount (the CLI's
    path too)."""
    rig = rig_from_table(inputs["rig"])
    points = assembled(inputs, rig, params)
    return fit_mount(samples_from_points(points, rig, max_points), rig)


def calibrate_stage(inputs: Mapping[str, Any], params: CalibrateParams,
                    progress: ProgressFn) -> StageResult:
    """The calibrate stage: ``profiles``, ``motor``, ``rig`` → ``calibration``, ``rig``."""
    if not params.enabled:
        return StageResult(tables={"calibration": calibration_table(None),
                                   "rig": inputs["rig"]},
                           report={"enabled": False})
    progress("calibrate", 0, 1)
    fit = run_fit(inputs, params.max_points, params.assemble)
    progress("calibrate", 1, 1)
    report = {"enabled": True, **fit.report()}
    return StageResult(tables={"calibration": calibration_table(fit), "rig": rig_table(fit.rig)},
                       report=report)


STAGE = Stage(
    name="calibrate",
    version=3,  # 3: planes grown whole (a changed fit: no cached fit of 2 is reused)
    params=CalibrateParams,
    inputs=("profiles", "motor", "rig"),
    outputs=("calibration", "rig"),
    func=calibrate_stage,
    description="mount self-calibration from the scan's planes (off unless calibrate.enabled)",
    libraries=("numpy", "pyarrow", "scipy"),
    borrows=("assemble",),
)
