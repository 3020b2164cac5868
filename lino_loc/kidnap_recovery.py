"""Kidnap recovery of the pose filter: likelihood averages, injection, validated candidate sets.

As in AMCL (Thrun et al., Probabilistic Robotics, table 8.3 "Augmented_MCL") the short- and
long-term averages ``w_fast``, ``w_slow`` of the APF's predictive likelihood of each observation
(``lino_loc.apf``) tell when the belief stops explaining the views. When the belief converges
(state ``global`` -> ``tracking``) both averages restart from the next likelihood, so that
``w_slow`` measures the likelihood while tracking rather than the low likelihood of the spread
initial belief.

Before the belief has converged (and with ``recovery="amcl"`` always), AMCL's rule: a fraction
``max(0, 1 - w_fast / w_slow)`` (capped by ``max_inject_fraction``) of the particles is replaced
by samples drawn from the sensor model's pose mixture. While tracking, that rule fails with an
appearance sensor model under changed light (measured in the lab, docs/evaluations.md: 0.32 /
3.32 / 3.28 m mean error under tube / bulb / natural light instead of 0.14 / 0.29 / 0.27 m
without recovery): ``w_fast / w_slow`` fluctuates about 1, so injection fires in most updates,
and the sensor model's wrong matches are wrong CONSISTENTLY over seconds (an aliased place
explains the views better than the true one for up to 30 s under ``natural`` light, with the
true place at the outlier floor), so injected particles capture the belief; even 5 % injection
does, and so does a candidate set tested by accumulated likelihood alone (an evidence of +219
nats over 150 updates was measured for a wrong place, against +240 nats over 50 updates for a
true kidnapping). What separates the two cases is how familiar the view is: after a
kidnapping in a mapped place the image is close to some map entry in feature space; under
other light it is not (``PoseMixture.novelty``, the distance to the nearest map entry over the
map's own median nearest-neighbour distance: 1.3 in the median under the mapping light in the
lab, 2.6 under ``bulb``, 3.7 under ``natural``). The recovery used while tracking
(``recovery="validated"``) is therefore:

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
likelihood, as a sequential likelihood-ratio test) gated by the view's familiarity. When the
lights are switched while tracking, w_slow still holds the old light's level and every view
looks like lost evidence; the filter's appearance-change detector
(``lino_loc.appearance_change``) then calls :meth:`KidnapRecovery.relearn_averages`. Measured
(240 s lab drive, scene changes, 1000 particles): mean error 0.15 / 0.33 / 0.30 m under tube /
bulb / natural light, the same as without recovery (no candidate set is drawn); a kidnapping
(the belief displaced by 3 m, or 2.5 m and 57 deg, or turned by 143 deg) under the mapping
light is recovered in 35-61 updates (7-12 s); the synthetic kidnapping of the tests in 27-33
updates (AMCL's rule: 1-15). Its limits: a kidnapping seen only through unfamiliar views
(other light) is NOT recovered (and under ``bulb`` light not even reported ``lost``, see
``lino_loc.lost_detection``); and a novelty threshold is
a property of the map's features (relative to the map's own spacing, so it transfers between
maps, but it was chosen on one simulated lab).

:class:`KidnapRecovery` is a mixin of ``lino_loc.particle_filter.AuxiliaryParticleFilter``
(it works on the filter's particles, weights, action model and random generator).

Usage (inside the filter's update)::

    self._track_likelihood(ll, self.familiarity(mixture.novelty), outlier_floor(mixture))
    if self.candidates is not None:
        self._test_candidates(delta, loglik, ll, familiarity)
    self._maybe_inject(mixture, pan, familiarity)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lino_loc.resampling import effective_sample_size, logsumexp
from lino_loc.sensor_model import PoseMixture

if TYPE_CHECKING:
    from lino_loc.motion_model import OdometryMotionModel
    from lino_loc.resampling import Resampler

FloatArray = NDArray[np.float64]

# log-likelihood standing in for exp underflow (the observation is not explained at all)
UNEXPLAINED = -745.0


def outlier_floor(mixture: PoseMixture) -> float:
    """log of the mixture's density far from every kernel inside the mapped area (the uniform
    outlier component), -inf without one."""
    if mixture.outlier_log_weight == -math.inf or mixture.bounds is None:
        return -math.inf
    return mixture.outlier_log_weight + mixture.bounds.log_uniform_density + mixture.log_scale


def log_ema(log_avg: float, log_value: float, alpha: float) -> float:
    """log((1 - alpha) exp(log_avg) + alpha exp(log_value)), in scalar arithmetic."""
    if alpha >= 1.0:
        return log_value
    a = math.log1p(-alpha) + log_avg
    b = math.log(alpha) + log_value
    hi, lo = (a, b) if a >= b else (b, a)
    if hi == -math.inf:
        return -math.inf
    return hi + math.log1p(math.exp(lo - hi))


class KidnapRecovery:
    """w_slow / w_fast tracking and kidnap recovery (see the module docstring); a mixin of
    the pose filter, which provides the attributes annotated here."""

    config: Any  # FilterConfig
    motion: OdometryMotionModel
    rng: np.random.Generator
    _resample: Resampler
    particles: FloatArray
    log_weights: FloatArray
    n: int
    converged_once: bool
    _state: str
    _restart_averages: bool
    _belief_converged: bool

    def sample_from_mixture(self, mixture: PoseMixture, pan: float, n: int) -> FloatArray:
        raise NotImplementedError

    def _reset_recovery(self) -> None:
        self.log_w_slow = -math.inf
        self.log_w_fast = -math.inf
        self.injected = 0
        self._restart_averages = False
        self._since_change: int | None = None  # updates since an appearance change (relearning)
        self.lost_updates = 0
        self.recoveries = 0  # candidate sets adopted since the last reset
        self.candidate_draws = 0  # candidate sets drawn since the last reset
        self._drop_candidates()

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
        """AMCL's w_slow / w_fast: exponential averages of the likelihood (in log space).

        After an appearance change (:meth:`relearn_averages`) both start as the plain mean of
        the likelihoods seen since (rate 1 / n until it falls to ``alpha_slow`` /
        ``alpha_fast``), so that w_slow is the typical likelihood under the NEW light rather
        than one frame's."""
        c = self.config
        if not math.isfinite(ll):
            ll = UNEXPLAINED
        a_slow, a_fast = c.alpha_slow, c.alpha_fast
        if self._since_change is not None:
            self._since_change += 1
            a_slow = max(a_slow, 1.0 / self._since_change)
            a_fast = max(a_fast, 1.0 / self._since_change)
            if a_slow <= c.alpha_slow:
                self._since_change = None
        if not math.isfinite(self.log_w_slow) or self._restart_averages:
            self._restart_averages = False
            self.log_w_slow = ll
            self.log_w_fast = ll
            self.lost_updates = 0
            return
        self.log_w_slow = log_ema(self.log_w_slow, ll, a_slow)
        self.log_w_fast = log_ema(self.log_w_fast, ll, a_fast)
        collapsed = self.log_w_fast < self.log_w_slow + math.log(c.recovery_ratio)
        unexplained = self.log_w_fast < floor + math.log(c.recovery_floor_factor)
        if not (collapsed or unexplained):
            self.lost_updates = 0
        elif self.candidates is None and familiarity >= 0.5:
            self.lost_updates += 1  # a novel view neither adds to nor clears the evidence

    def relearn_averages(self) -> None:
        """The scene's appearance changed (``lino_loc.appearance_change``): restart w_slow and
        w_fast as running means from the next likelihood, clear the lost evidence and drop a
        candidate set under test (it was drawn and scored under the old appearance)."""
        self._restart_averages = True
        self._since_change = 0
        self.lost_updates = 0
        self._drop_candidates()

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
        x = self.particles[idx]
        slots = self.rng.choice(self.n, size=m, replace=False)
        x[slots] = self.sample_from_mixture(mixture, pan, m)
        self.particles = x
        self.log_weights = np.full(self.n, -math.log(self.n))

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
        self.candidate_evidence += max(ll_cand, UNEXPLAINED) - familiarity * max(
            ll_main, UNEXPLAINED
        )
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
            self._belief_converged = False  # a new belief: its convergence restarts the tests
            self._state = "global"
        elif ev < -c.candidate_margin or age >= c.candidate_max_updates:
            self._drop_candidates()

    def _drop_candidates(self) -> None:
        self.candidates: FloatArray | None = None
        self.candidate_log_weights = np.zeros(0)
        self.candidate_evidence = 0.0
        self.candidate_age = 0
        self.candidate_trusted = 0.0
