"""The simulator's fault control: request model and replies, the controller against a real
(not started) simulated robot, the socket server, and the emulators' new fault switches."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator

import pytest
import zmq

from drivers.dynamixel_head import DynamixelHead, HeadConfig
from drivers.dynamixel_protocol import XAddr
from drivers.odometry_protocol import parse_line
from drivers.sim.dynamixel_emulator import DynamixelBusEmulator
from drivers.sim.fault_control import (
    FAULTS,
    MAX_REQUEST_BYTES,
    FaultController,
    FaultServer,
    RequestError,
    check_loopback,
    parse_request,
    respond,
)
from drivers.sim.odometry_emulator import OdometryBoardEmulator
from drivers.sim.robot import SimRobot, SimRobotConfig
from lino_loc.errors import LinoLocError


def test_every_fault_parses_with_its_defaults() -> None:
    assert set(FAULTS) == {
        "head_no_reply", "head_crc", "head_hardware_error", "head_unplug", "odometry_crc", "odometry_garbage",
        "odometry_drop", "odometry_split", "odometry_unplug", "camera_stall", "camera_unplug", "camera_malformed",
    }
    for name in FAULTS:
        req = parse_request(json.dumps({"cmd": "inject", "fault": name}).encode())
        assert req.fault == name and req.duration_s == 2.0  # type: ignore[attr-defined]
    req = parse_request(b'{"cmd": "inject", "fault": "odometry_garbage", "duration_s": 0.5, "fraction": 0.25, "bytes": 7}')
    assert (req.duration_s, req.fraction, req.bytes) == (0.5, 0.25, 7)  # type: ignore[attr-defined]
    for cmd in ("clear", "status", "ping"):
        assert parse_request(json.dumps({"cmd": cmd}).encode()).cmd == cmd  # type: ignore[union-attr]
    assert parse_request(b'{"cmd": "clear", "fault": "camera_stall"}').fault == "camera_stall"  # type: ignore[union-attr]


@pytest.mark.parametrize(
    "raw, words",
    [
        (b"{nope", "not JSON"),
        (b"\xff\xfe", "not UTF-8"),
        (b"[1, 2]", "JSON object"),
        (b"[" * 100_000, "not JSON"),
        (b'{"cmd": 3}', "cmd: must be one of"),
        (b'{"cmd": "self_destruct"}', '"self_destruct"'),
        (b'{"cmd": "inject"}', "fault: must be one of"),
        (b'{"cmd": "inject", "fault": "meteor"}', '"meteor"'),
        (b'{"cmd": "inject", "fault": "head_crc", "duration_s": 0}', "duration_s"),
        (b'{"cmd": "inject", "fault": "head_crc", "duration_s": 1e9}', "duration_s"),
        (b'{"cmd": "inject", "fault": "head_crc", "duration_s": NaN}', "duration_s"),
        (b'{"cmd": "inject", "fault": "head_crc", "duration_s": "long"}', "duration_s"),
        (b'{"cmd": "inject", "fault": "head_crc", "fraction": 1.5}', "fraction"),
        (b'{"cmd": "inject", "fault": "head_no_reply", "servo": "wheel"}', "servo"),
        (b'{"cmd": "inject", "fault": "head_hardware_error", "bits": 256}', "bits"),
        (b'{"cmd": "inject", "fault": "camera_stall", "fraction": 0.5}', "fraction: Extra inputs"),
        (b'{"cmd": "clear", "fault": "meteor"}', "clear: fault"),
        (b'{"cmd": "lights"}', "lighting"),
        (b'{"cmd": "ping", "x": 1}', "x: Extra inputs"),
    ],
)
def test_bad_requests_get_one_line_naming_the_field(raw: bytes, words: str) -> None:
    with pytest.raises(RequestError) as exc:
        parse_request(raw)
    msg = str(exc.value)
    assert words in msg and "\n" not in msg and len(msg) < 400, msg


def test_loopback_only() -> None:
    for ok in ("tcp://127.0.0.1:*", "tcp://127.0.0.2:5000", "tcp://localhost:1", "tcp://[::1]:5", "ipc:///tmp/x"):
        assert check_loopback(ok) == ok
    for bad in ("tcp://0.0.0.0:5000", "tcp://*:5000", "tcp://192.168.1.2:1", "tcp://eth0:1", "udp://x"):
        with pytest.raises(LinoLocError, match="not a loopback endpoint"):
            check_loopback(bad)


@pytest.fixture()
def robot() -> SimRobot:
    """A real simulated robot, not started: its emulators and camera switches are what change."""
    return SimRobot(SimRobotConfig(width=32, height=24, drive=False))


def _inject(control: FaultController, **kw: object) -> dict:
    return respond(control, [json.dumps({"cmd": "inject", **kw}).encode()])


def test_controller_applies_each_fault_and_ends_it_on_time(robot: SimRobot) -> None:
    switched: list[str] = []
    control = FaultController(robot, switched.append)
    head, odo = robot.head, robot.odometry
    assert _inject(control, fault="head_hardware_error", servo="tilt")["ok"]  # one-shot
    assert head.register(2, XAddr.HARDWARE_ERROR_STATUS) == 0x20 and head.servos[2].persistent_error == 0
    assert respond(control, [b'{"cmd": "clear"}'])["cleared"] == ["head_hardware_error"]
    r = _inject(control, fault="head_no_reply", servo="tilt", duration_s=1.0)
    assert r["ok"] and r["active"] == {"head_no_reply": 1.0} and r["until"] > time.time()
    assert head.servos[2].no_reply and not head.servos[1].no_reply
    assert _inject(control, fault="head_crc", fraction=0.3)["ok"]
    assert head.corruption_rate == 0.3
    assert _inject(control, fault="head_hardware_error", bits=4, persistent=True)["ok"]
    assert head.register(1, XAddr.HARDWARE_ERROR_STATUS) == 4 and head.servos[1].persistent_error == 4
    for name, kind in (("odometry_crc", "corrupt"), ("odometry_garbage", "garbage"), ("odometry_drop", "drop"),
                       ("odometry_split", "split")):
        assert _inject(control, fault=name, fraction=0.5)["ok"]
        assert odo.fault_rate(kind) == 0.5
    odo.start(stream=False)
    try:
        assert _inject(control, fault="odometry_unplug")["ok"] and not odo.connected
        for name in ("camera_stall", "camera_unplug"):
            assert _inject(control, fault=name)["ok"]
        assert _inject(control, fault="camera_malformed", fraction=0.2)["ok"]
        assert robot.camera_faults() == {"stall": 1.0, "unplug": 1.0, "malformed": 0.2}
        assert respond(control, [b'{"cmd": "lights", "lighting": "bulb"}'])["ok"] and switched == ["bulb"]
        assert "unknown lighting" in respond(control, [b'{"cmd": "lights", "lighting": "disco"}'])["error"]
        status = respond(control, [b'{"cmd": "status"}'])
        assert status["ok"] and len(status["active"]) == 11
        control.expire(time.monotonic() + 1.5)  # head_no_reply (1 s) is over, the others (2 s) not
        assert not head.servos[2].no_reply and "head_no_reply" not in control.active()
        assert head.corruption_rate == 0.3
        control.expire(time.monotonic() + 2.5)
        assert control.active() == {} and control.next_deadline() is None
        assert head.corruption_rate == 0.0 and head.servos[1].persistent_error == 0
        assert all(odo.fault_rate(k) == 0.0 for k in ("corrupt", "garbage", "drop", "split"))
        assert odo.connected and robot.camera_faults() == {}
    finally:
        odo.stop()


def test_reinjecting_replaces_and_clear_ends(robot: SimRobot) -> None:
    control = FaultController(robot)
    robot.odometry.start(stream=False)
    try:
        assert _inject(control, fault="odometry_unplug", duration_s=1.0)["ok"]
        assert _inject(control, fault="odometry_unplug", duration_s=5.0)["active"]["odometry_unplug"] > 4.0
        assert not robot.odometry.connected  # still out (not plugged back in between)
        assert _inject(control, fault="head_crc", fraction=0.5)["ok"]
        assert _inject(control, fault="head_crc", fraction=0.1)["ok"] and robot.head.corruption_rate == 0.1
        r = respond(control, [b'{"cmd": "clear", "fault": "head_crc"}'])
        assert r["cleared"] == ["head_crc"] and robot.head.corruption_rate == 0.0
        r = respond(control, [b'{"cmd": "clear"}'])
        assert r["cleared"] == ["odometry_unplug"] and r["active"] == {} and robot.odometry.connected
    finally:
        robot.odometry.stop()


def test_refusals_and_internal_errors_are_one_line_replies(robot: SimRobot) -> None:
    control = FaultController(robot)  # no lights; the head has no stable link
    assert "stable head link" in _inject(control, fault="head_unplug")["error"]
    assert "cannot switch its lights" in respond(control, [b'{"cmd": "lights", "lighting": "bulb"}'])["error"]
    assert "one frame" in respond(control, [b'{"cmd": "ping"}', b"x"])["error"]

    def broken(kind: str, on: bool, fraction: float = 1.0) -> None:
        raise RuntimeError("camera on fire\nsecond line")

    robot.set_camera_fault = broken  # type: ignore[method-assign]
    r = _inject(control, fault="camera_stall")
    assert r == {"ok": False, "error": "internal error: RuntimeError: camera on fire"}
    assert control.active() == {}


def test_server_answers_on_a_socket_and_survives_abuse(robot: SimRobot) -> None:
    ctx = zmq.Context()
    control = FaultController(robot)
    server = FaultServer(control, ctx, "tcp://127.0.0.1:*")
    endpoint = server.start()
    try:
        def ask(*frames: bytes) -> dict:
            s = ctx.socket(zmq.REQ)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(endpoint)
            try:
                s.send_multipart(list(frames))
                return json.loads(s.recv()) if s.poll(3000) else {"timeout": True}
            finally:
                s.close(0)

        assert ask(b'{"cmd": "ping"}') == {"ok": True, "cmd": "ping", "active": {}}
        assert ask(b"x" * (MAX_REQUEST_BYTES + 1)) == {"timeout": True}  # dropped by ZMQ_MAXMSGSIZE
        assert ask(b"", b"") ["ok"] is False
        assert ask(b'{"cmd": "inject", "fault": "head_crc", "duration_s": 0.1}')["ok"]
        time.sleep(0.3)  # the server ends it on time, unasked
        assert robot.head.corruption_rate == 0.0
        assert ask(b'{"cmd": "status"}')["active"] == {}
    finally:
        server.stop()
        ctx.term()
    with pytest.raises(LinoLocError, match="not a loopback"):
        FaultServer(control, zmq.Context.instance(), "tcp://0.0.0.0:*")


# the emulators' switches ---------------------------------------------------------------------


@pytest.fixture()
def bus(tmp_path: os.PathLike[str]) -> Iterator[DynamixelBusEmulator]:
    with DynamixelBusEmulator((1, 2), boot_time=0.02, link=os.path.join(tmp_path, "head")) as e:
        yield e


def test_persistent_hardware_error_returns_after_reboots_until_cleared(bus: DynamixelBusEmulator) -> None:
    head = DynamixelHead(HeadConfig(port=bus.port, min_read_interval=0.0, boot_wait=0.2, max_reboots=100))
    assert head.open()
    try:
        bus.set_hardware_error(1, 0x20, persistent=True)
        for _ in range(3):
            head.read()
            time.sleep(0.05)
        assert head.health().counters["reboots"] >= 2  # rebooted, and the fault came back
        bus.clear_hardware_error(1)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and (head.read().stale or bus.register(1, XAddr.HARDWARE_ERROR_STATUS)):
            time.sleep(0.05)
        assert bus.register(1, XAddr.HARDWARE_ERROR_STATUS) == 0 and bus.register(1, XAddr.TORQUE_ENABLE) == 1
    finally:
        head.close()


def test_bus_unplug_removes_the_link_and_the_adapter_finds_it_again(bus: DynamixelBusEmulator) -> None:
    head = DynamixelHead(HeadConfig(port=bus.port, min_read_interval=0.0, reconnect_backoff_max=0.05))
    assert head.open()
    try:
        bus.disconnect()
        assert not os.path.lexists(bus.port) and not bus.connected
        time.sleep(0.1)
        head.read()
        assert head.health().state.value != "ok"
        bus.reconnect()
        assert os.path.islink(bus.port)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and head.read().stale:
            time.sleep(0.05)
        assert not head.read().stale and head.health().counters["reconnects"] >= 1
    finally:
        head.close()


def test_bus_corruption_rate_is_a_share_of_replies() -> None:
    # No retries, so each corrupt reply is one stale read; a long packet timeout, so that a
    # loaded machine's slow emulator thread is not counted as corruption (CI failed open()
    # at 34 ms with the load at 9 on 2 cores).
    with DynamixelBusEmulator((1, 2), seed=3) as emu:
        head = DynamixelHead(HeadConfig(port=emu.port, min_read_interval=0.0, retries=0, latency_timer_ms=250.0))
        assert head.open()
        try:
            emu.set_corruption_rate(0.5)
            stale = sum(head.read().stale for _ in range(40))
            assert 5 <= stale <= 38 and head.health().counters["crc_errors"] >= stale, stale  # some fail
            with pytest.raises(ValueError, match="rate"):
                emu.set_corruption_rate(1.5)
        finally:
            head.close()


def _stream(emu: OdometryBoardEmulator, n: int) -> bytes:
    """At least n lines' worth of what the board sends (read on the slave side)."""
    slave = os.open(emu.port, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    buf = b""
    try:
        deadline = time.monotonic() + 5.0
        while buf.count(b"$ODO") < n + 1 and time.monotonic() < deadline:
            try:
                buf += os.read(slave, 4096)
            except BlockingIOError:
                time.sleep(0.01)
    finally:
        os.close(slave)
    return buf


@pytest.mark.parametrize("kind", ["corrupt", "garbage"])
def test_odometry_fault_rate_hits_every_line_at_one(kind: str) -> None:
    emu = OdometryBoardEmulator(rate_hz=200.0, seed=1)
    emu.set_fault_rate(kind, 1.0, garbage_bytes=5)
    with emu:
        sentences = _stream(emu, 20).split(b"$")[1:-1]
        assert len(sentences) >= 20
        if kind == "corrupt":
            assert all(_bad(b"$" + s[: s.index(b"*") + 3]) for s in sentences)
        else:  # 5 bytes of noise after each line's CR LF, before the next '$'
            assert all(len(s) - (s.index(b"*") + 5) == 5 for s in sentences)
        emu.set_fault_rate(kind, 0.0)
        time.sleep(0.05)
        sentences = _stream(emu, 10).split(b"$")[2:-1]
        assert not any(_bad(b"$" + s[: s.index(b"*") + 3]) for s in sentences)
        assert all(s.endswith(b"\r\n") for s in sentences)
        with pytest.raises(ValueError, match="unknown line fault"):
            emu.set_fault_rate("fire", 0.5)


def _bad(line: bytes) -> bool:
    try:
        parse_line(line.strip())
    except ValueError:
        return True
    return False
