"""When is the pose filter lost? A sequential test of the belief against the views.

Each observation either is explained by the belief (a HIT: the APF's predictive likelihood of
the view, ``log p(y_t | y_1..t-1)``, exceeds the sensor model's outlier floor by ``hit_nats``)
or not (a MISS). A correct belief hits at a rate rho that depends on how well the views match
the map: 96 % of the frames under the mapping light in the lab, 30 % under ``bulb``, 28 % under
``natural`` (measured on the 240 s lab drive with scene changes); a wrong belief (the same
particles displaced by 2-3 m or turned by 90 deg) hits at the chance rate rho_0, 4-5 % in every
light. "Lost" is the decision between those two hypotheses by Page's CUSUM (a sequential
probability ratio test with restart, Page 1954; Basseville and Nikiforov 1993, ch. 2):

    S_t = max(0, S_t-1 + v_t * llr_t),  llr_t = log(rho_0 / rho)           for a hit,
                                               log((1 - rho_0) / (1 - rho)) for a miss,

lost while ``S_t > threshold`` (nats). Two things make it calibrated rather than a fixed ratio:

- rho is LEARNT: the hit rate of the recent views while the belief is trusted (state
  ``tracking`` or ``lost``, not during a search; exponential forgetting, ``memory`` per view, Jeffreys' Beta(1/2, 1/2) prior;
  while evidence stands, S > 0, only slowly: ``memory_suspect``). It is kept when the belief
  changes (re-convergence, kidnap recovery): it describes the place and the light. Evidence
  counts once ``warmup_views`` views have taught it. Where the views are unreliable (changed light) misses carry little
  evidence (0.3 nats under natural light), where they are reliable a miss is strong evidence
  (3 nats under the mapping light). When rho <= rho_0 a view says nothing.
- Views, not frames, are counted: consecutive frames at 5 Hz see almost the same image, and
  their hits and misses come in runs (under natural light a correct belief went 141 frames,
  28 s, without a hit). Each frame counts as v_t = min(1, |dxy| / view_xy + |dtheta| /
  view_theta) of an independent view (the odometry increment over the sensor model's kernel
  widths, 0.35 m and 0.3 rad: poses closer than that are not told apart by the model).

The w_fast < lost_ratio * w_slow rule it replaces (AMCL's averages) was raised in 25 % / 69 %
of the frames under bulb / natural light while the error stayed near 0.3 m: a linear-space
average is dominated by the hits, so every run of misses looked like a collapse.

Measured (240 s lab drive with scene changes, 1000 particles, kidnap recovery on; a
kidnapping = the belief displaced by 2.5 m, by (-2, 1.5) m and 57 deg, or turned by 143 deg
at frame 300), ``threshold`` 12:

| light | lost, known start | lost, uniform start | after a kidnapping |
|---|---|---|---|
| tube (mapped) | 0 % | 0 % | lost after 23 frames (4.6 s); 21-73 % of the frames with error > 1 m (recovery: 29-59 frames) |
| bulb | 0 % | 0 % | not detected |
| natural | 4 % | 8 % | not detected |

The w_fast / w_slow rule gave 1 / 25 / 69 % from a known start. Threshold 10: natural 6 % /
19 %, a kidnapping under tube light lost after 18 frames; threshold 15: 0 % / 6 %, 31 frames.
Its limit: under changed light the views say too little (or, aliased, the wrong thing) to tell
a wrong belief from a correct one within a drive. When the views become less familiar all at
once (lights switched), ``lino_loc.appearance_change`` makes it forget the learnt rho
(:meth:`LostDetector.appearance_changed`); on the lab drive under one light that never happens,
so the figures above stand.

A converged belief is reported ``tracking`` only once the views have confirmed it
(:attr:`LostDetector.confirmed`, ``confirm_views`` views' worth of hits); until then it is
still ``global``.

Usage::

    det = LostDetector(threshold=12.0)
    lost = det.update(log_likelihood - outlier_floor, delta)   # per observation
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike


def independent_views(delta: ArrayLike, view_xy: float, view_theta: float) -> float:
    """How much of an independent view one frame is: min(1, |dxy| / view_xy + |dtheta| /
    view_theta) for the odometry increment (dx, dy, dtheta) since the previous frame (poses
    closer than the sensor model's kernel widths are not told apart by it)."""
    d = np.asarray(delta, dtype=np.float64).reshape(3)
    return min(1.0, math.hypot(float(d[0]), float(d[1])) / view_xy + abs(float(d[2])) / view_theta)


@dataclass
class LostDetector:
    """Page's CUSUM on hits and misses of the belief (see the module docstring)."""

    threshold: float = 12.0  # nats of evidence for "lost"
    chance_hit_rate: float = 0.05  # rho_0: hit rate of a wrong belief
    hit_nats: float = 1.0  # a hit: predictive log-likelihood this far above the outlier floor
    memory: float = 0.97  # forgetting factor of the learnt hit rate, per view
    memory_suspect: float = 0.995  # ... per view while evidence of being lost stands
    view_xy: float = 0.35  # m of travel that make one independent view
    view_theta: float = 0.3  # rad of turn that make one independent view
    warmup_views: float = 5.0  # views learnt after a full reset before evidence counts
    confirm_views: float = 1.0  # views' worth of hits that confirm a new belief
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
        (it described the old light; ``warmup_views`` views teach the new one before evidence
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
        since :meth:`new_belief` (a belief concentrated by one ambiguous image explains none of
        the next views when it is wrong: 7-26 s of such frames from a uniform start in the lab
        were labelled ``tracking`` before)."""
        return self._trusted or self._belief_hits >= self.confirm_views

    @property
    def hit_rate(self) -> float:
        """rho: the learnt hit rate of a correct belief (Beta(1/2, 1/2) prior, Jeffreys)."""
        return (self._hits + 0.5) / (self._views + 1.0)

    @property
    def lost(self) -> bool:
        return self.score > self.threshold

    @property
    def doubt(self) -> float:
        """Evidence against the belief as a fraction of the threshold: 0 = the views agree,
        1 = lost. Active vision looks once it passes ``trigger_doubt`` (the observations fit
        the map badly), before the belief is declared lost."""
        return self.score / self.threshold

    def update(self, excess: float, delta: ArrayLike, learn: bool = True) -> bool:
        """One observation: ``excess`` = predictive log-likelihood minus the outlier floor
        (nats; -inf or nan: a miss), ``delta`` the odometry increment (dx, dy, dtheta) since
        the last one; ``learn``: the belief is trusted (tracking), so its hits and misses
        teach rho. Returns whether the belief is lost."""
        v = independent_views(delta, self.view_xy, self.view_theta)
        if v <= 0.0:
            return self.lost
        hit = bool(excess > self.hit_nats)  # nan: a miss
        self._belief_hits += v if hit else 0.0
        rho = min(max(self.hit_rate, 1e-3), 1.0 - 1e-3)
        p0 = self.chance_hit_rate
        llr = min(0.0, math.log(p0 / rho)) if hit else max(0.0, math.log((1.0 - p0) / (1.0 - rho)))
        if self._learnt >= self.warmup_views:  # until then the views only teach rho
            score = self.score
            self.score = max(0.0, self.score + v * llr)
        else:
            score = 0.0
        if learn:
            # the hit rate of a correct belief is learnt from unsuspected views; while evidence
            # stands (S > 0 before this view) it adapts only slowly (memory_suspect), so that a
            # run of misses does not teach the test to expect misses, and a lasting change of
            # the views (another light) still lowers rho in the end instead of holding "lost"
            forget = (self.memory if score == 0.0 else self.memory_suspect) ** v
            self._hits = forget * self._hits + (v if hit else 0.0)
            self._views = forget * self._views + v
            self._learnt += v
        return self.lost
