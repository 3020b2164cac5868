"""Where the robot stood when a survey frame was taken: the survey's pose sources.

- :class:`PoseTrack`: stamped robot poses (s since the epoch; m, m, rad), in stamp order,
  interpolated at a frame's stamp: linear in x, y and in the unwrapped heading between the
  two samples around the stamp. :meth:`PoseTrack.at` returns None when the stamp is outside
  the track, or when the two samples around it are more than ``max_gap`` s apart (a gap of
  the source: no pose is guessed across it).
- :func:`read_tum_track`: a TUM trajectory file (``stamp tx ty tz qx qy qz qw`` per line,
  ``#`` comments) of the ROBOT BASE in the map frame, z up: x, y of the position and the yaw
  of the rotation about z. The file may still be growing (another localization system
  writing it during the survey): :class:`TumFilePoses` reads it again when a stamp is past its
  end. LinoLocError naming the file and the line for a malformed line.
- :class:`StreamPoses`: a ZeroMQ SUB socket receiving the project's own ``pose`` messages
  (:class:`services.messages.PoseMessage`: the stamp and the robot pose; docs/zeromq.md) or
  ``truth`` messages (:class:`services.messages.TruthMessage`), collected by a thread into a
  :class:`PoseTrack`. A message that does not decode is counted and skipped.
- :class:`OdometryPoses`: dead reckoning from a known start pose, composing the odometry
  increments (:class:`services.device_threads.OdometryBuffer`) up to each frame's stamp. It
  drifts without bound (wheel slip, the track width's error): the survey warns.

Every source has ``pose_at(stamp, timeout) -> (x, y, theta) | None``, waiting up to
``timeout`` s for the source to cover the stamp.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from lino_loc.errors import LinoLocError
from lino_loc.poses import compose, wrap_angle

log = logging.getLogger("lino_loc.survey")

Pose = tuple[float, float, float]

#: Default largest gap (s) between two samples of an external source that a pose is interpolated across.
MAX_GAP_S = 0.5


class PoseSource(Protocol):
    def pose_at(self, stamp: float, timeout: float = 0.0) -> Pose | None: ...

    def close(self) -> None: ...


class PoseTrack:
    """Stamped poses, interpolated at a stamp (see the module docstring). Thread-safe."""

    def __init__(self, max_gap: float = MAX_GAP_S) -> None:
        self.max_gap = float(max_gap)
        self._lock = threading.Condition()
        self._t: list[float] = []
        self._p: list[Pose] = []
        self.out_of_order = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._t)

    @property
    def last_stamp(self) -> float | None:
        with self._lock:
            return self._t[-1] if self._t else None

    def add(self, stamp: float, pose: Pose) -> None:
        """Append a sample; one not newer than the last is counted and dropped."""
        with self._lock:
            if self._t and stamp <= self._t[-1]:
                self.out_of_order += 1
                return
            self._t.append(float(stamp))
            self._p.append((float(pose[0]), float(pose[1]), float(pose[2])))
            self._lock.notify_all()

    def at(self, stamp: float) -> Pose | None:
        """The interpolated pose at ``stamp``, or None (outside, or across a gap)."""
        with self._lock:
            ts = self._t
            if not ts or stamp < ts[0] or stamp > ts[-1]:
                return None
            i = bisect.bisect_left(ts, stamp)
            if ts[i] == stamp:
                return self._p[i]
            t0, t1 = ts[i - 1], ts[i]
            if t1 - t0 > self.max_gap:
                return None
            a, b = self._p[i - 1], self._p[i]
        f = (stamp - t0) / (t1 - t0)
        dth = float(wrap_angle(b[2] - a[2]))
        return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), float(wrap_angle(a[2] + f * dth)))

    def wait_past(self, stamp: float, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a sample at or after ``stamp``; whether there is one."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while not (self._t and self._t[-1] >= stamp):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(left)
            return True

    def pose_at(self, stamp: float, timeout: float = 0.0) -> Pose | None:
        self.wait_past(stamp, timeout)
        return self.at(stamp)

    def close(self) -> None:
        pass


def yaw_of_quaternion(qx: float, qy: float, qz: float, qw: float) -> float:
    """Heading (rad) of the x axis of the rotation (qx, qy, qz, qw) projected on the floor."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def parse_tum_lines(lines: list[str], name: str, first_line: int = 1) -> list[tuple[float, Pose]]:
    """(stamp, pose) of TUM trajectory lines (see the module docstring)."""
    out = []
    for n, line in enumerate(lines, start=first_line):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 8:
            raise LinoLocError(f"{name}: line {n}: expected 8 numbers (stamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            v = [float(p) for p in parts]
        except ValueError:
            raise LinoLocError(f"{name}: line {n}: not a number in {s[:80]!r}") from None
        if not all(math.isfinite(x) for x in v):
            raise LinoLocError(f"{name}: line {n}: not finite: {s[:80]!r}")
        q = np.array(v[4:8])
        norm = float(np.linalg.norm(q))
        if not 0.5 < norm < 1.5:
            raise LinoLocError(f"{name}: line {n}: the quaternion's norm is {norm:.3g}, not 1")
        qx, qy, qz, qw = (q / norm).tolist()
        out.append((v[0], (v[1], v[2], yaw_of_quaternion(qx, qy, qz, qw))))
    return out


def read_tum_track(path: str | Path, max_gap: float = MAX_GAP_S) -> PoseTrack:
    """The whole TUM file ``path`` as a :class:`PoseTrack`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LinoLocError(f"{p}: TUM pose file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LinoLocError(f"{p}: cannot read the TUM pose file: {exc}") from None
    track = PoseTrack(max_gap)
    for t, pose in parse_tum_lines(text.splitlines(), str(p)):
        track.add(t, pose)
    return track


class TumFilePoses:
    """A TUM file as a pose source, read again while a stamp is past its end (it may grow).
    Only whole lines are read (a line still being written is left for the next read)."""

    def __init__(self, path: str | Path, max_gap: float = MAX_GAP_S) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise LinoLocError(f"{self.path}: TUM pose file not found")
        self.track = PoseTrack(max_gap)
        self._offset = 0
        self._line = 1
        self._read_more()

    def _read_more(self) -> None:
        try:
            with open(self.path, "rb") as fh:
                fh.seek(self._offset)
                data = fh.read()
        except OSError as exc:
            raise LinoLocError(f"{self.path}: cannot read the TUM pose file: {exc.strerror or exc}") from None
        whole = data[: data.rfind(b"\n") + 1]
        if not whole:
            return
        try:
            lines = whole.decode("utf-8").splitlines()
        except UnicodeDecodeError:
            raise LinoLocError(f"{self.path}: not a UTF-8 text file") from None
        for t, pose in parse_tum_lines(lines, str(self.path), self._line):
            self.track.add(t, pose)
        self._offset += len(whole)
        self._line += len(lines)

    def pose_at(self, stamp: float, timeout: float = 0.0) -> Pose | None:
        deadline = time.monotonic() + timeout
        while True:
            last = self.track.last_stamp
            if last is not None and last >= stamp:
                return self.track.at(stamp)
            self._read_more()
            last = self.track.last_stamp
            if (last is not None and last >= stamp) or time.monotonic() >= deadline:
                return self.track.at(stamp)
            time.sleep(0.05)

    def close(self) -> None:
        pass


class StreamPoses:
    """``pose`` (or ``truth``) messages from a ZeroMQ PUB endpoint (see the module docstring)."""

    def __init__(self, endpoint: str, context: Any, max_gap: float = MAX_GAP_S,
                 curve: Any = None) -> None:
        import zmq

        self.endpoint = endpoint
        self.track = PoseTrack(max_gap)
        self.received = 0
        self.bad = 0
        self._stop = threading.Event()
        sock = context.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, 10000)
        for topic in (b"pose", b"truth"):
            sock.setsockopt(zmq.SUBSCRIBE, topic)
        try:
            sock.connect(endpoint)
        except zmq.ZMQError as exc:
            sock.close(0)
            raise LinoLocError(f"--pose-stream {endpoint!r}: {exc}") from None
        self._sock = sock
        self._thread = threading.Thread(target=self._run, name="survey-poses", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import zmq

        from services.messages import PoseMessage, TruthMessage, decode

        while not self._stop.is_set():
            try:
                if not self._sock.poll(100):
                    continue
                frames = self._sock.recv_multipart()
            except zmq.ZMQError:
                return
            try:
                _, msg = decode(frames)
            except Exception:  # noqa: BLE001 - a bad message never stops the survey
                self.bad += 1
                continue
            if isinstance(msg, (PoseMessage, TruthMessage)):
                self.received += 1
                self.track.add(float(msg.stamp), msg.pose.as_tuple())

    def pose_at(self, stamp: float, timeout: float = 0.0) -> Pose | None:
        return self.track.pose_at(stamp, timeout)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close(0)


class OdometryPoses:
    """Dead reckoning from ``start`` over an odometry buffer (see the module docstring).

    ``pose_at`` must be called with increasing stamps: the increments up to each stamp are
    taken from the buffer and composed onto the running pose."""

    def __init__(self, start: Pose, buffer: Any) -> None:
        self.pose = np.asarray(start, dtype=np.float64)
        self.buffer = buffer
        self.distance = 0.0
        self.turned = 0.0
        self._stamp = -math.inf

    def pose_at(self, stamp: float, timeout: float = 0.0) -> Pose | None:
        deadline = time.monotonic() + timeout
        while (self.buffer.last_stamp is None or self.buffer.last_stamp < stamp) and time.monotonic() < deadline:
            time.sleep(0.01)
        if stamp >= self._stamp:
            delta, _ = self.buffer.take_until(stamp)
            self.pose = compose(self.pose, delta)
            self.distance += math.hypot(float(delta[0]), float(delta[1]))
            self.turned += abs(float(delta[2]))
            self._stamp = stamp
        return (float(self.pose[0]), float(self.pose[1]), float(self.pose[2]))

    def close(self) -> None:
        pass
