"""The daemon's recorder: ``[recording]`` and a bounded queue to a writer thread.

The loop (and the odometry, head and truth threads) hand events to :class:`Recorder`; each
hand-over is a ``put_nowait`` on a bounded queue and never waits: when the queue is full
(more than :data:`MAX_QUEUED` events, or :data:`MAX_QUEUED_FRAMES` frames, about 2 s at
15 fps) the event is dropped and counted (``status.recording.dropped``). The writer thread
encodes (PNG, protobuf, JSON: :mod:`services.recording.topic_messages`) and writes them to
the session's MCAP file (:class:`services.recording.session_file.SessionFile`), flushing a
chunk every :data:`FLUSH_PERIOD_S`, so a kill -9 loses at most that plus what was queued.
An error of the file (a bad path, a full disk) is logged once and reported in the status
(``recording.error``); recording stops, the daemon goes on.

What is recorded (docs/recording.md): every frame the loop took, with the exact inputs of its
``Localizer.update`` (``/localizer/input``: the composed action, the pan, the image used or
not), dead reckoning, every belief change (the start, the control socket, the reset after
failed updates), every odometry increment and head reading as the drivers gave them, the
published poses, the particles at ``particles_rate_hz`` (by the frames' stamps), the status,
and in simulation the truth.

Usage::

    rec = Recorder.open(cfg.recording, metadata)   # Recorder.off() records nothing
    rec.start(); rec.frame(frame, record); rec.pose(msg); ...; rec.close()
"""

from __future__ import annotations

import functools
import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.messages import RecordingInfo
from services.recording import topic_messages as tm

log = logging.getLogger("lino_loc.service.recording")

#: Events the queue holds at most (odometry 50/s, head ~50/s, frames, poses: ~10 s).
MAX_QUEUED = 2000
#: Frames the queue holds at most (2 s at 15 fps; ~0.4 MB each with disparity).
MAX_QUEUED_FRAMES = 30
#: s between two flushes of the file (a chunk ended, written to the OS): what a kill -9 loses.
FLUSH_PERIOD_S = 0.5


def _never_raises(method: Callable[..., None]) -> Callable[..., None]:
    """A hand-over that cannot fail its caller (the loop, a device thread): an exception is
    logged (the first of each method with its traceback) and counted as a dropped event."""
    seen: list[bool] = []

    @functools.wraps(method)
    def guarded(self: Recorder, *args: Any, **kwargs: Any) -> None:
        try:
            method(self, *args, **kwargs)
        except Exception:  # noqa: BLE001 - recording must never stop the loop
            self.dropped += 1
            if not seen:
                seen.append(True)
                log.exception("recording: %s failed (event dropped; logged once)", method.__name__)

    return guarded


class RecordingConfig(BaseModel):
    """The ``[recording]`` section (``lino-loc run --record FILE`` turns it on for FILE)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="record every session")
    path: Path = Field(
        Path("~/.local/state/lino-loc/recordings"),
        description="a directory (one lino-YYYYmmdd-HHMMSS.mcap per session) or a .mcap file",
        validate_default=True,
    )
    rotate_mb: float = Field(
        1024.0, ge=0.0, description="start the next part when a file reaches this many MB (0: never)"
    )
    particles_rate_hz: float = Field(
        2.0, ge=0.0, le=30.0, description="particle sets recorded per second of frames (0: none)"
    )
    particles_max_count: int = Field(
        500, ge=1, description="particles per recorded set (every k-th when the filter has more)"
    )

    @field_validator("path")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        if str(v).strip() == "":
            raise ValueError("an empty path: give a directory or a .mcap file")
        return v.expanduser()

    def session_path(self, now: float | None = None) -> Path:
        """The session's file: ``path`` itself when it ends in ``.mcap``, else a new file
        named by the UTC start time in the directory ``path``."""
        path = self.path.expanduser()
        if path.suffix == ".mcap":
            return path
        when = datetime.fromtimestamp(time.time() if now is None else now, UTC)
        return path / f"lino-{when:%Y%m%d-%H%M%S}.mcap"


def subsample(poses: np.ndarray, max_count: int) -> np.ndarray:
    """Every k-th row, ``k = ceil(n / max_count)`` (deterministic, no random draws)."""
    n = poses.shape[0]
    return poses if n <= max_count else poses[:: -(-n // max_count)]


class Recorder:
    """The recorder (module docstring). ``Recorder.off()`` is one that records nothing."""

    def __init__(self, cfg: RecordingConfig | None, metadata: dict[str, Any] | None = None,
                 scene: Any = None) -> None:
        self.cfg = cfg or RecordingConfig()
        self.scene = scene  # the map's survey poses and outline (live_view.MapScene), or None
        self.enabled = cfg is not None
        self.metadata = dict(metadata or {})
        self.path = self.cfg.session_path() if self.enabled else None
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(MAX_QUEUED)
        self._frames_queued = 0
        self._lock = threading.Lock()
        self._seq = itertools.count()
        self._input_seq = itertools.count()
        self._next_particles: float | None = None
        self._thread: threading.Thread | None = None
        self._file: Any = None
        self.dropped = 0
        self.messages = 0
        self.error: str | None = None
        self._bad_kinds: set[str] = set()

    @classmethod
    def off(cls) -> Recorder:
        return cls(None)

    # ------------------------------------------------------------------ hand-over (any thread)
    def _put(self, event: tuple[Any, ...], frame: bool = False) -> None:
        if not self.enabled:
            return
        with self._lock:
            full = self.error is not None or (frame and self._frames_queued >= MAX_QUEUED_FRAMES)
            if not full:
                try:
                    self._queue.put_nowait((next(self._seq), time.time_ns(), frame, *event))
                    self._frames_queued += frame
                    return
                except queue.Full:
                    pass
            self.dropped += 1

    def _input(self, kind: str, stamp: float, **fields: Any) -> dict[str, Any]:
        return {"seq": next(self._input_seq), "kind": kind, "stamp": float(stamp), **fields}

    @_never_raises
    def frame(self, stamp: float, left: np.ndarray | None, disparity_map: np.ndarray | None,
              /, **inputs: Any) -> None:
        """A frame the loop took and its update's inputs (``channels.InputRecord`` fields)."""
        if self.enabled:
            self._put(("frame", float(stamp), left, disparity_map, self._input("update", stamp, **inputs)), True)

    @_never_raises
    def call(self, kind: str, stamp: float | None = None, **fields: Any) -> None:
        """A call on the Localizer other than a frame's update (predict, set_pose, start_global)."""
        if self.enabled:
            self._put(("input", self._input(kind, time.time() if stamp is None else stamp, **fields)))

    @_never_raises
    def pose(self, msg: BaseModel | None) -> None:
        if msg is not None and self.enabled:
            self._put(("pose", msg))

    @_never_raises
    def particles(self, stamp: float, particles: Callable[[], tuple[np.ndarray, np.ndarray]]) -> None:
        """The particle set, at most ``particles_rate_hz`` times per second of frame stamps."""
        rate = self.cfg.particles_rate_hz
        if not self.enabled or rate <= 0 or (self._next_particles is not None and stamp < self._next_particles):
            return
        self._next_particles = stamp + 1.0 / rate
        poses, _ = particles()
        self._put(("particles", float(stamp), subsample(np.asarray(poses), self.cfg.particles_max_count)))

    @_never_raises
    def odometry(self, increments: list[Any]) -> None:
        if self.enabled and increments:
            self._put(("odometry", [
                {"stamp": float(i.stamp), "dt": float(i.dt), "dx": float(i.dx), "dy": float(i.dy),
                 "dtheta": float(i.dtheta), "sequence": int(i.sequence)} for i in increments]))

    @_never_raises
    def head(self, state: Any) -> None:
        if self.enabled:
            self._put(("head", {"stamp": float(state.stamp), "pan": float(state.pan),
                                "tilt": float(state.tilt), "moving": bool(state.moving)}))

    @_never_raises
    def status(self, msg: BaseModel) -> None:
        if self.enabled:
            self._put(("status", msg))

    @_never_raises
    def truth(self, truth_json: bytes) -> None:
        if self.enabled:
            self._put(("truth", bytes(truth_json)))

    def info(self) -> RecordingInfo | None:
        """What the status says of the recording (None when off)."""
        if not self.enabled:
            return None
        f = self._file
        try:  # read from the status thread while the writer writes: plain values only
            files = list(f.files) if f is not None else []
            megabytes = round((f.bytes_written if f is not None else 0) / 1e6, 3)
        except Exception:  # noqa: BLE001 - the status must never fail on the recorder
            files, megabytes = [], 0.0
        return RecordingInfo(
            file=str(files[-1] if files else self.path), files=len(files), megabytes=megabytes,
            messages=self.messages, dropped=self.dropped, error=self.error,
        )

    # ------------------------------------------------------------------ the writer thread
    def start(self) -> None:
        if self.enabled and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
            self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued, finish the file (idempotent)."""
        if self._thread is None:
            return
        try:
            self._queue.put(None, timeout=timeout)  # after what is queued
        except queue.Full:
            log.error("recording: the writer did not drain its queue in %.0f s", timeout)
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.error("recording: the writer did not finish %s in %.0f s", self.path, timeout)
        self._thread = None

    def _run(self) -> None:
        from services.recording.session_file import SessionFile

        try:
            assert self.path is not None
            self._file = SessionFile(self.path, self.metadata, self.cfg.rotate_mb, self._preamble())
            log.info("recording to %s", self.path)
        except Exception as exc:  # noqa: BLE001 - a bad path must not stop the daemon
            self._failed(exc)
        next_flush = time.monotonic() + FLUSH_PERIOD_S
        while True:
            try:
                event = self._queue.get(timeout=max(0.0, next_flush - time.monotonic()))
            except queue.Empty:
                event = ()
            if event is None:
                break
            if event:
                self._write(event)
            if time.monotonic() >= next_flush:
                self._guard(lambda f: f.flush())
                next_flush = time.monotonic() + FLUSH_PERIOD_S
        self._guard(lambda f: f.close())

    def _preamble(self) -> tm.Messages:
        """/map/survey and /map/outline, written at the start of each part (none without a
        scene; a scene that cannot be encoded is logged and left out)."""
        s = self.scene
        if s is None:
            return []
        try:
            return tm.map_messages(s.poses, s.outline, time.time(), s.outline_what)
        except Exception as exc:  # noqa: BLE001 - the map drawing is not worth the session
            log.warning("recording: the map's drawing left out: %s", exc)
            return []

    def _write(self, event: tuple[Any, ...]) -> None:
        seq, wall_ns, frame, kind, *args = event
        if frame:
            with self._lock:
                self._frames_queued -= 1
        if self._file is None or self.error is not None:
            return
        try:
            messages = _messages(kind, args)
        except Exception as exc:  # noqa: BLE001 - one bad event is skipped, counted
            if kind not in self._bad_kinds:
                self._bad_kinds.add(kind)
                log.warning("recording: a %s event could not be encoded (skipped, counted as "
                            "dropped; logged once): %s", kind, exc)
            self.dropped += 1
            if kind != "frame":
                return
            messages = tm.input_messages(args[3])  # the call itself, without its images

        def write(f: Any) -> None:
            for topic, log_ns, data in messages:
                f.write(topic, log_ns, wall_ns, data, seq)
                self.messages += 1

        self._guard(write)

    def _guard(self, action: Callable[[Any], None]) -> None:
        if self._file is None or self.error is not None:
            return
        try:
            action(self._file)
        except Exception as exc:  # noqa: BLE001 - disk full etc.: stop recording, keep serving
            self._failed(exc)

    def _failed(self, exc: BaseException) -> None:
        self.error = f"{self.path}: {type(exc).__name__}: {exc}"
        log.error("recording stopped: %s (the daemon goes on)", self.error)


def _messages(kind: str, args: list[Any]) -> tm.Messages:
    """The topic messages of one queued event."""
    if kind == "frame":  # the images first: a replay reads a frame's images, then its input
        stamp, left, disparity, record = args
        return tm.frame_messages(stamp, left, disparity) + tm.input_messages(record)
    if kind == "input":
        return tm.input_messages(args[0])
    if kind == "pose":
        msg = args[0]
        return tm.pose_messages(msg.model_dump_json().encode(), msg.model_dump())
    if kind == "particles":
        return tm.particles_messages(args[0], args[1])
    if kind == "odometry":
        return tm.odometry_messages(args[0])
    if kind == "head":
        return tm.head_messages(args[0])
    if kind == "status":
        msg = args[0]
        return tm.status_messages(msg.model_dump_json().encode(), float(msg.stamp))
    if kind == "truth":
        return tm.truth_messages(args[0])
    raise ValueError(f"unknown event {kind!r}")


class BeliefTap:
    """The Localizer as seen by one caller that changes the belief: ``set_pose`` and
    ``start_global`` are recorded on ``/localizer/input`` (with ``cause``) before they run;
    everything else is the Localizer's own."""

    def __init__(self, localizer: Any, recorder: Recorder, cause: str) -> None:
        self._localizer = localizer
        self._recorder = recorder
        self._cause = cause

    def __getattr__(self, name: str) -> Any:
        return getattr(self._localizer, name)

    def set_pose(self, mean: Any, cov: Any, confirmed: bool = True) -> Any:
        self._recorder.call(
            "set_pose", mean=[float(v) for v in np.asarray(mean, dtype=np.float64).reshape(-1)],
            cov=[float(v) for v in np.asarray(cov, dtype=np.float64).reshape(-1)],
            confirmed=bool(confirmed), cause=self._cause,
        )
        return self._localizer.set_pose(mean, cov, confirmed=confirmed)

    def start_global(self) -> Any:
        self._recorder.call("start_global", cause=self._cause)
        return self._localizer.start_global()


def tap(localizer: Any, recorder: Recorder, cause: str) -> Any:
    """``localizer`` itself when ``recorder`` is off, else a :class:`BeliefTap`."""
    return BeliefTap(localizer, recorder, cause) if recorder.enabled else localizer
