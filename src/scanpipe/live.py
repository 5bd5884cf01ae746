"""The live view while recording: the scan as it grows, over the Foxglove WebSocket protocol.

:class:`LiveView` is a tap on the recorder's sink (:class:`~scanpipe.acquire.sink.SinkTap`):
the sink hands it every scanner byte chunk, motor state, camera frame and event; a worker thread
decodes the scanner stream (the rig's dialect), places each profile at the platform angle of the
latest motor state, and publishes, through foxglove-sdk's WebSocket server, on the topics and
with the messages of the Foxglove export (:mod:`scanpipe.exporters.mcap_foxglove`):

- ``/tf``: ``world`` → ``rig``, ``platform`` → ``camera_<id>`` (repeated once a second, so a
  client that connects later has them) and ``rig`` → ``platform`` at every motor state;
- ``/scan/profile``: each profile as it arrives, in the ``rig`` frame;
- ``/scan/cloud``: the cloud so far (at most ``max_points``, evenly thinned), every
  ``cloud_interval_s``;
- ``/camera/<id>/image`` and ``/camera/<id>/calibration``: every camera frame;
- ``/events`` (``foxglove.Log``): start, stop, warnings and errors of the recording.

The points are a preview: raw ranges at the angles the scanner reports, without the assemble
stage's clock fitting and calibration offsets. The sink never waits for the view: when the
worker falls behind, items are dropped and counted (:attr:`LiveView.dropped`).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanpipe.errors import LiveError
from scanpipe.exporters import mcap_foxglove as fx
from scanpipe.extras import require
from scanpipe.motion import beta_deg_from_steps
from scanpipe.protobuf import file_descriptor_set
from scanpipe.rig import Rig

#: Event kinds shown as warnings / errors in Foxglove's Log panel (the rest are INFO).
_ERROR_WORDS = ("error", "fail", "lost")
_WARNING_WORDS = ("warn", "drop", "limit", "mismatch", "gap", "timeout", "interrupt", "retry")


def event_level(kind: str) -> int:
    """The ``foxglove.Log`` level of a recorder event kind."""
    from foxglove_schemas_protobuf.Log_pb2 import Log

    lowered = kind.lower()
    if any(word in lowered for word in _ERROR_WORDS):
        return int(Log.Level.ERROR)
    if any(word in lowered for word in _WARNING_WORDS):
        return int(Log.Level.WARNING)
    return int(Log.Level.INFO)


class _Subscriptions:
    """The server listener: a client's subscription is queued for the worker."""

    def __init__(self, view: LiveView) -> None:
        self.view = view

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.view.subscriptions += 1
        self.view._put(("subscribed", str(channel.topic)))

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self.view.subscriptions -= 1


class LiveView:
    """Serves the scan as it grows on ``ws://host:port`` (foxglove.websocket.v1); see the
    module docstring. Use as a context manager, or call :meth:`close`."""

    def __init__(self, rig: Rig, port: int, host: str = "127.0.0.1",
                 cloud_interval_s: float = 0.5, max_points: int = 300_000,
                 queue_size: int = 4096) -> None:
        foxglove = require("foxglove", "the live view (--live)")
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.Log_pb2 import Log
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

        from scanpipe.protocol.registry import get_dialect

        self.rig = rig
        self.cloud_interval_s = cloud_interval_s
        self.max_points = max_points
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="scanpipe", host=host, port=port,
                                                 context=self._context,
                                                 server_listener=_Subscriptions(self))
        except RuntimeError as err:
            raise LiveError(f"--live {port}: cannot serve on {host}:{port} ({err}); choose "
                            "another port") from err
        self.port = int(self._server.port)
        self.host = host

        def channel(topic: str, message_class: Any) -> Any:
            schema = foxglove.Schema(name=message_class.DESCRIPTOR.full_name,
                                     encoding="protobuf",
                                     data=file_descriptor_set(message_class))
            return foxglove.Channel(topic, schema=schema, message_encoding="protobuf",
                                    context=self._context)

        self._channels: dict[str, Any] = {
            "/tf": channel("/tf", FrameTransform),
            "/scan/profile": channel("/scan/profile", PointCloud),
            "/scan/cloud": channel("/scan/cloud", PointCloud),
            "/events": channel("/events", Log),
        }
        for cam in rig.cameras:
            self._channels[f"/camera/{cam.id}/image"] = channel(f"/camera/{cam.id}/image",
                                                                CompressedImage)
            self._channels[f"/camera/{cam.id}/calibration"] = channel(
                f"/camera/{cam.id}/calibration", CameraCalibration)
        self._decoder = get_dialect(rig.scanner.dialect).stream_decoder("strict")
        self._beta_deg: float | None = None
        self._clouds: list[NDArray[np.float32]] = []
        self._points = 0
        self._last_cloud_s = 0.0
        self._last_stream_ns = 0
        self._last_static_s = 0.0
        self.published: dict[str, int] = dict.fromkeys(self._channels, 0)
        self.dropped = 0
        self.errors = 0
        #: Subscriptions of connected viewers (per client and channel).
        self.subscriptions = 0
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(queue_size)
        self._worker = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._worker.start()

    @property
    def url(self) -> str:
        """The WebSocket URL a Foxglove client opens."""
        return f"ws://{self.host}:{self.port}"

    # -- the sink tap (called under the sink's lock: only queue) -------------------------------

    def _put(self, item: tuple[Any, ...]) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def on_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        """Scanner bytes received (RX) go to the decoder; the rest is ignored."""
        if link == "scanner" and direction == 0:
            self._put(("stream", bytes(data), log_time_ns))

    def on_motor_state(self, log_time_ns: int, step_count: int) -> None:
        """A motor state: the platform angle from now on."""
        self._put(("motor", log_time_ns, step_count))

    def on_image(self, camera_id: str, log_time_ns: int, data: bytes) -> None:
        """A camera frame (JPEG)."""
        self._put(("image", camera_id, log_time_ns, data))

    def on_event(self, kind: str, message: str, data: Mapping[str, Any],
                 log_time_ns: int) -> None:
        """A recorder event (start, stop, warnings, errors)."""
        self._put(("event", kind, message, log_time_ns))

    # -- the worker ------------------------------------------------------------------------

    def _log(self, topic: str, message: Any, time_ns: int) -> None:
        self._channels[topic].log(message.SerializeToString(), log_time=time_ns)
        self.published[topic] += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                self._handle(item)
            except Exception:  # the preview must never stop the recording: count and go on
                self.errors += 1

    def _handle(self, item: tuple[Any, ...]) -> None:
        kind, *rest = item
        now_ns = time.time_ns()
        self._static_transforms(now_ns)
        if kind == "stream":
            self._profiles(rest[0], rest[1])
        elif kind == "motor":
            self._beta_deg = float(beta_deg_from_steps(np.array([rest[1]]), self.rig.motor)[0])
            self._log("/tf", fx.platform_transform(rest[0], self._beta_deg), rest[0])
        elif kind == "image":
            camera_id, time_ns, data = rest
            topic = f"/camera/{camera_id}/image"
            if topic in self._channels:
                self._log(f"/camera/{camera_id}/calibration",
                          fx.camera_calibration(time_ns, self.rig.camera(camera_id)),
                          time_ns)
                self._log(topic, fx.compressed_image(time_ns, camera_id, data, "jpeg"),
                          time_ns)
        elif kind == "event":
            self._event(*rest)
        elif kind == "subscribed":  # a new viewer: what it would otherwise wait for
            if rest[0] == "/tf":
                self._static_transforms(now_ns, force=True)
            elif rest[0] == "/scan/cloud":
                self.publish_cloud()

    def _static_transforms(self, now_ns: int, force: bool = False) -> None:
        """world → rig and platform → cameras: at once for a new subscriber, else once a
        second."""
        now_s = time.monotonic()
        if not force and now_s - self._last_static_s < 1.0:
            return
        self._last_static_s = now_s
        self._log("/tf", fx.world_transform(now_ns), now_ns)
        for cam in self.rig.cameras:
            self._log("/tf", fx.camera_transform(now_ns, cam), now_ns)

    def _profiles(self, data: bytes, time_ns: int) -> None:
        try:
            profiles = self._decoder.feed(data)
        except Exception:  # a damaged stream: the decoder resyncs; a preview never stops
            return
        self._last_stream_ns = time_ns
        self._place(profiles, time_ns)
        if time.monotonic() - self._last_cloud_s >= self.cloud_interval_s:
            self.publish_cloud(time_ns)

    def _place(self, profiles: list[Any], time_ns: int) -> None:
        """Publish each profile at the latest platform angle and keep it for the cloud."""
        from scanpipe.stages.assemble import points_from_grid

        if self._beta_deg is None:
            return  # no platform angle yet: the profile cannot be placed
        for profile in profiles:
            ranges = np.asarray(profile.ranges_m, np.float32)
            alpha = profile.start_angle_deg + profile.step_deg * np.arange(len(ranges))
            grid = points_from_grid(ranges[None, :], alpha.astype(np.float64),
                                    np.array([self._beta_deg]), self.rig)
            xyz = np.stack([grid["x"][0], grid["y"][0], grid["z"][0]], axis=1)
            xyz = xyz[np.isfinite(xyz).all(axis=1)].astype(np.float32)
            if not len(xyz):
                continue
            self._log("/scan/profile", fx.cloud_message(time_ns, fx.RIG_FRAME, xyz, None, None),
                      time_ns)
            self._clouds.append(xyz)
            self._points += len(xyz)

    def publish_cloud(self, time_ns: int | None = None) -> None:
        """Publish the cloud so far now (thinned evenly to ``max_points``)."""
        if not self._clouds:
            return
        self._last_cloud_s = time.monotonic()
        cloud = np.concatenate(self._clouds)
        self._clouds = [cloud]
        if len(cloud) > self.max_points:
            cloud = cloud[np.linspace(0, len(cloud) - 1, self.max_points).astype(np.int64)]
        when = time.time_ns() if time_ns is None else time_ns
        self._log("/scan/cloud", fx.cloud_message(when, fx.RIG_FRAME, cloud, None, None), when)

    def _event(self, kind: str, message: str, time_ns: int) -> None:
        from foxglove_schemas_protobuf.Log_pb2 import Log

        log = Log(level=event_level(kind), message=message, name=kind)  # type: ignore[arg-type]
        log.timestamp.seconds, log.timestamp.nanos = divmod(time_ns, 1_000_000_000)
        self._log("/events", log, time_ns)

    # -- life cycle ------------------------------------------------------------------------

    def close(self, linger_s: float = 1.0) -> None:
        """Publish what is queued and the final cloud, keep serving ``linger_s`` seconds while a
        viewer is subscribed, then stop the server.

        Stopping the server at once drops the messages still on their way: a viewer would miss
        the final cloud and the end of the recording."""
        self._queue.put(None)
        self._worker.join(timeout=10.0)
        try:  # the last frame, held by the decoder until a next marker would confirm it
            self._place(self._decoder.finish(), self._last_stream_ns)
        except Exception:
            self.errors += 1
        self.publish_cloud()
        if linger_s > 0 and self.subscriptions > 0:
            time.sleep(linger_s)
        self._server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
