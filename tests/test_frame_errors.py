"""A frame whose update raises does not end the daemon: a real ``Daemon`` (its sockets, its
threads, its loop) on in-process fake devices and the tiny map of ``test_localizer``; the
update raises on chosen frames; the error is logged once with its traceback, counted in
``status`` (``update_errors``) and the poses keep coming."""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_localizer import _config, _world  # noqa: E402

from drivers.interfaces import (
    CameraIntrinsics,
    DeviceHealth,
    HeadCommand,
    HeadLimits,
    HeadState,
    HealthState,
    OdometryIncrement,
    StereoFrame,
)
from lino_loc.poses import camera_pose
from services.config import ServiceConfig
from services.daemon import RESET_AFTER_FAILED_UPDATES, Daemon, DeviceFactories

FPS = 20.0


class _Device:
    def open(self) -> bool:
        return True

    def health(self) -> DeviceHealth:
        return DeviceHealth(HealthState.OK)

    def close(self) -> None:
        pass


class _Camera(_Device):
    """Frames at FPS: the tiny map's "image" of a robot standing at (2, 1.5, 0)."""

    def __init__(self) -> None:
        _, f_img, _ = _world()
        self.image = f_img(camera_pose(np.array([2.0, 1.5, 0.0]), 0.0))[0]
        self.seq = 0

    def read(self, timeout: float | None = None) -> StereoFrame:
        time.sleep(1.0 / FPS)
        self.seq += 1
        return StereoFrame(time.time(), self.image, None, None, CameraIntrinsics(50, 50, 8, 1, 16, 1), 0.1, self.seq)


class _Odometry(_Device):
    def counters(self) -> None:
        return None

    def read(self, timeout: float | None = None) -> list[OdometryIncrement]:
        time.sleep(timeout or 0.05)
        return [OdometryIncrement(time.time(), 0.0, 0.0, 0.0, 0.05)]


class _Head(_Device):
    limits = HeadLimits(-1.5, 1.5, -0.5, 0.5)

    def command(self, pan: float, tilt: float) -> HeadCommand:
        return HeadCommand(pan, tilt, False)

    def read(self) -> HeadState:
        time.sleep(0.02)
        return HeadState(time.time(), 0.0, 0.0, False)


def _request(ctx: zmq.Context[Any], endpoint: str, payload: dict[str, Any]) -> dict[str, Any]:
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.setsockopt(zmq.RCVTIMEO, 5000)
    s.connect(endpoint)
    try:
        s.send(json.dumps(payload).encode())
        return json.loads(s.recv())
    finally:
        s.close(0)


class _Failing:
    """Wraps ``Localizer.update``: raises on the next ``n`` calls after :meth:`fail`."""

    def __init__(self, update: Any) -> None:
        self.update = update
        self.pending = 0
        self.raised = 0

    def fail(self, n: int) -> None:
        self.pending += n

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.pending > 0:
            self.pending -= 1
            self.raised += 1
            raise RuntimeError(f"injected failure {self.raised}")
        return self.update(*args, **kwargs)


def test_a_frame_whose_update_raises_is_logged_counted_and_survived(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    m, _, _ = _world()
    pub, rep = f"ipc://{tmp_path}/pub", f"ipc://{tmp_path}/rep"
    cfg = ServiceConfig(
        devices={"camera": {"kind": "sim", "sim": {"fps": FPS}}},
        localizer=_config(),
        active_vision={"enabled": False},
        endpoints={"pub": pub, "rep": rep},
        persistence={"state_file": str(tmp_path / "state.json"), "restore": False},
        publish={"truth": False},
    )
    factories = DeviceFactories(camera=_Camera, head=_Head, odometry=_Odometry)
    ctx: zmq.Context[Any] = zmq.Context()
    daemon = Daemon(cfg, m, device_factories=factories, context=ctx)
    failing = _Failing(daemon.localizer.update)
    daemon.localizer.update = failing  # type: ignore[method-assign]
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"pose")
    caplog.set_level(logging.INFO, logger="lino_loc.service")
    daemon.start()
    loop = threading.Thread(target=daemon.run, name="loop")
    loop.start()
    try:
        sub.connect(pub)

        def poses(n: int, timeout: float = 20.0) -> list[int]:
            seqs: list[int] = []
            deadline = time.monotonic() + timeout
            while len(seqs) < n and time.monotonic() < deadline:
                if sub.poll(200):
                    seqs.append(json.loads(sub.recv_multipart()[1])["seq"])
            assert len(seqs) == n, f"only {len(seqs)} poses; loop alive: {loop.is_alive()}"
            return seqs

        before = poses(5)
        failing.fail(1)
        after = poses(10)
        assert failing.raised == 1 and loop.is_alive()
        assert after[0] > before[-1] and after == sorted(after)
        st = _request(ctx, rep, {"cmd": "status"})["status"]
        assert st["update_errors"] == 1 and st["state"] != "starting"
        # more of the same: counted, not logged with a traceback again (rate-limited)
        failing.fail(3)
        poses(10)
        assert _request(ctx, rep, {"cmd": "status"})["status"]["update_errors"] == 4
        tracebacks = [r for r in caplog.records if r.exc_info and "frame update failed" in r.getMessage()]
        assert len(tracebacks) == 1 and "injected failure 1" in tracebacks[0].getMessage()
        # a belief that makes every update fail is reset to global localization
        failing.fail(RESET_AFTER_FAILED_UPDATES)
        poses(5)
        assert any("starting global localization" in r.getMessage() for r in caplog.records)
        assert _request(ctx, rep, {"cmd": "ping"})["ok"] is True
    finally:
        daemon.request_stop()
        loop.join(20)
        sub.close(0)
        ctx.term()
    assert not loop.is_alive()
