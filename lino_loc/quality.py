"""The estimate's quality: one number in [0, 1], higher meaning a smaller error.

    quality = support x mass x exp(-(s_xy / S)^2 / 2) x (1 - min(1, doubt))

- ``support``: the views' support of the belief (``lino_loc.view_fit.ViewFit.support``: 0
  when a channel able to confirm a pose stops fitting, 0.3 to 1 when such channels confirm
  it, more the more reliable they are and the better they fit, below 0.3 when no channel's
  views can confirm a pose);
- ``mass``: the dominant mode's share of the weight (``lino_loc.pose_estimate``);
- s_xy: the square root of the largest eigenvalue of the mode's position covariance, S the
  convergence limit ``filter.estimate.converged_std_xy`` (a mode at the limit keeps 61 %);
- ``doubt``: the lost test's evidence against the belief as a share of its threshold
  (``lino_loc.lost_detection``): a lost belief has quality 0.

Each factor is in [0, 1], so is the product; a non-finite input gives 0. It is calibrated by
measurement, not by construction: docs/results.md, "Honest states", tabulates the position
error by quality band over the tracking evaluation's runs.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from lino_loc.pose_estimate import EstimateConfig


def largest_std_xy(cov: NDArray[np.float64]) -> float:
    """sqrt of the largest eigenvalue of the 2 x 2 position block of a 3 x 3 covariance."""
    a, b, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    return math.sqrt(max(0.5 * (a + d) + math.hypot(0.5 * (a - d), b), 0.0))


def estimate_quality(
    state: str,
    cov: NDArray[np.float64],
    mass: float,
    doubt: float,
    support: float,
    config: EstimateConfig | None = None,
) -> float:
    """The quality of the module docstring; 0 for the ``lost`` state (the lost test's)."""
    if state == "lost":
        return 0.0
    limit = (config or EstimateConfig()).converged_std_xy
    s = largest_std_xy(np.asarray(cov, dtype=np.float64))
    q = (
        min(max(support, 0.0), 1.0)
        * min(max(mass, 0.0), 1.0)
        * math.exp(-0.5 * (s / limit) ** 2)
        * (1.0 - min(max(doubt, 0.0), 1.0))
    )
    return q if math.isfinite(q) else 0.0
