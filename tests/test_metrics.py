"""Evaluation metrics: section 6.1 success, eq. 10 sensor-model error, ATE and heading RMSE."""

from __future__ import annotations

import numpy as np
import pytest

from lino_loc.metrics import (
    ate_rmse,
    heading_errors,
    heading_rmse,
    nearest_map_index,
    position_errors,
    sensor_model_error,
    success,
    success_pose,
)

STEP, HSTEP = 0.75, np.radians(15)


def _grid():
    xs, ys = np.arange(0, 3.01, STEP), np.arange(0, 1.51, STEP)
    ts = -np.pi + np.arange(24) * HSTEP
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), T.ravel()])


def test_success_pose_same_cell() -> None:
    m = _grid()
    truth = np.array([[1.6, 0.7, 0.3]])
    same = np.array([[1.4, 0.8, 0.2]])  # nearest map pose (1.5, 0.75, 15 deg) for both
    other_pos = np.array([[2.0, 0.7, 0.3]])  # nearest x is 2.25
    other_head = np.array([[1.6, 0.7, 0.45]])  # nearest heading 30 deg
    assert success_pose(same, truth, m, STEP, HSTEP)[0]
    assert not success_pose(other_pos, truth, m, STEP, HSTEP)[0]
    assert not success_pose(other_head, truth, m, STEP, HSTEP)[0]
    assert success_pose(truth, truth, m, STEP, HSTEP)[0]
    res = success_pose(np.vstack([same, other_pos]), np.vstack([truth, truth]), m, STEP, HSTEP)
    assert res.tolist() == [True, False]


def test_success_is_by_nearest_map_position() -> None:
    """The paper's words: the closest training POINT (position) to a and to c; heading ignored."""
    m = _grid()
    truth = np.array([[1.6, 0.7, 0.3]])
    other_head = np.array([[1.6, 0.7, 0.3 + np.pi]])  # same position, opposite heading
    near_pos = np.array([[1.85, 0.45, -2.0]])  # nearest position still (1.5, 0.75)
    other_pos = np.array([[1.9, 0.7, 0.3]])  # nearest x is 2.25: 0.35 m < 0.4 m away
    res = success(np.vstack([other_head, near_pos, other_pos, truth]), np.repeat(truth, 4, axis=0), m)
    assert res.tolist() == [True, True, False, True]
    assert not success_pose(other_head, truth, m, STEP, HSTEP)[0]  # the strict variant differs
    # map positions given directly (K, 2) give the same answer
    xy = np.unique(m[:, :2], axis=0)
    assert success(np.vstack([other_head, near_pos, other_pos]), np.repeat(truth, 3, axis=0), xy).tolist() == [
        True, True, False]
    # tie: exactly between two map positions counts when the truth's nearest is one of them
    mid = np.array([[1.875, 0.75, 0.0]])
    assert success(mid, np.array([[2.1, 0.8, 0.0]]), m)[0]
    assert success(mid, truth, m)[0]
    # pose success implies position success (random poses)
    rng = np.random.default_rng(0)
    e = np.column_stack([rng.uniform(0, 3, 500), rng.uniform(0, 1.5, 500), rng.uniform(-np.pi, np.pi, 500)])
    t = e + rng.normal(0, [0.3, 0.3, 0.3], (500, 3))
    sp, ss = success_pose(e, t, m, STEP, HSTEP), success(e, t, m)
    assert np.all(ss[sp]) and ss.sum() > sp.sum()


def test_success_across_the_angle_cut() -> None:
    m = _grid()
    truth = np.array([[1.5, 0.75, np.pi - 0.02]])
    est = np.array([[1.5, 0.75, -np.pi + 0.02]])  # both nearest to heading -pi (== pi)
    assert success_pose(est, truth, m, STEP, HSTEP)[0]
    assert success(est, truth, m)[0]
    idx = nearest_map_index(np.vstack([truth, est]), m, STEP, HSTEP)
    assert idx[0] == idx[1]


def test_nearest_map_index_in_blocks_equals_all_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    import lino_loc.metrics as metrics

    m = _grid()
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(-0.5, 3.5, 101), rng.uniform(-0.5, 2.0, 101), rng.uniform(-4, 4, 101)])
    whole = np.argmin(metrics._grid_distances(p, m, STEP, HSTEP), axis=1)
    for budget in (1, len(m) * 7, 10**9):  # one row per block, 7 rows (the last block short), all
        monkeypatch.setattr(metrics, "NEAREST_BLOCK_ELEMENTS", budget)
        np.testing.assert_array_equal(nearest_map_index(p, m, STEP, HSTEP), whole)
    assert nearest_map_index(np.zeros((0, 3)), m, STEP, HSTEP).shape == (0,)


def test_sensor_model_error_is_min_position_distance() -> None:
    truth = np.array([1.0, 1.0, 0.0])
    nb = np.array([[1.3, 1.4, 3.0], [0.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    assert sensor_model_error(truth, nb) == pytest.approx(0.5)  # heading ignored


def test_ate_and_heading_rmse() -> None:
    est = np.array([[0.0, 0.0, np.pi - 0.1], [1.0, 1.0, 0.0]])
    tru = np.array([[3.0, 4.0, -np.pi + 0.1], [1.0, 1.0, 0.3]])
    np.testing.assert_allclose(position_errors(est, tru), [5.0, 0.0])
    assert ate_rmse(est, tru) == pytest.approx(np.sqrt(12.5))
    np.testing.assert_allclose(heading_errors(est, tru), [0.2, 0.3], atol=1e-12)
    assert heading_rmse(est, tru) == pytest.approx(np.sqrt((0.04 + 0.09) / 2))
