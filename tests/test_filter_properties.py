"""Property tests: whatever the data and the settings, filters never add points, every point
taken is counted once, and mark mode agrees with remove mode."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scan_tables import make_rig, positions_scan

from scanpipe.params import validate
from scanpipe.pointio import points_table
from scanpipe.stages import assemble
from scanpipe.stages.filter import STAGE, FilterParams

SAMPLES = (4, 6, 8, 12, 18, 24, 36)


@st.composite
def gridded_points(draw: st.DrawFn) -> pa.Table:
    samples = draw(st.sampled_from(SAMPLES))
    profiles = draw(st.integers(1, 8))
    step = draw(st.sampled_from([5.0, 10.0, 30.0, 60.0]))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    ranges = rng.choice([1.0, 2.0, 4.0], (profiles, samples)) + rng.normal(0, 0.02,
                                                                           (profiles, samples))
    ranges[rng.random(ranges.shape) < draw(st.floats(0, 0.5))] = np.nan
    ranges[rng.random(ranges.shape) < 0.05] = 0.1
    rig = make_rig(pulse_step_deg=step, beam_step_deg=360.0 / samples)
    table = assemble.STAGE.run(positions_scan(rig, list(range(profiles)), ranges))
    return table.tables["points"]


@st.composite
def loose_points(draw: st.DrawFn) -> pa.Table:
    n = draw(st.integers(0, 60))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    return points_table(rng.normal(0, 2, (n, 3)), None, (0.0, 0.0, 0.0))


@st.composite
def filter_params(draw: st.DrawFn) -> FilterParams:
    data = {
        "mode": draw(st.sampled_from(["remove", "mark"])),
        "no_return": {"enabled": draw(st.booleans())},
        "range_gate": {"enabled": draw(st.booleans()), "min_range_m": 0.5},
        "depth_edges": {"enabled": draw(st.booleans()),
                        "remove": draw(st.sampled_from(["far", "both"]))},
        "grid_median": {"enabled": draw(st.booleans()),
                        "action": draw(st.sampled_from(["remove", "replace"]))},
        "smoothing": {"enabled": draw(st.booleans())},
        "double_coverage": {"action": draw(st.sampled_from(["keep", "merge", "best"]))},
        "statistical_outlier": {"enabled": draw(st.booleans()), "neighbours": 4,
                                "with_grid": draw(st.booleans())},
        "voxel": {"enabled": draw(st.booleans()),
                  "size_m": draw(st.sampled_from([0.05, 0.5, 3.0]))},
    }
    return validate(FilterParams, data)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(gridded_points(), loose_points()), filter_params())
def test_filters_never_add_points(points: pa.Table, params: FilterParams) -> None:
    result = STAGE.run({"points": points}, params)
    out = result.tables["points"]
    report = result.report
    assert out.num_rows <= points.num_rows
    taken = sum(f["taken"] for f in report["filters"].values())
    assert taken == points.num_rows - report["kept"]
    if params.mode == "remove":
        assert out.num_rows == report["kept"]
        cells_in = set(zip(points.column("profile").to_pylist(),
                           points.column("sample").to_pylist(), strict=True))
        if points.num_rows and points.column("profile").to_numpy().min() >= 0:
            cells_out = set(zip(out.column("profile").to_pylist(),
                                out.column("sample").to_pylist(), strict=True))
            assert cells_out <= cells_in
    else:
        assert out.num_rows == points.num_rows
        assert out.column("filtered_by").null_count == report["kept"]
    assert out.schema.field("x").type == pa.float32()
