"""Concurrent readers of the robot's three devices, and the buffers the loop reads them from.

The localization loop (:mod:`services.daemon`) must never wait on a device. Each device gets
its own thread (:class:`DeviceWorker`), which owns the driver and leaves what it read in a
buffer built for the question the loop asks. The drivers own device resilience (reconnect
with :class:`drivers.backoff.Backoff`, never raising on a glitch); a worker only re-creates a
driver whose factory, ``open`` or ``read`` raised, after the same kind of backoff.

- camera -> :class:`FrameMailbox`: a mailbox of ONE frame. A frame that arrives while the
  previous one is still waiting replaces it, and the replaced frame is counted as dropped,
  so frames never queue up behind a slow update. The loop always gets the newest frame.
- odometry -> :class:`OdometryBuffer`: stamped increments ``(t0, t1, dx, dy, dtheta)``;
  :meth:`OdometryBuffer.take_until` composes everything up to a frame's stamp (splitting the
  increment that straddles it in proportion to time) into the action ``u_t`` of the paper's
  action model (eq. 5): the base's motion between two frames, in the base frame at the
  earlier one.
- head -> :class:`HeadHistory`: present pan/tilt samples with host stamps;
  :meth:`HeadHistory.pan_at` interpolates the pan at a frame's capture time (the camera
  heading is the robot heading plus that pan). The head thread also sends the goals the loop
  asks for (:meth:`HeadWorker.command`, latest goal wins), so a slow or silent servo bus
  (the Dynamixel SDK waits 2 x ``LATENCY_TIMER`` + 2 ms for a silent id) never stalls the
  loop.

Every worker reports a :class:`drivers.interfaces.DeviceHealth`: the driver's own health, or
FAILED with the error when the driver cannot even be created or opened.

Usage::

    mailbox, odo_buf, heads = FrameMailbox(), OdometryBuffer(), HeadHistory()
    cam = CameraWorker(lambda: SimStereoCamera(endpoint), mailbox); cam.start()
    frame = mailbox.get(timeout=0.1)
    delta, n = odo_buf.take_until(frame.stamp)
    pan, moving = heads.pan_at(frame.stamp)
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from drivers.backoff import Backoff
from drivers.interfaces import (
    BoardCounters,
    Device,
    DeviceHealth,
    HeadState,
    HealthState,
    Odometry,
    OdometryIncrement,
    PanTiltHead,
    StereoCamera,
    StereoFrame,
)
from lino_loc.poses import between, compose

log = logging.getLogger("lino_loc.service.devices")

T = TypeVar("T")
D = TypeVar("D", bound=Device)

#: Factories of the three drivers (called again to re-create a driver that raised).
CameraFactory = Callable[[], StereoCamera]
OdometryFactory = Callable[[], Odometry]
HeadFactory = Callable[[], PanTiltHead]

# --------------------------------------------------------------------------------------------
# camera: a mailbox of one
# --------------------------------------------------------------------------------------------


class FrameMailbox(Generic[T]):
    """Holds at most one item: ``put`` replaces an unread item (counted in ``dropped``)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._woken = False
        self.received = 0
        self.dropped = 0

    def put(self, item: T) -> bool:
        """Leave ``item`` for the reader; True if an unread item was dropped for it."""
        with self._cond:
            self.received += 1
            dropped = self._item is not None
            if dropped:
                self.dropped += 1
            self._item = item
            self._cond.notify()
        return dropped

    def get(self, timeout: float | None = None) -> T | None:
        """The waiting item (and empty the box), waiting up to ``timeout`` s; None if none."""
        with self._cond:
            if self._item is None and timeout:
                self._cond.wait_for(lambda: self._item is not None or self._woken, timeout)
            self._woken = False
            item, self._item = self._item, None
            return item

    def wake(self) -> None:
        """Wake a waiting ``get`` (it returns None if still empty)."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()


# --------------------------------------------------------------------------------------------
# odometry: stamped increments, composed between frame stamps
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Span:
    t0: float
    t1: float
    delta: np.ndarray  # (3,) base motion over (t0, t1], base frame at t0


def _scale(delta: np.ndarray, f: float) -> np.ndarray:
    """The first fraction ``f`` of a constant-velocity increment (exact for an arc)."""
    dx, dy, dth = (float(v) for v in delta)
    if abs(dth) < 1e-9:
        return np.array([f * dx, f * dy, f * dth])
    # An arc of curvature dth / chord: the chord of the fraction f of it.
    chord = math.hypot(dx, dy)
    radius = chord / (2.0 * math.sin(dth / 2.0)) if abs(math.sin(dth / 2.0)) > 1e-12 else 0.0
    a = f * dth
    sub = 2.0 * radius * math.sin(a / 2.0)
    heading = math.atan2(dy, dx) - dth / 2.0  # direction of travel at the start
    return np.array([sub * math.cos(heading + a / 2.0), sub * math.sin(heading + a / 2.0), a])


class OdometryBuffer:
    """Increments of the base, composed between frame stamps (thread-safe).

    ``take_until(t)`` returns the composition of all motion with end stamp up to ``t`` since
    the previous call: the odometry action ``u_t`` between two frames (eq. 5). Motion that
    arrives late (its stamp is before the previous frame) is not lost: it goes into the next
    action. At most ``max_spans`` increments are kept; beyond that the two oldest are merged.
    """

    def __init__(self, max_spans: int = 2000) -> None:
        self._lock = threading.Lock()
        self._spans: collections.deque[_Span] = collections.deque()
        self._last_t1: float | None = None
        self.max_spans = max_spans
        self.received = 0
        self.last_stamp: float | None = None
        #: the board's absolute counters at its latest sample (None: none yet)
        self.counters: BoardCounters | None = None
        #: called with every batch of increments as it arrives (the recorder; must not block)
        self.listener: Callable[[list[OdometryIncrement]], None] | None = None

    def add(self, increments: list[OdometryIncrement]) -> None:
        if self.listener is not None:
            self.listener(increments)
        with self._lock:
            for inc in increments:
                t1 = float(inc.stamp)
                t0 = t1 - float(inc.dt) if inc.dt > 0 else (self._last_t1 if self._last_t1 is not None else t1)
                t0 = min(t0, t1)
                self._spans.append(_Span(t0, t1, np.array([inc.dx, inc.dy, inc.dtheta], dtype=np.float64)))
                self._last_t1 = t1 if self._last_t1 is None else max(self._last_t1, t1)
                self.received += 1
                self.last_stamp = self._last_t1
            while len(self._spans) > self.max_spans:
                a = self._spans.popleft()
                b = self._spans.popleft()
                self._spans.appendleft(_Span(a.t0, max(a.t1, b.t1), compose(a.delta, b.delta)))

    def take_until(self, t: float) -> tuple[np.ndarray, int]:
        """(composed (dx, dy, dtheta) up to stamp ``t``, number of increments used).

        An increment that straddles ``t`` is split: the part before ``t`` (in proportion to
        time, along its arc) is used now, the rest stays for the next call."""
        total = np.zeros(3)
        used = 0
        with self._lock:
            while self._spans:
                s = self._spans[0]
                if s.t1 <= t:
                    total = compose(total, s.delta)
                    self._spans.popleft()
                    used += 1
                    continue
                if s.t0 < t < s.t1 and s.t1 > s.t0:
                    f = (t - s.t0) / (s.t1 - s.t0)
                    part = _scale(s.delta, f)
                    rest = between(part, s.delta)
                    total = compose(total, part)
                    self._spans[0] = _Span(t, s.t1, rest)
                    used += 1
                break
        return total, used

    def take_all(self) -> tuple[np.ndarray, int]:
        """Everything buffered (dead reckoning without frames)."""
        return self.take_until(math.inf)

    def __len__(self) -> int:
        with self._lock:
            return len(self._spans)


# --------------------------------------------------------------------------------------------
# head: history of present angles
# --------------------------------------------------------------------------------------------


class HeadHistory:
    """Present head angles with host stamps; the pan at any recent time (thread-safe)."""

    def __init__(self, maxlen: int = 1000) -> None:
        self._lock = threading.Lock()
        self._t: collections.deque[float] = collections.deque(maxlen=maxlen)
        self._s: collections.deque[HeadState] = collections.deque(maxlen=maxlen)
        self.last_motion: float | None = None  # stamp of the last sample that was moving
        #: called with every reading that is not stale (the recorder; must not block)
        self.listener: Callable[[HeadState], None] | None = None

    def add(self, state: HeadState) -> None:
        if state.stale:
            return
        if self.listener is not None:
            self.listener(state)
        with self._lock:
            if self._t and state.stamp < self._t[-1]:
                return  # out of order
            self._t.append(float(state.stamp))
            self._s.append(state)
            if state.moving:
                self.last_motion = float(state.stamp)

    def latest(self) -> HeadState | None:
        with self._lock:
            return self._s[-1] if self._s else None

    def pan_at(self, t: float) -> tuple[float, bool]:
        """(pan at time ``t`` by linear interpolation, whether the head moved around ``t``).

        Before the first / after the last sample: the nearest sample's pan. No sample: 0."""
        with self._lock:
            if not self._t:
                return 0.0, False
            ts = list(self._t)
            i = bisect.bisect_left(ts, t)
            if i <= 0:
                s = self._s[0]
                return float(s.pan), bool(s.moving)
            if i >= len(ts):
                s = self._s[-1]
                return float(s.pan), bool(s.moving)
            a, b = self._s[i - 1], self._s[i]
            span = b.stamp - a.stamp
            f = 0.0 if span <= 0 else (t - a.stamp) / span
            moving = bool(a.moving or b.moving or abs(b.pan - a.pan) > 1e-3)
            return float(a.pan + f * (b.pan - a.pan)), moving


# --------------------------------------------------------------------------------------------
# worker threads
# --------------------------------------------------------------------------------------------


class DeviceWorker(threading.Thread, Generic[D]):
    """A thread that owns one driver and calls ``_step`` on it until stopped.

    The drivers reconnect their devices themselves and never raise on a device glitch, so the
    worker only has to obtain a driver: it calls ``factory()`` then ``open()``, and while
    either raises it records the error (health FAILED, counter ``worker_failures``) and tries
    again after ``Backoff(backoff_min, backoff_max)`` (:mod:`drivers.backoff`). A ``_step``
    that raises breaks the driver's contract: it is logged with its traceback, counted the
    same way, and the driver is closed and re-created through the same backoff. Every step
    that returns resets the backoff.
    """

    kind = "device"

    def __init__(
        self,
        factory: Callable[[], D],
        *,
        backoff_min: float = 0.2,
        backoff_max: float = 5.0,
    ) -> None:
        super().__init__(name=f"{self.kind}-worker", daemon=True)
        self._factory = factory
        self._stop_event = threading.Event()
        self._device: D | None = None
        self._lock = threading.Lock()
        self._error: str | None = None
        self._error_stamp: float | None = None
        self._failures = 0
        self._backoff = Backoff(backoff_min, backoff_max)

    # -- lifecycle ---------------------------------------------------------------------
    def stop(self, timeout: float = 3.0) -> None:
        self._stop_event.set()
        self._wake()
        if self.is_alive() and threading.current_thread() is not self:
            self.join(timeout)
        self._close_device()

    @property
    def stopping(self) -> bool:
        return self._stop_event.is_set()

    def run(self) -> None:
        while not self._stop_event.is_set():
            try:
                device = self._device if self._device is not None else self._create()
                self._step(device)
            except Exception as exc:  # noqa: BLE001 - a device must never end the daemon
                self._failed(exc)
                self._close_device()
                if self._backoff.wait(self._stop_event):
                    break
            else:
                self._backoff.reset()

    def _create(self) -> D:
        """A new driver from the factory, opened (closed again if ``open`` raises)."""
        device = self._factory()
        try:
            device.open()
        except Exception:
            self._close(device)
            raise
        with self._lock:
            self._device = device
            self._error = None
        self._opened(device)
        return device

    def _failed(self, exc: Exception) -> None:
        """Record a raising factory, ``open`` or ``_step`` (the last with its traceback)."""
        msg = f"{self.kind}: {type(exc).__name__}: {exc}"
        with self._lock:
            running = self._device is not None
            self._error = msg
            self._error_stamp = time.time()
            self._failures += 1
        retry = self._backoff.delay
        if running:
            log.error("%s: driver raised (retry in %.1f s)", msg, retry, exc_info=exc)
        else:
            log.warning("%s (retry in %.1f s)", msg, retry)

    def _close_device(self) -> None:
        with self._lock:
            dev, self._device = self._device, None
        if dev is not None:
            self._close(dev)

    def _close(self, device: D) -> None:
        try:
            device.close()
        except Exception as exc:  # noqa: BLE001
            log.debug("%s: close failed: %s", self.kind, exc)

    # -- hooks -------------------------------------------------------------------------
    def _opened(self, device: D) -> None:
        pass

    def _step(self, device: D) -> None:
        raise NotImplementedError

    def _wake(self) -> None:
        pass

    # -- health ------------------------------------------------------------------------
    def health(self) -> DeviceHealth:
        """The driver's health (plus ``worker_failures`` once any), or FAILED with the error
        while there is no driver."""
        with self._lock:
            dev, err, stamp, failures = self._device, self._error, self._error_stamp, self._failures
        if dev is None or err is not None:
            return DeviceHealth(
                state=HealthState.FAILED,
                last_error=err or f"{self.kind}: not started",
                last_error_stamp=stamp,
                counters={"worker_failures": failures},
            )
        try:
            h = dev.health()
        except Exception as exc:  # noqa: BLE001
            return DeviceHealth(HealthState.FAILED, f"{self.kind}: health: {exc}", time.time())
        if failures:
            counters = dict(h.counters)
            counters["worker_failures"] = failures
            return DeviceHealth(h.state, h.last_error, h.last_error_stamp, counters)
        return h


class CameraWorker(DeviceWorker[StereoCamera]):
    """Reads frames (``StereoCamera.read``) into a :class:`FrameMailbox`."""

    kind = "camera"

    def __init__(
        self, factory: CameraFactory, mailbox: FrameMailbox[StereoFrame], **backoff: float
    ) -> None:
        super().__init__(factory, **backoff)
        self.mailbox = mailbox
        self.last_frame_mono: float | None = None

    def _step(self, device: StereoCamera) -> None:
        frame = device.read(timeout=0.2)
        if frame is not None:
            self.last_frame_mono = time.monotonic()
            self.mailbox.put(frame)


class OdometryWorker(DeviceWorker[Odometry]):
    """Moves increments (``Odometry.read``) into an :class:`OdometryBuffer`, and the
    board's absolute counters (``Odometry.counters``) into its ``counters``."""

    kind = "odometry"

    def __init__(self, factory: OdometryFactory, buffer: OdometryBuffer, **backoff: float) -> None:
        super().__init__(factory, **backoff)
        self.buffer = buffer

    def _step(self, device: Odometry) -> None:
        incs = device.read(timeout=0.1)
        if incs:
            self.buffer.add(incs)
        counters = device.counters()
        if counters is not None:
            self.buffer.counters = counters


class HeadWorker(DeviceWorker[PanTiltHead]):
    """Polls the head's present angles into a :class:`HeadHistory` every ``period`` s and
    sends the latest goal from :meth:`command` (all bus traffic in this thread). A re-created
    driver is sent the last commanded goal again."""

    kind = "head"

    def __init__(
        self, factory: HeadFactory, history: HeadHistory, period: float = 0.02, **backoff: float
    ) -> None:
        super().__init__(factory, **backoff)
        self.history = history
        self.period = period
        self._goal: tuple[float, float] | None = None
        self._goal_event = threading.Event()
        self.commanded: tuple[float, float] | None = None

    def command(self, pan: float, tilt: float = 0.0) -> None:
        """Ask for new goal angles (sent by the head thread; a newer goal replaces it)."""
        with self._lock:
            self._goal = (float(pan), float(tilt))
        self._goal_event.set()

    def _wake(self) -> None:
        self._goal_event.set()

    def _opened(self, device: PanTiltHead) -> None:
        if self.commanded is not None and self._goal is None:
            self.command(*self.commanded)  # re-send the last goal to a re-created driver

    def _step(self, device: PanTiltHead) -> None:
        with self._lock:
            goal, self._goal = self._goal, None
        self._goal_event.clear()
        if goal is not None:
            cmd = device.command(*goal)
            self.commanded = (float(cmd.pan), float(cmd.tilt))
        self.history.add(device.read())
        self._goal_event.wait(self.period)
