"""The device ↔ host clock model, the motor controller's clock, and grids with repeated angles."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from scanpipe.clock import DEVICE_TIME_WRAP_MS, fit_clock, unwrap_device_ms
from scanpipe.grid import grid_from_indices
from scanpipe.motion import motor_clock, motor_times_ns
from scanpipe.normals import grid_normals

T0 = 1_790_000_000_000_000_000


def _pairs(rate: float, n: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Device times every 20 ms and host receipts with one-sided, bursty latency."""
    rng = np.random.default_rng(seed)
    device = 5_000_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    latency = rng.exponential(2e6, n) + 1e6  # ≥ 1 ms, mostly a few ms
    spikes = rng.random(n) < 0.05  # batching: now and then a receipt is very late
    latency[spikes] += rng.uniform(0, 300e6, np.count_nonzero(spikes))
    host = T0 + np.rint(device * rate + latency).astype(np.int64)
    return device, host


@pytest.mark.parametrize("rate", [1.0, 1.00005, 0.1, 0.05])
def test_fit_recovers_rate_and_envelope(rate: float) -> None:
    device, host = _pairs(rate)
    model = fit_clock(device, host)
    assert model.rate == pytest.approx(rate, rel=2e-4)
    # The envelope sits at the smallest latency (1 ms here): the mapped times are never
    # later than the receipts and within a few ms of the true event times.
    mapped = model.to_host_ns(device)
    true = T0 + np.rint(device * rate).astype(np.int64)
    assert np.all(mapped <= host)
    assert np.median(np.abs(mapped - true)) < 3e6
    assert (abs(rate - 1) > 1e-3) == bool(model.problems())


def test_fit_follows_the_least_late_pairs_when_the_backlog_drifts() -> None:
    # A loaded host: the backlog grows over the first two thirds of the recording and drains,
    # and only now and then is a receipt as prompt as it can be. A least-squares line through
    # most pairs tilts with the drift; the line under the least-late pairs does not.
    rng = np.random.default_rng(3)
    n, rate = 1500, 0.1
    device = np.arange(n, dtype=np.int64) * 20_000_000
    ramp = np.interp(np.arange(n), [0, n * 2 // 3, n], [0.0, 40e6, 5e6])
    latency = 1e6 + rng.exponential(3e6, n) + ramp * rng.uniform(0.5, 1.0, n)
    prompt = rng.random(n) < 0.05
    latency[prompt] = 1e6 + rng.exponential(0.2e6, np.count_nonzero(prompt))
    host = T0 + np.rint(device * rate + latency).astype(np.int64)
    model = fit_clock(device, host)
    assert model.rate == pytest.approx(rate, rel=2e-4)
    true = T0 + 1_000_000 + np.rint(device * rate).astype(np.int64)
    assert np.abs(model.to_host_ns(device) - true).max() < 1e6
    assert model.problems() == [] or all("prompt" not in p for p in model.problems())
    # A host that fell behind for a stretch (no prompt receipt in it): the times there are
    # a guess, and the fit says so instead of passing them off as measured.
    behind = latency.copy()
    behind[n // 4: n // 2] += 60e6
    lagging = fit_clock(device, T0 + np.rint(device * rate + behind).astype(np.int64))
    assert lagging.floor_drift_s > 0.05
    assert any("no receipt was prompt" in p for p in lagging.problems())
    assert lagging.report()["floor_drift_ms"] > 50


def test_fit_with_given_offset_keeps_rate_one() -> None:
    device, host = _pairs(1.0)
    model = fit_clock(device, host, offset_ns=T0)
    assert model.rate == 1.0 and model.offset_ns == T0
    assert model.median_latency_s > 0.001


def test_fit_degenerate_inputs() -> None:
    assert fit_clock(np.zeros(0, np.int64), np.zeros(0, np.int64)).rate == 1.0
    single = fit_clock(np.array([7], np.int64), np.array([T0], np.int64))
    assert single.rate == 1.0 and single.to_host_ns(np.array([7]))[0] == T0


def test_latency_spread_is_a_problem() -> None:
    device = np.arange(100, dtype=np.int64) * 200_000_000
    host = T0 + device + np.where(np.arange(100) % 7 == 0, 3_000_000_000, 0)
    assert any("latency" in p for p in fit_clock(device, host).problems())


@pytest.mark.parametrize("device_per_host", [1.0, 10.0])
def test_unwrap_across_a_pause_longer_than_a_wrap(device_per_host: float) -> None:
    # 5 Hz stamps, then a pause of 100 s of device time, then more stamps.
    true_ms = np.concatenate([np.arange(50) * 200, 100_000 + 50 * 200 + np.arange(50) * 200])
    host_ns = T0 + np.rint(true_ms / device_per_host * 1e6).astype(np.int64)
    raw = (true_ms + 60_000) % DEVICE_TIME_WRAP_MS
    unwrapped = unwrap_device_ms(raw, host_ns)
    assert (unwrapped - unwrapped[0]).tolist() == (true_ms - true_ms[0]).tolist()


def _motor_table(jitter: bool, device: bool = True) -> pa.Table:
    rng = np.random.default_rng(1)
    n = 400
    device_us = 7_000_000 + np.arange(n, dtype=np.int64) * 20_000  # every 20 ms device time
    log = T0 + device_us * 100  # rate 0.1 (×10 speed-up) → every 2 ms host time
    if jitter:
        # Read in order over one serial link: a late state delays the ones behind it.
        log = np.maximum.accumulate(log + np.rint(rng.exponential(1e6, n)).astype(np.int64))
    columns = {"log_time_ns": log, "step_count": np.arange(n, dtype=np.int64),
               "target_step_count": np.full(n, n, np.int64), "moving": np.ones(n, bool)}
    if device:
        columns["device_time_us"] = device_us
    return pa.table(columns)


def test_motor_states_are_placed_by_the_controller_clock() -> None:
    table = _motor_table(jitter=True)
    clock = motor_clock(table)
    assert clock is not None and clock.rate == pytest.approx(0.1, rel=1e-3)
    times = motor_times_ns(table)
    ideal = _motor_table(jitter=False).column("log_time_ns").to_numpy()
    raw_error = np.abs(table.column("log_time_ns").to_numpy() - ideal)
    assert np.median(np.abs(times - ideal)) < 0.2 * np.median(raw_error)
    # Without device times (or with a reset controller) the receive times stand.
    no_device = _motor_table(jitter=True, device=False)
    assert motor_clock(no_device) is None
    assert np.array_equal(motor_times_ns(no_device), no_device.column("log_time_ns").to_numpy())
    reset = table.set_column(4, "device_time_us", pa.array(
        np.concatenate([np.arange(200), np.arange(200)]).astype(np.int64) * 20_000))
    assert motor_clock(reset) is None


def test_repeated_platform_angles_do_not_divide_by_zero() -> None:
    # A step scan assembled as continuous: several profiles at each platform position.
    profiles, samples = 12, 90
    beta = np.repeat(np.arange(4) * 5.0, 3)
    alpha = np.arange(samples) * 4.0
    p, s = np.divmod(np.arange(profiles * samples), samples)
    grid = grid_from_indices(p, s, np.tile(alpha, profiles), np.repeat(beta, samples))
    assert grid is not None
    assert grid.beta_step_deg == pytest.approx(15.0 / 11)
    a, b = np.radians(alpha)[None, :], np.radians(beta)[:, None]
    r = 3.0
    xyz = np.stack([r * np.sin(a) * np.cos(b), r * np.cos(a) + 0 * b,
                    r * np.sin(a) * np.sin(b)], axis=-1).astype(np.float32)
    normals = grid_normals(xyz, grid)
    assert normals.shape == xyz.shape
    # No platform motion at all: no step, still no error.
    still = grid_from_indices(p, s, np.tile(alpha, profiles), np.zeros(profiles * samples))
    assert still is not None and np.isnan(still.beta_step_deg)
    assert grid_normals(xyz, still).shape == xyz.shape
