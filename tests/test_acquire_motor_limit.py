"""The travel limit holds on the platform's absolute travel since power-on, over the real pty
emulator: across ZERO and reconnects, in the client (checked before sending) and in the
controller (ERR LIMIT, nothing moves); the host obeys the smaller of two limits."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, Literal

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scanpipe.acquire.motor_client import MotorClient, applied_limit
from scanpipe.errors import DeviceError
from scanpipe.rig import MotorConfig
from scanpipe.sim.clock import SimClock
from scanpipe.sim.controller import MotorController
from scanpipe.sim.emulators import MotorEmulator
from scanpipe.sim.motion import PlatformState

SPEEDUP = 500.0  # 5000 pulses at 1000 Hz: ~5 s of device time, ~10 ms here


class _Sink:
    def __init__(self) -> None:
        self.tx: list[bytes] = []
        self.states: list[tuple[Any, ...]] = []

    def write_stream(self, link: str, data: bytes, direction: int, log_time_ns: int) -> None:
        if direction == 1:
            self.tx.append(data)

    def write_motor_state(self, *args: Any) -> None:
        self.states.append(args)

    def moves_sent(self) -> list[bytes]:
        return [d for d in self.tx if d.startswith(b"MOVE")]


@contextmanager
def _emulator(pulse_limit: int = 5000, unlimited_travel: bool = False,
              controller_limit: int | Literal["rig"] | None = "rig"
              ) -> Iterator[MotorEmulator]:
    motor = MotorConfig(pulse_limit=pulse_limit, unlimited_travel=unlimited_travel)
    platform = PlatformState(motor.pulse_step_deg)
    emulator = MotorEmulator(motor, platform, SimClock(SPEEDUP))
    emulator.controller = MotorController(motor, platform, pulse_limit=controller_limit)
    emulator.start()
    try:
        yield emulator
    finally:
        emulator.stop()


def _client(emulator: MotorEmulator, sink: _Sink, pulse_limit: int = 5000,
            unlimited_travel: bool = False) -> MotorClient:
    motor = MotorConfig(serial_url=emulator.port_path, pulse_limit=pulse_limit,
                        unlimited_travel=unlimited_travel)
    client = MotorClient(motor, sink, reply_timeout_s=2.0)
    client.connect()
    return client


def _absolute(emulator: MotorEmulator) -> int:
    """The truth: the platform's pulses from power-on, now."""
    return emulator.controller.absolute_at(emulator.clock.now_s())


def _move_and_wait(client: MotorClient, pulses: int) -> None:
    before = client.query_position().step_count
    client.move(pulses)
    reached = client.wait_for_state(
        lambda s: not s.moving and s.step_count == before + pulses, 5.0)
    assert reached is not None


def test_zero_move_sequence_of_the_issue_is_refused() -> None:
    # MOVE +5000, ZERO, MOVE +5000, ZERO, MOVE +5000 turned the platform 540°.
    sink = _Sink()
    with _emulator() as emulator:
        client = _client(emulator, sink)
        try:
            _move_and_wait(client, 5000)
            travel = client.zero()
            assert (travel.absolute, travel.origin, travel.controller_limit) == (5000, 5000, 5000)
            sent_before = len(sink.moves_sent())
            with pytest.raises(DeviceError, match=r"from absolute 5000 would reach 10000, "
                                                  r"outside 0…5000 \(travel limit 5000 pulses"):
                client.move(5000)
            assert len(sink.moves_sent()) == sent_before  # refused before sending
            # Sent raw, the controller refuses it too (on the absolute position): nothing moves.
            reply = client.command("MOVE +5000")
            assert not reply.ok and reply.text == "LIMIT absolute 5000+5000 = 10000 outside 0..5000"
            client.zero()
            assert not client.command("MOVE +1").ok
            assert _absolute(emulator) == 5000
            assert max(m.target_steps for m in emulator.controller.platform.timeline().moves) \
                == 5000
        finally:
            client.close()


def test_reconnect_keeps_the_absolute_count() -> None:
    sink = _Sink()
    with _emulator() as emulator:
        first = _client(emulator, sink)
        try:
            _move_and_wait(first, 3000)
            first.zero()
        finally:
            first.close()
        second = _client(emulator, sink)  # a new connection, a new client: same controller
        try:
            assert second.travel is None
            travel = second.query_travel()
            assert (travel.absolute, travel.origin) == (3000, 3000)
            assert second.query_position().step_count == 0
            with pytest.raises(DeviceError, match="from absolute 3000 would reach 6000"):
                second.move(3000)
            _move_and_wait(second, 2000)  # up to the limit exactly is fine
            assert _absolute(emulator) == 5000
            with pytest.raises(DeviceError, match="would reach 5001"):
                second.move(1)
        finally:
            second.close()


@pytest.mark.parametrize(("rig", "controller", "applied", "source"), [
    (5000, 400, 400, "controller"),
    (300, 400, 300, "rig"),
    (400, 400, 400, "rig and controller"),
    (None, 400, 400, "controller"),
    (400, None, 400, "rig"),
    (None, None, None, "none"),
])
def test_applied_limit_is_the_smaller_and_named(rig: int | None, controller: int | None,
                                                applied: int | None, source: str) -> None:
    limit = applied_limit(rig, controller)
    assert (limit.pulses, limit.source) == (applied, source)


def test_a_smaller_controller_limit_is_obeyed_and_named() -> None:
    sink = _Sink()
    with _emulator(controller_limit=400) as emulator:
        client = _client(emulator, sink, pulse_limit=5000)
        try:
            limit = client.limit()
            assert (limit.pulses, limit.source, limit.rig, limit.controller) == (
                400, "controller", 5000, 400)
            assert "the controller's own limit" in limit.describe()
            with pytest.raises(DeviceError, match=r"outside 0…400 \(travel limit 400 pulses "
                                                  r"from home \(the controller's own limit\)"):
                client.move(401)
            assert sink.moves_sent() == []
        finally:
            client.close()


def test_unlimited_rig_and_controller_turn_past_a_turn() -> None:
    # A slip ring: the rig says so, the controller has no limit; 540° is allowed.
    sink = _Sink()
    with _emulator(unlimited_travel=True, controller_limit=None) as emulator:
        client = _client(emulator, sink, unlimited_travel=True)
        try:
            assert client.limit().pulses is None
            for _ in range(3):
                _move_and_wait(client, 5000)
                client.zero()
            assert _absolute(emulator) == 15000
            assert client.travel is not None and client.travel.controller_limit is None
        finally:
            client.close()


def test_an_unlimited_rig_still_obeys_a_limited_controller() -> None:
    sink = _Sink()
    with _emulator(controller_limit=5000) as emulator:
        client = _client(emulator, sink, unlimited_travel=True)
        try:
            assert (client.limit().pulses, client.limit().source) == (5000, "controller")
            with pytest.raises(DeviceError, match="outside 0…5000"):
                client.move(5001)
        finally:
            client.close()


def test_old_firmware_without_travel_is_refused() -> None:
    # Firmware 1 reset its only count on ZERO: the host cannot keep the limit with it.
    sink = _Sink()
    with _emulator() as emulator:
        controller = emulator.controller
        original = controller.handle

        def old_firmware(line: str, time_s: float) -> list[str]:
            if line.strip().upper().startswith("TRAVEL"):
                return [f"ERR UNKNOWN command {line.split()[0]!r}"]
            return original(line, time_s)

        controller.handle = old_firmware  # type: ignore[method-assign]
        client = _client(emulator, sink)
        try:
            with pytest.raises(DeviceError, match=r"no answer to TRAVEL\? .*update its firmware"):
                client.move(10)
            assert sink.moves_sent() == []
        finally:
            client.close()


def test_unopenable_port_is_a_device_error() -> None:
    client = MotorClient(MotorConfig(serial_url="/dev/does-not-exist-scanpipe"), _Sink())
    with pytest.raises(DeviceError, match="cannot open"):
        client.connect()


# -- property: no sequence of MOVE / ZERO / reconnect passes the limit -------------------------

LIMIT = 600
_actions = st.lists(st.one_of(
    st.tuples(st.just("move"), st.integers(-900, 900)),  # through the client's check
    st.tuples(st.just("raw"), st.integers(-900, 900)),   # straight to the controller
    st.tuples(st.just("zero"), st.just(0)),
    st.tuples(st.just("reconnect"), st.just(0)),
), min_size=1, max_size=12)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(actions=_actions)
def test_no_command_sequence_passes_the_limit(actions: list[tuple[str, int]]) -> None:
    sink = _Sink()
    with _emulator(pulse_limit=LIMIT) as emulator:
        client = _client(emulator, sink, pulse_limit=LIMIT)
        try:
            for kind, pulses in actions:
                if kind == "zero":
                    client.zero()
                elif kind == "reconnect":
                    client.close()
                    client = _client(emulator, sink, pulse_limit=LIMIT)
                else:
                    count = client.query_position().step_count  # fresh: the check uses it
                    start = _absolute(emulator)
                    allowed = 0 <= start + pulses <= LIMIT
                    if kind == "move":
                        try:
                            client.move(pulses)
                        except DeviceError:
                            assert not allowed
                            continue
                        accepted = True
                    else:
                        accepted = client.command(f"MOVE {pulses:+d}").ok
                    assert accepted == allowed
                    if accepted and pulses:
                        assert client.wait_for_state(
                            lambda s: not s.moving and s.step_count == count + pulses,  # noqa: B023
                            5.0) is not None
                assert 0 <= _absolute(emulator) <= LIMIT
        finally:
            client.close()
    moves = emulator.controller.platform.timeline().moves
    assert all(0 <= m.from_steps <= LIMIT and 0 <= m.target_steps <= LIMIT for m in moves)
