"""Kidnap recovery: AMCL's likelihood averages, injection, and validated candidate sets.

AMCL (Thrun, Burgard, Fox, "Probabilistic Robotics", 2005, table 8.3): short- and long-term
exponential averages ``w_fast``, ``w_slow`` of the APF's predictive likelihood of each
observation (``lino_loc.apf``) tell when the belief stops explaining the views. In log space,

    log w <- log((1 - alpha) w + alpha p(y_t | y_1..t-1)),   alpha = ALPHA_SLOW or ALPHA_FAST,

a likelihood that is not finite counting as :data:`UNEXPLAINED`. Both averages (re)start from
the next likelihood when the belief (re)converges (:meth:`KidnapRecovery.restart_averages`),
so that ``w_slow`` measures the likelihood while tracking rather than that of the spread
initial belief, and after an appearance change (:meth:`KidnapRecovery.relearn_averages`) they
are plain running means of the likelihoods since (rate max(alpha, 1 / k) for the k-th).

Two ways to recover (``mode``, :class:`RecoveryConfig`):

- AMCL's rule, used before the belief has ever converged and always with ``mode="amcl"``: a
  fraction ``max(0, 1 - w_fast / w_slow)`` of the particles, capped by
  ``max_inject_fraction``, is replaced by draws from the sensor model's pose mixture
  (verdict ``inject``).
- validated recovery (``mode="validated"``, while tracking). With an appearance sensor model
  the wrong matches of a changed light are wrong consistently over seconds, so injected
  particles capture the belief; what separates a kidnapping in a mapped place from a changed
  light is how familiar the view is (``PoseMixture.novelty``). Hence:

  1. lost evidence: ``w_fast < RATIO * w_slow`` or ``w_fast < FLOOR_FACTOR`` x the sensor
     model's outlier floor (:func:`outlier_floor`: the belief explains the views no better
     than the uniform component); counted per update on views of familiarity >= 1/2 while no
     candidate set is under test (a novel view neither adds to nor clears the count);
  2. when it has held for :data:`MIN_UPDATES` counted updates and the view is familiar
     (familiarity 1), a SEPARATE candidate set of max(32, round(CANDIDATE_FRACTION N))
     particles is drawn from the sensor model (verdict ``draw``); the belief is left alone;
  3. the candidate set (:class:`CandidateSet`) is propagated with the odometry and weighted by
     the views (a bootstrap filter, resampled when its ESS falls below half its size), each
     view tempered by its familiarity f (p(y | x)^f: :meth:`KidnapRecovery.familiarity`); its
     evidence is the sum over updates of ``log p(y | candidates) - f log p(y | belief)``
     (both predictive likelihoods, floored at UNEXPLAINED), a sequential likelihood-ratio test;
  4. it replaces the belief (verdict ``adopt``, with N particles resampled from it) when the
     evidence exceeds ``candidate_margin`` after at least CANDIDATE_MIN_UPDATES trusted
     updates (the sum of f), and is dropped (verdict ``drop``) when the evidence falls below
     ``-candidate_margin`` or after CANDIDATE_MAX_UPDATES updates;
  5. with ``channel_margin`` > 0 and an observation of several channels (eq. 8's intensity
     and disparity), the candidate set must also be preferred by EVERY channel on its own:
     each channel's evidence, the same sum with the channel's likelihood of the view under the
     updated candidate set and under the updated belief, counted from the first update after
     the candidates have moved one independent view (``lino_loc.lost_detection.
     independent_views``: they sit on the kernels of the view they were drawn from, and must
     predict a view they were not drawn from), must exceed ``channel_margin``. A kidnapping
     moves the robot, so every channel prefers the right place; a changed light misleads the
     appearance channel only, and two channels pointing at different places is evidence of
     the light, not of a kidnapping.

A kidnapping seen only through unfamiliar views (another light) is not recovered. How the
constants were chosen and what they give: docs/results.md, "Notes moved from the code:
filter".

:class:`KidnapRecovery` keeps its own state and never touches the filter's particles: it
reads the belief's predictive likelihood and returns a :class:`Verdict` that the filter
carries out.

Usage (inside the filter's update)::

    verdict = recovery.observe(ll, mixture.novelty, outlier_floor(mixture), delta=d,
                               loglik=loglik, converged=pf.converged_once, n=pf.n,
                               draw=lambda m: pf.sample_from_mixture(mixture, pan, m), rng=rng)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from lino_loc.lost_detection import independent_views
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.resampling import Resampler, logsumexp, systematic
from lino_loc.sensor_model import PoseMixture
from lino_loc.weights import NoFiniteWeightError, Weights

FloatArray = NDArray[np.float64]

# log-likelihood standing in for exp underflow (the observation is not explained at all)
UNEXPLAINED = -745.0
# The constants below: docs/results.md, "Notes moved from the code: filter".
ALPHA_SLOW = 0.001  # rate of AMCL's long-term likelihood average w_slow, per update
ALPHA_FAST = 0.1  # rate of AMCL's short-term likelihood average w_fast, per update
RATIO = 0.2  # lost evidence: w_fast below this share of w_slow
FLOOR_FACTOR = 2.0  # lost evidence also: w_fast below this factor times the outlier floor
MIN_UPDATES = 5  # consecutive updates of lost evidence before a candidate set is drawn
CANDIDATE_FRACTION = 0.1  # candidate set size relative to the belief's (at least 32)
CANDIDATE_MIN_UPDATES = 8  # trusted updates a candidate set is tested before it may win
CANDIDATE_MAX_UPDATES = 40  # a candidate set that has not won after this many is dropped


class RecoveryConfig(BaseModel):
    """Kidnap recovery's settings, ``filter.recovery``."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["validated", "amcl"] = Field(
        "validated",
        description="while tracking: 'validated' draws a candidate set from the sensor model "
        "when the evidence of being lost is sustained and adopts it only when it out-scores the "
        "belief over several updates; 'amcl' injects into the belief directly",
    )
    max_inject_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="cap on the share of particles AMCL's rule replaces "
        "per update; 0 switches kidnap recovery off",
    )
    candidate_margin: float = Field(
        20.0, ge=0.0, description="log likelihood ratio (nats) by which a candidate set must "
        "out-score the belief to replace it",
    )
    familiar_novelty: float = Field(
        1.5, gt=0.0, description="views of novelty (PoseMixture.novelty) up to this count fully "
        "as evidence for kidnap recovery",
    )
    novel_novelty: float = Field(
        2.0, gt=0.0, description="... from this one on not at all (linear in between)"
    )
    channel_margin: float = Field(
        5.0, ge=0.0, description="log likelihood ratio (nats) by which EVERY channel of the "
        "observation (intensity, disparity) must also prefer a candidate set on its own, counted "
        "once it has moved one independent view, before it replaces the belief: a changed light "
        "misleads one channel, a kidnapping moves all of them; 0 switches the test off",
    )

    @model_validator(mode="after")
    def _ordered(self) -> RecoveryConfig:
        if self.novel_novelty <= self.familiar_novelty:
            raise ValueError("recovery.novel_novelty must exceed recovery.familiar_novelty")
        return self


def outlier_floor(mixture: PoseMixture) -> float:
    """log of the mixture's density far from every kernel inside the mapped area (the uniform
    outlier component: log w_out + log(1 / area 2 pi) + log_scale), -inf without one."""
    if mixture.outlier_log_weight == -math.inf or mixture.bounds is None:
        return -math.inf
    return mixture.outlier_log_weight + mixture.bounds.log_uniform_density + mixture.log_scale


def log_ema(log_avg: float, log_value: float, alpha: float) -> float:
    """log((1 - alpha) exp(log_avg) + alpha exp(log_value)), in scalar arithmetic; alpha >= 1
    gives log_value."""
    if alpha >= 1.0:
        return log_value
    a = math.log1p(-alpha) + log_avg
    b = math.log(alpha) + log_value
    hi, lo = (a, b) if a >= b else (b, a)
    if hi == -math.inf:
        return -math.inf
    return hi + math.log1p(math.exp(lo - hi))


@dataclass
class CandidateSet:
    """A hypothesis drawn from the sensor model, tested against the belief: its particles, its
    normalized weights, its evidence (nats), its age (updates) and its trusted updates (the
    sum of the views' familiarities)."""

    particles: FloatArray
    weights: Weights
    evidence: float = 0.0
    age: int = 0
    trusted: float = 0.0
    channel_evidence: dict[str, float] = field(default_factory=dict)
    seen: float = 0.0  # independent views since the draw


@dataclass(frozen=True)
class Verdict:
    """What the filter must do after :meth:`KidnapRecovery.observe`.

    ``none``: nothing; ``inject``: resample the belief to equal weights and replace ``count``
    random particles by draws from the sensor model; ``draw``: a candidate set of ``count``
    particles was drawn (the belief is left alone); ``drop``: the candidate set was dropped;
    ``adopt``: replace the belief by ``particles`` with equal weights (a new belief); ``join``:
    resample the belief to equal weights and replace ``count`` random particles by
    ``particles`` (a belief refuted by its rivals, ``lino_loc.belief_challenge``).
    ``count``: the particles injected, drawn or joined (``inject``, ``draw``, ``join``), else 0."""

    action: Literal["none", "inject", "draw", "drop", "adopt", "join"] = "none"
    count: int = 0
    particles: FloatArray | None = None


NOTHING = Verdict()


@dataclass(frozen=True)
class ChannelView:
    """One channel of an observation, for the candidate test's agreement (step 5): the
    log-likelihood of robot poses under the channel alone, and the channel's log-likelihood
    of the view under the updated belief, log sum_i pi^i p_c(y | x^i)."""

    loglik: Callable[[FloatArray], FloatArray]
    belief_ll: float


@dataclass
class KidnapRecovery:
    """w_slow / w_fast and kidnap recovery (see the module docstring)."""

    config: RecoveryConfig
    motion: OdometryMotionModel
    resample: Resampler = systematic
    log_w_slow: float = field(default=-math.inf, init=False)
    log_w_fast: float = field(default=-math.inf, init=False)
    lost_updates: int = field(default=0, init=False)  # consecutive updates of lost evidence
    recoveries: int = field(default=0, init=False)  # candidate sets adopted since the reset
    candidate_draws: int = field(default=0, init=False)  # candidate sets drawn since the reset
    candidates: CandidateSet | None = field(default=None, init=False)
    _restart: bool = field(default=False, init=False)
    _since_change: int | None = field(default=None, init=False)  # updates since relearning

    def reset(self) -> None:
        """Forget everything (a new start of the filter)."""
        self.log_w_slow = self.log_w_fast = -math.inf
        self.lost_updates = self.recoveries = self.candidate_draws = 0
        self.candidates = None
        self._restart = False
        self._since_change = None

    def restart_averages(self) -> None:
        """Restart w_slow and w_fast from the next likelihood (the belief converged anew)."""
        self._restart = True

    def forget_evidence(self) -> None:
        """The belief was replaced from outside: drop the candidate set, clear the evidence."""
        self.candidates = None
        self.lost_updates = 0

    def relearn_averages(self) -> None:
        """The scene's appearance changed (``lino_loc.appearance_change``): restart w_slow and
        w_fast as running means from the next likelihood, clear the lost evidence and drop a
        candidate set under test (it was drawn and scored under the old appearance)."""
        self._restart = True
        self._since_change = 0
        self.forget_evidence()

    def familiarity(self, novelty: float) -> float:
        """How far recovery may trust a view of the given novelty: 1 up to
        ``familiar_novelty``, 0 from ``novel_novelty`` on, linear in between; 1 if unknown."""
        c = self.config
        if not math.isfinite(novelty) or novelty <= c.familiar_novelty:
            return 1.0
        if novelty >= c.novel_novelty:
            return 0.0
        return (c.novel_novelty - novelty) / (c.novel_novelty - c.familiar_novelty)

    def track_likelihood(
        self, ll: float, familiarity: float = 1.0, floor: float = -math.inf
    ) -> None:
        """Feed one predictive log-likelihood to w_slow / w_fast and count the lost evidence
        (see the module docstring); ``floor`` is the sensor model's outlier floor."""
        if not math.isfinite(ll):
            ll = UNEXPLAINED
        a_slow, a_fast = ALPHA_SLOW, ALPHA_FAST
        if self._since_change is not None:
            self._since_change += 1
            a_slow = max(a_slow, 1.0 / self._since_change)
            a_fast = max(a_fast, 1.0 / self._since_change)
            if a_slow <= ALPHA_SLOW:
                self._since_change = None
        if not math.isfinite(self.log_w_slow) or self._restart:
            self._restart = False
            self.log_w_slow = self.log_w_fast = ll
            self.lost_updates = 0
            return
        self.log_w_slow = log_ema(self.log_w_slow, ll, a_slow)
        self.log_w_fast = log_ema(self.log_w_fast, ll, a_fast)
        collapsed = self.log_w_fast < self.log_w_slow + math.log(RATIO)
        unexplained = self.log_w_fast < floor + math.log(FLOOR_FACTOR)
        if not (collapsed or unexplained):
            self.lost_updates = 0
        elif self.candidates is None and familiarity >= 0.5:
            self.lost_updates += 1  # a novel view neither adds to nor clears the evidence

    def inject_fraction(self) -> float:
        """max(0, 1 - w_fast / w_slow), capped at ``max_inject_fraction``; 0 before both
        averages are known."""
        if not (math.isfinite(self.log_w_fast) and math.isfinite(self.log_w_slow)):
            return 0.0
        frac = max(0.0, 1.0 - math.exp(min(0.0, self.log_w_fast - self.log_w_slow)))
        return min(frac, self.config.max_inject_fraction)

    def predict(self, delta: FloatArray, rng: np.random.Generator) -> None:
        """An update without observation: the candidate set (if any) moves with the odometry."""
        if self.candidates is not None:
            self.candidates.particles = self.motion.sample(self.candidates.particles, delta, rng)

    def observe(
        self,
        ll: float,
        novelty: float,
        floor: float,
        *,
        delta: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        converged: bool,
        n: int,
        draw: Callable[[int], FloatArray],
        rng: np.random.Generator,
        channels: dict[str, ChannelView] | None = None,
        views: float | None = None,
    ) -> Verdict:
        """One observation: the belief's predictive log-likelihood ``ll``, the view's novelty,
        the outlier floor, the odometry increment, the log-likelihood of poses (for the
        candidate set), whether the belief has ever converged, the belief's size, a sampler
        of ``m`` poses from the sensor model and the random generator. Random draws, in
        order: the candidate set's (propagation, resampling, adoption), then ``draw``.
        ``channels``, for an observation of several channels: per channel, the log-likelihood
        of poses under that channel alone and the channel's log-likelihood of the view under
        the updated belief (step 5 of the module docstring); ``views``, the frame's
        independent views (default: those of ``delta``)."""
        fam = self.familiarity(novelty)
        self.track_likelihood(ll, fam, floor)
        verdict = NOTHING
        if self.candidates is not None:
            verdict = self._test_candidates(delta, loglik, ll, fam, n, rng, channels, views)
            if verdict.action == "adopt":
                return verdict
        decided = self._decide(converged, n, fam, draw)
        return decided if decided.action != "none" else verdict

    def _decide(
        self, converged: bool, n: int, familiarity: float, draw: Callable[[int], FloatArray]
    ) -> Verdict:
        """AMCL's injection, or (validated, after convergence) whether to draw candidates."""
        c = self.config
        if c.max_inject_fraction <= 0.0:
            return NOTHING
        if not (converged and c.mode == "validated"):
            return Verdict("inject", int(math.floor(self.inject_fraction() * n)))
        if self.candidates is None and self.lost_updates >= MIN_UPDATES and familiarity >= 1.0:
            m = max(32, int(round(CANDIDATE_FRACTION * n)))
            self.candidates = CandidateSet(draw(m), Weights.uniform(m))
            self.candidate_draws += 1
            self.lost_updates = 0  # a new candidate set needs sustained evidence again
            return Verdict("draw", m)
        return NOTHING

    def _test_candidates(
        self,
        delta: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        ll_main: float,
        familiarity: float,
        n: int,
        rng: np.random.Generator,
        channels: dict[str, ChannelView] | None = None,
        views: float | None = None,
    ) -> Verdict:
        """One bootstrap-filter step of the candidate set, its evidence (fused, and per
        channel when ``channels`` are given and ``channel_margin`` is set), and the decision;
        ``views``: the frame's independent views (default: the odometry increment's)."""
        cs = self.candidates
        assert cs is not None
        x = self.motion.sample(cs.particles, delta, rng)
        cs.age += 1
        if familiarity <= 0.0:  # a novel view: the sensor model is not trusted, predict only
            cs.particles = x
            return self._drop() if cs.age >= CANDIDATE_MAX_UPDATES else NOTHING
        # familiarity f tempers the likelihood, p(y | x)^f: a half-trusted view counts half
        m = x.shape[0]
        try:
            w = Weights.from_log(cs.weights.log + familiarity * loglik(x), one_pass=False)
            ll_cand = w.log_normalizer
        except NoFiniteWeightError:
            w, ll_cand = Weights.uniform(m), -math.inf
        cs.evidence += max(ll_cand, UNEXPLAINED) - familiarity * max(ll_main, UNEXPLAINED)
        cs.trusted += familiarity
        if w.ess() < 0.5 * m:
            x = x[self.resample(w, rng)]
            w = Weights.uniform(m)
        margin_c = self.config.channel_margin
        several = margin_c > 0.0 and channels is not None and len(channels) > 1
        if several and cs.seen >= 1.0:
            assert channels is not None
            for name, view in channels.items():
                ll_c = float(logsumexp(w.log + view.loglik(x)))
                gain = max(ll_c, UNEXPLAINED) - max(view.belief_ll, UNEXPLAINED)
                cs.channel_evidence[name] = cs.channel_evidence.get(name, 0.0) + familiarity * gain
        cs.seen += independent_views(delta) if views is None else views
        cs.particles, cs.weights = x, w
        agree = not several or (
            len(cs.channel_evidence) > 1 and min(cs.channel_evidence.values()) > margin_c
        )
        if cs.trusted >= CANDIDATE_MIN_UPDATES and cs.evidence > self.config.candidate_margin and agree:
            adopted = x[self.resample(w, rng, n)]
            self.recoveries += 1
            self.forget_evidence()
            self._restart = True
            return Verdict("adopt", 0, adopted)
        if cs.evidence < -self.config.candidate_margin or cs.age >= CANDIDATE_MAX_UPDATES:
            return self._drop()
        return NOTHING

    def _drop(self) -> Verdict:
        self.candidates = None
        return Verdict("drop")
