"""Device interfaces of the robot and the data they return.

Three small interfaces, each with a real adapter (vendor library) and a fake (emulator or
renderer) behind it, and the :class:`Device` life cycle they share (``open``, ``health``,
``close``):

- :class:`StereoCamera` -> :class:`StereoFrame` (rectified grey pair, optional disparity,
  intrinsics and baseline: the inputs of the paper's disparity sensor model);
- :class:`PanTiltHead` -> :class:`HeadState` (present pan/tilt; the camera heading is the
  robot heading plus the pan angle, ``lino_loc.poses.camera_pose``);
- :class:`Odometry` -> :class:`OdometryIncrement` (pose increments of the base in its own
  frame, the input of the odometry action model), and :class:`BoardCounters` (the board's
  absolute counters, which outlive the daemon: how far the wheels went across a restart).

All of them report a :class:`DeviceHealth`. Adapters never raise into the caller for device
glitches (timeouts, corrupt packets, an unplugged cable): they retry (reconnecting with
:class:`drivers.backoff.Backoff`), count, and say so in their health. They raise only for
programming or configuration mistakes.

Usage::

    from drivers.interfaces import Device, StereoCamera, PanTiltHead, Odometry, HealthState
"""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

# --------------------------------------------------------------------------------------------
# Health, shared by all devices
# --------------------------------------------------------------------------------------------


class HealthState(enum.Enum):
    """OK: working. DEGRADED: working with errors or recovering. FAILED: not working."""

    OK = "ok"
    DEGRADED = "degraded"
    FAILED = "failed"


@dataclass(frozen=True)
class DeviceHealth:
    """A snapshot of a device's health.

    ``counters`` are monotonic event counts since the adapter was created (e.g. ``timeouts``,
    ``crc_errors``, ``reboots``, ``reconnects``, ``corrupt_lines``); ``last_error`` is the most
    recent error message (kept after recovery, with ``last_error_stamp`` in host seconds).
    """

    state: HealthState
    last_error: str | None = None
    last_error_stamp: float | None = None
    counters: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}))

    @property
    def ok(self) -> bool:
        return self.state is HealthState.OK

    def as_dict(self) -> dict[str, object]:
        """JSON-friendly form (for status messages)."""
        return {
            "state": self.state.value,
            "last_error": self.last_error,
            "last_error_stamp": self.last_error_stamp,
            "counters": dict(self.counters),
        }


class HealthTracker:
    """Thread-safe mutable health record that adapters update and snapshot."""

    def __init__(self, counters: tuple[str, ...] = ()) -> None:
        self._lock = threading.Lock()
        self._state = HealthState.OK
        self._last_error: str | None = None
        self._last_error_stamp: float | None = None
        self._counters: dict[str, int] = dict.fromkeys(counters, 0)

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counters[name] = self._counters.get(name, 0) + n

    def error(self, message: str, state: HealthState = HealthState.DEGRADED) -> None:
        """Record an error message and set the state (DEGRADED unless told otherwise)."""
        with self._lock:
            self._last_error = message
            self._last_error_stamp = time.time()
            self._state = state

    def set_state(self, state: HealthState) -> None:
        with self._lock:
            self._state = state

    @property
    def state(self) -> HealthState:
        with self._lock:
            return self._state

    def snapshot(self) -> DeviceHealth:
        with self._lock:
            return DeviceHealth(
                state=self._state,
                last_error=self._last_error,
                last_error_stamp=self._last_error_stamp,
                counters=MappingProxyType(dict(self._counters)),
            )


@runtime_checkable
class Device(Protocol):
    """The life cycle every device shares: open, report health, close."""

    def open(self) -> bool | None:
        """Connect or start streaming. Never raises for a missing device: health says so."""

    def health(self) -> DeviceHealth: ...

    def close(self) -> None: ...


# --------------------------------------------------------------------------------------------
# Stereo camera
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the rectified left image, pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """One rectified stereo pair.

    ``stamp``: capture time, seconds since the epoch on the host clock. ``left``/``right``:
    uint8 (H, W) rectified grey images (``right`` may be None if not streamed). ``disparity``:
    float32 (H, W) in pixels of the left image, NaN where there is no value, or None.
    Depth = fx * baseline_m / disparity.
    """

    stamp: float
    left: NDArray[np.uint8]
    right: NDArray[np.uint8] | None
    disparity: NDArray[np.float32] | None
    intrinsics: CameraIntrinsics
    baseline_m: float
    sequence: int = 0


@runtime_checkable
class StereoCamera(Device, Protocol):
    """A calibrated stereo camera producing rectified pairs (and optionally disparity)."""

    def open(self) -> bool | None:
        """Start streaming. Never raises for a missing device: health says so instead."""

    def read(self, timeout: float | None = None) -> StereoFrame | None:
        """The next frame, or None if none arrived within ``timeout`` seconds."""


# --------------------------------------------------------------------------------------------
# Pan-tilt head
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HeadLimits:
    """Allowed angles, radians (inclusive)."""

    pan_min: float
    pan_max: float
    tilt_min: float
    tilt_max: float

    def clamp(self, pan: float, tilt: float) -> tuple[float, float, bool]:
        """(pan, tilt) clamped to the limits, and whether anything was clamped."""
        p = min(max(pan, self.pan_min), self.pan_max)
        t = min(max(tilt, self.tilt_min), self.tilt_max)
        return p, t, (p != pan or t != tilt)


@dataclass(frozen=True)
class HeadCommand:
    """What was actually commanded after clamping to the limits."""

    pan: float
    tilt: float
    clamped: bool


@dataclass(frozen=True)
class HeadState:
    """Present state of the head.

    ``stamp``: host time of the read (seconds since the epoch). ``pan``/``tilt``: present
    angles, radians (pan CCW positive about the robot's vertical axis, tilt up positive).
    ``moving``: any servo moving. ``pan_error``/``tilt_error``: hardware error status bits of
    each servo (0 = none). ``stale``: this read failed and the values are the last known ones.
    """

    stamp: float
    pan: float
    tilt: float
    moving: bool
    pan_error: int = 0
    tilt_error: int = 0
    stale: bool = False


@runtime_checkable
class PanTiltHead(Device, Protocol):
    """A pan-tilt unit in position control."""

    @property
    def limits(self) -> HeadLimits: ...

    def open(self) -> bool | None:
        """Connect and set up. Never raises for a missing device: health says so instead."""

    def command(self, pan: float, tilt: float) -> HeadCommand:
        """Send goal angles (radians); they are clamped to the limits."""

    def read(self) -> HeadState: ...


# --------------------------------------------------------------------------------------------
# Odometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryIncrement:
    """Motion of the base between two encoder samples, in the base frame at the first sample.

    ``stamp``: host time of the second sample (seconds since the epoch); ``dt``: time between
    the samples by the board's clock (s). ``dx``, ``dy`` metres, ``dtheta`` radians (REP-103);
    compose with ``lino_loc.poses.compose(pose, (dx, dy, dtheta))``.
    """

    stamp: float
    dx: float
    dy: float
    dtheta: float
    dt: float = 0.0
    sequence: int = 0


@dataclass(frozen=True)
class BoardCounters:
    """The odometry board's absolute counters at one sample. They count from the board's
    power-up whatever the daemon does, so two readings, even from two runs of the daemon,
    tell how far each wheel went in between (``drivers.odometry_protocol.wheel_travel``),
    unless the board restarted meanwhile (its clock then went back or jumped).

    ``stamp``: host time of the sample (s since the epoch, the increments' clock);
    ``board_ms``: the board's clock (ms, unsigned 32-bit, wraps); ``left``, ``right``: the raw
    encoder counts (unsigned 32-bit, wrap); ``left_m_per_tick``, ``right_m_per_tick``: wheel
    travel per count (m, signed by the encoder's direction), ``track_width`` (m): the
    geometry of the driver that read them.
    """

    stamp: float
    board_ms: int
    left: int
    right: int
    left_m_per_tick: float
    right_m_per_tick: float
    track_width: float


@runtime_checkable
class Odometry(Device, Protocol):
    """Timestamped pose increments of the base, and the board's absolute counters."""

    def open(self) -> bool | None:
        """Start receiving. Never raises for a missing device: health says so instead."""

    def read(self, timeout: float | None = None) -> list[OdometryIncrement]:
        """Increments received since the previous call (waits up to ``timeout`` s for one)."""

    def counters(self) -> BoardCounters | None:
        """The board's absolute counters at its latest valid sample (None: no sample yet, or
        a source without absolute counters)."""
