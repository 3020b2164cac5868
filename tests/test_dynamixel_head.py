"""DynamixelHead (real dynamixel_sdk) against the Protocol 2.0 bus emulator on a pty:
set-up, angle conversion and limits, motion, and every injected fault."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator

import dynamixel_sdk
import dynamixel_sdk.port_handler as sdk_port_handler
import pytest

import drivers.dynamixel_head as dh
from drivers.dynamixel_head import DynamixelHead, HeadConfig
from drivers.dynamixel_protocol import (
    HardwareError,
    XAddr,
    profile_velocity_to_rad_s,
    rad_s_to_profile_velocity,
    rad_to_tick,
)
from drivers.interfaces import HealthState, PanTiltHead
from drivers.sim.dynamixel_emulator import DynamixelBusEmulator


def make_config(port: str, **kw: object) -> HeadConfig:
    base: dict[str, object] = dict(
        port=port,
        latency_timer_ms=16.0,  # SDK default: 34 ms packet timeout, room for a loaded machine
        min_read_interval=0.0,
        profile_velocity=6.0,
        retries=2,
        boot_wait=0.5,
        reconnect_backoff_max=0.05,
    )
    base.update(kw)
    return HeadConfig(**base)  # type: ignore[arg-type]


@pytest.fixture()
def emu() -> Iterator[DynamixelBusEmulator]:
    with DynamixelBusEmulator((1, 2), boot_time=0.02) as e:
        yield e


@pytest.fixture()
def head(emu: DynamixelBusEmulator) -> Iterator[DynamixelHead]:
    h = DynamixelHead(make_config(emu.port))
    assert h.open(), h.health()
    yield h
    h.close()


def test_open_configures_servos(emu: DynamixelBusEmulator, head: DynamixelHead) -> None:
    assert isinstance(head, PanTiltHead)
    c = head.config
    assert sdk_port_handler.LATENCY_TIMER == 16.0
    assert emu.register(1, XAddr.MAX_POSITION_LIMIT) == rad_to_tick(c.pan_max)
    assert emu.register(1, XAddr.MIN_POSITION_LIMIT) == rad_to_tick(c.pan_min)
    assert emu.register(2, XAddr.MAX_POSITION_LIMIT) == rad_to_tick(c.tilt_max)
    assert emu.register(2, XAddr.MIN_POSITION_LIMIT) == rad_to_tick(c.tilt_min)
    for i in (1, 2):
        assert emu.register(i, XAddr.TORQUE_ENABLE) == 1
        assert emu.register(i, XAddr.PROFILE_VELOCITY) == rad_s_to_profile_velocity(6.0)
    assert head.health().state is HealthState.OK
    state = head.read()
    assert (state.pan, state.tilt, state.moving, state.stale) == (0.0, 0.0, False, False)


def test_profile_velocity_units() -> None:
    # 0.229 rev/min per unit: 1 rev/min = 2 pi / 60 rad/s
    assert rad_s_to_profile_velocity(2 * math.pi / 60 * 0.229 * 100) == 100
    assert profile_velocity_to_rad_s(100) == pytest.approx(100 * 0.229 * 2 * math.pi / 60)


def test_command_moves_at_profile_velocity(emu: DynamixelBusEmulator, head: DynamixelHead) -> None:
    t0 = time.monotonic()
    cmd = head.command(0.6, -0.3)
    assert (cmd.pan, cmd.tilt, cmd.clamped) == (0.6, -0.3, False)
    mid = head.read()
    assert mid.moving and not mid.stale
    state = head.wait_until_still(2.0, poll=0.005)
    elapsed = time.monotonic() - t0
    assert not state.moving
    assert state.pan == pytest.approx(0.6, abs=2 * math.pi / 4096)
    assert state.tilt == pytest.approx(-0.3, abs=2 * math.pi / 4096)
    # 0.6 rad at the profile velocity (6 rad/s after rounding to units) takes ~0.1 s
    v = profile_velocity_to_rad_s(rad_s_to_profile_velocity(6.0))
    assert 0.6 / v * 0.8 < elapsed < 0.6 / v + 1.0  # never faster than the profile
    assert emu.position_rad(1) == pytest.approx(state.pan, abs=1e-3)


def test_commands_are_clamped_to_limits(emu: DynamixelBusEmulator, head: DynamixelHead) -> None:
    cmd = head.command(10.0, -5.0)
    assert cmd.clamped
    assert (cmd.pan, cmd.tilt) == (head.limits.pan_max, head.limits.tilt_min)
    time.sleep(0.01)
    assert emu.register(1, XAddr.GOAL_POSITION) == rad_to_tick(head.limits.pan_max)
    assert emu.register(2, XAddr.GOAL_POSITION) == rad_to_tick(head.limits.tilt_min)
    assert head.health().counters["clamped"] == 1
    assert not head.command(0.1, 0.1).clamped


def test_no_reply_retries_then_degraded_not_exception(
    emu: DynamixelBusEmulator, head: DynamixelHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "READ_FAILURE_HOLD_S", 0.3)
    good = head.read()
    emu.set_no_reply(2)
    t0 = time.monotonic()
    state = head.read()  # must not raise
    assert time.monotonic() - t0 < 1.0
    assert state.stale
    assert state.tilt == good.tilt
    health = head.health()
    assert health.state is HealthState.DEGRADED
    assert "servo 2 (tilt)" in (health.last_error or "")
    assert health.counters["timeouts"] >= 3  # first try + 2 retries (+ the single read)
    assert health.counters["retries"] == 2
    emu.set_no_reply(2, False)
    t_back = time.monotonic()
    assert not head.read().stale
    # the failed read is reported for READ_FAILURE_HOLD_S of clean reads
    while time.monotonic() - t_back < 0.2:
        assert not head.read().stale
        assert head.health().state is HealthState.DEGRADED
        assert "servo 2 (tilt)" in (head.health().last_error or "")
        time.sleep(0.02)
    time.sleep(0.15)
    head.read()
    assert head.health().state is HealthState.OK


def test_all_silent_does_not_burn_a_core(emu: DynamixelBusEmulator, head: DynamixelHead) -> None:
    emu.set_no_reply(1)
    emu.set_no_reply(2)
    # The adapter works in the caller's thread: thread_time excludes the emulator's thread and
    # whatever else runs in this process.
    c0, w0 = time.thread_time(), time.monotonic()
    for _ in range(5):
        assert head.read().stale
    cpu, wall = time.thread_time() - c0, time.monotonic() - w0
    assert wall > 0.05  # the timeouts really happened
    # the same wait with the SDK as shipped (serial timeout 0) spins; compare on this machine
    port = dynamixel_sdk.PortHandler(emu.port)
    port.openPort()
    try:
        ph = dynamixel_sdk.PacketHandler(2.0)
        s0, t0 = time.thread_time(), time.monotonic()
        while time.monotonic() - t0 < 0.3:
            assert ph.ping(port, 1)[1] == dynamixel_sdk.COMM_RX_TIMEOUT
        spin = (time.thread_time() - s0) / (time.monotonic() - t0)
    finally:
        port.closePort()
    assert cpu / wall < 0.25 and cpu / wall < 0.5 * spin, (cpu / wall, spin)


def test_crc_error_is_retried(emu: DynamixelBusEmulator, head: DynamixelHead) -> None:
    emu.corrupt_replies(1)
    state = head.read()
    assert not state.stale
    h = head.health()
    assert h.counters["crc_errors"] == 1 and h.counters["retries"] == 1
    assert h.state is HealthState.OK  # a retry that succeeds loses nothing: only counted


def test_hardware_error_reboots_and_restores(
    emu: DynamixelBusEmulator, head: DynamixelHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "INCIDENT_HOLD_S", 0.3)
    head.command(0.2, 0.1)
    head.wait_until_still(1.0, poll=0.005)
    emu.set_hardware_error(2, HardwareError.OVERHEATING)
    state = head.read()  # must not raise
    assert state.tilt_error == HardwareError.OVERHEATING
    assert emu.instructions["REBOOT"] == 1
    h = head.health()
    assert h.counters["reboots"] == 1 and h.counters["hardware_errors"] == 1
    assert "servo 2 (tilt)" in (h.last_error or "") and "overheating" in (h.last_error or "")
    assert "rebooted" in (h.last_error or "")
    # the servo is back: torque on, profile velocity and goal restored
    assert emu.register(2, XAddr.HARDWARE_ERROR_STATUS) == 0
    assert emu.register(2, XAddr.TORQUE_ENABLE) == 1
    assert emu.register(2, XAddr.GOAL_POSITION) == rad_to_tick(0.1)
    assert emu.register(2, XAddr.PROFILE_VELOCITY) == rad_s_to_profile_velocity(6.0)
    after = head.read()
    assert after.tilt_error == 0 and not after.stale
    # the servo recovered at once, but the health says so for INCIDENT_HOLD_S
    assert head.health().state is HealthState.DEGRADED
    assert "overheating" in (head.health().last_error or "")
    time.sleep(0.35)
    head.read()
    assert head.health().state is HealthState.OK
    assert head.health().counters["reboots"] == 1


def test_a_one_off_hardware_error_shows_in_the_health_for_the_hold_time(
    emu: DynamixelBusEmulator, head: DynamixelHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "INCIDENT_HOLD_S", 0.4)
    emu.set_hardware_error(1, HardwareError.OVERLOAD)
    head.read()  # rebooted and restored: the hold starts
    t0 = time.monotonic()
    seen: list[HealthState] = []
    while time.monotonic() - t0 < 0.3:  # within the hold: every clean read still DEGRADED
        assert not head.read().stale
        h = head.health()
        seen.append(h.state)
        assert "servo 1 (pan)" in (h.last_error or "") and "overload" in (h.last_error or "")
        time.sleep(0.02)
    assert seen and set(seen) == {HealthState.DEGRADED}
    time.sleep(max(0.0, 0.45 - (time.monotonic() - t0)))
    head.read()
    assert head.health().state is HealthState.OK
    assert emu.instructions["REBOOT"] == 1 and head.health().counters["hardware_errors"] == 1


def test_a_hardware_error_at_open_is_not_reported_ok(
    emu: DynamixelBusEmulator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "INCIDENT_HOLD_S", 0.3)
    emu.set_hardware_error(2, HardwareError.OVERHEATING)
    head = DynamixelHead(make_config(emu.port))
    try:
        assert head.open()
        h = head.health()
        assert h.state is HealthState.DEGRADED and "servo 2 (tilt)" in (h.last_error or "")
        assert emu.instructions["REBOOT"] == 1 and emu.register(2, XAddr.TORQUE_ENABLE) == 1
        time.sleep(0.35)
        head.read()
        assert head.health().state is HealthState.OK
    finally:
        head.close()


def test_a_servo_given_up_at_open_is_reported_failed(emu: DynamixelBusEmulator) -> None:
    emu.set_hardware_error(1, HardwareError.OVERLOAD)
    head = DynamixelHead(make_config(emu.port, auto_reboot=False))
    try:
        head.open()
        h = head.health()
        assert h.state is HealthState.FAILED and "servo 1 (pan)" in (h.last_error or "")
        head.read()
        assert head.health().state is HealthState.FAILED
    finally:
        head.close()


def test_persistent_hardware_error_gives_up(emu: DynamixelBusEmulator) -> None:
    head = DynamixelHead(make_config(emu.port, max_reboots=1))
    assert head.open(), head.health()
    try:
        emu.set_hardware_error(1, HardwareError.OVERLOAD)
        head.read()
        assert head.health().counters["reboots"] == 1
        emu.set_hardware_error(1, HardwareError.OVERLOAD)
        head.read()
        head.read()
        h = head.health()
        assert h.counters["reboots"] == 1 and emu.instructions["REBOOT"] == 1
        assert h.state is HealthState.FAILED and "overload" in (h.last_error or "")
    finally:
        head.close()


def test_lost_torque_and_missed_goal_are_restored(
    emu: DynamixelBusEmulator, head: DynamixelHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "INCIDENT_HOLD_S", 0.3)
    head.command(0.3, 0.0)
    time.sleep(0.01)  # let the emulator take the sync write first
    with emu._lock:  # a brown-out on servo 1, a sync write missed by servo 2
        emu.servos[1].table[XAddr.TORQUE_ENABLE] = 0
        emu.servos[2].set(XAddr.GOAL_POSITION, 2100)
    head.read()
    h = head.health()
    assert h.counters["torque_restores"] == 1 and h.counters["goal_rewrites"] == 1
    assert emu.register(1, XAddr.TORQUE_ENABLE) == 1
    assert emu.register(2, XAddr.GOAL_POSITION) == rad_to_tick(0.0)
    head.read()  # clean, but both repairs are reported for INCIDENT_HOLD_S
    h = head.health()
    assert h.state is HealthState.DEGRADED and "servo 2 (tilt)" in (h.last_error or "")
    time.sleep(0.35)
    head.read()
    assert head.health().state is HealthState.OK


def test_missing_port_and_reconnect(tmp_path: os.PathLike[str]) -> None:
    link = os.path.join(tmp_path, "head")
    head = DynamixelHead(make_config(link))
    assert not head.open()  # no device: no exception
    assert head.health().state is HealthState.FAILED
    assert head.read().stale
    with DynamixelBusEmulator((1, 2), link=link):
        deadline = time.monotonic() + 2.0
        while head.read().stale and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not head.read().stale
        assert head.health().state is HealthState.OK
    # the device vanishes while open
    state = head.read()
    assert state.stale
    assert head.health().state is HealthState.FAILED
    with DynamixelBusEmulator((1, 2), link=link):
        deadline = time.monotonic() + 2.0
        while head.read().stale and time.monotonic() < deadline:
            time.sleep(0.02)
        assert head.health().state is HealthState.OK
        assert head.health().counters["reconnects"] >= 1
    head.close()


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        HeadConfig(pan_min=1.0, pan_max=0.5)
    with pytest.raises(ValueError):
        HeadConfig(baudrate=12345)
    with pytest.raises(ValueError):
        HeadConfig(pan_id=3, tilt_id=3)


def test_a_given_up_servo_gets_a_new_round_of_reboots_after_the_retry_time(
    emu: DynamixelBusEmulator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dh, "GIVEN_UP_RETRY_S", 0.3)
    monkeypatch.setattr(dh, "INCIDENT_HOLD_S", 0.2)
    head = DynamixelHead(make_config(emu.port, max_reboots=1))
    assert head.open(), head.health()
    try:
        emu.set_hardware_error(1, HardwareError.OVERLOAD)
        head.read()
        emu.set_hardware_error(1, HardwareError.OVERLOAD)  # back at once: given up
        head.read()
        assert head.health().state is HealthState.FAILED and emu.instructions["REBOOT"] == 1
        head.read()  # still within the retry time: no reboot, not counted again
        assert emu.instructions["REBOOT"] == 1 and head.health().counters["hardware_errors"] == 2
        time.sleep(0.35)
        head.read()  # cooled down: rebooted, the error cleared, torque restored
        assert emu.instructions["REBOOT"] == 2 and emu.register(1, XAddr.TORQUE_ENABLE) == 1
        head.read()
        h = head.health()  # failed -> degraded (the reboot, for INCIDENT_HOLD_S) -> ok
        assert h.state is HealthState.DEGRADED and "rebooted it" in (h.last_error or "")
        time.sleep(0.25)
        head.read()
        assert head.health().state is HealthState.OK
    finally:
        head.close()
