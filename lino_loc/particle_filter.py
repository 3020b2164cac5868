"""Auxiliary particle filter over robot poses (paper, eq. 2-6; Pitt and Shephard 1999).

The belief p(x_t | u_1..t, y_1..t) is carried by particles ``x^i`` (robot poses, (N, 3)) with
normalized log-weights ``log pi^i`` (eq. 4). One update with action u_t and observation y_t
(eq. 5-6) is the auxiliary particle filter of Pitt and Shephard, "Filtering via simulation:
auxiliary particle filters", JASA 94 (1999):

1. first stage: predict each particle's mean ``mu^i = E[x_t | u_t, x^i]`` (noise-free
   propagation) and weigh it by how well it explains the new observation,
   ``log lambda^i = log pi^i + log p(y_t | mu^i)``; draw ancestors ``k_j`` by these weights
   (systematic resampling);
2. propagate: ``x_t^j ~ p(x_t | u_t, x^{k_j})`` (the action model, eq. 5);
3. second stage: ``log pi_t^j = log p(y_t | x_t^j) - log p(y_t | mu^{k_j})`` (the correction
   that makes the pair of stages target eq. 6 exactly), normalized; resample again only when
   the effective sample size falls below ``resample_threshold * N``.

The generic step :func:`apf_step` takes the propagation and the likelihood as callables, so
any state space can be filtered (the tests run it on a linear-Gaussian model against the
Kalman filter). :class:`AuxiliaryParticleFilter` specializes it to robot poses, the odometry
action model and the appearance sensor model, whose mixture is over CAMERA poses and is
evaluated at ``camera_pose(particles, pan)``.

The product of the two stages also estimates the predictive likelihood of the observation,
``p(y_t | y_1..t-1) ~ (sum_i pi^i p(y | mu^i)) * mean_j(second-stage weights)``; as in AMCL
(Thrun et al., Probabilistic Robotics, table 8.3 "Augmented_MCL") its short- and long-term
averages ``w_fast``, ``w_slow`` tell when the belief stops explaining the views. When the belief
converges (state ``global`` -> ``tracking``) both averages restart from the next likelihood, so
that ``w_slow`` measures the likelihood while tracking rather than the low likelihood of the
spread initial belief.

Kidnap recovery. Before the belief has converged (and with ``recovery="amcl"`` always), AMCL's
rule: a fraction ``max(0, 1 - w_fast / w_slow)`` (capped by ``max_inject_fraction``) of the
particles is replaced by samples drawn from the sensor model's pose mixture. While tracking,
that rule fails with an appearance sensor model under changed light (measured in the lab,
docs/evaluations.md: 0.32 / 3.32 / 3.28 m mean error under tube / bulb / natural
light instead of 0.14 / 0.29 / 0.27 m without recovery): ``w_fast / w_slow`` fluctuates about 1,
so injection fires in most updates, and the sensor model's wrong matches are wrong
CONSISTENTLY over seconds (an aliased place explains the views better than the true one for
up to 30 s under ``natural`` light, with the true place at the outlier floor), so injected
particles capture the belief; even 5 % injection does, and so does a candidate set tested by
accumulated likelihood alone (an evidence of +219 nats over 150 updates was measured for a
wrong place, against +240 nats over 50 updates for a true kidnapping). What separates the two
cases is how familiar the view is: after a kidnapping in a mapped place the image is close to
some map entry in feature space; under other light it is not (``PoseMixture.novelty``, the
distance to the nearest map entry over the map's own median nearest-neighbour distance: 1.3
in the median under the mapping light in the lab, 2.6 under ``bulb``, 3.7 under ``natural``).
The recovery used while tracking (``recovery="validated"``) is therefore:

1. lost evidence: ``w_fast < recovery_ratio * w_slow`` (0.2: well under 1, not merely < 1) or
   ``w_fast < recovery_floor_factor`` x the sensor model's outlier floor (the belief explains
   the views no better than the uniform component: catches a belief that converged to a wrong
   place, where w_slow was learnt); counted only on familiar views (novel views neither add to
   nor clear the count);
2. when it has held for ``recovery_min_updates`` (5) counted updates and the current view is
   familiar (novelty <= ``familiar_novelty``), a SEPARATE candidate set (``candidate_fraction``
   of N, at least 32) is drawn from the sensor model; the belief is left alone;
3. the candidate set is propagated with the odometry and weighted by the views (a bootstrap
   filter), each view tempered by its familiarity f (p(y | x)^f: 1 below ``familiar_novelty``,
   0 above ``novel_novelty``, linear between); its evidence is the sum over updates of
   ``log p(y | candidates) - f log p(y | belief)`` (both predictive likelihoods, log space);
4. it replaces the belief when the evidence exceeds ``candidate_margin`` (20 nats) after at
   least ``candidate_min_updates`` (8) trusted updates, and is dropped when the evidence falls
   below ``-candidate_margin`` or after ``candidate_max_updates`` (40).

This is a multi-hypothesis check (the candidate competes with the belief by accumulated
likelihood, as a sequential likelihood-ratio test) gated by the view's familiarity. Measured
(240 s lab drive, scene changes, 1000 particles): mean error 0.15 / 0.33 / 0.30 m under tube /
bulb / natural light, the same as without recovery (no candidate set is drawn); a kidnapping
(the belief displaced by 3 m, or 2.5 m and 57 deg, or turned by 143 deg) under the mapping
light is recovered in 35-61 updates (7-12 s); the synthetic kidnapping of the tests in 27-33
updates (AMCL's rule: 1-15). Its limits: a kidnapping seen only through unfamiliar views
(other light) is NOT recovered, the filter reports ``lost`` instead; and a novelty threshold is
a property of the map's features (relative to the map's own spacing, so it transfers between
maps, but it was chosen on one simulated lab).

``first_stage_exponent`` (beta) tempers the first-stage weights to ``p(y | mu)^beta`` (the
second stage divides by the same factor, so the filter stays exact): beta = 1 is the classic
APF, beta = 0 the bootstrap filter. On the linear-Gaussian test model the classic APF's ESS
dips to ~n/30 on an outlying observation (its first-stage weights ignore the process noise);
keep beta = 1 unless the motion noise is large against the kernel widths.

The estimate is the dominant mode of the belief. When every particle lies within
``compact_xy`` (1 m) and ``compact_theta`` (60 deg) of the weighted mean, the cloud is one mode
and its weighted mean and covariance are the estimate (the usual case while tracking; saves
the ~1 ms clustering at 1000 particles). Otherwise particles are binned into cells
(0.5 m x 30 deg by default), occupied cells that touch (26-neighbourhood, heading cyclic) form
clusters, and the heaviest cluster gives the weighted mean (circular mean for theta) and the
3 x 3 covariance (heading differences wrapped about the mean). States: ``global`` (no cluster
holds ``converged_mass`` of the weight, or its spread is large), ``tracking`` (converged),
``lost`` (it had converged, and the observation likelihood has since collapsed:
``w_fast < lost_ratio * w_slow``).

Usage::

    pf = AuxiliaryParticleFilter(OdometryMotionModel(), bounds, FilterConfig(n_particles=1000))
    pf.start_global()
    pf.update(delta, pan, sensor_model.observe(y))
    est = pf.estimate()
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from lino_loc.errors import LinoLocError
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.poses import wrap_angle
from lino_loc.resampling import (
    Resampler,
    effective_sample_size,
    get_resampler,
    logsumexp,
    systematic,
    weights_from_log,
)
from lino_loc.sensor_model import Bounds, PoseMixture

FloatArray = NDArray[np.float64]
FreeSpace = Callable[[FloatArray], NDArray[np.bool_]]
State = Literal["global", "tracking", "lost"]


# --------------------------------------------------------------------------- generic core


@dataclass
class StepResult:
    """Outcome of one :func:`apf_step`."""

    particles: FloatArray
    log_weights: FloatArray  # normalized
    log_likelihood: float  # estimate of log p(y_t | y_1..t-1), -inf if nothing explains y
    ancestors: NDArray[np.int64]


def normalize(log_weights: ArrayLike) -> FloatArray:
    lw = np.asarray(log_weights, dtype=np.float64)
    return lw - logsumexp(lw)


def apf_step(
    particles: FloatArray,
    log_weights: FloatArray,
    rng: np.random.Generator,
    *,
    predict_mean: Callable[[FloatArray], FloatArray],
    propagate: Callable[[FloatArray, np.random.Generator], FloatArray],
    log_likelihood: Callable[[FloatArray], FloatArray] | None,
    resample: Resampler = systematic,
    first_stage_exponent: float = 1.0,
) -> StepResult:
    """One auxiliary-particle-filter step (Pitt and Shephard 1999; paper eq. 5-6).

    ``log_weights`` must be normalized. ``log_likelihood=None`` means no observation: the
    particles are propagated and keep their weights. ``first_stage_exponent`` (beta) tempers
    the first-stage weights, ``p(y | mu)^beta``; beta = 1 is the classic APF, beta = 0 the
    bootstrap filter. The second stage divides by the same factor, so the target is exact for
    every beta.
    """
    n = particles.shape[0]
    if log_likelihood is None:
        return StepResult(propagate(particles, rng), log_weights.copy(), 0.0, np.arange(n))
    l1 = (
        first_stage_exponent * log_likelihood(predict_mean(particles))
        if first_stage_exponent
        else np.zeros(n)
    )
    lw1 = log_weights + l1
    log_c1 = float(logsumexp(lw1))
    if not math.isfinite(log_c1):  # no predicted mean explains y: fall back to the bootstrap filter
        l1 = np.zeros(n)
        lw1 = log_weights
        log_c1 = 0.0
    anc = resample(lw1, rng)
    x = propagate(particles[anc], rng)
    l2 = log_likelihood(x)
    lw2 = l2 - l1[anc]
    log_c2 = float(logsumexp(lw2))
    if not math.isfinite(log_c2):  # nothing explains y: keep the prediction, uniform weights
        return StepResult(x, np.full(n, -math.log(n)), -math.inf, anc)
    return StepResult(x, lw2 - log_c2, log_c1 + log_c2 - math.log(n), anc)


def _camera_loglik(mixture: PoseMixture, pan: float) -> Callable[[FloatArray], FloatArray]:
    """x (robot poses) -> log p(y | camera_pose(x, pan)) under the sensor-model mixture."""

    def loglik(x: FloatArray) -> FloatArray:
        # camera_pose(x, pan) without the wrap: the kernels use cos/sin of the heading
        if pan == 0.0:
            return mixture.log_pdf(x)
        cam = x.copy()
        cam[:, 2] += pan
        return mixture.log_pdf(cam)

    return loglik


def _outlier_floor(mixture: PoseMixture) -> float:
    """log of the mixture's density far from every kernel inside the mapped area (the uniform
    outlier component), -inf without one."""
    if mixture.outlier_log_weight == -math.inf or mixture.bounds is None:
        return -math.inf
    return mixture.outlier_log_weight + mixture.bounds.log_uniform_density + mixture.log_scale


def _log_ema(log_avg: float, log_value: float, alpha: float) -> float:
    """log((1 - alpha) exp(log_avg) + alpha exp(log_value))."""
    if alpha >= 1.0:
        return log_value
    return float(np.logaddexp(math.log1p(-alpha) + log_avg, math.log(alpha) + log_value))


# --------------------------------------------------------------------------- estimate


def cluster_labels(
    poses: FloatArray, cell_xy: float = 0.5, cell_theta: float = math.radians(30.0)
) -> NDArray[np.int64]:
    """Connected components of occupied (x, y, theta) cells; heading bins are cyclic.

    Two particles are in the same cluster when a chain of occupied cells, each touching the
    next (26-neighbourhood), joins their cells. Returns one label (0..C-1) per pose.
    Implementation: ``scipy.ndimage.label`` on the dense occupancy grid of the particles'
    bounding box, then the labels that touch across the heading seam (-pi / pi) are merged.
    """
    p = np.asarray(poses, dtype=np.float64)
    n_th = max(1, int(round(2.0 * math.pi / cell_theta)))
    ix = np.floor(p[:, 0] / cell_xy).astype(np.int64)
    iy = np.floor(p[:, 1] / cell_xy).astype(np.int64)
    it = np.floor((wrap_angle(p[:, 2]) + math.pi) / (2.0 * math.pi / n_th)).astype(np.int64) % n_th
    ix -= ix.min()
    iy -= iy.min()
    shape = (int(ix.max()) + 1, int(iy.max()) + 1, n_th)
    occ = np.zeros(shape, dtype=bool)
    occ[ix, iy, it] = True
    grid, n_lab = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    if n_th >= 3 and n_lab > 1:
        # 26-neighbourhood across the seam: cell (x, y, last) touches (x + a, y + b, 0).
        first, last = grid[:, :, 0], grid[:, :, -1]
        pairs = []
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                sa = slice(max(a, 0), shape[0] + min(a, 0))
                sb = slice(max(b, 0), shape[1] + min(b, 0))
                ta = slice(max(-a, 0), shape[0] + min(-a, 0))
                tb = slice(max(-b, 0), shape[1] + min(-b, 0))
                la, lb = last[ta, tb], first[sa, sb]
                both = (la > 0) & (lb > 0) & (la != lb)
                if both.any():
                    pairs.append(np.column_stack([la[both], lb[both]]))
        if pairs:
            parent = np.arange(n_lab + 1)

            def find(u: int) -> int:
                while parent[u] != u:
                    parent[u] = parent[parent[u]]
                    u = int(parent[u])
                return u

            for u, v in np.unique(np.concatenate(pairs), axis=0):
                ru, rv = find(int(u)), find(int(v))
                if ru != rv:
                    parent[max(ru, rv)] = min(ru, rv)
            roots = np.array([find(u) for u in range(n_lab + 1)])
            grid = roots[grid]
    if n_lab <= 1:
        return np.zeros(p.shape[0], dtype=np.int64)
    lab = grid[ix, iy, it]
    present = np.zeros(int(grid.max()) + 1, dtype=bool)  # relabel 0..C-1 without sorting
    present[lab] = True
    return (np.cumsum(present) - 1)[lab].astype(np.int64)


def _pose_stats(poses: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(mean, covariance, deviations from the mean (3, M) with theta wrapped) of weighted poses."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    p = np.asarray(poses, dtype=np.float64)
    # vector dot products only (a 3 x 3 einsum over M poses cost 3x more; BLAS matrix
    # products are avoided in hot paths, see sensor_model.PoseMixture._component_terms)
    d = np.empty((3, p.shape[0]))
    d[0], d[1], d[2] = p[:, 0], p[:, 1], p[:, 2]
    mean = np.array(
        [
            np.dot(w, d[0]),
            np.dot(w, d[1]),
            math.atan2(np.dot(w, np.sin(d[2])), np.dot(w, np.cos(d[2]))),
        ]
    )
    d -= mean[:, None]
    d[2] = wrap_angle(d[2])
    wd = d * w
    cov = np.empty((3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[i, j] = cov[j, i] = np.dot(wd[i], d[j])
    return mean, cov, d


def weighted_pose_stats(poses: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted mean (circular mean for theta) and 3 x 3 covariance (theta wrapped about the mean)."""
    mean, cov, _ = _pose_stats(poses, weights)
    return mean, cov


@dataclass(frozen=True)
class PoseEstimate:
    """The filter's estimate: dominant mode, its covariance, and how much to trust it."""

    pose: FloatArray  # (3,) robot pose
    covariance: FloatArray  # (3, 3) over (x, y, theta)
    ess: float
    n_particles: int
    state: State
    cluster_weight: float  # weight of the dominant cluster, in [0, 1]
    log_likelihood: float  # last observation's predictive log-likelihood (nan if none yet)


# --------------------------------------------------------------------------- pose filter


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
    lost_ratio: float = Field(
        0.5, gt=0.0, le=1.0, description="lost when w_fast < lost_ratio * w_slow"
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
    seed: int | None = None


class AuxiliaryParticleFilter:
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
        self.particles = np.zeros((n, 3))
        self.log_weights = np.full(n, -math.log(n))
        self.start_global()

    # ----------------------------------------------------------------- initial beliefs

    @property
    def n(self) -> int:
        return int(self.particles.shape[0])

    def _reset_tracking(self) -> None:
        self.log_w_slow = -math.inf
        self.log_w_fast = -math.inf
        self.last_log_likelihood = math.nan
        self.converged_once = False
        self.injected = 0
        self._state: State = "global"
        self._summary: tuple[FloatArray, FloatArray, float] | None = None
        self._restart_averages = False
        self.lost_updates = 0
        self.recoveries = 0  # candidate sets adopted since the last reset
        self.candidate_draws = 0  # candidate sets drawn since the last reset
        self._drop_candidates()

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
        self._summary = None
        self._drop_candidates()  # a candidate set tested against the old belief is void
        self.lost_updates = 0
        self._uniform_prior = False

    # ----------------------------------------------------------------- update

    @property
    def weights(self) -> FloatArray:
        return weights_from_log(self.log_weights)

    def ess(self) -> float:
        return effective_sample_size(self.log_weights)

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
        self.particles = self.motion.sample(self.particles, delta, self.rng)
        if self.candidates is not None:
            self.candidates = self.motion.sample(self.candidates, delta, self.rng)
        self._summary = None

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
        if getattr(self, "_uniform_prior", False) and self.config.global_proposal_fraction > 0.0:
            return self.global_seed(d, pan, mixture)
        self._uniform_prior = False

        loglik = _camera_loglik(mixture, pan)
        res = apf_step(
            self.particles,
            self.log_weights,
            self.rng,
            predict_mean=lambda x: self.motion.predict_mean(x, d),
            propagate=lambda x, g: self.motion.sample(x, d, g),
            log_likelihood=loglik,
            resample=self._resample,
            first_stage_exponent=self.config.first_stage_exponent,
        )
        self.particles, self.log_weights = res.particles, res.log_weights
        ll = res.log_likelihood
        self.last_log_likelihood = ll
        fam = self.familiarity(mixture.novelty)
        self._track_likelihood(ll, fam, _outlier_floor(mixture))
        self.injected = 0
        if self.candidates is not None:
            self._test_candidates(d, loglik, ll, fam)
        self._maybe_inject(mixture, pan, fam)
        if self.ess() < self.config.resample_threshold * self.n:
            idx = self._resample(self.log_weights, self.rng)
            self.particles = self.particles[idx]
            self.log_weights = np.full(self.n, -math.log(self.n))
        self._update_state()
        return ll

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
        self._summary = None
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
            idx = self._resample(self.log_weights, self.rng)
            self.particles = self.particles[idx]
            self.log_weights = np.full(self.n, -math.log(self.n))
        self._update_state()
        return ll

    def familiarity(self, novelty: float) -> float:
        """How far kidnap recovery may trust an observation of the given novelty: 1 below
        ``familiar_novelty``, 0 above ``novel_novelty``, linear in between; 1 if unknown."""
        c = self.config
        if not math.isfinite(novelty):
            return 1.0
        if novelty <= c.familiar_novelty:
            return 1.0
        if novelty >= c.novel_novelty:
            return 0.0
        return (c.novel_novelty - novelty) / (c.novel_novelty - c.familiar_novelty)

    def _track_likelihood(
        self, ll: float, familiarity: float = 1.0, floor: float = -math.inf
    ) -> None:
        """AMCL's w_slow / w_fast: exponential averages of the likelihood (in log space)."""
        c = self.config
        if not math.isfinite(ll):
            ll = -745.0  # exp underflow: the observation is not explained at all
        if not math.isfinite(self.log_w_slow) or self._restart_averages:
            self._restart_averages = False
            self.log_w_slow = ll
            self.log_w_fast = ll
            self.lost_updates = 0
            return
        self.log_w_slow = _log_ema(self.log_w_slow, ll, c.alpha_slow)
        self.log_w_fast = _log_ema(self.log_w_fast, ll, c.alpha_fast)
        collapsed = self.log_w_fast < self.log_w_slow + math.log(c.recovery_ratio)
        unexplained = self.log_w_fast < floor + math.log(c.recovery_floor_factor)
        if not (collapsed or unexplained):
            self.lost_updates = 0
        elif self.candidates is None and familiarity >= 0.5:
            self.lost_updates += 1  # a novel view neither adds to nor clears the evidence

    def inject_fraction(self) -> float:
        """max(0, 1 - w_fast / w_slow), capped at ``max_inject_fraction``."""
        if not (math.isfinite(self.log_w_fast) and math.isfinite(self.log_w_slow)):
            return 0.0
        frac = max(0.0, 1.0 - math.exp(min(0.0, self.log_w_fast - self.log_w_slow)))
        return min(frac, self.config.max_inject_fraction)

    def _maybe_inject(self, mixture: PoseMixture, pan: float, familiarity: float = 1.0) -> None:
        """Kidnap recovery (see module docstring).

        Before the belief has converged (global localization) and with ``recovery="amcl"``: a
        fraction ``inject_fraction()`` of the particles is replaced by draws from the sensor
        model, as AMCL does. While tracking with ``recovery="validated"``: when w_fast has stayed
        below ``recovery_ratio * w_slow`` for ``recovery_min_updates`` updates, a separate
        candidate set is drawn from the sensor model; :meth:`_test_candidates` decides.
        """
        c = self.config
        if c.max_inject_fraction <= 0.0:
            return
        if self.converged_once and c.recovery == "validated":
            if (
                self.candidates is None
                and self.lost_updates >= c.recovery_min_updates
                and familiarity >= 1.0
            ):
                m = max(32, int(round(c.candidate_fraction * self.n)))
                self.candidates = self.sample_from_mixture(mixture, pan, m)
                self.candidate_log_weights = np.full(m, -math.log(m))
                self.candidate_evidence = 0.0
                self.candidate_age = 0
                self.candidate_trusted = 0.0
                self.candidate_draws += 1
                self.injected = m
                self.lost_updates = 0  # a new candidate set needs sustained evidence again
            return
        m = int(math.floor(self.inject_fraction() * self.n))
        self.injected = m
        if m <= 0:
            return
        # Resample the whole set to equal weights, then overwrite m randomly chosen particles.
        idx = self._resample(self.log_weights, self.rng)
        self.particles = self.particles[idx]
        self.log_weights = np.full(self.n, -math.log(self.n))
        slots = self.rng.choice(self.n, size=m, replace=False)
        self.particles[slots] = self.sample_from_mixture(mixture, pan, m)

    def _test_candidates(
        self,
        delta: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        ll_main: float,
        familiarity: float = 1.0,
    ) -> None:
        """Propagate the candidate set (bootstrap filter), add the log of its predictive
        likelihood minus the belief's to the evidence, and decide: adopt the candidates when
        the evidence exceeds ``candidate_margin`` after at least ``candidate_min_updates``,
        drop them when it falls below ``-candidate_margin`` or after ``candidate_max_updates``."""
        c = self.config
        assert self.candidates is not None
        x = self.motion.sample(self.candidates, delta, self.rng)
        self.candidate_age += 1
        if familiarity <= 0.0:  # a novel view: the sensor model is not trusted, predict only
            self.candidates = x
            if self.candidate_age >= c.candidate_max_updates:
                self._drop_candidates()
            return
        # familiarity f tempers the likelihood, p(y | x)^f: a half-trusted view counts half
        lw = self.candidate_log_weights + familiarity * loglik(x)
        ll_cand = float(logsumexp(lw))
        floor = -745.0
        self.candidate_evidence += max(ll_cand, floor) - familiarity * max(ll_main, floor)
        self.candidate_trusted += familiarity
        if math.isfinite(ll_cand):
            lw = lw - ll_cand
        else:
            lw = np.full(x.shape[0], -math.log(x.shape[0]))
        if effective_sample_size(lw) < 0.5 * x.shape[0]:
            x = x[self._resample(lw, self.rng)]
            lw = np.full(x.shape[0], -math.log(x.shape[0]))
        self.candidates, self.candidate_log_weights = x, lw
        ev, age = self.candidate_evidence, self.candidate_age
        if self.candidate_trusted >= c.candidate_min_updates and ev > c.candidate_margin:
            idx = self._resample(lw, self.rng, self.n)
            self.particles = x[idx]
            self.log_weights = np.full(self.n, -math.log(self.n))
            self.recoveries += 1
            self._drop_candidates()
            self.lost_updates = 0
            self._restart_averages = True
            self._state = "global"
        elif ev < -c.candidate_margin or age >= c.candidate_max_updates:
            self._drop_candidates()

    def _drop_candidates(self) -> None:
        self.candidates = None
        self.candidate_log_weights = np.zeros(0)
        self.candidate_evidence = 0.0
        self.candidate_age = 0
        self.candidate_trusted = 0.0

    # ----------------------------------------------------------------- estimate

    def _dominant(self) -> tuple[FloatArray, FloatArray, float]:
        """(mean, covariance, weight) of the heaviest cluster; cached until the particles change."""
        if self._summary is None:
            self._summary = self._compute_dominant()
        return self._summary

    def _compute_dominant(self) -> tuple[FloatArray, FloatArray, float]:
        c = self.config
        w = self.weights
        # Compact cloud (the usual case while tracking): every particle within compact_xy and
        # compact_theta of the weighted mean is one mode, whatever a cell grid would say; the
        # clustering (~1 ms at 1000 particles) is skipped.
        mean, cov, d = _pose_stats(self.particles, w)
        if (
            float(np.max(d[0] * d[0] + d[1] * d[1])) <= c.compact_xy**2
            and float(np.max(np.abs(d[2]))) <= c.compact_theta
        ):
            return mean, cov, 1.0
        labels = cluster_labels(self.particles, c.cluster_cell_xy, c.cluster_cell_theta)
        if labels.max() == 0:  # one cluster
            return mean, cov, 1.0
        mass = np.bincount(labels, weights=w)
        best = int(np.argmax(mass))
        sel = labels == best
        mean, cov = weighted_pose_stats(self.particles[sel], w[sel])
        return mean, cov, float(mass[best])

    def _update_state(self) -> None:
        self._summary = None
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
        collapsed = (
            math.isfinite(self.log_w_fast)
            and math.isfinite(self.log_w_slow)
            and self.log_w_fast < self.log_w_slow + math.log(c.lost_ratio)
        )
        if self.converged_once and collapsed:
            self._state = "lost"
        elif converged:
            if self._state == "global":
                # Converged (again): both averages restart from the next observation's
                # likelihood, so that w_slow measures the likelihood while tracking, not the
                # low likelihood of the spread global belief; otherwise a kidnapping is noticed
                # only after w_fast has decayed to the global level (25 updates measured on
                # the synthetic map of tests/test_particle_filter.py instead of 1-2).
                self._restart_averages = True
            self._state = "tracking"
            self.converged_once = True
        else:
            self._state = "global"

    @property
    def state(self) -> State:
        return self._state

    def estimate(self) -> PoseEstimate:
        """Dominant mode: weighted mean (circular theta), covariance, ESS and state."""
        mean, cov, mass = self._dominant()
        return PoseEstimate(
            pose=mean,
            covariance=cov,
            ess=self.ess(),
            n_particles=self.n,
            state=self._state,
            cluster_weight=mass,
            log_likelihood=float(self.last_log_likelihood),
        )
