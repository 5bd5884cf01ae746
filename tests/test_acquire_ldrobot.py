"""The recorder's scanner client with the LDRobot driver, against the virtual device on a real
pseudo-terminal."""

from __future__ import annotations

import threading
import time

import pytest

from scanpipe.acquire.scanner_client import ScannerClient
from scanpipe.errors import DeviceError
from scanpipe.protocol import ldrobot as ld
from scanpipe.rig import ScannerConfig, default_rig, scanner_for_model
from scanpipe.sim.clock import SimClock
from scanpipe.sim.ldrobot_device import LdrobotEmulator, LdrobotHead, ldrobot_model
from scanpipe.sim.motion import PlatformState
from scanpipe.sim.room import resolve_scene
from scanpipe.sim.scanner import MeasurementModel


def ld06(url: str, **update: object) -> ScannerConfig:
    return scanner_for_model("ld06").model_copy(update={"serial_url": url, **update})


class ListSink:
    def __init__(self) -> None:
        self.chunks: list[tuple[str, bytes, int, int]] = []
        self.lock = threading.Lock()

    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        with self.lock:
            self.chunks.append((link, data, direction, log_time_ns))


def emulator(speedup: float = 5.0) -> LdrobotEmulator:
    rig = default_rig()
    m = ldrobot_model("ld06")
    scanner = rig.scanner.model_copy(update={"min_range_m": m.min_range_m,
                                             "max_range_m": m.max_range_m})
    head = LdrobotHead(m, resolve_scene("room"), scanner,
                       PlatformState(rig.motor.pulse_step_deg), MeasurementModel(seed=4))
    return LdrobotEmulator(head, SimClock(speedup))


def test_client_records_every_byte_and_counts_revolutions() -> None:
    emu = emulator()
    emu.start()
    sink = ListSink()
    lost: list[str] = []
    client = ScannerClient(ld06(emu.port_path), sink, on_disconnect=lost.append)
    try:
        client.connect()
        assert client.wait_for_profiles(time.time_ns(), 5, timeout_s=5.0)
        client.close()
    finally:
        emu.stop()
    assert lost == [] and not client.connected
    data = b"".join(c[1] for c in sink.chunks)
    assert all(c[0] == "scanner" and c[2] == 0 for c in sink.chunks)
    times = [c[3] for c in sink.chunks]
    assert times == sorted(times)
    profiles, counters = ld.decode_revolutions(data)
    assert client.stats.profiles >= 5 and len(profiles) >= client.stats.profiles
    assert client.ident.startswith("LDRobot ld06")
    assert client.stats.rx_bytes == len(data) and counters.checksum_failures == 0


def test_a_device_that_goes_silent_is_reported_once() -> None:
    emu = emulator()
    emu.start()
    lost: list[str] = []
    client = ScannerClient(ld06(emu.port_path), ListSink(), on_disconnect=lost.append)
    client.connect()
    client.wait_for_profiles(time.time_ns(), 2, timeout_s=5.0)
    emu.stop()  # unplugged
    deadline = time.monotonic() + 5.0
    while client.connected and time.monotonic() < deadline:
        time.sleep(0.02)
    client.close()
    assert len(lost) == 1, lost


def test_refusals_name_the_port_or_the_limit() -> None:
    client = ScannerClient(ld06("/dev/does-not-exist"), ListSink())
    with pytest.raises(DeviceError, match="scanner at /dev/does-not-exist: cannot open"):
        client.connect()
    fast = ld06("/dev/null", scan_hz=20.0, beam_step_deg=1.6)
    with pytest.raises(DeviceError, match=r"scanner.scan_hz: scan_hz = 20 is outside the LD06"):
        ScannerClient(fast, ListSink()).connect()
