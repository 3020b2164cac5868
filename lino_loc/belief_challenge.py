"""Is a new belief the place, or one of several that look alike? A sequential test against rivals.

A search (global localization, a recovery) converges when the particles gather in one mode.
That says the views so far fit that mode; it does not say that no other place fits them as
well. A particle filter loses the other places as it resamples, so the mode's weight share
overstates how sure the views make it (a row of identical doors, a light the map was not made
in). Before the filter calls a new belief ``tracking`` it must beat its RIVALS: a particle set
drawn from the sensor model's mixture of the views (the places the views look like) away from
the belief, propagated by the same odometry and weighted by the same views (a bootstrap
filter, as kidnap recovery's candidate sets, ``lino_loc.kidnap_recovery``).

The test is Wald's sequential probability ratio test (Wald 1945) between "the camera is at the
belief" and "it is at one of the rivals", on the predictive likelihoods of the two sets:

    E_t = max(-margin, E_t-1 + v_t clip(log p(y_t | belief) - log p(y_t | rivals), +-max_view_nats)),

v_t the frame's share of an independent view (``lino_loc.lost_detection.independent_views``
of the camera's increment: consecutive frames of one view are not independent evidence; a
camera that did not move adds nothing). The belief PASSES when E_t reaches ``margin``; until
then the filter keeps calling it ``global``. E_t does not fall below -``margin``: rivals that
explain the views better keep the belief unconfirmed, and the belief must out-score them by
the whole width 2 ``margin`` to pass.

A belief the rivals keep beating is REFUTED: when E_t has stayed at -``margin`` for
``refute_views`` independent views in a row (the rivals out-scored the belief on every one of
them), a share ``refute_share`` of the belief's particles is replaced by rivals (drawn by their
weights) and the streak starts again. The rivals JOIN the belief rather than replace it: the
filter's own weighting over the next views decides between the old place and the new ones, so
a right belief that a changed light made look worse for a while keeps its place, and a search
that settled on the wrong place gets the better ones back (a converged particle filter has
lost them; Mixture-MCL's dual proposal, Thrun, Fox, Burgard, Dellaert 2001, restores them the
same way).

Rivals are the particles more than :data:`lino_loc.lost_detection.CONFIRM_RADIUS_XY` (1 m, the
evaluations' confident-wrong bound) in position or
:data:`lino_loc.lost_detection.CONFIRM_RADIUS_THETA` in heading from the belief's estimate
(:func:`lino_loc.lost_detection.near_pose`): a rival that drifts into the belief's
neighbourhood is no longer a rival and loses its weight. After each view a share
:data:`REFRESH` of them is replaced by draws from that view's mixture away from the belief
(Mixture-MCL's dual proposal, Thrun, Fox, Burgard, Dellaert 2001): every view adds the places
it looks like, and the test stays one between the belief and the best alternatives of the
recent views. The draws are scored from the next view on (no view scores its own draws).
While there are no rivals (the views' kernels all lie near the belief) the alternative is the
sensor model's outlier component, whose density is the outlier floor.

Usage (inside the filter's update, after the APF step)::

    challenge.start(pose)                                # a belief converged at pose
    challenge.observe(ll, floor, v, delta=d, loglik=loglik, near=near, draw=draw, n=n, rng=rng)
    challenge.passed                                     # the belief beat its rivals
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from lino_loc.kidnap_recovery import UNEXPLAINED, CandidateSet, Verdict
from lino_loc.lost_detection import near_pose
from lino_loc.motion_model import OdometryMotionModel
from lino_loc.resampling import Resampler, systematic
from lino_loc.weights import NoFiniteWeightError, Weights

FloatArray = NDArray[np.float64]

#: rivals drawn per challenge (at least; ``rival_fraction`` of the belief's particles otherwise)
MIN_RIVALS = 32
#: draws from the view's mixture per rival wanted: most of a view's kernels may lie near the
#: belief, the rest are the rivals
DRAW_FACTOR = 4


class ChallengeConfig(BaseModel):
    """The challenge of a new belief by its rivals, ``filter.challenge``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="a belief converged from a search is 'tracking' only once it has "
        "out-scored the places the views also look like (rivals drawn from the sensor model); "
        "chosen with the defaults below on three worlds x three seeds (docs/results.md)",
    )
    margin: float = Field(
        8.0, gt=0.0, description="nats, counted per independent view: the belief passes when "
        "its log likelihood ratio against the rivals reaches +margin (the ratio is held at "
        "-margin or above)",
    )
    max_view_nats: float = Field(
        4.0, gt=0.0, description="a view's log likelihood ratio is clipped to +-this, so that "
        "no one view decides the test",
    )
    rival_fraction: float = Field(
        0.1, gt=0.0, le=1.0, description="rivals per challenge, as a share of the belief's "
        f"particles (at least {MIN_RIVALS})",
    )
    refresh: float = Field(
        0.2, ge=0.0, le=1.0, description="share of the rivals replaced after each view by "
        "draws from that view's mixture (0: drawn once, again only when none is left)",
    )
    probation_views: float = Field(
        1.0, ge=0.0, description="a refreshed rival is scored only once the camera has moved "
        "this many independent views since it was drawn: it must predict a view it was not "
        "drawn from",
    )
    refute_views: float = Field(
        5.0, ge=0.0, description="independent views in a row with the evidence at -margin "
        "that refute the belief: rivals then join it (0: never)",
    )
    refute_share: float = Field(
        0.5, gt=0.0, le=1.0, description="share of a refuted belief's particles replaced by "
        "rivals drawn by their weights",
    )
    after_misfit: bool = Field(
        True, description="a tracked belief whose views stop fitting it (the view fit's "
        "misfit, reported 'lost') is challenged again, as a new belief is: it is 'tracking' "
        "again only once it has out-scored its rivals, who never join it (false: once its "
        "views fit again); chosen with after_misfit_views on three worlds x five seeds "
        "(docs/results.md, 'A belief its views refuted is challenged again')",
    )
    after_misfit_views: float = Field(
        3.0, ge=0.0, description="with after_misfit: the misfit must have lasted this many "
        "independent views in a row (0: the first misfit frame); lower reports 'tracking' "
        "less often",
    )
    adopt: bool = Field(
        False, description="rivals that reach -margin replace the belief (a search that "
        "settled on the wrong place starts again from the better one); off: measured, it made "
        "the belief jump between aliased places under another light",
    )


@dataclass
class BeliefChallenge:
    """The SPRT of a new belief against its rivals (see the module docstring)."""

    config: ChallengeConfig
    motion: OdometryMotionModel
    resample: Resampler = systematic
    active: bool = field(default=False, init=False)
    passed: bool = field(default=True, init=False)  # no challenge: nothing to pass
    evidence: float = field(default=0.0, init=False)  # E_t, nats
    rivals: CandidateSet | None = field(default=None, init=False)
    challenges: int = field(default=0, init=False)  # challenges started since construction
    rival_wins: int = field(default=0, init=False)  # times the rivals reached -margin
    refutations: int = field(default=0, init=False)  # times the rivals joined a refuted belief
    _pinned: float = field(default=0.0, init=False)  # independent views in a row at -margin
    _seen: FloatArray | None = field(default=None, init=False)  # views each rival has lived
    _at: FloatArray | None = field(default=None, init=False)  # where the last challenge was
    _won: bool = field(default=False, init=False)  # ... and whether it passed
    _refuting: bool = field(default=True, init=False)  # rivals may join a refuted belief

    def start(self, pose: ArrayLike, refute: bool = True) -> None:
        """A belief converged at robot pose ``pose``: challenge it (when enabled). The same
        belief converged again (within :func:`lino_loc.lost_detection.near_pose` of where the
        last challenge stopped) resumes that challenge, its evidence and verdict kept: a
        belief that spreads for a moment does not start afresh. ``refute`` false: the
        challenge only decides whether the belief is confirmed; rivals that keep beating it
        never join it (a tracked belief challenged again after its views misfit)."""
        self._refuting = refute
        p = np.asarray(pose, dtype=np.float64).reshape(3)
        same = self._at is not None and bool(near_pose(p[None, :], self._at)[0])
        self._at = p
        self.rivals = self._seen = None
        if not same:
            self.evidence, self._won, self._pinned = 0.0, False, 0.0
            self.challenges += int(self.config.enabled)
        self.passed = self._won or not self.config.enabled
        self.active = not self.passed

    def stop(self) -> None:
        """The belief spread: nothing to challenge, nothing passed until it converges again
        (:meth:`start` then resumes the challenge of a belief at the same place)."""
        self.rivals = self._seen = None
        self.active = False
        self.passed = False

    def reset(self) -> None:
        """A new belief elsewhere (a new start, a recovery): forget the last challenge."""
        self.stop()
        self._at, self.evidence, self._won, self._pinned = None, 0.0, False, 0.0

    def waive(self) -> None:
        """The belief needs no challenge (a pose given by the user)."""
        self.reset()
        self.passed = True

    def predict(self, delta: FloatArray, rng: np.random.Generator) -> None:
        """An update without observation: the rivals move with the odometry."""
        if self.rivals is not None:
            self.rivals.particles = self.motion.sample(self.rivals.particles, delta, rng)

    def observe(
        self,
        ll: float,
        floor: float,
        views: float,
        *,
        delta: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        near: Callable[[FloatArray], NDArray[np.bool_]],
        draw: Callable[[int], FloatArray],
        n: int,
        rng: np.random.Generator,
    ) -> Verdict | None:
        """One observation: the belief's predictive log-likelihood ``ll``, the outlier floor,
        the frame's independent views ``views``, the odometry increment, the log-likelihood of
        robot poses, which robot poses are near the belief, a sampler of ``m`` robot poses from
        the view's mixture, the belief's size and the random generator. Returns what the filter
        must do to the belief: ``adopt`` (``n`` rivals replace it: the rivals won and ``adopt``
        is set), ``join`` (rivals replace ``count`` of its particles: the belief is refuted),
        else None."""
        if not self.active:
            return None
        ll_rivals = self._step_rivals(delta, loglik, near, rng, views)
        if ll_rivals is None:
            ll_rivals = floor if math.isfinite(floor) else UNEXPLAINED
        lr = max(ll, UNEXPLAINED) - max(ll_rivals, UNEXPLAINED)
        cap, margin = self.config.max_view_nats, self.config.margin
        before = self.evidence
        self.evidence = max(-margin, before + views * min(cap, max(-cap, lr)))
        if self.evidence >= margin:
            self.active, self.passed, self._won, self.rivals, self._seen = False, True, True, None, None
            return None
        if self.evidence <= -margin < before:
            self.rival_wins += 1
            if self.config.adopt and self.rivals is not None:
                adopted = self._drawn(n, rng)
                self.reset()  # the rivals are the new belief; its convergence starts a challenge
                return Verdict("adopt", 0, adopted)
        verdict = self._refute(views, n, rng)
        self._refresh(near, draw, max(MIN_RIVALS, int(round(self.config.rival_fraction * n))), rng)
        return verdict

    def _refute(self, views: float, n: int, rng: np.random.Generator) -> Verdict | None:
        """Count the views in a row at -margin; at ``refute_views`` of them, rivals drawn by
        their weights join the belief (``refute_share`` of ``n``) and the count restarts."""
        self._pinned = self._pinned + views if self.evidence <= -self.config.margin else 0.0
        limit = self.config.refute_views
        if limit <= 0.0 or not self._refuting or self._pinned < limit or self.rivals is None:
            return None
        self._pinned = 0.0
        self.refutations += 1
        count = max(1, int(round(self.config.refute_share * n)))
        return Verdict("join", count, self._drawn(count, rng))

    def _drawn(self, m: int, rng: np.random.Generator) -> FloatArray:
        """``m`` rivals drawn by their weights (the resampler's draw); there must be rivals."""
        assert self.rivals is not None
        return self.rivals.particles[self.resample(self.rivals.weights, rng, m)]

    def _refresh(self, near: Callable[[FloatArray], NDArray[np.bool_]], draw: Callable[[int], FloatArray],
                 m: int, rng: np.random.Generator) -> None:
        """After the view has been scored: a share :data:`REFRESH` of the rivals (all of them
        when there are none) replaced by draws from this view's mixture away from the belief,
        at the rivals' lowest weight (the places the latest view looks like join the rivals,
        and must earn their weight; scored once past their probation)."""
        cs = self.rivals
        if cs is not None and self.config.refresh <= 0.0:
            return
        k = m if cs is None else max(1, int(math.ceil(self.config.refresh * m)))
        x = draw(DRAW_FACTOR * k)
        x = x[~near(x)][:k]
        if x.shape[0] == 0:
            return
        if cs is None or self._seen is None:  # a first draw: scored from the next view
            self.rivals = CandidateSet(x, Weights.uniform(x.shape[0]))
            self._seen = np.full(x.shape[0], self.config.probation_views)
            return
        slots = rng.choice(cs.particles.shape[0], size=min(x.shape[0], cs.particles.shape[0]), replace=False)
        particles = cs.particles.copy()
        particles[slots] = x[: slots.size]
        lw = cs.weights.log.copy()
        finite = np.isfinite(lw)  # rivals that drifted near the belief have no weight
        lw[slots] = float(lw[finite].min()) if finite.any() else -math.log(lw.size)
        self._seen[slots] = 0.0
        cs.particles, cs.weights = particles, Weights.from_log(lw, one_pass=False)

    def _step_rivals(
        self,
        delta: FloatArray,
        loglik: Callable[[FloatArray], FloatArray],
        near: Callable[[FloatArray], NDArray[np.bool_]],
        rng: np.random.Generator,
        views: float,
    ) -> float | None:
        """Propagate and weight the rivals (bootstrap filter); the predictive log-likelihood of
        those away from the belief and past their probation, None when there is none (the
        rivals are dropped when none is away). Rivals on probation keep their share of the
        weight (their likelihood factor is the scored rivals' mean)."""
        cs, seen = self.rivals, self._seen
        if cs is None or seen is None:
            return None
        x = self.motion.sample(cs.particles, delta, rng)
        lw = np.where(near(x), -np.inf, cs.weights.log)  # rivals that are still away
        away = np.isfinite(lw)
        scored = away & (seen >= self.config.probation_views)
        seen += views
        if not away.any():
            self.rivals = self._seen = None
            return None
        if not scored.any():  # every rival away from the belief is on probation
            cs.particles, cs.weights = x, Weights.from_log(lw, one_pass=False)
            return None
        lik = np.where(scored, loglik(x), -np.inf)
        try:
            ll = Weights.from_log(np.where(scored, lw, -np.inf), one_pass=False).log + lik
            ll = float(Weights.from_log(ll, one_pass=False).log_normalizer)
        except NoFiniteWeightError:  # no scored rival explains the view at all
            ll = UNEXPLAINED
        # rivals on probation keep their share: their likelihood factor is the scored ones' mean
        try:
            w = Weights.from_log(lw + np.where(scored, lik, ll), one_pass=False)
        except NoFiniteWeightError:  # no rival left that could explain anything
            self.rivals = self._seen = None
            return ll
        m = x.shape[0]
        if w.ess() < 0.5 * m:
            idx = self.resample(w, rng)
            x, w, self._seen = x[idx], Weights.uniform(m), seen[idx]
        cs.particles, cs.weights = x, w
        cs.age += 1
        return ll
