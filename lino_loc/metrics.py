"""Evaluation metrics: success (paper, section 6.1), sensor-model error (eq. 10), ATE.

* :func:`success` - the paper's criterion of section 6.1: an estimate is correct when the
  map (training) pose nearest to the estimate is the same as the map pose nearest to the
  truth. "Nearest" is measured in grid units so that position and heading are comparable:
  the distance between poses a and b is the Euclidean norm of
  ``((a_x - b_x) / position_step, (a_y - b_y) / position_step, wrap(a_t - b_t) / heading_step)``;
  on a regular survey grid this picks the grid cell the pose falls into. Ties (a pose exactly
  between two map poses) count as correct when both nearest sets share a map pose.
* :func:`sensor_model_error` - eq. 10, ``e = min_n |r - n|`` over the J map poses that define
  the sensor model, as the POSITION distance in metres (issue 3 / Fig. 5 report metres).
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


def nearest_map_index(
    poses: ArrayLike, map_poses: ArrayLike, position_step: float, heading_step: float
) -> NDArray[np.int64]:
    """Index of the map pose nearest (in grid units) to each pose (M, 3) -> (M,)."""
    a = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(map_poses, dtype=np.float64).reshape(-1, 3)
    return np.argmin(_grid_distances(a, m, position_step, heading_step), axis=1).astype(np.int64)


def success(
    estimates: ArrayLike,
    truths: ArrayLike,
    map_poses: ArrayLike,
    position_step: float,
    heading_step: float,
    tie_tol: float = 1e-9,
) -> NDArray[np.bool_]:
    """Section 6.1: True where the nearest map pose to the estimate is the nearest to the truth."""
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
