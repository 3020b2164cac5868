"""Map refresh: the daemon writes the views it is confident about into a dataset for a later
``lino-loc map extend`` (the ``[map_refresh]`` section, off by default).

While the daemon localizes, every frame whose image was used (the head at rest) is offered
with the estimate's camera pose (:func:`lino_loc.poses.camera_pose` of the robot pose and the
pan), its ``quality`` (``lino_loc.quality``) and state. It is kept when the state is
``tracking``, the quality is at least ``min_quality``, and the camera moved at least
``min_distance_m`` or turned ``min_turn_deg`` since the last kept view (a robot standing
still would otherwise fill the disk with one view), up to ``max_views`` per session.

Files: one folder per daemon session, ``PATH/refresh-YYYYmmdd-HHMMSS/``, holding dataset
folders ``part-000001``, ``part-000002``, ... (:class:`lino_loc.dataset.DatasetWriter`:
images, disparity when the frame has it, the camera pose, the stamp and ``condition``). A
part is finalised (its ``poses.csv`` and ``dataset.json`` written atomically) every
``part_views`` views, ``part_seconds`` after its first view, and at shutdown, so a kill -9
loses at most the open part (its images stay on disk without a ``dataset.json``: no dataset
reader takes that folder). Extend a map with the finished parts::

    lino-loc map extend MAP PATH/refresh-*/part-* --out MAP2

The daemon's loop only puts the view into a bounded queue (``offer``, never blocking: a full
queue drops the view and counts it); a thread writes. A write error (disk full, a bad path,
an image of another size than the map's camera) is logged (rate-limited), counted, and ends
the open part; the daemon goes on (``info()`` reports the counts).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter
from lino_loc.poses import camera_pose, wrap_angle

log = logging.getLogger(__name__)


class MapRefreshConfig(BaseModel):
    """The ``[map_refresh]`` section."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="write confident views into a dataset for `lino-loc map extend`")
    path: Path = Field(Path("~/.local/state/lino-loc/refresh"), validate_default=True,
                       description="folder; one refresh-YYYYmmdd-HHMMSS/ of part-NNNNNN datasets per daemon session")
    min_quality: float = Field(0.8, ge=0.0, le=1.0, description="keep views whose pose quality is at least this")
    min_distance_m: float = Field(0.25, ge=0.0, description="keep a view only this far from the last kept one ...")
    min_turn_deg: float = Field(10.0, ge=0.0, le=180.0, description="... or turned this much from it")
    condition: str = Field("refresh", description="the rows' condition (e.g. the light: bulb)")
    part_views: int = Field(200, ge=1, description="finalise a part after this many views")
    part_seconds: float = Field(60.0, gt=0.0, description="... or this long after its first view")
    max_views: int = Field(20000, ge=1, description="views written per daemon session at most")
    queue_size: int = Field(8, ge=1, le=1024, description="views waiting for the writer; more are dropped")

    @field_validator("path")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        if str(v).strip() == "":
            raise ValueError("an empty path: give a folder")
        return Path(str(v)).expanduser()

    @field_validator("condition")
    @classmethod
    def _condition(cls, v: str) -> str:
        if v == "" or "," in v or "\n" in v:
            raise ValueError(f"{v!r}: a condition is a non-empty word without commas")
        return v


@dataclass
class _View:
    stamp: float
    image: np.ndarray
    disparity: np.ndarray | None
    pose: np.ndarray  # camera pose (x, y, theta)


class MapRefreshWriter:
    """See the module docstring. ``camera`` is the map's camera (the dataset's ``camera``)."""

    def __init__(self, cfg: MapRefreshConfig, camera: CameraInfo, map_name: str = "") -> None:
        self.cfg = cfg
        self.camera = camera
        self.map_name = map_name
        self.enabled = cfg.enabled
        self._queue: queue.Queue[_View | None] = queue.Queue(maxsize=cfg.queue_size)
        self._thread: threading.Thread | None = None
        self._last: np.ndarray | None = None  # camera pose of the last accepted view
        self.session_dir: Path | None = None
        self._writer: DatasetWriter | None = None
        self._part = 0
        self._part_started = 0.0
        self._lock = threading.Lock()
        self.accepted = 0
        self.written = 0
        self.dropped = 0
        self.errors = 0
        self.parts_done = 0
        self.last_error: str | None = None
        self._last_error_log = -math.inf

    @classmethod
    def for_map(cls, cfg: MapRefreshConfig, amap: Any) -> MapRefreshWriter:
        """The writer of the daemon of ``amap`` (its camera and name), or :meth:`off` when the
        section is off or the map has no camera."""
        cam = getattr(amap, "camera", None)
        if not cfg.enabled or not isinstance(cam, CameraInfo):
            return cls.off()
        return cls(cfg, cam, str(getattr(amap, "name", "") or ""))

    @classmethod
    def off(cls) -> MapRefreshWriter:
        """A writer that keeps nothing."""
        return cls(MapRefreshConfig(), CameraInfo(width=1, height=1, fx=1, fy=1, cx=0, cy=0))

    # ------------------------------------------------------------------ the loop's side
    def start(self) -> None:
        """Start the writer thread (no folder is made before the first kept view)."""
        if not self.enabled or self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="map-refresh", daemon=True)
        self._thread.start()

    def offer(self, stamp: float, image: np.ndarray | None, disparity: np.ndarray | None,
              robot_pose: np.ndarray, pan: float | None, quality: float, state: str) -> bool:
        """Keep the view (its camera pose: ``robot_pose`` turned by the head's ``pan``) if it
        passes the rules (module docstring); True when queued. Never blocks, never raises."""
        try:
            if not self.enabled or image is None or state != "tracking" or not quality >= self.cfg.min_quality:
                return False
            if self.accepted >= self.cfg.max_views or pan is None:
                return False
            pose = camera_pose(np.asarray(robot_pose, dtype=np.float64).reshape(3), float(pan))
            if not np.all(np.isfinite(pose)):
                return False
            if self._last is not None:
                moved = math.hypot(pose[0] - self._last[0], pose[1] - self._last[1])
                turned = abs(float(wrap_angle(pose[2] - self._last[2])))
                if moved < self.cfg.min_distance_m and turned < math.radians(self.cfg.min_turn_deg):
                    return False
            view = _View(float(stamp), np.array(image, copy=True),
                         None if disparity is None else np.array(disparity, copy=True), pose)
            try:
                self._queue.put_nowait(view)
            except queue.Full:
                self.dropped += 1
                return False
            self._last = pose
            self.accepted += 1
            return True
        except Exception as exc:  # noqa: BLE001 - the daemon never dies on a refresh
            self._error(exc)
            return False

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued, finalise the open part, stop the thread (idempotent)."""
        if self._thread is None:
            return
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            log.warning("map refresh: the writer did not keep up; %d views not written", self._queue.qsize())
        self._thread.join(timeout)
        self._thread = None

    def info(self) -> dict[str, Any]:
        """Counts for the status and the log."""
        return {"enabled": self.enabled, "folder": None if self.session_dir is None else str(self.session_dir),
                "accepted": self.accepted, "written": self.written, "parts": self.parts_done,
                "dropped": self.dropped, "errors": self.errors, "last_error": self.last_error}

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=1.0)
            except queue.Empty:
                item = False  # type: ignore[assignment]
            try:
                if item is None:
                    self._finish_part()
                    return
                if item is not False:
                    self._write(item)
                if self._writer is not None and (
                    len(self._writer) >= self.cfg.part_views
                    or time.monotonic() - self._part_started >= self.cfg.part_seconds
                ):
                    self._finish_part()
            except Exception as exc:  # noqa: BLE001 - a write error ends the part, not the daemon
                self._error(exc)
                self._abandon_part()

    def _write(self, v: _View) -> None:
        if self._writer is None:
            if self.session_dir is None:
                self.session_dir = self.cfg.path / time.strftime("refresh-%Y%m%d-%H%M%S", time.gmtime())
                self.session_dir.mkdir(parents=True, exist_ok=True)
            self._part += 1
            meta = DatasetMeta(name=f"refresh-{self.map_name}" if self.map_name else "refresh", camera=self.camera,
                               source="lino-loc run [map_refresh]")
            self._writer = DatasetWriter(self.session_dir / f"part-{self._part:06d}", meta)
            self._part_started = time.monotonic()
        self._writer.add(v.image, v.pose, condition=self.cfg.condition, disparity=v.disparity, stamp=v.stamp)
        self.written += 1

    def _finish_part(self) -> None:
        if self._writer is None:
            return
        w, self._writer = self._writer, None
        if len(w):
            w.close()
            self.parts_done += 1
            log.info("map refresh: wrote %s (%d views)", w.root, len(w))

    def _abandon_part(self) -> None:
        """After a write error: try to finalise what the part holds, else leave it unfinished."""
        w, self._writer = self._writer, None
        if w is None:
            return
        try:
            if len(w):
                w.close()
                self.parts_done += 1
        except Exception as exc:  # noqa: BLE001
            self._error(exc)

    def _error(self, exc: BaseException) -> None:
        self.errors += 1
        self.last_error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        now = time.monotonic()
        if now - self._last_error_log >= 30.0:
            self._last_error_log = now
            log.warning("map refresh: %s (%d errors so far; the daemon goes on)", self.last_error, self.errors)
