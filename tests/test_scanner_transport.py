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
        with pytest.raises(DeviceError, match=r"scan_hz = 50 is outside the LMS111 limit"):
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
