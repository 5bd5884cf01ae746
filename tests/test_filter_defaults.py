"""The filter's defaults follow the rig: the range gate is the scanner's own window; a filter
that takes much of the cloud is a warning."""

from __future__ import annotations

import numpy as np
from scan_tables import make_rig, positions_scan
from test_filter_grid import ALL_OFF, cloud_without_grid

from scanpipe.params import validate
from scanpipe.rig import Rig
from scanpipe.stages import assemble
from scanpipe.stages.filter import STAGE, FilterParams


def short_range_rig() -> Rig:
    rig = make_rig(pulse_step_deg=2.0, beam_step_deg=30.0)
    scanner = rig.scanner.model_copy(update={"min_range_m": 0.05, "max_range_m": 4.0})
    return rig.model_copy(update={"scanner": scanner})


def gate_only(**gate: object) -> FilterParams:
    return validate(FilterParams, {**ALL_OFF, "range_gate": {"enabled": True, **gate}})


def test_range_gate_follows_the_rigs_scanner() -> None:
    ranges = np.full((4, 12), 0.3)  # a short-range scanner: everything nearer than 0.5 m
    ranges[0, 0] = 0.02
    ranges[1, 1] = 5.0
    points = assemble.STAGE.run(positions_scan(short_range_rig(), [0, 1, 2, 3], ranges)
                                ).tables["points"]
    result = STAGE.run({"points": points}, gate_only())
    gate = result.report["filters"]["range_gate"]
    assert (gate["taken"], gate["min_range_m"], gate["max_range_m"]) == (2, 0.05, 4.0)
    assert gate["source"] == "the scanner's range (rig)"
    assert result.report["warnings"] == []
    # A bound the user sets wins; the other stays the scanner's.
    set_low = STAGE.run({"points": points}, gate_only(min_range_m=0.5)).report
    assert set_low["filters"]["range_gate"]["taken"] == 48
    assert set_low["filters"]["range_gate"]["max_range_m"] == 4.0
    (warning,) = set_low["warnings"]
    assert warning.startswith("filter range_gate took 100% of the points (48 of 48; "
                              "warn_taken_share 0.3) (kept 0.5 to 4.0 m")


def test_points_from_another_tool_get_no_range_gate_and_say_so() -> None:
    table = cloud_without_grid(np.array([[0.1, 0, 0], [1.0, 0, 0], [300.0, 0, 0]]))
    result = STAGE.run({"points": table}, gate_only())
    assert result.tables["points"].num_rows == 3
    assert "range_gate" in result.report["skipped"]
    assert any("range_gate not applied: the points carry no scanner range" in w
               for w in result.report["warnings"])
    gated = STAGE.run({"points": table}, gate_only(max_range_m=250.0))
    assert gated.tables["points"].num_rows == 2


def test_share_threshold_is_a_parameter() -> None:
    table = cloud_without_grid(np.array([[0.1, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]]))
    params = {**ALL_OFF, "range_gate": {"enabled": True, "min_range_m": 0.5}}
    quiet = STAGE.run({"points": table}, validate(FilterParams, params)).report
    assert quiet["warnings"] == []  # 25 % < 30 %
    loud = STAGE.run({"points": table},
                     validate(FilterParams, {**params, "warn_taken_share": 0.2})).report
    assert loud["warnings"][0].startswith("filter range_gate took 25% of the points")
