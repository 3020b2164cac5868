"""Auxiliary particle filter over robot poses (paper, eq. 2-6; Pitt and Shephard 1999).

The belief p(x_t | u_1..t, y_1..t) is carried by particles ``x^i`` (robot poses, (N, 3)) with
normalized weights ``pi^i`` (eq. 4; a :class:`lino_loc.weights.Weights` value). One update with
action u_t (the odometry increment) and observation y_t (the sensor model's pose mixture of the
image, over CAMERA poses, evaluated at ``camera_pose(particles, pan)``) is a pipeline of named
steps (:meth:`AuxiliaryParticleFilter.update`):

1. predict and weight: one step of the auxiliary particle filter (``lino_loc.apf.apf_step``:
   first-stage weights from the likelihood of each particle's predicted mean, propagation by
   the odometry action model, second-stage correction); it also estimates the predictive
   log-likelihood ``log p(y_t | y_1..t-1)`` of the observation;
2. watch the appearance (``lino_loc.appearance_change``): when the views become less familiar
   all at once (lights switched), kidnap recovery and the lost test relearn what normal looks
   like; the belief is left alone;
3. test for lost (``lino_loc.lost_detection``): a CUSUM test of the belief against the views
   (the camera's motion, base and head pan, makes a view new);
4. recover (``lino_loc.kidnap_recovery``): AMCL's w_slow / w_fast averages decide injection
   before convergence, validated candidate sets while tracking; the component returns a
   verdict, the filter carries it out. A converged belief not yet confirmed is then
   challenged by its rivals (``lino_loc.belief_challenge``: the places the views also look
   like), and is ``tracking`` only once it out-scores them; rivals that keep out-scoring
   it refute it and join it (half of its particles);
5. resample: systematic (by default) resampling to equal weights when the effective sample size
   falls below ``resample_threshold * N``;
6. estimate and state (``lino_loc.pose_estimate``): the dominant mode of the belief and the
   state ``global`` / ``tracking`` / ``lost``.

The first observation after :meth:`~AuxiliaryParticleFilter.start_global` replaces step 1 by
importance sampling with the sensor model as part of the proposal
(:meth:`~AuxiliaryParticleFilter.global_seed`).

The mixture's kernels need the heading only through cos and sin: the first stage takes them
from the action model's composition (``predict_mean_trig``), and those of the second stage are
kept for the estimate's circular mean. The linear weights are cached in the Weights value (ESS,
estimate, resampling).

``first_stage_exponent`` (beta) tempers the first-stage weights to ``p(y | mu)^beta`` (the
second stage divides by the same factor, so the filter stays exact): beta = 1 is the classic
APF, beta = 0 the bootstrap filter. The classic APF's first-stage weights ignore the process
noise; lower beta when the motion noise is large against the sensor model's kernel widths.

States: ``global`` (the dominant mode is not converged, :class:`lino_loc.pose_estimate.
EstimateConfig`, or it has converged but the views have not yet confirmed it, ``filter.lost.
confirm_views``), ``tracking`` (converged and confirmed), ``lost`` (it had converged, and the
lost test has since found the views contradicting the belief). The REPORTED state
(:attr:`AuxiliaryParticleFilter.state`, the estimate's) is also ``tracking`` only while the
views confirm the belief (``lino_loc.view_fit``, per channel of the observation): views
that cannot confirm any pose report it ``global``, an informative channel whose views stop
fitting ``global`` too, and ``lost`` once they misfit beyond a right belief's chance
(``ViewFitConfig.misfit_alpha``), and it changes only once a new state has lasted ``state_hold`` updates
(``lino_loc.state_hold``; 1 by default: at once); the filter's own steps (what the lost test
learns from) use the state above. The estimate's ``quality`` is ``lino_loc.quality``'s.

Only the filter assigns its particles, weights and state; the components keep their own
state and are told what happened.

Usage::

    pf = AuxiliaryParticleFilter(OdometryMotionModel(), bounds, FilterConfig(n_particles=1000))
    pf.start_global()
    pf.update(delta, pan, sensor_model.observe(y))
    est = pf.estimate()
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from lino_loc.apf import StepResult, apf_step
from lino_loc.appearance_change import AppearanceChangeConfig, AppearanceChangeDetector
from lino_loc.belief_challenge import BeliefChallenge, ChallengeConfig
from lino_loc.channel_agreement import overlap
from lino_loc.errors import LinoLocError
from lino_loc.kidnap_recovery import (
    ChannelView,
    KidnapRecovery,
    RecoveryConfig,
    Verdict,
    outlier_floor,
)
from lino_loc.lost_detection import (
    HIT_NATS,
    LostConfig,
    LostDetector,
    independent_views,
    near_pose,
    view_share,
    viewed_increment,
)
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.pose_estimate import (
    Estimate,
    EstimateConfig,
    State,
    cluster_labels,
    dominant_mode,
    pose_stats,
    weighted_pose_stats,
)
from lino_loc.poses import wrap_angle
from lino_loc.quality import estimate_quality
from lino_loc.resampling import Resampler, get_resampler, logsumexp
from lino_loc.sensor_model import Bounds, PoseMixture
from lino_loc.state_hold import StateHold
from lino_loc.view_fit import ViewFit, ViewFitConfig
from lino_loc.weights import NoFiniteWeightError, Weights

FloatArray = NDArray[np.float64]
FreeSpace = Callable[[FloatArray], NDArray[np.bool_]]

#: Independent views (``lino_loc.lost_detection.independent_views``) a recalled pose
#: (``set_pose(..., confirmed=False)``) must explain IN A ROW, while converged, before it is
#: ``tracking`` (on top of ``filter.lost.confirm_views``): the saved pose is a prior of
#: unknown age, and a belief concentrated near it by one ambiguous view is often wrong
#: (the restart table, benchmarks/restart_table.py, in docs/results.md). The head's turns
#: count as views too (``lino_loc.lost_detection.camera_increment``). A belief pulled away
#: from the saved pose by the views slides towards the truth while it already hits them; the
#: run must outlast that slide (docs/results.md, "Honest restarts").
RECALL_CONFIRM_VIEWS = 8.0

__all__ = [
    "AuxiliaryParticleFilter",
    "FilterConfig",
    "FreeSpace",
    "Estimate",
    "State",
    "StepResult",
    "apf_step",
    "cluster_labels",
    "dominant_mode",
    "pose_stats",
    "weighted_pose_stats",
]

class _CameraLikelihood:
    """x (robot poses) -> log p(y | camera_pose(x, pan)) under the sensor-model mixture.

    Keeps the cos / sin of the last evaluated particles' headings, so that the estimate's
    circular mean reuses them (:meth:`trig_of`)."""

    def __init__(self, mixture: PoseMixture, pan: float) -> None:
        self.mixture = mixture
        self.pan = pan
        self._last: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def __call__(self, x: FloatArray) -> FloatArray:
        th = x[:, 2] + self.pan if self.pan else x[:, 2]
        c, s = np.cos(th), np.sin(th)
        self._last = (x, c, s)
        return self.mixture.log_pdf_trig(x[:, 0], x[:, 1], c, s)

    def trig_of(self, x: FloatArray) -> tuple[FloatArray, FloatArray] | None:
        """(cos theta, sin theta) of the robot headings of ``x`` if it was the last argument."""
        if self._last is None or self._last[0] is not x:
            return None
        _, c, s = self._last
        if not self.pan:
            return c, s
        cp, sp = math.cos(self.pan), math.sin(self.pan)  # rotate back by -pan
        return c * cp + s * sp, s * cp - c * sp


# Old flat keys of FilterConfig: the new key, or the module constant that replaced the setting.
_RENAMED = {
    "lost_threshold": "lost.threshold",
    "confirm_views": "lost.confirm_views",
    "max_inject_fraction": "recovery.max_inject_fraction",
    "candidate_margin": "recovery.candidate_margin",
    "familiar_novelty": "recovery.familiar_novelty",
    "novel_novelty": "recovery.novel_novelty",
    "converged_mass": "estimate.converged_mass",
    "converged_std_xy": "estimate.converged_std_xy",
    "converged_std_theta": "estimate.converged_std_theta",
}
_CONSTANT = {
    "lost_chance_hit_rate": "lost_detection.CHANCE_HIT_RATE",
    "lost_hit_nats": "lost_detection.HIT_NATS",
    "lost_memory": "lost_detection.MEMORY",
    "lost_memory_suspect": "lost_detection.MEMORY_SUSPECT",
    "lost_view_xy": "lost_detection.VIEW_XY",
    "lost_view_theta": "lost_detection.VIEW_THETA",
    "lost_warmup_views": "lost_detection.WARMUP_VIEWS",
    "alpha_slow": "kidnap_recovery.ALPHA_SLOW",
    "alpha_fast": "kidnap_recovery.ALPHA_FAST",
    "recovery_ratio": "kidnap_recovery.RATIO",
    "recovery_floor_factor": "kidnap_recovery.FLOOR_FACTOR",
    "recovery_min_updates": "kidnap_recovery.MIN_UPDATES",
    "candidate_fraction": "kidnap_recovery.CANDIDATE_FRACTION",
    "candidate_min_updates": "kidnap_recovery.CANDIDATE_MIN_UPDATES",
    "candidate_max_updates": "kidnap_recovery.CANDIDATE_MAX_UPDATES",
    "appearance_change_ratio": "appearance_change.RATIO",
    "appearance_change_evidence": "appearance_change.EVIDENCE",
    "cluster_cell_xy": "pose_estimate.CLUSTER_CELL_XY",
    "cluster_cell_theta": "pose_estimate.CLUSTER_CELL_THETA",
    "compact_xy": "pose_estimate.COMPACT_XY",
    "compact_theta": "pose_estimate.COMPACT_THETA",
}
# keys that became groups: an old scalar value names the group's new field
_GROUPS = {"recovery": "recovery.mode", "appearance_change": "appearance_change.enabled"}


def old_key_problems(data: dict[str, Any]) -> list[str]:
    """One message per key of ``data`` that an earlier FilterConfig had and this one has not
    (renamed, or turned into a module constant); [] when there is none."""
    out = []
    for key, value in data.items():
        if key in _RENAMED:
            out.append(f"filter.{key} was renamed: use filter.{_RENAMED[key]}")
        elif key in _CONSTANT:
            out.append(
                f"filter.{key} is no longer a setting (the constant lino_loc.{_CONSTANT[key]})"
            )
        elif key in _GROUPS and not isinstance(value, dict | BaseModel):
            out.append(f"filter.{key} = {value!r} was renamed: use filter.{_GROUPS[key]}")
    return out


class FilterConfig(BaseModel):
    """Particle filter settings (eq. 4-6), and those of its components, nested."""

    model_config = ConfigDict(extra="forbid")

    n_particles: int = Field(1000, ge=1)
    resample_threshold: float = Field(0.5, ge=0.0, le=1.0, description="resample when ESS/N below")
    resampling: Literal["systematic", "stratified", "multinomial"] = "systematic"
    first_stage_exponent: float = Field(
        1.0, ge=0.0, le=1.0, description="beta: the APF's first stage uses p(y | mu)^beta "
        "(1: the classic APF, 0: the bootstrap filter)",
    )
    global_proposal_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="first image after start_global: this share of the "
        "particles is drawn from the image's sensor-model mixture (importance-weighted, see "
        "AuxiliaryParticleFilter.global_seed); 0 = the plain APF from the uniform set",
    )
    seed: int | None = None
    lost: LostConfig = Field(default_factory=LostConfig)
    challenge: ChallengeConfig = Field(default_factory=ChallengeConfig)
    recovery: RecoveryConfig = Field(default_factory=RecoveryConfig)
    appearance_change: AppearanceChangeConfig = Field(default_factory=AppearanceChangeConfig)
    view_fit: ViewFitConfig = Field(default_factory=ViewFitConfig)
    estimate: EstimateConfig = Field(default_factory=EstimateConfig)
    # 1 (no hold) by default: a longer hold flickers less but reports a loss later, and the
    # tracking evaluation's confident-wrong frames grow (docs/results.md, "A hold on the
    # reported state")
    state_hold: int = Field(
        1, ge=1, description="the reported state changes only once a new state has lasted this "
        "many consecutive updates with an image (lino_loc.state_hold); 1: at once",
    )

    @model_validator(mode="before")
    @classmethod
    def _no_old_keys(cls, data: Any) -> Any:
        """A configuration written for the flat FilterConfig fails with the new key's name."""
        if isinstance(data, dict):
            problems = old_key_problems(data)
            if problems:
                raise ValueError("; ".join(problems))
        return data


class AuxiliaryParticleFilter:
    """Robot-pose APF with odometry action model, pose-mixture sensor model, appearance watch,
    lost test and kidnap recovery (see the module docstring)."""

    def __init__(
        self,
        motion_model: OdometryMotionModel,
        bounds: Bounds,
        config: FilterConfig | None = None,
        free_space: FreeSpace | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.config = config or FilterConfig()
        self.motion = motion_model
        self.bounds = bounds
        self.free_space = free_space
        self.rng = rng if rng is not None else np.random.default_rng(self.config.seed)
        self._resample: Resampler = get_resampler(self.config.resampling)
        self._log_free: float | None = None
        c = self.config
        self.lost_detector = LostDetector(c.lost)
        self.view_fit = ViewFit(c.view_fit)
        self._hold = StateHold(c.state_hold)
        self.recovery = KidnapRecovery(c.recovery, motion_model, self._resample)
        self.challenge = BeliefChallenge(c.challenge, motion_model, self._resample)
        self.appearance_watch = AppearanceChangeDetector() if c.appearance_change.enabled else None
        self.injected = 0  # particles injected or drawn as candidates by the last update
        self._last_pan: float | None = None  # the head's pan at the last observation
        self._channel_ll: dict[str, float] = {}  # per channel, log p_c(y) under the belief
        self.start_global()

    # ----------------------------------------------------------------- the weighted set

    def _assign(
        self,
        particles: FloatArray,
        weights: Weights,
        trig: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """The one place the belief changes: new particles, their weights, and the cos / sin
        of their headings when known; the cached estimate is invalidated."""
        self._particles = particles
        self._weights = weights
        self._trig = trig
        self._summary: tuple[FloatArray, FloatArray, float] | None = None

    @property
    def particles(self) -> FloatArray:
        """Robot poses (N, 3); do not modify (use :meth:`set_particles`)."""
        return self._particles

    @property
    def particle_weights(self) -> Weights:
        """The particles' weights (do not modify)."""
        return self._weights

    @property
    def log_weights(self) -> FloatArray:
        """Normalized log-weights (N,); do not modify."""
        return self._weights.log

    @property
    def weights(self) -> FloatArray:
        """Normalized linear weights (a copy)."""
        return self._weights.linear.copy()

    def ess(self) -> float:
        """Kish's effective sample size 1 / sum(w^2)."""
        return self._weights.ess()

    @property
    def n(self) -> int:
        return int(self._particles.shape[0])

    def _resample_belief(self) -> None:
        """Resample to equal weights (the cos / sin of the headings follow their particles)."""
        idx = self._resample(self._weights, self.rng)
        trig = self._trig
        self._assign(
            self._particles[idx],
            Weights.uniform(self.n),
            None if trig is None else (trig[0][idx], trig[1][idx]),
        )

    # ----------------------------------------------------------------- initial beliefs

    def _reset_tracking(self) -> None:
        self.last_log_likelihood = math.nan
        self.converged_once = False
        self._state: State = "global"
        self._belief_converged = False  # the current belief has converged (since its start)
        self.injected = 0
        self._recall_run: float | None = None  # hit views in a row of an unconfirmed recalled pose
        self._misfit_views = 0.0  # independent views of the current run of misfit verdicts
        self.recovery.reset()
        self.challenge.reset()
        self.lost_detector.reset()
        self.view_fit.reset()
        self._hold.reset("global")

    def _uniform(self, n: int) -> FloatArray:
        """n poses uniform over the bounds (and the free space, by rejection) and all headings."""
        if self.free_space is None:
            return self.bounds.sample(n, self.rng)
        out = np.zeros((0, 3))
        for _ in range(100):
            cand = self.bounds.sample(max(2 * (n - out.shape[0]), 16), self.rng)
            ok = np.asarray(self.free_space(cand[:, :2]), dtype=bool)
            out = np.concatenate([out, cand[ok]])
            if out.shape[0] >= n:
                return out[:n]
        raise LinoLocError(
            "free space: the predicate accepts (almost) no pose inside the map bounds"
        )

    def start_global(self) -> None:
        """Uniform belief over the mapped area (optionally its free space) and all headings."""
        n = self.config.n_particles
        self._assign(self._uniform(n), Weights.uniform(n))
        self._reset_tracking()
        self._uniform_prior = True  # the next observation may seed from the sensor model

    def set_pose(self, mean: ArrayLike, cov: ArrayLike, confirmed: bool = True) -> None:
        """Gaussian belief around a robot pose (heading wrapped).

        ``confirmed=True`` (a pose given by an operator): the belief is trusted at once, state
        ``tracking``. ``confirmed=False`` (a pose recalled from a saved state): the belief is
        new and unconfirmed, state ``global`` until the views confirm it (``filter.lost.
        confirm_views`` views' worth of hits, :attr:`LostDetector.confirmed`) and it has
        converged (``filter.estimate``) and explained :data:`RECALL_CONFIRM_VIEWS`
        independent views in a row (a miss restarts the count); a belief the views never
        confirm stays ``global`` and kidnap recovery treats it as a search."""
        n = self.config.n_particles
        m = np.asarray(mean, dtype=np.float64).reshape(3)
        c = np.asarray(cov, dtype=np.float64).reshape(3, 3)
        x = self.rng.multivariate_normal(m, c, size=n, method="eigh")
        x[:, 2] = wrap_angle(x[:, 2])
        self._assign(x, Weights.uniform(n))
        self._reset_tracking()
        self._uniform_prior = False
        if not confirmed:  # a search around a recalled pose: _update_state decides
            self._state = "global"
            self._recall_run = 0.0
            return
        self.converged_once = True
        self._belief_converged = True
        self.lost_detector.confirm()  # a given pose needs no confirmation by the views
        self.challenge.waive()
        self.view_fit.trust()
        self._state = "tracking"
        self._hold.reset(self._proposed_state())

    def set_particles(self, particles: ArrayLike, log_weights: ArrayLike | None = None) -> None:
        """Replace the particle set (for tests and for restoring a saved belief); log-weights
        need not be normalized (None: equal weights). Raises ValueError when no log-weight is
        finite."""
        p = np.asarray(particles, dtype=np.float64).reshape(-1, 3).copy()
        p[:, 2] = wrap_angle(p[:, 2])
        lw = np.zeros(p.shape[0]) if log_weights is None else log_weights
        self._assign(p, Weights.from_log(lw, one_pass=False))
        self.recovery.forget_evidence()  # a candidate set tested against the old belief is void
        self.challenge.reset()
        self._uniform_prior = False

    def move_particles(self, particles: ArrayLike, relocated: bool = False) -> None:
        """Move the particles to new poses (N, 3), same N, keeping their weights and the
        filter's evidence (lost test, recovery, challenge): the belief moved, not replaced
        (:class:`lino_loc.standing_match.StandingMatch`). ``relocated``: the belief was taken
        to another place, so the belief that converges next is a new one (its lost test, view
        fit and challenge start afresh; a challenge resumes only at the place it stopped, as
        after a spread). Raises ValueError on another shape."""
        p = np.asarray(particles, dtype=np.float64).reshape(-1, 3).copy()
        if p.shape != self._particles.shape:
            raise ValueError(f"move_particles: {p.shape[0]} poses for {self._particles.shape[0]} particles")
        p[:, 2] = wrap_angle(p[:, 2])
        self._assign(p, self._weights)
        if relocated:
            self._belief_converged = False
            self.challenge.stop()

    # ----------------------------------------------------------------- update

    def sample_from_mixture(self, mixture: PoseMixture, pan: float, n: int) -> FloatArray:
        """Robot poses whose camera pose (pan applied) is drawn from the sensor-model mixture
        (draws outside the free space are redrawn, up to 10 times)."""
        cam = mixture.sample(n, self.rng)
        cam[:, 2] = wrap_angle(cam[:, 2] - pan)
        if self.free_space is not None:
            for _ in range(10):
                bad = ~np.asarray(self.free_space(cam[:, :2]), dtype=bool)
                if not bad.any():
                    break
                redraw = mixture.sample(int(bad.sum()), self.rng)
                redraw[:, 2] = wrap_angle(redraw[:, 2] - pan)
                cam[bad] = redraw
        return cam

    def predict(self, delta: ArrayLike) -> None:
        """Pure prediction by the action model (eq. 5): no observation."""
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        self._assign(self.motion.sample(self._particles, d, self.rng), self._weights)
        self.recovery.predict(d, self.rng)
        self.challenge.predict(d, self.rng)

    def update(self, delta: ArrayLike, pan: float, mixture: PoseMixture | None,
               rng: np.random.Generator | None = None) -> float:
        """One update: odometry increment ``delta`` (robot frame), head pan (rad), the image's
        sensor-model mixture (None: prediction only); ``rng`` replaces the generator from now
        on. Returns the predictive log-likelihood of the observation (nan without one)."""
        if rng is not None:
            self.rng = rng
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        if mixture is None:
            self.predict(d)
            return math.nan
        pan_change = math.nan if self._last_pan is None else float(pan) - self._last_pan
        self._last_pan = float(pan)
        if self._uniform_prior and self.config.global_proposal_fraction > 0.0:
            return self.global_seed(d, pan, mixture)
        self._uniform_prior = False
        loglik, ll = self._predict_and_weight(d, pan, mixture)
        self._watch_appearance(mixture, d)
        floor = outlier_floor(mixture)
        views = self._test_lost(ll, floor, viewed_increment(d, pan_change), mixture, pan)
        self._recover(ll, floor, d, loglik, mixture, pan, views)
        self._resample_if_degenerate()
        self._update_state(views)
        return ll

    def _predict_and_weight(
        self, d: FloatArray, pan: float, mixture: PoseMixture
    ) -> tuple[_CameraLikelihood, float]:
        """Step 1: the APF step (``lino_loc.apf``); returns the likelihood of robot poses and
        the predictive log-likelihood of the observation."""
        motion = self.motion
        loglik = _CameraLikelihood(mixture, pan)
        res = apf_step(
            self._particles,
            self._weights,
            self.rng,
            predict_mean=lambda x: motion.predict_mean(x, d),
            propagate=lambda x, g: motion.sample(x, d, g),
            log_likelihood=loglik,
            resample=self._resample,
            first_stage_exponent=self.config.first_stage_exponent,
            # log p(y | camera_pose(predict_mean(x), pan)) without forming the means' headings
            first_stage=lambda x: mixture.log_pdf_trig(*motion.predict_mean_trig(x, d, pan)),
        )
        self._assign(res.particles, res.weights, loglik.trig_of(res.particles))
        self.last_log_likelihood = res.log_likelihood
        return loglik, res.log_likelihood

    def _watch_appearance(self, mixture: PoseMixture, d: FloatArray) -> None:
        """Step 2: when the views became less familiar all at once (lino_loc.appearance_change)
        the light, not the pose, changed. What the self-checks learnt under the old appearance
        no longer holds: kidnap recovery restarts its likelihood averages and drops a candidate
        set it was testing, the lost test forgets its learnt hit rate and its evidence. The
        belief itself is left alone. With ``appearance_change.per_channel`` and the view's
        channels known, each channel's novelty is watched (a rise of intensity and disparity
        together is the place, not the light: no relearning)."""
        channels = mixture.channels
        novelty: float | dict[str, float] = mixture.novelty
        if self.config.appearance_change.per_channel and channels and len(channels) > 1:
            novelty = {name: m.novelty for name, m in channels.items()}
        if self.appearance_watch is not None and self.appearance_watch.update(
            novelty, independent_views(d)
        ):
            self.recovery.relearn_averages()
            self.lost_detector.appearance_changed()
            self.view_fit.appearance_changed()

    def _test_lost(
        self, ll: float, floor: float, d: FloatArray, mixture: PoseMixture, pan: float
    ) -> float:
        """Step 3: the lost test on the likelihood's excess over the outlier floor; the hit
        rate is learnt from trusted beliefs (tracking, or lost: slowly), not from a search.
        ``d`` is the increment whose views count (``lino_loc.lost_detection.
        viewed_increment``: the camera's, with the head's pan change, on a standing base; the
        odometry's on a driving one), so a standing robot whose head pans sees new views. For a recalled belief not yet confirmed, the run of
        hit views grows by this frame's independent views on a hit and restarts on a miss (a
        frame where the camera did not move: neither). Returns the frame's independent views."""
        excess = ll - floor if math.isfinite(floor) else ll
        if self._recall_run is not None:
            v = independent_views(d)
            if excess > HIT_NATS:
                self._recall_run += v
            elif v > 0.0:
                self._recall_run = 0.0
        learn = self._state != "global"
        share = 1.0
        if self.config.lost.confirm_share > 0.0 and excess > HIT_NATS:
            share = self._view_share(mixture, pan)
        self.lost_detector.update(excess, d, learn=learn, share=share)
        views = independent_views(d)
        self.view_fit.update(self._channel_excess(mixture, excess, pan), views, learn, self._channel_overlap(mixture))
        return views

    def _view_share(self, mixture: PoseMixture, pan: float) -> float:
        """The view's kernel weight near the estimate's camera pose
        (``lino_loc.lost_detection.view_share``), the largest over the observation's channels
        (a channel that singles out the belief where the other's kernels scatter, as intensity's
        do under a light the map was not made in, confirms it); the fused mixture's when the
        channels are not known; nan when no channel has a kernel."""
        mean = self._dominant()[0]
        cam = (float(mean[0]), float(mean[1]), float(mean[2]) + pan)
        parts = list(mixture.channels.values()) if mixture.channels else [mixture]
        shares = [view_share(m.poses, m.log_weights, cam) for m in parts]
        finite = [x for x in shares if not math.isnan(x)]
        return max(finite) if finite else math.nan

    def _channel_overlap(self, mixture: PoseMixture) -> float:
        """The overlap of the view's two channel mixtures (``lino_loc.channel_agreement``)
        when ``view_fit.max_disagreement`` or ``view_fit.joint = "agreeing"`` asks for it;
        nan otherwise."""
        channels = mixture.channels
        vf = self.config.view_fit
        wanted = vf.max_disagreement < 1.0 or vf.joint == "agreeing"
        if not wanted or not channels or len(channels) != 2:
            return math.nan
        a, b = channels.values()
        return overlap(a, b)

    def _channel_excess(self, mixture: PoseMixture, excess: float, pan: float) -> dict[str, float]:
        """Per channel of the observation (``PoseMixture.channels``), the channel's
        log-likelihood of the view under the updated belief, log sum_i pi^i p_c(y |
        camera_pose(x^i, pan)), minus the channel's outlier floor; with one channel (or none
        named) the predictive log-likelihood's ``excess`` itself, under the channel's name
        (``view`` when unnamed). The channels' log-likelihoods themselves are kept for kidnap
        recovery's agreement test (:meth:`_recover`)."""
        channels = mixture.channels
        self._channel_ll = {}
        if not channels or len(channels) == 1:
            return {next(iter(channels)) if channels else "view": excess}
        x = self._particles
        th = x[:, 2] + pan
        c, s_ = np.cos(th), np.sin(th)
        out = {}
        for name, m in channels.items():
            ll = float(logsumexp(self._weights.log + m.log_pdf_trig(x[:, 0], x[:, 1], c, s_)))
            self._channel_ll[name] = ll
            fl = outlier_floor(m)
            out[name] = ll - fl if math.isfinite(fl) else ll
        return out

    def _recover(
        self,
        ll: float,
        floor: float,
        d: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        mixture: PoseMixture,
        pan: float,
        views: float,
    ) -> None:
        """Step 4: kidnap recovery's verdict (``lino_loc.kidnap_recovery``), carried out; then
        a new belief's challenge by its rivals (:meth:`_challenge`; ``views``: the frame's
        independent views). An observation of several channels also gives recovery each
        channel's view of the candidates and of the belief (``kidnap_recovery.ChannelView``)."""
        per_channel = None
        if mixture.channels and len(mixture.channels) > 1 and self._channel_ll:
            per_channel = {name: ChannelView(_CameraLikelihood(m, pan), self._channel_ll[name])
                           for name, m in mixture.channels.items() if name in self._channel_ll}
        verdict = self.recovery.observe(
            ll,
            mixture.novelty,
            floor,
            delta=d,
            loglik=loglik,
            converged=self.converged_once,
            n=self.n,
            draw=lambda m: self.sample_from_mixture(mixture, pan, m),
            rng=self.rng,
            channels=per_channel,
            views=views,
        )
        self._carry_out(verdict, mixture, pan)
        self._challenge(ll, floor, views, d, loglik, mixture, pan)

    def _challenge(
        self,
        ll: float,
        floor: float,
        views: float,
        d: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        mixture: PoseMixture,
        pan: float,
    ) -> None:
        """Step 4b: a new converged belief against its rivals (``lino_loc.belief_challenge``):
        it is confirmed only once it out-scores them."""
        if not self.challenge.active:
            return
        mean = self._dominant()[0]
        verdict = self.challenge.observe(
            ll, floor, views, delta=d, loglik=loglik, near=lambda x: near_pose(x, mean),
            draw=lambda m: self.sample_from_mixture(mixture, pan, m), n=self.n, rng=self.rng,
        )
        if verdict is not None:
            self.recovery.forget_evidence()
            self.recovery.restart_averages()
            self._carry_out(verdict, mixture, pan)

    def _carry_out(self, verdict: Verdict, mixture: PoseMixture, pan: float) -> None:
        """inject: resample the belief to equal weights (its softmax recomputed from the
        log-weights), then overwrite ``count`` random particles by draws from the sensor model;
        adopt: the candidate set's particles become the belief, whose convergence restarts;
        join: as inject, with the verdict's particles (a refuted belief's rivals) in place of
        draws; the belief's convergence restarts (the next one is a new belief)."""
        self.injected = verdict.count
        if verdict.action == "inject" and verdict.count > 0:
            self._mix_in(verdict.count, lambda m: self.sample_from_mixture(mixture, pan, m))
        elif verdict.action == "join" and verdict.particles is not None:
            joined = verdict.particles
            self._mix_in(min(verdict.count, self.n, joined.shape[0]), lambda m: joined[:m])
            self._belief_converged = False  # whatever converges next is a new belief
        elif verdict.action == "adopt":
            assert verdict.particles is not None
            self._assign(verdict.particles, Weights.uniform(verdict.particles.shape[0]))
            self._belief_converged = False  # a new belief: its convergence restarts the tests
            self.challenge.reset()
            self._state = "global"

    def _mix_in(self, count: int, fresh: Callable[[int], FloatArray]) -> None:
        """Resample the belief to equal weights (its softmax recomputed from the log-weights),
        then overwrite ``count`` random particles by ``fresh(count)`` (inject and join)."""
        x = self._particles[self._resample(self._weights.log, self.rng)]
        slots = self.rng.choice(self.n, size=count, replace=False)
        x[slots] = fresh(count)
        self._assign(x, Weights.uniform(self.n))

    def _resample_if_degenerate(self) -> None:
        """Step 5: resample when ESS < resample_threshold * N."""
        if self._weights.ess() < self.config.resample_threshold * self.n:
            self._resample_belief()

    def _log_free_fraction(self) -> float:
        """log of the free-space share of the bounds (Monte Carlo, 8192 draws of a fixed seed,
        cached; at least log(1 / 8192))."""
        if self._log_free is None:
            if self.free_space is None:
                self._log_free = 0.0
            else:
                cand = self.bounds.sample(8192, np.random.default_rng(12345))
                ok = np.asarray(self.free_space(cand[:, :2]), dtype=bool)
                self._log_free = math.log(max(float(ok.mean()), 1.0 / 8192))
        return float(self._log_free)

    def global_seed(self, delta: ArrayLike, pan: float, mixture: PoseMixture) -> float:
        """First observation from a uniform belief: importance sampling with the sensor model
        as part of the proposal (the dual proposal of Mixture-MCL, Thrun, Fox, Burgard,
        Dellaert 2001). Returns the predictive log-likelihood.

        Target: the posterior p(x | y) = u(x) p(y | x) / p(y), u the uniform prior over the
        free space and all headings, u = 1 / (A_free 2 pi). Proposal: the deterministic mixture
        r(x) = (1 - phi) u(x) + phi q(x) with phi = ``global_proposal_fraction``: N - m
        particles keep their uniform draws (moved by the odometry), m = round(phi N) are drawn
        from q, the distribution the observation samples from restricted to the free space
        (q(x) = proposal(camera_pose(x, pan)) / Q_free, ``PoseMixture.proposal_log_pdf``: the
        sensor-model mixture itself for the nearest-neighbour model, its proposal kernels for
        the interpolated one; the pan is a rotation, its Jacobian is 1). The
        importance weight of EVERY particle (balance heuristic, Veach 1997) is

            w(x) = u(x) p(y | x) / r(x) = u p(y | x) / ((1 - phi) u + phi q(x)).

        For phi = 1 and p(y | x) = s q(x) (the nearest-neighbour mixture is the sensor model up
        to its constant s = exp(log_scale)) this is w = u s: constant. The uniform share keeps poses the J
        neighbours of this one image miss. ``mean(w)`` is an unbiased estimate of the
        predictive likelihood p(y) = integral u p(y | x) dx, fed to the w_slow / w_fast averages
        like the APF's. Monte Carlo estimates of A_free (fixed seed) and of Q_free (the share
        of q's draws that is free, from max(256, m) draws) stand in for the exact areas. When
        no weight is finite the weights are equal and the likelihood is -inf.
        """
        self._uniform_prior = False
        n = self.n
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        phi = self.config.global_proposal_fraction
        m = min(n, int(round(phi * n)))
        x = self.motion.sample(self._particles, d, self.rng)  # the uniform belief, moved
        log_q_free = 0.0
        if m > 0:
            probe = mixture.sample(max(256, m), self.rng)
            if self.free_space is not None:
                ok = np.asarray(self.free_space(probe[:, :2]), dtype=bool)
                log_q_free = math.log(max(float(ok.mean()), 1.0 / probe.shape[0]))
            slots = self.rng.choice(n, size=m, replace=False)
            x[slots] = self.sample_from_mixture(mixture, pan, m)
        ll = self._seed_weights(x, pan, mixture, phi, log_q_free)
        self.recovery.track_likelihood(ll)
        self.injected = m
        self._resample_if_degenerate()
        self._update_state()
        return ll

    def _seed_weights(
        self, x: FloatArray, pan: float, mixture: PoseMixture, phi: float, log_q_free: float
    ) -> float:
        """The belief := x (headings wrapped) with the importance weights of :meth:`global_seed`;
        returns log mean(w)."""
        cam = x.copy()
        cam[:, 2] += pan
        log_p = mixture.log_pdf(cam)  # log p(y | x), log_scale included
        # the density sample() draws from: the mixture itself (log_p - log_scale) for the
        # nearest-neighbour model, its proposal kernels for lino_loc.interpolated_appearance
        log_q = mixture.proposal_log_pdf(cam) - log_q_free
        log_u = self.bounds.log_uniform_density - self._log_free_fraction()
        log_r = np.logaddexp(math.log1p(-phi) + log_u if phi < 1.0 else -math.inf,
                             math.log(phi) + log_q)
        x[:, 2] = wrap_angle(x[:, 2])
        n = x.shape[0]
        try:
            w = Weights.from_log(log_u + log_p - log_r, one_pass=False)
            ll = w.log_normalizer - math.log(n)
        except NoFiniteWeightError:
            w, ll = Weights.uniform(n), -math.inf
        self._assign(x, w)
        self.last_log_likelihood = ll
        return ll

    # ----------------------------------------------------------------- estimate and state

    def _dominant(self) -> tuple[FloatArray, FloatArray, float]:
        """(mean, covariance, weight) of the heaviest cluster; cached until the belief changes."""
        if self._summary is None:
            self._summary = dominant_mode(self._particles, self._weights.linear, trig=self._trig)
        return self._summary

    def _update_state(self, views: float = 0.0) -> None:
        """Step 6: the state from the dominant mode, the lost test and the confirmation;
        ``views``: the observation's independent views (0 for the first, a uniform belief's)."""
        mean, cov, mass = self._dominant()
        converged = self.config.estimate.converged(cov, mass)
        if self.converged_once and self.lost_detector.lost:
            self._state = "lost"
        elif converged:
            if not self._belief_converged:
                # Converged (again): both averages restart from the next observation's
                # likelihood, so that w_slow measures the likelihood while tracking, not the
                # low likelihood of the spread global belief (otherwise a kidnapping is noticed
                # only after w_fast has decayed to the global level). The lost test starts
                # afresh for the new belief.
                self._belief_converged = True
                self.recovery.restart_averages()
                self.lost_detector.new_belief()
                self.view_fit.new_belief()
                self.challenge.start(mean)
            self.converged_once = True
            # "tracking" once the views have confirmed the new belief; until then it is still
            # a search (a belief concentrated by one ambiguous image is often wrong)
            self._state = "tracking" if self._confirmed() else "global"
            if self._state == "tracking":
                self._recall_run = None  # a recalled belief, confirmed: an ordinary one now
                self._rechallenge_if_refuted(mean, views)
        else:
            self._belief_converged = False
            self._recall_run = None if self._recall_run is None else 0.0
            self.challenge.stop()
            self._state = "global"
        self._hold.offer(self._proposed_state())

    def _rechallenge_if_refuted(self, mean: FloatArray, views: float) -> None:
        """With ``challenge.after_misfit``: a tracked belief whose views have stopped fitting
        (``ViewFit.stopped_fitting``, the share rule; reported ``global`` or ``lost``) for ``challenge.after_misfit_views``
        independent views in a row must out-score its rivals again before it is ``tracking``
        (:meth:`_confirmed`); its rivals never join it. Without it, the same belief is
        reported ``tracking`` as soon as its views fit again, also when the views fit another
        place as well (a room symmetric in depth under a light that spoils the intensity
        channel)."""
        c = self.config
        if not (c.challenge.after_misfit and c.challenge.enabled and c.view_fit.enabled):
            return
        if not self.view_fit.stopped_fitting():
            self._misfit_views = 0.0
            return
        self._misfit_views += views
        if self._misfit_views >= c.challenge.after_misfit_views:
            self._misfit_views = 0.0
            self.challenge.reset()
            self.challenge.start(mean, refute=False)

    def _confirmed(self) -> bool:
        """The views' confirmation of the converged belief (:attr:`LostDetector.confirmed`);
        for a recalled pose also a run of :data:`RECALL_CONFIRM_VIEWS` hit views in a row
        while converged."""
        if self._recall_run is not None and self._recall_run < RECALL_CONFIRM_VIEWS:
            return False
        return self.lost_detector.confirmed and self.challenge.passed

    @property
    def state(self) -> State:
        """The reported state: :meth:`_proposed_state` under the hold of ``state_hold``
        updates (``lino_loc.state_hold``; with a hold of 1, the proposed state itself)."""
        return self._proposed_state() if self._hold.hold == 1 else self._hold.reported

    def _proposed_state(self) -> State:
        """The lost test's state (``global`` / ``tracking`` / ``lost``), and a ``tracking``
        belief only while the views confirm it (``lino_loc.view_fit``): views that cannot
        confirm any pose make it ``global``, an informative channel that stops fitting makes
        it ``global`` and, beyond chance (``ViewFit.verdict``), ``lost``. The filter's own
        steps use the lost test's state."""
        s = self._state
        if s != "tracking" or not self.config.view_fit.enabled:
            return s
        verdict = self.view_fit.verdict()
        return "lost" if verdict == "misfit" else "global" if verdict == "uninformative" else s

    @property
    def appearance_changes(self) -> int:
        """Appearance changes detected since construction (0 when the watch is off)."""
        return self.appearance_watch.changes if self.appearance_watch is not None else 0

    def estimate(self) -> Estimate:
        """Dominant mode: weighted mean (circular theta), covariance, ESS, state and doubt."""
        mean, cov, mass = self._dominant()
        state = self.state
        doubt = float(self.lost_detector.doubt)
        return Estimate(
            pose=mean,
            covariance=cov,
            ess=self.ess(),
            n_particles=self.n,
            state=state,
            cluster_weight=mass,
            log_likelihood=float(self.last_log_likelihood),
            doubt=doubt,
            quality=estimate_quality(
                self._state, cov, mass, doubt, self.view_fit.support(), self.config.estimate
            ),
        )
