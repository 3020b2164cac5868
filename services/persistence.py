"""The daemon's saved state: the last pose with its covariance, written atomically.

As AMCL does with its ``initial_pose`` parameters, the daemon saves its latest pose estimate
every ``persistence.save_period_s`` and at shutdown, and at the next start sets the
filter's belief to a Gaussian with that mean and covariance instead of starting a global
localization (:meth:`lino_loc.localizer.Localizer.set_pose`).

File: one JSON object (:class:`SavedState`), written by :func:`save_state` to a temporary
file in the same folder, flushed and ``fsync``-ed, then renamed over the old file (and the
folder ``fsync``-ed): after a crash or ``kill -9`` the file holds either the old or the new
state, never a mixture. :func:`load_state` returns None for a missing file and, with a
warning, for a corrupt, foreign or invalid one (the daemon then localizes globally).

A saved state is reused only when :func:`refusal` finds nothing against it: saved while
``tracking``, for the same map (its checksum), recent (``persistence.max_age_s``, and not
stamped in the future beyond :data:`FUTURE_TOLERANCE_S`), inside the map's bounds (with
:data:`BOUNDS_MARGIN_M`) and with a sane covariance (:data:`MAX_STD_XY_M`,
:data:`MAX_STD_THETA_RAD`). Even then it is an unconfirmed belief: the filter reports
``global`` until the views confirm it (``Localizer.set_pose(..., confirmed=False)``), with
its covariance widened by the state's age (``services.daemon.restore_min_std``).

The motion since the save: the odometry board's counters are absolute and outlive the
daemon (:class:`drivers.interfaces.BoardCounters`), so every save carries the board's
counters at the time of writing (:class:`SavedCounters`, filled in by :class:`StateSaver`),
and at the next start :func:`board_motion` compares them with the board's counters then: a
robot that moved more than :data:`BARELY_MOVED_M` or turned more than
:data:`BARELY_TURNED_RAD` since the save has its saved pose refused. When the motion cannot
be known the check is skipped, saying why (:attr:`BoardMotion.note`), and the other checks
decide: a file saved without counters (an older file, or no odometry board), no counters
from the board at the start, or a board that restarted in between
(``drivers.odometry_protocol.wheel_travel``). The counters are the board's NET counts: a
motion whose wheel travels cancel (forward, then back the same way) counts as none, and
motion between the estimate's stamp and the write (up to a frame period or two) is in
neither; the views still have to confirm the pose.

The daemon writes off its loop's thread: :class:`StateSaver` is a thread that writes the
latest :class:`SavedState` handed to it (a newer one replaces one not yet written), and
writes synchronously at shutdown and on the control socket's ``save_state``. Only a
``tracking`` estimate is saved (:meth:`SavedState.of_estimate`): a global or lost belief is
no pose to restart from.

Usage::

    save_state(path, SavedState.from_estimate(pose, cov, stamp, "tracking"))
    state = load_state(path)          # SavedState or None
    saver = StateSaver(path); saver.start(); saver.submit(state); saver.stop()
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from drivers.interfaces import BoardCounters
from drivers.odometry_protocol import U32, arc_step, wheel_travel
from lino_loc.atomic_file import atomic_write
from lino_loc.pose_estimate import Estimate
from services.messages import Covariance, Pose2D

log = logging.getLogger("lino_loc.service.persistence")

class PersistenceConfig(BaseModel):
    """The service's ``[persistence]`` section: the last pose, saved atomically and used as the
    initial belief at the next start."""

    model_config = ConfigDict(extra="forbid")

    state_file: Path = Field(Path("/var/lib/lino-loc/state.json"))
    save_period_s: float = Field(5.0, gt=0.0, description="seconds between saves")
    restore: bool = Field(True, description="start from the saved pose (as AMCL does)")
    max_age_s: float = Field(
        30.0, gt=0.0, description="a saved pose older than this (s, by its stamp) is not "
        "reused: the robot may have moved meanwhile (30 s at 0.3 m/s: 9 m), and a search "
        "around an old pose is no faster than a global localization",
    )

    @field_validator("state_file")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        return v.expanduser()


STATE_FORMAT = "lino-loc-state"
STATE_VERSION = 1


class SavedCounters(BaseModel):
    """The odometry board's absolute counters when a state was written
    (:class:`drivers.interfaces.BoardCounters` without the driver's geometry: the driver's
    at the next start applies)."""

    model_config = ConfigDict(extra="ignore")

    stamp: float = Field(ge=0.0, allow_inf_nan=False, description="host time of the sample, s since the epoch")
    board_ms: int = Field(ge=0, lt=U32, description="the board's clock, ms")
    left: int = Field(ge=0, lt=U32, description="raw left encoder count")
    right: int = Field(ge=0, lt=U32, description="raw right encoder count")

    @classmethod
    def of(cls, c: BoardCounters) -> SavedCounters:
        return cls(stamp=c.stamp, board_ms=c.board_ms, left=c.left, right=c.right)

    def with_geometry(self, like: BoardCounters) -> BoardCounters:
        """These counts with ``like``'s metres per tick and track width."""
        return BoardCounters(self.stamp, self.board_ms, self.left, self.right,
                             like.left_m_per_tick, like.right_m_per_tick, like.track_width)  # fmt: skip


class SavedState(BaseModel):
    """The persisted belief summary (what the next start uses as its initial belief)."""

    model_config = ConfigDict(extra="ignore")

    format: Literal["lino-loc-state"] = STATE_FORMAT
    version: Literal[1] = STATE_VERSION
    stamp: float = Field(ge=0.0, description="time of the estimate, s since the epoch")
    saved_at: float = Field(ge=0.0, description="time the file was written")
    pose: Pose2D
    covariance: Covariance
    state: str = "tracking"
    map_checksum: str | None = None
    odometry: SavedCounters | None = Field(
        None, description="the odometry board's counters when written (absent in older files "
        "and without a board: the motion check is skipped)",
    )

    @classmethod
    def from_estimate(
        cls,
        pose: np.ndarray | list[float] | tuple[float, float, float],
        covariance: np.ndarray | list[float],
        stamp: float,
        state: str = "tracking",
        map_checksum: str | None = None,
    ) -> SavedState:
        """The state to save for an estimate: pose (3,), covariance (3, 3) or (9,) made symmetric
        ((C + C^T) / 2), stamp of the estimate, saved_at = now.
        """
        p = [float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3)]
        c = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
        c = 0.5 * (c + c.T)
        return cls(
            stamp=float(stamp),
            saved_at=time.time(),
            pose=Pose2D(x=p[0], y=p[1], theta=p[2]),
            covariance=[float(v) for v in c.reshape(-1)],
            state=state,
            map_checksum=map_checksum,
        )

    @classmethod
    def of_estimate(cls, est: Estimate | None, map_checksum: str | None = None) -> SavedState | None:
        """The state to save for a filter estimate: None unless it is ``tracking``; stamped
        with the estimate's time (the clock when it has none)."""
        if est is None or est.state != "tracking":
            return None
        return cls.from_estimate(
            est.pose, est.covariance, est.stamp or time.time(), est.state, map_checksum
        )

    def mean(self) -> np.ndarray:
        """The saved pose as (x, y, theta), float64 (3,)."""
        return np.array(self.pose.as_tuple(), dtype=np.float64)

    def cov(self) -> np.ndarray:
        """The saved covariance, float64 (3, 3)."""
        return np.asarray(self.covariance, dtype=np.float64).reshape(3, 3)


def save_state(path: str | Path, state: SavedState) -> Path:
    """Write ``state`` atomically (temp file + fsync + rename + fsync of the folder)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    data = state.model_dump_json(indent=1).encode("utf-8") + b"\n"
    with atomic_write(path, "wb", sync_folder=True) as fh:
        fh.write(data)
    return path


def load_state(path: str | Path) -> SavedState | None:
    """The saved state, or None (missing file; corrupt or invalid file: with a warning)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        log.warning("%s: cannot read the saved state (%s); ignoring it", path, exc.strerror or exc)
        return None
    try:
        return SavedState.model_validate_json(raw)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0] if exc.errors() else {"msg": "invalid"}
        where = ".".join(str(p) for p in first.get("loc", ())) or "(file)"
        log.warning(
            "%s: corrupt or foreign saved state (%s: %s); ignoring it", path, where, first.get("msg")
        )
        return None
    except ValueError as exc:
        log.warning("%s: corrupt saved state (%s); ignoring it", path, exc)
        return None


#: A saved stamp this far (s) ahead of the clock is still taken as now (clock steps, NTP);
#: further ahead, the state is refused.
FUTURE_TOLERANCE_S = 5.0
#: A saved pose this far (m) outside the map's bounds is refused (the bounds already carry the
#: sensor model's ``map_margin``).
BOUNDS_MARGIN_M = 1.0
#: Largest standard deviations of a saved covariance that is reused: position (m, the largest
#: of the 2 x 2 block's eigenvalues' roots) and heading (rad). A ``tracking`` estimate's are
#: below ``filter.estimate.converged_std_xy`` / ``converged_std_theta`` (0.5 m, 25 deg).
MAX_STD_XY_M = 1.0
MAX_STD_THETA_RAD = 0.8


#: "Barely moved" since the save, by the odometry board's counters (:func:`board_motion`):
#: the net displacement (m) and turn (rad) of the arc of the wheels' net travels. Below the
#: sensor model's kernel widths (``lino_loc.lost_detection.VIEW_XY`` 0.35 m,
#: ``VIEW_THETA`` 0.3 rad: poses that close are not told apart by the views) and within the
#: restored belief's spread (``services.daemon.restore_min_std``: at least 0.1 m and 0.05 rad,
#: growing by 0.3 m/s and 0.1 rad/s of the state's age), so the views confirm or correct the
#: recalled pose; beyond, the saved pose is refused.
BARELY_MOVED_M = 0.25
BARELY_TURNED_RAD = 0.25


@dataclass(frozen=True)
class BoardMotion:
    """What the odometry board says about the motion since a save: ``refusal`` (the robot
    moved more than "barely": why the saved pose must not be reused) or None, and ``note``,
    one line for the log and the status (the motion, or why it is unknown)."""

    refusal: str | None
    note: str


def board_motion(state: SavedState, now: BoardCounters | None) -> BoardMotion:
    """The motion since ``state`` was saved by the board's counters: the net wheel travels
    (``drivers.odometry_protocol.wheel_travel``, ``now``'s geometry) as one arc
    (``arc_step``): displacement ``hypot(dx, dy)`` and turn ``|dtheta|``, refused beyond
    :data:`BARELY_MOVED_M` or :data:`BARELY_TURNED_RAD`. Unknown (no refusal, the note says
    why): no counters in the file or from the board, or a board restart in between."""
    skip = "motion since the save unknown, the odometry check is skipped: "
    if state.odometry is None:
        return BoardMotion(None, skip + "the saved state has no odometry counters (an older file)")
    if now is None:
        return BoardMotion(None, skip + "no counters from the odometry board at the start")
    travel = wheel_travel(state.odometry.with_geometry(now), now)
    if isinstance(travel, str):
        return BoardMotion(None, skip + travel)
    dx, dy, dth = arc_step(travel[0], travel[1], now.track_width)
    moved, turned = math.hypot(dx, dy), abs(dth)
    said = (f"the odometry board says the robot moved {moved:.2f} m and turned {turned:.2f} "
            "rad since the save")  # fmt: skip
    if moved > BARELY_MOVED_M or turned > BARELY_TURNED_RAD:
        return BoardMotion(f"{said} (barely moved: <= {BARELY_MOVED_M:g} m, <= "
                           f"{BARELY_TURNED_RAD:g} rad)", said)  # fmt: skip
    return BoardMotion(None, said)


@dataclass(frozen=True)
class RestoreContext:
    """What a saved state is checked against at start: the clock (s since the epoch), the
    loaded map's checksum (None: unknown), its bounds (x_min, x_max, y_min, y_max; m), the
    largest age (s) and the odometry board's counters now (None: none came)."""

    now: float
    map_checksum: str | None
    bounds: tuple[float, float, float, float]
    max_age_s: float
    odometry: BoardCounters | None = None


def refusal(state: SavedState, ctx: RestoreContext) -> str | None:
    """Why ``state`` must not be reused as the initial belief, in a few words naming the
    value, or None when it may. Checked in order:

    - saved while ``tracking`` (a global or lost belief is no pose);
    - the same map: both checksums known and equal;
    - recent: ``ctx.now - stamp <= max_age_s``, and not ahead of the clock by more than
      :data:`FUTURE_TOLERANCE_S`;
    - inside the map: (x, y) within the bounds widened by :data:`BOUNDS_MARGIN_M`;
    - a sane covariance: finite and positive semi-definite (already checked on loading),
      position std <= :data:`MAX_STD_XY_M`, heading std <= :data:`MAX_STD_THETA_RAD`;
    - barely moved since the save by the odometry board's counters (:func:`board_motion`
      with ``ctx.odometry``; skipped when unknown).
    """
    if state.state != "tracking":
        return f"saved while {state.state!r}, not 'tracking'"
    if state.map_checksum is None or ctx.map_checksum is None:
        return "no map checksum to compare (saved or loaded map)"
    if state.map_checksum != ctx.map_checksum:
        return (f"saved for another map (checksum {state.map_checksum[:12]}, the map's "
                f"{ctx.map_checksum[:12]})")  # fmt: skip
    age = ctx.now - state.stamp
    if age > ctx.max_age_s:
        return f"{age:.0f} s old (persistence.max_age_s = {ctx.max_age_s:g})"
    if age < -FUTURE_TOLERANCE_S:
        return f"stamped {-age:.0f} s in the future"
    x0, x1, y0, y1 = ctx.bounds
    m = BOUNDS_MARGIN_M
    x, y = state.pose.x, state.pose.y
    if not (x0 - m <= x <= x1 + m and y0 - m <= y <= y1 + m):
        return (f"pose ({x:.2f}, {y:.2f}) outside the map's bounds x [{x0:.2f}, {x1:.2f}], "
                f"y [{y0:.2f}, {y1:.2f}] (+{m:g} m)")  # fmt: skip
    c = state.cov()
    std_xy = math.sqrt(max(float(np.linalg.eigvalsh(c[:2, :2])[-1]), 0.0))
    std_th = math.sqrt(max(float(c[2, 2]), 0.0))
    if not (math.isfinite(std_xy) and std_xy <= MAX_STD_XY_M):
        return f"position std {std_xy:.3g} m > {MAX_STD_XY_M:g} m"
    if not (math.isfinite(std_th) and std_th <= MAX_STD_THETA_RAD):
        return f"heading std {std_th:.3g} rad > {MAX_STD_THETA_RAD:g} rad"
    return board_motion(state, ctx.odometry).refusal


class StateSaver(threading.Thread):
    """Writes the :class:`SavedState` handed to it (latest wins), off the caller's thread.

    :meth:`submit` returns at once; :meth:`write` writes in the caller's thread and returns
    False (with :attr:`last_error`, and a warning) when the file cannot be written. A state
    without odometry counters gets the board's at the time of writing from ``counters``
    (None, or a callable returning None: none). The thread ends after :meth:`stop`, dropping
    a state not yet written."""

    def __init__(
        self, path: Path, counters: Callable[[], BoardCounters | None] | None = None
    ) -> None:
        super().__init__(name="state-saver", daemon=True)
        self.path = path
        self.counters = counters
        self._cond = threading.Condition()
        self._pending: SavedState | None = None
        self._closing = False
        self.saves = 0
        self.last_error: str | None = None

    def submit(self, state: SavedState) -> None:
        with self._cond:
            self._pending = state
            self._cond.notify()

    def run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closing)
                state, self._pending = self._pending, None
                if state is None and self._closing:
                    return
            if state is not None:
                self.write(state)

    def write(self, state: SavedState) -> bool:
        c = self.counters() if self.counters is not None and state.odometry is None else None
        if c is not None:
            state = state.model_copy(update={"odometry": SavedCounters.of(c)})
        try:
            save_state(self.path, state)
            self.saves += 1
            self.last_error = None
            return True
        except OSError as exc:
            self.last_error = f"{self.path}: {exc.strerror or exc}"
            log.warning("cannot save the pose: %s", self.last_error)
            return False

    def stop(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify()
        if self.is_alive():
            self.join(2.0)
