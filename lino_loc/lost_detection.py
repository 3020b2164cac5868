"""When is the pose filter lost? A sequential test of the belief against the views.

Each observation either is explained by the belief (a HIT: the APF's predictive likelihood of
the view, ``log p(y_t | y_1..t-1)``, exceeds the sensor model's outlier floor by
:data:`HIT_NATS`) or not (a MISS). A correct belief hits at a rate rho that depends on how well
the views match the map (the place and the light); a wrong belief hits at the chance rate
rho_0 = :data:`CHANCE_HIT_RATE`. "Lost" is the decision between those two hypotheses by Page's
CUSUM (a sequential probability ratio test with restart, Page 1954; Basseville and Nikiforov
1993, ch. 2):

    S_t = max(0, S_t-1 + v_t * llr_t),  llr_t = min(0, log(rho_0 / rho))               for a hit,
                                               max(0, log((1 - rho_0) / (1 - rho)))  for a miss,

lost while ``S_t > threshold`` (nats, :class:`LostConfig`). Two things make it calibrated
rather than a fixed ratio:

- rho is LEARNT: ``rho = (hits + 1/2) / (views + 1)`` (Jeffreys' Beta(1/2, 1/2) prior), hits
  and views counted with exponential forgetting, :data:`MEMORY` per view, only while the
  belief is trusted (``learn``: state ``tracking`` or ``lost``, not during a search), and only
  slowly (:data:`MEMORY_SUSPECT`) while evidence stands (S_t-1 > 0); rho is clipped to
  [0.001, 0.999]. It is kept when the belief changes (re-convergence, kidnap recovery): it
  describes the place and the light. Evidence counts once :data:`WARMUP_VIEWS` views have
  taught it. Where the views are unreliable (rho low) a miss carries little evidence, where
  they are reliable a miss is strong evidence; when rho <= rho_0 a view says nothing.
- Views, not frames, are counted: each frame counts as v_t = min(1, |dxy| / VIEW_XY +
  |dtheta| / VIEW_THETA) of an independent view (:func:`independent_views`) of the CAMERA's
  pose increment over the sensor model's kernel widths (poses closer than that are not told
  apart by the model, and consecutive frames' hits and misses come in runs). The camera sits
  on the robot's vertical axis (``lino_loc.poses.camera_pose``), so its increment is the
  odometry increment with the head's pan change added to the turn (:func:`camera_increment`):
  a standing robot whose head pans sees new views, one whose head holds still does not. A
  pan change under :data:`MIN_PAN_CHANGE` is the servo's holding jitter, not a new view. A
  frame with v_t = 0 changes nothing.

When the views become less familiar all at once (lights switched), ``lino_loc.appearance_change``
makes it forget the learnt rho and the evidence (:meth:`LostDetector.appearance_changed`).

A converged belief is reported ``tracking`` only once the views have confirmed it
(:attr:`LostDetector.confirmed`: ``confirm_views`` views' worth of hits since the belief was
new); until then it is still ``global``. Measurements: docs/results.md, "Tracking in the lab
with light and scene changes" and "Notes moved from the code: filter".

Usage::

    det = LostDetector(LostConfig(threshold=12.0))
    lost = det.update(log_likelihood - outlier_floor, delta)   # per observation
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.poses import wrap_angle

# Constants of the test (each chosen on the 240 s lab drive; docs/results.md, "Notes moved from
# the code: filter"):
CHANCE_HIT_RATE = 0.05  # rho_0: the hit rate of a wrong belief
HIT_NATS = 1.0  # a hit: the predictive log-likelihood this far above the outlier floor
MEMORY = 0.97  # forgetting factor of the learnt hit rate, per view
MEMORY_SUSPECT = 0.995  # ... per view while evidence of being lost stands
VIEW_XY = 0.35  # m of travel that make one independent view (the sensor model's sigma_xy)
VIEW_THETA = 0.3  # rad of turn that make one independent view (the sensor model's sigma_theta)
WARMUP_VIEWS = 5.0  # views that only teach the hit rate after a full reset
#: rad: a change of the head's pan between two observations smaller than this is not a camera
#: motion (:func:`camera_increment`). Above a servo's holding jitter (a Dynamixel X holds its
#: goal within a few ticks of 2 pi / 4096 = 0.0015 rad), and no larger than the smallest turn
#: active vision makes (``ActiveVisionConfig.pan_tolerance``, 0.02 rad: a best action closer
#: than that is "stay"; its candidate pans are 0.25 rad apart).
MIN_PAN_CHANGE = 0.02


class LostConfig(BaseModel):
    """The lost test's settings, ``filter.lost``."""

    model_config = ConfigDict(extra="forbid")

    threshold: float = Field(
        12.0, gt=0.0, description="lost when the CUSUM evidence against the belief exceeds this "
        "(nats): lower reports a kidnapping sooner and raises more false alarms under changed "
        "light",
    )
    confirm_views: float = Field(
        2.0, ge=0.0, description="a converged belief is 'tracking' once it has explained this "
        "many independent views' worth of observations (until then: still 'global'); chosen on "
        "the tracking evaluation's three worlds together (docs/results.md, 'Honest states')",
    )
    confirm_share: float = Field(
        0.0, ge=0.0, le=1.0, description="a hit counts towards the confirmation only when at "
        "least this share of the view's sensor-model kernel weight lies near the belief "
        "(view_share: within CONFIRM_RADIUS_XY and CONFIRM_RADIUS_THETA of the estimate's "
        "camera pose); views that other places explain as well confirm nothing. 0: every hit "
        "counts",
    )


def independent_views(
    delta: ArrayLike, view_xy: float = VIEW_XY, view_theta: float = VIEW_THETA
) -> float:
    """How much of an independent view one frame is: min(1, |dxy| / view_xy + |dtheta| /
    view_theta) for the pose increment (dx, dy, dtheta) since the previous frame, the
    camera's (:func:`camera_increment`) or the robot's (poses closer than the sensor model's
    kernel widths are not told apart by it); in [0, 1]."""
    d = np.asarray(delta, dtype=np.float64).reshape(3)
    return min(1.0, math.hypot(float(d[0]), float(d[1])) / view_xy + abs(float(d[2])) / view_theta)


#: A base that moved less than this share of an independent view since the last frame stands
#: (:func:`viewed_increment`; 3.5 mm or 3 mrad, where encoder jitter of a tick or two is
#: 0.1 mm); a driving base makes new views itself.
STANDING_VIEWS = 0.01


def base_stands(delta: ArrayLike) -> bool:
    """Whether the base stood for a frame whose odometry increment is ``delta``: less than
    :data:`STANDING_VIEWS` of an independent view (:func:`independent_views`)."""
    return independent_views(delta) < STANDING_VIEWS


def viewed_increment(delta: ArrayLike, pan_change: float) -> np.ndarray:
    """The increment whose views the lost test counts: the camera's
    (:func:`camera_increment`) while the base stands (less than :data:`STANDING_VIEWS` of a
    view, :func:`independent_views`), the odometry's ``delta`` while it drives. The head's
    turns give a standing robot its new views; while driving, the base's motion alone is the
    count, as before pans were counted, so that a driving robot's search is not confirmed
    sooner by the head's turns."""
    d = np.array(delta, dtype=np.float64).reshape(3)
    return camera_increment(d, pan_change) if base_stands(d) else d


def camera_increment(delta: ArrayLike, pan_change: float) -> np.ndarray:
    """The camera's pose increment (dx, dy, dtheta + dpan) for the odometry increment
    ``delta`` = (dx, dy, dtheta) (robot frame) and the head's pan change ``pan_change`` (rad,
    wrapped to [-pi, pi]) since the previous observation; |pan_change| < :data:`MIN_PAN_CHANGE`
    counts as 0, and a non-finite one (no pan known) as 0. The camera shares the robot's
    position, so only the heading differs; a turn of the base undone by the head (dtheta =
    -dpan) leaves the camera where it was."""
    d = np.array(delta, dtype=np.float64).reshape(3)
    dp = float(pan_change)
    if math.isfinite(dp):
        dp = math.remainder(dp, 2.0 * math.pi)
        if abs(dp) >= MIN_PAN_CHANGE:
            d[2] += dp
    return d


#: m and rad: a kernel of the view's sensor-model mixture this close to the estimate's camera
#: pose counts as pointing at the belief (:func:`view_share`): the confident-wrong bound of the
#: evaluations (1 m) and two kernel widths in heading (the sensor model's sigma_theta, 0.3 rad)
CONFIRM_RADIUS_XY = 1.0
CONFIRM_RADIUS_THETA = 0.6


def view_share(
    kernel_poses: ArrayLike, kernel_log_weights: ArrayLike, camera_pose: ArrayLike
) -> float:
    """The share of a view's sensor-model kernel weight near a camera pose: sum of w_k over
    the kernels k within :data:`CONFIRM_RADIUS_XY` (position) and
    :data:`CONFIRM_RADIUS_THETA` (heading, wrapped) of ``camera_pose``, over the sum of all
    w_k (the outlier component not counted), in [0, 1]; nan without a kernel of finite weight.

    Under a uniform prior over the map this is the posterior probability, given the view
    alone, that the camera is near that pose (the kernels are narrow beside the radii). A view
    the belief explains while other places explain it as well (a blank wall, one of a row of
    identical doors) has a small share: such hits say the belief is possible, not that it is
    the place."""
    p = np.asarray(kernel_poses, dtype=np.float64).reshape(-1, 3)
    lw = np.asarray(kernel_log_weights, dtype=np.float64).reshape(-1)
    finite = np.isfinite(lw)
    if not bool(finite.any()):
        return math.nan
    w = np.exp(lw[finite] - float(lw[finite].max()))
    near = near_pose(p[finite], camera_pose)
    return float(w[near].sum() / w.sum())


def near_pose(poses: ArrayLike, pose: ArrayLike) -> np.ndarray:
    """Which of ``poses`` (n, 3) lie within :data:`CONFIRM_RADIUS_XY` in position and
    :data:`CONFIRM_RADIUS_THETA` in heading (wrapped) of ``pose`` (3,): (n,) bool."""
    q = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(pose, dtype=np.float64).reshape(3)
    dth = np.abs(wrap_angle(q[:, 2] - c[2]))
    return (np.hypot(q[:, 0] - c[0], q[:, 1] - c[1]) <= CONFIRM_RADIUS_XY) & (dth <= CONFIRM_RADIUS_THETA)


@dataclass
class LostDetector:
    """Page's CUSUM on hits and misses of the belief (see the module docstring)."""

    config: LostConfig = field(default_factory=LostConfig)
    score: float = field(default=0.0, init=False)  # S_t, nats
    _hits: float = field(default=0.0, init=False)
    _views: float = field(default=0.0, init=False)
    _learnt: float = field(default=0.0, init=False)  # views rho was learnt from (no forgetting)
    _belief_hits: float = field(default=0.0, init=False)  # hit views of the current belief
    _trusted: bool = field(default=False, init=False)

    def reset(self) -> None:
        """Forget everything, the learnt hit rate included (a new start)."""
        self._hits = 0.0
        self._views = 0.0
        self._learnt = 0.0
        self.new_belief()

    def new_belief(self) -> None:
        """A new belief (converged again, or adopted by kidnap recovery): clear the evidence and
        the confirmation, keep the learnt hit rate (how reliable the views are is a property of
        the place and the light, not of the belief)."""
        self.score = 0.0
        self._belief_hits = 0.0
        self._trusted = False

    def appearance_changed(self) -> None:
        """The scene's appearance changed (lino_loc.appearance_change): forget the learnt hit rate
        (it described the old light; :data:`WARMUP_VIEWS` views teach the new one before evidence
        counts again) and the evidence, keep the belief's confirmation."""
        self._hits = 0.0
        self._views = 0.0
        self._learnt = 0.0
        self.score = 0.0

    def confirm(self) -> None:
        """Take the belief as confirmed without views (a pose given by the user)."""
        self._trusted = True

    @property
    def confirmed(self) -> bool:
        """Whether the views have confirmed the belief: ``confirm_views`` views' worth of hits
        since :meth:`new_belief`, or :meth:`confirm` (a belief concentrated by one ambiguous
        image explains none of the next views when it is wrong)."""
        return self._trusted or self._belief_hits >= self.config.confirm_views

    @property
    def hit_rate(self) -> float:
        """rho: the learnt hit rate of a correct belief (Beta(1/2, 1/2) prior, Jeffreys)."""
        return (self._hits + 0.5) / (self._views + 1.0)

    @property
    def lost(self) -> bool:
        return self.score > self.config.threshold

    @property
    def doubt(self) -> float:
        """Evidence against the belief as a fraction of the threshold: 0 = the views agree,
        1 = lost (score / threshold, >= 0). Active vision looks once it passes its
        ``trigger_doubt``, before the belief is declared lost."""
        return self.score / self.config.threshold

    def update(
        self, excess: float, delta: ArrayLike, learn: bool = True, share: float = 1.0
    ) -> bool:
        """One observation: ``excess`` = predictive log-likelihood minus the outlier floor
        (nats; -inf or nan: a miss), ``delta`` the camera's pose increment (dx, dy, dtheta)
        since the last one (:func:`camera_increment`: the odometry's, with the pan change);
        ``learn``: the belief is trusted (tracking), so its hits and misses teach rho;
        ``share``: the view's kernel weight near the belief (:func:`view_share`), a hit
        confirms the belief only when it is at least ``confirm_share``.
        Returns whether the belief is lost."""
        v = independent_views(delta)
        if v <= 0.0:
            return self.lost
        hit = bool(excess > HIT_NATS)  # nan: a miss
        if hit and share >= self.config.confirm_share:
            self._belief_hits += v
        rho = min(max(self.hit_rate, 1e-3), 1.0 - 1e-3)
        p0 = CHANCE_HIT_RATE
        llr = min(0.0, math.log(p0 / rho)) if hit else max(0.0, math.log((1.0 - p0) / (1.0 - rho)))
        if self._learnt >= WARMUP_VIEWS:  # until then the views only teach rho
            score = self.score
            self.score = max(0.0, self.score + v * llr)
        else:
            score = 0.0
        if learn:
            # the hit rate of a correct belief is learnt from unsuspected views; while evidence
            # stands (S > 0 before this view) it adapts only slowly (MEMORY_SUSPECT), so that a
            # run of misses does not teach the test to expect misses, and a lasting change of
            # the views (another light) still lowers rho in the end instead of holding "lost"
            forget = (MEMORY if score == 0.0 else MEMORY_SUSPECT) ** v
            self._hits = forget * self._hits + (v if hit else 0.0)
            self._views = forget * self._views + v
            self._learnt += v
        return self.lost
