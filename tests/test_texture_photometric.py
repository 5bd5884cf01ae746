"""Photometric outliers: the sorting network and the blockwise judge against a plain per-face
reference (np.nanmedian), for the default six views and for more than the network takes."""

from __future__ import annotations

import numpy as np
import pytest

from scanpipe.texturing.photometric import (
    NETWORK_SLOTS,
    Views,
    pack_levels,
    packed_image,
    photometric_outliers,
    sort_small_axis0,
    unpack_levels,
)


@pytest.mark.parametrize("count", [1, 2, 3, 5, 6, 8, NETWORK_SLOTS + 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sort_small_axis0_is_npsort(count: int, dtype: type) -> None:
    rng = np.random.default_rng(count)
    values = rng.integers(0, 6, size=(count, 5000, 3)).astype(dtype)  # many ties
    values[rng.random(values.shape) < 0.2] = np.inf  # not sampled
    expected = np.sort(values, axis=0)
    np.testing.assert_array_equal(sort_small_axis0(values.copy()), expected)


def plain_outliers(views: Views, gains: np.ndarray, levels: float) -> np.ndarray:
    """The module docstring's rule, face by face."""
    outlier = np.zeros(views.frame.shape, bool)
    for face in range(len(views.frame)):
        colour = views.colour[face].astype(np.float64)
        sampled = np.isfinite(colour[:, 0])
        if sampled.sum() < 3:
            continue
        level = (colour * gains[np.maximum(views.frame[face], 0)]).astype(np.float32)
        median = np.nanmedian(level, axis=0)
        deviation = np.abs(level - median).max(axis=1)
        mad = np.nanmedian(deviation) * 1.4826
        outlier[face] = sampled & (deviation > max(levels, 3 * mad))
    return outlier


@pytest.mark.parametrize("slots", [6, NETWORK_SLOTS + 4])
def test_outliers_are_the_plain_rule(slots: int) -> None:
    rng = np.random.default_rng(slots)
    faces, frames = 3000, 40
    frame = rng.integers(0, frames, size=(faces, slots))
    frame[rng.random(frame.shape) < 0.2] = -1
    colour = (rng.normal(120, 8, size=(faces, 1, 3)) + rng.normal(0, 6, size=(faces, slots, 3))
              ).astype(np.float32)
    person = rng.random((faces, slots)) < 0.1  # someone walking through these frames
    colour[person] = rng.uniform(0, 255, size=(int(person.sum()), 3))
    colour[(frame < 0) | (rng.random(frame.shape) < 0.05)] = np.nan  # none, or off the image
    gains = rng.uniform(0.8, 1.25, size=(frames, 3))
    views = Views.from_levels(frame, colour)
    outlier = photometric_outliers(views, gains, 40.0)
    assert outlier.sum() > 100  # the test has outliers to find
    np.testing.assert_array_equal(outlier, plain_outliers(views, gains, 40.0))


def test_packed_levels_round_trip() -> None:
    """A colour sample in one uint32: the three levels back exactly, NaN where not sampled
    (also a black pixel, which is sampled)."""
    colour = np.array([[[0, 0, 0], [255, 128, 7], [np.nan] * 3],
                       [[12, 250, 99], [np.nan] * 3, [1, 2, 3]]], np.float32)
    packed = pack_levels(colour)
    assert packed.dtype == np.uint32 and packed.shape == (2, 3)
    assert (packed == 0).tolist() == [[False, False, True], [False, True, False]]
    np.testing.assert_array_equal(unpack_levels(packed), colour)  # NaN where NaN
    image = np.array([[[7, 128, 255], [0, 0, 0]]], np.uint8)  # BGR as decoded
    np.testing.assert_array_equal(unpack_levels(packed_image(image)), image.astype(np.float32))


@pytest.mark.parametrize("gain_range", [(1.0, 1.0), (0.9, 1.1), (0.5, 2.0)])
def test_outliers_near_the_limit_are_the_plain_rule(gain_range: tuple[float, float]) -> None:
    """Faces whose levelled colours span about ``outlier_levels`` (the quick test that skips
    the even faces decides there): the plain rule's outliers, face for face."""
    rng = np.random.default_rng(int(gain_range[1] * 10))
    faces, slots, frames = 1500, 6, 30
    frame = rng.integers(0, frames, size=(faces, slots))
    frame[rng.random(frame.shape) < 0.1] = -1
    low = rng.integers(40, 160, size=(faces, 1, 3))
    span = rng.integers(36, 45, size=(faces, 1, 1))  # recorded spread about the limit of 40
    colour = (low + rng.integers(0, 2, size=(faces, slots, 3)) * span).astype(np.float32)
    colour[frame < 0] = np.nan
    gains = rng.uniform(*gain_range, size=(frames, 3))
    views = Views.from_levels(frame, colour)
    outlier = photometric_outliers(views, gains, 40.0)
    np.testing.assert_array_equal(outlier, plain_outliers(views, gains, 40.0))
    if gain_range == (1.0, 1.0):
        assert outlier.sum() > 30  # the limit is crossed both ways here
