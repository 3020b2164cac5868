"""The daemon's status: rates, latency, frame counters and the ``status`` message.

:class:`StatusReporter` keeps what the loop reports about itself and turns it into a
:class:`services.messages.StatusMessage` (topic ``status`` every
:data:`STATUS_PERIOD_S`, and the ``status`` reply of the control socket):

- rates over the last status period: ``pose_rate_hz = poses / dt``, ``frame_rate_hz =
  frames / dt`` (frames the loop took from the mailbox), ``dt`` the period's length (s);
- the frame-to-publish latency of the poses published in that period, its 50th and 99th
  percentiles (ms, ``numpy.percentile``, linear interpolation); a period without a pose keeps
  the previous figures;
- counters since start: frames received and dropped (the mailbox's plus the camera driver's
  ``dropped``/``frames_dropped`` counters), frames skipped as out of order, frame updates
  that raised (``update_errors``: the first of each exception type is logged with its
  traceback, later ones at most once per :data:`UPDATE_ERROR_LOG_PERIOD_S`, with the count);
- the devices' health, the map, the active-vision switches, the filter's state.

The loop calls :meth:`pose_published`, :meth:`frame_taken`, :meth:`out_of_order`,
:meth:`update_failed`,
:meth:`check_appearance_changes` (logs each new appearance change) and, once per period,
:meth:`publish` (which ends the period with :meth:`roll`); :meth:`build` may run in any thread (the control thread answers
``status`` with it). The systemd status line is :meth:`line`.

Usage::

    status = StatusReporter(mailbox, workers, map_info, simulated=False, sources=...)
    status.pose_published(stamp)          # after each published pose
    status.roll(time.monotonic())         # once per status period
    msg = status.build()
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.interfaces import DeviceHealth, HealthState
from lino_loc import __version__
from services.messages import (
    ActiveVisionInfo,
    DeviceHealthModel,
    LatencyStats,
    LiveViewInfo,
    MapInfo,
    PersistenceInfo,
    PosePortInfo,
    RecordingInfo,
    StatusMessage,
)

log = logging.getLogger("lino_loc.service")

DEVICES = ("camera", "head", "odometry")

#: Seconds between two status messages (topic ``status``: once a second, docs/zeromq.md).
STATUS_PERIOD_S = 1.0

#: Latencies kept between two status messages (the oldest are dropped beyond this).
LATENCY_WINDOW = 10000

#: Seconds between two log lines about failed updates of an exception type already logged
#: (each new type is logged at once, with its traceback).
UPDATE_ERROR_LOG_PERIOD_S = 60.0


def percentile(values: list[float], q: float) -> float | None:
    """The ``q``-th percentile of ``values`` (numpy's linear interpolation); None if empty."""
    return float(np.percentile(np.asarray(values), q)) if values else None


def map_info(amap: Any, configured_path: Any) -> MapInfo:
    """What the status says of the map: its path (the map's own, else the configured one),
    number of images, channels and checksum (None when the map has no header)."""
    checksum = None
    try:
        checksum = amap.meta.sha256
    except Exception:  # noqa: BLE001 - a duck-typed map may have no header
        pass
    path = getattr(amap, "path", None) or configured_path
    return MapInfo(
        path=str(path),
        n_images=int(np.asarray(amap.poses).shape[0]),
        channels=sorted(amap.channels),
        checksum=checksum,
    )


@dataclass(frozen=True)
class StatusSources:
    """Where the reporter reads what others own: the filter's state (``"starting"`` before
    the first estimate), its count of appearance changes, the active-vision switches, the
    saved pose's story (how the belief started, the saves) and the pose port's subscribers."""

    state: Callable[[], str]
    appearance_changes: Callable[[], int]
    active_vision: Callable[[], ActiveVisionInfo | None]
    persistence: Callable[[], PersistenceInfo | None] = lambda: None
    pose_port: Callable[[], PosePortInfo | None] = lambda: None
    control_refused_handshakes: Callable[[], int] = lambda: 0
    recording: Callable[[], RecordingInfo | None] = lambda: None
    live_view: Callable[[], LiveViewInfo | None] = lambda: None
    standing_matches: Callable[[], int] = lambda: 0
    standing_relocations: Callable[[], int] = lambda: 0


class StatusReporter:
    """Rates, latency, counters and the status message (module docstring). Thread-safe."""

    def __init__(
        self,
        mailbox: Any,
        workers: Mapping[str, Any],
        map_info: MapInfo,
        *,
        simulated: bool,
        sources: StatusSources,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.mailbox = mailbox
        self.workers = workers
        self.map_info = map_info
        self.simulated = simulated
        self.sources = sources
        self._clock = clock
        self._lock = threading.Lock()
        self._started = clock()
        self._period_start = self._started
        self._period_poses = 0
        self._period_frames = 0
        self._latencies: collections.deque[float] = collections.deque(maxlen=LATENCY_WINDOW)
        self.latency = LatencyStats()
        self.rates = (0.0, 0.0)
        self.out_of_order_frames = 0
        self.update_errors = 0
        self._error_types: set[str] = set()
        self._errors_unlogged = 0
        self._next_error_log = 0.0
        self.appearance_changes_logged = 0
        self.last: StatusMessage | None = None

    # ------------------------------------------------------------------ fed by the loop
    def pose_published(self, stamp: float, now: float | None = None) -> None:
        """One pose published for a frame taken at ``stamp`` (s since the epoch)."""
        now = time.time() if now is None else now
        with self._lock:
            self._latencies.append(max(0.0, (now - stamp) * 1000.0))
            self._period_poses += 1

    def frame_taken(self) -> None:
        """One camera frame taken by the loop (used or for prediction only)."""
        with self._lock:
            self._period_frames += 1

    def out_of_order(self) -> None:
        """One frame skipped: not newer than the last one used."""
        with self._lock:
            self.out_of_order_frames += 1

    def update_failed(self, exc: BaseException) -> None:
        """One frame's update raised ``exc`` (the loop skipped that frame): counted; logged
        with its traceback the first time its type is seen, else at most once per
        :data:`UPDATE_ERROR_LOG_PERIOD_S` with the number of failures since the last line."""
        kind = type(exc).__name__
        now = self._clock()
        with self._lock:
            self.update_errors += 1
            total = self.update_errors
            new = kind not in self._error_types and len(self._error_types) < 64
            if new:
                self._error_types.add(kind)
            self._errors_unlogged += 1
            due = new or now >= self._next_error_log
            if due:
                unlogged, self._errors_unlogged = self._errors_unlogged, 0
                self._next_error_log = now + UPDATE_ERROR_LOG_PERIOD_S
        if new:
            log.error("frame update failed (%d so far), frame skipped: %s: %s", total, kind, exc,
                      exc_info=exc)
        elif due:
            log.error("frame update failed again (%d since the last report, %d so far): %s: %s",
                      unlogged, total, kind, exc)

    def check_appearance_changes(self) -> int:
        """Log each appearance change the filter found since the last call (lights switched:
        the filter relearns the views); returns the count since start."""
        n = int(self.sources.appearance_changes())
        if n > self.appearance_changes_logged:
            self.appearance_changes_logged = n
            log.info("the views became less familiar all at once (lights switched?): the filter "
                     "relearns what they look like (appearance change %d)", n)
        return n

    def roll(self, mono: float | None = None) -> None:
        """End the period at ``mono`` (monotonic s): rates and latency figures of the period."""
        mono = self._clock() if mono is None else mono
        with self._lock:
            dt = max(mono - self._period_start, 1e-6)
            lat = list(self._latencies)
            self._latencies.clear()
            self.rates = (self._period_poses / dt, self._period_frames / dt)
            if lat:
                self.latency = LatencyStats(p50=percentile(lat, 50), p99=percentile(lat, 99))
            self._period_poses = self._period_frames = 0
            self._period_start = mono

    # ------------------------------------------------------------------ read anywhere
    def device_health(self) -> dict[str, DeviceHealth]:
        """The health of each device worker; a missing worker is FAILED ("not started")."""
        out = {}
        for name in DEVICES:
            w = self.workers.get(name)
            out[name] = (
                w.health() if w is not None else DeviceHealth(HealthState.FAILED, f"{name}: not started")
            )
        return out

    def dropped_frames(self) -> int:
        """Frames dropped since start: replaced in the mailbox, plus the camera's own drops."""
        n = int(self.mailbox.dropped)
        cam = self.workers.get("camera")
        if cam is not None:
            c = cam.health().counters
            n += int(c.get("dropped", 0)) + int(c.get("frames_dropped", 0))
        return n

    def build(self) -> StatusMessage:
        """The status message now."""
        health = self.device_health()
        av = self.sources.active_vision()
        with self._lock:
            latency, (pose_rate, frame_rate) = self.latency, self.rates
            out_of_order, update_errors = self.out_of_order_frames, self.update_errors
        return StatusMessage(
            stamp=time.time(),
            state=self.sources.state(),  # type: ignore[arg-type]
            pose_rate_hz=pose_rate,
            frame_rate_hz=frame_rate,
            frames=self.mailbox.received,
            dropped_frames=self.dropped_frames(),
            out_of_order_frames=out_of_order,
            update_errors=update_errors,
            appearance_changes=self.sources.appearance_changes(),
            standing_matches=self.sources.standing_matches(),
            standing_relocations=self.sources.standing_relocations(),
            latency_ms=latency,
            devices={k: DeviceHealthModel.from_health(h) for k, h in health.items()},
            uptime_s=self._clock() - self._started,
            map=self.map_info,
            active_vision=av,
            persistence=self.sources.persistence(),
            pose_port=self.sources.pose_port(),
            control_refused_handshakes=self.sources.control_refused_handshakes(),
            recording=self.sources.recording(),
            live_view=self.sources.live_view(),
            simulated=self.simulated,
            version=__version__,
        )

    def publish(self, mono: float | None = None) -> StatusMessage:
        """End the period (:meth:`roll`) and build the message of it, kept as :attr:`last`."""
        self.roll(mono)
        msg = self.build()
        with self._lock:
            self.last = msg
        return msg


def status_line(msg: StatusMessage | None, endpoint: str, dead_reckoning: bool) -> str:
    """The one-line status for systemd: state, pose rate, dropped frames, dead reckoning,
    devices not ok; ``serving on ENDPOINT: starting`` before the first status message."""
    if msg is None:
        return f"serving on {endpoint}: starting"
    bad = [f"{k} {v.state}" for k, v in msg.devices.items() if v.state != "ok"]
    text = f"{msg.state} at {msg.pose_rate_hz:.1f} Hz, {msg.dropped_frames} frames dropped"
    if dead_reckoning:
        text += ", DEAD RECKONING (no camera)"
    if bad:
        text += "; " + ", ".join(bad)
    return text
