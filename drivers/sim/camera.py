"""The simulated stereo camera, client side: frames from `lino-loc sim` over ZeroMQ.

:class:`SimStereoCamera` implements :class:`drivers.interfaces.StereoCamera` on a ZeroMQ SUB
socket connected to the PUB socket of the simulated robot (:mod:`drivers.sim.robot`, wire
format in :mod:`drivers.sim.frame_transport`). It is the counterpart of the OAK-D adapter:

- ``read(timeout)`` returns the NEWEST frame available: it drains the socket's queue and
  counts the older frames it skipped as ``dropped`` (a localizer wants the latest view, not
  a backlog). Frames lost before they reached this reader (a sequence gap) are counted as
  ``lost``; a malformed message is counted as ``malformed`` and skipped, and leaves the health
  DEGRADED, naming it, until ``MALFORMED_HOLD_S`` after it (so that a few bad messages among
  good frames show in the status, not only in the counters);
- the disparity map is computed on the host with :func:`lino_loc.disparity.compute_disparity`
  (OpenCV StereoBM, sparse), standing in for the OAK-D's on-device stereo; switch it off
  with ``compute_disparity=False``;
- ``open()`` never raises for a missing publisher: ZeroMQ connects (and reconnects after the
  publisher went away and came back) in the background, and the health says what happens:
  DEGRADED until the first frame and whenever no frame came for ``stale_after`` s, FAILED
  after ``fail_after`` s without a frame (or when the endpoint is not a valid address).

Not thread-safe across ``read`` calls from several threads (one consumer, as with the OAK-D);
``close`` may be called from another thread.

Usage::

    cam = SimStereoCamera("tcp://127.0.0.1:5560"); cam.open()
    frame = cam.read(timeout=0.5)          # StereoFrame (newest) or None
    cam.health().counters["dropped"]; cam.close()
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import replace

import zmq

from drivers.interfaces import DeviceHealth, HealthState, HealthTracker, StereoFrame
from drivers.sim.frame_transport import FRAME_TOPIC, FrameError, decode_frame
from lino_loc.disparity import StereoConfig, compute_disparity
from lino_loc.errors import LinoLocError

log = logging.getLogger("lino_loc.drivers.sim_camera")

#: A malformed message keeps the health DEGRADED, naming it, for this long after it, s (twice
#: the daemon's status period: at least one status shows it), even while good frames arrive.
MALFORMED_HOLD_S = 2.0


class SimStereoCamera:
    """:class:`~drivers.interfaces.StereoCamera` fed by the simulated robot's frame publisher."""

    def __init__(
        self,
        endpoint: str,
        stereo: StereoConfig | None = None,
        *,
        compute_disparity: bool = True,
        rcvhwm: int = 4,
        stale_after: float = 1.0,
        fail_after: float = 10.0,
        context: zmq.Context | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.stereo = stereo or StereoConfig()
        self.compute_disparity = compute_disparity
        self.rcvhwm = rcvhwm
        self.stale_after = stale_after
        self.fail_after = fail_after
        self._ctx = context
        self._own_ctx = context is None
        self._sock: zmq.Socket | None = None
        self._lock = threading.Lock()
        self._health = HealthTracker(
            ("frames", "dropped", "lost", "malformed", "disparity_errors", "publisher_restarts")
        )
        self._health.error(f"sim camera: not opened ({endpoint})", HealthState.FAILED)
        self._opened_mono: float | None = None
        self._last_frame_mono: float | None = None
        self._last_malformed = -math.inf  # monotonic time of the last malformed message
        self._last_seq: int | None = None
        self._bad_endpoint = False

    # lifecycle ---------------------------------------------------------------------------------
    def open(self) -> bool:
        """Connect the SUB socket (never raises for a missing publisher). False only if the
        endpoint is not a valid address; True does not mean frames arrive (see health)."""
        with self._lock:
            if self._sock is not None:
                return True
            if self._ctx is None:
                self._ctx = zmq.Context()
            sock = self._ctx.socket(zmq.SUB)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.RCVHWM, self.rcvhwm)
            sock.setsockopt(zmq.SUBSCRIBE, FRAME_TOPIC)
            self._opened_mono = time.monotonic()
            try:
                sock.connect(self.endpoint)
            except zmq.ZMQError as exc:
                sock.close(0)
                self._bad_endpoint = True
                self._health.error(
                    f"sim camera: cannot connect to {self.endpoint!r}: {exc}", HealthState.FAILED
                )
                log.error("sim camera: cannot connect to %r: %s", self.endpoint, exc)
                return False
            self._sock = sock
            self._bad_endpoint = False
            self._health.error(f"sim camera: waiting for the first frame from {self.endpoint}")
            return True

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close(0)
                self._sock = None
            if self._own_ctx and self._ctx is not None:
                self._ctx.term()
                self._ctx = None
            self._opened_mono = None
            self._health.set_state(HealthState.FAILED)

    def __enter__(self) -> SimStereoCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # health ------------------------------------------------------------------------------------
    def health(self) -> DeviceHealth:
        """OK while frames arrive; DEGRADED before the first one and after ``stale_after`` s
        without one; FAILED after ``fail_after`` s without one, when closed or unreachable."""
        now = time.monotonic()
        state = self._health.state
        if self._sock is None or self._opened_mono is None:
            if state is not HealthState.FAILED:
                self._health.set_state(HealthState.FAILED)
            return self._health.snapshot()
        since = self._last_frame_mono if self._last_frame_mono is not None else self._opened_mono
        quiet = now - since
        if quiet > self.fail_after and state is not HealthState.FAILED:
            self._health.error(
                f"sim camera: no frame from {self.endpoint} for {quiet:.1f} s", HealthState.FAILED
            )
        elif quiet > self.stale_after and state is HealthState.OK:
            self._health.error(
                f"sim camera: no frame from {self.endpoint} for more than {self.stale_after:g} s"
            )
        return self._health.snapshot()

    # reading -----------------------------------------------------------------------------------
    def read(self, timeout: float | None = None) -> StereoFrame | None:
        """The newest frame available (older queued ones are dropped and counted), waiting up to
        ``timeout`` s for one (``None`` or 0: do not wait). None if there is none."""
        with self._lock:
            sock = self._sock
            if sock is None:
                if timeout:
                    time.sleep(timeout)
                return None
            deadline = time.monotonic() + (timeout or 0.0)
            newest: StereoFrame | None = None
            while True:
                newest = self._drain(sock, newest)
                if newest is not None:
                    break
                left = deadline - time.monotonic()
                if left <= 0 or not sock.poll(max(1, int(left * 1000)), zmq.POLLIN):
                    break
            if newest is None:
                self.health()
                return None
            self._last_frame_mono = time.monotonic()
        self._health.count("frames")
        held = time.monotonic() - self._last_malformed < MALFORMED_HOLD_S
        if self._health.state is not HealthState.OK and not held:
            log.info("sim camera: frames arriving from %s", self.endpoint)
            self._health.set_state(HealthState.OK)
        if self.compute_disparity:
            newest = self._with_disparity(newest)
        return newest

    def _drain(self, sock: zmq.Socket, newest: StereoFrame | None) -> StereoFrame | None:
        """Receive everything queued; keep the newest valid frame, count the rest."""
        while True:
            try:
                parts = sock.recv_multipart(zmq.NOBLOCK, copy=True)
            except zmq.Again:
                return newest
            except zmq.ZMQError as exc:  # socket closed under us
                self._health.error(f"sim camera: receive failed: {exc}")
                return newest
            try:
                frame = decode_frame(parts)
            except FrameError as exc:
                self._health.count("malformed")
                self._last_malformed = time.monotonic()
                self._health.error(f"sim camera: malformed frame skipped: {exc}")
                log.warning("sim camera: malformed frame skipped: %s", exc)
                continue
            self._track_seq(frame.sequence)
            if newest is not None:
                self._health.count("dropped")
            newest = frame

    def _track_seq(self, seq: int) -> None:
        last = self._last_seq
        if last is not None:
            if seq > last + 1:
                self._health.count("lost", seq - last - 1)
            elif seq <= last:
                self._health.count("publisher_restarts")
                log.info(
                    "sim camera: frame sequence restarted (%d after %d): publisher restarted",
                    seq,
                    last,
                )
        self._last_seq = seq

    def _with_disparity(self, frame: StereoFrame) -> StereoFrame:
        if frame.right is None:
            return frame
        try:
            disp = compute_disparity(frame.left, frame.right, self.stereo)
        except LinoLocError as exc:  # e.g. an image too small for the matcher's search range
            self._health.count("disparity_errors")
            self._health.error(f"sim camera: no disparity: {exc}")
            return frame
        return replace(frame, disparity=disp)
