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
frame rate. The level mu starts at the first observation's x and is learnt (mu += alpha v_t
(x_t - mu)) only from views seen while no evidence stands (S_t-1 = 0: the in-control level,
as in a textbook CUSUM; a level that kept learning during a change would follow it). It
reports a change when ``S_t > evidence`` and then restarts from the new level (S = 0, mu =
x_t). A drop in novelty (lights back to the mapping light) is not reported: the views fit
better, neither check is misled. Observations without a positive finite novelty are ignored.
``ratio`` is relative to the map's own spacing, so it transfers between maps; ``evidence`` is
in log-novelty x independent views, so it does not depend on the frame rate. How the defaults
were chosen: docs/results.md, "Lights switched while tracking" and "Notes moved from the code:
filter".

Usage::

    watch = AppearanceChangeDetector()
    if watch.update(mixture.novelty, views=independent_views(delta)):
        ...  # relearn what normal looks like
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field

# The detector's constants (docs/results.md, "Notes moved from the code: filter": chosen on the
# 240 s lab drive and the simulated office service):
RATIO = 1.65  # a rise of the views' novelty by more than this factor is evidence of a change
EVIDENCE = 5.0  # CUSUM evidence (log-novelty x independent views) for a change
ALPHA = 0.05  # learning rate of the in-control level, per view


class AppearanceChangeConfig(BaseModel):
    """The appearance-change watch, ``filter.appearance_change``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="watch for changes of the scene's appearance (lights switched): "
        "kidnap recovery and the lost test then relearn what normal looks like instead of "
        "taking the worse views for a kidnapping",
    )


@dataclass
class AppearanceChangeDetector:
    """One-sided CUSUM on log-novelty (see the module docstring)."""

    ratio: float = RATIO  # a rise of the novelty by more than this factor counts as evidence
    evidence: float = EVIDENCE  # S_t above this (log-novelty x views): the appearance changed
    alpha: float = ALPHA  # learning rate of the level mu, per view
    score: float = field(default=0.0, init=False)  # S_t
    level: float = field(default=math.nan, init=False)  # mu_t, log-novelty
    changes: int = field(default=0, init=False)

    def update(self, novelty: float, views: float = 1.0) -> bool:
        """One observation's novelty (nan or non-positive: ignored) and how much of an
        independent view it is (0..1). True when the scene's appearance has changed; the
        detector then restarts from this observation's level."""
        if not (math.isfinite(novelty) and novelty > 0.0):
            return False
        x = math.log(novelty)
        if not math.isfinite(self.level):
            self.level = x
            return False
        v = min(max(float(views), 0.0), 1.0)
        in_control = self.score == 0.0
        self.score = max(0.0, self.score + v * (x - self.level - math.log(self.ratio)))
        if in_control:
            self.level += self.alpha * v * (x - self.level)
        if self.score > self.evidence:
            self.changes += 1
            self.score = 0.0
            self.level = x
            return True
        return False
