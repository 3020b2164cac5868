"""Other final decisions on the same filter runs, for a robot standing still.

The active-localization experiment (:mod:`services.evaluation.active`) judges the filter's
estimate, the weighted mean of its dominant mode (:mod:`lino_loc.pose_estimate`). With the
robot standing still, every view taken since the start was taken at the same pose, so the
views can also decide jointly. Two such decisions, each searched only near the filter's
estimate (the filter chooses the neighbourhood, the views the place in it):

* ``posterior_peak``: the maximum of the views' joint sensor-model likelihood
  ``sum_i log p(y_i | x, u_i)`` (eq. 4 products, the uniform prior) on a local pose lattice
  around the estimate (:data:`PEAK_RADIUS`, :data:`PEAK_STEP`, headings within
  :data:`PEAK_HEADING_SPAN` every :data:`PEAK_HEADING_STEP`);
* ``map_match``: the map position within :data:`MATCH_RADIUS` of the estimate, and the
  heading, whose stored views best match the views taken, ``sum_i |y_i - y(g, o + u_i)|^2``
  (the map oracle's rule of :func:`services.evaluation.active_bounds.map_oracle_hits`, there
  over the whole map and the sweep's views, here near the filter's estimate and over the views
  the strategy chose). It needs a product-grid map (positions x headings); the intensity
  channel's features.

Neither changes the filter; `eval active --decisions` reports their success beside the
estimate's.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lino_loc.view_match import ViewLattice, ViewMatchConfig

DECISIONS: tuple[str, ...] = ("posterior_peak", "map_match")
PEAK_RADIUS = 0.45  # m
PEAK_STEP = 0.025  # m
PEAK_HEADING_SPAN = math.radians(20.0)
PEAK_HEADING_STEP = math.radians(2.5)
MATCH_RADIUS = 0.5  # m


class MapTable(ViewLattice):
    """The map's intensity features as a table of positions x headings, matched at every
    heading within :data:`MATCH_RADIUS` (:class:`lino_loc.view_match.ViewLattice`, the
    standing match's lattice)."""

    def __init__(self, entries: np.ndarray, features: np.ndarray) -> None:
        super().__init__(entries, features, ViewMatchConfig(radius=MATCH_RADIUS, heading_span=math.pi))


def posterior_peak(estimate: np.ndarray, views: list[tuple[float, Any, np.ndarray]]) -> np.ndarray:
    """The ``posterior_peak`` decision (module docstring): ``views`` are (pan, sensor-model
    mixture, intensity features) of every view taken so far."""
    g = np.arange(-PEAK_RADIUS, PEAK_RADIUS + 1e-9, PEAK_STEP)
    h = np.arange(-PEAK_HEADING_SPAN, PEAK_HEADING_SPAN + 1e-9, PEAK_HEADING_STEP)
    gx, gy, gh = np.meshgrid(estimate[0] + g, estimate[1] + g, estimate[2] + h, indexing="ij")
    poses = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    log_lik = np.zeros(poses.shape[0])
    for pan, mixture, _ in views:
        camera = poses.copy()
        camera[:, 2] += pan
        log_lik += mixture.log_pdf(camera)
    return poses[int(np.argmax(log_lik))]


def map_match(estimate: np.ndarray, views: list[tuple[float, Any, np.ndarray]], table: MapTable) -> np.ndarray:
    """The ``map_match`` decision (module docstring, :meth:`lino_loc.view_match.ViewLattice.match`);
    the estimate itself when no map position within :data:`MATCH_RADIUS` has every view."""
    if not views:
        return np.asarray(estimate, dtype=np.float64)
    pose = table.match(np.asarray(estimate, dtype=np.float64), np.array([v[0] for v in views]),
                       np.stack([v[2] for v in views]))
    return np.asarray(estimate, dtype=np.float64) if pose is None else pose


def decide(rule: str, estimate: np.ndarray, views: list[tuple[float, Any, np.ndarray]],
           table: MapTable | None) -> np.ndarray:
    """The decision of ``rule`` (one of :data:`DECISIONS`)."""
    if rule == "posterior_peak":
        return posterior_peak(estimate, views)
    if rule == "map_match" and table is not None:
        return map_match(estimate, views, table)
    raise ValueError(f"unknown decision rule {rule!r} (known: {', '.join(DECISIONS)})")
