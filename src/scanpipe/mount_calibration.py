"""Self-calibration of the scanner's mount from the scan itself: planes must be flat.

The model (see docs/calibration.md): a return at range r and beam angle α lies at
``P = R_y(β) · (R0 · Rx(a) · r d(α + ψ) + t0 + (dx, 0, dz))`` in the rig frame, where R0, t0
and the α offset are the nominal rig's, ``d(α) = (sin α, cos α, 0)``, and the four fitted
parameters are:

- ``a``: the tilt of the scan plane about the scan's own x axis (the plane no longer holds
  the motor axis);
- ``ψ``: the in-plane rotation, added to the α zero (a mount rotation about the scan plane's
  normal turns the scan within its plane exactly as the α zero does: only their sum is seen);
- ``dx, dz``: the scanner's offset from the motor axis, perpendicular to it.

Not observable from one scan, whatever the scene: a rotation of the whole platform frame about
the motor axis (the β zero, and the mount's rotation about the axis) and a shift along the axis
(the offset along y): the room would simply sit turned or shifted. They keep their nominal
values and the report says so.

The cost (after LM-Calibr and Alismail & Browning): the points fall into voxels; each voxel
that holds a plane contributes its points' distances to the plane fitted to them (re-fitted at
every evaluation, so the cost is the planes' thickness). Coarse to fine: big voxels with loose
flatness first (the wrong mount bends and doubles planes by centimetres), then smaller ones.
Normal-aware weights (after LiMo-Calib) keep planes facing every way in the fit, so a room's
many floor points do not drown its walls. scipy's ``least_squares`` runs with the analytic
Jacobian (the derivative of the distance to the re-fitted plane equals that with the plane
held, at the plane's optimum); the covariance is ``s² (JᵀJ)⁻¹`` at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import StageError
from scanpipe.geometry import rotation_matrix_deg
from scanpipe.rig import Pose, Rig

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: How far the fit may move each parameter from the rig's value (rad, rad, m, m): a mount
#: error beyond these is a wrong rig file, not a calibration.
BOUNDS = np.array([math.radians(10.0), math.radians(10.0), 0.5, 0.5])
#: The fitted parameters, in the order of the parameter vector.
PARAMETERS = ("tilt_x_deg", "alpha_zero_deg", "offset_x_m", "offset_z_m")
#: A parameter whose 1σ exceeds this is not constrained by the scan (unobservable).
MAX_SIGMA = {"tilt_x_deg": 0.2, "alpha_zero_deg": 0.2, "offset_x_m": 0.01,
             "offset_z_m": 0.01}
#: Coarse to fine: voxel edge (m), and how far (degrees, metres) a voxel's plane may lie from
#: the plane it joins (and a point from its plane).
LEVELS = ((0.5, 10.0, 0.15), (0.5, 4.0, 0.06), (0.4, 2.0, 0.03))
#: Normal directions for normal-aware weighting (sign-free): the 13 of a cube's faces,
#: edges and corners.
_DIRS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [1, 0, 1],
                  [1, 0, -1], [0, 1, 1], [0, 1, -1], [1, 1, 1], [1, 1, -1], [1, -1, 1],
                  [-1, 1, 1]], dtype=np.float64)
_DIRS /= np.linalg.norm(_DIRS, axis=1, keepdims=True)


@dataclass(frozen=True)
class ScanSamples:
    """The returns used by the fit: range, beam angle and platform angle per point (degrees
    include the nominal offsets)."""

    range_m: F64
    alpha_deg: F64
    beta_deg: F64


@dataclass
class ParameterEstimate:
    """One parameter: its value, 1σ, whether the scan constrains it, and why not."""

    name: str
    value: float
    sigma: float | None
    observable: bool
    unit: str
    note: str = ""


@dataclass
class MountFit:
    """What the fit found: parameters, residuals, the planes used, and the calibrated rig."""

    parameters: list[ParameterEstimate]
    rig: Rig
    residual_before_m: float
    residual_after_m: float
    planes: int
    points: int
    normal_directions: int
    warnings: list[str] = field(default_factory=list)

    def report(self) -> dict[str, Any]:
        """Plain data for ``--json`` and the stage report."""
        return {
            "parameters": {p.name: {"value": p.value, "sigma": p.sigma,
                                    "observable": p.observable, "unit": p.unit,
                                    **({"note": p.note} if p.note else {})}
                           for p in self.parameters},
            "residual_before_m": self.residual_before_m,
            "residual_after_m": self.residual_after_m,
            "planes": self.planes, "points": self.points,
            "normal_directions": self.normal_directions,
            "warnings": list(self.warnings),
        }


def samples_from_points(points: Any, rig: Rig, max_points: int, seed: int = 0) -> ScanSamples:
    """Valid returns of a ``points`` table (range, α, β columns), at most ``max_points`` of
    them, drawn at random with a fixed seed."""
    r = points.column("range_m").to_numpy(zero_copy_only=False).astype(np.float64)
    alpha = points.column("alpha_deg").to_numpy(zero_copy_only=False).astype(np.float64)
    beta = points.column("beta_deg").to_numpy(zero_copy_only=False).astype(np.float64)
    scanner = rig.scanner
    ok = np.isfinite(r) & (r >= max(scanner.min_range_m, 0.05)) & (r <= scanner.max_range_m)
    index = np.flatnonzero(ok)
    if index.size > max_points:
        index = np.sort(np.random.default_rng(seed).choice(index, max_points, replace=False))
    return ScanSamples(r[index], alpha[index], beta[index])


class _Model:
    """Points and their Jacobian for a parameter vector (a rad, ψ rad, dx m, dz m)."""

    def __init__(self, samples: ScanSamples, rig: Rig) -> None:
        mount = rig.scanner.mount
        self.r = samples.range_m
        self.alpha = np.radians(samples.alpha_deg)
        beta = np.radians(samples.beta_deg)
        self.cb, self.sb = np.cos(beta), np.sin(beta)
        self.r0 = rotation_matrix_deg(mount.rotation_deg)
        self.t0 = np.asarray(mount.translation_m, dtype=np.float64)

    def subset(self, index: I64) -> _Model:
        """The same model over some of its points."""
        out = object.__new__(_Model)
        out.r, out.alpha = self.r[index], self.alpha[index]
        out.cb, out.sb = self.cb[index], self.sb[index]
        out.r0, out.t0 = self.r0, self.t0
        return out

    def points(self, x: F64, jacobian: bool = False) -> tuple[F64, F64 | None]:
        """(N, 3) rig-frame points and, when asked, their (N, 3, 4) derivatives."""
        a, psi, dx, dz = x
        ap = self.alpha + psi
        sa, ca = np.sin(ap), np.cos(ap)
        v0, v1 = self.r * sa, self.r * ca
        c, s = math.cos(a), math.sin(a)
        w = (v0, c * v1, s * v1)
        m = self.r0
        t = self.t0 + np.array([dx, 0.0, dz])
        q = [m[k, 0] * w[0] + m[k, 1] * w[1] + m[k, 2] * w[2] + t[k] for k in range(3)]
        cb, sb = self.cb, self.sb
        p = np.stack([q[0] * cb - q[2] * sb, q[1], q[0] * sb + q[2] * cb], axis=1)
        if not jacobian:
            return p, None
        dvp0, dvp1 = self.r * ca, -self.r * sa  # d v / d ψ
        dw = {0: (np.zeros_like(v0), -s * v1, c * v1),  # d w / d a
              1: (dvp0, c * dvp1, s * dvp1)}  # d w / d ψ
        jac = np.zeros((p.shape[0], 3, 4))
        for j, (w0, w1, w2) in dw.items():
            dq = [m[k, 0] * w0 + m[k, 1] * w1 + m[k, 2] * w2 for k in range(3)]
            jac[:, 0, j] = dq[0] * cb - dq[2] * sb
            jac[:, 1, j] = dq[1]
            jac[:, 2, j] = dq[0] * sb + dq[2] * cb
        jac[:, 0, 2], jac[:, 2, 2] = cb, sb
        jac[:, 0, 3], jac[:, 2, 3] = -sb, cb
        return p, jac


@dataclass
class _Planes:
    """Voxel planes: each kept point's voxel (0…V−1) and its weight."""

    member: I64  # index into the model's points of each kept point
    voxel: I64
    weight: F64
    count: int
    directions: int


def _plane_fit(p: F64, voxel: I64, weight: F64, count: int) -> tuple[F64, F64, F64]:
    """Weighted per-voxel planes: unit normals (V, 3), offsets (V,), eigenvalues (V, 3)."""
    wsum = np.bincount(voxel, weight, count)
    mean: F64 = np.stack([np.bincount(voxel, weight * p[:, k], count) for k in range(3)],
                         1).astype(np.float64) / wsum[:, None]
    d = p - mean[voxel]
    cov = np.empty((count, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(voxel, weight * d[:, i] * d[:, j], count)
    cov /= wsum[:, None, None]
    values, vectors = np.linalg.eigh(cov)
    normal = vectors[:, :, 0]
    return normal, np.einsum("vk,vk->v", normal, mean), values


def _voxel_planes(p: F64, size_m: float, angle_deg: float, tolerance_m: float) -> _Planes:
    """Whole planes: flat voxels of ``size_m`` merged when their normals agree within
    ``angle_deg`` and their offsets within ``tolerance_m``, then the points within
    ``tolerance_m`` of the merged plane; normal-aware weights."""
    cell = np.floor(p / size_m).astype(np.int64)
    flat_cell = (cell[:, 0] * 1_000_003 + cell[:, 1]) * 1_000_003 + cell[:, 2]
    _, voxel, counts = np.unique(flat_cell, return_inverse=True, return_counts=True)
    voxel = voxel.ravel()
    ones = np.ones(p.shape[0])
    normal, offset, values = _plane_fit(p, voxel, ones, counts.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        flat = (counts >= 15) & (values[:, 0] <= 0.05 * values[:, 1]) & (
            values[:, 1] >= 0.05 * values[:, 2])
    candidates = np.flatnonzero(flat)
    candidates = candidates[np.argsort(-counts[candidates])]
    cos_limit = math.cos(math.radians(angle_deg))
    label = np.full(counts.size, -1, np.int64)
    planes_n: list[F64] = []
    planes_d: list[float] = []
    for seed in candidates:
        if label[seed] >= 0:
            continue
        n, d = normal[seed], float(offset[seed])
        dots = normal[candidates] @ n
        sign = np.where(dots < 0, -1.0, 1.0)
        same = (np.abs(dots) >= cos_limit) & (np.abs(sign * offset[candidates] - d)
                                               <= tolerance_m) & (label[candidates] < 0)
        chosen = candidates[same]
        if counts[chosen].sum() < 200:
            label[seed] = -2
            continue
        label[chosen] = len(planes_n)
        planes_n.append(n)
        planes_d.append(d)
    if not planes_n:
        return _Planes(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), 0, 0)
    plane_of_point = label[voxel]
    member = np.flatnonzero(plane_of_point >= 0)
    pn = np.asarray(planes_n)
    pd = np.asarray(planes_d)
    k = plane_of_point[member]
    near = np.abs(np.einsum("ik,ik->i", p[member], pn[k]) - pd[k]) <= tolerance_m
    member, k = member[near], k[near]
    count = len(planes_n)
    sizes = np.bincount(k, minlength=count).astype(np.float64)
    # Normal-aware: every direction of plane weighs alike, whatever its points' number.
    direction = np.argmax(np.abs(pn @ _DIRS.T), axis=1)
    area_per_dir = np.bincount(direction, sizes, len(_DIRS))
    weight = (1.0 / np.maximum(area_per_dir[direction], 1.0))[k]
    weight *= member.size / max(float(weight.sum()), 1e-12)
    return _Planes(member, k, weight, count, int(np.count_nonzero(area_per_dir > 0)))


def _residuals(model: _Model, planes: _Planes, x: F64, jacobian: bool
               ) -> tuple[F64, F64 | None]:
    p, dp = model.points(x, jacobian)  # the model holds the planes' members only
    normal, offset, _ = _plane_fit(p, planes.voxel, planes.weight, planes.count)
    n = normal[planes.voxel]
    sw = np.sqrt(planes.weight)
    res = (np.einsum("ik,ik->i", n, p) - offset[planes.voxel]) * sw
    if dp is None:
        return res, None
    jac = np.einsum("ik,ikj->ij", n, dp) * sw[:, None]
    return res, _project_out_planes(jac, p, normal, planes, sw)


def _project_out_planes(jac: F64, p: F64, normal: F64, planes: _Planes, sw: F64) -> F64:
    """The Jacobian of the distances to planes that are re-fitted (variable projection):
    remove from each plane's rows what a change of that plane (its offset and two tilts)
    explains, so Gauss–Newton sees the cost the planes' thickness really is."""
    count, k = planes.count, planes.voxel
    helper = np.where(np.abs(normal[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]),
                      np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    wsum = np.bincount(k, planes.weight, count)
    centre: F64 = np.stack([np.bincount(k, planes.weight * p[:, j], count) for j in range(3)],
                           1).astype(np.float64) / wsum[:, None]
    d = p - centre[k]
    basis = np.stack([sw, sw * np.einsum("ik,ik->i", d, e1[k]),
                      sw * np.einsum("ik,ik->i", d, e2[k])], 1)  # (N, 3)
    gram = np.empty((count, 3, 3))
    cross = np.empty((count, 3, jac.shape[1]))
    for i in range(3):
        for j in range(3):
            gram[:, i, j] = np.bincount(k, basis[:, i] * basis[:, j], count)
        for j in range(jac.shape[1]):
            cross[:, i, j] = np.bincount(k, basis[:, i] * jac[:, j], count)
    gram += np.eye(3) * 1e-12
    coef = np.linalg.solve(gram, cross)  # (V, 3, P)
    return np.asarray(jac - np.einsum("ib,ibj->ij", basis, coef[k]), dtype=np.float64)


def _solve(model: _Model, planes: _Planes, x0: F64, free: NDArray[np.bool_],
           scale_m: float) -> F64:
    from scipy.optimize import least_squares

    if not free.any():
        return x0
    model = model.subset(planes.member)

    def fun(y: F64) -> F64:
        x = x0.copy()
        x[free] = y
        return _residuals(model, planes, x, False)[0]

    def jac(y: F64) -> F64:
        x = x0.copy()
        x[free] = y
        j = _residuals(model, planes, x, True)[1]
        assert j is not None
        return j[:, free]

    # Bounded: a thickness cost also falls when the scene collapses (a 90° tilt flattens a
    # floor to a line), so the parameters stay near the rig's values (BOUNDS).
    result = least_squares(fun, np.clip(x0[free], -BOUNDS[free], BOUNDS[free]), jac=jac,
                           method="trf", bounds=(-BOUNDS[free], BOUNDS[free]),
                           x_scale=np.array([0.01, 0.01, 0.01, 0.01])[free], max_nfev=20,
                           xtol=1e-7, ftol=1e-9)
    x = x0.copy()
    x[free] = result.x
    return x


def _rms(model: _Model, planes: _Planes, x: F64) -> float:
    res, _ = _residuals(model.subset(planes.member), planes, x, False)
    w = planes.weight
    return float(np.sqrt(np.sum(res**2) / max(np.sum(w), 1e-12)))


def fit_mount(samples: ScanSamples, rig: Rig) -> MountFit:
    """Fit the mount (tilt, α zero, offsets perpendicular to the axis) to one scan.

    Parameters the scan does not constrain (1σ above :data:`MAX_SIGMA`) keep their nominal
    value and are reported unobservable with the reason; the rest are refitted without them.
    """
    mount = rig.scanner.mount
    axis_in_scan = rotation_matrix_deg(mount.rotation_deg).T @ np.array([0.0, 1.0, 0.0])
    if abs(axis_in_scan[1]) < 0.9:
        raise StageError("calibrate: the rig's scan plane does not hold the motor axis (its "
                         f"mount rotation {list(mount.rotation_deg)}° turns the axis "
                         f"{math.degrees(math.acos(min(1.0, abs(axis_in_scan[1])))):.0f}° "
                         "away from the scan's α = 0 direction); self-calibration models a "
                         "scanner mounted upright, within 25° of it")
    if samples.range_m.size < 1000:
        raise StageError(f"calibrate: only {samples.range_m.size} valid returns; at least "
                         "1000 are needed to find planes")
    model = _Model(samples, rig)
    x = np.zeros(4)
    free = np.ones(4, bool)
    planes = None
    before = None
    # Twice: planes chosen under the nominal mount can join the wrong pieces and hold the fit
    # in a false minimum; chosen again under the first fit, they let it go (a 360° seed moved
    # from 14 mm to 0.4 mm off).
    for size_m, angle_deg, tolerance_m in (*LEVELS, *LEVELS[1:]):
        planes = _voxel_planes(model.points(x)[0], size_m, angle_deg, tolerance_m)
        if planes.count < 1:
            continue
        if before is None:
            before = _rms(model, planes, np.zeros(4))
        x = _solve(model, planes, x, free, scale_m=tolerance_m / 3)
    if planes is None or planes.count < 1:
        raise StageError("calibrate: no plane found in the scan; "
                         "self-calibration needs flat surfaces (walls, floor, ceiling)")
    # Final planes at the solution, then observability from the covariance.
    planes = _voxel_planes(model.points(x)[0], *LEVELS[-1])
    x = _solve(model, planes, x, free, scale_m=0.02)
    sigma = _sigmas(model, planes, x, free)
    warnings: list[str] = []
    at_bound = np.abs(x) >= BOUNDS * 0.999
    unobservable = np.array([s is None or s > MAX_SIGMA[n] for n, s in zip(PARAMETERS, sigma,
                                                                              strict=True)])
    unobservable |= at_bound
    if unobservable.any():
        free = ~unobservable
        x[unobservable] = 0.0
        x = _solve(model, planes, x, free, scale_m=0.02)
        kept = _sigmas(model, planes, x, free)
        sigma = [kept[i] if free[i] else sigma[i] for i in range(4)]
        names = ", ".join(n for n, u in zip(PARAMETERS, unobservable, strict=True) if u)
        warnings.append(f"calibrate: {names} not constrained by this scan ({planes.count} "
                        f"planes facing {planes.directions} direction(s)); kept at the "
                        "rig's values: scan a room with planes facing several ways")
    after = _rms(model, planes, x)
    return MountFit(
        parameters=_estimates(rig, x, sigma, unobservable),
        rig=_calibrated_rig(rig, x),
        residual_before_m=float(before if before is not None else after),
        residual_after_m=after, planes=planes.count, points=int(planes.member.size),
        normal_directions=planes.directions, warnings=warnings)


def _sigmas(model: _Model, planes: _Planes, x: F64, free: NDArray[np.bool_]
            ) -> list[float | None]:
    """1σ of each parameter (in its reported unit) from ``s² (JᵀJ)⁻¹``; None when the
    information matrix is singular in that parameter."""
    res, jac = _residuals(model.subset(planes.member), planes, x, True)
    assert jac is not None
    dof = max(res.size - int(free.sum()) - planes.count * 3, 1)
    s2 = float(np.sum(res**2) / dof)
    info = jac.T @ jac
    scale = np.sqrt(np.maximum(np.diag(info), 1e-300))
    normalised = info / np.outer(scale, scale)
    values, vectors = np.linalg.eigh(normalised)
    floor = 1e-9 * max(float(values.max()), 1e-300)
    inv = (vectors / np.maximum(values, floor)) @ vectors.T / np.outer(scale, scale)
    units = np.array([math.degrees(1), math.degrees(1), 1.0, 1.0])
    out: list[float | None] = []
    for i in range(4):
        # A direction of (near) zero information: unobservable, whatever the numbers say.
        weak = bool(np.any((values < 1e-6 * values.max()) & (np.abs(vectors[i]) > 0.1)))
        out.append(None if weak or np.diag(info)[i] <= 0 else
                   float(math.sqrt(max(inv[i, i] * s2, 0.0)) * units[i]))
    return out


def _calibrated_rig(rig: Rig, x: F64) -> Rig:
    a, psi, dx, dz = x
    scanner = rig.scanner
    rotation = rotation_matrix_deg(scanner.mount.rotation_deg) @ rotation_matrix_deg(
        (math.degrees(a), 0.0, 0.0))
    t = scanner.mount.translation_m
    mount = Pose(translation_m=(t[0] + dx, t[1], t[2] + dz),
                 rotation_deg=euler_deg(rotation))
    alpha = scanner.alpha_offset_deg + math.degrees(psi)
    new_scanner = scanner.model_copy(update={"mount": mount, "alpha_offset_deg": alpha})
    return rig.model_copy(update={"scanner": new_scanner})


def euler_deg(rotation: F64) -> tuple[float, float, float]:
    """Euler angles ``(rx, ry, rz)`` in degrees of ``R = Rz @ Ry @ Rx`` (the rig's order)."""
    ry = math.asin(max(-1.0, min(1.0, -float(rotation[2, 0]))))
    rx = math.atan2(float(rotation[2, 1]), float(rotation[2, 2]))
    rz = math.atan2(float(rotation[1, 0]), float(rotation[0, 0]))
    return math.degrees(rx), math.degrees(ry), math.degrees(rz)


def _estimates(rig: Rig, x: F64, sigma: list[float | None], unobservable: NDArray[np.bool_]
               ) -> list[ParameterEstimate]:
    scanner = rig.scanner
    fitted = _calibrated_rig(rig, x).scanner
    values = [fitted.mount.rotation_deg[0], fitted.alpha_offset_deg,
              fitted.mount.translation_m[0], fitted.mount.translation_m[2]]
    units = ["deg", "deg", "m", "m"]
    notes = ["scanner.mount.rotation_deg[0]: the scan plane's tilt about its horizontal axis",
             "scanner.alpha_offset_deg: includes the mount's in-plane rotation (rz), which "
             "turns the scan within its plane exactly as the α zero does",
             "scanner.mount.translation_m[0]", "scanner.mount.translation_m[2]"]
    out = [ParameterEstimate(name, float(v), sigma[i], not bool(unobservable[i]), units[i],
                             notes[i] + ("; not constrained by this scan: kept at the rig's "
                                         "value" if unobservable[i] else ""))
           for i, (name, v) in enumerate(zip(PARAMETERS, values, strict=True))]
    out += [
        ParameterEstimate("offset_y_m", float(scanner.mount.translation_m[1]), None, False, "m",
                          "the offset along the motor axis shifts the whole scan along it: "
                          "not observable from one scan; kept at the rig's value"),
        ParameterEstimate("beta_zero_deg", float(rig.motor.beta_offset_deg), None, False, "deg",
                          "the β zero (and the mount's rotation about the axis, ry) turns the "
                          "whole scan about the axis: not observable from one scan; kept"),
    ]
    return out


def observable_invariants(rig: Rig) -> dict[str, float]:
    """What one scan determines of a rig's mount, free of the unobservable turn about the
    axis and shift along it: the scan plane's tilt from the axis, the axis' angle within the
    scan plane (α zero and in-plane rotation together), and the offsets from the axis across
    and along the scan plane. Used to compare a fit with the truth."""
    scanner = rig.scanner
    rotation = rotation_matrix_deg(scanner.mount.rotation_deg) @ rotation_matrix_deg(
        (0.0, 0.0, -scanner.alpha_offset_deg))
    u = rotation.T @ np.array([0.0, 1.0, 0.0])  # the motor axis in the scan frame
    n = rotation @ np.array([0.0, 0.0, 1.0])  # the scan plane's normal in the platform
    n_h = np.array([n[0], 0.0, n[2]]) / math.hypot(n[0], n[2])
    across = np.cross(np.array([0.0, 1.0, 0.0]), n_h)
    t = np.asarray(scanner.mount.translation_m, dtype=np.float64)
    return {"tilt_deg": math.degrees(math.asin(float(u[2]))),
            "axis_in_plane_deg": math.degrees(math.atan2(float(u[0]), float(u[1]))),
            "offset_normal_m": float(t @ n_h), "offset_in_plane_m": float(t @ across)}
