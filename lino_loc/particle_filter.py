"""Auxiliary particle filter over robot poses (paper, eq. 2-6; Pitt and Shephard 1999).

The belief p(x_t | u_1..t, y_1..t) is carried by particles ``x^i`` (robot poses, (N, 3)) with
normalized log-weights ``log pi^i`` (eq. 4). One update with action u_t and observation y_t
(eq. 5-6) is one step of the auxiliary particle filter (``lino_loc.apf.apf_step``: first-stage
weights from the likelihood of each particle's predicted mean, propagation, second-stage
correction; systematic resampling again only when the effective sample size falls below
``resample_threshold * N``), specialized here to robot poses, the odometry action model and
the appearance sensor model, whose mixture is over CAMERA poses and is evaluated at
``camera_pose(particles, pan)``.

The pieces live in modules named after what they compute:

- ``lino_loc.apf``: the generic APF step (any state space; the tests run it against a Kalman
  filter);
- ``lino_loc.kidnap_recovery``: AMCL's w_slow / w_fast averages of the predictive likelihood
  and the recovery from a kidnapping (injection before convergence, validated candidate sets
  while tracking);
- ``lino_loc.lost_detection``: the ``lost`` state (a CUSUM test of the belief against the
  views, calibrated by the hit rate it learns);
- ``lino_loc.pose_estimate``: the estimate, the dominant mode of the belief (clustering only
  when the cloud is not compact);
- this module: the configuration, the initial beliefs (uniform, Gaussian, seeded from the
  first image), the update and the state.

Speed (issue 3: at most 2 ms per 1000-particle update including the image projection). The
likelihood of the sensor-model mixture is the cost: N x J kernel terms, twice per update (at
the predicted means and at the propagated particles; the first stage's values are reused,
indexed by ancestor, in the second). The kernels need the heading only through cos and sin:
the first stage takes them from the action model's composition (``predict_mean_trig``), and
those of the second stage are kept for the estimate's circular mean. Linear weights are
cached next to the log-weights (ESS, estimate, resampling). Measured with ``lino-loc bench
update`` (lab map, 4500 entries; this 2-core AMD EPYC, load 1.8): 0.85 / 1.26 / 4.5 ms median
for 150 / 1000 / 10000 particles, from 1.95 / 3.21 / 10.0 ms (quiet machine) before.

``first_stage_exponent`` (beta) tempers the first-stage weights to ``p(y | mu)^beta`` (the
second stage divides by the same factor, so the filter stays exact): beta = 1 is the classic
APF, beta = 0 the bootstrap filter. On the linear-Gaussian test model the classic APF's ESS
dips to ~n/30 on an outlying observation (its first-stage weights ignore the process noise);
keep beta = 1 unless the motion noise is large against the kernel widths.

States: ``global`` (no cluster holds ``converged_mass`` of the weight, or its spread is large,
or it has converged but the views have not yet confirmed it: ``confirm_views``), ``tracking``
(converged and confirmed), ``lost`` (it had converged, and the views have since contradicted the
belief: a sequential test of how often the belief explains them against how often it did,
``lino_loc.lost_detection``).

Usage::

    pf = AuxiliaryParticleFilter(OdometryMotionModel(), bounds, FilterConfig(n_particles=1000))
    pf.start_global()
    pf.update(delta, pan, sensor_model.observe(y))
    est = pf.estimate()
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.apf import StepResult, apf_step, normalize
from lino_loc.appearance_change import AppearanceChangeDetector
from lino_loc.errors import LinoLocError
from lino_loc.kidnap_recovery import KidnapRecovery, outlier_floor
from lino_loc.lost_detection import LostDetector, independent_views
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.pose_estimate import (
    Estimate,
    State,
    cluster_labels,
    dominant_mode,
    pose_stats,
    weighted_pose_stats,
)
from lino_loc.poses import wrap_angle
from lino_loc.resampling import Resampler, get_resampler, logsumexp
from lino_loc.sensor_model import Bounds, PoseMixture

FloatArray = NDArray[np.float64]
FreeSpace = Callable[[FloatArray], NDArray[np.bool_]]

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
    "normalize",
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


class FilterConfig(BaseModel):
    """Particle filter settings (eq. 4-6) and the thresholds of the estimate's state."""

    model_config = ConfigDict(extra="forbid")

    n_particles: int = Field(1000, ge=1)
    resample_threshold: float = Field(0.5, ge=0.0, le=1.0, description="resample when ESS/N below")
    resampling: Literal["systematic", "stratified", "multinomial"] = "systematic"
    first_stage_exponent: float = Field(1.0, ge=0.0, le=1.0)
    alpha_slow: float = Field(
        0.001, gt=0.0, le=1.0, description="AMCL long-term likelihood average"
    )
    alpha_fast: float = Field(0.1, gt=0.0, le=1.0, description="AMCL short-term likelihood average")
    max_inject_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="cap on particles replaced per update"
    )
    cluster_cell_xy: float = Field(0.5, gt=0.0, description="cell size for mode clustering, m")
    cluster_cell_theta: float = Field(math.radians(30.0), gt=0.0, description="cell size, rad")
    converged_mass: float = Field(
        0.6, ge=0.0, le=1.0, description="dominant cluster weight for tracking"
    )
    converged_std_xy: float = Field(0.5, gt=0.0, description="max position std (m) for tracking")
    converged_std_theta: float = Field(
        math.radians(25.0), gt=0.0, description="max heading std (rad)"
    )
    lost_threshold: float = Field(
        12.0, gt=0.0, description="lost when the CUSUM evidence of lino_loc.lost_detection "
        "(nats) exceeds this"
    )
    lost_chance_hit_rate: float = Field(
        0.05, gt=0.0, lt=1.0, description="rate at which a WRONG belief still explains a view"
    )
    lost_hit_nats: float = Field(
        1.0, ge=0.0, description="a view is explained when the predictive log-likelihood is "
        "this far above the sensor model's outlier floor"
    )
    lost_memory: float = Field(
        0.97, gt=0.0, lt=1.0, description="forgetting factor per view of the learnt hit rate"
    )
    lost_memory_suspect: float = Field(
        0.995, gt=0.0, lt=1.0, description="... while evidence of being lost stands"
    )
    lost_view_xy: float = Field(0.35, gt=0.0, description="travel (m) that makes one new view")
    lost_view_theta: float = Field(0.3, gt=0.0, description="turn (rad) that makes one new view")
    lost_warmup_views: float = Field(
        5.0, ge=0.0, description="views after convergence that only teach the hit rate"
    )
    confirm_views: float = Field(
        1.0, ge=0.0, description="a converged belief is 'tracking' once it has explained this "
        "many views' worth of observations (before: still 'global')"
    )
    recovery: Literal["validated", "amcl"] = Field(
        "validated",
        description="kidnap recovery while tracking: 'validated' draws a candidate set from the "
        "sensor model when the evidence of being lost is sustained and adopts it only when it "
        "out-scores the belief over several updates; 'amcl' injects into the belief directly",
    )
    recovery_ratio: float = Field(
        0.2, gt=0.0, le=1.0, description="lost evidence: w_fast < recovery_ratio * w_slow"
    )
    recovery_floor_factor: float = Field(
        2.0,
        ge=1.0,
        description="lost evidence also: w_fast below this factor times the sensor model's "
        "outlier floor (the belief explains the views no better than the uniform component)",
    )
    recovery_min_updates: int = Field(
        5, ge=1, description="consecutive updates of lost evidence before candidates are drawn"
    )
    candidate_fraction: float = Field(
        0.1, gt=0.0, le=1.0, description="candidate set size relative to n_particles"
    )
    candidate_min_updates: int = Field(
        8, ge=1, description="updates a candidate set is tested before it may replace the belief"
    )
    candidate_max_updates: int = Field(
        40, ge=1, description="a candidate set that has not won after this many updates is dropped"
    )
    candidate_margin: float = Field(
        20.0, ge=0.0, description="log likelihood ratio the candidate set must win by"
    )
    familiar_novelty: float = Field(
        1.5,
        gt=0.0,
        description="observations with novelty (PoseMixture.novelty) below count fully as "
        "evidence for kidnap recovery",
    )
    novel_novelty: float = Field(
        2.0, gt=0.0, description="... above: not at all (linear in between)"
    )
    compact_xy: float = Field(
        1.0, gt=0.0, description="cloud within this radius (m) of its mean: one mode, no clustering"
    )
    compact_theta: float = Field(
        math.radians(60.0), gt=0.0, description="... and within this heading difference (rad)"
    )
    global_proposal_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="first image after start_global: this share of the "
        "particles is drawn from the image's sensor-model mixture (importance-weighted, see "
        "AuxiliaryParticleFilter.global_seed); 0 = the plain APF from the uniform set",
    )
    appearance_change: bool = Field(
        True, description="watch for changes of the scene's appearance (lights switched): kidnap "
        "recovery and the lost test then relearn what normal looks like instead of taking the "
        "worse views for a kidnapping (lino_loc.appearance_change)",
    )
    appearance_change_ratio: float = Field(
        1.65, gt=1.0, description="a rise of the views' novelty by more than this factor is "
        "evidence of an appearance change",
    )
    appearance_change_evidence: float = Field(
        5.0, gt=0.0, description="CUSUM evidence (log-novelty x independent views) for an "
        "appearance change"
    )
    seed: int | None = None


class AuxiliaryParticleFilter(KidnapRecovery):
    """Robot-pose APF with odometry action model, pose-mixture sensor model and kidnap recovery."""

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
        n = self.config.n_particles
        self._log_free: float | None = None
        c = self.config
        self.lost_detector = LostDetector(
            threshold=c.lost_threshold,
            chance_hit_rate=c.lost_chance_hit_rate,
            hit_nats=c.lost_hit_nats,
            memory=c.lost_memory,
            memory_suspect=c.lost_memory_suspect,
            view_xy=c.lost_view_xy,
            view_theta=c.lost_view_theta,
            warmup_views=c.lost_warmup_views,
            confirm_views=c.confirm_views,
        )
        self.appearance_watch = (
            AppearanceChangeDetector(ratio=c.appearance_change_ratio, evidence=c.appearance_change_evidence)
            if c.appearance_change
            else None
        )
        self.particles = np.zeros((n, 3))
        self.log_weights = np.full(n, -math.log(n))
        self.start_global()

    # ----------------------------------------------------------------- the weighted set

    @property
    def particles(self) -> FloatArray:
        """Robot poses (N, 3); assigning a new array invalidates the cached estimate."""
        return self._particles

    @particles.setter
    def particles(self, value: FloatArray) -> None:
        self._particles = value
        self._summary: tuple[FloatArray, FloatArray, float] | None = None
        self._trig: tuple[FloatArray, FloatArray] | None = None

    @property
    def log_weights(self) -> FloatArray:
        """Normalized log-weights (N,); assigning them invalidates the cached linear weights."""
        return self._log_weights

    @log_weights.setter
    def log_weights(self, value: FloatArray) -> None:
        self._log_weights = value
        self._w: FloatArray | None = None
        self._summary = None

    def _linear_weights(self) -> FloatArray:
        """exp(log_weights), normalized, cached (do not modify)."""
        if self._w is None:
            lw = self._log_weights
            w = lw - lw.max()
            np.exp(w, out=w)
            w /= w.sum()
            self._w = w
        return self._w

    @property
    def weights(self) -> FloatArray:
        """Normalized linear weights (a copy)."""
        return self._linear_weights().copy()

    def ess(self) -> float:
        """Kish's effective sample size 1 / sum(w^2)."""
        w = self._linear_weights()
        return float(1.0 / np.dot(w, w))

    @property
    def n(self) -> int:
        return int(self._particles.shape[0])

    def _resample_belief(self) -> None:
        """Resample to equal weights (the cos / sin of the headings follow their particles)."""
        idx = self._resample(self._log_weights, self.rng, weights=self._linear_weights())
        trig = self._trig
        self.particles = self._particles[idx]
        self.log_weights = np.full(self.n, -math.log(self.n))
        if trig is not None:
            self._trig = (trig[0][idx], trig[1][idx])

    # ----------------------------------------------------------------- initial beliefs

    def _reset_tracking(self) -> None:
        self.last_log_likelihood = math.nan
        self.converged_once = False
        self._state: State = "global"
        self._belief_converged = False  # the current belief has converged (since its start)
        self._summary = None
        self._reset_recovery()
        self.lost_detector.reset()

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
        self.particles = self._uniform(n)
        self.log_weights = np.full(n, -math.log(n))
        self._reset_tracking()
        self._uniform_prior = True  # the next observation may seed from the sensor model

    def set_pose(self, mean: ArrayLike, cov: ArrayLike) -> None:
        """Gaussian belief around a known robot pose (heading wrapped)."""
        n = self.config.n_particles
        m = np.asarray(mean, dtype=np.float64).reshape(3)
        c = np.asarray(cov, dtype=np.float64).reshape(3, 3)
        x = self.rng.multivariate_normal(m, c, size=n, method="eigh")
        x[:, 2] = wrap_angle(x[:, 2])
        self.particles = x
        self.log_weights = np.full(n, -math.log(n))
        self._reset_tracking()
        self._uniform_prior = False
        self.converged_once = True
        self._belief_converged = True
        self.lost_detector.confirm()  # a given pose needs no confirmation by the views
        self._state = "tracking"

    def set_particles(self, particles: ArrayLike, log_weights: ArrayLike | None = None) -> None:
        """Replace the particle set (for tests and for restoring a saved belief)."""
        p = np.asarray(particles, dtype=np.float64).reshape(-1, 3).copy()
        p[:, 2] = wrap_angle(p[:, 2])
        self.particles = p
        lw = (
            np.zeros(p.shape[0])
            if log_weights is None
            else np.asarray(log_weights, dtype=np.float64)
        )
        self.log_weights = normalize(lw)
        self._drop_candidates()  # a candidate set tested against the old belief is void
        self.lost_updates = 0
        self._uniform_prior = False

    # ----------------------------------------------------------------- update

    def sample_from_mixture(self, mixture: PoseMixture, pan: float, n: int) -> FloatArray:
        """Robot poses whose camera pose (pan applied) is drawn from the sensor-model mixture."""
        cam = mixture.sample(n, self.rng)
        cam[:, 2] = wrap_angle(cam[:, 2] - pan)
        if self.free_space is not None:
            # replace draws outside the free space by fresh draws (a few tries)
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
        self.particles = self.motion.sample(self._particles, delta, self.rng)
        if self.candidates is not None:
            self.candidates = self.motion.sample(self.candidates, delta, self.rng)

    def update(
        self,
        delta: ArrayLike,
        pan: float,
        mixture: PoseMixture | None,
        rng: np.random.Generator | None = None,
    ) -> float:
        """One filter update with odometry increment ``delta`` (robot frame), head pan angle
        and the sensor-model mixture of the new image (None: prediction only).

        Returns the predictive log-likelihood of the observation (nan without observation).
        """
        if rng is not None:
            self.rng = rng
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        if mixture is None:
            self.predict(d)
            return math.nan
        if self._uniform_prior and self.config.global_proposal_fraction > 0.0:
            return self.global_seed(d, pan, mixture)
        self._uniform_prior = False

        motion = self.motion
        loglik = _CameraLikelihood(mixture, pan)
        res = apf_step(
            self._particles,
            self._log_weights,
            self.rng,
            predict_mean=lambda x: motion.predict_mean(x, d),
            propagate=lambda x, g: motion.sample(x, d, g),
            log_likelihood=loglik,
            resample=self._resample,
            first_stage_exponent=self.config.first_stage_exponent,
            # log p(y | camera_pose(predict_mean(x), pan)) without forming the means' headings
            first_stage=lambda x: mixture.log_pdf_trig(*motion.predict_mean_trig(x, d, pan)),
        )
        self.particles, self.log_weights = res.particles, res.log_weights
        self._w = res.weights
        self._trig = loglik.trig_of(res.particles)
        ll = res.log_likelihood
        self.last_log_likelihood = ll
        fam = self.familiarity(mixture.novelty)
        floor = outlier_floor(mixture)
        if self.appearance_watch is not None and self.appearance_watch.update(
            mixture.novelty, independent_views(d, self.config.lost_view_xy, self.config.lost_view_theta)
        ):
            self._appearance_changed()
        self._track_likelihood(ll, fam, floor)
        self.lost_detector.update(
            # rho is learnt from trusted beliefs (tracking, or lost: slowly, while evidence
            # stands), not from a search
            ll - floor if math.isfinite(floor) else ll, d, learn=self._state != "global"
        )
        self.injected = 0
        if self.candidates is not None:
            self._test_candidates(d, loglik, ll, fam)
        self._maybe_inject(mixture, pan, fam)
        if self.ess() < self.config.resample_threshold * self.n:
            self._resample_belief()
        self._update_state()
        return ll

    def _appearance_changed(self) -> None:
        """The views became less familiar all at once (lino_loc.appearance_change): the light,
        not the pose, changed. What the self-checks learnt under the old appearance no longer
        holds: kidnap recovery restarts its likelihood averages from this view and drops a
        candidate set it was testing, the lost test forgets its learnt hit rate and its
        evidence. The belief itself is left alone."""
        self.relearn_averages()
        self.lost_detector.appearance_changed()

    def _log_free_fraction(self) -> float:
        """log of the free-space share of the bounds (Monte Carlo, fixed seed, cached)."""
        if getattr(self, "_log_free", None) is None:
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
        Dellaert 2001; design.md section 2: the mixture "can also be *sampled*: that is how
        particles are seeded for global localization").

        Target: the posterior p(x | y) = u(x) p(y | x) / p(y), u the uniform prior over the
        free space and all headings, u = 1 / (A_free 2 pi). Proposal: the deterministic mixture
        r(x) = (1 - phi) u(x) + phi q(x) with phi = ``global_proposal_fraction``: N - m
        particles keep their uniform draws (independent of y: they are the prior), m = round(phi
        N) are drawn from q, the sensor-model mixture of the image restricted to the free space
        (q(x) = mixture(camera_pose(x, pan)) / Q_free; the pan is a rotation, its Jacobian is 1).
        The importance weight of EVERY particle (balance heuristic, Veach 1997) is

            w(x) = u(x) p(y | x) / r(x) = u p(y | x) / ((1 - phi) u + phi q(x)).

        For phi = 1 (all particles from q) and p(y | x) = s q(x) (the mixture is the sensor
        model up to its constant s = exp(log_scale), the outlier component included in both)
        this is w = u s: constant, i.e. a sample drawn from q gets weight prior / q times the
        likelihood, which is flat. The uniform share keeps poses the J neighbours of this one
        image miss (an off-grid view's own cell is among them only about 60 % of the time in
        the office), at the importance weight they deserve. ``mean(w)`` is an unbiased estimate
        of the predictive likelihood p(y) = integral u p(y | x) dx, returned and fed to the
        w_slow / w_fast averages like the APF's. A Monte Carlo estimate of A_free (fixed seed)
        and of Q_free (the share of q's draws that is free) stand in for the exact areas.
        """
        self._uniform_prior = False
        n = self.n
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        phi = self.config.global_proposal_fraction
        m = min(n, int(round(phi * n)))
        x = self.motion.sample(self.particles, d, self.rng)  # the uniform belief, moved
        log_q_free = 0.0
        if m > 0:
            probe = mixture.sample(max(256, m), self.rng)
            if self.free_space is not None:
                ok = np.asarray(self.free_space(probe[:, :2]), dtype=bool)
                log_q_free = math.log(max(float(ok.mean()), 1.0 / probe.shape[0]))
            slots = self.rng.choice(n, size=m, replace=False)
            x[slots] = self.sample_from_mixture(mixture, pan, m)
        cam = x.copy()
        cam[:, 2] += pan
        log_p = mixture.log_pdf(cam)  # log p(y | x), log_scale included
        log_q = log_p - mixture.log_scale - log_q_free
        log_u = self.bounds.log_uniform_density - self._log_free_fraction()
        log_r = np.logaddexp(math.log1p(-phi) + log_u if phi < 1.0 else -math.inf,
                             math.log(phi) + log_q)
        log_w = log_u + log_p - log_r
        log_c = float(logsumexp(log_w))
        x[:, 2] = wrap_angle(x[:, 2])
        self.particles = x
        if not math.isfinite(log_c):
            self.log_weights = np.full(n, -math.log(n))
            ll = -math.inf
        else:
            self.log_weights = log_w - log_c
            ll = log_c - math.log(n)
        self.last_log_likelihood = ll
        self._track_likelihood(ll)
        self.injected = m
        if self.ess() < self.config.resample_threshold * self.n:
            self._resample_belief()
        self._update_state()
        return ll


    # ----------------------------------------------------------------- estimate

    def _dominant(self) -> tuple[FloatArray, FloatArray, float]:
        """(mean, covariance, weight) of the heaviest cluster; cached until the particles change."""
        if self._summary is None:
            c = self.config
            self._summary = dominant_mode(
                self._particles,
                self._linear_weights(),
                compact_xy=c.compact_xy,
                compact_theta=c.compact_theta,
                cell_xy=c.cluster_cell_xy,
                cell_theta=c.cluster_cell_theta,
                trig=self._trig,
            )
        return self._summary

    def _update_state(self) -> None:
        mean, cov, mass = self._dominant()
        c = self.config
        a, b, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
        std_xy = math.sqrt(
            max(0.5 * (a + d) + math.hypot(0.5 * (a - d), b), 0.0)
        )  # largest eigenvalue
        std_th = math.sqrt(max(float(cov[2, 2]), 0.0))
        converged = (
            mass >= c.converged_mass
            and std_xy <= c.converged_std_xy
            and std_th <= c.converged_std_theta
        )
        if self.converged_once and self.lost_detector.lost:
            self._state = "lost"
        elif converged:
            if not self._belief_converged:
                # Converged (again): both averages restart from the next observation's
                # likelihood, so that w_slow measures the likelihood while tracking, not the
                # low likelihood of the spread global belief; otherwise a kidnapping is noticed
                # only after w_fast has decayed to the global level (25 updates measured on
                # the synthetic map of tests/test_particle_filter.py instead of 1-2). The lost
                # test starts afresh for the new belief.
                self._belief_converged = True
                self._restart_averages = True
                self.lost_detector.new_belief()
            self.converged_once = True
            # "tracking" once the views have confirmed the new belief; until then it is still
            # a search (a belief concentrated by one ambiguous image is often wrong)
            self._state = "tracking" if self.lost_detector.confirmed else "global"
        else:
            self._belief_converged = False
            self._state = "global"

    @property
    def state(self) -> State:
        return self._state

    @property
    def appearance_changes(self) -> int:
        """Appearance changes detected since construction (0 when the watch is off)."""
        return self.appearance_watch.changes if self.appearance_watch is not None else 0

    def estimate(self) -> Estimate:
        """Dominant mode: weighted mean (circular theta), covariance, ESS, state and doubt."""
        mean, cov, mass = self._dominant()
        return Estimate(
            pose=mean,
            covariance=cov,
            ess=self.ess(),
            n_particles=self.n,
            state=self._state,
            cluster_weight=mass,
            log_likelihood=float(self.last_log_likelihood),
            doubt=float(self.lost_detector.doubt),
        )
