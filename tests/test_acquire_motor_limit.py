"""The motor client never sends a move past the pulse limit (checked on this side)."""

from __future__ import annotations

from typing import Any

import pytest

from scanpipe.acquire.motor_client import MotorClient
from scanpipe.errors import DeviceError
from scanpipe.rig import MotorConfig


class _Sink:
    def __init__(self) -> None:
        self.tx: list[bytes] = []
        self.states: list[tuple[Any, ...]] = []

    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        if direction == 1:
            self.tx.append(data)

    def write_motor_state(self, *args: Any) -> None:
        self.states.append(args)


def test_move_past_the_limit_is_refused_before_sending() -> None:
    sink = _Sink()
    client = MotorClient(MotorConfig(serial_url="loop://", pulse_limit=5000), sink,
                         reply_timeout_s=0.2)
    client.connect()
    try:
        with pytest.raises(DeviceError, match=r"would reach 5001, outside 0…5000"):
            client.check_move(+3, 4998)
        with pytest.raises(DeviceError, match=r"outside 0…5000"):
            client.check_move(-1, 0)
        client.check_move(+2, 4998)  # exactly at the limit is allowed
        assert sink.tx == []  # nothing went on the wire
    finally:
        client.close()


def test_unopenable_port_is_a_device_error() -> None:
    client = MotorClient(MotorConfig(serial_url="/dev/does-not-exist-scanpipe"), _Sink())
    with pytest.raises(DeviceError, match="cannot open"):
        client.connect()
