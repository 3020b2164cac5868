"""A survey with the robot itself: stops, head sweeps, and a crash-safe dataset folder.

:class:`RobotSurvey` runs a plan (:mod:`services.survey_plan`) with the daemon's device
threads (:mod:`services.device_threads`: the camera worker's newest frame, the head worker's
history of present angles, the odometry buffer) and writes a dataset folder
(docs/datasets.md) through :class:`lino_loc.dataset.DatasetWriter` with its journal.

At each stop (every other one in the reverse order of the sweep, so that the head and the
base go on from where they are), for each base turn of :func:`services.survey_plan.head_sweep`, the mover
(:mod:`services.survey_moves`) brings the robot to (x, y, theta + turn); then for each pan of
that turn the head is commanded there and the first frame is kept that

- was taken after the command (its stamp later than the command's),
- shows the head at rest by :class:`lino_loc.active_vision.HeadSettle` (not moving at the
  frame's stamp, and ``settle_s`` past its last motion), with the pan the head reported at
  the frame's stamp (interpolated in its history) within ``pan_tolerance`` of the goal
  (frames failing these are counted as ``discarded_moving``),
- has a robot pose at its stamp from the pose source (:mod:`services.survey_poses`; with
  the plan as the source, the pose asked of the mover).

Its row: the left image, the right image and the disparity when the camera gives them, the
camera pose ``camera_pose(robot pose, reported pan)`` (:func:`lino_loc.poses.camera_pose`),
the condition and the frame's stamp; the row's journal entry names the capture (stop, base
turn, pan index) and the robot pose. A pan with no such frame within ``pan_timeout`` s is
left out (counted).

Crash safety and resumption: every row is in the journal once :meth:`DatasetWriter.add`
returns (a ``kill -9`` loses no captured image), and ``survey.json`` in the folder records
the plan and the sweep. Run again with the same folder, the survey refuses another plan
(one line), skips every capture the journal holds, and continues with the first stop that
has one missing (only its missing captures are taken). ``poses.csv`` and ``dataset.json``
are written at the end, also when the run is interrupted (SIGINT/SIGTERM, the operator's
quit), so the folder is a valid dataset of what was captured so far.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lino_loc.active_vision import HeadSettle
from lino_loc.atomic_file import atomic_write
from lino_loc.dataset import CameraInfo, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.poses import camera_pose, wrap_angle
from services.survey_plan import Capture, Stop

log = logging.getLogger("lino_loc.survey")

STATE_FILE = "survey.json"
STATE_VERSION = 1


@dataclass(frozen=True)
class CaptureSettings:
    """How a pan's frame is chosen (see the module docstring). Seconds, radians."""

    condition: str
    settle_s: float = 0.2
    pan_tolerance: float = 0.01
    pan_timeout: float = 10.0
    pose_timeout: float = 2.0
    tilt: float = 0.0
    first_frame_timeout: float = 30.0


@dataclass
class SurveyReport:
    dataset: str
    stops: int
    stops_done: int = 0
    stops_skipped: int = 0
    images: int = 0
    images_this_run: int = 0
    resumed_images: int = 0
    pans_missed: int = 0
    discarded_moving: int = 0
    discarded_stale: int = 0
    discarded_no_pose: int = 0
    seconds: float = 0.0
    interrupted: bool = False
    odometry_distance_m: float | None = None
    #: where this run's time went (s): the mover (driving, the operator), the head (from a pan
    #: command until the head stopped moving plus the settle time), waiting for the next frame
    #: after that, and writing the rows
    drive_s: float = 0.0
    head_s: float = 0.0
    frame_wait_s: float = 0.0
    write_s: float = 0.0

    @property
    def images_per_minute(self) -> float:
        return 60.0 * self.images_this_run / self.seconds if self.seconds > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        for k in ("seconds", "drive_s", "head_s", "frame_wait_s", "write_s"):
            out[k] = round(out[k], 3)
        out["images_per_minute"] = round(self.images_per_minute, 2)
        return out


class PlanPoses:
    """The pose source of marked positions: the pose the mover was asked to reach."""

    def __init__(self) -> None:
        self.pose: tuple[float, float, float] | None = None

    def pose_at(self, stamp: float, timeout: float = 0.0) -> tuple[float, float, float] | None:
        return self.pose

    def close(self) -> None:
        pass


@dataclass
class SurveyDevices:
    """The daemon's three device threads for a survey (head, camera; odometry for its buffer)."""

    factories: Any
    workers: dict[str, Any] = field(default_factory=dict)

    def start(self) -> SurveyDevices:
        from services.device_threads import (
            CameraWorker,
            FrameMailbox,
            HeadHistory,
            HeadWorker,
            OdometryBuffer,
            OdometryWorker,
        )

        self.mailbox: Any = FrameMailbox()
        self.heads: Any = HeadHistory(maxlen=2000)
        self.odometry: Any = OdometryBuffer()
        head = HeadWorker(self.factories["head"], self.heads)
        self.workers = {
            "camera": CameraWorker(self.factories["camera"], self.mailbox),
            "odometry": OdometryWorker(self.factories["odometry"], self.odometry),
            "head": head,
        }
        for w in self.workers.values():
            w.start()
        return self

    @property
    def head(self) -> Any:
        return self.workers["head"]

    def health(self) -> str:
        return "; ".join(f"{k}: {w.health().state.value} ({w.health().last_error or 'no error'})"
                         for k, w in self.workers.items())

    def stop(self) -> None:
        for w in self.workers.values():
            w.stop()


def survey_state(stops: list[Stop], sweep: list[Capture], condition: str) -> dict[str, Any]:
    """What ``survey.json`` holds: the plan, the sweep and the condition."""
    return {
        "version": STATE_VERSION,
        "stops": [s.as_list() for s in stops],
        "sweep": [[c.turn_index, c.turn, c.pan_index, c.pan] for c in sweep],
        "condition": condition,
    }


def check_state(out: Path, state: dict[str, Any]) -> None:
    """Write ``survey.json``, or check that the one there is ``state`` (LinoLocError if not)."""
    path = out / STATE_FILE
    if path.is_file():
        try:
            saved = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise LinoLocError(f"{path}: unreadable ({exc}); remove it or use another --out") from None
        for key in ("stops", "sweep", "condition"):
            if _rounded(saved.get(key)) != _rounded(state[key]):
                raise LinoLocError(
                    f"{out}: holds a survey with another {key} ({path}); run it with the same plan and "
                    "settings to continue it, or use another --out"
                )
        return
    with atomic_write(path, "w", encoding="utf-8") as fh:
        fh.write(json.dumps(state, indent=1) + "\n")


def _rounded(v: Any) -> Any:
    if isinstance(v, float):
        return round(v, 9)
    if isinstance(v, list):
        return [_rounded(x) for x in v]
    return v


def camera_info(frame: Any) -> CameraInfo:
    k = frame.intrinsics
    baseline = float(frame.baseline_m) if frame.right is not None and frame.baseline_m > 0 else None
    return CameraInfo(width=int(k.width), height=int(k.height), fx=float(k.fx), fy=float(k.fy),
                      cx=float(k.cx), cy=float(k.cy), baseline_m=baseline)


class RobotSurvey:
    """One run of a survey (see the module docstring)."""

    def __init__(
        self,
        out: str | Path,
        stops: list[Stop],
        sweep: list[Capture],
        devices: SurveyDevices,
        mover: Any,
        poses: Any,
        settings: CaptureSettings,
        *,
        name: str = "robot-survey",
        source: str = "lino-loc survey --robot",
        disparity_source: str = "",
        progress: Callable[[int, int], None] | None = None,
        overwrite: bool = False,
    ) -> None:
        self.out = Path(out)
        self.stops = stops
        self.sweep = sweep
        self.devices = devices
        self.mover = mover
        self.poses = poses
        self.settings = settings
        self.name = name
        self.source = source
        self.disparity_source = disparity_source
        self.progress = progress
        self.overwrite = overwrite
        self.settle = HeadSettle(settings.settle_s)
        self.report = SurveyReport(dataset=str(self.out), stops=len(stops))
        #: stops whose every capture was in the folder when this run started (a resumed survey)
        self.stops_resumed = 0
        self._quit = False

    # ------------------------------------------------------------------------------------
    def _first_frame(self) -> Any:
        deadline = time.monotonic() + self.settings.first_frame_timeout
        while time.monotonic() < deadline:
            frame = self.devices.mailbox.get(timeout=0.5)
            if frame is not None:
                return frame
        raise LinoLocError(f"survey: no camera frame within {self.settings.first_frame_timeout:g} s "
                           f"({self.devices.health()})")

    def run(self) -> SurveyReport:
        t0 = time.monotonic()
        first = self._first_frame()
        meta = DatasetMeta(name=self.name, camera=camera_info(first), conditions=[self.settings.condition],
                           source=self.source,
                           disparity_source=self.disparity_source if first.disparity is not None else "")
        writer = DatasetWriter(self.out, meta, overwrite=self.overwrite, journal=True)
        try:
            check_state(self.out, survey_state(self.stops, self.sweep, self.settings.condition))
            done = {(e.get("stop"), e.get("turn_index"), e.get("pan_index")) for e in writer.extras}
            self.report.resumed_images = len(writer)
            if len(writer):
                log.info("survey: continuing %s: %d images already captured", self.out, len(writer))
            try:
                self._run_stops(writer, done)
            except KeyboardInterrupt:
                self.report.interrupted = True
                log.warning("survey: interrupted; the images captured are kept (run again to continue)")
        finally:
            self.report.images = len(writer)
            writer.close()
            self.report.seconds = time.monotonic() - t0
            if isinstance(getattr(self.poses, "distance", None), float):
                self.report.odometry_distance_m = round(self.poses.distance, 3)
        return self.report

    def _run_stops(self, writer: DatasetWriter, done: set[tuple[Any, Any, Any]]) -> None:
        n = len(self.stops)
        self.stops_resumed = sum(all((si, c.turn_index, c.pan_index) in done for c in self.sweep)
                                 for si in range(n))
        for si, stop in enumerate(self.stops):
            # every other stop sweeps backwards: the head and the base go on from where they are
            order = self.sweep if si % 2 == 0 else self.sweep[::-1]
            todo = [c for c in order if (si, c.turn_index, c.pan_index) not in done]
            if todo:
                self._stop(si, stop, todo, writer)
            else:
                self.report.stops_done += 1
            if self._quit:
                self.report.interrupted = True
                return
            if self.progress is not None:
                self.progress(self.report.stops_done + self.report.stops_skipped, n)

    def _stop(self, si: int, stop: Stop, todo: list[Capture], writer: DatasetWriter) -> None:
        label = f"stop {si + 1}/{len(self.stops)}"
        for _, group in itertools.groupby(todo, key=lambda c: c.turn_index):
            caps = list(group)
            target = (stop.x, stop.y, float(wrap_angle(stop.theta + caps[0].turn)))
            if caps[0].turn != 0.0:
                label_t = f"{label} (base turned {math.degrees(caps[0].turn):+.0f} deg)"
            else:
                label_t = label
            t_move = time.monotonic()
            answer = self.mover.reach(si, target, label_t)
            self.report.drive_s += time.monotonic() - t_move
            if answer == "quit":
                self._quit = True
                return
            if answer == "skip":
                self.report.stops_skipped += 1
                return
            if isinstance(self.poses, PlanPoses):
                self.poses.pose = target
            for c in caps:
                self._capture(si, c, writer)
        self.report.stops_done += 1
        log.info("%s done (%d images so far)", label, len(writer))

    def _capture(self, si: int, c: Capture, writer: DatasetWriter) -> bool:
        s = self.settings
        dev = self.devices
        dev.head.command(c.pan, s.tilt)
        t_cmd = time.time()
        deadline = time.monotonic() + s.pan_timeout
        while time.monotonic() < deadline:
            frame = dev.mailbox.get(timeout=0.5)
            if frame is None:
                continue
            if frame.stamp <= t_cmd:
                self.report.discarded_stale += 1
                continue
            # the head's history must reach past the frame for its pan to be interpolated
            wait_until = time.monotonic() + 0.5
            while (dev.heads.latest() is None or dev.heads.latest().stamp < frame.stamp) \
                    and time.monotonic() < wait_until:
                time.sleep(0.005)
            pan, moving = dev.heads.pan_at(frame.stamp)
            if not self.settle.at_rest(frame.stamp, moving, dev.heads.last_motion) \
                    or abs(pan - c.pan) > s.pan_tolerance:
                self.report.discarded_moving += 1
                continue
            robot = self.poses.pose_at(frame.stamp, s.pose_timeout)
            if robot is None:
                self.report.discarded_no_pose += 1
                continue
            cam = camera_pose(robot, pan)
            lm = dev.heads.last_motion
            settled = max(t_cmd, lm + s.settle_s if lm is not None else t_cmd)
            self.report.head_s += settled - t_cmd
            self.report.frame_wait_s += max(0.0, frame.stamp - settled)
            t_write = time.monotonic()
            writer.add(frame.left, cam, condition=s.condition, disparity=frame.disparity, right=frame.right,
                       stamp=frame.stamp, extra={"stop": si, "turn_index": c.turn_index, "pan_index": c.pan_index,
                                                 "robot": [float(v) for v in robot], "pan": float(pan)})
            self.report.write_s += time.monotonic() - t_write
            self.report.images_this_run += 1
            return True
        self.report.pans_missed += 1
        log.warning("stop %d: no usable frame at pan %.1f deg within %g s (%s)", si + 1, math.degrees(c.pan),
                    s.pan_timeout, dev.health())
        return False
