"""Import profiles: ranges + beam angles + platform angles from another rig → ``profiles``,
``motor`` and ``rig`` artifacts that :mod:`scanpipe.stages.assemble` places like a recording.

Layouts (docs/import.md, "Profiles"):

- *long* (CSV or Parquet): one row per sample with columns ``profile``, ``beam_deg``,
  ``platform_deg``, ``range_m`` and optionally ``intensity`` (``time_s`` is accepted and
  ignored: the platform stands still per profile).
- *wide* (NPZ written by ``np.savez``): ``ranges`` (profiles × samples), ``beam_deg``
  (samples), ``platform_deg`` (profiles), optionally ``intensity`` (profiles × samples).

``beam_deg`` is the paper's α (0 along the scanner's +y, positive towards +x; a field of view
centred on 0 has negative angles), ``platform_deg`` is β about the rig's y axis. A range of 0,
a negative one, NaN or one at or above ``max_range_m`` is a no-return (NaN in the profile,
counted). Each profile becomes a step-and-scan position: a motor state at rest at
``round(β / pulse step)`` pulses, the profile inside that stationary second, so assemble's
``step`` association places it exactly (to the rig's pulse step; the generated rig uses
0.001°).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
from numpy.typing import NDArray
from pydantic import Field

from scanpipe.errors import ArtifactError, StageError
from scanpipe.params import Params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.rig import default_rig, rig_from_toml, rig_table
from scanpipe.stage import Stage, StageResult

F64 = NDArray[np.float64]
LENGTH_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: The generated rig's pulse step: platform angles are kept to this.
IMPORT_PULSE_STEP_DEG = 0.001
#: One stationary position per profile, this long on the synthetic clock.
POSITION_NS = 1_000_000_000
EPOCH_NS = 1_700_000_000_000_000_000


#: Beam angles closer than this (degrees) are one beam written with float noise (float32
#: angles printed in full differ by ~1e-5° at 270°); no scanner's step is near it.
BEAM_NOISE_DEG = 1e-4
#: A beam farther than this fraction of a step from the equal-step grid is refused.
OFF_GRID_STEPS = 0.01
#: More beams than this per profile is not a 2-D scanner (and would not fit in memory).
MAX_BEAMS = 100_000


class ImportProfilesParams(Params):
    """How a ranges + angles data set becomes profiles, motor states and a rig."""

    layout: Literal["auto", "long", "wide"] = Field(
        "auto", description="long (one row per sample) or wide (NPZ arrays); auto = by extension")
    units: Literal["m", "cm", "mm"] = Field("m", description="unit of the ranges")
    ranges_col: str = Field("range_m", min_length=1, description="long layout: range column")
    max_range_m: float | None = Field(
        None, gt=0, description="ranges at or above are no-returns (default: none)")
    rig_toml: str | None = Field(
        None, description="rig TOML (mount, calibration, motor) to start from; its scanner "
                          "angles are set from the data")


def _load(path: Path, params: ImportProfilesParams) -> tuple[F64, F64, F64, F64 | None]:
    """Ranges (P, S) in file units, beam angles (S,), platform angles (P,), intensity."""
    layout = params.layout
    if layout == "auto":
        layout = "wide" if path.suffix.lower() in (".npz", ".npy") else "long"
    if layout == "wide":
        try:
            with np.load(path, allow_pickle=False) as arrays:
                ranges = np.asarray(arrays["ranges"], np.float64)
                beam = np.asarray(arrays["beam_deg"], np.float64).ravel()
                platform = np.asarray(arrays["platform_deg"], np.float64).ravel()
                intensity = (np.asarray(arrays["intensity"], np.float64)
                             if "intensity" in arrays.files else None)
        except (OSError, ValueError, KeyError, AttributeError) as err:
            raise ArtifactError(f"{path}: not an NPZ with arrays ranges, beam_deg, "
                                f"platform_deg ({type(err).__name__}: {err})") from None
        if ranges.ndim != 2 or ranges.shape != (platform.size, beam.size):
            raise ArtifactError(f"{path}: ranges has shape {ranges.shape}; expected "
                                f"(platform_deg {platform.size}, beam_deg {beam.size})")
        return ranges, beam, platform, intensity
    try:
        table = (pq.read_table(path) if path.suffix.lower() == ".parquet"
                 else pacsv.read_csv(path))
    except (OSError, pa.ArrowInvalid) as err:
        raise ArtifactError(f"{path}: not a readable CSV/Parquet table ({err})") from None
    needed = ("profile", "beam_deg", "platform_deg", params.ranges_col)
    missing = [c for c in needed if c not in table.column_names]
    if missing:
        raise ArtifactError(f"{path}: no column {', '.join(missing)} (found: "
                            f"{', '.join(table.column_names)}); long layout needs profile, "
                            f"beam_deg, platform_deg, {params.ranges_col}")
    try:
        cols = {c: table.column(c).to_numpy().astype(np.float64) for c in needed}
        intensity_col = (table.column("intensity").to_numpy().astype(np.float64)
                         if "intensity" in table.column_names else None)
    except (ValueError, TypeError, pa.ArrowInvalid) as err:
        raise ArtifactError(f"{path}: columns must be numbers ({err})") from None
    profile = cols["profile"]
    if not np.isfinite(profile).all() or not np.isfinite(cols["beam_deg"]).all():
        raise ArtifactError(f"{path}: profile and beam_deg must be finite numbers")
    ids, row = np.unique(profile, return_inverse=True)
    beam_values = np.unique(cols["beam_deg"])
    # Values closer than BEAM_NOISE_DEG are one beam written with float noise: group them,
    # take the smallest gap between groups as a first step, then fit start and step to every
    # group (noise must not accumulate over a thousand beams).
    group = np.concatenate([[0], np.cumsum(np.diff(beam_values) > BEAM_NOISE_DEG)])
    centres = np.bincount(group, beam_values) / np.bincount(group)
    if centres.size > 1:
        rough = float(np.min(np.diff(centres)))
        index = np.rint((centres - centres[0]) / rough)
        start, step = float(centres[0]), rough
        if np.max(np.abs(centres - (start + index * step))) > 1e-9 * max(1.0, abs(step)):
            fitted = np.polyfit(index, centres, 1)
            step, start = float(fitted[0]), float(fitted[1])
        position = (cols["beam_deg"] - start) / step
        column = np.rint(position).astype(np.int64)
        off = np.abs(position - column)
        worst = int(np.argmax(off))
        if off[worst] > OFF_GRID_STEPS:
            raise ArtifactError(f"{path}: beam_deg {cols['beam_deg'][worst]:g} is not on the "
                                f"equal-step grid from {start:.6g}° by {step:.6g}° (off by "
                                f"{off[worst] * step:g}°); beam angles must rise in equal "
                                "steps")
        samples = int(column.max()) + 1
        if samples > MAX_BEAMS:
            raise ArtifactError(f"{path}: beam_deg from {start:g}° to {beam_values[-1]:g}° by "
                                f"{step:g}° is {samples} beams; at most {MAX_BEAMS}")
    else:
        step, column, samples = 1.0, np.zeros(profile.size, np.int64), 1
    ranges = np.full((ids.size, samples), np.nan)
    flat = row * samples + column
    if np.unique(flat).size != flat.size:
        raise ArtifactError(f"{path}: two rows share a (profile, beam_deg) cell")
    ranges.ravel()[flat] = cols[params.ranges_col]
    intensity = None
    if intensity_col is not None:
        intensity = np.zeros_like(ranges)
        intensity.ravel()[flat] = intensity_col
    platform = (np.bincount(row, cols["platform_deg"], ids.size)
                / np.bincount(row, minlength=ids.size))
    spread = np.abs(cols["platform_deg"] - platform[row])
    if np.nanmax(spread) > 1e-6:
        raise ArtifactError(f"{path}: platform_deg varies within a profile (by up to "
                            f"{np.nanmax(spread):g}°); one platform angle per profile is "
                            "supported")
    first = start if centres.size > 1 else float(beam_values[0])
    beam = first + np.arange(samples, dtype=np.float64) * step
    return ranges, beam, platform, intensity


def import_profiles(path: Path, params: ImportProfilesParams) -> StageResult:
    """The three artifacts and a report from one data file (see the module doc)."""
    ranges, beam, platform, intensity = _load(path, params)
    if ranges.size == 0:
        raise ArtifactError(f"{path}: no samples")
    if not np.isfinite(beam).all() or not np.isfinite(platform).all():
        raise ArtifactError(f"{path}: beam_deg and platform_deg must be finite")
    steps = np.diff(beam)
    step = float(np.median(steps)) if steps.size else 1.0
    if steps.size and step > 0:
        # Angles stored as float32 (np.linspace) step unevenly by ~1e-5°: fit the grid and
        # accept beams within OFF_GRID_STEPS of it, as the long layout does.
        index = np.arange(beam.size, dtype=np.float64)
        fitted = np.polyfit(index, beam, 1)
        grid = fitted[1] + index * fitted[0]
        if np.max(np.abs(beam - grid)) <= OFF_GRID_STEPS * float(fitted[0]):
            if np.max(np.abs(steps - step)) > 1e-9 * max(1.0, step):
                beam, step = grid, float(fitted[0])
        else:
            step = -1.0
    if step <= 0:
        raise ArtifactError(f"{path}: beam_deg must rise in equal steps (found steps "
                            f"{np.min(steps):g}…{np.max(steps):g}°)")
    fov = step * beam.size
    if fov > 360.0 + 1e-6:
        raise ArtifactError(f"{path}: {beam.size} beams × {step:g}° = {fov:g}° > 360°")
    ranges_m = ranges * LENGTH_SCALE[params.units]
    with np.errstate(invalid="ignore"):
        no_return = ~np.isfinite(ranges_m) | (ranges_m <= 0)
        if params.max_range_m is not None:
            no_return |= ranges_m >= params.max_range_m
    ranges_m = np.where(no_return, np.nan, ranges_m).astype(np.float32)

    rig = (rig_from_toml(params.rig_toml, "--rig") if params.rig_toml
           else default_rig().model_copy(update={"cameras": ()}))
    data = rig.model_dump(mode="json")
    start = float(beam[0])
    data["name"] = f"imported from {path.name}"
    data["scanner"].update(dialect="paper", beam_step_deg=step, start_angle_deg=start,
                           end_angle_deg=start + fov)
    if not params.rig_toml:
        data["scanner"].update(min_range_m=0.0, max_range_m=255.0,
                               scan_hz=5.0)
        data["motor"].update(full_step_deg=IMPORT_PULSE_STEP_DEG, gear_ratio=1.0,
                             unlimited_travel=True, beta_offset_deg=0.0)
    rig = rig_from_toml(_to_toml(data), "imported rig")
    pulse = rig.motor.pulse_step_deg
    counts = np.rint((platform - rig.motor.beta_offset_deg) / pulse).astype(np.int64)
    quantised = float(np.max(np.abs(counts * pulse + rig.motor.beta_offset_deg - platform)))

    n = ranges_m.shape[0]
    frames_per_position = max(1, round(POSITION_NS / 1e9 * rig.scanner.scan_hz))
    t0 = EPOCH_NS + np.arange(n, dtype=np.int64) * POSITION_NS
    profiles = {
        "recv_time_ns": pa.array(t0 + POSITION_NS // 2),
        "frame": pa.array(np.arange(n, dtype=np.int64) * frames_per_position),
        "sector": pa.array(np.zeros(n, np.int32)),
        "start_angle_deg": pa.array(np.full(n, start)),
        "step_deg": pa.array(np.full(n, step)),
        "ranges_m": pa.array(list(ranges_m), pa.list_(pa.float32())),
        "dialect": pa.array(["import"] * n),
    }
    if intensity is not None:
        echo = np.clip(np.rint(np.nan_to_num(intensity)), 0, 65535).astype(np.uint16)
        profiles["echo"] = pa.array(list(echo), pa.list_(pa.uint16()))
    # Per position: at rest at its count, then moving towards the next one 0.9 s later.
    nxt = np.concatenate([counts[1:], counts[-1:]])
    motor = {
        "log_time_ns": pa.array(np.stack([t0, t0 + 9 * POSITION_NS // 10], 1).ravel()),
        "step_count": pa.array(np.stack([counts, counts], 1).ravel()),
        "target_step_count": pa.array(np.stack([counts, nxt], 1).ravel()),
        "moving": pa.array(np.tile([False, True], n)),
    }
    warnings = []
    if quantised > 0.01:
        warnings.append(f"platform angles rounded to the rig's pulse step {pulse:g}° (by up to "
                        f"{quantised:g}°)")
    report = {
        "file": str(path),
        "grid": {"profiles": n, "samples": int(beam.size)},
        "beam_deg": [start, start + (beam.size - 1) * step],
        "beam_step_deg": step,
        "field_of_view_deg": fov,
        "platform_deg": [float(platform.min()), float(platform.max())],
        "no_return": int(np.count_nonzero(no_return)),
        "platform_rounding_deg": quantised,
        "warnings": warnings,
    }
    return StageResult(tables={"profiles": pa.table(profiles), "motor": pa.table(motor),
                               "rig": rig_table(rig)}, report=report)


def _to_toml(data: dict[str, Any]) -> str:
    from scanpipe.params import to_toml

    return to_toml(data, {})


def import_profiles_stage(inputs: Mapping[str, Any], params: ImportProfilesParams,
                          progress: ProgressFn = no_progress) -> StageResult:
    """Stage function: ``inputs["profile_file"]`` is the path of the data file."""
    path = inputs.get("profile_file")
    if not isinstance(path, str | Path):
        raise StageError("import-profiles needs inputs['profile_file']: a data file's path")
    progress("import profiles", 0, 1)
    result = import_profiles(Path(path), params)
    progress("import profiles", 1, 1)
    return result


STAGE = Stage(
    name="import-profiles",
    version=2,
    params=ImportProfilesParams,
    inputs=("profile_file",),
    outputs=("profiles", "motor", "rig"),
    func=import_profiles_stage,
    description="ranges + beam and platform angles from another rig (CSV/Parquet/NPZ) → "
                "profiles, motor, rig",
)
