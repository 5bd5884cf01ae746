"""The simulated 2-D scanner: true ranges by ray casting, then the measurement model.

A profile's samples are taken while the head turns: sample i (beam angle α_i) is measured
``(α_i − start) / (360 · scan_hz)`` seconds after the profile starts, at the platform angle of
that instant. Rays leave the scanner's TRUE optical centre (its mounting pose on the platform
included) along the TRUE beam direction (alpha offset and mount tilt included); the nominal rig
the user believes may differ. The measurement model, deterministic per (seed, profile):
Gaussian range noise, dropouts (a base rate plus grazing incidence), optional mixed pixels at
depth edges, and the scanner's minimum and maximum range. Quantisation to 1/256 m happens in
the wire encoders; the truth stays noise-free and un-quantised.

The echo amplitude (:func:`echo_amplitude`) follows the lidar equation for a diffuse target:
``ECHO_AT_1M · ρ · cos θ / r²`` (r in metres, at least ``ECHO_NEAR_M``), clipped to u16, where
ρ is the reflectance of the hit surface (the luminance of its texture, at least
``MIN_REFLECTANCE``) and θ the incidence angle; 0 where there is no return.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from scanpipe.geometry import rotation_matrix_deg, scan_plane_direction
from scanpipe.rig import ScannerConfig
from scanpipe.sim.scene import Scene

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class MeasurementModel:
    """How a true range becomes a measured one (see the module docstring)."""

    noise_sigma_m: float = 0.010
    dropout_rate: float = 0.002
    grazing_start_deg: float = 75.0
    mixed_pixels: bool = False
    mixed_pixel_rate: float = 0.5
    mixed_pixel_edge_m: float = 0.2
    seed: int = 0


def beam_angles_deg(scanner: ScannerConfig) -> F64:
    """The nominal beam angle of every sample of a profile: ``start + i · step``."""
    return np.asarray(
        scanner.start_angle_deg + np.arange(scanner.samples_per_profile) * scanner.beam_step_deg,
        dtype=np.float64,
    )


def sample_time_offsets_s(scanner: ScannerConfig) -> F64:
    """Seconds from a profile's start to each sample (the head turns at ``scan_hz``)."""
    return (beam_angles_deg(scanner) - scanner.start_angle_deg) / (360.0 * scanner.scan_hz)


def sector_duration_s(scanner: ScannerConfig) -> float:
    """Seconds from a profile's first to its last sample plus one step (the sector's time)."""
    return (scanner.end_angle_deg - scanner.start_angle_deg) / (360.0 * scanner.scan_hz)


@dataclass(frozen=True)
class TrueProfiles:
    """Noise-free ranges (NaN = no hit or out of the scanner's range) and the cosine of the
    incidence angle, both (profiles, samples)."""

    ranges_m: F64
    cos_incidence: F32
    #: Diffuse reflectance 0..1 of the surface hit (None: unknown, taken as 0.5).
    reflectance: F32 | None = None


#: Echo of a white (ρ = 1) surface at 1 m, hit head-on (u16 counts).
ECHO_AT_1M = 40_000.0
#: Closer than this the receiver saturates: the range fall-off stops.
ECHO_NEAR_M = 0.8
#: Even black paint returns a little.
MIN_REFLECTANCE = 0.05
#: Rec. 709 luma weights: a texture's RGB to its reflectance.
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def surface_reflectance(rgb: NDArray[np.uint8]) -> F32:
    """Diffuse reflectance 0..1 of surfaces of colour ``rgb`` (N, 3): their luminance, at least
    :data:`MIN_REFLECTANCE`."""
    luma = (np.asarray(rgb, dtype=np.float32) @ _LUMA) / 255.0
    return np.asarray(np.maximum(luma, MIN_REFLECTANCE), dtype=np.float32)


def echo_amplitude(measured_m: NDArray[np.floating], truth: TrueProfiles) -> NDArray[np.uint16]:
    """The echo of every measured sample (same shape as ``measured_m``; 0 = no return)."""
    rho = (np.full(truth.cos_incidence.shape, 0.5, np.float32) if truth.reflectance is None
           else truth.reflectance)
    r = np.maximum(np.nan_to_num(np.asarray(measured_m, np.float32), nan=1.0), ECHO_NEAR_M)
    echo = ECHO_AT_1M * rho * truth.cos_incidence / (r * r)
    echo = np.where(np.isfinite(measured_m), np.clip(np.rint(echo), 1, 65535), 0)
    return np.asarray(echo, dtype=np.uint16)


def true_ranges(scene: Scene, scanner_true: ScannerConfig, beta_deg: F64,
                beam_deg: F64 | None = None) -> TrueProfiles:
    """Cast every sample of many profiles in one call.

    ``beta_deg`` is (profiles, samples): the true platform angle at each sample's instant.
    ``scanner_true`` is the true scanner (mount pose and alpha offset as they really are).
    ``beam_deg``: the samples' device angles (default: the scanner's grid,
    :func:`beam_angles_deg`), for heads whose beams do not sit on a fixed grid (LDRobot).
    """
    beta = np.atleast_2d(np.asarray(beta_deg, dtype=np.float64))
    beams = beam_angles_deg(scanner_true) if beam_deg is None else np.asarray(beam_deg,
                                                                              np.float64)
    alpha = beams + scanner_true.alpha_offset_deg
    mount_r = rotation_matrix_deg(scanner_true.mount.rotation_deg)
    d_platform = scan_plane_direction(alpha) @ mount_r.T  # (S, 3)
    t_mount = np.asarray(scanner_true.mount.translation_m, dtype=np.float64)
    c, s = np.cos(np.radians(beta)), np.sin(np.radians(beta))  # (P, S)
    directions = np.stack(
        [d_platform[:, 0] * c - d_platform[:, 2] * s,
         np.broadcast_to(d_platform[:, 1], c.shape),
         d_platform[:, 0] * s + d_platform[:, 2] * c], axis=-1)
    origins = np.stack(
        [t_mount[0] * c - t_mount[2] * s, np.full(c.shape, t_mount[1]),
         t_mount[0] * s + t_mount[2] * c], axis=-1)
    hits = scene.cast(origins.reshape(-1, 3), directions.reshape(-1, 3))
    ranges = hits.t_hit_m.reshape(beta.shape)
    in_window = (ranges >= scanner_true.min_range_m) & (ranges <= scanner_true.max_range_m)
    ranges = np.where(np.isfinite(ranges) & in_window, ranges, np.nan)
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal.astype(np.float64),
                               directions.reshape(-1, 3))).astype(np.float32)
    reflectance = surface_reflectance(scene.color_at(hits.triangle_id, hits.barycentric))
    return TrueProfiles(ranges, cos_inc.reshape(beta.shape), reflectance.reshape(beta.shape))


def profile_rng(seed: int, profile: int) -> np.random.Generator:
    """The random stream of one profile: the same in direct mode and in the emulator."""
    return np.random.default_rng([seed, profile])


def packet_beams(scene: Scene, scanner_true: ScannerConfig, beta_deg: F64) -> TrueProfiles:
    """What each sample of the profiles measures: :func:`true_ranges` on the grid, except for
    a head whose samples are not where their angle says (the LD14/LD14P, dialect
    ``ldrobot_ld14``: the sample reported at angle ``a`` is the beam at ``a − shift(d)``,
    :func:`scanpipe.protocol.ldrobot.sl_packet_angles_deg`), whose beams are cast there, one
    profile at a time (their angles differ per profile). The truth of the profile itself stays
    :func:`true_ranges` on the grid: the decoder's correction maps the samples back onto it."""
    beta = np.atleast_2d(np.asarray(beta_deg, np.float64))
    if scanner_true.dialect != "ldrobot_ld14":
        return true_ranges(scene, scanner_true, beta)
    from scanpipe.protocol import ldrobot

    grid = beam_angles_deg(scanner_true)
    rows = []
    for row in beta:
        def range_at(beam_deg: F64, row: F64 = row) -> F64:
            cast = true_ranges(scene, scanner_true, row[None, :], beam_deg=beam_deg)
            return np.asarray(cast.ranges_m[0], np.float64)

        beams, ranges = ldrobot.sl_packet_angles_deg(grid, range_at)
        cast = true_ranges(scene, scanner_true, row[None, :], beam_deg=beams)
        # where the beam found is not consistent (a depth edge), no return
        rows.append(replace(cast, ranges_m=np.where(np.isfinite(ranges), cast.ranges_m,
                                                    np.nan).astype(cast.ranges_m.dtype)))
    reflectance = [r.reflectance for r in rows]
    return TrueProfiles(
        np.concatenate([r.ranges_m for r in rows]),
        np.concatenate([r.cos_incidence for r in rows]),
        None if any(r is None for r in reflectance) else np.concatenate(
            [r for r in reflectance if r is not None]))


def measure(truth: TrueProfiles, model: MeasurementModel, first_profile: int,
            scanner: ScannerConfig) -> F32:
    """Measured ranges (float32, NaN = no return) for consecutive profiles starting at index
    ``first_profile``; each profile draws from its own stream (:func:`profile_rng`)."""
    ranges = truth.ranges_m
    measured = np.empty(ranges.shape, dtype=np.float32)
    grazing = np.cos(np.radians(model.grazing_start_deg))
    for row in range(ranges.shape[0]):
        rng = profile_rng(model.seed, first_profile + row)
        true_row = ranges[row]
        samples = len(true_row)
        noise = rng.standard_normal(samples) * model.noise_sigma_m
        drop_draw = rng.random(samples)
        value = true_row.copy()
        if model.mixed_pixels:
            value = _mixed_pixels(value, model, rng)
        value = value + noise
        # grazing incidence: the return fades linearly from the start angle to 90°
        cos_inc = truth.cos_incidence[row].astype(np.float64)
        p_graze = np.clip((grazing - cos_inc) / max(grazing, 1e-9), 0.0, 1.0)
        dropped = drop_draw < model.dropout_rate + (1 - model.dropout_rate) * p_graze
        value[dropped] = np.nan
        value[(value < scanner.min_range_m) | (value > scanner.max_range_m)] = np.nan
        measured[row] = value
    return measured



def _mixed_pixels(ranges: F64, model: MeasurementModel, rng: np.random.Generator) -> F64:
    """At a depth edge the beam straddles both surfaces: some samples get a range between them."""
    draws = rng.random(len(ranges))
    weights = rng.random(len(ranges))
    nxt = np.roll(ranges, -1)
    jump = np.abs(nxt - ranges) > model.mixed_pixel_edge_m
    edge = np.isfinite(ranges) & np.isfinite(nxt) & jump
    edge[-1] = False
    mixed = edge & (draws < model.mixed_pixel_rate)
    out = ranges.copy()
    out[mixed] = weights[mixed] * ranges[mixed] + (1 - weights[mixed]) * nxt[mixed]
    return out
