"""Where a position log ends while the platform turns (scanpipe.motion.beyond_log): what lies
beyond it is misplaced if held; what lies beyond an end at rest is not."""

from __future__ import annotations

import numpy as np

from scanpipe.motion import beyond_log, turning_at_ends

MS = 1_000_000


def test_a_slow_turn_that_repeats_a_count_is_still_turning() -> None:
    times = np.arange(0, 3000 * MS, 20 * MS, dtype=np.int64)  # 50 Hz reports
    steps = times // (100 * MS)  # one pulse per 100 ms: five reports per count
    assert turning_at_ends(times, steps) == (True, True)


def test_a_platform_at_rest_for_a_second_at_an_end_is_at_rest() -> None:
    times = np.arange(0, 5000 * MS, 20 * MS, dtype=np.int64)
    steps = np.clip((times - 1500 * MS) // MS, 0, 2000)  # rests 1.5 s, turns 2 s, rests 1.5 s
    assert turning_at_ends(times, steps) == (False, False)
    assert turning_at_ends(times[:150], steps[:150]) == (False, True)  # cut mid-turn


def test_a_moving_flag_of_false_at_an_end_wins() -> None:
    times = np.arange(0, 1000 * MS, 20 * MS, dtype=np.int64)
    steps = times // MS
    flags = [True] * (len(times) - 1) + [False]
    assert turning_at_ends(times, steps, flags) == (True, False)
    assert turning_at_ends(times, steps, [None] * len(times)) == (True, True)


def test_only_spans_past_a_turning_end_are_beyond() -> None:
    times = np.arange(1000 * MS, 2000 * MS, 20 * MS, dtype=np.int64)
    steps = times // MS
    start = np.array([900, 1000, 1500, 1979, 1981], np.int64) * MS
    end = start + 1 * MS
    assert beyond_log(start, end, times, steps).tolist() == [True, False, False, False, True]
    at_rest = np.full(times.shape, 7)
    assert not beyond_log(start, end, times, at_rest).any()
