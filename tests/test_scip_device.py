"""Hokuyo scanners on the virtual rig: the emulated UST-10LX (TCP) and URG-04LX (pty) answer
the SCIP commands, the recorder's driver starts and stops them, simulate → run meets 1.1 σ."""

from __future__ import annotations

import os
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from scanpipe.acquire.scanner_client import ScannerClient
from scanpipe.artifacts import read_provenance
from scanpipe.errors import DeviceError
from scanpipe.evaluate import SurfaceDistance, load_reference
from scanpipe.protocol import scip
from scanpipe.protocol.registry import decode_bytes
from scanpipe.recording.reader import read_recording
from scanpipe.rig import default_rig, rig_to_toml, scanner_for_model
from scanpipe.scanner_models import SCANNER_MODELS
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.options import SimOptions
from scanpipe.sim.room import box_room
from scanpipe.sim.scip_device import ScipDevice


class Sink:
    """Collects what the client records."""

    def __init__(self) -> None:
        self.chunks: list[tuple[str, bytes, int]] = []

    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        self.chunks.append((link, data, direction))


def _options(model: str) -> SimOptions:
    rig = default_rig()
    return SimOptions(rig=rig.model_copy(update={"scanner": scanner_for_model(model)}),
                      cameras=False)


def test_the_device_answers_its_commands() -> None:
    device = ScipDevice(scanner_for_model("urg04lx"))
    replies = device.receive(b"VV\nPP\nII\nBM\nBM\nMD0044072501003\nXX\nMD0044099901000\n", 1.0)
    statuses = ["00", "00", "00", "00", "02", "00", "0E", "04"]
    assert [r.split(b"\n")[1] + b"\n" for r in replies] == [scip.status_line(c)
                                                           for c in statuses]
    reader = scip.ScipReader()
    reader.feed(replies[1])
    assert reader.geometry == scip.URG04_GEOMETRY
    # MD0044072501003: three scans, counting down, then the stream ends by itself.
    ranges = np.full(682, 2.0, np.float32)
    config = device.config()
    assert config.samples_per_profile == 682
    assert config.start_angle_deg == pytest.approx(-119.53125)
    sent = [device.encode(k, ranges, None, config, k * 0.1) for k in range(3)]
    assert [s[:15] for s in sent] == [b"MD0044072501002", b"MD0044072501001",
                                      b"MD0044072501000"]
    assert not device.streaming
    profiles, counters = decode_bytes(replies[1] + b"".join(sent), "scip")
    assert len(profiles) == 3 and counters.checksum_failures == 0
    assert np.allclose(profiles[0].ranges_m, 2.0)
    assert device.receive(b"QT\n", 2.0) == [b"QT\n00P\n\n"]


def test_urg04lx_streams_over_a_pty_and_stops_with_qt() -> None:
    with VirtualRig(_options("urg04lx"), speedup=2.0, scene=box_room()) as virtual:
        scanner = virtual.client_rig().scanner
        assert scanner.serial_url.startswith("/dev/pts/")
        sink = Sink()
        client = ScannerClient(scanner, sink)
        client.connect()
        try:
            assert client.wait_for_profiles(time.time_ns() - 1, 3, timeout_s=5.0)
        finally:
            client.close()
        requests = virtual.scanner.requests
    assert requests[:4] == ["VV", "PP", "BM", "MD"] and requests[-1] == "QT"
    received = b"".join(d for _, d, direction in sink.chunks if direction == 0)
    profiles, _ = decode_bytes(received, "scip")
    assert len(profiles) >= 3
    assert profiles[0].start_angle_deg == pytest.approx(-119.53125)  # from the PP reply
    assert profiles[0].echo is None


def test_ust10lx_streams_intensities_over_tcp() -> None:
    with VirtualRig(_options("ust10lx"), speedup=1.0, scene=box_room()) as virtual:
        sink = Sink()
        client = ScannerClient(virtual.client_rig().scanner, sink)
        client.connect()
        try:
            assert client.wait_for_profiles(time.time_ns() - 1, 3, timeout_s=5.0)
        finally:
            client.close()
        assert "ME" in virtual.scanner.requests
    received = b"".join(d for _, d, direction in sink.chunks if direction == 0)
    profiles, _ = decode_bytes(received, "scip")
    assert profiles[0].start_angle_deg == -135.0 and len(profiles[0].ranges_m) == 1081
    assert profiles[0].echo is not None and profiles[0].device_wrap_ticks == 1 << 24


@pytest.mark.slow
@pytest.mark.parametrize(("model", "mode", "options"), [
    ("ust10lx", "step", ("--motor-step", "3", "--beam-step", "1", "--speedup", "1")),
    ("ust10lx", "continuous", ("--motor-step", "3", "--beam-step", "1", "--speedup", "1")),
    ("urg04lx", "continuous", ("--motor-step", "2", "--speedup", "2"))])
def test_scip_live_through_the_emulator_and_run(tmp_path: Path, cli: Callable[..., Any],
                                                model: str, mode: str,
                                                options: tuple[str, ...]) -> None:
    """The user's path: simulate live (SCIP: UST-10LX on TCP, ME stream with intensities;
    URG-04LX on a pty, MD stream) → run; points within 1.1 σ of the device's noise.
    (UST-10LX at speed-up 1: a 40 Hz scanner at a higher speed-up outruns the emulator on a
    loaded machine.)"""
    rec, truth, work = tmp_path / "s.mcap", tmp_path / "t", tmp_path / "w"
    result = cli("simulate", "--scanner", model, "--out", rec, "--truth", truth,
                 "--mode", mode, *options, "--no-cameras", "--seed", "4", "--quiet")
    assert result.code == 0, result.err
    result = cli("run", rec, "--workdir", work, "--quiet")
    assert result.code == 0 and "Traceback" not in result.err
    profiles = pq.read_table(work / "decode" / "profiles.parquet")
    assert set(profiles.column("dialect").to_pylist()) == {"scip"}
    # The UST-10LX sends intensities (ME), the URG-04LX none (MD).
    assert (profiles.column("echo").null_count == 0) == SCANNER_MODELS[model].intensity
    report = read_provenance(work / "assemble" / "points.parquet")["report"]
    assert report["time_source"] == "device" and report["mode"] == mode
    table = pq.read_table(work / "assemble" / "points.parquet", columns=["x", "y", "z"])
    xyz = np.stack([table.column(c).to_numpy() for c in "xyz"], axis=1).astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    rms = float(np.sqrt(np.mean(np.square(
        SurfaceDistance(load_reference(truth).mesh).distance_m(xyz)))))
    sigma = SCANNER_MODELS[model].noise_sigma_m
    assert rms <= 1.1 * sigma, f"RMS {rms * 1e3:.2f} mm = {rms / sigma:.3f} σ"


def test_a_scip11_device_answers_as_scip11_until_switched() -> None:
    device = ScipDevice(scanner_for_model("urg04lx"), protocol="1.1")
    assert device.receive(b"VV\nSCIP2.0\nVV\n", 1.0)[:2] == [b"VV\nE\n\n", b"SCIP2.0\n0\n\n"]
    assert device.protocol == "2.0"
    refusing = ScipDevice(scanner_for_model("urg04lx"), protocol="1.1-only")
    assert refusing.receive(b"SCIP2.0\nVV\n", 1.0) == [b"SCIP2.0\nE\n\n", b"VV\nE\n\n"]
    # A SCIP 2.0 device answers the switch 0E (already SCIP 2.0).
    assert ScipDevice(scanner_for_model("urg04lx")).receive(b"SCIP2.0\n", 1.0) == [
        b"SCIP2.0\n" + scip.status_line("0E") + b"\n"]


def test_a_scip11_urg_is_switched_to_scip20_over_a_pty() -> None:
    """A URG-04LX of older firmware starts in SCIP 1.1: the driver's VV is answered 'E' (it
    timed out before: the reply was no SCIP 2.0 message); the driver sends SCIP2.0, as
    urg_library does, and records the SCIP 2.0 stream, which decodes as the 2.0 device's."""
    options = _options("urg04lx").model_copy(update={"scip_protocol": "1.1"})
    with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
        sink = Sink()
        client = ScannerClient(virtual.client_rig().scanner, sink)
        client.connect()
        try:
            assert client.wait_for_profiles(time.time_ns() - 1, 3, timeout_s=5.0)
        finally:
            client.close()
        requests = virtual.scanner.requests
    assert requests[:6] == ["VV", "SC", "VV", "PP", "BM", "MD"]
    received = b"".join(d for _, d, direction in sink.chunks if direction == 0)
    assert received.startswith(b"VV\nE\n\nSCIP2.0\n0\n\nVV\n00P\n")
    profiles, counters = decode_bytes(received, "scip")
    assert len(profiles) >= 3 and profiles[0].start_angle_deg == pytest.approx(-119.53125)
    assert counters.other_frames >= 5 and counters.checksum_failures == 0
    # The handshake (the two SCIP 1.1 answers, VV, PP, BM, MD) is read whole: six other
    # frames, not a byte skipped as noise.
    handshake = received[:received.index(b"\n\n", received.index(b"\nMD")) + 2]
    _, counters = decode_bytes(handshake, "scip")
    assert counters.other_frames == 6 and counters.bytes_skipped == 0


def test_a_scip11_urg_that_refuses_the_switch_is_one_line() -> None:
    options = _options("urg04lx").model_copy(update={"scip_protocol": "1.1-only"})
    with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
        client = ScannerClient(virtual.client_rig().scanner, Sink())
        with pytest.raises(DeviceError) as raised:
            client.connect()
        client.close()
    message = str(raised.value)
    assert "\n" not in message and "SCIP 1.1" in message and "refused the switch" in message
    assert "update the sensor's firmware" in message


@pytest.mark.slow
def test_record_a_scip11_urg_then_run_and_a_refusing_one_is_one_line(
        tmp_path: Path, cli: Callable[..., Any]) -> None:
    """The user's path with a URG-04LX that starts in SCIP 1.1: ``record`` (switched, as
    urg_library does) → ``run``; one that refuses the switch: ``record`` fails in one line
    naming SCIP 1.1, and its file is finished and says what happened."""
    for protocol in ("1.1", "1.1-only"):
        options = _options("urg04lx").model_copy(update={"scip_protocol": protocol})
        rec = tmp_path / f"{protocol}.mcap"
        with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
            rig_file = tmp_path / f"{protocol}.toml"
            rig_file.write_text(rig_to_toml(virtual.client_rig()))
            result = cli("record", "--rig", rig_file, "--out", rec, "--mode", "continuous",
                         "--motor-step", "10", "--no-cameras", "--quiet")
        assert "Traceback" not in result.err
        if protocol == "1.1-only":
            assert result.code == 1 and result.err.count("\n") == 1, result.err
            assert "SCIP 1.1" in result.err and "refused the switch" in result.err
            recording = read_recording(rec)
            assert recording.complete and "device_error" in [e.kind for e in recording.events]
            continue
        assert result.code == 0, result.err
        work = tmp_path / "work"
        result = cli("run", rec, "--workdir", work, "--quiet")
        assert result.code == 0, result.err
        report = read_provenance(work / "decode" / "profiles.parquet")["report"]
        assert report["dialect"] == "scip" and report["counters"]["checksum_failures"] == 0
        assert report["counters"]["frames_decoded"] >= 10
        assert (work / "assemble" / "points.parquet").is_file()


def test_a_scip11_urg_that_leaves_vv_unanswered_is_switched_too() -> None:
    """A SCIP 1.1 device that ignores SCIP 2.0 commands: VV times out, the driver tries the
    switch before giving up, and records SCIP 2.0."""
    options = _options("urg04lx").model_copy(update={"scip_protocol": "1.1-silent"})
    with VirtualRig(options, speedup=2.0, scene=box_room()) as virtual:
        client = ScannerClient(virtual.client_rig().scanner, Sink(), reply_timeout_s=1.0)
        client.connect()
        try:
            assert client.wait_for_profiles(time.time_ns() - 1, 3, timeout_s=5.0)
        finally:
            client.close()
        assert virtual.scanner.requests[:4] == ["VV", "SC", "VV", "PP"]
    silent = ScipDevice(scanner_for_model("urg04lx"), protocol="1.1-silent")
    assert silent.receive(b"VV\nPP\n", 1.0) == []


def test_a_port_that_answers_nothing_is_one_line() -> None:
    master, slave = os.openpty()  # a real serial line with nothing behind it
    try:
        tty.setraw(slave)
        scanner = scanner_for_model("urg04lx").model_copy(update={
            "serial_url": os.ttyname(slave)})
        client = ScannerClient(scanner, Sink(), reply_timeout_s=0.5)
        with pytest.raises(DeviceError) as raised:
            client.connect()
        client.close()
    finally:
        os.close(master)
        os.close(slave)
    message = str(raised.value)
    assert "\n" not in message and "no reply to SCIP VV" in message
    assert "nor to SCIP2.0" in message and "Hokuyo on this port" in message
