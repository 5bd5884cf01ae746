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


def _moments(p: F64, voxel: I64, weight: F64, count: int) -> tuple[F64, F64, F64]:
    """Weighted per-voxel sums: weights (V,), means (V, 3), covariances (V, 3, 3)."""
    wsum: F64 = np.bincount(voxel, weight, count).astype(np.float64)
    safe = np.maximum(wsum, 1e-300)
    mean: F64 = np.stack([np.bincount(voxel, weight * p[:, k], count) for k in range(3)],
                         1).astype(np.float64) / safe[:, None]
    d = p - mean[voxel]
    cov = np.empty((count, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(voxel, weight * d[:, i] * d[:, j], count)
    cov /= safe[:, None, None]
    return wsum, mean, cov


def _plane_fit(p: F64, voxel: I64, weight: F64, count: int) -> tuple[F64, F64, F64]:
    """Weighted per-voxel planes: unit normals (V, 3), offsets (V,), eigenvalues (V, 3)."""
    _, mean, cov = _moments(p, voxel, weight, count)
    values, vectors = np.linalg.eigh(cov)
    normal = vectors[:, :, 0]
    return normal, np.einsum("vk,vk->v", normal, mean), values


def _voxel_planes(p: F64, size_m: float, angle_deg: float, tolerance_m: float) -> _Planes:
    """Whole planes: flat voxels of ``size_m`` grown into planes (a voxel joins when its
    normal agrees within ``angle_deg`` and its centre lies within ``tolerance_m`` of the plane
    refitted from the voxels taken so far), then the points within ``tolerance_m`` of the
    plane; normal-aware weights."""
    cell = np.floor(p / size_m).astype(np.int64)
    flat_cell = (cell[:, 0] * 1_000_003 + cell[:, 1]) * 1_000_003 + cell[:, 2]
    _, voxel, counts = np.unique(flat_cell, return_inverse=True, return_counts=True)
    voxel = voxel.ravel()
    wsum, mean, cov = _moments(p, voxel, np.ones(p.shape[0]), counts.size)
    values, vectors = np.linalg.eigh(cov)
    normal = vectors[:, :, 0]
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
        n, d = normal[seed], float(normal[seed] @ mean[seed])
        chosen = np.array([seed])
        # Region growing on the whole plane, refitted from the voxels it took (pooled
        # moments): a voxel joins when its normal agrees and its points' centre lies on the
        # plane. Compared by offsets at the origin instead, a voxel whose normal is off by
        # its noise (0.4° at 3 m: 2 cm) is left out, and a wall falls into pieces; points
        # then go to the nearer of two almost coincident planes by the sign of their noise,
        # a bias the fit takes for a mount error (2-3 mm across the scan plane at 180°).
        for _ in range(3):
            free = candidates[(label[candidates] < 0)]
            same = (np.abs(normal[free] @ n) >= cos_limit) & (
                np.abs(mean[free] @ n - d) <= tolerance_m)
            chosen = free[same]
            if chosen.size == 0:
                chosen = np.array([seed])
                break
            w = wsum[chosen]
            centre = (w[:, None] * mean[chosen]).sum(0) / w.sum()
            spread = mean[chosen] - centre
            pooled = np.einsum("v,vij->ij", w, cov[chosen]) + np.einsum(
                "v,vi,vj->ij", w, spread, spread)
            n = np.linalg.eigh(pooled)[1][:, 0]
            d = float(n @ centre)
        if counts[chosen].sum() < 200:
            label[seed] = -2
            continue
        label[chosen] = len(planes_n)
        planes_n.append(n)
        planes_d.append(d)
    if not planes_n:
        return _Planes(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), 0, 0)
    pn = np.asarray(planes_n)
    pd = np.asarray(planes_d)
    member, k = _members(p, cell, np.unique(flat_cell), label, pn, pd, size_m, tolerance_m)
    count = len(planes_n)
    sizes = np.bincount(k, minlength=count).astype(np.float64)
    # Normal-aware: every direction of plane weighs alike, whatever its points' number.
    direction = np.argmax(np.abs(pn @ _DIRS.T), axis=1)
    area_per_dir = np.bincount(direction, sizes, len(_DIRS))
    weight = (1.0 / np.maximum(area_per_dir[direction], 1.0))[k]
    weight *= member.size / max(float(weight.sum()), 1e-12)
    return _Planes(member, k, weight, count, int(np.count_nonzero(area_per_dir > 0)))


def _members(p: F64, cell: I64, keys: I64, label: I64, normal: F64, offset: F64,
             size_m: float, tolerance_m: float) -> tuple[I64, I64]:
    """Each point's plane: the nearest, within ``tolerance_m``, of the planes that hold its
    voxel or a voxel ``tolerance_m`` away along an axis.

    Not its own voxel's alone: a surface lying on a voxel face splits its points between two
    voxels by the sign of their noise, and where one of the two is not kept (too few points,
    a corner) the plane would keep only the points on one side of it: a bias of about a σ
    that the fit would take for a mount error."""
    choices = [cell]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            shifted = p.copy()
            shifted[:, axis] += sign * tolerance_m
            choices.append(np.floor(shifted / size_m).astype(np.int64))
    best = np.full(p.shape[0], -1, np.int64)
    best_distance = np.full(p.shape[0], np.inf)
    for c in choices:
        flat_cell = (c[:, 0] * 1_000_003 + c[:, 1]) * 1_000_003 + c[:, 2]
        at = np.minimum(np.searchsorted(keys, flat_cell), keys.size - 1)
        plane = np.where(keys[at] == flat_cell, label[at], -1)
        ok = plane >= 0
        safe = np.where(ok, plane, 0)
        distance = np.abs(np.einsum("ik,ik->i", p, normal[safe]) - offset[safe])
        better = ok & (distance <= tolerance_m) & (distance < best_distance)
        best[better], best_distance[better] = plane[better], distance[better]
    member = np.flatnonzero(best >= 0)
    return member, best[member]


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


class _RayFit:
    """The final fit: mount and planes together, each residual the distance along the beam
    from the point to its plane (the range error, for range noise).

    Why along the beam: with noise along the ray, the point-to-plane distance's variance is
    σ² (n·u)², which depends on the mount (through u) and the plane; its minimum is then not
    at the true mount (a bias of about a millimetre across the scan plane at σ = 10 mm, 180°
    of travel). The range error has variance σ² whatever the mount, so the cost's expected
    minimum is the truth."""

    def __init__(self, model: _Model, planes: _Planes, x0: F64, free: NDArray[np.bool_]
                 ) -> None:
        self.model = model.subset(planes.member)
        self.k = planes.voxel
        self.count = planes.count
        self.x0, self.free = x0.copy(), free.copy()
        self.nx = int(free.sum())
        p = self.model.points(x0)[0]
        self.n0, self.d0, _ = _plane_fit(p, self.k, np.ones(self.k.size), self.count)
        helper = np.where(np.abs(self.n0[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]),
                          np.array([[0.0, 1.0, 0.0]]))
        e1 = np.cross(self.n0, helper)
        self.e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
        self.e2 = np.cross(self.n0, self.e1)

    def start(self) -> F64:
        return np.concatenate([self.x0[self.free], np.zeros(3 * self.count)])

    def mount(self, y: F64) -> F64:
        x = self.x0.copy()
        x[self.free] = y[:self.nx]
        return x

    def evaluate(self, y: F64, jacobian: bool) -> tuple[F64, F64 | None, F64 | None]:
        """Residuals (m), and with ``jacobian`` the mount's columns and each row's three
        columns of its own plane (tilt about e1, e2, offset)."""
        x = self.mount(y)
        theta = y[self.nx:].reshape(-1, 3)
        m = self.n0 + theta[:, :1] * self.e1 + theta[:, 1:2] * self.e2
        norm = np.linalg.norm(m, axis=1, keepdims=True)
        n = m / norm
        d = self.d0 + theta[:, 2]
        k, model = self.k, self.model
        p, dp = model.points(x, jacobian)
        t = model.t0 + np.array([x[2], 0.0, x[3]])
        origin = np.stack([t[0] * model.cb - t[2] * model.sb, np.full_like(model.cb, t[1]),
                           t[0] * model.sb + t[2] * model.cb], 1)
        u = (p - origin) / model.r[:, None]  # the beam's direction
        nk = n[k]
        e = np.einsum("ik,ik->i", nk, p) - d[k]
        c = np.einsum("ik,ik->i", nk, u)
        # Grazing beams (beyond ~78°) are kept but not amplified without bound.
        graze = np.abs(c) < _MIN_COS
        c = np.where(graze, np.copysign(_MIN_COS, c), c)
        live = np.where(graze, 0.0, 1.0)
        res = e / c
        if dp is None:
            return res, None, None
        jx = np.empty((res.size, self.nx))
        for column, j in enumerate(np.flatnonzero(self.free)):
            de = np.einsum("ik,ik->i", nk, dp[:, :, j])
            # d u / d(rotation) = d p / d(rotation) / r; the offsets do not turn the beam.
            dc = de / model.r if j < 2 else 0.0
            jx[:, column] = de / c - e * live * dc / c**2
        jp = np.empty((res.size, 3))
        for a, axis in enumerate((self.e1, self.e2)):
            dn = ((axis - n * np.einsum("ik,ik->i", n, axis)[:, None]) / norm)[k]
            jp[:, a] = (np.einsum("ik,ik->i", dn, p) / c
                        - e * live * np.einsum("ik,ik->i", dn, u) / c**2)
        jp[:, 2] = -1.0 / c
        return res, jx, jp

    def projected(self, jx: F64, jp: F64) -> F64:
        """The mount's Jacobian with each plane's own freedom projected out."""
        k, count = self.k, self.count
        gram = np.empty((count, 3, 3))
        cross = np.empty((count, 3, self.nx))
        for i in range(3):
            for j in range(3):
                gram[:, i, j] = np.bincount(k, jp[:, i] * jp[:, j], count)
            for j in range(self.nx):
                cross[:, i, j] = np.bincount(k, jp[:, i] * jx[:, j], count)
        coef = np.linalg.solve(gram + np.eye(3) * 1e-12, cross)
        return np.asarray(jx - np.einsum("ib,ibj->ij", jp, coef[k]), dtype=np.float64)


#: Beams meeting a plane more obliquely than this cosine (78°) count as at this cosine.
_MIN_COS = 0.2


def _solve_rays(model: _Model, planes: _Planes, x0: F64, free: NDArray[np.bool_],
                iterations: int = 12) -> tuple[F64, _RayFit, F64]:
    """The along-beam fit from ``x0`` (Levenberg–Marquardt on the normal equations, each
    plane's three unknowns eliminated per plane: a 4 × 4 system whatever the number of
    points and planes); the mount within :data:`BOUNDS`. Returns the mount, the fit and its
    parameter vector (for the covariance)."""
    fit = _RayFit(model, planes, x0, free)
    y = fit.start()
    nx, k, count = fit.nx, fit.k, fit.count
    res, jx, jp = fit.evaluate(y, True)
    cost = float(res @ res)
    damping = 1e-3
    for _ in range(iterations):
        assert jx is not None and jp is not None
        a = jx.T @ jx
        gx = jx.T @ res
        b = np.empty((count, nx, 3))
        d = np.empty((count, 3, 3))
        for i in range(3):
            for j in range(nx):
                b[:, j, i] = np.bincount(k, jx[:, j] * jp[:, i], count)
            for j in range(3):
                d[:, i, j] = np.bincount(k, jp[:, i] * jp[:, j], count)
        gp = np.stack([np.bincount(k, jp[:, i] * res, count) for i in range(3)], 1)
        while True:
            da = a + damping * np.diag(np.diag(a))
            dd = d + damping * d * np.eye(3) + np.eye(3) * 1e-15
            dinv = np.linalg.inv(dd)
            bd = np.einsum("kji,kil->kjl", b, dinv)  # B D⁻¹ (K, P, 3)
            schur = da - np.einsum("kjl,kml->jm", bd, b)
            rhs = gx - np.einsum("kjl,kl->j", bd, gp)
            step_x = -np.linalg.solve(schur + np.eye(nx) * 1e-30, rhs) if nx else np.zeros(0)
            step_p = -np.einsum("kil,kl->ki", dinv, gp + np.einsum("kjl,j->kl", b, step_x))
            trial = y + np.concatenate([step_x, step_p.ravel()])
            trial[:nx] = np.clip(trial[:nx], -BOUNDS[free], BOUNDS[free])
            trial_res = fit.evaluate(trial, False)[0]
            trial_cost = float(trial_res @ trial_res)
            if trial_cost <= cost or damping > 1e6:
                break
            damping *= 10.0
        if trial_cost > cost:
            break
        converged = cost - trial_cost <= 1e-10 * cost
        y, cost = trial, trial_cost
        damping = max(damping / 10.0, 1e-7)
        res, jx, jp = fit.evaluate(y, True)
        if converged:
            break
    return fit.mount(y), fit, y


def fit_mount(samples: ScanSamples, rig: Rig, coarse_points: int = 60_000) -> MountFit:
    """Fit the mount (tilt, α zero, offsets perpendicular to the axis) to one scan.

    The coarse levels (plane association) use at most ``coarse_points`` of the samples; the
    final fit uses them all. Parameters the scan does not constrain (1σ above
    :data:`MAX_SIGMA`) keep their nominal value and are reported unobservable with the
    reason; the rest are refitted without them.
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
    coarse = model
    if samples.range_m.size > coarse_points:
        coarse = model.subset(np.sort(np.random.default_rng(1).choice(
            samples.range_m.size, coarse_points, replace=False)))
    x = np.zeros(4)
    free = np.ones(4, bool)
    planes = None
    before = None
    # Twice: planes chosen under the nominal mount can join the wrong pieces and hold the fit
    # in a false minimum; chosen again under the first fit, they let it go (a 360° seed moved
    # from 14 mm to 0.4 mm off).
    for size_m, angle_deg, tolerance_m in (*LEVELS, *LEVELS[1:]):
        planes = _voxel_planes(coarse.points(x)[0], size_m, angle_deg, tolerance_m)
        if planes.count < 1:
            continue
        if before is None:
            before = _rms(coarse, planes, np.zeros(4))
        if planes.directions < 3:
            # Too few ways of facing to hold the fit: solved, it runs off to the bounds
            # (a 360° seed: 2 planes, 11° of tilt); the next, finer level may see more.
            continue
        x = _solve(coarse, planes, x, free, scale_m=tolerance_m / 3)
    if planes is None or planes.count < 1:
        raise StageError("calibrate: no plane found in the scan; "
                         "self-calibration needs flat surfaces (walls, floor, ceiling)")
    # Final: planes over all samples at the coarse solution, every point alike (the
    # normal-aware weights steer the coarse levels; weighting a few points up inflates the
    # estimate's variance and hides it from s²(JᵀJ)⁻¹), distances along the beam.
    for _ in range(5):
        planes = _uniform(_voxel_planes(model.points(x)[0], *LEVELS[-1]))
        if planes.count < 1:
            raise StageError("calibrate: no plane found in the scan; self-calibration "
                             "needs flat surfaces (walls, floor, ceiling)")
        previous = x
        x, ray_fit, y = _solve_rays(model, planes, x, free)
        # Chosen again at the new mount, the planes may take in points the old one left
        # out: repeat until the mount stays (0.1 mm, 0.002°).
        if np.all(np.abs(x - previous) <= np.array([3e-5, 3e-5, 1e-4, 1e-4])):
            break
    sigma = _ray_sigmas(ray_fit, y)
    at_bound = np.abs(x) >= BOUNDS * 0.999
    unobservable = np.array([s is None or s > MAX_SIGMA[n] for n, s in zip(PARAMETERS, sigma,
                                                                              strict=True)])
    unobservable |= at_bound
    warnings: list[str] = []
    if unobservable.any():
        free = ~unobservable
        x[unobservable] = 0.0
        if free.any():
            x, ray_fit, y = _solve_rays(model, planes, x, free)
            kept = _ray_sigmas(ray_fit, y)
            it = iter(kept)
            sigma = [next(it) if free[i] else sigma[i] for i in range(4)]
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


def _uniform(planes: _Planes) -> _Planes:
    """The same planes, every point weighing alike."""
    return _Planes(planes.member, planes.voxel, np.ones(planes.member.size), planes.count,
                   planes.directions)


_UNITS = np.array([math.degrees(1), math.degrees(1), 1.0, 1.0])


def _ray_sigmas(fit: _RayFit, y: F64) -> list[float | None]:
    """1σ of each free parameter (reported unit), the largest of three estimates:

    - ``s² (JᵀJ)⁻¹``, with the planes' own freedom projected out;
    - the sandwich ``A⁻¹ (Σ gᵢgᵢᵀ) A⁻¹`` over points, which holds when the residuals' spread
      differs from place to place;
    - the jackknife over planes (each plane left out in turn, to first order): when the
      mount rests on a few planes, or one plane pulls it (a wall that is not quite flat, a
      piece of another surface joined to it), the estimate moves with that plane and the
      jackknife says so where the other two, which treat points as independent, do not.

    None where the information matrix is (near) singular in that parameter."""
    res, jx, jp = fit.evaluate(y, True)
    assert jx is not None and jp is not None
    jac = fit.projected(jx, jp)
    nx, k, count = fit.nx, fit.k, fit.count
    dof = max(res.size - nx - 3 * count, 1)
    info = jac.T @ jac
    scale = np.sqrt(np.maximum(np.diag(info), 1e-300))
    values, vectors = np.linalg.eigh(info / np.outer(scale, scale))
    if values.max() <= 0:
        return [None] * nx
    floor = 1e-9 * float(values.max())
    inv = (vectors / np.maximum(values, floor)) @ vectors.T / np.outer(scale, scale)
    classical = np.diag(inv) * float(res @ res) / dof
    g = jac * res[:, None]
    sandwich = np.diag(inv @ (g.T @ g) @ inv) * res.size / dof
    jackknife = np.zeros(nx)
    if count >= 3:
        grad = np.stack([np.bincount(k, g[:, j], count) for j in range(nx)], 1)  # (K, P)
        deltas = []
        for plane in range(count):
            rows = jac[k == plane]
            without = info - rows.T @ rows
            try:
                deltas.append(np.linalg.solve(without + np.eye(nx) * floor * scale**2,
                                              grad[plane]))
            except np.linalg.LinAlgError:
                deltas.append(np.full(nx, np.inf))
        spread = np.asarray(deltas) - np.mean(deltas, axis=0)
        jackknife = (count - 1) / count * np.sum(spread**2, axis=0)
    variance = np.maximum(np.maximum(classical, sandwich), jackknife)
    units = _UNITS[fit.free]
    out: list[float | None] = []
    for i in range(nx):
        weak = bool(np.any((values < 1e-6 * values.max()) & (np.abs(vectors[i]) > 0.1)))
        out.append(None if weak or not np.isfinite(variance[i]) or info[i, i] <= 0 else
                   float(math.sqrt(max(variance[i], 0.0)) * units[i]))
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
