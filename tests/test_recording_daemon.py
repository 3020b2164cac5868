"""The daemon hands the recorder what its Localizer gets: a real ``Daemon`` (its sockets, its
threads, its loop) on the in-process fake devices of ``test_frame_errors`` and the tiny map of
``test_localizer``, recording; belief changes from the control socket go into the recording
in their place among the frames, and the replay of the recorded calls gives the daemon's
poses bit for bit, dead reckoning included. A recording that cannot be written (a bad path)
is reported in the status and the daemon goes on."""

from __future__ import annotations

import dataclasses
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

pytest.importorskip("mcap")
pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_frame_errors import FPS, _Camera, _Head, _Odometry, _request  # noqa: E402
from test_localizer import _config, _world  # noqa: E402

from services.config import ServiceConfig  # noqa: E402
from services.daemon import Daemon, DeviceFactories  # noqa: E402
from services.recording.recorder import Recorder, RecordingConfig  # noqa: E402
from services.recording.recording_reader import Recording, read_recording  # noqa: E402


class _Camera8(_Camera):
    """The fake camera's frames as a real camera gives them: 8-bit grey."""

    def read(self, timeout: float | None = None) -> Any:
        f = super().read(timeout)
        img = np.clip((np.asarray(f.left, dtype=np.float64) + 1.0) * 127.5, 0, 255).astype(np.uint8)
        return dataclasses.replace(f, left=img)


class _StallingCamera(_Camera8):
    """Frames for 1 s, none for the next 2 s (the daemon dead-reckons), then frames again."""

    def __init__(self) -> None:
        super().__init__()
        self.t0 = time.monotonic()

    def read(self, timeout: float | None = None) -> Any:
        if 1.0 < time.monotonic() - self.t0 < 3.0:
            time.sleep(0.05)
            return None
        return super().read(timeout)


def _daemon(tmp_path: Path, path: Path, camera: Any = None, rotate_mb: float = 1024.0) -> tuple[Daemon, zmq.Context[Any], str, str]:
    m, _, _ = _world()
    pub, rep = f"ipc://{tmp_path}/pub", f"ipc://{tmp_path}/rep"
    cfg = ServiceConfig(
        devices={"camera": {"kind": "sim", "sim": {"fps": FPS}}},
        localizer=_config(),
        active_vision={"enabled": False},
        endpoints={"pub": pub, "rep": rep, "relay": {"enabled": False}},
        persistence={"state_file": str(tmp_path / "state.json"), "restore": False},
        publish={"truth": False},
    )
    ctx: zmq.Context[Any] = zmq.Context()
    factories = DeviceFactories(camera=camera or _Camera8, head=_Head, odometry=_Odometry)
    recorder = Recorder(RecordingConfig(path=path, rotate_mb=rotate_mb), {"seed": "3"})
    return Daemon(cfg, m, device_factories=factories, context=ctx, recorder=recorder), ctx, pub, rep


def _poses(sub: zmq.Socket[Any], n: int, timeout: float = 20.0) -> None:
    got, deadline = 0, time.monotonic() + timeout
    while got < n and time.monotonic() < deadline:
        if sub.poll(200):
            sub.recv_multipart()
            got += 1
    assert got == n


def test_control_belief_changes_are_recorded_in_place_and_replay_bit_for_bit(tmp_path: Path) -> None:
    from services.replay import _Session

    path = tmp_path / "d.mcap"
    daemon, ctx, pub, rep = _daemon(tmp_path, path)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"pose")
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="loop")
    loop.start()
    try:
        sub.connect(pub)
        _poses(sub, 8)
        pose = {"x": 2.0, "y": 1.5, "theta": 0.0}
        cov = [0.04, 0, 0, 0, 0.04, 0, 0, 0, 0.01]
        assert _request(ctx, rep, {"cmd": "set_pose", "pose": pose, "covariance": cov})["ok"]
        _poses(sub, 8)
        assert _request(ctx, rep, {"cmd": "global_localization"})["ok"]
        _poses(sub, 8)
        st = _request(ctx, rep, {"cmd": "status"})["status"]
        assert st["recording"]["file"] == str(path) and st["recording"]["error"] is None
    finally:
        daemon.request_stop()
        loop.join(20)
        sub.close(0)
        ctx.term()
    rec = Recording([path])
    msgs = list(read_recording([path], rec))
    inputs = [json.loads(m.data) for m in msgs if m.topic == "/localizer/input"]
    assert [r["seq"] for r in inputs] == list(range(len(inputs)))
    beliefs = [(r["kind"], r["cause"]) for r in inputs if r["kind"] != "update"]
    assert beliefs == [("start_global", "start"), ("set_pose", "control"), ("start_global", "control")]
    sp = next(r for r in inputs if r["kind"] == "set_pose")
    assert sp["mean"] == [2.0, 1.5, 0.0] and sp["cov"] == [float(v) for v in cov]
    assert {m.topic for m in msgs} >= {"/camera/image", "/odometry", "/head/state", "/pose",
                                       "/pose/estimate", "/pose/ellipse", "/particles", "/tf"}
    session = _Session(rec, daemon.cfg, daemon.localizer.map, None, False)
    for m in msgs:
        session.on_message(m)
    same = session.compare()
    assert same is not None and same["bit_identical"] and same["matched"] >= 24, same


def test_a_recording_that_cannot_be_written_is_reported_and_the_daemon_goes_on(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    daemon, ctx, pub, rep = _daemon(tmp_path, blocker / "d.mcap")
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"pose")
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="loop")
    loop.start()
    try:
        sub.connect(pub)
        _poses(sub, 5)
        st = _request(ctx, rep, {"cmd": "status"})["status"]
        assert st["recording"]["error"] is not None and "not-a-dir" in st["recording"]["error"]
        _poses(sub, 5)
        assert loop.is_alive()
    finally:
        daemon.request_stop()
        loop.join(20)
        sub.close(0)
        ctx.term()


def test_dead_reckoning_is_recorded_and_replays_bit_for_bit(tmp_path: Path) -> None:
    from services.replay import _Session

    path = tmp_path / "dr.mcap"
    daemon, ctx, pub, rep = _daemon(tmp_path, path, _StallingCamera)
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="loop")
    loop.start()
    try:
        time.sleep(4.0)
    finally:
        daemon.request_stop()
        loop.join(20)
        ctx.term()
    rec = Recording([path])
    msgs = list(read_recording([path], rec))
    kinds = [json.loads(m.data)["kind"] for m in msgs if m.topic == "/localizer/input"]
    assert kinds.count("predict") >= 5 and kinds[-1] == "update", kinds
    session = _Session(rec, daemon.cfg, daemon.localizer.map, None, False)
    for m in msgs:
        session.on_message(m)
    same = session.compare()
    assert same is not None and same["bit_identical"] and session.result.predicts == kinds.count("predict")


def test_a_rotated_recording_replays_from_its_parts_in_order(tmp_path: Path) -> None:
    from services.recording.session_file import part_path
    from services.replay import _Session

    path = tmp_path / "rot.mcap"
    daemon, ctx, pub, rep = _daemon(tmp_path, path, rotate_mb=0.01)  # a part per 10 kB
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="loop")
    loop.start()
    try:
        time.sleep(3.0)
    finally:
        daemon.request_stop()
        loop.join(20)
        ctx.term()
    parts = [part_path(path, i) for i in range(100) if part_path(path, i).is_file()]
    assert len(parts) >= 3
    rec = Recording(parts)
    msgs = list(read_recording(parts, rec))
    seqs = [json.loads(m.data)["seq"] for m in msgs if m.topic == "/localizer/input"]
    assert seqs == list(range(len(seqs)))
    session = _Session(rec, daemon.cfg, daemon.localizer.map, None, False)
    for m in msgs:
        session.on_message(m)
    same = session.compare()
    assert same is not None and same["bit_identical"] and session.result.missing_inputs == 0
