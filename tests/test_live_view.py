"""``scanpipe simulate --live``: the scan served while it is recorded, over the Foxglove
WebSocket protocol, read by a real WebSocket client (the ``websockets`` package speaking the
Foxglove WebSocket subprotocol: subscribe, then receive binary message data)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import struct
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import websockets
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

from scanpipe.cli.common import expand_optional_values
from scanpipe.rig import default_rig, rig_to_toml

SRC = Path(__file__).resolve().parents[1] / "src"
#: The protocol's subprotocol names: foxglove-sdk ≥ 0.30 speaks ``foxglove.sdk.v1`` (the
#: renamed ``foxglove.websocket.v1``, same framing); the client offers both, as Foxglove does.
SUBPROTOCOLS = [websockets.Subprotocol("foxglove.sdk.v1"),
                websockets.Subprotocol("foxglove.websocket.v1")]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


async def _collect(port: int, process: subprocess.Popen[bytes], deadline_s: float
                   ) -> tuple[dict[str, list[bytes]], dict[str, Any], list[str]]:
    """Connect (retrying until the server is up), subscribe to every advertised channel and
    gather message payloads by topic until the server goes away; also the topics in the order
    their messages arrived."""
    uri = f"ws://127.0.0.1:{port}"
    end = time.monotonic() + deadline_s
    while True:
        try:
            connection = await websockets.connect(uri, subprotocols=SUBPROTOCOLS,
                                                  max_size=None, open_timeout=2)
            break
        except OSError:
            if time.monotonic() > end or process.poll() is not None:
                raise
            await asyncio.sleep(0.1)
    topics: dict[int, str] = {}
    schemas: dict[str, Any] = {}
    received: dict[str, list[bytes]] = defaultdict(list)
    order: list[str] = []
    assert connection.subprotocol in SUBPROTOCOLS
    async with connection:
        while time.monotonic() < end:
            try:
                frame = await asyncio.wait_for(connection.recv(), timeout=1.0)
            except TimeoutError:
                if process.poll() is not None:
                    break
                continue
            except websockets.ConnectionClosed:
                break
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] == "advertise":
                    new = []
                    for channel in message["channels"]:
                        subscription = len(topics) + 1
                        topics[subscription] = channel["topic"]
                        schemas[channel["topic"]] = (channel["schemaName"], channel["encoding"])
                        new.append({"id": subscription, "channelId": channel["id"]})
                    await connection.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            assert frame[0] == 0x01  # message data: opcode, subscription id, time, payload
            (subscription,) = struct.unpack_from("<I", frame, 1)
            received[topics[subscription]].append(bytes(frame[13:]))
            order.append(topics[subscription])
    return received, schemas, order


def test_simulate_live_serves_the_growing_scan(tmp_path: Path) -> None:
    rig = default_rig()
    rig = rig.model_copy(update={"motor": rig.motor.model_copy(update={"pulse_limit": 700})})
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    port = _free_port()
    command = [sys.executable, "-m", "scanpipe.cli.main", "simulate", "--out",
               str(tmp_path / "sim.mcap"), "--truth", str(tmp_path / "truth"), "--rig",
               str(rig_file), "--scene", "box", "--beam-step", "2", "--motor-step", "5",
               "--camera-scale", "0.04", "--camera-fps", "2", "--speedup", "10", "--quiet",
               "--live", str(port)]
    env = {**os.environ, "PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    process = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        received, schemas, order = asyncio.run(_collect(port, process, deadline_s=120))
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err.decode()
    assert f"live: serving the scan on ws://127.0.0.1:{port}" in err.decode()
    assert schemas["/scan/cloud"] == ("foxglove.PointCloud", "protobuf")
    assert schemas["/camera/cam0/image"] == ("foxglove.CompressedImage", "protobuf")
    assert schemas["/events"] == ("foxglove.Log", "protobuf")

    # The cloud grows: later clouds hold more points, all finite, within the box scene.
    clouds = [PointCloud.FromString(data) for data in received["/scan/cloud"]]
    sizes = [len(c.data) // c.point_stride for c in clouds]
    # The cloud so far only grows, and grows by no more than the profiles served meanwhile.
    # Counted from the first cloud after the first profile received: the client joins a scan
    # under way, so profiles served before its subscriptions took effect are in the cloud but
    # were never received (comparing against all profiles received raced on that).
    assert clouds and sizes[0] > 0 and sizes == sorted(sizes)
    kinds = [topic for topic in order if topic in ("/scan/profile", "/scan/cloud")]
    first_cloud = kinds.index("/scan/cloud", kinds.index("/scan/profile"))
    last_cloud = len(kinds) - 1 - kinds[::-1].index("/scan/cloud")
    profile_sizes = [len(PointCloud.FromString(d).data) // 12 for d in received["/scan/profile"]]
    profiles_before = kinds[:first_cloud].count("/scan/profile")
    profiles_between = kinds[first_cloud:last_cloud].count("/scan/profile")
    grown = sizes[-1] - sizes[kinds[:first_cloud].count("/scan/cloud")]
    # (0 when the client's first cloud after a profile is already the last: nothing to compare)
    assert 0 <= grown <= sum(profile_sizes[profiles_before:profiles_before + profiles_between])
    assert sizes[-1] > 0 and profile_sizes and min(profile_sizes) > 0
    last = clouds[-1]
    xyz = np.frombuffer(last.data, np.uint8).reshape(-1, last.point_stride)[:, :12].copy()
    points = xyz.view(np.float32).reshape(-1, 3)
    assert np.isfinite(points).all() and np.abs(points).max() < 20
    assert len(received["/scan/profile"]) > 10

    # The platform turns: rig → platform transforms at growing angles.
    turns = [FrameTransform.FromString(d) for d in received["/tf"]]
    platform = [t for t in turns if t.child_frame_id == "platform"]
    assert len(platform) > 3
    angles = [2 * np.degrees(np.arctan2(t.rotation.y, t.rotation.w)) for t in platform]
    assert max(angles) - min(angles) > 10
    assert {t.child_frame_id for t in turns} >= {"rig", "platform", "camera_cam0"}

    images = [CompressedImage.FromString(d) for d in received["/camera/cam0/image"]]
    assert images and images[0].data[:2] == b"\xff\xd8" and images[0].format == "jpeg"
    assert len(received["/camera/cam0/calibration"]) == len(images)

    events = [Log.FromString(d) for d in received["/events"]]
    names = {e.name for e in events}
    assert "recording_end" in names
    assert any(e.level == Log.Level.INFO for e in events)


def test_live_port_is_optional_on_the_command_line() -> None:
    assert expand_optional_values(["record", "--live"]) == ["record", "--live", "8765"]
    assert expand_optional_values(["record", "--live", "9000", "-q"]) == [
        "record", "--live", "9000", "-q"]
    assert expand_optional_values(["record", "--live", "--quiet"]) == [
        "record", "--live", "8765", "--quiet"]
    assert expand_optional_values(["info", "--", "--live"]) == ["info", "--", "--live"]


def test_live_refuses_direct_and_a_taken_port(cli, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    out, truth = tmp_path / "sim.mcap", tmp_path / "truth"
    result = cli("simulate", "--direct", "--live", "--out", out, "--truth", truth)
    assert result.code == 2
    assert "--live serves a scan as it is recorded" in result.err
    assert result.err.count("\n") == 1
    assert not out.exists() and not truth.exists()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = cli("simulate", "--live", str(port), "--out", out, "--truth", truth,
                     "--scene", "box", "--speedup", "20")
    assert result.code == 2, result.err
    assert f"--live {port}: cannot serve on 127.0.0.1:{port}" in result.err
    assert not out.exists()


@pytest.mark.parametrize("kind, level", [("recording_end", Log.Level.INFO),
                                         ("camera_frames_dropped", Log.Level.WARNING),
                                         ("device_error", Log.Level.ERROR),
                                         ("motor_limit", Log.Level.WARNING)])
def test_event_levels(kind: str, level: int) -> None:
    from scanpipe.live import event_level

    assert event_level(kind) == level


def test_a_subscribed_viewer_gets_the_final_cloud_when_the_recording_ends() -> None:
    """The last profiles arrive and the recording stops at once (no periodic cloud in
    between): the viewer still receives the final cloud with every point (stopping the server
    straight after publishing it dropped it on its way)."""
    from scanpipe.live import LiveView
    from scanpipe.protocol.profile import Profile
    from scanpipe.protocol.registry import get_dialect

    rig = default_rig()
    dialect = get_dialect(rig.scanner.dialect)
    view = LiveView(rig, _free_port(), cloud_interval_s=3600.0)

    async def watch() -> list[int]:
        connection = await websockets.connect(view.url, subprotocols=SUBPROTOCOLS, max_size=None)
        topics: dict[int, str] = {}
        sizes: list[int] = []
        async with connection:
            while True:
                try:
                    frame = await asyncio.wait_for(connection.recv(), timeout=10.0)
                except websockets.ConnectionClosed:
                    return sizes
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] == "advertise":
                        wanted = [c for c in message["channels"] if c["topic"] == "/scan/cloud"]
                        for channel in wanted:
                            topics[len(topics) + 1] = channel["topic"]
                        await connection.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": i + 1, "channelId": c["id"]} for i, c in enumerate(wanted)]}))
                        for _ in range(100):  # the subscription registered: now end the scan
                            if view.subscriptions:
                                break
                            await asyncio.sleep(0.05)
                        await asyncio.get_running_loop().run_in_executor(None, end_scan)
                    continue
                cloud = PointCloud.FromString(bytes(frame[13:]))
                sizes.append(len(cloud.data) // cloud.point_stride)

    ranges = np.full(100, 2.0, np.float32)

    def end_scan() -> None:
        view.on_motor_state(0, 0)
        for frame in range(5):
            profile = Profile(frame=frame, sector=0, start_angle_deg=0.0, step_deg=0.9,
                              ranges_m=ranges, device_time_ms=frame * 50,
                              device_end_time_ms=frame * 50 + 40)
            view.on_stream("scanner", dialect.encode_profile(profile), 0, frame * 50_000_000)
        view.close()

    sizes = asyncio.run(watch())
    assert sizes and sizes[-1] == 5 * len(ranges)
