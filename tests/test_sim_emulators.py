"""The emulators on real endpoints: TCP sockets for the scanner, a pty for the motor controller,
the virtual camera, and a recording made through them that decodes to the truth."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import serial

from scanpipe.protocol import ldoem
from scanpipe.protocol.profile import Profile
from scanpipe.protocol.registry import DIALECTS
from scanpipe.recording.writer import RecordingWriter
from scanpipe.rig import Rig, default_rig
from scanpipe.sim.emulators import VirtualRig
from scanpipe.sim.options import SimOptions
from scanpipe.sim.truth import load_truth
from scanpipe.stages.decode import STAGE as DECODE

QUANTUM_M = 1.0 / 256


def _options(dialect: str = "ldoem", **extra: object) -> SimOptions:
    rig = default_rig()
    rig = rig.model_copy(update={"scanner": rig.scanner.model_copy(update={"dialect": dialect})})
    base: dict[str, object] = {"rig": rig, "beam_step_deg": 2.0, "motor_step_deg": 5.0,
                               "noise_sigma_m": 0.0, "dropout_rate": 0.0, "grazing_start_deg": 90.0,
                               "camera_scale": 0.05}
    base.update(extra)
    return SimOptions.model_validate(base)


@pytest.fixture
def virtual_rig() -> Iterator[VirtualRig]:
    with VirtualRig(_options(), speedup=20.0) as rig:
        yield rig


class _Reader:
    """A tiny scanner client: collects frames from a socket in a thread."""

    def __init__(self, sock: socket.socket, dialect: str) -> None:
        self.sock = sock
        self.reader = DIALECTS[dialect].frame_reader() if dialect == "paper" else \
            ldoem.FrameReader(accept_unknown=True)
        self.payloads: list[bytes] = []
        self.chunks: list[tuple[int, bytes]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.sock.settimeout(0.05)
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            self.chunks.append((time.time_ns(), data))
            self.payloads.extend(f.payload for f in self.reader.feed(data))

    def wait_for(self, predicate: object, timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():  # type: ignore[operator]
                return
            time.sleep(0.01)
        raise AssertionError("timed out waiting for the emulator")

    def replies(self) -> list[ldoem.Message]:
        return [ldoem.parse_payload(p) for p in self.payloads]

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        self.sock.close()


def _connect(rig: VirtualRig) -> socket.socket:
    return socket.create_connection(rig.scanner.address, timeout=2)


def test_ldoem_emulator_answers_requests_and_streams(virtual_rig: VirtualRig) -> None:
    client = _Reader(_connect(virtual_rig), "ldoem")
    try:
        client.sock.sendall(ldoem.get_ident_request())
        client.sock.sendall(ldoem.get_status_request())
        client.sock.sendall(ldoem.rotate_request(30))
        client.wait_for(lambda: len(client.payloads) >= 3)
        ident, status, rotate = client.replies()[:3]
        assert ident.body.startswith(b"LD-OEM1000")
        assert ldoem.parse_status_reply(status)[1] == ldoem.MOTOR_OK
        assert rotate.body.startswith(b"\xff\xff") and b"scan_hz 30" in rotate.body
        client.sock.sendall(ldoem.get_profile_request(4, ldoem.MASK_RANGES_ECHO))
        client.wait_for(lambda: sum(m.is_profile_reply for m in client.replies()) >= 4)
        time.sleep(0.1)
        profiles = [m for m in client.replies() if m.is_profile_reply]
        assert len(profiles) == 4  # GET_PROFILE n=4 stops after four
        payload = next(p for p in client.payloads if ldoem.parse_payload(p).is_profile_reply)
        reply = ldoem.decode_profile_reply(payload)
        assert reply.mask == ldoem.MASK_RANGES_ECHO
        client.sock.sendall(ldoem.get_profile_request(0, ldoem.MASK_RANGES))
        client.wait_for(lambda: sum(m.is_profile_reply for m in client.replies()) >= 8)
        client.sock.sendall(ldoem.cancel_profile_request())
        client.wait_for(lambda: any(m.sub == ldoem.CANCEL_PROFILE for m in client.replies()))
        time.sleep(0.15)
        count = len(client.payloads)
        time.sleep(0.3)  # 6 head turns at 20× speed-up: nothing more after CANCEL
        assert len(client.payloads) == count
    finally:
        client.close()


def test_paper_emulator_streams_on_connect() -> None:
    with VirtualRig(_options("paper"), speedup=20.0) as rig:
        client = _Reader(_connect(rig), "paper")
        try:
            client.wait_for(lambda: len(client.payloads) >= 3)
            profiles = DIALECTS["paper"].decode_payload(client.payloads[0], True)
            assert profiles is not None and len(profiles[0].ranges_m) == 180
        finally:
            client.close()


def test_motor_emulator_over_a_pty_refuses_moves_past_the_limit(virtual_rig: VirtualRig) -> None:
    port = serial.serial_for_url(virtual_rig.motor.port_path, baudrate=115200, timeout=2)
    try:
        port.write(b"ZERO\n")
        assert port.readline() == b"OK 0\n"
        port.write(b"MOVE +5001\n")
        assert port.readline().startswith(b"ERR LIMIT")
        port.write(b"MOVE -1\n")
        assert port.readline().startswith(b"ERR LIMIT")
        port.write(b"POS?\n")
        assert port.readline().split()[1:4] == [b"0", b"0", b"0"]  # nothing moved
        assert port.readline() == b"OK\n"
        port.write(b"MOVE +200\n")
        assert port.readline() == b"OK 200\n"
        lines = []
        while not lines or lines[-1].split()[3] != b"0":
            lines.append(port.readline())
        assert len(lines) >= 3 and lines[-1].split()[1:4] == [b"200", b"200", b"0"]
        port.write(b"MOVE +2000\r\n")
        assert port.readline() == b"OK 2200\n"
        port.readline()
        time.sleep(0.05)  # one simulated second at 20× speed-up: the move is under way
        port.write(b"STOP\n")
        final = port.readline()
        while final.startswith(b"POS") and final.split()[3] == b"1":
            final = port.readline()
        assert port.readline().startswith(b"OK ")
        assert 200 < int(final.split()[1]) < 2200
    finally:
        port.close()
    assert virtual_rig.motor.commands[:3] == ["ZERO", "MOVE +5001", "MOVE -1"]


def test_virtual_camera_has_the_capture_interface(virtual_rig: VirtualRig) -> None:
    camera = virtual_rig.camera("sim:cam1")
    assert camera.isOpened() and camera.is_live
    assert camera.get(cv2.CAP_PROP_FPS) == 1.0
    assert camera.get(cv2.CAP_PROP_FRAME_WIDTH) == 54  # the default cameras stand upright
    ok, frame = camera.read()
    assert ok and frame is not None and frame.shape == (96, 54, 3) and frame.dtype == np.uint8
    assert camera.grab()
    ok, _ = camera.retrieve()
    assert ok and camera.get(cv2.CAP_PROP_POS_FRAMES) == 2 and len(camera.captures) == 2
    assert camera.set(cv2.CAP_PROP_FPS, 60) is False
    camera.release()
    assert camera.read() == (False, None)
    client = virtual_rig.client_rig()
    assert client.scanner.port == virtual_rig.scanner.address[1]
    assert client.motor.serial_url == virtual_rig.motor.port_path


def _record_with_a_tiny_client(rig: VirtualRig, path: Path, moves: int) -> None:
    """Connect, stream, step the motor a few times over the pty, all into a recording."""
    client_rig: Rig = rig.client_rig()
    with RecordingWriter(path, client_rig, {"mode": "test"}) as writer:
        sock = _connect(rig)
        stream = _Reader(sock, "ldoem")
        request = ldoem.get_profile_request(0, ldoem.MASK_RANGES)
        writer.write_stream("scanner", request, 1, time.time_ns())
        sock.sendall(request)
        port = serial.serial_for_url(rig.motor.port_path, baudrate=115200, timeout=2)
        try:
            for _ in range(moves):
                command = b"MOVE +139\n"
                writer.write_stream("motor", command, 1, time.time_ns())
                port.write(command)
                while True:
                    line = port.readline()
                    now = time.time_ns()
                    writer.write_stream("motor", line, 0, now)
                    if line.startswith(b"POS"):
                        _, count, target, moving, t_us = line.split()
                        writer.write_motor_state(now, int(count), int(target), moving == b"1",
                                                 int(t_us))
                        if moving == b"0":
                            break
                time.sleep(0.03)
            stream.wait_for(lambda: len(stream.payloads) >= 12)
        finally:
            port.close()
            stream.close()
        for t_ns, chunk in stream.chunks:
            writer.write_stream("scanner", chunk, 0, t_ns)


def test_recording_through_the_emulators_decodes_to_the_truth(tmp_path: Path) -> None:
    with VirtualRig(_options(), speedup=20.0) as rig:
        _record_with_a_tiny_client(rig, tmp_path / "rec.mcap", moves=3)
        rig.stop()
        rig.write_truth(tmp_path / "truth")
    truth = load_truth(tmp_path / "truth")
    decoded = DECODE.run({"recording": tmp_path / "rec.mcap"})
    profiles = decoded.tables["profiles"]
    measured = np.array(profiles.column("ranges_m").to_pylist(), dtype=np.float64)
    expected = truth.ranges_true_m().astype(np.float64)
    assert measured.shape == expected.shape and len(measured) >= 12
    both = np.isfinite(expected)
    assert np.array_equal(np.isfinite(measured), both)
    assert np.abs(measured[both] - expected[both]).max() <= QUANTUM_M / 2 + 1e-6
    betas = truth.profiles.column("beta_deg").to_numpy()
    assert betas.max() - betas.min() > 10.0  # the platform turned during the stream
    assert decoded.tables["motor"].num_rows >= 3


def test_profiles_use_the_platform_angle_of_their_instant() -> None:
    with VirtualRig(_options(), speedup=20.0) as rig:
        rig.platform.start_move(rig.clock.now_s(), 5000, 1000.0, 5000.0)
        client = _Reader(_connect(rig), "ldoem")
        try:
            client.sock.sendall(ldoem.get_profile_request(0, ldoem.MASK_RANGES))
            client.wait_for(lambda: len(client.payloads) >= 5)
        finally:
            client.close()
    sent = rig.scanner.sent
    assert all(s.beta_last_deg > s.beta_first_deg for s in sent[:5])
    for s in sent[:5]:
        steps = rig.platform.timeline().steps_at(s.start_s)
        assert s.beta_first_deg == pytest.approx(float(steps) * rig.platform.pulse_step_deg)
    frame: list[Profile] = DIALECTS["ldoem"].decode_payload(client.payloads[0], True) or []
    assert len(frame[0].ranges_m) == 180


def test_stop_is_clean_and_idempotent() -> None:
    rig = VirtualRig(_options(cameras=False), speedup=10.0)
    before = threading.active_count()
    rig.start()
    sock = _connect(rig)
    rig.stop()
    rig.stop()
    sock.settimeout(1)
    try:
        closed = sock.recv(10) == b""  # the emulator closed the connection …
    except ConnectionResetError:
        closed = True  # … or reset it
    assert closed
    sock.close()
    deadline = time.monotonic() + 2
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.02)
    assert threading.active_count() <= before
