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
)

STEP, HSTEP = 0.75, np.radians(15)


def _grid():
    xs, ys = np.arange(0, 3.01, STEP), np.arange(0, 1.51, STEP)
    ts = -np.pi + np.arange(24) * HSTEP
    X, Y, T = np.meshgrid(xs, ys, ts, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), T.ravel()])


def test_success_same_cell() -> None:
    m = _grid()
    truth = np.array([[1.6, 0.7, 0.3]])
    same = np.array([[1.4, 0.8, 0.2]])  # nearest map pose (1.5, 0.75, 15 deg) for both
    other_pos = np.array([[2.0, 0.7, 0.3]])  # nearest x is 2.25
    other_head = np.array([[1.6, 0.7, 0.45]])  # nearest heading 30 deg
    assert success(same, truth, m, STEP, HSTEP)[0]
    assert not success(other_pos, truth, m, STEP, HSTEP)[0]
    assert not success(other_head, truth, m, STEP, HSTEP)[0]
    assert success(truth, truth, m, STEP, HSTEP)[0]
    res = success(np.vstack([same, other_pos]), np.vstack([truth, truth]), m, STEP, HSTEP)
    assert res.tolist() == [True, False]


def test_success_across_the_angle_cut() -> None:
    m = _grid()
    truth = np.array([[1.5, 0.75, np.pi - 0.02]])
    est = np.array([[1.5, 0.75, -np.pi + 0.02]])  # both nearest to heading -pi (== pi)
    assert success(est, truth, m, STEP, HSTEP)[0]
    idx = nearest_map_index(np.vstack([truth, est]), m, STEP, HSTEP)
    assert idx[0] == idx[1]


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
