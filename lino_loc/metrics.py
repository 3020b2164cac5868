"""Evaluation metrics: success (paper, section 6.1), sensor-model error (eq. 10), ATE.

* :func:`success` - the paper's criterion of section 6.1, as written: "If we consider the
  estimation a to be correct if the closest training point to a is the same as the closest
  training point to the correct position c, then the success ratio in localization after 3
  camera movements is over 95%." In the same paragraph a and c are POSITIONS ("measuring the
  error ||c - a|| with c the correct position and a the position estimated by our system",
  Fig. 3 plots a position error), so "training point" is read as a map position (a surveyed
  (x, y); on the 75 cm grid, every grid point carries its 24 headings): the estimate is
  correct when the map position nearest to the estimated (x, y) is the one nearest to the
  true (x, y), Euclidean distance in metres, heading ignored. This is the headline figure.
* :func:`success_pose` - the stricter variant reported beside it (never instead of it): the
  map POSE nearest to the estimate must be the one nearest to the truth, "nearest" in grid
  units so that position and heading are comparable: the distance between poses a and b is
  the Euclidean norm of
  ``((a_x - b_x) / position_step, (a_y - b_y) / position_step, wrap(a_t - b_t) / heading_step)``;
  on a regular survey grid this picks the (x, y, theta) cell the pose falls into (75 cm x
  15 deg in section 6.1), i.e. the heading must also be right to half a heading step.
  In both, ties (a pose exactly between two map entries) count as correct when both nearest
  sets share an entry.
* :func:`sensor_model_error` - eq. 10, ``e = min_n |r - n|`` over the J map poses that define
  the sensor model, as the POSITION distance in metres (as the paper's Fig. 5 reports it).
* :func:`ate_rmse` - absolute trajectory error (RMSE of position errors, metres, in the map
  frame: no alignment since both trajectories live in the map frame), and
  :func:`heading_rmse` (radians, differences wrapped).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lino_loc.poses import pose_distance, wrap_angle

FloatArray = NDArray[np.float64]


def _grid_distances(
    a: FloatArray, map_poses: FloatArray, position_step: float, heading_step: float
) -> FloatArray:
    """(M, N) grid-unit distances between poses a (M, 3) and map poses (N, 3)."""
    dx = (a[:, None, 0] - map_poses[None, :, 0]) / position_step
    dy = (a[:, None, 1] - map_poses[None, :, 1]) / position_step
    dt = wrap_angle(a[:, None, 2] - map_poses[None, :, 2]) / heading_step
    return np.sqrt(dx * dx + dy * dy + dt * dt)


#: Largest (rows x map poses) block of grid distances :func:`nearest_map_index` holds at once
#: (float64 elements; a few temporaries of this size): 4M elements, 32 MB each, so that a
#: floor's map (117k poses) against thousands of particles does not need gigabytes.
NEAREST_BLOCK_ELEMENTS = 4_000_000


def nearest_map_index(
    poses: ArrayLike, map_poses: ArrayLike, position_step: float, heading_step: float
) -> NDArray[np.int64]:
    """Index of the map pose nearest (in grid units) to each pose (M, 3) -> (M,); the first
    such index on ties. Computed in blocks of rows (:data:`NEAREST_BLOCK_ELEMENTS`), the same
    result as all rows at once."""
    a = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(map_poses, dtype=np.float64).reshape(-1, 3)
    rows = max(1, NEAREST_BLOCK_ELEMENTS // max(m.shape[0], 1))
    out = np.empty(a.shape[0], dtype=np.int64)
    for i in range(0, a.shape[0], rows):
        out[i : i + rows] = np.argmin(_grid_distances(a[i : i + rows], m, position_step, heading_step), axis=1)
    return out


def map_positions(map_poses: ArrayLike, decimals: int = 6) -> FloatArray:
    """The distinct surveyed positions (K, 2) of map poses (N, 3) (rounded to ``decimals``)."""
    m = np.asarray(map_poses, dtype=np.float64).reshape(-1, 3)
    return np.unique(np.round(m[:, :2], decimals), axis=0)


def success(
    estimates: ArrayLike,
    truths: ArrayLike,
    map_poses: ArrayLike,
    tie_tol: float = 1e-9,
) -> NDArray[np.bool_]:
    """Section 6.1 (headline): True where the map POSITION nearest to the estimated (x, y) is
    the one nearest to the true (x, y) (Euclidean, metres; heading ignored), see the module
    docstring for the quote and the reading. ``map_poses`` (N, 3) or positions (K, 2)."""
    m = np.asarray(map_poses, dtype=np.float64)
    grid = map_positions(m) if m.shape[-1] == 3 else np.unique(m.reshape(-1, 2), axis=0)
    e = np.asarray(estimates, dtype=np.float64).reshape(-1, 3)[:, :2]
    t = np.asarray(truths, dtype=np.float64).reshape(-1, 3)[:, :2]
    de = np.hypot(e[:, None, 0] - grid[None, :, 0], e[:, None, 1] - grid[None, :, 1])
    dt = np.hypot(t[:, None, 0] - grid[None, :, 0], t[:, None, 1] - grid[None, :, 1])
    near_e = de <= de.min(axis=1, keepdims=True) + tie_tol
    near_t = dt <= dt.min(axis=1, keepdims=True) + tie_tol
    return np.any(near_e & near_t, axis=1)


def success_pose(
    estimates: ArrayLike,
    truths: ArrayLike,
    map_poses: ArrayLike,
    position_step: float,
    heading_step: float,
    tie_tol: float = 1e-9,
) -> NDArray[np.bool_]:
    """Stricter variant of section 6.1: True where the nearest map POSE (x, y, theta; grid
    units) to the estimate is the nearest to the truth (the same grid cell, heading included)."""
    e = np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(truths, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(map_poses, dtype=np.float64).reshape(-1, 3)
    de = _grid_distances(e, m, position_step, heading_step)
    dt = _grid_distances(t, m, position_step, heading_step)
    near_e = de <= de.min(axis=1, keepdims=True) + tie_tol
    near_t = dt <= dt.min(axis=1, keepdims=True) + tie_tol
    return np.any(near_e & near_t, axis=1)


def sensor_model_error(truth: ArrayLike, neighbour_poses: ArrayLike) -> float:
    """Eq. 10: min over the J map poses of the position distance to the true pose, metres."""
    n = np.asarray(neighbour_poses, dtype=np.float64).reshape(-1, 3)
    return float(np.min(pose_distance(np.asarray(truth, dtype=np.float64), n)))


def position_errors(estimates: ArrayLike, truths: ArrayLike) -> FloatArray:
    """Euclidean position error of each estimate, metres."""
    return pose_distance(
        np.asarray(estimates, dtype=np.float64), np.asarray(truths, dtype=np.float64)
    )


def heading_errors(estimates: ArrayLike, truths: ArrayLike) -> FloatArray:
    """Absolute wrapped heading error of each estimate, radians."""
    e = np.asarray(estimates, dtype=np.float64)
    t = np.asarray(truths, dtype=np.float64)
    return np.abs(wrap_angle(e[..., 2] - t[..., 2]))


def ate_rmse(estimates: ArrayLike, truths: ArrayLike) -> float:
    """Absolute trajectory error: RMSE of the position errors, metres."""
    err = position_errors(estimates, truths)
    return float(np.sqrt(np.mean(err**2)))


def heading_rmse(estimates: ArrayLike, truths: ArrayLike) -> float:
    """RMSE of the wrapped heading errors, radians."""
    err = heading_errors(estimates, truths)
    return float(np.sqrt(np.mean(err**2)))
