"""Has the appearance of the whole scene changed (lights switched), rather than the pose?

The filter's two self-checks learn what "normal" looks like: kidnap recovery compares the
likelihood of each view with its long-term average ``w_slow`` (``lino_loc.kidnap_recovery``),
the lost test with the hit rate it has learnt (``lino_loc.lost_detection``). Both were learnt
under the light of the moment. When the lights are switched (tube -> bulb in the lab), every
view fits the map worse at once: the likelihood drops far below ``w_slow`` (which needs ~1000
updates to follow, ``alpha_slow``) and the misses look like a kidnapping, so recovery draws
candidate sets from a sensor model that is now wrong, and an aliased place wins (measured:
mean error after the switch 4.3 m, against 0.31 m for the same drive under bulb light from the
start; docs/results.md).

What tells the two apart is how FAMILIAR the views are (``PoseMixture.novelty``, the distance of
the view to its nearest map entry over the map's own typical spacing): a kidnapped robot in a
mapped place sees views as familiar as before, under another light every view is less familiar
(median novelty in the lab 1.27 under the mapping light, 2.62 under bulb). This detector is a
one-sided CUSUM (Page 1954) on the log-novelty against its slowly learnt level:

    S_t = max(0, S_t-1 + v_t (log n_t - mu - log ratio))

where v_t is how much of an independent view the frame is (``lino_loc.lost_detection.
independent_views``: the odometry increment over the sensor model's kernel widths; the lost
test counts the same way), so that the evidence does not depend on the frame rate: at 15 fps
consecutive frames see nearly the same image, and counting frames raised two false alarms a
minute in the simulated service under constant light. The level mu is learnt (exponential
average, rate ``alpha`` per view) only from views seen while no evidence stands (S_t-1 = 0:
the in-control level, as in a textbook CUSUM; a level that kept learning during a change would
follow it and never let the evidence build up). It reports a change when ``S_t > evidence``
and then restarts from the new level. Chosen on the 240 s lab drive at 5 Hz (3.9 frames per
view; per-frame log-novelty spread 0.33-0.38) and the simulated service in the office (15 fps,
wandering, active vision on): ``ratio`` 1.65 (log 0.5) and ``evidence`` 5 found the lab's tube
-> bulb switch 9 s after it (tube -> natural: 5.6 s) and raised nothing over the lab drive
under tube, bulb or natural light alone, nor in 2.5 min of the office service; ``evidence`` 2
(3 s) raised four alarms under natural light (daylight changes the views by place) and one a
minute in the office service. A clean doubling of the novelty takes 32 views.
A drop in novelty (lights back to the mapping light) is not a change it reports: the views fit
better, neither check is misled. Chosen in simulation only; ``ratio`` is relative to the map's
own spacing, so it transfers between maps, the evidence is a number of independent views'
worth, so it does not depend on the frame rate.

Usage::

    watch = AppearanceChangeDetector()
    if watch.update(mixture.novelty, views=independent_views(delta, 0.35, 0.3)):
        ...  # relearn what normal looks like
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class AppearanceChangeDetector:
    """One-sided CUSUM on log-novelty (see the module docstring)."""

    ratio: float = 1.65  # a rise of the novelty by more than this factor counts as evidence
    evidence: float = 5.0  # S_t above this (log-novelty x views): the appearance changed
    alpha: float = 0.05  # learning rate of the level mu, per view
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
