"""The simulated LDRobot head: packets the decoder reads back to the truth, within the noise."""

from __future__ import annotations

import numpy as np
import pytest

from scanpipe.errors import SimulationError
from scanpipe.protocol import ldrobot as ld
from scanpipe.rig import default_rig
from scanpipe.sim.ldrobot_device import (
    LDROBOT_MODELS,
    LdrobotHead,
    cast_beams,
    ldrobot_model,
)
from scanpipe.sim.motion import PlatformState
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import MeasurementModel


def head(model: str = "ld06", noise: float = 0.01, dropout: float = 0.002,
         seed: int = 1) -> LdrobotHead:
    rig = default_rig()
    m = ldrobot_model(model)
    scanner = rig.scanner.model_copy(update={"min_range_m": m.min_range_m,
                                             "max_range_m": m.max_range_m})
    return LdrobotHead(m, resolve_scene("room"), scanner,
                              PlatformState(rig.motor.pulse_step_deg),
                              MeasurementModel(noise_sigma_m=noise, dropout_rate=dropout,
                                               seed=seed))


def test_packets_do_not_depend_on_batching() -> None:
    h = head()
    whole = h.packets(0, 40).data
    parts = h.packets(0, 13).data + h.packets(13, 1).data + h.packets(14, 26).data
    assert whole == parts
    assert head(seed=2).packets(0, 40).data != whole


def test_decoded_revolutions_match_the_scene_within_the_noise() -> None:
    h = head()
    sent = h.packets(0, 1200)  # 3.2 s of an LD06
    profiles, counters = ld.decode_revolutions(sent.data)
    assert counters.frames_decoded == 1200 and counters.resyncs == 0
    sigma = ldrobot_model("ld06").noise_sigma_m
    errors = []
    for p in profiles[1:-1]:
        grid = np.arange(len(p.ranges_m)) * p.step_deg
        # The platform stands still: the truth at the grid angles is a cast at β = 0.
        truth, _ = cast_beams(h.scene, h.scanner, grid, np.zeros(grid.size))
        both = np.isfinite(truth) & np.isfinite(p.ranges_m)
        errors.append(p.ranges_m[both] - truth[both])
    err = np.concatenate(errors)
    assert err.size > 5000
    assert np.sqrt(np.mean(err ** 2)) <= 1.1 * sigma


def test_the_head_wobbles_and_reports_it() -> None:
    h = head()
    sent = h.packets(0, 4000)
    packets, _ = ld.locate_packets(sent.data)
    speeds = packets.speed_dps.astype(float)
    assert 3570 < speeds.min() < speeds.max() < 3630
    per_turn = np.diff(np.flatnonzero(np.diff(np.floor(sent.beam_deg.ravel() / 360)) > 0))
    assert len(set(per_turn.tolist())) > 1  # a turn holds a varying number of samples
    # Reported angles are the truth within the encoder jitter and the 0.01° quantum.
    start = packets.start_cdeg / 100.0
    miss = (start - sent.beam_deg[:, 0] + 180) % 360 - 180
    assert np.abs(miss).max() < 0.1


def test_device_clock_wraps_at_30000_ms() -> None:
    h = head()
    n = int(20.0 / h.packet_s)  # 20 s: the clock (starting at 12 345 ms) wraps once
    packets, _ = ld.locate_packets(h.packets(0, n).data)
    stamps = packets.timestamp_ms.astype(int)
    assert stamps.max() < 30_000
    assert np.count_nonzero(np.diff(stamps) < 0) == 1


def test_dropouts_are_zero_distance_with_low_intensity() -> None:
    h = head(dropout=0.2)
    packets, _ = ld.locate_packets(h.packets(0, 500).data)
    zero = packets.distance_mm == 0
    assert 0.15 < zero.mean() < 0.5
    assert packets.intensity[zero].max() < 16 <= packets.intensity[~zero].min()


def test_stl27l_streams_21600_samples_per_second() -> None:
    h = head("stl27l")
    assert h.packet_s == pytest.approx(12 / 21_600)
    profiles, _ = ld.decode_revolutions(h.packets(0, 2000).data)
    assert 2140 <= len(profiles[1].ranges_m) <= 2180
    assert LDROBOT_MODELS["stl27l"].baud == 921_600


def test_unknown_model() -> None:
    with pytest.raises(SimulationError, match="allowed: ld06, ld19, stl27l"):
        ldrobot_model("ld07")


def test_emulator_streams_on_a_pty_without_being_asked() -> None:
    import time

    import serial

    from scanpipe.sim.clock import SimClock
    from scanpipe.sim.ldrobot_device import LdrobotEmulator

    emulator = LdrobotEmulator(head(), SimClock(speedup=5.0))
    emulator.start()
    try:
        port = serial.Serial(emulator.port_path, 230_400, timeout=0.05)
        data = bytearray()
        deadline = time.monotonic() + 0.6
        while time.monotonic() < deadline:
            data += port.read(1 << 16)
        port.close()
    finally:
        emulator.stop()
    assert emulator.port_path and emulator._master == -1
    profiles, counters = ld.decode_revolutions(bytes(data))
    # 0.6 s at 5× is 3 s of device time: ~30 turns of 450 beams (the first one partial).
    assert 20 <= len(profiles) <= 40 and counters.frames_decoded > 800
    assert counters.checksum_failures == 0
    assert [p.frame for p in profiles] == list(range(profiles[0].frame,
                                                     profiles[0].frame + len(profiles)))


def test_limit_checks_of_the_models() -> None:
    from types import SimpleNamespace

    from scanpipe.device_limits import LDROBOT_LIMITS, ldrobot_limit_checks

    def failing(model: str, **kw: float) -> list[str]:
        settings = dict(scan_hz=10.0, beam_step_deg=0.8, start_angle_deg=0.0,
                        end_angle_deg=360.0, min_range_m=0.02, max_range_m=12.0)
        settings.update(kw)
        checks = ldrobot_limit_checks(SimpleNamespace(**settings), model)  # type: ignore[arg-type]
        return [c.name for c in checks if not c.ok]

    assert failing("ld06") == [] and failing("ld19") == []
    assert failing("ld06", scan_hz=20.0, beam_step_deg=1.6) == ["scan_hz"]
    assert failing("ld06", beam_step_deg=0.25) == ["beam_step_deg"]
    assert failing("ld06", max_range_m=25.0) == ["max_range_m"]
    assert failing("stl27l", beam_step_deg=360 / 2160, min_range_m=0.03, max_range_m=25.0) == []
    assert LDROBOT_LIMITS["stl27l"].beam_step_deg(10.0) == pytest.approx(1 / 6)
