"""Has the appearance of the whole scene changed (lights switched), rather than the pose?

The filter's two self-checks learn what "normal" looks like: kidnap recovery compares the
likelihood of each view with its long-term average ``w_slow`` (``lino_loc.kidnap_recovery``),
the lost test with the hit rate it has learnt (``lino_loc.lost_detection``). Both were learnt
under the light of the moment. When the lights are switched every view fits the map worse at
once, and the misses would look like a kidnapping. What tells the two apart is how FAMILIAR
the views are (``PoseMixture.novelty``, the distance of the view to its nearest map entry over
the map's own typical spacing): a kidnapped robot in a mapped place sees views as familiar as
before, under another light every view is less familiar. This detector is a one-sided CUSUM
(Page 1954) on the log-novelty x_t = log n_t against its learnt level mu:

    S_t = max(0, S_t-1 + v_t (x_t - mu - log ratio))

where v_t in [0, 1] is how much of an independent view the frame is
(``lino_loc.lost_detection.independent_views``), so that the evidence does not depend on the
frame rate. The level mu is learnt only from views seen while no evidence stands (S_t-1 =
0: the in-control level, as in a textbook CUSUM; a level that kept learning during a change
would follow it), as the running mean of those views until they add up to 1 / alpha views,
then as an exponentially weighted one:

    n_t = n_t-1 + v_t,    mu += v_t max(alpha, 1 / n_t) (x_t - mu)

(the first observation sets mu = x_t, n = v_t). A level learnt at the rate alpha from the first
view alone would keep that view's place for about 1 / alpha views: a first view far less
familiar than its successors (novelty varies several-fold between places) left the detector
blind to a light switch for a minute of driving (docs/results.md, "The appearance-change
watch's start"). It reports a change when ``S_t > evidence`` and then restarts from the new
level (S = 0, mu = x_t, n = v_t). A drop in novelty (lights back to the mapping light) is not reported: the views fit
better, neither check is misled. Observations without a positive finite novelty are ignored.
``ratio`` is relative to the map's own spacing, so it transfers between maps; ``evidence`` is
in log-novelty x independent views, so it does not depend on the frame rate. How the defaults
were chosen: docs/results.md, "Lights switched while tracking" and "Notes moved from the code:
filter".

Per channel (``update`` given a mapping channel -> novelty, the view's channels as in
``PoseMixture.channels``). The channels answer a light change differently: an intensity
image changes with the light, the disparity of a stereo pair (its geometry) barely does
(``lino_loc.view_fit.LIGHT_INVARIANT``). The CUSUM above runs on the light-variant channels'
novelty (the largest of them, when there are several); each light-invariant channel c keeps
its own level mu_c (learnt as mu is, only while no evidence stands) and, while evidence stands (S > 0), the mean rise of its log-novelty over the
views since the evidence began (Page's change-point estimate),

    r_c = sum_t v_t (x_c,t - mu_c) / sum_t v_t.

When S passes ``evidence`` the change is classified:

- ``light``: every light-invariant channel stayed steady, r_c <= log :data:`STEADY_RATIO`
  (or there is none: a view of intensity alone). The lights switched; the filter's checks
  relearn (this is what :meth:`AppearanceChangeDetector.update` reports as True);
- ``scene``: a light-invariant channel rose too, r_c > log STEADY_RATIO: the place itself
  is unlike the map (an unmapped room, a rearranged one), not the light. Not reported as a
  change of the light (no relearning: the misses are the place's, and the lost test should
  hear them); counted in ``scene_changes``.

A kidnapping into a mapped place raises neither channel: nothing is reported. Either way the
detector restarts from the new level (S = 0, mu = x_t, mu_c = x_c,t, their means' views from
this one). A light-invariant
channel missing from a view (nan, or not in the mapping) adds nothing to r_c; with no view of
it during the evidence, the change is ``light``. A single novelty (a float) is the channel of
intensity alone, as before.

Usage::

    watch = AppearanceChangeDetector()
    if watch.update(mixture.novelty, views=independent_views(delta)):
        ...  # relearn what normal looks like
    watch.update({"intensity": n_i, "disparity": n_d}, views=v)   # per channel
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from lino_loc.view_fit import LIGHT_INVARIANT

# The detector's constants (docs/results.md, "Notes moved from the code: filter": chosen on the
# 240 s lab drive and the simulated office service):
RATIO = 1.65  # a rise of the views' novelty by more than this factor is evidence of a change
EVIDENCE = 5.0  # CUSUM evidence (log-novelty x independent views) for a change
ALPHA = 0.05  # learning rate of the in-control level, per view
#: a light-invariant channel whose log-novelty rose by more than log(STEADY_RATIO) on average
#: over a change's views says the place, not the light, changed: half the light-variant
#: channel's log(RATIO) (how the channels' novelty moves with the light: docs/results.md,
#: "Depth in the self-checks")
STEADY_RATIO = math.sqrt(RATIO)

Change = Literal["light", "scene"]


class AppearanceChangeConfig(BaseModel):
    """The appearance-change watch, ``filter.appearance_change``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="watch for changes of the scene's appearance (lights switched): "
        "kidnap recovery and the lost test then relearn what normal looks like instead of "
        "taking the worse views for a kidnapping",
    )
    per_channel: bool = Field(
        False, description="with a light-invariant channel (disparity) in the view, a rise of "
        "the intensity channel's novelty is a light change only while the disparity channel's "
        "stays steady; when both rise the place is unlike the map (no relearning)",
    )


@dataclass
class _SteadyChannel:
    """A light-invariant channel's level and its rise since the evidence began."""

    level: float = math.nan  # mu_c, log-novelty
    learnt: float = 0.0  # n_c: the in-control views mu_c was learnt from
    rise: float = 0.0  # sum v_t (x_c,t - mu_c) since the evidence began
    views: float = 0.0  # sum v_t over those views

    def observe(self, x: float, v: float, in_control: bool, alpha: float) -> None:
        if not math.isfinite(self.level):
            self.level, self.learnt = x, v
            return
        if in_control:
            self.rise = self.views = 0.0
            self.level, self.learnt = learn_level(self.level, self.learnt, x, v, alpha)
        else:
            self.rise += v * (x - self.level)
            self.views += v

    @property
    def mean_rise(self) -> float:
        return self.rise / self.views if self.views > 0.0 else 0.0


@dataclass
class AppearanceChangeDetector:
    """One-sided CUSUM on log-novelty, per channel (see the module docstring)."""

    ratio: float = RATIO  # a rise of the novelty by more than this factor counts as evidence
    evidence: float = EVIDENCE  # S_t above this (log-novelty x views): the appearance changed
    alpha: float = ALPHA  # learning rate of the level mu, per view
    steady_ratio: float = STEADY_RATIO  # a light-invariant channel's largest steady rise
    score: float = field(default=0.0, init=False)  # S_t
    level: float = field(default=math.nan, init=False)  # mu_t, log-novelty
    learnt: float = field(default=0.0, init=False)  # n_t: the in-control views mu was learnt from
    changes: int = field(default=0, init=False)  # light changes reported
    scene_changes: int = field(default=0, init=False)  # changes of the place itself
    last_change: Change | None = field(default=None, init=False)
    steady: dict[str, _SteadyChannel] = field(default_factory=dict, init=False)

    def update(self, novelty: float | Mapping[str, float], views: float = 1.0) -> bool:
        """One observation's novelty (a float: one channel; a mapping channel -> novelty: per
        channel; nan or non-positive: ignored) and how much of an independent view it is
        (0..1). True when the light changed (module docstring); the detector then restarts
        from this observation's level."""
        if isinstance(novelty, Mapping):
            variant = [n for c, n in novelty.items() if c not in LIGHT_INVARIANT and _valid(n)]
            invariant = {c: n for c, n in novelty.items() if c in LIGHT_INVARIANT and _valid(n)}
        else:
            variant, invariant = ([novelty] if _valid(novelty) else []), {}
        if not variant:
            return False
        x = math.log(max(variant))
        v = min(max(float(views), 0.0), 1.0)
        in_control = self.score == 0.0
        for name, n in invariant.items():
            self.steady.setdefault(name, _SteadyChannel()).observe(math.log(n), v, in_control, self.alpha)
        if not math.isfinite(self.level):
            self.level, self.learnt = x, v
            return False
        self.score = max(0.0, self.score + v * (x - self.level - math.log(self.ratio)))
        if in_control:
            self.level, self.learnt = learn_level(self.level, self.learnt, x, v, self.alpha)
        if self.score <= self.evidence:
            return False
        return self._classify(x, v, invariant)

    def _classify(self, x: float, v: float, invariant: Mapping[str, float]) -> bool:
        """The evidence passed: light or scene (module docstring); restart from this view."""
        rose = any(ch.mean_rise > math.log(self.steady_ratio) for ch in self.steady.values())
        self.last_change = "scene" if rose else "light"
        if rose:
            self.scene_changes += 1
        else:
            self.changes += 1
        self.score = 0.0
        self.level, self.learnt = x, v
        for name, ch in self.steady.items():
            ch.rise = ch.views = 0.0
            if name in invariant:
                ch.level, ch.learnt = math.log(invariant[name]), v
        return not rose


def learn_level(level: float, learnt: float, x: float, v: float, alpha: float) -> tuple[float, float]:
    """One in-control view x of weight v (independent views) taught to a level learnt from
    ``learnt`` views: the running mean until 1 / alpha views, then the exponentially weighted
    mean of rate alpha per view (module docstring). Returns (level, learnt)."""
    learnt += v
    if learnt <= 0.0:
        return level, learnt
    return level + v * max(alpha, 1.0 / learnt) * (x - level), learnt


def _valid(novelty: float) -> bool:
    return math.isfinite(novelty) and novelty > 0.0
