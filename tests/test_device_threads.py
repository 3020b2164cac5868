"""Device threads and their buffers: the mailbox of one, odometry composition between frame
stamps, head-pan interpolation, and workers that survive failing drivers."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from drivers.interfaces import (
    BoardCounters,
    DeviceHealth,
    HeadCommand,
    HeadState,
    HealthState,
    OdometryIncrement,
)
from lino_loc.poses import compose
from services.device_threads import (
    CameraWorker,
    FrameMailbox,
    HeadHistory,
    HeadWorker,
    OdometryBuffer,
    OdometryWorker,
)


def _arc_increments(v: float, w: float, t0: float, dt: float, n: int) -> list[OdometryIncrement]:
    """n increments of constant (v, w), each the exact arc over dt."""
    out = []
    for k in range(n):
        th = w * dt
        if abs(w) < 1e-12:
            d = (v * dt, 0.0, 0.0)
        else:
            r = v / w
            d = (r * math.sin(th), r * (1 - math.cos(th)), th)
        out.append(OdometryIncrement(stamp=t0 + (k + 1) * dt, dx=d[0], dy=d[1], dtheta=d[2], dt=dt, sequence=k))
    return out


def _arc(v: float, w: float, t: float) -> np.ndarray:
    th = w * t
    if abs(w) < 1e-12:
        return np.array([v * t, 0.0, 0.0])
    r = v / w
    return np.array([r * math.sin(th), r * (1 - math.cos(th)), th])


# ------------------------------------------------------------------ mailbox


def test_mailbox_keeps_newest_and_counts_drops() -> None:
    box: FrameMailbox[int] = FrameMailbox()
    assert box.get(timeout=0.0) is None
    assert box.put(1) is False
    assert box.put(2) is True  # 1 was never read: dropped
    assert box.put(3) is True
    assert box.get() == 3 and box.get() is None
    assert (box.received, box.dropped) == (3, 2)
    box.put(4)
    assert box.get() == 4
    assert box.dropped == 2  # read in time: no drop


def test_mailbox_get_waits_and_wakes() -> None:
    box: FrameMailbox[str] = FrameMailbox()
    threading.Timer(0.05, box.put, args=("x",)).start()
    t = time.monotonic()
    assert box.get(timeout=2.0) == "x"
    assert time.monotonic() - t < 1.0
    t = time.monotonic()
    threading.Timer(0.05, box.wake).start()
    assert box.get(timeout=2.0) is None
    assert time.monotonic() - t < 1.0


# ------------------------------------------------------------------ odometry


def test_take_until_composes_an_arc_exactly() -> None:
    buf = OdometryBuffer()
    buf.add(_arc_increments(0.4, 0.5, 100.0, 0.02, 50))  # 1 s of driving
    d1, n1 = buf.take_until(100.5)
    np.testing.assert_allclose(d1, _arc(0.4, 0.5, 0.5), atol=1e-9)
    assert n1 == 25
    d2, _ = buf.take_until(101.0)
    np.testing.assert_allclose(compose(d1, d2), _arc(0.4, 0.5, 1.0), atol=1e-9)
    assert len(buf) == 0


def test_take_until_splits_the_straddling_increment() -> None:
    buf = OdometryBuffer()
    buf.add(_arc_increments(0.3, -0.7, 10.0, 0.02, 10))
    total = np.zeros(3)
    for t in (10.013, 10.0371, 10.05, 10.1999, 10.2):  # mid-increment stamps
        d, _ = buf.take_until(t)
        total = compose(total, d)
        np.testing.assert_allclose(total, _arc(0.3, -0.7, t - 10.0), atol=1e-9)


def test_late_motion_goes_into_the_next_action_and_rotation_in_place() -> None:
    buf = OdometryBuffer()
    d, n = buf.take_until(5.0)
    assert n == 0 and np.all(d == 0)
    buf.add([OdometryIncrement(stamp=4.0, dx=0.1, dy=0.0, dtheta=0.0, dt=0.02)])  # late
    d, n = buf.take_until(6.0)
    assert n == 1 and d[0] == pytest.approx(0.1)
    buf.add([OdometryIncrement(stamp=7.0, dx=0.0, dy=0.0, dtheta=0.4, dt=1.0)])
    d, _ = buf.take_until(6.5)
    np.testing.assert_allclose(d, [0.0, 0.0, 0.2], atol=1e-12)


def test_buffer_is_bounded_without_losing_motion() -> None:
    buf = OdometryBuffer(max_spans=10)
    incs = _arc_increments(0.2, 0.3, 0.0, 0.02, 200)
    buf.add(incs)
    assert len(buf) <= 10
    d, _ = buf.take_all()
    np.testing.assert_allclose(d, _arc(0.2, 0.3, 4.0), atol=1e-9)


# ------------------------------------------------------------------ head


def test_pan_interpolation_and_moving_flag() -> None:
    h = HeadHistory()
    assert h.pan_at(1.0) == (0.0, False)
    h.add(HeadState(stamp=1.0, pan=0.0, tilt=0.0, moving=False))
    h.add(HeadState(stamp=1.1, pan=0.2, tilt=0.0, moving=True))
    h.add(HeadState(stamp=1.2, pan=0.4, tilt=0.0, moving=False))
    h.add(HeadState(stamp=1.3, pan=0.4, tilt=0.0, moving=False))
    h.add(HeadState(stamp=1.25, pan=9.0, tilt=0.0, moving=False))  # out of order: ignored
    h.add(HeadState(stamp=1.4, pan=9.0, tilt=0.0, moving=False, stale=True))  # stale: ignored
    pan, moving = h.pan_at(1.15)
    assert pan == pytest.approx(0.3) and moving
    assert h.pan_at(1.27) == (pytest.approx(0.4), False)
    assert h.pan_at(0.5) == (0.0, False)  # before the first sample
    assert h.pan_at(5.0)[0] == pytest.approx(0.4)  # after the last
    assert h.last_motion == 1.1


# ------------------------------------------------------------------ workers


class _FlakyCamera:
    """Raises on the first ``fail`` creations, then yields numbered frames."""

    created = 0

    def __init__(self, fail: int) -> None:
        type(self).created += 1
        if type(self).created <= fail:
            raise OSError("no device")
        self.n = 0

    def open(self) -> None:
        pass

    def read(self, timeout: float | None = None) -> int:
        time.sleep(0.005)
        self.n += 1
        return self.n

    def health(self) -> DeviceHealth:
        return DeviceHealth(HealthState.OK)

    def close(self) -> None:
        pass


def test_camera_worker_retries_a_failing_driver_and_reports_it() -> None:
    _FlakyCamera.created = 0
    box: FrameMailbox[int] = FrameMailbox()
    w = CameraWorker(lambda: _FlakyCamera(fail=2), box, backoff_min=0.05, backoff_max=0.05)
    assert w.health().state is HealthState.FAILED
    w.start()
    try:
        deadline = time.monotonic() + 5
        while box.get(timeout=0.1) is None and time.monotonic() < deadline:
            pass
        assert _FlakyCamera.created == 3
        h = w.health()
        assert h.state is HealthState.OK and h.counters["worker_failures"] == 2
        time.sleep(0.1)  # nobody reads: frames replace each other and count as dropped
        assert box.dropped > 0
    finally:
        w.stop()
    assert not w.is_alive()


def test_odometry_worker_fills_the_buffer() -> None:
    class Odo:
        def __init__(self) -> None:
            self.incs = _arc_increments(0.5, 0.0, 0.0, 0.02, 5)

        def open(self) -> None:
            pass

        def read(self, timeout: float | None = None) -> list[OdometryIncrement]:
            out, self.incs = self.incs, []
            if not out:
                time.sleep(0.01)
            return out

        def health(self) -> DeviceHealth:
            return DeviceHealth(HealthState.DEGRADED, "stale")

        def counters(self) -> BoardCounters:
            return BoardCounters(time.time(), 1234, 5, 6, 1e-4, 1e-4, 0.3)

        def close(self) -> None:
            pass

    buf = OdometryBuffer()
    assert buf.counters is None
    w = OdometryWorker(Odo, buf)
    w.start()
    try:
        deadline = time.monotonic() + 5
        while buf.received < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.health().state is HealthState.DEGRADED  # the driver's own health
    finally:
        w.stop()
    np.testing.assert_allclose(buf.take_all()[0], [0.05, 0.0, 0.0], atol=1e-12)
    assert buf.counters is not None and (buf.counters.board_ms, buf.counters.left) == (1234, 5)


def test_head_worker_sends_latest_goal_and_records_history() -> None:
    class Head:
        def __init__(self) -> None:
            self.pan = 0.0
            self.commands: list[float] = []

        def open(self) -> None:
            pass

        def command(self, pan: float, tilt: float) -> HeadCommand:
            self.commands.append(pan)
            self.pan = min(pan, 1.0)
            return HeadCommand(self.pan, tilt, pan > 1.0)

        def read(self) -> HeadState:
            return HeadState(stamp=time.time(), pan=self.pan, tilt=0.0, moving=False)

        def health(self) -> DeviceHealth:
            return DeviceHealth(HealthState.OK)

        def close(self) -> None:
            pass

    dev = Head()
    hist = HeadHistory()
    w = HeadWorker(lambda: dev, hist, period=0.01)
    w.command(0.3)
    w.start()
    try:
        deadline = time.monotonic() + 5
        while (hist.latest() is None or hist.latest().pan != 0.3) and time.monotonic() < deadline:
            time.sleep(0.01)
        w.command(2.0)  # clamped by the driver
        while w.commanded != (1.0, 0.0) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.commanded == (1.0, 0.0)
        assert dev.commands[:2] == [0.3, 2.0]
    finally:
        w.stop()


class _BrokenCamera:
    """Opens, then raises in ``read`` after ``frames`` frames (a driver breaking its promise)."""

    opened = 0
    closed = 0

    def __init__(self, frames: int, open_raises: bool = False) -> None:
        self.frames = frames
        self.open_raises = open_raises

    def open(self) -> None:
        type(self).opened += 1
        if self.open_raises:
            raise RuntimeError("open failed")

    def read(self, timeout: float | None = None) -> int | None:
        time.sleep(0.005)
        if self.frames <= 0:
            raise ValueError("driver bug")
        self.frames -= 1
        return self.frames

    def health(self) -> DeviceHealth:
        return DeviceHealth(HealthState.OK)

    def close(self) -> None:
        type(self).closed += 1


def test_a_raising_read_recreates_the_driver_after_the_backoff() -> None:
    _BrokenCamera.opened = _BrokenCamera.closed = 0
    box: FrameMailbox[int] = FrameMailbox()
    w = CameraWorker(lambda: _BrokenCamera(frames=2), box, backoff_min=0.05, backoff_max=0.05)
    w.start()
    try:
        deadline = time.monotonic() + 5
        while _BrokenCamera.opened < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert _BrokenCamera.opened >= 3  # re-created after each raise
        assert _BrokenCamera.closed >= 2  # the broken driver was closed each time
        assert w.health().counters["worker_failures"] >= 2
    finally:
        w.stop()
    assert not w.is_alive()


def test_a_driver_whose_open_raises_is_closed_and_retried() -> None:
    _BrokenCamera.opened = _BrokenCamera.closed = 0
    box: FrameMailbox[int] = FrameMailbox()
    w = CameraWorker(
        lambda: _BrokenCamera(1, open_raises=True), box, backoff_min=0.02, backoff_max=0.02
    )
    w.start()
    try:
        deadline = time.monotonic() + 5
        while _BrokenCamera.opened < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        h = w.health()
        assert h.state is HealthState.FAILED and "open failed" in (h.last_error or "")
    finally:
        w.stop()
    assert _BrokenCamera.closed == _BrokenCamera.opened >= 3


def test_stop_ends_a_long_backoff_promptly() -> None:
    def factory() -> _FlakyCamera:
        raise OSError("not plugged in")

    w = CameraWorker(factory, FrameMailbox(), backoff_min=30.0, backoff_max=60.0)
    w.start()
    time.sleep(0.05)
    t0 = time.monotonic()
    w.stop()
    assert not w.is_alive() and time.monotonic() - t0 < 2.0
    assert w.health().counters["worker_failures"] == 1
