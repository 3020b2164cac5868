"""The live view as a Foxglove client sees it: a real ``Daemon`` (its sockets, threads and
loop) on the in-process fake devices of ``test_frame_errors`` with ``[live_view]`` on, and a
plain ``websockets`` client that speaks the Foxglove WebSocket protocol (serverInfo,
advertise, subscribe, binary message frames). The pose, the particles and the map are decoded
with ``mcap_protobuf``'s decoder built from the schema the server advertised, not with the
encoders that made them. Nothing is handed to the live view while no client watches; a client
that vanishes without closing does not hurt the daemon; a port in use is reported in the
status and the daemon goes on; bad settings are one line each."""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")
websockets = pytest.importorskip("websockets")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_frame_errors import FPS, _Head, _Odometry, _request  # noqa: E402
from test_localizer import _config, _world  # noqa: E402
from test_recording_daemon import _Camera8, _poses  # noqa: E402

from services.config import ServiceConfig, check_config  # noqa: E402
from services.daemon import Daemon, DeviceFactories  # noqa: E402
from services.recording.channels import TOPICS  # noqa: E402
from services.recording.live_view import (  # noqa: E402
    LIVE_TOPICS,
    LiveView,
    LiveViewConfig,
    MapScene,
    extent_outline,
)

SUBPROTOCOL = "foxglove.sdk.v1"


def _daemon(tmp_path: Path, port: int = 0) -> tuple[Daemon, zmq.Context[Any], str, str]:
    m, _, _ = _world()
    pub, rep = f"ipc://{tmp_path}/pub", f"ipc://{tmp_path}/rep"
    cfg = ServiceConfig(
        devices={"camera": {"kind": "sim", "sim": {"fps": FPS}}},
        localizer=_config(),
        active_vision={"enabled": False},
        endpoints={"pub": pub, "rep": rep, "relay": {"enabled": False}},
        persistence={"state_file": str(tmp_path / "state.json"), "restore": False},
        publish={"truth": False},
        live_view={"enabled": True, "port": port, "particles_rate_hz": 5.0},
    )
    ctx: zmq.Context[Any] = zmq.Context()
    factories = DeviceFactories(camera=_Camera8, head=_Head, odometry=_Odometry)
    scene = MapScene(m.poses, extent_outline(m.poses), "survey extent")
    live = LiveView(cfg.live_view, scene)
    return Daemon(cfg, m, device_factories=factories, context=ctx, live_view=live), ctx, pub, rep


class _Running:
    def __init__(self, tmp_path: Path, port: int = 0) -> None:
        self.daemon, self.ctx, self.pub, self.rep = _daemon(tmp_path, port)
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"pose")
        self.daemon.start()
        self.loop = threading.Thread(target=self.daemon.run, name="loop")
        self.loop.start()
        self.sub.connect(self.pub)

    def status(self) -> dict[str, Any]:
        return _request(self.ctx, self.rep, {"cmd": "status"})["status"]

    def stop(self) -> None:
        self.daemon.request_stop()
        self.loop.join(20)
        self.sub.close(0)
        self.ctx.term()


@pytest.fixture
def running(tmp_path: Path) -> Iterator[_Running]:
    r = _Running(tmp_path)
    try:
        yield r
    finally:
        r.stop()


def _decoder(channel: dict[str, Any]) -> Any:
    """A protobuf decoder from the advertised schema (base64 FileDescriptorSet)."""
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
    schema = Schema(id=channel["id"], name=channel["schemaName"], encoding="protobuf",
                    data=base64.b64decode(channel["schema"]))
    decode = DecoderFactory().decoder_for("protobuf", schema)
    assert decode is not None
    return decode


async def _advertised(ws: Any, topics: set[str], timeout: float = 5.0) -> dict[str, dict[str, Any]]:
    """serverInfo first, then advertise messages until every topic in ``topics`` came."""
    info = json.loads(await asyncio.wait_for(ws.recv(), timeout))
    assert info["op"] == "serverInfo" and info["name"] == "lino-loc"
    channels: dict[str, dict[str, Any]] = {}
    deadline = time.monotonic() + timeout
    while not topics <= set(channels) and time.monotonic() < deadline:
        msg = await asyncio.wait_for(ws.recv(), timeout)
        if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
            channels.update({c["topic"]: c for c in json.loads(msg)["channels"]})
    return channels


async def _collect(ws: Any, by_sub: dict[int, str], want: set[str], timeout: float = 15.0) -> dict[str, list[tuple[int, bytes]]]:
    """Binary message frames (opcode 1, u32 subscription id, u64 log time, payload) by topic,
    until every topic in ``want`` has at least 3 (the map: 1)."""
    got: dict[str, list[tuple[int, bytes]]] = {t: [] for t in by_sub.values()}
    deadline = time.monotonic() + timeout

    def enough() -> bool:
        return all(len(got[t]) >= (1 if t.startswith("/map/") else 3) for t in want)

    while not enough() and time.monotonic() < deadline:
        try:
            msg = await asyncio.wait_for(ws.recv(), max(0.05, deadline - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(msg, bytes) and msg[0] == 0x01:
            sub_id, log_ns = struct.unpack_from("<IQ", msg, 1)
            got[by_sub[sub_id]].append((log_ns, msg[13:]))
    return got


def test_a_foxglove_client_subscribes_receives_and_decodes_the_pose_and_the_particles(running: _Running) -> None:
    _poses(running.sub, 5)
    live = running.daemon.live
    assert live.queued == 0 and live.messages == 0  # nobody watched: nothing handed over
    st = running.status()["live_view"]
    assert st["serving"] and st["error"] is None and st["clients"] == 0
    port = live.port
    assert st["address"] == f"ws://127.0.0.1:{port}"
    want = {"/pose", "/particles", "/pose/ellipse", "/tf", "/map/survey", "/map/outline"}

    async def client() -> tuple[dict[str, dict[str, Any]], dict[str, list[tuple[int, bytes]]], dict[str, Any]]:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            channels = await _advertised(ws, set(LIVE_TOPICS))
            subs = [{"id": i + 1, "channelId": channels[t]["id"]} for i, t in enumerate(sorted(want))]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            got = await _collect(ws, {s["id"]: t for s, t in zip(subs, sorted(want), strict=True)}, want)
            status = await asyncio.to_thread(running.status)
            return channels, got, status

    channels, got, status = asyncio.run(client())
    assert set(channels) == set(LIVE_TOPICS)
    for topic, ch in channels.items():
        assert ch["schemaName"] == TOPICS[topic].schema_name and ch["encoding"] == TOPICS[topic].encoding
    assert status["live_view"]["clients"] == 1 and set(status["live_view"]["topics"]) == want
    for topic in want:
        assert got[topic], f"nothing received on {topic}"

    pose = _decoder(channels["/pose"])
    poses = [pose(data) for _, data in got["/pose"]]
    for (log_ns, _), p in zip(got["/pose"], poses, strict=True):
        assert p.frame_id == "map"
        assert log_ns == p.timestamp.seconds * 1_000_000_000 + p.timestamp.nanos
        q = p.pose.orientation
        assert q.x == 0.0 and q.y == 0.0 and abs(q.z**2 + q.w**2 - 1.0) < 1e-9
        assert -1.0 <= p.pose.position.x <= 7.0 and -1.0 <= p.pose.position.y <= 4.0
    stamps = [p.timestamp.seconds + 1e-9 * p.timestamp.nanos for p in poses]
    assert stamps == sorted(stamps) and abs(stamps[-1] - time.time()) < 10.0

    particles = _decoder(channels["/particles"])
    sets = [particles(data) for _, data in got["/particles"]]
    assert all(s.frame_id == "map" and 0 < len(s.poses) <= 500 for s in sets)
    spread = np.array([[q.position.x, q.position.y] for q in sets[-1].poses])
    assert np.all(np.isfinite(spread)) and spread.std(axis=0).max() > 0.0
    # throttled to particles_rate_hz = 5 by the frames' stamps (20 fps)
    t = np.array([ns for ns, _ in got["/particles"]]) * 1e-9
    assert np.all(np.diff(t) >= 0.2 - 1e-6)

    scene = _decoder(channels["/map/survey"])
    survey = scene(got["/map/survey"][0][1])
    assert survey.entities[0].id == "survey" and survey.entities[0].frame_id == "map"
    assert len(survey.entities[0].spheres) == len(np.unique(running.daemon.localizer.map.poses[:, :2], axis=0))
    outline = _decoder(channels["/map/outline"])(got["/map/outline"][0][1])
    assert outline.entities[0].id == "outline" and len(outline.entities[0].lines[0].points) == 8
    ellipse = _decoder(channels["/pose/ellipse"])(got["/pose/ellipse"][-1][1])
    assert ellipse.entities[0].id == "pose_ellipse"
    tf = _decoder(channels["/tf"])
    frames = {(m.parent_frame_id, m.child_frame_id): m for m in (tf(d) for _, d in got["/tf"])}
    assert set(frames) == {("map", "base_link"), ("base_link", "camera")}  # the head's pan
    head = frames[("base_link", "camera")].rotation
    assert head.x == 0.0 and head.y == 0.0 and abs(head.z**2 + head.w**2 - 1.0) < 1e-9


def test_the_truth_goes_live_to_a_subscribed_client(running: _Running) -> None:
    port = running.daemon.live.port
    relay = running.daemon._truth_tap()  # what the truth relay calls (simulation)
    assert relay is not None
    truth = {"v": 1, "stamp": time.time(), "frame_id": "map", "pose": {"x": 1.5, "y": 0.5, "theta": 0.25}}

    async def client() -> dict[str, list[tuple[int, bytes]]]:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            channels = await _advertised(ws, {"/truth/pose"})
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 3, "channelId": channels["/truth/pose"]["id"]}]}))
            await asyncio.sleep(0.3)
            for _ in range(3):
                relay(json.dumps(truth).encode())
            got = await _collect(ws, {3: "/truth/pose"}, {"/truth/pose"}, timeout=5.0)
            return {"channel": channels["/truth/pose"], **got}  # type: ignore[dict-item]

    got = asyncio.run(client())
    assert len(got["/truth/pose"]) == 3
    p = _decoder(got["channel"])(got["/truth/pose"][0][1])  # type: ignore[arg-type]
    assert p.frame_id == "map" and (p.pose.position.x, p.pose.position.y) == (1.5, 0.5)


def test_a_client_that_vanishes_without_closing_does_not_hurt_the_daemon(running: _Running) -> None:
    port = running.daemon.live.port

    async def vanish() -> int:
        ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL])
        channels = await _advertised(ws, {"/pose", "/camera/image"})
        subs = [{"id": 1, "channelId": channels["/pose"]["id"]},
                {"id": 2, "channelId": channels["/camera/image"]["id"]}]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        got = await _collect(ws, {1: "/pose", 2: "/camera/image"}, {"/pose", "/camera/image"})
        ws.transport.abort()  # no close frame: the TCP connection is reset
        return len(got["/pose"])

    assert asyncio.run(vanish()) >= 3
    _poses(running.sub, 20)  # the loop goes on
    deadline = time.monotonic() + 5.0
    while running.status()["live_view"]["clients"] and time.monotonic() < deadline:
        time.sleep(0.1)
    st = running.status()
    assert st["live_view"]["clients"] == 0 and st["live_view"]["serving"], st["live_view"]
    assert st["update_errors"] == 0
    sent = running.daemon.live.messages
    _poses(running.sub, 5)
    assert running.daemon.live.messages == sent  # nobody watching: nothing sent

    async def again() -> int:  # a new client is served as before
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
            channels = await _advertised(ws, {"/pose"})
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 7, "channelId": channels["/pose"]["id"]}]}))
            return len((await _collect(ws, {7: "/pose"}, {"/pose"}))["/pose"])

    assert asyncio.run(again()) >= 3


def test_a_port_in_use_is_reported_in_the_status_and_the_daemon_goes_on(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen(1)
    port = blocker.getsockname()[1]
    caplog.set_level(logging.WARNING, logger="lino_loc.service.live_view")
    r = _Running(tmp_path, port)
    try:
        _poses(r.sub, 10)
        st = r.status()["live_view"]
        assert not st["serving"] and st["address"] == f"ws://127.0.0.1:{port}"
        assert st["error"] is not None and "in use" in st["error"], st
        assert r.loop.is_alive() and r.status()["update_errors"] == 0
        assert any("live view not served" in rec.message for rec in caplog.records)
    finally:
        r.stop()
        blocker.close()


def test_a_host_off_loopback_is_served_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="lino_loc.service.live_view")
    live = LiveView(LiveViewConfig(enabled=True, host="0.0.0.0", port=0))
    live.start()
    try:
        assert live.info() is not None and live.info().serving
        assert any("without authentication" in r.message for r in caplog.records)
    finally:
        live.close()
    assert LiveViewConfig().host == "127.0.0.1" and not LiveViewConfig().enabled
    assert LiveView.off().info() is None


@pytest.mark.parametrize(("body", "key"), [
    ("port = 70000", "live_view.port"),
    ('host = "not a host"', "live_view.host"),
    ('host = "ws://robot:8765"', "live_view.host"),
    ('enabled = "maybe"', "live_view.enabled"),
    ("particles_rate_hz = -1", "live_view.particles_rate_hz"),
    ("colour = 1", "live_view.colour"),
])
def test_bad_live_view_settings_are_one_line_naming_the_key(tmp_path: Path, body: str, key: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f"[live_view]\n{body}\n")
    problems = [p for p in check_config(path) if "live_view" in p]
    assert len(problems) == 1 and key in problems[0] and "\n" not in problems[0], problems


def test_the_simulated_service_enables_the_live_view_on_loopback() -> None:
    cfg = ServiceConfig.simulated_defaults()
    assert cfg.live_view.enabled and cfg.live_view.host == "127.0.0.1" and cfg.live_view.port == 8765
    assert not ServiceConfig().live_view.enabled


def test_a_recording_carries_the_map_drawing_at_the_start_of_each_part(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from services.recording.recorder import Recorder, RecordingConfig

    m, _, _ = _world()
    cfg = ServiceConfig.simulated_defaults()
    scene = MapScene.of(m, cfg)  # the office's walls and boxes
    assert scene.outline_what == "walls" and scene.outline.shape[1:] == (2, 2) and len(scene.outline) >= 4
    path = tmp_path / "map.mcap"
    rec = Recorder(RecordingConfig(path=path), {"seed": "1"}, scene=scene)
    rec.start()
    rec.close()
    with open(path, "rb") as f:
        got = {ch.topic: msg for _, ch, _, msg in
               make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                   topics=["/map/survey", "/map/outline"])}
    assert set(got) == {"/map/survey", "/map/outline"}
    lines = got["/map/outline"].entities[0].lines[0]
    assert len(lines.points) == 2 * len(scene.outline)
    assert got["/map/outline"].entities[0].metadata[0].value == "walls"
    assert got["/map/survey"].entities[0].id == "survey"


def test_the_committed_foxglove_layout_is_the_generated_one_and_opens_every_channel() -> None:
    from services.messages import PoseMessage
    from services.recording.foxglove_layout import LAYOUT_FILE, layout, layout_text

    assert LAYOUT_FILE.read_text(encoding="utf-8") == layout_text(), (
        "run python -m services.recording.foxglove_layout")
    lay = layout()
    assert set(lay) == {"configById", "globalVariables", "userNodes", "playbackConfig", "layout"}
    panels = lay["configById"]

    def leaves(node: Any) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert set(node) == {"first", "second", "direction", "splitPercentage"}
        assert node["direction"] in ("row", "column") and 0 < node["splitPercentage"] < 100
        return leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(lay["layout"])) == sorted(panels)
    assert {p.split("!")[0] for p in panels} == {"3D", "Image", "StateTransitions", "Plot", "RawMessages"}
    three_d = panels["3D!map"]
    assert three_d["followTf"] == "map"
    drawn = {"/pose", "/pose/ellipse", "/particles", "/truth/pose", "/map/survey", "/map/outline"}
    assert set(three_d["topics"]) == drawn and all(three_d["topics"][t]["visible"] for t in drawn)
    assert three_d["layers"]["grid"]["layerId"] == "foxglove.Grid"
    assert panels["Image!camera"]["imageMode"]["imageTopic"] == "/camera/image"
    used = drawn | {"/camera/image", "/pose/estimate", "/status"}
    assert used <= set(LIVE_TOPICS) and used <= set(TOPICS)
    for path in (panels["StateTransitions!state"]["paths"] + panels["Plot!quality"]["paths"]):
        topic, field = path["value"].split(".", 1)
        assert topic == "/pose/estimate" and field in PoseMessage.model_fields
    assert panels["RawMessages!status"]["topicPath"] == "/status"



def test_the_truth_goes_to_both_the_recorder_and_the_live_view(tmp_path: Path) -> None:
    from services.recording.recorder import Recorder, RecordingConfig

    m, _, _ = _world()
    cfg = ServiceConfig(devices={"camera": {"kind": "sim"}}, localizer=_config(),
                        endpoints={"pub": f"ipc://{tmp_path}/p", "rep": f"ipc://{tmp_path}/r"},
                        live_view={"enabled": True})
    live = LiveView(cfg.live_view)
    live._listener.topics = frozenset({"/truth/pose"})  # as a subscribed client makes it
    rec = Recorder(RecordingConfig(path=tmp_path / "t.mcap"))
    ctx: zmq.Context[Any] = zmq.Context()
    try:
        d = Daemon(cfg, m, device_factories=DeviceFactories(camera=_Camera8, head=_Head, odometry=_Odometry),
                   context=ctx, recorder=rec, live_view=live)
        tap = d._truth_tap()
        assert tap is not None
        tap(b'{"v":1,"stamp":1.0,"frame_id":"map","pose":{"x":0,"y":0,"theta":0}}')
        assert live.queued == 1 and rec._queue.qsize() == 1
    finally:
        ctx.term()
