"""Analytic scans for tests and benchmarks: a box room, optionally with a ball in it.

Ranges are exact ray intersections (plus optional Gaussian noise), laid out as a points table
with the full grid, so that meshing can be checked against the known surface without the
virtual rig.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from scanpipe.geometry import platform_rotation, scan_plane_direction
from scanpipe.schema import ORIGIN

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class BoxRoom:
    """An axis-aligned room around the scanner, and an optional ball inside it."""

    low_m: tuple[float, float, float] = (-3.0, -1.2, -2.5)
    high_m: tuple[float, float, float] = (4.0, 1.5, 3.0)
    ball_centre_m: tuple[float, float, float] | None = None
    ball_radius_m: float = 0.5

    def ray_range_m(self, origins: F64, directions: F64) -> F64:
        """Distance along unit ``directions`` from ``origins`` (inside) to the first surface."""
        low, high = np.asarray(self.low_m), np.asarray(self.high_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_high = (high - origins) / directions
            t_low = (low - origins) / directions
        t_exit = np.where(directions > 0, t_high, np.where(directions < 0, t_low, np.inf))
        distance = np.min(t_exit, axis=-1)
        if self.ball_centre_m is not None:
            offset = origins - np.asarray(self.ball_centre_m)
            half_b = np.einsum("...k,...k->...", offset, directions)
            c = np.einsum("...k,...k->...", offset, offset) - self.ball_radius_m**2
            disc = half_b * half_b - c
            with np.errstate(invalid="ignore"):
                hit = -half_b - np.sqrt(disc)
            ball = (disc >= 0) & (hit > 0)
            distance = np.where(ball, np.minimum(distance, hit), distance)
        return np.asarray(distance, dtype=np.float64)

    def distance_m(self, points: NDArray[np.floating]) -> F64:
        """Unsigned distance from points inside the room to the nearest wall or the ball."""
        p = np.asarray(points, dtype=np.float64)
        low, high = np.asarray(self.low_m), np.asarray(self.high_m)
        walls = np.minimum(p - low, high - p).min(axis=1)
        distance = np.abs(walls)
        if self.ball_centre_m is not None:
            ball = np.abs(np.linalg.norm(p - np.asarray(self.ball_centre_m), axis=1)
                          - self.ball_radius_m)
            distance = np.minimum(distance, ball)
        return np.asarray(distance, dtype=np.float64)


def scan_table(
    room: BoxRoom,
    alpha_step_deg: float = 2.0,
    beta_step_deg: float = 5.0,
    profiles: int | None = None,
    noise_m: float = 0.0,
    mount_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    seed: int = 0,
) -> pa.Table:
    """A points table (the ``points`` artifact's columns) of a 360° scanner over ``room``.

    ``profiles`` defaults to the half turn (180° / ``beta_step_deg``); more profiles scan past
    180° into the duplicate coverage half.
    """
    samples = round(360.0 / alpha_step_deg)
    profiles = profiles if profiles is not None else round(180.0 / beta_step_deg)
    alpha = np.arange(samples) * float(alpha_step_deg)
    beta = np.arange(profiles) * float(beta_step_deg)
    rotations = platform_rotation(beta)  # (P, 3, 3)
    directions = np.einsum("pij,sj->psi", rotations, scan_plane_direction(alpha))
    origins = np.broadcast_to(
        (rotations @ np.asarray(mount_translation_m, dtype=np.float64))[:, None, :],
        directions.shape)
    ranges = room.ray_range_m(origins, directions)
    if noise_m > 0:
        ranges = ranges + np.random.default_rng(seed).normal(0.0, noise_m, ranges.shape)
    xyz = origins + directions * ranges[..., None]
    profile, sample = np.meshgrid(np.arange(profiles), np.arange(samples), indexing="ij")
    columns = {
        "x": xyz[..., 0], "y": xyz[..., 1], "z": xyz[..., 2], "range_m": ranges,
    }
    data = {name: pa.array(v.ravel().astype(np.float32)) for name, v in columns.items()}
    data["alpha_deg"] = pa.array(np.broadcast_to(alpha, ranges.shape).ravel())
    data["beta_deg"] = pa.array(np.broadcast_to(beta[:, None], ranges.shape).ravel())
    data["time_ns"] = pa.array((profile.ravel() * 200_000_000).astype(np.int64))
    data["profile"] = pa.array(profile.ravel().astype(np.int32))
    data["sample"] = pa.array(sample.ravel().astype(np.int32))
    for axis, name in enumerate(ORIGIN):
        data[name] = pa.array(origins[..., axis].ravel().astype(np.float32))
    return pa.table(data)
