"""What the map can tell at the active-localization test positions, without the filter.

References for the success figures of :mod:`services.evaluation.active` (section 6.1):

* :func:`feature_diagnostics`: how often one test view's nearest map entries (feature space)
  are at the truth's map cell;
* :func:`ideal_success`: the sensor model's own bound, its exact posterior (eq. 4 products over
  the images) on a dense pose grid instead of 150 particles;
* :func:`map_oracle_success`: a model-free reference, the map position whose stored views best
  match the test views taken so far (nearest neighbour over the views jointly, the robot's
  heading searched), i.e. how many views the map needs before "which map position is this?"
  has the right answer.

All three see the same rendered test views as the filter.
"""

from __future__ import annotations

import math

import numpy as np

from lino_loc.metrics import nearest_map_index, success, success_pose
from lino_loc.poses import wrap_angle
from lino_loc.sensor_model import NearestNeighbourSensorModel
from lino_loc.view_match import views_by_position
from services.evaluation.active_setup import ActiveSetup


def feature_diagnostics(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
                        truths: np.ndarray,
                        pans: np.ndarray, feats: np.ndarray) -> dict[str, float]:
    """How well single test views match the map: over all test views, the fraction whose
    truth map cell (nearest grid pose to the camera pose, grid units) is the nearest map entry in
    feature space, and is among the J nearest; the fraction of the J neighbours within one
    grid step (position and heading) of the camera pose; the mean number of distinct grid
    positions the J neighbours' cells fall on (how many places one view's mixture spreads over)."""
    model = NearestNeighbourSensorModel(entries, map_features, setup.sensor)
    cams = np.repeat(truths[:, None, :], pans.size, axis=1)
    cams[:, :, 2] = wrap_angle(cams[:, :, 2] + pans[None, :])
    cams = cams.reshape(-1, 3)
    cell = nearest_map_index(cams, grid, setup.judged_step, math.radians(setup.heading_step_deg))
    idx, _ = model.neighbours(feats.reshape(cams.shape[0], -1))
    # the grid cells of the neighbours only (all the entries' against the grid: N x N distances)
    idx_cell = nearest_map_index(entries[idx.ravel()], grid, setup.judged_step,
                                 math.radians(setup.heading_step_deg)).reshape(idx.shape)
    position_of = np.unique(np.round(grid[:, :2], 6), axis=0, return_inverse=True)[1].reshape(-1)
    near = (np.hypot(entries[idx, 0] - cams[:, None, 0], entries[idx, 1] - cams[:, None, 1]) <= setup.judged_step * 1.05) & (
        np.abs(wrap_angle(entries[idx, 2] - cams[:, None, 2])) <= math.radians(setup.heading_step_deg) * 1.05)
    return {
        "truth_cell_is_nearest_in_features": float(np.mean(idx_cell[:, 0] == cell)),
        "truth_cell_among_j_nearest": float(np.mean(np.any(idx_cell == cell[:, None], axis=1))),
        "j_neighbours_distinct_positions": float(np.mean(1 + np.sum(np.diff(np.sort(position_of[idx_cell], axis=1),
                                                                            axis=1) != 0, axis=1))),
        "j_neighbours_within_one_grid_step": float(near.mean()),
    }


def ideal_success(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
                  truths: np.ndarray,
                  pans: np.ndarray, feats: np.ndarray, images: tuple[int, ...] = (1, 2, 4, 11)) -> dict[str, float]:
    """Upper bound of the sensor model, without particles: success ratio over the test
    positions of :func:`ideal_hits` (keys ``"k"``, position criterion, and ``"k_pose"``)."""
    return {key: float(np.mean(v)) for key, v in ideal_hits(setup, grid, entries, map_features, truths, pans, feats,
                                                             images).items()}


def ideal_hits(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
               truths: np.ndarray, pans: np.ndarray, feats: np.ndarray,
               images: tuple[int, ...] = (1, 2, 4, 11)) -> dict[str, np.ndarray]:
    """The sensor model's bound per test position: the posterior of the first k images (first
    pan of run 0, then the sweep) on a dense pose grid (10 cm, 5 deg over the mapped area +
    30 cm), its maximum as the estimate; success (P,) per test position under key ``"k"``
    (:func:`lino_loc.metrics.success`) and ``"k_pose"`` (:func:`lino_loc.metrics.success_pose`);
    k beyond the number of pans left out. The sensor model is the one ``setup.sensor_model`` names."""
    model = setup.sensor_model_for(entries, map_features)
    xmin, xmax = grid[:, 0].min() - 0.3, grid[:, 0].max() + 0.3
    ymin, ymax = grid[:, 1].min() - 0.3, grid[:, 1].max() + 0.3
    gx, gy, gh = np.meshgrid(np.arange(xmin, xmax + 1e-9, 0.1), np.arange(ymin, ymax + 1e-9, 0.1),
                             np.radians(np.arange(-180.0, 180.0, 5.0)), indexing="ij")
    dense = np.column_stack([gx.ravel(), gy.ravel(), gh.ravel()])
    hstep = math.radians(setup.heading_step_deg)
    images = tuple(k for k in images if k <= pans.size)
    out: dict[str, np.ndarray] = {}
    hits: dict[int, list[bool]] = {k: [] for k in images}
    hits_pose: dict[int, list[bool]] = {k: [] for k in images}
    for pos in range(truths.shape[0]):
        lp = np.zeros(dense.shape[0])
        for k, a in enumerate(sweep_order(setup, pos, 0, pans.size)[: max(images)]):
            cam = dense.copy()
            cam[:, 2] += pans[a]
            lp += model.observe(feats[pos, a]).log_pdf(cam)
            if k + 1 in hits:
                best = dense[int(np.argmax(lp))]
                hits[k + 1].append(bool(success(best, truths[pos], grid)[0]))
                hits_pose[k + 1].append(bool(success_pose(best, truths[pos], grid, setup.judged_step, hstep)[0]))
    for k, v in hits.items():
        out[str(k)] = np.asarray(v)
        out[f"{k}_pose"] = np.asarray(hits_pose[k])
    return out


def sweep_order(setup: ActiveSetup, pos: int, run: int, n_actions: int) -> list[int]:
    """The pans of the fixed sweep from run ``run``'s first pan at test position ``pos`` (the
    first pan is drawn as :func:`services.evaluation.active.run_position` draws it)."""
    a0 = int(np.random.default_rng((setup.seed, pos, run, 1)).integers(n_actions))
    return [(a0 + setup.sweep_stride * k) % n_actions for k in range(n_actions)]


def map_oracle_success(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
                       truths: np.ndarray, pans: np.ndarray, feats: np.ndarray,
                       images: tuple[int, ...] = (1, 2, 4, 6, 11, 22)) -> dict[str, float]:
    """Success ratio of :func:`map_oracle_hits` over the test positions and runs (key ``"k"``)."""
    return {key: float(np.mean(v)) for key, v in map_oracle_hits(setup, grid, entries, map_features, truths, pans,
                                                                 feats, images).items()}


def map_oracle_hits(setup: ActiveSetup, grid: np.ndarray, entries: np.ndarray, map_features: np.ndarray,
                    truths: np.ndarray, pans: np.ndarray, feats: np.ndarray,
                    images: tuple[int, ...] = (1, 2, 4, 6, 11, 22)) -> dict[str, np.ndarray]:
    """Success (P, runs) of the map-grid nearest neighbour over the first k views of the sweep
    (key ``"k"``; k beyond the number of pans left out).

    For test position p and the views y_1..y_k taken at pans u_1..u_k, every map position g
    and robot heading o (on the map's heading lattice) is scored by
    ``sum_i |y_i - y(g, o + u_i)|^2`` with y(g, theta) the map's stored features; the best g
    is the decision and it succeeds when it is the map position nearest to the truth
    (:func:`lino_loc.metrics.success`, section 6.1, against ``grid``, the survey poses). It uses nothing but the map and knows which pans
    were taken, so it says how many views the map needs to tell the test positions' cells
    apart; one column per run's first pan (sweep order, stride ``sweep_stride``).
    """
    xy, table, step = views_by_position(entries, map_features)
    n_head = table.shape[1]
    shift = np.round(np.asarray(pans) / step).astype(np.int64)
    images = tuple(k for k in images if k <= pans.size)
    hits: dict[int, list[bool]] = {k: [] for k in images}
    for pos in range(truths.shape[0]):
        for run in range(setup.runs):
            cost = np.zeros(table.shape[:2])
            for k, a in enumerate(sweep_order(setup, pos, run, pans.size)[: max(images)]):
                cols = (np.arange(n_head) + shift[a]) % n_head
                cost += np.sum((table[:, cols, :] - feats[pos, a]) ** 2, axis=2)
                if k + 1 in hits:
                    g = np.unravel_index(np.nanargmin(np.where(np.isnan(cost), np.inf, cost)), cost.shape)[0]
                    named = np.array([xy[g, 0], xy[g, 1], 0.0])
                    hits[k + 1].append(bool(success(named, truths[pos], grid)[0]))
    return {str(k): np.asarray(v).reshape(truths.shape[0], setup.runs) for k, v in hits.items()}
