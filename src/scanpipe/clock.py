"""Device clock ↔ host clock: a fitted linear model, checked against what a clock can do.

A scanner stamps its sectors on its own clock; the recorder stamps every chunk it receives on
the host clock. The two are related by ``host_ns = offset_ns + rate · device_ns`` plus the
receive latency, which is never negative. ``rate`` is 1 up to the crystals' drift (tens of
ppm) for real hardware; a simulated device whose clock runs at a speed-up shows that speed-up
(the virtual rig's emulators at ``--speedup 10`` give a rate of 0.1). Assuming a rate of 1
there puts every profile at the wrong host time, which is why the rate is fitted, not assumed.

The fit: least squares over all pairs, then again over the pairs closest to the line's lower
side (latency spikes from batching only ever delay); the rate is then the slope of the lower
envelope itself (the convex hull's edge under the middle of the recording: the least-late
pairs, which a backlog that drifts over the recording does not tilt), and the offset is the
lower envelope: the smallest latency is zero. :func:`unwrap_device_ms` uses the same idea to
count the wraps of 16-bit millisecond clocks across pauses when the device clock does not run
at host speed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.protocol.profile import DEVICE_TIME_WRAP_MS

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]

#: A real device's clock drifts by far less than this against the host's (crystals: ~50 ppm).
DRIFT_WARN = 1e-3
#: A latency spread beyond this says the device times and the receive times disagree.
LATENCY_SPREAD_WARN_S = 1.0
#: The least latency of a stretch of the recording above the envelope beyond which the fit is
#: flagged: the host fell behind the device for that stretch (no prompt receipt in it), so the
#: times there may be off by up to that much. Each eighth of the pairs is a stretch.
FLOOR_DRIFT_WARN_S = 0.025
_STRETCHES = 8
#: Pairs used for the second, lower-side fit: the best-fitting share of them.
_LOWER_SHARE = 0.75


@dataclass(frozen=True)
class ClockModel:
    """``host_ns = offset_ns + rate · device_ns`` (receive latency excluded), and its check."""

    offset_ns: int
    rate: float
    #: Pairs the model was fitted to (0: given, not fitted).
    pairs: int = 0
    #: Receive latency over the pairs: median and 99th percentile above the envelope, in s.
    median_latency_s: float = 0.0
    p99_latency_s: float = 0.0
    #: The largest least latency of an eighth of the pairs (0 when fewer than 16 pairs): where
    #: no receipt was prompt, the envelope is a guess.
    floor_drift_s: float = 0.0
    #: What the device times are, for messages.
    name: str = "the device clock"

    def to_host_ns(self, device_ns: I64) -> I64:
        """Host times of device times."""
        scaled = np.rint(np.asarray(device_ns, np.float64) * self.rate).astype(np.int64)
        return np.asarray(scaled + self.offset_ns, np.int64)

    def problems(self) -> list[str]:
        """What looks wrong with this clock relation, one sentence each (empty when fine)."""
        found: list[str] = []
        if abs(self.rate - 1.0) > DRIFT_WARN:
            found.append(f"{self.name} runs {1.0 / self.rate:.4g}× as fast as the host "
                         f"clock (a simulated speed-up, or a wrong clock or scan rate); its "
                         f"times are scaled by the fitted rate {self.rate:.6g}")
        if self.floor_drift_s > FLOOR_DRIFT_WARN_S:
            found.append(f"no receipt was prompt for a stretch of the recording (its least "
                         f"latency {self.floor_drift_s * 1e3:.0f} ms: the host fell behind "
                         f"{self.name}); times there may be off by up to that much")
        if self.p99_latency_s > LATENCY_SPREAD_WARN_S:
            found.append(f"receive latency varies by {self.p99_latency_s:.2f} s (99th "
                         f"percentile): device and receive times disagree")
        return found

    def report(self) -> dict[str, Any]:
        """The model as JSON-ready values for a stage report."""
        return {"offset_ns": self.offset_ns, "rate": self.rate, "pairs": self.pairs,
                "median_latency_ms": self.median_latency_s * 1e3,
                "p99_latency_ms": self.p99_latency_s * 1e3,
                "floor_drift_ms": self.floor_drift_s * 1e3, "problems": self.problems()}


def _least_squares(x: F64, y: F64) -> tuple[float, float]:
    """Slope and intercept of ``y ≈ a·x + b``; slope 1 when ``x`` does not vary."""
    x_mean, y_mean = float(x.mean()), float(y.mean())
    dx = x - x_mean
    denominator = float(np.dot(dx, dx))
    slope = float(np.dot(dx, y - y_mean)) / denominator if denominator > 0 else 1.0
    if not np.isfinite(slope) or slope <= 0:
        slope = 1.0
    return slope, y_mean - slope * x_mean


def _envelope_slope(x: F64, y: F64, guess: float, bins: int = 512) -> float:
    """The slope of the lower envelope of ``y`` over ``x`` (its convex hull's edge under the
    mean ``x``), ``guess`` when it has none.

    Receipts are only ever late, by a latency that a loaded host makes vary over the
    recording (a backlog grows, then drains); a least-squares line through the lower share of
    the pairs tilts with that drift (0.5–0.8 % at a 10× speed-up on a loaded machine: a time
    error of tens of ms at the ends of a scan), while the line under the least-late pairs does
    not. The hull runs over the least-late pair of each of ``bins`` stretches of ``x`` (relative
    to ``guess``), so its cost does not grow with the pairs."""
    low, high = float(x.min()), float(x.max())
    if not high > low:
        return guess
    cell = np.minimum(((x - low) / (high - low) * bins).astype(np.int64), bins - 1)
    order = np.lexsort((y - guess * x, cell))
    first = np.concatenate([[True], cell[order][1:] != cell[order][:-1]])
    pick = order[first]  # by cell, so by x
    hx, hy = x[pick], y[pick]
    hull: list[int] = []
    for i in range(hx.size):  # Andrew's monotone chain, lower part (≤ ``bins`` points)
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (hx[b] - hx[a]) * (hy[i] - hy[a]) - (hy[b] - hy[a]) * (hx[i] - hx[a]) > 0:
                break
            hull.pop()
        hull.append(i)
    if len(hull) < 2:
        return guess
    vertices = np.asarray(hull)
    k = int(np.clip(np.searchsorted(hx[vertices], float(x.mean())), 1, vertices.size - 1))
    a, b = vertices[k - 1], vertices[k]
    slope = float((hy[b] - hy[a]) / (hx[b] - hx[a]))
    return slope if np.isfinite(slope) and slope > 0 else guess


def _floor_drift_s(x: F64, above: F64) -> float:
    """The largest least latency (``above`` the envelope) of each eighth of the pairs in
    device-time order; 0 for fewer than 16 pairs."""
    if above.size < 2 * _STRETCHES:
        return 0.0
    order = np.argsort(x, kind="stable")
    return float(max(float(part.min()) for part in np.array_split(above[order], _STRETCHES)))


def fit_clock(device_ns: I64, host_ns: I64, rate: float | None = None,
              offset_ns: int | None = None) -> ClockModel:
    """Fit ``host = offset + rate · device`` to pairs; ``rate``/``offset_ns`` fix either part.

    An offset given without a rate means a rate of 1 (``host = device + offset``).

    The offset is the lower envelope (the smallest latency is taken as zero); latencies are
    reported above it.
    """
    device = np.asarray(device_ns, np.int64)
    host = np.asarray(host_ns, np.int64)
    if device.size == 0:
        return ClockModel(offset_ns=offset_ns or 0, rate=rate or 1.0)
    # Relative to the first pair, in seconds: float64 keeps sub-ns resolution over days.
    x = (device - device[0]).astype(np.float64) / 1e9
    y = (host - host[0]).astype(np.float64) / 1e9
    if rate is None and offset_ns is not None:
        rate = 1.0  # an offset given alone keeps its meaning: host = device + offset
    if rate is None:
        rate, intercept = _least_squares(x, y)
        residual = y - (rate * x + intercept)
        if device.size >= 8:
            lower = residual <= np.quantile(residual, _LOWER_SHARE)
            rate, _ = _least_squares(x[lower], y[lower])
            rate = _envelope_slope(x, y, rate)
    latency = y - rate * x  # up to a constant
    floor = float(latency.min())
    if offset_ns is None:
        # host[0] + floor·1e9 is the envelope's host time at device[0].
        offset_ns = int(host[0]) + round(floor * 1e9) - round(float(device[0]) * rate)
        above = latency - floor
    else:
        above = (host - offset_ns).astype(np.float64) / 1e9 - rate * device.astype(
            np.float64) / 1e9
    return ClockModel(offset_ns=int(offset_ns), rate=float(rate), pairs=int(device.size),
                      median_latency_s=float(np.median(above)),
                      p99_latency_s=float(np.quantile(above, 0.99)),
                      floor_drift_s=_floor_drift_s(x, above))


def unwrap_device_ticks(device_ticks: NDArray[np.integer], host_ns: I64,
                        wrap_ticks: int = DEVICE_TIME_WRAP_MS, tick_ns: int = 1_000_000) -> I64:
    """Unwrap a device clock that wraps at ``wrap_ticks`` counts of ``tick_ns`` each (the
    LD-OEM's 16-bit ms, SICK's 32-bit µs), counting wraps from the host receive times.

    Between consecutive stamps the device step is taken modulo the wrap and then corrected by
    the whole number of wrap periods that best matches the host's elapsed time, scaled by the
    device's rate against the host. That rate comes from the consecutive pairs whose host gap
    is far below a wrap (there the step is unambiguous). The result starts at the first raw
    value.
    """
    t = np.asarray(device_ticks, dtype=np.int64)
    wrap = int(wrap_ticks)
    if t.size == 0:
        return t
    step = np.diff(t) % wrap
    host_step = np.diff(np.asarray(host_ns, dtype=np.int64)).astype(np.float64) / tick_ns
    dense = (host_step > 0) & (host_step < wrap / 8) & (
        step < wrap / 2)
    device_per_host = 1.0
    if np.count_nonzero(dense) >= 4 and host_step[dense].sum() > 0:
        device_per_host = float(step[dense].sum() / host_step[dense].sum())
        if not np.isfinite(device_per_host) or device_per_host <= 0:
            device_per_host = 1.0
    expected = host_step * device_per_host
    wraps = np.rint((expected - step) / wrap).astype(np.int64)
    wraps = np.maximum(wraps, 0)  # device time never runs backwards
    steps = np.concatenate([[0], np.cumsum(step + wraps * wrap)])
    return np.asarray(t[0] + steps, dtype=np.int64)


def unwrap_device_ms(device_ms: NDArray[np.integer], host_ns: I64) -> I64:
    """Unwrap 16-bit millisecond device timestamps (:func:`unwrap_device_ticks`)."""
    return unwrap_device_ticks(device_ms, host_ns, DEVICE_TIME_WRAP_MS, 1_000_000)
