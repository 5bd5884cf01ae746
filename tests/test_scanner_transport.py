"""The scanner link beyond the LD-OEM: a serial scanner on a pty, SICK's start-up and refusals."""

from __future__ import annotations

import time

import pytest

from scanpipe.acquire import scanner_client
from scanpipe.acquire.scanner_client import ScannerClient
from scanpipe.errors import DeviceError
from scanpipe.rig import default_rig, scanner_for_model
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import box_room


class Sink:
    """Collects what the client records."""

    def __init__(self) -> None:
        self.chunks: list[tuple[str, bytes, int]] = []

    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        self.chunks.append((link, data, direction))


def _options(scanner_update: dict[str, object] | None = None, model: str | None = None
             ) -> SimOptions:
    rig = default_rig()
    scanner = scanner_for_model(model) if model else rig.scanner
    scanner = scanner.model_copy(update=scanner_update or {})
    return SimOptions(rig=rig.model_copy(update={"scanner": scanner}), cameras=False)


def test_a_serial_scanner_streams_over_a_pty() -> None:
    options = _options({"dialect": "paper", "transport": "serial", "baudrate": 230400})
    with VirtualRig(options, speedup=10.0, scene=box_room()) as virtual:
        scanner = virtual.client_rig().scanner
        assert scanner.serial_url.startswith("/dev/pts/")
        sink = Sink()
        client = ScannerClient(scanner, sink)
        client.connect()
        try:
            assert client.wait_for_profiles(time.time_ns() - 1, 3, timeout_s=5.0)
        finally:
            client.close()
    assert client.stats.profiles >= 3 and all(d == 0 for _, _, d in sink.chunks)


def test_sick_start_and_stop_commands_are_the_devices_own() -> None:
    with VirtualRig(_options(model="lms111"), speedup=2.0, scene=box_room()) as virtual:
        sink = Sink()
        client = ScannerClient(virtual.client_rig().scanner, sink)
        client.connect()
        assert client.wait_for_profiles(time.time_ns() - 1, 2, timeout_s=5.0)
        client.close()
        requests = virtual.scanner.requests
    assert requests == ["sMN SetAccessMode", "sMN mLMPsetscancfg", "sMN Run",
                        "sEN LMDscandata", "sEN LMDscandata"]
    sent = b"".join(d for _, d, direction in sink.chunks if direction == 1)
    assert sent.count(b"sEN LMDscandata \x01") == 1 and sent.count(b"sEN LMDscandata \x00") == 1


def test_sick_cola_a_speaks_ascii_both_ways() -> None:
    """An LMS1xx on its CoLa-A port: the same start-up and stop, as STX … ETX telegrams."""
    options = _options({"dialect": "cola_a", "port": 2111}, model="lms111")
    with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
        sink = Sink()
        client = ScannerClient(virtual.client_rig().scanner, sink)
        client.connect()
        assert client.wait_for_profiles(time.time_ns() - 1, 2, timeout_s=5.0)
        client.close()
        requests = virtual.scanner.requests
    assert requests == ["sMN SetAccessMode", "sMN mLMPsetscancfg", "sMN Run",
                        "sEN LMDscandata", "sEN LMDscandata"]
    sent = b"".join(d for _, d, direction in sink.chunks if direction == 1)
    assert sent == (b"\x02sMN SetAccessMode 3 F4724744\x03"
                    b"\x02sMN mLMPsetscancfg 9C4 1 1388 FFF92230 225510\x03\x02sMN Run\x03"
                    b"\x02sEN LMDscandata 1\x03\x02sEN LMDscandata 0\x03")
    received = b"".join(d for _, d, direction in sink.chunks if direction == 0)
    assert received.startswith(b"\x02sAN SetAccessMode 1\x03")
    assert b"\x02sSN LMDscandata " in received and b"\x02\x02\x02\x02" not in received


def test_cola_a_refusal_names_the_status(monkeypatch: pytest.MonkeyPatch) -> None:
    """A mode the device lacks comes back as ``sAN mLMPsetscancfg 2 …`` in ASCII."""
    monkeypatch.setattr(scanner_client, "limit_problems", lambda scanner: [])
    options = _options({"dialect": "cola_a", "port": 2111}, model="lms111")
    with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
        scanner = virtual.client_rig().scanner.model_copy(update={"scan_hz": 50.0,
                                                                  "beam_step_deg": 0.25})
        client = ScannerClient(scanner, Sink())
        with pytest.raises(DeviceError, match=r"status 2: resolution not possible"):
            client.connect()
        assert not client.connected


def test_settings_outside_the_model_are_refused_before_connecting() -> None:
    with VirtualRig(_options(model="lms111"), speedup=2.0, scene=box_room()) as virtual:
        scanner = virtual.client_rig().scanner.model_copy(update={"scan_hz": 50.0,
                                                                  "beam_step_deg": 0.25})
        # 50 Hz is one of its rates, 0.25° is not a step it offers at 50 Hz: the step is named
        with pytest.raises(DeviceError, match=r"beam_step_deg = 0.25 is outside the LMS111 "
                                              r"limit \(at 50 Hz: one of 0.5°\)"):
            ScannerClient(scanner, Sink()).connect()
        assert virtual.scanner.requests == []


def test_the_emulated_scanner_refuses_a_mode_it_lacks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(scanner_client, "limit_problems", lambda scanner: [])
    with VirtualRig(_options(model="lms111"), speedup=2.0, scene=box_room()) as virtual:
        scanner = virtual.client_rig().scanner.model_copy(update={"scan_hz": 50.0,
                                                                  "beam_step_deg": 0.25})
        client = ScannerClient(scanner, Sink())
        with pytest.raises(DeviceError, match=r"status 2: resolution not possible"):
            client.connect()
        assert not client.connected


class _NoSink:
    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        pass


def test_a_late_profile_is_not_fresh_at_a_stopped_position() -> None:
    """A stop at 850 ms (host), scans every 100 ms of 75 ms sectors: scans received on time
    place the head's turns; a scan that began before the stop but arrives after it (a lagging
    link) does not count, the next one that began after it does."""
    client = ScannerClient(default_rig().scanner, _NoSink())  # type: ignore[arg-type]
    ms = 1_000_000
    period, sector = 100 * ms, 75 * ms
    for k in range(8):  # on time: received 1 ms after each sector ends (k · 100 + 75 + 1 ms)
        client._profiles_arrived(1, k * period + sector + ms, [k])
    stop = 850 * ms  # the scan under way (counter 8) began at 800 ms
    assert client._fresh_count(stop, 1, period, sector)[0] == 0
    client._profiles_arrived(1, 990 * ms, [8])  # 114 ms late: began before the stop
    assert client._fresh_count(stop, 1, period, sector)[0] == 0
    client._profiles_arrived(1, 1000 * ms, [9])  # began at 900 ms, after the stop
    fresh, hold_ns = client._fresh_count(stop, 1, period, sector)
    # then hold still half a turn plus the 90th-percentile delay past the least-delayed
    # placement (delays 0 × 8, 24 and 114 ms: 24 ms)
    assert fresh == 1 and hold_ns == 1000 * ms + period // 2 + 24 * ms
    # counters wrap at 2¹⁶ without breaking the placement
    client._last_counter = None
    client._profile_times.clear()
    client._profile_counters.clear()
    for i, k in enumerate(range(65534, 65540)):
        client._profiles_arrived(1, i * period + sector + ms, [k & 0xFFFF])
    assert client._profile_counters[-1] == 65539
    assert client._fresh_count(3 * period + 2 * ms, 2, period, sector)[0] == 2  # began 400, 500


def test_without_counters_the_first_profile_after_a_stop_is_not_counted() -> None:
    client = ScannerClient(default_rig().scanner, _NoSink())  # type: ignore[arg-type]
    for t in (10, 20, 30):
        client._profiles_arrived(1, t)
    assert client._fresh_count(15, 1, 10, 5) == (1, 0)  # 20 and 30 arrived after; 20 may be stale
